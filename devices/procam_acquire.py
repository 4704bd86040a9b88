"""Delay–exposure sweeps of the synchronised projector–camera rig, written frame by frame (§5.2.3, §5.3).

``acquire_plane_to_ray``: the white pattern, every (delay, exposure) → a ``(delay, exposure, row, col)``
store. ``acquire_full_transport``: a vertical line at each position l_p (width l_w) × every (delay,
exposure) → ``(delay, exposure, line, row, col)``. Like the tomography sweep (``selpath.devices.tomography_acquire``),
the store
is pre-allocated, each frame is a region write followed by its ``written__`` flag, and running the same
sweep again captures only what is missing. A sweep the controller cannot do is refused before anything
moves, naming the limit. Order: exposure (slowest), line, delay, so settings change as little as possible.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import xarray as xr
from rich.progress import Progress, TextColumn, TimeElapsedColumn

from selpath.devices.patterns import checkerboard, gray_code_levels, vertical_line, white
from selpath.devices.protocols import Camera, Projector, SyncController
from selpath.pipeline.errors import DeviceError, Problem, SpecError
from selpath.pipeline.locks import store_lock
from selpath.pipeline.progress import BAR_COLUMNS, show_bars

#: camera rows per stored chunk of a capture
CAPTURE_BAND_ROWS = 64


@dataclass
class ProcamInstruments:
    """The instruments of a delay–exposure sweep and the attrs (v_p, t_p, …) its captures carry."""

    sync: SyncController
    projector: Projector
    camera: Camera
    attrs: Mapping[str, Any] = field(default_factory=dict)

    def close(self) -> None:
        for device in (self.sync, self.projector, self.camera):
            device.close()


@dataclass(frozen=True)
class SweepPlan:
    """How many captures a sweep needs, and what scanning one projector block at a time would need (§5.2.4)."""

    delays: int
    exposures: int
    lines: int
    pixel_to_pixel: int

    @property
    def captures(self) -> int:
        return self.delays * self.exposures * self.lines

    def describe(self) -> str:
        shape = f"{self.delays} delays × {self.exposures} exposures"
        if self.lines > 1:
            shape += f" × {self.lines} lines"
        ratio = self.pixel_to_pixel / max(self.captures, 1)
        verdict = (f"this sweep takes {ratio:.1f}× fewer captures" if ratio >= 1 else
                   f"this sweep takes {1 / ratio:.1f}× as many captures here (it pays off where the sensor has "
                   "many more rows than the sweep has delays × exposures)")
        return (f"{self.captures} captures ({shape}); pixel-to-pixel scanning (§5.2.4: one block of projector rows "
                f"lit per capture, as tall as the rows the scan crosses in one delay step) needs "
                f"{self.pixel_to_pixel:,} for the same rows: {verdict}")


def plan_sweep(delays: Sequence[float], exposures: Sequence[float], lines: Sequence[float] | None = None, *,
               row_block: float, row_span: float) -> SweepPlan:
    """Captures of a sweep versus pixel-to-pixel scanning (one block of ``row_block`` projector rows — and,
    for the full transport, one ``row_block``-wide column block per line position — lit at a time, stepped
    over ``row_span`` rows).

    The thesis's §5.4.2 arithmetic: 46 line positions (0…900 px every 20) × 11 delays = 506 captures, versus
    46 × 81 blocks of 20 px = 3,726 for pixel-to-pixel scanning.
    """
    n_lines = len(lines) if lines is not None else 1
    return SweepPlan(len(delays), len(exposures), n_lines, n_lines * math.ceil(row_span / row_block))


def refuse_impossible(instruments: ProcamInstruments, delays, exposures) -> None:
    problems = instruments.sync.limits.problems(delays, exposures)
    if problems:
        raise SpecError([Problem(p, fix="narrow the sweep to what the sync controller can do") for p in problems])


def capture_template(instruments: ProcamInstruments, kind: str, delays, exposures, lines=None,
                     extra_attrs=None) -> xr.Dataset:
    rows, cols = instruments.camera.shape
    coords = {"delay": ("delay", np.asarray(delays, float), {"units": "us", "long_name": "sync delay t_d"}),
              "exposure": ("exposure", np.asarray(exposures, float), {"units": "us", "long_name": "exposure t_e"})}
    dims = ["delay", "exposure"]
    if lines is not None:
        coords["line"] = ("line", np.asarray(lines, float), {"units": "px", "long_name": "line centre l_p"})
        dims.append("line")
    shape = tuple(len(coords[d][1]) for d in dims) + (rows, cols)
    import dask.array as da  # on acquiring, not on reading a workflow that acquires

    # stored in bands of rows, so per-pixel work (demultiplexing) reads a band of every frame, not whole frames
    stack = da.zeros(shape, dtype=np.float32, chunks=(1,) * len(dims) + (min(rows, CAPTURE_BAND_ROWS), cols))
    return xr.Dataset({"image": ((*dims, "row", "col"), stack, {"units": "counts"})}, coords=coords,
                      attrs={"selpath_kind": kind, **instruments.attrs, **(extra_attrs or {})})


def sweep_frames(instruments: ProcamInstruments, store, template: xr.Dataset, kind: str, show: Callable,
                 progress: bool, log: Callable[[str], None]) -> xr.Dataset:
    """Capture every missing frame of ``template`` into ``store`` (created or resumed, and locked while the
    sweep runs), ``show(line)`` putting each frame's pattern on the projector (line None for sweeps without
    lines)."""
    with store_lock(store, purpose=kind):
        return _sweep_frames(instruments, store, template, kind, show, progress, log)


def show_line(projector, position: float, width: float) -> None:
    """A vertical line (``selpath.devices.patterns.vertical_line``) on ``projector``: drawn by the projector itself
    where
    it can (``show_line``: one command instead of a pattern upload), else shown as a pattern."""
    if hasattr(projector, "show_line"):
        projector.show_line(position, width)
    else:
        projector.show(vertical_line(projector.shape, position, width))


def _sweep_frames(instruments: ProcamInstruments, store, template: xr.Dataset, kind: str, show: Callable,
                  progress: bool, log: Callable[[str], None]) -> xr.Dataset:
    from selpath.pipeline.capture_store import create_capture, missing_frames, write_frame  # zarr: on acquiring
    from selpath.pipeline.store import open_store

    delays, exposures = template["delay"].values, template["exposure"].values
    refuse_impossible(instruments, delays, exposures)
    speed = float(instruments.attrs.get("scan_speed_px_per_us", 0.0))
    if speed > 0 and len(delays) > 1:  # the §5.2.4 comparison: lighting one block of rows at a time instead
        step = float(np.min(np.diff(np.sort(delays))))
        lines = template["line"].values if "line" in template.dims else None
        log("   plan: " + plan_sweep(delays, exposures, lines, row_block=max(speed * step, 1.0),
                                  row_span=instruments.camera.shape[0]).describe())
    create_capture(store, template, kind)
    todo = missing_frames(store)["image"]
    if not todo:
        log(f"   every frame is already captured in {store}")
        return open_store(store)
    dims = [d for d in ("delay", "exposure", "line") if d in template.dims]
    index = {d: {float(v): i for i, v in enumerate(template[d].values)} for d in dims}
    todo = sorted(todo, key=lambda f: (f["exposure"], f.get("line", 0.0), f["delay"]))
    total = int(np.prod([template.sizes[d] for d in dims]))
    resuming = len(todo) < total
    log(f"   capturing {len(todo)} frame(s) into {store}" + (" (resuming: the others are already captured)"
                                                           if resuming else ""))
    current: dict[str, Any] = {}
    began = time.perf_counter()
    with Progress(*BAR_COLUMNS, TextColumn("frames"), TimeElapsedColumn(), disable=not show_bars(progress),
                  transient=True) as bar:
        task = bar.add_task("capture", total=len(todo))
        for frame in todo:
            if current.get("line", object()) != frame.get("line"):
                show(frame.get("line"))
                current["line"] = frame.get("line")
            if current.get("exposure") != frame["exposure"]:
                _verified(instruments.sync.set_exposure(frame["exposure"]), frame["exposure"], "exposure", instruments)
                current["exposure"] = frame["exposure"]
            _verified(instruments.sync.set_delay(frame["delay"]), frame["delay"], "delay", instruments)
            instruments.sync.arm()
            image = instruments.camera.capture()
            write_frame(store, "image", {d: index[d][float(frame[d])] for d in dims}, image)
            bar.update(task, advance=1, description=f"capture: t_d = {frame['delay']:g} µs, t_e = "
                       f"{frame['exposure']:g} µs" + (f", l_p = {frame['line']:g} px" if "line" in frame else ""))
    log(f"   captured {len(todo)} frame(s) in {time.perf_counter() - began:.1f} s")
    return open_store(store)


def _verified(actual: float, wanted: float, name: str, instruments: ProcamInstruments) -> None:
    if abs(actual - wanted) > instruments.sync.limits.step / 2:
        raise DeviceError(f"controller holds {name} {actual:g} µs, the sweep asked {wanted:g} µs",
                          command=f"set_{name}({wanted})", fix="check the controller, then run the sweep again")


@dataclass(frozen=True)
class HdrPlan:
    """What the HDR planner tried and chose: the preview exposures at t_d = 0 with their clipped pixel counts, the
    exposure it added (None: none helps or none is needed) and what that costs in captures."""

    tried: tuple[tuple[float, int], ...]
    added: float | None
    delays: int

    @property
    def previews(self) -> int:
        return len(self.tried)

    @property
    def captures(self) -> int:
        """Captures the plan adds to the sweep (its previews are captures too)."""
        return self.previews + (self.delays if self.added is not None else 0)

    def attrs(self) -> dict[str, Any]:
        return {"hdr_tried_exposures_us": [e for e, _ in self.tried],
                "hdr_tried_clipped_pixels": [n for _, n in self.tried],
                "hdr_added_exposure_us": self.added if self.added is not None else "none",
                "hdr_captures": self.captures}

    def describe(self) -> str:
        seen = ", ".join(f"{n} px clip at t_e = {e:g} µs" for e, n in self.tried)
        if not self.tried or self.tried[0][1] == 0:
            return f"hdr: nothing clips at the shortest exposure ({seen}); no exposure added ({self.captures} preview)"
        if self.added is None:
            return (f"hdr: {seen}: a shorter exposure does not unclip them (their light clips within one line time, "
                    f"so only attenuation helps: lower the projector's power); nothing added, {self.captures} "
                    "preview captures spent")
        left = dict(self.tried)[self.added]
        return (f"hdr: {seen}; added t_e = {self.added:g} µs for every delay: +{self.delays} captures "
                f"(+{self.previews} previews){'' if not left else f'; {left} px still clip there (attenuate)'}")


def plan_hdr(instruments: ProcamInstruments, delays: Sequence[float], exposures: Sequence[float]) -> HdrPlan:
    """Preview frames at t_d = 0 (the epipolar frame, where the direct light is) from the shortest requested
    exposure down, halving (on the controller's step) while pixels clip, to the shortest exposure whose frames the
    demultiplexing keeps (2 t_p: its edges clear the epipolar row's line time). Adds the exposure tried that clips
    fewest pixels (the longest among equals) if it clips fewer than the shortest requested one. Each preview is
    one capture (shown, never stored); at most log2(t_e / 2 t_p) + 1 of them."""
    level = float(instruments.attrs["saturation_counts"])
    limits = instruments.sync.limits
    floor = max(limits.exposure_min, 2.0 * float(instruments.attrs.get("line_time_us", 0.0)))
    exposure, tried = float(min(exposures)), []
    while True:
        _verified(instruments.sync.set_exposure(exposure), exposure, "exposure", instruments)
        _verified(instruments.sync.set_delay(0.0), 0.0, "delay", instruments)
        instruments.sync.arm()
        clipped = int(np.sum(instruments.camera.capture() >= level))
        tried.append((exposure, clipped))
        shorter = max(floor, round(exposure / 2 / limits.step) * limits.step)
        if clipped == 0 or shorter >= exposure:  # a frame cannot say how far above the level it is: try to the floor
            break
        exposure = shorter
    best = min(tried[1:], key=lambda t: (t[1], -t[0]), default=None)
    added = best[0] if best is not None and best[1] < tried[0][1] else None
    return HdrPlan(tuple(tried), added, len(delays))


def acquire_plane_to_ray(instruments: ProcamInstruments, store: str | os.PathLike, delays: Sequence[float],
                         exposures: Sequence[float], *, hdr: bool = False, progress: bool = True,
                         log: Callable[[str], None] = lambda _: None) -> xr.Dataset:
    """White pattern, every (delay, exposure): a ``plane_to_ray_capture`` store, resumable. With ``hdr``, the
    planner (:func:`plan_hdr`) may add one shorter exposure first; a resumed store keeps the one it added."""
    extra = {}
    if hdr:
        instruments.projector.show(white(instruments.projector.shape))
        existing = _existing_hdr(store)
        if existing is None:
            plan = plan_hdr(instruments, delays, exposures)
            log("   " + plan.describe())
            extra = plan.attrs()
        else:
            extra = existing
        if extra["hdr_added_exposure_us"] != "none":
            exposures = sorted({*map(float, exposures), float(extra["hdr_added_exposure_us"])})
    template = capture_template(instruments, "plane_to_ray_capture", delays, exposures, extra_attrs=extra)
    pattern = white(instruments.projector.shape)
    return sweep_frames(instruments, store, template, "plane_to_ray_capture",
                        lambda _: instruments.projector.show(pattern), progress, log)


def _existing_hdr(store: str | os.PathLike) -> dict[str, Any] | None:
    """The HDR plan an existing capture at ``store`` recorded (its sweep is resumed as planned), else None."""
    from selpath.pipeline.integrity import is_selpath_store
    from selpath.pipeline.store import open_store

    if not is_selpath_store(store):
        return None
    attrs = open_store(store, keep_flags=True).attrs
    keys = ("hdr_tried_exposures_us", "hdr_tried_clipped_pixels", "hdr_added_exposure_us", "hdr_captures")
    return {k: attrs[k] for k in keys} if all(k in attrs for k in keys) else None


def acquire_full_transport(instruments: ProcamInstruments, store: str | os.PathLike, delays: Sequence[float],
                           exposures: Sequence[float], lines: Sequence[float], line_width: float, *,
                           progress: bool = True, log: Callable[[str], None] = lambda _: None) -> xr.Dataset:
    """A vertical line at each l_p (width l_w) × every (delay, exposure): a ``full_transport_capture`` store."""
    template = capture_template(instruments, "full_transport_capture", delays, exposures, lines,
                                {"line_width_px": float(line_width)})
    return sweep_frames(instruments, store, template, "full_transport_capture",
                        lambda position: show_line(instruments.projector, position, line_width), progress, log)


def checkerboard_shifts(square: tuple[int, int], per_axis: int) -> np.ndarray:
    """``per_axis``² shifts (rows, cols) [projector px] evenly over one period (two squares) in both axes: the
    §5.4.6 stack (the thesis shifted a 24-px board 128 times). Rounded to whole pixels; repeats removed."""
    steps = [np.unique(np.round(np.arange(per_axis) * 2 * side / per_axis).astype(int)) for side in square]
    return np.array([(r, c) for r in steps[0] for c in steps[1]], dtype=int)


def acquire_checkerboards(instruments: ProcamInstruments, store: str | os.PathLike, square: tuple[int, int],
                          shifts: np.ndarray, *, mode: str, delay: float, exposure: float, progress: bool = True,
                          log: Callable[[str], None] = lambda _: None) -> xr.Dataset:
    """One frame per shifted checkerboard (§5.4.6) into a ``checkerboard_capture`` store, resumable: ``mode``
    ``floodlit`` (global shutter, the exposure spanning the whole scan: Nayar's frames) or ``epipolar`` (rolling
    shutter at ``delay``/``exposure``, normally 0 and t_p: the epipolar frames)."""
    shifts = np.asarray(shifts, dtype=int)
    shape = instruments.projector.shape
    coords = {"shift": ("shift", np.arange(len(shifts)), {"units": "1", "long_name": "checkerboard shift number"}),
              "shift_row": ("shift", shifts[:, 0], {"units": "px", "long_name": "board shift in projector rows"}),
              "shift_col": ("shift", shifts[:, 1], {"units": "px", "long_name": "board shift in projector columns"})}
    return pattern_stack(instruments, store, "checkerboard_capture", coords,
                         lambda i: checkerboard(shape, square, tuple(shifts[i])),
                         {"square_px": [int(v) for v in square]}, mode=mode, delay=delay, exposure=exposure,
                         progress=progress, log=log, what=f"{mode} checkerboard",
                         describe=lambda i: f"{mode} board shifted by {tuple(shifts[i])} px")


def acquire_gray_code(instruments: ProcamInstruments, store: str | os.PathLike, *, delay: float, exposure: float,
                      progress: bool = True, log: Callable[[str], None] = lambda _: None) -> xr.Dataset:
    """White, black, then every column and row bit of the projector's Gray code with its inverse
    (:func:`selpath.devices.patterns.gray_code_levels`) into a ``gray_code_capture`` store, resumable, with the rolling
    shutter at ``delay``/``exposure``: an exposure of many rows lets every pixel see the projector rows around
    its own, so the codes tell which row and column light it directly (``selpath.stages.procam.rectify``)."""
    levels, column_bits, row_bits = gray_code_levels(instruments.projector.shape)
    coords = {"pattern": ("pattern", np.arange(len(levels)),
                          {"units": "1", "long_name": "pattern number: white, black, column bits, row bits"})}
    return pattern_stack(instruments, store, "gray_code_capture", coords, lambda i: levels[i] / 255.0,
                         {"column_bits": column_bits, "row_bits": row_bits}, mode="epipolar", delay=delay,
                         exposure=exposure, progress=progress, log=log, what="Gray code",
                         describe=lambda i: f"Gray code pattern {i}")


def pattern_stack(instruments: ProcamInstruments, store: str | os.PathLike, kind: str, coords: dict,
                  pattern_of: Callable[[int], np.ndarray], attrs: Mapping[str, Any], *, mode: str, delay: float,
                  exposure: float, progress: bool, log: Callable[[str], None], what: str,
                  describe: Callable[[int], str]) -> xr.Dataset:
    """One frame per pattern ``pattern_of(i)`` at one delay and exposure into a ``kind`` store over the first of
    ``coords``' dims, resumable: ``floodlit`` (global shutter) or ``epipolar`` (the synchronised rolling
    shutter)."""
    from selpath.pipeline.capture_store import create_capture, missing_frames, write_frame  # zarr: on acquiring
    from selpath.pipeline.store import open_store

    rows, cols = instruments.camera.shape
    refuse_impossible(instruments, [delay], [exposure])
    if mode == "floodlit":
        if not hasattr(instruments.camera, "set_shutter"):
            raise DeviceError("floodlit patterns need a camera with a global-shutter mode (set_shutter)",
                              command="set_shutter", fix="use mode: epipolar, or a camera with a global shutter")
        instruments.camera.set_shutter("global")
    elif hasattr(instruments.camera, "set_shutter"):
        instruments.camera.set_shutter("rolling")  # a camera left in global mode by a floodlit stack
    import dask.array as da

    dim = next(iter(coords))
    count = len(coords[dim][1])
    template = xr.Dataset(
        {"image": ((dim, "row", "col"), da.zeros((count, rows, cols), dtype=np.float32,
                                                 chunks=(1, min(rows, CAPTURE_BAND_ROWS), cols)),
                   {"units": "counts"})},
        coords=coords,
        attrs={"selpath_kind": kind, **instruments.attrs, **attrs, "mode": mode,
               "shutter": "global" if mode == "floodlit" else "rolling", "delay_us": float(delay),
               "exposure_us": float(exposure)})
    with store_lock(store, purpose=kind):
        create_capture(store, template, kind)
        todo = [int(f[dim]) for f in missing_frames(store)["image"]]
        if not todo:
            log(f"   every frame is already captured in {store}")
            return open_store(store)
        log(f"   capturing {len(todo)} {what} frame(s) into {store}"
            + (" (resuming: the others are already captured)" if len(todo) < count else ""))
        _verified(instruments.sync.set_exposure(exposure), exposure, "exposure", instruments)
        _verified(instruments.sync.set_delay(delay), delay, "delay", instruments)
        began = time.perf_counter()
        with Progress(*BAR_COLUMNS, TextColumn("frames"), TimeElapsedColumn(), disable=not show_bars(progress),
                      transient=True) as bar:
            task = bar.add_task("capture", total=len(todo))
            for i in todo:
                instruments.projector.show(pattern_of(i))
                instruments.sync.arm()
                write_frame(store, "image", {dim: i}, instruments.camera.capture())
                bar.update(task, advance=1, description=f"capture: {describe(i)}")
        log(f"   captured {len(todo)} frame(s) in {time.perf_counter() - began:.1f} s")
    return open_store(store)
