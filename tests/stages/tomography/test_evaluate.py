"""reconstruction_error against numpy on the same arrays, and the grids it refuses to compare."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from pipeline.errors import StageError
from stages.tomography.evaluate import reconstruction_error


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
