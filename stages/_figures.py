"""How both instruments' figure stages draw: a lazy RGBA ``figure`` cube rendered by matplotlib's Agg canvas.

A figure is data like any other output: it has provenance, is skipped when unchanged, and renders only when the
workflow computes it (inside one dask task). Figures are built from :class:`matplotlib.figure.Figure` with their
own Agg canvas, never through pyplot, so importing a figure stage leaves a notebook's backend and pyplot's figure
list alone.
"""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np
import xarray as xr
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

#: every figure's size in inches and its resolution (dots per inch)
SIZE_IN, DPI = (9.0, 4.0), 100


def panels(*args, **kwargs):
    """A new figure of the standard size and its axes: ``Figure.subplots(*args, **kwargs)``."""
    figure = Figure(figsize=SIZE_IN, dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure, figure.subplots(*args, **kwargs)


def rgba(figure: Figure) -> np.ndarray:
    """The figure drawn into an (height, width, 4) uint8 array."""
    canvas = figure.canvas if isinstance(figure.canvas, FigureCanvasAgg) else FigureCanvasAgg(figure)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba()).copy()


def as_figure(render, *args) -> xr.Dataset:
    """A lazy ``figure`` Dataset whose ``image`` is ``render(*args)``, computed in one dask task."""
    h, w = int(SIZE_IN[1] * DPI), int(SIZE_IN[0] * DPI)
    image = da.from_delayed(dask.delayed(render)(*args), shape=(h, w, 4), dtype=np.uint8)
    return xr.Dataset({"image": (("y", "x", "rgba"), image)}, attrs={"selpath_kind": "figure"})
