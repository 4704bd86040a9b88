"""The illumination model of the synchronised projector–camera rig (Eq. 32–33, 37–38), on the offset grid.

A frame at delay t_d and exposure t_e lights camera row s with projector row s + o for the part of the row's
line time t_p that falls inside the row's exposure. Projector row v is lit during [v/v_p, v/v_p + t_p]; camera
row s is exposed for t_e centred at s/v_p + t_p/2 + t_d + t_o (t_o the calibrated sync offset, §5.3.2), so the
weight of offset o is

    w(o; t_d, t_e) = |[o/v_p − t_p/2, o/v_p + t_p/2] ∩ [t_d + t_o − t_e/2, t_d + t_o + t_e/2]| / t_p,

the box of Eq. 33 (centre I_d = v_p t_d, width I_w = v_p t_e) with fractional edges and widened by t_p. It
depends only on the sweep, never on the pixel: the one matrix every pixel's demultiplexing shares (DESIGN §6).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class RigTiming:
    """The scan timing a demultiplexing uses: v_p ``scan_speed`` [camera rows per µs], t_p ``line_time`` [µs] and
    t_o ``sync_offset`` [µs] (the light of offset o is centred in the exposure at t_d = o / v_p − t_o)."""

    scan_speed: float
    line_time: float
    sync_offset: float

    def keywords(self) -> dict[str, float]:
        """The three as the illumination model's keyword arguments
        (:mod:`selpath.stages.procam._illumination`)."""
        return asdict(self)


def box_overlap(low_a, high_a, low_b, high_b) -> np.ndarray:
    """Length of the intersection of intervals [low_a, high_a] and [low_b, high_b] (broadcasting), ≥ 0."""
    return np.clip(np.minimum(high_a, high_b) - np.maximum(low_a, low_b), 0.0, None)


def offset_cells(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The integer offsets each cell of an evenly spaced offset grid covers: (cell index, offset, share)
    triples, share the part of that offset's row the cell holds.

    A grid of step h > 1 treats the transport as constant over h neighbouring rows (cell k covers the
    integer offsets o with |o − o_k| < h/2, and half of each offset at exactly h/2 when h is even).
    """
    offsets = np.asarray(offsets, dtype=float)
    step = float(np.min(np.diff(offsets))) if offsets.size > 1 else 1.0
    j = np.arange(-int(np.floor(step / 2)), int(np.floor(step / 2)) + 1)
    cells = np.repeat(np.arange(offsets.size), j.size)
    rows = (offsets[:, None] + j[None, :]).ravel()
    share = np.tile(np.where(2 * np.abs(j) == step, 0.5, 1.0), offsets.size)
    return cells, rows, share


def plane_to_ray_illumination(delays, exposures, offsets, *, scan_speed: float, line_time: float,
                              sync_offset: float = 0.0) -> np.ndarray:
    """Illumination matrix L[i, k] of frames i = (delays[i], exposures[i]) [µs] on the offset grid ``offsets``
    [rows]: the (N, K) matrix of Eq. 34 in the image's own units (1 = a row lit for its whole t_p).

    ``scan_speed`` v_p [rows per µs], ``line_time`` t_p [µs], ``sync_offset`` t_o [µs].
    """
    delays = np.asarray(delays, dtype=float)[:, None]
    exposures = np.asarray(exposures, dtype=float)[:, None]
    if delays.shape != exposures.shape:
        raise ValueError(f"{delays.shape[0]} delays but {exposures.shape[0]} exposures: one of each per frame")
    cells, rows, share = offset_cells(offsets)
    lit = rows[None, :] / scan_speed
    centre = delays + sync_offset
    weight = box_overlap(lit - line_time / 2, lit + line_time / 2, centre - exposures / 2, centre + exposures / 2)
    weight = weight / line_time * share[None, :]
    out = np.zeros((delays.shape[0], len(offsets)))
    np.add.at(out.T, cells, weight.T)
    return out


#: what a ``sync_delay`` coordinate carries, wherever it is made (a transport store, the accessor)
SYNC_DELAY_ATTRS = {"units": "us", "long_name": "sync delay t_d (o / v_p − t_o)"}


def offset_delay(offsets, *, scan_speed: float, sync_offset: float = 0.0) -> np.ndarray:
    """The sync delay t_d [µs] at which offset o's light is centred in the exposure: t_d = o / v_p − t_o (the box
    of Eq. 33 centred on o; ``scan_speed`` v_p [rows per µs], ``sync_offset`` t_o [µs]). A frame at t_d with
    exposure t_e sees the offsets within v_p·(t_e + t_p)/2 of v_p·(t_d + t_o).

    >>> offset_delay([-10, 0, 10], scan_speed=1 / 17, sync_offset=5.0).tolist()
    [-175.0, -5.0, 165.0]
    """
    return np.asarray(offsets, dtype=float) / scan_speed - sync_offset


def epipolar_boundary(delays, exposures, *, sync_offset: float = 0.0, margin: float) -> np.ndarray:
    """True for frames whose exposure edge passes within ``margin`` [µs] of the epipolar row (t_d ≈ ±t_e/2).

    There the direct light — the strongest path — is cut by the edge of the exposure, so the slightest
    timing jitter or sync error moves a large share of it in or out of the frame (the thesis drops these
    frames: "significant horizontal artifacts due to synchronization problems", §5.2.2).
    """
    delays = np.asarray(delays, dtype=float) + sync_offset
    return np.abs(np.abs(delays) - np.asarray(exposures, dtype=float) / 2) < margin


def difference_operator(size: int) -> np.ndarray:
    """First differences along the offset axis, (K − 1, K): the ∂T/∂v of the smoothness term E_c."""
    return np.diff(np.eye(size), axis=0)


def smoothness_matrix(size: int) -> np.ndarray:
    """DᵀD, (K, K): the Hessian of ‖D T‖² over two, D the first differences (:func:`difference_operator`); the one
    place the demultiplexer's problems and its exact finish form it."""
    d = difference_operator(size)
    return d.T @ d


def line_cells(lines, line_width: float, step: float | None = None) -> tuple[np.ndarray, float]:
    """(centres [projector columns], width) of the u-cells a line sweep resolves: cells of width ``step``
    (None: the spacing of the lines) tiling every column some line lights, from the first line's left edge."""
    lines = np.sort(np.asarray(lines, dtype=float))
    if lines.size == 0 or line_width <= 0:
        raise ValueError("a line sweep needs at least one line and a positive line width")
    if step is None:
        step = float(np.min(np.diff(lines))) if lines.size > 1 else float(line_width)
    if not step > 0:
        raise ValueError(f"the u-cell width must be positive, got {step}")
    low, high = lines[0] - line_width / 2, lines[-1] + line_width / 2
    count = int(np.ceil((high - low) / step - 1e-9))
    return low + step * (np.arange(count) + 0.5), float(step)


def line_illumination(lines, line_width: float, cells, step: float) -> np.ndarray:
    """Illumination matrix L_u[j, k] of vertical lines centred at ``lines[j]`` of width l_w on the u-cells of
    width ``step`` centred at ``cells`` (Eq. 38's box in u): the share of cell k the line covers (1 = all).

    With the frames forming a full (line × delay–exposure) grid, a full-transport frame's weights are the
    Kronecker product L_u ⊗ L (the box of Eq. 38 is separable); the demultiplexing never forms it.
    """
    lines, cells = np.asarray(lines, dtype=float)[:, None], np.asarray(cells, dtype=float)[None, :]
    covered = box_overlap(lines - line_width / 2, lines + line_width / 2, cells - step / 2, cells + step / 2)
    return covered / step
