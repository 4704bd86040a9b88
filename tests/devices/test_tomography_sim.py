"""The scene simulator against analytic truth: chords through disks and polygons, Monte Carlo limits."""

from __future__ import annotations

import matplotlib.path
import numpy as np
import pytest
from scipy.ndimage import binary_erosion

import selpath.devices.sim.tomography as tomo
from selpath.devices.sim.scene import Scene

R = 10.0  # mm, radius of the object
DISK = {"kind": "cylinder", "radius": "2.5 mm", "centre": ["3 mm", "2 mm"]}
TRIANGLE = {"kind": "polygon", "vertices": [["-4 mm", "-3 mm"], ["1 mm", "-4 mm"], ["-1 mm", "2 mm"]]}


def scene(camera: dict, light: str = "sheet", theta_l: float = 60.0, inclusion: dict = DISK, sigma: float = 0.2,
          **extra) -> Scene:
    return Scene.model_validate({
        "scene": "test",
        "object": {"shape": {"kind": "cylinder", "radius": f"{R} mm"}, "height": "40 mm",
                   "medium": {"sigma": "0.01 /mm"},
                   "inclusions": [{"shape": inclusion, "sigma": f"{sigma} /mm"}]},
        "light": {"kind": light, "angle": f"{theta_l} deg", "distance": "300 mm", "height": "0 mm"},
        "camera": camera,
    } | extra)


ORTHO = {"model": "orthographic", "rows": 5, "cols": 81, "pixel_size": "0.3 mm"}
PERSPECTIVE = {"model": "perspective", "rows": 5, "cols": 81, "distance": "60 mm", "focal_length": "150 px"}


def absorption(s: Scene, angle: float) -> np.ndarray:
    """A = log E_reference − log E_target, NaN off the object."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.log(tomo.straight_path(s, angle, reference=True)) - np.log(tomo.straight_path(s, angle,
                                                                                                 reference=False))
    return np.where(tomo.silhouette(s, angle), out, np.nan)


def rotate(p, phi_deg):
    a = np.deg2rad(phi_deg)
    return np.array([np.cos(a) * p[0] - np.sin(a) * p[1], np.sin(a) * p[0] + np.cos(a) * p[1]])


def exit_point_closed_form(camera: dict, col: int) -> np.ndarray:
    """Where pixel column ``col`` of the middle row sees the disk of radius R (lab frame, x–y)."""
    cx = (camera["cols"] - 1) / 2
    if camera["model"] == "orthographic":
        x = (col - cx) * 0.3
        return np.array([x, -np.sqrt(R**2 - x**2)]) if abs(x) < R else None
    d, f = 60.0, 150.0
    u = np.array([(col - cx) / f, 1.0])
    origin = np.array([0.0, -d])
    a, b, c = u @ u, 2 * origin @ u, origin @ origin - R**2
    disc = b * b - 4 * a * c
    return origin + (-b - np.sqrt(disc)) / (2 * a) * u if disc > 0 else None


def disk_chord(p, q, centre, radius):
    """Chord of the line through p, q in a disk (the disk lies between p and q)."""
    u = (q - p) / np.linalg.norm(q - p)
    w = centre - p
    d2 = w @ w - (w @ u) ** 2
    return 2 * np.sqrt(max(radius**2 - d2, 0.0))


def sampled_chord(p, q, vertices, n=200_001):
    t = np.linspace(0, 1, n)
    points = p[None] + t[:, None] * (q - p)[None]
    inside = matplotlib.path.Path(vertices).contains_points(points)
    return inside.mean() * np.linalg.norm(q - p)


@pytest.mark.parametrize("camera", [ORTHO, PERSPECTIVE], ids=["orthographic", "perspective"])
@pytest.mark.parametrize("phi", [0.0, 37.0, 200.0])
def test_sheet_absorption_is_the_disk_chord(camera, phi):
    """Every row of a light-sheet frame holds σ·chord of the entry→exit line through the inclusion (1e-9)."""
    s = scene(camera)
    got = absorption(s, phi)
    entry = R * np.array([np.sin(np.deg2rad(60.0)), np.cos(np.deg2rad(60.0))])
    centre = rotate((3.0, 2.0), phi)
    checked = 0
    for col in range(camera["cols"]):
        exit_ = exit_point_closed_form(camera, col)
        if exit_ is None:
            assert np.isnan(got[:, col]).all()
            continue
        want = 0.2 * disk_chord(entry, exit_, centre, 2.5)
        np.testing.assert_allclose(got[:, col], want, atol=1e-9)
        checked += want > 0
    assert checked > 1  # the inclusion's shadow is in view


@pytest.mark.parametrize("camera", [ORTHO, PERSPECTIVE], ids=["orthographic", "perspective"])
def test_sheet_absorption_through_a_polygon_matches_sampling(camera):
    """Polygon inclusion: Cyrus–Beck chords agree with brute-force point sampling (to 1e-4 mm)."""
    phi = 25.0
    s = scene(camera, inclusion=TRIANGLE, sigma=1.0)
    got = absorption(s, phi)
    entry = R * np.array([np.sin(np.deg2rad(60.0)), np.cos(np.deg2rad(60.0))])
    vertices = np.array([rotate(v, phi) for v in [(-4, -3), (1, -4), (-1, 2)]])
    hits = 0
    for col in range(0, camera["cols"], 4):
        exit_ = exit_point_closed_form(camera, col)
        if exit_ is None:
            continue
        want = sampled_chord(entry, exit_, vertices)
        assert got[2, col] == pytest.approx(want, abs=1e-4)
        hits += want > 0
    assert hits > 3


def test_beam_paths_are_three_dimensional():
    """A narrow beam at z = 0 lights rows above and below along oblique rays: chord × (3-D / 2-D length)."""
    camera = {"model": "orthographic", "rows": 9, "cols": 41, "pixel_size": "0.5 mm"}
    s = scene(camera, light="beam", theta_l=90.0)
    phi = 10.0
    got = absorption(s, phi)
    entry = np.array([R, 0.0, 0.0])
    centre = rotate((3.0, 2.0), phi)
    for row in (0, 4, 8):
        z = (4 - row) * 0.5
        for col in range(0, 41, 3):
            x = (col - 20) * 0.5
            if abs(x) >= R:
                continue
            exit_ = np.array([x, -np.sqrt(R**2 - x**2), z])
            flat = disk_chord(entry[:2], exit_[:2], centre, 2.5)
            stretch = np.linalg.norm(exit_ - entry) / np.linalg.norm(exit_[:2] - entry[:2])
            assert got[row, col] == pytest.approx(0.2 * flat * stretch, abs=1e-9)


def test_reference_minus_target_is_zero_without_inclusions():
    """Invariant: a uniform medium cancels exactly in A (the BTDF and 1/L factors cancel too)."""
    s = scene(PERSPECTIVE, sigma=0.0)
    got = absorption(s, 123.0)
    assert np.nanmax(np.abs(got)) < 1e-12
    assert np.isfinite(got).sum() > 100


def mc_scene(sigma_s: float, photons: int) -> Scene:
    return Scene.model_validate({
        "scene": "mc",
        "object": {"shape": {"kind": "cylinder", "radius": "1 mm"}, "height": "4 mm",
                   "inclusions": [{"shape": {"kind": "cylinder", "radius": "0.3 mm", "centre": ["0.3 mm", "0.2 mm"]},
                                   "sigma": "3 /mm"}]},
        "light": {"kind": "beam", "angle": "45 deg", "distance": "30 mm"},
        "camera": {"model": "orthographic", "rows": 24, "cols": 48, "pixel_size": "0.05 mm"},
        "effects": {"scattering": {"sigma_s": f"{sigma_s} /mm", "photons": photons, "seed": 3}},
    })


def test_monte_carlo_without_scattering_converges_to_straight_paths():
    """σ_s → 0: the Monte Carlo frame equals the straight-path frame within its own standard error.

    Compared on pixels two or more inside the silhouette (edge pixels straddle the contour). Expected:
    mean z² ≈ 1 (±0.05 for ~700 pixels); allowed 0.7–1.35 and no |z| above 5.
    """
    s = mc_scene(1e-6, 2_000_000)
    straight = tomo.straight_path(s, 30.0, reference=True)
    mc = tomo.monte_carlo(s, 30.0, reference=True)
    inner = binary_erosion(tomo.silhouette(s, 30.0), iterations=2)
    z = (mc.image[inner] - straight[inner]) / mc.std_error[inner]
    assert 0.7 < np.mean(z**2) < 1.35
    assert np.max(np.abs(z)) < 5
    assert mc.mean_events < 1e-3  # essentially no photon scattered


def blur_measures(sigma_s: float) -> tuple[float, float]:
    """How much of A's mass lies in the inclusion's straight-path shadow, and A's correlation with the
    sharp (straight-path) projection: both 1-ish when sharp, both fall as scattering blurs."""
    s = mc_scene(sigma_s, 300_000)
    sharp = np.log(tomo.straight_path(s, 30.0, reference=True) + 1e-300) - np.log(
        tomo.straight_path(s, 30.0, reference=False) + 1e-300)
    inner = binary_erosion(tomo.silhouette(s, 30.0), iterations=2)
    shadow = inner & (sharp > 0.5 * sharp[inner].max())
    ref, tgt = (tomo.monte_carlo(s, 30.0, reference=r).image for r in (True, False))
    a = np.log(np.maximum(ref, 1e-9)) - np.log(np.maximum(tgt, 1e-9))
    return float(a[shadow].sum() / np.abs(a[inner]).sum()), float(np.corrcoef(a[inner], sharp[inner])[0, 1])


@pytest.mark.slow  # default job over its 8 minutes: run in the slow job
def test_scattering_blurs_the_projection_monotonically():
    """§4.4.4: the inclusion's shadow spreads as σ_s grows (≈0, 1, 2, 3, 5 /mm), in both measures.

    Measured gaps between neighbours are ≥ 0.03 (mass) and ≥ 0.1 (correlation); the change with the
    photon count (300k vs 600k) is below 0.01 and 0.08.
    """
    mass, correlation = zip(*(blur_measures(s) for s in (1e-6, 1.0, 2.0, 3.0, 5.0)), strict=True)
    assert all(a > b for a, b in zip(mass, mass[1:], strict=False)), mass
    assert all(a > b for a, b in zip(correlation, correlation[1:], strict=False)), correlation
    assert correlation[0] > 0.999 and correlation[-1] < 0.7


def test_a_scene_without_scattering_never_runs_monte_carlo(monkeypatch):
    """Cost follows the effects: without effects.scattering the Monte Carlo code path is never entered."""
    def forbidden(*args, **kwargs):
        raise AssertionError("Monte Carlo ran for a scene without scattering")

    monkeypatch.setattr(tomo, "monte_carlo", forbidden)
    s = scene(PERSPECTIVE, light="beam")
    assert tomo.lit_frame(s, 0.0, "target").max() > 0
    with pytest.raises(AssertionError, match="Monte Carlo ran"):
        tomo.lit_frame(mc_scene(1.0, 10), 0.0, "target")


def test_monte_carlo_frames_do_not_depend_on_the_threads():
    """Each photon batch has its own random stream, seeded by its index: one thread and two trace the same frame,
    bit for bit."""
    s = mc_scene(2.0, 100_000)
    one, two = (tomo.monte_carlo(s, 30.0, reference=False, workers=w) for w in (1, 2))
    np.testing.assert_array_equal(one.image, two.image)
    np.testing.assert_array_equal(one.std_error, two.std_error)
    assert one.mean_events == two.mean_events > 0.5
