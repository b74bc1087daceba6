"""The training run's own callbacks: the peft adapter's export, checkpoints at the step that ends a run (or that a
SIGTERM stops it after), checkpoint files written whole, and a progress bar without Lightning 2.6's epoch total.

conf/callbacks/*.yaml instantiates `StepCheckpoint` and `AdapterExport` (`aynamics.callbacks` re-exports both, the
names older configs give); train.py adds the progress bar and the checkpoint writer:

    callbacks += progress_bar(callbacks, enabled=True)
    trainer = L.Trainer(callbacks=callbacks, ...); use_atomic_checkpoints(trainer)
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint, RichProgressBar
from lightning.pytorch.callbacks.progress.rich_progress import _RICH_AVAILABLE
from lightning.pytorch.plugins.io import TorchCheckpointIO
from lightning.pytorch.utilities.exceptions import SIGTERMException

from aynamics import adapters, lm, sharding

log = logging.getLogger(__name__)


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
    partial `last.ckpt` in place of the previous good one. Once a file is in place, the `.NAME.tmp-PID` files beside
    it whose process is gone (a kill mid-write left them: a whole checkpoint's size each) are deleted."""

    def save_checkpoint(self, checkpoint: dict, path, storage_options=None) -> None:
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
        for leftover in path.parent.glob(f".{path.name}.tmp-*"):
            pid = leftover.name.rpartition("-")[2]
            if pid.isdigit() and not _alive(int(pid)) and leftover.is_file() and not leftover.is_symlink():
                leftover.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    """Whether a process of this id runs on this machine."""
    try:
        os.kill(pid, 0)
    except PermissionError:  # another user's
        return True
    except (ProcessLookupError, OverflowError):  # none, or past what a process id can be
        return False
    return True


class StepsProgressBar(RichProgressBar):
    """Lightning's rich progress bar without the epoch total it shows when epochs are unlimited: a run limited by
    `trainer.max_steps` has `max_epochs = -1`, which Lightning 2.6 prints as "Epoch 3/-2" (Lightning issue 21925,
    fixed in its later releases)."""

    @property
    def total_train_batches(self) -> int | float:
        """The epoch's batches the run trains: Lightning's counts the optimizer steps left as batches (4 batches
        of accumulation 2 shown "4/2") and, on a resume that starts the bar after its first batch, leaves out the
        batches of the epoch already run ("2/1"). Here: those run (this one included) + the steps left × the
        accumulation, at most the epoch's."""
        t = self.trainer
        if t.max_epochs != -1 or t.max_steps is None or t.max_steps <= 0:
            return t.num_training_batches
        run = t.fit_loop.epoch_loop.batch_progress.current.processed  # 0 at the epoch's start
        left = (t.max_steps - t.global_step) * t.accumulate_grad_batches
        return min(t.num_training_batches, run + left)

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


def ends_training(trainer: L.Trainer) -> bool:
    """Whether the fit ends after the current batch (or the validation now running is its last): max_steps
    reached, or the last batch of the last epoch (max_epochs)."""
    if trainer.max_steps is not None and trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps:
        return True
    max_epochs = trainer.max_epochs
    if max_epochs is None or max_epochs < 0 or trainer.current_epoch + 1 < max_epochs:
        return False
    return bool(trainer.fit_loop.epoch_loop.batch_progress.is_last_batch)


def _plain(value):
    return sorted(value) if isinstance(value, set | frozenset) else str(value)
