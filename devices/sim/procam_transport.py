"""The projector–camera transport simulator: ground-truth transport from a scene's effects, and images
formed by integrating the raster scan and the rolling shutter over time (§5.2.2, §5.3.1).

**Ground truth** (:mod:`selpath.devices.sim.procam_lobes`). Each pixel's transport is a sum of separable *lobes*
in offset space, one or more per effect its object names (``selpath.devices.sim.procam_scene``): weight · k_u(du) ·
k_v(dv), with du in projector columns from the pixel's direct correspondence u_d and dv = projector row − camera
row. Kernels are integrated over each unit offset cell, so a lobe's mass on the integer grid is exactly its weight
(hat: linear interpolation of a delta; gauss; exp: a Laplace lobe). Only the named effects' code runs.

**Images.** Nothing here uses the demultiplexing's illumination matrix. A frame is formed by integrating
over time: projector row v is lit during [vτ + j_v, vτ + j_v + t_p] (τ = 1/v_p the row period, j_v the
laser jitter when the rig names it), camera row s exposes during t_e centred at sτ + t_p/2 + t_d (t_d the
commanded delay plus the rig's true sync offset); the light row v sends to row s is the overlap of the two
intervals over t_p. The pattern's column profile weights du. Sensor noise (shot, read), quantisation and
saturation apply only when named. Frames are rendered in row tiles, so memory stays bounded at any
sensor size.

**Patterns.** The signal is linear in the pattern, so a pattern is rendered as the sum of its rank-1 terms
b_k(v)·a_k(u) (:func:`pattern_terms`: one term for white, lines, stripes and column Gray codes; two for a
checkerboard, ½·1 + ½·s(v)s(u); the SVD for any other), each term by the separable time integration above, and
noise, quantisation and saturation applied once to the sum. Low-rank patterns are rendered exactly; a pattern
that needs more than ``max_terms`` terms is refused with its residual at that rank, or rendered to a stated
tolerance (``pattern_rtol``).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterator

import numpy as np

from selpath.devices.sim.procam_lobes import Lobe, Tile, cell_kernel, lobe_reach, tile_lobes
from selpath.devices.sim.procam_scene import ProcamRig, ProcamScene

#: rows rendered at a time (bounded memory at any sensor width)
TILE_ROWS = 64
#: a pattern's rank-1 terms are kept until the rest holds at most this share of its Frobenius norm
PATTERN_RTOL = 1e-9
#: the most rank-1 terms a pattern may take by default (each costs one separable render of the frame)
MAX_PATTERN_TERMS = 32


# -- time integration ----------------------------------------------------------------------------------


def frame_key(delay: float, exposure: float, pattern: np.ndarray | None) -> int:
    """A deterministic seed for one capture's random effects (resumed sweeps reproduce the same frames)."""
    digest = zlib.crc32(np.ascontiguousarray(pattern).tobytes()) if pattern is not None else 0
    return zlib.crc32(np.array([delay, exposure], dtype=np.float64).tobytes(), digest)


#: the jitter vector starts at this (virtual) projector row; rows beyond the vector's ends reuse its ends
JITTER_FIRST = -4096


def row_jitter(rig: ProcamRig, key: int) -> np.ndarray | None:
    """Laser timing jitter j_v [µs] of projector rows JITTER_FIRST … R − JITTER_FIRST − 1 for one capture,
    or None when the rig does not name jitter. One draw per row, the same for every tile."""
    if rig.jitter is None or rig.jitter.std == 0:
        return None
    rng = np.random.default_rng([rig.jitter.seed, key])
    return rng.normal(0.0, rig.jitter.std, rig.camera_rows - 2 * JITTER_FIRST)


def exposure_overlap(rig: ProcamRig, camera_row, projector_row, delay: float, exposure: float,
                     jitter: np.ndarray | None = None, jitter_first: int = 0, shutter: str = "rolling") -> np.ndarray:
    """Fraction of projector row v's lit time t_p that falls in camera row s's exposure (broadcasting).

    The two intervals on the time axis: lit [vτ + j_v, vτ + j_v + t_p]; exposed t_e wide, centred at
    sτ + t_p/2 + t_d + t_o (t_o the rig's true sync offset) with the synchronised rolling shutter, or
    [t_d + t_o, t_d + t_o + t_e] after VSYNC for every row with a global shutter (the v_p calibration).
    """
    tau, tp = rig.row_period, rig.line_time
    start = projector_row * tau
    if jitter is not None:
        start = start + jitter[np.clip(np.asarray(projector_row) - jitter_first, 0, jitter.size - 1)]
    if shutter == "global":
        centre = delay + rig.sync_offset + exposure / 2
    else:
        centre = camera_row * tau + tp / 2 + delay + rig.sync_offset
    overlap = np.minimum(start + tp, centre + exposure / 2) - np.maximum(start, centre - exposure / 2)
    return np.clip(overlap, 0.0, None) / tp


def _delay_window(rig: ProcamRig, delay: float, exposure: float, margin: float) -> tuple[int, int]:
    """Offsets o (projector − camera row) that can receive light at this delay/exposure."""
    tau, tp = rig.row_period, rig.line_time
    low = (delay + rig.sync_offset - exposure / 2 - tp / 2 - margin) / tau - 1
    high = (delay + rig.sync_offset + exposure / 2 + tp / 2 + margin) / tau + 1
    return int(np.floor(low)), int(np.ceil(high))


def _distinct(*columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct tuples of equal-length columns, (len(columns), n_distinct), and each row's tuple index.

    Each column is coded by a 1-D ``np.unique`` and the codes are combined into one int64 key: much faster
    than ``np.unique(axis=1)``, which sorts a structured view.
    """
    key = np.zeros(columns[0].shape, dtype=np.int64)
    for column in columns:
        values, codes = np.unique(column, return_inverse=True)
        key = key * len(values) + codes.ravel()
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return np.stack([c[first] for c in columns]), inverse.ravel()


def _horizontal(lobe: Lobe, u_direct: np.ndarray, column_profile: np.ndarray) -> np.ndarray:
    """Σ_du pattern[u_d + du] · k_u(du) for each of the lobe's pixels (columns outside the projector are dark),
    once per distinct (u_d, du, width)."""
    unique, inverse = _distinct(u_direct[lobe.index].astype(float), lobe.du, lobe.width_u)
    reach = lobe_reach(unique[2], lobe.shape_u)
    j = np.arange(-reach, reach + 1)[None, :] + np.round(unique[1])[:, None].astype(np.int64)
    k_u = cell_kernel(j, unique[1][:, None], unique[2][:, None], lobe.shape_u)
    u = unique[0].astype(np.int64)[:, None] + j
    n_cols = column_profile.shape[0]
    lit = np.where((u >= 0) & (u < n_cols), column_profile[np.clip(u, 0, n_cols - 1)], 0.0)
    return np.einsum("pk,pk->p", k_u, lit)[inverse]


def render_tile(scene: ProcamScene, tile: Tile, delay: float, exposure: float,
                profiles: tuple[np.ndarray, np.ndarray], key: int,
                effects: dict[str, Callable] | None = None, shutter: str = "rolling") -> np.ndarray:
    """Signal [counts, before noise] of ``tile`` for one capture, by time integration.

    ``profiles``: one rank-1 term of the pattern, (row profile on camera rows, column profile on projector
    columns), from :func:`pattern_terms`; linear in each.
    """
    row_profile, column_profile = profiles
    rig = scene.rig
    lobes, u_direct = tile_lobes(scene, tile, effects)
    margin = 6 * rig.jitter.std if rig.jitter is not None else 0.0
    if shutter == "global":  # every row exposes at once: any offset can be lit
        o_low, o_high = -rig.camera_rows - 1, rig.camera_rows + 1
    else:
        o_low, o_high = _delay_window(rig, delay, exposure, margin)
    jitter = row_jitter(rig, key)
    signal = np.zeros(tile.rows.shape)
    for lobe in lobes:
        # Both sums depend on a pixel only through a few parameters (its row and the lobe's dv and width; its
        # u_d and the lobe's du and width), so they are evaluated once per distinct parameter tuple: an
        # object's direct or subsurface lobe costs per row and per column, not per pixel.
        unique, inverse = _distinct(tile.rows[lobe.index].astype(float), lobe.dv, lobe.width_v)
        rows, dv, width = unique[0].astype(np.int64)[:, None], unique[1][:, None], unique[2][:, None]
        reach = lobe_reach(unique[2], lobe.shape_v)
        if o_high - o_low < 2 * reach:  # the exposure band is narrower than the lobe: sum over the band
            o = np.arange(o_low, o_high + 1)[None, :]
        else:  # sum over the lobe's window around its centre (the band cuts it by zero overlap)
            o = np.round(dv).astype(np.int64) + np.arange(-reach, reach + 1)[None, :]
        k_v = cell_kernel(o, dv, width, lobe.shape_v, lobe.absorbed_v)
        v = rows + o
        light = exposure_overlap(rig, rows, v, delay, exposure, jitter, JITTER_FIRST, shutter)
        inside = (v >= 0) & (v < row_profile.size)
        light = light * np.where(inside, row_profile[np.clip(v, 0, row_profile.size - 1)], 0.0)
        vertical = np.einsum("pk,pk->p", k_v, light)[inverse]
        horizontal = _horizontal(lobe, u_direct, column_profile)
        signal[lobe.index] += lobe.weight * vertical * horizontal  # a lobe's pixels are distinct
    return rig.intensity * signal


def sensor(rig: ProcamRig, signal: np.ndarray, key: int, where: int) -> np.ndarray:
    """Noise (when named), dark level, quantisation and saturation: raw float32 counts."""
    if rig.noise is not None:
        rng = np.random.default_rng([rig.noise.seed, key, where])
        if rig.noise.gain is not None:
            signal = rng.poisson(np.clip(signal, 0, None) / rig.noise.gain) * rig.noise.gain
        signal = signal + rng.normal(0.0, rig.noise.read_std, signal.shape)
    raw = rig.dark_level + signal
    if rig.bits is not None:
        raw = np.round(raw)
    return np.clip(raw, 0.0, rig.saturation_level).astype(np.float32)


def tiles(scene: ProcamScene, tile_rows: int = TILE_ROWS) -> Iterator[Tile]:
    for r0 in range(0, scene.rig.camera_rows, tile_rows):
        yield Tile.of(scene, r0, min(r0 + tile_rows, scene.rig.camera_rows))


def render_frame(scene: ProcamScene, delay: float, exposure: float, pattern: np.ndarray | None = None, *,
                 effects: dict[str, Callable] | None = None, shutter: str = "rolling",
                 pattern_rtol: float = PATTERN_RTOL, max_terms: int = MAX_PATTERN_TERMS, scans: int = 1
                 ) -> np.ndarray:
    """One raw frame (float32 counts, camera shape) for a capture at ``delay``, ``exposure`` [µs].

    ``pattern``: (projector rows, cols) in [0, 1], any (:func:`pattern_terms`: its rank-1 terms, each rendered
    by time integration, summed before the sensor); None: white. ``scans``: the exposure repeats over this many
    identical projector scans of a static pattern (a long exposure: the signal × scans, read out once; with the
    global shutter, a window of one scan per frame period).
    """
    if scans < 1:
        raise ValueError(f"scans is {scans}; a frame integrates at least one scan")
    rig = scene.rig
    terms = pattern_terms(rig, pattern, rtol=pattern_rtol, max_terms=max_terms)
    key = frame_key(delay, exposure, pattern) ^ (1 if shutter == "global" else 0) ^ (scans - 1) << 1
    out = np.empty((rig.camera_rows, rig.camera_cols), dtype=np.float32)
    for tile in tiles(scene):
        r0 = int(tile.rows[0])
        signal = scans * sum(render_tile(scene, tile, delay, exposure, term, key, effects, shutter) for term in terms)
        out[r0:r0 + tile.shape[0]] = sensor(rig, signal, key, r0).reshape(tile.shape)
    return out


def seen_rows(rig: ProcamRig) -> np.ndarray:
    """The projector row that lights each camera row on a rectified rig: the one under the camera row's centre,
    ⌊(s + ½) · P_rows / C_rows⌋ (rows as unit cells, so camera row s's centre s + ½ lies at (s + ½)·P/C in
    projector rows)."""
    return ((2 * np.arange(rig.camera_rows) + 1) * rig.projector_rows) // (2 * rig.camera_rows)


def on_camera_rows(rig: ProcamRig, row_profile: np.ndarray) -> np.ndarray:
    """A projector-row profile (or pattern, rows first) rectified onto camera rows (:func:`seen_rows`)."""
    return row_profile[seen_rows(rig)]


def pattern_terms(rig: ProcamRig, pattern: np.ndarray | None, *, rtol: float = PATTERN_RTOL,
                  max_terms: int = MAX_PATTERN_TERMS) -> list[tuple[np.ndarray, np.ndarray]]:
    """A pattern P as rank-1 terms [(row profile on camera rows, column profile on projector columns), …] with
    P = Σ_k b_k(v) · a_k(u).

    The pattern's rows are first rectified onto the camera's (the rows no camera row sees are never rendered). A
    separable pattern (white, lines, stripes, column Gray codes) is then one term, found exactly without a
    factorisation. Any other is its SVD truncated at the first rank whose residual ‖P − P_k‖_F is at most
    ``rtol`` · ‖P‖_F: exact to rounding for low-rank patterns (a checkerboard, ½ + ½·s(v)·s(u), has rank 2). A
    pattern that needs more than ``max_terms`` terms is refused, naming its residual at that rank (raise
    ``rtol`` to render it approximately: rendering is linear, so the frame's error is then the render of the
    dropped terms P − P_k, whose Frobenius norm is at most ``rtol`` · ‖P‖_F).
    """
    if pattern is None:
        return [(np.ones(rig.camera_rows), np.ones(rig.projector_cols))]
    pattern = np.asarray(pattern, dtype=float)
    if pattern.shape != (rig.projector_rows, rig.projector_cols):
        raise ValueError(f"pattern is {pattern.shape}; the projector is {(rig.projector_rows, rig.projector_cols)}")
    if not np.all(np.isfinite(pattern)) or pattern.min() < 0 or pattern.max() > 1:
        raise ValueError("pattern values must be finite and in [0, 1]")
    # only the projector rows the camera's rows are rectified onto are ever rendered: factorise what is seen
    pattern = on_camera_rows(rig, pattern)
    r, c = np.unravel_index(np.argmax(pattern), pattern.shape)
    peak = pattern[r, c]
    rows, cols = (pattern[:, c] / peak, pattern[r, :]) if peak > 0 else (np.zeros(pattern.shape[0]), pattern[0])
    if np.allclose(np.outer(rows, cols), pattern, rtol=0.0, atol=1e-12):
        return [(rows, cols)]
    # P = C·E with C its distinct columns (a checkerboard has 2) and E copying column j of C counts[j] times, so
    # P·Pᵀ = (C·W)(C·W)ᵀ with W = diag(√counts): P's singular values and left vectors are those of C·W, its right
    # vectors Vᵀ·W⁻¹ spread back over the copies: rows × distinct² instead of rows × cols². Distinct columns are
    # found on a byte view of each column (np.unique(axis=1) sorts lexicographically and takes as long as the
    # full SVD). Measured: a 1200 × 1600 checkerboard's terms in about 0.1 s, all checks included.
    columns = np.ascontiguousarray(pattern.T)
    _, first, inverse = np.unique(columns.view((np.void, columns.shape[1] * columns.itemsize)).ravel(),
                                  return_index=True, return_inverse=True)
    distinct = pattern[:, first]
    weight = np.sqrt(np.bincount(inverse.ravel(), minlength=distinct.shape[1]))
    u, s, vt = np.linalg.svd(distinct * weight, full_matrices=False)
    vt = (vt / weight)[:, inverse.ravel()]
    tail = np.sqrt(np.cumsum((s**2)[::-1])[::-1])  # tail[k]: ‖P − P_k‖_F, the residual after k terms
    residual = np.append(tail[1:], 0.0) / tail[0]  # after 1, 2, … terms, as a share of ‖P‖_F
    rank = int(np.argmax(residual <= rtol)) + 1
    if rank > max_terms:
        raise ValueError(f"the pattern needs {rank} rank-1 terms to render within {rtol:g} of its norm; at "
                         f"{max_terms} terms its residual is {residual[max_terms - 1]:.2e} of it: pass a larger "
                         "max_terms, or a pattern_rtol at least that large to render it approximately")
    return [(u[:, k] * s[k], vt[k]) for k in range(rank)]


# -- ground truth on the offset grid --------------------------------------------------------------------


def truth_tile(scene: ProcamScene, tile: Tile, dv: np.ndarray, du: np.ndarray | None = None,
               effects: dict[str, Callable] | None = None) -> np.ndarray:
    """Ground-truth transport of ``tile`` on the offset grid: (len(dv), P) plane-to-ray (the white pattern's
    sum over the projector's columns), or (len(du), len(dv), P) full transport. Offsets that point outside
    the projector carry nothing."""
    rig = scene.rig
    lobes, u_direct = tile_lobes(scene, tile, effects)
    n = tile.rows.size
    out = np.zeros((len(dv), n) if du is None else (len(du), len(dv), n))
    white = np.ones(rig.projector_cols)
    for lobe in lobes:
        k_v = cell_kernel(np.asarray(dv)[None, :], lobe.dv[:, None], lobe.width_v[:, None], lobe.shape_v,
                          lobe.absorbed_v)
        v = tile.rows[lobe.index][:, None] + np.asarray(dv)[None, :]
        k_v = k_v * ((v >= 0) & (v < rig.camera_rows))  # no light from rows the projector does not have
        if du is None:  # the white pattern's sum over the projector's columns
            out.T[lobe.index] += (lobe.weight * _horizontal(lobe, u_direct, white))[:, None] * k_v
        else:
            k_u = cell_kernel(np.asarray(du)[None, :], lobe.du[:, None], lobe.width_u[:, None], lobe.shape_u)
            u = u_direct[lobe.index][:, None] + np.asarray(du)[None, :]
            k_u = k_u * ((u >= 0) & (u < rig.projector_cols))
            out.transpose(2, 0, 1)[lobe.index] += lobe.weight[:, None, None] * k_u[:, :, None] * k_v[:, None, :]
    return out
