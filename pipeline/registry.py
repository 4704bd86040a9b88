"""Stages: pure functions on labelled arrays, registered by name.

``@stage("name")`` only *marks* a function (no global state changes at import). A
:class:`StageRegistry` is an object built from modules, normally those named by the ``selpath.stages``
entry-point group, where built-in stages and third-party plugins register alike (xarray's backend
registry is the model). A stage's signature defines its workflow interface:

* parameters before ``*`` (conventionally positional, e.g. ``capture, /``) are **data inputs**:
  labelled arrays wired in a workflow with ``$step`` or ``$step.variable``;
* keyword-only parameters are **settings**, typed, with defaults; the registry builds a strict
  pydantic model from them, so a workflow with a wrong name, type or value fails before anything runs.

A stage names the cube kind(s) its result is (``kind=``, :class:`~selpath.pipeline.kinds.CubeKind`): the registry
holds those kinds too, by name, so that the engine stores a plugin's result, and opens its store, like a built-in's.
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

from selpath.pipeline import manifest
from selpath.pipeline.errors import Problem, SelpathError, StoreError
from selpath.pipeline.kinds import CubeKind

ENTRY_POINT_GROUP = manifest.GROUP
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
    #: the cube kinds the stage's result may be (its ``selpath_kind`` attr says which); with one, a result without
    #: that attr is taken to be of it. Empty: any kind, named by the result (``load_store``, ``import_capture``)
    kinds: tuple[CubeKind, ...] = ()

    @property
    def returns(self) -> str:
        """The description in the docstring's numpydoc ``Returns`` section, on one line ("" where it has none)."""
        doc = inspect.cleandoc(self.func.__doc__ or "")
        found = re.search(r"^Returns\n-{3,}\n[^\n]*\n((?:[ \t]+\S[^\n]*\n?)+)", doc, re.M)
        return " ".join(line.strip() for line in found.group(1).splitlines()) if found else ""

    @property
    def source(self) -> str:
        return f"{self.func.__module__}:{self.func.__qualname__}"

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.func(*args, **kwargs)


ROLE = re.compile(r":(?:func|class|mod|data|meth|attr|obj|exc):`~?([^`]+)`")


def plain_text(doc: str) -> str:
    """Docstring text for people: reST roles (``:func:`x```) and literals (````x````) as plain ``x``."""
    return ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1] if m.group(0).count("~") else m.group(1),
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
                 writes: Callable | None = None, variables: Callable | None = None,
                 kind: CubeKind | Iterable[CubeKind] | None = None) -> Stage:
    if not _NAME.match(name):
        raise SelpathError(f"stage name {name!r} must be lower_snake_case")
    kinds = () if kind is None else (kind,) if isinstance(kind, CubeKind) else tuple(kind)
    if not all(isinstance(k, CubeKind) for k in kinds):
        raise SelpathError(f"stage {name!r} ({func.__module__}:{func.__qualname__}): kind= takes CubeKind "
                           f"declarations (selpath.CubeKind), not {kind!r}")
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
                 variables, kinds)


def stage(name: str, *, kind: CubeKind | Iterable[CubeKind] | None = None,
          precheck: Callable[[Any], list[str]] | None = None,
          identity: Callable[[Any], Any] | None = None, writes: Callable[[Any], str] | None = None,
          variables: Callable[[Any], Iterable[str] | None] | None = None) -> Callable:
    """Mark ``func`` as the stage ``name``; the function itself is returned unchanged.

    ``kind`` is the cube kind of the stage's result (:class:`~selpath.pipeline.kinds.CubeKind`), or the kinds it
    may be (the result's ``selpath_kind`` attr says which): registered with the stage, so a workflow stores the
    result checked against it and stamped with its units and long names, and ``open_store`` opens the store.

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
        setattr(func, _MARK, _build_stage(name, func, precheck, identity, writes, variables, kind))
        return func

    return mark


class StageRegistry:
    """Stages by name, and the cube kinds they make. Duplicate names are refused, naming both sources."""

    def __init__(self, stages: Iterable[Stage] = ()):
        self._stages: dict[str, Stage] = {}
        self._kinds: dict[str, tuple[CubeKind, str]] = {}
        #: plugins left out because they failed to import (``from_entry_points(skip_broken=True)``): name → why
        self.broken: dict[str, str] = {}
        for s in stages:
            self.add(s)

    def add(self, new: Stage) -> None:
        old = self._stages.get(new.name)
        if old is not None and old.func is not new.func:
            raise SelpathError(f"stage {new.name!r} is registered twice: by {old.source} and by {new.source}; "
                               "rename one of them")
        for kind in new.kinds:
            known, source = self._kinds.get(kind.name, (None, ""))
            if known is not None and known != kind:
                raise SelpathError(f"cube kind {kind.name!r} is declared twice, differently: by {source} and by "
                                   f"{new.source}; rename one of them, or import one declaration in both")
            self._kinds.setdefault(kind.name, (kind, new.source))
        self._stages[new.name] = new

    @property
    def kinds(self) -> dict[str, CubeKind]:
        """Every registered cube kind by name, sorted."""
        return {name: self._kinds[name][0] for name in sorted(self._kinds)}

    def kind(self, kind: str | CubeKind) -> CubeKind:
        """The registered kind ``kind`` names (a :class:`CubeKind` is returned as it is); a StoreError for a name no
        installed stage package declares."""
        if isinstance(kind, CubeKind):
            return kind
        if kind not in self._kinds:
            raise StoreError(Problem(f"unknown cube kind {kind!r}: no installed stage package declares it",
                                     fix=f"install the package whose stage makes it (`selpath kinds` lists the "
                                     f"installed kinds: {', '.join(sorted(self._kinds)) or 'none'})"))
        return self._kinds[kind][0]

    def makers(self, kind: str) -> list[str]:
        """The names of the stages whose result may be of ``kind``."""
        return [s.name for s in self if any(k.name == kind for k in s.kinds)]

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
    def from_entry_points(cls, group: str = ENTRY_POINT_GROUP, *, skip_broken: bool = False) -> StageRegistry:
        """The stages (and their kinds) of every module the entry-point ``group`` names. A module that fails to import
        is a SelpathError naming it, or with ``skip_broken`` left out and named in :attr:`broken`."""
        modules, broken = [], {}
        for ep in sorted(entry_points(group=group), key=lambda e: e.name):
            try:
                modules.append(ep.load())
            except Exception as exc:  # a broken plugin must say which one it is
                message = f"stage plugin {ep.name!r} ({ep.value}) failed to import: {type(exc).__name__}: {exc}"
                if not skip_broken:
                    raise SelpathError(message) from exc
                broken[ep.name] = message
        registry = cls.from_modules(modules)
        registry.broken = broken
        return registry

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
    """The stages installed in this environment (entry-point group ``selpath.stages``) and their kinds, cached; the
    installation's manifest of where each is declared is kept for :func:`registry_for`."""
    stamp = manifest.key(ENTRY_POINT_GROUP)  # before importing: a module edited meanwhile gets another key
    registry = StageRegistry.from_entry_points()
    manifest.write(ENTRY_POINT_GROUP, index(registry), stamp)
    return registry


def index(registry: StageRegistry) -> dict[str, dict[str, dict]]:
    """What a manifest keeps of ``registry`` (:func:`selpath.pipeline.manifest.read`): each stage's module, plain-text
    summary and kinds; each kind's module (where it was declared) and description."""
    return {"stages": {s.name: {"module": s.func.__module__, "summary": plain_text(s.summary),
                                "kinds": [k.name for k in s.kinds]} for s in registry},
            "kinds": {name: {"module": kind.module or source.split(":")[0], "description": kind.description}
                      for name, (kind, source) in registry._kinds.items()}}


def registry_for(names: Iterable[str]) -> StageRegistry:
    """A registry that holds the installed stages ``names`` (and every kind their modules declare), importing only
    the modules that declare them where the installation's manifest (:mod:`selpath.pipeline.manifest`) says which;
    else, or where a name is unknown to the manifest or its module, every installed stage (:func:`default_registry`,
    which also names the unknown ones' nearest matches)."""
    names = set(names)
    known = manifest.read(ENTRY_POINT_GROUP)
    if known is None or not names <= known["stages"].keys():
        return default_registry()
    modules = sorted({known["stages"][n]["module"] for n in names})
    if any(m.split(".")[0] not in _entry_point_packages() for m in modules):  # only what an entry point installs
        return default_registry()
    try:
        registry = StageRegistry.from_modules(modules)
    except Exception:  # noqa: BLE001 - a module that fails: the full registry names it and why
        return default_registry()
    return registry if all(n in registry for n in names) else default_registry()


def installed_kind_names(asked: Iterable[str] = ()) -> set[str]:
    """The names of every installed cube kind: from the installation's manifest where it has one and it names every
    kind ``asked`` (no stage module imported), else from :func:`default_registry` (a manifest that lies costs time,
    never a wrong "unknown kind")."""
    known = manifest.read(ENTRY_POINT_GROUP)
    if known is not None and set(asked) <= known["kinds"].keys():
        return set(known["kinds"])
    return set(default_registry().kinds)


def resolve_kind(kind: str | CubeKind, registry: StageRegistry | None = None, *, module: str | None = None) -> CubeKind:
    """``kind`` itself, or the kind it names: in ``registry`` if that declares it (a workflow's own, a test's), else
    in ``module`` (a store's ``selpath_kind_module``: imported alone, and only if an installed ``selpath.stages``
    entry point names it), else among every installed one (:func:`default_registry`; plugins that fail to import are
    then passed over, and named if the kind is found nowhere). A StoreError names an unknown kind."""
    if isinstance(kind, CubeKind):
        return kind
    if registry is not None and kind in registry.kinds:
        return registry.kind(kind)
    if module and kind in _kinds_of(module):
        return _kinds_of(module)[kind]
    try:
        return default_registry().kind(kind)
    except StoreError:
        raise
    except SelpathError:  # a plugin failed to import: the others still declare their kinds
        lenient = _lenient_registry()
        if kind in lenient.kinds:
            return lenient.kind(kind)
        raise StoreError(Problem(f"unknown cube kind {kind!r}: no installed stage package that imports declares it",
                                 fix="mend the plugins that failed to import: " + "; ".join(lenient.broken.values())
                                 )) from None


@functools.cache
def _entry_point_packages(group: str = ENTRY_POINT_GROUP) -> frozenset[str]:
    """The top-level packages of the modules the installed entry points name (``selpath``, a plugin's)."""
    return frozenset(ep.value.split(":")[0].split(".")[0] for ep in entry_points(group=group))


@functools.cache
def _kinds_of(module: str) -> dict[str, CubeKind]:
    """The kinds declared in ``module`` (module constants made there), where it lies in a package an installed entry
    point names (no other module is ever imported from what a store says); empty where it does not, or where it
    fails to import."""
    if module.split(".")[0] not in _entry_point_packages():
        return {}
    try:
        found = vars(importlib.import_module(module)).values()
    except Exception:  # noqa: BLE001 - a broken module: the full registry says why
        return {}
    return {k.name: k for k in found if isinstance(k, CubeKind) and k.module == module}


@functools.cache
def _lenient_registry() -> StageRegistry:
    return StageRegistry.from_entry_points(skip_broken=True)
