"""Where a demultiplexing call's time goes, phase by phase, and what #25's speed goal leaves for each phase.

On pixels drawn as the throughput benchmark's K = 128 stack's (``benchmarks._demux_sweep.sample``, seed 0: the same
distribution, clipped frames one-sided), one ``DemuxADMM.solve`` call of the stage's size for a 64-row band of a
1600-column sensor (``pixels_per_call``: 15 streaming batches of 1024, 15 360 pixels) is timed whole, then again
phase by phase: ``DemuxADMM(timed=True)`` times each of its kernels and host steps, each waiting for its result
(``jax.block_until_ready``), and returns the seconds in ``stats["phase_seconds"]``, so the phases add up to the
timed call and "other" is the host bookkeeping between them. Compiles are excluded (a first call compiles). BLAS
runs on one thread, as in a workflow's compute (``selpath.pipeline.compute.blas_on_one_thread``).

Phases: ``start`` (the unconstrained warm start, clipped), ``start certificate`` (the cheap KKT bound that lets an
already optimal pixel skip iterating), ``ADMM`` (the streaming batch and its compacted tail), ``polish +
certificate`` (the CG polish rounds, the objective and the certified bound with its dual ascent), ``host
certificate`` (the float64 KKT bound of pixels with masked or clipped frames) and ``exact finish`` (the
active-set rounds on the pixels still above ``max_gap``). Settings: the fast ones (the defaults before #25's
certificate, no dual ascent) and the defaults.

The peer, in the same run: CVXPY's default solver with the problem built per pixel (the thesis's way;
``benchmarks._demux_sweep.default_cvxpy_seconds``). #25's goal, 2000× its throughput, is a budget of its median
time / 2000 per pixel for the whole store-to-store step; the throughput benchmark measured the step's I/O alone at
2.0 µs/px (docs/results.md). The last lines say how many ADMM iterations of this call's own cost the
budget would leave after the phases no method here can skip (the start, one certificate, the I/O).

    python -m benchmarks.demux_phases [--pixels 15360] [--calls 2] [--io-us 2.0]

Last line: ``demux_phases: defaults_us_per_px=<a> fast_us_per_px=<b> budget_us_per_px=<c> us_per_iteration=<d>
iterations_in_budget=<e>``
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

#: the solver's phases, as ``DemuxADMM(timed=True)`` names them in ``stats["phase_seconds"]``
PHASES = ("start", "start certificate", "ADMM", "polish + certificate", "host certificate", "exact finish")


def profile(solver, problem, data, clipped, calls: int) -> dict:
    """µs/px of ``calls`` calls (after one that compiles), whole and per phase, with the mean iterations and the
    share of pixels the exact finish took (bound above ``max_gap`` before it)."""
    solution = solver.solve(problem, data, clipped=clipped)  # compile
    start = time.perf_counter()
    for _ in range(calls):
        solution = solver.solve(problem, data, clipped=clipped)
    whole = (time.perf_counter() - start) / calls
    totals: dict = {}
    timed = dataclasses.replace(solver, timed=True)
    start = time.perf_counter()
    for _ in range(calls):
        for label, seconds in timed.solve(problem, data, clipped=clipped).stats["phase_seconds"].items():
            totals[label] = totals.get(label, 0.0) + seconds
    timed_call = (time.perf_counter() - start) / calls
    pixels = data.shape[0]
    phases = {label: seconds / calls / pixels * 1e6 for label, seconds in totals.items()}
    phases["other"] = timed_call / pixels * 1e6 - sum(phases.values())
    unfinished = solver.__class__(**{**solver.__dict__, "finish_rounds": 0}).solve(problem, data, clipped=clipped)
    tail = float(np.mean(unfinished.stats["gap_bound"] > solver.max_gap)) if solver.max_gap < 1 else 0.0
    return {"us_per_px": whole / pixels * 1e6, "timed_us_per_px": timed_call / pixels * 1e6, "phases": phases,
            "iterations": float(np.mean(solution.stats["iterations"])), "tail": tail,
            "bound_median": float(np.median(solution.stats["gap_bound"])),
            "bound_max": float(np.max(solution.stats["gap_bound"])), "converged": float(np.mean(solution.converged))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixels", type=int, help="pixels per call (default: the stage's call at K = 128)")
    parser.add_argument("--calls", type=int, default=2, help="timed calls of each kind")
    parser.add_argument("--io-us", type=float, default=2.0,
                        help="the store-to-store step's I/O alone, µs/px (the throughput benchmark's measurement)")
    args = parser.parse_args()
    import jax

    from benchmarks._demux_sweep import FAST, default_cvxpy_seconds, device_line, matrix, sample
    from selpath.pipeline.compute import blas_on_one_thread
    from selpath.stages.procam.solver import DemuxADMM, DemuxProblem, pixels_per_call

    k = 128
    pixels = args.pixels or pixels_per_call(1600 * 64, k)
    problem = DemuxProblem.build(matrix(k, kept_only=True))
    data, clipped = sample(k, pixels, 1, pixels)
    print(f"device: {device_line(jax)}")
    cvxpy_s = float(np.median(default_cvxpy_seconds(problem, data)))
    budget = cvxpy_s / 2000 * 1e6
    print(f"default CVXPY, per pixel: {cvxpy_s * 1e3:.1f} ms (median of 20): #25's 2000× leaves {budget:.2f} µs/px "
          f"for the whole step, {budget - args.io_us:.2f} µs/px after the I/O ({args.io_us:.1f} µs/px)")
    # BLAS on one thread, as the stage's tasks see it in a workflow (pipeline.compute.blas_on_one_thread): else
    # the host steps' OpenBLAS pool spins on the cores after each call, and the next call's start reads ~1.3 µs/px
    # slower
    with blas_on_one_thread():
        results = {label: profile(DemuxADMM(**settings), problem, data, clipped, args.calls)
                   for label, settings in (("fast", FAST), ("defaults", {}))}
    labels = [*PHASES, "other"]
    print(f"\nK = {k}, {pixels} px a call, float32, µs/px (one thread calling; XLA's own threads inside):")
    print(f"{'phase':<22}" + "".join(f"{name:>12}" for name in results))
    for label in labels:
        print(f"{label:<22}" + "".join(f"{r['phases'].get(label, 0.0):>12.2f}" for r in results.values()))
    for label, key, fmt in (("whole call", "us_per_px", ".2f"), ("timed call", "timed_us_per_px", ".2f"),
                            ("mean iterations", "iterations", ".1f"), ("tail > max_gap", "tail", ".1%"),
                            ("bound median", "bound_median", ".1e"), ("bound max", "bound_max", ".1e"),
                            ("converged", "converged", ".1%")):
        print(f"{label:<22}" + "".join(f"{format(r[key], fmt):>12}" for r in results.values()))
    fast, defaults = results["fast"], results["defaults"]
    per_iteration = fast["phases"]["ADMM"] / fast["iterations"]
    floor = min(r["phases"]["start"] + r["phases"]["start certificate"] for r in results.values())  # the same work
    left = budget - args.io_us - floor
    print(f"\none ADMM iteration: {per_iteration:.2f} µs/px (the fast settings' ADMM phase / their mean iterations); "
          f"the start and its certificate {floor:.2f} µs/px; the budget leaves {left:.2f} µs/px, "
          f"{max(left, 0.0) / per_iteration:.1f} iterations with no polish and no final certificate, where the "
          f"defaults take {defaults['iterations']:.1f} and {defaults['us_per_px']:.1f} µs/px in all "
          f"({defaults['us_per_px'] / max(budget - args.io_us, 1e-9):.1f}× the budget's solve)")
    print(f"demux_phases: defaults_us_per_px={defaults['us_per_px']:.2f} fast_us_per_px={fast['us_per_px']:.2f} "
          f"budget_us_per_px={budget:.2f} us_per_iteration={per_iteration:.3f} "
          f"iterations_in_budget={max(left, 0.0) / per_iteration:.1f}")


if __name__ == "__main__":
    main()
