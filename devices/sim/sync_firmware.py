"""A fake sync-controller firmware on a pseudo-terminal, speaking the protocol of ``docs/devices.md``.

The line faults of :mod:`devices.sim.firmware` apply, plus one of the device's own:

``drift``  apply a ``DELAY``/``EXPO`` three steps off the value asked for, but answer as if it were exact
           (a controller whose counter clock is off); only the read-back catches it.

``python -m devices.sim.sync_firmware`` prints a port a real driver can open.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from devices.protocols import SyncLimits
from devices.sim.firmware import FakeFirmware

#: the limits of the fake controller: ±10 ms delay, 10 µs … 20 ms exposure (one 50 Hz frame), 1 µs step
DEFAULT_LIMITS = SyncLimits(delay_min=-10_000.0, delay_max=10_000.0, exposure_min=10.0, exposure_max=20_000.0,
                            step=1.0)


class FakeSyncFirmware(FakeFirmware):
    """A controller at delay 0 µs, exposure 1000 µs, not armed."""

    DEVICE_FAULTS = ("drift",)
    NAME = "fake-sync-firmware"

    def __init__(self, faults: Mapping[int, str] | None = None, *, limits: SyncLimits = DEFAULT_LIMITS):
        super().__init__(faults)
        self.limits = limits
        self.delay, self.exposure, self.armed = 0.0, 1000.0, False

    def execute(self, command: str, fault: str | None) -> str:
        name, _, argument = command.partition(" ")
        lim = self.limits
        if name == "*IDN?":
            return "IDN selpath,fake-sync,1.0"
        if name == "LIM?":
            return f"LIM {lim.delay_min:.1f} {lim.delay_max:.1f} {lim.exposure_min:.1f} {lim.exposure_max:.1f} " \
                   f"{lim.step:.1f}"
        if name == "STAT?":
            return f"STAT {self.delay:.1f} {self.exposure:.1f} {'ARMED' if self.armed else 'IDLE'}"
        if name == "ARM":
            self.armed = True
            return "OK ARM"
        if name in ("DELAY", "EXPO"):
            try:
                value = float(argument)
            except ValueError:
                return "ERR 2 BAD ARGUMENT"
            low, high = (lim.delay_min, lim.delay_max) if name == "DELAY" else (lim.exposure_min, lim.exposure_max)
            if not low <= value <= high:
                return "ERR 2 OUT OF RANGE"
            applied = round(value / lim.step) * lim.step + (3 * lim.step if fault == "drift" else 0.0)
            with self._lock:
                if name == "DELAY":
                    self.delay = applied
                else:
                    self.exposure = applied
                self.armed = False  # a new setting disarms, as the real circuit does
            return f"OK {name} {value:.1f}"
        return "ERR 1 UNKNOWN COMMAND"


def main() -> None:  # pragma: no cover - interactive helper
    with FakeSyncFirmware() as firmware:
        print(f"fake sync firmware on {firmware.port}; Ctrl-C to stop")
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":  # pragma: no cover
    main()
