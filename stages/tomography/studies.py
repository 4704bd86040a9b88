"""Experiments of §4.4 as stages: one setting swept, every reconstruction and its error against the truth.

``light_angle_study`` is §4.4.1 (Fig. 18, Table 1): for each θ_l the rig's sinogram of a scene
(:func:`selpath.stages.tomography.phantom.simulate_sinogram`: exact line integrals, the observed mask θ_l gives), FBP
and
the constrained optimisation, and their RMSE and largest absolute error against the scene's true σ.
Lazy like the stages it wires (the sinograms themselves are cheap and made at once).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import xarray as xr

from selpath.devices.sim.scene import scene_identity
from selpath.pipeline.constraints import Count, NonNegative, Positive, StorePath, memory_problems
from selpath.pipeline.kinds import ANGLE_UNITS, LENGTH_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import MaxIter
from selpath.stages.tomography import _tv_settings as tv
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.phantom import (
    LightAngle,
    _precheck,
    phantom_truth,
    ray_problems,
    simulate_sinogram,
    truth_problems,
)
from selpath.stages.tomography.reconstruct import fbp, reconstruct_tv
from selpath.stages.tomography.sinogram import Bins

_SIGMA = "1/{length}"
LIGHT_ANGLE_STUDY = CubeKind(
    name="light_angle_study",
    description="reconstructions and their errors versus the light angle θ_l (§4.4.1, Table 1)",
    variables={"rmse": Variable(("light_angle", "method"), units=_SIGMA, long_name="RMSE of σ"),
               "max_abs_error": Variable(("light_angle", "method"), units=_SIGMA, long_name="max |error| of σ"),
               "sigma": Variable(("light_angle", "method", "y", "x"), units=_SIGMA,
                                 long_name="absorption coefficient σ")},
    coord_units={"light_angle": ANGLE_UNITS, "y": LENGTH_UNITS, "x": LENGTH_UNITS},
)


def _study_precheck(settings) -> list[str]:
    """The scene, and the largest arrays of one θ_l: the rays, the truth raster (supersample 4 on the n_x grid)
    and the optimisation's projector, which interpolates (n_theta, n_x, n_x) float32 arrays."""
    n_theta, n_x = settings.n_theta, settings.n_x
    return (_precheck(settings) + ray_problems(n_theta, n_x) + truth_problems(n_x, 4)
            + memory_problems(n_theta * n_x * n_x * 4, f"the projector's interpolation arrays ({n_theta:,} × "
                              f"{n_x:,} × {n_x:,} float32)", fix="lower n_theta or n_x"))


@stage("light_angle_study", kind=LIGHT_ANGLE_STUDY, precheck=_study_precheck)
def light_angle_study(*, scene: StorePath,
                      light_angles: Annotated[tuple[LightAngle, ...], pydantic.Field(min_length=1)] = (
                          0.0, 30.0, 60.0, 90.0, 120.0),
                      n_theta: Count = 180, n_x: Bins = 128, noise_std: NonNegative = 0.0,
                      tv_weight: NonNegative = tv.TV_WEIGHT, tol: Positive = tv.TOL, max_iter: MaxIter = tv.MAX_ITER,
                      angles: AngleSweep = AngleSweep()) -> xr.Dataset:  # noqa: B008 (frozen model)
    """FBP and the optimisation versus θ_l, with RMSE and max |error| against the truth (Table 1).

    Parameters
    ----------
    scene : str
        Scene file (the thesis: ``scenes/phantom-cylinder.yaml``).
    light_angles : tuple of float
        θ_l values, each in [0, 180], at least one [degree].
    n_theta : int
        θ bins over [0°, 180°).
    n_x : int
        X bins, and the image size (at least 2).
    noise_std : float
        Gaussian noise on every bin [absorption].
    tv_weight : float
        λ of Eq. 20 (``reconstruct_tv``'s default; the shipped tomography-setup workflow sets 1e-4 for the
        noise-free phantom).
    tol : float
        ADMM stopping tolerance [1].
    max_iter : int
        ADMM iteration cap.
    angles : AngleSweep
        Stage angles of the simulated sweep [degree]; stop > start, at most 100 000 angles.

    Returns
    -------
    xr.Dataset
        A ``light_angle_study`` cube: ``rmse`` and ``max_abs_error`` [per length unit] over (light_angle, method), and
        the reconstructions ``sigma`` over (light_angle, method, y, x).

    References
    ----------
    Thesis §4.4.1 Appropriate setup of the measurement.
    """
    results, observed = [], []
    truth = None
    for angle in light_angles:
        sinogram = simulate_sinogram(scene=scene, light_angle_deg=angle, n_theta=n_theta, n_x=n_x,
                                     angles=angles, noise_std=noise_std).chunk({"slice": 1})
        if truth is None:
            truth = phantom_truth(sinogram, scene=scene)["sigma"].isel(slice=0, drop=True)
        observed.append(float(sinogram["observed"].mean()))
        pair = [fbp(sinogram)["sigma"], reconstruct_tv(sinogram, tv_weight=tv_weight, tol=tol,
                                                       max_iter=max_iter)["sigma"]]
        results.append(xr.concat([p.isel(slice=0, drop=True) for p in pair], dim="method"))
    sigma = xr.concat(results, dim="light_angle").assign_coords(
        light_angle=("light_angle", np.asarray(light_angles, float), {"units": "degree"}),
        method=("method", ["fbp", "optimisation"]))
    error = sigma - truth
    return LIGHT_ANGLE_STUDY.label(xr.Dataset(
        {"sigma": sigma, "rmse": np.sqrt((error**2).mean(("y", "x"))), "max_abs_error": abs(error).max(("y", "x")),
         "observed_fraction": ("light_angle", np.array(observed)), "truth": truth},
        attrs={**scene_identity(scene), "tv_weight": tv_weight}))
