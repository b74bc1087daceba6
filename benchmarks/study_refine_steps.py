"""Study: which initial CMA-ES step scale (`refine`'s `sigma_scale`) refines best, from close, medium and far starts.

For each of N sampled scenes (1-3 objects, seed 7), every object's horizontal position and velocity get normal
errors of the level's size; `refine` (default params: positions, orientations, velocities) then runs with each
step scale at the same budget, against the true scene's own observation. Prints each scene's start and final
full-sequence IoU per scale and their means. `refine_space.DEFAULT_SIGMA_SCALE` quotes its output (2 cores,
about 3 minutes per level for 3 scales).

    python benchmarks/study_refine_steps.py [--level close|medium|far] [--scales 1,0.3,0.1] [--scenes 10]
"""

from __future__ import annotations

import argparse

import numpy as np

from aynamics.observation import Observation
from aynamics.refine import refine
from aynamics.sampler import SamplerConfig, sample_scene, scene_seed
from aynamics.scene import SceneError, from_items, to_items

LEVELS = {"close": (0.1, 0.4), "medium": (0.3, 1.0), "far": (2.0, 3.0)}  # error sd: position m, velocity m/s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--level", choices=sorted(LEVELS), default="close")
    ap.add_argument("--scales", default="1,0.3,0.1")
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--budget", type=int, default=400)
    args = ap.parse_args()
    scales = [float(s) for s in args.scales.split(",")]
    dpos, dvel = LEVELS[args.level]
    rows = []
    for i in range(args.scenes):
        truth = sample_scene(np.random.default_rng(scene_seed(7, i)), SamplerConfig(max_objects=3))
        rng = np.random.default_rng(100 + i)
        items = to_items(truth)
        for it in items:
            if "state" in it:
                st = it["state"]
                st["position"][:2] = np.add(st["position"][:2], rng.normal(0, dpos, 2)).tolist()
                st["linear_velocity"][:2] = np.add(st["linear_velocity"][:2], rng.normal(0, dvel, 2)).tolist()
        try:
            pred = from_items(items)
        except SceneError as e:  # an error that leaves the range table
            print(f"scene {i}: skipped ({e})")
            continue
        observed = Observation.from_scene(truth)
        row = {}
        for s in scales:
            result = refine(pred, observed, budget=args.budget, seconds=600, sigma_scale=s, nthread=1)
            row["start"], row[s] = result.before.iou_full, result.after.iou_full
        rows.append(row)
        print(f"scene {i}: start {row['start']:.3f}", " ".join(f"x{s:g}: {row[s]:.3f}" for s in scales), flush=True)
    means = " ".join(f"x{s:g}: {np.mean([r[s] for r in rows]):.3f}" for s in scales)
    print(f"{args.level}: {len(rows)} scenes, mean start IoU {np.mean([r['start'] for r in rows]):.3f}, final {means}")


if __name__ == "__main__":
    main()
