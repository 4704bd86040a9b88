"""Demultiplexing a delay–exposure stack into plane-to-ray transport T(offset, row, col) (§5.2.2).

Lazy over bands of camera rows (dask, one task per band), JAX inside each band (``stages.demux_solver``). The
illumination matrix (``stages.illumination``) is built once from the sweep, v_p, t_p and the sync offset —
from a ``scan_calibration`` store when one is wired in — and shared by every pixel. Frames at the epipolar
boundary are dropped by the rule of :func:`stages.illumination.epipolar_boundary`; saturated and non-finite
observations are masked per pixel. T is in the capture's counts: the image of a row lit for its whole line
time t_p, so Σ_o T(o) w(o; t_d, t_e) reproduces a frame.
"""

from __future__ import annotations

import dask.array as da
import jax
import numpy as np
import pydantic
import xarray as xr

from pipeline.errors import Problem, StageError
from pipeline.registry import stage
from stages.demux_solver import DemuxProblem, solve
from stages.illumination import epipolar_boundary, plane_to_ray_illumination
from stages.reconstruct import Dtype

#: pixels per solver call: one compiled shape (the last call is padded), ~100 MB of solver state in float32
PIXELS_PER_CALL = 16384


class OffsetGrid(pydantic.BaseModel):
    """Offsets o = projector row − camera row: start, start+step, …, up to and including stop [rows]."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True)
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


def solve_pixels(problem: DemuxProblem, data: np.ndarray, weight: np.ndarray, *, dtype: str, **options):
    """``solve`` over (P, N) pixels in calls of PIXELS_PER_CALL (the last one padded with empty pixels)."""
    p = data.shape[0]
    calls = max(1, -(-p // PIXELS_PER_CALL))
    size = min(PIXELS_PER_CALL, p) if calls == 1 else PIXELS_PER_CALL
    parts = []
    for c in range(calls):
        chunk_data = data[c * size:(c + 1) * size]
        chunk_weight = weight[c * size:(c + 1) * size]
        pad = size - chunk_data.shape[0]
        if pad:
            chunk_data = np.pad(chunk_data, ((0, pad), (0, 0)))
            chunk_weight = np.pad(chunk_weight, ((0, pad), (0, 0)))
        with jax.enable_x64(dtype == "float64"):
            result = solve(problem, chunk_data, chunk_weight, dtype=np.dtype(dtype), **options)
        keep = slice(0, size - pad)
        parts.append((result.transport[keep], result.iterations[keep], result.converged[keep],
                      result.objective[keep]))
    return [np.concatenate(column) for column in zip(*parts, strict=True)]


def _band(block: xr.Dataset, *, problem: DemuxProblem, keep: np.ndarray, dark: float, full_scale: float,
          saturation: float, dtype: str, options: dict) -> xr.Dataset:
    image = block["image"].transpose("delay", "exposure", "row", "col").values
    rows, cols = image.shape[-2:]
    frames = image.reshape(-1, rows * cols)[keep.ravel()].T  # (P, N kept)
    weight = np.isfinite(frames) & (frames < saturation)
    data = np.where(weight, (frames - dark) / full_scale, 0.0)
    transport, iterations, converged, objective = solve_pixels(problem, data, weight, dtype=dtype, **options)
    shape = (rows, cols)
    return xr.Dataset({
        "transport": (("offset", "row", "col"), (transport.T * full_scale).reshape(-1, *shape).astype(dtype)),
        "iterations": (("row", "col"), iterations.reshape(shape).astype(np.int32)),
        "converged": (("row", "col"), converged.reshape(shape)),
        "objective": (("row", "col"), objective.reshape(shape).astype(np.float32)),
        "frames_used": (("row", "col"), weight.sum(-1).reshape(shape).astype(np.int32)),
    }, coords={name: block[name] for name in ("row", "col") if name in block.coords})


@stage("demux_plane_to_ray")
def demux_plane_to_ray(capture: xr.Dataset, scan_calibration: xr.Dataset | None = None, /, *,
                       offsets: OffsetGrid | None = None, alpha: float = 0.01, beta: float = 0.01,
                       tol: float = 1e-3, max_iter: int = 40, polish_iter: int = 0,
                       boundary_margin_us: float | None = None, sync_offset_us: float | None = None,
                       full_scale: float | None = None, rows_per_tile: int = 32,
                       dtype: Dtype = "float32") -> xr.Dataset:
    """Plane-to-ray transport T(offset, row, col) from a ``(delay, exposure, row, col)`` capture (§5.2.2).

    Per pixel: min Σ_i ‖I_i − L_i ∗ T‖² + α‖∂T/∂v‖² + β‖T‖₁, T ≥ 0, on images scaled to [0, 1] by
    ``full_scale``; T is returned in counts. Besides T: per-pixel iterations, convergence flag, objective
    and the number of frames used (saturated or non-finite observations are masked).

    Parameters
    ----------
    offsets : {start, stop, step} or None
        Offset grid [rows]; None: every offset some frame of the sweep lights.
    alpha : float
        Smoothness weight α (thesis: 0.01).
    beta : float
        Sparsity weight β (thesis: 0.01).
    tol : float
        Relative primal and dual residual at which a pixel counts as converged.
    max_iter : int
        Iteration cap (ADMM iterations, checked every 10).
    polish_iter : int
        Conjugate-gradient steps of the final support polish (0: none).
    boundary_margin_us : float or None
        Drop frames whose exposure edge is within this many µs of the epipolar row; None: t_p/2 (the edge
        cuts the epipolar row's own line time; widen it by the laser jitter of a real rig).
    sync_offset_us : float or None
        Sync offset t_o [µs]; None: the scan calibration's when wired in, else 0.
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
    delays, exposures = np.meshgrid(capture["delay"].values, capture["exposure"].values, indexing="ij")
    margin = timing["line_time"] / 2 if boundary_margin_us is None else boundary_margin_us
    keep = ~epipolar_boundary(delays, exposures, sync_offset=timing["sync_offset"], margin=margin)
    if keep.sum() == 0:
        raise StageError(Problem(f"every frame lies within {margin} µs of the epipolar boundary",
                                 fix="lower boundary_margin_us, or sweep delays away from ±t_e/2"))
    grid = offsets.values() if offsets is not None else sweep_offsets(delays[keep], exposures[keep], **timing)
    matrix = plane_to_ray_illumination(delays[keep], exposures[keep], grid, **timing)
    problem = DemuxProblem.build(matrix, alpha=alpha, beta=beta)
    stack = capture[["image"]].chunk({"delay": -1, "exposure": -1, "row": rows_per_tile, "col": -1})
    rows, cols = capture.sizes["row"], capture.sizes["col"]
    row_chunks = stack.chunksizes["row"]

    def lazy(shape, chunks, dt):
        return da.zeros(shape, dtype=dt, chunks=chunks)

    template = xr.Dataset({
        "transport": (("offset", "row", "col"), lazy((grid.size, rows, cols), (grid.size, row_chunks, cols), dtype)),
        "iterations": (("row", "col"), lazy((rows, cols), (row_chunks, cols), np.int32)),
        "converged": (("row", "col"), lazy((rows, cols), (row_chunks, cols), bool)),
        "objective": (("row", "col"), lazy((rows, cols), (row_chunks, cols), np.float32)),
        "frames_used": (("row", "col"), lazy((rows, cols), (row_chunks, cols), np.int32)),
    }, coords={name: capture[name] for name in ("row", "col") if name in capture.coords})
    options = {"tol": tol, "max_iter": max_iter, "polish_iter": polish_iter}
    out = xr.map_blocks(_band, stack.assign_attrs({}), kwargs={
        "problem": problem, "keep": keep, "dark": dark, "full_scale": scale, "saturation": saturation,
        "dtype": dtype, "options": options}, template=template)
    out = out.assign_coords(offset=("offset", grid, {"units": "px", "long_name": "projector row − camera row"}))
    out["transport"].attrs = {"units": "counts", "long_name": "plane-to-ray transport T(v, s, t)"}
    out["objective"].attrs = {"long_name": "objective at T (images scaled to [0, 1])"}
    dropped = [[float(d), float(e)] for d, e in zip(delays[~keep], exposures[~keep], strict=True)]
    return out.assign_attrs({
        "selpath_kind": "plane_to_ray_transport", "alpha": alpha, "beta": beta, "tol": tol, "max_iter": max_iter,
        "scan_speed_px_per_us": timing["scan_speed"], "line_time_us": timing["line_time"],
        "sync_offset_us": timing["sync_offset"], "full_scale_counts": scale,
        "frames_dropped": dropped, "boundary_margin_us": margin, "dtype": dtype})
