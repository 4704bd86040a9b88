"""What an acquisition sweep needs from an instrument, as ``typing.Protocol``s.

A sweep (``selpath.devices.tomography_acquire``) talks only to these protocols, so a real rig
(``selpath.devices.serial_stage``,
``selpath.devices.opencv_camera``, ``selpath.devices.manual``) and the simulated rig (``selpath.devices.sim.rig``) are
interchangeable: a sweep cannot tell one from the other. Every method either does what it says or
raises :class:`~selpath.pipeline.errors.DeviceError` naming the port, the command and the reply.

Angles are in degrees, in the object frame of DESIGN §8 (stage angle φ turns the object
counter-clockwise seen from +z). Sync times are in µs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class RotaryStage(Protocol):
    """A motorised rotary stage carrying the object."""

    def home(self) -> None:
        """Find the stage's index and define it as 0°; blocks until done."""

    def move_to(self, angle_deg: float) -> float:
        """Move to an absolute angle in [0, 360), block until motion ends, and return the *verified* angle.

        Implementations never report an angle they have not read back from the device.
        """

    def position(self) -> float:
        """The stage's current angle as the device reports it, in [0, 360)."""

    def close(self) -> None:
        """Release the port."""


@runtime_checkable
class Camera(Protocol):
    """A camera delivering single frames of a fixed shape."""

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of every frame."""

    def capture(self) -> np.ndarray:
        """One frame, float32 raw counts, shape :attr:`shape`."""

    def close(self) -> None:
        """Release the device."""


@runtime_checkable
class LightSource(Protocol):
    """A light that is either on or off (the narrow beam, the backlight behind the object)."""

    def set(self, on: bool) -> None:
        """Switch the light on or off; blocks until the light is stable."""


@runtime_checkable
class SampleChanger(Protocol):
    """Puts the target or the reference object (§4.4.2) on the stage."""

    def load(self, sample: str) -> None:
        """Make ``sample`` (``"target"`` or ``"reference"``) the object on the stage; blocks until done."""


@runtime_checkable
class SyncController(Protocol):
    """The sync circuit between a raster-scan projector and a rolling-shutter camera (§5.2.2, §5.3.2).

    Times are in µs. ``delay`` is t_d of Eq. 31 (centre of a camera row's exposure minus the centre of the
    illumination of the same projector row); ``exposure`` is t_e. Setters return the value the controller
    *reports back*, never the one that was asked for.
    """

    @property
    def limits(self) -> SyncLimits:
        """What the controller can do: delay and exposure ranges and their step [µs]."""

    def set_delay(self, delay_us: float) -> float:
        """Set t_d; return the verified delay [µs]."""

    def set_exposure(self, exposure_us: float) -> float:
        """Set t_e; return the verified exposure [µs]."""

    def arm(self) -> None:
        """Arm the trigger: the next camera frame starts on the projector's next VSYNC with these settings."""

    def status(self) -> SyncStatus:
        """Delay, exposure and whether the trigger is armed, as the controller reports them."""

    def close(self) -> None:
        """Release the port."""


@runtime_checkable
class Projector(Protocol):
    """A projector showing one pattern (float array in [0, 1], shape :attr:`shape`) at a time."""

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the projector."""

    def show(self, pattern: np.ndarray) -> None:
        """Project ``pattern`` from the next frame on; blocks until it is displayed."""

    def close(self) -> None:
        """Release the device."""


@dataclass(frozen=True)
class SyncLimits:
    """Settings a sync controller accepts [µs]; a sweep outside them is refused before it starts."""

    delay_min: float
    delay_max: float
    exposure_min: float
    exposure_max: float
    step: float = 1.0

    def problems(self, delays, exposures) -> list[str]:
        """Every requested setting the controller cannot do, each naming the limit."""
        out = []
        delays, exposures = np.asarray(delays, float), np.asarray(exposures, float)
        if delays.size and (delays.min() < self.delay_min or delays.max() > self.delay_max):
            out.append(f"delays span [{delays.min():g}, {delays.max():g}] µs; the controller does "
                       f"[{self.delay_min:g}, {self.delay_max:g}] µs")
        if exposures.size and (exposures.min() < self.exposure_min or exposures.max() > self.exposure_max):
            out.append(f"exposures span [{exposures.min():g}, {exposures.max():g}] µs; the controller does "
                       f"[{self.exposure_min:g}, {self.exposure_max:g}] µs")
        for name, values in (("delay", delays), ("exposure", exposures)):
            off = values[np.abs(values / self.step - np.round(values / self.step)) > 1e-6]
            if off.size:
                out.append(f"{name} {off[0]:g} µs is not a multiple of the controller's step {self.step:g} µs")
        return out


@dataclass(frozen=True)
class SyncStatus:
    delay_us: float
    exposure_us: float
    armed: bool
