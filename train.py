"""Train a vision-language model to write scenes: the only place Hydra appears.

    python train.py stage=sft model=tiny data.dir=DIR trainer.max_steps=20 hydra.run.dir=OUT
    python train.py -m data.modality=rgb,flow stage.target=answer,think_answer   # then: python -m aynamics.collect
    python train.py experiment=make_train                                          # what `make train` runs
    python train.py debug=fast_dev_run                                             # one batch end to end

`train(cfg)` turns the config into plain typed objects (a `ModelSpec`, a `SceneDataModule`, an `SFTModule`,
callbacks, loggers, a `Trainer`), fits, writes `OUT/metrics.json` and returns the final metrics.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import shlex
import sys
import traceback
import warnings
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering of the evaluation animations (before mujoco loads)


def _instantiate_group(group: DictConfig | None) -> list:
    """Instantiate every entry of a config group holding several objects (callbacks, loggers); nulls skipped."""
    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if c is not None and "_target_" in c]


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit the stage described by `cfg` and return the final metrics (also written to `OUT/metrics.json`)."""
    import lightning as L

    from aynamics.adapters import check_resume_checkpoint, check_resume_settings
    from aynamics.callbacks import SceneEvaluation, format_reasons, format_table, json_safe
    from aynamics.lm import TARGETS
    from aynamics.processor import PixelBoundsError
    from aynamics.run_callbacks import progress_bar, use_atomic_checkpoints
    from aynamics.sharding import model_init_context

    check_whole_numbers(cfg)
    interval = cfg.trainer.get("val_check_interval")
    if interval is not None and not (isinstance(interval, int) and not isinstance(interval, bool) and interval > 0):
        # Lightning divided by 0 after the first step, and refused a share of an epoch with a traceback
        raise ValueError(f"trainer.val_check_interval = {interval}: must be a whole number of steps > 0")
    steps = cfg.trainer.get("max_steps")
    if not (isinstance(steps, int) and (steps >= 1 or steps == -1)):  # 0 trained nothing and wrote no adapter
        raise ValueError(f"trainer.max_steps = {steps}: must be >= 1 (or -1 with trainer.max_epochs > 0)")
    epochs = cfg.trainer.get("max_epochs")
    if epochs is not None and not (isinstance(epochs, int) and not isinstance(epochs, bool) and epochs >= -1):
        raise ValueError(f"trainer.max_epochs = {epochs!r}: must be a whole number >= 1, or -1 (no epoch limit)")
    if epochs == 0 or (steps == -1 and epochs == -1):  # null: Lightning's 1000 epochs
        # 0 stopped before the first batch: exit status 0, no adapter, an empty metrics.json; both -1 failed in the
        # learning-rate schedule, once the model had loaded
        raise ValueError(
            f"trainer.max_steps = {steps}, trainer.max_epochs = {epochs}: "
            + ("trains nothing" if epochs == 0 else "training has no end, so the learning-rate schedule has no length")
            + "; set trainer.max_steps (or trainer.max_epochs with trainer.max_steps=-1) to a count >= 1"
        )
    seed = cfg.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
        # "-1 is not in bounds, numpy accepts from 0 to 4294967295" or "invalid literal for int()", naming no key
        raise ValueError(f"seed = {seed!r}: must be a whole number in [0, 2**32 - 1]")
    every = ((cfg.get("callbacks") or {}).get("checkpoint") or {}).get("every_n_train_steps")
    if every is not None and not (isinstance(every, int) and every >= 1):
        raise ValueError(f"callbacks.checkpoint.every_n_train_steps = {every}: must be a whole number >= 1")
    clip = cfg.trainer.get("gradient_clip_val")
    if clip is not None and not (isinstance(clip, int | float) and math.isfinite(clip) and clip >= 0):
        # a negative value turned clipping off without a word; NaN failed in the first step, once the model had
        # loaded, with Lightning's "set gradient_clip_val ... use only one of them"
        raise ValueError(f"trainer.gradient_clip_val = {clip}: must be a finite number >= 0, or null (no clipping)")
    if cfg.trainer.get("use_distributed_sampler"):  # Lightning would shard each process's share again
        raise ValueError(
            "trainer.use_distributed_sampler = true: the data modules give each process its own share themselves "
            "(resumable, evaluation padding marked); set it to false"
        )
    if cfg.stage.target not in TARGETS:
        raise ValueError(f"stage.target = {cfg.stage.target!r}: must be one of {TARGETS}")
    if cfg.data.get("target", cfg.stage.target) != cfg.stage.target:  # the data take the stage's: one key
        raise ValueError(f"data.target = {cfg.data.target!r}: set the target as stage.target={cfg.data.target}")
    if cfg.get("ckpt_path"):
        check_resume_checkpoint(cfg.ckpt_path, cfg.stage.get("name"))  # before the model loads
    L.seed_everything(cfg.seed, workers=True)
    out = Path(cfg.output_dir)
    checkpoints = ((cfg.get("callbacks") or {}).get("checkpoint") or {}).get("dirpath")
    if not cfg.get("ckpt_path") and (found := earlier_run(out, checkpoints)):
        # a fresh run there versioned its checkpoints beside the earlier ones (last-v1.ckpt, while the SIGTERM
        # message and the README name last.ckpt, the earlier run's) and overwrote its adapter, predictions and CSV
        raise ValueError(
            f"hydra.run.dir = {str(out)!r} holds an earlier run ({found}): resume it with ckpt_path=CHECKPOINT, or "
            "give a new hydra.run.dir (a fresh run there would overwrite its adapter and results)"
        )
    folder = Path(checkpoints) if checkpoints else out / "checkpoints"
    if cfg.get("ckpt_path") and Path(cfg.ckpt_path).resolve().parent != folder.resolve():
        if found := earlier_run(out, checkpoints):
            # another run's checkpoint resumed there mixed two runs: last-v1.ckpt beside the other's last.ckpt, and
            # the other's adapter and metrics.json overwritten
            raise ValueError(
                f"ckpt_path = {cfg.ckpt_path!r} is not a checkpoint of the run in hydra.run.dir = {str(out)!r} "
                f"({found}): resume in the checkpoint's own run folder, or give a new hydra.run.dir"
            )
    out.mkdir(parents=True, exist_ok=True)
    callbacks = _instantiate_group(cfg.get("callbacks"))
    shown = cfg.trainer.get("enable_progress_bar")  # null: Lightning's default, a bar (none under barebones)
    callbacks += progress_bar(callbacks, enabled=(shown is None or bool(shown)) and not cfg.trainer.get("barebones"))
    loggers = _instantiate_group(cfg.get("logger"))
    # Lightning's CSV logger deletes the metrics.csv it finds when it starts: a resume keeps its rows aside and
    # puts them back in front of the resumed ones
    csv_logs = keep_csv_logs(loggers) if cfg.get("ckpt_path") else []
    # val_check_interval counts steps, as checkpoints do: Lightning counts batches, accumulation times as many
    accumulate = int(cfg.trainer.get("accumulate_grad_batches") or 1)
    batches = {} if interval is None else {"val_check_interval": interval * accumulate}
    # before the model: a strategy or precision this machine lacks (deepspeed not installed) fails in seconds
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, **batches)
    use_atomic_checkpoints(trainer)  # a kill or a full disk mid-save never leaves a partial last.ckpt
    L.seed_everything(cfg.seed, workers=True, verbose=False)  # the model's random draws as before the trainer
    spec = hydra.utils.instantiate(cfg.model)
    datamodule = hydra.utils.instantiate(cfg.data, processor_path=spec.processor_path, target=cfg.stage.target)
    try:
        datamodule.setup("fit")  # a wrong data.dir or data.num_frames is named now, not after the model has loaded
    except PixelBoundsError as error:  # the processor's "min_pixels = 20000 > max_pixels = 10000": data's keys
        raise ValueError(re.sub(r"\b(min|max)_pixels\b", r"data.\1_pixels", str(error))) from None
    if cfg.get("ckpt_path"):  # another base, adapter or (SFT) prompt: named before the model loads, not after
        prompt = datamodule.prompt if cfg.stage.get("name") == "sft" else None  # PRO's is its init adapter's
        check_resume_settings(cfg.ckpt_path, spec, prompt)
    warn_drifting_validation(datamodule, trainer, interval, accumulate)
    # the run ends at whichever limit comes first: max_steps, or max_epochs' steps
    limits = [n for n in (steps if steps > 0 else None, run_steps(datamodule, trainer, accumulate)) if n is not None]
    length = min(limits) if limits else None
    if length is not None and 0 < length < trainer.log_every_n_steps:  # shorter than the interval (null: 50)
        trainer.log_every_n_steps = length  # logged no training metrics (csv/metrics.csv held its header only)
    with model_init_context(trainer):  # trainer=fsdp: only rank 0 loads the base, the others get its weights
        try:
            module = hydra.utils.instantiate(cfg.stage.module)(spec=spec)
        except ValueError as error:  # "lr = -1: ..." is stage.module.lr
            if not raised_in_init(error):  # the model's build ("lora dropout = 1.5", model.tiny's "hidden_size")
                raise
            raise ValueError(name_keys(str(error), "stage.module")) from error
    try:
        with warnings.catch_warnings():
            # Lightning warns when an epoch has fewer batches than the logging interval, but it counts the interval
            # over the run's steps, epochs together (and a run shorter than it logs its last step, above)
            warnings.filterwarnings("ignore", r"The number of training batches \(\d+\) is smaller than the logging")
            trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
    except Exception as error:
        with contextlib.suppress(AttributeError):
            error.raised_in_fit = True  # see input_error_message
        raise

    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    metrics = {k: v for k, v in metrics.items() if math.isfinite(v) or k.startswith("val/")}
    resumed = getattr(module, "resumed_step", None)
    evaluation = next((c for c in callbacks if isinstance(c, SceneEvaluation)), None)
    if resumed is not None and resumed >= trainer.global_step:  # nothing trained
        validated_last = interval is not None and resumed % interval == 0
        if recorded_step(out) == resumed or not validated_last:  # the results stay as they were
            if trainer.is_global_zero:
                join_csv_logs(csv_logs, resumed)
            logging.getLogger(__name__).warning(
                f"ckpt_path = {cfg.ckpt_path!r} had reached step {resumed}, trainer.max_steps = "
                f"{cfg.trainer.max_steps}: nothing trained, {out / 'metrics.json'} left as it was; give a larger "
                "trainer.max_steps to continue"
            )
            return metrics
        # the run was stopped after its last checkpoint and before its results (in the final validation, which a
        # resumed run skips): validate that step again, then write its metrics.json as the run would have
        logging.getLogger(__name__).warning(
            f"ckpt_path = {cfg.ckpt_path!r} had reached step {resumed} without its results in "
            f"{out / 'metrics.json'}: validating step {resumed} again"
        )
        trainer.validate(module, datamodule=datamodule, verbose=False)
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
        metrics = {k: v for k, v in metrics.items() if math.isfinite(v) or k.startswith("val/")}
    if trainer.is_global_zero:
        join_csv_logs(csv_logs, resumed)
        save_run_config(cfg)  # the settings of these results (a resume's), beside them
        overrides = OmegaConf.to_container(cfg, resolve=False) if cfg.get("save_config", True) else {}
        record = {"metrics": metrics, "global_step": trainer.global_step, "config": overrides}
        if evaluation is not None and evaluation.step is not None:
            record["val_step"] = evaluation.step  # the step of the val/ metrics (the last validation's)
        text = json.dumps(json_safe(record), indent=2, default=str, allow_nan=False)
        tmp = out / f".metrics.json.tmp-{os.getpid()}"
        tmp.write_text(text)
        os.replace(tmp, out / "metrics.json")  # whole or not at all: a resume reads its global_step
        if cfg.get("print_table", True) and evaluation is not None and evaluation.last:
            rows = {"model": evaluation.last}
            if evaluation.last_baseline:
                rows["average scene"] = evaluation.last_baseline
            print(f"\nValidation ({evaluation.evaluated} held-out scenes, step {evaluation.step}):")
            print(format_table(rows))
            if why := format_reasons(evaluation.last_reasons, evaluation.evaluated):
                print(why)
            adapter = ((cfg.get("callbacks") or {}).get("adapter") or {}).get("dirpath")
            if adapter and cfg.get("data", {}).get("dir"):  # the split training never read, in the same settings
                command = ["aynamics", "evaluate", "--adapter", adapter, "--data", cfg.data.dir]
                command += ["--batch-size", evaluation.batch_size, "--max-new-tokens", evaluation.max_new_tokens]
                print(f"The test split's table: {shlex.join(str(c) for c in command)}")
    return metrics


# keys holding a count: (the least value, whether null is allowed); a fraction, a NaN or a string failed deep in
# the data loaders or Lightning with a traceback (accumulate_grad_batches=0: a ZeroDivisionError once the model had
# loaded), and PRO took data.limit_val=0 as "no validation split" and validated on training videos
WHOLE_NUMBERS = {
    "trainer.accumulate_grad_batches": (1, False),
    "data.num_frames": (1, False),
    "data.batch_size": (1, False),
    "data.eval_batch_size": (1, True),
    "data.num_workers": (0, True),
    "data.num_examples": (0, False),
    "data.limit_train": (1, True),
    "data.limit_val": (1, True),
}


def check_whole_numbers(cfg: DictConfig) -> None:
    """Refuse a count key of `WHOLE_NUMBERS` that is not a whole number in its range, naming the key and value."""
    absent = object()
    for key, (least, nullable) in WHOLE_NUMBERS.items():
        value = OmegaConf.select(cfg, key, default=absent)
        if value is absent or (value is None and nullable):
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ValueError(f"{key} = {value!r}: must be >= {least} (a whole number{', or null' * nullable})")


def save_run_config(cfg: DictConfig) -> None:
    """Write `OUT/.hydra/` (config.yaml, hydra.yaml, overrides.yaml) as Hydra does, which conf/config.yaml turns
    off (`hydra.output_subdir: null`): `main` writes it into a folder without an earlier run, and `train` when it
    writes the run's results, so a run refused because the folder holds another run (a fresh one, or another run's
    checkpoint) leaves that run's settings there (`aynamics collect` reads its overrides.yaml). Nothing outside
    Hydra (`train(cfg)` called directly), nor in a process of local rank > 0."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized() or int(os.environ.get("LOCAL_RANK") or 0) != 0:
        return
    hydra_cfg = HydraConfig.instance().cfg
    folder = Path(hydra_cfg.hydra.runtime.output_dir) / ".hydra"
    folder.mkdir(parents=True, exist_ok=True)
    for name, node in (
        ("config.yaml", cfg),
        ("hydra.yaml", hydra_cfg),
        ("overrides.yaml", hydra_cfg.hydra.overrides.task),
    ):
        tmp = folder / f".{name}.tmp-{os.getpid()}"
        tmp.write_text(OmegaConf.to_yaml(node))
        os.replace(tmp, folder / name)


def earlier_run(out: Path, checkpoints: str | None) -> str | None:
    """What of an earlier training run the folder `out` holds (a checkpoint, else its metrics.json), or None."""
    folder = Path(checkpoints) if checkpoints else out / "checkpoints"
    names = sorted(p.name for p in folder.glob("*.ckpt")) if folder.is_dir() else []
    if names:
        return str(folder / ("last.ckpt" if "last.ckpt" in names else names[-1]))
    return str(out / "metrics.json") if (out / "metrics.json").is_file() else None


CSV_KEPT = "metrics.before-resume.csv"


def keep_csv_logs(loggers: list) -> list[Path]:
    """The `metrics.csv` of each CSV logger in `loggers`. Lightning's CSVLogger deletes the one it finds when it
    starts, so before a resume its rows are copied beside it (`metrics.before-resume.csv`, joined to those of an
    earlier resume that was stopped before `join_csv_logs`); rank 0 only, as the logger."""
    from lightning.fabric.utilities.rank_zero import rank_zero_only
    from lightning.pytorch.loggers import CSVLogger

    paths = [Path(log.log_dir) / "metrics.csv" for log in loggers if isinstance(log, CSVLogger)]
    if rank_zero_only.rank == 0:
        for path in paths:
            if path.is_file():
                _write_csv(path.with_name(CSV_KEPT), *_joined_rows(path.with_name(CSV_KEPT), path))
    return paths


def join_csv_logs(paths: list[Path], resumed_step: int | None) -> None:
    """Each `metrics.csv` of `paths` whole again after a resume from `resumed_step`: the kept rows logged before
    that step (a run stopped after its last checkpoint logged steps the resume trains again), then the resumed
    run's."""
    for path in paths:
        kept = path.with_name(CSV_KEPT)
        if kept.is_file():
            _write_csv(path, *_joined_rows(kept, path, until=resumed_step))
            kept.unlink()


def _joined_rows(older: Path, newer: Path, until: int | None = None) -> tuple[list[str], list[dict]]:
    """The columns and rows of two Lightning CSV logs (either may be missing), `older`'s first: those of its rows
    logged before step `until`, the step the newer run resumed from, or without it before the first training step
    `newer` logs. (The step column counts from 0: a checkpoint at step 5 holds the rows of steps 0-4 and of a
    validation at step 5, which is logged as 4.)"""
    import csv

    def read(path: Path) -> tuple[list[str], list[dict]]:
        if not path.is_file():
            return [], []
        with path.open(newline="") as file:
            reader = csv.DictReader(file)
            return list(reader.fieldnames or []), list(reader)

    def step(row: dict) -> float:
        try:
            return float(row.get("step") or "nan")
        except ValueError:
            return math.nan

    def validation_only(row: dict) -> bool:
        return all(k in ("epoch", "step") or k.startswith("val/") or not v for k, v in row.items())

    (old_fields, old_rows), (new_fields, new_rows) = read(older), read(newer)
    if until is None:
        until = min((step(r) for r in new_rows if not validation_only(r) and math.isfinite(step(r))), default=math.inf)
    old_rows = [r for r in old_rows if not step(r) >= until]  # a row without a step is kept
    fields = old_fields + [f for f in new_fields if f not in old_fields]
    return fields, old_rows + new_rows


def _write_csv(path: Path, fields: list[str], rows: list[dict]) -> None:
    """`rows` under the header `fields`, written beside `path` and renamed into it."""
    import csv

    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with tmp.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


def recorded_step(out: Path) -> int | None:
    """The `global_step` of the run's `metrics.json` (written once its results are), or None without one."""
    try:
        return json.loads((out / "metrics.json").read_text())["global_step"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def epoch_batches(datamodule, trainer) -> int | None:
    """Training batches in one process's epoch, as `loaders.resumable_loader` shards them (SFT: `data.limit_train`
    or the training split; PRO: its videos or preference rows), or None for a data module that does not say."""
    if hasattr(datamodule, "splits"):
        n = len(datamodule.splits["train"])
        n, size = (min(n, datamodule.limit_train) if datamodule.limit_train else n), datamodule.batch_size
    elif hasattr(datamodule, "train_set"):
        n, size = len(datamodule.train_set), datamodule.hparams.batch_size
    else:
        return None
    batches = math.ceil(math.ceil(n / trainer.world_size) / size)
    limit = trainer.limit_train_batches  # Lightning's own cap: a count, or a share of the epoch
    if isinstance(limit, int):
        return min(batches, limit)
    return int(batches * limit) if isinstance(limit, float) and limit < 1 else batches


def run_steps(datamodule, trainer, accumulate: int) -> int | None:
    """Optimizer steps of a run limited by `trainer.max_epochs` (`max_steps` -1): Lightning steps on every
    `accumulate`-th batch and on each epoch's last. None where unknown (no epoch limit, another data module)."""
    batches = epoch_batches(datamodule, trainer)
    epochs = trainer.max_epochs
    if batches is None or epochs is None or epochs < 1:
        return None
    return epochs * math.ceil(batches / accumulate)


def warn_drifting_validation(datamodule, trainer, interval: int | None, accumulate: int) -> None:
    """Warn when validation every `interval` optimizer steps cannot keep to them: Lightning validates every
    `interval * accumulate` batches counted across epochs, and steps the optimizer on each epoch's last batch too,
    so when an epoch's batches are not a multiple of `accumulate` the validations fall later and later in steps."""
    if interval is None or accumulate <= 1 or (batches := epoch_batches(datamodule, trainer)) is None:
        return
    if batches % accumulate:
        logging.getLogger(__name__).warning(
            f"trainer.val_check_interval = {interval} steps with trainer.accumulate_grad_batches = {accumulate}: an "
            f"epoch is {batches} batches, not a multiple of {accumulate}, so its last step takes fewer batches and "
            "validation drifts off every "
            f"{interval} steps (and off the checkpoints' steps); choose data.batch_size or data.limit_train so that "
            f"an epoch's batches divide by {accumulate}"
        )


class _NoTips(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "Tip:" not in str(record.msg)  # Lightning's advertisement of a cloud logger


def one_log_stream() -> None:
    """Each log line once: Lightning's loggers print through their own console handler and again, propagated,
    through Hydra's (console and `OUT/train.log`); Hydra's is kept. Lines nobody can act on are dropped:
    Lightning's cloud-logger tip, PyOpenGL's missing accelerator and Lightning's pytree deprecation under
    this torch."""
    import lightning  # noqa: F401  (adds Lightning's handlers, removed here)

    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            if type(handler) is logging.StreamHandler:
                logger.removeHandler(handler)
                logger.propagate = True
    logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(_NoTips())
    logging.getLogger("OpenGL").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", r".*isinstance\(treespec, LeafSpec\)", category=FutureWarning)


def input_error_message(error: BaseException) -> str | None:
    """The one-paragraph message of an error in the run's input, or None for any other error (a bug, out of
    memory, a NaN: those keep their traceback). Input errors are the ones the config, the data or a checkpoint
    cause: a value out of range (ValueError, with the key and the value), a missing or unreadable file or
    model (OSError), an optional package not installed, an interpolation that cannot resolve, and a
    constructor refusing its config (Hydra's InstantiationException, whose cause is named with its key).
    Once training has started, only those this project raised (a check of ours, e.g. a checkpoint that does not
    fit the config): a ValueError from inside torch or a full disk while saving keeps its traceback."""
    from hydra.errors import InstantiationException
    from lightning.fabric.utilities.exceptions import MisconfigurationException
    from omegaconf.errors import OmegaConfBaseException

    if getattr(error, "raised_in_fit", False) and not raised_here(error):
        return None
    config_errors = ValueError | OSError | ImportError | MisconfigurationException  # ImportError: a missing package
    if isinstance(error, InstantiationException):
        cause = error.__cause__
        key = re.search(r"full_key: (\S+)", str(error))
        if cause is None or not isinstance(cause, config_errors | TypeError):
            return None
        return name_keys(_said(cause), key.group(1)) if key else _said(cause)
    if isinstance(error, OmegaConfBaseException):  # its text goes on with full_key and object_type lines
        key = getattr(error, "full_key", None)
        return f"{str(error).splitlines()[0]} (config: {key})" if key else str(error).splitlines()[0]
    if isinstance(error, config_errors):  # flash-attn not installed: ImportError while the model loads
        return _said(error)
    return None


def _said(error: BaseException) -> str:
    """An error's text; a missing file's without "[Errno 2] " ("stage.init_adapter = '/x' holds no ...")."""
    if isinstance(error, FileNotFoundError):
        from aynamics.cli import missing_file_message

        return missing_file_message(error)
    return str(error)


def raised_in_init(error: BaseException) -> bool:
    """Whether a module's own constructor raised the error (its arguments are stage.module's keys), not a function
    it called: `lm.build_model` refuses the model config's values (model.lora_dropout, model.tiny.hidden_size)."""
    import lightning as L

    tb = innermost(error)
    return (
        tb is not None
        and tb.tb_frame.f_code.co_name == "__init__"
        and isinstance(tb.tb_frame.f_locals.get("self"), L.LightningModule)
    )  # not a transformers config's __init__ inside the model's build


def name_keys(message: str, key: str) -> str:
    """A config node's error with its keys in full: "min_pixels = 0: must be >= 784" from `data` reads
    "data.min_pixels = 0: must be >= 784"; a message naming no `name = value` before its first ': ' ends
    "(config: data)"; one that names its key in full already ("model.lora_rank = 0: ...") is left as it is."""
    head, sep, tail = message.partition(": ")
    if re.match(rf"{re.escape(key)}\.\w", head):  # named in full already: "model.tiny.num_heads = 0"
        return message
    named, n = re.subn(r"(^|, )([a-z_]\w*) = ", rf"\g<1>{key}.\g<2> = ", head)
    return f"{named}{sep}{tail}" if n else f"{message} (config: {key})"


def innermost(error: BaseException):
    """The innermost traceback entry of an error (where it was raised), or None for one never raised."""
    tb = error.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb


def raised_here(error: BaseException) -> bool:
    """Whether a check of this project raised the error: the innermost frame of its traceback is a `raise`
    statement in aynamics/ or train.py (a builtin failing there, `open` on a full disk or an unpacking, adds no
    frame of its own and is not a `raise`)."""
    import linecache

    import aynamics

    tb = innermost(error)
    if tb is None:
        return False
    filename = tb.tb_frame.f_code.co_filename
    path = Path(filename).resolve()
    ours = path == Path(__file__).resolve() or Path(aynamics.__file__).resolve().parent in path.parents
    return ours and linecache.getline(filename, tb.tb_lineno).lstrip().startswith("raise")


def report_input_error(error: BaseException, message: str) -> None:
    """Write an input error's message (`input_error_message`) as one paragraph on stderr, its traceback to the
    run's log files only."""
    message = " ".join(message.split())
    files = [h for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]
    detail = "".join(traceback.format_exception(error))
    for handler in files:
        handler.stream.write(f"{message}\n{detail}")
        handler.flush()
    where = f" (traceback in {files[0].baseFilename})" if files else ""
    sys.stderr.write(f"train.py: {message}{where}\n")


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    """`python train.py ...`: an input error (see `input_error_message`) ends the run with status 2 and one
    paragraph naming the key and the value; HYDRA_FULL_ERROR=1 shows Hydra's report with the traceback. SIGTERM
    (a preemption) ends it with status 143 after the step under way, saved by `run_callbacks.StepCheckpoint`."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from lightning.pytorch.utilities.exceptions import SIGTERMException
    from lightning.pytorch.utilities.rank_zero import rank_zero_only

    one_log_stream()
    checkpoints = ((cfg.get("callbacks") or {}).get("checkpoint") or {}).get("dirpath")
    if earlier_run(Path(HydraConfig.get().runtime.output_dir), checkpoints) is None:
        save_run_config(cfg)  # a new folder: a run that fails still shows its overrides (collect: "failed")
    try:
        metrics = train(cfg)
    except SIGTERMException as stop:  # Lightning stopped after the step under way (a SystemExit of status 0)
        checkpoints = (cfg.get("callbacks") or {}).get("checkpoint") or {}
        folder = Path(checkpoints.get("dirpath") or "/nonexistent")
        saved = getattr(stop, "checkpoint", None)  # the file StepCheckpoint wrote (last-v1.ckpt beside another's)
        if saved and Path(saved).is_file():
            where = f"resume with ckpt_path={saved}"
        elif (folder / "last.ckpt").is_file():
            where = f"resume with ckpt_path={folder / 'last.ckpt'}"
        else:
            where = f"the checkpoints are in {folder}" if folder.is_dir() else "no checkpoint was saved"
        logging.getLogger(__name__).warning(f"stopped by SIGTERM: {where}")
        # 128 + SIGTERM, as a shell reports a process the signal ended; rank 0 only: Lightning's launcher kills
        # every process, rank 0 included, when one of the others exits non-zero
        sys.exit(143 if getattr(rank_zero_only, "rank", 0) == 0 else 0)
    except Exception as error:
        message = input_error_message(error)
        if os.environ.get("HYDRA_FULL_ERROR") == "1" or message is None:
            raise
        report_input_error(error, message)
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            raise  # Hydra records the job as failed and runs the sweep's other jobs
        sys.exit(2)
    return metrics.get("val/iou_full")  # the value a Hydra sweeper would optimise


def refuse_file_output_dir(argv: list[str]) -> str | None:
    """The message for a `hydra.run.dir=` or `hydra.sweep.dir=` override that names a file, or a folder below one,
    else None: Hydra's own mkdir failed on it with a FileExistsError traceback naming no key, before `main`."""
    for arg in argv:
        key, sep, value = arg.partition("=")
        path = Path(value.strip("'\""))
        if sep and key.lstrip("+~") in ("hydra.run.dir", "hydra.sweep.dir") and value:
            if file := next((p for p in (path, *path.parents) if p.is_file()), None):
                where = "is a file" if file == path else f"is below the file {str(file)!r}"
                return f"{key.lstrip('+~')} = {value!r} {where}: give a folder for the run's outputs"
    return None


if __name__ == "__main__":
    if refused := refuse_file_output_dir(sys.argv[1:]):
        sys.stderr.write(f"train.py: {refused}\n")
        sys.exit(2)  # as train.py's other input errors
    main()
