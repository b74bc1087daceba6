"""Evaluation metrics of generated scenes, the table, the animation, predict and collect."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from aynamics.callbacks import METRIC_KEYS, evaluate_texts, format_table, side_by_side, summarize
from aynamics.collect import DEFAULT_METRICS, collect, to_markdown
from aynamics.observation import Observation
from aynamics.scene import dump, load
from aynamics.scorer import EPE_INVALID

ASSET = Path(__file__).parent / "assets" / "paper_example.yaml"


@pytest.fixture(scope="module")
def truth():
    scene = load(str(ASSET))
    return scene, Observation.from_scene(scene)


def test_true_scene_scores_perfectly_and_garbage_scores_invalid(truth):
    """The true YAML (in answer tags) parses, simulates, has IoU 1, EPE 0 and zero state errors; text that is no
    scene, and a scene cut mid-way, are invalid with IoU 0, EPE = EPE_INVALID and a reason, without raising."""
    scene, obs = truth
    texts = [f"<think>x</think>\n\n<answer>\n{dump(scene)}</answer>", "no scene here", dump(scene)[:200]]
    per = evaluate_texts(texts, [scene] * 3, [obs] * 3)
    assert per["yaml_valid"] == [1.0, 0.0, 0.0] and per["sim_valid"] == [1.0, 0.0, 0.0]
    assert per["iou_first"][0] == pytest.approx(1.0) and per["iou_full"][0] == pytest.approx(1.0)
    assert per["epe_first"][0] == pytest.approx(0.0, abs=1e-6) and per["epe_full"][0] == pytest.approx(0.0, abs=1e-6)
    assert per["position_mae"][0] == 0.0 and per["velocity_mae"][0] == 0.0
    assert per["count_acc"] == [1.0, 0.0, 0.0] and per["composition_acc"] == [1.0, 0.0, 0.0]
    assert per["iou_full"][1:] == [0.0, 0.0] and per["epe_full"][1:] == [EPE_INVALID, EPE_INVALID]
    assert per["reason"][0] is None and all(per["reason"][1:])
    s = summarize(per)
    assert set(s) == set(METRIC_KEYS) and s["yaml_valid"] == pytest.approx(1 / 3)


def test_wrong_object_count_is_counted(truth):
    """Dropping the cylinder: still valid YAML, count and composition wrong, IoU below 1."""
    scene, obs = truth
    one = scene.model_copy(update={"objects": scene.objects[:1]})
    per = evaluate_texts([dump(one)], [scene], [obs])
    assert per["yaml_valid"] == [1.0] and per["count_acc"] == [0.0] and per["composition_acc"] == [0.0]
    assert 0.0 < per["iou_full"][0] < 1.0


def test_first_frame_and_full_metrics_and_state_errors_are_told_apart(truth):
    """Two wrong starts of the paper's example, each wrong in one way, on cylinder_0 (box_0 starts out of view).
    1.2 m/s faster along x: frame 0 is the same (IoU first 1), later frames and the flow of every frame are not;
    position MAE 0, velocity MAE 1.2 / (2 objects × 3 components) = 0.2. 0.6 m further along x, same velocity:
    frame 0 already differs; position MAE 0.6 / 6 = 0.1, velocity MAE 0."""
    scene, obs = truth
    texts = [dump(_moved(scene, "linear_velocity", 1.2)), dump(_moved(scene, "position", 0.6))]
    per = evaluate_texts(texts, [scene] * 2, [obs] * 2)
    assert per["yaml_valid"] == [1.0, 1.0] and per["count_acc"] == [1.0, 1.0]
    assert per["iou_first"][0] == pytest.approx(1.0) and per["iou_full"][0] < 0.9  # measured 0.67
    assert per["epe_first"][0] > 1.0 and per["epe_full"][0] > 0.3  # px at 480 wide; measured 3.5 and 0.81
    assert per["iou_first"][1] < 0.5 and per["iou_full"][1] < 0.5  # measured 0.03 and 0.28
    assert per["position_mae"] == pytest.approx([0.0, 0.1]) and per["velocity_mae"] == pytest.approx([0.2, 0.0])


def test_format_table():
    table = format_table({"model": {"yaml_valid": 0.5, "iou_full": 0.25}, "average scene": {"yaml_valid": 1.0}})
    lines = table.splitlines()
    assert lines[0].split() == ["metric", "model", "average", "scene"]
    assert lines[1].split() == ["yaml_valid", "0.5000", "1.0000"]
    assert lines[2].split() == ["iou_full", "0.2500", "nan"]


def test_metric_files_are_strict_json(tmp_path):
    """A mean nothing could be computed for (EPE of videos without observed flow: NaN) is written as null in
    `metrics.json`, `--json` and `predictions.jsonl`: Python's bare NaN is not JSON to other readers."""
    from aynamics.callbacks import json_safe
    from aynamics.evaluate import Evaluation, summary, write_evaluation

    assert json_safe({"a": [1.0, math.nan, (math.inf, "x")], "b": -math.inf, "c": 2}) == {
        "a": [1.0, None, [None, "x"]],
        "b": None,
        "c": 2,
    }
    nan = float("nan")
    result = Evaluation(
        table={"model": {"iou_full": 0.5, "epe_full": nan}},
        records=[{"index": "v0"}],
        texts=["- type: box"],
        per_item={"iou_full": [0.5], "epe_full": [nan]},
        split_size=1,
    )

    def strict(text):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))

    out = write_evaluation(tmp_path / "eval", result, {"videos": "v"})
    assert strict((out / "metrics.json").read_text())["table"]["model"] == {"iou_full": 0.5, "epe_full": None}
    assert strict((out / "predictions.jsonl").read_text())["epe_full"] is None
    assert summary(result)["table"]["model"]["epe_full"] is None


def _moved(scene, field: str, dx: float):
    """The scene with cylinder_0's initial `field` (position or linear_velocity) moved by dx along x."""
    cyl = scene.objects[1]
    value = list(getattr(cyl.state, field))
    value[0] += dx
    state = cyl.state.model_copy(update={field: value})
    return scene.model_copy(update={"objects": [scene.objects[0], cyl.model_copy(update={"state": state})]})


def _need_gl():
    from aynamics.render import gl_available

    ok, why = gl_available()
    if not ok:
        pytest.skip(why)


def test_side_by_side_animation(truth):
    """Observed left, predicted right: a prediction 1.2 m/s faster keeps the left half of the true pair and
    changes the right one (frame 0 is the same start, so only later frames differ)."""
    _need_gl()
    scene, _ = truth
    same = side_by_side(scene, scene, width=64, height=48)
    assert same.shape == (30, 48, 128, 3) and same.dtype == np.uint8
    assert np.array_equal(same[:, :, :64], same[:, :, 64:])  # same scene, same seed: identical halves
    faster = side_by_side(scene, _moved(scene, "linear_velocity", 1.2), width=64, height=48)
    assert np.array_equal(faster[:, :, :64], same[:, :, :64])
    assert np.array_equal(faster[0, :, 64:], same[0, :, 64:]) and not np.array_equal(
        faster[-1, :, 64:], same[-1, :, 64:]
    )


def test_evaluation_writes_predictions_animation_and_tensorboard(tmp_path, truth):
    """`SceneEvaluation._write` with a real TensorBoard logger: the JSONL rows (index, prediction, metrics,
    reason), the observed | predicted GIF for the valid prediction only, and the text and rollout strip in the
    event file."""
    from types import SimpleNamespace

    import imageio.v3 as iio
    from lightning.pytorch.loggers import TensorBoardLogger
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from aynamics.callbacks import SceneEvaluation

    _need_gl()
    scene, obs = truth
    texts = [dump(_moved(scene, "linear_velocity", 1.2)), "no scene here"]
    records = [{"index": 3, "scene_yaml": dump(scene), "scene": scene}, {"index": 5, "scene_yaml": "x", "scene": scene}]
    per = evaluate_texts(texts, [scene] * 2, [obs] * 2)
    tb = TensorBoardLogger(str(tmp_path), name="tb", version=0)
    trainer = SimpleNamespace(global_step=7, default_root_dir=str(tmp_path), loggers=[tb])
    SceneEvaluation(num_samples=2, max_new_tokens=8, num_animations=2)._write(trainer, texts, records, per)

    rows = [json.loads(x) for x in (tmp_path / "eval" / "predictions_step000007.jsonl").read_text().splitlines()]
    assert [(r["index"], r["prediction"]) for r in rows] == [(3, texts[0]), (5, texts[1])]
    assert rows[0]["reason"] is None and rows[1]["reason"] and rows[0]["velocity_mae"] == pytest.approx(0.2)
    gif = iio.imread(tmp_path / "eval" / "step000007_sample0.gif")
    assert gif.shape[1:3] == (106, 320) and len(gif) > 10  # Pillow merges repeated frames (objects at rest)
    assert not (tmp_path / "eval" / "step000007_sample1.gif").exists()  # no scene: nothing to animate
    tb.experiment.flush()
    events = EventAccumulator(str(tmp_path / "tb" / "version_0"))
    events.Reload()
    assert events.Tags()["images"] == ["val/rollout_0"]
    assert {"val/prediction_0/text_summary", "val/prediction_1/text_summary"} <= set(events.Tags()["tensors"])


def test_collect_multirun_folder(tmp_path):
    for k, (modality, iou) in enumerate([("rgb", 0.5), ("flow", 0.25)]):
        run = tmp_path / str(k)
        (run / ".hydra").mkdir(parents=True)
        (run / ".hydra" / "overrides.yaml").write_text(f"- data.modality={modality}\n- stage.target=answer\n")
        record = {"global_step": 20, "metrics": {"val/iou_full": iou, "val/yaml_valid": 1.0}}
        (run / "metrics.json").write_text(json.dumps(record))
    (tmp_path / "2" / ".hydra").mkdir(parents=True)
    (tmp_path / "2" / ".hydra" / "overrides.yaml").write_text("- data.modality=rgb\n")
    never_validated = '{"global_step": 3, "metrics": {"train/loss": 2.5}}'
    for k, text in [(3, "[1, 2]"), (4, "{not json"), (5, never_validated)]:  # other metrics.json files
        (tmp_path / str(k)).mkdir()
        (tmp_path / str(k) / "metrics.json").write_text(text)
    (tmp_path / "0" / "test").mkdir()  # `aynamics evaluate --out OUT/test`'s metrics.json is no run (helper-43)
    (tmp_path / "0" / "test" / "metrics.json").write_text('{"table": {"model": {"iou_full": 0.1}}}')
    (tmp_path / "2" / "train.log").write_text("Traceback (most recent call last):\n  ...\nValueError: x\n")
    rows = collect(tmp_path)
    assert [r["run"] for r in rows] == ["0", "1", "2", "3", "4", "5"]
    assert [r.get("data.modality") for r in rows] == ["rgb", "flow", "rgb", None, None, None]
    assert [r["val/iou_full"] for r in rows] == [0.5, 0.25, None, None, None, None]
    statuses = ["done", "done", "failed (train.log)"] + ["unreadable metrics.json"] * 2 + ["done"]
    assert [r["status"] for r in rows] == statuses
    assert rows[0]["val_step"] == 20  # a record without val_step but with val/ metrics: its final step
    assert (rows[5]["step"], rows[5]["val_step"]) == (3, None)  # no val/ metrics: the run never validated
    assert [r["train/loss"] for r in rows] == [None] * 5 + [2.5]  # its training loss is still a column
    assert "| 1 | flow | answer | done | 20 |" in to_markdown(rows)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        collect(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="is a file, not a multirun folder"):
        collect(tmp_path / "0" / "metrics.json")


def _clip_folder(path: Path, n: int = 10) -> Path:
    """A folder of `n` 16×16 frames: with 10, a default adapter's clip itself (every third frame of 30)."""
    import imageio.v3 as iio

    path.mkdir()
    for k in range(n):
        iio.imwrite(path / f"{k}.png", np.full((16, 16, 3), k, np.uint8))
    return path


def test_predict_cli_errors_are_clear(tmp_path, capsys):
    """Exit 2 naming the problem: a missing input, no frames, a video too short for the clip the adapter was
    trained on (every third frame of 30 at 30 fps: 0 to 0.9 s), a bad --fps."""
    from aynamics import adapters, lm
    from aynamics.cli import main

    (tmp_path / "aynamics.json").write_text(json.dumps(adapters.adapter_meta(lm.ModelSpec(), lm.PromptSpec())))
    assert main(["predict", "--adapter", str(tmp_path), str(tmp_path / "missing")]) == 2
    assert "file not found" in capsys.readouterr().err
    (tmp_path / "frames").mkdir()
    assert main(["predict", "--adapter", str(tmp_path), str(tmp_path / "frames")]) == 2
    assert "holds no frames" in capsys.readouterr().err
    short = _clip_folder(tmp_path / "short", 20)  # 20 frames at 30 fps: 0.63 s
    assert main(["predict", "--adapter", str(tmp_path), str(short)]) == 2
    err = capsys.readouterr().err
    assert "short' (20 frames at 30 fps) lasts 0.667 s (its last frame comes at 0.633 s), but frames up" in err
    assert "but frames up to 0.9 s are needed" in err
    for bad in ("0", "nan", "-30", "inf"):
        assert main(["predict", "--adapter", str(tmp_path), str(short), "--fps", bad]) == 2
        assert f"predict: --fps {float(bad)}: must be a finite number > 0" in capsys.readouterr().err
    assert main(["predict", "--adapter", str(tmp_path), str(short), "--max-new-tokens", "0"]) == 2
    assert "predict: --max-new-tokens = 0: must be >= 1" in capsys.readouterr().err


def test_inference_device_names_a_device_this_machine_lacks(tmp_path, capsys):
    """ "auto" is the first GPU when there is one, else the CPU; a GPU the machine lacks, or no device name, is
    refused before a model loads, also by `predict --device` (exit 2, the value named)."""
    import torch

    from aynamics.cli import main
    from aynamics.lm import inference_device

    assert (
        inference_device("auto")
        == inference_device(None)
        == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    )
    assert inference_device("cpu") == torch.device("cpu")
    gpus = torch.cuda.device_count()
    with pytest.raises(ValueError, match=rf"device = 'cuda:{gpus}': this machine has {gpus} CUDA devices"):
        inference_device(f"cuda:{gpus}")
    with pytest.raises(ValueError, match="device = 'gpu0': not a torch device name"):
        inference_device("gpu0")
    with pytest.raises(ValueError, match="device = 'meta': only cpu and cuda"):
        inference_device("meta")
    from aynamics import adapters, lm

    adapter = tmp_path / "adapter"
    adapter.mkdir()
    (adapter / "aynamics.json").write_text(json.dumps(adapters.adapter_meta(lm.ModelSpec(), lm.PromptSpec())))
    frames = _clip_folder(tmp_path / "frames")
    assert main(["predict", "--adapter", str(adapter), str(frames), "--device", f"cuda:{gpus}"]) == 2
    assert f"predict: device = 'cuda:{gpus}'" in capsys.readouterr().err


def test_predict_cli_names_the_broken_file(tmp_path, capsys):
    """A truncated frame, and each broken file of an adapter folder, exit 2 naming the file and the problem (they
    raised OSError, KeyError 'prompt', SafetensorError, or "Expecting value" without a file name). Every check runs
    before a base model is built, so the folders here are written by hand."""

    from aynamics import adapters, lm
    from aynamics.cli import main

    frames = _clip_folder(tmp_path / "frames")
    broken = _clip_folder(tmp_path / "broken")
    png = (broken / "3.png").read_bytes()
    (broken / "3.png").write_bytes(png[: len(png) // 2])
    good_meta = json.dumps(adapters.adapter_meta(lm.ModelSpec(), lm.PromptSpec()))
    adapter = tmp_path / "adapter"
    adapter.mkdir()
    (adapter / "aynamics.json").write_text(good_meta)
    assert main(["predict", "--adapter", str(adapter), str(broken)]) == 2
    assert f"cannot read frame {str(broken / '3.png')!r}" in capsys.readouterr().err
    (adapter / "aynamics.json").unlink()
    weights = b"\x40\x00\x00\x00\x00\x00\x00\x00" + b'{"w": {"dtype": "F32", "shape": [4], "data_offsets": [0, 16]}}'
    cases = [  # (file, content, what the message says)
        ("aynamics.json", "{}", "aynamics.json': not the model and prompt specs training writes"),
        ("aynamics.json", "garbage", "aynamics.json' (the adapter's model and prompt specs) is not valid JSON"),
        ("aynamics.json", '{"model": {"kind": "huge"}, "prompt": {}}', "model.kind = 'huge'"),
        ("adapter_config.json", "garbage", "adapter_config.json' (peft's adapter config) is not valid JSON"),
        ("adapter_config.json", "{}", "adapter_config.json' is not a peft adapter config"),
        ("adapter_model.safetensors", weights[:30], "adapter_model.safetensors' is not a readable safetensors"),
        ("adapter_model.safetensors", weights, "adapter_model.safetensors' is not a readable safetensors"),
    ]
    for name, content, message in cases:
        files = {"aynamics.json": good_meta, "adapter_config.json": '{"peft_type": "LORA"}', name: content}
        for file, text in files.items():
            (adapter / file).write_bytes(text if isinstance(text, bytes) else text.encode())
        assert main(["predict", "--adapter", str(adapter), str(frames)]) == 2, name
        err = capsys.readouterr().err
        assert err.startswith("predict: ") and message in err and str(adapter) in err, (name, content, err)
        for file in files:
            (adapter / file).unlink()


def test_export_adapter_refuses_a_folder_that_is_not_an_adapter(tmp_path, capsys):
    """--out DIR holding other files (a repository's README.md) is refused before anything is read or written;
    a folder written as an adapter before (adapter_config.json) may be rewritten."""
    from aynamics.cli import main

    repo = tmp_path / "repo"
    repo.mkdir()
    (repo / "README.md").write_text("mine")
    assert main(["export-adapter", str(tmp_path / "none.ckpt"), "--out", str(repo)]) == 2
    err = capsys.readouterr().err
    assert f"--out {str(repo)!r} is a folder with files in it and not an adapter folder" in err
    assert (repo / "README.md").read_text() == "mine" and len(list(repo.iterdir())) == 1
    (tmp_path / "a_file").write_text("x")
    assert main(["export-adapter", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "a_file")]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    adapter = tmp_path / "adapter"
    adapter.mkdir()
    (adapter / "adapter_config.json").write_text("{}")
    for out in (adapter, tmp_path / "empty", tmp_path / "new"):  # accepted: the checkpoint is what is missing
        (tmp_path / "empty").mkdir(exist_ok=True)
        assert main(["export-adapter", str(tmp_path / "none.ckpt"), "--out", str(out)]) == 2
        assert "no such checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_export_adapter_names_a_checkpoints_folder(tmp_path, capsys):
    """OUT/checkpoints given instead of a .ckpt in it: exit 2 naming the folder and the file to give (it said "no
    such checkpoint" of a folder that is there); nothing written."""
    from aynamics.cli import main

    folder = tmp_path / "checkpoints"
    folder.mkdir()
    assert main(["export-adapter", str(folder), "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "is a folder, not a checkpoint: give a .ckpt file" in err and "no such" not in err, err
    (folder / "step000004.ckpt").write_bytes(b"")
    (folder / "last.ckpt").write_bytes(b"")
    assert main(["export-adapter", str(folder), "--out", str(tmp_path / "a")]) == 2
    assert f"e.g. {folder / 'last.ckpt'}" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()


def test_predict_reads_the_response_and_exits_by_its_validity(tmp_path, monkeypatch, capsys):
    """`aynamics predict` with the model swapped for fixed responses (the adapter's files are not read past
    aynamics.json). "<think> why </think><answer>SCENE</answer>": reasoning "why" (stripped), the canonical YAML of
    SCENE, valid, exit 0, printed as "# reasoning", "why", a blank line, then the YAML. A response cut inside its
    <think> by the token limit: the reasoning so far ("the box slides"), no scene, exit 1, the response printed
    after the line naming its problems."""
    from aynamics import adapters, lm
    from aynamics.cli import main
    from aynamics.predict import predict

    scene = load(str(ASSET))
    response = [f"<think>\n why \n</think><answer>\n{dump(scene)}</answer>"]
    monkeypatch.setattr(adapters, "load_adapter", lambda adapter, device: (None, lm.ModelSpec(), lm.PromptSpec()))
    monkeypatch.setattr(lm, "load_processor", lambda spec, prompt: None)
    monkeypatch.setattr(lm, "prompt_inputs", lambda processor, prompt, frames: {"frames": len(frames)})
    monkeypatch.setattr(lm, "greedy_texts", lambda model, processor, prompts, max_new_tokens: response[:1])
    got = predict(tmp_path, [], max_new_tokens=8, device="cpu")
    assert got == {"response": response[0], "reasoning": "why", "yaml": dump(scene), "valid": True, "problems": []}
    (tmp_path / "aynamics.json").write_text(json.dumps(adapters.adapter_meta(lm.ModelSpec(), lm.PromptSpec())))
    frames = _clip_folder(tmp_path / "frames")
    args = ["predict", "--adapter", str(tmp_path), str(frames), "--device", "cpu"]
    assert main(args) == 0
    assert capsys.readouterr().out == f"# reasoning\nwhy\n\n{dump(scene)}"
    response[0] = "<think> the box slides"
    got = predict(tmp_path, [], max_new_tokens=8, device="cpu")
    assert got["reasoning"] == "the box slides" and got["yaml"] is None and not got["valid"] and got["problems"]
    assert main(args) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[:2] == ["# reasoning", "the box slides"] and out[-1] == response[0]
    assert out[3].startswith("# the response holds no valid scene: ")


def test_evaluate_scores_refines_and_counts_by_hand(truth, monkeypatch):
    """`_score` of 2 scorable records (responses: the true scene, and no scene) of the 3 read from a split of 10,
    with refinement swapped for one that returns the true scene and stops, by the time limit, 1 search for the
    model's starts and 2 for the average scene's: 1 + 2 = 3 cut short; 3 read - 2 scored = 1 left out; valid YAML
    1/2 for the model, 2/2 refined, 0/2 for an average "scene" that is none, 2/2 for it refined. The line above the
    table says "of 10 (--num)" only while fewer than the split were read (2 scored + 1 left out of a split of 3: all
    of it)."""
    from aynamics import evaluate as ev
    from aynamics.evaluate_cli import describe

    scene, obs = truth
    records = [{"index": k, "scene_yaml": dump(scene), "scene": scene, "observation": obs} for k in range(2)]
    searched = []

    def fixed(texts, recs, budget, seconds, progress=False, **kept):
        searched.append((list(texts), budget, seconds))
        return [dump(scene)] * len(texts), len(searched)

    monkeypatch.setattr(ev, "refine_texts", fixed)
    texts = [dump(scene), "no scene"]
    result = ev._score(
        records,
        texts,
        average="none",
        refine_budget=5,
        refine_seconds=2.0,
        progress=False,
        n=3,
        split_size=10,
        what="x",
    )
    assert searched == [(texts, 5, 2.0), (["none", "none"], 5, 2.0)]
    assert (result.refine_timed_out, result.left_out, result.split_size) == (3, 1, 10)
    valid = {name: column["yaml_valid"] for name, column in result.table.items()}
    assert valid == {"model": 0.5, "average scene": 0.0, "model + refine": 1.0, "average scene + refine": 1.0}
    assert result.refined == [dump(scene)] * 2 and result.refined_per_item["yaml_valid"] == [1.0, 1.0]
    cut = "3 refinements stopped by --refine-seconds before their budget"
    assert describe(result, "test") == f"test: 2 scenes of 10 (--num), 1 left out (named above), {cut}"
    result.split_size = 3
    assert describe(result, "test") == f"test: 2 scenes, 1 left out (named above), {cut}"
    result.left_out, result.refine_timed_out, result.records = 0, 0, records[:1]
    assert describe(result, None) == "videos: 1 video of 3 (--num)"


def test_evaluate_command_passes_its_settings_and_writes_them(tmp_path, capsys, monkeypatch):
    """`aynamics evaluate` with the scoring swapped for a fixed result (1 video scored, 1 left out, of 5): --videos
    writes settings with no split (videos have none) and prints "videos: 1 video of 5 (--num), 1 left out"; --data
    hands the split, --num and the baseline choice to the evaluation, and --json prints metrics.json less the
    settings."""
    from aynamics import evaluate as ev
    from aynamics import evaluate_cli
    from aynamics.cli import main

    calls = []

    def fixed(adapter, source, **kwargs):
        calls.append((source, kwargs))
        per = {"yaml_valid": [1.0], "reason": [None]}
        return ev.Evaluation({"model": {"yaml_valid": 1.0}}, [{"index": "v0"}], ["t"], per, left_out=1, split_size=5)

    monkeypatch.setattr(evaluate_cli, "evaluate_videos", fixed)
    monkeypatch.setattr(evaluate_cli, "evaluate_adapter", fixed)
    (tmp_path / "adapter").mkdir()
    base = ["evaluate", "--adapter", str(tmp_path / "adapter"), "--num", "2", "--quiet"]
    assert main([*base, "--videos", "V", "--out", str(tmp_path / "v")]) == 0
    assert capsys.readouterr().out.splitlines()[0] == "videos: 1 video of 5 (--num), 1 left out (named above)"
    written = json.loads((tmp_path / "v" / "metrics.json").read_text())
    assert (written["scenes"], written["left_out"], written["split_size"]) == (1, 1, 5)
    assert written["settings"]["split"] is None and written["settings"]["videos"] == "V"
    assert main([*base, "--data", "D", "--split", "validation", "--no-baseline", "--json"]) == 0
    summary = {"table": {"model": {"yaml_valid": 1.0}}, "scenes": 1, "left_out": 1, "split_size": 5}
    assert json.loads(capsys.readouterr().out) == summary | {"refine_timed_out": 0, "invalid_reasons": {}}
    assert [source for source, _ in calls] == ["V", "D"]
    assert calls[1][1]["split"] == "validation" and calls[1][1]["baseline"] is False and calls[1][1]["num"] == 2


def test_evaluate_reads_only_num_records_of_a_split_or_folder(tmp_path, tmp_path_factory):
    """An adapter of the tiny model (2 new tokens: no scene) on the tiny data set's test split of 3 scenes: --num 2
    scores 2 of a split of 3; --num 100 scores the 3 there are. On 2 video folders (a: 10 frames beside 30 masks;
    b: masks only, unreadable), --num 1 reads a alone: b is never read, so never named as left out."""
    import warnings

    from train_fixtures import tiny_dataset

    from aynamics import adapters, lm
    from aynamics.evaluate import evaluate_adapter, evaluate_videos

    spec = lm.ModelSpec(kind="tiny", lora_rank=8, lora_alpha=16.0, lora_dropout=0.0)
    prompt = lm.PromptSpec(num_frames=2, min_pixels=3136, max_pixels=3136)
    adapter = tmp_path / "adapter"
    adapters.save_adapter(lm.build_model(spec), adapter, spec, prompt)
    data = tiny_dataset(tmp_path_factory)
    settings = {"max_new_tokens": 2, "device": "cpu", "baseline": False}
    two = evaluate_adapter(adapter, data, num=2, **settings)
    assert (len(two.records), two.left_out, two.split_size) == (2, 0, 3)
    every = evaluate_adapter(adapter, data, num=100, **settings)
    assert [r["index"] for r in every.records] == [r["index"] for r in two.records] + [every.records[2]["index"]]
    assert (len(every.records), every.left_out, every.split_size) == (3, 0, 3)
    for name in ("a", "b"):
        (tmp_path / "videos" / name).mkdir(parents=True)
        np.save(tmp_path / "videos" / name / "segmentation.npy", np.full((30, 16, 16), -1, np.int16))
    _clip_folder(tmp_path / "videos" / "a" / "frames")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        one = evaluate_videos(adapter, tmp_path / "videos", num=1, max_new_tokens=2, device="cpu")
    assert [r["index"] for r in one.records] == ["a"] and (one.left_out, one.split_size) == (0, 2)
    assert not [w for w in seen if "left out" in str(w.message)]


def _trainer(step, epoch, *, max_steps=-1, max_epochs=None, last_batch=False, sanity=False):
    from types import SimpleNamespace

    progress = SimpleNamespace(is_last_batch=last_batch)
    return SimpleNamespace(
        global_step=step,
        current_epoch=epoch,
        max_steps=max_steps,
        max_epochs=max_epochs,
        sanity_checking=sanity,
        is_global_zero=True,
        fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=progress)),
    )


def test_evaluation_every_n_validations_and_always_at_the_end(monkeypatch):
    """Validation runs are counted (not epochs: a step-based run validates every val_check_interval steps inside
    one epoch); the sanity check does not count; the run that ends training is evaluated off the cadence, whether
    training ends on max_steps or on the last batch of max_epochs."""
    from aynamics.callbacks import SceneEvaluation
    from aynamics.run_callbacks import ends_training

    cb = SceneEvaluation(every_n_validations=3)
    done = []
    monkeypatch.setattr(cb, "evaluate", lambda trainer, module: done.append(trainer.global_step))
    cb.on_validation_epoch_end(_trainer(0, 0, max_steps=70, sanity=True), None)
    for step in (10, 20, 30, 40, 50, 60, 70):  # val_check_interval = 10 within epoch 0, max_steps = 70
        cb.on_validation_epoch_end(_trainer(step, 0, max_steps=70), None)
    assert done == [30, 60, 70]

    assert not ends_training(_trainer(5, 1, max_epochs=2))  # mid-epoch validation in the last epoch
    assert ends_training(_trainer(8, 1, max_epochs=2, last_batch=True))
    assert not ends_training(_trainer(4, 0, max_epochs=2, last_batch=True))  # end of a non-last epoch
    assert not ends_training(_trainer(4, 0, max_epochs=-1, last_batch=True))  # max_epochs -1: no epoch limit
    with pytest.raises(ValueError, match="every_n_validations = 0"):
        SceneEvaluation(every_n_validations=0)


def test_sim_valid_is_not_yaml_valid(truth):
    """A sphere whose centre starts 0.4 m under the floor is a valid scene (z in [-0.5, 10]) that does not
    simulate (it overlaps the floor by 0.6 m at t = 0): yaml_valid 1, sim_valid 0, with the simulator's reason."""
    scene, obs = truth
    text = "- {type: sphere, radius: 0.2, state: {position: [0, 0, -0.4]}}\n- {type: camera, position: [0, -2, 3.5]}\n"
    per = evaluate_texts([text], [scene], [obs])
    assert per["yaml_valid"] == [1.0] and per["sim_valid"] == [0.0]
    assert per["reason"][0].startswith("sim: overlapping start")


def test_evaluation_baseline_scores_the_average_training_scene(monkeypatch):
    """With a stand-in data module (two training spheres at x = 0 and x = 2, two validation scenes) the baseline is
    the metrics of the average scene (one sphere at x = 1) written for every record:
    `summarize(evaluate_texts([dump(avg)] * 2, targets, observations))`; the model's own summary is separate."""
    from types import SimpleNamespace

    from aynamics.average_scene import mean_scene_of_split
    from aynamics.callbacks import SceneEvaluation
    from aynamics.observation import scoring_size
    from aynamics.scene import parse

    sphere = (
        "- {{type: sphere, radius: 0.3, state: {{position: [{}, 0, 0.3]}}}}\n- type: camera\n  position: [0, -2, 3.5]\n"
    )
    train = {"scene_yaml": [sphere.format(0), sphere.format(2)]}
    val = [sphere.format(0.5), sphere.format(1)]
    records = [{"index": i, "scene_yaml": t, "size": (64, 48)} for i, t in enumerate(val)]
    dm = SimpleNamespace(eval_records=lambda split, n: [dict(r) for r in records][:n], splits={"train": train}, dir="x")
    trainer = SimpleNamespace(datamodule=dm, default_root_dir="unused", global_rank=0, world_size=1)
    cb = SceneEvaluation(num_samples=2, num_animations=0)
    monkeypatch.setattr(cb, "_generate", lambda trainer, module, records: ["no scene here"] * len(records))
    monkeypatch.setattr(cb, "_write", lambda *a: None)
    logged = {}
    module = SimpleNamespace(log=lambda k, v, **kw: logged.__setitem__(k, v), model=torch.nn.Linear(1, 1))
    summary = cb.evaluate(trainer, module)

    avg = mean_scene_of_split(train)
    assert avg.objects[0].state.position == (1.0, 0.0, 0.3)
    targets = [parse(t) for t in val]
    width, height = scoring_size(64, 48)
    observations = [Observation.from_scene(s, width=width, height=height) for s in targets]
    expected = summarize(evaluate_texts([dump(avg)] * 2, targets, observations))
    assert cb.last_baseline == pytest.approx(expected)
    assert expected["yaml_valid"] == 1.0 and expected["position_mae"] == pytest.approx((0.5 + 0.0) / 3 / 2)
    assert summary["yaml_valid"] == 0.0
    assert logged["val/baseline/position_mae"] == pytest.approx(expected["position_mae"])


def test_records_of_rank_split_and_pad():
    """5 records over 2 processes: [0, 2, 4] and [1, 3]; padded (sharded weights: the same generate calls on
    every rank) rank 1 repeats its last record, and a rank without records (2 over 4) generates record 0 and
    scores none; a bad rank is named."""
    from aynamics.callbacks import records_of_rank

    assert records_of_rank(5, 0, 1) == ([0, 1, 2, 3, 4], 5)
    assert [records_of_rank(5, r, 2) for r in (0, 1)] == [([0, 2, 4], 3), ([1, 3], 2)]
    assert [records_of_rank(5, r, 2, pad=True) for r in (0, 1)] == [([0, 2, 4], 3), ([1, 3, 3], 2)]
    assert records_of_rank(2, 3, 4) == ([], 0) and records_of_rank(2, 3, 4, pad=True) == ([0], 0)
    with pytest.raises(ValueError, match="rank = 2, world = 2"):
        records_of_rank(5, 2, 2)


def test_merge_parts_restores_record_order():
    """The processes' parts of `records_of_rank` are put back in record order; a record missing or given twice
    is named."""
    from aynamics.callbacks import merge_parts

    parts = [([0, 2], ["a", "c"], {"iou_full": [0.0, 0.2]}), ([1], ["b"], {"iou_full": [0.1]})]
    assert merge_parts(parts, 3) == (["a", "b", "c"], {"iou_full": [0.0, 0.1, 0.2]})
    with pytest.raises(ValueError, match=r"\[0, 1, 2, 2\] are not each of the 3 records once"):
        merge_parts([*parts, ([2], ["c"], {"iou_full": [0.2]})], 3)


def test_evaluation_split_over_two_processes_equals_one_process(monkeypatch, truth):
    """Three records evaluated by two processes (each generating and scoring its share; rank 0 gathers) log
    and write exactly what one process does: the same per-record rows in record order and the same means; the
    other rank logs and writes nothing. Responses differ per record (true, slower, none), so order matters."""
    from types import SimpleNamespace

    import aynamics.callbacks as callbacks
    from aynamics.callbacks import SceneEvaluation

    scene, _ = truth
    answers = {0: dump(scene), 1: dump(_moved(scene, "linear_velocity", 0.5)), 2: "no scene here"}
    records = [{"index": i, "scene_yaml": dump(scene), "size": (96, 64)} for i in range(3)]
    dm = SimpleNamespace(eval_records=lambda split, n: [dict(r) for r in records][:n], dir="x")

    def run(rank: int, world: int, gather):
        trainer = SimpleNamespace(datamodule=dm, default_root_dir="unused", global_rank=rank, world_size=world)
        cb = SceneEvaluation(num_samples=3, num_animations=0, baseline=False)
        made = []

        def generate(trainer, module, recs):
            made.extend(r["index"] for r in recs)
            return [answers[r["index"]] for r in recs]

        monkeypatch.setattr(cb, "_generate", generate)
        written, logged = [], {}
        monkeypatch.setattr(cb, "_write", lambda trainer, texts, recs, per: written.append((texts, per)))
        monkeypatch.setattr(callbacks, "_gather_objects", gather)
        module = SimpleNamespace(log=lambda k, v, **kw: logged.__setitem__(k, v), model=torch.nn.Linear(1, 1))
        return cb.evaluate(trainer, module), made, written, logged, cb.evaluated

    one = run(0, 1, lambda obj, world: [obj])
    sent = []
    other = run(1, 2, lambda obj, world: sent.append(obj) or [None, obj])
    zero = run(0, 2, lambda obj, world: [obj, sent[0]])
    assert one[1] == [0, 1, 2] and zero[1] == [0, 2] and other[1] == [1]
    assert other[0] == {} and other[2] == [] and other[3] == {}
    assert zero[0] == one[0] and zero[3] == one[3] and zero[2] == one[2]
    assert zero[4] == one[4] == 3  # rank 0 reports all 3 records evaluated (train.py prints it), not its own 2
    texts, per = zero[2][0]
    assert texts == [answers[i] for i in range(3)] and per["yaml_valid"] == [1.0, 1.0, 0.0]
    assert per["velocity_mae"][0] == 0.0 and per["velocity_mae"][1] > 0


def test_videos_without_a_label_get_the_metrics_that_need_none(truth):
    """Without true scenes (`targets=None`: real videos) the validity, IoU and EPE are those computed with them,
    and count, composition and state errors are not reported rather than guessed."""
    scene, obs = truth
    texts = [dump(scene), "no scene here"]
    labelled = evaluate_texts(texts, [scene] * 2, [obs] * 2)
    unlabelled = evaluate_texts(texts, None, [obs] * 2)
    kept = ("yaml_valid", "sim_valid", "iou_first", "iou_full", "epe_first", "epe_full", "reason")
    assert list(unlabelled) == list(kept) and unlabelled == {k: labelled[k] for k in kept}
    assert set(summarize(unlabelled)) == set(kept) - {"reason"}


def test_evaluate_goes_on_after_an_interruption(tmp_path, tmp_path_factory, monkeypatch, capsys):
    """`aynamics evaluate --out OUT` on the tiny data set's test split (3 scenes, 1 a batch, 6-simulation
    refinements of the average scene) is interrupted at its second batch of responses (with --num 2), then again at
    its second refinement (the whole split): each run does only what was not kept (responses of scenes 1 and 2,
    then the refinements of scenes 1 and 2), other settings and a --num of fewer scenes than were kept are refused
    naming the difference, and the third run writes the predictions and metrics of an uninterrupted run and deletes
    OUT.partial. Before, an interruption lost every response and
    refinement (hours on a real model)."""
    from train_fixtures import tiny_dataset

    import aynamics.refine
    from aynamics import adapters, lm
    from aynamics.cli import main

    spec = lm.ModelSpec(kind="tiny", lora_rank=8, lora_alpha=16.0, lora_dropout=0.0)
    prompt = lm.PromptSpec(num_frames=2, min_pixels=3136, max_pixels=3136)
    adapter = tmp_path / "adapter"
    adapters.save_adapter(lm.build_model(spec), adapter, spec, prompt)
    data = tiny_dataset(tmp_path_factory)
    args = ["evaluate", "--adapter", str(adapter), "--data", str(data), "--batch-size", "1", "--quiet"]
    args += ["--max-new-tokens", "3", "--refine", "6", "--refine-seconds", "60", "--device", "cpu"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    generate, refine, calls = lm.greedy_texts, aynamics.refine.refine, []

    def counted(fn, name, stop_at):
        def call(*a, **k):
            calls.append(name)
            if calls.count(name) == stop_at[0]:
                raise KeyboardInterrupt
            return fn(*a, **k)

        return call

    stop = {"generate": [2], "refine": [0]}
    monkeypatch.setattr(lm, "greedy_texts", counted(generate, "generate", stop["generate"]))
    monkeypatch.setattr(aynamics.refine, "refine", counted(refine, "refine", stop["refine"]))
    out = tmp_path / "eval"
    assert main([*args, "--num", "2", "--out", str(out)]) == 130  # a larger --num goes on from it (below)
    err = capsys.readouterr().err
    assert f"evaluate: kept in {str(tmp_path / 'eval.partial')!r} (1 batch of responses): the same command" in err
    assert main([*args, "--max-new-tokens", "4", "--out", str(out)]) == 2
    assert "with other settings (max_new_tokens 3 there, 4 now)" in capsys.readouterr().err
    calls.clear()
    stop["generate"][0], stop["refine"][0] = 0, 2
    assert main([*args, "--out", str(out)]) == 130
    assert calls == ["generate", "generate", "refine", "refine"]  # scenes 1 and 2 answered; scene 0 refined
    assert "going on from" in capsys.readouterr().err and not out.exists()
    assert main([*args, "--num", "2", "--out", str(out)]) == 2
    assert "holds 3 batches of responses, but these records make 2 (a smaller --num" in capsys.readouterr().err
    calls.clear()
    stop["refine"][0] = 0
    assert main([*args, "--out", str(out)]) == 0
    assert calls == ["refine", "refine"]  # scenes 1 and 2 (the model's responses hold no scene: not refined)
    # every response kept, and 4 refinements: the model's 3 (no scene: kept as they are) and the average scene's first
    assert "(3 batches of responses, 4 refinements)" in capsys.readouterr().err
    assert not (tmp_path / "eval.partial").exists()
    for name in ("predictions.jsonl", "metrics.json"):
        whole = (tmp_path / "whole" / name).read_text().replace(str(tmp_path / "whole"), str(out))
        assert (out / name).read_text() == whole, name


def test_evaluate_with_another_refinement_budget_keeps_the_responses(tmp_path, tmp_path_factory, monkeypatch, capsys):
    """Interrupted in its refinements (3 responses kept, the average scene refined for 1 scene), `aynamics evaluate`
    run again with another --refine-seconds generates nothing and refines the average scene for all 3 scenes again,
    saying so; it was refused ("other settings (refine_seconds ...)"), and only deleting the kept folder, with its
    responses (hours on a real model), went on."""
    from train_fixtures import tiny_dataset

    import aynamics.refine
    from aynamics import adapters, lm
    from aynamics.cli import main

    spec = lm.ModelSpec(kind="tiny", lora_rank=8, lora_alpha=16.0, lora_dropout=0.0)
    adapter = tmp_path / "adapter"
    adapters.save_adapter(
        lm.build_model(spec), adapter, spec, lm.PromptSpec(num_frames=2, min_pixels=3136, max_pixels=3136)
    )
    args = ["evaluate", "--adapter", str(adapter), "--data", str(tiny_dataset(tmp_path_factory)), "--batch-size", "1"]
    args += ["--quiet", "--max-new-tokens", "3", "--refine", "6", "--device", "cpu", "--out", str(tmp_path / "eval")]
    generate, refine, calls = lm.greedy_texts, aynamics.refine.refine, []

    def counted(fn, name, stop_at=None):
        def call(*a, **k):
            calls.append(name)
            if calls.count(name) == stop_at:
                raise KeyboardInterrupt
            return fn(*a, **k)

        return call

    monkeypatch.setattr(lm, "greedy_texts", counted(generate, "generate"))
    monkeypatch.setattr(aynamics.refine, "refine", counted(refine, "refine", stop_at=2))
    assert main([*args, "--refine-seconds", "60"]) == 130
    assert calls == ["generate"] * 3 + ["refine"] * 2
    calls.clear()
    monkeypatch.setattr(aynamics.refine, "refine", counted(refine, "refine"))
    assert main([*args, "--refine-seconds", "30"]) == 0
    assert calls == ["refine"] * 3  # no response generated again; every refinement of the average scene done again
    err = capsys.readouterr().err
    assert "refine_seconds 60.0 there, 30.0 now: the kept refinements are done again, the kept responses used" in err


def test_kept_responses_of_other_records_or_prompts_are_refused(tmp_path, monkeypatch):
    """Batches kept for records 0 and 1 (batch size 1) are read back for the same records and prompts, and refused
    for other records at their place, for another prompt under the same index (a data set made again), and when
    fewer records make fewer batches than are kept."""
    from aynamics import evaluate as ev
    from aynamics import lm
    from aynamics.kept_batches import KeptBatches

    answered = []
    monkeypatch.setattr(lm, "greedy_texts", lambda m, p, prompts, n: answered.extend(prompts) or ["t"] * len(prompts))

    def items(indices, value=1, seen=None):
        return ([{"index": i, "prompt": {"ids": torch.tensor([i, value])}, "observation": seen}] for i in indices)

    def run(indices, value=1, seen=None):
        return ev._generate(None, None, items(indices, value, seen), len(indices), 1, 8, "x", False, kept)

    kept = KeptBatches(tmp_path / "k", {}, run="an evaluation", verb="score", fields=ev.KEPT_FIELDS)
    with kept.opened():
        records, texts, digests = run([0, 1])
        assert len(answered) == 2 and texts == ["t", "t"] and len(set(digests)) == 2 and kept.count("responses") == 2
        assert run([0, 1])[2] == digests and len(answered) == 2  # read back: nothing generated
        # other masks: the responses stand (they see the frames only); the record digests refinements check change
        assert run([0, 1], seen=np.ones(2))[2] != digests and len(answered) == 2
        with pytest.raises(ValueError, match=r"batch 1 holds records \[1\], but this run's batch 1 is records \[2\]"):
            run([0, 2])
        with pytest.raises(ValueError, match=r"other prompts \(frames\) of the records \[0\]"):
            run([0, 1], value=2)
        with pytest.raises(ValueError, match="holds 2 batches of responses, but these records make 1"):
            run([0])


def test_a_larger_num_goes_on_from_the_short_last_batch_of_a_smaller_one(tmp_path, monkeypatch):
    """Kept with batch size 2 and 3 records (batches [0, 1], [2], and refinements of records 0-2), 4 records answer
    batch [2, 3] again whole (as an uninterrupted run batches them): the kept [0, 1] is read back, nothing refused.
    When the batch answers record 2 otherwise, its refinement (the third) is dropped, the first two stay. Then 3
    records are refused as fewer than the kept batch [2, 3] holds. Before, the larger --num was refused: "its
    responses batch 1 holds records [2], but this run's batch 1 is records [2, 3]: the data changed since"."""
    from aynamics import evaluate as ev
    from aynamics import lm
    from aynamics.kept_batches import KeptBatches

    answered, word = [], ["t"]

    def greedy(model, processor, prompts, n):
        answered.append(len(prompts))
        return word * len(prompts)

    monkeypatch.setattr(lm, "greedy_texts", greedy)

    def run(indices):
        items = ([{"index": i, "prompt": {"ids": torch.tensor([i])}, "observation": None}] for i in indices)
        return ev._generate(None, None, items, len(indices), 2, 8, "x", False, kept)

    kept = KeptBatches(tmp_path / "k", {}, run="an evaluation", verb="score", fields=ev.KEPT_FIELDS)
    with kept.opened():
        run([0, 1, 2])
        for k in range(3):
            kept.save(ev.REFINED_KEPT, k, {"keys": [k], "digests": [], "texts": [], "timed_out": 0})
        assert answered == [2, 1]
        assert run([0, 1, 2, 3])[1] == ["t"] * 4 and answered == [2, 1, 2]
        assert kept.count(ev.REFINED_KEPT) == 3  # record 2's response is the same: its refinement stands
        word[0] = "u"
        kept.save(ev.RESPONSES, 1, {"keys": [2], "digests": kept.done(ev.RESPONSES)[1]["digests"][:1], "texts": ["t"]})
        assert run([0, 1, 2, 3])[1] == ["t", "t", "u", "u"] and answered == [2, 1, 2, 2]
        assert kept.count(ev.REFINED_KEPT) == 2
        with pytest.raises(ValueError, match="holds 2 batches of responses, but this run's last batch holds fewer"):
            run([0, 1, 2])


def test_evaluate_refused_or_interrupted_before_a_batch_leaves_no_partial_folder(
    tmp_path, tmp_path_factory, capsys, monkeypatch
):
    """`aynamics evaluate --out OUT` refused after OUT.partial was opened (--num 0: exit 2), or interrupted before
    its first batch of responses (exit 130), leaves no OUT.partial and says nothing is kept. Both left OUT.partial
    (settings.json and .lock, no batch) beside OUT, and the interruption said "nothing are kept in 'OUT.partial':
    the same command goes on from them"."""
    from train_fixtures import tiny_dataset

    from aynamics import evaluate_cli
    from aynamics.cli import main

    (tmp_path / "adapter").mkdir()
    data = tiny_dataset(tmp_path_factory)
    base = ["evaluate", "--adapter", str(tmp_path / "adapter"), "--data", str(data), "--quiet"]
    assert main([*base, "--num", "0", "--out", str(tmp_path / "a")]) == 2
    assert "--num = 0: must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "a.partial").exists()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate_cli, "evaluate_adapter", interrupted)
    assert main([*base, "--out", str(tmp_path / "b")]) == 130
    assert "kept in" not in capsys.readouterr().err and not (tmp_path / "b.partial").exists()


def test_evaluate_cli_errors_are_clear(tmp_path, capsys, tmp_path_factory):
    """`aynamics evaluate` names a missing data set, a split it lacks (with the ones it has), bad counts and an output
    folder of other files, each with exit 2 before any model loads."""
    from train_fixtures import tiny_dataset

    from aynamics.cli import main

    data = tiny_dataset(tmp_path_factory)
    adapter = tmp_path / "adapter"
    adapter.mkdir()
    base = ["evaluate", "--adapter", str(adapter), "--quiet"]
    (tmp_path / "v.txt").write_text("a file")
    cases = [
        (["--data", str(tmp_path / "nothing")], "--data = '" + str(tmp_path / "nothing") + "' holds no data set"),
        (["--data", str(data), "--split", "dev"], "--split 'dev': the data set"),
        (["--data", str(data), "--num", "0"], "evaluate: --num = 0: must be >= 1"),
        (["--data", str(data), "--refine", "-1"], "evaluate: --refine = -1: must be >= 0"),
        (["--data", str(data), "--refine-seconds", "nan"], "--refine-seconds = nan"),
        (["--data", str(data), "--refine-seconds", "-3"], "--refine-seconds = -3.0"),
        (["--data", str(data), "--refine-seconds", "inf"], "--refine-seconds = inf: must be a finite number"),
        (["--adapter", str(tmp_path / "none"), "--data", str(data)], "is not a folder"),
        (["--videos", str(tmp_path), "--split", "test"], "evaluate: --split is for --data (a data set)"),
        (["--videos", str(tmp_path), "--no-baseline"], "evaluate: --no-baseline is for --data (a data set)"),
        (["--videos", str(tmp_path / "v.txt")], "'" + str(tmp_path / "v.txt") + "' is a file, not a video folder"),
    ]
    for extra, message in cases:
        assert main(base + extra) == 2, extra
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
    capsys.readouterr()
    assert main([*base, "--data", str(data), "--split", "dev"]) == 2
    assert "(splits: {'train': " in capsys.readouterr().err  # the ones it has
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "notes.txt").write_text("mine")
    assert main([*base, "--data", str(data), "--out", str(tmp_path / "taken")]) == 2
    assert "holds other files ('notes.txt'" in capsys.readouterr().err
    assert (tmp_path / "taken" / "notes.txt").read_text() == "mine"
    import datasets

    held_out = datasets.load_from_disk(str(data))
    del held_out["train"]
    held_out.save_to_disk(str(tmp_path / "held_out"))  # a data set of held-out scenes only: no train split
    assert main([*base, "--data", str(tmp_path / "held_out")]) == 2
    assert "aynamics.json' not found: --adapter must be" in capsys.readouterr().err  # past the data set


def test_refine_texts_refines_valid_scenes_and_keeps_the_rest(truth):
    """Test-time refinement in `aynamics evaluate --refine`: a prediction with its cylinder 0.3 m off in x is
    refined to a higher full IoU with the same objects; a response without a scene is kept as it is (scored invalid
    again)."""
    from aynamics.evaluate import refine_texts
    from aynamics.scene import from_items, parse, to_items
    from aynamics.scorer import score

    scene, obs = truth
    items = to_items(scene)
    items[1]["state"]["position"][0] += 0.3  # the cylinder, in view
    off = dump(from_items(items))
    before = score([parse(off)], obs)[0].iou_full
    refined, timed_out = refine_texts([off, "no scene"], [{"observation": obs}] * 2, budget=60, seconds=30)
    assert refined[1] == "no scene" and timed_out == 0
    after = parse(refined[0])
    assert after.structure == scene.structure and before < 0.6  # 0.47 measured
    assert score([after], obs)[0].iou_full > 0.9  # 0.98 measured
    assert refine_texts([off], [{"observation": obs}], budget=100_000, seconds=0.2)[1] == 1  # cut by the time limit


def test_a_record_whose_frames_cannot_be_read_is_left_out_with_its_reason():
    """The evaluation's records (training's and `aynamics evaluate`'s): a record without frames, or one whose
    image cannot be decoded, is named and left out instead of stopping the run."""
    from PIL import UnidentifiedImageError

    from aynamics import lm
    from aynamics.eval_records import readable_eval_record

    class Broken:  # a split whose row 0 holds a PNG Pillow cannot identify
        def __getitem__(self, i):
            raise UnidentifiedImageError("cannot identify image file")

    processor = lm.load_processor(lm.ModelSpec(), lm.PromptSpec())
    empty = [{"index": 7, "rgb": [], "scene_yaml": "- type: camera\n  position: [0, -2, 3]\n"}]
    with pytest.warns(UserWarning, match=r"record 0 of the test records of X is left out: .*record 7 has no 'rgb'"):
        assert readable_eval_record(empty, 0, processor, lm.PromptSpec(), "test records of X") is None
    with pytest.warns(
        UserWarning,
        match=r"record 0 of the test records of X is left out: its frames cannot be read \(cannot identify image",
    ):
        assert readable_eval_record(Broken(), 0, processor, lm.PromptSpec(), "test records of X") is None


def test_scene_evaluation_simulates_with_the_data_sets_own_substeps(tmp_path):
    """A data set generated with substeps=2 (1/60 s steps): the evaluation records carry that (the scene evaluation
    re-simulated the truth at the default 8 per frame, other physics than the video's), and the observation, its
    candidates' simulation and the true scene agree: IoU 1."""
    import datasets

    from aynamics import eval_records, lm
    from aynamics.callbacks import scorable_records
    from aynamics.dataset_store import dataset_substeps
    from aynamics.generate import GenerateConfig, generate_dataset
    from aynamics.render import gl_available

    if not gl_available()[0]:
        pytest.skip("no headless OpenGL")
    config = GenerateConfig(width=64, height=48, substeps=2, workers=0, splits=(1.0, 0.0, 0.0))
    path = generate_dataset(tmp_path / "d", num=2, seed=0, config=config)
    assert dataset_substeps(path) == 2
    prompt = lm.PromptSpec(num_frames=2)
    processor = lm.load_processor(lm.ModelSpec(kind="tiny"), prompt)
    split = datasets.load_from_disk(str(path))["train"]
    steps = dataset_substeps(path)
    records = [eval_records.readable_eval_record(split, i, processor, prompt, "test", steps) for i in (0, 1)]
    assert [r["substeps"] for r in records] == [2, 2]
    scored = scorable_records(records)
    assert [r["observation"].config.substeps for r in scored] == [2, 2]
    per = evaluate_texts(
        [r["scene_yaml"] for r in scored], [r["scene"] for r in scored], [r["observation"] for r in scored]
    )
    assert per["iou_full"] == pytest.approx([1.0, 1.0])


def test_collect_runs_named_with_words_beside_numbers(tmp_path):
    """A run folder named with letters ("best", "3_rerun") beside Hydra's numbered ones: the sort compared a str
    with an int and `aynamics collect` ended in a TypeError traceback; an unreadable overrides.yaml likewise."""
    from aynamics.cli import main

    for name in ("10", "2", "best", "3_rerun"):
        (tmp_path / name / ".hydra").mkdir(parents=True)
        (tmp_path / name / ".hydra" / "overrides.yaml").write_text(f"- seed={len(name)}\n")
        (tmp_path / name / "metrics.json").write_text('{"global_step": 1, "metrics": {}}')
    (tmp_path / "best" / ".hydra" / "overrides.yaml").write_text("- 'data.dir=/x\n")  # cut short
    rows = collect(tmp_path)
    assert [r["run"] for r in rows] == ["2", "3_rerun", "10", "best"]
    assert rows[3]["overrides"] == "unreadable .hydra/overrides.yaml" and rows[3]["status"] == "done"
    assert main(["collect", str(tmp_path)]) == 0


def test_collect_out_replaces_only_a_table_it_wrote(tmp_path, capsys):
    """`aynamics collect DIR --out FILE` overwrote any FILE without a word: a run's metrics.json, train.py. FILE is
    replaced when it is a table collect wrote (header run, ..., status, ...) or empty; anything else is refused
    (exit 2), naming it, and left as it was. The default DIR/summary.csv is rewritten on every call."""
    from aynamics.cli import main

    runs = tmp_path / "multirun"
    (runs / "0").mkdir(parents=True)
    record = '{"global_step": 5, "metrics": {"val/iou_full": 0.5}}'
    (runs / "0" / "metrics.json").write_text(record)
    notes = tmp_path / "notes.csv"
    notes.write_text("run,score\n1,2\n")  # a CSV, but no status column: not collect's
    for other in (runs / "0" / "metrics.json", notes):
        before = other.read_text()
        assert main(["collect", str(runs), "--out", str(other)]) == 2
        err = capsys.readouterr().err
        assert f"collect: --out {str(other)!r} exists and is not a table that collect wrote" in err
        assert other.read_text() == before
    table, empty = tmp_path / "table.csv", tmp_path / "empty.csv"
    empty.write_text("")
    for out in (table, table, empty):  # new, then its own table again, then an empty file
        assert main(["collect", str(runs), "--out", str(out)]) == 0
        assert out.read_text().splitlines()[:2] == [
            "run,status,step,val_step," + ",".join(DEFAULT_METRICS),
            "0,done,5,5,,,,,,0.5" + "," * 8,
        ]
    assert main(["collect", str(runs)]) == 0 and main(["collect", str(runs)]) == 0
    assert (runs / "summary.csv").read_text() == table.read_text()
    assert (runs / "0" / "metrics.json").read_text() == record


@pytest.mark.parametrize(("max_epochs", "described"), [(-1, "Epoch 0"), (3, "Epoch 0/2")])
def test_progress_bar_names_an_epoch_total_only_when_there_is_one(max_epochs, described):
    """A run limited by max_steps (max_epochs -1, every run of train.py) reads "Epoch 0", not Lightning 2.6's
    "Epoch 0/-2"; with an epoch limit the bar keeps its "Epoch 0/2". train.py adds the bar only where Lightning
    would add a rich one: enabled, and no progress bar given."""
    import lightning as L
    from lightning.pytorch.callbacks import TQDMProgressBar
    from lightning.pytorch.demos.boring_classes import BoringModel

    from aynamics.run_callbacks import StepsProgressBar, progress_bar

    assert progress_bar([], enabled=False) == [] and progress_bar([TQDMProgressBar()], enabled=True) == []
    (bar,) = progress_bar([], enabled=True)
    seen = []

    class Look(L.Callback):
        def on_train_batch_end(self, trainer, *args):
            seen.append(bar._get_train_description(trainer.current_epoch).rstrip())

    trainer = L.Trainer(
        max_steps=2, max_epochs=max_epochs, callbacks=[bar, Look()], logger=False, enable_checkpointing=False
    )
    trainer.fit(BoringModel())
    assert isinstance(bar, StepsProgressBar) and seen == [described, described]


def test_progress_bar_total_counts_batches_not_steps_and_those_run_before_a_resume():
    """Lightning 2.6 sized the bar by the optimizer steps left: 2 batches at accumulation 2 read "2/1", and a run
    resumed at step 3 of max_steps 5 (its bar starts after its first batch, at global step 4) read "2/1". The total
    is the epoch's batches run + steps left × accumulation, at most the epoch's (3 here); unlimited epochs only."""
    from types import SimpleNamespace

    from aynamics.run_callbacks import StepsProgressBar

    def total(processed, global_step, accumulate=1, max_steps=5, max_epochs=-1):
        bar = StepsProgressBar()
        progress = SimpleNamespace(current=SimpleNamespace(processed=processed))
        bar._trainer = SimpleNamespace(
            max_epochs=max_epochs,
            max_steps=max_steps,
            global_step=global_step,
            accumulate_grad_batches=accumulate,
            num_training_batches=3,
            fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=progress)),
        )
        return bar.total_train_batches

    assert total(0, 0, accumulate=2, max_steps=1) == 2  # Lightning: 1
    assert total(1, 4) == 2  # the resumed run's first batch (Lightning: 1)
    assert total(0, 3) == 2 and total(0, 0) == 3  # at an epoch's start: as Lightning's
    assert total(0, 0, max_epochs=4, max_steps=-1) == 3


def test_invalid_reasons_count_why_responses_fail():
    """The line under the validation table: each invalid response counted once by its kind, the simulation's
    failures by their own first words, most first (ties in the order met); none when every scene simulates."""
    from aynamics.callbacks import format_reasons, invalid_reasons

    reasons = [
        None,
        "sim: overlapping start: box_0 and the floor by 0.09 m at t=0 (more than 0.05 m)",
        "no YAML found in the response",
        "sim: overlapping start: sphere_0 and box_0 by 0.2 m at t=0 (more than 0.05 m)",
        "objects[0].physics.mass = -2.0: must be > 0",
        "sim: camera inside box_0 at t=0.000s (camera.position = [0, 0, 1]): a video cannot show that view",
        "truncated at max_new_tokens = 16: no YAML found in the response",
        "sim: blew up: box_0 at t=0.500s has speed 300 m/s, spin 0 rad/s, distance 4 m",
        None,
    ]
    counts = invalid_reasons(reasons)
    assert list(counts.items()) == [
        ("overlapping start", 2),
        ("no YAML", 1),
        ("invalid fields", 1),
        ("camera inside", 1),
        ("cut off at max_new_tokens", 1),
        ("blew up", 1),
    ]
    assert format_reasons(counts, len(reasons)) == (
        "Why 7 of 9 responses do not simulate: overlapping start 2, no YAML 1, invalid fields 1, camera inside 1, "
        "cut off at max_new_tokens 1, blew up 1"
    )
    assert invalid_reasons([None, None]) == {} and format_reasons({}, 2) == ""
