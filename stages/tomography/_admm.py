"""Constrained TV reconstruction by ADMM (Eq. 20–30): a small solver object that returns a result.

Problem, per slice::

    min_σ  ½‖M (R σ − A)‖²  +  λ ‖∇σ‖_{2,1}  +  ι_[0, σ_max](σ)

M masks the observed rays, R is :mod:`selpath.stages.tomography._projector`, ∇ forward differences (isotropic TV, Eq.
30) and
σ_max the per-cell bound of Eq. 26–28 (0 outside the object's support). ADMM splits z₁ = D σ (TV) and
z₂ = K σ (box). Both splits are scaled to the projector: K = ‖M R‖ and D = (K/‖∇‖)·∇, so the three terms
of the σ-update matrix RᵀMR + ρ(DᵀD + K²I) have the same norm and one penalty ρ (dimensionless, default
:attr:`TVADMM.DEFAULT_RHO`) balances them whatever the units, grid or mask (DESIGN §6: worth ~3× in RMSE at
equal cost). The σ-update is solved by a few warm-started conjugate-gradient steps (written here: lineax's
``CG`` takes one inner product over its whole operand, so the slices of a batch would share step lengths), the
z-updates are exact (isotropic shrinkage, clipping). Slices are solved in batches (:meth:`TVADMM.solve_batch`):
each product is one for the batch, through the sparse system matrix where it fits in memory
(:class:`~selpath.stages.tomography._projector.MatrixProjector`, 100× the matrix-free walk per slice in batches of 32 at
256²/360, ``benchmarks/tomo_projector.py``; :class:`~selpath.stages.tomography._projector.HostProjector`, scipy on host
threads, for small batches: 14× the walk for one slice), while every slice keeps its own scaling, stopping test
and count. The reported iterate is z₂/K, which lies in the box at every iteration by construction. Stops when
Boyd's relative primal and dual residuals fall below ``tol`` (the dual one relative to the larger of ρ‖Dᵀu₁ + Ku₂‖
and ‖RᵀMA‖: on clean data the former tends to 0), or at ``max_iter``; the result code
(:class:`selpath.stages._solution.Result`) says which.

``TVADMM`` is the only home of the reconstruction's defaults (λ, ρ, tol, the caps): ``reconstruct_tv`` and
``light_angle_study`` take theirs from its ``DEFAULT_*`` constants. λ here (``tv_weight``, TV weight of Eq. 20)
and ρ (relative to ‖MR‖²) are not the demultiplexing's α, β and ``rho_factor`` (:mod:`selpath.stages.procam`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from selpath.pipeline.constraints import machine_memory
from selpath.stages._solution import Solution, outcome, raise_if_failed
from selpath.stages.tomography import _tv_settings as defaults
from selpath.stages.tomography._projector import Geometry, HostProjector, MatrixProjector, WalkProjector, operator_norm

_GRADIENT_NORM = np.sqrt(8.0)  # ‖∇‖₂ of 2D forward differences (Neumann boundary)


def gradient(image: jnp.ndarray) -> jnp.ndarray:
    """Forward differences (..., 2, n, n) of (..., n, n) images, zero across the last row/column (Neumann)."""
    dy = jnp.concatenate([image[..., 1:, :] - image[..., :-1, :], jnp.zeros_like(image[..., :1, :])], axis=-2)
    dx = jnp.concatenate([image[..., :, 1:] - image[..., :, :-1], jnp.zeros_like(image[..., :, :1])], axis=-1)
    return jnp.stack([dy, dx], axis=-3)


def gradient_adjoint(field: jnp.ndarray) -> jnp.ndarray:
    """∇ᵀ (minus the divergence), the exact transpose of :func:`gradient`."""
    template = jax.ShapeDtypeStruct((*field.shape[:-3], *field.shape[-2:]), field.dtype)
    (out,) = jax.linear_transpose(gradient, template)(field)
    return out


def total_variation(image: jnp.ndarray) -> jnp.ndarray:
    """Isotropic TV of Eq. 30: Σ √(∇₁σ² + ∇₂σ²), per image of a (..., n, n) batch."""
    return jnp.sqrt((gradient(image) ** 2).sum(axis=-3)).sum(axis=(-2, -1))


def _per_slice(x: jnp.ndarray) -> jnp.ndarray:
    """Σ over every axis but the first (the slice): (S, …) → (S,)."""
    return jnp.sum(x, axis=tuple(range(1, x.ndim)))


def _cg(normal, rhs: jnp.ndarray, start: jnp.ndarray, steps: int) -> jnp.ndarray:
    """``steps`` conjugate-gradient steps on normal(x) = rhs from ``start``, for every slice of a batch at once (each
    slice its own step lengths; a slice whose residual vanished stays put)."""
    def dot(a, b):
        return jnp.sum(a * b, axis=(-2, -1), keepdims=True)

    def step(_, state):
        x, r, p, rr = state
        q = normal(p)
        pq = dot(p, q)
        alpha = jnp.where(pq > 0, rr / jnp.where(pq > 0, pq, 1.0), 0.0)
        x, r = x + alpha * p, r - alpha * q
        new = dot(r, r)
        p = r + jnp.where(rr > 0, new / jnp.where(rr > 0, rr, 1.0), 0.0) * p
        return x, r, p, new

    r = rhs - normal(start)
    return jax.lax.fori_loop(0, steps, step, (start, r, r, dot(r, r)))[0]


@dataclass(frozen=True)
class TVADMM:
    """ADMM for Eq. 20 on one geometry: an immutable solver whose :meth:`solve` returns a :class:`Solution`.

    :meth:`solve` (one slice, the matrix-free walk) and :meth:`solve_batch` (S slices through the projector it is
    given) are pure, so ``jax.jit`` them freely; nothing can raise inside a jitted function, so ``throw`` acts in
    :meth:`solve_slices` (the batched, host-side entry point, which picks the projector), which raises
    :class:`selpath.stages._solution.SolverError` when ``throw`` is set and a slice did not converge.

    The :class:`Solution` of one slice: ``value`` σ (n, n) inside [0, σ_max]; ``result`` a scalar
    :class:`selpath.stages._solution.Result` code (``converged``, ``max_steps``, ``nonfinite``); ``stats``:
    ``iterations`` (int), and per iteration (max_iter,) ``objective`` ½‖M(Rσ−A)‖² + λ TV(σ) of each reported
    iterate, relative ``primal_residual`` and ``dual_residual``, NaN after the stop. Batched: a leading slice
    axis everywhere.
    """

    #: the defaults (:mod:`selpath.stages.tomography._tv_settings`, where each is described)
    DEFAULT_TV_WEIGHT: ClassVar[float] = defaults.TV_WEIGHT
    DEFAULT_RHO: ClassVar[float] = defaults.RHO
    DEFAULT_TOL: ClassVar[float] = defaults.TOL
    DEFAULT_MAX_ITER: ClassVar[int] = defaults.MAX_ITER
    DEFAULT_CG_STEPS: ClassVar[int] = defaults.CG_STEPS

    geometry: Geometry
    tv_weight: float = DEFAULT_TV_WEIGHT
    rho: float = DEFAULT_RHO
    tol: float = DEFAULT_TOL
    max_iter: int = DEFAULT_MAX_ITER
    cg_steps: int = DEFAULT_CG_STEPS
    throw: bool = False

    def solve(self, sinogram: jnp.ndarray, observed: jnp.ndarray, sigma_max: jnp.ndarray,
              norm: float | None = None) -> Solution:
        """Reconstruct one slice (pure, jit-able, never raises) with the matrix-free projector; ``norm`` is ‖M R‖
        (estimated when None)."""
        norms = None if norm is None else jnp.reshape(jnp.asarray(norm, sinogram.dtype), (1,))
        solution = self.solve_batch(WalkProjector(), sinogram[None], observed[None], sigma_max[None], norms)
        return jax.tree.map(lambda a: a[0], solution)

    def solve_batch(self, projector: WalkProjector | MatrixProjector | HostProjector, sinograms: jnp.ndarray,
                    observed: jnp.ndarray, sigma_max: jnp.ndarray, norms: jnp.ndarray | None = None) -> Solution:
        """Reconstruct S slices (S, T, X) at once (pure, jit-able, never raises): every product is one for the whole
        batch (with a :class:`MatrixProjector`, one sparse–dense product), while each slice keeps its own scaling,
        CG steps, stopping test and iteration count; a slice that has converged is held as it stopped while the
        others go on. ``norms`` (S,) are ‖M R‖ per slice (estimated when None)."""
        g, dtype = self.geometry, sinograms.dtype
        mask = observed.astype(dtype)
        b = jnp.where(observed, jnp.nan_to_num(sinograms), 0.0).astype(dtype)
        if norms is None:
            norms = operator_norm(g, mask, dtype=dtype, projector=projector)
        k = jnp.maximum(jnp.asarray(norms, dtype), jnp.finfo(dtype).tiny ** 0.25)  # all-unobserved: keep it finite
        k, k_field = k[:, None, None], k[:, None, None, None]  # per slice, against images and gradient fields
        scale, scale_field = k / _GRADIENT_NORM, k_field / _GRADIENT_NORM
        upper = jnp.maximum(jnp.nan_to_num(sigma_max.astype(dtype), nan=0.0, posinf=jnp.finfo(dtype).max), 0.0)
        rho, lam = jnp.asarray(self.rho, dtype), jnp.asarray(self.tv_weight, dtype)

        def fwd(x):
            return projector.forward(g, x)

        def adj(y):
            return projector.adjoint(g, y)

        def normal(x):  # (RᵀMR + ρ(DᵀD + K²I)) x, per slice
            return adj(mask * fwd(x)) + rho * (scale**2 * gradient_adjoint(gradient(x)) + k**2 * x)

        rhs0 = adj(mask * b)
        rhs0_norm = jnp.sqrt(_per_slice(rhs0**2))  # the data term's gradient at σ = 0: the dual residual's floor
        threshold = lam / (rho * scale_field)  # TV(σ) = ‖z₁‖/scale, so z₁ shrinks by λ/(ρ·scale)
        eps = jnp.finfo(dtype).eps

        def step(carry):
            i, iterations, state, done, history = carry
            sigma, z1, z2, u1, u2 = state
            rhs = rhs0 + rho * (scale * gradient_adjoint(z1 - u1) + k * (z2 - u2))
            sigma = _cg(normal, rhs, sigma, self.cg_steps)
            d = scale_field * gradient(sigma)
            v = d + u1
            magnitude = jnp.sqrt((v**2).sum(axis=-3, keepdims=True))
            z1_new = v * jnp.maximum(1.0 - threshold / jnp.maximum(magnitude, jnp.finfo(dtype).tiny), 0.0)
            z2_new = jnp.clip(k * sigma + u2, 0.0, k * upper)
            u1, u2 = u1 + d - z1_new, u2 + k * sigma - z2_new
            primal = jnp.sqrt(_per_slice((d - z1_new) ** 2) + _per_slice((k * sigma - z2_new) ** 2))
            dual = rho * jnp.sqrt(_per_slice((scale * gradient_adjoint(z1_new - z1) + k * (z2_new - z2)) ** 2))
            primal_scale = jnp.maximum(jnp.sqrt(_per_slice(d**2) + _per_slice((k * sigma) ** 2)),
                                       jnp.sqrt(_per_slice(z1_new**2) + _per_slice(z2_new**2)))
            dual_scale = jnp.maximum(rho * jnp.sqrt(_per_slice((scale * gradient_adjoint(u1) + k * u2) ** 2)),
                                     rhs0_norm)
            rel_primal = primal / jnp.maximum(primal_scale, eps)
            rel_dual = dual / jnp.maximum(dual_scale, eps)
            sigma_now = z2_new / k
            residual = mask * (fwd(sigma_now) - b)
            objective = 0.5 * _per_slice(residual**2) + lam * total_variation(sigma_now)
            # a slice that had converged keeps its state, count and history (NaN after its stop)
            running = ~done
            state = jax.tree.map(lambda old, new: jnp.where(running.reshape(-1, *[1] * (new.ndim - 1)), new, old),
                                 carry[2], (sigma, z1_new, z2_new, u1, u2))
            history = tuple(h.at[:, i].set(jnp.where(running, value, h[:, i]))
                            for h, value in zip(history, (objective, rel_primal, rel_dual), strict=True))
            done = done | ((rel_primal <= self.tol) & (rel_dual <= self.tol))
            return i + 1, iterations + running, state, done, history

        def keep_going(carry):
            i, _, _, done, _ = carry
            return (i < self.max_iter) & ~jnp.all(done)

        count = sinograms.shape[0]
        image, field = jnp.zeros((count, g.n, g.n), dtype), jnp.zeros((count, 2, g.n, g.n), dtype)
        nan = jnp.full((count, self.max_iter), jnp.nan, dtype)
        init = (jnp.asarray(0), jnp.zeros(count, jnp.int32), (image, field, image, field, image),
                jnp.zeros(count, bool), (nan, nan, nan))
        _, iterations, state, done, history = jax.lax.while_loop(keep_going, step, init)
        sigma = state[2] / k
        stats = {"iterations": iterations, "objective": history[0], "primal_residual": history[1],
                 "dual_residual": history[2]}
        return Solution(sigma, outcome(done, jnp.all(jnp.isfinite(sigma), axis=(-2, -1)), jnp), stats)

    def solve_slices(self, sinograms: jnp.ndarray, observed: jnp.ndarray, sigma_max: jnp.ndarray) -> Solution:
        """Every slice of (S, θ, X) sinograms at once, as numpy: through the sparse system matrix
        (:func:`projector_for`: built once per geometry and dtype and kept for the next call) where it fits in
        :data:`MATRIX_SHARE` of this machine's memory, else the matrix-free walk (the same iterates to rounding);
        raises :class:`selpath.stages._solution.SolverError` if ``throw`` is set and a slice did not converge."""
        dtype = jnp.dtype(sinograms.dtype).name
        projector = projector_for(self.geometry, dtype, sinograms.shape[0])
        solve = _batched(replace(self, throw=False))  # one compile per solver, projector, dtype and batch shape
        solution = jax.tree.map(np.asarray, solve(projector, sinograms, observed, sigma_max))
        if self.throw:
            raise_if_failed(solution, "TVADMM", items="slices",
                            fix="raise max_iter or loosen tol (or cg_steps); throw=False keeps them as data")
        return solution


#: the system matrix is used where building it (its peak, :data:`BUILD_PEAK` times what R and Rᵀ keep) takes at
#: most this share of the machine's memory (else the walk)
MATRIX_SHARE = 0.25
#: the build's peak memory over what R and Rᵀ keep: measured 4× at 192² and 270 angles (the taps, COO lists, the
#: transpose)
BUILD_PEAK = 5
#: batches of at least this many slices take the matrix in JAX (BCSR: 15 ms a slice's forward–adjoint pair at 8
#: slices and 4 at 32, 256²/360), smaller ones scipy's on host threads (26 ms for one slice, where BCSR takes 365;
#: both ~15 ms at 8 slices)
DEVICE_BATCH = 16
_BUILD = threading.Lock()
_MATRICES: dict = {}


def projector_for(geometry: Geometry, dtype: str, slices: int) -> WalkProjector | MatrixProjector | HostProjector:
    """The projector :meth:`TVADMM.solve_slices` uses for a batch of ``slices``: the sparse system matrix where its
    build fits (as :class:`MatrixProjector` from :data:`DEVICE_BATCH` slices on, else :class:`HostProjector`), else
    the walk; float64 always in JAX. Each is built once per (geometry, dtype, kind), under a lock so that concurrent
    slice chunks build it
    once, and kept for the process's life: the compiled solves hold it anyway (a rebuilt one would compile again),
    and a process meets few geometries (0.65 GB each at 256²/360)."""
    total = machine_memory()
    if total is not None and BUILD_PEAK * MatrixProjector.nbytes(geometry, dtype) > MATRIX_SHARE * total:
        return WalkProjector()
    # float64 never takes the host product: jax.pure_callback moves its operands to the host under the calling
    # thread's x64 setting, and ``jax.enable_x64`` is thread-local, so a callback run on one of XLA's threads got
    # float32 operands for a float64 solve (an intermittent "Incorrect output dtype" in CI, 2026-11-26)
    key = (geometry, dtype, slices >= DEVICE_BATCH or np.dtype(dtype) == np.float64)
    with _BUILD:
        if key not in _MATRICES:
            with jax.enable_x64(dtype == "float64"):  # else JAX would keep a float64 matrix as float32
                _MATRICES[key] = (MatrixProjector if key[2] else HostProjector).build(geometry, np.dtype(dtype))
        return _MATRICES[key]


@lru_cache(maxsize=16)
def _batched(solver: TVADMM):
    return jax.jit(solver.solve_batch)
