"""The observation rate of light paths, the coverage (§4.2.7, Eq. 8–19).

``coverage`` measures, per slice, which share of the object's sinogram (``bin_sinogram``,
:mod:`selpath.stages.tomography.sinogram`) holds a ray, and sets it beside the thesis's closed form for a cylinder
(:func:`coverage_model`; :func:`optimal_light_angle` is the light angle of largest coverage, Eq. 12 and 19).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.geometry.rig import RigGeometry
from selpath.geometry.shapes import support_function
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.tomography.hull import contours


def _eq8(what: str) -> Variable:
    return Variable(("slice",), False, units="1", long_name=what)


COVERAGE = CubeKind(
    name="coverage",
    description="observation rate of a sinogram: measured and analytic d_min, d_max (§4.2.7)",
    variables={"coverage": Variable(("slice",), units="1", long_name="observed share d_max − d_min"),
               "d_min": Variable(("slice",), units="1", long_name="lowest observed |X| / R, d_min"),
               "d_max": Variable(("slice",), units="1", long_name="highest observed |X| / R, d_max"),
               "analytic_d_min": _eq8("d_min of Eq. 8–19 (cylinder of this radius)"),
               "analytic_d_max": _eq8("d_max of Eq. 8–19 (cylinder of this radius)"),
               "analytic_coverage": _eq8("coverage of Eq. 8–19"),
               "radius": Variable(("slice",), False, units="{length}", long_name="mean contour radius")},
)


def coverage_model(light_angle_deg, fov_deg=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d_min, d_max and coverage d_max − d_min of a cylinder (Eq. 8–11 orthographic, 13–18 perspective).

    ``fov_deg`` is the angle the cylinder subtends at the camera, 2·asin(R / D_c) (the camera's FOV when
    the object fills it); None for an orthographic camera.

    >>> [round(float(v), 4) for v in coverage_model(90.0)]
    [0.0, 1.0, 1.0]
    """
    t = np.deg2rad(np.asarray(light_angle_deg, dtype=float))
    if fov_deg is None:
        low = t <= np.pi / 2
        d_min = np.where(low, 0.0, np.sin(t / 2 - np.pi / 4))
        d_max = np.where(low, np.cos(np.pi / 4 - t / 2), 1.0)
    else:
        f = np.deg2rad(fov_deg)
        first, last = t <= (np.pi - f) / 2, t >= (np.pi + f) / 2
        d_min = np.where(first, 0.0, np.cos(3 * np.pi / 4 - t / 2 - f / 4))
        d_max = np.where(last, 1.0, np.cos(np.pi / 4 - t / 2 + f / 4))
    return d_min, d_max, d_max - d_min


def optimal_light_angle(fov_deg: float | None = None) -> float:
    """θ_l of largest coverage that keeps the sinogram's centre (Eq. 12 and 19), degrees."""
    return 90.0 if fov_deg is None else (180.0 - fov_deg) / 2


def _coverage_kernel(observed, vertices, n_vertices, *, theta, x):
    # (slice block, theta, x) observed; the slice's contour -> coverage and band edges in d = X / support
    out = np.full((4, observed.shape[0]), np.nan)
    for k in range(observed.shape[0]):
        count = int(n_vertices[k])
        if count < 3:
            continue
        v = vertices[k, :count]
        plus, minus = support_function(v, theta), support_function(v, theta + 180.0)
        d = np.where(x[None, :] >= 0, x[None, :] / plus[:, None], -x[None, :] / minus[:, None])
        inside = d <= 1.0
        seen = observed[k] & inside
        out[0, k] = seen.sum() / max(inside.sum(), 1)
        if seen.any():
            out[1, k], out[2, k] = d[seen].min(), d[seen].max()
        out[3, k] = np.mean(np.linalg.norm(v, axis=1))
    return np.moveaxis(out, 0, -1)


@stage("coverage", kind=COVERAGE)
def coverage(sinogram: xr.Dataset, hull: xr.Dataset, /) -> xr.Dataset:
    """Observed share of each slice's sinogram, with the band [d_min, d_max] it covers and Eq. 8–19.

    d = X / h(θ) is a ray's distance from the axis relative to the contour's support on its side (|X|/R
    for a cylinder); the coverage is the share of (θ, X) bins inside the object that hold a ray. The
    closed form uses the cylinder of the contour's mean radius, and for a perspective camera the angle
    it subtends, 2·asin(R / D_c). A global reduction per slice (lazy, small).

    Parameters
    ----------
    sinogram : xr.Dataset
        A ``sinogram`` store (``bin_sinogram``): ``observed`` over (slice, theta, x), X in the hull's length unit;
        its attrs ``light_angle_deg`` and ``length_unit`` are used where the hull lacks them.
    hull : xr.Dataset
        A ``hull`` store (``visual_hull``) holding every slice of the sinogram: ``vertices``, ``n_vertices``, and the
        camera's geometry attrs.

    Returns
    -------
    xr.Dataset
        A ``coverage`` cube: per slice the observed share ``coverage`` [1] of the sinogram and the band [``d_min``,
        ``d_max``] it covers, with Eq. 8–19's analytic values where the hull allows them.

    References
    ----------
    Thesis §4.2.7 Observation rate of the light path.
    """
    require_variables(sinogram, ("observed",), "coverage")
    if "slice" not in sinogram.dims:
        raise StageError(Problem("the sinogram has no slice dim", fix="bin it with bin_sinogram"))
    shell = contours(hull, sinogram["slice"], "coverage")
    fields = xr.apply_ufunc(
        _coverage_kernel, sinogram["observed"].chunk({"theta": -1, "x": -1}), shell["vertices"], shell["n_vertices"],
        input_core_dims=[["theta", "x"], ["vertex", "xy"], []], output_core_dims=[["field"]],
        dask="parallelized", output_dtypes=[np.float64], dask_gufunc_kwargs={"output_sizes": {"field": 4}},
        kwargs={"theta": sinogram["theta"].values, "x": sinogram["x"].values})
    measured, d_min, d_max, radius = (fields.isel(field=i, drop=True) for i in range(4))
    # the camera from the hull; the light angle and length unit from the sinogram where the hull lacks them
    carried = {k: sinogram.attrs[k] for k in ("light_angle_deg", "length_unit") if k in sinogram.attrs}
    geometry = RigGeometry.from_attrs(hull.attrs | carried, where="coverage: hull and sinogram")
    theta_l, camera = float(geometry.light_angle_deg), geometry.camera

    def model(r):
        return coverage_model(theta_l, camera.subtended_angle_deg(r))

    def bounds(r):
        return np.stack(np.broadcast_arrays(*model(r), r)[:3], axis=-1)

    analytic = xr.apply_ufunc(bounds, radius, output_core_dims=[["bound"]],
                              dask="parallelized", output_dtypes=[np.float64],
                              dask_gufunc_kwargs={"output_sizes": {"bound": 3}})
    bound = {name: analytic.isel(bound=i, drop=True).drop_attrs(deep=False)
             for i, name in enumerate(("analytic_d_min", "analytic_d_max", "analytic_coverage"))}
    return COVERAGE.label(xr.Dataset(
        {"coverage": measured, "d_min": d_min, "d_max": d_max, **bound, "radius": radius.drop_attrs(deep=False)},
        attrs={"light_angle_deg": theta_l, "camera_model": camera.model, "length_unit": geometry.length_unit}))
