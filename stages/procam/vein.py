"""Seeing below the surface with the delay chosen for you: vein imaging (thesis §5.4.7, Fig. 49).

A frame at sync delay t_d and exposure t_e records the light that entered the surface between v_p·(t_d − t_e/2)
and v_p·(t_d + t_e/2) rows from each pixel (widened by the line time t_p). Light entering a distance ρ away
travelled down to a depth of about ρ/2, so the delay selects how deep the image looks: at t_d = 0 the skin's
direct reflection hides a vein; at large t_d the light has passed below it and the vein is lost again (the far-range
indirect image); between them is a delay at which the vein shows best. The thesis chose it by hand and left the
choice to further study.

:func:`choose_delay` chooses it from a plane-to-ray transport T(offset, row, col): for each candidate t_d it forms
the frame an ideal rig would record, I(t_d) = Σ_o w(o; t_d, t_e)·T(o) (the illumination weights of the
demultiplexing, :mod:`selpath.stages.procam._illumination`), and measures the **Weber contrast** of the structure
against its
surround, C = |μ_surround − μ_structure| / μ_surround (region means over labelled pixels), and picks the delay of
the highest C. Only delays whose frames hold no direct light are candidates: the exposure window plus the line time
must stay clear of the pixel's own row, |t_d| ≥ (t_e + t_p)/2 (the thesis's t_d ≥ t_e/2, with the line time's half,
which the thesis's rig made negligible). Delays whose surround is darker than ``min_signal`` of the regular image's
are left out too: a contrast of two near-zero means is noise, not structure.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Fraction, Positive, StorePath
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import TIME_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.procam._illumination import plane_to_ray_illumination
from selpath.stages.procam._labels import Labels, label_identity, label_map, label_precheck
from selpath.stages.procam.acquire import TimeSweep

#: the three images of Fig. 49
VIEWS = ("regular", "far-range indirect", "chosen delay")


def weber_contrast(structure: xr.DataArray, surround: xr.DataArray) -> xr.DataArray:
    """|μ_surround − μ_structure| / μ_surround (element-wise; NaN where the surround is not bright)."""
    return abs(surround - structure) / surround.where(surround > 0)


def direct_free(delays: np.ndarray, exposure: float, line_time: float) -> np.ndarray:
    """Which delays' frames hold no light from the pixel's own row: |t_d| ≥ (t_e + t_p)/2."""
    return np.abs(delays) >= (exposure + line_time) / 2 - 1e-9


DELAY_CHOICE = CubeKind(
    name="delay_choice",
    description="the delay that shows a structure below the surface best, and its images (§5.4.7)",
    variables={"image": Variable(("view", "row", "col"), units="counts",
                                 long_name="regular, far-range indirect, chosen-delay"),
               "contrast": Variable(("delay",), units="1", long_name="Weber contrast |μ_s − μ_v| / μ_s of the frame"),
               "contrast_of": Variable(("view",), False, units="1", long_name="Weber contrast of each image")},
    coord_units={"delay": TIME_UNITS},
    attrs={"chosen_delay_us": "the delay of the highest contrast, µs"},
)


@stage("choose_delay", kind=DELAY_CHOICE, precheck=label_precheck, identity=label_identity)
def choose_delay(transport: xr.Dataset, /, *, delays: TimeSweep = TimeSweep(start=0, stop=1020, step=17),
                 exposure: Positive = 170.0, structure: str = "vein", surround: str = "skin",
                 labels: Labels = "scene", label_image: StorePath = "", classes: tuple[str, ...] | None = None,
                 min_signal: Fraction = 0.01) -> xr.Dataset:
    """Choose the sync delay that shows a structure below the surface best, and image it (§5.4.7, Fig. 49).

    Parameters
    ----------
    transport : xr.Dataset
        A ``plane_to_ray_transport`` (``demux_plane_to_ray``): ``transport`` over (offset, row, col) [counts], attrs
        ``scan_speed_px_per_us`` and ``line_time_us``.
    delays : dict
        Candidate delays {start, stop, step} [µs] (negative delays look the other way along the scan).
    exposure : float
        The exposure t_e of the frames compared [µs].
    structure, surround : str
        The class names of the structure (darker or brighter) and of what surrounds it, in the labels.
    labels, label_image, classes
        Where the regions come from, as ``train_material_classifier`` takes them: ``scene`` (the simulated scene's
        objects) or ``image`` (an integer label image, its codes named by ``classes``).
    min_signal : float
        Delays whose surround's mean is below this share of its regular-image mean are left out [1].

    Returns
    -------
    xr.Dataset
        A ``delay_choice`` cube: ``image`` over (view, row, col) [counts]: the regular image (all the transport's
        light), the far-range indirect image (all light from beyond the direct band, |o| ≥ v_p·(t_e + t_p)/2) and the
        frame at the chosen delay; ``contrast`` over delay (NaN where a delay is not a candidate) and ``contrast_of``
        over view; attrs ``chosen_delay_us`` (the true delay: the transport's offsets are true ones) and
        ``commanded_delay_us`` (what to set on this rig's controller: chosen minus the calibrated sync offset t_o).

    Raises
    ------
    StageError
        No candidate delay clear of direct light, a structure or surround with no pixel.

    References
    ----------
    Thesis §5.4.7 Visualization of vein.
    """
    require_variables(transport, ("transport",), "choose_delay")
    t = transport["transport"]
    speed, line_time = transport.attrs.get("scan_speed_px_per_us"), transport.attrs.get("line_time_us")
    if "offset" not in t.dims or not speed or line_time is None:
        raise StageError(Problem(f"a plane-to-ray transport over (offset, row, col) with attrs scan_speed_px_per_us "
                                 f"and line_time_us is needed; this one has dims {t.dims}",
                                 fix="wire in the output of demux_plane_to_ray"))
    candidates = delays.values()
    clear = direct_free(candidates, exposure, float(line_time))
    if not clear.any():
        raise StageError(Problem(f"no candidate delay ({candidates[0]:g} … {candidates[-1]:g} µs) is clear of direct "
                                 f"light: |t_d| ≥ (t_e + t_p)/2 = {(exposure + float(line_time)) / 2:g} µs is needed",
                                 fix="sweep delays beyond half the exposure (and line time), or shorten the exposure"))
    codes, names = label_map(transport, labels, label_image, classes, "transport")
    masks = {}
    for role, name in (("structure", structure), ("surround", surround)):
        if name not in names or not (codes == names.index(name) + 1).any():
            raise StageError(Problem(f"the {role} {name!r} has no labelled pixel (classes: {list(names)})",
                                     fix=f"name the {role} by one of the labels' classes"))
        masks[role] = xr.DataArray(codes == names.index(name) + 1, dims=("row", "col"))
    offsets = t["offset"].values
    weights = plane_to_ray_illumination(candidates, np.full(candidates.shape, exposure), offsets,
                                        scan_speed=float(speed), line_time=float(line_time))
    w = xr.DataArray(weights, dims=("delay", "offset"))
    # region means are linear in T: mean over the region first, then the frames' weights (cheap at any size)
    means = {role: t.where(mask).mean(("row", "col")) for role, mask in masks.items()}
    regular = {role: m.sum("offset") for role, m in means.items()}
    curve = {role: xr.dot(w, m, dim="offset") for role, m in means.items()}
    bright_enough = curve["surround"] >= min_signal * regular["surround"]
    contrast = weber_contrast(curve["structure"], curve["surround"]).where(bright_enough & xr.DataArray(
        clear, dims="delay"))
    contrast, bright_enough = xr.concat([contrast, bright_enough.astype(float)], "what").values
    if not np.isfinite(contrast).any():
        raise StageError(Problem(f"at every candidate delay clear of direct light the surround is darker than "
                                 f"{min_signal:.0%} of its regular image", fix="sweep nearer delays"))
    best = int(np.nanargmax(contrast))
    reach = float(speed) * (exposure + float(line_time)) / 2
    images = xr.concat([t.sum("offset"), t.where(abs(t["offset"]) >= reach, 0.0).sum("offset"),
                        xr.dot(w.isel(delay=best), t, dim="offset")], dim="view")
    region = {role: images.where(mask).mean(("row", "col")) for role, mask in masks.items()}
    coords = {"delay": ("delay", candidates, {"units": "us", "long_name": "candidate sync delay t_d"}),
              "view": ("view", list(VIEWS))}
    keep = {k: v for k, v in transport.attrs.items() if k != "selpath_kind"}
    return DELAY_CHOICE.label(xr.Dataset(
        {"image": images.drop_attrs(deep=False), "contrast": ("delay", contrast),
         "contrast_of": weber_contrast(region["structure"], region["surround"]),
         "bright_enough": ("delay", bright_enough.astype(bool),
                           {"long_name": f"surround at least {min_signal:g} of its regular mean"})},
        coords=coords,
        attrs=keep | {"chosen_delay_us": float(candidates[best]),
                      "commanded_delay_us": float(candidates[best]) - float(transport.attrs.get("sync_offset_us", 0.0)),
                      "exposure_us": float(exposure), "structure": structure, "surround": surround,
                      "direct_free_from_us": (exposure + float(line_time)) / 2, "far_range_rows": reach}))
