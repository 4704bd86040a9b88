"""Setting types (ranges, paths), and the memory check for settings that size arrays.

Stage settings are validated by pydantic before anything runs (:mod:`selpath.pipeline.registry`); every float must
be finite (``.nan`` and ``.inf`` are refused for all stages), and the annotations below add ranges. They are
plain ``typing.Annotated`` types, so a plugin uses them the same way::

    @stage("blur")
    def blur(frames: xr.DataArray, /, *, sigma: Positive = 1.0, passes: Count = 1) -> xr.DataArray: ...

``selpath stages NAME`` shows each setting's range (:func:`describe`).
"""

from __future__ import annotations

import os
import types
import typing
from typing import Annotated, Any

import pydantic
from annotated_types import Ge, Gt, Le, Lt

#: a size or a number of things: at least 1
Count = Annotated[int, pydantic.Field(ge=1)]
#: an index or a count that may be zero
Index = Annotated[int, pydantic.Field(ge=0)]
#: a strictly positive number (a length, a weight that must act, a tolerance)
Positive = Annotated[float, pydantic.Field(gt=0)]
#: zero or more (a weight that may be off, a noise level, a slack)
NonNegative = Annotated[float, pydantic.Field(ge=0)]
#: a share of something, in [0, 1]
Fraction = Annotated[float, pydantic.Field(ge=0, le=1)]


class PathMarker:
    """Annotation metadata: this str setting is a filesystem path (or an fsspec URL), resolved against the workflow
    file's folder when the workflow is validated (:mod:`selpath.pipeline.spec`)."""


#: a setting that names a file or store: relative paths resolve against the workflow file's folder, and no output
#: may be written over it
StorePath = Annotated[str, PathMarker()]

#: share of this machine's memory one array a setting sizes may take before validation refuses it
MEMORY_SHARE = 0.5


def machine_memory() -> int | None:
    """Physical memory of this machine in bytes (None where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def _size(nbytes: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if nbytes < 1024 or unit == "PiB":
            return f"{nbytes:.0f} {unit}" if unit == "bytes" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes:.1f} PiB"


def memory_problems(nbytes: float, what: str, fix: str = "") -> list[str]:
    """A problem (as a string) if one array of ``nbytes`` would not fit in MEMORY_SHARE of this machine's memory.

    >>> memory_problems(1e15, "one frame")[0].split(", more")[0]
    'one frame would take 909.5 TiB'
    """
    total = machine_memory()
    if total is None or nbytes <= MEMORY_SHARE * total:
        return []
    return [f"{what} would take {_size(nbytes)}, more than {MEMORY_SHARE:.0%} of this machine's memory "
            f"({_size(total)})" + (f" (fix: {fix})" if fix else "")]


_BOUNDS = ((Gt, "gt", ">"), (Ge, "ge", "≥"), (Lt, "lt", "<"), (Le, "le", "≤"))


def bounds_text(metadata) -> list[str]:
    """A field's ranges as text (``> 0``, ``≤ 1``), from its annotation's metadata (pydantic's or annotated-types')."""
    items = [m for item in metadata for m in (getattr(item, "metadata", None) or [item])]  # Field(gt=0) holds Gt
    return [f"{symbol} {getattr(item, attr):g}" for item in items for cls, attr, symbol in _BOUNDS
            if isinstance(item, cls)]


def _type_text(annotation: Any) -> str:
    """``int``, ``float > 0``, ``float > 0 | None``, ``tuple[float, ...]``, ``'scene' | 'image'``: a type with its
    ranges, or the values it may take."""
    if typing.get_origin(annotation) is typing.Annotated:
        base, *metadata = typing.get_args(annotation)
        bounds = bounds_text(metadata)
        return f"{_type_text(base)} {', '.join(bounds)}" if bounds else _type_text(base)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return " | ".join("None" if a is type(None) else _type_text(a) for a in typing.get_args(annotation))
    if typing.get_origin(annotation) is typing.Literal:  # the values a setting may take, as a workflow writes them
        return " | ".join(repr(v) if isinstance(v, str) else str(v) for v in typing.get_args(annotation))
    return getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")


def describe(field: Any) -> str:
    """A setting's type with its range, e.g. ``int ≥ 1`` or ``float ≥ 0, ≤ 1``, for ``selpath stages``."""
    text = _type_text(field.annotation)
    bounds = bounds_text(field.metadata)
    return f"{text} {', '.join(bounds)}" if bounds else text
