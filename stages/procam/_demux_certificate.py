"""The certificate of a demultiplexed pixel (#25): certified bounds on its relative objective gap, from weak duality.

:func:`certified_gap` is the float64 reference (the first-order bound from T's own gradients with a dual search,
:func:`best_dual_value`, and for every pixel of a dense problem the second-order :func:`kkt_gap`, through
:func:`kept_hessian` where frames are masked or clipped: :func:`kkt_bound`); :mod:`selpath.stages.procam._demux_kernels`
evaluates the same bounds in the solver's dtype with these functions (written for numpy or ``jax.numpy`` through
``xp``; there the second-order one for fully observed, unclipped pixels only, the solver adding :func:`kkt_bound` on
the host for the others). The problems themselves are in :mod:`selpath.stages.procam._demux_problem`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selpath.stages.procam._demux_problem import DemuxProblem, SeparableDemuxProblem, _residual
from selpath.stages.procam._demux_settings import DUAL_STEPS

#: golden-section steps of the dual search in :func:`best_dual_value` (the interval shrinks 0.618× per step)
DUAL_SEARCH_STEPS = 16
_GOLDEN = (5**0.5 - 1) / 2

def best_dual_value(xp, a, b, z, g, e_y, e_u, n_e, beta, steps=DUAL_SEARCH_STEPS):
    """The largest dual value D(θu + s·e, θv) found over θ ≥ 0 and real s, feasible (see certified_gap).

    Per pixel: a = Σ u ỹ, b = Σ r² + α‖DT‖² (D(θ, 0) = −θa − θ²b), z = Aᵀu + Dᵀv (K,), g = Aᵀe (K,) with e the
    unclipped observed frames, e_y = Σ e ỹ, e_u = Σ e u, n_e = Σ e; beta (P,) or scalar.
    D(θ, s) = −θa − θ²b − s e_y − θ s e_u / 2 − s² n_e / 4, feasible where θ z_k + s g_k ≥ −β for every k.
    """
    beta = xp.asarray(beta) * xp.ones_like(a)
    tiny = xp.finfo(a.dtype).tiny
    blind = g <= 0
    # offsets no unclipped frame sees: only θ can keep them feasible
    worst_blind = xp.max(xp.where(blind, xp.maximum(-z, 0.0), 0.0), axis=-1)
    cap = xp.where(worst_blind > 0, beta / xp.maximum(worst_blind, tiny), xp.inf)
    theta_free = xp.where(b > 0, -a / xp.maximum(2.0 * b, tiny), 1.0)
    safe_g = xp.where(blind, 1.0, g)
    # offset k needs s ≥ lift_k + θ·slope_k (never, where blind)
    lift = xp.where(blind, -xp.inf, -beta[:, None] / safe_g)
    slope = xp.where(blind, 0.0, -z / safe_g)

    def value(theta):
        s_min = xp.max(lift + theta[:, None] * slope, axis=-1)  # −∞ where every offset is blind
        s_free = xp.where(n_e > 0, -(2.0 * e_y + theta * e_u) / xp.maximum(n_e, tiny), 0.0)
        s = xp.maximum(s_min, s_free)
        return -theta * a - theta**2 * b - s * e_y - theta * s * e_u / 2.0 - s**2 * n_e / 4.0

    # the scaling-only point of the first-order bound: s = 0, θ clipped to keep every offset feasible
    worst = xp.maximum(-xp.min(z, axis=-1), 0.0)
    theta_scaled = xp.clip(theta_free, 0.0, xp.where(worst > 0, beta / xp.maximum(worst, tiny), xp.inf))
    best = xp.maximum(-theta_scaled * a - theta_scaled**2 * b, value(xp.zeros_like(a)))
    best = xp.maximum(best, value(xp.minimum(cap, 1.0)))  # the gradients' own point, lifted: exact at an optimum

    def step(_, bracket):  # golden-section search of the concave value(θ) on [lo, hi]
        lo, hi = bracket
        left, right = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
        keep_left = value(left) > value(right)
        return xp.where(keep_left, lo, left), xp.where(keep_left, right, hi)

    bracket = _repeat(xp, steps, step, (xp.zeros_like(a), xp.minimum(cap, 2.0 * xp.maximum(theta_free, 1.0))))
    return xp.maximum(best, value((bracket[0] + bracket[1]) / 2.0))


def _repeat(xp, steps, body, carry):
    """``body(i, carry)`` ``steps`` times: a Python loop for numpy, one traced ``fori_loop`` step for JAX (not
    ``steps`` unrolled copies: compile time)."""
    if xp is np:
        for i in range(steps):
            carry = body(i, carry)
        return carry
    import jax

    return jax.lax.fori_loop(0, steps, body, carry)


#: the KKT bound's multipliers: offsets at most each of these shares of a pixel's peak count as held at 0 (any choice
#: is a valid bound, and the smallest is kept: a solver leaves ~1e-6 of the peak where the optimum is 0, and
#: which offsets count as held decides the bound, by orders of magnitude where one is missed)
KKT_HELD = (0.0, 1e-6, 1e-4, 1e-2)


def kkt_gap(xp, t, gradient, quadratic, primal, applies, shares=KKT_HELD, *, inverse=None, step=0.0, steps=0):
    """A second certified bound, from the Lagrangian dual of min f(T) s.t. T ≥ 0 through a quadratic q ≤ f that
    touches f at T: f's squared residuals of the observed, unclipped frames, α‖DT‖² and β1ᵀT as they are, and each
    other frame's convex term (a clipped frame's max(0, y − A_iT)², or nothing for a masked one) replaced by its
    tangent at T. Then q has Hessian 2G_p = 2(A_EᵀA_E + αDᵀD) over the kept frames E, q(T) = f(T), ∇q(T) = ∇f(T),
    and where 2G_p is positive definite, for any multiplier λ ≥ 0, g(λ) = min_T' q(T') − λᵀT' ≤ q(T*) ≤ f* (T* ≥ 0
    the optimum), and with δ = ∇f(T) − λ

        f(T) − g(λ) = λᵀT + ½ δᵀ(2G_p)⁻¹δ

    (q − λᵀT' is quadratic with Hessian 2G_p, minimised at T − (2G_p)⁻¹δ). With λ = max(∇f(T), 0) on the offsets
    held at 0 (at most a share of the peak, for each of ``shares``; the smallest bound over them) and 0 elsewhere,
    both terms vanish at the optimum and the bound is second order in T's KKT residual (the first-order bound of
    :func:`certified_gap` is first order in it). No cancellation: both terms are non-negative. ``quadratic`` maps
    (P, K) rows δ to each pixel's δᵀ(2G_p)⁻¹δ (P,) (the shared (2G)⁻¹ where every frame is kept;
    :func:`kept_hessian` otherwise); ``applies`` (P,) says where 2G_p is positive definite; elsewhere the bound is
    1 (no information).

    Every λ ≥ 0 gives a bound, and the best is the dual optimum (then the bound is the true gap), so with ``steps``
    > 0 the best share's λ climbs g(λ) (concave, ∇g(λ) = (2G)⁻¹δ − T, Lipschitz 1/λ_min(2G)) by projected
    accelerated gradient steps (FISTA with step ``step`` = λ_min(2G), ``inverse`` applying the shared (2G)⁻¹ to
    rows, so for pixels whose 2G_p is 2G): one product a step, the bound taken at each projected point and the
    smallest kept. The steps matter where ADMM's T leaves δ in 2G's weak directions, which (2G)⁻¹ amplifies and
    the fixed shares cannot remove. Relative to ``primal`` = f(T)."""
    if steps:  # the shares' products give the start's (2G)⁻¹δ as well: every step then adds a new point
        gap, best, solved = _kkt_shares(xp, t, gradient, quadratic, shares, inverse=inverse)
        gap = _dual_ascent(xp, t, gradient, inverse, best, gap, step, steps, solved=solved)
    else:
        gap, _, _ = _kkt_shares(xp, t, gradient, quadratic, shares)
    return _relative(xp, gap, primal, applies)


def _kkt_shares(xp, t, gradient, quadratic, shares, inverse=None):
    """The smallest λᵀT + ½δᵀ(2G_p)⁻¹δ over the shares' multipliers (see :func:`kkt_gap`), those multipliers, and
    (with ``inverse``, which then replaces ``quadratic``) their (2G_p)⁻¹δ, else None."""
    peak = xp.max(t, axis=-1, keepdims=True)
    gap = best = best_solved = None
    for share in shares:
        lam = xp.where(t <= share * peak, xp.maximum(gradient, 0.0), 0.0)
        delta = gradient - lam
        if inverse is None:
            candidate, solved = xp.sum(lam * t, axis=-1) + 0.5 * quadratic(delta), None
        else:
            solved = inverse(delta)
            candidate = xp.sum(lam * t, axis=-1) + 0.5 * xp.sum(delta * solved, axis=-1)
        if gap is None:
            gap, best, best_solved = candidate, lam, solved
        else:
            better = (candidate < gap)[:, None]
            best = xp.where(better, lam, best)
            best_solved = None if solved is None else xp.where(better, solved, best_solved)
            gap = xp.minimum(gap, candidate)
    return gap, best, best_solved


def _relative(xp, gap, primal, applies):
    """The bound relative to f(T) = ``primal``, in [0, 1]; 1 where it does not apply. Divided by f(T) itself wherever
    it is positive, subnormal too (a floor on the divisor would shrink the bound below the truth there)."""
    relative = xp.where(primal > 0, xp.minimum(xp.maximum(gap, 0.0) / xp.where(primal > 0, primal, 1.0), 1.0), 0.0)
    return xp.where(applies, relative, 1.0)


def _dual_ascent(xp, t, gradient, inverse, lam, gap, step, steps, solved=None):
    """``steps`` FISTA steps on g(λ) over λ ≥ 0 from ``lam`` (whose (2G)⁻¹(∇f − λ) is ``solved``, computed here
    where None; see :func:`kkt_gap`); the smallest λᵀT + ½δᵀ(2G)⁻¹δ over ``gap`` and the ``steps`` projected
    points, one product each (the gradient at a point is its (2G)⁻¹δ − T, so its bound comes free)."""
    if solved is None:
        solved = inverse(gradient - lam)

    def body(_, carry):
        point, solved, previous, momentum, gap = carry
        new = xp.maximum(point + step * (solved - t), 0.0)
        following = (1.0 + (1.0 + 4.0 * momentum**2) ** 0.5) / 2.0
        point = xp.maximum(new + (momentum - 1.0) / following * (new - previous), 0.0)
        delta = gradient - point
        solved = inverse(delta)
        gap = xp.minimum(gap, xp.sum(point * t, axis=-1) + 0.5 * xp.sum(delta * solved, axis=-1))
        return point, solved, new, following, gap

    return _repeat(xp, steps, body, (lam, solved, lam, xp.ones((), t.dtype), gap))[4]


#: the least margin below which a pixel's Woodbury core M = I − 2A_R(2G)⁻¹A_Rᵀ (eigenvalues in (0, 1] where its
#: reduced Hessian is positive definite) does not count as positive definite: :func:`kept_hessian` factorises
#: M − floor·I, whose inverse is above M⁻¹ (a looser bound, never a wrong one), and gives up where that fails. The
#: floor used is the larger of this and 1000 ε · tr(2G)/λ_min(2G) (an upper bound on cond(2G) times the float64 ε):
#: M's entries, at most ~1, carry the error of (2G)⁻¹, about ε · cond(2G), which the floor must cover
WOODBURY_FLOOR = 1e-9


@dataclass(frozen=True)
class KeptHessian:
    """Each pixel's 2G_p over its kept frames, as :func:`kkt_gap` uses it (built by :func:`kept_hessian`): the shared
    H = (2G)⁻¹ and A, and per group of pixels with the same number of left-out frames (their rows, those frames'
    indices, L⁻¹ of their Woodbury cores)."""

    inverse_matrix: np.ndarray  # H = (2G)⁻¹, (K, K)
    illumination: np.ndarray  # A, (N, K)
    lifting: np.ndarray  # A H, (N, K): a left-out frame's correction back on the offsets
    groups: tuple  # ((rows (m,), left-out frames (m, r), L⁻¹ (m, r, r)), ...)
    step: np.ndarray  # (P, 1): a lower bound on λ_min(2G_p), the dual ascent's step
    applies: np.ndarray  # (P,) bool: 2G_p positive definite (2G, and M − floor·I)

    def _whitened(self, hd):
        """Per group: (rows, left-out frames, L⁻¹, L⁻¹v_R) with v = A H δ, given the rows H δ."""
        v = hd @ self.illumination.T
        for rows, index, whitening in self.groups:
            yield rows, index, whitening, np.einsum("pij,pj->pi", whitening, np.take_along_axis(v[rows], index, 1))

    def quadratic(self, delta):
        """(P, K) rows δ ↦ (P,) δᵀ(2G_p)⁻¹δ = δᵀHδ + 2‖L⁻¹v_R‖²."""
        hd = delta @ self.inverse_matrix
        value = np.sum(delta * hd, axis=-1)
        for rows, _, _, w in self._whitened(hd):
            value[rows] += 2.0 * np.sum(w**2, axis=-1)
        return value

    def inverse(self, delta):
        """(P, K) rows δ ↦ (P, K) (2G_p)⁻¹δ = Hδ + 2 (M⁻¹v_R lifted to the frames) A H."""
        hd = delta @ self.inverse_matrix
        if not self.groups:
            return hd
        lifted = np.zeros((hd.shape[0], self.illumination.shape[0]))
        for rows, index, whitening, w in self._whitened(hd):
            part = np.zeros((rows.size, lifted.shape[1]))
            np.put_along_axis(part, index, np.einsum("pji,pj->pi", whitening, w), axis=1)  # M⁻¹v_R = L⁻ᵀL⁻¹v_R
            lifted[rows] = part
        return hd + 2.0 * lifted @ self.lifting

    def rows(self, rows: np.ndarray) -> KeptHessian:
        """The same pixels' Hessians for the (sorted, distinct) ``rows`` only, renumbered 0…: no factorisation
        again."""
        position = np.full(self.applies.shape[0], -1)
        position[rows] = np.arange(rows.size)
        groups = []
        for members, index, whitening in self.groups:
            inside = position[members] >= 0
            if inside.any():
                groups.append((position[members[inside]], index[inside], whitening[inside]))
        return KeptHessian(self.inverse_matrix, self.illumination, self.lifting, tuple(groups), self.step[rows],
                           self.applies[rows])


def kept_hessian(problem: DemuxProblem, kept: np.ndarray) -> KeptHessian:
    """Each pixel's 2G_p = 2(A_EᵀA_E + αDᵀD) over its kept frames E (``kept`` (P, N) bool), from the shared
    H = (2G)⁻¹ by Woodbury: with R the frames left out, 2G_p = 2G − 2A_RᵀA_R and

        (2G_p)⁻¹ = H + 2 H A_Rᵀ M⁻¹ A_R H,   M = I − 2 A_R H A_Rᵀ  (|R| × |R|),   so
        δᵀ(2G_p)⁻¹δ = δᵀHδ + 2 ‖L⁻¹v‖²,   v = A_R H δ,  LLᵀ = M (− :data:`WOODBURY_FLOOR` · I),

    so a pixel pays a Cholesky factor of its |R| × |R| core (C = A H Aᵀ's submatrix on R, C shared), not a K × K
    factorisation, and 2G_p is positive definite exactly where M is (Schur complement): ``applies`` where the factor
    of M − floor·I exists (:data:`WOODBURY_FLOOR`). Its smallest eigenvalue is at least λ_min(2G) · min(1, λ_min(M))
    (2G_p = (2G)^½ (I − 2H^½A_RᵀA_RH^½) (2G)^½, whose middle factor has M's eigenvalues and ones), with λ_min(M)
    taken as that of M − floor·I (a batched eigvalsh of the |R| × |R| cores): the dual ascent's safe step. (It
    replaced λ_min(M) ≥ 1/‖L⁻¹‖_F², 0.33–0.94 of it on the certificate tests' pixels, with which 10 steps left the
    catalogue's NaN case at a median bound of 1.00e-4 where they now reach 9.2e-5, at no measurable cost.)
    Float64, host (pixels grouped by |R|, one batched factorisation a group, pixel by pixel only where one of a
    group's fails). Dense problems only."""
    kept = np.asarray(kept, bool)
    h, a = problem.inverse, problem.illumination
    removed = ~kept
    counts = removed.sum(axis=1)
    usable = bool(problem.definite) and problem.dual_step > 0  # dual_step: λ_min(2G), set by DemuxProblem.build
    applies = np.full(kept.shape[0], usable)
    step = np.full((kept.shape[0], 1), problem.dual_step)
    groups = []
    if usable:
        core = a @ h @ a.T
        floor = max(WOODBURY_FLOOR, 1e3 * np.finfo(float).eps * np.trace(problem.gram2) / problem.dual_step)
        for r in np.unique(counts[counts > 0]):
            rows = np.flatnonzero(counts == r)
            index = np.nonzero(removed[rows])[1].reshape(rows.size, r)  # each row's left-out frames, in order
            shifted = (1.0 - floor) * np.eye(r) - 2.0 * core[index[:, :, None], index[:, None, :]]
            try:
                factor = np.linalg.cholesky(shifted)
            except np.linalg.LinAlgError:  # some pixel's M − floor·I is not positive definite: each on its own
                factor = np.empty_like(shifted)
                for i, matrix in enumerate(shifted):
                    try:
                        factor[i] = np.linalg.cholesky(matrix)
                    except np.linalg.LinAlgError:
                        applies[rows[i]], factor[i] = False, np.eye(r)
            whitening = np.linalg.inv(factor)
            step[rows, 0] *= np.clip(np.linalg.eigvalsh(shifted)[:, 0], 0.0, 1.0)  # λ_min(M − floor I) ≤ λ_min(M)
            groups.append((rows, index, whitening))
    return KeptHessian(h, a, a @ h, tuple(groups), step, applies)


def kkt_bound(problem: DemuxProblem, transport: np.ndarray, data: np.ndarray, weight: np.ndarray | None = None,
              clipped: np.ndarray | None = None, *, dual_steps: int = DUAL_STEPS, above: float = 0.0) -> np.ndarray:
    """:func:`kkt_gap` of each pixel of a dense problem in float64, each with the Hessian of its observed unclipped
    frames (:func:`kept_hessian`) and ``dual_steps`` of its dual ascent for the pixels whose bound without it
    exceeds ``above`` (the others need no better one); 1 where it does not apply (2G or a pixel's 2G_p not positive
    definite). Arguments as for :func:`certified_gap`."""
    t = np.asarray(transport, np.float64)
    if weight is not None:
        weight = (np.asarray(weight) > 0).astype(np.float64)
    residual, _ = _residual(problem, t, data, weight, clipped)
    gradient = 2.0 * problem.adjoint(residual) + 2.0 * problem.alpha * problem.smooth_gradient(t) + problem.beta
    primal = (residual**2).sum(-1) + problem.alpha * problem.smoothness(t) + problem.beta * t.sum(-1)
    # the frames the objective counts (weight None: all of them, non-finite data as 0 like _residual; the solver
    # always passes its weight, which masks them) less the clipped ones
    kept = np.ones(np.shape(data), bool) if weight is None else weight > 0
    if clipped is not None:
        kept &= ~np.asarray(clipped, bool)

    hessian = kept_hessian(problem, kept)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        gap, lam, _ = _kkt_shares(np, t, gradient, hessian.quadratic, KKT_HELD)
        relative = _relative(np, gap, primal, hessian.applies)
        rows = np.flatnonzero((relative > above) & hessian.applies) if dual_steps else np.zeros(0, int)
        if rows.size:  # the ascent with these pixels' own factors
            part = hessian.rows(rows)
            ascended = _dual_ascent(np, t[rows], gradient[rows], part.inverse, lam[rows], gap[rows], part.step,
                                    dual_steps)
            relative[rows] = _relative(np, ascended, primal[rows], part.applies)
    return np.where(np.isfinite(relative), relative, 1.0)


def first_order_gap(xp, ops, t, residual, target, beta, e=None, *, steps=DUAL_SEARCH_STEPS):
    """The first-order bound of :func:`certified_gap` relative to f(T), in [0, 1], with ∇f(T) − β (z, (P, K)) and f(T)
    (P,): the one computation the float64 reference and the solver's kernels
    (:mod:`selpath.stages.procam._demux_kernels`, scaled data in the solver's dtype) share.

    ``ops`` gives ``adjoint``, ``smooth_gradient``, ``smoothness`` and ``alpha`` (a problem in numpy, its operators in
    JAX, with ``xp`` the array module); ``residual`` is w(AT − ỹ) and ``target`` ỹ (P, N); ``beta`` (P,) or a scalar;
    ``e`` the observed unclipped frames (1, else 0) of the dual's shift; None: every frame of every pixel, whose Aᵀe
    is then one row for all pixels."""
    u = 2.0 * residual
    z = ops.adjoint(u) + 2.0 * ops.alpha * ops.smooth_gradient(t)
    a = xp.sum(u * target, axis=-1)
    b = xp.sum(residual * residual, axis=-1) + ops.alpha * ops.smoothness(t)
    if e is None:
        shift = (ops.adjoint(xp.ones((1, u.shape[-1]), u.dtype)), xp.sum(target, axis=-1), xp.sum(u, axis=-1),
                 xp.full(a.shape, u.shape[-1], u.dtype))
    else:
        shift = ops.adjoint(e), xp.sum(e * target, axis=-1), xp.sum(e * u, axis=-1), xp.sum(e, axis=-1)
    dual = best_dual_value(xp, a, b, z, *shift, beta, steps=steps)
    primal = b + beta * xp.sum(t, axis=-1)
    return _relative(xp, primal - dual, primal, True), z, primal


def certified_gap(problem: DemuxProblem | SeparableDemuxProblem, transport: np.ndarray, data: np.ndarray,
                  weight: np.ndarray | None = None, clipped: np.ndarray | None = None, *,
                  search_steps: int = DUAL_SEARCH_STEPS, dual_steps: int = DUAL_STEPS) -> np.ndarray:
    """A certified bound on each pixel's relative objective gap (f(T) − f*)/f(T), from weak duality, in float64.

    f(T) = g(AT) + h(DT) + β1ᵀT with T ≥ 0, g(r) = Σ w(r − y)², h(s) = α‖s‖². Its Fenchel dual is
    D(u, v) = −Σ (u y + u²/4) − ‖v‖²/(4α) subject to Aᵀu + Dᵀv ≥ −β (u = 0 on masked frames), and every
    feasible (u, v) gives D ≤ f* (weak duality). The dual points tried are those T's own gradients give,
    u = 2w(AT − y), v = 2αDT (at the optimum they are the dual optimum), scaled by θ ≥ 0 and shifted by s
    on every observed unclipped frame (u + s·e: Aᵀe ≥ 0 since the illumination is non-negative, so the shift
    lifts every offset's constraint where scaling alone must shrink the whole point): (θ, s) maximises D subject
    to feasibility (:func:`best_dual_value`: a closed form in s, a golden-section search in θ, never below the
    scaling-only point θ = min(θ_free, β / max(0, −min(Aᵀu + Dᵀv))), s = 0). Then f(T) − f* ≤ f(T) − D: a bound,
    not an estimate. Scale-invariant (both sides scale with the data squared), and with the shift it stays
    useful where β is negligible against the data (at 1e8 scale with β not rescaled the scaling-only point
    gave 1 everywhere); 0 where f(T) = 0 (an all-zero pixel at T = 0 is certified at once). Its tightness is
    T's own KKT accuracy: where an offset held at 0 has a negative gradient δ, the bound is about δ·ΣT / f(T)
    (first order in δ while the true gap is second order: an ADMM answer with true gap 1e-5 reads ~5e-3).

    A clipped frame's term max(0, y − r)² has the conjugate u y + u²/4 for u ≤ 0 (+∞ above): the same with the
    constraint u ≤ 0, which its gradient u = 2 min(0, AT − y), every θ ≥ 0 and a shift on unclipped frames keep.

    For a dense problem whose 2G is positive definite, the smaller of this bound and :func:`kkt_gap`'s (second
    order in the KKT residual; with ``dual_steps`` of its dual ascent) is returned: both are bounds. A pixel with
    masked or clipped frames takes the latter with its own Hessian over its observed unclipped frames
    (:func:`kept_hessian`), where that is positive definite.
    """
    t = np.asarray(transport, np.float64)
    if weight is not None:  # a frame is observed or not (the solver's rule): a fractional weight is not this QP's
        weight = (np.asarray(weight) > 0).astype(np.float64)
    residual, target = _residual(problem, t, data, weight, clipped)
    e = np.ones_like(target) if weight is None else weight
    if clipped is not None:
        e = e * ~np.asarray(clipped, bool)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        relative, _, _ = first_order_gap(np, problem, t, residual, target, problem.beta, e, steps=search_steps)
    if problem.second_order_bound:
        relative = np.minimum(relative, kkt_bound(problem, t, data, weight, clipped, dual_steps=dual_steps))
    return np.where(np.isfinite(relative), relative, 1.0)
