"""Demultiplexing a line sweep into full transport T(du, dv, row, col) (§5.3.1).

The same per-pixel problem as plane-to-ray (:mod:`selpath.stages.procam.demux`, whose machinery it shares through
:mod:`selpath.stages.procam._capture_to_transport`) over u-cells × offsets, with the separable illumination
L_u ⊗ L of Eq. 38 (:class:`selpath.stages.procam._demux_problem.SeparableDemuxProblem`: A is never formed). Lazy
over bands of camera rows; each pixel's answer is re-indexed from its direct correspondence u₀, so du = 0 is the
direct light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Count, Index, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import PX_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import Dtype, GapTol, MaxIter
from selpath.stages.procam import _demux_settings as defaults
from selpath.stages.procam._capture_to_transport import (
    DEMUX_EXTRAS,
    TRANSPORT_ATTRS,
    Levels,
    OffsetGrid,
    describe_transport,
    levels_of,
    rig_timing,
    solve_band,
    sweep_illumination,
    transport_attrs,
    transport_template,
    with_sync_delay,
)
from selpath.stages.procam._illumination import line_cells, line_illumination

if TYPE_CHECKING:
    from selpath.stages.procam._demux_problem import SeparableDemuxProblem
    from selpath.stages.procam._demux_solver import DemuxADMM

#: bytes of full transport one dask task may hold (the default rows_per_tile of demux_full follows from it)
FULL_TILE_BYTES = 64 * 2**20


def _band_full(block: xr.Dataset, *, solver: DemuxADMM, problem: SeparableDemuxProblem, keep: np.ndarray,
               levels: Levels, reach: int, centre_v: int, cells: np.ndarray) -> xr.Dataset:
    image = block["image"].transpose("line", "delay", "exposure", "row", "col").values
    n_lines, rows, cols = image.shape[0], *image.shape[-2:]
    frames = image.reshape(n_lines, -1, rows * cols)[:, keep.ravel()].reshape(-1, rows * cols).T  # line-major
    shape = (rows, cols)
    transport, per_pixel = solve_band(solver, problem, frames, shape, levels)
    k_u, k_v = problem.cells
    absolute = transport.reshape(-1, k_u, k_v)  # (P, u-cell, dv)
    # the direct correspondence u₀: the brightest u-cell on the epipolar row (dv = 0)
    epipolar = absolute[:, :, centre_v]
    peak = np.argmax(epipolar, axis=1)
    lit = epipolar.max(axis=1) > 0
    du = np.arange(-reach, reach + 1)
    index = peak[:, None] + du[None, :]
    inside = (index >= 0) & (index < k_u)
    relative = np.take_along_axis(absolute, np.clip(index, 0, k_u - 1)[:, :, None], axis=1)
    relative = np.where(inside[:, :, None], relative, np.nan)  # columns the sweep never lit: unobserved
    relative[~lit] = np.where(inside[~lit, :, None], 0.0, np.nan)
    return xr.Dataset({
        "transport": (("du", "dv", "row", "col"), relative.transpose(1, 2, 0).reshape(du.size, k_v, *shape)
                      .astype(solver.dtype)),
        "u_direct": (("row", "col"), np.where(lit, cells[peak], np.nan).reshape(shape).astype(np.float32)),
        **per_pixel,
    }, coords={name: block[name] for name in ("row", "col") if name in block.coords})


#: the full transport's residual tolerance: plane-to-ray's pre-#25 default, kept here (see ``tol`` below)
FULL_TOL = 5e-3


FULL_TRANSPORT = CubeKind(
    name="full_transport",
    description="T(u, v, s, t) indexed by offsets from the direct correspondence",
    variables={"transport": Variable(("du", "dv", "row", "col"), units="counts",
                                     long_name="full transport T(u, v, s, t)"),
               "u_direct": Variable(("row", "col"), False, units="px",
                                    long_name="direct correspondence u₀ (centre of the brightest cell)"),
               **DEMUX_EXTRAS},
    coord_units={"du": PX_UNITS, "dv": PX_UNITS},
    attrs={**TRANSPORT_ATTRS,
           "line_width_px": "width l_w of the projected vertical line, projector columns",
           "cell_width_px": "width of a u-cell, projector columns (du steps by it)",
           "cells_px": "centres of the u-cells solved for, projector columns (u₀ is one of them)"},
)


@stage("demux_full", kind=FULL_TRANSPORT)
def demux_full(capture: xr.Dataset, scan_calibration: xr.Dataset | None = None, /, *,
               offsets: OffsetGrid | None = None, cell_width_px: Positive | None = None,
               du_reach_px: NonNegative | None = None, alpha: NonNegative = defaults.DEFAULT_ALPHA,
               beta: NonNegative = defaults.DEFAULT_BETA, tol: Positive = FULL_TOL,
               gap_tol: GapTol = defaults.GAP_TOL, max_iter: MaxIter = defaults.MAX_ITER,
               polish_iter: Index = defaults.POLISH_ITER,
               boundary_margin_us: NonNegative | None = None, sync_offset_us: float | None = None,
               full_scale: Positive | None = None, rows_per_tile: Count | None = None,
               dtype: Dtype = "float32") -> xr.Dataset:
    """Full transport T(du, dv, row, col) from a ``(delay, exposure, line, row, col)`` capture (§5.3.1).

    Per pixel the thesis's problem (Eq. 40 with the α, β and T ≥ 0 of plane-to-ray) over u-cells × offsets,
    with the separable illumination L_u ⊗ L (Eq. 38): the lines' boxes on cells of ``cell_width_px``
    projector columns, and the delay–exposure boxes of Eq. 32–33 on the offset grid. It is solved on
    absolute u-cells, then each pixel is re-indexed from its direct correspondence u₀ (the brightest cell on
    its epipolar row, stored as ``u_direct``), so du = 0 is the direct light. Cells the sweep never lit
    are NaN; pixels with no epipolar light keep du relative to cell 0 and ``u_direct`` NaN.

    Parameters
    ----------
    capture : xr.Dataset
        A ``full_transport_capture`` store (``acquire_full_transport``): ``image`` over (delay, exposure, line [px],
        row, col) [counts]; attrs ``scan_speed_px_per_us``, ``line_time_us``, ``line_width_px``,
        ``saturation_counts``, ``dark_level_counts``.
    scan_calibration : xr.Dataset or None
        A ``scan_calibration`` store (``calibrate_scan_speed``): its attrs ``scan_speed_px_per_us`` and
        ``sync_offset_us`` replace the capture's v_p and t_o = 0 (sync_offset_us wins); None: the nominal values.
    offsets : {start, stop, step} or None
        dv grid [rows], stop included, at most 10 000 offsets; None: every offset some frame of the sweep lights.
    cell_width_px : float or None
        Width of a u-cell [projector columns]; None: the spacing of the lines (the thesis's 20 px).
    du_reach_px : float or None
        Keep |du| up to this [px]; None: every offset the sweep can express (2 K_u − 1 cells).
    alpha, beta : float
        Smoothness along dv and sparsity weights (thesis: 0.01), on images scaled to [0, 1].
    tol : float
        Relative primal and dual residual at which a pixel converges (checked every 5 iterations). The default,
        5e-3, is not plane-to-ray's: this problem has neither the exact finish nor the second-order certificate
        (its Hessian is a Kronecker product, never formed), so ``gap_bound`` is the first-order one (~1e-2 at the
        median) and ``converged`` means the residual test, or a bound ≤ ``gap_tol``; plane-to-ray's tighter
        defaults were measured on dense problems only.
    gap_tol, max_iter, polish_iter, boundary_margin_us, sync_offset_us, full_scale, dtype
        As for ``demux_plane_to_ray``.
    rows_per_tile : int or None
        Camera rows per dask task; None: as many as keep a task's transport within 64 MiB.

    Returns
    -------
    xr.Dataset
        A ``full_transport`` cube: ``transport`` T over (du, dv, row, col) [counts: the image of one u-cell lit for a
        line time], lazily per row band, with the solver's ``converged``, ``iterations``, ``gap_bound`` and the clipping
        flags per pixel.

    References
    ----------
    Thesis §5.3 Acquisition of full light transport; §5.3.1 Illumination multiplexing.
    """
    if "line" not in capture.dims:
        raise StageError(Problem("this capture has no line dimension (a plane-to-ray sweep)",
                                 fix="use demux_plane_to_ray for (delay, exposure, row, col) captures"))
    if "line_width_px" not in capture.attrs:
        raise StageError(Problem("the capture has no attr 'line_width_px'", where="capture",
                                 fix="acquire with acquire_full_transport, or add the attr (docs/format.md)"))
    timing = rig_timing(capture, scan_calibration, sync_offset_us)
    levels = levels_of(capture, full_scale)
    sweep = sweep_illumination(capture, timing, boundary_margin_us, offsets)
    keep, grid = sweep.keep, sweep.offsets
    lines, width = capture["line"].values, float(capture.attrs["line_width_px"])
    if lines.size > 1 and not np.allclose(np.diff(lines), np.diff(lines)[0]) and cell_width_px is None:
        raise StageError(Problem("the line positions are not evenly spaced, so the u-cell width is ambiguous",
                                 fix="set cell_width_px"))
    try:
        cells, step = line_cells(lines, width, cell_width_px)
    except ValueError as error:
        raise StageError(Problem(str(error), where="capture line sweep", fix="set cell_width_px > 0")) from None
    from selpath.stages.procam._demux_problem import SeparableDemuxProblem  # JAX: when it solves, not on reading
    from selpath.stages.procam._demux_solver import DemuxADMM

    problem = SeparableDemuxProblem.build(line_illumination(lines, width, cells, step), sweep.matrix,
                                          alpha=alpha, beta=beta)
    k_u = cells.size
    reach = k_u - 1 if du_reach_px is None else min(int(np.floor(du_reach_px / step)), k_u - 1)
    cols = capture.sizes["col"]
    if rows_per_tile is None:
        per_row = cols * (2 * reach + 1 + k_u) * grid.size * 4
        rows_per_tile = int(np.clip(FULL_TILE_BYTES // max(per_row, 1), 1, 64))
    stack = capture[["image"]].chunk({"delay": -1, "exposure": -1, "line": -1, "row": rows_per_tile, "col": -1})
    template = transport_template(capture, ("du", "dv"), (2 * reach + 1, grid.size), stack.chunksizes["row"], dtype,
                                  u_direct=np.float32)
    # one polish round, as before #25's certified defaults; the Kronecker problem has no second-order bound, so the
    # solver runs neither the KKT bound's ascent, the exact finish nor the max_gap cap on it (its `exact_finish`):
    # max_gap 1 only keeps any gap_tol valid, and the store does not record those three settings
    solver = DemuxADMM(tol=tol, gap_tol=gap_tol, max_iter=max_iter, polish_iter=polish_iter, dtype=dtype,
                       polish_rounds=1, max_gap=1.0)
    out = xr.map_blocks(_band_full, stack.assign_attrs({}), kwargs={
        "solver": solver,
        "problem": problem,
        "keep": keep, "levels": levels, "reach": reach,
        "centre_v": int(np.argmin(np.abs(grid))), "cells": cells}, template=template)
    out = out.assign_coords(
        du=("du", np.arange(-reach, reach + 1) * step, {"units": "px", "long_name": "projector column − u₀"}),
        dv=("dv", grid, {"units": "px", "long_name": "projector row − camera row"}))
    out = with_sync_delay(out, "dv", timing)
    out["transport"].attrs = {"description": f"light from a {step:g}-column u-cell; NaN where no line reached"}
    out = describe_transport(out, int(keep.sum()) * capture.sizes["line"], FULL_TRANSPORT, gap_tol)
    return out.assign_attrs(transport_attrs(
        capture, timing=timing, sweep=sweep, full_scale=levels.full_scale, alpha=alpha, beta=beta,
        **{k: v for k, v in solver.settings().items() if k not in ("max_gap", "finish_rounds", "dual_steps")},
        line_width_px=width, cell_width_px=step, cells_px=cells.tolist(), lines=int(lines.size),
        **{name: capture.attrs[name] for name in ("projector_shape",) if name in capture.attrs}))
