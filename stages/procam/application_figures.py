"""Projector–camera application figures as stages (§5.4.3–5.4.6): Fig. 42 a line relit from a multiplexed stack
against the line projected alone, Fig. 45 short-range renders, Fig. 46 transport-matrix slices, Fig. 48
direct/global separation (the §5.4.7–5.4.10 figures are in :mod:`selpath.stages.procam.material_figures`).

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``, with a one-paragraph
``caption`` attr; how is :mod:`selpath.stages._figures`.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import xarray as xr

from selpath.pipeline.constraints import Fraction, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.registry import stage
from selpath.stages._figures import FIGURE, as_figure, image_colorbar, panels, pixel_axes, rgba
from selpath.stages.procam.figures import display_top

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


@stage("separation_figure", kind=FIGURE)
def separation_figure(floodlit: xr.Dataset, epipolar: xr.Dataset, /) -> xr.Dataset:
    """Fig. 48: Nayar et al.'s direct image beside the epipolar image and its direct and global parts.

    Parameters
    ----------
    floodlit : xr.Dataset
        A ``direct_global`` store (``separate_direct_global``) of floodlit (global-shutter) checkerboards.
    epipolar : xr.Dataset
        A ``direct_global`` store of epipolar checkerboards (t_d = 0, t_e = t_p).

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.6 Epipolar direct/global separation.
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


@stage("short_range_figure", kind=FIGURE)
def short_range_figure(short_range: xr.Dataset, /) -> xr.Dataset:
    """Fig. 45: floodlit renders of short-range sweeps |t_d| ≤ T_dmax, with their energy and capture counts.

    Parameters
    ----------
    short_range : xr.Dataset
        A ``short_range`` store (``short_range_images``).

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.4 Efficient Acquisition of Short Range Transport.
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


@stage("line_relighting_figure", kind=FIGURE)
def line_relighting_figure(study: xr.Dataset, /) -> xr.Dataset:
    """Fig. 42: a line relit from the demultiplexed stack beside the line projected alone, short and long.

    Parameters
    ----------
    study : xr.Dataset
        A ``line_relighting_snr`` store (``line_relighting_snr``).

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.3 Improving SNR by Multiplexing.
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


@stage("multiplexed_relighting_figure", kind=FIGURE)
def multiplexed_relighting_figure(simplex: xr.Dataset, multiplexed: xr.Dataset, /) -> xr.Dataset:
    """Fig. 43: the scene relit from full transport under a checkerboard and floodlit, simplex against
    multiplexed sweeps of the same capture count, beside the simulator's noiseless truth.

    Parameters
    ----------
    simplex : xr.Dataset
        A ``relighting_snr`` store (``full_relighting_snr``) of the simplex sweep.
    multiplexed : xr.Dataset
        A ``relighting_snr`` store of the multiplexed sweep, relit under the same checkerboard.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.3 Improving SNR by Multiplexing.
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


@stage("transport_matrix_figure", kind=FIGURE)
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

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.4 Efficient Acquisition of Short Range Transport.
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
