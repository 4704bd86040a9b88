"""The command line's compile cache: compiled kernels land in the chosen folder, and ``off`` turns it off."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
from pipeline.compute import enable_compile_cache
folder = enable_compile_cache()
import jax, jax.numpy as jnp
jax.jit(lambda x: jnp.cumsum(x * 2.0 + 1.0))(jnp.ones(7)).block_until_ready()
print(folder)
"""


@pytest.mark.parametrize("setting", ["folder", "off"])
def test_compile_cache_writes_to_its_folder_or_nowhere(tmp_path, setting):
    folder = tmp_path / "cache"
    env = os.environ | {"SELPATH_COMPILE_CACHE": str(folder) if setting == "folder" else "off",
                        "XDG_CACHE_HOME": str(tmp_path / "xdg")}
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True)
    if setting == "folder":
        assert out.stdout.strip() == str(folder) and any(folder.iterdir())  # the kernel is cached there
    else:
        assert out.stdout.strip() == "None" and not folder.exists()
    assert not (tmp_path / "xdg").exists()  # never the default folder when one is named or it is off
