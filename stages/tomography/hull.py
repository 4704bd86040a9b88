"""Silhouettes and the visual hull (§4.2.6): the object's convex contour per slice.

A silhouette is where the object hides the lit diffuse plane behind it in a backlit frame. Each
silhouette row bounds the slice seen by that camera row from two sides: the rays through the left and
right silhouette edges are tangent to the object, so each gives a half-plane containing it. The visual
hull of a slice is the intersection of these half-planes over every angle, a convex polygon
(``scipy.spatial.HalfspaceIntersection``). Camera rows are treated as slices through their x–y
projections, which is exact for the vertical prisms the rig measures (and for orthographic cameras).
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection
from skimage.filters import threshold_otsu
from skimage.measure import label
from skimage.morphology import remove_small_holes, remove_small_objects

from devices.geometry import RigGeometry, geometry_attrs
from pipeline.constraints import Index, Positive
from pipeline.errors import Problem, StageError
from pipeline.quality import usable_share
from pipeline.registry import stage
from stages._common import require_variables, sorted_sweep


def _silhouette_kernel(backlit: np.ndarray, dark: np.ndarray, *, threshold: float | None, min_size: int) -> np.ndarray:
    signal = backlit.astype(np.float64) - dark
    out = np.zeros(signal.shape, dtype=bool)
    for i, frame in enumerate(signal.reshape(-1, *signal.shape[-2:])):
        finite = np.isfinite(frame)
        level = threshold
        if level is None:
            values = frame[finite]
            level = threshold_otsu(values) if values.size and np.ptp(values) > 0 else np.inf
        mask = finite & (frame < level)  # the object blocks the lit plane
        if min_size > 0:
            mask = _fill_small_holes(remove_small_objects(mask, max_size=min_size), min_size)
        out.reshape(-1, *signal.shape[-2:])[i] = mask
    return out


def _fill_small_holes(mask: np.ndarray, max_size: int) -> np.ndarray:
    """Fill holes up to ``max_size`` pixels; background touching the image border is never a hole (a thin
    strip of lit plane beside the object must stay background)."""
    border = np.zeros_like(mask)
    border[[0, -1], :] = border[:, [0, -1]] = True
    labels = label(~mask, connectivity=1)
    outside = np.unique(labels[border & ~mask])
    filled = remove_small_holes(mask, max_size=max_size)
    return filled & ~np.isin(labels, outside[outside > 0])


@stage("silhouettes")
def silhouettes(capture: xr.Dataset, /, *, threshold: Positive | None = None, min_size: Index = 16) -> xr.Dataset:
    """Binary object masks from the backlit frames, per angle (lazy, one task per angle chunk).

    Parameters
    ----------
    threshold : float or None
        Counts above dark below which a pixel is object; None: Otsu's threshold per frame [counts].
    min_size : int
        Blobs and holes up to this many pixels are removed (noise, dust); 0: none [px].
    """
    require_variables(capture, ("backlit",), "silhouettes")
    capture = sorted_sweep(capture, "angle", "silhouettes")
    backlit = capture["backlit"].chunk({"row": -1, "col": -1})
    dark = capture["dark"] if "dark" in capture else xr.zeros_like(backlit.isel(angle=0, drop=True))
    mask = xr.apply_ufunc(_silhouette_kernel, backlit, dark.chunk({"row": -1, "col": -1}),
                          input_core_dims=[["row", "col"], ["row", "col"]], output_core_dims=[["row", "col"]],
                          dask="parallelized", output_dtypes=[bool],
                          kwargs={"threshold": threshold, "min_size": min_size})
    mask = mask.transpose("angle", "row", "col")
    covered = mask.mean(("row", "col"))
    share = usable_share(((covered > 0) & (covered < 1)).mean(), floor=SILHOUETTE_FLOOR,
                         what="backlit frames with a silhouette (neither empty nor the whole frame)",
                         fix="check the backlit and dark frames (NaN, unlit, saturated) or set `threshold` [counts]")
    return xr.Dataset({"silhouette": mask, "object_fraction": share},
                      attrs=geometry_attrs(capture.attrs) | {"selpath_kind": "silhouettes"})


#: floor of ``object_fraction``: a hull from fewer than half the views is not the object's
SILHOUETTE_FLOOR = 0.5


def silhouette_half_planes(mask_row: np.ndarray, angles_deg: np.ndarray, geometry: RigGeometry, row: int
                           ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Half-planes ``n·p ≤ h`` (object frame) from one silhouette row at every angle, and counts of
    views that give no constraint: empty, touching the image border (that side), non-convex (gaps)."""
    normals, offsets = [], []
    counts = {"empty": 0, "border": 0, "gaps": 0}
    cols = mask_row.shape[-1]
    cx, _ = geometry.centre_px
    for phi, line in zip(angles_deg, mask_row, strict=True):
        on = np.flatnonzero(line)
        if not len(on):
            counts["empty"] += 1
            continue
        if len(on) != on[-1] - on[0] + 1:
            counts["gaps"] += 1  # not one run: the hull uses the outermost edges (its convex hull)
        rotation = np.array([[np.cos(np.deg2rad(phi)), -np.sin(np.deg2rad(phi))],
                             [np.sin(np.deg2rad(phi)), np.cos(np.deg2rad(phi))]])
        for edge, side, inside in ((on[0] - 0.5, -1.0, on[0] > 0), (on[-1] + 0.5, 1.0, on[-1] < cols - 1)):
            if not inside:
                counts["border"] += 1
                continue
            if geometry.camera_model == "orthographic":
                n_lab = np.array([side, 0.0])
                h = side * (edge - cx) * float(geometry.pixel_size)
            else:
                slope = (edge - cx) / float(geometry.focal_length_px)
                n_lab = side * np.array([1.0, -slope]) / np.hypot(1.0, slope)
                h = float(n_lab @ np.array([0.0, -float(geometry.camera_distance)]))
            normals.append(rotation.T @ n_lab)  # n·R(φ)p = (R(φ)ᵀ n)·p
            offsets.append(h)
    return np.array(normals).reshape(-1, 2), np.array(offsets), counts


def intersect_half_planes(normals: np.ndarray, offsets: np.ndarray) -> np.ndarray | None:
    """Vertices (counter-clockwise) of ``{p : normals·p ≤ offsets}``, or None if empty or unbounded."""
    if len(normals) < 3:
        return None
    # opposite views give the same tangent line twice (orthographic φ and φ + 180°): qhull wants each once
    _, unique = np.unique(np.round(np.column_stack([normals, offsets]), 9), axis=0, return_index=True)
    normals, offsets = normals[np.sort(unique)], offsets[np.sort(unique)]
    # Chebyshev centre: the deepest interior point (linear programme), also proves the set is bounded
    norms = np.linalg.norm(normals, axis=1)
    result = linprog(c=[0, 0, -1], A_ub=np.column_stack([normals, norms]), b_ub=offsets,
                     bounds=[(None, None), (None, None), (0, None)], method="highs")
    if result.status != 0 or result.x[2] <= 1e-12:
        return None
    try:
        points = HalfspaceIntersection(np.column_stack([normals, -offsets]), result.x[:2]).intersections
        hull = ConvexHull(points)
    except Exception:  # noqa: BLE001 - scipy's qhull raises its own QhullError for degenerate input
        return None
    return points[hull.vertices]


def _hull_kernel(masks: np.ndarray, rows: np.ndarray, *, angles: np.ndarray, geometry: RigGeometry,
                 max_vertices: int) -> tuple[np.ndarray, ...]:
    # masks: (row block, angle, col); one convex polygon per row
    vertices = np.full((masks.shape[0], max_vertices, 2), np.nan)
    counts = np.zeros((4, masks.shape[0]), dtype=np.int64)  # vertices, empty, border, gapped views
    for k, row in enumerate(rows.reshape(-1)):
        normals, offsets, views = silhouette_half_planes(masks[k], angles, geometry, int(row))
        counts[1:, k] = views["empty"], views["border"], views["gaps"]
        polygon = intersect_half_planes(normals, offsets)
        if polygon is not None:
            n = min(len(polygon), max_vertices)
            vertices[k, :n], counts[0, k] = polygon[:n], n
    # one output: the counts ride in two extra "vertex" slots (see stages.tomography.paths on multi-output graphs)
    extra = counts.T.reshape(-1, 2, 2).astype(np.float64)
    return np.concatenate([vertices, extra], axis=1)


@stage("visual_hull")
def visual_hull(silhouettes: xr.Dataset, /) -> xr.Dataset:
    """The convex contour of every slice (camera row) from the silhouettes of all angles.

    Lazy, one task per block of rows; each needs every angle of its rows (a reduction over angles).
    Rows where the object is absent or not bounded by the views get ``n_vertices = 0``; the variables
    ``empty_views``, ``border_views`` and ``gapped_views`` count, per slice, the views that constrained
    nothing (no object in the row; the object touching the image border, per side) or were not one run
    of pixels (a non-convex object or noise: the hull then uses the outermost edges).
    The contour is exact to ``hull_resolution`` (half a pixel at the rotation axis) for convex objects.
    """
    require_variables(silhouettes, ("silhouette",), "visual_hull")
    mask = silhouettes["silhouette"]
    problems = [Problem(f"attr {a!r} is missing; visual_hull needs the rig geometry", fix="compute the silhouettes "
                        "from a capture whose attrs carry it") for a in ("camera_model",) if a not in silhouettes.attrs]
    if problems:
        raise StageError(problems)
    rows, cols = mask.sizes["row"], mask.sizes["col"]
    geometry = RigGeometry.from_attrs(silhouettes.attrs, rows, cols)
    angles = mask["angle"].values
    max_vertices = 2 * len(angles)
    row_index = xr.DataArray(np.arange(rows), dims="row")
    packed = xr.apply_ufunc(
        _hull_kernel, mask.chunk({"angle": -1, "col": -1}), row_index,
        input_core_dims=[["angle", "col"], []], output_core_dims=[["vertex", "xy"]],
        dask="parallelized", output_dtypes=[np.float64],
        dask_gufunc_kwargs={"output_sizes": {"vertex": max_vertices + 2, "xy": 2}},
        kwargs={"angles": angles, "geometry": geometry, "max_vertices": max_vertices})
    vertices = packed.isel(vertex=slice(0, max_vertices))
    counts, empty, border, gapped = (packed.isel(vertex=max_vertices + i // 2, xy=i % 2, drop=True).astype(np.int64)
                                     for i in range(4))
    if geometry.camera_model == "orthographic":
        resolution = float(geometry.pixel_size) / 2
    else:
        resolution = float(geometry.camera_distance) / float(geometry.focal_length_px) / 2
    attrs = geometry_attrs(silhouettes.attrs) | {"selpath_kind": "hull", "hull_resolution": resolution,
                                                 "n_views": len(angles)}
    views = {"long_name": "views per slice"}
    return xr.Dataset({"vertices": vertices, "n_vertices": counts, "empty_views": empty.assign_attrs(views),
                       "border_views": border.assign_attrs(views), "gapped_views": gapped.assign_attrs(views)},
                      attrs=attrs | {"xy": "x, y in the object frame"})


def hull_polygons(hull: xr.Dataset) -> list[np.ndarray | None]:
    """The contour of each slice as an (n, 2) array of vertices, or None where the slice has none."""
    vertices, counts = hull["vertices"].values, hull["n_vertices"].values
    return [vertices[i, :n] if n >= 3 else None for i, n in enumerate(counts)]
