"""Frames of a tomography scene: straight paths (shortest-path model, §4.2.3) or Monte Carlo (§4.4.4).

Light model, in the object frame at stage angle φ (conventions in :mod:`selpath.geometry.rig`):

* The light's central ray enters the object at ``p_l`` (first crossing of the object's surface), where
  the thin skin diffuses it (Lambertian, transmittance T). A **beam** enters at one point; a **sheet**
  lights each slice at its own height (the beam scanned in z): the light of height z enters where the beam's
  ray moved to z meets the object (a vertical line on a prism, a curve on an ellipsoid).
* Without scattering, light runs straight from ``p_l`` to every surface point ``p_c``, losing
  ``exp(-∫σ)`` on the way (medium plus inclusions), and leaves through the skin again (Lambertian).
  A camera pixel seeing ``p_c`` records the exit radiance::

      E = I₀ T² cos ω_i cos ω_o (d/L)^k exp(-∫σ),   k = 2 (beam), 1 (sheet, per slice)

  with L = |p_c − p_l|, ω_i, ω_o the angles to the inward normal at p_l and the outward normal at p_c,
  and d the object's diameter (so I₀ is about the count of the exit point opposite the entry).
  The reference object (no inclusions) shares every factor but the inclusions' absorption, so
  ``log E_reference − log E_target`` is exactly the inclusions' line integral: the truth the
  processing stages must recover.
* With ``effects.scattering`` (σ_s > 0, isotropic phase function), photons are traced in 3-D by
  Monte Carlo from the same entry point and the same Lambertian launch; absorption acts on photon
  weights, so the target and reference frames of an angle use the *same* photon paths (common random
  numbers: their ratio is far less noisy than either frame). As σ_s → 0 the estimate converges to the
  straight-path E above (for a beam), which the tests check against its stated standard error.

Only the effects a scene names run: a scene without ``scattering`` never enters :func:`monte_carlo`.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from selpath.devices.sim.scene import Scene
from selpath.geometry.directions import cosine_hemisphere, isotropic
from selpath.geometry.rig import Camera, RigGeometry, to_lab, to_object
from selpath.geometry.shapes import Solid, segment_length_inside

SAMPLES = ("target", "reference")


@dataclass(frozen=True)
class ExitPoints:
    """What each pixel sees at one stage angle: whether it hits the object, where, and the normal there."""

    hit: np.ndarray  # (N,) bool
    points: np.ndarray  # (N, 3) object frame
    normals: np.ndarray  # (N, 3) object frame, outward


def exit_points(scene: Scene, angle_deg: float, geometry: RigGeometry | None = None) -> ExitPoints:
    geometry = geometry or scene.geometry()
    origins, directions = geometry.camera.pixel_rays()
    o, d = to_object(origins, angle_deg), to_object(directions, angle_deg)
    iv = scene.body().interval(o, d)
    t = np.where(iv.hit, iv.t_in, 0.0)
    return ExitPoints(iv.hit, o + t[:, None] * d, iv.normal_in)


def entry_points(scene: Scene, angle_deg: float, heights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the light's ray at each height z enters the object (the beam's ray moved to that height, as a sheet
    lights every slice): points and outward normals (N, 3) in the object frame, and whether it enters at all."""
    origin, direction = scene.geometry().beam()
    heights = np.asarray(heights, float).ravel()
    origins = np.tile(origin, (len(heights), 1))
    origins[:, 2] = heights  # the stage turns about z: a height is the same in the lab and the object frame
    o = to_object(origins, angle_deg)
    d = np.tile(to_object(direction[None], angle_deg), (len(heights), 1))
    iv = scene.body().interval(o, d)
    t = np.where(iv.hit, iv.t_in, 0.0)
    return o + t[:, None] * d, iv.normal_in, iv.hit


def entry_point(scene: Scene, angle_deg: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the light's central ray enters the object (object frame) and the outward normal there."""
    points, normals, hit = entry_points(scene, angle_deg, [scene.geometry().beam_height])
    return (points[0], normals[0]) if hit[0] else None


def _diameter(scene: Scene) -> float:
    return 2.0 * scene.object.shape.build().reach()


def path_absorption(scene: Scene, start: np.ndarray, end: np.ndarray, *, reference: bool) -> np.ndarray:
    """∫σ along segments inside the object: medium everywhere, inclusions unless ``reference``."""
    total = scene.object.medium.sigma * np.linalg.norm(end - start, axis=1)
    if not reference:
        for solid, sigma in scene.inclusions():
            total = total + sigma * segment_length_inside(solid, start, end)
    return total


def straight_path(scene: Scene, angle_deg: float, *, reference: bool, seen: ExitPoints | None = None) -> np.ndarray:
    """Counts above dark of the lit frame at one angle under the shortest-path model, (rows, cols).

    ``seen`` may pass this angle's :func:`exit_points`, when the caller has them already.
    """
    geometry = scene.geometry()
    camera = geometry.camera
    seen = seen or exit_points(scene, angle_deg, geometry)
    image = np.zeros(camera.rows * camera.cols)
    p_c, n_c = seen.points[seen.hit], seen.normals[seen.hit]
    if scene.light.kind == "sheet":  # each slice lit at its own height: horizontal paths
        start, n_l, lit = entry_points(scene, angle_deg, p_c[:, 2])
        power = 1
    else:
        entry = entry_point(scene, angle_deg)
        if entry is None:
            return image.reshape(camera.rows, camera.cols)
        start, n_l, lit = np.tile(entry[0], (len(p_c), 1)), np.tile(entry[1], (len(p_c), 1)), True
        power = 2
    span = p_c - start
    length = np.linalg.norm(span, axis=1)
    safe = np.maximum(length, 1e-12)
    u = span / safe[:, None]
    cos_i = np.clip(-np.einsum("ij,ij->i", u, n_l), 0.0, None) * lit
    cos_o = np.clip(np.einsum("ij,ij->i", u, n_c), 0.0, None)
    scale = scene.light.intensity * scene.object.skin.transmittance**2
    absorbed = path_absorption(scene, start, p_c, reference=reference)
    image[seen.hit] = scale * cos_i * cos_o * (_diameter(scene) / safe) ** power * np.exp(-absorbed)
    return image.reshape(camera.rows, camera.cols)


def silhouette(scene: Scene, angle_deg: float, seen: ExitPoints | None = None) -> np.ndarray:
    """True where the object hides the lit plane behind it, (rows, cols)."""
    geometry = scene.geometry()
    return (seen or exit_points(scene, angle_deg, geometry)).hit.reshape(geometry.camera.rows, geometry.camera.cols)


@dataclass(frozen=True)
class MonteCarloFrame:
    """Monte Carlo estimate of a lit frame (counts above dark) and its standard error, (rows, cols)."""

    image: np.ndarray
    std_error: np.ndarray
    photons: int
    mean_events: float


def monte_carlo(scene: Scene, angle_deg: float, *, reference: bool, batch: int = 1 << 15,
                seen: ExitPoints | None = None, workers: int | None = None) -> MonteCarloFrame:
    """Trace ``effects.scattering.photons`` photons in 3-D from the entry point; estimate the exit radiance.

    Photons go in batches of at most ``batch``, each with its own random stream seeded by (scattering seed, angle,
    batch index), not by the sample: target and reference share their paths, and the frame is the same whatever
    ``workers`` traces the batches (threads; None: one per core; threads share the scene unpickled, and most of a
    batch's time is in numpy kernels that release the GIL: a 400 k-photon frame 1.45× faster on 2 cores).
    """
    settings = scene.effects.scattering
    if settings is None:
        raise ValueError("the scene has no scattering effect; use straight_path")
    geometry = scene.geometry()
    camera = geometry.camera
    n_pixels = camera.rows * camera.cols
    entry = entry_point(scene, angle_deg)
    if entry is None:
        zero = np.zeros((camera.rows, camera.cols))
        return MonteCarloFrame(zero, zero, settings.photons, 0.0)
    sizes = [min(batch, settings.photons - first) for first in range(0, settings.photons, batch)]
    streams = np.random.SeedSequence([settings.seed, int(round(angle_deg * 1000)) % 360_000]).spawn(len(sizes))

    body = scene.body()

    def trace(n: int, stream: np.random.SeedSequence) -> tuple[np.ndarray, np.ndarray, int]:
        return _trace_batch(scene, body, camera, angle_deg, entry, n, np.random.default_rng(stream),
                            reference=reference)

    sums, squares, events = np.zeros(n_pixels), np.zeros(n_pixels), 0
    with ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
        for part in pool.map(trace, sizes, streams):  # in batch order, whatever finished first: the same sums
            sums += part[0]
            squares += part[1]
            events += part[2]
    seen = seen or exit_points(scene, angle_deg, geometry)
    footprint = np.full(n_pixels, np.inf)
    footprint[seen.hit] = camera.pixel_footprint(to_lab(seen.points[seen.hit], angle_deg),
                                                 to_lab(seen.normals[seen.hit], angle_deg))
    scale = scene.light.intensity * scene.object.skin.transmittance**2 * np.pi * _diameter(scene) ** 2
    per_photon = scale / (settings.photons * footprint)
    shape = (camera.rows, camera.cols)
    return MonteCarloFrame((sums * per_photon).reshape(shape), (np.sqrt(squares) * per_photon).reshape(shape),
                           settings.photons, events / settings.photons)


def _trace_batch(scene: Scene, body: Solid, camera: Camera, angle_deg: float, entry: tuple[np.ndarray, np.ndarray],
                 n: int, rng: np.random.Generator, *, reference: bool) -> tuple[np.ndarray, np.ndarray, int]:
    """``n`` photons from the entry point until they leave (or ``max_events``): per pixel the sum of their exit
    weights and of the weights squared, and the number of scattering events."""
    settings = scene.effects.scattering
    sums, squares = np.zeros(camera.rows * camera.cols), np.zeros(camera.rows * camera.cols)
    p_l, n_l = entry
    pos = np.tile(p_l - 1e-9 * n_l, (n, 1))
    direction = cosine_hemisphere(-n_l, n, rng)
    weight = np.ones(n)
    events = 0
    for _ in range(settings.max_events):
        if not len(pos):
            break
        iv = body.interval(pos, direction)  # normals: where photons leave
        t_exit = np.maximum(iv.t_out, 0.0)
        free = rng.exponential(1.0 / settings.sigma_s, len(pos))
        leaving = free >= t_exit
        step = np.where(leaving, t_exit, free)
        end = pos + step[:, None] * direction
        weight = weight * np.exp(-path_absorption(scene, pos, end, reference=reference))
        _bin_exits(camera, angle_deg, end[leaving], iv.normal_out[leaving], weight[leaving], sums, squares)
        stay = ~leaving
        events += int(stay.sum())
        pos, weight = end[stay], weight[stay]
        direction = isotropic(len(pos), rng)
    return sums, squares, events


def _bin_exits(camera: Camera, angle_deg: float, points: np.ndarray, normals: np.ndarray,
               weight: np.ndarray, sums: np.ndarray, squares: np.ndarray) -> None:
    """Add exiting photons to the pixel that sees their exit point (front-facing points only)."""
    q, n = to_lab(points, angle_deg), to_lab(normals, angle_deg)
    facing = camera.facing(q, n)
    index, ok = camera.pixel_index(*camera.project(q[facing]))
    index = index[ok]
    w = weight[facing][ok]
    sums += np.bincount(index, w, minlength=len(sums))
    squares += np.bincount(index, w * w, minlength=len(squares))


def lit_frame(scene: Scene, angle_deg: float, sample: str, seen: ExitPoints | None = None) -> np.ndarray:
    """Counts above dark with the light on: Monte Carlo only when the scene names scattering."""
    if sample not in SAMPLES:
        raise ValueError(f"sample must be one of {SAMPLES}, not {sample!r}")
    reference = sample == "reference"
    if scene.effects.scattering is not None:
        return monte_carlo(scene, angle_deg, reference=reference, seen=seen).image
    return straight_path(scene, angle_deg, reference=reference, seen=seen)


#: the frames :func:`render_rows` stacks, in its first axis
FRAME_KINDS = ("target", "reference", "backlit")


def render_rows(scene: Scene, angles_deg: np.ndarray, first: int, count: int) -> np.ndarray:
    """Rows ``first`` … ``first + count − 1`` of the target, reference and backlit frames at each angle, as the
    simulated rig's camera records them (dark level, saturation, noise), float32 (3, angles, count, cols).

    Straight paths only (a Monte Carlo frame traces photons over the whole object: render it with the rig). Noise
    is seeded per (seed, angle, frame, row), so any banding of the rows gives the same frames; they are not the
    rig's, which seeds a whole frame at once.
    """
    if scene.effects.scattering is not None:
        raise ValueError("render_rows renders straight paths; a scene with scattering is rendered by the rig")
    band, sensor, noise = scene.rows(first, count), scene.sensor, scene.effects.noise
    out = np.empty((3, len(angles_deg), count, scene.camera.cols), np.float32)
    for a, angle in enumerate(np.asarray(angles_deg, float)):
        seen = exit_points(band, angle)
        signals = [straight_path(band, angle, reference=False, seen=seen),
                   straight_path(band, angle, reference=True, seen=seen),
                   sensor.backlight * ~silhouette(band, angle, seen)]
        for k, signal in enumerate(signals):
            if noise is not None:
                signal = signal.copy()
                for r in range(count):
                    rng = np.random.default_rng([noise.seed, int(round(angle * 1000)) % 360_000, k, first + r])
                    if noise.gain is not None:
                        signal[r] = rng.poisson(np.clip(signal[r], 0, None) / noise.gain) * noise.gain
                    signal[r] = signal[r] + rng.normal(0.0, noise.read_std, signal.shape[1])
            out[k, a] = np.clip(sensor.dark_level + signal, 0.0, sensor.saturation_level)
    return out
