"""The code passes the linter the project is configured for (``[tool.ruff]`` in pyproject.toml: pycodestyle, pyflakes,
isort, bugbear, pyupgrade; 120 columns), so that CI says so and not a reviewer. ``ruff check .`` shows the same."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_code_passes_ruff():
    pytest.importorskip("ruff", reason="the linter is part of the [test] extra")
    command = [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", str(ROOT)]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, check=False)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
