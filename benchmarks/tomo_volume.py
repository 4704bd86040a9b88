"""Tomography at volume scale (#26 item 3): a full 1600 × 1200 × 360 capture, simulated lazily, to a volume on a
``processes`` cluster with a memory limit per worker, and its scaling from 1 to 2 workers.

The grape (``workflows/scenes/grape-ellipsoid.yaml``: an ellipsoid with two seeds and a bruise at three heights) on
a 1600 × 1200 telecentric camera of 0.02 mm pixels, a light sheet, 360 views: target, reference and backlit frames
of 2.76 GB each as float32, 8.3 GB in all, never held. ``simulate_capture`` renders each chunk (one whole frame)
inside the task that needs it. Two passes over the frames, each one lazy graph over all 1200 slices: the visual hull
(silhouettes, contours: small), then absorption, paths, the sinogram at the capture's bins (180 × 1601) and FBP on
``--n-pixels``² cells (default 400, 0.08 mm). One graph would hold every angle's absorption (2.8 GB at full size)
until the last silhouette is in; two passes render the frames twice instead (a stored capture is read twice). The
volume is written to a zarr store on a ``LocalCluster`` of single-threaded worker processes (one XLA thread each,
``selpath.pipeline.compute.local_cluster``) with ``--memory-limit`` each, first with 1 worker, then with 2, each a fresh
cluster. Printed: wall time, slices per second, each worker's peak RSS (``getrusage``), the 1 → 2 speed-up, and
the volume's RMSE against the scene's truth on a sample of slices (a check that the graph computed the right thing).

A larger cluster (``tcp://`` scheduler, ``DASK_SCHEDULER_ADDRESS``): the graph is the same; tasks are independent per
angle chunk up to the silhouettes and per row after the sinogram's rechunk, so throughput grows with workers until
the rechunk between them dominates: every angle chunk to every row chunk, each ray's flat bin (int32) and absorption
(float32), 5.5 GB at full size, moved once over the network (the stage's task-based rechunk, whose pieces a worker
spills to disk); workers need the project installed and the scene file readable.

    python benchmarks/tomo_volume.py [--rows 1200 --cols 1600 --angles 360 --n-pixels 400 --memory-limit 4GB]

Last line: ``volume: slices_per_s=<2 workers> peak_rss_gb=<largest worker peak, either run> speedup_2w=<t1 / t2>``.
Measured (docs/results.md, 2026-11-26): at full size, 1257.9 s on 1 worker, 646.2 s on 2 (1.95×, 1.86 slices/s), peak
3.01 GB, RMSE 2.5e-3 /mm; most of the time is the rendering, twice.
"""

from __future__ import annotations

import argparse
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr
import yaml

from selpath import workflows
from selpath.pipeline.compute import local_cluster
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.calibrate import absorption
from selpath.stages.tomography.hull import silhouettes, visual_hull
from selpath.stages.tomography.paths import align_paths
from selpath.stages.tomography.phantom import phantom_truth
from selpath.stages.tomography.reconstruct import fbp
from selpath.stages.tomography.simulate import simulate_capture
from selpath.stages.tomography.sinogram import bin_sinogram


def scene_file(folder: Path, rows: int, cols: int) -> Path:
    """The grape scene on a ``rows × cols`` camera whose pixels keep the 1600 × 1200 sensor's field (32 × 24 mm)."""
    spec = yaml.safe_load((workflows.folder() / "scenes" / "grape-ellipsoid.yaml").read_text())
    spec["camera"] = {"model": "orthographic", "rows": rows, "cols": cols, "pixel_size": f"{32.0 / cols} mm"}
    path = folder / "grape-large.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def capture_of(scene: Path, angles: int) -> xr.Dataset:
    return simulate_capture(scene=str(scene), angles=AngleSweep(start=0, stop=360, step=360 / angles))


def volume_graph(capture: xr.Dataset, hull: xr.Dataset, n_pixels: int) -> xr.Dataset:
    """The absorption → FBP chain as one lazy graph, on a hull computed before."""
    sinogram = bin_sinogram(align_paths(absorption(capture, min_signal=1.0), hull))
    return fbp(sinogram, hull, n_pixels=n_pixels, fill="linear")


def peak_rss() -> int:
    """This process's peak resident memory [bytes] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def run(workers: int, scene: Path, angles: int, n_pixels: int, memory_limit: str, store: Path) -> tuple[float, float]:
    """Write the volume with ``workers`` fresh worker processes: (seconds, largest worker peak RSS [GB])."""
    shutil.rmtree(store, ignore_errors=True)
    with local_cluster(workers, memory_limit=memory_limit) as client:
        client.run(lambda: __import__("jax").numpy.zeros(1).block_until_ready())  # JAX imported before the clock
        capture = capture_of(scene, angles)
        start = time.perf_counter()
        # two passes over the frames: the hull (small: the contours) first, then the volume, so that no worker
        # holds every angle's absorption until the last silhouette is in (2.8 GB at full size)
        hull = visual_hull(silhouettes(capture)).compute()
        volume = volume_graph(capture, hull, n_pixels)
        volume[["sigma"]].drop_attrs().to_zarr(store, mode="w", consolidated=False)
        seconds = time.perf_counter() - start
        peaks = client.run(peak_rss)
    return seconds, max(peaks.values()) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1200)
    parser.add_argument("--cols", type=int, default=1600)
    parser.add_argument("--angles", type=int, default=360)
    parser.add_argument("--n-pixels", type=int, default=400)
    parser.add_argument("--memory-limit", default="4GB")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="cluster sizes to run, in turn")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scene = scene_file(folder, args.rows, args.cols)
        capture = capture_of(scene, args.angles)
        volume = volume_graph(capture, visual_hull(silhouettes(capture)), args.n_pixels)
        frames = sum(capture[k].nbytes for k in ("target", "reference", "backlit")) / 1e9
        print(f"capture {args.cols} × {args.rows} × {args.angles}: {frames:.2f} GB as float32 (never held); "
              f"volume {volume.sizes['slice']} × {args.n_pixels}² cells; graph of "
              f"{len(volume['sigma'].data.__dask_graph__()):,} tasks; memory limit {args.memory_limit} per worker")
        print(f"{'workers':>8} {'wall [s]':>10} {'slices/s':>10} {'peak RSS/worker [GB]':>22}")
        results = {}
        for workers in args.workers:
            seconds, rss = run(workers, scene, args.angles, args.n_pixels, args.memory_limit, folder / "volume.zarr")
            results[workers] = (seconds, rss)
            print(f"{workers:>8} {seconds:>10.1f} {volume.sizes['slice'] / seconds:>10.2f} {rss:>22.2f}")
        written = xr.open_zarr(folder / "volume.zarr", consolidated=False)["sigma"]
        sample = np.linspace(0, volume.sizes["slice"] - 1, 9).round().astype(int)[1:-1]
        truth = phantom_truth(volume.isel(slice=sample).assign_attrs(x_extent=float(volume["x"].max()
                                                                                   + volume.attrs["cell_size"] / 2)),
                              scene=str(scene), n_pixels=args.n_pixels)["sigma"].values
        rmse = float(np.sqrt(np.mean((written.isel(slice=sample).values - truth) ** 2)))
        print(f"RMSE against the truth on {len(sample)} slices: {rmse:.3g} /mm (largest true σ 0.4 /mm)")
    if {1, 2} <= results.keys():
        (t1, _), (t2, _) = results[1], results[2]
        print(f"volume: slices_per_s={volume.sizes['slice'] / t2:.3g} "
              f"peak_rss_gb={max(r for _, r in results.values()):.3g} speedup_2w={t1 / t2:.3g}")


if __name__ == "__main__":
    main()
