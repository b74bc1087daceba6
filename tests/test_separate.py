"""Separating a scene's start (`aynamics.separate`): hand-worked moves for objects inside each other and the floor."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aynamics import simulate as sim
from aynamics.scene import dump, parse
from aynamics.separate import separate_start

CAMERA = """
- type: camera
  fovy: 50
  orientation: 45
  position: [0, -1.5, 3.0]
"""


def _scene(objects: str) -> object:
    return parse(objects + CAMERA)


def _positions(scene) -> np.ndarray:
    return np.array([o.state.position for o in scene.objects])


def test_two_spheres_at_one_position_part_by_half_the_depth_each():
    """Spheres of radius 0.2 at one point on the floor overlap by 0.4 m: each moves 0.2 m, in opposite directions
    along the floor (MuJoCo's normal of coincident spheres), in one round; their heights stay."""
    sphere = "- type: sphere\n  radius: 0.2\n  state: {position: [0.5, 1.0, 0.2]}\n"
    scene = _scene(sphere * 2)
    assert sim.simulate(scene).reason.startswith("overlapping start")
    result = separate_start(scene)
    a, b = (np.array(result.moved[n]) for n in ("sphere_0", "sphere_1"))
    assert result.rounds == 1 and np.allclose(a, -b) and np.isclose(np.linalg.norm(a), 0.2) and a[2] == 0
    p = _positions(result.scene)
    assert np.isclose(np.linalg.norm(p[0] - p[1]), 0.4) and np.allclose(p[:, 2], 0.2)
    assert sim.start_overlap_pairs(result.scene) == {} and sim.simulate(result.scene).valid


def test_a_box_sunk_into_the_floor_is_lifted_onto_it():
    """A box of half-extents 0.1 at height 0.02 is 0.08 m into the floor: lifted 0.08 m straight up, to rest on
    it at 0.1; a sphere beside it that touches the floor without sinking (radius 0.3 at 0.3) stays where it is."""
    scene = _scene(
        "- type: box\n  size: [0.1, 0.1, 0.1]\n  state: {position: [0.0, 1.0, 0.02]}\n"
        "- type: sphere\n  radius: 0.3\n  state: {position: [1.5, 1.0, 0.3]}\n"
    )
    result = separate_start(scene)
    assert list(result.moved) == ["box_0"] and np.allclose(result.moved["box_0"], (0, 0, 0.08))
    assert np.allclose(_positions(result.scene), [(0, 1, 0.1), (1.5, 1, 0.3)])
    assert result.scene.objects[1] == scene.objects[1]
    assert result.scene.objects[0].state.orientation == scene.objects[0].state.orientation


def test_a_scene_that_does_not_overlap_comes_back_as_it_is():
    """Two boxes resting side by side on the floor, touching (0.2 m apart at half-extent 0.1): nothing moves."""
    box = "- type: box\n  size: [0.1, 0.1, 0.1]\n  state: {{position: [{x}, 1.0, 0.1]}}\n"
    scene = _scene(box.format(x=0.0) + box.format(x=0.2))
    result = separate_start(scene)
    assert result.scene is scene and result.moved == {} and result.rounds == 0


def test_a_pile_of_five_objects_at_one_point_is_separated_and_simulates():
    """The model's stock output: five objects written at one position, sunk into the floor. Separated, no contact
    is deeper than the tolerance, velocities and physics are kept, and the rollout is valid."""
    objects = (
        "- type: box\n  size: [0.2, 0.2, 0.2]\n  state: {position: [0, 1, 0.1], linear_velocity: [1, 0, 0]}\n"
        "- type: box\n  size: [0.15, 0.2, 0.1]\n  state: {position: [0, 1, 0.1]}\n"
        "- type: sphere\n  radius: 0.2\n  state: {position: [0, 1, 0.1]}\n"
        "- type: sphere\n  radius: 0.1\n  state: {position: [0, 1, 0.1]}\n"
        "- type: cylinder\n  radius: 0.2\n  height: 0.3\n  state: {position: [0, 1, 0.1]}\n"
    )
    scene = _scene(objects)
    result = separate_start(scene)
    assert set(result.moved) == set(scene.names) and 1 < result.rounds < 100
    assert sim.start_overlap_pairs(result.scene) == {} and sim.simulate(result.scene).valid
    for before, after in zip(scene.objects, result.scene.objects, strict=True):
        assert after.physics == before.physics and after.state.linear_velocity == before.state.linear_velocity
    again = separate_start(result.scene, tolerance=2e-3)  # what the rounds left is within their tolerance
    assert again.moved == {}


def test_separating_follows_a_tilted_floor():
    """On a floor tilted 10 degrees about x a sphere sunk 0.1 m moves out along the floor's normal
    (0, -sin 10°, cos 10°)."""
    scene = _scene(
        "- type: sphere\n  radius: 0.2\n  state: {position: [0, 0, 0.1]}\n- type: environment\n  floor_tilt: [10, 0]\n"
    )
    d = np.array(separate_start(scene).moved["sphere_0"])
    normal = d / np.linalg.norm(d)
    assert np.allclose(abs(normal), (0, np.sin(np.radians(10)), np.cos(np.radians(10))), atol=1e-6), normal


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"tolerance": 0}, "tolerance = 0: must be a finite number of metres > 0"),
        ({"tolerance": float("nan")}, "tolerance = nan"),
        ({"max_rounds": 0}, "max_rounds = 0: must be a whole number >= 1"),
        ({"max_rounds": 1.5}, "max_rounds = 1.5"),
    ],
)
def test_bad_settings_are_named(kwargs, message):
    scene = _scene("- type: sphere\n  radius: 0.2\n  state: {position: [0, 1, 0.2]}\n")
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        separate_start(scene, **kwargs)
    with pytest.raises(TypeError, match="scene"):
        separate_start(dump(scene))


def test_a_row_of_overlaps_halves_each_round():
    """Spheres of radius 0.2 at x = 0, 0.3, 0.6 overlap by 0.1 m pairwise: a round moves the outer ones out by
    0.05 and the middle one not at all (its two pushes cancel), so the overlaps halve each round: 0.1 / 2^k <=
    1e-3 after k = 7 rounds, the outer ones moved 0.05 + 0.025 + ... = 0.1 (1 - 2^-7) each.
    With max_rounds=2 the 0.025 m left, within the simulation's MAX_START_OVERLAP, is returned as it is."""
    sphere = "- type: sphere\n  radius: 0.2\n  state: {{position: [{x}, 1, 0.2]}}\n"
    scene = _scene("".join(sphere.format(x=x) for x in (0.0, 0.3, 0.6)))
    result = separate_start(scene)
    assert result.rounds == 7 and "sphere_1" not in result.moved
    assert np.allclose(result.moved["sphere_0"], (-(0.1 - 0.1 / 2**7), 0, 0))
    short = separate_start(scene, max_rounds=2)  # 0.025 m left, within what the simulation accepts: returned
    assert short.rounds == 2 and np.allclose(short.moved["sphere_0"], (-0.075, 0, 0))


def test_refine_starts_from_the_separated_scene_when_it_scores_higher():
    """Two spheres the prediction writes at one point, where the video shows them 0.4 m apart: refinement scores
    the prediction (invalid: an overlapping start) and its separated start, and starts from the latter ('separated'
    in the trace); `before` stays the prediction's score. With separate=False it starts from the prediction."""
    from aynamics.observation import Observation
    from aynamics.refine import refine

    sphere = "- type: sphere\n  radius: 0.2\n  state: {{position: [{x}, 1.0, 0.2]}}\n"
    truth = _scene(sphere.format(x=-0.2) + sphere.format(x=0.2))
    pred = _scene(sphere.format(x=0.0) * 2)
    obs = Observation.from_scene(truth)
    result = refine(pred, obs, params=["position"], budget=3, seconds=30)
    assert result.trace[1][3] == "separated" and result.start != pred and result.simulations <= 3 + 1
    assert result.before.iou_full == 0 and result.after.iou_full > 0.5
    assert sim.start_overlap_pairs(result.start) == {}
    plain = refine(pred, obs, params=["position"], budget=3, seconds=30, separate=False)
    assert plain.start == pred and all(stage != "separated" for *_, stage in plain.trace)


def test_predict_separates_on_request(tmp_path, monkeypatch, capsys):
    """`aynamics predict --separate` with the model swapped for a fixed response of two spheres at one point: the
    YAML printed is the separated scene, after one comment line per object moved; --json gives "moved"."""
    from aynamics import adapters, lm
    from aynamics.cli import main

    sphere = "- type: sphere\n  radius: 0.2\n  state: {position: [0, 1.0, 0.2]}\n"
    scene = _scene(sphere * 2)
    monkeypatch.setattr(adapters, "load_adapter", lambda adapter, device: (None, lm.ModelSpec(), lm.PromptSpec()))
    monkeypatch.setattr(lm, "load_processor", lambda spec, prompt: None)
    monkeypatch.setattr(lm, "prompt_inputs", lambda processor, prompt, frames: {})
    monkeypatch.setattr(lm, "greedy_texts", lambda model, processor, prompts, max_new_tokens: [dump(scene)])
    (tmp_path / "aynamics.json").write_text(json.dumps(adapters.adapter_meta(lm.ModelSpec(), lm.PromptSpec())))
    frames = tmp_path / "frames"
    frames.mkdir()
    import imageio.v3 as iio

    for k in range(10):
        iio.imwrite(frames / f"{k}.png", np.zeros((32, 32, 3), np.uint8))
    args = ["predict", "--adapter", str(tmp_path), str(frames), "--device", "cpu"]
    assert main([*args, "--separate"]) == 0
    out = capsys.readouterr().out
    separated = separate_start(scene).scene
    assert out.startswith("# separated: sphere_0 moved by [") and out.endswith(dump(separated))
    assert out.count("# separated: ") == 2
    assert main([*args, "--separate", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["yaml"] == dump(separated) and set(got["moved"]) == {"sphere_0", "sphere_1"} and got["valid"]
    assert main(args) == 0 and capsys.readouterr().out == dump(scene)


def test_cli_refine_separates_unless_told_not_to(tmp_path, capsys):
    """`aynamics refine` of two spheres written at one point: the JSON trace shows the separated start;
    `--no-separate` starts from the prediction as written."""
    from aynamics.cli import main

    sphere = "- type: sphere\n  radius: 0.2\n  state: {{position: [{x}, 1.0, 0.2]}}\n"
    truth, pred = tmp_path / "truth.yaml", tmp_path / "pred.yaml"
    truth.write_text(sphere.format(x=-0.2) + sphere.format(x=0.2) + CAMERA)
    pred.write_text(sphere.format(x=0.0) * 2 + CAMERA)
    args = ["refine", str(pred), "--observed", str(truth), "--budget", "3", "--params", "position", "--json"]
    stages = []
    for extra in ([], ["--no-separate"]):
        assert main([*args, *extra]) == 0
        stages.append([stage for *_, stage in json.loads(capsys.readouterr().out)["trace"]])
    assert "separated" in stages[0] and "separated" not in stages[1]


def test_evaluation_scores_the_responses_separated_beside_them(tmp_path, monkeypatch, capsys):
    """`evaluate._score(separate=True)` of two records whose video shows two spheres 0.4 m apart: the response
    that writes them at one point does not simulate (validity 0, IoU 0), separated it does and overlaps the video;
    a response without a scene stays invalid in both columns. `aynamics evaluate --separate` hands it on and
    records it in metrics.json's settings."""
    from aynamics import evaluate as ev
    from aynamics import evaluate_cli
    from aynamics.observation import Observation
    from aynamics.separate import separate_texts

    sphere = "- type: sphere\n  radius: 0.2\n  state: {{position: [{x}, 1.0, 0.2]}}\n"
    truth = _scene(sphere.format(x=-0.2) + sphere.format(x=0.2))
    obs = Observation.from_scene(truth)
    records = [{"index": k, "scene_yaml": dump(truth), "scene": truth, "observation": obs} for k in range(2)]
    texts = [dump(_scene(sphere.format(x=0.0) * 2)), "no scene"]
    assert separate_texts(texts) == [dump(separate_start(parse(texts[0])).scene), "no scene"]
    result = ev._score(
        records, texts, average=None, refine_budget=0, refine_seconds=1.0, progress=False, n=2, split_size=2,
        what="x", separate=True,
    )  # fmt: skip
    model, separated = result.table["model"], result.table["model, separated"]
    assert (model["sim_valid"], model["iou_full"]) == (0.0, 0.0)
    assert separated["sim_valid"] == 0.5 and separated["iou_full"] > 0.25 and separated["yaml_valid"] == 0.5
    calls = []

    def fixed(adapter, source, **kwargs):
        calls.append(kwargs)
        return ev.Evaluation({"model": {"yaml_valid": 1.0}}, [{"index": 0}], ["t"], {"yaml_valid": [1.0]})

    monkeypatch.setattr(evaluate_cli, "evaluate_adapter", fixed)
    (tmp_path / "adapter").mkdir()
    args = ["evaluate", "--adapter", str(tmp_path / "adapter"), "--data", "D", "--quiet", "--out", str(tmp_path / "e")]
    from aynamics.cli import main

    assert main([*args, "--separate"]) == 0
    capsys.readouterr()
    assert calls[0]["separate"] is True
    assert json.loads((tmp_path / "e" / "metrics.json").read_text())["settings"]["separate"] is True


def test_a_tall_tower_whose_rounds_run_out_within_the_simulations_tolerance_is_separated():
    """Ten boxes of half-height 0.1 stacked, each written 3 cm into the one below (the bottom one 3 cm into the
    floor): the scene simulates as written (no overlap deeper than MAX_START_OVERLAP), but a chain of ten halves
    its overlaps slowly (~300 rounds to 1 mm): after MAX_ROUNDS = 200 some 6.6 mm are left. That is no reason to
    refuse it (`predict --separate` called the valid scene invalid): it comes back as the rounds left it, still
    simulating; a tower 6 cm deep at each joint (an overlapping start) is made valid the same way. What is left
    deeper than MAX_START_OVERLAP is still refused: a row 0.2 m deep pairwise has 0.1 m left after one round."""

    def tower(overlap: float, n: int = 10, h: float = 0.1):
        z = [h - overlap + k * (2 * h - overlap) for k in range(n)]
        return _scene(
            "".join(f"- type: box\n  size: [0.2, 0.2, {h}]\n  state: {{position: [0, 1, {x:.4f}]}}\n" for x in z)
        )

    for overlap in (0.03, 0.06):
        scene = tower(overlap)
        assert sim.simulate(scene).valid == (overlap < sim.MAX_START_OVERLAP)
        result = separate_start(scene)
        assert result.rounds == 200 and len(result.moved) == 10
        assert sim.start_overlap_pairs(result.scene) == {} and sim.simulate(result.scene).valid
    sphere = "- type: sphere\n  radius: 0.2\n  state: {{position: [{x}, 1, 0.2]}}\n"
    with pytest.raises(
        ValueError, match=r"still overlap after max_rounds = 1 rounds: sphere_\d and sphere_\d by 0.1 m"
    ):
        separate_start(_scene("".join(sphere.format(x=x) for x in (0.0, 0.2, 0.4))), max_rounds=1)
