"""Absorption at real size: throughput and peak memory, tile by tile, against eager NumPy; and the cost of
reading a store back (every chunk decoded and its checksum verified).

A lazily simulated 1600×1200 capture with 360 angles (2.8 GB per frame variable in float32) goes through
the ``absorption`` stage into a zarr store with the threaded scheduler. The simulation's own cost is
measured alone and subtracted. The peer is the same arithmetic in eager NumPy on frames already in
memory (what a notebook would write), scaled to the same pixel count. ``read`` opens the written store
with ``open_store`` and reduces both variables (decode + checksum of every chunk). Each measurement runs
in its own process so peak RSS is its own.

    python benchmarks/absorption_throughput.py [--angles 360] [--rows 1200] [--cols 1600]

Last lines: ``absorption: px_per_s=<a> numpy_px_per_s=<b> ratio=<a/b> peak_rss_gb=<c> numpy_peak_rss_gb=<d>``,
the same without the background flag (``flag_background: false``: no silhouettes of the backlit frames; the peer
flags no background either), and ``read: px_per_s=<r> mb_per_s=<m>`` (MB of decoded absorption + flags per
second).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB on Linux


def _capture(args):
    from selpath.stages.tomography.acquire import AngleSweep
    from selpath.stages.tomography.simulate import simulate_parallel_capture

    return simulate_parallel_capture(angles=AngleSweep(start=0, stop=360, step=360 / args.angles),
                                     n_rows=args.rows, n_cols=args.cols, pixel_size=40.0 / args.cols * 1.2)


def _read(store: str) -> float:
    """Seconds to open ``store`` and reduce every variable (every chunk read, decoded and verified)."""
    import dask

    from selpath.pipeline.store import open_store

    start = time.perf_counter()
    ds = open_store(store)
    dask.compute(ds["absorption"].sum(), ds["flags"].max(), scheduler="threads")
    return time.perf_counter() - start


def measure(mode: str, args) -> dict:
    import dask
    import numpy as np

    from selpath.pipeline.store import to_store
    from selpath.stages.tomography.calibrate import absorption

    pixels = args.angles * args.rows * args.cols
    if mode == "simulate":
        capture = _capture(args)
        start = time.perf_counter()
        dask.compute(capture["target"].sum(), capture["reference"].sum(), scheduler="threads")
        return {"seconds": time.perf_counter() - start, "peak_rss_gb": _peak_rss_gb(), "pixels": pixels}
    if mode in ("selpath", "selpath_no_background"):
        capture = _capture(args)
        with tempfile.TemporaryDirectory() as folder:
            start = time.perf_counter()
            with dask.config.set(scheduler="threads"):
                to_store(absorption(capture, flag_background=mode == "selpath"), f"{folder}/absorption.zarr",
                         "absorption")
            seconds = time.perf_counter() - start
            read = _read(f"{folder}/absorption.zarr")
        return {"seconds": seconds, "peak_rss_gb": _peak_rss_gb(), "pixels": pixels, "read_seconds": read}
    if mode == "numpy":
        n = max(1, min(args.angles, 8))  # eager NumPy holds everything: measure 8 angles, scale by pixels
        frames = _capture(argparse.Namespace(**{**vars(args), "angles": n})).compute()
        t, r, d = (frames[v].values for v in ("target", "reference", "dark"))
        start = time.perf_counter()
        ct, cr = t - d, r - d
        valid = (t < 4095) & (r < 4095) & (ct > 0) & (cr > 0) & np.isfinite(t) & np.isfinite(r)
        with np.errstate(all="ignore"):
            a = np.where(valid, np.log(cr) - np.log(ct), np.nan).astype(np.float32)
        seconds = time.perf_counter() - start
        assert np.isfinite(a[valid]).all()
        return {"seconds": seconds, "peak_rss_gb": _peak_rss_gb(), "pixels": n * args.rows * args.cols}
    raise ValueError(mode)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--angles", type=int, default=360)
    parser.add_argument("--rows", type=int, default=1200)
    parser.add_argument("--cols", type=int, default=1600)
    parser.add_argument("--measure", choices=["simulate", "selpath", "selpath_no_background", "numpy"],
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure, args)))
        return
    results = {}
    for mode in ("simulate", "selpath", "selpath_no_background", "numpy"):
        cmd = [sys.executable, __file__, "--measure", mode, "--angles", str(args.angles),
               "--rows", str(args.rows), "--cols", str(args.cols)]
        results[mode] = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
    stage_seconds = max(results["selpath"]["seconds"] - results["simulate"]["seconds"], 1e-9)
    ours = results["selpath"]["pixels"] / stage_seconds
    peer = results["numpy"]["pixels"] / results["numpy"]["seconds"]
    print(f"capture: {args.angles} angles x {args.rows} x {args.cols} = {results['selpath']['pixels'] / 1e6:.0f} "
          f"Mpx per variable")
    print(f"{'run':<28}{'seconds':>10}{'peak RSS GB':>14}")
    print(f"{'simulate only (subtracted)':<28}{results['simulate']['seconds']:>10.2f}"
          f"{results['simulate']['peak_rss_gb']:>14.2f}")
    print(f"{'selpath absorption -> zarr':<28}{results['selpath']['seconds']:>10.2f}"
          f"{results['selpath']['peak_rss_gb']:>14.2f}")
    print(f"{'  flag_background: false':<28}{results['selpath_no_background']['seconds']:>10.2f}"
          f"{results['selpath_no_background']['peak_rss_gb']:>14.2f}")
    print(f"{'numpy eager (8 angles)':<28}{results['numpy']['seconds']:>10.2f}{results['numpy']['peak_rss_gb']:>14.2f}")
    print(f"absorption: px_per_s={ours:.3g} numpy_px_per_s={peer:.3g} ratio={ours / peer:.2f} "
          f"peak_rss_gb={results['selpath']['peak_rss_gb']:.2f} "
          f"numpy_peak_rss_gb={results['numpy']['peak_rss_gb']:.2f}")
    plain = results["selpath_no_background"]["pixels"] / max(
        results["selpath_no_background"]["seconds"] - results["simulate"]["seconds"], 1e-9)
    print(f"absorption without the background flag: px_per_s={plain:.3g} ratio={plain / peer:.2f} (the flag's "
          f"silhouettes cost {plain / ours:.1f}x)")
    read = results["selpath"]["read_seconds"]
    print(f"read: px_per_s={results['selpath']['pixels'] / read:.3g} "
          f"mb_per_s={results['selpath']['pixels'] * 5 / 1e6 / read:.0f} seconds={read:.2f}")


if __name__ == "__main__":
    main()
