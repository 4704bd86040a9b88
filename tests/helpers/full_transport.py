"""A small full-transport rig, scene and line sweep (§5.3.1) rendered by the simulator, for the demux_full tests."""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.devices.patterns import vertical_line
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.stages.procam._capture_to_transport import OffsetGrid

RIG = {"camera_rows": 16, "camera_cols": 24, "projector_rows": 16, "projector_cols": 24, "bits": None}


OBJECTS = [
    {"name": "candle", "region": {"kind": "rectangle", "x": [0.05, 0.45], "y": [0.1, 0.9]}, "albedo": 0.9,
     "disparity": "2 px", "effects": {"subsurface": {"width": "1.5 px", "fraction": 0.4}}},
    {"name": "page", "region": {"kind": "rectangle", "x": [0.55, 0.95], "y": [0.1, 0.9]}, "albedo": 0.8,
     "effects": {"specular_interreflection": {"centre": [0.75, 0.5], "reach": 0.5, "gain": 0.0,
                                              "displacement": ["-6 px", "2 px"], "strength": 0.6}}},
]


DELAYS = np.arange(-170.0, 171.0, 34.0)  # 2-row steps over ±10 rows


EXPOSURES = np.array([51.0])


LINES = np.arange(0.0, 23.0, 2.0)  # l_p every 2 columns …


WIDTH = 4.0  # … l_w = 4: each line lights two 2-column cells


GRID = OffsetGrid(start=-8, stop=8)


def scene() -> ProcamScene:
    return ProcamScene.model_validate({"scene": "test", "background": {"albedo": 0.3}, "objects": OBJECTS,
                                       "rig": RIG})


def full_capture(s: ProcamScene) -> xr.Dataset:
    shape = (s.rig.projector_rows, s.rig.projector_cols)
    frames = np.stack([np.stack([np.stack([tr.render_frame(s, d, e, vertical_line(shape, line, WIDTH))
                                           for line in LINES]) for e in EXPOSURES]) for d in DELAYS])
    return xr.Dataset({"image": (("delay", "exposure", "line", "row", "col"), frames, {"units": "counts"})},
                      coords={"delay": ("delay", DELAYS, {"units": "us"}),
                              "exposure": ("exposure", EXPOSURES, {"units": "us"}),
                              "line": ("line", LINES, {"units": "px"})},
                      attrs={"selpath_kind": "full_transport_capture", "line_width_px": WIDTH, **s.rig.attrs()})
