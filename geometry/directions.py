"""Unit directions drawn at random, as light leaves a diffuse surface or scatters isotropically: the Monte Carlo
simulator (:mod:`selpath.devices.sim.tomography`) and the scattering model's walks
(:mod:`selpath.stages.tomography._walks`) draw them alike."""

from __future__ import annotations

import numpy as np


def cosine_hemisphere(normal: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Lambertian directions about the unit ``normal`` (N, 3)."""
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], axis=1)
    helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return local @ np.stack([e1, e2, normal])


def isotropic(n: int, rng: np.random.Generator) -> np.ndarray:
    """Directions uniform on the unit sphere (N, 3)."""
    z = 2 * rng.random(n) - 1
    phi = 2 * np.pi * rng.random(n)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
