"""The demultiplexing solver as a library: what ``demux_plane_to_ray`` and ``demux_full`` run per band, for scripts,
benchmarks and notebooks that solve pixels without a store (thesis §5.3.3, #25, #56).

- :class:`DemuxProblem` (one illumination matrix A, N frames × K offsets) and :class:`SeparableDemuxProblem` (the
  full transport's A = line matrix ⊗ frame matrix) hold the objective ‖w(AT − y)‖² + α‖DT‖² + β1ᵀT, T ≥ 0;
- :class:`DemuxADMM` solves a batch of pixels (``solve(problem, data, clipped=...)`` → a :class:`Solution` whose
  ``stats`` hold each pixel's certified ``gap_bound`` and its iterations, and with ``timed=True`` each
  phase's seconds);
- :func:`certified_gap` is the float64 reference of that bound (weak duality), for any answer, from any solver;
- :func:`solve_pixels` is the stages' own call (counts in, counts out, clipped frames as lower bounds);
  :func:`pixels_per_call` the batch size they use.

The modules behind these names (``_demux_*``) are private: their layout may change, these names do not.

>>> import numpy as np
>>> problem = DemuxProblem.build(np.eye(3), alpha=0.0, beta=0.0)
>>> solution = DemuxADMM().solve(problem, np.array([[1.0, 0.0, 2.0]]))
>>> np.round(solution.value, 3).tolist(), bool(certified_gap(problem, solution.value, [[1.0, 0.0, 2.0]])[0] < 1e-3)
([[1.0, 0.0, 2.0]], True)
"""

from __future__ import annotations

from selpath.stages._solution import Solution
from selpath.stages.procam._capture_to_transport import OffsetGrid, pixels_per_call, solve_pixels
from selpath.stages.procam._demux_certificate import certified_gap
from selpath.stages.procam._demux_problem import DemuxProblem, SeparableDemuxProblem
from selpath.stages.procam._demux_solver import DemuxADMM

__all__ = ["DemuxADMM", "DemuxProblem", "OffsetGrid", "SeparableDemuxProblem", "Solution", "certified_gap",
           "pixels_per_call", "solve_pixels"]
