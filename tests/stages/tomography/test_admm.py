"""TVADMM against an independent optimum: CVXPY (Clarabel) on the same problem, and its result codes.

The problem is exactly the one ``TVADMM`` states (``selpath.stages.tomography._admm``)::

    min_σ  ½‖M (R σ − A)‖²  +  λ Σ_ij √((∇_y σ)²_ij + (∇_x σ)²_ij)   subject to  0 ≤ σ ≤ σ_max

with R the project's own projector as a dense matrix (the forward operator applied to every unit image), M the
observed-ray mask, ∇ forward differences that are zero across the last row/column (Neumann, as ``gradient``),
and σ_max = 0 outside a disk support (σ = 0 there) and a bound inside it that the data push against.
"""

from __future__ import annotations

import cvxpy as cp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sps

from selpath.stages._solution import Result, SolverError
from selpath.stages.tomography._admm import TVADMM, total_variation
from selpath.stages.tomography._projector import Geometry, forward

N = 12
THETA = np.array([0.0, 30.0, 75.0, 110.0, 150.0])  # five angles: far too few for FBP, TV and the box carry it
X = np.linspace(-1.0, 1.0, 17)
BOUND = 0.8  # σ_max inside the support; the truth's inclusion (1.0) is above it, so the box is active


def system_matrix(geometry: Geometry) -> np.ndarray:
    """R as a dense (rays, cells) matrix: the forward operator applied to each unit image (float64)."""
    unit = jnp.eye(geometry.n * geometry.n).reshape(-1, geometry.n, geometry.n)
    return np.asarray(jax.vmap(lambda image: forward(geometry, image))(unit)).reshape(geometry.n**2, -1).T


def forward_difference(n: int, axis: int) -> sps.csr_matrix:
    """∇ along ``axis`` of a row-major n × n image, zero on the last row (axis 0) or column (axis 1)."""
    index = np.arange(n * n).reshape(n, n)
    here = index[:-1, :] if axis == 0 else index[:, :-1]
    there = index[1:, :] if axis == 0 else index[:, 1:]
    rows = np.concatenate([here.ravel(), here.ravel()])
    cols = np.concatenate([there.ravel(), here.ravel()])
    values = np.concatenate([np.ones(here.size), -np.ones(here.size)])
    return sps.csr_matrix((values, (rows, cols)), shape=(n * n, n * n))


def problem(method: str, seed: int):
    """(geometry, sinogram A, observed mask, σ_max) of a disk with an inclusion above the bound, noisy, 15 % of
    the bins unobserved."""
    geometry = Geometry.from_grids(THETA, X, N, 1.0, method)
    yy, xx = np.meshgrid(geometry.centres, geometry.centres, indexing="ij")
    support = xx**2 + yy**2 < 0.85**2
    truth = np.where(support, 0.3 + 0.7 * ((xx - 0.2) ** 2 + (yy + 0.1) ** 2 < 0.35**2), 0.0)
    rng = np.random.default_rng(seed)
    sinogram = (system_matrix(geometry) @ truth.ravel()).reshape(len(THETA), len(X))
    sinogram += rng.normal(0.0, 0.02, sinogram.shape)
    observed = rng.random(sinogram.shape) > 0.15
    return geometry, sinogram, observed, np.where(support, BOUND, 0.0)


def cvxpy_optimum(geometry, sinogram, observed, upper, tv_weight) -> float:
    """The optimum of TVADMM's objective by Clarabel (default tolerances, ~1e-8 relative)."""
    r, sigma = system_matrix(geometry), cp.Variable(geometry.n**2)
    mask, data = observed.ravel().astype(float), np.where(observed, sinogram, 0.0).ravel()
    gradient = cp.vstack([forward_difference(geometry.n, 0) @ sigma, forward_difference(geometry.n, 1) @ sigma])
    objective = 0.5 * cp.sum_squares(cp.multiply(mask, r @ sigma - data)) + tv_weight * cp.sum(
        cp.norm(gradient, 2, axis=0))
    qp = cp.Problem(cp.Minimize(objective), [sigma >= 0, sigma <= upper.ravel()])
    qp.solve(solver=cp.CLARABEL)
    assert qp.status == cp.OPTIMAL, qp.status
    return float(qp.value)


@pytest.mark.parametrize(("method", "tv_weight", "seed"), [
    ("joseph", 1e-2, 0), pytest.param("binary", 3e-3, 1, marks=pytest.mark.slow)])
def test_tvadmm_reaches_the_cvxpy_optimum(method, tv_weight, seed):
    """In float64 at tol 1e-6, TVADMM's objective (½‖M(Rσ − A)‖² + λ TV(σ), recomputed here from its σ with the
    dense R) is within 1e-4 relative of Clarabel's optimum (the bar), and not below it by more than Clarabel's
    own accuracy (1e-6 relative allowed); σ lies in the box, and the solve reports ``converged``."""
    with jax.enable_x64(True):
        geometry, sinogram, observed, upper = problem(method, seed)
        optimum = cvxpy_optimum(geometry, sinogram, observed, upper, tv_weight)
        solver = TVADMM(geometry, tv_weight=tv_weight, tol=1e-6, max_iter=5000, throw=True)
        solution = solver.solve_slices(jnp.asarray(sinogram[None]), jnp.asarray(observed[None]),
                                       jnp.asarray(upper[None]))
        sigma = solution.value[0]
        data = np.where(observed, sinogram, 0.0).ravel()
        residual = observed.ravel() * (system_matrix(geometry) @ sigma.ravel() - data)
        value = 0.5 * residual @ residual + tv_weight * float(total_variation(jnp.asarray(sigma)))
    assert solution.result[0] == Result.converged and bool(solution.converged[0])
    assert (sigma >= 0).all() and (sigma <= upper + 1e-12).all()
    gap = (value - optimum) / abs(optimum)
    assert -1e-6 <= gap <= 1e-4, gap
    iterations = int(solution.stats["iterations"][0])
    np.testing.assert_allclose(solution.stats["objective"][0, iterations - 1], value, rtol=1e-9)


def test_capped_solve_is_data_unless_throw():
    """At a cap of 5 iterations the slice is ``max_steps`` (not converged); with ``throw=True`` the same solve
    raises, naming the code and how many slices failed."""
    geometry, sinogram, observed, upper = problem("joseph", 0)
    args = (jnp.asarray(np.stack([sinogram, sinogram]), jnp.float32), jnp.asarray(np.stack([observed, observed])),
            jnp.asarray(np.stack([upper, upper]), jnp.float32))
    solution = TVADMM(geometry, max_iter=5).solve_slices(*args)
    assert solution.result.tolist() == [Result.max_steps, Result.max_steps]
    assert not solution.converged.any() and solution.stats["iterations"].tolist() == [5, 5]
    with pytest.raises(SolverError, match=r"TVADMM: 2 of 2 slices did not end converged: 2 max_steps \(stopped at the "
                                          r"iteration cap"):
        TVADMM(geometry, max_iter=5, throw=True).solve_slices(*args)


@pytest.mark.slow  # default job over its 8 minutes: run in the slow job
@pytest.mark.parametrize("device", [False, True])
def test_a_batch_of_slices_is_each_slice_solved_alone(device, monkeypatch):
    """solve_slices (one batch, the sparse system matrix as JAX's BCSR, which float64 always takes) gives each slice
    what
    TVADMM.solve gives it alone (the matrix-free walk): σ to 1e-9 of its peak in float64, the same iterations and
    result, although the slices stop at different iterations (a converged slice is held while the others go on) and
    one sees no ray at all."""
    from selpath.stages.tomography import _admm
    from selpath.stages.tomography._projector import HostProjector, MatrixProjector

    monkeypatch.setattr(_admm, "DEVICE_BATCH", 1 if device else 10**6)
    geometry, first, observed, upper = problem("joseph", 2)
    _, second, _, _ = problem("joseph", 3)
    sinograms = np.stack([first, 0.5 * second, first])
    masks = np.stack([observed, observed, np.zeros_like(observed)])
    uppers = np.stack([upper, upper, upper])
    solver = TVADMM(geometry, tv_weight=3e-3, tol=1e-5, max_iter=400)
    assert isinstance(_admm.projector_for(geometry, "float32", 3), MatrixProjector if device else HostProjector)
    # float64 always in JAX: the host callback's operands would follow the calling thread's x64 setting
    assert isinstance(_admm.projector_for(geometry, "float64", 3), MatrixProjector)
    with jax.enable_x64(True):
        batch = solver.solve_slices(jnp.asarray(sinograms), jnp.asarray(masks), jnp.asarray(uppers))
        alone = [jax.jit(solver.solve)(jnp.asarray(s), jnp.asarray(m), jnp.asarray(u))
                 for s, m, u in zip(sinograms, masks, uppers, strict=True)]
    iterations = [int(a.stats["iterations"]) for a in alone]
    assert len(set(iterations)) > 1, iterations  # the slices do stop apart
    assert batch.stats["iterations"].tolist() == iterations
    assert batch.result.tolist() == [int(a.result) for a in alone]
    for ours, single in zip(batch.value, alone, strict=True):
        np.testing.assert_allclose(ours, single.value, rtol=0, atol=1e-9 * max(float(np.abs(single.value).max()), 1.0))
