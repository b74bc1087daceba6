"""Dataset generation speed: full scenes per minute on this machine next to the render-only bound.

    .venv/bin/python benchmarks/bench_generate.py [--num 24] [--width 480 --height 320] [--workers 2] [--repeats 2]

Render-only bound: exactly the OpenGL work a record needs (`generate.render_sampled`: RGB, segmentation and depth
of the 10 sampled frames, same scenes, same looks), for already simulated scenes, nothing else, in the same worker
pool. Full: sampling, simulation, rendering, flow, reasoning text and PNG encoding in that pool; then the Arrow
chunk writes; then one end-to-end `generate` run (worker start-up included). The two pool measurements alternate
in blocks of 4 scenes per worker, each block timed as the best of `--repeats` runs, so that both see the same load
on a shared machine (the load average is printed). Then a one-process breakdown of a record into its stages, and
the PNG encoder next to Pillow's. Targets of the issue: >= 60 full scenes per minute on 2 cores, within 1.5x of
the render-only bound.
"""

from __future__ import annotations

import argparse
import io
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import timing  # noqa: E402

from aynamics import generate as gen  # noqa: E402


def _init(config: gen.GenerateConfig) -> None:
    gen._worker_init(config)


def _simulated(job: tuple[int, int]) -> tuple:
    index, seed = job
    scene, rollout, attempt = gen.sample_simulated(index, seed, gen._WORKER["config"])
    return scene, rollout, gen.appearance_seed(seed, index, attempt)


def _render_only(job: tuple) -> float:
    scene, rollout, look = job
    t = time.perf_counter()
    gen.render_sampled(scene, rollout, gen._WORKER["renderer"], gen._WORKER["config"], look)
    return time.perf_counter() - t


def _full(job: tuple[int, int]) -> dict:
    return gen._worker_record((*job, None))  # (index, seed, no scene file): a sampled scene


def _best(fn, repeats: int) -> tuple[float, object]:
    t = timing.timed(fn, repeats)
    return t.best, t.result


def stages(config: gen.GenerateConfig, indices: range) -> dict[str, float]:
    """Mean seconds per scene of each stage of `make_record`, in this process (one OpenGL context)."""
    from aynamics import reasoning as rs
    from aynamics.render import Renderer

    total: dict[str, float] = {}

    def timed(name, fn, *a, **kw):
        t = time.perf_counter()
        out = fn(*a, **kw)
        total[name] = total.get(name, 0.0) + time.perf_counter() - t
        return out

    with Renderer(config.width, config.height) as r:
        gen.make_record(10_000, 0, config, r)  # warm-up
        for i in indices:
            scene, rollout, attempt = timed("sample + simulate", gen.sample_simulated, i, 0, config)
            look = gen.appearance_seed(0, i, attempt)
            fr = timed("render (RGB + seg + depth)", gen.render_sampled, scene, rollout, r, config, look)
            colours, _ = timed("exact flow + colours", gen.flow_images, fr, rollout)
            visible = timed("visibility + reasoning", rs.visibility, fr.segmentation, len(scene.objects))
            timed("visibility + reasoning", rs.reasoning_text, scene, rollout, visible, rollout.t[fr.states], seed=look)
            images = [*fr.rgb, *colours, *(fr.segmentation + 1).astype(np.uint8)]
            timed("PNG encoding (30 images)", lambda images=images: [gen._png(x) for x in images])
        t = time.perf_counter()
        for i in indices:
            gen.make_record(i, 0, config, r)
        total["whole make_record"] = time.perf_counter() - t
    return {k: v / len(indices) for k, v in total.items()}


def png_comparison(config: gen.GenerateConfig) -> tuple[float, float, float, float]:
    """ms per RGB frame and kB per frame: `png_bytes` vs Pillow (compress_level=1, Z_RLE, as before)."""
    from PIL import Image

    from aynamics.render import Renderer

    with Renderer(config.width, config.height) as r:
        scene, rollout, attempt = gen.sample_simulated(0, 0, config)
        rgb = gen.render_sampled(scene, rollout, r, config, gen.appearance_seed(0, 0, attempt)).rgb

    def pillow(im):
        buf = io.BytesIO()
        Image.fromarray(im).save(buf, format="PNG", compress_level=1, compress_type=3)
        return buf.getvalue()

    ours_s, ours = _best(lambda: [gen.png_bytes(im) for im in rgb], 3)
    pil_s, pil = _best(lambda: [pillow(im) for im in rgb], 3)
    n = len(rgb)
    size = lambda out: sum(map(len, out)) / n / 1e3  # noqa: E731
    return ours_s / n * 1e3, size(ours), pil_s / n * 1e3, size(pil)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--num", type=int, default=24)
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--height", type=int, default=320)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--repeats", type=int, default=2, help="pool measurements: best of this many runs")
    p.add_argument("--stages", type=int, default=6, help="scenes of the one-process stage breakdown (0: skip)")
    a = p.parse_args()
    import multiprocessing as mp

    config = gen.GenerateConfig(width=a.width, height=a.height, workers=a.workers, chunk_size=8)
    jobs = [(i, 0) for i in range(a.num)]
    print(f"machine: {os.cpu_count()} CPU cores; {a.num} scenes at {a.width}x{a.height}, {a.workers} workers")
    print(f"load average before: {' '.join(f'{x:.1f}' for x in os.getloadavg())} (1, 5, 15 min)")
    block = 4 * a.workers  # render-only and full alternate block by block: both see the same machine load
    render_s = full_s = 0.0
    records: list[dict] = []
    with mp.get_context("spawn").Pool(a.workers, initializer=_init, initargs=(config,)) as pool:
        pool.map(_full, [(10_000 + k, 0) for k in range(a.workers)])  # warm up: imports, GL contexts, textures
        simulated = pool.map(_simulated, jobs, chunksize=1)  # not timed
        for start in range(0, a.num, block):
            part = slice(start, start + block)
            t, _ = _best(lambda part=part: pool.map(_render_only, simulated[part], chunksize=1), a.repeats)
            render_s += t
            t, out = _best(lambda part=part: pool.map(_full, jobs[part], chunksize=1), a.repeats)
            full_s += t
            records += out

    def write_all() -> None:
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / "chunks").mkdir()
            for c, r in enumerate(gen.chunk_ranges(a.num, config.chunk_size)):
                gen.write_chunk(Path(d), c, records[r.start : r.stop])

    write_s, _ = _best(write_all, a.repeats)

    def end_to_end() -> None:
        with tempfile.TemporaryDirectory() as d:
            gen.generate(d, a.num, 0, config, progress=False)

    e2e_s, _ = _best(end_to_end, a.repeats)
    per_min = lambda s: 60 * a.num / s  # noqa: E731
    print(f"render-only bound    : {per_min(render_s):7.1f} scenes/min ({render_s / a.num * 1e3:.0f} ms/scene wall)")
    print(f"full records (pool)  : {per_min(full_s):7.1f} scenes/min ({full_s / a.num * 1e3:.0f} ms/scene wall)")
    print(f"  + Arrow chunk writes: {per_min(full_s + write_s):7.1f} scenes/min (writes {write_s:.2f} s)")
    print(f"end-to-end generate  : {per_min(e2e_s):7.1f} scenes/min ({e2e_s:.1f} s incl. worker start-up)")
    print(f"ratio full / render-only: {full_s / render_s:.2f}x (target <= 1.5x)")
    print(f"ratio full+write / render-only: {(full_s + write_s) / render_s:.2f}x")
    print(f"ratio end-to-end / render-only: {e2e_s / render_s:.2f}x")
    print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    if a.stages > 0:
        one = gen.GenerateConfig(width=a.width, height=a.height, workers=0)
        print(f"one process, mean over {a.stages} scenes (ms per scene):")
        for name, s in stages(one, range(100, 100 + a.stages)).items():
            print(f"  {name:28s} {s * 1e3:7.1f}")
        ours_ms, ours_kb, pil_ms, pil_kb = png_comparison(one)
        print(
            f"PNG of an RGB frame: png_bytes {ours_ms:.1f} ms, {ours_kb:.0f} kB; Pillow (level 1, Z_RLE) "
            f"{pil_ms:.1f} ms, {pil_kb:.0f} kB: {pil_ms / ours_ms:.2f}x faster, {ours_kb / pil_kb:.2f}x the size"
        )


if __name__ == "__main__":
    main()
