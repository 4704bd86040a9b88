"""Figures of what the transport says about materials and what lies below a surface, as stages (§5.4.7–5.4.10):
Fig. 49 vein imaging at the chosen delay, Fig. 50 appearance capture, Figs. 51–52 material recognition, Fig. 53 the
material atlas.

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``, with a one-paragraph
``caption`` attr; how is :mod:`selpath.stages._figures`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages._figures import FIGURE, as_figure, panels, pixel_axes, rgba
from selpath.stages.procam.figures import display_top

#: the material figure's size [in]: regular image, mean profiles, label map, confusion matrix
MATERIAL_SIZE = (12.0, 3.0)


def _draw_materials(image, delays, mean, names, label, hidden, confusion, brightness_accuracy,
                    objects=None) -> np.ndarray:
    from matplotlib.colors import ListedColormap

    fig, axes = panels(1, 4, size=MATERIAL_SIZE, width_ratios=[1.3, 1.1, 1.3, 1.0])
    colours = [f"C{k % 10}" for k in range(len(names))]
    axes[0].imshow(image, cmap="gray", vmin=0, vmax=display_top(image), interpolation="nearest")
    axes[0].set_title("(a) regular image", fontsize=8)
    pixel_axes(axes[0], fontsize=7)
    for k, name in enumerate(names):
        axes[1].plot(delays, mean[k], color=colours[k], label=name, lw=1.2)
    axes[1].set(xlabel="sync delay t_d [µs]", ylabel="profile / its area")
    axes[1].set_title("(b) mean delay profiles (training)", fontsize=8)
    axes[1].legend(fontsize=6)
    axes[1].tick_params(labelsize=7)
    axes[1].xaxis.label.set_size(7)
    axes[1].yaxis.label.set_size(7)
    shown = np.ma.masked_where((label < 0) | hidden, label)
    axes[2].imshow(shown, cmap=ListedColormap(colours), vmin=-0.5, vmax=len(names) - 0.5, interpolation="nearest")
    axes[2].set_facecolor("black")
    if objects is not None and (objects > 0).any():  # each object's outline
        axes[2].contour(objects > 0, levels=[0.5], colors="white", linewidths=0.6)
    axes[2].set_title("(c) classified by delay profile", fontsize=8)
    pixel_axes(axes[2], ylabel=None, fontsize=7)
    if confusion is None:
        axes[3].text(0.5, 0.5, "no labels:\nnot scored", ha="center", va="center", fontsize=8)
        axes[3].set_axis_off()
    else:
        rows = confusion / np.maximum(confusion.sum(axis=1, keepdims=True), 1)
        axes[3].imshow(rows, cmap="Blues", vmin=0, vmax=1)
        for (i, j), value in np.ndenumerate(rows):
            axes[3].text(j, i, f"{100 * value:.1f}", ha="center", va="center", fontsize=6,
                         color="white" if value > 0.6 else "black")
        ticks = range(len(names))
        axes[3].set_xticks(ticks, names, rotation=45, ha="right", fontsize=6)
        axes[3].set_yticks(ticks, names, fontsize=6)
        axes[3].set_xlabel("predicted", fontsize=7)
        axes[3].set_title(f"(d) confusion [%]; brightness: {np.nanmean(brightness_accuracy):.0%}", fontsize=8)
    return rgba(fig)


@stage("material_figure", kind=FIGURE)
def material_figure(classification: xr.Dataset, classifier: xr.Dataset, /) -> xr.Dataset:
    """Figs. 51–52: the regular image, the classes' mean delay profiles, the pixels classified, the confusion matrix.

    Parameters
    ----------
    classification : xr.Dataset
        A ``material_classification`` store (``classify_materials``); scored (with its ``confusion``) or not.
    classifier : xr.Dataset
        The ``material_classifier`` store that classified it (its mean training profiles are drawn).

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.9 Material Recognition of Subsurface Scattering.
    """
    require_variables(classification, ("label", "image"), "material_figure")
    require_variables(classifier, ("mean_profile",), "material_figure")
    names = [str(v) for v in classifier["material"].values]
    scored = "confusion" in classification.data_vars
    source = classifier.attrs.get("source_kind", "plane_to_ray_capture")
    unlabelled = ", or unlabelled" if scored else ", or unlike every trained class"
    panel_d = ("the confusion matrix over the labelled pixels, each true class (row) in percent of its pixels, with "
               "the brightness-only baseline's mean per-class accuracy in the title" if scored else
               "no confusion matrix: the capture was classified without labels")
    made = "delay sweep at one exposure" if source == "plane_to_ray_capture" else "demultiplexed transport"
    found = "object" in classification.data_vars
    outlined = ("; white outlines: the objects found, each classified as one (classify_materials's objects)"
                if found else "")
    caption = f"""Material recognition from delay profiles (thesis Fig. 51 and Fig. 52): (a) the regular image of the
        capture classified (the profiles' area, counts; the materials are all white); (b) each class's mean
        training profile over the sync delay t_d [µs], divided by its area so albedo cancels (from a {made});
        (c) every pixel classified by an RBF-kernel SVM on its profile (C = {classifier.attrs.get('svm_C', '?')},
        γ = {classifier.attrs.get('svm_gamma', '?')} per delay count, by {classifier.attrs.get('folds', '?')}-fold
        cross-validation; black: no usable profile{unlabelled}{outlined}); (d) {panel_d}."""
    args = [classification["image"].data, classifier["delay"].values, classifier["mean_profile"].values, names,
            classification["label"].data,
            classification["true_label"].data < 0 if scored else (
                classification["unlike_training"].data if "unlike_training" in classification.data_vars
                else np.zeros(classification["label"].shape, bool)),
            classification["confusion"].data if scored else None,
            classification["brightness_accuracy"].data if scored else None,
            classification["object"].data if found else None]

    def render(image, delays, mean, names, label, hidden, confusion, brightness, objects):
        return _draw_materials(np.asarray(image), delays, mean, names, np.asarray(label), np.asarray(hidden),
                               None if confusion is None else np.asarray(confusion),
                               None if brightness is None else np.asarray(brightness),
                               None if objects is None else np.asarray(objects))

    return as_figure(render, *args, caption=caption, size=MATERIAL_SIZE)


#: the vein figure's size [in]: three images and the contrast curve
VEIN_SIZE = (12.0, 2.8)


def _draw_vein(images, contrast_of, delays, contrast, chosen: float, free_from: float) -> np.ndarray:
    fig, axes = panels(1, 4, size=VEIN_SIZE, width_ratios=[1.3, 1.3, 1.3, 1.1])
    titles = ["(a) regular image", "(b) far-range indirect", f"(c) chosen delay t_d = {chosen:g} µs"]
    for ax, image, title, c in zip(axes[:3], images, titles, contrast_of, strict=True):
        ax.imshow(image, cmap="gray", vmin=0, vmax=display_top(image), interpolation="nearest")
        ax.set_title(f"{title}\ncontrast {c:.3f}", fontsize=8)
        pixel_axes(ax, ylabel="row [px]" if ax is axes[0] else None, fontsize=7)
    axes[3].plot(delays, contrast, "k.-", ms=3, lw=1)
    axes[3].axvline(chosen, color="C3", lw=1, label="chosen")
    axes[3].axvspan(-free_from, free_from, color="0.85", label="direct light in the frame")
    axes[3].set_xlim(min(delays.min(), -free_from) - 10, delays.max() + 10)
    axes[3].set_xlabel("sync delay t_d [µs]", fontsize=7)
    axes[3].set_ylabel("Weber contrast", fontsize=7)
    axes[3].set_title("(d) contrast over the delay", fontsize=8)
    axes[3].legend(fontsize=6)
    axes[3].tick_params(labelsize=7)
    return rgba(fig)


@stage("vein_figure", kind=FIGURE)
def vein_figure(choice: xr.Dataset, /) -> xr.Dataset:
    """Fig. 49: the regular image, the far-range indirect image and the chosen delay's, with the contrast curve.

    Parameters
    ----------
    choice : xr.Dataset
        A ``delay_choice`` store (``choose_delay``).

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.7 Visualization of vein.
    """
    require_variables(choice, ("image", "contrast", "contrast_of"), "vein_figure")
    a = choice.attrs
    caption = f"""Seeing a structure below the surface (thesis Fig. 49), in counts, each image on its own scale, axes
        in camera pixels: (a) the regular image (all the transport's light), where the surface's reflection hides
        the {a.get('structure', 'structure')}; (b) the far-range indirect image (all light from beyond
        {a.get('far_range_rows', 0):.1f} rows of the pixel's epipolar plane: the surface's reflection is gone, but
        light from every depth dilutes the structure's);
        (c) the frame at the delay chosen (t_e = {a.get('exposure_us', 0):g} µs), the one of the highest Weber
        contrast |μ_surround − μ_structure| / μ_surround between the labelled {a.get('structure', 'structure')} and
        {a.get('surround', 'surround')}; (d) that contrast over the candidate delays clear of direct light
        (|t_d| ≥ (t_e + t_p)/2 = {a.get('direct_free_from_us', 0):g} µs; grey: frames holding direct light; gaps:
        too dark to measure). Titles give each image's contrast."""
    chosen, free_from = float(a.get("chosen_delay_us", np.nan)), float(a.get("direct_free_from_us", 0.0))

    def render(images, contrast_of, contrast):
        return _draw_vein(np.asarray(images), np.asarray(contrast_of), choice["delay"].values, np.asarray(contrast),
                          chosen, free_from)

    return as_figure(render, choice["image"].data, choice["contrast_of"].data, choice["contrast"].data,
                     caption=caption, size=VEIN_SIZE)


#: the atlas figure's size [in]: the white image and a grid of profiles
ATLAS_SIZE = (12.0, 5.0)


def _draw_atlas(image, sites, rows, cols, du, dv, profiles, extents) -> np.ndarray:
    from matplotlib.colors import LogNorm

    n = len(sites)
    grid = int(np.ceil(n / 3))
    fig, axes = panels(3, grid + 2, size=ATLAS_SIZE, squeeze=False)
    for ax in axes[:, :2].ravel():
        ax.remove()
    big = fig.add_subplot(1, grid + 2, (1, 2))
    big.imshow(image, cmap="gray", vmin=0, vmax=display_top(image), interpolation="nearest")
    for k, (r, c) in enumerate(zip(rows, cols, strict=True)):
        big.plot(c, r, "o", ms=5, mfc="none", mew=1, color=f"C{k % 10}")
        big.annotate(str(k + 1), (c, r), xytext=(2, -4), textcoords="offset points", fontsize=6, color=f"C{k % 10}")
    big.set_title("(a) white image Σ T, sites numbered", fontsize=8)
    pixel_axes(big, fontsize=7)
    extent_box = [du[0] - 0.5, du[-1] + 0.5, dv[-1] + 0.5, dv[0] - 0.5]
    cells = axes[:, 2:].ravel()
    for k, ax in enumerate(cells):
        if k >= n:
            ax.set_axis_off()
            continue
        ax.imshow(np.clip(profiles[k].T, 1e-3, 1), cmap="magma", norm=LogNorm(1e-3, 1), extent=extent_box,
                  interpolation="nearest")
        ax.set_title(f"{k + 1}. {sites[k]}\nextent {extents[k]:.2f} px", fontsize=7)
        ax.tick_params(labelsize=5)
    return rgba(fig)


@stage("atlas_figure", kind=FIGURE)
def atlas_figure(atlas: xr.Dataset, /) -> xr.Dataset:
    """Fig. 53: the white image with the atlas's sites, and each site's 2-D transport profile with its extent.

    Parameters
    ----------
    atlas : xr.Dataset
        A ``material_atlas`` store (``material_atlas``).

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.10 Acquired materials.
    """
    require_variables(atlas, ("profile", "extent", "image"), "atlas_figure")
    reach, floor = atlas.attrs.get("reach_px", "?"), atlas.attrs.get("extent_floor", 0)
    caption = f"""A material atlas from full transport (thesis Fig. 53): (a) the white image Σ T in counts, axes in
        camera pixels, with the sites numbered; then each site's profile T(du, dv) over the projector column du
        (horizontal) and row dv (vertical) relative to its direct correspondence, a window of ±{reach} px, scaled to
        its own maximum (dimensionless, on a log scale from 10⁻³; this rig is monochrome, so no white balance;
        blank: cells the sweep never lit), titled with its extent, the RMS distance from the direct correspondence
        of its light above {floor:g} of its maximum [px]. A Lambertian surface gives a compact peak,
        subsurface scattering a wider one (the more translucent, the wider); materials that differ only in albedo
        (textured styrofoam, the sponge's pink and red) share a shape; inter-reflection stretches the profile
        towards the surface the light comes from."""
    sites = [str(s) for s in atlas["site"].values]

    def render(image, profiles, extents):
        return _draw_atlas(np.asarray(image), sites, atlas["site_row"].values, atlas["site_col"].values,
                           atlas["du"].values, atlas["dv"].values, np.asarray(profiles), np.asarray(extents))

    return as_figure(render, atlas["image"].data, atlas["profile"].data, atlas["extent"].data, caption=caption,
                     size=ATLAS_SIZE)


#: the appearance figure's size [in]: the fit, R(d) and the two renders
APPEARANCE_SIZE = (12.0, 3.0)


def _draw_appearance(delays, measured, model, distance, profile, lambertian, subsurface, fit_text: str) -> np.ndarray:
    fig, axes = panels(1, 4, size=APPEARANCE_SIZE, width_ratios=[1.0, 1.0, 1.3, 1.3])
    axes[0].plot(delays, measured, "k.", ms=3, label="measured (mean)")
    axes[0].plot(delays, model, "C3-", lw=1, label="fitted R, through the sweep")
    axes[0].set_xlabel("sync delay t_d [µs]", fontsize=7)
    axes[0].set_ylabel("counts", fontsize=7)
    axes[0].set_title("(a) delay profile", fontsize=8)
    axes[0].legend(fontsize=6)
    axes[1].semilogy(distance, np.clip(profile, 1e-6, None), "C0.-", ms=3)
    axes[1].set_xlabel("distance d [px]", fontsize=7)
    axes[1].set_title(f"(b) R(d): {fit_text}", fontsize=8)
    for ax in axes[:2]:
        ax.tick_params(labelsize=7)
    top = max(float(np.percentile(lambertian, 99.9)), 1e-12)
    for ax, image, title in ((axes[2], lambertian, "(c) without subsurface (R = δ)"),
                             (axes[3], subsurface, "(d) with the captured subsurface")):
        ax.imshow(image, cmap="gray", vmin=0, vmax=top, interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_axis_off()
    return rgba(fig)


@stage("appearance_figure", kind=FIGURE)
def appearance_figure(profile: xr.Dataset, render: xr.Dataset, /) -> xr.Dataset:
    """Fig. 50: a material's fitted scattering profile and a mesh rendered without and with it.

    Parameters
    ----------
    profile : xr.Dataset
        A ``scattering_profile`` store (``fit_scattering_profile``).
    render : xr.Dataset
        An ``appearance_render`` store (``render_appearance``) of that profile.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.8 Appearance capture for graphics.
    """
    require_variables(profile, ("profile",), "appearance_figure")
    require_variables(render, ("image",), "appearance_figure")
    a = profile.attrs
    fit_text = (f"f = {a.get('fraction', np.nan):.3f} ± {a.get('fraction_std', np.nan):.3f}, "
                f"w = {a.get('width_px', np.nan):.2f} ± {a.get('width_std_px', np.nan):.2f} px")
    caption = f"""Appearance capture (thesis Fig. 50): (a) the mean delay profile of the {a.get('material', '')}
        pixels (counts over the sync delay, µs) and the fitted scattering profile's delay sweep, computed through
        the sweep's own illumination matrix; (b) the fitted profile R(d) = (1 − f)·δ + f·Laplace(w) over the
        distance below the surface [px], log scale ({fit_text}, standard errors of the fit); (c) a
        {render.attrs.get('mesh', 'mesh')} under a directional light, Lambertian (R = δ), and (d) the same with
        the captured subsurface scattering, the share f of the irradiance spread by R over the surface in screen
        space (lobe {render.attrs.get('width_render_px', 0):.2f} render px wide); both with the same highlight and
        on one scale. Regions the light misses brighten where light scatters in from lit ones."""

    def render_figure(measured, model, profile_values, images):
        images = np.asarray(images)
        return _draw_appearance(profile["delay"].values, np.asarray(measured), np.asarray(model),
                                profile["distance"].values, np.asarray(profile_values), images[0], images[1], fit_text)

    return as_figure(render_figure, profile["measured"].data, profile["model"].data, profile["profile"].data,
                     render["image"].data, caption=caption, size=APPEARANCE_SIZE)
