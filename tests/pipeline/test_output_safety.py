"""Nothing a user owns is deleted: output path rules, staged writes moved into place, leftovers tidied."""

from __future__ import annotations

import os

import dask.array as da
import numpy as np
import pytest
import xarray as xr
from typer.testing import CliRunner

from selpath import workflows
from selpath.pipeline import SpecError, StageRegistry, load_workflow, open_store, read_provenance, run_workflow, stage
from selpath.pipeline.cli import app
from selpath.pipeline.outputs import Staging, tidy_staging
from selpath.pipeline.registry import default_registry
from selpath.pipeline.store import to_store

runner = CliRunner()

CAPTURE = """\
workflow: t
scheduler: synchronous
steps:
  - id: capture
    stage: simulate_parallel_capture
    with: {{angles: {{start: 0, stop: 20, step: 5}}, n_rows: 2, n_cols: 16}}
outputs:
{outputs}
"""


def _wf(folder, outputs: str):
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "wf.yaml"
    path.write_text(CAPTURE.format(outputs=outputs))
    return path


def _problems(path) -> str:
    with pytest.raises(SpecError) as info:
        load_workflow(path)
    return str(info.value)


def test_an_empty_store_path_is_refused_and_the_folder_survives_a_run(tmp_path):
    """The reported data loss: store "" resolved to the workflow's own folder, and `run` wiped it."""
    path = _wf(tmp_path / "project", '  a: {from: capture, store: ""}')
    (tmp_path / "project" / "notes.txt").write_text("my notes")
    message = _problems(path)
    assert "wf.yaml:8: outputs.a.store: output 'a' store '' is not a path ending in '.zarr'" in message
    result = runner.invoke(app, ["run", str(path), "--no-progress"])
    assert result.exit_code == 2 and "is not a path ending in '.zarr'" in result.output
    assert sorted(os.listdir(tmp_path / "project")) == ["notes.txt", "wf.yaml"]


def test_an_output_that_is_the_parent_of_another_is_refused(tmp_path):
    path = _wf(tmp_path, "  a: {from: capture, store: out/run1.zarr}\n"
                         "  b: {from: capture, store: out/run1.zarr/capture.zarr}")
    message = _problems(path)
    assert "outputs.a.store: output 'a' (" in message
    assert "run1.zarr) is a parent folder of output 'b'" in message and "writing one would delete the other" in message


def test_an_existing_folder_that_is_not_a_selpath_store_is_never_replaced(tmp_path):
    (tmp_path / "out" / "data.zarr").mkdir(parents=True)
    (tmp_path / "out" / "data.zarr" / "thesis.tex").write_text("years of work")
    path = _wf(tmp_path, "  a: {from: capture, store: out/data.zarr}")
    assert "holds files that are not a selpath store (no selpath_format marker); selpath never replaces them" in \
        _problems(path)
    assert (tmp_path / "out" / "data.zarr" / "thesis.tex").read_text() == "years of work"


@pytest.mark.parametrize(("store", "protected"), [
    ("..", "is not a path ending in '.zarr'"),
    ("../project.zarr", "would replace the workflow file"),
])
def test_outputs_never_hold_the_workflow_file_or_its_folder(tmp_path, store, protected):
    folder = tmp_path / "project.zarr"  # an odd but possible name for a project folder
    path = _wf(folder, f"  a: {{from: capture, store: {store}}}")
    assert protected in _problems(path)


def test_an_output_may_not_replace_an_input_store(tmp_path):
    path = _wf(tmp_path, "  a: {from: capture, store: cap.zarr}")
    run_workflow(load_workflow(path), progress=False)
    (tmp_path / "wf2.yaml").write_text("""\
workflow: t2
steps:
  - id: load
    stage: load_store
    with: {store: cap.zarr}
  - id: absorption
    stage: absorption
    with: {capture: $load}
outputs:
  a: {from: absorption, store: cap.zarr}
""")
    assert "would replace the input steps[0].with.store" in _problems(tmp_path / "wf2.yaml")


def test_an_acquisition_store_is_checked_at_its_own_setting(tmp_path):
    (tmp_path / "wf.yaml").write_text("""\
workflow: t
steps:
  - id: capture
    stage: acquire_tomography
    with: {rig: sim, scene: scene.yaml, store: "", angles: {start: 0, stop: 10, step: 5}}
""")
    import shutil
    shutil.copy(workflows.scene("gelatin-bin"), tmp_path / "scene.yaml")
    message = _problems(tmp_path / "wf.yaml")
    assert "wf.yaml:5: steps[0].with.store: output 'capture' store" in message and "ending in '.zarr'" in message


def _failing_registry(fail: bool) -> StageRegistry:
    """The built-in stages plus `ramp`, whose second block raises when ``fail`` (a crash in mid-write)."""
    @stage("ramp")
    def ramp(*, scale: float = 1.0) -> xr.Dataset:
        def block(x):
            if fail and x.min() >= 4:
                raise RuntimeError("power cut")
            return x * scale
        data = da.arange(8, chunks=4, dtype=float).map_blocks(block, dtype=float)
        return xr.Dataset({"sigma": (("y", "x"), data.reshape(2, 4))},
                          coords={"y": ("y", [0.0, 1.0], {"units": "mm"}), "x": ("x", np.arange(4.0), {"units": "mm"})},
                          attrs={"selpath_kind": "reconstruction"})

    registry = StageRegistry(default_registry())
    registry.add(ramp.__selpath_stage__)
    return registry


def test_a_crash_while_writing_leaves_the_old_store_whole_and_no_partial_store(tmp_path):
    path = tmp_path / "wf.yaml"
    text = "workflow: t\nscheduler: synchronous\nsteps:\n  - {{id: r, stage: ramp, with: {{scale: {scale}}}}}\n" \
           "outputs:\n  r: {{from: r, store: out/r.zarr}}\n"
    path.write_text(text.format(scale=1.0))
    run_workflow(load_workflow(path, _failing_registry(False)), progress=False)
    old = read_provenance(tmp_path / "out" / "r.zarr")["step_hash"]
    path.write_text(text.format(scale=2.0))
    with pytest.raises(RuntimeError, match="power cut"):
        run_workflow(load_workflow(path, _failing_registry(True)), progress=False)
    assert read_provenance(tmp_path / "out" / "r.zarr")["step_hash"] == old
    np.testing.assert_array_equal(open_store(tmp_path / "out" / "r.zarr")["sigma"].values.ravel(), np.arange(8.0))
    assert sorted(os.listdir(tmp_path / "out")) == ["r.zarr"]  # no partial sibling, no lock file left
    run_workflow(load_workflow(path, _failing_registry(False)), progress=False)
    np.testing.assert_array_equal(open_store(tmp_path / "out" / "r.zarr")["sigma"].values.ravel(), 2 * np.arange(8.0))


def test_leftovers_of_a_killed_writer_are_tidied_and_a_lost_store_restored(tmp_path):
    sigma = {"units": "1/mm", "long_name": "absorption coefficient σ"}  # as the reconstruction kind fixes them
    ds = xr.Dataset({"sigma": (("y", "x"), np.ones((2, 2)), sigma)},
                    coords={"y": ("y", [0.0, 1.0], {"units": "mm"}), "x": ("x", [0.0, 1.0], {"units": "mm"})})
    final = tmp_path / "r.zarr"
    to_store(ds, final, "reconstruction")
    (tmp_path / ".r.zarr.partial-0123").mkdir()  # killed mid-write
    os.rename(final, tmp_path / ".r.zarr.replaced-4567")  # killed between the two renames of a commit
    done = tidy_staging(final)
    assert done == ["removed .r.zarr.partial-0123", f"restored {final} from .r.zarr.replaced-4567"]
    assert sorted(os.listdir(tmp_path)) == ["r.zarr"]
    xr.testing.assert_identical(open_store(final)["sigma"].load(), ds["sigma"])


def test_a_commit_replaces_only_selpath_stores(tmp_path):
    final = tmp_path / "x.zarr"
    final.mkdir()
    (final / "keep.txt").write_text("mine")
    from selpath.pipeline.errors import StoreError
    staging = Staging(final)
    os.makedirs(staging.path)
    with pytest.raises(StoreError, match="not a selpath store appeared at this path"):
        staging.commit()
    assert (final / "keep.txt").read_text() == "mine" and os.listdir(tmp_path) == ["x.zarr"]


def test_a_figure_png_selpath_did_not_write_is_never_replaced(tmp_path):
    import matplotlib.image

    from selpath.pipeline import StoreError

    (tmp_path / "out").mkdir()
    matplotlib.image.imsave(tmp_path / "out" / "fig.png", np.zeros((2, 2, 3)))  # the user's own picture
    before = (tmp_path / "out" / "fig.png").read_bytes()
    path = _wf(tmp_path, "  a: {from: capture, store: out/fig.zarr}")  # not a figure: its PNG name is free
    assert load_workflow(path)
    path.write_text(path.read_text().replace("outputs:", "  - {id: f, stage: capture_figure, with: {capture: "
                                             "$capture}}\noutputs:").replace("from: capture", "from: f"))
    with pytest.raises(StoreError, match=r"a figure output also writes .*fig.png, which exists and was not written"):
        run_workflow(load_workflow(path), progress=False)
    assert (tmp_path / "out" / "fig.png").read_bytes() == before and sorted(os.listdir(tmp_path / "out")) == [
        "fig.png"]


def test_another_workflows_store_is_never_replaced(tmp_path):
    """Any selpath store used to be replaceable: a second workflow silently replaced another's capture."""
    first = _wf(tmp_path / "a", "  capture: {from: capture, store: ../shared.zarr}")
    run_workflow(load_workflow(first), progress=False)
    second = tmp_path / "b" / "wf.yaml"
    second.parent.mkdir()
    second.write_text(first.read_text().replace("workflow: t", "workflow: other"))
    assert "holds output 'capture' of workflow 't'; selpath replaces a store only for the output that wrote it" in \
        _problems(second)
    assert read_provenance(tmp_path / "shared.zarr")["workflow"] == "t"


def test_a_store_name_is_never_a_pattern_for_another_stores_leftovers(tmp_path):
    (tmp_path / ".abc.zarr.partial-0123").mkdir()  # another output's staging folder, being written
    assert tidy_staging(tmp_path / "a*.zarr") == [] and (tmp_path / ".abc.zarr.partial-0123").is_dir()


def test_remote_outputs_are_rewritten_in_place(tmp_path):
    """Object storage cannot rename: a second write (settings changed) replaces the store in place."""
    ds = xr.Dataset({"sigma": (("y", "x"), np.ones((2, 2)))},
                    coords={"y": ("y", [0.0, 1.0], {"units": "mm"}), "x": ("x", [0.0, 1.0], {"units": "mm"})})
    url = f"memory://{tmp_path.name}/r.zarr"
    to_store(ds, url, "reconstruction")
    to_store(ds * 2, url, "reconstruction")
    assert float(open_store(url)["sigma"].sum()) == 8.0


def test_to_store_does_not_replace_a_workflows_output_unless_told(tmp_path):
    """The Python API's to_store replaced any selpath store at its path, a workflow's finished output included.
    Now it refuses one, naming the output and workflow; ``replace=True`` replaces it (atomically), and a store
    to_store wrote itself is still rewritten in place of the old one."""
    from selpath.pipeline import StoreError

    path = _wf(tmp_path / "a", "  capture: {from: capture, store: out/capture.zarr}")
    run_workflow(load_workflow(path), progress=False)
    store = tmp_path / "a" / "out" / "capture.zarr"
    data = open_store(store).load()
    with pytest.raises(StoreError, match="holds output 'capture' of workflow 't'; to_store does not replace"):
        to_store(data, store, data.attrs["selpath_kind"])
    assert read_provenance(store)["workflow"] == "t"
    to_store(data, store, data.attrs["selpath_kind"], replace=True)
    assert read_provenance(store) is None
    to_store(data, store, data.attrs["selpath_kind"])  # its own store now: rewritten as before
