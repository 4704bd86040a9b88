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
``python -m devices.sim.stage_firmware`` prints a port a real driver can open.
"""

from __future__ import annotations

import os
import pty
import select
import threading
import time
import tty
from collections.abc import Mapping

from devices.serial_line import checksum, frame_reply

FAULTS = ("silent", "garble", "partial", "noise", "disconnect", "slip", "lost-move")


class FakeStageFirmware:
    """A stage at 0°, not homed, answering on a pseudo-terminal."""

    def __init__(self, faults: Mapping[int, str] | None = None, *, move_s_per_deg: float = 0.0):
        unknown = sorted(set((faults or {}).values()) - set(FAULTS))
        if unknown:
            raise ValueError(f"unknown faults {unknown}; known: {FAULTS}")
        self.faults = dict(faults or {})
        self.move_s_per_deg = move_s_per_deg
        self.position = 0.0
        self.homed = False
        self.received: list[str] = []
        self._master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="fake-stage-firmware", daemon=True)
        self._lock = threading.Lock()

    def __enter__(self) -> FakeStageFirmware:
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
        body = self._execute(command, slip=fault == "slip")
        if fault in ("silent", "lost-move"):
            return True
        reply = frame_reply(body)
        if fault == "garble":
            i = min(len(reply) - 5, len(body) // 2)
            reply = reply[:i] + bytes([reply[i] ^ 0x01]) + reply[i + 1:]
        elif fault == "partial":
            reply = reply[: len(reply) // 2]
        elif fault == "noise":
            reply = b"\xff\xfe\x00garbage\n"
        self._send(reply)
        return True

    def _execute(self, command: str, *, slip: bool = False) -> str:
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


def main() -> None:  # pragma: no cover - interactive helper
    with FakeStageFirmware() as firmware:
        print(f"fake stage firmware on {firmware.port} (checksum of 'POS 0.000' is {checksum('POS 0.000')}); "
              "Ctrl-C to stop")
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":  # pragma: no cover
    main()
