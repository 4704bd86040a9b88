"""Photon random walks in a hull's slice: the Monte Carlo of :mod:`selpath.stages.tomography.scattering` and
:mod:`selpath.stages.tomography.scattering_estimate`.

The object is the slice's contour extruded in z (a prism), filled with an isotropic scatterer of coefficient σ_s
and no absorption: the reference object of the capture. A walk is launched through the skin where the light's ray
enters the contour (Lambertian about the inward normal, as :mod:`selpath.devices.sim.tomography` launches its photons)
and
scattered isotropically until it leaves.

A walk's probability density at σ_s, given its directions, is σ_s^k · exp(−σ_s · L) for its k scatterings and the
length L it travelled (k free paths, and a last one cut off by the exit). So walks traced at one σ_s stand for those
of any other by the ratio of the two (:func:`walk_weights`): the estimate of σ_s compares many candidates on one
set of walks, smoothly, instead of tracing each.

Where a walk leaves is also known without waiting for it to leave: from each of its vertices, the chance that its next
flight leaves through a given patch of the surface is closed form (:func:`exit_weights`, next-event estimation). So
every walk tells every pixel how much of its light would reach it, and by which path, where its own exit reaches one
pixel at most.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selpath.geometry.directions import cosine_hemisphere, isotropic
from selpath.geometry.rig import RigGeometry, to_object, to_object_xy
from selpath.geometry.shapes import Prism, convex_polygon

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


#: vertices × patches whose connections :func:`exit_weights` computes at once (its temporaries: ~100 bytes each)
CONNECT_BLOCK = 1 << 18


def exit_weights(walks: Walks, normal: np.ndarray, points: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 sigma_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Next-event estimates of where ``walks`` (traced with their vertices) leave through surface patches: points
    (T, 3) with outward ``normals`` (T, 3) and ``areas`` (T,), in the walks' frame. For each vertex a walk flew from
    (its launch through the skin at the outward ``normal``, and its scatterings) and each patch, the chance that the
    next flight from it leaves through the patch without scattering again: the flight direction's density toward
    the patch (Lambertian about −``normal``, cos/π, at the launch; isotropic, 1/4π, after a scattering) × the patch's
    solid angle × exp(−σ_s d), d the distance; the solid angle is that of a disc of the patch's area seen on its
    axis, 2π(1 − d/√(d² + area/π)), times the cosine at the exit (0 where the flight would enter the patch from
    outside): area·cos/d² far from the patch, and bounded near it, where a point's 1/d² would let one vertex close
    to the surface outweigh thousands (its variance is unbounded). The body must be convex (the flight stays
    inside). Summed over a walk's vertices this is the walk's expected share of light leaving through the patch;
    divided by the walks traced, an estimate of the light per launched photon that reaches each patch, biased only
    by the vertices within about a patch's size of it (tested against the walks' own exits with patches of a 25th
    of the mean free path).

    Returns the walk and the vertex index of each of those vertices (M,), and their weights (M, T)."""
    vertices = walks.vertices
    finite = np.isfinite(vertices[..., 0])
    last = finite.sum(axis=1) - 1  # each walk's exit: not a vertex it flies from
    walk, vertex = np.nonzero(finite & (np.arange(vertices.shape[1])[None, :] < last[:, None]))
    origin = vertices[walk, vertex]
    points, normals = np.asarray(points, float), np.asarray(normals, float)
    inward = -np.asarray(normal, float)
    radius2 = np.asarray(areas, float) / np.pi  # each patch as a disc of its area
    launch = vertex == 0
    weights = np.empty((len(walk), len(points)))
    step = max(CONNECT_BLOCK // max(len(points), 1), 1)
    for k in range(0, len(walk), step):
        toward = points[None, :, :] - origin[k:k + step, None, :]  # (m, T, 3)
        square = np.einsum("mtj,mtj->mt", toward, toward)
        distance = np.sqrt(square)
        cos_exit = np.einsum("mtj,tj->mt", toward, normals) / np.maximum(distance, 1e-300)
        solid = 2 * np.pi * (1 - distance / np.sqrt(square + radius2))  # the patch's disc, seen on its axis
        block = np.maximum(cos_exit, 0.0) * solid * np.exp(-sigma_s * distance) * (0.25 / np.pi)
        first = np.flatnonzero(launch[k:k + step])  # launches: Lambertian (cos/π), not isotropic (1/4π)
        if len(first):
            cos_in = (toward[first] @ inward) / np.maximum(distance[first], 1e-300)
            block[first] *= 4.0 * np.maximum(cos_in, 0.0)
        weights[k:k + step] = block
    return walk, vertex, weights


def surface_seen(body: Prism, origins: np.ndarray, directions: np.ndarray, angle_deg: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where camera rays (lab ``origins``, unit ``directions``, (N, 3)) first meet ``body`` at stage angle
    ``angle_deg``: whether they do (N,), the point and the outward normal there (object frame, (N, 3); the ray's
    origin where it misses), and the directions in the object frame."""
    o, d = to_object(origins, angle_deg), to_object(directions, angle_deg)
    seen = body.interval(o, d)
    return seen.hit, o + np.where(seen.hit, seen.t_in, 0.0)[:, None] * d, seen.normal_in, d


def walk_body(polygon: np.ndarray, geometry: RigGeometry) -> Prism:
    """The prism the walks of a slice stay in: its hull contour (vertices (K, 2), object frame) simplified to within
    :data:`WALK_TOLERANCE` of a camera pixel (Douglas–Peucker keeps a subset of the vertices: still convex, and
    inside the contour)."""
    from skimage.measure import approximate_polygon  # scikit-image when walks are traced, not on reading

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
