"""Full-transport figures as stages (§5.4): Fig. 39 the 2-D profiles T(du, dv) of chosen pixels, and Fig. 41
relighting from full transport with a checkerboard of projector squares.

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``, with a one-paragraph
``caption`` attr; how is :mod:`selpath.stages._figures`.
"""

from __future__ import annotations

import textwrap

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Count
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.registry import stage
from selpath.stages._common import Pixels, pixel_at
from selpath.stages._figures import FIGURE, as_figure, image_colorbar, panels, pixel_axes, rgba, shared_colorbar
from selpath.stages.procam.figures import (
    CHECKERBOARD_SIZE,
    PROFILES_SIZE,
    censored_note,
    censored_of,
    display_top,
    draw_relit,
    mark_pixels,
    named_pixels,
)
from selpath.stages.procam.relight import checkerboard_relight


def _full(transport: xr.Dataset) -> xr.Dataset:
    if not {"du", "dv"} <= set(transport.dims):
        raise StageError(Problem(f"this transport has dims {tuple(transport.dims)}, not full transport (du, dv, …)",
                                 where="transport", fix="wire in the output of demux_full"))
    return transport


def _draw_profiles_2d(du, dv, step: float, overview, profiles: dict, at: dict) -> np.ndarray:
    count = len(profiles)
    fig, axes = panels(1, count + 1, size=PROFILES_SIZE, width_ratios=[2.2] + [1] * count)
    shown = axes[0].imshow(overview, cmap="gray", vmin=0, vmax=display_top(overview), interpolation="nearest")
    image_colorbar(fig, axes[0], shown, "counts")
    mark_pixels(axes[0], at)
    axes[0].set_title("(a) white image Σ T, pixels marked", fontsize=8)
    pixel_axes(axes[0], fontsize=7)
    # the window where any shown profile holds ≥ 1 % of its peak, two cells/rows wider
    lit = np.zeros((du.size, dv.size), bool)
    for t in profiles.values():
        top = np.nanmax(t) if np.isfinite(t).any() else 0.0
        lit |= np.nan_to_num(t) >= 0.01 * top if top > 0 else False
    i_u, i_v = (np.flatnonzero(lit.any(axis)) for axis in (1, 0))
    u_sl = slice(max(i_u.min() - 2, 0), i_u.max() + 3) if i_u.size else slice(None)
    v_sl = slice(max(i_v.min() - 2, 0), i_v.max() + 3) if i_v.size else slice(None)
    du, dv = du[u_sl], dv[v_sl]
    extent = (du[0] - step / 2, du[-1] + step / 2, dv[-1] + 0.5, dv[0] - 0.5)
    for i, (ax, (name, t)) in enumerate(zip(axes[1:], profiles.items(), strict=True)):
        t = t[u_sl, v_sl]
        top = float(np.nanmax(t)) if np.isfinite(t).any() and np.nanmax(t) > 0 else 1.0
        shown = ax.imshow(t.T / top, extent=extent, aspect="auto", cmap="magma", vmin=0, vmax=1,
                          interpolation="nearest")
        title = textwrap.wrap(f"({chr(98 + i)}) {name}", 16, break_on_hyphens=False)
        ax.set_title("\n".join(title), fontsize=8, color=f"C{i}")
        ax.set_xlabel("du [projector px]", fontsize=7)
        if i == 0:
            ax.set_ylabel("dv = v − s [projector rows]", fontsize=7)
        ax.tick_params(labelsize=6)
        for spine in ax.spines.values():
            spine.set(color=f"C{i}", linewidth=2)
    shared_colorbar(fig, axes[1:], shown, "T / its peak [1]", shrink=0.8)
    return rgba(fig)


@stage("profile_2d_figure", kind=FIGURE)
def profile_2d_figure(transport: xr.Dataset, /, *, pixels: Pixels) -> xr.Dataset:
    """Fig. 39: the 2-D profile T(du, dv) of full transport at named pixels, each scaled to its peak, beside
    the white image Σ T with the pixels marked. du is projector columns from the direct correspondence u₀,
    dv projector rows from the camera row; cells the sweep never lit are blank.

    Parameters
    ----------
    transport : xr.Dataset
        A ``full_transport`` store (``demux_full``): ``transport`` over (du, dv, row, col), with the
        ``cell_width_px`` attr.
    pixels : dict
        name → [x, y] in image fractions (the scene files' units), each in [0, 1]; at least one pixel.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.1 Analysis of light behavior.
    """
    t = _full(transport)["transport"]
    at = {name: pixel_at(transport, where) for name, where in pixels.items()}
    profiles = {name: t.isel(row=r, col=c).transpose("du", "dv").data for name, (r, c) in at.items()}
    overview = t.sum(("du", "dv"), skipna=True).data
    step = float(transport.attrs["cell_width_px"])
    caption = f"""Two-dimensional profiles of full light transport at single camera pixels (thesis Fig. 39):
        (a) the white image Σ T (every projector pixel lit) in counts, axes in camera pixels, with the named
        pixels marked ({named_pixels(at)}); then, for each pixel, T(du, dv) scaled to its own peak
        (dimensionless), over du, the projector column relative to the pixel's direct correspondence u₀, in
        cells of {step:g} projector px, and dv = v − s, the projector row relative to the camera row [rows],
        cropped to where any profile holds at least 1 % of its peak; cells the sweep never lit are blank. A
        diffuse surface gives a compact peak at (0, 0), subsurface scattering a wider one, inter-reflection
        an extent along du, a specular inter-reflection a second, separate peak."""

    def render(overview, profiles):
        return _draw_profiles_2d(transport["du"].values, transport["dv"].values, step, np.asarray(overview),
                                 {k: np.asarray(v) for k, v in profiles.items()}, at)

    return as_figure(render, overview, profiles, caption=caption, size=PROFILES_SIZE)


@stage("relighting_full_figure", kind=FIGURE)
def relighting_full_figure(transport: xr.Dataset, /, *, square_px: Count | None = None,
                           projector_cols: Count | None = None) -> xr.Dataset:
    """Fig. 41: the scene relit from full transport under a virtual checkerboard, its complement, and white
    (:func:`checkerboard_relight`).

    Parameters
    ----------
    transport : xr.Dataset
        A ``full_transport`` store (``demux_full``): ``transport`` over (du, dv, row, col), ``u_direct``, and
        the ``cell_width_px`` and ``cells_px`` attrs.
    square_px : int or None
        Checkerboard square [projector px]; None: four u-cells (T resolves a pattern only to a cell).
    projector_cols : int or None
        Projector columns; None: the capture's projector_shape, else up to the last u-cell's edge.

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.2 Relighting.
    """
    _full(transport)
    step, cells = float(transport.attrs["cell_width_px"]), transport.attrs["cells_px"]
    shape = transport.attrs.get("projector_shape")
    if projector_cols is None:
        projector_cols = int(shape[1]) if shape is not None else int(np.ceil(cells[-1] + step / 2))
    square = max(1, round(4 * step)) if square_px is None else square_px
    if square < 1 or projector_cols < 1:
        raise StageError(Problem(f"square_px {square} and projector_cols {projector_cols} must be ≥ 1",
                                 fix="give positive sizes"))
    # squares look square on the image: rows scaled as the camera samples the projector's columns
    per_col = transport.sizes["col"] / projector_cols
    square_rows = max(1, round(square * per_col)) if shape is not None else square
    relit = checkerboard_relight(transport, square, projector_cols, square_rows)
    titles = [f"(a) checkerboard, {square} px squares", "(b) its complement", "(c) white: every pixel lit"]
    caption = f"""The scene relit from its full light transport T under virtual projector patterns (thesis Fig.
        41): (a) a checkerboard of {square} × {square_rows} projector-px squares ({square} columns by
        {square_rows} rows rectified onto camera rows) over {projector_cols} projector columns, (b) its
        complement and (c) white, every projector pixel lit; all on one colour scale in counts, axes in camera
        pixels. (a) + (b) = (c); light in the dark squares is light that left a lit square and reached the
        pixel indirectly (inter-reflection, scattering). T resolves a pattern only to its u-cells of {step:g}
        projector columns.{censored_note(transport)}"""
    censored = censored_of(transport)

    def render(checkerboard, complement, white, *mask):
        return draw_relit([np.asarray(a) for a in (checkerboard, complement, white)], titles, CHECKERBOARD_SIZE,
                           censored=np.asarray(mask[0]) if mask else None)

    return as_figure(render, *(relit[name].data for name in ("checkerboard", "complement", "white")),
                     *([censored] if censored is not None else []), caption=caption, size=CHECKERBOARD_SIZE)
