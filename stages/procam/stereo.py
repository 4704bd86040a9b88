"""Geometric calibration of the projector–camera pair from a checkerboard target, and its rectification (§6.1).

The method of Moreno and Taubin ("Simple, accurate, and robust projector-camera calibration", 2012): at each pose of
a planar checkerboard the camera finds the board's inner corners (``cv2.findChessboardCornersSB``); the Gray codes
filmed at the same pose say which projector pixel lights each camera pixel (``selpath.stages.procam.rectify``,
sub-pixel);
a homography fitted to the decoded pixels around each corner carries the corner into the projector, which thereby
"sees" the board too. Then ``cv2.calibrateCamera`` for each device, ``cv2.stereoCalibrate`` for their relative pose,
and ``cv2.stereoRectify`` for the rotations that make their rows epipolar. Two measures of the rows, both over the
corresponding corners: the row disparity (the difference of their rows on the camera's pixel scale, undistorted;
before and after rectification: what the geometric model says and what rectification leaves), and what the sync
sees (the projector row, on the camera's row scale as the sync pairs them, (y_p + ½)·C/P − ½, minus the camera row,
raw pixels): the sync rows are epipolar only when this is small, which also needs the projector's vertical field of
view and principal row to match the camera's. The warning is on the latter.
"""

from __future__ import annotations

import warnings

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Count, Fraction, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.camera_target import board_points, camera_corners
from selpath.stages.procam._gray_code import check_code_count, decode_band, resolved_drop
from selpath.stages.procam.rectify import paired_camera_row

_M = ("i", "j")
PROCAM_STEREO_CALIBRATION = CubeKind(
    name="procam_stereo_calibration",
    description="camera and projector intrinsics, their relative pose and the rectification (calibrate_procam_stereo)",
    variables={
        "camera_matrix": Variable(_M, units="px", long_name="camera intrinsics K_c"),
        "projector_matrix": Variable(_M, units="px", long_name="projector intrinsics K_p"),
        "rotation": Variable(_M, units="1", long_name="projector from camera rotation R"),
        "translation": Variable(("i",), units="mm", long_name="projector from camera translation t"),
        "camera_distortion": Variable(("k",), False, units="1", long_name="camera k1, k2, p1, p2, k3"),
        "projector_distortion": Variable(("k",), False, units="1", long_name="projector k1, k2, p1, p2, k3"),
        "rectify_camera": Variable(_M, False, units="1", long_name="camera rectifying rotation R1"),
        "rectify_projector": Variable(_M, False, units="1", long_name="projector rectifying rotation R2"),
        "project_camera": Variable(("i", "m"), False, units="px", long_name="rectified camera projection P1"),
        "project_projector": Variable(("i", "m"), False, units="px", long_name="rectified projector projection P2"),
        "pose_used": Variable(("pose",), False, units=None, long_name="board found and decoded at this pose"),
        "pose_rms_px": Variable(("pose",), False, units="px", long_name="stereo reprojection error of the pose"),
    },
    attrs={"reprojection_rms_px": "stereo reprojection error, px",
           "roll_deg": "rotation of the projector about its optical axis against the camera, degree",
           "row_disparity_before": "median |row difference| of corresponding corners on the camera's scale, "
           "unrectified, px",
           "row_disparity_after": "the same after stereoRectify, px",
           "sync_rows_median": "median |projector row as the sync pairs it − camera row| at the corners, camera rows"},
)

#: decoded pixels a corner's local homography needs (it has 8 degrees of freedom)
MIN_HOMOGRAPHY_PIXELS = 12


def euler_angles(r: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) [degree] of R = Rz(roll)·Ry(yaw)·Rx(pitch)
    (``selpath.devices.sim.stereo_target.rotation``)."""
    roll = np.degrees(np.arctan2(r[1, 0], r[0, 0]))
    yaw = np.degrees(np.arcsin(np.clip(-r[2, 0], -1.0, 1.0)))
    pitch = np.degrees(np.arctan2(r[2, 1], r[2, 2]))
    return float(roll), float(pitch), float(yaw)


def projector_corners(corners: np.ndarray, col: np.ndarray, row: np.ndarray, usable: np.ndarray,
                      window: int) -> np.ndarray:
    """Each camera corner carried into the projector by a homography fitted to the decoded pixels within
    ``window`` px of it (NaN where fewer than MIN_HOMOGRAPHY_PIXELS are usable)."""
    import cv2  # OpenCV when it calibrates, not when a workflow is read

    ys, xs = np.nonzero(usable)
    out = np.full(corners.shape, np.nan, dtype=np.float64)
    for k, (x, y) in enumerate(corners):
        near = (np.abs(xs - x) <= window) & (np.abs(ys - y) <= window)
        if near.sum() < MIN_HOMOGRAPHY_PIXELS:
            continue
        source = np.stack([xs[near], ys[near]], axis=1).astype(np.float64)
        target = np.stack([col[ys[near], xs[near]], row[ys[near], xs[near]]], axis=1)
        h, _ = cv2.findHomography(source, target, 0)
        if h is None:
            continue
        p = h @ np.array([x, y, 1.0])
        out[k] = p[:2] / p[2]
    return out


def _rows(points: np.ndarray, k: np.ndarray, dist: np.ndarray, rect: np.ndarray | None, p: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.undistortPoints(points.reshape(-1, 1, 2).astype(np.float64), k, dist, R=rect, P=p).reshape(-1, 2)[:, 1]


@stage("calibrate_procam_stereo", kind=PROCAM_STEREO_CALIBRATION)
def calibrate_procam_stereo(target: xr.Dataset, /, *, window_px: Count = 10, min_sharpness: Fraction = 0.75,
                            min_lit: Fraction = 0.02, min_contrast: Fraction = 0.2,
                            tolerance_rows: Positive = 0.5) -> xr.Dataset:
    """Camera and projector intrinsics, their relative pose and rectification, from a checkerboard target.

    Also how far the rows are from epipolar, with a UserWarning when the sync's rows are off by more than
    ``tolerance_rows`` at one corner in ten; the intrinsics come with standard deviations.

    Parameters
    ----------
    target : xr.Dataset
        A ``stereo_target_capture``: ``image`` [counts] over (pose, pattern, row, col), patterns as in a
        ``gray_code_capture``; attrs ``column_bits``, ``row_bits``, ``projector_shape`` [rows, cols],
        ``board_corners`` [columns, rows of inner corners], ``board_square_mm``, ``saturation_counts`` and
        ``dark_level_counts``.
    window_px : int
        Half-width of the camera window whose decoded pixels carry a corner into the projector [camera px].
    min_sharpness : float
        Decoded pixels used for the homographies must have a code at least this sharp [1] (``decode_gray_code``).
    min_lit, min_contrast : float
        As for ``decode_gray_code`` [1]: shadow below ``min_lit`` of the sensor's range; a bit is clear from
        ``min_contrast`` of the pixel's white − black.
    tolerance_rows : float
        The sync's rows off by more than this at one corner in ten are warned of [camera rows].

    Returns
    -------
    xr.Dataset
        A ``procam_stereo_calibration`` cube: ``camera_matrix``, ``projector_matrix``, ``rotation`` (3 × 3 over (i, j)),
        ``translation`` [mm] (i), ``camera_distortion`` and ``projector_distortion`` (k: OpenCV's k1, k2, p1, p2, k3),
        ``rectify_camera`` and ``rectify_projector`` (stereoRectify's R1, R2), ``project_camera`` and
        ``project_projector`` (its P1, P2 over (i, m)), and per pose ``pose_used`` and ``pose_rms_px``; attrs the
        reprojection errors, ``roll_deg``, ``pitch_deg``, ``yaw_deg`` (of R = Rz·Ry·Rx), ``baseline_mm``, the
        intrinsics' standard deviations, ``row_disparity_before``/``_after`` (median |row difference| of corresponding
        corners on the camera's scale, undistorted, unrectified and rectified; ``_p90`` too) and
        ``sync_rows_median``/``_p90`` (|projector row as the sync pairs it − camera row| at the corners, camera rows).

    References
    ----------
    Thesis §5.2.1 Epipolar geometry and light transport.
    """
    import cv2

    require_variables(target, ("image",), "calibrate_procam_stereo")
    attrs = target.attrs
    missing = [a for a in ("column_bits", "row_bits", "projector_shape", "board_corners", "board_square_mm",
                           "saturation_counts", "dark_level_counts") if a not in attrs]
    if missing:
        raise StageError(Problem(f"the target capture lacks attrs {', '.join(missing)}",
                                 fix="capture it with acquire_stereo_target"))
    image = target["image"].transpose("pose", "pattern", "row", "col")
    column_bits, row_bits = int(attrs["column_bits"]), int(attrs["row_bits"])
    check_code_count(image.sizes["pattern"], column_bits, row_bits)
    projector_shape = (int(attrs["projector_shape"][0]), int(attrs["projector_shape"][1]))
    corners_shape = (int(attrs["board_corners"][0]), int(attrs["board_corners"][1]))
    rows, cols = image.sizes["row"], image.sizes["col"]
    drop = (resolved_drop(projector_shape[0], rows), resolved_drop(projector_shape[1], cols))
    full_scale = float(attrs["saturation_counts"]) - float(attrs["dark_level_counts"])
    board = board_points(corners_shape, float(attrs["board_square_mm"]))

    objects, cam_points, proj_points, used = [], [], [], []
    for pose in range(image.sizes["pose"]):
        stack = np.asarray(image.isel(pose=pose).values, float)  # one pose's frames: (pattern, row, col)
        corners = camera_corners(stack[0] - stack[1], corners_shape)
        if corners is None:
            used.append(False)
            continue
        decoded = decode_band(np.moveaxis(stack, 0, -1), column_bits=column_bits, row_bits=row_bits,
                               shape=projector_shape, min_lit=min_lit * full_scale, min_contrast=min_contrast,
                               drop=drop)
        usable = np.isfinite(decoded[..., 0]) & (decoded[..., 2] >= min_sharpness)
        projected = projector_corners(corners, decoded[..., 0], decoded[..., 1], usable, window_px)
        keep = np.all(np.isfinite(projected), axis=1)
        if keep.sum() < 6:
            used.append(False)
            continue
        objects.append(board[keep])
        cam_points.append(corners[keep])
        proj_points.append(projected[keep].astype(np.float32))
        used.append(True)
    if len(objects) < 3:
        raise StageError(Problem(f"the board was found and decoded at {len(objects)} of {image.sizes['pose']} poses; "
                                 "a calibration needs at least 3", fix="film the board whole, lit by the projector, "
                                 "at more poses; check board_corners"))
    camera_size, projector_size = (cols, rows), (projector_shape[1], projector_shape[0])
    rms_c, k_c, d_c, _, _, std_c, _, _ = cv2.calibrateCameraExtended(objects, cam_points, camera_size, None, None)
    rms_p, k_p, d_p, _, _, std_p, _, _ = cv2.calibrateCameraExtended(objects, proj_points, projector_size, None, None)
    rms, k_c, d_c, k_p, d_p, r, t, *_, per_view = cv2.stereoCalibrateExtended(
        objects, cam_points, proj_points, k_c, d_c, k_p, d_p, camera_size, None, None,
        flags=cv2.CALIB_FIX_INTRINSIC)
    r1, r2, p1, p2, *_ = cv2.stereoRectify(k_c, d_c, k_p, d_p, camera_size, r, t, alpha=0)
    cams, projs = np.concatenate(cam_points), np.concatenate(proj_points)
    before = np.abs(_rows(cams, k_c, d_c, None, k_c) - _rows(projs, k_p, d_p, None, k_c))
    after = np.abs(_rows(cams, k_c, d_c, r1, p1) - _rows(projs, k_p, d_p, r2, p2))
    sync = np.abs(paired_camera_row(projs[:, 1], projector_shape[0], rows) - cams[:, 1])
    roll, pitch, yaw = euler_angles(r)
    summary = {
        "reprojection_rms_px": float(rms), "camera_rms_px": float(rms_c), "projector_rms_px": float(rms_p),
        "roll_deg": roll, "pitch_deg": pitch, "yaw_deg": yaw,
        "baseline_mm": float(np.linalg.norm(-r.T @ t.ravel())),
        "camera_focal_std_px": [float(v) for v in std_c.ravel()[:2]],
        "camera_principal_std_px": [float(v) for v in std_c.ravel()[2:4]],
        "projector_focal_std_px": [float(v) for v in std_p.ravel()[:2]],
        "projector_principal_std_px": [float(v) for v in std_p.ravel()[2:4]],
        "row_disparity_before": float(np.median(before)), "row_disparity_before_p90": float(np.quantile(before, 0.9)),
        "row_disparity_after": float(np.median(after)), "row_disparity_after_p90": float(np.quantile(after, 0.9)),
        "sync_rows_median": float(np.median(sync)), "sync_rows_p90": float(np.quantile(sync, 0.9)),
        "corners_used": int(cams.shape[0]), "tolerance_rows": float(tolerance_rows)}
    if summary["sync_rows_p90"] > tolerance_rows:
        warnings.warn(f"calibrate_procam_stereo: the sync rows are not epipolar: at one corner in ten the projector "
                      f"row the sync pairs with the camera's is {summary['sync_rows_p90']:.2f} camera rows or more off "
                      f"(median {summary['sync_rows_median']:.2f}), more than {tolerance_rows:g}. The projector is "
                      f"turned {roll:.3f}° about its axis (pitch {pitch:.3f}°, yaw {yaw:.3f}°); corresponding points' "
                      f"row disparity is {summary['row_disparity_before']:.2f} px unrectified, "
                      f"{summary['row_disparity_after']:.3f} rectified", UserWarning, stacklevel=2)
    pose_rms = np.full(image.sizes["pose"], np.nan)
    pose_rms[np.flatnonzero(used)] = np.sqrt(np.mean(np.asarray(per_view, float) ** 2, axis=1))
    m = ("i", "j")
    out = xr.Dataset({
        "camera_matrix": (m, k_c), "projector_matrix": (m, k_p), "rotation": (m, r), "translation": ("i", t.ravel()),
        "camera_distortion": ("k", d_c.ravel()[:5]), "projector_distortion": ("k", d_p.ravel()[:5]),
        "rectify_camera": (m, r1), "rectify_projector": (m, r2), "project_camera": (("i", "m"), p1),
        "project_projector": (("i", "m"), p2), "pose_used": ("pose", np.array(used)), "pose_rms_px": ("pose", pose_rms),
    }, coords={"pose": target["pose"].values}, attrs=summary)
    return PROCAM_STEREO_CALIBRATION.label(out)
