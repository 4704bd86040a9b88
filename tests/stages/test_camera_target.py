"""A camera's intrinsics from a checkerboard target (stages.camera_target) against the simulated pinhole's planted
ones, and their use in a tomography capture."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.devices.sim.stereo_target import StereoTargetScene, capture_target
from selpath.pipeline.errors import StageError
from selpath.stages.camera_target import apply_camera_calibration, calibrate_camera, distortion_shift

CAMERA = {"width": 320, "height": 240, "focal_px": 400, "principal_px": [161.3, 118.2]}


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    scene = StereoTargetScene.model_validate({
        "scene": "t", "camera": CAMERA, "projector": {"width": 256, "height": 160, "focal_px": 320},
        "poses": {"count": 8, "seed": 4}})
    target = capture_target(scene, tmp_path_factory.mktemp("target") / "target.zarr", progress=False)
    return calibrate_camera(target)


def test_the_planted_intrinsics_are_recovered_within_their_uncertainty(calibration):
    """8 poses with shot and read noise: focal length and principal point within 3 standard deviations (plus the
    0.1 px corner error of the 3 × 3 sub-pixel render), square pixels, reprojection under 0.2 px, and a distortion
    that moves no pixel the board covered by 0.5 px (the simulated lens has none)."""
    a = calibration.attrs
    assert abs(a["focal_length_px"] - 400) <= 3 * a["focal_length_std_px"] + 0.3
    for got, want, std in zip(a["principal_point_px"], CAMERA["principal_px"], a["principal_point_std_px"],
                              strict=True):
        assert abs(got - want) <= 3 * std + 0.3
    assert abs(a["pixel_aspect"] - 1) < 0.005 and a["reprojection_rms_px"] < 0.2
    assert a["distortion_max_px"] < 0.5 and a["sensor_px"] == [240, 320]
    assert calibration["pose_used"].values.all()


def test_distortion_shift_is_the_pixel_displacement_of_the_model():
    """Against a brute-force forward model: a pure k1 = 0.1 moves the sensor's corner by k1·r³·f px."""
    matrix = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]])
    assert distortion_shift(matrix, np.zeros(5), (0, 0, 319, 239)) < 1e-9
    shift = distortion_shift(matrix, np.array([0.1, 0, 0, 0, 0]), (0, 0, 319, 239))
    r = np.hypot(159.5, 119.5) / 400  # the corner's undistorted radius is smaller; the forward model bounds it
    assert 0.5 * 0.1 * r**3 * 400 < shift < 0.1 * r**3 * 400 * 1.01


def tomography_capture(rows=240, cols=320, model="perspective") -> xr.Dataset:
    camera = ({"focal_length_px": 390.0, "camera_distance": 400.0, "principal_point_px": [158.0, 119.5]}
              if model == "perspective" else {"pixel_size": 0.1})
    return xr.Dataset({"target": (("angle", "row", "col"), np.zeros((2, rows, cols), np.float32))},
                      coords={"angle": ("angle", [0.0, 180.0], {"units": "degree"})},
                      attrs={"selpath_kind": "tomography_capture", "camera_model": model, "light_angle_deg": 45.0,
                             "length_unit": "mm", **camera})


def test_a_tomography_capture_takes_the_focal_length_and_principal_row(calibration):
    got = apply_camera_calibration(tomography_capture(), calibration).attrs
    assert got["focal_length_px"] == calibration.attrs["focal_length_px"]
    assert got["principal_point_px"] == [158.0, calibration.attrs["principal_point_px"][1]]  # the column: the axis
    assert got["stated_focal_length_px"] == 390.0 and got["stated_principal_point_px"] == [158.0, 119.5]
    again = apply_camera_calibration(tomography_capture().assign_attrs(got), calibration).attrs
    assert again["stated_focal_length_px"] == 390.0  # the first stated values are kept


def test_a_calibration_that_does_not_fit_the_capture_is_refused(calibration):
    with pytest.raises(StageError, match="the calibration is of a 240 × 320 sensor, the capture's is 120 × 320"):
        apply_camera_calibration(tomography_capture(rows=120), calibration)
    with pytest.raises(StageError, match="a focal length means something only for a perspective camera"):
        apply_camera_calibration(tomography_capture(model="orthographic"), calibration)
    distorted = calibration.assign_attrs(distortion_max_px=2.0)
    with pytest.raises(StageError, match="the lens distortion moves pixels by up to 2.00 px"):
        apply_camera_calibration(tomography_capture(), distorted)
    with pytest.raises(StageError, match="the pixels are not square"):
        apply_camera_calibration(tomography_capture(), calibration.assign_attrs(pixel_aspect=1.05))


def test_a_target_without_its_board_or_with_too_few_poses_is_named(calibration):
    frames = xr.Dataset({"image": (("pose", "row", "col"), np.zeros((3, 40, 50), np.float32))},
                        attrs={"board_corners": [9, 6], "board_square_mm": 25.0})
    with pytest.raises(StageError, match=r"the board was found at 0 of 3 poses"):
        calibrate_camera(frames)
    with pytest.raises(StageError, match="lacks attrs board_corners"):
        calibrate_camera(frames.drop_attrs())
