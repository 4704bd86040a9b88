"""Sweep settings ({start, stop, step}) checked when a workflow is validated, before any array is built.

A sweep's values are ``numpy.arange`` of its bounds; :func:`sweep_problem` counts them without building
them, so ``stop: 1e300`` is refused with the count it would have, never a MemoryError at run time.

>>> sweep_problem(0.0, 1e300, 1.0, inclusive=False, what="angles", cap=100_000).split(";")[0]
'the sweep would have 1e+300 angles (start 0, stop 1e+300, step 1)'
>>> sweep_problem(0.0, 360.0, 1.0, inclusive=False, what="angles", cap=100_000) is None
True
"""

from __future__ import annotations

import math
from typing import ClassVar

import pydantic


def sweep_count(start: float, stop: float, step: float, *, inclusive: bool) -> float:
    """How many values ``start, start+step, …`` has: below ``stop`` (exclusive) or up to and including it,
    computed as ``numpy.arange`` does for the sweeps' own ``values()`` (inf where the span overflows)."""
    end = stop + 1e-9 * step if inclusive else stop - 1e-9 * step
    span = (end - start) / step
    if not math.isfinite(span):
        return math.inf
    return float(max(math.ceil(span), 0))


def _count_text(count: float) -> str:
    return f"{int(count):,}" if count < 1e15 else f"{count:.3g}"


def sweep_problem(start: float, stop: float, step: float, *, inclusive: bool, what: str, cap: int) -> str | None:
    """Why the sweep is refused (empty, or more than ``cap`` values of ``what``), or None."""
    bounds = f"start {start:g}, stop {stop:g}, step {step:g}"
    if step <= 0:
        return f"step must be > 0 ({bounds})"
    if stop < start or (stop == start and not inclusive):
        need = "at least" if inclusive else "greater than"
        return f"the sweep is empty: stop must be {need} start ({bounds})"
    count = sweep_count(start, stop, step, inclusive=inclusive)
    if count < 1:
        return f"the sweep is empty ({bounds})"
    if count > cap:
        return (f"the sweep would have {_count_text(count)} {what} ({bounds}); at most {cap:,} are allowed: "
                "take a larger step or a narrower range")
    return None


class Sweep(pydantic.BaseModel):
    """Base of the sweep settings: subclasses declare ``start``, ``stop``, ``step`` and ``values()``; this
    refuses an empty sweep or one of more than ``MAX_VALUES`` values, naming ``LABEL`` and ``WHAT``."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    #: most values a sweep may have
    MAX_VALUES: ClassVar[int] = 100_000
    #: what its values are called ("angles") and what it is called ("angle sweep") in messages
    WHAT: ClassVar[str] = "values"
    LABEL: ClassVar[str] = "sweep"
    #: stop is a value of the sweep (True) or the first value past it (False)
    INCLUSIVE: ClassVar[bool] = True

    @pydantic.model_validator(mode="after")
    def _bounded(self):
        problem = sweep_problem(self.start, self.stop, self.step, inclusive=self.INCLUSIVE, what=self.WHAT,
                                cap=self.MAX_VALUES)
        if problem:
            raise ValueError(f"{self.LABEL}: {problem}")
        return self
