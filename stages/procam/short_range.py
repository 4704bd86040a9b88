"""Short-range acquisition (thesis §5.4.4, Fig. 45): what a sweep limited to |t_d| ≤ T_dmax sees.

A delay t_d with exposure t_e admits light from projector rows lit (for a line time t_p) while the camera row
exposes: offsets o with |o·τ − t_d| < (t_e + t_p)/2 (τ = 1/v_p); a sweep limited to |t_d| ≤ T_dmax therefore records
the transport within |o| < v_p·(T_dmax + (t_e + t_p)/2), and a floodlit render from it holds only the light that
travelled that far between epipolar planes. Shorter ranges
need fewer captures: 2·⌊T_dmax / step⌋ + 1 delays per line, against pixel-to-pixel scanning's one capture per
block of rows the scan crosses in one step (:func:`selpath.devices.procam_acquire.plan_sweep`).

From any recovered transport (plane-to-ray ``T(offset, row, col)`` or full ``T(du, dv, row, col)``) the stage
renders the floodlit image each T_dmax would give, the share of the transport's energy it keeps, and the captures
it costs: the transport of a full-range sweep restricted to the short range is what the short sweep recovers
(the offsets outside it are not observed by any of its frames).
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
import pydantic
import xarray as xr

from selpath.devices.procam_acquire import plan_sweep
from selpath.pipeline.constraints import Count, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import TIME_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables

SHORT_RANGE = CubeKind(
    name="short_range",
    description="floodlit images of delay-limited sweeps |t_d| ≤ T_dmax, their energy and captures (§5.4.4)",
    variables={
        "image": Variable(("max_delay", "row", "col"), units="counts",
                          long_name="floodlit image of the short-range sweep"),
        "energy_fraction": Variable(("max_delay",), units="1",
                                    long_name="share of the transport's energy within the range"),
        "reach_rows": Variable(("max_delay",), False, units="px",
                               long_name="offsets kept: |o| < v_p·(T_dmax + (t_e + t_p)/2)"),
        "captures": Variable(("max_delay",), False, units="1", long_name="captures of the short-range sweep"),
        "pixel_to_pixel_captures": Variable(("max_delay",), False, units="1",
                                            long_name="captures of pixel-to-pixel scanning"),
        "censored": Variable(("row", "col"), False, units=None,
                             long_name="light seen only clipped: the images are lower bounds there"),
    },
    coord_units={"max_delay": TIME_UNITS},
)


@stage("short_range_images", kind=SHORT_RANGE)
def short_range_images(transport: xr.Dataset, /, *,
                       max_delays: Annotated[tuple[NonNegative, ...], pydantic.Field(min_length=1)] = (
                           0.0, 850.0, 1700.0, 2550.0),
                       delay_step: Positive = 170.0, exposure: Positive = 170.0,
                       lines: Count | None = None) -> xr.Dataset:
    """Floodlit images of short-range sweeps |t_d| ≤ T_dmax, their energy and capture counts (§5.4.4, Fig. 45).

    Parameters
    ----------
    transport : xr.Dataset
        A ``plane_to_ray_transport`` (``demux_plane_to_ray``) or ``full_transport`` (``demux_full``) store, with
        attr ``scan_speed_px_per_us`` (v_p, camera rows per µs).
    max_delays : tuple of float
        The ranges T_dmax to render [µs]; 0 keeps the direct cell only (the epipolar image).
    delay_step : float
        The sweep's delay step [µs], for the capture counts (the thesis: t_e = 170 µs).
    exposure : float
        The sweep's exposure t_e [µs]: a frame at t_d sees offsets o with |o/v_p − t_d| < (t_e + t_p)/2 (t_p the
        transport's ``line_time_us``), so T_dmax = 0 (one frame at t_d = 0) keeps |o| < v_p·(t_e + t_p)/2.
    lines : int or None
        Line positions of the sweep, for the capture counts [1]; None: 1 for a plane-to-ray transport, the
        transport's ``lines`` attr for a full one (else give it).

    Returns
    -------
    xr.Dataset
        A ``short_range`` cube: the floodlit short-range ``image`` [counts] over (max_delay, row, col), each sweep's
        ``energy_fraction`` and its capture counts.

    References
    ----------
    Thesis §5.4.4 Efficient Acquisition of Short Range Transport.
    """
    require_variables(transport, ("transport",), "short_range_images")
    t = transport["transport"]
    offset = "offset" if "offset" in t.dims else "dv" if "dv" in t.dims else None
    speed = transport.attrs.get("scan_speed_px_per_us")
    if offset is None or not speed:
        raise StageError(Problem(f"a transport over (offset | du, dv, row, col) with attr scan_speed_px_per_us is "
                                 f"needed; this one has dims {t.dims} and v_p {speed!r}",
                                 fix="wire in the output of demux_plane_to_ray or demux_full"))
    summed = [d for d in t.dims if d in ("offset", "du", "dv")]
    line_time = float(transport.attrs.get("line_time_us", 0.0))
    reach = xr.DataArray([float(speed) * (d + (exposure + line_time) / 2) for d in max_delays], dims="max_delay")
    rows_from_plane = abs(t[offset])
    images = xr.concat([t.where(rows_from_plane < r, 0.0).sum(summed) for r in reach.values], dim="max_delay")
    total = t.sum()
    energy = images.sum(("row", "col")) / total
    if lines is None:
        lines = 1 if offset == "offset" else transport.attrs.get("lines")
    if lines is None:
        raise StageError(Problem("a full transport does not record how many line positions its sweep had",
                                 fix="give lines: the sweep's line count (its `line` dim's size)"))
    plan = [plan_sweep(np.arange(-math.floor(d / delay_step), math.floor(d / delay_step) + 1) * delay_step,
                       [delay_step], None if lines == 1 else np.arange(lines),
                       row_block=max(float(speed) * delay_step, 1.0), row_span=t.sizes["row"]) for d in max_delays]
    coords = {"max_delay": ("max_delay", np.asarray(max_delays, float),
                            {"units": "us", "long_name": "delay range T_dmax of the sweep"})}
    censored = ({"censored": transport["censored"].drop_attrs(deep=False)} if "censored" in transport.data_vars else {})
    return SHORT_RANGE.label(xr.Dataset(
        {"image": images.drop_attrs(deep=False), "energy_fraction": energy.drop_attrs(deep=False),
         "reach_rows": reach.drop_attrs(deep=False), "captures": ("max_delay", [p.captures for p in plan]),
         "pixel_to_pixel_captures": ("max_delay", [p.pixel_to_pixel for p in plan]), **censored},
        coords=coords,
        attrs={k: v for k, v in transport.attrs.items() if k != "selpath_kind"}
        | {"delay_step_us": float(delay_step), "exposure_us": float(exposure), "lines": lines}))
