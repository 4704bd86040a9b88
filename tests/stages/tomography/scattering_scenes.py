"""Monte Carlo captures of the §4.4.4 scene (an absorber σ = 10 in a scattering cylinder) for the tests of
reconstruct_scattering and estimate_scattering."""

from __future__ import annotations

import numpy as np


def monte_carlo_capture(seed: int, step: float = 12.0, photons: int = 100_000, sigma_s: float = 1.0,
                        samples: tuple[str, ...] = ("target", "reference")):
    """The §4.4.4 scene (absorber σ = 10, radius 0.2 in a radius-1 cylinder) at ``sigma_s``: Monte Carlo frames of
    ``samples`` every ``step`` degrees with the given scattering seed, backlit and dark frames, unclipped; and the
    scene's path."""
    import xarray as xr

    from selpath import workflows
    from selpath.devices.sim import tomography as tomo
    from selpath.devices.sim.scene import load_scene

    path = workflows.scene("cylinder-in-cylinder-s1")
    scene = load_scene(path)
    scene = scene.model_copy(update={"effects": scene.effects.model_copy(update={
        "scattering": scene.effects.scattering.model_copy(update={"seed": seed, "photons": photons,
                                                                  "sigma_s": sigma_s})})})
    angles = np.arange(0.0, 360.0, step)
    frames = {k: [] for k in (*samples, "backlit")}
    for a in angles:
        seen = tomo.exit_points(scene, a)
        for sample in samples:
            frames[sample].append(tomo.lit_frame(scene, a, sample, seen) + 64)
        frames["backlit"].append(np.where(tomo.silhouette(scene, a, seen), 64.0, 2064.0))
    dims = ("angle", "row", "col")
    cap = xr.Dataset({k: (dims, np.array(v)) for k, v in frames.items()}
                     | {"dark": (("row", "col"), np.full(frames["backlit"][0].shape, 64.0))},
                     coords={"angle": ("angle", angles, {"units": "degree"})},
                     attrs=scene.geometry().attrs() | {"saturation_level": 1e9}).chunk({"angle": 10})
    return cap, path


def scattering_capture(seed: int, step: float = 12.0, photons: int = 100_000):
    """:func:`monte_carlo_capture` at σ_s = 1 through absorption, hull, rays and a sinogram of one θ bin per view
    and 32 X bins; with the truth on the reconstruction grid, and the capture."""
    from selpath.stages.tomography.calibrate import absorption
    from selpath.stages.tomography.hull import silhouettes, visual_hull
    from selpath.stages.tomography.paths import align_paths
    from selpath.stages.tomography.phantom import phantom_truth
    from selpath.stages.tomography.sinogram import bin_sinogram

    cap, path = monte_carlo_capture(seed, step, photons)
    hull = visual_hull(silhouettes(cap)).compute()
    rays = align_paths(absorption(cap, min_signal=1.0), hull).compute()
    sinogram = bin_sinogram(rays, n_theta=int(180 / step), n_x=32).compute()
    truth = phantom_truth(sinogram, scene=str(path)).compute()
    return rays, sinogram, hull, truth["sigma"].values[0], cap
