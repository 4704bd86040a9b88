"""Scene files of the tomography simulator (YAML under ``workflows/scenes/``), with units.

Every length carries its unit (``"20 mm"``, ``"2 cm"``), every absorption or scattering coefficient
its inverse length (``"0.15 /mm"``), every angle ``deg`` or ``rad``, pixel quantities ``px`` and times
``s``/``ms``/``us``; a bare number where a unit is needed is an error naming the field. Internally
everything is converted to mm, degrees and seconds. The simulator computes **only the effects a scene
names** under ``effects:`` (``scattering``, ``noise``); an unknown effect is an error.

>>> scene = Scene.model_validate({
...     "scene": "disk", "object": {"shape": {"kind": "cylinder", "radius": "2 cm"}, "height": "40 mm"},
...     "light": {"kind": "beam", "angle": "45 deg", "distance": "300 mm"},
...     "camera": {"model": "orthographic", "rows": 8, "cols": 64, "pixel_size": "0.7 mm"}})
>>> scene.object.shape.radius, scene.light.angle, scene.effects.names()
(20.0, 45.0, ())
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from typing import Annotated, Any, Literal

import numpy as np
import pydantic
from pydantic_core import PydanticCustomError

from selpath.devices.sim.units import (
    SCENE_LENGTH_UNITS,
    Angle,
    Duration,
    InvLength,
    Length,
    Pixels,
    lengths_in,
    scene_length_unit,
)
from selpath.geometry.rig import OrthographicCamera, PerspectiveCamera, RigGeometry
from selpath.geometry.shapes import Ellipse, Ellipsoid, Polygon, Prism, Solid, convex_polygon
from selpath.pipeline.yaml_source import load_yaml_model


def saturation_above_dark(sensor):
    """Model validator of sensors: the full well lies above the dark level."""
    if sensor.saturation_level <= sensor.dark_level:
        raise ValueError(f"saturation_level ({sensor.saturation_level:g}) must be above dark_level "
                         f"({sensor.dark_level:g}) [counts]")
    return sensor


class _Model(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Cylinder(_Model):
    kind: Literal["cylinder"]
    radius: Annotated[Length, pydantic.Field(gt=0)]
    centre: tuple[Length, Length] = (0.0, 0.0)

    def build(self) -> Ellipse:
        return Ellipse(self.centre, (self.radius, self.radius))


#: a semi-axis of an ellipse or ellipsoid
SemiAxis = Annotated[Length, pydantic.Field(gt=0)]


class EllipseSpec(_Model):
    kind: Literal["ellipse"]
    semi_axes: tuple[SemiAxis, SemiAxis]
    angle: Angle = 0.0
    centre: tuple[Length, Length] = (0.0, 0.0)

    def build(self) -> Ellipse:
        return Ellipse(self.centre, self.semi_axes, np.deg2rad(self.angle))


class PolygonSpec(_Model):
    kind: Literal["polygon"]
    vertices: list[tuple[Length, Length]]

    @pydantic.field_validator("vertices")
    @classmethod
    def _convex(cls, value):
        convex_polygon(value)  # raises ValueError naming the vertex where it is not convex
        return value

    def build(self) -> Polygon:
        return convex_polygon(self.vertices)


class EllipsoidSpec(_Model):
    """A solid ellipsoid (a grape): its own height, so an object of this shape takes no ``height`` and an inclusion
    no ``z_range``."""

    kind: Literal["ellipsoid"]
    semi_axes: tuple[SemiAxis, SemiAxis, SemiAxis] = pydantic.Field(description="along x, y and z before the turn")
    centre: tuple[Length, Length, Length] = (0.0, 0.0, 0.0)
    angle: Angle = pydantic.Field(0.0, description="turn about z, counter-clockwise seen from +z")

    def build(self) -> Ellipsoid:
        return Ellipsoid(self.centre, self.semi_axes, np.deg2rad(self.angle))


ShapeSpec = Annotated[Cylinder | EllipseSpec | PolygonSpec | EllipsoidSpec, pydantic.Field(discriminator="kind")]


def solid(shape, z_range: tuple[float, float] | None) -> Solid:
    """The solid a shape spec makes: an ellipsoid as it is, a cross-section extruded over ``z_range``."""
    if isinstance(shape, EllipsoidSpec):
        return shape.build()
    return Prism(shape.build(), z_range if z_range is not None else (-np.inf, np.inf))


class Inclusion(_Model):
    """A region whose absorption adds to the medium's (negative values allowed, as in Shepp–Logan)."""

    name: str = ""
    shape: ShapeSpec
    sigma: InvLength
    z_range: tuple[Length, Length] | None = pydantic.Field(None, description="[low, high], low < high; default: "
                                                           "the object's height")

    @pydantic.field_validator("z_range")
    @classmethod
    def _ordered(cls, value):
        if value is not None and not value[0] < value[1]:
            raise ValueError(f"z_range [{value[0]:g}, {value[1]:g}] mm is empty: the low end must be below the high")
        return value

    @pydantic.model_validator(mode="after")
    def _one_height(self):
        if isinstance(self.shape, EllipsoidSpec) and self.z_range is not None:
            raise ValueError("an ellipsoid inclusion has its own height: leave out z_range")
        return self


class Skin(_Model):
    transmittance: float = pydantic.Field(0.8, gt=0, le=1, description="thin diffusing skin, crossed twice")


class Medium(_Model):
    sigma: Annotated[InvLength, pydantic.Field(ge=0)] = 0.0


class SceneObject(_Model):
    shape: ShapeSpec
    height: Annotated[Length, pydantic.Field(gt=0)] | None = pydantic.Field(
        None, description="of the prism a cross-section makes, centred on z = 0; none for an ellipsoid")
    skin: Skin = Skin()
    medium: Medium = Medium()
    inclusions: list[Inclusion] = []

    @pydantic.model_validator(mode="after")
    def _height_given_once(self):
        if isinstance(self.shape, EllipsoidSpec) and self.height is not None:
            raise ValueError("an ellipsoid has its own height (2 × its z semi-axis): leave out object.height")
        if not isinstance(self.shape, EllipsoidSpec) and self.height is None:
            raise ValueError(f"a {self.shape.kind} is a cross-section: give object.height, the prism's height")
        return self

    def solid(self) -> Solid:
        """The object as a solid (object frame: z up along the rotation axis)."""
        half = None if self.height is None else (-self.height / 2.0, self.height / 2.0)
        return solid(self.shape, half)

    def inclusion_solids(self) -> tuple[tuple[Solid, float], ...]:
        """Each inclusion's solid (a cross-section spans ``z_range``, by default the object's height) and σ."""
        body_z = self.solid().z_range
        return tuple((solid(i.shape, i.z_range or body_z), i.sigma) for i in self.inclusions)

    @pydantic.model_validator(mode="after")
    def _inclusions_inside(self):
        body = self.solid()
        solids = self.inclusion_solids()
        for i, ((inc, _), spec) in enumerate(zip(solids, self.inclusions, strict=True)):
            if not body.contains(inc.surface(64)).all():
                hint = ("; a cross-section spans the object's height unless given a z_range"
                        if isinstance(self.shape, EllipsoidSpec) and not isinstance(spec.shape, EllipsoidSpec)
                        and spec.z_range is None else "")
                raise ValueError(f"inclusions[{i}] ({spec.name or spec.shape.kind}) reaches outside the object{hint}")
        if solids:  # the absorption field must be physical: sum of medium and inclusions >= 0
            total = absorption_field(self.medium.sigma, body, solids)
            if total.min() < -1e-12:
                raise ValueError(f"medium + inclusions give a negative absorption ({total.min():.3g} /mm)")
        return self


def absorption_field(medium: float, body: Solid, solids) -> np.ndarray:
    """σ of the medium plus the inclusions at sample points inside ``body``: 201² in x–y at the mid-height of
    every z band between the solids' ends, and at every ellipsoid's centre."""
    reach = body.reach()
    ends = sorted({float(z) for s in (body, *(s for s, _ in solids)) for z in s.z_range if np.isfinite(z)})
    heights = [(a + b) / 2 for a, b in zip(ends, ends[1:], strict=False)] or [0.0]
    heights += [s.centre[2] for s, _ in solids if isinstance(s, Ellipsoid)]
    xy = np.stack(np.meshgrid(*[np.linspace(-reach, reach, 201)] * 2), axis=-1).reshape(-1, 2)
    points = np.vstack([np.column_stack([xy, np.full(len(xy), z)]) for z in heights])
    points = points[body.contains(points)]
    total = np.full(len(points), medium)
    for inc, sigma in solids:
        total += sigma * inc.contains(points)
    return total


class Light(_Model):
    kind: Literal["beam", "sheet"] = pydantic.Field(description="narrow collimated beam, or vertical light sheet")
    angle: Annotated[Angle, pydantic.Field(ge=0, le=180)] = pydantic.Field(description="θ_l to the camera axis")
    distance: Annotated[Length, pydantic.Field(gt=0)]
    height: Length = pydantic.Field(0.0, description="z of the beam (beam only)")
    intensity: float = pydantic.Field(3000.0, gt=0, description="counts of the brightest exit point, about")


class PerspectiveCameraSpec(_Model):
    model: Literal["perspective"]
    rows: int = pydantic.Field(gt=0)
    cols: int = pydantic.Field(gt=0)
    distance: Annotated[Length, pydantic.Field(gt=0)]
    focal_length: Annotated[Pixels, pydantic.Field(gt=0)] | None = None
    fov: Annotated[Angle, pydantic.Field(gt=0, lt=180)] | None = pydantic.Field(
        None, description="horizontal field of view, instead of focal_length")
    principal_point: tuple[Pixels, Pixels] | None = None

    @pydantic.model_validator(mode="after")
    def _one_focal(self):
        if (self.focal_length is None) == (self.fov is None):
            raise ValueError("give exactly one of focal_length (px) and fov (deg)")
        return self

    @property
    def focal_length_px(self) -> float:
        if self.focal_length is not None:
            return self.focal_length
        return (self.cols / 2.0) / np.tan(np.deg2rad(self.fov) / 2.0)

    def build(self) -> PerspectiveCamera:
        return PerspectiveCamera(rows=self.rows, cols=self.cols, principal_point_px=self.principal_point,
                                 focal_length_px=self.focal_length_px, camera_distance=self.distance)


class OrthographicCameraSpec(_Model):
    model: Literal["orthographic"]
    rows: int = pydantic.Field(gt=0)
    cols: int = pydantic.Field(gt=0)
    pixel_size: Annotated[Length, pydantic.Field(gt=0)]
    principal_point: tuple[Pixels, Pixels] | None = pydantic.Field(
        None, description="(col, row) where the rotation axis and the height 0 are seen; default: the centre")

    def build(self) -> OrthographicCamera:
        return OrthographicCamera(rows=self.rows, cols=self.cols, pixel_size=self.pixel_size,
                                  principal_point_px=self.principal_point)


class Stated(_Model):
    """What the rig's records say where they differ from the truth the simulator renders: a miscalibrated rig.

    The frames show the scene's ``light`` and ``camera``; the capture's attrs record these values instead, as a
    lab's notes would after the beam or the stage was moved (``calibrate_rig`` recovers the truth).
    """

    light_angle: Annotated[Angle, pydantic.Field(ge=0, le=180)] | None = pydantic.Field(
        None, description="θ_l the records give")
    principal_point: tuple[Pixels, Pixels] | None = pydantic.Field(
        None, description="(col, row) the records give for the principal point (col: the rotation axis's column)")


class Sensor(_Model):
    dark_level: float = pydantic.Field(64.0, ge=0, description="counts")
    saturation_level: float = pydantic.Field(4095.0, gt=0, description="counts")
    backlight: float = pydantic.Field(2000.0, ge=0, description="counts of the lit plane behind the object")
    frame_interval: Duration = pydantic.Field(0.0, ge=0, description="simulated readout time per frame")

    _levels = pydantic.model_validator(mode="after")(lambda self: saturation_above_dark(self))


class Scattering(_Model):
    """Volumetric scattering with an isotropic phase function, by Monte Carlo (§4.4.4)."""

    sigma_s: Annotated[InvLength, pydantic.Field(gt=0)]
    photons: int = pydantic.Field(200_000, gt=0, description="photons per frame")
    seed: int = pydantic.Field(0, ge=0)
    max_events: int = pydantic.Field(10_000, gt=0, description="scattering events before a photon is dropped")


class Noise(_Model):
    read_std: float = pydantic.Field(2.0, ge=0, description="Gaussian read noise, counts")
    gain: float | None = pydantic.Field(1.0, gt=0, description="counts per photo-electron (shot noise); "
                                        "null for none")
    seed: int = pydantic.Field(0, ge=0)


class Effects(_Model):
    scattering: Scattering | None = None
    noise: Noise | None = None

    @pydantic.model_validator(mode="before")
    @classmethod
    def _known(cls, value):
        if isinstance(value, dict):
            unknown = sorted(set(value) - set(cls.model_fields))
            if unknown:
                raise ValueError(f"unknown effect {', '.join(map(repr, unknown))}; the tomography simulator "
                                 f"computes: {', '.join(cls.model_fields)}")
        return value

    def names(self) -> tuple[str, ...]:
        return tuple(name for name in type(self).model_fields if getattr(self, name) is not None)


class Scene(_Model):
    """A tomography scene: object, light, camera, sensor and the effects to simulate."""

    scene: str
    description: str = ""
    length_unit: Literal[SCENE_LENGTH_UNITS] = pydantic.Field("mm", description=(
        "`mm`: every length carries a physical unit and is read in mm; `\"1\"`: lengths are dimensionless (a "
        "renderer's scene units), bare numbers, coefficients per that unit; the captures record it as their "
        "length_unit"))
    object: SceneObject
    light: Light
    camera: Annotated[PerspectiveCameraSpec | OrthographicCameraSpec, pydantic.Field(discriminator="model")]
    sensor: Sensor = Sensor()
    effects: Effects = Effects()
    stated: Stated | None = pydantic.Field(None, description="a miscalibrated rig: what its records say instead")

    @pydantic.model_validator(mode="wrap")
    @classmethod
    def _read_in_its_length_unit(cls, data: Any, handler):
        unit = data.get("length_unit", "mm") if isinstance(data, dict) else getattr(data, "length_unit", "mm")
        unit = scene_length_unit(unit)
        if unit not in SCENE_LENGTH_UNITS:  # its own error alone: the lengths cannot be read in an unknown unit
            raise pydantic.ValidationError.from_exception_data(cls.__name__, [{
                "type": PydanticCustomError("length_unit", "neither 'mm' nor '1' (dimensionless lengths)"),
                "loc": ("length_unit",), "input": unit}])
        with lengths_in(unit):  # read as text: YAML's unquoted 1 is a number
            return handler({**data, "length_unit": unit} if isinstance(data, dict) and "length_unit" in data else data)

    @pydantic.model_serializer(mode="wrap")
    def _written_in_its_length_unit(self, handler):
        with lengths_in(self.length_unit):
            return handler(self)

    @pydantic.model_validator(mode="after")
    def _scattering_needs_beam(self):
        if self.effects.scattering is not None and self.light.kind != "beam":
            raise ValueError("effects.scattering is simulated for light.kind 'beam' only (§4.4.4)")
        return self

    def geometry(self) -> RigGeometry:
        """The rig geometry this scene's camera and light define (lengths in mm, or dimensionless)."""
        return RigGeometry(self.camera.build(), light_angle_deg=self.light.angle, length_unit=self.length_unit,
                           light_distance=self.light.distance, light_kind=self.light.kind,
                           beam_height=self.light.height)

    def stated_geometry(self) -> RigGeometry:
        """The rig geometry the capture's attrs record: :meth:`geometry` unless ``stated`` overrides a value."""
        geometry = self.geometry()
        if self.stated is None:
            return geometry
        camera = geometry.camera
        if self.stated.principal_point is not None:
            camera = dataclasses.replace(camera, principal_point_px=tuple(self.stated.principal_point))
        angle = self.stated.light_angle if self.stated.light_angle is not None else geometry.light_angle_deg
        return dataclasses.replace(geometry, camera=camera, light_angle_deg=angle)

    def rows(self, first: int, count: int) -> Scene:
        """This scene seen by rows ``first`` … ``first + count − 1`` of its camera only (the principal point moved
        with them, so every pixel keeps its ray): a band of the sensor, rendered on its own."""
        cx, cy = self.camera.build().centre_px
        camera = self.camera.model_copy(update={"rows": int(count), "principal_point": (cx, cy - first)})
        update = {"camera": camera}
        if self.stated is not None and self.stated.principal_point is not None:  # the records' point moves alike
            col, row = self.stated.principal_point
            update["stated"] = self.stated.model_copy(update={"principal_point": (col, row - first)})
        return self.model_copy(update=update)

    def body(self) -> Solid:
        return self.object.solid()

    def inclusions(self) -> tuple[tuple[Solid, float], ...]:
        return self.object.inclusion_solids()


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and check a scene file; one SpecError lists every problem with its file:line and field."""
    return load_yaml_model(path, Scene, what="scene")


def scene_identity(path: str | os.PathLike) -> dict[str, str]:
    """What a store's attrs record of the scene file it was simulated from: ``scene``, the name the file
    declares (as captures record it), and ``scene_sha256``, the SHA-256 of the file's bytes. No path: a store
    stays the same wherever the scene file was, and the hash tells whether a scene file is that one."""
    with open(path, "rb") as file:
        digest = hashlib.sha256(file.read()).hexdigest()
    return {"scene": load_scene(path).scene, "scene_sha256": digest}
