"""Devices an operator works by hand: lights without a remote switch, swapping target and reference.

Each asks the operator on the console and waits for Enter. Without a terminal (a batch job) they refuse
with a :class:`~selpath.pipeline.errors.DeviceError` rather than hang.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

from selpath.pipeline.errors import DeviceError


def _console_prompt(message: str) -> None:
    if not sys.stdin.isatty():
        raise DeviceError(f"needs an operator: {message}", port="console",
                          fix="run the acquisition from a terminal, or use remotely switched devices")
    input(f"{message}, then press Enter ")


class ManualLight:
    """A light the operator switches; asks only when the state changes."""

    def __init__(self, name: str, prompt: Callable[[str], None] = _console_prompt):
        self.name, self.prompt, self.on = name, prompt, None

    def set(self, on: bool) -> None:
        if self.on is not on:
            self.prompt(f"switch the {self.name} {'on' if on else 'off'}")
            self.on = on


class ManualSampleChanger:
    """The operator puts the target or the reference object on the stage."""

    def __init__(self, prompt: Callable[[str], None] = _console_prompt):
        self.prompt, self.sample = prompt, None

    def load(self, sample: str) -> None:
        if sample != self.sample:
            self.prompt(f"put the {sample} object on the stage, in the same position")
            self.sample = sample
