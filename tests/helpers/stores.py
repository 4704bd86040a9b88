"""A minimal valid store of every installed kind, and ways to damage one, for the store and corruption tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from selpath.pipeline.kinds import LENGTH_UNITS
from selpath.pipeline.registry import default_registry

#: every installed kind (selpath's own are declared beside the stages that make them)
KINDS = default_registry().kinds


SIZES = {"angle": 3, "row": 4, "col": 5, "vertex": 3, "xy": 2, "slice": 2, "delay": 3, "exposure": 2, "line": 2,
         "offset": 3, "du": 2, "dv": 3, "theta": 4, "x": 5, "y": 5, "rgba": 4, "light_angle": 2, "method": 2,
         "iteration": 3, "shift": 2, "max_delay": 2, "signal": 2, "code": 2, "pattern": 2,
         "light_angle_trial": 3, "pose": 2, "i": 3, "j": 3, "k": 5, "m": 4, "byte": 64, "material": 3, "view": 3,
         "site": 2, "distance": 4, "render": 2,
         "candidate": 3, "distance_bin": 4, "band": 2, "sample": 3, "window": 3}


def minimal(kind: str) -> xr.Dataset:
    """A small valid cube of ``kind`` built from its schema: every variable, coordinate unit and attr."""
    spec = KINDS[kind]
    rng = np.random.default_rng(0)
    ds = xr.Dataset({name: (var.dims, rng.random(tuple(SIZES[d] for d in var.dims)).astype(np.float32))
                     for name, var in spec.variables.items()})
    for dim, units in spec.coord_units.items():
        unit = "mm" if units == LENGTH_UNITS else sorted(units)[0]
        ds = ds.assign_coords({dim: (dim, np.arange(SIZES[dim], dtype=float), {"units": unit})})
    attrs = dict.fromkeys(spec.attrs, 1.0)
    if "camera_model" in attrs:
        attrs.update(camera_model="orthographic", pixel_size=0.1, length_unit="mm")
    return ds.assign_attrs(attrs)


def damage_chunk(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif how == "garbage":
        middle = len(data) // 2
        path.write_bytes(data[:middle] + bytes(255 - b for b in data[middle:middle + 8]) + data[middle + 8:])
    else:
        path.unlink()
