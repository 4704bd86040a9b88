"""A material atlas from full transport (thesis §5.4.10, Fig. 53): each material's 2-D transport profile and extent.

At a camera pixel the full transport T(du, dv) says how much light arrives from the projector pixel du columns and
dv rows away from the pixel's direct correspondence: a diffuse (Lambertian) surface gives a compact peak at the
origin, subsurface scattering a wider one (the more translucent, the wider), inter-reflection an extent towards the
surface it comes from. The atlas crops each named pixel's T to a (2·reach + 1)² window (the thesis: 41 × 41, about
10 × 10 mm at its rig), scales it to its own maximum (the thesis's "normalised by its maximum after white balance":
this rig is monochrome, so there is no balance to make) and measures its **extent**, the RMS distance of its light
from the direct correspondence, √(Σ (du² + dv²)·T / Σ T) [px], over the window's cells that hold at least ``floor``
of the profile's maximum (the rest is the recovery's noise, which the r² weight would make dominate a narrow
profile: measured on the shipped atlas, a Lambertian pixel's extent is 2.3 px with no floor and 0.7 px with 2 %).
The extent of every pixel is mapped too.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import xarray as xr

from selpath.pipeline.constraints import Fraction
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import PX_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import Pixels, pixel_at, require_variables


def extent(profile: xr.DataArray, floor: float) -> xr.DataArray:
    """√(Σ (du² + dv²)·T / Σ T) over (du, dv) [px], over the cells holding at least ``floor`` of the maximum (cells
    never lit, NaN, left out)."""
    light = profile.fillna(0.0)
    light = light.where(light >= floor * light.max(("du", "dv")), 0.0)
    radius2 = profile["du"] ** 2 + profile["dv"] ** 2
    return np.sqrt((light * radius2).sum(("du", "dv")) / light.sum(("du", "dv")).where(lambda s: s > 0))


_EXTENT = "RMS distance from the direct correspondence"
MATERIAL_ATLAS = CubeKind(
    name="material_atlas",
    description="2-D transport profiles of named pixels scaled to their maximum, and extents (§5.4.10)",
    variables={"profile": Variable(("site", "du", "dv"), units="1", long_name="T / its maximum"),
               "extent": Variable(("site",), units="px", long_name=_EXTENT),
               "extent_map": Variable(("row", "col"), False, units="px", long_name=_EXTENT),
               "image": Variable(("row", "col"), units="counts", long_name="white image Σ T")},
    coord_units={"du": PX_UNITS, "dv": PX_UNITS},
    attrs={"reach_px": "half-width of the profiles' window, px"},
)


@stage("material_atlas", kind=MATERIAL_ATLAS)
def material_atlas(transport: xr.Dataset, /, *, pixels: Pixels,
                   reach: Annotated[int, pydantic.Field(ge=1, le=500)] = 20, floor: Fraction = 0.02) -> xr.Dataset:
    """2-D transport profiles of named pixels, each scaled to its maximum, with their extents (§5.4.10, Fig. 53).

    Parameters
    ----------
    transport : xr.Dataset
        A ``full_transport`` store (``demux_full``): ``transport`` over (du, dv, row, col) [counts] with attr
        ``cell_width_px``; du in projector columns from the direct correspondence, dv in rows.
    pixels : dict
        name → [x, y] in image fractions (the scene files' units), each in [0, 1]; at least one pixel.
    reach : int
        Half-width of the window [px]: the thesis's 41 × 41 profiles are reach 20.
    floor : float
        Cells below this share of a profile's maximum are left out of its extent [1] (0: every cell).

    Returns
    -------
    xr.Dataset
        A ``material_atlas`` cube: ``profile`` over (site, du, dv) [1], ``extent`` over site and ``extent_map`` over
        (row, col) [px: RMS distance of the light from the direct correspondence], and the white image ``image`` (Σ T)
        [counts].

    Raises
    ------
    StageError
        A transport whose du or dv range does not reach ``reach``, cells wider than 1 px along du or dv (the window
        would not be in pixels).

    References
    ----------
    Thesis §5.4.10 Acquired materials.
    """
    require_variables(transport, ("transport",), "material_atlas")
    t = transport["transport"]
    if not {"du", "dv"} <= set(t.dims):
        raise StageError(Problem(f"this transport has dims {t.dims}, not full transport (du, dv, row, col)",
                                 where="transport", fix="wire in the output of demux_full"))
    cell = float(transport.attrs.get("cell_width_px", 1.0))
    problems = []
    if cell != 1.0:
        problems.append(Problem(f"the transport's u-cells are {cell:g} px wide; the atlas's window is in pixels",
                                fix="sweep lines every projector column (the thesis's 1-px steps), or "
                                    "demux_full with cell_width_px: 1"))
    if np.any(np.diff(t["dv"].values) != 1):
        problems.append(Problem("the transport's dv grid is not every row; the atlas's window is in pixels",
                                fix="demux_full with an offsets step of 1"))
    for dim in ("du", "dv"):
        values = t[dim].values
        if values.min() > -reach or values.max() < reach:
            problems.append(Problem(f"{dim} spans {values.min():g} … {values.max():g}; the window needs ±{reach}",
                                    fix=f"lower reach, or sweep {'wider delays' if dim == 'dv' else 'du_reach_px'}"))
    if problems:
        raise StageError(problems)
    window = t.sel(du=slice(-reach, reach), dv=slice(-reach, reach))
    at = {name: pixel_at(transport, where) for name, where in pixels.items()}
    rows, cols = (xr.DataArray([rc[k] for rc in at.values()], dims="site") for k in (0, 1))
    sites = window.isel(row=rows, col=cols, drop=True).transpose("site", "du", "dv")  # one vectorised read
    extent_map = extent(window, floor)
    peak = sites.max(("du", "dv"))
    profile = sites / peak.where(peak > 0)
    return MATERIAL_ATLAS.label(xr.Dataset(
        {"profile": profile.drop_attrs(deep=False),
         "extent": extent_map.isel(row=rows, col=cols, drop=True),  # the map's own numbers at the sites
         "extent_map": extent_map, "image": t.sum(("du", "dv"), skipna=True).drop_attrs(deep=False)},
        coords={"site": ("site", list(at)), "site_row": rows, "site_col": cols},
        attrs={k: v for k, v in transport.attrs.items() if k not in ("selpath_kind", "simulated_scene")}
        | {"reach_px": reach, "extent_floor": floor}))
