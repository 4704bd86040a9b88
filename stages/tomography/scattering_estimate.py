"""σ_s of a scattering medium from its reference frames (#27, thesis §4.4.4): the ``estimate_scattering`` stage.

The reference object (the target's medium without the inclusions) spreads the beam's light around its entry point,
and how fast that light falls with the distance is set by σ_s. This stage bins the reference frames by each pixel's
distance from the entry point and fits photon walks in the hull's slice to that profile, with a bootstrap interval
over the views, so that a user need not know σ_s: :func:`selpath.stages.tomography.scattering.reconstruct_scattering`
takes
its store in place of its ``sigma_s`` setting. The profile and its fit are in
:mod:`selpath.stages.tomography._exit_profile`,
the walks in :mod:`selpath.stages.tomography._walks`.
"""

from __future__ import annotations

from typing import Annotated

import dask
import numpy as np
import pydantic
import xarray as xr

from selpath.geometry.rig import RigGeometry, geometry_attrs, saturation_counts
from selpath.pipeline.constraints import Count, Index, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.tomography._exit_profile import (
    CANDIDATES,
    REACH_OCTAVES,
    candidate_counts,
    exit_profile,
    fit_profile,
    trusted_candidates,
)
from selpath.stages.tomography._walks import walk_body
from selpath.stages.tomography.hull import contours

SCATTERING_ESTIMATE = CubeKind(
    name="scattering_estimate",
    description="σ_s of the medium fitted to how the reference frames spread the beam's light (#27)",
    variables={
        "sigma_s": Variable((), units="1/{length}", long_name="scattering coefficient σ_s (estimate)"),
        "sigma_s_low": Variable((), units="1/{length}", long_name="16th percentile of the bootstrap σ_s"),
        "sigma_s_high": Variable((), units="1/{length}", long_name="84th percentile of the bootstrap σ_s"),
        "settled": Variable((), units=None, long_name="the last round's estimate stayed near its walks' σ_s"),
        "rounds": Variable((), units="1", long_name="rounds of walks traced"),
        "effective_walks": Variable((), units="1", long_name="effective number of walks at the estimate"),
        "objective": Variable(("candidate",), units="1", long_name="misfit of the log exit profile"),
        "candidate_sigma_s": Variable(("candidate",), units="1/{length}", long_name="candidate σ_s"),
        "measured_profile": Variable(("distance_bin",), units="counts·{length}^2",
                                     long_name="reference light per distance bin (counts × pixel area)"),
        "modelled_profile": Variable(("distance_bin",), units="counts·{length}^2",
                                     long_name="walks per distance bin at the estimate, scaled"),
        "bin_distance": Variable(("distance_bin",), units="{length}",
                                 long_name="distance from the entry point (bin centre)"),
    },
)


def _estimate_sigma_s(raw, dark, vertices, count, *, geometry: RigGeometry, angles: np.ndarray, rows: np.ndarray,
                      settings: dict, seed: int) -> tuple[np.ndarray, ...]:
    """σ_s of the reference frames ``raw`` (views, band rows, cols; raw counts) and what :func:`estimate_scattering`
    stores beside it, in the order of :data:`_ESTIMATE`."""
    bins, n = settings["distance_bins"], CANDIDATES
    nothing = _estimate_out(np.nan, np.nan, np.nan, 0.0, 0, False, np.full(n, np.inf), np.full(n, np.nan),
                            np.zeros(bins), np.zeros(bins), np.full(bins, np.nan))
    if count < 3:
        return nothing
    body = walk_body(vertices[:count], geometry)
    above = raw - dark
    usable = np.isfinite(above)  # dark and dim pixels are measurements too: leaving them out would bias the profile
    if settings["saturation"] is not None:
        usable &= raw < settings["saturation"]
    profile = exit_profile(np.where(usable, above, 0.0), usable, angles, rows, body, geometry,
                           geometry.beam_height, bins)
    if len(profile.views) < 2 or not np.all(profile.measured.sum(axis=0) > 0):
        return nothing
    everyone = np.ones(len(profile.views))
    contour = vertices[:count]
    traced_at = settings["initial"] or 1.0 / float(np.mean(np.hypot(*(contour - contour.mean(axis=0)).T)))
    for round_ in range(1, settings["max_rounds"] + 1):
        grid = traced_at * 2.0 ** np.linspace(-REACH_OCTAVES, REACH_OCTAVES, n)
        counts = candidate_counts(profile, body, geometry, angles, rows, grid, traced_at, settings,
                                   np.random.SeedSequence([seed, round_]))
        trusted = trusted_candidates(*counts)
        estimate, misfit = fit_profile(everyone, profile.measured, *counts, grid, trusted)
        span = grid[trusted]
        settled = bool(np.isfinite(estimate) and span.min() < estimate < span.max())
        if settled or not np.isfinite(estimate):
            break
        traced_at = estimate
    if not np.isfinite(estimate):
        return nothing
    rng = np.random.default_rng([seed, 0])
    shares = rng.multinomial(len(profile.views), np.full(len(profile.views), 1 / len(profile.views)),
                             size=settings["bootstrap"]).astype(float)
    spread = np.array([fit_profile(share, profile.measured, *counts, grid, trusted)[0] for share in shares])
    # a draw whose minimum is at an end of the trusted candidates lies somewhere beyond it: 0 or ∞, not the end
    spread = np.where(spread <= span.min(), 0.0, np.where(spread >= span.max(), np.inf, spread))
    low, high = np.percentile(spread, 16.0, method="lower"), np.percentile(spread, 84.0, method="higher")
    # the walks' weights at the candidate nearest the estimate: their effective number, and the profile
    at = int(np.argmin(np.abs(np.log(grid / estimate))))
    total, square = counts[0][at].sum(axis=0), counts[1][at].sum(axis=0)
    effective = float(total.sum() ** 2 / square.sum()) if square.sum() > 0 else 0.0
    measured = profile.measured.sum(axis=0)
    scale = np.exp(np.mean(np.log(measured) - np.log(np.maximum(total, np.finfo(float).tiny))))
    centres = 0.5 * (profile.edges[1:] + profile.edges[:-1])
    return _estimate_out(estimate, low, high, effective, round_, settled, misfit, grid, measured, scale * total,
                         centres)


def _estimate_out(*values) -> tuple[np.ndarray, ...]:
    return tuple(np.asarray(v, dtype) for v, dtype in zip(values, (d for _, d in _ESTIMATE.values()), strict=True))


#: the variables of an ``estimate_scattering`` store: dims and dtype, in :func:`_estimate_sigma_s`'s order
_ESTIMATE = {"sigma_s": ((), np.float64), "sigma_s_low": ((), np.float64), "sigma_s_high": ((), np.float64),
             "effective_walks": ((), np.float64), "rounds": ((), np.int64), "settled": ((), bool),
             "objective": (("candidate",), np.float64), "candidate_sigma_s": (("candidate",), np.float64),
             "measured_profile": (("distance_bin",), np.float64), "modelled_profile": (("distance_bin",), np.float64),
             "bin_distance": (("distance_bin",), np.float64)}


@stage("estimate_scattering", kind=SCATTERING_ESTIMATE)
def estimate_scattering(capture: xr.Dataset, hull: xr.Dataset, /, *, views: Count = 36, photons: Count = 50_000,
                        row_band: Index = 32, distance_bins: Annotated[int, pydantic.Field(ge=3)] = 12,
                        initial: Positive | None = None, bootstrap: Count = 200,
                        max_rounds: Annotated[int, pydantic.Field(ge=1, le=20)] = 6, max_events: Count = 1000,
                        seed: Index = 0) -> xr.Dataset:
    """σ_s of the medium, with its uncertainty, from how the reference object's frames spread the beam's light
    (lazy: one task).

    The reference object (the target's medium without the inclusions) shows, around the beam's slice, the light
    that left its surface after scattering: the farther from the entry point, the less, and how much less is set by
    σ_s. Its frames are binned by each pixel's distance from the entry point (over ``views`` views and the rows
    within ``row_band`` of the slice), and compared on a log scale, with a free scale, to photon walks in the hull's
    slice traced at σ_0 and reweighted to 41 candidates over half an octave each side (a walk's probability at σ_s is
    σ_s^k e^{−σ_s L}: one set of walks serves every candidate, with common random numbers, so the misfit is smooth
    in σ_s); the Monte Carlo share of the misfit is taken away (``_exit_profile.profile_misfit``). Only candidates whose
    walks keep half their number as effective walks are compared; where the minimum is at their end, the walks are
    traced again there, up to ``max_rounds`` rounds. The uncertainty is a bootstrap over the views (each its own
    frame and its own walks): ``sigma_s_low`` and ``sigma_s_high`` are the 16th and 84th percentiles, about ±1
    standard deviation; a draw whose minimum is at an end of the compared candidates counts as beyond it (0 or ∞),
    so a profile that no longer tells σ_s apart gives an open interval.

    **Where it stops telling.** Without absorption, the deeper into the diffusive regime, the less the profile's
    shape changes: on the §4.4.4 cylinders (radius 1) the misfit is within its noise for every σ_s from 4 to 11 at
    the σ_s = 5 capture. There ``sigma_s_high`` is ∞: read ``sigma_s_low`` as a lower bound.

    Assumes what the walks of ``reconstruct_scattering`` assume: isotropic scattering, no absorption in the medium,
    refractive index 1, the slice's contour extruded in z; and a beam (a light sheet lights every height at once).

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture``: ``reference`` (angle, row, col) [counts], ``dark`` (row, col) [counts; 0 if
        absent], the rig geometry and ``saturation_counts`` in its attrs. Every pixel that sees the hull counts, dim
        and dark ones too (a bin's sum is unbiased only so); pixels at or above saturation or not finite are left out.
    hull : xr.Dataset
        The ``hull`` store of the same capture: the beam's slice's contour.
    views : int
        Views used, evenly spaced over the capture's angles [1].
    photons : int
        Walks traced per view and round [1]; the Monte Carlo noise falls as 1/√photons.
    row_band : int
        Rows each side of the beam's row whose pixels are compared [rows]: more rows, more of the walks traced are
        compared (at 16 instead of 32 the σ_s = 3 capture's interval was 1.7× wider), as far as the contour
        extruded in z stays the object's.
    distance_bins : int
        Bins of the distance from the entry point, of equal numbers of pixels [1].
    initial : float or None
        σ_0 of the first round [1/length unit]; None: one over the contour's mean radius. The rounds climb (or
        descend) from it half an octave at most each, and stop at the first minimum: where the profile stops
        changing with σ_s (below), that is the smallest σ_s it allows.
    bootstrap : int
        Resamplings of the views for the uncertainty [1].
    max_rounds : int
        Rounds of walks at most [1]; ``settled`` is False where the last one's estimate still moved.
    max_events : int
        Scatterings before a walk is dropped [1].
    seed : int
        Seed of the walks and of the bootstrap.

    Returns
    -------
    xr.Dataset
        A ``scattering_estimate`` store: ``sigma_s`` (NaN where no view gave light in every distance bin),
        ``sigma_s_low``/``sigma_s_high``, ``settled``, ``rounds``, ``effective_walks`` (the walks' effective number at
        the estimate: low means the reweighting is stretched), and the last round's ``objective`` over its candidates
        ``candidate_sigma_s``, and the ``measured_profile``/``modelled_profile`` over ``bin_distance`` [length unit].

    References
    ----------
    Thesis §4.4.4 Effect of scattering.
    """
    require_variables(capture, ("reference",), "estimate_scattering")
    geometry = RigGeometry.from_attrs(capture.attrs, capture.sizes["row"], capture.sizes["col"],
                                      where="estimate_scattering: capture")
    if geometry.light_kind != "beam":
        raise StageError(Problem("estimate_scattering reads how a beam's light spreads from its entry point; this "
                                 "capture's light is a sheet, which lights every height at once",
                                 fix="capture the reference object with the beam (light_kind: beam)"))
    row = int(geometry.lit_rows()[0])
    shell = contours(hull, [row], "estimate_scattering")
    rows = np.arange(max(row - row_band, 0), min(row + row_band + 1, geometry.camera.rows))
    pick = np.unique(np.linspace(0, capture.sizes["angle"] - 1, min(views, capture.sizes["angle"])).round()
                     .astype(int))
    raw = capture["reference"].isel(angle=pick, row=rows).data
    dark = capture["dark"].isel(row=rows).data if "dark" in capture else np.zeros((len(rows), capture.sizes["col"]))
    settings = {"distance_bins": distance_bins, "initial": initial, "photons": photons,
                "bootstrap": bootstrap, "max_rounds": max_rounds, "max_events": max_events,
                "saturation": saturation_counts(capture.attrs)}
    parts = dask.delayed(_estimate_sigma_s, nout=len(_ESTIMATE), pure=True)(
        raw, dark, shell["vertices"].isel(slice=0).data, shell["n_vertices"].isel(slice=0).data, geometry=geometry,
        angles=capture["angle"].values[pick], rows=rows, settings=settings, seed=seed)
    import dask.array as da  # on computing, not on reading a workflow

    sizes = {"candidate": CANDIDATES, "distance_bin": distance_bins}
    variables = {name: (dims, da.from_delayed(part, tuple(sizes[d] for d in dims), dtype))
                 for (name, (dims, dtype)), part in zip(_ESTIMATE.items(), parts, strict=True)}
    unit = geometry.length_unit
    out = xr.Dataset(variables)
    attrs = {"row": row, "views": len(pick), "photons": photons, "row_band": row_band, "seed": seed}
    return SCATTERING_ESTIMATE.label(out.assign_attrs(geometry_attrs(capture.attrs) | attrs | {"length_unit": unit}))
