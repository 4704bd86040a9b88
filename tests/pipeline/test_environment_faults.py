"""What the machine refuses is named as such, with the fix, never reported as a bug in selpath: a folder the user
may not write, a store name too long for the file system, a dask scheduler that does not answer. And an output path
naming a folder of the user's own files says so."""

from __future__ import annotations

import errno
import os
import subprocess
import sys

import dask
import pytest
from typer.testing import CliRunner

from selpath.pipeline import EnvironmentFault, SpecError, load_workflow
from selpath.pipeline.cli import app
from selpath.pipeline.errors import environment_fault
from tests.conftest import SMALL_WORKFLOW
from tests.helpers.permissions import unprivileged_folder

runner = CliRunner()
ENV = {"COLUMNS": "200"}


def _one_line(text: str) -> str:
    return " ".join(text.split())


def test_the_faults_of_the_environment_are_named_other_errors_are_not():
    fault = environment_fault(PermissionError(errno.EACCES, "Permission denied", "/data/out"), "writing")
    assert isinstance(fault, EnvironmentFault)
    assert str(fault) == ("/data/out: permission denied while writing (fix: use a folder you may write to (the "
                          "workflow's output `store:` paths, or `selpath demo --out`), or change the folder's "
                          "permissions)")
    wrapped = RuntimeError("a library's own error")
    wrapped.__cause__ = OSError(errno.ENOSPC, "No space left on device", "/data/out/x.zarr")
    assert "no space left on the device" in str(environment_fault(wrapped))  # found through the chain
    long = "x" * 300
    assert "its last part has 300 bytes" in str(environment_fault(OSError(errno.ENAMETOOLONG, "too long", long)))
    assert environment_fault(FileNotFoundError(errno.ENOENT, "gone", "/a")) is None  # could be a bug: not named
    assert environment_fault(ValueError("x")) is None


def test_a_store_name_too_long_for_the_file_system_is_named(tmp_path):
    name = "n" * 260 + ".zarr"
    (tmp_path / "wf.yaml").write_text(SMALL_WORKFLOW.replace("out/absorption.zarr", f"out/{name}"))
    shown = runner.invoke(app, ["run", str(tmp_path / "wf.yaml"), "--no-progress"], env=ENV)
    text = _one_line(shown.output)
    assert shown.exit_code == 2, shown.output
    assert "a file name is too long for the file system" in text and "shorten the store's name" in text, text
    assert "bug" not in text and "Traceback" not in text


def test_an_unreachable_dask_scheduler_is_named_with_the_fix(small_workflow):
    with dask.config.set({"distributed.comm.timeouts.connect": "2s"}):
        shown = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--scheduler", "tcp://127.0.0.1:9"],
                              env=ENV)
    text = _one_line(shown.output)
    assert shown.exit_code == 2, shown.output
    assert "no dask scheduler answers at tcp://127.0.0.1:9" in text and "--scheduler threads" in text, text
    assert "bug" not in text


def test_an_output_naming_a_folder_of_the_users_files_says_so(tmp_path):
    (tmp_path / "mydata").mkdir()
    (tmp_path / "mydata" / "notes.txt").write_text("mine")
    (tmp_path / "wf.yaml").write_text(SMALL_WORKFLOW.replace("out/absorption.zarr", "mydata"))
    with pytest.raises(SpecError) as raised:
        load_workflow(tmp_path / "wf.yaml")
    assert ("output 'absorption' store" in str(raised.value) and "is not a path ending in '.zarr': it is an existing "
            "folder, and not a selpath store, so selpath never writes into it" in str(raised.value))
    assert (tmp_path / "mydata" / "notes.txt").read_text() == "mine"


def test_a_read_only_output_folder_is_named_with_the_fix():
    """As an unprivileged user (uid 65534, no capabilities: root's chmod is no test), in a folder owned by root."""
    with unprivileged_folder() as (prefix, base):
        (base / "wf.yaml").write_text(SMALL_WORKFLOW)
        result = subprocess.run([*prefix, sys.executable, "-m", "selpath", "run", "wf.yaml", "--no-progress"],
                                cwd=base, capture_output=True, text=True, timeout=240,
                                env={"HOME": "/tmp", "PATH": os.environ.get("PATH", ""),
                                     "SELPATH_COMPILE_CACHE": "off", "COLUMNS": "200"})
        text = _one_line(result.stdout + result.stderr)
        assert result.returncode == 2, text
        assert "permission denied while taking the lock of the output store" in text, text
        assert "use a folder you may write to" in text and "bug" not in text
        assert sorted(p.name for p in base.iterdir()) == ["wf.yaml"]
