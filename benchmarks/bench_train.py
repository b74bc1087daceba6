"""Training throughput and peak memory of the tiny model on the CPU: frames as images vs one video, and gradient
checkpointing off vs on.

    python benchmarks/bench_train.py [--data DIR] [--steps 6] [--batch-size 4] [--frames 4]

Each configuration runs in a fresh process (so its peak resident memory is its own): build the model and the
data module, run `steps` optimizer steps (the first is a warm-up, not timed), print samples/s and the peak RSS
increase over the process after setup. Uses `data/generated/make_train_plain` when present, else generates 12 scenes at
64×48 into a temporary folder with the real generator. Numbers depend on the machine and its load: compare the
ratios printed at the end, measured in one run.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = [
    ("images", False, False),
    ("images + checkpointing", False, True),
    ("video", True, False),
    ("video + checkpointing", True, True),
]


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB


def _measure(args: tuple) -> dict:
    data, as_video, checkpointing, steps, batch_size, frames, tiny = args
    import torch

    from aynamics import lm
    from aynamics.data import SceneDataModule
    from aynamics.processor import model_inputs

    torch.manual_seed(0)
    spec = lm.ModelSpec(kind="tiny", tiny=tiny, gradient_checkpointing=checkpointing, lora_dropout=0.0)
    model = lm.build_model(spec)
    dm = SceneDataModule(data, spec.processor_path, num_frames=frames, as_video=as_video, batch_size=batch_size)
    dm.setup("fit")
    ds = dm.dataset("train")
    batches = [dm._collate([ds[(s * batch_size + i) % len(ds)] for i in range(batch_size)]) for s in range(steps)]
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-3)
    base = _peak_rss_mb()
    times = []
    for batch in batches:
        t = time.perf_counter()
        loss, _ = lm.sft_loss(model(**model_inputs(batch), use_cache=False).logits, batch["labels"])
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
        times.append(time.perf_counter() - t)
    timed = times[1:]  # the first step warms up allocators and kernels
    return {
        "samples_per_s": batch_size * len(timed) / sum(timed),
        "step_s": sum(timed) / len(timed),
        "tokens": int(batches[0]["input_ids"].numel()),
        "peak_rss_mb": _peak_rss_mb(),
        "train_rss_mb": _peak_rss_mb() - base,
    }


def _dataset(path: str | None) -> str:
    if path:
        return path
    default = ROOT / "data" / "generated" / "make_train_plain"
    if (default / "dataset_dict.json").is_file():
        return str(default)
    from aynamics.generate import GenerateConfig, generate_dataset

    out = Path(tempfile.mkdtemp(prefix="bench_train_")) / "data"
    print(f"generating 12 scenes at 64x48 into {out} ...", flush=True)
    generate_dataset(
        out, num=12, seed=0, config=GenerateConfig(width=64, height=48, workers=0, splits=(0.5, 0.25, 0.25))
    )
    return str(out)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", help="generated data set folder (default: data/generated/make_train_plain or a fresh one)")
    p.add_argument("--steps", type=int, default=6, help="optimizer steps per configuration (first untimed)")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--frames", type=int, default=4, help="frames per example")
    p.add_argument("--tiny", default="{}", help="tiny model overrides as JSON, e.g. '{\"hidden_size\": 128}'")
    args = p.parse_args(argv)
    if args.steps < 2:
        raise SystemExit(f"--steps = {args.steps}: need >= 2 (the first is a warm-up)")
    data = _dataset(args.data)
    tiny = json.loads(args.tiny)
    print(
        f"tiny model {tiny or 'default'}, batch {args.batch_size}, {args.frames} frames, {args.steps} steps, CPU "
        f"threads {os.cpu_count()}, data {data}"
    )
    results = {}
    ctx = mp.get_context("spawn")
    for name, as_video, ckpt in CONFIGS:
        with ctx.Pool(1) as pool:
            r = pool.apply(_measure, ((data, as_video, ckpt, args.steps, args.batch_size, args.frames, tiny),))
        results[name] = r
        print(
            f"  {name:<24} {r['samples_per_s']:7.2f} samples/s  {r['step_s'] * 1000:8.0f} ms/step  "
            f"{r['tokens']:6d} tokens/batch  peak RSS {r['peak_rss_mb']:7.0f} MB  "
            f"(+{r['train_rss_mb']:.0f} MB in training)",
            flush=True,
        )
    img, vid = results["images"], results["video"]
    print(
        f"video / images throughput: {vid['samples_per_s'] / img['samples_per_s']:.2f}x, "
        f"tokens per batch {vid['tokens'] / img['tokens']:.2f}x"
    )
    for kind in ("images", "video"):
        on, off = results[f"{kind} + checkpointing"], results[kind]
        print(
            f"checkpointing on / off ({kind}): throughput {on['samples_per_s'] / off['samples_per_s']:.2f}x, "
            f"training memory {on['train_rss_mb'] / max(off['train_rss_mb'], 1e-9):.2f}x"
        )


if __name__ == "__main__":
    sys.exit(main())
