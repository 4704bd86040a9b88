"""Projector–camera application figures as stages (§5.4.3–5.4.6): Fig. 42 a line relit from a multiplexed stack
against the line projected alone, Fig. 45 short-range renders, Fig. 46 transport-matrix slices, Fig. 48
direct/global separation.

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``, with a one-paragraph
``caption`` attr; how is :mod:`stages._figures`.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import xarray as xr

from pipeline.constraints import Fraction, Positive
from pipeline.errors import Problem, StageError
from pipeline.registry import stage
from stages._figures import as_figure, image_colorbar, panels, pixel_axes, rgba
from stages.procam.figures import display_top

#: the separation figure's size [in]: four images in a row
SEPARATION_SIZE = (9.0, 2.6)


def _draw_separation(images: list[np.ndarray], titles: list[str]) -> np.ndarray:
    fig, axes = panels(1, 4, size=SEPARATION_SIZE)
    top = max(display_top(image) for image in images[:3])
    for ax, image, title in zip(axes, images, titles, strict=True):
        shown = ax.imshow(image, cmap="gray", vmin=0, vmax=top if ax is not axes[3] else display_top(images[3]),
                          interpolation="nearest")
        ax.set_title(title, fontsize=8)
        pixel_axes(ax, ylabel="row [px]" if ax is axes[0] else None, fontsize=7)
        if ax is axes[2]:
            image_colorbar(fig, ax, shown, "counts, (a)–(c)")
    image_colorbar(fig, axes[3], shown, "counts, (d)")
    return rgba(fig)


@stage("separation_figure")
def separation_figure(floodlit: xr.Dataset, epipolar: xr.Dataset, /) -> xr.Dataset:
    """Fig. 48: Nayar et al.'s direct image beside the epipolar image and its direct and global parts.

    Parameters
    ----------
    floodlit : xr.Dataset
        A ``direct_global`` store (``separate_direct_global``) of floodlit (global-shutter) checkerboards.
    epipolar : xr.Dataset
        A ``direct_global`` store of epipolar checkerboards (t_d = 0, t_e = t_p).
    """
    for name, ds in (("floodlit", floodlit), ("epipolar", epipolar)):
        if not {"direct", "global"} <= set(ds.data_vars):
            raise StageError(Problem(f"{name} has no direct and global images", where=name,
                                     fix="wire in the output of separate_direct_global"))
    square = floodlit.attrs.get("square_px", "?")
    caption = f"""Direct/global separation from shifted checkerboards (thesis Fig. 48), in counts, axes in camera
        pixels: (a) Nayar et al.'s direct image from {floodlit.attrs.get('shifts', '?')} floodlit frames of a
        checkerboard of {square} projector-px squares (max − min over the shifts, with the projector's black level
        b = {floodlit.attrs.get('black_level', 0):g}); (b) the epipolar image (t_d = 0, t_e = t_p: light from the
        pixel's own epipolar plane only), the sum of (c) and (d); (c) the epipolar-direct and (d) the
        epipolar-global image, the same separation applied to {epipolar.attrs.get('shifts', '?')} epipolar
        frames (d on its own scale). Specular inter-reflections from other epipolar planes count as direct light
        in (a), but are absent from (b)–(d); subsurface scattering within the plane stays in (d)."""
    titles = ["(a) Nayar direct (floodlit)", "(b) epipolar image", "(c) epipolar-direct", "(d) epipolar-global"]

    def render(nayar, direct, global_):
        direct, global_ = np.asarray(direct), np.asarray(global_)
        return _draw_separation([np.asarray(nayar), direct + global_, direct, global_], titles)

    return as_figure(render, floodlit["direct"].data, epipolar["direct"].data, epipolar["global"].data,
                     caption=caption, size=SEPARATION_SIZE)


#: the short-range figure's size [in]
SHORT_RANGE_SIZE = (9.0, 2.8)


def _draw_short_range(images: np.ndarray, titles: list[str]) -> np.ndarray:
    fig, axes = panels(1, len(images), size=SHORT_RANGE_SIZE, squeeze=False)
    top = display_top(images[-1])
    for ax, image, title in zip(axes[0], images, titles, strict=True):
        shown = ax.imshow(image, cmap="gray", vmin=0, vmax=top, interpolation="nearest")
        ax.set_title(title, fontsize=7)
        pixel_axes(ax, ylabel="row [px]" if ax is axes[0][0] else None, fontsize=7)
    image_colorbar(fig, axes[0][-1], shown, "counts")
    return rgba(fig)


@stage("short_range_figure")
def short_range_figure(short_range: xr.Dataset, /) -> xr.Dataset:
    """Fig. 45: floodlit renders of short-range sweeps |t_d| ≤ T_dmax, with their energy and capture counts.

    Parameters
    ----------
    short_range : xr.Dataset
        A ``short_range`` store (``short_range_images``).
    """
    if "image" not in short_range or "max_delay" not in short_range.dims:
        raise StageError(Problem("not a short_range store", where="short_range",
                                 fix="wire in the output of short_range_images"))
    delays = short_range["max_delay"].values
    energy = short_range["energy_fraction"].data
    caption = f"""Short-range acquisition (thesis Fig. 45): the scene floodlit as sweeps limited to |t_d| ≤ T_dmax
        would record it, for T_dmax = {', '.join(f'{d:g}' for d in delays)} µs (each keeps the transport within
        v_p·(T_dmax + (t_e + t_p)/2) camera rows of the pixel's epipolar plane, t_e = {short_range.attrs.get(
        'exposure_us', 170):g} µs: 0 is the single frame at t_d = 0), on one colour scale in counts, axes in camera
        pixels.
        Titles give the share of the transport's energy each keeps and the captures
        its sweep takes at a {short_range.attrs.get('delay_step_us', 170):g} µs delay step (the store's
        pixel_to_pixel_captures gives pixel-to-pixel scanning's count for comparison).
        Light displaced far between planes (specular
        inter-reflection, refraction) appears only as the range grows."""

    def render(images, energy, captures):
        images, energy = np.asarray(images), np.asarray(energy)
        titles = [f"T_dmax = {d:g} µs\n{e:.1%} of the energy, {int(c)} captures"
                  for d, e, c in zip(delays, energy, np.asarray(captures), strict=True)]
        return _draw_short_range(images, titles)

    return as_figure(render, short_range["image"].data, energy, short_range["captures"].data, caption=caption,
                     size=SHORT_RANGE_SIZE)


#: the line-relighting figure's size [in]: truth and three estimates in a row
LINE_SIZE = (9.0, 2.6)


def _draw_line(images: list[np.ndarray], titles: list[str], band: tuple[int, int]) -> np.ndarray:
    fig, axes = panels(1, len(images), size=LINE_SIZE, squeeze=False)
    top = display_top(images[0])
    for ax, image, title in zip(axes[0], images, titles, strict=True):
        shown = ax.imshow(image, cmap="gray", vmin=0, vmax=top, interpolation="nearest")
        ax.axhline(band[0] - 0.5, color="C1", lw=0.6, ls=":")
        ax.axhline(band[1] - 0.5, color="C1", lw=0.6, ls=":")
        ax.set_title(title, fontsize=7)
        pixel_axes(ax, ylabel="row [px]" if ax is axes[0][0] else None, fontsize=7)
    image_colorbar(fig, axes[0][-1], shown, "counts of one scan")
    return rgba(fig)


@stage("line_relighting_figure")
def line_relighting_figure(study: xr.Dataset, /) -> xr.Dataset:
    """Fig. 42: a line relit from the demultiplexed stack beside the line projected alone, short and long.

    Parameters
    ----------
    study : xr.Dataset
        A ``line_relighting_snr`` store (``line_relighting_snr``).
    """
    if study.attrs.get("selpath_kind") != "line_relighting_snr" or "image" not in study:
        raise StageError(Problem("not a line_relighting_snr store", where="study",
                                 fix="wire in the output of line_relighting_snr"))
    band = tuple(int(v) for v in study.attrs["line_rows"])
    methods = [str(m) for m in study["method"].values]
    caption = f"""Illumination multiplexing for relighting with a single line (thesis Fig. 42), in counts of one
        projector scan on one colour scale, axes in camera pixels; the line lights camera rows {band[0]}–
        {band[1] - 1} (dotted). (a) The simulator's noiseless image of the line; (b) the line relit from the
        demultiplexed delay–exposure stack ({int(study['captures'].values[0])} captures); (c)–(d) the line
        projected alone and captured at the exposures named. Titles give the SNR on the
        {study.attrs.get('lit_pixels', '?')} lit pixels (true value at least {study.attrs.get('lit_fraction', 0):g}
        of the brightest) against (a), measured, and for the single captures the noise model's prediction
        (read noise {study.attrs.get('read_std_counts', 0):g} counts, {study.attrs.get('gain_counts_per_electron',
        0):g} count per photo-electron)."""

    def render(truth, images, measured, predicted):
        images = np.asarray(images)
        titles = ["(a) truth (noiseless)"]
        for k, (name, m, p) in enumerate(zip(methods, np.asarray(measured), np.asarray(predicted), strict=True)):
            label = name.replace("multiplexed (demultiplexed)", "relit from the stack")
            titles.append(f"({'bcd'[k] if k < 3 else k}) {label}\nSNR {m:.1f} dB"
                          + (f" (model {p:.1f})" if np.isfinite(p) else ""))
        return _draw_line([np.asarray(truth), *images], titles, band)

    return as_figure(render, study["truth"].data, study["image"].data, study["snr_db"].data,
                     study["predicted_snr_db"].data, caption=caption, size=LINE_SIZE)


#: the multiplexed-relighting figure's size [in]: two rows (checkerboard, floodlit) of truth and two estimates
MULTIPLEXED_SIZE = (8.0, 5.2)


def _draw_multiplexed(truth: np.ndarray, simplex: np.ndarray, multiplexed: np.ndarray, titles: list[list[str]]
                      ) -> np.ndarray:
    fig, axes = panels(2, 3, size=MULTIPLEXED_SIZE, squeeze=False)
    for i in range(2):
        top = display_top(truth[i])
        for j, image in enumerate((truth[i], simplex[i], multiplexed[i])):
            ax = axes[i][j]
            shown = ax.imshow(image, cmap="gray", vmin=0, vmax=top, interpolation="nearest")
            ax.set_title(titles[i][j], fontsize=7)
            pixel_axes(ax, xlabel="col [px]" if i == 1 else "", ylabel="row [px]" if j == 0 else None, fontsize=7)
        image_colorbar(fig, axes[i][2], shown, "counts")
    return rgba(fig)


@stage("multiplexed_relighting_figure")
def multiplexed_relighting_figure(simplex: xr.Dataset, multiplexed: xr.Dataset, /) -> xr.Dataset:
    """Fig. 43: the scene relit from full transport under a checkerboard and floodlit, simplex against
    multiplexed sweeps of the same capture count, beside the simulator's noiseless truth.

    Parameters
    ----------
    simplex : xr.Dataset
        A ``relighting_snr`` store (``full_relighting_snr``) of the simplex sweep.
    multiplexed : xr.Dataset
        A ``relighting_snr`` store of the multiplexed sweep, relit under the same checkerboard.
    """
    for name, ds in (("simplex", simplex), ("multiplexed", multiplexed)):
        if ds.attrs.get("selpath_kind") != "relighting_snr":
            raise StageError(Problem(f"{name} is not a relighting_snr store", where=name,
                                     fix="wire in the output of full_relighting_snr"))
    if simplex.attrs.get("square_px") != multiplexed.attrs.get("square_px"):
        raise StageError(Problem(f"the two were relit under different checkerboards ({simplex.attrs.get('square_px')}"
                                 f" and {multiplexed.attrs.get('square_px')} px squares)",
                                 fix="give both full_relighting_snr steps the same square_px"))

    def sweep(ds: xr.Dataset) -> str:
        return (f"l_w = {ds.attrs.get('line_width_px', float('nan')):g} px, t_e = "
                f"{', '.join(f'{e:g}' for e in ds.attrs.get('exposures_us', []))} µs, {ds.attrs.get('captures')} "
                "captures")

    caption = f"""Illumination multiplexing for relighting from full transport (thesis Fig. 43), in counts, axes in
        camera pixels, each row on its own colour scale: the scene relit under a checkerboard of
        {simplex.attrs.get('square_px')} projector-px squares (top) and floodlit, every projector pixel lit
        (bottom), from (a) the simulator's noiseless render of the pattern, (b) the transport of the simplex sweep
        ({sweep(simplex)}) and (c) that of the multiplexed sweep ({sweep(multiplexed)}). Titles give the SNR on
        the lit pixels (true value at least {simplex.attrs.get('lit_fraction', 0):g} of the brightest)."""
    patterns = [str(p) for p in simplex["pattern"].values]

    def render(truth, simplex_images, multiplexed_images, simplex_snr, multiplexed_snr):
        titles = [[f"(a) {p}: truth", f"(b) simplex, SNR {a:.1f} dB", f"(c) multiplexed, SNR {b:.1f} dB"]
                  for p, a, b in zip(patterns, np.asarray(simplex_snr), np.asarray(multiplexed_snr), strict=True)]
        return _draw_multiplexed(np.asarray(truth), np.asarray(simplex_images), np.asarray(multiplexed_images),
                                 titles)

    return as_figure(render, simplex["truth"].data, simplex["image"].data, multiplexed["image"].data,
                     simplex["snr_db"].data, multiplexed["snr_db"].data, caption=caption, size=MULTIPLEXED_SIZE)


def column_slice(transport: xr.Dataset, col: int) -> xr.DataArray:
    """Camera column ``col`` of the transport over (offset, row): plane-to-ray T(offset, row, col) (light from
    whole projector rows) or full T(du, dv, row, col) at du = 0 (the projector column the pixel sees directly: the
    thesis's 'corresponding column'). Lazy."""
    t = transport["transport"]
    if "dv" in t.dims:
        t = t.sel(du=0.0, method="nearest").rename(dv="offset")
    return t.isel(col=col).transpose("offset", "row")


def transport_matrix(column: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The slice of the transport matrix M[s, v] (the light camera row s receives from projector row v, rectified
    onto camera rows) from one column's T(offset, row); offsets outside the grid and unobserved cells are 0."""
    column = np.nan_to_num(np.asarray(column, dtype=float))
    rows = column.shape[1]
    v = np.arange(rows)[None, :] + np.asarray(offsets, dtype=int)[:, None]  # (offset, row): the projector row
    inside = (v >= 0) & (v < rows)
    o_index, s_index = np.nonzero(inside)
    matrix = np.zeros((rows, rows))
    matrix[s_index, v[inside]] = column[o_index, s_index]
    return matrix


#: the transport-matrix figure's size [in]
MATRIX_SIZE = (9.0, 3.4)


def _draw_matrices(matrices: list[np.ndarray], titles: list[str], gamma: float) -> np.ndarray:
    from matplotlib.colors import PowerNorm

    fig, axes = panels(1, len(matrices), size=MATRIX_SIZE, squeeze=False)
    top = max(display_top(m) for m in matrices)
    for ax, matrix, title in zip(axes[0], matrices, titles, strict=True):
        shown = ax.imshow(matrix, cmap="magma", norm=PowerNorm(gamma, vmin=0, vmax=top), interpolation="nearest")
        n = matrix.shape[0]
        ax.plot([0, n - 1], [0, n - 1], color="w", lw=0.4, ls=":")  # the epipolar (direct) diagonal
        ax.set_title(title, fontsize=7)
        pixel_axes(ax, xlabel="projector row v [px]", ylabel="camera row s [px]" if ax is axes[0][0] else None,
                   fontsize=7)
    image_colorbar(fig, axes[0][-1], shown, f"counts (colour ∝ counts^{gamma:g})")
    return rgba(fig)


@stage("transport_matrix_figure")
def transport_matrix_figure(transport: xr.Dataset, /, *,
                            columns: Annotated[dict[str, Fraction], pydantic.Field(min_length=1)],
                            gamma: Positive = 0.5) -> xr.Dataset:
    """Fig. 46: slices of the light transport matrix, projector rows to one camera column each.

    Parameters
    ----------
    transport : xr.Dataset
        A ``plane_to_ray_transport`` (``demux_plane_to_ray``: light from whole projector rows) or
        ``full_transport`` (``demux_full``: the projector column the pixel sees directly, du = 0).
    columns : dict of str to float
        Named camera columns, as fractions of the image width [1] (e.g. ``disco ball: 0.2``).
    gamma : float
        Colour ∝ counts^gamma [1], so that weak off-diagonal light shows beside the direct diagonal.
    """
    if "transport" not in transport or not ({"offset", "row", "col"} <= set(transport["transport"].dims)
                                            or {"du", "dv", "row", "col"} <= set(transport["transport"].dims)):
        raise StageError(Problem("not a transport over (offset | du, dv, row, col)", where="transport",
                                 fix="wire in the output of demux_plane_to_ray or demux_full"))
    cols = transport.sizes["col"]
    at = {name: min(int(x * cols), cols - 1) for name, x in columns.items()}
    full = "dv" in transport["transport"].dims
    source = "the projector column each pixel sees directly (du = 0)" if full else "whole projector rows"
    caption = f"""Slices of the light transport matrix (thesis Fig. 46): for each named camera column, the light
        camera row s (vertical) receives from projector row v (horizontal, rectified onto camera rows) through
        {source}, in counts on one colour scale (colour ∝ counts^{gamma:g}), from the recovered transport. The
        dotted diagonal v = s is the epipolar plane: direct reflection lies on it; light off it travelled between
        planes (inter-reflection, refraction, subsurface scattering), and only offsets the sweep resolved
        ({int(transport[('dv' if full else 'offset')].min())} to {int(transport[('dv' if full else 'offset')].max())}
        rows) can appear."""
    titles = [f"{name}: camera column {c}" for name, c in at.items()]
    slices = [column_slice(transport, c) for c in at.values()]
    offsets = slices[0]["offset"].values

    def render(*columns):
        return _draw_matrices([transport_matrix(column, offsets) for column in columns], titles, gamma)

    return as_figure(render, *(column.data for column in slices), caption=caption, size=MATRIX_SIZE)


#: the material figure's size [in]: regular image, mean profiles, label map, confusion matrix
MATERIAL_SIZE = (12.0, 3.0)


def _draw_materials(image, delays, mean, names, label, hidden, confusion, brightness_accuracy) -> np.ndarray:
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


@stage("material_figure")
def material_figure(classification: xr.Dataset, classifier: xr.Dataset, /) -> xr.Dataset:
    """Figs. 51–52: the regular image, the classes' mean delay profiles, the pixels classified, the confusion matrix.

    Parameters
    ----------
    classification : xr.Dataset
        A ``material_classification`` store (``classify_materials``); scored (with its ``confusion``) or not.
    classifier : xr.Dataset
        The ``material_classifier`` store that classified it (its mean training profiles are drawn).
    """
    for name, ds, needed in (("classification", classification, ("label", "image")),
                             ("classifier", classifier, ("mean_profile",))):
        if not set(needed) <= set(ds.data_vars):
            raise StageError(Problem(f"{name} lacks {needed}", where=name,
                                     fix="wire in classify_materials' and train_material_classifier's outputs"))
    names = [str(v) for v in classifier["material"].values]
    scored = "confusion" in classification.data_vars
    source = classifier.attrs.get("source_kind", "plane_to_ray_capture")
    unlabelled = ", or unlabelled" if scored else ", or unlike every trained class"
    panel_d = ("the confusion matrix over the labelled pixels, each true class (row) in percent of its pixels, with "
               "the brightness-only baseline's mean per-class accuracy in the title" if scored else
               "no confusion matrix: the capture was classified without labels")
    made = "delay sweep at one exposure" if source == "plane_to_ray_capture" else "demultiplexed transport"
    caption = f"""Material recognition from delay profiles (thesis Fig. 51 and Fig. 52): (a) the regular image of the
        capture classified (the profiles' area, counts; the materials are all white); (b) each class's mean
        training profile over the sync delay t_d [µs], divided by its area so albedo cancels (from a {made});
        (c) every pixel classified by an RBF-kernel SVM on its profile (C = {classifier.attrs.get('svm_C', '?')},
        γ = {classifier.attrs.get('svm_gamma', '?')} per delay count, by {classifier.attrs.get('folds', '?')}-fold
        cross-validation; black: no usable profile{unlabelled}); (d) {panel_d}."""
    args = [classification["image"].data, classifier["delay"].values, classifier["mean_profile"].values, names,
            classification["label"].data,
            classification["true_label"].data < 0 if scored else (
                classification["unlike_training"].data if "unlike_training" in classification.data_vars
                else np.zeros(classification["label"].shape, bool)),
            classification["confusion"].data if scored else None,
            classification["brightness_accuracy"].data if scored else None]

    def render(image, delays, mean, names, label, hidden, confusion, brightness):
        return _draw_materials(np.asarray(image), delays, mean, names, np.asarray(label), np.asarray(hidden),
                               None if confusion is None else np.asarray(confusion),
                               None if brightness is None else np.asarray(brightness))

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


@stage("vein_figure")
def vein_figure(choice: xr.Dataset, /) -> xr.Dataset:
    """Fig. 49: the regular image, the far-range indirect image and the chosen delay's, with the contrast curve.

    Parameters
    ----------
    choice : xr.Dataset
        A ``delay_choice`` store (``choose_delay``).
    """
    if not {"image", "contrast", "contrast_of"} <= set(choice.data_vars):
        raise StageError(Problem("not a delay_choice store", where="choice", fix="wire in the output of choose_delay"))
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


@stage("atlas_figure")
def atlas_figure(atlas: xr.Dataset, /) -> xr.Dataset:
    """Fig. 53: the white image with the atlas's sites, and each site's 2-D transport profile with its extent.

    Parameters
    ----------
    atlas : xr.Dataset
        A ``material_atlas`` store (``material_atlas``).
    """
    if not {"profile", "extent", "image"} <= set(atlas.data_vars):
        raise StageError(Problem("not a material_atlas store", where="atlas", fix="wire in the output of material_atlas"))
    reach = atlas.attrs.get("reach_px", "?")
    caption = f"""A material atlas from full transport (thesis Fig. 53): (a) the white image Σ T in counts, axes in
        camera pixels, with the sites numbered; then each site's profile T(du, dv) over the projector column du
        (horizontal) and row dv (vertical) relative to its direct correspondence, a window of ±{reach} px, scaled to
        its own maximum (dimensionless, on a log scale from 10⁻³; this rig is monochrome, so no white balance;
        blank: cells the sweep never lit), titled with its extent, the RMS distance from the direct correspondence
        of its light above {atlas.attrs.get('extent_floor', 0):g} of its maximum [px]. A Lambertian surface gives a compact peak,
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


@stage("appearance_figure")
def appearance_figure(profile: xr.Dataset, render: xr.Dataset, /) -> xr.Dataset:
    """Fig. 50: a material's fitted scattering profile and a mesh rendered without and with it.

    Parameters
    ----------
    profile : xr.Dataset
        A ``scattering_profile`` store (``fit_scattering_profile``).
    render : xr.Dataset
        An ``appearance_render`` store (``render_appearance``) of that profile.
    """
    if "profile" not in profile.data_vars or "image" not in render.data_vars:
        raise StageError(Problem("needs a scattering_profile and an appearance_render",
                                 fix="wire in fit_scattering_profile's and render_appearance's outputs"))
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
