"""Constrained TV reconstruction by ADMM (Eq. 20–30): a small solver object that returns a result.

Problem, per slice::

    min_σ  ½‖M (R σ − A)‖²  +  λ ‖∇σ‖_{2,1}  +  ι_[0, σ_max](σ)

M masks the observed rays, R is :mod:`stages.tomography._projector`, ∇ forward differences (isotropic TV, Eq. 30) and
σ_max the per-cell bound of Eq. 26–28 (0 outside the object's support). ADMM splits z₁ = D σ (TV) and
z₂ = K σ (box). Both splits are scaled to the projector: K = ‖M R‖ and D = (K/‖∇‖)·∇, so the three terms
of the σ-update matrix RᵀMR + ρ(DᵀD + K²I) have the same norm and one penalty ρ (dimensionless, default
:attr:`TVADMM.DEFAULT_RHO`) balances them whatever the units, grid or mask (DESIGN §6: worth ~3× in RMSE at
equal cost). The σ-update is solved by a few warm-started conjugate-gradient steps (lineax ``CG``), the
z-updates are exact (isotropic shrinkage, clipping). The reported iterate is z₂/K, which lies in the box at every
iteration by construction. Stops when Boyd's relative primal and dual residuals fall below ``tol`` (the
dual one relative to the larger of ρ‖Dᵀu₁ + Ku₂‖ and ‖RᵀMA‖: on clean data the former tends to 0), or
at ``max_iter``; the result code (:class:`stages._solution.Result`) says which.

``TVADMM`` is the only home of the reconstruction's defaults (λ, ρ, tol, the caps): ``reconstruct_tv`` and
``light_angle_study`` take theirs from its ``DEFAULT_*`` constants. λ here (``tv_weight``, TV weight of Eq. 20)
and ρ (relative to ‖MR‖²) are not the demultiplexing's α, β and ``rho_factor`` (:mod:`stages.procam`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import ClassVar

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np

from stages._solution import Solution, outcome, raise_if_failed
from stages.tomography._projector import Geometry, adjoint, forward, operator_norm

_GRADIENT_NORM = np.sqrt(8.0)  # ‖∇‖₂ of 2D forward differences (Neumann boundary)


def gradient(image: jnp.ndarray) -> jnp.ndarray:
    """Forward differences (2, n, n), zero across the last row/column (Neumann)."""
    dy = jnp.concatenate([image[1:] - image[:-1], jnp.zeros_like(image[:1])], axis=0)
    dx = jnp.concatenate([image[:, 1:] - image[:, :-1], jnp.zeros_like(image[:, :1])], axis=1)
    return jnp.stack([dy, dx])


def gradient_adjoint(field: jnp.ndarray) -> jnp.ndarray:
    """∇ᵀ (minus the divergence), the exact transpose of :func:`gradient`."""
    (out,) = jax.linear_transpose(gradient, jax.ShapeDtypeStruct(field.shape[1:], field.dtype))(field)
    return out


def total_variation(image: jnp.ndarray) -> jnp.ndarray:
    """Isotropic TV of Eq. 30: Σ √(∇₁σ² + ∇₂σ²)."""
    return jnp.sqrt((gradient(image) ** 2).sum(axis=0)).sum()


@dataclass(frozen=True)
class TVADMM:
    """ADMM for Eq. 20 on one geometry: an immutable solver whose :meth:`solve` returns a :class:`Solution`.

    :meth:`solve` (one slice) is pure, so ``jax.jit``/``jax.vmap`` it freely; nothing can raise inside a
    jitted function, so ``throw`` acts in :meth:`solve_slices` (the batched, host-side entry point), which
    raises :class:`stages._solution.SolverError` when ``throw`` is set and a slice did not converge.

    The :class:`Solution` of one slice: ``value`` σ (n, n) inside [0, σ_max]; ``result`` a scalar
    :class:`stages._solution.Result` code (``converged``, ``max_steps``, ``nonfinite``); ``stats``:
    ``iterations`` (int), and per iteration (max_iter,) ``objective`` ½‖M(Rσ−A)‖² + λ TV(σ) of each reported
    iterate, relative ``primal_residual`` and ``dual_residual``, NaN after the stop. Batched: a leading slice
    axis everywhere.
    """

    #: λ of Eq. 20 [absorption² per (1/length)·cell]
    DEFAULT_TV_WEIGHT: ClassVar[float] = 1e-3
    #: ADMM penalty relative to ‖MR‖² [1]
    DEFAULT_RHO: ClassVar[float] = 0.1
    #: relative primal and dual residual at which to stop [1]
    DEFAULT_TOL: ClassVar[float] = 1e-3
    DEFAULT_MAX_ITER: ClassVar[int] = 200
    #: conjugate-gradient steps per σ-update (warm-started)
    DEFAULT_CG_STEPS: ClassVar[int] = 3

    geometry: Geometry
    tv_weight: float = DEFAULT_TV_WEIGHT
    rho: float = DEFAULT_RHO
    tol: float = DEFAULT_TOL
    max_iter: int = DEFAULT_MAX_ITER
    cg_steps: int = DEFAULT_CG_STEPS
    throw: bool = False

    def solve(self, sinogram: jnp.ndarray, observed: jnp.ndarray, sigma_max: jnp.ndarray,
              norm: float | None = None) -> Solution:
        """Reconstruct one slice (pure, jit-able, never raises); ``norm`` is ‖M R‖ (estimated when None)."""
        g, dtype = self.geometry, sinogram.dtype
        mask = observed.astype(dtype)
        b = jnp.where(observed, jnp.nan_to_num(sinogram), 0.0).astype(dtype)
        k = jnp.asarray(norm if norm is not None else operator_norm(g, mask, dtype=dtype), dtype)
        k = jnp.maximum(k, jnp.finfo(dtype).tiny ** 0.25)  # all-unobserved slice: keep the scaling finite
        scale = k / _GRADIENT_NORM
        upper = jnp.maximum(jnp.nan_to_num(sigma_max.astype(dtype), nan=0.0, posinf=jnp.finfo(dtype).max), 0.0)
        rho, lam = jnp.asarray(self.rho, dtype), jnp.asarray(self.tv_weight, dtype)

        def normal(x):  # (RᵀMR + ρ(DᵀD + K²I)) x
            return adjoint(g, mask * forward(g, x)) + rho * (scale**2 * gradient_adjoint(gradient(x)) + k**2 * x)

        structure = jax.ShapeDtypeStruct((g.n, g.n), dtype)
        operator = lx.FunctionLinearOperator(normal, structure, tags=(lx.symmetric_tag, lx.positive_semidefinite_tag))
        cg = lx.CG(rtol=1e-6, atol=1e-12, max_steps=self.cg_steps)
        rhs0 = adjoint(g, mask * b)
        rhs0_norm = jnp.linalg.norm(rhs0)  # the data term's gradient at σ = 0: the dual residual's floor scale
        threshold = lam / (rho * scale)  # TV(σ) = ‖z₁‖/scale, so z₁ shrinks by λ/(ρ·scale)

        def objective(sigma):
            residual = mask * (forward(g, sigma) - b)
            return 0.5 * jnp.vdot(residual, residual) + lam * total_variation(sigma)

        def step(carry):
            i, sigma, z1, z2, u1, u2, _, history = carry
            rhs = rhs0 + rho * (scale * gradient_adjoint(z1 - u1) + k * (z2 - u2))
            sigma = lx.linear_solve(operator, rhs, cg, options={"y0": sigma}, throw=False).value
            d = scale * gradient(sigma)
            v = d + u1
            magnitude = jnp.sqrt((v**2).sum(axis=0, keepdims=True))
            z1_new = v * jnp.maximum(1.0 - threshold / jnp.maximum(magnitude, jnp.finfo(dtype).tiny), 0.0)
            z2_new = jnp.clip(k * sigma + u2, 0.0, k * upper)
            u1, u2 = u1 + d - z1_new, u2 + k * sigma - z2_new
            primal = jnp.sqrt(jnp.sum((d - z1_new) ** 2) + jnp.sum((k * sigma - z2_new) ** 2))
            dual = rho * jnp.linalg.norm(scale * gradient_adjoint(z1_new - z1) + k * (z2_new - z2))
            eps = jnp.finfo(dtype).eps
            primal_scale = jnp.maximum(jnp.sqrt(jnp.sum(d**2) + jnp.sum((k * sigma) ** 2)),
                                       jnp.sqrt(jnp.sum(z1_new**2) + jnp.sum(z2_new**2)))
            dual_scale = jnp.maximum(rho * jnp.linalg.norm(scale * gradient_adjoint(u1) + k * u2), rhs0_norm)
            rel_primal = primal / jnp.maximum(primal_scale, eps)
            rel_dual = dual / jnp.maximum(dual_scale, eps)
            done = (rel_primal <= self.tol) & (rel_dual <= self.tol)
            objective_value = objective(z2_new / k)
            history = (history[0].at[i].set(objective_value), history[1].at[i].set(rel_primal),
                       history[2].at[i].set(rel_dual))
            return i + 1, sigma, z1_new, z2_new, u1, u2, done, history

        def keep_going(carry):
            i, *_, done, _ = carry
            return (i < self.max_iter) & ~done

        zeros = jnp.zeros((g.n, g.n), dtype)
        nan = jnp.full((self.max_iter,), jnp.nan, dtype)
        init = (jnp.asarray(0), zeros, jnp.zeros((2, g.n, g.n), dtype), zeros, jnp.zeros((2, g.n, g.n), dtype),
                zeros, jnp.asarray(False), (nan, nan, nan))
        i, _, _, z2, _, _, done, history = jax.lax.while_loop(keep_going, step, init)
        sigma = z2 / k
        stats = {"iterations": i, "objective": history[0], "primal_residual": history[1], "dual_residual": history[2]}
        return Solution(sigma, outcome(done, jnp.all(jnp.isfinite(sigma)), jnp), stats)

    def solve_slices(self, sinograms: jnp.ndarray, observed: jnp.ndarray, sigma_max: jnp.ndarray) -> Solution:
        """Every slice of (S, θ, X) sinograms at once (jitted and vmapped once per solver and dtype), as numpy;
        raises :class:`stages._solution.SolverError` if ``throw`` is set and a slice did not converge."""
        batched = _batched(replace(self, throw=False), jnp.dtype(sinograms.dtype).name)  # one compile for both
        solution = jax.tree.map(np.asarray, batched(sinograms, observed, sigma_max))
        if self.throw:
            raise_if_failed(solution, "TVADMM", items="slices",
                            fix="raise max_iter or loosen tol (or cg_steps); throw=False keeps them as data")
        return solution


@lru_cache(maxsize=16)
def _batched(solver: TVADMM, dtype: str):
    return jax.jit(jax.vmap(solver.solve))
