"""The closed-form parallel-light simulator against brute force, and end to end through absorption."""

from __future__ import annotations

import numpy as np
import pytest

from selpath.devices.sim.parallel_light import Rod, column_x, line_integrals
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.calibrate import absorption
from selpath.stages.tomography.simulate import RodSpec, simulate_parallel_capture

RODS = (Rod(6.0, 3.0, 4.0, 0.05), Rod(-5.0, -7.0, 2.5, 0.2))


def brute_force_integrals(angles_deg, n_cols, pixel_size, rods, step=1e-3):
    """Integrate σ along y by sampling a fine grid and rotating the samples back into the object frame."""
    x = column_x(n_cols, pixel_size)
    y = np.arange(-25.0, 25.0, step) + step / 2
    out = np.zeros((len(angles_deg), n_cols))
    for i, phi in enumerate(np.deg2rad(angles_deg)):
        # a lab point p sits at R(-φ)·p in the object frame
        xo = np.cos(phi) * x[:, None] + np.sin(phi) * y[None, :]
        yo = -np.sin(phi) * x[:, None] + np.cos(phi) * y[None, :]
        for rod in rods:
            inside = (xo - rod.x) ** 2 + (yo - rod.y) ** 2 < rod.radius**2
            out[i] += rod.sigma * inside.sum(axis=1) * step
    return out


def test_line_integrals_match_brute_force():
    angles = np.array([0.0, 30.0, 95.0, 180.0, 271.0])
    analytic = line_integrals(angles, 64, 0.7, RODS)
    brute = brute_force_integrals(angles, 64, 0.7, RODS)
    # sampling error per disk crossing ≤ 2 steps · σ_max
    np.testing.assert_allclose(analytic, brute, atol=2 * 1e-3 * 0.2)
    assert analytic.max() > 0.3  # the test sees real chords, not zeros


@pytest.mark.parametrize("chunked", [False, True])
def test_simulated_capture_recovers_the_line_integrals(chunked):
    sweep = AngleSweep(start=0, stop=360, step=30)
    capture = simulate_parallel_capture(
        angles=sweep, n_rows=2, n_cols=80, pixel_size=0.5, radius=20.0,
        rods=tuple(RodSpec(x=r.x, y=r.y, radius=r.radius, sigma=r.sigma) for r in RODS),
    )
    if chunked:
        capture = capture.chunk({"angle": 5})
    out = absorption(capture).compute()
    truth = line_integrals(sweep.values(), 80, 0.5, RODS)
    inside = np.abs(column_x(80, 0.5)) < 20.0
    flags = out["flags"].values
    assert (flags[:, :, inside] == 0).all() and (flags[:, :, ~inside] != 0).all()  # outside: source saturates
    np.testing.assert_allclose(out["absorption"].values[:, 0, inside], truth[:, inside], atol=1e-5)
    np.testing.assert_array_equal(out["absorption"].values[:, 0], out["absorption"].values[:, 1])


def test_noise_is_independent_of_chunking(monkeypatch):
    kwargs = dict(angles=AngleSweep(start=0, stop=50, step=5), n_rows=3, n_cols=16, noise_std=3.0, seed=7)
    whole = simulate_parallel_capture(**kwargs)
    assert whole["target"].data.numblocks[0] == 1
    # three frames a chunk
    monkeypatch.setattr("selpath.stages.tomography.simulate._FRAME_BYTES_PER_CHUNK", 3 * 16 * 4 * 3)
    pieces = simulate_parallel_capture(**kwargs)
    assert pieces["target"].data.chunks[0] == (3, 3, 3, 1)
    whole, pieces = whole.compute(), pieces.compute()
    np.testing.assert_array_equal(whole["target"].values, pieces["target"].values)
    assert float(whole["target"].std()) > 0
