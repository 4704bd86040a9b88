"""Acquisition as a workflow step: ``acquire_tomography`` on the simulated rig or on hardware.

Acquisition stages are the one exception to lazy stages: they drive instruments, so they run when the
workflow runs and fill their own store frame by frame (``writes=``). The engine records the store's
provenance when the sweep is complete and never rewrites it; a killed run leaves a store without
provenance, and running the workflow again resumes at the first missing frame.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import pydantic
import xarray as xr

from selpath.devices.hardware import hardware_rig, load_hardware
from selpath.devices.sim.rig import simulated_rig
from selpath.devices.sim.scene import load_scene
from selpath.devices.tomography_acquire import acquire_tomography as sweep
from selpath.geometry.rig import RIG_ATTRS, camera_attr_problems
from selpath.pipeline.constraints import StorePath, memory_problems
from selpath.pipeline.kinds import ANGLE_UNITS, SENSOR_COUNTS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import read_file, sweep_log
from selpath.stages._sweeps import Sweep


#: frames of the rotating object (DESIGN §2): what ``acquire_tomography``, the simulators and ``import_capture`` make
def stated_axis_advice(capture: xr.Dataset) -> list[str]:
    """:func:`selpath.stages.tomography._axis_check.stated_axis_advice` (imported when a store is checked: the fits
    are not needed to declare the kind)."""
    from selpath.stages.tomography._axis_check import stated_axis_advice as check

    return check(capture)


TOMOGRAPHY_CAPTURE = CubeKind(
    name="tomography_capture",
    description="frames of the rotating object: target, reference (no inclusion), backlit, dark",
    variables={
        "target": Variable(("angle", "row", "col"), description="object with the inclusion", **SENSOR_COUNTS),
        "reference": Variable(("angle", "row", "col"), description="same object without it (§4.4.2)",
                              **SENSOR_COUNTS),
        "backlit": Variable(("angle", "row", "col"), False, "silhouettes against a lit plane (§4.2.6)",
                            **SENSOR_COUNTS),
        "dark": Variable(("row", "col"), False, "sensor offset with all lights off", **SENSOR_COUNTS),
    },
    coord_units={"angle": ANGLE_UNITS},
    attrs=RIG_ATTRS,
    attr_checks=(camera_attr_problems,),
    data_checks=(stated_axis_advice,),
)


class AngleSweep(Sweep):
    """Stage angles start, start+step, … below stop, in degrees: stop > start, step > 0, at most
    :attr:`MAX_VALUES` angles (a sweep of 0.0036° steps over a full turn; far beyond any stage)."""

    MAX_VALUES: ClassVar[int] = 100_000
    WHAT: ClassVar[str] = "angles"
    LABEL: ClassVar[str] = "angle sweep"
    INCLUSIVE: ClassVar[bool] = False
    start: float = 0.0
    stop: float = pydantic.Field(360.0, description="exclusive end, degree")
    step: float = pydantic.Field(1.0, gt=0, description="degree")

    def values(self) -> np.ndarray:
        return np.arange(self.start, self.stop - 1e-9 * self.step, self.step)


def _precheck(settings) -> list[str]:
    """Read the scene or rig file at validation time: a bad file fails before anything moves."""
    source = settings.scene if settings.rig == "sim" else settings.hardware
    name = "scene" if settings.rig == "sim" else "hardware"
    if not source:
        return [f"rig {settings.rig!r} needs the setting {name!r} (a YAML file)"]
    spec, problems = read_file(load_scene if settings.rig == "sim" else load_hardware, source, name)
    if problems:
        return problems
    if len(settings.angles.values()) == 0:
        return ["the angle sweep is empty"]
    if settings.rig == "sim":  # the simulator traces one ray per pixel: (rows × cols, 3) float64 end points
        rows, cols = spec.camera.rows, spec.camera.cols
        return memory_problems(rows * cols * 3 * 8, f"the simulated camera's rays ({rows:,} × {cols:,} px, "
                               "3 float64 coordinates each)", fix="lower camera.rows or camera.cols in the scene")
    return []


def _identity(settings) -> dict:
    source = Path(settings.scene if settings.rig == "sim" else settings.hardware)
    digest = hashlib.sha256(source.read_bytes()).hexdigest() if source.is_file() else None
    return {"rig": settings.rig, "file": str(source), "sha256": digest}


@stage("acquire_tomography", kind=TOMOGRAPHY_CAPTURE, precheck=_precheck, identity=_identity,
       writes=lambda settings: settings.store,
       variables=lambda settings: ["target", "reference", "backlit", "dark"])  # as capture_template writes
def acquire_tomography(
    *,
    store: StorePath,
    rig: Literal["sim", "hardware"] = "sim",
    scene: StorePath = "",
    hardware: StorePath = "",
    angles: AngleSweep = AngleSweep(),  # noqa: B008 (a frozen model: immutable default)
    progress: bool = True,
) -> xr.Dataset:
    """Sweep the stage and capture target, backlit, dark and reference frames into ``store``, resumably.

    Parameters
    ----------
    store : str
        Zarr store the frames are written into as they arrive; an existing store of the same sweep is
        resumed at its first missing frame, a different one is refused.
    rig : str
        ``sim`` (the scene simulator) or ``hardware`` (serial stage, OpenCV camera, operator).
    scene : str
        Scene file for ``rig: sim`` (``workflows/scenes/*.yaml``).
    hardware : str
        Rig file for ``rig: hardware`` (``docs/devices.md``).
    angles : AngleSweep
        Stage angles {start, stop, step} [degree]; stop > start, at most 100 000 angles.
    progress : bool
        Show a progress bar.

    Returns
    -------
    xr.Dataset
        A ``tomography_capture`` cube: the store ``store``: ``target`` and ``reference`` [counts] over (angle, row,
        col), with ``backlit`` and ``dark`` where the rig has them, and the rig geometry in its attrs; written angle by
        angle, opened lazily.

    References
    ----------
    Thesis §4.2.5 Setup of the measurement.
    """
    if rig == "sim":
        instruments = simulated_rig(load_scene(scene))
    else:
        instruments = hardware_rig(load_hardware(hardware))
    try:
        return sweep(instruments, store, angles.values(), progress=progress, log=sweep_log(progress))
    finally:
        instruments.close()
