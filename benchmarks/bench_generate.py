"""Dataset generation speed: full scenes per minute on this machine next to the render-only bound.

    .venv/bin/python benchmarks/bench_generate.py [--num 24] [--width 480 --height 320] [--workers 2]

Render-only: the same frames (10 RGB + segmentation + depth, and segmentation + depth of the 10 next frames for
flow) rendered for already simulated scenes, nothing else. Full: sampling, simulation, rendering, flow, reasoning
text and PNG encoding in the same worker pool; then the Arrow writes; then one end-to-end `generate` run
(including worker start-up). Targets of the issue: >= 60 full scenes per minute on 2 cores, within 1.5x of the
render-only bound.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from aynamics import generate as gen  # noqa: E402


def _init(config: gen.GenerateConfig) -> None:
    gen._worker_init(config)


def _render_only(job: tuple[int, int]) -> float:
    index, seed = job
    config, renderer = gen._WORKER["config"], gen._WORKER["renderer"]
    scene, rollout, _ = gen.sample_simulated(index, seed, config)  # not timed
    t = time.perf_counter()
    from aynamics.flow import sample_frames

    idx = sample_frames(len(rollout.t) - 1, config.stride)
    renderer.render(scene, rollout, seed=index, states=idx)
    renderer.render(scene, rollout, seed=index, states=idx + 1, rgb=False)
    return time.perf_counter() - t


def _full(job: tuple[int, int]) -> dict:
    return gen._worker_record(job)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--num", type=int, default=24)
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--height", type=int, default=320)
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args()
    import multiprocessing as mp

    config = gen.GenerateConfig(width=a.width, height=a.height, workers=a.workers, chunk_size=8)
    jobs = [(i, 0) for i in range(a.num)]
    print(f"machine: {os.cpu_count()} CPU cores; {a.num} scenes at {a.width}x{a.height}, {a.workers} workers")
    with mp.get_context("spawn").Pool(a.workers, initializer=_init, initargs=(config,)) as pool:
        pool.map(_full, [(10_000 + k, 0) for k in range(a.workers)])  # warm up: imports, GL contexts, textures
        t = time.perf_counter()
        pool.map(_render_only, jobs, chunksize=1)
        render_s = time.perf_counter() - t
        t = time.perf_counter()
        records = pool.map(_full, jobs, chunksize=1)
        full_s = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "chunks").mkdir()
        t = time.perf_counter()
        for c, r in enumerate(gen.chunk_ranges(a.num, config.chunk_size)):
            gen._write_chunk(Path(d), c, records[r.start : r.stop])
        write_s = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        gen.generate(d, a.num, 0, config, progress=False)
        e2e_s = time.perf_counter() - t
    per_min = lambda s: 60 * a.num / s  # noqa: E731
    print(f"render-only bound    : {per_min(render_s):7.1f} scenes/min ({render_s / a.num * 1e3:.0f} ms/scene wall)")
    print(f"full records (pool)  : {per_min(full_s):7.1f} scenes/min ({full_s / a.num * 1e3:.0f} ms/scene wall)")
    print(f"  + Arrow chunk writes: {per_min(full_s + write_s):7.1f} scenes/min (writes {write_s:.2f} s)")
    print(f"end-to-end generate  : {per_min(e2e_s):7.1f} scenes/min ({e2e_s:.1f} s incl. worker start-up)")
    print(f"ratio full+write / render-only: {(full_s + write_s) / render_s:.2f}x (target <= 1.5x)")
    print(f"ratio end-to-end / render-only: {e2e_s / render_s:.2f}x")


if __name__ == "__main__":
    main()
