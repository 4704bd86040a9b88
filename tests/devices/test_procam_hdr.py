"""The sweep's HDR planner (#30 item 3): a shorter exposure added where it unclips a highlight, its cost stated,
nothing added where only attenuation helps, and a resumed sweep keeping what was planned."""

from __future__ import annotations

import numpy as np
import pytest

from selpath.devices.procam_acquire import acquire_plane_to_ray
from selpath.devices.sim.procam_rig import simulated_procam_rig
from selpath.stages.procam.demux import demux_plane_to_ray
from tests.helpers.highlight import DELAYS, highlight_scene, truth_of

REQUESTED = [510.0, 850.0]  # the thesis's longer exposures: a bright lobe clips in both at t_d = 0


def _window_error(capture, out, s) -> float:
    """Median relative error of the light in the 10-row epipolar window over the pixels that clipped."""
    truth = truth_of(s, out["offset"].values)
    clipped = (capture["image"].values >= s.rig.saturation_level).any(axis=(0, 1))
    window = np.abs(out["offset"].values) <= 5
    ratio = out["transport"].values[window].sum(0)[clipped] / truth[window].sum(0)[clipped]
    return float(np.median(np.abs(ratio - 1)))


@pytest.mark.slow  # 10 s: in the slow job, so the default job keeps its 8-minute budget
def test_hdr_adds_the_exposure_that_unclips_a_bright_lobe_and_states_its_cost(tmp_path):
    s = highlight_scene(7_000.0, albedo=0.9, effects={"subsurface": {"width": "10 px", "fraction": 0.9}})
    logs: list[str] = []
    capture = acquire_plane_to_ray(simulated_procam_rig(s), tmp_path / "hdr.zarr", DELAYS, REQUESTED, hdr=True,
                                   progress=False, log=logs.append)
    plain = acquire_plane_to_ray(simulated_procam_rig(s), tmp_path / "plain.zarr", DELAYS, REQUESTED, progress=False)
    assert capture["exposure"].values.tolist() == [255.0, 510.0, 850.0]
    assert capture.attrs["hdr_added_exposure_us"] == 255.0
    assert capture.attrs["hdr_tried_exposures_us"] == [510.0, 255.0]
    assert capture.attrs["hdr_tried_clipped_pixels"][0] > 100 and capture.attrs["hdr_tried_clipped_pixels"][1] == 0
    assert capture.attrs["hdr_captures"] == len(DELAYS) + 2  # a frame per delay, and the two previews
    assert any(f"+{len(DELAYS)} captures (+2 previews)" in line for line in logs), logs
    hdr, without = demux_plane_to_ray(capture).compute(), demux_plane_to_ray(plain).compute()
    assert not hdr["censored"].any()
    # the unclipped 255 µs frames pin the window's light: 0.15 % against 2.0 % from the clipped sweep alone
    assert _window_error(capture, hdr, s) < 0.005 < 0.01 < _window_error(plain, without, s)


@pytest.mark.slow  # default job over its 8 minutes: run in the slow job
def test_hdr_adds_nothing_where_the_light_clips_within_one_line_time(tmp_path):
    """A mirror-like direct peak (8 000 counts in one row's line time): every exposure clips it equally."""
    s = highlight_scene(10_000.0, albedo=0.8)
    logs: list[str] = []
    capture = acquire_plane_to_ray(simulated_procam_rig(s), tmp_path / "c.zarr", DELAYS, REQUESTED, hdr=True,
                                   progress=False, log=logs.append)
    assert capture["exposure"].values.tolist() == REQUESTED and capture.attrs["hdr_added_exposure_us"] == "none"
    tried = capture.attrs["hdr_tried_exposures_us"]
    assert tried == [510.0, 255.0, 128.0, 64.0, 2 * s.rig.line_time]  # halved on the 1 µs step, down to 2 t_p
    assert len(set(capture.attrs["hdr_tried_clipped_pixels"])) == 1
    assert any("only attenuation helps" in line for line in logs), logs
    assert demux_plane_to_ray(capture).compute()["censored"].sum() > 100


def test_a_resumed_hdr_sweep_keeps_its_plan_and_previews_nothing(tmp_path):
    s = highlight_scene(7_000.0, albedo=0.9, effects={"subsurface": {"width": "10 px", "fraction": 0.9}})
    first = acquire_plane_to_ray(simulated_procam_rig(s), tmp_path / "c.zarr", DELAYS, REQUESTED, hdr=True,
                                 progress=False)
    logs: list[str] = []
    again = acquire_plane_to_ray(simulated_procam_rig(s), tmp_path / "c.zarr", DELAYS, REQUESTED, hdr=True,
                                 progress=False, log=logs.append)
    assert not any(line.strip().startswith("hdr:") for line in logs), logs
    assert any("already captured" in line for line in logs)
    assert again["exposure"].values.tolist() == first["exposure"].values.tolist()
