"""A folder the test process may not write (as another user), for the read-only archive tests."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest


def _unprivileged() -> list[str] | None:
    """The command prefix that runs a process as ``nobody`` without capabilities (setpriv), if this runs as root,
    setpriv exists and this Python and selpath are readable to that user; else None."""
    import subprocess
    import sys

    setpriv = shutil.which("setpriv")
    if os.geteuid() != 0 or setpriv is None:
        return None
    prefix = [setpriv, "--reuid=65534", "--regid=65534", "--clear-groups"]
    probe = subprocess.run([*prefix, sys.executable, "-c", "import selpath.pipeline.cli, selpath.stages"],
                           capture_output=True, cwd="/", env={"HOME": "/tmp", "PATH": os.environ.get("PATH", "")})
    return prefix if probe.returncode == 0 else None


@contextmanager
def unprivileged_folder() -> Iterator[tuple[list[str], Path]]:
    """(the command prefix that runs as uid 65534, a fresh root-owned folder under /tmp it may read); skips the test
    where that cannot be; the folder goes afterwards, whatever modes the test gave its contents."""
    prefix = _unprivileged()
    if prefix is None:
        pytest.skip("needs root, setpriv, and a Python that uid 65534 may run (.ci/run makes its venv so)")
    base = Path(tempfile.mkdtemp(dir="/tmp", prefix="selpath-ro-"))
    try:
        base.chmod(0o755)
        yield prefix, base
    finally:
        for path in [base, *base.rglob("*")]:
            if path.is_dir():
                path.chmod(0o755)
        shutil.rmtree(base, ignore_errors=True)
