"""The scorer: 32 candidates × 10 frames against one observed video, as candidates per second, next to
(a) a naive loop that simulates each candidate and renders it at 480×320 with OpenGL, and (b) the physics alone.

    python benchmarks/bench_scorer.py [--candidates 32] [--repeats 5]

Targets on 2 cores: >= 20× the naive loop, <= 0.3 s per 32-candidate case.
"""

from __future__ import annotations

import argparse
import os

import numpy as np
from timing import timed

from aynamics import flow as flowlib
from aynamics import metrics, observation, scorer
from aynamics import render as renderlib
from aynamics import scene as S
from aynamics import simulate as sim

OBSERVED = S.parse(
    """
- {type: box, name: box_0, size: [0.3, 0.2, 0.15], state: {position: [-1.2, 0.8, 0.15], linear_velocity: [3, 0.2, 0]}}
- {type: sphere, name: sphere_0, radius: 0.2, state: {position: [0, 1.1, 0.2], linear_velocity: [0.5, -0.3, 0]}}
- {type: cylinder, name: cyl_0, radius: 0.2, height: 0.4,
   state: {position: [1.2, 0.8, 0.2], linear_velocity: [-3, 0, 0]}}
- type: camera
  position: [0, -2.5, 3.5]
"""
)


def candidates(n: int, seed: int = 0) -> list[S.Scene]:
    """CMA-ES-like perturbations of the observed scene: positions ±0.2 m, velocities ±0.5 m/s, own cameras."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        objs = []
        for o in OBSERVED.objects:
            p = np.array(o.state.position) + np.r_[rng.uniform(-0.2, 0.2, 2), 0]
            v = np.array(o.state.linear_velocity) + np.r_[rng.uniform(-0.5, 0.5, 2), 0]
            state = o.state.model_copy(update={"position": tuple(p), "linear_velocity": tuple(v)})
            objs.append(o.model_copy(update={"state": state}))
        cam = OBSERVED.camera.model_copy(update={"fovy": 45 + rng.uniform(-3, 3)})
        out.append(S.from_items(S.to_items(OBSERVED.model_copy(update={"objects": tuple(objs), "camera": cam}))))
    return out


def naive(cands: list[S.Scene], obs: observation.Observation, r: renderlib.Renderer) -> list[float]:
    """One candidate at a time: simulate, render segmentation + depth at 480×320 with OpenGL, flow, metrics."""
    out = []
    for c in cands:
        rollout = sim.simulate(c)
        frames = r.render(c, rollout, rgb=False, states=obs.frames)
        flows = []
        for fi, k in enumerate(obs.frames):
            f, _ = flowlib.motion_field(
                frames.depth[fi],
                frames.segmentation[fi],
                frames.camera,
                rollout.position[k : k + 2],
                rollout.orientation[k : k + 2],
            )
            flows.append(f)
        rows = ((np.arange(obs.height) + 0.5) * r.height / obs.height).astype(int)
        cols = ((np.arange(obs.width) + 0.5) * r.width / obs.width).astype(int)
        seg = frames.segmentation[:, rows][:, :, cols]
        flow = np.stack(flows)[:, rows][:, :, cols] * (obs.width / r.width)
        out.append(metrics.segmentation_iou(seg, obs.segmentation)[1])
        metrics.flow_epe(flow, obs.flow, seg, obs.segmentation, obs.occluded)
    return out


def median_time(fn, repeats: int) -> float:
    return timed(fn, repeats).median


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    cands = candidates(args.candidates)
    obs = observation.Observation.from_scene(OBSERVED)
    n = len(cands)
    print(f"machine: {os.cpu_count()} CPU cores; {n} candidates × {len(obs.frames)} frames at {obs.width}×{obs.height}")
    scorer.score(cands, obs)  # warm-up: template compile, Batch allocation
    t_score = median_time(lambda: scorer.score(cands, obs), args.repeats)
    t_phys = median_time(lambda: sim.rollout_raw(cands, OBSERVED.structure), args.repeats)
    print(f"scorer:        {t_score:.3f} s per case  {n / t_score:8.1f} candidates/s")
    print(
        f"physics alone: {t_phys:.3f} s per case  {n / t_phys:8.1f} candidates/s  "
        f"(scorer = {t_score / t_phys:.1f}× physics)"
    )
    ok, why = renderlib.gl_available()
    if not ok:
        print(f"naive OpenGL loop skipped: {why}")
        return
    with renderlib.Renderer() as r:
        naive(cands[:2], obs, r)  # warm-up
        t_naive = median_time(lambda: naive(cands, obs, r), max(1, args.repeats // 2))
    print(f"naive loop:    {t_naive:.3f} s per case  {n / t_naive:8.1f} candidates/s")
    print(f"speed-up over the naive loop: {t_naive / t_score:.1f}×  (target >= 20×; target <= 0.3 s per case)")


if __name__ == "__main__":
    main()
