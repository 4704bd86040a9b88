"""What a cube kind is and how the engine finds one: declared beside its stage, registered with it, resolved by name
from a workflow's registry, a store's hint or every installed package; never a hidden special case."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import xarray as xr

from selpath.pipeline import (
    SelpathError,
    StageError,
    StageRegistry,
    StoreError,
    load_workflow,
    open_store,
    run_workflow,
    stage,
    to_store,
)
from selpath.pipeline.kinds import LENGTH_UNITS, CubeKind, Variable
from selpath.pipeline.registry import default_registry, resolve_kind

HEIGHT = CubeKind("height_map", {"height": Variable(("y", "x"), units="{length}", long_name="surface height")},
                  coord_units={"y": LENGTH_UNITS, "x": LENGTH_UNITS}, description="a height per point")


def _heights() -> xr.Dataset:
    coords = {d: (d, np.arange(3.0), {"units": "mm"}) for d in ("y", "x")}
    return xr.Dataset({"height": (("y", "x"), np.ones((3, 3)), {"units": "degree", "long_name": "wrong"})},
                      coords=coords)


def test_label_gives_the_kinds_metadata_and_leaves_its_input_alone():
    ds = _heights()
    labelled = HEIGHT.label(ds)
    assert labelled["height"].attrs == {"units": "mm", "long_name": "surface height"}  # {length} from x, y
    assert labelled.attrs == {"selpath_kind": "height_map", "selpath_kind_module": __name__}
    assert ds["height"].attrs == {"units": "degree", "long_name": "wrong"} and ds.attrs == {}
    assert HEIGHT.check(labelled) == [] and HEIGHT.module == __name__ and hash(HEIGHT) == hash("height_map")


def test_a_kind_refuses_a_bad_name_and_a_png_that_is_no_image():
    with pytest.raises(SelpathError, match="must be lower_snake_case"):
        CubeKind("Height", {})
    with pytest.raises(SelpathError, match="png names 'height', which must be one of its variables with dims"):
        CubeKind("flat", {"height": Variable(("y", "x"))}, png="height")


def test_batch_dims_are_a_field_of_the_kind_not_a_special_case():
    stacked = HEIGHT.label(_heights().expand_dims(slice=2))
    assert "has dims ('slice', 'y', 'x')" in HEIGHT.check(stacked)[0].message
    sliced = CubeKind("height_stack", dict(HEIGHT.variables), coord_units=HEIGHT.coord_units, batch_dims=("slice",))
    assert sliced.check(sliced.label(_heights().expand_dims(slice=2))) == []


def test_two_declarations_of_one_kind_name_are_refused_naming_both():
    @stage("one", kind=HEIGHT)
    def one(*, n: int = 1) -> xr.Dataset: ...

    other = CubeKind("height_map", {"height": Variable(("y", "x"), units="m")})

    @stage("two", kind=other)
    def two(*, n: int = 1) -> xr.Dataset: ...

    with pytest.raises(SelpathError, match=r"cube kind 'height_map' is declared twice, differently: by "
                                           r".*one and by .*two"):
        StageRegistry([one.__selpath_stage__, two.__selpath_stage__])
    registry = StageRegistry([one.__selpath_stage__])
    assert registry.kinds == {"height_map": HEIGHT} and registry.makers("height_map") == ["one"]
    assert resolve_kind("height_map", registry) is HEIGHT and resolve_kind("sinogram").batch_dims == ("slice",)
    with pytest.raises(StoreError, match=r"unknown cube kind 'height_map': no installed stage package declares it"):
        resolve_kind("height_map")


def test_a_stage_result_that_kept_its_inputs_kind_is_stored_as_the_stages_kind(small_workflow, tmp_path):
    """A stage declaring one kind whose result carries its input's selpath_kind (``capture.assign``) is stored as
    the stage's kind, checked against it: not silently as its input's."""
    frames = CubeKind("doubled_frames", {"target": Variable(("angle", "row", "col"), units="counts",
                                                            long_name="frames times two")})

    @stage("double_frames", kind=frames)
    def double_frames(capture: xr.Dataset, /) -> xr.Dataset:
        return capture[["target"]].assign(target=capture["target"] * 2)  # keeps the capture's attrs

    registry = StageRegistry([*default_registry(), double_frames.__selpath_stage__])
    text = small_workflow.read_text().replace(
        "outputs:", "  - {id: doubled, stage: double_frames, with: {capture: $capture}}\noutputs:")
    path = tmp_path / "double.yaml"
    path.write_text(text + "  doubled: {from: doubled, store: out/doubled.zarr}\n")
    report = run_workflow(load_workflow(path, registry), progress=False)
    stored = open_store(report.written[-1], registry=registry)
    assert stored.attrs["selpath_kind"] == "doubled_frames"
    assert stored["target"].attrs == {"units": "counts", "long_name": "frames times two"}


def test_a_kind_outside_the_stages_declarations_is_refused_by_name(small_workflow, tmp_path):
    @stage("relabel", kind=(HEIGHT, CubeKind("height_map_2", dict(HEIGHT.variables))))
    def relabel(capture: xr.Dataset, /) -> xr.Dataset:
        return capture

    registry = StageRegistry([*default_registry(), relabel.__selpath_stage__])
    path = tmp_path / "relabel.yaml"
    path.write_text(small_workflow.read_text().replace(
        "outputs:", "  - {id: again, stage: relabel, with: {capture: $capture}}\noutputs:")
        + "  again: {from: again, store: out/again.zarr}\n")
    with pytest.raises(StageError, match=r"is a 'tomography_capture' cube; its stage 'relabel' makes height_map or "
                                         r"height_map_2"):
        run_workflow(load_workflow(path, registry), progress=False)


def test_opening_a_store_imports_the_module_that_declares_its_kind_alone(tmp_path):
    """A store names where its kind was declared (``selpath_kind_module``): opening it imports that module, not every
    installed stage package (which takes seconds: JAX, OpenCV, scikit-learn …)."""
    from tests.helpers.stores import minimal

    store = tmp_path / "a.zarr"
    to_store(minimal("absorption"), store, "absorption")
    assert open_store(store).attrs["selpath_kind_module"] == "selpath.stages.tomography.calibrate"
    code = ("import sys, selpath\nds = selpath.open_store(sys.argv[1])\n"
            "print(ds.attrs['selpath_kind'], 'selpath.stages.tomography.calibrate' in sys.modules,"
            " 'selpath.stages.procam.demux' in sys.modules)")
    shown = subprocess.run([sys.executable, "-c", code, str(store)], capture_output=True, text=True, check=True)
    assert shown.stdout.split() == ["absorption", "True", "False"]


def test_a_hint_naming_a_module_outside_the_installed_packages_is_never_imported(tmp_path):
    from tests.helpers.stores import minimal

    store = tmp_path / "a.zarr"
    to_store(minimal("absorption"), store, "absorption")
    import zarr

    zarr.open_group(store, mode="r+").attrs["selpath_kind_module"] = "antigravity"  # would open a browser
    ds = open_store(store)  # found among the installed kinds instead
    assert ds.attrs["selpath_kind"] == "absorption" and "antigravity" not in sys.modules


def test_a_result_that_names_no_kind_from_a_stage_that_declares_none_is_refused_with_the_fix(small_workflow, tmp_path):
    @stage("bare")
    def bare(capture: xr.Dataset, /) -> xr.Dataset:
        return capture[["target"]].drop_attrs(deep=False)

    registry = StageRegistry([*default_registry(), bare.__selpath_stage__])
    path = tmp_path / "bare.yaml"
    path.write_text(small_workflow.read_text().replace(
        "outputs:", "  - {id: plain, stage: bare, with: {capture: $capture}}\noutputs:")
        + "  plain: {from: plain, store: out/plain.zarr}\n")
    with pytest.raises(StageError, match=r"outputs.plain: the result of step 'plain' names no cube kind \(no "
                                         r"selpath_kind attr\); its stage 'bare' declares none .*set `kind:` on the"):
        run_workflow(load_workflow(path, registry), progress=False)
    assert not (tmp_path / "out" / "plain.zarr").exists()
