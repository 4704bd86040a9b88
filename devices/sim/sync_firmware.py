"""The sync controller's behaviour, simulated: :class:`SimSyncController` (what the simulated rig drives
directly) and :class:`FakeSyncFirmware`, the same state machine speaking the protocol of ``docs/devices.md``
on a pseudo-terminal for the serial driver's tests.

The line faults of :mod:`selpath.devices.sim.firmware` apply, plus one of the device's own:

``drift``  apply a ``DELAY``/``EXPO`` three steps off the value asked for (within the limits), but answer as
           if it were exact (a controller whose counter clock is off); only the read-back catches it.
``corrupt`` store a pattern ``ROW`` with one byte flipped but answer ``OK``
(:mod:`selpath.devices.sim.projector_firmware`);
           only the slot's checksum catches it.

With a ``screen`` (e.g. the simulated projector) the firmware also drives the projector: the pattern commands
of :mod:`selpath.devices.sim.projector_firmware`.

``python -m selpath.devices.sim.sync_firmware`` prints a port a real driver can open.
"""

from __future__ import annotations

from collections.abc import Mapping

from selpath.devices.protocols import SyncLimits, SyncStatus
from selpath.devices.sim.firmware import FakeFirmware, serve_by_hand
from selpath.devices.sim.projector_firmware import PatternMemory
from selpath.pipeline.errors import DeviceError

#: the limits of the simulated controller: ±10 ms delay, 10 µs … 20 ms exposure (one 50 Hz frame), 1 µs step
DEFAULT_LIMITS = SyncLimits(delay_min=-10_000.0, delay_max=10_000.0, exposure_min=10.0, exposure_max=20_000.0,
                            step=1.0)


class SimSyncController:
    """A sync controller that holds exactly what it is set to (rounded to its step), refuses settings outside
    its limits, and disarms on every new setting, as the circuit does."""

    def __init__(self, limits: SyncLimits = DEFAULT_LIMITS) -> None:
        self._limits = limits
        self._status = SyncStatus(0.0, 1000.0, False)

    @property
    def limits(self) -> SyncLimits:
        return self._limits

    def _check(self, name: str, value: float, low: float, high: float) -> float:
        if not low <= value <= high:
            raise DeviceError(f"{name} {value:g} µs is outside [{low:g}, {high:g}] µs", port="sim",
                              command=f"{name.upper()} {value:.1f}", reply="ERR 2 OUT OF RANGE")
        return round(value / self._limits.step) * self._limits.step

    def set_delay(self, delay_us: float) -> float:
        value = self._check("delay", float(delay_us), self._limits.delay_min, self._limits.delay_max)
        self._status = SyncStatus(value, self._status.exposure_us, False)
        return value

    def set_exposure(self, exposure_us: float) -> float:
        value = self._check("exposure", float(exposure_us), self._limits.exposure_min, self._limits.exposure_max)
        self._status = SyncStatus(self._status.delay_us, value, False)
        return value

    def arm(self) -> None:
        self._status = SyncStatus(self._status.delay_us, self._status.exposure_us, True)

    def disarm(self) -> None:
        self._status = SyncStatus(self._status.delay_us, self._status.exposure_us, False)

    def status(self) -> SyncStatus:
        return self._status

    def close(self) -> None:
        pass


class FakeSyncFirmware(FakeFirmware):
    """A :class:`SimSyncController` (delay 0 µs, exposure 1000 µs, not armed) answering on a pseudo-terminal;
    with a ``screen`` (anything with ``show(pattern)``) also the projector's ``projector_shape`` pattern memory."""

    DEVICE_FAULTS = ("drift", "corrupt")
    NAME = "fake-sync-firmware"

    def __init__(self, faults: Mapping[int, str] | None = None, *, limits: SyncLimits = DEFAULT_LIMITS,
                 screen=None, projector_shape: tuple[int, int] = (720, 1280), slots: int = 8):
        super().__init__(faults)
        self.controller = SimSyncController(limits)
        self.patterns = PatternMemory(projector_shape, screen, slots) if screen is not None else None

    def execute(self, command: str, fault: str | None) -> str:
        name, _, argument = command.partition(" ")
        lim = self.controller.limits
        if self.patterns is not None:
            with self._lock:
                reply = self.patterns.execute(name, argument, fault)
            if reply is not None:
                return reply
        if name == "*IDN?":
            return "IDN selpath,fake-sync,1.0"
        if name == "LIM?":
            return f"LIM {lim.delay_min:.1f} {lim.delay_max:.1f} {lim.exposure_min:.1f} {lim.exposure_max:.1f} " \
                   f"{lim.step:.1f}"
        if name == "STAT?":
            status = self.controller.status()
            return f"STAT {status.delay_us:.1f} {status.exposure_us:.1f} {'ARMED' if status.armed else 'IDLE'}"
        if name == "ARM":
            self.controller.arm()
            return "OK ARM"
        if name in ("DELAY", "EXPO"):
            try:
                value = float(argument)
            except ValueError:
                return "ERR 2 BAD ARGUMENT"
            setter = self.controller.set_delay if name == "DELAY" else self.controller.set_exposure
            try:
                with self._lock:
                    setter(value)
                    if fault == "drift":
                        setter(value + 3 * lim.step)
            except DeviceError:
                return "ERR 2 OUT OF RANGE"
            return f"OK {name} {value:.1f}"
        return "ERR 1 UNKNOWN COMMAND"


if __name__ == "__main__":  # pragma: no cover
    serve_by_hand(FakeSyncFirmware(), "fake sync firmware")
