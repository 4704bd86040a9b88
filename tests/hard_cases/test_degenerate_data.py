"""Degenerate data never gives confident zeros: all-NaN, all-zero, all-saturated captures, impossible dark frames,
another intensity scale, one or two views, repeated or unsorted angles, mismatched frames, eager sinograms.
Each either stops with the share that was usable and the setting to change, or is handled and said."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest
import xarray as xr

from selpath.pipeline import StageError, load_workflow, run_workflow, to_store
from selpath.pipeline.quality import enforce
from selpath.stages._common import UnsortedSweepWarning
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.calibrate import absorption
from selpath.stages.tomography.hull import silhouettes, visual_hull
from selpath.stages.tomography.paths import align_paths
from selpath.stages.tomography.reconstruct import fbp, reconstruct_tv
from selpath.stages.tomography.simulate import simulate_parallel_capture
from selpath.stages.tomography.sinogram import bin_sinogram
from tests.helpers.tomography import capture as simulated
from tests.helpers.tomography import cylinder_camera, make_scene


@pytest.fixture(scope="module")
def clean() -> xr.Dataset:
    return simulate_parallel_capture(angles=AngleSweep(start=0, stop=40, step=5), n_rows=3, n_cols=48,
                                     pixel_size=1.0, noise_std=1.5).load()


def _broken(clean: xr.Dataset, case: str) -> xr.Dataset:
    frames = ("target", "reference", "backlit")
    if case == "all-NaN":
        return clean.assign({v: clean[v] * np.nan for v in frames})
    if case == "all-zero":
        return clean.assign({v: clean[v] * 0 for v in (*frames, "dark")})
    if case == "all-saturated":
        return clean.assign({v: clean[v] * 0 + 4095.0 for v in frames})
    if case == "dark above the frames":
        return clean.assign(dark=clean["dark"] + 1e6)
    if case == "dark of -1000":
        return clean.assign(dark=clean["dark"] * 0 - 1000.0)
    raise ValueError(case)


EXPECTED = {
    "all-NaN": "signal_fraction: only 0.00% of reference pixels with usable signal",
    "all-zero": "signal_fraction: only 0.00% of reference pixels with usable signal",
    "all-saturated": "signal_fraction: only 0.00% of reference pixels with usable signal",
    "dark above the frames": "signal_fraction: only 0.00% of reference pixels with usable signal",
    "dark of -1000": "dark_fraction: only 0.00% of dark pixels at or above 0 counts",
}


@pytest.mark.parametrize("case", list(EXPECTED))
def test_a_degenerate_capture_stops_the_run_and_writes_nothing(tmp_path, clean, case):
    """Each of these completed with σ ≡ 0 (or A compressed toward 0) and exit code 0."""
    to_store(_broken(clean, case), tmp_path / "capture.zarr", "tomography_capture")
    (tmp_path / "wf.yaml").write_text("workflow: d\nsteps:\n"
                                      "  - {id: c, stage: load_store, with: {store: capture.zarr}}\n"
                                      "  - {id: a, stage: absorption, with: {capture: $c, min_signal: 1.0}}\n"
                                      "outputs:\n  a: {from: a, store: absorption.zarr}\n")
    with pytest.raises(StageError, match=re.escape(EXPECTED[case])) as info:
        run_workflow(load_workflow(tmp_path / "wf.yaml"), progress=False)
    assert "step 'a'" in str(info.value) and "(fix: " in str(info.value)
    assert sorted(os.listdir(tmp_path)) == ["capture.zarr", "wf.yaml"]


def test_another_intensity_scale_needs_the_relative_threshold(clean):
    """Radiance-scale data (here counts / 1e4) with the shipped `min_signal: 1.0` flagged every pixel and gave
    σ ≡ 0. Now it stops, and `min_signal_relative` gives the counts-scale result (A is scale-free)."""
    scaled = (clean / 1e4).assign_attrs(clean.attrs | {"saturation_counts": 4095 / 1e4})
    with pytest.raises(StageError, match=r"only 0.00% of reference pixels.*set min_signal_relative"):
        enforce(absorption(scaled, min_signal=1.0))
    relative = absorption(scaled, min_signal=0.0, min_signal_relative=0.01)
    counts = absorption(clean, min_signal=0.0, min_signal_relative=0.01)
    shares = enforce(relative)
    assert shares["usable_fraction"] > 0.9 and shares["signal_fraction"] > 0.5
    np.testing.assert_array_equal(relative["flags"].values, counts["flags"].values)
    np.testing.assert_allclose(relative["absorption"].values, counts["absorption"].values, rtol=1e-5, atol=1e-6)


def test_the_relative_threshold_flags_dim_pixels_of_each_frame(clean):
    """A pixel under 1 % of its frame's brightest unsaturated reference pixel is NO_SIGNAL (bit 2 / 16)."""
    result = absorption(clean, min_signal_relative=0.5)
    corrected = (clean["reference"] - clean["dark"]).values
    peak = np.nanmax(np.where(clean["reference"].values < 4095, corrected, np.nan), axis=(1, 2))
    dim = corrected <= 0.5 * peak[:, None, None]
    assert dim.any() and ((result["flags"].values & 16) > 0).tolist() == dim.tolist()


def test_repeated_angles_are_refused_and_unsorted_ones_sorted(clean):
    repeated = clean.assign_coords(angle=("angle", np.r_[clean["angle"].values[:-1], 0.0], {"units": "degree"}))
    with pytest.raises(StageError, match=r"coordinate 'angle' repeats \[0.0\] \(1 duplicate frame\(s\)\)"):
        absorption(repeated)
    shuffled = clean.isel(angle=[3, 0, 7, 1, 2, 6, 5, 4])
    with pytest.warns(UnsortedSweepWarning, match="coordinate 'angle' is not sorted; frames were reordered"):
        result = absorption(shuffled)
    xr.testing.assert_identical(result["absorption"], absorption(clean)["absorption"])


def test_a_reference_of_another_shape_names_both_shapes(clean):
    other = clean.assign(reference=clean["reference"].isel(angle=0, drop=True))
    with pytest.raises(StageError, match=re.escape("reference has dims ('row', 'col') and shape (3, 48), target "
                                                   "('angle', 'row', 'col') and (8, 3, 48); they must match")):
        absorption(other)


@pytest.mark.parametrize("angles", [[0.0], [0.0, 90.0]], ids=["one view", "two views"])
def test_one_or_two_views_are_too_few_for_a_reconstruction(angles):
    scene = make_scene({"kind": "cylinder", "radius": "10 mm"}, cylinder_camera(40.0, cols=256), 45.0)
    cap = simulated(scene, np.array(angles))
    rays = align_paths(absorption(cap), visual_hull(silhouettes(cap)))
    if len(angles) > 1:  # 2° bins against views 90° apart: the binning says so too
        with pytest.warns(UserWarning, match=r"finer than the 180° between views.*n_theta ≤ 1\b"):
            sinogram = bin_sinogram(rays, n_theta=90, n_x=64, x_extent=10.2)
    else:
        sinogram = bin_sinogram(rays, n_theta=90, n_x=64, x_extent=10.2)
    with pytest.raises(StageError, match=r"observed_fraction: only \d.\d\d% of sinogram bins holding a ray \(floor "
                                         r"5.00%\).*capture more angles"):
        enforce(sinogram)
    many = simulated(scene, np.arange(0.0, 360.0, 10.0))
    assert enforce(bin_sinogram(align_paths(absorption(many), visual_hull(silhouettes(many))), n_theta=18, n_x=64,
                                x_extent=10.2))["observed_fraction"] > 0.3


def test_reconstructions_take_an_eager_sinogram_as_a_lazy_one():
    """fbp and reconstruct_tv on a loaded (numpy) sinogram raised a map_blocks ValueError."""
    scene = make_scene({"kind": "cylinder", "radius": "10 mm"}, cylinder_camera(40.0, cols=128), 45.0)
    cap = simulated(scene, np.arange(0.0, 360.0, 10.0))
    hull = visual_hull(silhouettes(cap))
    lazy = bin_sinogram(align_paths(absorption(cap), hull), n_theta=18, n_x=32, x_extent=10.2)
    eager = lazy.load()
    for method in (fbp, lambda s, h: reconstruct_tv(s, h, max_iter=20)):
        xr.testing.assert_allclose(method(eager, hull.load())["sigma"].compute(), method(lazy, hull)["sigma"].compute())


def test_a_silhouette_less_capture_is_named(clean, tmp_path):
    dark_backlit = clean.assign(backlit=clean["backlit"] * np.nan)
    with pytest.raises(StageError, match=r"object_fraction: only 0.00% of backlit frames with a silhouette"):
        enforce(silhouettes(dark_backlit))
