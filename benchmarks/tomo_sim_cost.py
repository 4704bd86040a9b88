"""What each simulated effect costs: one lit frame with straight paths versus Monte Carlo scattering.

Same scene and camera; the Monte Carlo run uses the photons of the shipped §4.4.4 scenes. Prints a table
and, last, ``tomo_sim: straight_s=… monte_carlo_s=… ratio=…``.

    python benchmarks/tomo_sim_cost.py [--rows 64 --cols 96 --photons 400000]
"""

from __future__ import annotations

import argparse
import time

from selpath import workflows
from selpath.devices.sim.scene import Scene, load_scene
from selpath.devices.sim.tomography import lit_frame

SCENE = workflows.scene("cylinder-in-cylinder-s1")


def timed(scene: Scene, repeats: int) -> float:
    best = float("inf")
    for i in range(repeats):
        start = time.perf_counter()
        lit_frame(scene, 10.0 * i, "target")
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=64)
    parser.add_argument("--cols", type=int, default=96)
    parser.add_argument("--photons", type=int, default=400_000)
    args = parser.parse_args()
    base = load_scene(SCENE)
    camera = base.camera.model_copy(update={"rows": args.rows, "cols": args.cols})
    straight = base.model_copy(update={"camera": camera, "effects": base.effects.model_copy(
        update={"scattering": None})})
    print(f"{'sigma_s /mm':>12} {'photons':>9} {'s/frame':>9}")
    t_straight = timed(straight, 5)
    print(f"{'none':>12} {'-':>9} {t_straight:9.4f}")
    times = {}
    for sigma_s in (1.0, 2.0, 3.0, 5.0):
        scattering = base.effects.scattering.model_copy(update={"sigma_s": sigma_s, "photons": args.photons})
        scene = base.model_copy(update={"camera": camera, "effects": base.effects.model_copy(
            update={"scattering": scattering})})
        times[sigma_s] = timed(scene, 2)
        print(f"{sigma_s:12.1f} {args.photons:9d} {times[sigma_s]:9.4f}")
    print(f"tomo_sim: straight_s={t_straight:.4f} monte_carlo_s={times[1.0]:.4f} "
          f"ratio={times[1.0] / t_straight:.0f}")


if __name__ == "__main__":
    main()
