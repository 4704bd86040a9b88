"""The phase profile of ``benchmarks/demux_phases.py``: a timed solve names every phase the solver ran, each with a
positive time, and answers exactly as the untimed solve (timing only waits for each phase's result)."""

import numpy as np

from benchmarks._demux_sweep import matrix, sample
from benchmarks.demux_phases import PHASES
from selpath.stages.procam.solver import DemuxADMM, DemuxProblem


def test_a_timed_solve_times_every_phase_and_answers_as_the_untimed_one():
    problem = DemuxProblem.build(matrix(64, kept_only=True))
    data, clipped = sample(64, 256, 1, 256)
    data[:8, 3] = np.nan  # masked frames: the host certificate runs
    # max_gap 0: every pixel above it gets the exact finish, so every phase runs
    solver = DemuxADMM(max_gap=1e-12, gap_tol=0.0, finish_rounds=1)
    timed = DemuxADMM(max_gap=1e-12, gap_tol=0.0, finish_rounds=1, timed=True).solve(problem, data, clipped=clipped)
    seconds = timed.stats.pop("phase_seconds")
    assert list(seconds) == list(PHASES) and all(s > 0 for s in seconds.values())
    plain = solver.solve(problem, data, clipped=clipped)
    assert "phase_seconds" not in plain.stats
    np.testing.assert_array_equal(timed.value, plain.value)
    np.testing.assert_array_equal(timed.result, plain.result)
    for name, values in plain.stats.items():
        np.testing.assert_array_equal(timed.stats[name], values)


def test_the_benchmarks_solve_through_the_public_solver_module():
    """#56: the demultiplexing benchmarks import the solver from ``selpath.stages.procam.solver``, never from the
    private ``_demux_*`` modules behind it (``demux_solve_sizes`` alone sets the kernels' product precision, a knob
    no public name holds, and says so in its docstring)."""
    import re
    from pathlib import Path

    import selpath.stages.procam.solver as public

    root = Path(__file__).resolve().parents[2] / "benchmarks"
    private = re.compile(r"selpath\.stages\.procam\._(demux_\w+|capture_to_transport)")
    offenders = {path.name: private.findall(path.read_text()) for path in sorted(root.glob("demux_*.py"))}
    offenders = {name: found for name, found in offenders.items() if found}
    assert offenders == {"demux_solve_sizes.py": ["demux_problem"]}, offenders
    for name in public.__all__:  # each public name is what the private module defines (no copy)
        assert getattr(public, name).__module__.startswith(("selpath.stages.procam._", "selpath.stages._")), name
