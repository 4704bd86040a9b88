"""Reconstruction (§4.3): FBP and the constrained TV optimisation, per slice, from a binned sinogram.

Both stages reconstruct on an ``n × n`` grid over ``[−x_extent, x_extent]²`` of the object frame (DESIGN §8;
``y`` grows with the row index) and treat the sinogram's bins in three explicit classes:

* **observed**: the ``observed`` mask; their absorption is data;
* **known zero**: rays that miss the object's contour (the visual hull) entirely carry no absorption, so
  their value is 0 even though no camera pixel saw them;
* **missing**: the rest (the missing areas of Fig. 14). FBP fills them by a stated rule (``fill``); the
  optimisation leaves them out of its data term (Eq. 24).

Outputs carry ``reliable``: cells every one of whose rays (nearest bin, every θ) is observed or known —
the area inside the blue line of Fig. 21, where FBP is exact up to discretisation.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np
import xarray as xr

from selpath.geometry.rig import geometry_attrs
from selpath.geometry.shapes import cells_inside, support_function
from selpath.pipeline.constraints import Count, NonNegative, Positive, memory_problems
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import LENGTH_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import Dtype, MaxIter, require_variables
from selpath.stages.tomography import _tv_settings as tv
from selpath.stages.tomography._filters import ramp_filter
from selpath.stages.tomography._ome import ome_attrs
from selpath.stages.tomography.hull import contours
from selpath.stages.tomography.sinogram import observed_share

if TYPE_CHECKING:  # the solvers and projectors (JAX) are imported when a reconstruction runs, not on import
    from selpath.stages.tomography._admm import TVADMM
    from selpath.stages.tomography._projector import Geometry

_SIGMA = "1/{length}"
RECONSTRUCTION = CubeKind(
    name="reconstruction",
    description="absorption coefficient σ per slice",
    variables={
        "sigma": Variable(("y", "x"), description="absorption coefficient per unit length", units=_SIGMA,
                          long_name="absorption coefficient σ"),
        "reliable": Variable(("y", "x"), required=False, units=None,
                             long_name="cell every ray through which is observed or known"),
        "sigma_max": Variable(("y", "x"), required=False, units=_SIGMA,
                              long_name="upper bound σ_max of the box constraint"),
        "iterations": Variable((), required=False, units="1", long_name="ADMM iterations run"),
        "converged": Variable((), required=False, units=None, long_name="ADMM met its tolerance"),
        "objective": Variable(("iteration",), required=False, units="1",
                              long_name="objective of Eq. 20 per ADMM iteration (NaN after the stop)"),
        "primal_residual": Variable(("iteration",), required=False, units="1",
                                    long_name="relative primal residual per ADMM iteration (NaN after the stop)"),
        "dual_residual": Variable(("iteration",), required=False, units="1",
                                  long_name="relative dual residual per ADMM iteration (NaN after the stop)"),
        # reconstruct_scattering's (selpath.stages.tomography.scattering): L-BFGS-B's end and the bundles' sizes
        "final_objective": Variable((), required=False, units="1", long_name="objective at the stop"),
        "paths_per_bin": Variable((), required=False, units="1", long_name="median distinct paths per observed bin"),
        "bins_without_paths": Variable((), required=False, units="1",
                                       long_name="observed bins no walk reached (left out of the fit)"),
    },
    coord_units={"y": LENGTH_UNITS, "x": LENGTH_UNITS},
    batch_dims=("slice",),
)


def image_problems(n_pixels: int | None) -> list[str]:
    """One slice's n × n image, where the settings give n (cell-centre grids are float64)."""
    if n_pixels is None:
        return []  # the sinogram's X bins: known only when it is computed
    return memory_problems(n_pixels * n_pixels * 8, f"one {n_pixels:,} × {n_pixels:,} px slice (float64)",
                           fix="lower n_pixels")


def _image_precheck(settings) -> list[str]:
    return image_problems(settings.n_pixels)


def grid_geometry(sinogram: xr.Dataset, n_pixels: int | None, method: str = "joseph") -> Geometry:
    """The projector geometry of a sinogram: its (θ, X) grid and an n × n image over ±x_extent."""
    x = sinogram["x"].values
    extent = float(sinogram.attrs.get("x_extent", max(abs(x[0]), abs(x[-1]))))
    from selpath.stages.tomography._projector import Geometry

    return Geometry.from_grids(sinogram["theta"].values, x, int(n_pixels or len(x)), extent, method)


def support_mask(vertices: np.ndarray | None, geometry: Geometry) -> np.ndarray:
    """True on cells whose centre lies inside the convex contour (counter-clockwise vertices; edges included, see
    :func:`~selpath.geometry.shapes.cells_inside`); all True when there is no contour."""
    if vertices is None or len(vertices) < 3:
        return np.ones((geometry.n, geometry.n), dtype=bool)
    return cells_inside(vertices, geometry.centres)


def known_zero(vertices: np.ndarray | None, geometry: Geometry) -> np.ndarray:
    """(θ, X) bins whose ray misses the contour: X above its support h(θ) or below −h(θ + 180°)."""
    if vertices is None or len(vertices) < 3:
        return np.zeros(geometry.shape, dtype=bool)
    theta, x = np.asarray(geometry.theta_deg), np.asarray(geometry.x)
    plus, minus = support_function(vertices, theta), support_function(vertices, theta + 180.0)
    return (x[None, :] > plus[:, None]) | (x[None, :] < -minus[:, None])


def reliable_cells(known: np.ndarray, geometry: Geometry) -> np.ndarray:
    """Cells whose nearest bin is known (observed or known zero) at every θ: (n, n) from one (θ, X) mask, (S, n, n)
    from a batch."""
    from selpath.stages.tomography._projector import any_nearest

    return ~any_nearest(geometry, ~np.asarray(known, bool))


def upper_bound(absorption: np.ndarray, observed: np.ndarray, geometry: Geometry, slack: float = 0.0) -> np.ndarray:
    """σ_max of Eq. 26–28: per cell, the least over θ of what the rays at that θ allow it.

    A ray crossing a cell of size Δ over a length ℓ = Δ/|a| (|a| = max(|cos θ|, |sin θ|), the step of the
    projector; Δ for the binary r_ij) cannot absorb less than σ·ℓ there, so σ ≤ A/ℓ. At each θ the cell
    is bounded by the largest absorption among the bins within its shadow (half-width Δ(|cos θ| + |sin θ|)/2)
    widened by one bin, all of which must be observed: a cell only partly covered by an inclusion is then
    never clipped by a ray that happens to miss the inclusion. The thesis's r_ij = 1 is ℓ = 1 (σ per
    cell). ``slack`` [absorption] loosens the bound for noisy data. Cells without such rays are unbounded.
    """
    t = np.deg2rad(np.asarray(geometry.theta_deg))
    x = np.asarray(geometry.x)
    step, cell = (x[-1] - x[0]) / (len(x) - 1), geometry.cell
    c = geometry.centres
    data = np.where(observed, absorption + slack, np.inf)
    best = np.full((geometry.n, geometry.n), np.inf)
    for i, angle in enumerate(t):
        cos, sin = abs(np.cos(angle)), abs(np.sin(angle))
        length = cell if geometry.method == "binary" else cell / max(cos, sin)
        reach = cell * (cos + sin) / 2 + step
        proj = c[None, :] * np.cos(angle) + c[:, None] * np.sin(angle)
        first = np.ceil((proj - reach - x[0]) / step - 1e-9).astype(np.int64)
        last = np.floor((proj + reach - x[0]) / step + 1e-9).astype(np.int64)
        inside = (first >= 0) & (last < len(x))
        worst = np.zeros_like(proj)
        for offset in range(int(np.ceil(2 * reach / step)) + 1):
            j = np.clip(first + offset, 0, len(x) - 1)
            worst = np.where(first + offset <= last, np.maximum(worst, data[i, j]), worst)
        best = np.minimum(best, np.where(inside, worst / length, np.inf))
    return np.maximum(best, 0.0)


def _fill_missing(absorption: np.ndarray, known: np.ndarray, fill: str) -> np.ndarray:
    """Unknown bins of (…, θ, X) sinograms: 0 (``zero``), or (``linear``) interpolated along X between the nearest
    known bins on either side, 0 beyond the outermost known bin (``np.interp(…, left=0, right=0)``, row by row)."""
    values = np.where(known, np.nan_to_num(absorption), 0.0)
    if fill == "zero":
        return values
    count = values.shape[-1]
    index = np.arange(count)
    before = np.maximum.accumulate(np.where(known, index, -1), axis=-1)  # nearest known bin at or below
    after = np.flip(np.minimum.accumulate(np.flip(np.where(known, index, count), axis=-1), axis=-1), axis=-1)
    between = ~known & (before >= 0) & (after < count)
    low = np.take_along_axis(values, np.clip(before, 0, count - 1), axis=-1)
    high = np.take_along_axis(values, np.clip(after, 0, count - 1), axis=-1)
    weight = (index - before) / np.maximum(after - before, 1)
    return np.where(between, low + weight * (high - low), values)


def _slice_inputs(sinogram: xr.Dataset, hull: xr.Dataset | None, geometry: Geometry):
    """Per slice: absorption, observed, hull vertices (or None)."""
    absorption = sinogram["absorption"].values
    observed = sinogram["observed"].values & np.isfinite(absorption)
    vertices = None
    if hull is not None:
        vertices = hull["vertices"].values, hull["n_vertices"].values
    for k in range(absorption.shape[0]):
        polygon = None
        if vertices is not None and vertices[1][k] >= 3:
            polygon = vertices[0][k, : vertices[1][k]]
        yield absorption[k], observed[k], polygon


def check_inputs(sinogram: xr.Dataset, hull: xr.Dataset | None, name: str) -> None:
    """Raise a ``StageError`` naming stage ``name`` unless ``sinogram`` has ``absorption`` and ``observed`` over a
    ``slice`` dim and ``hull`` (if given) has a contour for each of its slices."""
    require_variables(sinogram, ("absorption", "observed"), name)
    if "slice" not in sinogram.dims:
        raise StageError(Problem(f"{name}: the sinogram has no slice dim", fix="bin it with bin_sinogram"))
    if hull is not None:
        contours(hull, sinogram["slice"], name)  # raises naming the sinogram's slices the hull lacks


def reconstruction_store(sinogram: xr.Dataset, geometry: Geometry, variables: dict, attrs: dict) -> xr.Dataset:
    """A ``reconstruction`` store of ``variables`` (``sigma`` over (slice, y, x) and per-slice numbers) on
    ``geometry``'s grid in the sinogram's length unit, with its slices, heights (and OME-Zarr attrs where they form a
    grid), observed share and rig attrs, plus ``attrs``."""
    unit = sinogram["x"].attrs.get("units", sinogram.attrs.get("length_unit", "px"))
    centres = geometry.centres
    coords = {"y": ("y", centres, {"units": unit}), "x": ("x", centres, {"units": unit}),
              "slice": sinogram["slice"]}
    volume = {}
    if "z" in sinogram.coords:  # each slice's height (bin_sinogram, simulate_sinogram)
        coords["z"] = sinogram["z"]
        volume = ome_attrs(sinogram["z"].values, centres, centres, unit)
    out = xr.Dataset(variables, coords=coords)
    out["observed_fraction"] = observed_share(sinogram["observed"])
    return RECONSTRUCTION.label(out.assign_attrs(geometry_attrs(sinogram.attrs) | {"cell_size": geometry.cell}
                                                 | volume | attrs))


def fbp_slice(absorption: np.ndarray, known: np.ndarray, support: np.ndarray, geometry: Geometry, *,
              filter_name: str = "ram-lak", fill: str = "zero", dtype: str = "float32") -> np.ndarray:
    """FBP of (θ, X) sinograms, one or a (S, θ, X) batch: unknown bins filled (``fill``), ramp-filtered,
    back-projected, and zero outside ``support`` ((n, n) or (S, n, n))."""
    import jax.numpy as jnp

    from selpath.stages.tomography._projector import backproject

    values = _fill_missing(absorption, known, fill)
    filtered = ramp_filter(values, float(geometry.x[1] - geometry.x[0]), filter_name)
    return np.where(support, np.asarray(backproject(geometry, jnp.asarray(filtered, dtype))), 0.0)


def _fbp_block(block: xr.Dataset, *, geometry: Geometry, filter_name: str, fill: str, dtype: str) -> xr.Dataset:
    import jax

    hull = block if "vertices" in block else None
    absorption, observed, polygons = zip(*_slice_inputs(block, hull, geometry), strict=True)
    known = np.array([o | known_zero(p, geometry) for o, p in zip(observed, polygons, strict=True)])
    support = np.array([support_mask(p, geometry) for p in polygons])
    with jax.enable_x64(dtype == "float64"):
        sigma = fbp_slice(np.array(absorption), known, support, geometry, filter_name=filter_name, fill=fill,
                          dtype=dtype)
    dims = ("slice", "y", "x")
    reliable = reliable_cells(known, geometry) & support
    return xr.Dataset({"sigma": (dims, sigma.astype(dtype)), "reliable": (dims, reliable)},
                      coords={"slice": block["slice"]})


def _template(inputs: xr.Dataset, geometry: Geometry, variables: dict[str, tuple[tuple[str, ...], type]],
              extra: dict[str, int] | None = None) -> xr.Dataset:
    """Lazy zeros shaped like the blocks' results, chunked along slice as ``inputs`` (from :func:`_blocks`)."""
    import dask.array as da

    sizes = {"slice": inputs.sizes["slice"], "y": geometry.n, "x": geometry.n} | (extra or {})
    chunks = inputs.chunksizes["slice"]
    data = {name: (dims, da.zeros(tuple(sizes[d] for d in dims), dtype=dtype,
                                  chunks=tuple(chunks if d == "slice" else sizes[d] for d in dims)))
            for name, (dims, dtype) in variables.items()}
    return xr.Dataset(data, coords={"slice": inputs["slice"]})


#: slices per reconstruction task, at least (larger slice chunks of the input are kept): FBP back-projects a batch in
#: one compiled loop, the optimisation solves it as one batch (with the system matrix from
#: :data:`selpath.stages.tomography._admm.DEVICE_BATCH` slices on)
SLICE_BATCH = 16


def _blocks(sinogram: xr.Dataset, hull: xr.Dataset | None) -> xr.Dataset:
    """The sinogram (and the hull's contours) chunked whole in θ and X, in slice chunks of at least
    :data:`SLICE_BATCH` slices."""
    inputs = sinogram[["absorption", "observed"]]
    batch = max([SLICE_BATCH, *inputs.chunksizes.get("slice", ())])
    inputs = inputs.chunk({"theta": -1, "x": -1, "slice": batch})
    if hull is not None:
        shell = contours(hull, sinogram["slice"], "reconstruction")
        inputs = xr.merge([inputs, shell.chunk({"slice": inputs.chunksizes["slice"]})], join="exact",
                          compat="override", combine_attrs="drop_conflicts")
    return inputs.assign_attrs({})


@stage("fbp", kind=RECONSTRUCTION, precheck=_image_precheck)
def fbp(sinogram: xr.Dataset, hull: xr.Dataset | None = None, /, *, n_pixels: Count | None = None,
        filter: Literal["ram-lak", "shepp-logan", "cosine", "hamming", "hann"] = "ram-lak",  # noqa: A002
        fill: Literal["zero", "linear"] = "zero", dtype: Dtype = "float32") -> xr.Dataset:
    """Filtered back-projection per slice (lazy, one task per slice chunk).

    Parameters
    ----------
    sinogram : xr.Dataset
        A ``sinogram`` store (``bin_sinogram`` or ``simulate_sinogram``): ``absorption``, ``observed`` over (slice,
        theta, x), θ [degree], X [length unit]; attr ``x_extent`` (else the outermost X) spans the image.
    hull : xr.Dataset or None
        A ``hull`` store (``visual_hull``) holding the sinogram's slices, in X's length unit: σ = 0 outside it, and
        bins whose ray misses it are known zeros; None: no support, every unobserved bin is missing.
    n_pixels : int or None
        Image size n (n × n over ±x_extent); None: the sinogram's number of X bins.
    filter : str
        Ramp filter window.
    fill : str
        Missing bins: ``zero`` (as the thesis) or ``linear`` (interpolated along X between known bins).
        Bins whose ray misses the hull are known zeros either way.
    dtype : str
        ``float32`` or ``float64``.

    Returns
    -------
    xr.Dataset
        A ``reconstruction`` cube: ``sigma`` over (slice, y, x) [per length unit], zero outside the hull, lazily per
        slice chunk.

    References
    ----------
    Thesis §4.2.2 Radon transform; §4.3 Reconstruction.
    """
    check_inputs(sinogram, hull, "fbp")
    geometry = grid_geometry(sinogram, n_pixels)
    inputs = _blocks(sinogram, hull)
    template = _template(inputs, geometry, {"sigma": (("slice", "y", "x"), np.dtype(dtype)),
                                              "reliable": (("slice", "y", "x"), np.dtype(bool))})
    out = xr.map_blocks(_fbp_block, inputs, kwargs={"geometry": geometry, "filter_name": filter, "fill": fill,
                                                    "dtype": dtype}, template=template)
    return reconstruction_store(sinogram, geometry, {"sigma": out["sigma"], "reliable": out["reliable"]},
                                {"method": "fbp", "filter": filter, "fill": fill})


def _tv_block(block: xr.Dataset, *, solver: TVADMM, slack: float, bound: str, dtype: str) -> xr.Dataset:
    import jax
    import jax.numpy as jnp

    geometry = solver.geometry
    hull = block if "vertices" in block else None
    sinograms, masks, uppers, known, supports = [], [], [], [], []
    with jax.enable_x64(dtype == "float64"):
        for absorption, observed, polygon in _slice_inputs(block, hull, geometry):
            support = support_mask(polygon, geometry)
            limit = upper_bound(absorption, observed, geometry, slack) if bound == "physical" else np.inf
            uppers.append(np.where(support, np.minimum(limit, np.finfo(dtype).max), 0.0))
            sinograms.append(np.where(observed, absorption, 0.0))
            masks.append(observed)
            known.append(observed | known_zero(polygon, geometry))
            supports.append(support)
        solution = solver.solve_slices(jnp.asarray(np.array(sinograms), dtype), jnp.asarray(np.array(masks)),
                                       jnp.asarray(np.array(uppers), dtype))
    dims, hist, stats = ("slice", "y", "x"), ("slice", "iteration"), solution.stats
    return xr.Dataset(
        {"sigma": (dims, solution.value.astype(dtype)), "sigma_max": (dims, np.array(uppers, dtype=dtype)),
         "reliable": (dims, reliable_cells(np.array(known), geometry) & np.array(supports)),
         "iterations": ("slice", stats["iterations"].astype(np.int64)),
         "converged": ("slice", solution.converged.astype(bool)),
         **{name: (hist, stats[name].astype(dtype)) for name in ("objective", "primal_residual", "dual_residual")}},
        coords={"slice": block["slice"]})


@stage("reconstruct_tv", kind=RECONSTRUCTION, precheck=_image_precheck)
def reconstruct_tv(sinogram: xr.Dataset, hull: xr.Dataset | None = None, /, *,
                   tv_weight: NonNegative = tv.TV_WEIGHT, n_pixels: Count | None = None,
                   bound: Literal["physical", "nonnegative"] = "physical", bound_slack: NonNegative = 0.0,
                   rho: Positive = tv.RHO, tol: Positive = tv.TOL,
                   max_iter: MaxIter = tv.MAX_ITER, cg_steps: Count = tv.CG_STEPS,
                   projector: Literal["joseph", "binary"] = "joseph", dtype: Dtype = "float32") -> xr.Dataset:
    """Constrained TV reconstruction of Eq. 20 by ADMM, per slice (lazy; slices of a chunk are batched).

    Data fidelity on observed rays only (Eq. 24), box 0 ≤ σ ≤ σ_max (Eq. 25–29; σ = 0 outside the hull)
    and isotropic TV (Eq. 30). Besides σ it returns σ_max, the iterations, whether each slice converged,
    and per-iteration objective and relative primal/dual residuals (NaN after the stop).

    Parameters
    ----------
    sinogram : xr.Dataset
        A ``sinogram`` store (``bin_sinogram`` or ``simulate_sinogram``): ``absorption``, ``observed`` over (slice,
        theta, x), θ [degree], X [length unit]; attr ``x_extent`` (else the outermost X) spans the image.
    hull : xr.Dataset or None
        A ``hull`` store (``visual_hull``) holding the sinogram's slices, in X's length unit: σ_max = 0 outside it,
        and ``reliable`` counts bins whose ray misses it as known; None: no support.
    tv_weight : float
        λ of Eq. 20 [absorption² per (1/length)·cell].
    n_pixels : int or None
        Image size n; None: the sinogram's number of X bins.
    bound : str
        ``physical``: σ_max of Eq. 26–28; ``nonnegative``: σ ≥ 0 only.
    bound_slack : float
        Added to every observed absorption before the bound is taken (noisy data) [absorption].
    rho : float
        ADMM penalty relative to ‖MR‖² [1].
    tol : float
        Relative primal and dual residual at which to stop [1].
    max_iter : int
        Iteration cap, in [1, 1 000 000].
    cg_steps : int
        Conjugate-gradient steps per σ-update (warm-started).
    projector : str
        ``joseph`` (interpolating) or ``binary`` (the thesis's r_ij of Eq. 22).
    dtype : str
        ``float32`` or ``float64``.

    Returns
    -------
    xr.Dataset
        A ``reconstruction`` cube: ``sigma`` over (slice, y, x) [per length unit], zero outside the hull, with the
        solver's ``converged``, ``iterations`` and residual histories per slice, lazily.

    References
    ----------
    Thesis §4.3.1 Formulation as an optimization problem.
    """
    check_inputs(sinogram, hull, "reconstruct_tv")
    if tv_weight < 0 or rho <= 0 or tol <= 0 or max_iter < 1 or cg_steps < 1 or bound_slack < 0:
        raise StageError(Problem("tv_weight and bound_slack must be >= 0; rho, tol > 0; max_iter, cg_steps >= 1"))
    geometry = grid_geometry(sinogram, n_pixels, projector)
    from selpath.stages.tomography._admm import TVADMM

    solver = TVADMM(geometry, tv_weight=tv_weight, rho=rho, tol=tol, max_iter=max_iter, cg_steps=cg_steps)
    inputs = _blocks(sinogram, hull)
    image, flag, hist = ("slice", "y", "x"), ("slice",), ("slice", "iteration")
    template = _template(inputs, geometry, {
        "sigma": (image, np.dtype(dtype)), "sigma_max": (image, np.dtype(dtype)), "reliable": (image, np.dtype(bool)),
        "iterations": (flag, np.dtype(np.int64)), "converged": (flag, np.dtype(bool)),
        "objective": (hist, np.dtype(dtype)), "primal_residual": (hist, np.dtype(dtype)),
        "dual_residual": (hist, np.dtype(dtype))}, {"iteration": max_iter})
    out = xr.map_blocks(_tv_block, inputs, kwargs={"solver": solver, "slack": bound_slack, "bound": bound,
                                                   "dtype": dtype}, template=template)
    return reconstruction_store(sinogram, geometry, {name: out[name] for name in template.data_vars},
                                {"method": "admm_tv", "tv_weight": tv_weight, "bound": bound, "tol": tol,
                                 "max_iter": max_iter})
