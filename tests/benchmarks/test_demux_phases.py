"""The phase profile of ``benchmarks/demux_phases.py``: its timers see every phase of a solve, and leave the solver
as they found it (a phase the solver stopped calling through its module would hide in "other", silently)."""

import numpy as np

import selpath.stages.procam._demux_kernels as kernels
from benchmarks._demux_sweep import matrix, sample
from benchmarks.demux_phases import PHASES, timed_phases
from selpath.stages.procam._demux_problem import DemuxProblem
from selpath.stages.procam._demux_solver import DemuxADMM


def test_every_phase_is_timed_and_the_solver_is_restored():
    problem = DemuxProblem.build(matrix(64, kept_only=True))
    data, clipped = sample(64, 256, 1, 256)
    data[:8, 3] = np.nan  # masked frames: the host certificate runs
    before = [getattr(kernels, name) for _, owner, name in PHASES if owner == "kernels"]
    finish, certify = DemuxADMM._finish, DemuxADMM._certify_partial
    totals: dict = {}
    calls: dict = {}
    with timed_phases(totals, calls):
        # max_gap 0: every pixel above it gets the exact finish, so every phase runs
        DemuxADMM(max_gap=1e-12, gap_tol=0.0, finish_rounds=1).solve(problem, data, clipped=clipped)
    assert set(totals) == {label for label, _, _ in PHASES}
    assert set(calls) == {name for _, _, name in PHASES}  # each wrapped function, also those that share a label
    assert all(seconds > 0 for seconds in totals.values())
    assert [getattr(kernels, name) for _, owner, name in PHASES if owner == "kernels"] == before
    assert (DemuxADMM._finish, DemuxADMM._certify_partial) == (finish, certify)

