"""The ``selpath`` command line: run, validate, stages, inspect, demo."""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from pipeline.compute import enable_compile_cache
from pipeline.constraints import describe
from pipeline.engine import RunReport, run_workflow
from pipeline.errors import SelpathError, StoreError
from pipeline.integrity import verify_store
from pipeline.locks import store_lock
from pipeline.provenance import read_provenance
from pipeline.registry import default_registry
from pipeline.report import write_html
from pipeline.spec import load_workflow
from pipeline.store import forget_frames, is_complete, missing_frames, open_store

app = typer.Typer(help="selpath: selected light path measurement, from capture to science.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)
console = Console()
errors = Console(stderr=True)

#: the workflows `selpath demo` runs on the built-in simulated rigs: instrument → (workflow, report name)
DEMO_WORKFLOWS = {
    "tomography": (Path(__file__).resolve().parent.parent / "workflows" / "tomography-sim.yaml", "report.html"),
    "procam": (Path(__file__).resolve().parent.parent / "workflows" / "procam-sim.yaml", "procam-report.html"),
}


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
) -> None:
    """Validate and run a workflow; steps whose stored output is up to date are skipped."""
    enable_compile_cache()
    with _guard():
        workflow = load_workflow(file)
        report = run_workflow(workflow, scheduler=scheduler, progress=progress, reuse=not force, log=console.print)
    _print_report(report)


@app.command()
def validate(file: Annotated[Path, typer.Argument(help="workflow YAML file")]) -> None:
    """Check a workflow without running it; lists every problem with file:line and the fix."""
    with _guard():
        workflow = load_workflow(file)
    console.print(f"[green]ok[/]: {escape(workflow.name)}: {len(workflow.steps)} steps, outputs "
                  + escape(", ".join(f"{n} -> {o.store}" for n, o in workflow.outputs.items())))


@app.command()
def stages(name: Annotated[str | None, typer.Argument(help="show one stage in full")] = None) -> None:
    """List the registered stages with their inputs, settings, defaults, units and docs."""
    with _guard():
        registry = default_registry()
    if name and name not in registry:
        errors.print(f"[bold red]error:[/] unknown stage {escape(repr(name))}; known: {', '.join(registry.names())}")
        raise typer.Exit(2)
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


def _tomography_summary(workflow) -> list[str]:
    absorption = open_store(workflow.outputs["absorption"].store)
    valid = absorption["flags"] == 0
    summary = [f"absorption: {float(valid.mean()) * 100:.1f}% of pixels valid, "
               f"max A = {float(absorption['absorption'].where(valid).max()):.4f}"]
    truth = open_store(workflow.outputs["truth"].store)["sigma"].isel(slice=0)
    for name in ("fbp", "optimised"):
        recon = open_store(workflow.outputs[name].store)
        error = recon["sigma"] - truth
        line = (f"{name}: RMSE {float((error**2).mean() ** 0.5):.3e}, max |error| {float(abs(error).max()):.3e}"
                f" over {recon.sizes['slice']} slice(s)")
        if "iterations" in recon:
            line += (f"; ADMM iterations {recon['iterations'].values.tolist()}, converged "
                     f"{recon['converged'].values.tolist()}")
        summary.append(line)
    return summary


def _procam_summary(workflow) -> list[str]:
    speed = open_store(workflow.outputs["scan_speed"].store)
    transport = open_store(workflow.outputs["transport"].store)
    t = transport["transport"]
    return [f"scan calibration: v_p = {speed.attrs['scan_speed_px_per_us']:.5f} rows/µs, "
            f"sync offset {speed.attrs['sync_offset_us']:.1f} µs",
            f"plane-to-ray transport: {t.sizes['offset']} offsets × {t.sizes['row']} × {t.sizes['col']} pixels, "
            f"{float(transport['converged'].mean()) * 100:.1f}% converged, mean "
            f"{float(transport['iterations'].mean()):.0f} iterations, {len(transport.attrs['frames_dropped'])} "
            f"boundary frames dropped; epipolar share of the light "
            f"{float(t.sel(offset=0).sum() / t.sum()) * 100:.0f}%"]


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="folder for the demo's stores")] = Path("selpath-demo"),
    instrument: Annotated[str, typer.Option(help="tomography, procam or all")] = "all",
    scheduler: Annotated[str | None, typer.Option(help="override the scheduler")] = None,
) -> None:
    """The main jobs on the built-in simulated rigs: the gelatin bin (acquire, process, reconstruct) and the
    projector–camera rig (calibrate, acquire a delay–exposure stack, demultiplex, draw Fig. 38/40/47).

    Writes every store and figure under ``--out``, and ``report.html`` / ``procam-report.html`` beside them.
    """
    enable_compile_cache()
    names = list(DEMO_WORKFLOWS) if instrument == "all" else [instrument]
    if any(name not in DEMO_WORKFLOWS for name in names):
        _fail(SelpathError(f"unknown instrument {instrument!r}: choose tomography, procam or all"))
    summaries = {"tomography": _tomography_summary, "procam": _procam_summary}
    with _guard():
        for name in names:
            path, page_name = DEMO_WORKFLOWS[name]
            workflow = load_workflow(path).rerooted(out)
            report = run_workflow(workflow, scheduler=scheduler, log=console.print)
            _print_report(report)
            summary = summaries[name](workflow)
            page = write_html(workflow, report, Path(out) / page_name, summary=summary)
            for line in summary:
                console.print(line)
            console.print(f"report: {escape(str(page))}")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
