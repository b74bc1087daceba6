"""Every config group composes, and the objects it describes instantiate (those this CPU machine can hold)."""

from __future__ import annotations

from pathlib import Path

import hydra
import pytest
import torch
from hydra import compose, initialize_config_dir

from aynamics.lm import ModelSpec

CONF = Path(__file__).resolve().parents[1] / "conf"
GROUPS = {
    "model": ["tiny", "qwen2_5_vl_3b", "qwen2_5_vl_7b"],
    "trainer": ["cpu", "gpu", "ddp", "fsdp", "deepspeed"],
    "logger": ["default", "csv", "tensorboard", "none"],
    "stage": ["sft", "pro"],
    "data": ["default", "unlabeled"],
    "callbacks": ["default", "pro"],
    "debug": ["fast_dev_run"],
    "experiment": ["make_train"],
}


def _compose(tmp_path, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=[f"output_dir={tmp_path}", *overrides])


def test_every_group_file_is_listed():
    """A new config file must be added to GROUPS (so it is composed here)."""
    for group, names in GROUPS.items():
        on_disk = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
        assert on_disk == sorted(names), group


@pytest.mark.parametrize("group,name", [(g, n) for g, names in GROUPS.items() for n in names])
def test_group_composes(tmp_path, group, name):
    cfg = _compose(tmp_path, f"{group}={name}")
    assert cfg.stage.target in ("answer", "think_answer")
    assert cfg.trainer._target_ == "lightning.pytorch.Trainer"
    if group == "model":
        spec = hydra.utils.instantiate(cfg.model)
        assert isinstance(spec, ModelSpec)
        assert spec.kind == ("tiny" if name == "tiny" else "pretrained")
        assert isinstance(spec.lora_targets, tuple) and spec.lora_rank > 0
        if name != "tiny":
            assert spec.path.startswith("Qwen/Qwen2.5-VL-") and spec.dtype == "bfloat16"
    if group == "logger":
        loggers = [hydra.utils.instantiate(c) for c in cfg.logger.values()]
        assert len(loggers) == {"default": 2, "csv": 1, "tensorboard": 1, "none": 0}[name]
    if group == "trainer":
        if name in ("cpu", "ddp", "fsdp"):  # FSDP2 (aynamics.sharding) runs on the CPU too
            trainer = hydra.utils.instantiate(
                cfg.trainer, accelerator="cpu", devices=2 if name != "cpu" else 1, logger=False
            )
            assert trainer.world_size == (1 if name == "cpu" else 2)
            if name != "cpu":  # multi-process configs are for GPUs: every visible one, bf16-mixed
                assert cfg.trainer.devices == -1 and cfg.trainer.precision == "bf16-mixed"
            if name == "fsdp":
                from aynamics.sharding import FullyShardedDataParallel

                assert isinstance(trainer.strategy, FullyShardedDataParallel)
        elif torch.cuda.is_available():
            hydra.utils.instantiate(cfg.trainer, logger=False)
        else:
            assert cfg.trainer.accelerator == "gpu"  # composes; instantiating needs CUDA (and deepspeed)
    if group == "debug":
        assert cfg.trainer.fast_dev_run is True


def test_data_stage_and_callbacks_instantiate(tmp_path):
    cfg = _compose(tmp_path, "stage.target=think_answer", "data.modality=flow", "data.as_video=true")
    spec = hydra.utils.instantiate(cfg.model)
    dm = hydra.utils.instantiate(cfg.data, processor_path=spec.processor_path, target=cfg.stage.target)
    assert dm.prompt.target == "think_answer" and dm.prompt.modality == "flow" and dm.prompt.as_video
    factory = hydra.utils.instantiate(cfg.stage.module)
    assert factory.func.__name__ == "SFTModule"
    callbacks = [hydra.utils.instantiate(c) for c in cfg.callbacks.values()]
    assert {type(c).__name__ for c in callbacks} == {"StepCheckpoint", "AdapterExport", "SceneEvaluation"}


def test_experiment_overrides_compose(tmp_path):
    cfg = _compose(tmp_path, "experiment=make_train")
    makefile = (Path(__file__).resolve().parents[1] / "Makefile").read_text()
    assert f"TRAIN_DATA ?= {cfg.data.dir}\n" in makefile  # the folder `make train` generates is the one it reads
    assert cfg.model.tiny.hidden_size == 128
    assert cfg.data.visual_targets and cfg.stage.module.vision_aux_weight > 0  # the dense loss needs its targets
    cfg = _compose(tmp_path, "experiment=make_train", "trainer.max_steps=7")
    assert cfg.trainer.max_steps == 7
    # debug comes last: a smoke test of an experiment stays a smoke test (the experiment's 32 scenes and 760
    # tokens won: helper-43); the tiny base's seed is the run's (seed=0,1,2 sweeps had one random base)
    cfg = _compose(tmp_path, "debug=fast_dev_run", "experiment=make_train", "seed=3")
    assert (cfg.callbacks.evaluation.num_samples, cfg.callbacks.evaluation.max_new_tokens) == (2, 16)
    assert cfg.trainer.fast_dev_run and cfg.model.seed == 3


def test_a_missing_optional_package_is_an_input_error():
    """flash-attn not installed (ImportError while the model loads) and a strategy Lightning cannot set up here
    (MisconfigurationException, e.g. deepspeed not installed) end the run with status 2 and their message; they
    kept a traceback and status 1 (helper-43)."""
    from hydra.errors import InstantiationException
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    from train import input_error_message

    assert input_error_message(ImportError("FlashAttention2 needs flash_attn")) == "FlashAttention2 needs flash_attn"
    wrapped = InstantiationException("Error in call to target 'Trainer':\nfull_key: trainer")
    wrapped.__cause__ = MisconfigurationException("DeepSpeed is not installed")
    assert input_error_message(wrapped) == "DeepSpeed is not installed (config: trainer)"


def test_bad_values_are_named(tmp_path):
    cfg = _compose(tmp_path, "model.kind=huge")
    with pytest.raises(Exception, match="model.kind = 'huge'"):
        hydra.utils.instantiate(cfg.model)


def test_run_and_sweep_folders_hold_microseconds():
    """Two `python train.py` runs (or sweeps) started in the same second must get two folders: with Hydra's default
    `outputs/DATE/HH-MM-SS` two single runs shared one and overwrote each other's adapter, metrics.json and
    .hydra/ (their checkpoints became last.ckpt / last-v1.ckpt of either run)."""
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", return_hydra_config=True)
    for key in ("run", "sweep"):
        pattern = OmegaConf.to_container(cfg.hydra[key], resolve=False)["dir"]
        assert pattern.endswith("${now:%H-%M-%S-%f}"), (key, pattern)
