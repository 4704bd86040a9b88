"""Constrained setting types, and the memory check for settings that size arrays.

Stage settings are validated by pydantic before anything runs (:mod:`pipeline.registry`); every float must
be finite (``.nan`` and ``.inf`` are refused for all stages), and the annotations below add ranges. They are
plain ``typing.Annotated`` types, so a plugin uses them the same way::

    @stage("blur")
    def blur(frames: xr.DataArray, /, *, sigma: Positive = 1.0, passes: Count = 1) -> xr.DataArray: ...

``selpath stages NAME`` shows each setting's range (:func:`describe`).
"""

from __future__ import annotations

import os
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


def describe(field: Any) -> str:
    """A setting's type with its range, e.g. ``int ≥ 1`` or ``float in [0, 1]``, for ``selpath stages``."""
    annotation = field.annotation
    text = getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")
    bounds = []
    for item in field.metadata:
        for cls, attr, symbol in _BOUNDS:
            if isinstance(item, cls):
                bounds.append(f"{symbol} {getattr(item, attr):g}")
    return f"{text} {', '.join(bounds)}" if bounds else text
