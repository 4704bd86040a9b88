"""``rig: hardware`` for the projector–camera sweeps: the serial sync controller and the projector behind it
(pattern slots, lines drawn by the controller) against the fake firmware on a pseudo-terminal, with a simulated
camera standing in for OpenCV's. The whole path must give the simulated rig's frames, survive the line's faults,
keep every frame through a disconnect or a SIGKILL, and resume."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml

import selpath.devices.procam_hardware as procam_hardware
from selpath.devices.procam_acquire import acquire_full_transport, acquire_plane_to_ray
from selpath.devices.procam_hardware import load_procam_hardware, procam_hardware_rig
from selpath.devices.protocols import SyncLimits
from selpath.devices.sim.procam_rig import FakeProcamHardware, simulated_procam_rig
from selpath.pipeline.capture_store import missing_frames
from selpath.pipeline.engine import run_workflow
from selpath.pipeline.errors import DeviceDisconnected, SpecError
from selpath.pipeline.provenance import read_provenance
from selpath.pipeline.spec import load_workflow
from selpath.pipeline.store import open_store
from tests.devices.conftest import written_frames
from tests.helpers.procam_hardware import scene

DELAYS, EXPOSURES = [-68.0, -34.0, 0.0, 34.0], [85.0, 170.0]


def rig_file(folder: Path, port: str, **changes) -> Path:
    """A rig file for ``port`` whose timing and levels are the scene rig's (17 µs rows and line time)."""
    spec = {"sync": {"url": port, "timeout_s": 0.5}, "camera": {"source": 0},
            "scan": {"row_period_us": 17.0, "line_time_us": 17.0}, "dark_level": 0.0, "saturation_level": 4095.0}
    path = folder / "procam-rig.yaml"
    path.write_text(yaml.safe_dump(spec | changes))
    return path


@pytest.fixture
def fake_camera(monkeypatch):
    """``use(hardware)``: the rig's OpenCV camera is ``hardware.camera``; the settings it was opened with are kept."""
    opened = []

    def use(hardware: FakeProcamHardware):
        def open_camera(source, **settings):
            opened.append((source, settings))
            return hardware.camera
        monkeypatch.setattr(procam_hardware, "OpenCVCamera", open_camera)
        return opened

    return use


def test_a_hardware_sweep_gives_the_simulated_rigs_frames_and_uploads_the_white_pattern_once(tmp_path, fake_camera):
    """Bit for bit: the frames through the serial line, the projector's slot and the triggered camera equal the
    simulated rig's at the same settings; the white pattern is uploaded once and verified by its checksum."""
    want = acquire_plane_to_ray(simulated_procam_rig(scene()), tmp_path / "sim.zarr", DELAYS, EXPOSURES,
                                progress=False).load()
    with FakeProcamHardware(scene()) as hardware:
        opened = fake_camera(hardware)
        instruments = procam_hardware_rig(load_procam_hardware(rig_file(tmp_path, hardware.port)))
        try:
            got = acquire_plane_to_ray(instruments, tmp_path / "hw.zarr", DELAYS, EXPOSURES, progress=False).load()
        finally:
            instruments.close()
        received = hardware.firmware.received
    assert opened == [(0, {"width": None, "height": None, "exposure": None, "discard": 0, "keep_first": False})]
    xr.testing.assert_identical(got["image"].drop_attrs(), want["image"].drop_attrs())
    for name in ("scan_speed_px_per_us", "line_time_us", "projector_shape", "dark_level_counts", "saturation_counts"):
        assert got.attrs[name] == want.attrs[name], name
    assert got.attrs["rig"] == "hardware" and got.attrs["sync_controller"] == "selpath,fake-sync,1.0"
    commands = [c.split()[0] for c in received]
    assert commands.count("UPLOAD") == 1 and commands.count("SUM?") == 1 and commands.count("SHOW") == 1
    assert commands.count("ROW") == 16 and commands.count("ARM") == 1 + len(DELAYS) * len(EXPOSURES)


def test_full_transport_lines_are_drawn_by_the_controller(tmp_path, fake_camera):
    """Each l_p is one LINE command (no upload) confirmed by PAT?, and the frames equal the simulated rig's (odd
    widths at whole-pixel centres: the 8-bit projector shows the line exactly)."""
    lines, width = [4.0, 11.0, 20.0], 3.0
    want = acquire_full_transport(simulated_procam_rig(scene()), tmp_path / "sim.zarr", [0.0, 34.0], [170.0], lines,
                                  width, progress=False).load()
    with FakeProcamHardware(scene()) as hardware:
        fake_camera(hardware)
        instruments = procam_hardware_rig(load_procam_hardware(rig_file(tmp_path, hardware.port)))
        try:
            got = acquire_full_transport(instruments, tmp_path / "hw.zarr", [0.0, 34.0], [170.0], lines, width,
                                         progress=False).load()
        finally:
            instruments.close()
        received = hardware.firmware.received
    xr.testing.assert_identical(got["image"].drop_attrs(), want["image"].drop_attrs())
    assert [c for c in received if c.startswith("LINE")] == [f"LINE {p:.3f} 3.000" for p in lines]
    assert not any(c.startswith("UPLOAD") for c in received)


def _uninterrupted(tmp_path: Path) -> xr.Dataset:
    return acquire_plane_to_ray(simulated_procam_rig(scene()), tmp_path / "want.zarr", DELAYS, EXPOSURES,
                                progress=False).load()


def test_a_disconnect_mid_sweep_keeps_every_frame_and_the_rerun_resumes(tmp_path, fake_camera):
    want = _uninterrupted(tmp_path)
    store = tmp_path / "hw.zarr"
    with FakeProcamHardware(scene(), faults={40: "disconnect"}) as hardware:
        fake_camera(hardware)
        instruments = procam_hardware_rig(load_procam_hardware(rig_file(tmp_path, hardware.port)))
        with pytest.raises(DeviceDisconnected, match="the port went away") as caught:
            acquire_plane_to_ray(instruments, store, DELAYS, EXPOSURES, progress=False)
        instruments.close()
    assert caught.value.port == hardware.port and "resume" in caught.value.fix
    kept = len(DELAYS) * len(EXPOSURES) - len(missing_frames(store)["image"])
    assert 0 < kept < len(DELAYS) * len(EXPOSURES)
    with FakeProcamHardware(scene()) as hardware:  # reconnected: a fresh controller, patterns gone
        fake_camera(hardware)
        instruments = procam_hardware_rig(load_procam_hardware(rig_file(tmp_path, hardware.port)))
        try:
            got = acquire_plane_to_ray(instruments, store, DELAYS, EXPOSURES, progress=False).load()
        finally:
            instruments.close()
        rearmed = sum(c == "ARM" for c in hardware.firmware.received) - 1  # the one on opening
    assert rearmed == len(DELAYS) * len(EXPOSURES) - kept  # only the missing frames were captured again
    xr.testing.assert_identical(got["image"].drop_attrs(), want["image"].drop_attrs())


def test_a_sweep_the_controller_cannot_do_is_refused_before_anything_moves(tmp_path, fake_camera):
    limits = SyncLimits(delay_min=-100.0, delay_max=30.0, exposure_min=10.0, exposure_max=150.0, step=1.0)
    with FakeProcamHardware(scene(), limits=limits) as hardware:
        fake_camera(hardware)
        instruments = procam_hardware_rig(load_procam_hardware(rig_file(tmp_path, hardware.port)))
        try:
            with pytest.raises(SpecError, match=r"delays span \[-68, 34\] µs; the controller does \[-100, 30\] "
                                                r"µs.*\n.*exposures span \[85, 170\] µs; "
                                                r"the controller does \[10, 150\]"):
                acquire_plane_to_ray(instruments, tmp_path / "c.zarr", DELAYS, EXPOSURES, progress=False)
        finally:
            instruments.close()
        assert not any(c.startswith(("DELAY", "EXPO", "UPLOAD")) for c in hardware.firmware.received)
    assert not (tmp_path / "c.zarr").exists()


WORKFLOW = """\
workflow: procam-hardware
scheduler: synchronous
steps:
  - id: capture
    stage: acquire_plane_to_ray
    with: {rig: hardware, hardware: procam-rig.yaml, delays: {start: -68, stop: 34, step: 34}, exposures: [85, 170],
           store: capture.zarr, progress: false}
"""


@pytest.mark.parametrize("change, message", [
    ({"hardware": None}, "rig 'hardware' needs the setting 'hardware'"),
    ({"scene": "scene.yaml"}, "scene is a setting of the simulated rig"),
    ({"sensor": [12, 16]}, "sensor is a setting of the simulated rig"),
    ({"hardware": "broken.yaml"}, r"hardware file: .*broken.yaml:1: scan: is required but missing"),
])
def test_a_hardware_workflow_is_checked_before_anything_moves(tmp_path, change, message):
    rig_file(tmp_path, "/dev/null")
    (tmp_path / "broken.yaml").write_text("sync: {url: /dev/null}\ncamera: {source: 0}\n")
    spec = yaml.safe_load(WORKFLOW)
    settings = spec["steps"][0]["with"]
    for key, value in change.items():
        settings.pop(key) if value is None else settings.__setitem__(key, value)
    path = tmp_path / "wf.yaml"
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(SpecError, match=message):
        load_workflow(path)


KILLED_RUN = """\
import sys
import selpath.devices.procam_hardware as procam_hardware
from selpath.devices.sim.procam_rig import FakeProcamHardware
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.pipeline.engine import run_workflow
from selpath.pipeline.spec import load_workflow
import json, os
folder = sys.argv[1]
scene = ProcamScene.model_validate(json.loads(open(os.path.join(folder, "scene.json")).read()))
with FakeProcamHardware(scene) as hardware:
    link = os.path.join(folder, "port")
    os.symlink(hardware.port, link + ".new")
    os.replace(link + ".new", link)
    procam_hardware.OpenCVCamera = lambda source, **settings: hardware.camera
    run_workflow(load_workflow(os.path.join(folder, "workflow.yaml")), progress=False)
"""


@pytest.mark.slow  # the default job's 8 minutes; the tomography acquisition's SIGKILL test stays in it
def test_sigkill_mid_hardware_sweep_then_rerun_gives_the_uninterrupted_store(tmp_path, fake_camera):
    """A real SIGKILL of a `run_workflow` process driving the fake controller through its pseudo-terminal (the rig
    file names a stable link to it, as /dev/serial/by-id/… does); run again, only the missing frames are
    captured and the store equals the uninterrupted sweep's."""
    import json

    want = _uninterrupted(tmp_path)
    folder = tmp_path / "run"
    folder.mkdir()
    paced = scene(frame_interval="60 ms")
    (folder / "scene.json").write_text(json.dumps(paced.model_dump(mode="json")))
    rig_file(folder, str(folder / "port"))
    (folder / "workflow.yaml").write_text(WORKFLOW)
    (folder / "run.py").write_text(KILLED_RUN)
    store = folder / "capture.zarr"
    process = subprocess.Popen([sys.executable, str(folder / "run.py"), str(folder)], cwd=Path.cwd(),
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while written_frames(store, "written__image") < 3 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    process.kill()
    _, err = process.communicate()
    kept = written_frames(store, "written__image")
    assert 3 <= kept < 8, f"the kill must land mid-sweep ({kept} frames; {err.decode()[-400:]})"
    assert read_provenance(store) is None

    with FakeProcamHardware(scene()) as hardware:
        (folder / "port").unlink()
        (folder / "port").symlink_to(hardware.port)
        fake_camera(hardware)
        run_workflow(load_workflow(folder / "workflow.yaml"), progress=False)
        rearmed = sum(c == "ARM" for c in hardware.firmware.received) - 1
    assert rearmed == 8 - kept
    got = open_store(store).load()
    xr.testing.assert_identical(got["image"].drop_attrs(), want["image"].drop_attrs())
    assert read_provenance(store)["step_hash"]
    assert not missing_frames(store)["image"]


def test_gray_codes_through_the_controllers_slots_equal_the_simulated_rigs(tmp_path, fake_camera):
    """Gray codes through the controller's 8 slots (20 frames here, 44 on a 1280 × 720 projector): every pattern is
    uploaded once (none repeats), verified and shown, the frames equal the simulated rig's, and they decode to each
    pixel's projector column (within the scene's sensor noise)."""
    from selpath.devices.procam_acquire import acquire_gray_code
    from selpath.stages.procam.rectify import decode_gray_code

    want = acquire_gray_code(simulated_procam_rig(scene()), tmp_path / "sim.zarr", delay=0.0, exposure=289.0,
                             progress=False).load()
    with FakeProcamHardware(scene()) as hardware:
        fake_camera(hardware)
        instruments = procam_hardware_rig(load_procam_hardware(rig_file(tmp_path, hardware.port)))
        try:
            got = acquire_gray_code(instruments, tmp_path / "hw.zarr", delay=0.0, exposure=289.0,
                                    progress=False).load()
        finally:
            instruments.close()
        uploads = sum(c.startswith("UPLOAD") for c in hardware.firmware.received)
    assert got.sizes["pattern"] == 2 + 2 * (5 + 4) == uploads
    xr.testing.assert_identical(got["image"].drop_attrs(), want["image"].drop_attrs())
    decoded = decode_gray_code(got).compute()["projector_col"].values
    seen = np.isfinite(decoded)
    assert seen.mean() > 0.9
    np.testing.assert_allclose(decoded[seen], np.broadcast_to(np.arange(32), (24, 32))[seen], atol=0.25)  # noise


def test_epipolar_checkerboards_on_hardware_equal_the_simulated_rigs_and_floodlit_is_refused(tmp_path, fake_camera):
    """Each distinct board is one upload verified by its checksum (a repeated one is shown from its slot), the frames
    equal the simulated rig's; a hardware
    workflow asking for floodlit boards (a global shutter the OpenCV camera lacks) fails validation, and the
    acquisition stage at t_d = 0, t_e = t_p runs through the serial path."""
    from selpath.devices.procam_acquire import acquire_checkerboards, checkerboard_shifts

    shifts = checkerboard_shifts((4, 4), 2)
    want = acquire_checkerboards(simulated_procam_rig(scene()), tmp_path / "sim.zarr", (4, 4), shifts,
                                 mode="epipolar", delay=0.0, exposure=17.0, progress=False).load()
    with FakeProcamHardware(scene()) as hardware:
        fake_camera(hardware)
        instruments = procam_hardware_rig(load_procam_hardware(rig_file(tmp_path, hardware.port)))
        try:
            got = acquire_checkerboards(instruments, tmp_path / "hw.zarr", (4, 4), shifts, mode="epipolar",
                                        delay=0.0, exposure=17.0, progress=False).load()
        finally:
            instruments.close()
        # shifts of one square give the complementary board, of two squares the same one: 2 distinct boards of 4
        assert sum(c.startswith("UPLOAD") for c in hardware.firmware.received) == 2
    xr.testing.assert_identical(got["image"].drop_attrs(), want["image"].drop_attrs())

    boards = {"workflow": "boards", "scheduler": "synchronous", "steps": [{
        "id": "boards", "stage": "acquire_checkerboards",
        "with": {"rig": "hardware", "hardware": "procam-rig.yaml", "mode": "floodlit", "square": 4,
                 "shifts_per_axis": 2, "store": "boards.zarr", "progress": False}}]}
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(boards))
    with pytest.raises(SpecError, match="mode floodlit needs the camera's global shutter"):
        load_workflow(tmp_path / "wf.yaml")
    boards["steps"][0]["with"]["mode"] = "epipolar"
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(boards))
    with FakeProcamHardware(scene()) as hardware:
        rig_file(tmp_path, hardware.port)
        fake_camera(hardware)
        run_workflow(load_workflow(tmp_path / "wf.yaml"), progress=False)
    stored = open_store(tmp_path / "boards.zarr")
    assert stored.attrs["delay_us"] == 0.0 and stored.attrs["exposure_us"] == 17.0
    xr.testing.assert_identical(stored["image"].drop_attrs(), want["image"].drop_attrs())
