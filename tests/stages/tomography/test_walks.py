"""Photon walks in a slice's prism (stages/tomography/_walks.py): exits, free paths, and the reweighting to another
σ_s against walks traced at it."""

from __future__ import annotations

import numpy as np

from selpath.geometry.rig import OrthographicCamera, RigGeometry
from selpath.geometry.shapes import Ellipse, Prism
from selpath.stages.tomography._walks import beam_entry, exit_weights, random_walks, walk_body, walk_weights

CIRCLE = Prism(Ellipse((0.0, 0.0), (1.0, 1.0), 0.0))
ENTRY, NORMAL = np.array([-1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])


def test_random_walks_leave_through_the_surface_with_exponential_free_paths():
    """Walks in a prism (circle, radius 1): every exit lies on the side wall (|r| = 1 within 1e-9) with the outward
    normal there; scatterings per length travelled estimate σ_s within 4 standard errors (free paths exponential,
    the last one cut by the exit: the censored estimate); σ_s → 0 gives one straight step from the entry to the exit."""
    body = Prism(Ellipse((0.0, 0.0), (1.0, 1.0), 0.0))
    entry, normal = np.array([-1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])
    walks = random_walks(body, entry, normal, 2.0, 4000, np.random.default_rng(1))
    exits = walks.exit_point
    assert len(exits) == 4000
    np.testing.assert_allclose(np.hypot(exits[:, 0], exits[:, 1]), 1.0, atol=1e-9)
    np.testing.assert_allclose(walks.exit_normal[:, :2], exits[:, :2], atol=1e-9)
    steps = np.linalg.norm(np.diff(walks.vertices, axis=1), axis=2)
    scatterings = np.isfinite(walks.vertices[..., 0]).sum() - 2 * len(exits)  # vertices less entries and exits
    assert scatterings > 4000
    rate = scatterings / np.nansum(steps)  # events per length travelled: the censored exponential's estimate
    assert abs(rate - 2.0) < 4 * 2.0 / np.sqrt(scatterings)
    straight = random_walks(body, entry, normal, 1e-9, 200, np.random.default_rng(2))
    assert straight.vertices.shape[1] == 2
    np.testing.assert_allclose(straight.vertices[:, 0], np.tile(entry, (200, 1)), atol=1e-8)


def test_a_walks_scatterings_and_length_are_those_of_its_vertices_recorded_or_not():
    """events = the walk's vertices less its launch and exit; length = the sum of its segments (1e-12); tracing
    without the vertices draws the same walks (same exits, scatterings and lengths, bit for bit)."""
    walks = random_walks(CIRCLE, ENTRY, NORMAL, 3.0, 500, np.random.default_rng(4))
    finite = np.isfinite(walks.vertices[..., 0])
    np.testing.assert_array_equal(walks.events, finite.sum(axis=1) - 2)
    np.testing.assert_allclose(walks.length, np.nansum(np.linalg.norm(np.diff(walks.vertices, axis=1), axis=2),
                                                       axis=1), rtol=1e-12)
    light = random_walks(CIRCLE, ENTRY, NORMAL, 3.0, 500, np.random.default_rng(4), record=False)
    assert light.vertices is None
    for field in ("exit_point", "exit_normal", "events", "length"):
        np.testing.assert_array_equal(getattr(light, field), getattr(walks, field))


def test_walks_traced_at_one_sigma_s_and_weighted_count_as_walks_traced_at_another():
    """Walks at σ_0 = 2 weighted by :func:`walk_weights` to σ_s = 1.5 and 3: their weights average 1 (every walk
    leaves), and the weighted histogram of the exits' polar angle (8 bins) matches walks traced at σ_s, per bin
    within 4 combined standard errors; the weight at σ_0 itself is 1."""
    traced = random_walks(CIRCLE, ENTRY, NORMAL, 2.0, 40_000, np.random.default_rng(5), record=False)
    np.testing.assert_allclose(walk_weights(traced, 2.0, 2.0), 1.0, rtol=1e-12)
    edges = np.linspace(-np.pi, np.pi, 9)

    def histogram(walks, weights):
        angle = np.arctan2(walks.exit_point[:, 1], walks.exit_point[:, 0])
        return (np.histogram(angle, edges, weights=weights)[0] / len(weights),
                np.sqrt(np.histogram(angle, edges, weights=weights**2)[0]) / len(weights))

    for sigma_s in (1.5, 3.0):
        weights = walk_weights(traced, sigma_s, 2.0)
        assert abs(weights.mean() - 1.0) < 4 * weights.std() / np.sqrt(len(weights))
        direct = random_walks(CIRCLE, ENTRY, NORMAL, sigma_s, 40_000, np.random.default_rng(6), record=False)
        got, got_se = histogram(traced, weights)
        want, want_se = histogram(direct, np.ones(len(direct.events)))
        assert np.all(np.abs(got - want) < 4 * np.hypot(got_se, want_se)), (sigma_s, got, want)


def test_the_walks_contour_is_simplified_within_its_tolerance_and_the_beam_enters_on_it():
    """A 360-vertex circle of radius 1 (pixel 0.02 at the axis): the walks' contour keeps fewer vertices, all of
    them the contour's, and no point of the original is farther than 0.05 pixel from it; the beam (θ_l = 45°) at
    stage angle 0 enters the circle where its ray meets it, with the outward normal there."""
    angle = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    contour = np.c_[np.cos(angle), np.sin(angle)]
    geometry = RigGeometry(OrthographicCamera(rows=10, cols=100, pixel_size=0.02), 45.0, light_distance=30.0)
    body = walk_body(contour, geometry)
    kept = np.asarray(body.shape.vertices)
    assert 3 <= len(kept) < 200
    assert np.isin(kept.view([("x", float), ("y", float)]), contour.copy().view([("x", float), ("y", float)])).all()
    normals, offsets = body.shape.half_planes
    assert (contour @ normals.T - offsets).max() <= 0.05 * 0.02 + 1e-12
    entry, normal = beam_entry(CIRCLE, geometry, 0.0, 0.25)
    np.testing.assert_allclose(entry, [np.sin(np.pi / 4), np.cos(np.pi / 4), 0.25], atol=1e-12)
    np.testing.assert_allclose(normal, [np.sin(np.pi / 4), np.cos(np.pi / 4), 0.0], atol=1e-12)


def test_next_event_weights_predict_where_the_walks_leave():
    """Eight regions of the circle prism's wall (0.4 rad × 0.4 tall about z = 0, all around), each tiled by 256
    patches of 0.025 (a 25th of the mean free path): the next-event weights of 2 000 recorded walks
    (:func:`exit_weights`), summed over a region's patches, estimate the share of 400 000 walks that leave through it,
    within 4 combined standard errors; and the launch sends light straight only where its flight is inward."""
    sigma_s, tile, span = 1.5, 0.025, 0.4
    centres = np.linspace(-np.pi, np.pi, 8, endpoint=False) + np.pi / 8
    offsets = (np.arange(16) + 0.5) * tile - span / 2
    phi = (centres[:, None, None] + offsets[None, :, None] + 0 * offsets[None, None, :]).ravel()
    z = np.broadcast_to(offsets[None, None, :], (8, 16, 16)).ravel()
    points, normals = np.c_[np.cos(phi), np.sin(phi), z], np.c_[np.cos(phi), np.sin(phi), 0 * z]
    walks = random_walks(CIRCLE, ENTRY, NORMAL, sigma_s, 2000, np.random.default_rng(8))
    walk, vertex, weights = exit_weights(walks, NORMAL, points, normals, np.full(len(z), tile**2), sigma_s)
    per_walk = np.zeros((2000, 8))
    np.add.at(per_walk, walk, weights.reshape(len(walk), 8, 256).sum(axis=2))  # each walk's expected exits
    predicted, predicted_se = per_walk.mean(axis=0), per_walk.std(axis=0) / np.sqrt(2000)
    direct = random_walks(CIRCLE, ENTRY, NORMAL, sigma_s, 400_000, np.random.default_rng(9), record=False)
    angle = np.arctan2(direct.exit_point[:, 1], direct.exit_point[:, 0])
    near = np.abs(np.angle(np.exp(1j * (angle[:, None] - centres[None, :])))) < span / 2
    share = (near & (np.abs(direct.exit_point[:, 2:3]) < span / 2)).mean(axis=0)
    share_se = np.sqrt(share * (1 - share) / 400_000)
    assert share.min() > 0.003  # the far side gets light too (after scatterings)
    assert np.all(np.abs(predicted - share) < 4 * np.hypot(predicted_se, share_se)), (predicted, share)
    launch = weights[vertex == 0]
    toward = points[None, :, :2] - walks.vertices[walk[vertex == 0], 0][:, None, :2]
    assert np.all(launch[np.einsum("mtj,j->mt", toward, -NORMAL[:2]) <= 0] == 0)
