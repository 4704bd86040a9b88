"""Gray-code correspondences, the rig's row misalignment and the rectified transport (stages.procam.rectify),
against the simulator's planted misalignment, OpenCV's own decoder and analytic mixtures of two codes."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
import xarray as xr

from selpath.devices.patterns import gray_code_levels
from selpath.devices.procam_acquire import acquire_gray_code
from selpath.devices.sim.procam_rig import simulated_procam_rig
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.devices.sim.procam_transport import seen_rows
from selpath.pipeline.errors import StageError
from selpath.stages.procam.acquire_patterns import gray_code_window
from selpath.stages.procam.rectify import decode_gray_code, epipolar_alignment, rectify_transport, row_offsets

RIG = {"camera_rows": 40, "camera_cols": 48, "projector_rows": 40, "projector_cols": 48}
CANDLE = {"name": "candle", "region": {"kind": "rectangle", "x": [0.1, 0.45], "y": [0.2, 0.8]}, "albedo": 0.9,
          "effects": {"subsurface": {"width": "3 px", "fraction": 0.5}}}


def scene(objects=(CANDLE,), **rig) -> ProcamScene:
    return ProcamScene.model_validate({"scene": "t", "background": {"albedo": 0.3}, "objects": list(objects),
                                       "rig": RIG | rig})


def codes(s: ProcamScene, folder, max_offset_rows: float = 16.0) -> xr.Dataset:
    delay, exposure = gray_code_window(s.rig.line_time, s.rig.scan_speed, max_offset_rows)
    return acquire_gray_code(simulated_procam_rig(s), folder / "codes.zarr", delay=delay, exposure=exposure,
                             progress=False)


def test_codes_decode_exactly_on_an_aligned_rig_and_agree_with_opencv(tmp_path):
    """Direct light only, no noise, a projector of half the camera's size: every pixel decodes to the projector pixel
    the simulator lights it from (columns from its correspondence, rows from ``seen_rows``), and OpenCV's
    ``getProjPixel`` on the same frames (as 8-bit images) answers the same for every pixel."""
    s = scene(objects=(), projector_rows=20, projector_cols=24, bits=None)
    capture = codes(s, tmp_path)
    got = decode_gray_code(capture).compute()
    col = np.round((np.arange(48) + 0.5) * 24 / 48 - 0.5)
    np.testing.assert_array_equal(got["projector_col"].values, np.broadcast_to(col, (40, 48)))
    np.testing.assert_array_equal(got["projector_row"].values, np.broadcast_to(seen_rows(s.rig)[:, None], (40, 48)))
    assert float(got["decoded_fraction"]) == 1.0 and float(got["code_sharpness"].min()) == pytest.approx(1.0)

    frames = capture["image"].values
    scaled = np.rint(255 * (frames - frames.min()) / (frames.max() - frames.min())).astype(np.uint8)
    peer = cv2.structured_light.GrayCodePattern.create(24, 20)
    peer.setWhiteThreshold(5)
    peer.setBlackThreshold(5)
    patterns = list(scaled[2:])
    for y in range(40):
        for x in range(48):
            error, pixel = peer.getProjPixel(patterns, x, y)
            assert not error and tuple(pixel) == (got["projector_col"][y, x], got["projector_row"][y, x]), (y, x)


def test_positions_between_two_projector_pixels_come_from_the_one_bit_they_differ_in(tmp_path):
    """Analytic truth: each pixel's frames mix the codes of projector pixels (r, c), (r ± 1, c ± 1) with weights
    (1 − |f|, |f|) per axis (a pixel seen between two); decoding returns r + f and c + g to rounding, for random
    f, g in [−½, ½] over the whole projector."""
    shape = (16, 24)
    levels, column_bits, row_bits = gray_code_levels(shape)
    rng = np.random.default_rng(7)
    rows, cols = 24, 32  # a camera with more pixels than the projector: every bit resolved
    r = rng.integers(1, shape[0] - 1, (rows, cols))
    c = rng.integers(1, shape[1] - 1, (rows, cols))
    f, g = rng.uniform(-0.5, 0.5, (2, rows, cols))
    pattern = levels.astype(float) / 255

    def at(rr, cc):
        return pattern[:, rr, cc]

    r2, c2 = r + np.sign(f).astype(int), c + np.sign(g).astype(int)
    mix = ((1 - abs(f)) * (1 - abs(g)) * at(r, c) + abs(f) * (1 - abs(g)) * at(r2, c)
           + (1 - abs(f)) * abs(g) * at(r, c2) + abs(f) * abs(g) * at(r2, c2))
    capture = xr.Dataset({"image": (("pattern", "row", "col"), 10 + 800 * mix)},
                         attrs={"column_bits": column_bits, "row_bits": row_bits, "projector_shape": list(shape),
                                "saturation_counts": 4095.0, "dark_level_counts": 10.0})
    got = decode_gray_code(capture, min_contrast=0.01).compute()
    np.testing.assert_allclose(got["projector_row"].values, r + f, atol=1e-9)
    np.testing.assert_allclose(got["projector_col"].values, c + g, atol=1e-9)


def peak_offset(transport: xr.Dataset) -> np.ndarray:
    """Each pixel's direct peak: the centroid of the largest offset and its two neighbours."""
    t = np.nan_to_num(transport["transport"].transpose("offset", "row", "col").values)
    offsets = transport["offset"].values.astype(float)
    i = np.argmax(t, axis=0)
    index = np.stack([np.clip(i - 1, 0, len(offsets) - 1), i, np.clip(i + 1, 0, len(offsets) - 1)])
    weight = np.take_along_axis(t, index, 0)
    return (weight * offsets[index]).sum(0) / np.maximum(weight.sum(0), 1e-12)


def test_a_planted_misalignment_is_measured_warned_of_and_rectified_out_of_the_transport(tmp_path):
    """The projector rolled 1.5° and shifted 0.6 rows (with a scattering candle and sensor noise): the fit recovers
    both within 3 standard errors (and 0.02 rows, 0.05°), warns with the numbers, and the demultiplexed transport's
    direct peak moves from a median |offset| of about 0.6 rows to under 0.1 after rectification (goal 0.25)."""
    from selpath.stages.procam.demux import demux_plane_to_ray
    from tests.helpers.procam import capture_of

    s = scene(misalignment={"roll": "1.5 deg", "shift": "0.6 px"}, noise={"gain": 1.0, "read_std": 2.0})
    correspondence = decode_gray_code(codes(s, tmp_path)).compute()
    with pytest.warns(UserWarning, match=r"the sync rows are not epipolar: .* rows or more off its row .*roll "
                                         r"1\.\d+°.*turn the projector by -1\.\d+° about its axis"):
        alignment = epipolar_alignment(correspondence)
    a = alignment.attrs
    assert abs(a["shift_rows"] - 0.6) <= min(3 * a["shift_rows_std"], 0.02) + 1e-3
    assert abs(a["roll_deg"] - 1.5) <= min(3 * a["roll_deg_std"], 0.05) + 1e-3
    truth = s.rig.misalignment.offset(np.arange(48), 48)
    assert np.max(np.abs(alignment["model"].values - truth)) < 0.05

    transport = demux_plane_to_ray(capture_of(s.with_rig(noise=None, bits=None))).compute()
    before = peak_offset(transport)
    assert np.median(np.abs(before - truth)) < 0.05 and np.median(np.abs(before)) > 0.5  # the peak sits at δ
    after = peak_offset(rectify_transport(transport, alignment).compute())
    assert np.median(np.abs(after)) < 0.1 and np.quantile(np.abs(after), 0.9) < 0.25


def test_an_aligned_rig_is_epipolar_without_a_warning(tmp_path):
    correspondence = decode_gray_code(codes(scene(noise={"gain": 1.0, "read_std": 2.0}), tmp_path)).compute()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        alignment = epipolar_alignment(correspondence)
    assert abs(alignment.attrs["shift_rows"]) < 0.01 and abs(alignment.attrs["roll_deg"]) < 0.02
    assert alignment.attrs["p90_abs_rows"] < alignment.attrs["tolerance_rows"] == 0.5  # v_p·t_p / 2 = 1/2 row


def test_a_camera_coarser_than_the_projector_leaves_out_the_bits_it_cannot_resolve(tmp_path):
    """A projector with 6× the camera's rows and columns (a sensor rendered small): the finest 3 bits per axis
    alias and are left out; the misalignment is still measured to 0.05 rows and 0.1°."""
    s = scene(projector_rows=240, projector_cols=288, misalignment={"roll": "1 deg", "shift": "0.8 px"})
    correspondence = decode_gray_code(codes(s, tmp_path)).compute()
    assert correspondence.attrs["bits_unresolved"] == [3, 3]
    with pytest.warns(UserWarning):
        alignment = epipolar_alignment(correspondence)
    assert abs(alignment.attrs["shift_rows"] - 0.8) < 0.05 and abs(alignment.attrs["roll_deg"] - 1.0) < 0.1


def test_row_offsets_put_the_sync_pairing_at_zero():
    rows = seen_rows(scene(projector_rows=24).rig).astype(float)  # a rectified rig's decoded rows
    delta = row_offsets(np.broadcast_to(rows[:, None], (40, 3)), 24)
    assert np.max(np.abs(delta)) <= 0.5 * 40 / 24  # within half a projector row, on the camera's scale
    assert abs(float(np.mean(delta))) < 0.05


def test_bad_input_is_named(tmp_path):
    capture = codes(scene(objects=()), tmp_path)
    with pytest.raises(StageError, match="missing attrs: column_bits"):
        decode_gray_code(capture.drop_attrs().assign_attrs(row_bits=6))
    with pytest.raises(StageError, match=r"10 patterns; white, black and 6 column and 6 row bits .* = 26"):
        decode_gray_code(capture.isel(pattern=slice(0, 10)))
    alignment = epipolar_alignment(decode_gray_code(capture).compute())
    transport = xr.Dataset({"transport": (("offset", "row", "col"), np.zeros((3, 20, 48)))},
                           coords={"offset": [-1, 0, 1]})
    with pytest.raises(StageError, match="the transport is 20 × 48 px"):
        rectify_transport(transport, alignment)


def test_offsets_are_shifted_as_numpy_interp_does_pixel_by_pixel():
    """The vectorised re-indexing against ``np.interp`` per pixel (uneven grid, NaN outside it)."""
    from selpath.stages.procam.rectify import _shift_offsets

    rng = np.random.default_rng(3)
    offsets = np.array([-3.0, -2.0, -1.0, 0.0, 1.0, 2.5, 4.0])
    transport, delta = rng.random((5, 6, offsets.size)), rng.uniform(-2, 2, (5, 6))
    want = np.array([[np.interp(offsets + delta[i, j], offsets, transport[i, j], left=np.nan, right=np.nan)
                      for j in range(6)] for i in range(5)])
    np.testing.assert_allclose(_shift_offsets(transport, delta, offsets=offsets), want, atol=1e-12)


def test_the_fit_trims_one_sided_outliers_and_refuses_degenerate_pixel_sets():
    """Review finding: trimming around 0 instead of around the bulk dropped every pixel once one-sided outliers pulled
    the first fit (then a raw LinAlgError). Now 30 % of pixels 4–5 rows off leave the fit exact; pixels all in one
    row or one column are refused with the reason."""
    from selpath.stages.procam.rectify import fit_misalignment

    rng = np.random.default_rng(1)
    s, c = np.mgrid[:40, :48]
    delta = 0.8 + np.tan(np.deg2rad(0.5)) * (c - 23.5) + rng.normal(0, 0.005, s.shape)
    delta[rng.random(s.shape) < 0.3] += rng.uniform(4, 5)
    coef, std = fit_misalignment(delta)
    assert abs(coef[0] - 0.8) < 0.005 and abs(coef[1] - np.tan(np.deg2rad(0.5))) < 1e-4 and abs(coef[2]) < 1e-4
    one_row = np.full((40, 48), np.nan)
    one_row[7] = 0.5
    with pytest.raises(StageError, match=r"48 decoded pixel\(s\) in 1 row\(s\) and 48 column\(s\)"):
        fit_misalignment(one_row)
