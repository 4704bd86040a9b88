"""Synthetic sinograms and ground truths from scene files (§4.4.1: sinograms by the forward Radon transform).

``simulate_sinogram`` is the study setting of §4.4.1: the exact line integrals of the scene's inclusions on
a (θ, X) grid (chord lengths through each shape, no discretisation), with the ``observed`` mask the rig
would produce at a light angle θ_l: for every stage angle and camera column of the slice z = 0, the chord
from the light's entry point to the pixel's exit point is binned, exactly as ``align_paths`` +
``bin_sinogram`` do with a measured contour. ``phantom_truth`` rasterises the same field (cell averages by
supersampling) on the reconstruction grid, for error tables.

What a capture measures is A = log I_reference − log I_target, the inclusions' absorption (the medium and
the skin cancel), so both stages describe the inclusions' σ only.
"""

from __future__ import annotations

from typing import Annotated

import dask
import numpy as np
import pydantic
import xarray as xr

from selpath.devices.sim import tomography as tomo
from selpath.devices.sim.scene import Scene, load_scene
from selpath.geometry.rig import to_object
from selpath.pipeline.constraints import Count, Index, NonNegative, Positive, StorePath, memory_problems
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.registry import stage
from selpath.stages._common import read_file
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.paths import sinogram_coordinates
from selpath.stages.tomography.reconstruct import RECONSTRUCTION, ome_attrs
from selpath.stages.tomography.sinogram import SINOGRAM, Bins, bin_index

#: θ_l, the light's angle to the camera axis [degree]
LightAngle = Annotated[float, pydantic.Field(ge=0, le=180)]


def _precheck(settings) -> list[str]:
    return read_file(load_scene, settings.scene, "scene")[1]


def ray_problems(n_theta: int, n_x: int) -> list[str]:
    """The exact Radon transform traces one segment per (θ, X) bin: two (n_theta·n_x, 3) float64 end points."""
    return memory_problems(n_theta * n_x * 3 * 8, f"the sinogram's rays ({n_theta:,} × {n_x:,} bins, 3 float64 "
                           "coordinates each)", fix="lower n_theta or n_x")


def truth_problems(n_pixels: int | None, supersample: int) -> list[str]:
    """The truth raster samples (n·supersample)² points of 3 float64 coordinates; n is at least 2 (a sinogram's
    X bins) where n_pixels is None."""
    n = n_pixels or 2
    side = n * supersample
    grid = f"{n:,} × {n:,} px" if n_pixels else "even the smallest (2 × 2 px) grid"
    return memory_problems(side * side * 3 * 8, f"the truth raster's sample points ({grid} × {supersample}² "
                           "samples, 3 float64 coordinates each)", fix="lower n_pixels or supersample")


def _sinogram_precheck(settings) -> list[str]:
    return _precheck(settings) + ray_problems(settings.n_theta, settings.n_x)


def _truth_precheck(settings) -> list[str]:
    return _precheck(settings) + truth_problems(settings.n_pixels, settings.supersample)


def scene_radon(scene: Scene, theta_deg: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Exact ∫σ of the inclusions along the lines p·(cos θ, sin θ) = X in the slice z = 0, (θ, X)."""
    t = np.deg2rad(np.asarray(theta_deg, float))[:, None]
    x = np.asarray(x, float)[None, :]
    reach = 2.0 * scene.object.shape.build().reach() + float(np.abs(x).max())
    normal = np.stack(np.broadcast_arrays(np.cos(t), np.sin(t)), axis=-1)
    direction = np.stack(np.broadcast_arrays(np.sin(t), -np.cos(t)), axis=-1)
    centre = np.broadcast_to(x[..., None] * normal, (t.shape[0], x.shape[1], 2)).reshape(-1, 2)
    d = np.broadcast_to(direction, (t.shape[0], x.shape[1], 2)).reshape(-1, 2)
    zeros = np.zeros((len(centre), 1))
    start = np.hstack([centre - reach * d, zeros])
    end = np.hstack([centre + reach * d, zeros])
    total = tomo.path_absorption(scene, start, end, reference=False) - tomo.path_absorption(
        scene, start, end, reference=True)
    return total.reshape(t.shape[0], x.shape[1])


def observed_mask(scene: Scene, angles_deg: np.ndarray, theta_deg: np.ndarray, x: np.ndarray,
                  min_exit_cos: float = 0.02) -> np.ndarray:
    """Bins of the (θ, X) grid that the rig sees: entry-to-exit chords of the slice z = 0 over every angle.

    ``theta_deg`` and ``x`` are a sinogram's grid (X evenly over [−x_extent, x_extent]); chords are binned by the
    rule of :func:`~selpath.stages.tomography.sinogram.bin_index`, as ``bin_sinogram`` bins measured rays."""
    flat = scene.model_copy(update={"camera": scene.camera.model_copy(update={"rows": 1,
                                                                               "principal_point": None})})
    seen = np.zeros((len(theta_deg), len(x)), dtype=bool)
    _, directions = flat.geometry().camera.pixel_rays()
    for angle in angles_deg:
        entry = tomo.entry_point(flat, angle)
        if entry is None:
            continue
        exits = tomo.exit_points(flat, angle)
        d = to_object(directions, angle)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        grazing = np.abs(np.einsum("ij,ij->i", d, exits.normals)) < min_exit_cos
        ok = exits.hit & ~grazing
        p_c = exits.points[ok, :2]
        p_l = np.broadcast_to(entry[0][:2], p_c.shape)
        far = np.linalg.norm(p_c - p_l, axis=1) > 1e-9
        i, j, keep = bin_index(*sinogram_coordinates(p_l[far], p_c[far]), n_theta=len(theta_deg), n_x=len(x),
                               extent=float(x[-1]))
        seen[i[keep], j[keep]] = True
    return seen


@stage("simulate_sinogram", kind=SINOGRAM, precheck=_sinogram_precheck)
def simulate_sinogram(*, scene: StorePath, light_angle_deg: LightAngle | None = None, n_theta: Count = 180,
                      n_x: Bins = 128, x_extent: Positive | None = None,
                      angles: AngleSweep = AngleSweep(),  # noqa: B008 (a frozen model: immutable default)
                      noise_std: NonNegative = 0.0, seed: Index = 0) -> xr.Dataset:
    """An exact sinogram of a scene's inclusions with the rig's mask of observed rays (§4.4.1).

    Parameters
    ----------
    scene : str
        Scene file (``workflows/scenes/*.yaml``).
    light_angle_deg : float or None
        θ_l in [0, 180] [degree]; None: the scene's.
    n_theta : int
        Bins over [0°, 180°).
    n_x : int
        Bins over [−x_extent, x_extent], at least 2.
    x_extent : float or None
        Half-width of the X grid [scene length unit, mm]; None: 1.02 × the object's reach.
    angles : AngleSweep
        Stage angles of the simulated sweep [degree]; stop > start, at most 100 000 angles.
    noise_std : float
        Gaussian noise added to the absorption of every bin [absorption].
    seed : int
        Noise seed.

    Returns
    -------
    xr.Dataset
        A ``sinogram`` cube: the exact ``absorption`` [1] over (slice, theta, x) and the rig's ``observed`` mask.

    References
    ----------
    Thesis §4.4.1 Appropriate setup of the measurement.
    """
    spec = load_scene(scene)
    if light_angle_deg is not None:
        if not 0.0 <= light_angle_deg <= 180.0:
            raise StageError(Problem(f"light_angle_deg = {light_angle_deg}; θ_l lies in [0, 180]"))
        spec = spec.model_copy(update={"light": spec.light.model_copy(update={"angle": float(light_angle_deg)})})
    extent = float(x_extent if x_extent is not None else 1.02 * spec.object.shape.build().reach())
    theta = np.arange(n_theta) * 180.0 / n_theta
    x = np.linspace(-extent, extent, n_x)
    absorption = scene_radon(spec, theta, x)
    if noise_std > 0:
        absorption = absorption + np.random.default_rng(seed).normal(0.0, noise_std, absorption.shape)
    observed = observed_mask(spec, angles.values(), theta, x)
    dims = ("slice", "theta", "x")
    geometry = spec.geometry().attrs()
    return SINOGRAM.label(xr.Dataset(
        {"absorption": (dims, absorption[None]), "observed": (dims, observed[None]),
         "count": (dims, observed[None].astype(np.int64))},
        coords={"slice": ("slice", [0]),
                "z": ("slice", [0.0], {"units": spec.length_unit, "long_name": "slice height z"}),
                "theta": ("theta", theta, {"units": "degree"}),
                "x": ("x", x, {"units": spec.length_unit})},
        attrs=geometry | {"x_extent": extent, "theta_step_deg": 180.0 / n_theta,
                          "x_step": 2 * extent / (n_x - 1), "scene": spec.scene, "noise_std": noise_std}))


def truth_raster(scene: Scene, n: int, extent: float, supersample: int = 4, z: float = 0.0) -> np.ndarray:
    """Cell averages (n, n) [(y, x)] of the inclusions' σ over [−extent, extent]², in the slice at height ``z``."""
    cell = 2 * extent / n
    centres = -extent + (np.arange(n) + 0.5) * cell
    offsets = ((np.arange(supersample) + 0.5) / supersample - 0.5) * cell
    fine = (centres[:, None] + offsets[None, :]).reshape(-1)
    yy, xx = np.meshgrid(fine, fine, indexing="ij")
    points = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, float(z))])
    total = np.zeros(len(points))
    for prism, sigma in scene.inclusions():
        total += sigma * prism.contains(points)
    return total.reshape(n, supersample, n, supersample).mean(axis=(1, 3))


@stage("phantom_truth", kind=RECONSTRUCTION, precheck=_truth_precheck)
def phantom_truth(sinogram: xr.Dataset, /, *, scene: StorePath, n_pixels: Count | None = None,
                  supersample: Count = 4) -> xr.Dataset:
    """The scene's inclusion σ on the reconstruction grid of ``sinogram`` (the reference for error tables).

    Parameters
    ----------
    sinogram : xr.Dataset
        A ``sinogram`` store (``simulate_sinogram`` of the same scene); only its grid is read: the ``x`` coordinate
        (whose units must be the scene's length unit), attr ``x_extent``, the ``slice`` coordinate and, where present,
        ``z`` (each slice's height, in x's unit; absent: every slice is z = 0). Lazy: one task per slice height.
    scene : str
        Scene file.
    n_pixels : int or None
        Image size n (as given to the reconstruction); None: the sinogram's number of X bins.
    supersample : int
        Samples per cell and axis.

    Returns
    -------
    xr.Dataset
        A ``reconstruction`` cube: ``sigma`` [per length unit] of the scene's inclusions over (slice, y, x) on
        ``sinogram``'s grid.

    References
    ----------
    Thesis §4.4.1 Appropriate setup of the measurement.
    """
    spec = load_scene(scene)
    x = sinogram["x"].values
    extent = float(sinogram.attrs.get("x_extent", np.abs(x).max()))
    n = int(n_pixels or len(x))
    cell = 2 * extent / n
    centres = -extent + (np.arange(n) + 0.5) * cell
    unit = sinogram["x"].attrs.get("units", "mm")
    slices = sinogram["slice"].values
    heights = sinogram["z"].values if "z" in sinogram.coords else np.zeros(len(slices))
    if "z" in sinogram.coords and sinogram["z"].attrs.get("units", unit) != unit:
        raise StageError(Problem(f"the sinogram's z is in {sinogram['z'].attrs['units']!r}, its x in {unit!r}",
                                 fix="bin it with bin_sinogram from one capture"))
    import dask.array as da  # on computing, not on reading a workflow

    rasters = {z: dask.delayed(truth_raster)(spec, n, extent, supersample, z) for z in dict.fromkeys(heights.tolist())}
    volume = da.stack([da.from_delayed(rasters[z], (n, n), np.float64) for z in heights.tolist()])  # a slice a task
    return RECONSTRUCTION.label(xr.Dataset(
        {"sigma": (("slice", "y", "x"), volume)},
        coords={"slice": ("slice", slices), "z": ("slice", heights, {"units": unit, "long_name": "slice height z"}),
                "y": ("y", centres, {"units": unit}), "x": ("x", centres, {"units": unit})},
        attrs={"method": "truth", "scene": spec.scene, "cell_size": cell}
        | ome_attrs(heights, centres, centres, unit)))
