"""Geometric calibration of the tomography rig from its own capture (§4.2.5–4.2.6): where the rotation axis is
seen, and the light's angle θ_l. No calibration target is needed; both come from consistency the rig's geometry
must show, so a wrong value shows as a contradiction in the data.

**Rotation-axis column** (``axis_column``, the principal point's column: the camera is aimed at the axis,
:mod:`selpath.geometry.rig`). Each backlit silhouette's outer edge in a camera row is a ray tangent to the object's
slice, i.e. a sample ``h = H(ψ)`` of the slice's support function H (the largest ``n(ψ)·p`` over the slice, n the
tangent's outward normal in the object frame). Over a turn the left edges and the right edges sample the same H;
seen from a wrong axis column they disagree by twice the error (in length at the axis). The fit minimises, per
row, the left samples minus the right samples interpolated at the same ψ (and the reverse), as TomoPy's
``find_center`` compares opposite projections, but exact under perspective and for any convex object. Edges are
sub-pixel by area coverage (:func:`silhouette_edges`; on a sensor that renders pixels all-or-nothing that is the
pixel's edge, and an object off the axis dithers it over the turn).

**Light angle θ_l** (``light_angle_deg``). The beam passes the axis (the rig points light and camera at it,
§4.2.5, Fig. 13), so at stage angle φ it enters the slice's contour at the point of polar angle 90° − θ_l − φ
(object frame). A pixel at (φ, c) sees the chord from that entry point to its exit point p_c; the same chord run
backwards (entry p_c, exit the first entry point) is seen at the stage angle φ' = 90° − θ_l − arg p_c, in the
column that sees the first entry point. Under the shortest-path model both carry the same absorption. With a
wrong θ_l the pairs are wrong and disagree wherever the absorption varies (an inclusion); the fit minimises the
absorption at (φ, c) minus the absorption interpolated (bilinearly in angle and column) at (φ', c'). A profile
of the mean squared disagreement over ``stated ± search_deg`` finds the basin; least squares refines it.

Both fits are least squares (Levenberg–Marquardt, scipy: the residuals are cheap numpy, a JAX trace cost seconds
per fit) with the standard uncertainty s²(JᵀJ)⁻¹, s² the residual variance. Neighbouring residuals are not
independent, so each uncertainty adds what the data cannot average away: the axis's is inflated by √(rows used)
(a prism's rows repeat one silhouette) and floored by the edge quantisation, 1/√(12·n) px for n distinct sub-pixel
edge positions (an object centred on the axis has edges that never move: n = 1, 0.29 px); θ_l's is inflated by √8
(one absorption sample enters about four bilinear pairs, each pair twice), and adds, in quadrature, the spread of
θ_l fitted on each quarter turn's pairs (the hull's error varies with direction) and how far θ_l moves when the axis
moves by its uncertainty. On the test rigs the errors lie within 1.5 of these uncertainties.

Assumed and not estimated: the focal length (or pixel size), the camera distance, the beam's height, and that the
beam passes the axis (a beam offset from the axis is not in the rig model, DESIGN §8).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import xarray as xr
from scipy.ndimage import map_coordinates
from scipy.optimize import least_squares

from selpath.geometry.rig import RIG_ATTRS, Camera, RigGeometry, camera_attr_problems, geometry_attrs, to_object_xy
from selpath.geometry.shapes import convex_polygon
from selpath.pipeline.constraints import Count, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import ANGLE_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables, sorted_sweep
from selpath.stages.tomography.acquire import TOMOGRAPHY_CAPTURE
from selpath.stages.tomography.calibrate import absorption as absorption_stage
from selpath.stages.tomography.hull import backlight_levels, intersect_half_planes, tangent_half_planes


def _fitted(units: str, long_name: str, description: str = "") -> Variable:
    return Variable((), False, description, units=units, long_name=long_name)


RIG_CALIBRATION = CubeKind(
    name="rig_calibration",
    description="the tomography rig's axis column and light angle θ_l estimated from a capture (calibrate_rig); its "
    "attrs are the corrected geometry",
    variables={
        "axis_column": _fitted("px", "column the rotation axis is seen in", "principal point's column: where the axis "
                               "is seen"),
        "axis_column_std": _fitted("px", "standard uncertainty of axis_column", "standard uncertainty"),
        "axis_column_stated": _fitted("px", "axis column stated"),
        "axis_residual_rms": _fitted("px", "RMS disagreement of left and right silhouette tangents, pixels at the "
                                     "axis"),
        "light_angle": _fitted("degree", "light angle θ_l", "θ_l"),
        "light_angle_std": _fitted("degree", "standard uncertainty of θ_l", "standard uncertainty"),
        "contour_offset": _fitted("px", "outward offset of the lit slice's contour fitted with θ_l, pixels at the "
                                  "axis"),
        "contour_offset_std": _fitted("px", "standard uncertainty of it"),
        "light_angle_stated": _fitted("degree", "θ_l stated"),
        "light_residual_rms": _fitted("1", "RMS absorption disagreement of reversed chords"),
        "light_cost": Variable(("light_angle_trial",), False, "θ_l profile", units="1",
                               long_name="mean squared disagreement of reversed chords"),
        "light_pairs": Variable(("light_angle_trial",), False, units="1", long_name="pairs compared"),
    },
    coord_units={"light_angle_trial": ANGLE_UNITS},
    attrs={**RIG_ATTRS, "stated_principal_point_px": "(col, row) principal point the capture stated, px",
           "stated_light_angle_deg": "θ_l the capture stated, degree"},
    attr_checks=(camera_attr_problems,),
)

#: sweeps must cover a full turn (within this, degree) for the axis and light fits to pair opposite views
FULL_TURN_TOLERANCE = 1e-6
#: the θ_l profile's median must lie this far above its minimum (noise alone: about 3 %; the test rig's stick: 10×)
MIN_PROFILE_DEPTH = 0.25


# -- silhouette edges ---------------------------------------------------------------------------------------
def silhouette_edges(signal: np.ndarray) -> np.ndarray:
    """Sub-pixel outer edges (left, right) of the silhouette in each row of backlit frames, NaN where unusable:
    (angle, row, 2).

    ``signal``: backlit counts above dark, (angle, row, col). Per frame the object's and the lit plane's levels are
    the means of Otsu's two classes (:func:`selpath.stages.tomography.hull.backlight_levels`); a pixel is object below
    halfway between them. A pixel's signal between the two levels is the share of it the object hides (area
    coverage), so the edge lies that share inside the outermost object pixel and its lit neighbour together: the
    pixel's edge on an all-or-nothing sensor, sub-pixel on a real one. A row whose object is absent, is not one run
    of pixels, or touches that side of the image gives NaN.
    """
    signal = np.asarray(signal, np.float64)
    n_angle, n_row, n_col = signal.shape
    edges = np.full((n_angle, n_row, 2), np.nan)
    cols, rows = np.arange(n_col), np.arange(n_row)
    for a, frame in enumerate(signal):
        levels = backlight_levels(frame[np.isfinite(frame)])
        if levels is None:
            continue
        _, dark, lit = levels
        inside = np.isfinite(frame) & (frame < 0.5 * (dark + lit))
        any_on = inside.any(axis=1)
        first = np.where(any_on, inside.argmax(axis=1), -1)
        last = np.where(any_on, n_col - 1 - inside[:, ::-1].argmax(axis=1), -1)
        run = (cols[None, :] >= first[:, None]) & (cols[None, :] <= last[:, None])
        one_run = any_on & (inside == run).all(axis=1)
        cover = np.clip((lit - frame) / (lit - dark), 0.0, 1.0)  # share of each pixel the object hides
        r = rows[one_run & (first > 0)]
        edges[a, r, 0] = first[r] + 0.5 - cover[r, first[r] - 1] - cover[r, first[r]]
        r = rows[one_run & (last < n_col - 1)]
        edges[a, r, 1] = last[r] - 0.5 + cover[r, last[r]] + cover[r, last[r] + 1]
    return edges


# -- the rotation axis --------------------------------------------------------------------------------------
def _with_axis(camera: Camera, column: float) -> Camera:
    """``camera`` with the rotation axis (the principal point's column) seen at ``column``."""
    return dataclasses.replace(camera, principal_point_px=(float(column), camera.centre_px[1]))


def _support_samples(edges, angles_deg, side: float, camera: Camera):
    """(ψ, h) of the finite sub-pixel edges of one side (−1 left, +1 right) over the angles: each tangent's outward
    normal angle ψ in the object frame and its offset h = H(ψ)
    (:func:`selpath.stages.tomography.hull.tangent_half_planes`)."""
    none = np.full_like(edges, np.nan)
    normals, offsets = tangent_half_planes(*((edges, none) if side < 0 else (none, edges)), angles_deg, camera)
    return np.arctan2(normals[:, 1], normals[:, 0]), offsets


def _axis_residuals(column, rows_data, angles_deg, camera: Camera):
    camera = _with_axis(camera, column)
    pieces = []
    for left, right, keep_l, keep_r in rows_data:
        psi_l, h_l = _support_samples(left, angles_deg, -1.0, camera)
        psi_r, h_r = _support_samples(right, angles_deg, 1.0, camera)
        pieces.append((h_l - np.interp(psi_l, psi_r, h_r, period=2 * np.pi))[keep_l])
        pieces.append((h_r - np.interp(psi_r, psi_l, h_l, period=2 * np.pi))[keep_r])
    return np.concatenate(pieces)


def _near(psi: np.ndarray, others: np.ndarray, gap: float) -> np.ndarray:
    """Whether each angle ψ has a sample of ``others`` within ``gap`` on both sides (periodic)."""
    grid = np.sort(np.mod(others, 2 * np.pi))
    x = np.mod(psi, 2 * np.pi)
    k = np.searchsorted(grid, x)
    below = np.where(k > 0, x - grid[np.maximum(k - 1, 0)], x - (grid[-1] - 2 * np.pi))
    above = np.where(k < len(grid), grid[np.minimum(k, len(grid) - 1)] - x, grid[0] + 2 * np.pi - x)
    return (below <= gap) & (above <= gap)


@dataclass(frozen=True)
class Fit:
    """A least-squares fit: values, standard uncertainties, residual RMS, residuals used."""

    value: np.ndarray
    std: np.ndarray
    rms: float
    count: int
    converged: bool


def _least_squares(residuals, start, inflation: float, step: float = 1e-4) -> Fit:
    """Levenberg–Marquardt (scipy's MINPACK, central differences of ``step``) from ``start``; standard
    uncertainties s²(JᵀJ)⁻¹ × ``inflation``², s² the residual variance."""
    x0 = np.atleast_1d(np.asarray(start, float))
    solution = least_squares(residuals, x0, method="lm", jac="3-point", diff_step=step, xtol=1e-12, ftol=1e-12)
    r, jac = solution.fun, solution.jac
    s2 = float(r @ r) / max(len(r) - len(x0), 1)
    cov = s2 * np.linalg.pinv(jac.T @ jac)
    std = np.sqrt(np.clip(np.diag(cov), 0, None)) * inflation
    return Fit(solution.x, std, float(np.sqrt(np.mean(r**2))) if len(r) else np.nan, len(r), bool(solution.success))


def fit_axis_column(edges: np.ndarray, angles_deg: np.ndarray, camera: Camera) -> Fit:
    """The axis column from sub-pixel silhouette edges (angle, row, left/right) over a full turn, starting at
    ``camera``'s; the rest of ``camera`` is taken as it is."""
    gap = 2.5 * np.deg2rad(360.0 / len(angles_deg))
    start = camera.centre_px[0]
    rows_data = []
    for r in range(edges.shape[1]):
        left, right = edges[:, r, 0], edges[:, r, 1]
        if np.isfinite(left).sum() < 8 or np.isfinite(right).sum() < 8:
            continue
        psi_l, _ = _support_samples(left, angles_deg, -1.0, camera)
        psi_r, _ = _support_samples(right, angles_deg, 1.0, camera)
        keep_l, keep_r = _near(psi_l, psi_r, gap), _near(psi_r, psi_l, gap)
        if keep_l.sum() + keep_r.sum() < 8:
            continue
        rows_data.append((left, right, keep_l, keep_r))
    if not rows_data:
        raise StageError(Problem("calibrate_rig: no camera row has silhouette edges on both sides over the turn",
                                 fix="the object must stay inside the image in the backlit frames (none touching "
                                 "its sides) over a full turn; check the backlit and dark frames"))
    fit = _least_squares(lambda p: _axis_residuals(p[0], rows_data, angles_deg, camera), start,
                         np.sqrt(len(rows_data)))
    # edges that never move (an object centred on the axis) keep their quantisation error (±½ px on an
    # all-or-nothing sensor) however many views there are: count the distinct sub-pixel edge positions per side
    distinct = min(len(np.unique(np.round(side[np.isfinite(side)] * 20) / 20)) for d in rows_data for side in d[:2])
    floor = 1.0 / np.sqrt(12.0 * distinct)
    return Fit(fit.value, np.hypot(fit.std, floor), fit.rms, fit.count, fit.converged)


# -- the light angle ----------------------------------------------------------------------------------------
def _edge_at(corners, beta):
    """Index of the contour edge a ray from the axis at polar angle β crosses (``corners``: the vertices' polar
    angles, increasing from the first vertex, which has the smallest; edge k runs from vertex k to k + 1)."""
    k = np.searchsorted(corners, np.mod(beta - corners[0], 2 * np.pi) + corners[0], side="right") - 1
    return np.mod(k, len(corners))


def _radius(normals, offsets, corners, beta):
    """Distance from the axis to a convex polygon (containing the axis) along polar angles β [rad]."""
    k = _edge_at(corners, beta)
    n = normals[k]
    return offsets[k] / (n[..., 0] * np.cos(beta) + n[..., 1] * np.sin(beta))


@dataclass(frozen=True)
class _LightData:
    """One slice's pairs for the θ_l fit (angles in radians, everything float64)."""

    table: np.ndarray  # (angle + 1, col) absorption, the first angle repeated at the end; NaN → 0
    valid: np.ndarray  # (angle + 1, col) bool
    phi: np.ndarray  # (P,) stage angle of each source pixel
    exit: np.ndarray  # (P, 2) its exit point on the contour (object frame)
    ray: np.ndarray  # (P, 2) the pixel's unit ray direction (object frame)
    ray_cos: np.ndarray  # (P,) n·ray at the exit point (n: that edge's outward normal; negative)
    value: np.ndarray  # (P,) its absorption
    normals: np.ndarray  # (E, 2) outward normals of the contour's edges, edge k from vertex k to k + 1
    offsets: np.ndarray  # (E,) n·p on edge k
    corners: np.ndarray  # (E,) polar angles of the vertices, increasing (vertex 0 has the smallest)
    phi0: float
    step: float


def _conjugates(params, data: _LightData, camera: Camera):
    """Fractional (angle index, column) where each pair's reversed chord is seen, and that stage angle φ' [rad].

    ``params``: θ_l [degree] and the contour's outward offset [pixels at the axis]: the hull of binary silhouettes
    is off by up to half a pixel, and the pairs are sensitive to it (0.1 mm moves θ_l by 0.4° on the test rig)."""
    theta, offset = np.deg2rad(params[0]), params[1] * camera.axis_pixel_size
    light = np.pi / 2 - theta
    exit_ = data.exit + data.ray * (offset / data.ray_cos)[..., None]  # the moved edge meets the pixel's ray
    phi_c = light - np.arctan2(exit_[..., 1], exit_[..., 0])  # stage angle whose beam enters at the exit point
    beta = light - data.phi  # polar angle of the first chord's entry point (object frame)
    radius = _radius(data.normals, data.offsets + offset, data.corners, beta)
    entry = radius[..., None] * np.stack([np.cos(beta), np.sin(beta)], -1)
    q = to_object_xy(entry, -phi_c)  # in the lab at φ'
    _, col = camera.project(np.column_stack([q, np.zeros(len(q))]))
    index = np.mod(phi_c - data.phi0, 2 * np.pi) / data.step
    return index, col, phi_c


def _pair_mask(params, data: _LightData, camera: Camera, min_exit_cos: float = 0.05) -> np.ndarray:
    """Pairs whose reversed chord is seen: its exit faces the camera (not grazing), on the sensor, with four valid
    neighbours in (angle, column)."""
    index, col, phi_c = _conjugates(params, data, camera)
    n_angle, n_col = data.table.shape[0] - 1, data.table.shape[1]
    i0, j0 = np.floor(index).astype(int), np.floor(col).astype(int)
    on = np.isfinite(col) & (j0 >= 0) & (j0 < n_col - 1) & (i0 >= 0) & (i0 < n_angle)
    i0, j0 = np.clip(i0, 0, n_angle - 1), np.clip(j0, 0, n_col - 2)
    ok = on & data.valid[i0, j0] & data.valid[i0, j0 + 1] & data.valid[i0 + 1, j0] & data.valid[i0 + 1, j0 + 1]
    # the outward normal where the reversed chord leaves (the edge the first chord's entry lies on), in the lab,
    # against the ray of the pixel that sees it (as align_paths judges grazing exits)
    normal = to_object_xy(data.normals[_edge_at(data.corners, np.pi / 2 - np.deg2rad(params[0]) - data.phi)], -phi_c)
    _, ray = camera.slice_rays(np.nan_to_num(col))
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return ok & (-np.einsum("ij,ij->i", normal, ray) >= min_exit_cos)


def _light_residuals(params, slices) -> np.ndarray:
    """Absorption of each pair minus its reversed chord's; ``slices``: (pairs, camera) of each lit slice."""
    pieces = []
    for d, camera in slices:
        index, col, _ = _conjugates(params, d, camera)
        pieces.append(d.value - map_coordinates(d.table, [index, col], order=1, mode="nearest"))  # bilinear
    return np.concatenate(pieces)


def _seen_pairs(params, slices, camera: Camera, keep=None) -> list[tuple[_LightData, Camera]]:
    """Each slice's pairs whose reversed chord is seen at ``params`` (:func:`_pair_mask`), and where ``keep`` (a
    function of the pairs' stage angles) says so: the residuals then compute only what they use."""
    out = []
    for d in slices:
        mask = _pair_mask(params, d, camera) & (keep(d.phi - d.phi0) if keep is not None else True)
        out.append((dataclasses.replace(d, phi=d.phi[mask], exit=d.exit[mask], ray=d.ray[mask],
                                        ray_cos=d.ray_cos[mask], value=d.value[mask]), camera))
    return out


def light_slice_data(absorption: np.ndarray, valid: np.ndarray, angles_deg: np.ndarray, polygon_vertices: np.ndarray,
                     camera: Camera, min_exit_cos: float = 0.05) -> _LightData | None:
    """The pairs of one lit slice: its absorption (angle, col) over a full turn of equal steps, its contour."""
    vertices = np.asarray(polygon_vertices, float)
    corners = np.arctan2(vertices[:, 1], vertices[:, 0])
    start = int(np.argmin(corners))  # counter-clockwise from the smallest polar angle (see _edge_at)
    polygon = convex_polygon(np.roll(vertices, -start, axis=0))
    if not polygon.contains(np.zeros((1, 2)))[0]:
        raise StageError(Problem("calibrate_rig: the rotation axis is outside the object's contour in the lit "
                                 "slice; the light angle is calibrated on an object the beam's line (through the "
                                 "axis) enters", fix="centre the object on the stage, or give light_angle: false"))
    n_angle, n_col = absorption.shape
    phi = np.repeat(np.deg2rad(np.asarray(angles_deg, float)), n_col)
    origin, direction = camera.slice_rays(np.tile(np.arange(n_col, dtype=float), n_angle))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    o_obj, d_obj = to_object_xy(origin, phi), to_object_xy(direction, phi)
    seen = polygon.interval(o_obj, d_obj)
    p_c = o_obj + np.where(seen.hit, seen.t_in, 0.0)[:, None] * d_obj
    ray_cos = np.einsum("ij,ij->i", d_obj, seen.normal_in)
    use = seen.hit & (np.abs(ray_cos) >= min_exit_cos) & valid.ravel()
    if use.sum() < 16:
        return None
    normals, offsets = polygon.half_planes
    table = np.where(valid, absorption, 0.0)
    return _LightData(np.concatenate([table, table[:1]]), np.concatenate([valid, valid[:1]]),
                      phi[use], p_c[use], d_obj[use], ray_cos[use], absorption.ravel()[use],
                      normals, offsets, np.roll(corners, -start), float(phi[0]), 2 * np.pi / n_angle)


def light_cost(params, slices, camera: Camera) -> tuple[float, int]:
    """Mean squared disagreement of reversed chords at (θ_l, contour offset), and the pairs it is taken over."""
    r = _light_residuals(params, _seen_pairs(params, slices, camera))
    return (float(np.mean(r**2)) if len(r) else np.nan), len(r)


def fit_light_angle(slices, camera: Camera, stated: float, search_deg: float, step_deg: float
                    ) -> tuple[Fit, np.ndarray, np.ndarray, np.ndarray]:
    """θ_l and the contour's offset: a profile of :func:`light_cost` over ``stated ± search_deg`` (offset 0), then
    least squares in both from the profile's minimum (twice, the pairs chosen again at the first answer).

    ``camera`` sees the axis where the slices were built. Returns the fit (values and uncertainties of θ_l
    [degree] and the offset [pixels at the axis]) and the profile (trial angles, mean squared disagreement,
    pairs)."""
    trials = stated + np.arange(-search_deg, search_deg + step_deg / 2, step_deg)
    trials = trials[(trials >= 0) & (trials <= 180)]
    profile = np.array([light_cost((t, 0.0), slices, camera) for t in trials])
    cost, pairs = profile[:, 0], profile[:, 1].astype(int)
    enough = pairs >= max(16, 0.25 * pairs.max())
    if not enough.any() or not np.isfinite(cost[enough]).any():
        raise StageError(Problem("calibrate_rig: no reversed chord is seen at any trial light angle",
                                 fix="capture a full turn with the beam's far side in view, or give light_angle: false"))
    params = np.array([trials[int(np.nanargmin(np.where(enough, cost, np.nan)))], 0.0])
    for _ in range(2):
        seen = _seen_pairs(params, slices, camera)
        fit = _least_squares(lambda p: _light_residuals(p, seen), params, np.sqrt(8.0))
        params = fit.value
    # (the √8: one absorption sample enters about four pairs through the bilinear weights, and each pair twice)
    # The contour's error varies with direction (each part of the hull is cut by other views' edges); the pairs of
    # each quarter turn see another part of it. Their fits' spread, over √4, is the systematic part of θ_l's error.
    quarters = []
    for q in range(4):
        part = _seen_pairs(params, slices, camera,
                           keep=lambda phi, q=q: np.floor(np.mod(phi, 2 * np.pi) / (np.pi / 2)) == q)
        if sum(len(d.value) for d, _ in part) >= 16:
            quarters.append(_least_squares(lambda p, part=part: _light_residuals(p, part), params, 1.0).value)
    if len(quarters) >= 2:
        spread = np.std(quarters, axis=0, ddof=1) / np.sqrt(len(quarters))
        fit = Fit(fit.value, np.hypot(fit.std, spread), fit.rms, fit.count, fit.converged)
    return fit, trials, cost, pairs


# -- the stages ---------------------------------------------------------------------------------------------
def _full_turn(angles: np.ndarray, what: str) -> None:
    steps = np.diff(angles)
    if len(angles) < 8 or not np.allclose(steps, steps[0], rtol=0, atol=1e-6) or \
            abs(len(angles) * steps[0] - 360.0) > FULL_TURN_TOLERANCE * 360 + 1e-6:
        raise StageError(Problem(f"calibrate_rig: {what} needs a full turn in equal steps; the capture's angles "
                                 f"are {angles[:3].round(3).tolist()} … {angles[-2:].round(3).tolist()} "
                                 f"({len(angles)} views)", fix="capture 0 ≤ φ < 360° in equal steps"))


def _spread(n: int, count: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(count, n)).round().astype(int))


@stage("calibrate_rig", kind=RIG_CALIBRATION)
def calibrate_rig(capture: xr.Dataset, /, *, axis: bool = True, light_angle: bool = True,
                  search_deg: Positive = 5.0, search_step_deg: Positive = 0.25, rows: Count = 32,
                  min_signal: NonNegative = 1.0) -> xr.Dataset:
    """Estimate the rotation axis's column and the light angle θ_l from a capture, with uncertainties.

    The result holds the estimates, their standard uncertainties, the values the capture stated and the fit
    residuals (attrs, and as 0-d variables), the θ_l profile (``light_cost`` over ``light_angle_trial``), and the
    corrected rig geometry in its attrs; ``apply_rig_calibration`` writes it into a capture's attrs. See the
    module's docstring for the method and its assumptions.

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` store over a full turn in equal steps: ``backlit`` (and ``dark``) frames for the
        axis, ``target`` and ``reference`` for θ_l [counts]; attrs: the rig geometry as stated.
    axis : bool
        Estimate the axis column (else keep the stated principal point).
    light_angle : bool
        Estimate θ_l (needs an object with absorbing structure, the axis inside it, and the beam's far side seen).
    search_deg : float
        Half-width of the θ_l profile around the stated value [degree].
    search_step_deg : float
        Step of that profile [degree].
    rows : int
        Camera rows (spread over the object's height) whose silhouettes fit the axis; the lit rows fit θ_l.
    min_signal : float
        Counts above dark below which a pixel's absorption is not used for θ_l [counts].
    """
    if not axis and not light_angle:
        raise StageError(Problem("calibrate_rig: nothing to calibrate", fix="set axis or light_angle to true"))
    capture = sorted_sweep(capture, "angle", "calibrate_rig")
    n_rows, n_cols = capture.sizes["row"], capture.sizes["col"]
    stated = RigGeometry.from_attrs(capture.attrs, n_rows, n_cols, where="calibrate_rig: capture")
    angles = capture["angle"].values.astype(float)
    _full_turn(angles, "calibration")
    require_variables(capture, ("backlit",), "calibrate_rig")
    edges = _all_edges(capture)  # one pass over the backlit frames serves both fits
    geometry, axis_fit = stated, None
    if axis:
        candidates = np.flatnonzero(np.isfinite(edges).any(axis=(0, 2)))
        if not len(candidates):
            raise StageError(Problem("calibrate_rig: no backlit frame shows the object inside the image",
                                     fix="check the backlit and dark frames"))
        axis_fit = fit_axis_column(edges[:, candidates[_spread(len(candidates), rows)]], angles, stated.camera)
        geometry = dataclasses.replace(stated, camera=_with_axis(stated.camera, axis_fit.value[0]))
    light_fit, profile = None, None
    if light_angle:
        require_variables(capture, ("target", "reference"), "calibrate_rig")
        lit = geometry.lit_rows()
        lit = lit[_spread(len(lit), max(1, min(rows, 8)))]
        flags_ok = absorption_stage(capture.isel(row=lit), min_signal=min_signal)
        values = flags_ok["absorption"].transpose("angle", "row", "col").values.astype(float)
        valid = (flags_ok["flags"].transpose("angle", "row", "col").values == 0) & np.isfinite(values)

        def lit_slices(camera: Camera) -> list[_LightData]:
            out = []
            for k, row in enumerate(lit):
                polygon = intersect_half_planes(*tangent_half_planes(edges[:, row, 0], edges[:, row, 1], angles,
                                                                     camera))
                data = None if polygon is None else light_slice_data(values[:, k], valid[:, k], angles, polygon,
                                                                     camera)
                if data is not None:
                    out.append(data)
            if not out:
                raise StageError(Problem("calibrate_rig: no lit slice has a contour and valid absorption",
                                         fix="check the target, reference and backlit frames, or give "
                                         "light_angle: false"))
            return out

        light_fit, trials, cost, pairs = fit_light_angle(lit_slices(geometry.camera), geometry.camera,
                                                         stated.light_angle_deg, search_deg, search_step_deg)
        if axis_fit is not None:  # the axis's uncertainty moves θ_l too: refit one standard uncertainty away
            moved = _with_axis(geometry.camera, axis_fit.value[0] + axis_fit.std[0])
            shifted, *_ = fit_light_angle(lit_slices(moved), moved, float(light_fit.value[0]),
                                          min(search_deg, 1.0), search_step_deg)
            light_fit = Fit(light_fit.value, np.hypot(light_fit.std, shifted.value - light_fit.value),
                            light_fit.rms, light_fit.count, light_fit.converged)
        theta_l, theta_std = float(light_fit.value[0]), float(light_fit.std[0])
        edge = abs(theta_l - stated.light_angle_deg) >= search_deg - search_step_deg
        depth = float(np.nanmedian(cost) / np.nanmin(cost) - 1.0) if np.nanmin(cost) > 0 else np.inf
        if edge or not np.isfinite(theta_std) or theta_std > search_deg / 3 or depth < MIN_PROFILE_DEPTH:
            raise StageError(Problem(
                f"calibrate_rig: θ_l is not determined by this capture (estimate {theta_l:.3f}° ± "
                f"{theta_std:.3f}° within the search {stated.light_angle_deg:g} ± {search_deg:g}°; the profile's "
                f"median lies {depth:.0%} above its minimum, {MIN_PROFILE_DEPTH:.0%} needed)",
                fix="the absorption must vary (an object with an inclusion); widen search_deg if the estimate sits "
                "at its edge; or give light_angle: false"))
        profile = (trials, cost, pairs)
        geometry = dataclasses.replace(geometry, light_angle_deg=theta_l)
    return _calibration_dataset(capture, stated, geometry, axis_fit, light_fit, profile)


def _all_edges(capture: xr.Dataset) -> np.ndarray:
    """:func:`silhouette_edges` of every backlit frame (dark subtracted), (angle, row, 2), lazily one task per angle
    chunk and computed at once (the edges are small: two numbers per row and view)."""
    signal = capture["backlit"] - capture["dark"] if "dark" in capture else capture["backlit"]
    edges = xr.apply_ufunc(silhouette_edges, signal.transpose("angle", "row", "col").chunk({"row": -1, "col": -1}),
                           input_core_dims=[["row", "col"]], output_core_dims=[["row", "side"]], dask="parallelized",
                           output_dtypes=[np.float64], dask_gufunc_kwargs={"output_sizes": {"side": 2}})
    return np.asarray(edges.transpose("angle", "row", "side").values)


def _calibration_dataset(capture, stated: RigGeometry, geometry: RigGeometry, axis_fit: Fit | None,
                         light_fit: Fit | None, profile) -> xr.Dataset:
    data, attrs = {}, {}
    if axis_fit is not None:
        data |= {"axis_column": axis_fit.value[0], "axis_column_std": axis_fit.std[0],
                 "axis_column_stated": stated.camera.centre_px[0],
                 "axis_residual_rms": axis_fit.rms / stated.camera.axis_pixel_size}
        attrs |= {"axis_edges_used": axis_fit.count, "axis_converged": axis_fit.converged}
    if light_fit is not None:
        trials, cost, pairs = profile
        data |= {"light_angle": light_fit.value[0], "light_angle_std": light_fit.std[0],
                 "contour_offset": light_fit.value[1], "contour_offset_std": light_fit.std[1],
                 "light_angle_stated": stated.light_angle_deg, "light_residual_rms": light_fit.rms,
                 "light_cost": (("light_angle_trial",), cost), "light_pairs": (("light_angle_trial",), pairs)}
        attrs |= {"light_pairs_used": light_fit.count, "light_converged": light_fit.converged}
    coords = {} if profile is None else {"light_angle_trial": ("light_angle_trial", profile[0], {"units": "degree"})}
    return RIG_CALIBRATION.label(xr.Dataset(data, coords=coords, attrs=geometry_attrs(capture.attrs) | geometry.attrs()
                                            | attrs | {"stated_principal_point_px": list(stated.camera.centre_px),
                                                       "stated_light_angle_deg": stated.light_angle_deg}))


#: camera attrs a calibration must share with the capture it is applied to (it estimates none of them)
_SHARED = ("camera_model", "focal_length_px", "camera_distance", "pixel_size", "length_unit", "light_kind",
           "beam_height")


@stage("apply_rig_calibration", kind=TOMOGRAPHY_CAPTURE)
def apply_rig_calibration(capture: xr.Dataset, calibration: xr.Dataset, /) -> xr.Dataset:
    """The capture with the calibrated rig geometry in its attrs (frames untouched, lazy); the values it stated
    are kept as ``stated_principal_point_px`` and ``stated_light_angle_deg``.

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` store of the rig (the calibrated one, or a later capture on the same rig).
    calibration : xr.Dataset
        A ``calibrate_rig`` result. Its camera (model, focal length or pixel size, distance), length unit and
        light kind must be the capture's: a calibration of another rig is refused.
    """
    if calibration.attrs.get("selpath_kind") != RIG_CALIBRATION.name:
        raise StageError(Problem("apply_rig_calibration: the calibration is not a calibrate_rig result "
                                 f"(selpath_kind {calibration.attrs.get('selpath_kind')!r})"))
    differ = [f"{k}: capture {capture.attrs.get(k)!r}, calibration {calibration.attrs.get(k)!r}" for k in _SHARED
              if not _same(capture.attrs.get(k), calibration.attrs.get(k))]
    if differ:
        raise StageError(Problem("apply_rig_calibration: the calibration is of another rig (" + "; ".join(differ)
                                 + ")", fix="calibrate from a capture of this rig"))
    stated = RigGeometry.from_attrs(capture.attrs, capture.sizes["row"], capture.sizes["col"],
                                    where="apply_rig_calibration: capture")
    updates = {"stated_principal_point_px": list(stated.camera.centre_px),
               "stated_light_angle_deg": stated.light_angle_deg}
    if "axis_column" in calibration:
        updates["principal_point_px"] = [float(calibration["axis_column"]), stated.camera.centre_px[1]]
    if "light_angle" in calibration:
        updates["light_angle_deg"] = float(calibration["light_angle"])
    return capture.assign_attrs(updates)


def _same(a, b) -> bool:
    if isinstance(a, int | float) and isinstance(b, int | float):
        return bool(np.isclose(a, b, rtol=1e-9, atol=0))
    return a == b
