"""Work and results survive an interruption or a re-run: a fresh run into an earlier run's folder, a run stopped in
its final validation, a checkpoint, an adapter folder and an evaluation's files each interrupted while written."""

from __future__ import annotations

import errno
import json
import sys

import lightning as L
import pytest
import torch
from train_fixtures import ROOT, tiny_dataset, train_cfg

from aynamics import lm

sys.path.insert(0, str(ROOT))
_cfg = train_cfg


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return tiny_dataset(tmp_path_factory)


class FailInValidation(L.Callback):
    """Stops the run (as a kill would) in the validation of step `step`, after that step's checkpoint."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_validation_batch_start(self, trainer, *args) -> None:
        if trainer.global_step == self.step and not trainer.sanity_checking:
            raise RuntimeError("killed")


def test_a_fresh_run_into_an_earlier_runs_folder_is_refused(tmp_path, dataset_dir):
    """It versioned its checkpoints as last-v1.ckpt beside the earlier run's last.ckpt, which train.py's SIGTERM
    message named (resuming it resumed the other run), and overwrote the earlier adapter and predictions."""
    from train import train

    run = [f"data.dir={dataset_dir}", "callbacks.evaluation=null", "trainer.val_check_interval=null"]
    out = tmp_path / "run"
    train(_cfg(out, *run, "trainer.max_steps=1"))
    adapter = (out / "adapter" / "adapter_model.safetensors").read_bytes()
    with pytest.raises(ValueError, match=r"holds an earlier run \(.*last\.ckpt\): resume it with ckpt_path"):
        train(_cfg(out, *run, "trainer.max_steps=2", "stage.module.lr=5e-4"))
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["last.ckpt", "step000001.ckpt"]
    assert (out / "adapter" / "adapter_model.safetensors").read_bytes() == adapter
    train(_cfg(out, *run, "trainer.max_steps=2", f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}"))  # resumes


def test_a_run_stopped_in_its_final_validation_resumes_to_its_results(tmp_path, dataset_dir):
    """The last step is saved before its validation, which a resumed run skips: resuming trained nothing, said
    'metrics.json left as it was' and never wrote metrics.json, the table or the step's predictions."""
    from train import train

    run = [f"data.dir={dataset_dir}", "trainer.max_steps=2", "trainer.val_check_interval=2"]
    run += ["callbacks.evaluation.num_samples=1", "callbacks.evaluation.max_new_tokens=4"]
    run += ["callbacks.evaluation.num_animations=0"]
    out = tmp_path / "run"
    stop = ["+callbacks.stop._target_=test_interrupted_writes.FailInValidation", "+callbacks.stop.step=2"]
    with pytest.raises(RuntimeError, match="killed"):
        train(_cfg(out, *run, *stop))
    assert not (out / "metrics.json").exists() and (out / "checkpoints" / "last.ckpt").is_file()
    metrics = train(_cfg(out, *run, f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}"))
    record = json.loads((out / "metrics.json").read_text())
    assert (record["global_step"], record["val_step"]) == (2, 2) and "val/yaml_valid" in metrics
    assert (out / "eval" / "predictions_step000002.jsonl").is_file()
    before = (out / "metrics.json").read_text()  # a finished run resumed again: left as it was
    train(_cfg(out, *run, f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}"))
    assert (out / "metrics.json").read_text() == before


def test_a_checkpoint_interrupted_while_written_leaves_the_previous_one(tmp_path, monkeypatch):
    """Lightning's writer copied over the final path when $TMPDIR is on another filesystem (truncating it first):
    a kill or a full disk mid-copy left an empty last.ckpt where the previous good one was."""
    from aynamics.callbacks import AtomicCheckpointIO

    path = tmp_path / "checkpoints" / "last.ckpt"
    io = AtomicCheckpointIO()
    io.save_checkpoint({"global_step": 1}, path)
    real = torch.save

    def full_disk(obj, f, *args, **kwargs):
        f.write(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(OSError):
        io.save_checkpoint({"global_step": 2}, path)
    monkeypatch.setattr(torch, "save", real)
    assert torch.load(path, weights_only=True)["global_step"] == 1
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.ckpt"]


def test_an_adapter_folder_is_replaced_whole(tmp_path, monkeypatch):
    """Rewritten file by file, an interrupted `export-adapter` (or training's export) left one checkpoint's weights
    with another's aynamics.json, a folder that loads without a word under the wrong prompt."""
    spec = lm.ModelSpec(kind="tiny")
    model = lm.build_model(spec)
    out = tmp_path / "adapter"
    lm.save_adapter(model, out, spec, lm.PromptSpec(num_frames=2))
    (out / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with torch.no_grad():
        next(p for n, p in model.named_parameters() if "lora_B" in n).add_(1.0)

    def dying(spec, prompt):
        raise KeyboardInterrupt  # a kill after the weights were written, before aynamics.json

    monkeypatch.setattr(lm, "adapter_meta", dying)
    with pytest.raises(KeyboardInterrupt):
        lm.save_adapter(model, out, spec, lm.PromptSpec(num_frames=4))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    monkeypatch.undo()
    lm.save_adapter(model, out, spec, lm.PromptSpec(num_frames=4))
    assert json.loads((out / "aynamics.json").read_text())["prompt"]["num_frames"] == 4
    assert (out / "notes.txt").read_text() == "mine" and (out / "adapter_model.safetensors").read_bytes() != before[
        "adapter_model.safetensors"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adapter"]


def _evaluation(index: int):
    """A one-record evaluation of record `index` (`evaluate.write_evaluation`'s input)."""
    from aynamics import evaluate as ev

    per = {"yaml_valid": [1.0], "reason": [None]}
    return ev.Evaluation({"model": {"yaml_valid": 1.0}}, [{"index": index, "scene_yaml": "x"}], ["t"], per)


def test_an_evaluation_folder_never_pairs_two_evaluations(tmp_path, monkeypatch):
    """`evaluate --out` into an earlier evaluation's folder replaced predictions.jsonl, then metrics.json: stopped
    between them, the new predictions sat beside the old metrics.json (its split, adapter and numbers)."""
    from aynamics import evaluate as ev

    out = tmp_path / "eval"
    ev.write_evaluation(out, _evaluation(1), {"split": "test"})
    real = ev.write_predictions

    def dying(path, *args):
        real(path, *args)
        raise KeyboardInterrupt  # a kill after predictions.jsonl

    monkeypatch.setattr(ev, "write_predictions", dying)
    with pytest.raises(KeyboardInterrupt):
        ev.write_evaluation(out, _evaluation(2), {"split": "validation"})
    if (out / "metrics.json").exists():  # then both files are one evaluation's
        rows = [json.loads(line) for line in (out / "predictions.jsonl").read_text().splitlines()]
        split = json.loads((out / "metrics.json").read_text())["settings"]["split"]
        assert (split, rows[0]["index"]) in {("test", 1), ("validation", 2)}
    monkeypatch.undo()
    ev.write_evaluation(out, _evaluation(2), {"split": "validation"})
    assert json.loads((out / "metrics.json").read_text())["settings"]["split"] == "validation"


def test_an_evaluation_stopped_after_its_predictions_or_inside_its_metrics_leaves_no_metrics_json(
    tmp_path, monkeypatch
):
    """Stopped right after the new predictions.jsonl is in place, the earlier evaluation's metrics.json is already
    gone (deleted first: it would stand beside the new predictions); stopped half-way through writing metrics.json,
    no half-written metrics.json is left (it is written beside and renamed whole)."""
    import os
    from pathlib import Path

    from aynamics import evaluate as ev

    out = tmp_path / "eval"
    ev.write_evaluation(out, _evaluation(1), {"split": "test"})
    real = os.replace

    def dying_after_predictions(src, dst):
        real(src, dst)
        if Path(dst).name == "predictions.jsonl":
            raise KeyboardInterrupt

    monkeypatch.setattr(ev.os, "replace", dying_after_predictions)
    with pytest.raises(KeyboardInterrupt):
        ev.write_evaluation(out, _evaluation(2), {"split": "validation"})
    monkeypatch.undo()
    assert json.loads((out / "predictions.jsonl").read_text())["index"] == 2
    assert not (out / "metrics.json").exists()

    ev.write_evaluation(out, _evaluation(3), {"split": "train"})

    def half(self, text, *args, **kwargs):  # a kill half-way through the write
        with open(self, "w") as f:
            f.write(text[: len(text) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "write_text", half)
    with pytest.raises(KeyboardInterrupt):
        ev.write_evaluation(out, _evaluation(4), {"split": "validation"})
    monkeypatch.undo()
    assert not (out / "metrics.json").exists()
