"""Silhouettes → visual hull → aligned rays → sinogram → coverage, against closed forms (§4.2.6–4.2.7)."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from scipy.spatial.distance import directed_hausdorff

from selpath.pipeline import FORMAT_VERSION, StageError, open_store
from selpath.pipeline.integrity import write_manifest
from selpath.stages.tomography.calibrate import absorption
from selpath.stages.tomography.coverage import coverage, coverage_model, optimal_light_angle
from selpath.stages.tomography.hull import hull_polygons, silhouettes, visual_hull
from selpath.stages.tomography.paths import REASONS, align_paths
from selpath.stages.tomography.reconstruct import fbp, reconstruct_tv
from selpath.stages.tomography.sinogram import bin_sinogram
from tests.helpers.tomography import R, capture, cylinder_camera, lazy_chain, make_scene

#: θ_l × camera pairs the default job keeps (both sides of the optimum, each camera model); the other 12 run in the
#: slow job (about 6.5 s each)
_COVERAGE_DEFAULT = {(30.0, None), (60.0, 30.0), (120.0, 60.0)}


@pytest.mark.parametrize(("theta_l", "fov"), [
    pytest.param(theta_l, fov, id=f"{theta_l}-{name}",
                 marks=() if (theta_l, fov) in _COVERAGE_DEFAULT else pytest.mark.slow)
    for fov, name in ((None, "orthographic"), (30.0, "fov30"), (60.0, "fov60"))
    for theta_l in (0.0, 30.0, 60.0, 90.0, 120.0)])
def test_measured_coverage_matches_eq_8_to_19(theta_l, fov):
    """A cylinder's sinogram is observed exactly on d_min <= |X|/R <= d_max of Eq. 8–19, to one X bin.

    The bin is 2·1.02/63 = 0.032 in d; the camera's sampling near the tangents costs below 0.012
    (2048 columns). The missing areas fall at the sides for θ_l below the optimum, at the centre above.
    """
    scene = make_scene({"kind": "cylinder", "radius": f"{R} mm"}, cylinder_camera(fov), theta_l)
    cap = capture(scene, np.arange(0.0, 360.0, 2.0))
    hull = visual_hull(silhouettes(cap))
    sino = bin_sinogram(align_paths(absorption(cap), hull), n_theta=90, n_x=64, x_extent=1.02 * R)
    got = coverage(sino, hull).compute().isel(slice=0)
    d_min, d_max, cov = (float(v) for v in coverage_model(theta_l, fov))
    step = 2 * 1.02 / 63
    assert float(got.d_min) == pytest.approx(d_min, abs=step)
    assert float(got.d_max) == pytest.approx(d_max, abs=step)
    assert float(got.coverage) == pytest.approx(cov, abs=step)
    assert float(got.analytic_coverage) == pytest.approx(cov, abs=2e-3)  # hull radius within 0.1%
    if theta_l < optimal_light_angle(fov) - 1e-9:
        assert d_min == 0.0 and d_max < 1.0  # sides missing (Fig. 14, θ_l = 30°, 60°)
    elif fov is not None and theta_l > (180.0 + fov) / 2:
        assert d_min > 0.0 and d_max == 1.0  # centre missing (Fig. 14, θ_l = 120°)


def test_coverage_model_peaks_at_the_optimal_angle():
    angles = np.linspace(0, 180, 3601)
    for fov in (None, 30.0, 60.0):
        best = angles[np.argmax(coverage_model(angles, fov)[2])]
        assert best == pytest.approx(optimal_light_angle(fov), abs=0.1)
    assert np.all(coverage_model(angles, 60.0)[2] <= coverage_model(angles, 30.0)[2] + 1e-12)  # Fig. 16
    assert coverage_model(angles, 30.0)[2].max() < 1.0  # never complete with a perspective camera


PENTAGON = [[10.0 * np.cos(a), 10.0 * np.sin(a) + 1.0] for a in np.deg2rad(90 + 72 * np.arange(5))]


def polygon_boundary(vertices, n=4000) -> np.ndarray:
    v = np.asarray(vertices, float)
    edges = [(v[i], v[(i + 1) % len(v)]) for i in range(len(v))]
    return np.concatenate([a + np.linspace(0, 1, n // len(v), endpoint=False)[:, None] * (b - a) for a, b in edges])


@pytest.mark.parametrize("camera", [
    {"model": "orthographic", "rows": 1, "cols": 512, "pixel_size": "0.05 mm"},
    {"model": "perspective", "rows": 1, "cols": 512, "distance": "40 mm", "fov": "40 deg"},
], ids=["orthographic", "perspective"])
def test_visual_hull_of_a_convex_polygon_converges_with_views(camera):
    """Hausdorff distance to the true pentagon shrinks with the number of views, to the hull resolution."""
    shape = {"kind": "polygon", "vertices": [[f"{x} mm", f"{y} mm"] for x, y in PENTAGON]}
    scene = make_scene(shape, camera, 45.0)
    truth = polygon_boundary(PENTAGON)
    distances = []
    for n in (3, 6, 12, 48, 180):
        hull = visual_hull(silhouettes(capture(scene, np.arange(n) * 360.0 / n))).compute()
        polygon = hull_polygons(hull)[0]
        estimate = polygon_boundary(polygon)
        distances.append(max(directed_hausdorff(truth, estimate)[0], directed_hausdorff(estimate, truth)[0]))
    assert all(a >= b for a, b in zip(distances, distances[1:], strict=False)), distances
    assert distances[-1] < 4 * float(hull.hull_resolution) + 0.05, (distances, float(hull.hull_resolution))
    assert distances[0] > 5 * distances[-1]


def disk_radon(theta_deg, x, centre, radius, sigma):
    n = np.stack([np.cos(np.deg2rad(theta_deg)), np.sin(np.deg2rad(theta_deg))], axis=-1)
    offset = x - n @ np.asarray(centre)
    return 2 * sigma * np.sqrt(np.clip(radius**2 - offset**2, 0, None))


@pytest.mark.parametrize("camera", [cylinder_camera(None, 256), cylinder_camera(30.0, 256)],
                         ids=["orthographic", "perspective"])
def test_observed_sinogram_bins_equal_the_analytic_radon_transform(camera):
    """Noise-free straight paths: every observed bin lies within the range the analytic Radon transform
    of the phantom takes over that bin (± the hull's resolution in X): the discretisation error."""
    disks = [((3.0, 2.0), 2.5, 0.2), ((-4.0, -3.0), 1.5, 0.5)]
    inclusions = [{"shape": {"kind": "cylinder", "radius": f"{r} mm", "centre": [f"{c[0]} mm", f"{c[1]} mm"]},
                   "sigma": f"{s} /mm"} for c, r, s in disks]
    scene = make_scene({"kind": "cylinder", "radius": f"{R} mm"}, camera, 60.0, inclusions)
    cap = capture(scene, np.arange(0.0, 360.0, 2.0))
    hull = visual_hull(silhouettes(cap))
    sino = bin_sinogram(align_paths(absorption(cap), hull), n_theta=60, n_x=48, x_extent=1.02 * R).compute()
    sino = sino.isel(slice=0)
    resolution = float(hull.hull_resolution)
    d_theta, d_x = float(sino.theta_step_deg), float(sino.x_step)
    t_grid = np.linspace(-d_theta / 2, d_theta / 2, 9)
    x_grid = np.linspace(-(d_x / 2 + resolution), d_x / 2 + resolution, 21)
    observed = np.argwhere(sino["observed"].values)
    assert len(observed) > 0.4 * sino["observed"].size
    for i, j in observed:
        theta, x = sino["theta"].values[i] + t_grid[:, None], sino["x"].values[j] + x_grid[None, :]
        truth = sum(disk_radon(theta, x, c, r, s) for c, r, s in disks)
        value = float(sino["absorption"].values[i, j])
        assert truth.min() - 1e-9 <= value <= truth.max() + 1e-9, (i, j, value, truth.min(), truth.max())


def test_grazing_rays_and_tangent_contours_stay_finite_and_are_counted():
    """A square seen edge-on (tangent faces) under a grazing beam: every kept ray is finite, every dropped
    pixel has its reason, and the counts add up."""
    square = {"kind": "polygon", "vertices": [["-8 mm", "-8 mm"], ["8 mm", "-8 mm"], ["8 mm", "8 mm"],
                                              ["-8 mm", "8 mm"]]}
    scene = make_scene(square, cylinder_camera(None, 256), 90.0)  # the beam runs along a face at 0°
    cap = capture(scene, np.arange(0.0, 360.0, 15.0))
    rays = align_paths(absorption(cap), visual_hull(silhouettes(cap)), min_exit_cos=0.05).compute()
    kept = rays["reason"].values == 0
    assert np.isfinite(rays["theta"].values[kept]).all() and np.isfinite(rays["x"].values[kept]).all()
    assert np.isnan(rays["theta"].values[~kept]).all()
    reasons = dict(zip(*np.unique(rays["reason"].values, return_counts=True), strict=True))
    assert set(reasons) <= {0, *REASONS}
    assert reasons.get(1, 0) > 0  # pixels beside the object
    assert sum(reasons.values()) == rays["reason"].size
    assert ((rays["theta"].values[kept] >= 0) & (rays["theta"].values[kept] < 180)).all()


def test_empty_rows_and_a_missed_beam_give_explicit_masks():
    """Rows without object get no contour (counted views), and a beam that misses gives reason 3."""
    off_axis = {"kind": "cylinder", "radius": "3 mm", "centre": ["6 mm", "0 mm"]}
    camera = {"model": "orthographic", "rows": 3, "cols": 128, "pixel_size": "0.2 mm"}
    scene = make_scene(off_axis, camera, 0.0)
    cap = capture(scene, np.arange(0.0, 360.0, 30.0))
    cap["backlit"][:, 0, :] = 2064.0  # row 0: the object never blocks the light (empty silhouettes)
    hull = visual_hull(silhouettes(cap, min_size=0)).compute()
    assert int(hull["n_vertices"][0]) == 0 and int(hull["empty_views"][0]) == 12
    assert int(hull["n_vertices"][1]) >= 3
    rays = align_paths(absorption(cap), hull).compute()
    assert (rays["reason"].isel(row=0) == 6).all()
    assert (rays["reason"].isel(row=1) == 3).any()  # the beam along the axis misses an off-axis cylinder


def test_stages_stay_lazy(no_compute):
    lazy_chain()
    assert no_compute.count == 0


@pytest.mark.parametrize("old_format", [1, 2])
def test_a_hull_of_the_old_layout_opens_and_feeds_every_stage(tmp_path, old_format):
    """Formats 1–2 indexed the hull by ``row``, without a coordinate: open_store migrates it to ``slice`` (the
    camera rows as coordinate), and align_paths, coverage, fbp and reconstruct_tv give exactly what they give
    with a new hull. The old layout handed over in memory is refused, saying how to read it."""
    camera = {"model": "perspective", "rows": 3, "cols": 128, "distance": "60 mm", "focal_length": "200 px"}
    scene = make_scene({"kind": "cylinder", "radius": f"{R} mm"}, camera, 60.0)
    cap = capture(scene, np.arange(0.0, 360.0, 15.0))
    hull = visual_hull(silhouettes(cap)).compute()
    old = hull.drop_vars("slice").rename(slice="row").assign_attrs(selpath_format=old_format, selpath_kind="hull")
    old.to_zarr(tmp_path / "hull.zarr", consolidated=False, write_empty_chunks=True)
    write_manifest(tmp_path / "hull.zarr", old)
    opened = open_store(tmp_path / "hull.zarr")
    xr.testing.assert_identical(opened.load(), hull.assign_attrs(selpath_format=FORMAT_VERSION, selpath_kind="hull"))

    rays = align_paths(absorption(cap), opened)
    xr.testing.assert_identical(rays.compute(), align_paths(absorption(cap), hull).compute())
    sino = bin_sinogram(rays, n_theta=12, n_x=32, x_extent=1.02 * R).compute()
    xr.testing.assert_identical(coverage(sino, opened).compute(), coverage(sino, hull).compute())
    xr.testing.assert_identical(fbp(sino, opened).compute(), fbp(sino, hull).compute())
    xr.testing.assert_identical(reconstruct_tv(sino, opened, max_iter=5).compute(),
                                reconstruct_tv(sino, hull, max_iter=5).compute())
    for stage in (lambda h: align_paths(absorption(cap), h), lambda h: coverage(sino, h), lambda h: fbp(sino, h)):
        with pytest.raises(StageError, match=r"the hull has no slice coordinate .*fix: open its store with "
                                             r"selpath\.open_store, which migrates"):
            stage(old)


def test_coverage_takes_the_light_angle_from_the_sinogram_when_the_hull_lacks_it():
    """As before the geometry refactor: a hull without light_angle_deg (valid for its kind) is enough."""
    _, hull, sino, cover = lazy_chain()
    bare = hull.assign_attrs({k: v for k, v in hull.attrs.items() if k != "light_angle_deg"})
    bare.attrs.pop("light_angle_deg", None)
    assert "light_angle_deg" not in bare.attrs and "light_angle_deg" in sino.attrs
    xr.testing.assert_identical(coverage(sino, bare).compute(), cover.compute())


def test_bins_finer_than_the_views_are_warned_of_and_leave_a_checkerboard():
    """A user's report: 4° views binned into 180 θ bins observed about half the bins that 45 bins observe, without
    a word. A ray's θ is its view's angle plus its pixel's offset, so at a fixed X only one bin in four holds one.
    Measured on this cylinder (n_x 128): 0.527 of the bins observed at 180, 0.938 at 45."""
    import warnings

    scene = make_scene({"kind": "cylinder", "radius": f"{R} mm"}, cylinder_camera(None, 512), 60.0)
    cap = capture(scene, np.arange(0.0, 360.0, 4.0))
    rays = align_paths(absorption(cap), visual_hull(silhouettes(cap))).compute()
    with pytest.warns(UserWarning, match=r"n_theta = 180 makes 1° bins, finer than the 4° between views.*"
                                         r"one θ bin in 4 holds a ray.*n_theta ≤ 45"):
        fine = bin_sinogram(rays, n_theta=180, n_x=128, x_extent=1.02 * R)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        coarse = bin_sinogram(rays, n_theta=45, n_x=128, x_extent=1.02 * R)
    assert float(fine["observed"].mean()) < 0.6 < 0.9 < float(coarse["observed"].mean())


def test_a_dimensionless_length_unit_runs_the_chain_with_sigma_per_that_unit(tmp_path):
    """Renders in scene units (object radius 1) had no length_unit to state. With "1" every stage runs; lengths
    carry "1" and σ too (not "1/1"); the numbers are those of the same rig labelled in mm."""
    from selpath.pipeline import to_store

    scene = make_scene({"kind": "cylinder", "radius": f"{R} mm"}, cylinder_camera(None, 64), 60.0,
                       inclusions=[{"shape": {"kind": "cylinder", "radius": "3 mm"}, "sigma": "0.05 /mm"}])
    mm = capture(scene, np.arange(0.0, 360.0, 10.0))
    unitless = mm.assign_attrs(length_unit="1")
    results = {}
    for name, cap in (("mm", mm), ("1", unitless)):
        hull = visual_hull(silhouettes(cap))
        sino = bin_sinogram(align_paths(absorption(cap), hull), n_theta=18, n_x=32, x_extent=1.02 * R)
        results[name] = fbp(sino, hull).compute()
        to_store(results[name], tmp_path / f"{name}.zarr", "reconstruction")  # the schema accepts it
    got = open_store(tmp_path / "1.zarr")
    assert got["x"].attrs["units"] == "1" and got["sigma"].attrs["units"] == "1"
    assert open_store(tmp_path / "mm.zarr")["sigma"].attrs["units"] == "1/mm"
    np.testing.assert_array_equal(got["sigma"].values, results["mm"]["sigma"].values)


def _filled_by_hand(observed: np.ndarray) -> float:
    """filled_fraction by its definition, bin by bin: a bin is between observed bins when both X neighbours or
    both θ neighbours hold a ray; θ wraps to 0° with X mirrored."""
    n_theta, n_x = observed.shape[-2:]
    hits = between = 0
    for s in np.ndindex(observed.shape[:-2]):
        o = observed[s]
        for i in range(n_theta):
            for j in range(n_x):
                x_pair = 0 < j < n_x - 1 and o[i, j - 1] and o[i, j + 1]
                before = o[i - 1, j] if i > 0 else o[n_theta - 1, n_x - 1 - j]
                after = o[i + 1, j] if i < n_theta - 1 else o[0, n_x - 1 - j]
                if x_pair or (before and after):
                    between += 1
                    hits += bool(o[i, j])
    return hits / max(between, 1)


@pytest.mark.parametrize("seed", range(4))
def test_filled_fraction_counts_the_holes_between_observed_bins(seed):
    """Against the definition evaluated bin by bin, on random masks (dense and sparse), the θ wrap included."""
    from selpath.stages.tomography.sinogram import filled_share

    rng = np.random.default_rng(seed)
    observed = rng.random((2, 7, 9)) < (0.3, 0.6, 0.8, 0.95)[seed]
    got = filled_share(xr.DataArray(observed, dims=("slice", "theta", "x")), (7, 9))
    assert float(got) == pytest.approx(_filled_by_hand(observed), abs=1e-12)
    full = filled_share(xr.DataArray(np.ones((1, 4, 5), bool), dims=("slice", "theta", "x")), (4, 5))
    assert float(full) == 1.0


def test_default_bins_follow_the_capture_and_fill_it():
    """Without n_theta/n_x: one θ bin per view step (4° → 45) and one X bin per pixel pitch at the axis, which over
    the default extent (the sensor's width at the axis) is cols + 1. These bins fill ≥ 97 % of the bins between
    observed ones (measured 98.6 %); twice finer in θ and thrice in X fill under half (measured 0.18), with a
    warning for each and the capture's counts in the advice."""
    import warnings

    from selpath.pipeline.quality import ADVISE, FIX

    cols = 160
    scene = make_scene({"kind": "cylinder", "radius": f"{R} mm"}, cylinder_camera(30.0, cols), 45.0)
    cap = capture(scene, np.arange(0.0, 360.0, 4.0))
    rays = align_paths(absorption(cap), visual_hull(silhouettes(cap))).compute()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sino = bin_sinogram(rays)
    assert (sino.sizes["theta"], sino.sizes["x"]) == (45, cols + 1)
    assert (sino.attrs["capture_n_theta"], sino.attrs["capture_n_x"]) == (45, cols + 1)
    filled = sino["filled_fraction"]
    assert float(filled) >= filled.attrs[ADVISE] == 0.97
    assert "n_theta ≤ 45, n_x ≤ 161" in filled.attrs[FIX]
    with pytest.warns(UserWarning) as record:
        fine = bin_sinogram(rays, n_theta=90, n_x=3 * cols)
    assert any("finer than the 4° between views" in str(w.message) for w in record)
    assert any("less than half the" in str(w.message) and "n_x ≤ 161" in str(w.message) for w in record)
    assert float(fine["filled_fraction"]) < 0.5
    assert (fine.attrs["capture_n_theta"], fine.attrs["capture_n_x"]) == (45, cols + 1)
