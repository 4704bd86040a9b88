"""The exact active-set finish (#25): certified bounds below gap_tol where ADMM alone leaves them ~1e-2, the
objective at Clarabel's optimum, with masked and clipped frames as without."""

from __future__ import annotations

import numpy as np
import pytest

from selpath.stages._solution import Result, SolverError
from selpath.stages.procam._demux_certificate import certified_gap
from selpath.stages.procam._demux_problem import DemuxProblem
from selpath.stages.procam._demux_solver import DemuxADMM
from tests.helpers.demux_cases import CASES, cvxpy_optimum, sparse_transport, sweep_matrix

#: the hard cases' slow sweep: 9 delays 5 rows apart, exposures of 10 and 30 rows over 65 offsets (a clean pixel
#: needs thousands of ADMM iterations at tol 1e-4)
SLOW = (np.arange(-340.0, 341.0, 85.0), [170.0, 510.0], np.arange(-32, 33))


@pytest.mark.parametrize("case", ["rank-deficient", *(pytest.param(c, marks=pytest.mark.slow)
                                                     for c in [*CASES, "slow"] if c != "rank-deficient")])
def test_the_finish_certifies_every_pixel_and_reaches_clarabels_optimum(case):
    delays, exposures, offsets = SLOW if case == "slow" else CASES[case]
    a = sweep_matrix(delays, exposures, offsets)
    rng = np.random.default_rng(11)
    truth = sparse_transport(rng, 16, offsets)
    data = truth @ a.T + rng.normal(0, 2e-3, (16, a.shape[0]))
    problem = DemuxProblem.build(a)
    # ADMM stopped early (8 iterations) and its KKT bound without the dual ascent, so that its answers leave the
    # finish work: at the defaults the KKT bound certifies most of them to 1e-6 without it (all of the wide case's)
    # (a batch of the pool's own 16 pixels, as measured: padded to 64, the kernels' float32 rounding differs and
    # takes the wide case's one pixel left to the finish from a bound of 2.2e-6 to 7.5e-7, leaving none)
    plain = DemuxADMM(gap_tol=1e-6, tol=5e-3, max_iter=8, dual_steps=0, polish_rounds=1, max_gap=1.0,
                      slots=16).solve(problem, data)
    finished = DemuxADMM(gap_tol=1e-6, max_gap=1e-6, tol=5e-3, max_iter=8, dual_steps=0, polish_rounds=1,
                         finish_rounds=6, slots=16).solve(problem, data)
    # measured: ADMM's bound max 0.44 / 0.22 / 2.2e-3 / 8.0e-2 (well-posed, rank-deficient, wide, slow); finished
    # max 1.3e-5 / 4.8e-6 / 1.5e-5 / 5.9e-6 (the float32 rounding of the returned T is the floor)
    bound, touched = finished.stats["gap_bound"], plain.stats["gap_bound"] > 1e-6
    assert touched.any()  # measured: 9, 13, 1 and 16 of 16 left to the finish (well-posed, rank-deficient, wide, slow)
    # a finished pixel's bound is of the returned (float32) transport in float64: a proof, recomputed here
    np.testing.assert_allclose(bound[touched], certified_gap(problem, finished.value.astype(float), data,
                                                             dual_steps=0)[touched],
                               rtol=1e-6, atol=1e-15)  # the bound is stored in float32
    assert bound.max() <= 1e-4, (bound.max(), plain.stats["gap_bound"].max())
    # with the finish, converged means certified to gap_tol (1e-6 here: below the float32 floor for most pixels)
    np.testing.assert_array_equal(finished.converged, bound <= 1e-6)
    assert np.all(bound <= plain.stats["gap_bound"])  # never worse than ADMM's own answer
    _, optimum = cvxpy_optimum(problem, data)
    value = problem.objective(finished.value.astype(float), data)
    # Clarabel at its default accuracy is itself ~1e-8 from the optimum; the finish is within float32 rounding
    np.testing.assert_allclose(value, optimum, rtol=1e-5)
    assert np.all(finished.stats["objective"] <= plain.stats["objective"] * (1 + 1e-6))


@pytest.mark.parametrize("case", ["well-posed", pytest.param("rank-deficient", marks=pytest.mark.slow)])
def test_pixels_with_masked_and_clipped_frames_are_finished_to_clarabels_optimum(case):
    """Masked (NaN) frames and clipped frames (the one-sided penalty, whose acting frames the finish re-decides
    each round) get their own free-set Hessians: certified like the others, at Clarabel's optimum of the same
    objective (``benchmarks.demux_catalogue.reference``: 1e-12 on the rescaled problem)."""
    from benchmarks.demux_catalogue import reference

    delays, exposures, offsets = CASES[case]
    a = sweep_matrix(delays, exposures, offsets)
    rng = np.random.default_rng(12)
    data = sparse_transport(rng, 24, offsets) @ a.T + rng.normal(0, 2e-3, (24, a.shape[0]))
    data[rng.random(data.shape) < 0.1] = np.nan
    level = np.nanpercentile(data, 90)  # the brightest 10 % of observations clip
    clipped = np.isfinite(data) & (data >= level)
    data = np.where(clipped, level, data)
    assert clipped.any(axis=1).mean() > 0.25 and np.isnan(data).any(axis=1).mean() > 0.25
    problem = DemuxProblem.build(a)
    plain = DemuxADMM(gap_tol=1e-6, tol=5e-3, polish_rounds=1, max_gap=1.0).solve(problem, data, clipped=clipped)
    finished = DemuxADMM(gap_tol=1e-6, max_gap=1e-6, tol=5e-3, polish_rounds=1, finish_rounds=8).solve(
        problem, data, clipped=clipped)
    bound = finished.stats["gap_bound"]
    # measured: ADMM's bound max 0.13 (well-posed) / 0.69 (rank-deficient); finished max 5.1e-6 / 6.7e-6
    assert bound.max() <= 1e-4 and np.all(bound <= plain.stats["gap_bound"]), (bound.max(),
                                                                              plain.stats["gap_bound"].max())
    seen = np.isfinite(data)
    recomputed = certified_gap(problem, finished.value.astype(float), data, seen, clipped)
    touched = plain.stats["gap_bound"] > 1e-6  # the others ADMM certified itself: the solver's float32 bound
    # a finished pixel's bound is a float64 one of the returned T: with the dual ascent where it was above gap_tol
    # without it (the finish's rule), so between the two recomputed here
    fixed = certified_gap(problem, finished.value.astype(float), data, seen, clipped, dual_steps=0)
    assert np.all(bound[touched] >= recomputed[touched] * (1 - 1e-6) - 1e-15)
    assert np.all(bound[touched] <= fixed[touched] * (1 + 1e-6) + 1e-15)
    # the solver's float32 bound against the float64 reference: below ~1e-7 of f both sit at float32's rounding
    # (measured: 4.9e-8 against 4.7e-8 at the worst pixel, the two dual ascents taking different float paths)
    np.testing.assert_allclose(bound[~touched], recomputed[~touched], rtol=2e-2, atol=1e-8)
    optimum = reference(problem, data, seen, clipped)
    value = problem.objective(finished.value.astype(float), data, seen, clipped)
    assert np.all((value - optimum) / value <= bound + 1e-9)  # the bound holds
    np.testing.assert_allclose(value, optimum, rtol=2e-5)


def test_max_gap_is_what_converged_proves_and_where_the_finish_runs():
    """``max_gap`` (the defaults' 1e-3): the exact finish runs on the pixels whose bound after the solve exceeds it
    and on no other (a pixel between gap_tol and max_gap keeps ADMM's answer), and ``converged`` means exactly a
    certified bound of at most max_gap, whatever the residual test said; max_gap = 1 (no cap, no finish) is the
    residual test alone. The finished pixels' bounds hold against Clarabel's optimum."""
    delays, exposures, offsets = CASES["rank-deficient"]
    a = sweep_matrix(delays, exposures, offsets)
    rng = np.random.default_rng(14)
    data = sparse_transport(rng, 64, offsets) @ a.T + rng.normal(0, 2e-3, (64, a.shape[0]))
    problem = DemuxProblem.build(a)
    assert problem.definite  # the cap applies where the second-order bound does
    # a loose residual test, no polish, no dual ascent: answers it accepts with bounds far above 1e-3
    short = {"tol": 5e-2, "max_iter": 20, "polish_iter": 0, "dual_steps": 0}
    loose = DemuxADMM(**short, finish_rounds=0, max_gap=1.0).solve(problem, data)
    capped = DemuxADMM(**short, finish_rounds=0).solve(problem, data)
    finished = DemuxADMM(**short).solve(problem, data)
    bound = loose.stats["gap_bound"]
    above = bound > 1e-3
    # measured: 52 of 64 pixels above max_gap, every one of them passed the residual test
    assert (loose.converged & above).sum() >= 5 and (~above).sum() >= 5
    np.testing.assert_array_equal(capped.value, loose.value)
    np.testing.assert_array_equal(capped.converged, ~above)  # the residual test's verdict no longer counts
    assert np.all(capped.result[above] == Result.unproven)  # not converged for want of a proof, not of iterations
    with pytest.raises(SolverError, match=r"unproven \(its certified error bound"):
        DemuxADMM(**short, finish_rounds=0, throw=True).solve(problem, data)
    # the finish touched the pixels above max_gap only, and took each to a bound of at most max_gap: all converged
    np.testing.assert_array_equal(finished.value[~above], loose.value[~above])
    assert np.all(finished.stats["gap_bound"][above] <= 1e-3) and finished.converged.all()
    _, optimum = cvxpy_optimum(problem, data)
    value = problem.objective(finished.value.astype(float), data)
    assert np.all((value - optimum) / value <= finished.stats["gap_bound"] + 1e-7)  # the bound holds
    with pytest.raises(ValueError, match="gap_tol ≤ max_gap"):
        DemuxADMM(gap_tol=1e-2, max_gap=1e-3)
