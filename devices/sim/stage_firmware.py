"""A fake rotary-stage firmware on a pseudo-terminal, speaking the protocol of ``docs/devices.md``.

The driver under test opens :attr:`FakeStageFirmware.port` (a real ``/dev/pts/N``) with pyserial, so
the whole serial path runs. Faults are scheduled by command number (0-based, in the order the
firmware receives them) and reproduce what real hardware does:

``silent``      read the command, never answer (a dropped reply);
``garble``      answer with a corrupted byte (the checksum no longer matches);
``partial``     answer half a line, without its newline, and stop;
``noise``       answer bytes that are not ASCII;
``disconnect``  close the line (cable pulled): every later read fails;
``slip``        perform a MOVE short by 1.5° but report success (a motor losing steps);
``lost-move``   perform the MOVE, then lose its reply (the host must ask where the stage is).

Use it as a context manager; it runs in a daemon thread. Also usable by hand:
``python -m selpath.devices.sim.stage_firmware`` prints a port a real driver can open.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from selpath.devices.serial_line import checksum
from selpath.devices.sim.firmware import LINE_FAULTS, FakeFirmware, serve_by_hand

FAULTS = (*LINE_FAULTS, "slip", "lost-move")


class FakeStageFirmware(FakeFirmware):
    """A stage at 0°, not homed, answering on a pseudo-terminal."""

    DEVICE_FAULTS = ("slip",)
    ALIASES = {"lost-move": "lost-reply"}
    NAME = "fake-stage-firmware"

    def __init__(self, faults: Mapping[int, str] | None = None, *, move_s_per_deg: float = 0.0):
        super().__init__(faults)
        self.move_s_per_deg = move_s_per_deg
        self.position = 0.0
        self.homed = False

    def execute(self, command: str, fault: str | None) -> str:
        slip = fault == "slip"
        name, _, argument = command.partition(" ")
        if name == "*IDN?":
            return "IDN selpath,fake-stage,1.0"
        if name == "POS?":
            return f"POS {self.position:.3f}"
        if name == "HOME":
            self._travel(0.0)
            self.homed = True
            return "OK HOME"
        if name == "MOVE":
            if not self.homed:
                return "ERR 3 NOT HOMED"
            try:
                target = float(argument)
            except ValueError:
                return "ERR 2 BAD ARGUMENT"
            if not 0.0 <= target < 360.0:
                return "ERR 2 OUT OF RANGE"
            self._travel((target - 1.5) % 360.0 if slip else target)
            return f"OK MOVE {target:.3f}"
        return "ERR 1 UNKNOWN COMMAND"

    def _travel(self, target: float) -> None:
        if self.move_s_per_deg:
            time.sleep(abs(target - self.position) * self.move_s_per_deg)
        with self._lock:
            self.position = target


if __name__ == "__main__":  # pragma: no cover
    serve_by_hand(FakeStageFirmware(), "fake stage firmware", f" (checksum of 'POS 0.000' is {checksum('POS 0.000')})")
