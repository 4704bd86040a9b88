"""Line–shape intervals against independent truth (hypothesis over random convex polygons and ellipses)."""

from __future__ import annotations

import matplotlib.path
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from selpath.geometry.shapes import Ellipse, Ellipsoid, Prism, convex_polygon, segment_length_inside

coords = st.floats(-5, 5, allow_nan=False)


@st.composite
def hull_polygons(draw):
    points = np.array(draw(st.lists(st.tuples(coords, coords), min_size=3, max_size=12)))
    try:
        hull = ConvexHull(points)
    except Exception:  # degenerate (collinear) draws
        return None
    if hull.volume < 0.5:
        return None
    return points[hull.vertices]


@settings(max_examples=40, deadline=None)
@given(hull_polygons(), st.tuples(coords, coords), st.tuples(coords, coords))
def test_polygon_chord_matches_point_sampling(vertices, p, q):
    if vertices is None or np.hypot(p[0] - q[0], p[1] - q[1]) < 1e-3:
        return
    polygon = convex_polygon(vertices[::-1])  # either orientation is accepted
    offsets = np.array([p, q]) @ polygon._normals.T - polygon._offsets
    if (np.abs(offsets) < 1e-6).all(axis=0).any():
        return  # the segment runs along an edge: on the boundary, inside or out is a matter of convention
    p3, q3 = np.array([[*p, 0.0]]), np.array([[*q, 0.0]])
    got = segment_length_inside(Prism(polygon), p3, q3)[0]
    t = np.linspace(0, 1, 100_001)
    pts = np.array(p)[None] + t[:, None] * (np.array(q) - np.array(p))[None]
    want = matplotlib.path.Path(vertices).contains_points(pts).mean() * np.hypot(q[0] - p[0], q[1] - p[1])
    assert got == pytest.approx(want, abs=2e-4 * np.hypot(q[0] - p[0], q[1] - p[1]) + 1e-9)


@settings(max_examples=40, deadline=None)
@given(st.floats(0.2, 4), st.floats(0.2, 4), st.floats(-3, 3), st.tuples(coords, coords), st.floats(0, np.pi))
def test_ellipse_interval_ends_lie_on_the_ellipse(a, b, angle, origin, heading):
    """Both ends satisfy the ellipse equation, normals are unit and point outward."""
    e = Ellipse((0.5, -0.3), (a, b), angle)
    o = np.array([origin])
    d = np.array([[np.cos(heading), np.sin(heading)]])
    iv = e.interval(o, d)
    if not iv.hit[0]:
        assert not e.contains(o + np.linspace(-20, 20, 4001)[:, None] * d).any()
        return
    for t, n in ((iv.t_in, iv.normal_in), (iv.t_out, iv.normal_out)):
        point = o + t[:, None] * d
        m = e._to_unit()
        assert np.sum(((point - e.centre) @ m.T) ** 2) == pytest.approx(1.0, abs=1e-9)
        assert np.linalg.norm(n) == pytest.approx(1.0)
        assert e.contains(point - 1e-6 * n).all() and not e.contains(point + 1e-6 * n).any()


def test_prism_caps_bound_oblique_rays():
    """A ray leaving through the top cap: the interval ends there, with normal +z."""
    prism = Prism(Ellipse((0.0, 0.0), (1.0, 1.0)), (-1.0, 1.0))
    iv = prism.interval(np.array([[0.0, 0.0, 0.0]]), np.array([[0.1, 0.0, 1.0]]))
    assert iv.t_out[0] == pytest.approx(1.0)
    np.testing.assert_allclose(iv.normal_out[0], [0, 0, 1])


def test_non_convex_polygon_is_refused_naming_the_vertex():
    with pytest.raises(ValueError, match=r"not convex: .* at vertex 2 \[1.0, 1.0\]"):
        convex_polygon([(0, 0), (4, 0), (1, 1), (0, 4)])


@settings(max_examples=40, deadline=None)
@given(st.tuples(*[st.floats(0.3, 4)] * 3), st.floats(0, np.pi), st.tuples(coords, coords, coords),
       st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)))
def test_ellipsoid_chords_match_point_sampling_and_normals_the_gradient(semi, angle, origin, heading):
    """The chord inside an ellipsoid equals the share of 200 001 points along the line that it contains; the
    normals are unit, outward and along the gradient of the quadric at each end."""
    solid = Ellipsoid((0.4, -0.2, 0.7), semi, angle)
    d = np.array([heading], float)
    if np.linalg.norm(d) < 1e-3:
        return
    d /= np.linalg.norm(d)
    o = np.array([origin], float)
    iv = solid.interval(o, d)
    t = np.linspace(-30, 30, 200_001)
    inside = solid.contains(o + t[:, None] * d)
    chord = max(float(iv.t_out[0] - iv.t_in[0]), 0.0) if iv.hit[0] else 0.0
    assert chord == pytest.approx(inside.mean() * 60.0, abs=2 * 60.0 / 200_000)
    got = segment_length_inside(solid, o - 30 * d, o + 30 * d)[0]
    assert got == pytest.approx(chord, abs=1e-9)
    if iv.hit[0] and chord > 1e-6:
        for t_end, n, sign in ((iv.t_in, iv.normal_in, -1), (iv.t_out, iv.normal_out, 1)):
            point = o + t_end[:, None] * d
            m = solid._to_unit()
            q = (point - solid.centre) @ m.T
            assert np.sum(q**2) == pytest.approx(1.0, abs=1e-9)
            gradient = q @ m
            np.testing.assert_allclose(n, gradient / np.linalg.norm(gradient), atol=1e-9)
            assert sign * float(n[0] @ d[0]) >= -1e-12  # entering against the normal, leaving along it


def test_ellipsoid_sections_are_the_ellipses_its_points_fill():
    solid = Ellipsoid((0.5, -0.5, 1.0), (3.0, 2.0, 4.0), 0.4)
    for z in (-2.9, 0.0, 1.0, 4.5):
        section = solid.section(z)
        grid = np.stack(np.meshgrid(np.linspace(-4, 5, 181), np.linspace(-4, 3, 141)), axis=-1).reshape(-1, 2)
        want = solid.contains(np.column_stack([grid, np.full(len(grid), z)]))
        np.testing.assert_array_equal(section.contains(grid), want)
    assert solid.section(5.01) is None and solid.section(-3.01) is None
    assert solid.z_range == (-3.0, 5.0)
    q = (solid.surface(32) - solid.centre) @ solid._to_unit().T
    np.testing.assert_allclose(np.sum(q**2, axis=1), 1.0, rtol=1e-12)  # on the surface


def test_a_polygon_clips_many_lines_in_blocks_with_each_lines_own_result():
    """More lines than :data:`CLIP_BLOCK` go in blocks; every line's interval equals that of the line clipped alone
    (to 1e-12: the matrix products round differently by size) and its normals are the same edges', including misses
    and lines that start inside."""
    from selpath.geometry.shapes import CLIP_BLOCK

    rng = np.random.default_rng(3)
    angle = np.sort(rng.uniform(0, 2 * np.pi, 40))
    polygon = convex_polygon(np.c_[np.cos(angle), np.sin(angle)])
    n = 2 * CLIP_BLOCK + 17
    origin, direction = rng.uniform(-2, 2, (n, 2)), rng.normal(size=(n, 2))
    many = polygon.interval(origin, direction)
    assert many.hit.any() and not many.hit.all()
    for k in rng.choice(n, 50, replace=False).tolist() + [0, CLIP_BLOCK - 1, CLIP_BLOCK, n - 1]:
        one = polygon.interval(origin[k:k + 1], direction[k:k + 1])
        for field in ("t_in", "t_out"):
            np.testing.assert_allclose(getattr(many, field)[k], getattr(one, field)[0], rtol=1e-12)
        for field in ("normal_in", "normal_out"):
            np.testing.assert_array_equal(getattr(many, field)[k], getattr(one, field)[0])
    assert polygon.interval(origin, direction, normals=False).normal_in is None
