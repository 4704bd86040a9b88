"""The projector, driven through the sync controller's serial line (protocol in ``docs/devices.md``).

The raster-scan projector shows the controller's video output: the controller holds a few 8-bit pattern slots
and draws vertical lines itself (the full-transport sweep's l_p steps cost one command, not an upload).
Commands: ``PROJ?`` (size and slots) and ``PAT?`` (what is shown), idempotent queries retried a bounded number of
times; ``UPLOAD``/``ROW`` (a pattern into a slot, row by row, base64), ``SUM?`` (the slot's CRC-32),
``SHOW <slot>`` and ``LINE <centre> <width>``. Like the sync settings, nothing is trusted until read back: every
upload is compared with the controller's CRC-32 of the slot (uploaded again once on a mismatch), and every
``SHOW``/``LINE`` is confirmed by ``PAT?``, so no frame is recorded under a pattern other than the one asked.
"""

from __future__ import annotations

import base64
import zlib

import numpy as np

from selpath.devices.serial_line import SerialLine
from selpath.pipeline.errors import DeviceError, DeviceProtocolError, DeviceTimeout

#: grey levels of the projector's video input: a pattern value p in [0, 1] is shown as round(255·p) / 255
LEVELS = 255
#: uploads of one pattern before a checksum mismatch is an error
UPLOAD_TRIES = 2


def quantise(pattern: np.ndarray) -> np.ndarray:
    """A pattern in [0, 1] as the projector's 8-bit levels (uint8); anything else is a ValueError naming it."""
    values = np.asarray(pattern, dtype=float)
    if not np.all(np.isfinite(values)):
        raise ValueError("the pattern holds NaN or infinite values")
    if values.size and (values.min() < 0 or values.max() > 1):
        raise ValueError(f"the pattern spans [{values.min():g}, {values.max():g}]; a projector shows [0, 1]")
    return np.rint(values * LEVELS).astype(np.uint8)


def pattern_checksum(levels: np.ndarray) -> str:
    """CRC-32 of a slot's bytes (row-major uint8), eight upper-case hex digits, as ``SUM?`` answers.

    >>> pattern_checksum(np.zeros((2, 3), np.uint8))
    'B1C2A1A3'
    """
    return f"{zlib.crc32(np.ascontiguousarray(levels, dtype=np.uint8).tobytes()):08X}"


class SyncLineProjector:
    """:class:`~selpath.devices.protocols.Projector` whose patterns go through the sync controller's line ``line``.

    Patterns are kept by content: one already in a slot is shown without an upload; a new one goes into the
    slot used longest ago. ``show_line`` asks the controller to draw the line, the same as
    ``show(selpath.devices.patterns.vertical_line(shape, centre, width))`` at 8 bits.
    """

    def __init__(self, line: SerialLine, *, retries: int = 2):
        self.line, self.retries = line, retries
        self._shape: tuple[int, int] | None = None
        self._slots = 0
        self._held: dict[str, int] = {}  # checksum -> slot, for slots whose upload was verified
        self._order: list[int] = []  # slots, least recently used first
        self.uploads = 0  # patterns uploaded (a report for tests and logs)

    @property
    def url(self) -> str:
        return self.line.url

    def _size(self) -> None:
        body = self.line.query("PROJ?", expect="PROJ", retries=self.retries)
        fields = body.split()[1:]
        try:
            rows, cols, slots = (int(v) for v in fields)
        except ValueError:
            raise DeviceProtocolError("expected rows, cols and slots after 'PROJ'", port=self.url, command="PROJ?",
                                      reply=body) from None
        if min(rows, cols, slots) < 1:
            raise DeviceProtocolError("the projector's size or slots are not positive", port=self.url,
                                      command="PROJ?", reply=body)
        self._shape, self._slots = (rows, cols), slots
        self._order = list(range(slots))

    @property
    def shape(self) -> tuple[int, int]:
        if self._shape is None:
            self._size()
        assert self._shape is not None
        return self._shape

    def showing(self) -> str:
        """What the controller says it projects: ``SLOT <n>``, ``LINE <centre> <width>`` or ``NONE``."""
        return self.line.query("PAT?", expect="PAT", retries=self.retries).partition(" ")[2]

    def show(self, pattern: np.ndarray) -> None:
        pattern = np.asarray(pattern)
        if pattern.shape != self.shape:
            raise DeviceError(f"pattern is {pattern.shape}; the projector is {self.shape}", port=self.url,
                              command="show")
        try:
            levels = quantise(pattern)
        except ValueError as exc:
            raise DeviceError(str(exc), port=self.url, command="show", fix="pass a pattern in [0, 1]") from None
        key = pattern_checksum(levels)
        slot = self._held.get(key)
        if slot is None:
            slot = self._upload(levels, key)
        self._setting(f"SHOW {slot}", f"SLOT {slot}")
        self._order.remove(slot)
        self._order.append(slot)

    def show_line(self, centre: float, width: float) -> None:
        """A vertical line at projector column ``centre`` (pixel-centre coordinates) of ``width`` px."""
        if not width > 0:
            raise DeviceError(f"line width must be positive, got {width}", port=self.url, command="show_line")
        self._setting(f"LINE {centre:.3f} {width:.3f}", f"LINE {centre:.3f} {width:.3f}")

    def close(self) -> None:
        pass  # the line belongs to the sync controller, which closes it

    # -- the protocol -----------------------------------------------------------------------------------

    def _upload(self, levels: np.ndarray, key: str) -> int:
        slot = self._order[0]
        self._held = {k: s for k, s in self._held.items() if s != slot}
        rows, cols = levels.shape
        held = None
        for _ in range(UPLOAD_TRIES):
            # starting an upload and writing a row are idempotent: a lost reply is answered by sending it again
            self._ok(f"UPLOAD {slot} {rows} {cols}", f"OK UPLOAD {slot}", retries=self.retries)
            for r in range(rows):
                text = base64.b64encode(levels[r].tobytes()).decode("ascii")
                self._ok(f"ROW {r} {text}", f"OK ROW {r}", retries=self.retries)
            held = self.line.query(f"SUM? {slot}", expect="SUM", retries=self.retries).split()[-1]
            self.uploads += 1
            if held == key:
                self._held[key] = slot
                return slot
        raise DeviceError(f"slot {slot} holds a pattern with CRC-32 {held}, not the {key} uploaded "
                          f"({UPLOAD_TRIES} uploads)", port=self.url, command=f"SUM? {slot}",
                          fix="check the controller's line and memory, then run the acquisition again to resume")

    def _ok(self, command: str, reply: str, *, retries: int = 0) -> None:
        """Send ``command`` until it is answered by ``reply`` (``retries`` more times after a lost or garbled
        answer; a refusal is never retried)."""
        last: DeviceError | None = None
        for _ in range(retries + 1):
            try:
                body = self.line.exchange(command, answers=lambda b: b == reply)
            except (DeviceTimeout, DeviceProtocolError) as exc:
                if isinstance(exc.reply, str) and exc.reply.startswith("ERR"):
                    raise
                last = exc
                continue
            if body == reply:
                return
            last = DeviceProtocolError(f"unexpected reply to {command.split()[0]}", port=self.url,
                                       command=command[:40], reply=body)
        assert last is not None
        raise last

    def _setting(self, command: str, wanted: str) -> None:
        """Send a display setting once; whatever its reply, believe only ``PAT?``."""
        after = ""
        try:
            self._ok(command, f"OK {command}")
        except (DeviceTimeout, DeviceProtocolError) as exc:
            if isinstance(exc.reply, str) and exc.reply.startswith("ERR"):
                raise
            after = f" (the reply was lost: {exc.message})"
        try:
            shown = self.showing()
        except DeviceError as exc:
            raise type(exc)(f"cannot confirm {command!r}: {exc.message}", port=self.url, command=command,
                            reply=exc.reply, fix="check the controller, then run the acquisition again to resume"
                            ) from exc
        if shown != wanted:
            raise DeviceError(f"the controller shows {shown!r} after {command!r}{after}", port=self.url,
                              command=command, fix="check the projector's video link, then run the acquisition "
                              "again to resume")
