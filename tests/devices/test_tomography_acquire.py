"""Acquisition sweeps: frames land as captured, a killed run resumes to the identical store."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from selpath import workflows
from selpath.devices.sim.rig import simulated_rig
from selpath.devices.sim.scene import load_scene
from selpath.devices.tomography_acquire import acquire_tomography
from selpath.pipeline.capture_store import missing_frames
from selpath.pipeline.engine import run_workflow
from selpath.pipeline.errors import DeviceError, StoreError
from selpath.pipeline.provenance import read_provenance
from selpath.pipeline.spec import load_workflow
from selpath.pipeline.store import open_store
from tests.helpers.acquisition import SCENE, make_workflow


def test_sigkill_mid_sweep_then_rerun_gives_the_uninterrupted_store(tmp_path, kill_mid_sweep):
    """A real SIGKILL of `selpath run` mid-sweep; running the workflow again resumes (not restarts) and the
    store equals an uninterrupted run's: every frame, no frame lost or duplicated, same flags."""
    reference_run = make_workflow(tmp_path / "uninterrupted")
    run_workflow(load_workflow(reference_run), progress=False)
    want = open_store(tmp_path / "uninterrupted" / "capture.zarr", keep_flags=True).load()

    killed = make_workflow(tmp_path / "killed", frame_interval="40 ms")
    store = tmp_path / "killed" / "capture.zarr"
    done_before = kill_mid_sweep(killed, store, "written__target", 5)
    assert 5 <= done_before < 24, "the kill must land mid-sweep"
    assert read_provenance(store) is None  # unfinished: no provenance, so the engine will run the step again

    # speed the simulated camera back up (the scene's identity changes, the sweep does not)
    (tmp_path / "killed" / "scene.yaml").write_text(SCENE.replace("FRAME", "0 s"))
    messages = []
    report = run_workflow(load_workflow(killed), progress=False, log=messages.append)
    assert report.steps["capture"].status == "computed"
    got = open_store(store, keep_flags=True).load()
    xr.testing.assert_identical(got, want)
    assert not any(missing_frames(store).values())
    assert read_provenance(store)["step_hash"]


def test_rerunning_a_finished_acquisition_captures_nothing(tmp_path):
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    report = run_workflow(load_workflow(path), progress=False)
    assert report.steps["capture"].status == "reused"
    forced = run_workflow(load_workflow(path), progress=False, reuse=False)  # --force never loses frames
    assert forced.steps["capture"].status == "computed"
    assert not any(missing_frames(tmp_path / "capture.zarr").values())


def test_capture_holds_geometry_and_is_a_valid_tomography_cube(tmp_path):
    scene = load_scene(SCENE.replace("FRAME", "0 s"))
    ds = acquire_tomography(simulated_rig(scene), tmp_path / "c.zarr", [0.0, 90.0], progress=False)
    assert ds.attrs["camera_model"] == "perspective" and ds.attrs["light_angle_deg"] == 45.0
    assert ds.attrs["length_unit"] == "mm" and ds.attrs["camera_distance"] == 80.0
    assert ds.angle.attrs["units"] == "degree"
    dark = float(ds.dark.mean())
    assert dark == pytest.approx(64.0, abs=0.5)  # read noise only
    lit = ds.backlit.values > 1000
    assert lit.any() and (~lit).any()  # silhouette against the lit plane


def test_a_different_sweep_into_the_same_store_is_refused(tmp_path):
    scene = load_scene(SCENE.replace("FRAME", "0 s"))
    acquire_tomography(simulated_rig(scene), tmp_path / "c.zarr", [0.0, 90.0], progress=False)
    with pytest.raises(StoreError, match="a different sweep is already stored here"):
        acquire_tomography(simulated_rig(scene), tmp_path / "c.zarr", [0.0, 45.0, 90.0], progress=False)


def test_a_device_fault_keeps_every_frame_captured_so_far(tmp_path):
    scene = load_scene(SCENE.replace("FRAME", "0 s"))
    rig = simulated_rig(scene)
    real_capture, shots = rig.camera.capture, []

    def flaky():
        if len(shots) == 7:
            raise DeviceError("the camera returned no frame", port="sim")
        shots.append(1)
        return real_capture()

    rig.camera.capture = flaky
    with pytest.raises(DeviceError, match="no frame"):
        acquire_tomography(rig, tmp_path / "c.zarr", np.arange(0, 360, 60.0), progress=False)
    missing = missing_frames(tmp_path / "c.zarr")
    assert len(missing["target"]) == 6 - 4 and len(missing["backlit"]) == 6 - 3  # 7 frames kept


def test_the_shipped_workflow_acquires_the_gelatin_bin_into_a_capture_store():
    path = workflows.path("tomography-sim")
    workflow = load_workflow(path)
    capture = workflow.steps["capture"]
    assert capture.stage.name == "acquire_tomography" and "capture" in Path(capture.settings.store).name
    assert load_scene(capture.settings.scene).scene == "gelatin-bin"
    assert capture.settings.store in workflow.self_written and "capture" in workflow.outputs


def test_a_bad_scene_fails_validation_before_anything_moves(tmp_path):
    path = make_workflow(tmp_path)
    (tmp_path / "scene.yaml").write_text(SCENE.replace("FRAME", "0 s").replace("radius: 10 mm", "radius: 10"))
    with pytest.raises(Exception, match=textwrap.dedent(r"scene file: .*scene.yaml:3: object.shape.radius: 10 has "
                                                        r"no unit")):
        load_workflow(path)
    assert not (tmp_path / "capture.zarr").exists()
