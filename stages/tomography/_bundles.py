"""The path-bundle model of tomography through scattering (#27): what :mod:`selpath.stages.tomography.scattering`'s
``reconstruct_scattering`` fits.

A sinogram bin (or a ray) is a bundle of paths by which light reaches its pixels, drawn from photon walks connected
to the pixels (:func:`trace_bundles`); its modelled absorption is −log of the mean of exp(−∫σ) over the bundle
(:func:`forward`): ∫σ along each path by bilinear interpolation at its samples (:func:`line_integrals` in JAX, the
same as the sparse :func:`path_matrix` for the fit), and the fit is L-BFGS-B on the bins' squared misfit plus a
smooth TV (:func:`fit_slice`, through :func:`slice_objective`). The stage module's docstring gives the model's
physics and assumptions.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import scipy.sparse

from selpath.geometry.rig import RigGeometry, to_lab
from selpath.stages._solution import Solution, outcome
from selpath.stages.tomography._admm import gradient
from selpath.stages.tomography._projector import Geometry
from selpath.stages.tomography._walks import beam_entry, exit_weights, random_walks, surface_seen, walk_body


@dataclass(frozen=True)
class Bundles:
    """The sampled paths of one slice's rays, ready for :func:`forward`: sample ``points`` (P, 2) in the object frame
    (x, y) with the 3-D ``lengths`` (P,) each stands for and the path each belongs to (P,); the group each path
    belongs to (paths,), a ray or a sinogram bin whose measurement the bundle models; the paths of each group, and
    how many of them are distinct (a path drawn twice counts twice in ``counts``; None: all are)."""

    points: np.ndarray
    lengths: np.ndarray
    path: np.ndarray
    group: np.ndarray
    counts: np.ndarray
    distinct: np.ndarray | None = None


def path_samples(vertices: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoint samples of polylines (N, V, 3), NaN-padded: points (P, 2) in x–y, the 3-D length each stands for
    (P,), and the polyline each belongs to (P,). Each segment gets ⌈horizontal length / spacing⌉ samples (at least
    one), so that a sample's reach in the image is at most ``spacing``."""
    start, end = vertices[:, :-1], vertices[:, 1:]
    valid = np.isfinite(end[..., 0]) & np.isfinite(start[..., 0])
    owner, _ = np.nonzero(valid)
    return segment_samples(start[valid], end[valid], owner, spacing)


def segment_samples(a: np.ndarray, b: np.ndarray, owner: np.ndarray, spacing: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`path_samples` of segments from ``a`` to ``b`` (S, 3), each of polyline ``owner`` (S,)."""
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
    """Σ (√(|∇σ|² + ε²) − ε) with :func:`selpath.stages.tomography._admm.gradient`'s differences: the isotropic TV of
    ``reconstruct_tv`` within ε per cell, and differentiable at 0."""
    return (jnp.sqrt((gradient(image) ** 2).sum(axis=-3) + eps**2) - eps).sum()


def trace_bundles(geometry: RigGeometry, polygon: np.ndarray, row: int, angles: np.ndarray, group: np.ndarray,
                  n_groups: int, *, sigma_s: float, photons: int, paths_per_group: int, spacing: float,
                  rng: np.random.Generator, max_events: int = 200) -> Bundles:
    """The bundles of one slice, per group of its rays: ``group`` (angle, col) names each ray's group (its own index,
    or its sinogram bin, below ``n_groups``), −1 for no ray.

    Per angle, ``photons`` walks from where the light's ray enters the contour, each connected from every vertex it
    flew from to the surface point that each pixel of the row with a ray sees (next-event estimation,
    :func:`selpath.stages.tomography._walks.exit_weights`, over the pixel's footprint): a path (the walk up to the
    vertex,
    then straight to the point) and the light it brings. Each group holds ``paths_per_group`` paths drawn with
    replacement from all the connections to its pixels, over all angles, in proportion to their light (a reservoir:
    a pixel's light at a later angle takes over each path with the chance of its share of the group's light so far):
    the paths by which its pixels' light arrives, on the row itself, every group that light reaches with the same
    number of paths. Where a walk's own exit lands on one pixel at most, its connections reach them all."""
    body = walk_body(polygon, geometry)
    camera = geometry.camera
    height = float(camera.axis_height(row)[0]) if geometry.light_kind == "sheet" else geometry.beam_height
    origins, directions = camera.back_project(np.full(camera.cols, row), np.arange(camera.cols))
    slots = np.full((n_groups, paths_per_group), -1)  # index into the paths drawn
    held = np.zeros(n_groups)  # the light of the connections seen so far, per group
    drawn, lengths, first = [], [], 0  # the drawn paths' vertices, flat, and how many each has
    for a, angle in enumerate(np.asarray(angles, float)):
        cols = np.flatnonzero(group[a] >= 0)
        if not len(cols) or (light := beam_entry(body, geometry, angle, height)) is None:
            continue
        cols, point, normal, area = _seen_patches(body, camera, origins[cols], directions[cols], cols, angle)
        if not len(cols):
            continue
        walks = random_walks(body, *light, sigma_s, photons, rng, max_events=max_events)
        walk, vertex, weights = exit_weights(walks, light[1], point, normal, area, sigma_s)
        total = weights.sum(axis=0)
        cumulative = np.cumsum(weights, axis=0)
        picks, targets, owners = [], [], []
        for t in np.flatnonzero(total > 0):
            g = group[a, cols[t]]
            held[g] += total[t]
            taken = np.flatnonzero(rng.random(paths_per_group) < total[t] / held[g])  # all, for a group's first
            if len(taken):
                picks.append(np.searchsorted(cumulative[:, t], rng.random(len(taken)) * total[t], side="right"))
                targets.append(np.full(len(taken), t))
                owners.append((g, taken))
        if not picks:
            continue
        pick = np.minimum(np.concatenate(picks), len(walk) - 1)
        target = np.concatenate(targets)
        reach = vertex[pick]  # each path: the walk's vertices up to here, then the pixel's point
        longest = int(reach.max()) + 2
        path = np.full((len(pick), longest, 3), np.nan)
        path[:, :longest - 1] = walks.vertices[walk[pick], :longest - 1]
        path[np.arange(longest)[None, :] > reach[:, None]] = np.nan
        path[np.arange(len(pick)), reach + 1] = point[target]
        keep = np.isfinite(path[..., 0])
        drawn.append(path[keep])
        lengths.append(keep.sum(axis=1))
        number = first + np.arange(len(pick))
        k = 0
        for g, taken in owners:
            slots[g, taken] = number[k:k + len(taken)]
            k += len(taken)
        first += len(pick)
    counts = (slots >= 0).sum(axis=1)
    if not first:
        return Bundles(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), counts, counts)
    owner, taken = np.nonzero(slots >= 0)
    chosen = slots[owner, taken]  # the paths kept, in group order (a path drawn twice counts twice)
    points, sample_lengths, path = _kept_samples(np.concatenate(drawn), np.concatenate(lengths), chosen, spacing)
    pairs = np.unique(np.c_[owner, chosen], axis=0)
    return Bundles(points, sample_lengths, path, owner, counts, np.bincount(pairs[:, 0], minlength=n_groups))


def _seen_patches(body, camera, origins: np.ndarray, directions: np.ndarray, cols: np.ndarray, angle: float):
    """The pixels of ``cols`` (lab rays ``origins``, ``directions``) that see ``body`` facing them at stage angle
    ``angle``: their columns, the points they see and the outward normals there (object frame), and the area each
    pixel's footprint covers."""
    hit, point, normal, _ = surface_seen(body, origins, directions, angle)
    lab_point, lab_normal = to_lab(point, angle), to_lab(normal, angle)
    facing = hit & camera.facing(lab_point, lab_normal)
    area = camera.pixel_footprint(lab_point[facing], lab_normal[facing])
    return cols[facing], point[facing], normal[facing], area


def _kept_samples(vertices: np.ndarray, lengths: np.ndarray, chosen: np.ndarray, spacing: float):
    """:func:`segment_samples` of the polylines ``chosen`` (a polyline may be chosen twice) among those whose vertices
    lie one after another in ``vertices`` (V, 3), ``lengths`` (polylines,) each; the samples' polyline is its place in
    ``chosen``."""
    counts = lengths[chosen]
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    flat = vertices[np.repeat((np.cumsum(lengths) - lengths)[chosen], counts) + within]
    of = np.repeat(np.arange(len(chosen)), counts)
    same = of[:-1] == of[1:]  # consecutive vertices of one polyline: a segment
    return segment_samples(flat[:-1][same], flat[1:][same], of[:-1][same], spacing)


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
