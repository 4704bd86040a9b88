"""The demultiplexing problem catalogue of the solver tests: sweep matrices, sparse transports and the cases
(well-posed, rank-deficient, wide exposures …), with the independent reference optimum (CVXPY) to compare with."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from selpath.stages.procam._demux_problem import DemuxProblem
from selpath.stages.procam._illumination import plane_to_ray_illumination


def cvxpy_optimum(problem: DemuxProblem, data: np.ndarray,
                  weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The thesis's per-pixel CVXPY problem, solved to Clarabel's default accuracy, one pixel at a time."""
    n, k = problem.illumination.shape
    t, y, w = cp.Variable(k), cp.Parameter(n), cp.Parameter(n, nonneg=True)
    residual = cp.multiply(w, problem.illumination @ t) - y  # y holds w·data: DPP, one compiled problem
    objective = cp.sum_squares(residual) + problem.alpha * cp.sum_squares(cp.diff(t)) + problem.beta * cp.sum(t)
    qp = cp.Problem(cp.Minimize(objective), [t >= 0])
    solutions, values = [], []
    for p in range(data.shape[0]):
        w.value = np.ones(n) if weight is None else weight[p].astype(float)
        y.value = np.nan_to_num(data[p]) * w.value
        qp.solve(solver=cp.CLARABEL)
        solutions.append(np.clip(t.value, 0, None))
        values.append(qp.value)
    return np.array(solutions), np.array(values)


def sweep_matrix(delays, exposures, offsets):
    d, e = np.meshgrid(delays, exposures, indexing="ij")
    return plane_to_ray_illumination(d.ravel(), e.ravel(), offsets, scan_speed=1 / 17, line_time=17)


def sparse_transport(rng, pixels, offsets):
    o = offsets[None, :]
    return (rng.uniform(0.2, 0.9, (pixels, 1)) * (o == 0)
            + rng.uniform(0, 0.1, (pixels, 1)) * np.exp(-np.abs(o) / rng.uniform(1, 4, (pixels, 1)))
            + rng.uniform(0, 0.2, (pixels, 1)) * np.exp(-(o - rng.integers(-6, 7, (pixels, 1))) ** 2 / 2.0))


CASES = {
    # N = 21 frames ≥ K = 17 offsets, exposures 1–5 rows
    "well-posed": (np.arange(-136, 137, 34.0), [17.0, 51.0, 85.0], np.arange(-8, 9)),
    # N = 6 < K = 17: rank-deficient, only the smoothness term makes it unique
    "rank-deficient": (np.array([-85.0, 0.0, 85.0]), [51.0, 119.0], np.arange(-8, 9)),
    # exposures of 15 rows against a 1-row delay step: heavily overlapping boxes
    "wide-exposures": (np.arange(-136, 137, 17.0), [255.0], np.arange(-8, 9)),
}
