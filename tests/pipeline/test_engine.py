"""The engine: one lazy graph, reuse by provenance, the same outputs under every scheduler."""

from __future__ import annotations

import collections
import functools
import os
import shutil

import numpy as np
import pytest
import xarray as xr

from selpath.pipeline import StageError, StageRegistry, build, load_workflow, open_store, read_provenance, run_workflow
from selpath.pipeline.errors import SpecError
from selpath.pipeline.registry import default_registry, stage

CALLS: collections.Counter = collections.Counter()


def counting_registry() -> StageRegistry:
    registry = StageRegistry()
    for builtin in default_registry():
        def make(original=builtin):
            @functools.wraps(original.func)
            def wrapper(*args, **kwargs):
                CALLS[original.name] += 1
                return original.func(*args, **kwargs)
            return stage(original.name, precheck=original.precheck,
                         identity=original.identity)(wrapper).__selpath_stage__
        registry.add(make())
    return registry


@pytest.fixture
def counted():
    CALLS.clear()
    return counting_registry()


def test_building_the_graph_computes_nothing(small_workflow, no_compute):
    results, _, report = build(load_workflow(small_workflow), reuse=False)
    assert set(results) == {"capture", "absorption"}
    assert report.computed() == ["capture", "absorption"]
    assert no_compute.count == 0


def test_rerun_recomputes_nothing_and_a_changed_setting_only_what_follows(small_workflow, counted):
    first = run_workflow(load_workflow(small_workflow, counted), progress=False)
    assert first.computed() == ["capture", "absorption"] and CALLS == {"simulate_parallel_capture": 1,
                                                                        "absorption": 1}
    before = open_store(first.written[1]).load()

    CALLS.clear()
    again = run_workflow(load_workflow(small_workflow, counted), progress=False)
    assert again.computed() == [] and again.written == [] and not CALLS
    assert {s.status for s in again.steps.values()} == {"reused"}

    small_workflow.write_text(small_workflow.read_text().replace("min_signal: 1.0", "min_signal: 2.0"))
    changed = run_workflow(load_workflow(small_workflow, counted), progress=False)
    assert changed.computed() == ["absorption"] and CALLS == {"absorption": 1}
    assert changed.steps["absorption"].reason == "settings changed: min_signal 1.0 -> 2.0"
    xr.testing.assert_identical(open_store(changed.written[0])["absorption"].load(), before["absorption"])

    CALLS.clear()
    small_workflow.write_text(small_workflow.read_text().replace("noise_std: 1.5", "noise_std: 0.5"))
    upstream = run_workflow(load_workflow(small_workflow, counted), progress=False)
    assert upstream.computed() == ["capture", "absorption"]
    assert upstream.steps["absorption"].reason == "inputs changed: $capture"


def test_an_interrupted_output_is_redone(small_workflow, counted):
    """A run killed while writing leaves only its staging sibling (the final path keeps the old store, or
    nothing): the next run tidies it away and writes the output."""
    report = run_workflow(load_workflow(small_workflow, counted), progress=False)
    final = report.written[1]
    os.rename(final, final.replace("absorption.zarr", ".absorption.zarr.partial-0123456789ab"))
    redo = run_workflow(load_workflow(small_workflow, counted), progress=False)
    assert redo.computed() == ["absorption"]
    assert redo.steps["absorption"].reason.startswith("no finished output at")
    assert sorted(p.name for p in (small_workflow.parent / "out").iterdir()) == ["absorption.zarr", "capture.zarr"]


def test_a_store_without_provenance_at_an_output_path_is_kept_unless_the_output_says_replace(small_workflow):
    """A store at an output path with no provenance and no manifest is not a run's leftover (outputs land
    through staging): it was made by hand or by an older selpath, so it is refused like another owner's
    store; ``replace: true`` on the output replaces it."""
    report = run_workflow(load_workflow(small_workflow), progress=False)
    shutil.rmtree(report.written[1] + "/_selpath")  # as a hand-made store: selpath's attrs, no record
    with pytest.raises(SpecError, match="no record of who wrote it"):
        load_workflow(small_workflow)
    small_workflow.write_text(small_workflow.read_text().replace(
        "absorption: {from: absorption, store: out/absorption.zarr}",
        "absorption: {from: absorption, store: out/absorption.zarr, replace: true}"))
    again = run_workflow(load_workflow(small_workflow), progress=False)
    assert again.computed() == ["absorption"] and read_provenance(report.written[1])["output"] == "absorption"


def test_outputs_carry_provenance(small_workflow):
    report = run_workflow(load_workflow(small_workflow), progress=False)
    provenance = read_provenance(report.written[1])
    assert provenance["workflow"] == "small-absorption"
    assert provenance["workflow_text"] == small_workflow.read_text()
    assert provenance["steps"]["capture"]["settings"]["rods"] == [{"x": 6.0, "y": 3.0, "radius": 4.0, "sigma": 0.05}]
    assert provenance["steps"]["absorption"]["settings"] == {"saturation_level": None, "min_signal": 1.0,
                                                             "min_signal_relative": 0.0, "flag_background": True,
                                                             "silhouette_threshold": None}
    assert set(provenance["versions"]) >= {"selpath", "xarray", "dask", "zarr"}


def _outputs(report) -> list[xr.Dataset]:
    return [open_store(path).load() for path in report.written]


def _run_copy(small_workflow, folder, **options) -> list[xr.Dataset]:
    """Run a copy of the workflow in its own folder (so its stores are its own) and load the outputs."""
    folder.mkdir()
    shutil.copy(small_workflow, folder / "wf.yaml")
    return _outputs(run_workflow(load_workflow(folder / "wf.yaml"), progress=False, **options))


@pytest.fixture
def synchronous_outputs(small_workflow, tmp_path) -> list[xr.Dataset]:
    return _run_copy(small_workflow, tmp_path / "synchronous", scheduler="synchronous")


def test_same_outputs_under_every_local_scheduler(small_workflow, tmp_path, synchronous_outputs):
    threaded = _run_copy(small_workflow, tmp_path / "threads", scheduler="threads")
    for a, b in zip(synchronous_outputs, threaded, strict=True):
        xr.testing.assert_identical(a, b)
    assert float(synchronous_outputs[1]["absorption"].max()) > 0.3


def test_same_outputs_on_a_two_worker_process_cluster(small_workflow, tmp_path, synchronous_outputs):
    clustered = _run_copy(small_workflow, tmp_path / "processes", scheduler="processes")
    for a, b in zip(synchronous_outputs, clustered, strict=True):
        xr.testing.assert_identical(a, b)


def test_dask_scheduler_address_overrides(small_workflow, tmp_path, monkeypatch, synchronous_outputs, capsys):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", cluster.scheduler_address)
        folder = tmp_path / "tcp"
        folder.mkdir()
        shutil.copy(small_workflow, folder / "wf.yaml")
        lines: list[str] = []
        # progress asked for, but the output is not a terminal: distributed's text bars stay out of it
        report = run_workflow(load_workflow(folder / "wf.yaml"), progress=True, log=lines.append)
        remote = _outputs(report)
    # the log names what ran the computation: the cluster's address and its one worker
    assert any(line.startswith(f"[dim]scheduler: {cluster.scheduler_address} (1 worker;") for line in lines), lines
    printed = capsys.readouterr()
    assert "[####" not in printed.out + printed.err and "% Completed" not in printed.out + printed.err
    for a, b in zip(synchronous_outputs, remote, strict=True):
        xr.testing.assert_identical(a, b)


def test_the_scheduler_line_of_a_cluster_without_a_dashboard():
    from selpath.pipeline.compute import scheduler_line

    class NoDashboard:  # a scheduler started without bokeh: distributed's dashboard_link raises KeyError
        def scheduler_info(self):
            return {"address": "tcp://10.0.0.1:8786", "workers": {"a": {}, "b": {}}, "services": {}}

        @property
        def dashboard_link(self):
            raise KeyError("dashboard")

    assert scheduler_line("tcp://10.0.0.1:8786", NoDashboard()) == "scheduler: tcp://10.0.0.1:8786 (2 workers)"


def test_the_log_names_a_local_scheduler(small_workflow, tmp_path):
    (tmp_path / "wf").mkdir()
    shutil.copy(small_workflow, tmp_path / "wf" / "wf.yaml")
    lines: list[str] = []
    run_workflow(load_workflow(tmp_path / "wf" / "wf.yaml"), scheduler="threads", progress=False, log=lines.append)
    assert "[dim]scheduler: threads (this process)[/]" in lines


@stage("scaled_transmittance")
def scaled_transmittance(frames: xr.DataArray, /, *, factor: float = 0.5) -> xr.Dataset:
    """Test stage: a DataArray input wired with $step.variable."""
    return xr.Dataset({"transmittance": frames * factor, "flags": xr.zeros_like(frames, dtype=np.uint8)},
                      attrs={"selpath_kind": "transmittance"})


def test_variable_references(small_workflow, tmp_path):
    registry = StageRegistry([*default_registry(), scaled_transmittance.__selpath_stage__])
    text = small_workflow.read_text().replace(
        "outputs:", "  - id: scaled\n    stage: scaled_transmittance\n    with: {frames: $capture.target}\noutputs:")
    text += "  scaled: {from: scaled, store: out/scaled.zarr}\n"
    path = tmp_path / "vars.yaml"
    path.write_text(text)
    report = run_workflow(load_workflow(path, registry), progress=False)
    scaled, capture = open_store(report.written[-1]), open_store(report.written[0])
    xr.testing.assert_allclose(scaled["transmittance"], capture["target"] * 0.5)
    path.write_text(text.replace("$capture.target", "$capture.nosuch"))
    with pytest.raises(StageError, match=r"\$capture.nosuch names no variable of step 'capture' \(it has \["):
        run_workflow(load_workflow(path, registry), progress=False, reuse=False)
