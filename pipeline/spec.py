"""Workflow files: strict schema, wiring and validation against the stage registry.

A workflow is YAML read with the safe loader (it can name registered stages only, never code).
:func:`load_workflow` checks the *whole* file before anything runs and raises one
:class:`~selpath.pipeline.errors.SpecError` listing every problem with its ``file:line``, its path in the
file (``steps[2].with.n_theta``) and a fix. Relative paths in settings typed
:data:`~selpath.pipeline.constraints.StorePath` are
resolved against the workflow file's folder, so a workflow runs the same from any working directory.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pydantic

from selpath.pipeline.constraints import PathMarker, describe
from selpath.pipeline.errors import Problem, SpecError
from selpath.pipeline.outputs import OutputPath, output_problems
from selpath.pipeline.registry import Stage, StageRegistry, installed_kind_names, registry_for
from selpath.pipeline.remote import is_url, local_path, url_problems
from selpath.pipeline.report_spec import ReportSpec, report_problems
from selpath.pipeline.yaml_source import Located, format_path, parse_yaml, pydantic_message, read_source

REF = re.compile(r"^\$(?P<step>[A-Za-z_][A-Za-z0-9_-]*)(?:\.(?P<variable>[A-Za-z_][A-Za-z0-9_]*))?$")
SCHEDULERS = ("synchronous", "threads", "processes")


@dataclass(frozen=True)
class Ref:
    """A wire from another step's result (``$step``) or one of its variables (``$step.variable``)."""

    step: str
    variable: str | None = None

    def __str__(self) -> str:
        return f"${self.step}" + (f".{self.variable}" if self.variable else "")


def parse_ref(value: Any) -> Ref | None:
    if isinstance(value, str):
        match = REF.match(value)
        if match:
            return Ref(match["step"], match["variable"])
    return None


# -- the file's structure (pydantic, strict, every field described) ---------------------------------


class _Strict(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", strict=True, populate_by_name=True)


class StepSpec(_Strict):
    id: str = pydantic.Field(pattern=r"^[A-Za-z_][A-Za-z0-9_-]*$", description="unique step name, used as $id")
    stage: str = pydantic.Field(description="a registered stage name (see `selpath stages`)")
    with_: dict[str, Any] = pydantic.Field(default_factory=dict, alias="with",
                                           description="data inputs ($id, $id.var) and settings of the stage")


class OutputSpec(_Strict):
    from_: str = pydantic.Field(alias="from", description="id of the step whose result is stored")
    store: str = pydantic.Field(description="zarr store path, relative to the workflow file's folder")
    kind: str | None = pydantic.Field(None, description="cube kind to check before writing (default: the "
                                      "result's selpath_kind attr)")
    replace: bool = pydantic.Field(False, description="replace a finished store that another workflow or output "
                                   "wrote at this path (atomically: the old one stays until the new one is "
                                   "complete); without it such a store is refused")


class WorkflowFile(_Strict):
    workflow: str = pydantic.Field(description="name of the workflow")
    scheduler: str = pydantic.Field("threads", description="synchronous | threads | processes | tcp://host:port")
    steps: list[StepSpec] = pydantic.Field(min_length=1, description="the stages to run, wired by $id")
    outputs: dict[str, OutputSpec] = pydantic.Field(default_factory=dict, description="results stored as zarr")
    report: ReportSpec | None = pydantic.Field(None, description="the HTML report `selpath run --report` and "
                                               "`selpath demo` write: figures and summary numbers")

    @pydantic.field_validator("scheduler")
    @classmethod
    def _scheduler(cls, value: str) -> str:
        if value not in SCHEDULERS and not value.startswith("tcp://"):
            raise ValueError(f"must be one of {', '.join(SCHEDULERS)} or a tcp://host:port address")
        return value


# -- the validated workflow ------------------------------------------------------------------------


@dataclass(frozen=True)
class Step:
    id: str
    stage: Stage
    inputs: dict[str, Ref]
    settings: pydantic.BaseModel
    index: int


@dataclass(frozen=True)
class Workflow:
    name: str
    scheduler: str
    steps: dict[str, Step]  # in an order where every step follows its inputs
    outputs: dict[str, OutputSpec]  # store paths already resolved
    text: str
    source: str
    base_dir: Path
    #: stores that a step's stage fills itself (acquisitions): outputs the engine must not rewrite
    self_written: frozenset[str] = frozenset()
    #: the ``report:`` section, its file already resolved (None: the workflow declares no report)
    report: ReportSpec | None = None
    #: the registry the workflow was validated against: its stages, and the cube kinds they make
    registry: StageRegistry | None = None

    def ancestors(self, step_id: str) -> list[str]:
        """The steps ``step_id`` reads, directly or through others, and itself, inputs first."""
        seen: list[str] = []

        def visit(i: str) -> None:
            if i not in seen:
                for ref in self.steps[i].inputs.values():
                    visit(ref.step)
                seen.append(i)

        visit(step_id)
        return seen

    def rerooted(self, folder: str | os.PathLike) -> Workflow:
        """The same workflow with every output store (and the stores stages fill) moved into ``folder``."""
        moved = {o.store: str((Path(folder) / Path(o.store).name).resolve()) for o in self.outputs.values()}
        steps = {}
        for step_id, step in self.steps.items():
            update = {name: moved[value] for name in type(step.settings).model_fields
                      if is_path_setting(type(step.settings), name)
                      and (value := getattr(step.settings, name)) in moved}
            steps[step_id] = dataclasses.replace(step, settings=step.settings.model_copy(update=update))
        outputs = {n: o.model_copy(update={"store": moved[o.store]}) for n, o in self.outputs.items()}
        report = self.report and self.report.model_copy(
            update={"file": str((Path(folder) / Path(self.report.file).name).resolve())})
        return dataclasses.replace(self, steps=steps, outputs=outputs, report=report,
                                   self_written=frozenset(moved[s] for s in self.self_written))


def load_workflow(path_or_text: str | os.PathLike, registry: StageRegistry | None = None,
                  *, source: str | None = None) -> Workflow:
    """Read, validate and wire a workflow file (or YAML text). Raises one SpecError listing every problem.

    ``registry``: the stages to validate against; by default the installed stages the file names
    (:func:`~selpath.pipeline.registry.registry_for`: only the modules declaring them are imported)."""
    text, source, base_dir = read_source(path_or_text, source)
    raw, located = parse_yaml(text, source)
    if not isinstance(raw, dict):
        raise SpecError(Problem("a workflow file is a mapping with keys workflow, steps and outputs", f"{source}:1"))
    try:
        spec = WorkflowFile.model_validate(raw)
    except pydantic.ValidationError as exc:
        for err in exc.errors():
            loc = tuple("with" if p == "with_" else "from" if p == "from_" else p for p in err["loc"])
            located.add(loc, pydantic_message(err))
        raise SpecError(located.problems) from None
    if registry is None:  # the installed stages the file names: only their modules are imported (a manifest says which)
        registry = registry_for(step.stage for step in spec.steps)
    steps = _check_steps(spec, raw, registry, located, base_dir)
    outputs = _check_outputs(spec, steps, located, base_dir, registry)
    self_written = _self_written_outputs(steps, outputs, located)
    order = _topological_order(steps, located)
    report = _check_report(spec.report, outputs, located, base_dir)
    if not located.problems:
        workflow = Workflow(spec.workflow, spec.scheduler, {i: steps[i] for i in order}, outputs, text, source,
                            base_dir, frozenset(self_written), report, registry)
        for field, message, fix in output_path_problems(workflow):
            located.add(field, message, fix)
    if located.problems:
        raise SpecError(located.problems)
    return workflow


def output_path_problems(workflow: Workflow) -> list[tuple[tuple, str, str]]:
    """Every output store that breaks the rules of :mod:`selpath.pipeline.outputs` (a path ending in ``.zarr``, absent
    or a selpath store, never the folder of another output, an input, the workflow file, its folder or the
    working folder), as ``(location in the file, message, fix)``."""
    writers = {}
    for step in workflow.steps.values():
        if step.stage.writes is not None:
            writers[_resolved(step.stage.writes(step.settings))] = step
    outputs = []
    for name, out in workflow.outputs.items():
        step = writers.get(out.store)
        field = ("steps", step.index, "with", "store") if step is not None else ("outputs", name, "store")
        outputs.append(OutputPath(name, out.store, field, workflow.name, out.store in workflow.self_written,
                                  out.replace))
    protected: dict[str, str] = {}
    for step in workflow.steps.values():
        own = step.stage.writes(step.settings) if step.stage.writes is not None else None
        for name in type(step.settings).model_fields:
            value = getattr(step.settings, name)
            if is_path_setting(type(step.settings), name) and isinstance(value, str) and value and value != own:
                protected[f"the input steps[{step.index}].with.{name}"] = value
    if not workflow.source.startswith("<"):
        protected["the workflow file"] = str(Path(workflow.source).resolve())
    protected["the workflow's folder"] = str(workflow.base_dir)
    protected["the working folder"] = str(Path.cwd())
    return output_problems(outputs, protected)


def check_output_paths(workflow: Workflow) -> None:
    """Raise one SpecError if any output store breaks the rules (see :func:`output_path_problems`)."""
    problems = [Problem(message, workflow.source, format_path(field), fix)
                for field, message, fix in output_path_problems(workflow)]
    if problems:
        raise SpecError(problems)


def _resolved(store: str) -> str:
    return store if "://" in store else str(Path(store).resolve())


def _self_written_outputs(steps: dict[str, Step], outputs: dict[str, OutputSpec], located: Located) -> set[str]:
    """Stages that fill their own store (acquisitions) make it an output, named after the step.

    An explicit output of the same step and store is the same thing; any other output that names
    that store would overwrite the capture and is refused.
    """
    written: set[str] = set()
    for step in steps.values():
        if step.stage.writes is None:
            continue
        store = _resolved(step.stage.writes(step.settings))
        clash = [n for n, o in outputs.items() if o.store == store and o.from_ != step.id]
        for name in clash:
            located.add(("outputs", name, "store"), f"store {store} is filled by step {step.id!r} "
                        f"({step.stage.name}); output {name!r} would overwrite it", "give the output its own store")
        if not any(o.store == store for o in outputs.values()):
            if step.id in outputs:
                located.add(("outputs", step.id), f"output name {step.id!r} is taken by step {step.id!r}'s own store",
                            "rename the output")
            outputs[step.id] = OutputSpec.model_validate({"from": step.id, "store": store})
        written.add(store)
    return written


def _suggest(name: str, choices: list[str]) -> str:
    close = difflib.get_close_matches(name, choices, n=3)
    return f"did you mean {' or '.join(repr(c) for c in close)}?" if close else f"one of: {', '.join(choices)}"


def is_path_setting(model: type[pydantic.BaseModel], name: str) -> bool:
    return any(isinstance(m, PathMarker) for m in model.model_fields[name].metadata)


def _check_steps(spec: WorkflowFile, raw: dict, registry: StageRegistry, located: Located,
                 base_dir: Path) -> dict[str, Step]:
    steps: dict[str, Step] = {}
    seen: dict[str, int] = {}
    for i, step in enumerate(spec.steps):
        where = ("steps", i)
        if step.id in seen:
            located.add((*where, "id"), f"duplicate step id {step.id!r} (also steps[{seen[step.id]}])",
                        "give every step a unique id")
            continue
        seen[step.id] = i
        if step.stage not in registry:
            located.add((*where, "stage"), f"unknown stage {step.stage!r}", _suggest(step.stage, registry.names()))
            continue
        stage = registry[step.stage]
        inputs: dict[str, Ref] = {}
        settings: dict[str, Any] = {}
        for key, value in step.with_.items():
            ref = parse_ref(value)
            path = (*where, "with", key)
            if key in stage.inputs:
                if ref is None:
                    located.add(path, f"data input {key!r} of stage {stage.name!r} takes a reference, got {value!r}",
                                "write $step or $step.variable")
                else:
                    inputs[key] = ref
            elif ref is not None and key in stage.params.model_fields:
                located.add(path, f"setting {key!r} takes a value, not a reference ({value})")
            elif key not in stage.params.model_fields:
                known = list(stage.inputs) + list(stage.params.model_fields)
                located.add(path, f"stage {stage.name!r} has no parameter {key!r}", _suggest(key, known))
            else:
                settings[key] = value
        for name in stage.required_inputs:
            if name not in step.with_:
                located.add((*where, "with"), f"data input {name!r} of stage {stage.name!r} is missing",
                            f"add `{name}: $step`")
        try:
            # strict JSON-mode validation: YAML lists fill tuples, but "3" is no int and 1 no bool
            model = stage.params.model_validate_json(json.dumps(settings, default=str))
        except pydantic.ValidationError as exc:
            for err in exc.errors():
                field = err["loc"][0] if err["loc"] else ""
                expected = stage.params.model_fields.get(str(field))
                fix = f"expected {describe(expected)}" if expected is not None else ""
                located.add((*where, "with", *err["loc"]), f"setting of stage {stage.name!r} "
                            f"{pydantic_message(err)}", fix)
            continue
        refused = False
        for name in stage.params.model_fields:
            value = getattr(model, name)
            if is_path_setting(stage.params, name) and isinstance(value, str) and value:
                if is_url(value):  # object storage: kept as written, credentials never in the file
                    for message in url_problems(value):
                        located.add((*where, "with", name), message)
                        refused = True
                    continue
                model = model.model_copy(update={name: str((base_dir / local_path(value)).resolve())})
        if stage.precheck is not None and not refused:  # a refused URL is never opened
            for message in stage.precheck(model):
                located.add((*where, "with"), message)
        steps[step.id] = Step(step.id, stage, inputs, model, i)
    for step in steps.values():
        for key, ref in step.inputs.items():
            if ref.step not in seen:
                located.add(("steps", step.index, "with", key), f"reference {ref} names no step",
                            _suggest(ref.step, list(seen)))
            elif ref.variable is not None and ref.step in steps:
                known = _variables_of(steps[ref.step])
                if known is not None and ref.variable not in known:
                    located.add(("steps", step.index, "with", key), f"{ref} names no variable of step "
                                f"{ref.step!r} (it has {', '.join(sorted(known))})", _suggest(ref.variable,
                                                                                          sorted(known)))
    return steps


def _variables_of(step: Step) -> set[str] | None:
    """The data variables a step's result will have, where its stage can tell from its settings."""
    if step.stage.variables is None:
        return None
    try:
        names = step.stage.variables(step.settings)
    except Exception:  # noqa: BLE001 - an unreadable store is reported by the stage's own precheck
        return None
    return None if names is None else {str(n) for n in names}


def _check_outputs(spec: WorkflowFile, steps: dict[str, Step], located: Located, base_dir: Path,
                   registry: StageRegistry) -> dict[str, OutputSpec]:
    outputs: dict[str, OutputSpec] = {}
    stores: dict[str, str] = {}
    ids = [s.id for s in spec.steps]
    asked = {out.kind for out in spec.outputs.values() if out.kind is not None} - set(registry.kinds)
    known = sorted(set(registry.kinds) | installed_kind_names(asked)) if asked else sorted(registry.kinds)
    for name, out in spec.outputs.items():
        path = ("outputs", name)
        if out.from_ not in ids:
            located.add((*path, "from"), f"output {name!r} comes from unknown step {out.from_!r}",
                        _suggest(out.from_, ids))
        if out.kind is not None and out.kind not in known:
            located.add((*path, "kind"), f"unknown cube kind {out.kind!r}", _suggest(out.kind, known))
        store = out.store if is_url(out.store) else str((base_dir / local_path(out.store)).resolve())
        for message in url_problems(out.store) if is_url(out.store) else []:
            located.add((*path, "store"), message)
        if not out.store.strip():
            store = ""  # never resolved to the workflow's folder: refused by the path rules below
        if store in stores:
            located.add((*path, "store"), f"store {out.store!r} is also written by output {stores[store]!r}",
                        "give each output its own store")
        stores[store] = name
        outputs[name] = out.model_copy(update={"store": store})
    return outputs


def _check_report(report: ReportSpec | None, outputs: dict[str, OutputSpec], located: Located,
                  base_dir: Path) -> ReportSpec | None:
    """The ``report:`` section with its file resolved; its figures and summary fields must name outputs, and its
    file may not lie inside an output store."""
    if report is None:
        return None
    for field, message, fix in report_problems(report, list(outputs)):
        located.add(field, message, fix)
    file = (base_dir / report.file).resolve()
    for name, out in outputs.items():
        if "://" not in out.store and (file == Path(out.store) or Path(out.store) in file.parents):
            located.add(("report", "file"), f"report file {report.file!r} lies in output {name!r}'s store",
                        "write the report beside the stores, not into one")
    return report.model_copy(update={"file": str(file)})


def _topological_order(steps: dict[str, Step], located: Located) -> list[str]:
    """Steps in dependency order; a cycle is reported with its members (Kahn's algorithm)."""
    needs = {i: {r.step for r in s.inputs.values() if r.step in steps} for i, s in steps.items()}
    order: list[str] = []
    ready = [i for i in steps if not needs[i]]
    while ready:
        current = ready.pop(0)
        order.append(current)
        for i in steps:
            if current in needs[i]:
                needs[i].discard(current)
                if not needs[i]:
                    ready.append(i)
    stuck = [i for i in steps if i not in order]
    if stuck:
        cycle = " -> ".join(f"${i}" for i in stuck)
        located.add(("steps", steps[stuck[0]].index), f"steps form a cycle: {cycle}",
                    "a step cannot depend on itself or on a later step that depends on it")
    return order
