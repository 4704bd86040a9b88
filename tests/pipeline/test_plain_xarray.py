"""Stores as a user sees them in plain xarray: ``xr.open_zarr(path)`` is quiet and shows what selpath wrote
(consolidated metadata kept fresh through captures, manifests and provenance), and strings are written in a
type zarr v3 specifies (no UnstableSpecificationWarning)."""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

import dask.array as da
import numpy as np
import pytest
import xarray as xr
import zarr

from selpath.pipeline import (
    StoreError,
    create_capture,
    load_workflow,
    open_store,
    read_provenance,
    run_workflow,
    to_store,
    write_frame,
    write_provenance,
)
from selpath.pipeline.integrity import open_group, verify_store
from tests.helpers.acquisition import make_workflow

GEOMETRY = {"camera_model": "orthographic", "pixel_size": 0.1, "light_angle_deg": 45.0, "length_unit": "mm"}


def study() -> xr.Dataset:
    """A light-angle study: its ``method`` coordinate is fixed-width numpy strings (``<U12``), as the stage makes."""
    sigma = np.random.default_rng(0).random((2, 2, 3, 3))
    ds = xr.Dataset(
        {"sigma": (("light_angle", "method", "y", "x"), sigma), "rmse": (("light_angle", "method"), sigma.mean((2, 3))),
         "max_abs_error": (("light_angle", "method"), sigma.max((2, 3)))},
        coords={"light_angle": ("light_angle", [0.0, 30.0], {"units": "degree"}), "method": ["fbp", "optimisation"],
                "y": ("y", np.arange(3.0), {"units": "mm"}), "x": ("x", np.arange(3.0), {"units": "mm"}),
                "label": ("light_angle", ["side", "behind"])},
        attrs={"scene": "phantom-cylinder"})
    assert ds["method"].dtype.kind == "U" and ds["label"].dtype.kind == "U"
    return ds


def capture_template(n_angles: int = 3) -> xr.Dataset:
    frames = da.zeros((n_angles, 4, 5), dtype=np.float32, chunks=(1, 4, 5))
    counts = {"units": "counts", "long_name": "sensor counts"}
    return xr.Dataset({"target": (("angle", "row", "col"), frames, counts),
                       "reference": (("angle", "row", "col"), frames, counts)},
                      coords={"angle": ("angle", np.arange(n_angles) * 1.5, {"units": "degree"})},
                      attrs=dict(GEOMETRY))


def assert_plain_view_is_fresh(path: Path) -> None:
    """``xr.open_zarr(path)`` (consolidated metadata) warns of nothing and shows the store as its nodes' own
    metadata do, attrs of the root and of every variable; zarr's consolidated view of ``_selpath`` (manifest,
    provenance) is as fresh."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plain = xr.open_zarr(path)
        consolidated = zarr.open_group(path, mode="r")
    fresh = xr.open_zarr(path, consolidated=False)
    assert plain.attrs == fresh.attrs
    assert set(plain.variables) == set(fresh.variables)
    for name, var in fresh.variables.items():
        assert plain[name].attrs == var.attrs, name
        assert plain[name].dims == var.dims, name
    assert consolidated.metadata.consolidated_metadata is not None  # not read member by member
    assert dict(consolidated["_selpath"].attrs) == dict(open_group(path)["_selpath"].attrs)


def test_fixed_width_strings_are_written_portably_and_read_back_equal(tmp_path):
    ds = study()
    path = tmp_path / "study.zarr"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # zarr's UnstableSpecificationWarning is a UserWarning
        to_store(ds, path, "light_angle_study")
    for name in ("method", "label"):
        assert open_group(path)[name].metadata.data_type.to_json(zarr_format=3) == "string", name
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = open_store(path).load()
        plain = xr.open_zarr(path).load()
    for read in (back, plain):
        assert read["method"].values.tolist() == ["fbp", "optimisation"]
        assert read["label"].values.tolist() == ["side", "behind"]
        xr.testing.assert_equal(read.drop_attrs(), ds.drop_attrs())
        assert float(read["rmse"].sel({"method": "optimisation", "light_angle": 30.0})) == pytest.approx(
            float(ds["rmse"][1, 1]))
    assert verify_store(path) == []


def test_a_whole_store_opens_quietly_in_plain_xarray_and_stays_fresh_after_provenance(tmp_path):
    path = tmp_path / "study.zarr"
    to_store(study(), path, "light_angle_study")
    assert_plain_view_is_fresh(path)
    write_provenance(path, {"step_hash": "abc", "workflow": "w", "output": "study"})
    assert_plain_view_is_fresh(path)
    assert dict(zarr.open_group(path, mode="r")["_selpath"].attrs)["provenance"]["step_hash"] == "abc"


def test_a_capture_opens_quietly_in_plain_xarray_while_frames_arrive_and_after_provenance(tmp_path):
    path = tmp_path / "capture.zarr"
    create_capture(path, capture_template(), "tomography_capture")
    assert_plain_view_is_fresh(path)
    frame = np.full((4, 5), 7.0, dtype=np.float32)
    write_frame(path, "target", {"angle": 1}, frame)
    assert_plain_view_is_fresh(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plain = xr.open_zarr(path)
    np.testing.assert_array_equal(plain["target"][1].values, frame)  # data is read live, never from metadata
    assert plain["written__target"].values.tolist() == [False, True, False]
    for angle in range(3):
        for name in ("target", "reference"):
            write_frame(path, name, {"angle": angle}, frame)
    write_provenance(path, {"step_hash": "abc"})
    assert_plain_view_is_fresh(path)
    assert read_provenance(path) == {"step_hash": "abc"}


def test_selpath_reads_each_nodes_own_metadata_never_a_stale_consolidated_copy(tmp_path):
    """A units attr edited with zarr after writing (the consolidated copy in the root is now stale) is still
    refused on open: selpath does not read the consolidated copy."""
    path = tmp_path / "capture.zarr"
    create_capture(path, capture_template(), "tomography_capture")
    open_group(path, mode="r+")["angle"].attrs["units"] = "rad"
    assert zarr.open_group(path, mode="r")["angle"].attrs["units"] == "degree"  # the stale consolidated copy
    with pytest.raises(StoreError, match="'angle' has units 'rad' but was written in 'degree'"):
        open_store(path)


def test_every_store_a_workflow_writes_opens_quietly_in_plain_xarray(tmp_path, small_workflow):
    """The engine's paths: an acquisition's capture (filled frame by frame, provenance written in place) and
    staged outputs (manifest and provenance written, then moved into place)."""
    run_workflow(load_workflow(make_workflow(tmp_path / "acquired")), progress=False)
    run_workflow(load_workflow(small_workflow), progress=False)
    stores = sorted(tmp_path.rglob("*.zarr"))
    assert len(stores) == 3, stores
    for store in stores:
        assert read_provenance(store) is not None, store
        assert_plain_view_is_fresh(store)


def test_a_study_records_its_scene_by_name_and_content_never_by_path(tmp_path):
    from selpath import workflows
    from selpath.stages.tomography.acquire import AngleSweep
    from selpath.stages.tomography.studies import light_angle_study

    source = workflows.scene("phantom-cylinder")
    study = light_angle_study(scene=source, light_angles=(30.0,), n_theta=8, n_x=8, angles=AngleSweep(step=30.0),
                              max_iter=2)  # lazy: the attrs are known before anything is reconstructed
    assert study.attrs["scene"] == "phantom-cylinder"
    assert study.attrs["scene_sha256"] == hashlib.sha256(Path(source).read_bytes()).hexdigest()
    assert not any(os.sep in str(value) for value in study.attrs.values())
