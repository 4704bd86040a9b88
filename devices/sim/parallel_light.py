"""Closed-form frames of a cylinder under parallel light (the §4.4.2 comparison setting, θ_l = 0).

Object frame (DESIGN §8): origin on the rotation axis, z up; stage angle φ turns the object
counter-clockwise seen from +z. The orthographic camera looks along +y; image column c sees lab
x = (c − (n_cols − 1)/2)·pixel_size, row r sees z = ((n_rows − 1)/2 − r)·pixel_size. With θ_l = 0 the
beam runs along −y, so every pixel inside the silhouette sees one straight ray parallel to y, and
Lambert–Beer with disk chords is exact (no scattering, no noise unless asked).

The object is a cylinder of radius R filled with a medium of absorption ``medium_sigma`` and vertical
rods (inclusions) with extra absorption ``sigma`` (per length unit); the reference object is the same
without rods. Pixels outside the silhouette look straight into the source and saturate.
Vectorised over (angle, col); rows repeat because every solid is vertical.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selpath.geometry.rig import OrthographicCamera


@dataclass(frozen=True)
class Rod:
    """A vertical rod inclusion: centre (x, y) in the object frame, radius, extra absorption."""

    x: float
    y: float
    radius: float
    sigma: float


def chord(x_lab: np.ndarray, centre_x: np.ndarray, radius: float) -> np.ndarray:
    """Length of the line x = x_lab (parallel to y) inside a disk of ``radius`` centred at x = centre_x.

    As 2·√(r − d)·√(r + d) with the distance d clipped at r: never squares or multiplies huge lengths (a rod at
    x = 1e300, or of radius 1e300, overflowed r² − d²)."""
    d = np.minimum(np.abs(x_lab - centre_x), radius)
    return 2.0 * np.sqrt(radius - d) * np.sqrt(radius + d)


def column_x(n_cols: int, pixel_size: float) -> np.ndarray:
    """Lab x of each column's ray (the camera's pixel convention, :mod:`selpath.geometry.rig`)."""
    origins, _ = OrthographicCamera(rows=1, cols=n_cols, pixel_size=pixel_size).slice_rays(np.arange(n_cols))
    return origins[:, 0]


def line_integrals(angles_deg: np.ndarray, n_cols: int, pixel_size: float, rods: tuple[Rod, ...]) -> np.ndarray:
    """∫σ_rods dy for every (angle, col): the total absorption the reference normalisation should recover."""
    x = column_x(n_cols, pixel_size)[None, :]
    phi = np.deg2rad(np.asarray(angles_deg, dtype=float))[:, None]
    total = np.zeros((phi.shape[0], n_cols))
    for rod in rods:
        centre_x = rod.x * np.cos(phi) - rod.y * np.sin(phi)  # x of R(φ)·(x, y)
        total += rod.sigma * chord(x, centre_x, rod.radius)
    return total


def render(angles_deg: np.ndarray, *, n_rows: int, n_cols: int, pixel_size: float, radius: float,
           rods: tuple[Rod, ...], medium_sigma: float, intensity: float, skin_transmittance: float,
           dark_level: float, saturation_level: float, backlight: float, noise_std: float = 0.0,
           seed: int = 0, angle_index: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Target, reference and backlit frames (angle, row, col) and the dark frame (row, col), float32 counts.

    ``noise_std`` adds Gaussian read noise seeded per angle index, so any chunking gives the same frames.
    """
    x = column_x(n_cols, pixel_size)
    inside = np.abs(x) < radius
    medium = medium_sigma * chord(x, 0.0, radius)
    through = dark_level + intensity * skin_transmittance**2 * np.exp(-medium)
    reference_row = np.where(inside, through, saturation_level)
    rods_integral = line_integrals(angles_deg, n_cols, pixel_size, rods)
    target_rows = np.where(inside, dark_level + (through - dark_level) * np.exp(-rods_integral), saturation_level)
    backlit_row = np.where(inside, dark_level, dark_level + backlight)
    n_angles = len(angles_deg)
    frames = {
        "target": np.broadcast_to(target_rows[:, None, :], (n_angles, n_rows, n_cols)),
        "reference": np.broadcast_to(reference_row, (n_angles, n_rows, n_cols)),
        "backlit": np.broadcast_to(backlit_row, (n_angles, n_rows, n_cols)),
    }
    if noise_std > 0 and n_angles:
        index = np.arange(n_angles) if angle_index is None else np.asarray(angle_index)
        noisy = {}
        for name, stack in frames.items():
            salt = {"target": 1, "reference": 2, "backlit": 3}[name]
            noise = np.stack([np.random.default_rng([seed, salt, int(i)]).normal(0.0, noise_std, (n_rows, n_cols))
                              for i in index])
            noisy[name] = stack + noise
        frames = noisy
    out = {k: np.clip(v, 0.0, saturation_level).astype(np.float32) for k, v in frames.items()}
    out["dark"] = np.full((n_rows, n_cols), dark_level, dtype=np.float32)
    return out
