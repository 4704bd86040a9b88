"""The projector–camera simulator: time integration against the analytic illumination model, the Fig. 30
behaviour, effects cost, pattern handling, tiles and determinism."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from selpath.devices import patterns
from selpath.devices.sim import procam_lobes as lobes
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene

SMALL = {"camera_rows": 80, "camera_cols": 96, "projector_rows": 48, "projector_cols": 96, "bits": None}


def scene(objects=(), background=None, **rig) -> ProcamScene:
    return ProcamScene.model_validate({"scene": "test", "background": background or {"albedo": 0.5},
                                       "objects": list(objects), "rig": SMALL | rig})


MIXED = [
    {"name": "candle", "region": {"kind": "rectangle", "x": [0.1, 0.45], "y": [0.2, 0.8]}, "albedo": 0.9,
     "effects": {"subsurface": {"width": "4 px", "fraction": 0.6}}},
    {"name": "page", "region": {"kind": "rectangle", "x": [0.5, 0.95], "y": [0.1, 0.9]}, "albedo": 0.8,
     "effects": {"diffuse_interreflection": {"corner_x": 0.7, "strength": 0.3},
                 "specular_interreflection": {"centre": [0.7, 0.5], "reach": 0.25,
                                              "displacement": ["6 px", "20 px"], "strength": 0.5}}},
    {"name": "glass", "region": {"kind": "disk", "centre": [0.3, 0.5], "radius": 0.1}, "albedo": 0.05,
     "effects": {"refraction": {"centre": [0.3, 0.5], "transmittance": 0.7}}},
]
OFFSETS = np.arange(-60, 61)


def truth(s: ProcamScene, dv=OFFSETS, du=None) -> np.ndarray:
    return np.concatenate([tr.truth_tile(s, t, dv, du) for t in tr.tiles(s)], axis=-1)


def box_weights(rig, delay, exposure, offsets=OFFSETS):
    """The analytic illumination (Eq. 32–33 with fractional edges, widened by t_p), written independently of
    the simulator: the overlap of [oτ − t_p/2, oτ + t_p/2] with [t_d − t_e/2, t_d + t_e/2], over t_p."""
    tau, tp, d = rig.row_period, rig.line_time, delay + rig.sync_offset
    lo = np.maximum(offsets * tau - tp / 2, d - exposure / 2)
    hi = np.minimum(offsets * tau + tp / 2, d + exposure / 2)
    return np.clip(hi - lo, 0, None) / tp


@settings(max_examples=25, deadline=None)
@given(delay=st.floats(-600, 600), exposure=st.floats(5, 900), line_time=st.floats(10, 60),
       offset=st.floats(-40, 40))
def test_time_integration_equals_the_analytic_box_model(delay, exposure, line_time, offset):
    """Tolerance: float32 rounding of the frame (relative 1e-6 of the brightest pixel)."""
    s = scene(MIXED, line_time=f"{line_time} us", sync_offset=f"{offset} us")
    image = tr.render_frame(s, delay, exposure)
    predicted = s.rig.intensity * (box_weights(s.rig, delay, exposure) @ truth(s)).reshape(image.shape)
    assert np.abs(image - predicted).max() <= 1e-6 * max(1.0, float(np.abs(predicted).max())) + 1e-4


def test_brute_force_time_sampling_agrees_with_the_interval_overlap():
    """Independent check of the time integral: sample 200 000 instants, mark which projector row is lit and
    whether camera row s exposes, and count (tolerance: 2 samples per row period)."""
    rig = scene(line_time="30 us").rig
    delay, exposure, s = 55.0, 140.0, 20
    t = np.linspace(-2000, 4000, 200_001)
    dt = t[1] - t[0]
    centre = s * rig.row_period + rig.line_time / 2 + delay
    exposing = np.abs(t - centre) <= exposure / 2
    for o in range(-3, 15):
        v = s + o
        lit = (t >= v * rig.row_period) & (t < v * rig.row_period + rig.line_time)
        sampled = np.sum(lit & exposing) * dt / rig.line_time
        exact = tr.exposure_overlap(rig, s, v, delay, exposure)
        assert abs(sampled - exact) <= 2 * dt / rig.line_time


def test_delay_zero_short_exposure_is_the_epipolar_image_and_large_delay_loses_the_direct_light():
    direct_only = scene([{"name": "book", "region": {"kind": "rectangle", "x": [0.2, 0.8], "y": [0.2, 0.8]},
                          "albedo": 0.9}])
    rig = direct_only.rig
    epipolar = tr.render_frame(direct_only, 0.0, rig.line_time)
    t0 = truth(direct_only, np.array([0]))[0].reshape(epipolar.shape)  # Eq. 35: T at offset 0
    np.testing.assert_allclose(epipolar, rig.intensity * t0, rtol=1e-6)
    assert epipolar.min() > 0
    late = tr.render_frame(direct_only, 10 * rig.row_period, 4 * rig.row_period)  # t_d > t_e/2 + t_p/2
    assert np.all(late == 0.0)
    # with subsurface scattering the late frame keeps the indirect light (Fig. 30(c))
    candle = scene(MIXED[:1])
    assert tr.render_frame(candle, 10 * rig.row_period, 4 * rig.row_period).max() > 1.0


def test_wider_exposure_gathers_a_wider_band_of_indirect_light():
    s = scene(MIXED[:1])
    narrow = tr.render_frame(s, 170.0, 85.0)
    wide = tr.render_frame(s, 170.0, 340.0)
    assert wide.sum() > 2 * narrow.sum()


def test_only_named_effects_run():
    calls: dict[str, int] = {}

    def counted(name):
        def wrapper(*args):
            calls[name] = calls.get(name, 0) + 1
            return lobes.EFFECTS[name](*args)
        return wrapper

    table = {name: counted(name) for name in lobes.EFFECTS}
    direct = scene([{"name": "book", "region": {"kind": "rectangle", "x": [0.2, 0.8], "y": [0.2, 0.8]},
                     "albedo": 0.9}])
    tr.render_frame(direct, 0.0, 170.0, effects=table)
    tr.truth_tile(direct, next(tr.tiles(direct)), OFFSETS, effects=table)
    assert calls == {}
    tr.render_frame(scene(MIXED), 0.0, 170.0, effects=table)
    assert set(calls) == set(lobes.EFFECTS)


@pytest.mark.slow  # 11 s: in the slow job, so the default job keeps its 8-minute budget
def test_full_transport_with_a_vertical_line_matches_the_separable_model():
    s = scene(MIXED)
    rig = s.rig
    du = np.arange(-80, 81)
    full = truth(s, OFFSETS, du)  # (du, dv, P)
    line, width, delay, exposure = 40.0, 6.0, 34.0, 170.0
    image = tr.render_frame(s, delay, exposure, patterns.vertical_line((rig.projector_rows, rig.projector_cols),
                                                                       line, width))
    profile = patterns.vertical_line((1, rig.projector_cols), line, width)[0]
    tiles = list(tr.tiles(s))
    u_direct = np.concatenate([lobes.tile_lobes(s, t)[1] for t in tiles])
    u = u_direct[None, :] + du[:, None]
    lit = np.where((u >= 0) & (u < rig.projector_cols), profile[np.clip(u, 0, rig.projector_cols - 1)], 0.0)
    vertical = np.einsum("k,ukp->up", box_weights(rig, delay, exposure), full)
    predicted = rig.intensity * np.sum(lit * vertical, axis=0).reshape(image.shape)
    np.testing.assert_allclose(image, predicted, atol=1e-3 * predicted.max())
    # the plane-to-ray truth is the full transport summed over du (less the broad inter-reflection lobes'
    # tails beyond the ±80 px du grid: below 2e-4 of a unit transport)
    np.testing.assert_allclose(full.sum(axis=0), truth(s), atol=2e-4)


@pytest.mark.parametrize("shutter", ["rolling", "global"])
def test_a_checkerboard_renders_as_the_sum_of_its_squares(shutter):
    """Brute force, independent of the factorisation: a checkerboard is the sum of its white squares, each a
    separable rectangle rendered alone (22 renders); rendering is linear in the pattern before the sensor, so the
    board rendered at once (its two rank-1 terms) must equal that sum, pixel by pixel. Tolerance: float32 frames
    summed 22 times, 2e-5 of the peak."""
    s = scene(MIXED)
    shape = (s.rig.projector_rows, s.rig.projector_cols)
    board = patterns.checkerboard(shape, 12, shift=(5, 3))
    assert len(tr.pattern_terms(s.rig, board)) == 2
    delay, exposure = (-100.0, 2000.0) if shutter == "global" else (0.0, 340.0)
    dark = s.rig.dark_level
    whole = tr.render_frame(s, delay, exposure, board, shutter=shutter) - dark
    rows, cols = (np.arange(n) for n in shape)
    total = np.zeros_like(whole, dtype=np.float64)
    squares = 0
    for r0 in range(-5, shape[0], 12):
        for c0 in range(-3, shape[1], 12):
            square = np.outer((rows >= r0) & (rows < r0 + 12), (cols >= c0) & (cols < c0 + 12)).astype(float)
            if (square * board).any():
                total += tr.render_frame(s, delay, exposure, square, shutter=shutter) - dark
                squares += 1
    assert squares == 22 and whole.max() > 10
    np.testing.assert_allclose(whole, total, rtol=0, atol=2e-5 * whole.max())


def test_any_pattern_renders_as_its_rank_one_terms_or_is_refused_naming_its_residual():
    """A rank-3 pattern renders exactly as the sum of its three (non-negative) separable terms rendered alone; a
    random full-rank one needs more terms than allowed and is refused, naming its residual; at a stated tolerance
    it renders approximately: the frame's error is the render of the dropped terms P − P_k (‖P − P_k‖_F ≤ 0.45
    ‖P‖_F here), and its relative norm stays below that share."""
    s = scene(MIXED)
    rng = np.random.default_rng(4)
    factors = [(rng.uniform(0, 1, s.rig.projector_rows), rng.uniform(0, 1, s.rig.projector_cols)) for _ in range(3)]
    low_rank = sum(np.outer(b, a) for b, a in factors) / 3
    assert len(tr.pattern_terms(s.rig, low_rank)) == 3
    dark = s.rig.dark_level
    each = sum(tr.render_frame(s, 0.0, 340.0, np.outer(b, a) / 3) - dark for b, a in factors)
    np.testing.assert_allclose(tr.render_frame(s, 0.0, 340.0, low_rank) - dark, each, rtol=0, atol=1e-5 * each.max())
    noise = rng.uniform(0, 1, (s.rig.projector_rows, s.rig.projector_cols))
    with pytest.raises(ValueError, match=r"needs \d+ rank-1 terms to render within 1e-09 of its norm; at 32 terms its "
                                         r"residual is [\d.e+-]+ of it"):
        tr.render_frame(s, 0.0, 340.0, noise)
    exact = tr.render_frame(s, 0.0, 340.0, noise, max_terms=48) - dark
    rough = tr.render_frame(s, 0.0, 340.0, noise, pattern_rtol=0.45) - dark
    assert len(tr.pattern_terms(s.rig, noise, rtol=0.45)) == 5
    error = np.linalg.norm(rough - exact) / np.linalg.norm(exact)  # measured 0.38: the transport smooths P − P_k
    assert 0 < error < 0.45


def test_noise_and_jitter_are_deterministic_per_capture_and_only_when_named():
    clean = tr.render_frame(scene(MIXED), 0.0, 170.0)
    noisy = scene(MIXED, noise={"gain": 1.0, "read_std": 2.0}, bits=12)
    a, b = tr.render_frame(noisy, 0.0, 170.0), tr.render_frame(noisy, 0.0, 170.0)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, tr.render_frame(noisy, 17.0, 170.0))
    assert np.all(a == np.round(a))
    # shot + read noise: var = signal/gain·gain² + read² (gain 1), pooled over the frame, within 10 %
    expected = np.sqrt(np.mean(clean) + 4.0 + 1 / 12)
    assert abs(np.std(a - clean) - expected) < 0.1 * expected
    jittered = scene(MIXED, jitter={"std": "3 us"})
    j = tr.render_frame(jittered, 0.0, 170.0)
    assert not np.allclose(j, clean)
    assert abs(j.sum() / clean.sum() - 1) < 0.02  # jitter moves light between rows, it does not make any


def test_saturation_clips_at_the_sensor_full_well():
    s = scene(intensity=1e6, saturation_level=4095.0)
    assert tr.render_frame(s, 0.0, 170.0).max() == 4095.0


def test_a_long_exposure_integrates_its_scans_and_is_read_out_once():
    """``scans = k``: k times one scan's signal, before the sensor (noise-free: exactly k×); with noise, the
    variance of the per-scan estimate (frame/k) is (g·k·x + r²)/k², pooled over the frame within 10 %."""
    window = (-34.0, 80 * 17.0 + 68.0)
    unclipped = scene(MIXED, saturation_level=1e9)
    one = tr.render_frame(unclipped, *window, shutter="global")
    np.testing.assert_allclose(tr.render_frame(unclipped, *window, shutter="global", scans=7), 7 * one, rtol=1e-6)
    noisy = scene(MIXED, noise={"gain": 1.0, "read_std": 5.0}, bits=None, intensity=20.0)
    clean = tr.render_frame(scene(MIXED, intensity=20.0), *window, shutter="global")
    k = 10
    estimate = tr.render_frame(noisy, *window, shutter="global", scans=k) / k
    expected = np.sqrt(np.mean((k * clean + 25.0) / k**2))
    assert abs(np.std(estimate - clean) - expected) < 0.1 * expected
    with pytest.raises(ValueError, match="at least one scan"):
        tr.render_frame(noisy, *window, scans=0)


def test_a_scene_dumped_to_json_validates_to_itself():
    """What a capture records (``simulated_scene``) rebuilds the scene exactly: quantities dump with units."""
    s = scene(MIXED, noise={"gain": 1.0, "read_std": 2.0}, jitter={"std": "3 us"})
    assert ProcamScene.model_validate(s.model_dump(mode="json")) == s
    assert s.model_dump(mode="json")["rig"]["row_period"] == "17.0 us"


def test_an_absorber_below_the_surface_takes_its_share_of_the_light_that_crossed_its_depth():
    """A subsurface lobe (Laplace, w = 5 px) over an absorber at depth 3 px, 2 px thick, absorbing 0.8: the light
    entering ρ ∈ [6, 10] rows away loses 0.8 of itself, cell by cell (cells cut by the band's edges in part), and
    nothing else changes. Against scipy's Laplace distribution over each cell ∩ band, to 1e-12; a frame rendered by
    time integration agrees with the truth through the illumination weights (the absorber acts in both paths)."""
    import scipy.stats

    lobe = {"width": "5 px", "fraction": 1.0}
    objects = [{"name": "skin", "region": {"kind": "rectangle", "x": [0.0, 0.5], "y": [0.0, 1.0]}, "albedo": 0.6,
                "effects": {"subsurface": lobe}},
               {"name": "vein", "region": {"kind": "rectangle", "x": [0.5, 1.0], "y": [0.0, 1.0]}, "albedo": 0.6,
                "effects": {"subsurface": lobe | {"absorber": {"depth": "3 px", "thickness": "2 px",
                                                               "absorption": 0.8}}}}]
    s = scene(objects, camera_rows=120, projector_rows=120, camera_cols=192, projector_cols=192)
    vertical = truth(s).reshape(len(OFFSETS), 120, 192)[:, 60]  # offsets × columns of the middle row
    laplace = scipy.stats.laplace(scale=5.0)
    cell = laplace.cdf(OFFSETS + 0.5) - laplace.cdf(OFFSETS - 0.5)
    lo, hi = np.clip(np.abs(OFFSETS) - 0.5, 6, 10), np.clip(np.abs(OFFSETS) + 0.5, 6, 10)
    band = np.where(OFFSETS != 0, np.abs(laplace.cdf(hi) - laplace.cdf(lo)), 0.0)
    # columns 47.5 px from either edge of the projector, so both lose the same (tiny) share of their u lobe
    skin, vein = vertical[:-1, 47], vertical[:-1, 144]  # offset 60 points past the projector's last row
    np.testing.assert_allclose(skin / cell[:-1], skin[60] / cell[60], rtol=1e-12)
    np.testing.assert_allclose(vein / skin, 1.0 - 0.8 * band[:-1] / cell[:-1], rtol=1e-12)
    # time integration sees the same transport: a frame over the band is darker over the vein by the band's share
    frame = tr.render_frame(s, delay=8 * s.rig.row_period, exposure=2 * s.rig.row_period)
    weights = box_weights(s.rig, 8 * s.rig.row_period, 2 * s.rig.row_period)
    np.testing.assert_allclose(frame[60, [47, 144]], s.rig.intensity * weights @ vertical[:, [47, 144]], rtol=1e-6)
