"""The ``selpath`` command line: run, validate, stages, kinds, schema, inspect, import, workflows, demo."""

from __future__ import annotations

import difflib
import functools
import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
import typer.core
import typer.models
from rich.markup import escape
from rich.table import Table

from selpath import workflows as shipped
from selpath.pipeline.cli_common import Command, Group, console, errors, fail, flag, guard
from selpath.pipeline.cli_import import import_
from selpath.pipeline.cli_inspect import inspect
from selpath.pipeline.errors import SelpathError

if TYPE_CHECKING:
    from selpath.pipeline.engine import RunReport

# Each command imports what it runs (the engine, stores, the stage registry) when it runs: `--help`, `--version` and
# a mistyped command answer without importing xarray, dask or JAX (benchmarks/cli_startup.py)

# docstrings and help texts are Markdown: ``code`` renders as code, never as raw backticks
app = typer.Typer(help="selpath: selected light path measurement, from capture to science.", cls=Group,
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  rich_markup_mode="markdown")
command = functools.partial(app.command, cls=Command)


def _version(show: bool) -> None:
    if show:
        from importlib.metadata import version

        console.print(f"selpath {version('selpath')}")
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", help="print the version and exit", callback=_version,
                                                is_eager=True, metavar="")] = False) -> None:
    """selpath: selected light path measurement, from capture to science."""


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
    from selpath.pipeline.report import report_tables, summary_lines

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
    force: Annotated[bool, flag("force", "recompute every output even if up to date")] = False,
    verify: Annotated[bool, flag("verify", "read every chunk of the up-to-date outputs first: damaged ones are "
                                  "computed again, damaged capture frames captured again")] = False,
    progress: Annotated[bool, typer.Option(help="show progress bars", metavar="")] = True,
    report: Annotated[bool, flag("report", "also write the workflow's HTML report (its `report:` section's "
                                  "file, else beside the first output)")] = False,
) -> None:
    """Validate and run a workflow; steps whose stored output is up to date are reused, never recomputed.

    Prints one heading per step (why it runs), then the steps' table and the `report:` section's summary and
    tables.
    """
    from selpath.pipeline.compute import enable_compile_cache
    from selpath.pipeline.engine import run_workflow
    from selpath.pipeline.spec import load_workflow

    enable_compile_cache()
    if not file.exists() and file.suffix == "" and file.name in shipped.names():
        fail(SelpathError(f"{file} is a shipped workflow, not a file here: copy it to run it where its stores "
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
    from selpath.pipeline.report import write_html

    page = write_html(workflow, result, summary=summary, tables=tables)
    console.print(f"report: {escape(str(page))}")


@command()
def schema() -> None:
    """Print the workflow file's JSON Schema, with every installed stage's settings, for YAML editors
    (``selpath schema > workflow.schema.json``; docs/tutorials/workflows.md)."""
    from selpath.pipeline.workflow_schema import workflow_schema

    print(json.dumps(workflow_schema(), indent=1, ensure_ascii=False))


@command()
def workflows(
    copy: Annotated[Path | None, typer.Option(help="copy every shipped workflow and its scenes into this "
                                              "folder, to run or edit", metavar="DIR")] = None,
) -> None:
    """List the workflows selpath ships, one line each with what it does (or copy them, with their scenes, to
    edit)."""
    if copy is None:
        width = max(map(len, shipped.names()))
        for name in shipped.names():
            after = f" (run {shipped.AFTER[name]} first)" if name in shipped.AFTER else ""
            typer.echo(f"{name:<{width}}  {shipped.describe(name)}{after}")
        console.print(f"in {escape(str(shipped.folder()))} (read-only where selpath is installed: `selpath workflows "
                      "--copy DIR` to run or edit them)", soft_wrap=True)
        return
    with guard():
        if copy.exists() and not copy.is_dir():
            fail(SelpathError(f"{copy} is a file; --copy needs a folder (absent or empty of the shipped files)"))
        copy.mkdir(parents=True, exist_ok=True)
        taken = [p.name for p in (*shipped.folder().glob("*.yaml"), shipped.folder() / "scenes") if
                 (copy / p.name).exists()]
        if taken:
            fail(SelpathError(f"{copy} already holds {', '.join(taken)}; copy into an empty folder"))
        for name in shipped.names():
            shutil.copy(shipped.path(name), copy / f"{name}.yaml")
        shutil.copytree(shipped.folder() / "scenes", copy / "scenes")
    console.print(f"copied {len(shipped.names())} workflows and their scenes to {escape(str(copy))}")


@command()
def validate(file: Annotated[Path, typer.Argument(help="workflow YAML file", metavar="FILE",
                                                 show_default=False)]) -> None:
    """Check a workflow without running it; lists every problem with file:line and the fix."""
    from selpath.pipeline.spec import load_workflow

    with guard():
        workflow = load_workflow(file)
    steps = len(workflow.steps)
    console.print(f"[green]ok[/]: {escape(workflow.name)}: {steps} step{'s' if steps != 1 else ''}, outputs "
                  + escape(", ".join(f"{n} -> {o.store}" for n, o in workflow.outputs.items())))


command("import")(import_)


def _installed() -> dict[str, dict[str, dict]]:
    """Every installed stage and kind as the installation's manifest keeps them (no stage module imported); where
    none is kept, from every stage, imported (which keeps it)."""
    from selpath.pipeline import manifest

    known = manifest.read(manifest.GROUP)
    if known is None:
        from selpath.pipeline.registry import default_registry, index

        known = index(default_registry())
    return known


@command()
def stages(
    name: Annotated[str | None, typer.Argument(help="show one stage in full", metavar="NAME",
                                               show_default=False)] = None,
    all_: Annotated[bool, flag("all", "show every stage in full")] = False,
) -> None:
    """List the registered stages, one line each (a table in a terminal; piped, plain lines: name, module and summary
    separated by tabs); NAME (or --all) shows inputs, settings, defaults, units and docs."""
    with guard():
        known = _installed()["stages"]  # the manifest: no stage module imported to list them
        if name and name not in known:  # every installed stage decides (a manifest is only a hint)
            from selpath.pipeline.registry import default_registry

            known = {s.name: {} for s in default_registry()}
    if name and name not in known:
        close = difflib.get_close_matches(name, list(known), n=3)
        errors.print(f"[bold red]error:[/] unknown stage {escape(repr(name))}; "
                     + (f"did you mean {' or '.join(map(repr, close))}?" if close else f"known: {', '.join(known)}"))
        raise typer.Exit(2)
    if not name and not all_:
        rows = [(n, s["module"].removeprefix("selpath.stages."), s["summary"]) for n, s in sorted(known.items())]
        if not console.is_terminal:  # piped or redirected: one plain line a stage, to grep
            for row in rows:
                typer.echo("\t".join(row))
            return
        table = Table(title="stages (selpath stages NAME for one in full)", show_lines=False)
        for column in ("stage", "module", "what it does"):
            table.add_column(column, overflow="fold")
        for row in rows:
            table.add_row(*map(escape, row))
        console.print(table)
        return
    from selpath.pipeline.registry import default_registry, registry_for

    with guard():
        registry = registry_for([name]) if name else default_registry()
    for s in [registry[name]] if name else list(registry):
        _print_stage(s)


def _print_stage(s) -> None:
    """One stage in full: its summary, the kinds it makes, then each input and setting with its type, default and
    description."""
    from rich.padding import Padding

    from selpath.pipeline.constraints import describe
    from selpath.pipeline.registry import plain_text

    console.print(f"[bold]{escape(s.name)}[/]  [dim]({escape(s.source)})[/]")
    console.print(escape(plain_text(s.summary)), highlight=False)
    makes = " or ".join(k.name for k in s.kinds) or "any kind (its result's selpath_kind attr names it)"
    console.print(f"  [underline]result[/]: {escape(makes)}", highlight=False)
    if s.returns:
        console.print(Padding(escape(plain_text(s.returns)), (0, 0, 0, 6)), highlight=False)
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
    markdown: Annotated[bool, flag("markdown", "print every kind as the Markdown table of docs/format.md")] = False,
) -> None:
    """List the cube kinds the installed stages make (selpath's and plugins'), one line each (a table in a terminal;
    piped, plain lines: kind, makers and description separated by tabs); NAME shows its variables with dims and
    units, its coordinates' units and its required attrs."""
    with guard():
        index = _installed()  # the manifest: no stage module imported to list them
    makers = {kind: sorted(n for n, s in index["stages"].items() if kind in s["kinds"]) for kind in index["kinds"]}
    if markdown:
        from selpath.pipeline.kinds import describe_kinds
        from selpath.pipeline.registry import default_registry

        with guard():
            print(describe_kinds(default_registry().kinds.values()))
        return
    if name is not None:
        from selpath.pipeline.registry import default_registry, resolve_kind

        with guard():
            if name in index["kinds"]:
                _print_kind(resolve_kind(name, module=index["kinds"][name]["module"]), makers[name])
                return
            registry = default_registry()  # every installed stage decides (a manifest is only a hint)
        if name not in registry.kinds:
            fail(SelpathError(f"unknown cube kind {name!r}; installed: {', '.join(registry.kinds)}"))
        _print_kind(registry.kinds[name], registry.makers(name))
        return
    rows = [(kind, ", ".join(makers[kind]), about["description"]) for kind, about in sorted(index["kinds"].items())]
    if not console.is_terminal:  # piped or redirected: one plain line a kind, to grep
        for row in rows:
            typer.echo("\t".join(row))
        return
    table = Table(title="cube kinds (selpath kinds NAME for one in full)")
    for column in ("kind", "made by", "what it holds"):
        table.add_column(column, overflow="fold")
    for row in rows:
        table.add_row(*map(escape, row))
    console.print(table)


def _print_kind(kind, makers: list[str]) -> None:
    from rich.padding import Padding

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


command()(inspect)


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
    from selpath.pipeline.compute import enable_compile_cache
    from selpath.pipeline.engine import run_workflow
    from selpath.pipeline.spec import load_workflow

    enable_compile_cache()
    names = list(shipped.DEMO) if instrument == "all" else [instrument]
    if any(name not in shipped.DEMO for name in names):
        fail(SelpathError(f"unknown instrument {instrument!r}: choose {', '.join(shipped.DEMO)} or all"))
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
        app.command(name=point.name, cls=Command)(function)
        known.add(point.name)


def main() -> None:
    add_commands()
    app()


if __name__ == "__main__":
    main()
