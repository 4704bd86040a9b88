"""How both instruments' figure stages draw: a lazy RGBA ``figure`` cube rendered by matplotlib's Agg canvas.

A figure is data like any other output: it has provenance, is skipped when unchanged, and renders only when the
workflow computes it (inside one dask task). Figures are built from :class:`matplotlib.figure.Figure` with their
own Agg canvas, never through pyplot, so importing a figure stage leaves a notebook's backend and pyplot's figure
list alone.

Every figure carries a ``caption`` attr: one paragraph of plain text saying what it shows, which thesis figure
it reproduces, the settings that matter and the units. It is known before the figure is drawn, so numbers only
the data give (errors, iterations) are printed in the figure itself.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import dask
import numpy as np
import xarray as xr

from selpath.pipeline.kinds import CubeKind, Variable

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: every figure stage's result: an RGBA image a workflow output also saves as ``<store>.png``
FIGURE = CubeKind(
    name="figure",
    description="a rendered figure (RGBA)",
    variables={"image": Variable(("y", "x", "rgba"), units=None, long_name="RGBA image")},
    png="image",
)

#: the standard figure size in inches and every figure's resolution (dots per inch)
SIZE_IN, DPI = (9.0, 4.0), 100


def panels(*args, size: tuple[float, float] = SIZE_IN, **kwargs):
    """A new figure of ``size`` inches and its axes: ``Figure.subplots(*args, **kwargs)`` (matplotlib is imported
    here, when a figure is drawn, so that reading or validating a workflow of figure stages never loads it)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=size, dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure, figure.subplots(*args, **kwargs)


def rgba(figure: Figure) -> np.ndarray:
    """The figure drawn into an (height, width, 4) uint8 array."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = figure.canvas if isinstance(figure.canvas, FigureCanvasAgg) else FigureCanvasAgg(figure)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba()).copy()


def shape_of(size: tuple[float, float] = SIZE_IN) -> tuple[int, int, int]:
    """The (height, width, 4) of a figure of ``size`` inches."""
    return int(size[1] * DPI), int(size[0] * DPI), 4


def one_line(text: str) -> str:
    """``text`` with its runs of white space (line breaks of a source literal) made single spaces."""
    return " ".join(text.split())


def as_figure(render, *args, caption: str, size: tuple[float, float] = SIZE_IN) -> xr.Dataset:
    """A lazy ``figure`` Dataset whose ``image`` is ``render(*args)``, computed in one dask task.

    ``render`` draws a figure of ``size`` inches (:func:`panels` with the same ``size``); ``caption`` is the
    figure's one-paragraph description, stored as the ``caption`` attr (white space collapsed).
    """
    shape = shape_of(size)

    def checked(*arrays):
        image = render(*arrays)
        if image.shape != shape:
            raise ValueError(f"a figure drew {image.shape}, not the {shape} its size of {size} in declares")
        return image

    caption = one_line(caption)
    if not caption:
        raise ValueError("a figure needs a caption")
    import dask.array as da  # on drawing, not on reading a workflow that draws

    image = da.from_delayed(dask.delayed(checked)(*args), shape=shape, dtype=np.uint8)
    return FIGURE.label(xr.Dataset({"image": (("y", "x", "rgba"), image)}, attrs={"caption": caption}))


def image_colorbar(figure: Figure, ax, mappable, label: str):
    """A colour bar as tall as the image drawn in ``ax`` (not its slot), just right of it."""
    bar = ax.inset_axes([1.02, 0.0, 0.035, 1.0])
    colorbar = figure.colorbar(mappable, cax=bar)
    colorbar.set_label(label, fontsize=8)
    bar.tick_params(labelsize=7)
    return colorbar


def shared_colorbar(figure: Figure, axes, mappable, label: str, *, shrink: float = 0.85, ticks=None):
    """One colour bar for several panels (``Figure.colorbar(ax=axes)``), labelled in the figures' small type."""
    colorbar = figure.colorbar(mappable, ax=list(np.ravel(axes)), shrink=shrink, ticks=ticks)
    colorbar.set_label(label, fontsize=8)
    colorbar.ax.tick_params(labelsize=7)
    return colorbar


def pixel_axes(ax, xlabel: str = "col [px]", ylabel: str | None = "row [px]", fontsize: float = 8) -> None:
    """Label an image's axes in pixels, with small tick labels."""
    ax.set_xlabel(xlabel, fontsize=fontsize)
    if ylabel:
        ax.set_ylabel(ylabel, fontsize=fontsize)
    ax.tick_params(labelsize=fontsize - 1)


def slice_name(ds: xr.Dataset, index: int) -> str:
    """'slice 0 of 2 (camera row 59)': a slice's position and, where the dataset has one, its coordinate."""
    if "slice" not in ds.dims:
        return "the one slice"
    name = f"slice {index} of {ds.sizes['slice']}"
    if "slice" in ds.coords:
        name += f" (camera row {ds['slice'].values[index]:g})"
    return name
