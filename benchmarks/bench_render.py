"""Seconds per full record: 30 frames of RGB + segmentation + depth and 29 exact flow maps at 480×320.

    python benchmarks/bench_render.py [--repeats 3]

Prints the median over repeats with one reused OpenGL context (`Renderer`), and its parts: RGB alone,
segmentation + depth alone, and the flow computation.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from aynamics import flow as flowlib
from aynamics import render as renderlib
from aynamics import scene as S
from aynamics import simulate as sim


def timed(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    ok, why = renderlib.gl_available()
    if not ok:
        print(f"skipped: {why}")
        return
    scene = S.load(os.path.join(os.path.dirname(__file__), "..", "tests", "assets", "paper_example.yaml"))
    rollout = sim.simulate(scene)
    print(f"machine: {os.cpu_count()} CPU cores, OpenGL backend {renderlib.gl_backend()}, 480×320")
    with renderlib.Renderer() as r:
        r.render(scene, rollout, seed=0)  # warm-up: texture loading, shader compilation

        def record():
            frames = r.render(scene, rollout, seed=1)
            flow = flowlib.motion_flow(scene, rollout, frames.depth, frames.camera, frames.segmentation)
            return frames, flow

        total, (frames, _) = timed(record, args.repeats)
        rgb, _ = timed(lambda: r.render(scene, rollout, seed=1, segmentation=False, depth=False), args.repeats)
        segdepth, _ = timed(lambda: r.render(scene, rollout, seed=1, rgb=False), args.repeats)
        flow, _ = timed(
            lambda: flowlib.motion_flow(scene, rollout, frames.depth, frames.camera, frames.segmentation), args.repeats
        )
    n = len(frames.rgb)
    print(f"full record ({n} frames RGB + seg + depth, {n - 1} flow maps): {total:.3f} s")
    print(f"  RGB alone:               {rgb:.3f} s  ({n / rgb:.0f} frames/s)")
    print(f"  segmentation + depth:    {segdepth:.3f} s  ({n / segdepth:.0f} frames/s)")
    print(f"  exact flow (29 maps):    {flow:.3f} s")


if __name__ == "__main__":
    main()
