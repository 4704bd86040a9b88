"""Tomography figures of what was captured and binned, as stages: capture, sinogram, coverage. The figures of
reconstructions (the images, the solver's convergence, volumes) are in
:mod:`selpath.stages.tomography.reconstruction_figures`.

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``, with a one-paragraph
``caption`` attr; how is :mod:`selpath.stages._figures`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Index
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages._figures import FIGURE, as_figure, image_colorbar, panels, pixel_axes, rgba, slice_name
from selpath.stages.tomography.coverage import coverage_model, optimal_light_angle

#: sizes [in] of the figures that are not of the standard size
CAPTURE_SIZE = (9.0, 2.2)


def _draw_sinogram(absorption: np.ndarray, observed: np.ndarray, theta: np.ndarray, x: np.ndarray,
                   unit: str, title: str) -> np.ndarray:
    from matplotlib import colormaps  # matplotlib when drawing, not on import

    fig, (left, right) = panels(1, 2)
    fig.suptitle(title, fontsize=10)
    step_t = (theta[1] - theta[0]) / 2 if theta.size > 1 else 0.5
    step_x = (x[1] - x[0]) / 2 if x.size > 1 else 0.5
    extent = (x[0] - step_x, x[-1] + step_x, theta[-1] + step_t, theta[0] - step_t)
    shown = left.imshow(np.where(observed, absorption, np.nan), aspect="auto", extent=extent,
                        cmap=colormaps["magma"].with_extremes(bad="0.7"), interpolation="nearest")
    fig.colorbar(shown, ax=left, label="total absorption A [1]")
    left.set(xlabel=f"ray position X [{unit}]", ylabel="ray angle θ [degree]")
    left.set_title("(a) A(θ, X); grey: no ray observed", fontsize=9)
    right.imshow(observed, aspect="auto", extent=extent, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    right.set(xlabel=f"ray position X [{unit}]", ylabel="ray angle θ [degree]")
    right.set_title(f"(b) observed bins (white): {observed.mean() * 100:.1f} % of all", fontsize=9)
    return rgba(fig)


@stage("sinogram_figure", kind=FIGURE)
def sinogram_figure(sinogram: xr.Dataset, /, *, slice_index: Index = 0) -> xr.Dataset:
    """The sinogram of one slice beside its mask of observed rays (the missing areas of Fig. 14 / 20).

    Parameters
    ----------
    sinogram : xr.Dataset
        A ``sinogram`` store (``bin_sinogram``): ``absorption`` and ``observed`` over (slice, theta, x).
    slice_index : int
        Position along the sinogram's ``slice`` dim.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §4.2.7 Observation rate of the light path.
    """
    require_variables(sinogram, ("absorption", "observed"), "sinogram_figure")
    one = sinogram.isel(slice=slice_index) if "slice" in sinogram.dims else sinogram
    where = slice_name(sinogram, slice_index)
    light = sinogram.attrs.get("light_angle_deg")
    light_text = f"θ_l = {light:g}°" if light is not None else "θ_l unknown"
    unit = sinogram["x"].attrs.get("units", "")
    caption = f"""Sinogram of {where}, light at {light_text}: (a) the total absorption A = log I_reference − log
        I_target (dimensionless) of every ray, binned by ray angle θ [degree] and signed distance X of the ray
        from the rotation axis [{unit}]; bins no ray reached are grey. (b) the mask of observed bins, with their
        share. A small object traces one sinusoid; the side bands no ray reaches are the missing areas of the
        sinogram. Reproduces thesis Fig. 20 (acquired sinogram, shortest-path measurement) and the missing
        areas of Fig. 14."""
    return as_figure(_draw_sinogram, one["absorption"].data, one["observed"].data, sinogram["theta"].values,
                     sinogram["x"].values, unit, f"sinogram of {where}, light at {light_text}", caption=caption)


def _draw_coverage(measured: np.ndarray | None, analytic: np.ndarray | None, light_angle: float | None) -> np.ndarray:
    fig, ax = panels()
    angles = np.linspace(0, 180, 361)
    for i, (fov, style) in enumerate(((None, "-"), (30.0, "--"), (60.0, ":"))):
        label = "orthographic" if fov is None else f"perspective, FOV = {fov:.0f}°"
        ax.plot(angles, coverage_model(angles, fov)[2], style, color=f"C{i}", label=label)
    for i, fov in enumerate((None, 30.0, 60.0)):
        ax.axvline(optimal_light_angle(fov), color="0.6", lw=0.8, zorder=0,
                   label="optimal θ_l = (180° − FOV) / 2" if i == 0 else None)
    if measured is not None and light_angle is not None:
        ax.plot([light_angle] * len(measured), measured, "ko", label=f"measured ({len(measured)} slice(s))")
        if analytic is not None:
            ax.plot([light_angle] * len(analytic), analytic, "kx", ms=9,
                    label="Eq. 8–19 for this rig (hull radius, camera distance)")
    ax.set(xlabel="light angle θ_l [degree]", ylabel="coverage d_max − d_min [1]", ylim=(0, 1.05), xlim=(0, 180),
           xticks=np.arange(0, 181, 15))
    ax.set_title("coverage of the sinogram versus the light angle θ_l (Eq. 8–19)", fontsize=10)
    ax.legend(fontsize=8, loc="lower left")
    return rgba(fig)


@stage("coverage_figure", kind=FIGURE)
def coverage_figure(coverage: xr.Dataset | None = None, /) -> xr.Dataset:
    """Coverage versus θ_l for orthographic and perspective (FOV 30°, 60°) cameras, with measured points.

    Parameters
    ----------
    coverage : xr.Dataset or None
        A ``coverage`` store (the ``coverage`` stage): measured ``coverage`` per slice, and
        ``analytic_coverage`` where present, drawn at its ``light_angle_deg``; None: the model curves only.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §4.2.7 Observation rate of the light path.
    """
    caption = """Coverage d_max − d_min (dimensionless share of the sinogram's X range that holds observed rays)
        versus the light angle θ_l [degree], by the closed forms of Eq. 8–19 for a cylinder seen by an
        orthographic camera and by perspective cameras whose field of view spans 30° and 60°; grey vertical
        lines mark each camera's optimal θ_l = (180° − FOV) / 2, the largest coverage that keeps the
        sinogram's centre. Reproduces thesis Fig. 16."""
    if coverage is None:
        return as_figure(_draw_coverage, None, None, None, caption=caption)
    light = coverage.attrs.get("light_angle_deg")
    caption += f""" Dots: the coverage measured in each reconstructed slice at θ_l = {light}°; crosses: Eq. 8–19
        for a cylinder of the hull's mean radius at this rig's camera distance."""
    analytic = coverage["analytic_coverage"].data if "analytic_coverage" in coverage else None
    return as_figure(_draw_coverage, coverage["coverage"].data, analytic, light, caption=caption)


def _draw_capture(frame: np.ndarray, backlit: np.ndarray, angle: float) -> np.ndarray:
    fig, axes = panels(1, 2, size=CAPTURE_SIZE)
    for ax, image, title in ((axes[0], frame, f"(a) target frame, stage angle φ = {angle:g}°"),
                             (axes[1], backlit, f"(b) backlit frame (silhouette), φ = {angle:g}°")):
        shown = ax.imshow(image, cmap="gray", vmin=0, vmax=max(float(np.nanmax(image)), 1e-12),
                          interpolation="nearest")
        image_colorbar(fig, ax, shown, "counts")
        ax.set_title(title, fontsize=9)
        pixel_axes(ax, ylabel="row [px]")
    return rgba(fig)


@stage("capture_figure", kind=FIGURE)
def capture_figure(capture: xr.Dataset, /, *, angle_index: Index = 0) -> xr.Dataset:
    """One target frame beside its backlit frame.

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` store (``acquire_tomography``): ``target`` and ``backlit`` frames over
        (angle, row, col).
    angle_index : int
        Position along the capture's ``angle`` dim.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §4.2.5 Setup of the measurement.
    """
    require_variables(capture, ("target", "backlit"), "capture_figure")
    one = capture.isel(angle=angle_index)
    angle = float(one["angle"])
    light = capture.attrs.get("light_angle_deg")
    light_text = f" with the light at θ_l = {light:g}°" if light is not None else ""
    caption = f"""Raw frames of the tomography capture at stage angle φ = {angle:g}° (angle index {angle_index}),
        in sensor counts: (a) the target frame{light_text}, the diffuse glow where the beam's rays leave the
        object, from which the total absorption of Eq. 3 is taken against the reference frame; (b) the backlit
        frame, whose dark silhouette bounds the object and feeds the visual hull. Axes are camera pixels.
        The measurement of thesis Fig. 13 and 19; cf. the camera projections of Fig. 24."""
    return as_figure(_draw_capture, one["target"].data, one["backlit"].data, angle, caption=caption,
                     size=CAPTURE_SIZE)
