"""How far a reconstruction is from a known truth (a simulated scene's σ, ``phantom_truth``): RMSE and max |error|.

The numbers a workflow's report quotes (``{fbp_error.rmse:.3e}``) and a study compares; lazy (two 0-d dask
reductions).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.errors import Problem, StageError
from pipeline.registry import stage
from stages._common import require_variables


@stage("reconstruction_error")
def reconstruction_error(reconstruction: xr.Dataset, truth: xr.Dataset, /) -> xr.Dataset:
    """RMSE and max |error| of ``reconstruction``'s σ against ``truth``'s, over every slice and pixel (NaN skipped).

    A truth of one slice is compared with every slice of the reconstruction (a prism's σ is the same at every
    height); otherwise slices are matched by their ``slice`` coordinate. Both must share the (y, x) grid.

    Parameters
    ----------
    reconstruction : xr.Dataset
        A ``reconstruction`` store (``fbp`` or ``reconstruct_tv``): ``sigma`` over (slice, y, x); its ``units``
        label the errors.
    truth : xr.Dataset
        A ``reconstruction`` store of the true σ (``phantom_truth``) on the same (y, x) grid and in the same units,
        of one slice or of every reconstructed slice.
    """
    require_variables(reconstruction, ("sigma",), "reconstruction_error")
    require_variables(truth, ("sigma",), "reconstruction_error")
    expected = truth["sigma"]
    if "slice" in expected.dims and expected.sizes["slice"] == 1:
        expected = expected.isel(slice=0, drop=True)
    for dim in ("y", "x"):
        ours, theirs = reconstruction["sigma"][dim].values, expected[dim].values
        if ours.shape != theirs.shape or not np.allclose(ours, theirs, rtol=1e-6, atol=1e-9 * np.ptp(ours)):
            raise StageError(Problem(f"reconstruction_error: the reconstruction's {dim} grid ({ours.size} cells, "
                                     f"{_span(ours)}) is not the truth's ({theirs.size} cells, {_span(theirs)})",
                                     where=dim, fix="rasterise the truth on the reconstruction's grid "
                                     "(phantom_truth with the reconstruction's sinogram and n_pixels)"))
    if "slice" in expected.dims:
        missing = sorted(set(reconstruction["sigma"]["slice"].values.tolist())
                         - set(expected["slice"].values.tolist()))
        if missing:
            raise StageError(Problem(f"reconstruction_error: the truth has no slice {missing[:5]}", where="slice",
                                     fix="give a truth of one slice or of every reconstructed slice"))
        expected = expected.sel(slice=reconstruction["sigma"]["slice"])
    error = reconstruction["sigma"] - expected.assign_coords(y=reconstruction["y"], x=reconstruction["x"])
    slices = reconstruction.sizes.get("slice", 1)
    unit = reconstruction["sigma"].attrs.get("units", "")
    return xr.Dataset(
        {"rmse": ((), ((error**2).mean() ** 0.5).data, {"units": unit}),
         "max_abs_error": ((), abs(error).max().data, {"units": unit})},
        attrs={"selpath_kind": "reconstruction_error", "slices": int(slices),
               "method": reconstruction.attrs.get("method", "")})


def _span(values: np.ndarray) -> str:
    return f"{values.min():.4g} … {values.max():.4g}" if values.size else "empty"
