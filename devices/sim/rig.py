"""The simulated tomography rig: the protocols of :mod:`selpath.devices.protocols` on top of the scene simulator.

The camera renders what the rig's state says it sees: the stage's reported angle, which lights are on
and which sample is loaded. A sweep drives it exactly as it drives hardware. Frames are deterministic
for a given state (noise is seeded by angle, sample and lights), so a resumed acquisition yields the
same store as an uninterrupted one.
"""

from __future__ import annotations

import time

import numpy as np

from selpath.devices.protocols import RotaryStage
from selpath.devices.sim.scene import Scene
from selpath.devices.sim.tomography import SAMPLES, ExitPoints, exit_points, lit_frame, silhouette
from selpath.devices.tomography_acquire import TomographyRig
from selpath.pipeline.errors import DeviceError


class SimRotaryStage:
    """A stage that is exactly where it is told to be (after homing, like the real one)."""

    def __init__(self) -> None:
        self._angle = 0.0
        self._homed = False

    def home(self) -> None:
        self._angle, self._homed = 0.0, True

    def move_to(self, angle_deg: float) -> float:
        if not self._homed:
            raise DeviceError("stage is not homed", port="sim", command=f"MOVE {angle_deg:.3f}",
                              fix="call home() first")
        self._angle = float(angle_deg) % 360.0
        return self._angle

    def position(self) -> float:
        return self._angle

    def close(self) -> None:
        pass


class SimLight:
    def __init__(self, name: str) -> None:
        self.name, self.on = name, False

    def set(self, on: bool) -> None:
        self.on = bool(on)


class SimSampleChanger:
    def __init__(self) -> None:
        self.sample = "target"

    def load(self, sample: str) -> None:
        if sample not in SAMPLES:
            raise DeviceError(f"no sample {sample!r}; the simulated rig holds {SAMPLES}", port="sim")
        self.sample = sample


class SimCamera:
    """Renders the scene as the rig's state shows it: dark + lit object (beam) + lit plane (backlight) + noise."""

    def __init__(self, scene: Scene, stage: RotaryStage, beam: SimLight, backlight: SimLight,
                 samples: SimSampleChanger) -> None:
        self.scene, self.stage, self.beam, self.backlight, self.samples = scene, stage, beam, backlight, samples
        self._seen: tuple[float, ExitPoints] | None = None  # what the pixels see at the last angle

    def _exit_points(self, angle: float) -> ExitPoints:
        if self._seen is None or self._seen[0] != angle:
            self._seen = (angle, exit_points(self.scene, angle))
        return self._seen[1]

    @property
    def shape(self) -> tuple[int, int]:
        return (self.scene.camera.rows, self.scene.camera.cols)

    def capture(self) -> np.ndarray:
        sensor = self.scene.sensor
        angle = self.stage.position()
        signal = np.zeros(self.shape)
        if self.beam.on:
            signal += lit_frame(self.scene, angle, self.samples.sample, self._exit_points(angle))
        if self.backlight.on:
            signal += sensor.backlight * ~silhouette(self.scene, angle, self._exit_points(angle))
        noise = self.scene.effects.noise
        if noise is not None:
            state = [noise.seed, int(round(angle * 1000)) % 360_000, SAMPLES.index(self.samples.sample),
                     int(self.beam.on), int(self.backlight.on)]
            rng = np.random.default_rng(state)
            if noise.gain is not None:
                signal = rng.poisson(np.clip(signal, 0, None) / noise.gain) * noise.gain
            signal = signal + rng.normal(0.0, noise.read_std, self.shape)
        if sensor.frame_interval:
            time.sleep(sensor.frame_interval)
        return np.clip(sensor.dark_level + signal, 0.0, sensor.saturation_level).astype(np.float32)

    def close(self) -> None:
        pass


def simulated_rig(scene: Scene) -> TomographyRig:
    """A :class:`~selpath.devices.tomography_acquire.TomographyRig` of simulated devices showing ``scene``."""
    stage = SimRotaryStage()
    beam, backlight, samples = SimLight("beam"), SimLight("backlight"), SimSampleChanger()
    camera = SimCamera(scene, stage, beam, backlight, samples)
    attrs = scene.stated_geometry().attrs() | {
        "saturation_counts": scene.sensor.saturation_level,
        "rig": "simulated",
        "scene": scene.scene,
        "effects": list(scene.effects.names()),
    }
    return TomographyRig(stage, camera, beam, backlight, samples, attrs)
