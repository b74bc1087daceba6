"""The `aynamics preferences` command: sample, score and store PRO preferences (`aynamics.preference_data`).

    aynamics preferences --data data/synth --split train --out data/prefs --num-samples 32 --pairs 3 \\
        --temperature 0.1 [--model tiny | CHECKPOINT_DIR] [--adapter SFT_ADAPTER] [--limit K]

It prints the summary (`summary.json`). Sampling takes hours on real models, so each batch is kept in `OUT.partial`
as soon as it is scored (`SamplingProgress`): run the same command again after an interruption and it goes on from
the last kept batch, giving the rows an uninterrupted run gives; the folder is deleted once OUT is written.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from aynamics import adapters
from aynamics import reward as rw
from aynamics.kept_batches import file_digest, partial_folder
from aynamics.preference_data import SamplingProgress, build_preferences, check_out, write_preferences
from aynamics.unlabeled import UnlabeledVideo


# --------------------------------------------------------------------------------------------
# CLI: aynamics preferences
# --------------------------------------------------------------------------------------------
def add_preferences_command(sub) -> None:
    """Register `aynamics preferences` on the CLI's subparsers."""
    from aynamics.cli import add_device_option

    p = sub.add_parser("preferences", help="sample, score and store a PRO preference data set (offline mode)")
    p.add_argument("--data", required=True, help="unlabeled videos: a generated data set or a folder of videos")
    p.add_argument("--out", required=True, help="folder to write the preference data set to")
    p.add_argument("--split", help="split of a generated data set (default train; not for video folders)")
    p.add_argument(
        "--model",
        default=None,
        help="'tiny' or a checkpoint directory (default: --adapter's base, else tiny)",
    )
    p.add_argument("--adapter", default=None, help="peft adapter to sample with (e.g. the SFT stage's)")
    p.add_argument("--num-samples", type=int, default=32, help="candidates per video (default 32, as the paper)")
    p.add_argument("--pairs", type=int, default=3, help="pairs kept per video (default 3, as the paper)")
    p.add_argument("--temperature", type=float, default=0.1, help="sampling temperature (default 0.1)")
    p.add_argument("--top-p", type=float, default=1.0, help="nucleus sampling mass (default 1.0)")
    p.add_argument(
        "--max-new-tokens", type=int, default=1800, help="response length limit (default 1800: the longest scene)"
    )
    p.add_argument("--metric", default="iou", choices=rw.METRICS, help="reward metric (default iou)")
    p.add_argument("--span", default="full", choices=rw.SPANS, help="full sequence or first frame (default full)")
    p.add_argument(
        "--inputs", default="rgb", choices=("rgb", "flow"), help="images the model sees without --adapter (default rgb)"
    )
    p.add_argument("--limit", type=int, default=None, help="use only the first LIMIT videos")
    p.add_argument("--batch-size", type=int, default=1, help="videos sampled together (default 1)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    add_device_option(p)
    p.add_argument(
        "--dtype",
        default=None,
        choices=("float32", "bfloat16"),
        help="weights of a --model checkpoint (default: bfloat16 on a GPU, float32 on the CPU; tiny: float32)",
    )
    p.set_defaults(run=run_preferences)


def run_preferences(args) -> int:
    """`aynamics preferences`: sample, score and pair responses for each video, write the data set; a usage error
    raises `cli.UsageError` (exit 2)."""
    from aynamics import lm
    from aynamics.cli import UsageError, print_json
    from aynamics.pro import ProModule
    from aynamics.unlabeled import GeneratedVideos, is_generated, open_videos

    if args.limit is not None and args.limit < 1:
        raise UsageError(f"preferences: --limit {args.limit}: must be >= 1")
    if args.split is not None and Path(args.data).is_dir() and not is_generated(args.data):
        raise UsageError(f"preferences: --split {args.split}: --data {args.data!r} holds video folders, not splits")
    try:
        check_out(args.out)  # before hours of sampling, not after
        device = lm.inference_device(args.device)
        trained, prompt = adapters.read_adapter_meta(args.adapter) if args.adapter else (None, None)
        model = args.model or (trained.path if trained is not None and trained.kind == "pretrained" else "tiny")
        if model == "tiny":
            spec = lm.ModelSpec(kind="tiny") if trained is None or trained.kind != "tiny" else trained
        else:
            dtype = args.dtype or ("bfloat16" if device.type == "cuda" else "float32")
            spec = lm.ModelSpec(kind="pretrained", path=model, dtype=dtype)
            if trained is not None:  # the adapter's architecture, this run's dtype (no warning for what was not given)
                spec = dataclasses.replace(trained, path=model, dtype=dtype)
        if trained is not None and (trained.kind, trained.path) != (spec.kind, spec.path):
            raise ValueError(
                f"--adapter {args.adapter!r} was trained on model kind={trained.kind!r} path={trained.path!r}, but "
                f"--model is {model!r}: leave --model out to use the adapter's"
            )
        prompt = prompt or lm.PromptSpec(modality=args.inputs)
        videos = open_videos(
            args.data,
            args.split or "train",
            inputs=prompt.modality,
            use_flow=args.metric != "iou",
            limit=args.limit,
            clip_times=prompt.frame_times,  # a folder's images at the adapter's times, as predict reads a video
        )
        if args.metric != "iou":  # before sampling: the first valid candidate would stop the run
            from aynamics.pro_datamodule import without_flow

            missing = without_flow(videos)
            if missing is not None:
                raise ValueError(
                    f"--metric {args.metric} scores the flow, but the video {missing!r} of --data has no observed "
                    "flow (flow.npy): add it or use --metric iou"
                )
        if isinstance(videos, GeneratedVideos):  # the recorded prompt holds the videos' clock, as in PRO
            from aynamics.data import with_clock

            prompt = with_clock(prompt, args.data, videos.ds)
        split = (args.split or "train") if isinstance(videos, GeneratedVideos) else None  # as open_videos read it
        settings = _settings(args, model=model, dtype=spec.dtype, split=split, inputs=prompt.modality)
        progress = SamplingProgress(partial_folder(args.out), settings)
        with progress.opened():  # other settings or a second writer are refused before minutes of model loading
            module = ProModule(
                spec,
                init_adapter=args.adapter,
                num_samples=max(args.num_samples, 2),
                temperature=args.temperature,
                top_p=args.top_p,
                max_new_tokens=args.max_new_tokens,
                reward_metric=args.metric,
                reward_span=args.span,
                prompt=prompt,
            )
            module.to(device)
            torch.manual_seed(args.seed)
            summary = _sample_and_write(module, videos, progress, args)
            progress.remove()  # under the lock: no second writer starts on the batches meanwhile
    except ValueError as e:
        raise UsageError(f"preferences: {e}") from None
    print_json(summary)
    return 0


def _batches(n: int) -> str:
    return f"{n} batch" if n == 1 else f"{n} batches"


def _sample_and_write(module: Any, videos: Sequence[UnlabeledVideo], progress: SamplingProgress, args) -> dict:
    """`build_preferences` going on from the kept batches, then the set written to --out; its summary. An
    interruption, or a set that cannot be written, says where the batches are kept."""
    if len(progress):
        print(f"preferences: going on from {str(progress.folder)!r} ({_batches(len(progress))} kept)", file=sys.stderr)
    try:
        rows, summary = build_preferences(
            module,
            videos,
            num_samples=args.num_samples,
            pairs=args.pairs,
            temperature=args.temperature,
            batch_size=args.batch_size,
            progress=progress,
        )
    except KeyboardInterrupt:
        if not len(progress):  # (a folder without a batch is deleted)
            raise
        print(
            f"preferences: {_batches(len(progress))} kept in {str(progress.folder)!r}: the same command goes on "
            "from them",
            file=sys.stderr,
        )
        raise
    try:
        write_preferences(rows, summary, args.out)
    except (OSError, ValueError) as e:
        from aynamics.cli import UsageError

        raise UsageError(
            f"preferences: cannot write --out {args.out!r}: {e}; the sampled batches are kept in "
            f"{str(progress.folder)!r}: the same command writes them without sampling again"
        ) from None
    return summary


def _settings(args, *, model: str, dtype: str, split: str | None, inputs: str) -> dict:
    """What `aynamics preferences`' samples depend on: a kept run is gone on from only with the same (each as it was
    resolved: the same run spelled otherwise, `--split train` or none, `--inputs` an adapter overrides, goes on)."""

    def path(p: str | None) -> str | None:  # a folder by where it is (a hub id stays as written)
        return p if p is None or not os.path.exists(p) else os.path.abspath(p)

    return {
        "data": path(args.data),
        "split": split,
        "limit": args.limit,
        "model": model if model == "tiny" else path(model),  # the tiny model, whatever folder is named so here
        "dtype": dtype,
        "adapter": path(args.adapter),
        "adapter_weights": file_digest(Path(args.adapter) / "adapter_model.safetensors") if args.adapter else None,
        "inputs": inputs,
        **{k: getattr(args, k) for k in ("num_samples", "pairs", "temperature", "top_p", "max_new_tokens")},
        **{k: getattr(args, k) for k in ("metric", "span", "batch_size", "seed")},
    }
