"""A motorised rotary stage over a serial line (protocol in ``docs/devices.md``).

Commands (one line each): ``*IDN?``, ``HOME``, ``MOVE <deg>``, ``POS?``. Queries (``*IDN?``, ``POS?``)
are idempotent and retried a bounded number of times; ``HOME`` and ``MOVE`` are sent exactly once. Only
the line that answers a command counts (``OK MOVE <the commanded angle>``): a stray or late well-formed
line is skipped while the reply's timeout lasts. When
the reply to a move is lost or garbled, the driver asks the stage where it is instead of moving again;
after every move it reads the position back and refuses to report an angle the stage does not confirm.
"""

from __future__ import annotations

from selpath.devices.serial_line import SerialLine
from selpath.pipeline.errors import DeviceError, DeviceProtocolError, DeviceTimeout


def _angle(text: str, *, port: str, command: str, reply: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise DeviceProtocolError(f"{text!r} is not an angle", port=port, command=command, reply=reply) from None
    if not 0.0 <= value < 360.0:
        raise DeviceProtocolError(f"angle {value} is outside [0, 360)", port=port, command=command, reply=reply)
    return value


def angular_distance(a: float, b: float) -> float:
    """Distance between two angles on the circle, degrees in [0, 180].

    >>> angular_distance(359.9, 0.1)
    0.2
    """
    d = abs(a - b) % 360.0
    return round(min(d, 360.0 - d), 12)


class SerialRotaryStage:
    """:class:`~selpath.devices.protocols.RotaryStage` over ``serial.serial_for_url(url)``.

    Parameters
    ----------
    url : str
        ``/dev/ttyUSB0``, ``socket://host:port``, a pseudo-terminal, ...
    timeout_s : float
        Time allowed for a query's reply [s].
    move_timeout_s : float
        Time allowed for a move or homing to finish and be confirmed [s].
    retries : int
        Extra tries of an idempotent query after a timeout or a garbled reply.
    tolerance_deg : float
        Largest accepted difference between the commanded and the read-back angle [degree].
    """

    def __init__(self, url: str, *, timeout_s: float = 1.0, move_timeout_s: float = 30.0, retries: int = 2,
                 tolerance_deg: float = 0.01):
        self.line = SerialLine(url, timeout_s=timeout_s)
        self.url, self.move_timeout_s, self.retries, self.tolerance_deg = url, move_timeout_s, retries, tolerance_deg

    def identify(self) -> str:
        return self.line.query("*IDN?", expect="IDN", retries=self.retries).partition(" ")[2]

    def position(self) -> float:
        body = self.line.query("POS?", expect="POS", retries=self.retries)
        return _angle(body.partition(" ")[2], port=self.url, command="POS?", reply=body)

    def home(self) -> None:
        body = self.line.exchange("HOME", timeout_s=self.move_timeout_s, answers=lambda b: b.startswith("OK HOME"))
        if body != "OK HOME":
            raise DeviceProtocolError("unexpected reply to HOME", port=self.url, command="HOME", reply=body)
        self._verify("HOME", 0.0)

    def move_to(self, angle_deg: float) -> float:
        target = float(angle_deg) % 360.0
        command = f"MOVE {target:.3f}"
        try:
            body = self.line.exchange(command, timeout_s=self.move_timeout_s,  # a late OK of an earlier move: skipped
                                      answers=lambda b: b == f"OK MOVE {target:.3f}")
        except (DeviceTimeout, DeviceProtocolError) as exc:
            if isinstance(exc.reply, str) and exc.reply.startswith("ERR"):
                raise  # the firmware refused: it did not move
            # The reply was lost or garbled: the stage may or may not have moved. Never move again
            # blindly; ask where it is and accept only a confirmed arrival.
            return self._verify(command, target, after=f"the reply was lost ({exc})")
        keyword, _, value = body.partition(" MOVE ")
        if keyword != "OK":
            raise DeviceProtocolError("unexpected reply to MOVE", port=self.url, command=command, reply=body)
        _angle(value, port=self.url, command=command, reply=body)
        return self._verify(command, target)

    def _verify(self, command: str, target: float, after: str = "") -> float:
        try:
            actual = self.position()
        except DeviceError as exc:  # same class (timeout, garble, disconnect), with the move it followed
            raise type(exc)(f"cannot confirm the stage's angle{'; ' + after if after else ''}: "
                            f"{exc.command} failed: {exc.message}", port=self.url, command=command, reply=exc.reply,
                            fix=exc.fix or "check the stage, then run the acquisition again to resume") from exc
        if angular_distance(actual, target) > self.tolerance_deg:
            raise DeviceError(f"stage reports {actual:.3f}° but {target:.3f}° was commanded"
                              + (f" ({after})" if after else ""), port=self.url, command=command,
                              fix="home the stage and run the acquisition again to resume")
        return actual

    def close(self) -> None:
        self.line.close()
