"""Line–shape intervals against independent truth (hypothesis over random convex polygons and ellipses)."""

from __future__ import annotations

import matplotlib.path
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from devices.sim.shapes import Ellipse, Prism, convex_polygon, segment_length_inside

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
