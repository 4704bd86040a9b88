"""Projector patterns as arrays in [0, 1], shape (projector rows, cols) (§5.3, §5.4.6).

Edges fall on fractional positions and are integrated over each projector pixel, so a line of width
l_w = 40.5 px at l_p = 100.25 px carries exactly 40.5 px of light. Gray codes come from OpenCV contrib's
``cv2.structured_light`` (the well-kept implementation; we only convert its uint8 images).
"""

from __future__ import annotations

import numpy as np


def _coverage(n: int, low: float, high: float) -> np.ndarray:
    """Fraction of each pixel cell [i, i+1) covered by [low, high) (pixel i's centre is at i + ½)."""
    edges = np.arange(n, dtype=float)
    return np.clip(np.minimum(edges + 1, high) - np.maximum(edges, low), 0.0, 1.0)


def white(shape: tuple[int, int]) -> np.ndarray:
    return np.ones(shape)


def vertical_line(shape: tuple[int, int], position: float, width: float) -> np.ndarray:
    """A vertical line centred at projector column ``position`` (l_p, pixel-centre coordinates) of ``width`` l_w."""
    if width <= 0:
        raise ValueError(f"line width must be positive, got {width}")
    rows, cols = shape
    centre = position + 0.5  # pixel i covers [i, i+1): its centre is i + ½
    return np.broadcast_to(_coverage(cols, centre - width / 2, centre + width / 2), (rows, cols)).copy()


def horizontal_line(shape: tuple[int, int], position: float, width: float = 1.0) -> np.ndarray:
    """A horizontal line at projector row ``position`` (for the v_p calibration of §5.3.2)."""
    rows, cols = shape
    centre = position + 0.5
    return np.broadcast_to(_coverage(rows, centre - width / 2, centre + width / 2)[:, None], (rows, cols)).copy()


def checkerboard(shape: tuple[int, int], square: int | tuple[int, int],
                 shift: tuple[int, int] = (0, 0)) -> np.ndarray:
    """A checkerboard of ``square``-pixel squares (or (rows, cols) rectangles) shifted by (rows, cols) pixels
    (the §5.4.6 shifted boards)."""
    rows, cols = shape
    square_rows, square_cols = (square, square) if np.isscalar(square) else square
    r = (np.arange(rows) + shift[0]) // square_rows
    c = (np.arange(cols) + shift[1]) // square_cols
    return ((r[:, None] + c[None, :]) % 2).astype(float)


def gray_code_levels(shape: tuple[int, int]) -> tuple[np.ndarray, int, int]:
    """White, black, then the Gray-code patterns of ``cv2.structured_light`` (each column bit, most significant
    first, followed by its inverse; then each row bit likewise), as uint8 levels (n, rows, cols), with the numbers
    of column and row bits. uint8 keeps a 1280 × 720 projector's 44 patterns at 41 MB (float64: 324 MB)."""
    import cv2

    rows, cols = shape
    generator = cv2.structured_light.GrayCodePattern.create(cols, rows)
    ok, patterns = generator.generate()
    if not ok:
        raise RuntimeError("cv2.structured_light could not generate Gray codes for this projector size")
    column_bits, row_bits = int(np.ceil(np.log2(cols))), int(np.ceil(np.log2(rows)))
    full, empty = np.full(shape, 255, np.uint8), np.zeros(shape, np.uint8)
    return np.stack([full, empty, *patterns]), column_bits, row_bits


def gray_codes(shape: tuple[int, int], *, columns_only: bool = False) -> np.ndarray:
    """The Gray-code patterns (and their inverses) of ``cv2.structured_light``: (n, rows, cols) in {0, 1}.

    ``columns_only`` keeps the patterns that code the column (constant along rows), which is what a
    rolling-shutter rig with row-wise illumination can project without tearing.
    """
    stack = gray_code_levels(shape)[0][2:].astype(float) / 255.0
    if columns_only:
        stack = stack[np.ptp(stack, axis=1).max(axis=1) == 0]
    return stack
