"""What keeping clipped frames as lower bounds costs (#30): time per pixel and accuracy, against masking them.

The benchmark stack of ``demux_throughput.py`` (K = 128, 25 delays × 3 exposures, 69 frames kept) with a share of
its pixels made highlights: their direct peak is raised to 1.5–20× the clip level, so every frame that sees it
clips (the hard case: the peak is known only as a bound; HDR from a sweep whose short exposure stays unclipped is
tested in tests/stages/procam/test_demux_highlight.py). Three solves of the same pixels with the stage's solver and
defaults, float32, each timed on its second run (the first compiles the calls' shapes; since #25's certified
defaults the ratios include the finish on each run's own tail above max_gap, which differs between the three):

* ``ideal``: a sensor that never clips (the unclipped frames), the accuracy any method could reach;
* ``masked``: clipped frames dropped, selpath's rule before #30;
* ``bounded``: clipped frames as the one-sided penalty max(0, s − A_i T)², the stage's rule now.

Printed per method: µs per pixel (all pixels, and the cost ratio to the ideal's), mean iterations, and on the
highlight pixels the light recovered in the peak's window against the truth (the median of recovered/true) and
how many pixels are flagged censored.

    python -m benchmarks.demux_clipped [--pixels 32768] [--share 0.1]

Last line: ``demux_clipped: cost_ratio=<bounded/masked time> window_ratio=<median recovered/true, bounded>
censored=<share of highlight pixels flagged>``
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixels", type=int, default=32768)
    parser.add_argument("--share", type=float, default=0.1, help="share of pixels that are highlights")
    args = parser.parse_args()

    from benchmarks._demux_sweep import matrix as _matrix
    from benchmarks._demux_sweep import offsets as _offsets
    from benchmarks._demux_sweep import pixels as _pixels
    from selpath.stages.procam.solver import DemuxADMM, DemuxProblem, solve_pixels

    k = 128
    matrix = _matrix(k, kept_only=True)
    problem = DemuxProblem.build(matrix)
    truth, _ = _pixels(k, args.pixels, seed=1)
    rng = np.random.default_rng(2)
    offsets = _offsets(k)
    bright = rng.random(args.pixels) < args.share
    # highlight peaks in units of the clip level: scaled images are counts / 4095 (the sweep's counts are ×1000)
    truth[bright, offsets == 0] = rng.uniform(1.5, 20.0, bright.sum()) * 4.095
    ideal = truth @ matrix.T * 1000 / 4095 + rng.normal(0, 2 / 4095, (args.pixels, matrix.shape[0]))
    clipped = ideal >= 1.0
    data = np.where(clipped, 1.0, ideal)
    window = np.abs(offsets) <= 5
    solver = DemuxADMM()
    runs = {
        "ideal": (ideal, np.ones_like(clipped), None),
        "masked": (data, ~clipped, None),
        "bounded": (data, np.ones_like(clipped), clipped),
    }
    print(f"{args.pixels} pixels, {bright.mean():.1%} highlights ({clipped.any(1).mean():.1%} of pixels with a "
          f"clipped frame, {clipped.mean():.1%} of observations); K = {k}, N = {matrix.shape[0]}, float32, "
          f"the stage's defaults")
    print(f"{'method':<10}{'µs/px':>8}{'× ideal':>9}{'iterations':>12}{'window recovered/true (median, p10)':>38}"
          f"{'censored':>10}")
    results = {}
    for name, (y, weight, flags) in runs.items():
        solve_pixels(solver, problem, y, weight, flags)  # the same calls: every shape compiled
        start = time.perf_counter()
        solution = solve_pixels(solver, problem, y, weight, flags)
        seconds = (time.perf_counter() - start) / args.pixels
        recovered = solution.value[bright][:, window].sum(1) * 4095 / 1000
        ratio = recovered / truth[bright][:, window].sum(1)
        censored = float(np.mean(solution.stats["censored_offsets"][bright] > 0))
        results[name] = {"s": seconds, "ratio": float(np.median(ratio)), "censored": censored}
        print(f"{name:<10}{seconds * 1e6:>8.1f}{seconds / results['ideal']['s']:>9.2f}"
              f"{solution.stats['iterations'].mean():>12.1f}{np.median(ratio):>26.3f}{np.percentile(ratio, 10):>12.3f}"
              f"{censored:>10.1%}")
    cost = results["bounded"]["s"] / results["masked"]["s"]
    print(f"demux_clipped: cost_ratio={cost:.2f} window_ratio={results['bounded']['ratio']:.3f} "
          f"censored={results['bounded']['censored']:.3f}")


if __name__ == "__main__":
    main()
