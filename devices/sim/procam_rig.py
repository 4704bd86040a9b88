"""The simulated projector–camera rig: sync controller, projector and rolling-shutter camera on top of the
transport simulator (``selpath.devices.sim.procam_transport``), behind the protocols of
:mod:`selpath.devices.protocols`.

The camera renders what the rig's state says: the delay and exposure the controller holds (plus the
rig's true sync offset, which only a calibration reveals) and the pattern on the projector. Like the
real circuit, a frame needs the trigger armed, and a new setting disarms it. Frames are deterministic for
a given state, so a resumed sweep writes the same frames as an uninterrupted one.
"""

from __future__ import annotations

import time

import numpy as np

from selpath.devices.protocols import SyncLimits
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.devices.sim.procam_transport import render_frame
from selpath.devices.sim.sync_firmware import DEFAULT_LIMITS, SimSyncController
from selpath.pipeline.errors import DeviceError


class SimProjector:
    def __init__(self, shape: tuple[int, int]) -> None:
        self._shape = shape
        self.pattern: np.ndarray | None = None  # None: white

    @property
    def shape(self) -> tuple[int, int]:
        return self._shape

    def show(self, pattern: np.ndarray) -> None:
        pattern = np.asarray(pattern, dtype=float)
        if pattern.shape != self._shape:
            raise DeviceError(f"pattern is {pattern.shape}; the projector is {self._shape}", port="sim",
                              command="show")
        self.pattern = None if np.all(pattern == 1.0) else pattern

    def close(self) -> None:
        pass


class SimRollingShutterCamera:
    """A rolling-shutter camera triggered by the sync controller, rendering ``scene`` by time integration."""

    def __init__(self, scene: ProcamScene, sync: SimSyncController, projector: SimProjector) -> None:
        self.scene, self.sync, self.projector = scene, sync, projector
        self.shutter = "rolling"

    def set_shutter(self, mode: str) -> None:
        """``rolling`` (synchronised to the scan) or ``global`` (all rows expose t_e after VSYNC + delay:
        the mode of the v_p calibration, §5.3.2)."""
        if mode not in ("rolling", "global"):
            raise DeviceError(f"unknown shutter mode {mode!r}", port="sim", command="set_shutter")
        self.shutter = mode

    @property
    def shape(self) -> tuple[int, int]:
        return (self.scene.rig.camera_rows, self.scene.rig.camera_cols)

    def capture(self) -> np.ndarray:
        status = self.sync.status()
        if not status.armed:
            raise DeviceError("capture without an armed trigger: the frame would not be synchronised", port="sim",
                              command="capture", fix="arm the sync controller after setting delay and exposure")
        frame = render_frame(self.scene, status.delay_us, status.exposure_us, self.projector.pattern,
                             shutter=self.shutter)
        self.sync.disarm()  # one frame per trigger
        if self.scene.rig.frame_interval:
            time.sleep(self.scene.rig.frame_interval * 1e-6)
        return frame

    def close(self) -> None:
        pass


def simulated_procam_rig(scene: ProcamScene, limits: SyncLimits = DEFAULT_LIMITS):
    """A :class:`~selpath.devices.procam_acquire.ProcamInstruments` of simulated devices showing ``scene``."""
    from selpath.devices.procam_acquire import ProcamInstruments

    rig = scene.rig
    sync = SimSyncController(limits)
    projector = SimProjector((rig.projector_rows, rig.projector_cols))
    camera = SimRollingShutterCamera(scene, sync, projector)
    # the whole scene as simulated (after any sensor or rig changes), what a study needs for the simulator's truth;
    # without the frame pacing, which changes no frame (a sweep resumed at another pace is the same sweep)
    attrs = rig.attrs() | {"rig": "simulated", "scene": scene.scene, "effects": list(scene.effect_names()),
                           "simulated_scene": scene.model_dump(mode="json", exclude={"rig": {"frame_interval"}})}
    return ProcamInstruments(sync, projector, camera, attrs)


class FakeProcamHardware:
    """The simulated rig behind the hardware path, for tests of ``rig: hardware``: the fake sync firmware on a
    pseudo-terminal (the sync and projector protocols of ``docs/devices.md``, with its faults) driving a
    simulated projector, and a rolling-shutter camera that renders what the firmware holds. ``port`` is what a
    rig file's ``sync.url`` names; ``camera`` stands in for the OpenCV camera. A context manager."""

    def __init__(self, scene: ProcamScene, faults=None, *, limits: SyncLimits = DEFAULT_LIMITS, slots: int = 8):
        from selpath.devices.sim.sync_firmware import FakeSyncFirmware

        rig = scene.rig
        self.projector = SimProjector((rig.projector_rows, rig.projector_cols))
        self.firmware = FakeSyncFirmware(faults, limits=limits, screen=self.projector,
                                         projector_shape=(rig.projector_rows, rig.projector_cols), slots=slots)
        self.camera = SimRollingShutterCamera(scene, self.firmware.controller, self.projector)
        self.port = self.firmware.port

    def __enter__(self) -> FakeProcamHardware:
        self.firmware.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.firmware.close()
