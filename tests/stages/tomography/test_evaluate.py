"""reconstruction_error against numpy on the same arrays, and the grids it refuses to compare."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.pipeline.errors import StageError
from selpath.stages.tomography.evaluate import reconstruction_error


def cube(sigma: np.ndarray, extent: float = 1.0) -> xr.Dataset:
    n = sigma.shape[-1]
    grid = np.linspace(-extent, extent, n)
    return xr.Dataset({"sigma": (("slice", "y", "x"), sigma)},
                      coords={"slice": np.arange(sigma.shape[0]), "y": ("y", grid, {"units": "mm"}),
                              "x": ("x", grid, {"units": "mm"})})


def test_errors_equal_numpy_and_a_one_slice_truth_serves_every_slice():
    rng = np.random.default_rng(0)
    recon, truth = rng.random((3, 8, 8)), rng.random((1, 8, 8))
    recon[1, 2, 3] = np.nan  # skipped, as xarray's reductions skip NaN
    out = reconstruction_error(cube(recon).chunk({"slice": 1}), cube(truth)).compute()
    error = recon - truth
    assert float(out["rmse"]) == pytest.approx(np.sqrt(np.nanmean(error**2)), rel=1e-12)
    assert float(out["max_abs_error"]) == pytest.approx(np.nanmax(np.abs(error)), rel=1e-12)
    assert out.attrs["slices"] == 3


def test_slices_are_matched_by_coordinate():
    rng = np.random.default_rng(1)
    recon, truth = rng.random((2, 4, 4)), rng.random((3, 4, 4))
    shifted = cube(truth).assign_coords(slice=[1, 0, 5])
    out = reconstruction_error(cube(recon), shifted).compute()
    expected = np.stack([recon[0] - truth[1], recon[1] - truth[0]])
    assert float(out["rmse"]) == pytest.approx(np.sqrt(np.mean(expected**2)), rel=1e-12)
    with pytest.raises(StageError, match=r"the truth has no slice \[1\]"):
        reconstruction_error(cube(recon), cube(truth[:1]).assign_coords(slice=[0]).pipe(
            lambda t: xr.concat([t, t.assign_coords(slice=[4])], "slice")))


def test_a_truth_on_another_grid_is_refused():
    with pytest.raises(StageError, match=r"the reconstruction's y grid \(8 cells, -1 … 1\) is not the truth's"):
        reconstruction_error(cube(np.zeros((1, 8, 8))), cube(np.zeros((1, 8, 8)), extent=2.0))


def test_the_inclusions_mean_centroid_and_radius_against_their_definitions():
    """A disc of σ = 10 (radius 0.3) on a 64-grid: a reconstruction at half its σ, moved by three cells in x, on a
    σ = 1 background: mean_inside is numpy's mean over the truth's disc, the centroid three cells off (1e-9: the same
    cells, moved), the radius the same (0), both in the grid's unit; a reconstruction with no σ above 0 has no
    region: NaN, not 0."""
    n = 64
    grid = np.linspace(-1.0, 1.0, n)
    cell = grid[1] - grid[0]
    x, y = np.meshgrid(grid, grid)
    disc = (x - 0.2) ** 2 + (y + 0.1) ** 2 < 0.3**2
    truth = np.where(disc, 10.0, 0.0)[None]
    moved = np.roll(np.where(disc, 5.0, 0.0), 3, axis=1) + 1.0
    out = reconstruction_error(cube(moved[None]), cube(truth)).compute()
    assert float(out["mean_inside"]) == pytest.approx(moved[disc].mean(), rel=1e-12)
    assert float(out["truth_inside"]) == pytest.approx(10.0)
    assert float(out["centroid_error"]) == pytest.approx(3 * cell, rel=1e-9)
    assert float(out["radius_error"]) == pytest.approx(0.0, abs=1e-12)
    assert out["centroid_error"].attrs["units"] == "mm"
    empty = reconstruction_error(cube(np.zeros((1, n, n))), cube(truth)).compute()
    assert np.isnan(float(empty["centroid_error"])) and np.isnan(float(empty["radius_error"]))
    assert float(empty["mean_inside"]) == 0.0
