"""The scene sampler: ranges from the one table, determinism, physical sense, collisions."""

from __future__ import annotations

import numpy as np
import pytest

from aynamics import camera as camlib
from aynamics.sampler import SamplerConfig, sample_scene, scene_seed
from aynamics.scene import Box, Cylinder, dump
from aynamics.simulate import half_extents, simulate_batch


def _scenes(n: int, cfg: SamplerConfig = SamplerConfig(), seed: int = 0):
    return [sample_scene(np.random.default_rng(scene_seed(seed, i)), cfg) for i in range(n)]


def _rot(q):
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_config_checked_against_range_table():
    with pytest.raises(ValueError, match=r"box_size = \[0.1, 3.0\].*RANGES\['box.size'\]"):
        SamplerConfig(box_size=(0.1, 3.0))
    with pytest.raises(ValueError, match=r"camera_fovy = \[5.0, 50.0\]"):
        SamplerConfig(camera_fovy=(5.0, 50.0))
    with pytest.raises(ValueError, match="collision_share = 1.5"):
        SamplerConfig(collision_share=1.5)
    with pytest.raises(ValueError, match="min_objects = 3, max_objects = 2"):
        SamplerConfig(min_objects=3, max_objects=2)


def test_deterministic_per_index():
    a, b = _scenes(5), _scenes(5)
    assert [dump(s) for s in a] == [dump(s) for s in b]
    assert len({dump(s) for s in a}) == 5
    assert dump(_scenes(1, seed=1)[0]) != dump(a[0])


def test_scenes_are_sensible_and_in_view():
    """Values inside the sampler's ranges; objects on or above the floor, apart, centres in the picture."""
    cfg = SamplerConfig()
    for s in _scenes(60, cfg):
        assert cfg.min_objects <= len(s.objects) <= cfg.max_objects
        assert cfg.camera_fovy[0] <= s.camera.fovy <= cfg.camera_fovy[1]
        cam = camlib.matrices(s.camera, 150, 100)
        for i, o in enumerate(s.objects):
            lo, hi = cfg.mass
            assert lo - 1e-3 <= o.physics.mass <= hi + 1e-3
            if isinstance(o, Box):
                assert all(cfg.box_size[0] <= v <= cfg.box_size[1] for v in o.size)
            rot = _rot(o.state.orientation)
            lowest = o.state.position[2] - np.abs(rot[2] * half_extents(o)).sum()  # box/cylinder bounding box
            if not isinstance(o, Box | Cylinder):
                lowest = o.state.position[2] - o.radius
            assert lowest >= -2e-3, (dump(s), i)
            assert lowest <= cfg.drop_height[1] + 2e-3
            uv, z = cam.project(np.array(o.state.position))
            assert z > 0 and 0 <= uv[0] <= 150 and 0 <= uv[1] <= 100
            for p in s.objects[i + 1 :]:
                d = np.hypot(*(np.subtract(o.state.position, p.state.position)[:2]))
                assert d > 0.1
    shapes = {o.type for s in _scenes(30, cfg) for o in s.objects}
    assert shapes == {"box", "sphere", "cylinder"}


def test_shape_mix():
    assert {o.type for s in _scenes(15, SamplerConfig(shape_weights=(0, 1, 0))) for o in s.objects} == {"sphere"}


def test_collision_share_controls_collisions():
    """Aimed scenes collide most of the time; with nothing moving and no aim, objects never touch."""
    aimed = _scenes(30, SamplerConfig(min_objects=2, max_objects=3, collision_share=1.0))
    hits = [any(c.b != "floor" for c in r.contacts) for r in simulate_batch(aimed, nthread=2)]
    assert np.mean(hits) >= 0.6
    still = _scenes(20, SamplerConfig(min_objects=2, collision_share=0.0, moving_share=0.0, airborne_share=0.0))
    rollouts = simulate_batch(still, nthread=2)
    assert all(r.valid for r in rollouts)
    assert not any(c.b != "floor" for r in rollouts for c in r.contacts)


def test_sampled_scenes_simulate_validly():
    rollouts = simulate_batch(_scenes(40), nthread=2)
    assert np.mean([r.valid for r in rollouts]) >= 0.95
    assert np.mean([r.in_view[0].all() for r in rollouts]) == 1.0


def test_objects_listed_left_to_right_in_the_first_frame():
    """left_to_right: image x of the centres increasing; the same draws as `drawn`, only reordered and renamed."""
    with pytest.raises(ValueError, match="object_order = 'random'"):
        SamplerConfig(object_order="random")
    sorted_, drawn = _scenes(30, SamplerConfig(object_order="left_to_right")), _scenes(30)
    reordered = 0
    for s, d in zip(sorted_, drawn):
        u = camlib.matrices(s.camera, 150, 100).project(np.array([o.state.position for o in s.objects]))[0][:, 0]
        assert np.all(np.diff(u) > 0)
        key = sorted(o.state.position for o in s.objects)
        assert key == sorted(o.state.position for o in d.objects)  # same objects, same camera
        assert s.camera == d.camera and s.gravity == d.gravity
        reordered += [o.state.position for o in s.objects] != [o.state.position for o in d.objects]
    assert reordered >= 5  # the draw order is not already left to right


def test_object_counts_span_min_to_max_inclusive():
    """`min_objects`..`max_objects` inclusive: 40 scenes of 1-3 objects hold each of 1, 2 and 3 (a uniform draw
    misses one of three counts in 40 tries with chance 3·(2/3)^40 < 1e-6); min = max = 2 gives exactly 2."""
    assert {len(s.objects) for s in _scenes(40, SamplerConfig(min_objects=1, max_objects=3))} == {1, 2, 3}
    assert {len(s.objects) for s in _scenes(10, SamplerConfig(min_objects=2, max_objects=2))} == {2}


def test_spheres_start_rolling_without_slipping():
    """ω = ẑ × v / r: the contact point's velocity v + ω × (0, 0, -r) is 0. E.g. v = (1, 2, 0) at r = 0.2:
    ω = (-2, 1, 0) / 0.2 = (-10, 5, 0), and ω × (0, 0, -0.2) = (5·(-0.2), -(-10)·(-0.2), 0) = (-1, -2, 0) = -v.
    (The cap at 50 rad/s never binds: speed <= 5 m/s and r >= 0.1 m; 1e-3 m/s: the scene stores its numbers rounded.)"""
    cfg = SamplerConfig(shape_weights=(0, 1, 0), moving_share=1.0, collision_share=0.0)  # aimed-at spheres stand still
    spheres = [o for s in _scenes(20, cfg) for o in s.objects]
    assert len(spheres) >= 20
    for o in spheres:
        v, w = np.array(o.state.linear_velocity), np.array(o.state.angular_velocity)
        assert np.linalg.norm(v) > 0.4
        np.testing.assert_allclose(v + np.cross(w, [0.0, 0.0, -o.radius]), 0.0, atol=1e-3)


def test_gravity_and_restitution_shares_are_chances_of_the_optional_values():
    """gravity_share 0: every scene has g = (0, 0, -9.81); 1: every g_z is drawn from gravity_z = [-15, -5]
    (rounded to 0.01). restitution_share 0: no object has `restitution`; 1: every object has one in [0, 0.8]."""
    never = _scenes(15, SamplerConfig(gravity_share=0.0, restitution_share=0.0))
    assert {s.gravity for s in never} == {(0.0, 0.0, -9.81)}
    assert all(o.physics.restitution is None for s in never for o in s.objects)
    always = _scenes(15, SamplerConfig(gravity_share=1.0, restitution_share=1.0))
    gz = [s.gravity[2] for s in always]
    assert all(-15.0 <= g <= -5.0 and g == round(g, 2) for g in gz) and len(set(gz)) >= 10
    assert all(0.0 <= o.physics.restitution <= 0.8 for s in always for o in s.objects)
