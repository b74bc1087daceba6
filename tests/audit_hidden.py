"""SEALED generator of "measured" data with a hidden effect, for the audit tests and benchmark.

It shares no simulation code with aynamics: its own hand-written MJCF, a 1 ms time step (the audit uses
1/240 s), MuJoCo's default contact softness, and the effects injected its own way: MJCF options and geom attributes
for drag, wind, floor, gravity and rolling friction, an explicit contact pair for bounce; forces (Magnus) and
friction (speed-dependent) recomputed in a Python stepping loop; a wrong clock by re-stamping the frames. The
audit sees only the CSV and a scene whose nominal μ is off by up to ±20 % and that has no effect in it.

The friction cone is elliptic, the exact Coulomb law in which the effect sizes are stated. MuJoCo's default
pyramidal cone is not: it bends a sliding box's path (friction not opposite to the slip) and, with condim 6,
shares one normal-force budget between sliding and rolling friction (a sphere's rolling deceleration at
c_rr = 0.06 comes out 12 % low), so its hidden sizes would not mean what they say.

    case = make_case("wind", seed=3, out_dir)   # -> Case(csv, scene, effect, size, truth)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

EFFECTS = (
    "rolling_resistance",
    "restitution",
    "air_drag_quadratic",
    "air_drag_linear",
    "wind",
    "floor_tilt",
    "floor_offset",
    "gravity",
    "magnus",
    "speed_dependent_friction",
    "time_scale",
)
RADIUS, MASS, HALF = 0.1, 0.3, 0.1
NOMINAL_MU = 0.3


@dataclass(frozen=True)
class Case:
    csv: str
    scene: str
    effects: tuple[str, ...]
    sizes: dict  # effect -> the number the audit must recover (scene units)
    truth: dict  # every hidden value


def _draw(effect: str, rng: np.random.Generator) -> dict:
    sign = rng.choice([-1.0, 1.0])
    if effect == "rolling_resistance":
        return {"c_rr": rng.uniform(0.03, 0.08)}
    if effect == "restitution":
        return {"restitution": rng.uniform(0.5, 0.8)}
    if effect == "air_drag_quadratic":
        return {"air_density": rng.uniform(2.0, 4.0)}
    if effect == "air_drag_linear":
        return {"air_viscosity": rng.uniform(0.06, 0.15)}
    if effect == "wind":
        ang = rng.uniform(0, 2 * math.pi)
        speed = rng.uniform(4.0, 8.0)
        return {"wind": (speed * math.cos(ang), speed * math.sin(ang))}
    if effect == "floor_tilt":
        ang = rng.uniform(0, 2 * math.pi)
        mag = rng.uniform(2.0, 5.0)
        return {"tilt": (mag * math.cos(ang), mag * math.sin(ang))}
    if effect == "floor_offset":
        return {"floor_offset": sign * rng.uniform(0.02, 0.05)}
    if effect == "gravity":
        ang = rng.uniform(0, 2 * math.pi)
        lateral = rng.uniform(0.5, 1.0)
        return {"gravity": (lateral * math.cos(ang), lateral * math.sin(ang), -9.81 * rng.uniform(0.9, 1.1))}
    if effect == "magnus":
        return {"magnus": sign * rng.uniform(0.003, 0.006)}
    if effect == "speed_dependent_friction":
        return {"friction_slope": rng.uniform(0.06, 0.12)}
    if effect == "time_scale":
        return {"time_scale": 1.0 + sign * rng.uniform(0.06, 0.12)}
    raise ValueError(effect)


def _size(effect: str, h: dict) -> float:
    if effect == "wind":
        return math.hypot(*h["wind"])
    if effect == "floor_tilt":
        return math.hypot(*h["tilt"])
    if effect == "gravity":
        return math.dist(h["gravity"], (0.0, 0.0, -9.81))
    if effect == "time_scale":
        return h["time_scale"] - 1.0
    return float(next(iter(h.values())))


def _quat_about(ax: float, ay: float) -> list[float]:
    qx = np.array([math.cos(math.radians(ax) / 2), math.sin(math.radians(ax) / 2), 0, 0])
    qy = np.array([math.cos(math.radians(ay) / 2), 0, math.sin(math.radians(ay) / 2), 0])
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, qy, qx)
    return list(out)


def _xml(shape: str, mu: float, h: dict) -> str:
    g = h.get("gravity", (0.0, 0.0, -9.81))
    rho = h.get("air_density", 1.2 if "wind" in h else 0.0)
    wind = (*h.get("wind", (0.0, 0.0)), 0.0)
    floor_quat = _quat_about(*h.get("tilt", (0.0, 0.0)))
    geom = f'type="sphere" size="{RADIUS}"' if shape == "sphere" else f'type="box" size="{HALF} {HALF} {HALF}"'
    rolling = h.get("c_rr", 0.0) * (RADIUS if shape == "sphere" else HALF)
    off, contact = "", ""
    if "restitution" in h:  # underdamped spring k = 1e4 with the damping ratio giving this bounce
        le = math.log(h["restitution"])
        b = 2 * (-le / math.sqrt(math.pi**2 + le**2)) * 100.0
        # on an explicit pair, whose friction rows keep MuJoCo's default reference: a geom's solref set theirs too,
        # and friction turned viscous below mu g / b (a bounce coefficient means Coulomb friction all the same)
        off = 'contype="0" conaffinity="0"'
        contact = f"""<contact>
    <pair geom1="g" geom2="floor" condim="6" friction="{mu} {mu} 0 {rolling} {rolling}" solref="-10000 {-b}"
          solreffriction="0.02 1"/>
  </contact>"""
    return f"""
<mujoco>
  <option timestep="0.001" cone="elliptic" gravity="{g[0]} {g[1]} {g[2]}" density="{rho}"
          viscosity="{h.get("air_viscosity", 0.0)}" wind="{wind[0]} {wind[1]} {wind[2]}"/>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1" pos="0 0 {h.get("floor_offset", 0.0)}"
          quat="{" ".join(map(str, floor_quat))}" friction="0 0 0" {off}/>
    <body name="ball" pos="0 0 1">
      <freejoint/>
      <geom name="g" {geom} mass="{MASS}" friction="{mu} 0 {rolling}" condim="6" priority="1" {off}/>
    </body>
  </worldbody>
  {contact}
</mujoco>"""


def _run(shape: str, mu: float, h: dict, init: tuple, duration: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    model = mujoco.MjModel.from_xml_string(_xml(shape, mu, h))
    data = mujoco.MjData(model)
    pos, vel, spin = init
    data.qpos[:3] = pos
    data.qpos[3:] = [1, 0, 0, 0]
    data.qvel[:3] = vel
    data.qvel[3:] = spin
    n = int(round(duration / model.opt.timestep))
    out_q, out_w = np.empty((n + 1, 7)), np.empty((n + 1, 3))
    out_q[0], out_w[0] = data.qpos, data.qvel[3:]
    for k in range(n):
        if "magnus" in h:
            rot = data.xmat[1].reshape(3, 3)
            data.xfrc_applied[1, :3] = h["magnus"] * np.cross(rot @ data.qvel[3:], data.qvel[:3])
        if "friction_slope" in h:
            model.geom_friction[1, 0] = mu + h["friction_slope"] * math.hypot(*data.qvel[:2])
        mujoco.mj_step(model, data)
        out_q[k + 1], out_w[k + 1] = data.qpos, data.qvel[3:]
    return np.arange(n + 1) * model.opt.timestep, out_q, out_w


def make_case(
    effects: str | tuple[str, ...] | None,
    seed: int,
    out_dir: str | Path,
    n_tracks: int = 20,
    duration: float = 1.5,
    rate: float = 100.0,
    noise: float = 0.001,
) -> Case:
    """Write measured.csv and scene.yaml for a hidden effect (None: the null control) drawn from the seed."""
    rng = np.random.default_rng(seed)
    effects = () if effects is None else (effects,) if isinstance(effects, str) else tuple(effects)
    h: dict = {}
    sizes = {}
    for e in effects:
        d = _draw(e, rng)
        h.update(d)
        sizes[e] = _size(e, d)
    shape = "box" if "speed_dependent_friction" in effects else "sphere"
    mu = NOMINAL_MU * rng.uniform(0.8, 1.2)  # the scene says 0.3: the baseline must refit it
    s = h.get("time_scale", 1.0)
    rows = ["trajectory,t,object,x,y,z,qw,qx,qy,qz,wx,wy,wz"]
    for k in range(n_tracks):
        if shape == "sphere":
            pos = (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.3, 0.8))
            vel = (rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-1, 2.5))
            spin = tuple(rng.uniform(-15, 15, 3))
        else:  # a box set down sliding flat (3 mm above the floor), at speeds where it slides without hopping
            pos = (rng.uniform(-1, 1), rng.uniform(-1, 1), HALF + 0.003 + h.get("floor_offset", 0.0))
            ang = rng.uniform(0, 2 * math.pi)
            speed = rng.uniform(1.0, 2.5)
            vel, spin = (speed * math.cos(ang), speed * math.sin(ang), 0.0), (0.0, 0.0, 0.0)
        t_true, q, w = _run(shape, mu, h, (pos, vel, spin), duration * max(s, 1.0) + 0.05)
        stamps = np.arange(0, duration, 1 / rate) + rng.normal(0, 0.0015, int(math.ceil(duration * rate)))
        stamps[0] = 0.0
        keep = np.ones(len(stamps), bool)
        keep[6:] = rng.random(len(stamps) - 6) > 0.08  # dropped frames
        for ts in np.sort(stamps[keep]):
            i = int(round(ts * s / 0.001))  # the data clock runs s times too slow: stamp t is physical s·t
            p = q[i, :3] + rng.normal(0, noise, 3)
            qq = q[i, 3:]
            ww = w[i] * s + rng.normal(0, 0.2, 3)  # spin read off the same wrong clock
            rows.append(
                f"{k},{ts:.5f},ball,{p[0]:.5f},{p[1]:.5f},{p[2]:.5f},"
                f"{qq[0]:.5f},{qq[1]:.5f},{qq[2]:.5f},{qq[3]:.5f},{ww[0]:.4f},{ww[1]:.4f},{ww[2]:.4f}"
            )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "measured.csv").write_text("\n".join(rows) + "\n")
    size = f"size: [{HALF}, {HALF}, {HALF}]" if shape == "box" else f"radius: {RADIUS}"
    (out / "scene.yaml").write_text(
        f"- type: {shape}\n  name: ball\n  {size}\n  state:\n    position: [0, 0, 0.5]\n"
        f"  physics:\n    friction: [{NOMINAL_MU}, 0.0]\n    mass: {MASS}\n    damping: -6\n"
        "- type: camera\n  position: [0, -3, 2]\n- type: gravity\n  gravity: [0, 0, -9.81]\n"
    )
    return Case(str(out / "measured.csv"), str(out / "scene.yaml"), effects, sizes, {**h, "mu": mu})
