"""Scene -> MuJoCo model, and rollouts (one scene or many at once) with states, contacts, rest and view.

Scenes with the same structure (object types in order) share one compiled template model; a scene's
numbers (sizes, masses, inertias, friction, damping, gravity, camera, extension fields) are written into
that model's fields, so a batch of candidates costs one compile and a few array writes, and runs on
MuJoCo's threaded `mujoco.batch.Batch` (bit-identical to one simulation at a time).

    rollout = simulate(scene)                    # 1 s at 30 FPS, 8 physics steps per frame
    rollouts = simulate_batch(scenes, nthread=2)  # many scenes or CMA-ES/reward candidates

The fields' physical meaning in MuJoCo (friction, damping, restitution, the hooks, the clock) is documented
in `mujoco_model.py`, which builds the templates and writes the parameters; the per-step hook forces (Magnus,
speed-dependent friction) are `hooks.py`'s; the records a rollout is timed by and gives back (`SimConfig`,
`Rollout`, `Contact`, `RawRollout`) are `rollout.py`'s.
"""

from __future__ import annotations

import copy
import logging
import os
import threading
from collections import OrderedDict

import mujoco
import numpy as np
from mujoco import batch as mjbatch

from aynamics import camera as camlib
from aynamics.hooks import Hooks, magnus_force, step_hooked  # noqa: F401 - simulate.Hooks, ... (re-exported)

# the model builder's names are part of simulate's API (simulate.template, simulate.FPS, ...)
from aynamics.mujoco_model import (  # noqa: F401
    FPS,
    PARAM_FIELDS,
    PHYSICS_HZ,
    RESTITUTION_STIFFNESS,
    RESTITUTION_TIMESTEP,
    SUBSTEPS,
    Template,
    bounding_radius,
    build_spec,
    camera_inside,
    geom_size,
    half_extents,
    inertia,
    initial_qpos_qvel,
    pair_sliding,
    quat_to_mat,
    restitution_solref,
    rolling_radius,
    scene_params,
    template,
    tilt_quaternion,
    write_params,
)

# the records are part of simulate's API too (simulate.Rollout, simulate.SimConfig, ...)
from aynamics.rollout import (  # noqa: F401
    DURATION,
    MAX_STEPS,
    Contact,
    RawRollout,
    Rollout,
    SimConfig,
    whole_in_range,
)
from aynamics.scene import Scene, is_whole, require_scene

# Raise when a change makes the same scene simulate differently (generated data sets record it: a run made under
# another physics is neither resumed nor assembled with this one). 2: damping exact per step (5330873). 3: every
# contact an explicit pair, so restitution no longer turns sliding friction viscous (`mujoco_model`). 4: Magnus
# lift turns v without lengthening it (`magnus_force`; scenes without `physics.magnus` simulate as in version 3).
PHYSICS_VERSION = 4
REST_LINEAR = 0.02  # m/s: below this (and REST_ANGULAR) for every later frame, an object is at rest
REST_ANGULAR = 0.2  # rad/s
MAX_SPEED = 200.0  # m/s: beyond this a rollout has blown up
MAX_SPIN = 1000.0  # rad/s
MAX_DISTANCE = 1000.0  # m from the origin
# m: objects interpenetrating deeper at t = 0 (each other or the floor) are refused. The contact pushes them apart
# at about 8 × depth m/s (measured: 1 cm 0.08, 3 cm 0.24, 5 cm 0.8, 20 cm 3.7 m/s), a launch that is not in the
# scene; shallower starts (a box at its nominal height on a tilted floor: 3.5 cm at 10°) are left to settle.
MAX_START_OVERLAP = 0.05
# J/kg: the most an object's energy (½v² + ½ω·Iω/m − g·x) may rise above its every earlier value while no other
# object touches it. Nothing in a scene does work on such an object (floor, friction, damping and restitution take
# energy away; Magnus lift is normal to v), yet MuJoCo's plane-cylinder contact launches upright cylinders: with the
# axis vertical to rounding (~1e-16), mjc_PlaneCylinder normalises that noise into a rim direction along the axis and
# reports one contact a whole radius deep. 4 % of sampled scenes had such a jump (up to 9 m high); every other
# object of 400 sampled scenes stays at 0 (`unpushed_energy_gain`).
MAX_UNPUSHED_GAIN = 0.5

_log = logging.getLogger(__name__)


def _mujoco_warning(message: str) -> None:
    """MuJoCo's warnings (e.g. "Nan, Inf or huge value in QACC") as debug log lines: they were printed to stderr
    and appended to MUJOCO_LOG.TXT in the working directory (files beside a user's data, many per PRO run of bad
    candidates). A rollout that warned is invalid, its reason naming the count (`check_states`)."""
    _log.debug("MuJoCo: %s", message.strip())


if mujoco.get_mju_user_warning() is None:  # a handler the user installed is kept
    mujoco.set_mju_user_warning(_mujoco_warning)


def compile_scene(scene: Scene, config: SimConfig | None = None) -> tuple[mujoco.MjModel, Template]:
    """A standalone MjModel of the scene (for rendering and single simulations), and its template."""
    tpl = template(scene.structure)
    model = _copy_model(tpl.model)
    dt = (config or SimConfig()).timestep * time_scale(scene)
    write_params(model, scene_params(scene, tpl, dt))
    model.opt.timestep = dt  # magnus / friction_slope: no hook here
    mujoco.mj_setConst(model, mujoco.MjData(model))
    return model, tpl


def _copy_model(model: mujoco.MjModel) -> mujoco.MjModel:
    return copy.copy(model)


# --------------------------------------------------------------------------------------------
# Rollouts
# --------------------------------------------------------------------------------------------
def simulate(scene: Scene, config: SimConfig = SimConfig()) -> Rollout:
    """Simulate one scene."""
    require_scene(scene, "simulate: scene")  # a list went on to "'list' object has no attribute 'structure'"
    return simulate_batch([scene], config, nthread=1)[0]


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity (a cluster job's allocation, a `taskset`), not the
    node's count, which `os.cpu_count` gives (8 ranks of a 16-core job on a 128-core node would each start 16
    MuJoCo threads)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def default_threads() -> int:
    return max(1, min(usable_cores(), 8))


def simulate_batch(scenes: list[Scene], config: SimConfig = SimConfig(), nthread: int | None = None) -> list[Rollout]:
    """Simulate many scenes at once on MuJoCo's threaded Batch, one batch per structure.

    Results are in the order of `scenes` and bit-identical to `simulate` one by one.

    Raises:
        TypeError: `scenes` is not a list of `Scene`s, `config` not a `SimConfig`, `nthread` not a whole number.
    """
    if isinstance(scenes, (Scene, str, bytes)) or not hasattr(scenes, "__len__"):
        raise TypeError(f"simulate_batch: scenes is a {type(scenes).__name__}: must be a list of Scenes")
    for k, s in enumerate(scenes):
        require_scene(s, f"simulate_batch: scenes[{k}]")
    if not isinstance(config, SimConfig):
        raise TypeError(f"config is a {type(config).__name__}, not a SimConfig (e.g. SimConfig(duration=2.0))")
    if nthread is not None and not is_whole(nthread):
        raise TypeError(f"nthread = {nthread!r}: must be a whole number of threads (or None: the default)")
    out: list[Rollout | None] = [None] * len(scenes)
    groups: dict[tuple[str, ...], list[int]] = {}
    for k, s in enumerate(scenes):
        groups.setdefault(s.structure, []).append(k)
    for structure, idx in groups.items():
        for k, r in zip(idx, _simulate_group([scenes[k] for k in idx], structure, config, nthread), strict=True):
            out[k] = r
    return out  # type: ignore[return-value]


_BATCHES = threading.local()  # per-thread cache: a Batch must not be used from two threads at once
_BATCH_CACHE_SIZE = 16


def _cached_batch(tpl: Template, n: int, nthread: int) -> mjbatch.Batch:
    cache: OrderedDict = getattr(_BATCHES, "cache", None) or OrderedDict()
    _BATCHES.cache = cache
    key = (tpl.structure, n, nthread)
    b = cache.pop(key, None)
    if b is None:
        b = mjbatch.Batch(tpl.model, n, nthread=nthread)
        for name in (*PARAM_FIELDS, "opt.timestep"):
            b.expand(name)
    cache[key] = b
    while len(cache) > _BATCH_CACHE_SIZE:
        cache.popitem(last=False)
    return b


def prepare_batch(
    scenes: list[Scene], structure: tuple[str, ...], nthread: int | None = None, timestep: float | None = None
) -> tuple[mjbatch.Batch, Template]:
    """A Batch over the structure's template with each scene's parameters and initial state written in.

    Batches are cached per (structure, size, threads) and rewritten completely on each call. `timestep` is the
    physics step in seconds (default 1 / 240: `SimConfig().timestep`), times each scene's
    `environment.time_scale`.
    """
    tpl = template(structure)
    n = len(scenes)
    b = _cached_batch(tpl, n, max(1, min(nthread or default_threads(), n)))
    dt = SimConfig().timestep if timestep is None else timestep
    steps = [dt * time_scale(s) for s in scenes]
    params = [scene_params(s, tpl, step) for s, step in zip(scenes, steps, strict=True)]
    for name in PARAM_FIELDS:
        b.expand(name)[...] = np.stack([p[name] for p in params]).reshape(b.expand(name).shape)
    b.expand("opt.timestep")[...] = np.array(steps)
    b.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
    b.set_const()
    qpos, qvel = b.bind("qpos"), b.bind("qvel")
    for k, s in enumerate(scenes):
        qpos[k], qvel[k] = initial_qpos_qvel(s, tpl)
    b.forward()
    return b, tpl


def time_scale(scene: Scene) -> float:
    """The recording's clock factor s (1 without an environment item)."""
    return 1.0 if scene.environment is None else float(scene.environment.time_scale)


def start_overlaps(b: mjbatch.Batch, tpl: Template, n_sim: int) -> tuple:
    """Per simulation of a batch at its initial state: (depth, i, j) of the deepest contact deeper than
    `MAX_START_OVERLAP` (objects i, j; j = N for the floor), else None. ~0.07 ms a scene (one mj_forward)."""
    found = (max(pairs.items(), key=lambda p: p[1], default=None) for pairs in _deep_pairs(b, tpl, n_sim))
    return tuple(None if f is None else (f[1], *f[0]) for f in found)


def _deep_pairs(b: mjbatch.Batch, tpl: Template, n_sim: int) -> list[dict[tuple[int, int], float]]:
    """Per simulation at its initial state: {(i, j): depth} of every pair of objects (j = N for the floor) whose
    deepest contact is deeper than `MAX_START_OVERLAP`, in contact order."""
    out = []
    model = data = None
    for k in range(n_sim):
        model, data = b.get_model(k, model), b.get_data(k, data)
        mujoco.mj_forward(model, data)
        out.append({pair: depth for pair, (depth, _) in deep_contacts(data, tpl, MAX_START_OVERLAP).items()})
    return out


def deep_contacts(data: mujoco.MjData, tpl: Template, deeper_than: float) -> dict:
    """{(i, j): (depth, normal)} of the deepest contact of each pair of objects i < j (j = N for the floor) deeper
    than `deeper_than` m at the state `data`'s collision was last run at, in contact order; the normal (3,) points
    from i to j."""
    obj_of = {int(g): i for i, g in enumerate(tpl.geom_ids)} | {int(tpl.floor_geom): len(tpl.geom_ids)}
    out: dict[tuple[int, int], tuple[float, np.ndarray]] = {}
    con = data.contact
    for c in np.flatnonzero(con.dist[: data.ncon] < -deeper_than):
        i, j = obj_of[int(con.geom1[c])], obj_of[int(con.geom2[c])]
        normal = np.array(con.frame[c, :3])  # MuJoCo's contact normal points from geom1 to geom2
        if i > j:
            i, j, normal = j, i, -normal
        depth = float(-con.dist[c])
        if depth > out.get((i, j), (0.0,))[0]:
            out[(i, j)] = (depth, normal)
    return out


def rollout_raw(
    scenes: list[Scene],
    structure: tuple[str, ...],
    config: SimConfig = SimConfig(),
    nthread: int | None = None,
    sensors: bool = True,
) -> RawRollout:
    """Simulate same-structure scenes in one Batch; states per frame, contact sensors per physics step
    (`sensors=False` skips recording them: `sensor` is then an empty (n, S, 0) array)."""
    b, tpl = prepare_batch(scenes, structure, nthread, config.timestep)
    overlap = start_overlaps(b, tpl, len(scenes))
    qpos0 = np.array(b.bind("qpos"))
    qvel0 = np.array(b.bind("qvel"))
    sub = config.substeps
    fields = ("qpos", "qvel", "sensordata") if sensors else ("qpos", "qvel")
    hooks = Hooks.of(scenes, tpl)
    if hooks is None:
        rec = b.rollout(config.frames * sub, record=fields)
    else:
        rec = step_hooked(b, hooks, config.frames * sub, fields)
    qpos = np.concatenate([qpos0[:, None], rec["qpos"][:, sub - 1 :: sub]], axis=1)
    qvel = np.concatenate([qvel0[:, None], rec["qvel"][:, sub - 1 :: sub]], axis=1)
    warnings = np.array(b.warning).sum(axis=(1, 2))
    sensor = rec["sensordata"] if sensors else np.zeros((len(scenes), config.frames * sub, 0))
    return RawRollout(tpl, qpos, qvel, sensor, warnings, b, overlap)


def _simulate_group(
    scenes: list[Scene], structure: tuple[str, ...], config: SimConfig, nthread: int | None
) -> list[Rollout]:
    raw = rollout_raw(scenes, structure, config, nthread)
    return assemble(scenes, raw, config)


def assemble(scenes: list[Scene], raw: RawRollout, config: SimConfig = SimConfig()) -> list[Rollout]:
    """Turn a batch's raw records into `Rollout`s (vectorised over the batch)."""
    tpl = raw.template
    n_sim, n, sub, frames = len(scenes), len(tpl.structure), config.substeps, config.frames
    q = raw.qpos[:, :, tpl.qpos_adr[:, None] + np.arange(7)]  # (B, T, N, 7)
    v = raw.qvel[:, :, tpl.dof_adr[:, None] + np.arange(6)]  # (B, T, N, 6)
    position = q[..., :3]
    with np.errstate(invalid="ignore", divide="ignore"):
        orientation = q[..., 3:] / np.linalg.norm(q[..., 3:], axis=-1, keepdims=True)
    angular = np.einsum("btnij,btnj->btni", quat_to_mat(orientation), v[..., 3:])  # body -> world
    t = np.arange(frames + 1) / config.fps

    # contacts: the pair's sensor counts a contact at any physics step of the frame interval; at frame 0, in the
    # first half frame: an object placed exactly on the floor may meet it only at the second step (float rounding
    # of a yawed box's corners: it read as landing at 1/30 s), and one that lands within 1/60 s starts ~1 mm up
    found = raw.sensor[:, : frames * sub] > 0  # (B, S, P)
    start = found[:, : max(1, sub // 2)].any(axis=1, keepdims=True)
    per_frame = np.concatenate([start, found.reshape(n_sim, frames, sub, -1).any(axis=2)], axis=1)
    touching = np.zeros((n_sim, frames + 1, n, n + 1), dtype=bool)
    pi = np.array([i for i, _ in tpl.pairs], dtype=int)
    pj = np.array([n if j < 0 else j for _, j in tpl.pairs], dtype=int)
    touching[:, :, pi, pj] = per_frame
    obj = pj < n
    touching[:, :, pj[obj], pi[obj]] = per_frame[:, :, obj]
    # interval edges with time as the fastest axis, so that each pair's starts and ends come out in step
    padded = np.pad(touching.transpose(0, 2, 3, 1), ((0, 0), (0, 0), (0, 0), (1, 1))).astype(np.int8)
    edges = np.diff(padded, axis=-1)  # (B, N, N+1, T+1)
    starts, ends = np.nonzero(edges == 1), np.nonzero(edges == -1)  # (k, i, j, frame) each

    speed = np.linalg.norm(v[..., :3], axis=-1)  # (B, T, N)
    spin = np.linalg.norm(v[..., 3:], axis=-1)
    # the frame's mean speed, from the displacement since the previous frame (physical m/s): a resting object's
    # contact jitter (a `restitution` spring bounces it at ~0.03 m/s by 0.04 mm, for the whole rollout) is not
    # motion; the instant speed alone called such a still object "moving until the end"
    scale = np.array([time_scale(s) for s in scenes])[:, None, None]
    with np.errstate(invalid="ignore"):
        mean = np.linalg.norm(np.diff(position, axis=1), axis=-1) * config.fps / scale
    mean = np.concatenate([speed[:, :1], mean], axis=1)
    # an object touching nothing in the frame is in flight: it moves at its instant speed whatever the frame's mean
    # (at the top of a bounce or throw the frame's displacement is ~0 while it falls at g·dt/2: a ball at its apex
    # in the last frame "came to rest at t=1.00s" 4.9 m up)
    flying = ~touching.any(axis=-1)  # (B, T, N)
    with np.errstate(invalid="ignore"):
        moving = (
            (np.minimum(speed, mean) > REST_LINEAR)
            | (flying & (speed > REST_LINEAR))
            | (spin > REST_ANGULAR)
            | ~np.isfinite(speed)
        )
    last_moving = np.where(moving.any(axis=1), frames - np.argmax(moving[:, ::-1], axis=1), -1)  # (B, N)

    out = []
    for k, scene in enumerate(scenes):
        names = scene.names
        sel_s, sel_e = starts[0] == k, ends[0] == k
        contacts = tuple(
            Contact(names[i], "floor" if j == n else names[j], float(t[a]), float(t[b - 1]))
            for i, j, a, b in zip(starts[1][sel_s], starts[2][sel_s], starts[3][sel_s], ends[3][sel_e], strict=True)
            if i != j
        )
        cam = camlib.matrices(scene.camera)
        radii = np.array([bounding_radius(o) for o in scene.objects])
        with np.errstate(invalid="ignore"):
            in_view = camlib.sphere_in_view(cam, position[k], radii)
        valid, reason = check_states(
            scene, position[k], v[k], int(raw.warnings[k]), t, overlap_of(raw, k, names), orientation[k]
        )
        rest = tuple(
            None if not valid or last == frames else (0.0 if last < 0 else float(t[last + 1]))
            for last in last_moving[k]
        )
        out.append(
            Rollout(
                names=names,
                t=t,
                position=position[k],
                orientation=orientation[k],
                linear_velocity=v[k, ..., :3],
                angular_velocity=angular[k],
                touching=touching[k],
                in_view=in_view,
                rest_time=rest,
                valid=valid,
                reason=reason,
                contacts=contacts,
            )
        )
    return out


def overlap_of(raw: RawRollout, k: int, names: tuple[str, ...]) -> str | None:
    """The start overlap of simulation k of `raw` in words ("A and B by 0.31 m"), or None."""
    return _overlap_words(raw.overlap[k] if raw.overlap is not None else None, names)


def start_overlap_pairs(scene: Scene) -> dict[tuple[str, str], float]:
    """Every pair of a scene's objects, or an object and "the floor", that start inside each other deeper than
    `MAX_START_OVERLAP`, with the depth of its deepest contact in m (the edit language compares a scene's before
    and after its edit with it)."""
    b, tpl = prepare_batch([scene], scene.structure, nthread=1)
    names = (*scene.names, "the floor")
    return {(names[i], names[j]): depth for (i, j), depth in _deep_pairs(b, tpl, 1)[0].items()}


def _overlap_words(found: tuple | None, names: tuple[str, ...]) -> str | None:
    if found is None:
        return None
    depth, i, j = found
    return overlap_words(names[i], "the floor" if j == len(names) else names[j], depth)


def overlap_words(a: str, b: str, depth: float) -> str:
    """How an overlap is named: "box_0 and the floor by 0.31 m"."""
    return f"{a} and {b} by {depth:.3g} m"


def unpushed_energy_gain(scene: Scene, rollout: Rollout) -> np.ndarray:
    """(N,) J/kg: the largest rise of each object's mechanical energy per kilogram, ½|v|² + ½ω·(I/m)ω − g·x, above
    its every earlier value, over the frames in which it touches no other object (neither in that frame nor the one
    before: a push from another object may add energy). 0 for an object that nothing lifts or speeds up; a scene
    with wind (which does work through drag) gives 0 for every object."""
    n = len(scene.objects)
    out = np.zeros(n)
    env = scene.environment
    if env is not None and any(env.wind):
        return out
    g = np.asarray(scene.gravity, dtype=float)
    for i, obj in enumerate(scene.objects):
        spin = np.einsum("tji,tj->ti", quat_to_mat(rollout.orientation[:, i]), rollout.angular_velocity[:, i])
        energy = (
            0.5 * (rollout.linear_velocity[:, i] ** 2).sum(-1)
            + 0.5 * (inertia(obj) / obj.physics.mass * spin**2).sum(-1)
            - rollout.position[:, i] @ g
        )
        pushed = rollout.touching[:, i, :n].any(axis=1)
        free = ~(pushed[1:] | pushed[:-1])  # frames 1.. touched by no other object, nor in the frame before
        rise = energy[1:] - np.maximum.accumulate(energy)[:-1]  # above the highest of every earlier frame
        out[i] = max(0.0, rise[free].max(initial=0.0))
    return out


def check_states(
    scene: Scene,
    position: np.ndarray,
    v: np.ndarray,
    nwarning: int,
    t: np.ndarray,
    overlap: str | None = None,
    orientation: np.ndarray | None = None,
) -> tuple[bool, str | None]:
    """(valid, reason) of simulated states: objects that start inside each other or the floor (`overlap`, from
    `overlap_of`: the contact pushes them apart at any speed, a launch not in the scene), non-finite values,
    blow-up speeds, the camera below the floor plane, tunnelling, the camera inside an object (with `orientation`),
    MuJoCo warnings.

    position (T, N, 3) and v (T, N, 6) per frame and object, orientation (T, N, 4) wxyz, nwarning the MuJoCo
    warning count, t (T,) seconds.
    """
    if overlap is not None:
        return False, f"overlapping start: {overlap} at t=0 (more than {MAX_START_OVERLAP} m)"
    names = scene.names
    finite = np.isfinite(position).all(-1) & np.isfinite(v).all(-1)  # (T, N)
    if not finite.all():
        k, i = np.argwhere(~finite)[0]
        return False, f"diverged: non-finite state of {names[i]} at t={t[k]:.3f}s"
    speed = np.linalg.norm(v[..., :3], axis=-1)
    spin = np.linalg.norm(v[..., 3:], axis=-1)
    far = np.linalg.norm(position, axis=-1)
    bad = (speed > MAX_SPEED) | (spin > MAX_SPIN) | (far > MAX_DISTANCE)
    if bad.any():
        k, i = np.argwhere(bad)[0]
        return False, (
            f"blew up: {names[i]} at t={t[k]:.3f}s has speed {speed[k, i]:.3g} m/s, spin {spin[k, i]:.3g} rad/s, "
            f"distance {far[k, i]:.3g} m"
        )
    floor = scene.environment.floor_offset if scene.environment is not None else 0.0
    tilt = scene.environment.floor_tilt if scene.environment is not None else (0.0, 0.0)
    # signed height of each centre above the (possibly tilted) floor plane through (0, 0, floor_offset)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, tilt_quaternion(*tilt))
    normal = rot.reshape(3, 3)[:, 2]  # the floor's z axis in world
    height = (position - np.array([0.0, 0.0, floor])) @ normal
    under = -float((np.asarray(scene.camera.position, float) - np.array([0.0, 0.0, floor])) @ normal)
    if under >= 0:  # mj_ray ignores a plane met from below, OpenGL draws its underside: no view to compare
        return False, (
            f"camera below the floor: camera.position = {list(scene.camera.position)} is {under:.3g} m under the "
            "floor plane; a video cannot show that view (the renderer sees the floor's underside, the scorer sees "
            "the objects through it)"
        )
    depth = np.array([half_extents(o).min() for o in scene.objects])
    below = height < -depth  # the centre went through the floor
    if below.any():
        k, i = np.argwhere(below)[0]
        return False, f"tunnelled: {names[i]} fell through the floor at t={t[k]:.3f}s (z={position[k, i, 2]:.3g} m)"
    if orientation is not None:
        inside = camera_inside(scene, position, orientation)
        if inside.any():
            k, i = np.argwhere(inside)[0]
            return False, (
                f"camera inside {names[i]} at t={t[k]:.3f}s (camera.position = {list(scene.camera.position)}): "
                "a video cannot show that view (the renderer sees the object's inside, the scorer only the object)"
            )
    if nwarning > 0:
        return (
            False,
            f"diverged: MuJoCo raised {nwarning} instability warning(s) (bad acceleration or contact overflow)",
        )
    return True, None
