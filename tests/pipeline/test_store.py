"""Stores: round-trips, the schema check, frame-by-frame capture with resume, provenance."""

from __future__ import annotations

import re
import shutil

import dask.array as da
import numpy as np
import pytest
import xarray as xr
import zarr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from selpath.pipeline import (
    StoreError,
    create_capture,
    missing_frames,
    open_store,
    read_provenance,
    to_store,
    write_frame,
    write_provenance,
)
from selpath.pipeline.integrity import write_manifest
from selpath.pipeline.kinds import FORMAT_VERSION
from selpath.pipeline.store import IncompleteStoreWarning

GEOMETRY = {"camera_model": "perspective", "focal_length_px": 1800.0, "principal_point_px": [800.0, 600.0],
            "camera_distance": 300.0, "light_distance": 250.0, "light_angle_deg": 45.0, "length_unit": "mm"}


def capture(n_angles=3, rows=4, cols=5, dtype=np.float32, data=None, lazy=False) -> xr.Dataset:
    shape = (n_angles, rows, cols)
    if data is None:
        data = np.arange(np.prod(shape), dtype=dtype).reshape(shape)
    frames = da.zeros(shape, dtype=dtype, chunks=(1, rows, cols)) if lazy else data
    counts = {"units": "counts", "long_name": "sensor counts"}  # what the kind fixes (checked on open)
    return xr.Dataset(
        {"target": (("angle", "row", "col"), frames, counts), "reference": (("angle", "row", "col"), frames, counts)},
        coords={"angle": ("angle", np.arange(n_angles) * 1.5, {"units": "degree"})},
        attrs=dict(GEOMETRY),
    )


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    data=arrays(np.float32, st.tuples(st.integers(1, 4), st.integers(1, 5), st.integers(1, 6)),
                elements=st.floats(width=32, allow_nan=True, allow_infinity=True)),
    channel=st.booleans(),
)
def test_round_trip_is_identical(tmp_path_factory, data, channel):
    ds = capture(*data.shape, data=data)
    if channel:
        ds = ds.expand_dims(channel=["r", "g", "b"], axis=-1)
    path = tmp_path_factory.mktemp("rt") / "s.zarr"
    to_store(ds, path, "tomography_capture")
    back = open_store(path).load()
    expected = ds.assign_attrs(selpath_format=FORMAT_VERSION, selpath_kind="tomography_capture",
                               selpath_kind_module="selpath.stages.tomography.acquire")  # where the kind is declared
    xr.testing.assert_identical(back, expected)


def test_opening_a_store_and_building_on_it_computes_nothing(tmp_path, no_compute):
    from selpath.stages.tomography.calibrate import absorption

    to_store(capture().assign_attrs(saturation_level=1e9), tmp_path / "s.zarr", "tomography_capture")  # numpy
    opened = open_store(tmp_path / "s.zarr")
    result = absorption(opened)
    assert result["absorption"].chunks is not None and no_compute.count == 0


@pytest.mark.parametrize(("shape", "disk"), [((6, 2200, 1000), (4, 1100, 1000)), ((40, 300, 400), (1, 300, 400))])
def test_stores_are_read_in_whole_on_disk_chunks(tmp_path, shape, disk):
    """An on-disk chunk over PROCESSING_CHUNK (17.6 MB here) is read whole, never split into pieces that each
    decode it; small ones (a frame of 0.5 MB) are grouped, whole, up to about PROCESSING_CHUNK."""
    frames = da.zeros(shape, dtype=np.float32, chunks=disk)
    ds = xr.Dataset({"target": (("angle", "row", "col"), frames), "reference": (("angle", "row", "col"), frames)},
                    coords={"angle": ("angle", np.arange(shape[0]) * 1.5, {"units": "degree"})}, attrs=dict(GEOMETRY))
    to_store(ds, tmp_path / "s.zarr", "tomography_capture")
    opened = open_store(tmp_path / "s.zarr")["target"]
    assert opened.encoding["chunks"] == disk
    for chunks, size in zip(opened.chunks, disk, strict=True):
        assert all(c % size == 0 for c in chunks[:-1])  # whole on-disk chunks, whatever their size
    nbytes = max(np.prod([c[0] for c in opened.chunks]) * 4, np.prod(disk) * 4)
    assert nbytes <= max(np.prod(disk) * 4, 16 * 2**20)
    if np.prod(disk) * 4 < 2**20:
        assert opened.chunks[0][0] > 1  # small frames are grouped


def test_numeric_data_are_written_with_fast_zstd_and_a_checksum(tmp_path):
    to_store(capture(), tmp_path / "s.zarr", "tomography_capture")
    for name in ("target", "angle"):
        compressors = zarr.open_array(tmp_path / "s.zarr" / name).compressors
        assert [(type(c).__name__, getattr(c, "level", None)) for c in compressors] == [("ZstdCodec", 1),
                                                                                        ("Crc32cCodec", None)]


def test_variables_cut_differently_along_a_dim_are_written_with_one_cut(tmp_path):
    """A result beside its input's flags (a stage's image in bands of 3 rows, a map read in one chunk): the store
    takes one chunking (Dataset.chunks refuses to answer otherwise) and reads back equal (#55's crash)."""
    ds = capture(rows=7)
    ds["target"] = ds["target"].chunk({"row": 3})
    ds["reference"] = ds["reference"].chunk({"row": 7})
    to_store(ds, tmp_path / "s.zarr", "tomography_capture")
    back = open_store(tmp_path / "s.zarr")
    xr.testing.assert_equal(back["target"].compute(), capture(rows=7)["target"])
    assert back["target"].chunks == back["reference"].chunks


def test_store_written_by_plain_xarray_opens(tmp_path):
    """The documented format is enough: no selpath writer involved. Without a manifest nothing says the writing
    finished, so opening warns; write_manifest (what to_store does last) records it."""
    ds = capture().assign_attrs(selpath_format=1, selpath_kind="tomography_capture")
    ds.to_zarr(tmp_path / "plain.zarr", consolidated=False)
    with pytest.warns(IncompleteStoreWarning, match="plain.zarr: no record that writing this store finished"):
        opened = open_store(tmp_path / "plain.zarr").load()
    # migrated from format 1 on open: labelled as its kind (units, long names, where the kind is declared)
    expected = ds.assign_attrs(selpath_format=FORMAT_VERSION, selpath_kind_module="selpath.stages.tomography.acquire")
    xr.testing.assert_identical(opened, expected)
    write_manifest(tmp_path / "plain.zarr", ds)
    xr.testing.assert_identical(open_store(tmp_path / "plain.zarr").load(), expected)


def test_schema_check_lists_every_problem(tmp_path):
    ds = capture().drop_vars("reference").transpose("row", "angle", "col")
    ds["angle"].attrs["units"] = "rad"
    del ds.attrs["length_unit"], ds.attrs["focal_length_px"]
    ds = ds.assign_attrs(selpath_format=1, selpath_kind="tomography_capture")
    ds.to_zarr(tmp_path / "bad.zarr", consolidated=False)
    with pytest.raises(StoreError) as info:
        open_store(tmp_path / "bad.zarr")
    message = str(info.value)
    assert message.startswith("5 problems in the store:"), message
    for expected in [
        r"bad.zarr: target: variable 'target' has dims \('row', 'angle', 'col'\); expected \('angle', 'row', 'col'\)",
        r"bad.zarr: reference: variable 'reference' is missing",
        r"coordinate 'angle' is in 'rad'; expected one of \[degree\]",
        r"attr 'length_unit' is missing",
        r"attr 'focal_length_px' is required for a perspective camera",
    ]:
        assert re.search(expected, message), (expected, message)


def test_newer_format_and_wrong_kind_and_corrupt_store(tmp_path):
    to_store(capture(), tmp_path / "s.zarr", "tomography_capture")
    with pytest.raises(StoreError, match="holds a 'tomography_capture' cube, not a 'sinogram' cube"):
        open_store(tmp_path / "s.zarr", "sinogram")
    zarr.open_group(tmp_path / "s.zarr", mode="r+").attrs["selpath_format"] = FORMAT_VERSION + 1
    newer = rf"format {FORMAT_VERSION + 1} is newer than this selpath reads \(format {FORMAT_VERSION}\)"
    with pytest.raises(StoreError, match=newer):
        open_store(tmp_path / "s.zarr")
    (tmp_path / "junk.zarr").mkdir()
    (tmp_path / "junk.zarr" / "zarr.json").write_text("{not json")
    with pytest.raises(StoreError, match=r"junk.zarr: cannot be read as a zarr store"):
        open_store(tmp_path / "junk.zarr")


def test_region_written_capture_reports_missing_frames_and_resumes(tmp_path):
    path = tmp_path / "cap.zarr"
    template = capture(n_angles=5, lazy=True)
    create_capture(path, template, "tomography_capture")
    assert missing_frames(path)["target"] == [{"angle": a} for a in (0.0, 1.5, 3.0, 4.5, 6.0)]
    truth = np.random.default_rng(0).normal(size=(5, 4, 5)).astype(np.float32)
    for i in (0, 1, 3):
        write_frame(path, "target", {"angle": i}, truth[i])
    for i in range(5):
        write_frame(path, "reference", {"angle": i}, truth[i] * 2)
    assert missing_frames(path) == {"target": [{"angle": 3.0}, {"angle": 6.0}], "reference": []}
    # resume: reopening with the same sweep keeps every frame already captured
    reopened = create_capture(path, template, "tomography_capture")
    np.testing.assert_array_equal(reopened["target"][[0, 1, 3]].values, truth[[0, 1, 3]])
    for i in (2, 4):
        write_frame(path, "target", {"angle": i}, truth[i])
    assert missing_frames(path) == {"target": [], "reference": []}
    np.testing.assert_array_equal(open_store(path)["target"].values, truth)
    assert "written__target" not in open_store(path)


def test_opening_an_unfinished_capture_for_processing_warns_with_the_count(tmp_path):
    """Unwritten frames read as NaN; without the flags nothing else would tell (a demultiplexing that masks
    NaN frames would silently run on fewer frames)."""
    from selpath.pipeline.store import IncompleteCaptureWarning

    path = tmp_path / "cap.zarr"
    create_capture(path, capture(n_angles=5, lazy=True), "tomography_capture")
    write_frame(path, "target", {"angle": 0}, np.ones((4, 5), np.float32))
    for i in range(5):
        write_frame(path, "reference", {"angle": i}, np.ones((4, 5), np.float32))
    with pytest.warns(IncompleteCaptureWarning, match=r"4 of 5 frames of 'target'.*run the acquisition again"):
        open_store(path)
    open_store(path, keep_flags=True)  # asking for the flags is how to see them: no warning


def test_resume_refuses_a_different_sweep_and_bad_frames(tmp_path):
    path = tmp_path / "cap.zarr"
    create_capture(path, capture(n_angles=5, lazy=True), "tomography_capture")
    other = capture(n_angles=5, lazy=True).assign_coords(angle=("angle", np.arange(5) * 2.0, {"units": "degree"}))
    with pytest.raises(StoreError, match=r"coordinate 'angle' differs from the new sweep's"):
        create_capture(path, other, "tomography_capture")
    with pytest.raises(StoreError, match=r"frame has shape \(3, 5\); the store expects \(4, 5\)"):
        write_frame(path, "target", {"angle": 0}, np.zeros((3, 5)))
    with pytest.raises(StoreError, match=r"must name exactly the frame dims \('angle',\)"):
        write_frame(path, "target", {"delay": 0}, np.zeros((4, 5)))
    assert len(missing_frames(path)["target"]) == 5


def test_provenance_survives_region_writes(tmp_path):
    path = tmp_path / "cap.zarr"
    create_capture(path, capture(lazy=True), "tomography_capture")
    write_provenance(path, {"step_hash": "abc", "settings": {"n": np.int64(3)}})
    write_frame(path, "target", {"angle": 1}, np.ones((4, 5)))
    assert read_provenance(path) == {"step_hash": "abc", "settings": {"n": 3}}
    assert read_provenance(tmp_path / "absent.zarr") is None
    shutil.rmtree(path)


def test_format_doc_lists_every_kind_as_the_code_does():
    from pathlib import Path

    from selpath.pipeline.kinds import describe_kinds
    from selpath.pipeline.registry import default_registry

    doc = (Path(__file__).resolve().parents[2] / "docs" / "format.md").read_text()
    assert describe_kinds(default_registry().kinds.values()) in doc, \
        "docs/format.md is out of date: paste `selpath kinds --markdown`"


def test_a_projector_camera_capture_must_say_where_its_sensor_clips(tmp_path):
    """A delay–exposure stack made by another tool without ``saturation_counts`` and ``dark_level_counts`` used
    to open, pass ``selpath validate``, and either fail at run time or (given ``full_scale``) be demultiplexed with
    clipped frames taken as data. It is refused on opening, naming both attrs."""
    image = np.zeros((2, 1, 3, 4), np.float32)
    ds = xr.Dataset({"image": (("delay", "exposure", "row", "col"), image, {"units": "counts"})},
                    coords={"delay": ("delay", [0.0, 17.0], {"units": "us"}),
                            "exposure": ("exposure", [170.0], {"units": "us"})},
                    attrs={"selpath_format": FORMAT_VERSION, "selpath_kind": "plane_to_ray_capture",
                           "scan_speed_px_per_us": 1 / 17, "line_time_us": 17.0})
    ds.to_zarr(tmp_path / "stack.zarr", consolidated=False)
    with pytest.raises(StoreError) as info:
        open_store(tmp_path / "stack.zarr")
    assert "attr 'saturation_counts' is missing" in str(info.value)
    assert "attr 'dark_level_counts' is missing" in str(info.value)
    ds.assign_attrs(saturation_counts=4095.0, dark_level_counts=64.0).to_zarr(tmp_path / "ok.zarr", consolidated=False)
    with pytest.warns(IncompleteStoreWarning):  # written by hand: no manifest says it finished
        assert open_store(tmp_path / "ok.zarr").attrs["dark_level_counts"] == 64.0
