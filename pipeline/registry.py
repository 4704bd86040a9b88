"""Stages: pure functions on labelled arrays, registered by name.

``@stage("name")`` only *marks* a function (no global state changes at import). A
:class:`StageRegistry` is an object built from modules, normally those named by the ``selpath.stages``
entry-point group, where built-in stages and third-party plugins register alike (xarray's backend
registry is the model). A stage's signature defines its workflow interface:

* parameters before ``*`` (conventionally positional, e.g. ``capture, /``) are **data inputs**:
  labelled arrays wired in a workflow with ``$step`` or ``$step.variable``;
* keyword-only parameters are **settings**, typed, with defaults; the registry builds a strict
  pydantic model from them, so a workflow with a wrong name, type or value fails before anything runs.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import re
import typing
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any

import pydantic
import xarray as xr
from selpath.pipeline.errors import SelpathError

ENTRY_POINT_GROUP = "selpath.stages"
_MARK = "__selpath_stage__"
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_DATA_TYPES = (xr.Dataset, xr.DataArray)


@dataclass(frozen=True)
class Stage:
    """A registered stage: its function, data inputs, settings model and docs."""

    name: str
    func: Callable[..., Any]
    inputs: tuple[str, ...]
    required_inputs: tuple[str, ...]
    params: type[pydantic.BaseModel]
    summary: str = ""
    param_docs: dict[str, str] = field(default_factory=dict)
    #: optional check run at validation time on validated settings; returns problems as strings
    precheck: Callable[[pydantic.BaseModel], list[str]] | None = None
    #: optional identity of external data the stage reads (e.g. an input store), for provenance
    identity: Callable[[pydantic.BaseModel], Any] | None = None
    #: for stages that write their own store as they go (acquisitions): the store path from the settings.
    #: The engine treats that store as the step's output and never rewrites it.
    writes: Callable[[pydantic.BaseModel], str] | None = None
    #: optional: the data variables the stage's result will have, from its validated settings (None where
    #: unknown), so ``$step.variable`` references are checked when the workflow is validated
    variables: Callable[[pydantic.BaseModel], Iterable[str] | None] | None = None

    @property
    def source(self) -> str:
        return f"{self.func.__module__}:{self.func.__qualname__}"

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.func(*args, **kwargs)


_ROLE = re.compile(r":(?:func|class|mod|data|meth|attr|obj|exc):`~?([^`]+)`")


def plain_text(doc: str) -> str:
    """Docstring text for people: reST roles (``:func:`x```) and literals (````x````) as plain ``x``."""
    return _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1] if m.group(0).count("~") else m.group(1),
                     doc).replace("``", "")


def _param_docs(doc: str) -> dict[str, str]:
    """Descriptions of parameters from a numpydoc ``Parameters`` section."""
    docs: dict[str, str] = {}
    lines = inspect.cleandoc(doc or "").splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Parameters") + 2
    except StopIteration:
        return docs
    current = None
    for i in range(start, len(lines)):
        line = lines[i]
        if i + 1 < len(lines) and re.match(r"^-{3,}$", lines[i + 1].strip()):
            break  # the next section begins
        if line and not line.startswith(" "):
            current = [name.strip() for name in line.split(":")[0].split(",")]  # "alpha, beta : float" documents both
            docs.update(dict.fromkeys(current, ""))
        elif current and line.strip():
            for name in current:
                docs[name] = (docs[name] + " " + line.strip()).strip()
    return docs


def _build_stage(name: str, func: Callable[..., Any], precheck: Callable | None, identity: Callable | None,
                 writes: Callable | None = None, variables: Callable | None = None) -> Stage:
    if not _NAME.match(name):
        raise SelpathError(f"stage name {name!r} must be lower_snake_case")
    hints = typing.get_type_hints(func, include_extras=True)
    signature = inspect.signature(func)
    inputs, required, fields = [], [], {}
    docs = _param_docs(func.__doc__ or "")
    for param in signature.parameters.values():
        where = f"stage {name!r} ({func.__module__}:{func.__qualname__}) parameter {param.name!r}"
        if param.kind in (param.VAR_KEYWORD, param.VAR_POSITIONAL):
            raise SelpathError(f"{where}: *args/**kwargs are not allowed; a stage's parameters must be explicit")
        if param.name not in hints:
            raise SelpathError(f"{where} has no type annotation")
        if param.kind is param.KEYWORD_ONLY:
            default = ... if param.default is param.empty else param.default
            fields[param.name] = (hints[param.name], pydantic.Field(default, description=docs.get(param.name, "")))
        else:
            annotation = hints[param.name]
            types = typing.get_args(annotation) or (annotation,)
            if not any(t in _DATA_TYPES for t in types):
                raise SelpathError(f"{where}: a data input must be annotated xr.Dataset or xr.DataArray; "
                                   "make settings keyword-only (after '*')")
            inputs.append(param.name)
            if param.default is param.empty:
                required.append(param.name)
    model = pydantic.create_model(
        f"{name}_settings",
        __config__=pydantic.ConfigDict(extra="forbid", strict=True, allow_inf_nan=False),
        **fields,
    )
    summary = inspect.cleandoc(func.__doc__ or "").split("\n\n")[0].replace("\n", " ")
    return Stage(name, func, tuple(inputs), tuple(required), model, summary, docs, precheck, identity, writes,
                 variables)


def stage(name: str, *, precheck: Callable[[Any], list[str]] | None = None,
          identity: Callable[[Any], Any] | None = None, writes: Callable[[Any], str] | None = None,
          variables: Callable[[Any], Iterable[str] | None] | None = None) -> Callable:
    """Mark ``func`` as the stage ``name``; the function itself is returned unchanged.

    ``precheck(settings)`` runs when a workflow is validated and returns problems as strings;
    ``identity(settings)`` names external data the stage reads, so provenance changes with it;
    ``writes(settings)`` is the store a stage fills itself while it runs (an acquisition), which then
    is the step's output: the engine records its provenance but never rewrites it; ``variables(settings)``
    lists the data variables of the result where the settings tell them (a store's, a capture kind's).

    >>> import xarray as xr
    >>> @stage("double")
    ... def double(data: xr.DataArray, /, *, factor: float = 2.0) -> xr.DataArray:
    ...     return data * factor
    >>> double.__selpath_stage__.inputs, list(double.__selpath_stage__.params.model_fields)
    (('data',), ['factor'])
    """

    def mark(func: Callable[..., Any]) -> Callable[..., Any]:
        setattr(func, _MARK, _build_stage(name, func, precheck, identity, writes, variables))
        return func

    return mark


class StageRegistry:
    """Stages by name. Duplicate names are refused, naming both sources."""

    def __init__(self, stages: Iterable[Stage] = ()):
        self._stages: dict[str, Stage] = {}
        for s in stages:
            self.add(s)

    def add(self, new: Stage) -> None:
        old = self._stages.get(new.name)
        if old is not None and old.func is not new.func:
            raise SelpathError(f"stage {new.name!r} is registered twice: by {old.source} and by {new.source}; "
                               "rename one of them")
        self._stages[new.name] = new

    @classmethod
    def from_modules(cls, modules: Iterable[ModuleType | str]) -> StageRegistry:
        registry = cls()
        for module in modules:
            if isinstance(module, str):
                module = importlib.import_module(module)
            for _, obj in sorted(vars(module).items()):
                marked = getattr(obj, _MARK, None)
                if isinstance(marked, Stage) and getattr(obj, "__module__", None) == module.__name__:
                    registry.add(marked)
        return registry

    @classmethod
    def from_entry_points(cls, group: str = ENTRY_POINT_GROUP) -> StageRegistry:
        modules = []
        for ep in sorted(entry_points(group=group), key=lambda e: e.name):
            try:
                modules.append(ep.load())
            except Exception as exc:  # a broken plugin must say which one it is
                raise SelpathError(f"stage plugin {ep.name!r} ({ep.value}) failed to import: "
                                   f"{type(exc).__name__}: {exc}") from exc
        return cls.from_modules(modules)

    def __getitem__(self, name: str) -> Stage:
        return self._stages[name]

    def __contains__(self, name: object) -> bool:
        return name in self._stages

    def __iter__(self):
        return iter(sorted(self._stages.values(), key=lambda s: s.name))

    def names(self) -> list[str]:
        return sorted(self._stages)


@functools.cache
def default_registry() -> StageRegistry:
    """The stages installed in this environment (entry-point group ``selpath.stages``), cached."""
    return StageRegistry.from_entry_points()
