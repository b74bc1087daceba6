"""MuJoCo simulation against closed-form physics, per-field monotonicity, determinism, divergence, CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest

from aynamics import cli
from aynamics import scene as S
from aynamics import simulate as sim

ASSETS = Path(__file__).parent / "assets"
DT = 1 / 240


def scene(objects, gravity=(0.0, 0.0, -9.81), environment=None, camera=None):
    items = [*objects, camera or {"type": "camera", "position": [0, -6, 4], "orientation": 60, "fovy": 60}]
    items.append({"type": "gravity", "gravity": list(gravity)})
    if environment:
        items.append({"type": "environment", **environment})
    return S.from_items(items)


def box(x=0.0, y=0.0, v=(3.0, 0.0, 0.0), mu=0.5, crr=0.0, size=(0.3, 0.3, 0.1), mass=1.0, damping=-8.0, name=None):
    d = {
        "type": "box",
        "size": list(size),
        "state": {"position": [x, y, size[2]], "linear_velocity": list(v)},
        "physics": {"friction": [mu, crr], "mass": mass, "damping": damping},
    }
    return d | ({"name": name} if name else {})


def sphere(
    x=0.0,
    y=0.0,
    z=None,
    v=(0.0, 0.0, 0.0),
    w=(0.0, 0.0, 0.0),
    r=0.2,
    mu=0.5,
    crr=0.0,
    mass=1.0,
    damping=-8.0,
    name=None,
    **kw,
):
    d = {
        "type": "sphere",
        "radius": r,
        "state": {"position": [x, y, r if z is None else z], "linear_velocity": list(v), "angular_velocity": list(w)},
        "physics": {"friction": [mu, crr], "mass": mass, "damping": damping, **kw},
    }
    return d | ({"name": name} if name else {})


def run(s, duration=1.0, fps=30, substeps=8):
    r = sim.simulate(s, sim.SimConfig(duration=duration, fps=fps, substeps=substeps))
    assert r.valid, r.reason
    return r


# --------------------------------------------------------------------------------------------
# Closed-form physics
# --------------------------------------------------------------------------------------------
def test_projectile_under_custom_gravity():
    """x(t) = x0 + v t and z(t) = z0 + vz t + g t²/2. MuJoCo's semi-implicit Euler adds exactly g·dt·t/2 to z:
    v_k = v0 + g k dt, z_k = z0 + dt Σ v_j = z0 + vz t + g t²/2 + g dt t/2 (t = k dt)."""
    g = -3.7  # Mars
    s = scene([sphere(x=-1, z=5.0, v=(1.5, 0.5, 2.0), r=0.1)], gravity=(0, 0, g))
    r = run(s)
    t = r.t
    np.testing.assert_allclose(r.position[:, 0, 0], -1 + 1.5 * t, atol=1e-7)
    np.testing.assert_allclose(r.position[:, 0, 1], 0.5 * t, atol=1e-7)
    np.testing.assert_allclose(r.position[:, 0, 2], 5 + 2 * t + 0.5 * g * t**2 + 0.5 * g * DT * t, atol=1e-6)
    assert abs(r.position[-1, 0, 2] - (5 + 2 + 0.5 * g)) < 0.01  # the continuous law within 1 cm after 1 s
    np.testing.assert_allclose(r.linear_velocity[:, 0, 2], 2 + g * t, atol=1e-7)


@pytest.mark.parametrize("mu", [0.2, 0.5, 1.0])
def test_sliding_box_stops_after_v2_over_2_mu_g(mu):
    """A flat box sliding at v = 3 m/s with friction μ stops after d = v² / (2 μ g), at t = v / (μ g)."""
    s = scene([box(v=(3.0, 0.0, 0.0), mu=mu)])
    r = run(s, duration=2.5)
    d = r.position[-1, 0, 0] - r.position[0, 0, 0]
    expected = 9 / (2 * mu * 9.81)
    assert abs(d / expected - 1) < 0.03
    assert abs(r.rest_time[0] - 3 / (mu * 9.81)) < 0.1


def test_floor_does_not_override_object_friction():
    """Slippery and grippy objects both follow their own μ (the floor has priority 0 and friction 0):
    d(t) = v t - μ g t² / 2 until t_stop = v / (μ g)."""
    for mu in (0.05, 1.5):
        r = run(scene([box(v=(2.0, 0.0, 0.0), mu=mu)]), duration=3.0)
        d = r.position[-1, 0, 0] - r.position[0, 0, 0]
        t = min(3.0, 2.0 / (mu * 9.81))
        assert abs(d / (2.0 * t - 0.5 * mu * 9.81 * t * t) - 1) < 0.03


def test_sphere_rolls_without_slipping():
    """v = ω r is kept (no rolling resistance): speed constant, contact point at rest."""
    r_ = 0.25
    r = run(scene([sphere(v=(2.0, 0, 0), w=(0, 2.0 / r_, 0), r=r_)]))
    np.testing.assert_allclose(r.linear_velocity[:, 0, 0], 2.0, rtol=2e-3)
    np.testing.assert_allclose(r.angular_velocity[:, 0, 1] * r_, r.linear_velocity[:, 0, 0], rtol=2e-3)
    assert abs(r.position[-1, 0, 0] - 2.0) < 0.01


def test_sliding_sphere_ends_rolling_at_five_sevenths():
    """A sphere launched sliding without spin ends up rolling at 5/7 of its speed, whatever μ (angular momentum
    about the contact point is conserved: m v0 r = m v r + 2/5 m r² v / r)."""
    r = run(scene([sphere(v=(2.0, 0, 0), r=0.2, mu=0.4)]), duration=1.5)
    assert abs(r.linear_velocity[-1, 0, 0] - 2.0 * 5 / 7) < 0.005
    assert abs(r.angular_velocity[-1, 0, 1] * 0.2 - 2.0 * 5 / 7) < 0.005


def test_rolling_resistance_decelerates_at_c_rr_g_over_1_4():
    """Rolling-resistance torque c_rr·r·N on a rolling sphere: a = c_rr g / (1 + 2/5) (elliptic cones)."""
    c_rr = 0.05
    r = run(scene([sphere(v=(2.0, 0, 0), w=(0, 10.0, 0), r=0.2, crr=c_rr)]), duration=0.5)
    decel = (r.linear_velocity[0, 0, 0] - r.linear_velocity[-1, 0, 0]) / 0.5
    assert abs(decel / (c_rr * 9.81 / 1.4) - 1) < 0.05


def test_world_frame_spin_is_honoured():
    """A free, tilted box spinning about world z at 3 rad/s (z is a principal axis here only in the world frame
    if the box is turned about z): the output spin stays (0, 0, 3) in world axes, and the orientation advances by
    exp(ω t / 2) ⊗ q0 (left-multiplied: a world-frame rotation)."""
    q0 = np.array([math.cos(0.3), 0, 0, math.sin(0.3)])  # turned 0.6 rad about z: z stays a principal axis
    s = scene(
        [
            {
                "type": "box",
                "size": [0.3, 0.2, 0.1],
                "state": {"position": [0, 0, 2], "orientation": q0.tolist(), "angular_velocity": [0, 0, 3.0]},
                "physics": {"damping": -8},
            }
        ],
        gravity=(0, 0, 0),
    )
    r = run(s)
    np.testing.assert_allclose(r.angular_velocity[:, 0], np.tile([0, 0, 3.0], (len(r.t), 1)), atol=1e-6)
    half = 3.0 * r.t[-1] / 2
    expected = np.zeros(4)
    mujoco.mju_mulQuat(expected, np.array([math.cos(half), 0, 0, math.sin(half)]), q0 / np.linalg.norm(q0))
    assert min(np.abs(r.orientation[-1, 0] - expected).max(), np.abs(r.orientation[-1, 0] + expected).max()) < 1e-3


def test_world_spin_about_x_of_a_rotated_sphere():
    """The spin is given in world axes even when the body is rotated: a sphere turned 90° about z spinning about
    world x reports world x spin (body frame would read y)."""
    q = [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]
    s = scene([sphere(z=3, w=(4.0, 0, 0)) | {}], gravity=(0, 0, 0))
    items = S.to_items(s)
    items[0]["state"]["orientation"] = q
    r = run(S.from_items(items))
    np.testing.assert_allclose(r.angular_velocity[-1, 0], [4.0, 0, 0], atol=1e-6)


# --------------------------------------------------------------------------------------------
# Every field moves the rollout monotonically
# --------------------------------------------------------------------------------------------
def _monotone(values, strictly_increasing=True):
    d = np.diff(values)
    return bool(np.all(d > 0)) if strictly_increasing else bool(np.all(d < 0))


def test_mass_pushes_the_struck_object_further():
    """Momentum transfer: a heavier striker sends a resting target further."""
    out = []
    for m in (0.5, 1.0, 2.0, 4.0):
        s = scene([sphere(x=-1.0, v=(3, 0, 0), mass=m, mu=0.3, name="s"), sphere(x=0.0, mass=1.0, mu=0.3)])
        out.append(run(s).position[-1, 1, 0])
    assert _monotone(out)


def test_sliding_friction_shortens_the_slide():
    assert _monotone([run(scene([box(mu=mu)])).position[-1, 0, 0] for mu in (0.2, 0.4, 0.8, 1.6)], False)


def test_rolling_friction_shortens_the_roll():
    rolls = [run(scene([sphere(v=(2, 0, 0), w=(0, 10, 0), crr=c)])).position[-1, 0, 0] for c in (0.0, 0.02, 0.1, 0.3)]
    assert _monotone(rolls, False)


def test_damping_slows_free_flight_as_exp_minus_k_t():
    """Zero gravity: v(t) = v0 exp(-k t) with k = 10^damping, for any mass."""
    for damping, mass in ((-1.0, 0.3), (0.0, 5.0), (1.0, 2.0), (2.0, 0.05)):
        s = scene([sphere(z=3, v=(2, 0, 0), w=(0, 0, 5), damping=damping, mass=mass)], gravity=(0, 0, 0))
        r = run(s)
        k = 10.0**damping
        t = r.t[3]  # 0.1 s: at damping 2 the speed was exp(-8.36) of v0, not exp(-10) (the implicit step)
        assert abs(r.linear_velocity[3, 0, 0] / (2 * math.exp(-k * t)) - 1) < 0.01, damping
        assert abs(r.angular_velocity[3, 0, 2] / (5 * math.exp(-k * t)) - 1) < 0.01, damping
    dist = [
        run(scene([sphere(z=3, v=(2, 0, 0), damping=d)], gravity=(0, 0, 0))).position[-1, 0, 0] for d in (-3, -1, 0, 1)
    ]
    assert _monotone(dist, False)


def test_gravity_magnitude_speeds_the_fall():
    z = [run(scene([sphere(z=4.0)], gravity=(0, 0, -g))).position[-1, 0, 2] for g in (1.0, 3.0, 6.0)]
    assert _monotone(z, False)
    x = [run(scene([sphere(z=4.0)], gravity=(gx, 0, -1))).position[-1, 0, 0] for gx in (-1.0, 0.0, 1.0)]
    assert _monotone(x)


def test_restitution_raises_the_bounce():
    peaks = []
    for e in (0.2, 0.5, 0.8):
        r = run(scene([sphere(z=1.0, restitution=e)]), duration=1.2, fps=240, substeps=1)
        peaks.append(r.linear_velocity[:, 0, 2].max())
    assert _monotone(peaks)
    assert abs(peaks[-1] / math.sqrt(2 * 9.81 * 0.8) - 0.8) < 0.1  # rebound speed ≈ e × impact speed


@pytest.mark.parametrize("e", [0.5, 0.8, 0.9])
def test_restitution_leaves_sliding_friction_coulomb(e):
    """A bouncy object still slides to d = v² / (2 μ g): μ = 1, v = 1 m/s stops after 1 / 19.62 = 0.051 m. The
    contact's friction rows took the restitution spring's damping b = 2ζ√k as their reference (b = 6.7/s at
    e = 0.9), a viscous pull -b·v below μg/b = 1.5 m/s instead of Coulomb friction: the box slid 1.56 / 3.27
    times as far at e = 0.8 / 0.9 (0.95: 6.6). Explicit contact pairs keep MuJoCo's default friction reference."""
    r = run(scene([box(v=(1.0, 0.0, 0.0), mu=1.0) | {"physics": {"friction": [1.0, 0.0], "restitution": e}}]))
    d = r.position[-1, 0, 0] - r.position[0, 0, 0]
    assert abs(d / (1 / (2 * 9.81)) - 1) < 0.05, d


def test_restitution_between_two_objects_is_the_less_bouncy_ones():
    """Two equal spheres meet head-on without gravity. MuJoCo takes the element-wise minimum of the two direct-form
    solrefs: the less bouncy sphere's e governs (the README had "the bouncier wins"), a sphere without restitution
    takes the other's, and the parting speed is above e at low e (0.38 / 0.61 / 0.84 at this start gap; over the
    step's phase 0.24-0.38 / 0.50-0.60 / 0.78-0.84, the README's ranges, as off the floor)."""

    def parting(e1, e2):
        kw1 = {} if e1 is None else {"restitution": e1}
        kw2 = {} if e2 is None else {"restitution": e2}
        s = scene([sphere(x=-0.5, z=1.0, v=(2, 0, 0), **kw1), sphere(x=0.5, z=1.0, v=(-2, 0, 0), **kw2)], (0, 0, 0))
        v = run(s, duration=0.6).linear_velocity[-1, :, 0]
        return (v[1] - v[0]) / 4.0

    assert parting(0.8, 0.2) == pytest.approx(parting(0.2, 0.2), abs=1e-6)
    assert parting(0.8, None) == pytest.approx(parting(0.8, 0.8), abs=1e-6)
    assert [round(parting(e, e), 2) for e in (0.2, 0.5, 0.8)] == pytest.approx([0.38, 0.61, 0.84], abs=0.02)


def test_restitution_holds_at_coarser_physics_steps():
    """A sphere dropped 1 m onto the floor rebounds to e² of its drop (rebound coefficient e) whether time runs at
    1x, 1.5x or 2x (environment.time_scale: coarser steps of the same clock) or the step is 1/120 s: with the
    contact spring fixed at its 1/240 s stiffness, e = 0 rebounded 0.34 at 1.5x and 1.02 at 2x (energy gained)."""

    def rebound(e, time_scale=1.0, substeps=4):
        s = scene([sphere(z=1.1, r=0.1, restitution=e)], environment={"time_scale": time_scale})
        z = run(s, duration=2.0, fps=60, substeps=substeps).position[:, 0, 2] - 0.1
        after = z[int(np.argmax(z < 0.005)) :]  # from the first impact on
        return math.sqrt(max(after.max(), 0.0) / 1.0)

    for e, tol in ((0.0, 0.02), (0.5, 0.05), (0.8, 0.05)):
        for time_scale in (1.0, 1.5, 2.0):
            assert abs(rebound(e, time_scale) - e) < tol, (e, time_scale)
        assert abs(rebound(e, substeps=2) - e) < tol, (e, "1/120 s")
    assert sim.restitution_solref(0.5, 1 / 120)[0] == -2500.0  # k scaled by (dt0 / dt)² = 1/4
    assert sim.restitution_solref(0.5, 1 / 960)[0] == -1e4  # finer steps keep k


def test_sizes_raise_the_resting_height():
    zs = [run(scene([sphere(z=1.0, r=r_)])).position[-1, 0, 2] for r_ in (0.1, 0.2, 0.4)]
    assert _monotone(zs)
    hs = [
        run(scene([{"type": "cylinder", "radius": 0.2, "height": h, "state": {"position": [0, 0, 1.5]}}])).position[
            -1, 0, 2
        ]
        for h in (0.2, 0.5, 1.0)
    ]
    assert _monotone(hs)
    np.testing.assert_allclose(hs, [0.1, 0.25, 0.5], atol=5e-3)  # `height` is the full height
    bs = [run(scene([box(v=(0, 0, 0), size=(0.3, 0.3, c))])).position[-1, 0, 2] for c in (0.1, 0.2, 0.3)]
    np.testing.assert_allclose(bs, [0.1, 0.2, 0.3], atol=5e-3)  # `size` is half-extents


def test_initial_state_fields_move_the_rollout():
    base = run(scene([box(v=(1, 0, 0))])).position[-1, 0]
    assert run(scene([box(x=0.5, v=(1, 0, 0))])).position[-1, 0, 0] > base[0]
    assert run(scene([box(v=(2, 0, 0))])).position[-1, 0, 0] > base[0]
    assert run(scene([box(v=(1, 1, 0))])).position[-1, 0, 1] > base[1]


def test_camera_fields_change_what_is_in_view():
    """fovy widens and orientation (tilt from straight down) sweeps the view: counted objects in view move
    monotonically."""
    row = [sphere(x=0.0, y=float(y), name=f"s{k}") for k, y in enumerate(range(-2, 12, 2))]

    def seen(cam):
        return int(run(scene(row, camera={"type": "camera", **cam})).in_view[0].sum())

    fov = [seen({"position": [0, -4, 3], "orientation": 60, "fovy": f}) for f in (15, 30, 60, 100)]
    assert all(np.diff(fov) >= 0) and fov[-1] > fov[0]
    tilt = [seen({"position": [0, 0, 2], "orientation": o, "fovy": 30}) for o in (0, 30, 60, 85)]
    assert tilt[0] < max(tilt)


@pytest.mark.parametrize(
    "env, measure, increasing",
    [
        ({"air_density": 1.2}, "range", False),
        ({"air_viscosity": 1.0}, "range", False),
        ({"air_density": 1.2, "wind": [5, 0, 0]}, "range", True),
        ({"floor_offset": 0.2}, "rest_z", True),
        ({"floor_tilt": [0, 10]}, "slide_x", True),  # normal tilts to +x: the floor falls toward +x
    ],
)
def test_environment_extension_fields(env, measure, increasing):
    if measure == "range":
        make = lambda e: scene([sphere(z=3, v=(4, 0, 0), r=0.3, mass=0.2)], environment=e)  # noqa: E731
        base, changed = (run(make(e)).position[-1, 0, 0] for e in ({}, env))
    elif measure == "rest_z":
        make = lambda e: scene([sphere(z=1.0)], environment=e)  # noqa: E731
        base, changed = (run(make(e)).position[-1, 0, 2] for e in ({}, env))
    else:
        make = lambda e: scene([box(v=(0, 0, 0), mu=0.1, size=(0.2, 0.2, 0.2))], environment=e)  # noqa: E731
        base, changed = (run(make(e)).position[-1, 0, 0] for e in ({}, env))
    assert (changed > base + 1e-3) if increasing else (changed < base - 1e-3)


# --------------------------------------------------------------------------------------------
# Contacts, rest, view
# --------------------------------------------------------------------------------------------
def test_contacts_ground_and_collision_times():
    """A sphere dropped from z0 touches the floor at sqrt(2 (z0 - r) / g); two spheres 1 m apart (gap 0.6 m)
    closing at 3 m/s meet at t = 0.2 s."""
    drop = run(scene([sphere(z=1.2, r=0.2)]))
    t_hit = math.sqrt(2 * 1.0 / 9.81)
    first = [c for c in drop.contacts if c.b == "floor"][0]
    assert abs(first.start - t_hit) <= 1 / 30 + 1e-9
    two = run(
        scene(
            [sphere(x=-0.5, z=1, v=(1.5, 0, 0), mu=0.0), sphere(x=0.5, z=1, v=(-1.5, 0, 0), mu=0.0)], gravity=(0, 0, 0)
        )
    )
    hits = [c for c in two.contacts if c.b == "sphere_1"]
    assert hits and abs(hits[0].start - 0.6 / 3.0) <= 1 / 30 + 1e-9
    assert two.touching[:, 0, 1].any() and not two.touching[:, 0, 2].any()  # no floor contact in zero gravity


def test_in_view_flags_objects_behind_the_camera():
    r = run(scene([sphere(x=0, y=3), sphere(x=0, y=-9)]))  # the camera is at y = -6 looking along +y
    assert r.in_view[:, 0].all() and not r.in_view[:, 1].any()


def test_summary_and_npz(tmp_path):
    s = S.load(str(ASSETS / "paper_example.yaml"))
    r = run(s)
    assert r.position.shape == (31, 2, 3) and r.orientation.shape == (31, 2, 4) and r.t.shape == (31,)
    summary = r.summary()
    assert set(summary["objects"]) == {"box_0", "cylinder_0"} and summary["valid"]
    path = tmp_path / "traj.npz"
    r.to_npz(str(path))
    z = np.load(path)
    assert list(z["names"]) == ["box_0", "cylinder_0"]
    np.testing.assert_array_equal(z["position"], r.position)
    np.testing.assert_array_equal(z["position"][0], [[-5.0, -0.3, 0.4], [-0.5, 0.8, 0.3]])  # frame 0 = initial state


def test_cli_simulate_json_and_npz(tmp_path, capsys):
    out = tmp_path / "traj.npz"
    assert cli.main(["simulate", str(ASSETS / "paper_example.yaml"), "--out", str(out), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["valid"] is True and set(data["objects"]["box_0"]) == {"final_position", "rest_time", "contacts"}
    assert np.load(out)["t"].shape == (31,)


# --------------------------------------------------------------------------------------------
# Determinism and batching
# --------------------------------------------------------------------------------------------
def _mixed_scenes():
    return [
        S.load(str(ASSETS / "paper_example.yaml")),
        scene([box(v=(2, 1, 0)), sphere(x=1.0, v=(-1, 0, 0))]),
        scene([box(v=(1, 0, 0), mu=0.9)]),
        scene([box(x=-1, v=(2, 0.5, 0), mu=0.3), sphere(x=1.0, v=(-1, 0, 0), crr=0.1)]),
    ]


def _same(a: sim.Rollout, b: sim.Rollout) -> bool:
    return all(
        np.array_equal(getattr(a, f), getattr(b, f))
        for f in ("position", "orientation", "linear_velocity", "angular_velocity", "touching", "in_view")
    ) and (a.rest_time, a.contacts, a.valid) == (b.rest_time, b.contacts, b.valid)


def test_rollouts_are_bit_identical_and_batched_equals_one_by_one():
    scenes = _mixed_scenes()
    singles = [sim.simulate(s) for s in scenes]
    assert all(_same(a, b) for a, b in zip(singles, [sim.simulate(s) for s in scenes], strict=True))
    for nthread in (1, 2):
        batched = sim.simulate_batch(scenes, nthread=nthread)
        assert all(_same(a, b) for a, b in zip(singles, batched, strict=True))


def test_template_parameters_match_a_model_compiled_from_the_numbers():
    """Writing a scene's numbers into the shared template gives the same physics as compiling an MJCF that holds
    them (MuJoCo computes the inertia itself there)."""
    s = S.load(str(ASSETS / "paper_example.yaml"))
    model, tpl = sim.compile_scene(s)
    box_, cyl = s.objects
    spec = mujoco.MjSpec()
    spec.option.timestep = DT
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.gravity = list(s.gravity)
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], friction=[0, 0, 0])
    for o, gtype, size in (
        (box_, mujoco.mjtGeom.mjGEOM_BOX, list(box_.size)),
        (cyl, mujoco.mjtGeom.mjGEOM_CYLINDER, [cyl.radius, cyl.height / 2, 0]),
    ):
        b = spec.worldbody.add_body()
        b.add_freejoint()
        rr = min(o.size) if o.type == "box" else o.radius
        b.add_geom(
            type=gtype,
            size=size,
            mass=o.physics.mass,
            priority=1,
            condim=6,
            friction=[o.physics.friction[0], 0, o.physics.friction[1] * rr],
        )
    ref = spec.compile()
    for b in (1, 2):
        np.testing.assert_allclose(model.body_inertia[b], ref.body_inertia[b], rtol=1e-9)
        np.testing.assert_allclose(model.body_mass[b], ref.body_mass[b])
    for g in (1, 2):
        np.testing.assert_allclose(model.geom_rbound[g], ref.geom_rbound[g], rtol=1e-9)
        np.testing.assert_allclose(model.geom_size[g], ref.geom_size[g])


# --------------------------------------------------------------------------------------------
# Divergence
# --------------------------------------------------------------------------------------------
def test_divergence_is_an_invalid_rollout_with_a_reason():
    """Absurd timing (one physics step per 1/2 s) with stiff bouncy contact blows up; it is reported, not raised."""
    s = scene([sphere(z=0.3, v=(0, 0, -20), r=0.05, restitution=0.95, mass=0.01)] + [sphere(x=0.09, z=0.05, r=0.05)])
    r = sim.simulate(s, sim.SimConfig(duration=10, fps=2, substeps=1))
    assert not r.valid and r.reason and any(w in r.reason for w in ("blew up", "diverged", "tunnelled"))
    assert all(t is None for t in r.rest_time)


def test_check_names_the_object_and_time():
    s = scene([sphere(name="a"), sphere(x=1.0)])
    t = np.arange(3) / 30
    pos = np.zeros((3, 2, 3))
    vel = np.zeros((3, 2, 6))
    pos[2, 1, 0] = np.nan
    ok, reason = sim.check_states(s, pos, vel, 0, t)
    assert not ok and "sphere_0" in reason and "t=0.067" in reason
    pos[2, 1, 0] = 0.0
    pos[1, 0, 2] = -1.0
    ok, reason = sim.check_states(s, pos, vel, 0, t)
    assert not ok and reason.startswith("tunnelled: a")


def test_tunnelling_through_a_tilted_floor_is_invalid():
    """A small fast sphere passes through the floor; with a tilted floor it was reported valid (z = -4.1 m)."""
    for tilt in ((0.0, 0.0), (0.5, 0.0), (20.0, 0.0)):
        s = scene(
            [sphere(z=8.0, v=(0, 0, -20), r=0.05, mass=0.01)],
            gravity=(0.0, 0.0, -30.0),
            environment={"floor_tilt": list(tilt), "time_scale": 2.0},
        )
        r = sim.simulate(s)
        assert not r.valid and r.reason.startswith("tunnelled"), (tilt, r.reason, r.position[-1, 0])
    # resting on (or sliding down) a tilted, raised floor is not tunnelling
    s = scene([sphere(z=0.45, r=0.2)], environment={"floor_tilt": [15.0, -10.0], "floor_offset": 0.2})
    assert sim.simulate(s).valid


def test_a_camera_inside_an_object_is_an_invalid_rollout():
    """The renderer saw through a box around the camera (its back faces) while the ray-caster saw only the box: a
    true scene scored IoU 0 against its own render. Such a scene is refused, by the simulator and the scorer."""
    from aynamics import observation, scorer

    cam = {"type": "camera", "position": [0.0, 0.0, 1.0], "orientation": 30, "fovy": 60}
    around = box(v=(0, 0, 0), size=(1.0, 1.0, 1.0))  # centre (0, 0, 1): the camera at its centre
    r = sim.simulate(scene([around], camera=cam))
    assert not r.valid and r.reason.startswith("camera inside box_0 at t=0.000s (camera.position = [0.0, 0.0, 1.0])")
    # a 45°-turned box whose bounding box holds the camera but whose solid does not
    turned = box(x=1.3, v=(0, 0, 0), size=(0.5, 0.5, 1.0)) | {}
    turned["state"]["orientation"] = [math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)]
    assert sim.simulate(scene([turned], camera=cam)).valid  # the camera 1.3 m away, the corner at 0.71 m
    ball = sphere(x=0.35, z=1.0, v=(-3, 0, 0), r=0.1)  # flies through the camera: inside at 0.1 s only
    r = sim.simulate(scene([ball], gravity=(0, 0, 0), camera=cam))
    assert not r.valid and r.reason.startswith("camera inside sphere_0 at t=0.100s")
    cyl = {
        "type": "cylinder",
        "radius": 0.3,
        "height": 2.4,
        "state": {"position": [0, 0, 1.2]},
        "physics": {"mass": 1.0, "friction": [0.5, 0], "damping": -8},
    }
    s = scene([cyl], camera=cam)
    assert "camera inside cylinder_0" in sim.simulate(s).reason
    observed = observation.Observation.from_scene(scene([sphere(x=2.0)], camera=cam), width=12, height=8)
    (got,) = scorer.score([s], observed)  # the scorer's ray-cast rollout says so too
    assert not got.valid and got.iou_full == 0 and "camera inside cylinder_0" in got.reason


def test_a_camera_below_the_floor_is_an_invalid_rollout():
    """Under a raised floor the renderer drew the floor's underside over the ball while the ray-caster (MuJoCo's
    ray meets a plane only from above) saw the ball through it: the true scene scored IoU 0 against its own render.
    Such a scene is refused, by the simulator and the scorer, whether the floor is raised (0.5 m over a camera at
    0.3 m) or tilted (-20° about x: 2.18 m over a camera at y = -6, z = 1.5); a camera above a tilted floor is fine."""
    from aynamics import observation, scorer

    low = {"type": "camera", "position": [0.0, -2.0, 0.3], "orientation": 89, "fovy": 60}
    raised = scene([sphere(y=1.0, z=0.75, r=0.25)], camera=low, environment={"floor_offset": 0.5})
    r = sim.simulate(raised)
    assert not r.valid and r.reason.startswith("camera below the floor: camera.position = [0.0, -2.0, 0.3] is 0.2 m")
    cam = {"type": "camera", "position": [0.0, -6.0, 1.5], "orientation": 80, "fovy": 60}
    tilted = scene([sphere(z=0.3)], camera=cam, environment={"floor_tilt": [-20.0, 0.0]})
    assert sim.simulate(tilted).reason.startswith("camera below the floor")
    assert sim.simulate(scene([sphere(z=0.3)], camera=cam, environment={"floor_tilt": [20.0, 0.0]})).valid
    observed = observation.Observation.from_scene(
        scene([sphere(y=1.0, z=0.25, r=0.25)], camera=low), width=12, height=8
    )
    (got,) = scorer.score([raised], observed)
    assert not got.valid and got.iou_full == 0 and got.reason.startswith("camera below the floor")


def test_invalid_timing_is_refused():
    with pytest.raises(ValueError, match="duration"):
        sim.SimConfig(duration=-1)
    with pytest.raises(ValueError, match=r"duration = 0.01 s at fps = 30 is 0 frames: need at least 1"):
        sim.SimConfig(duration=0.01)  # was MuJoCo's "nstep must be positive" at the rollout
    assert sim.SimConfig(duration=0.02).frames == 1
    with pytest.raises(ValueError, match=r"fps = 1000 with substeps = 1000 is 60000000 physics steps: at most 200000"):
        sim.SimConfig(duration=60, fps=1000, substeps=1000)  # each factor in range; > 6 GB of recorded states
    assert sim.SimConfig(duration=60, fps=30, substeps=100).frames == 1800
    for bad in ({"fps": 2.5}, {"substeps": 2.5}, {"substeps": "8"}, {"fps": True}):  # was a bare TypeError / 2.5 fps
        with pytest.raises(ValueError, match="must be a whole number in"):
            sim.SimConfig(**bad)


def test_simulate_refuses_what_is_not_a_scene_or_a_config():
    """A list, YAML text or a dict in place of a Scene or SimConfig is named with its argument (it was
    "'list' object has no attribute 'structure'" from inside simulate_batch, or a bare comparison TypeError)."""
    s = scene([sphere()])
    with pytest.raises(TypeError, match=r"simulate: scene is a list, not a Scene"):
        sim.simulate([s])
    with pytest.raises(TypeError, match=r"simulate: scene is a str, not a Scene"):
        sim.simulate(S.dump(s))
    with pytest.raises(TypeError, match=r"simulate_batch: scenes is a Scene: must be a list of Scenes"):
        sim.simulate_batch(s)
    with pytest.raises(TypeError, match=r"simulate_batch: scenes\[1\] is a str, not a Scene"):
        sim.simulate_batch([s, S.dump(s)])
    with pytest.raises(TypeError, match=r"config is a dict, not a SimConfig"):
        sim.simulate(s, {"duration": 1.0})
    with pytest.raises(TypeError, match=r"nthread = '2': must be a whole number"):
        sim.simulate_batch([s], nthread="2")
    for bad in ("1", np.array([1.0]), None):
        with pytest.raises(ValueError, match=r"duration = .*: must be a number of seconds in \(0, 60\]"):
            sim.SimConfig(duration=bad)
    assert sim.simulate_batch([]) == []


def test_the_physics_step_stays_near_1_240_s_at_any_frame_rate():
    """Steps per frame follow the frame rate: a 15 fps video is the 30 fps rollout's every other frame, bit for
    bit (with 8 steps per frame at 15 fps it was simulated at 1/120 s: other bounces, a true scene scored 0.56)."""
    assert [sim.SimConfig(fps=f).substeps for f in (30, 15, 25, 60, 240, 1000)] == [8, 16, 10, 4, 1, 1]
    assert sim.SimConfig(fps=15).timestep == sim.SimConfig().timestep == 1 / 240
    s = scene([sphere(z=1.0, v=(1, 0, 0), restitution=0.7), box(x=1.5, v=(-2, 0, 0))])
    a = sim.simulate(s, sim.SimConfig(fps=30))
    b = sim.simulate(s, sim.SimConfig(fps=15))
    assert a.valid and b.valid and b.position.shape[0] == 16
    np.testing.assert_array_equal(b.position, a.position[::2])
    assert not np.array_equal(sim.simulate(s, sim.SimConfig(fps=15, substeps=8)).position, a.position[::2])


def test_contact_intervals_of_interleaved_pairs():
    """Each contact interval agrees with the per-frame `touching` flags, also when intervals of different pairs
    interleave in time (a sphere rests on the floor throughout while another bounces)."""
    s = scene([sphere(x=-1.0), sphere(x=1.0, z=1.0, restitution=0.8)])
    r = run(s, duration=2.0)
    assert [(c.start, c.end) for c in r.contacts if c.a == "sphere_0" and c.b == "floor"] == [(0.0, 2.0)]
    n = len(r.names)
    for c in r.contacts:
        i, j = r.names.index(c.a), (n if c.b == "floor" else r.names.index(c.b))
        a, b = round(c.start * 30), round(c.end * 30)
        assert r.touching[a : b + 1, i, j].all()
        assert (a == 0 or not r.touching[a - 1, i, j]) and (b == len(r.t) - 1 or not r.touching[b + 1, i, j])
    bounces = [c for c in r.contacts if c.a == "sphere_1" and c.b == "floor"]
    assert len(bounces) >= 2


# --------------------------------------------------------------------------------------------
# Extension fields the measured-data audit writes: magnus, friction_slope, time_scale
# --------------------------------------------------------------------------------------------
def test_magnus_lift_turns_a_spinning_flight_and_grows_with_k():
    """Spin ω = 10 ẑ, v = 2 x̂, lift k·ω×v: the horizontal velocity turns at Ω = k·ω/m (vertical ω ⟂ v_xy), so
    y(t) = (v/Ω)(1 − cos Ωt); k = 0.01 kg, m = 1 kg: Ω = 0.1/s, y(1) = 20·(1 − cos 0.1) = 0.09992 m."""
    ys = []
    for k in (None, 0.002, 0.005, 0.01):
        r = run(scene([sphere(z=8.0, v=(2.0, 0, 0), w=(0, 0, 10.0), r=0.1, magnus=k)]))
        ys.append(r.position[-1, 0, 1])
    assert abs(ys[0]) < 1e-12 and all(a < b for a, b in zip(ys, ys[1:], strict=False)), ys
    omega = 0.01 * 10.0 / 1.0
    assert ys[-1] == pytest.approx(2.0 / omega * (1 - math.cos(omega)), rel=0.02)
    flipped = run(scene([sphere(z=8.0, v=(2.0, 0, 0), w=(0, 0, 10.0), r=0.1, magnus=-0.01)]))
    assert flipped.position[-1, 0, 1] == pytest.approx(-ys[-1], rel=1e-6)


def test_magnus_lift_keeps_the_speed_of_a_fast_turn():
    """No gravity, a ball of 0.1 kg at v = 3 x̂ spinning at 40 ẑ with k = 0.05 kg (both in range): the lift turns
    v at Ω = k|ω|/m = 20/s, a circle of radius |v|/Ω = 0.15 m at 3 m/s. Applied as k·ω×v for
    each 1/240 s step, it lengthened v by √(1 + (Ω/240)²) a step: 3 → 6.9 m/s in 1 s (`magnus_force`)."""
    ball = sphere(z=3.0, v=(3.0, 0, 0), w=(0, 0, 40.0), r=0.1, mass=0.1, magnus=0.05)
    r = run(scene([ball], gravity=(0.0, 0.0, 0.0)))
    speed = np.linalg.norm(r.linear_velocity[:, 0], axis=1)
    assert np.allclose(speed, 3.0, atol=1e-9), speed[-1]
    x, y = r.position[:, 0, 0], r.position[:, 0, 1]  # on one circle: x² + y² + Dx + Ey + F = 0 fits every frame
    (d, e, f), *_ = np.linalg.lstsq(np.stack([x, y, np.ones_like(x)], axis=1), -(x**2 + y**2), rcond=None)
    assert np.abs(x**2 + y**2 + d * x + e * y + f).max() < 1e-9 and np.allclose(r.position[:, 0, 2], 3.0)
    assert math.sqrt(d**2 / 4 + e**2 / 4 - f) == pytest.approx(0.15, rel=2e-3)  # (the step's centre: half a step off)
    assert r.valid and sim.unpushed_energy_gain(scene([ball], gravity=(0.0, 0.0, 0.0)), r).max() < 1e-9


def test_friction_slope_shortens_the_slide_as_closed_form():
    """dv/dt = −g(μ + κv): v(t) = (v0 + μ/κ)e^{−gκt} − μ/κ stops at t_s = ln(1 + κv0/μ)/(gκ) after
    x_s = (v0 + μ/κ)(1 − e^{−gκ t_s})/(gκ) − μ t_s/κ. μ = 0.3, v0 = 3 m/s: κ = 0 → 1.529 m, κ = 0.1 → 1.292 m."""
    stops = {}
    for kappa in (-0.05, None, 0.05, 0.1):
        r = run(scene([box(v=(3.0, 0, 0), mu=0.3)]), 2.0)
        if kappa is not None:
            b = box(v=(3.0, 0, 0), mu=0.3)
            b["physics"]["friction_slope"] = kappa
            r = run(scene([b]), 2.0)
        stops[kappa] = r.position[-1, 0, 0]
    xs = [stops[k] for k in (-0.05, None, 0.05, 0.1)]
    assert all(a > b for a, b in zip(xs, xs[1:], strict=False)), stops
    g, mu, v0, kappa = 9.81, 0.3, 3.0, 0.1
    ts = math.log(1 + kappa * v0 / mu) / (g * kappa)
    expected = (v0 + mu / kappa) * (1 - math.exp(-g * kappa * ts)) / (g * kappa) - mu * ts / kappa
    assert stops[0.1] == pytest.approx(expected, rel=0.03)
    assert stops[None] == pytest.approx(v0**2 / (2 * mu * g), rel=0.03)


def test_time_scale_samples_the_physics_at_s_times_the_frame_time():
    """A frame stamped t shows the physical instant s·t: a projectile's x = v·s·t, and the larger s the farther."""
    xs = []
    for s in (0.8, 1.0, 1.25):
        env = None if s == 1.0 else {"time_scale": s}
        r = run(scene([sphere(z=8.0, v=(2.0, 0, 0), r=0.1)], environment=env))
        np.testing.assert_allclose(r.position[:, 0, 0], 2.0 * s * r.t, atol=1e-9)
        xs.append(r.position[-1, 0, 0])
    assert xs[0] < xs[1] < xs[2]


def test_extension_fields_round_trip_and_old_dumps_stay_unchanged():
    plain = scene([sphere()], environment={"floor_offset": 0.01})
    assert "time_scale" not in S.dump(plain) and "magnus" not in S.dump(plain)
    ext = scene([sphere(magnus=0.0045, friction_slope=0.08)], environment={"floor_offset": 0.01, "time_scale": 1.1})
    again = S.parse(S.dump(ext))
    assert again == ext and again.objects[0].physics.magnus == 0.0045 and again.environment.time_scale == 1.1
    with pytest.raises(S.SceneError, match=r"environment.*time_scale = 3.0: must be in \[0.5, 2\]"):
        scene([sphere()], environment={"time_scale": 3.0})
    with pytest.raises(S.SceneError, match=r"physics.magnus = 0.2: must be in \[-0.05, 0.05\] kg"):
        scene([sphere(magnus=0.2)])


def test_hooked_batch_is_bit_identical_to_one_by_one():
    scenes = [
        scene([sphere(z=1.0, v=(2, 0, 1), w=(0, 3, 10), r=0.1, magnus=0.004), box(x=2.0, mu=0.3)]),
        scene([sphere(z=1.0, v=(1, 1, 1), w=(5, 0, 0), r=0.1), box(x=2.0, mu=0.3)]),
    ]
    b = scenes[1].objects[1]
    scenes[1] = scenes[1].model_copy(
        update={
            "objects": (
                scenes[1].objects[0],
                b.model_copy(update={"physics": b.physics.model_copy(update={"friction_slope": 0.1})}),
            )
        }
    )
    batch = sim.simulate_batch(scenes, nthread=2)
    for s, r in zip(scenes, batch, strict=True):
        one = sim.simulate(s)
        assert r.valid and np.array_equal(one.position, r.position) and np.array_equal(one.orientation, r.orientation)


def test_objects_starting_inside_each_other_or_the_floor_are_invalid():
    """Interpenetration at t = 0 pushes objects apart at about 8 × depth m/s (a sphere sunk 1.3 m into the floor
    flew to 20 m, 'valid' before): deeper than MAX_START_OVERLAP (5 cm) the start is invalid, naming the pair and
    the depth. Touching (resting on the floor, boxes side by side) and shallow overlaps are fine."""
    big = dict(size=(2.0, 2.0, 2.0), v=(0.0, 0.0, 0.0))
    r = sim.simulate(scene([box(x=0.0, **big), box(x=3.9, **big)]))
    assert not r.valid and r.reason.startswith("overlapping start: box_0 and box_1 by 0.1 m")
    assert sim.simulate(scene([box(x=0.0, **big), box(x=3.97, **big)])).valid  # 3 cm: ~0.24 m/s, left to settle
    sunk = scene([{"type": "sphere", "radius": 1.4, "state": {"position": [0, 0, 0.1]}}])
    r = sim.simulate(sunk)
    assert not r.valid and r.reason.startswith("overlapping start: sphere_0 and the floor by 1.3")
    side_by_side = sim.simulate(scene([box(x=0.0, v=(0, 0, 0)), box(x=0.6, v=(0, 0, 0))]))  # half-extent 0.3
    assert side_by_side.valid, side_by_side.reason
    # the scorer's ray casting path judges the same way
    from aynamics import raycast

    cast = raycast.cast_group([sunk], sunk.structure, np.array([0]), 16, 12, sim.SimConfig(), 1)
    assert cast.reasons[0].startswith("overlapping start: sphere_0 and the floor")
    # and so does start_overlap_pairs, without simulating (the edit language's check), naming every pair
    assert sim.start_overlap_pairs(scene([box(x=0.0, **big), box(x=3.9, **big)])) == {
        ("box_0", "box_1"): pytest.approx(0.1)
    }
    assert sim.start_overlap_pairs(sunk) == {("sphere_0", "the floor"): pytest.approx(1.3)}
    assert sim.start_overlap_pairs(scene([box(x=0.0, **big), box(x=3.97, **big)])) == {}
    sunk_box = box(x=7.7, **big)  # 0.2 m into box_1, and 0.3 m into the floor:
    sunk_box["state"]["position"][2] = 1.7
    three = scene([box(x=0.0, **big), box(x=3.9, **big), sunk_box])
    assert sim.start_overlap_pairs(three) == {
        ("box_0", "box_1"): pytest.approx(0.1),
        ("box_1", "box_2"): pytest.approx(0.2),
        ("box_2", "the floor"): pytest.approx(0.3),
    }
    r = sim.simulate(three)  # the rollout names the deepest
    assert not r.valid and r.reason.startswith("overlapping start: box_2 and the floor by 0.3 m")


def test_mujoco_warnings_are_log_lines_not_files(tmp_path, monkeypatch, capfd, caplog):
    """A batch whose states blow up (velocities of 1e30) warns in MuJoCo's worker threads: the warnings are counted
    as before (each simulation invalid) and logged at debug level, with nothing on stderr and no MUJOCO_LOG.TXT in
    the working directory (both were written before)."""
    import logging

    monkeypatch.chdir(tmp_path)
    s = S.load(str(ASSETS / "paper_example.yaml"))
    b, _ = sim.prepare_batch([s] * 4, s.structure, nthread=2)
    b.bind("qvel")[...] = 1e30
    with caplog.at_level(logging.DEBUG, logger="aynamics.simulate"):
        b.rollout(5, record=("qpos",))
    assert np.array(b.warning).sum(axis=(1, 2)).tolist() == [1, 1, 1, 1]
    assert sum("MuJoCo: Nan, Inf or huge value in QVEL" in r.getMessage() for r in caplog.records) == 4
    assert "WARNING" not in capfd.readouterr().err and not (tmp_path / "MUJOCO_LOG.TXT").exists()


@pytest.mark.parametrize("yaw", [0.0, 0.3, 1.1, 2.0])
def test_a_box_resting_on_the_floor_touches_it_from_the_start(yaw):
    """A box at its half-height (0.243 m) yawed by 0.3 or 1.1 rad met the floor only at the second physics step
    (float rounding of its corners), so its floor contact began at 1/30 s (helper-39: the reasoning text said so for
    ~30 % of resting boxes); at frame 0 a contact within the first half frame counts."""
    q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    s = S.parse(
        f"""
- type: box
  size: [0.3, 0.2, 0.243]
  state: {{position: [0, 1, 0.243], orientation: {q}, linear_velocity: [0, 0, 0], angular_velocity: [0, 0, 0]}}
  physics: {{mass: 1.0, friction: [0.5, 0.0], damping: -4}}
- type: camera
  fovy: 45
  orientation: 45
  position: [0, -2, 3]
"""
    )
    r = sim.simulate(s)
    assert [(c.a, c.b, c.start, c.end) for c in r.contacts] == [("box_0", "floor", 0.0, 1.0)]


def test_a_still_ball_with_restitution_is_at_rest_from_the_start():
    """A ball resting on the floor with restitution 0.59 bounces on its contact spring at ~0.03 m/s by 0.04 mm for
    the whole second (generated record seed 0 index 9 of `width=64 height=48`): no video shows that, so it is at
    rest from t=0, not "comes to rest at t=1.00s" (nor, in other such records, "keeps moving until the end")."""
    scene = S.parse(
        """
- type: sphere
  radius: 0.24
  state: {position: [0.8974, 2.7539, 0.24], orientation: [1, 0, 0, 0], linear_velocity: [0, 0, 0],
          angular_velocity: [0, 0, 0]}
  physics: {friction: [0.8447, 0.0562], mass: 0.8382, damping: -4.5898, restitution: 0.5885}
- type: camera
  fovy: 51.34
  orientation: 59.63
  position: [-0.265, -1.996, 3.885]
"""
    )
    r = sim.simulate(scene)
    assert np.abs(r.position[:, 0] - r.position[0, 0]).max() < 1e-3  # it does not move
    assert r.rest_time == (0.0,)


def test_a_ball_at_the_top_of_its_flight_in_the_last_frame_is_not_at_rest():
    """A ball thrown straight up at g·236.5/240 m/s: MuJoCo's semi-implicit step gives v0 - n·g·dt after step n,
    so steps 233-240 (the last frame) sum to no displacement, the frame's mean speed is 0, while the ball, 4.9 m up
    and touching nothing, falls at 3.5·g·dt = 0.143 m/s at t = 1 s. It never comes to rest: rest_time None (it
    read 1.0, "stops at t=1.00s"). A ball resting on the floor is still at rest from the start."""
    g = 9.81
    thrown = run(scene([sphere(y=2.0, v=(0.0, 0.0, g * 236.5 / 240))]))
    assert abs(thrown.position[-1, 0, 2] - thrown.position[-2, 0, 2]) < 1e-4
    assert thrown.linear_velocity[-1, 0, 2] == pytest.approx(-3.5 * g / 240, rel=1e-3)
    assert not thrown.touching[-1, 0].any()
    assert thrown.rest_time == (None,)
    assert run(scene([sphere(y=2.0)])).rest_time == (0.0,)


# --------------------------------------------------------------------------------------------
# Hand-worked checks of the conversions (mutation audit helper-68)
# --------------------------------------------------------------------------------------------
def test_rolling_friction_is_written_on_a_boxs_smallest_half_extent():
    """geom_friction = [μ, 0 (torsional), c_rr · r]: a box of half-extents (0.3, 0.2, 0.1) with c_rr 0.2 rolls on
    its smallest half-extent, 0.2 × 0.1 = 0.02 (not 0.2 × 0.3 = 0.06); a sphere of radius 0.25 with c_rr 0.2 on its
    radius, 0.05."""
    s = scene([box(mu=0.4, crr=0.2, size=(0.3, 0.2, 0.1)), sphere(x=2.0, r=0.25, mu=0.6, crr=0.2)])
    model, tpl = sim.compile_scene(s)
    np.testing.assert_allclose(model.geom_friction[tpl.geom_ids], [[0.4, 0.0, 0.02], [0.6, 0.0, 0.05]], rtol=1e-12)


def test_floor_tilt_turns_the_floor_about_world_x_then_y():
    """floor_tilt (a, b) in degrees is Rx(a) first, then Ry(b) (world axes): the floor's normal is
    Ry(b)·Rx(a)·ẑ = Ry(b)·(0, -sin a, cos a) = (cos a sin b, -sin a, cos a cos b). At (10, 20):
    (0.98481 · 0.34202, -0.17365, 0.98481 · 0.93969) = (0.33682, -0.17365, 0.92542); y first would give
    (sin b, -sin a cos b, cos a cos b) = (0.34202, -0.16318, 0.92542). A +x tilt alone turns the normal to -y:
    (10, 0) gives (0, -0.17365, 0.98481)."""
    for tilt, normal in (((10.0, 20.0), (0.33682, -0.17365, 0.92542)), ((10.0, 0.0), (0.0, -0.17365, 0.98481))):
        model, tpl = sim.compile_scene(scene([sphere()], environment={"floor_tilt": list(tilt)}))
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, model.geom_quat[tpl.floor_geom])
        np.testing.assert_allclose(rot.reshape(3, 3)[:, 2], normal, atol=2e-5)


def test_tunnelling_is_measured_against_the_smallest_half_extent():
    """A plank of half-extents (1, 1, 0.05) whose centre is 0.1 m below the floor has gone through it: 0.1 is more
    than its smallest half-extent, 0.05 (against its largest, 1 m, it would pass); 0.04 m below is a plank pressed
    into the floor, not through it."""
    s = scene([box(v=(0, 0, 0), size=(1.0, 1.0, 0.05))])
    t = np.arange(2) / 30
    pos, vel = np.zeros((2, 1, 3)), np.zeros((2, 1, 6))
    pos[0, 0, 2], pos[1, 0, 2] = 0.05, -0.1
    ok, reason = sim.check_states(s, pos, vel, 0, t)
    assert not ok and reason.startswith("tunnelled: box_0 fell through the floor at t=0.033s"), reason
    pos[1, 0, 2] = -0.04
    assert sim.check_states(s, pos, vel, 0, t) == (True, None)


@pytest.mark.parametrize(
    "field, value, valid",
    [
        ("speed", 200.0, True),  # MAX_SPEED 200 m/s: strictly beyond it blew up
        ("speed", 201.0, False),
        ("spin", 1000.0, True),  # MAX_SPIN 1000 rad/s
        ("spin", 1001.0, False),
        ("distance", 999.0, True),  # MAX_DISTANCE 1000 m from the origin
        ("distance", 1001.0, False),
    ],
)
def test_blow_up_limits_of_speed_spin_and_distance(field, value, valid):
    """Each of the three limits on its own, one frame at the limit (valid) or 1 beyond it (invalid, named)."""
    s = scene([sphere(z=0.2)])
    t = np.arange(2) / 30
    pos, vel = np.zeros((2, 1, 3)), np.zeros((2, 1, 6))
    pos[:, 0, 2] = 0.2
    if field == "speed":
        vel[1, 0, 0] = value
    elif field == "spin":
        vel[1, 0, 5] = value
    else:
        pos[1, 0, 0] = value
    ok, reason = sim.check_states(s, pos, vel, 0, t)
    assert ok == valid, reason
    if not valid:
        assert reason.startswith("blew up: sphere_0 at t=0.033s"), reason


def test_the_camera_inside_test_works_in_the_objects_own_frame():
    """A long box (half-extents 1, 0.1, 0.1) at (0, 0, 1) yawed +45°: its long axis runs along world (1, 1, 0)/√2.
    A camera 0.5 m along x and y from its centre is at Rᵀ·(0.5, 0.5, 0) = (0.707, 0, 0) in the box's frame:
    inside (0.707 < 1, 0 < 0.1); with R instead of Rᵀ it would be at (0, 0.707, 0), outside. A camera at
    (0.5, -0.5) from the centre is at (0, -0.707, 0): outside (R would put it at (0.707, 0, 0), inside)."""
    c, s = math.cos(math.pi / 8), math.sin(math.pi / 8)
    position = np.array([[[0.0, 0.0, 1.0]]])
    orientation = np.array([[[c, 0.0, 0.0, s]]])
    for cam_xy, inside in (((0.5, 0.5), True), ((0.5, -0.5), False)):
        cam = {"type": "camera", "position": [*cam_xy, 1.0], "orientation": 30, "fovy": 60}
        sc = scene([box(v=(0, 0, 0), size=(1.0, 0.1, 0.1))], camera=cam)
        assert sim.camera_inside(sc, position, orientation).tolist() == [[inside]], cam_xy


@pytest.mark.parametrize("time_scale, rest", [(1.0, 0.4), (0.5, 0.8)])
def test_rest_time_by_hand_in_real_time_and_slow_motion(time_scale, rest):
    """Zero gravity, damping 1 (k = 10/s), v0 = 1 m/s: the damping is exact per step, so the speed at frame n is
    exp(-k·s·n/30) (s = time_scale). The frame's mean speed (its displacement × fps / s, physical m/s) is above the
    instant speed while slowing, so the object moves while exp(-k s n / 30) > REST_LINEAR = 0.02.
    s = 1: exp(-n/3) > 0.02 for n < 3 ln 50 = 11.74: frame 11 is the last moving one, at rest from t[12] = 0.4 s.
    s = 0.5 (slow motion): exp(-n/6) > 0.02 for n < 23.47: at rest from t[24] = 0.8 s. (The mean speed as
    displacement × fps × s would be a quarter of the physical 1.088 exp(-n/6), below 0.02 from n = 16: 0.533 s.)"""
    env = None if time_scale == 1.0 else {"time_scale": time_scale}
    s = scene([sphere(z=3.0, v=(1.0, 0, 0), damping=1.0)], gravity=(0, 0, 0), environment=env)
    r = run(s)
    k = 10.0 * time_scale / 30
    np.testing.assert_allclose(r.linear_velocity[:, 0, 0], np.exp(-k * np.arange(31)), rtol=1e-6)
    assert r.rest_time == (pytest.approx(rest, abs=1e-9),)


def test_view_test_by_hand_at_the_frustums_side_and_behind_the_camera():
    """A camera at the origin looking along +z with 45° half-angles (K = I, a 2 × 2 image: tan = (2/2)/1 = 1): the
    right side plane is x = z, at distance (x - z)/√2 from a centre. Radius 0.4: (1.5, 0, 1) is 0.5/√2 = 0.354 from
    it, so the sphere reaches into the view; (1.6, 0, 1) is 0.6/√2 = 0.424 away, out of it. Behind the camera,
    (0, 0, -0.3) still reaches z = +0.1 in front (and is 0.3/√2 from each side plane): in view; (0, 0, -0.5) does
    not reach the camera plane."""
    from aynamics import camera as camlib

    cam = camlib.CameraMatrices(K=np.eye(3), R=np.eye(3), t=np.zeros(3), width=2, height=2)
    centres = np.array([[1.5, 0.0, 1.0], [1.6, 0.0, 1.0], [0.0, 0.0, -0.3], [0.0, 0.0, -0.5]])
    assert camlib.sphere_in_view(cam, centres, 0.4).tolist() == [True, False, True, False]


def test_sim_config_takes_a_zero_dimensional_array_duration():
    """duration = np.array(1.0) (a 0-d array, e.g. a reduction's result) was refused since the argument checks; it
    simulated as 1.0 before. A 1-element 1-d array or a str still is not a duration."""
    cfg = sim.SimConfig(duration=np.array(1.0))
    assert cfg == sim.SimConfig(duration=1.0) and type(cfg.duration) is float
    for bad in (np.array([1.0]), "1.0", np.array(True)):
        with pytest.raises(ValueError, match=r"duration = .*: must be a number of seconds"):
            sim.SimConfig(duration=bad)


def upright_cylinder(spin, x=0.0, mu=0.8):
    """An upright cylinder (r 0.306 m, h 0.675 m) standing on the floor at rest, spun about its axis."""
    return {
        "type": "cylinder",
        "radius": 0.306,
        "height": 0.675,
        "state": {
            "position": [x, 0.0, 0.3375],
            "orientation": [0.9014, 0.0, 0.0, 0.433],
            "angular_velocity": [0.0, 0.0, spin],
        },
        "physics": {"friction": [mu, 0.2392], "mass": 1.0, "damping": -6.0},
    }


def test_energy_gained_untouched_names_an_upright_cylinder_that_mujoco_launches():
    """Nothing can lift a cylinder standing on the floor: friction only stops its spin (2 rad/s at μ = 0.8 in
    0.04 s, α = 2μg/r = 51 rad/s²), so its energy per kg never rises above the ½ω²·r²/2 = 0.094 J/kg it starts
    with. MuJoCo's plane-cylinder contact launches it all the same (one contact a radius deep once the axis is
    vertical to rounding): its centre rises 12 cm, 1.3 J/kg, and `unpushed_energy_gain` names that rise. Real
    motion gains nothing untouched: a ball dropped from 1 m with restitution 0.8, a box sliding to rest, a ball
    rolling, a box dropped on a corner; a box struck by a ball takes its energy from the push (0)."""
    spun = scene([upright_cylinder(-2.0)])
    launched = run(spun)
    assert launched.position[:, 0, 2].max() > 0.3375 + 0.1  # the artefact, by itself
    assert sim.unpushed_energy_gain(spun, launched)[0] > sim.MAX_UNPUSHED_GAIN
    tilted = {"position": [0.0, 0.0, 0.8], "orientation": [0.9, 0.3, 0.2, 0.1]}
    tilted_box = box(v=(0, 0, 0), size=(0.3, 0.2, 0.1)) | {"state": tilted}
    real = [
        scene([sphere(z=1.2, r=0.2, restitution=0.8)]),
        scene([box(v=(3.0, 1.0, 0.0))]),
        scene([sphere(v=(2.0, 0.0, 0.0), w=(0.0, 10.0, 0.0), crr=0.05)]),
        scene([tilted_box]),
        scene(
            [sphere(x=-1.0, v=(3.0, 0.0, 0.0), w=(0.0, 15.0, 0.0), mass=5.0), box(x=0.0, v=(0, 0, 0), name="struck")]
        ),
    ]
    for s in real:
        r = run(s)
        assert sim.unpushed_energy_gain(s, r).max() < 0.1, s.names
    struck = run(real[-1])
    assert struck.touching[:, 1, 0].any() and np.linalg.norm(struck.linear_velocity[:, 1], axis=-1).max() > 0.5
