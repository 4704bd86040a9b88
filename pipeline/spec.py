"""Workflow files: strict schema, wiring and validation against the stage registry.

A workflow is YAML read with the safe loader (it can name registered stages only, never code).
:func:`load_workflow` checks the *whole* file before anything runs and raises one
:class:`~pipeline.errors.SpecError` listing every problem with its ``file:line``, its path in the
file (``steps[2].with.n_theta``) and a fix. Relative paths in settings typed :data:`StorePath` are
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
from typing import Annotated, Any, TypeVar

import pydantic
import yaml

from pipeline.constraints import describe
from pipeline.errors import ConfigError, Problem, SpecError
from pipeline.outputs import OutputPath, output_problems
from pipeline.registry import Stage, StageRegistry, default_registry
from pipeline.schema import KINDS


class _PathMarker:
    """Annotation metadata: this str setting is a filesystem path, resolved against the workflow's folder."""


#: Type of a stage setting that names a file or store (relative paths resolve against the workflow file).
StorePath = Annotated[str, _PathMarker()]

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


class WorkflowFile(_Strict):
    workflow: str = pydantic.Field(description="name of the workflow")
    scheduler: str = pydantic.Field("threads", description="synchronous | threads | processes | tcp://host:port")
    steps: list[StepSpec] = pydantic.Field(min_length=1, description="the stages to run, wired by $id")
    outputs: dict[str, OutputSpec] = pydantic.Field(default_factory=dict, description="results stored as zarr")

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

    def rerooted(self, folder: str | os.PathLike) -> Workflow:
        """The same workflow with every output store (and the stores stages fill) moved into ``folder``."""
        moved = {o.store: str((Path(folder) / Path(o.store).name).resolve()) for o in self.outputs.values()}
        steps = {}
        for step_id, step in self.steps.items():
            update = {name: moved[value] for name in type(step.settings).model_fields
                      if _is_path_setting(type(step.settings), name)
                      and (value := getattr(step.settings, name)) in moved}
            steps[step_id] = dataclasses.replace(step, settings=step.settings.model_copy(update=update))
        outputs = {n: o.model_copy(update={"store": moved[o.store]}) for n, o in self.outputs.items()}
        return dataclasses.replace(self, steps=steps, outputs=outputs,
                                   self_written=frozenset(moved[s] for s in self.self_written))


# -- YAML with locations ---------------------------------------------------------------------------


#: Largest document accepted, counting every node as often as aliases repeat it. A workflow has hundreds; nested
#: aliases ("billion laughs") expand a few hundred bytes into billions, which no check may walk.
MAX_NODES = 100_000
#: Deepest nesting accepted (PyYAML and pydantic recurse once per level).
MAX_DEPTH = 64


def _expanded_size(root: yaml.Node, source: str) -> int:
    """Nodes of the document with aliases expanded, counted without expanding them (each node once: linear);
    raises SpecError past MAX_NODES or MAX_DEPTH, or for a recursive alias."""
    sizes: dict[int, int] = {}
    on_path: set[int] = set()

    def size(node: yaml.Node, depth: int) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in on_path:
            raise SpecError(Problem("an alias refers to a node that contains it (a recursive document)",
                                    f"{source}:{node.start_mark.line + 1}", fix="write the value out"))
        if depth > MAX_DEPTH:
            raise SpecError(Problem(f"nested deeper than {MAX_DEPTH} levels", f"{source}:{node.start_mark.line + 1}"))
        on_path.add(key)
        children = ([v for pair in node.value for v in pair] if isinstance(node, yaml.MappingNode)
                    else node.value if isinstance(node, yaml.SequenceNode) else [])
        total = 1 + sum(size(child, depth + 1) for child in children)
        on_path.discard(key)
        sizes[key] = total
        if total > MAX_NODES:
            raise SpecError(Problem(f"the document expands to more than {MAX_NODES:,} nodes through its aliases "
                                    "(a YAML bomb, or a file that is not a workflow)",
                                    f"{source}:{node.start_mark.line + 1}",
                                    fix="write the workflow without nested aliases"))
        return total

    return size(root, 0)


def _locations(node: yaml.Node, path: tuple = (), out: dict | None = None, seen: set | None = None
               ) -> dict[tuple, int]:
    """Map each path in the document (keys and list indices) to its 1-based line. A node reached again through
    an alias is not walked again (its paths resolve to the alias's line)."""
    out = {} if out is None else out
    seen = set() if seen is None else seen
    out[path] = node.start_mark.line + 1
    if id(node) in seen:
        return out
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            out[(*path, key.value)] = key.start_mark.line + 1
            _locations(value, (*path, key.value), out, seen)
            out[(*path, key.value)] = key.start_mark.line + 1
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _locations(item, (*path, i), out, seen)
    return out


def _format_path(path: tuple) -> str:
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text


class _Located:
    def __init__(self, source: str, lines: dict[tuple, int]):
        self.source, self.lines, self.problems = source, lines, []

    def add(self, path: tuple, message: str, fix: str = "") -> None:
        probe = path
        while probe and probe not in self.lines:
            probe = probe[:-1]
        self.problems.append(Problem(message, f"{self.source}:{self.lines.get(probe, 1)}", _format_path(path), fix))


def _read(path_or_text: str | os.PathLike, source: str | None, what: str = "workflow") -> tuple[str, str, Path]:
    candidate = Path(path_or_text) if not isinstance(path_or_text, str) or "\n" not in path_or_text else None
    if candidate is not None:
        if not candidate.is_file():
            raise SpecError(Problem(f"no such {what} file", where=str(candidate), fix="check the path"))
        data = candidate.read_bytes()
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            line = data[: exc.start].count(b"\n") + 1
            raise SpecError(Problem(f"not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start}): a {what} "
                                    "file is YAML text", where=f"{candidate}:{line}",
                                    fix="check that this is the right file; save it as UTF-8")) from None
        return text, source or str(candidate), candidate.resolve().parent
    return str(path_or_text), source or f"<{what}>", Path.cwd()


def _parse(text: str, source: str) -> tuple[Any, _Located]:
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is not None:
            _expanded_size(node, source)
        raw = loader.construct_document(node) if node is not None else None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark else ""
        raise SpecError(Problem(f"not valid YAML: {getattr(exc, 'problem', exc)}", where=f"{source}{line}")) from exc
    except RecursionError:
        raise SpecError(Problem(f"nested too deeply to read (over {MAX_DEPTH} levels)", where=source)) from None
    finally:
        loader.dispose()
    return raw, _Located(source, _locations(node) if node is not None else {})


M = TypeVar("M", bound=pydantic.BaseModel)


def load_yaml_model(path_or_text: str | os.PathLike, model: type[M], *, what: str = "configuration") -> M:
    """Read a YAML file (or text) into a pydantic ``model``; one SpecError lists every problem with file:line.

    Used for every YAML file selpath reads besides workflows (scenes, rig configurations).
    """
    text, source, _ = _read(path_or_text, None, what)
    raw, located = _parse(text, source)
    try:
        return model.model_validate(raw)
    except pydantic.ValidationError as exc:
        for err in exc.errors():
            located.add(_document_path(raw, err["loc"]), _pydantic_message(err))
        raise ConfigError(located.problems) from None


def _document_path(raw: Any, loc: tuple) -> tuple:
    """A pydantic error location as a path in the document: union tags (``kind: cylinder``) dropped."""
    path, node = [], raw
    for part in loc:
        if isinstance(node, dict) and part not in node and part in (node.get("kind"), node.get("model")):
            continue  # a discriminated union's tag, not a key of the file
        if str(part).startswith("function-"):
            continue
        path.append(part)
        if isinstance(node, dict):
            node = node.get(part)
        elif isinstance(node, list) and isinstance(part, int) and part < len(node):
            node = node[part]
        else:
            node = None
    return tuple(path)


def load_workflow(path_or_text: str | os.PathLike, registry: StageRegistry | None = None,
                  *, source: str | None = None) -> Workflow:
    """Read, validate and wire a workflow file (or YAML text). Raises one SpecError listing every problem."""
    registry = default_registry() if registry is None else registry
    text, source, base_dir = _read(path_or_text, source)
    raw, located = _parse(text, source)
    if not isinstance(raw, dict):
        raise SpecError(Problem("a workflow file is a mapping with keys workflow, steps and outputs", f"{source}:1"))
    try:
        spec = WorkflowFile.model_validate(raw)
    except pydantic.ValidationError as exc:
        for err in exc.errors():
            loc = tuple("with" if p == "with_" else "from" if p == "from_" else p for p in err["loc"])
            located.add(loc, _pydantic_message(err))
        raise SpecError(located.problems) from None
    steps = _check_steps(spec, raw, registry, located, base_dir)
    outputs = _check_outputs(spec, steps, located, base_dir)
    self_written = _self_written_outputs(steps, outputs, located)
    order = _topological_order(steps, located)
    if not located.problems:
        workflow = Workflow(spec.workflow, spec.scheduler, {i: steps[i] for i in order}, outputs, text, source,
                            base_dir, frozenset(self_written))
        for field, message, fix in output_path_problems(workflow):
            located.add(field, message, fix)
    if located.problems:
        raise SpecError(located.problems)
    return workflow


def output_path_problems(workflow: Workflow) -> list[tuple[tuple, str, str]]:
    """Every output store that breaks the rules of :mod:`pipeline.outputs` (a path ending in ``.zarr``, absent
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
        outputs.append(OutputPath(name, out.store, field))
    protected: dict[str, str] = {}
    for step in workflow.steps.values():
        own = step.stage.writes(step.settings) if step.stage.writes is not None else None
        for name in type(step.settings).model_fields:
            value = getattr(step.settings, name)
            if _is_path_setting(type(step.settings), name) and isinstance(value, str) and value and value != own:
                protected[f"the input steps[{step.index}].with.{name}"] = value
    if not workflow.source.startswith("<"):
        protected["the workflow file"] = str(Path(workflow.source).resolve())
    protected["the workflow's folder"] = str(workflow.base_dir)
    protected["the working folder"] = str(Path.cwd())
    return output_problems(outputs, protected)


def check_output_paths(workflow: Workflow) -> None:
    """Raise one SpecError if any output store breaks the rules (see :func:`output_path_problems`)."""
    problems = [Problem(message, workflow.source, _format_path(field), fix)
                for field, message, fix in output_path_problems(workflow)]
    if problems:
        raise SpecError(problems)


def _resolved(store: str) -> str:
    return store if "://" in store else str(Path(store).resolve())


def _self_written_outputs(steps: dict[str, Step], outputs: dict[str, OutputSpec], located: _Located) -> set[str]:
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


def _pydantic_message(err: dict) -> str:
    if err["type"] == "missing":
        return "is required but missing"
    if err["type"] == "extra_forbidden":
        return "is not a known field"
    message = err["msg"].removeprefix("Value error, ")
    if isinstance(err.get("input"), dict | list):
        return message
    return f"{message} (got {err['input']!r})"


def _suggest(name: str, choices: list[str]) -> str:
    close = difflib.get_close_matches(name, choices, n=3)
    return f"did you mean {' or '.join(repr(c) for c in close)}?" if close else f"one of: {', '.join(choices)}"


def _is_path_setting(model: type[pydantic.BaseModel], name: str) -> bool:
    return any(isinstance(m, _PathMarker) for m in model.model_fields[name].metadata)


def _check_steps(spec: WorkflowFile, raw: dict, registry: StageRegistry, located: _Located,
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
                            f"{_pydantic_message(err)}", fix)
            continue
        for name in stage.params.model_fields:
            value = getattr(model, name)
            if _is_path_setting(stage.params, name) and isinstance(value, str) and value:
                model = model.model_copy(update={name: str((base_dir / value).resolve())})
        if stage.precheck is not None:
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


def _check_outputs(spec: WorkflowFile, steps: dict[str, Step], located: _Located,
                   base_dir: Path) -> dict[str, OutputSpec]:
    outputs: dict[str, OutputSpec] = {}
    stores: dict[str, str] = {}
    ids = [s.id for s in spec.steps]
    for name, out in spec.outputs.items():
        path = ("outputs", name)
        if out.from_ not in ids:
            located.add((*path, "from"), f"output {name!r} comes from unknown step {out.from_!r}",
                        _suggest(out.from_, ids))
        if out.kind is not None and out.kind not in KINDS:
            located.add((*path, "kind"), f"unknown cube kind {out.kind!r}", _suggest(out.kind, sorted(KINDS)))
        store = out.store if "://" in out.store else str((base_dir / out.store).resolve())
        if not out.store.strip():
            store = ""  # never resolved to the workflow's folder: refused by the path rules below
        if store in stores:
            located.add((*path, "store"), f"store {out.store!r} is also written by output {stores[store]!r}",
                        "give each output its own store")
        stores[store] = name
        outputs[name] = out.model_copy(update={"store": store})
    return outputs


def _topological_order(steps: dict[str, Step], located: _Located) -> list[str]:
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
