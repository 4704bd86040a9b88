"""Simulated captures as lazy stages (frames are rendered chunk by chunk, only when computed)."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pydantic
import xarray as xr
from dask.base import tokenize

from devices.sim.parallel_light import Rod, render
from pipeline.registry import stage

_FRAME_BYTES_PER_CHUNK = 64 * 2**20


class AngleSweep(pydantic.BaseModel):
    """Stage angles start, start+step, … below stop, in degrees."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    start: float = 0.0
    stop: float = pydantic.Field(360.0, description="exclusive end, degree")
    step: float = pydantic.Field(1.0, gt=0, description="degree")

    def values(self) -> np.ndarray:
        return np.arange(self.start, self.stop - 1e-9 * self.step, self.step)


class RodSpec(pydantic.BaseModel):
    """A vertical rod inside the object: centre (x, y) and radius in the length unit, extra σ per unit length."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    x: float
    y: float
    radius: float = pydantic.Field(gt=0)
    sigma: float = pydantic.Field(ge=0)


_DEFAULT_RODS = (RodSpec(x=6.0, y=3.0, radius=2.0, sigma=0.15),)


@stage("simulate_parallel_capture")
def simulate_parallel_capture(
    *,
    angles: AngleSweep = AngleSweep(),  # noqa: B008 (a frozen model: immutable default)
    n_rows: int = 8,
    n_cols: int = 256,
    pixel_size: float = 0.2,
    radius: float = 20.0,
    rods: tuple[RodSpec, ...] = _DEFAULT_RODS,
    medium_sigma: float = 0.01,
    intensity: float = 3000.0,
    skin_transmittance: float = 0.8,
    dark_level: float = 64.0,
    saturation_level: float = 4095.0,
    backlight: float = 2000.0,
    noise_std: float = 0.0,
    seed: int = 0,
) -> xr.Dataset:
    """A tomography capture of a cylinder with rods under parallel light (θ_l = 0, orthographic camera).

    The §4.4.2 comparison setting, in closed form (devices.sim.parallel_light): lazy frames, one dask
    chunk per group of angles, identical under any chunking or scheduler.

    Parameters
    ----------
    angles : AngleSweep
        Stage angles {start, stop, step} [degree].
    n_rows : int
        Sensor rows (slices along the rotation axis).
    n_cols : int
        Sensor columns.
    pixel_size : float
        Object-space size of a pixel [mm].
    radius : float
        Radius of the cylinder [mm].
    rods : list of RodSpec
        Rod inclusions {x, y, radius [mm], sigma [1/mm]}.
    medium_sigma : float
        Absorption of the medium, present in target and reference [1/mm].
    intensity : float
        Counts a pixel would get through a non-absorbing object [counts].
    skin_transmittance : float
        Transmittance of the diffusing skin, crossed twice [1].
    dark_level : float
        Sensor offset [counts].
    saturation_level : float
        Full-well count; direct views of the source saturate [counts].
    backlight : float
        Counts of the lit diffuse plane in backlit frames [counts].
    noise_std : float
        Gaussian read noise; 0 for none [counts].
    seed : int
        Seed of the noise.
    """
    angle_values = angles.values()
    frame_bytes = n_rows * n_cols * 4
    per_chunk = max(1, min(len(angle_values), _FRAME_BYTES_PER_CHUNK // frame_bytes))
    lazy_angles = da.from_array(np.stack([angle_values, np.arange(len(angle_values))], axis=1),
                                chunks=(per_chunk, 2))
    solids = tuple(Rod(r.x, r.y, r.radius, r.sigma) for r in rods)
    options = dict(n_rows=n_rows, n_cols=n_cols, pixel_size=pixel_size, radius=radius, rods=solids,
                   medium_sigma=medium_sigma, intensity=intensity, skin_transmittance=skin_transmittance,
                   dark_level=dark_level, saturation_level=saturation_level, backlight=backlight,
                   noise_std=noise_std, seed=seed)

    def frames(name: str) -> da.Array:
        def block(a: np.ndarray) -> np.ndarray:
            return render(a[:, 0], angle_index=a[:, 1].astype(int), **options)[name]

        return da.map_blocks(block, lazy_angles, dtype=np.float32, drop_axis=1, new_axis=[1, 2],
                             chunks=(lazy_angles.chunks[0], (n_rows,), (n_cols,)),
                             name=f"simulate-{name}-{tokenize(repr(options), angle_values, name)}")

    dims = ("angle", "row", "col")
    dark = np.full((n_rows, n_cols), dark_level, dtype=np.float32)
    return xr.Dataset(
        {name: (dims, frames(name), {"units": "counts"}) for name in ("target", "reference", "backlit")}
        | {"dark": (("row", "col"), dark, {"units": "counts"})},
        coords={"angle": ("angle", angle_values, {"units": "degree", "long_name": "stage angle φ"})},
        attrs={
            "selpath_kind": "tomography_capture",
            "camera_model": "orthographic",
            "light_angle_deg": 0.0,
            "length_unit": "mm",
            "pixel_size": pixel_size,
            "saturation_level": saturation_level,
            "simulator": "devices.sim.parallel_light",
        },
    )

