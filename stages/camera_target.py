"""A camera's intrinsics from a checkerboard target (OpenCV ``calibrateCamera``), for either instrument.

``calibrate_camera`` finds the board's inner corners in one frame per pose (``cv2.findChessboardCornersSB``) and
fits the pinhole with OpenCV's distortion model, with standard deviations. ``apply_camera_calibration`` writes the
focal length and the principal row into a tomography capture: the principal column is where the rotation axis is
seen, which the tomography rig's model ties to the axis (``calibrate_rig`` measures it from the capture itself).
The rig model has no lens distortion: a calibration whose distortion moves a pixel by more than half a pixel
within the area the board covered is flagged (``distortion_max_px``) and refused by ``apply_camera_calibration``;
film the board near the sensor's corners too, or the check sees only its middle.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables

CAMERA_CALIBRATION = CubeKind(
    name="camera_calibration",
    description="a camera's intrinsics and distortion from a checkerboard target (calibrate_camera)",
    variables={"camera_matrix": Variable(("i", "j"), units="px", long_name="camera intrinsics K"),
               "distortion": Variable(("k",), units="1", long_name="k1, k2, p1, p2, k3"),
               "pose_used": Variable(("pose",), False, units=None, long_name="board found at this pose"),
               "pose_rms_px": Variable(("pose",), False, units="px", long_name="reprojection error of the pose")},
    attrs={"focal_length_px": "mean of fx and fy, px", "principal_point_px": "[cx, cy], px",
           "reprojection_rms_px": "reprojection error, px",
           "distortion_max_px": "largest shift of a pixel inside the sensor by the distortion, px",
           "sensor_px": "[rows, cols] of the calibrated sensor"},
)

#: distortion the tomography rig's pinhole model tolerates: the largest shift of a pixel inside the sensor [px]
MAX_DISTORTION_PX = 0.5


def camera_corners(frame: np.ndarray, corners: tuple[int, int]) -> np.ndarray | None:
    """The board's inner corners in a frame, sub-pixel (N, 2) float32 in OpenCV's order, or None if not all found.
    The frame is scaled to 8 bits by its own 99.5th percentile (any intensity scale)."""
    import cv2  # OpenCV when it calibrates, not when a workflow is read

    finite = np.nan_to_num(np.asarray(frame, float))
    top = np.percentile(finite, 99.5)
    image = np.clip(finite / max(top, 1e-12) * 255, 0, 255).astype(np.uint8)
    found, points = cv2.findChessboardCornersSB(image, tuple(corners), flags=cv2.CALIB_CB_ACCURACY)
    return points.reshape(-1, 2).astype(np.float32) if found else None


def board_points(corners: tuple[int, int], square: float) -> np.ndarray:
    """The inner corners on the board's plane [mm], row by row as OpenCV lists them, (N, 3) float32."""
    grid = np.stack(np.meshgrid(np.arange(corners[0]), np.arange(corners[1])), axis=-1).reshape(-1, 2)
    return np.hstack([grid * float(square), np.zeros((grid.shape[0], 1))]).astype(np.float32)


def board_frames(target: xr.Dataset) -> xr.DataArray:
    """One frame per pose: white − black of a ``stereo_target_capture``, or ``image`` over (pose, row, col)."""
    image = target["image"]
    if "pattern" in image.dims:
        return (image.isel(pattern=0) - image.isel(pattern=1)).transpose("pose", "row", "col")
    if set(image.dims) != {"pose", "row", "col"}:
        raise StageError(Problem(f"image has dims {image.dims}; expected (pose, row, col) or (pose, pattern, row, "
                                 "col)", path="image", fix="one frame of the board per pose"))
    return image.transpose("pose", "row", "col")


def distortion_shift(matrix: np.ndarray, distortion: np.ndarray, box: tuple[float, float, float, float]) -> float:
    """The largest distance [px] between where the distortion model puts a pixel and where the pinhole would, over
    a grid on ``box`` = (x0, y0, x1, y1) [px]: the area the board's corners covered (beyond it the polynomial is
    an extrapolation)."""
    import cv2

    xs, ys = np.meshgrid(np.linspace(box[0], box[2], 17), np.linspace(box[1], box[3], 13))
    points = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2).astype(np.float64)
    ideal = cv2.undistortPoints(points, matrix, distortion, P=matrix).reshape(-1, 2)
    return float(np.max(np.linalg.norm(ideal - points.reshape(-1, 2), axis=1)))


@stage("calibrate_camera", kind=CAMERA_CALIBRATION)
def calibrate_camera(target: xr.Dataset, /) -> xr.Dataset:
    """A camera's intrinsics from frames of a checkerboard target at several poses (OpenCV ``calibrateCamera``).

    Parameters
    ----------
    target : xr.Dataset
        Frames of the board: a ``stereo_target_capture`` (white − black of each pose) or ``image`` over (pose, row,
        col); attrs ``board_corners`` [columns, rows of inner corners] and ``board_square_mm``.

    Returns
    -------
    xr.Dataset
        A ``camera_calibration`` cube: ``camera_matrix`` (i, j) [px], ``distortion`` (k: k1, k2, p1, p2, k3) and per
        pose ``pose_used`` and ``pose_rms_px``; attrs ``focal_length_px`` (the mean of fx and fy),
        ``principal_point_px`` [cx, cy] (pixel centres at whole numbers), their standard deviations (``*_std_px``),
        ``pixel_aspect`` (fy / fx), ``reprojection_rms_px``, ``distortion_max_px`` (how far the distortion moves a pixel
        within the area the board's corners covered; k3 is held at 0) and ``sensor_px`` [rows, cols].

    References
    ----------
    Thesis §4.2.6 Light path alignment.
    """
    import cv2

    require_variables(target, ("image",), "calibrate_camera")
    missing = [a for a in ("board_corners", "board_square_mm") if a not in target.attrs]
    if missing:
        raise StageError(Problem(f"the target capture lacks attrs {', '.join(missing)}",
                                 fix="state the board: board_corners [columns, rows of inner corners], "
                                 "board_square_mm"))
    corners_shape = (int(target.attrs["board_corners"][0]), int(target.attrs["board_corners"][1]))
    board = board_points(corners_shape, float(target.attrs["board_square_mm"]))
    frames = board_frames(target)
    found = [camera_corners(frames.isel(pose=i).values, corners_shape) for i in range(frames.sizes["pose"])]
    used = np.array([f is not None for f in found])
    if used.sum() < 3:
        raise StageError(Problem(f"the board was found at {int(used.sum())} of {frames.sizes['pose']} poses; a "
                                 "calibration needs at least 3", fix="film the whole board at more poses, "
                                 "tilted differently; check board_corners"))
    points = [f for f in found if f is not None]
    rows, cols = frames.sizes["row"], frames.sizes["col"]
    # k3 fixed at 0 (OpenCV's advice for lenses that are not fish-eyes: free, it extrapolates wildly off the board)
    rms, matrix, distortion, _, _, std, _, per_view = cv2.calibrateCameraExtended(
        [board] * len(points), points, (cols, rows), None, None, flags=cv2.CALIB_FIX_K3)
    distortion = distortion.ravel()[:5]
    seen = np.concatenate(points)
    pose_rms = np.full(frames.sizes["pose"], np.nan)
    pose_rms[used] = np.asarray(per_view, float).ravel()
    std = std.ravel()
    attrs = {"focal_length_px": float((matrix[0, 0] + matrix[1, 1]) / 2),
             "focal_length_std_px": float(np.hypot(std[0], std[1]) / 2),
             "principal_point_px": [float(matrix[0, 2]), float(matrix[1, 2])],
             "principal_point_std_px": [float(std[2]), float(std[3])],
             "pixel_aspect": float(matrix[1, 1] / matrix[0, 0]), "reprojection_rms_px": float(rms),
             "distortion_max_px": distortion_shift(matrix, distortion, (*seen.min(axis=0), *seen.max(axis=0))),
             "sensor_px": [rows, cols]}
    return CAMERA_CALIBRATION.label(xr.Dataset({
        "camera_matrix": (("i", "j"), matrix), "distortion": ("k", distortion), "pose_used": ("pose", used),
        "pose_rms_px": ("pose", pose_rms)}, coords={"pose": frames["pose"].values}, attrs=attrs))


@stage("apply_camera_calibration")
def apply_camera_calibration(capture: xr.Dataset, calibration: xr.Dataset, /) -> xr.Dataset:
    """A tomography capture with the calibrated focal length and principal row in its attrs (frames untouched,
    lazy); the values it stated are kept as ``stated_focal_length_px`` and ``stated_principal_point_px``.

    The principal column is left as stated: in the rig's model it is where the rotation axis is seen
    (``calibrate_rig`` measures it). Refused: another sensor size, an orthographic camera (no focal length),
    a calibration whose distortion moves a pixel more than half a pixel (the rig's model is a pinhole) or whose
    pixels are not square within 3 standard deviations.

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` with a perspective camera (attrs ``camera_model``, ``focal_length_px``,
        ``principal_point_px`` where stated).
    calibration : xr.Dataset
        A ``calibrate_camera`` result of the same camera.

    Returns
    -------
    xr.Dataset
        The capture unchanged but for its attrs: ``focal_length_px`` and the principal point's row from the calibration,
        the stated values kept (``stated_focal_length_px``, ``stated_principal_point_px``); its kind is the capture's.

    References
    ----------
    Thesis §4.2.6 Light path alignment.
    """
    if calibration.attrs.get("selpath_kind") != CAMERA_CALIBRATION.name:
        raise StageError(Problem("the calibration is not a calibrate_camera result (selpath_kind "
                                 f"{calibration.attrs.get('selpath_kind')!r})"))
    a = calibration.attrs
    problems = []
    if capture.attrs.get("camera_model") != "perspective":
        problems.append(f"the capture's camera is {capture.attrs.get('camera_model')!r}; a focal length means "
                        "something only for a perspective camera")
    sensor = [capture.sizes.get("row"), capture.sizes.get("col")]
    if list(a["sensor_px"]) != sensor:
        problems.append(f"the calibration is of a {a['sensor_px'][0]} × {a['sensor_px'][1]} sensor, the capture's "
                        f"is {sensor[0]} × {sensor[1]}")
    if a["distortion_max_px"] > MAX_DISTORTION_PX:
        problems.append(f"the lens distortion moves pixels by up to {a['distortion_max_px']:.2f} px; the rig's "
                        f"pinhole model tolerates {MAX_DISTORTION_PX} (undistort the frames first)")
    aspect_std = 2 * a["focal_length_std_px"] / a["focal_length_px"]
    if abs(a["pixel_aspect"] - 1) > max(3 * aspect_std, 1e-4):
        problems.append(f"the pixels are not square (fy/fx = {a['pixel_aspect']:.5f}); the rig's model has one "
                        "focal length")
    if problems:
        raise StageError([Problem(p, where="apply_camera_calibration") for p in problems])
    stated = capture.attrs.get("principal_point_px", [(sensor[1] - 1) / 2, (sensor[0] - 1) / 2])
    # (a value another calibration already replaced keeps its first stated value)
    first = {k: v for k, v in {"stated_focal_length_px": capture.attrs.get("focal_length_px"),
                               "stated_principal_point_px": [float(v) for v in stated]}.items()
             if k not in capture.attrs}
    return capture.assign_attrs(first | {"focal_length_px": float(a["focal_length_px"]),
                                         "principal_point_px": [float(stated[0]), float(a["principal_point_px"][1])]})
