"""The serial sync-controller driver against a fake firmware on a real pseudo-terminal (pyserial end to end)."""

from __future__ import annotations

import pytest

from selpath.devices.protocols import SyncController, SyncLimits
from selpath.devices.serial_sync import SerialSyncController
from selpath.devices.sim.sync_firmware import DEFAULT_LIMITS, FakeSyncFirmware
from selpath.pipeline.errors import DeviceDisconnected, DeviceError, DeviceProtocolError, DeviceTimeout


def driver(fw: FakeSyncFirmware) -> SerialSyncController:
    return SerialSyncController(fw.port, timeout_s=0.2)


def test_settings_are_sent_once_and_each_is_read_back():
    with FakeSyncFirmware() as fw:
        sync = driver(fw)
        assert isinstance(sync, SyncController)
        assert sync.identify() == "selpath,fake-sync,1.0"
        assert sync.set_delay(-1700) == -1700.0
        assert sync.set_exposure(170) == 170.0
        sync.arm()
        status = sync.status()
        sync.close()
    assert (status.delay_us, status.exposure_us, status.armed) == (-1700.0, 170.0, True)
    # LIM? is asked once (the protocol check reads the property) and cached for the read-back tolerance
    assert fw.received == ["LIM?", "*IDN?", "DELAY -1700.0", "STAT?", "EXPO 170.0", "STAT?", "ARM", "STAT?",
                           "STAT?"]


def test_limits_are_read_from_the_controller():
    with FakeSyncFirmware() as fw:
        sync = driver(fw)
        assert sync.limits == DEFAULT_LIMITS
        sync.close()


@pytest.mark.parametrize("fault", ["silent", "garble", "partial", "noise"])
def test_a_lost_or_garbled_reply_to_a_setting_is_resolved_by_asking_not_by_resending(fault):
    with FakeSyncFirmware({0: fault}) as fw:
        sync = driver(fw)
        assert sync.set_delay(850) == 850.0
        sync.close()
    assert fw.received.count("DELAY 850.0") == 1  # never resent
    assert fw.received[1] == "STAT?"


def test_lost_reply_to_arm_is_confirmed_by_status():
    with FakeSyncFirmware({0: "lost-reply"}) as fw:
        sync = driver(fw)
        sync.arm()
        sync.close()
    assert fw.received == ["ARM", "STAT?"]


def test_a_drifting_controller_is_caught_by_the_read_back():
    with FakeSyncFirmware({0: "drift"}) as fw:
        sync = driver(fw)
        with pytest.raises(DeviceError, match=r"reports exposure 343 µs but 340 µs was set") as info:
            sync.set_exposure(340)
        sync.close()
    assert info.value.port == fw.port and info.value.command == "EXPO 340.0"


def test_out_of_range_is_refused_by_the_firmware_and_not_retried():
    with FakeSyncFirmware() as fw:
        sync = driver(fw)
        with pytest.raises(DeviceProtocolError, match="ERR 2 OUT OF RANGE"):
            sync.set_delay(20_000)
        sync.close()
    assert fw.received == ["DELAY 20000.0"]


def test_status_is_retried_a_bounded_number_of_times():
    with FakeSyncFirmware({0: "silent", 1: "silent", 2: "silent"}) as fw:
        sync = driver(fw)
        with pytest.raises(DeviceTimeout, match=r"3 tries failed") as info:
            sync.status()
        sync.close()
    assert info.value.command == "STAT?" and fw.port in str(info.value)


def test_disconnect_names_the_port():
    with FakeSyncFirmware({0: "disconnect"}) as fw:
        sync = driver(fw)
        with pytest.raises((DeviceDisconnected, DeviceTimeout)) as info:
            sync.set_delay(0)
        sync.close()
    assert info.value.port == fw.port


def test_limits_name_every_setting_the_controller_cannot_do():
    limits = SyncLimits(-1000, 1000, 10, 2000, step=1.0)
    problems = limits.problems([-1700, 0, 1700], [5, 170, 0.5])
    assert any("delays span [-1700, 1700] µs; the controller does [-1000, 1000] µs" in p for p in problems)
    assert any("exposures span [0.5, 170] µs; the controller does [10, 2000] µs" in p for p in problems)
    assert any("exposure 0.5 µs is not a multiple" in p for p in problems)
    assert limits.problems([-850, 0, 850], [170, 850]) == []
