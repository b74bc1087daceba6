"""The scene-evaluation callback: judge generated scenes by simulating them (adapter export and checkpoints are
`aynamics.run_callbacks`).

`SceneEvaluation` generates greedily for a fixed validation subset at the end of every validation epoch and logs

    val/yaml_valid       share of responses that parse and validate as a scene
    val/sim_valid        share that also simulate without diverging
    val/count_acc        object-count accuracy;  val/composition_acc: multiset of shapes right
    val/iou_first, val/iou_full   segmentation IoU (first frame, sampled frames), 0 for invalid responses
    val/epe_first, val/epe_full   flow end-point error in px of a 480-wide image, `scorer.EPE_INVALID` if invalid
    val/position_mae, val/velocity_mae   initial-state errors (m, m/s), the metrics' penalties if unparsable
    val/baseline/...     the same metrics of the constant "average scene" predictor (`average_scene.mean_scene`)

and writes `eval/predictions_stepNNNNNN.jsonl` and `eval/stepNNNNNN_sampleK.gif` (observed | predicted rollout,
side by side) under the run folder, plus the text and a frame strip to TensorBoard. A bad response never
raises: it is counted invalid with its reason. With several processes (trainer=ddp, fsdp) each one generates and
scores its share of the subset, and rank 0 gathers, logs and writes the results.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import numpy as np
import torch

from aynamics import lm, metrics, sharding
from aynamics.run_callbacks import (  # noqa: F401 - re-exported: configs name callbacks.StepCheckpoint, AdapterExport
    AdapterExport,
    StepCheckpoint,
    ends_training,
)
from aynamics.scene import Scene, SceneError, parse

METRIC_KEYS = (
    "yaml_valid",
    "sim_valid",
    "count_acc",
    "composition_acc",
    "iou_first",
    "iou_full",
    "epe_first",
    "epe_full",
    "position_mae",
    "velocity_mae",
)


def evaluate_texts(texts: Sequence[str], targets: Sequence[Scene] | None, observations: Sequence) -> dict[str, list]:
    """Per-response metrics of model outputs against their true scenes and observed videos (pure, batched).

    Args:
        texts: Model responses (the YAML is taken from <answer> tags when present).
        targets: The true scenes; None for videos without one (no count, composition or state errors then).
        observations: `observation.Observation` of each video.

    Returns:
        One list per key of `METRIC_KEYS` (floats, 1.0/0.0 for the rates; without targets only validity, IoU and
        EPE) plus "reason" (None when valid).
    """
    from aynamics.reward import score_completions

    n_targets = len(texts) if targets is None else len(targets)
    if not len(texts) == n_targets == len(observations):
        raise ValueError(f"{len(texts)} texts, {n_targets} targets, {len(observations)} observations: must match")
    yaml_valid = []
    for t in texts:
        try:
            parse(t)
            yaml_valid.append(1.0)
        except SceneError:
            yaml_valid.append(0.0)
    scores = [s[0] for s in score_completions([[t] for t in texts], observations)]
    out = {"yaml_valid": yaml_valid, "sim_valid": [float(s.valid) for s in scores]}
    if targets is not None:
        out["count_acc"], out["composition_acc"] = metrics.composition_accuracy(texts, targets)
    out |= {
        "iou_first": [s.iou_first for s in scores],
        "iou_full": [s.iou_full for s in scores],
        "epe_first": [s.epe_first for s in scores],
        "epe_full": [s.epe_full for s in scores],
    }
    if targets is not None:
        mae = metrics.state_mae_batch(texts, targets)
        out |= {"position_mae": [m[0] for m in mae], "velocity_mae": [m[1] for m in mae]}
    return out | {"reason": [s.reason for s in scores]}


def summarize(per_item: dict[str, list]) -> dict[str, float]:
    """Mean of each metric list of `evaluate_texts` (None entries skipped)."""
    return {k: metrics.mean_finite(per_item[k]) for k in METRIC_KEYS if k in per_item}


_INVALID_LABELS = {"no_yaml": "no YAML", "invalid_scene": "invalid fields", "truncated": "cut off at max_new_tokens"}


def invalid_reasons(reasons: Sequence[str | None]) -> dict[str, int]:
    """How many responses fail for each kind of reason (`evaluate_texts`' "reason"; None is valid), most first:
    "no YAML" (none, a syntax error or not a list of items), "invalid fields" (missing or out of range), "cut off at
    max_new_tokens", and for a scene that does not simulate the simulation's own words ("overlapping start",
    "blew up", "diverged", "tunnelled", "camera inside")."""
    from aynamics.reward import reason_kind

    counts: Counter[str] = Counter()
    for r in reasons:
        kind = reason_kind(r)
        if kind == "simulation":
            rest = r.removeprefix("sim:").strip()
            counts[re.match(r"camera inside|[^:]*", rest).group(0).strip() or "simulation"] += 1
        elif kind != "valid":
            counts[_INVALID_LABELS.get(kind, kind)] += 1
    return dict(counts.most_common())


def format_reasons(counts: dict[str, int], total: int) -> str:
    """The line under a table that says why the model's scenes fail ("" when every one simulates)."""
    if not counts:
        return ""
    bad = sum(counts.values())
    return f"Why {bad} of {total} responses do not simulate: " + ", ".join(f"{k} {v}" for k, v in counts.items())


def format_table(rows: dict[str, dict[str, float]]) -> str:
    """A plain-text table: one column per row name (e.g. "model", "average scene"), one line per metric."""
    names = list(rows)
    keys = [k for k in METRIC_KEYS if any(k in r for r in rows.values())]
    width = max(len(k) for k in keys) if keys else 10
    lines = [f"{'metric':<{width}}  " + "  ".join(f"{n:>14}" for n in names)]
    for k in keys:
        cells = [rows[n].get(k, float("nan")) for n in names]
        lines.append(f"{k:<{width}}  " + "  ".join(f"{c:>14.4f}" for c in cells))
    return "\n".join(lines)


def validation_number(trainer: L.Trainer, counted: int) -> int:
    """Which validation of the run this is (1 for the first): for validation every `val_check_batch` batches
    across epochs, from the batches trained (a resumed run continues the count; its own count restarted at 0 and
    missed the validation of the step it resumed from, which Lightning skips), else `counted`."""
    every = getattr(trainer, "val_check_batch", None)
    if getattr(trainer, "check_val_every_n_epoch", 1) is None and isinstance(every, int) and every > 0:
        return (trainer.fit_loop.epoch_loop.total_batch_idx + 1) // every
    return counted


class SceneEvaluation(L.Callback):
    """Generate scenes for a fixed validation subset and log simulated-scene metrics (see the module docstring).

    Args:
        num_samples: Validation records evaluated (the first ones, the same every time).
        max_new_tokens: Response length limit (a scene is ~600 tiny-tokenizer tokens; reasoning doubles it).
        batch_size: Prompts generated at once.
        num_animations: Records whose observed | predicted rollouts are written as GIFs (0: none).
        every_n_validations: Evaluate at every n-th validation run (Lightning validates every
            `val_check_interval` steps or each epoch); the one that ends training (max_steps reached, or the
            last batch of the last epoch) is always evaluated.
        baseline: Also score the constant "average scene" (`average_scene.mean_scene`): the training scenes of the
            most common object list (in generated data, usually a single object), every number averaged.
        out_dir: Folder of predictions and animations (default: `<trainer.default_root_dir>/eval`).
    """

    def __init__(
        self,
        num_samples: int = 8,
        max_new_tokens: int = 768,
        batch_size: int = 4,
        num_animations: int = 2,
        every_n_validations: int = 1,
        baseline: bool = True,
        out_dir: str | None = None,
    ) -> None:
        if num_samples < 1 or max_new_tokens < 1 or batch_size < 1 or num_animations < 0 or every_n_validations < 1:
            raise ValueError(
                f"num_samples = {num_samples}, max_new_tokens = {max_new_tokens}, batch_size = {batch_size}, "
                f"num_animations = {num_animations}, every_n_validations = {every_n_validations}: counts must be >= 1 "
                "(num_animations >= 0)"
            )
        self.num_samples, self.max_new_tokens, self.batch_size = num_samples, max_new_tokens, batch_size
        self.num_animations, self.every_n, self.baseline = num_animations, every_n_validations, baseline
        self.validations = 0  # validation runs seen (sanity checks excluded)
        self.out_dir = out_dir
        self._records: list[dict] | None = None
        self._baseline: dict[str, float] | None = None
        self.last: dict[str, float] = {}  # the latest summary (model), for scripts and tests
        self.last_reasons: dict[str, int] = {}  # why its invalid responses fail (`invalid_reasons`)
        self.evaluated = 0  # records in the latest evaluation (num_samples, or fewer if the split is smaller)
        self.step: int | None = None  # the training step of the latest evaluation
        self.last_baseline: dict[str, float] = {}

    def _prepare(self, trainer: L.Trainer, baseline: bool = True) -> None:
        """The evaluation records (and, with `baseline`, the average scene's scores): once per fit."""
        if self._records is not None:
            return
        dm = trainer.datamodule
        source = f"data.dir = {getattr(dm, 'dir', '?')!r}"
        self._records = scorable_records(
            dm.eval_records("validation", self.num_samples), f"validation records of {source}"
        )
        if self.baseline and baseline and self._records:
            average = average_scene_text(dm.splits["train"])
            if average is not None:
                self._baseline = baseline_summary(average, self._records)

    def _out(self, trainer: L.Trainer) -> Path:
        out = Path(self.out_dir) if self.out_dir else Path(trainer.default_root_dir) / "eval"
        out.mkdir(parents=True, exist_ok=True)
        return out

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        self.validations += 1
        if validation_number(trainer, self.validations) % self.every_n and not ends_training(trainer):
            return
        self.evaluate(trainer, pl_module)

    def evaluate(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, float]:
        """Generate, score, log and write files; returns the model's summary (on rank 0; {} on the others).

        With several processes (ddp, fsdp) each generates and scores its share of the records
        (`records_of_rank`) and rank 0 gathers the results, logs and writes them: the numbers of one process
        when the responses do not depend on the batching (batch_size 1; in larger batches a prompt's padding
        partners change with the number of processes). Every process builds the observed videos of all records,
        once per fit. Every process must call this (it gathers)."""
        rank, world = trainer.global_rank, trainer.world_size
        self._prepare(trainer, baseline=rank == 0)  # the same records on every rank; the baseline is rank 0's
        records = self._records
        if not records:  # every record left out (warned in _prepare)
            return {}
        mine, real = records_of_rank(len(records), rank, world, pad=sharding.is_sharded(pl_module.model))
        texts = self._generate(trainer, pl_module, [records[i] for i in mine])[:real]
        mine = mine[:real]
        per = evaluate_texts(texts, [records[i]["scene"] for i in mine], [records[i]["observation"] for i in mine])
        parts = _gather_objects((mine, texts, per), world)
        if rank != 0:
            return {}
        texts, per = merge_parts(parts, len(records))
        summary = summarize(per)
        self.last, self.evaluated, self.step = summary, len(records), getattr(trainer, "global_step", None)
        self.last_baseline = dict(self._baseline or {})
        self.last_reasons = invalid_reasons(per["reason"])
        log = {f"val/{k}": v for k, v in summary.items()}
        log |= {f"val/baseline/{k}": v for k, v in self.last_baseline.items()}
        for k, v in log.items():
            pl_module.log(k, float(v), rank_zero_only=True, on_epoch=True)
        self._write(trainer, texts, records, per)
        return summary

    def _generate(self, trainer: L.Trainer, pl_module: L.LightningModule, records: list[dict]) -> list[str]:
        """Greedy responses to the records' prompts."""
        processor = trainer.datamodule.processor
        texts: list[str] = []
        with torch.no_grad():
            for i in range(0, len(records), self.batch_size):
                chunk = [r["prompt"] for r in records[i : i + self.batch_size]]
                texts += lm.greedy_texts(pl_module.model, processor, chunk, self.max_new_tokens)
        return texts

    def _write(self, trainer: L.Trainer, texts: list[str], records: list[dict], per: dict[str, list]) -> None:
        out = self._out(trainer)
        step = trainer.global_step
        write_predictions(out / f"predictions_step{step:06d}.jsonl", texts, records, per)
        tb = _tensorboard(trainer)
        if tb is not None:
            for k, text in enumerate(texts[:4]):
                tb.add_text(f"val/prediction_{k}", "```\n" + text + "\n```", global_step=step)
        for k in range(min(self.num_animations, len(records))):
            try:
                predicted = parse(texts[k])
            except SceneError:
                continue
            try:
                frames = side_by_side(records[k]["scene"], predicted)
            except Exception as e:  # no OpenGL here, or a diverging prediction: skip the animation, say why
                warnings.warn(f"animation of sample {k} skipped: {type(e).__name__}: {e}", stacklevel=2)
                continue
            import imageio.v3 as iio

            iio.imwrite(out / f"step{step:06d}_sample{k}.gif", frames, duration=1000 / 15, loop=0)
            if tb is not None:
                strip = np.concatenate(list(frames[:: max(1, len(frames) // 4)]), axis=0)  # (4H, 2W, 3)
                tb.add_image(f"val/rollout_{k}", strip, global_step=step, dataformats="HWC")


def json_safe(value):
    """`value` with every NaN or infinite float (a metric nothing could be computed for, e.g. EPE without observed
    flow) as None: strict JSON readers refuse Python's bare NaN."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def write_predictions(path: Path, texts: Sequence[str], records: Sequence[dict], per: dict[str, list]) -> None:
    """One JSON line per record: its `index` (a video folder's name for unlabeled videos), the `prediction`, the
    `target` scene (None without one) and its metrics and `reason` (`evaluate_texts`; every key of `per`, in its
    order)."""
    with open(path, "w") as f:
        for k, (text, r) in enumerate(zip(texts, records, strict=True)):
            key = r["index"] if isinstance(r["index"], str) else int(r["index"])  # a video folder's name, or an index
            row = {"index": key, "prediction": text, "target": r.get("scene_yaml")}
            row |= {m: v[k] for m, v in per.items()}
            f.write(json.dumps(json_safe(row), allow_nan=False) + "\n")


def scorable_records(records: Sequence[dict], where: str = "records") -> list[dict]:
    """The records (`eval_records.eval_record`) that can be scored, each with its parsed `scene` and the
    `observation` of it in the video's view; a record whose `scene_yaml` cannot be scored (hand-edited, corrupted)
    is left out with a warning naming its index among `where` (e.g. "validation records of data.dir = 'DIR'"): it
    never stops a training run or an evaluation."""
    from aynamics.observation import Observation, scoring_size
    from aynamics.simulate import FPS

    out = []
    for r in records:
        try:
            scene = parse(r["scene_yaml"])
            # The video's aspect ratio: the camera's field of view is vertical, so at another width the scene
            # would be scored in a wider or narrower view than the model saw.
            width, height = scoring_size(*r["size"])
            observation = Observation.from_scene(
                scene,
                width=width,
                height=height,
                frames=r.get("frames"),
                fps=r.get("fps", FPS),
                substeps=r.get("substeps"),
            )
        except (SceneError, ValueError) as e:
            warnings.warn(
                f"scene evaluation: record {r['index']} of the {where} is left out: its scene_yaml cannot be "
                f"scored ({e})",
                stacklevel=2,
            )
            continue
        out.append(r | {"scene": scene, "observation": observation})
    return out


def average_scene_text(train_split) -> str | None:
    """The constant "average scene" (`average_scene.mean_scene` of a training split's scenes) as YAML; None, with a
    warning, when no training scene parses."""
    from aynamics.average_scene import mean_scene_of_split
    from aynamics.scene import dump

    try:
        return dump(mean_scene_of_split(train_split))
    except ValueError as e:
        warnings.warn(f"scene evaluation: no average-scene baseline ({e})", stacklevel=2)
        return None


def baseline_summary(text: str, records: Sequence[dict]) -> dict[str, float]:
    """The metrics of one constant prediction `text` (the average scene) on every record of `records` (with `scene`
    and `observation`, from `scorable_records`)."""
    texts = [text] * len(records)
    return summarize(evaluate_texts(texts, [r["scene"] for r in records], [r["observation"] for r in records]))


def records_of_rank(n: int, rank: int, world: int, pad: bool = False) -> tuple[list[int], int]:
    """The evaluation records (indices into n) that process `rank` of `world` generates and scores.

    Every `world`-th record from `rank` on. With `pad` (sharded weights: every process takes part in every
    `generate` call, so all must make the same calls) the list is filled up to ceil(n / world) with its last
    record, or record 0 when it has none; those extra responses are generated and dropped.

    Returns:
        (indices, real): the records to generate for, and how many of them (the first `real`) to score.
    """
    if n < 0 or world < 1 or not 0 <= rank < world:
        raise ValueError(f"n = {n}, rank = {rank}, world = {world}: need n >= 0, world >= 1, 0 <= rank < world")
    mine = list(range(rank, n, world))
    real = len(mine)
    if pad and n:
        mine += [mine[-1] if mine else 0] * (-(-n // world) - real)
    return mine, real


def merge_parts(parts: Sequence[tuple[list[int], list[str], dict[str, list]]], n: int) -> tuple[list, dict]:
    """The texts and per-record metrics of all `n` records, in record order, from each process's
    (indices, texts, per-record metrics) of `records_of_rank`.

    Raises:
        ValueError: a record is missing or given twice.
    """
    order = [i for indices, _, _ in parts for i in indices]
    if sorted(order) != list(range(n)):
        raise ValueError(f"the processes' records {sorted(order)} are not each of the {n} records once")
    where = {i: (p, k) for p, (indices, _, _) in enumerate(parts) for k, i in enumerate(indices)}
    texts = [parts[where[i][0]][1][where[i][1]] for i in range(n)]
    keys = parts[0][2].keys() if parts else ()
    per = {key: [parts[where[i][0]][2][key][where[i][1]] for i in range(n)] for key in keys}
    return texts, per


def _gather_objects(obj, world: int) -> list:
    """Every process's `obj`, in rank order (the default process group; just [obj] for one process)."""
    if world == 1:
        return [obj]
    out: list = [None] * world
    torch.distributed.all_gather_object(out, obj)
    return out


def _tensorboard(trainer: L.Trainer):
    from lightning.pytorch.loggers import TensorBoardLogger

    for logger in trainer.loggers:
        if isinstance(logger, TensorBoardLogger):
            return logger.experiment
    return None


def side_by_side(observed: Scene, predicted: Scene, width: int = 160, height: int = 106) -> np.ndarray:
    """(T, H, 2W, 3) uint8 video: the observed scene's rollout left, the predicted one right (OpenGL).

    Raises:
        aynamics.render.RenderError: no headless OpenGL.
        ValueError: the predicted scene's simulation diverged.
    """
    from aynamics import render as renderlib
    from aynamics.simulate import simulate

    roll_obs, roll_pred = simulate(observed), simulate(predicted)
    if not roll_pred.valid:
        raise ValueError(f"predicted scene does not simulate: {roll_pred.reason}")
    with renderlib.Renderer(width, height) as r:
        left = r.render(observed, roll_obs, seed=0, segmentation=False, depth=False).rgb
        right = r.render(predicted, roll_pred, seed=0, segmentation=False, depth=False).rgb
    return np.concatenate([left, right], axis=2)
