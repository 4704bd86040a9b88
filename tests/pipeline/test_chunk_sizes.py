"""A chunk changed since it was written is found by one listing, without reading it: every complete store's manifest
records its chunks' sizes. ``selpath inspect`` names a truncated or replaced chunk and exits 1, and a workflow does
not reuse such a store: a capture captures the frames under it again, another output is computed again. A chunk
changed in place to bytes of the same size is found only by reading it (``--verify``), and inspect says so."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import xarray as xr
from typer.testing import CliRunner

from selpath.pipeline import load_workflow, open_store, run_workflow, to_store
from selpath.pipeline.cli import app
from selpath.pipeline.integrity import CHUNK_BYTES, read_manifest, resized_chunks, verify_store
from tests.helpers.acquisition import make_workflow
from tests.helpers.stores import damage_chunk, minimal

runner = CliRunner()
ENV = {"COLUMNS": "200"}


def _sizes_on_disk(array: Path) -> dict[str, int]:
    """Every chunk file of an array folder and its size: an independent reading of the folder."""
    return {p.relative_to(array).as_posix(): p.stat().st_size for p in array.rglob("*")
            if p.is_file() and p.name != "zarr.json"}


def _lengthen(path: Path) -> None:
    path.write_bytes(path.read_bytes() + b"\0" * 7)


def test_a_complete_store_records_the_size_of_every_chunk(tmp_path):
    store = tmp_path / "r.zarr"
    ds = minimal("reconstruction")
    to_store(ds.chunk(dict.fromkeys(ds.dims, 2)), store, "reconstruction")
    recorded = read_manifest(store)[CHUNK_BYTES]
    arrays = [p.name for p in store.iterdir() if p.is_dir() and p.name != "_selpath"]
    assert sorted(recorded) == sorted(arrays) and "sigma" in recorded
    for name in arrays:  # every chunk exists in a complete store: its sizes, in the grid's order
        assert sorted(recorded[name]) == sorted(_sizes_on_disk(store / name).values()) and min(recorded[name]) > 0
    assert len(recorded["sigma"]) == 9  # (5, 5) cells in 2 × 2 chunks, row by row
    assert recorded["sigma"][3] == (store / "sigma" / "c" / "1" / "0").stat().st_size
    assert resized_chunks(store) == []
    shown = runner.invoke(app, ["inspect", str(store)], env=ENV)
    assert shown.exit_code == 0 and "every one has the size it was written with" in shown.output, shown.output


@pytest.mark.parametrize("damage", ["truncate", "lengthen"])
def test_inspect_names_a_chunk_whose_size_changed_without_verify(tmp_path, damage):
    store = tmp_path / "r.zarr"
    ds = minimal("reconstruction")
    to_store(ds.chunk(dict.fromkeys(ds.dims, 2)), store, "reconstruction")
    chunk = store / "sigma" / "c" / "1" / "0"
    size = chunk.stat().st_size
    damage_chunk(chunk, "truncate") if damage == "truncate" else _lengthen(chunk)
    bad = resized_chunks(store)
    assert [(b.variable, b.chunk) for b in bad] == [("sigma", (1, 0))]
    assert f"written as {size:,}" in bad[0].reason and "changed since it was written" in bad[0].reason
    shown = runner.invoke(app, ["inspect", str(store)], env=ENV)
    assert shown.exit_code == 1, shown.output
    assert "1 bad chunk(s)" in shown.output and "sigma chunk (1, 0)" in shown.output, shown.output


def test_a_chunk_replaced_by_one_that_decodes_is_found_by_inspect_and_verify(tmp_path):
    """Another store's chunk (valid zstd + crc32c) in place of one: it decodes, so only its size tells."""
    ds = minimal("reconstruction")
    for name, scale in (("r.zarr", 1.0), ("other.zarr", 0.0)):  # zeros: a chunk that compresses to fewer bytes
        to_store((ds * scale).assign_attrs(ds.attrs).chunk(dict.fromkeys(ds.dims, 2)), tmp_path / name,
                 "reconstruction")
    chunk = Path("sigma") / "c" / "0" / "0"
    (tmp_path / "r.zarr" / chunk).write_bytes((tmp_path / "other.zarr" / chunk).read_bytes())
    assert [(b.variable, b.chunk) for b in resized_chunks(tmp_path / "r.zarr")] == [("sigma", (0, 0))]
    assert [(b.variable, b.chunk) for b in verify_store(tmp_path / "r.zarr")] == [("sigma", (0, 0))]


def test_a_chunk_changed_in_place_is_found_by_verify_and_inspect_says_it_read_no_contents(tmp_path):
    store = tmp_path / "r.zarr"
    ds = minimal("reconstruction")
    to_store(ds.chunk(dict.fromkeys(ds.dims, 2)), store, "reconstruction")
    damage_chunk(store / "sigma" / "c" / "1" / "0", "garbage")  # same size, other bytes
    assert resized_chunks(store) == []
    shown = runner.invoke(app, ["inspect", str(store), "--no-valid"], env=ENV)
    assert shown.exit_code == 0 and "contents not read" in shown.output and "--verify" in shown.output
    verified = runner.invoke(app, ["inspect", str(store), "--verify"], env=ENV)
    assert verified.exit_code == 1 and "sigma chunk (1, 0): corrupt" in verified.output, verified.output


def test_a_rerun_captures_again_the_frame_under_a_truncated_chunk(tmp_path):
    """The reported case: a capture with one chunk truncated passed `inspect` (exit 0) and a rerun reused it,
    leaving it corrupt. Now inspect names the chunk, and the rerun captures that frame again, same values."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    assert resized_chunks(store) == []  # the engine recorded the capture's sizes once its last frame landed
    clean = open_store(store).load()
    damage_chunk(store / "target" / "c" / "5" / "0" / "0", "truncate")
    shown = runner.invoke(app, ["inspect", str(store)], env=ENV)
    assert shown.exit_code == 1 and "target chunk (5, 0, 0)" in shown.output, shown.output

    lines: list[str] = []
    report = run_workflow(load_workflow(path), progress=False, log=lines.append)
    assert report.computed() == ["capture"], lines
    assert any("check" in line and "1 frame(s) will be captured again" in line for line in lines), lines
    assert verify_store(store) == [] and resized_chunks(store) == []
    xr.testing.assert_identical(open_store(store).load(), clean)  # the simulator is deterministic
    assert runner.invoke(app, ["inspect", str(store)], env=ENV).exit_code == 0


def test_a_rerun_computes_again_an_output_one_of_whose_chunks_was_replaced(small_workflow):
    run_workflow(load_workflow(small_workflow), progress=False)
    store = small_workflow.parent / "out" / "absorption.zarr"
    clean = open_store(store).load()
    chunk = next(p for p in sorted((store / "absorption").rglob("*")) if p.is_file() and p.name != "zarr.json")
    chunk.write_bytes(os.urandom(chunk.stat().st_size + 16))  # another chunk's worth of bytes, longer
    lines: list[str] = []
    report = run_workflow(load_workflow(small_workflow), progress=False, log=lines.append)
    assert report.computed() == ["absorption"], lines
    assert any("it will be computed again" in line for line in lines), lines
    assert verify_store(store) == []
    xr.testing.assert_identical(open_store(store).load(), clean)


def test_frames_marked_for_capture_drop_the_record_until_the_capture_is_complete_again(tmp_path):
    """Frames captured again change their chunks (and the frame flags'): the record goes when they are marked, so no
    legitimate write is taken for damage, and comes back when the acquisition has written its last frame."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    damage_chunk(store / "target" / "c" / "5" / "0" / "0", "garbage")
    shown = runner.invoke(app, ["inspect", str(store), "--verify", "--recapture"], env=ENV)
    assert shown.exit_code == 1 and "marked 1 frame(s) as not captured" in shown.output, shown.output
    assert resized_chunks(store) is None
    assert "no record of their sizes" in _one_line(runner.invoke(app, ["inspect", str(store)], env=ENV).output)
    assert run_workflow(load_workflow(path), progress=False).computed() == ["capture"]
    assert resized_chunks(store) == [] and verify_store(store) == []


def _one_line(text: str) -> str:
    return " ".join(text.split())
