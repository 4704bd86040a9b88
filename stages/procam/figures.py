"""Projector–camera figures as stages (§5.4): Fig. 38 delay profiles, Fig. 40 relighting, Fig. 47 regular and
sharpened epipolar images (full transport's Figs. 39 and 41 are in :mod:`selpath.stages.procam.full_figures`, the
applications' in :mod:`selpath.stages.procam.application_figures`).

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``, with a one-paragraph
``caption`` attr; how is :mod:`selpath.stages._figures`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Count, Fraction, Index, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.registry import stage
from selpath.stages._common import Pixels, pixel_at
from selpath.stages._figures import FIGURE, as_figure, image_colorbar, panels, pixel_axes, rgba, shared_colorbar
from selpath.stages.procam.relight import epipolar_image, relight

#: sizes [in] of the figures that are not of the standard size
PROFILES_SIZE, EPIPOLAR_SIZE, CHECKERBOARD_SIZE = (9.0, 3.2), (9.0, 3.0), (9.0, 2.6)


def named_pixels(at: dict[str, tuple[int, int]]) -> str:
    return "; ".join(f"{name} at row {r}, col {c}" for name, (r, c) in at.items())


def display_top(image: np.ndarray) -> float:
    """The display maximum of an image: its 99.5th percentile, at least a tiny positive number."""
    finite = np.asarray(image, dtype=float)[np.isfinite(image)]
    return max(float(np.percentile(finite, 99.5)) if finite.size else 0.0, 1e-12)


def mark_pixels(ax, at: dict[str, tuple[int, int]], *, legend: bool = False) -> None:
    for i, (name, (r, c)) in enumerate(at.items()):
        ax.plot(c, r, "o", ms=8, mfc="none", mew=1.5, color=f"C{i}", label=name)
    if legend:
        ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.22), ncols=2, frameon=False)


def _draw_profiles(frame, delays, measured: dict, offsets, recovered: dict, at: dict, exposure: float,
                   frame_delay: float) -> np.ndarray:
    fig, axes = panels(1, 3, size=PROFILES_SIZE, width_ratios=[1.3, 1, 1])
    shown = axes[0].imshow(frame, cmap="gray", vmin=0, vmax=display_top(frame), interpolation="nearest")
    image_colorbar(fig, axes[0], shown, "counts")
    mark_pixels(axes[0], at)
    axes[0].set_title(f"(a) frame at t_d = {frame_delay:g} µs, t_e = {exposure:g} µs", fontsize=9)
    pixel_axes(axes[0])
    for i, (name, values) in enumerate(measured.items()):
        axes[1].plot(delays, values / max(float(np.nanmax(values)), 1e-12), marker=".", color=f"C{i}", label=name)
    axes[1].set(xlabel="sync delay t_d [µs]", ylabel="I(t_d) / its peak [1]")
    axes[1].set_title(f"(b) delay profiles, t_e = {exposure:g} µs", fontsize=9)
    axes[1].legend(fontsize=6, loc="upper left")
    for i, (name, values) in enumerate(recovered.items()):
        axes[2].plot(offsets, values, color=f"C{i}", label=name)
    axes[2].set(xlabel="offset v − s [rows]", ylabel="T [counts] (symlog)", yscale="symlog")
    axes[2].set_title("(c) demultiplexed T, same pixels", fontsize=9)
    return rgba(fig)


@stage("delay_profile_figure", kind=FIGURE)
def delay_profile_figure(capture: xr.Dataset, transport: xr.Dataset, /, *,
                         pixels: Pixels, exposure: Positive | None = None) -> xr.Dataset:
    """Fig. 38: measured delay profiles I(t_d) and the demultiplexed T(offset) at named pixels.

    Parameters
    ----------
    capture : xr.Dataset
        A ``plane_to_ray_capture`` store (``acquire_plane_to_ray``): ``image`` over (delay, exposure, row, col).
    transport : xr.Dataset
        A ``plane_to_ray_transport`` store demultiplexed from it (``demux_plane_to_ray``): ``transport`` over
        (offset, row, col).
    pixels : dict
        name → [x, y] in image fractions (the scene files' units), each in [0, 1]; at least one pixel.
    exposure : float or None
        Exposure whose delay sweep is drawn [µs]; None: the shortest.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.1 Analysis of light behavior.
    """
    exposure = float(capture["exposure"].min()) if exposure is None else exposure
    if exposure not in capture["exposure"].values:
        raise StageError(Problem(f"exposure {exposure} µs is not in the capture",
                                 fix=f"choose one of {capture['exposure'].values.tolist()}"))
    at = {name: pixel_at(capture, where) for name, where in pixels.items()}
    measured = {name: capture["image"].sel(exposure=exposure).isel(row=r, col=c) for name, (r, c) in at.items()}
    recovered = {name: transport["transport"].isel(row=r, col=c) for name, (r, c) in at.items()}
    delays = capture["delay"].values
    frame_delay = float(delays[np.argmin(np.abs(delays))])
    frame = capture["image"].sel(exposure=exposure, delay=frame_delay).data
    caption = f"""Delay profiles of single pixels (thesis Fig. 38): (a) the captured frame at the sync delay
        nearest 0 (t_d = {frame_delay:g} µs, the epipolar frame) and exposure t_e = {exposure:g} µs, in counts,
        with the named pixels marked ({named_pixels(at)}); (b) each pixel's intensity over the sync delay t_d
        [µs] at that exposure, scaled to its own peak: direct light peaks at t_d = 0, light that travelled
        between rows (inter-reflection, subsurface scattering) arrives at other delays; (c) the plane-to-ray
        transport T [counts] demultiplexed from the whole delay–exposure stack at the same pixels, over the
        offset v − s between the lit projector row and the camera row [rows], on a symmetric log scale. A
        specular inter-reflection shows a second peak, a translucent material (the candle) a broad one."""

    def render(frame, delays, offsets, measured, recovered):
        return _draw_profiles(np.asarray(frame), delays, {k: np.asarray(v) for k, v in measured.items()}, offsets,
                              {k: np.asarray(v) for k, v in recovered.items()}, at, exposure, frame_delay)

    return as_figure(render, frame, delays, transport["offset"].values,
                     {k: v.data for k, v in measured.items()}, {k: v.data for k, v in recovered.items()},
                     caption=caption, size=PROFILES_SIZE)


#: the colour censored pixels are drawn in (RGBA): their light was seen only clipped, so their values are lower bounds
CENSORED_COLOUR = (1.0, 0.0, 1.0, 0.85)


def censored_of(transport: xr.Dataset):
    """The transport's per-pixel ``censored`` map (lazy), or None for a store written before #30 had one."""
    return transport["censored"].data if "censored" in transport.data_vars else None


def censored_note(transport: xr.Dataset) -> str:
    """The caption's sentence on censored pixels (empty for a store without the map)."""
    if "censored" not in transport.data_vars:
        return ""
    return (" Pixels whose light was seen only in clipped (saturated) frames are drawn magenta, their count in the"
            " titles: there T is a lower bound, so their relit values are too, never black holes.")


def mark_censored(ax, censored: np.ndarray | None) -> int:
    """Paint the censored pixels of an image panel magenta; returns how many there are."""
    if censored is None or not np.any(censored):
        return 0
    overlay = np.zeros((*censored.shape, 4))
    overlay[np.asarray(censored, bool)] = CENSORED_COLOUR
    ax.imshow(overlay, interpolation="nearest")
    return int(np.sum(censored))


def _grid(count: int) -> tuple[int, int]:
    """Rows and columns of a grid of ``count`` 4:3 panels on a wide figure."""
    cols = count if count <= 3 else int(np.ceil(count / 2)) if count <= 8 else int(np.ceil(np.sqrt(2 * count)))
    return int(np.ceil(count / cols)), cols


def draw_relit(images: list[np.ndarray], titles: list[str], size: tuple[float, float], extra=None,
                gamma: float = 1.0, censored: np.ndarray | None = None, scale_by_last: bool = True) -> np.ndarray:
    """Images on one colour scale (0 to the last image's, white's, 99.5th percentile, or with ``scale_by_last``
    false the largest image's; a power law ``gamma``)
    with one colour bar; ``extra(ax, images)`` draws into one more panel after them; ``censored`` pixels
    (:func:`mark_censored`) painted on every image."""
    from matplotlib.colors import Normalize, PowerNorm  # matplotlib when drawing, not on import

    count = len(images) + (extra is not None)
    rows, cols = _grid(count)
    fig, axes = panels(rows, cols, size=size, squeeze=False)
    axes = axes.ravel()
    top = display_top(images[-1]) if scale_by_last else max(display_top(image) for image in images)
    norm = Normalize(0, top) if gamma == 1 else PowerNorm(gamma, vmin=0, vmax=top)
    for ax, image, title in zip(axes, images, titles, strict=False):
        shown = ax.imshow(image, cmap="gray", norm=norm,
                          interpolation="nearest")
        marked = mark_censored(ax, censored)
        ax.set_title(title + (f"\n{marked} px censored (magenta)" if marked else ""), fontsize=8)
        pixel_axes(ax, fontsize=7)
    label = "counts" if gamma == 1 else f"counts (colour ∝ counts^{gamma:g})"
    ticks = None
    if gamma != 1:  # ticks evenly spaced in colour, rounded to two significant digits
        ticks = np.unique([float(f"{top * (k / 5) ** (1 / gamma):.2g}") for k in range(6)])
        ticks = ticks[ticks <= top]
    shared_colorbar(fig, axes[:len(images)], shown, label, ticks=ticks)
    if extra is not None:
        extra(axes[len(images)], images)
    for ax in axes[count:]:
        ax.set_visible(False)
    return rgba(fig)


@stage("relighting_figure", kind=FIGURE)
def relighting_figure(transport: xr.Dataset, /, *, lines: tuple[Fraction, ...] = (0.2, 0.4, 0.6, 0.8),
                      line_rows: Count = 5) -> xr.Dataset:
    """Fig. 40: the scene relit by single virtual lines sweeping down, and under white (the regular image).

    Parameters
    ----------
    transport : xr.Dataset
        A ``plane_to_ray_transport`` store (``demux_plane_to_ray``): ``transport`` over (offset, row, col).
    lines : list of float
        Line centres as fractions of the image height, each in [0, 1].
    line_rows : int
        Line width in projector rows.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.2 Relighting.
    """
    t = transport["transport"]
    rows = t.sizes["row"]
    images, titles, lit = [], [], []
    for i, centre in enumerate(lines):
        pattern = (np.abs(np.arange(rows) - centre * rows) < line_rows / 2).astype(float)
        on = np.flatnonzero(pattern)
        span = f"v = {on[0]}–{on[-1]}" if on.size > 1 else f"v = {on[0]}" if on.size else "no row"
        images.append(relight(t, pattern).data)
        titles.append(f"({chr(97 + i)}) line {span} ({centre:.0%} of height)")
        lit.append(on)
    images.append(relight(t, np.ones(rows)).data)
    titles.append(f"({chr(97 + len(lines))}) white: every row lit (regular image)")
    letter = chr(98 + len(lines))

    def profiles(ax, images):
        for i, image in enumerate(images[:-1]):
            ax.semilogy(np.nanmean(image, axis=1), color=f"C{i}", lw=1, label=f"({chr(97 + i)})")
            if lit[i].size:
                ax.axvspan(lit[i][0] - 0.5, lit[i][-1] + 0.5, color=f"C{i}", alpha=0.25, lw=0)
        white = np.nanmean(images[-1], axis=1)
        ax.semilogy(white, color="0.3", lw=1, label=f"({chr(97 + len(lines))})")
        if np.nanmax(white) > 0:
            ax.set_ylim(bottom=1e-3 * float(np.nanmax(white)))
        ax.set_xlabel("camera row s [px]", fontsize=7)
        ax.set_ylabel("row mean [counts]", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_title(f"({letter}) mean over each row; shaded: lit rows", fontsize=8)
        ax.legend(fontsize=6, ncols=2, loc="lower right")

    caption = f"""The scene relit from its plane-to-ray transport T by single virtual lines of {line_rows}
        projector rows (rows rectified onto camera rows, so row v lights the camera's epipolar row v) centred
        at {", ".join(f"{c:.0%}" for c in lines)} of the image height and sweeping down, and under white (every
        row lit: the regular image), all on one colour scale in counts (a square-root scale, so that dim indirect
        light shows), axes in camera pixels; the last panel
        gives each image's mean over camera columns per camera row on a log scale, with the lit rows shaded,
        so light that lands away from the line (inter-reflection, scattering) shows as counts outside the
        shading. Reproduces thesis Fig. 40.{censored_note(transport)}"""
    size = (9.0, 2.6 * _grid(len(images) + 1)[0])
    censored = censored_of(transport)

    def render(*arrays):
        mask = np.asarray(arrays[-1]) if censored is not None else None
        images = arrays[:-1] if censored is not None else arrays
        return draw_relit([np.asarray(a, dtype=float) for a in images], titles, size, profiles, gamma=0.5,
                           censored=mask)

    return as_figure(render, *images, *([censored] if censored is not None else []), caption=caption, size=size)


def _draw_epipolar(regular, sharpened, row: int, exposure: float, half_width: int, delay: float,
                   censored: np.ndarray | None = None) -> np.ndarray:
    fig, axes = panels(1, 3, size=EPIPOLAR_SIZE)
    top = display_top(regular)
    for ax, image, title in ((axes[0], regular, f"(a) epipolar frame, t_d = {delay:g} µs, t_e = {exposure:g} µs"),
                             (axes[1], sharpened, f"(b) sharpened from T: |v − s| ≤ {half_width} rows")):
        shown = ax.imshow(image, cmap="gray", vmin=0, vmax=top, interpolation="nearest")
        marked = mark_censored(ax, censored) if image is sharpened else 0
        ax.axhline(row, color="tab:red", lw=0.8)
        ax.set_title(title + (f"\n{marked} px censored (magenta)" if marked else ""), fontsize=8)
        pixel_axes(ax, fontsize=7)
    shared_colorbar(fig, axes[:2], shown, "counts", shrink=0.8)
    axes[2].plot(regular[row], lw=0.8, label="(a) epipolar frame")
    axes[2].plot(sharpened[row], lw=0.8, label="(b) sharpened")
    axes[2].set_xlabel("col [px]", fontsize=8)
    axes[2].set_ylabel("counts", fontsize=8)
    axes[2].tick_params(labelsize=7)
    axes[2].set_title(f"(c) cross-section at row {row} (red line)", fontsize=8)
    axes[2].legend(fontsize=7)
    return rgba(fig)


@stage("epipolar_figure", kind=FIGURE)
def epipolar_figure(capture: xr.Dataset, transport: xr.Dataset, /, *, exposure: Positive | None = None,
                    half_width: Index = 0, row: Fraction = 0.5) -> xr.Dataset:
    """Fig. 47: the captured epipolar frame (t_d = 0) at a long exposure against the sharpened epipolar image
    synthesised from T, with a cross-section.

    Parameters
    ----------
    capture : xr.Dataset
        A ``plane_to_ray_capture`` store (``acquire_plane_to_ray``) whose delays include 0.
    transport : xr.Dataset
        A ``plane_to_ray_transport`` store demultiplexed from it (``demux_plane_to_ray``).
    exposure : float or None
        Exposure of the captured epipolar frame [µs]; None: the longest.
    half_width : int
        Offsets kept by the sharpened image: |offset| ≤ half_width rows.
    row : float
        Cross-section row, as a fraction of the image height, in [0, 1].

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.5 Sharpening epipolar imaging.
    """
    if 0.0 not in capture["delay"].values:
        raise StageError(Problem("the capture has no frame at delay 0 (the epipolar frame)",
                                 fix="sweep delays through 0"))
    exposure = float(capture["exposure"].max()) if exposure is None else exposure
    regular = capture["image"].sel(delay=0.0, exposure=exposure).data
    sharpened = epipolar_image(transport["transport"], half_width).data
    at = min(int(row * capture.sizes["row"]), capture.sizes["row"] - 1)
    speed = capture.attrs.get("scan_speed_px_per_us")
    band = f"the band of about v_p·t_e = {speed * exposure:.0f} projector rows" if speed else "a band of projector rows"
    caption = f"""Regular against sharpened epipolar imaging (thesis Fig. 47): (a) the captured epipolar frame
        (sync delay t_d = 0) at exposure t_e = {exposure:g} µs, which admits light from {band} around each
        camera row, and so some subsurface scattering and inter-reflection; (b)
        the epipolar image synthesised from the demultiplexed transport T, keeping only offsets |v − s| ≤
        {half_width} projector rows; both on one colour scale in counts, axes in camera pixels; (c) both along
        camera row {at} ({row:.0%} of the height, red line). Light that the long exposure lets in from farther
        rows (the candle's scattering) is removed in (b).{censored_note(transport)}"""
    censored = censored_of(transport)

    def render(regular, sharpened, *mask):
        return _draw_epipolar(np.asarray(regular), np.asarray(sharpened), at, exposure, half_width, 0.0,
                              np.asarray(mask[0]) if mask else None)

    return as_figure(render, regular, sharpened, *([censored] if censored is not None else []), caption=caption,
                     size=EPIPOLAR_SIZE)
