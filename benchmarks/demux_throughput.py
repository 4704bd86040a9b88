"""Demultiplexing at full-sensor scale: throughput, peak memory, accuracy versus time, against CVXPY.

A lazily generated 1600×1200 stack of 75 frames (25 delays × 3 exposures, the thesis's N) over K = 128
offsets (and K = 256) goes through the ``demux_plane_to_ray`` stage into a zarr store with dask's threaded
scheduler. Each band of rows is drawn from a seeded random transport (a direct peak, a subsurface-like
lobe, and for 30 % of pixels a displaced specular peak) through the illumination model, with Poisson and
read noise. The peer, in the same run, is the thesis's per-pixel CVXPY solve on a sample of the same
pixels: CVXPY's default solver with the problem built per pixel (what the thesis did), and one
parametrised problem solved by Clarabel. The objective gap is ours against Clarabel's optimum.

    python benchmarks/demux_throughput.py [--rows 1200] [--cols 1600] [--sample 200] [--quick]

Last line: ``demux: px_per_s=<a> speedup_vs_cvxpy=<b> gap=<median relative objective gap> peak_rss_gb=<c>``
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time

DELAYS_US = [-1020.0 + 85.0 * i for i in range(25)]  # 5 rows apart: K = 128 spans ±64 rows
EXPOSURES_US = [170.0, 510.0, 850.0]
SPEED, LINE_TIME = 1 / 17, 17.0  # the default rig: v_p = 1 row per 17 µs, t_p = 17 µs


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB on Linux


def _offsets(k: int):
    import numpy as np

    return np.arange(-k // 2, k // 2)


def _matrix(k: int):
    import numpy as np

    from stages.illumination import plane_to_ray_illumination

    d, e = np.meshgrid(DELAYS_US, EXPOSURES_US, indexing="ij")
    return plane_to_ray_illumination(d.ravel(), e.ravel(), _offsets(k), scan_speed=SPEED, line_time=LINE_TIME)


def _pixels(k: int, n: int, seed: int):
    """(truth (n, K), images (n, N) in [0, 1]) for n pixels."""
    import numpy as np

    rng = np.random.default_rng(seed)
    o = _offsets(k)[None, :]
    truth = (rng.uniform(0.2, 0.9, (n, 1)) * (o == 0)
             + rng.uniform(0, 0.05, (n, 1)) * np.exp(-np.abs(o) / rng.uniform(1, 8, (n, 1)))
             + rng.uniform(0, 0.1, (n, 1)) * (rng.random((n, 1)) < 0.3)
             * np.exp(-(o - rng.uniform(-50, 50, (n, 1))) ** 2 / 8))
    counts = rng.poisson(truth @ _matrix(k).T * 1000) + rng.normal(0, 2, (n, len(DELAYS_US) * len(EXPOSURES_US)))
    return truth, np.clip(counts, 0, 4095) / 4095


def _capture(k: int, rows: int, cols: int, band: int = 64):
    """The lazy (delay, exposure, row, col) capture, one dask task per band of rows."""
    import dask.array as da
    import numpy as np
    import xarray as xr

    n_d, n_e = len(DELAYS_US), len(EXPOSURES_US)

    def band_of(block_id=None):
        r0 = block_id[2] * band
        n = min(band, rows - r0)
        _, images = _pixels(k, n * cols, seed=r0)
        return (images.T * 4095).astype(np.float32).reshape(n_d, n_e, n, cols)

    chunks = ((n_d,), (n_e,), tuple(min(band, rows - r) for r in range(0, rows, band)), (cols,))
    stack = da.map_blocks(band_of, dtype=np.float32, chunks=chunks)
    return xr.Dataset({"image": (("delay", "exposure", "row", "col"), stack, {"units": "counts"})},
                      coords={"delay": ("delay", DELAYS_US, {"units": "us"}),
                              "exposure": ("exposure", EXPOSURES_US, {"units": "us"})},
                      attrs={"selpath_kind": "plane_to_ray_capture", "scan_speed_px_per_us": SPEED,
                             "line_time_us": LINE_TIME, "dark_level_counts": 0.0, "saturation_counts": 4095.0})


def measure(mode: str, args) -> dict:
    import dask
    import numpy as np

    k = args.k
    if mode in ("selpath", "generate"):
        from stages.demux import OffsetGrid, demux_plane_to_ray

        capture = _capture(k, args.rows, args.cols)
        pixels = args.rows * args.cols
        with dask.config.set(scheduler="threads", num_workers=args.workers), tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            if mode == "generate":
                capture["image"].sum().compute()
            else:
                out = demux_plane_to_ray(capture, offsets=OffsetGrid(start=-k // 2, stop=k // 2 - 1),
                                         max_iter=args.max_iter, tol=args.tol)
                out.to_zarr(f"{tmp}/t.zarr", consolidated=False)
            seconds = time.perf_counter() - start
        return {"seconds": seconds, "pixels": pixels, "peak_rss_gb": _peak_rss_gb()}
    if mode == "curve":  # accuracy versus iterations and time, against Clarabel's optimum
        import cvxpy as cp

        from stages.demux_solver import DemuxProblem, solve

        matrix = _matrix(k)
        problem = DemuxProblem.build(matrix)
        _, sample = _pixels(k, args.sample, seed=12345)
        t, y = cp.Variable(k), cp.Parameter(matrix.shape[0])
        qp = cp.Problem(cp.Minimize(cp.sum_squares(matrix @ t - y) + 0.01 * cp.sum_squares(cp.diff(t))
                                    + 0.01 * cp.sum(t)), [t >= 0])
        optimum = []
        start = time.perf_counter()
        for p in range(args.sample):
            y.value = sample[p]
            qp.solve(solver=cp.CLARABEL)
            optimum.append(qp.value)
        clarabel_s = (time.perf_counter() - start) / args.sample
        optimum = np.array(optimum)
        default_s = []
        for p in range(min(args.sample, 20)):  # the thesis's way: a problem built and solved per pixel
            start = time.perf_counter()
            tp = cp.Variable(k)
            cp.Problem(cp.Minimize(cp.sum_squares(matrix @ tp - sample[p]) + 0.01 * cp.sum_squares(cp.diff(tp))
                                   + 0.01 * cp.sum(tp)), [tp >= 0]).solve()
            default_s.append(time.perf_counter() - start)
        timing_block = np.tile(sample, (16384 // args.sample + 1, 1))[:16384]
        rows = []
        for max_iter in (10, 20, 40, 80, 160):
            for polish in (0, 20):
                result = solve(problem, sample, max_iter=max_iter, tol=1e-7, polish_iter=polish)
                gap = (problem.objective(result.transport, sample) - optimum) / np.abs(optimum)
                solve(problem, timing_block, max_iter=max_iter, tol=1e-7, polish_iter=polish)  # compile
                start = time.perf_counter()
                solve(problem, timing_block, max_iter=max_iter, tol=1e-7, polish_iter=polish)
                per_px = (time.perf_counter() - start) / timing_block.shape[0]
                rows.append({"max_iter": max_iter, "polish": polish, "gap_median": float(np.median(gap)),
                             "gap_p90": float(np.percentile(gap, 90)), "s_per_px": per_px})
        stopped = solve(problem, sample, max_iter=args.max_iter, tol=args.tol)
        gap = (problem.objective(stopped.transport, sample) - optimum) / np.abs(optimum)
        return {"clarabel_s_per_px": clarabel_s, "default_s_per_px": float(np.median(default_s)),
                "curve": rows, "gap_median": float(np.median(gap)), "gap_p90": float(np.percentile(gap, 90)),
                "converged": float(stopped.converged.mean()), "iterations_median": float(np.median(stopped.iterations)),
                "peak_rss_gb": _peak_rss_gb()}
    raise ValueError(mode)


def _run(mode: str, argv: list[str], **overrides) -> dict:
    extra = [f"--{name.replace('_', '-')}={value}" for name, value in overrides.items()]
    out = subprocess.run([sys.executable, __file__, "--measure", mode, *argv, *extra], check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1200)
    parser.add_argument("--cols", type=int, default=1600)
    parser.add_argument("--k", type=int, default=128)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--sample", type=int, default=200)
    parser.add_argument("--max-iter", type=int, default=40)
    parser.add_argument("--tol", type=float, default=1e-2)
    parser.add_argument("--quick", action="store_true", help="a 240×320 sensor and a 60-pixel sample")
    parser.add_argument("--measure", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure, args)))
        return
    argv = [f"--rows={args.rows}", f"--cols={args.cols}", f"--sample={args.sample}", f"--max-iter={args.max_iter}",
            f"--tol={args.tol}"]
    if args.quick:
        argv = ["--rows=240", "--cols=320", "--sample=60", f"--max-iter={args.max_iter}", f"--tol={args.tol}"]
    curve = _run("curve", argv, k=128)
    print(f"per-pixel CVXPY at K = 128: default solver {curve['default_s_per_px'] * 1e3:.1f} ms, "
          f"parametrised Clarabel {curve['clarabel_s_per_px'] * 1e3:.1f} ms")
    print("accuracy versus time (K = 128, float32, one 16384-pixel call; gap = relative objective gap to Clarabel):")
    print(f"{'iterations':>10}{'polish':>8}{'gap median':>12}{'gap p90':>10}{'µs/px':>8}{'px/s':>10}")
    for row in curve["curve"]:
        print(f"{row['max_iter']:>10}{row['polish']:>8}{row['gap_median']:>12.1e}{row['gap_p90']:>10.1e}"
              f"{row['s_per_px'] * 1e6:>8.1f}{1 / row['s_per_px']:>10.0f}")
    print(f"stage defaults (max_iter {args.max_iter}, tol {args.tol:g}): gap median {curve['gap_median']:.1e}, "
          f"p90 {curve['gap_p90']:.1e}; converged {curve['converged']:.0%}, "
          f"median {curve['iterations_median']:.0f} its")
    generate = _run("generate", argv, k=128)
    print(f"\n{'run':<34}{'seconds':>9}{'px/s':>10}{'peak RSS GB':>13}")
    print(f"{'generate the stack (K=128)':<34}{generate['seconds']:>9.1f}{'':>10}{generate['peak_rss_gb']:>13.2f}")
    results = {}
    for k, workers in ((128, 2), (128, 1), (256, 2)):
        run = _run("selpath", argv, k=k, workers=workers)
        seconds = max(run["seconds"] - (generate["seconds"] if k == 128 else 0.0), 1e-9)
        results[(k, workers)] = run | {"px_per_s": run["pixels"] / seconds}
        print(f"{f'demux K={k}, {workers} worker(s)':<34}{run['seconds']:>9.1f}{run['pixels'] / seconds:>10.0f}"
              f"{run['peak_rss_gb']:>13.2f}")
    main_run = results[(128, 2)]
    print(f"scaling 1 → 2 workers: {main_run['px_per_s'] / results[(128, 1)]['px_per_s']:.2f}×; "
          f"full 1600×1200 frame at K = 128: {1600 * 1200 / main_run['px_per_s']:.0f} s (goal ≤ 60 s)")
    speedup = curve["default_s_per_px"] * main_run["px_per_s"]
    print(f"speed-up versus default CVXPY {speedup:.0f}× (goal ≥ 1000×), versus parametrised Clarabel "
          f"{curve['clarabel_s_per_px'] * main_run['px_per_s']:.0f}×")
    peak = max(r["peak_rss_gb"] for r in results.values())
    print(f"demux: px_per_s={main_run['px_per_s']:.0f} speedup_vs_cvxpy={speedup:.0f} gap={curve['gap_median']:.2e} "
          f"peak_rss_gb={peak:.2f}")


if __name__ == "__main__":
    main()
