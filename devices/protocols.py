"""What an acquisition sweep needs from an instrument, as ``typing.Protocol``s.

A sweep (``devices.acquire``) talks only to these protocols, so a real rig (``devices.serial_stage``,
``devices.opencv_camera``, ``devices.manual``) and the simulated rig (``devices.sim.rig``) are
interchangeable: a sweep cannot tell one from the other. Every method either does what it says or
raises :class:`~pipeline.errors.DeviceError` naming the port, the command and the reply.

Angles are in degrees, in the object frame of DESIGN §8 (stage angle φ turns the object
counter-clockwise seen from +z).
"""

from __future__ import annotations

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
