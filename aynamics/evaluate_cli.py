"""The `aynamics evaluate` command: a trained adapter's simulated-scene table (`aynamics.evaluate`) printed or written.

    aynamics evaluate --adapter OUT/adapter --data DIR                          # every scene of the test split
    aynamics evaluate --adapter OUT/adapter --data DIR --split validation --num 32 --out EVAL/
    aynamics evaluate --adapter OUT/adapter --data DIR --refine 300             # + CMA-ES test-time refinement
    aynamics evaluate --adapter OUT/adapter --videos VIDEOS/                     # videos without labels: IoU, EPE

`--out DIR` writes `predictions.jsonl` and `metrics.json` (`write_evaluation`, with the command's settings).
Meanwhile it keeps each batch of responses and each refinement in `OUT.partial` as it is done
(`evaluation_progress`; a real model with `--refine` takes hours): run the same command again after an
interruption and it goes on from there, with the table an uninterrupted run gives; another process on the same OUT,
or the same OUT with other settings, is refused.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from pathlib import Path

from aynamics.callbacks import format_reasons, format_table
from aynamics.evaluate import (
    AVERAGE_REFINED_KEPT,
    KEPT_FIELDS,
    REFINED_KEPT,
    RESPONSES,
    Evaluation,
    evaluate_adapter,
    evaluate_videos,
    summary,
    write_evaluation,
)
from aynamics.kept_batches import KeptBatches, file_digest, partial_folder

OUT_FILES = ("predictions.jsonl", "metrics.json")


# --------------------------------------------------------------------------------------------
# Command line: aynamics evaluate
# --------------------------------------------------------------------------------------------
def add_evaluate_command(sub) -> None:
    """Register `aynamics evaluate` on the CLI's subparsers."""
    from aynamics.cli import add_device_option

    p = sub.add_parser(
        "evaluate",
        help="score a trained adapter's scenes on a data-set split or unlabeled videos by simulation (IoU, EPE, ...)",
    )
    p.add_argument("--adapter", required=True, help="adapter folder written by training (OUT/adapter)")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", help="data set folder (aynamics generate --out): scenes with their true YAML")
    source.add_argument(
        "--videos",
        help="or videos without a label: a folder of frames/*.png (flow/*.png for a flow-trained adapter) beside "
        "segmentation.npy or segmentation/*.png (optional flow.npy), as aynamics render writes, or a folder of "
        "such folders: validity, IoU and EPE only",
    )
    p.add_argument("--split", help="with --data: train, validation or test (default test)")
    p.add_argument("--num", type=int, help="score the first NUM scenes or videos (default: all)")
    p.add_argument("--batch-size", type=int, default=4, help="prompts generated at once (default 4)")
    p.add_argument("--max-new-tokens", type=int, default=2048, help="response length limit (default 2048)")
    p.add_argument(
        "--refine",
        type=int,
        default=0,
        metavar="N",
        help="also refine each valid scene, and the average scene, with N CMA-ES simulations each",
    )
    p.add_argument("--refine-seconds", type=float, default=60.0, help="time limit of each refinement (default 60)")
    p.add_argument("--no-baseline", action="store_true", help="leave out the average scene")
    p.add_argument(
        "--separate",
        action="store_true",
        help="also score each response with its objects that start inside each other or the floor pushed apart "
        "(column 'model, separated')",
    )
    p.add_argument("--out", help="folder for predictions.jsonl and metrics.json")
    p.add_argument(
        "--json", action="store_true", help="print the table and counts as JSON (metrics.json less settings)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_device_option(p)
    p.set_defaults(run=run_evaluate)


def run_evaluate(args) -> int:
    """`aynamics evaluate`: generate, simulate and score, print the table (and write OUT); a usage error raises
    `cli.UsageError` (exit 2)."""
    from aynamics.cli import UsageError, check_out_folder, missing_file_message, warnings_as_lines

    if args.out is not None:
        check_out_folder("evaluate", args.out, writes=OUT_FILES)
    if args.videos is not None and (args.split is not None or args.no_baseline):
        option = "--split" if args.split is not None else "--no-baseline"
        raise UsageError(f"evaluate: {option} is for --data (a data set); videos have no splits nor training scenes")
    args.split = args.split or "test"
    if not Path(args.adapter).is_dir():
        raise UsageError(f"evaluate: --adapter {args.adapter!r} is not a folder (give OUT/adapter of a training run)")
    settings = {
        "adapter": str(args.adapter),
        "data": args.data,
        "videos": args.videos,
        "split": args.split if args.data else None,
        "num": args.num,
        "batch_size": args.batch_size,
        "max_new_tokens": args.max_new_tokens,
        "refine": args.refine,
        "refine_seconds": args.refine_seconds,
    }
    common = {
        "num": args.num,
        "batch_size": args.batch_size,
        "max_new_tokens": args.max_new_tokens,
        "device": args.device,
        "refine_budget": args.refine,
        "refine_seconds": args.refine_seconds,
        "progress": not args.quiet,
        "separate": args.separate,
    }
    try:
        kept = (
            None if args.out is None else evaluation_progress(args.out, settings | {"baseline": not args.no_baseline})
        )
        common["kept"] = kept
        with contextlib.ExitStack() as stack:
            if kept is not None:  # other settings or a second writer are refused before the model loads
                stack.enter_context(kept.opened())
                if kept.redone is not None:
                    changed, _ = kept.redone
                    print(
                        f"evaluate: {'; '.join(changed)}: the kept refinements are done again, the kept responses used",
                        file=sys.stderr,
                    )
                if len(kept):
                    print(f"evaluate: going on from {str(kept.folder)!r} ({_kept_line(kept)})", file=sys.stderr)
            try:
                with warnings_as_lines("evaluate", "scene evaluation: "):  # records left out: named as found
                    if args.data is not None:
                        split, baseline = args.split, not args.no_baseline
                        result = evaluate_adapter(args.adapter, args.data, split=split, baseline=baseline, **common)
                    else:
                        result = evaluate_videos(args.adapter, args.videos, **common)
            except KeyboardInterrupt:
                if kept is not None and len(kept):  # (a folder without a batch is deleted)
                    print(
                        f"evaluate: kept in {str(kept.folder)!r} ({_kept_line(kept)}): the same command goes on "
                        "from them",
                        file=sys.stderr,
                    )
                raise
            if kept is not None:
                try:
                    write_evaluation(args.out, result, settings | {"separate": args.separate})
                except OSError as e:
                    raise UsageError(
                        f"evaluate: cannot write --out {args.out!r}: {e}; the responses and refinements are kept in "
                        f"{str(kept.folder)!r}: the same command writes them without generating again"
                    ) from None
                kept.remove()  # under the lock: no second writer starts on the batches meanwhile
    except FileNotFoundError as e:
        raise UsageError(f"evaluate: {missing_file_message(e)}") from None
    except ValueError as e:
        raise UsageError(f"evaluate: {e}") from None
    if args.json:
        json.dump(summary(result), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(describe(result, args.split if args.data else None))
        print(format_table(result.table))
        if why := format_reasons(result.invalid_reasons, len(result.records)):
            print(why)
    return 0


def evaluation_progress(out: str | Path, settings: dict) -> KeptBatches:
    """Where `aynamics evaluate --out OUT` keeps each batch of responses and each refinement as it is done
    (`OUT.partial`, deleted once OUT is written): run the same command again after an interruption and it goes on
    from them, with the table an uninterrupted run prints. `settings` are the command's; the adapter and the data
    are kept by absolute path, the adapter's weights by their digest (one trained again into its folder writes
    other responses) and, with refinement, the physics (`simulate.PHYSICS_VERSION`: a scene refined by other
    physics is not the one this run's search finds). Another refinement budget, time limit, physics or baseline
    choice keeps the responses (hours of generation on a real model) and does the refinements again. `--num` is
    not among them: the batches and refinements of a run of fewer scenes are those of a run of more (each is checked
    by its records' keys and contents), so a larger --num goes on from them."""
    from aynamics import simulate

    def path(p: str | None) -> str | None:
        return None if p is None else os.path.abspath(p)

    adapter = settings["adapter"]
    resolved = settings | {
        "adapter": path(adapter),
        "adapter_weights": file_digest(Path(adapter) / "adapter_model.safetensors"),
        "data": path(settings.get("data")),
        "videos": path(settings.get("videos")),
        "physics": simulate.PHYSICS_VERSION if settings.get("refine") else None,
    }
    resolved.pop("num", None)
    refinements = (REFINED_KEPT, AVERAGE_REFINED_KEPT)
    redone_on = {"refine": refinements, "refine_seconds": refinements, "physics": refinements}
    redone_on["baseline"] = (AVERAGE_REFINED_KEPT,)  # the model's responses and refinements stand
    return KeptBatches(
        partial_folder(out), resolved, run="an evaluation", verb="score", fields=KEPT_FIELDS, redone_on=redone_on
    )


def _kept_line(kept: KeptBatches) -> str:
    """What `kept` holds, in words: "3 batches of responses, 5 refinements"."""
    counts = [
        (kept.count(RESPONSES), "batch", "batches", " of responses"),
        (kept.count(REFINED_KEPT) + kept.count(AVERAGE_REFINED_KEPT), "refinement", "refinements", ""),
    ]
    return ", ".join(f"{n} {one if n == 1 else many}{of}" for n, one, many, of in counts if n) or "nothing"


def describe(result: Evaluation, split: str | None) -> str:
    """The line above the table: how many scenes of the split (or videos, `split` None) were scored, left out,
    cut short."""
    n = len(result.records)
    noun = "scene" if split else "video"
    line = f"{split or 'videos'}: {n} {noun}{'s' * (n != 1)}"
    if n + result.left_out < result.split_size:
        line += f" of {result.split_size} (--num)"
    if result.left_out:
        line += f", {result.left_out} left out (named above)"
    if result.refine_timed_out:
        line += f", {result.refine_timed_out} refinements stopped by --refine-seconds before their budget"
    return line
