"""What the stages of both instruments share: required variables, sorted sweeps and the solver settings' types.

Kept small on purpose: a helper lands here only when both ``selpath.stages.tomography`` and ``selpath.stages.procam``
use it.
"""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pydantic
import xarray as xr

from selpath.pipeline.constraints import Fraction
from selpath.pipeline.errors import Problem, SelpathError, StageError

#: the float precision of a solver's arithmetic (a stage setting)
Dtype = Literal["float32", "float64"]

#: an iteration cap: at least 1, at most a million (solvers keep per-iteration histories and int32 counters)
MaxIter = Annotated[int, pydantic.Field(ge=1, le=1_000_000)]

#: a tolerance on a certified relative objective gap: a share of the objective, in [0, 1)
GapTol = Annotated[float, pydantic.Field(ge=0, lt=1)]

#: the largest certified relative objective gap a converged answer may have: a share of the objective, in [0, 1]
#: (1: no cap)
MaxGap = Annotated[float, pydantic.Field(ge=0, le=1)]

#: rounds of an exact active-set finish: 0 (none) to 20 (it converges in a few or cycles)
FinishRounds = Annotated[int, pydantic.Field(ge=0, le=20)]

#: steps of a certificate's dual ascent: 0 (none) to 1000 (each costs about an iteration; past ~100 the bound is
#: within 1e-4 of its limit on the solver tests' sweeps)
DualSteps = Annotated[int, pydantic.Field(ge=0, le=1000)]


def sweep_log(progress: bool):
    """Where an acquisition's messages (its plan, resuming, frames captured) go: the terminal, under the step's
    heading, when it shows progress; nowhere otherwise."""
    if not progress:
        return lambda _: None
    from rich.console import Console
    from rich.markup import escape

    console = Console()
    return lambda message: console.print(escape(message), highlight=False)


def file_identity(path) -> dict:
    """A file a stage reads (a scene, rig or label file) by its path and content (sha256; None where it is not a
    file), for the stage's ``identity``: provenance changes when the file does."""
    source = Path(path)
    digest = hashlib.sha256(source.read_bytes()).hexdigest() if source.is_file() else None
    return {"file": str(source), "sha256": digest}


def read_file(load, path, what: str) -> tuple[object | None, list[str]]:
    """``load(path)`` and no problems, or None and every problem it raised, each headed ``"{what} file: "`` (a
    stage's precheck reads its scene or rig file at validation time)."""
    try:
        return load(path), []
    except SelpathError as exc:
        return None, [f"{what} file: {p}" for p in getattr(exc, "problems", [exc])]


def require_variables(ds: xr.Dataset, names: tuple[str, ...], stage_name: str) -> None:
    """Refuse ``ds`` unless it has every data variable in ``names`` (one problem per missing variable)."""
    problems = [
        Problem(f"stage {stage_name!r} needs variable {name!r}; the input has {sorted(map(str, ds.data_vars))}",
                path=name)
        for name in names
        if name not in ds.data_vars
    ]
    if problems:
        raise StageError(problems)


class UnsortedSweepWarning(UserWarning):
    """A sweep coordinate (angle, delay, …) was not in increasing order; the stage sorted it."""


def sorted_sweep(ds: xr.Dataset, dim: str, stage_name: str) -> xr.Dataset:
    """``ds`` with its sweep coordinate ``dim`` sorted (warning if it was not); a repeated value is refused."""
    if dim not in ds.coords:
        return ds
    values = np.asarray(ds[dim].values)
    unique, counts = np.unique(values, return_counts=True)
    if (counts > 1).any():
        repeated = unique[counts > 1]
        raise StageError(Problem(f"stage {stage_name!r}: coordinate {dim!r} repeats {repeated[:5].tolist()} "
                                 f"({int((counts - 1).sum())} duplicate frame(s)); each {dim} must be captured once",
                                 path=dim, fix="drop the duplicates (ds.drop_duplicates) or fix the coordinate"))
    if (np.diff(values) < 0).any():
        warnings.warn(f"stage {stage_name!r}: coordinate {dim!r} is not sorted; frames were reordered by {dim}",
                      UnsortedSweepWarning, stacklevel=3)
        ds = ds.sortby(dim)
    return ds


#: named pixels, name → [x, y] in image fractions, each in [0, 1]; at least one
Pixels = Annotated[dict[str, tuple[Fraction, Fraction]], pydantic.Field(min_length=1)]


def pixel_at(ds: xr.Dataset, where: tuple[float, float]) -> tuple[int, int]:
    """The (row, col) of the pixel at image fractions ``where`` = [x, y] of ``ds``'s frame."""
    x, y = where
    if not (0 <= x <= 1 and 0 <= y <= 1):
        raise StageError(Problem(f"pixel {where} is not in image fractions [0, 1]", fix="give [x, y] fractions"))
    return (min(int(y * ds.sizes["row"]), ds.sizes["row"] - 1), min(int(x * ds.sizes["col"]), ds.sizes["col"] - 1))
