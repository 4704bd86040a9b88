"""Which sinogram bins a capture fills: ``filled_fraction`` (the share of bins between observed bins that hold a
ray) and the observed share, for the capture's own bins (``bin_sinogram``'s defaults: one θ bin per view step,
one X bin per pixel pitch at the axis) and finer ones, on simulated cylinders with an absorbing inclusion
(noise-free, light sheet at θ_l = 45°). The numbers in docs/results.md ("Sinogram bins that fit the capture").

    python benchmarks/sinogram_bins.py        # about 30 s on 2 cores
"""

from __future__ import annotations

import warnings

import numpy as np
import xarray as xr

from selpath.devices.sim import tomography as tomo
from selpath.devices.sim.scene import Scene
from selpath.pipeline.quality import enforce
from selpath.stages.tomography.calibrate import absorption
from selpath.stages.tomography.hull import silhouettes, visual_hull
from selpath.stages.tomography.paths import align_paths
from selpath.stages.tomography.sinogram import bin_sinogram

R = 10.0  # cylinder radius [mm]


def camera(fov: float | None, cols: int) -> dict:
    if fov is None:
        return {"model": "orthographic", "rows": 1, "cols": cols, "pixel_size": f"{2.04 * R / cols} mm"}
    distance = R / np.sin(np.deg2rad(fov) / 2)
    return {"model": "perspective", "rows": 1, "cols": cols, "distance": f"{distance} mm", "fov": f"{fov * 1.02} deg"}


def capture(fov: float | None, cols: int, step: float) -> xr.Dataset:
    scene = Scene.model_validate({
        "scene": "bins", "light": {"kind": "sheet", "angle": "45 deg", "distance": "500 mm"},
        "camera": camera(fov, cols),
        "object": {"shape": {"kind": "cylinder", "radius": f"{R} mm"}, "height": "40 mm", "inclusions": [
            {"shape": {"kind": "cylinder", "radius": "3 mm"}, "sigma": "0.05 /mm"}]}})
    frames = {"target": [], "reference": [], "backlit": []}
    angles = np.arange(0.0, 360.0, step)
    for a in angles:
        seen = tomo.exit_points(scene, a)
        frames["target"].append(tomo.straight_path(scene, a, reference=False, seen=seen) + 64)
        frames["reference"].append(tomo.straight_path(scene, a, reference=True, seen=seen) + 64)
        frames["backlit"].append(np.where(tomo.silhouette(scene, a, seen), 64.0, 2064.0))
    dims = ("angle", "row", "col")
    return xr.Dataset({k: (dims, np.array(v)) for k, v in frames.items()}
                      | {"dark": (("row", "col"), np.full(frames["target"][0].shape, 64.0))},
                      coords={"angle": ("angle", angles, {"units": "degree"})},
                      attrs=scene.geometry().attrs() | {"saturation_counts": 1e9})


def main() -> None:
    print(f"{'rig, views':<24} {'bins (θ × X)':<14} {'':<24} {'filled':>7} {'observed':>9}")
    for fov, cols, step in ((30.0, 320, 1.0), (None, 320, 4.0), (60.0, 640, 2.0)):
        cap = capture(fov, cols, step)
        rays = align_paths(absorption(cap), visual_hull(silhouettes(cap))).compute()
        own = bin_sinogram(rays)
        n_theta, n_x = own.sizes["theta"], own.sizes["x"]
        rig = f"{'orthographic' if fov is None else f'perspective {fov:g}°'}, {step:g}°"
        for what, bins in (("the capture's", (n_theta, n_x)), ("X half as wide", (n_theta, 2 * (n_x - 1) + 1)),
                           ("θ half as wide", (2 * n_theta, n_x)), ("θ half, X a third", (2 * n_theta, 3 * n_x))):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the finer bins warn, as they should
                shares = enforce(bin_sinogram(rays, n_theta=bins[0], n_x=bins[1]))
            print(f"{rig:<24} {f'{bins[0]} × {bins[1]}':<14} {what:<24} {shares['filled_fraction']:>7.3f} "
                  f"{shares['observed_fraction']:>9.3f}")


if __name__ == "__main__":
    main()
