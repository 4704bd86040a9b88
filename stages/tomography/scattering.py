"""Tomography through scattering (#27, thesis §4.4.4 and §6.1): a forward model that accounts for σ_s.

The shortest-path model reads each lit pixel as one straight chord from the light's entry point ``p_l`` to the exit
point ``p_c`` it sees. In a scattering medium the light that reaches ``p_c`` took many paths, and an absorber that
blocks the chord is partly walked around, so the straight model under-reads it (about half of σ = 10 at σ_s = 1 in
docs/results.md). Here each sinogram bin is a **bundle of paths**:

* Photon random walks are traced from ``p_l`` in the homogeneous object (the hull's contour extruded in z, the
  scattering coefficient σ_s, isotropic phase function, Lambertian launch through the skin), exactly as in the
  reference object, which has the same σ_s and no absorber: its frames are the sum over these paths' exits.
* A walk belongs to the sinogram bin of the ray of the camera pixel that sees its exit point, where that pixel is
  on the slice's row (within ``row_band`` rows: the walks that leave just above or below the slice, for statistics)
  and holds a ray; each bin keeps up to ``paths_per_bin`` walks.
* The target's frame weighs each path by exp(−∫σ) along it, so the absorption the pipeline measures,
  A = log I_reference − log I_target, is modelled as ``A(σ) = −log( mean over the bundle of exp(−∫_path σ) )``:
  nonlinear in σ, smooth, and differentiable in JAX. ∫σ along a path is a sum over its samples (``spacing`` cells
  apart) of σ interpolated bilinearly on the image grid, times the 3-D length each stands for (σ does not vary with
  height within a slice: a prism).

The reconstruction minimises ½ Σ (A_b(σ) − a_b)² over the observed bins + λ TV_ε(σ) over 0 ≤ σ ≤ σ_max (0 outside
the hull) by L-BFGS-B (scipy, with JAX's gradient): the data term of ``reconstruct_tv`` on the same binned sinogram,
so λ means what it means there; TV_ε = Σ (√(|∇σ|² + ε²) − ε), a smooth TV. With σ_s = 0 there is nothing to walk
around: the stage is ``reconstruct_tv``, at its cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import dask
import dask.array as da
import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import xarray as xr

from devices.geometry import RigGeometry, to_lab
from pipeline.constraints import Count, Index, NonNegative, Positive, memory_problems
from pipeline.errors import Problem, StageError
from pipeline.registry import stage
from stages._common import MaxIter, require_variables
from stages._solution import Result, Solution, outcome
from stages.tomography._admm import TVADMM, gradient
from stages.tomography._projector import Geometry
from stages.tomography._walks import beam_entry, random_walks, walk_body
from stages.tomography.hull import contours
from stages.tomography.reconstruct import _check, _output, grid_geometry, reconstruct_tv, support_mask
from stages.tomography.sinogram import bin_index


@dataclass(frozen=True)
class Bundles:
    """The sampled paths of one slice's rays, ready for :func:`forward`: sample ``points`` (P, 2) in the object frame
    (x, y) with the 3-D ``lengths`` (P,) each stands for and the path each belongs to (P,); the group each path
    belongs to (paths,), a ray or a sinogram bin whose measurement the bundle models; the paths of each group."""

    points: np.ndarray
    lengths: np.ndarray
    path: np.ndarray
    group: np.ndarray
    counts: np.ndarray


def path_samples(vertices: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoint samples of polylines (N, V, 3), NaN-padded: points (P, 2) in x–y, the 3-D length each stands for
    (P,), and the polyline each belongs to (P,). Each segment gets ⌈horizontal length / spacing⌉ samples (at least
    one), so that a sample's reach in the image is at most ``spacing``."""
    start, end = vertices[:, :-1], vertices[:, 1:]
    valid = np.isfinite(end[..., 0]) & np.isfinite(start[..., 0])
    owner, _ = np.nonzero(valid)
    a, b = start[valid], end[valid]
    flat = np.linalg.norm(b[:, :2] - a[:, :2], axis=1)
    count = np.maximum(np.ceil(flat / spacing), 1).astype(np.int64)
    segment = np.repeat(np.arange(len(a)), count)
    first = np.cumsum(count) - count
    fraction = (np.arange(len(segment)) - first[segment] + 0.5) / count[segment]
    points = a[segment, :2] + fraction[:, None] * (b[segment, :2] - a[segment, :2])
    lengths = (np.linalg.norm(b - a, axis=1) / count)[segment]
    return points, lengths, owner[segment]


def line_integrals(image: jnp.ndarray, bundles: Bundles, geometry: Geometry) -> jnp.ndarray:
    """∫σ along every path of ``bundles`` through an (n, n) image on ``geometry``'s grid (rows y, columns x, cell
    centres −L + (m + ½)Δ): σ interpolated bilinearly at each sample (0 outside the grid), times its length."""
    coords = (jnp.asarray(bundles.points[:, ::-1].T) + geometry.extent) / geometry.cell - 0.5  # (row, col)
    values = jax.scipy.ndimage.map_coordinates(image, list(coords), order=1, mode="constant", cval=0.0)
    return jax.ops.segment_sum(values * jnp.asarray(bundles.lengths, image.dtype), jnp.asarray(bundles.path),
                               num_segments=len(bundles.group))


def forward(image: jnp.ndarray, bundles: Bundles, geometry: Geometry) -> jnp.ndarray:
    """The modelled absorption of every group (its count of groups): −log of the mean of exp(−∫σ) over its bundle
    (a stable log-mean-exp); NaN for a group without paths."""
    integrals = line_integrals(image, bundles, geometry)
    group = jnp.asarray(bundles.group)
    n_groups = len(bundles.counts)
    least = jax.ops.segment_min(integrals, group, num_segments=n_groups)
    least = jnp.where(jnp.isfinite(least), least, 0.0)
    total = jax.ops.segment_sum(jnp.exp(-(integrals - least[group])), group, num_segments=n_groups)
    counts = jnp.asarray(bundles.counts, image.dtype)
    return jnp.where(counts > 0, least - jnp.log(total / jnp.maximum(counts, 1)), jnp.nan)


def smooth_total_variation(image: jnp.ndarray, eps: float) -> jnp.ndarray:
    """Σ (√(|∇σ|² + ε²) − ε) with :func:`stages.tomography._admm.gradient`'s differences: the isotropic TV of
    ``reconstruct_tv`` within ε per cell, and differentiable at 0."""
    return (jnp.sqrt((gradient(image) ** 2).sum(axis=-3) + eps**2) - eps).sum()


def trace_bundles(geometry: RigGeometry, polygon: np.ndarray, row: int, angles: np.ndarray, group: np.ndarray,
                  n_groups: int, *, sigma_s: float, photons: int, paths_per_group: int, row_band: int, spacing: float,
                  rng: np.random.Generator, max_events: int = 200) -> Bundles:
    """The bundles of one slice, per group of its rays: ``group`` (angle, col) names each ray's group (its own index,
    or its sinogram bin, below ``n_groups``), −1 for no ray. Per angle, ``photons`` walks from where the light's
    ray enters the contour; a walk that leaves toward the camera onto a pixel within ``row_band`` rows of ``row``
    belongs to the group of that pixel's column, until the group holds ``paths_per_group`` paths."""
    body = walk_body(polygon, geometry)
    camera = geometry.camera
    height = float(camera.axis_height(row)[0]) if geometry.light_kind == "sheet" else geometry.beam_height
    taken = np.zeros(n_groups, np.int64)
    chosen, owners = [], []
    for a, angle in enumerate(np.asarray(angles, float)):
        if not (group[a] >= 0).any() or (light := beam_entry(body, geometry, angle, height)) is None:
            continue
        walks = random_walks(body, *light, sigma_s, photons, rng, max_events=max_events)
        q, n = to_lab(walks.exit_point, angle), to_lab(walks.exit_normal, angle)
        r, c = (np.rint(v).astype(np.int64) for v in camera.project(q))
        seen = camera.facing(q, n) & (np.abs(r - row) <= row_band) & (c >= 0) & (c < camera.cols)
        owner = np.full(len(seen), -1)
        owner[seen] = group[a, c[seen]]
        index = np.flatnonzero(owner >= 0)
        owner = owner[index]
        order = np.argsort(owner, kind="stable")  # each group's walks in the order traced
        index, owner = index[order], owner[order]
        rank = np.arange(len(owner)) - np.searchsorted(owner, owner, side="left") + taken[owner]
        keep = rank < paths_per_group
        chosen.append(walks.vertices[index[keep]])
        owners.append(owner[keep])
        taken += np.bincount(owner[keep], minlength=n_groups)
    if not chosen:
        return Bundles(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), taken)
    samples = [path_samples(v, spacing) for v in chosen]
    first = np.cumsum([0] + [len(v) for v in chosen])
    return Bundles(np.concatenate([p for p, _, _ in samples]), np.concatenate([s for _, s, _ in samples]),
                   np.concatenate([k + f for (_, _, k), f in zip(samples, first[:-1], strict=True)]),
                   np.concatenate(owners), taken)


def fit_slice(bundles: Bundles, absorption: np.ndarray, weights: np.ndarray, upper: np.ndarray, geometry: Geometry,
              *, tv_weight: float, eps: float, start: np.ndarray | None = None, max_iter: int = 300,
              tol: float = 1e-9) -> Solution:
    """σ (n, n) minimising ½ Σ_g w_g (A_g(σ) − a_g)² + λ TV_ε(σ) over the bundles' groups g (rays or bins;
    w_g = 0 leaves one out), 0 ≤ σ ≤ ``upper`` (per cell; 0 outside the support), by L-BFGS-B (scipy) with the
    exact gradient of :func:`forward` (JAX, float64) from ``start`` (None: zero). ``result`` is ``converged`` where
    L-BFGS-B met its own test (relative reduction of the objective below ``tol``, or a projected gradient of zero),
    ``max_steps`` at the cap; ``stats``: iterations, objective."""
    with jax.enable_x64(True):
        data = jnp.asarray(np.nan_to_num(absorption, nan=0.0), jnp.float64)
        w = jnp.asarray(weights, jnp.float64)
        shape = (geometry.n, geometry.n)

        def objective(flat):
            image = flat.reshape(shape)
            residual = jnp.where(w > 0, forward(image, bundles, geometry) - data, 0.0)
            return 0.5 * jnp.sum(w * residual**2) + tv_weight * smooth_total_variation(image, eps)

        value_and_grad = jax.jit(jax.value_and_grad(objective))

        def both(flat):
            value, grad = value_and_grad(jnp.asarray(flat))
            return float(value), np.asarray(grad, float)

        upper = np.nan_to_num(np.asarray(upper, float), nan=0.0, posinf=np.inf).ravel()
        x0 = np.zeros(upper.size) if start is None else np.clip(np.nan_to_num(np.ravel(start)), 0.0, upper)
        result = scipy.optimize.minimize(both, x0, jac=True, method="L-BFGS-B",
                                         bounds=scipy.optimize.Bounds(0.0, upper),
                                         options={"maxiter": max_iter, "ftol": tol, "gtol": 0.0})
    value = result.x.reshape(shape)
    code = outcome(np.asarray(result.status == 0), np.asarray(np.all(np.isfinite(value))))
    return Solution(value, code, {"iterations": int(result.nit), "objective": float(result.fun)})


#: the TV smoothing ε of :func:`smooth_total_variation`, relative to the data's σ scale (the largest observed
#: absorption over the image's width, the σ a uniform object across the grid would need) [1]
TV_SMOOTHING = 1e-3

#: bytes per path sample held while fitting (points, lengths, owner, the sampled σ and its gradient, float64)
SAMPLE_BYTES = 64


def _fit_one_slice(theta, x, absorption, data, observed, vertices, count, *, geometry: RigGeometry, row: int,
                   angles: np.ndarray, grid: Geometry, settings: dict, seed: int):
    """σ (n, n) of one slice by the bundle model, and (converged, iterations, objective, median paths, bins
    without paths)."""
    n_theta, n_x = data.shape
    nan = np.full((grid.n, grid.n), np.nan)
    if count < 3:
        return nan, _stats(False, 0, np.nan, 0.0, int(observed.sum()))
    polygon = vertices[:count]
    i, j, on_grid = bin_index(theta, x, n_theta=n_theta, n_x=n_x, extent=grid.extent)
    flat = np.where(on_grid & np.isfinite(absorption), i * n_x + j, -1)
    group = np.where((flat >= 0) & observed.ravel()[np.maximum(flat, 0)], flat, -1)
    bundles = trace_bundles(geometry, polygon, row, angles, group, n_theta * n_x, sigma_s=settings["sigma_s"],
                            photons=settings["photons"], paths_per_group=settings["paths_per_bin"],
                            row_band=settings["row_band"], spacing=grid.cell * settings["spacing"],
                            rng=np.random.default_rng([seed, row]), max_events=settings["max_events"])
    if problems := memory_problems(len(bundles.points) * SAMPLE_BYTES, f"slice {row}'s path samples",
                                   fix="lower paths_per_bin or raise spacing"):
        raise StageError([Problem(p) for p in problems])
    counts = bundles.counts
    used = observed.ravel() & (counts > 0)
    if not used.any():  # no walk reached an observed bin: no data, not a confident σ = 0
        return nan, _stats(False, 0, np.nan, 0.0, int(observed.sum()))
    values = data.ravel()
    scale = float(np.nanmax(np.where(used, values, np.nan), initial=0.0)) / (2 * grid.extent)
    upper = np.where(support_mask(polygon, grid), settings["sigma_max"], 0.0)
    fit = fit_slice(bundles, values, used.astype(float), upper, grid, tv_weight=settings["tv_weight"],
                    eps=TV_SMOOTHING * max(scale, np.finfo(float).tiny), max_iter=settings["max_iter"],
                    tol=settings["tol"])
    return fit.value, _stats(int(fit.result) == Result.converged, fit.stats["iterations"], fit.stats["objective"],
                             float(np.median(counts[used])), int((observed.ravel() & (counts == 0)).sum()))


def _stats(*values) -> tuple[np.ndarray, ...]:
    return tuple(np.asarray(v, dtype) for v, dtype in zip(values, _STATS.values(), strict=True))


@stage("reconstruct_scattering")
def reconstruct_scattering(rays: xr.Dataset, sinogram: xr.Dataset, hull: xr.Dataset, /, *, sigma_s: NonNegative,
                           tv_weight: NonNegative = TVADMM.DEFAULT_TV_WEIGHT, n_pixels: Count | None = None,
                           photons: Count = 40_000, paths_per_bin: Count = 64, row_band: Index = 16,
                           spacing: Positive = 1.0, sigma_max: Positive | None = None, max_events: Count = 1000,
                           max_iter: MaxIter = 500, tol: Positive = 1e-7, seed: Index = 0) -> xr.Dataset:
    """σ per slice under the path-bundle model of a scattering medium (module docstring; lazy, one task per slice).

    Each observed sinogram bin is modelled as −log of the mean transmittance of ``paths_per_bin`` photon walks that
    reach its rays' pixels, traced from each view's entry point in the hull with scattering coefficient σ_s; the fit
    is L-BFGS-B on ½‖A(σ) − a‖² over observed bins + λ TV, 0 ≤ σ ≤ σ_max, σ = 0 outside the hull. With σ_s = 0 this is
    :func:`stages.tomography.reconstruct.reconstruct_tv` (its defaults, ``tv_weight`` and ``n_pixels``).

    Parameters
    ----------
    rays : xr.Dataset
        The ``rays`` store (``align_paths``) the sinogram was binned from: ``theta`` [degree], ``x`` and
        ``absorption`` over (angle, row, col), angle the stage angle [degree]; which views and pixels hold rays.
    sinogram : xr.Dataset
        Its ``sinogram`` (``bin_sinogram``): ``absorption`` and ``observed`` over (slice, theta, x); attr
        ``x_extent`` spans the image, as for ``reconstruct_tv``.
    hull : xr.Dataset
        The ``hull`` store (``visual_hull``): the contour each slice's walks stay inside, and the rig geometry (the
        camera and the light) in its attrs.
    sigma_s : float
        Scattering coefficient of the medium [1/length unit]; 0: the shortest-path model (``reconstruct_tv``).
    tv_weight : float
        λ, as for ``reconstruct_tv`` [absorption² per (1/length)·cell].
    n_pixels : int or None
        Image size n; None: the sinogram's number of X bins.
    photons : int
        Walks traced per view [1].
    paths_per_bin : int
        Walks kept per sinogram bin (its bundle) [1]; the samples of a slice grow with it.
    row_band : int
        Walks that leave within this many camera rows of the slice's row count for it [rows]: more walks, at the
        cost of some that left a little above or below the slice.
    spacing : float
        Distance between samples along a path, in cells [1].
    sigma_max : float or None
        Upper bound of σ [1/length unit]; None: none (σ ≥ 0 only). The shortest-path σ_max of Eq. 26–28 does not hold
        under scattering, where a ray's absorption under-reads what it crossed.
    max_events : int
        Scatterings before a walk is dropped [1].
    max_iter : int
        L-BFGS-B iteration cap, in [1, 1 000 000].
    tol : float
        Stop when an iteration lowers the objective by less than this share of it [1].
    seed : int
        Seed of the walks (with the slice's row).

    Returns a ``reconstruction`` store: ``sigma`` over (slice, y, x), NaN for a slice without a contour or where no
    walk reached an observed bin (no data: never a confident 0); per slice ``converged`` (L-BFGS-B met ``tol``),
    ``iterations``, ``final_objective``, ``paths_per_bin`` (median over the observed bins) and ``bins_without_paths``
    (observed bins no walk reached: left out of the fit; raise ``photons`` or ``row_band`` if many).
    """
    if sigma_s == 0:
        return reconstruct_tv(sinogram, hull, tv_weight=tv_weight, n_pixels=n_pixels)
    require_variables(rays, ("theta", "x", "absorption"), "reconstruct_scattering")
    _check(sinogram, hull, "reconstruct_scattering")
    geometry = RigGeometry.from_attrs(hull.attrs, rays.sizes["row"], rays.sizes["col"],
                                      where="reconstruct_scattering: hull")
    rows = sinogram["slice"].values
    missing = sorted(set(rows.tolist()) - set(rays["row"].values.tolist()))
    if missing:
        raise StageError(Problem(f"the sinogram's slices {missing[:5]} are not rows of the rays",
                                 fix="give the rays the sinogram was binned from"))
    grid = grid_geometry(sinogram, n_pixels)
    shell = contours(hull, sinogram["slice"], "reconstruct_scattering")
    settings = {"sigma_s": sigma_s, "tv_weight": tv_weight, "photons": photons, "paths_per_bin": paths_per_bin,
                "row_band": row_band, "spacing": spacing, "sigma_max": np.inf if sigma_max is None else sigma_max,
                "max_events": max_events, "max_iter": max_iter, "tol": tol}
    angles = rays["angle"].values
    fit = dask.delayed(_fit_one_slice, nout=2, pure=True)
    images, stats = [], []
    for k, row in enumerate(rows):
        ray = rays.sel(row=row)
        image, numbers = fit(ray["theta"].data, ray["x"].data, ray["absorption"].data,
                             sinogram["absorption"].isel(slice=k).data, sinogram["observed"].isel(slice=k).data,
                             shell["vertices"].isel(slice=k).data, shell["n_vertices"].isel(slice=k).data,
                             geometry=geometry, row=int(row), angles=angles, grid=grid, settings=settings, seed=seed)
        images.append(da.from_delayed(image, (grid.n, grid.n), np.float64).astype(np.float32))
        stats.append([da.from_delayed(numbers[m], (), dtype) for m, dtype in enumerate(_STATS.values())])
    image = ("slice", "y", "x")
    variables = {"sigma": (image, da.stack(images))}
    for m, name in enumerate(_STATS):
        variables[name] = (("slice",), da.stack([s[m] for s in stats]))
    return _output(sinogram, grid, variables, {"method": "bundle_lbfgsb_tv", "sigma_s": sigma_s,
                                               "tv_weight": tv_weight, "photons": photons,
                                               "paths_per_bin": paths_per_bin, "row_band": row_band, "seed": seed})


#: per-slice statistics of :func:`reconstruct_scattering` and their dtypes
_STATS = {"converged": np.dtype(bool), "iterations": np.dtype(np.int64), "final_objective": np.dtype(np.float64),
          "paths_per_bin": np.dtype(np.float64), "bins_without_paths": np.dtype(np.int64)}
