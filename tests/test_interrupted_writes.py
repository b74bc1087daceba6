"""Work and results survive an interruption or a re-run: a fresh run into an earlier run's folder, a run stopped in
its final validation, a checkpoint, an adapter folder and an evaluation's files each interrupted while written."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import lightning as L
import pytest
import torch
from train_fixtures import ROOT, tiny_dataset, train_cfg

from aynamics import adapters, lm

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
    from aynamics.run_callbacks import AtomicCheckpointIO

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
    # a kill mid-write leaves its .last.ckpt.tmp-PID (a whole checkpoint's size): the next write deletes those of
    # processes that are gone, and keeps a live writer's and files of other names
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    leftovers = [f".last.ckpt.tmp-{int(dead.stdout)}", f".last.ckpt.tmp-{os.getppid()}", ".last.ckpt.tmp-mine"]
    for name in [*leftovers, ".other.ckpt.tmp-99999999"]:
        (path.parent / name).write_bytes(b"partial")
    io.save_checkpoint({"global_step": 3}, path)
    assert torch.load(path, weights_only=True)["global_step"] == 3
    assert sorted(p.name for p in path.parent.iterdir()) == sorted(
        [*leftovers[1:], ".other.ckpt.tmp-99999999", "last.ckpt"]
    )


def test_an_adapter_folder_is_replaced_whole(tmp_path, monkeypatch):
    """Rewritten file by file, an interrupted `export-adapter` (or training's export) left one checkpoint's weights
    with another's aynamics.json, a folder that loads without a word under the wrong prompt."""
    spec = lm.ModelSpec(kind="tiny")
    model = lm.build_model(spec)
    out = tmp_path / "adapter"
    adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=2))
    (out / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with torch.no_grad():
        next(p for n, p in model.named_parameters() if "lora_B" in n).add_(1.0)

    def dying(spec, prompt):
        raise KeyboardInterrupt  # a kill after the weights were written, before aynamics.json

    monkeypatch.setattr(adapters, "adapter_meta", dying)
    with pytest.raises(KeyboardInterrupt):
        adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=4))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    monkeypatch.undo()
    adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=4))
    assert json.loads((out / "aynamics.json").read_text())["prompt"]["num_frames"] == 4
    assert (out / "notes.txt").read_text() == "mine" and (out / "adapter_model.safetensors").read_bytes() != before[
        "adapter_model.safetensors"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".adapter.lock", "adapter"]


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


def _preference_rows(key: str) -> list[dict]:
    from PIL import Image

    return [
        {
            "key": key,
            "frames": [Image.new("RGB", (2, 2))],
            "completions": ["a", "b"],
            "completion_ids": [[1], [2]],
            "rewards": [1.0, 0.0],
            "reasons": [None, None],
            "case_rewards": [1.0, 0.0],
        }
    ]


def test_a_preference_set_killed_between_its_renames_is_put_back_and_leftovers_go(tmp_path, monkeypatch):
    """`write_preferences` moves the earlier set to `.OUT.old-*`, then renames its new one (`.OUT.tmp-*`) to OUT: a
    kill between the two left no OUT, the earlier set only under its hidden name, and both folders for good (the
    next write made OUT anew beside them). The next write now puts the earlier set back first (so that, failing
    on a full disk here, it leaves OUT as it was), and once its own set is in place deletes the `.OUT.tmp-*` and
    `.OUT.old-*` folders of earlier writes; a folder of the user's named alike (other characters, or holding
    other files) and another OUT's stay."""
    import datasets

    from aynamics.preference_data import load_preferences, write_preferences

    out = tmp_path / "prefs"
    write_preferences(_preference_rows("v1"), {"v": 1}, out)
    real_rename = Path.rename

    def killed(self, target):  # SIGKILL after OUT was moved aside, before the new set took its place
        if ".tmp-" in self.name:
            raise KeyboardInterrupt
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", killed)
    with pytest.raises(KeyboardInterrupt):
        write_preferences(_preference_rows("v2"), {"v": 2}, out)
    monkeypatch.undo()
    assert not out.exists()
    assert len(list(tmp_path.glob(".prefs.old-*"))) == len(list(tmp_path.glob(".prefs.tmp-*"))) == 1

    def full(self, path, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(datasets.Dataset, "save_to_disk", full)
    with pytest.raises(OSError, match="No space left"):
        write_preferences(_preference_rows("v3"), {"v": 3}, out)
    monkeypatch.undo()
    assert load_preferences(out)["key"] == ["v1"] and json.loads((out / "summary.json").read_text()) == {"v": 1}

    for name in (".prefs.tmp-mine", ".prefs.old-abcd1234", ".other.tmp-abcd1234"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "notes.txt").write_text("mine")
    (tmp_path / ".prefs.old-abcd1234" / "state.json").write_text("{}")
    write_preferences(_preference_rows("v3"), {"v": 3}, out)
    assert load_preferences(out)["key"] == ["v3"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        ".other.tmp-abcd1234",
        ".prefs.old-abcd1234",
        ".prefs.tmp-mine",
        "prefs",
    ]


def test_a_users_copies_of_a_preference_set_beside_it_stay(tmp_path):
    """A user's copies of the set `prefs`, named `prefs.old-20240101` and `prefs.tmp-backup01` (8 characters after
    the dash, as `tempfile.mkdtemp` draws, and nothing but a preference set's files), were taken for leftovers of
    killed writes: the next write deleted both, and with `prefs` gone it first renamed the copy to `prefs` and
    then replaced it. The writes' own folders are hidden now (`.prefs.tmp-*`, `.prefs.old-*`); the copies stay,
    each still holding its set (v1), and `prefs` holds the new one (v2, then v3)."""
    import shutil

    from aynamics.preference_data import load_preferences, write_preferences

    out = tmp_path / "prefs"
    write_preferences(_preference_rows("v1"), {"v": 1}, out)
    copies = [tmp_path / "prefs.old-20240101", tmp_path / "prefs.tmp-backup01"]
    for copy in copies:
        shutil.copytree(out, copy)
    write_preferences(_preference_rows("v2"), {"v": 2}, out)
    assert load_preferences(out)["key"] == ["v2"]
    assert [load_preferences(copy)["key"] for copy in copies] == [["v1"], ["v1"]]
    shutil.rmtree(out)
    write_preferences(_preference_rows("v3"), {"v": 3}, out)
    assert load_preferences(out)["key"] == ["v3"]
    assert [load_preferences(copy)["key"] for copy in copies] == [["v1"], ["v1"]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prefs", "prefs.old-20240101", "prefs.tmp-backup01"]


def test_an_adapter_write_killed_midway_is_finished_by_the_next(tmp_path, monkeypatch):
    """`save_adapter` writes `.adapter.tmp-PID`, moves the user's files into it, moves `adapter` aside to
    `.adapter.old-PID` and renames the new one in; each write removed only its own process's leftovers. Killed
    between the renames (here: renamed as another process's), the next write left no `adapter` until it ended,
    and deleted nothing: the user's notes.txt stayed hidden in the new adapter's folder. Now the next write first
    finishes that swap (failing at once here, it leaves the killed write's adapter, notes.txt in it). Killed
    while moving the user's files (a `.tmp-PID` with aynamics.json and notes.txt), the next write moves them back.
    Folders of other names stay; the one lock file is left beside."""
    import os
    import shutil

    spec = lm.ModelSpec(kind="tiny")
    model = lm.build_model(spec)
    out = tmp_path / "adapter"
    adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=2))
    (out / "notes.txt").write_text("mine")
    real_replace = os.replace

    def killed(src, dst):  # SIGKILL after the earlier adapter was moved aside
        if Path(src).name.startswith(".adapter.tmp-"):
            raise KeyboardInterrupt
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=4))
    monkeypatch.undo()
    for kind in ("tmp", "old"):  # as another process left them
        (tmp_path / f".adapter.{kind}-{os.getpid()}").rename(tmp_path / f".adapter.{kind}-999999")
    (tmp_path / ".adapter.tmp-mine").mkdir()
    assert not out.exists() and (tmp_path / ".adapter.tmp-999999" / "notes.txt").is_file()

    def dying(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(type(model), "save_pretrained", dying)
    with pytest.raises(KeyboardInterrupt):
        adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=8))
    monkeypatch.undo()
    assert json.loads((out / adapters.ADAPTER_META).read_text())["prompt"]["num_frames"] == 4
    assert (out / "notes.txt").read_text() == "mine"

    moving = tmp_path / ".adapter.tmp-888888"  # killed while moving the user's files into its new adapter
    shutil.copytree(out, moving)
    (out / "notes.txt").rename(moving / "notes.txt")
    adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=8))
    assert json.loads((out / adapters.ADAPTER_META).read_text())["prompt"]["num_frames"] == 8
    assert (out / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".adapter.lock", ".adapter.tmp-mine", "adapter"]


def test_an_adapter_is_written_on_a_file_system_without_locks(tmp_path, monkeypatch):
    """`save_adapter` takes a lock beside the folder (`.adapter.lock`); where the file system has none (`flock`
    fails with ENOLCK: NFS without its lock daemon; ENOSYS: Lustre mounted noflock) every checkpoint of a training
    run failed with OSError, where before the lock it wrote. It writes unlocked there, as before: the adapter is
    replaced (num_frames 2, then 4), the user's notes.txt stays in it, and another process's `.adapter.tmp-PID`
    (perhaps a live writer's: nothing says otherwise without the lock) is left alone."""
    import fcntl
    import os

    def no_locks(*args):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(fcntl, "flock", no_locks)
    spec = lm.ModelSpec(kind="tiny")
    model = lm.build_model(spec)
    out = tmp_path / "adapter"
    adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=2))
    (out / "notes.txt").write_text("mine")
    (tmp_path / ".adapter.tmp-999999").mkdir()
    adapters.save_adapter(model, out, spec, lm.PromptSpec(num_frames=4))
    assert json.loads((out / adapters.ADAPTER_META).read_text())["prompt"]["num_frames"] == 4
    assert (out / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".adapter.lock", ".adapter.tmp-999999", "adapter"]


def test_an_evaluations_temporary_files_left_by_a_kill_are_removed_by_the_next(tmp_path):
    """A kill while `write_evaluation` wrote left `.predictions.jsonl.tmp-PID` (or `.metrics.json.tmp-PID`) in the
    folder, which no later write removed (each knew only its own process's name). The next write removes them
    once its pair is in place; files of other names stay."""
    from aynamics import evaluate as ev

    out = tmp_path / "eval"
    out.mkdir()
    for name in (".predictions.jsonl.tmp-999999", ".metrics.json.tmp-999998", ".metrics.json.tmp-mine", "a.tmp-1"):
        (out / name).write_text("half")
    ev.write_evaluation(out, _evaluation(1), {"split": "test"})
    kept = [".metrics.json.tmp-mine", "a.tmp-1", "metrics.json", "predictions.jsonl"]
    assert sorted(p.name for p in out.iterdir()) == kept
