"""Gray-code decoding for :mod:`selpath.stages.procam.rectify` and :mod:`selpath.stages.procam.stereo`: the projector
column and row lighting each camera pixel, to sub-pixel, from white, black and every bit with its inverse (the
module docstring of ``rectify`` says how)."""

from __future__ import annotations

import numpy as np

from selpath.pipeline.errors import Problem, StageError


def _gray(value: np.ndarray) -> np.ndarray:
    return value ^ (value >> 1)


def _axis(contrast: np.ndarray, size: int, min_contrast: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One axis's bits (bits, ...) of contrast c = (pattern − inverse) / (white − black) → (sub-pixel position, ok).

    The nearest projector pixel r is the Gray code of the bits' signs. Neighbouring pixels' codes differ in one
    bit, so light split between r and r + f·1 (a pixel seen between two, |f| ≤ ½) dims exactly that bit's contrast
    to |1 − 2f| and leaves the others whole: the position is r + (|c₋| − |c₊|) / 2, c₊ and c₋ the contrasts of the
    bits r shares with its neighbours above and below (exact for a pixel that integrates two neighbours; a
    symmetric blur dims both alike and cancels). One bit may therefore be unclear (|c| < min_contrast: the pixel
    lies on that bit's edge) if it is one the nearest pixel shares with a neighbour; two or more, or another bit:
    undecoded. Returns the position, whether it is decoded, and the code's
    sharpness: the smallest contrast of the bits not shared with a neighbour (1: light from at most two
    neighbouring pixels; less: light spread wider, whose position this model biases)."""
    n = contrast.shape[0]
    weights = 2 ** np.arange(n - 1, -1, -1)
    bits = (contrast > 0).astype(np.int64)
    binary = np.cumsum(bits, axis=0) % 2  # binary-reflected Gray code, most significant first
    nearest = np.tensordot(weights, binary, axes=1)
    ok = (np.sum(np.abs(contrast) < min_contrast, axis=0) <= 1) & (nearest < size)

    def flipped_bit(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # bit index (MSB first) where codes a, b differ
        return n - 1 - np.log2(np.maximum(_gray(a) ^ _gray(b), 1)).astype(np.int64)

    strength = np.abs(contrast)
    take = np.indices(nearest.shape)
    up = np.minimum(nearest + 1, size - 1)
    down = np.maximum(nearest - 1, 0)
    bit_up, bit_down = flipped_bit(nearest, up), flipped_bit(nearest, down)
    c_up = np.where(up > nearest, strength[(bit_up, *take)], 1.0)
    c_down = np.where(down < nearest, strength[(bit_down, *take)], 1.0)
    # (not clipped at 1: a full-contrast bit's noise is symmetric about 1, and clipping it would bias the position)
    position = nearest + np.clip((c_down - c_up) / 2, -0.5, 0.5)
    # the other bits keep their full contrast for light from two neighbours only; light spread wider (global
    # light, a blurred code) dims them too: their smallest contrast says how sharp the pixel's code is
    index = np.arange(n).reshape((n,) + (1,) * nearest.ndim)
    shared = (index == bit_up) | (index == bit_down)
    # the one unclear bit must be an edge of the nearest pixel; any other makes the code a jump, not a split
    ok &= ~np.any((strength < min_contrast) & ~shared, axis=0)
    others = np.where(shared, np.inf, strength)
    sharpness = np.minimum(np.min(others, axis=0), 1.0) if n > 2 else np.ones(nearest.shape)
    return position, ok, sharpness


def _coarse_axis(contrast: np.ndarray, size: int, drop: int, min_contrast: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_axis` on the bits coarser than the camera resolves: without the ``drop`` least significant bits a
    Gray code counts blocks of 2^drop pixels (its top bits are the code of value >> drop), whose centre is returned,
    in projector pixels."""
    kept = contrast.shape[0] - drop
    units, ok, sharpness = _axis(contrast[:kept], -(-size // 2**drop), min_contrast)
    # (the last block may overhang the projector's last pixel: its centre is kept on the projector)
    return np.minimum((units + 0.5) * 2**drop - 0.5, size - 0.5), ok, sharpness


def resolved_drop(projector: int, camera: int) -> int:
    """Least significant Gray-code bits a camera of ``camera`` pixels cannot resolve across ``projector`` pixels: a
    camera pixel spans P / C projector pixels, so bits whose stripes are narrower alias (ceil(log2(P / C)), ≥ 0).

    >>> resolved_drop(720, 1200), resolved_drop(720, 120), resolved_drop(48, 48)
    (0, 3, 0)
    """
    return max(0, int(np.ceil(np.log2(projector / camera) - 1e-9)))


def decode_band(stack: np.ndarray, *, column_bits: int, row_bits: int, shape: tuple[int, int], min_lit: float,
                 min_contrast: float, drop: tuple[int, int]) -> np.ndarray:
    """(..., pattern) frames → (..., 3) projector (col, row) to sub-pixel and the code's sharpness (the smaller of
    the two axes'), NaN where the pixel is not decoded."""
    stack = np.moveaxis(stack.astype(np.float64), -1, 0)
    lit = stack[0] - stack[1]
    finite = np.all(np.isfinite(stack), axis=0)
    ok = finite & (lit >= min_lit)
    with np.errstate(invalid="ignore", divide="ignore"):
        contrast = np.where(ok, (stack[2::2] - stack[3::2]) / np.where(ok, lit, 1.0), 0.0)
    col, col_ok, col_sharp = _coarse_axis(contrast[:column_bits], shape[1], drop[1], min_contrast)
    row, row_ok, row_sharp = _coarse_axis(contrast[column_bits:column_bits + row_bits], shape[0], drop[0],
                                          min_contrast)
    ok &= col_ok & row_ok
    return np.stack([np.where(ok, col, np.nan), np.where(ok, row, np.nan),
                     np.where(ok, np.minimum(col_sharp, row_sharp), np.nan)], axis=-1)


def check_code_count(patterns: int, column_bits: int, row_bits: int) -> None:
    """Refuse a stack that is not white, black and every bit's pair: a truncated one would decode from fewer bits."""
    want = 2 + 2 * (column_bits + row_bits)
    if patterns != want:
        raise StageError(Problem(f"{patterns} patterns; white, black and {column_bits} column and {row_bits} row bits "
                                 f"with their inverses are 2 + 2·({column_bits} + {row_bits}) = {want}", path="image",
                                 fix="capture the whole stack (a killed acquisition resumes where it stopped)"))
