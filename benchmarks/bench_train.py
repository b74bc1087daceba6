"""Training throughput and peak memory of the tiny model on the CPU: frames as images vs one video, and gradient
checkpointing off vs on.

    python benchmarks/bench_train.py [--data DIR] [--steps 6] [--batch-size B] [--frames F] [OVERRIDE ...]
    python benchmarks/bench_train.py experiment=make_train      # the model and targets `make train` trains
    python benchmarks/bench_train.py --only "images + checkpointing" --only video model=qwen2_5_vl_3b model.path=DIR

The model, the LoRA setting and the data options are `train.py`'s, composed from `conf/` with the Hydra overrides
given (default: `model=tiny` as configured); --frames and --batch-size set data.num_frames / data.batch_size.
Each configuration runs in a fresh process: build the SFT module and the data module, run `steps` AdamW steps on
the module's training loss (the first is a warm-up, not timed), print samples/s and the peak resident memory of
the training steps above the memory before them (the kernel's high-water mark is reset first, through
/proc/self/clear_refs). Uses `data/generated/make_train_plain` when present, else generates 12 scenes at 64×48
into a temporary folder with the real generator. Numbers depend on the machine and its load: compare the ratios
printed at the end, measured in one run.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = [
    ("images", False, False),
    ("images + checkpointing", False, True),
    ("video", True, False),
    ("video + checkpointing", True, True),
]


def _status_mb(key: str) -> float:
    """VmRSS / VmHWM (current / peak resident memory) of this process in MB, from /proc/self/status."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024  # kB
    raise RuntimeError(f"{key} not in /proc/self/status")


def _reset_peak() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) to the current RSS (Linux >= 4.0); False where not allowed."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _compose(overrides: list[str], data: str):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=[*overrides, f"data.dir={data}", "output_dir=/tmp"])


def _measure(args: tuple) -> dict:
    overrides, data, as_video, checkpointing, steps = args
    import dataclasses

    import hydra
    import torch

    from aynamics.sft import SFTModule

    cfg = _compose(overrides, data)
    torch.manual_seed(0)
    spec = dataclasses.replace(hydra.utils.instantiate(cfg.model), gradient_checkpointing=checkpointing)
    module = SFTModule(spec)
    dm = hydra.utils.instantiate(
        cfg.data, processor_path=spec.processor_path, target=cfg.stage.target, as_video=as_video, cache=False
    )
    dm.setup("fit")
    ds, batch_size = dm.dataset("train"), dm.hparams.batch_size
    batches = [dm._collate([ds[(s * batch_size + i) % len(ds)] for i in range(batch_size)]) for s in range(steps)]
    opt = torch.optim.AdamW([p for p in module.parameters() if p.requires_grad], lr=1e-3)
    module.train()
    base, exact = _status_mb("VmRSS"), _reset_peak()
    times = []
    for batch in batches:
        t = time.perf_counter()
        loss, _, _ = module._loss(batch, weighted=True)  # the training step's loss
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
        times.append(time.perf_counter() - t)
    timed, peak = times[1:], _status_mb("VmHWM")  # the first step warms up allocators and kernels
    return {
        "samples_per_s": batch_size * len(timed) / sum(timed),
        "step_s": sum(timed) / len(timed),
        "tokens": int(batches[0]["input_ids"].numel()),
        "peak_rss_mb": peak,
        "train_rss_mb": peak - base,
        "exact_peak": exact,
    }


def _dataset(path: str | None) -> tuple[str, Path | None]:
    """The data set to measure on, and the scratch folder to delete afterwards when one was generated here."""
    if path:
        return path, None
    default = ROOT / "data" / "generated" / "make_train_plain"
    if (default / "dataset_dict.json").is_file():
        return str(default), None
    from aynamics.generate import GenerateConfig, generate_dataset

    scratch = Path(tempfile.mkdtemp(prefix="bench_train_"))
    out = scratch / "data"
    print(f"generating 12 scenes at 64x48 into {out} ...", flush=True)
    try:
        generate_dataset(
            out, num=12, seed=0, config=GenerateConfig(width=64, height=48, workers=0, splits=(0.5, 0.25, 0.25))
        )
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    return str(out), scratch


def main(argv: list[str] | None = None) -> int:
    """Measure the configurations; exit status 1 when a measuring process died (the others are still printed)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", help="generated data set folder (default: data/generated/make_train_plain or a fresh one)")
    p.add_argument("--steps", type=int, default=6, help="optimizer steps per configuration (first untimed)")
    p.add_argument("--batch-size", type=int, help="data.batch_size (default: the config's)")
    p.add_argument("--frames", type=int, help="data.num_frames (default: the config's)")
    p.add_argument(
        "--only",
        action="append",
        choices=[name for name, _, _ in CONFIGS],
        metavar="CONFIG",
        help=f"measure only this configuration, one of {[name for name, _, _ in CONFIGS]}; repeat for more "
        "(default: all)",
    )
    p.add_argument("overrides", nargs="*", help="train.py overrides, e.g. experiment=make_train model.lora_rank=8")
    args = p.parse_args(argv)
    if args.steps < 2:
        raise SystemExit(f"--steps = {args.steps}: need >= 2 (the first is a warm-up)")
    data, scratch = _dataset(args.data)
    try:
        return _run(args, data)
    finally:  # the scenes generated for lack of a data set (each run left a bench_train_* folder in /tmp)
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)


def _run(args, data: str) -> int:
    overrides = [*args.overrides]
    overrides += [f"data.batch_size={args.batch_size}"] if args.batch_size else []
    overrides += [f"data.num_frames={args.frames}"] if args.frames else []
    cfg = _compose(overrides, data)
    import torch  # the thread count the spawned runs get (same environment)

    print(
        f"model {dict(cfg.model.tiny) if cfg.model.kind == 'tiny' else cfg.model.path}, LoRA r {cfg.model.lora_rank}, "
        f"vision trained {cfg.model.train_vision}, batch {cfg.data.batch_size}, {cfg.data.num_frames} frames, "
        f"{args.steps} steps, overrides {args.overrides or 'none'}, {os.cpu_count()} CPU cores, torch threads "
        f"{torch.get_num_threads()}, data {data}"
    )
    results, died = {}, []
    for name, as_video, ckpt in [c for c in CONFIGS if not args.only or c[0] in args.only]:
        # a pool of its own for each: a worker killed (out of memory) breaks only its pool, and is named
        with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
            try:
                r = pool.submit(_measure, (overrides, data, as_video, ckpt, args.steps)).result()
            except BrokenProcessPool:
                print(f"  {name:<24} the measuring process died (killed: out of memory?)", flush=True)
                died.append(name)
                continue
        results[name] = r
        print(
            f"  {name:<24} {r['samples_per_s']:7.2f} samples/s  {r['step_s'] * 1000:8.0f} ms/step  "
            f"{r['tokens']:6d} tokens/batch  peak RSS {r['peak_rss_mb']:7.0f} MB  "
            f"(+{r['train_rss_mb']:.0f} MB in training{'' if r['exact_peak'] else ', peak since start'})",
            flush=True,
        )
    if "images" in results and "video" in results:
        img, vid = results["images"], results["video"]
        print(
            f"video / images throughput: {vid['samples_per_s'] / img['samples_per_s']:.2f}x, "
            f"tokens per batch {vid['tokens'] / img['tokens']:.2f}x"
        )
    for kind in ("images", "video"):
        if kind not in results or f"{kind} + checkpointing" not in results:
            continue
        on, off = results[f"{kind} + checkpointing"], results[kind]
        print(
            f"checkpointing on / off ({kind}): throughput {on['samples_per_s'] / off['samples_per_s']:.2f}x, "
            f"training memory {on['train_rss_mb'] / max(off['train_rss_mb'], 1e-9):.2f}x"
        )
    if died:
        print(f"not measured: {', '.join(died)} (its process died)", file=sys.stderr)
    return 1 if died else 0


if __name__ == "__main__":
    sys.exit(main())
