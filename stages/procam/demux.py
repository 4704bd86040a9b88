"""Demultiplexing a delay–exposure stack into plane-to-ray transport T(offset, row, col) (§5.2.2).

Lazy over bands of camera rows (dask, one task per band), JAX inside each band (``stages.procam._demux_solver``). The
illumination matrix (``stages.procam._illumination``) is built once from the sweep, v_p, t_p and the sync offset —
from a ``scan_calibration`` store when one is wired in — and shared by every pixel. Frames at the epipolar
boundary are dropped by the rule of :func:`stages.procam._illumination.epipolar_boundary`; non-finite observations
are masked per pixel, and clipped ones (at or above ``saturation_counts``) kept as lower bounds on the light: where
an offset's light was seen only clipped, the pixel is ``censored`` and T there is a lower bound (the solver's
one-sided penalty, :mod:`stages.procam._demux_solver`). T is in the capture's counts: the image of a row lit for
its whole line time t_p, so Σ_o T(o) w(o; t_d, t_e) reproduces a frame.
"""

from __future__ import annotations

from dataclasses import replace
from typing import ClassVar

import dask.array as da
import jax
import numpy as np
import pydantic
import xarray as xr

from pipeline.constraints import Count, Index, NonNegative, Positive
from pipeline.errors import Problem, StageError
from pipeline.quality import usable_share
from pipeline.registry import stage
from pipeline.schema import with_metadata
from stages._common import Dtype, FinishRounds, GapTol, MaxIter
from stages._solution import Solution, raise_if_failed
from stages._sweeps import Sweep
from stages.procam._demux_problem import DEFAULT_ALPHA, DEFAULT_BETA, DemuxProblem, SeparableDemuxProblem
from stages.procam._demux_solver import DemuxADMM, batch_slots, observed
from stages.procam._illumination import epipolar_boundary, line_cells, line_illumination, plane_to_ray_illumination

#: streaming batches per solver call: a call's pool (data, warm starts, results: ~8 (P × K) arrays, 64 MB at
#: K = 128) is bounded while the batch's tail (its last, slowest pixels) is paid once per 16 batches of pixels
POOL_BATCHES = 16


def pixels_per_call(pixels: int, offsets: int) -> int:
    """Pixels per solver call: at most POOL_BATCHES streaming batches, the calls of ``pixels`` equal in size
    (a multiple of the batch, so a band's calls share one compiled shape and little is padding)."""
    slots = batch_slots(offsets)
    calls = max(1, -(-pixels // (POOL_BATCHES * slots)))
    return slots * max(1, -(-pixels // (calls * slots)))


class OffsetGrid(Sweep):
    """Offsets o = projector row − camera row: start, start+step, …, up to and including stop [rows]: stop ≥
    start, step > 0, at most :attr:`MAX_VALUES` offsets (every offset of a 5 000-row sensor; the solver's
    K × K float64 matrices then take 800 MB)."""

    MAX_VALUES: ClassVar[int] = 10_000
    WHAT: ClassVar[str] = "offsets"
    LABEL: ClassVar[str] = "offset grid"
    start: int
    stop: int
    step: int = pydantic.Field(1, gt=0)

    def values(self) -> np.ndarray:
        return np.arange(self.start, self.stop + 1, self.step)


def sweep_offsets(delays, exposures, *, scan_speed: float, line_time: float, sync_offset: float) -> np.ndarray:
    """Every integer offset that some frame of the sweep lights (the default offset grid)."""
    delays, exposures = np.asarray(delays, float) + sync_offset, np.asarray(exposures, float)
    low = np.min(delays - exposures / 2) - line_time / 2
    high = np.max(delays + exposures / 2) + line_time / 2
    return np.arange(int(np.floor(low * scan_speed)), int(np.ceil(high * scan_speed)) + 1)


def _rig_timing(capture: xr.Dataset, calibration: xr.Dataset | None, sync_offset: float | None) -> dict:
    attrs = capture.attrs
    for name in ("scan_speed_px_per_us", "line_time_us"):
        if name not in attrs:
            raise StageError(Problem(f"the capture has no attr {name!r}", where="capture",
                                     fix="acquire with selpath's procam stages, or add the attr (docs/format.md)"))
    speed, offset = float(attrs["scan_speed_px_per_us"]), 0.0
    if calibration is not None:  # the calibrated values win over the rig's nominal ones
        speed, offset = float(calibration.attrs["scan_speed_px_per_us"]), float(calibration.attrs["sync_offset_us"])
    if sync_offset is not None:
        offset = sync_offset
    return {"scan_speed": speed, "line_time": float(attrs["line_time_us"]), "sync_offset": offset}


def _levels(capture: xr.Dataset, full_scale: float | None) -> tuple[float, float, float]:
    """(dark level, full scale, saturation level) in counts."""
    dark = float(capture.attrs.get("dark_level_counts", 0.0))
    saturation = float(capture.attrs.get("saturation_counts", np.inf))
    if full_scale is None:
        if not np.isfinite(saturation):
            raise StageError(Problem("the capture records no saturation_counts, so the data's full scale is unknown "
                                     "(α and β apply to images scaled to [0, 1], as in the thesis)",
                                     where="capture", fix="set full_scale: <counts of a saturated pixel>"))
        full_scale = saturation - dark
    if not full_scale > 0:
        raise StageError(Problem(f"full_scale is {full_scale}; it must be positive", fix="set full_scale > 0"))
    return dark, float(full_scale), saturation


def _frames(capture: xr.Dataset, timing: dict, boundary_margin_us: float | None, offsets: OffsetGrid | None):
    """(delays, exposures, kept frames, margin, offset grid, illumination matrix) of a delay–exposure sweep."""
    delays, exposures = np.meshgrid(capture["delay"].values, capture["exposure"].values, indexing="ij")
    margin = timing["line_time"] / 2 if boundary_margin_us is None else boundary_margin_us
    keep = ~epipolar_boundary(delays, exposures, sync_offset=timing["sync_offset"], margin=margin)
    if keep.sum() == 0:
        raise StageError(Problem(f"every frame lies within {margin} µs of the epipolar boundary",
                                 fix="lower boundary_margin_us, or sweep delays away from ±t_e/2"))
    grid = offsets.values() if offsets is not None else sweep_offsets(delays[keep], exposures[keep], **timing)
    matrix = plane_to_ray_illumination(delays[keep], exposures[keep], grid, **timing)
    return delays, exposures, keep, margin, grid, matrix


def solve_pixels(solver: DemuxADMM, problem: DemuxProblem | SeparableDemuxProblem, data: np.ndarray,
                 weight: np.ndarray, clipped: np.ndarray | None = None) -> Solution:
    """``solver.solve`` over (P, N) pixels in calls of :func:`pixels_per_call` (the last one padded with all-zero
    pixels), as one :class:`Solution` over the P pixels (``solver.throw`` judged on all of them at the end).

    A call with any masked or clipped observation takes the solver's majorised path (about twice the products
    per iteration), so the pixels with such observations (weight 0, non-finite or clipped) are solved last,
    together: only the calls that hold them pay.
    """
    p, per_call = data.shape[0], pixels_per_call(data.shape[0], problem.offsets)
    clipped = np.zeros(data.shape, bool) if clipped is None else np.asarray(clipped, bool)
    if p == 0:  # no pixels (an empty band): nothing to solve, the solver's batches need at least one row
        return Solution(np.zeros((0, problem.offsets), solver.dtype), np.zeros(0, np.int8),
                        {"iterations": np.zeros(0, np.int32), "objective": np.zeros(0, solver.dtype),
                         "gap_bound": np.zeros(0), "censored_offsets": np.zeros(0, np.int32)})
    plain = observed(data, weight).all(axis=1) & ~clipped.any(axis=1)
    order = np.argsort(~plain, kind="stable")
    data, weight, clipped = data[order], weight[order], clipped[order]
    size = min(per_call, p)  # one call of exactly p pixels, or equal calls with the last one padded
    parts, each = [], replace(solver, throw=False)
    for c in range(max(1, -(-p // per_call))):
        chunk = slice(c * size, (c + 1) * size)
        chunk_data, chunk_weight, chunk_clipped = data[chunk], weight[chunk], clipped[chunk]
        pad = size - chunk_data.shape[0]
        if pad:  # zero observations, unmasked: a weight of 0 would send the whole call down the masked path
            chunk_data = np.pad(chunk_data, ((0, pad), (0, 0)))
            chunk_weight = np.pad(chunk_weight, ((0, pad), (0, 0)), constant_values=1)
            chunk_clipped = np.pad(chunk_clipped, ((0, pad), (0, 0)))
        with jax.enable_x64(bool(np.dtype(solver.dtype) == np.float64)):
            solution = each.solve(problem, chunk_data, chunk_weight, chunk_clipped)
        parts.append(jax.tree.map(lambda a, keep=size - pad: a[:keep], solution))
    inverse = np.argsort(order)
    solution = jax.tree.map(lambda *column: np.concatenate(column)[inverse], *parts)
    if solver.throw:
        raise_if_failed(solution, "DemuxADMM", items="pixels")
    return solution


def _solve_band(solver: DemuxADMM, problem: DemuxProblem | SeparableDemuxProblem, frames: np.ndarray,
                shape: tuple[int, int], *, dark: float, full_scale: float, saturation: float
                ) -> tuple[np.ndarray, dict]:
    """Solve a band's (P, N) raw frames: (T (P, K) in counts, the per-pixel variables beside it).

    A frame at or above ``saturation`` is kept as a clipped observation (its light is at least the clip level,
    a one-sided penalty); a non-finite one is masked."""
    finite = np.isfinite(frames)
    clipped = finite & (frames >= saturation)
    data = np.where(finite, (np.where(clipped, saturation, frames) - dark) / full_scale, 0.0)
    solution = solve_pixels(solver, problem, data, finite, clipped)
    transport = solution.value * full_scale
    censored = solution.stats["censored_offsets"]
    # the brightest frame T predicts against the clip level: above 1 the light must drop by that much (projector
    # power, a filter) for the sweep to stay unclipped; a lower bound where censored (T is one there)
    clip_level = saturation - dark
    # in the solver's dtype (a diagnostic: in float64 after a float32 solve the product took 13 % of a band's time)
    brightest = (problem.forward(solution.value, solution.value.dtype).max(axis=-1) * full_scale if problem.frames
                 else np.zeros(len(data)))
    ratio = brightest / clip_level if np.isfinite(clip_level) and clip_level > 0 else np.full(len(data), np.nan)
    return transport, {
        "iterations": (("row", "col"), solution.stats["iterations"].reshape(shape).astype(np.int32)),
        "converged": (("row", "col"), solution.converged.reshape(shape)),
        "censored": (("row", "col"), (censored > 0).reshape(shape)),
        "censored_offsets": (("row", "col"), censored.reshape(shape).astype(np.int32)),
        "gap_bound": (("row", "col"), solution.stats["gap_bound"].reshape(shape).astype(np.float32)),
        "objective": (("row", "col"), solution.stats["objective"].reshape(shape).astype(np.float32)),
        "frames_used": (("row", "col"), (finite & ~clipped).sum(-1).reshape(shape).astype(np.int32)),
        "frames_clipped": (("row", "col"), clipped.sum(-1).reshape(shape).astype(np.int32)),
        "clip_ratio": (("row", "col"), ratio.reshape(shape).astype(np.float32)),
    }


#: per-pixel variables every transport store holds beside T (see _solve_band), with their dtypes
_PER_PIXEL = {"iterations": np.int32, "converged": bool, "censored": bool, "censored_offsets": np.int32,
              "objective": np.float32, "frames_used": np.int32, "frames_clipped": np.int32, "gap_bound": np.float32,
              "clip_ratio": np.float32}


def _template(capture: xr.Dataset, transport_dims: tuple[str, ...], transport_sizes: tuple[int, ...],
              row_chunks: tuple[int, ...], dtype: str, **per_pixel) -> xr.Dataset:
    """The lazy template of a transport store: T over ``transport_dims`` + (row, col), and per-pixel maps."""
    rows, cols = capture.sizes["row"], capture.sizes["col"]

    def lazy(dims, sizes, dt):
        return dims, da.zeros((*sizes, rows, cols), dtype=dt, chunks=(*sizes, row_chunks, cols))

    variables = {"transport": lazy((*transport_dims, "row", "col"), transport_sizes, dtype)}
    variables |= {name: lazy(("row", "col"), (), dt) for name, dt in (per_pixel | _PER_PIXEL).items()}
    return xr.Dataset(variables, coords={name: capture[name] for name in ("row", "col") if name in capture.coords})


#: what a transport keeps of its capture's attrs: which rig and scene it saw (a simulated capture's scene is the truth
#: later stages score against, e.g. the labels of ``choose_delay``)
CAPTURE_ATTRS = ("rig", "scene", "effects", "simulated_scene")


def _transport_attrs(kind: str, capture: xr.Dataset, *, timing: dict, delays, exposures, keep, margin: float,
                     full_scale: float, **settings) -> dict:
    """The attrs every transport store records: what it was captured of, its settings, the timing used and the
    frames dropped."""
    dropped = [[float(d), float(e)] for d, e in zip(delays[~keep], exposures[~keep], strict=True)]
    return {"selpath_kind": kind, **{k: capture.attrs[k] for k in CAPTURE_ATTRS if k in capture.attrs}, **settings,
            "scan_speed_px_per_us": timing["scan_speed"], "line_time_us": timing["line_time"],
            "sync_offset_us": timing["sync_offset"],
            "full_scale_counts": full_scale, "frames_dropped": dropped, "boundary_margin_us": margin}


def _band(block: xr.Dataset, *, solver: DemuxADMM, problem: DemuxProblem, keep: np.ndarray, levels: dict
          ) -> xr.Dataset:
    image = block["image"].transpose("delay", "exposure", "row", "col").values
    shape = image.shape[-2:]
    frames = image.reshape(-1, shape[0] * shape[1])[keep.ravel()].T  # (P, N kept)
    transport, per_pixel = _solve_band(solver, problem, frames, shape, **levels)
    return xr.Dataset({"transport": (("offset", "row", "col"),
                                     transport.T.reshape(-1, *shape).astype(solver.dtype)),
                       **per_pixel}, coords={name: block[name] for name in ("row", "col") if name in block.coords})


@stage("demux_plane_to_ray")
def demux_plane_to_ray(capture: xr.Dataset, scan_calibration: xr.Dataset | None = None, /, *,
                       offsets: OffsetGrid | None = None, alpha: NonNegative = DEFAULT_ALPHA,
                       beta: NonNegative = DEFAULT_BETA, tol: Positive = DemuxADMM.DEFAULT_TOL,
                       gap_tol: GapTol = DemuxADMM.DEFAULT_GAP_TOL, finish_rounds: FinishRounds = 0,
                       max_iter: MaxIter = DemuxADMM.DEFAULT_MAX_ITER,
                       polish_iter: Index = DemuxADMM.DEFAULT_POLISH_ITER,
                       boundary_margin_us: NonNegative | None = None, sync_offset_us: float | None = None,
                       full_scale: Positive | None = None, rows_per_tile: Count = 32,
                       dtype: Dtype = "float32") -> xr.Dataset:
    """Plane-to-ray transport T(offset, row, col) from a ``(delay, exposure, row, col)`` capture (§5.2.2).

    Per pixel: min Σ_i ‖I_i − L_i ∗ T‖² + α‖∂T/∂v‖² + β‖T‖₁, T ≥ 0, on images scaled to [0, 1] by
    ``full_scale``; T is returned in counts. A frame at or above ``saturation_counts`` is kept as a lower bound
    (the one-sided penalty max(0, s − A_i T)²); a non-finite one is masked. Besides T, per pixel: iterations,
    ``converged``, objective, ``gap_bound`` (a certified upper bound on the relative objective gap
    (f(T) − f*)/f(T), from weak duality: conservative, as tight as T's KKT conditions), ``frames_used`` and
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
        Relative primal and dual residual at which a pixel counts as converged (checked every 5 iterations).
        Measured against a float64 solve at tol 1e-7, gap = relative objective gap (median, p90), mean
        iterations in brackets. Benchmark stack (K = 128, 4096 px): 5e-3 → 7.0e-5 [20]. Fig. 38 stack (rows
        140–156 of the procam workflow's capture, K = 253, N = 63, 6400 px): 1e-2 → 6.0e-4 [19]; 5e-3 →
        2.7e-4, p90 6.2e-4 [38]; 3e-3 → 1.2e-4 [55]; 2e-3 → 6.1e-5, p90 2.3e-4 [72]; 1e-3 → 1.5e-5 [114,
        4.5 % at the cap]. The default meets the issue's 1e-4 median on the benchmark's stack at K = 128; many
        offsets per pixel (Fig. 38) need 2e-3 for it, at about twice the time.
    gap_tol : float
        A pixel whose certified bound on the relative objective gap (``gap_bound``) is at most this, in [0, 1),
        is converged whatever its residuals say: checked at the warm start (such a pixel, e.g. one whose light β
        outweighs so that T = 0 is exactly optimal, takes no iteration) and after the polish. 0: only exactly
        optimal pixels. Dimensionless (a share of the pixel's own objective), so meaningful on any intensity
        scale.
    finish_rounds : int
        Exact active-set rounds after the polish (float64 solves on each pixel's free offsets, masked and clipped
        frames included) for the pixels whose bound still exceeds ``gap_tol``; in [0, 20]; 0: none. With it,
        ``converged`` means certified (``gap_bound`` ≤ ``gap_tol``). Measured (``benchmarks/demux_catalogue.py``,
        2048 px per case, this 2-core machine): 16 rounds certify every pixel of every case (thesis-like K = 64,
        128, 256, NaN and clipped frames, 1e8 data, N < K, a wide exposure) to 1e-4, at 35–216 µs/px against
        ADMM's 9–43 µs/px; in the stage's calls on the benchmark stack (``benchmarks/demux_throughput.py``
        --quick), 67 against 7.2 µs/px, bound median 3.1e-3 → 1.2e-6, max 0.18 → 8.5e-5. Use it when each
        pixel's answer must be proven.
    max_iter : int
        Iteration cap, in [1, 1 000 000]; a pixel that reaches it is flagged unconverged. A solver call streams its
        pixels through a batch refilled as they converge, so the cap bounds only the slow ones.
    polish_iter : int
        Conjugate-gradient steps of the final support polish (0: none); it costs about as many products as
        iterations and is kept per pixel only where it lowers the objective.
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
    """
    if "line" in capture.dims:
        raise StageError(Problem("this capture has a line dimension (a full-transport sweep)",
                                 fix="use demux_full for (delay, exposure, line, row, col) captures"))
    timing = _rig_timing(capture, scan_calibration, sync_offset_us)
    dark, scale, saturation = _levels(capture, full_scale)
    delays, exposures, keep, margin, grid, matrix = _frames(capture, timing, boundary_margin_us, offsets)
    problem = DemuxProblem.build(matrix, alpha=alpha, beta=beta)
    stack = capture[["image"]].chunk({"delay": -1, "exposure": -1, "row": rows_per_tile, "col": -1})
    template = _template(capture, ("offset",), (grid.size,), stack.chunksizes["row"], dtype)
    levels = {"dark": dark, "full_scale": scale, "saturation": saturation}
    solver = DemuxADMM(tol=tol, gap_tol=gap_tol, finish_rounds=finish_rounds, max_iter=max_iter,
                       polish_iter=polish_iter, dtype=dtype)
    out = xr.map_blocks(_band, stack.assign_attrs({}), kwargs={
        "solver": solver, "problem": problem, "keep": keep, "levels": levels}, template=template)
    out = out.assign_coords(offset=("offset", grid, {"units": "px", "long_name": "projector row − camera row"}))
    out["transport"].attrs = {"units": "counts", "long_name": "plane-to-ray transport T(v, s, t)"}
    out = _describe(out, int(keep.sum()), "plane_to_ray_transport", gap_tol)
    return out.assign_attrs(_transport_attrs(
        "plane_to_ray_transport", capture, timing=timing, delays=delays, exposures=exposures, keep=keep, margin=margin,
        full_scale=scale, alpha=alpha, beta=beta, tol=tol, gap_tol=gap_tol, finish_rounds=finish_rounds,
        max_iter=max_iter, polish_iter=polish_iter, dtype=dtype))


#: floor of ``usable_fraction``: below it most observations are saturated or missing, and T is a guess
USABLE_FLOOR = 0.05

#: what the per-pixel variables of a transport store need said beyond their schema's units and long_name
PER_PIXEL_DESCRIPTIONS = {
    "censored_offsets": "lit by a clipped frame, by no unclipped one, and holding at least 1 % of the clip level: "
                        "T there is what the clipped frames prove (the least light consistent with them), not an "
                        "estimate",
    "clip_ratio": "above 1 the pixel clipped: the light (projector power, a neutral-density filter) must drop by this "
                  "factor for no frame of the sweep to clip; a lower bound where censored",
}


def _describe(out: xr.Dataset, frames: int, kind: str, gap_tol: float) -> xr.Dataset:
    """Attrs of the per-pixel variables (the schema's units and long names, as a store written from it will
    carry them) and the result's shares: usable observations (floor 5 %), pixels not censored (no floor: a
    report, which the engine logs with its advice when below 1) and pixels certified (``gap_bound`` ≤ ``gap_tol``;
    no floor: a report; ``converged`` also counts pixels whose residuals met ``tol``)."""
    for name, description in PER_PIXEL_DESCRIPTIONS.items():
        out[name].attrs = {"description": description}
    out = with_metadata(out, kind)
    out["usable_fraction"] = _usable(out["frames_used"], frames)
    out["uncensored_fraction"] = usable_share(
        1.0 - out["censored"].mean(), floor=0.0, label="uncensored",
        what="pixels whose every bright offset was seen unclipped (the others are `censored`: T is a lower bound)",
        fix="where pixels are censored, lower the projector's power or add a neutral-density filter by their "
            "clip_ratio (or sweep shorter exposures where the clipped light sums over many rows)",
        advise_below=1.0)
    out["certified_fraction"] = usable_share(
        (out["gap_bound"] <= gap_tol).mean(), floor=0.0, label="certified",
        what=f"pixels whose certified objective-gap bound is at most gap_tol = {gap_tol:g} (converged ones "
             "beyond them met the residual test, tol: their gap_bound says what is proven)",
        fix=CERTIFY_ADVICE[kind])
    return out


#: how each transport kind certifies more pixels (the full transport's solver has no exact finish)
CERTIFY_ADVICE = {
    "plane_to_ray_transport": "for a certificate on every pixel set finish_rounds (16 rounds certified every pixel of "
                              "the benchmarks' catalogue, at 2–10× the time); a tighter tol certifies more pixels, "
                              "at more iterations",
    "full_transport": "a tighter tol certifies more pixels, at more iterations (the full transport has no exact "
                      "finish)",
}


def _usable(frames_used: xr.DataArray, frames: int) -> xr.DataArray:
    return usable_share(frames_used.sum() / max(frames * frames_used.size, 1), floor=USABLE_FLOOR,
                        what="observations (pixel × frame) that were usable, neither saturated nor missing",
                        fix="check the capture: saturation_counts, NaN frames, exposures too long for the scene")


#: bytes of full transport one dask task may hold (the default rows_per_tile of demux_full follows from it)
FULL_TILE_BYTES = 64 * 2**20


def _band_full(block: xr.Dataset, *, solver: DemuxADMM, problem: SeparableDemuxProblem, keep: np.ndarray,
               levels: dict, reach: int, centre_v: int, cells: np.ndarray) -> xr.Dataset:
    image = block["image"].transpose("line", "delay", "exposure", "row", "col").values
    n_lines, rows, cols = image.shape[0], *image.shape[-2:]
    frames = image.reshape(n_lines, -1, rows * cols)[:, keep.ravel()].reshape(-1, rows * cols).T  # line-major
    shape = (rows, cols)
    transport, per_pixel = _solve_band(solver, problem, frames, shape, **levels)
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


@stage("demux_full")
def demux_full(capture: xr.Dataset, scan_calibration: xr.Dataset | None = None, /, *,
               offsets: OffsetGrid | None = None, cell_width_px: Positive | None = None,
               du_reach_px: NonNegative | None = None, alpha: NonNegative = DEFAULT_ALPHA,
               beta: NonNegative = DEFAULT_BETA, tol: Positive = DemuxADMM.DEFAULT_TOL,
               gap_tol: GapTol = DemuxADMM.DEFAULT_GAP_TOL, max_iter: MaxIter = DemuxADMM.DEFAULT_MAX_ITER,
               polish_iter: Index = DemuxADMM.DEFAULT_POLISH_ITER,
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
    tol, gap_tol, max_iter, polish_iter, boundary_margin_us, sync_offset_us, full_scale, dtype
        As for ``demux_plane_to_ray``.
    rows_per_tile : int or None
        Camera rows per dask task; None: as many as keep a task's transport within 64 MiB.
    """
    if "line" not in capture.dims:
        raise StageError(Problem("this capture has no line dimension (a plane-to-ray sweep)",
                                 fix="use demux_plane_to_ray for (delay, exposure, row, col) captures"))
    if "line_width_px" not in capture.attrs:
        raise StageError(Problem("the capture has no attr 'line_width_px'", where="capture",
                                 fix="acquire with acquire_full_transport, or add the attr (docs/format.md)"))
    timing = _rig_timing(capture, scan_calibration, sync_offset_us)
    dark, scale, saturation = _levels(capture, full_scale)
    delays, exposures, keep, margin, grid, frame_matrix = _frames(capture, timing, boundary_margin_us, offsets)
    lines, width = capture["line"].values, float(capture.attrs["line_width_px"])
    if lines.size > 1 and not np.allclose(np.diff(lines), np.diff(lines)[0]) and cell_width_px is None:
        raise StageError(Problem("the line positions are not evenly spaced, so the u-cell width is ambiguous",
                                 fix="set cell_width_px"))
    try:
        cells, step = line_cells(lines, width, cell_width_px)
    except ValueError as error:
        raise StageError(Problem(str(error), where="capture line sweep", fix="set cell_width_px > 0")) from None
    problem = SeparableDemuxProblem.build(line_illumination(lines, width, cells, step), frame_matrix,
                                          alpha=alpha, beta=beta)
    k_u = cells.size
    reach = k_u - 1 if du_reach_px is None else min(int(np.floor(du_reach_px / step)), k_u - 1)
    cols = capture.sizes["col"]
    if rows_per_tile is None:
        per_row = cols * (2 * reach + 1 + k_u) * grid.size * 4
        rows_per_tile = int(np.clip(FULL_TILE_BYTES // max(per_row, 1), 1, 64))
    stack = capture[["image"]].chunk({"delay": -1, "exposure": -1, "line": -1, "row": rows_per_tile, "col": -1})
    template = _template(capture, ("du", "dv"), (2 * reach + 1, grid.size), stack.chunksizes["row"], dtype,
                         u_direct=np.float32)
    out = xr.map_blocks(_band_full, stack.assign_attrs({}), kwargs={
        "solver": DemuxADMM(tol=tol, gap_tol=gap_tol, max_iter=max_iter, polish_iter=polish_iter, dtype=dtype),
        "problem": problem,
        "keep": keep, "levels": {"dark": dark, "full_scale": scale, "saturation": saturation}, "reach": reach,
        "centre_v": int(np.argmin(np.abs(grid))), "cells": cells}, template=template)
    out = out.assign_coords(
        du=("du", np.arange(-reach, reach + 1) * step, {"units": "px", "long_name": "projector column − u₀"}),
        dv=("dv", grid, {"units": "px", "long_name": "projector row − camera row"}))
    out["transport"].attrs = {"units": "counts", "long_name": "full transport T(u, v, s, t)",
                              "description": f"light from a {step:g}-column u-cell; NaN where no line reached"}
    out["u_direct"].attrs = {"units": "px", "long_name": "direct correspondence u₀ (centre of the brightest cell)"}
    out = _describe(out, int(keep.sum()) * capture.sizes["line"], "full_transport", gap_tol)
    return out.assign_attrs(_transport_attrs(
        "full_transport", capture, timing=timing, delays=delays, exposures=exposures, keep=keep, margin=margin,
        full_scale=scale, alpha=alpha, beta=beta, tol=tol, gap_tol=gap_tol, max_iter=max_iter,
        polish_iter=polish_iter, dtype=dtype,
        line_width_px=width, cell_width_px=step, cells_px=cells.tolist(), lines=int(lines.size),
        **{name: capture.attrs[name] for name in ("projector_shape",) if name in capture.attrs}))
