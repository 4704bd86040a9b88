"""Rig geometry of the tomography setup (DESIGN §8): camera rays, the light, lab ↔ object frames.

The lab holds the camera and the light; the object frame turns with the stage. Object frame: origin on
the rotation axis, z up; stage angle φ turns the object counter-clockwise seen from +z, so a point p of
the object is at ``R(φ)·p`` in the lab. The camera looks along +y from (0, −D_c, 0); image columns grow
with lab x and rows grow downward (decreasing z). The light comes from D_l·(sin θ_l, cos θ_l) and
travels toward the axis.

The same :class:`RigGeometry` is written into a capture's attrs by an acquisition and read back by the
processing stages, so the simulator and the light-path alignment can never disagree on a convention.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np


def rotation_z(angle_deg: float) -> np.ndarray:
    """3×3 rotation by ``angle_deg`` counter-clockwise about +z."""
    a = np.deg2rad(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def to_object(points_lab: np.ndarray, angle_deg: float) -> np.ndarray:
    """Lab points (or directions), shape (N, 3), in the object frame at stage angle φ: R(−φ)·q."""
    return np.asarray(points_lab, float) @ rotation_z(angle_deg)  # row vectors: q·R(φ) = (R(φ)ᵀ q)ᵀ


def to_lab(points_object: np.ndarray, angle_deg: float) -> np.ndarray:
    """Object points (or directions), shape (N, 3), in the lab at stage angle φ: R(φ)·p."""
    return np.asarray(points_object, float) @ rotation_z(angle_deg).T


@dataclass(frozen=True)
class RigGeometry:
    """Camera and light of a tomography rig; lengths in ``length_unit``.

    ``light_kind`` is ``beam`` (a narrow collimated beam at height ``beam_height``) or ``sheet`` (a
    vertical light sheet: every slice lit at its own height).
    """

    camera_model: Literal["perspective", "orthographic"]
    rows: int
    cols: int
    light_angle_deg: float
    length_unit: str = "mm"
    focal_length_px: float | None = None
    principal_point_px: tuple[float, float] | None = None
    camera_distance: float | None = None
    pixel_size: float | None = None
    light_distance: float | None = None
    light_kind: Literal["beam", "sheet"] = "beam"
    beam_height: float = 0.0

    @property
    def centre_px(self) -> tuple[float, float]:
        if self.principal_point_px is not None:
            return (float(self.principal_point_px[0]), float(self.principal_point_px[1]))
        return ((self.cols - 1) / 2.0, (self.rows - 1) / 2.0)

    def attrs(self) -> dict[str, Any]:
        """The capture attrs of DESIGN §2 (``tomography_capture`` kind); None values are left out."""
        out = {k: v for k, v in asdict(self).items() if v is not None and k not in ("rows", "cols")}
        if self.camera_model == "perspective":
            out["principal_point_px"] = list(self.centre_px)
        return out

    @classmethod
    def from_attrs(cls, attrs: Mapping[str, Any], rows: int, cols: int) -> RigGeometry:
        names = set(cls.__dataclass_fields__) - {"rows", "cols"}
        values = {k: attrs[k] for k in names if k in attrs}
        if values.get("principal_point_px") is not None:
            values["principal_point_px"] = tuple(values["principal_point_px"])
        return cls(rows=rows, cols=cols, **values)

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions in the lab of every pixel's ray, shape (rows·cols, 3), row-major."""
        r, c = np.meshgrid(np.arange(self.rows, dtype=float), np.arange(self.cols, dtype=float), indexing="ij")
        r, c = r.ravel(), c.ravel()
        cx, cy = self.centre_px
        if self.camera_model == "perspective":
            f = float(self.focal_length_px)
            directions = np.stack([(c - cx) / f, np.ones_like(c), (cy - r) / f], axis=1)
            directions /= np.linalg.norm(directions, axis=1, keepdims=True)
            origins = np.tile([0.0, -float(self.camera_distance), 0.0], (len(r), 1))
        else:
            s = float(self.pixel_size)
            origins = np.stack([(c - cx) * s, np.zeros_like(c), (cy - r) * s], axis=1)
            directions = np.tile([0.0, 1.0, 0.0], (len(r), 1))
        return origins, directions

    def project(self, points_lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel (row, col) where the camera sees lab points (N, 3)."""
        q = np.asarray(points_lab, float)
        cx, cy = self.centre_px
        if self.camera_model == "perspective":
            f, depth = float(self.focal_length_px), q[:, 1] + float(self.camera_distance)
            return cy - f * q[:, 2] / depth, cx + f * q[:, 0] / depth
        s = float(self.pixel_size)
        return cy - q[:, 2] / s, cx + q[:, 0] / s

    def pixel_footprint(self, points_lab: np.ndarray, normals_lab: np.ndarray) -> np.ndarray:
        """Area of the surface patch one pixel sees at each point (with its outward normal)."""
        q, n = np.asarray(points_lab, float), np.asarray(normals_lab, float)
        if self.camera_model == "perspective":
            view = q - np.array([0.0, -float(self.camera_distance), 0.0])
            distance = np.linalg.norm(view, axis=1)
            cos_axis = view[:, 1] / distance
            cos_view = np.abs(np.einsum("ij,ij->i", n, view)) / distance
            solid_angle = cos_axis**3 / float(self.focal_length_px) ** 2
            return solid_angle * distance**2 / np.maximum(cos_view, 1e-12)
        return float(self.pixel_size) ** 2 / np.maximum(np.abs(n[:, 1]), 1e-12)

    def beam(self) -> tuple[np.ndarray, np.ndarray]:
        """Origin and unit direction of the light's central ray in the lab (toward the axis)."""
        a = np.deg2rad(self.light_angle_deg)
        towards = np.array([np.sin(a), np.cos(a), 0.0])
        distance = self.light_distance if self.light_distance is not None else 1.0
        return towards * distance + np.array([0.0, 0.0, self.beam_height]), -towards


GEOMETRY_ATTRS = tuple(set(RigGeometry.__dataclass_fields__) - {"rows", "cols"})


def geometry_attrs(attrs) -> dict:
    """The rig-geometry attrs of a cube (carried from the capture through every tomography stage)."""
    return {k: v for k, v in attrs.items() if k in GEOMETRY_ATTRS or k == "saturation_level"}
