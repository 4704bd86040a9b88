"""Reading a capture from object storage against reading it from local disk (#29).

A delay–exposure capture store (75 frames of ``--rows`` × ``--cols`` float32, one frame per chunk as the rig
writes it) is written locally and uploaded to an S3-compatible server started here on 127.0.0.1 (moto, from
the test extras). Each run opens the store with ``open_store`` (checks included: chunk listing, migration,
schema) and sums every frame through dask's threaded scheduler, so every chunk is fetched, checksummed and
decoded. Printed: seconds and MB/s for local and remote, and the ratio.

moto is a single-process Python server, so the remote number is a floor for the method, not a prediction for
a real object store (which serves many parallel requests); what it shows is that the remote path adds no
per-chunk overhead of ours beyond the requests themselves.

    python -m benchmarks.remote_read [--rows 600] [--cols 800] [--workers 8]

Last line: ``remote_read: local_mb_s=<a> remote_mb_s=<b> ratio=<b/a>``
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=600)
    parser.add_argument("--cols", type=int, default=800)
    parser.add_argument("--workers", type=int, default=8, help="dask threads (requests in flight)")
    args = parser.parse_args()

    import dask
    import dask.array as da
    import numpy as np
    import xarray as xr
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.WARNING)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    os.environ.update(AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench", AWS_DEFAULT_REGION="us-east-1",
                      AWS_ENDPOINT_URL=f"http://{host}:{port}")
    import s3fs

    from selpath.pipeline.store import open_store, to_store

    fs = s3fs.S3FileSystem()
    fs.mkdir("bench")
    n_d, n_e = 25, 3
    image = da.random.default_rng(0).uniform(0, 4095, (n_d, n_e, args.rows, args.cols), chunks=(1, 1, -1, -1))
    capture = xr.Dataset({"image": (("delay", "exposure", "row", "col"), image.astype(np.float32),
                                    {"units": "counts"})},
                         coords={"delay": ("delay", np.arange(n_d) * 170.0 - 2040.0, {"units": "us"}),
                                 "exposure": ("exposure", [170.0, 510.0, 850.0], {"units": "us"})},
                         attrs={"scan_speed_px_per_us": 1 / 17, "line_time_us": 17.0, "saturation_counts": 4095.0,
                                "dark_level_counts": 0.0})
    megabytes = capture["image"].nbytes / 1e6
    with tempfile.TemporaryDirectory() as tmp:
        local = f"{tmp}/capture.zarr"
        to_store(capture, local, "plane_to_ray_capture")
        start = time.perf_counter()
        fs.put(local, "bench/capture.zarr", recursive=True)
        upload = time.perf_counter() - start
        times = {}
        with dask.config.set(scheduler="threads", num_workers=args.workers):
            for name, where in (("local", local), ("remote", "s3://bench/capture.zarr")):
                start = time.perf_counter()
                total = float(open_store(where)["image"].sum().compute())
                times[name] = time.perf_counter() - start
                print(f"{name:<7}{times[name]:>8.2f} s{megabytes / times[name]:>9.1f} MB/s  (sum {total:.6g})")
    server.stop()
    rates = {name: megabytes / seconds for name, seconds in times.items()}
    print(f"{megabytes:.0f} MB in {n_d * n_e} frame chunks; upload {upload:.1f} s; {args.workers} threads")
    print(f"remote_read: local_mb_s={rates['local']:.1f} remote_mb_s={rates['remote']:.1f} "
          f"ratio={rates['remote'] / rates['local']:.2f}")


if __name__ == "__main__":
    main()
