"""The explorer's response per interaction on a full-size transport, and the accessor's on the same store.

A 1600 × 1200 × 253 float32 plane-to-ray transport (1.9 GB, chunked as ``demux_plane_to_ray`` writes it: every
offset of 32 rows a chunk) and its 21 × 3-frame capture are generated lazily and written as stores (a direct peak
at offset 0 and a broad lobe whose width varies across the frame). Then, in one process, as ``selpath explore``
does: open them, build the transport's preview (read once, columns binned to fit 512 MB) and time each interaction
the page offers: the ideal frame at a delay and exposure, a relit image under a band of projector rows, the
epipolar and non-epipolar images of a band, and a clicked pixel (its T at full resolution and its I(t_d) from the
capture). The peer, in the same run, is the same view computed by the accessor straight from the lazy store (what
the explorer would cost without its preview). Peak memory is the process's maximum resident set.

    python benchmarks/explore_interactions.py [--rows 1200] [--cols 1600] [--offsets 253] [--repeat 3]

Goal (#54): every interaction ≤ 0.5 s on 2 cores, peak memory ≤ 2 GB. Last line:
``explore: worst_interaction_s=<a> preview_s=<b> peak_rss_gb=<c> speedup_vs_lazy=<d>``
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import dask.array as da
import numpy as np
import xarray as xr

import selpath
from selpath.explore.views import TransportView
from selpath.stages.procam.acquire import PLANE_TO_RAY_CAPTURE
from selpath.stages.procam.demux import PLANE_TO_RAY_TRANSPORT

SPEED, LINE_TIME = 1 / 17, 17.0


def _transport_band(block_info=None, *, offsets: np.ndarray, cols: int):
    (r0, r1) = block_info[None]["array-location"][1]
    rows = np.arange(r0, r1)[:, None]
    width = 3.0 + 8.0 * (rows / 1200.0) + 4.0 * (np.arange(cols)[None, :] / cols)  # (r, c)
    o = offsets[:, None, None].astype(np.float32)
    direct = 800.0 * (o == 0)
    lobe = 40.0 * np.exp(-np.abs(o) / width[None]).astype(np.float32)
    return (direct + lobe).astype(np.float32)


def write_stores(folder: Path, rows: int, cols: int, n_offsets: int) -> tuple[Path, Path]:
    half = n_offsets // 2
    offsets = np.arange(-half, n_offsets - half)
    data = da.map_blocks(_transport_band, offsets=offsets, cols=cols, dtype=np.float32,
                         chunks=((n_offsets,), tuple(min(32, rows - r) for r in range(0, rows, 32)), (cols,)))
    transport = xr.Dataset({"transport": (("offset", "row", "col"), data)},
                           coords={"offset": ("offset", offsets, {"units": "px"})},
                           attrs={"scan_speed_px_per_us": SPEED, "line_time_us": LINE_TIME, "sync_offset_us": 0.0,
                                  "projector_shape": [720, 1280], "full_scale_counts": 4095.0})
    t_path = folder / "transport.zarr"
    selpath.to_store(PLANE_TO_RAY_TRANSPORT.label(transport), t_path, "plane_to_ray_transport")
    delays, exposures = np.arange(-1700.0, 1701.0, 170.0), np.array([170.0, 510.0, 850.0])
    frames = da.random.default_rng(0).random((delays.size, exposures.size, rows, cols), dtype=np.float32,
                                             chunks=(1, 1, min(64, rows), cols)) * 1000
    capture = xr.Dataset({"image": (("delay", "exposure", "row", "col"), frames)},
                         coords={"delay": ("delay", delays, {"units": "us"}),
                                 "exposure": ("exposure", exposures, {"units": "us"})},
                         attrs={"scan_speed_px_per_us": SPEED, "line_time_us": LINE_TIME,
                                "saturation_counts": 4095.0, "dark_level_counts": 0.0})
    c_path = folder / "capture.zarr"
    selpath.to_store(PLANE_TO_RAY_CAPTURE.label(capture), c_path, "plane_to_ray_capture")
    return t_path, c_path


def _best(function, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rows", type=int, default=1200)
    parser.add_argument("--cols", type=int, default=1600)
    parser.add_argument("--offsets", type=int, default=253)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        t_path, c_path = write_stores(Path(tmp), args.rows, args.cols, args.offsets)
        print(f"wrote {args.offsets} × {args.rows} × {args.cols} transport and a 21 × 3-frame capture in "
              f"{time.perf_counter() - start:.1f} s")
        start = time.perf_counter()
        transport, capture = selpath.open_store(t_path), selpath.open_store(c_path)
        view = TransportView(transport, capture)
        preview_s = time.perf_counter() - start
        mb = view.cube.nbytes / 2**20
        print(f"opened and built the preview in {preview_s:.1f} s: columns binned by {view.bin}, {mb:.0f} MB")
        r, c = args.rows // 3, args.cols // 3
        rows_lit = range(300, 340)
        cases = {
            "ideal frame (t_d = −340 µs, t_e = 510 µs)": (
                lambda: view.image("ideal frame", delay=-340.0, exposure=510.0),
                lambda: transport.selpath.ideal_frame(-340.0, 510.0).values),
            "relit (projector rows 300–339)": (
                lambda: view.image("relit", line=300, width=40),
                lambda: transport.selpath.relight(rows=rows_lit).values),
            "epipolar (|offset| ≤ 5)": (lambda: view.image("epipolar", band=5),
                                        lambda: transport.selpath.epipolar(5).values),
            "non-epipolar (|offset| > 5)": (lambda: view.image("non-epipolar", band=5),
                                            lambda: transport.selpath.non_epipolar(5).values),
            "click: T at full resolution + I(t_d)": (lambda: (view.profile(r, c), view.intensity(r, c)),
                                                     lambda: (view.profile(r, c), view.intensity(r, c))),
        }
        print(f"{'interaction':<42} {'explorer s':>10} {'lazy store s':>12} {'ratio':>7}")
        worst, ratios = 0.0, []
        for name, (ours, peer) in cases.items():
            ours_s = _best(ours, args.repeat)
            peer_s = _best(peer, 1)
            worst = max(worst, ours_s)
            ratios.append(peer_s / ours_s)
            print(f"{name:<42} {ours_s:>10.3f} {peer_s:>12.2f} {peer_s / ours_s:>6.0f}×")
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        print(f"explore: worst_interaction_s={worst:.3f} preview_s={preview_s:.1f} peak_rss_gb={peak:.2f} "
              f"speedup_vs_lazy={np.median(ratios):.0f}")


if __name__ == "__main__":
    main()
