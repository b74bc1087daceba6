"""Random scenes for the synthetic dataset, drawn inside the scene language's one range table.

Every sampled quantity has a `(lo, hi)` interval in `SamplerConfig`; each interval is checked against the
matching entry of `aynamics.scene.RANGES` (its key is in `RANGE_KEYS`), so the sampler can never write a
value the scene language would refuse, and narrowing a range is a one-line config change.

Scenes are physically sensible and mostly in view: the camera is drawn first, each object is placed where a
ray through a random pixel of the central image area meets the plane of its resting height (no overlaps in
the floor plane), grounded objects start at the resting height of their orientation, a share start a little
above the floor, and a share of scenes aim one object at another so that they collide.

    rng = np.random.default_rng(scene_seed(seed, index))
    scene = sample_scene(rng, SamplerConfig(max_objects=3))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from aynamics import camera as camlib
from aynamics.scene import OBJECT_TYPES, RANGES, Camera, Scene, from_items

# SamplerConfig field -> the RANGES key whose bounds it must lie in (vectors: every component)
RANGE_KEYS: dict[str, str] = {
    "box_size": "box.size",
    "sphere_radius": "sphere.radius",
    "cylinder_radius": "cylinder.radius",
    "cylinder_height": "cylinder.height",
    "mass": "physics.mass",
    "sliding_friction": "physics.friction",
    "rolling_friction": "physics.friction",
    "damping": "physics.damping",
    "restitution": "physics.restitution",
    "speed": "state.linear_velocity",
    "spin": "state.angular_velocity",
    "drop_height": "state.position",
    "camera_fovy": "camera.fovy",
    "camera_pitch": "camera.orientation",
    "camera_x": "camera.position",
    "camera_y": "camera.position",
    "camera_z": "camera.position",
    "gravity_z": "gravity.gravity",
}
OBJECT_ORDERS = ("drawn", "left_to_right")
_COMPONENT = {"sliding_friction": 0, "rolling_friction": 1, "camera_x": 0, "camera_y": 1, "camera_z": 2}


@dataclass(frozen=True)
class SamplerConfig:
    """What the sampler draws. Every `(lo, hi)` pair is a uniform interval (mass: log-uniform).

    Attributes:
        min_objects, max_objects: number of objects, uniform in [min, max].
        shape_weights: relative frequency of box, sphere, cylinder.
        collision_share: share of scenes (with >= 2 objects) where one object is aimed at a resting one.
        moving_share: chance that an object (not aimed) gets an initial velocity.
        airborne_share: chance that an object starts `drop_height` above its resting height.
        upright_share: chance that a cylinder stands on a circular face (else it lies on its side).
        restitution_share: chance that an object gets the optional `restitution` field.
        gravity_share: chance that a scene's gravity differs from -9.81 (z drawn from `gravity_z`).
        aspect: image width / height, used to keep objects inside the picture.
        view_margin: fraction of the image width/height kept free at each border when placing objects.
        max_distance: m, farthest an object is placed from the camera.
        gap: m, minimum clearance between objects in the floor plane.
        duration: s, simulated time (used to give aimed objects enough speed to arrive).
        object_order: "drawn" (default) lists the objects in the order they were drawn, which no frame reveals;
            "left_to_right" by where their centres appear in the first frame (image x, left first): an order a
            model writing the objects one by one can read off the video. Same draws either way (same seed, same
            objects and camera), only the order and the default names differ.
    """

    min_objects: int = 1
    max_objects: int = 4
    shape_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    collision_share: float = 0.5
    moving_share: float = 0.7
    airborne_share: float = 0.15
    upright_share: float = 0.5
    restitution_share: float = 0.3
    gravity_share: float = 0.3
    box_size: tuple[float, float] = (0.1, 0.5)  # m, half-extents
    sphere_radius: tuple[float, float] = (0.1, 0.4)  # m
    cylinder_radius: tuple[float, float] = (0.1, 0.35)  # m
    cylinder_height: tuple[float, float] = (0.2, 0.9)  # m, full height
    mass: tuple[float, float] = (0.2, 10.0)  # kg, log-uniform
    sliding_friction: tuple[float, float] = (0.1, 1.0)
    rolling_friction: tuple[float, float] = (0.0, 0.3)
    damping: tuple[float, float] = (-6.0, -1.0)  # log10(1/s)
    restitution: tuple[float, float] = (0.0, 0.8)
    speed: tuple[float, float] = (0.5, 5.0)  # m/s, horizontal
    spin: tuple[float, float] = (-3.0, 3.0)  # rad/s about the vertical (boxes, cylinders)
    drop_height: tuple[float, float] = (0.05, 0.6)  # m above the resting height
    camera_fovy: tuple[float, float] = (40.0, 60.0)  # deg
    camera_pitch: tuple[float, float] = (35.0, 60.0)  # deg from straight down
    camera_x: tuple[float, float] = (-0.5, 0.5)  # m
    camera_y: tuple[float, float] = (-3.0, -1.5)  # m
    camera_z: tuple[float, float] = (2.5, 4.0)  # m
    gravity_z: tuple[float, float] = (-15.0, -5.0)  # m/s²
    aspect: float = 1.5
    view_margin: float = 0.15
    max_distance: float = 9.0
    gap: float = 0.05
    duration: float = 1.0
    object_order: str = "drawn"

    def __post_init__(self):
        if not 1 <= self.min_objects <= self.max_objects <= 16:
            raise ValueError(
                f"min_objects = {self.min_objects}, max_objects = {self.max_objects}: need 1 <= min <= max <= 16"
            )
        if len(self.shape_weights) != 3 or min(self.shape_weights) < 0 or sum(self.shape_weights) <= 0:
            raise ValueError(
                f"shape_weights = {self.shape_weights}: need 3 weights (box, sphere, cylinder), >= 0, not all 0"
            )
        for name in ("collision_share", "moving_share", "airborne_share", "upright_share"):
            _check_share(name, getattr(self, name))
        for name in ("restitution_share", "gravity_share"):
            _check_share(name, getattr(self, name))
        if not 0 <= self.view_margin < 0.5:
            raise ValueError(f"view_margin = {self.view_margin}: must be in [0, 0.5)")
        if self.aspect <= 0 or self.max_distance <= 0 or self.gap < 0 or self.duration <= 0:
            raise ValueError(
                f"aspect = {self.aspect}, max_distance = {self.max_distance}, gap = {self.gap}, "
                f"duration = {self.duration}: must be > 0 (gap >= 0)"
            )
        for f in fields(self):
            if f.name in RANGE_KEYS:
                _check_interval(f.name, getattr(self, f.name))
        if self.mass[0] <= 0:
            raise ValueError(f"mass = {self.mass}: lower bound must be > 0 (log-uniform)")
        if self.object_order not in OBJECT_ORDERS:
            raise ValueError(f"object_order = {self.object_order!r}: must be one of {OBJECT_ORDERS}")


def _check_share(name: str, value: float) -> None:
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} = {value}: must be in [0, 1]")


def _check_interval(name: str, value: tuple[float, float]) -> None:
    key = RANGE_KEYS[name]
    if len(value) != 2 or not value[0] <= value[1]:
        raise ValueError(f"{name} = {value}: must be [lo, hi] with lo <= hi")
    r = RANGES[key]
    lo, hi = r.bounds(3)
    k = _COMPONENT.get(name, 0)
    lo, hi = lo[k], hi[k]
    if name == "speed":  # a horizontal speed: each component must stay inside the range
        lo = 0.0
    if name == "drop_height":
        lo, hi = 0.0, 2.0
    if not lo <= value[0] <= value[1] <= hi:
        raise ValueError(f"{name} = {list(value)}: must lie in [{lo:g}, {hi:g}] {r.unit} (RANGES[{key!r}])")


def scene_seed(seed: int, index: int, attempt: int = 0) -> np.random.SeedSequence:
    """The seed of scene `index` of a run with global `seed` (the same in every shard and on resume)."""
    if seed < 0 or index < 0 or attempt < 0:
        raise ValueError(f"seed = {seed}, index = {index}, attempt = {attempt}: must be >= 0")
    return np.random.SeedSequence([seed, index, attempt])


# --------------------------------------------------------------------------------------------
# Shapes
# --------------------------------------------------------------------------------------------
def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _random_quat(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def _shape(rng: np.random.Generator, kind: str, cfg: SamplerConfig) -> tuple[dict, np.ndarray, float, float]:
    """Size fields, orientation (wxyz), resting height of the centre, radius of the footprint (m)."""
    yaw = rng.uniform(-math.pi, math.pi)
    if kind == "box":
        size = rng.uniform(*cfg.box_size, size=3).round(3)
        return {"size": size.tolist()}, _yaw_quat(yaw), float(size[2]), float(math.hypot(size[0], size[1]))
    if kind == "sphere":
        r = round(float(rng.uniform(*cfg.sphere_radius)), 3)
        return {"radius": r}, _random_quat(rng), r, r
    r = round(float(rng.uniform(*cfg.cylinder_radius)), 3)
    h = round(float(rng.uniform(*cfg.cylinder_height)), 3)
    if rng.random() < cfg.upright_share:
        return {"radius": r, "height": h}, _yaw_quat(yaw), h / 2, r
    lying = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])  # axis along world y
    return {"radius": r, "height": h}, _quat_mul(_yaw_quat(yaw), lying), r, math.hypot(r, h / 2)


# --------------------------------------------------------------------------------------------
# Camera and placement
# --------------------------------------------------------------------------------------------
def _camera(rng: np.random.Generator, cfg: SamplerConfig) -> dict:
    return {
        "type": "camera",
        "fovy": round(float(rng.uniform(*cfg.camera_fovy)), 2),
        "orientation": round(float(rng.uniform(*cfg.camera_pitch)), 2),
        "position": [round(float(rng.uniform(*r)), 3) for r in (cfg.camera_x, cfg.camera_y, cfg.camera_z)],
    }


def floor_point(cam: camlib.CameraMatrices, u: float, v: float, height: float) -> np.ndarray | None:
    """World point (3,) where the ray through pixel (u, v) meets the plane z = height, or None if it does not."""
    d = cam.R.T @ np.linalg.solve(cam.K, np.array([u, v, 1.0]))  # ray direction in the world
    c = cam.position
    if d[2] >= -1e-9:
        return None
    s = (height - c[2]) / d[2]
    return c + s * d if s > 0 else None


def _place(
    rng: np.random.Generator, cam: camlib.CameraMatrices, height: float, radius: float, taken: list, cfg: SamplerConfig
) -> np.ndarray | None:
    lo_p, hi_p = RANGES["state.position"].bounds(3)
    m = cfg.view_margin
    for _ in range(200):
        u = rng.uniform(m, 1 - m) * cam.width
        v = rng.uniform(m, 1 - m) * cam.height
        p = floor_point(cam, u, v, height)
        if p is None or np.linalg.norm(p - cam.position) > cfg.max_distance:
            continue
        if not all(lo_p[i] + radius <= p[i] <= hi_p[i] - radius for i in range(2)):
            continue
        if all(np.hypot(*(p[:2] - q[:2])) >= radius + r + cfg.gap for q, r in taken):
            return p
    return None


# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------
def sample_scene(rng: np.random.Generator, cfg: SamplerConfig = SamplerConfig()) -> Scene:
    """Draw one scene. Raises RuntimeError when the objects cannot be placed without overlaps."""
    camera = _camera(rng, cfg)
    cam = camlib.matrices(Camera.model_validate(camera), width=round(100 * cfg.aspect), height=100)
    n = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    weights = np.asarray(cfg.shape_weights, dtype=float)
    kinds = rng.choice(OBJECT_TYPES, size=n, p=weights / weights.sum())
    gravity = -9.81 if rng.random() >= cfg.gravity_share else round(float(rng.uniform(*cfg.gravity_z)), 2)

    items, taken, speeds = [], [], []
    for kind in kinds:
        size, quat, rest_z, footprint = _shape(rng, str(kind), cfg)
        z = rest_z + (rng.uniform(*cfg.drop_height) if rng.random() < cfg.airborne_share else 0.0)
        p = _place(rng, cam, rest_z, footprint, taken, cfg)
        if p is None:
            raise RuntimeError(
                f"cannot place {kind} (footprint radius {footprint:.2f} m) without overlap in view after 200 tries; "
                "lower max_objects or the sizes, or widen the camera ranges"
            )
        p[2] = z
        taken.append((p, footprint))
        mu = float(rng.uniform(*cfg.sliding_friction))
        physics = {
            "friction": [mu, float(rng.uniform(*cfg.rolling_friction))],
            "mass": float(math.exp(rng.uniform(math.log(cfg.mass[0]), math.log(cfg.mass[1])))),
            "damping": float(rng.uniform(*cfg.damping)),
        }
        if rng.random() < cfg.restitution_share:
            physics["restitution"] = float(rng.uniform(*cfg.restitution))
        heading = rng.uniform(-math.pi, math.pi)
        speed = float(rng.uniform(*cfg.speed)) if rng.random() < cfg.moving_share else 0.0
        speeds.append(speed)
        item = {
            "type": str(kind),
            **size,
            "state": {
                "position": p.tolist(),
                "orientation": quat.tolist(),
                "linear_velocity": [speed * math.cos(heading), speed * math.sin(heading), 0.0],
                "angular_velocity": [0.0, 0.0, float(rng.uniform(*cfg.spin)) if kind != "sphere" else 0.0],
            },
            "physics": physics,
        }
        items.append(item)

    if n >= 2 and rng.random() < cfg.collision_share:
        _aim(rng, items, taken, abs(gravity), cfg)
    spin_max = RANGES["state.angular_velocity"].hi
    for item in items:  # spheres roll without slipping, ω = z × v / r (capped at the range's bound)
        if item["type"] == "sphere":
            vx, vy, _ = item["state"]["linear_velocity"]
            w = np.array([-vy, vx]) / item["radius"]
            w *= min(1.0, spin_max / max(np.abs(w).max(), 1e-12))
            item["state"]["angular_velocity"] = [float(w[0]), float(w[1]), 0.0]
    if cfg.object_order == "left_to_right":
        u = cam.project(np.array([item["state"]["position"] for item in items]))[0][:, 0]
        items = [items[i] for i in np.argsort(u, kind="stable")]
    return from_items([*items, camera, {"type": "gravity", "gravity": [0.0, 0.0, gravity]}])


def _aim(rng: np.random.Generator, items: list[dict], taken: list, g: float, cfg: SamplerConfig) -> None:
    """Aim a random object at another (which is left at rest), fast enough to arrive within the duration."""
    a, b = rng.choice(len(items), size=2, replace=False)
    (pa, ra), (pb, rb) = taken[a], taken[b]
    d = pb[:2] - pa[:2]
    dist = float(np.linalg.norm(d))
    gap = max(dist - ra - rb, 0.0)
    mu = items[a]["physics"]["friction"][0]
    t = 0.7 * cfg.duration  # arrive well before the end
    # sliding with deceleration μg: reach `gap` at all (v² ≥ 2μg·gap) and within t (gap ≤ v t − μg t²/2)
    need = max(math.sqrt(2 * mu * g * gap), gap / t + 0.5 * mu * g * t)
    speed = min(max(need * 1.15, float(rng.uniform(*cfg.speed))), cfg.speed[1])
    v = d / dist * speed
    items[a]["state"]["linear_velocity"] = [float(v[0]), float(v[1]), 0.0]
    items[b]["state"]["linear_velocity"] = [0.0, 0.0, 0.0]
    items[b]["state"]["angular_velocity"] = [0.0, 0.0, 0.0]
