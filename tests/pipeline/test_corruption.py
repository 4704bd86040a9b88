"""Corruption never passes unseen: for every store kind and every way a chunk goes bad (truncated, garbage,
deleted), `inspect --verify` names it and no read returns data from it; a capture frame whose chunk is bad
is captured again; incomplete stores and edited units are reported."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
import xarray as xr
import zarr
from typer.testing import CliRunner

from selpath.pipeline import SpecError, StoreError, load_workflow, open_store, run_workflow, to_store
from selpath.pipeline.capture_store import missing_frames
from selpath.pipeline.cli import app
from selpath.pipeline.integrity import verify_store
from selpath.pipeline.provenance import write_provenance
from tests.helpers.acquisition import make_workflow
from tests.helpers.stores import KINDS, damage_chunk, minimal

runner = CliRunner()


def _chunk_file(store: Path, variable: str) -> Path:
    files = sorted(p for p in (store / variable).rglob("*") if p.is_file() and p.name != "zarr.json")
    return files[len(files) // 2]


@pytest.mark.parametrize("how", ["truncate", "garbage", "delete"])
@pytest.mark.parametrize("kind", sorted(KINDS))
def test_a_bad_chunk_of_any_kind_is_named_and_never_read(tmp_path, kind, how):
    store = tmp_path / "s.zarr"
    ds = minimal(kind)
    to_store(ds.chunk(dict.fromkeys(ds.dims, 2)), store, kind)
    variable = next(iter(KINDS[kind].variables))
    chunk = _chunk_file(store, variable)
    index = tuple(int(p) for p in chunk.relative_to(store / variable / "c").parts)
    damage_chunk(chunk, how)

    assert [(b.variable, b.chunk, b.reason.split(" ")[0]) for b in verify_store(store)] == [
        (variable, index, "missing" if how == "delete" else "corrupt")]
    shown = runner.invoke(app, ["inspect", str(store), "--verify"], env={"COLUMNS": "200"})
    assert shown.exit_code == 1 and f"{variable} chunk {index}: " in shown.output.replace("\n", ""), shown.output

    with pytest.raises(StoreError) as info:
        open_store(store)[variable].load()
    message = str(info.value)
    assert f"s.zarr: variable {variable}: " in message, message
    if how == "delete":
        assert "1 of " in message and f"chunks are missing, first {index}" in message
    else:
        assert f"chunk {index} (" in message and "cannot be read: the store is corrupt" in message


def test_a_corrupt_capture_frame_is_captured_again_on_resume(tmp_path):
    """The reported case: garbage in one chunk of capture/target went unseen, and a deleted chunk read as NaN
    while its flag said captured. Now a read names it, and `inspect --verify --recapture` (or a deleted chunk on
    its own) makes the acquisition capture that frame again on the next run."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    clean = open_store(store).load()
    damage_chunk(store / "target" / "c" / "5" / "0" / "0", "garbage")
    with pytest.raises(StoreError, match=r"variable target: chunk \(5, 0, 0\) \(.*\) cannot be read"):
        open_store(store)["target"].load()
    shown = runner.invoke(app, ["inspect", str(store), "--verify", "--recapture"], env={"COLUMNS": "200"})
    assert shown.exit_code == 1 and "marked 1 frame(s) as not captured" in shown.output, shown.output
    assert missing_frames(store)["target"] == [{"angle": 75.0}]
    damage_chunk(store / "reference" / "c" / "7" / "0" / "0", "delete")
    assert missing_frames(store)["reference"] == [{"angle": 105.0}]

    report = run_workflow(load_workflow(path), progress=False)
    assert report.computed() == ["capture"]
    assert verify_store(store) == [] and not any(missing_frames(store).values())
    xr.testing.assert_identical(open_store(store).load(), clean)  # the simulator is deterministic


def test_run_with_verify_captures_again_only_the_frames_under_bad_chunks(tmp_path):
    """``selpath run --verify`` does inspect's repair itself: a finished acquisition with one garbage chunk is not
    trusted, the frame under it (only) is captured again, and the same values come back."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    clean = open_store(store).load()
    damage_chunk(store / "target" / "c" / "5" / "0" / "0", "garbage")
    assert run_workflow(load_workflow(path), progress=False).computed() == []  # trusted without --verify
    lines: list[str] = []
    report = run_workflow(load_workflow(path), progress=False, verify=True, log=lines.append)
    assert report.computed() == ["capture"], lines
    assert any("1 frame(s) will be captured again" in line for line in lines), lines
    assert verify_store(store) == []
    xr.testing.assert_identical(open_store(store).load(), clean)
    shown = runner.invoke(app, ["run", str(path), "--verify", "--no-progress"], env={"COLUMNS": "200"})
    assert shown.exit_code == 0 and "reused" in shown.output, shown.output


@pytest.mark.parametrize("damaged", ["written__target/c/0", "angle/c/0", "target/zarr.json"])
def test_capture_damage_that_is_no_frame_is_named_and_nothing_is_changed(tmp_path, damaged):
    """Review finding: ``--verify`` crashed with a raw ValueError on a garbled ``written__`` flag, and a bad
    coordinate chunk (under no frame) was logged as "0 frame(s) will be captured again". A capture's flags,
    coordinates and metadata cannot be captured again: verify_store lists them, the run stops with a StoreError
    naming the chunk and the fix, and no byte of the store changes."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    (store / damaged).write_bytes(b"garbage")
    variable = damaged.split("/")[0]
    listed = verify_store(store)
    assert [b.variable for b in listed] == [variable] and (listed[0].chunk is None) == damaged.endswith("zarr.json")
    before = {p: p.read_bytes() for p in store.rglob("*") if p.is_file()}
    with pytest.raises(StoreError, match=rf"1 bad chunk\(s\) of this capture are not frames .*{variable}.*"
                                         r"restore the store from a backup"):
        run_workflow(load_workflow(path), progress=False, verify=True)
    assert {p: p.read_bytes() for p in store.rglob("*") if p.is_file()} == before


def test_an_array_whose_metadata_was_deleted_is_listed_by_verify(tmp_path):
    """Review finding: with a variable's zarr.json deleted the array vanished from the group's listing and verify
    said every chunk reads, while opening the store said the variable is missing."""
    store = tmp_path / "sinogram.zarr"
    to_store(minimal("sinogram"), store, "sinogram")
    (store / "absorption" / "zarr.json").unlink()
    assert [(b.variable, b.chunk) for b in verify_store(store)] == [("absorption", None)]


def test_a_garbled_provenance_record_is_named_and_the_store_kept(tmp_path):
    """A torn ``_selpath/zarr.json`` raised a raw JSONDecodeError from loading the workflow. Now the output check
    names it, and the store (whose owner can no longer be proven) is neither trusted nor replaced."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    (store / "_selpath" / "zarr.json").write_text("{")
    assert [(b.variable, b.chunk) for b in verify_store(store)] == [("_selpath", None)]
    with pytest.raises(SpecError, match=r"provenance record \(_selpath/zarr.json\) cannot be read .*JSONDecodeError"):
        load_workflow(path)
    shown = runner.invoke(app, ["run", str(path), "--no-progress"], env={"COLUMNS": "200"})
    assert shown.exit_code != 0 and "cannot be read" in shown.output and "Traceback" not in shown.output
    assert (store / "target").is_dir()


def test_a_store_without_a_completion_record_is_reported_incomplete(tmp_path):
    """Partial outputs of a killed run (older selpath wrote in place) passed inspect and open_store silently."""
    store = tmp_path / "sinogram.zarr"
    ds = minimal("sinogram").assign_attrs(selpath_format=1, selpath_kind="sinogram")
    ds.to_zarr(store, consolidated=False)  # as a killed run of the old engine left it: no provenance
    with pytest.warns(UserWarning, match="no record that writing this store finished"):
        open_store(store)
    shown = runner.invoke(app, ["inspect", str(store)], env={"COLUMNS": "200"})
    assert shown.exit_code == 1 and "incomplete" in shown.output
    write_provenance(store, {"step_hash": "x"})  # what the old engine wrote once an output was complete
    assert runner.invoke(app, ["inspect", str(store)]).exit_code == 0


def test_edited_units_are_refused_naming_both(tmp_path):
    store = tmp_path / "sinogram.zarr"
    to_store(minimal("sinogram"), store, "sinogram")
    zarr.open_array(store / "x", mode="r+").attrs["units"] = "m"
    with pytest.raises(StoreError, match=re.escape("x: 'x' has units 'm' but was written in 'mm'")):
        open_store(store)
    assert runner.invoke(app, ["inspect", str(store)]).exit_code == 2


def test_inspect_of_a_complete_store_exits_zero(tmp_path):
    store = tmp_path / "r.zarr"
    to_store(minimal("reconstruction"), store, "reconstruction")
    shown = runner.invoke(app, ["inspect", str(store), "--verify"])
    assert shown.exit_code == 0 and "every chunk reads" in shown.output
    assert os.listdir(tmp_path) == ["r.zarr"]


def test_a_missing_coordinate_chunk_of_a_capture_is_named(tmp_path):
    """The angles of a capture read back as NaN, unreported, when their chunk was deleted."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    (store / "angle" / "c" / "0").unlink()
    with pytest.raises(StoreError, match=r"variable angle: 1 of 1 chunks are missing, first \(0,\)"):
        open_store(store)
    assert [(b.variable, b.reason) for b in verify_store(store)] == [("angle", "missing")]


def test_a_format_1_capture_with_a_fill_valued_frame_is_not_missing_frames(tmp_path):
    """Format 1 did not write chunks that held only the fill value: there an absent chunk is no evidence."""
    path = make_workflow(tmp_path)
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "capture.zarr"
    zarr.open_group(store, mode="r+").attrs["selpath_format"] = 1
    (store / "target" / "c" / "5" / "0" / "0").unlink()  # as format 1 left an all-fill frame
    assert not any(missing_frames(store).values()) and verify_store(store) == []
