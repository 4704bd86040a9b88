"""Batched non-negative, smooth and sparse deconvolution with one shared illumination matrix (§5.2.2, §5.3.1).

Every pixel p solves the thesis's problem

    min_T  Σ_i w_pi (A T − y_p)_i² + α ‖D T‖² + β 1ᵀT   subject to  T ≥ 0,

with A (N frames × K offsets) the same for all pixels and w_pi ∈ {0, 1} masking non-finite frames; a clipped
frame (its observation the clip level y) enters as the one-sided max(0, y − A_i T)² instead: its light is at least
y, so the problem stays a convex QP and T is never pulled below what the clipped frames prove.

No library solves millions of small QPs that share a Hessian as one matrix–matrix product per iteration
(CVXPY/Clarabel factorise each problem; optimistix has no bound constraints, DESIGN §6), so this is a batched
ADMM in plain JAX (kernels in :mod:`selpath.stages.procam._demux_kernels`):

* splitting T = Z, Z ≥ 0 carrying the L1 term: the T-update is one shared (2G + ρI)⁻¹, G = AᵀA + αDᵀD, so P
  pixels cost one (P × K)·(K × K) product per iteration; the Z-update max(0, · − β/ρ) is exact;
* a warm start at the unconstrained minimiser clipped at 0, and fast ADMM with restart (Goldstein et al.);
* masked and clipped frames by majorisation (ỹ = w y + (1 − w) A Z; max(y, A Z) on clipped frames), whose fixed
  points are exactly the optima of the problem with masked frames left out and clipped ones one-sided;
* each pixel scaled by its largest observation (β with it), so data from 1e-8 to 1e8 run in float32;
* a final polish (conjugate gradients on the support's KKT system, ``polish_rounds`` of them with active-set
  steps), kept per pixel only where it lowers the objective;
* a certificate beside the answer (:func:`~selpath.stages.procam._demux_kernels.scaled_gap`; the float64
  reference :func:`~selpath.stages.procam._demux_certificate.certified_gap`): a bound on each pixel's relative
  objective gap from weak duality, and where the problem has the second-order bound
  (``problem.second_order_bound``) the smaller of it and the KKT bound, tightened by ``dual_steps`` of dual ascent;
  pixels with masked or clipped frames get theirs on the host (:meth:`DemuxADMM._certify_partial`);
* an exact finish (``finish_rounds``, where ``problem.exact_finish``) on the pixels whose bound still exceeds
  ``max_gap``: active-set rounds with float64 solves (:mod:`selpath.stages.procam._demux_finish`).

A call's pixels stream through one batch refilled as they converge or reach ``max_iter``
(:func:`~selpath.stages.procam._demux_kernels.stream`), its tail compacted into smaller batches
(:meth:`DemuxADMM._iterate_tail`), so a call costs its pixels' mean iterations, not its slowest pixel's.
:class:`DemuxADMM` returns a :class:`selpath.stages._solution.Solution`: the transport, a result code per pixel
(converged, censored, unproven, max_steps, nonfinite) and ``stats``.

What each design choice and default bought, measured: docs/demux-settings.md.

References
----------
Thesis §5.2.2 (plane-to-ray), §5.3.1 (full transport); T. Goldstein et al., "Fast alternating direction
optimization methods", SIAM J. Imaging Sci. 7 (2014).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selpath.stages._solution import Result, Solution, outcome, raise_if_failed
from selpath.stages.procam import _demux_kernels as kernels
from selpath.stages.procam import _demux_settings as defaults
from selpath.stages.procam._demux_certificate import kkt_bound
from selpath.stages.procam._demux_finish import active_set_finish
from selpath.stages.procam._demux_kernels import MIN_BATCH, Batch, Limits, Rows, State, alive, compact_at
from selpath.stages.procam._demux_problem import DemuxProblem, SeparableDemuxProblem

__all__ = ["CENSORED_SHARE", "MIN_BATCH", "DemuxADMM", "batch_slots", "censored_offsets", "observed",
           "pool_size"]

#: elements (pixels × offsets) of the batch the pixels stream through: its (P × K) iterates stay in cache
BATCH_ELEMENTS = 1024 * 128


def batch_slots(offsets: int) -> int:
    """Rows of the streaming batch for K offsets: a power of two near BATCH_ELEMENTS / K, within [64, 16384]."""
    return int(np.clip(2 ** np.round(np.log2(BATCH_ELEMENTS / max(offsets, 1))), 64, 16384))


def pool_size(pixels: int, slots: int) -> int:
    """The pool a solve of ``pixels`` pixels runs on: a pool smaller than the batch is padded to a power of two
    (at least MIN_BATCH, at most ``slots``), so that pools of 3, 40 or 1900 pixels share their compiled kernels
    (every distinct pool size compiles the start, stream, certificate and finish once: 1–2 s each on a CPU); a
    larger pool runs as it is."""
    if pixels >= slots or pixels == 0:
        return pixels
    return int(min(slots, max(MIN_BATCH, 2 ** int(np.ceil(np.log2(max(pixels, 1)))))))


def _batch_size(active: int) -> int:
    """The batch the unconverged pixels are packed into: MIN_BATCH times a power of COMPACTION."""
    size = MIN_BATCH
    while size < active:
        size *= kernels.COMPACTION
    return size


#: an offset counts as censored only where its light is at least this share of the clip level: offsets that only
#: clipped frames see but that hold (next to) no light are unknown the same way any unlit offset is
CENSORED_SHARE = 0.01


def censored_offsets(problem: DemuxProblem | SeparableDemuxProblem, transport: np.ndarray, data: np.ndarray,
                     weight: np.ndarray, clipped: np.ndarray) -> np.ndarray:
    """Per pixel, the number of offsets whose light is known only as a lower bound: lit (A_ik > 0) by some
    clipped frame, by no usable unclipped one, and holding at least :data:`CENSORED_SHARE` of the pixel's
    lowest clip level. There T is what the clipped frames prove (the one-sided penalty holds AT up to the clip
    level, β pulls no higher), not an estimate. (P,) int32; host-side, two (P × N)·(N × K) products."""
    usable = np.asarray(weight, bool)
    clipped = np.asarray(clipped, bool) & usable
    seen_clipped = problem.lit_by(clipped) > 0
    seen_unclipped = problem.lit_by(usable & ~clipped) > 0
    level = np.min(np.where(clipped, data, np.inf), axis=-1, keepdims=True)
    bright = np.asarray(transport) >= CENSORED_SHARE * level
    return np.sum(seen_clipped & ~seen_unclipped & bright, axis=-1).astype(np.int32)


def observed(data: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """(P, N) bool: the observations that count, finite and (where ``weight`` is given) of weight > 0."""
    finite = np.isfinite(data)
    return finite if weight is None else (np.asarray(weight) > 0) & finite


class _Start(NamedTuple):
    """The warm start of every pixel, in the data's units, its bound and whether it was certified (not iterated)."""

    certified: np.ndarray
    transport: np.ndarray
    gap: np.ndarray


def _host_take(rows: jnp.ndarray, order: np.ndarray) -> jnp.ndarray:
    """``rows[order]`` permuted on the host and put back with ``jax.device_put``: an eager gather on the device, and
    ``jnp.asarray`` of a host array, each compile one program per pool shape."""
    return jax.device_put(np.asarray(rows)[order])


class _Clock:
    """Seconds per phase of one solve (``DemuxADMM(timed=True)``): each timed call waits for its result
    (``jax.block_until_ready``), so a phase's seconds are its own; untimed, a call runs as it is."""

    def __init__(self, on: bool):
        self.on, self.seconds = on, {}

    def __call__(self, label: str, function, *args, **kwargs):
        if not self.on:
            return function(*args, **kwargs)
        start = time.perf_counter()
        result = jax.block_until_ready(function(*args, **kwargs))
        self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - start
        return result


@dataclass(frozen=True)
class DemuxADMM:
    """The batched demultiplexing ADMM: immutable settings; :meth:`solve` returns a :class:`Solution`.

    ``tol``: relative primal and dual residual at which a pixel stops iterating; ``max_iter``: iteration cap;
    ``check_every``: iterations between convergence checks; ``polish_iter``: conjugate-gradient steps of the
    final support polish (0: none); ``polish_rounds``: polish rounds, each after the first with an active-set
    step; ``gap_tol``: the certificate's target: a pixel whose certified relative objective gap is at most this is
    certified, and converged whatever its residuals say (checked at the warm start, where such a pixel is not
    iterated at all, and at the end), and the finish aims at it; ``max_gap`` (≥ ``gap_tol``): the largest certified
    gap a converged pixel may have: a pixel whose bound exceeds it after the solve gets the exact finish, and one
    still above it is ``unproven``: ``converged`` means exactly a proven gap of at most ``max_gap``, whatever the
    residuals said (a pixel at ``max_iter`` whose bound is within it is converged) (1: no cap, no finish: the
    residual test or ``gap_tol``). It applies to dense problems whose 2G is positive definite, where the bound is
    second order in T's KKT residual (:func:`~selpath.stages.procam._demux_certificate.kkt_gap`); elsewhere (the
    Kronecker problem, α = 0 with rank-deficient A) only the first-order bound exists, which an answer short of
    the exact optimum rarely meets: there neither the cap nor the finish runs, and ``converged`` keeps its
    residual meaning;
    ``dual_steps``: projected accelerated gradient steps on the multipliers of the final certificate's KKT bound
    (its dual ascent, :func:`~selpath.stages.procam._demux_certificate.kkt_gap`: one K × K product per pixel each; 0:
    the
    fixed multipliers alone, a bound up to 7× looser at the median and 18× at the p99 on the catalogue);
    ``finish_rounds``: exact active-set rounds (float64 free-set solves, :mod:`selpath.stages.procam._demux_finish`) on
    the pixels whose bound exceeds ``max_gap`` after the polish (where ``max_gap`` applies; masked and clipped
    frames included), each taken towards ``gap_tol`` (0: none; a pixel of a finished call certified by the
    solver's float32 bound may read up to ~1 % above it in float64);
    ``slots``: rows of the streaming batch (None: :func:`batch_slots`);
    ``dtype``: ``float32`` or ``float64`` arithmetic (float64 needs ``jax.enable_x64``); ``throw``: raise
    :class:`selpath.stages._solution.SolverError` when a pixel did not converge (default: keep going, the result
    codes say which); ``timed``: return each phase's seconds in ``stats["phase_seconds"]`` (start, start
    certificate, ADMM, polish + certificate, host certificate, exact finish; each phase waits for its result,
    so a timed solve is slightly slower: for profiling, ``benchmarks/demux_phases.py``).

    The defaults (tol 2e-3, two polish rounds, max_gap 1e-3 with 16 finish rounds) are the cheapest measured to
    meet #25's accuracy goals on every case of ``benchmarks/demux_catalogue.py`` (certified bound: median ≤ 1e-4,
    max ≤ 1e-3; narrowly for the medians of the 1e8 and NaN cases, 9.5e-5 and 9.2e-5) and the throughput
    benchmark's (true gap p99 ≤ 1e-3): 1.3–2.5× the time of the earlier defaults (tol 5e-3, one polish round, no
    finish), whose true gap's p99 was 1.3e-3 on the benchmark's stack and whose bound reached 4e-3–0.23
    (docs/results.md). Those remain a setting away for throughput: ``DemuxADMM(tol=5e-3, polish_rounds=1,
    max_gap=1)``.
    """

    DEFAULT_TOL: ClassVar[float] = defaults.TOL
    DEFAULT_MAX_ITER: ClassVar[int] = defaults.MAX_ITER
    DEFAULT_CHECK_EVERY: ClassVar[int] = defaults.CHECK_EVERY
    DEFAULT_POLISH_ITER: ClassVar[int] = defaults.POLISH_ITER
    DEFAULT_POLISH_ROUNDS: ClassVar[int] = defaults.POLISH_ROUNDS
    DEFAULT_GAP_TOL: ClassVar[float] = defaults.GAP_TOL
    DEFAULT_MAX_GAP: ClassVar[float] = defaults.MAX_GAP
    DEFAULT_DUAL_STEPS: ClassVar[int] = defaults.DUAL_STEPS
    DEFAULT_FINISH_ROUNDS: ClassVar[int] = defaults.FINISH_ROUNDS

    tol: float = DEFAULT_TOL
    max_iter: int = DEFAULT_MAX_ITER
    check_every: int = DEFAULT_CHECK_EVERY
    polish_iter: int = DEFAULT_POLISH_ITER
    polish_rounds: int = DEFAULT_POLISH_ROUNDS
    gap_tol: float = DEFAULT_GAP_TOL
    max_gap: float = DEFAULT_MAX_GAP
    dual_steps: int = DEFAULT_DUAL_STEPS
    finish_rounds: int = DEFAULT_FINISH_ROUNDS
    slots: int | None = None
    dtype: str = "float32"
    throw: bool = False
    timed: bool = False

    #: the settings a transport store records (the stage writes them from the solver it ran, one list): what decides
    #: the answer, not how the pixels are batched
    RECORDED: ClassVar[tuple[str, ...]] = ("tol", "gap_tol", "max_gap", "finish_rounds", "dual_steps", "max_iter",
                                           "polish_iter", "polish_rounds", "dtype")

    def settings(self) -> dict:
        """:data:`RECORDED`'s settings and their values."""
        return {name: getattr(self, name) for name in self.RECORDED}

    def __post_init__(self):
        if not (self.tol > 0 and 0 <= self.gap_tol <= self.max_gap and self.finish_rounds >= 0 and self.max_iter >= 1
                and self.check_every >= 1 and self.polish_iter >= 0 and self.polish_rounds >= 1
                and self.dual_steps >= 0 and (self.slots is None or self.slots >= 1)
                and np.dtype(self.dtype) in (np.float32, np.float64)):
            raise ValueError(f"DemuxADMM needs tol > 0, max_iter ≥ 1, check_every ≥ 1, polish_iter ≥ 0, "
                             f"polish_rounds ≥ 1, 0 ≤ gap_tol ≤ max_gap, dual_steps ≥ 0, finish_rounds ≥ 0, slots ≥ 1 "
                             f"and dtype float32 or float64 (got {self})")

    def solve(self, problem: DemuxProblem | SeparableDemuxProblem, data: np.ndarray,
              weight: np.ndarray | None = None, clipped: np.ndarray | None = None) -> Solution:
        """Solve every pixel's problem: ``data`` (P, N) observations, ``weight`` (P, N) 0/1 (None: all 1),
        ``clipped`` (P, N) bool (None: none): frames whose sensor clipped, where ``data`` holds the clip level.

        Non-finite observations are masked whatever ``weight`` says. A clipped frame is a one-sided penalty
        max(0, y − AT)²: its light is at least the clip level. Returns the (P, K) transport in the data's units,
        a result code per pixel (``censored`` where the solve met ``tol`` but some offset's light was seen only
        in clipped frames: see :func:`censored_offsets`) and ``stats`` {``iterations`` (P,) int32, ``objective``
        (P,), ``gap_bound`` (P,): the certified bound on the relative objective gap, ``censored_offsets`` (P,)
        int32}.
        """
        data = np.asarray(data)
        if data.ndim != 2 or data.shape[1] != problem.frames:
            raise ValueError(f"data is {data.shape}; expected (pixels, {problem.frames} frames)")
        weight = observed(data, weight)
        if clipped is not None and np.shape(clipped) != data.shape:  # before any broadcasting could hide it
            raise ValueError(f"clipped is {np.shape(clipped)}; expected {data.shape} like the data")
        clipped = np.zeros(data.shape, bool) if clipped is None else np.asarray(clipped, bool) & weight
        any_clipped = bool(clipped.any())
        dtype = jnp.dtype(self.dtype)
        if dtype == jnp.float64 and not jax.config.jax_enable_x64:
            raise ValueError("float64 demultiplexing needs x64: call inside `with jax.enable_x64(True):`")
        ops = problem.operators(dtype)
        # without clipped frames one column stands for all (broadcast): the pool and batch carry no (P, N) zeros
        flags = clipped if any_clipped else np.zeros((data.shape[0], 1), bool)
        clock = _Clock(self.timed)
        slots = int(self.slots or batch_slots(problem.offsets))
        # the pool padded with copies of its first pixel (each pixel's problem is its own: the copies change no
        # other pixel's answer, and are dropped)
        p = data.shape[0]
        pad = np.zeros(pool_size(p, slots) - p, int)
        pool = (np.where(weight, data, 0.0), weight, flags)
        run = self._run(clock, ops, *(jax.device_put(np.concatenate([a, a[pad]]).astype(dtype)) for a in pool),
                        masked=not bool(weight.all()) or any_clipped, slots=slots)
        transport, iterations, done, objective, gap = (np.asarray(a)[:p] for a in run[:5])
        start = _Start(*(np.asarray(a)[:p] for a in run[5]))
        transport, objective, gap = np.array(transport), np.array(objective), np.array(gap)
        done = np.array(done)
        # a pixel certified at its warm start and never iterated keeps that start where the polish, which accepts
        # any lower objective, raised its bound above gap_tol
        lost = np.flatnonzero(start.certified & (gap > self.gap_tol))
        if lost.size:
            transport[lost] = start.transport[lost]
            gap[lost] = start.gap[lost]
            objective[lost] = problem.objective(start.transport[lost], np.where(weight, data, 0.0)[lost],
                                                weight[lost], clipped[lost]).astype(objective.dtype)
            done[lost] = True
        if problem.second_order_bound and (any_clipped or not weight.all()):
            gap, done = clock("host certificate", self._certify_partial, problem, data, weight, clipped, transport,
                              gap, np.array(done))
        proven = self.max_gap < 1 and problem.exact_finish
        if self.finish_rounds and proven:
            transport, objective, gap = clock("exact finish", self._finish, problem, data, weight, clipped, transport,
                                              objective, gap)
        if proven:  # converged means a proven gap of at most max_gap, whatever the residuals said
            done = gap <= self.max_gap
        finite = np.isfinite(transport).all(axis=-1) & np.isfinite(objective)
        censored = (censored_offsets(problem, transport, np.where(weight, data, 0.0), weight, clipped)
                    if any_clipped else np.zeros(data.shape[0], np.int32))
        result = outcome(np.asarray(done), finite)
        result = np.where((result == int(Result.converged)) & (censored > 0), np.int8(Result.censored), result)
        if proven:  # not converged for want of a proof, not of iterations
            result = np.where((result == int(Result.max_steps)) & (gap > self.max_gap), np.int8(Result.unproven),
                              result)
        solution = Solution(transport, result.astype(np.int8),
                            {"iterations": np.asarray(iterations), "objective": objective, "gap_bound": gap,
                             "censored_offsets": censored} | ({"phase_seconds": clock.seconds} if self.timed else {}))
        if self.throw:
            raise_if_failed(solution, "DemuxADMM", items="pixels")
        return solution

    def _certify_partial(self, problem: DemuxProblem, data, weight, clipped, transport, gap, done):
        """The KKT bound, in float64 on the host, of the finite pixels with masked or clipped frames whose bound
        exceeds ``gap_tol`` (the solver's kernels give those the first-order bound only: their Hessian is their own,
        here by Woodbury from the shared one, :func:`~selpath.stages.procam._demux_certificate.kkt_bound`); each such
        pixel keeps the smaller bound, and is converged where it is at most ``gap_tol``."""
        partial = ~(weight & ~clipped).all(axis=1)
        scope = np.flatnonzero(partial & (gap > self.gap_tol) & np.isfinite(transport).all(axis=1))
        if scope.size:
            host = kkt_bound(problem, transport[scope], data[scope], weight[scope], clipped[scope],
                             dual_steps=self.dual_steps, above=self.gap_tol)
            gap[scope] = np.minimum(gap[scope], host).astype(gap.dtype)
            done[scope] |= gap[scope] <= self.gap_tol
        return gap, done

    def _finish(self, problem: DemuxProblem, data, weight, clipped, transport, objective, gap):
        """The exact active-set finish, aimed at ``gap_tol``, on the finite pixels whose bound exceeds ``max_gap``;
        their objective and bound (float64, of the returned transport) follow (the caller's converged rule, bound ≤
        ``max_gap``, then reads that bound)."""
        scope = np.flatnonzero(np.isfinite(transport).all(axis=1) & (gap > self.max_gap))
        if scope.size:
            value, bound = active_set_finish(problem, transport[scope], data[scope], gap[scope],
                                             rounds=self.finish_rounds, gap_tol=self.gap_tol, weight=weight[scope],
                                             clipped=clipped[scope], dual_steps=self.dual_steps)
            transport[scope], gap[scope] = value, bound.astype(gap.dtype)
            objective[scope] = problem.objective(value, np.where(weight[scope], data[scope], 0.0), weight[scope],
                                                 clipped[scope]).astype(objective.dtype)
        return transport, objective, gap

    def _run(self, clock: _Clock, ops, data, weight, clipped, *, masked: bool, slots: int):
        """Start, set aside the pixels certified at their warm start (gap bound ≤ ``gap_tol``: no iteration), stream
        the others through a batch of ``slots`` (:func:`~selpath.stages.procam._demux_kernels.stream`), compact its tail
        (:meth:`_iterate_tail`), finish: (transport, iterations, converged, objective, gap bound, the warm start
        as :class:`_Start`). A pixel is
        converged where its residuals met ``tol`` or where its final certified bound is at most ``gap_tol``."""
        p = data.shape[0]
        slots = min(slots, p)
        pool, scale, z0 = clock("start", kernels.start, ops, data, weight, clipped, masked=masked, chunk=slots)
        start_gap = np.asarray(clock("start certificate", kernels.gaps, ops, pool, z0, chunk=slots, masked=masked))
        certified = start_gap <= self.gap_tol
        order = np.argsort(certified, kind="stable")  # the live pixels first, in their order
        live = int(p - certified.sum())
        start = _Start(certified, np.asarray(z0 * scale), start_gap)  # in the pixels' own order
        if live < p:
            pool, z0 = Rows(*(_host_take(a, order) for a in pool)), _host_take(z0, order)
        limits = Limits(jnp.asarray(self.tol, data.dtype), jnp.asarray(self.max_iter, jnp.int32))
        pixel, rows, batch, _, out = clock("ADMM", kernels.stream, ops, limits, pool, z0, jnp.asarray(live, jnp.int32),
                                           check_every=self.check_every, masked=masked, slots=slots)
        pixel, z, iters, done = self._iterate_tail(clock, ops, limits, np.array(pixel), rows, batch, pool_size=p,
                                                   masked=masked)
        held = pixel < p
        z_out, iters_out, done_out = (np.array(a) for a in out)
        z_out[pixel[held]], iters_out[pixel[held]], done_out[pixel[held]] = z[held], iters[held], done[held]
        z_out[live:], iters_out[live:], done_out[live:] = np.asarray(z0[live:]), 0, False  # judged by their gap
        if live < p:
            inverse = np.argsort(order)
            pool = Rows(*(_host_take(a, inverse) for a in pool))
            z_out, iters_out, done_out = z_out[inverse], iters_out[inverse], done_out[inverse]
        transport, objective, gap = clock("polish + certificate", kernels.finish, ops, pool, scale,
                                          jnp.asarray(z_out), polish_iter=self.polish_iter,
                                          polish_rounds=self.polish_rounds, dual_steps=self.dual_steps, masked=masked,
                                          chunk=slots)
        done_out = done_out | (np.asarray(gap) <= self.gap_tol)
        return transport, iters_out, done_out, objective, gap, start

    def _iterate_tail(self, clock: _Clock, ops, limits: Limits, pixel: np.ndarray, rows: Rows, batch: Batch, *,
                      pool_size: int, masked: bool):
        """The batch's living pixels once the pool is exhausted, gathered into a batch COMPACTION times smaller
        each time all but 1/COMPACTION of them have converged, and iterated on alone (each size compiles once).
        In numpy between the jitted calls (index bookkeeping no jit does cheaply). Returns the batch's (pixel,
        Z, iterations, converged); ``pixel`` is ``pool_size`` on an empty row."""
        iters, done, age = (np.array(a) for a in (batch.iters, batch.done, batch.age))
        state, rows = State(*(np.array(a) for a in batch.state)), [np.asarray(a) for a in rows]
        index = np.flatnonzero(alive(done, age, self.max_iter) & (pixel < pool_size))
        while index.size:
            n = index.size
            size = _batch_size(n)
            padded = np.concatenate([index, np.full(size - n, index[0])])
            pad_done = np.arange(size) >= n  # padding rows count as converged and are never written back
            part = clock(
                "ADMM", kernels.iterate, ops, limits, Rows(*(a[padded] for a in rows)),
                Batch(State(*(a[padded] for a in state)), iters[padded], done[padded] | pad_done, age[padded]),
                jnp.asarray(compact_at(size), jnp.int32), check_every=self.check_every, masked=masked)
            for full, new in zip(state, part.state, strict=True):
                full[index] = np.asarray(new)[:n]
            iters[index], done[index], age[index] = (np.asarray(a)[:n] for a in (part.iters, part.done, part.age))
            index = index[alive(done[index], age[index], self.max_iter)]
        return pixel, state.z, iters, done
