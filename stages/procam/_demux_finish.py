"""An exact finish for the demultiplexing ADMM: primal–dual active-set rounds with float64 free-set solves (#25).

ADMM's answer is accurate in the objective (~1e-4) but not in its KKT conditions, so its certified bound (weak
duality from T's own gradients, :func:`stages.procam._demux_problem.certified_gap`) stays ~1e-2. Where the
active set is right, the free offsets' KKT system G_FF T_F = (Aᵀy − β/2)_F solved exactly gives the optimum,
and the bound falls to rounding. This finish (Hintermüller, Ito & Kunisch's primal–dual active-set method) starts
from ADMM's support and, each round, frees the offsets where λ_i − κT_i ≤ 0 (λ = ∇f, κ = :data:`KAPPA`), holds
the others at 0 and solves the free set exactly; a pixel keeps a round's answer only where it lowers its bound,
and leaves the rounds once certified to ``gap_tol``.

Measured (``benchmarks/demux_active_set_probe.py``, benchmark stack, K = 128): from ADMM's 1.2e-2 median bound,
every pixel ≤ 1e-4 after 4 rounds, ≤ 3e-12 after 5, in float64. In float32 the free sets' systems are too
ill-conditioned to settle (max 0.44 after 5 rounds), so the solves here are float64, on the host: numpy's batched
LAPACK solve over the pixels grouped by free-set size (each group one (m, n, n) solve; no library batches
factorisations of differently masked submatrices of one matrix, and JAX would compile one kernel per size).

Scope: dense problems (:class:`~stages.procam._demux_problem.DemuxProblem`) and pixels without masked or clipped
frames (their Hessian is the shared 2G); the others keep ADMM's answer and its bound.
"""

from __future__ import annotations

import numpy as np

from stages.procam._demux_problem import DemuxProblem, certified_gap

#: the active-set rule's weight on T against λ: large, so an offset with light stays free whatever its gradient
KAPPA = 1e3


def active_set_finish(problem: DemuxProblem, transport: np.ndarray, data: np.ndarray, bound: np.ndarray, *,
                      rounds: int, gap_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``rounds`` exact active-set rounds on the pixels whose ``bound`` exceeds ``gap_tol``.

    ``transport`` (P, K) is ADMM's answer in the data's units, ``data`` (P, N) complete and unclipped, ``bound``
    (P,) its certified bounds. Returns (transport in ``transport``'s dtype, the float64 certified bound of that
    returned transport), each pixel's never worse than it came.
    """
    transport, bound = np.array(transport), np.array(bound, np.float64)
    todo = np.flatnonzero(bound > gap_tol)
    if not todo.size or rounds < 1:
        return transport, bound
    y = np.asarray(data, np.float64)[todo]
    scale = np.max(np.abs(y), axis=1, keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    q = problem.gram2
    c = 2.0 * (y / scale) @ problem.illumination - problem.beta / scale  # ∇f(T) = QT − c on the scaled data
    t = transport[todo].astype(np.float64) / scale
    # start from the float64 bound of the incoming answer (the solver's is float32 and may read low), so every
    # returned bound of these pixels is a float64 one of the returned transport
    best_t, best_bound = transport[todo], certified_gap(problem, transport[todo].astype(np.float64), y)
    live = np.ones(todo.size, bool)
    free = t > 0
    for round_ in range(rounds):
        if round_:
            free = (t @ q - c) - KAPPA * t <= 0
        t = np.where(live[:, None], _solve_free(q, c, free, live), t)
        candidate = (np.maximum(t, 0.0) * scale).astype(transport.dtype)  # as returned: its bound is the proof
        gap = certified_gap(problem, candidate.astype(np.float64), y)
        better = live & (gap < best_bound)
        best_t[better], best_bound[better] = candidate[better], gap[better]
        live &= best_bound > gap_tol
        if not live.any():
            break
    transport[todo], bound[todo] = best_t, best_bound
    return transport, bound


def _solve_free(q: np.ndarray, c: np.ndarray, free: np.ndarray, live: np.ndarray) -> np.ndarray:
    """Per live pixel, T with T_F = Q_FF⁻¹ c_F on its free set F and 0 elsewhere (float64; pixels grouped by
    |F|, each group one batched solve; a singular Q_FF gets its least-squares solution)."""
    t = np.zeros(c.shape)
    counts = free.sum(axis=1)
    for n in np.unique(counts[live]):
        if n == 0:
            continue
        rows = np.flatnonzero(live & (counts == n))
        index = np.nonzero(free[rows])[1].reshape(rows.size, n)  # each row's free offsets, in order
        sub = q[index[:, :, None], index[:, None, :]]
        rhs = np.take_along_axis(c[rows], index, axis=1)
        try:
            solved = np.linalg.solve(sub, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            solved = np.stack([np.linalg.lstsq(s, r, rcond=None)[0] for s, r in zip(sub, rhs, strict=True)])
        part = np.zeros((rows.size, c.shape[1]))
        np.put_along_axis(part, index, solved, axis=1)
        t[rows] = part
    return t
