"""Tomography scenes, a simulated capture of them and the lazy processing chain (absorption → hull → rays →
sinogram) the tomography tests share."""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.devices.sim import tomography as tomo
from selpath.devices.sim.scene import Scene
from selpath.stages.tomography.calibrate import absorption
from selpath.stages.tomography.coverage import coverage
from selpath.stages.tomography.hull import silhouettes, visual_hull
from selpath.stages.tomography.paths import align_paths
from selpath.stages.tomography.sinogram import bin_sinogram

R = 10.0


def make_scene(shape: dict, camera: dict, theta_l: float, inclusions=(), light: str = "sheet") -> Scene:
    return Scene.model_validate({
        "scene": "t", "object": {"shape": shape, "height": "40 mm", "inclusions": list(inclusions)},
        "light": {"kind": light, "angle": f"{theta_l} deg", "distance": "500 mm"}, "camera": camera})


def capture(scene: Scene, angles: np.ndarray) -> xr.Dataset:
    """An in-memory capture from the simulator (no noise): target, reference, backlit, dark."""
    target, reference, backlit = [], [], []
    for a in angles:
        seen = tomo.exit_points(scene, a)
        target.append(tomo.straight_path(scene, a, reference=False, seen=seen) + 64)
        reference.append(tomo.straight_path(scene, a, reference=True, seen=seen) + 64)
        backlit.append(np.where(tomo.silhouette(scene, a, seen), 64.0, 2064.0))
    dims = ("angle", "row", "col")
    return xr.Dataset(
        {"target": (dims, np.array(target)), "reference": (dims, np.array(reference)),
         "backlit": (dims, np.array(backlit)), "dark": (("row", "col"), np.full(target[0].shape, 64.0))},
        coords={"angle": ("angle", angles, {"units": "degree"})},
        attrs=scene.geometry().attrs() | {"saturation_level": 1e9}).chunk({"angle": 30})


def cylinder_camera(fov: float | None, cols: int = 2048) -> dict:
    if fov is None:
        return {"model": "orthographic", "rows": 1, "cols": cols, "pixel_size": f"{2.04 * R / cols} mm"}
    distance = R / np.sin(np.deg2rad(fov) / 2)
    return {"model": "perspective", "rows": 1, "cols": cols, "distance": f"{distance} mm", "fov": f"{fov * 1.02} deg"}


def lazy_chain() -> tuple[xr.Dataset, xr.Dataset, xr.Dataset, xr.Dataset]:
    """A small capture and its hull, sinogram and coverage, as graphs (nothing computed)."""
    scene = make_scene({"kind": "cylinder", "radius": f"{R} mm"}, cylinder_camera(None, 64), 60.0)
    with xr.set_options(keep_attrs=True):
        cap = capture(scene, np.arange(0.0, 360.0, 15.0))  # 15° views: 12 θ bins of 15°, none finer
    hull = visual_hull(silhouettes(cap))
    sino = bin_sinogram(align_paths(absorption(cap), hull), n_theta=12, n_x=16, x_extent=R)
    return cap, hull, sino, coverage(sino, hull)
