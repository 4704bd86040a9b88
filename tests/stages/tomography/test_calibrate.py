"""Calibration stages against closed forms, with planted bad pixels and a laziness check."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline import StageError
from stages.tomography.calibrate import NO_SIGNAL, NONFINITE, SATURATED, absorption, normalise_reference, subtract_dark

DIMS = ("angle", "row", "col")


def make_capture(target, reference, dark=None, saturation_level=4095.0, chunks=None) -> xr.Dataset:
    data = {"target": (DIMS, target), "reference": (DIMS, reference)}
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
