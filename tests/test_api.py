"""The public surface a notebook uses: ``import selpath``."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import selpath


def test_the_namespace_exports_what_it_lists():
    assert sorted(selpath.__all__) == sorted(set(selpath.__all__))
    missing = [name for name in selpath.__all__ if not hasattr(selpath, name)]
    assert not missing
    assert selpath.__version__.split(".")[0].isdigit()


def test_run_a_workflow_from_python_then_open_its_stores(small_workflow):
    report = selpath.run(small_workflow, scheduler="synchronous")
    assert report.computed() == ["capture", "absorption"] and len(report.written) == 2
    absorption = selpath.open_store(small_workflow.parent / "out" / "absorption.zarr")
    assert absorption.attrs["selpath_kind"] == "absorption"
    assert absorption["absorption"].attrs["units"] == "1"
    assert np.isfinite(absorption["absorption"].values).any()
    again = selpath.run(small_workflow)  # nothing recomputed: every output is up to date
    assert again.computed() == [] and sorted(again.fresh) == sorted(report.written)


def test_a_workflow_that_does_not_validate_raises_one_spec_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("workflow: w\nsteps:\n  - {id: a, stage: no_such_stage}\n")
    with pytest.raises(selpath.SpecError, match=r"unknown stage 'no_such_stage'"):
        selpath.run(bad)


def test_python_dash_m_selpath_is_the_command_line():
    shown = subprocess.run([sys.executable, "-m", "selpath", "--version"], capture_output=True, text=True, check=True)
    assert shown.stdout.strip() == f"selpath {selpath.__version__}"
