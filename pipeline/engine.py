"""Running a validated workflow: lazy graphs, outputs written upstream first, provenance, reuse.

Every step gets a *step hash* from its stage, its settings, the hashes of the steps it reads and the
identity of any external store it reads. A step with a stored output whose provenance carries the
same hash is not run at all: its result is read back lazily from that store, so re-running an
unchanged workflow computes nothing, and changing one setting recomputes only the steps after it.
Provenance is written only after an output's data is complete, so an interrupted run is redone.

Nothing a user owns is ever deleted: output paths are checked before anything runs
(:func:`selpath.pipeline.spec.check_output_paths`), every output store is locked for the run
(:mod:`selpath.pipeline.locks`), and each is written into a temporary sibling, given its manifest and provenance,
and only then moved into place (:mod:`selpath.pipeline.outputs`).
"""

from __future__ import annotations

import datetime as _dt
import inspect
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import xarray as xr
import zarr
from rich.markup import escape

from selpath.pipeline.capture_store import forget_frames, has_missing_frames
from selpath.pipeline.compute import compute, scheduler_line, scheduler_session
from selpath.pipeline.errors import Problem, StageError, StoreError
from selpath.pipeline.identity import package_versions, step_records, why_changed
from selpath.pipeline.integrity import (
    PROVENANCE_GROUP,
    BadChunk,
    record_chunk_sizes,
    resized_chunks,
    verify_store,
    write_manifest,
)
from selpath.pipeline.kinds import CubeKind
from selpath.pipeline.locks import store_locks
from selpath.pipeline.outputs import PNG_MARKER, Staging, check_png, png_path, tidy_staging
from selpath.pipeline.provenance import read_provenance, write_provenance
from selpath.pipeline.quality import ADVISE, FIX, LABEL, WHAT, below_floor, shares
from selpath.pipeline.registry import resolve_kind
from selpath.pipeline.spec import OutputSpec, Ref, Step, Workflow, check_output_paths
from selpath.pipeline.store import open_store, write_store


@dataclass
class StepReport:
    id: str
    status: str  # "computed" | "reused" | "not needed"
    reason: str
    #: the step's stage name
    stage: str = ""
    #: wall-clock seconds the step took in this run: its stage call (an acquisition captures there) plus the writing
    #: of its outputs (where a lazy step's work happens, with that of the unstored steps it reads); None for an
    #: unstored (intermediate) step, whose work is counted in the output that reads it
    seconds: float | None = None


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


class _Graph:
    """The lazy results of a workflow's steps, built on demand, reusing stored outputs of the same provenance."""

    def __init__(self, workflow: Workflow, *, reuse: bool, log: Callable[[str], None], verify: bool = False):
        self.workflow, self.reuse, self.log = workflow, reuse, log
        self.records = step_records(workflow)
        self.report = RunReport(workflow.name)
        self.results: dict[str, Any] = {}
        self._outputs_of: dict[str, list[OutputSpec]] = {}
        self._stored: dict[str, dict | None] = {}
        #: steps whose usable shares were checked when an output was written
        self.checked: set[str] = set()
        #: up-to-date outputs in which ``verify`` found bad chunks: recomputed (frames: captured again)
        self.damaged: dict[str, list[BadChunk]] = {}
        for out in workflow.outputs.values():
            self._outputs_of.setdefault(out.from_, []).append(out)
            self._stored[out.store] = read_provenance(out.store)  # once per output
            if reuse and (self._stored[out.store] or {}).get("step_hash") == self.records[out.from_]["step_hash"]:
                if self._damaged(out, None if verify else _resized(out.store)):
                    continue
                if out.store in workflow.self_written and has_missing_frames(out.store):
                    continue  # a frame's chunk was lost (or marked for recapture): the acquisition resumes
                self.report.fresh.add(out.store)

    def _damaged(self, out: OutputSpec, bad: list[BadChunk] | None = None) -> bool:
        """Whether an up-to-date output is damaged: ``bad`` chunks already found (a chunk whose size changed since it
        was written, :func:`_resized`), else every chunk read (``--verify``). A damaged capture has the frames under
        its bad chunks marked not captured, so its acquisition captures just those again; any other damaged output
        is recomputed whole (the outputs after it were made from its intact data and stay; after a capture, whose
        frames captured again differ by their noise, they are recomputed)."""
        capture = out.store in self.workflow.self_written
        how = "verify" if bad is None else "check"
        if bad is None:
            try:
                bad = verify_store(out.store)
            except StoreError as exc:  # its root metadata does not read: a capture cannot resume from it
                if capture:
                    raise
                bad = [BadChunk("zarr.json", None, exc.problems[0].message)]
        if not bad:
            return False
        self.damaged[out.store] = bad
        listed = "; ".join(str(b) for b in bad[:3]) + (" …" if len(bad) > 3 else "")
        if capture:
            frames = forget_frames(out.store, bad)  # StoreError where a bad chunk is not a frame
            self.log(f"[yellow]{how}[/]: {escape(out.store)}: {len(bad)} bad chunk(s) ({escape(listed)}); "
                     f"{frames} frame(s) will be captured again")
            return frames > 0 or has_missing_frames(out.store)
        self.log(f"[yellow]{how}[/]: {escape(out.store)}: {len(bad)} bad chunk(s) ({escape(listed)}); "
                 "it will be computed again")
        return True

    def resolve(self, step_id: str) -> Any:
        """The step's lazy result: read back from a fresh output, or its stage called on its inputs."""
        if step_id in self.results:
            return self.results[step_id]
        step, record = self.workflow.steps[step_id], self.records[step_id]
        reasons = []
        for out in self._outputs_of.get(step_id, []):
            if out.store in self.report.fresh:
                self.results[step_id] = open_store(out.store, registry=self.workflow.registry)
                self.report.steps[step_id] = StepReport(step_id, "reused", f"{out.store} has the same provenance",
                                                        step.stage.name)
                self.log(f"[dim]── {escape(step_id)} ({escape(step.stage.name)}): reused, {escape(out.store)} is up "
                         "to date[/]")
                return self.results[step_id]
            reasons.append(f"{out.store} has {len(self.damaged[out.store])} bad chunk(s) (--verify)"
                           if out.store in self.damaged else
                           why_changed(self._stored[out.store], record, out.store) if self.reuse else
                           "forced (--force)")
        inputs = {name: _select(self.resolve(ref.step), ref, step) for name, ref in step.inputs.items()}
        own = [o.store for o in self._outputs_of.get(step_id, []) if o.store in self.workflow.self_written]
        recaptured = [s for s in own if self._stored[s] is not None]  # frames captured again into a finished store
        stored = bool(self._outputs_of.get(step_id))
        reason = "; ".join(reasons) if stored else "intermediate step: computed while writing the outputs that read it"
        self.report.steps[step_id] = StepReport(step_id, "computed", reason, step.stage.name)
        self.log(f"[bold]── {escape(step_id)}[/] ({escape(step.stage.name)}): {escape(reason)}")
        start = time.perf_counter()
        self.results[step_id] = _call(step, inputs)
        if stored:
            self.report.steps[step_id].seconds = time.perf_counter() - start
        if recaptured:
            self._stale_after(step_id)
        return self.results[step_id]

    def _stale_after(self, step_id: str) -> None:
        """Outputs downstream of ``step_id`` are no longer fresh: its store's data changed under the same
        settings (frames captured again after a chunk was lost), so their stored results are out of date."""
        for out in self.workflow.outputs.values():
            if out.from_ != step_id and step_id in self.workflow.ancestors(out.from_):
                self.report.fresh.discard(out.store)

    def unchecked(self, step_id: str) -> list[str]:
        """``step_id`` and the steps upstream of it computed in this run whose usable shares are not yet checked
        (a step read back from a store was checked when it was written)."""
        return [i for i in self.workflow.ancestors(step_id)
                if i not in self.checked and self.report.steps.get(i, StepReport(i, "", "")).status == "computed"]

    def finish(self) -> None:
        for step_id, step in self.workflow.steps.items():
            self.report.steps.setdefault(step_id, StepReport(step_id, "not needed", "no output depends on it",
                                                             step.stage.name))


def build(workflow: Workflow, *, reuse: bool = True, log: Callable[[str], None] = lambda _: None):
    """Build every output's lazy result, reusing stored outputs with the same provenance.

    Returns ``(results by step id, step records, RunReport)``; nothing is computed.
    """
    graph = _Graph(workflow, reuse=reuse, log=log)
    for out in workflow.outputs.values():
        graph.resolve(out.from_)
    graph.finish()
    return graph.results, graph.records, graph.report


def _as_dataset(result: xr.Dataset | xr.DataArray, name: str) -> xr.Dataset:
    if isinstance(result, xr.DataArray):
        return result.to_dataset(name=result.name or name, promote_attrs=True)
    return result


def run_workflow(workflow: Workflow, *, scheduler: str | None = None, progress: bool = True, reuse: bool = True,
                 verify: bool = False, log: Callable[[str], None] = lambda _: None) -> RunReport:
    """Run ``workflow``: write every stale output, upstream first, and record its provenance.

    Outputs are written one at a time in dependency order, and a written output is read back from its
    store by the steps after it, so nothing stored is ever computed twice. (Writing all outputs in one
    ``dask.compute`` does not share their common upstream: dask 2026.8 gives each ``to_zarr(compute=False)``
    a private, optimised copy of its graph, ``ProhibitReuse``, so every output recomputed it.) An output's
    provenance is written as soon as its data is complete, so a killed run keeps every finished output.

    Before an output is reused, its chunks' sizes are compared with those recorded when it was written (one listing,
    nothing read): a chunk truncated or replaced since makes it damaged. ``verify`` also reads every chunk of the
    outputs that would be reused (their checksums). A damaged output is computed again, a damaged capture captures
    again only the frames under its bad chunks (and the outputs after it are recomputed). A chunk changed in place to
    bytes of the same size is found only by ``verify``, or when it is read (a StoreError naming it).
    """
    start = time.perf_counter()
    scheduler = scheduler or workflow.scheduler
    check_output_paths(workflow)
    stores = [out.store for out in workflow.outputs.values()]
    with store_locks(stores, purpose=f"selpath run {workflow.source}"):
        for store in stores:
            for done in tidy_staging(store):
                log(f"[dim]tidy[/] {escape(done)}")
        graph = _Graph(workflow, reuse=reuse, log=log, verify=verify)
        order = list(workflow.steps)  # dependency order
        outputs = sorted(workflow.outputs.items(), key=lambda item: order.index(item[1].from_))
        with scheduler_session(scheduler) as client:
            log(f"[dim]{escape(scheduler_line(scheduler, client))}[/]")
            for number, (name, out) in enumerate(outputs, 1):
                result = graph.resolve(out.from_)
                if out.store in graph.report.fresh:
                    continue
                began = time.perf_counter()
                if out.store in workflow.self_written:  # the stage filled it as it ran: record, never rewrite
                    if not has_missing_frames(out.store):  # complete: its chunks' sizes, for the checks to come
                        record_chunk_sizes(out.store)
                    _record(workflow, graph.records, name, out, scheduler, out.store)
                else:
                    _write_output(graph, name, out, _as_dataset(result, name), scheduler, client, progress,
                                  f"output {number}/{len(outputs)}: writing {os.path.basename(out.store)}")
                graph.report.written.append(out.store)
                step = graph.report.steps[out.from_]
                step.seconds = (step.seconds or 0.0) + time.perf_counter() - began
                log(f"   wrote {escape(out.store)} ({step.seconds:.1f} s)")
                # the steps after it read the stored cube
                graph.results[out.from_] = open_store(out.store, registry=workflow.registry)
    graph.finish()
    graph.report.seconds = time.perf_counter() - start
    return graph.report


def _write_output(graph: _Graph, name: str, out: OutputSpec, data: xr.Dataset, scheduler: str, client: Any,
                  progress: bool, description: str) -> None:
    """Write one output into a staging sibling, check usable shares (:mod:`selpath.pipeline.quality`), add its manifest,
    provenance and (for figures) PNG, then move it into place.

    Checked: the output step's own shares; for a step with none (a figure), those of the unstored steps upstream,
    written beside it in the same pass. Upstream shares of a step with its own are computed only to explain its
    failure: carrying them would make every upstream pixel be computed (a beam rig's absorption on every camera
    row, where align_paths reads one or two).
    """
    workflow = graph.workflow
    kind = _output_kind(workflow, name, out, data)
    if kind.png is not None:
        check_png(out.store)
    upstream = [step for step in graph.unchecked(out.from_) if step != out.from_]
    own = shares(data)
    carried = {} if own else {f"{_CARRIED}{step}.{var}": (step, var, share) for step in upstream
                              for var, share in shares(graph.results[step]).items()}
    staging = Staging(out.store)
    try:
        write = write_store(data.assign({key: share for key, (_, _, share) in carried.items()}), staging.path, kind,
                            compute=False,
                            replace=staging.path == staging.final)
        compute([write], scheduler=scheduler, client=client, progress=progress, description=description)
        usable = _usable(staging.path, out.from_, data, carried, graph, explain=upstream if own else [],
                         compute_on=(scheduler, client))
        write_manifest(staging.path, data)
        _record(workflow, graph.records, name, out, scheduler, staging.path, usable)
        if kind.png is not None:
            _save_png(staging.path, out.store, kind)
    except BaseException:
        staging.abort()
        raise
    staging.commit()
    graph.checked.update([*upstream, out.from_])


def _output_kind(workflow: Workflow, name: str, out: OutputSpec, data: xr.Dataset) -> CubeKind:
    """The kind an output is stored as: the output's ``kind:``; else the result's ``selpath_kind`` attr where the stage
    declares that kind or declares none; else the one kind its stage declares (a result that kept its input's attr
    is still the stage's kind); looked up among the workflow's registry's kinds, then the installed ones."""
    stage = workflow.steps[out.from_].stage
    named, declared = data.attrs.get("selpath_kind"), [k.name for k in stage.kinds]
    if out.kind is not None:
        kind = out.kind
    elif named is not None and (named in declared or not declared):
        kind = named
    elif len(declared) == 1:
        kind = stage.kinds[0]
    else:
        what = f"is a {named!r} cube" if named is not None else "names no cube kind (no selpath_kind attr)"
        makes = f"makes {' or '.join(declared)}" if declared else "declares none"
        raise StageError(Problem(f"the result of step {out.from_!r} {what}; its stage {stage.name!r} {makes}",
                                 path=f"outputs.{name}", fix="set `kind:` on the output, or label the result with a "
                                 "kind its stage declares (@stage(..., kind=...): docs/tutorials/plugins.md)"))
    try:
        return resolve_kind(kind, workflow.registry)
    except StoreError as exc:
        raise StageError([Problem(p.message, path=f"outputs.{name} (step {out.from_!r})", fix=p.fix)
                          for p in exc.problems]) from None


#: prefix of the upstream shares written beside an output, ``usable.<step>.<variable>``
_CARRIED = "usable."


def _usable(staging: str, step_id: str, data: xr.Dataset, carried: dict[str, tuple[str, str, xr.DataArray]],
            graph: _Graph, *, explain: list[str], compute_on: tuple[str, Any]) -> dict[str, dict[str, float]]:
    """The usable shares just written beside an output, checked against their floors, the carried ones of
    upstream steps removed from the store. Below a floor: the shares of the ``explain`` steps are computed too,
    and one StageError names every share below its floor, upstream first. Returns the shares by step."""
    group = zarr.open_group(staging, mode="r+")
    found: dict[str, dict[str, float]] = {}
    attrs: dict[str, dict[str, Any]] = {}
    for var, share in shares(data).items():
        found.setdefault(step_id, {})[var] = float(group[var][()])
        attrs.setdefault(step_id, {})[var] = share.attrs
    for key, (step, var, share) in carried.items():
        found.setdefault(step, {})[var] = float(group[key][()])
        attrs.setdefault(step, {})[var] = share.attrs
        del group[key]
    problems = [p for step, values in found.items() for p in below_floor(step, values, attrs[step])]
    for step, values in found.items():
        for var, value in values.items():
            meta = attrs[step][var]
            label = escape(str(meta.get(LABEL, "usable")))
            graph.log(f"   {label} ({escape(step)}): {value:.1%} of {escape(meta[WHAT])}")
            if value < meta.get(ADVISE, -math.inf):
                graph.log(f"   advice ({escape(step)}): {escape(meta[FIX])}")
    if problems and explain:
        upstream = [(step, var, share) for step in explain for var, share in shares(graph.results[step]).items()]
        scheduler, client = compute_on
        values = compute([share.data for _, _, share in upstream], scheduler=scheduler, client=client, progress=False)
        causes = [p for (step, var, share), value in zip(upstream, values, strict=True)
                  for p in below_floor(step, {var: float(value)}, {var: share.attrs})]
        problems = causes + problems
    if problems:
        raise StageError(problems)
    return found


def _resized(store: str) -> list[BadChunk]:
    """The chunks of a stored output whose size changed since it was written (one listing, nothing read); none where
    the store records no sizes. A manifest that does not read counts as a bad record."""
    try:
        return resized_chunks(store) or []
    except StoreError as exc:
        return [BadChunk(PROVENANCE_GROUP, None, exc.problems[0].message)]


def _record(workflow: Workflow, records: dict[str, dict[str, Any]], name: str, out: OutputSpec, scheduler: str,
            target: str, usable: dict[str, dict[str, float]] | None = None) -> None:
    """Write an output's provenance into ``target`` (its store, or the staging copy), once its data is complete."""
    chain = workflow.ancestors(out.from_)
    write_provenance(target, {
        "step_hash": records[out.from_]["step_hash"],
        "step_record": records[out.from_],
        "output": name,
        "workflow": workflow.name,
        "workflow_source": workflow.source,
        # where it ran, for people: the step records' relative paths are relative to this folder
        "workflow_folder": str(workflow.base_dir),
        "workflow_text": workflow.text,
        "steps": {i: {"stage": records[i]["stage"], "settings": records[i]["settings"],
                      "external": records[i]["external"]} for i in chain},
        "versions": package_versions(),
        "scheduler": scheduler,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "usable": usable or {},
    })


def _save_png(source: str, store: str, kind: CubeKind) -> None:
    """A cube whose kind names a ``png`` variable (a figure; written at ``source``) is also saved as
    ``<store>.png`` beside its store, for people."""
    import matplotlib.image

    image = open_store(source, kind)[kind.png].values
    staging = f"{png_path(store)}.partial"
    matplotlib.image.imsave(staging, image, format="png", metadata={PNG_MARKER: store})
    os.replace(staging, png_path(store))
