"""The projector–camera sync controller over a serial line (protocol in ``docs/devices.md``).

Commands: ``*IDN?``, ``LIM?``, ``STAT?`` (idempotent queries, retried a bounded number of times), and
``DELAY <µs>``, ``EXPO <µs>``, ``ARM`` (sent exactly once). When the reply to a setting is lost or garbled
the driver asks ``STAT?`` what the controller holds instead of sending it again, and after every setting it
reads ``STAT?`` back and refuses a value the controller does not confirm, so no frame is ever recorded
with a delay or exposure other than the one in the store's coords.
"""

from __future__ import annotations

from selpath.devices.protocols import SyncLimits, SyncStatus
from selpath.devices.serial_line import SerialLine
from selpath.pipeline.errors import DeviceError, DeviceProtocolError, DeviceTimeout


def _numbers(body: str, count: int, *, port: str, command: str) -> list[float]:
    fields = body.split()[1:]
    try:
        values = [float(v) for v in fields[:count]]
    except ValueError:
        values = []
    if len(values) != count:
        raise DeviceProtocolError(f"expected {count} numbers after {body.split(' ')[0]!r}", port=port,
                                  command=command, reply=body)
    return values


class SerialSyncController:
    """:class:`~selpath.devices.protocols.SyncController` over ``serial.serial_for_url(url)``.

    Parameters
    ----------
    url : str
        ``/dev/ttyACM0``, ``socket://host:port``, a pseudo-terminal, ...
    timeout_s : float
        Time allowed for each reply [s].
    retries : int
        Extra tries of an idempotent query after a timeout or a garbled reply.
    tolerance_us : float or None
        Largest accepted difference between a setting and its read-back [µs]; None: half the
        controller's step.
    """

    def __init__(self, url: str, *, timeout_s: float = 1.0, retries: int = 2, tolerance_us: float | None = None):
        self.line = SerialLine(url, timeout_s=timeout_s)
        self.url, self.retries = url, retries
        self._limits: SyncLimits | None = None
        self._tolerance = tolerance_us

    def identify(self) -> str:
        return self.line.query("*IDN?", expect="IDN", retries=self.retries).partition(" ")[2]

    @property
    def limits(self) -> SyncLimits:
        if self._limits is None:
            body = self.line.query("LIM?", expect="LIM", retries=self.retries)
            dmin, dmax, emin, emax, step = _numbers(body, 5, port=self.url, command="LIM?")
            if not (dmin <= dmax and 0 < emin <= emax and step > 0):
                raise DeviceProtocolError("limits are inconsistent", port=self.url, command="LIM?", reply=body)
            self._limits = SyncLimits(dmin, dmax, emin, emax, step)
        return self._limits

    def status(self) -> SyncStatus:
        body = self.line.query("STAT?", expect="STAT", retries=self.retries)
        delay, exposure = _numbers(body, 2, port=self.url, command="STAT?")
        state = body.split()[-1]
        if state not in ("ARMED", "IDLE"):
            raise DeviceProtocolError(f"unknown state {state!r}", port=self.url, command="STAT?", reply=body)
        return SyncStatus(delay, exposure, state == "ARMED")

    def set_delay(self, delay_us: float) -> float:
        return self._set("DELAY", "delay_us", float(delay_us))

    def set_exposure(self, exposure_us: float) -> float:
        return self._set("EXPO", "exposure_us", float(exposure_us))

    def arm(self) -> None:
        try:
            body = self.line.exchange("ARM", answers=lambda b: b == "OK ARM")
            if body != "OK ARM":
                raise DeviceProtocolError("unexpected reply to ARM", port=self.url, command="ARM", reply=body)
        except (DeviceTimeout, DeviceProtocolError) as exc:
            if isinstance(exc.reply, str) and exc.reply.startswith("ERR"):
                raise
        if not self._confirmed("ARM").armed:
            raise DeviceError("the controller does not report itself armed after ARM", port=self.url,
                              command="ARM", fix="check the sync circuit, then run the acquisition again to resume")

    def close(self) -> None:
        self.line.close()

    def _set(self, keyword: str, field: str, value: float) -> float:
        command = f"{keyword} {value:.1f}"
        after = ""
        try:
            body = self.line.exchange(command, answers=lambda b: b == f"OK {keyword} {value:.1f}")
            if body != f"OK {keyword} {value:.1f}":
                raise DeviceProtocolError(f"unexpected reply to {keyword}", port=self.url, command=command,
                                          reply=body)
        except (DeviceTimeout, DeviceProtocolError) as exc:
            if isinstance(exc.reply, str) and exc.reply.startswith("ERR"):
                raise  # refused: nothing changed
            after = f" (the reply was lost: {exc.message})"  # never resend blindly; ask what it holds
        actual = getattr(self._confirmed(command), field)
        tolerance = self._tolerance if self._tolerance is not None else self.limits.step / 2
        if abs(actual - value) > tolerance:
            raise DeviceError(f"controller reports {field.removesuffix('_us')} {actual:g} µs but {value:g} µs was "
                              f"set{after}", port=self.url, command=command,
                              fix="check the sync circuit's clock, then run the acquisition again to resume")
        return actual

    def _confirmed(self, command: str) -> SyncStatus:
        try:
            return self.status()
        except DeviceError as exc:
            raise type(exc)(f"cannot confirm {command!r}: {exc.command} failed: {exc.message}", port=self.url,
                            command=command, reply=exc.reply,
                            fix=exc.fix or "check the controller, then run the acquisition again to resume") from exc
