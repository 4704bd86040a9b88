"""Calibration stages against closed forms, with planted bad pixels and a laziness check."""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from selpath.pipeline import StageError
from selpath.stages.tomography.calibrate import (
    BACKGROUND,
    FLAG_MASKS,
    NO_SIGNAL,
    NONFINITE,
    SATURATED,
    absorption,
    normalise_reference,
    subtract_dark,
)
from selpath.stages.tomography.hull import silhouettes

DIMS = ("angle", "row", "col")


def make_capture(target, reference, dark=None, saturation_level=4095.0, chunks=None, backlit=None) -> xr.Dataset:
    data = {"target": (DIMS, target), "reference": (DIMS, reference)}
    if backlit is not None:
        data["backlit"] = (DIMS, backlit)
    if dark is not None:
        data["dark"] = (("row", "col"), dark)
    ds = xr.Dataset(data, coords={"angle": ("angle", np.arange(target.shape[0]) * 1.0, {"units": "degree"})},
                    attrs={"saturation_level": saturation_level})
    return ds.chunk(chunks) if chunks else ds


@pytest.fixture
def closed_form():
    rng = np.random.default_rng(42)
    shape = (6, 7, 9)
    dark = rng.uniform(50, 70, shape[1:])
    incident = rng.uniform(500, 3000, shape)
    a_true = rng.uniform(0, 2.5, shape)
    return make_capture(dark + incident * np.exp(-a_true), dark + incident, dark), a_true


def test_absorption_equals_closed_form(closed_form):
    capture, a_true = closed_form
    out = absorption(capture)
    assert (out["flags"] == 0).all()
    # float64 frames: the log difference is exact to rounding
    np.testing.assert_allclose(out["absorption"].values, a_true, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(normalise_reference(capture)["transmittance"].values, np.exp(-a_true), rtol=1e-12)


def test_float32_frames_stay_float32_within_tolerance(closed_form):
    capture, a_true = closed_form
    out = absorption(capture.astype(np.float32))
    assert out["absorption"].dtype == np.float32
    np.testing.assert_allclose(out["absorption"].values, a_true, rtol=0, atol=2e-5)  # float32 eps · log range


def test_dark_subtraction_first_gives_the_same_result(closed_form):
    capture, _ = closed_form
    capture["target"][0, 0, 0] = 4095.0  # saturated raw count: must still be flagged after dark subtraction
    direct, staged = absorption(capture), absorption(subtract_dark(capture))
    xr.testing.assert_allclose(direct["absorption"], staged["absorption"])
    xr.testing.assert_identical(direct["flags"], staged["flags"])
    assert int(staged["flags"][0, 0, 0]) == SATURATED
    with pytest.raises(StageError, match="'dark' was already subtracted"):
        subtract_dark(subtract_dark(capture))


def test_planted_bad_pixels_get_exact_flags():
    shape = (2, 4, 4)
    reference = np.full(shape, 1000.0)
    target = np.full(shape, 500.0)
    planted = {  # (angle, row, col): (target, reference, expected flags)
        (0, 0, 0): (4095.0, 1000.0, SATURATED),
        (0, 0, 1): (500.0, 5000.0, SATURATED << 3),
        (0, 1, 0): (10.0, 1000.0, NO_SIGNAL),           # equals dark: no signal
        (0, 1, 1): (500.0, 3.0, NO_SIGNAL << 3),          # below dark
        (1, 2, 2): (np.nan, 1000.0, NONFINITE),
        (1, 2, 3): (500.0, np.inf, NONFINITE << 3),
        (1, 3, 3): (4095.0, 10.0, SATURATED | NO_SIGNAL << 3),
    }
    for index, (t, r, _) in planted.items():
        target[index], reference[index] = t, r
    out = absorption(make_capture(target, reference, np.full(shape[1:], 10.0)))
    expected = np.zeros(shape, dtype=np.uint8)
    for index, (_, _, bits) in planted.items():
        expected[index] = bits
    np.testing.assert_array_equal(out["flags"].values, expected)
    values = out["absorption"].values
    assert np.isnan(values[expected != 0]).all()
    np.testing.assert_allclose(values[expected == 0], np.log(990.0 / 490.0), rtol=1e-12)
    assert out["flags"].attrs["flag_meanings"].split()[3] == "reference_saturated"


@settings(max_examples=40, deadline=None)
@given(level=st.floats(1e-3, 1e6), reference=st.floats(1e-3, 1e6))
def test_identical_target_and_reference_give_zero_absorption(level, reference):
    """Invariant: an object identical to its reference absorbs nothing (or is flagged, never wrong)."""
    frames = np.full((1, 2, 2), reference)
    out = absorption(make_capture(frames, frames.copy(), saturation_level=level))
    valid = out["flags"].values == 0
    assert valid.all() == (reference < level)
    np.testing.assert_array_equal(out["absorption"].values[valid], 0.0)


def test_integer_frames_use_the_dtype_maximum_as_saturation():
    target = np.array([[[65535, 1000]]], dtype=np.uint16)
    reference = np.array([[[2000, 2000]]], dtype=np.uint16)
    capture = make_capture(target, reference).drop_attrs()
    capture = capture.assign_coords(angle=("angle", [0.0], {"units": "degree"}))
    out = absorption(capture)
    np.testing.assert_array_equal(out["flags"].values, [[[SATURATED, 0]]])
    np.testing.assert_allclose(out["absorption"].values[0, 0, 1], np.log(2.0), rtol=1e-6)


def test_bad_inputs_are_named():
    frames = np.ones((1, 2, 2))
    with pytest.raises(StageError, match=r"cannot tell saturated pixels of float frames \(fix: set the capture's"):
        absorption(make_capture(frames, frames).drop_attrs())
    orphan = make_capture(frames, frames, np.zeros((2, 2)), saturation_level=9.0)
    with pytest.raises(StageError, match=r"stage 'absorption' needs variable 'dark'"):
        absorption(subtract_dark(orphan).drop_vars("dark"))
    with pytest.raises(StageError, match=r"stage 'absorption' needs variable 'reference'"):
        absorption(make_capture(frames, frames).drop_vars("reference"))


def test_calibration_stages_stay_lazy(closed_form, no_compute):
    capture, _ = closed_form
    lazy = capture.chunk({"angle": 2, "row": 4, "col": 4})
    out = absorption(subtract_dark(lazy))
    assert isinstance(out["absorption"].data, da.Array) and isinstance(out["flags"].data, da.Array)
    assert out["absorption"].chunks == lazy["target"].chunks
    assert isinstance(normalise_reference(lazy)["transmittance"].data, da.Array)
    assert no_compute.count == 0


@pytest.fixture
def disc_capture():
    """An object disc (a different centre per angle) in front of a lit plane; off it, target and reference are the
    dark level plus noise that often clears min_signal (the demo's 'max A = 2.29' of a background pixel)."""
    rng = np.random.default_rng(7)
    shape = (3, 20, 24)
    rows, cols = np.mgrid[:shape[1], :shape[2]]
    disc = np.stack([(rows - r) ** 2 + (cols - c) ** 2 <= 6.0**2 for r, c in ((9, 11), (10, 12.5), (8.5, 14))])
    dark = rng.uniform(55, 65, shape[1:])
    incident = rng.uniform(800, 3000, shape)
    a_true = rng.uniform(0.1, 2.0, shape)
    target = np.where(disc, dark + incident * np.exp(-a_true), dark + rng.uniform(-3, 6, shape))
    reference = np.where(disc, dark + incident, dark + rng.uniform(-3, 6, shape))
    backlit = np.where(disc, dark, dark + 2000.0) + rng.normal(0, 2.0, shape)
    return make_capture(target, reference, dark, backlit=backlit), disc, a_true


def test_background_pixels_are_flagged_and_object_pixels_keep_their_exact_absorption(disc_capture):
    capture, disc, a_true = disc_capture
    out = absorption(capture, min_signal=1.0)
    flags, values = out["flags"].values, out["absorption"].values
    np.testing.assert_array_equal((flags & BACKGROUND) > 0, ~disc)  # exactly the pixels off the disc
    assert np.isnan(values[~disc]).all()
    assert (flags[disc] == 0).all()
    np.testing.assert_allclose(values[disc], a_true[disc], rtol=1e-12, atol=1e-12)
    without = absorption(capture, min_signal=1.0, flag_background=False)
    assert (without["flags"].values[~disc] == 0).any()  # the noise the bit removes: background pixels "valid"
    np.testing.assert_array_equal(without["flags"].values, flags & (255 - BACKGROUND))  # the other bits are kept
    transmittance = normalise_reference(capture, min_signal=1.0)
    np.testing.assert_array_equal(transmittance["flags"].values, flags)
    np.testing.assert_allclose(transmittance["transmittance"].values[disc], np.exp(-a_true[disc]), rtol=1e-12)


def test_shares_count_the_objects_pixels_only(disc_capture):
    capture, disc, _ = disc_capture
    out = absorption(capture, min_signal=1.0)
    shares = {v: float(out[v]) for v in ("signal_fraction", "usable_fraction", "object_valid_fraction",
                                         "background_fraction")}
    assert shares == {"signal_fraction": 1.0, "usable_fraction": 1.0, "object_valid_fraction": 1.0,
                      "background_fraction": pytest.approx(float((~disc).mean()), abs=1e-15)}
    assert out.attrs["background_flagged"] == 1
    # informative, not usable shares: the quality check skips them (no floor)
    assert "selpath_floor" not in out["object_valid_fraction"].attrs
    assert "selpath_floor" in out["signal_fraction"].attrs


def test_a_failed_backlight_stops_the_run_instead_of_flagging_noise(disc_capture):
    """A backlight that never came on (backlit = dark + noise): Otsu still splits the noise, which would flag about
    half of every frame background, the object included, while every other share reads 100 %. The silhouette share
    (classes more than 2 noise widths apart) is 0 and the quality check refuses it, naming the fix."""
    from selpath.pipeline.quality import enforce

    capture, _, _ = disc_capture
    assert float(absorption(capture, min_signal=1.0)["silhouette_fraction"]) == 1.0
    noise = np.random.default_rng(3).normal(0.0, 2.0, capture["backlit"].shape)
    failed = capture.assign(backlit=capture["backlit"].copy(data=capture["dark"].values + noise))
    out = absorption(failed, min_signal=1.0)
    assert float(out["silhouette_fraction"]) == 0.0
    with pytest.raises(StageError, match="backlit frames whose silhouette stands out of the noise.*flag_background"):
        enforce(out, "absorption")
    assert float(absorption(failed, min_signal=1.0, flag_background=False)["signal_fraction"]) > 0.4


def test_a_dark_subtracted_tiled_capture_flags_the_same_background_lazily(disc_capture, no_compute):
    capture, _, _ = disc_capture
    direct = absorption(capture, min_signal=1.0)
    tiled = absorption(subtract_dark(capture.chunk({"angle": 2, "row": 8, "col": 8})), min_signal=1.0)
    assert no_compute.count == 0 and tiled["flags"].chunks == ((2, 1), (8, 8, 4), (8, 8, 8))
    with dask.config.set(scheduler="synchronous"):  # (computing now is the point)
        xr.testing.assert_identical(direct["flags"], tiled["flags"].compute())


def test_a_fixed_silhouette_threshold_and_a_mismatched_backlit(disc_capture):
    capture, disc, _ = disc_capture
    fixed = absorption(capture, min_signal=1.0, silhouette_threshold=1000.0)
    np.testing.assert_array_equal((fixed["flags"].values & BACKGROUND) > 0, ~disc)
    assert fixed.attrs["silhouette_threshold"] == 1000.0
    one_frame = capture.assign(backlit=capture["backlit"].isel(angle=0, drop=True))
    with pytest.raises(StageError, match=r"backlit has dims \('row', 'col'\), target \('angle', 'row', 'col'\); "
                       "they must match to flag the background"):
        absorption(one_frame)
    assert absorption(one_frame, flag_background=False).attrs["background_flagged"] == 0


def test_a_backlit_frame_never_filmed_flags_no_background(disc_capture):
    """A missing backlit frame (NaN, as a store's unwritten frame reads back) says nothing about the object."""
    capture, disc, _ = disc_capture
    capture["backlit"][1] = np.nan
    flags = absorption(capture, min_signal=1.0)["flags"].values
    np.testing.assert_array_equal((flags & BACKGROUND) > 0, ~disc & (np.arange(3) != 1)[:, None, None])


def test_without_backlit_frames_no_pixel_is_background(closed_form):
    capture, _ = closed_form
    out = absorption(capture)
    assert not (out["flags"].values & BACKGROUND).any() and out.attrs["background_flagged"] == 0
    assert float(out["background_fraction"]) == 0.0
    assert float(out["object_valid_fraction"]) == float((out["flags"] == 0).mean()) == 1.0


def test_flag_meanings_list_the_background_bit():
    flags = absorption(make_capture(np.ones((1, 2, 2)), np.full((1, 2, 2), 2.0)))["flags"]
    assert flags.attrs["flag_masks"] == FLAG_MASKS and BACKGROUND == 64
    meanings = flags.attrs["flag_meanings"].split()
    assert len(meanings) == len(FLAG_MASKS) and meanings[FLAG_MASKS.index(BACKGROUND)] == "background"


def test_the_background_bit_drops_no_ray():
    """Rays come from pixels whose camera ray meets the hull, which the silhouettes bound: the pixels the bit
    flags (off the silhouette) already gave no ray (reason 1). Noisy background, perspective camera."""
    from selpath.stages.tomography.hull import silhouettes, visual_hull
    from selpath.stages.tomography.paths import align_paths
    from tests.helpers.tomography import capture as simulated
    from tests.helpers.tomography import make_scene

    camera = {"model": "perspective", "rows": 2, "cols": 160, "distance": "60 mm", "fov": "24 deg"}
    scene = make_scene({"kind": "ellipse", "semi_axes": ["10 mm", "7 mm"], "angle": "20 deg"}, camera, 45.0)
    cap = simulated(scene, np.arange(0.0, 360.0, 20.0))
    noise = np.random.default_rng(3).uniform(-2, 6, (2, *cap["target"].shape))
    off = cap["backlit"] > 1000
    cap = cap.assign(target=cap["target"].where(~off, 64.0 + noise[0]),
                     reference=cap["reference"].where(~off, 64.0 + noise[1]))
    hull = visual_hull(silhouettes(cap)).compute()
    flagged, plain = absorption(cap, min_signal=1.0), absorption(cap, min_signal=1.0, flag_background=False)
    assert ((plain["flags"] == 0) & off).any() and not ((flagged["flags"] == 0) & off).any()
    rays, rays_plain = align_paths(flagged, hull).compute(), align_paths(plain, hull).compute()
    assert (rays["reason"] == 0).sum() > 100
    xr.testing.assert_identical(rays[["reason", "theta", "x", "absorption"]],
                                rays_plain[["reason", "theta", "x", "absorption"]])


def test_silhouettes_wired_in_give_the_same_flags_and_numbers_as_masks_made_here(disc_capture):
    """The hull's silhouettes given to absorption: the frames are thresholded once and the result is the default
    path's, bit for bit (flags, absorption, every share)."""
    capture, disc, _ = disc_capture
    masks = silhouettes(capture)
    here, given = absorption(capture, min_signal=1.0), absorption(capture, masks, min_signal=1.0)
    xr.testing.assert_identical(here.drop_attrs(), given.drop_attrs())
    np.testing.assert_array_equal((given["flags"].values & BACKGROUND) > 0, ~disc)
    # a silhouette that says otherwise is obeyed: the masks, not a second threshold, decide
    wider = masks.assign(silhouette=masks["silhouette"] | True)
    assert not (absorption(capture, wider, min_signal=1.0)["flags"].values & BACKGROUND).any()
    xr.testing.assert_identical(normalise_reference(capture, masks, min_signal=1.0)["flags"], here["flags"])


def test_silhouettes_of_another_capture_or_with_a_second_threshold_are_refused(disc_capture):
    capture, _, _ = disc_capture
    masks = silhouettes(capture)
    with pytest.raises(StageError, match="silhouettes' angles are not the capture's"):
        absorption(capture, masks.assign_coords(angle=masks["angle"] + 1.0))
    with pytest.raises(StageError, match=r"the silhouettes are \{'angle': 2"):
        absorption(capture, masks.isel(angle=slice(0, 2)))
    with pytest.raises(StageError, match="(?s)flag_background is false.*silhouette_threshold is set"):
        absorption(capture, masks, silhouette_threshold=10.0, flag_background=False)
    with pytest.raises(StageError, match="has no `silhouette` variable"):
        absorption(capture, masks.rename(silhouette="mask"))
    with pytest.raises(StageError, match="target"):  # the capture's own problem, named, before the masks are read
        absorption(capture.drop_vars("target"), masks)
