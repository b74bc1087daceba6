"""Seconds per full record: 30 frames of RGB + segmentation + depth and 29 exact flow maps at 480×320.

    python benchmarks/bench_render.py [--repeats 5]

Prints the best and the median over repeats (the machine may be shared: the load average is printed) with one
reused OpenGL context (`Renderer`), and the parts: RGB alone, segmentation + depth alone, the exact flow with
occlusion masks, and its colour coding. The scene is tests/assets/paper_example.yaml.
"""

from __future__ import annotations

import argparse
import os

from timing import timed

from aynamics import flow as flowlib
from aynamics import render as renderlib
from aynamics import scene as S
from aynamics import simulate as sim


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    ok, why = renderlib.gl_available()
    if not ok:
        print(f"skipped: {why}")
        return
    scene = S.load(os.path.join(os.path.dirname(__file__), "..", "tests", "assets", "paper_example.yaml"))
    rollout = sim.simulate(scene)
    print(f"machine: {os.cpu_count()} CPU cores, OpenGL backend {renderlib.gl_backend()}, 480×320")
    print(f"load average: {' '.join(f'{x:.1f}' for x in os.getloadavg())} (1, 5, 15 min)")
    with renderlib.Renderer() as r:
        r.render(scene, rollout, seed=0)  # warm-up: texture loading, shader compilation

        def record():
            frames = r.render(scene, rollout, seed=1)
            flow = flowlib.motion_flow(scene, rollout, frames.depth, frames.camera, frames.segmentation)
            return frames, flow

        n = args.repeats
        total, total_med, (frames, (flow, _)) = timed(record, n)
        rgb, rgb_med, _ = timed(lambda: r.render(scene, rollout, seed=1, segmentation=False, depth=False), n)
        segdepth, segdepth_med, _ = timed(lambda: r.render(scene, rollout, seed=1, rgb=False), n)
        flow_s, flow_med, _ = timed(
            lambda: flowlib.motion_flow(scene, rollout, frames.depth, frames.camera, frames.segmentation), n
        )
        colour, colour_med, _ = timed(lambda: flowlib.flow_to_color(flow), n)
    k = len(frames.rgb)
    print(f"best (median) of {n} repeats")
    print(f"full record ({k} frames RGB + seg + depth, {k - 1} flow maps): {total:.3f} s ({total_med:.3f})")
    print(f"  RGB alone:               {rgb:.3f} s ({rgb_med:.3f})  {k / rgb:.0f} frames/s")
    print(f"  segmentation + depth:    {segdepth:.3f} s ({segdepth_med:.3f})  {k / segdepth:.0f} frames/s")
    print(f"  exact flow + occlusion:  {flow_s:.3f} s ({flow_med:.3f})  {(k - 1) / flow_s:.0f} maps/s")
    print(f"  flow colour coding:      {colour:.3f} s ({colour_med:.3f})  (not part of the record above)")


if __name__ == "__main__":
    main()
