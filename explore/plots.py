"""Figures of selpath's cubes for a notebook: matplotlib :class:`~matplotlib.figure.Figure` objects a user can adjust
(``fig.axes[0].set_xlim(…)``, ``fig.savefig(…)``), drawn from each variable's own labels.

Built with their own Agg canvas, never through pyplot, so a notebook's figure list and backend stay as they were;
Jupyter displays a returned figure inline.
"""

from __future__ import annotations

import io
import textwrap

import numpy as np
import xarray as xr
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from selpath.stages._figures import DPI


class NotebookFigure(Figure):
    """A matplotlib figure that Jupyter shows as a PNG whether or not pyplot's inline backend is on (these figures
    never pass through pyplot)."""

    def _repr_png_(self) -> bytes:
        buffer = io.BytesIO()
        self.savefig(buffer, format="png")
        return buffer.getvalue()


def panels(*args, size: tuple[float, float], **kwargs):
    """A new figure of ``size`` inches with its own Agg canvas, and its axes: ``Figure.subplots(*args, **kwargs)``."""
    figure = NotebookFigure(figsize=size, dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure, figure.subplots(*args, **kwargs)


#: a flag map's two colours: False, True
FLAG_COLOURS = ("0.85", "tab:red")


def label(da: xr.DataArray | xr.Variable, fallback: str = "") -> str:
    """``long_name [units]`` of a variable or coordinate, for an axis: its name instead where the long name is
    too long for one (over 40 characters; the title carries it)."""
    name = da.attrs.get("long_name") or getattr(da, "name", None) or fallback
    if len(str(name)) > 40 and getattr(da, "name", None):
        name = da.name
    units = da.attrs.get("units")
    return f"{name} [{units}]" if units not in (None, "") else str(name)


def title(da: xr.DataArray) -> str:
    """The variable's long name, wrapped to lines of 70 characters."""
    return textwrap.fill(str(da.attrs.get("long_name", da.name or "")), 70)


def _frame_dims(da: xr.DataArray) -> tuple[str, str] | None:
    for dims in (("row", "col"), ("y", "x"), ("theta", "x")):
        if set(dims) <= set(da.dims) and da.ndim == 2:
            return dims
    return None


def _extent(da: xr.DataArray, dims: tuple[str, str]) -> list[float] | None:
    """imshow's extent from evenly spaced coordinates (cell edges), None for index axes."""
    if not all(d in da.coords for d in dims):
        return None
    ys, xs = da[dims[0]].values.astype(float), da[dims[1]].values.astype(float)
    if ys.size < 2 or xs.size < 2:
        return None
    dy, dx = (ys[-1] - ys[0]) / (ys.size - 1), (xs[-1] - xs[0]) / (xs.size - 1)
    return [xs[0] - dx / 2, xs[-1] + dx / 2, ys[-1] + dy / 2, ys[0] - dy / 2]


def _axis_label(da: xr.DataArray, dim: str) -> str:
    return label(da[dim], dim) if dim in da.coords else f"{dim} [px]"


def image(da: xr.DataArray, *, cmap: str = "gray", size=(6.0, 4.5), centre: bool = False, **imshow):
    """A 2-D variable as an image with a colour bar naming it; a boolean one (a flag map) with a categorical key
    instead (its two values, no colour scale). Camera frames (row, col) and sinograms (θ, X) are drawn with their
    first row at the top, lab sections (y, x) with y increasing upward (as the reconstruction figures draw them).
    ``centre``: a colour scale symmetric about 0 (an error map, with a diverging ``cmap``)."""
    dims = _frame_dims(da) or tuple(da.dims)
    da = da.transpose(*dims)
    fig, ax = panels(1, 1, size=size)
    values = np.asarray(da.values)
    extent = _extent(da, dims)
    origin = "lower" if dims == ("y", "x") else "upper"
    if extent is not None and origin == "lower":
        extent = [extent[0], extent[1], extent[3], extent[2]]
    placed = {"extent": extent, "origin": origin, "aspect": "auto" if extent and dims != ("y", "x") else None,
              "interpolation": "nearest"}
    if values.dtype == bool:
        ax.imshow(values.astype(int), cmap=ListedColormap(FLAG_COLOURS), vmin=0, vmax=1, **placed)
        name = da.name or da.attrs.get("long_name", "flag")
        ax.legend(handles=[Patch(color=FLAG_COLOURS[1], label=f"{name}: yes ({int(values.sum())} px)"),
                           Patch(color=FLAG_COLOURS[0], label=f"no ({int((~values).sum())} px)")],
                  fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncols=2, frameon=False)
    else:
        if centre:
            top = float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 1.0
            imshow = {"vmin": -top, "vmax": top, **imshow}
        shown = ax.imshow(values, cmap=cmap, **placed, **imshow)
        fig.colorbar(shown, ax=ax, label=label(da, "value"))
    ax.set(xlabel=_axis_label(da, dims[1]), ylabel=_axis_label(da, dims[0]))
    ax.set_title(title(da), fontsize=9)
    return fig


def profile(da: xr.DataArray, *, size=(6.0, 3.5), log: bool = False):
    """A 1-D variable over its dim; over offset with a ``sync_delay`` coordinate, a second x axis in µs (the two
    are linear in each other: t_d = o / v_p − t_o)."""
    (dim,) = da.dims
    fig, ax = panels(1, 1, size=size)
    x = da[dim].values if dim in da.coords else np.arange(da.sizes[dim])
    ax.plot(x, np.asarray(da.values), marker="." if da.sizes[dim] < 80 else None)
    if log:
        ax.set_yscale("symlog", linthresh=max(float(np.nanmax(np.abs(da.values))) * 1e-3, 1e-12))
    ax.set(xlabel=_axis_label(da, dim), ylabel=label(da, "value"))
    ax.set_title(title(da), fontsize=9)
    if "sync_delay" in da.coords and da["sync_delay"].dims == (dim,) and da.sizes[dim] > 1:
        o, t = x.astype(float), da["sync_delay"].values.astype(float)
        slope, intercept = np.polyfit(o, t, 1)
        top = ax.secondary_xaxis("top", functions=(lambda v: slope * v + intercept,
                                                   lambda d: (d - intercept) / slope))
        top.set_xlabel(label(da["sync_delay"], "sync delay"))
    return fig


def sweep(da: xr.DataArray, *, size=(6.0, 3.5)):
    """A pixel's capture over (delay, exposure): I(t_d), one line per exposure."""
    fig, ax = panels(1, 1, size=size)
    for i, e in enumerate(da["exposure"].values):
        ax.plot(da["delay"].values, np.asarray(da.sel(exposure=e).values), marker=".", color=f"C{i % 10}",
                label=f"t_e = {e:g} {da['exposure'].attrs.get('units', '')}")
    ax.set(xlabel=_axis_label(da, "delay"), ylabel=label(da, "value"))
    ax.set_title(title(da), fontsize=9)
    ax.legend(fontsize=7)
    return fig


def sinogram(ds: xr.Dataset, *, slice: int = 0, size=(6.0, 4.5)):
    """A sinogram's absorption over (θ, X) with the bins no ray observed in grey, named in a key."""
    absorption, observed = ds["absorption"], ds["observed"]
    if "slice" in absorption.dims:
        absorption, observed = absorption.isel(slice=slice), observed.isel(slice=slice)
    absorption, observed = absorption.transpose("theta", "x"), observed.transpose("theta", "x")
    values = np.ma.masked_where(~np.asarray(observed.values, bool), np.asarray(absorption.values, float))
    fig, ax = panels(1, 1, size=size)
    cmap = colormaps["viridis"].with_extremes(bad="0.6")
    extent = _extent(absorption, ("theta", "x"))
    shown = ax.imshow(values, cmap=cmap, interpolation="nearest", extent=extent, aspect="auto")
    fig.colorbar(shown, ax=ax, label=label(absorption, "absorption"))
    share = float(np.asarray(observed.values).mean())
    ax.legend(handles=[Patch(color="0.6", label=f"unobserved ({1 - share:.0%} of bins)")], fontsize=7,
              loc="upper right")
    ax.set(xlabel=_axis_label(absorption, "x"), ylabel=_axis_label(absorption, "theta"))
    ax.set_title("sinogram" + (f", slice {slice}" if "slice" in ds["absorption"].dims else ""), fontsize=9)
    return fig


def plot(da: xr.DataArray, **kwargs):
    """The figure that suits ``da``: an image (or flag map) for a frame, a profile for one dim, I(t_d) per
    exposure for a pixel's capture; anything else through xarray's own ``.plot`` on a new figure."""
    if _frame_dims(da) is not None:
        return image(da, **kwargs)
    if da.ndim == 1:
        return profile(da, **kwargs)
    if set(da.dims) == {"delay", "exposure"}:
        return sweep(da, **kwargs)
    fig, ax = panels(1, 1, size=kwargs.pop("size", (6.0, 4.5)))
    da.plot(ax=ax, **kwargs)
    return fig
