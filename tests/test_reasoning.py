"""Motion-reasoning text: every fact agrees with the simulation it describes."""

from __future__ import annotations

import re

import numpy as np
import pytest

from aynamics import reasoning as rs
from aynamics.sampler import SamplerConfig, sample_scene, scene_seed
from aynamics.scene import dump, load, parse
from aynamics.simulate import REST_ANGULAR, simulate_batch

FRAMES = np.arange(0, 30, 3)


@pytest.fixture(scope="module")
def simulated():
    cfg = SamplerConfig(min_objects=2, max_objects=4, collision_share=0.7)
    scenes = [sample_scene(np.random.default_rng(scene_seed(7, i)), cfg) for i in range(16)]
    scenes.append(load("tests/assets/paper_example.yaml"))
    rollouts = simulate_batch(scenes, nthread=2)
    return [(s, r) for s, r in zip(scenes, rollouts, strict=True) if r.valid]


def test_bins_follow_the_thresholds():
    """Edges from the paper: x < -2 far left, [-2,-1) moderately, [-1,-0.5) slightly, [-0.5,0.5] centre, ..."""
    cases = {-2.01: 0, -2.0: 1, -1.01: 1, -1.0: 2, -0.51: 2, -0.5: 3, 0.0: 3, 0.5: 3, 0.51: 4, 1.0: 4, 1.5: 5, 2.0: 5}
    for v, b in {**cases, 2.01: 6, -7.0: 0, 9.0: 6}.items():
        assert rs.position_bin(v) == b, v
    assert rs.position_words(np.array([-5.0, -0.3, 0.4])) == ("far left", "at mid-depth", "close to the surface")


def test_direction_words():
    assert rs.direction_words(np.array([4.3, 2.5, 0.0])) == ["rightward", "forward"]
    assert rs.direction_words(np.array([-1.0, -0.1, 0.0])) == ["leftward"]
    assert rs.direction_words(np.array([0.0, 0.0, 0.001])) == []
    # "at least a quarter": |v| = sqrt(1 + 15) = 4 exactly, and x = 1 is exactly 0.25 × 4: named
    assert rs.direction_words(np.array([1.0, np.sqrt(15.0), 0.0])) == ["rightward", "forward"]


def test_visibility_from_segmentation():
    seg = np.full((3, 4, 5), -1, np.int16)
    seg[0, 0, 0] = 0
    seg[0, 1, 1] = 1
    seg[2, :, :] = 1
    vis = rs.visibility(seg, 2)
    assert vis.tolist() == [[True, True], [False, False], [False, True]]
    assert rs.visibility(seg, 2, min_pixels=2).tolist() == [[False, False], [False, False], [False, True]]
    with pytest.raises(ValueError, match=r"segmentation values in \[-1, 1\]: must be in \[-1, 0\]"):
        rs.visibility(seg, 1)


def _object_lines(text: str, n: int) -> list[str]:
    return text.split("\n")[:n]


def _check_facts(scene, rollout, visible, text):
    times = rollout.t[FRAMES]
    lines = _object_lines(text, len(scene.objects))
    for i, (obj, line) in enumerate(zip(scene.objects, lines, strict=True)):
        name = rollout.names[i]
        assert line.startswith(name[0].upper() + name[1:] + ":")
        assert f"{obj.physics.mass:.2f} kg" in line
        for word in rs.position_words(rollout.position[0, i]):  # bins recomputed from the state
            assert f" {word}" in line, (word, line)
        v0 = rollout.linear_velocity[0, i]
        speeds = re.findall(r"(\d+\.\d+) m/s", line)
        if np.linalg.norm(v0) >= 0.02:
            assert abs(float(speeds[0]) - np.linalg.norm(v0)) <= 0.0051
            for d in rs.direction_words(v0):
                assert d in line
        else:
            assert not speeds
            spin = np.linalg.norm(rollout.angular_velocity[0, i])
            in_place = re.search(r"(?:spinning|spins|turning) at (\d+\.\d+) rad/s", line)
            assert (in_place is not None) == (spin > REST_ANGULAR), line
            still = re.search("starts at rest|initially stationary|begins motionless", line)
            assert (still is None) == (spin > REST_ANGULAR), line
        rest = rollout.rest_time[i]
        stop = re.search(r"(?:stops|comes to rest|halts) at t=(\d+\.\d+)s", line)
        if rest is None or rest == 0.0:
            assert stop is None
        else:
            assert abs(float(stop.group(1)) - rest) < 0.006
        ground = [(c.start, c.end) for c in rollout.contacts if c.a == name and c.b == "floor"]
        got = [(float(a), float(b)) for a, b in re.findall(r"(\d+\.\d\d)-(\d+\.\d\d)s", line)]
        assert np.allclose(got, ground, atol=0.006) if ground else not got
        hits = [(c.b, c.start) for c in rollout.contacts if c.a == name and c.b != "floor"]
        said = [
            (o, float(t))
            for o, t in re.findall(r"(?:Collides with|Hits|Makes contact with) (\w+) at t=(\d+\.\d+)s", line)
        ]
        assert [o for o, _ in said] == [o for o, _ in hits]
        assert np.allclose([t for _, t in said], [t for _, t in hits], atol=0.006)
    vis_line = next(ln for ln in text.split("\n") if ln.startswith("Visibility:"))
    for i, name in enumerate(rollout.names):
        k = re.search(rf"{name} (?:visible in|is seen in|appears in) (\d+)/(\d+) frames", vis_line)
        assert (int(k.group(1)), int(k.group(2))) == (int(visible[:, i].sum()), len(FRAMES))
        start = vis_line.index(f"{name} ")
        ends = [vis_line.index(f" {m} ") for m in rollout.names[i + 1 :]]
        sentence = vis_line[start : min(ends, default=len(vis_line))]
        for j in range(1, len(FRAMES)):
            if visible[j - 1, i] != visible[j, i]:  # leaves or enters at the first frame of the change
                assert f"t={times[j]:.2f}s" in sentence, (name, sentence)
    resting = sum(r is not None for r in rollout.rest_time)
    assert f"{resting} of {len(scene.objects)}" in text or f"{resting}/{len(scene.objects)}" in text


def test_an_object_spinning_in_place_is_not_said_to_start_at_rest():
    """A box with no linear velocity spinning at 2 rad/s about z: "spinning at 2.00 rad/s" (or a paraphrase),
    never "starts at rest" (helper-39 found 5 of 50 generated objects so described)."""
    from aynamics.simulate import simulate

    scene = parse(
        """
- type: box
  size: [0.2, 0.1, 0.1]
  state: {position: [0, 1, 0.1], orientation: [1, 0, 0, 0], linear_velocity: [0, 0, 0], angular_velocity: [0, 0, 2]}
  physics: {mass: 1.0, friction: [0.5, 0.0], damping: -4}
- type: camera
  fovy: 45
  orientation: 45
  position: [0, -2, 3]
"""
    )
    rollout = simulate(scene)
    for seed in range(3):
        text = rs.reasoning_text(scene, rollout, rollout.in_view[FRAMES], rollout.t[FRAMES], seed=seed)
        first = text.split("\n")[0]
        assert re.search(r"(?:spinning|spins|turning) at 2\.00 rad/s", first), first
        _check_facts(scene, rollout, rollout.in_view[FRAMES], text)


def test_facts_agree_with_the_simulation(simulated):
    """Bins, speeds, stop times, ground intervals, collisions and visibility recomputed from the rollout."""
    assert len(simulated) >= 12
    some_collision = False
    for k, (scene, rollout) in enumerate(simulated):
        visible = rollout.in_view[FRAMES].copy()  # stands in for segmentation-based visibility here
        visible[-3:, 0] = False  # object 0 leaves the view: the text must say when
        text = rs.reasoning_text(scene, rollout, visible, rollout.t[FRAMES], seed=k)
        _check_facts(scene, rollout, visible, text)
        assert "leaves the view" in text or "exits the frame" in text or "goes out of view" in text
        some_collision |= any(c.b != "floor" for c in rollout.contacts)
    assert some_collision


def test_paraphrases_keep_the_facts(simulated):
    scene, rollout = simulated[0]
    visible = rollout.in_view[FRAMES]
    texts = [rs.reasoning_text(scene, rollout, visible, rollout.t[FRAMES], seed=s) for s in range(6)]
    assert len(set(texts)) > 1
    numbers = {tuple(re.findall(r"\d+\.\d+", t)) for t in texts}
    assert len(numbers) == 1  # same facts, same order, different wording
    assert rs.reasoning_text(scene, rollout, visible, rollout.t[FRAMES], seed=3) == texts[3]


def test_targets_round_trip(simulated):
    scene, rollout = simulated[0]
    text = rs.reasoning_text(scene, rollout, rollout.in_view[FRAMES], rollout.t[FRAMES])
    target = rs.think_target(text, dump(scene))
    assert target.startswith("<think>\n") and "</think>\n\n<answer>\n" in target and target.endswith("</answer>")
    assert parse(target) == scene
    assert parse(rs.answer_target(dump(scene))) == scene


def test_bad_input_is_named(simulated):
    scene, rollout = simulated[0]
    with pytest.raises(ValueError, match=r"visible shape \(3, 1\)"):
        rs.reasoning_text(scene, rollout, np.ones((3, 1), bool), np.zeros(3))


def test_an_object_hidden_behind_another_is_not_said_to_leave_the_view(simulated):
    """No pixels while the centre is inside the picture: "hidden behind another object", then "reappears"; only an
    object whose centre is out of the picture "leaves the view"."""
    scene, rollout = simulated[0]
    n = len(scene.objects)
    visible = np.ones((len(FRAMES), n), dtype=bool)
    visible[3:5, 0] = False  # covered by another object at frames 9 and 12
    visible[7:, 1] = False  # out of the picture from frame 21
    inside = np.ones_like(visible)
    inside[7:, 1] = False
    times = rollout.t[FRAMES]
    for seed in range(3):
        line = rs.reasoning_text(scene, rollout, visible, times, seed=seed, in_picture=inside).split("\n")
        vis_line = next(ln for ln in line if ln.startswith("Visibility:"))
        first, second = vis_line.split(f" {rollout.names[1]} ")[0], vis_line.split(f" {rollout.names[1]} ")[1]
        assert re.search(r"(?:hidden behind|disappears behind|covered by) another object at t=0\.30s", first), first
        assert re.search(r"(?:reappears|comes out from behind another object|is uncovered) at t=0\.50s", first), first
        assert not re.search(r"leaves the view|exits the frame|goes out of view|enters the view", first), first
        assert re.search(r"(?:leaves the view|exits the frame|goes out of view) at t=0\.70s", second), second


def test_the_height_words_are_above_the_floor_where_the_floor_is():
    """A ball resting on a floor raised by `environment.floor_offset` 0.5 m (centre at z = 0.8) is "close to the
    surface", as it touches the ground the whole second; it was called "slightly raised" (world z)."""
    from aynamics.simulate import simulate

    scene = parse(
        """
- type: sphere
  radius: 0.3
  state: {position: [0, 1, 0.8], orientation: [1, 0, 0, 0], linear_velocity: [0, 0, 0], angular_velocity: [0, 0, 0]}
  physics: {mass: 1.0, friction: [0.5, 0.05], damping: -4}
- type: camera
  fovy: 50
  orientation: 45
  position: [0, -2, 3.5]
- type: environment
  floor_offset: 0.5
"""
    )
    rollout = simulate(scene)
    text = rs.reasoning_text(scene, rollout, rollout.in_view[FRAMES], rollout.t[FRAMES])
    assert "close to the surface" in text and "raised" not in text, text


def test_sizes_poses_and_the_collision_summary_by_hand():
    """Box half-extents (0.3, 0.2, 0.1) are told as full edges, "0.60 x 0.40 x 0.20 m". A cylinder turned 90° about z
    (w = z = √½) still stands: its axis' world z is 1 - 2(x² + y²) = 1, "upright"; one turned 90° about x (w = x = √½)
    has 1 - 2·½ = 0 < cos 45°, "lying". Two spheres 0.6 m apart (gap between surfaces) closing at 3 m/s without
    gravity meet 0.2 s in, first touching at frame 7 (7/30 = 0.23 s): the summary names the pair once."""
    h = 0.7071067811865476
    scene = parse(
        f"""
- {{type: sphere, radius: 0.2, state: {{position: [-0.5, 1, 1], linear_velocity: [1.5, 0, 0]}},
   physics: {{mass: 1.0, friction: [0.0, 0.0], damping: -8}}}}
- {{type: sphere, radius: 0.2, state: {{position: [0.5, 1, 1], linear_velocity: [-1.5, 0, 0]}},
   physics: {{mass: 1.0, friction: [0.0, 0.0], damping: -8}}}}
- {{type: box, size: [0.3, 0.2, 0.1], state: {{position: [-1.5, 2.5, 0.1]}}}}
- {{type: cylinder, radius: 0.1, height: 0.4, state: {{position: [1.5, 2.5, 0.2], orientation: [{h}, 0, 0, {h}]}}}}
- {{type: cylinder, radius: 0.1, height: 0.4, state: {{position: [0, 3, 0.1], orientation: [{h}, {h}, 0, 0]}}}}
- {{type: camera, position: [0, -2, 3], orientation: 45, fovy: 60}}
- {{type: gravity, gravity: [0, 0, 0]}}
"""
    )
    from aynamics.simulate import simulate

    rollout = simulate(scene)
    for seed in range(3):
        lines = rs.reasoning_text(scene, rollout, rollout.in_view[FRAMES], rollout.t[FRAMES], seed=seed).split("\n")
        assert "0.60 x 0.40 x 0.20 m" in lines[2], lines[2]
        assert re.search(r"\bupright\b", lines[3]) and "lying" not in lines[3], lines[3]
        assert re.search(r"\blying\b", lines[4]) and "upright" not in lines[4], lines[4]
        hits = re.match(r"(?:Interactions|Summary of interactions|Collisions): (.*?)\. ", lines[-1]).group(1)
        assert hits == "sphere_0 and sphere_1 at t=0.23s", lines[-1]


def test_an_object_coming_into_the_picture_enters_the_view(simulated):
    """No pixels with its centre outside the picture at frames 0, 3 and 6 (t = 0, 0.1, 0.2), then seen with its
    centre inside from frame 9 on: it "enters the view at t=0.30s"; "reappears" is for an object that was hidden
    while its centre was in the picture."""
    scene, rollout = simulated[0]
    visible = np.ones((len(FRAMES), len(scene.objects)), dtype=bool)
    visible[:3, 0] = False
    inside = visible.copy()
    for seed in range(3):
        lines = rs.reasoning_text(scene, rollout, visible, rollout.t[FRAMES], seed=seed, in_picture=inside)
        vis_line = next(ln for ln in lines.split("\n") if ln.startswith("Visibility:"))
        first = vis_line.split(f" {rollout.names[1]} ")[0]
        assert re.search(r"(?:enters the view|comes into the frame|becomes visible) at t=0\.30s", first), first
        assert not re.search(r"reappears|comes out from behind|is uncovered", first), first


def test_height_above_a_tilted_floor_is_along_its_normal():
    """floor_tilt (10, 0) turns the floor's normal to Rx(10°)·ẑ = (0, -sin 10°, cos 10°) = (0, -0.17365, 0.98481):
    the point (0, 2, 1.1) over a floor raised 0.1 m is 2·(-0.17365) + 1·0.98481 = 0.63752 m above it ("slightly
    raised"; the normal's sign flipped would give 1.33211, "raised")."""
    scene = parse(
        """
- {type: sphere, radius: 0.2, state: {position: [0, 2, 1.1]}}
- {type: camera, position: [0, -2, 3]}
- {type: environment, floor_tilt: [10, 0], floor_offset: 0.1}
"""
    )
    assert rs.floor_heights(scene, np.array([[0.0, 2.0, 1.1]])) == pytest.approx([0.63752], abs=1e-5)
    assert rs.BIN_WORDS["z"][rs.position_bin(0.63752)] == "slightly raised"
