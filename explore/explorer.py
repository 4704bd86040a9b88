"""``selpath explore``: the stores in a local web page, interactively (Panel and Bokeh; no JavaScript of ours).

What the thesis's chapter-5 and chapter-4 figures show, moved by hand: click a pixel of a transport's image → its
T over offset with the sync delay [µs] on a second axis, and its captured I(t_d) per exposure where the capture was
given too; slide delay and exposure → the frame an ideal rig records; pick a projector row band → the relit image;
a band half-width → the epipolar and non-epipolar images; a sinogram with its unobserved bins in grey; a
reconstruction's slices beside its truth and error. The numbers come from :mod:`selpath.explore.views`.

A local tool: it listens on 127.0.0.1 unless told otherwise (and warns when told), serves its page and Panel's own
assets and nothing else (no route reads a path), opens only the stores it was given (read-only, lazily) and never
writes; a store's caption is shown as plain text. A transport's I(t_d) comes from a plane-to-ray capture of the
same frame size among the stores given (the first such): give the two that belong together.
Every plot's data source is named (``image-source``, ``profile-source``, ``intensity-source``), so a browser test
reads back what is drawn.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import panel as pn
import xarray as xr
from bokeh.events import Tap
from bokeh.models import ColorBar, ColumnDataSource, LinearAxis, LinearColorMapper, Range1d
from bokeh.plotting import figure

from selpath.explore.views import TransportView, find_stores, open_stores, pair_captures, truth_of
from selpath.stages.procam._illumination import offset_delay

#: the image panel's width in screen pixels (its height follows the frame's aspect)
WIDTH = 560


def _top(image: np.ndarray) -> float:
    finite = image[np.isfinite(image)]
    return max(float(np.percentile(finite, 99.5)) if finite.size else 1.0, 1e-12)


class Frame:
    """A frame drawn as an image (row 0 at the top, axes in full-resolution pixels) that reports clicked pixels."""

    def __init__(self, rows: int, cols: int, title: str, units: str, on_pixel: Callable[[int, int], None] | None,
                 palette: str = "Greys256", x_label: str = "col [px]", y_label: str = "row [px]",
                 extent: tuple[float, float, float, float] | None = None) -> None:
        x0, x1, y0, y1 = extent or (-0.5, cols - 0.5, -0.5, rows - 0.5)
        self.rows, self.cols = rows, cols
        self.source = ColumnDataSource({"image": [np.zeros((1, 1), np.float32)], "x": [x0], "y": [y0],
                                        "dw": [x1 - x0], "dh": [y1 - y0]}, name="image-source")
        self.mapper = LinearColorMapper(palette=palette, low=0, high=1, nan_color="#9a9a9a")
        height = int(WIDTH * (y1 - y0) / max(x1 - x0, 1e-9)) if extent is None else 380
        self.figure = figure(title=title, x_range=Range1d(x0, x1), y_range=Range1d(y1, y0) if extent is None
                             else Range1d(y0, y1), width=WIDTH, height=max(200, min(height, 700)),
                             tools="tap,pan,wheel_zoom,box_zoom,reset", x_axis_label=x_label, y_axis_label=y_label,
                             name="frame")
        self.figure.image(image="image", x="x", y="y", dw="dw", dh="dh", source=self.source,
                          color_mapper=self.mapper)
        self.figure.add_layout(ColorBar(color_mapper=self.mapper, title=units, width=10), "right")
        self.marker = ColumnDataSource({"x": [], "y": []}, name="marker-source")
        self.figure.scatter("x", "y", source=self.marker, size=12, fill_alpha=0, line_color="red", line_width=2)
        if on_pixel is not None:
            def tapped(event) -> None:
                row = int(np.clip(round(event.y), 0, rows - 1))
                col = int(np.clip(round(event.x), 0, cols - 1))
                self.marker.data = {"x": [col], "y": [row]}
                on_pixel(row, col)
            self.figure.on_event(Tap, tapped)

    def show(self, image: np.ndarray, title: str | None = None) -> None:
        image = np.asarray(image, dtype=np.float32)
        self.mapper.high = _top(image)
        finite = image[np.isfinite(image)]
        self.mapper.low = min(0.0, float(finite.min())) if finite.size else 0.0
        self.source.data = {**self.source.data, "image": [image]}
        if title is not None:
            self.figure.title.text = title


def _profile_figure(title: str, x_label: str, y_label: str, name: str) -> tuple:
    source = ColumnDataSource({"x": [], "y": []}, name=name)
    fig = figure(title=title, width=WIDTH, height=260, x_axis_label=x_label, y_axis_label=y_label,
                 tools="pan,wheel_zoom,box_zoom,reset")
    fig.line("x", "y", source=source, line_width=2)
    return fig, source


def transport_panel(view: TransportView, name: str) -> pn.viewable.Viewable:
    rows, cols = view.shape
    status = pn.pane.Markdown("", name="status")
    modes = pn.widgets.RadioButtonGroup(label="view", options=["ideal frame", "relit", "epipolar", "non-epipolar"],
                                        value="ideal frame")
    low, high = view.delays()
    delay = pn.widgets.EditableFloatSlider(label="sync delay t_d [µs]", start=low, end=high,
                                           value=float(np.clip(0.0, low, high)), step=1.0)
    exposures = view.exposures()
    exposure = pn.widgets.EditableFloatSlider(label="exposure t_e [µs]", start=float(view.store.attrs.get(
        "line_time_us", 1.0)), end=max(exposures) * 2, value=exposures[0], step=1.0)
    projector_rows = view.projector_rows()
    line = pn.widgets.EditableIntSlider(label="projector row (first lit)", start=0, end=projector_rows - 1,
                                        value=projector_rows // 2)
    width = pn.widgets.EditableIntSlider(label="projector rows lit", start=1, end=projector_rows,
                                         value=max(1, projector_rows // 100))
    offsets = view.store["offset"].values
    band = pn.widgets.EditableIntSlider(label="band |offset| ≤ [rows]", start=0, end=int(np.abs(offsets).max()),
                                        value=0)
    binned = f" (columns binned by {view.bin}: exact means)" if view.bin > 1 else ""
    pfig, psource = _profile_figure("click a pixel", "offset [px]", "T [counts]", "profile-source")
    speed = float(view.store.attrs.get("scan_speed_px_per_us", 0) or 0)
    if speed:
        t_o = float(view.store.attrs.get("sync_offset_us", 0.0))
        o0, o1 = float(offsets.min()), float(offsets.max())
        pfig.x_range = Range1d(o0, o1)
        d0, d1 = offset_delay([o0, o1], scan_speed=speed, sync_offset=t_o)
        pfig.extra_x_ranges = {"delay": Range1d(float(d0), float(d1))}
        pfig.add_layout(LinearAxis(x_range_name="delay", axis_label="sync delay t_d [µs]"), "above")
    ifig, isource = None, None
    if view.capture is not None:
        isource = ColumnDataSource({"xs": [], "ys": [], "exposure": []}, name="intensity-source")
        ifig = figure(title="captured I(t_d), per exposure", width=WIDTH, height=260,
                      x_axis_label="sync delay t_d [µs]", y_axis_label="I [counts]", tools="pan,wheel_zoom,reset")
        ifig.multi_line("xs", "ys", source=isource, line_width=2)

    def pixel(row: int, col: int) -> None:
        start = time.perf_counter()
        p = view.profile(row, col)
        psource.data = {"x": p["offset"].values.astype(float), "y": p.values.astype(float)}
        pfig.title.text = f"T at pixel (row {row}, col {col})"
        if isource is not None:
            i = view.intensity(row, col)
            isource.data = {"xs": [i["delay"].values.astype(float)] * i.sizes["exposure"],
                            "ys": [i.isel(exposure=k).values.astype(float) for k in range(i.sizes["exposure"])],
                            "exposure": [float(e) for e in i["exposure"].values]}
        status.object = f"pixel (row {row}, col {col}) in {1e3 * (time.perf_counter() - start):.0f} ms"

    frame = Frame(rows, cols, f"{name}{binned}", "counts", pixel)  # the binned image spans the whole frame

    def draw(*_events) -> None:
        start = time.perf_counter()
        image = view.image(modes.value, delay=delay.value, exposure=exposure.value, line=line.value,
                           width=width.value, band=band.value)
        what = {"ideal frame": f"ideal frame, t_d = {delay.value:g} µs, t_e = {exposure.value:g} µs",
                "relit": f"relit: projector rows {line.value}–{line.value + width.value - 1} of {projector_rows}",
                "epipolar": f"epipolar image, |offset| ≤ {band.value}",
                "non-epipolar": f"non-epipolar image, |offset| > {band.value}"}[modes.value]
        frame.show(image, f"{name}: {what}{binned}")
        status.object = f"{what} in {1e3 * (time.perf_counter() - start):.0f} ms"

    for widget in (modes, delay, exposure, line, width, band):
        widget.param.watch(draw, "value")
    draw()
    pixel(rows // 2, cols // 2)  # a pixel to start from: the frame's centre
    frame.marker.data = {"x": [cols // 2], "y": [rows // 2]}
    controls = pn.Column(modes, delay, exposure, line, width, band, status, width=340)
    plots = pn.Column(pn.pane.Bokeh(pfig), *([pn.pane.Bokeh(ifig)] if ifig is not None else []))
    return pn.Row(controls, pn.pane.Bokeh(frame.figure), plots)


def capture_panel(ds: xr.Dataset, name: str) -> pn.viewable.Viewable:
    rows, cols = ds.sizes["row"], ds.sizes["col"]
    delays = [float(d) for d in ds["delay"].values]
    delay = pn.widgets.DiscreteSlider(label="sync delay t_d [µs]", options=delays,
                                      value=min(delays, key=abs))
    exposure = pn.widgets.Select(label="exposure t_e [µs]", options=[float(e) for e in ds["exposure"].values])
    isource = ColumnDataSource({"xs": [], "ys": []}, name="intensity-source")
    ifig = figure(title="click a pixel", width=WIDTH, height=260, x_axis_label="sync delay t_d [µs]",
                  y_axis_label="I [counts]", tools="pan,wheel_zoom,reset")
    ifig.multi_line("xs", "ys", source=isource, line_width=2)

    def pixel(row: int, col: int) -> None:
        i = ds.selpath.intensity(row=row, col=col).load()
        isource.data = {"xs": [i["delay"].values.astype(float)] * i.sizes["exposure"],
                        "ys": [i.isel(exposure=k).values.astype(float) for k in range(i.sizes["exposure"])]}
        ifig.title.text = f"I(t_d) at pixel (row {row}, col {col}), one line per exposure"

    frame = Frame(rows, cols, name, "counts", pixel)

    def draw(*_events) -> None:
        image = ds["image"].sel(delay=delay.value, exposure=exposure.value).values
        frame.show(image, f"{name}: frame at t_d = {delay.value:g} µs, t_e = {exposure.value:g} µs")

    delay.param.watch(draw, "value")
    exposure.param.watch(draw, "value")
    draw()
    pixel(rows // 2, cols // 2)
    return pn.Row(pn.Column(delay, exposure, width=340), pn.pane.Bokeh(frame.figure), pn.pane.Bokeh(ifig))


def figure_panel(ds: xr.Dataset, name: str) -> pn.viewable.Viewable:
    """A figure store (RGBA), as its PNG, with its caption."""
    import io

    import matplotlib.image

    buffer = io.BytesIO()
    matplotlib.image.imsave(buffer, np.asarray(ds["image"].values), format="png")
    return pn.Column(pn.pane.PNG(buffer.getvalue(), width=900),
                     pn.pane.Str(ds.attrs.get("caption", ""), width=900))  # a store's text, never read as HTML


def _slice_widget(ds: xr.Dataset) -> pn.widgets.Widget | None:
    if "slice" not in ds.dims or ds.sizes["slice"] < 2:
        return None
    return pn.widgets.EditableIntSlider(label="slice (index)", start=0, end=ds.sizes["slice"] - 1,
                                        value=ds.sizes["slice"] // 2)


def _coords_extent(da: xr.DataArray, ydim: str, xdim: str) -> tuple[float, float, float, float]:
    ys, xs = da[ydim].values.astype(float), da[xdim].values.astype(float)
    dy = (ys[-1] - ys[0]) / max(ys.size - 1, 1) or 1.0
    dx = (xs[-1] - xs[0]) / max(xs.size - 1, 1) or 1.0
    return xs[0] - dx / 2, xs[-1] + dx / 2, ys[0] - dy / 2, ys[-1] + dy / 2


def sinogram_panel(ds: xr.Dataset, name: str) -> pn.viewable.Viewable:
    chooser = _slice_widget(ds)
    a = ds["absorption"]
    unit = lambda d: a[d].attrs.get("units", "")  # noqa: E731
    frame = Frame(a.sizes["theta"], a.sizes["x"], name, "A [1]", None, palette="Viridis256",
                  x_label=f"x [{unit('x')}]", y_label=f"θ [{unit('theta')}]", extent=_coords_extent(a, "theta", "x"))

    def draw(*_events) -> None:
        k = chooser.value if chooser is not None else 0
        masked = ds.selpath.sinogram(k if "slice" in a.dims else None).transpose("theta", "x").values
        share = float(np.isnan(masked).mean())
        frame.show(masked, f"{name}: sinogram{f', slice {k}' if chooser else ''}; grey: unobserved ({share:.0%})")

    if chooser is not None:
        chooser.param.watch(draw, "value")
    draw()
    return pn.Row(pn.Column(*([chooser] if chooser else []), width=340), pn.pane.Bokeh(frame.figure))


def reconstruction_panel(ds: xr.Dataset, name: str, truth: xr.Dataset | None) -> pn.viewable.Viewable:
    chooser = _slice_widget(ds)
    sigma = ds["sigma"]
    units = sigma.attrs.get("units", "")
    extent = _coords_extent(sigma, "y", "x")
    length = sigma["x"].attrs.get("units", "")
    frames = {"σ": Frame(sigma.sizes["y"], sigma.sizes["x"], name, units, None, palette="Viridis256",
                         x_label=f"x [{length}]", y_label=f"y [{length}]", extent=extent)}
    compared = ds.selpath.compare(truth) if truth is not None else None
    if compared is not None:
        for key in ("truth", "error"):
            frames[key] = Frame(sigma.sizes["y"], sigma.sizes["x"], key, units, None, palette="Viridis256",
                                x_label=f"x [{length}]", y_label=f"y [{length}]", extent=extent)
    status = pn.pane.Markdown("")

    def draw(*_events) -> None:
        k = chooser.value if chooser is not None else 0
        pick = (lambda a: a.isel(slice=k)) if "slice" in sigma.dims else (lambda a: a)
        frames["σ"].show(pick(sigma).values, f"{name}: σ" + (f", slice {k}" if chooser else ""))
        if compared is not None:
            frames["truth"].show(pick(compared["truth"]).values if "slice" in compared["truth"].dims
                                 else compared["truth"].values, "truth")
            error = pick(compared["error"]).values
            frames["error"].show(error, "error σ − truth")
            status.object = f"slice RMSE {float(np.sqrt(np.nanmean(error ** 2))):.3g} {units}"

    if chooser is not None:
        chooser.param.watch(draw, "value")
    draw()
    return pn.Row(pn.Column(*([chooser] if chooser else []), status, width=340),
                  *(pn.pane.Bokeh(f.figure) for f in frames.values()))


def generic_panel(ds: xr.Dataset, name: str) -> pn.viewable.Viewable:
    framed = [v for v in ds.data_vars if {"row", "col"} <= set(ds[v].dims)]
    if not framed:
        return pn.pane.Markdown(f"**{name}** ({ds.attrs.get('selpath_kind')}): no (row, col) image to show; "
                                f"variables {', '.join(map(str, ds.data_vars))}")
    variable = pn.widgets.Select(label="variable", options=framed)
    index_widgets: dict[str, pn.widgets.Widget] = {}
    for dim in {d for v in framed for d in ds[v].dims} - {"row", "col"}:
        index_widgets[dim] = pn.widgets.EditableIntSlider(label=f"{dim} (index)", start=0,
                                                          end=max(ds.sizes[dim] - 1, 1), value=0)
    frame = Frame(ds.sizes["row"], ds.sizes["col"], name, "", None)

    def draw(*_events) -> None:
        a = ds[variable.value]
        a = a.isel({d: min(w.value, ds.sizes[d] - 1) for d, w in index_widgets.items() if d in a.dims})
        frame.mapper.title = a.attrs.get("units", "")
        frame.show(a.transpose("row", "col").values.astype(np.float32),
                   f"{name}: {a.attrs.get('long_name', variable.value)}")

    for w in (variable, *index_widgets.values()):
        w.param.watch(draw, "value")
    draw()
    return pn.Row(pn.Column(variable, *index_widgets.values(), width=340), pn.pane.Bokeh(frame.figure))


class Explorer:
    """The stores, opened once, and the page every browser session gets."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = find_stores(paths)
        self.stores = open_stores(self.paths)
        self.captures = pair_captures(self.stores)
        self.transports: dict[str, TransportView] = {}  # built when first shown (a full-size one: ~10 s, 0.5 GB)

    def panel(self, name: str) -> pn.viewable.Viewable:
        ds, kind = self.stores[name], self.stores[name].attrs.get("selpath_kind")
        if kind == "plane_to_ray_transport":
            if name not in self.transports:
                self.transports[name] = TransportView(ds, self.stores.get(self.captures.get(name, "")))
            return transport_panel(self.transports[name], name)
        if kind == "plane_to_ray_capture":
            return capture_panel(ds, name)
        if kind == "sinogram":
            return sinogram_panel(ds, name)
        if kind == "figure":
            return figure_panel(ds, name)
        if kind == "reconstruction":
            truth = truth_of(self.stores, name)
            return reconstruction_panel(ds, name, self.stores[truth] if truth else None)
        return generic_panel(ds, name)

    def page(self) -> pn.viewable.Viewable:
        names = list(self.stores)
        asked = pn.state.session_args.get("store", [b""])[0].decode()  # ?store=NAME opens that store's view
        first = asked if asked in self.stores else names[0]
        chooser = pn.widgets.Select(label="store", options=names, value=first, width=480)
        body = pn.Column(self.panel(first))
        chooser.param.watch(lambda event: body.__setitem__(slice(None), [self.panel(event.new)]), "value")
        header = pn.pane.Markdown(f"### selpath explore\nread-only: {len(names)} store(s); nothing is written")
        return pn.Column(header, chooser, body)


LOCAL = ("127.0.0.1", "localhost")


def free_port(host: str) -> int:
    """A port nothing listens on now (the system's choice)."""
    with socket.socket() as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def view(*paths: str | Path) -> pn.viewable.Viewable:
    """The explorer's page for a notebook: ``selpath.explore.explorer.view("selpath-demo")`` displays inline in
    Jupyter (Panel's extension loaded), the same views as ``selpath explore``, served by the notebook's kernel."""
    pn.extension()
    return Explorer([Path(p) for p in paths]).page()


def serve(paths: list[Path], *, host: str = "127.0.0.1", port: int = 5006, show: bool = False,
          log: Callable[[str], None] = print) -> None:
    """Open the stores and serve the explorer until interrupted (port 0: any free one, printed)."""
    start = time.perf_counter()
    explorer = Explorer(paths)
    port = port or free_port(host)
    # a local page accepts its own origin only; on another address the browser's origin is the machine's name,
    # which the server cannot know, so any is accepted (and the start says the page is open to the network)
    origins = [f"{host}:{port}", f"localhost:{port}", f"127.0.0.1:{port}"] if host in LOCAL else ["*"]
    server = pn.serve({"/": explorer.page}, address=host, port=port, show=False, start=False,
                      title="selpath explore", websocket_origin=origins, print=False)
    url = f"http://{host}:{port}/"
    log(f"selpath explore: {len(explorer.stores)} store(s), read-only, ready in {time.perf_counter() - start:.1f} s")
    for name, path in explorer.paths.items():
        log(f"  {name}: {path} ({explorer.stores[name].attrs.get('selpath_kind')})")
    if host not in LOCAL:
        log(f"warning: listening on {host}: anyone who can reach this machine can view these stores (no password)")
    log(f"listening on {url} (Ctrl-C stops)")
    server.start()
    if show:
        server.io_loop.add_callback(server.show, "/")
    server.io_loop.start()
