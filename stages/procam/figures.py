"""Projector–camera figures as stages (§5.4): Fig. 38 delay profiles, Fig. 40 relighting, Fig. 47 regular and
sharpened epipolar images, 2-D profiles and Fig. 41 relighting from full transport.

Each renders lazily into a ``figure`` cube (RGBA), saved by the engine as ``<store>.png``; how is
:mod:`stages._figures`.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import xarray as xr

from pipeline.constraints import Count, Fraction, Index, Positive
from pipeline.errors import Problem, StageError
from pipeline.registry import stage
from stages._figures import as_figure, panels, rgba
from stages.procam.relight import checkerboard_relight, epipolar_image, relight

#: named pixels, name → [x, y] in image fractions, each in [0, 1]; at least one
Pixels = Annotated[dict[str, tuple[Fraction, Fraction]], pydantic.Field(min_length=1)]


def _pixel(ds: xr.Dataset, where: tuple[float, float]) -> tuple[int, int]:
    x, y = where
    if not (0 <= x <= 1 and 0 <= y <= 1):
        raise StageError(Problem(f"pixel {where} is not in image fractions [0, 1]", fix="give [x, y] fractions"))
    return (min(int(y * ds.sizes["row"]), ds.sizes["row"] - 1), min(int(x * ds.sizes["col"]), ds.sizes["col"] - 1))


def _draw_profiles(delays, measured: dict, offsets, recovered: dict, exposure: float) -> np.ndarray:
    fig, (left, right) = panels(1, 2)
    for name, values in measured.items():
        left.plot(delays, values / max(values.max(), 1e-12), marker=".", label=name)
    left.set(xlabel="delay t_d [µs]", ylabel="intensity / its peak", title=f"delay profiles, t_e = {exposure:g} µs")
    left.legend(fontsize="small")
    for name, values in recovered.items():
        right.plot(offsets, values, label=name)
    right.set(xlabel="offset v − s [rows]", ylabel="T [counts]", yscale="symlog",
              title="demultiplexed transport T(v) at the same pixels")
    return rgba(fig)


@stage("delay_profile_figure")
def delay_profile_figure(capture: xr.Dataset, transport: xr.Dataset, /, *,
                         pixels: Pixels, exposure: Positive | None = None) -> xr.Dataset:
    """Fig. 38: measured delay profiles I(t_d) and the demultiplexed T(offset) at named pixels.

    Parameters
    ----------
    pixels : dict
        name → [x, y] in image fractions (the scene files' units), each in [0, 1]; at least one pixel.
    exposure : float or None
        Exposure whose delay sweep is drawn [µs]; None: the shortest.
    """
    exposure = float(capture["exposure"].min()) if exposure is None else exposure
    if exposure not in capture["exposure"].values:
        raise StageError(Problem(f"exposure {exposure} µs is not in the capture",
                                 fix=f"choose one of {capture['exposure'].values.tolist()}"))
    at = {name: _pixel(capture, where) for name, where in pixels.items()}
    measured = {name: capture["image"].sel(exposure=exposure).isel(row=r, col=c) for name, (r, c) in at.items()}
    recovered = {name: transport["transport"].isel(row=r, col=c) for name, (r, c) in at.items()}

    def render(delays, offsets, measured, recovered):
        return _draw_profiles(delays, {k: np.asarray(v) for k, v in measured.items()}, offsets,
                              {k: np.asarray(v) for k, v in recovered.items()}, exposure)

    return as_figure(render, capture["delay"].values, transport["offset"].values,
                      {k: v.data for k, v in measured.items()}, {k: v.data for k, v in recovered.items()})


def _draw_relit(images: list[np.ndarray], titles: list[str]) -> np.ndarray:
    fig, axes = panels(1, len(images))
    for ax, image, title in zip(np.atleast_1d(axes), images, titles, strict=True):
        ax.imshow(image, cmap="gray", vmin=0, vmax=max(float(np.percentile(image, 99.5)), 1e-12))
        ax.set(title=title, xticks=[], yticks=[])
    return rgba(fig)


@stage("relighting_figure")
def relighting_figure(transport: xr.Dataset, /, *, lines: tuple[Fraction, ...] = (0.2, 0.4, 0.6, 0.8),
                      line_rows: Count = 5) -> xr.Dataset:
    """Fig. 40: the scene relit by single virtual lines sweeping down, and under white (the regular image).

    Parameters
    ----------
    lines : list of float
        Line centres as fractions of the image height, each in [0, 1].
    line_rows : int
        Line width in projector rows.
    """
    t = transport["transport"]
    rows = t.sizes["row"]
    images, titles = [], []
    for centre in lines:
        pattern = (np.abs(np.arange(rows) - centre * rows) < line_rows / 2).astype(float)
        images.append(relight(t, pattern).data)
        titles.append(f"line at {centre:.0%} height")
    images.append(relight(t, np.ones(rows)).data)
    titles.append("white (regular image)")

    def render(*arrays):
        return _draw_relit([np.asarray(a) for a in arrays], titles)

    return as_figure(render, *images)


def _draw_epipolar(regular, sharpened, row: int, exposure: float, half_width: int) -> np.ndarray:
    fig, axes = panels(1, 3)
    top = max(float(np.percentile(regular, 99.5)), 1e-12)
    for ax, image, title in ((axes[0], regular, f"epipolar frame, t_e = {exposure:g} µs"),
                             (axes[1], sharpened, f"sharpened from T (|offset| ≤ {half_width})")):
        ax.imshow(image, cmap="gray", vmin=0, vmax=top)
        ax.axhline(row, color="tab:red", lw=0.8)
        ax.set(title=title, xticks=[], yticks=[])
    axes[2].plot(regular[row], label="epipolar frame")
    axes[2].plot(sharpened[row], label="sharpened")
    axes[2].set(xlabel="column", ylabel="counts", title=f"row {row}")
    axes[2].legend(fontsize="small")
    return rgba(fig)


@stage("epipolar_figure")
def epipolar_figure(capture: xr.Dataset, transport: xr.Dataset, /, *, exposure: Positive | None = None,
                    half_width: Index = 0, row: Fraction = 0.5) -> xr.Dataset:
    """Fig. 47: the captured epipolar frame (t_d = 0) at a long exposure against the sharpened epipolar image
    synthesised from T, with a cross-section.

    Parameters
    ----------
    exposure : float or None
        Exposure of the captured epipolar frame [µs]; None: the longest.
    half_width : int
        Offsets kept by the sharpened image: |offset| ≤ half_width rows.
    row : float
        Cross-section row, as a fraction of the image height, in [0, 1].
    """
    if 0.0 not in capture["delay"].values:
        raise StageError(Problem("the capture has no frame at delay 0 (the epipolar frame)",
                                 fix="sweep delays through 0"))
    exposure = float(capture["exposure"].max()) if exposure is None else exposure
    regular = capture["image"].sel(delay=0.0, exposure=exposure).data
    sharpened = epipolar_image(transport["transport"], half_width).data
    at = min(int(row * capture.sizes["row"]), capture.sizes["row"] - 1)

    def render(regular, sharpened):
        return _draw_epipolar(np.asarray(regular), np.asarray(sharpened), at, exposure, half_width)

    return as_figure(render, regular, sharpened)


def _full(transport: xr.Dataset) -> xr.Dataset:
    if not {"du", "dv"} <= set(transport.dims):
        raise StageError(Problem(f"this transport has dims {tuple(transport.dims)}, not full transport (du, dv, …)",
                                 where="transport", fix="wire in the output of demux_full"))
    return transport


def _draw_profiles_2d(du, dv, step: float, overview, profiles: dict, at: dict) -> np.ndarray:
    fig, axes = panels(1, len(profiles) + 1)
    axes[0].imshow(overview, cmap="gray", vmin=0, vmax=max(float(np.nanpercentile(overview, 99.5)), 1e-12))
    for i, (name, (r, c)) in enumerate(at.items()):
        axes[0].plot(c, r, "o", mfc="none", color=f"C{i}", label=name)
    axes[0].set(title="white (Σ T)", xticks=[], yticks=[])
    axes[0].legend(fontsize="x-small", loc="lower left")
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
        ax.imshow(t.T / top, extent=extent, aspect="auto", cmap="magma", vmin=0, vmax=1, interpolation="nearest")
        ax.set(title=name, xlabel="du [px]", ylabel="dv [rows]" if i == 0 else None)
        for spine in ax.spines.values():
            spine.set(color=f"C{i}", linewidth=2)
    return rgba(fig)


@stage("profile_2d_figure")
def profile_2d_figure(transport: xr.Dataset, /, *, pixels: Pixels) -> xr.Dataset:
    """Fig. 39: the 2-D profile T(du, dv) of full transport at named pixels, each scaled to its peak, beside
    the white image Σ T with the pixels marked. du is projector columns from the direct correspondence u₀,
    dv projector rows from the camera row; cells the sweep never lit are blank.

    Parameters
    ----------
    pixels : dict
        name → [x, y] in image fractions (the scene files' units), each in [0, 1]; at least one pixel.
    """
    t = _full(transport)["transport"]
    at = {name: _pixel(transport, where) for name, where in pixels.items()}
    profiles = {name: t.isel(row=r, col=c).transpose("du", "dv").data for name, (r, c) in at.items()}
    overview = t.sum(("du", "dv"), skipna=True).data

    def render(overview, profiles):
        return _draw_profiles_2d(transport["du"].values, transport["dv"].values,
                                 float(transport.attrs["cell_width_px"]), np.asarray(overview),
                                 {k: np.asarray(v) for k, v in profiles.items()}, at)

    return as_figure(render, overview, profiles)


@stage("relighting_full_figure")
def relighting_full_figure(transport: xr.Dataset, /, *, square_px: Count | None = None,
                           projector_cols: Count | None = None) -> xr.Dataset:
    """Fig. 41: the scene relit from full transport under a virtual checkerboard, its complement, and white
    (:func:`checkerboard_relight`).

    Parameters
    ----------
    square_px : int or None
        Checkerboard square [projector px]; None: four u-cells (T resolves a pattern only to a cell).
    projector_cols : int or None
        Projector columns; None: the capture's projector_shape, else up to the last u-cell's edge.
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
    titles = [f"checkerboard, {square} px squares", "its complement", "white"]

    def render(*arrays):
        return _draw_relit([np.asarray(a) for a in arrays], titles)

    return as_figure(render, *(relit[name].data for name in ("checkerboard", "complement", "white")))
