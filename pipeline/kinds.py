"""The capture-cube kinds (DESIGN §2): what every kind of store holds, declared once.

A kind fixes, for each variable, its dims in order (an optional trailing ``channel`` dim is always allowed), its
``units`` and ``long_name`` (:class:`Variable`), which dims need a coordinate with a ``units`` attr (and which units),
and which attrs the store must carry (:class:`CubeKind`, :data:`KINDS`); with them the store format's version
(:data:`FORMAT_VERSION`) and the rig attrs a tomography capture carries (:data:`RIG_ATTRS`, :data:`CAMERA_ATTRS`).
The check of a dataset against its kind is :mod:`selpath.pipeline.schema`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

#: Schema version written into every store as ``selpath_format``. Bump it (and add a migration in
#: :data:`selpath.pipeline.migrations.MIGRATIONS`) whenever a kind's dims, units or required attrs change.
#: Format 2 (2026-11): every chunk carries a crc32c checksum and is written even when it holds only the fill
#: value, and a manifest in ``_selpath`` records completion and units. Its cubes are those of format 1.
#: Format 3 (2026-12): the hull is indexed by ``slice`` (a coordinate: the camera row), as sinograms and
#: reconstructions are; formats 1–2 named that dim ``row``, without a coordinate.
#: Format 4 (2026-12): every variable a kind declares has the ``units`` and ``long_name`` the kind fixes
#: (:class:`Variable`), written by :func:`with_metadata` and checked on open.
#: Format 5 (2026-12): the solvers' and calibrations' extra variables (iterations, convergence, objective,
#: residuals, masks) are declared too, optional, with their units and long names; format 4 left them bare.
#: Format 6 (2026-11): transports keep clipped frames as lower bounds and flag pixels whose light was seen only
#: clipped (``censored``, ``censored_offsets``, ``frames_clipped``, ``clip_ratio``); formats ≤ 5 masked clipped
#: frames, so their ``converged`` says nothing of clipped light (a note says so on open).
FORMAT_VERSION = 6


PIXEL_DIMS = ("row", "col")
CHANNEL_DIM = "channel"
#: length units of a tomography store; "1": dimensionless (lengths in a unit the user keeps consistent, e.g. a
#: renderer's scene units with the object's radius 1; σ is then per that unit, written "1")
LENGTH_UNITS = frozenset({"m", "cm", "mm", "um", "px", "1"})
ANGLE_UNITS = frozenset({"degree"})
TIME_UNITS = frozenset({"us"})
PX_UNITS = frozenset({"px"})


@dataclass(frozen=True)
class Variable:
    """One variable of a kind: dims in order, whether required, and its CF metadata.

    ``units``: the ``units`` attr every store of the kind gives it (``{length}`` is the store's length unit:
    its ``length_unit`` attr, else its x/y coordinates'); ``None``: none (flags, masks, images); ``""``:
    not fixed by the kind. ``long_name`` is written with it.
    """

    dims: tuple[str, ...]
    required: bool = True
    description: str = ""
    units: str | None = ""
    long_name: str = ""


@dataclass(frozen=True)
class CubeKind:
    """The schema of one kind of capture cube."""

    name: str
    variables: Mapping[str, Variable]
    #: dims whose coordinate must exist and carry one of these units (``None``: any length unit)
    coord_units: Mapping[str, frozenset[str]]
    #: attrs every store of this kind carries, with a description for errors and docs
    attrs: Mapping[str, str] = field(default_factory=dict)
    #: extra checks on attr values; each returns problems
    attr_checks: tuple[Callable[[Mapping], list[str]], ...] = ()
    description: str = ""

    def frame_dims(self, variable: str) -> tuple[str, ...]:
        """Dims that index whole frames (everything but row/col/channel): the unit of a region write."""
        return tuple(d for d in self.variables[variable].dims if d not in (*PIXEL_DIMS, CHANNEL_DIM))


#: Rig-geometry attrs of a tomography capture (DESIGN §2, §8). This and :data:`CAMERA_ATTRS` are the one
#: declaration of them: the store check (:mod:`selpath.pipeline.schema`), ``selpath.devices.geometry`` (which builds the cameras
#: from attrs) and the hardware rig's config read them; ``pipeline`` imports neither of those (DESIGN §1).
RIG_ATTRS = {
    "camera_model": "'perspective' or 'orthographic'",
    "light_angle_deg": "light angle θ_l between the beam and the camera axis, degree",
    "length_unit": "unit of every length attr and of sinogram x: 'm', 'cm', 'mm', 'um', 'px' or '1' (dimensionless)",
}
#: Further attrs each camera model needs. ``principal_point_px`` is in every perspective store; a camera built
#: from a config (``sensor_defaults``) may leave it out: it defaults to the sensor's centre.
CAMERA_ATTRS: dict[str, tuple[str, ...]] = {
    # light_distance (D_l) is not required: a beam is a line, and where its source sits on it changes no ray
    "perspective": ("focal_length_px", "principal_point_px", "camera_distance"),
    "orthographic": ("pixel_size",),
}
SENSOR_DEFAULTS = frozenset({"principal_point_px"})


def camera_attr_problems(attrs: Mapping, *, sensor_defaults: bool = False) -> list[str]:
    """What the attrs of a camera model (``attrs['camera_model']``; none given: nothing to check) lack."""
    model = attrs.get("camera_model")
    if model is None:
        return []
    if model not in CAMERA_ATTRS:
        return [f"attr camera_model is {model!r}; expected {' or '.join(map(repr, CAMERA_ATTRS))}"]
    skip = SENSOR_DEFAULTS if sensor_defaults else frozenset()
    return [f"attr {a!r} is required for a {model} camera" for a in CAMERA_ATTRS[model]
            if a not in attrs and a not in skip]


_FRAME = ("row", "col")
#: the per-pixel solver's results beside a transport (:mod:`selpath.stages.procam._demux_store`)
_DEMUX_EXTRAS = {
    "iterations": Variable(_FRAME, required=False, units="1", long_name="ADMM iterations run for the pixel"),
    "converged": Variable(_FRAME, required=False, units=None,
                          long_name="the pixel's solve met its tolerance (plane-to-ray: a certified gap_bound "
                                    "within max_gap) and no offset's light is censored"),
    "censored": Variable(_FRAME, required=False, units=None,
                         long_name="some offset's light was seen only in clipped frames: T is a lower bound there"),
    "censored_offsets": Variable(_FRAME, required=False, units="1",
                                 long_name="offsets whose light was seen only in clipped frames"),
    "gap_bound": Variable(_FRAME, required=False, units="1",
                          long_name="certified bound on the relative objective gap (f(T) − f*)/f(T)"),
    "frames_used": Variable(_FRAME, required=False, units="1",
                            long_name="frames observed for the pixel, neither clipped nor missing"),
    "frames_clipped": Variable(_FRAME, required=False, units="1",
                               long_name="frames at or above saturation_counts, kept as lower bounds"),
    "clip_ratio": Variable(_FRAME, required=False, units="1",
                           long_name="brightest frame T predicts over the clip level (counts above dark)"),
    "objective": Variable(_FRAME, required=False, units="1",
                          long_name="objective at T (images scaled to [0, 1])"),
}
_COUNTS = {"units": "counts", "long_name": "sensor counts"}
#: what a projector–camera capture must say about its sensor: without them clipped frames pass as data
_CAMERA_LEVELS = {
    "saturation_counts": "raw counts at and above which a pixel is clipped (kept as lower bounds on the light)",
    "dark_level_counts": "raw counts of an unlit pixel (black level), subtracted before demultiplexing",
}
#: what a transport carries from its sweep, read by the stages after it (short_range_images, the relighting figures)
_TRANSPORT_ATTRS = {
    "scan_speed_px_per_us": "v_p used, camera rows per µs (offset o ↔ delay o / v_p)",
    "line_time_us": "t_p, µs",
    "full_scale_counts": "counts that scaled the images to [0, 1] (the objective's scale)",
}
_FLAGS = {"units": None, "long_name": "why a pixel is invalid (CF flags; 0: valid)"}
_ABSORPTION = "total absorption A = log I_reference − log I_target"
_SIGMA, _SIGMA_NAME = "1/{length}", "absorption coefficient σ"
#: what a reconstruction holds beside σ (:mod:`selpath.stages.tomography.reconstruct`; ADMM's only with ``reconstruct_tv``)
_RECONSTRUCTION_EXTRAS = {
    "reliable": Variable(("y", "x"), required=False, units=None,
                         long_name="cell every ray through which is observed or known"),
    "sigma_max": Variable(("y", "x"), required=False, units=_SIGMA,
                          long_name="upper bound σ_max of the box constraint"),
    "iterations": Variable((), required=False, units="1", long_name="ADMM iterations run"),
    "converged": Variable((), required=False, units=None, long_name="ADMM met its tolerance"),
    "objective": Variable(("iteration",), required=False, units="1",
                          long_name="objective of Eq. 20 per ADMM iteration (NaN after the stop)"),
    "primal_residual": Variable(("iteration",), required=False, units="1",
                                long_name="relative primal residual per ADMM iteration (NaN after the stop)"),
    "dual_residual": Variable(("iteration",), required=False, units="1",
                              long_name="relative dual residual per ADMM iteration (NaN after the stop)"),
    # reconstruct_scattering's (stages.tomography.scattering): L-BFGS-B's end and the bundles' sizes
    "final_objective": Variable((), required=False, units="1", long_name="objective at the stop"),
    "paths_per_bin": Variable((), required=False, units="1", long_name="median distinct paths per observed bin"),
    "bins_without_paths": Variable((), required=False, units="1",
                                   long_name="observed bins no walk reached (left out of the fit)"),
}
KINDS: dict[str, CubeKind] = {
    k.name: k
    for k in (
        CubeKind(
            name="tomography_capture",
            description="frames of the rotating object: target, reference (no inclusion), backlit, dark",
            variables={
                "target": Variable(("angle", *_FRAME), description="object with the inclusion", **_COUNTS),
                "reference": Variable(("angle", *_FRAME), description="same object without it (§4.4.2)", **_COUNTS),
                "backlit": Variable(("angle", *_FRAME), False, "silhouettes against a lit plane (§4.2.6)", **_COUNTS),
                "dark": Variable(_FRAME, False, "sensor offset with all lights off", **_COUNTS),
            },
            coord_units={"angle": ANGLE_UNITS},
            attrs=RIG_ATTRS,
            attr_checks=(camera_attr_problems,),
        ),
        CubeKind(
            name="rig_calibration",
            description="the tomography rig's axis column and light angle θ_l estimated from a capture "
            "(calibrate_rig); its attrs are the corrected geometry",
            variables={
                "axis_column": Variable((), False, "principal point's column: where the axis is seen", units="px",
                                        long_name="column the rotation axis is seen in"),
                "axis_column_std": Variable((), False, "standard uncertainty", units="px",
                                            long_name="standard uncertainty of axis_column"),
                "light_angle": Variable((), False, "θ_l", units="degree", long_name="light angle θ_l"),
                "light_angle_std": Variable((), False, "standard uncertainty", units="degree",
                                            long_name="standard uncertainty of θ_l"),
                "light_cost": Variable(("light_angle_trial",), False, "θ_l profile", units="1",
                                       long_name="mean squared disagreement of reversed chords"),
            },
            coord_units={"light_angle_trial": ANGLE_UNITS},
            attrs={**RIG_ATTRS, "stated_principal_point_px": "(col, row) principal point the capture stated, px",
                   "stated_light_angle_deg": "θ_l the capture stated, degree"},
            attr_checks=(camera_attr_problems,),
        ),
        CubeKind(
            name="absorption",
            description="total absorption A = log I_reference − log I_target per pixel, with flags",
            variables={
                "absorption": Variable(("angle", *_FRAME), units="1", long_name=_ABSORPTION),
                "flags": Variable(("angle", *_FRAME), description="CF flag bits; 0 means valid", **_FLAGS),
            },
            coord_units={"angle": ANGLE_UNITS},
        ),
        CubeKind(
            name="transmittance",
            description="I_target / I_reference per pixel, with flags",
            variables={
                "transmittance": Variable(("angle", *_FRAME), units="1",
                                          long_name="transmittance I_target / I_reference"),
                "flags": Variable(("angle", *_FRAME), description="CF flag bits; 0 means valid", **_FLAGS),
            },
            coord_units={"angle": ANGLE_UNITS},
        ),
        CubeKind(
            name="silhouettes",
            description="object masks per angle from backlit frames (§4.2.6)",
            variables={"silhouette": Variable(("angle", *_FRAME), description="True where the object is", units=None,
                                               long_name="object mask")},
            coord_units={"angle": ANGLE_UNITS},
            attrs=RIG_ATTRS,  # visual_hull builds the rig's geometry from them
            attr_checks=(camera_attr_problems,),
        ),
        CubeKind(
            name="hull",
            description="visual hull: the object's convex contour per slice (coordinate: camera row), object frame",
            variables={
                "vertices": Variable(("slice", "vertex", "xy"), description="counter-clockwise, NaN-padded",
                                     units="{length}", long_name="contour vertex (x, y), object frame"),
                "n_vertices": Variable(("slice",), description="vertices used per slice; 0: no contour", units="1",
                                       long_name="vertices of the contour"),
            },
            coord_units={},
            attrs={**RIG_ATTRS,  # align_paths and coverage build the rig's geometry from them
                   "hull_resolution": "largest gap between the silhouette edge and the contour, length unit"},
            attr_checks=(camera_attr_problems,),
        ),
        CubeKind(
            name="rays",
            description="aligned light paths per pixel: sinogram coordinates and total absorption (§4.2.6)",
            variables={
                "theta": Variable(("angle", *_FRAME), description="normal angle of the ray, degree in [0, 180)",
                                  units="degree", long_name="normal angle θ of the ray"),
                "x": Variable(("angle", *_FRAME), description="signed distance of the ray from the axis",
                              units="{length}", long_name="signed distance X of the ray from the axis"),
                "absorption": Variable(("angle", *_FRAME), description="total absorption; NaN where dropped", units="1",
                                       long_name=_ABSORPTION),
                "reason": Variable(("angle", *_FRAME), description="0: ray kept; else why it was dropped", units=None,
                                   long_name="why the ray was dropped (0: kept)"),
            },
            coord_units={"angle": ANGLE_UNITS},
            attrs={"length_unit": RIG_ATTRS["length_unit"], "light_angle_deg": RIG_ATTRS["light_angle_deg"]},
        ),
        CubeKind(
            name="coverage",
            description="observation rate of a sinogram: measured and analytic d_min, d_max (§4.2.7)",
            variables={"coverage": Variable(("slice",), units="1", long_name="observed share d_max − d_min"),
                       "d_min": Variable(("slice",), units="1", long_name="lowest observed |X| / R, d_min"),
                       "d_max": Variable(("slice",), units="1", long_name="highest observed |X| / R, d_max")},
            coord_units={},
        ),
        CubeKind(
            name="scan_calibration",
            description="scan speed v_p and sync offset t_o from global-shutter frames of a white target (§5.3.2)",
            variables={
                "count": Variable(("delay", "exposure"), description="illuminated rows counted per frame", units="1",
                                  long_name="illuminated camera rows"),
                "centroid": Variable(("delay", "exposure"), description="row centroid of the lit band", units="px",
                                     long_name="camera row at the lit band's centroid"),
                "used": Variable(("delay", "exposure"), required=False, units=None,
                                 long_name="frame used in the fit (a band inside the frame)"),
            },
            coord_units={"delay": TIME_UNITS, "exposure": TIME_UNITS},
            attrs={"scan_speed_px_per_us": "fitted v_p, camera rows per µs", "scan_speed_std": "its standard error",
                   "sync_offset_us": "fitted t_o, µs", "sync_offset_std": "its standard error"},
        ),
        CubeKind(
            name="figure",
            description="a rendered figure (RGBA); the engine also saves it as <store>.png",
            variables={"image": Variable(("y", "x", "rgba"), units=None, long_name="RGBA image")},
            coord_units={},
        ),
        CubeKind(
            name="checkerboard_capture",
            description="one frame per shifted checkerboard, floodlit or epipolar (§5.4.6)",
            variables={"image": Variable(("shift", *_FRAME), **_COUNTS)},
            coord_units={"shift": frozenset({"1"})},
            attrs={"square_px": "checkerboard square [rows, cols], projector px",
                   "mode": "'floodlit' (global shutter over the whole scan) or 'epipolar' (t_d = 0, t_e = t_p)",
                   **_CAMERA_LEVELS},
        ),
        CubeKind(
            name="gray_code_capture",
            description="white, black and every Gray-code bit with its inverse, columns then rows (acquire_gray_code)",
            variables={"image": Variable(("pattern", *_FRAME), **_COUNTS)},
            coord_units={"pattern": frozenset({"1"})},
            attrs={"column_bits": "column bits (patterns 2, 4, … after white and black; each followed by its inverse)",
                   "row_bits": "row bits (after the column bits' pairs)",
                   "projector_shape": "[rows, cols] of the projector",
                   "exposure_us": "t_e of every frame, µs (many rows: a pixel sees the rows around its own)",
                   **_CAMERA_LEVELS},
        ),
        CubeKind(
            name="projector_correspondence",
            description="the projector column and row that light each camera pixel directly (decode_gray_code)",
            variables={"projector_col": Variable(_FRAME, units="px", long_name="projector column lighting the pixel"),
                       "projector_row": Variable(_FRAME, units="px", long_name="projector row lighting the pixel")},
            coord_units={},
            attrs={"projector_shape": "[rows, cols] of the projector"},
        ),
        CubeKind(
            name="epipolar_alignment",
            description="how far each pixel's direct light is off its epipolar row, measured and fitted "
            "(epipolar_alignment)",
            variables={"measured": Variable(_FRAME, units="px", long_name="decoded row offset δ, camera rows"),
                       "model": Variable(_FRAME, units="px", long_name="fitted row offset δ, camera rows")},
            coord_units={},
            attrs={"shift_rows": "fitted δ at the image centre, camera rows",
                   "roll_deg": "fitted rotation of the projector's rows against the camera's, degree",
                   "median_abs_rows": "median |δ| of the model over the decoded pixels, camera rows",
                   "tolerance_rows": "|δ| above which the rows are not epipolar (default half the lit line's height), camera rows"},
        ),
        CubeKind(
            name="stereo_target_capture",
            description="a checkerboard target at several poses under white, black and the projector's Gray codes",
            variables={"image": Variable(("pose", "pattern", *_FRAME), **_COUNTS)},
            coord_units={"pose": frozenset({"1"}), "pattern": frozenset({"1"})},
            attrs={"column_bits": "column bits (as in a gray_code_capture)", "row_bits": "row bits",
                   "projector_shape": "[rows, cols] of the projector",
                   "board_corners": "[columns, rows] of the board's inner corners",
                   "board_square_mm": "side of a board square, mm", **_CAMERA_LEVELS},
        ),
        CubeKind(
            name="camera_calibration",
            description="a camera's intrinsics and distortion from a checkerboard target (calibrate_camera)",
            variables={"camera_matrix": Variable(("i", "j"), units="px", long_name="camera intrinsics K"),
                       "distortion": Variable(("k",), units="1", long_name="k1, k2, p1, p2, k3")},
            coord_units={},
            attrs={"focal_length_px": "mean of fx and fy, px", "principal_point_px": "[cx, cy], px",
                   "reprojection_rms_px": "reprojection error, px",
                   "distortion_max_px": "largest shift of a pixel inside the sensor by the distortion, px",
                   "sensor_px": "[rows, cols] of the calibrated sensor"},
        ),
        CubeKind(
            name="procam_stereo_calibration",
            description="camera and projector intrinsics, their relative pose and the rectification "
            "(calibrate_procam_stereo)",
            variables={
                "camera_matrix": Variable(("i", "j"), units="px", long_name="camera intrinsics K_c"),
                "projector_matrix": Variable(("i", "j"), units="px", long_name="projector intrinsics K_p"),
                "rotation": Variable(("i", "j"), units="1", long_name="projector from camera rotation R"),
                "translation": Variable(("i",), units="mm", long_name="projector from camera translation t"),
            },
            coord_units={},
            attrs={"reprojection_rms_px": "stereo reprojection error, px",
                   "roll_deg": "rotation of the projector about its optical axis against the camera, degree",
                   "row_disparity_before": "median |row difference| of corresponding corners on the camera's "
                   "scale, unrectified, px",
                   "row_disparity_after": "the same after stereoRectify, px",
                   "sync_rows_median": "median |projector row as the sync pairs it − camera row| at the corners, "
                   "camera rows"},
        ),
        CubeKind(
            name="short_range",
            description="floodlit images of delay-limited sweeps |t_d| ≤ T_dmax, their energy and captures (§5.4.4)",
            variables={"image": Variable(("max_delay", *_FRAME), units="counts",
                                         long_name="floodlit image of the short-range sweep"),
                       "energy_fraction": Variable(("max_delay",), units="1",
                                                   long_name="share of the transport's energy within the range")},
            coord_units={"max_delay": TIME_UNITS},
        ),
        CubeKind(
            name="delay_choice",
            description="the delay that shows a structure below the surface best, and its images (§5.4.7)",
            variables={"image": Variable(("view", *_FRAME), units="counts",
                                         long_name="regular, far-range indirect, chosen-delay"),
                       "contrast": Variable(("delay",), units="1", long_name="Weber contrast |μ_s − μ_v| / μ_s of the frame")},
            coord_units={"delay": TIME_UNITS},
            attrs={"chosen_delay_us": "the delay of the highest contrast, µs"},
        ),
        CubeKind(
            name="material_atlas",
            description="2-D transport profiles of named pixels scaled to their maximum, and extents (§5.4.10)",
            variables={"profile": Variable(("site", "du", "dv"), units="1", long_name="T / its maximum"),
                       "extent": Variable(("site",), units="px",
                                          long_name="RMS distance from the direct correspondence"),
                       "image": Variable(_FRAME, units="counts", long_name="white image Σ T")},
            coord_units={"du": PX_UNITS, "dv": PX_UNITS},
            attrs={"reach_px": "half-width of the profiles' window, px"},
        ),
        CubeKind(
            name="scattering_profile",
            description="a material's fitted scattering profile R(d) = (1 − f)·δ + f·Laplace(w) (§5.4.8)",
            variables={"profile": Variable(("distance",), units="1", long_name="scattering profile R(d)"),
                       "measured": Variable(("delay",), units="counts", long_name="the material's mean delay profile")},
            coord_units={"distance": PX_UNITS, "delay": TIME_UNITS},
            attrs={"fraction": "the share f of the light that scatters below the surface",
                   "width_px": "the Laplace lobe's width w, px"},
        ),
        CubeKind(
            name="appearance_render",
            description="a mesh rendered with and without a captured subsurface profile (§5.4.8, Fig. 50)",
            variables={"image": Variable(("render", *_FRAME), units="1", long_name="rendered radiance")},
            coord_units={},
        ),
        CubeKind(
            name="delay_profiles",
            description="per-pixel delay profiles normalised by their area, so albedo cancels (§5.4.9)",
            variables={"profile": Variable(("delay", *_FRAME), units="1", long_name="delay profile / its area"),
                       "area": Variable(_FRAME, units="counts",
                                        long_name="area of the delay profile (the regular image)"),
                       "flags": Variable(_FRAME, **_FLAGS)},
            coord_units={"delay": TIME_UNITS},
            attrs={"source_kind": "the kind the profiles were made from: a capture or a transport"},
        ),
        CubeKind(
            name="material_classifier",
            description="an RBF-kernel SVM on delay profiles and its brightness-only baseline, a skops archive",
            variables={"model": Variable(("byte",), units=None, long_name="the classifiers, a skops archive"),
                       "mean_profile": Variable(("material", "delay"), units="1",
                                                long_name="mean training profile")},
            coord_units={"delay": TIME_UNITS},
            attrs={"source_kind": "the kind of the training profiles' source",
                   "svm_C": "the chosen SVM regularisation C", "svm_gamma": "the chosen RBF width γ"},
        ),
        CubeKind(
            name="material_classification",
            description="pixels classified by delay profile and by brightness, and their accuracy (Figs. 51–52)",
            variables={"label": Variable(_FRAME, units=None, long_name="class index into material"),
                       "brightness_label": Variable(_FRAME, units=None, long_name="class index, brightness only"),
                       "accuracy": Variable(("material",), required=False, units="1",
                                            long_name="share of the class's pixels classified right")},
            coord_units={},
        ),
        CubeKind(
            name="multiplexing_study",
            description="SNR gain of multiplexed line codes over simplex: noise model and simulation (§5.4.3)",
            variables={"predicted_gain_db": Variable(("signal", "code"), units="dB",
                                                     long_name="SNR gain over simplex, noise model"),
                       "measured_gain_db": Variable(("signal", "code"), units="dB",
                                                    long_name="SNR gain over simplex, simulated")},
            coord_units={"signal": frozenset({"counts"})},
        ),
        CubeKind(
            name="line_relighting_snr",
            description="a line relit from a demultiplexed stack against the line projected alone, SNR (Fig. 42)",
            variables={"image": Variable(("method", *_FRAME), units="counts", long_name="the line's image"),
                       "truth": Variable(_FRAME, units="counts", long_name="the line's image without noise"),
                       "snr_db": Variable(("method",), units="dB", long_name="SNR on the lit pixels, measured")},
            coord_units={},
            attrs={"line_rows": "the line's camera rows [first, stop)",
                   "lit_fraction": "lit pixels: truth at least this fraction of its maximum"},
        ),
        CubeKind(
            name="relighting_snr",
            description="the scene relit from full transport under a checkerboard and floodlit, SNR (Fig. 43)",
            variables={"image": Variable(("pattern", *_FRAME), units="counts", long_name="relit from the transport"),
                       "truth": Variable(("pattern", *_FRAME), units="counts",
                                         long_name="the pattern's image without noise"),
                       "snr_db": Variable(("pattern",), units="dB", long_name="SNR on the lit pixels, measured")},
            coord_units={},
            attrs={"square_px": "checkerboard square, projector px",
                   "lit_fraction": "lit pixels: truth at least this fraction of its maximum"},
        ),
        CubeKind(
            name="direct_global",
            description="direct and global light per pixel from shifted checkerboards (§5.4.6, Nayar et al.)",
            variables={"direct": Variable(_FRAME, units="counts", long_name="direct light L_d"),
                       "global": Variable(_FRAME, units="counts", long_name="global light L_g"),
                       "flags": Variable(_FRAME, required=False, **_FLAGS)},
            coord_units={},
        ),
        CubeKind(
            name="plane_to_ray_capture",
            description="image stacks over sync delay and exposure (§5.2.3)",
            variables={"image": Variable(("delay", "exposure", *_FRAME), **_COUNTS)},
            coord_units={"delay": TIME_UNITS, "exposure": TIME_UNITS},
            attrs={
                "scan_speed_px_per_us": "projector scan speed v_p, projector rows per µs",
                "line_time_us": "projector line time t_p, µs",
                **_CAMERA_LEVELS,
            },
        ),
        CubeKind(
            name="full_transport_capture",
            description="stacks over delay, exposure and projected line position (§5.3.1)",
            variables={"image": Variable(("delay", "exposure", "line", *_FRAME), **_COUNTS)},
            coord_units={"delay": TIME_UNITS, "exposure": TIME_UNITS, "line": PX_UNITS},
            attrs={
                "scan_speed_px_per_us": "projector scan speed v_p, projector rows per µs",
                "line_time_us": "projector line time t_p, µs",
                "line_width_px": "width l_w of the projected vertical line, projector columns",
                **_CAMERA_LEVELS,
            },
        ),
        CubeKind(
            name="plane_to_ray_transport",
            description="T(v, s, t) indexed by offset = projector row − camera row",
            variables={"transport": Variable(("offset", *_FRAME), units="counts",
                                                 long_name="plane-to-ray transport T(v, s, t)"), **_DEMUX_EXTRAS},
            coord_units={"offset": PX_UNITS},
            attrs=_TRANSPORT_ATTRS,
        ),
        CubeKind(
            name="full_transport",
            description="T(u, v, s, t) indexed by offsets from the direct correspondence",
            variables={"transport": Variable(("du", "dv", *_FRAME), units="counts",
                                                 long_name="full transport T(u, v, s, t)"), **_DEMUX_EXTRAS},
            coord_units={"du": PX_UNITS, "dv": PX_UNITS},
            attrs={**_TRANSPORT_ATTRS,
                   "line_width_px": "width l_w of the projected vertical line, projector columns",
                   "cell_width_px": "width of a u-cell, projector columns (du steps by it)",
                   "cells_px": "centres of the u-cells solved for, projector columns (u₀ is one of them)"},
        ),
        CubeKind(
            name="sinogram",
            description="total absorption on a (θ, X) grid with a mask of observed rays",
            variables={
                "absorption": Variable(("theta", "x"), units="1", long_name=_ABSORPTION),
                "observed": Variable(("theta", "x"), description="True where a ray was measured", units=None,
                                     long_name="bin holds a measured ray"),
                "count": Variable(("theta", "x"), False, "rays averaged into the bin", units="1",
                                  long_name="rays averaged into the bin"),
            },
            coord_units={"theta": ANGLE_UNITS, "x": LENGTH_UNITS},
        ),
        CubeKind(
            name="light_angle_study",
            description="reconstructions and their errors versus the light angle θ_l (§4.4.1, Table 1)",
            variables={"rmse": Variable(("light_angle", "method"), units=_SIGMA, long_name="RMSE of σ"),
                       "max_abs_error": Variable(("light_angle", "method"), units=_SIGMA, long_name="max |error| of σ"),
                       "sigma": Variable(("light_angle", "method", "y", "x"), units=_SIGMA, long_name=_SIGMA_NAME)},
            coord_units={"light_angle": ANGLE_UNITS, "y": LENGTH_UNITS, "x": LENGTH_UNITS},
        ),
        CubeKind(
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
            coord_units={},
        ),
        CubeKind(
            name="scattering_estimate",
            description="σ_s of the medium fitted to how the reference frames spread the beam's light (#27)",
            variables={
                "sigma_s": Variable((), units="1/{length}", long_name="scattering coefficient σ_s (estimate)"),
                "sigma_s_low": Variable((), units="1/{length}", long_name="16th percentile of the bootstrap σ_s"),
                "sigma_s_high": Variable((), units="1/{length}", long_name="84th percentile of the bootstrap σ_s"),
                "settled": Variable((), units=None, long_name="the last round's estimate stayed near its walks' σ_s"),
                "rounds": Variable((), units="1", long_name="rounds of walks traced"),
                "effective_walks": Variable((), units="1", long_name="effective number of walks at the estimate"),
                "objective": Variable(("candidate",), units="1", long_name="misfit of the log exit profile"),
                "candidate_sigma_s": Variable(("candidate",), units="1/{length}", long_name="candidate σ_s"),
                "measured_profile": Variable(("distance_bin",), units="counts·{length}^2",
                                             long_name="reference light per distance bin (counts × pixel area)"),
                "modelled_profile": Variable(("distance_bin",), units="counts·{length}^2",
                                             long_name="walks per distance bin at the estimate, scaled"),
                "bin_distance": Variable(("distance_bin",), units="{length}",
                                         long_name="distance from the entry point (bin centre)"),
            },
            coord_units={},
        ),
        CubeKind(
            name="reconstruction",
            description="absorption coefficient σ per slice",
            variables={"sigma": Variable(("y", "x"), description="absorption coefficient per unit length", units=_SIGMA,
                                        long_name=_SIGMA_NAME), **_RECONSTRUCTION_EXTRAS},
            coord_units={"y": LENGTH_UNITS, "x": LENGTH_UNITS},
        ),
    )
}
