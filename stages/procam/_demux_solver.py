"""Batched non-negative, smooth and sparse deconvolution with one shared illumination matrix (§5.2.2, §5.3.1).

Every pixel p solves the thesis's problem

    min_T  Σ_i w_pi (A T − y_p)_i² + α ‖D T‖² + β 1ᵀT   subject to  T ≥ 0,

with A (N frames × K offsets) the same for all pixels and w_pi ∈ {0, 1} masking saturated or non-finite
frames. No library solves millions of small QPs that share a Hessian as one matrix–matrix product per
iteration (CVXPY/Clarabel factorise each problem; optimistix has no bound constraints and the softplus
detour was slow, DESIGN §6), so this is a batched ADMM in plain JAX:

* splitting T = Z with Z ≥ 0 carrying the L1 term: the T-update is (2G + ρI)⁻¹(2Aᵀỹ + ρ(Z − U)) with
  G = AᵀA + αDᵀD, one shared K × K inverse, so a tile of P pixels costs one (P × K)·(K × K) product per
  iteration; the Z-update max(0, ·− β/ρ) is exact;
* a warm start at the unconstrained minimiser, clipped at 0, and Goldstein et al.'s fast ADMM with restart
  (Nesterov momentum per pixel while the combined residual falls): measured against plain and
  over-relaxed ADMM, 4–10× fewer iterations to a 1e-4 objective gap; ρ = ``rho_factor`` · λ_max(2G)
  (0.01, the best of 0.003–0.3 on a Fig. 38-like sweep);
* masked frames by majorisation: a masked observation is replaced by the current prediction (ỹ = w y +
  (1 − w) A Z), whose fixed points are exactly the masked problem's optima, so unmasked tiles keep the
  cheapest path and masked ones pay two more products per iteration;
* each pixel is scaled by its largest observation (β with it), so data from 1e-8 to 1e8 run in float32;
* a final polish: conjugate gradients on the KKT system of the support ADMM found (the free offsets), kept
  per pixel only where it lowers the objective (OSQP's "solution polishing", batched).

The full transport (§5.3.1) uses the same iteration with the Kronecker-factored operators of
:class:`~stages.procam._demux_problem.SeparableDemuxProblem` (A = L_u ⊗ L, never formed).

Per pixel it returns the iterations to convergence (primal and dual residuals ≤ ``tol`` relative, checked
every ``check_every`` iterations) and an honest flag. A call's pixels stream through one batch whose rows are
written out and refilled as their pixels converge or reach ``max_iter`` (:func:`_stream`), and the batch's
tail is compacted into smaller batches (:func:`_solve`), so a call costs about its pixels' mean iterations,
not its slowest pixel's. A pixel stops at the check where it meets ``tol``: it is not iterated further while
slower pixels finish (an earlier version did, for free accuracy at the same recorded iterations).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from stages.procam._demux_problem import DemuxProblem, SeparableDemuxProblem


@dataclass(frozen=True)
class DemuxResult:
    transport: np.ndarray  # (P, K), ≥ 0, in the data's units
    iterations: np.ndarray  # (P,) iterations until the pixel's residuals met the tolerance (max_iter if never)
    converged: np.ndarray  # (P,) bool
    objective: np.ndarray  # (P,) the objective at ``transport`` (float32 arithmetic)


def _sq(x):
    return jnp.sum(x * x, axis=-1)


def _operators(kind: str, arrays, alpha):
    """(forward, adjoint, update, inverse, gram2, smoothness²) for a problem kind, on flat (P, K) iterates."""
    if kind == "dense":
        a, gram2, update, inverse = arrays
        return (lambda t: t @ a.T, lambda r: r @ a, lambda v: v @ update, lambda v: v @ inverse,
                lambda v: v @ gram2, lambda t: _sq(jnp.diff(t, axis=-1)))
    line, frame, basis, update, inverse, smooth = arrays
    k_u, k_v, n_u = line.shape[1], frame.shape[1], line.shape[0]

    def cells(v):
        return v.reshape(v.shape[0], k_u, k_v)

    def forward(t):
        return jnp.einsum("ju,pun->pjn", line, cells(t) @ frame.T).reshape(t.shape[0], -1)

    def adjoint(r):
        return jnp.einsum("ju,pjv->puv", line, r.reshape(r.shape[0], n_u, -1) @ frame).reshape(r.shape[0], -1)

    def blockwise(blocks):
        def apply(v):  # (Q ⊗ I) blockdiag (Q ⊗ I)ᵀ v
            y = jnp.einsum("ui,puv->piv", basis, cells(v))
            y = jnp.einsum("piv,ivw->piw", y, blocks)
            return jnp.einsum("ui,piw->puw", basis, y).reshape(v.shape[0], -1)
        return apply

    def gram2(v):
        return 2.0 * (adjoint(forward(v)) + alpha * (cells(v) @ smooth).reshape(v.shape[0], -1))

    def smoothness(t):
        return jnp.sum(jnp.diff(cells(t), axis=-1) ** 2, axis=(-2, -1))

    return forward, adjoint, blockwise(update), blockwise(inverse), gram2, smoothness


def _scaled(data, weight, beta):
    """Per-pixel scale: the objective at (s x; s y, β) is s² times the one at (x; y, β/s)."""
    scale = jnp.max(jnp.abs(data) * weight, axis=-1, keepdims=True)
    scale = jnp.where(scale > 0, scale, 1.0)
    return data / scale, beta / scale, scale


def _objective(forward, smoothness, y, weight, b_pixel, alpha, t):
    """Each pixel's objective on the scaled data (float32 arithmetic)."""
    return _sq((forward(t) - y) * weight) + alpha * smoothness(t) + b_pixel[:, 0] * jnp.sum(t, axis=-1)


def _rhs(forward, adjoint, y, weight, two_aty, z, masked: bool):
    """2Aᵀỹ; with masked frames by majorisation: masked frames observe the current prediction."""
    if masked:
        return 2.0 * adjoint(weight * y + (1 - weight) * forward(z))
    return two_aty


def _in_chunks(fn, rows: int, *arrays):
    """``fn`` over ``rows``-row chunks of the (P, …) arrays (``lax.map``; the last chunk padded with zero rows).

    On a whole pool (P = 16384, K = 128: 8 MB per array) every elementwise pass streams from memory; on
    chunks of the batch size the temporaries stay in cache (start and polish ~3× cheaper).
    """
    p = arrays[0].shape[0]
    if p <= rows:
        return fn(*arrays)
    count = -(-p // rows)
    chunks = tuple(jnp.pad(a, [(0, count * rows - p)] + [(0, 0)] * (a.ndim - 1)).reshape(count, rows, *a.shape[1:])
                   for a in arrays)
    out = jax.lax.map(lambda xs: fn(*xs), chunks)
    return jax.tree.map(lambda o: o.reshape(count * rows, *o.shape[2:])[:p], out)


@partial(jax.jit, static_argnames=("kind", "masked", "chunk"))
def _start(arrays, alpha, beta, data, weight, *, kind: str, masked: bool, chunk: int):
    """(scaled data, weight, 2Aᵀwy, β per pixel), scale and the warm start. The warm start is the unconstrained
    minimiser (2G)⁺(2Aᵀỹ − β), clipped (worth ~5× fewer iterations on Fig. 38-like pixels), or, where its
    objective is over twice as high, the same with β through the ρ-damped (2G + ρI)⁻¹. Along G's weak directions (those
    only α holds, e.g. a u-cell no line separates from its neighbour in the full transport) (2G)⁺β is huge
    (1e5 on the Fig. 39 sweep) while Aᵀy has no component there: that start left every pixel unconverged."""
    forward, adjoint, apply_update, apply_inverse, _, smoothness = _operators(kind, arrays, alpha)

    def rows(data, weight):
        y, b_pixel, scale = _scaled(data, weight, beta)
        two_aty = 2.0 * adjoint(weight * y)
        least_squares = apply_inverse(_rhs(forward, adjoint, y, weight, two_aty, jnp.zeros_like(two_aty), masked))
        # β is the same on every offset: M(β 1) = β (M 1), one row for all pixels instead of two products
        ones = jnp.ones((1, two_aty.shape[1]), two_aty.dtype)
        exact, damped = (jnp.maximum(least_squares - b_pixel * apply(ones), 0.0)
                         for apply in (apply_inverse, apply_update))
        objective = partial(_objective, forward, smoothness, y, weight, b_pixel, alpha)
        z0 = jnp.where((objective(exact) <= 2.0 * objective(damped))[:, None], exact, damped)
        return (y, weight, two_aty, b_pixel), scale, z0

    return _in_chunks(rows, chunk, data, weight)


def _admm_block(kind, arrays, rho, alpha, tol, max_iter, *, check_every: int, masked: bool):
    """One block of ``check_every`` ADMM iterations: (rows, state, iters, done, age) → (state, iters, done, age).

    Goldstein et al.'s fast ADMM with restart, per pixel: Nesterov momentum on (Z, U) while the combined
    residual c falls by the factor η, else back to the last iterate without momentum. Only the four (P, K)
    iterates are carried (the loop is memory-bound between the products); the residuals are formed on the
    last iteration of each block. ``age`` counts each pixel's own iterations (the pixels of a refilled batch
    started at different times); a pixel converges at the first check where its residuals meet ``tol``
    within ``max_iter`` (rounded up to a whole block).
    """
    forward, adjoint, apply_update, *_ = _operators(kind, arrays, alpha)
    eta = jnp.asarray(0.999, tol.dtype)

    def step(rows, state, check=False):
        y, weight, two_aty, b_pixel = rows
        z_hat, u_hat, z_old, u_old, momentum, c_old = state
        x = apply_update(_rhs(forward, adjoint, y, weight, two_aty, z_hat, masked) + rho * (z_hat - u_hat))
        z = jnp.maximum(x + u_hat - b_pixel / rho, 0.0)
        u = u_hat + x - z
        c = _sq(u - u_hat)[:, None] + _sq(z - z_hat)[:, None]
        ok = c < eta * c_old
        grown = jnp.where(ok, (1 + jnp.sqrt(1 + 4 * momentum * momentum)) / 2, 1.0)
        weight_m = jnp.where(ok, (momentum - 1) / grown, 0.0)
        new = (jnp.where(ok, z + weight_m * (z - z_old), z_old), jnp.where(ok, u + weight_m * (u - u_old), u_old),
               jnp.where(ok, z, z_old), jnp.where(ok, u, u_old), grown, jnp.where(ok, c, c_old / eta))
        if not check:
            return new
        primal = jnp.sqrt(_sq(x - z))
        dual = rho * jnp.sqrt(_sq(z - z_old))
        size = jnp.maximum(jnp.sqrt(jnp.maximum(_sq(x), _sq(z))), 1e-6)
        now = (primal <= tol * size) & (dual <= tol * jnp.maximum(rho * jnp.sqrt(_sq(u)), 1e-6))
        return new, now

    def block(rows, state, iters, done, age):
        state = jax.lax.fori_loop(0, check_every - 1, lambda _, s: step(rows, s), state)
        state, now = step(rows, state, check=True)
        age = age + check_every
        now = now & (age < max_iter + check_every)
        iters = jnp.where(done | ~now, iters, age)
        return state, iters, done | now, age

    return block


def _alive(done, age, max_iter):
    """The pixels still iterating: not converged and under the cap."""
    return ~done & (age < max_iter)


@partial(jax.jit, static_argnames=("kind", "check_every", "masked"), donate_argnames=("state", "iters", "done", "age"))
def _iterate(arrays, rho, alpha, rows, state, iters, done, age, stop_at, tol, max_iter, *, kind: str,
             check_every: int, masked: bool):
    """ADMM blocks on one batch until at most ``stop_at`` of its pixels are alive."""
    block = _admm_block(kind, arrays, rho, alpha, tol, max_iter, check_every=check_every, masked=masked)

    def keep_going(carry):
        return jnp.sum(_alive(carry[2], carry[3], max_iter)) > stop_at

    return jax.lax.while_loop(keep_going, lambda carry: block(rows, *carry), (state, iters, done, age))


def _fresh(pool, z0, index):
    """The pool's rows and a first ADMM state (the warm start, no momentum) for the pixels ``index``."""
    z = z0[index]
    u = jnp.zeros_like(z)
    ones = jnp.ones((z.shape[0], 1), z.dtype)
    return tuple(a[index] for a in pool), (z, u, z, u, ones, jnp.full_like(ones, jnp.inf))


@partial(jax.jit, static_argnames=("kind", "check_every", "masked", "slots"))
def _stream(arrays, rho, alpha, pool, z0, tol, max_iter, *, kind: str, check_every: int, masked: bool, slots: int):
    """Every pixel of the pool through one batch of ``slots`` rows, refilled as its pixels finish.

    A batch iterated to the end runs as long as its slowest pixel while most converge in a fraction of that
    (on the benchmark's stack: median 20 iterations, a batch's slowest 40–200). So after each block the
    finished rows (converged or at the cap) are written out and refilled with the pool's next pixels: each
    pixel costs about its own iterations and the products stay full-sized. Returns once the pool is
    exhausted and at most 1/COMPACTION of the batch is alive: the batch (pixel index, P for an empty row;
    rows, state, iters, done, age) and the transport, iterations and flags of the pixels written out so far.
    """
    block = _admm_block(kind, arrays, rho, alpha, tol, max_iter, check_every=check_every, masked=masked)
    p = z0.shape[0]

    def refill(carry):
        pixel, rows, state, iters, done, age, queue, out = carry
        free = ~_alive(done, age, max_iter)
        target = jnp.where(free, pixel, p)  # living rows and empty ones (pixel = P) are dropped
        out = tuple(o.at[target].set(v, mode="drop") for o, v in zip(out, (state[2], iters, done), strict=True))
        new = queue + jnp.cumsum(free) - 1
        take = free & (new < p)
        pixel = jnp.where(take, new, jnp.where(free, p, pixel))
        new_rows, new_state = _fresh(pool, z0, jnp.minimum(new, p - 1))
        rows, state = (tuple(jnp.where(take[:, None], b, a) for a, b in zip(old, fresh, strict=True))
                       for old, fresh in ((rows, new_rows), (state, new_state)))
        iters, done, age = jnp.where(take, max_iter, iters), done & ~take, jnp.where(take, 0, age)
        return pixel, rows, state, iters, done, age, queue + jnp.sum(take), out

    def body(carry):
        pixel, rows, state, iters, done, age, queue, out = carry
        state, iters, done, age = block(rows, state, iters, done, age)
        return jax.lax.cond(queue < p, refill, lambda c: c, (pixel, rows, state, iters, done, age, queue, out))

    def keep_going(carry):
        pixel, _, _, _, done, age, queue, _ = carry
        return (queue < p) | (jnp.sum(_alive(done, age, max_iter) & (pixel < p)) > _stop_at(slots))

    pixel = jnp.arange(slots)
    rows, state = _fresh(pool, z0, pixel)
    out = (jnp.zeros_like(z0), jnp.full((p,), max_iter, jnp.int32), jnp.zeros((p,), bool))
    batch = (jnp.full((slots,), max_iter, jnp.int32), jnp.zeros((slots,), bool), jnp.zeros((slots,), jnp.int32))
    return jax.lax.while_loop(keep_going, body, (pixel, rows, state, *batch, jnp.asarray(slots, pixel.dtype), out))


@partial(jax.jit, static_argnames=("kind", "polish_iter", "masked", "chunk"))
def _finish(arrays, alpha, y, weight, two_aty, b_pixel, scale, z, *, kind: str, polish_iter: int, masked: bool,
            chunk: int):
    """The polish (conjugate gradients on the free offsets' KKT system, kept where it lowers the objective), then
    T and its objective back in the data's units."""
    return _in_chunks(partial(_finish_rows, arrays, alpha, kind=kind, polish_iter=polish_iter, masked=masked),
                      chunk, y, weight, two_aty, b_pixel, scale, z)


def _finish_rows(arrays, alpha, y, weight, two_aty, b_pixel, scale, z, *, kind: str, polish_iter: int, masked: bool):
    forward, adjoint, _, _, apply_gram2, smoothness = _operators(kind, arrays, alpha)
    dtype = y.dtype

    objective = partial(_objective, forward, smoothness, y, weight, b_pixel, alpha)
    if polish_iter:
        free = (z > 0).astype(dtype)
        target = free * (0.5 * _rhs(forward, adjoint, y, weight, two_aty, z, masked) - b_pixel / 2)

        def mv(v):
            return free * apply_gram2(v) / 2

        r0 = target - mv(z)

        def cg(_, s):
            x, r, d, rs = s
            ad = mv(d)
            step_len = rs / jnp.maximum(jnp.sum(d * ad, -1, keepdims=True), jnp.finfo(dtype).tiny)
            x, r = x + step_len * d, r - step_len * ad
            rs_new = jnp.sum(r * r, -1, keepdims=True)
            d = r + rs_new / jnp.maximum(rs, jnp.finfo(dtype).tiny) * d
            return x, r, d, rs_new

        polished, *_ = jax.lax.fori_loop(0, polish_iter, cg, (z, r0, r0, jnp.sum(r0 * r0, -1, keepdims=True)))
        polished = jnp.maximum(jnp.where(jnp.all(jnp.isfinite(polished), -1, keepdims=True), polished, z), 0.0)
        value, before = objective(polished), objective(z)
        better = value < before
        z, value = jnp.where(better[:, None], polished, z), jnp.where(better, value, before)
    else:
        value = objective(z)
    return z * scale, value * scale[:, 0] ** 2


#: elements (pixels × offsets) of the batch the pixels stream through: its (P × K) iterates stay in cache
BATCH_ELEMENTS = 1024 * 128


def batch_slots(offsets: int) -> int:
    """Rows of the streaming batch for K offsets: a power of two near BATCH_ELEMENTS / K, within [64, 16384]."""
    return int(np.clip(2 ** np.round(np.log2(BATCH_ELEMENTS / max(offsets, 1))), 64, 16384))


#: the smallest batch the active set is compacted into (below it a call's fixed cost dominates)
MIN_BATCH = 64


#: the factor a batch's tail shrinks by between compactions: each batch size compiles once per process (~0.5 s),
#: so a factor of 4 (1024 → 256 → 64) halves the compiles of a factor of 2 for a little more tail iteration
COMPACTION = 4


def _stop_at(size: int) -> int:
    """Unconverged pixels at which a batch of ``size`` is compacted (never below MIN_BATCH: run to the end)."""
    return size // COMPACTION if size > MIN_BATCH else 0


def _batch_size(active: int) -> int:
    """The batch the unconverged pixels are packed into: MIN_BATCH times a power of COMPACTION."""
    size = MIN_BATCH
    while size < active:
        size *= COMPACTION
    return size


def _solve(arrays, rho, alpha, beta, data, weight, tol, *, kind: str, max_iter: int, check_every: int,
           polish_iter: int, masked: bool, slots: int):
    """Start, stream the pixels through a batch of ``slots`` (:func:`_stream`), compact its tail, finish.

    Once the pool is exhausted the batch's living pixels are gathered into a batch COMPACTION times smaller
    each time all but 1/COMPACTION of them have converged, and iterated on alone (each size compiles once).
    """
    p = data.shape[0]
    slots = min(slots, p)
    pool, scale, z0 = _start(arrays, alpha, beta, data, weight, kind=kind, masked=masked, chunk=slots)
    options = {"kind": kind, "check_every": check_every, "masked": masked}
    limits = (tol, jnp.asarray(max_iter, jnp.int32))
    pixel, rows, state, iters, done, age, _, out = _stream(arrays, rho, alpha, pool, z0, *limits, slots=slots,
                                                           **options)
    # the tail, in numpy between the jitted calls (index bookkeeping no jit does cheaply)
    pixel, iters, done, age = (np.array(a) for a in (pixel, iters, done, age))
    state, rows = [np.array(a) for a in state], [np.asarray(a) for a in rows]
    index = np.flatnonzero(_alive(done, age, max_iter) & (pixel < p))
    while index.size:
        n = index.size
        size = _batch_size(n)
        padded = np.concatenate([index, np.full(size - n, index[0])])
        pad_done = np.arange(size) >= n  # padding rows count as converged and are never written back
        part_state, part_iters, part_done, part_age = _iterate(
            arrays, rho, alpha, tuple(a[padded] for a in rows), tuple(a[padded] for a in state), iters[padded],
            done[padded] | pad_done, age[padded], jnp.asarray(_stop_at(size), jnp.int32), *limits, **options)
        for full, part in zip(state, part_state, strict=True):
            full[index] = np.asarray(part)[:n]
        iters[index], done[index], age[index] = (np.asarray(a)[:n] for a in (part_iters, part_done, part_age))
        index = index[_alive(done[index], age[index], max_iter)]
    held = pixel < p
    z_out, iters_out, done_out = (np.array(a) for a in out)
    z_out[pixel[held]], iters_out[pixel[held]], done_out[pixel[held]] = state[2][held], iters[held], done[held]
    transport, objective = _finish(arrays, alpha, *pool, scale, jnp.asarray(z_out), kind=kind,
                                   polish_iter=polish_iter, masked=masked, chunk=slots)
    return transport, iters_out, done_out, objective


def observed(data: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """(P, N) bool: the observations that count, finite and (where ``weight`` is given) of weight > 0."""
    finite = np.isfinite(data)
    return finite if weight is None else (np.asarray(weight) > 0) & finite


def solve(problem: DemuxProblem | SeparableDemuxProblem, data: np.ndarray, weight: np.ndarray | None = None, *,
          tol: float = 1e-3, max_iter: int = 200, check_every: int = 5, polish_iter: int = 20,
          slots: int | None = None, dtype=np.float32) -> DemuxResult:
    """Solve every pixel's problem: ``data`` (P, N) observations, ``weight`` (P, N) 0/1 (None: all 1).

    The pixels stream through a batch of ``slots`` rows (None: :func:`batch_slots`). Non-finite observations
    are masked whatever ``weight`` says. float64 needs ``jax.enable_x64``.
    """
    data = np.asarray(data)
    if data.ndim != 2 or data.shape[1] != problem.frames:
        raise ValueError(f"data is {data.shape}; expected (pixels, {problem.frames} frames)")
    weight = observed(data, weight)
    masked = not bool(weight.all())
    jdtype = jnp.dtype(dtype)
    if jdtype == jnp.float64 and not jax.config.jax_enable_x64:
        raise ValueError("float64 demultiplexing needs x64: call inside `with jax.enable_x64(True):`")
    cast = partial(jnp.asarray, dtype=jdtype)
    z, iters, done, objective = _solve(
        tuple(cast(m) for m in problem.arrays()), cast(problem.rho), cast(problem.alpha), cast(problem.beta),
        cast(np.where(weight, data, 0.0)), cast(weight), cast(tol), kind=problem.kind, max_iter=int(max_iter),
        check_every=int(check_every), polish_iter=int(polish_iter), masked=masked,
        slots=int(slots or batch_slots(problem.offsets)))
    return DemuxResult(np.asarray(z), np.asarray(iters), np.asarray(done), np.asarray(objective))
