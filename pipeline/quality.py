"""Degenerate data must not give confident zeros: each stage states what share of its input was usable.

A stage puts the share in its result as a 0-d data variable made by :func:`usable_share` (lazy, like the
rest of the result), with the floor below which its output means nothing, the cause and the setting to
change in the variable's attrs. The share stays in the stage's store, where anyone can read it
(``xr.open_zarr(path).usable_fraction``).

The engine computes these shares in the same pass that writes an output, for the output's own step and
every step upstream of it that was not read back from a store, and refuses to move the output into place
when one is below its floor: a :class:`~selpath.pipeline.errors.StageError` names the step, the share, the floor,
the cause and the fix. In a notebook, :func:`enforce` does the same on any result.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import dask
import numpy as np
import xarray as xr

from selpath.pipeline.errors import Problem, StageError

FLOOR = "selpath_floor"
WHAT = "selpath_usable"
FIX = "selpath_fix"
LABEL = "selpath_label"
ADVISE = "selpath_advise_below"


def usable_share(share: xr.DataArray | float, *, floor: float, what: str, fix: str, label: str = "usable",
                 advise_below: float | None = None) -> xr.DataArray:
    """A 0-d variable holding the usable share of a stage's input (lazy if ``share`` is), checked against
    ``floor``: ``what`` names the input in words ("lit reference pixels whose target is usable"), ``fix``
    the setting to change or the data to look at. ``label`` heads the engine's log line; with ``advise_below``
    the engine logs ``fix`` as advice whenever the share is below it (a report above its floor, e.g. the share of
    pixels not censored, whose floor is 0)."""
    share = share if isinstance(share, xr.DataArray) else xr.DataArray(float(share))
    extra = {LABEL: label} | ({ADVISE: float(advise_below)} if advise_below is not None else {})
    return share.astype(np.float64).drop_attrs(deep=False).assign_attrs({
        "long_name": f"share of {what}", "units": "1", FLOOR: float(floor), WHAT: what, FIX: fix} | extra)


def shares(result: xr.Dataset | xr.DataArray) -> dict[str, xr.DataArray]:
    """The usable-share variables of a stage's result (none for a DataArray)."""
    if not isinstance(result, xr.Dataset):
        return {}
    return {str(n): v for n, v in result.data_vars.items() if v.ndim == 0 and FLOOR in v.attrs}


def below_floor(step: str, values: Mapping[str, float], attrs: Mapping[str, Mapping]) -> list[Problem]:
    """Problems for the shares of ``step`` below their floors (NaN, an empty input, counts as 0)."""
    problems = []
    for name, value in values.items():
        meta = attrs[name]
        share = 0.0 if value is None or not math.isfinite(value) else float(value)
        if share < meta[FLOOR]:
            problems.append(Problem(f"only {share:.2%} of {meta[WHAT]} (floor {meta[FLOOR]:.2%}): its output would "
                                    "mean nothing", path=f"step {step!r} {name}", fix=meta[FIX]))
    return problems


def enforce(result: xr.Dataset, step: str = "result") -> dict[str, float]:
    """Compute the usable shares of ``result`` and raise StageError if any is below its floor; returns them."""
    found = shares(result)
    values = dict(zip(found, (float(v) for v in dask.compute(*[v.data for v in found.values()])), strict=True))
    problems = below_floor(step, values, {n: v.attrs for n, v in found.items()})
    if problems:
        raise StageError(problems)
    return values


def valid_shares(ds: xr.Dataset) -> dict[str, dict[str, float] | float | None]:
    """What share of each data variable holds a value, for people (``selpath inspect``), in one pass.

    A floating variable: the share of finite values (flagged pixels hold NaN). A CF flags variable (attrs
    ``flag_masks``, ``flag_meanings``): the share of values 0 (valid) under ``"valid"`` and the share with each
    flag bit set under its meaning. A boolean variable: the share true. Other variables (counts, images): None.
    """
    lazy: dict[str, dict[str, xr.DataArray] | xr.DataArray] = {}
    for name, array in ds.data_vars.items():
        masks, meanings = array.attrs.get("flag_masks"), array.attrs.get("flag_meanings")
        if masks is not None and meanings is not None and np.issubdtype(array.dtype, np.integer):
            bits = dict(zip(str(meanings).split(), np.atleast_1d(masks).tolist(), strict=False))
            lazy[str(name)] = {"valid": (array == 0).mean()} | {m: ((array & int(b)) != 0).mean()
                                                                 for m, b in bits.items()}
        elif np.issubdtype(array.dtype, np.floating) and array.ndim:
            lazy[str(name)] = np.isfinite(array).mean()
        elif array.dtype == bool and array.ndim:
            lazy[str(name)] = array.mean()
    flat = [(name, key, value) for name, entry in lazy.items()
            for key, value in (entry.items() if isinstance(entry, dict) else [(None, entry)])]
    values = dask.compute(*(value.data for _, _, value in flat))
    out: dict[str, dict[str, float] | float | None] = {str(n): None for n in ds.data_vars}
    for (name, key, _), value in zip(flat, values, strict=True):
        if key is None:
            out[name] = float(value)
        else:
            entry = out[name] if isinstance(out[name], dict) else {}
            out[name] = entry | {key: float(value)}
    return out
