"""The simulated-scene table of a trained adapter on a split of a data set (held-out numbers) or on unlabeled videos.

    result = evaluate_adapter("OUT/adapter", "DIR", split="test", num=32, refine_budget=300)
    result.table["model"], result.table["average scene"], result.per_item
    write_evaluation("EVAL/", result, settings)                             # predictions.jsonl, metrics.json

Training scores a fixed validation subset while it runs (`callbacks.SceneEvaluation`); this scores any split of
any data set afterwards (the test split that training never looks at, or data of your own made by `aynamics
generate`), with the same functions: YAML and simulation validity, object-count and composition accuracy,
segmentation IoU and flow EPE (first frame and full), position and velocity MAE — beside the constant "average
scene" of the data set's training split. The prompt is rebuilt from the adapter folder as `aynamics predict` does
(modality, frames, pixels, in-context examples), so at training's batch size the responses are the training
evaluation's. With `refine_budget` N every valid prediction is also refined by CMA-ES against its video
(`refine_texts`: `aynamics.refine`, N simulations and at most `refine_seconds` each) and scored again: the paper's
test-time refinement column; the average scene is refined the same way beside it, so the table shows what the
model's start adds to the search. With `separate`, the responses are also scored with their starts separated
(`aynamics.separate`: objects written inside each other or the floor pushed apart), column "model, separated":
how the model places objects, apart from the overlaps that make most of a weak model's scenes invalid.

`evaluate_videos` scores videos that have no scene label, as the paper does on real videos: folders of
`frames/*.png` beside the observed segmentation (and optional flow) that `aynamics render` writes and the PRO stage
reads (`aynamics.unlabeled`); there only validity, IoU and EPE can be measured.

`write_evaluation` writes `predictions.jsonl` (per scene: the response, the target and each metric; with refinement
the refined scene and its metrics) and `metrics.json` (`summary`: the table, the split, the counts; and the
settings). With `kept` (a `kept_batches.KeptBatches`) each batch of responses and each refinement is kept as it is
done, and what it holds is read back rather than done again. The command line, `aynamics evaluate`, is
`aynamics.evaluate_cli`.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from aynamics.callbacks import (
    average_scene_text,
    baseline_summary,
    evaluate_texts,
    invalid_reasons,
    json_safe,
    scorable_records,
    summarize,
    write_predictions,
)
from aynamics.kept_batches import KeptBatches, content_digest
from aynamics.separate import separate_texts

MODEL, BASELINE = "model", "average scene"
REFINED, BASELINE_REFINED = f"{MODEL} + refine", f"{BASELINE} + refine"
SEPARATED = f"{MODEL}, separated"
# what `--out OUT` keeps in OUT.partial as it goes (`kept_batches`): each batch's responses, each refinement
RESPONSES, REFINED_KEPT, AVERAGE_REFINED_KEPT = "responses", "refined", "average-refined"
KEPT_FIELDS = {
    RESPONSES: frozenset({"keys", "digests", "texts"}),
    REFINED_KEPT: frozenset({"keys", "digests", "texts", "timed_out"}),
    AVERAGE_REFINED_KEPT: frozenset({"keys", "digests", "texts", "timed_out"}),
}


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

    @property
    def invalid_reasons(self) -> dict[str, int]:
        """Why the model's invalid responses fail, counted (`callbacks.invalid_reasons`)."""
        return invalid_reasons(self.per_item.get("reason", []))


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
    kept: KeptBatches | None = None,
) -> tuple[list[dict], list[str], list[str]]:
    """Greedy responses for the records of `items` (per source item, a list of 0 or 1 scorable records with a
    `prompt`), `batch_size` scorable records at a time (the training evaluation's batches); the records are
    returned without their prompts, with each one's `content_digest` of prompt and observation (what a refinement
    depends on).

    With `kept`, each batch's responses are kept as they are generated, and batches it holds are read back rather
    than generated again (greedy: the responses an uninterrupted run gives, batched the same way), checked by the
    digests of their prompts (masks made again leave the responses valid; their refinements are checked apart).
    A kept last batch shorter than this run's (of a smaller --num) is answered again whole, as an uninterrupted run
    batches it; if its responses come out otherwise, the refinements kept from its first record on are dropped.

    Raises:
        ValueError: a kept batch of other records or other prompts than these (the data changed since), or kept
            responses of more records than these.
    """
    from tqdm.auto import tqdm

    from aynamics import lm

    done = kept.done(RESPONSES) if kept is not None else []
    records: list[dict] = []
    texts: list[str] = []
    digests: list[str] = []
    pending: list[dict] = []

    def answer(batch: list[dict]) -> list[str]:
        k = len(records) // batch_size  # every batch but the last is full
        keys = [r["index"] for r in batch]
        prompts = [content_digest(r["prompt"]) for r in batch] if kept is not None else []
        digests.extend(content_digest(p, r["observation"]) for p, r in zip(prompts, batch, strict=False))
        held = done[k]["keys"] if k < len(done) else []
        if len(keys) < len(held) and held[: len(keys)] == keys:  # this run's last batch is shorter
            raise ValueError(
                _fewer_records(kept, f"{len(done)} batches of responses", "this run's last batch holds fewer records")
            )
        tail = k == len(done) - 1 and len(held) < len(keys) and keys[: len(held)] == held
        if k < len(done) and not tail:
            _check_kept(kept, RESPONSES, k, done[k], keys, prompts)
            return list(done[k]["texts"])
        if tail:  # the last, shorter batch of a smaller --num: answered again whole, as an uninterrupted run batches it
            _check_kept(kept, RESPONSES, k, done[k], held, prompts[: len(held)])
        out = lm.greedy_texts(model, processor, [r["prompt"] for r in batch], max_new_tokens)
        if kept is not None:
            kept.save(RESPONSES, k, {"keys": keys, "digests": prompts, "texts": out})
        if tail and out[: len(held)] != list(done[k]["texts"]):  # batched otherwise, a response came out otherwise:
            kept.drop(REFINED_KEPT, len(records))  # the refinements of this batch's responses start from other scenes
        return out

    with tqdm(total=n, unit="scene", desc=desc, disable=not progress) as bar:
        for i, found in enumerate(items):
            pending += found
            if pending and (len(pending) == batch_size or i == n - 1):
                texts += answer(pending)
                records += [{k: v for k, v in r.items() if k != "prompt"} for r in pending]
                pending.clear()
            bar.update(1)
    made = -(-len(records) // batch_size)
    if len(done) > made:
        raise ValueError(_fewer_records(kept, f"{len(done)} batches of responses", f"these records make {made}"))
    return records, texts, digests


def _fewer_records(kept: KeptBatches, holds: str, but: str) -> str:
    """The refusal of kept work of more records than this run has ("holds {holds}, but {but}")."""
    return (
        f"{str(kept.folder)!r} holds {holds}, but {but} (a smaller --num than the kept run's, or the data changed "
        "since): give its --num to go on from it, or delete it to score afresh"
    )


def _check_kept(kept: KeptBatches, stream: str, k: int, batch: dict, keys: list, digests: list[str]) -> None:
    """Refuse a kept batch made from other records (keys) or other contents under the same keys (a data set made
    again, a video folder replaced) than batch `k` of this run."""
    if batch["keys"] != keys or len(batch["texts"]) != len(keys):
        raise ValueError(
            f"{str(kept.folder)!r}: its {stream} batch {k} holds records {batch['keys']}, but this run's batch {k} "
            f"is records {keys}: the data changed since it was written; delete it to score afresh"
        )
    changed = [key for key, d, d_kept in zip(keys, digests, batch["digests"], strict=True) if d != d_kept]
    if changed:
        what = "prompts (frames)" if stream == RESPONSES else "frames, masks or starting scenes"
        raise ValueError(
            f"{str(kept.folder)!r}: its {stream} batch {k} was made from other {what} of the records {changed} than "
            "this run's: the data changed since it was written; delete it to score afresh"
        )


def _score(
    records: list[dict],
    texts: list[str],
    *,
    average: str | None,
    refine_budget: int,
    refine_seconds: float,
    progress: bool,
    n: int,
    separate: bool = False,
    split_size: int,
    what: str,
    kept: KeptBatches | None = None,
    digests: list[str] | None = None,
) -> Evaluation:
    """The table of the responses to the `records` scorable among the `n` read (of `split_size`; `what` they
    were, for the error when none is), and of the `average` scene, refined when `refine_budget` > 0. Records with
    a true `scene` get every metric; videos without one the validity, IoU and EPE only. With `kept`, each
    refinement is kept as it ends and those kept are read back (`refine_texts`; `digests`: the records')."""
    if not records:
        raise ValueError(f"no {what} can be scored (each one was named above)")
    targets = [r["scene"] for r in records] if "scene" in records[0] else None
    observations = [r["observation"] for r in records]
    per = evaluate_texts(texts, targets, observations)
    result = Evaluation({MODEL: summarize(per)}, records, texts, per, left_out=n - len(records), split_size=split_size)
    if separate:
        result.table[SEPARATED] = summarize(evaluate_texts(separate_texts(texts), targets, observations))
    if average is not None:
        result.table[BASELINE] = baseline_summary(average, records)
    if refine_budget:
        keep = {"kept": kept, "digests": digests} if kept is not None else {}
        result.refined, result.refine_timed_out = refine_texts(
            texts, records, refine_budget, refine_seconds, progress, stream=REFINED_KEPT, **keep
        )
        result.refined_per_item = evaluate_texts(result.refined, targets, observations)
        result.table[REFINED] = summarize(result.refined_per_item)
        if average is not None:  # the same search from the average scene: what the model's start adds
            start = [average] * len(records)
            from_average, timed_out = refine_texts(
                start, records, refine_budget, refine_seconds, progress, stream=AVERAGE_REFINED_KEPT, **keep
            )
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
    separate: bool = False,
    baseline: bool = True,
    progress: bool = False,
    kept: KeptBatches | None = None,
) -> Evaluation:
    """Generate greedily for the first `num` records of `split` (all when None), score the responses by
    simulation, and the average scene beside them. With `kept` (opened: `evaluate_cli.evaluation_progress`), each
    batch of responses and each refinement is kept as it is done, and what it holds is read back, not done again.

    Raises:
        FileNotFoundError: no data set at `data_dir`, or no adapter folder.
        ValueError: a split the data set lacks or an empty one, bad counts, an adapter that cannot be loaded, or a
            data set without the adapter's modality.
    """
    from aynamics import adapters, data, eval_records, lm

    _check_counts(num, batch_size, max_new_tokens, refine_budget, refine_seconds)
    splits = data.load_splits(data_dir, what="--data", require_train=False)
    if split not in splits or len(splits[split]) == 0:
        raise ValueError(
            f"--split {split!r}: the data set {str(data_dir)!r} has no {split!r} scenes "
            f"(splits: {dict(splits.num_rows)})"
        )
    model, spec, prompt = adapters.load_adapter(adapter, device)
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
    found = (eval_records.readable_eval_record(rows, i, processor, prompt, where, steps) for i in range(n))
    items = ([] if r is None else scorable_records([r], where) for r in found)
    records, texts, digests = _generate(
        model, processor, items, n, batch_size, max_new_tokens, f"evaluate {split}", progress, kept
    )
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
        kept=kept,
        digests=digests,
        separate=separate,
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
    separate: bool = False,
    progress: bool = False,
    kept: KeptBatches | None = None,
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
    from aynamics import adapters, lm
    from aynamics.cli import missing_file_message
    from aynamics.unlabeled import video_folders, video_from_folder

    _check_counts(num, batch_size, max_new_tokens, refine_budget, refine_seconds)
    found = video_folders(videos)
    model, spec, prompt = adapters.load_adapter(adapter, device)
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
    records, texts, digests = _generate(
        model, processor, items, n, batch_size, max_new_tokens, "evaluate videos", progress, kept
    )
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
        kept=kept,
        digests=digests,
        separate=separate,
    )


def refine_texts(
    texts: list[str],
    records: list[dict],
    budget: int,
    seconds: float,
    progress: bool = False,
    *,
    kept: KeptBatches | None = None,
    stream: str = REFINED_KEPT,
    digests: list[str] | None = None,
) -> tuple[list[str], int]:
    """Each response's scene refined by CMA-ES against its record's observation (`aynamics.refine`, seed 0: the
    same result for a budget of simulations unless the time limit `seconds` stops it first); a response without a
    valid scene is kept as it is (it scores as invalid again).

    With `kept`, each refinement is kept in its `stream` as it ends (a minute of search a scene on a real
    evaluation), and those it holds are read back, checked against the records' `digests` (`content_digest` of
    prompt and observation) and the response.

    Returns:
        The refined texts, and how many refinements the time limit stopped before their budget.

    Raises:
        ValueError: a kept refinement of another record, response or observation.
    """
    from tqdm.auto import tqdm

    from aynamics.refine import refine
    from aynamics.scene import SceneError, parse

    done = kept.done(stream) if kept is not None else []
    if len(done) > len(texts):
        raise ValueError(_fewer_records(kept, f"{len(done)} {stream} scenes", f"there are {len(texts)} to refine"))
    out, timed_out = [], 0
    pairs = list(zip(texts, records, strict=True))
    for k, (text, r) in enumerate(tqdm(pairs, unit="scene", desc="refine", disable=not progress)):
        mark = [content_digest(digests[k], text)] if kept is not None else []
        if k < len(done):
            _check_kept(kept, stream, k, done[k], [r["index"]], mark)
            out += done[k]["texts"]
            timed_out += done[k]["timed_out"]
            continue
        try:
            start = parse(text)
        except SceneError:
            refined, cut = text, False
        else:
            result = refine(start, r["observation"], budget=budget, seconds=seconds)
            refined, cut = result.yaml, result.simulations < budget and result.seconds >= seconds
        if kept is not None:
            kept.save(stream, k, {"keys": [r["index"]], "digests": mark, "texts": [refined], "timed_out": int(cut)})
        out.append(refined)
        timed_out += cut
    return out, timed_out


def write_evaluation(out: str | Path, result: Evaluation, settings: dict) -> Path:
    """`predictions.jsonl` and `metrics.json` of `result` in the folder `out` (made if needed).

    Each is written to a hidden `.NAME.tmp-PID` beside it and renamed; once both are in place, such files that
    killed writes left (for good before: each write knew only its own process's name) are deleted. A process
    writing the same `out` at once could lose its file to this: callers that may run together hold the lock of
    `partial_folder(out)` (`KeptBatches.opened`), as `aynamics evaluate --out` does.
    """
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
    for name in ("predictions.jsonl", "metrics.json"):
        for leftover in out.glob(f".{name}.tmp-*"):
            if leftover.name.rpartition("-")[2].isdigit() and leftover.is_file() and not leftover.is_symlink():
                leftover.unlink(missing_ok=True)
    return out


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
            "invalid_reasons": result.invalid_reasons,
        }
    )
