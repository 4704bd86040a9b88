"""Simulated captures as lazy stages (frames are rendered chunk by chunk, only when computed)."""

from __future__ import annotations

from typing import Annotated

import dask.array as da
import numpy as np
import pydantic
import xarray as xr
from dask.base import tokenize

from devices.geometry import OrthographicCamera
from devices.sim.parallel_light import Rod, render
from pipeline.constraints import Count, Index, NonNegative, Positive, memory_problems
from pipeline.registry import stage
from stages.tomography.acquire import AngleSweep

_FRAME_BYTES_PER_CHUNK = 64 * 2**20


class RodSpec(pydantic.BaseModel):
    """A vertical rod inside the object: centre (x, y) and radius in the length unit, extra σ per unit length."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    x: float
    y: float
    radius: float = pydantic.Field(gt=0)
    sigma: float = pydantic.Field(ge=0)


_DEFAULT_RODS = (RodSpec(x=6.0, y=3.0, radius=2.0, sigma=0.15),)


#: peak bytes :func:`devices.sim.parallel_light.render` allocates per float32 frame it renders, without and with
#: noise (tracemalloc, 256 × 1024 and 64 × 512 frames, 1 and 4 angles: 5.0–5.3 and 13.0–13.1; every call renders
#: target, reference and backlit in float64 before the cast, and the noise in float64 beside them)
RENDER_FRAMES = {False: 5.3, True: 13.1}


def angles_per_chunk(n_angles: int, frame_bytes: int) -> int:
    """Angles rendered per dask task: as many frames as fit in 64 MiB, at least one."""
    return max(1, min(n_angles, _FRAME_BYTES_PER_CHUNK // max(frame_bytes, 1)))


def _capture_precheck(settings) -> list[str]:
    """Sensor levels in order, and one render task's arrays within this machine's memory."""
    problems = []
    if settings.saturation_level <= settings.dark_level:
        problems.append(f"saturation_level ({settings.saturation_level:g}) must be above dark_level "
                        f"({settings.dark_level:g}) [counts]")
    frame = settings.n_rows * settings.n_cols * 4
    per_chunk = angles_per_chunk(len(settings.angles.values()), frame)
    factor = RENDER_FRAMES[settings.noise_std > 0]
    frames = "a frame" if per_chunk == 1 else f"{per_chunk:,} frames"
    problems += memory_problems(
        factor * per_chunk * frame,
        f"one render task ({frames} of {settings.n_rows:,} × {settings.n_cols:,} px float32, about {factor:g}× "
        "that in working arrays)", fix="lower n_rows or n_cols")
    return problems


@stage("simulate_parallel_capture", precheck=_capture_precheck)
def simulate_parallel_capture(
    *,
    angles: AngleSweep = AngleSweep(),  # noqa: B008 (a frozen model: immutable default)
    n_rows: Count = 8,
    n_cols: Count = 256,
    pixel_size: Positive = 0.2,
    radius: Positive = 20.0,
    rods: tuple[RodSpec, ...] = _DEFAULT_RODS,
    medium_sigma: NonNegative = 0.01,
    intensity: Positive = 3000.0,
    skin_transmittance: Annotated[float, pydantic.Field(gt=0, le=1)] = 0.8,
    dark_level: NonNegative = 64.0,
    saturation_level: Positive = 4095.0,
    backlight: NonNegative = 2000.0,
    noise_std: NonNegative = 0.0,
    seed: Index = 0,
) -> xr.Dataset:
    """A tomography capture of a cylinder with rods under parallel light (θ_l = 0, orthographic camera).

    The §4.4.2 comparison setting, in closed form (devices.sim.parallel_light): lazy frames, one dask
    chunk per group of angles, identical under any chunking or scheduler.

    Parameters
    ----------
    angles : AngleSweep
        Stage angles {start, stop, step} [degree]; stop > start, at most 100 000 angles.
    n_rows : int
        Sensor rows (slices along the rotation axis); sizes whose render would not fit in memory are refused.
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
        Transmittance of the diffusing skin, crossed twice, in (0, 1] [1].
    dark_level : float
        Sensor offset [counts].
    saturation_level : float
        Full-well count, above ``dark_level``; direct views of the source saturate [counts].
    backlight : float
        Counts of the lit diffuse plane in backlit frames [counts].
    noise_std : float
        Gaussian read noise; 0 for none [counts].
    seed : int
        Seed of the noise.
    """
    angle_values = angles.values()
    per_chunk = angles_per_chunk(len(angle_values), n_rows * n_cols * 4)
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
            **OrthographicCamera(rows=n_rows, cols=n_cols, pixel_size=pixel_size).attrs(),
            "light_angle_deg": 0.0,
            "length_unit": "mm",
            "saturation_counts": saturation_level,
            "simulator": "devices.sim.parallel_light",
        },
    )

