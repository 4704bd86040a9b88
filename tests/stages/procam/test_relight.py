"""Relighting and epipolar synthesis from T, against the simulator rendering the same virtual pattern."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.devices import patterns
from selpath.devices.sim import procam_lobes as lobes
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.stages.procam.relight import epipolar_image, non_epipolar_image, relight

RIG = {"camera_rows": 40, "camera_cols": 48, "projector_rows": 40, "projector_cols": 48, "bits": None}
OBJECTS = [{"name": "candle", "region": {"kind": "rectangle", "x": [0.1, 0.5], "y": [0.2, 0.8]}, "albedo": 0.9,
            "effects": {"subsurface": {"width": "3 px", "fraction": 0.5},
                        "specular_interreflection": {"centre": [0.3, 0.5], "reach": 0.3,
                                                     "displacement": ["2 px", "-7 px"], "strength": 0.6}}}]
OFFSETS = np.arange(-39, 40)


@pytest.fixture(scope="module")
def scene_and_truth():
    s = ProcamScene.model_validate({"scene": "t", "background": {"albedo": 0.3}, "objects": OBJECTS, "rig": RIG})
    truth = s.rig.intensity * np.concatenate([tr.truth_tile(s, t, OFFSETS) for t in tr.tiles(s)], axis=-1)
    transport = xr.DataArray(truth.reshape(len(OFFSETS), 40, 48), dims=("offset", "row", "col"),
                             coords={"offset": OFFSETS})
    return s, transport.chunk({"row": 16})  # lazy, in bands, as the stage writes it


@pytest.mark.parametrize("row", [5, 20, 33])
def test_relighting_a_single_line_equals_the_simulator_under_that_line(scene_and_truth, row):
    """The simulator with a global shutter open over the whole scan renders Σ_o T(o) b(s + o) by time
    integration; relight() must match it to float32 rounding (1e-5 of the brightest pixel)."""
    s, transport = scene_and_truth
    pattern = patterns.horizontal_line((s.rig.projector_rows, s.rig.projector_cols), row, 1.0)
    rendered = tr.render_frame(s, -100.0, 2000.0, pattern, shutter="global")
    relit = relight(transport, pattern[:, 0]).compute().values
    np.testing.assert_allclose(relit, rendered, rtol=0, atol=1e-5 * rendered.max() + 1e-3)


def test_white_relighting_is_the_sum_and_epipolar_plus_non_epipolar_is_the_whole(scene_and_truth):
    _, transport = scene_and_truth
    total = transport.sum("offset").compute()
    xr.testing.assert_allclose(relight(transport, np.ones(40)).compute(), total)
    xr.testing.assert_allclose((epipolar_image(transport) + non_epipolar_image(transport)).compute(), total)
    xr.testing.assert_allclose(epipolar_image(transport).compute(), transport.sel(offset=0, drop=True).compute())


def test_sharpened_epipolar_removes_what_a_long_exposure_lets_in(scene_and_truth):
    """§5.4.5: the epipolar frame at t_e = 10 rows carries the subsurface and specular light of ±5 rows; the
    image synthesised from |offset| ≤ 0 does not. Against the simulator's direct-only render."""
    s, transport = scene_and_truth
    long_epipolar = tr.render_frame(s, 0.0, 10 * s.rig.row_period)
    direct_only = tr.render_frame(s, 0.0, s.rig.line_time, effects=dict.fromkeys(lobes.EFFECTS, lambda *_: []))
    sharpened = epipolar_image(transport).compute().values
    candle = (slice(10, 30), slice(8, 22))
    err_long = np.abs(long_epipolar - direct_only)[candle].mean()
    err_sharp = np.abs(sharpened - direct_only)[candle].mean()
    assert err_sharp < 0.5 * err_long
