"""The search space of test-time refinement: a scene's chosen continuous parameters in a normalised box.

The user picks which parameters move (`params`): per-object groups `position`, `orientation`, `linear_velocity`,
`angular_velocity`, `friction`, `mass`, `damping`, `restitution` (every object, or one object as
`box_0.position`) and scene groups `camera`, `gravity`. Each parameter lives in [0, 1]; the bounds come from the
scene language's range table (`aynamics.scene.RANGES`; mass on a log scale), so one CMA-ES step size fits all.

    space = param_space(scene, ["position", "linear_velocity"])
    x = space.encode(scene)          # (D,) in [0, 1]
    scene2 = space.decode(x + 0.01)  # validated Scene of the same structure
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from aynamics.scene import RANGES, Scene, from_items, to_items

OBJECT_GROUPS = (
    "position",
    "orientation",
    "linear_velocity",
    "angular_velocity",
    "friction",
    "mass",
    "damping",
    "restitution",
)
SCENE_GROUPS = ("camera", "gravity")
DEFAULT_PARAMS = ("position", "orientation", "linear_velocity", "angular_velocity")
# What `refine` multiplies the steps by at first. Measured (`benchmarks/study_refine_steps.py`: 10 sampled scenes
# of 1-3 objects per level, positions and velocities perturbed horizontally by normal errors, default params,
# budget 400): final full IoU at step scales 1 / 0.3 / 0.1 was 0.82 / 0.90 / 0.91 from close starts (0.1 m,
# 0.4 m/s; start IoU 0.54), 0.90 / 0.93 / 0.92 from medium ones (0.3 m, 1 m/s; 0.21) and 0.77 / 0.79 from far
# ones (2 m, 3 m/s; 0.07, where the track stage moves first).
DEFAULT_SIGMA_SCALE = 0.3

# Vertical steps of object states: objects mostly rest on the floor, where a height error shows at once.
_VERTICAL_STEP = {"position": 0.05, "linear_velocity": 0.2}

# group -> (item keys, RANGES key, initial step in the field's own units, log10 scale)
_FIELDS: dict[str, tuple[tuple[str, ...], str, float, bool]] = {
    "position": (("state", "position"), "state.position", 0.3, False),
    "orientation": (("state", "orientation"), "state.orientation", 0.15, False),
    "linear_velocity": (("state", "linear_velocity"), "state.linear_velocity", 0.5, False),
    "angular_velocity": (("state", "angular_velocity"), "state.angular_velocity", 1.0, False),
    "friction": (("physics", "friction"), "physics.friction", 0.15, False),
    "mass": (("physics", "mass"), "physics.mass", 0.3, True),
    "damping": (("physics", "damping"), "physics.damping", 0.5, False),
    "restitution": (("physics", "restitution"), "physics.restitution", 0.15, False),
    "camera.position": (("position",), "camera.position", 0.2, False),
    "camera.orientation": (("orientation",), "camera.orientation", 3.0, False),
    "camera.fovy": (("fovy",), "camera.fovy", 3.0, False),
    "gravity": (("gravity",), "gravity.gravity", 1.0, False),
}


# --------------------------------------------------------------------------------------------
# Parameter vectorisation
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Param:
    """One scalar the search moves: item index, keys inside the item, vector element, bounds, scale."""

    name: str  # e.g. "box_0.state.position[0]"
    item: int
    keys: tuple[str, ...]
    element: int | None
    lo: float
    hi: float
    step: float  # initial CMA-ES step, in normalised units
    log: bool


@dataclass(frozen=True)
class ParamSpace:
    """The chosen parameters of one scene structure, each mapped to [0, 1] (mass through log10)."""

    params: tuple[Param, ...]
    base: Scene  # values not searched come from here

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.params]

    @property
    def steps(self) -> np.ndarray:
        return np.array([p.step for p in self.params])

    def encode(self, scene: Scene) -> np.ndarray:
        """(D,) normalised coordinates of a scene of the same structure (clipped into [0, 1])."""
        items = to_items(scene)
        out = np.empty(len(self.params))
        for k, p in enumerate(self.params):
            v = _get(items[p.item], p.keys)
            v = float(v[p.element] if p.element is not None else v)
            v = math.log10(v) if p.log else v
            out[k] = (v - p.lo) / (p.hi - p.lo)
        return np.clip(out, 0.0, 1.0)

    def decode(self, x: np.ndarray) -> Scene:
        """The base scene with the parameters set from x (quaternions renormalised), validated.

        Raises:
            SceneError: the values make an invalid scene (e.g. a quaternion of zero length).
        """
        items = to_items(self.base)
        for p, u in zip(self.params, np.clip(x, 0.0, 1.0), strict=True):
            v = p.lo + float(u) * (p.hi - p.lo)
            v = 10.0**v if p.log else v
            if p.element is None:
                _set(items[p.item], p.keys, v)
            else:
                _get(items[p.item], p.keys)[p.element] = v
        for item in items:
            if "state" in item:
                q = np.asarray(item["state"]["orientation"], dtype=float)
                n = float(np.linalg.norm(q))
                item["state"]["orientation"] = (q / n).tolist() if n > 1e-6 else q.tolist()
        return from_items(items)


def _get(item: dict, keys: tuple[str, ...]):
    for k in keys:
        item = item[k]
    return item


def _set(item: dict, keys: tuple[str, ...], value) -> None:
    for k in keys[:-1]:
        item = item[k]
    item[keys[-1]] = value


def param_space(scene: Scene, params: Sequence[str] = DEFAULT_PARAMS, frozen: Collection[str] = ()) -> ParamSpace:
    """The search space of the chosen parameter groups of a scene.

    Args:
        scene: the starting scene (its structure is kept; unsearched values are kept from it).
        params: group names (`position`, `mass`, `camera`, `gravity`, ...) or `NAME.group` for one object.
        frozen: parameter names to leave out (e.g. `box_0.state.position[2]`, see `grounded_dims`).

    Raises:
        ValueError: an unknown group or object name (the message lists the allowed ones).
    """
    if not params:
        raise ValueError(f"params is empty: choose from {list(OBJECT_GROUPS + SCENE_GROUPS)}")
    items = to_items(scene)
    chosen: list[Param] = []
    seen: set[str] = set()
    for spec in params:
        name, _, group = spec.rpartition(".")
        if group in SCENE_GROUPS and not name:
            targets = [next(i for i, it in enumerate(items) if it["type"] == group)]
            keys = ["camera.position", "camera.orientation", "camera.fovy"] if group == "camera" else ["gravity"]
        elif group in OBJECT_GROUPS:
            if name and name not in scene.names:
                raise ValueError(f"params: {spec!r} names object {name!r}; the scene has {list(scene.names)}")
            targets = [scene.names.index(name)] if name else list(range(len(scene.objects)))
            keys = [group]
        else:
            allowed = ", ".join(OBJECT_GROUPS + SCENE_GROUPS)
            raise ValueError(f"params: unknown group {spec!r}; allowed: {allowed} (or NAME.group for one object)")
        for i in targets:
            for key in keys:
                path, rkey, step, log = _FIELDS[key]
                value = _get(items[i], path) if path[-1] in _get(items[i], path[:-1]) else None
                if value is None:  # e.g. restitution absent: nothing to refine on this object
                    continue
                lo, hi = RANGES[rkey].bounds(len(value) if isinstance(value, list) else 1)
                head = items[i].get("name", items[i]["type"])
                for e in range(len(value)) if isinstance(value, list) else [None]:
                    a, b = lo[e or 0], hi[e or 0]
                    if key == "mass":
                        a, b = math.log10(max(a, 1e-3)), math.log10(b)
                    pname = f"{head}.{'.'.join(path)}" + (f"[{e}]" if e is not None else "")
                    if pname not in seen and pname not in frozen:
                        seen.add(pname)
                        s = _VERTICAL_STEP.get(key, step) if e == 2 else step
                        chosen.append(Param(pname, i, path, e, a, b, s / (b - a), log))
    if not chosen:
        raise ValueError(f"params {list(params)}: none of these fields is present in the scene")
    return ParamSpace(tuple(chosen), scene)


def grounded_dims(scene: Scene, config=None) -> set[str]:
    """Names of the vertical position and velocity of the objects that start on the floor (touching it within the
    first frame, vertical speed < 0.05 m/s): a contact fixes them, and searching them only adds noise dimensions
    whose every move makes the object hop or sink. None for a scene whose rollout is invalid: an object sunk into
    the floor (an overlapping start) touches it too, and only its height can make the scene valid."""
    from aynamics.simulate import SimConfig, simulate

    rollout = simulate(scene, config or SimConfig())
    if not rollout.valid:
        return set()
    out = set()
    for i, obj in enumerate(scene.objects):
        if rollout.touching[:2, i, -1].any() and abs(obj.state.linear_velocity[2]) < 0.05:
            out |= {f"{obj.name}.state.position[2]", f"{obj.name}.state.linear_velocity[2]"}
    return out
