"""Running a validated workflow: one lazy graph, all outputs in one pass, provenance, reuse.

Every step gets a *step hash* from its stage, its settings, the hashes of the steps it reads and the
identity of any external store it reads. A step with a stored output whose provenance carries the
same hash is not run at all: its result is read back lazily from that store, so re-running an
unchanged workflow computes nothing, and changing one setting recomputes only the steps after it.
Provenance is written only after an output's data is complete, so an interrupted run is redone.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import inspect
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import xarray as xr

from pipeline.compute import compute, scheduler_session
from pipeline.errors import Problem, StageError
from pipeline.spec import OutputSpec, Ref, Step, Workflow
from pipeline.store import open_store, read_provenance, to_store, write_provenance

_PACKAGES = ("selpath", "xarray", "dask", "zarr", "numpy", "jax")


def package_versions() -> dict[str, str]:
    out = {}
    for name in _PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def _digest(payload: Any) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:32]


def step_records(workflow: Workflow) -> dict[str, dict[str, Any]]:
    """For each step, what determines its result (stage, settings, inputs, external data) and its hash."""
    records: dict[str, dict[str, Any]] = {}
    selpath_version = package_versions()["selpath"]
    for step_id, step in workflow.steps.items():  # dependency order: inputs are already recorded
        settings = step.settings.model_dump(mode="json")
        record = {
            "stage": step.stage.name,
            "stage_source": step.stage.source,
            "selpath": selpath_version,
            "settings": settings,
            "inputs": {k: {"ref": str(r), "step_hash": records[r.step]["step_hash"]} for k, r in step.inputs.items()},
            "external": step.stage.identity(step.settings) if step.stage.identity else None,
        }
        record["step_hash"] = _digest(record)
        records[step_id] = record
    return records


@dataclass
class StepReport:
    id: str
    status: str  # "computed" | "reused" | "not needed"
    reason: str


@dataclass
class RunReport:
    workflow: str
    steps: dict[str, StepReport] = field(default_factory=dict)
    written: list[str] = field(default_factory=list)
    #: output stores whose provenance already matches their step: read back, never rewritten
    fresh: set[str] = field(default_factory=set)
    seconds: float = 0.0

    def computed(self) -> list[str]:
        return [s.id for s in self.steps.values() if s.status == "computed"]


def _why_changed(stored: dict | None, record: dict, store: str) -> str:
    if stored is None:
        return f"no finished output at {store}"
    old = stored.get("step_record", {})
    changed = sorted(k for k in set(old.get("settings", {})) | set(record["settings"])
                     if old.get("settings", {}).get(k) != record["settings"].get(k))
    if changed:
        return "settings changed: " + ", ".join(
            f"{k} {old.get('settings', {}).get(k)!r} -> {record['settings'].get(k)!r}" for k in changed)
    if old.get("stage") != record["stage"] or old.get("stage_source") != record["stage_source"]:
        return "stage changed"
    if old.get("selpath") != record["selpath"]:
        return f"selpath version changed ({old.get('selpath')} -> {record['selpath']})"
    inputs = sorted(k for k in record["inputs"] if old.get("inputs", {}).get(k) != record["inputs"][k])
    if inputs:
        return "inputs changed: " + ", ".join(record["inputs"][k]["ref"] for k in inputs)
    return "input data changed"


def _select(result: Any, ref: Ref, step: Step) -> xr.Dataset | xr.DataArray:
    if ref.variable is None:
        return result
    if not isinstance(result, xr.Dataset) or ref.variable not in result.data_vars:
        have = list(result.data_vars) if isinstance(result, xr.Dataset) else "a single array"
        raise StageError(Problem(f"{ref} names no variable of step {ref.step!r} (it has {have})",
                                 path=f"steps[{step.index}]", fix="use one of its variables or the whole $step"))
    return result[ref.variable]


def _call(step: Step, inputs: dict[str, Any]) -> xr.Dataset | xr.DataArray:
    signature = inspect.signature(step.stage.func)
    args = []
    for name in step.stage.inputs:
        args.append(inputs[name] if name in inputs else signature.parameters[name].default)
    settings = {name: getattr(step.settings, name) for name in type(step.settings).model_fields}
    result = step.stage.func(*args, **settings)
    if not isinstance(result, xr.Dataset | xr.DataArray):
        raise StageError(Problem(f"stage {step.stage.name!r} returned {type(result).__name__}, "
                                 "not an xarray Dataset or DataArray", path=f"steps[{step.index}] ({step.id})"))
    return result


def build(workflow: Workflow, *, reuse: bool = True, log: Callable[[str], None] = lambda _: None):
    """Build every output's lazy result, reusing stored outputs with the same provenance.

    Returns ``(results by step id, step records, RunReport)``; nothing is computed.
    """
    records = step_records(workflow)
    report = RunReport(workflow.name)
    outputs_of: dict[str, list[OutputSpec]] = {}
    stored: dict[str, dict | None] = {}
    for out in workflow.outputs.values():
        outputs_of.setdefault(out.from_, []).append(out)
        stored[out.store] = read_provenance(out.store)  # once per output, shared with run_workflow
        if reuse and (stored[out.store] or {}).get("step_hash") == records[out.from_]["step_hash"]:
            report.fresh.add(out.store)
    results: dict[str, Any] = {}

    def resolve(step_id: str) -> Any:
        if step_id in results:
            return results[step_id]
        step, record = workflow.steps[step_id], records[step_id]
        reasons = []
        for out in outputs_of.get(step_id, []):
            if out.store in report.fresh:
                results[step_id] = open_store(out.store)
                report.steps[step_id] = StepReport(step_id, "reused", f"{out.store} has the same provenance")
                log(f"[dim]skip[/] {step_id}: {out.store} is up to date")
                return results[step_id]
            reasons.append(_why_changed(stored[out.store], record, out.store) if reuse else "forced")
        inputs = {name: _select(resolve(ref.step), ref, step) for name, ref in step.inputs.items()}
        results[step_id] = _call(step, inputs)
        reason = "; ".join(reasons) if reasons else "no stored output (intermediate step)"
        report.steps[step_id] = StepReport(step_id, "computed", reason)
        log(f"[bold]run[/]  {step_id} ({step.stage.name}): {reason}")
        return results[step_id]

    for out in workflow.outputs.values():
        resolve(out.from_)
    for step_id in workflow.steps:
        report.steps.setdefault(step_id, StepReport(step_id, "not needed", "no output depends on it"))
    return results, records, report


def _as_dataset(result: xr.Dataset | xr.DataArray, name: str) -> xr.Dataset:
    if isinstance(result, xr.DataArray):
        return result.to_dataset(name=result.name or name, promote_attrs=True)
    return result


def run_workflow(workflow: Workflow, *, scheduler: str | None = None, progress: bool = True, reuse: bool = True,
                 log: Callable[[str], None] = lambda _: None) -> RunReport:
    """Run ``workflow``: build one lazy graph, compute every stale output in one pass, record provenance."""
    start = time.perf_counter()
    scheduler = scheduler or workflow.scheduler
    results, records, report = build(workflow, reuse=reuse, log=log)
    pending = []
    for name, out in workflow.outputs.items():
        if out.store in report.fresh:
            continue
        if out.store in workflow.self_written:  # the stage filled it as it ran: record, never rewrite
            pending.append((name, out, None))
            continue
        data = _as_dataset(results[out.from_], name)
        kind = out.kind or data.attrs.get("selpath_kind")
        if kind is None:
            raise StageError(Problem(f"the result of step {out.from_!r} has no selpath_kind attr",
                                     path=f"outputs.{name}", fix="set `kind:` on the output"))
        pending.append((name, out, to_store(data, out.store, kind, compute=False)))
    with scheduler_session(scheduler) as client:
        compute([write for _, _, write in pending if write is not None], scheduler=scheduler, client=client,
                progress=progress,
                description=f"{workflow.name}: writing {len(pending)} output(s)")
    for name, out, _ in pending:
        if (out.kind or "") == "figure" or _as_dataset(results[out.from_], name).attrs.get("selpath_kind") == "figure":
            _save_png(out.store)
    now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    for name, out, _ in pending:
        chain = _ancestors(workflow, out.from_)
        write_provenance(out.store, {
            "step_hash": records[out.from_]["step_hash"],
            "step_record": records[out.from_],
            "output": name,
            "workflow": workflow.name,
            "workflow_source": workflow.source,
            "workflow_text": workflow.text,
            "steps": {i: {"stage": records[i]["stage"], "settings": records[i]["settings"],
                          "external": records[i]["external"]} for i in chain},
            "versions": package_versions(),
            "scheduler": scheduler,
            "created": now,
        })
        report.written.append(out.store)
    report.seconds = time.perf_counter() - start
    return report


def _save_png(store: str) -> None:
    """A ``figure`` cube is also written as ``<store>.png`` beside its store, for people."""
    import matplotlib.image

    image = open_store(store, "figure")["image"].values
    matplotlib.image.imsave(f"{store.removesuffix('.zarr')}.png", image)


def _ancestors(workflow: Workflow, step_id: str) -> list[str]:
    seen: list[str] = []

    def visit(i: str) -> None:
        if i not in seen:
            for ref in workflow.steps[i].inputs.values():
                visit(ref.step)
            seen.append(i)

    visit(step_id)
    return seen
