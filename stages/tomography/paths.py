"""Light-path alignment (§4.2.6): every camera pixel on the far side becomes one straight ray.

For each angle, slice (camera row) and pixel: the exit point ``p_c`` is where the pixel's ray first
meets the slice's contour (visual hull), the entry point ``p_l`` where the light's central ray does.
Under the shortest-path model the light ran straight from ``p_l`` to ``p_c``, so the pixel's total
absorption is the line integral along that chord. The chord is written in sinogram coordinates
(DESIGN §8): θ is the angle of its *normal* n = (cos θ, sin θ), X = p·n for any point p on it,
θ folded into [0°, 180°) by flipping the sign of X. (Eq. 6–7 as printed use a direction angle; the
convention here is the one the sinogram, the projector and scikit-image's ``radon`` agree on.)

Rays that cannot be aligned are dropped and counted, never guessed (``reason``):
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.geometry.rig import RIG_ATTRS, RigGeometry, geometry_attrs, to_object_xy
from selpath.geometry.shapes import convex_polygon
from selpath.pipeline.constraints import Fraction
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import ANGLE_UNITS, CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.tomography.hull import contours, slice_heights

_PIXELS = ("angle", "row", "col")
RAYS = CubeKind(
    name="rays",
    description="aligned light paths per pixel: sinogram coordinates and total absorption (§4.2.6)",
    variables={
        "theta": Variable(_PIXELS, description="normal angle of the ray, degree in [0, 180)", units="degree",
                          long_name="normal angle θ of the ray"),
        "x": Variable(_PIXELS, description="signed distance of the ray from the axis", units="{length}",
                      long_name="signed distance X of the ray from the axis"),
        "absorption": Variable(_PIXELS, description="total absorption; NaN where dropped", units="1",
                               long_name="total absorption A = log I_reference − log I_target"),
        "reason": Variable(_PIXELS, description="0: ray kept; else why it was dropped", units=None,
                           long_name="why the ray was dropped (0: kept)"),
    },
    coord_units={"angle": ANGLE_UNITS},
    attrs={"length_unit": RIG_ATTRS["length_unit"], "light_angle_deg": RIG_ATTRS["light_angle_deg"]},
)

#: why a pixel gave no ray (``reason`` variable; 0: a ray)
REASONS = {
    1: "camera ray misses the contour",
    2: "camera ray grazes the contour",
    3: "light ray misses the contour",
    4: "exit point is the entry point",
    5: "absorption is flagged or not finite",
    6: "slice has no contour",
}
__doc__ += "\n".join(f"``{k}``: {v}; " for k, v in REASONS.items())


def sinogram_coordinates(entry: np.ndarray, exit_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(θ in degrees in [0, 180), X) of the lines through ``entry`` and ``exit_`` (…, 2).

    >>> sinogram_coordinates(np.array([0.0, 1.0]), np.array([0.0, -1.0]))  # a vertical ray through 0
    (array(0.), array(0.))
    """
    d = exit_ - entry
    theta = np.arctan2(d[..., 0], -d[..., 1])  # d = (sin θ, −cos θ)  =>  n = (cos θ, sin θ)
    x = entry[..., 0] * np.cos(theta) + entry[..., 1] * np.sin(theta)
    flip = theta < 0
    theta = np.where(flip, theta + np.pi, theta)
    x = np.where(flip, -x, x)
    theta_deg = np.rad2deg(theta)
    wrap = theta_deg >= 180.0
    return np.where(wrap, theta_deg - 180.0, theta_deg), np.where(wrap, -x, x)


def _align_kernel(absorption, flags, angle, row, col, vertices, n_vertices, *, geometry: RigGeometry,
                  min_exit_cos: float):
    # apply_ufunc hands every input broadcastable over (angle, row, col), in that order (leading axes left out); the
    # camera's rays depend on (angle, col) only and the light's on the angle only, so each is traced once per row
    shape = np.broadcast_shapes(absorption.shape, flags.shape, angle.shape, row.shape, col.shape)
    vertices = np.broadcast_to(vertices, (*shape, *vertices.shape[-2:]))  # views, nothing copied
    absorption, flags = np.broadcast_to(absorption, shape), np.broadcast_to(flags, shape)
    phi = np.deg2rad(np.broadcast_to(angle, shape)[:, 0, 0])[:, None]
    cam_o, cam_d = geometry.camera.slice_rays(np.broadcast_to(col, shape)[0, 0, :])
    cam_d = cam_d / np.linalg.norm(cam_d, axis=1, keepdims=True)
    o, d = to_object_xy(cam_o[None], phi), to_object_xy(cam_d[None], phi)  # (angle, col, 2)
    beam_origin, beam_direction = geometry.beam()
    light_o, light_d = to_object_xy(beam_origin[:2], phi[:, 0]), to_object_xy(beam_direction[:2], phi[:, 0])
    out = np.full((*shape, 4), np.nan)
    reason = out[..., 3]
    reason[:] = 1  # the camera ray misses the contour, unless found otherwise below
    for j, count in enumerate(np.broadcast_to(n_vertices, shape)[0, :, 0]):
        if count < 3:
            reason[:, j] = 6
            continue
        polygon = convex_polygon(vertices[0, j, 0, :int(count)])
        light = polygon.interval(light_o, light_d)
        p_l = light_o + np.where(light.hit, light.t_in, 0.0)[:, None] * light_d  # (angle, 2)
        # only rays that meet the contour's bounding circle can meet the contour
        centre, radius = polygon.bounding_circle()
        rel = centre - o
        gap = np.abs(rel[..., 0] * d[..., 1] - rel[..., 1] * d[..., 0])
        near = np.nonzero(gap <= radius * (1 + 1e-9) + 1e-12)
        on, dn = o[near], d[near]
        seen = polygon.interval(on, dn)
        p_c = on + np.where(seen.hit, seen.t_in, 0.0)[:, None] * dn
        cos_exit = np.abs(np.einsum("ij,ij->i", dn, seen.normal_in))
        entry = p_l[near[0]]
        length = np.linalg.norm(p_c - entry, axis=1)
        a = absorption[near[0], j, near[1]]
        why = np.zeros(len(a))
        why[~np.isfinite(a) | (flags[near[0], j, near[1]] != 0)] = 5
        why[length <= 1e-9 * max(polygon.reach(), 1.0)] = 4
        why[~light.hit[near[0]]] = 3
        why[seen.hit & (cos_exit < min_exit_cos)] = 2
        why[~seen.hit] = 1
        ok = why == 0
        t, xx = sinogram_coordinates(entry[ok], p_c[ok])
        hit = (near[0][ok], j, near[1][ok])
        out[hit + (0,)], out[hit + (1,)], out[hit + (2,)] = t, xx, a[ok]
        reason[near[0], j, near[1]] = why
    return out


#: floor of ``ray_fraction`` (the demo keeps 82 % of its lit-row pixels)
RAY_FLOOR = 0.05


@stage("align_paths", kind=RAYS)
def align_paths(absorption: xr.Dataset, hull: xr.Dataset, /, *, min_exit_cos: Fraction = 0.02) -> xr.Dataset:
    """Turn every lit pixel into a ray (θ, X) with its total absorption, on the lit slices only (lazy).

    For a light sheet every camera row is a slice; for a narrow beam only the row(s) at the beam's
    height are (other rows see light that left the slice). Geometry comes from the hull's attrs.

    Parameters
    ----------
    absorption : xr.Dataset
        An ``absorption`` store (the ``absorption`` stage): ``absorption`` over (angle, row, col), angle the stage angle
        [degree]; ``flags`` where present (non-zero: the pixel is dropped). Its rows must be the hull's slices.
    hull : xr.Dataset
        A ``hull`` store (``visual_hull``) of the same capture: ``vertices``, ``n_vertices`` per slice; its attrs give
        the rig geometry the rays are traced in (camera, ``light_angle_deg``, ``light_kind``, ``beam_height``).
    min_exit_cos : float
        Rays leaving the contour at a smaller |cos| to its normal graze it and are dropped, in [0, 1]; 0: none [1].

    Returns
    -------
    xr.Dataset
        A ``rays`` cube: ``theta`` [degree], ``x`` [length unit] and ``absorption`` [1] over (angle, row, col): every
        lit pixel's ray, with ``reason`` (why a pixel gives none), lazily.

    References
    ----------
    Thesis §4.2.6 Light path alignment.
    """
    require_variables(absorption, ("absorption",), "align_paths")
    geometry = RigGeometry.from_attrs(hull.attrs, absorption.sizes["row"], absorption.sizes["col"],
                                      where="align_paths: hull")
    if "slice" in hull.dims and absorption.sizes["row"] != hull.sizes["slice"]:
        raise StageError(Problem(f"absorption has {absorption.sizes['row']} rows, the hull {hull.sizes['slice']} "
                                 "slices", fix="compute both from the same capture"))
    rows = geometry.lit_rows()
    if not len(rows):
        raise StageError(Problem("no camera row sees the beam's height", fix="check beam_height and the camera"))
    flags = absorption["flags"] if "flags" in absorption else xr.zeros_like(absorption["absorption"], dtype=np.int8)
    lit = {"row": ("row", rows), "z": slice_heights(geometry.camera, rows, hull.attrs["length_unit"], "row")}
    data = absorption["absorption"].isel(row=rows).assign_coords(lit)
    flags = flags.isel(row=rows).assign_coords(lit)
    # the slice each camera row sees; one chunk (small: the contours), not the hull's blocks of rows, which would
    # split every chunk of the absorption that spans them
    shell = contours(hull, data["row"], "align_paths").drop_vars("slice")
    shell = shell.chunk({"row": -1}) if shell.chunks else shell
    angle = data["angle"]
    row = data["row"]
    col = xr.DataArray(np.arange(data.sizes["col"]), dims="col")
    # one stacked output, split below (multi-output apply_ufunc graphs trip dask 2026.8 when computed
    # together with their dependents: "Missing dependency transpose-…")
    fields = xr.apply_ufunc(
        _align_kernel, data, flags, angle, row, col, shell["vertices"], shell["n_vertices"],
        input_core_dims=[[], [], [], [], [], ["vertex", "xy"], []], output_core_dims=[["field"]],
        dask="parallelized", output_dtypes=[np.float64], dask_gufunc_kwargs={"output_sizes": {"field": 4}},
        kwargs={"geometry": geometry, "min_exit_cos": min_exit_cos})
    theta, x, total = (fields.isel(field=i, drop=True) for i in range(3))
    total = total.astype(data.dtype)  # the kernel's stack is float64; the absorption keeps its own precision
    reason = fields.isel(field=3, drop=True).astype(np.int8)
    half_width = geometry.camera.view_half_width
    meanings = " ".join(f"{k}={v.replace(' ', '_')}" for k, v in REASONS.items())
    out = xr.Dataset(
        {"theta": theta, "x": x, "absorption": total,
         "reason": reason.assign_attrs(flag_values=list(REASONS), flag_meanings=meanings),
         "ray_fraction": usable_share(
             (reason == 0).sum() / np.maximum((reason != 1).sum(), 1), floor=RAY_FLOOR,
             what="lit-row pixels whose camera ray meets the contour that became rays",
             fix="see `reason`: flagged absorption (5) points at min_signal or the frames, no contour (6) or misses "
             "(3) at the silhouettes and the hull, grazing (2) at min_exit_cos")},
        attrs=geometry_attrs(hull.attrs) | {"x_extent": half_width, "min_exit_cos": min_exit_cos})
    out = RAYS.label(out)
    # (transpose only when needed: a no-op transpose layer trips dask 2026.8 when several outputs share it)
    return out if tuple(out["theta"].dims) == ("angle", "row", "col") else out.transpose("angle", "row", "col")
