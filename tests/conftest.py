"""Shared fixtures: a small valid workflow, and a dask scheduler that fails on any compute."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
import textwrap
from pathlib import Path

import dask
import pytest

# The command line's rich consoles take their width from COLUMNS when they are made (at import), and a test gives
# each command its width through the runner's environment: a COLUMNS that the test run inherits (pytest-xdist's
# workers set 80, some shells export it) would freeze every console at that width first.
os.environ.pop("COLUMNS", None)
os.environ.pop("LINES", None)

# The stage manifest (selpath.pipeline.manifest) is kept in ~/.cache: the tests, and the commands they start, keep
# theirs in a folder of their own from the start (collection may build the registry), removed at the end.
_MANIFESTS = tempfile.mkdtemp(prefix="selpath-test-manifests-")
os.environ["SELPATH_MANIFEST_CACHE"] = _MANIFESTS
atexit.register(shutil.rmtree, _MANIFESTS, ignore_errors=True)

#: the folder of XLA's compiled kernels the tests keep between runs (see pytest_configure), or None
TEST_COMPILE_CACHE: Path | None = None


def pytest_configure(config):
    """XLA's compiled kernels are kept between test runs (JAX's persistent compilation cache), for this process and
    every command and worker it starts (they inherit the environment; set before any test module imports JAX). Most
    of the demultiplexer tests' time is compiling (tests/hard_cases/test_demux_hard.py: 30 s cold, 8.5 s from the
    cache on a 2-core VM), so a second run of the default job skips it. Kernels are keyed by their HLO, JAX's version
    and the machine, so a changed kernel is compiled again and its old entry stays: the folder grows by a few MB a
    run that changes kernels (delete it at will).

    The folder is pytest's cache (``.pytest_cache/d/selpath-jax``, or ``--cache-dir``'s); SELPATH_TEST_COMPILE_CACHE
    names another, or ``off`` for a cold run (CI's clone starts empty anyway). None where pytest keeps no cache
    (``-p no:cacheprovider``), the folder cannot be written, or JAX_COMPILATION_CACHE_DIR is set (the user's wins)."""
    global TEST_COMPILE_CACHE
    setting = os.environ.get("SELPATH_TEST_COMPILE_CACHE", "")
    if setting.lower() == "off" or "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return
    try:
        folder = Path(setting).resolve() if setting else (config.cache.mkdir("selpath-jax")
                                                          if getattr(config, "cache", None) else None)
        if folder is not None:
            folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        folder = None
    if folder is None or not os.access(folder, os.W_OK | os.X_OK):  # a read-only checkout: no cache, as before
        return
    TEST_COMPILE_CACHE = folder
    os.environ |= {"JAX_COMPILATION_CACHE_DIR": str(folder), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}


SMALL_WORKFLOW = textwrap.dedent("""\
    workflow: small-absorption
    scheduler: synchronous
    steps:
      - id: capture
        stage: simulate_parallel_capture
        with:
          angles: {start: 0, stop: 40, step: 5}
          n_rows: 3
          n_cols: 48
          pixel_size: 1.0
          radius: 20.0
          rods:
            - {x: 6.0, y: 3.0, radius: 4.0, sigma: 0.05}
          noise_std: 1.5
      - id: absorption
        stage: absorption
        with:
          capture: $capture
          min_signal: 1.0
    outputs:
      capture: {from: capture, store: out/capture.zarr}
      absorption: {from: absorption, store: out/absorption.zarr}
    """)


@pytest.fixture(autouse=True)
def no_compile_cache(monkeypatch):
    """The command line keeps compiled kernels in ~/.cache; tests leave the home folder alone (their kernels go to the
    test cache of :func:`pytest_configure`)."""
    monkeypatch.setenv("SELPATH_COMPILE_CACHE", "off")


@pytest.fixture
def workflow_text() -> str:
    return SMALL_WORKFLOW


@pytest.fixture
def small_workflow(tmp_path: Path) -> Path:
    path = tmp_path / "small.yaml"
    path.write_text(SMALL_WORKFLOW)
    return path


class ComputeCounter:
    """A dask scheduler that counts computes and, if strict, fails on the first one (cf. xarray's
    raise_if_dask_computes)."""

    def __init__(self, strict: bool = True):
        self.strict, self.count = strict, 0

    def __call__(self, dsk, keys, **kwargs):
        self.count += 1
        if self.strict:
            raise RuntimeError("a dask compute happened where the graph must stay lazy")
        return dask.get(dsk, keys, **kwargs)


@pytest.fixture
def no_compute():
    counter = ComputeCounter()
    with dask.config.set(scheduler=counter):
        yield counter
