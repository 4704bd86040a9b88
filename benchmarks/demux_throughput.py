"""Demultiplexing at full-sensor scale: throughput, peak memory, accuracy versus time, against CVXPY.

A lazily generated 1600×1200 stack of 75 frames (25 delays × 3 exposures, the thesis's N) over K = 128
offsets (and K = 256) is written band by band to a capture store, as the rig's acquisition would leave it;
each timed run is then the workflow step, in a fresh process: open the store, ``demux_plane_to_ray``, write
the transport store (dask's threaded scheduler, compiles included). Each band of rows is drawn from a
seeded random transport (a direct peak, a subsurface-like lobe, and for 30 % of pixels a displaced specular
peak) through the illumination model, with Poisson and read noise. The peer, in the same run, is the thesis's
per-pixel CVXPY solve on a sample of the same pixels: CVXPY's default solver with the problem built per pixel
(what the thesis did), and one parametrised problem solved by Clarabel. The objective gap is the stage's
stored output against Clarabel's optimum (at 1e-12, ``benchmarks.demux_catalogue.reference``) on the first pixels
of row 0 (same frames; a frame at 4095 counts is clipped, a one-sided penalty, as the stage treats it), so it is
the accuracy of the run whose speed is reported (the goal: median ≤ 1e-4, p99 ≤ 1e-3); the curve shows what more
ADMM iterations cost, and the fast settings (the defaults before #25's certified ones), the defaults (the exact
finish on the pixels whose bound exceeds ``max_gap``) and the finish on every pixel above ``gap_tol`` side by side.
``--tol 5e-3 --polish-rounds 1 --max-gap 1 --dual-steps 0`` times the whole step at the fast settings.

    python benchmarks/demux_throughput.py [--rows 1200] [--cols 1600] [--sample 200] [--quick]
                                          [--scheduler threads|processes]

The I/O floor (reading the capture and writing a transport like the stage's, timed alone in a fresh process)
is what no solver can go under in this store-to-store step; with it the run's time splits into I/O and solve.

Last line: ``demux: px_per_s=<a> speedup_vs_cvxpy=<b> gap=<median relative objective gap> peak_rss_gb=<c>``
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time

if __package__ in (None, ""):  # run as a script: the repository root on the path, for the shared sweep
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks._demux_sweep import (
    FAST,
    UNCAPPED,
    capture,
    default_cvxpy_seconds,
    device_line,
    matrix,
    peak_rss_gb,
    sample,
)

__all__ = ["FAST", "UNCAPPED", "main", "measure"]


def _options(args) -> dict:
    """The solver settings given on the command line; the rest stay at the stage's defaults."""
    return {name: getattr(args, name) for name in ("tol", "max_iter", "polish_iter", "polish_rounds", "finish_rounds",
                                                   "max_gap", "dual_steps") if getattr(args, name) is not None}


def measure(mode: str, args) -> dict:
    import dask
    import numpy as np

    from selpath.pipeline.compute import compute, enable_compile_cache
    from selpath.pipeline.store import open_store, to_store

    if args.compile_cache:  # as the command line runs it, in a folder of this benchmark's own
        os.environ["SELPATH_COMPILE_CACHE"] = args.compile_cache
        enable_compile_cache()
    k = args.k
    if mode in ("selpath", "generate", "io"):
        from selpath.stages.procam.demux import demux_plane_to_ray
        from selpath.stages.procam.solver import OffsetGrid

        pixels = args.rows * args.cols
        with contextlib.ExitStack() as stack:
            tmp = stack.enter_context(tempfile.TemporaryDirectory())
            start, client = time.perf_counter(), None
            if args.scheduler == "processes" and mode == "selpath":  # as `scheduler: processes` runs a workflow:
                from selpath.pipeline.compute import local_cluster  # single-threaded worker processes (timed from here)

                client = stack.enter_context(local_cluster(args.workers))
            else:
                stack.enter_context(dask.config.set(scheduler="threads", num_workers=args.workers))
            if mode == "generate":
                to_store(capture(k, args.rows, args.cols), args.store, "plane_to_ray_capture")
            elif mode == "io":  # the floor under any solver: read the capture, write a transport like the stage's
                images = open_store(args.store)["image"]
                images.sum(("delay", "exposure")).compute()
                read = time.perf_counter() - start
                # the stage's own output, in memory: only the write is timed
                written = open_store(args.out).unify_chunks().persist()
                start = time.perf_counter()
                to_store(written, f"{tmp}/t.zarr", "plane_to_ray_transport")
                return {"read_s": read, "write_s": time.perf_counter() - start, "pixels": pixels}
            else:
                out = demux_plane_to_ray(open_store(args.store), offsets=OffsetGrid(start=-k // 2, stop=k // 2 - 1),
                                         **_options(args))
                # written as a workflow's engine writes an output (pipeline.compute: one BLAS thread per dask thread)
                compute([to_store(out, args.out or f"{tmp}/t.zarr", "plane_to_ray_transport", compute=False)],
                        scheduler=args.scheduler, client=client, progress=False)
            seconds = time.perf_counter() - start
            # with worker processes, this one's peak and each worker's, added: what the machine must hold at most
            peak = peak_rss_gb() + (sum(client.run(peak_rss_gb).values()) if client is not None else 0.0)
            result = {"seconds": seconds, "pixels": pixels, "peak_rss_gb": peak}
            if mode == "selpath":  # the stage's own output on the sample pixels, for the objective gap
                from selpath.stages.procam.solver import DemuxProblem

                stored = open_store(args.out or f"{tmp}/t.zarr")
                n = min(args.sample, args.cols)
                transport = stored["transport"].isel(row=0, col=slice(0, n)).values.T / 4095
                images, clipped = sample(k, n, args.rows, args.cols)
                objective = DemuxProblem.build(matrix(k, kept_only=True)).objective(transport, images, None, clipped)
                bound = stored["gap_bound"].values
                result |= {"objective": objective.tolist(),
                           "sample_bound": stored["gap_bound"].isel(row=0, col=slice(0, n)).values.tolist(),
                           "bound_median": float(np.median(bound)), "bound_p99": float(np.percentile(bound, 99)),
                           "converged": float(stored["converged"].mean()),
                           "certified": float(stored["certified_fraction"]),
                           "iterations_mean": float(stored["iterations"].mean()),
                           "settings": {name: stored.attrs[name] for name in ("tol", "max_iter", "polish_iter",
                                                                              "polish_rounds", "finish_rounds",
                                                                              "dual_steps", "gap_tol", "max_gap")}}
        return result
    if mode == "curve":  # accuracy versus iterations and time, against Clarabel's optimum
        from concurrent.futures import ThreadPoolExecutor

        import cvxpy as cp

        from selpath.stages.procam.solver import DemuxADMM, DemuxProblem, solve_pixels

        a = matrix(k, kept_only=True)
        problem = DemuxProblem.build(a)
        from benchmarks.demux_catalogue import reference

        images, clipped = sample(k, min(args.sample, args.cols), args.rows, args.cols)
        weight = (~clipped).astype(float)  # the timed peer masks clipped frames (as selpath did before #30)
        args.sample = images.shape[0]
        # DPP: one compiled problem, y and the saturation mask w as parameters (y holds w·data)
        t, y, w = cp.Variable(k), cp.Parameter(a.shape[0]), cp.Parameter(a.shape[0], nonneg=True)
        qp = cp.Problem(cp.Minimize(cp.sum_squares(cp.multiply(w, a @ t) - y)
                                    + problem.alpha * cp.sum_squares(cp.diff(t)) + problem.beta * cp.sum(t)), [t >= 0])
        start = time.perf_counter()
        for p in range(args.sample):
            w.value, y.value = weight[p], weight[p] * images[p]
            qp.solve(solver=cp.CLARABEL)
        clarabel_s = (time.perf_counter() - start) / args.sample
        optimum = reference(problem, images, None, clipped)  # the stage's objective, clipped frames one-sided
        default_s = default_cvxpy_seconds(problem, images)  # the thesis's way: a problem built and solved per pixel
        # timing as the stage runs: two halves of 16384 pixels at once, in the stage's calls
        tiles = 16384 // args.sample + 1
        halves = list(zip(np.array_split(np.tile(images, (tiles, 1))[:16384], 2),
                          np.array_split(np.tile(clipped, (tiles, 1))[:16384], 2), strict=True))

        def timed(**options) -> float:
            def run(part):
                return solve_pixels(DemuxADMM(**options), problem, part[0], np.ones(part[0].shape, bool), part[1])

            with ThreadPoolExecutor(2) as pool:
                list(pool.map(run, halves))  # compile
                start = time.perf_counter()
                list(pool.map(run, halves))
            return (time.perf_counter() - start) / 16384

        rows = []
        for max_iter in (10, 20, 40, 80, 160):
            for polish in (0, 20):
                result = DemuxADMM(max_iter=max_iter, tol=1e-7, polish_iter=polish, **UNCAPPED).solve(
                    problem, images, clipped=clipped)
                gap = (problem.objective(result.value, images, None, clipped) - optimum) / np.abs(optimum)
                rows.append({"max_iter": max_iter, "polish": polish, "gap_median": float(np.median(gap)),
                             "gap_p90": float(np.percentile(gap, 90)), "gap_p99": float(np.percentile(gap, 99)),
                             "s_per_px": timed(max_iter=max_iter, tol=1e-7, polish_iter=polish, **UNCAPPED)})
        # the fast settings (the defaults before #25's certified ones, without the dual ascent), the defaults, and the
        # exact finish on every pixel above gap_tol
        for label, options in (("fast", FAST), ("defaults", {}), ("finish all", {"max_gap": 1e-4})):
            result = DemuxADMM(**options).solve(problem, images, clipped=clipped)
            gap = (problem.objective(result.value, images, None, clipped) - optimum) / np.abs(optimum)
            rows.append({"max_iter": label, "polish": "dflt",
                         "gap_median": float(np.median(gap)), "gap_p90": float(np.percentile(gap, 90)),
                         "gap_p99": float(np.percentile(gap, 99)),
                         "bound_median": float(np.median(result.stats["gap_bound"])),
                         "bound_max": float(np.max(result.stats["gap_bound"])),
                         "certified": float(np.mean(result.stats["gap_bound"] <= DemuxADMM.DEFAULT_GAP_TOL)),
                         "s_per_px": timed(**options)})
        import jax

        return {"device": device_line(jax), "clarabel_s_per_px": clarabel_s,
                "default_s_per_px": float(np.median(default_s)), "curve": rows, "optimum": optimum.tolist(),
                "peak_rss_gb": peak_rss_gb()}
    raise ValueError(mode)


def _run(mode: str, argv: list[str], **overrides) -> dict:
    extra = [f"--{name.replace('_', '-')}={value}" for name, value in overrides.items()]
    out = subprocess.run([sys.executable, __file__, "--measure", mode, *argv, *extra], capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"the {mode} run failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1200)
    parser.add_argument("--cols", type=int, default=1600)
    parser.add_argument("--k", type=int, default=128)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scheduler", choices=("threads", "processes"), default="threads",
                        help="the timed runs' scheduler, as a workflow's `scheduler:` (processes: single-threaded "
                             "worker processes, timed from the cluster's start; peak RSS adds the workers')")
    parser.add_argument("--sample", type=int, default=200)
    parser.add_argument("--max-iter", type=int, help="default: the stage's")
    parser.add_argument("--polish-iter", type=int, help="default: the stage's")
    parser.add_argument("--tol", type=float, help="default: the stage's")
    parser.add_argument("--finish-rounds", type=int, help="default: the stage's (exact active-set finish rounds)")
    parser.add_argument("--polish-rounds", type=int, help="default: the stage's")
    parser.add_argument("--max-gap", type=float, help="default: the stage's (the finish runs on pixels above it)")
    parser.add_argument("--dual-steps", type=int, help="default: the stage's (the certificate's dual ascent)")
    parser.add_argument("--quick", action="store_true", help="a 240×320 sensor and a 60-pixel sample")
    parser.add_argument("--measure", help=argparse.SUPPRESS)
    parser.add_argument("--store", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--compile-cache", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure, args)))
        return
    settings = [f"--{name.replace('_', '-')}={value}" for name, value in _options(args).items()]
    settings.append(f"--scheduler={args.scheduler}")
    argv = [f"--rows={args.rows}", f"--cols={args.cols}", f"--sample={args.sample}", *settings]
    if args.quick:
        argv = ["--rows=240", "--cols=320", "--sample=60", *settings]
    curve = _run("curve", argv, k=128)
    print(f"device: {curve['device']}")
    print(f"per-pixel CVXPY at K = 128: default solver {curve['default_s_per_px'] * 1e3:.1f} ms, "
          f"parametrised Clarabel {curve['clarabel_s_per_px'] * 1e3:.1f} ms")
    print("accuracy versus time (K = 128, float32, 16384 pixels in the stage's calls on 2 threads; gap = relative "
          "objective gap to Clarabel):")
    print(f"{'iterations':>10}{'polish':>8}{'gap median':>12}{'gap p90':>10}{'gap p99':>10}{'µs/px':>8}{'px/s':>10}")
    for row in curve["curve"]:
        print(f"{row['max_iter']:>10}{row['polish']:>8}{row['gap_median']:>12.1e}{row['gap_p90']:>10.1e}"
              f"{row['gap_p99']:>10.1e}"
              f"{row['s_per_px'] * 1e6:>8.1f}{1 / row['s_per_px']:>10.0f}"
              + (f"   certified bound median {row['bound_median']:.1e}, max {row['bound_max']:.1e}, "
                 f"{row['certified']:.0%} ≤ gap_tol" if "bound_median" in row else ""))
    print(f"\n{'run (fresh process each)':<38}{'seconds':>9}{'px/s':>10}{'peak RSS GB':>13}{'converged':>11}"
          f"{'iterations':>12}")
    results, io = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        cache = [f"--compile-cache={tmp}/jax"]
        # (K, workers, compile cache): the first runs compile from scratch; the 1-worker run fills the cache the
        # command line keeps between runs (same band shapes), and the last run loads its kernels from it
        for k, workers, cached in ((128, 2, False), (128, 1, True), (128, 2, True), (256, 2, False)):
            store = [f"--store={tmp}/capture-{k}.zarr"]
            if (k, workers, cached) in ((128, 2, False), (256, 2, False)):
                generate = _run("generate", argv + store, k=k)
                print(f"{f'generate the capture store (K={k})':<38}{generate['seconds']:>9.1f}{'':>10}"
                      f"{generate['peak_rss_gb']:>13.2f}")
            out = [f"--out={tmp}/transport-{k}.zarr"] if (k, workers, cached) == (128, 2, False) else []
            run = _run("selpath", argv + store + out + (cache if cached else []), k=k, workers=workers)
            results[(k, workers, cached)] = run | {"px_per_s": run["pixels"] / run["seconds"]}
            kind = "process(es)" if args.scheduler == "processes" else "worker(s)"
            label = f"demux K={k}, {workers} {kind}" + (", cache warm" if workers == 2 and cached else "")
            print(f"{label:<38}{run['seconds']:>9.1f}{run['pixels'] / run['seconds']:>10.0f}"
                  f"{run['peak_rss_gb']:>13.2f}{run['converged']:>11.1%}{run['iterations_mean']:>12.1f}")
            if out:
                io = _run("io", argv + store + out, k=k, workers=workers)
                print(f"{'  I/O alone: read the capture':<38}{io['read_s']:>9.1f}")
                print(f"{'  I/O alone: write its transport':<38}{io['write_s']:>9.1f}")
    main_run, warm = results[(128, 2, False)], results[(128, 2, True)]
    import numpy as np

    gap = (np.array(main_run["objective"]) - curve["optimum"]) / np.abs(curve["optimum"])
    used = main_run["settings"]
    print(f"the stage's output (tol {used['tol']:g}, max_iter {used['max_iter']}, polish {used['polish_iter']} × "
          f"{used['polish_rounds']}, finish rounds {used['finish_rounds']} above max_gap {used['max_gap']:g}, dual "
          f"steps {used['dual_steps']}) on {gap.size} pixels of row 0: gap median {np.median(gap):.1e}, p90 "
          f"{np.percentile(gap, 90):.1e}, p99 {np.percentile(gap, 99):.1e} (goal: median ≤ 1e-4, p99 ≤ 1e-3); "
          f"whole frame converged {main_run['converged']:.0%}, mean {main_run['iterations_mean']:.0f} iterations")
    bound = np.array(main_run["sample_bound"])
    print(f"certified gap bound (gap_bound, from weak duality): on those pixels median {np.median(bound):.1e}, max "
          f"{bound.max():.1e}, never below the measured gap: {bool(np.all(bound >= gap - 1e-6))}; whole frame median "
          f"{main_run['bound_median']:.1e}, p99 {main_run['bound_p99']:.1e}; certified (bound ≤ gap_tol "
          f"{used['gap_tol']:g}) {main_run['certified']:.1%} of the frame, converged {main_run['converged']:.1%}")
    print(f"scaling 1 → 2 workers: {main_run['px_per_s'] / results[(128, 1, True)]['px_per_s']:.2f}×; "
          f"full 1600×1200 frame at K = 128: {1600 * 1200 / main_run['px_per_s']:.0f} s (goal ≤ 30 s)")
    speedup = curve["default_s_per_px"] * main_run["px_per_s"]
    floor = io["read_s"] + io["write_s"]
    print(f"I/O floor: {floor:.1f} s a frame ({floor / main_run['pixels'] * 1e6:.1f} µs/px) to read the capture and "
          f"write a transport, with no solving at all: no solver in this store-to-store step can beat "
          f"{curve['default_s_per_px'] * main_run['pixels'] / floor:.0f}× default CVXPY; the solve's own share of the "
          f"run is {main_run['seconds'] - floor:.1f} s ({(main_run['seconds'] - floor) / main_run['pixels'] * 1e6:.1f}"
          " µs/px)")
    print(f"speed-up versus default CVXPY {speedup:.0f}× (goal ≥ 2000×), versus parametrised Clarabel "
          f"{curve['clarabel_s_per_px'] * main_run['px_per_s']:.0f}×; with the compile cache warm "
          f"{curve['default_s_per_px'] * warm['px_per_s']:.0f}× ({1600 * 1200 / warm['px_per_s']:.0f} s a frame)")
    peak = max(r["peak_rss_gb"] for r in results.values())
    print(f"demux: px_per_s={main_run['px_per_s']:.0f} speedup_vs_cvxpy={speedup:.0f} gap={np.median(gap):.2e} "
          f"peak_rss_gb={peak:.2f}")


if __name__ == "__main__":
    main()
