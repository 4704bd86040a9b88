"""A real projector–camera rig described by a YAML file: the serial sync controller, the projector behind it
and a rolling-shutter camera triggered by it through OpenCV.

Example (``docs/devices.md``)::

    sync: {url: /dev/ttyACM0, timeout_s: 1}
    camera: {source: 0, width: 1600, height: 1200, discard: 0}
    scan: {row_period_us: 17.0, line_time_us: 17.0}   # 1/v_p (µs per camera row) and t_p, from calibrate_scan_speed
    dark_level: 64          # counts
    saturation_level: 4095  # counts

The projector's size and pattern slots are read from the controller (``PROJ?``); the delay and exposure
limits too (``LIM?``), so a sweep it cannot do is refused before anything moves.
"""

from __future__ import annotations

import os

import pydantic

from selpath.devices.hardware import CameraConfig
from selpath.devices.opencv_camera import OpenCVCamera
from selpath.devices.procam_acquire import ProcamInstruments
from selpath.devices.serial_projector import SyncLineProjector
from selpath.devices.serial_sync import SerialSyncController
from selpath.pipeline.yaml_source import load_yaml_model


class _Model(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SyncConfig(_Model):
    url: str = pydantic.Field(description="serial.serial_for_url URL of the sync controller: /dev/ttyACM0, ...")
    timeout_s: float = pydantic.Field(1.0, gt=0, description="time allowed for each reply [s]")
    retries: int = pydantic.Field(2, ge=0, le=10, description="extra tries of an idempotent query")


class ScanConfig(_Model):
    """The raster scan's timing, from the scan-speed calibration (§5.3.2; ``calibrate_scan_speed``)."""

    row_period_us: float = pydantic.Field(gt=0, description="µs the scan takes per camera row: 1/v_p, v_p in camera "
                                          "rows per µs as calibrate_scan_speed reports it")
    line_time_us: float = pydantic.Field(gt=0, description="t_p, how long one row is lit [µs]")


class ProcamHardwareConfig(_Model):
    sync: SyncConfig
    camera: CameraConfig
    scan: ScanConfig
    dark_level: float = pydantic.Field(0.0, ge=0, description="counts of an unlit pixel")
    saturation_level: float = pydantic.Field(4095.0, gt=0, description="raw count at which the sensor clips")

    @pydantic.model_validator(mode="after")
    def _levels(self):
        if self.saturation_level <= self.dark_level:
            raise ValueError(f"saturation_level {self.saturation_level:g} must exceed dark_level "
                             f"{self.dark_level:g} counts")
        return self


def load_procam_hardware(path: str | os.PathLike) -> ProcamHardwareConfig:
    """Read and check a projector–camera rig file; one SpecError lists every problem with its file:line."""
    return load_yaml_model(path, ProcamHardwareConfig, what="projector-camera rig")


def procam_hardware_rig(config: ProcamHardwareConfig) -> ProcamInstruments:
    """Open the sync controller (and the projector on its line) and the camera.

    The camera is opened with the trigger armed, so a camera waiting for its trigger delivers the frame that
    tells its size; that frame is dropped, and every capture reads the frame of the next trigger.
    """
    sync = SerialSyncController(config.sync.url, timeout_s=config.sync.timeout_s, retries=config.sync.retries)
    try:
        identity = sync.identify()
        projector = SyncLineProjector(sync.line, retries=config.sync.retries)
        shape = projector.shape
        sync.limits  # noqa: B018 (read now: a controller that cannot say its limits fails before the camera opens)
        sync.arm()
        cam = config.camera
        camera = OpenCVCamera(cam.source, width=cam.width, height=cam.height, exposure=cam.exposure,
                              discard=cam.discard, keep_first=False)
    except BaseException:
        sync.close()
        raise
    attrs = {"scan_speed_px_per_us": 1.0 / config.scan.row_period_us, "line_time_us": config.scan.line_time_us,
             "projector_shape": list(shape), "dark_level_counts": config.dark_level,
             "saturation_counts": config.saturation_level, "rig": "hardware", "sync_controller": identity}
    return ProcamInstruments(sync, projector, camera, attrs)
