"""Shared by the acquisition tests: kill a real `selpath run` mid-sweep."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr


def written_frames(store: Path, flag: str) -> int:
    """Frames a capture store has marked written in its ``flag`` array (0 before the store exists)."""
    try:
        return int(np.sum(zarr.open_group(str(store), mode="r")[flag][:]))
    except Exception:  # not created yet, or mid-creation
        return 0


@pytest.fixture
def kill_mid_sweep():
    """``kill(workflow, store, flag, at_least)``: start `selpath run workflow` in a subprocess, SIGKILL it once
    ``at_least`` frames are flagged written (or after 120 s), and return how many were written by then."""

    def kill(workflow: Path, store: Path, flag: str, at_least: int) -> int:
        process = subprocess.Popen([sys.executable, "-m", "selpath", "run", str(workflow), "--no-progress"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 120
        while written_frames(store, flag) < at_least and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
        return written_frames(store, flag)

    return kill
