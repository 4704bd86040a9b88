"""The path-bundle model of tomography through scattering (#27): what :mod:`stages.tomography.scattering`'s
``reconstruct_scattering`` fits.

A sinogram bin (or a ray) is a bundle of photon walks that reach its pixels (:func:`trace_bundles`); its modelled
absorption is −log of the mean of exp(−∫σ) over the bundle (:func:`forward`): ∫σ along each path by bilinear
interpolation at its samples (:func:`line_integrals` in JAX, the same as the sparse :func:`path_matrix` for the
fit), and the fit is L-BFGS-B on the bins' squared misfit plus a smooth TV (:func:`fit_slice`, through
:func:`slice_objective`). The stage module's docstring gives the model's physics and assumptions.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import scipy.sparse

from devices.geometry import RigGeometry, to_lab
from stages._solution import Solution, outcome
from stages.tomography._admm import gradient
from stages.tomography._projector import Geometry
from stages.tomography._walks import beam_entry, random_walks, walk_body


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


def path_matrix(bundles: Bundles, geometry: Geometry) -> scipy.sparse.csr_array:
    """:func:`line_integrals` as a sparse (paths × n²) matrix W, so that ∫σ along the paths is W @ σ.ravel(): each
    sample's four bilinear weights times its length, on the cells inside the grid (a neighbour outside adds 0, as
    ``map_coordinates``' constant mode does), summed where a path's samples share a cell (float64 weights, int32
    cells).

    The fit multiplies by W and Wᵀ hundreds of times; a path's samples are about a cell apart, so W holds about two
    entries per sample where ``map_coordinates`` gathers, and its gradient scatters, four. Built row by row in place
    (each sample's four entries in its path's row, then scipy sums the duplicates): about 80 bytes per sample at the
    peak, where a COO build took 300."""
    n, count = geometry.n, len(bundles.points)
    points, lengths, path = bundles.points, bundles.lengths, bundles.path
    if np.any(np.diff(path) < 0):  # each path's samples together, as a row of W
        order = np.argsort(path, kind="stable")
        points, lengths, path = points[order], lengths[order], path[order]
    coords = (points[:, ::-1] + geometry.extent) / geometry.cell - 0.5  # (row, col) per sample
    low = np.floor(coords)
    frac = coords - low
    low = low.astype(np.int32)
    values, cells = np.empty((count, 4)), np.empty((count, 4), np.int32)
    for j, (dr, dc) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        r, c = low[:, 0] + dr, low[:, 1] + dc
        inside = (r >= 0) & (r < n) & (c >= 0) & (c < n)
        values[:, j] = np.where(inside, (frac[:, 0] if dr else 1 - frac[:, 0]) * (frac[:, 1] if dc else 1 - frac[:, 1])
                                * lengths, 0.0)
        cells[:, j] = np.where(inside, r * n + c, 0)
    indptr = np.zeros(len(bundles.group) + 1, np.int64)
    np.cumsum(4 * np.bincount(path, minlength=len(bundles.group)), out=indptr[1:])
    matrix = scipy.sparse.csr_array((values.ravel(), cells.ravel(), indptr), shape=(len(bundles.group), n * n))
    matrix.sum_duplicates()
    matrix.eliminate_zeros()
    return matrix


def bundle_absorption(integrals: jnp.ndarray, bundles: Bundles) -> jnp.ndarray:
    """The modelled absorption of every group from its paths' ``integrals`` (∫σ): −log of the mean of exp(−∫σ) over
    its bundle (a stable log-mean-exp); NaN for a group without paths."""
    group = jnp.asarray(bundles.group)
    n_groups = len(bundles.counts)
    least = jax.ops.segment_min(integrals, group, num_segments=n_groups)
    least = jnp.where(jnp.isfinite(least), least, 0.0)
    total = jax.ops.segment_sum(jnp.exp(-(integrals - least[group])), group, num_segments=n_groups)
    counts = jnp.asarray(bundles.counts, integrals.dtype)
    return jnp.where(counts > 0, least - jnp.log(total / jnp.maximum(counts, 1)), jnp.nan)


def forward(image: jnp.ndarray, bundles: Bundles, geometry: Geometry) -> jnp.ndarray:
    """The modelled absorption of every group (its count of groups): :func:`bundle_absorption` of
    :func:`line_integrals`."""
    return bundle_absorption(line_integrals(image, bundles, geometry), bundles)


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


def slice_objective(bundles: Bundles, absorption: np.ndarray, weights: np.ndarray, geometry: Geometry, *,
                    tv_weight: float, eps: float):
    """f(σ) = ½ Σ_g w_g (A_g(σ) − a_g)² + λ TV_ε(σ) and its gradient, as a function of the flat σ (float64 arrays in
    and out): the integrals by :func:`path_matrix` (W σ, and Wᵀ for the gradient, in scipy), the bundles' absorption
    and TV with their exact gradients in JAX. The same value and gradient as JAX differentiating :func:`forward`
    (tested), at a fraction of its cost: ``map_coordinates`` gathers four neighbours per sample and its gradient
    scatters them."""
    matrix = path_matrix(bundles, geometry)
    shape = (geometry.n, geometry.n)
    with jax.enable_x64(True):
        data = jnp.asarray(np.nan_to_num(absorption, nan=0.0), jnp.float64)
        w = jnp.asarray(weights, jnp.float64)

        def data_term(integrals):
            residual = jnp.where(w > 0, bundle_absorption(integrals, bundles) - data, 0.0)
            return 0.5 * jnp.sum(w * residual**2)

        data_grad = jax.jit(jax.value_and_grad(data_term))
        tv_grad = jax.jit(jax.value_and_grad(lambda image: tv_weight * smooth_total_variation(image, eps)))

    def both(flat):
        flat = np.asarray(flat, np.float64)
        with jax.enable_x64(True):
            value, grad_integrals = data_grad(jnp.asarray(matrix @ flat))
            tv, grad_tv = tv_grad(jnp.asarray(flat.reshape(shape)))
        return float(value) + float(tv), matrix.T @ np.asarray(grad_integrals) + np.asarray(grad_tv).ravel()

    return both


def fit_slice(bundles: Bundles, absorption: np.ndarray, weights: np.ndarray, upper: np.ndarray, geometry: Geometry,
              *, tv_weight: float, eps: float, start: np.ndarray | None = None, max_iter: int = 300,
              tol: float = 1e-9) -> Solution:
    """σ (n, n) minimising ½ Σ_g w_g (A_g(σ) − a_g)² + λ TV_ε(σ) over the bundles' groups g (rays or bins;
    w_g = 0 leaves one out), 0 ≤ σ ≤ ``upper`` (per cell; 0 outside the support), by L-BFGS-B (scipy) with the
    exact gradient (:func:`slice_objective`, float64) from ``start`` (None: zero). ``result`` is ``converged`` where
    L-BFGS-B met its own test (relative reduction of the objective below ``tol``, or a projected gradient of zero),
    ``max_steps`` at the cap; ``stats``: iterations, objective."""
    both = slice_objective(bundles, absorption, weights, geometry, tv_weight=tv_weight, eps=eps)
    upper = np.nan_to_num(np.asarray(upper, float), nan=0.0, posinf=np.inf).ravel()
    x0 = np.zeros(upper.size) if start is None else np.clip(np.nan_to_num(np.ravel(start)), 0.0, upper)
    result = scipy.optimize.minimize(both, x0, jac=True, method="L-BFGS-B", bounds=scipy.optimize.Bounds(0.0, upper),
                                     options={"maxiter": max_iter, "ftol": tol, "gtol": 0.0})
    value = result.x.reshape(geometry.n, geometry.n)
    code = outcome(np.asarray(result.status == 0), np.asarray(np.all(np.isfinite(value))))
    return Solution(value, code, {"iterations": int(result.nit), "objective": float(result.fun)})
