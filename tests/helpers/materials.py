"""The simulated materials captures (five translucent materials, §5.4.9) at the thesis's materials sweep."""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath import workflows
from selpath.devices.sim.procam_scene import load_procam_scene
from tests.helpers.procam import capture_of

#: the materials capture's sweep: ±340 µs every 17 µs (one camera row per step) at t_e = 170 µs
SWEEP = np.arange(-340.0, 341.0, 17.0)


SENSOR = {"camera_rows": 120, "camera_cols": 160}


def materials(name: str, seed: int) -> xr.Dataset:
    """A capture of a shipped materials scene over the sweep, with the noise drawn from ``seed``, recording its scene
    as the simulated rig does."""
    s = load_procam_scene(workflows.scene(name))
    s = s.with_rig(**SENSOR, noise=s.rig.noise.model_copy(update={"seed": seed}))
    capture = capture_of(s, SWEEP, np.array([170.0]))
    return capture.assign_attrs(simulated_scene=s.model_dump(mode="json"))
