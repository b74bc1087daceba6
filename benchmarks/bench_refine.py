"""Benchmark: CMA-ES refinement of perturbed synthetic scenes against their own observation.

For each of N synthetic scenes (1-3 objects, `aynamics.sampler`), the ground truth is observed by the fast scorer
(segmentation + flow at 120×80, frames 0, 3, ..., 27); a "prediction" is made by adding errors to the initial
positions and velocities (horizontal components, scaled so that the scene's mean absolute error over x, y, z is
the target MAE, as `metrics.state_mae` measures it); `refine` then searches the chosen groups (default:
positions and velocities) within a budget of simulations and seconds. Prints each scene and the distribution
of full-sequence IoU before/after, the share reaching IoU 0.9 within the budget, simulations and seconds to
reach it, for the paper-like and a mild error level. Wall times depend on the machine's load (printed).

    python benchmarks/bench_refine.py [--scenes 20] [--budget 1000] [--seconds 60] [--levels paper,mild]
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from aynamics.metrics import state_mae
from aynamics.observation import Observation
from aynamics.refine import DEFAULT_SIGMA_SCALE, refine
from aynamics.sampler import SamplerConfig, sample_scene, scene_seed
from aynamics.scene import RANGES, Scene, from_items, to_items

LEVELS = {"mild": (0.3, 0.5), "paper": (2.0, 3.0)}  # (position MAE m, velocity MAE m/s) over x, y, z


def perturb(scene: Scene, rng: np.random.Generator, pos_mae: float, vel_mae: float) -> Scene:
    """Add horizontal errors (Laplace directions and sizes, rescaled) so that the scene's mean |error| over its
    objects' x, y, z components is exactly pos_mae / vel_mae (before clipping into the range table)."""
    items = to_items(scene)
    plo, phi = RANGES["state.position"].bounds(3)
    vlo, vhi = RANGES["state.linear_velocity"].bounds(3)
    states = [it["state"] for it in items if "state" in it]
    for key, mae, lo, hi in (("position", pos_mae, plo, phi), ("linear_velocity", vel_mae, vlo, vhi)):
        err = rng.laplace(0.0, 1.0, size=(len(states), 2))
        err *= mae * 3 * len(states) / np.abs(err).sum()  # z gets none: x and y carry the whole mean
        for st, e in zip(states, err, strict=True):
            st[key][:2] = np.clip(np.add(st[key][:2], e), lo[:2], hi[:2]).tolist()
    return from_items(items)


def _reach(trace, target: float) -> tuple[float, float]:
    """(simulations, seconds) when the objective first reached `target`, or (nan, nan)."""
    return next(((float(n), float(t)) for n, t, v, _ in trace if v >= target), (math.nan, math.nan))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--budget", type=int, default=1000)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--levels", default="paper,mild")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stop-at", type=float, default=0.99, help="refine's stop_at (objective value)")
    ap.add_argument("--params", default="position,linear_velocity", help="groups searched (refine's params)")
    ap.add_argument("--sigma-scale", type=float, default=DEFAULT_SIGMA_SCALE, help="refine's initial step scale")
    args = ap.parse_args()
    print(
        f"machine: {os.cpu_count()} CPU cores, load average {os.getloadavg()[0]:.1f} at start; budget "
        f"{args.budget} simulations / {args.seconds:g} s per scene; params {args.params}; stop at {args.stop_at}; "
        f"step scale {args.sigma_scale:g}"
    )
    cfg = SamplerConfig(max_objects=3)
    for level in args.levels.split(","):
        pos_mae, vel_mae = LEVELS[level]
        rows = []
        for i in range(args.scenes):
            truth = sample_scene(np.random.default_rng(scene_seed(args.seed, i)), cfg)
            pred = perturb(truth, np.random.default_rng(1000 + i), pos_mae, vel_mae)
            obs = Observation.from_scene(truth)
            t = time.perf_counter()
            try:
                res = refine(
                    pred,
                    obs,
                    params=args.params.split(","),
                    budget=args.budget,
                    seconds=args.seconds,
                    seed=i,
                    stop_at=args.stop_at,
                    sigma_scale=args.sigma_scale,
                )
            except Exception as e:  # report and go on: one failing scene must not hide the others' figures
                print(f"  [{level}] scene {i:2d} FAILED: {type(e).__name__}: {e}", flush=True)
                continue
            dt = time.perf_counter() - t
            mae0, mae1 = state_mae(pred, truth), state_mae(res.scene, truth)
            n90, t90 = _reach(res.trace, 0.9)
            rows.append((res.before.iou_full, res.after.iou_full, res.simulations, dt, n90, t90, *mae0))
            print(
                f"  [{level}] scene {i:2d} ({len(truth.objects)} obj) IoU_full {res.before.iou_full:.3f} -> "
                f"{res.after.iou_full:.3f}  IoU_first -> {res.after.iou_first:.3f}  pos/vel MAE "
                f"{mae0[0]:.2f}/{mae0[1]:.2f} -> {mae1[0]:.2f}/{mae1[1]:.2f}  sims {res.simulations}  {dt:.1f} s  "
                f"objective >= 0.9 at {n90:.0f} sims / {t90:.1f} s",
                flush=True,
            )
        if not rows:
            print(f"== {level}: no scene finished")
            continue
        b, a, n, s, n90, t90, pm, vm = np.array(rows, dtype=float).T
        q = lambda x: " / ".join(f"{v:.3f}" for v in np.percentile(x, [10, 50, 90]))  # noqa: E731
        hit = np.isfinite(n90) & (n90 <= args.budget) & (t90 <= args.seconds)
        print(
            f"== {level}: target position MAE {pos_mae} m, velocity MAE {vel_mae} m/s; drawn: mean {pm.mean():.2f} m, "
            f"{vm.mean():.2f} m/s; {len(rows)} scenes; load average now {os.getloadavg()[0]:.1f}"
        )
        print(f"   IoU_full before  p10/median/p90: {q(b)}  mean {b.mean():.3f}")
        print(
            f"   IoU_full after   p10/median/p90: {q(a)}  mean {a.mean():.3f}  (after/before mean ratio "
            f"{a.mean() / max(b.mean(), 1e-9):.2f})"
        )
        print(
            f"   share with final IoU_full >= 0.9: {(a >= 0.9).mean():.2f}; share whose objective (IoU_full - 0.01 EPE "
            f"<= IoU_full) reached 0.9 within {args.budget} simulations and {args.seconds:g} s: {hit.mean():.2f}"
        )
        if hit.any():
            print(
                f"   to reach it: simulations median {np.median(n90[hit]):.0f} (max {n90[hit].max():.0f}), "
                f"seconds median {np.median(t90[hit]):.1f} (max {t90[hit].max():.1f})"
            )
        print(
            f"   whole run: simulations median {np.median(n):.0f}, seconds median {np.median(s):.1f}, max {s.max():.1f}"
        )


if __name__ == "__main__":
    main()
