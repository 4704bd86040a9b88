"""A fake device firmware on a pseudo-terminal: the line loop and the faults every serial device can show.

Device firmwares (:mod:`selpath.devices.sim.stage_firmware`, :mod:`selpath.devices.sim.sync_firmware`) subclass
:class:`FakeFirmware` and implement :meth:`FakeFirmware.execute`. The driver under test opens
:attr:`FakeFirmware.port` (a real ``/dev/pts/N``) with pyserial, so the whole serial path runs. Faults are
scheduled by command number (0-based, in the order the firmware receives them):

``silent``      read the command, never answer (a dropped reply);
``garble``      answer with a corrupted byte (the checksum no longer matches);
``partial``     answer half a line, without its newline, and stop;
``noise``       answer bytes that are not ASCII;
``disconnect``  close the line (cable pulled): every later read fails;
``lost-reply``  perform the command, then lose its reply (the host must ask what happened);
``stray``       send an unsolicited well-formed status line (``EVT …``) just before the reply;
``late``        send the previous command's reply again (arriving late) just before this one's.

Subclasses add device faults (``DEVICE_FAULTS``), handed to ``execute``. Use as a context manager; the
firmware runs in a daemon thread.
"""

from __future__ import annotations

import os
import pty
import select
import threading
import time
import tty
from collections.abc import Mapping

from selpath.devices.serial_line import frame_reply

LINE_FAULTS = ("silent", "garble", "partial", "noise", "disconnect", "lost-reply", "stray", "late")


class FakeFirmware:
    """A device answering one checksummed line per command on a pseudo-terminal."""

    #: faults the device itself can show (handed to :meth:`execute`), beyond the line faults
    DEVICE_FAULTS: tuple[str, ...] = ()
    #: other names of line faults, kept for the device's vocabulary
    ALIASES: Mapping[str, str] = {}
    NAME = "fake-firmware"

    def __init__(self, faults: Mapping[int, str] | None = None):
        known = (*LINE_FAULTS, *self.DEVICE_FAULTS, *self.ALIASES)
        unknown = sorted(set((faults or {}).values()) - set(known))
        if unknown:
            raise ValueError(f"unknown faults {unknown}; known: {known}")
        self.faults = {k: self.ALIASES.get(v, v) for k, v in (faults or {}).items()}
        self.received: list[str] = []
        self._previous_reply = b""
        self._master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=self.NAME, daemon=True)
        self._lock = threading.Lock()

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass  # already closed by a "disconnect" fault

    def execute(self, command: str, fault: str | None) -> str:
        """Do ``command`` (with a device fault, if one is scheduled) and return the reply body."""
        raise NotImplementedError

    # -- the firmware loop -------------------------------------------------------------------------

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                chunk = os.read(self._master, 1024)
            except OSError:
                return  # the line is closed
            buffer += chunk
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                if not self._answer(line.decode("ascii", "replace").strip()):
                    return

    def _send(self, data: bytes) -> None:
        os.write(self._master, data)

    def _answer(self, command: str) -> bool:
        number = len(self.received)
        self.received.append(command)
        fault = self.faults.get(number)
        if fault == "disconnect":
            os.close(self._master)
            return False
        body = self.execute(command, fault if fault in self.DEVICE_FAULTS else None)
        if fault in ("silent", "lost-reply"):
            return True
        reply = frame_reply(body)
        if fault == "garble":
            i = min(len(reply) - 5, len(body) // 2)
            reply = reply[:i] + bytes([reply[i] ^ 0x01]) + reply[i + 1:]
        elif fault == "partial":
            reply = reply[: len(reply) // 2]
        elif fault == "noise":
            reply = b"\xff\xfe\x00garbage\n"
        elif fault == "stray":
            self._send(frame_reply("EVT TEMPERATURE 31.5"))
        elif fault == "late" and self._previous_reply:
            self._send(self._previous_reply)
        self._previous_reply = reply
        self._send(reply)
        return True


def serve_by_hand(firmware: FakeFirmware, what: str, hint: str = "") -> None:  # pragma: no cover - interactive
    """Run ``firmware`` until Ctrl-C, printing the port a real driver can open."""
    with firmware:
        print(f"{what} on {firmware.port}{hint}; Ctrl-C to stop")
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass
