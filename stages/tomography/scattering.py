"""Tomography through scattering (#27, thesis §4.4.4 and §6.1): a forward model that accounts for σ_s.

The shortest-path model reads each lit pixel as one straight chord from the light's entry point ``p_l`` to the exit
point ``p_c`` it sees. In a scattering medium the light that reaches ``p_c`` took many paths, and an absorber that
blocks the chord is partly walked around, so the straight model under-reads it (about half of σ = 10 at σ_s = 1 in
docs/results.md). Here each sinogram bin is a **bundle of paths**:

* Photon random walks are traced from ``p_l`` in the homogeneous object (the hull's contour extruded in z, the
  scattering coefficient σ_s, isotropic phase function, Lambertian launch through the skin), exactly as in the
  reference object, which has the same σ_s and no absorber: its frames are the sum over these paths' exits.
* Each walk is connected, from every vertex it flew from, to the surface point each pixel of the slice's row sees
  (next-event estimation: the chance that its next flight leaves there,
  :func:`selpath.stages.tomography._walks.exit_weights`),
  so every walk tells every pixel by which paths, and how much of, its light arrives; a sinogram bin draws
  ``paths_per_bin`` paths from the connections to its rays' pixels, in proportion to their light. A walk's own exit
  would reach one pixel, and the slice's row only by chance (at σ_s = 3, 2 walks in 1 000): each bin gets the same
  number of paths, on the row itself, for a fraction of the walks.
* The target's frame weighs each path by exp(−∫σ) along it, so the absorption the pipeline measures,
  A = log I_reference − log I_target, is modelled as ``A(σ) = −log( mean over the bundle of exp(−∫_path σ) )``:
  nonlinear in σ, smooth, and differentiable in JAX. ∫σ along a path is a sum over its samples (``spacing`` cells
  apart) of σ interpolated bilinearly on the image grid, times the 3-D length each stands for (σ does not vary with
  height within a slice: a prism).

The reconstruction minimises ½ Σ (A_b(σ) − a_b)² over the observed bins + λ TV_ε(σ) over 0 ≤ σ ≤ σ_max (0 outside
the hull) by L-BFGS-B (scipy; the paths' integrals through a sparse path matrix built once per slice, the bundles'
absorption and TV with JAX's exact gradients): the data term of ``reconstruct_tv`` on the same binned sinogram,
so λ means what it means there; TV_ε = Σ (√(|∇σ|² + ε²) − ε), a smooth TV. With σ_s = 0 there is nothing to walk
around: the stage is ``reconstruct_tv``, at its cost. The model's pieces (the bundles, their integrals and the fit)
are in :mod:`selpath.stages.tomography._bundles`.

Known bias: behind a strong absorber, where few of a bin's paths dodge it, −log of a drawn bundle's mean reads high
(the rare dodgers are what a finite bundle from a finite pool of walks misses), so σ there reads low. Measured on
the §4.4.4 scenes from captures with 4× the workflow's photons (docs/results.md, "What these numbers rest on"): the
model at the true σ predicts the shadow's absorption 0.09 (σ_s = 1) to 0.18 (σ_s = 3) too high at the defaults, 0.04
at σ_s = 1 with ``paths_per_bin: 256`` from ``photons: 20000``. With the defaults the absorber's mean σ read 32 %
low at σ_s = 1, with those settings 22 % (5× the time). Raise both where an absorber's σ matters more than time and
memory (the samples grow with ``paths_per_bin``).

Known limit: behind a strong absorber in a strongly scattering medium the light that arrives is the light that went
around it, so once the paths through it are dark a darker absorber changes the data very little. At σ_s = 3 bundles
freed of the bias above (drawn by importance around the fit, docs/results.md) model the shadow within 0.04 of the
data at the true σ, yet change by only 0.005–0.06 between a fifth of the true σ and the truth: the data say that the
absorber is dark, not how dark, and σ inside is left to the prior (TV shrinks it).

σ_s need not be known: :func:`selpath.stages.tomography.scattering_estimate.estimate_scattering` fits it, with a
bootstrap
interval, to how the reference frames spread the beam's light with the distance from its entry point, on the same
walks (:mod:`selpath.stages.tomography._walks`), and ``reconstruct_scattering`` takes its store in place of the setting.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import dask
import numpy as np
import xarray as xr

from selpath.geometry.rig import RigGeometry
from selpath.pipeline.constraints import Count, Index, NonNegative, Positive, memory_problems
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.registry import stage
from selpath.stages._common import MaxIter, require_variables
from selpath.stages._solution import Result
from selpath.stages.tomography import _tv_settings
from selpath.stages.tomography.hull import contours
from selpath.stages.tomography.reconstruct import (
    RECONSTRUCTION,
    check_inputs,
    grid_geometry,
    reconstruct_tv,
    reconstruction_store,
    support_mask,
)
from selpath.stages.tomography.sinogram import bin_index

if TYPE_CHECKING:
    from selpath.stages.tomography._projector import Geometry

#: the TV smoothing ε of :func:`selpath.stages.tomography._bundles.smooth_total_variation`, relative to the data's σ
#: scale (the largest observed absorption over the image's width, the σ a uniform object across the grid would need) [1]
TV_SMOOTHING = 1e-3

#: bytes per path sample held while fitting, at the peak of building
#: :func:`selpath.stages.tomography._bundles.path_matrix`: the sample (points, length, owner: 32) and its four
#: (cell, weight) pairs in int32/float64 with the build's temporaries (~80); the matrix kept is ~2 entries per sample
#: (24). Measured: 15.5 M samples of the scattering workflow's slice at σ_s = 1, 1.7 GB
SAMPLE_BYTES = 128


def _fit_one_slice(theta, x, absorption, data, observed, vertices, count, *, geometry: RigGeometry, row: int,
                   angles: np.ndarray, grid: Geometry, settings: dict, seed: int):
    """σ (n, n) of one slice by the bundle model, and (converged, iterations, objective, median paths, bins
    without paths)."""
    from selpath.stages.tomography._bundles import fit_slice, trace_bundles  # JAX: when a slice is fitted

    n_theta, n_x = data.shape
    nan = np.full((grid.n, grid.n), np.nan)
    if count < 3:
        return nan, _stats(False, 0, np.nan, 0.0, int(observed.sum()))
    polygon = vertices[:count]
    i, j, on_grid = bin_index(theta, x, n_theta=n_theta, n_x=n_x, extent=grid.extent)
    flat = np.where(on_grid & np.isfinite(absorption), i * n_x + j, -1)
    group = np.where((flat >= 0) & observed.ravel()[np.maximum(flat, 0)], flat, -1)
    bundles = trace_bundles(geometry, polygon, row, angles, group, n_theta * n_x, sigma_s=settings["sigma_s"],
                            photons=settings["photons"], paths_per_group=settings["paths_per_bin"],
                            spacing=grid.cell * settings["spacing"],
                            rng=np.random.default_rng([seed, row]), max_events=settings["max_events"])
    if problems := memory_problems(len(bundles.points) * SAMPLE_BYTES, f"slice {row}'s path samples",
                                   fix="lower paths_per_bin or raise spacing"):
        raise StageError([Problem(p) for p in problems])
    counts = bundles.counts
    used = observed.ravel() & (counts > 0)
    if not used.any():  # no walk reached an observed bin: no data, not a confident σ = 0
        return nan, _stats(False, 0, np.nan, 0.0, int(observed.sum()))
    values = data.ravel()
    scale = float(np.nanmax(np.where(used, values, np.nan), initial=0.0)) / (2 * grid.extent)
    upper = np.where(support_mask(polygon, grid), settings["sigma_max"], 0.0)
    fit = fit_slice(bundles, values, used.astype(float), upper, grid, tv_weight=settings["tv_weight"],
                    eps=TV_SMOOTHING * max(scale, np.finfo(float).tiny), max_iter=settings["max_iter"],
                    tol=settings["tol"])
    return fit.value, _stats(int(fit.result) == Result.converged, fit.stats["iterations"], fit.stats["objective"],
                             float(np.median(bundles.distinct[used])), int((observed.ravel() & (counts == 0)).sum()))


def _stats(*values) -> tuple[np.ndarray, ...]:
    return tuple(np.asarray(v, dtype) for v, dtype in zip(values, _STATS.values(), strict=True))


@stage("reconstruct_scattering", kind=RECONSTRUCTION)
def reconstruct_scattering(rays: xr.Dataset, sinogram: xr.Dataset, hull: xr.Dataset,
                           scattering: xr.Dataset | None = None, /, *, sigma_s: NonNegative | None = None,
                           tv_weight: NonNegative = _tv_settings.TV_WEIGHT, n_pixels: Count | None = None,
                           photons: Count = 5_000, paths_per_bin: Count = 64,
                           spacing: Positive = 1.0, sigma_max: Positive | None = None, max_events: Count = 1000,
                           max_iter: MaxIter = 500, tol: Positive = 1e-7, seed: Index = 0) -> xr.Dataset:
    """σ per slice under the path-bundle model of a scattering medium (module docstring; lazy, one task per slice).

    Each observed sinogram bin is modelled as −log of the mean transmittance of ``paths_per_bin`` paths by which light
    reaches its rays' pixels, drawn from photon walks traced from each view's entry point in the hull with scattering
    coefficient σ_s and connected to the pixels (next-event estimation); the fit is L-BFGS-B on ½‖A(σ) − a‖² over
    observed bins + λ TV, 0 ≤ σ ≤ σ_max, σ = 0 outside the hull. With σ_s = 0 this is
    :func:`selpath.stages.tomography.reconstruct.reconstruct_tv` (its defaults, ``tv_weight`` and ``n_pixels``).

    Parameters
    ----------
    rays : xr.Dataset
        The ``rays`` store (``align_paths``) the sinogram was binned from: ``theta`` [degree], ``x`` and
        ``absorption`` over (angle, row, col), angle the stage angle [degree]; which views and pixels hold rays.
    sinogram : xr.Dataset
        Its ``sinogram`` (``bin_sinogram``): ``absorption`` and ``observed`` over (slice, theta, x); attr
        ``x_extent`` spans the image, as for ``reconstruct_tv``.
    hull : xr.Dataset
        The ``hull`` store (``visual_hull``): the contour each slice's walks stay inside, and the rig geometry (the
        camera and the light) in its attrs.
    scattering : xr.Dataset or None
        A ``scattering_estimate`` store (:func:`selpath.stages.tomography.scattering_estimate.estimate_scattering`)
        whose
        ``sigma_s`` to use (read when the graph is built), in place of ``sigma_s``.
    sigma_s : float or None
        Scattering coefficient of the medium [1/length unit]; 0: the shortest-path model (``reconstruct_tv``). Give
        it or ``scattering``, not both.
    tv_weight : float
        λ, as for ``reconstruct_tv`` [absorption² per (1/length)·cell].
    n_pixels : int or None
        Image size n; None: the sinogram's number of X bins.
    photons : int
        Walks traced per view [1]: each is connected to every pixel of the row, so more walks give a bundle more
        distinct paths to be drawn from (fewer repeats).
    paths_per_bin : int
        Paths drawn per sinogram bin (its bundle; with replacement, so a path may count twice) [1]; the samples of a
        slice grow with it.
    spacing : float
        Distance between samples along a path, in cells [1].
    sigma_max : float or None
        Upper bound of σ [1/length unit]; None: none (σ ≥ 0 only). The shortest-path σ_max of Eq. 26–28 does not hold
        under scattering, where a ray's absorption under-reads what it crossed.
    max_events : int
        Scatterings before a walk is dropped [1].
    max_iter : int
        L-BFGS-B iteration cap, in [1, 1 000 000].
    tol : float
        Stop when an iteration lowers the objective by less than this share of it [1].
    seed : int
        Seed of the walks (with the slice's row).

    Returns
    -------
    xr.Dataset
        A ``reconstruction`` store: ``sigma`` over (slice, y, x), NaN for a slice without a contour or where no walk
        reached an observed bin (no data: never a confident 0); per slice ``converged`` (L-BFGS-B met ``tol``),
        ``iterations``, ``final_objective``, ``paths_per_bin`` (the median over the observed bins of their distinct
        paths: below the setting where paths repeat) and ``bins_without_paths`` (observed bins no walk's light reached:
        left out of the fit; raise ``photons`` if many).

    References
    ----------
    Thesis §4.4.4 Effect of scattering.
    """
    sigma_s = _scattering_coefficient(scattering, sigma_s)
    if sigma_s == 0:
        return reconstruct_tv(sinogram, hull, tv_weight=tv_weight, n_pixels=n_pixels)
    require_variables(rays, ("theta", "x", "absorption"), "reconstruct_scattering")
    check_inputs(sinogram, hull, "reconstruct_scattering")
    geometry = RigGeometry.from_attrs(hull.attrs, rays.sizes["row"], rays.sizes["col"],
                                      where="reconstruct_scattering: hull")
    rows = sinogram["slice"].values
    missing = sorted(set(rows.tolist()) - set(rays["row"].values.tolist()))
    if missing:
        raise StageError(Problem(f"the sinogram's slices {missing[:5]} are not rows of the rays",
                                 fix="give the rays the sinogram was binned from"))
    grid = grid_geometry(sinogram, n_pixels)
    shell = contours(hull, sinogram["slice"], "reconstruct_scattering")
    settings = {"sigma_s": sigma_s, "tv_weight": tv_weight, "photons": photons, "paths_per_bin": paths_per_bin,
                "spacing": spacing, "sigma_max": np.inf if sigma_max is None else sigma_max,
                "max_events": max_events, "max_iter": max_iter, "tol": tol}
    angles = rays["angle"].values
    import dask.array as da  # on computing, not on reading a workflow

    fit = dask.delayed(_fit_one_slice, nout=2, pure=True)
    images, stats = [], []
    for k, row in enumerate(rows):
        ray = rays.sel(row=row)
        image, numbers = fit(ray["theta"].data, ray["x"].data, ray["absorption"].data,
                             sinogram["absorption"].isel(slice=k).data, sinogram["observed"].isel(slice=k).data,
                             shell["vertices"].isel(slice=k).data, shell["n_vertices"].isel(slice=k).data,
                             geometry=geometry, row=int(row), angles=angles, grid=grid, settings=settings, seed=seed)
        images.append(da.from_delayed(image, (grid.n, grid.n), np.float64).astype(np.float32))
        stats.append([da.from_delayed(numbers[m], (), dtype) for m, dtype in enumerate(_STATS.values())])
    image = ("slice", "y", "x")
    variables = {"sigma": (image, da.stack(images))}
    for m, name in enumerate(_STATS):
        variables[name] = (("slice",), da.stack([s[m] for s in stats]))
    estimated = {} if scattering is None else {"sigma_s_estimated": True}
    return reconstruction_store(sinogram, grid, variables,
                                estimated | {"method": "bundle_lbfgsb_tv", "sigma_s": sigma_s, "tv_weight": tv_weight,
                                             "photons": photons, "paths_per_bin": paths_per_bin, "seed": seed})


def _scattering_coefficient(scattering: xr.Dataset | None, sigma_s: float | None) -> float:
    """σ_s from the setting or from an estimate's store: exactly one of them, and a finite, non-negative value."""
    if (scattering is None) == (sigma_s is None):
        raise StageError(Problem("reconstruct_scattering needs σ_s: give the sigma_s setting or a scattering "
                                 "estimate, one of them" + ("" if scattering is None else ", not both"),
                                 fix="estimate it with estimate_scattering, or set sigma_s [1/length unit]"))
    if scattering is None:
        return float(sigma_s)
    require_variables(scattering, ("sigma_s",), "reconstruct_scattering")
    value = float(scattering["sigma_s"].values)
    if not np.isfinite(value) or value < 0:
        raise StageError(Problem(f"the scattering estimate's sigma_s is {value}: it could not be estimated",
                                 where="reconstruct_scattering: scattering",
                                 fix="look at its measured_profile (no light in some distance bin?) or set sigma_s"))
    return value


#: per-slice statistics of :func:`reconstruct_scattering` and their dtypes
_STATS = {"converged": np.dtype(bool), "iterations": np.dtype(np.int64), "final_objective": np.dtype(np.float64),
          "paths_per_bin": np.dtype(np.float64), "bins_without_paths": np.dtype(np.int64)}
