"""Training end to end: fast_dev_run for both targets and modalities, the exact CLI, parameter updates,
adapter save/reload, exact resume, and DDP on the CPU (slow)."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from train_fixtures import FAST, ROOT, run_two_processes, tiny_dataset, train_cfg

from aynamics import adapters, lm
from aynamics.batching import model_inputs
from aynamics.data import SceneDataModule
from aynamics.sft import SFTModule

sys.path.insert(0, str(ROOT))
from train import train  # noqa: E402

_cfg = train_cfg


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return tiny_dataset(tmp_path_factory)


@pytest.mark.parametrize(
    "target,modality,as_video",
    [
        ("answer", "rgb", False),
        ("think_answer", "flow", True),
        pytest.param("think_answer", "rgb", False, marks=pytest.mark.slow),
        pytest.param("answer", "flow", True, marks=pytest.mark.slow),
    ],
)
def test_fast_dev_run(tmp_path, dataset_dir, target, modality, as_video, capsys):
    """One batch of training and validation, then the scene evaluation on 2 records (16 tokens: invalid), its
    table printed with the command that scores the test split."""
    cfg = _cfg(
        tmp_path,
        "debug=fast_dev_run",
        f"data.dir={dataset_dir}",
        f"stage.target={target}",
        f"data.modality={modality}",
        f"data.as_video={as_video}",
    )
    metrics = train(cfg)
    printed = capsys.readouterr().out
    assert "Validation (2 held-out scenes, step 1):" in printed and "average scene" in printed
    assert "Why 2 of 2 responses do not simulate: no YAML 2\n" in printed  # 16 tokens cannot hold a scene
    evaluate = f"aynamics evaluate --adapter {tmp_path / 'adapter'} --data {dataset_dir} --batch-size 8"
    assert f"The test split's table: {evaluate} --max-new-tokens 16\n" in printed  # the evaluation's settings
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))
    assert metrics["val/yaml_valid"] == 0.0 and metrics["val/iou_full"] == 0.0  # 16 tokens cannot hold a scene
    assert metrics["val/baseline/yaml_valid"] == 1.0  # the average scene is a valid scene
    assert (tmp_path / "adapter" / "adapter_model.safetensors").is_file()
    rows = [json.loads(x) for x in (tmp_path / "eval" / "predictions_step000001.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and all(r["reason"] for r in rows)
    _predict_gives_the_evaluation_response(cfg, tmp_path / "adapter", rows[0])
    if (target, modality) == ("answer", "rgb"):
        _evaluate_gives_the_training_evaluation(tmp_path, dataset_dir, metrics, rows)
    if (target, modality) in (("answer", "rgb"), ("think_answer", "flow")):
        _evaluate_scores_videos_without_labels(tmp_path, dataset_dir, modality)


def _evaluate_scores_videos_without_labels(run: Path, dataset_dir: Path, modality: str) -> None:
    """`aynamics evaluate --videos` on 2 folders written by `aynamics render` (frames/ and flow/ images,
    segmentation.npy): one row per video, named by its folder, no target, and the metrics that need no label; a
    third folder missing one of the images the adapter reads (frames, or flow images) and a fourth whose images the
    processor refuses (600x2 pixels) are named and left out."""
    import datasets
    from PIL import Image

    from aynamics.cli import main
    from aynamics.render import gl_available

    if not gl_available()[0]:
        return  # render needs headless OpenGL (the CI image has it)
    videos = run / "videos"
    for k, record in enumerate(datasets.load_from_disk(str(dataset_dir))["validation"].select(range(2))):
        (run / f"scene{k}.yaml").write_text(record["scene_yaml"])
        args = ["render", str(run / f"scene{k}.yaml"), "--out", str(videos / f"v{k}"), "--width", "64"]
        with contextlib.redirect_stdout(io.StringIO()):
            assert main([*args, "--height", "48", "--no-gif"]) == 0
    shutil.copytree(videos / "v1", videos / "v2")
    images = "frames" if modality == "rgb" else "flow"
    sorted((videos / "v2" / images).iterdir())[5].unlink()  # one image missing: left out, named, the rest scored
    shutil.copytree(videos / "v1", videos / "v3")  # 600x2 frames and masks: read, then refused by the processor
    np.save(videos / "v3" / "segmentation.npy", np.zeros((30, 2, 600), np.int16))
    (videos / "v3" / "flow.npy").unlink()
    for f in (videos / "v3" / images).iterdir():
        Image.new("RGB", (600, 2)).save(f)
    stdout, stderr = io.StringIO(), io.StringIO()
    args = ["evaluate", "--adapter", str(run / "adapter"), "--videos", str(videos), "--max-new-tokens", "16"]
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        assert main([*args, "--out", str(run / "video_eval"), "--json", "--quiet", "--device", "cpu"]) == 0
    assert f"evaluate: video folder {str(videos / 'v2')!r} is left out: " in stderr.getvalue()
    every = 30 if modality == "rgb" else 29  # the segmentation's frames, or the flow images between them
    assert f"{every - 1} images; need one for every video frame ({every}: the segmentation has 30" in stderr.getvalue()
    assert f"evaluate: video folder {str(videos / 'v3')!r} is left out: absolute aspect ratio" in stderr.getvalue()
    assert json.loads(stdout.getvalue())["left_out"] == 2
    table = json.loads(stdout.getvalue())["table"]
    assert set(table) == {"model"}  # no average scene without training scenes
    assert set(table["model"]) == {"yaml_valid", "sim_valid", "iou_first", "iou_full", "epe_first", "epe_full"}
    rows = [json.loads(x) for x in (run / "video_eval" / "predictions.jsonl").read_text().splitlines()]
    assert [(r["index"], r["target"]) for r in rows] == [("v0", None), ("v1", None)]


def _evaluate_gives_the_training_evaluation(run: Path, dataset_dir: Path, metrics: dict, rows: list[dict]) -> None:
    """`aynamics evaluate` of the run's adapter on the first 2 validation scenes, at the evaluation's batch size and
    token limit: the same responses, the same per-scene rows and the same table (model and average scene) as the
    evaluation during training; the files it writes hold them. With `--refine`, the responses (no scene in 16
    tokens) stay as they are and the average scene refined gains IoU."""
    from aynamics.callbacks import METRIC_KEYS
    from aynamics.cli import main

    out = run / "evaluated"
    args = ["evaluate", "--adapter", str(run / "adapter"), "--data", str(dataset_dir), "--split", "validation"]
    args += ["--num", "2", "--batch-size", "8", "--max-new-tokens", "16", "--out", str(out), "--json", "--quiet"]
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert main([*args, "--device", "cpu", "--refine", "30"]) == 0
    table = json.loads(stdout.getvalue())["table"]
    for key in METRIC_KEYS:
        assert table["model"][key] == pytest.approx(metrics[f"val/{key}"]), key
        assert table["average scene"][key] == pytest.approx(metrics[f"val/baseline/{key}"]), key
        assert table["model + refine"][key] == table["model"][key]  # 16 tokens hold no scene: nothing to refine
    assert table["average scene + refine"]["iou_full"] > table["average scene"]["iou_full"]
    predicted = [json.loads(x) for x in (out / "predictions.jsonl").read_text().splitlines()]
    assert [{k: v for k, v in p.items() if not k.startswith("refined")} for p in predicted] == rows
    assert [p["refined"] for p in predicted] == [r["prediction"] for r in rows]
    written = json.loads((out / "metrics.json").read_text())
    assert written["table"] == table and written["scenes"] == 2 and written["settings"]["split"] == "validation"
    assert written["left_out"] == 0 and written["refine_timed_out"] == 0
    assert written["invalid_reasons"] == {"no YAML": 2}  # as the training evaluation's line says
    _evaluate_names_the_records_it_leaves_out(run, dataset_dir)


def _evaluate_names_the_records_it_leaves_out(run: Path, dataset_dir: Path) -> None:
    """Records whose scene cannot be scored are named on stderr as they are found, even when that leaves nothing
    to score (exit 2 with one line saying so)."""
    import datasets

    from aynamics.cli import main

    broken = datasets.load_from_disk(str(dataset_dir))
    broken["validation"] = broken["validation"].map(lambda r: {"scene_yaml": "- type: box\n  size: -1\n"})
    broken.save_to_disk(str(run / "broken"))
    args = ["evaluate", "--adapter", str(run / "adapter"), "--data", str(run / "broken"), "--split", "validation"]
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        assert main([*args, "--num", "2", "--max-new-tokens", "4", "--device", "cpu", "--quiet"]) == 2
    lines = stderr.getvalue().splitlines()
    named = [x for x in lines if x.startswith("evaluate: record ") and "is left out: its scene_yaml cannot" in x]
    assert len(named) == 2, lines
    assert lines[-1] == (
        f"evaluate: no scene of the validation records of --data {str(run / 'broken')!r} can be scored (each one was "
        "named above)"
    )


def _predict_gives_the_evaluation_response(cfg, adapter: Path, row: dict) -> None:
    """`aynamics predict --adapter` on the stored frames of the first evaluated record, written out as PNG files:
    the prompt it rebuilds from the adapter folder and the files (frame choice, pixels, text, images or video)
    equals, tensor for tensor, the one the run's data module gave the evaluation, and it prints the evaluation's
    greedy response. The same frames as an MP4 (lossy) are read and answered too."""
    import hydra
    import imageio.v3 as iio

    from aynamics.cli import main
    from aynamics.eval_records import frames_of
    from aynamics.predict import clip_of

    spec = hydra.utils.instantiate(cfg.model)
    dm = hydra.utils.instantiate(cfg.data, processor_path=spec.processor_path, target=cfg.stage.target)
    dm.setup("fit")
    expected = dm.eval_records("validation", 1)[0]
    assert expected["index"] == row["index"]
    record = dm.splits["validation"][0]
    frames = [np.asarray(im.convert("RGB")) for im in frames_of(record, cfg.data.modality)]
    folder = adapter.parent / "frames"
    folder.mkdir()
    for k, f in enumerate(frames):
        iio.imwrite(folder / f"{k:03d}.png", f)
    iio.imwrite(adapter.parent / "video.mp4", np.stack(frames), plugin="pyav", codec="libx264", fps=10)
    saved_spec, prompt = adapters.read_adapter_meta(adapter)
    assert prompt.clip_frames == tuple(record["frame_indices"]) and prompt.fps == 30  # the data's clock
    ours = lm.prompt_inputs(lm.load_processor(saved_spec, prompt), prompt, clip_of(folder, prompt))
    assert sorted(ours) == sorted(expected["prompt"])
    for key, value in expected["prompt"].items():
        assert torch.equal(ours[key], value), key
    for source, same in ((folder, True), (adapter.parent / "video.mp4", False)):
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            args = ["predict", "--adapter", str(adapter), str(source), "--max-new-tokens", "16", "--json"]
            code = main([*args, "--device", "cpu"])  # where training generated: the same greedy tokens
        result = json.loads(out.getvalue())
        assert code == (0 if result["valid"] else 1) and isinstance(result["response"], str)
        if same:
            assert result["response"] == row["prediction"]


def test_pretrained_config_runs_from_a_model_folder(tmp_path, dataset_dir):
    """`model=qwen2_5_vl_3b model.path=DIR`, the real-model path end to end, with DIR a Qwen2.5-VL written by
    `save_pretrained` (the tiny architecture, seed 3) beside the processor files: `from_pretrained` for the model
    and the processor, the 3B config's LoRA (r 16, tower frozen), one training and validation batch, and an
    adapter folder naming DIR from which `predict` rebuilds those base weights, not a fresh tiny model."""
    import shutil

    from aynamics.model import build_tiny_model
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    folder = tmp_path / "qwen"
    saved = build_tiny_model(seed=3)
    saved.save_pretrained(folder)
    shutil.copytree(TINY_ASSET_DIR, folder, dirs_exist_ok=True)  # tokenizer, chat template, image processor
    cfg = _cfg(
        tmp_path / "run",
        "debug=fast_dev_run",
        f"data.dir={dataset_dir}",
        "model=qwen2_5_vl_3b",
        f"model.path={folder}",
        "model.dtype=float32",
        "model.gradient_checkpointing=false",
    )
    metrics = train(cfg)
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))
    spec, _ = adapters.read_adapter_meta(tmp_path / "run" / "adapter")
    assert (spec.kind, spec.path, spec.lora_rank, spec.train_vision) == ("pretrained", str(folder), 16, False)
    model, _, _ = adapters.load_adapter(tmp_path / "run" / "adapter")
    name = "lm_head.weight"
    ours = dict(model.base_model.model.named_parameters())[name]
    assert torch.equal(ours, dict(saved.named_parameters())[name])
    assert not torch.equal(ours, dict(build_tiny_model(seed=0).named_parameters())[name])


@pytest.mark.slow
def test_the_3b_architecture_trains_and_predicts_at_its_real_widths(tmp_path):
    """`model=qwen2_5_vl_3b` on a checkpoint of the published 3B architecture with random weights
    (`model.random_checkpoint`: every width, head count, the 151936-token vocabulary and tied embeddings; 1 of its 36
    layers and 8 of its 32 vision blocks, block 7 with full attention and windows elsewhere), on 480x320 frames as
    generated by default: 187 visual tokens a frame, one bfloat16 training step with float32 LoRA (r 16 on the
    3B's 2048-wide projections), a validation, the adapter, `predict` from it, and a PRO step from it."""
    from aynamics.data import SceneDataModule
    from aynamics.generate import GenerateConfig, generate_dataset
    from aynamics.model import random_checkpoint
    from aynamics.predict import predict

    folder = random_checkpoint(tmp_path / "qwen", "3b", text_layers=1, vision_depth=8)
    data = tmp_path / "data"
    generate_dataset(data, num=6, seed=0, config=GenerateConfig(workers=0, splits=(0.5, 0.25, 0.25)))
    dm = SceneDataModule(str(data), str(folder), num_frames=2, batch_size=1)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    image_token = dm.processor.tokenizer.convert_tokens_to_ids("<|image_pad|>")
    assert int((batch["input_ids"] == image_token).sum()) == 2 * 187  # (476 / 28) x (308 / 28) a frame
    out = tmp_path / "run"
    metrics = train(
        _cfg(
            out,
            f"data.dir={data}",
            "data.batch_size=1",
            "model=qwen2_5_vl_3b",
            f"model.path={folder}",
            "trainer.max_steps=1",
            "trainer.val_check_interval=1",
            "callbacks.evaluation.num_samples=1",
            "callbacks.evaluation.max_new_tokens=4",
            "callbacks.evaluation.num_animations=0",
        )
    )
    assert math.isfinite(metrics["train/loss"]) and math.isfinite(metrics["val/loss"])
    assert metrics["val/yaml_valid"] == 0.0  # random weights write no scene, and that is scored, not raised
    from safetensors.torch import load_file

    adapter = load_file(out / "adapter" / "adapter_model.safetensors")
    a = next(v for k, v in adapter.items() if k.endswith("layers.0.self_attn.q_proj.lora_A.weight"))
    assert a.dtype == torch.float32 and a.shape == (16, 2048)
    frames = [np.full((320, 480, 3), 100 * k, np.uint8) for k in range(2)]  # the 2 frames it was trained on
    result = predict(out / "adapter", frames, max_new_tokens=4, device="cpu")
    assert isinstance(result["response"], str) and result["valid"] is False
    pro = [f"data.dir={data}", "data.batch_size=1", f"stage.init_adapter={out / 'adapter'}", "stage.num_samples=2"]
    pro += ["stage.module.max_new_tokens=4", "trainer.max_steps=1", "model=qwen2_5_vl_3b", f"model.path={folder}"]
    metrics = train(_cfg(tmp_path / "pro", "stage=pro", *pro))  # sampled at the 3B's widths, simulated, scored
    assert metrics["reward/invalid"] == 1.0 and (tmp_path / "pro" / "adapter" / "adapter_model.safetensors").is_file()


def test_cli_command_as_written(tmp_path, dataset_dir):
    """`python train.py stage=sft model=tiny data.dir=DIR trainer.max_steps=N hydra.run.dir=OUT` leaves the
    adapter and the CSV metrics under OUT (N = 2 here; the issue's 20 runs the same code path)."""
    out = tmp_path / "run"
    cmd = [sys.executable, "train.py", "stage=sft", "model=tiny", f"data.dir={dataset_dir}", "trainer.max_steps=2"]
    cmd += [f"hydra.run.dir={out}", "trainer.val_check_interval=2", "data.num_frames=2", "data.batch_size=2"]
    cmd += ["callbacks.evaluation.num_samples=2", "callbacks.evaluation.max_new_tokens=8"]
    cmd += ["callbacks.evaluation.num_animations=0", "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (out / "adapter" / "adapter_config.json").is_file()
    assert (out / "checkpoints" / "last.ckpt").is_file()
    with open(out / "csv" / "metrics.csv") as f:
        header = next(csv.reader(f))
    assert {
        "train/loss",
        "val/loss",
        "val/image_gap",
        "val/yaml_valid",
        "val/iou_full",
        "val/baseline/iou_full",
        "train/grad_norm",
    } <= set(header)
    assert json.loads((out / "metrics.json").read_text())["global_step"] == 2
    with open(out / "csv" / "metrics.csv") as f:
        norms = [float(row["train/grad_norm"]) for row in csv.DictReader(f) if row.get("train/grad_norm")]
    assert len(norms) == 2 and max(norms) > 1.0  # logged before clipping (trainer.gradient_clip_val = 1)
    assert "yaml_valid" in done.stdout  # the validation table
    console = done.stdout + done.stderr  # each log line once (was Lightning's handler and Hydra's), in the log file
    assert console.count("Seed set to 0") == 1 and "INFO: " not in console and "Tip:" not in console
    assert "LeafSpec" not in console and "Seed set to 0" in (out / "train.log").read_text()


def _module_and_batch(dataset_dir, **spec_kw):
    spec = lm.ModelSpec(kind="tiny", lora_dropout=0.0, **spec_kw)
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=2)
    dm.setup("fit")
    return SFTModule(spec, lr=1e-2), next(iter(dm.train_dataloader())), dm


def test_one_step_changes_trainable_only(dataset_dir):
    module, batch, _ = _module_and_batch(dataset_dir, train_vision=False)
    before = {k: p.detach().clone() for k, p in module.model.named_parameters()}
    trainable = {k for k, p in module.model.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in k for k in trainable)
    opt = torch.optim.AdamW([p for p in module.model.parameters() if p.requires_grad], lr=1e-2)
    loss, _, _ = module._loss(batch)
    loss.backward()
    opt.step()
    for k, p in module.model.named_parameters():
        changed = not torch.equal(before[k], p.detach())
        if k in trainable and "lora_A" in k:  # lora_B starts at 0 and moves too, but A is the clearer check
            assert changed, k
        if k not in trainable:
            assert not changed, k
    assert any(not torch.equal(before[k], p) for k, p in module.model.named_parameters() if "lora_B" in k)


def test_adapter_save_and_reload_give_identical_outputs(tmp_path, dataset_dir):
    module, batch, dm = _module_and_batch(dataset_dir, train_vision=True, modules_to_save=("embed_tokens", "lm_head"))
    with torch.no_grad():
        for k, p in module.model.named_parameters():  # move the adapter off its initial value
            if p.requires_grad:
                p.add_(0.01 * torch.randn_like(p))
    module.model.eval()
    with torch.no_grad():
        expected = module.model(**model_inputs(batch)).logits
    adapters.save_adapter(module.model, tmp_path / "adapter", module.spec, dm.prompt)
    reloaded, spec, prompt = adapters.load_adapter(tmp_path / "adapter")
    with torch.no_grad():
        got = reloaded(**model_inputs(batch)).logits
    assert spec == module.spec and prompt == dm.prompt
    assert torch.equal(expected, got)


@pytest.mark.parametrize("vision_aux", [False, True])
def test_resume_continues_exactly(tmp_path, dataset_dir, vision_aux):
    """7 steps straight vs 1 step + resume from the step-1 checkpoint: the same adapter weights at every step, bit
    for bit, and the same epochs.

    LoRA dropout is on (0.1), so the RNG state must be restored too; the training records at batch size 1 make 6
    batches per epoch, so the resumed run starts early in epoch 0 and crosses into epoch 1 (a resumed epoch that
    Lightning ended early, because the loader's length left out the batches already done, broke this from step 5).
    With the dense visual loss, the fresh runs warm the vision tower up first and the resumed one must not (its
    checkpoint holds the warmed-up tower and the head).
    """
    common = [
        f"data.dir={dataset_dir}",
        "data.batch_size=1",
        "callbacks.evaluation=null",
        "callbacks.checkpoint.every_n_train_steps=1",
        "trainer.val_check_interval=null",
        "trainer.check_val_every_n_epoch=100",
        "trainer.enable_progress_bar=false",
        "model.lora_dropout=0.1",
    ]
    if vision_aux:
        common += ["data.visual_targets=true", "stage.module.vision_aux_weight=0.5"]
        common += ["stage.module.vision_warmup_steps=3"]
    train(_cfg(tmp_path / "a", *common, "trainer.max_steps=7"))
    train(_cfg(tmp_path / "b", *common, "trainer.max_steps=1"))
    ckpt = tmp_path / "b" / "checkpoints" / "step000001.ckpt"
    train(_cfg(tmp_path / "c", *common, "trainer.max_steps=7", f"ckpt_path={ckpt}"))
    epochs = []
    for step in range(2, 8):
        a = torch.load(tmp_path / "a" / "checkpoints" / f"step{step:06d}.ckpt", weights_only=False)
        c = torch.load(tmp_path / "c" / "checkpoints" / f"step{step:06d}.ckpt", weights_only=False)
        assert a["global_step"] == c["global_step"] == step and a["epoch"] == c["epoch"], step
        assert a["state_dict"].keys() == c["state_dict"].keys() and len(a["state_dict"]) > 0
        for k in a["state_dict"]:
            assert torch.equal(a["state_dict"][k], c["state_dict"][k]), (step, k)
        epochs.append(a["epoch"])
    assert epochs[0] == 0 and epochs[-1] == 1  # the comparison crossed an epoch boundary
    # the checkpoint holds only trainable weights (the adapter), not the frozen base
    assert all("lora_" in k or "modules_to_save" in k or "visual" in k for k in a["state_dict"])
    assert ("visual_head.weight" in a["state_dict"]) == vision_aux
    # c resumed (a fresh run would also give a's weights): it wrote no step-1 checkpoint of its own
    assert sorted(p.name for p in (tmp_path / "c" / "checkpoints").glob("step*")) == [
        f"step{k:06d}.ckpt" for k in range(2, 8)
    ]
    # and the Lightning loop trained: LoRA B starts at zero, and steps 2-7 moved it further
    b = torch.load(ckpt, weights_only=False)
    lora_b = [k for k in a["state_dict"] if "lora_B" in k]
    assert lora_b and all(b["state_dict"][k].abs().max() > 0 for k in lora_b)
    assert all(not torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in lora_b)
    _exported_checkpoint_is_the_adapter_of_its_step(ckpt, tmp_path / "b" / "adapter", tmp_path / "exported")


def test_last_checkpoint_is_the_final_step_and_continues_exactly(tmp_path, dataset_dir):
    """A 3-step run checkpointing every 2 steps also saves step 3 (step000003.ckpt, and last.ckpt at step 3, not
    2: Lightning alone saves at the end only when nothing was saved before); resumed from that last.ckpt to step
    5 it writes steps 4 and 5 with the weights of a straight 5-step run, bit for bit, and no step-3 file."""
    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "callbacks.evaluation=null"]
    common += ["callbacks.checkpoint.every_n_train_steps=2", "trainer.val_check_interval=null"]
    common += ["trainer.check_val_every_n_epoch=100", "trainer.enable_progress_bar=false"]
    train(_cfg(tmp_path / "short", *common, "trainer.max_steps=3"))
    names = sorted(p.name for p in (tmp_path / "short" / "checkpoints").iterdir())
    assert names == ["last.ckpt", "step000002.ckpt", "step000003.ckpt"]
    last = torch.load(tmp_path / "short" / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["global_step"] == 3
    train(_cfg(tmp_path / "long", *common, "trainer.max_steps=5"))
    ckpt = tmp_path / "short" / "checkpoints" / "last.ckpt"
    train(_cfg(tmp_path / "resumed", *common, "trainer.max_steps=5", f"ckpt_path={ckpt}"))
    names = sorted(p.name for p in (tmp_path / "resumed" / "checkpoints").iterdir())
    assert names == ["last.ckpt", "step000004.ckpt", "step000005.ckpt"]
    _same_steps(tmp_path / "long", tmp_path / "resumed", (4, 5))

    # SIGTERM during step 3 of a 5-step run: step 3 is saved (off the 2-step cadence) and the run stops there;
    # resumed, it ends on the straight run's weights. Without the save, last.ckpt held step 2.
    sigterm = ["+callbacks.sigterm._target_=train_fixtures.SigtermAt", "+callbacks.sigterm.step=3"]
    with pytest.raises(SystemExit):  # Lightning's SIGTERMException
        train(_cfg(tmp_path / "stopped", *common, "trainer.max_steps=5", *sigterm))
    names = sorted(p.name for p in (tmp_path / "stopped" / "checkpoints").iterdir())
    assert names == ["last.ckpt", "step000002.ckpt", "step000003.ckpt"]
    ckpt = tmp_path / "stopped" / "checkpoints" / "last.ckpt"
    assert torch.load(ckpt, weights_only=False)["global_step"] == 3
    train(_cfg(tmp_path / "after_sigterm", *common, "trainer.max_steps=5", f"ckpt_path={ckpt}"))
    _same_steps(tmp_path / "long", tmp_path / "after_sigterm", (4, 5))
    # SIGTERM during the last step: saved, and the run ends as planned (its metrics written)
    train(_cfg(tmp_path / "last_step", *common, "trainer.max_steps=3", *sigterm))
    assert json.loads((tmp_path / "last_step" / "metrics.json").read_text())["global_step"] == 3
    _same_steps(tmp_path / "short", tmp_path / "last_step", (3,))


def test_sigterm_with_gradient_accumulation_stops_after_an_optimizer_step(tmp_path, dataset_dir):
    """Two batches per optimizer step, SIGTERM at the first batch of step 2: the run saves and stops after the
    second (step 2 done), not inside the window; resumed, step 3 ends on the weights of a straight 3-step run."""
    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "callbacks.evaluation=null"]
    common += ["trainer.accumulate_grad_batches=2", "trainer.val_check_interval=null"]
    common += ["trainer.check_val_every_n_epoch=100", "trainer.enable_progress_bar=false", "trainer.max_steps=3"]
    train(_cfg(tmp_path / "straight", *common))
    sigterm = ["+callbacks.sigterm._target_=train_fixtures.SigtermAt", "+callbacks.sigterm.step=2"]
    with pytest.raises(SystemExit):
        train(_cfg(tmp_path / "stopped", *common, *sigterm))
    last = tmp_path / "stopped" / "checkpoints" / "last.ckpt"
    stopped = torch.load(last, weights_only=False)
    assert stopped["global_step"] == 2
    assert stopped["loops"]["fit_loop"]["epoch_loop.batch_progress"]["total"]["ready"] == 4  # batches 1-4 done
    train(_cfg(tmp_path / "resumed", *common, f"ckpt_path={last}"))
    _same_steps(tmp_path / "straight", tmp_path / "resumed", (3,))


def test_a_nan_gradient_stops_the_run_before_it_reaches_the_weights(tmp_path, dataset_dir):
    """A NaN gradient in step 3 of 5 (checkpoints every step): the run stops there naming the step, and every file
    it wrote holds finite weights: step 1, step 2, last.ckpt (step 2) and the adapter. Without the check AdamW
    wrote NaN into the weights, and the next saves into last.ckpt and the adapter."""
    from safetensors.torch import load_file

    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "callbacks.evaluation=null", "trainer.max_steps=5"]
    common += ["callbacks.checkpoint.every_n_train_steps=1", "trainer.val_check_interval=null"]
    common += ["trainer.check_val_every_n_epoch=100", "trainer.enable_progress_bar=false"]
    nan = ["+callbacks.nan._target_=train_fixtures.NanGradientAt", "+callbacks.nan.step=3"]
    with pytest.raises(FloatingPointError, match=r"the gradient norm is nan at step 3: training diverged"):
        train(_cfg(tmp_path / "run", *common, *nan))
    folder = tmp_path / "run" / "checkpoints"
    assert sorted(p.name for p in folder.iterdir()) == ["last.ckpt", "step000001.ckpt", "step000002.ckpt"]
    assert torch.load(folder / "last.ckpt", weights_only=False)["global_step"] == 2
    for name in ("last.ckpt", "step000001.ckpt", "step000002.ckpt"):
        state = torch.load(folder / name, weights_only=False)["state_dict"]
        assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point()), name
    adapter = load_file(tmp_path / "run" / "adapter" / "adapter_model.safetensors")
    assert all(torch.isfinite(v).all() for v in adapter.values())


def test_gradient_check_under_loss_scaling_and_deepspeed():
    """check_gradients by hand: a gradient of norm 5 (3-4-5) is logged; a NaN one raises naming the step, but not
    under fp16 loss scaling (the scaler skips that step), where it is still logged; under DeepSpeed nothing runs."""
    from types import SimpleNamespace

    from lightning.pytorch.strategies import DeepSpeedStrategy

    from aynamics.sft import check_gradients

    weight = torch.nn.Parameter(torch.zeros(2))
    optimizer = torch.optim.SGD([weight], lr=0.1)
    logged: list = []

    def module(scaler=None, strategy=None):
        trainer = SimpleNamespace(strategy=strategy, precision_plugin=SimpleNamespace(scaler=scaler), global_step=6)
        return SimpleNamespace(trainer=trainer, log=lambda name, value, **kw: logged.append((name, float(value))))

    weight.grad = torch.tensor([3.0, 4.0])
    check_gradients(module(), optimizer)
    assert logged == [("train/grad_norm", 5.0)]
    weight.grad = torch.tensor([float("nan"), 1.0])
    with pytest.raises(FloatingPointError, match="the gradient norm is nan at step 7: training diverged"):
        check_gradients(module(), optimizer)
    check_gradients(module(scaler=object()), optimizer)
    assert len(logged) == 3 and math.isnan(logged[-1][1])
    check_gradients(module(strategy=DeepSpeedStrategy.__new__(DeepSpeedStrategy)), optimizer)
    assert len(logged) == 3


def _same_steps(a_dir: Path, b_dir: Path, steps) -> None:
    """Runs a and b wrote the same weights at these steps' checkpoints, bit for bit."""
    for step in steps:
        a = torch.load(a_dir / "checkpoints" / f"step{step:06d}.ckpt", weights_only=False)
        c = torch.load(b_dir / "checkpoints" / f"step{step:06d}.ckpt", weights_only=False)
        assert a["global_step"] == c["global_step"] == step and a["state_dict"].keys() == c["state_dict"].keys()
        assert all(torch.equal(a["state_dict"][k], c["state_dict"][k]) for k in a["state_dict"]), step


def _exported_checkpoint_is_the_adapter_of_its_step(ckpt: Path, adapter: Path, out: Path) -> None:
    """`aynamics export-adapter` of run b's checkpoint writes the folder run b exported when it ended at that
    step: the same peft tensors and specs, loadable with `PeftModel.from_pretrained`. A file that is no
    training checkpoint is named."""
    from safetensors.torch import load_file

    from aynamics.cli import main

    assert main(["export-adapter", str(ckpt), "--out", str(out)]) == 0
    ours, theirs = load_file(out / "adapter_model.safetensors"), load_file(adapter / "adapter_model.safetensors")
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
    assert adapters.read_adapter_meta(out) == adapters.read_adapter_meta(adapter)
    assert json.loads((out / "adapter_config.json").read_text()) == json.loads(
        (adapter / "adapter_config.json").read_text()
    )
    adapters.load_adapter(out)  # PeftModel.from_pretrained on the rebuilt base
    torch.save({"state_dict": {}}, out / "other.ckpt")
    assert main(["export-adapter", str(out / "other.ckpt"), "--out", str(out / "x")]) == 2
    assert main(["export-adapter", str(out / "adapter_config.json"), "--out", str(out / "x")]) == 2  # not a ckpt
    assert main(["export-adapter", str(out / "missing.ckpt"), "--out", str(out / "x")]) == 2
    assert not (out / "x").exists()


def test_learning_rate_schedule_by_hand():
    """Warm-up 4 then cosine to 0.1 over 12 steps: 0.25 at step 0, 1 at 3 and 4, 0.1 + 0.9 · ½(1 + cos ½π) = 0.55
    half-way (step 8), 0.1 at the end and after; constant stays 1 after warm-up."""
    from aynamics.sft import lr_factor

    kw = dict(warmup_steps=4, total_steps=12, schedule="cosine", min_ratio=0.1)
    got = [lr_factor(s, **kw) for s in (0, 3, 4, 8, 12, 20)]
    assert got == pytest.approx([0.25, 1.0, 1.0, 0.55, 0.1, 0.1])
    assert lr_factor(8, **(kw | {"schedule": "constant"})) == 1.0


def test_training_steps_follow_the_schedule(tmp_path, dataset_dir):
    """Six Lightning steps at lr 1e-3, warm-up 2, cosine to 0.1: the CSV's train/lr per step is the schedule
    by hand (progress (step - 2) / 4: 1, 0.868, 0.55, 0.232 after 0.5, 1), and the loss is finite."""
    cfg = _cfg(
        tmp_path,
        f"data.dir={dataset_dir}",
        "logger=csv",
        "trainer.max_steps=6",
        "trainer.log_every_n_steps=1",
        "trainer.val_check_interval=null",
        "trainer.check_val_every_n_epoch=100",
        "callbacks.evaluation=null",
        "trainer.enable_progress_bar=false",
        "stage.module.lr=1e-3",
        "stage.module.warmup_steps=2",
        "stage.module.schedule=cosine",
        "stage.module.min_lr_ratio=0.1",
    )
    train(cfg)
    with open(tmp_path / "csv" / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("train/lr")]
    c = [0.1 + 0.45 * (1 + math.cos(math.pi * p)) for p in (0.0, 0.25, 0.5, 0.75)]
    assert [int(r["step"]) for r in rows] == list(range(6))
    assert [float(r["train/lr"]) for r in rows] == pytest.approx([1e-3 * x for x in (0.5, 1.0, *c)], rel=1e-5)


def test_lora_and_pixel_overrides_reach_peft_and_the_processor(tmp_path, dataset_dir):
    """model.lora_rank/alpha/dropout from the command line are what peft builds (scaling alpha / r = 3, dropout
    p = 0.2 on every adapted layer); data.min_pixels = 12544 scales the 64×48 frames up to 112×140 pixels (8×10
    patches of 14: Qwen's smart_resize rounds each side up to 28 when it enlarges) where the defaults give 56×56
    (4×4), and data.max_pixels = 3000 down to 28×56 (2×4)."""
    import hydra

    cfg = _cfg(
        tmp_path, f"data.dir={dataset_dir}", "model.lora_rank=8", "model.lora_alpha=24", "model.lora_dropout=0.2"
    )
    model = lm.build_model(hydra.utils.instantiate(cfg.model))
    config = model.peft_config["default"]
    assert (config.r, config.lora_alpha, config.lora_dropout) == (8, 24, 0.2)
    layers = [m for m in model.modules() if hasattr(m, "lora_A") and "default" in m.lora_A]
    assert layers and all(m.scaling["default"] == 3.0 and m.lora_dropout["default"].p == 0.2 for m in layers)

    def grid(*overrides, processor_path=lm.ModelSpec().processor_path):
        c = _cfg(tmp_path, f"data.dir={dataset_dir}", *overrides)
        dm = hydra.utils.instantiate(c.data, processor_path=processor_path, target="answer")
        dm.setup("fit")
        return dm.dataset("train")[0]["image_grid_thw"][0].tolist()

    assert grid() == [1, 4, 4]
    assert grid("data.min_pixels=12544", "data.max_pixels=20000") == [1, 8, 10]
    assert grid("data.min_pixels=784", "data.max_pixels=3000") == [1, 2, 4]
    # by default (null) the limits are the model's own processor's: a checkpoint folder whose
    # preprocessor_config.json says 12544-20000 pixels (as Qwen's says 3136-12845056) gets those, not the tiny's
    import shutil

    folder = shutil.copytree(lm.ModelSpec().processor_path, tmp_path / "checkpoint")
    config = json.loads((folder / "preprocessor_config.json").read_text())
    config["size"] = {"shortest_edge": 12544, "longest_edge": 20000}
    (folder / "preprocessor_config.json").write_text(json.dumps(config))
    assert grid(processor_path=str(folder)) == [1, 8, 10]


def test_type_weights_reach_the_training_loss_only(dataset_dir):
    """Training takes the weighted mean of `data.type_weight`; validation reports the plain one."""
    dm = SceneDataModule(
        str(dataset_dir), lm.ModelSpec(kind="tiny").processor_path, num_frames=2, batch_size=2, type_weight=5.0
    )
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    module = SFTModule(lm.ModelSpec(kind="tiny"))
    with torch.no_grad():
        logits = module.model(**model_inputs(batch), use_cache=False).logits
        weighted, plain = module._loss(batch, weighted=True)[0].item(), module._loss(batch)[0].item()
    assert weighted == pytest.approx(lm.sft_loss(logits, batch["labels"], batch["loss_weights"])[0].item(), rel=1e-5)
    assert plain == pytest.approx(lm.sft_loss(logits, batch["labels"])[0].item(), rel=1e-5)
    assert abs(weighted - plain) > 1e-4


def test_training_step_trains_on_the_weighted_loss_plus_the_visual_term(dataset_dir, monkeypatch):
    """`training_step` returns (and logs as train/loss) the type-weighted mean NLL, not the plain one, and with the
    dense visual loss returns train/loss + vision_aux_weight · train/vision_aux (= train/total_loss): 0.5 · aux
    here. train/response_tokens is the batch's labelled-token count."""
    dm = SceneDataModule(
        str(dataset_dir),
        lm.ModelSpec(kind="tiny").processor_path,
        num_frames=2,
        batch_size=2,
        type_weight=5.0,
        visual_targets=True,
    )
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    module = SFTModule(lm.ModelSpec(kind="tiny", train_vision=True), vision_aux_weight=0.5)
    logged = {}
    monkeypatch.setattr(module, "log", lambda name, value, **kw: logged.__setitem__(name, float(value)))
    monkeypatch.setattr(module, "optimizers", lambda: torch.optim.SGD(module.parameters(), lr=0.1))
    with torch.no_grad():
        weighted, n, _ = module._loss(batch, weighted=True)
        plain = module._loss(batch)[0].item()
        returned = module.training_step(batch, 0).item()
    assert abs(weighted.item() - plain) > 1e-4  # the weights matter on this batch
    assert logged["train/loss"] == pytest.approx(weighted.item(), rel=1e-5)
    assert returned == pytest.approx(weighted.item() + 0.5 * logged["train/vision_aux"], rel=1e-5)
    assert logged["train/total_loss"] == pytest.approx(returned, rel=1e-5) and logged["train/vision_aux"] > 0
    assert logged["train/response_tokens"] == n.item()


def test_image_gap_is_the_loss_on_other_frames_minus_the_loss_on_its_own(dataset_dir):
    """val/image_gap: each batch's loss with every example's frames replaced by the next one's (`shifted_visuals`)
    minus its loss on its own frames, averaged over the split's response tokens (positive: the model reads its
    own frames better)."""
    import lightning as L

    spec = lm.ModelSpec(kind="tiny")
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=2, eval_batch_size=2)
    dm.setup("fit")
    module = SFTModule(spec).eval()
    gap = tokens = 0.0
    with torch.no_grad():
        for batch in dm.val_dataloader():
            shifted = lm.shifted_visuals(batch)
            assert shifted is not None
            loss, n, _ = module._loss(batch)
            gap += (module._loss(shifted)[0].item() - loss.item()) * n.item()
            tokens += n.item()
    assert abs(gap) > 1e-4 * tokens  # the sign is seen
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False)
    metrics = trainer.validate(module, datamodule=dm, verbose=False)[0]
    assert metrics["val/image_gap"] == pytest.approx(gap / tokens, rel=1e-4, abs=1e-6)


def test_validation_means_are_over_tokens_not_batches(dataset_dir):
    """val/loss is the split's total response NLL over its token count, and val/type_acc the share of right type
    tokens, whatever the batch sizes: one example per batch, answers of different lengths (a mean of batch means
    differs)."""
    import lightning as L

    spec = lm.ModelSpec(kind="tiny")
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=1, eval_batch_size=1)
    dm.setup("fit")
    module = SFTModule(spec).eval()
    nll = tokens = right = typed = 0.0
    per_batch = []
    with torch.no_grad():
        for batch in dm.val_dataloader():
            logits = module.model(**model_inputs(batch), use_cache=False).logits
            loss, n = lm.sft_loss(logits, batch["labels"])
            nll, tokens = nll + loss.item() * n.item(), tokens + n.item()
            per_batch.append(loss.item())
            k = lm.token_count(batch["labels"], batch["type_tokens"])
            right += lm.token_accuracy(logits, batch["labels"], batch["type_tokens"]).item() * k
            typed += k
    assert len(per_batch) >= 2 and abs(np.mean(per_batch) - nll / tokens) > 1e-4  # the two means differ here
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False)
    metrics = trainer.validate(module, datamodule=dm, verbose=False)[0]
    assert metrics["val/loss"] == pytest.approx(nll / tokens, rel=1e-5)
    assert metrics["val/type_acc"] == pytest.approx(right / typed, rel=1e-5)


def test_the_padding_of_a_process_share_is_not_counted(dataset_dir, monkeypatch):
    """Under several processes `eval_shard` pads each share with repeats of the first items (every process runs the
    same batches): a share of the validation items followed by item 0 again, marked as padding (`EvalShard.real`),
    gives the same val/loss, type_acc, image_gap and dense visual loss statistics, and test/loss, as the items once
    each (counted, item 0 weighed twice and the means moved)."""
    import lightning as L

    from aynamics import data as data_module

    spec = lm.ModelSpec(kind="tiny", train_vision=True)
    dm = SceneDataModule(
        str(dataset_dir), spec.processor_path, num_frames=2, batch_size=2, eval_batch_size=2, visual_targets=True
    )
    dm.setup("fit")
    module = SFTModule(spec, vision_aux_weight=0.5).eval()

    def run(shard):
        monkeypatch.setattr(data_module, "eval_shard", lambda n, trainer: shard(n))
        trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False)
        metrics = trainer.validate(module, datamodule=dm, verbose=False)[0]
        return metrics | trainer.test(module, datamodule=dm, verbose=False)[0]

    once = run(lambda n: None)
    for pad in ([0], [0, 1]):  # batches of 2: the padding shares a batch with an item, or fills one
        padded = run(lambda n, pad=pad: data_module.EvalShard([*range(n), *pad], n))
        assert set(once) == set(padded) >= {"val/loss", "val/type_acc", "val/image_gap", "test/loss", "val/vision_aux"}
        for k in once:
            assert padded[k] == pytest.approx(once[k], rel=1e-5), k
    counted = run(lambda n: [*range(n), 0])  # the padding taken for items: the means move
    assert abs(counted["val/loss"] - once["val/loss"]) > 1e-5


def test_vision_aux_is_logged_and_misconfigurations_are_named(tmp_path, dataset_dir):
    """The dense visual loss and its warm-up reach the CSV; wrong combinations fail before training, naming the keys."""
    cfg = _cfg(
        tmp_path,
        f"data.dir={dataset_dir}",
        "data.visual_targets=true",
        "data.type_weight=5",
        "stage.module.vision_aux_weight=1.0",
        "stage.module.vision_warmup_steps=2",
        "data.warmup_views=1",
        "logger=csv",
        "trainer.max_steps=2",
        "trainer.log_every_n_steps=1",
        "trainer.val_check_interval=2",
        "callbacks.evaluation=null",
        "trainer.enable_progress_bar=false",
    )
    metrics = train(cfg)
    assert {"train/vision_aux", "val/vision_aux", "val/vision_count_acc", "val/vision_frame_count_acc"} <= set(metrics)
    assert 0 <= metrics["val/type_acc"] <= 1 and 0 <= metrics["val/type_acc_other_frames"] <= 1
    with open(tmp_path / "csv" / "metrics.csv") as f:
        header = next(csv.reader(f))
    assert {"warmup/vision_loss", "train/vision_aux", "train/total_loss"} <= set(header)

    with pytest.raises(ValueError, match="model.train_vision=true"):
        SFTModule(lm.ModelSpec(kind="tiny", train_vision=False), vision_aux_weight=1.0)
    with pytest.raises(ValueError, match="vision_share_weight = -1"):
        SFTModule(lm.ModelSpec(kind="tiny"), vision_aux_weight=1.0, vision_share_weight=-1.0)
    with pytest.raises(ValueError, match="vision_warmup_steps = 5"):
        SFTModule(lm.ModelSpec(kind="tiny"), vision_warmup_steps=5)
    with pytest.raises(ValueError, match="data.visual_targets=true"):
        overrides = [f"data.dir={dataset_dir}", "stage.module.vision_aux_weight=1.0", "trainer.max_steps=1"]
        train(_cfg(tmp_path / "x", *overrides))


def test_multirun_grid_and_collect(tmp_path, dataset_dir, capsys):
    """The README's ablation grid, `python train.py -m data.modality=rgb,flow stage.target=answer,think_answer`,
    at 1 step each: four runs in one sweep folder, and `aynamics collect` gives one row per run with its
    overrides, status and final metrics, in the printed table and summary.csv."""
    from aynamics.cli import main

    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "train.py", "-m", "data.modality=rgb,flow", "stage.target=answer,think_answer"]
    cmd += [f"data.dir={dataset_dir}", "trainer.max_steps=1", "trainer.val_check_interval=1", *FAST]
    cmd += ["callbacks.evaluation.num_samples=1", "callbacks.evaluation.max_new_tokens=4"]
    cmd += ["callbacks.evaluation.num_animations=0", "callbacks.evaluation.baseline=false"]
    cmd += ["trainer.enable_progress_bar=false", f"hydra.sweep.dir={sweep}"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert main(["collect", str(sweep)]) == 0
    table = capsys.readouterr().out
    with open(sweep / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    grid = [(r["data.modality"], r["stage.target"], r["status"]) for r in rows]
    assert sorted(grid) == sorted((m, t, "done") for m in ("rgb", "flow") for t in ("answer", "think_answer"))
    assert all(r["val/yaml_valid"] == "0.0" for r in rows)  # 4 tokens hold no scene
    assert all(any(f"| {m} | {t} |" in line and "| done |" in line for line in table.splitlines()) for m, t, _ in grid)


@pytest.mark.slow
def test_ddp_two_processes_on_cpu(tmp_path, dataset_dir):
    """trainer=ddp on 2 CPU processes trains, writes the adapter, and evaluates its scenes split over the two
    processes (one prompt each, rank 0 gathers): the predictions file holds both records in order, each the
    greedy response of the written adapter to that record's prompt, generated here in one process."""
    out = tmp_path / "ddp"
    _two_processes(
        out,
        "trainer=ddp",
        f"data.dir={dataset_dir}",
        "trainer.max_steps=2",
        "trainer.val_check_interval=2",
        "callbacks.evaluation.batch_size=1",
    )
    record = json.loads((out / "metrics.json").read_text())
    assert record["global_step"] == 2 and "val/yaml_valid" in record["metrics"]
    model, spec, prompt = adapters.load_adapter(out / "adapter")
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=2)
    dm.setup("fit")
    assert dm.prompt == prompt
    records = dm.eval_records("validation", 2)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in the training processes (OMP_NUM_THREADS=1)
    try:
        texts = [lm.greedy_texts(model, dm.processor, [r["prompt"]], 8)[0] for r in records]
    finally:
        torch.set_num_threads(threads)
    rows = [json.loads(x) for x in (out / "eval" / "predictions_step000002.jsonl").read_text().splitlines()]
    assert [(r["index"], r["prediction"]) for r in rows] == [(r["index"], t) for r, t in zip(records, texts)]
    assert rows[0]["index"] != rows[1]["index"]


@pytest.mark.slow
def test_ddp_resume_continues_exactly_on_every_rank(tmp_path, dataset_dir):
    """trainer=ddp on 2 CPU processes with LoRA dropout: resumed from the step-2 checkpoint, step 3 ends on the
    adapter of the straight 3-step run, bit for bit. Each rank's random state is saved and restored (dropout
    masks draw from it; rank 1 used to be given rank 0's state)."""
    from safetensors.torch import load_file

    three = [f"data.dir={dataset_dir}", "trainer=ddp", "trainer.max_steps=3", "trainer.val_check_interval=3"]
    three += ["model.lora_dropout=0.3", "callbacks.checkpoint.every_n_train_steps=2", "callbacks.evaluation=null"]
    _two_processes(tmp_path / "straight", *three)
    step2 = tmp_path / "straight" / "checkpoints" / "step000002.ckpt"
    _two_processes(tmp_path / "resumed", *three, f"ckpt_path={step2}")
    straight = load_file(tmp_path / "straight" / "adapter" / "adapter_model.safetensors")
    resumed = load_file(tmp_path / "resumed" / "adapter" / "adapter_model.safetensors")
    assert set(straight) == set(resumed) and all(torch.equal(straight[k], resumed[k]) for k in straight)

    # SIGTERM to rank 1 alone during step 1 (off the 2-step cadence): both processes save step 1 and stop with
    # status 143 (Lightning's own handling hung here); resumed from it, step 3 ends on the straight run's adapter
    sigterm = ["+callbacks.sigterm._target_=train_fixtures.SigtermAt", "+callbacks.sigterm.step=1"]
    _two_processes(tmp_path / "stopped", *three, *sigterm, "+callbacks.sigterm.ranks=[1]", returncode=143)
    last = tmp_path / "stopped" / "checkpoints" / "last.ckpt"
    assert sorted(p.name for p in last.parent.iterdir()) == ["last.ckpt", "step000001.ckpt"]
    _two_processes(tmp_path / "after_sigterm", *three, f"ckpt_path={last}")
    resumed = load_file(tmp_path / "after_sigterm" / "adapter" / "adapter_model.safetensors")
    assert set(straight) == set(resumed) and all(torch.equal(straight[k], resumed[k]) for k in straight)


@pytest.mark.slow
def test_ddp_a_nan_on_one_process_stops_every_process(tmp_path, dataset_dir):
    """trainer=ddp on 2 CPU processes, a NaN weight on rank 1 alone in step 2 (checkpoints every step): the
    all-reduce carries its NaN gradient to rank 0, both stop before the optimizer step (no hang), and every file
    written holds finite weights."""
    common = [f"data.dir={dataset_dir}", "trainer=ddp", "trainer.max_steps=4", "trainer.val_check_interval=null"]
    common += ["callbacks.checkpoint.every_n_train_steps=1", "callbacks.evaluation=null"]
    nan = ["+callbacks.nan._target_=train_fixtures.NanWeightAt", "+callbacks.nan.step=2", "+callbacks.nan.ranks=[1]"]
    done = _two_processes(tmp_path / "run", *common, *nan, returncode=None)
    assert done.returncode != 0 and "the gradient norm is nan at step 2" in done.stderr
    folder = tmp_path / "run" / "checkpoints"
    assert sorted(p.name for p in folder.iterdir()) == ["last.ckpt", "step000001.ckpt"]
    state = torch.load(folder / "last.ckpt", weights_only=False)["state_dict"]
    assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())


def _two_processes(out: Path, *overrides: str, returncode: int | None = 0) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "train.py", "trainer.accelerator=cpu", "trainer.devices=2", f"hydra.run.dir={out}"]
    cmd += [*FAST, "callbacks.evaluation.num_samples=2", "callbacks.evaluation.max_new_tokens=8"]
    cmd += ["trainer.enable_progress_bar=false", *overrides]
    if "trainer=ddp" in overrides:  # ddp.yaml is for GPUs (bf16-mixed); float32 on the CPU
        cmd.append("trainer.precision=32-true")
    done = run_two_processes(cmd, out, cwd=ROOT, capture_output=True, text=True, timeout=900, env=_one_thread())
    assert returncode is None or done.returncode == returncode, done.stderr[-3000:]
    return done


def test_two_process_runs_are_run_again_only_when_their_port_was_taken(tmp_path):
    """run_two_processes reruns a run that failed with EADDRINUSE once, from an empty folder; no other failure."""
    script = "import sys; f = open(sys.argv[1], 'a+'); f.write('x'); f.seek(0); n = len(f.read()); "
    script += "sys.exit(0 if n > 1 else sys.argv[2])"
    for error, runs, code in (("name: EADDRINUSE, message: address already in use", 2, 0), ("other", 1, 1)):
        out, count = tmp_path / error[:5], tmp_path / f"{error[:5]}.count"
        (out / "checkpoints").mkdir(parents=True)
        cmd = [sys.executable, "-c", script, str(count), error]
        done = run_two_processes(cmd, out, capture_output=True, text=True)
        assert (done.returncode, len(count.read_text()), out.exists()) == (code, runs, runs == 1), error


def _one_thread() -> dict:  # and tests/ on the path, for train_fixtures' callbacks
    return dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT / "tests"))


def _weights(run: Path, name: str = "last.ckpt") -> dict[str, torch.Tensor]:
    return torch.load(run / "checkpoints" / name, map_location="cpu", weights_only=True)["state_dict"]


def test_fsdp_gradients_equal_data_parallel_ones(tmp_path, dataset_dir):
    """Two CPU processes (gloo), a different batch each, the tiny model with its tower trained and the dense
    visual head: the gradients of the sharded model (aynamics.sharding.shard_from_rank0, FSDP2 reduce-scatter;
    rank 1 builds it on the meta device and takes rank 0's weights and buffers), gathered, equal the mean of the
    two unsharded models' gradients on all 60 trainable tensors (without the buffers' broadcast, rank 1's rotary
    frequencies were uninitialised memory and the tower's gradients differed)."""
    out = tmp_path / "grads.pt"
    env = dict(_one_thread(), PYTHONPATH=str(ROOT), FSDP_TEST_STORE=str(tmp_path / "store"))
    worker = [sys.executable, str(ROOT / "tests" / "fsdp_worker.py")]
    procs = [subprocess.Popen([*worker, str(r), str(dataset_dir), str(out)], env=env) for r in (1, 0)]
    try:
        assert [p.wait(timeout=600) for p in procs] == [0, 0]
    finally:
        for p in procs:  # one failed: the other would wait for it forever
            p.kill()
    grads = torch.load(out, weights_only=True)
    ddp, fsdp = grads["ddp"], grads["fsdp"]
    assert set(ddp) == set(fsdp) and len(ddp) == 60 and "visual_head.weight" in ddp
    for k in ddp:
        assert (ddp[k].abs().max() > 0) != ("lora_A" in k), k  # all but LoRA's A (B starts at 0) get gradients
        torch.testing.assert_close(fsdp[k], ddp[k], rtol=1e-5, atol=1e-7, msg=k)


@pytest.mark.slow
def test_fsdp_matches_ddp_and_resumes_exactly(tmp_path, dataset_dir):
    """trainer=fsdp (FSDP2, aynamics.sharding) on 2 CPU processes, with the tower trained and the dense visual
    head (sharded like the adapter): 2 steps end where DDP's end. Their gradients are equal (the test above),
    but entries whose true gradient is 0 (e.g. attention key biases) carry float noise that Adam's first steps
    scale to ±lr, so the weights agree to about one step (lr 1e-3) and the losses to 1e-4. Only rank 0 builds
    the weights (rank 1's module is on the meta device until `configure_model` gives it rank 0's: under ddp
    both build theirs). The scene evaluation runs (every rank generates, rank 0 scores), the adapter holds the
    full gathered weights, and a run resumed from step 2 ends exactly where the straight run ends."""
    from safetensors.torch import load_file

    same = [f"data.dir={dataset_dir}", "model.train_vision=true", "data.visual_targets=true"]
    same += ["stage.module.vision_aux_weight=1.0", "trainer.max_steps=2", "trainer.val_check_interval=2"]
    same += ["+callbacks.init._target_=train_fixtures.RecordInit"]
    for strategy in ("ddp", "fsdp"):
        _two_processes(
            tmp_path / strategy, f"trainer={strategy}", *same, f"+callbacks.init.dirpath={tmp_path / strategy}"
        )
    init = {s: [json.loads((tmp_path / s / f"init_rank{r}.json").read_text()) for r in (0, 1)] for s in ("ddp", "fsdp")}
    assert [r["devices"] for r in init["ddp"]] == [["cpu"], ["cpu"]]
    assert [r["devices"] for r in init["fsdp"]] == [["cpu"], ["meta"]]
    ddp, fsdp = _weights(tmp_path / "ddp"), _weights(tmp_path / "fsdp")
    assert set(fsdp) == set(ddp) and any("visual_head" in k for k in fsdp) and any("lora_B" in k for k in fsdp)
    for k in ddp:
        assert fsdp[k].shape == ddp[k].shape and torch.allclose(fsdp[k], ddp[k], atol=1e-3), k
    a = load_file(tmp_path / "fsdp" / "adapter" / "adapter_model.safetensors")
    b = load_file(tmp_path / "ddp" / "adapter" / "adapter_model.safetensors")
    assert set(a) == set(b) and all(a[k].shape == b[k].shape and torch.allclose(a[k], b[k], atol=1e-3) for k in a)
    record = json.loads((tmp_path / "fsdp" / "metrics.json").read_text())["metrics"]
    reference = json.loads((tmp_path / "ddp" / "metrics.json").read_text())["metrics"]
    for key in ("val/loss", "val/vision_aux"):
        assert record[key] == pytest.approx(reference[key], rel=1e-3), key
    assert record["val/yaml_valid"] == 0.0  # 8 tokens hold no scene
    assert len((tmp_path / "fsdp" / "eval" / "predictions_step000002.jsonl").read_text().splitlines()) == 2

    three = [f"data.dir={dataset_dir}", "trainer.max_steps=3", "trainer.val_check_interval=3", "trainer=fsdp"]
    three += ["callbacks.checkpoint.every_n_train_steps=2"]
    _two_processes(tmp_path / "straight", *three)
    step2 = tmp_path / "straight" / "checkpoints" / "step000002.ckpt"
    _two_processes(tmp_path / "resumed", *three, f"ckpt_path={step2}")
    # the adapter holds the final (step 3) weights, as does last.ckpt (run_callbacks.StepCheckpoint)
    straight = load_file(tmp_path / "straight" / "adapter" / "adapter_model.safetensors")
    resumed = load_file(tmp_path / "resumed" / "adapter" / "adapter_model.safetensors")
    at_step2 = _weights(tmp_path / "straight", step2.name)
    assert not torch.equal(
        straight["base_model.model.lm_head.weight"],
        at_step2["model.base_model.model.lm_head.modules_to_save.default.weight"],
    )
    assert set(straight) == set(resumed) and all(torch.equal(straight[k], resumed[k]) for k in straight)


@pytest.mark.slow
def test_fsdp_resumes_checkpoints_of_other_strategies(tmp_path, dataset_dir):
    """A checkpoint written by a one-process run resumes under trainer=fsdp (its optimizer state numbers the
    optimizer's own parameters, which Lightning's loader read as positions among all the model's: a size
    mismatch) and continues as the same checkpoint resumed under DDP does (Adam's noise apart: 1e-3); resumed
    with other LoRA targets it is refused on every process, naming them (was a tensor size mismatch; then its
    optimizer groups were named as not fitting, now `check_same_base` names the setting before that)."""
    from safetensors.torch import load_file

    base = [f"data.dir={dataset_dir}", "trainer.val_check_interval=3", "callbacks.checkpoint.every_n_train_steps=2"]
    cmd = [sys.executable, "train.py", f"hydra.run.dir={tmp_path / 'cpu'}", *FAST, *base, "trainer.max_steps=2"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600, env=_one_thread())
    assert done.returncode == 0, done.stderr[-3000:]
    step2 = tmp_path / "cpu" / "checkpoints" / "step000002.ckpt"
    for strategy in ("fsdp", "ddp"):
        _two_processes(tmp_path / strategy, f"trainer={strategy}", *base, "trainer.max_steps=3", f"ckpt_path={step2}")
    a = load_file(tmp_path / "fsdp" / "adapter" / "adapter_model.safetensors")
    b = load_file(tmp_path / "ddp" / "adapter" / "adapter_model.safetensors")
    assert set(a) == set(b) and all(torch.allclose(a[k], b[k], atol=1e-3) for k in a)
    cmd = [sys.executable, "train.py", "trainer=fsdp", "trainer.accelerator=cpu", "trainer.devices=2", *FAST, *base]
    cmd += [f"hydra.run.dir={tmp_path / 'other'}", "trainer.max_steps=3", f"ckpt_path={step2}"]
    cmd += ["model.lora_targets=[q_proj]", "trainer.enable_progress_bar=false"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600, env=_one_thread())
    assert done.returncode != 0, done.stderr[-3000:]
    assert "the checkpoint was trained on model lora_targets=('q_proj', 'k_proj'" in done.stderr, done.stderr[-3000:]
    assert "but the run builds lora_targets=('q_proj',)" in done.stderr, done.stderr[-3000:]


def test_saved_optimizer_ids_are_named_by_their_place_in_the_groups():
    """`named_optimizer_state` by hand: a module of weights frozen, a, b, c and an optimizer of groups [c, a] and
    [b] (not the module's order). A checkpoint numbering them 0, 1 | 2 (the optimizer's own order, as a one-process
    run saves) names 0 -> c, 1 -> a, 2 -> b, whatever the module's order or a frozen weight before them; groups
    of other sizes (another LoRA setting) are refused, naming both."""
    from aynamics.sharding import named_optimizer_state

    module = torch.nn.Module()
    for name in ("frozen", "a", "b", "c"):
        module.register_parameter(name, torch.nn.Parameter(torch.zeros(1), requires_grad=name != "frozen"))
    optimizer = torch.optim.SGD([{"params": [module.c, module.a]}, {"params": [module.b], "lr": 0.5}], lr=0.1)
    saved = {
        "state": {0: {"m": 10}, 1: {"m": 11}, 2: {"m": 12}},
        "param_groups": [{"params": [0, 1], "lr": 0.1}, {"params": [2], "lr": 0.5}],
    }
    named = named_optimizer_state(saved, optimizer, module)
    assert named["state"] == {"c": {"m": 10}, "a": {"m": 11}, "b": {"m": 12}}
    assert named["param_groups"] == [{"params": ["c", "a"], "lr": 0.1}, {"params": ["b"], "lr": 0.5}]
    other = {"state": {}, "param_groups": [{"params": [0]}, {"params": [1, 2]}]}
    with pytest.raises(ValueError, match=r"groups of \[1, 2\] parameters, this run's of \[2, 1\]"):
        named_optimizer_state(other, optimizer, module)


@pytest.mark.slow
def test_fsdp_with_the_7b_config(tmp_path, dataset_dir):
    """`model=qwen2_5_vl_7b trainer=fsdp` as a GPU user runs it (bfloat16 base, float32 LoRA, gradient
    checkpointing, bf16-mixed), on 2 CPU processes with a tiny Qwen2.5-VL saved as the checkpoint: it trains,
    validates and writes a float32 adapter of full (gathered) LoRA weights, rank 16 as configured."""
    from safetensors.torch import load_file

    from aynamics.model import build_tiny_model
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    folder = tmp_path / "qwen"
    build_tiny_model(seed=3).save_pretrained(folder)
    shutil.copytree(TINY_ASSET_DIR, folder, dirs_exist_ok=True)
    out = tmp_path / "run"
    _two_processes(
        out,
        "trainer=fsdp",
        "model=qwen2_5_vl_7b",
        f"model.path={folder}",
        f"data.dir={dataset_dir}",
        "trainer.max_steps=2",
        "trainer.val_check_interval=2",
    )
    record = json.loads((out / "metrics.json").read_text())
    assert record["config"]["trainer"]["precision"] == "bf16-mixed" and record["config"]["model"]["dtype"] == "bfloat16"
    assert math.isfinite(record["metrics"]["val/loss"])
    adapter = load_file(out / "adapter" / "adapter_model.safetensors")
    a = next(v for k, v in adapter.items() if k.endswith("q_proj.lora_A.weight"))
    assert a.dtype == torch.float32 and a.shape == (16, 64)  # rank 16 x the tiny width, not a shard


def test_vision_lr_scale_sets_the_tower_group(dataset_dir):
    """vision_lr_scale = 0 leaves the (warmed-up) tower and the dense head as they are while the adapter moves;
    another value puts them in a second group at lr × scale; 1 keeps one group; a bad value is named."""
    spec = lm.ModelSpec(kind="tiny", lora_dropout=0.0, train_vision=True)
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=2, visual_targets=True)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    module = SFTModule(spec, lr=1e-2, vision_aux_weight=1.0, vision_lr_scale=0.0)
    opt = module.configure_optimizers()["optimizer"]
    tower = {k for k, p in module.named_parameters() if "visual" in k and p.requires_grad}  # the trained copy
    assert [g["lr"] for g in opt.param_groups] == [1e-2, 0.0]
    assert {id(p) for p in opt.param_groups[1]["params"]} == {id(p) for k, p in module.named_parameters() if k in tower}
    before = {k: p.detach().clone() for k, p in module.named_parameters()}
    loss, _, _ = module._loss(batch)
    (loss + module._vision_aux(batch, 2, "train")).backward()
    module.on_before_optimizer_step(opt)  # Lightning calls it before clipping: the fixed group's norm must not count
    assert all(p.grad is None for p in opt.param_groups[1]["params"])
    assert all(p.grad is not None for p in opt.param_groups[0]["params"])  # the adapter's are kept
    opt.step()
    for k, p in module.named_parameters():
        if k in tower:
            assert torch.equal(before[k], p.detach()), k
    assert tower and any(not torch.equal(before[k], p) for k, p in module.named_parameters() if "lora_B" in k)

    half = SFTModule(spec, lr=1e-2, vision_aux_weight=1.0, vision_lr_scale=0.5).configure_optimizers()["optimizer"]
    assert [g["lr"] for g in half.param_groups] == [1e-2, 5e-3]
    assert len(SFTModule(spec, lr=1e-2).configure_optimizers()["optimizer"].param_groups) == 1
    with pytest.raises(ValueError, match="vision_lr_scale = -1"):
        SFTModule(spec, vision_lr_scale=-1.0)
    # resuming with another value would load one optimizer group into two (or keep the old rate): refused
    ckpt = {
        "state_dict": {k: p for k, p in module.named_parameters() if p.requires_grad},
        "hyper_parameters": {"vision_lr_scale": 1.0},
    }
    with pytest.raises(ValueError, match="vision_lr_scale = 0.0, but the checkpoint was trained with 1.0"):
        module.on_load_checkpoint(ckpt)
    ckpt["hyper_parameters"]["vision_lr_scale"] = 0.0
    module.on_load_checkpoint(ckpt)


def test_config_mistakes_are_named_before_training(tmp_path, dataset_dir):
    """Values that Lightning or the loaders would take without a word (no training batch at all, frames that are
    not stored, an infinite schedule) or fail on deep inside stop first with the key and the value."""
    cases = [
        (
            ["trainer.max_steps=-1", "trainer.max_epochs=-1"],
            "trainer.max_steps = -1, trainer.max_epochs = -1: training",
        ),
        (["data.limit_train=0"], r"data.limit_train = 0: must be >= 1"),
        (["data.limit_val=-1"], r"data.limit_val = -1: must be >= 1"),
        (["data.eval_batch_size=0"], r"data.eval_batch_size = 0: must be >= 1"),
        (["data.num_frames=20"], r"data.num_frames = 20: the scenes in data.dir = .* store 10 frames each"),
        (["data.min_pixels=0"], r"min_pixels = 0: must be >= 784"),
        (
            ["data.min_pixels=20000", "data.max_pixels=10000"],
            r"^data.min_pixels = 20000 > data.max_pixels = 10000 .*: need data.min_pixels <= data.max_pixels$",
        ),
        (["trainer.val_check_interval=0"], r"trainer.val_check_interval = 0: must be a whole number of steps > 0"),
        (["trainer.val_check_interval=0.5"], r"val_check_interval = 0.5: must be a whole number"),  # Lightning's
        # traceback; helper-43's: no adapter written, a traceback, a key ignored, a target named as data's
        (["trainer.max_steps=0"], r"trainer.max_steps = 0: must be >= 1"),
        # max_epochs 0 stopped before the first batch with exit status 0, no adapter and an empty metrics.json
        (["trainer.max_steps=-1", "trainer.max_epochs=0"], r"trainer.max_steps = -1, trainer.max_epochs = 0: trains"),
        (["trainer.max_epochs=0"], r"trainer.max_steps = 200, trainer.max_epochs = 0: trains nothing"),
        (["trainer.max_epochs=-5"], r"trainer.max_epochs = -5: must be a whole number >= 1, or -1"),
        (["trainer.max_epochs=1.5"], r"trainer.max_epochs = 1.5: must be a whole number >= 1, or -1"),
        # numpy's "-1 is not in bounds, numpy accepts from 0 to 4294967295", int()'s "invalid literal": no key named
        (["seed=-1"], r"seed = -1: must be a whole number in \[0, 2\*\*32 - 1\]"),
        (["seed=abc"], r"seed = 'abc': must be a whole number"),
        # each process's share would be split again by Lightning (a ddp run trained on 1 / world of its data)
        (["trainer.use_distributed_sampler=true"], r"trainer.use_distributed_sampler = true: the data modules"),
        (
            ["callbacks.checkpoint.every_n_train_steps=-5"],
            r"callbacks.checkpoint.every_n_train_steps = -5: must be a whole number >= 1",
        ),
        (["data.target=think_answer"], r"data.target = 'think_answer': set the target as stage.target=think"),
        (["stage.target=foo"], r"stage.target = 'foo': must be one of \('answer', 'think_answer'\)"),
        (["stage.module.lr=inf"], r"stage.module.lr = inf.*need finite lr > 0"),  # trained to NaN and saved the adapter
        (
            ["stage.module.vision_aux_weight=1", "model.train_vision=true", "data.visual_targets=false"],
            r"^stage.module.vision_aux_weight = 1 needs per-token targets: set data.visual_targets=true$",
        ),
    ]
    from hydra.errors import InstantiationException  # hydra's wrapper of an error in a config's constructor

    for overrides, message in cases:
        with pytest.raises((ValueError, InstantiationException), match=message):
            train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", "callbacks.evaluation=null", *overrides))
    with pytest.raises(FileNotFoundError, match="holds no data set"):
        train(_cfg(tmp_path / "x", f"data.dir={tmp_path / 'nope'}"))
    torch.save({"state_dict": {}}, tmp_path / "plain.pt")  # a torch file, not Lightning's: KeyError in Lightning
    (tmp_path / "garbage.ckpt").write_bytes(b"not a checkpoint")
    for ckpt, message in [
        (tmp_path / "plain.pt", "not a Lightning training checkpoint"),
        (tmp_path / "garbage.ckpt", "not a checkpoint torch can read"),
    ]:
        with pytest.raises(ValueError, match=rf"ckpt_path = .*{ckpt.name}': {message}"):
            train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", f"ckpt_path={ckpt}"))
    with pytest.raises(FileNotFoundError, match="no such checkpoint"):
        train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", f"ckpt_path={tmp_path / 'none.ckpt'}"))
    broken = tmp_path / "broken"
    shutil.copytree(dataset_dir, broken)
    arrow = next((broken / "train").glob("*.arrow"))
    arrow.write_bytes(
        arrow.read_bytes()[:1000]
    )  # truncated: was pyarrow's error, naming neither the folder nor the file
    with pytest.raises(ValueError, match=r"data.dir = .*broken': the data set cannot be read \(ArrowInvalid"):
        train(_cfg(tmp_path / "x", f"data.dir={broken}"))


def test_a_checkpoint_folder_or_another_stages_checkpoint_is_refused_before_the_model(tmp_path, dataset_dir):
    """ckpt_path = a run's checkpoints/ folder failed inside Lightning (IsADirectoryError, a traceback); an SFT
    checkpoint resumed under stage=pro (or a PRO one under stage=sft) went on without a word, with the other
    stage's optimizer state and schedule."""
    folder = tmp_path / "run" / "checkpoints"
    folder.mkdir(parents=True)
    stages = {"sft": {"warmup_steps": 10, "lr": 1e-3}, "pro": {"num_samples": 4, "lr": 1e-4}}
    for name, hp in stages.items():
        torch.save({"pytorch-lightning_version": "2.5.0", "hyper_parameters": hp}, folder / f"{name}.ckpt")
    with pytest.raises(ValueError, match=rf"ckpt_path = '{folder}': a folder, not a checkpoint .* ckpt_path={folder}/"):
        train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", f"ckpt_path={folder}"))
    deepspeed = tmp_path / "deepspeed.ckpt"  # DeepSpeed's folder is still Lightning's to read
    deepspeed.mkdir()
    (deepspeed / "latest").write_text("checkpoint")
    adapters.check_resume_checkpoint(deepspeed, "sft")
    for stage, other in (("sft", "pro"), ("pro", "sft")):
        with pytest.raises(ValueError, match=rf"a checkpoint of stage={other}, but the run is stage={stage}"):
            train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", f"stage={stage}", f"ckpt_path={folder / other}.ckpt"))
        adapters.check_resume_checkpoint(folder / f"{stage}.ckpt", stage)
    assert not (tmp_path / "x").exists()


def test_resuming_another_runs_checkpoint_into_a_run_folder_is_refused(tmp_path, dataset_dir):
    """ckpt_path=A/checkpoints/last.ckpt with hydra.run.dir=B, where B holds another run, wrote last-v1.ckpt beside
    B's last.ckpt and overwrote B's adapter and metrics.json; into a new folder, or its own, it still resumes."""
    a, b = tmp_path / "a" / "checkpoints", tmp_path / "b"
    a.mkdir(parents=True)
    torch.save({"pytorch-lightning_version": "2.5.0", "hyper_parameters": {"warmup_steps": 10}}, a / "last.ckpt")
    (b / "checkpoints").mkdir(parents=True)
    (b / "checkpoints" / "last.ckpt").write_bytes(b"b's")
    before = sorted(p.name for p in b.rglob("*"))
    with pytest.raises(ValueError, match=rf"ckpt_path = '{a}/last.ckpt' is not a checkpoint of the run in .*'{b}'"):
        train(_cfg(b, f"data.dir={dataset_dir}", f"ckpt_path={a / 'last.ckpt'}"))
    assert sorted(p.name for p in b.rglob("*")) == before
    (b / "checkpoints" / "last.ckpt").unlink()
    (b / "metrics.json").write_text("{}")  # a finished run without its checkpoints
    with pytest.raises(ValueError, match="is not a checkpoint of the run in"):
        train(_cfg(b, f"data.dir={dataset_dir}", f"ckpt_path={a / 'last.ckpt'}"))


def test_cli_input_errors_are_one_paragraph_with_the_traceback_in_the_log(tmp_path, dataset_dir):
    """`python train.py` with a wrong data.dir or an out-of-range value exits 2 with one line on stderr naming the
    key and the value, the traceback in OUT/train.log only (Hydra printed the traceback around the message);
    HYDRA_FULL_ERROR=1 still gives Hydra's full report. Errors that are not the input's keep their traceback."""
    from hydra.errors import InstantiationException
    from omegaconf import OmegaConf

    from train import input_error_message, name_keys

    out = tmp_path / "run"
    cmd = [sys.executable, "train.py", f"data.dir={tmp_path / 'nope'}", f"hydra.run.dir={out}"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr[-3000:]
    lines = [line for line in done.stderr.splitlines() if line.startswith("train.py: ")]
    assert len(lines) == 1 and "Traceback" not in done.stderr + done.stdout
    assert f"data.dir = '{tmp_path / 'nope'}' holds no data set" in lines[0]
    assert lines[0].endswith(f"(traceback in {out / 'train.log'})")
    log = (out / "train.log").read_text()
    assert "holds no data set" in log and "Traceback (most recent call last)" in log and "load_splits" in log
    sweep = [sys.executable, "train.py", "-m", f"data.dir={tmp_path / 'a'},{tmp_path / 'b'}"]
    multirun = subprocess.run(
        [*sweep, f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=ROOT, capture_output=True, text=True
    )
    said = [line for line in multirun.stderr.splitlines() if line.startswith("train.py: ")]
    assert (
        multirun.returncode != 0
        and len(said) == 2
        and f"{tmp_path / 'a'}' holds no" in said[0]
        and f"{tmp_path / 'b'}' holds" in said[1]
    )
    full = subprocess.run(
        cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env={**os.environ, "HYDRA_FULL_ERROR": "1"}
    )
    assert full.returncode == 1 and "Traceback (most recent call last)" in full.stderr

    wrapped = InstantiationException(
        "Error in call to target 'aynamics.data.SceneDataModule':\nValueError(..)\nfull_key: data"
    )
    wrapped.__cause__ = ValueError("min_pixels = 0: must be >= 784")
    assert input_error_message(wrapped) == "data.min_pixels = 0: must be >= 784"
    wrapped.__cause__ = ValueError("no data set in 'x'")
    assert input_error_message(wrapped) == "no data set in 'x' (config: data)"
    assert name_keys("lr = -1, weight_decay = 0.1: need lr > 0", "stage.module") == (
        "stage.module.lr = -1, stage.module.weight_decay = 0.1: need lr > 0"
    )
    try:
        OmegaConf.create({"model": {"path": "???"}}).model.path
    except Exception as missing:
        assert input_error_message(missing) == "Missing mandatory value: model.path (config: model.path)"
    assert input_error_message(FileNotFoundError("no such checkpoint")) == "no such checkpoint"
    no_adapter = FileNotFoundError(2, "stage.init_adapter = '/x' holds no adapter_config.json", "/x")
    assert input_error_message(no_adapter) == "stage.init_adapter = '/x' holds no adapter_config.json"  # no [Errno 2]
    assert input_error_message(FileNotFoundError(2, "No such file or directory", "/y")) == "file not found: /y"
    # once training has started, only the errors this project raises: a ValueError from numpy keeps its traceback
    # and a builtin failing inside our code (an unpacking, `open` on a full disk) is no check of ours either
    import aynamics
    from aynamics.scene import SceneError, parse

    namespace: dict = {}
    exec(
        compile("def unpack():\n    a, b = (1, 2, 3)\n", str(Path(aynamics.__file__).parent / "x.py"), "exec"),
        namespace,
    )
    for raise_it, ours in (
        (lambda: parse("- type: box\n  size: [-1, 1, 1]"), True),
        (lambda: np.ones(2) + np.ones(3), False),
        (namespace["unpack"], False),
    ):
        try:
            raise_it()
        except ValueError as error:
            error.raised_in_fit = True
            assert (input_error_message(error) is not None) == ours and isinstance(error, SceneError) == ours
    assert input_error_message(RuntimeError("CUDA out of memory")) is None  # not the input's: traceback kept
    assert input_error_message(InstantiationException("x")) is None  # no cause to name
    bug = InstantiationException("y")
    bug.__cause__ = ZeroDivisionError("division by zero")
    assert input_error_message(bug) is None


def test_cli_sigterm_saves_the_step_and_exits_143(tmp_path, dataset_dir):
    """SIGTERM (a cluster's preemption) during step 2 of `python train.py`: the step is saved as last.ckpt (the
    cadence is every 100 steps), the run stops with status 143 and the log names the checkpoint to resume from
    (was: Lightning's silent stop, status 0, the steps since the last periodic save lost)."""
    out = tmp_path / "run"
    cmd = [sys.executable, "train.py", f"data.dir={dataset_dir}", f"hydra.run.dir={out}", "trainer.max_steps=4"]
    cmd += [*FAST, "callbacks.evaluation=null", "trainer.val_check_interval=null", "trainer.enable_progress_bar=false"]
    cmd += ["+callbacks.sigterm._target_=train_fixtures.SigtermAt", "+callbacks.sigterm.step=2"]
    env = {**os.environ, "PYTHONPATH": str(ROOT / "tests")}
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 143, done.stderr[-3000:]
    last = out / "checkpoints" / "last.ckpt"
    assert f"stopped by SIGTERM: resume with ckpt_path={last}" in done.stdout + done.stderr
    assert torch.load(last, weights_only=False)["global_step"] == 2
    assert (out / "adapter" / "adapter_config.json").is_file()


def test_data_without_validation_or_with_a_broken_record_still_trains(tmp_path, dataset_dir):
    """A data set with no validation scene trains without validation (it stopped at the first one, after the model
    had loaded); a validation record whose scene_yaml cannot be scored is left out of the scene evaluation with a
    warning naming it (a bare SceneError stopped the run at its first validation)."""
    from datasets import DatasetDict, load_from_disk

    dd = load_from_disk(str(dataset_dir))
    run = [*FAST, "trainer.max_steps=2", "trainer.val_check_interval=1", "callbacks.evaluation.num_samples=2"]
    run += ["callbacks.evaluation.max_new_tokens=8", "callbacks.evaluation.num_animations=0"]

    from aynamics.generate import GenerateConfig, generate_dataset

    none = tmp_path / "no_validation"  # what `generate --num 12 --seed 2` gives by chance
    generate_dataset(none, num=3, seed=0, config=GenerateConfig(width=64, height=48, workers=0, splits=(1.0, 0, 0)))
    with pytest.warns(UserWarning, match="holds no validation scenes"):
        metrics = train(_cfg(tmp_path / "a", f"data.dir={none}", *run))
    assert "train/loss" in metrics and not any(k.startswith("val/") for k in metrics)
    assert (tmp_path / "a" / "adapter" / "adapter_config.json").is_file()

    broken = tmp_path / "broken_record"
    first = dd["validation"][0]["index"]
    bad = dd["validation"].map(
        lambda r: {"scene_yaml": "- type: box\n  size: -1\n" if r["index"] == first else r["scene_yaml"]}
    )
    DatasetDict({"train": dd["train"], "validation": bad, "test": dd["test"]}).save_to_disk(str(broken))
    with pytest.warns(UserWarning, match=rf"record {first} of the validation records of data.dir = .* is left out"):
        metrics = train(_cfg(tmp_path / "b", f"data.dir={broken}", *run))
    assert 0 <= metrics["val/yaml_valid"] <= 1  # the other record was evaluated


@pytest.mark.parametrize("stage", ["sft", "pro"])
def test_checkpoint_hooks_accept_deepspeed_checkpoints(stage):
    """DeepSpeed keeps the weights out of Lightning's checkpoint dict (it writes its own files, without the frozen
    base: exclude_frozen_parameters in conf/trainer/deepspeed.yaml): saving and loading such a dict works, RNG
    states included; a plain checkpoint that lacks trainable weights is still refused (for PRO too: it loaded one,
    the missing weights keeping their fresh values) and one of another LoRA rank names the setting."""
    from aynamics.pro import ProModule

    module = SFTModule(lm.ModelSpec(kind="tiny")) if stage == "sft" else ProModule(lm.ModelSpec(kind="tiny"))
    checkpoint = {"hyper_parameters": {"vision_lr_scale": 1.0}}
    module.on_save_checkpoint(checkpoint)
    assert "state_dict" not in checkpoint and set(checkpoint["rng"]["per_rank"][0]) >= {"torch", "numpy", "python"}
    module.on_load_checkpoint(checkpoint)
    with pytest.raises(ValueError, match="checkpoint lacks .* trainable weights"):
        module.on_load_checkpoint({**checkpoint, "state_dict": {}})
    other = {k: v for k, v in module.state_dict().items() if "lora_A" not in k}
    with pytest.raises(ValueError, match=r"lora_A.*written for a different model.\* / LoRA setting"):
        module.on_load_checkpoint({**checkpoint, "state_dict": other})


def test_rng_states_are_restored_per_rank():
    """`rng.restore` gives rank r the states saved for rank r (torch, NumPy and Python draw what they drew after
    the save), rank r mod the count for a checkpoint of fewer processes, and reads the older one-set format."""
    import random

    import numpy as np

    from aynamics import rng

    def draws() -> tuple:
        return torch.rand(2).tolist(), np.random.rand(), np.random.standard_normal(), random.random()

    saved, expected = [], []
    for seed in (1, 2):
        torch.manual_seed(seed), np.random.seed(seed), random.seed(seed)
        np.random.standard_normal()  # NumPy makes normals in pairs: the second is cached (has_gauss = 1) ...
        assert np.random.get_state()[3] == 1
        saved.append(rng.local_state())  # ... and the state holds it: the next normal drawn after a restore
        expected.append(draws())  # what the generators draw after the save
    assert expected[0] != expected[1]
    for state, want in zip(saved, expected, strict=True):
        rng.restore({"per_rank": [state]}, 0)
        assert draws() == want
    both = {"per_rank": saved}
    for rank, want in ((0, 0), (1, 1), (2, 0), (3, 1)):
        rng.restore(both, rank)
        assert draws() == expected[want], rank
    rng.restore(saved[1], 0)  # a checkpoint written before the states were kept per rank
    assert draws() == expected[1]


def test_runs_say_when_their_results_are_from(tmp_path, dataset_dir, caplog, capsys):
    """helper-43's run-level findings, each on a 2-4 step run:
    - 3 steps validated every 2: metrics.json's val/ metrics are step 2's, and say so (`val_step`; the table said
      step 3), with callbacks.adapter=null (a crash after training);
    - with 2 batches per step, validation every 2 steps is at step 2 only (it counted batches: steps 1, 2, 3);
    - resuming the finished run at the same max_steps trains nothing and leaves metrics.json as it was (it was
      overwritten empty); resuming under another modality is refused, naming both."""
    import logging

    common = [f"data.dir={dataset_dir}", "callbacks.evaluation.num_samples=1", "callbacks.evaluation.max_new_tokens=4"]
    common += ["callbacks.evaluation.num_animations=0", "trainer.val_check_interval=2"]
    out = tmp_path / "run"
    train(_cfg(out, *common, "trainer.max_steps=3", "callbacks.adapter=null"))
    record = json.loads((out / "metrics.json").read_text())
    assert (record["global_step"], record["val_step"]) == (3, 2) and "val/yaml_valid" in record["metrics"]
    assert "held-out scenes, step 2):" in capsys.readouterr().out
    acc = tmp_path / "acc"
    train(_cfg(acc, *common, "trainer.max_steps=3", "trainer.accumulate_grad_batches=2"))
    assert sorted(p.name for p in (acc / "eval").glob("predictions_step*.jsonl")) == ["predictions_step000002.jsonl"]
    before = (acc / "metrics.json").read_text()
    with caplog.at_level(logging.WARNING):
        train(_cfg(acc, *common, "trainer.max_steps=3", f"ckpt_path={acc / 'checkpoints' / 'last.ckpt'}"))
    assert "had reached step 3" in caplog.text and (acc / "metrics.json").read_text() == before
    again = [*common, "trainer.max_steps=4", f"ckpt_path={acc / 'checkpoints' / 'last.ckpt'}", "data.modality=flow"]
    with pytest.raises(ValueError, match="trained with modality='rgb'.* set to data.modality='flow'"):
        train(_cfg(tmp_path / "other", *again))


def test_resumed_to_a_longer_run_steps_on_the_new_schedule(tmp_path, dataset_dir):
    """3 cosine steps (no warm-up) resumed to 4: step 4 takes the 4-step schedule's rate, as a straight 4-step
    run's step 4 does (it took the 3-step run's last rate: helper-43). The first three steps had the 3-step
    schedule's rates, so the weights are not the straight run's: a longer schedule is a warm restart."""
    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "callbacks.evaluation=null"]
    common += ["stage.module.warmup_steps=0", "trainer.val_check_interval=null", "trainer.check_val_every_n_epoch=100"]
    train(_cfg(tmp_path / "short", *common, "trainer.max_steps=3"))
    straight = train(_cfg(tmp_path / "long", *common, "trainer.max_steps=4"))
    ckpt = tmp_path / "short" / "checkpoints" / "last.ckpt"
    resumed = train(_cfg(tmp_path / "resumed", *common, "trainer.max_steps=4", f"ckpt_path={ckpt}"))
    assert resumed["train/lr"] == pytest.approx(straight["train/lr"], rel=1e-6)


def test_resume_from_a_validated_step_continues_exactly(tmp_path, dataset_dir):
    """LoRA dropout on (as in the 3B / 7B configs), validation every 2 steps, a checkpoint every step: resumed from
    step 2 (saved before that step's validation, which the resumed run skips), steps 3 and 4 are the straight run's
    bit for bit. The validation loader drew its workers' base seed from torch's global generator, so every
    validation moved the dropout masks of the steps after it, and the resumed run's differed."""
    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "callbacks.evaluation=null", "model.lora_dropout=0.1"]
    common += ["callbacks.checkpoint.every_n_train_steps=1", "trainer.val_check_interval=2"]
    common += ["trainer.enable_progress_bar=false"]
    train(_cfg(tmp_path / "straight", *common, "trainer.max_steps=4"))
    train(_cfg(tmp_path / "short", *common, "trainer.max_steps=2"))
    ckpt = tmp_path / "short" / "checkpoints" / "step000002.ckpt"
    train(_cfg(tmp_path / "resumed", *common, "trainer.max_steps=4", f"ckpt_path={ckpt}"))
    _same_steps(tmp_path / "straight", tmp_path / "resumed", (3, 4))


def test_resume_refuses_another_base_scaling_data_order_or_examples(tmp_path, dataset_dir, monkeypatch):
    """A checkpoint resumed under another model.seed (the tiny model's random base: the adapter was trained on other
    frozen weights), model.lora_alpha (the update's scale), data.seed (the loader's stored seed: the resumed epoch
    skipped the first examples of another order) or in-context examples is refused, naming the setting; all four
    resumed silently (the adapter folder then named the new base). Another base or prompt (stage.target,
    data.modality) is named before the model is built (helper-109: after it, minutes for the 3B)."""
    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "callbacks.evaluation=null"]
    common += ["trainer.val_check_interval=null", "trainer.check_val_every_n_epoch=100"]
    train(_cfg(tmp_path / "a", *common, "trainer.max_steps=1"))
    ckpt = f"ckpt_path={tmp_path / 'a' / 'checkpoints' / 'last.ckpt'}"
    with monkeypatch.context() as m:  # named before the model is built (minutes for the 3B), not as Lightning loads
        m.setattr(lm, "build_model", lambda *a, **k: pytest.fail("the model was built before the refusal"))
        for override, message in (
            ("model.seed=7", "trained on model seed=0, but the run builds seed=7"),
            ("model.lora_alpha=8", "lora_alpha=64.0, but the run builds lora_alpha=8"),
            ("stage.target=think_answer", r"the checkpoint was trained with .*answer.*, but the data are set to"),
            ("data.modality=flow", r"the checkpoint was trained with .*rgb.*, but the data are set to .*flow"),
        ):
            with pytest.raises(ValueError, match=message):
                train(_cfg(tmp_path / "b", *common, "trainer.max_steps=2", override, ckpt))
    for override, message in (
        ("data.seed=5", "data.seed = 5, but the checkpoint was trained with 0"),
        ("data.num_examples=1", "trained with 0 in-context examples in its prompt, but the data are set to 1"),
    ):
        with pytest.raises(ValueError, match=message):
            train(_cfg(tmp_path / "b", *common, "trainer.max_steps=2", override, ckpt))


def test_resume_refuses_another_adapter_shape_before_loading_its_weights():
    """A checkpoint of another model.lora_rank failed inside Lightning with a size-mismatch traceback; one with more
    LoRA targets or trained modules than the run dropped the rest of its weights without a word."""
    import dataclasses

    spec = lm.ModelSpec(kind="tiny", lora_rank=32, lora_alpha=64.0, modules_to_save=["embed_tokens", "lm_head"])
    stored = dataclasses.asdict(spec)
    adapters.check_same_base(stored, spec)  # the same settings, tuples or lists alike
    adapters.check_same_base({**stored, "lora_targets": list(spec.lora_targets)}, spec)
    for key, value, message in (
        ("lora_rank", 8, "lora_rank=32, but the run builds lora_rank=8"),
        ("lora_targets", ("q_proj",), r"lora_targets=\(.*'down_proj'\), but the run builds lora_targets=\('q_proj',\)"),
        (
            "modules_to_save",
            (),
            r"modules_to_save=\('embed_tokens', 'lm_head'\), but the run builds modules_to_save=\(\)",
        ),
        ("train_vision", True, "train_vision=False, but the run builds train_vision=True"),
    ):
        with pytest.raises(ValueError, match=message):
            adapters.check_same_base(stored, dataclasses.replace(spec, **{key: value}))


def test_resume_takes_the_same_adapter_modules_listed_in_another_order():
    """model.modules_to_save=[lm_head,embed_tokens] (or the LoRA targets reordered) on resuming a run of the default
    [embed_tokens, lm_head] builds the same trainable weights in the same order: it was refused as another model."""
    import dataclasses

    spec = lm.ModelSpec(kind="tiny", modules_to_save=["embed_tokens", "lm_head"])
    stored = dataclasses.asdict(spec)
    adapters.check_same_base(stored, dataclasses.replace(spec, modules_to_save=("lm_head", "embed_tokens")))
    adapters.check_same_base(stored, dataclasses.replace(spec, lora_targets=tuple(reversed(spec.lora_targets))))
    with pytest.raises(ValueError, match=r"modules_to_save=\('embed_tokens', 'lm_head'\), but the run builds"):
        adapters.check_same_base(stored, dataclasses.replace(spec, modules_to_save=("lm_head",)))


def test_validation_that_cannot_keep_to_its_steps_under_accumulation_is_named(tmp_path, dataset_dir, caplog):
    """5 training records at batch 1 with 2 batches per step: each epoch's last step takes 1 batch, so validation
    'every 3 steps' (every 6 batches) fell at steps 3 and 7 of an 8-step run, not 3 and 6 (the checkpoints' steps):
    the run says so before training."""
    import logging

    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "callbacks.evaluation=null", "trainer.max_steps=1"]
    common += ["trainer.accumulate_grad_batches=2", "trainer.val_check_interval=3"]
    with caplog.at_level(logging.WARNING):
        train(_cfg(tmp_path / "drift", *common))
    assert "an epoch is 5 batches, not a multiple of 2" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        train(_cfg(tmp_path / "even", *common, "data.batch_size=2", "trainer.accumulate_grad_batches=3"))
    assert "validation drifts" not in caplog.text


def test_every_n_validations_keeps_its_cadence_across_a_resume(tmp_path, dataset_dir):
    """Scene evaluation at every 2nd validation (validation every step): a 4-step run evaluates at steps 2 and 4,
    and so does the same run resumed from step 1 (its count restarted at 0 and Lightning skips the validation of
    the resumed step: it evaluated at 3 and 4)."""
    common = [f"data.dir={dataset_dir}", "data.batch_size=1", "trainer.val_check_interval=1"]
    common += ["callbacks.evaluation.every_n_validations=2", "callbacks.evaluation.num_samples=1"]
    common += ["callbacks.evaluation.max_new_tokens=2", "callbacks.evaluation.num_animations=0"]
    common += ["callbacks.evaluation.baseline=false", "callbacks.checkpoint.every_n_train_steps=1"]
    train(_cfg(tmp_path / "straight", *common, "trainer.max_steps=4"))
    train(_cfg(tmp_path / "short", *common, "trainer.max_steps=1"))
    ckpt = tmp_path / "short" / "checkpoints" / "step000001.ckpt"
    train(_cfg(tmp_path / "resumed", *common, "trainer.max_steps=4", f"ckpt_path={ckpt}"))
    for run in ("straight", "resumed"):
        files = sorted(p.name for p in (tmp_path / run / "eval").glob("predictions_step*.jsonl"))
        assert files == ["predictions_step000002.jsonl", "predictions_step000004.jsonl"], run


def test_resuming_a_finished_run_keeps_its_csv_log(tmp_path, dataset_dir):
    """Lightning's CSV logger deletes the metrics.csv it finds when it starts: resuming a finished run at its own
    max_steps trained nothing and left csv/metrics.csv gone (helper-67). It is put back as it was."""
    common = [f"data.dir={dataset_dir}", "logger=csv", "callbacks.evaluation=null", "trainer.max_steps=1"]
    common += ["trainer.log_every_n_steps=1"]
    out = tmp_path / "run"
    train(_cfg(out, *common))
    log = out / "csv" / "metrics.csv"
    before = log.read_text()
    assert "train/loss" in before
    train(_cfg(out, *common, f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}"))
    assert log.read_text() == before


def test_resuming_into_the_same_folder_keeps_the_earlier_csv_rows(tmp_path, dataset_dir):
    """A resume from step 2 to 4 in the run's folder, validating every 2 steps: Lightning's CSV logger would start
    metrics.csv again (steps 2-3 only). The step column counts from 0 and a validation at step n is logged as n - 1:
    the first run's rows (steps 0, 1, validation 1) stay in front of the resumed run's (2, 3, validation 3)."""
    common = [f"data.dir={dataset_dir}", "logger=csv", "trainer.log_every_n_steps=1", "trainer.val_check_interval=2"]
    common += ["callbacks.evaluation.num_samples=1", "callbacks.evaluation.max_new_tokens=4"]
    out = tmp_path / "run"
    train(_cfg(out, *common, "trainer.max_steps=2"))
    log = out / "csv" / "metrics.csv"
    first = log.read_text().splitlines()
    train(_cfg(out, *common, "trainer.max_steps=4", f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}"))
    rows = list(csv.DictReader(log.open()))
    kind = ["train" if r["train/loss"] else "val" for r in rows]
    assert [(r["step"], k) for r, k in zip(rows, kind)] == [
        ("0", "train"), ("1", "train"), ("1", "val"), ("2", "train"), ("3", "train"), ("3", "val")
    ]  # fmt: skip
    assert log.read_text().splitlines()[1:4] == first[1:4]
    assert not (out / "csv" / "metrics.before-resume.csv").exists()


def test_joined_csv_rows_drop_the_steps_a_resume_logs_again(tmp_path):
    """A run logged steps 0-6 (a validation at step 5 logged as 4) and was stopped; its checkpoint is at step 5.
    Resumed from 5, the kept rows are those before step 5: 0-4 and the validation, then the resumed run's 5, 6.
    Without the resume step (an earlier resume stopped before the join), the first training step the newer log
    holds takes its place: a validation row it starts with (logged as 4) does not count."""
    from train import _joined_rows

    older, newer = tmp_path / "older.csv", tmp_path / "newer.csv"
    older.write_text("epoch,step,train/loss,val/x\n" + "".join(f"0,{s},{s}.0,\n" for s in range(7)) + "0,4,,9\n")
    newer.write_text("epoch,step,train/loss,train/lr\n0,5,5.5,1\n0,6,6.5,1\n")
    fields, rows = _joined_rows(older, newer, until=5)
    assert fields == ["epoch", "step", "train/loss", "val/x", "train/lr"]
    assert [(r["step"], r["train/loss"]) for r in rows] == [
        ("0", "0.0"), ("1", "1.0"), ("2", "2.0"), ("3", "3.0"), ("4", "4.0"), ("4", ""), ("5", "5.5"), ("6", "6.5")
    ]  # fmt: skip
    newer.write_text("epoch,step,train/loss,val/x\n0,4,,8\n0,5,5.5,\n")
    assert [r["step"] for r in _joined_rows(older, newer)[1]] == ["0", "1", "2", "3", "4", "4", "4", "5"]
    assert [r["step"] for r in _joined_rows(tmp_path / "missing.csv", newer)[1]] == ["4", "5"]


def test_a_second_resume_after_one_stopped_before_the_join_keeps_the_csv_rows_in_order(tmp_path):
    """A run logged steps 0-6 and was resumed from step 5; that resume logged 5, 6, 7 into a new metrics.csv and
    was stopped before the join, leaving metrics.before-resume.csv (0-6) beside it. The next resume's keep puts
    the older file first and keeps its rows before the first step the newer one trained (5): 0-4, then 5, 6, 7.
    (Kept the other way round, the stale 5, 6 of the first run would come after step 7, and 7 would be lost.) A
    row without a step (written by hand: 0,,9.9) cannot be placed before or after the resume and is kept."""
    from lightning.pytorch.loggers import CSVLogger

    from train import CSV_KEPT, keep_csv_logs

    logger = CSVLogger(tmp_path, name="csv", version="")
    log = Path(logger.log_dir) / "metrics.csv"
    log.parent.mkdir(parents=True, exist_ok=True)
    log.with_name(CSV_KEPT).write_text(
        "epoch,step,train/loss\n" + "".join(f"0,{s},{s}.0\n" for s in range(7)) + "0,,9.9\n"
    )
    log.write_text("epoch,step,train/loss\n" + "".join(f"0,{s},{s}.5\n" for s in (5, 6, 7)))
    assert keep_csv_logs([object(), logger]) == [log]
    rows = list(csv.DictReader(log.with_name(CSV_KEPT).open()))
    assert [(r["step"], r["train/loss"]) for r in rows] == [
        ("0", "0.0"), ("1", "1.0"), ("2", "2.0"), ("3", "3.0"), ("4", "4.0"), ("", "9.9"),
        ("5", "5.5"), ("6", "6.5"), ("7", "7.5"),
    ]  # fmt: skip


def test_counts_that_are_not_whole_numbers_are_named(tmp_path, dataset_dir):
    """A fraction, a NaN, a string or a count below its range in a count key stops the run before anything is built
    (was: a TypeError or ValueError traceback from the loaders or Lightning, accumulate_grad_batches=0 a
    ZeroDivisionError after the model had loaded, and PRO's data.limit_val=0 validated on training videos)."""
    cases = [
        (["data.num_frames=1.5"], r"data.num_frames = 1.5: must be >= 1 \(a whole number\)$"),
        (["data.num_frames=abc"], r"data.num_frames = 'abc': must be >= 1 \(a whole number\)$"),
        (["data.batch_size=nan"], r"data.batch_size = nan: must be >= 1 \(a whole number\)$"),
        (["data.num_workers=1.5"], r"data.num_workers = 1.5: must be >= 0 \(a whole number, or null\)"),
        (
            ["trainer.accumulate_grad_batches=0"],
            r"trainer.accumulate_grad_batches = 0: must be >= 1 \(a whole number\)",
        ),
        (["trainer.accumulate_grad_batches=1.5"], r"accumulate_grad_batches = 1.5: must be >= 1 \(a whole number\)"),
        (["stage=pro", "data.limit_val=0"], r"data.limit_val = 0: must be >= 1 \(a whole number, or null\)"),
        (["stage=pro", "data.limit_train=-1"], r"data.limit_train = -1: must be >= 1 \(a whole number, or null\)"),
    ]
    for overrides, message in cases:
        with pytest.raises(ValueError, match=message):
            train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", *overrides))
        assert not (tmp_path / "x").exists()  # before the run folder is made


def test_optimizer_and_clipping_values_that_cannot_work_are_named(tmp_path, dataset_dir):
    """AdamW betas outside [0, 1) failed in torch once the model had loaded (a traceback), a NaN
    trainer.gradient_clip_val with Lightning's misleading "use only one of them", and a negative one turned
    clipping off without a word."""
    from hydra.errors import InstantiationException

    cases = [
        (["stage.module.betas=[2,0]"], r"stage.module.betas = \[2, 0\]: need two numbers in \[0, 1\)"),
        (["stage.module.betas=[0.9]"], r"stage.module.betas = \[0.9\]: need two numbers"),
        (["trainer.gradient_clip_val=nan"], r"trainer.gradient_clip_val = nan: must be a finite number >= 0"),
        (["trainer.gradient_clip_val=-1"], r"trainer.gradient_clip_val = -1: must be a finite number >= 0"),
    ]
    for overrides, message in cases:
        with pytest.raises((ValueError, InstantiationException), match=message):
            train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", "callbacks.evaluation=null", *overrides))


def test_a_refused_run_leaves_the_earlier_runs_hydra_record(tmp_path):
    """A fresh run into a folder holding an earlier run is refused, and that run's `.hydra/` (its settings, whose
    overrides.yaml `aynamics collect` shows as the run's columns) is left as it was: Hydra wrote the refused
    command's settings over it before train.py could refuse. A run that fails in a new folder still gets its
    `.hydra/overrides.yaml`, as Hydra wrote it (collect lists it as failed, with its overrides)."""
    from aynamics.collect import collect

    out = tmp_path / "run"
    (out / ".hydra").mkdir(parents=True)
    (out / "metrics.json").write_text(json.dumps({"metrics": {}, "global_step": 4, "config": {}}))
    record = "- trainer.max_steps=4\n"
    (out / ".hydra" / "overrides.yaml").write_text(record)
    cmd = [sys.executable, "train.py", "data.modality=flow", "trainer.max_steps=8", f"hydra.run.dir={out}"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=_one_thread())
    assert done.returncode == 2 and "holds an earlier run" in done.stderr, done.stderr[-3000:]
    assert (out / ".hydra" / "overrides.yaml").read_text() == record
    assert sorted(p.name for p in (out / ".hydra").iterdir()) == ["overrides.yaml"]
    assert collect(out)[0]["trainer.max_steps"] == "4"

    new = tmp_path / "new"
    cmd = [sys.executable, "train.py", "trainer.max_steps=0", f"hydra.run.dir={new}"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=_one_thread())
    assert done.returncode == 2 and "trainer.max_steps = 0" in done.stderr, done.stderr[-3000:]
    assert sorted(p.name for p in (new / ".hydra").iterdir()) == ["config.yaml", "hydra.yaml", "overrides.yaml"]
    assert (new / ".hydra" / "overrides.yaml").read_text() == "- trainer.max_steps=0\n"
    assert "max_steps: 0" in (new / ".hydra" / "config.yaml").read_text()
    assert collect(new)[0]["status"] == "failed (train.log)"


def test_a_run_shorter_than_the_logging_interval_logs_its_last_step(tmp_path, dataset_dir):
    """3 steps under the default `trainer.log_every_n_steps` of 5 log step 3's training metrics (csv/metrics.csv
    held its header only: Lightning logs every 5th step); a longer run keeps the configured interval."""
    out = tmp_path / "run"
    train(_cfg(out, f"data.dir={dataset_dir}", "trainer.max_steps=3", "logger=csv", "callbacks.evaluation=null"))
    with open(out / "csv" / "metrics.csv") as f:
        rows = [row for row in csv.DictReader(f) if row.get("train/loss")]
    assert [int(row["step"]) for row in rows] == [2] and math.isfinite(float(rows[0]["train/loss"]))
    out = tmp_path / "longer"
    train(_cfg(out, f"data.dir={dataset_dir}", "trainer.max_steps=6", "logger=csv", "callbacks.evaluation=null"))
    with open(out / "csv" / "metrics.csv") as f:
        assert [int(row["step"]) for row in csv.DictReader(f) if row.get("train/loss")] == [4]


def test_run_steps_counts_an_epoch_limited_runs_optimizer_steps():
    """By hand: SFT, 10 training records cut to data.limit_train = 7, 2 processes (4 each), batches of 2: 2
    batches an epoch, 1 optimizer step with accumulation 2, 3 over 3 epochs. PRO, 5 videos in batches of 2: 3
    batches; Lightning's limit_train_batches 0.5 keeps int(1.5) = 1, 2 keeps 2; with 3 epochs and accumulation 2,
    each epoch steps ceil(3 / 2) = 2 times (its last batch steps too): 6. No epoch limit or no known data: None."""
    from types import SimpleNamespace

    from train import epoch_batches, run_steps

    sft = SimpleNamespace(splits={"train": range(10)}, limit_train=7, batch_size=2)
    pro = SimpleNamespace(train_set=range(5), hparams=SimpleNamespace(batch_size=2))

    def trainer(world=1, limit=1.0, epochs=3):
        return SimpleNamespace(world_size=world, limit_train_batches=limit, max_epochs=epochs)

    assert epoch_batches(sft, trainer(world=2)) == 2 and run_steps(sft, trainer(world=2), 2) == 3
    assert [epoch_batches(pro, trainer(limit=x)) for x in (1.0, 0.5, 2, 10)] == [3, 1, 2, 3]
    assert run_steps(pro, trainer(), 2) == 6 and run_steps(pro, trainer(), 1) == 9
    assert run_steps(pro, trainer(epochs=-1), 1) is None and run_steps(SimpleNamespace(), trainer(), 1) is None


def test_an_epoch_limited_run_shorter_than_the_logging_interval_logs_its_last_step(tmp_path, dataset_dir):
    """`trainer.max_steps=-1` with `trainer.max_epochs=2` over 6 examples in batches of 2, 2 at a time: each epoch
    is ceil(3 / 2) = 2 optimizer steps (Lightning steps on the epoch's last batch too), 4 in all, under the interval
    of 5, so step 4 (index 3) logs its training metrics; csv/metrics.csv held its header only before."""
    out = tmp_path / "run"
    overrides = ["trainer.max_steps=-1", "trainer.max_epochs=2", "data.limit_train=6", "data.batch_size=2"]
    overrides += ["trainer.accumulate_grad_batches=2", "trainer.val_check_interval=null", "logger=csv"]
    train(_cfg(out, f"data.dir={dataset_dir}", *overrides, "callbacks.evaluation=null"))
    with open(out / "csv" / "metrics.csv") as f:
        rows = [row for row in csv.DictReader(f) if row.get("train/loss")]
    assert [int(row["step"]) for row in rows] == [3] and math.isfinite(float(rows[0]["train/loss"]))


def test_epochs_shorter_than_the_logging_interval_log_over_the_run_without_lightnings_warning(tmp_path, dataset_dir):
    """3 epochs of 2 steps (4 examples in batches of 2) under the interval of 5: Lightning counts the interval over
    the run's steps, so step 5 (index 4, in the third epoch) logs its training metrics, and its warning that "the
    number of training batches (2) is smaller than the logging interval" (shown on every such run) is not shown."""
    out = tmp_path / "run"
    overrides = ["trainer.max_steps=-1", "trainer.max_epochs=3", "data.limit_train=4", "data.batch_size=2"]
    overrides += ["trainer.val_check_interval=null", "logger=csv", "callbacks.evaluation=null"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train(_cfg(out, f"data.dir={dataset_dir}", *overrides))
    assert not [w for w in caught if "logging interval" in str(w.message)]
    with open(out / "csv" / "metrics.csv") as f:
        rows = [row for row in csv.DictReader(f) if row.get("train/loss")]
    assert [(int(row["step"]), int(row["epoch"])) for row in rows] == [(4, 2)]


def test_train_shows_the_steps_bar_and_logs_a_short_run_with_lightnings_defaults(tmp_path, dataset_dir, monkeypatch):
    """train.py puts `StepsProgressBar` on the trainer ("Epoch 0", not "Epoch 0/-2") also where
    `trainer.enable_progress_bar` is null (Lightning's default: a bar), and a run shorter than a null
    `trainer.log_every_n_steps` (Lightning's 50) logs its last step's training metrics."""
    from lightning.pytorch.callbacks import RichProgressBar

    seen = []
    start = RichProgressBar.on_train_epoch_start

    def look(self, trainer, *args):
        seen.append((type(self).__name__, self._get_train_description(trainer.current_epoch).rstrip()))
        return start(self, trainer, *args)

    monkeypatch.setattr(RichProgressBar, "on_train_epoch_start", look)
    out = tmp_path / "run"
    overrides = ["trainer.max_steps=2", "logger=csv", "callbacks.evaluation=null", "trainer.enable_progress_bar=null"]
    train(_cfg(out, f"data.dir={dataset_dir}", *overrides, "trainer.log_every_n_steps=null"))
    assert seen == [("StepsProgressBar", "Epoch 0")]
    with open(out / "csv" / "metrics.csv") as f:
        assert [int(row["step"]) for row in csv.DictReader(f) if row.get("train/loss")] == [1]


def test_a_run_that_both_limits_end_by_its_epochs_logs_its_last_step(tmp_path, dataset_dir):
    """`trainer.max_steps=200` (more than the run takes) with `trainer.max_epochs=2`: the epochs end the run after
    4 optimizer steps, under the interval of 5, so step 4 (index 3) logs its training metrics."""
    out = tmp_path / "run"
    overrides = ["trainer.max_steps=200", "trainer.max_epochs=2", "data.limit_train=6", "data.batch_size=2"]
    overrides += ["trainer.accumulate_grad_batches=2", "trainer.val_check_interval=null", "logger=csv"]
    train(_cfg(out, f"data.dir={dataset_dir}", *overrides, "callbacks.evaluation=null"))
    with open(out / "csv" / "metrics.csv") as f:
        rows = [row for row in csv.DictReader(f) if row.get("train/loss")]
    assert [int(row["step"]) for row in rows] == [3] and math.isfinite(float(rows[0]["train/loss"]))


def test_a_model_config_error_is_not_named_as_a_stage_module_key(tmp_path, dataset_dir):
    """The model is built inside the module's constructor: "lora dropout = 1.5" (model.lora_dropout) read
    "... (config: stage.module)" and model.tiny.hidden_size "stage.module.hidden_size = 62"."""
    from hydra.errors import InstantiationException

    from train import input_error_message

    # the model config's values are refused with the spec, before the data and the model load, named in full: 0
    # heads was a ZeroDivisionError traceback inside tiny_config, an unknown key a TypeError, a negative width
    # torch's own; "lora dropout = 1.5" and "LoRA target_modules = []" came once the base had loaded
    for override, message in [
        ("model.lora_dropout=1.5", "model.lora_dropout = 1.5: must be a number in [0, 1)"),
        ("model.lora_targets=[]", "model.lora_targets = []: must be a list of projection names"),
        ("model.tiny.hidden_size=62", "model.tiny.hidden_size = 62, model.tiny.num_heads = 4: head_dim must be"),
        ("model.tiny.num_heads=0", "model.tiny.num_heads = 0: must be a whole number >= 1"),
        ("model.tiny.hidden_size=-64", "model.tiny.hidden_size = -64: must be a whole number >= 1"),
        ("+model.tiny.foo=1", "model.tiny.foo = 1: not a size of the tiny model"),
    ]:
        with pytest.raises(InstantiationException) as caught:
            train(_cfg(tmp_path / "x", f"data.dir={dataset_dir}", "callbacks.evaluation=null", override))
        assert input_error_message(caught.value) == str(caught.value.__cause__)  # no "(config: model)" after it
        assert str(caught.value.__cause__).startswith(message)
    # a misspelt target beside a right one trained without it, without a word
    with pytest.raises(ValueError, match=r"^model.lora_targets = \['q_proj', 'vproj'\]: \['vproj'\] names no linear"):
        train(
            _cfg(
                tmp_path / "x",
                f"data.dir={dataset_dir}",
                "callbacks.evaluation=null",
                "model.lora_targets=[q_proj,vproj]",
            )
        )


def test_a_run_folder_that_is_a_file_is_named(tmp_path):
    """hydra.run.dir naming a file (or a folder below one) failed in Hydra's own mkdir with a FileExistsError
    traceback naming no key (helper-109); now status 2 and one line, before Hydra starts."""
    from train import refuse_file_output_dir

    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    folder = "give a folder for the run's outputs"
    assert refuse_file_output_dir([f"hydra.run.dir={afile}"]) == f"hydra.run.dir = {str(afile)!r} is a file: {folder}"
    below = refuse_file_output_dir(["stage=sft", f"hydra.sweep.dir={afile / 'x'}"])
    assert below == f"hydra.sweep.dir = {str(afile / 'x')!r} is below the file {str(afile)!r}: {folder}"
    assert refuse_file_output_dir([f"hydra.run.dir={tmp_path / 'new'}", f"data.dir={afile}"]) is None
    done = subprocess.run(
        [sys.executable, "train.py", f"hydra.run.dir={afile}"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2 and done.stderr.strip().endswith("is a file: give a folder for the run's outputs")
    assert "Traceback" not in done.stderr and afile.read_text() == "mine"


def test_gradient_accumulation_trains_the_token_mean_of_the_step(dataset_dir):
    """The first two training scenes of the epoch's order, of different response lengths: one optimizer step over
    them as one batch, or as two batches with accumulate_grad_batches=2, takes the gradient of sum(nll) / n over
    the step's n response tokens both ways (and a shorter last window of an epoch counts its own tokens). Each
    micro-batch's own mean, divided by 2 as Lightning does, gave (mean_1 + mean_2) / 2 instead: the tokens of the
    shorter response weighed more (and alike across ddp processes)."""
    import lightning as L

    class Grad(L.Callback):
        def on_before_optimizer_step(self, trainer, module, optimizer):
            self.grad = torch.cat([p.grad.flatten() for p in module.parameters() if p.grad is not None])

    spec = lm.ModelSpec(kind="tiny", lora_rank=8, lora_alpha=16.0, lora_dropout=0.0)

    def step_gradient(batch_size: int, accumulate: int) -> tuple[torch.Tensor, list[int]]:
        dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=batch_size)
        torch.manual_seed(0)  # the same LoRA initialisation
        module, grad = SFTModule(spec), Grad()
        trainer = L.Trainer(
            max_steps=1,
            accumulate_grad_batches=accumulate,
            accelerator="cpu",
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
            limit_val_batches=0,
            callbacks=[grad],
        )
        trainer.fit(module, datamodule=dm)
        order = dm.train_dataloader().sampler._order()[:2]  # epoch 0's
        tokens = [int((dm.dataset("train")[i]["labels"] != -100).sum()) for i in order]
        return grad.grad, tokens

    whole, tokens = step_gradient(2, 1)
    accumulated, same = step_gradient(1, 2)
    assert tokens == same and tokens[0] != tokens[1]  # the same two scenes, of different lengths
    torch.testing.assert_close(accumulated, whole, rtol=1e-4, atol=1e-6)
    # the loader's windows: 2 batches a step, a shorter last window at the epoch's end
    from aynamics.batching import window_weight, with_window_weights

    batches = [
        {"input_ids": torch.zeros(1, n + 1, dtype=torch.long), "labels": torch.tensor([[-100] + [1] * n])}
        for n in (4, 45, 7)
    ]
    assert [window_weight(b).item() for b in with_window_weights(batches, 2)] == [49.0, 49.0, 7.0]
    assert "window_weight_bits" not in model_inputs(next(with_window_weights(batches, 2)))


def test_a_step_cut_short_by_limit_train_batches_is_the_mean_of_its_own_tokens(tmp_path):
    """Six one-example batches of 3..17 response tokens, each token's nll (θ - 1)²/2 at θ = 0: every step's
    token-mean gradient is -1 whatever its tokens. With accumulate_grad_batches=2 and limit_train_batches=3,
    Lightning's epoch steps on batches {0, 1} and {2}; the loader's window for batch 2 held batch 3's tokens too
    (gradient -w2 / (w2 + w3), -0.79 for this order). Resumed after step 3 (mid-epoch 1), the run trains the
    batch and gradient an uninterrupted run does (it skipped by the whole epoch's length: another batch, -0.23)."""
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint

    from aynamics.loaders import resumable_loader

    tokens = [3, 5, 7, 11, 13, 17]
    rows = [
        {"input_ids": torch.zeros(n + 1, dtype=torch.long), "labels": torch.tensor([-100] + [1] * n)} for n in tokens
    ]

    class Tiny(L.LightningModule):
        _step_mean = SFTModule._step_mean

        def __init__(self):
            super().__init__()
            self.theta = torch.nn.Parameter(torch.zeros(()))
            self.grads, self.seen = [], []

        def train_dataloader(self):
            collate = lambda b: {k: torch.stack([r[k] for r in b]) for k in b[0]}  # noqa: E731
            return resumable_loader(rows, self.trainer, batch_size=1, seed=0, collate_fn=collate, window_weights=True)

        def training_step(self, batch, batch_idx):
            mask = batch["labels"][:, 1:] != -100
            self.seen.append(int(mask.sum()))
            loss = (0.5 * (self.theta - batch["labels"][:, 1:].float()) ** 2 * mask).sum() / mask.sum()
            return self._step_mean(loss, batch)

        def on_before_optimizer_step(self, optimizer):
            self.grads.append(float(self.theta.grad))

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.0)

    def fit(module, callbacks=(), ckpt_path=None):
        L.Trainer(
            max_steps=4, accumulate_grad_batches=2, limit_train_batches=3, accelerator="cpu", logger=False,
            enable_checkpointing=bool(callbacks), callbacks=list(callbacks), default_root_dir=tmp_path,
            enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
        ).fit(module, ckpt_path=ckpt_path)  # fmt: skip
        return module

    each = ModelCheckpoint(tmp_path, every_n_train_steps=1, save_top_k=-1, filename="{step}")
    whole = fit(Tiny(), [each])
    assert whole.grads == pytest.approx([-1.0] * 4)
    resumed = fit(Tiny(), ckpt_path=tmp_path / "step=3.ckpt")
    assert resumed.seen == whole.seen[-1:] and resumed.grads == pytest.approx([-1.0])
