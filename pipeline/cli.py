"""The ``selpath`` command line: run, validate, stages, kinds, schema, inspect, import, workflows, demo."""

from __future__ import annotations

import functools
import json
import os
import shutil
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import dask
import numpy as np
import typer
import typer.core
import typer.models
from rich.console import Console
from rich.markup import escape
from rich.padding import Padding
from rich.table import Table

from selpath import workflows as shipped
from selpath.pipeline.compute import enable_compile_cache
from selpath.pipeline.constraints import describe
from selpath.pipeline.engine import RunReport, run_workflow
from selpath.pipeline.errors import Problem, SelpathError, StoreError, environment_fault
from selpath.pipeline.integrity import open_group, resized_chunks, verify_store
from selpath.pipeline.kinds import describe_kinds
from selpath.pipeline.locks import store_lock
from selpath.pipeline.provenance import archive_stores, read_provenance
from selpath.pipeline.registry import default_registry, plain_text, resolve_kind
from selpath.pipeline.report import report_tables, summary_lines, write_html
from selpath.pipeline.spec import load_workflow
from selpath.pipeline.store import forget_frames, is_complete, missing_frames, open_store


class _Command(typer.core.TyperCommand):
    """A command whose help shows no ``<bool>`` type beside ``--help`` (flags say what they do)."""

    def get_help_option(self, ctx):
        return _untyped(super().get_help_option(ctx))


class _Group(typer.core.TyperGroup):
    def get_help_option(self, ctx):
        return _untyped(super().get_help_option(ctx))


def _untyped(option):
    if option is not None:
        option.metavar = ""
    return option


# docstrings and help texts are Markdown: ``code`` renders as code, never as raw backticks
app = typer.Typer(help="selpath: selected light path measurement, from capture to science.", cls=_Group,
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  rich_markup_mode="markdown")
command = functools.partial(app.command, cls=_Command)


def _flag(name: str, help: str) -> typer.models.OptionInfo:  # noqa: A002 - typer's own keyword
    """An on/off option shown as ``--name`` alone (off unless given)."""
    return typer.Option(f"--{name}", help=help, metavar="")
console = Console()
errors = Console(stderr=True)


def _version(show: bool) -> None:
    if show:
        from importlib.metadata import version

        console.print(f"selpath {version('selpath')}")
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", help="print the version and exit", callback=_version,
                                                is_eager=True, metavar="")] = False) -> None:
    """selpath: selected light path measurement, from capture to science."""



#: ``inspect`` computes valid shares by default for stores of at most this many values (reading more takes long)
VALID_LIMIT = 2e8


def _fail(exc: SelpathError) -> None:
    errors.print(f"[bold red]error:[/] {escape(str(exc))}", markup=True, highlight=False, soft_wrap=True)
    raise typer.Exit(2)


@contextmanager
def guard() -> Iterator[None]:
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
        fault = environment_fault(exc)  # the machine refused (permissions, a long name, a full disk): no bug
        if fault is not None:
            _fail(fault)
        if os.environ.get("SELPATH_DEBUG"):
            raise
        text = escape(f"{type(exc).__name__}: {exc}".split("\n")[0][:500])
        errors.print(f"[bold red]error:[/] unexpected {text} (this is a bug in selpath or a plugin: please report "
                     "it with the command; SELPATH_DEBUG=1 shows the traceback)", highlight=False, soft_wrap=True)
        raise typer.Exit(3) from None


def _print_report(report: RunReport) -> None:
    """One row per step: what happened and how long it took (the reasons were printed with each step's heading)."""
    table = Table(title=f"workflow {escape(report.workflow)}: {report.seconds:.1f} s, {len(report.written)} "
                  "output(s) written")
    for column in ("step", "stage", "status", "time"):
        table.add_column(column, justify="right" if column == "time" else "left")
    colours = {"computed": "green", "reused": "cyan", "not needed": "dim"}
    for step in report.steps.values():
        seconds = "" if step.seconds is None else f"{step.seconds:.1f} s"
        if step.seconds is None and step.status == "computed":
            seconds = "[dim]in its reader[/]"
        table.add_row(escape(step.id), escape(step.stage), f"[{colours[step.status]}]{step.status}[/]", seconds)
    console.print(table)


def _print_results(workflow) -> tuple[list[str], list]:
    """The ``report:`` section's summary lines and tables, printed; returned for the page."""
    summary, tables = summary_lines(workflow), report_tables(workflow)
    for line in summary:
        console.print(escape(line), highlight=False)
    for view in tables:
        table = Table(title=escape(view.title))
        for column in view.columns:
            table.add_column(escape(column), overflow="fold")
        for row in view.rows:
            table.add_row(*map(escape, row))
        console.print(table)
    return summary, tables


@command()
def run(
    file: Annotated[Path, typer.Argument(help="workflow YAML file", metavar="FILE", show_default=False)],
    scheduler: Annotated[str | None, typer.Option(help="override the workflow's scheduler: synchronous, threads, "
                                                  "processes or tcp://host:port", metavar="NAME")] = None,
    force: Annotated[bool, _flag("force", "recompute every output even if up to date")] = False,
    verify: Annotated[bool, _flag("verify", "read every chunk of the up-to-date outputs first: damaged ones are "
                                  "computed again, damaged capture frames captured again")] = False,
    progress: Annotated[bool, typer.Option(help="show progress bars", metavar="")] = True,
    report: Annotated[bool, _flag("report", "also write the workflow's HTML report (its `report:` section's "
                                  "file, else beside the first output)")] = False,
) -> None:
    """Validate and run a workflow; steps whose stored output is up to date are reused, never recomputed.

    Prints one heading per step (why it runs), then the steps' table and the `report:` section's summary and
    tables.
    """
    enable_compile_cache()
    if not file.exists() and file.suffix == "" and file.name in shipped.names():
        _fail(SelpathError(f"{file} is a shipped workflow, not a file here: copy it to run it where its stores "
                           f"should land (`selpath workflows --copy DIR`, then `selpath run DIR/{file.name}.yaml`), "
                           "or run the demo (`selpath demo`)"))
    with guard():
        workflow = load_workflow(file)
        result = run_workflow(workflow, scheduler=scheduler, progress=progress, reuse=not force,
                              verify=verify, log=console.print)
    _print_report(result)
    with guard():
        summary, tables = _print_results(workflow)
        if report:
            _write_report(workflow, result, summary, tables)


def _write_report(workflow, result: RunReport, summary: list[str], tables: list) -> None:
    page = write_html(workflow, result, summary=summary, tables=tables)
    console.print(f"report: {escape(str(page))}")


@command()
def schema() -> None:
    """Print the workflow file's JSON Schema, with every installed stage's settings, for YAML editors
    (``selpath schema > workflow.schema.json``; see the README)."""
    from selpath.pipeline.workflow_schema import workflow_schema

    print(json.dumps(workflow_schema(), indent=1, ensure_ascii=False))


@command()
def workflows(
    copy: Annotated[Path | None, typer.Option(help="copy every shipped workflow and its scenes into this "
                                              "folder, to run or edit", metavar="DIR")] = None,
) -> None:
    """List the workflows selpath ships (or copy them, with their scenes, to edit)."""
    if copy is None:
        for name in shipped.names():
            after = f"  (run {shipped.AFTER[name]} first)" if name in shipped.AFTER else ""
            console.print(f"{name}  {escape(str(shipped.path(name)))}{after}")
        console.print("(read-only where selpath is installed: `selpath workflows --copy DIR` to run or edit them)")
        return
    with guard():
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


@command()
def validate(file: Annotated[Path, typer.Argument(help="workflow YAML file", metavar="FILE",
                                                 show_default=False)]) -> None:
    """Check a workflow without running it; lists every problem with file:line and the fix."""
    with guard():
        workflow = load_workflow(file)
    steps = len(workflow.steps)
    console.print(f"[green]ok[/]: {escape(workflow.name)}: {steps} step{'s' if steps != 1 else ''}, outputs "
                  + escape(", ".join(f"{n} -> {o.store}" for n, o in workflow.outputs.items())))


@command("import")
def import_(spec: Annotated[Path, typer.Argument(help="import spec (YAML): kind, frames, geometry or timing",
                                                 metavar="SPEC", show_default=False)],
            store: Annotated[Path, typer.Argument(help="capture store to write (a new .zarr path)", metavar="STORE",
                                                  show_default=False)]) -> None:
    """Turn frames made elsewhere (TIFF/PNG folders, .npy/.npz, HDF5) into a checked capture store.

    The spec says the cube kind, where each variable's frames lie and the geometry or timing the stages read,
    with units (docs/format.md, "Importing captures"). Frames are copied one by one; nothing is written into
    the sources, and an existing store is never replaced.
    """
    from selpath.pipeline.store import to_store

    with guard():
        if store.exists():
            raise StoreError(Problem("exists; selpath import writes a new store and never replaces one",
                                     where=str(store), fix="choose another path, or delete that store yourself"))
        ds = default_registry()["import_capture"].func(spec=str(spec))
        with dask.config.set(scheduler="threads"):
            to_store(ds, store, ds.attrs["selpath_kind"])
    sizes = ", ".join(f"{d} {n}" for d, n in ds.sizes.items())
    console.print(f"[green]ok[/]: {escape(str(store))}: {ds.attrs['selpath_kind']} ({escape(sizes)}); "
                  f"variables {escape(', '.join(map(str, ds.data_vars)))}")


@command()
def stages(
    name: Annotated[str | None, typer.Argument(help="show one stage in full", metavar="NAME",
                                               show_default=False)] = None,
    all_: Annotated[bool, _flag("all", "show every stage in full")] = False,
) -> None:
    """List the registered stages, one line each; NAME (or --all) shows inputs, settings, defaults, units and docs."""
    with guard():
        registry = default_registry()
    if name and name not in registry:
        errors.print(f"[bold red]error:[/] unknown stage {escape(repr(name))}; known: {', '.join(registry.names())}")
        raise typer.Exit(2)
    if not name and not all_:
        table = Table(title="stages (selpath stages NAME for one in full)", show_lines=False)
        for column in ("stage", "module", "what it does"):
            table.add_column(column, overflow="fold")
        for s in registry:
            module = s.func.__module__.removeprefix("selpath.stages.")
            table.add_row(s.name, escape(module), escape(plain_text(s.summary)))
        console.print(table)
        return
    for s in [registry[name]] if name else list(registry):
        _print_stage(s)


def _print_stage(s) -> None:
    """One stage in full: its summary, the kinds it makes, then each input and setting with its type, default and
    description."""
    console.print(f"[bold]{escape(s.name)}[/]  [dim]({escape(s.source)})[/]")
    console.print(escape(plain_text(s.summary)), highlight=False)
    makes = " or ".join(k.name for k in s.kinds) or "any kind (its result's selpath_kind attr names it)"
    console.print(f"  [underline]result[/]: {escape(makes)}", highlight=False)
    sections = (("inputs (data: $step or $step.variable)", [
        (i, "required" if i in s.required_inputs else "optional", s.param_docs.get(i, "")) for i in s.inputs]),
        ("settings", [(n, f"{describe(f)} = {'required' if f.is_required() else repr(f.default)}", f.description or "")
                      for n, f in s.params.model_fields.items()]))
    for title, rows in sections:
        if not rows:
            continue
        console.print(f"\n  [underline]{title}[/]")
        for field_name, kind, text in rows:
            console.print(f"  [bold cyan]{escape(field_name)}[/]  {escape(kind)}", highlight=False)
            if text:
                console.print(Padding(escape(plain_text(text)), (0, 0, 0, 6)), highlight=False)
    console.print()


@command()
def kinds(
    name: Annotated[str | None, typer.Argument(help="show one kind in full", metavar="NAME",
                                               show_default=False)] = None,
    markdown: Annotated[bool, _flag("markdown", "print every kind as the Markdown table of docs/format.md")] = False,
) -> None:
    """List the cube kinds the installed stages make (selpath's and plugins'), one line each; NAME shows its
    variables with dims and units, its coordinates' units and its required attrs."""
    with guard():
        registry = default_registry()
    known = registry.kinds
    if markdown:
        print(describe_kinds(known.values()))
        return
    if name is not None:
        if name not in known:
            _fail(SelpathError(f"unknown cube kind {name!r}; installed: {', '.join(known)}"))
        _print_kind(known[name], registry.makers(name))
        return
    table = Table(title="cube kinds (selpath kinds NAME for one in full)")
    for column in ("kind", "made by", "what it holds"):
        table.add_column(column, overflow="fold")
    for kind in known.values():
        table.add_row(kind.name, escape(", ".join(registry.makers(kind.name))), escape(kind.description))
    console.print(table)


def _print_kind(kind, makers: list[str]) -> None:
    console.print(f"[bold]{escape(kind.name)}[/]  [dim](made by {escape(', '.join(makers))})[/]")
    console.print(escape(kind.description), highlight=False)
    console.print("\n  [underline]variables[/]")
    for name, var in kind.variables.items():
        units = "not fixed" if var.units == "" else "none" if var.units is None else var.units
        batch = "".join(f"[{d}] " for d in kind.batch_dims)
        console.print(f"  [bold cyan]{escape(name)}[/]  {escape(batch)}({escape(', '.join(var.dims))}) [+ channel]  "
                      f"units: {escape(units)}{'' if var.required else '  (optional)'}", highlight=False)
        text = "; ".join(t for t in (var.long_name, var.description) if t)
        if text:
            console.print(Padding(escape(text), (0, 0, 0, 6)), highlight=False)
    if kind.coord_units:
        console.print("\n  [underline]coordinates[/]")
        for dim, units in kind.coord_units.items():
            console.print(f"  [bold cyan]{escape(dim)}[/]  units in {escape(', '.join(sorted(units)))}",
                          highlight=False)
    if kind.attrs:
        console.print("\n  [underline]attrs[/]")
        for attr, text in kind.attrs.items():
            console.print(f"  [bold cyan]{escape(attr)}[/]  {escape(text)}", highlight=False)
    if kind.png:
        console.print(f"\n  a workflow output also saves {escape(kind.png)} as <store>.png")
    console.print()


def _print_archive(folder: Path) -> None:
    """One table of the stores under ``folder`` and where each came from (``selpath inspect FOLDER``)."""
    stores = archive_stores(folder)
    if not stores:
        _fail(SelpathError(f"{folder} holds no selpath store (a folder whose zarr.json carries selpath_format)"))
    table = Table(title=f"{escape(str(folder))}: {len(stores)} store(s)")
    for column in ("store", "kind", "workflow", "output", "created (UTC)"):
        table.add_column(column, overflow="fold")
    for row in stores:
        made = row["workflow"] is not None
        created = str(row["created"] or "")[:16].replace("T", " ")
        table.add_row(*(escape(str(row[k])) for k in ("store", "kind")),
                      *(("[red]provenance record unreadable[/]", "", "") if row.get("problem") else
                        (escape(str(row["workflow"])), escape(str(row["output"])), created) if made else
                        ("[dim]outside a workflow[/]", "", "")))
    console.print(table)
    console.print("selpath inspect STORE shows one store in full, with its provenance.")


@command()
def inspect(
    store: Annotated[Path, typer.Argument(help="a selpath zarr store, or a folder of stores (an archive)",
                                          metavar="STORE", show_default=False)],
    verify: Annotated[bool, _flag("verify", "read every chunk and list the missing and corrupt ones")] = False,
    recapture: Annotated[bool, _flag("recapture", "mark capture frames with bad chunks as not captured, so the "
                                     "next run of the acquisition captures them again")] = False,
    valid: Annotated[bool | None, typer.Option("--valid/--no-valid", metavar="",
                                               help="compute each variable's valid share (reads every value; "
                                               f"default: for stores of at most {VALID_LIMIT:.0e} values)")] = None,
) -> None:
    """Check a store and show its kind, dims, coords with units, variables, missing frames and provenance; or,
    given a folder that is not a store (an archive), list every store under it with its provenance in one table.

    Every chunk's size is compared with the one recorded when the store was written (one listing, contents not
    read); --verify reads every chunk and checks its checksum. Exit status 0: complete, and every chunk of its
    recorded size (with --verify: every chunk readable); 1: incomplete (frames missing, or no record that writing
    finished) or bad chunks; 2: it cannot be opened or breaks its kind's schema.
    """
    if store.is_dir() and not (store / "zarr.json").exists():
        _print_archive(store)
        return
    with guard(), warnings.catch_warnings(record=True) as caught:
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
        resized = None if verify else resized_chunks(store)  # one listing: sizes against the manifest's record
        bad = verify_store(store) if verify else resized or []
        provenance = read_provenance(store)
        complete = is_complete(store) or bool(missing)
    with guard(), np.errstate(all="ignore"):
        _describe_store(store, ds.drop_vars([v for v in ds.data_vars if str(v).startswith("written__")]), valid,
                        readable=not bad)
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
    elif resized is None:
        console.print("chunks: no record of their sizes (written before selpath 0.2, or a capture not finished); "
                      "contents not read: `selpath inspect --verify` reads every chunk and checks its checksum")
    elif bad:
        _print_bad(bad, recapture and store, how="check (sizes against the record; contents not read)")
        console.print("a chunk changed since it was written: `selpath inspect --verify` reads every chunk; running "
                      "the workflow that wrote the store computes it again (a capture: captures those frames again)")
    else:
        console.print("chunks: every one has the size it was written with (contents not read: `selpath inspect "
                      "--verify` reads every chunk and checks its checksum)")
    if provenance:
        console.print("[underline]provenance[/]")
        step = provenance.get("step_record", {})
        lines = {"workflow": f"{provenance.get('workflow')} ({provenance.get('workflow_source')}), output "
                             f"{provenance.get('output')}",
                 "step": f"stage {step.get('stage')}, settings {json.dumps(step.get('settings', {}))}",
                 "created": f"{provenance.get('created')} with selpath {provenance.get('versions', {}).get('selpath')}"
                            f" ({provenance.get('scheduler')} scheduler)",
                 "step hash": str(provenance.get("step_hash"))}
        for key, value in lines.items():
            console.print(f"  {key}: {escape(value)}", highlight=False, soft_wrap=True)
    else:
        console.print("provenance: none (written outside a workflow, e.g. by selpath.to_store or another tool, or "
                      "still being written)")
    if incomplete or bad:
        raise typer.Exit(1)


def _describe_store(path: Path, ds, valid: bool | None, readable: bool) -> None:
    """Kind, dims, coordinates with units, attrs and each variable with units and valid share."""
    from selpath.pipeline.quality import valid_shares

    kind = ds.attrs.get("selpath_kind")
    about = resolve_kind(kind, module=ds.attrs.get("selpath_kind_module")).description  # (opened: a known kind)
    on_disk = open_group(path).attrs.get("selpath_format")
    migrated = f", migrated to {ds.attrs.get('selpath_format')} on open" if on_disk != ds.attrs.get(
        "selpath_format") else ""
    console.print(f"[bold]{escape(str(path))}[/]: {escape(str(kind))} store, format {on_disk}{migrated}"
                  f" ({escape(about)})", highlight=False)
    console.print("dims: " + ", ".join(f"{d} {n:,}" for d, n in ds.sizes.items()), highlight=False)
    total = sum(int(v.size) for v in ds.data_vars.values())
    shares, scalar_values, unread = {}, {}, "valid share not computed (--valid reads every value)"
    if readable:
        try:
            shares = valid_shares(ds) if valid or (valid is None and total <= VALID_LIMIT) else {}
            scalars = [n for n, v in ds.data_vars.items() if v.ndim == 0]
            scalar_values = dict(zip(scalars, dask.compute(*(ds[n].data for n in scalars)), strict=True))
        except StoreError:
            shares, unread = {}, "values not read: a chunk is bad (--verify lists every bad chunk)"
    else:
        unread = "values not read: bad chunks (below)"
    for title, group in (("coordinates", ds.coords), ("variables", ds.data_vars)):
        console.print(f"[underline]{title}[/]")
        for name, array in group.items():
            units = array.attrs.get("units")
            head = (f"  [bold cyan]{escape(str(name))}[/] ({escape(', '.join(map(str, array.dims)))}) {array.dtype}"
                    + (f" \\[{escape(str(units))}]" if units else ""))
            if name in scalar_values:
                head += f" = {_scalar_text(np.asarray(scalar_values[name]).item())}"
            elif title == "coordinates" and array.size and np.issubdtype(array.dtype, np.number):
                head += f": {array.values.min():g} … {array.values.max():g}"
            elif title == "variables":
                share = shares.get(str(name))
                head += (f": {unread}" if not shares else
                         "" if share is None else f": {share:.1%} {'true' if array.dtype == bool else 'finite'}"
                         if isinstance(share, float) else
                         ": " + ", ".join(f"{k} {v:.1%}" for k, v in share.items() if v or k == "valid"))
            console.print(head, highlight=False, soft_wrap=True)
            if array.attrs.get("long_name"):
                console.print(f"      {escape(str(array.attrs['long_name']))}", highlight=False, soft_wrap=True)
    hidden = ("selpath_kind", "selpath_format", "selpath_kind_module")
    attrs = {k: v for k, v in ds.attrs.items() if k not in hidden and not k.startswith("_")}
    if attrs:
        console.print("[underline]attrs[/]")
        for key, value in attrs.items():
            text = json.dumps(value, default=str, ensure_ascii=False)
            console.print(f"  {escape(key)}: {escape(text if len(text) <= 200 else text[:197] + '…')}",
                          highlight=False, soft_wrap=True)


def _scalar_text(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    return f"{value:.6g}" if isinstance(value, int | float) else escape(str(value))


def _print_bad(bad: list, recapture_store: Path | bool, how: str = "verify") -> None:
    console.print(f"{how}: {'[green]every chunk reads[/]' if not bad else f'[red]{len(bad)} bad chunk(s)[/]'}")
    for chunk in bad:
        console.print(f"  {escape(str(chunk))}")
    if bad and recapture_store:
        with guard(), store_lock(recapture_store, purpose="inspect --recapture"):
            frames = forget_frames(recapture_store, bad)
        console.print(f"marked {frames} frame(s) as not captured: run the acquisition again to capture them")


@command()
def demo(
    out: Annotated[Path, typer.Option(help="folder for the demo's stores", metavar="DIR")] = Path("selpath-demo"),
    instrument: Annotated[str, typer.Option(help=f"{', '.join(shipped.DEMO)} or all", metavar="NAME")] = "all",
    scheduler: Annotated[str | None, typer.Option(help="override the scheduler", metavar="NAME")] = None,
) -> None:
    """The main jobs on the built-in simulated rigs: the gelatin bin's tomography (workflow `tomography-sim`) and the
    projector–camera rig's plane-to-ray transport (`procam-sim`).

    Writes every store and figure under `--out`, and each workflow's HTML report beside them.
    """
    enable_compile_cache()
    names = list(shipped.DEMO) if instrument == "all" else [instrument]
    if any(name not in shipped.DEMO for name in names):
        _fail(SelpathError(f"unknown instrument {instrument!r}: choose {', '.join(shipped.DEMO)} or all"))
    with guard():
        for name in names:
            workflow = load_workflow(shipped.path(shipped.DEMO[name])).rerooted(out)
            result = run_workflow(workflow, scheduler=scheduler, log=console.print)
            _print_report(result)
            _write_report(workflow, result, *_print_results(workflow))


def add_commands() -> None:
    """The commands other packages add: each entry point of the ``selpath.commands`` group names a typer command
    function (selpath's own ``explore`` comes this way, so this layer never imports the one above it). A command
    that fails to load is left out with a warning; the others still run."""
    from importlib.metadata import entry_points

    known = {c.name or c.callback.__name__ for c in app.registered_commands}
    for point in entry_points(group="selpath.commands"):
        if point.name in known:
            continue
        try:
            function = point.load()
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the command line
            errors.print(f"[yellow]warning:[/] command {point.name!r} ({point.value}) did not load: "
                         f"{escape(f'{type(exc).__name__}: {exc}')}", highlight=False)
            continue
        app.command(name=point.name, cls=_Command)(function)
        known.add(point.name)


def main() -> None:
    add_commands()
    app()


if __name__ == "__main__":
    main()
