"""material_atlas (§5.4.10): extents against the lobes' analytic second moments, albedo-free profiles, ordering on
the shipped atlas, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats
import xarray as xr

from selpath import workflows
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.pipeline import StageError
from selpath.stages.procam.atlas import material_atlas

DU = DV = np.arange(-20, 21)


def strips(widths, albedos) -> ProcamScene:
    n = len(widths)
    objects = [{"name": f"m{k}", "region": {"kind": "rectangle", "x": [k / n, (k + 1) / n], "y": [0.0, 1.0]},
                "albedo": a, **({"effects": {"subsurface": {"width": f"{w} px", "fraction": 0.6}}} if w else {})}
               for k, (w, a) in enumerate(zip(widths, albedos, strict=True))]
    rig = {"camera_rows": 44, "camera_cols": 42 * n, "projector_rows": 44, "projector_cols": 42 * n, "bits": None,
           "noise": None}
    return ProcamScene.model_validate({"scene": "strips", "background": {"albedo": 0.0}, "objects": objects,
                                       "rig": rig})


def full_truth(s: ProcamScene) -> xr.Dataset:
    """The simulator's full transport T(du, dv, row, col) on 1-px cells, as demux_full lays it out."""
    t = s.rig.intensity * np.concatenate([tr.truth_tile(s, tile, DV, DU) for tile in tr.tiles(s)], axis=-1)
    return xr.Dataset({"transport": (("du", "dv", "row", "col"), t.reshape(len(DU), len(DV), 44, -1),
                                     {"units": "counts"})},
                      coords={"du": ("du", DU.astype(float), {"units": "px"}), "dv": ("dv", DV, {"units": "px"})},
                      attrs={"cell_width_px": 1.0})


def analytic_extent(w: float, f: float = 0.6) -> float:
    """RMS radius over the 41 × 41 window of (1 − f)·δ + f·Laplace(w)(du)·Laplace(w)(dv), unit cells (scipy)."""
    if not w:
        return 0.0
    cell = scipy.stats.laplace(scale=w).cdf(DU + 0.5) - scipy.stats.laplace(scale=w).cdf(DU - 0.5)
    second = f * 2 * (DU**2 * cell).sum() * cell.sum()
    return float(np.sqrt(second / ((1 - f) + f * cell.sum() ** 2)))


def test_extents_are_the_lobes_second_moments_and_albedo_leaves_the_profile_alone():
    """Noise-free truth, floor 0: each strip's extent is its lobe's RMS radius over the window, to 1e-9; the same
    lobe under albedos 0.3 and 0.9 gives the same scaled profile; each profile's maximum is 1."""
    widths, albedos = (0.0, 1.5, 3.0, 3.0), (0.5, 0.8, 0.3, 0.9)
    s = strips(widths, albedos)
    pixels = {f"m{k}": ((k + 0.5) / len(widths), 0.5) for k in range(len(widths))}
    atlas = material_atlas(full_truth(s), pixels=pixels, floor=0.0).compute()
    for k, w in enumerate(widths):
        assert atlas["extent"][k].item() == pytest.approx(analytic_extent(w), rel=1e-9, abs=1e-12), w
    np.testing.assert_allclose(atlas["profile"].max(("du", "dv")).values, 1.0)
    np.testing.assert_allclose(atlas["profile"][2].values, atlas["profile"][3].values, rtol=1e-12)
    # the map holds the same numbers at the sites
    for k in range(len(widths)):
        r, c = int(atlas["site_row"][k]), int(atlas["site_col"][k])
        assert atlas["extent_map"][r, c].item() == pytest.approx(atlas["extent"][k].item(), rel=1e-12)


def test_windows_the_transport_cannot_fill_and_wide_cells_are_refused():
    t = full_truth(strips((2.0,), (0.8,)))
    with pytest.raises(StageError, match="du spans -20 … 20; the window needs ±25"):
        material_atlas(t, pixels={"a": (0.5, 0.5)}, reach=25)
    with pytest.raises(StageError, match="u-cells are 2 px wide"):
        material_atlas(t.assign_attrs(cell_width_px=2.0), pixels={"a": (0.5, 0.5)})
    with pytest.raises(StageError, match="not full transport"):
        material_atlas(t.isel(du=0, drop=True).rename(dv="offset"), pixels={"a": (0.5, 0.5)})


@pytest.mark.slow
def test_the_shipped_atlas_orders_its_materials_by_their_scattering(tmp_path):
    """procam-atlas end to end (about 70 s, 2624 noisy frames demultiplexed): the extents follow the lobe widths of
    the scene (wood 0 < styrofoam 1 < marble 2 1.5 < plastic 2 < marble 1 2.5 < sponge 3 < candle 4 px, each
    group's mean), and materials that differ only in albedo agree within 0.4 px."""
    import shutil

    from selpath.pipeline import load_workflow
    from selpath.pipeline.engine import run_workflow
    from selpath.pipeline.store import open_store

    shutil.copy(workflows.path("procam-atlas"), tmp_path / "procam-atlas.yaml")
    shutil.copytree(workflows.folder() / "scenes", tmp_path / "scenes")
    run_workflow(load_workflow(tmp_path / "procam-atlas.yaml"), progress=False)
    atlas = open_store(tmp_path / "out/procam-atlas/atlas.zarr")
    extent = dict(zip(atlas["site"].values, atlas["extent"].values, strict=True))
    groups = [["wood"], ["styrofoam 1", "styrofoam 2", "styrofoam 3"], ["marble 2"],
              ["plastic green", "plastic mixed", "plastic white"], ["marble 1"], ["sponge pink", "sponge red"],
              ["candle"]]
    means = [np.mean([extent[name] for name in group]) for group in groups]
    assert means == sorted(means), dict(zip(map(tuple, groups), means, strict=True))
    for group in groups:
        values = [extent[name] for name in group]
        assert max(values) - min(values) < 0.4, group
