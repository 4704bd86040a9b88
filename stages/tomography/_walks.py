"""Photon random walks in a hull's slice (the scattering stages' Monte Carlo, :mod:`stages.tomography.scattering`).

The object is the slice's contour extruded in z (a prism), filled with an isotropic scatterer of coefficient σ_s
and no absorption: the reference object of the capture. A walk is launched through the skin where the light's ray
enters the contour (Lambertian about the inward normal, as :mod:`devices.sim.tomography` launches its photons) and
scattered isotropically until it leaves.

A walk's probability density at σ_s, given its directions, is σ_s^k · exp(−σ_s · L) for its k scatterings and the
length L it travelled (k free paths, and a last one cut off by the exit). So walks traced at one σ_s stand for those
of any other by the ratio of the two (:func:`walk_weights`): the estimate of σ_s compares many candidates on one
set of walks, smoothly, instead of tracing each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.measure import approximate_polygon

from devices.geometry import RigGeometry, to_object_xy
from devices.sim.shapes import Prism, convex_polygon
from devices.sim.tomography import cosine_hemisphere, isotropic

#: a contour is simplified for walking to within this share of a camera pixel at the axis [1]: far below the
#: hull's own error (about a pixel), and a 360-vertex contour clips ~3× faster with the ~100 vertices left
WALK_TOLERANCE = 0.05


@dataclass(frozen=True)
class Walks:
    """Photon walks that left the object, in the object frame: where each left and the outward normal there (N, 3),
    its scatterings (N,) and the length it travelled (N,), which give its probability at another σ_s
    (:func:`walk_weights`); and its vertices (N, V, 3; NaN after the exit, the last finite one) where recorded."""

    exit_point: np.ndarray
    exit_normal: np.ndarray
    events: np.ndarray
    length: np.ndarray
    vertices: np.ndarray | None = None


def random_walks(body: Prism, entry: np.ndarray, normal: np.ndarray, sigma_s: float, n: int,
                 rng: np.random.Generator, *, max_events: int = 200, record: bool = True) -> Walks:
    """``n`` photons launched through the skin at ``entry`` (Lambertian about the inward normal, −``normal``) and
    scattered isotropically with free paths of mean 1/σ_s until they leave ``body``; photons still inside after
    ``max_events`` scatterings are dropped. No absorption: the walks of the reference object. ``record``: keep
    every walk's vertices (for path integrals), else only its exit, scatterings and length."""
    exit_point, exit_normal = np.zeros((n, 3)), np.zeros((n, 3))
    events, length = np.zeros(n, np.int64), np.zeros(n)
    left = np.zeros(n, bool)
    alive = np.arange(n)
    pos = np.tile(np.asarray(entry, float) - 1e-9 * np.asarray(normal, float), (n, 1))
    steps = [(alive, pos)]  # who moved, and where to, at each event: only the walks still inside take memory
    direction = cosine_hemisphere(-np.asarray(normal, float), n, rng)
    for scatterings in range(max_events + 1):
        if not len(alive):
            break
        iv = body.interval(pos, direction)
        t_exit = np.maximum(iv.t_out, 0.0)
        free = rng.exponential(1.0 / sigma_s, len(alive))
        leaving = free >= t_exit
        step = np.where(leaving, t_exit, free)
        pos = pos + step[:, None] * direction
        length[alive] += step
        if record:
            steps.append((alive, pos))
        gone = alive[leaving]
        exit_point[gone], exit_normal[gone] = pos[leaving], iv.normal_out[leaving]
        events[gone], left[gone] = scatterings, True
        stay = ~leaving
        alive, pos = alive[stay], pos[stay]
        direction = isotropic(len(alive), rng)
    vertices = None
    if record:
        vertices = np.full((n, len(steps), 3), np.nan)
        for k, (who, where) in enumerate(steps):
            vertices[who, k] = where
        vertices = vertices[left]
    return Walks(exit_point[left], exit_normal[left], events[left], length[left], vertices)


def walk_weights(walks: Walks, sigma_s: float, traced_at: float) -> np.ndarray:
    """Each walk's weight at ``sigma_s`` when it was traced at ``traced_at``: the ratio of its densities,
    (σ_s / σ_0)^k · exp(−(σ_s − σ_0) L), so that a weighted count of walks estimates what walks at σ_s would
    count (unbiased; its variance grows as σ_s moves away from σ_0)."""
    ratio = float(sigma_s) / float(traced_at)
    return np.exp(walks.events * np.log(ratio) - (float(sigma_s) - float(traced_at)) * walks.length)


def walk_body(polygon: np.ndarray, geometry: RigGeometry) -> Prism:
    """The prism the walks of a slice stay in: its hull contour (vertices (K, 2), object frame) simplified to within
    :data:`WALK_TOLERANCE` of a camera pixel (Douglas–Peucker keeps a subset of the vertices: still convex, and
    inside the contour)."""
    polygon = np.asarray(polygon, float)
    closed = np.vstack([polygon, polygon[:1]])
    simple = approximate_polygon(closed, WALK_TOLERANCE * geometry.camera.axis_pixel_size)[:-1]
    return Prism(convex_polygon(simple if len(simple) >= 3 else polygon))


def beam_entry(body: Prism, geometry: RigGeometry, angle_deg: float, height: float
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the light's ray (moved to ``height``) enters ``body`` at stage angle ``angle_deg``, and the outward
    normal there, in the object frame (3-D); None where the ray misses it."""
    origin, direction = geometry.beam()
    phi = np.deg2rad(angle_deg)
    o, d = to_object_xy(origin[:2], phi), to_object_xy(direction[:2], phi)
    iv = body.shape.interval(o[None], d[None])
    if not iv.hit[0]:
        return None
    return np.array([*(o + iv.t_in[0] * d), height]), np.array([*iv.normal_in[0], 0.0])
