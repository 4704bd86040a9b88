"""Tomography at volume scale (#26 item 3): a full 1600 × 1200 × 360 capture, simulated lazily, to a volume on a
``processes`` cluster with a memory limit per worker, and its scaling from 1 to 2 workers.

The grape (``workflows/scenes/grape-ellipsoid.yaml``: an ellipsoid with two seeds and a bruise at three heights) on
a 1600 × 1200 telecentric camera of 0.02 mm pixels, a light sheet, 360 views: target, reference and backlit frames
of 2.76 GB each as float32, 8.3 GB in all, never held. ``simulate_capture`` renders each chunk (one whole frame)
inside the task that needs it. The whole chain is one lazy graph over all 1200 slices: absorption,
silhouettes, visual hull, paths, the sinogram at the capture's bins (180 × 1601), FBP on ``--n-pixels``² cells
(default 400, 0.08 mm; the capture's 1601² costs about 3 s a slice). The volume
is written to a zarr store on a ``LocalCluster`` of single-threaded worker processes (one XLA thread each,
``pipeline.compute.WORKER_ENV``) with ``--memory-limit`` each, first with 1 worker, then with 2, each a fresh
cluster. Printed: wall time, slices per second, each worker's peak RSS (``getrusage``), the 1 → 2 speed-up, and
the volume's RMSE against the scene's truth on a sample of slices (a check that the graph computed the right thing).

A larger cluster (``tcp://`` scheduler, ``DASK_SCHEDULER_ADDRESS``): the graph is the same; tasks are independent per
angle chunk up to the silhouettes and per row after the sinogram's rechunk, so throughput grows with workers until
the rechunk between them (every angle chunk to every row, about the capture's absorption in float64 moved once over
the network: 3 × 4.4 GB at full size) dominates; workers need the project installed and the scene file readable.

    python benchmarks/tomo_volume.py [--rows 1200 --cols 1600 --angles 360 --n-pixels 400 --memory-limit 4GB]

Last line: ``volume: slices_per_s=<2 workers> peak_rss_gb=<largest worker peak, either run> speedup_2w=<t1 / t2>``.
Measured (docs/results.md): at 800 × 600 × 180, 938.7 s on 1 worker, 518.0 s on 2 (1.81×), peak 2.88 GB; the full size
stalled a single 4 GB worker (paused at 80 % in unmanaged memory), which is still open.
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

import workflows
from pipeline.compute import WORKER_ENV
from stages.tomography.acquire import AngleSweep
from stages.tomography.calibrate import absorption
from stages.tomography.hull import silhouettes, visual_hull
from stages.tomography.paths import align_paths
from stages.tomography.phantom import phantom_truth
from stages.tomography.reconstruct import fbp
from stages.tomography.simulate import simulate_capture
from stages.tomography.sinogram import bin_sinogram


def scene_file(folder: Path, rows: int, cols: int) -> Path:
    """The grape scene on a ``rows × cols`` camera whose pixels keep the 1600 × 1200 sensor's field (32 × 24 mm)."""
    spec = yaml.safe_load((workflows.folder() / "scenes" / "grape-ellipsoid.yaml").read_text())
    spec["camera"] = {"model": "orthographic", "rows": rows, "cols": cols, "pixel_size": f"{32.0 / cols} mm"}
    path = folder / "grape-large.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def volume_graph(scene: Path, angles: int, n_pixels: int) -> tuple[xr.Dataset, xr.Dataset]:
    """The capture → FBP chain as one lazy graph, and the capture (for its size)."""
    capture = simulate_capture(scene=str(scene), angles=AngleSweep(start=0, stop=360, step=360 / angles))
    hull = visual_hull(silhouettes(capture))
    sinogram = bin_sinogram(align_paths(absorption(capture, min_signal=1.0), hull))
    return fbp(sinogram, hull, n_pixels=n_pixels, fill="linear"), capture


def peak_rss() -> int:
    """This process's peak resident memory [bytes] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def run(workers: int, scene: Path, angles: int, n_pixels: int, memory_limit: str, store: Path) -> tuple[float, float]:
    """Write the volume with ``workers`` fresh worker processes: (seconds, largest worker peak RSS [GB])."""
    from distributed import Client, LocalCluster

    shutil.rmtree(store, ignore_errors=True)
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, memory_limit=memory_limit,
                      dashboard_address=None, env=WORKER_ENV) as cluster, Client(cluster) as client:
        client.run(lambda: __import__("jax").numpy.zeros(1).block_until_ready())  # JAX imported before the clock
        volume, _ = volume_graph(scene, angles, n_pixels)
        start = time.perf_counter()
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
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scene = scene_file(folder, args.rows, args.cols)
        volume, capture = volume_graph(scene, args.angles, args.n_pixels)
        frames = sum(capture[k].nbytes for k in ("target", "reference", "backlit")) / 1e9
        print(f"capture {args.cols} × {args.rows} × {args.angles}: {frames:.2f} GB as float32 (never held); "
              f"volume {volume.sizes['slice']} × {args.n_pixels}² cells; graph of "
              f"{len(volume['sigma'].data.__dask_graph__()):,} tasks; memory limit {args.memory_limit} per worker")
        print(f"{'workers':>8} {'wall [s]':>10} {'slices/s':>10} {'peak RSS/worker [GB]':>22}")
        results = {}
        for workers in (1, 2):
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
    (t1, rss1), (t2, rss2) = results[1], results[2]
    print(f"volume: slices_per_s={volume.sizes['slice'] / t2:.3g} peak_rss_gb={max(rss1, rss2):.3g} "
          f"speedup_2w={t1 / t2:.3g}")


if __name__ == "__main__":
    main()
