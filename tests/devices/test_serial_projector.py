"""The projector driven through the sync controller's line (devices.serial_projector) against the fake firmware
on a pseudo-terminal: patterns kept by content in the controller's slots, uploads verified by their checksum,
displays confirmed by read-back, the line's faults resolved without resending a display command."""

from __future__ import annotations

import numpy as np
import pytest

from selpath.devices.patterns import checkerboard, vertical_line
from selpath.devices.serial_line import SerialLine
from selpath.devices.serial_projector import SyncLineProjector, quantise
from selpath.devices.sim.procam_rig import FakeProcamHardware
from selpath.pipeline.errors import DeviceError
from tests.helpers.procam_hardware import scene


def _projector(hardware: FakeProcamHardware, timeout_s: float = 0.3) -> SyncLineProjector:
    return SyncLineProjector(SerialLine(hardware.port, timeout_s=timeout_s))


def test_patterns_are_kept_by_content_and_the_least_recently_used_slot_is_reused():
    boards = [checkerboard((16, 32), 4, (0, s)) for s in (0, 2, 4)]
    with FakeProcamHardware(scene(), slots=2) as hardware:
        projector = _projector(hardware)
        for board in (boards[0], boards[1], boards[0], boards[2], boards[0], boards[1]):
            projector.show(board)
            np.testing.assert_array_equal(hardware.projector.pattern, board)
            assert projector.showing().startswith("SLOT ")
        # 0 and 1 uploaded; 0 again from its slot; 2 replaces 1 (used longest ago); 0 kept; 1 uploaded again
        assert projector.uploads == 4
        projector.line.close()


def test_grey_levels_are_shown_at_the_projectors_8_bits_and_bad_patterns_are_refused():
    ramp = np.broadcast_to(np.linspace(0, 1, 32), (16, 32))
    with FakeProcamHardware(scene()) as hardware:
        projector = _projector(hardware)
        projector.show(ramp)
        np.testing.assert_array_equal(hardware.projector.pattern, np.rint(ramp * 255) / 255)
        assert np.max(np.abs(hardware.projector.pattern - ramp)) <= 0.5 / 255
        for bad, message in ((ramp * 2, r"spans \[0, 2\]"), (np.full((16, 32), np.nan), "NaN"),
                             (np.ones((8, 32)), r"pattern is \(8, 32\); the projector is \(16, 32\)")):
            with pytest.raises(DeviceError, match=message):
                projector.show(bad)
        projector.show_line(7.0, 2.0)
        np.testing.assert_array_equal(hardware.projector.pattern,
                                      np.rint(vertical_line((16, 32), 7.0, 2.0) * 255) / 255)
        projector.line.close()


def test_a_corrupted_upload_is_caught_by_its_checksum_and_sent_again():
    """The firmware stores a row with a flipped byte but answers OK: the slot's CRC-32 differs, the pattern is
    uploaded again, and what is shown is the pattern. Corrupted twice: an error naming slot and checksums."""
    board = checkerboard((16, 32), 4)
    rows = 16
    first_row, second_upload_row = 2, rows + 4  # PROJ?, UPLOAD, ROW×16, SUM?, UPLOAD, ROW…
    with FakeProcamHardware(scene(), faults={first_row: "corrupt"}) as hardware:
        projector = _projector(hardware)
        projector.show(board)
        np.testing.assert_array_equal(hardware.projector.pattern, board)
        assert projector.uploads == 2
        projector.line.close()
    with FakeProcamHardware(scene(), faults={first_row: "corrupt", second_upload_row: "corrupt"}) as hardware:
        projector = _projector(hardware)
        with pytest.raises(DeviceError, match=r"slot 0 holds a pattern with CRC-32 [0-9A-F]{8}, not the "
                                              r"[0-9A-F]{8} uploaded \(2 uploads\)"):
            projector.show(board)
        assert hardware.projector.pattern is None  # still the white it started with: the board was never shown
        projector.line.close()


@pytest.mark.parametrize("fault", ["lost-reply", "garble", "late", "stray", "noise"])
@pytest.mark.parametrize("at", ["ROW", "SHOW", "LINE"])
def test_line_faults_on_pattern_commands_are_resolved(fault, at):
    """A lost or garbled reply to a row is answered by writing the row again (idempotent); to SHOW or LINE by
    asking PAT? what is shown, never by resending; either way the right pattern is on the projector."""
    board = checkerboard((16, 32), 4)
    index = {"ROW": 2, "SHOW": 19, "LINE": 0}[at]  # PROJ?, UPLOAD, ROW×16, SUM?, SHOW / LINE
    with FakeProcamHardware(scene(), faults={index: fault}) as hardware:
        projector = _projector(hardware)
        if at == "LINE":
            projector.show_line(5.0, 3.0)
            want = vertical_line((16, 32), 5.0, 3.0)
        else:
            projector.show(board)
            want = board
        assert hardware.firmware.received[index].startswith(at)
        np.testing.assert_array_equal(hardware.projector.pattern, want)
        assert sum(c.startswith(("SHOW", "LINE")) for c in hardware.firmware.received) == 1  # never resent
        projector.line.close()


def test_a_projector_that_shows_something_else_is_caught_by_the_read_back(monkeypatch):
    from selpath.devices.sim.projector_firmware import PatternMemory

    real = PatternMemory._show

    def stuck(self, args, fault):  # acknowledges, changes nothing
        real(self, args, fault)
        self.shown = "NONE"
        return f"OK SHOW {args[0]}"

    monkeypatch.setattr(PatternMemory, "_show", stuck)
    with FakeProcamHardware(scene()) as hardware:
        projector = _projector(hardware)
        with pytest.raises(DeviceError, match=r"the controller shows 'NONE' after 'SHOW 0'"):
            projector.show(checkerboard((16, 32), 4))
        projector.line.close()


def test_quantise_is_the_projectors_grey_levels():
    assert quantise(np.array([0.0, 0.5, 1.0, 1 / 255, 0.3])).tolist() == [0, 128, 255, 1, 76]
