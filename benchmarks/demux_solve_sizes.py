"""The demultiplexing solver alone, on whatever device JAX has: time per pixel against pixels per call, and the
precision of its products (for a GPU session: see docs/results.md, "On a GPU").

On the throughput benchmark's K = 128 sweep (``benchmarks.demux_throughput``'s pixels), ``DemuxADMM`` at its defaults
solves P pixels in one call, for growing P (compiles excluded: the second of two calls); the stage calls it with
``selpath.stages.procam.solver.pixels_per_call`` pixels (16 batches), so this shows what larger calls would give. On
the first 200 pixels it also reports the objective gap against Clarabel's optimum and the certified bound, for the
defaults, the exact finish on every pixel above gap_tol (``max_gap=1e-4``) and float64 and, with
``--default-precision``, for JAX's own default precision of float32
products (TF32 on NVIDIA Ampere and Hopper GPUs; the same as full precision on a CPU), which the solver no longer uses.

    python -m benchmarks.demux_solve_sizes [--sizes 16384 65536 262144] [--default-precision]

Last line: ``solve_sizes: device=<…> us_per_px=<at each size> gap=<median at the defaults>``
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[16384, 65536, 262144], help="pixels per call")
    parser.add_argument("--default-precision", action="store_true",
                        help="also solve with JAX's default precision of float32 products (TF32 on recent GPUs)")
    args = parser.parse_args()
    import jax

    import selpath.stages.procam._demux_problem as demux_problem
    from benchmarks._demux_sweep import device_line
    from benchmarks._demux_sweep import matrix as _matrix
    from benchmarks._demux_sweep import sample as _sample
    from benchmarks.demux_catalogue import reference
    from selpath.stages.procam.solver import DemuxADMM

    device = device_line(jax)
    print(f"device: {device}")
    k = 128
    problem = demux_problem.DemuxProblem.build(_matrix(k, kept_only=True))
    largest = max(args.sizes)
    data, clipped = _sample(k, largest, 1, largest)  # the benchmark's pixels as the stage sees them, one row of them
    optimum = reference(problem, data[:200], None, clipped[:200])
    methods = [("defaults", jax.lax.Precision.HIGHEST, {}), ("finish all", jax.lax.Precision.HIGHEST,
                                                            {"max_gap": 1e-4}),
               ("float64", jax.lax.Precision.HIGHEST, {"dtype": "float64"})]
    if args.default_precision:
        methods.append(("default precision", None, {}))
    print(f"{'method':<19}{'gap med':>9}{'gap p90':>9}{'bnd med':>9}{'bnd max':>9}{'conv':>7}{'iters':>7}  µs/px at "
          + ", ".join(f"{p} px" for p in args.sizes))
    timings = {}
    for label, precision, settings in methods:
        demux_problem.PRECISION = precision  # read when the kernels are traced: clear the caches around it
        jax.clear_caches()
        solver = DemuxADMM(**settings)
        with jax.enable_x64(solver.dtype == "float64"):
            result = solver.solve(problem, data[:200], clipped=clipped[:200])
            value = problem.objective(result.value, data[:200], None, clipped[:200])
            gap = (value - optimum) / np.abs(optimum)
            bound = result.stats["gap_bound"]
            times = []
            for p in (args.sizes if label == "defaults" else args.sizes[:1]):  # the others at the first size only
                solver.solve(problem, data[:p], clipped=clipped[:p])  # compile
                start = time.perf_counter()
                solver.solve(problem, data[:p], clipped=clipped[:p])
                times.append((time.perf_counter() - start) / p * 1e6)
        timings[label] = times
        print(f"{label:<19}{np.median(gap):>9.1e}{np.percentile(gap, 90):>9.1e}{np.median(bound):>9.1e}"
              f"{bound.max():>9.1e}{np.mean(result.converged):>7.1%}{np.mean(result.stats['iterations']):>7.1f}  "
              + ", ".join(f"{t:.2f}" for t in times), flush=True)
        if label == "defaults":
            default_gap = float(np.median(gap))
    demux_problem.PRECISION = jax.lax.Precision.HIGHEST
    jax.clear_caches()
    per_size = ",".join(f"{t:.2f}" for t in timings["defaults"])
    print(f"solve_sizes: device={device.split(' (')[0]!r} us_per_px={per_size} gap={default_gap:.2e}")


if __name__ == "__main__":
    main()
