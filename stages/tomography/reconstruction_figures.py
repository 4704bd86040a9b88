"""Tomography figures of reconstructions, as stages: the images beside the truth and their errors, the solver's
convergence, and sections of a volume. The figures of what was captured and binned are in
:mod:`selpath.stages.tomography.figures`.

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``, with a one-paragraph
``caption`` attr; how is :mod:`selpath.stages._figures`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Index
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import in_length
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages._figures import FIGURE, as_figure, panels, pixel_axes, rgba, shared_colorbar, slice_name

#: inches per column of the reconstruction figure, and its height with and without the truth's row of errors
RECONSTRUCTION_COLUMN, RECONSTRUCTION_HEIGHT, RECONSTRUCTION_HEIGHT_NO_TRUTH = 3.0, 6.0, 3.2


def reconstruction_size(reconstructions: int, truth: bool) -> tuple[float, float]:
    """The reconstruction figure's size: a column per reconstruction and one for the truth (or the overview)."""
    height = RECONSTRUCTION_HEIGHT if truth else RECONSTRUCTION_HEIGHT_NO_TRUTH
    return RECONSTRUCTION_COLUMN * (1 + reconstructions), height


def object_window(support: np.ndarray, *, margin: float = 0.3, min_cells: int = 8) -> tuple[slice, slice]:
    """A square window (rows, cols) around the True cells of ``support``, widened by ``margin`` of its side on
    each side and at least ``min_cells`` wide; the whole grid when ``support`` is empty."""
    ny, nx = support.shape
    if not support.any():
        return slice(0, ny), slice(0, nx)
    rows, cols = np.flatnonzero(support.any(axis=1)), np.flatnonzero(support.any(axis=0))
    span = max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1
    side = min(max(int(np.ceil(span * (1 + 2 * margin))), min_cells), ny, nx)

    def window(low: int, high: int, size: int) -> slice:
        start = int(round((low + high) / 2 - (side - 1) / 2))
        start = min(max(start, 0), size - side)
        return slice(start, start + side)

    return window(rows[0], rows[-1], ny), window(cols[0], cols[-1], nx)


def _draw_reconstructions(images: list[np.ndarray], titles: list[str], truth: np.ndarray | None,
                          reliable: np.ndarray | None, x: np.ndarray, y: np.ndarray, unit: str, sigma_unit: str,
                          title: str) -> np.ndarray:
    images = [np.asarray(i, dtype=float) for i in images]
    peak = float(np.nanmax(truth)) if truth is not None and np.nanmax(truth) > 0 else \
        max(float(np.nanpercentile(i, 99.5)) for i in images)
    peak = peak if peak > 0 else 1.0
    # the object: where the truth is (≥ 10 % of its peak) or a reconstruction is strong (≥ half of it)
    support = np.zeros(images[0].shape, bool) if truth is None else np.nan_to_num(truth) >= 0.1 * peak
    for image in images:
        support |= np.nan_to_num(image) >= 0.5 * peak
    rows, cols = object_window(support)
    hx, hy = (x[1] - x[0]) / 2 if x.size > 1 else 0.5, (y[1] - y[0]) / 2 if y.size > 1 else 0.5
    extent = (x[0] - hx, x[-1] + hx, y[0] - hy, y[-1] + hy)
    window = (x[cols.start] - hx, x[cols.stop - 1] + hx, y[rows.start] - hy, y[rows.stop - 1] + hy)

    def draw(ax, image, cmap, vmin, vmax, label, crop=True):
        shown = ax.imshow(image, origin="lower", extent=extent, cmap=cmap, vmin=vmin, vmax=vmax,
                          interpolation="nearest")
        if crop:
            ax.set(xlim=window[:2], ylim=window[2:])
        ax.set_title(label, fontsize=8)
        ax.set_xlabel(f"x [{unit}]", fontsize=8)
        ax.set_ylabel(f"y [{unit}]", fontsize=8)
        ax.tick_params(labelsize=7)
        return shown

    def overview(ax):
        from matplotlib.patches import Rectangle  # matplotlib when drawing, not on import

        draw(ax, images[0], "magma", 0, peak, f"whole slice, {titles[0].split(') ')[-1]}; box: window", crop=False)
        ax.add_patch(Rectangle((window[0], window[2]), window[1] - window[0], window[3] - window[2], fill=False,
                               edgecolor="tab:cyan", lw=1.2))
        if reliable is not None and reliable.any() and not reliable.all():
            ax.contour(x, y, reliable.astype(float), levels=[0.5], colors="tab:blue", linewidths=0.8)

    columns = 1 + len(images)
    if truth is None:
        fig, axes = panels(1, columns, size=reconstruction_size(len(images), False))
        fig.suptitle(title, fontsize=10)
        overview(axes[0])
        for ax, image, label in zip(axes[1:], images, titles, strict=True):
            shown = draw(ax, image, "magma", 0, peak, label)
        shared_colorbar(fig, axes, shown, f"σ [{sigma_unit}]", shrink=0.9)
        return rgba(fig)

    fig, axes = panels(2, columns, size=reconstruction_size(len(images), True))
    fig.suptitle(title, fontsize=10)
    for ax, image, label in zip(axes[0], [truth, *images], ["(a) truth", *titles], strict=True):
        shown = draw(ax, image, "magma", 0, peak, label)
    shared_colorbar(fig, axes[0], shown, f"σ [{sigma_unit}]", shrink=0.9)
    letters = "abcdefghij"[columns:]  # after the truth and the reconstructions: the overview, then the errors
    overview(axes[1, 0])
    axes[1, 0].set_title(f"({letters[0]}) {axes[1, 0].get_title()}", fontsize=8)
    errors = [image - truth for image in images]
    inside = [e[rows, cols] for e in errors]
    limit = max(float(np.nanmax(np.abs(e))) if np.isfinite(e).any() else 0.0 for e in inside)
    limit = limit if limit > 0 else 0.01 * peak  # exact reconstructions: a scale of 1 % of the peak
    for ax, error, label, letter in zip(axes[1, 1:], errors, titles, letters[1:], strict=False):
        rmse = float(np.sqrt(np.nanmean(error ** 2)))
        worst = float(np.nanmax(np.abs(error)))
        name = label.split(") ", 1)[-1].split(" (")[0]
        text = f"({letter}) {name} − truth, whole slice:\nRMSE {rmse:.2e}, max |error| {worst:.2e} {sigma_unit}"
        shown = draw(ax, error, "RdBu_r", -limit, limit, text)
    shared_colorbar(fig, axes[1], shown, f"error Δσ [{sigma_unit}]", shrink=0.9)
    return rgba(fig)


@stage("reconstruction_figure", kind=FIGURE)
def reconstruction_figure(fbp: xr.Dataset, optimised: xr.Dataset, truth: xr.Dataset | None = None,
                          bundles: xr.Dataset | None = None, /, *, slice_index: Index = 0) -> xr.Dataset:
    """FBP beside the constrained optimisation (and the truth, with errors, when given), as in Fig. 18/21; with
    ``bundles``, the path-bundle reconstruction through scattering beside them (#27: both models side by side).

    Parameters
    ----------
    fbp : xr.Dataset
        A ``reconstruction`` store made by ``fbp``: ``sigma`` (and ``reliable``) over (slice, y, x).
    optimised : xr.Dataset
        A ``reconstruction`` store made by ``reconstruct_tv`` on the same grid.
    truth : xr.Dataset or None
        A ``reconstruction`` store holding the true σ on the same grid (``phantom_truth``), of one slice or
        of every reconstructed slice (matched by the ``slice`` coordinate); None: no truth, no error panels.
    bundles : xr.Dataset or None
        A ``reconstruction`` store made by ``reconstruct_scattering`` on the same grid (its attrs ``sigma_s``
        [1/length unit] and ``tv_weight`` title the panel); None: the two shortest-path reconstructions only.
    slice_index : int
        Position along the reconstructions' ``slice`` dim.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §4.4.1 Appropriate setup of the measurement.
    """
    given = [fbp, optimised] + ([] if bundles is None else [bundles])
    for reconstruction in given:
        require_variables(reconstruction, ("sigma",), "reconstruction_figure")
    images = [r["sigma"].isel(slice=slice_index).data if "slice" in r["sigma"].dims else r["sigma"].data
              for r in given]
    grids = [image.shape[-2:] for image in images]
    if len(set(grids)) > 1:
        raise StageError(Problem(f"the reconstructions' grids differ: (y, x) = {', '.join(map(str, grids))} for "
                                 f"{', '.join(['fbp', 'optimised', 'bundles'][:len(grids)])}",
                                 fix="reconstruct on one grid (the same sinogram and n_pixels)"))
    x = fbp["x"].values
    y = fbp["y"].values if "y" in fbp.coords else x
    unit = fbp["x"].attrs.get("units", "")
    sigma_unit = fbp["sigma"].attrs.get("units") or (in_length("1/{length}", unit) if unit else "1/length")
    reference = None
    if truth is not None:
        require_variables(truth, ("sigma",), "reconstruction_figure")
        sigma = truth["sigma"]
        if "slice" in sigma.dims and sigma.sizes["slice"] == 1:
            sigma = sigma.isel(slice=0)
        elif "slice" in sigma.dims and "slice" in sigma.coords and "slice" in fbp.coords:
            sigma = sigma.sel(slice=fbp["slice"].values[slice_index])
        elif "slice" in sigma.dims:
            sigma = sigma.isel(slice=slice_index)
        reference = sigma.data
    reliable = None
    if "reliable" in fbp:
        reliable = fbp["reliable"].isel(slice=slice_index).data if "slice" in fbp["reliable"].dims \
            else fbp["reliable"].data
    where = slice_name(fbp, slice_index)
    tv = optimised.attrs.get("tv_weight")
    titles = ["(b) FBP", "(c) optimisation (box + TV" + (f", λ = {tv:g})" if tv is not None else ")")]
    bundle_text = ""
    if bundles is not None:
        sigma_s, bundle_tv = bundles.attrs.get("sigma_s"), bundles.attrs.get("tv_weight")
        settings = ", ".join(([f"σ_s = {sigma_s:g} {sigma_unit}"] if sigma_s is not None else [])
                             + ([f"λ = {bundle_tv:g}"] if bundle_tv is not None else []))
        titles.append("(d) path bundles" + (f" ({settings})" if settings else ""))
        bundle_text = """ and (d) the path-bundle reconstruction through scattering (reconstruct_scattering: each
            sinogram bin modelled as the mean transmittance over photon walks in the hull at the scattering
            coefficient σ_s, fitted by L-BFGS-B with the same box and TV)"""
    light = fbp.attrs.get("light_angle_deg")
    title = f"absorption coefficient σ [{sigma_unit}], {where}" + (f", θ_l = {light:g}°" if light is not None else "")
    window = ("a window around the object (where the truth is at least 10 % of its peak or a reconstruction at "
              "least half of it, widened by 30 % on each side)")
    overview, error_letters = ("(e)", "(f–h)") if bundles is not None else ("(d)", "(e, f)")
    if truth is not None:
        shown = f"""(a) the true σ, (b) filtered back projection (FBP) and (c) the constrained optimisation of
            Eq. 20 (box 0 ≤ σ ≤ σ_max, σ = 0 outside the hull, total variation, by ADMM){bundle_text}, on one
            colour scale from 0 to the truth's peak; {overview} the whole slice by FBP"""
        errors = f"""{error_letters} each reconstruction minus the truth, on one diverging colour scale symmetric
            about 0; their titles give the RMSE and the largest absolute error over the whole slice (as the
            reconstruction_error stage computes them), in {sigma_unit}."""
    else:
        shown = f"""(b) filtered back projection (FBP) and (c) the constrained optimisation of Eq. 20 (box 0 ≤ σ ≤
            σ_max, σ = 0 outside the hull, total variation, by ADMM){bundle_text}, on one colour scale from 0 to
            the reconstructions' peak; (a) the whole slice by FBP"""
        errors = "No truth was given, so no errors are shown."
    caption = f"""Reconstructed absorption coefficient σ [{sigma_unit}] of {where}, axes in {unit}, in {window}:
        {shown}, with that window boxed and, in blue, the boundary of the cells every ray of which was observed
        (cf. the blue line of Fig. 21). {errors} Reproduces thesis Fig. 21 (expected distribution, FBP and
        optimisation) and the error maps of Fig. 18 with Table 1."""
    return as_figure(_draw_reconstructions, images, titles, reference, reliable, x, y, unit, sigma_unit, title,
                     caption=caption, size=reconstruction_size(len(images), truth is not None))


def _draw_convergence(objective: np.ndarray, primal: np.ndarray, dual: np.ndarray, iterations: np.ndarray,
                      converged: np.ndarray, names: list[str], tol: float | None, tv: float | None) -> np.ndarray:
    fig, (left, right) = panels(1, 2)
    for k in range(objective.shape[0]):
        stop = f", {int(iterations[k])} iterations" if iterations is not None else ""
        stop += ("" if converged[k] else ", not converged") if converged is not None else ""
        left.semilogy(objective[k], color=f"C{k % 10}", label=f"{names[k]}{stop}")
        right.semilogy(primal[k], "-", color=f"C{k % 10}", label=f"primal, {names[k]}")
        right.semilogy(dual[k], "--", color=f"C{k % 10}", label=f"dual, {names[k]}")
    if tol is not None:
        right.axhline(tol, color="0.4", lw=0.8, ls=":", label=f"tol = {tol:g}")
    weight = f", λ = {tv:g}" if tv is not None else ""
    left.set(xlabel="ADMM iteration", ylabel="objective [1]")
    left.set_title(f"(a) objective ½‖M(Rσ − A)‖² + λ·TV(σ){weight}", fontsize=9)
    right.set(xlabel="ADMM iteration", ylabel="relative residual [1]")
    right.set_title("(b) relative primal (—) and dual (--) residuals", fontsize=9)
    left.legend(fontsize=7)
    right.legend(fontsize=7, ncols=2 if objective.shape[0] > 2 else 1)
    return rgba(fig)


@stage("convergence_figure", kind=FIGURE)
def convergence_figure(optimised: xr.Dataset, /) -> xr.Dataset:
    """Objective and relative primal/dual residuals per ADMM iteration, every slice.

    Parameters
    ----------
    optimised : xr.Dataset
        A ``reconstruction`` store made by ``reconstruct_tv``: ``objective``, ``primal_residual`` and
        ``dual_residual`` over (slice, iteration), and ``iterations`` and ``converged`` per slice where present.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §4.3.1 Formulation as an optimization problem.
    """
    require_variables(optimised, ("objective", "primal_residual", "dual_residual"), "convergence_figure")
    count = optimised["objective"].shape[0]
    names = [f"row {v:g}" for v in optimised["slice"].values] if "slice" in optimised.coords \
        else [f"slice {k}" for k in range(count)]
    tol, tv = optimised.attrs.get("tol"), optimised.attrs.get("tv_weight")
    caption = f"""Convergence of the constrained TV reconstruction (Eq. 20, by ADMM) for each of the {count}
        reconstructed slice(s), named by camera row: (a) the objective ½‖M(Rσ − A)‖² + λ·TV(σ) (observed rays
        only, λ = {tv if tv is not None else "?"}), dimensionless as the absorption A, (b) the relative primal
        and dual residuals (dimensionless), which stop the iterations once both are below
        tol = {tol if tol is not None else "?"} (dotted line); the legend gives each slice's iterations and
        whether it converged. The thesis shows no such figure; it documents the optimisation behind Fig. 18 and 21."""
    stats = [optimised[v].data if v in optimised else None for v in ("iterations", "converged")]
    return as_figure(_draw_convergence, optimised["objective"].data, optimised["primal_residual"].data,
                     optimised["dual_residual"].data, *stats, names, tol, tv, caption=caption)


#: size [in] of the volume figure with and without a truth row
VOLUME_SIZE, VOLUME_SIZE_NO_TRUTH = (9.0, 4.5), (9.0, 2.5)


def _volume_views(sigma: xr.DataArray, at_slice: int, y: float, x: float) -> list:
    """The three sections through slice ``at_slice`` and the grid row and column nearest ``y`` and ``x``, and the
    maximum along z, each a (lazy) 2-D array."""
    return [sigma.isel(slice=at_slice).data, sigma.sel(y=y, method="nearest").data,
            sigma.sel(x=x, method="nearest").data, sigma.max("slice").data]


def upright(section: np.ndarray, z: np.ndarray) -> np.ndarray:
    """A vertical section (slice, …) with its rows ordered from the highest z to the lowest, as drawn (origin upper)."""
    return section if z[0] >= z[-1] else section[::-1]


def _draw_volume(views: list, titles: list[str], rows: list[str], x: np.ndarray, y: np.ndarray, z: np.ndarray,
                 unit: str, sigma_unit: str, size: tuple[float, float]) -> np.ndarray:
    fig, axes = panels(len(rows), 4, size=size, squeeze=False)
    dx, dy, dz = (x[1] - x[0]) / 2, (y[1] - y[0]) / 2, abs(z[0] - z[-1]) / max(len(z) - 1, 1) / 2
    top, bottom = max(z[0], z[-1]) + dz, min(z[0], z[-1]) - dz
    extents = [(x[0] - dx, x[-1] + dx, y[0] - dy, y[-1] + dy), (x[0] - dx, x[-1] + dx, bottom, top),
               (y[0] - dy, y[-1] + dy, bottom, top), (x[0] - dx, x[-1] + dx, y[0] - dy, y[-1] + dy)]
    labels = [("x", "y"), ("x", "z"), ("y", "z"), ("x", "y")]
    vmax = max(float(np.nanmax(v)) for v in views) or 1.0
    for r, name in enumerate(rows):
        for c in range(4):
            ax, image = axes[r, c], np.asarray(views[r * 4 + c])
            image = upright(image, z) if c in (1, 2) else image
            origin = "lower" if c in (0, 3) else "upper"
            shown = ax.imshow(image, extent=extents[c], origin=origin, cmap="magma", vmin=0, vmax=vmax,
                              interpolation="nearest", aspect="equal")
            pixel_axes(ax, f"{labels[c][0]} [{unit}]", f"{labels[c][1]} [{unit}]", 7)
            ax.set_title(f"({'abcdefgh'[r * 4 + c]}) {name}: {titles[c]}", fontsize=8)
    shared_colorbar(fig, axes, shown, f"σ [{sigma_unit}]")
    return rgba(fig)


@stage("volume_figure", kind=FIGURE)
def volume_figure(reconstruction: xr.Dataset, truth: xr.Dataset | None = None, /, *,
                  at: tuple[float, float, float] | None = None) -> xr.Dataset:
    """A reconstructed volume at a glance: three orthogonal sections and the maximum-intensity projection along z.

    Lazy and bounded in memory: the figure's task reads the three sections and reduces the volume along z slice
    chunk by slice chunk, never the whole volume at once.

    Parameters
    ----------
    reconstruction : xr.Dataset
        A ``reconstruction`` store (``fbp`` or ``reconstruct_tv``) of at least 2 slices: ``sigma`` over (slice, y, x)
        with the slices' heights ``z`` [the x coordinate's length unit] (``bin_sinogram`` gives them).
    truth : xr.Dataset or None
        The same grid's truth (``phantom_truth``), drawn as a second row on the same colour scale; None: none.
    at : (float, float, float) or None
        (x, y, z) [length unit] where the sections cross; the nearest slice, row and column are drawn. None: the
        rotation axis (x = y = 0) at the middle slice's height.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §4.4.2 Experiment on a real object.
    """
    volumes = {"reconstruction": reconstruction} | ({"truth": truth} if truth is not None else {})
    for name, volume in volumes.items():
        require_variables(volume, ("sigma",), f"volume_figure: {name}")
        if "slice" not in volume["sigma"].dims or volume.sizes["slice"] < 2:
            count = volume.sizes.get("slice", 1)
            raise StageError(Problem(
                f"volume_figure: the {name} has {count} slice{'s' if count != 1 else ''}; a volume needs the "
                "object's height covered by at least 2", fix="capture with a light sheet (light kind 'sheet'), which "
                "lights every camera row's slice; a beam lights one"))
        if "z" not in volume.coords:
            raise StageError(Problem(f"volume_figure: the {name}'s slices have no height z", fix="reconstruct it "
                                     "from a sinogram binned by this version's bin_sinogram, which carries z"))
    sigma = reconstruction["sigma"]
    if truth is not None and (truth.sizes["slice"], truth.sizes["y"]) != (sigma.sizes["slice"], sigma.sizes["y"]):
        raise StageError(Problem("volume_figure: the truth's grid differs from the reconstruction's",
                                 fix="make the truth with phantom_truth from the reconstruction's sinogram"))
    z = sigma["z"].values
    point = tuple(at) if at is not None else (0.0, 0.0, float(z[len(z) // 2]))
    at_slice = int(np.abs(z - point[2]).argmin())
    near = (float(sigma["x"].sel(x=point[0], method="nearest")), float(sigma["y"].sel(y=point[1], method="nearest")),
            float(z[at_slice]))
    views = [v for volume in volumes.values() for v in _volume_views(volume["sigma"], at_slice, near[1], near[0])]
    unit = sigma["x"].attrs.get("units", "px")
    sigma_unit = sigma.attrs.get("units", in_length("1/{length}", unit))
    titles = [f"z = {near[2]:.3g}", f"y = {near[1]:.3g}", f"x = {near[0]:.3g}", "maximum along z"]
    rows = [{"reconstruction": reconstruction.attrs.get("method", "reconstruction"), "truth": "truth"}[n]
            for n in volumes]
    caption = f"""Absorption coefficient σ [{sigma_unit}] of a reconstructed volume of {sigma.sizes['slice']} slices
        ({rows[0]}{' above, the truth below' if truth is not None else ''}), axes in {unit}: (a) the horizontal
        section at height z, (b) the vertical section x–z at y and (c) y–z at x, through ({near[0]:.3g}, {near[1]:.3g},
        {near[2]:.3g}) {unit}, and (d) the maximum-intensity projection along z, all on one colour scale from 0;
        z is each slice's height at the rotation axis, up on the page. The thesis shows single slices (Fig. 18, 21);
        this figure shows the volumes a light sheet (a beam scanned in height) gives."""
    size = VOLUME_SIZE if truth is not None else VOLUME_SIZE_NO_TRUTH
    return as_figure(_draw_volume, views, titles, rows, sigma["x"].values, sigma["y"].values, z, unit, sigma_unit,
                     size, caption=caption, size=size)
