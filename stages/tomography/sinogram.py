"""Sinograms (§4.2.6).

``bin_sinogram`` puts aligned rays on a regular (θ, X) grid per slice: bin centres θ_i = i·180°/n_theta
and X_j evenly over [−x_extent, x_extent]; rays falling in one bin are averaged, ``count`` says how
many, and ``observed`` marks bins holding at least one ray. Which share of the object's sinogram is observed,
beside the thesis's closed form for a cylinder, is :mod:`selpath.stages.tomography.coverage`.
"""

from __future__ import annotations

import warnings
from typing import Annotated

import dask
import numpy as np
import pydantic
import xarray as xr

from selpath.geometry.rig import RigGeometry, geometry_attrs
from selpath.pipeline.constraints import Positive, memory_problems
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import ANGLE_UNITS, LENGTH_UNITS, CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables

SINOGRAM = CubeKind(
    name="sinogram",
    description="total absorption on a (θ, X) grid with a mask of observed rays",
    variables={
        "absorption": Variable(("theta", "x"), units="1",
                               long_name="total absorption A = log I_reference − log I_target"),
        "observed": Variable(("theta", "x"), description="True where a ray was measured", units=None,
                             long_name="bin holds a measured ray"),
        "count": Variable(("theta", "x"), False, "rays averaged into the bin", units="1",
                          long_name="rays averaged into the bin"),
    },
    coord_units={"theta": ANGLE_UNITS, "x": LENGTH_UNITS},
    batch_dims=("slice",),
)


#: bins of a grid whose step is span / (bins − 1): at least 2
Bins = Annotated[int, pydantic.Field(ge=2)]


def bin_index(theta, x, *, n_theta: int, n_x: int, extent: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sinogram bin (i, j) of rays (θ [degree] in [0, 180), X), and whether it is on the grid.

    Bin i spans [θ_i − Δθ/2, θ_i + Δθ/2) around θ_i = i·180°/n_theta; the last half-bin wraps to bin 0 with X
    flipped (the same line). j is the nearest of the n_x points X_j evenly over [−extent, extent]. Rays with
    a non-finite θ or X are off the grid.

    >>> bin_index(np.array([0.0, 179.9, np.nan]), np.array([0.4, 0.4, 0.0]), n_theta=4, n_x=3, extent=1.0)
    (array([0, 0, 0]), array([1, 1, 1]), array([ True,  True, False]))
    """
    step_theta, step_x = 180.0 / n_theta, 2 * extent / (n_x - 1)
    shifted = theta + step_theta / 2
    wrap = shifted >= 180.0
    shifted = np.where(wrap, shifted - 180.0, shifted)
    x = np.where(wrap, -x, x)
    finite = np.isfinite(theta) & np.isfinite(x)
    i = np.floor(np.where(finite, shifted, 0.0) / step_theta).astype(np.int64)
    j = np.rint((np.where(finite, x, 0.0) + extent) / step_x).astype(np.int64)
    return i, j, finite & (j >= 0) & (j < n_x)


def _flat_bin(theta, x, absorption, *, n_theta: int, n_x: int, extent: float):
    # each ray's flat bin i·n_x + j, −1 off the grid or without a finite absorption
    i, j, on_grid = bin_index(theta, x, n_theta=n_theta, n_x=n_x, extent=extent)
    return np.where(on_grid & np.isfinite(absorption), i * n_x + j, -1).astype(_index_dtype(n_theta * n_x))


def _index_dtype(bins: int) -> np.dtype:
    return np.dtype(np.int32 if bins < 2**31 else np.int64)


def _bin_kernel(index, absorption, *, n_theta: int, n_x: int):
    # (slice block, angle, col) flat bins and absorption -> (slice block, n_theta, n_x) means and counts
    slices, size = index.shape[0], n_theta * n_x
    ok = index >= 0
    where = (index + np.arange(slices).reshape(-1, 1, 1) * size)[ok]  # slice k's bins at k·size
    sums = np.bincount(where, absorption[ok].astype(np.float64), minlength=slices * size)
    counts = np.bincount(where, minlength=slices * size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    shape = (slices, n_theta, n_x)
    return np.stack([mean.reshape(shape), counts.reshape(shape)], axis=-1)


#: bytes per binning task, at most: its rays (flat bin and absorption) or its sums and counts (16 bytes a bin),
#: whichever is larger. The rays move from the capture's angle chunks to chunks of whole slices (every angle and
#: column of a few rows), the one all-to-all step of the volume's graph: larger tasks make fewer pieces (one per
#: angle chunk and row chunk; one row per task made 1.3 M at 1600 × 1200 × 360)
BIN_CHUNK_BYTES = 64 * 2**20

#: how the rays move from angle chunks to slice chunks, on any scheduler: dask's task-based rechunk, whose pieces are
#: managed memory a worker can spill (distributed's p2p stalled a 4 GB worker at 1600 × 1200 × 360: docs/results.md)
RAYS_RECHUNK = "tasks"


def rows_per_bin_task(rays: xr.Dataset, bins: int) -> int:
    """Slices (camera rows) per binning task: as many as keep a task within :data:`BIN_CHUNK_BYTES`."""
    per_ray = _index_dtype(bins).itemsize + rays["absorption"].dtype.itemsize
    per_row = max(rays.sizes["angle"] * rays.sizes["col"] * per_ray, bins * 16)
    return int(np.clip(BIN_CHUNK_BYTES // per_row, 1, rays.sizes["row"]))


def _bin_precheck(settings) -> list[str]:
    """One slice's binned sums and counts, (n_theta, n_x, 2) float64, the largest array of the binning (bins
    derived from the capture are checked when the stage runs)."""
    if settings.n_theta is None or settings.n_x is None:
        return []
    return _bin_memory(settings.n_theta, settings.n_x)


def _bin_memory(n_theta: int, n_x: int) -> list[str]:
    return memory_problems(n_theta * n_x * 2 * 8, f"one slice's binned sinogram ({n_theta:,} × {n_x:,} bins, "
                           "sums and counts in float64)", fix="lower n_theta or n_x")


#: ``filled_fraction`` below this: the engine logs the advice to bin coarser. Measured on simulated cylinders
#: (perspective and orthographic, 1–4° views): bins at the capture's own sampling fill 0.98–0.99; X bins of half
#: the pixel pitch 0.934–0.948; θ bins of half the view step 0.53–0.68 (benchmarks/sinogram_bins.py).
FILLED_ADVICE = 0.97


@stage("bin_sinogram", kind=SINOGRAM, precheck=_bin_precheck)
def bin_sinogram(rays: xr.Dataset, /, *, n_theta: Bins | None = None, n_x: Bins | None = None,
                 x_extent: Positive | None = None) -> xr.Dataset:
    """Bin rays into a (θ, X) sinogram per slice, with the mask of observed bins (lazy, per slice).

    The default bins follow the capture's sampling: one θ bin per step between views, one X bin per pixel
    pitch at the axis (:func:`capture_bins`). Finer bins leave empty bins between observed ones, which the
    coverage and the reconstructions count as missing data: ``filled_fraction`` measures them, and the engine
    logs advice with the capture's bin counts when it is below 97 %.

    Parameters
    ----------
    rays : xr.Dataset
        A ``rays`` store (``align_paths``): ``theta`` [degree, in [0, 180)], ``x`` and ``absorption`` (NaN: dropped)
        over (angle, row, col), angle the stage angle [degree]; attrs ``x_extent`` (used when x_extent is None),
        ``length_unit`` and the camera's (for the default n_x).
    n_theta : int or None
        Bins over [0°, 180°), at least 2; None: one per step between views, 180° / step.
    n_x : int or None
        Bins over [−x_extent, x_extent], at least 2; None: one per pixel pitch at the axis, 2·x_extent / pitch + 1.
    x_extent : float or None
        Half-width of the X grid [length unit]; None: the camera's view half-width at the axis.

    Returns
    -------
    xr.Dataset
        A ``sinogram`` cube: ``absorption`` [1] over (slice, theta, x), the mean of the rays in each bin, and
        ``observed`` (True where a ray fell), lazily per slice.

    References
    ----------
    Thesis §4.2.2 Radon transform; §4.2.6 Light path alignment.
    """
    require_variables(rays, ("theta", "x", "absorption"), "bin_sinogram")
    extent = float(x_extent if x_extent is not None else rays.attrs.get("x_extent", np.nan))
    if not np.isfinite(extent) or extent <= 0:
        raise StageError(Problem("the X extent of the grid is unknown", fix="set x_extent"))
    step, pitch = capture_sampling(rays)
    supported = capture_bins(step, pitch, extent)
    n_theta = supported[0] if n_theta is None else n_theta
    n_x = supported[1] if n_x is None else n_x
    if n_theta < 2 or n_x < 2:
        raise StageError(Problem(f"n_theta = {n_theta}, n_x = {n_x}; both must be at least 2"))
    if problems := _bin_memory(n_theta, n_x):
        raise StageError([Problem(p) for p in problems])
    _warn_finer_than_views(n_theta, step)
    _warn_finer_than_pixels(n_x, extent, pitch, supported[1])
    # the flat bin of each ray where the rays are (their angle chunks), so that only it and the absorption move
    grid = {"n_theta": n_theta, "n_x": n_x}
    parts = rays[["theta", "x", "absorption"]].drop_vars("z", errors="ignore")
    index = xr.apply_ufunc(_flat_bin, parts["theta"], parts["x"], parts["absorption"], dask="parallelized",
                           output_dtypes=[_index_dtype(n_theta * n_x)], kwargs=grid | {"extent": extent})
    whole = {"angle": -1, "col": -1, "row": rows_per_bin_task(parts, n_theta * n_x)}
    with dask.config.set({"array.rechunk.method": RAYS_RECHUNK}):  # read as the graph is built
        moved = index.chunk(whole), parts["absorption"].chunk(whole)
    both = xr.apply_ufunc(  # one stacked output (see stages.tomography.paths on dask and multi-output graphs)
        _bin_kernel, *moved, input_core_dims=[["angle", "col"]] * 2,
        output_core_dims=[["theta", "x", "field"]], dask="parallelized", output_dtypes=[np.float64],
        dask_gufunc_kwargs={"output_sizes": {"theta": n_theta, "x": n_x, "field": 2}}, kwargs=grid)
    # (apply_ufunc gives its outputs the first input's attrs, θ's: dropped, the kind's metadata set below)
    mean = both.isel(field=0, drop=True).drop_attrs(deep=False)
    count = both.isel(field=1, drop=True).astype(np.int64).drop_attrs(deep=False)
    unit = rays.attrs.get("length_unit", "px")
    coords = {"theta": ("theta", np.arange(n_theta) * 180.0 / n_theta, {"units": "degree"}),
              "x": ("x", np.linspace(-extent, extent, n_x), {"units": unit})}
    out = xr.Dataset({"absorption": mean, "observed": count > 0, "count": count}, coords=coords)
    out["observed_fraction"] = observed_share(out["observed"])
    out["filled_fraction"] = filled_share(out["observed"], supported)
    if "z" in rays.coords:  # each slice's height, as align_paths gave it (not chunked: a coordinate to compare)
        out = out.assign_coords(z=rays["z"].variable)
    out = out.rename({"row": "slice"})
    if tuple(out["absorption"].dims) != ("slice", "theta", "x"):
        out = out.transpose("slice", "theta", "x")
    return SINOGRAM.label(out.assign_attrs(geometry_attrs(rays.attrs) | {
        "theta_step_deg": 180.0 / n_theta, "x_step": 2 * extent / (n_x - 1),
        "x_extent": extent, "capture_n_theta": supported[0], "capture_n_x": supported[1]}))


def capture_sampling(rays: xr.Dataset) -> tuple[float | None, float | None]:
    """How finely a capture samples the sinogram: the step between views [degree] (None without two views) and one
    pixel's size at the axis [length unit] (perspective: camera_distance / focal_length_px; orthographic:
    pixel_size; None without a camera in the attrs)."""
    step = view_step_deg(rays["angle"].values) if "angle" in rays.coords else None
    try:
        pitch = RigGeometry.from_attrs(rays.attrs, where="bin_sinogram: rays").camera.axis_pixel_size
    except StageError:
        pitch = None
    return step, pitch


def capture_bins(step: float | None, pitch: float | None, extent: float) -> tuple[int, int]:
    """The bins a capture's sampling fills: (n_theta, n_x) = (180° / view step, 2·extent / pitch + 1).

    At a fixed X consecutive views' rays lie one view step apart in θ; at a fixed θ neighbouring pixels' rays lie
    about half an exit-point spacing apart in X, which is at least one pitch. Measured on simulated cylinders:
    these bins leave 1–2 % of the bins between observed ones empty; bins half as wide in X 5–7 %, in θ 32–47 %
    (``benchmarks/sinogram_bins.py``).
    Without a view step (one view) n_theta is 180; without a pitch n_x is 256.

    >>> capture_bins(4.0, 0.1, 8.0)
    (45, 161)
    """
    n_theta = max(2, int(np.floor(180.0 / step + 1e-6))) if step else 180
    return n_theta, (max(2, int(np.rint(2 * extent / pitch)) + 1) if pitch else 256)


def _warn_finer_than_pixels(n_x: int, extent: float, pitch: float | None, supported: int) -> None:
    """X bins narrower than half a pixel pitch at the axis: neighbouring pixels' rays skip bins."""
    width = 2 * extent / (n_x - 1)
    if pitch is not None and width < 0.5 * pitch * (1 - 1e-6):
        warnings.warn(f"bin_sinogram: n_x = {n_x} makes X bins of {width:.3g}, less than half the {pitch:.3g} a "
                      f"pixel spans at the axis: neighbouring pixels' rays skip bins, holes that the coverage and "
                      f"the reconstructions count as missing data; bin n_x ≤ {supported}", UserWarning, stacklevel=3)


def filled_share(observed: xr.DataArray, supported: tuple[int, int]) -> xr.DataArray:
    """The share of bins between observed bins that hold a ray (a report; the engine advises below 97 %).

    A bin lies between observed bins when both its X neighbours or both its θ neighbours hold a ray (θ wraps
    to 0° with X mirrored, the same line). Empty ones are holes in the sampling: bins finer than the capture's
    sampling, or rays dropped between kept ones (the rays' ``reason``)."""
    import dask.array as da  # on computing, not on reading a workflow

    o = observed.transpose(..., "theta", "x").data
    xp = da if isinstance(o, da.Array) else np
    pad_x = xp.pad(o, [(0, 0)] * (o.ndim - 1) + [(1, 1)], constant_values=False)
    # θ neighbours, wrapping: the bin before θ = 0 is the last θ bin with X reversed, and vice versa
    before = xp.concatenate([o[..., -1:, ::-1], o[..., :-1, :]], axis=-2)
    after = xp.concatenate([o[..., 1:, :], o[..., :1, ::-1]], axis=-2)
    between = (pad_x[..., :-2] & pad_x[..., 2:]) | (before & after)
    share = (o & between).sum() / xp.maximum(between.sum(), 1)
    n_theta, n_x = supported
    return usable_share(
        xr.DataArray(share), floor=0.0, label="filled", advise_below=FILLED_ADVICE,
        what="sinogram bins between observed bins that hold a ray",
        fix=f"empty bins among observed ones are missing data to the coverage and the reconstructions: bins finer "
        f"than the capture's sampling (it fills n_theta ≤ {n_theta}, n_x ≤ {n_x}, the defaults) or rays dropped "
        "between kept ones (see the rays' reason)")


def view_step_deg(angles) -> float | None:
    """The typical step between the stage angles of the views [degree] (median gap of the distinct angles mod
    360°, the wrap included); None for fewer than two views."""
    unique = np.unique(np.mod(np.asarray(angles, float), 360.0))
    if unique.size < 2:
        return None
    return float(np.median(np.diff(np.append(unique, unique[0] + 360.0))))


def _warn_finer_than_views(n_theta: int, step: float | None) -> None:
    """Bins finer than the views: a ray's θ is its view's angle plus a pixel's offset, so at a fixed X only one θ
    bin in (view step / bin width) holds rays and the sinogram is a checkerboard of unobserved bins that are only
    binning (measured: 4° views into 180 bins observed 0.53 of the bins, into 45 bins 0.94)."""
    width = 180.0 / n_theta
    if step is not None and width < step * (1 - 1e-6):
        warnings.warn(f"bin_sinogram: n_theta = {n_theta} makes {width:.3g}° bins, finer than the {step:.3g}° "
                      f"between views: at a fixed X only about one θ bin in {step / width:.2g} holds a ray, a "
                      "checkerboard of unobserved bins that the coverage and the reconstructions count as missing "
                      f"data; bin n_theta ≤ {int(np.floor(180.0 / step + 1e-6))} or capture more angles",
                      UserWarning, stacklevel=3)


#: floor of ``observed_fraction``: the demo observes 72 % of its bins; one or two views under 2 %
OBSERVED_FLOOR = 0.05


def observed_share(observed: xr.DataArray) -> xr.DataArray:
    """The share of sinogram bins holding a ray, as a usable share (:mod:`selpath.pipeline.quality`)."""
    return usable_share(observed.mean(), floor=OBSERVED_FLOOR, what="sinogram bins holding a ray",
                        fix="too few views or rays for a reconstruction: capture more angles, check the earlier "
                        "steps' shares, or bin coarser (n_theta, n_x)")
