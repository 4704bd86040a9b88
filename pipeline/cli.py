"""The ``selpath`` command line: run, validate, stages, schema, inspect, workflows, demo."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

import workflows as shipped
from pipeline.compute import enable_compile_cache
from pipeline.constraints import describe
from pipeline.engine import RunReport, run_workflow
from pipeline.errors import SelpathError, StoreError
from pipeline.integrity import verify_store
from pipeline.locks import store_lock
from pipeline.provenance import read_provenance
from pipeline.registry import default_registry
from pipeline.report import summary_lines, write_html
from pipeline.spec import load_workflow
from pipeline.store import forget_frames, is_complete, missing_frames, open_store

app = typer.Typer(help="selpath: selected light path measurement, from capture to science.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)
console = Console()
errors = Console(stderr=True)


def _version(show: bool) -> None:
    if show:
        from importlib.metadata import version

        console.print(f"selpath {version('selpath')}")
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", help="print the version and exit", callback=_version,
                                                is_eager=True)] = False) -> None:
    """selpath: selected light path measurement, from capture to science."""



def _fail(exc: SelpathError) -> None:
    errors.print(f"[bold red]error:[/] {escape(str(exc))}", markup=True, highlight=False, soft_wrap=True)
    raise typer.Exit(2)


@contextmanager
def _guard() -> Iterator[None]:
    """Every error reaches the user as one message, never a traceback (SELPATH_DEBUG=1 shows it)."""
    try:
        yield
    except SelpathError as exc:
        _fail(exc)
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
        if os.environ.get("SELPATH_DEBUG"):
            raise
        text = escape(f"{type(exc).__name__}: {exc}".split("\n")[0][:500])
        errors.print(f"[bold red]error:[/] unexpected {text} (this is a bug in selpath or a plugin: please report "
                     "it with the command; SELPATH_DEBUG=1 shows the traceback)", highlight=False, soft_wrap=True)
        raise typer.Exit(3) from None


def _print_report(report: RunReport) -> None:
    table = Table(title=f"workflow {report.workflow}: {report.seconds:.1f} s")
    for column in ("step", "status", "why"):
        table.add_column(column)
    colours = {"computed": "green", "reused": "cyan", "not needed": "dim"}
    for step in report.steps.values():
        table.add_row(step.id, f"[{colours[step.status]}]{step.status}[/]", escape(step.reason))
    console.print(table)
    for store in report.written:
        console.print(f"wrote {escape(store)}")


@app.command()
def run(
    file: Annotated[Path, typer.Argument(help="workflow YAML file")],
    scheduler: Annotated[str | None, typer.Option(help="override the workflow's scheduler")] = None,
    force: Annotated[bool, typer.Option(help="recompute every output even if up to date")] = False,
    progress: Annotated[bool, typer.Option(help="show a progress bar")] = True,
    report: Annotated[bool, typer.Option(help="write the workflow's HTML report (its `report:` section, else "
                                         "every figure beside the first output)")] = False,
) -> None:
    """Validate and run a workflow; steps whose stored output is up to date are skipped."""
    enable_compile_cache()
    if not file.exists() and file.suffix == "" and file.name in shipped.names():
        _fail(SelpathError(f"{file} is a shipped workflow, not a file here: copy it to run it where its stores "
                           f"should land (`selpath workflows --copy DIR`, then `selpath run DIR/{file.name}.yaml`), "
                           "or run the demo (`selpath demo`)"))
    with _guard():
        workflow = load_workflow(file)
        result = run_workflow(workflow, scheduler=scheduler, progress=progress, reuse=not force, log=console.print)
    _print_report(result)
    if report:
        with _guard():
            _write_report(workflow, result)


def _write_report(workflow, result: RunReport) -> None:
    summary = summary_lines(workflow)
    page = write_html(workflow, result, summary=summary)
    for line in summary:
        console.print(line)
    console.print(f"report: {escape(str(page))}")


@app.command()
def schema() -> None:
    """Print the workflow file's JSON Schema, with every installed stage's settings, for YAML editors
    (``selpath schema > workflow.schema.json``; see the README)."""
    from pipeline.workflow_schema import workflow_schema

    print(json.dumps(workflow_schema(), indent=1, ensure_ascii=False))


@app.command()
def workflows(
    copy: Annotated[Path | None, typer.Option(help="copy every shipped workflow and its scenes into this "
                                              "folder, to run or edit")] = None,
) -> None:
    """List the workflows selpath ships (or copy them, with their scenes, to edit)."""
    if copy is None:
        for name in shipped.names():
            console.print(f"{name}  {escape(str(shipped.path(name)))}")
        console.print("(read-only where selpath is installed: `selpath workflows --copy DIR` to run or edit them)")
        return
    with _guard():
        if copy.exists() and not copy.is_dir():
            _fail(SelpathError(f"{copy} is a file; --copy needs a folder (absent or empty of the shipped files)"))
        copy.mkdir(parents=True, exist_ok=True)
        taken = [p.name for p in (*shipped.folder().glob("*.yaml"), shipped.folder() / "scenes") if
                 (copy / p.name).exists()]
        if taken:
            _fail(SelpathError(f"{copy} already holds {', '.join(taken)}; copy into an empty folder"))
        for name in shipped.names():
            shutil.copy(shipped.path(name), copy / f"{name}.yaml")
        shutil.copytree(shipped.folder() / "scenes", copy / "scenes")
    console.print(f"copied {len(shipped.names())} workflows and their scenes to {escape(str(copy))}")


@app.command()
def validate(file: Annotated[Path, typer.Argument(help="workflow YAML file")]) -> None:
    """Check a workflow without running it; lists every problem with file:line and the fix."""
    with _guard():
        workflow = load_workflow(file)
    steps = len(workflow.steps)
    console.print(f"[green]ok[/]: {escape(workflow.name)}: {steps} step{'s' if steps != 1 else ''}, outputs "
                  + escape(", ".join(f"{n} -> {o.store}" for n, o in workflow.outputs.items())))


@app.command()
def stages(
    name: Annotated[str | None, typer.Argument(help="show one stage in full")] = None,
    all_: Annotated[bool, typer.Option("--all", help="show every stage in full")] = False,
) -> None:
    """List the registered stages, one line each; NAME (or --all) shows inputs, settings, defaults, units and docs."""
    with _guard():
        registry = default_registry()
    if name and name not in registry:
        errors.print(f"[bold red]error:[/] unknown stage {escape(repr(name))}; known: {', '.join(registry.names())}")
        raise typer.Exit(2)
    if not name and not all_:
        table = Table(title="stages (selpath stages NAME for one in full)", show_lines=False)
        for column in ("stage", "module", "what it does"):
            table.add_column(column, overflow="fold")
        for s in registry:
            table.add_row(s.name, escape(s.func.__module__.removeprefix("stages.")), escape(s.summary))
        console.print(table)
        return
    chosen = [registry[name]] if name else list(registry)
    for s in chosen:
        table = Table(title=f"[bold]{s.name}[/]  ({s.source})", caption=escape(s.summary), show_lines=False)
        for column in ("parameter", "kind", "type", "default", "description"):
            table.add_column(column, overflow="fold")
        for i in s.inputs:
            table.add_row(i, "input", "Dataset/DataArray", "required" if i in s.required_inputs else "None", "")
        for field_name, field in s.params.model_fields.items():
            default = "required" if field.is_required() else repr(field.default)
            table.add_row(field_name, "setting", escape(describe(field)), escape(default),
                          escape(field.description or ""))
        console.print(table)


@app.command()
def inspect(
    store: Annotated[Path, typer.Argument(help="a selpath zarr store")],
    verify: Annotated[bool, typer.Option(help="read every chunk and list the missing and corrupt ones")] = False,
    recapture: Annotated[bool, typer.Option(help="with --verify: mark capture frames with bad chunks as not "
                                                   "captured, so the next run of the acquisition captures them "
                                                   "again")] = False,
) -> None:
    """Check a store and show its kind, dims, coords with units, variables, missing frames and provenance.

    Exit status 0: complete and (with --verify) every chunk readable; 1: incomplete (frames missing, or no
    record that writing finished) or bad chunks; 2: it cannot be opened or breaks its kind's schema.
    """
    with _guard(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            ds = open_store(store, keep_flags=True)
        except StoreError as exc:
            if not verify:
                raise
            bad = verify_store(store)  # say which chunks, even where the store cannot be opened for use
            errors.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
            _print_bad(bad, recapture and store)
            raise typer.Exit(1 if bad else 2) from None
        missing = missing_frames(store)
        bad = verify_store(store) if verify else []
        provenance = read_provenance(store)
        complete = is_complete(store) or bool(missing)
    console.print(f"[bold]{escape(str(store))}[/]: {ds.attrs.get('selpath_kind')} cube, format "
                  f"{ds.attrs.get('selpath_format')}")
    console.print(ds.drop_vars([v for v in ds.data_vars if str(v).startswith("written__")]))
    incomplete = not complete
    for variable, frames in missing.items():
        state = "[green]complete[/]" if not frames else f"[yellow]{len(frames)} frames missing[/], first {frames[0]}"
        console.print(f"capture of {escape(variable)}: {state}")
        incomplete |= bool(frames)
    for warning in caught:
        console.print(f"[yellow]warning[/]: {escape(str(warning.message))}")
    if not missing and not complete:
        console.print("[yellow]incomplete[/]: no record that writing this store finished (a killed run leaves "
                      "such stores); write it again")
    if verify:
        _print_bad(bad, recapture and store)
    if provenance:
        summary = {k: provenance.get(k) for k in ("workflow", "output", "created", "step_hash", "versions")}
        console.print_json(json.dumps(summary))
    if incomplete or bad:
        raise typer.Exit(1)


def _print_bad(bad: list, recapture_store: Path | bool) -> None:
    console.print(f"verify: {'[green]every chunk reads[/]' if not bad else f'[red]{len(bad)} bad chunk(s)[/]'}")
    for chunk in bad:
        console.print(f"  {escape(str(chunk))}")
    if bad and recapture_store:
        with _guard(), store_lock(recapture_store, purpose="inspect --recapture"):
            frames = forget_frames(recapture_store, bad)
        console.print(f"marked {frames} frame(s) as not captured: run the acquisition again to capture them")


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="folder for the demo's stores")] = Path("selpath-demo"),
    instrument: Annotated[str, typer.Option(help=f"{', '.join(shipped.DEMO)} or all")] = "all",
    scheduler: Annotated[str | None, typer.Option(help="override the scheduler")] = None,
) -> None:
    """The main jobs on the built-in simulated rigs: the shipped workflows of ``workflows.DEMO`` (the gelatin
    bin's tomography and the projector–camera rig's plane-to-ray transport).

    Writes every store and figure under ``--out``, and the report each workflow declares beside them.
    """
    enable_compile_cache()
    names = list(shipped.DEMO) if instrument == "all" else [instrument]
    if any(name not in shipped.DEMO for name in names):
        _fail(SelpathError(f"unknown instrument {instrument!r}: choose {', '.join(shipped.DEMO)} or all"))
    with _guard():
        for name in names:
            workflow = load_workflow(shipped.path(shipped.DEMO[name])).rerooted(out)
            result = run_workflow(workflow, scheduler=scheduler, log=console.print)
            _print_report(result)
            _write_report(workflow, result)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
