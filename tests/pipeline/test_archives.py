"""Reprocessing archives: a workflow folder moved, copied or unpacked reuses every finished step; a store read
by a step is identified by its content, never its path or file times; inputs are never written."""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import tarfile
from pathlib import Path

import numpy as np
import pytest

from selpath.pipeline import StoreError, load_workflow, open_store, run_workflow, to_store
from selpath.pipeline.integrity import verify_store
from selpath.pipeline.provenance import content_digest, read_provenance, store_identity
from tests.helpers.permissions import unprivileged_folder

REPROCESS = """\
workflow: reprocess
scheduler: synchronous
steps:
  - id: cap
    stage: load_store
    with: {store: out/capture.zarr}
  - id: foreign
    stage: load_store
    with: {store: archive/foreign.zarr}
  - id: absorption
    stage: absorption
    with: {capture: $cap, min_signal: 1.0}
  - id: foreign_absorption
    stage: absorption
    with: {capture: $foreign, min_signal: 1.0}
outputs:
  again: {from: absorption, store: results/again.zarr}
  foreign: {from: foreign_absorption, store: results/foreign.zarr}
"""


def _files(folder: Path) -> dict[str, tuple[int, int, str]]:
    """Every file under ``folder``: (size, modification time, SHA-256), by relative path."""
    return {p.relative_to(folder).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns,
                                               hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _run(folder: Path) -> dict[str, dict[str, str]]:
    """Run both workflows of an archive folder; each step's status."""
    return {name: {i: s.status for i, s in run_workflow(load_workflow(folder / name), progress=False).steps.items()}
            for name in ("small.yaml", "reprocess.yaml")}


@pytest.fixture
def archive(tmp_path, small_workflow) -> Path:
    """A folder holding two workflows and their stores: a simulated capture and its absorption, a store written
    outside any workflow (``to_store``: no provenance), and a reprocessing of both (``load_store`` chains)."""
    folder = tmp_path / "archive-a"
    folder.mkdir()
    shutil.move(small_workflow, folder / "small.yaml")
    run_workflow(load_workflow(folder / "small.yaml"), progress=False)
    capture = open_store(folder / "out" / "capture.zarr").load()
    to_store(capture, folder / "archive" / "foreign.zarr", capture.attrs["selpath_kind"])
    (folder / "reprocess.yaml").write_text(REPROCESS)
    run_workflow(load_workflow(folder / "reprocess.yaml"), progress=False)
    return folder


def test_a_copied_moved_or_unpacked_folder_reuses_every_step_and_rewrites_nothing(archive, tmp_path):
    """``cp`` with fresh file times, a move, and a tar round trip: every step of both workflows is reused (the
    identities hold no absolute path and no modification time) and no file of the folder changes."""
    everything_reused = {"small.yaml": {"capture": "reused", "absorption": "reused"},
                         "reprocess.yaml": {"cap": "not needed", "foreign": "not needed", "absorption": "reused",
                                            "foreign_absorption": "reused"}}
    copied = tmp_path / "copied"
    shutil.copytree(archive, copied, copy_function=shutil.copyfile)  # new modification times everywhere
    assert _files(copied)["archive/foreign.zarr/zarr.json"][1] != _files(archive)["archive/foreign.zarr/zarr.json"][1]
    before = _files(copied)
    assert _run(copied) == everything_reused
    assert _files(copied) == before

    moved = tmp_path / "elsewhere" / "moved"
    moved.parent.mkdir()
    shutil.move(copied, moved)
    assert _run(moved) == everything_reused

    with tarfile.open(tmp_path / "archive.tar.gz", "w:gz") as tar:
        tar.add(archive, arcname="archive-a")
    unpacked = tmp_path / "unpacked"
    with tarfile.open(tmp_path / "archive.tar.gz") as tar:
        tar.extractall(unpacked, filter="data")
    before = _files(unpacked / "archive-a")
    assert _run(unpacked / "archive-a") == everything_reused
    assert _files(unpacked / "archive-a") == before
    # provenance still says where a store was made, for people
    assert read_provenance(archive / "results" / "again.zarr")["workflow_folder"] == str(archive)


def test_a_changed_foreign_store_is_recomputed_and_a_damaged_one_is_named(archive):
    """A store with no provenance is identified by its bytes: new content (same path, same size) reruns the
    steps that read it and only those; one damaged byte of a chunk changes its identity too, and the rerun that
    follows fails on the chunk's checksum, naming it, instead of reusing old results."""
    foreign = archive / "archive" / "foreign.zarr"
    identity = store_identity(foreign)
    assert set(identity) == {"content_sha256"} and identity == store_identity(foreign)
    capture = open_store(foreign).load()
    shutil.rmtree(foreign)
    to_store(capture.assign(target=capture["target"] * 0.5), foreign, capture.attrs["selpath_kind"])
    assert store_identity(foreign) != identity
    statuses = _run(archive)["reprocess.yaml"]
    assert statuses["foreign_absorption"] == "computed" and statuses["absorption"] == "reused"
    recomputed = open_store(archive / "results" / "foreign.zarr")["absorption"].values
    assert np.nanmax(np.abs(recomputed - open_store(archive / "results" / "again.zarr")["absorption"].values)) > 0.5

    chunk = sorted(p for p in (foreign / "target").rglob("*") if p.is_file() and p.name != "zarr.json")[0]
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="foreign.zarr"):
        _run(archive)


def damage(store: Path, variable: str) -> None:
    """Flip one byte in the middle of the first chunk of ``variable``."""
    chunk = sorted(p for p in (store / variable).rglob("*") if p.is_file() and p.name != "zarr.json")[0]
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))


def test_one_damaged_byte_after_a_move_is_found_by_verify_and_recomputed(archive, tmp_path):
    """A workflow's own output damaged by one byte after the folder moved: a plain run trusts its provenance
    (reused: reading every byte of a large archive on every run is what ``--verify`` is for); ``verify=True``
    finds the bad chunk, recomputes that output alone and writes the same values as before the damage (a damaged
    acquisition: tests/pipeline/test_corruption.py)."""
    moved = tmp_path / "moved"
    shutil.move(archive, moved)
    result = moved / "out" / "absorption.zarr"
    before = open_store(result)["absorption"].values
    damage(result, "absorption")
    workflow = load_workflow(moved / "small.yaml")
    assert {i: s.status for i, s in run_workflow(workflow, progress=False).steps.items()} == \
        {"capture": "reused", "absorption": "reused"}
    with pytest.raises(StoreError, match="absorption"):
        open_store(result)["absorption"].values  # noqa: B018 - the damage is still there, and named when read
    lines: list[str] = []
    report = run_workflow(workflow, progress=False, verify=True, log=lines.append)
    assert {i: s.status for i, s in report.steps.items()} == {"capture": "reused", "absorption": "computed"}
    assert "bad chunk" in report.steps["absorption"].reason
    assert any("absorption.zarr" in line and "computed again" in line for line in lines)
    np.testing.assert_array_equal(open_store(result)["absorption"].values, before)
    assert not verify_store(result)

    assert {i: s.status for i, s in run_workflow(workflow, progress=False, verify=True).steps.items()} == \
        {"capture": "reused", "absorption": "reused"}


def test_an_output_whose_array_metadata_is_garbled_is_recomputed_by_verify(archive):
    """Review finding: a torn ``zarr.json`` of one array made ``--verify`` crash with a raw JSONDecodeError. It is
    a bad node like a bad chunk: listed by verify_store (not raised), and the output is computed again."""
    result = archive / "out" / "absorption.zarr"
    before = open_store(result)["absorption"].values
    (result / "absorption" / "zarr.json").write_text('{"zarr_format": 3, "node_ty')
    assert [(b.variable, b.chunk) for b in verify_store(result)] == [("absorption", None)]
    report = run_workflow(load_workflow(archive / "small.yaml"), progress=False, verify=True)
    assert {i: s.status for i, s in report.steps.items()} == {"capture": "reused", "absorption": "computed"}
    np.testing.assert_array_equal(open_store(result)["absorption"].values, before)
    assert not verify_store(result)


def test_the_content_digest_ignores_where_a_store_is_and_when_its_files_were_written(archive, tmp_path):
    foreign = archive / "archive" / "foreign.zarr"
    copy = tmp_path / "somewhere" / "else.zarr"
    shutil.copytree(foreign, copy, copy_function=shutil.copyfile)
    os.utime(next(p for p in copy.rglob("*") if p.is_file()), (1, 1))
    assert content_digest(copy) == content_digest(foreign)
    (copy / "zarr.json").write_text((copy / "zarr.json").read_text() + " ")  # one byte more
    assert content_digest(copy) != content_digest(foreign)


def test_read_only_inputs_are_read_and_never_written(archive):
    """Reprocessing reads archives on read-only media: with every input store's files and folders made
    read-only, a run that recomputes from them completes, and not one file, time or folder entry of the inputs
    (or beside them: no lock files) changes."""
    shutil.rmtree(archive / "results")
    inputs = [archive / "out" / "capture.zarr", archive / "archive" / "foreign.zarr"]
    before = {p: _files(p) for p in inputs}
    beside = {p.parent: sorted(os.listdir(p.parent)) for p in inputs}
    modes = {}
    try:
        for store in inputs:
            for path in [store, *store.rglob("*")]:
                modes[path] = path.stat().st_mode
            for path in sorted([store, *store.rglob("*")], key=lambda p: len(p.parts), reverse=True):
                path.chmod(path.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
        report = run_workflow(load_workflow(archive / "reprocess.yaml"), progress=False)
    finally:
        for path, mode in sorted(modes.items(), key=lambda item: len(item[0].parts)):
            path.chmod(mode)
    assert set(report.computed()) == {"cap", "foreign", "absorption", "foreign_absorption"}
    assert {p: _files(p) for p in inputs} == before
    assert {p.parent: sorted(os.listdir(p.parent)) for p in inputs} == beside


def test_inspect_lists_an_archives_stores_with_their_provenance(archive, monkeypatch):
    """``selpath inspect FOLDER`` (a folder that is not a store): one row per store under it, with its kind and
    the workflow and output that wrote it, and stores written outside a workflow said to be so."""
    from typer.testing import CliRunner

    from selpath.pipeline.cli import app
    from selpath.pipeline.provenance import archive_stores

    rows = {r["store"]: r for r in archive_stores(archive)}
    assert set(rows) == {"archive/foreign.zarr", "out/absorption.zarr", "out/capture.zarr", "results/again.zarr",
                         "results/foreign.zarr"}
    assert (rows["results/again.zarr"]["workflow"], rows["results/again.zarr"]["output"]) == ("reprocess", "again")
    assert rows["archive/foreign.zarr"]["workflow"] is None
    from rich.console import Console

    monkeypatch.setattr("selpath.pipeline.cli_inspect.console", Console(width=250))  # one line per store
    result = CliRunner().invoke(app, ["inspect", str(archive)])
    assert result.exit_code == 0, result.output
    assert "5 store(s)" in result.output and "outside a workflow" in result.output
    assert all(store in result.output for store in rows)
    assert "small-absorption" in result.output and "reprocess" in result.output

    # review finding: one store with a garbled provenance record made the whole listing fail
    (archive / "results" / "again.zarr" / "_selpath" / "zarr.json").write_text("{")
    rows = {r["store"]: r for r in archive_stores(archive)}
    assert len(rows) == 5 and "cannot be read" in rows["results/again.zarr"]["problem"]
    assert rows["out/absorption.zarr"]["problem"] is None
    result = CliRunner().invoke(app, ["inspect", str(archive)])
    assert result.exit_code == 0 and "provenance record unreadable" in result.output, result.output


def test_a_user_without_write_permission_reprocesses_a_read_only_archive(archive, tmp_path_factory):
    """The read-only test above runs as root, whom chmod does not stop. Here the archive is read-only and owned by
    root, and the run is an unprivileged user's (uid 65534, no capabilities): any write into an input (a lock, a
    provenance rewrite, consolidated metadata) would fail with EACCES. The run completes and the archive is
    byte-for-byte and time-for-time unchanged."""
    import subprocess
    import sys

    with unprivileged_folder() as (prefix, base):
        shutil.copytree(archive / "out", base / "archive" / "out")
        shutil.copytree(archive / "archive", base / "archive" / "archive")
        store = base / "archive"
        for path in sorted([store, *store.rglob("*")], key=lambda p: len(p.parts), reverse=True):
            path.chmod(0o555 if path.is_dir() else 0o444)
        before = _files(store)
        work = base / "work"
        work.mkdir()
        (work / "reprocess.yaml").write_text(REPROCESS.replace("out/capture.zarr", "../archive/out/capture.zarr")
                                             .replace("archive/foreign.zarr", "../archive/archive/foreign.zarr"))
        os.chown(work, 65534, 65534)
        selpath = str(Path(sys.executable).with_name("selpath"))
        result = subprocess.run([*prefix, selpath, "run", "reprocess.yaml", "--no-progress"], cwd=work,
                                capture_output=True, text=True, timeout=240,
                                env={"HOME": str(work), "PATH": os.environ.get("PATH", ""),
                                     "SELPATH_COMPILE_CACHE": "off", "COLUMNS": "200"})
        assert result.returncode == 0, result.stdout + result.stderr
        assert (work / "results" / "again.zarr").is_dir() and (work / "results" / "foreign.zarr").is_dir()
        assert (work / "results" / "again.zarr").stat().st_uid == 65534
        assert _files(store) == before
