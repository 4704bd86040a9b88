"""The fits behind ``calibrate_rig`` (:mod:`selpath.stages.tomography.rig_calibration`, whose docstring derives
them): sub-pixel silhouette edges, the rotation axis's column from the support function the left and right edges
sample, and the light angle θ_l from reversed chords that must carry the same absorption; least squares with the
uncertainties the stage reports.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from selpath.geometry.rig import Camera, to_object_xy
from selpath.geometry.shapes import convex_polygon
from selpath.pipeline.errors import Problem, StageError
from selpath.stages.tomography.hull import backlight_levels, tangent_half_planes


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
def with_axis(camera: Camera, column: float) -> Camera:
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
    camera = with_axis(camera, column)
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
    from scipy.optimize import least_squares  # scipy when it fits, not when a workflow is read

    x0 = np.atleast_1d(np.asarray(start, float))
    # (tolerances of 1e-9: far below any uncertainty the fits state, and the residuals, piecewise linear through
    # the interpolation, never converge quadratically: at 1e-12 MINPACK iterated ~20 times a fit)
    solution = least_squares(residuals, x0, method="lm", jac="3-point", diff_step=step, xtol=1e-9, ftol=1e-9)
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
class LightData:
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


def _conjugates(params, data: LightData, camera: Camera):
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


def _pair_mask(params, data: LightData, camera: Camera, min_exit_cos: float = 0.05) -> np.ndarray:
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
    from scipy.ndimage import map_coordinates

    pieces = []
    for d, camera in slices:
        index, col, _ = _conjugates(params, d, camera)
        pieces.append(d.value - map_coordinates(d.table, [index, col], order=1, mode="nearest"))  # bilinear
    return np.concatenate(pieces)


def _seen_pairs(params, slices, camera: Camera, keep=None) -> list[tuple[LightData, Camera]]:
    """Each slice's pairs whose reversed chord is seen at ``params`` (:func:`_pair_mask`), and where ``keep`` (a
    function of the pairs' stage angles) says so: the residuals then compute only what they use."""
    out = []
    for d in slices:
        mask = _pair_mask(params, d, camera) & (keep(d.phi - d.phi0) if keep is not None else True)
        out.append((dataclasses.replace(d, phi=d.phi[mask], exit=d.exit[mask], ray=d.ray[mask],
                                        ray_cos=d.ray_cos[mask], value=d.value[mask]), camera))
    return out


def light_slice_data(absorption: np.ndarray, valid: np.ndarray, angles_deg: np.ndarray, polygon_vertices: np.ndarray,
                     camera: Camera, min_exit_cos: float = 0.05) -> LightData | None:
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
    return LightData(np.concatenate([table, table[:1]]), np.concatenate([valid, valid[:1]]),
                      phi[use], p_c[use], d_obj[use], ray_cos[use], absorption.ravel()[use],
                      normals, offsets, np.roll(corners, -start), float(phi[0]), 2 * np.pi / n_angle)


def light_cost(params, slices, camera: Camera) -> tuple[float, int]:
    """Mean squared disagreement of reversed chords at (θ_l, contour offset), and the pairs it is taken over."""
    r = _light_residuals(params, _seen_pairs(params, slices, camera))
    return (float(np.mean(r**2)) if len(r) else np.nan), len(r)


def fit_light_angle(slices, camera: Camera, stated: float, search_deg: float, step_deg: float,
                    quarter_spread: bool = True) -> tuple[Fit, np.ndarray, np.ndarray, np.ndarray]:
    """θ_l and the contour's offset: a profile of :func:`light_cost` over ``stated ± search_deg`` (offset 0), then
    least squares in both from the profile's minimum (twice, the pairs chosen again at the first answer).

    ``camera`` sees the axis where the slices were built. Returns the fit (values and uncertainties of θ_l
    [degree] and the offset [pixels at the axis]) and the profile (trial angles, mean squared disagreement,
    pairs). ``quarter_spread``: add the quarter turns' spread to the uncertainties (four more fits; not needed where
    only the value is)."""
    trials = stated + np.arange(-search_deg, search_deg + step_deg / 2, step_deg)
    trials = trials[(trials >= 0) & (trials <= 180)]
    profile = np.array([light_cost((t, 0.0), slices, camera) for t in trials])
    cost, pairs = profile[:, 0], profile[:, 1].astype(int)
    enough = pairs >= max(16, 0.25 * pairs.max())
    if not enough.any() or not np.isfinite(cost[enough]).any():
        raise StageError(Problem("calibrate_rig: no reversed chord is seen at any trial light angle",
                                 fix="capture a full turn with the beam's far side in view, "
                                 "or give light_angle: false"))
    params = np.array([trials[int(np.nanargmin(np.where(enough, cost, np.nan)))], 0.0])
    for _ in range(2):
        seen = _seen_pairs(params, slices, camera)
        fit = _least_squares(lambda p, seen=seen: _light_residuals(p, seen), params, np.sqrt(8.0))
        params = fit.value
    # (the √8: one absorption sample enters about four pairs through the bilinear weights, and each pair twice)
    # The contour's error varies with direction (each part of the hull is cut by other views' edges); the pairs of
    # each quarter turn see another part of it. Their fits' spread is the scale of θ_l's systematic error, not
    # divided by √4: the quarters share the part of the error that does not vary with direction, which their spread
    # cannot show and which, over simulated rigs, grows with it (benchmarks/calibrate_rig_coverage.py --vary: over
    # √4, rigs with a wide spread were off by 3 standard uncertainties).
    if not quarter_spread:
        return fit, trials, cost, pairs
    quarters = []
    for q in range(4):
        part = _seen_pairs(params, slices, camera,
                           keep=lambda phi, q=q: np.floor(np.mod(phi, 2 * np.pi) / (np.pi / 2)) == q)
        if sum(len(d.value) for d, _ in part) >= 16:
            quarters.append(_least_squares(lambda p, part=part: _light_residuals(p, part), params, 1.0).value)
    if len(quarters) >= 2:
        spread = np.std(quarters, axis=0, ddof=1)
        fit = Fit(fit.value, np.hypot(fit.std, spread), fit.rms, fit.count, fit.converged)
    return fit, trials, cost, pairs


def grid_phase_spread(params, halves, camera: Camera) -> np.ndarray:
    """How far θ_l and the contour offset move with the angle grid: each half of the turn's angles (the even
    steps and the odd ones, ``halves``: each its lit slices' :class:`LightData`) refitted from ``params``; half the
    difference of the two fits, the standard error of their mean.

    The pairs interpolate absorption bilinearly between stage angles; how that error falls depends on where the
    grid lies against the object's inclusions and differs from rig to rig, so the fits at one grid agree with each
    other (every quarter turn, every slice, shares it) and no split of the pairs shows it. Two interleaved grids
    of twice the step do: on simulated rigs of the shipped gelatin bin, grid errors of 0.03–0.16° at a 2° step,
    while noise accounts for 0.02–0.05° (``benchmarks/calibrate_rig_coverage.py --vary``)."""
    fits = []
    for slices in halves:
        seen = _seen_pairs(params, slices, camera)
        if sum(len(d.value) for d, _ in seen) < 16:
            return np.zeros(len(params))
        fits.append(_least_squares(lambda p, seen=seen: _light_residuals(p, seen), params, 1.0).value)
    return np.abs(fits[0] - fits[1]) / 2
