"""Projector–camera scenes: what the simulated rig looks at, and the rig itself (§5.2–5.4).

A scene is a list of objects painted over a background in camera-image coordinates (fractions of the
image's width and height, so one scene renders at any sensor size). Each object has an albedo, a
disparity (where its direct correspondence lies in the projector) and the light-transport **effects** it
shows; the ground-truth transport of a pixel is assembled from *only the effects its object names*
(``selpath.devices.sim.procam_transport``), each as separable lobes in offset space:

``subsurface``               an isotropic exponential lobe at the direct correspondence (candle, milk, soap),
                             optionally with an absorbing layer below the surface (a vein: :class:`Absorber`);
``diffuse_interreflection``  a broad, horizontally extended lobe whose strength falls with the distance from
                             a concave corner (the book's gutter);
``specular_interreflection`` a narrow peak far from the direct correspondence, displaced by a fixed vector
                             plus a gain times the pixel's position (a mirror or disco ball reflecting the
                             projector onto the pixel's surface), optionally broken into facet spots;
``refraction``               a narrow peak at the point mirrored through a ball's centre (a glass ball).

Direct diffuse reflection (a delta at zero offset, weight = albedo minus what subsurface takes) is always
present where albedo > 0. The rig (:class:`ProcamRig`) names its own effects: laser/sync jitter and sensor
noise run only when given.

Rows are rectified: projector rows are resampled onto camera rows, so a plane-to-ray offset is in camera
rows and v_p is in camera rows per µs. Projector columns stay projector pixels (the ``du`` axis).
"""

from __future__ import annotations

import os
from typing import Annotated, Literal

import numpy as np
import pydantic

from selpath.devices.sim.scene import saturation_above_dark
from selpath.devices.sim.units import Angle, Pixels, quantity
from selpath.pipeline.yaml_source import load_yaml_model

Micros = quantity({"us": 1.0, "ms": 1e3, "s": 1e6}, "170 us", "a duration")
Fraction = Annotated[float, pydantic.Field(ge=0.0, le=1.0)]


class _Model(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, validate_default=True)


class Rectangle(_Model):
    kind: Literal["rectangle"]
    x: tuple[float, float] = pydantic.Field(description="left, right as fractions of the image width; left < right")
    y: tuple[float, float] = pydantic.Field(description="top, bottom as fractions of the image height; top < bottom")

    @pydantic.field_validator("x", "y")
    @classmethod
    def _ordered(cls, value):
        if not value[0] < value[1]:
            raise ValueError(f"[{value[0]:g}, {value[1]:g}] is empty: the first edge must be below the second")
        return value

    def mask(self, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        return (fx >= self.x[0]) & (fx < self.x[1]) & (fy >= self.y[0]) & (fy < self.y[1])


class Disk(_Model):
    kind: Literal["disk"]
    centre: tuple[float, float] = pydantic.Field(description="x, y as fractions of width and height")
    radius: float = pydantic.Field(gt=0, description="fraction of the image height")

    def mask(self, fx: np.ndarray, fy: np.ndarray, aspect: float) -> np.ndarray:
        return ((fx - self.centre[0]) * aspect) ** 2 + (fy - self.centre[1]) ** 2 < self.radius**2


class Band(_Model):
    """A straight band (a vein): from ``start`` to ``end`` (fractions), ``width`` as a fraction of the height."""

    kind: Literal["band"]
    start: tuple[float, float]
    end: tuple[float, float]
    width: float = pydantic.Field(gt=0)

    def mask(self, fx: np.ndarray, fy: np.ndarray, aspect: float) -> np.ndarray:
        p0, p1 = np.array(self.start) * [aspect, 1.0], np.array(self.end) * [aspect, 1.0]
        d = p1 - p0
        px, py = fx * aspect - p0[0], fy - p0[1]
        t = np.clip((px * d[0] + py * d[1]) / max(float(d @ d), 1e-12), 0.0, 1.0)
        return np.hypot(px - t * d[0], py - t * d[1]) < self.width / 2


Region = Annotated[Rectangle | Disk | Band, pydantic.Field(discriminator="kind")]


class Absorber(_Model):
    """A layer below the surface that absorbs light crossing it: a vein under the skin (§5.4.7).

    Light that leaves a pixel having entered the surface a distance ρ away travelled down to a depth of about ρ/2
    (diffuse reflectance's rule of thumb: the probing depth is about half the source–detector separation; stated,
    not fitted). So the light that crossed a layer at depths [depth, depth + thickness] is the light that entered
    at ρ in [2·depth, 2·(depth + thickness)], and ``absorption`` of it is lost. It acts on the vertical offset: in
    the plane-to-ray geometry the lit row's distance from the pixel's row is ρ. Deeper paths are taken to pass the
    layer by (a vein is narrow against the paths' spread)."""

    depth: Annotated[Pixels, pydantic.Field(ge=0)] = pydantic.Field(description="depth of the layer's top, px")
    thickness: Annotated[Pixels, pydantic.Field(gt=0)] = pydantic.Field(description="the layer's thickness, px")
    absorption: Fraction = pydantic.Field(description="share of the light crossing the layer that it absorbs")

    def absorbed_offsets(self) -> tuple[float, float, float]:
        """(low, high, share): the entry distances [px] whose light crosses the layer, and the share it loses."""
        return 2.0 * self.depth, 2.0 * (self.depth + self.thickness), self.absorption


class Subsurface(_Model):
    width: Annotated[Pixels, pydantic.Field(gt=0)] = pydantic.Field(description="1/e width of the lobe, px")
    fraction: Fraction = pydantic.Field(description="share of the albedo that scatters below the surface")
    absorber: Absorber | None = pydantic.Field(None, description="an absorbing layer below (a vein); None: none")


class DiffuseInterreflection(_Model):
    corner_x: float = pydantic.Field(description="x of the concave corner (fraction of the width)")
    strength: Annotated[float, pydantic.Field(ge=0)]
    falloff: float = pydantic.Field(0.1, gt=0, description="fraction of the width over which it falls by 1/e")
    width_v: Annotated[Pixels, pydantic.Field(gt=0)] = "3 px"


class SpecularInterreflection(_Model):
    centre: tuple[float, float] = pydantic.Field(description="x, y of the reflecting ball (fractions)")
    reach: float = pydantic.Field(gt=0, description="radius of the pool of reflected light (fraction of height)")
    displacement: tuple[Pixels, Pixels] = pydantic.Field(description="du, dv of the peak at the ball's centre")
    gain: float = pydantic.Field(-1.0, description="how the peak moves with the pixel: d(du, dv)/d(pixel)")
    strength: Annotated[float, pydantic.Field(ge=0)]
    width: Annotated[Pixels, pydantic.Field(gt=0)] = "0.7 px"
    facets: float | None = pydantic.Field(None, gt=0, description="disco ball: spot period (fraction of height)")


class Refraction(_Model):
    centre: tuple[float, float] = pydantic.Field(description="x, y of the glass ball (fractions)")
    transmittance: Fraction
    width: Annotated[Pixels, pydantic.Field(gt=0)] = "1 px"


class Effects(_Model):
    subsurface: Subsurface | None = None
    diffuse_interreflection: DiffuseInterreflection | None = None
    specular_interreflection: SpecularInterreflection | None = None
    refraction: Refraction | None = None

    def names(self) -> tuple[str, ...]:
        return tuple(name for name in type(self).model_fields if getattr(self, name) is not None)


class SceneObject(_Model):
    name: str
    region: Region
    albedo: Fraction
    disparity: Pixels = "0 px"
    effects: Effects = Effects()


class Background(_Model):
    albedo: Fraction = 0.2
    disparity: Pixels = "0 px"
    effects: Effects = Effects()


class Jitter(_Model):
    std: Annotated[Micros, pydantic.Field(ge=0)] = pydantic.Field(description="per-row laser timing jitter")
    seed: int = pydantic.Field(0, ge=0)


class SensorNoise(_Model):
    gain: float | None = pydantic.Field(1.0, gt=0, description="counts per photo-electron (shot); null: none")
    read_std: float = pydantic.Field(2.0, ge=0, description="counts")
    seed: int = pydantic.Field(0, ge=0)


class Misalignment(_Model):
    """A rig whose rows are not epipolar (§6.1 assumes they are): the light a camera pixel (s, c) receives
    directly comes from projector row s + δ (in camera rows), δ(s, c) = shift + tan(roll)·(c − (C − 1)/2) — a
    projector rolled about its axis and shifted, as seen on the camera's rows."""

    roll: Angle = pydantic.Field("0 deg", description="rotation of the projector's rows against the camera's")
    shift: Pixels = pydantic.Field("0 px", description="offset of the projector's rows, camera rows")

    def offset(self, cols: np.ndarray, camera_cols: int) -> np.ndarray:
        """δ [camera rows] of pixels in camera columns ``cols`` (the same on every row)."""
        return self.shift + np.tan(np.deg2rad(self.roll)) * (np.asarray(cols, float) - (camera_cols - 1) / 2)


class ProcamRig(_Model):
    """The synchronised projector–camera rig (§5.3.2) and the effects of its own it simulates."""

    camera_rows: int = pydantic.Field(1200, gt=0)
    camera_cols: int = pydantic.Field(1600, gt=0)
    projector_rows: int = pydantic.Field(720, gt=0)
    projector_cols: int = pydantic.Field(1280, gt=0)
    row_period: Annotated[Micros, pydantic.Field(gt=0)] = pydantic.Field(
        "17 us", description="time between successive rows of the raster scan: 1/v_p (t_e = 170 µs ↔ 10 rows)")
    line_time: Annotated[Micros, pydantic.Field(gt=0)] = pydantic.Field(
        "17 us", description="t_p, how long one row is lit; above row_period the illumination widens")
    sync_offset: Micros = pydantic.Field("0 us", description="true delay minus the commanded one (calibrated, §5.3.2)")
    intensity: float = pydantic.Field(1000.0, gt=0, description="counts of a white pixel lit for the whole t_p")
    dark_level: float = pydantic.Field(0.0, ge=0)
    saturation_level: float = pydantic.Field(4095.0, gt=0)
    bits: int | None = pydantic.Field(12, gt=0, description="quantise to integers below 2**bits; null: float")
    jitter: Jitter | None = None
    noise: SensorNoise | None = None
    frame_interval: Micros = pydantic.Field("0 us", ge=0, description="simulated readout time per frame")
    misalignment: Misalignment | None = pydantic.Field(None, description="rows not epipolar (default: rectified)")

    _levels = pydantic.model_validator(mode="after")(lambda self: saturation_above_dark(self))

    @property
    def scan_speed(self) -> float:
        """v_p [camera rows per µs]."""
        return 1.0 / self.row_period

    def attrs(self) -> dict:
        """What a capture store records about the rig (docs/format.md)."""
        return {"scan_speed_px_per_us": self.scan_speed, "line_time_us": self.line_time,
                "projector_shape": [self.projector_rows, self.projector_cols],
                "dark_level_counts": self.dark_level, "saturation_counts": self.saturation_level}


class ProcamScene(_Model):
    """A projector–camera scene: background, objects (later ones paint over earlier ones), rig."""

    scene: str
    description: str = ""
    background: Background = Background()
    objects: tuple[SceneObject, ...] = ()
    rig: ProcamRig = ProcamRig()

    def with_rig(self, **changes) -> ProcamScene:
        return self.model_copy(update={"rig": self.rig.model_copy(update=changes)})

    def effect_names(self) -> tuple[str, ...]:
        names = set(self.background.effects.names())
        for obj in self.objects:
            names |= set(obj.effects.names())
        return tuple(sorted(names))


def load_procam_scene(path: str | os.PathLike) -> ProcamScene:
    """Read and check a projector–camera scene; one SpecError lists every problem with its file:line and field."""
    return load_yaml_model(path, ProcamScene, what="projector-camera scene")
