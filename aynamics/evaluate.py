"""`aynamics evaluate`: the simulated-scene table of a trained adapter on a split of a data set (held-out numbers).

    aynamics evaluate --adapter OUT/adapter --data DIR                          # every scene of the test split
    aynamics evaluate --adapter OUT/adapter --data DIR --split validation --num 32 --out EVAL/
    aynamics evaluate --adapter OUT/adapter --data DIR --refine 300             # + CMA-ES test-time refinement
    aynamics evaluate --adapter OUT/adapter --videos VIDEOS/                     # videos without labels: IoU, EPE

Training scores a fixed validation subset while it runs (`callbacks.SceneEvaluation`); this scores any split of
any data set afterwards (the test split that training never looks at, or data of your own made by `aynamics
generate`), with the same functions: YAML and simulation validity, object-count and composition accuracy,
segmentation IoU and flow EPE (first frame and full), position and velocity MAE — beside the constant "average
scene" of the data set's training split. The prompt is rebuilt from the adapter folder as `aynamics predict` does
(modality, frames, pixels, in-context examples), so at training's batch size the responses are the training
evaluation's. With `--refine N` every valid prediction is also refined by CMA-ES against its video (`aynamics.refine`,
N simulations and at most `--refine-seconds` each) and scored again: the paper's test-time refinement column; the
average scene is refined the same way beside it, so the table shows what the model's start adds to the search.

`--videos` scores videos that have no scene label, as the paper does on real videos: folders of `frames/*.png`
beside the observed segmentation (and optional flow) that `aynamics render` writes and the PRO stage reads
(`aynamics.unlabeled`); there only validity, IoU and EPE can be measured.

`--out DIR` writes `predictions.jsonl` (per scene: the response, the target and each metric; with `--refine` the
refined scene and its metrics) and `metrics.json` (the table, the split, the counts, the settings).
"""

from __future__ import annotations

import json
import math
import os
import sys
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from aynamics.callbacks import (
    average_scene_text,
    baseline_summary,
    evaluate_texts,
    format_table,
    json_safe,
    scorable_records,
    summarize,
    write_predictions,
)

MODEL, BASELINE = "model", "average scene"
REFINED, BASELINE_REFINED = f"{MODEL} + refine", f"{BASELINE} + refine"
OUT_FILES = ("predictions.jsonl", "metrics.json")


@dataclass
class Evaluation:
    """An adapter scored on a split.

    Attributes:
        table: column name ("model", "average scene", and with refinement "model + refine", "average scene +
            refine") -> metric -> mean.
        records: the scored records (`scorable_records`: index, scene_yaml, scene, observation; no prompt).
        texts: the model's response to each record.
        per_item: each record's metrics and reason (`evaluate_texts`).
        refined: with refinement, each record's refined scene as YAML (the response when it holds no valid scene).
        refined_per_item: the metrics of the refined scenes.
        left_out: records of the split that could not be scored (warned).
        split_size: records in the split (more than were read with `num`).
        refine_timed_out: refinements (of the model's and the average scene) stopped by the time limit before
            their budget of simulations: their results depend on the machine's speed.
    """

    table: dict[str, dict[str, float]]
    records: list[dict]
    texts: list[str]
    per_item: dict[str, list]
    refined: list[str] = field(default_factory=list)
    refined_per_item: dict[str, list] = field(default_factory=dict)
    left_out: int = 0
    refine_timed_out: int = 0
    split_size: int = 0


def _check_counts(num: int | None, batch_size: int, max_new_tokens: int, refine_budget: int, refine_seconds: float):
    """The counts and the time limit, each named as the command-line option that sets it."""
    for option, value, least in (
        ("--num", num, 1),
        ("--batch-size", batch_size, 1),
        ("--max-new-tokens", max_new_tokens, 1),
        ("--refine", refine_budget, 0),
    ):
        if value is not None and value < least:
            raise ValueError(f"{option} = {value}: must be >= {least}")
    if not (math.isfinite(refine_seconds) and refine_seconds > 0):
        raise ValueError(f"--refine-seconds = {refine_seconds}: must be a finite number > 0")


def _generate(
    model,
    processor,
    items: Iterator[list[dict]],
    n: int,
    batch_size: int,
    max_new_tokens: int,
    desc: str,
    progress: bool,
) -> tuple[list[dict], list[str]]:
    """Greedy responses for the records of `items` (per source item, a list of 0 or 1 scorable records with a
    `prompt`), `batch_size` scorable records at a time (the training evaluation's batches); the records are
    returned without their prompts."""
    from tqdm.auto import tqdm

    from aynamics import lm

    records: list[dict] = []
    texts: list[str] = []
    pending: list[dict] = []
    with tqdm(total=n, unit="scene", desc=desc, disable=not progress) as bar:
        for i, found in enumerate(items):
            pending += found
            if pending and (len(pending) == batch_size or i == n - 1):
                texts += lm.greedy_texts(model, processor, [r["prompt"] for r in pending], max_new_tokens)
                records += [{k: v for k, v in r.items() if k != "prompt"} for r in pending]
                pending.clear()
            bar.update(1)
    return records, texts


def _score(
    records: list[dict],
    texts: list[str],
    *,
    average: str | None,
    refine_budget: int,
    refine_seconds: float,
    progress: bool,
    n: int,
    split_size: int,
    what: str,
) -> Evaluation:
    """The table of the responses to the `records` scorable among the `n` read (of `split_size`; `what` they
    were, for the error when none is), and of the `average` scene, refined when `refine_budget` > 0. Records with
    a true `scene` get every metric; videos without one the validity, IoU and EPE only."""
    if not records:
        raise ValueError(f"no {what} can be scored (each one was named above)")
    targets = [r["scene"] for r in records] if "scene" in records[0] else None
    observations = [r["observation"] for r in records]
    per = evaluate_texts(texts, targets, observations)
    result = Evaluation({MODEL: summarize(per)}, records, texts, per, left_out=n - len(records), split_size=split_size)
    if average is not None:
        result.table[BASELINE] = baseline_summary(average, records)
    if refine_budget:
        result.refined, result.refine_timed_out = refine_texts(texts, records, refine_budget, refine_seconds, progress)
        result.refined_per_item = evaluate_texts(result.refined, targets, observations)
        result.table[REFINED] = summarize(result.refined_per_item)
        if average is not None:  # the same search from the average scene: what the model's start adds
            start = [average] * len(records)
            from_average, timed_out = refine_texts(start, records, refine_budget, refine_seconds, progress)
            result.refine_timed_out += timed_out
            result.table[BASELINE_REFINED] = summarize(evaluate_texts(from_average, targets, observations))
    return result


def evaluate_adapter(
    adapter: str | Path,
    data_dir: str | Path,
    *,
    split: str = "test",
    num: int | None = None,
    batch_size: int = 4,
    max_new_tokens: int = 2048,
    device: str = "auto",
    refine_budget: int = 0,
    refine_seconds: float = 60.0,
    baseline: bool = True,
    progress: bool = False,
) -> Evaluation:
    """Generate greedily for the first `num` records of `split` (all when None), score the responses by
    simulation, and the average scene beside them.

    Raises:
        FileNotFoundError: no data set at `data_dir`, or no adapter folder.
        ValueError: a split the data set lacks or an empty one, bad counts, an adapter that cannot be loaded, or a
            data set without the adapter's modality.
    """
    from aynamics import data, lm

    _check_counts(num, batch_size, max_new_tokens, refine_budget, refine_seconds)
    splits = data.load_splits(data_dir, what="--data", require_train=False)
    if split not in splits or len(splits[split]) == 0:
        raise ValueError(
            f"--split {split!r}: the data set {str(data_dir)!r} has no {split!r} scenes "
            f"(splits: {dict(splits.num_rows)})"
        )
    model, spec, prompt = lm.load_adapter(adapter, device)
    if prompt.modality not in splits[split].column_names:
        raise ValueError(
            f"--data {str(data_dir)!r}: its {split!r} split has no {prompt.modality!r} frames, which the adapter "
            f"(trained with data.modality = {prompt.modality!r}) reads"
        )
    prompt = data.with_clock(prompt, data_dir, splits[split])  # the scenes are scored on the data set's clock
    processor = lm.load_processor(spec, prompt)  # and a video's temporal positions follow it
    rows = data.used_columns(splits[split], ("index", "scene_yaml", "frame_indices", prompt.modality))
    n = len(rows) if num is None else min(num, len(rows))
    where = f"{split} records of --data {str(data_dir)!r}"
    from aynamics.dataset_store import dataset_substeps

    steps = dataset_substeps(data_dir)  # the physics the videos were made with
    found = (data.readable_eval_record(rows, i, processor, prompt, where, steps) for i in range(n))
    items = ([] if r is None else scorable_records([r], where) for r in found)
    records, texts = _generate(model, processor, items, n, batch_size, max_new_tokens, f"evaluate {split}", progress)
    average = None
    if baseline and records:  # (without records `_score` says so)
        if "train" in splits:
            average = average_scene_text(splits["train"])
        else:
            warnings.warn(f"scene evaluation: no average-scene baseline: --data {str(data_dir)!r} has no train split")
    return _score(
        records,
        texts,
        average=average,
        refine_budget=refine_budget,
        refine_seconds=refine_seconds,
        progress=progress,
        n=n,
        split_size=len(rows),
        what=f"scene of the {where}",
    )


def evaluate_videos(
    adapter: str | Path,
    videos: str | Path,
    *,
    num: int | None = None,
    batch_size: int = 4,
    max_new_tokens: int = 2048,
    device: str = "auto",
    refine_budget: int = 0,
    refine_seconds: float = 60.0,
    progress: bool = False,
) -> Evaluation:
    """The same for videos without a scene label (`aynamics.unlabeled`: a folder of frames/*.png, or flow/*.png for
    a flow-trained adapter, beside the observed segmentation and optional flow, or a folder of such folders):
    validity, IoU and EPE, the metrics the paper reports on real videos; no count, composition, state errors or
    average scene, which need true scenes.

    Raises:
        FileNotFoundError: no such folder, or one that is no video folder nor holds any (a video folder that
            lacks its images or masks is left out with a warning naming it).
        ValueError: bad counts or an adapter that cannot be loaded (a video folder that cannot be read is left out
            with a warning naming it).
    """
    from aynamics import lm
    from aynamics.cli import missing_file_message
    from aynamics.unlabeled import video_folders, video_from_folder

    _check_counts(num, batch_size, max_new_tokens, refine_budget, refine_seconds)
    found = video_folders(videos)
    model, spec, prompt = lm.load_adapter(adapter, device)
    processor = lm.load_processor(spec, prompt)
    n = len(found) if num is None else min(num, len(found))

    def item(folder: Path) -> list[dict]:
        try:  # read in its turn: --num reads only those
            video = video_from_folder(folder, inputs=prompt.modality, clip_times=prompt.frame_times)
            inputs = lm.prompt_inputs(processor, prompt, list(video.frames))
        except (OSError, ValueError) as e:  # one bad folder never stops the evaluation (FileNotFoundError: OSError)
            reason = missing_file_message(e) if isinstance(e, FileNotFoundError) else str(e)
            warnings.warn(f"scene evaluation: video folder {str(folder)!r} is left out: {reason}", stacklevel=2)
            return []
        return [{"index": video.key, "prompt": inputs, "observation": video.observation}]

    items = (item(folder) for folder in found[:n])
    records, texts = _generate(model, processor, items, n, batch_size, max_new_tokens, "evaluate videos", progress)
    return _score(
        records,
        texts,
        average=None,
        refine_budget=refine_budget,
        refine_seconds=refine_seconds,
        progress=progress,
        n=n,
        split_size=len(found),
        what=f"video of --videos {str(videos)!r}",
    )


def refine_texts(
    texts: list[str], records: list[dict], budget: int, seconds: float, progress: bool = False
) -> tuple[list[str], int]:
    """Each response's scene refined by CMA-ES against its record's observation (`aynamics.refine`, seed 0: the
    same result for a budget of simulations unless the time limit `seconds` stops it first); a response without a
    valid scene is kept as it is (it scores as invalid again).

    Returns:
        The refined texts, and how many refinements the time limit stopped before their budget.
    """
    from tqdm.auto import tqdm

    from aynamics.refine import refine
    from aynamics.scene import SceneError, parse

    out, timed_out = [], 0
    for text, r in tqdm(list(zip(texts, records, strict=True)), unit="scene", desc="refine", disable=not progress):
        try:
            start = parse(text)
        except SceneError:
            out.append(text)
            continue
        result = refine(start, r["observation"], budget=budget, seconds=seconds)
        timed_out += result.simulations < budget and result.seconds >= seconds
        out.append(result.yaml)
    return out, timed_out


def write_evaluation(out: str | Path, result: Evaluation, settings: dict) -> Path:
    """`predictions.jsonl` and `metrics.json` of `result` in the folder `out` (made if needed)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per = dict(result.per_item)
    if result.refined:
        per["refined"] = result.refined
        per |= {f"refined_{k}": v for k, v in result.refined_per_item.items()}
    meta = summary(result) | {"settings": settings}
    text = json.dumps(json_safe(meta), indent=2, allow_nan=False) + "\n"
    # metrics.json is written last and whole, and an earlier evaluation's goes first: a folder whose metrics.json
    # is there holds one evaluation's pair (a kill between the two files left this one's predictions beside the
    # earlier one's metrics.json and settings)
    (out / "metrics.json").unlink(missing_ok=True)
    tmp = out / f".predictions.jsonl.tmp-{os.getpid()}"
    write_predictions(tmp, result.texts, result.records, per)
    os.replace(tmp, out / "predictions.jsonl")
    tmp = out / f".metrics.json.tmp-{os.getpid()}"
    tmp.write_text(text)
    os.replace(tmp, out / "metrics.json")
    return out


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
    p.add_argument("--out", help="folder for predictions.jsonl and metrics.json")
    p.add_argument(
        "--json", action="store_true", help="print the table and counts as JSON (metrics.json less settings)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_device_option(p)
    p.set_defaults(run=run_evaluate)


def run_evaluate(args) -> int:
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
    }
    try:
        with warnings_as_lines("evaluate", "scene evaluation: "):  # records left out: named as they are found
            if args.data is not None:
                result = evaluate_adapter(
                    args.adapter, args.data, split=args.split, baseline=not args.no_baseline, **common
                )
            else:
                result = evaluate_videos(args.adapter, args.videos, **common)
    except FileNotFoundError as e:
        raise UsageError(f"evaluate: {missing_file_message(e)}") from None
    except ValueError as e:
        raise UsageError(f"evaluate: {e}") from None
    if args.out is not None:
        write_evaluation(args.out, result, settings)
    if args.json:
        json.dump(summary(result), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(describe(result, args.split if args.data else None))
        print(format_table(result.table))
    return 0


def summary(result: Evaluation) -> dict:
    """What `metrics.json` and `--json` report besides the settings (a mean nothing could be computed for, e.g. EPE
    without observed flow, as null)."""
    return json_safe(
        {
            "table": result.table,
            "scenes": len(result.records),
            "left_out": result.left_out,
            "split_size": result.split_size,
            "refine_timed_out": result.refine_timed_out,
        }
    )


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
