"""Acquisitions of projected patterns as workflow steps: shifted checkerboards (direct/global separation, §5.4.6),
Gray codes (the projector pixel lighting each camera pixel; the rows' alignment) and a checkerboard target seen by
the pair (stereo calibration). Like the sweeps of :mod:`selpath.stages.procam.acquire`, each fills its own store
frame by frame and resumes where a killed run stopped.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import xarray as xr

from selpath.devices.procam_acquire import acquire_checkerboards as checkerboard_sweep
from selpath.devices.procam_acquire import acquire_gray_code as gray_code_stack
from selpath.devices.procam_acquire import checkerboard_shifts
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.devices.sim.stereo_target import capture_target, load_stereo_target
from selpath.pipeline.constraints import Count, Positive, StorePath
from selpath.pipeline.errors import SelpathError
from selpath.pipeline.kinds import SENSOR_COUNTS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import file_identity, read_file, sweep_log
from selpath.stages.procam.acquire import (
    CAMERA_LEVELS,
    RigChanges,
    SensorSize,
    acquisition_identity,
    acquisition_precheck,
    acquisition_rig,
    acquisition_scene,
)

_FRAME = ("row", "col")
CHECKERBOARD_CAPTURE = CubeKind(
    name="checkerboard_capture",
    description="one frame per shifted checkerboard, floodlit or epipolar (§5.4.6)",
    variables={"image": Variable(("shift", *_FRAME), **SENSOR_COUNTS)},
    coord_units={"shift": frozenset({"1"})},
    attrs={"square_px": "checkerboard square [rows, cols], projector px",
           "mode": "'floodlit' (global shutter over the whole scan) or 'epipolar' (t_d = 0, t_e = t_p)",
           **CAMERA_LEVELS},
)
GRAY_CODE_CAPTURE = CubeKind(
    name="gray_code_capture",
    description="white, black and every Gray-code bit with its inverse, columns then rows (acquire_gray_code)",
    variables={"image": Variable(("pattern", *_FRAME), **SENSOR_COUNTS)},
    coord_units={"pattern": frozenset({"1"})},
    attrs={"column_bits": "column bits (patterns 2, 4, … after white and black; each followed by its inverse)",
           "row_bits": "row bits (after the column bits' pairs)",
           "projector_shape": "[rows, cols] of the projector",
           "exposure_us": "t_e of every frame, µs (many rows: a pixel sees the rows around its own)",
           **CAMERA_LEVELS},
)
STEREO_TARGET_CAPTURE = CubeKind(
    name="stereo_target_capture",
    description="a checkerboard target at several poses under white, black and the projector's Gray codes",
    variables={"image": Variable(("pose", "pattern", *_FRAME), **SENSOR_COUNTS)},
    coord_units={"pose": frozenset({"1"}), "pattern": frozenset({"1"})},
    attrs={"column_bits": "column bits (as in a gray_code_capture)", "row_bits": "row bits",
           "projector_shape": "[rows, cols] of the projector",
           "board_corners": "[columns, rows] of the board's inner corners",
           "board_square_mm": "side of a board square, mm", **CAMERA_LEVELS},
)


def _checkerboard_precheck(settings) -> list[str]:
    problems = acquisition_precheck(settings, lambda spec: tuple([v] for v in exposure_window(spec, settings.mode)))
    if settings.rig == "hardware" and settings.mode == "floodlit":
        problems.append("mode floodlit needs the camera's global shutter; a hardware rig's OpenCV camera has none "
                        "(use mode: epipolar)")
    return problems


def exposure_window(spec: ProcamScene, mode: str) -> tuple[float, float]:
    """(t_d, t_e) [µs]: ``epipolar``: 0 and t_p (the synchronised epipolar frame); ``floodlit``: a global-shutter
    exposure that opens before the scan's first row and closes after its last, with two line times, the sync
    offset and six jitter deviations to spare on each side (every row lit for its whole line time: the regular
    image). Its exposure, rows · τ plus the margins, must fit the controller: 20 ms, about 1,170 rows at
    τ = 17 µs (the shipped workflow renders 300)."""
    rig = spec.rig
    if mode == "epipolar":
        return 0.0, float(rig.line_time)
    margin = 2 * rig.line_time + abs(rig.sync_offset) + (6 * rig.jitter.std if rig.jitter is not None else 0.0)
    return -margin, float(rig.camera_rows * rig.row_period + rig.line_time + 2 * margin)


@stage("acquire_checkerboards", kind=CHECKERBOARD_CAPTURE, precheck=_checkerboard_precheck,
       identity=acquisition_identity, writes=lambda settings: settings.store, variables=lambda settings: ["image"])
def acquire_checkerboards(
    *,
    store: StorePath,
    mode: Literal["floodlit", "epipolar"],
    square: Count = 24,
    shifts_per_axis: Count = 4,
    rig: Literal["sim", "hardware"] = "sim",
    scene: StorePath = "",
    hardware: StorePath = "",
    sensor: SensorSize | None = None,
    rig_changes: RigChanges | None = None,
    progress: bool = True,
) -> xr.Dataset:
    """Shifted high-frequency checkerboards for direct/global separation (§5.4.6): one frame per shift, frame by
    frame and resumably, floodlit (global shutter: Nayar et al.'s frames) or epipolar (t_d = 0, t_e = t_p).

    Parameters
    ----------
    store : str
        Zarr store the frames land in (a ``checkerboard_capture``); an existing store of the same boards resumes.
    mode : str
        ``floodlit``: the camera's global shutter open over the whole scan (the regular image under the board);
        ``epipolar``: the synchronised rolling shutter at t_d = 0, t_e = t_p (only the pixel's own epipolar plane).
    square : int
        Side of a checkerboard square [projector px] (the thesis: 24); small against the scene's global light.
    shifts_per_axis : int
        Shifts per axis, evenly over one period (two squares) [1]: shifts_per_axis² frames (at least 2 per axis,
        so that every pixel is seen lit and dark; the thesis shifted its board 128 times).
    rig : str
        ``sim``: the transport simulator showing ``scene``; ``hardware``: the rig file ``hardware`` (epipolar mode
        only: its camera has no global shutter).
    scene : str
        Projector–camera scene file (``workflows/scenes/*.yaml``), for ``rig: sim``.
    hardware : str
        Projector–camera rig file, for ``rig: hardware`` (docs/devices.md).
    sensor : [rows, cols] or None
        Render at this sensor size instead of the scene rig's; a frame that would not fit in memory is refused.
    rig_changes : dict or None
        Changes to the scene's rig (as for ``acquire_plane_to_ray``).
    progress : bool
        Show a progress bar.

    Returns
    -------
    xr.Dataset
        A ``checkerboard_capture`` cube: the store ``store``: ``image`` [counts] over (shift, row, col) with each
        shift's board offset (``shift_row``, ``shift_col``), written frame by frame and opened lazily.

    References
    ----------
    Thesis §5.4.6 Epipolar direct/global separation.
    """
    if shifts_per_axis < 2:
        raise SelpathError(f"shifts_per_axis is {shifts_per_axis}: at least 2 are needed, so that every pixel of "
                           "the board is seen lit and dark")
    shifts = checkerboard_shifts((square, square), shifts_per_axis)
    with acquisition_rig(rig, scene, hardware, sensor, rig_changes) as instruments:
        if rig == "sim":
            delay, exposure = exposure_window(acquisition_scene(scene, sensor, rig_changes), mode)
        else:  # the synchronised epipolar frame: t_d = 0, t_e = t_p (floodlit is refused by the sweep)
            delay, exposure = 0.0, float(np.ceil(float(instruments.attrs["line_time_us"])))
        return checkerboard_sweep(instruments, store, (square, square), shifts, mode=mode, delay=delay,
                                  exposure=exposure, progress=progress, log=sweep_log(progress))


def gray_code_window(line_time: float, scan_speed: float, max_offset_rows: float) -> tuple[float, float]:
    """(t_d, t_e) [µs] of a Gray-code frame: delay 0 and an exposure that also takes in the projector rows up to
    ``max_offset_rows`` camera rows from each camera row's own (t_p + 2·max_offset / v_p, whole µs)."""
    return 0.0, float(np.ceil(line_time + 2 * max_offset_rows / scan_speed))


def _gray_code_precheck(settings) -> list[str]:
    return acquisition_precheck(settings, lambda spec: tuple([v] for v in gray_code_window(
        spec.rig.line_time, spec.rig.scan_speed, settings.max_offset_rows)))


@stage("acquire_gray_code", kind=GRAY_CODE_CAPTURE, precheck=_gray_code_precheck, identity=acquisition_identity,
       writes=lambda settings: settings.store, variables=lambda settings: ["image"])
def acquire_gray_code(
    *,
    store: StorePath,
    rig: Literal["sim", "hardware"] = "sim",
    scene: StorePath = "",
    hardware: StorePath = "",
    max_offset_rows: Positive = 16.0,
    sensor: SensorSize | None = None,
    rig_changes: RigChanges | None = None,
    progress: bool = True,
) -> xr.Dataset:
    """White, black and the projector's Gray codes at t_d = 0, frame by frame and resumably.

    Each column and row bit with its inverse (``cv2.structured_light``), with an exposure of many rows: what
    ``decode_gray_code`` turns into the projector pixel lighting each camera pixel, and ``epipolar_alignment`` into
    the rig's row misalignment.

    Parameters
    ----------
    store : str
        Zarr store the frames land in (a ``gray_code_capture``); an existing store of the same codes resumes.
    rig : str
        ``sim``: the transport simulator showing ``scene``; ``hardware``: the rig file ``hardware``.
    scene : str
        Projector–camera scene file, for ``rig: sim``.
    hardware : str
        Projector–camera rig file, for ``rig: hardware`` (docs/devices.md).
    max_offset_rows : float
        Misalignment the codes can still see [camera rows]: the exposure spans t_p + 2·max_offset / v_p, so each
        camera row also integrates the projector rows this far from its own (global light from them too).
    sensor : [rows, cols] or None
        Render at this sensor size instead of the scene rig's (``rig: sim``).
    rig_changes : dict or None
        Changes to the scene's rig (``rig: sim``), as for ``acquire_plane_to_ray``.
    progress : bool
        Show a progress bar.

    Returns
    -------
    xr.Dataset
        A ``gray_code_capture`` cube: the store ``store``: ``image`` [counts] over (pattern, row, col), white, black and
        the Gray codes, written frame by frame and opened lazily.

    References
    ----------
    Thesis §5.2.1 Epipolar geometry and light transport.
    """
    with acquisition_rig(rig, scene, hardware, sensor, rig_changes) as instruments:
        attrs = instruments.attrs
        delay, exposure = gray_code_window(float(attrs["line_time_us"]), float(attrs["scan_speed_px_per_us"]),
                                           max_offset_rows)
        return gray_code_stack(instruments, store, delay=delay, exposure=exposure, progress=progress,
                               log=sweep_log(progress))


def _target_precheck(settings) -> list[str]:
    return read_file(load_stereo_target, settings.scene, "scene")[1]


def _target_identity(settings) -> dict:
    return {"rig": "sim", **file_identity(settings.scene)}


@stage("acquire_stereo_target", kind=STEREO_TARGET_CAPTURE, precheck=_target_precheck, identity=_target_identity,
       writes=lambda settings: settings.store, variables=lambda settings: ["image"])
def acquire_stereo_target(*, store: StorePath, scene: StorePath, progress: bool = True) -> xr.Dataset:
    """A checkerboard target at several poses under white, black and Gray codes, filmed by a simulated pinhole pair.

    The pair and the target are ``scene``'s (``selpath.devices.sim.stereo_target``); frames are written one by one and a
    rerun resumes: what ``calibrate_procam_stereo`` calibrates the pair from.

    Parameters
    ----------
    store : str
        Zarr store the frames land in (a ``stereo_target_capture``); an existing store of the same scene resumes.
    scene : str
        Stereo target scene file (``workflows/scenes/stereo-target.yaml``): camera and projector intrinsics, the
        projector's pose (baseline, roll, pitch, yaw), the board and its poses, light and noise.
    progress : bool
        Show a progress bar.

    Returns
    -------
    xr.Dataset
        A ``stereo_target_capture`` cube: the store ``store``: ``image`` [counts] over (pose, pattern, row, col),
        written frame by frame and opened lazily.

    References
    ----------
    Thesis §5.2.1 Epipolar geometry and light transport.
    """
    return capture_target(load_stereo_target(scene), store, progress=progress, log=sweep_log(progress))
