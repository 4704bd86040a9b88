"""The ASCII line transport under every serial driver (``docs/devices.md``, "Line protocol").

One command per line, one reply per command. Every reply ends in ``*HH``, the XOR of its bytes before
``*`` in two hex digits (the NMEA 0183 checksum), so a garbled reply is caught instead of parsed. The
transport only moves lines; what a reply means is the driver's, which says which lines answer its command
(``answers``): a well-formed line that does not (a late reply to an earlier command, an unsolicited
status line) is skipped, not taken for the answer, until the answer or the timeout comes. It raises typed errors:
:class:`~selpath.pipeline.errors.DeviceTimeout` (no complete line in time, the partial bytes shown),
:class:`~selpath.pipeline.errors.DeviceProtocolError` (bad checksum, not ASCII, or an ``ERR`` reply) and
:class:`~selpath.pipeline.errors.DeviceDisconnected` (the port went away). Only :meth:`SerialLine.query`
retries, and only for commands the caller declares idempotent.

Any URL pyserial knows works: ``/dev/ttyUSB0``, ``socket://host:port``, ``loop://``, a pseudo-terminal.
"""

from __future__ import annotations

import serial

try:  # a pty or tty closing under pyserial's flush() raises termios.error, which is not an OSError
    import termios

    PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
except ImportError:  # Windows
    PORT_ERRORS = (serial.SerialException, OSError)

import time
from collections.abc import Callable

from selpath.pipeline.errors import DeviceDisconnected, DeviceError, DeviceProtocolError, DeviceTimeout

#: most well-formed lines that do not answer a command skipped while waiting for its answer
MAX_STRAY_LINES = 16


def checksum(body: str) -> str:
    """Two hex digits of the XOR of the bytes of ``body`` (NMEA 0183).

    >>> checksum("POS 12.500")
    '74'
    """
    value = 0
    for byte in body.encode("ascii"):
        value ^= byte
    return f"{value:02X}"


def frame_reply(body: str) -> bytes:
    """A reply line as a device sends it: ``body*HH\\n``."""
    return f"{body}*{checksum(body)}\n".encode("ascii")


class SerialLine:
    """A serial port speaking one-line commands and checksummed one-line replies."""

    def __init__(self, url: str, *, timeout_s: float = 1.0, baudrate: int = 115200):
        self.url, self.timeout_s = url, timeout_s
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s)
        except (*PORT_ERRORS, ValueError) as exc:
            raise DeviceError(f"cannot open the port ({exc})", port=url,
                              fix="check the cable, the port name and that no other program holds it") from exc

    def close(self) -> None:
        try:
            self._port.close()
        except PORT_ERRORS:
            pass  # closing a port that already went away is not an error

    def exchange(self, command: str, *, timeout_s: float | None = None,
                 answers: Callable[[str], bool] | None = None) -> str:
        """Send ``command`` once and return the checksum-verified body of the line that answers it.

        ``answers(body)`` says whether a well-formed line answers ``command`` (None: the first line does);
        others are skipped while the timeout lasts, and named in the error if no answer comes. An ``ERR``
        line always answers. A garbled line is an error at once (it may have been the answer).
        """
        timeout = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        strays: list[str] = []
        try:
            self._port.reset_input_buffer()  # a late reply to an earlier command must not answer this one
            self._port.write(f"{command}\n".encode("ascii"))
            self._port.flush()
            while True:
                self._port.timeout = max(deadline - time.monotonic(), 0.0)
                raw = self._port.read_until(b"\n")
                if not raw.endswith(b"\n"):
                    what = "no reply" if not raw else "an incomplete reply"
                    if strays:
                        what = f"no line answering it (skipped {len(strays)} that did not: {strays})"
                    raise DeviceTimeout(f"{what} within {timeout:g} s", port=self.url, command=command,
                                        reply=raw if raw else None)
                body = self._verify(command, raw)
                if answers is None or answers(body) or len(strays) >= MAX_STRAY_LINES:
                    return body
                strays.append(body)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeout("the port did not accept the command in time", port=self.url,
                                command=command) from exc
        except PORT_ERRORS as exc:
            raise DeviceDisconnected(f"the port went away ({exc})", port=self.url, command=command,
                                     fix="reconnect the device, then run the acquisition again to resume") from exc

    def _verify(self, command: str, raw: bytes) -> str:
        try:
            line = raw.decode("ascii").rstrip("\r\n")
        except UnicodeDecodeError:
            raise DeviceProtocolError("reply is not ASCII", port=self.url, command=command, reply=raw) from None
        body, star, digits = line.rpartition("*")
        if not star or digits.upper() != checksum(body):
            raise DeviceProtocolError("reply fails its checksum (garbled line)", port=self.url, command=command,
                                      reply=raw)
        if body.startswith("ERR"):
            raise DeviceProtocolError("the device refused the command", port=self.url, command=command, reply=body)
        return body

    def query(self, command: str, *, expect: str, retries: int = 2, timeout_s: float | None = None) -> str:
        """An idempotent query: resend up to ``retries`` times on timeout or garble; ``ERR`` is never retried.

        ``expect`` is the keyword the reply must start with, so a stray reply to another command is
        rejected (and retried) instead of being taken for this one's.
        """
        last: DeviceError | None = None
        for _ in range(retries + 1):
            try:
                body = self.exchange(command, timeout_s=timeout_s, answers=lambda b: b.split(" ", 1)[0] == expect)
            except DeviceTimeout as exc:
                last = exc
                continue
            except DeviceProtocolError as exc:
                if isinstance(exc.reply, str) and exc.reply.startswith("ERR"):
                    raise
                last = exc
                continue
            if body.split(" ", 1)[0] == expect:
                return body
            last = DeviceProtocolError(f"reply does not answer the command (expected {expect!r})",
                                       port=self.url, command=command, reply=body)
        assert last is not None
        raise type(last)(f"{retries + 1} tries failed, the last with: {last.message}", port=self.url,
                         command=command, reply=last.reply, fix=last.fix)
