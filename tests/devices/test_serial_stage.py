"""The serial rotary-stage driver against a fake firmware on a real pseudo-terminal (pyserial end to end)."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.devices.serial_line import SerialLine, frame_reply
from selpath.devices.serial_stage import SerialRotaryStage
from selpath.devices.sim.rig import SimCamera, SimLight, SimSampleChanger, simulated_rig
from selpath.devices.sim.scene import Scene
from selpath.devices.sim.stage_firmware import FakeStageFirmware
from selpath.devices.tomography_acquire import TomographyRig, acquire_tomography
from selpath.pipeline.capture_store import missing_frames
from selpath.pipeline.errors import DeviceDisconnected, DeviceError, DeviceProtocolError, DeviceTimeout
from selpath.pipeline.store import open_store

FAST = dict(timeout_s=0.2, move_timeout_s=0.5)


def homed(firmware: FakeStageFirmware) -> SerialRotaryStage:
    stage = SerialRotaryStage(firmware.port, **FAST)
    stage.home()
    return stage


def test_normal_sweep_moves_once_per_angle_and_verifies_each():
    with FakeStageFirmware() as fw:
        stage = homed(fw)
        assert stage.identify() == "selpath,fake-stage,1.0"
        reached = [stage.move_to(a) for a in (0.0, 12.5, 359.999, 360.0 + 7)]
        stage.close()
    assert reached == [0.0, 12.5, 359.999, 7.0]
    assert fw.received == ["HOME", "POS?", "*IDN?", "MOVE 0.000", "POS?", "MOVE 12.500", "POS?",
                           "MOVE 359.999", "POS?", "MOVE 7.000", "POS?"]


@pytest.mark.parametrize("fault", ["silent", "garble", "partial", "noise"])
def test_a_query_is_retried_after_a_bad_reply(fault):
    with FakeStageFirmware({2: fault}) as fw:  # 0 HOME, 1 POS?, 2 the POS? under test
        stage = homed(fw)
        assert stage.position() == 0.0
        stage.close()
    assert fw.received[2:] == ["POS?", "POS?"]


@pytest.mark.parametrize(("fault", "error", "message"), [
    ("silent", DeviceTimeout, r"3 tries failed, the last with: no reply within 0.2 s"),
    ("partial", DeviceTimeout, r"the last with: an incomplete reply within 0.2 s \(reply b'POS 0"),
    ("garble", DeviceProtocolError, r"the last with: reply fails its checksum \(garbled line\)"),
    ("noise", DeviceProtocolError, r"the last with: reply is not ASCII \(reply b'\\xff\\xfe"),
])
def test_bounded_retries_then_an_error_naming_port_command_and_reply(fault, error, message):
    with FakeStageFirmware({2: fault, 3: fault, 4: fault}) as fw:
        stage = homed(fw)
        with pytest.raises(error, match=message) as info:
            stage.position()
        stage.close()
    assert info.value.port == fw.port and info.value.command == "POS?"
    assert fw.port in str(info.value) and "'POS?'" in str(info.value)
    assert fw.received[2:] == ["POS?"] * 3


def test_a_lost_move_reply_is_resolved_by_asking_never_by_moving_again():
    with FakeStageFirmware({2: "lost-move"}) as fw:
        stage = homed(fw)
        assert stage.move_to(30.0) == 30.0
        stage.close()
    assert fw.received[2:] == ["MOVE 30.000", "POS?"]


def test_a_slipping_motor_is_caught_by_the_read_back():
    with FakeStageFirmware({2: "slip"}) as fw:
        stage = homed(fw)
        with pytest.raises(DeviceError, match=r"stage reports 28.500° but 30.000° was commanded"):
            stage.move_to(30.0)
        stage.close()
    assert fw.received.count("MOVE 30.000") == 1


def test_a_disconnect_says_the_port_went_away():
    with FakeStageFirmware({2: "disconnect"}) as fw:
        stage = homed(fw)
        with pytest.raises(DeviceDisconnected, match=r"port .*pts.* the port went away") as info:
            stage.move_to(10.0)
        stage.close()
    assert "resume" in info.value.fix


def test_firmware_errors_are_reported_and_never_retried():
    with FakeStageFirmware() as fw:
        stage = SerialRotaryStage(fw.port, **FAST)
        with pytest.raises(DeviceProtocolError, match=r"command 'MOVE 10.000': the device refused the command "
                                                      r"\(reply 'ERR 3 NOT HOMED'\)"):
            stage.move_to(10.0)
        stage.close()
    assert fw.received == ["MOVE 10.000"]


def test_a_port_that_cannot_be_opened_is_named():
    with pytest.raises(DeviceError, match=r"port /dev/nonexistent-stage: cannot open the port"):
        SerialRotaryStage("/dev/nonexistent-stage")


def test_the_line_protocol_works_over_loop_urls():
    """``serial_for_url`` URLs other than devices: loop:// echoes what is written (here: a framed reply)."""
    line = SerialLine("loop://", timeout_s=0.2)
    assert line.exchange(frame_reply("POS 1.000").decode().rstrip("\n")) == "POS 1.000"
    line.close()


SCENE = Scene.model_validate({
    "scene": "pty",
    "object": {"shape": {"kind": "cylinder", "radius": "10 mm"}, "height": "20 mm",
               "inclusions": [{"shape": {"kind": "cylinder", "radius": "2 mm", "centre": ["4 mm", "0 mm"]},
                               "sigma": "0.3 /mm"}]},
    "light": {"kind": "sheet", "angle": "45 deg", "distance": "100 mm"},
    "camera": {"model": "orthographic", "rows": 4, "cols": 40, "pixel_size": "0.6 mm"},
    "effects": {"noise": {"read_std": 1.0}},
})
ANGLES = np.arange(0.0, 360.0, 30.0)


def serial_rig(firmware: FakeStageFirmware) -> TomographyRig:
    """The simulated rig, but its stage is the real driver talking to the pty firmware."""
    stage = SerialRotaryStage(firmware.port, **FAST)
    beam, backlight, samples = SimLight("beam"), SimLight("backlight"), SimSampleChanger()
    camera = SimCamera(SCENE, stage, beam, backlight, samples)
    return TomographyRig(stage, camera, beam, backlight, samples, simulated_rig(SCENE).attrs)


def test_no_frame_is_ever_recorded_at_a_wrong_angle(tmp_path):
    """Faults mid-sweep: every recorded frame equals the clean frame at its angle; resuming completes it."""
    clean = acquire_tomography(simulated_rig(SCENE), tmp_path / "clean.zarr", ANGLES, progress=False)
    store = tmp_path / "faulty.zarr"
    # commands: HOME, POS?, then per angle k: MOVE (number 2 + 4k), POS? (verify), POS? ×2 (camera).
    # The reply to MOVE 60 is lost (resolved by asking), MOVE 90 slips (a motor losing steps); later
    # the line drops during the reference sweep.
    with FakeStageFirmware({10: "lost-move", 14: "slip"}) as fw:
        rig = serial_rig(fw)
        with pytest.raises(DeviceError, match="stage reports"):
            acquire_tomography(rig, store, ANGLES, progress=False)
        rig.close()
    partial = open_store(store, keep_flags=True).load()
    written = partial["written__target"].values
    assert written.tolist() == [True] * 3 + [False] * 9  # 0°, 30°, 60° captured; 90° refused
    xr.testing.assert_identical(partial.target[written], clean.target.load()[written])
    with FakeStageFirmware({40: "disconnect"}) as fw:
        rig = serial_rig(fw)
        with pytest.raises(DeviceDisconnected):
            acquire_tomography(rig, store, ANGLES, progress=False)
        rig.close()
    with FakeStageFirmware() as fw:
        rig = serial_rig(fw)
        resumed = acquire_tomography(rig, store, ANGLES, progress=False)
        rig.close()
    assert not any(missing_frames(store).values())
    xr.testing.assert_identical(resumed.load(), clean.load())


@pytest.mark.parametrize("fault", ["stray", "late"])
def test_a_stray_or_late_line_is_skipped_not_taken_for_the_reply(fault):
    """The reported stop: a well-formed line arriving before the reply (an unsolicited status line, or the
    previous command's reply arriving late) was called "unexpected reply to MOVE" and stopped the sweep."""
    with FakeStageFirmware({2: fault, 3: fault, 4: fault, 5: fault}) as fw:  # MOVE, POS?, MOVE, POS?
        stage = homed(fw)
        assert [stage.move_to(10.0), stage.move_to(20.0)] == [10.0, 20.0]
        stage.close()
    assert fw.received[2:] == ["MOVE 10.000", "POS?", "MOVE 20.000", "POS?"]  # nothing resent


def _fuzz(faults: tuple[str, ...], rate: float, moves: int, seed: int) -> tuple[int, int, list[str]]:
    """Random faults on a share of commands over ``moves`` moves: (wrong angles, completed moves, errors)."""
    rng = np.random.default_rng(seed)
    schedule = {i: str(rng.choice(faults)) for i in range(2, 4 * moves) if rng.random() < rate}
    wrong, done, errors = 0, 0, []
    with FakeStageFirmware(schedule) as fw:
        stage = homed(fw)
        for target in rng.uniform(0, 360, moves).round(3):
            try:
                reached = stage.move_to(target)
            except DeviceError as exc:
                errors.append(type(exc).__name__)
                continue
            done += 1
            wrong += abs(reached - target) > 0.01 or abs(fw.position - target) > 0.01
        stage.close()
    return wrong, done, errors


def test_fuzzed_stray_and_late_lines_never_stop_a_sweep():
    wrong, done, errors = _fuzz(("stray", "late"), 0.3, 150, seed=14)
    assert (wrong, done, errors) == (0, 150, [])


def test_fuzzed_line_and_motor_faults_never_record_a_wrong_angle():
    """Every fault the firmware knows but a disconnect, on 10 % of commands: moves may fail (a slip, a lost
    reply after retries), but no move ever returns an angle the stage is not at."""
    faults = ("silent", "garble", "partial", "noise", "lost-reply", "stray", "late", "slip")
    wrong, done, errors = _fuzz(faults, 0.1, 200, seed=19)
    assert wrong == 0 and done + len(errors) == 200 and done >= 150
