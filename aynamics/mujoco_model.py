"""Scene -> MuJoCo model: the shapes' geometry and inertia, one compiled template model per structure (object
types in order), and a scene's numbers written into that model's fields.

    tpl = template(scene.structure)               # compiled once per structure (cached)
    params = scene_params(scene, tpl, timestep)   # model field -> values: sizes, masses, friction, camera, ...
    write_params(model, params)                   # into a compiled model (a Batch: `simulate.prepare_batch`)

Physical meaning of the fields (see `aynamics.scene.RANGES`):
- friction[0] is the sliding coefficient, friction[1] a dimensionless rolling-resistance coefficient
  c_rr mapped to MuJoCo's rolling friction c_rr·r (condim 6; torsional friction 0). Object geoms have
  priority 1 over the floor, so an object's own friction (and contact softness) governs its floor contacts;
  two objects in contact use the larger of each coefficient (MuJoCo's rule for equal priority).
- damping d: free-joint damping of mass·c on the linear and I_i·c on the angular dofs, c = expm1(10^d·dt)/dt, so
  that MuJoCo's implicit damping step decays v and ω by exp(-10^d dt) per step: exp(-10^d t) whatever the mass.
- restitution e (optional): the direct contact form solref = (-k, -b) with k = 1e4 and b chosen so that
  a damped spring of that stiffness rebounds with coefficient e. Every contact is an explicit pair (floor-object
  and object-object, `Template.contact_pairs`) whose friction rows keep MuJoCo's default reference
  (solreffriction (0.02, 1)): with the geom's solref they took the spring's damping b as their own, a viscous
  -b·v_slip below μg/b instead of Coulomb friction (e = 0.95, b = 3.3/s: a box at μ = 1, 1 m/s slid 6.6 times
  v²/2μg, at e = 0.8 1.56 times). The pairs follow MuJoCo's rules for geom contacts: the object's friction and
  solref against the floor (priority), the larger of each friction and the element-wise smaller solref between two
  objects (the average where both are MuJoCo's standard form).
- magnus k and friction_slope κ (optional): a spin lift k·ω×v (world force on the body's centre) and a sliding
  μ + κ·|v_horizontal| recomputed before every physics step from the current state (a Python stepping hook
  over the whole batch, `simulate.step_hooked`). MuJoCo's ellipsoid fluid model has a Magnus term too, but it comes
  with added-mass forces and needs a global air density, so it cannot express a pure k·ω×v.
- environment.time_scale s (optional): the recording's clock; frame k at t = k/fps shows the physical instant
  s·t, so each simulation steps s·dt per physics step (velocities stay physical, m/s of real time).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import mujoco
import numpy as np

from aynamics import camera as camlib
from aynamics.scene import Box, Object, Scene, Sphere

FPS = 30
PHYSICS_HZ = 240  # physics steps per second of every rollout (contacts and restitution are tuned at 1/240 s)
SUBSTEPS = PHYSICS_HZ // FPS  # physics steps per frame at FPS: dt = 1 / 240 s
RESTITUTION_STIFFNESS = 1e4  # k of the direct contact form used for `physics.restitution` at RESTITUTION_TIMESTEP
RESTITUTION_TIMESTEP = 1.0 / 240  # s: the physics step at which that k was measured (REFERENCE.md)

_GEOM = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
}


# --------------------------------------------------------------------------------------------
# Geometry and inertia of the shapes
# --------------------------------------------------------------------------------------------
def geom_size(obj: Object) -> np.ndarray:
    """MuJoCo `geom_size` (3,): box half-extents, sphere (r, 0, 0), cylinder (r, half-length, 0)."""
    if isinstance(obj, Box):
        return np.array(obj.size, dtype=float)
    if isinstance(obj, Sphere):
        return np.array([obj.radius, 0.0, 0.0])
    return np.array([obj.radius, obj.height / 2, 0.0])


def half_extents(obj: Object) -> np.ndarray:
    """(3,) half-extents of the object's bounding box in its own frame."""
    if isinstance(obj, Box):
        return np.array(obj.size, dtype=float)
    if isinstance(obj, Sphere):
        return np.full(3, obj.radius)
    return np.array([obj.radius, obj.radius, obj.height / 2])


def bounding_radius(obj: Object) -> float:
    return float(np.linalg.norm(half_extents(obj))) if not isinstance(obj, Sphere) else float(obj.radius)


def rolling_radius(obj: Object) -> float:
    """Lever arm of rolling resistance: the radius, or a box's smallest half-extent."""
    return float(min(obj.size)) if isinstance(obj, Box) else float(obj.radius)


def inertia(obj: Object) -> np.ndarray:
    """(3,) principal moments of inertia (kg m²) of a uniform solid, about the object's own axes."""
    m = obj.physics.mass
    if isinstance(obj, Box):
        a, b, c = obj.size
        return m / 3 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    if isinstance(obj, Sphere):
        return np.full(3, 0.4 * m * obj.radius**2)
    r, h = obj.radius, obj.height
    side = m * (3 * r * r + h * h) / 12
    return np.array([side, side, 0.5 * m * r * r])


def restitution_solref(
    e: float, timestep: float = RESTITUTION_TIMESTEP, k: float = RESTITUTION_STIFFNESS
) -> tuple[float, float]:
    """Direct-form solref (-k, -b) of a damped spring whose rebound coefficient is e at this physics `timestep`.

    For x'' + b x' + k x = 0 released into contact, e = exp(-ζπ / sqrt(1 - ζ²)) with ζ = b / (2 sqrt k), so
    ζ = -ln e / sqrt(π² + ln² e). e = 0 is critical damping (ζ = 1). `k` is the stiffness measured to behave at
    `RESTITUTION_TIMESTEP` (1/240 s). At a coarser step it is scaled by (RESTITUTION_TIMESTEP / timestep)², so
    the spring's ω·dt and b·dt stay where they were measured: MuJoCo integrates the contact explicitly, and the
    same k and b gained energy (e = 0 rebounded higher than the drop at time_scale 2, dt = 1/120 s). At a finer
    step k is kept: stiffer contacts gain energy too (REFERENCE.md: k = 1e5). Measured rebound of a dropped
    sphere, sqrt(rebound height / drop) over drops of 0.1-2 m (it varies with the impact's phase in the step),
    e = 0 / 0.5 / 0.8: 0.00-0.14 / 0.48-0.60 / 0.77-0.84 at 1/240 s, 0.00-0.08 / 0.46-0.59 / 0.77-0.85 at 1/120 s,
    0.00-0.11 / 0.50-0.56 / 0.79-0.82 at 1/480 s.
    """
    if e <= 0:
        zeta = 1.0
    else:
        le = math.log(e)
        zeta = -le / math.sqrt(math.pi**2 + le * le)
    k = k * min(1.0, (RESTITUTION_TIMESTEP / timestep) ** 2)
    return -k, -2 * zeta * math.sqrt(k)


# --------------------------------------------------------------------------------------------
# Templates and parameters
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Template:
    """A compiled model for one structure, with the ids looked up once."""

    model: mujoco.MjModel
    structure: tuple[str, ...]
    body_ids: np.ndarray  # (N,) object bodies
    geom_ids: np.ndarray  # (N,) object geoms
    floor_geom: int
    camera_id: int
    qpos_adr: np.ndarray  # (N,) start of each free joint in qpos
    dof_adr: np.ndarray  # (N,) start in qvel
    pairs: tuple[tuple[int, int], ...]  # contact sensors: (i, j) objects, j = -1 for the floor
    contact_pairs: np.ndarray  # (len(pairs),) MuJoCo pair id of each of `pairs`: every contact is an explicit pair
    contact_objects: np.ndarray  # (len(pairs), 2) objects i, j of each of `pairs`, the floor's as (i, i): `write_pairs`


def build_spec(structure: tuple[str, ...]) -> mujoco.MjSpec:
    """The MjSpec of a scene structure (object types in order): floor, one free body per object, camera, sensors.

    `template` compiles it once per structure; `render.render_model` adds lights and materials to a fresh one.
    """
    spec = mujoco.MjSpec()
    spec.modelname = "aynamics_scene"
    spec.option.timestep = 1.0 / (FPS * SUBSTEPS)
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC  # exact Coulomb cone; c_rr·g/1.4 for c_rr ≤ μ/2 (README)
    spec.visual.headlight.active = 0  # lighting comes from the scene's lights (rendering randomises them)
    world = spec.worldbody
    # contype = conaffinity = 0: no automatic contacts; each pair below is an explicit one (module docstring)
    world.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], friction=[0, 0, 0], contype=0, conaffinity=0
    )
    for i, kind in enumerate(structure):
        body = world.add_body(name=f"obj{i}", pos=[0, 0, 1])
        body.add_freejoint(name=f"obj{i}_joint")
        body.add_geom(
            name=f"obj{i}_geom", type=_GEOM[kind], size=[0.1, 0.1, 0.1], priority=1, condim=6, contype=0, conaffinity=0
        )
    world.add_camera(name="camera", pos=[0, -2, 3.5], quat=[1, 0, 0, 0], fovy=45)
    n = len(structure)
    for i, j in _pair_list(n):
        other = "floor" if j < 0 else f"obj{j}_geom"
        spec.add_pair(
            name=_pair_name(i, j), geomname1=f"obj{i}_geom", geomname2=other, condim=6, solreffriction=FRICTION_SOLREF
        )
    for i in range(n):
        spec.add_sensor(
            name=f"contact_floor_{i}",
            type=mujoco.mjtSensor.mjSENS_CONTACT,
            objtype=mujoco.mjtObj.mjOBJ_GEOM,
            objname="floor",
            reftype=mujoco.mjtObj.mjOBJ_BODY,
            refname=f"obj{i}",
            intprm=[1, 0, 1],  # data = found; reduce = none; num = 1
        )
    for i in range(n):
        for j in range(i + 1, n):
            spec.add_sensor(
                name=f"contact_{i}_{j}",
                type=mujoco.mjtSensor.mjSENS_CONTACT,
                objtype=mujoco.mjtObj.mjOBJ_BODY,
                objname=f"obj{i}",
                reftype=mujoco.mjtObj.mjOBJ_BODY,
                refname=f"obj{j}",
                intprm=[1, 0, 1],
            )
    return spec


FRICTION_SOLREF = (0.02, 1.0)  # friction rows of every contact: MuJoCo's default reference, whatever the solref


def _pair_list(n: int) -> tuple[tuple[int, int], ...]:
    """(i, -1) floor contacts first, then (i, j) object pairs, i < j: the order of `Template.pairs`."""
    return tuple((i, -1) for i in range(n)) + tuple((i, j) for i in range(n) for j in range(i + 1, n))


def _pair_name(i: int, j: int) -> str:
    return f"pair_floor_{i}" if j < 0 else f"pair_{i}_{j}"


@functools.lru_cache(maxsize=64)
def template(structure: tuple[str, ...]) -> Template:
    """The compiled template model for a structure (cached)."""
    model = build_spec(structure).compile()
    n = len(structure)
    body_ids = np.array([model.body(f"obj{i}").id for i in range(n)])
    joints = [model.joint(f"obj{i}_joint") for i in range(n)]
    pairs = _pair_list(n)
    return Template(
        model=model,
        structure=structure,
        body_ids=body_ids,
        geom_ids=np.array([model.geom(f"obj{i}_geom").id for i in range(n)]),
        floor_geom=model.geom("floor").id,
        camera_id=model.camera("camera").id,
        qpos_adr=np.array([j.qposadr[0] for j in joints]),
        dof_adr=np.array([j.dofadr[0] for j in joints]),
        pairs=pairs,
        contact_pairs=np.array([model.pair(_pair_name(i, j)).id for i, j in pairs], dtype=int),
        contact_objects=np.array([(i, i if j < 0 else j) for i, j in pairs], dtype=int).reshape(-1, 2),
    )


# the model fields a scene writes; `Batch.expand` makes them per-simulation
PARAM_FIELDS = (
    "geom_size",
    "geom_rbound",
    "geom_aabb",
    "geom_friction",
    "geom_solref",
    "pair_friction",
    "pair_solref",
    "geom_pos",
    "geom_quat",
    "body_mass",
    "body_inertia",
    "dof_damping",
    "cam_pos",
    "cam_quat",
    "cam_fovy",
    "opt.gravity",
    "opt.density",
    "opt.viscosity",
    "opt.wind",
)


def scene_params(scene: Scene, tpl: Template, timestep: float = RESTITUTION_TIMESTEP) -> dict[str, np.ndarray]:
    """The template's parameter fields (full arrays, as in the model) filled with the scene's numbers."""
    m = tpl.model
    p = {
        name: np.array(getattr(m.opt, name[4:]) if name.startswith("opt.") else getattr(m, name))
        for name in PARAM_FIELDS
    }
    for i, obj in enumerate(scene.objects):
        g, b, d = tpl.geom_ids[i], tpl.body_ids[i], tpl.dof_adr[i]
        half = half_extents(obj)
        p["geom_size"][g] = geom_size(obj)
        p["geom_rbound"][g] = bounding_radius(obj)
        p["geom_aabb"][g] = np.concatenate([np.zeros(3), half])
        mu, c_rr = obj.physics.friction
        p["geom_friction"][g] = [mu, 0.0, c_rr * rolling_radius(obj)]
        if obj.physics.restitution is not None:
            p["geom_solref"][g] = restitution_solref(obj.physics.restitution, timestep)
        p["body_mass"][b] = obj.physics.mass
        moments = inertia(obj)
        p["body_inertia"][b] = moments
        # MuJoCo's Euler step treats damping implicitly: v <- v / (1 + c·dt) per step, a decay rate of
        # ln(1 + c·dt) / dt, not c (at damping 2, dt = 1/240 s: 83.6/s instead of 100/s). c = expm1(k·dt) / dt
        # makes every step decay by exactly exp(-k·dt), so v(t) = v0 exp(-k t) at the frames as documented.
        rate = math.expm1(10.0**obj.physics.damping * timestep) / timestep
        p["dof_damping"][d : d + 6] = rate * np.concatenate([np.full(3, obj.physics.mass), moments])
    write_pairs(p, tpl)
    c = tpl.camera_id
    p["cam_pos"][c] = scene.camera.position
    p["cam_quat"][c] = camlib.gl_quaternion(scene.camera)
    p["cam_fovy"][c] = scene.camera.fovy
    p["opt.gravity"][:] = scene.gravity
    env = scene.environment
    if env is not None:
        p["opt.density"] = np.array(env.air_density)
        p["opt.viscosity"] = np.array(env.air_viscosity)
        p["opt.wind"][:] = env.wind
        f = tpl.floor_geom
        p["geom_pos"][f] = [0.0, 0.0, env.floor_offset]
        p["geom_quat"][f] = tilt_quaternion(*env.floor_tilt)
    return p


def write_pairs(p: dict[str, np.ndarray], tpl: Template) -> None:
    """Fill `pair_friction` and `pair_solref` of every contact pair from the object geoms' friction and solref, by
    MuJoCo's rules for geom contacts: between two objects the larger of each friction coefficient, and the
    element-wise smaller solref (the mean where both are standard); against the floor the object's own (it has
    priority), which the same rules give for the floor's pairs taken as (i, i) (`Template.contact_objects`)."""
    fric, ref = p["geom_friction"], p["geom_solref"]
    a, b = tpl.geom_ids[tpl.contact_objects.T]
    standard = (ref[a, :1] > 0) & (ref[b, :1] > 0)
    p["pair_friction"][tpl.contact_pairs] = np.maximum(fric[a], fric[b])[:, [0, 0, 1, 2, 2]]
    p["pair_solref"][tpl.contact_pairs] = np.where(standard, (ref[a] + ref[b]) / 2, np.minimum(ref[a], ref[b]))


def pair_sliding(tpl: Template, mu: np.ndarray) -> np.ndarray:
    """(..., len(pairs)) sliding friction of every contact pair given each object's μ (..., N), as `write_pairs`
    mixes it."""
    i, j = tpl.contact_objects.T
    return np.maximum(mu[..., i], mu[..., j])


def tilt_quaternion(about_x: float, about_y: float) -> np.ndarray:
    qx = np.array([math.cos(math.radians(about_x) / 2), math.sin(math.radians(about_x) / 2), 0, 0])
    qy = np.array([math.cos(math.radians(about_y) / 2), 0, math.sin(math.radians(about_y) / 2), 0])
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, qy, qx)  # x first, then y (world axes)
    return out


def write_params(model: mujoco.MjModel, params: dict[str, np.ndarray]) -> None:
    """Write `scene_params` output (model field name -> values; "opt.x" for model.opt) into a compiled model."""
    for name, value in params.items():
        if name.startswith("opt."):
            setattr(model.opt, name[4:], value)
        else:
            getattr(model, name)[...] = value


def initial_qpos_qvel(scene: Scene, tpl: Template) -> tuple[np.ndarray, np.ndarray]:
    """qpos (nq,) and qvel (nv,) of the scene's initial state: unit quaternions, body-frame spin."""
    qpos = np.zeros(tpl.model.nq)
    qvel = np.zeros(tpl.model.nv)
    for i, obj in enumerate(scene.objects):
        s = obj.state
        quat = np.asarray(s.orientation, dtype=float)
        quat = quat / np.linalg.norm(quat)
        a, d = tpl.qpos_adr[i], tpl.dof_adr[i]
        qpos[a : a + 3] = s.position
        qpos[a + 3 : a + 7] = quat
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, quat)
        qvel[d : d + 3] = s.linear_velocity
        qvel[d + 3 : d + 6] = rot.reshape(3, 3).T @ np.asarray(s.angular_velocity)  # world -> body
    return qpos, qvel


def camera_inside(scene: Scene, position: np.ndarray, orientation: np.ndarray) -> np.ndarray:
    """(T, N) bool: the scene's camera centre lies inside object i's solid at frame k.

    position (T, N, 3), orientation (T, N, 4) wxyz body -> world.
    """
    rel = np.asarray(scene.camera.position, float) - position  # (T, N, 3) world
    local = np.einsum("tnji,tnj->tni", quat_to_mat(orientation), rel)  # R^T (c - p): the body frame
    out = np.zeros(position.shape[:2], dtype=bool)
    for i, obj in enumerate(scene.objects):
        g, d = geom_size(obj), local[:, i]
        if isinstance(obj, Box):
            out[:, i] = (np.abs(d) < g).all(-1)
        elif isinstance(obj, Sphere):
            out[:, i] = np.linalg.norm(d, axis=-1) < g[0]
        else:
            out[:, i] = (np.hypot(d[:, 0], d[:, 1]) < g[0]) & (np.abs(d[:, 2]) < g[1])
    return out


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(..., 4) w, x, y, z quaternions (normalised here) -> (..., 3, 3) rotation matrices."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
