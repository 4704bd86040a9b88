"""A specular highlight that clips the sensor, its sweep and its true transport, for the clipped-frame tests."""

from __future__ import annotations

import numpy as np

from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from tests.helpers.procam import RIG

# the thesis's sweep shape (delays every 10 rows, exposures of 10, 30 and 50 rows), 9 delays
DELAYS, EXPOSURES = np.arange(-680.0, 681.0, 170.0), np.array([170.0, 510.0, 850.0])


DISK = {"kind": "disk", "centre": [0.5, 0.5], "radius": 0.25}


def highlight_scene(intensity: float, **obj) -> ProcamScene:
    """A dim background (albedo 0.05: 500 counts at intensity 10 000) and a disk that clips."""
    return ProcamScene.model_validate({
        "scene": "highlight", "background": {"albedo": 0.05},
        "objects": [{"name": "highlight", "region": DISK} | obj], "rig": RIG | {"intensity": intensity}})


def truth_of(s: ProcamScene, offsets: np.ndarray) -> np.ndarray:
    cube = np.concatenate([tr.truth_tile(s, t, offsets) for t in tr.tiles(s)], axis=-1)
    return s.rig.intensity * cube.reshape(offsets.size, s.rig.camera_rows, s.rig.camera_cols)
