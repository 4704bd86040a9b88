"""The small plane-to-ray rig and scene the procam stage tests share, and its capture by the simulator."""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene

RIG = {"camera_rows": 40, "camera_cols": 48, "projector_rows": 40, "projector_cols": 48, "bits": None}


OBJECTS = [
    {"name": "candle", "region": {"kind": "rectangle", "x": [0.1, 0.45], "y": [0.2, 0.8]}, "albedo": 0.9,
     "effects": {"subsurface": {"width": "3 px", "fraction": 0.5}}},
    {"name": "page", "region": {"kind": "rectangle", "x": [0.55, 0.95], "y": [0.1, 0.9]}, "albedo": 0.8,
     "effects": {"specular_interreflection": {"centre": [0.75, 0.5], "reach": 0.3,
                                              "displacement": ["4 px", "9 px"], "strength": 0.5}}},
]


DELAYS = np.arange(-306.0, 307.0, 34.0)  # 2-row steps, delay 0 among them


EXPOSURES = np.array([51.0, 153.0])


def scene(**rig) -> ProcamScene:
    return ProcamScene.model_validate({"scene": "test", "background": {"albedo": 0.3}, "objects": OBJECTS,
                                       "rig": RIG | rig})


def capture_of(s: ProcamScene, delays=DELAYS, exposures=EXPOSURES) -> xr.Dataset:
    """A (delay, exposure, row, col) capture rendered frame by frame, with the attrs the rig records."""
    frames = np.stack([np.stack([tr.render_frame(s, d, e) for e in exposures]) for d in delays])
    return xr.Dataset({"image": (("delay", "exposure", "row", "col"), frames, {"units": "counts"})},
                      coords={"delay": ("delay", delays, {"units": "us"}),
                              "exposure": ("exposure", exposures, {"units": "us"})},
                      attrs={"selpath_kind": "plane_to_ray_capture", **s.rig.attrs()})
