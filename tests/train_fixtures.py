"""A tiny generated data set shared by the training tests (one copy per test session, also under xdist), their
config composition, their 2-process runs (`run_two_processes`), and callbacks that send SIGTERM or make a step NaN.

Made by the real generator (`aynamics.generate`) at 64×48 pixels: 12 scenes, split 5 / 4 / 3.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from pathlib import Path

import lightning as L
import torch
from filelock import FileLock

NUM_SCENES = 12
ROOT = Path(__file__).resolve().parents[1]
FAST = ["data.num_frames=2", "data.batch_size=2", "data.limit_val=2", "logger=none"]  # small, quick training runs


def train_cfg(out: Path, *overrides: str):
    """`conf/config.yaml` composed as `train.py` would be, writing to `out`, with FAST and `overrides`."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=[f"output_dir={out}", *FAST, *overrides])


def tiny_dataset(tmp_path_factory) -> Path:
    """Path of the shared tiny data set, generated on first use (a file lock serialises xdist workers)."""
    from aynamics.generate import GenerateConfig, generate_dataset
    from aynamics.simulate import PHYSICS_VERSION

    root = tmp_path_factory.getbasetemp().parent  # shared by every xdist worker, and kept between sessions:
    path = root / f"aynamics_tiny_dataset_p{PHYSICS_VERSION}"  # so one made by other physics is not reused
    with FileLock(str(root / "aynamics_tiny_dataset.lock")):
        if not (path / "dataset_dict.json").is_file():
            config = GenerateConfig(width=64, height=48, workers=0, splits=(0.5, 0.25, 0.25))
            generate_dataset(path, num=NUM_SCENES, seed=0, config=config)
    return path


def run_two_processes(cmd: list[str], out: Path, **kwargs) -> subprocess.CompletedProcess:
    """`subprocess.run(cmd, **kwargs)` of a 2-process `train.py` run writing to `out`, run once more (from an empty
    `out`) when its process group lost the port Lightning chose for it: Lightning binds a free port, frees it and
    gives it to the group's store, and another run (an xdist worker's) can take it in between (EADDRINUSE)."""
    done = subprocess.run(cmd, **kwargs)
    if done.returncode != 0 and "EADDRINUSE" in (done.stderr or ""):
        shutil.rmtree(out, ignore_errors=True)
        done = subprocess.run(cmd, **kwargs)
    return done


class SigtermAt(L.Callback):
    """Sends SIGTERM to the processes of these ranks (all by default, as a cluster's preemption does) at the start
    of training step `step` (1-based): `+callbacks.sigterm._target_=train_fixtures.SigtermAt
    +callbacks.sigterm.step=N [+callbacks.sigterm.ranks=[0]]`, with tests/ on the path."""

    def __init__(self, step: int, ranks: list[int] | None = None) -> None:
        self.step, self.ranks = step, ranks

    def on_train_batch_start(self, trainer: L.Trainer, *args) -> None:
        if trainer.global_step == self.step - 1 and (self.ranks is None or trainer.global_rank in self.ranks):
            os.kill(os.getpid(), signal.SIGTERM)


class NanGradientAt(L.Callback):
    """Makes the gradient of the first trainable parameter NaN in training step `step` (1-based), as a diverged
    step would: `+callbacks.nan._target_=train_fixtures.NanGradientAt +callbacks.nan.step=N`."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_after_backward(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.global_step == self.step - 1:
            grad = next(p for p in pl_module.parameters() if p.grad is not None).grad
            grad.view(-1)[0] = float("nan")


class NanWeightAt(L.Callback):
    """Makes the first trainable weight NaN at the start of training step `step` on the processes of these ranks,
    so that their loss and gradients are NaN, as a diverging step is: under ddp the gradient all-reduce then
    carries the NaN to every process. `+callbacks.nan._target_=train_fixtures.NanWeightAt +callbacks.nan.step=N
    +callbacks.nan.ranks=[1]`."""

    def __init__(self, step: int, ranks: list[int]) -> None:
        self.step, self.ranks = step, ranks

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, *args) -> None:
        if trainer.global_step == self.step - 1 and trainer.global_rank in self.ranks:
            weight = next(p for p in pl_module.parameters() if p.requires_grad)
            with torch.no_grad():
                weight.view(-1)[0] = float("nan")


class RecordInit(L.Callback):
    """Writes `DIR/init_rank<R>.json` for each process: the devices of its module's parameters before
    `configure_model` (at Lightning's `setup` hook): `+callbacks.init._target_=train_fixtures.RecordInit
    +callbacks.init.dirpath=DIR`."""

    def __init__(self, dirpath: str) -> None:
        self.dirpath = Path(dirpath)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self.dirpath.mkdir(parents=True, exist_ok=True)
        devices = sorted({p.device.type for p in pl_module.parameters()})
        (self.dirpath / f"init_rank{trainer.global_rank}.json").write_text(json.dumps({"devices": devices}))
