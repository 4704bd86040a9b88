"""The demultiplexing benchmarks' shared sweep: the thesis-like rig (25 delays × 3 exposures over K offsets), its
illumination matrix, seeded pixels and the lazy full-sensor capture, the fast settings, and the per-pixel CVXPY peer.

Used by ``benchmarks/demux_throughput.py`` (store to store), ``demux_phases.py`` (where a call's time goes),
``demux_solve_sizes.py``, ``demux_catalogue.py``, ``demux_clipped.py`` and ``demux_active_set_probe.py``: one
definition of the pixels every number in docs/results.md's demultiplexing sections was measured on.
"""

from __future__ import annotations

import os
import resource
import time

import numpy as np

#: the sweep's exposures [µs]
EXPOSURES_US = [170.0, 510.0, 850.0]
#: the default rig: v_p = 1 row per 17 µs, t_p = 17 µs
SPEED, LINE_TIME = 1 / 17, 17.0

#: the fast settings: the stage's defaults before #25's certified ones (tol 5e-3, one polish round, no finish, no
#: max_gap), without the certificate's dual ascent; ``--tol 5e-3 --polish-rounds 1 --max-gap 1 --dual-steps 0`` runs
#: the throughput benchmark so
FAST = {"tol": 5e-3, "polish_rounds": 1, "max_gap": 1.0, "dual_steps": 0}
#: the accuracy-versus-time curve's ADMM alone: no finish, no cap on converged
UNCAPPED = {"polish_rounds": 1, "max_gap": 1.0}


def delays(k: int) -> list[float]:
    """25 delays [µs], K/25.6 rows apart: K = 128 spans ±60 rows (±85 with the exposures), so every offset is
    lit (an unlit offset is held only by α and β, and its pixels crawl to convergence)."""
    step = 85.0 * k / 128
    return [step * (i - 12) for i in range(25)]


def device_line(jax) -> str:
    """What the solver ran on: JAX's first device and backend, JAX's version and the host's CPU cores (timings
    compare only on the same)."""
    return (f"{jax.devices()[0].device_kind} ({jax.default_backend()}), JAX {jax.__version__}, "
            f"{os.cpu_count()} CPU cores")


def peak_rss_gb() -> float:
    """This process's peak resident memory [GB]."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB on Linux


def offsets(k: int) -> np.ndarray:
    """The K offsets [rows], −K/2 … K/2 − 1."""
    return np.arange(-k // 2, k // 2)


def kept(k: int) -> np.ndarray:
    """The frames the stage keeps: its default rule drops the 6 whose exposure edge cuts the epipolar row."""
    from selpath.stages.procam._illumination import epipolar_boundary

    d, e = np.meshgrid(delays(k), EXPOSURES_US, indexing="ij")
    return ~epipolar_boundary(d.ravel(), e.ravel(), sync_offset=0.0, margin=LINE_TIME / 2)


def illumination(delays_us, exposures_us, offsets_rows) -> np.ndarray:
    """The default rig's (N, K) plane-to-ray illumination of every (delay, exposure) pair, delays outer."""
    from selpath.stages.procam._illumination import plane_to_ray_illumination

    d, e = np.meshgrid(delays_us, exposures_us, indexing="ij")
    return plane_to_ray_illumination(d.ravel(), e.ravel(), offsets_rows, scan_speed=SPEED, line_time=LINE_TIME)


def matrix(k: int, kept_only: bool = False) -> np.ndarray:
    """The sweep's (N, K) plane-to-ray illumination matrix (N = 75 frames, or the kept ones)."""
    a = illumination(delays(k), EXPOSURES_US, offsets(k))
    return a[kept(k)] if kept_only else a


def pixels(k: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(truth (n, K), images (n, N) in [0, 1]) for n pixels: a direct peak, a subsurface-like lobe and for 30 % of
    pixels a displaced specular peak, through the illumination model with Poisson and read noise (12-bit counts)."""
    rng = np.random.default_rng(seed)
    o = offsets(k)[None, :]
    truth = (rng.uniform(0.2, 0.9, (n, 1)) * (o == 0)
             + rng.uniform(0, 0.05, (n, 1)) * np.exp(-np.abs(o) / rng.uniform(1, 8, (n, 1)))
             + rng.uniform(0, 0.1, (n, 1)) * (rng.random((n, 1)) < 0.3)
             * np.exp(-(o - rng.uniform(-50, 50, (n, 1))) ** 2 / 8))
    counts = rng.poisson(truth @ matrix(k).T * 1000) + rng.normal(0, 2, (n, 25 * len(EXPOSURES_US)))
    return truth, np.clip(counts, 0, 4095) / 4095


def sample(k: int, n: int, rows: int, cols: int, band: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The first n pixels of the stack's row 0, as the stage sees them: (images of kept frames, clipped flags:
    a frame at 4095 counts is clipped, its light at least that, the one-sided penalty of the stage)."""
    _, images = pixels(k, min(band, rows) * cols, seed=0)  # the first band: row 0, col 0, 1, … come first
    counts = (images[:n] * 4095).astype(np.float32)[:, kept(k)]
    return counts / np.float32(4095), counts >= 4095


def capture(k: int, rows: int, cols: int, band: int = 64):  # sample() relies on band and seeding
    """The lazy (delay, exposure, row, col) capture, one dask task per band of rows."""
    import dask.array as da
    import xarray as xr

    n_d, n_e = 25, len(EXPOSURES_US)

    def band_of(block_id=None):
        r0 = block_id[2] * band
        n = min(band, rows - r0)
        _, images = pixels(k, n * cols, seed=r0)
        return (images.T * 4095).astype(np.float32).reshape(n_d, n_e, n, cols)

    chunks = ((n_d,), (n_e,), tuple(min(band, rows - r) for r in range(0, rows, band)), (cols,))
    stack = da.map_blocks(band_of, dtype=np.float32, chunks=chunks)
    return xr.Dataset({"image": (("delay", "exposure", "row", "col"), stack, {"units": "counts"})},
                      coords={"delay": ("delay", delays(k), {"units": "us"}),
                              "exposure": ("exposure", EXPOSURES_US, {"units": "us"})},
                      attrs={"selpath_kind": "plane_to_ray_capture", "scan_speed_px_per_us": SPEED,
                             "line_time_us": LINE_TIME, "dark_level_counts": 0.0, "saturation_counts": 4095.0})


def default_cvxpy_seconds(problem, images: np.ndarray, count: int = 20) -> list[float]:
    """The thesis's way, the peer of every speed-up: per pixel, a CVXPY problem built and solved with CVXPY's
    default solver (the first ``count`` rows of ``images``, all frames as they are); seconds per pixel, each."""
    import cvxpy as cp

    a, k = problem.illumination, problem.offsets
    seconds = []
    for p in range(min(count, images.shape[0])):
        start = time.perf_counter()
        t = cp.Variable(k)
        cp.Problem(cp.Minimize(cp.sum_squares(a @ t - images[p]) + problem.alpha * cp.sum_squares(cp.diff(t))
                               + problem.beta * cp.sum(t)), [t >= 0]).solve()
        seconds.append(time.perf_counter() - start)
    return seconds
