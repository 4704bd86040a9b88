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
θ_l fitted on each quarter turn's pairs (the hull's error varies with direction; the spread itself, not its standard
error: the quarters share the rest of that error), how far θ_l moves when the axis
moves by its uncertainty, and how far it moves with the angle grid: half the difference of θ_l fitted on the even
steps' absorption and on the odd steps' (an even number of steps, at least 16;
:func:`~selpath.stages.tomography._rig_fits.grid_phase_spread`; the
bilinear pairs' error depends on where the grid falls against the inclusions, the same for every subset of one
grid), and the method's own error that no split of one capture shows (``method_std_deg``, 0.05°). How often these
intervals hold the truth is measured over simulated rigs in ``benchmarks/calibrate_rig_coverage.py``
(docs/results.md).

Assumed and not estimated: the focal length (or pixel size), the camera distance, the beam's height, and that the
beam passes the axis (a beam offset from the axis is not in the rig model, DESIGN §8).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import xarray as xr

from selpath.geometry.rig import RIG_ATTRS, Camera, RigGeometry, camera_attr_problems, geometry_attrs
from selpath.pipeline.constraints import Count, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import ANGLE_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables, sorted_sweep
from selpath.stages.tomography._axis_check import all_edges, full_turn, spread
from selpath.stages.tomography._rig_fits import (
    Fit,
    LightData,
    fit_axis_column,
    fit_light_angle,
    grid_phase_spread,
    light_slice_data,
    silhouette_edges,  # noqa: F401  (the module docstring names it; the tests import it here)
    with_axis,
)
from selpath.stages.tomography.acquire import TOMOGRAPHY_CAPTURE
from selpath.stages.tomography.calibrate import absorption as absorption_stage
from selpath.stages.tomography.hull import intersect_half_planes, tangent_half_planes


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


# -- the stages ---------------------------------------------------------------------------------------------
def _full_turn(angles: np.ndarray, what: str) -> None:
    if not full_turn(angles, FULL_TURN_TOLERANCE):
        raise StageError(Problem(f"calibrate_rig: {what} needs a full turn in equal steps; the capture's angles "
                                 f"are {angles[:3].round(3).tolist()} … {angles[-2:].round(3).tolist()} "
                                 f"({len(angles)} views)", fix="capture 0 ≤ φ < 360° in equal steps"))


@stage("calibrate_rig", kind=RIG_CALIBRATION)
def calibrate_rig(capture: xr.Dataset, /, *, axis: bool = True, light_angle: bool = True,
                  search_deg: Positive = 5.0, search_step_deg: Positive = 0.25, rows: Count = 32,
                  min_signal: NonNegative = 1.0, method_std_deg: NonNegative = 0.05) -> xr.Dataset:
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
    method_std_deg : float
        The method's own error in θ_l, added in quadrature to the uncertainty the capture shows [degree]: what
        no split of one capture reveals (the pixels' footprint against the model's single rays, the hull). The
        default makes the errors over 16 simulated rigs about one standard uncertainty in the mean square (RMS z 0.95;
        ``benchmarks/calibrate_rig_coverage.py --vary``, the rigs of generator seed 57); a lab that has validated
        its rig against a known θ_l sets its own.

    Returns
    -------
    xr.Dataset
        A ``rig_calibration`` cube: the estimates ``axis_column`` [px] and ``light_angle`` [degree] with their standard
        uncertainties (``*_std``), the values stated, the fits' residuals and the θ_l profile ``light_cost`` over
        ``light_angle_trial``; the corrected geometry in its attrs.

    References
    ----------
    Thesis §4.2.5 Setup of the measurement; §4.2.6 Light path alignment.
    """
    if not axis and not light_angle:
        raise StageError(Problem("calibrate_rig: nothing to calibrate", fix="set axis or light_angle to true"))
    capture = sorted_sweep(capture, "angle", "calibrate_rig")
    n_rows, n_cols = capture.sizes["row"], capture.sizes["col"]
    stated = RigGeometry.from_attrs(capture.attrs, n_rows, n_cols, where="calibrate_rig: capture")
    angles = capture["angle"].values.astype(float)
    _full_turn(angles, "calibration")
    require_variables(capture, ("backlit",), "calibrate_rig")
    edges = all_edges(capture)  # one pass over the backlit frames serves both fits
    geometry, axis_fit = stated, None
    if axis:
        candidates = np.flatnonzero(np.isfinite(edges).any(axis=(0, 2)))
        if not len(candidates):
            raise StageError(Problem("calibrate_rig: no backlit frame shows the object inside the image",
                                     fix="check the backlit and dark frames"))
        axis_fit = fit_axis_column(edges[:, candidates[spread(len(candidates), rows)]], angles, stated.camera)
        geometry = dataclasses.replace(stated, camera=with_axis(stated.camera, axis_fit.value[0]))
    light_fit, profile = None, None
    if light_angle:
        require_variables(capture, ("target", "reference"), "calibrate_rig")
        lit = geometry.lit_rows()
        lit = lit[spread(len(lit), max(1, min(rows, 8)))]
        flags_ok = absorption_stage(capture.isel(row=lit), min_signal=min_signal)
        values = flags_ok["absorption"].transpose("angle", "row", "col").values.astype(float)
        valid = (flags_ok["flags"].transpose("angle", "row", "col").values == 0) & np.isfinite(values)

        def contours(camera: Camera) -> list:
            """Each lit slice's hull contour seen from ``camera`` (None where the tangents enclose nothing)."""
            return [intersect_half_planes(*tangent_half_planes(edges[:, row, 0], edges[:, row, 1], angles, camera))
                    for row in lit]

        def lit_slices(camera: Camera, steps: slice = slice(None), polygons: list | None = None
                       ) -> list[LightData]:
            out = []
            for k, polygon in enumerate(contours(camera) if polygons is None else polygons):
                data = None if polygon is None else light_slice_data(values[steps, k], valid[steps, k],
                                                                     angles[steps], polygon, camera)
                if data is not None:
                    out.append(data)
            if not out:
                raise StageError(Problem("calibrate_rig: no lit slice has a contour and valid absorption",
                                         fix="check the target, reference and backlit frames, or give "
                                         "light_angle: false"))
            return out

        polygons = contours(geometry.camera)  # the same contours serve the whole turn and its two halves
        light_fit, trials, cost, pairs = fit_light_angle(lit_slices(geometry.camera, polygons=polygons),
                                                         geometry.camera,
                                                         stated.light_angle_deg, search_deg, search_step_deg)
        if axis_fit is not None:  # the axis's uncertainty moves θ_l too: refit one standard uncertainty away
            moved = with_axis(geometry.camera, axis_fit.value[0] + axis_fit.std[0])
            shifted, *_ = fit_light_angle(lit_slices(moved), moved, float(light_fit.value[0]),
                                          min(search_deg, 1.0), search_step_deg, quarter_spread=False)
            light_fit = Fit(light_fit.value, np.hypot(light_fit.std, shifted.value - light_fit.value),
                            light_fit.rms, light_fit.count, light_fit.converged)
        if len(angles) % 2 == 0 and len(angles) >= 16:  # and the angle grid moves it: two interleaved halves
            halves = [lit_slices(geometry.camera, slice(phase, None, 2), polygons) for phase in (0, 1)]
            grid = grid_phase_spread(light_fit.value, halves, geometry.camera)
            light_fit = dataclasses.replace(light_fit, std=np.hypot(light_fit.std, grid))
        light_fit = dataclasses.replace(light_fit, std=np.hypot(light_fit.std, [method_std_deg, 0.0]))
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

    Returns
    -------
    xr.Dataset
        A ``tomography_capture`` cube: the capture with ``principal_point_px`` and ``light_angle_deg`` from the
        calibration, ``stated_principal_point_px`` and ``stated_light_angle_deg`` kept; frames untouched and lazy.

    References
    ----------
    Thesis §4.2.5 Setup of the measurement; §4.2.6 Light path alignment.
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
