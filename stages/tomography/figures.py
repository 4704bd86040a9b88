"""Tomography figures as stages (capture, sinogram, coverage, reconstructions, convergence).

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``; how is
:mod:`stages._figures`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.constraints import Index
from pipeline.registry import stage
from stages._common import require_variables
from stages._figures import as_figure, panels, rgba
from stages.tomography.sinogram import coverage_model, optimal_light_angle


def _draw_sinogram(absorption: np.ndarray, observed: np.ndarray, theta: np.ndarray, x: np.ndarray,
                   unit: str, title: str) -> np.ndarray:
    fig, (left, right) = panels(1, 2)
    extent = (x[0], x[-1], theta[-1], theta[0])
    shown = left.imshow(np.where(observed, absorption, np.nan), aspect="auto", extent=extent, cmap="magma")
    fig.colorbar(shown, ax=left, label="total absorption A")
    left.set(xlabel=f"X [{unit}]", ylabel="θ [degree]", title=title)
    right.imshow(observed, aspect="auto", extent=extent, cmap="gray", vmin=0, vmax=1)
    right.set(xlabel=f"X [{unit}]", title=f"observed rays (white): {observed.mean() * 100:.1f}% of bins")
    return rgba(fig)


@stage("sinogram_figure")
def sinogram_figure(sinogram: xr.Dataset, /, *, slice_index: Index = 0) -> xr.Dataset:
    """The sinogram of one slice beside its mask of observed rays (the missing areas of Fig. 14 / 20).

    Parameters
    ----------
    slice_index : int
        Position along the sinogram's ``slice`` dim.
    """
    require_variables(sinogram, ("absorption", "observed"), "sinogram_figure")
    one = sinogram.isel(slice=slice_index) if "slice" in sinogram.dims else sinogram
    title = f"sinogram, θ_l = {sinogram.attrs.get('light_angle_deg', '?')}°"
    return as_figure(_draw_sinogram, one["absorption"].data, one["observed"].data, sinogram["theta"].values,
                      sinogram["x"].values, sinogram["x"].attrs.get("units", ""), title)


def _draw_coverage(measured: np.ndarray | None, light_angle: float | None) -> np.ndarray:
    fig, ax = panels()
    angles = np.linspace(0, 180, 361)
    for fov, style in ((None, "-"), (30.0, "--"), (60.0, ":")):
        label = "orthographic" if fov is None else f"perspective, FOV = {fov:.0f}°"
        ax.plot(angles, coverage_model(angles, fov)[2], style, label=label)
        ax.axvline(optimal_light_angle(fov), color="0.8", lw=0.8)
    if measured is not None and light_angle is not None:
        ax.plot([light_angle] * len(measured), measured, "ko", label="measured")
    ax.set(xlabel="light angle θ_l [degree]", ylabel="coverage d_max − d_min", ylim=(0, 1.05), xlim=(0, 180),
           title="coverage of the sinogram versus θ_l (Eq. 8–19, thesis Fig. 16)")
    ax.legend()
    return rgba(fig)


@stage("coverage_figure")
def coverage_figure(coverage: xr.Dataset | None = None, /) -> xr.Dataset:
    """Coverage versus θ_l for orthographic and perspective (FOV 30°, 60°) cameras, with measured points."""
    if coverage is None:
        return as_figure(_draw_coverage, None, None)
    return as_figure(_draw_coverage, coverage["coverage"].data, coverage.attrs.get("light_angle_deg"))


def _draw_capture(frame: np.ndarray, backlit: np.ndarray, angle: float) -> np.ndarray:
    fig, (left, right) = panels(1, 2)
    shown = left.imshow(frame, cmap="gray")
    fig.colorbar(shown, ax=left, label="counts")
    left.set(title=f"target frame at stage angle {angle:g}° (beam exit glow)", xlabel="col", ylabel="row")
    right.imshow(backlit, cmap="gray")
    right.set(title="backlit frame (silhouette)", xlabel="col")
    return rgba(fig)


@stage("capture_figure")
def capture_figure(capture: xr.Dataset, /, *, angle_index: Index = 0) -> xr.Dataset:
    """One target frame beside its backlit frame.

    Parameters
    ----------
    angle_index : int
        Position along the capture's ``angle`` dim.
    """
    require_variables(capture, ("target", "backlit"), "capture_figure")
    one = capture.isel(angle=angle_index)
    return as_figure(_draw_capture, one["target"].data, one["backlit"].data, float(one["angle"]))


def _draw_reconstructions(images: list[np.ndarray], titles: list[str], truth: np.ndarray | None,
                          extent: tuple[float, float, float, float], unit: str) -> np.ndarray:
    count = len(images) + (truth is not None)
    fig, axes = panels(1, count)
    top = max(float(np.nanmax(truth)) if truth is not None else 0.0, *(float(np.nanpercentile(i, 99.5))
                                                                      for i in images))
    for ax, image, title in zip(axes, ([truth] if truth is not None else []) + images,
                                (["truth"] if truth is not None else []) + titles, strict=True):
        shown = ax.imshow(image, origin="lower", extent=extent, cmap="magma", vmin=0, vmax=top)
        if truth is not None and title != "truth":
            rmse = float(np.sqrt(np.nanmean((image - truth) ** 2)))
            title = f"{title}\nRMSE {rmse:.2e}, max |err| {float(np.nanmax(np.abs(image - truth))):.2e}"
        ax.set_title(title, fontsize=8)
        ax.set(xlabel=f"x [{unit}]")
    axes[0].set(ylabel=f"y [{unit}]")
    fig.colorbar(shown, ax=axes, label=f"σ [1/{unit}]", shrink=0.8)
    return rgba(fig)


@stage("reconstruction_figure")
def reconstruction_figure(fbp: xr.Dataset, optimised: xr.Dataset, truth: xr.Dataset | None = None, /, *,
                          slice_index: Index = 0) -> xr.Dataset:
    """FBP beside the constrained optimisation (and the truth, with errors, when given), as in Fig. 18/21.

    Parameters
    ----------
    slice_index : int
        Position along the reconstructions' ``slice`` dim.
    """
    images = [r["sigma"].isel(slice=slice_index).data for r in (fbp, optimised)]
    centres = fbp["x"].values
    half = (centres[1] - centres[0]) / 2
    extent = (centres[0] - half, centres[-1] + half, centres[0] - half, centres[-1] + half)
    reference = truth["sigma"].isel(slice=0 if truth.sizes.get("slice", 1) == 1 else slice_index).data \
        if truth is not None else None
    return as_figure(_draw_reconstructions, images, ["FBP", "optimisation (box + TV, ADMM)"], reference, extent,
                      fbp["x"].attrs.get("units", ""))


def _draw_convergence(objective: np.ndarray, primal: np.ndarray, dual: np.ndarray) -> np.ndarray:
    fig, (left, right) = panels(1, 2)
    for k in range(objective.shape[0]):
        left.semilogy(objective[k], label=f"slice {k}")
        right.semilogy(primal[k], "-", label=f"primal, slice {k}")
        right.semilogy(dual[k], "--", label=f"dual, slice {k}")
    left.set(xlabel="ADMM iteration", ylabel="objective ½‖M(Rσ−A)‖² + λ TV(σ)", title="objective")
    right.set(xlabel="ADMM iteration", ylabel="relative residual", title="residuals (stop at tol)")
    left.legend(fontsize=7)
    right.legend(fontsize=7)
    return rgba(fig)


@stage("convergence_figure")
def convergence_figure(optimised: xr.Dataset, /) -> xr.Dataset:
    """Objective and relative primal/dual residuals per ADMM iteration, every slice."""
    require_variables(optimised, ("objective", "primal_residual", "dual_residual"), "convergence_figure")
    return as_figure(_draw_convergence, optimised["objective"].data, optimised["primal_residual"].data,
                      optimised["dual_residual"].data)
