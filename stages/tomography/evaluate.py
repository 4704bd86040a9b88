"""How far a reconstruction is from a known truth (a simulated scene's σ, ``phantom_truth``): RMSE and max |error|,
and how well it recovers the truth's strongest feature (an absorbing inclusion): its mean σ there, where its centroid
lies and how large it is.

The numbers a workflow's report quotes (``{fbp_error.rmse:.3e}``) and a study compares; lazy (0-d dask
reductions).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables

_SIGMA = "1/{length}"
RECONSTRUCTION_ERROR = CubeKind(
    name="reconstruction_error",
    description="RMSE and largest absolute error of a reconstruction against a known truth; its inclusion's",
    variables={"rmse": Variable((), units=_SIGMA, long_name="RMSE of σ"),
               "max_abs_error": Variable((), units=_SIGMA, long_name="max |error| of σ"),
               "mean_inside": Variable((), required=False, units=_SIGMA,
                                       long_name="mean σ over the truth's half-maximum region"),
               "truth_inside": Variable((), required=False, units=_SIGMA,
                                        long_name="the truth's mean σ over its half-maximum region"),
               "centroid_error": Variable((), required=False, units="{length}",
                                          long_name="distance between the half-maximum regions' centroids"),
               "radius_error": Variable((), required=False, units="{length}",
                                        long_name="|difference| of the half-maximum regions' radii")},
)


@stage("reconstruction_error", kind=RECONSTRUCTION_ERROR)
def reconstruction_error(reconstruction: xr.Dataset, truth: xr.Dataset, /) -> xr.Dataset:
    """RMSE and max |error| of ``reconstruction``'s σ against ``truth``'s, over every slice and pixel (NaN skipped);
    and the inclusion's: the truth's cells at or above half its largest σ (per slice) are its inclusion, the
    reconstruction's cells at or above half of its own largest σ are the one it found (a half-maximum region: a
    blurred inclusion keeps about its size). ``mean_inside`` is the reconstruction's mean σ over the truth's
    inclusion (``truth_inside`` the truth's); ``centroid_error`` the distance between the σ-weighted centroids of
    the two regions and ``radius_error`` the difference of their radii (√(area/π)), the largest over the slices
    [length unit]; NaN where a region is empty (a truth or reconstruction with no σ above 0).

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

    Returns
    -------
    xr.Dataset
        A ``reconstruction_error`` cube: ``rmse`` and ``max_abs_error`` [per length unit] over every slice and pixel,
        and the inclusion's ``centroid_error`` and ``radius_error`` where it has one.

    References
    ----------
    Thesis §4.4.1 Appropriate setup of the measurement.
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
    expected = expected.assign_coords(y=reconstruction["y"], x=reconstruction["x"])
    sigma = reconstruction["sigma"]
    error = sigma - expected
    slices = reconstruction.sizes.get("slice", 1)
    inclusion = expected >= 0.5 * expected.max(("y", "x"))
    (x_true, y_true), radius_true = _region(expected, inclusion)
    (x_ours, y_ours), radius_ours = _region(sigma, sigma >= 0.5 * sigma.max(("y", "x")))
    return RECONSTRUCTION_ERROR.label(xr.Dataset(
        {"rmse": ((), ((error**2).mean() ** 0.5).data),
         "max_abs_error": ((), abs(error).max().data),
         "mean_inside": ((), sigma.where(inclusion).mean().data),
         "truth_inside": ((), expected.where(inclusion & sigma.notnull()).mean().data),
         "centroid_error": ((), np.hypot(x_ours - x_true, y_ours - y_true).max().data),
         "radius_error": ((), abs(radius_ours - radius_true).max().data)},
        attrs={"slices": int(slices), "method": reconstruction.attrs.get("method", ""),
               "length_unit": reconstruction["x"].attrs.get("units", reconstruction.attrs.get("length_unit", ""))}))


def _region(sigma: xr.DataArray, region: xr.DataArray) -> tuple[tuple[xr.DataArray, xr.DataArray], xr.DataArray]:
    """The σ-weighted centroid (x, y) of ``region``'s cells and its radius √(area/π), per slice (lazy)."""
    region = region & (sigma > 0)
    weight = sigma.where(region, 0.0)
    total = weight.sum(("y", "x"))
    centre = tuple((weight * sigma[dim]).sum(("y", "x")) / total.where(total > 0) for dim in ("x", "y"))
    cell = abs(float(np.diff(sigma["x"].values[:2])[0]) * float(np.diff(sigma["y"].values[:2])[0]))
    cells = region.sum(("y", "x"))
    return centre, np.sqrt(cells.where(cells > 0) * cell / np.pi)


def _span(values: np.ndarray) -> str:
    return f"{values.min():.4g} … {values.max():.4g}" if values.size else "empty"
