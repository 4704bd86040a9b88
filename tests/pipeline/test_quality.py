"""Usable shares: a step's own and those of the unstored steps upstream are checked in the pass that writes an
output; below its floor nothing is written and the error names the step, the share, the cause and the fix."""

from __future__ import annotations

import os

import dask.array as da
import numpy as np
import pytest
import xarray as xr

from selpath.pipeline import StageError, StageRegistry, load_workflow, open_store, read_provenance, run_workflow, stage
from selpath.pipeline.quality import enforce, usable_share

COORDS = {"y": ("y", [0.0, 1.0], {"units": "mm"}), "x": ("x", np.arange(4.0), {"units": "mm"})}


@stage("masked")
def masked(*, valid: int = 8) -> xr.Dataset:
    """8 values, the first ``valid`` of them usable (lazy)."""
    data = da.where(da.arange(8, chunks=4) < valid, 1.0, np.nan)
    share = usable_share(xr.DataArray(da.isfinite(data).mean()), floor=0.25, what="values that are finite",
                         fix="lower `valid`'s threshold")
    return xr.Dataset({"sigma": (("y", "x"), data.reshape(2, 4)), "usable_fraction": share}, coords=COORDS,
                      attrs={"selpath_kind": "reconstruction"})


@stage("doubled")
def doubled(source: xr.Dataset, /) -> xr.Dataset:
    return xr.Dataset({"sigma": source["sigma"] * 2}, coords=source.coords, attrs={"selpath_kind": "reconstruction"})


@stage("relay")
def relay(source: xr.Dataset, /) -> xr.Dataset:
    """Its own share: the finite share of what it passes on (fails where the source fails)."""
    share = usable_share(xr.DataArray(source["sigma"].notnull().mean()), floor=0.25, what="values passed on",
                         fix="look upstream")
    return xr.Dataset({"sigma": source["sigma"], "passed": share}, coords=source.coords,
                      attrs={"selpath_kind": "reconstruction"})


REGISTRY = StageRegistry([masked.__selpath_stage__, doubled.__selpath_stage__, relay.__selpath_stage__])
WORKFLOW = """\
workflow: q
scheduler: synchronous
steps:
  - {{id: m, stage: masked, with: {{valid: {valid}}}}}
  - {{id: d, stage: doubled, with: {{source: $m}}}}
outputs:
{outputs}
"""


def _run(tmp_path, valid, outputs):
    (tmp_path / "wf.yaml").write_text(WORKFLOW.format(valid=valid, outputs=outputs))
    return run_workflow(load_workflow(tmp_path / "wf.yaml", REGISTRY), progress=False)


def test_a_share_below_its_floor_stops_the_output_naming_cause_and_fix(tmp_path):
    with pytest.raises(StageError, match=r"step 'm' usable_fraction: only 12.50% of values that are finite \(floor "
                                         r"25.00%\): its output would mean nothing \(fix: lower `valid`'s threshold\)"):
        _run(tmp_path, 1, "  m: {from: m, store: m.zarr}")
    assert sorted(os.listdir(tmp_path)) == ["wf.yaml"]  # nothing written, nothing left behind


def test_an_unstored_upstream_step_is_checked_with_the_output_after_it(tmp_path):
    with pytest.raises(StageError, match=r"step 'm' usable_fraction: only 12.50%"):
        _run(tmp_path, 1, "  d: {from: d, store: d.zarr}")
    assert sorted(os.listdir(tmp_path)) == ["wf.yaml"]
    _run(tmp_path, 6, "  d: {from: d, store: d.zarr}")
    stored = open_store(tmp_path / "d.zarr")
    assert list(stored.data_vars) == ["sigma"]  # the carried share is recorded, not left in the store
    assert read_provenance(tmp_path / "d.zarr")["usable"] == {"m": {"usable_fraction": 0.75}}


def test_a_failing_step_with_its_own_share_is_explained_by_the_upstream_ones(tmp_path):
    """Upstream shares are computed only to explain a failure (carrying them would compute every upstream
    pixel); the error names the upstream cause first."""
    (tmp_path / "wf.yaml").write_text(WORKFLOW.format(valid=1, outputs="  r: {from: r, store: r.zarr}").replace(
        "outputs:", "  - {id: r, stage: relay, with: {source: $m}}\noutputs:"))
    with pytest.raises(StageError) as info:
        run_workflow(load_workflow(tmp_path / "wf.yaml", REGISTRY), progress=False)
    message = str(info.value)
    assert message.index("step 'm' usable_fraction: only 12.50%") < message.index("step 'r' passed: only 12.50%")
    assert sorted(os.listdir(tmp_path)) == ["wf.yaml"]


def test_the_share_stays_in_the_steps_own_store(tmp_path):
    _run(tmp_path, 8, "  m: {from: m, store: m.zarr}")
    stored = open_store(tmp_path / "m.zarr")
    assert float(stored["usable_fraction"]) == 1.0
    assert stored["usable_fraction"].attrs["long_name"] == "share of values that are finite"


def test_enforce_checks_a_result_in_a_notebook():
    assert enforce(masked(valid=4)) == {"usable_fraction": 0.5}
    with pytest.raises(StageError, match="only 0.00% of values that are finite"):
        enforce(masked(valid=0))
