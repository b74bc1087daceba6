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
    magnus                   physics.magnus k (kg): lift k·ω×v (simulate.py's stepping hook)
    speed_dependent_friction physics.friction_slope κ (s/m): μ(v) = μ + κ·|v_horizontal| (same hook)
    time_scale               environment.time_scale s: a frame stamped t happened at s·t (wrong frame rate)
Every cause is simulated through the scene it writes (`simulate.prepare_batch` / `simulate.step_hooked`), so
the extended scene YAML reproduces exactly what was fitted.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from aynamics import simulate as sim
from aynamics.measured import Track, initial_state
from aynamics.scene import Environment, Scene, is_number

STEP_HZ = 240  # physics steps per second of the data clock (simulate's default 1/240 s, × time_scale per scene)
WIND_AIR_DENSITY = 1.2  # kg/m³: the air the wind acts through when no density is fitted
LOST = 1.0  # m: residual used for a simulation that diverged (NaN)


@contextlib.contextmanager
def physics_rate(hz: int) -> Iterator[None]:
    """Simulate at `hz` physics steps per (data-clock) second inside the block (default `STEP_HZ` = 240).

    A finer step costs proportionally more; it matters where the integrator's own error is as large as the
    effect, e.g. a box sliding at 1–2.5 m/s stops about 3 % shorter at 1/240 s than at 1 ms.
    """
    global STEP_HZ
    # 240.5 ran at int(240.5) = 240 Hz, silently; "240" or None failed on a bare TypeError. 240.0 is 240.
    if isinstance(hz, np.ndarray) and hz.ndim == 0 and hz.dtype.kind in "iuf":
        hz = hz.item()  # a 0-d array, as np.int64(240) is taken
    if not is_number(hz) or not 30 <= hz <= 10_000 or hz % 1:
        raise ValueError(f"physics_rate: hz = {hz!r}: must be a whole number of steps per second in [30, 10000]")
    old, STEP_HZ = STEP_HZ, int(hz)
    try:
        yield
    finally:
        STEP_HZ = old


V_REF = 1.0  # m/s: sliding speed at which the speed-dependent-friction candidate keeps the baseline μ
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


def _slope(scene: Scene, v: dict) -> Scene:
    """μ(v) = μ + κ·v_h written so that the fitted 'mu' is the friction at V_REF: scene μ = mu − κ·V_REF.

    μ and κ are then nearly independent in the fit (with μ at v = 0 they trade off along a narrow valley).
    """
    k = v["friction_slope"]
    objs = []
    for o in scene.objects:
        mu = max(o.physics.friction[0] - k * V_REF, 0.0)
        phys = o.physics.model_copy(update={"friction": (mu, o.physics.friction[1]), "friction_slope": k})
        objs.append(o.model_copy(update={"physics": phys}))
    return scene.model_copy(update={"objects": tuple(objs)})


def _wind(scene: Scene, v: dict) -> Scene:
    env = scene.environment or Environment()
    rho = env.air_density if env.air_density > 0 else WIND_AIR_DENSITY
    return _env(scene, air_density=rho, wind=(v["wind_x"], v["wind_y"], 0.0))


def _gravity(scene: Scene, v: dict) -> Scene:
    return scene.model_copy(update={"gravity": (v["gx"], v["gy"], v["gz"])})


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
            "physics.magnus",
            lambda s, v: _physics(s, magnus=v["magnus"]),
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
            "physics.friction_slope (μ at V_REF kept)",
            _slope,
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
            "environment.time_scale",
            lambda s, v: _env(s, time_scale=v["time_scale"]),
            "time a free fall against an independent clock: gravity changes only accelerations",
        ),
    ]
}
NAMES = tuple(CANDIDATES)


def _ring(radii: tuple[float, ...], n: int = 8) -> tuple[tuple[float, float], ...]:
    """Points on circles of the given radii, n directions each: starts for a 2-D (direction, size) effect."""
    angles = np.arange(n) * 2 * math.pi / n
    return tuple((round(r * math.cos(a), 4), round(r * math.sin(a), 4)) for r in radii for a in angles)


# Coarse starting points of each candidate's own parameters, spanning its plausible sizes and directions. The
# screening simulates them all at once and the full fit starts from the best one: the position error of
# contact-rich motion is too rough a function of the parameters for a local fit started at "absent".
GRIDS: dict[str, tuple[tuple[float, ...], ...]] = {
    "rolling_resistance": ((0.01,), (0.03,), (0.06,), (0.12,)),
    "restitution": ((0.05,), (0.3,), (0.6,), (0.85,)),
    "air_drag_quadratic": ((0.5,), (1.5,), (3.0,), (5.0,)),
    "air_drag_linear": ((0.02,), (0.06,), (0.12,), (0.25,)),
    "wind": _ring((3.0, 6.0, 9.0), 12),
    "floor_tilt": _ring((1.5, 3.0, 5.0), 12),
    "floor_offset": ((-0.04,), (-0.015,), (-0.005,), (0.005,), (0.015,), (0.04,)),
    "gravity": ((0.0, 0.0, -9.3), (0.0, 0.0, -10.3))
    + tuple((x, y, gz) for x, y in _ring((0.75,), 12) for gz in (-9.3, -9.81, -10.3)),
    "magnus": ((-0.005,), (-0.002,), (0.002,), (0.005,)),
    "speed_dependent_friction": ((-0.1,), (0.05,), (0.1,), (0.2,)),
    "time_scale": ((0.9,), (0.95,), (1.05,), (1.1,)),
}


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


_INITIAL: dict[tuple[int, int, float], tuple[Track, dict]] = {}


def _initial(track: Track, i: int, time_scale: float) -> dict:
    """`initial_state`, memoised per track object (the fit asks for the same tracks hundreds of times)."""
    key = (id(track), i, time_scale)
    hit = _INITIAL.get(key)
    if hit is not None and hit[0] is track:
        return hit[1]
    if len(_INITIAL) > 20_000:
        _INITIAL.clear()
    out = initial_state(track, i, time_scale)
    _INITIAL[key] = (track, out)
    return out


def track_scene(scene: Scene, track: Track, time_scale: float = 1.0) -> Scene:
    """The scene with every object's initial state taken from the track's first frames."""
    objs = []
    for i, o in enumerate(scene.objects):
        s = _initial(track, i, time_scale)
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
    return simulate_many(base, tracks, [values], active, nthread, refine)[0]


def simulate_many(
    base: Scene,
    tracks: list[Track],
    values: list[dict],
    active: list[str],
    nthread: int | None = None,
    refine: bool = True,
) -> list[TrackSim]:
    """`simulate_tracks` for several parameter sets at once: one Batch over every (set, track) pair.

    A least-squares Jacobian's columns (one set per perturbed parameter) cost one call instead of one each.
    """
    scenes, all_tracks, s_of = [], [], []
    for v in values:
        scene = scene_with(base, v, active)
        s = sim.time_scale(scene)  # the recording's clock: measured velocities are divided by it
        scenes += [track_scene(scene, tr, s) for tr in tracks]
        all_tracks += tracks
        s_of += [s] * len(tracks)
    if refine:
        early = _run(scenes, all_tracks, nthread, horizon=REFINE_WINDOW)
        scenes = [_shifted(sc, tr, early.position[k], s) for k, (sc, tr, s) in enumerate(zip(scenes, all_tracks, s_of))]
    out = _run(scenes, all_tracks, nthread)
    n = len(tracks)
    return [
        TrackSim(
            out.position[k * n : (k + 1) * n], out.orientation[k * n : (k + 1) * n], out.scenes[k * n : (k + 1) * n]
        )
        for k in range(len(values))
    ]


def _shifted(sc: Scene, tr: Track, early: np.ndarray, s: float) -> Scene:
    """The scene with each object's initial position and velocity corrected by its early residual."""
    objs = []
    for i, o in enumerate(sc.objects):
        dp, dv = _early_offset(tr, i, early[:, i], o, s)
        st = o.state
        update = {
            "position": tuple(float(x) for x in np.asarray(st.position) - dp),
            "linear_velocity": tuple(float(x) for x in np.asarray(st.linear_velocity) - dv),
        }
        objs.append(o.model_copy(update={"state": st.model_copy(update=update)}))
    return sc.model_copy(update={"objects": tuple(objs)})


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


def _run(scenes: list[Scene], tracks: list[Track], nthread: int | None, horizon: float | None = None) -> TrackSim:
    """Simulate the scenes; positions at the tracks' (data-clock) times (held at the last step beyond `horizon`).

    Each scene steps 1/STEP_HZ·s physical seconds per step (its time_scale s), so data time t is step t·STEP_HZ.
    """
    duration = max(tr.duration for tr in tracks) if horizon is None else horizon
    nsteps = int(math.ceil(duration * STEP_HZ)) + 2
    b, tpl = sim.prepare_batch(scenes, scenes[0].structure, nthread, timestep=1.0 / STEP_HZ)
    qpos0 = np.array(b.bind("qpos"))
    hooks = sim.Hooks.of(scenes, tpl)
    if hooks is None:
        qpos = b.rollout(nsteps, record=("qpos",))["qpos"]
    else:
        qpos = sim.step_hooked(b, hooks, nsteps, ("qpos",))["qpos"]
    qpos = np.concatenate([qpos0[:, None], qpos], axis=1)  # (n, S+1, nq)
    cols = tpl.qpos_adr[:, None] + np.arange(7)
    out_p, out_q = [], []
    for k, tr in enumerate(tracks):
        q = qpos[k][:, cols]  # (S+1, N, 7)
        u = tr.t * STEP_HZ
        i0 = np.clip(np.floor(u).astype(int), 0, nsteps - 1)
        w = (u - i0)[:, None, None]
        pos = (1 - w) * q[i0, :, :3] + w * q[i0 + 1, :, :3]
        pos[~np.isfinite(pos)] = LOST
        out_p.append(pos)
        out_q.append(q[np.clip(np.rint(u).astype(int), 0, nsteps), :, 3:])
    return TrackSim(out_p, out_q, scenes)
