"""Evaluation metrics of generated scenes, the table, the animation, predict and collect."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aynamics.callbacks import METRIC_KEYS, evaluate_texts, format_table, side_by_side, summarize
from aynamics.collect import collect, to_markdown
from aynamics.scene import dump, load
from aynamics.scorer import EPE_INVALID, Observation

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


def test_format_table():
    table = format_table({"model": {"yaml_valid": 0.5, "iou_full": 0.25}, "average scene": {"yaml_valid": 1.0}})
    lines = table.splitlines()
    assert lines[0].split() == ["metric", "model", "average", "scene"]
    assert lines[1].split() == ["yaml_valid", "0.5000", "1.0000"]
    assert lines[2].split() == ["iou_full", "0.2500", "nan"]


def test_side_by_side_animation(truth):
    from aynamics.render import gl_available

    ok, why = gl_available()
    if not ok:
        pytest.skip(why)
    scene, _ = truth
    frames = side_by_side(scene, scene, width=64, height=48)
    assert frames.shape == (30, 48, 128, 3) and frames.dtype == np.uint8
    assert np.array_equal(frames[:, :, :64], frames[:, :, 64:])  # same scene, same seed: identical halves


def test_collect_multirun_folder(tmp_path):
    for k, (modality, iou) in enumerate([("rgb", 0.5), ("flow", 0.25)]):
        run = tmp_path / str(k)
        (run / ".hydra").mkdir(parents=True)
        (run / ".hydra" / "overrides.yaml").write_text(f"- data.modality={modality}\n- stage.target=answer\n")
        record = {"global_step": 20, "metrics": {"val/iou_full": iou, "val/yaml_valid": 1.0}}
        (run / "metrics.json").write_text(json.dumps(record))
    (tmp_path / "2" / ".hydra").mkdir(parents=True)
    (tmp_path / "2" / ".hydra" / "overrides.yaml").write_text("- data.modality=rgb\n")
    rows = collect(tmp_path)
    assert [r["run"] for r in rows] == ["0", "1", "2"]
    assert [r["data.modality"] for r in rows] == ["rgb", "flow", "rgb"]
    assert [r["val/iou_full"] for r in rows] == [0.5, 0.25, None]
    assert [r["status"] for r in rows] == ["done", "done", "missing"]
    assert "| 1 | flow | answer | done | 20 |" in to_markdown(rows)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        collect(tmp_path / "nope")


def test_predict_cli_errors_are_clear(tmp_path, capsys):
    from aynamics.cli import main

    assert main(["predict", "--adapter", str(tmp_path), str(tmp_path / "missing")]) == 2
    assert "file not found" in capsys.readouterr().err
    (tmp_path / "frames").mkdir()
    assert main(["predict", "--adapter", str(tmp_path), str(tmp_path / "frames")]) == 2
    assert "holds no frames" in capsys.readouterr().err
