"""Delay–exposure sweeps on the simulated projector–camera rig: resumable after a real SIGKILL, refused
before starting when the controller cannot do them, the planner's arithmetic, and the v_p calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from selpath.devices.procam_acquire import acquire_full_transport, acquire_plane_to_ray, plan_sweep
from selpath.devices.sim.procam_rig import simulated_procam_rig
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.devices.sim.procam_transport import render_frame
from selpath.pipeline.capture_store import missing_frames
from selpath.pipeline.engine import run_workflow
from selpath.pipeline.errors import SpecError
from selpath.pipeline.provenance import read_provenance
from selpath.pipeline.spec import load_workflow
from selpath.pipeline.store import open_store

SCENE = """\
scene: tiny-candle
background: {albedo: 0.4}
objects:
  - {name: candle, region: {kind: rectangle, x: [0.2, 0.6], y: [0.2, 0.8]}, albedo: 0.9,
     effects: {subsurface: {width: 3 px, fraction: 0.6}}}
rig: {camera_rows: 24, camera_cols: 32, projector_rows: 16, projector_cols: 32, frame_interval: FRAME,
      noise: {gain: 1.0, read_std: 2.0, seed: 3}, jitter: {std: 2 us}}
"""

WORKFLOW = """\
workflow: procam-kill-and-resume
scheduler: synchronous
steps:
  - id: capture
    stage: acquire_plane_to_ray
    with: {scene: scene.yaml, delays: {start: -170, stop: 170, step: 34}, exposures: [85, 170],
           store: capture.zarr, progress: false}
"""


def make_workflow(folder: Path, frame_interval: str = "0 us") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.yaml").write_text(SCENE.replace("FRAME", frame_interval))
    (folder / "workflow.yaml").write_text(WORKFLOW)
    return folder / "workflow.yaml"


@pytest.mark.slow  # the default job's 8 minutes; the tomography acquisition's SIGKILL test stays in it
def test_sigkill_mid_sweep_then_rerun_gives_the_uninterrupted_store(tmp_path, kill_mid_sweep):
    run_workflow(load_workflow(make_workflow(tmp_path / "uninterrupted")), progress=False)
    want = open_store(tmp_path / "uninterrupted" / "capture.zarr", keep_flags=True).load()

    killed = make_workflow(tmp_path / "killed", frame_interval="60 ms")
    store = tmp_path / "killed" / "capture.zarr"
    done_before = kill_mid_sweep(killed, store, "written__image", 4)
    assert 4 <= done_before < 22, "the kill must land mid-sweep"
    assert read_provenance(store) is None

    (tmp_path / "killed" / "scene.yaml").write_text(SCENE.replace("FRAME", "0 us"))
    messages: list[str] = []
    run_workflow(load_workflow(killed), progress=False, log=messages.append)
    got = open_store(store, keep_flags=True).load()
    xr.testing.assert_identical(got.drop_attrs(), want.drop_attrs())
    assert not any(missing_frames(store).values())
    assert read_provenance(store)["step_hash"]


def small_scene(**rig) -> ProcamScene:
    import yaml

    spec = yaml.safe_load(SCENE.replace("FRAME", "0 us"))
    spec["rig"] |= rig
    return ProcamScene.model_validate(spec)


def test_frames_are_the_simulator_frames_at_the_commanded_settings(tmp_path):
    scene = small_scene()
    ds = acquire_plane_to_ray(simulated_procam_rig(scene), tmp_path / "c.zarr", [-34.0, 0.0, 51.0], [85.0, 170.0],
                              progress=False).load()
    for delay in (-34.0, 51.0):
        np.testing.assert_array_equal(ds.image.sel(delay=delay, exposure=170.0).values,
                                      render_frame(scene, delay, 170.0))
    assert ds["delay"].attrs["units"] == "us" and ds.attrs["scan_speed_px_per_us"] == pytest.approx(1 / 17)


def test_rig_changes_reach_the_frames_and_the_record_and_bad_ones_name_the_field(tmp_path):
    """``rig_changes`` (here a dimmer projector and a dark level) change what the rig renders, the capture records
    the scene as simulated, and an unknown or invalid field is refused with its name."""
    from selpath.stages.procam._scene_truth import simulated_scene
    from selpath.stages.procam.acquire import acquisition_scene

    path = tmp_path / "scene.yaml"
    path.write_text(SCENE.replace("FRAME", "0 us"))
    dim = acquisition_scene(path, None, {"intensity": 250.0, "dark_level": 64.0})
    ds = acquire_plane_to_ray(simulated_procam_rig(dim), tmp_path / "c.zarr", [0.0], [170.0], progress=False)
    assert simulated_scene(ds, "capture") == dim
    assert dim.rig.intensity == 250.0 and dim.rig.noise.read_std == 2.0  # the rest of the rig is the file's
    bright = acquisition_scene(path, None).with_rig(noise=None, bits=None)
    np.testing.assert_allclose(render_frame(dim.with_rig(noise=None, bits=None), 0.0, 170.0) - 64.0,
                               render_frame(bright, 0.0, 170.0) / 4, rtol=1e-5, atol=1e-3)
    with pytest.raises(Exception, match="intensty: Extra inputs"):
        acquisition_scene(path, None, {"intensty": 3.0})
    with pytest.raises(Exception, match="dark_level: Input should be greater than or equal to 0"):
        acquisition_scene(path, None, {"dark_level": -1.0})


def test_full_transport_sweep_writes_every_line(tmp_path):
    ds = acquire_full_transport(simulated_procam_rig(small_scene()), tmp_path / "f.zarr", [0.0, 34.0], [170.0],
                                [4.0, 12.0, 20.0], 4.0, progress=False)
    assert ds.image.dims == ("delay", "exposure", "line", "row", "col") and ds.attrs["line_width_px"] == 4.0
    lit = ds.image.sel(delay=0.0, exposure=170.0).mean("row").values  # (line, col)
    assert np.all(np.argmax(lit, axis=1)[1:] > np.argmax(lit, axis=1)[:-1])  # the lit columns follow l_p


def test_a_sweep_the_controller_cannot_do_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(SpecError, match=r"delays span \[-20000, 0\] µs; the controller does \[-10000, 10000\] µs"):
        acquire_plane_to_ray(simulated_procam_rig(small_scene()), tmp_path / "c.zarr", [-20000.0, 0.0], [170.0],
                             progress=False)
    assert not (tmp_path / "c.zarr").exists()


def test_a_workflow_asking_for_impossible_exposures_fails_validation(tmp_path):
    path = make_workflow(tmp_path)
    path.write_text(WORKFLOW.replace("[85, 170]", "[85, 50000]"))
    with pytest.raises(SpecError, match=r"exposures span \[85, 50000\] µs"):
        load_workflow(path)


def test_planner_reproduces_the_thesis_arithmetic():
    """§5.4.2: 46 line positions (0…900 px every 20) × 11 delays = 506 captures versus 3,726 = 46 × 81
    blocks of 20 px for pixel-to-pixel scanning."""
    lines = np.arange(0, 901, 20)
    delays = np.arange(0, 1701, 170)
    plan = plan_sweep(delays, [170.0], lines, row_block=20, row_span=81 * 20)
    assert (plan.captures, plan.pixel_to_pixel) == (506, 3726)
    assert plan.describe().startswith("506 captures (11 delays × 1 exposures × 46 lines); pixel-to-pixel")
    assert "needs 3,726 for the same rows: this sweep takes 7.4× fewer captures" in plan.describe()


def test_scan_speed_calibration_recovers_the_rig_within_its_uncertainty(tmp_path):
    (tmp_path / "flat.yaml").write_text("""\
scene: flat
background: {albedo: 0.8}
rig: {camera_rows: 240, camera_cols: 96, projector_rows: 144, projector_cols: 96, sync_offset: 23 us,
      row_period: 16.5 us, line_time: 20 us, noise: {gain: 1.0, read_std: 2.0}, jitter: {std: 1 us}}
""")
    (tmp_path / "cal.yaml").write_text("""\
workflow: cal
scheduler: synchronous
steps:
  - id: frames
    stage: acquire_scan_calibration
    with: {store: frames.zarr, scene: flat.yaml, delays: {start: 500, stop: 1500, step: 250},
           exposures: [170, 340, 680, 1020], progress: false}
  - id: fit
    stage: calibrate_scan_speed
    with: {capture: $frames}
outputs:
  fit: {from: fit, store: fit.zarr}
""")
    run_workflow(load_workflow(tmp_path / "cal.yaml"), progress=False)
    fit = open_store(tmp_path / "fit.zarr", "scan_calibration").attrs
    assert fit["converged"] and fit["frames_used"] == 20
    # within 3 standard errors, and the standard errors are informative (well below 1 % and 1 row period)
    assert abs(fit["scan_speed_px_per_us"] - 1 / 16.5) < 3 * fit["scan_speed_std"]
    assert abs(fit["sync_offset_us"] - 23.0) < 3 * fit["sync_offset_std"]
    assert fit["scan_speed_std"] < 0.01 / 16.5 and fit["sync_offset_std"] < 16.5


def test_calibration_without_a_visible_band_names_the_frames_and_the_fix():
    from selpath.pipeline.errors import StageError
    from selpath.stages.procam.calibrate import calibrate_scan_speed

    dark = xr.Dataset({"image": (("delay", "exposure", "row", "col"), np.zeros((2, 2, 8, 4)))},
                      coords={"delay": [0.0, 170.0], "exposure": [170.0, 340.0]}, attrs={"line_time_us": 17.0})
    with pytest.raises(StageError, match=r"only 0 of 4 frames show at least 2.0 illuminated rows.*longer exposures"):
        calibrate_scan_speed(dark)


@pytest.mark.parametrize("mode", ["floodlit", "epipolar"])
def test_checkerboard_frames_are_the_simulators_and_a_lost_frame_is_captured_again(tmp_path, mode):
    """§5.4.6 stacks: each frame is the simulator's render of its shifted board (rectangular squares, so a swapped
    row/column shift shows) at the mode's window (floodlit: global shutter over the whole scan; epipolar: rolling
    shutter at t_d = 0, t_e = t_p); a frame marked lost is captured again, alone, and comes back identical."""
    from selpath.devices import patterns
    from selpath.devices.procam_acquire import acquire_checkerboards, checkerboard_shifts
    from selpath.pipeline.capture_store import forget_frames
    from selpath.pipeline.integrity import BadChunk
    from selpath.stages.procam.acquire_patterns import exposure_window

    scene = small_scene()
    square = (6, 10)
    shifts = checkerboard_shifts(square, 2)
    np.testing.assert_array_equal(shifts, [(0, 0), (0, 10), (6, 0), (6, 10)])
    store = tmp_path / "boards.zarr"
    delay, exposure = exposure_window(scene, mode)
    shutter = "global" if mode == "floodlit" else "rolling"
    ds = acquire_checkerboards(simulated_procam_rig(scene), store, square, shifts, mode=mode, delay=delay,
                               exposure=exposure, progress=False).load()
    assert ds.image.dims == ("shift", "row", "col") and ds.attrs["square_px"] == [6, 10]
    for i, shift in enumerate(shifts):
        board = patterns.checkerboard((scene.rig.projector_rows, scene.rig.projector_cols), square, tuple(shift))
        np.testing.assert_array_equal(ds.image.isel(shift=i).values,
                                      render_frame(scene, delay, exposure, board, shutter=shutter))
    assert forget_frames(store, [BadChunk("image", (2, 0, 0), "corrupt")]) == 1
    messages: list[str] = []
    again = acquire_checkerboards(simulated_procam_rig(scene), store, square, shifts, mode=mode, delay=delay,
                                  exposure=exposure, progress=False, log=messages.append).load()
    assert any(f"capturing 1 {mode} checkerboard frame(s)" in m for m in messages), messages
    xr.testing.assert_identical(again.image, ds.image)
