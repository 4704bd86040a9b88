"""What every ``selpath`` command shares: the consoles, on/off flags, and the guard that turns any error into one
message and an exit status (2: the input or the machine, 3: a bug; never a traceback unless SELPATH_DEBUG=1)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import typer
import typer.core
import typer.models
from rich.console import Console
from rich.markup import escape

from selpath.pipeline.errors import SelpathError, environment_fault


class Command(typer.core.TyperCommand):
    """A command whose help shows no ``<bool>`` type beside ``--help`` (flags say what they do)."""

    def get_help_option(self, ctx):
        return _untyped(super().get_help_option(ctx))


class Group(typer.core.TyperGroup):
    """The command group, its help option untyped alike."""

    def get_help_option(self, ctx):
        return _untyped(super().get_help_option(ctx))


def _untyped(option):
    if option is not None:
        option.metavar = ""
    return option


def flag(name: str, help: str) -> typer.models.OptionInfo:  # noqa: A002 - typer's own keyword
    """An on/off option shown as ``--name`` alone (off unless given)."""
    return typer.Option(f"--{name}", help=help, metavar="")


#: the command line's output and its errors (rich consoles; their width comes from COLUMNS when made)
console = Console()
errors = Console(stderr=True)


def fail(exc: SelpathError) -> None:
    errors.print(f"[bold red]error:[/] {escape(str(exc))}", markup=True, highlight=False, soft_wrap=True)
    raise typer.Exit(2)


@contextmanager
def guard() -> Iterator[None]:
    """Every error reaches the user as one message, never a traceback (SELPATH_DEBUG=1 shows it)."""
    try:
        yield
    except SelpathError as exc:
        fail(exc)
    except KeyboardInterrupt:
        errors.print("[bold red]interrupted[/]: every finished output and captured frame is kept; run the same "
                     "command again to resume", highlight=False)
        raise typer.Exit(130) from None
    except (typer.Exit, typer.Abort):
        raise
    except MemoryError:
        errors.print("[bold red]error:[/] out of memory; use smaller sizes, fewer angles or smaller tiles",
                     highlight=False)
        raise typer.Exit(2) from None
    except Exception as exc:  # noqa: BLE001 - the last line of defence between a bug and a traceback
        fault = environment_fault(exc)  # the machine refused (permissions, a long name, a full disk): no bug
        if fault is not None:
            fail(fault)
        if os.environ.get("SELPATH_DEBUG"):
            raise
        text = escape(f"{type(exc).__name__}: {exc}".split("\n")[0][:500])
        errors.print(f"[bold red]error:[/] unexpected {text} (this is a bug in selpath or a plugin: please report "
                     "it with the command; SELPATH_DEBUG=1 shows the traceback)", highlight=False, soft_wrap=True)
        raise typer.Exit(3) from None
