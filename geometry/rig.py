"""Rig geometry of the tomography setup (DESIGN §8): the camera, the light, lab ↔ object frames.

The lab holds the camera and the light; the object frame turns with the stage. Object frame: origin on
the rotation axis, z up; stage angle φ turns the object counter-clockwise seen from +z, so a point p of
the object is at ``R(φ)·p`` in the lab. The camera looks along +y from (0, −D_c, 0); image columns grow
with lab x and rows grow downward (decreasing z). The light comes from D_l·(sin θ_l, cos θ_l) and
travels toward the axis.

**Pixel convention** (here and nowhere else): pixel (r, c) is centred on the sub-pixel position (r, c) and
covers [r − ½, r + ½] × [c − ½, c + ½]; the principal point defaults to the sensor's centre
((cols − 1)/2, (rows − 1)/2).

One camera class per model (:class:`PerspectiveCamera`, :class:`OrthographicCamera`) owns projection,
back-projection, pixel rays and footprints; :class:`RigGeometry` holds the camera and the light. It is
written into a capture's attrs by an acquisition and built back from them (:meth:`RigGeometry.from_attrs`,
which checks them against the one declaration of the required attrs, :data:`RIG_ATTRS` and :data:`CAMERA_ATTRS`
below) by every
processing stage, the simulator and the phantom, so none of them can disagree on a convention.

>>> camera = OrthographicCamera(rows=3, cols=5, pixel_size=0.5)
>>> camera.project(np.array([[0.5, 7.0, -0.5]]))  # lab x = 0.5, z = -0.5: right of and below the centre
(array([2.]), array([3.]))
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any, ClassVar, Literal

import numpy as np

from selpath.pipeline.errors import Problem, StageError

#: Rig-geometry attrs of a tomography capture (DESIGN §2, §8). This and :data:`CAMERA_ATTRS` are the one
#: declaration of them: the tomography kinds require them (``selpath.stages.tomography``), :class:`RigGeometry`
#: builds the cameras from them and the hardware rig's config reads them.
RIG_ATTRS = {
    "camera_model": "'perspective' or 'orthographic'",
    "light_angle_deg": "light angle θ_l between the beam and the camera axis, degree",
    "length_unit": "unit of every length attr and of sinogram x: 'm', 'cm', 'mm', 'um', 'px' or '1' (dimensionless)",
}
#: Further attrs each camera model needs. ``principal_point_px`` is in every perspective store; a camera built
#: from a config (``sensor_defaults``) may leave it out: it defaults to the sensor's centre.
CAMERA_ATTRS: dict[str, tuple[str, ...]] = {
    # light_distance (D_l) is not required: a beam is a line, and where its source sits on it changes no ray
    "perspective": ("focal_length_px", "principal_point_px", "camera_distance"),
    "orthographic": ("pixel_size",),
}
SENSOR_DEFAULTS = frozenset({"principal_point_px"})


def camera_attr_problems(attrs: Mapping, *, sensor_defaults: bool = False) -> list[str]:
    """What the attrs of a camera model (``attrs['camera_model']``; none given: nothing to check) lack."""
    model = attrs.get("camera_model")
    if model is None:
        return []
    if model not in CAMERA_ATTRS:
        return [f"attr camera_model is {model!r}; expected {' or '.join(map(repr, CAMERA_ATTRS))}"]
    skip = SENSOR_DEFAULTS if sensor_defaults else frozenset()
    return [f"attr {a!r} is required for a {model} camera" for a in CAMERA_ATTRS[model]
            if a not in attrs and a not in skip]


def rotation_z(angle_deg: float) -> np.ndarray:
    """3×3 rotation by ``angle_deg`` counter-clockwise about +z."""
    a = np.deg2rad(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def to_object(points_lab: np.ndarray, angle_deg: float) -> np.ndarray:
    """Lab points (or directions), shape (N, 3), in the object frame at stage angle φ: R(−φ)·q."""
    return np.asarray(points_lab, float) @ rotation_z(angle_deg)  # row vectors: q·R(φ) = (R(φ)ᵀ q)ᵀ


def to_object_xy(v: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Lab (x, y) points or directions (N, 2) in the object frame, each at its own stage angle φ (N,) [rad]:
    R(−φ)·v; ``to_object_xy(v, −φ)`` turns object vectors into the lab."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], axis=-1)


def to_lab(points_object: np.ndarray, angle_deg: float) -> np.ndarray:
    """Object points (or directions), shape (N, 3), in the lab at stage angle φ: R(φ)·p."""
    return np.asarray(points_object, float) @ rotation_z(angle_deg).T


@dataclass(frozen=True, kw_only=True)
class Camera(ABC):
    """A camera of ``rows × cols`` pixels looking along +y at the rotation axis; lengths in the rig's unit.

    ``rows``/``cols`` may be None where only the optics matter (coverage closed forms, hull resolution).
    Subclasses give the model: :meth:`_rays`, :meth:`project`, :meth:`facing`, :meth:`pixel_footprint`,
    :attr:`axis_pixel_size` and :meth:`subtended_angle_deg`; everything else is shared.
    """

    model: ClassVar[str]
    rows: int | None = None
    cols: int | None = None
    principal_point_px: tuple[float, float] | None = None

    @property
    def centre_px(self) -> tuple[float, float]:
        """(cx, cy): the principal point in (col, row) pixels; by default the sensor's centre."""
        if self.principal_point_px is not None:
            return (float(self.principal_point_px[0]), float(self.principal_point_px[1]))
        if self.rows is None or self.cols is None:
            raise ValueError(f"a {self.model} camera of unknown sensor size has no default principal point")
        return ((self.cols - 1) / 2.0, (self.rows - 1) / 2.0)

    # -- the model -------------------------------------------------------------------------------------
    @abstractmethod
    def _rays(self, row: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Origins and directions per unit depth (y component 1) in the lab of the rays through sub-pixel
        (row, col), (N, 3)."""

    @abstractmethod
    def project(self, points_lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel (row, col) where the camera sees lab points (N, 3)."""

    @abstractmethod
    def facing(self, points_lab: np.ndarray, normals_lab: np.ndarray) -> np.ndarray:
        """Whether surface points (N, 3) with outward normals face the camera."""

    @abstractmethod
    def pixel_footprint(self, points_lab: np.ndarray, normals_lab: np.ndarray) -> np.ndarray:
        """Area of the surface patch one pixel sees at each point (with its outward normal)."""

    @property
    @abstractmethod
    def axis_pixel_size(self) -> float:
        """Object-space size of one pixel at the rotation axis [length unit]."""

    @abstractmethod
    def subtended_angle_deg(self, radius):
        """Angle a cylinder of ``radius`` on the axis subtends at the camera, 2·asin(R / D_c) [degree] (the
        field of view it fills); None for an orthographic camera (parallel rays)."""

    # -- shared ----------------------------------------------------------------------------------------
    def back_project(self, row, col) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions in the lab of the rays through sub-pixel (row, col), (N, 3)."""
        origins, directions = self._rays(np.asarray(row, float).ravel(), np.asarray(col, float).ravel())
        return origins, directions / np.linalg.norm(directions, axis=1, keepdims=True)

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions in the lab of every pixel's ray, shape (rows·cols, 3), row-major."""
        r, c = np.meshgrid(np.arange(self.rows, dtype=float), np.arange(self.cols, dtype=float), indexing="ij")
        return self.back_project(r, c)

    def slice_rays(self, col) -> tuple[np.ndarray, np.ndarray]:
        """The rays of sub-pixel columns projected on the slice plane: origins and directions in lab (x, y),
        (N, 2), each direction per unit depth (its y component is 1; normalise where a unit vector is needed).

        A camera row is treated as a slice through the x–y projection of its rays (exact for vertical prisms
        and for an orthographic camera)."""
        col = np.asarray(col, float).ravel()
        origins, directions = self._rays(np.full_like(col, self.centre_px[1]), col)
        return origins[:, :2], directions[:, :2]

    def axis_height(self, row) -> np.ndarray:
        """Height z [length unit] at which sub-pixel ``row`` sees the rotation axis: where the ray through the row
        and the principal column crosses the plane y = 0 (the object's slice height that row is read as)."""
        row = np.asarray(row, float).ravel()
        origins, directions = self._rays(row, np.full_like(row, self.centre_px[0]))
        return origins[:, 2] - origins[:, 1] * directions[:, 2] / directions[:, 1]

    def pixel_index(self, row, col) -> tuple[np.ndarray, np.ndarray]:
        """Row-major index of the pixel holding each sub-pixel (row, col), and whether it is on the sensor."""
        r, c = np.rint(row).astype(np.int64), np.rint(col).astype(np.int64)
        return r * self.cols + c, (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)

    @staticmethod
    def outer_edges(first, last) -> tuple[float, float]:
        """Sub-pixel positions of the outer edges of the run of pixels ``first`` … ``last`` (one row or column)."""
        return first - 0.5, last + 0.5

    def rows_at(self, row: float) -> np.ndarray:
        """The sensor rows whose pixels hold sub-pixel ``row`` (two where it lies on their common edge)."""
        rows = np.arange(int(np.floor(row)), int(np.ceil(row)) + 1)
        return rows[(np.abs(rows - row) <= 0.5) & (rows >= 0) & (rows < self.rows)]

    @property
    def view_half_width(self) -> float:
        """Half the width the sensor sees at the rotation axis [length unit]."""
        return (self.cols / 2) * self.axis_pixel_size

    def attrs(self) -> dict[str, Any]:
        """The camera's capture attrs (DESIGN §2); None values are left out."""
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("rows", "cols")}
        return {"camera_model": self.model} | {k: v for k, v in values.items() if v is not None}


@dataclass(frozen=True, kw_only=True)
class PerspectiveCamera(Camera):
    """A pinhole camera at distance ``camera_distance`` from the axis, focal length ``focal_length_px``."""

    model: ClassVar[str] = "perspective"
    focal_length_px: float
    camera_distance: float

    def _rays(self, row, col):
        cx, cy = self.centre_px
        f = float(self.focal_length_px)
        directions = np.stack([(col - cx) / f, np.ones_like(col), (cy - row) / f], axis=1)
        return np.tile([0.0, -float(self.camera_distance), 0.0], (len(row), 1)), directions

    def project(self, points_lab):
        q = np.asarray(points_lab, float)
        cx, cy = self.centre_px
        f, depth = float(self.focal_length_px), q[:, 1] + float(self.camera_distance)
        return cy - f * q[:, 2] / depth, cx + f * q[:, 0] / depth

    def facing(self, points_lab, normals_lab):
        eye = np.array([0.0, -float(self.camera_distance), 0.0])
        return np.einsum("ij,ij->i", np.asarray(normals_lab, float), eye - np.asarray(points_lab, float)) > 0

    def pixel_footprint(self, points_lab, normals_lab):
        q, n = np.asarray(points_lab, float), np.asarray(normals_lab, float)
        view = q - np.array([0.0, -float(self.camera_distance), 0.0])
        distance = np.linalg.norm(view, axis=1)
        cos_axis = view[:, 1] / distance
        cos_view = np.abs(np.einsum("ij,ij->i", n, view)) / distance
        solid_angle = cos_axis**3 / float(self.focal_length_px) ** 2
        return solid_angle * distance**2 / np.maximum(cos_view, 1e-12)

    @property
    def axis_pixel_size(self) -> float:
        return float(self.camera_distance) / float(self.focal_length_px)

    def subtended_angle_deg(self, radius):
        return np.rad2deg(2 * np.arcsin(np.clip(radius / float(self.camera_distance), 0, 1)))

    def attrs(self) -> dict[str, Any]:
        return super().attrs() | {"principal_point_px": list(self.centre_px)}


@dataclass(frozen=True, kw_only=True)
class OrthographicCamera(Camera):
    """A telecentric camera: parallel rays along +y, ``pixel_size`` in the object's length unit."""

    model: ClassVar[str] = "orthographic"
    pixel_size: float

    def _rays(self, row, col):
        cx, cy = self.centre_px
        s = float(self.pixel_size)
        origins = np.stack([(col - cx) * s, np.zeros_like(col), (cy - row) * s], axis=1)
        return origins, np.tile([0.0, 1.0, 0.0], (len(row), 1))

    def project(self, points_lab):
        q = np.asarray(points_lab, float)
        cx, cy = self.centre_px
        s = float(self.pixel_size)
        return cy - q[:, 2] / s, cx + q[:, 0] / s

    def facing(self, points_lab, normals_lab):
        return np.asarray(normals_lab, float)[:, 1] < 0

    def pixel_footprint(self, points_lab, normals_lab):
        n = np.asarray(normals_lab, float)
        return float(self.pixel_size) ** 2 / np.maximum(np.abs(n[:, 1]), 1e-12)

    @property
    def axis_pixel_size(self) -> float:
        return float(self.pixel_size)

    def subtended_angle_deg(self, radius):
        return None


#: the camera class of each model named in a store's ``camera_model`` attr
#: (the keys of :data:`CAMERA_ATTRS`; a test keeps the two in step)
CAMERAS: dict[str, type[Camera]] = {cls.model: cls for cls in (PerspectiveCamera, OrthographicCamera)}
#: a ``camera_model`` value, for typed configs
CameraModel = Literal[tuple(CAMERA_ATTRS)]  # Literal[("a", "b")] is Literal["a", "b"]


@dataclass(frozen=True)
class RigGeometry:
    """Camera and light of a tomography rig; lengths in ``length_unit``.

    ``light_kind`` is ``beam`` (a narrow collimated beam at height ``beam_height``) or ``sheet`` (a
    vertical light sheet: every slice lit at its own height).
    """

    camera: Camera
    light_angle_deg: float
    length_unit: str = "mm"
    light_distance: float | None = None
    light_kind: Literal["beam", "sheet"] = "beam"
    beam_height: float = 0.0

    def attrs(self) -> dict[str, Any]:
        """The capture attrs of DESIGN §2 (``tomography_capture`` kind); None values are left out."""
        light = {k: v for k, v in asdict(self).items() if k != "camera" and v is not None}
        return self.camera.attrs() | light

    @classmethod
    def from_attrs(cls, attrs: Mapping[str, Any], rows: int | None = None, cols: int | None = None, *,
                   where: str = "") -> RigGeometry:
        """The geometry a cube's attrs describe, for a sensor of ``rows × cols`` (None: unknown).

        Raises a :class:`~selpath.pipeline.errors.StageError` naming every missing or wrong attr (``where``: whose).
        """
        problems = [f"attr {a!r} is missing; the rig geometry needs it ({what})" for a, what in RIG_ATTRS.items()
                    if a not in attrs] + camera_attr_problems(attrs, sensor_defaults=True)
        if attrs.get("light_kind", "beam") not in ("beam", "sheet"):  # anything else was taken for a beam
            problems.append(f"attr light_kind is {attrs['light_kind']!r}; expected 'beam' or 'sheet'")
        if problems:
            fix = "compute it from a capture whose attrs carry the rig geometry (docs/format.md)"
            raise StageError([Problem(p, where=where, fix=fix) for p in problems])
        camera = CAMERAS[attrs["camera_model"]]
        names = {f.name for f in fields(camera)} - {"rows", "cols"}
        values = {k: attrs[k] for k in names if attrs.get(k) is not None}
        if "principal_point_px" in values:
            values["principal_point_px"] = tuple(values["principal_point_px"])
        light = {f.name: attrs[f.name] for f in fields(cls) if f.name != "camera" and f.name in attrs}
        return cls(camera(rows=rows, cols=cols, **values), **light)

    def beam(self) -> tuple[np.ndarray, np.ndarray]:
        """Origin and unit direction of the light's central ray in the lab (toward the axis)."""
        a = np.deg2rad(self.light_angle_deg)
        towards = np.array([np.sin(a), np.cos(a), 0.0])
        distance = self.light_distance if self.light_distance is not None else 1.0
        return towards * distance + np.array([0.0, 0.0, self.beam_height]), -towards

    def lit_rows(self) -> np.ndarray:
        """Camera rows whose slice the light reaches: all for a sheet, the beam's height for a beam."""
        if self.light_kind == "sheet":
            return np.arange(self.camera.rows)
        row, _ = self.camera.project(np.array([[0.0, 0.0, self.beam_height]]))
        return self.camera.rows_at(float(row[0]))


#: every attr a rig geometry writes (and the tomography stages carry from cube to cube)
GEOMETRY_ATTRS = tuple(dict.fromkeys(
    [*RIG_ATTRS, *(f.name for cls in CAMERAS.values() for f in fields(cls) if f.name not in ("rows", "cols")),
     *(f.name for f in fields(RigGeometry) if f.name != "camera")]))


def saturation_counts(attrs) -> float | None:
    """The raw count at and above which the sensor clips, from a store's attrs: ``saturation_counts`` (both
    instruments), or ``saturation_level``, its name in tomography stores of format ≤ 5; None if neither."""
    for name in ("saturation_counts", "saturation_level"):
        if name in attrs:
            return float(attrs[name])
    return None


def geometry_attrs(attrs) -> dict:
    """The rig-geometry attrs of a cube (carried from the capture through every tomography stage), and the
    sensor's clip level as ``saturation_counts``."""
    out = {k: v for k, v in attrs.items() if k in GEOMETRY_ATTRS}
    level = saturation_counts(attrs)
    return out | ({"saturation_counts": level} if level is not None else {})
