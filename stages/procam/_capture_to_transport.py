"""From a capture to a transport store: what ``demux_plane_to_ray`` (:mod:`selpath.stages.procam.demux`) and
``demux_full``
(:mod:`selpath.stages.procam.demux_full`) share.

The rig's timing (v_p, t_p, the sync offset: the capture's attrs or a scan calibration), the counts that scale the
images to [0, 1], the frames kept and the offset grid of a delay–exposure sweep, the per-band solve (raw frames →
T in counts and the per-pixel variables beside it: clipped frames as lower bounds, non-finite ones masked), the
lazy template of a transport store, the attrs every transport records, and the 0-d shares (usable, uncensored,
certified) the engine logs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import pydantic
import xarray as xr

from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.stages._solution import Solution, raise_if_failed
from selpath.stages._sweeps import Sweep
from selpath.stages.procam._illumination import (
    SYNC_DELAY_ATTRS,
    RigTiming,
    epipolar_boundary,
    offset_delay,
    plane_to_ray_illumination,
)

if TYPE_CHECKING:  # the solver imports JAX: these modules load when a band is solved, not when a workflow is read
    from selpath.stages.procam._demux_problem import DemuxProblem, SeparableDemuxProblem
    from selpath.stages.procam._demux_solver import DemuxADMM

#: streaming batches per solver call: a call's pool (data, warm starts, results: ~8 (P × K) arrays, 64 MB at
#: K = 128) is bounded while the batch's tail (its last, slowest pixels) is paid once per 16 batches of pixels
POOL_BATCHES = 16


def pixels_per_call(pixels: int, offsets: int) -> int:
    """Pixels per solver call: at most POOL_BATCHES streaming batches, the calls of ``pixels`` equal in size
    (a multiple of the batch, so a band's calls share one compiled shape and little is padding)."""
    from selpath.stages.procam._demux_solver import batch_slots

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


@dataclass(frozen=True)
class Levels:
    """The counts that scale raw frames to [0, 1]: ``dark`` level, ``full_scale`` (counts above dark of a
    saturated pixel) and the ``saturation`` level (frames at or above it are clipped observations)."""

    dark: float
    full_scale: float
    saturation: float


@dataclass(frozen=True)
class SweepFrames:
    """A delay–exposure sweep as the demultiplexer sees it: ``delays`` and ``exposures`` [µs] over the capture's
    (delay, exposure) grid, which frames it keeps, ``keep`` (those clear of the epipolar boundary by ``margin`` [µs]),
    the ``offsets`` it solves for [rows] and the kept frames' illumination ``matrix`` (frames × offsets)."""

    delays: np.ndarray
    exposures: np.ndarray
    keep: np.ndarray
    margin: float
    offsets: np.ndarray
    matrix: np.ndarray


def rig_timing(capture: xr.Dataset, calibration: xr.Dataset | None, sync_offset: float | None) -> RigTiming:
    """The capture's nominal timing, or a scan calibration's (which wins), with ``sync_offset`` [µs] winning over
    both where given."""
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
    return RigTiming(scan_speed=speed, line_time=float(attrs["line_time_us"]), sync_offset=offset)


def levels_of(capture: xr.Dataset, full_scale: float | None) -> Levels:
    """The capture's levels in counts (``full_scale`` given: it, else saturation − dark)."""
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
    return Levels(dark=dark, full_scale=float(full_scale), saturation=saturation)


def sweep_illumination(capture: xr.Dataset, timing: RigTiming, boundary_margin_us: float | None,
                       offsets: OffsetGrid | None) -> SweepFrames:
    """The capture's sweep: its frames clear of the epipolar boundary, the offset grid (``offsets``, else every
    offset some kept frame lights) and the kept frames' illumination matrix."""
    delays, exposures = np.meshgrid(capture["delay"].values, capture["exposure"].values, indexing="ij")
    margin = timing.line_time / 2 if boundary_margin_us is None else boundary_margin_us
    keep = ~epipolar_boundary(delays, exposures, sync_offset=timing.sync_offset, margin=margin)
    if keep.sum() == 0:
        raise StageError(Problem(f"every frame lies within {margin} µs of the epipolar boundary",
                                 fix="lower boundary_margin_us, or sweep delays away from ±t_e/2"))
    grid = offsets.values() if offsets is not None else sweep_offsets(delays[keep], exposures[keep],
                                                                      **timing.keywords())
    matrix = plane_to_ray_illumination(delays[keep], exposures[keep], grid, **timing.keywords())
    return SweepFrames(delays=delays, exposures=exposures, keep=keep, margin=margin, offsets=grid, matrix=matrix)


def solve_pixels(solver: DemuxADMM, problem: DemuxProblem | SeparableDemuxProblem, data: np.ndarray,
                 weight: np.ndarray, clipped: np.ndarray | None = None) -> Solution:
    """``solver.solve`` over (P, N) pixels in calls of :func:`pixels_per_call` (the last one padded with all-zero
    pixels), as one :class:`Solution` over the P pixels (``solver.throw`` judged on all of them at the end).

    A call with any masked or clipped observation takes the solver's majorised path (about twice the products
    per iteration), so the pixels with such observations (weight 0, non-finite or clipped) are solved last,
    together: only the calls that hold them pay.
    """
    import jax

    from selpath.stages.procam._demux_solver import observed

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


def solve_band(solver: DemuxADMM, problem: DemuxProblem | SeparableDemuxProblem, frames: np.ndarray,
               shape: tuple[int, int], levels: Levels) -> tuple[np.ndarray, dict]:
    """Solve a band's (P, N) raw frames: (T (P, K) in counts, the per-pixel variables beside it).

    A frame at or above ``saturation`` is kept as a clipped observation (its light is at least the clip level,
    a one-sided penalty); a non-finite one is masked."""
    dark, full_scale, saturation = levels.dark, levels.full_scale, levels.saturation
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


#: per-pixel variables every transport store holds beside T (see solve_band), with their dtypes
PER_PIXEL = {"iterations": np.int32, "converged": bool, "censored": bool, "censored_offsets": np.int32,
             "objective": np.float32, "frames_used": np.int32, "frames_clipped": np.int32, "gap_bound": np.float32,
             "clip_ratio": np.float32}


def transport_template(capture: xr.Dataset, transport_dims: tuple[str, ...], transport_sizes: tuple[int, ...],
                       row_chunks: tuple[int, ...], dtype: str, **per_pixel) -> xr.Dataset:
    """The lazy template of a transport store: T over ``transport_dims`` + (row, col), and per-pixel maps."""
    import dask.array as da

    rows, cols = capture.sizes["row"], capture.sizes["col"]

    def lazy(dims, sizes, dt):
        return dims, da.zeros((*sizes, rows, cols), dtype=dt, chunks=(*sizes, row_chunks, cols))

    variables = {"transport": lazy((*transport_dims, "row", "col"), transport_sizes, dtype)}
    variables |= {name: lazy(("row", "col"), (), dt) for name, dt in (per_pixel | PER_PIXEL).items()}
    return xr.Dataset(variables, coords={name: capture[name] for name in ("row", "col") if name in capture.coords})


_FRAME = ("row", "col")
#: the per-pixel solver's results beside a transport (both transport kinds declare them)
DEMUX_EXTRAS = {
    "iterations": Variable(_FRAME, required=False, units="1", long_name="ADMM iterations run for the pixel"),
    "converged": Variable(_FRAME, required=False, units=None,
                          long_name="the pixel's solve met its tolerance (plane-to-ray: a certified gap_bound "
                                    "within max_gap) and no offset's light is censored"),
    "censored": Variable(_FRAME, required=False, units=None,
                         long_name="some offset's light was seen only in clipped frames: T is a lower bound there"),
    "censored_offsets": Variable(_FRAME, required=False, units="1",
                                 long_name="offsets whose light was seen only in clipped frames"),
    "gap_bound": Variable(_FRAME, required=False, units="1",
                          long_name="certified bound on the relative objective gap (f(T) − f*)/f(T)"),
    "frames_used": Variable(_FRAME, required=False, units="1",
                            long_name="frames observed for the pixel, neither clipped nor missing"),
    "frames_clipped": Variable(_FRAME, required=False, units="1",
                               long_name="frames at or above saturation_counts, kept as lower bounds"),
    "clip_ratio": Variable(_FRAME, required=False, units="1",
                           long_name="brightest frame T predicts over the clip level (counts above dark)"),
    "objective": Variable(_FRAME, required=False, units="1", long_name="objective at T (images scaled to [0, 1])"),
}
#: what a transport carries from its sweep, read by the stages after it (short_range_images, the relighting figures)
TRANSPORT_ATTRS = {
    "scan_speed_px_per_us": "v_p used, camera rows per µs (offset o ↔ delay o / v_p)",
    "line_time_us": "t_p, µs",
    "full_scale_counts": "counts that scaled the images to [0, 1] (the objective's scale)",
}

#: what a transport keeps of its capture's attrs: which rig and scene it saw (a simulated capture's scene is the truth
#: later stages score against, e.g. the labels of ``choose_delay``)
CAPTURE_ATTRS = ("rig", "scene", "effects", "simulated_scene", "projector_shape")


def with_sync_delay(out: xr.Dataset, dim: str, timing: RigTiming) -> xr.Dataset:
    """``out`` with a ``sync_delay`` coordinate [µs] along its offset dim ``dim``: the delay t_d = o / v_p − t_o at
    which each offset's light is centred in the exposure (:func:`~selpath.stages.procam._illumination.offset_delay`,
    from the v_p and t_o the demultiplexing used), so a profile plots over the capture's own delay axis."""
    delay = offset_delay(out[dim].values, scan_speed=timing.scan_speed, sync_offset=timing.sync_offset)
    return out.assign_coords(sync_delay=(dim, delay, dict(SYNC_DELAY_ATTRS)))


def transport_attrs(capture: xr.Dataset, *, timing: RigTiming, sweep: SweepFrames, full_scale: float,
                    **settings) -> dict:
    """The attrs every transport store records: what it was captured of, its settings, the timing used and the
    frames dropped."""
    dropped = [[float(d), float(e)] for d, e in zip(sweep.delays[~sweep.keep], sweep.exposures[~sweep.keep],
                                                     strict=True)]
    return {**{k: capture.attrs[k] for k in CAPTURE_ATTRS if k in capture.attrs}, **settings,
            "scan_speed_px_per_us": timing.scan_speed, "line_time_us": timing.line_time,
            "sync_offset_us": timing.sync_offset,
            "full_scale_counts": full_scale, "frames_dropped": dropped, "boundary_margin_us": sweep.margin}


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


def describe_transport(out: xr.Dataset, frames: int, kind: CubeKind, gap_tol: float) -> xr.Dataset:
    """Attrs of the per-pixel variables (the schema's units and long names, as a store written from it will
    carry them) and the result's shares: usable observations (floor 5 %), pixels not censored (no floor: a
    report, which the engine logs with its advice when below 1) and pixels certified (``gap_bound`` ≤ ``gap_tol``;
    no floor: a report; ``converged`` also counts pixels whose residuals met ``tol``)."""
    for name, description in PER_PIXEL_DESCRIPTIONS.items():
        out[name].attrs = {"description": description}
    out = kind.label(out)
    out["usable_fraction"] = usable_observations(out["frames_used"], frames)
    out["uncensored_fraction"] = usable_share(
        1.0 - out["censored"].mean(), floor=0.0, label="uncensored",
        what="pixels whose every bright offset was seen unclipped (the others are `censored`: T is a lower bound)",
        fix="where pixels are censored, lower the projector's power or add a neutral-density filter by their "
            "clip_ratio (or sweep shorter exposures where the clipped light sums over many rows)",
        advise_below=1.0)
    out["certified_fraction"] = usable_share(
        (out["gap_bound"] <= gap_tol).mean(), floor=0.0, label="certified",
        what=f"pixels whose certified objective-gap bound is at most gap_tol = {gap_tol:g} (converged ones "
             "beyond them met the residual test, tol, with a bound at most max_gap where the solver has one: their "
             "gap_bound says what is proven)",
        fix=CERTIFY_ADVICE[kind.name])
    return out


#: how each transport kind certifies more pixels (the full transport's solver has no exact finish)
CERTIFY_ADVICE = {
    "plane_to_ray_transport": "for a certificate ≤ gap_tol on every pixel set max_gap = gap_tol (the exact finish "
                              "then runs on every pixel above gap_tol: it certified every pixel of the benchmarks' "
                              "catalogue, at 2–8× the time); a tighter tol certifies more pixels, at more "
                              "iterations",
    "full_transport": "a tighter tol certifies more pixels, at more iterations (the full transport has no exact "
                      "finish)",
}


def usable_observations(frames_used: xr.DataArray, frames: int) -> xr.DataArray:
    return usable_share(frames_used.sum() / max(frames * frames_used.size, 1), floor=USABLE_FLOOR,
                        what="observations (pixel × frame) that were usable, neither saturated nor missing",
                        fix="check the capture: saturation_counts, NaN frames, exposures too long for the scene")
