"""Demultiplexing a delay–exposure stack into plane-to-ray transport T(offset, row, col) (§5.2.2).

Lazy over bands of camera rows (dask, one task per band), JAX inside each band
(``selpath.stages.procam._demux_solver``). The
illumination matrix (``selpath.stages.procam._illumination``) is built once from the sweep, v_p, t_p and the sync
offset —
from a ``scan_calibration`` store when one is wired in — and shared by every pixel. Frames at the epipolar
boundary are dropped by the rule of :func:`selpath.stages.procam._illumination.epipolar_boundary`; non-finite
observations
are masked per pixel, and clipped ones (at or above ``saturation_counts``) kept as lower bounds on the light: where
an offset's light was seen only clipped, the pixel is ``censored`` and T there is a lower bound (the solver's
one-sided penalty, :mod:`selpath.stages.procam._demux_solver`). T is in the capture's counts: the image of a row lit for
its whole line time t_p, so Σ_o T(o) w(o; t_d, t_e) reproduces a frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Count, Index, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import PX_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import Dtype, DualSteps, FinishRounds, GapTol, MaxGap, MaxIter
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

if TYPE_CHECKING:
    from selpath.stages.procam._demux_problem import DemuxProblem
    from selpath.stages.procam._demux_solver import DemuxADMM


def _band(block: xr.Dataset, *, solver: DemuxADMM, problem: DemuxProblem, keep: np.ndarray, levels: Levels
          ) -> xr.Dataset:
    image = block["image"].transpose("delay", "exposure", "row", "col").values
    shape = image.shape[-2:]
    frames = image.reshape(-1, shape[0] * shape[1])[keep.ravel()].T  # (P, N kept)
    transport, per_pixel = solve_band(solver, problem, frames, shape, levels)
    return xr.Dataset({"transport": (("offset", "row", "col"),
                                     transport.T.reshape(-1, *shape).astype(solver.dtype)),
                       **per_pixel}, coords={name: block[name] for name in ("row", "col") if name in block.coords})


PLANE_TO_RAY_TRANSPORT = CubeKind(
    name="plane_to_ray_transport",
    description="T(v, s, t) indexed by offset = projector row − camera row",
    variables={"transport": Variable(("offset", "row", "col"), units="counts",
                                     long_name="plane-to-ray transport T(v, s, t)"), **DEMUX_EXTRAS},
    coord_units={"offset": PX_UNITS},
    attrs=TRANSPORT_ATTRS,
)


@stage("demux_plane_to_ray", kind=PLANE_TO_RAY_TRANSPORT)
def demux_plane_to_ray(capture: xr.Dataset, scan_calibration: xr.Dataset | None = None, /, *,
                       offsets: OffsetGrid | None = None, alpha: NonNegative = defaults.DEFAULT_ALPHA,
                       beta: NonNegative = defaults.DEFAULT_BETA, tol: Positive = defaults.TOL,
                       gap_tol: GapTol = defaults.GAP_TOL, max_gap: MaxGap | None = None,
                       finish_rounds: FinishRounds = defaults.FINISH_ROUNDS,
                       dual_steps: DualSteps = defaults.DUAL_STEPS,
                       max_iter: MaxIter = defaults.MAX_ITER,
                       polish_iter: Index = defaults.POLISH_ITER,
                       polish_rounds: Count = defaults.POLISH_ROUNDS,
                       boundary_margin_us: NonNegative | None = None, sync_offset_us: float | None = None,
                       full_scale: Positive | None = None, rows_per_tile: Count = 32,
                       dtype: Dtype = "float32") -> xr.Dataset:
    """Plane-to-ray transport T(offset, row, col) from a ``(delay, exposure, row, col)`` capture (§5.2.2).

    Per pixel: min Σ_i ‖I_i − L_i ∗ T‖² + α‖∂T/∂v‖² + β‖T‖₁, T ≥ 0, on images scaled to [0, 1] by
    ``full_scale``; T is returned in counts. A frame at or above ``saturation_counts`` is kept as a lower bound
    (the one-sided penalty max(0, s − A_i T)²); a non-finite one is masked. Besides T, per pixel: iterations,
    ``converged``, objective, ``gap_bound`` (a certified upper bound on the relative objective gap
    (f(T) − f*)/f(T), from weak duality: conservative, as tight as T's KKT conditions and ``dual_steps`` make it),
    ``frames_used`` and
    ``frames_clipped``, ``censored`` and ``censored_offsets`` (offsets whose light was seen only clipped: T there
    is a lower bound, and the pixel is not ``converged``) and ``clip_ratio`` (how much dimmer the light must be for
    nothing to clip). ``uncensored_fraction`` (0-d) is the share of pixels not censored, ``certified_fraction`` (0-d)
    the share whose ``gap_bound`` is at most ``gap_tol`` (docs/format.md).

    Parameters
    ----------
    capture : xr.Dataset
        A ``plane_to_ray_capture`` store (``acquire_plane_to_ray``): ``image`` [counts] over (delay, exposure, row,
        col), delay and exposure [µs]; attrs ``scan_speed_px_per_us``, ``line_time_us``, ``saturation_counts`` and
        ``dark_level_counts`` (raw counts: clipped at and above the first, unlit at the second).
    scan_calibration : xr.Dataset or None
        A ``scan_calibration`` store (``calibrate_scan_speed``): its attrs ``scan_speed_px_per_us`` and
        ``sync_offset_us`` replace the capture's v_p and t_o = 0 (sync_offset_us wins); None: the nominal values.
    offsets : {start, stop, step} or None
        Offset grid [rows], stop included, at most 10 000 offsets; None: every offset some frame of the sweep
        lights.
    alpha : float
        Smoothness weight α (thesis: 0.01).
    beta : float
        Sparsity weight β (thesis: 0.01).
    tol : float
        Relative primal and dual residual at which a pixel stops iterating (checked every 5 iterations). The
        default, 2e-3, is the cheapest measured to meet #25's accuracy goals with the polish and the finish
        (docs/demux-settings.md).
    gap_tol : float
        The certificate's target, in [0, 1): a pixel whose certified bound on the relative objective gap
        (``gap_bound``) is at most this is certified, and converged whatever its residuals say: checked at the warm
        start (such a pixel, e.g. one whose light β outweighs so that T = 0 is exactly optimal, takes no iteration)
        and after the polish; the finish aims at it. 0: only exactly optimal pixels. Dimensionless (a share of the
        pixel's own objective), so meaningful on any intensity scale.
    max_gap : float or None
        The largest certified gap a converged pixel may have, in [gap_tol, 1]; None: the larger of 1e-3 and
        ``gap_tol``. Pixels whose bound still exceeds it after the polish get the exact finish
        (``finish_rounds``), and ``converged`` then means exactly a proven gap ≤ ``max_gap``, whatever the
        residuals said (a pixel at ``max_iter`` with such a bound is converged, one above it is not). Set it to
        ``gap_tol`` to finish every pixel above ``gap_tol`` (a certificate to ``gap_tol`` on every pixel, at 2–8×
        the time); 1: no cap and no finish (``converged``: the residual test or ``gap_tol``). Where α = 0 leaves
        2G singular only the first-order bound exists, and neither the cap nor the finish applies.
        Dimensionless, like ``gap_tol``.
    finish_rounds : int
        Exact active-set rounds after the polish (float64 solves on each pixel's free offsets, masked and clipped
        frames included) for the pixels whose bound exceeds ``max_gap``; in [0, 20]; 0: none (then pixels above
        ``max_gap`` are left unconverged). At the defaults it runs on a few per cent of the pixels
        (docs/demux-settings.md); ``tol: 5e-3, polish_rounds: 1, max_gap: 1, dual_steps: 0`` trades the proof for
        throughput.
    dual_steps : int
        Steps of the certificate's dual ascent (projected accelerated gradient on the KKT bound's multipliers, one
        K × K product per pixel each), in [0, 1000]; 0: the fixed multipliers alone. It tightens ``gap_bound``,
        not ADMM's T (a tighter bound leaves fewer pixels to the finish); measured in docs/demux-settings.md.
    max_iter : int
        Iteration cap, in [1, 1 000 000]; a pixel that reaches it is flagged unconverged unless its certified bound
        is within ``max_gap`` (or, with ``max_gap`` 1, ``gap_tol``). A solver call streams its
        pixels through a batch refilled as they converge, so the cap bounds only the slow ones.
    polish_iter : int
        Conjugate-gradient steps of the final support polish (0: none); it costs about as many products as
        iterations and is kept per pixel only where it lowers the objective.
    polish_rounds : int
        Rounds of that polish, each after the first with an active-set step (the offsets held at 0 whose gradient
        is negative are freed); ≥ 1 (docs/demux-settings.md).
    boundary_margin_us : float or None
        Drop frames whose exposure edge is within this many µs of the epipolar row; None: t_p/2 (the edge
        cuts the epipolar row's own line time; widen it by the laser jitter of a real rig).
    sync_offset_us : float or None
        Sync offset t_o [µs], signed; None: the scan calibration's when wired in, else 0.
    full_scale : float or None
        Counts that scale the images to [0, 1]; None: the capture's saturation_counts − dark_level_counts.
    rows_per_tile : int
        Camera rows per dask task.
    dtype : str
        ``float32`` or ``float64`` arithmetic.

    Returns
    -------
    xr.Dataset
        A ``plane_to_ray_transport`` cube: ``transport`` T over (offset, row, col) [counts: the image of one projector
        row lit for a line time], lazily per row band, with the solver's ``converged``, ``iterations``, ``gap_bound``,
        ``objective`` and the clipping flags (``censored``, ``frames_clipped``, ``clip_ratio``) per pixel.

    References
    ----------
    Thesis §5.2.2 Light Multiplexing using Delay and Exposure; §5.2.3 Delay-Exposure Image Stacks.
    """
    max_gap = max(gap_tol, defaults.MAX_GAP) if max_gap is None else max_gap
    if gap_tol > max_gap:
        raise StageError(Problem(f"gap_tol = {gap_tol:g} is above max_gap = {max_gap:g}",
                                 fix="gap_tol is the certificate's target and max_gap the largest gap a converged "
                                     "pixel may have: set gap_tol ≤ max_gap"))
    if "line" in capture.dims:
        raise StageError(Problem("this capture has a line dimension (a full-transport sweep)",
                                 fix="use demux_full for (delay, exposure, line, row, col) captures"))
    timing = rig_timing(capture, scan_calibration, sync_offset_us)
    levels = levels_of(capture, full_scale)
    sweep = sweep_illumination(capture, timing, boundary_margin_us, offsets)
    grid = sweep.offsets
    from selpath.stages.procam._demux_problem import DemuxProblem  # JAX: when it solves, not when a workflow is read
    from selpath.stages.procam._demux_solver import DemuxADMM

    problem = DemuxProblem.build(sweep.matrix, alpha=alpha, beta=beta)
    stack = capture[["image"]].chunk({"delay": -1, "exposure": -1, "row": rows_per_tile, "col": -1})
    template = transport_template(capture, ("offset",), (grid.size,), stack.chunksizes["row"], dtype)
    solver = DemuxADMM(tol=tol, gap_tol=gap_tol, max_gap=max_gap, finish_rounds=finish_rounds, dual_steps=dual_steps,
                       max_iter=max_iter, polish_iter=polish_iter, polish_rounds=polish_rounds, dtype=dtype)
    out = xr.map_blocks(_band, stack.assign_attrs({}), kwargs={
        "solver": solver, "problem": problem, "keep": sweep.keep, "levels": levels}, template=template)
    out = out.assign_coords(offset=("offset", grid, {"units": "px", "long_name": "projector row − camera row"}))
    out = with_sync_delay(out, "offset", timing)
    out = describe_transport(out, int(sweep.keep.sum()), PLANE_TO_RAY_TRANSPORT, gap_tol)
    return out.assign_attrs(transport_attrs(capture, timing=timing, sweep=sweep, full_scale=levels.full_scale,
                                            alpha=alpha, beta=beta, **solver.settings()))
