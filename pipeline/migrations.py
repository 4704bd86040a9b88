"""Migrations of stores written by older selpath versions (``selpath_format``), applied step by step on open.

Each takes a Dataset of format n and the kind the store holds as it is declared today, and returns the Dataset as
format n + 1; :func:`selpath.pipeline.store.open_store` runs them in memory (the store on disk is never rewritten),
so an archive is read, checked and migrated, never guessed.
"""

from __future__ import annotations

from collections.abc import Callable

import xarray as xr

from selpath.pipeline.kinds import CubeKind


def _from_format_1(ds: xr.Dataset, kind: CubeKind) -> xr.Dataset:
    """Format 1 → 2: the cubes are unchanged (only how chunks are encoded differs, which zarr reads per array)."""
    return ds


def _from_format_2(ds: xr.Dataset, kind: CubeKind) -> xr.Dataset:
    """Format 2 → 3: a hull's dim ``row`` becomes ``slice``, with the camera rows as its coordinate."""
    if kind.name != "hull" or "row" not in ds.dims or "slice" in ds.dims:
        return ds
    return ds.rename({"row": "slice"}).assign_coords(slice=("slice", range(ds.sizes["row"])))


def _from_format_3(ds: xr.Dataset, kind: CubeKind) -> xr.Dataset:
    """Format 3 → 4: variables get the units and long names their kind fixes. Formats 1–3 could carry a
    coordinate's attrs on a sinogram's or a coverage's variables, or ``counts`` on flags and hull vertices (a
    labelling bug: the values are the same quantity)."""
    return kind.label(ds)


def _from_format_4(ds: xr.Dataset, kind: CubeKind) -> xr.Dataset:
    """Format 4 → 5: the solvers' extra variables (iterations, converged, objective, residuals, masks) get the
    units and long names their kind now declares; format 4 wrote them bare."""
    return _from_format_3(ds, kind)


#: what a format-5 transport's note says: its pixels may be confident black holes where light clipped
CLIPPED_MASKED_NOTE = ("written before selpath kept clipped frames (format ≤ 5): frames at or above saturation_counts "
                       "were masked, so a pixel whose brightest light was seen only clipped may hold T ≈ 0 there and "
                       "still be flagged converged; demultiplex the capture again to bound and flag that light")


def _from_format_5(ds: xr.Dataset, kind: CubeKind) -> xr.Dataset:
    """Format 5 → 6: the tomography stores' ``saturation_level`` attr is named ``saturation_counts``, as the
    projector–camera stores name it; a transport's ``converged`` and ``frames_used`` get the meaning they had
    (clipped frames were masked; nothing was censored), and the store a ``selpath_note`` saying what that hides."""
    if "saturation_level" in ds.attrs:  # where both are there, saturation_counts wins (as the stages read them)
        attrs = dict(ds.attrs)
        level = attrs.pop("saturation_level")
        ds = ds.drop_attrs(deep=False).assign_attrs({"saturation_counts": level} | attrs)
    if kind.name not in ("plane_to_ray_transport", "full_transport"):
        return ds
    out = ds.assign_attrs(selpath_note=CLIPPED_MASKED_NOTE)
    meanings = {"converged": "the pixel's solve met its tolerance (clipped frames masked: not censoring-aware)",
                "frames_used": "frames used for the pixel (neither saturated nor missing)"}
    for name, long_name in meanings.items():
        if name in out.data_vars:
            out[name] = out[name].copy(deep=False).assign_attrs(long_name=long_name)
    return out


#: Migrations from older formats: ``{old_version: function(Dataset) -> Dataset of old_version + 1}``.
#: Archives are migrated step by step on open, never guessed.
MIGRATIONS: dict[int, Callable[[xr.Dataset, CubeKind], xr.Dataset]] = {1: _from_format_1, 2: _from_format_2,
                                                                3: _from_format_3, 4: _from_format_4,
                                                                5: _from_format_5}
