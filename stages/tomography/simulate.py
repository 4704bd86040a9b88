"""Simulated captures as lazy stages (frames are rendered chunk by chunk, only when computed)."""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import xarray as xr
from dask.base import tokenize

from selpath.devices.sim import tomography as tomo
from selpath.devices.sim.parallel_light import Rod, render
from selpath.devices.sim.scene import load_scene, scene_identity
from selpath.geometry.rig import OrthographicCamera
from selpath.pipeline.constraints import Count, Index, NonNegative, Positive, StorePath, memory_problems
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.registry import stage
from selpath.stages._common import read_file
from selpath.stages.tomography.acquire import TOMOGRAPHY_CAPTURE, AngleSweep

_FRAME_BYTES_PER_CHUNK = 64 * 2**20


class RodSpec(pydantic.BaseModel):
    """A vertical rod inside the object: centre (x, y) and radius in the length unit, extra σ per unit length."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    x: float
    y: float
    radius: float = pydantic.Field(gt=0)
    sigma: float = pydantic.Field(ge=0)


_DEFAULT_RODS = (RodSpec(x=6.0, y=3.0, radius=2.0, sigma=0.15),)


#: peak bytes :func:`selpath.devices.sim.parallel_light.render` allocates per float32 frame it renders, without and with
#: noise (tracemalloc, 256 × 1024 and 64 × 512 frames, 1 and 4 angles: 5.0–5.3 and 13.0–13.1; every call renders
#: target, reference and backlit in float64 before the cast, and the noise in float64 beside them)
RENDER_FRAMES = {False: 5.3, True: 13.1}


def angles_per_chunk(n_angles: int, frame_bytes: int, chunk_bytes: int | None = None) -> int:
    """Angles rendered per dask task: as many frames as fit in ``chunk_bytes`` (default 64 MiB), at least one."""
    return max(1, min(n_angles, (chunk_bytes or _FRAME_BYTES_PER_CHUNK) // max(frame_bytes, 1)))


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


@stage("simulate_parallel_capture", kind=TOMOGRAPHY_CAPTURE, precheck=_capture_precheck)
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

    Returns
    -------
    xr.Dataset
        A ``tomography_capture`` cube: ``target``, ``reference`` and ``backlit`` [counts] over (angle, row, col) and
        ``dark`` (row, col), with the parallel rig's geometry in its attrs.

    References
    ----------
    Thesis §4.4.2 Experiment on a real object.
    """
    import dask.array as da  # on computing, not on reading a workflow

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
    return TOMOGRAPHY_CAPTURE.label(xr.Dataset(
        {name: (dims, frames(name)) for name in ("target", "reference", "backlit")} | {"dark": (("row", "col"), dark)},
        coords={"angle": ("angle", angle_values, {"units": "degree", "long_name": "stage angle φ"})},
        attrs={
            **OrthographicCamera(rows=n_rows, cols=n_cols, pixel_size=pixel_size).attrs(),
            "light_angle_deg": 0.0,
            "length_unit": "mm",
            "saturation_counts": saturation_level,
            "simulator": "selpath.devices.sim.parallel_light",
        },
    ))



#: bytes of one frame kind per chunk of a scene capture: 8 MiB, one 1600 × 1200 float32 frame, as acquisitions store
#: them; the per-pixel stages downstream (absorption, paths) hold about 40× a chunk in float64 temporaries, and 8
#: such frames (64 MiB) took a worker past a 4 GB limit (benchmarks/tomo_volume.py)
SCENE_CHUNK_BYTES = 8 * 2**20

#: peak bytes of working arrays per pixel and angle that :func:`selpath.devices.sim.tomography.render_rows` holds beside
#: its float32 output (3 frames): the pixels' rays, exit points and normals in float64, about 20 float64 values
RENDER_BYTES_PER_PIXEL = 160


def _scene_capture_precheck(settings) -> list[str]:
    spec, problems = read_file(load_scene, settings.scene, "scene")
    if problems:
        return problems
    if spec.effects.scattering is not None:
        return ["the scene has scattering (Monte Carlo over whole frames): capture it with acquire_tomography, rig sim"]
    rows = min(settings.rows_per_chunk or spec.camera.rows, spec.camera.rows)
    return memory_problems(rows * spec.camera.cols * RENDER_BYTES_PER_PIXEL,
                           f"one render task's working arrays ({rows:,} rows × {spec.camera.cols:,} px)",
                           fix="lower rows_per_chunk")


@stage("simulate_capture", kind=TOMOGRAPHY_CAPTURE, precheck=_scene_capture_precheck,
       identity=lambda settings: scene_identity(settings.scene) if settings.scene else {})
def simulate_capture(*, scene: StorePath, angles: AngleSweep = AngleSweep(),  # noqa: B008 (frozen model)
                     rows_per_chunk: Count | None = None) -> xr.Dataset:
    """A tomography capture of a scene file rendered lazily, chunk by chunk: any sensor size, never held whole.

    The frames the simulated rig would record (straight paths, dark level, saturation, the scene's noise), as
    dask arrays chunked in (angles, ``rows_per_chunk`` rows, all columns): a task renders its band of rows at its
    angles only, so a 1600 × 1200 × 360 capture (8.3 GB as float32) costs what the tasks a computation needs cost.
    The same capture as ``acquire_tomography`` with ``rig: sim`` except for the noise, which is seeded per
    (angle, frame, row) so that any chunking gives the same frames. Scenes with scattering are refused.

    Parameters
    ----------
    scene : str
        Scene file (``workflows/scenes/*.yaml``), without ``effects.scattering``.
    angles : AngleSweep
        Stage angles {start, stop, step} [degree]; stop > start, at most 100 000 angles.
    rows_per_chunk : int or None
        Sensor rows per chunk; None: whole frames, as an acquisition stores them (silhouettes need whole frames).
        Angles per chunk follow from whole frames (about 8 MiB of one frame kind, at least one angle), banded or not:
        silhouettes join the bands back into whole frames.

    Returns
    -------
    xr.Dataset
        A ``tomography_capture`` cube: ``target``, ``reference`` and ``backlit`` [counts] over (angle, row, col) and
        ``dark`` (row, col), rendered lazily chunk by chunk, with the scene's stated geometry in its attrs.

    References
    ----------
    Thesis §4.2.5 Setup of the measurement; §4.4.3 Measurement of arbitrary convex shape.
    """
    spec = load_scene(scene)
    if spec.effects.scattering is not None:
        raise StageError(Problem("simulate_capture renders straight paths; the scene has scattering",
                                 fix="capture it with acquire_tomography, rig sim"))
    import dask.array as da

    rows, cols = spec.camera.rows, spec.camera.cols
    band = min(rows_per_chunk or rows, rows)
    angle_values = angles.values()
    # angles per chunk from the whole frame, not the band: silhouettes join the bands back into whole frames
    per_chunk = angles_per_chunk(len(angle_values), rows * cols * 4, SCENE_CHUNK_BYTES)
    firsts = np.arange(0, rows, band)
    row_chunks = tuple(min(band, rows - first) for first in firsts)
    lazy_angles = da.from_array(angle_values, chunks=per_chunk)
    lazy_rows = da.from_array(firsts, chunks=1)

    def block(a: np.ndarray, first: np.ndarray) -> np.ndarray:
        start = int(first[0])
        return tomo.render_rows(spec, a, start, min(band, rows - start))

    frames = da.blockwise(block, "karc", lazy_angles, "a", lazy_rows, "r", new_axes={"k": 3, "c": cols},
                          adjust_chunks={"r": row_chunks}, dtype=np.float32, concatenate=False,
                          name=f"simulate-capture-{tokenize(spec.model_dump_json(), angle_values, band, per_chunk)}")
    dims = ("angle", "row", "col")
    geometry = spec.stated_geometry().attrs()
    dark = np.full((rows, cols), spec.sensor.dark_level, np.float32)
    return TOMOGRAPHY_CAPTURE.label(xr.Dataset(
        {name: (dims, frames[k]) for k, name in enumerate(tomo.FRAME_KINDS)} | {"dark": (("row", "col"), dark)},
        coords={"angle": ("angle", angle_values, {"units": "degree", "long_name": "stage angle φ"})},
        attrs={**geometry, "saturation_counts": spec.sensor.saturation_level, "rig": "simulated", "scene": spec.scene,
               "effects": list(spec.effects.names()), "simulator": "selpath.devices.sim.tomography.render_rows"}))
