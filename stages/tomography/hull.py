"""Silhouettes and the visual hull (§4.2.6): the object's convex contour per slice.

A silhouette is where the object hides the lit diffuse plane behind it in a backlit frame. Each
silhouette row bounds the slice seen by that camera row from two sides: the rays through the left and
right silhouette edges are tangent to the object, so each gives a half-plane containing it. The visual
hull of a slice is the intersection of these half-planes over every angle, a convex polygon
(``scipy.spatial.HalfspaceIntersection``). Camera rows are treated as slices through their x–y
projections, which is exact for the vertical prisms the rig measures (and for orthographic cameras):
the hull is indexed by ``slice``, whose coordinate is the camera row, as sinograms and reconstructions are.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.geometry.rig import RIG_ATTRS, Camera, RigGeometry, camera_attr_problems, geometry_attrs, to_object_xy
from selpath.pipeline.constraints import Index, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import ANGLE_UNITS, CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables, sorted_sweep

SILHOUETTES = CubeKind(
    name="silhouettes",
    description="object masks per angle from backlit frames (§4.2.6)",
    variables={"silhouette": Variable(("angle", "row", "col"), description="True where the object is", units=None,
                                      long_name="object mask")},
    coord_units={"angle": ANGLE_UNITS},
    attrs=RIG_ATTRS,  # visual_hull builds the rig's geometry from them
    attr_checks=(camera_attr_problems,),
)


def _views(what: str) -> Variable:
    return Variable(("slice",), False, units="1", long_name=f"views per slice {what}")


HULL = CubeKind(
    name="hull",
    description="visual hull: the object's convex contour per slice (coordinate: camera row), object frame",
    variables={
        "vertices": Variable(("slice", "vertex", "xy"), description="counter-clockwise, NaN-padded", units="{length}",
                             long_name="contour vertex (x, y), object frame"),
        "n_vertices": Variable(("slice",), description="vertices used per slice; 0: no contour", units="1",
                               long_name="vertices of the contour"),
        "empty_views": _views("with no silhouette"),
        "border_views": _views("whose silhouette touches the border"),
        "gapped_views": _views("whose silhouette has gaps"),
    },
    attrs={**RIG_ATTRS,  # align_paths and coverage build the rig's geometry from them
           "hull_resolution": "largest gap between the silhouette edge and the contour, length unit"},
    attr_checks=(camera_attr_problems,),
)


def _silhouette_kernel(backlit: np.ndarray, dark: np.ndarray, *, threshold: float | None, min_size: int
                       ) -> np.ndarray:
    from skimage.morphology import remove_small_objects  # scikit-image on computing, not on reading a workflow

    signal = backlit.astype(np.float64) - dark
    out = np.zeros(signal.shape, dtype=bool)
    for i, frame in enumerate(signal.reshape(-1, *signal.shape[-2:])):
        finite = np.isfinite(frame)
        level = threshold
        if level is None:
            levels = backlight_levels(frame[finite])
            level = np.inf if levels is None else 0.5 * (levels[1] + levels[2])
        mask = finite & (frame < level)  # the object blocks the lit plane
        if min_size > 0:
            mask = _fill_small_holes(remove_small_objects(mask, max_size=min_size), min_size)
        out.reshape(-1, *signal.shape[-2:])[i] = mask
    return out


def backlight_levels(values: np.ndarray) -> tuple[float, float, float] | None:
    """Otsu's level splitting a backlit frame's finite values into object and lit plane, and the two classes'
    means (object, plane); None where the values do not split (empty, constant)."""
    from skimage.filters import threshold_otsu

    if not values.size or np.ptp(values) <= 0:
        return None
    level = threshold_otsu(values)
    low, high = values[values < level], values[values >= level]
    if not low.size or not high.size:
        return None
    return float(level), float(low.mean()), float(high.mean())


def _fill_small_holes(mask: np.ndarray, max_size: int) -> np.ndarray:
    """Fill holes up to ``max_size`` pixels; background touching the image border is never a hole (a thin
    strip of lit plane beside the object must stay background)."""
    from skimage.measure import label
    from skimage.morphology import remove_small_holes

    border = np.zeros_like(mask)
    border[[0, -1], :] = border[:, [0, -1]] = True
    labels = label(~mask, connectivity=1)
    outside = np.unique(labels[border & ~mask])
    filled = remove_small_holes(mask, max_size=max_size)
    return filled & ~np.isin(labels, outside[outside > 0])


#: default ``min_size`` of the silhouettes, shared by :func:`object_masks` (and so by the absorption stage's background)
MIN_SIZE = 16


def object_masks(backlit: xr.DataArray, dark: xr.DataArray | None = None, *, threshold: float | None = None,
                 min_size: int = MIN_SIZE) -> xr.DataArray:
    """True where the object hides the lit plane in ``backlit`` (dims ``angle, row, col``), ``dark`` (``row, col``;
    None: 0) subtracted: the kernel of :func:`silhouettes`, lazy, one task per angle chunk.

    Without a ``threshold`` the level lies halfway between the means of the two classes Otsu's method splits
    (:func:`backlight_levels`), not at Otsu's level itself: skimage's Otsu returns the first histogram bin of a tie,
    which for a well separated backlight (no pixel between the classes) lies at the top of the object's noise,
    e.g. 0.4 counts above dark where the lit plane is at 2,000, and then splits that noise (the border rows of the
    calibration workflow's capture had 52 gapped silhouette rows, none with the midpoint)."""
    backlit = backlit.chunk({"row": -1, "col": -1})
    dark = xr.zeros_like(backlit.isel(angle=0, drop=True)) if dark is None else dark
    mask = xr.apply_ufunc(_silhouette_kernel, backlit, dark.chunk({"row": -1, "col": -1}),
                          input_core_dims=[["row", "col"], ["row", "col"]], output_core_dims=[["row", "col"]],
                          dask="parallelized", output_dtypes=[bool],
                          kwargs={"threshold": threshold, "min_size": min_size})
    return mask.transpose("angle", ..., "row", "col")


@stage("silhouettes", kind=SILHOUETTES)
def silhouettes(capture: xr.Dataset, /, *, threshold: Positive | None = None,
                min_size: Index = MIN_SIZE) -> xr.Dataset:
    """Binary object masks from the backlit frames, per angle (lazy, one task per angle chunk).

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` store (``acquire_tomography``): ``backlit`` [counts] over (angle, row, col), and
        ``dark`` (row, col) where present, subtracted here: give raw frames, not ``subtract_dark``'s output.
    threshold : float or None
        Counts above dark below which a pixel is object; None: per frame, halfway between the object's and the lit
        plane's levels (the means of Otsu's two classes) [counts].
    min_size : int
        Blobs and holes up to this many pixels are removed (noise, dust); 0: none [px].

    Returns
    -------
    xr.Dataset
        A ``silhouettes`` cube: ``silhouette`` (True where the object is) over (angle, row, col), lazily per angle
        chunk, and the usable share ``object_fraction``.

    References
    ----------
    Thesis §4.2.6 Light path alignment.
    """
    require_variables(capture, ("backlit",), "silhouettes")
    capture = sorted_sweep(capture, "angle", "silhouettes")
    mask = object_masks(capture["backlit"], capture["dark"] if "dark" in capture else None, threshold=threshold,
                        min_size=min_size)
    covered = mask.mean(("row", "col"))
    share = usable_share(((covered > 0) & (covered < 1)).mean(), floor=SILHOUETTE_FLOOR,
                         what="backlit frames with a silhouette (neither empty nor the whole frame)",
                         fix="check the backlit and dark frames (NaN, unlit, saturated) or set `threshold` [counts]")
    return SILHOUETTES.label(xr.Dataset({"silhouette": mask, "object_fraction": share},
                                        attrs=geometry_attrs(capture.attrs)))


#: floor of ``object_fraction``: a hull from fewer than half the views is not the object's
SILHOUETTE_FLOOR = 0.5


def silhouette_half_planes(mask_row: np.ndarray, angles_deg: np.ndarray, camera: Camera
                           ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Half-planes ``n·p ≤ h`` (object frame) from one silhouette row at every angle, and counts of
    views that give no constraint: empty, touching the image border (that side), non-convex (gaps).

    The ray through a silhouette's outer pixel edge is tangent to the object: the half-plane is bounded by it,
    on the object's side (:func:`tangent_half_planes`)."""
    mask_row = np.asarray(mask_row, bool)
    cols = mask_row.shape[-1]
    on = mask_row.any(axis=1)
    first = np.where(on, mask_row.argmax(axis=1), 0)
    last = np.where(on, cols - 1 - mask_row[:, ::-1].argmax(axis=1), cols - 1)
    counts = {"empty": int((~on).sum()), "border": int((on & (first == 0)).sum() + (on & (last == cols - 1)).sum()),
              "gaps": int((on & (mask_row.sum(axis=1) != last - first + 1)).sum())}
    # (a gapped row: the hull uses its outermost edges, its convex hull)
    left, right = camera.outer_edges(first.astype(float), last.astype(float))
    left = np.where(on & (first > 0), left, np.nan)
    right = np.where(on & (last < cols - 1), right, np.nan)
    normals, offsets = tangent_half_planes(left, right, angles_deg, camera)
    return normals, offsets, counts


def tangent_half_planes(left: np.ndarray, right: np.ndarray, angles_deg: np.ndarray, camera: Camera
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Half-planes ``n·p ≤ h`` (object frame) bounded by the rays through a slice's outer silhouette edges, sub-pixel
    columns per angle (NaN: that side gives none), in the order left, right of each angle in turn."""
    phi = np.deg2rad(np.asarray(angles_deg, float))
    edges = np.stack([left, right], axis=1)  # (angle, side)
    origins, directions = camera.slice_rays(np.nan_to_num(edges.ravel()))
    side = np.tile([-1.0, 1.0], len(phi))
    n_lab = side[:, None] * np.stack([directions[:, 1], -directions[:, 0]], 1)
    n_lab /= np.linalg.norm(n_lab, axis=1, keepdims=True)  # the ray's normal, away from the object
    offsets = np.einsum("ij,ij->i", n_lab, origins)
    normals = to_object_xy(n_lab, np.repeat(phi, 2))  # n·R(φ)p = (R(φ)ᵀ n)·p
    keep = np.isfinite(edges.ravel())
    return normals[keep], offsets[keep]


def intersect_half_planes(normals: np.ndarray, offsets: np.ndarray) -> np.ndarray | None:
    """Vertices (counter-clockwise) of ``{p : normals·p ≤ offsets}``, or None if empty or unbounded."""
    from scipy.optimize import linprog  # scipy here, not on import (~0.2 s of reading a workflow)
    from scipy.spatial import ConvexHull, HalfspaceIntersection

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


def _hull_kernel(masks: np.ndarray, *, angles: np.ndarray, camera: Camera, max_vertices: int) -> np.ndarray:
    # masks: (slice block, angle, col); one convex polygon per slice
    vertices = np.full((masks.shape[0], max_vertices, 2), np.nan)
    counts = np.zeros((4, masks.shape[0]), dtype=np.int64)  # vertices, empty, border, gapped views
    for k in range(masks.shape[0]):
        normals, offsets, views = silhouette_half_planes(masks[k], angles, camera)
        counts[1:, k] = views["empty"], views["border"], views["gaps"]
        polygon = intersect_half_planes(normals, offsets)
        if polygon is not None:
            n = min(len(polygon), max_vertices)
            vertices[k, :n], counts[0, k] = polygon[:n], n
    # one output: the counts ride in two extra "vertex" slots (see stages.tomography.paths on multi-output graphs)
    extra = counts.T.reshape(-1, 2, 2).astype(np.float64)
    return np.concatenate([vertices, extra], axis=1)


#: bytes of silhouette rows (all angles, all columns) one hull task reads: a volume's capture is never one task
HULL_CHUNK_BYTES = 64 * 2**20


def hull_rows_per_chunk(n_angles: int, cols: int) -> int:
    """Camera rows per hull task: as many as fit in :data:`HULL_CHUNK_BYTES` of boolean silhouettes, at least one."""
    return max(1, HULL_CHUNK_BYTES // max(n_angles * cols, 1))


@stage("visual_hull", kind=HULL)
def visual_hull(silhouettes: xr.Dataset, /) -> xr.Dataset:
    """The convex contour of every slice from the silhouettes of all angles: dim ``slice``, whose coordinate is
    the camera row the slice is seen in.

    Lazy, one task per block of rows (at most 64 MiB of silhouettes); each needs every angle of its rows.
    Rows where the object is absent or not bounded by the views get ``n_vertices = 0``; the variables
    ``empty_views``, ``border_views`` and ``gapped_views`` count, per slice, the views that constrained
    nothing (no object in the row; the object touching the image border, per side) or were not one run
    of pixels (a non-convex object or noise: the hull then uses the outermost edges).
    The contour is exact to ``hull_resolution`` (half a pixel at the rotation axis) for convex objects.

    Parameters
    ----------
    silhouettes : xr.Dataset
        A ``silhouettes`` store (the ``silhouettes`` stage): ``silhouette`` over (angle, row, col), angle the stage
        angle [degree]; attrs: the rig geometry (``camera_model`` and its camera's, ``light_angle_deg``).

    Returns
    -------
    xr.Dataset
        A ``hull`` cube: per slice the contour's ``vertices`` over (slice, vertex, xy) (counter-clockwise, object frame)
        [length unit] and ``n_vertices``, with the views that gave no constraint (``empty_views``, ``border_views``,
        ``gapped_views``).

    References
    ----------
    Thesis §4.2.6 Light path alignment.
    """
    require_variables(silhouettes, ("silhouette",), "visual_hull")
    mask = silhouettes["silhouette"]
    rows, cols = mask.sizes["row"], mask.sizes["col"]
    camera = RigGeometry.from_attrs(silhouettes.attrs, rows, cols, where="visual_hull: silhouettes").camera
    angles = mask["angle"].values
    max_vertices = 2 * len(angles)
    slices = mask.rename(row="slice").assign_coords(slice=("slice", np.arange(rows)))  # a camera row sees a slice
    packed = xr.apply_ufunc(
        _hull_kernel, slices.chunk({"angle": -1, "col": -1, "slice": hull_rows_per_chunk(len(angles), cols)}),
        input_core_dims=[["angle", "col"]], output_core_dims=[["vertex", "xy"]],
        dask="parallelized", output_dtypes=[np.float64],
        dask_gufunc_kwargs={"output_sizes": {"vertex": max_vertices + 2, "xy": 2}},
        kwargs={"angles": angles, "camera": camera, "max_vertices": max_vertices})
    vertices = packed.isel(vertex=slice(0, max_vertices))
    counts, empty, border, gapped = (packed.isel(vertex=max_vertices + i // 2, xy=i % 2, drop=True).astype(np.int64)
                                     for i in range(4))
    attrs = geometry_attrs(silhouettes.attrs) | {"hull_resolution": camera.axis_pixel_size / 2,
                                                 "n_views": len(angles)}
    hull = xr.Dataset({"vertices": vertices, "n_vertices": counts, "empty_views": empty.drop_attrs(deep=False),
                       "border_views": border.drop_attrs(deep=False), "gapped_views": gapped.drop_attrs(deep=False)},
                      attrs=attrs | {"xy": "x, y in the object frame"})
    # each slice's height (assigned after the chunked kernel, so it stays a numpy coordinate)
    hull = hull.assign_coords(z=slice_heights(camera, np.arange(rows), silhouettes.attrs["length_unit"]))
    return HULL.label(hull)


def slice_heights(camera: Camera, rows: np.ndarray, unit: str, dim: str = "slice") -> tuple[str, np.ndarray, dict]:
    """The ``z`` coordinate (along ``dim``) of slices seen in camera ``rows``: the height [``unit``, the rig's
    length unit] where each row sees the rotation axis (:meth:`~selpath.geometry.rig.Camera.axis_height`); z grows
    upward, so it falls as the row grows."""
    return (dim, camera.axis_height(rows), {"units": unit, "long_name": "slice height z at the rotation axis"})


def hull_polygons(hull: xr.Dataset) -> list[np.ndarray | None]:
    """The contour of each slice as an (n, 2) array of vertices, or None where the slice has none."""
    vertices, counts = hull["vertices"].values, hull["n_vertices"].values
    return [vertices[i, :n] if n >= 3 else None for i, n in enumerate(counts)]


def contours(hull: xr.Dataset, slices: xr.DataArray, stage_name: str) -> xr.Dataset:
    """``vertices`` and ``n_vertices`` of the hull at ``slices`` (camera rows), indexed like ``slices``.

    Raises a StageError naming the slices the hull lacks, or saying how to read a hull of an earlier layout.
    """
    if "slice" not in hull.dims or "slice" not in hull.indexes:
        fix = ("open its store with selpath.open_store, which migrates hulls of formats 1-2 (dim 'row')"
               if "row" in hull.dims else "compute it with visual_hull")
        raise StageError(Problem(f"{stage_name}: the hull has no slice coordinate (dims {tuple(hull.dims)})",
                                 fix=fix))
    missing = sorted(set(np.asarray(slices).tolist()) - set(hull["slice"].values.tolist()))
    if missing:
        raise StageError(Problem(f"{stage_name}: slices {missing[:5]} are not in the hull ({hull.sizes['slice']} "
                                 "slices)", fix="compute both from the same capture"))
    # z is the caller's to carry: the hull's and the indexer's would be compared (a compute where either is chunked)
    return hull[["vertices", "n_vertices"]].drop_vars("z", errors="ignore").sel(
        slice=slices.drop_vars("z", errors="ignore") if isinstance(slices, xr.DataArray) else slices)
