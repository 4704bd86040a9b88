"""Does a capture's stated axis column agree with its own backlit frames? The check ``selpath import`` runs on a
``tomography_capture`` (the kind's ``data_checks``), and the silhouette edges ``calibrate_rig`` fits.

Over a full turn the left and right silhouette edges sample the same support function only when the rotation axis is
seen in the stated column (:func:`~selpath.stages.tomography._rig_fits.fit_axis_column`): the fit says where it is
seen, with its uncertainty. A stated column off by more than three of those uncertainties misplaces every ray, and
an offset of half a pixel is the signature of the pixel-centre convention (a renderer's pixel j is centred at
j + ½; selpath's at j), which an import spec states with ``pixel_centres``.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.geometry.rig import RigGeometry
from selpath.pipeline.errors import SelpathError
from selpath.stages.tomography._rig_fits import fit_axis_column, silhouette_edges

#: an offset is reported beyond this many standard uncertainties, and when it is at least this many pixels
LIMIT_SIGMA, LIMIT_PX = 3.0, 0.1
#: rows whose silhouettes the check fits (spread over those that show the object), as calibrate_rig's default
CHECK_ROWS = 32


def spread(n: int, count: int) -> np.ndarray:
    """``count`` indices spread evenly over ``range(n)`` (all of them when ``n ≤ count``)."""
    return np.unique(np.linspace(0, n - 1, min(count, n)).round().astype(int))


def all_edges(capture: xr.Dataset) -> np.ndarray:
    """:func:`silhouette_edges` of every backlit frame (dark subtracted), (angle, row, 2), lazily one task per angle
    chunk and computed at once (the edges are small: two numbers per row and view)."""
    signal = capture["backlit"] - capture["dark"] if "dark" in capture else capture["backlit"]
    edges = xr.apply_ufunc(silhouette_edges, signal.transpose("angle", "row", "col").chunk({"row": -1, "col": -1}),
                           input_core_dims=[["row", "col"]], output_core_dims=[["row", "side"]], dask="parallelized",
                           output_dtypes=[np.float64], dask_gufunc_kwargs={"output_sizes": {"side": 2}})
    return np.asarray(edges.transpose("angle", "row", "side").values)


def full_turn(angles: np.ndarray, tolerance: float = 1e-6) -> bool:
    """Whether ``angles`` [degree] are at least 8 equal steps over one full turn (within ``tolerance`` of 360°)."""
    steps = np.diff(angles)
    return len(angles) >= 8 and bool(np.allclose(steps, steps[0], rtol=0, atol=1e-6)) and \
        abs(len(angles) * steps[0] - 360.0) <= tolerance * 360 + 1e-6


def stated_axis_advice(capture: xr.Dataset) -> list[str]:
    """Advice when the capture's stated axis column (``principal_point_px[0]``) disagrees with where its backlit
    silhouettes over a full turn put the rotation axis, beyond three standard uncertainties (and 0.1 px); naming
    the pixel-centre convention when the offset is half a pixel. Empty where it agrees, and where the capture
    cannot say (no backlit frames, not a full turn in equal steps, no row with both edges over the turn)."""
    if "backlit" not in capture or "angle" not in capture.coords:
        return []
    capture = capture.sortby("angle")
    angles = capture["angle"].values.astype(float)
    if not full_turn(angles):
        return []
    stated = RigGeometry.from_attrs(capture.attrs, capture.sizes["row"], capture.sizes["col"],
                                    where="the capture")
    rows = spread(capture.sizes["row"], 4 * CHECK_ROWS)  # read a few rows, fit those that show the object
    edges = all_edges(capture.isel(row=rows))
    seen = np.flatnonzero(np.isfinite(edges).any(axis=(0, 2)))
    if not len(seen):
        return []
    try:
        fit = fit_axis_column(edges[:, seen[spread(len(seen), CHECK_ROWS)]], angles, stated.camera)
    except SelpathError:
        return []
    column, std = float(fit.value[0]), float(fit.std[0])
    offset = column - stated.camera.centre_px[0]
    if not np.isfinite(offset) or abs(offset) <= max(LIMIT_SIGMA * std, LIMIT_PX):
        return []
    said = (f"the stated axis column (principal_point_px[0] = {stated.camera.centre_px[0]:g} px) is "
            f"{abs(offset):.2f} ± {std:.2f} px {'left' if offset > 0 else 'right'} of where the backlit silhouettes "
            f"put the rotation axis ({column:.2f} px)")
    calibrate = "or estimate the axis from the frames (calibrate_rig, then apply_rig_calibration)"
    if abs(abs(offset) - 0.5) <= max(LIMIT_SIGMA * std, LIMIT_PX):
        convention = ("if the frames' pixel j is centred at j + ½ (renderers, many calibration tools), state "
                      "pixel_centres: half" if offset < 0 else
                      "if the frames' pixel j is centred at j (selpath's convention), leave pixel_centres out")
        return [f"{said}. Half a pixel: the likely cause is the pixel-centre convention. Fix: {convention} in the "
                f"import spec and import again; {calibrate}."]
    return [f"{said}: every ray is misplaced by that much. Fix: correct principal_point_px; {calibrate}."]
