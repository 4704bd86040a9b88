"""The shared part of every pixel's demultiplexing problem (§5.2.2, §5.3.1): the illumination, the
regularisation and the factorised ADMM T-update, built once per sweep in float64 (:mod:`stages.procam._demux_solver`
solves with them).

Plane-to-ray transport (:class:`DemuxProblem`) has one dense (N frames × K offsets) illumination A, so
2G = 2(AᵀA + αDᵀD), (2G + ρI)⁻¹ and (2G)⁺ are K × K matrices.

The full transport (§5.3.1) has the same problem over (du, dv) cells with A = L_u ⊗ L: the frames form a
full (line × delay–exposure) grid and the illumination of Eq. 38 is separable. :class:`SeparableDemuxProblem`
never forms A or G: with L_uᵀL_u = QΛQᵀ, 2G + ρI = (Q ⊗ I)·blockdiag_i(2λ_i LᵀL + 2αDᵀD + ρI)·(Q ⊗ I)ᵀ,
so the T-update is two (K_u × K_u) products and K_u small (K_v × K_v) ones per pixel — for the thesis's
sweep (47 × 21 cells) 9× fewer operations than the dense (987 × 987) inverse, and ~100 kB instead of 4 MB
of shared matrices. The smoothness α acts along dv only (the thesis's ∂T/∂v); du is left to β and T ≥ 0.

Each problem hands the solver its operators by name (:meth:`DemuxProblem.operators`): a small pytree
(:class:`DenseOperators`, :class:`KroneckerOperators`) of JAX arrays in the solver's dtype with ``forward``,
``adjoint``, ``update``, ``inverse``, ``gram2`` and ``smoothness`` on flat (P, K) iterates, so the jitted
kernels of :mod:`stages.procam._demux_kernels` dispatch on its type, never on a string.

Defaults live here once (:data:`DEFAULT_ALPHA`, :data:`DEFAULT_BETA`, :data:`DEFAULT_RHO_FACTOR`); the stages
take theirs from them. α (smoothness along the offset) and β (sparsity) are not tomography's TV weight λ;
``rho_factor`` (ρ relative to λ_max(2G)) is not tomography's ``rho`` (relative to ‖MR‖²). ρ belongs to the
problem because the T-update's inverse (2G + ρI)⁻¹, built once per sweep, depends on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from stages.procam._illumination import difference_operator

#: smoothness weight α of the thesis (§5.2.2), on images scaled to [0, 1]
DEFAULT_ALPHA = 0.01
#: sparsity weight β of the thesis (§5.2.2), on images scaled to [0, 1]
DEFAULT_BETA = 0.01
#: ADMM penalty ρ = rho_factor · λ_max(2G): 0.01 was the best of 0.003–0.3 on a Fig. 38-like sweep
DEFAULT_RHO_FACTOR = 0.01


@dataclass(frozen=True)
class DemuxProblem:
    """The shared part of every pixel's problem: A, the regularisation, and the factorised T-update."""

    illumination: np.ndarray  # A, (N, K)
    alpha: float
    beta: float
    rho: float
    gram2: np.ndarray  # 2G = 2(AᵀA + αDᵀD), (K, K)
    update: np.ndarray  # (2G + ρI)⁻¹, (K, K)
    inverse: np.ndarray  # (2G)⁺, (K, K): the warm start's unconstrained solve
    #: 2G is positive definite (its smallest eigenvalue above 1e-12 of its largest): then (2G)⁺ = (2G)⁻¹ and the
    #: KKT bound of :func:`kkt_gap` holds
    definite: bool = False

    @classmethod
    def build(cls, illumination: np.ndarray, *, alpha: float = DEFAULT_ALPHA, beta: float = DEFAULT_BETA,
              rho_factor: float = DEFAULT_RHO_FACTOR) -> DemuxProblem:
        illumination = np.asarray(illumination, dtype=np.float64)
        if illumination.ndim != 2 or not np.all(np.isfinite(illumination)):
            raise ValueError("the illumination matrix must be a finite (frames, offsets) array")
        if alpha < 0 or beta < 0 or rho_factor <= 0:
            raise ValueError(f"need alpha ≥ 0, beta ≥ 0, rho_factor > 0 (got {alpha}, {beta}, {rho_factor})")
        k = illumination.shape[1]
        d = difference_operator(k)
        gram2 = 2.0 * (illumination.T @ illumination + alpha * d.T @ d)
        eigenvalues = np.linalg.eigvalsh(gram2) if k else np.ones(1)
        top = float(eigenvalues[-1])
        rho = rho_factor * max(top, np.finfo(float).tiny)
        update = np.linalg.inv(gram2 + rho * np.eye(k))
        definite = bool(k) and float(eigenvalues[0]) > 1e-12 * top
        return cls(illumination, float(alpha), float(beta), float(rho), gram2, update, np.linalg.pinv(gram2),
                   definite)

    @property
    def frames(self) -> int:
        return self.illumination.shape[0]

    @property
    def offsets(self) -> int:
        return self.illumination.shape[1]

    def operators(self, dtype) -> DenseOperators:
        """The operators the solver's kernels apply, as JAX arrays of ``dtype``."""
        cast = _caster(dtype)
        return DenseOperators(*map(cast, (self.illumination, self.gram2, self.update, self.inverse, self.alpha,
                                          self.beta, self.rho, float(self.definite))))

    def forward(self, transport: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(P, K) transport → (P, N) predicted observations, in ``dtype`` (the reference's float64 by default)."""
        return np.asarray(transport, dtype) @ self.illumination.T.astype(dtype)

    def lit_by(self, frames: np.ndarray) -> np.ndarray:
        """(P, N) 0/1 frames → (P, K): how many of them light each offset (A_ik > 0)."""
        return np.asarray(frames, np.float32) @ (self.illumination > 0).astype(np.float32)

    def objective(self, transport: np.ndarray, data: np.ndarray, weight: np.ndarray | None = None,
                  clipped: np.ndarray | None = None) -> np.ndarray:
        """The thesis's objective per pixel, in float64 (reference for tests and benchmarks); ``clipped`` frames
        (``data`` their clip level) enter as the one-sided max(0, y − AT)²."""
        return _objective(self, transport, data, weight, clipped)


@dataclass(frozen=True)
class SeparableDemuxProblem:
    """The full transport's shared part: A = L_u ⊗ L over (K_u, K_v) cells, u-major (index k_u·K_v + k_v).

    Data per pixel are ordered line-major: observation j_u·N_v + j_v is line j_u at delay–exposure j_v.
    """

    line_matrix: np.ndarray  # L_u, (N_u lines, K_u cells)
    frame_matrix: np.ndarray  # L, (N_v delay–exposure frames, K_v offsets)
    alpha: float
    beta: float
    rho: float
    basis: np.ndarray  # Q, (K_u, K_u): eigenvectors of L_uᵀL_u
    update_blocks: np.ndarray  # (K_u, K_v, K_v): (2λ_i LᵀL + 2αDᵀD + ρI)⁻¹
    inverse_blocks: np.ndarray  # (K_u, K_v, K_v): (2λ_i LᵀL + 2αDᵀD)⁺
    smooth: np.ndarray  # DᵀD, (K_v, K_v)

    @classmethod
    def build(cls, line_matrix: np.ndarray, frame_matrix: np.ndarray, *, alpha: float = DEFAULT_ALPHA,
              beta: float = DEFAULT_BETA, rho_factor: float = DEFAULT_RHO_FACTOR) -> SeparableDemuxProblem:
        line_matrix = np.asarray(line_matrix, dtype=np.float64)
        frame_matrix = np.asarray(frame_matrix, dtype=np.float64)
        for name, m in (("line", line_matrix), ("frame", frame_matrix)):
            if m.ndim != 2 or not np.all(np.isfinite(m)):
                raise ValueError(f"the {name} illumination matrix must be a finite 2-D array")
        if alpha < 0 or beta < 0 or rho_factor <= 0:
            raise ValueError(f"need alpha ≥ 0, beta ≥ 0, rho_factor > 0 (got {alpha}, {beta}, {rho_factor})")
        k_v = frame_matrix.shape[1]
        d = difference_operator(k_v)
        smooth = d.T @ d
        lam, basis = np.linalg.eigh(line_matrix.T @ line_matrix)
        lam = np.clip(lam, 0.0, None)
        blocks = 2.0 * (lam[:, None, None] * (frame_matrix.T @ frame_matrix)[None] + alpha * smooth[None])
        top = max(float(np.linalg.eigvalsh(blocks)[:, -1].max()) if blocks.size else 1.0, np.finfo(float).tiny)
        rho = rho_factor * top
        update = np.linalg.inv(blocks + rho * np.eye(k_v)[None])
        inverse = np.linalg.pinv(blocks, hermitian=True)
        return cls(line_matrix, frame_matrix, float(alpha), float(beta), float(rho), basis, update, inverse, smooth)

    @property
    def frames(self) -> int:
        return self.line_matrix.shape[0] * self.frame_matrix.shape[0]

    @property
    def offsets(self) -> int:
        return self.line_matrix.shape[1] * self.frame_matrix.shape[1]

    @property
    def cells(self) -> tuple[int, int]:
        return self.line_matrix.shape[1], self.frame_matrix.shape[1]

    def operators(self, dtype) -> KroneckerOperators:
        """The operators the solver's kernels apply, as JAX arrays of ``dtype``."""
        cast = _caster(dtype)
        return KroneckerOperators(*map(cast, (self.line_matrix, self.frame_matrix, self.basis, self.update_blocks,
                                              self.inverse_blocks, self.smooth, self.alpha, self.beta, self.rho)))

    def forward(self, transport: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(P, K_u·K_v) transport → (P, N_u·N_v) predicted observations, in ``dtype`` (float64 by default)."""
        t = np.asarray(transport, dtype).reshape(-1, *self.cells)
        out = np.einsum("ju,puv,nv->pjn", self.line_matrix.astype(dtype), t, self.frame_matrix.astype(dtype),
                        optimize=True)
        return out.reshape(t.shape[0], -1)

    def lit_by(self, frames: np.ndarray) -> np.ndarray:
        """(P, N_u·N_v) 0/1 frames (line-major) → (P, K_u·K_v): how many of them light each cell."""
        frames = np.asarray(frames, np.float32).reshape(-1, self.line_matrix.shape[0], self.frame_matrix.shape[0])
        lines, rows = (self.line_matrix > 0).astype(np.float32), (self.frame_matrix > 0).astype(np.float32)
        return np.einsum("ju,pjn,nv->puv", lines, frames, rows, optimize=True).reshape(frames.shape[0], -1)

    def objective(self, transport: np.ndarray, data: np.ndarray, weight: np.ndarray | None = None,
                  clipped: np.ndarray | None = None) -> np.ndarray:
        """The thesis's objective per pixel (smoothness along dv), in float64; ``clipped`` as for
        :meth:`DemuxProblem.objective`."""
        return _objective(self, transport, data, weight, clipped)


def _residual(problem: DemuxProblem | SeparableDemuxProblem, transport: np.ndarray, data: np.ndarray,
              weight: np.ndarray | None, clipped: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(w(AT − ỹ), ỹ) in float64: ỹ = y, and max(y, AT) on clipped frames (the one-sided penalty)."""
    y = np.nan_to_num(np.asarray(data, np.float64))
    prediction = problem.forward(transport)
    target = y if clipped is None else np.where(clipped, np.maximum(y, prediction), y)
    w = np.ones_like(y) if weight is None else np.asarray(weight, np.float64)
    return (prediction - target) * w, target


def _smoothness(problem: DemuxProblem | SeparableDemuxProblem, transport: np.ndarray) -> np.ndarray:
    """‖D T‖² per pixel (along dv for the full transport)."""
    if isinstance(problem, SeparableDemuxProblem):
        return (np.diff(transport.reshape(-1, *problem.cells), axis=-1) ** 2).sum((-2, -1))
    return (np.diff(transport, axis=-1) ** 2).sum(-1)


def _objective(problem, transport, data, weight, clipped) -> np.ndarray:
    transport = np.asarray(transport, np.float64)
    residual, _ = _residual(problem, transport, data, weight, clipped)
    return (residual**2).sum(-1) + problem.alpha * _smoothness(problem, transport) + problem.beta * transport.sum(-1)


def _dtd_np(t: np.ndarray) -> np.ndarray:
    """DᵀD along the last axis, in numpy."""
    d = np.diff(t, axis=-1)
    return -np.diff(np.pad(d, [(0, 0)] * (d.ndim - 1) + [(1, 1)]), axis=-1)


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

    bracket = (xp.zeros_like(a), xp.minimum(cap, 2.0 * xp.maximum(theta_free, 1.0)))
    if xp is np:
        for i in range(steps):
            bracket = step(i, bracket)
    else:  # one traced step, not `steps` unrolled copies (compile time)
        import jax

        bracket = jax.lax.fori_loop(0, steps, step, bracket)
    return xp.maximum(best, value((bracket[0] + bracket[1]) / 2.0))


#: the KKT bound's multipliers: offsets at most each of these shares of a pixel's peak count as held at 0 (any choice
#: is a valid bound, and the smallest is kept: a solver leaves ~1e-6 of the peak where the optimum is 0, and
#: which offsets count as held decides the bound, by orders of magnitude where one is missed)
KKT_HELD = (0.0, 1e-6, 1e-4, 1e-2)


def kkt_gap(xp, t, gradient, inverse, primal, applies, shares=KKT_HELD):
    """A second certified bound, from the Lagrangian dual of min f(T) s.t. T ≥ 0 when every frame of the pixel
    is an observed, unclipped one, so that f is the quadratic TᵀGT − 2yᵀAT + βᵀT + ‖y‖² with 2G = 2(AᵀA + αDᵀD)
    positive definite: for any multiplier λ ≥ 0, g(λ) = min_T f(T) − λᵀT ≤ f*, and with δ = ∇f(T) − λ,

        f(T) − g(λ) = λᵀT + ½ δᵀ(2G)⁻¹δ

    (f − λᵀT is quadratic with Hessian 2G, minimised at T − (2G)⁻¹δ). With λ = max(∇f(T), 0) on the offsets held
    at 0 (at most a share of the peak, for each of ``shares``; the smallest bound over them) and 0 elsewhere, both
    terms vanish at the optimum and the bound is
    second order in T's KKT residual (the first-order bound of :func:`certified_gap` is first order in it). No
    cancellation: both terms are non-negative. ``inverse`` applies (2G)⁻¹ to (P, K) rows; ``applies`` (P,) says
    where the pixel's objective is that quadratic; elsewhere the bound is 1 (no information). Relative to
    ``primal`` = f(T)."""
    peak = xp.max(t, axis=-1, keepdims=True)
    gap = None
    for share in shares:
        lam = xp.where(t <= share * peak, xp.maximum(gradient, 0.0), 0.0)
        delta = gradient - lam
        candidate = xp.sum(lam * t, axis=-1) + 0.5 * xp.sum(delta * inverse(delta), axis=-1)
        gap = candidate if gap is None else xp.minimum(gap, candidate)
    tiny = xp.finfo(t.dtype).tiny
    relative = xp.where(primal > 0, xp.minimum(xp.maximum(gap, 0.0) / xp.maximum(primal, tiny), 1.0), 0.0)
    return xp.where(applies, relative, 1.0)


def certified_gap(problem: DemuxProblem | SeparableDemuxProblem, transport: np.ndarray, data: np.ndarray,
                  weight: np.ndarray | None = None, clipped: np.ndarray | None = None, *,
                  search_steps: int = DUAL_SEARCH_STEPS) -> np.ndarray:
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

    Where every frame of a pixel is observed and unclipped and 2G is positive definite, the smaller of this bound
    and :func:`kkt_gap`'s (second order in the KKT residual) is returned: both are bounds.
    """
    t = np.asarray(transport, np.float64)
    if weight is not None:  # a frame is observed or not (the solver's rule): a fractional weight is not this QP's
        weight = (np.asarray(weight) > 0).astype(np.float64)
    residual, target = _residual(problem, t, data, weight, clipped)
    w = np.ones_like(target) if weight is None else weight
    e = w if clipped is None else w * ~np.asarray(clipped, bool)
    u = 2.0 * residual
    if isinstance(problem, SeparableDemuxProblem):
        cells = t.reshape(-1, *problem.cells)
        n_u = problem.line_matrix.shape[0]

        def adjoint(r):
            return np.einsum("ju,pjn,nv->puv", problem.line_matrix, r.reshape(r.shape[0], n_u, -1),
                             problem.frame_matrix, optimize=True).reshape(t.shape)

        smooth_gradient = _dtd_np(cells).reshape(t.shape)
    else:
        def adjoint(r):
            return r @ problem.illumination

        smooth_gradient = _dtd_np(t)
    z = adjoint(u) + 2.0 * problem.alpha * smooth_gradient
    a = (u * target * w).sum(-1)
    b = (residual**2).sum(-1) + problem.alpha * _smoothness(problem, t)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        dual = best_dual_value(np, a, b, z, adjoint(e), (e * target).sum(-1), (e * u).sum(-1), e.sum(-1),
                               problem.beta, steps=search_steps)
        primal = b + problem.beta * t.sum(-1)
        gap = np.maximum(primal - dual, 0.0)
        relative = np.where(primal > 0, np.minimum(gap / primal, 1.0), 0.0)
        if isinstance(problem, DemuxProblem) and problem.definite:
            applies = np.all(e * np.isfinite(np.asarray(data, np.float64)) > 0, axis=-1)
            relative = np.minimum(relative, kkt_gap(np, t, z + problem.beta, lambda v: v @ problem.inverse,
                                                    primal, applies))
    return np.where(np.isfinite(relative), relative, 1.0)


def _sq(x):
    return jnp.sum(x * x, axis=-1)


class DenseOperators(NamedTuple):
    """:class:`DemuxProblem`'s operators on flat (P, K) iterates (a pytree of arrays in the solver's dtype)."""

    illumination: jnp.ndarray  # A, (N, K)
    gram2_matrix: jnp.ndarray  # 2G, (K, K)
    update_matrix: jnp.ndarray  # (2G + ρI)⁻¹
    inverse_matrix: jnp.ndarray  # (2G)⁺
    alpha: jnp.ndarray
    beta: jnp.ndarray
    rho: jnp.ndarray
    definite: jnp.ndarray  # 1 where 2G is positive definite (the KKT bound holds), else 0

    def forward(self, t):
        """A T per pixel: (P, K) → (P, N)."""
        return t @ self.illumination.T

    def adjoint(self, r):
        """Aᵀ r per pixel: (P, N) → (P, K)."""
        return r @ self.illumination

    def update(self, v):
        """(2G + ρI)⁻¹ v: the ADMM T-update."""
        return v @ self.update_matrix

    def inverse(self, v):
        """(2G)⁺ v: the unconstrained solve of the warm start."""
        return v @ self.inverse_matrix

    def gram2(self, v):
        """2G v."""
        return v @ self.gram2_matrix

    def smoothness(self, t):
        """‖D T‖² per pixel."""
        return _sq(jnp.diff(t, axis=-1))

    def smooth_gradient(self, t):
        """DᵀD T per pixel: ½ the gradient of ‖D T‖²."""
        return _dtd(t)


class KroneckerOperators(NamedTuple):
    """:class:`SeparableDemuxProblem`'s operators on flat (P, K_u·K_v) iterates, A = L_u ⊗ L never formed."""

    line: jnp.ndarray  # L_u, (N_u, K_u)
    frame: jnp.ndarray  # L, (N_v, K_v)
    basis: jnp.ndarray  # Q, (K_u, K_u)
    update_blocks: jnp.ndarray  # (K_u, K_v, K_v)
    inverse_blocks: jnp.ndarray  # (K_u, K_v, K_v)
    smooth: jnp.ndarray  # DᵀD, (K_v, K_v)
    alpha: jnp.ndarray
    beta: jnp.ndarray
    rho: jnp.ndarray

    def _cells(self, v):
        return v.reshape(v.shape[0], self.line.shape[1], self.frame.shape[1])

    def forward(self, t):
        return jnp.einsum("ju,pun->pjn", self.line, self._cells(t) @ self.frame.T).reshape(t.shape[0], -1)

    def adjoint(self, r):
        n_u = self.line.shape[0]
        return jnp.einsum("ju,pjv->puv", self.line, r.reshape(r.shape[0], n_u, -1) @ self.frame).reshape(
            r.shape[0], -1)

    def _blockwise(self, blocks, v):  # (Q ⊗ I) blockdiag (Q ⊗ I)ᵀ v
        y = jnp.einsum("ui,puv->piv", self.basis, self._cells(v))
        y = jnp.einsum("piv,ivw->piw", y, blocks)
        return jnp.einsum("ui,piw->puw", self.basis, y).reshape(v.shape[0], -1)

    def update(self, v):
        return self._blockwise(self.update_blocks, v)

    def inverse(self, v):
        return self._blockwise(self.inverse_blocks, v)

    def gram2(self, v):
        smooth = (self._cells(v) @ self.smooth).reshape(v.shape[0], -1)
        return 2.0 * (self.adjoint(self.forward(v)) + self.alpha * smooth)

    def smoothness(self, t):
        return jnp.sum(jnp.diff(self._cells(t), axis=-1) ** 2, axis=(-2, -1))

    def smooth_gradient(self, t):
        return _dtd(self._cells(t)).reshape(t.shape[0], -1)


def _dtd(t):
    """DᵀD along the last axis (D the first difference): −Δ(pad(D t)) — no matrix formed."""
    d = jnp.diff(t, axis=-1)
    pad = [(0, 0)] * (d.ndim - 1) + [(1, 1)]
    return -jnp.diff(jnp.pad(d, pad), axis=-1)


def _caster(dtype):
    dtype = jnp.dtype(dtype)
    return lambda a: jnp.asarray(a, dtype=dtype)
