"""How far a reconstruction is from a known truth (a simulated scene's σ, ``phantom_truth``): RMSE and max |error|.

The numbers a workflow's report quotes (``{fbp_error.rmse:.3e}``) and a study compares; lazy (two 0-d dask
reductions).
"""

from __future__ import annotations

import xarray as xr

from pipeline.errors import Problem, StageError
from pipeline.registry import stage
from stages._common import require_variables


@stage("reconstruction_error")
def reconstruction_error(reconstruction: xr.Dataset, truth: xr.Dataset, /) -> xr.Dataset:
    """RMSE and max |error| of ``reconstruction``'s σ against ``truth``'s, over every slice and pixel (NaN skipped).

    A truth of one slice is compared with every slice of the reconstruction (a prism's σ is the same at every
    height); otherwise slices are matched by their ``slice`` coordinate. Both must share the (y, x) grid.
    """
    require_variables(reconstruction, ("sigma",), "reconstruction_error")
    require_variables(truth, ("sigma",), "reconstruction_error")
    expected = truth["sigma"]
    if "slice" in expected.dims and expected.sizes["slice"] == 1:
        expected = expected.isel(slice=0, drop=True)
    for dim in ("y", "x"):
        if reconstruction.sizes.get(dim) != expected.sizes.get(dim):
            raise StageError(Problem(f"reconstruction_error: the reconstruction has {dim} size "
                                     f"{reconstruction.sizes.get(dim)}, the truth {expected.sizes.get(dim)}",
                                     where=dim, fix="rasterise the truth on the reconstruction's grid "
                                     "(phantom_truth with the reconstruction's sinogram and n_pixels)"))
    error = reconstruction["sigma"] - expected.drop_vars(["y", "x"], errors="ignore").assign_coords(
        y=reconstruction["y"], x=reconstruction["x"])
    slices = reconstruction.sizes.get("slice", 1)
    unit = reconstruction["sigma"].attrs.get("units", "")
    return xr.Dataset(
        {"rmse": ((), ((error**2).mean() ** 0.5).data, {"units": unit}),
         "max_abs_error": ((), abs(error).max().data, {"units": unit})},
        attrs={"selpath_kind": "reconstruction_error", "slices": int(slices),
               "method": reconstruction.attrs.get("method", "")})
