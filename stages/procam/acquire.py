"""Projector–camera acquisition as workflow steps (§5.2.3, §5.3, §5.3.2).

``acquire_plane_to_ray`` and ``acquire_full_transport`` drive the simulated rig (``rig: sim``, a scene from
``workflows/scenes/``) through a delay–exposure sweep, frame by frame and resumably, like
``acquire_tomography``. ``acquire_scan_calibration`` films a white target with the camera in global-shutter
mode at several exposures and delays, for :func:`selpath.stages.procam.calibrate.calibrate_scan_speed`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
import pydantic
import xarray as xr

from selpath.devices.patterns import white
from selpath.devices.procam_acquire import ProcamInstruments, capture_template, sweep_frames
from selpath.devices.procam_acquire import acquire_full_transport as full_sweep
from selpath.devices.procam_acquire import acquire_plane_to_ray as plane_sweep
from selpath.devices.procam_hardware import load_procam_hardware, procam_hardware_rig
from selpath.devices.sim.procam_rig import simulated_procam_rig
from selpath.devices.sim.procam_scene import ProcamRig, ProcamScene, load_procam_scene
from selpath.devices.sim.sync_firmware import DEFAULT_LIMITS
from selpath.pipeline.constraints import Count, Positive, StorePath, memory_problems
from selpath.pipeline.errors import SelpathError
from selpath.pipeline.kinds import PX_UNITS, SENSOR_COUNTS, TIME_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import file_identity, read_file, sweep_log
from selpath.stages._sweeps import Sweep

_FRAME = ("row", "col")
#: what a projector–camera capture must say about its sensor: without them clipped frames pass as data
CAMERA_LEVELS = {
    "saturation_counts": "raw counts at and above which a pixel is clipped (kept as lower bounds on the light)",
    "dark_level_counts": "raw counts of an unlit pixel (black level), subtracted before demultiplexing",
}
PLANE_TO_RAY_CAPTURE = CubeKind(
    name="plane_to_ray_capture",
    description="image stacks over sync delay and exposure (§5.2.3)",
    variables={"image": Variable(("delay", "exposure", *_FRAME), **SENSOR_COUNTS)},
    coord_units={"delay": TIME_UNITS, "exposure": TIME_UNITS},
    attrs={"scan_speed_px_per_us": "projector scan speed v_p, projector rows per µs",
           "line_time_us": "projector line time t_p, µs", **CAMERA_LEVELS},
)
FULL_TRANSPORT_CAPTURE = CubeKind(
    name="full_transport_capture",
    description="stacks over delay, exposure and projected line position (§5.3.1)",
    variables={"image": Variable(("delay", "exposure", "line", *_FRAME), **SENSOR_COUNTS)},
    coord_units={"delay": TIME_UNITS, "exposure": TIME_UNITS, "line": PX_UNITS},
    attrs={"scan_speed_px_per_us": "projector scan speed v_p, projector rows per µs",
           "line_time_us": "projector line time t_p, µs",
           "line_width_px": "width l_w of the projected vertical line, projector columns", **CAMERA_LEVELS},
)


class TimeSweep(Sweep):
    """Times start, start+step, …, up to and including stop [µs]: stop ≥ start (equal: the one value start),
    step > 0, at most :attr:`MAX_VALUES` values (a 1 µs step over ±50 ms, far beyond a controller's range)."""

    MAX_VALUES: ClassVar[int] = 100_000
    WHAT: ClassVar[str] = "delays"
    LABEL: ClassVar[str] = "delays sweep"
    start: float
    stop: float
    step: float = pydantic.Field(gt=0, description="µs")

    def values(self) -> np.ndarray:
        return np.round(np.arange(self.start, self.stop + 1e-9 * self.step, self.step), 6)


class PixelSweep(TimeSweep):
    """Projector columns start, start+step, …, up to and including stop [px]: stop ≥ start, step > 0, at most
    :attr:`MAX_VALUES` lines (a line every 0.1 px across a 10 000-column projector)."""

    MAX_VALUES: ClassVar[int] = 100_000
    WHAT: ClassVar[str] = "lines"
    LABEL: ClassVar[str] = "lines sweep"


#: exposures t_e [µs]: each > 0, at least one
Exposures = Annotated[tuple[Positive, ...], pydantic.Field(min_length=1)]
#: a sensor size [rows, cols], each at least 1
SensorSize = tuple[Count, Count]


#: changes to a scene's rig: ``selpath.devices.sim.procam_scene.ProcamRig`` fields and their values
RigChanges = dict[str, Any]


def acquisition_scene(scene: StorePath, sensor: SensorSize | None,
                      rig_changes: RigChanges | None = None) -> ProcamScene:
    """The scene file's scene, its rig changed by ``rig_changes`` and ``sensor`` (checked as the file is)."""
    spec = load_procam_scene(scene)
    changes = dict(rig_changes or {})
    if sensor is not None:
        changes |= {"camera_rows": sensor[0], "camera_cols": sensor[1]}
    if not changes:
        return spec
    try:
        rig = ProcamRig.model_validate(spec.rig.model_dump(mode="json") | changes)
    except pydantic.ValidationError as exc:
        raise SelpathError("rig_changes: " + "; ".join(
            f"{'.'.join(str(p) for p in error['loc']) or 'rig'}: {error['msg']}" for error in exc.errors())) from None
    return spec.model_copy(update={"rig": rig})


def frame_problems(spec: ProcamScene) -> list[str]:
    """One camera frame (rows × cols float32) and one projector pattern (rows × cols float64) in memory."""
    rig = spec.rig
    return (memory_problems(rig.camera_rows * rig.camera_cols * 4, f"one camera frame ({rig.camera_rows:,} × "
                            f"{rig.camera_cols:,} px float32)", fix="a smaller sensor [rows, cols]")
            + memory_problems(rig.projector_rows * rig.projector_cols * 8, f"one projector pattern "
                              f"({rig.projector_rows:,} × {rig.projector_cols:,} px float64)",
                              fix="fewer projector_rows or projector_cols in the scene's rig"))


def _checked_scene(settings, sweep) -> list[str]:
    """Read the scene, check ``sweep(scene) = (delays, exposures)`` against the controller's limits and a frame
    against this machine's memory at validation time."""
    spec, problems = read_file(lambda path: acquisition_scene(path, settings.sensor, settings.rig_changes),
                               settings.scene,
                               "scene")
    if problems:
        return problems
    delays, exposures = sweep(spec)
    return DEFAULT_LIMITS.problems(delays, exposures) + frame_problems(spec)


def acquisition_precheck(settings, sweep) -> list[str]:
    """The hardware rig file's problems, or the scene's against ``sweep(scene) = (delays, exposures)``."""
    if getattr(settings, "rig", "sim") == "hardware":
        return _hardware_problems(settings)
    if not settings.scene:
        return ["rig 'sim' needs the setting 'scene' (a projector-camera scene file)"]
    return _checked_scene(settings, sweep)


def _precheck(settings) -> list[str]:
    return acquisition_precheck(settings, lambda _: (settings.delays.values(), settings.exposures))


def _hardware_problems(settings) -> list[str]:
    """Read the rig file at validation time; the controller's limits are read (and a sweep it cannot do is
    refused) when the acquisition opens it, before anything moves."""
    if not settings.hardware:
        return ["rig 'hardware' needs the setting 'hardware' (a projector-camera rig file, docs/devices.md)"]
    problems = [f"{name} is a setting of the simulated rig (rig: sim); a hardware rig's sensor is the camera's"
                for name in ("scene", "sensor", "rig_changes") if getattr(settings, name)]
    return problems + read_file(load_procam_hardware, settings.hardware, "hardware")[1]


def acquisition_identity(settings) -> dict:
    source = settings.hardware if getattr(settings, "rig", "sim") == "hardware" else settings.scene
    return {"rig": settings.rig, **file_identity(source), "sensor": settings.sensor,
            "rig_changes": settings.rig_changes}


@contextmanager
def _simulated_rig(scene: StorePath, sensor: SensorSize | None, rig_changes: RigChanges | None
                   ) -> Iterator[ProcamInstruments]:
    """The simulated rig showing ``scene`` (at ``sensor`` size and with ``rig_changes`` when given), closed when
    the sweep ends."""
    instruments = simulated_procam_rig(acquisition_scene(scene, sensor, rig_changes))
    try:
        yield instruments
    finally:
        instruments.close()


@contextmanager
def acquisition_rig(rig: str, scene: StorePath, hardware: StorePath, sensor: SensorSize | None,
         rig_changes: RigChanges | None) -> Iterator[ProcamInstruments]:
    """The simulated rig (``sim``) or the rig a hardware file describes (``hardware``), closed when the sweep
    ends."""
    if rig == "sim":
        with _simulated_rig(scene, sensor, rig_changes) as instruments:
            yield instruments
        return
    instruments = procam_hardware_rig(load_procam_hardware(hardware))
    try:
        yield instruments
    finally:
        instruments.close()


def _acquisition(name: str, kind: CubeKind):
    """``@stage(name, kind=kind)`` for a projector–camera acquisition: validated against the scene and the
    controller's limits, identified by the scene file, filling its own store; the settings every acquisition
    shares (rig, sensor, rig changes, progress) are documented once, here."""

    def register(func):
        doc = func.__doc__.rstrip()
        at = doc.find("\n\n    Returns\n")  # the shared settings end the Parameters section, before Returns
        shared = _SHARED_DOCS.rstrip()
        func.__doc__ = (doc + "\n" + _SHARED_DOCS) if at < 0 else (doc[:at] + "\n" + shared + doc[at:] + "\n")
        return stage(name, kind=kind, precheck=_precheck, identity=acquisition_identity,
                     writes=lambda settings: settings.store, variables=lambda settings: ["image"])(func)

    return register


_SHARED_DOCS = """    sensor : [rows, cols] or None
        Render at this sensor size instead of the scene rig's (scenes are drawn in fractions of the image); a
        frame that would not fit in memory is refused.
    rig_changes : dict or None
        Changes to the scene's rig, checked as the scene file is: ``intensity`` (counts of a white pixel lit for
        a whole line time: a dimmer projector), ``dark_level`` and ``saturation_level`` [counts], ``noise``
        {gain, read_std, seed}, ``jitter``, … (``selpath.devices.sim.procam_scene.ProcamRig``; docs/devices.md).
    progress : bool
        Show a progress bar.
    """


@_acquisition("acquire_plane_to_ray", PLANE_TO_RAY_CAPTURE)
def acquire_plane_to_ray(
    *,
    store: StorePath,
    delays: TimeSweep,
    exposures: Exposures,
    hdr: Literal["off", "auto"] = "off",
    rig: Literal["sim", "hardware"] = "sim",
    scene: StorePath = "",
    hardware: StorePath = "",
    sensor: SensorSize | None = None,
    rig_changes: RigChanges | None = None,
    progress: bool = True,
) -> xr.Dataset:
    """White pattern, every (delay, exposure) → a ``(delay, exposure, row, col)`` store, frame by frame, resumable.

    Parameters
    ----------
    store : str
        Zarr store the frames land in; an existing store of the same sweep resumes.
    rig : str
        ``sim``: the transport simulator showing ``scene``; ``hardware``: the sync controller, projector and
        camera of the ``hardware`` rig file (docs/devices.md).
    scene : str
        Projector–camera scene file (``workflows/scenes/*.yaml``), for ``rig: sim``.
    hardware : str
        Projector–camera rig file, for ``rig: hardware``.
    delays : TimeSweep
        Sync delays t_d {start, stop, step} [µs], stop included (stop ≥ start), at most 100 000 delays.
    exposures : list of float
        Exposures t_e [µs].
    hdr : str
        ``auto``: before the sweep, preview the epipolar frame (t_d = 0) at the shortest exposure and, halving it
        while pixels clip (down to 2 t_p), add the exposure that clips fewest to the sweep: one
        more exposure for every delay, so demultiplexing sees the light the longer ones clip (HDR from the
        sweep). The log and the store's ``hdr_*`` attrs state what was tried and what it cost in captures; a
        highlight that clips within one line time gets nothing added (only attenuation helps). ``off``: the
        exposures as given.

    Returns
    -------
    xr.Dataset
        A ``plane_to_ray_capture`` cube: the store ``store``: ``image`` [counts] over (delay, exposure, row, col),
        written frame by frame and opened lazily, with the rig's timing in its attrs.

    References
    ----------
    Thesis §5.2.2 Light Multiplexing using Delay and Exposure; §5.2.3 Delay-Exposure Image Stacks.
    """
    with acquisition_rig(rig, scene, hardware, sensor, rig_changes) as instruments:
        return plane_sweep(instruments, store, delays.values(), exposures, hdr=hdr == "auto", progress=progress,
                           log=sweep_log(progress))


@_acquisition("acquire_full_transport", FULL_TRANSPORT_CAPTURE)
def acquire_full_transport(
    *,
    store: StorePath,
    delays: TimeSweep,
    exposures: Exposures,
    lines: PixelSweep,
    line_width: Positive,
    rig: Literal["sim", "hardware"] = "sim",
    scene: StorePath = "",
    hardware: StorePath = "",
    sensor: SensorSize | None = None,
    rig_changes: RigChanges | None = None,
    progress: bool = True,
) -> xr.Dataset:
    """A vertical line at each l_p × every (delay, exposure) → ``(delay, exposure, line, row, col)``, resumable.

    Parameters
    ----------
    store : str
        Zarr store the frames land in; an existing store of the same sweep resumes.
    rig : str
        ``sim``: the transport simulator showing ``scene``; ``hardware``: the sync controller, projector and
        camera of the ``hardware`` rig file (docs/devices.md).
    scene : str
        Projector–camera scene file (``workflows/scenes/*.yaml``), for ``rig: sim``.
    hardware : str
        Projector–camera rig file, for ``rig: hardware``.
    delays : TimeSweep
        Sync delays t_d [µs], stop included (stop ≥ start), at most 100 000 delays.
    exposures : list of float
        Exposures t_e [µs].
    lines : PixelSweep
        Line centres l_p {start, stop, step} [px], stop included (stop ≥ start), at most 100 000 lines.
    line_width : float
        Line width l_w [px].

    Returns
    -------
    xr.Dataset
        A ``full_transport_capture`` cube: the store ``store``: ``image`` [counts] over (delay, exposure, line, row,
        col), written frame by frame and opened lazily, with the rig's timing in its attrs.

    References
    ----------
    Thesis §5.3 Acquisition of full light transport; §5.3.1 Illumination multiplexing.
    """
    with acquisition_rig(rig, scene, hardware, sensor, rig_changes) as instruments:
        return full_sweep(instruments, store, delays.values(), exposures, lines.values(), line_width,
                          progress=progress, log=sweep_log(progress))


@_acquisition("acquire_scan_calibration", PLANE_TO_RAY_CAPTURE)
def acquire_scan_calibration(
    *,
    store: StorePath,
    scene: StorePath,
    delays: TimeSweep,
    exposures: Exposures,
    rig: Literal["sim"] = "sim",
    sensor: SensorSize | None = None,
    rig_changes: RigChanges | None = None,
    progress: bool = True,
) -> xr.Dataset:
    """White pattern with the camera in global-shutter mode at every (delay, exposure), for
    :func:`calibrate_scan_speed` (§5.3.2): each frame shows the band of rows the scan lit during t_e.

    Parameters
    ----------
    store : str
        Zarr store the frames land in.
    scene : str
        Scene file (a flat white target is best).
    rig : str
        ``sim``: the transport simulator (a hardware rig's camera would need a global-shutter mode: not yet).
    delays : TimeSweep
        Trigger delays after VSYNC [µs], stop included (stop ≥ start), at most 100 000 delays; the band must stay
        inside the sensor.
    exposures : list of float
        Exposures [µs]; each must exceed t_p plus one row period for a fully lit row.

    Returns
    -------
    xr.Dataset
        A ``plane_to_ray_capture`` cube: the store ``store``: ``image`` [counts] over (delay, exposure, row, col), taken
        in global-shutter mode, for ``calibrate_scan_speed``.

    References
    ----------
    Thesis §5.3.2 Hardware.
    """
    with _simulated_rig(scene, sensor, rig_changes) as instruments:
        if not hasattr(instruments.camera, "set_shutter"):
            raise SelpathError("the scan calibration needs a camera with a global-shutter mode (set_shutter)")
        instruments.camera.set_shutter("global")
        template = capture_template(instruments, PLANE_TO_RAY_CAPTURE.name, delays.values(), exposures,
                                    extra_attrs={"shutter": "global"})
        pattern = white(instruments.projector.shape)
        return sweep_frames(instruments, store, template, PLANE_TO_RAY_CAPTURE.name,
                            lambda _: instruments.projector.show(pattern), progress,
                            sweep_log(progress))
