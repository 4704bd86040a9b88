"""A real tomography rig described by a YAML file: serial rotary stage, OpenCV camera, manual lights.

Example (``docs/devices.md``)::

    stage: {url: /dev/ttyUSB0, move_timeout_s: 30}
    camera: {source: 0, width: 1600, height: 1200}
    geometry: {camera_model: perspective, light_angle_deg: 45, length_unit: mm, focal_length_px: 2400,
               camera_distance: 400, light_distance: 300}
    saturation_level: 4095
"""

from __future__ import annotations

import os
from typing import Literal

import pydantic

from selpath.devices.manual import ManualLight, ManualSampleChanger
from selpath.devices.opencv_camera import OpenCVCamera
from selpath.devices.serial_stage import SerialRotaryStage
from selpath.devices.tomography_acquire import TomographyRig
from selpath.geometry.rig import CAMERA_ATTRS, CameraModel, RigGeometry, camera_attr_problems
from selpath.pipeline.yaml_source import load_yaml_model


class _Model(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class StageConfig(_Model):
    url: str = pydantic.Field(description="serial.serial_for_url URL: /dev/ttyUSB0, socket://host:port, ...")
    timeout_s: float = pydantic.Field(1.0, gt=0)
    move_timeout_s: float = pydantic.Field(30.0, gt=0)
    retries: int = pydantic.Field(2, ge=0, le=10)
    tolerance_deg: float = pydantic.Field(0.01, gt=0)


class CameraConfig(_Model):
    source: int | str = pydantic.Field(description="OpenCV camera index or stream URL")
    width: int | None = pydantic.Field(None, gt=0, description="frame width to ask for [px]")
    height: int | None = pydantic.Field(None, gt=0, description="frame height to ask for [px]")
    exposure: float | None = pydantic.Field(None, description="CAP_PROP_EXPOSURE as the backend reads it; signed "
                                            "(many backends take log2 seconds, e.g. -6)")
    discard: int = pydantic.Field(0, ge=0)


class GeometryConfig(_Model):
    """Rig geometry written into every capture (DESIGN §8); lengths in ``length_unit``.

    The fields are the attrs of :class:`selpath.geometry.rig.RigGeometry` (a test keeps them in step), and which a
    camera model needs comes from their one declaration, :data:`selpath.geometry.rig.CAMERA_ATTRS`; the principal
    point defaults to the sensor's centre.
    """

    camera_model: CameraModel
    light_angle_deg: float = pydantic.Field(ge=0, le=180)
    length_unit: Literal["m", "cm", "mm", "um"]
    light_kind: Literal["beam", "sheet"] = "beam"
    beam_height: float = 0.0
    focal_length_px: float | None = pydantic.Field(None, gt=0)
    principal_point_px: tuple[float, float] | None = None
    camera_distance: float | None = pydantic.Field(None, gt=0)
    light_distance: float | None = pydantic.Field(None, gt=0)
    pixel_size: float | None = pydantic.Field(None, gt=0)

    @pydantic.model_validator(mode="after")
    def _complete(self):
        given = self.model_dump(exclude_none=True)
        problems = camera_attr_problems(given, sensor_defaults=True)
        own = set(CAMERA_ATTRS[self.camera_model])
        foreign = {a for model, names in CAMERA_ATTRS.items() if model != self.camera_model for a in names}
        article = "an" if self.camera_model[0] in "aeiou" else "a"
        problems += [f"{a} is not a setting of {article} {self.camera_model} camera (it would be ignored)"
                     for a in sorted(foreign - own - {"light_distance"}) if a in given]
        if problems:
            raise ValueError("; ".join(problems))
        return self


class HardwareRigConfig(_Model):
    stage: StageConfig
    camera: CameraConfig
    geometry: GeometryConfig
    saturation_level: float = pydantic.Field(4095.0, gt=0, description="raw count at which the sensor saturates")


def load_hardware(path: str | os.PathLike) -> HardwareRigConfig:
    return load_yaml_model(path, HardwareRigConfig, what="rig")


def hardware_rig(config: HardwareRigConfig) -> TomographyRig:
    """Open the stage and the camera; lights and samples are switched by the operator."""
    stage = SerialRotaryStage(config.stage.url, timeout_s=config.stage.timeout_s,
                              move_timeout_s=config.stage.move_timeout_s, retries=config.stage.retries,
                              tolerance_deg=config.stage.tolerance_deg)
    try:
        cam = config.camera
        camera = OpenCVCamera(cam.source, width=cam.width, height=cam.height, exposure=cam.exposure,
                              discard=cam.discard)
    except BaseException:
        stage.close()
        raise
    rows, cols = camera.shape
    geometry = RigGeometry.from_attrs(config.geometry.model_dump(exclude_none=True), rows, cols, where="rig geometry")
    attrs = geometry.attrs() | {"saturation_counts": config.saturation_level, "rig": "hardware"}
    return TomographyRig(stage, camera, ManualLight("beam"), ManualLight("backlight"), ManualSampleChanger(),
                         attrs, tolerance_deg=config.stage.tolerance_deg)
