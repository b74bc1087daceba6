"""Comparing two scenes leaf by leaf: what an edit changed (`aynamics.edit`, the free editor's check in
`aynamics.edit_llm`, `aynamics edit`'s report).

    diff(before, after)   # [Change("box_0.physics.mass", 1.0, 2.0), Change("sphere_0", None, "sphere"), ...]
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from aynamics.edit_words import EditError
from aynamics.scene import OBJECT_TYPES, Environment, Scene, require_scene, to_items


@dataclass(frozen=True)
class Change:
    """One leaf of the scene that an edit changed. `path` uses object names: `box_0.state.position[0]`. An object
    the edit removed is one change: its name as the path, its type before, None after; one it added the other way
    round (its fields are in the edited scene)."""

    path: str
    before: Any
    after: Any

    @property
    def removed(self) -> bool:
        return self.after is None and "." not in self.path and self.before in OBJECT_TYPES

    @property
    def added(self) -> bool:
        return self.before is None and "." not in self.path and self.after in OBJECT_TYPES

    def __str__(self) -> str:
        if self.removed:
            return f"{self.path}: removed ({self.before})"
        if self.added:
            return f"{self.path}: added ({self.after})"
        return f"{self.path}: {self.before} -> {self.after}"


def _flatten(scene: Scene) -> dict[str, Any]:
    out: dict[str, Any] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        elif isinstance(value, list):
            for i, v in enumerate(value):
                walk(f"{prefix}[{i}]", v)
        else:
            out[prefix] = value

    # No environment item is the default one (no air, wind or tilt, clock 1), and time_scale is dumped only when it
    # is not 1: without both, a default item written out was 8 changes "None -> 0.0" and a clock set back to 1
    # was "environment.time_scale: 1.5 -> None"
    env = scene.environment or Environment()
    for item in to_items(scene.model_copy(update={"environment": env})):
        head = item["name"] if item["type"] in ("box", "sphere", "cylinder") else item["type"]
        walk(head, {k: v for k, v in item.items() if k not in ("type", "name")})
        if item["type"] in ("box", "sphere", "cylinder"):  # absent simulates as 0 (restitution's absence does not)
            for k in ("magnus", "friction_slope"):
                out[f"{head}.physics.{k}"] = item["physics"].get(k) or 0.0
    out["environment.time_scale"] = env.time_scale
    return out


def diff(before: Scene, after: Scene, tol: float = 1e-9) -> list[Change]:
    """Every leaf that differs between two scenes of the same objects (paths use object names), each object
    `after` leaves out (`Change(name, type, None)`, `Change.removed`) and each it adds (`Change(name, None, type)`,
    `Change.added`; a name `before` does not have). A scene without an environment item compares as one with the
    default item (no air, wind or tilt, time_scale 1), and an object without `magnus` or `friction_slope` as one
    with 0, as they simulate.

    Raises:
        EditError: `after` reorders the objects both have or gives one of them another shape (an edit keeps the
            objects, removes some or adds new ones).
    """
    require_scene(before, "diff: before")  # YAML text failed on "'str' object has no attribute 'names'"
    require_scene(after, "diff: after")
    try:  # numpy's float32 / int64 (and 0-d arrays) are numbers too; str and bool are not
        ok = not isinstance(tol, (bool, str, bytes)) and 0 <= float(tol) < math.inf  # NaN: tol ignored
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"diff: tol = {tol!r}: must be a finite number >= 0")
    tol = float(tol)
    now = list(zip(after.names, after.structure, strict=True))
    pairs = list(zip(before.names, before.structure, strict=True))
    if [p for p in pairs if p[0] in after.names] != [p for p in now if p[0] in before.names]:
        raise EditError(
            f"the edit changed the objects: {pairs} -> {now}; edits keep the objects (in their order and shapes), "
            "remove some or add new ones, and change numbers"
        )
    gone = [(name, kind) for name, kind in pairs if name not in after.names]
    new = [(name, kind) for name, kind in now if name not in before.names]
    out = [Change(name, kind, None) for name, kind in gone] + [Change(name, None, kind) for name, kind in new]
    a, b = _flatten(before), _flatten(after)
    a = {k: v for k, v in a.items() if not k.startswith(tuple(f"{name}." for name, _ in gone))}
    b = {k: v for k, v in b.items() if not k.startswith(tuple(f"{name}." for name, _ in new))}
    for key in [*a, *(k for k in b if k not in a)]:
        va, vb = a.get(key), b.get(key)
        same = va == vb or (
            isinstance(va, float | int) and isinstance(vb, float | int) and abs(float(va) - float(vb)) <= tol
        )
        if not same:
            out.append(Change(key, va, vb))
    return out
