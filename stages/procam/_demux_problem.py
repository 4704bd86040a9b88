"""The shared part of every pixel's demultiplexing problem (§5.2.2, §5.3.1): the illumination, the
regularisation and the factorised ADMM T-update, built once per sweep in float64
(:mod:`selpath.stages.procam._demux_solver`
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
kernels of :mod:`selpath.stages.procam._demux_kernels` call the same methods on either, never asking which it is.
Each problem also says what it supports: ``second_order_bound`` (the certificate's KKT bound) and ``exact_finish``
(the active-set finish and the ``max_gap`` cap), and its operators' ``SECOND_ORDER``; its float64 numpy
``forward``, ``adjoint``, ``smoothness`` and ``smooth_gradient`` serve the host certificate and the objective.

Defaults live once, in :mod:`selpath.stages.procam._demux_settings` (no JAX there; ``DEFAULT_ALPHA``,
``DEFAULT_BETA`` and ``DEFAULT_RHO_FACTOR`` are re-exported here); the stages take theirs from it. α (smoothness
along the offset) and β (sparsity) are not tomography's TV weight λ; ``rho_factor`` (ρ relative to λ_max(2G)) is not
tomography's ``rho`` (relative to ‖MR‖²). ρ belongs to the problem because the T-update's inverse (2G + ρI)⁻¹, built
once per sweep, depends on it.

Every product of the operators runs at :data:`PRECISION` (full float32 or float64). JAX's default precision for
float32 products is the hardware's fastest: TF32 on NVIDIA Ampere and Hopper GPUs (a 10-bit mantissa, relative
error ~5e-4 per product) and bfloat16 passes on TPUs. That is far coarser than the tolerances (``tol`` 2e-3 on
residuals, ``gap_tol`` 1e-4 and ``max_gap`` 1e-3 on the objective gap), and the certificate that decides
``converged`` is computed with the same products. On CPUs the setting changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selpath.stages.procam._demux_settings import DEFAULT_ALPHA, DEFAULT_BETA, DEFAULT_RHO_FACTOR
from selpath.stages.procam._illumination import smoothness_matrix


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
    #: KKT bound of :func:`selpath.stages.procam._demux_certificate.kkt_gap` holds
    definite: bool = False
    #: λ_min(2G) where 2G is positive definite (else 0): the step of the KKT bound's dual ascent, whose gradient
    #: (2G)⁻¹δ − T is 1/λ_min(2G)-Lipschitz in the multipliers
    dual_step: float = 0.0

    @classmethod
    def build(cls, illumination: np.ndarray, *, alpha: float = DEFAULT_ALPHA, beta: float = DEFAULT_BETA,
              rho_factor: float = DEFAULT_RHO_FACTOR) -> DemuxProblem:
        illumination = np.asarray(illumination, dtype=np.float64)
        if illumination.ndim != 2 or not np.all(np.isfinite(illumination)):
            raise ValueError("the illumination matrix must be a finite (frames, offsets) array")
        if alpha < 0 or beta < 0 or rho_factor <= 0:
            raise ValueError(f"need alpha ≥ 0, beta ≥ 0, rho_factor > 0 (got {alpha}, {beta}, {rho_factor})")
        k = illumination.shape[1]
        gram2 = 2.0 * (illumination.T @ illumination + alpha * smoothness_matrix(k))
        eigenvalues = np.linalg.eigvalsh(gram2) if k else np.ones(1)
        top = float(eigenvalues[-1])
        rho = rho_factor * max(top, np.finfo(float).tiny)
        update = np.linalg.inv(gram2 + rho * np.eye(k))
        definite = bool(k) and float(eigenvalues[0]) > 1e-12 * top
        return cls(illumination, float(alpha), float(beta), float(rho), gram2, update, np.linalg.pinv(gram2),
                   definite, float(eigenvalues[0]) if definite else 0.0)

    @property
    def second_order_bound(self) -> bool:
        """Whether the certificate's KKT bound (second order in T's KKT residual) holds: 2G positive definite."""
        return self.definite

    @property
    def exact_finish(self) -> bool:
        """Whether the exact active-set finish (:mod:`selpath.stages.procam._demux_finish`) and the ``max_gap`` cap
        apply: they need the second-order bound."""
        return self.definite

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
                                          self.beta, self.rho, float(self.definite),
                                          self.dual_step if self.definite else 0.0)))

    def forward(self, transport: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(P, K) transport → (P, N) predicted observations, in ``dtype`` (the reference's float64 by default)."""
        return np.asarray(transport, dtype) @ self.illumination.T.astype(dtype)

    def adjoint(self, residual: np.ndarray) -> np.ndarray:
        """(P, N) → (P, K): Aᵀ r per pixel, in float64."""
        return np.asarray(residual, np.float64) @ self.illumination

    def smoothness(self, transport: np.ndarray) -> np.ndarray:
        """‖D T‖² per pixel."""
        return (np.diff(transport, axis=-1) ** 2).sum(-1)

    def smooth_gradient(self, transport: np.ndarray) -> np.ndarray:
        """DᵀD T per pixel (½ the gradient of ‖D T‖²)."""
        return _dtd(np.asarray(transport, np.float64), np)

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
        smooth = smoothness_matrix(k_v)
        lam, basis = np.linalg.eigh(line_matrix.T @ line_matrix)
        lam = np.clip(lam, 0.0, None)
        blocks = 2.0 * (lam[:, None, None] * (frame_matrix.T @ frame_matrix)[None] + alpha * smooth[None])
        top = max(float(np.linalg.eigvalsh(blocks)[:, -1].max()) if blocks.size else 1.0, np.finfo(float).tiny)
        rho = rho_factor * top
        update = np.linalg.inv(blocks + rho * np.eye(k_v)[None])
        inverse = np.linalg.pinv(blocks, hermitian=True)
        return cls(line_matrix, frame_matrix, float(alpha), float(beta), float(rho), basis, update, inverse, smooth)

    #: the Kronecker problem keeps the certificate's first-order bound only: no KKT bound, no exact finish, no cap
    second_order_bound = False
    exact_finish = False

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

    def adjoint(self, residual: np.ndarray) -> np.ndarray:
        """(P, N_u·N_v) → (P, K_u·K_v): (L_u ⊗ L)ᵀ r per pixel, in float64, A never formed."""
        r = np.asarray(residual, np.float64)
        r = r.reshape(r.shape[0], self.line_matrix.shape[0], -1)
        return np.einsum("ju,pjn,nv->puv", self.line_matrix, r, self.frame_matrix, optimize=True).reshape(
            r.shape[0], -1)

    def smoothness(self, transport: np.ndarray) -> np.ndarray:
        """‖D T‖² per pixel, along dv."""
        return (np.diff(transport.reshape(-1, *self.cells), axis=-1) ** 2).sum((-2, -1))

    def smooth_gradient(self, transport: np.ndarray) -> np.ndarray:
        """DᵀD T per pixel along dv."""
        t = np.asarray(transport, np.float64)
        return _dtd(t.reshape(-1, *self.cells), np).reshape(t.shape)

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


def _objective(problem, transport, data, weight, clipped) -> np.ndarray:
    transport = np.asarray(transport, np.float64)
    residual, _ = _residual(problem, transport, data, weight, clipped)
    return (residual**2).sum(-1) + problem.alpha * problem.smoothness(transport) + problem.beta * transport.sum(-1)


def _sq(x):
    return jnp.sum(x * x, axis=-1)


#: precision of every matrix product of the operators: the input dtype's own, never TF32 or bfloat16 passes
PRECISION = jax.lax.Precision.HIGHEST


def _mm(a, b):
    return jnp.matmul(a, b, precision=PRECISION)


def _einsum(spec, a, b):
    return jnp.einsum(spec, a, b, precision=PRECISION)


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
    dual_step: jnp.ndarray  # λ_min(2G) where definite, else 0 (DemuxProblem.dual_step)

    #: the kernels' certificate adds the KKT bound (where ``definite``): a class constant, static under jit
    SECOND_ORDER = True

    def forward(self, t):
        """A T per pixel: (P, K) → (P, N)."""
        return _mm(t, self.illumination.T)

    def adjoint(self, r):
        """Aᵀ r per pixel: (P, N) → (P, K)."""
        return _mm(r, self.illumination)

    def update(self, v):
        """(2G + ρI)⁻¹ v: the ADMM T-update."""
        return _mm(v, self.update_matrix)

    def inverse(self, v):
        """(2G)⁺ v: the unconstrained solve of the warm start."""
        return _mm(v, self.inverse_matrix)

    def gram2(self, v):
        """2G v."""
        return _mm(v, self.gram2_matrix)

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

    #: the first-order bound only (a class constant, static under jit)
    SECOND_ORDER = False

    def _cells(self, v):
        return v.reshape(v.shape[0], self.line.shape[1], self.frame.shape[1])

    def forward(self, t):
        return _einsum("ju,pun->pjn", self.line, _mm(self._cells(t), self.frame.T)).reshape(t.shape[0], -1)

    def adjoint(self, r):
        n_u = self.line.shape[0]
        return _einsum("ju,pjv->puv", self.line, _mm(r.reshape(r.shape[0], n_u, -1), self.frame)).reshape(
            r.shape[0], -1)

    def _blockwise(self, blocks, v):  # (Q ⊗ I) blockdiag (Q ⊗ I)ᵀ v
        y = _einsum("ui,puv->piv", self.basis, self._cells(v))
        y = _einsum("piv,ivw->piw", y, blocks)
        return _einsum("ui,piw->puw", self.basis, y).reshape(v.shape[0], -1)

    def update(self, v):
        return self._blockwise(self.update_blocks, v)

    def inverse(self, v):
        return self._blockwise(self.inverse_blocks, v)

    def gram2(self, v):
        smooth = _mm(self._cells(v), self.smooth).reshape(v.shape[0], -1)
        return 2.0 * (self.adjoint(self.forward(v)) + self.alpha * smooth)

    def smoothness(self, t):
        return jnp.sum(jnp.diff(self._cells(t), axis=-1) ** 2, axis=(-2, -1))

    def smooth_gradient(self, t):
        return _dtd(self._cells(t)).reshape(t.shape[0], -1)


def _dtd(t, xp=jnp):
    """DᵀD along the last axis (D the first difference): −Δ(pad(D t)), no matrix formed; ``xp`` numpy for the
    float64 reference, ``jax.numpy`` in the kernels."""
    d = xp.diff(t, axis=-1)
    return -xp.diff(xp.pad(d, [(0, 0)] * (d.ndim - 1) + [(1, 1)]), axis=-1)


def _caster(dtype):
    """Cast to ``dtype``: a host array on the host and moved by ``jax.device_put`` (an eager device cast, and
    ``jnp.asarray`` of a host array, each compile one program per shape), a device array or tracer by JAX."""
    dtype = jnp.dtype(dtype)
    return lambda a: jnp.asarray(a, dtype=dtype) if isinstance(a, jax.Array) else jax.device_put(np.asarray(a, dtype))
