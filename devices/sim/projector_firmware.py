"""The sync controller's pattern memory, simulated: what the fake sync firmware answers to the projector
commands of ``docs/devices.md`` (``PROJ?``, ``UPLOAD``, ``ROW``, ``SUM?``, ``SHOW``, ``LINE``, ``PAT?``).

It shows what it holds on a ``screen`` (any object with ``show(pattern)``: the simulated projector, whose
pattern the simulated camera renders), at the projector's 8 bits, as the real video output would.

Device fault: ``corrupt``: a ``ROW`` is stored with one byte flipped but answered ``OK`` (a memory or line
error the reply does not show); only the slot's checksum catches it.
"""

from __future__ import annotations

import base64
import binascii

import numpy as np

from selpath.devices.patterns import vertical_line
from selpath.devices.serial_projector import LEVELS, pattern_checksum


class PatternMemory:
    """``slots`` 8-bit patterns of ``shape``, one being uploaded at a time, and what is shown."""

    def __init__(self, shape: tuple[int, int], screen, slots: int = 8):
        self.shape, self.screen = (int(shape[0]), int(shape[1])), screen
        self.slots: list[np.ndarray | None] = [None] * slots
        self._upload: tuple[int, np.ndarray, np.ndarray] | None = None  # slot, levels, rows written
        self.shown = "NONE"

    def execute(self, name: str, argument: str, fault: str | None) -> str | None:
        """The reply body to a projector command, or None when ``name`` is not one."""
        handler = {"PROJ?": self._size, "UPLOAD": self._begin, "ROW": self._row, "SUM?": self._sum,
                   "SHOW": self._show, "LINE": self._line, "PAT?": self._showing}.get(name)
        if handler is None:
            return None
        try:
            return handler(argument.split(), fault)
        except (ValueError, IndexError, binascii.Error):
            return "ERR 2 BAD ARGUMENT"

    def _size(self, args, fault) -> str:
        return f"PROJ {self.shape[0]} {self.shape[1]} {len(self.slots)}"

    def _slot(self, text: str) -> int:
        slot = int(text)
        if not 0 <= slot < len(self.slots):
            raise ValueError(slot)
        return slot

    def _begin(self, args, fault) -> str:
        slot, rows, cols = self._slot(args[0]), int(args[1]), int(args[2])
        if (rows, cols) != self.shape:
            return "ERR 2 BAD ARGUMENT"
        self.slots[slot] = None  # the old content is gone as the upload starts
        self._upload = (slot, np.zeros(self.shape, np.uint8), np.zeros(rows, bool))
        return f"OK UPLOAD {slot}"

    def _row(self, args, fault) -> str:
        if self._upload is None:
            return "ERR 3 NO UPLOAD"
        slot, levels, written = self._upload
        row = int(args[0])
        data = np.frombuffer(base64.b64decode(args[1], validate=True), np.uint8)
        if not 0 <= row < self.shape[0] or data.size != self.shape[1]:
            return "ERR 2 BAD ARGUMENT"
        levels[row] = data
        if fault == "corrupt":
            levels[row, 0] ^= 0x10
        written[row] = True
        if written.all():
            self.slots[slot] = levels.copy()
        return f"OK ROW {row}"

    def _sum(self, args, fault) -> str:
        slot = self._slot(args[0])
        held = self.slots[slot]
        return f"SUM {slot} {'NONE' if held is None else pattern_checksum(held)}"

    def _show(self, args, fault) -> str:
        slot = self._slot(args[0])
        held = self.slots[slot]
        if held is None:
            return "ERR 5 EMPTY SLOT"
        self.screen.show(held / LEVELS)
        self.shown = f"SLOT {slot}"
        return f"OK SHOW {slot}"

    def _line(self, args, fault) -> str:
        centre, width = float(args[0]), float(args[1])
        if not width > 0 or not np.isfinite(centre):
            return "ERR 2 BAD ARGUMENT"
        levels = np.rint(vertical_line(self.shape, centre, width) * LEVELS)
        self.screen.show(levels / LEVELS)
        self.shown = f"LINE {centre:.3f} {width:.3f}"
        return f"OK LINE {centre:.3f} {width:.3f}"

    def _showing(self, args, fault) -> str:
        return f"PAT {self.shown}"
