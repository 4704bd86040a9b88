"""What a KKT-accurate final step would buy the demultiplexing certificate (#25): a measured probe, not the stage.

The stage's ADMM stops on a relative-residual test, and its certified gap bound (weak duality from T's own
gradients) is first-order: about 1e-2 median on the benchmark stack while the true gap is ~1e-4, so the bound
cannot be the stopping rule. This probe starts from the stage's solution at its pre-#25-finish defaults
(``DemuxADMM(tol=5e-3, polish_rounds=1, max_gap=1)``: ADMM alone, float32) and
runs a primal–dual active-set method (Hintermüller, Ito & Kunisch 2003) with *exact* solves on the free set:
round 1 frees the offsets ADMM left positive; each later round frees i where λ_i − κ T_i ≤ 0 (λ = ∇f, κ = 1e3),
holds the others at 0 and solves the free set's KKT system exactly (a batched dense solve with the masked Gram
matrix, whose factorisation depends on the pixel's free set). Printed per round: the certified bound (median, p99,
max) on the pixels of the benchmark stack (K = 128, the kept frames, Gaussian noise), in float64 and float32, and
the share of pixels whose solve left a negative entry (the set not yet settled). Then the cost of one exact round
in JAX float32: the full K × K Cholesky per pixel, and the same at the median free-set size (what compacting each
pixel's free set, bucketed by size, would cost).

    python -m benchmarks.demux_active_set_probe [--pixels 1024]

Measured 2026-11-25 on the 2-core machine (1024 px): in float64 every pixel certified ≤ 1e-4 after 4 rounds and
≤ 3e-12 after 5 (median 4e-13, from 1.2e-2 after ADMM); in float32 the free sets' solves are too ill-conditioned
to settle (median 6e-5 but max 0.44, 12 % of pixels with a negative entry after 5 rounds), so this finish needs
float64 solves. One round's batched Cholesky costs, µs/px: float32 86 at K = 128 and 8–11 at the median free-set
size (46); float64 255 and 22 (ADMM's whole solve is ~10–30 µs/px). So the finish is affordable only with each
pixel's free set compacted (bucketed by size), in float64, and only on the pixels the bound has not yet certified.

Last line: ``active_set_probe: rounds_to_1e-4=<n, float64> float32_max_bound=<b> float64_max_bound=<c>
us_per_px_free_float64=<d>``
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def rounds(q: np.ndarray, c: np.ndarray, t: np.ndarray, bound, n: int, dtype) -> list[tuple]:
    """``n`` active-set rounds on min ½TᵀQT − cᵀT, T ≥ 0 (per pixel rows of ``c``), from ``t``: per round
    (bounds, share of pixels with a negative free entry)."""
    k = q.shape[0]
    q, c, t = q.astype(dtype), c.astype(dtype), t.astype(dtype)
    free, out = t > 0, []
    for r in range(n):
        if r:
            free = ~((t @ q - c) - 1e3 * t > 0)
        m = free.astype(dtype)
        masked = m[:, :, None] * q[None] * m[:, None, :] + np.eye(k, dtype=dtype)[None] * (1 - m)[:, :, None]
        t = np.where(free, np.linalg.solve(masked, (m * c)[..., None])[..., 0], 0)
        out.append((bound(np.maximum(t, 0)), float(np.mean((t < 0).any(1)))))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixels", type=int, default=1024)
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp

    from benchmarks._demux_sweep import matrix as _matrix
    from benchmarks._demux_sweep import pixels as _pixels
    from selpath.stages.procam.solver import DemuxADMM, DemuxProblem, certified_gap

    k, p = 128, args.pixels
    a = _matrix(k, kept_only=True)
    problem = DemuxProblem.build(a)
    truth, _ = _pixels(k, p, seed=1)
    data = truth @ a.T + np.random.default_rng(3).normal(0, 2e-3, (p, a.shape[0]))
    solution = DemuxADMM(tol=5e-3, polish_rounds=1, max_gap=1.0).solve(problem, data)
    start = certified_gap(problem, solution.value.astype(float), data)
    print(f"{p} pixels, K = {k}, N = {a.shape[0]}; ADMM at the stage's defaults (float32): bound median "
          f"{np.median(start):.2e}, p99 {np.percentile(start, 99):.2e}, max {start.max():.2e}; "
          f"{solution.stats['iterations'].mean():.1f} iterations")
    d = np.diff(np.eye(k), axis=0)
    q = 2 * (a.T @ a + problem.alpha * d.T @ d)
    scale = np.abs(data).max(1, keepdims=True)  # the solver's per-pixel scaling
    c = 2 * (data / scale) @ a - problem.beta / scale

    def bound(t):
        return certified_gap(problem, t.astype(float) * scale, data)

    t0 = solution.value.astype(float) / scale
    table = {name: rounds(q, c, t0, bound, 5, dtype) for name, dtype in (("float64", np.float64),
                                                                           ("float32", np.float32))}
    print(f"{'round':>5}  {'float64 median / p99 / max':>30}  {'float32 median / p99 / max':>30}  unsettled")
    for r in range(5):
        cells = [f"{np.median(g):.1e} / {np.percentile(g, 99):.1e} / {g.max():.1e}" for g, _ in
                 (table["float64"][r], table["float32"][r])]
        print(f"{r + 1:>5}  {cells[0]:>30}  {cells[1]:>30}  {table['float32'][r][1]:>8.1%}")
    settled = [r + 1 for r, (g, _) in enumerate(table["float64"]) if g.max() <= 1e-4]

    def exact_cost(size: int, dtype=jnp.float32) -> float:
        qj = jnp.asarray(q[:size, :size], dtype)
        free = jnp.asarray(np.random.default_rng(0).random((p, size)) < 0.9)
        rhs = jnp.asarray(c[:, :size], dtype)

        @jax.jit
        def solve(free, rhs):
            m = free.astype(dtype)
            masked = m[:, :, None] * qj[None] * m[:, None, :] + jnp.eye(size)[None] * (1 - m)[:, :, None]
            factor = jnp.linalg.cholesky(masked)
            return jax.scipy.linalg.cho_solve((factor, True), (m * rhs)[..., None])[..., 0]

        solve(free, rhs).block_until_ready()
        began = time.perf_counter()
        for _ in range(3):
            solve(free, rhs).block_until_ready()
        return (time.perf_counter() - began) / 3 / p * 1e6

    median_free = int(np.median((solution.value > 0).sum(1)))
    full, compact = exact_cost(k), exact_cost(median_free)
    with jax.enable_x64(True):
        full64, compact64 = exact_cost(k, jnp.float64), exact_cost(median_free, jnp.float64)
    print(f"one exact round, JAX batched Cholesky, µs/px: float32 {full:.1f} at K = {k}, {compact:.1f} at the median "
          f"free-set size {median_free}; float64 {full64:.1f} and {compact64:.1f}")
    print(f"active_set_probe: rounds_to_1e-4={settled[0] if settled else 'none'} "
          f"float32_max_bound={table['float32'][-1][0].max():.1e} "
          f"float64_max_bound={table['float64'][-1][0].max():.1e} "
          f"us_per_px_free_float64={compact64:.1f}")


if __name__ == "__main__":
    main()
