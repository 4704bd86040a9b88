"""Projector patterns (§5.3, §5.4.6) against brute-force definitions and the binary-reflected Gray code."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from selpath.devices import patterns


def supersampled_line(n: int, centre: float, width: float, factor: int = 1000) -> np.ndarray:
    """Brute force: the fraction of ``factor`` sub-pixel samples of each cell [i, i+1) inside the line."""
    samples = (np.arange(n * factor) + 0.5) / factor
    inside = np.abs(samples - centre) < width / 2
    return inside.reshape(n, factor).mean(axis=1)


@settings(max_examples=40, deadline=None)
@given(position=st.floats(-5.0, 70.0), width=st.floats(0.1, 30.0))
def test_vertical_line_integrates_its_edges_over_each_pixel(position, width):
    line = patterns.vertical_line((3, 64), position, width)
    expected = supersampled_line(64, position + 0.5, width)
    np.testing.assert_allclose(line, np.broadcast_to(expected, (3, 64)), atol=2e-3)  # 1/1000 sampling, 2 edges
    lit = line[0].sum()
    inside = min(position + 0.5 + width / 2, 64) - max(position + 0.5 - width / 2, 0)
    assert lit == pytest.approx(max(inside, 0.0), abs=1e-9)  # exactly the width where the line fits


def test_a_line_of_odd_integer_width_lights_whole_pixels_around_its_centre():
    np.testing.assert_array_equal(patterns.vertical_line((1, 9), 4.0, 3.0)[0], [0, 0, 0, 1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(patterns.vertical_line((1, 6), 2.5, 2.0)[0], [0, 0, 1, 1, 0, 0])  # l_p between two
    np.testing.assert_allclose(patterns.vertical_line((1, 6), 2.0, 2.0)[0], [0, 0.5, 1, 0.5, 0, 0])  # even on one


def test_horizontal_line_is_the_transposed_vertical_line():
    np.testing.assert_allclose(patterns.horizontal_line((40, 7), 12.3, 2.5),
                               patterns.vertical_line((7, 40), 12.3, 2.5).T)


def test_non_positive_width_is_refused():
    with pytest.raises(ValueError, match="width must be positive"):
        patterns.vertical_line((4, 4), 1.0, 0.0)


@settings(max_examples=30, deadline=None)
@given(square=st.tuples(st.integers(1, 9), st.integers(1, 9)), shift=st.tuples(st.integers(0, 20), st.integers(0, 20)))
def test_checkerboard_matches_its_definition_and_shifts(square, shift):
    board = patterns.checkerboard((30, 40), square, shift)
    brute = np.array([[((r + shift[0]) // square[0] + (c + shift[1]) // square[1]) % 2 for c in range(40)]
                      for r in range(30)], dtype=float)
    np.testing.assert_array_equal(board, brute)
    # shifting by one square along either axis gives the complementary board (the §5.4.6 pair)
    moved = patterns.checkerboard((30, 40), square, (shift[0] + square[0], shift[1]))
    np.testing.assert_array_equal(board + moved, np.ones((30, 40)))


@pytest.mark.parametrize("shape", [(6, 20), (12, 64), (720, 1280)])
def test_gray_codes_decode_to_every_column_and_row(shape):
    rows, cols = shape
    stack = patterns.gray_codes(shape)
    positive, negative = stack[0::2], stack[1::2]
    np.testing.assert_array_equal(positive + negative, 1.0)  # each pattern comes with its inverse
    column_bits, row_bits = int(np.ceil(np.log2(cols))), int(np.ceil(np.log2(rows)))
    assert positive.shape[0] == column_bits + row_bits

    def decode(bits):  # binary-reflected Gray code, most significant bit first → integer
        binary = np.cumsum(bits, axis=0) % 2  # b_i = g_0 ⊕ … ⊕ g_i
        return np.sum(binary * (2 ** np.arange(bits.shape[0] - 1, -1, -1))[:, None, None], axis=0)

    column = decode(positive[:column_bits].astype(int))
    row = decode(positive[column_bits:].astype(int))
    np.testing.assert_array_equal(column, np.broadcast_to(np.arange(cols), shape))
    np.testing.assert_array_equal(row, np.broadcast_to(np.arange(rows)[:, None], shape))


def test_column_only_gray_codes_are_constant_along_rows():
    stack = patterns.gray_codes((12, 64), columns_only=True)
    assert stack.shape[0] == 2 * 6
    np.testing.assert_array_equal(stack, np.broadcast_to(stack[:, :1, :], stack.shape))
