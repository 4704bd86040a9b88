"""The exact active-set finish (#25): certified bounds below gap_tol where ADMM alone leaves them ~1e-2, the
objective at Clarabel's optimum, and pixels outside its scope (masked or clipped frames) left as ADMM gave them."""

from __future__ import annotations

import numpy as np
import pytest

from stages.procam._demux_problem import DemuxProblem, certified_gap
from stages.procam._demux_solver import DemuxADMM
from tests.stages.procam.test_demux_solver import CASES, cvxpy_optimum, sparse_transport, sweep_matrix

#: the hard cases' slow sweep: 9 delays 5 rows apart, exposures of 10 and 30 rows over 65 offsets (a clean pixel
#: needs thousands of ADMM iterations at tol 1e-4)
SLOW = (np.arange(-340.0, 341.0, 85.0), [170.0, 510.0], np.arange(-32, 33))


@pytest.mark.parametrize("case", [*CASES, "slow"])
def test_the_finish_certifies_every_pixel_and_reaches_clarabels_optimum(case):
    delays, exposures, offsets = SLOW if case == "slow" else CASES[case]
    a = sweep_matrix(delays, exposures, offsets)
    rng = np.random.default_rng(11)
    truth = sparse_transport(rng, 16, offsets)
    data = truth @ a.T + rng.normal(0, 2e-3, (16, a.shape[0]))
    problem = DemuxProblem.build(a)
    plain = DemuxADMM(gap_tol=1e-6).solve(problem, data)
    finished = DemuxADMM(gap_tol=1e-6, finish_rounds=6).solve(problem, data)
    # measured: ADMM's bound max 0.44 / 0.22 / 2.2e-3 / 8.0e-2 (well-posed, rank-deficient, wide, slow); finished
    # max 1.3e-5 / 4.8e-6 / 1.5e-5 / 5.9e-6 (the float32 rounding of the returned T is the floor)
    bound, touched = finished.stats["gap_bound"], plain.stats["gap_bound"] > 1e-6
    assert touched.mean() >= 0.5
    # a finished pixel's bound is of the returned (float32) transport in float64: a proof, recomputed here
    np.testing.assert_allclose(bound[touched], certified_gap(problem, finished.value.astype(float), data)[touched],
                               rtol=1e-6, atol=1e-15)  # the bound is stored in float32
    assert bound.max() <= 1e-4 and finished.converged.all(), (bound.max(), plain.stats["gap_bound"].max())
    assert np.all(bound <= plain.stats["gap_bound"])  # never worse than ADMM's own answer
    _, optimum = cvxpy_optimum(problem, data)
    value = problem.objective(finished.value.astype(float), data)
    # Clarabel at its default accuracy is itself ~1e-8 from the optimum; the finish is within float32 rounding
    np.testing.assert_allclose(value, optimum, rtol=1e-5)
    assert np.all(finished.stats["objective"] <= plain.stats["objective"] * (1 + 1e-6))


def test_pixels_with_masked_or_clipped_frames_keep_admms_answer():
    delays, exposures, offsets = CASES["well-posed"]
    a = sweep_matrix(delays, exposures, offsets)
    rng = np.random.default_rng(12)
    data = sparse_transport(rng, 8, offsets) @ a.T
    data[0, 3] = np.nan
    clipped = np.zeros(data.shape, bool)
    clipped[1, data[1].argmax()] = True
    problem = DemuxProblem.build(a)
    plain = DemuxADMM(gap_tol=1e-6).solve(problem, data, clipped=clipped)
    finished = DemuxADMM(finish_rounds=6, gap_tol=1e-6).solve(problem, data, clipped=clipped)
    np.testing.assert_array_equal(finished.value[:2], plain.value[:2])
    np.testing.assert_array_equal(finished.stats["gap_bound"][:2], plain.stats["gap_bound"][:2])
    assert finished.stats["gap_bound"][2:].max() <= 1e-4
