"""An exact finish for the demultiplexing ADMM: primal–dual active-set rounds with float64 free-set solves (#25).

ADMM's answer is accurate in the objective (~1e-4) but not in its KKT conditions, so its certified bound (weak
duality from T's own gradients, :func:`selpath.stages.procam._demux_certificate.certified_gap`) stays ~1e-2. Where the
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

Scope: dense problems (:class:`~selpath.stages.procam._demux_problem.DemuxProblem`), every finite pixel. A pixel whose
frames all act has the shared Hessian 2G; one with masked frames, or clipped frames (the one-sided penalty
max(0, y − AT)², which acts while AT is below the clip level: each round also re-decides which clipped frames
act, a semismooth Newton step), builds its free block from A's free columns.
"""

from __future__ import annotations

import numpy as np

from selpath.stages.procam._demux_certificate import certified_gap
from selpath.stages.procam._demux_problem import DemuxProblem
from selpath.stages.procam._demux_settings import DUAL_STEPS
from selpath.stages.procam._illumination import smoothness_matrix

#: the active-set rule's weight on T against λ: large, so an offset with light stays free whatever its gradient
KAPPA = 1e3
#: golden-section steps of the bound's dual search in the rounds: none, as an exact free-set solve makes the
#: gradients' own dual point (θ = 1, lifted) tight and the search cost ~20 % of the finish for no measured gain
#: (the returned bound is computed once more with the search)
_SEARCH = 0


def active_set_finish(problem: DemuxProblem, transport: np.ndarray, data: np.ndarray, bound: np.ndarray, *,
                      rounds: int, gap_tol: float, weight: np.ndarray | None = None,
                      clipped: np.ndarray | None = None, dual_steps: int = DUAL_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``rounds`` exact active-set rounds on the pixels whose ``bound`` exceeds ``gap_tol``.

    ``transport`` (P, K) is ADMM's answer in the data's units, ``data`` (P, N) with ``weight`` (0/1, None: all
    observed; non-finite data are masked) and ``clipped`` flags (data there the clip level), ``bound`` (P,) its
    certified bounds; ``dual_steps`` of the KKT bound's dual ascent for the returned answers (none in the rounds,
    whose exact free-set solves leave no weak-direction residual for it to remove, nor for the incoming answer they
    are compared with). Returns (transport in ``transport``'s dtype, the float64 certified bound of that returned
    transport), each pixel's never worse than it came up to the rounding of the incoming bound (a pixel the rounds do
    not improve returns its own answer with that answer's float64 bound, which may read ~1e-6 relative above a
    float32 ``bound``).
    """
    transport, bound = np.array(transport), np.array(bound, np.float64)
    todo = np.flatnonzero(bound > gap_tol)
    if not todo.size or rounds < 1:
        return transport, bound
    raw = np.asarray(data, np.float64)[todo]
    seen = np.isfinite(raw) & (True if weight is None else np.asarray(weight)[todo] > 0)
    clip = np.zeros(raw.shape, bool) if clipped is None else np.asarray(clipped, bool)[todo] & seen
    y = np.where(seen, raw, 0.0)
    scale = np.max(np.abs(y), axis=1, keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    y = y / scale
    beta = problem.beta / scale
    a = problem.illumination
    smooth = 2.0 * problem.alpha * smoothness_matrix(a.shape[1])
    t = transport[todo].astype(np.float64) / scale
    # start from the float64 bound of the incoming answer (the solver's is float32 and may read low), so every
    # returned bound of these pixels is a float64 one of the returned transport
    best_t = transport[todo]
    best_bound = certified_gap(problem, best_t.astype(np.float64), raw, seen, clip, search_steps=_SEARCH,
                               dual_steps=0)  # the rounds' own bound, so that a round's answer is judged alike
    live = np.flatnonzero(best_bound > gap_tol)  # rows of todo still in the rounds
    free = t > 0
    for round_ in range(rounds):
        if not live.size:
            break
        y_l, t_l = y[live], t[live]
        prediction = t_l @ a.T
        # the frames whose penalty acts at T: every observed one, a clipped one only while T predicts below it
        frames = seen[live] & ~(clip[live] & (prediction >= y_l))
        if round_:
            gradient = 2.0 * (frames * (prediction - y_l)) @ a + t_l @ smooth + beta[live]
            free[live] = gradient - KAPPA * t_l <= 0
        t[live] = _solve_free(problem, frames, y_l, beta[live], free[live], smooth)
        candidate = (np.maximum(t[live], 0.0) * scale[live]).astype(transport.dtype)  # as returned: the proof's T
        gap = certified_gap(problem, candidate.astype(np.float64), raw[live], seen[live], clip[live],
                            search_steps=_SEARCH, dual_steps=0)
        better = gap < best_bound[live]
        best_t[live[better]], best_bound[live[better]] = candidate[better], gap[better]
        live = live[best_bound[live] > gap_tol]
    # the returned bound is certified_gap's own (with its dual search: never above the rounds' search-free one, and
    # its dual ascent); where a round's answer replaced the incoming one, the better of the two by that bound (the
    # ascent can favour the incoming answer that the rounds' bound ranked below)
    final = certified_gap(problem, best_t.astype(np.float64), raw, seen, clip, dual_steps=0)
    loose = np.flatnonzero(final > gap_tol) if dual_steps else np.zeros(0, int)  # the ascent only where it may matter
    if loose.size:
        final[loose] = certified_gap(problem, best_t[loose].astype(np.float64), raw[loose], seen[loose], clip[loose],
                                     dual_steps=dual_steps)
    # candidates for going back: a round's answer whose bound is above the incoming one's (the caller's, in its dtype)
    changed = np.flatnonzero(np.any(best_t != transport[todo], axis=1) & (bound[todo] < final))
    if dual_steps and changed.size:
        incoming = certified_gap(problem, transport[todo[changed]].astype(np.float64), raw[changed], seen[changed],
                                 clip[changed], dual_steps=dual_steps)
        back = changed[incoming < final[changed]]
        best_t[back], final[back] = transport[todo[back]], incoming[incoming < final[changed]]
    transport[todo], bound[todo] = best_t, final
    return transport, bound


def _solve_free(problem: DemuxProblem, frames: np.ndarray, y: np.ndarray, beta: np.ndarray, free: np.ndarray,
                smooth: np.ndarray) -> np.ndarray:
    """Per pixel, T with T_F = H_FF⁻¹ r_F on its free set F and 0 elsewhere, where H = 2AᵀWA + 2αDᵀD and
    r = 2AᵀWy − β over its acting frames W (float64; pixels grouped by |F|, each group one batched solve; a pixel
    with every frame acting takes H_FF from the shared 2G, the others build theirs from A's free columns; a
    singular H_FF gets its least-squares solution)."""
    a, q = problem.illumination, problem.gram2
    rhs_all = 2.0 * (frames * y) @ a - beta
    everything = frames.all(axis=1)
    t = np.zeros(rhs_all.shape)
    counts = free.sum(axis=1)
    for n in np.unique(counts):
        if n == 0:
            continue
        rows = np.flatnonzero(counts == n)
        index = np.nonzero(free[rows])[1].reshape(rows.size, n)  # each row's free offsets, in order
        sub = q[index[:, :, None], index[:, None, :]]
        partial_rows = np.flatnonzero(~everything[rows])
        if partial_rows.size:  # 2 A_Fᵀ W A_F + 2α (DᵀD)_FF for the pixels with masked or inactive frames
            columns = a[:, index[partial_rows]].transpose(1, 0, 2)  # (m, N, n)
            weighted = columns * frames[rows[partial_rows]][:, :, None]
            sub[partial_rows] = (2.0 * np.einsum("mji,mjk->mik", weighted, columns, optimize=True)
                                 + smooth[index[partial_rows][:, :, None], index[partial_rows][:, None, :]])
        rhs = np.take_along_axis(rhs_all[rows], index, axis=1)
        try:
            solved = np.linalg.solve(sub, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            solved = np.stack([np.linalg.lstsq(s, r, rcond=None)[0] for s, r in zip(sub, rhs, strict=True)])
        part = np.zeros((rows.size, rhs_all.shape[1]))
        np.put_along_axis(part, index, solved, axis=1)
        t[rows] = part
    return t
