"""The scene the simulated procam hardware (serial projector, sync controller, camera) films."""

from __future__ import annotations

from selpath.devices.sim.procam_scene import ProcamScene

SCENE = {
    "scene": "tiny-candle", "background": {"albedo": 0.4},
    "objects": [{"name": "candle", "region": {"kind": "rectangle", "x": [0.2, 0.6], "y": [0.2, 0.8]}, "albedo": 0.9,
                 "effects": {"subsurface": {"width": "3 px", "fraction": 0.6}}}],
    "rig": {"camera_rows": 24, "camera_cols": 32, "projector_rows": 16, "projector_cols": 32,
            "noise": {"gain": 1.0, "read_std": 2.0, "seed": 3}, "jitter": {"std": "2 us"}},
}


def scene(**rig) -> ProcamScene:
    spec = {**SCENE, "rig": SCENE["rig"] | rig}
    return ProcamScene.model_validate(spec)
