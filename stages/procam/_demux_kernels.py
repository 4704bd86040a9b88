"""The jitted kernels of :class:`selpath.stages.procam._demux_solver.DemuxADMM` (the method is described there).

JAX needs pure functions, so the iteration lives here as functions of few arguments: the problem's
operators (a :class:`~selpath.stages.procam._demux_problem.DenseOperators` or
:class:`~selpath.stages.procam._demux_problem.KroneckerOperators` pytree: its type picks the code path), the stopping
limits (:class:`Limits`), the per-pixel rows (:class:`Rows`) and the iterates (:class:`State`,
:class:`Batch`), with the few static settings (``check_every``, ``masked``, batch sizes) as keywords.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from selpath.stages.procam._demux_certificate import DUAL_SEARCH_STEPS, KKT_HELD, first_order_gap, kkt_gap
from selpath.stages.procam._demux_problem import _sq


class Limits(NamedTuple):
    """When a pixel stops: relative residual ``tol`` (solver dtype) and the cap ``max_iter`` (int32)."""

    tol: jnp.ndarray
    max_iter: jnp.ndarray


class Rows(NamedTuple):
    """Per pixel, on the scaled data: observations y, 0/1 weights, 0/1 clipped (y is then the clip level: the
    frame's light is at least y), 2Aᵀwy and β/scale (P, 1)."""

    y: jnp.ndarray
    weight: jnp.ndarray
    clipped: jnp.ndarray
    two_aty: jnp.ndarray
    beta: jnp.ndarray


class State(NamedTuple):
    """Fast ADMM's iterates per pixel: the extrapolated (Ẑ, Û), the last accepted (Z, U), the momentum and the
    combined residual c of the last accepted step."""

    z_hat: jnp.ndarray
    u_hat: jnp.ndarray
    z: jnp.ndarray
    u: jnp.ndarray
    momentum: jnp.ndarray
    residual: jnp.ndarray


class Batch(NamedTuple):
    """A batch of pixels being iterated: their state, iterations to convergence, flags and own ages."""

    state: State
    iters: jnp.ndarray
    done: jnp.ndarray
    age: jnp.ndarray


def _scaled(data, weight, beta):
    """Per-pixel scale: the objective at (s x; s y, β) is s² times the one at (x; y, β/s)."""
    scale = jnp.max(jnp.abs(data) * weight, axis=-1, keepdims=True)
    scale = jnp.where(scale > 0, scale, 1.0)
    return data / scale, beta / scale, scale


def _target(rows: Rows, prediction):
    """What each frame's prediction is pulled to: y; on a clipped frame max(y, prediction), so only a prediction
    below the clip level costs (the one-sided penalty max(0, y − AT)²)."""
    return jnp.where(rows.clipped > 0, jnp.maximum(rows.y, prediction), rows.y)


def _residual(ops, rows: Rows, t):
    """w(AT − ỹ(T)) per frame: the data term's residual (on a clipped frame min(0, AT − y))."""
    prediction = ops.forward(t)
    return (prediction - _target(rows, prediction)) * rows.weight


def _objective(ops, rows: Rows, t):
    """Each pixel's objective on the scaled data (float32 arithmetic)."""
    return _sq(_residual(ops, rows, t)) + ops.alpha * ops.smoothness(t) + rows.beta[:, 0] * jnp.sum(t, axis=-1)


def _rhs(ops, rows: Rows, z, masked: bool):
    """2Aᵀỹ; by majorisation where any frame is masked or clipped (``masked``): a masked frame observes the current
    prediction AZ, a clipped one max(y, AZ). Both quadratics touch their term at Z and lie above it (a masked
    frame's term is 0; a clipped one's is the convex, C¹ max(0, y − AT)²), so the fixed points are exactly the
    optima of the problem with masked frames left out and clipped ones as one-sided penalties."""
    if masked:
        prediction = ops.forward(z)
        return 2.0 * ops.adjoint(rows.weight * _target(rows, prediction) + (1 - rows.weight) * prediction)
    return rows.two_aty


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


@partial(jax.jit, static_argnames=("masked", "chunk"))
def start(ops, data, weight, clipped, *, masked: bool, chunk: int):
    """(the pool's :class:`Rows`, scale, the warm start). The warm start is the unconstrained minimiser
    (2G)⁺(2Aᵀỹ − β), clipped (worth ~5× fewer iterations on Fig. 38-like pixels), or, where its objective is
    over twice as high, the same with β through the ρ-damped (2G + ρI)⁻¹. Along G's weak directions (those
    only α holds, e.g. a u-cell no line separates from its neighbour in the full transport) (2G)⁺β is huge
    (1e5 on the Fig. 39 sweep) while Aᵀy has no component there: that start left every pixel unconverged."""

    def rows_of(data, weight, clipped):
        y, b_pixel, scale = _scaled(data, weight, ops.beta)
        two_aty = 2.0 * ops.adjoint(weight * y)
        rows = Rows(y, weight, clipped, two_aty, b_pixel)
        least_squares = ops.inverse(_rhs(ops, rows, jnp.zeros_like(two_aty), masked))
        # β is the same on every offset: M(β 1) = β (M 1), one row for all pixels instead of two products
        ones = jnp.ones((1, two_aty.shape[1]), two_aty.dtype)
        exact, damped = (jnp.maximum(least_squares - b_pixel * apply(ones), 0.0) for apply in (ops.inverse, ops.update))
        value_exact, value_damped = _objective(ops, rows, exact), _objective(ops, rows, damped)
        chosen = value_exact <= 2.0 * value_damped
        z0 = jnp.where(chosen[:, None], exact, damped)
        # never start worse than T = 0 (objective Σ w ỹ(0)², no product): in float32, (2G)⁺ along weak directions
        # can be large enough (1.6e10 on a sweep of wide lines with fewer lines than u-cells) that both starts are
        # rounding noise of size 1e5, from which ADMM settled at T = 0, flagged converged
        at_zero = _sq(rows.weight * _target(rows, jnp.zeros_like(rows.y)))
        z0 = jnp.where((jnp.where(chosen, value_exact, value_damped) <= at_zero)[:, None], z0, 0.0)
        return rows, scale, z0

    return _in_chunks(rows_of, chunk, data, weight, clipped)


def _admm_block(ops, limits: Limits, *, check_every: int, masked: bool):
    """One block of ``check_every`` ADMM iterations: (rows, batch) → batch.

    Goldstein et al.'s fast ADMM with restart, per pixel: Nesterov momentum on (Z, U) while the combined
    residual c falls by the factor η, else back to the last iterate without momentum. Only the four (P, K)
    iterates are carried (the loop is memory-bound between the products); the residuals are formed on the
    last iteration of each block. ``age`` counts each pixel's own iterations (the pixels of a refilled batch
    started at different times); a pixel converges at the first check where its residuals meet ``tol``
    within ``max_iter`` (rounded up to a whole block).
    """
    rho, tol = ops.rho, limits.tol
    eta = jnp.asarray(0.999, tol.dtype)

    def step(rows: Rows, state: State, check=False):
        z_hat, u_hat, z_old, u_old, momentum, c_old = state
        x = ops.update(_rhs(ops, rows, z_hat, masked) + rho * (z_hat - u_hat))
        z = jnp.maximum(x + u_hat - rows.beta / rho, 0.0)
        u = u_hat + x - z
        c = _sq(u - u_hat)[:, None] + _sq(z - z_hat)[:, None]
        ok = c < eta * c_old
        grown = jnp.where(ok, (1 + jnp.sqrt(1 + 4 * momentum * momentum)) / 2, 1.0)
        weight_m = jnp.where(ok, (momentum - 1) / grown, 0.0)
        new = State(jnp.where(ok, z + weight_m * (z - z_old), z_old), jnp.where(ok, u + weight_m * (u - u_old), u_old),
                    jnp.where(ok, z, z_old), jnp.where(ok, u, u_old), grown, jnp.where(ok, c, c_old / eta))
        if not check:
            return new
        primal = jnp.sqrt(_sq(x - z))
        dual = rho * jnp.sqrt(_sq(z - z_old))
        size = jnp.maximum(jnp.sqrt(jnp.maximum(_sq(x), _sq(z))), 1e-6)
        now = (primal <= tol * size) & (dual <= tol * jnp.maximum(rho * jnp.sqrt(_sq(u)), 1e-6))
        return new, now

    def block(rows: Rows, batch: Batch) -> Batch:
        state = jax.lax.fori_loop(0, check_every - 1, lambda _, s: step(rows, s), batch.state)
        state, now = step(rows, state, check=True)
        age = batch.age + check_every
        now = now & (age < limits.max_iter + check_every)
        iters = jnp.where(batch.done | ~now, batch.iters, age)
        return Batch(state, iters, batch.done | now, age)

    return block


def alive(done, age, max_iter):
    """The pixels still iterating: not converged and under the cap."""
    return ~done & (age < max_iter)


@partial(jax.jit, static_argnames=("check_every", "masked"), donate_argnames=("batch",))
def iterate(ops, limits: Limits, rows: Rows, batch: Batch, stop_at, *, check_every: int, masked: bool) -> Batch:
    """ADMM blocks on one batch until at most ``stop_at`` of its pixels are alive."""
    block = _admm_block(ops, limits, check_every=check_every, masked=masked)

    def keep_going(batch):
        return jnp.sum(alive(batch.done, batch.age, limits.max_iter)) > stop_at

    return jax.lax.while_loop(keep_going, lambda batch: block(rows, batch), batch)


def _fresh(pool: Rows, z0, index) -> tuple[Rows, State]:
    """The pool's rows and a first ADMM state (the warm start, no momentum) for the pixels ``index``."""
    z = z0[index]
    u = jnp.zeros_like(z)
    ones = jnp.ones((z.shape[0], 1), z.dtype)
    return Rows(*(a[index] for a in pool)), State(z, u, z, u, ones, jnp.full_like(ones, jnp.inf))


#: the smallest batch the active set is compacted into (below it a call's fixed cost dominates)
MIN_BATCH = 64


#: the factor a batch's tail shrinks by between compactions: each batch size compiles once per process (~0.5 s),
#: so a factor of 4 (1024 → 256 → 64) halves the compiles of a factor of 2 for a little more tail iteration
COMPACTION = 4


def compact_at(size: int) -> int:
    """Unconverged pixels at which a batch of ``size`` is compacted (never below MIN_BATCH: run to the end)."""
    return size // COMPACTION if size > MIN_BATCH else 0


@partial(jax.jit, static_argnames=("check_every", "masked", "slots"))
def stream(ops, limits: Limits, pool: Rows, z0, live, *, check_every: int, masked: bool, slots: int):
    """Every pixel of the pool through one batch of ``slots`` rows, refilled as its pixels finish.

    A batch iterated to the end runs as long as its slowest pixel while most converge in a fraction of that
    (on the benchmark's stack: median 20 iterations, a batch's slowest 40–200). So after each block the
    finished rows (converged or at the cap) are written out and refilled with the pool's next pixels: each
    pixel costs about its own iterations and the products stay full-sized. Returns once the pool is
    exhausted and at most 1/COMPACTION of the batch is alive: (pixel index per row, P for an empty row; the
    rows; the :class:`Batch`; the queue position; the transport, iterations and flags written out so far).
    Only the pool's first ``live`` pixels (a traced int: no recompile) are iterated; the rest were certified
    optimal at their warm start (:func:`gaps`) and are left to the caller.
    """
    block = _admm_block(ops, limits, check_every=check_every, masked=masked)
    p, max_iter = z0.shape[0], limits.max_iter

    def refill(carry):
        pixel, rows, batch, queue, out = carry
        free = ~alive(batch.done, batch.age, max_iter)
        target = jnp.where(free, pixel, p)  # living rows and empty ones (pixel = P) are dropped
        out = tuple(o.at[target].set(v, mode="drop")
                    for o, v in zip(out, (batch.state.z, batch.iters, batch.done), strict=True))
        new = queue + jnp.cumsum(free) - 1
        take = free & (new < live)
        pixel = jnp.where(take, new, jnp.where(free, p, pixel))
        new_rows, new_state = _fresh(pool, z0, jnp.minimum(new, p - 1))
        rows, state = (jax.tree.map(lambda a, b: jnp.where(take[:, None], b, a), old, fresh)
                       for old, fresh in ((rows, new_rows), (batch.state, new_state)))
        batch = Batch(state, jnp.where(take, max_iter, batch.iters), batch.done & ~take, jnp.where(take, 0, batch.age))
        return pixel, rows, batch, queue + jnp.sum(take), out

    def body(carry):
        pixel, rows, batch, queue, out = carry
        batch = block(rows, batch)
        return jax.lax.cond(queue < live, refill, lambda c: c, (pixel, rows, batch, queue, out))

    def keep_going(carry):
        pixel, _, batch, queue, _ = carry
        return (queue < live) | (jnp.sum(alive(batch.done, batch.age, max_iter) & (pixel < p)) > compact_at(slots))

    first = jnp.arange(slots)
    rows, state = _fresh(pool, z0, first)
    pixel = jnp.where(first < live, first, p)  # rows past the live pixels start empty, counted as done
    out = (jnp.zeros_like(z0), jnp.full((p,), max_iter, jnp.int32), jnp.zeros((p,), bool))
    batch = Batch(state, jnp.full((slots,), max_iter, jnp.int32), first >= live, jnp.zeros((slots,), jnp.int32))
    return jax.lax.while_loop(keep_going, body, (pixel, rows, batch, jnp.asarray(slots, pixel.dtype), out))


@partial(jax.jit, static_argnames=("polish_iter", "polish_rounds", "dual_steps", "masked", "chunk"))
def finish(ops, pool: Rows, scale, z, *, polish_iter: int, polish_rounds: int, dual_steps: int, masked: bool,
           chunk: int):
    """The polish (conjugate gradients on the free offsets' KKT system, kept where it lowers the objective; after
    the first round, offsets held at 0 whose gradient is negative are freed too), then T, its objective in the
    data's units and the certified gap bound (with ``dual_steps`` of the KKT bound's dual ascent)."""

    def rows_of(y, weight, clipped, two_aty, b_pixel, scale, z):
        return _finish_rows(ops, Rows(y, weight, clipped, two_aty, b_pixel), scale, z, polish_iter=polish_iter,
                            polish_rounds=polish_rounds, dual_steps=dual_steps, masked=masked)

    return _in_chunks(rows_of, chunk, *pool, scale, z)


#: the start's certificate: the KKT bound with one share (offsets at exactly 0 held) and the dual point of the
#: gradients themselves (no search). Both are exact (0 up to rounding) at an optimum, which is all the start asks:
#: whether a warm start (T = 0 under a β that outweighs the light; a non-negative unconstrained minimiser) is
#: optimal already; at a third of the full bound's cost
START_SEARCH_STEPS, START_SHARES = 0, (0.0,)


@partial(jax.jit, static_argnames=("chunk", "masked"))
def gaps(ops, pool: Rows, z, *, chunk: int, masked: bool):
    """:func:`scaled_gap` of every pixel of the pool at its warm start ``z`` with :data:`START_SEARCH_STEPS` and
    :data:`START_SHARES`: a pixel certified there needs no iteration."""
    return _in_chunks(lambda *a: scaled_gap(ops, Rows(*a[:-1]), a[-1], masked=masked, steps=START_SEARCH_STEPS,
                                            shares=START_SHARES), chunk, *pool, z)


def scaled_gap(ops, rows: Rows, t, *, masked: bool, steps: int = DUAL_SEARCH_STEPS, shares=KKT_HELD,
               dual_steps: int = 0):
    """:func:`selpath.stages.procam._demux_certificate.certified_gap` (the methods and their proofs are there: the
    first-order bound through the same :func:`~selpath.stages.procam._demux_certificate.first_order_gap`, and for
    dense problems on fully observed, unclipped pixels the smaller KKT bound) on the scaled data,
    in the solver's dtype, with ``steps`` of the dual search and the KKT bound's ``shares``: about as much as two
    to four iterations; and ``dual_steps`` of the KKT bound's dual ascent, one K × K product each. Where no frame
    of the call is masked or clipped (``masked`` False) every frame is in the dual's shift, whose Aᵀe is then one
    row for all pixels. In float32 it is a bound up to rounding (within 15 %
    or 1e-4 of the float64 reference on the solver's tests, where the bound lies at 1e-5 to 3e-3: the most negative
    gradient entry decides it and carries float32 rounding)."""
    prediction = ops.forward(t)
    target = _target(rows, prediction) if masked else rows.y
    residual = (prediction - target) * rows.weight if masked else prediction - target
    beta = rows.beta[:, 0]
    if masked:
        e = rows.weight * (1.0 - rows.clipped) * jnp.ones_like(residual)  # observed unclipped (flags may broadcast)
        first_order, z, primal = first_order_gap(jnp, ops, t, residual, target, beta, e, steps=steps)
        applies = jnp.all(e > 0, axis=-1)
    else:  # every frame observed and unclipped: e = 1
        first_order, z, primal = first_order_gap(jnp, ops, t, residual, target, beta, steps=steps)
        applies = jnp.ones(beta.shape, bool)
    if not ops.SECOND_ORDER:  # the separable problem keeps the first-order bound only
        return first_order
    return jnp.minimum(first_order, kkt_gap(jnp, t, z + rows.beta, lambda d: jnp.sum(d * ops.inverse(d), axis=-1),
                                            primal, applies & (ops.definite > 0), shares, inverse=ops.inverse,
                                            step=ops.dual_step, steps=dual_steps))


def _gradient(ops, rows: Rows, t):
    """∇f(T) per pixel on the scaled data: 2Aᵀ(w(AT − ỹ(T))) + 2αDᵀDT + β."""
    return ops.adjoint(2.0 * _residual(ops, rows, t)) + 2.0 * ops.alpha * ops.smooth_gradient(t) + rows.beta


def _polish(ops, rows: Rows, z, before, free, *, polish_iter: int, masked: bool):
    """Conjugate gradients on the KKT system of the offsets in ``free`` (the others held at 0), from z (whose
    objective is ``before``); the result clipped at 0 and kept per pixel only where it lowers the objective."""
    dtype = rows.y.dtype
    objective = partial(_objective, ops, rows)
    target = free * (0.5 * _rhs(ops, rows, z, masked) - rows.beta / 2)

    def mv(v):
        return free * ops.gram2(v) / 2

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
    value = objective(polished)
    better = value < before
    return jnp.where(better[:, None], polished, z), jnp.where(better, value, before)


def _finish_rows(ops, rows: Rows, scale, z, *, polish_iter: int, polish_rounds: int, dual_steps: int,
                 masked: bool):
    dtype = rows.y.dtype
    value = _objective(ops, rows, z)
    if polish_iter:
        for round_ in range(polish_rounds):
            free = z > 0
            if round_:  # an offset held at 0 whose gradient is negative would lower f: free it (an active-set step)
                free = free | (_gradient(ops, rows, z) < 0)
            z, value = _polish(ops, rows, z, value, free.astype(dtype), polish_iter=polish_iter, masked=masked)
    return z * scale, value * scale[:, 0] ** 2, scaled_gap(ops, rows, z, masked=masked, dual_steps=dual_steps)
