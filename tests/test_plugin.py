"""The plugin tutorial's example (docs/tutorials/plugins.md), installed as a package of its own, stores its output in
a workflow like a built-in stage does: the code and pyproject.toml are read from the tutorial itself, built with pip
(offline, into a folder of their own) and found by the real entry-point machinery in a fresh interpreter."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from selpath import StoreError, open_store, to_store
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.simulate import simulate_parallel_capture

ROOT = Path(__file__).resolve().parents[1]


def readme_blocks() -> dict[str, str]:
    """The python, toml and yaml blocks of the plugin tutorial."""
    section = (ROOT / "docs" / "tutorials" / "plugins.md").read_text()
    return {lang: code for lang, code in re.findall(r"```(\w+)\n(.*?)```", section, flags=re.S)}


@pytest.fixture(scope="module")
def plugin(tmp_path_factory) -> dict[str, str]:
    """The example built and installed into a folder of its own; the environment that sees it (PYTHONPATH)."""
    blocks = readme_blocks()
    source, site = tmp_path_factory.mktemp("plugin"), tmp_path_factory.mktemp("site")
    (source / "selpath_brighten.py").write_text(blocks["python"])
    (source / "pyproject.toml").write_text(blocks["toml"] + '\n[build-system]\nrequires = ["setuptools"]\n'
                                           'build-backend = "setuptools.build_meta"\n')
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                    "--target", str(site), str(source)], check=True, capture_output=True, text=True)
    assert (site / "selpath_brighten.py").is_file()
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
            "SELPATH_COMPILE_CACHE": "off", "COLUMNS": "200"}


def selpath(env: dict, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "selpath", *args], env=env, cwd=cwd, capture_output=True, text=True)


def test_the_readme_plugin_runs_in_a_workflow_and_its_store_opens(plugin, tmp_path):
    capture = simulate_parallel_capture(angles=AngleSweep(start=0, stop=40, step=10), n_rows=2, n_cols=24,
                                        pixel_size=1.0, radius=10.0, noise_std=1.0)
    to_store(capture, tmp_path / "capture.zarr", "tomography_capture")
    (tmp_path / "brighter.yaml").write_text(readme_blocks()["yaml"])
    run = selpath(plugin, "run", "brighter.yaml", "--no-progress", cwd=tmp_path)
    assert run.returncode == 0, run.stdout + run.stderr
    store = tmp_path / "out" / "bright.zarr"

    shown = selpath(plugin, "inspect", str(store), cwd=tmp_path)
    assert shown.returncode == 0, shown.stdout + shown.stderr
    assert "brightened_frames store" in shown.stdout and "frames times the gain" in shown.stdout
    kinds = selpath(plugin, "kinds", "brightened_frames", cwd=tmp_path)
    assert kinds.returncode == 0 and "made by brighten" in kinds.stdout

    # the values and labels, read with plain xarray: the plugin's kind stamped its units and long name
    bright = xr.open_zarr(store, consolidated=False)
    target = xr.open_zarr(tmp_path / "capture.zarr", consolidated=False)["target"]
    np.testing.assert_allclose(bright["frames"].values, 3.0 * target.values, rtol=1e-6)
    assert bright.attrs["selpath_kind"] == "brightened_frames"
    assert bright["frames"].attrs == {"units": "counts", "long_name": "frames times the gain"}

    # where the plugin is not installed, its store says which kind it holds and what to install
    with pytest.raises(StoreError, match=r"unknown cube kind 'brightened_frames': no installed stage package "
                                         r"declares it"):
        open_store(store)
