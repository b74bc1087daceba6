"""Candidate causes of model error, each a MuJoCo extension written through the scene language, and the
batched simulation of measured trajectories under a baseline plus any set of candidates.

    CANDIDATES["floor_offset"].apply(scene, {"floor_offset": 0.01})   # -> Scene with environment.floor_offset
    sim = simulate_tracks(scene, tracks, {"mu": 0.3, "floor_offset": 0.01}, ["floor_offset"])

Representation of each cause (scene field it writes):
    rolling_resistance       physics.friction[1] (c_rr, condim 6 rolling friction c_rr·r)
    restitution              physics.restitution (direct solref, see simulate.restitution_solref)
    air_drag_quadratic       environment.air_density (MuJoCo inertia-box quadratic drag)
    air_drag_linear          environment.air_viscosity (MuJoCo inertia-box linear drag)
    wind                     environment.wind with air_density = WIND_AIR_DENSITY (real air) unless fitted
    floor_tilt, floor_offset environment.floor_tilt / floor_offset
    gravity                  gravity item (full vector)
    magnus                   lift k·ω×v (k in kg), applied as xfrc_applied each physics step (a stepping hook)
    speed_dependent_friction μ(v) = μ + κ·|v_horizontal| (κ in s/m), written to geom_friction each step
    time_scale               data clock / physical clock s: a frame stamped t happened at s·t (wrong frame rate)
The last three have no scene field yet; the audit reports their values as parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from aynamics import simulate as sim
from aynamics.measured import Track, initial_state
from aynamics.scene import Environment, Scene

STEP_HZ = 240  # physics rate of the template model (simulate.FPS * simulate.SUBSTEPS)
WIND_AIR_DENSITY = 1.2  # kg/m³: the air the wind acts through when no density is fitted
LOST = 1.0  # m: residual used for a simulation that diverged (NaN)
REFINE_WINDOW = 0.2  # s of early motion used to correct the initial state
REFINE_GAP = 0.01  # m: lowest point this close to the floor ends the early window


@dataclass(frozen=True)
class Candidate:
    """One candidate cause: its parameters (value ranges, start, the value meaning 'absent') and scene writer."""

    name: str
    params: tuple[str, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    start: tuple[float, ...]
    null: tuple[float, ...]
    scale: tuple[float, ...]  # typical size: the fit's unit step
    field: str  # what it writes, for the report
    apply: Callable[[Scene, dict], Scene]
    tell_apart: str = ""  # the experiment that separates it from look-alikes
    alt_start: tuple[float, ...] | None = None  # a second start (non-convex fits): the better fit is kept


def _env(scene: Scene, **update) -> Scene:
    env = scene.environment or Environment()
    return scene.model_copy(update={"environment": env.model_copy(update=update)})


def _physics(scene: Scene, friction1: float | None = None, **update) -> Scene:
    objs = []
    for o in scene.objects:
        upd = dict(update)
        if friction1 is not None:
            upd["friction"] = (o.physics.friction[0], friction1)
        objs.append(o.model_copy(update={"physics": o.physics.model_copy(update=upd)}))
    return scene.model_copy(update={"objects": tuple(objs)})


def _wind(scene: Scene, v: dict) -> Scene:
    env = scene.environment or Environment()
    rho = env.air_density if env.air_density > 0 else WIND_AIR_DENSITY
    return _env(scene, air_density=rho, wind=(v["wind_x"], v["wind_y"], 0.0))


def _gravity(scene: Scene, v: dict) -> Scene:
    return scene.model_copy(update={"gravity": (v["gx"], v["gy"], v["gz"])})


def _same(scene: Scene, v: dict) -> Scene:
    return scene


CANDIDATES: dict[str, Candidate] = {
    c.name: c
    for c in [
        Candidate(
            "rolling_resistance",
            ("c_rr",),
            (0.0,),
            (0.5,),
            (0.01,),
            (0.0,),
            (0.05,),
            "physics.friction[1]",
            lambda s, v: _physics(s, friction1=v["c_rr"]),
            "roll a sphere on the floor at several speeds: rolling resistance decelerates at a constant c_rr·g·5/7",
        ),
        Candidate(
            "restitution",
            ("restitution",),
            (0.0,),
            (0.95,),
            (0.3,),
            (0.13,),
            (0.2,),
            "physics.restitution",
            lambda s, v: _physics(s, restitution=v["restitution"]),
            "drop the object from rest onto the floor and compare rebound heights",
            (0.05,),
        ),
        Candidate(
            "air_drag_quadratic",
            ("air_density",),
            (0.0,),
            (5.0,),
            (0.5,),
            (0.0,),
            (1.0,),
            "environment.air_density",
            lambda s, v: _env(s, air_density=v["air_density"]),
            "throw at two very different speeds: quadratic drag grows with v², linear drag with v",
        ),
        Candidate(
            "air_drag_linear",
            ("air_viscosity",),
            (0.0,),
            (5.0,),
            (0.02,),
            (0.0,),
            (0.1,),
            "environment.air_viscosity",
            lambda s, v: _env(s, air_viscosity=v["air_viscosity"]),
            "throw at two very different speeds: linear drag grows with v, quadratic drag with v²",
        ),
        Candidate(
            "wind",
            ("wind_x", "wind_y"),
            (-20.0, -20.0),
            (20.0, 20.0),
            (0.0, 0.0),
            (0.0, 0.0),
            (2.0, 2.0),
            "environment.wind (+ air_density 1.2)",
            _wind,
            "drop an object from rest: wind pushes it sideways in flight, a floor tilt only on the floor",
        ),
        Candidate(
            "floor_tilt",
            ("tilt_x", "tilt_y"),
            (-20.0, -20.0),
            (20.0, 20.0),
            (0.0, 0.0),
            (0.0, 0.0),
            (1.0, 1.0),
            "environment.floor_tilt",
            lambda s, v: _env(s, floor_tilt=(v["tilt_x"], v["tilt_y"])),
            "track a free flight: a tilted gravity bends it, a tilted floor does not",
        ),
        Candidate(
            "floor_offset",
            ("floor_offset",),
            (-0.5,),
            (0.5,),
            (0.0,),
            (0.0,),
            (0.01,),
            "environment.floor_offset",
            lambda s, v: _env(s, floor_offset=v["floor_offset"]),
            "measure the resting height of the object's centre",
            (-0.02,),  # the cost is rough within a few mm of 0: a second start below
        ),
        Candidate(
            "gravity",
            ("gx", "gy", "gz"),
            (-30.0, -30.0, -30.0),
            (30.0, 30.0, 30.0),
            (0.0, 0.0, -9.81),
            (0.0, 0.0, -9.81),
            (0.2, 0.2, 0.2),
            "gravity",
            _gravity,
            "time a free fall against an independent clock: a wrong frame rate scales speeds as well as g",
        ),
        Candidate(
            "magnus",
            ("magnus",),
            (-0.05,),
            (0.05,),
            (0.0,),
            (0.0,),
            (0.002,),
            "hook: force k·ω×v",
            _same,
            "throw with and without spin: only spinning flight curves",
        ),
        Candidate(
            "speed_dependent_friction",
            ("friction_slope",),
            (-0.5,),
            (1.0,),
            (0.0,),
            (0.0,),
            (0.05,),
            "hook: μ + κ·|v|",
            _same,
            "slide the object at several speeds and compare decelerations",
        ),
        Candidate(
            "time_scale",
            ("time_scale",),
            (0.5,),
            (2.0,),
            (1.0,),
            (1.0,),
            (0.02,),
            "clock of the data",
            _same,
            "time a free fall against an independent clock: gravity changes only accelerations",
        ),
    ]
}
NAMES = tuple(CANDIDATES)


def scene_with(base: Scene, values: dict, active: list[str]) -> Scene:
    """The base scene with the baseline μ (values['mu']) and every active candidate's fields written."""
    scene = base
    if "mu" in values:
        objs = tuple(
            o.model_copy(
                update={"physics": o.physics.model_copy(update={"friction": (values["mu"], o.physics.friction[1])})}
            )
            for o in scene.objects
        )
        scene = scene.model_copy(update={"objects": objs})
    for name in active:
        scene = CANDIDATES[name].apply(scene, values)
    return scene


def track_scene(scene: Scene, track: Track, time_scale: float = 1.0) -> Scene:
    """The scene with every object's initial state taken from the track's first frames."""
    objs = []
    for i, o in enumerate(scene.objects):
        s = initial_state(track, i, time_scale)
        state = o.state.model_copy(
            update={
                "position": tuple(float(x) for x in s["position"]),
                "orientation": tuple(float(x) for x in s["orientation"]),
                "linear_velocity": tuple(float(x) for x in np.clip(s["linear_velocity"], -20, 20)),
                "angular_velocity": tuple(float(x) for x in np.clip(s["angular"], -50, 50)),
            }
        )
        objs.append(o.model_copy(update={"state": state}))
    return scene.model_copy(update={"objects": tuple(objs)})


@dataclass(frozen=True)
class TrackSim:
    """Simulated states at each track's measured times: position (T, N, 3), orientation (T, N, 4)."""

    position: list[np.ndarray]
    orientation: list[np.ndarray]
    scenes: list[Scene]


def simulate_tracks(
    base: Scene, tracks: list[Track], values: dict, active: list[str], nthread: int | None = None, refine: bool = True
) -> TrackSim:
    """Simulate every track from its measured initial state under the baseline + active candidates.

    With `refine`, the initial position and velocity are corrected once by the model itself: the residual
    over the first `REFINE_WINDOW` s (before the first contact) is fitted by δp + δv·t and subtracted from the
    initial state, which is then simulated again (one Gauss-Newton step; exact for drag-free flight).
    """
    s = float(values.get("time_scale", 1.0)) if "time_scale" in active else 1.0
    scene = scene_with(base, values, active)
    scenes = [track_scene(scene, tr, s) for tr in tracks]
    if not refine:
        return _run(scenes, tracks, values, active, s, nthread)
    out = _run(scenes, tracks, values, active, s, nthread, horizon=REFINE_WINDOW)
    fixed = []
    for k, (tr, sc) in enumerate(zip(tracks, scenes, strict=True)):
        objs = []
        for i, o in enumerate(sc.objects):
            dp, dv = _early_offset(tr, i, out.position[k][:, i], o, s)
            st = o.state
            objs.append(
                o.model_copy(
                    update={
                        "state": st.model_copy(
                            update={
                                "position": tuple(float(x) for x in np.asarray(st.position) - dp),
                                "linear_velocity": tuple(float(x) for x in np.asarray(st.linear_velocity) - dv),
                            }
                        )
                    }
                )
            )
        fixed.append(sc.model_copy(update={"objects": tuple(objs)}))
    return _run(fixed, tracks, values, active, s, nthread)


def _early_offset(track: Track, i: int, sim_pos: np.ndarray, obj, s: float) -> tuple[np.ndarray, np.ndarray]:
    """δp, δv (3,) of the straight line that best fits the early residual (sim - measured) of object i."""
    p = track.position[:, i]
    r = sim_pos - p  # (T, 3)
    ok = np.isfinite(r).all(-1) & (track.t <= REFINE_WINDOW)
    zero = np.zeros(3)
    if ok.sum() < 4:
        return zero, zero
    z_low = p[:, 2] - sim_lowest(obj)
    contact = z_low < REFINE_GAP
    cut = np.flatnonzero(contact & ok)
    axes = np.arange(3)
    if len(cut) and cut[0] < 4:  # starts on the floor: correct the horizontal motion only
        axes = np.arange(2)
    elif len(cut):
        ok[cut[0] :] = False
    if ok.sum() < 4:
        return zero, zero
    tt = track.t[ok] * s
    a = np.stack([np.ones_like(tt), tt], 1)
    coef, *_ = np.linalg.lstsq(a, r[ok], rcond=None)  # (2, 3)
    dp, dv = zero.copy(), zero.copy()
    dp[axes], dv[axes] = coef[0, axes], coef[1, axes]
    return dp, dv


def sim_lowest(obj) -> float:
    """Largest distance from the centre to the lowest point (a box's half-diagonal, a sphere's radius)."""
    return float(np.linalg.norm(sim.half_extents(obj))) if obj.type != "sphere" else float(obj.radius)


def _run(
    scenes: list[Scene], tracks: list[Track], values: dict, active: list[str], s: float, nthread, horizon=None
) -> TrackSim:
    """Simulate the scenes; positions at the tracks' times (held at the last step beyond `horizon` s)."""
    duration = max(tr.duration for tr in tracks) if horizon is None else horizon
    nsteps = int(math.ceil(duration * s * STEP_HZ)) + 2
    b, tpl = sim.prepare_batch(scenes, scenes[0].structure, nthread)
    qpos0 = np.array(b.bind("qpos"))
    hooks = [n for n in ("magnus", "speed_dependent_friction") if n in active]
    if not hooks:
        qpos = b.rollout(nsteps, record=("qpos",))["qpos"]
    else:
        qpos = _stepped(b, tpl, scenes, values, hooks, nsteps)
    qpos = np.concatenate([qpos0[:, None], qpos], axis=1)  # (n, S+1, nq)
    cols = tpl.qpos_adr[:, None] + np.arange(7)
    out_p, out_q = [], []
    for k, tr in enumerate(tracks):
        q = qpos[k][:, cols]  # (S+1, N, 7)
        u = tr.t * s * STEP_HZ
        i0 = np.clip(np.floor(u).astype(int), 0, nsteps - 1)
        w = (u - i0)[:, None, None]
        pos = (1 - w) * q[i0, :, :3] + w * q[i0 + 1, :, :3]
        pos[~np.isfinite(pos)] = LOST
        out_p.append(pos)
        out_q.append(q[np.clip(np.rint(u).astype(int), 0, nsteps), :, 3:])
    return TrackSim(out_p, out_q, scenes)


def _stepped(b, tpl: sim.Template, scenes: list[Scene], values: dict, hooks: list[str], nsteps: int) -> np.ndarray:
    """Step the batch one physics step at a time, applying the Magnus force / speed-dependent friction."""
    qpos, qvel = b.bind("qpos"), b.bind("qvel")
    xfrc = b.bind("xfrc_applied")  # (n, nbody, 6) world force, torque
    fric = b.expand("geom_friction")  # (n, ngeom, 3)
    mu0 = fric[:, tpl.geom_ids, 0].copy()
    k_m = float(values.get("magnus", 0.0))
    kappa = float(values.get("friction_slope", 0.0))
    out = np.empty((len(scenes), nsteps, tpl.model.nq))
    for step in range(nsteps):
        for i, (a, d) in enumerate(zip(tpl.qpos_adr, tpl.dof_adr, strict=True)):
            v = qvel[:, d : d + 3]
            if "magnus" in hooks:
                quat = qpos[:, a + 3 : a + 7]
                w_world = np.einsum("nij,nj->ni", _mats(quat), qvel[:, d + 3 : d + 6])
                xfrc[:, tpl.body_ids[i], :3] = k_m * np.cross(w_world, v)
            if "speed_dependent_friction" in hooks:
                fric[:, tpl.geom_ids[i], 0] = np.maximum(mu0[:, i] + kappa * np.linalg.norm(v[:, :2], axis=1), 0.0)
        b.step()
        out[:, step] = qpos
    fric[:, tpl.geom_ids, 0] = mu0
    xfrc[...] = 0.0
    return out


def _mats(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    out = np.empty((len(q), 9))
    for k in range(len(q)):
        mujoco.mju_quat2Mat(out[k], q[k])
    return out.reshape(-1, 3, 3)
