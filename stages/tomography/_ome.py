"""The OME-Zarr (NGFF 0.5) description of a reconstruction store's volume, so that 3-D viewers open ``sigma`` with its
physical axes (``reconstruct_tv``, ``fbp``, ``reconstruct_scattering`` and the phantom's truth write it)."""

from __future__ import annotations

import numpy as np

#: NGFF names of the length units a rig may use (OME-Zarr axes take these or none)
_NGFF_UNITS = {"m": "meter", "cm": "centimeter", "mm": "millimeter", "um": "micrometer"}


def ome_attrs(z: np.ndarray, y: np.ndarray, x: np.ndarray, unit: str) -> dict:
    """The ``ome`` attr (OME-Zarr 0.5 multiscales, one level) that lets 3-D viewers open a reconstruction store's
    ``sigma`` (slice, y, x) as a volume in the rig's length unit; empty where the grid is not one: fewer than 2
    slices, or spacings that are not uniform.

    The axes keep the array's dim names (NGFF requires them to match its ``dimension_names``): ``slice`` is the
    height axis, with a negative scale, because z falls as the slice (camera row) grows."""
    steps = [np.diff(np.asarray(v, float)) for v in (z, y, x)]
    if len(z) < 2 or not all(np.allclose(d, d[0], rtol=1e-6, atol=0) and d[0] != 0 for d in steps):
        return {}
    ngff = {"unit": _NGFF_UNITS[unit]} if unit in _NGFF_UNITS else {}
    axes = [{"name": name, "type": "space"} | ngff for name in ("slice", "y", "x")]
    transforms = [{"type": "scale", "scale": [float(d[0]) for d in steps]},
                  {"type": "translation", "translation": [float(z[0]), float(y[0]), float(x[0])]}]
    return {"ome": {"version": "0.5", "multiscales": [{"name": "sigma", "axes": axes, "datasets": [
        {"path": "sigma", "coordinateTransformations": transforms}]}]}}
