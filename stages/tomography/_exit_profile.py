"""The reference frames' exit profile and the walks that model it: what
:func:`selpath.stages.tomography.scattering_estimate.estimate_scattering` fits σ_s with.

The frames' light around the beam's slice is binned by each pixel's distance from the light's entry point
(:func:`exit_profile`); walks traced at σ_0 are binned by the pixel that sees their exit and reweighted to candidates
near σ_0 (:func:`candidate_counts`); the log profiles are compared with a free scale, less the walks' own Monte Carlo
share (:func:`profile_misfit`), and the minimum refined in log σ_s (:func:`curve_minimum`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selpath.geometry.rig import RigGeometry, to_lab
from selpath.geometry.shapes import Prism
from selpath.stages.tomography._walks import Walks, beam_entry, random_walks, surface_seen, walk_weights

#: pixels that see the hull more obliquely than this (from its normal) are not compared: their areas are the hull's
#: least certain [degree]. On the workflow's σ_s = 3 capture, 72° gives 2.71 [2.49, ∞]; 80° closes the interval but
#: off the truth, 2.56 [2.39, 2.75]; 85° gives 2.20 at a misfit of 0.022 (−0.0002 at 72°): the limb's pixels bias it low
GRAZING_DEG = 72.0


@dataclass(frozen=True)
class ExitProfile:
    """What the reference frames show of the light leaving the object, per view: the distance bin (from the light's
    entry point, on the slice's prism) of each used pixel of the band of rows about the slice (−1: not used), and
    the measured light per bin (counts above dark × the surface area the pixel sees: proportional to the photons
    that left through it). Views the light misses are left out."""

    views: np.ndarray  # (V,) indices into the views given
    entries: list[tuple[np.ndarray, np.ndarray]]  # per view: entry point and outward normal, object frame
    pixel_bin: np.ndarray  # (V, pixels of the band) distance bin of each pixel, −1 where not used
    measured: np.ndarray  # (V, B)
    edges: np.ndarray  # (B + 1,) the bins' distance edges [length unit]


def exit_profile(reference: np.ndarray, usable: np.ndarray, angles: np.ndarray, rows: np.ndarray, body: Prism,
                 geometry: RigGeometry, height: float, n_bins: int) -> ExitProfile:
    """The :class:`ExitProfile` of reference frames (views, rows of the band, cols; counts above dark) where
    ``usable`` (same shape) marks pixels inside the sensor's range: a pixel is used where it is usable, sees the
    prism within :data:`GRAZING_DEG` of its normal and the light enters the prism; ``n_bins`` bins of equal pixel
    counts over the used pixels' distances."""
    camera = geometry.camera
    r, c = np.meshgrid(rows, np.arange(camera.cols), indexing="ij")
    origins, directions = camera.back_project(r, c)
    kept, entries, distance, light = [], [], [], []
    for v, angle in enumerate(np.asarray(angles, float)):
        if (entry := beam_entry(body, geometry, angle, height)) is None:
            continue
        hit, point, normal, d = surface_seen(body, origins, directions, angle)
        facing = np.einsum("ij,ij->i", normal, -d) > np.cos(np.deg2rad(GRAZING_DEG))
        used = hit & facing & usable[v].ravel()
        area = np.zeros(len(point))
        area[used] = camera.pixel_footprint(to_lab(point[used], angle), to_lab(normal[used], angle))
        kept.append(v)
        entries.append(entry)
        distance.append(np.where(used, np.linalg.norm(point - entry[0], axis=1), np.nan))
        light.append(np.where(used, reference[v].ravel() * area, 0.0))
    distance, light = np.array(distance).reshape(len(kept), -1), np.array(light).reshape(len(kept), -1)
    finite = distance[np.isfinite(distance)]
    if finite.size < n_bins:
        edges = np.zeros(n_bins + 1)
        pixel_bin = np.full(distance.shape, -1)
    else:
        edges = np.quantile(finite, np.linspace(0.0, 1.0, n_bins + 1))
        pixel_bin = np.where(np.isfinite(distance),
                             np.clip(np.searchsorted(edges, np.nan_to_num(distance), side="right") - 1, 0, n_bins - 1),
                             -1)
    measured = np.array([np.bincount(b[b >= 0], w[b >= 0], minlength=n_bins) for b, w in zip(pixel_bin, light,
                                                                                             strict=True)])
    return ExitProfile(np.asarray(kept, np.int64), entries, pixel_bin, measured.reshape(len(kept), n_bins), edges)


def walk_bins(profile: ExitProfile, v: int, walks: Walks, angle: float, rows: np.ndarray,
              geometry: RigGeometry) -> np.ndarray:
    """The distance bin of the pixel that sees each walk's exit at view ``v`` of ``profile`` (−1: no used pixel)."""
    camera = geometry.camera
    q, n = to_lab(walks.exit_point, angle), to_lab(walks.exit_normal, angle)
    r, c = (np.rint(x).astype(np.int64) for x in camera.project(q))
    seen = camera.facing(q, n) & (r >= rows[0]) & (r <= rows[-1]) & (c >= 0) & (c < camera.cols)
    out = np.full(len(r), -1)
    out[seen] = profile.pixel_bin[v][(r[seen] - rows[0]) * camera.cols + c[seen]]
    return out


def profile_misfit(measured: np.ndarray, modelled: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """The misfit of log exit profiles with a free scale, per candidate: Σ_b r_b² − (1 − 1/B) Σ_b var_b with
    r = log measured − log modelled less its mean over the B bins (the scale: the light's power and the skin's
    transmittance are unknown), and var_b the Monte Carlo variance of log modelled_b, whose share of Σ r² it takes
    away: the misfit of a candidate traced with few walks is not inflated by their noise. ``modelled`` and
    ``variance`` (candidates, B); +inf where a bin is empty."""
    with np.errstate(divide="ignore", invalid="ignore"):
        residual = np.log(measured)[None] - np.log(modelled)
        residual = residual - residual.mean(axis=-1, keepdims=True)
        misfit = (residual**2).sum(axis=-1) - (1 - 1 / measured.shape[-1]) * variance.sum(axis=-1)
    return np.where(np.isfinite(misfit), misfit, np.inf)


def curve_minimum(misfit: np.ndarray, grid: np.ndarray) -> float:
    """The minimiser of a misfit sampled on a log-uniform ``grid`` of σ_s: the parabola through the smallest sample
    and its neighbours, in log σ_s; the grid's end where the smallest is there."""
    k = int(np.argmin(misfit))
    if not np.isfinite(misfit[k]):
        return float("nan")
    if 0 < k < len(grid) - 1 and np.all(np.isfinite(misfit[k - 1:k + 2])):
        low, mid, high = misfit[k - 1:k + 2]
        curvature = low - 2 * mid + high
        if curvature > 0:
            step = np.log(grid[k + 1] / grid[k])
            return float(grid[k] * np.exp(0.5 * step * (low - high) / curvature))
    return float(grid[k])


#: candidates per round of ``estimate_scattering``: σ_0 · 2^u for u in [−REACH, REACH] octaves; farther, the
#: weights of walks traced at σ_0 grow heavy-tailed and the misfit turns down again at the ends (one octave: the
#: σ_s = 1 capture's misfit fell again at 2 σ_0, and bootstrap draws ended there)
CANDIDATES = 41
REACH_OCTAVES = 0.5
#: candidates whose walks keep less than this share of their number as effective walks are not compared
MIN_EFFECTIVE_SHARE = 0.5


def candidate_counts(profile: ExitProfile, body: Prism, geometry: RigGeometry, angles: np.ndarray, rows: np.ndarray,
                      grid: np.ndarray, traced_at: float, settings: dict, seeds: np.random.SeedSequence
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Walks traced at ``traced_at`` from each view's entry point, binned by the pixel that sees their exit and
    weighted to every candidate of ``grid``: the weighted counts and the sums of squared weights, (candidates,
    views, bins)."""
    shape = (len(grid), len(profile.views), profile.measured.shape[1])
    counts, squares = np.zeros(shape), np.zeros(shape)
    for k, (v, stream) in enumerate(zip(profile.views, seeds.spawn(len(profile.views)), strict=True)):
        walks = random_walks(body, *profile.entries[k], traced_at, settings["photons"], np.random.default_rng(stream),
                             max_events=settings["max_events"], record=False)
        where = walk_bins(profile, k, walks, angles[v], rows, geometry)
        reached = where >= 0
        walks = Walks(*(f[reached] for f in (walks.exit_point, walks.exit_normal, walks.events, walks.length)))
        for g, candidate in enumerate(grid):
            weight = walk_weights(walks, candidate, traced_at)
            counts[g, k] = np.bincount(where[reached], weight, minlength=shape[2])
            squares[g, k] = np.bincount(where[reached], weight**2, minlength=shape[2])
    return counts, squares


def trusted_candidates(counts: np.ndarray, squares: np.ndarray) -> np.ndarray:
    """The candidates whose reweighted walks keep at least :data:`MIN_EFFECTIVE_SHARE` of their number as
    effective walks ((Σw)² / Σw²): beyond, the weights are heavy-tailed and the misfit turns down spuriously."""
    total, square = counts.sum(axis=(1, 2)), squares.sum(axis=(1, 2))
    walks = counts[len(counts) // 2].sum()  # the middle candidate is σ_0 itself: every weight 1
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.nan_to_num(total**2 / square) >= MIN_EFFECTIVE_SHARE * walks


def fit_profile(share: np.ndarray, measured: np.ndarray, counts: np.ndarray, squares: np.ndarray, grid: np.ndarray,
                 trusted: np.ndarray) -> tuple[float, np.ndarray]:
    """The estimate and the misfit per candidate (+inf where not ``trusted``), with each view counted ``share``
    times (1: all once; a bootstrap draw: its multiplicities)."""
    total = np.einsum("v,gvb->gb", share, counts)
    with np.errstate(divide="ignore", invalid="ignore"):
        variance = np.einsum("v,gvb->gb", share**2, squares) / total**2
    misfit = np.where(trusted, profile_misfit(share @ measured, total, variance), np.inf)
    return curve_minimum(misfit, grid), misfit
