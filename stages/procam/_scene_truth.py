"""The truth of a capture of the simulated rig: the scene it was rendered from, and which object each pixel sees.

The one place a procam stage outside acquisition and the simulated studies reaches into the simulator: ``labels:
scene`` (``_labels``) and the multiplexing study read a capture's truth through it.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.devices.sim.procam_lobes import Tile
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.pipeline.errors import Problem, StageError


def simulated_scene(capture: xr.Dataset, where: str) -> ProcamScene:
    """The scene (rig included) a capture of the simulated rig was rendered from: its ``simulated_scene`` attr."""
    record = capture.attrs.get("simulated_scene")
    if record is None:
        raise StageError(Problem("the capture records no simulated scene: the simulator's truth is known only for "
                                 "captures of the simulated rig", where=where,
                                 fix="wire in a capture acquired with rig: sim"))
    return ProcamScene.model_validate(record)


def scene_labels(capture: xr.Dataset, where: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """Integer codes over the camera's (row, col) (0: background, k: the scene's k-th object) and the objects'
    names, for a capture of the simulated rig."""
    scene = simulated_scene(capture, where)
    tile = Tile.of(scene, 0, scene.rig.camera_rows)
    return (tile.label + 1).reshape(tile.shape), tuple(obj.name for obj in scene.objects)
