"""Rollouts per second for 3-object scenes: one by one, batched, and raw mj_step (the limit), plus the share of
building models / writing parameters and initial states against the rollouts themselves.

    python benchmarks/bench_simulate.py [--scenes 64] [--threads 2]
"""

from __future__ import annotations

import argparse
import os

import mujoco
import numpy as np
from timing import timed

from aynamics import scene as S
from aynamics import simulate as sim


def three_object_scenes(n: int, seed: int = 0) -> list[S.Scene]:
    """n scenes of a box, a sphere and a cylinder sliding toward each other (so contacts happen)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        v = rng.uniform(-3, 3, size=(3, 2))
        items = [
            {
                "type": "box",
                "size": [0.3, 0.2, 0.15],
                "state": {"position": [-1.5, 0, 0.15], "linear_velocity": [3, *v[0, 1:], 0][:3]},
            },
            {"type": "sphere", "radius": 0.2, "state": {"position": [0, 0.3, 0.2], "linear_velocity": [*v[1], 0]}},
            {
                "type": "cylinder",
                "radius": 0.2,
                "height": 0.4,
                "state": {"position": [1.5, 0, 0.2], "linear_velocity": [-3, *v[2, 1:], 0][:3]},
            },
            {"type": "camera", "position": [0, -5, 4], "orientation": 55, "fovy": 50},
        ]
        for it in items[:3]:
            it["physics"] = {
                "friction": [float(rng.uniform(0.2, 1.0)), float(rng.uniform(0, 0.05))],
                "mass": float(rng.uniform(0.5, 3)),
            }
        out.append(S.from_items(items))
    return out


def best_of(fn, repeats: int = 3) -> float:
    return timed(fn, repeats).best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=64)
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 2)
    args = ap.parse_args()
    scenes = three_object_scenes(args.scenes)
    config = sim.SimConfig()
    nstep = config.frames * config.substeps
    sim.simulate_batch(scenes, nthread=args.threads)  # warm caches (template compile, batch)

    t_one = best_of(lambda: [sim.simulate(s) for s in scenes])
    t_batch = best_of(lambda: sim.simulate_batch(scenes, nthread=args.threads))

    # raw mj_step on the same model: one MjData, a Python loop over scenes, the C loop inside mj_step
    model, tpl = sim.compile_scene(scenes[0])
    data = mujoco.MjData(model)
    inits = [sim.initial_qpos_qvel(s, tpl) for s in scenes]

    def raw():
        for qpos, qvel in inits:
            mujoco.mj_resetData(model, data)
            data.qpos[:], data.qvel[:] = qpos, qvel
            mujoco.mj_step(model, data, nstep)

    t_raw = best_of(raw)

    # setup (parameters + initial states written into the cached batch) vs the rollout call itself
    structure = scenes[0].structure

    def setup():
        sim.prepare_batch(scenes, structure, args.threads)

    t_setup = best_of(setup)
    b, _ = sim.prepare_batch(scenes, structure, args.threads)
    t_roll = (
        best_of(
            lambda: (
                sim.prepare_batch(scenes, structure, args.threads),
                b.rollout(nstep, record=("qpos", "qvel", "sensordata")),
            )
        )
        - t_setup
    )
    # first-time cost: compiling the template for a new structure
    sim.template.cache_clear()
    t_compile = best_of(lambda: (sim.template.cache_clear(), sim.template(structure)), repeats=5)

    n = len(scenes)
    print(f"machine: {os.cpu_count()} cores; {n} scenes of 3 objects, 1 s at 30 FPS x 8 substeps ({nstep} steps)")
    print(f"  one by one (simulate):        {n / t_one:8.1f} rollouts/s")
    ratio = t_one / t_batch
    print(f"  batched ({args.threads} threads): {n / t_batch:8.1f} rollouts/s, {ratio:5.2f}x one-by-one (target 1.7x)")
    print(f"  raw mj_step, 1 thread:        {n / t_raw:8.1f} rollouts/s   ({n * nstep / t_raw:,.0f} steps/s)")
    print(f"  batched vs raw 1-thread:      {t_raw / t_batch:5.2f}x")
    print(
        f"  setup (params + initial states) {t_setup / n * 1e3:6.3f} ms/scene"
        f" vs rollout {t_roll / n * 1e3:6.3f} ms/scene: "
        f"{t_setup / t_roll:5.1%} of the rollouts (target <= 20%)"
    )
    print(f"  template compile (once per structure): {t_compile * 1e3:6.2f} ms")


if __name__ == "__main__":
    main()
