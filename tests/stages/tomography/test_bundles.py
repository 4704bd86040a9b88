"""The path-bundle forward model of tomography through scattering (#27): walks, samples, integrals, gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selpath.geometry.shapes import Prism, convex_polygon
from selpath.stages._solution import Result
from selpath.stages.tomography._bundles import (
    Bundles,
    fit_slice,
    forward,
    line_integrals,
    path_matrix,
    path_samples,
    slice_objective,
    smooth_total_variation,
)
from selpath.stages.tomography._projector import Geometry
from selpath.stages.tomography._walks import random_walks

SQUARE = convex_polygon([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
GEOMETRY = Geometry.from_grids(np.arange(4) * 45.0, np.linspace(-1.2, 1.2, 48), 48, 1.2)


def blob(geometry: Geometry, centre=(0.2, -0.1), width=0.25, peak=2.0) -> np.ndarray:
    """A Gaussian σ on the grid's cell centres (rows y, columns x)."""
    c = geometry.centres
    return peak * np.exp(-((c[None, :] - centre[0]) ** 2 + (c[:, None] - centre[1]) ** 2) / (2 * width**2))


def blob_line_integral(p, q, centre=(0.2, -0.1), width=0.25, peak=2.0) -> float:
    """∫ of the Gaussian along the whole line through p and q: peak·√(2π)·width·exp(−d²/2width²), d its distance
    from the centre (the blob is ≪ the segment, so the segment's ends do not matter)."""
    p, q, c = np.asarray(p, float), np.asarray(q, float), np.asarray(centre, float)
    u = (q - p) / np.linalg.norm(q - p)
    d = abs((c - p)[0] * u[1] - (c - p)[1] * u[0])
    return peak * np.sqrt(2 * np.pi) * width * np.exp(-(d**2) / (2 * width**2))


def bundles_of(paths: list[np.ndarray], ray: list[int], n_rays: int, spacing: float) -> Bundles:
    """Bundles from explicit polylines (each (V, 3)), padded with NaN to one length."""
    longest = max(len(p) for p in paths)
    vertices = np.full((len(paths), longest, 3), np.nan)
    for k, p in enumerate(paths):
        vertices[k, : len(p)] = p
    points, lengths, path = path_samples(vertices, spacing)
    ray = np.asarray(ray)
    return Bundles(points, lengths, path, ray, np.bincount(ray, minlength=n_rays))


def test_path_samples_keep_every_polylines_3d_length_and_lie_on_it():
    """Σ lengths of a polyline's samples = its 3-D length (1e-12), and each sample is on its segment's x–y
    projection; a segment shorter than the spacing still gets one sample."""
    rng = np.random.default_rng(3)
    vertices = rng.uniform(-1, 1, (5, 6, 3))
    vertices[1, 4:] = np.nan  # a shorter walk
    vertices[2, 1] = vertices[2, 0] + [1e-4, 0.0, 0.3]  # a nearly vertical step
    points, lengths, owner = path_samples(vertices, 0.05)
    for k in range(5):
        v = vertices[k][np.isfinite(vertices[k, :, 0])]
        assert np.sum(lengths[owner == k]) == pytest.approx(np.sum(np.linalg.norm(np.diff(v, axis=0), axis=1)), 1e-12)
    assert np.bincount(owner).min() >= 5
    assert np.all(np.abs(points) <= 1.0 + 1e-12)


@pytest.mark.parametrize("p, q", [((-1.1, -0.9), (1.1, 0.8)), ((0.0, -1.15), (0.05, 1.15)), ((-1.1, 0.3), (1.1, 0.2))])
def test_a_straight_paths_integral_is_the_lines_analytic_integral(p, q):
    """One straight path through a Gaussian blob (width 6 cells): the bilinear samples' sum equals the analytic
    line integral within 1 %, and a bundle of one path is its own absorption (the straight model)."""
    bundles = bundles_of([np.array([[*p, 0.0], [*q, 0.0]])], [0], 1, GEOMETRY.cell / 2)
    image = jnp.asarray(blob(GEOMETRY))
    expected = blob_line_integral(p, q)
    assert float(line_integrals(image, bundles, GEOMETRY)[0]) == pytest.approx(expected, rel=1e-2)
    assert float(forward(image, bundles, GEOMETRY)[0]) == pytest.approx(expected, rel=1e-2)


def test_a_bundles_absorption_is_minus_log_of_its_mean_transmittance():
    """Two rays: one of two paths (I₁, I₂), one of a single path: A = −log((e^−I₁ + e^−I₂)/2) and A = I; a ray
    without paths is NaN. Exact against the integrals, also where e^−I underflows in float32."""
    paths = [np.array([[-1.1, y, 0.0], [1.1, y, 0.0]]) for y in (-0.1, 0.6, 0.0)]
    bundles = bundles_of(paths, [0, 0, 1], 3, GEOMETRY.cell / 2)
    for scale in (1.0, 400.0):
        image = jnp.asarray(scale * blob(GEOMETRY), jnp.float32)
        integrals = np.asarray(line_integrals(image, bundles, GEOMETRY), float)
        model = np.asarray(forward(image, bundles, GEOMETRY))
        low = integrals[:2].min()
        expected = low - np.log(np.mean(np.exp(-(integrals[:2] - low))))
        assert model[0] == pytest.approx(expected, rel=1e-5)
        assert model[1] == pytest.approx(integrals[2], rel=1e-6)
        assert np.isnan(model[2]) and np.isfinite(model[:2]).all()


def walked_bundles(seed: int = 5, walks: int = 300, groups: int = 7) -> Bundles:
    """Walks at σ_s = 2 from the square's left side, some leaving it (and the grid's inner cells) on every side,
    spread over ``groups`` groups."""
    rng = np.random.default_rng(seed)
    walked = random_walks(Prism(SQUARE), np.array([-1.0, 0.1, 0.0]), np.array([-1.0, 0.0, 0.0]), 2.0, walks, rng)
    group = np.arange(walks) % groups
    return Bundles(*path_samples(walked.vertices, GEOMETRY.cell / 2), group, np.bincount(group))


def test_the_objectives_gradient_matches_finite_differences():
    """d/dσ of ½ Σ w (A(σ) − a)² + λ TV_ε(σ) by JAX against central differences (float64, 1e-6 relative) at
    random cells of a non-trivial σ."""
    bundles = walked_bundles()
    rng = np.random.default_rng(5)
    data, weights = rng.uniform(0.5, 2.0, 7), rng.uniform(0.2, 1.0, 7)
    with jax.enable_x64(True):
        def objective(image):
            return (0.5 * jnp.sum(weights * (forward(image, bundles, GEOMETRY) - data) ** 2)
                    + 0.05 * smooth_total_variation(image, 1e-2))

        image = jnp.asarray(blob(GEOMETRY) + 0.3 * rng.random((GEOMETRY.n, GEOMETRY.n)))
        grad = np.asarray(jax.grad(objective)(image))
        for k in rng.choice(image.size, 12, replace=False):
            step = np.zeros(image.size)
            step[k] = 1e-6
            step = jnp.asarray(step.reshape(image.shape))
            numeric = (float(objective(image + step)) - float(objective(image - step))) / 2e-6
            assert grad.ravel()[k] == pytest.approx(numeric, rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("extent", [1.2, 0.8])  # the grid holds every path; the grid cuts them (samples outside)
def test_the_path_matrix_is_the_bilinear_line_integrals(extent):
    """W @ σ equals :func:`line_integrals` (``map_coordinates``, order 1, constant 0 outside) to 1e-12 of the largest
    integral, also where samples lie off the grid or next to its edge, and W holds fewer entries than the four
    neighbours per sample ``map_coordinates`` reads."""
    geometry = Geometry.from_grids(np.arange(4) * 45.0, np.linspace(-extent, extent, 40), 40, extent)
    bundles = walked_bundles()
    image = np.random.default_rng(1).random((geometry.n, geometry.n))
    with jax.enable_x64(True):
        expected = np.asarray(line_integrals(jnp.asarray(image), bundles, geometry))
    matrix = path_matrix(bundles, geometry)
    np.testing.assert_allclose(matrix @ image.ravel(), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    assert matrix.shape == (len(bundles.group), geometry.n**2) and matrix.nnz < 4 * len(bundles.points)
    if extent < 1:
        assert np.abs(bundles.points).max() > extent  # the case does cut paths


def test_the_fits_objective_is_jaxs_own_on_the_forward_model():
    """:func:`slice_objective` (the integrals by the sparse path matrix, the rest in JAX) gives the value and the
    gradient of ½ Σ w (A(σ) − a)² + λ TV_ε(σ) that JAX differentiating :func:`forward` gives, to 1e-12 relative, with
    some groups left out (w = 0) and one group without paths."""
    rng = np.random.default_rng(2)
    bundles = walked_bundles(groups=9)
    bundles = Bundles(bundles.points, bundles.lengths, bundles.path, bundles.group, np.append(bundles.counts, 0))
    data, weights = rng.uniform(0.5, 2.0, 10), np.where(rng.random(10) < 0.3, 0.0, rng.uniform(0.2, 1.0, 10))
    weights[-1] = 0.0  # the group without paths has no model: it must be left out
    image = blob(GEOMETRY) + 0.3 * rng.random((GEOMETRY.n, GEOMETRY.n))
    with jax.enable_x64(True):
        def objective(image):
            residual = jnp.where(weights > 0, forward(image, bundles, GEOMETRY) - data, 0.0)
            return 0.5 * jnp.sum(weights * residual**2) + 0.05 * smooth_total_variation(image, 1e-2)

        value, grad = jax.value_and_grad(objective)(jnp.asarray(image))
    ours, our_grad = slice_objective(bundles, data, weights, GEOMETRY, tv_weight=0.05, eps=1e-2)(image.ravel())
    assert ours == pytest.approx(float(value), rel=1e-12)
    np.testing.assert_allclose(our_grad, np.asarray(grad).ravel(), rtol=0, atol=1e-12 * np.abs(grad).max())


def test_fitting_the_models_own_data_recovers_the_absorber():
    """Data made by the bundle model itself from a known σ (walks at σ_s = 2 in a square, 24 angles' worth of entry
    points): the fit from zero, with a small TV weight, comes within 5 % of the absorber's mass and puts nothing
    outside the support; it reports convergence honestly (a cap of 3 iterations is max_steps)."""
    rng = np.random.default_rng(7)
    geometry = Geometry.from_grids(np.arange(4) * 45.0, np.linspace(-1.05, 1.05, 24), 24, 1.05)
    paths, ray = [], []
    for k, angle in enumerate(np.linspace(0, 2 * np.pi, 24, endpoint=False)):
        side = np.array([np.cos(angle), np.sin(angle)])
        entry = side / np.abs(side).max()
        walks = random_walks(Prism(SQUARE), np.array([*entry, 0.0]), np.array([*side, 0.0]), 2.0, 400, rng)
        exits = walks.exit_point[:, :2]
        bins = np.floor((np.arctan2(exits[:, 1], exits[:, 0]) + np.pi) / (2 * np.pi) * 16).astype(int) % 16
        paths.append(walks.vertices)
        ray.append(k * 16 + bins)
    longest = max(p.shape[1] for p in paths)
    vertices = np.concatenate([np.pad(p, ((0, 0), (0, longest - p.shape[1]), (0, 0)), constant_values=np.nan)
                               for p in paths])
    ray = np.concatenate(ray)
    bundles = Bundles(*path_samples(vertices, geometry.cell / 2), ray, np.bincount(ray, minlength=24 * 16))
    c = geometry.centres
    truth = np.where((c[None, :] - 0.3) ** 2 + (c[:, None] + 0.2) ** 2 < 0.3**2, 3.0, 0.0)
    with jax.enable_x64(True):
        data = np.asarray(forward(jnp.asarray(truth), bundles, geometry))
    observed = np.isfinite(data)
    upper = np.where((np.abs(c[None, :]) < 1) & (np.abs(c[:, None]) < 1), np.inf, 0.0)  # the square's cells
    fit = fit_slice(bundles, data, observed.astype(float), upper, geometry, tv_weight=1e-5, eps=1e-3, max_iter=2000)
    assert int(fit.result) == Result.converged
    assert fit.value.sum() == pytest.approx(truth.sum(), rel=0.05)
    assert np.all(fit.value[upper == 0] == 0)
    capped = fit_slice(bundles, data, observed.astype(float), upper, geometry, tv_weight=1e-5, eps=1e-3, max_iter=3)
    assert int(capped.result) == Result.max_steps
