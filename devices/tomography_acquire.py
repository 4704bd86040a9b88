"""Acquisition sweeps: drive a rig through its angles and write every frame into a store as it arrives.

The store is pre-allocated (``selpath.pipeline.capture_store.create_capture``) and each frame is a region write followed
by its ``written__`` flag, so a sweep killed at any point keeps every finished frame, and running it
again captures only the missing ones (``selpath.pipeline.capture_store.missing_frames``). A sweep talks only to the
protocols of :mod:`selpath.devices.protocols`: the simulated rig and hardware are driven by the same code.

Order, chosen to change samples once and lights as little as possible: the target at each missing
angle (beam frame, then backlit frame), the dark frame, then the reference at each missing angle.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import xarray as xr
from rich.progress import Progress, TextColumn, TimeElapsedColumn

from selpath.devices.protocols import Camera, LightSource, RotaryStage, SampleChanger
from selpath.devices.serial_stage import angular_distance
from selpath.pipeline.errors import DeviceError
from selpath.pipeline.locks import store_lock
from selpath.pipeline.progress import BAR_COLUMNS, show_bars

KIND = "tomography_capture"


@dataclass
class TomographyRig:
    """The instruments of a tomography sweep, and the attrs (geometry, calibration) its captures carry."""

    stage: RotaryStage
    camera: Camera
    beam: LightSource
    backlight: LightSource
    samples: SampleChanger
    attrs: Mapping[str, Any] = field(default_factory=dict)
    #: largest accepted difference between the commanded angle and the one the stage reports [degree]
    tolerance_deg: float = 0.01

    def close(self) -> None:
        for device in (self.stage, self.camera):
            device.close()


def capture_template(rig: TomographyRig, angles: Sequence[float]) -> xr.Dataset:
    """The full capture cube as lazy zeros (never computed): dims, coords and attrs of the store."""
    import dask.array as da  # on acquiring, not on reading a rig file

    rows, cols = rig.camera.shape
    angles = np.asarray(angles, dtype=float)
    stack = da.zeros((len(angles), rows, cols), dtype=np.float32, chunks=(1, rows, cols))
    counts = {"units": "counts"}
    return xr.Dataset(
        {name: (("angle", "row", "col"), stack, counts) for name in ("target", "reference", "backlit")}
        | {"dark": (("row", "col"), stack[0], counts)},
        coords={"angle": ("angle", angles, {"units": "degree", "long_name": "stage angle φ"})},
        attrs={"selpath_kind": KIND, **rig.attrs},
    )


def acquire_tomography(rig: TomographyRig, store: str | os.PathLike, angles: Sequence[float], *,
                       progress: bool = True, log: Callable[[str], None] = lambda _: None) -> xr.Dataset:
    """Capture target, backlit, dark and reference frames into ``store``; resume if it holds part of the sweep.

    Returns the store opened lazily. A device fault raises :class:`~selpath.pipeline.errors.DeviceError` after
    every frame captured so far is safely written; run the same sweep again to resume. The store is
    locked while the sweep runs: a second sweep into it is refused, naming this one.
    """
    with store_lock(store, purpose="acquire_tomography"):
        return _sweep(rig, store, angles, progress=progress, log=log)


def _sweep(rig: TomographyRig, store: str | os.PathLike, angles: Sequence[float], *, progress: bool,
           log: Callable[[str], None]) -> xr.Dataset:
    from selpath.pipeline.capture_store import create_capture, missing_frames, write_frame  # zarr: on acquiring
    from selpath.pipeline.store import open_store

    angles = [float(a) for a in angles]
    if len(set(np.round(np.asarray(angles) % 360.0, 6))) != len(angles):
        raise ValueError("the sweep repeats an angle (modulo 360°); each angle must be captured once")
    create_capture(store, capture_template(rig, angles), KIND)
    missing = missing_frames(store)
    index = {a: i for i, a in enumerate(angles)}
    todo = {name: sorted(index[f["angle"]] for f in frames) if name != "dark" else frames
            for name, frames in missing.items()}
    total = sum(len(v) for v in todo.values())
    if not total:
        log(f"   every frame is already captured in {store}")
        return open_store(store)
    resuming = total < 3 * len(angles) + 1
    log(f"   capturing {total} frame(s) into {store}" + (" (resuming: the others are already captured)" if resuming
                                                         else ""))
    began = time.perf_counter()
    with Progress(*BAR_COLUMNS, TextColumn("frames"), TimeElapsedColumn(), disable=not show_bars(progress),
                  transient=True) as bar:
        task = bar.add_task("capture", total=total)

        def shoot(variable: str, position: dict[str, int]) -> None:
            frame = rig.camera.capture()
            write_frame(store, variable, position, frame)
            where = f" at φ = {angles[position['angle']]:g}°" if "angle" in position else ""
            bar.update(task, advance=1, description=f"capture: {variable} frame{where}")

        rig.stage.home()
        target_like = sorted(set(todo["target"]) | set(todo["backlit"]))
        if target_like:
            rig.samples.load("target")
            for i in target_like:
                _move(rig, angles[i])
                if i in todo["target"]:
                    rig.backlight.set(False)
                    rig.beam.set(True)
                    shoot("target", {"angle": i})
                if i in todo["backlit"]:
                    rig.beam.set(False)
                    rig.backlight.set(True)
                    shoot("backlit", {"angle": i})
        if todo["dark"]:
            rig.beam.set(False)
            rig.backlight.set(False)
            shoot("dark", {})
        if todo["reference"]:
            rig.samples.load("reference")
            rig.backlight.set(False)
            rig.beam.set(True)
            for i in todo["reference"]:
                _move(rig, angles[i])
                shoot("reference", {"angle": i})
        rig.beam.set(False)
    log(f"   captured {total} frame(s) in {time.perf_counter() - began:.1f} s")
    return open_store(store)


def _move(rig: TomographyRig, angle: float) -> None:
    """Move and make sure the stage confirms the angle: a frame is never recorded at a wrong angle."""
    reached = rig.stage.move_to(angle)
    if angular_distance(reached, angle) > rig.tolerance_deg:
        raise DeviceError(f"stage reports {reached:.3f}° after a move to {angle:.3f}°",
                          command=f"move_to({angle})", fix="home the stage and run the sweep again to resume")
