"""The projector for volumes (#26 item 2): the matrix-free Joseph walk against a precomputed sparse system matrix.

A volume's slices share one (θ, X) grid, so one matrix R serves them all and R·[σ₁ … σ_S] is a single
sparse–dense product. Measured here at the accuracy benchmark's size (256² cells, 360 × 256 rays), per slice,
forward (R σ) plus adjoint (Rᵀ y), warm (compiles excluded), for S slices at once:

* ``walk``: :func:`selpath.stages.tomography._projector.forward` / ``adjoint`` (jitted, batched by ``vmap``), today's
projector;
* ``csr``: :func:`~selpath.stages.tomography._projector.system_matrix` with scipy (one thread);
* ``bcsr``: the same matrix as a JAX ``BCSR`` passed to the jitted product as an argument (closed over as a constant,
  XLA spends minutes constant-folding its 40 M indices).

Also the matrix's build time and size, its agreement with the walk, and what it buys the reconstruction: 30 ADMM
iterations (``TVADMM.solve_batch``, the stage's defaults otherwise) on S slices of a full sinogram, per slice, with
the walk and with the matrix. Last line: ``projector: walk_ms=<a> csr_ms=<b> bcsr_ms=<c> slices=<S>
speedup=<a / min(b, c)> admm_walk_s=<d> admm_matrix_s=<e>`` (per slice; the products at the largest S, the
ADMM at ``--admm-slices``).

    python benchmarks/tomo_projector.py [--n 256] [--angles 360] [--slices 1,8,32]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import sparse

from selpath.stages.tomography._admm import TVADMM
from selpath.stages.tomography._projector import (
    Geometry,
    MatrixProjector,
    WalkProjector,
    adjoint,
    forward,
    system_matrix,
)


def best_of(fn, *args, repeats: int = 3) -> float:
    """Fastest of ``repeats`` warm runs [s] (one run first to compile)."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=256)
    parser.add_argument("--angles", type=int, default=360)
    parser.add_argument("--slices", default="1,8,32")
    parser.add_argument("--admm-slices", type=int, default=8)
    args = parser.parse_args()
    n, counts = args.n, [int(s) for s in args.slices.split(",")]
    geometry = Geometry.from_grids(np.arange(args.angles) * 180.0 / args.angles, np.linspace(-1.0, 1.0, n), n, 1.02)
    start = time.perf_counter()
    matrix = system_matrix(geometry)
    build = time.perf_counter() - start
    transpose = matrix.T.tocsr()
    size_gb = 2 * (matrix.data.nbytes + matrix.indices.nbytes + matrix.indptr.nbytes) / 1e9
    print(f"{n}² cells, {args.angles} × {n} rays: R has {matrix.nnz / 1e6:.1f} M nonzeros; built in {build:.1f} s; "
          f"R and Rᵀ take {size_gb:.2f} GB")
    rng = np.random.default_rng(0)
    image = rng.random((n, n)).astype(np.float32)
    walked = np.asarray(jax.jit(lambda x: forward(geometry, x))(jnp.asarray(image)))
    product = (matrix @ image.ravel()).reshape(walked.shape)
    print(f"R σ against the walk: max difference {np.abs(product - walked).max() / np.abs(walked).max():.1e} of the "
          f"largest ray (float32)")

    walk_forward = jax.jit(lambda x: forward(geometry, x))
    walk_adjoint = jax.jit(lambda y: adjoint(geometry, y))
    r_bcsr, rt_bcsr = sparse.BCSR.from_scipy_sparse(matrix), sparse.BCSR.from_scipy_sparse(transpose)
    bcsr_product = jax.jit(lambda m, v: m @ v)
    print(f"\n{'slices':>7}{'walk ms':>10}{'csr ms':>10}{'bcsr ms':>10}   (per slice, forward + adjoint)")
    last = {}
    for count in counts:
        images = rng.random((count, n, n)).astype(np.float32)
        sinograms = rng.random((count, *geometry.shape)).astype(np.float32)
        columns, rays = images.reshape(count, -1).T.copy(), sinograms.reshape(count, -1).T.copy()
        walk = best_of(walk_forward, jnp.asarray(images)) + best_of(walk_adjoint, jnp.asarray(sinograms))
        csr = best_of(lambda v: matrix @ v, columns) + best_of(lambda v: transpose @ v, rays)
        bcsr = (best_of(bcsr_product, r_bcsr, jnp.asarray(columns))
                + best_of(bcsr_product, rt_bcsr, jnp.asarray(rays)))
        last = {"walk": walk / count * 1e3, "csr": csr / count * 1e3, "bcsr": bcsr / count * 1e3, "slices": count}
        print(f"{count:>7}{last['walk']:>10.1f}{last['csr']:>10.1f}{last['bcsr']:>10.1f}")
    count = args.admm_slices
    sinograms = jnp.asarray(np.stack([np.asarray(walk_forward(jnp.asarray(rng.random((n, n)).astype(np.float32))))
                                      for _ in range(count)]))
    observed, upper = jnp.ones(sinograms.shape, bool), jnp.full((count, n, n), 10.0, jnp.float32)
    solve = jax.jit(TVADMM(geometry, tol=1e-12, max_iter=30).solve_batch)
    admm = {name: best_of(solve, projector, sinograms, observed, upper, repeats=1) / count
            for name, projector in (("walk", WalkProjector()), ("matrix", MatrixProjector.build(geometry)))}
    print(f"\n30 ADMM iterations, {count} slices at once: {admm['walk']:.2f} s a slice walked, {admm['matrix']:.2f} s "
          f"with the matrix ({admm['walk'] / admm['matrix']:.0f}×)")
    print(f"projector: walk_ms={last['walk']:.1f} csr_ms={last['csr']:.1f} bcsr_ms={last['bcsr']:.1f} "
          f"slices={last['slices']} speedup={last['walk'] / min(last['csr'], last['bcsr']):.1f} "
          f"admm_walk_s={admm['walk']:.2f} admm_matrix_s={admm['matrix']:.2f}")


if __name__ == "__main__":
    main()
