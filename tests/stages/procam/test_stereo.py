"""The projector–camera pair calibrated from a checkerboard target (stages.procam.stereo) against the simulated
pinhole pair's planted intrinsics and pose (devices.sim.stereo_target)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from selpath.devices.patterns import gray_code_levels
from selpath.devices.sim.stereo_target import StereoTargetScene, capture_target, trace
from selpath.pipeline.errors import StageError
from selpath.stages.procam._gray_code import decode_band
from selpath.stages.procam.stereo import calibrate_procam_stereo, camera_corners, euler_angles, projector_corners


def scene(**changes) -> StereoTargetScene:
    spec = {"scene": "t", "camera": {"width": 320, "height": 240, "focal_px": 400},
            "projector": {"width": 256, "height": 160, "focal_px": 320, "principal_px": [130, 76]},
            "pose": {"roll": "1.5 deg"}, "poses": {"count": 6, "seed": 2}}
    return StereoTargetScene.model_validate(spec | changes)


def test_euler_angles_invert_the_simulators_rotation():
    from selpath.devices.sim.stereo_target import rotation

    for angles in [(0.8, -2.0, 9.5), (-30.0, 10.0, -20.0), (0.0, 0.0, 0.0)]:
        roll, pitch, yaw = angles
        assert euler_angles(rotation(roll_deg=roll, pitch_deg=pitch, yaw_deg=yaw)) == pytest.approx(angles, abs=1e-9)


def test_corners_carried_into_the_projector_land_where_the_projector_sees_them():
    """One noise-free pose: OpenCV finds the board's corners to 0.15 px of the pinhole projection, and the true corners
    carried through the decoded codes' local homographies match the board's corners projected by the true projector
    to 0.05 px (analytic truth: the pinhole model)."""
    s = scene(noise=None)
    rig, board = s.rig(), s.board()
    pose = s.target_poses()[0]
    traced = trace(rig, board, pose)
    levels, column_bits, row_bits = gray_code_levels((160, 256))
    stack = np.stack([s.frame(traced, level / 255.0, (0, i)) for i, level in enumerate(levels)]).astype(float)
    corners = camera_corners(stack[0] - stack[1], board.corners)
    truth_camera = cv2.projectPoints(board.object_points(), pose[0], pose[1], rig.camera_matrix, None)[0]
    # OpenCV may number the corners from the opposite end of the board (the same for every pose)
    found = min((corners, corners[::-1]), key=lambda c: np.max(np.abs(c - truth_camera.reshape(-1, 2))))
    assert np.max(np.abs(found - truth_camera.reshape(-1, 2))) < 0.15  # measured 0.11 (3 × 3 sub-pixel render)
    decoded = decode_band(np.moveaxis(stack, 0, -1), column_bits=column_bits, row_bits=row_bits, shape=(160, 256),
                           min_lit=0.02 * 4095, min_contrast=0.2, drop=(0, 0))
    usable = np.isfinite(decoded[..., 0]) & (decoded[..., 2] >= 0.75)
    carried = projector_corners(truth_camera.reshape(-1, 2), decoded[..., 0], decoded[..., 1], usable, 10)
    r = cv2.Rodrigues(pose[0])[0]
    in_projector = (rig.rotation @ (r @ board.object_points().T.astype(float) + pose[1][:, None])
                    + rig.translation[:, None])
    truth = (rig.projector_matrix @ in_projector)[:2] / (rig.projector_matrix @ in_projector)[2]
    assert np.nanmax(np.abs(carried - truth.T)) < 0.05


def test_the_planted_pair_is_recovered_and_its_rows_rectified(tmp_path):
    """A projector rolled 1.5° and turned in 9.5°, with sensor noise, 6 poses: focal lengths within 1 % and 3 standard
    deviations, the roll within 0.1°, the baseline within 1 %, reprojection under 0.2 px (measured 0.046);
    corresponding corners' rows, 0.89 apart before, agree to under 0.1 rows after rectification (measured 0.031;
    goal 0.25), with a warning that names the roll."""
    s = scene()
    target = capture_target(s, tmp_path / "target.zarr", progress=False)
    with pytest.warns(UserWarning, match=r"the sync rows are not epipolar: .* turned 1\.\d+° about its axis"):
        calibration = calibrate_procam_stereo(target)
    a = calibration.attrs
    k_c, k_p = calibration["camera_matrix"].values, calibration["projector_matrix"].values
    for got, want, std in ((k_c[0, 0], 400, a["camera_focal_std_px"][0]),
                           (k_p[0, 0], 320, a["projector_focal_std_px"][0])):
        assert abs(got - want) < min(0.01 * want, 3 * std + 0.5)
    assert abs(a["roll_deg"] - 1.5) < 0.1 and abs(a["pitch_deg"]) < 0.1
    assert abs(a["yaw_deg"] - np.degrees(np.arctan2(100, 600))) < 0.2
    assert abs(a["baseline_mm"] - 100) < 1.0 and a["reprojection_rms_px"] < 0.2
    assert a["row_disparity_before"] > 0.5 and a["row_disparity_after"] < 0.1 < 0.5 < a["sync_rows_p90"]
    assert calibration["pose_used"].values.all()


@pytest.mark.slow
def test_a_rectified_pair_is_left_without_a_warning(tmp_path):
    """Parallel axes, no roll, and a projector whose rows span the camera's as the sync pairs them (f_p·C/P = f_c,
    principal rows matched): no warning, the sync's rows within 0.1 at the corners; the row disparity left before
    rectification is the estimated principal points' error (0.40 px measured); the roll is zero within 0.05°."""
    s = scene(pose={"roll": "0 deg", "toe_in_distance": None}, noise=None, poses={"count": 4, "seed": 5},
              projector={"width": 256, "height": 160, "focal_px": 400 * 160 / 240, "principal_px": [127.5, 79.5]})
    target = capture_target(s, tmp_path / "target.zarr", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        calibration = calibrate_procam_stereo(target)
    a = calibration.attrs
    assert a["sync_rows_p90"] < 0.1 and a["row_disparity_before"] < 0.5 and abs(a["roll_deg"]) < 0.05


def test_a_board_never_seen_whole_is_refused(tmp_path):
    s = scene(camera={"width": 160, "height": 120, "focal_px": 200}, poses={"count": 3, "distance": "80 mm", "seed": 1},
              projector={"width": 64, "height": 40, "focal_px": 80})  # the board overflows the frame
    target = capture_target(s, tmp_path / "target.zarr", progress=False)
    with pytest.raises(StageError, match=r"the board was found and decoded at 0 of 3 poses"):
        calibrate_procam_stereo(target)
