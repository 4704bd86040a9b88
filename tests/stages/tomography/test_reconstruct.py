"""Projector, FBP and the constrained TV reconstruction against independent truths (§4.3, DESIGN §6).

Truths: the analytic Radon transform of disks (exact chords), scikit-image's ``radon``, brute-force
inner products for the adjoint, and cell-averaged rasters of the same disks.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import xarray as xr
from skimage.data import shepp_logan_phantom
from skimage.transform import radon, resize

from selpath import workflows
from selpath.stages.tomography._filters import ramp_response
from selpath.stages.tomography._projector import (
    Geometry,
    HostProjector,
    MatrixProjector,
    WalkProjector,
    adjoint,
    backproject,
    forward,
    system_matrix,
)
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.phantom import simulate_sinogram, truth_raster
from selpath.stages.tomography.reconstruct import (
    _fill_missing,
    fbp,
    reconstruct_tv,
    reliable_cells,
    support_mask,
    upper_bound,
)
from tests.helpers.sinograms import DISKS, L, disk_radon, sinogram


def disk_raster(n, disks=DISKS, sub=4):
    h = 2 * L / n
    c = -L + (np.arange(n) + 0.5) * h
    fine = (c[:, None] + ((np.arange(sub) + 0.5) / sub - 0.5)[None, :] * h).ravel()
    yy, xx = np.meshgrid(fine, fine, indexing="ij")
    image = sum(s * (((xx - c0[0]) ** 2 + (yy - c0[1]) ** 2) < r**2) for c0, r, s in disks)
    return image.reshape(n, sub, n, sub).mean(axis=(1, 3))


def rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - b) ** 2)))


@pytest.mark.parametrize(("n", "n_theta", "n_x", "seed", "method"), [
    # one grid of each method in the default job, two more in the slow one (each shape is an XLA compile, ~20 s)
    (5, 1, 2, 0, "joseph"), pytest.param(16, 7, 11, 1, "joseph", marks=pytest.mark.slow),
    pytest.param(9, 12, 20, 2, "binary", marks=pytest.mark.slow), (24, 3, 5, 3, "binary")])
def test_every_projectors_adjoint_is_its_forward_maps_transpose(n, n_theta, n_x, seed, method):
    """⟨Rx, y⟩ = ⟨x, Rᵀy⟩ in float64 to 1e-12 relative for the three projectors the solvers use, on a batch of two
    slices: the walk (its adjoint JAX's transpose of its forward, so this checks the batching around it), the
    BCSR matrices and the host's scipy blocks (each adjoint a separately stored transpose, split in row blocks: a
    wrong transpose or split fails here), on odd grids, random angles and a 45° tie (fixed cases: each new shape
    costs an XLA compile)."""
    rng = np.random.default_rng(seed)
    theta = np.sort(rng.uniform(0, 180, n_theta))
    theta[0] = 45.0
    g = Geometry.from_grids(theta, np.linspace(-1.3, 1.3, n_x), n, 1.0, method)
    with jax.enable_x64(True):
        x, y = jnp.asarray(rng.normal(size=(2, n, n))), jnp.asarray(rng.normal(size=(2, *g.shape)))
        for projector in (WalkProjector(), MatrixProjector.build(g, np.float64),
                          HostProjector.build(g, np.float64, threads=2)):
            left = float(jnp.vdot(projector.forward(g, x), y))
            right = float(jnp.vdot(x, projector.adjoint(g, y)))
            assert left == pytest.approx(right, rel=1e-12, abs=1e-12), type(projector).__name__
            np.testing.assert_allclose(projector.forward(g, x), forward(g, x), rtol=1e-12, atol=1e-12)


@pytest.mark.slow  # default job over its 8 minutes: run in the slow job
@pytest.mark.parametrize(("n", "n_theta", "n_x", "seed", "method"), [
    (16, 7, 11, 1, "joseph"), (9, 12, 20, 2, "binary"), (32, 45, 40, 4, "joseph")])
def test_the_system_matrix_is_the_projector(n, n_theta, n_x, seed, method):
    """system_matrix(g) @ σ is forward(g, σ) and its transpose is adjoint(g, ·), in float64 to 1e-12 relative (the
    same weights, summed in another order), with angles on both walking axes, the 45° tie and rays partly outside
    the grid; several slices at once are one product."""
    rng = np.random.default_rng(seed)
    theta = np.sort(rng.uniform(0, 180, n_theta))
    theta[0] = 45.0
    g = Geometry.from_grids(theta, np.linspace(-1.3, 1.3, n_x), n, 1.0, method)
    matrix = system_matrix(g, np.float64)
    assert matrix.shape == (n_theta * n_x, n * n)
    with jax.enable_x64(True):
        images, sinograms = rng.normal(size=(3, n, n)), rng.normal(size=(3, *g.shape))
        expected_forward = np.asarray(forward(g, jnp.asarray(images)))
        expected_adjoint = np.asarray(adjoint(g, jnp.asarray(sinograms)))
    ours_forward = (matrix @ images.reshape(3, -1).T).T.reshape(3, *g.shape)
    ours_adjoint = (matrix.T @ sinograms.reshape(3, -1).T).T.reshape(3, n, n)
    np.testing.assert_allclose(ours_forward, expected_forward, rtol=1e-12, atol=1e-12 * np.abs(expected_forward).max())
    np.testing.assert_allclose(ours_adjoint, expected_adjoint, rtol=1e-12, atol=1e-12 * np.abs(expected_adjoint).max())


def test_projector_matches_the_analytic_radon_transform_of_disks():
    """Joseph on the cell-averaged raster vs exact chords: 2% RMS (discretisation of the disk edges)."""
    g = Geometry.from_grids(np.arange(180.0), np.linspace(-L, L, 128), 128, L)
    truth = disk_radon(np.arange(180.0)[:, None], np.linspace(-L, L, 128)[None, :])
    ours = np.asarray(forward(g, jnp.asarray(disk_raster(128), jnp.float32)))
    assert rmse(ours, truth) / np.sqrt(np.mean(truth**2)) < 0.02


def test_projector_agrees_with_scikit_image_radon():
    """ours(θ, X) = radon(flipud(image), θ) at detector offset X (skimage's rows run down, y up):
    within 2.5% RMS (skimage rotates and resamples the image; we walk rays)."""
    n = 129
    theta = np.arange(0.0, 180.0, 3.0)
    g = Geometry.from_grids(theta, np.linspace(-L, L, n), n, L)
    image = resize(shepp_logan_phantom(), (n, n))
    ours = np.asarray(forward(g, jnp.asarray(image, jnp.float32)))
    peer = radon(np.flipud(image), theta=theta, circle=False)
    detector = (np.arange(peer.shape[0]) - (peer.shape[0] - 1) / 2) * g.cell
    peer = np.array([np.interp(g.x, detector, peer[:, i]) for i in range(len(theta))]) * g.cell
    assert rmse(ours, peer) / np.sqrt(np.mean(peer**2)) < 0.025


def test_ramp_response_is_the_ramp_at_low_frequency():
    size, spacing = 256, 0.1
    f = np.fft.fftfreq(size)[2:20] / spacing  # cycles per length; the spatial ramp dips below |f| at bin 1
    assert ramp_response(size, spacing)[2:20] == pytest.approx(np.abs(f), rel=0.02)
    assert ramp_response(size, spacing)[0] > 0  # no DC hole: a constant's level survives the filter


def test_fbp_recovers_disks_from_full_data():
    out = fbp(sinogram(180, 128)).compute()
    truth = disk_raster(128)
    assert rmse(out["sigma"][0], truth) < 6e-3  # 2.4% of the 0.25 peak
    assert float(out["sigma"][0, 64, 64]) == pytest.approx(0.25, abs=5e-3)  # the centre: 0.2 + 0.05


def test_tv_recovers_full_noise_free_data_within_the_box():
    out = reconstruct_tv(sinogram(90, 64), tv_weight=1e-3, max_iter=200, tol=1e-4).compute()
    sigma, upper = out["sigma"][0].values, out["sigma_max"][0].values
    assert rmse(sigma, disk_raster(64)) < 5e-3
    assert (sigma >= 0).all() and (sigma <= upper * (1 + 1e-6)).all()  # the reported iterate is feasible
    objective = out["objective"][0].values
    done = int(out["iterations"][0])
    assert bool(out["converged"][0]) and done < 200
    assert np.isnan(objective[done:]).all() and np.isfinite(objective[:done]).all()
    assert objective[done - 1] < 0.05 * objective[0]  # the objective falls ...
    assert objective[done - 1] <= np.min(objective[: done // 2]) * (1 + 1e-3)  # ... and ends near its lowest


def test_tv_beats_fbp_when_the_sides_are_missing():
    """The Fig. 18 situation: |X| > 0.6 unobserved. The box, support and TV recover what FBP cannot."""
    x = np.linspace(-L, L, 64)
    observed = np.broadcast_to(np.abs(x) <= 0.6, (90, 64)).copy()
    data = sinogram(90, 64, observed)
    truth = disk_raster(64)
    tv = reconstruct_tv(data, tv_weight=1e-3, max_iter=200).compute()["sigma"][0]
    plain = fbp(data).compute()["sigma"][0]
    assert rmse(tv, truth) < 0.7 * rmse(plain, truth)


def test_physical_bound_never_cuts_the_truth():
    """σ_max of Eq. 26 (with the bracketing rule) stays above the cell-averaged truth everywhere."""
    g = Geometry.from_grids(np.arange(0.0, 180.0, 2.0), np.linspace(-L, L, 64), 64, L)
    values = disk_radon(np.asarray(g.theta_deg)[:, None], np.asarray(g.x)[None, :])
    bound = upper_bound(values, np.ones(g.shape, bool), g)
    assert (bound >= disk_raster(64) - 1e-9).all()
    yy, xx = np.meshgrid(g.centres, g.centres, indexing="ij")
    ring = (np.hypot(xx, yy) > 0.9) & (np.hypot(xx, yy) < 0.95)  # outside the object: every ray there is 0
    assert ring.sum() > 50 and (bound[ring] == 0).all()


def test_simulated_sinogram_is_exact_and_truth_matches_it():
    """simulate_sinogram's values are the exact chords of the scene; its truth raster projects onto them."""
    scene = str(workflows.scene("phantom-cylinder"))
    data = simulate_sinogram(scene=scene, light_angle_deg=60.0, n_theta=60, n_x=64, angles=AngleSweep(step=3.0))
    assert 0.5 < float(data["observed"].mean()) < 1.0
    g = Geometry.from_grids(data["theta"].values, data["x"].values, 128, float(data.x_extent))
    from selpath.devices.sim.scene import load_scene

    raster = truth_raster(load_scene(scene), 128, float(data.x_extent))
    projected = np.asarray(forward(g, jnp.asarray(raster, jnp.float32)))
    values = data["absorption"][0].values
    # 3.2% at n = 128: the skull rim of the phantom is 0.3 mm thin, 2 cells (discretisation, not a bias)
    assert rmse(projected, values) / np.sqrt(np.mean(values**2)) < 0.04


def test_reconstruction_stages_stay_lazy(no_compute):
    data = sinogram(12, 16)
    fbp(data)
    reconstruct_tv(data, max_iter=3)
    assert no_compute.count == 0


def _convex(seed, count=40):
    from scipy.spatial import ConvexHull

    points = np.random.default_rng(seed).normal(scale=0.4, size=(count, 2))
    return points[ConvexHull(points).vertices]  # counter-clockwise


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_support_mask_row_intervals_equal_the_cross_product_test(seed):
    """The row-interval rasterisation equals the per-edge cross-product test (the definition) on every cell
    farther than 1e-9 from an edge."""
    g = Geometry.from_grids([0.0], np.linspace(-L, L, 5), 97, L)
    polygon = _convex(seed)
    yy, xx = np.meshgrid(g.centres, g.centres, indexing="ij")
    cross = np.array([(b[0] - a[0]) * (yy - a[1]) - (b[1] - a[1]) * (xx - a[0])
                      for a, b in zip(polygon, np.roll(polygon, -1, axis=0), strict=True)])
    clear = (np.abs(cross) > 1e-9).all(axis=0)
    assert clear.mean() > 0.99 and 0.05 < (cross >= 0).all(axis=0).mean() < 0.95
    np.testing.assert_array_equal(support_mask(polygon, g)[clear], (cross >= 0).all(axis=0)[clear])


def test_linear_fill_equals_numpy_interp_row_by_row():
    rng = np.random.default_rng(4)
    values = rng.normal(size=(3, 7, 30))
    known = rng.random(values.shape) < 0.4
    known[0, 0] = False  # a row with nothing known: zeros
    known[0, 1] = True  # a row with everything known: itself
    filled = _fill_missing(values, known, "linear")
    index = np.arange(30)
    for s in range(3):
        for t in range(7):
            have = known[s, t]
            expect = values[s, t].copy() if have.all() else np.zeros(30)
            if have.any() and not have.all():
                expect = np.where(have, values[s, t], np.interp(index, index[have], values[s, t, have], 0.0, 0.0))
            np.testing.assert_allclose(filled[s, t], expect, rtol=0, atol=1e-12)


def test_batched_backprojection_and_reliability_equal_brute_force():
    """The compiled, batched pixel-driven back-projection equals a numpy loop of ``np.interp`` per angle on the
    sinogram padded with a zero bin each side (float64, 1e-9), and the reliable cells equal the definition: the nearest
    bin known at every θ (exactly, on a grid where
    cell centres fall on half-bins, the ties)."""
    g = Geometry.from_grids(np.arange(0.0, 180.0, 7.5), np.linspace(-L, L, 33), 32, L)
    rng = np.random.default_rng(5)
    sinograms = rng.normal(size=(3, *g.shape))
    yy, xx = np.meshgrid(g.centres, g.centres, indexing="ij")
    xs, step = np.asarray(g.x), 2 * L / 32
    padded = np.concatenate([[xs[0] - step], xs, [xs[-1] + step]])
    expect = np.zeros((3, 32, 32))
    for i, angle in enumerate(np.deg2rad(g.theta_deg)):
        proj = xx * np.cos(angle) + yy * np.sin(angle)
        for s in range(3):
            expect[s] += np.interp(proj, padded, np.pad(sinograms[s, i], 1), left=0.0, right=0.0)
    expect *= np.pi / len(g.theta_deg)
    with jax.enable_x64(True):
        batched = np.asarray(backproject(g, jnp.asarray(sinograms)))
        one = np.asarray(backproject(g, jnp.asarray(sinograms[1])))
    np.testing.assert_allclose(batched, expect, atol=1e-9)
    np.testing.assert_allclose(one, expect[1], atol=1e-9)
    known = rng.random((3, *g.shape)) < 0.97
    reliable = np.ones((3, 32, 32), bool)
    for i, angle in enumerate(np.deg2rad(g.theta_deg)):
        j = np.rint((xx * np.cos(angle) + yy * np.sin(angle) - xs[0]) / step).astype(int)
        reliable &= (j >= 0) & (j < len(xs)) & known[:, i, np.clip(j, 0, len(xs) - 1)]
    assert 0.05 < reliable.mean() < 0.95
    np.testing.assert_array_equal(reliable_cells(known, g), reliable)
    np.testing.assert_array_equal(reliable_cells(known[2], g), reliable[2])


def test_fbp_of_a_batch_equals_fbp_of_each_slice():
    """Slices reconstructed in one batch (one task, one compiled loop) equal each slice reconstructed alone
    (float32 rounding)."""
    one = sinogram(45, 64)
    scaled = [one.assign(absorption=one["absorption"] * f).assign_coords(slice=[k]) for k, f in enumerate((1, .5, 2))]
    stack = xr.concat(scaled, "slice").chunk({"slice": 3})
    batch = fbp(stack, fill="linear")
    assert batch["sigma"].data.numblocks[0] == 1
    alone = [fbp(s, fill="linear")["sigma"].values for s in scaled]
    np.testing.assert_allclose(batch["sigma"].values, np.concatenate(alone), atol=1e-6)
