"""Evaluation and export callbacks: judge generated scenes by simulating them, and write the peft adapter.

`SceneEvaluation` generates greedily for a fixed validation subset at the end of every validation epoch and logs

    val/yaml_valid       share of responses that parse and validate as a scene
    val/sim_valid        share that also simulate without diverging
    val/count_acc        object-count accuracy;  val/composition_acc: multiset of shapes right
    val/iou_first, val/iou_full   segmentation IoU (first frame, sampled frames), 0 for invalid responses
    val/epe_first, val/epe_full   flow end-point error in px of a 480-wide image, `scorer.EPE_INVALID` if invalid
    val/position_mae, val/velocity_mae   initial-state errors (m, m/s), the metrics' penalties if unparsable
    val/baseline/...     the same metrics of the constant "average scene" predictor (`data.mean_scene`)

and writes `eval/predictions_stepNNNNNN.jsonl` and `eval/stepNNNNNN_sampleK.gif` (observed | predicted rollout,
side by side) under the run folder, plus the text and a frame strip to TensorBoard. A bad response never
raises: it is counted invalid with its reason. With several processes (trainer=ddp, fsdp) each one generates and
scores its share of the subset, and rank 0 gathers, logs and writes the results.
"""

from __future__ import annotations

import json
import logging
import math
import re
import signal
import threading
import warnings
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint, RichProgressBar
from lightning.pytorch.callbacks.progress.rich_progress import _RICH_AVAILABLE
from lightning.pytorch.plugins.io import TorchCheckpointIO
from lightning.pytorch.utilities.exceptions import SIGTERMException

from aynamics import adapters, lm, metrics, sharding
from aynamics.scene import Scene, SceneError, parse

log = logging.getLogger(__name__)

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
        observations: `scorer.Observation` of each video.

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


class AdapterExport(L.Callback):
    """Write the peft adapter (+ `aynamics.json`) to `dirpath` at every checkpoint and at the end of training, and
    put the specs into each checkpoint (`aynamics export-adapter CKPT --out DIR` writes that step's adapter).

    Args:
        dirpath: Folder of the adapter (default: `<trainer.default_root_dir>/adapter`).
    """

    def __init__(self, dirpath: str | None = None) -> None:
        self.dirpath = dirpath

    def _dir(self, trainer: L.Trainer) -> Path:
        return Path(self.dirpath) if self.dirpath else Path(trainer.default_root_dir) / "adapter"

    @staticmethod
    def _prompt(trainer: L.Trainer) -> lm.PromptSpec:
        return trainer.datamodule.prompt if trainer.datamodule is not None else lm.PromptSpec()

    def export(self, trainer: L.Trainer, pl_module: L.LightningModule) -> Path | None:
        """Rank 0 writes the adapter folder (returned; None on other ranks). Sharded weights (trainer=fsdp) are
        gathered first, on every rank."""
        state = sharding.trainable_state(pl_module.model) if sharding.is_sharded(pl_module.model) else None
        if not trainer.is_global_zero:
            return None
        return adapters.save_adapter(pl_module.model, self._dir(trainer), pl_module.spec, self._prompt(trainer), state)

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict) -> None:
        # plain JSON types (peft's dict holds enums and sets): checkpoints load with torch.load(weights_only=True)
        configs = {k: v.to_dict() for k, v in pl_module.model.peft_config.items()}
        checkpoint["adapter_config"] = json.loads(json.dumps(configs, default=_plain))
        # the specs too: `aynamics export-adapter CKPT` writes any checkpoint's adapter folder, not only the latest
        checkpoint["aynamics_meta"] = adapters.adapter_meta(pl_module.spec, self._prompt(trainer))
        self.export(trainer, pl_module)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.export(trainer, pl_module)


class StepCheckpoint(ModelCheckpoint):
    """Lightning's `ModelCheckpoint`, also saved after the step that ends training (max_steps, or the last batch of
    max_epochs) when it is off the cadence: a run of 1100 steps with `every_n_train_steps=200` writes
    `step001100.ckpt`, and its `last.ckpt` holds step 1100, not 1000 (Lightning alone saves at the end only when
    nothing was saved before, and then with the unfinished epoch marked done). `ckpt_path=OUT/checkpoints/last.ckpt`
    with a larger `trainer.max_steps` continues exactly where the run ended.

    SIGTERM (a cluster's preemption, `kill`) is noted and acted on where the checkpoints are saved: after the step
    under way, every process saves it and the run stops (Lightning's `SIGTERMException`; train.py exits 143), so
    `last.ckpt` resumes it exactly instead of from the last periodic save. Under ddp / fsdp the processes agree
    after each step (one all-reduce of a flag; the signal may reach any one of them): Lightning's own handling
    there hung on 2 CPU processes (its handler broadcasts from inside the signal). A signal during validation
    takes effect after the next training step, one during the last step lets the run end as planned (final
    validation included). The stopped step's training metrics are not logged (Lightning logs them after this
    hook). The save needs `save_last: true` when a `monitor` is set. A step must fit in the cluster's grace time
    (SLURM's KillWait: 30 s by default).

    The final-step save is skipped with a `monitor` (it comes before the final validation, which would rank it by
    the previous one's metric; the SIGTERM save then writes `last.ckpt` only), and for runs stopped otherwise
    (`should_stop`, `max_time`): Lightning's behaviour there."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._sigterm, self._step_seen = False, -1

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_fit_start(trainer, pl_module)
        self._sigterm = False

    def on_sanity_check_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_sanity_check_start(trainer, pl_module)
        self._listen()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_start(trainer, pl_module)
        self._step_seen = trainer.global_step
        self._listen()

    def _listen(self) -> None:
        # after Lightning registered its handler (just before the sanity check), which it restores (the one before
        # it) when the fit ends; signal handlers run in the main thread only
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._note_sigterm)

    def _note_sigterm(self, signum: int, frame) -> None:
        self._sigterm = True  # nothing else here: no collective, no logging, inside a signal handler

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args, **kwargs) -> None:
        super().on_train_batch_end(trainer, pl_module, *args, **kwargs)
        # saved where the periodic ones are (after the step, before the loop counts the batch done), so that
        # resuming from it continues the epoch; skipped when just saved, in fast_dev_run, outside fit
        # only after a batch that stepped the optimizer: with gradient accumulation a stop inside the window would
        # save a loop position the resumed batches would not line up with
        stepped, self._step_seen = trainer.global_step != self._step_seen, trainer.global_step
        stop = stepped and self._sigterm
        if stepped and trainer.world_size > 1:  # every process, after every step: one of them may have the signal
            stop = trainer.strategy.reduce_boolean_decision(stop, all=False)
        ending = ends_training(trainer)
        if not self._should_skip_saving_checkpoint(trainer) and (stop or ending):
            candidates = self._monitor_candidates(trainer)
            if self.monitor is None:
                self._save_topk_checkpoint(trainer, candidates)
            if self.monitor is None or stop:
                self._save_last_checkpoint(trainer, candidates)
        if stop and not ending:  # the last step: saved, and the run ends as planned
            log.warning("SIGTERM: the run stops after step %d", trainer.global_step)
            error = SIGTERMException()
            error.checkpoint = self.last_model_path or None  # the file to resume from, for train.py's message
            raise error


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint file writer, with each file written beside its final path and renamed into place.

    Lightning's own writes the checkpoint to a temporary file under $TMPDIR and moves it: where the run folder is on
    another filesystem (node-local /tmp, a shared run folder) the move copies over the final path, truncating it
    first, so a kill (SLURM after its grace time, the OOM killer) or a full disk during the copy left an empty or
    partial `last.ckpt` in place of the previous good one."""

    def save_checkpoint(self, checkpoint: dict, path, storage_options=None) -> None:
        import os

        from lightning.fabric.utilities.cloud_io import _is_local_file_protocol

        if storage_options is not None or not _is_local_file_protocol(str(path)):
            return super().save_checkpoint(checkpoint, path, storage_options)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.parent / f".{path.name}.tmp-{os.getpid()}"
        try:
            with open(tmp, "wb") as f:
                torch.save(checkpoint, f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)  # atomic: the file at `path` is the old checkpoint or the new one, whole
        finally:
            tmp.unlink(missing_ok=True)


class StepsProgressBar(RichProgressBar):
    """Lightning's rich progress bar without the epoch total it shows when epochs are unlimited: a run limited by
    `trainer.max_steps` has `max_epochs = -1`, which Lightning 2.6 prints as "Epoch 3/-2" (Lightning issue 21925,
    fixed in its later releases)."""

    def _get_train_description(self, current_epoch: int) -> str:
        text = f"Epoch {current_epoch}"
        if self.trainer.max_epochs is not None and self.trainer.max_epochs >= 0:
            text += f"/{self.trainer.max_epochs - 1}"
        return f"{text:{len(self.validation_description)}}"  # padded as Lightning's: no flicker beside Validation


def progress_bar(callbacks: Sequence[L.Callback], enabled: bool) -> list[L.Callback]:
    """The progress bar to add to `callbacks`: `StepsProgressBar` where Lightning would add its rich one (enabled,
    rich installed, none given); none otherwise (Lightning then adds its own tqdm bar, or none)."""
    from lightning.pytorch.callbacks.progress import ProgressBar

    if not enabled or not _RICH_AVAILABLE or any(isinstance(c, ProgressBar) for c in callbacks):
        return []
    return [StepsProgressBar()]


def use_atomic_checkpoints(trainer: L.Trainer) -> None:
    """Write the trainer's checkpoint files with `AtomicCheckpointIO` where it uses Lightning's plain file writer
    (strategies with their own, e.g. DeepSpeed's folders, keep theirs)."""
    if type(trainer.strategy.checkpoint_io) is TorchCheckpointIO:
        trainer.strategy.checkpoint_io = AtomicCheckpointIO()


def validation_number(trainer: L.Trainer, counted: int) -> int:
    """Which validation of the run this is (1 for the first): for validation every `val_check_batch` batches
    across epochs, from the batches trained (a resumed run continues the count; its own count restarted at 0 and
    missed the validation of the step it resumed from, which Lightning skips), else `counted`."""
    every = getattr(trainer, "val_check_batch", None)
    if getattr(trainer, "check_val_every_n_epoch", 1) is None and isinstance(every, int) and every > 0:
        return (trainer.fit_loop.epoch_loop.total_batch_idx + 1) // every
    return counted


def ends_training(trainer: L.Trainer) -> bool:
    """Whether the fit ends after the current batch (or the validation now running is its last): max_steps
    reached, or the last batch of the last epoch (max_epochs)."""
    if trainer.max_steps is not None and trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps:
        return True
    max_epochs = trainer.max_epochs
    if max_epochs is None or max_epochs < 0 or trainer.current_epoch + 1 < max_epochs:
        return False
    return bool(trainer.fit_loop.epoch_loop.batch_progress.is_last_batch)


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
        baseline: Also score the constant "average scene" (`data.mean_scene`): the training scenes of the most
            common object list (in generated data, usually a single object), every number averaged.
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
    """The records (`data.eval_record`) that can be scored, each with its parsed `scene` and the `observation` of
    it in the video's view; a record whose `scene_yaml` cannot be scored (hand-edited, corrupted) is left out with a
    warning naming its index among `where` (e.g. "validation records of data.dir = 'DIR'"): it never stops a
    training run or an evaluation."""
    from aynamics.scorer import Observation, scoring_size
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
    """The constant "average scene" (`data.mean_scene` of a training split's scenes) as YAML; None, with a warning,
    when no training scene parses."""
    from aynamics.data import mean_scene_of_split
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


def _plain(value):
    return sorted(value) if isinstance(value, set | frozenset) else str(value)


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
