"""The scene language's canonical dump: a `Scene` as YAML with the paper's fixed key order and at most `DECIMALS`
decimals, and as the plain Python items that YAML lists (`to_items`: what edits and refinement change before
`scene.from_items` validates them again). Also the names `parse` gives unnamed objects (`{type}_{k}`).

    text = dump(scene)         # canonical: fixed key order, fixed decimals; parse(dump(s)) == s

`scene.py` re-exports `dump`, `to_items`, `is_default_name` and `default_names`.
"""

from __future__ import annotations

import re
from typing import Any

from aynamics.scene_records import DECIMALS, Box, Cylinder, Scene


# --------------------------------------------------------------------------------------------
# Canonical dump
# --------------------------------------------------------------------------------------------
def _num(x: float, decimals: int = DECIMALS) -> str:
    text = f"{x:.{decimals}f}"
    if "." in text:  # trailing zeros of the fraction only ("10" at 0 decimals stays 10)
        text = text.rstrip("0")
        text = text + "0" if text.endswith(".") else text
    return {"-0.0": "0.0", "-0": "0"}.get(text, text)


def _vec(v: tuple[float, ...], decimals: int = DECIMALS) -> str:
    return "[" + ", ".join(_num(x, decimals) for x in v) + "]"


def to_items(scene: Scene) -> list[dict[str, Any]]:
    """The scene as plain Python data in canonical order (what `dump` writes)."""
    items: list[dict[str, Any]] = []
    for o in scene.objects:
        d: dict[str, Any] = {"type": o.type, "name": o.name}
        if isinstance(o, Box):
            d["size"] = list(o.size)
        else:
            d["radius"] = o.radius
            if isinstance(o, Cylinder):
                d["height"] = o.height
        s = o.state
        d["state"] = {
            "angular_velocity": list(s.angular_velocity),
            "linear_velocity": list(s.linear_velocity),
            "orientation": list(s.orientation),
            "position": list(s.position),
        }
        p = o.physics
        d["physics"] = {"friction": list(p.friction), "mass": p.mass, "damping": p.damping}
        if p.restitution is not None:
            d["physics"]["restitution"] = p.restitution
        if p.magnus is not None:
            d["physics"]["magnus"] = p.magnus
        if p.friction_slope is not None:
            d["physics"]["friction_slope"] = p.friction_slope
        items.append(d)
    c = scene.camera
    items.append({"type": "camera", "fovy": c.fovy, "orientation": c.orientation, "position": list(c.position)})
    items.append({"type": "gravity", "gravity": list(scene.gravity)})
    if scene.environment is not None:
        e = scene.environment
        env: dict[str, Any] = {
            "type": "environment",
            "air_density": e.air_density,
            "air_viscosity": e.air_viscosity,
            "wind": list(e.wind),
            "floor_offset": e.floor_offset,
            "floor_tilt": list(e.floor_tilt),
        }
        if e.time_scale != 1.0:  # written only when set: older environment items dump as before
            env["time_scale"] = e.time_scale
        items.append(env)
    return items


def _emit(value: Any, indent: int, lines: list[str], key: str | None = None, decimals: int = DECIMALS) -> None:
    pad = " " * indent
    if isinstance(value, dict):
        if key is not None:
            lines.append(f"{pad}{key}:")
            indent += 2
        for k, v in value.items():
            _emit(v, indent, lines, k, decimals)
        return
    if isinstance(value, list):
        text = _vec(tuple(value), decimals)
    elif isinstance(value, float | int) and not isinstance(value, bool):
        text = _num(float(value), decimals)
    else:
        text = str(value)
    lines.append(f"{pad}{key}: {text}")


_DEFAULT_NAME = re.compile(r"(box|sphere|cylinder)_\d+")


def is_default_name(name: str) -> bool:
    """Whether `name` has the form `parse` gives an unnamed object (`{type}_{k}`): a label for the object's place
    in the list, which says nothing about which object it is (`metrics.match_objects` pairs such objects by
    overlap, not by name)."""
    return _DEFAULT_NAME.fullmatch(name) is not None


def default_names(structure: tuple[str, ...]) -> tuple[str, ...]:
    """The names `parse` gives objects written without one: `{type}_{k}`, k counting objects of that type."""
    seen: dict[str, int] = {}
    out = []
    for t in structure:
        out.append(f"{t}_{seen.get(t, 0)}")
        seen[t] = seen.get(t, 0) + 1
    return tuple(out)


def dump(scene: Scene, decimals: int = DECIMALS, names: bool = True, objects_last: bool = False) -> str:
    """Canonical YAML: fixed key order (the paper's), numbers with at most `decimals` decimals.

    `parse(dump(s)) == s` for every valid scene (at the default `DECIMALS`). Fewer decimals round every number
    (shorter training targets: `data.decimals`); the result is validated again by whoever parses it.
    `names=False` leaves the `name` lines out when every name is the default one (`default_names`), which
    `parse` fills back in, so the scene read back is the same; a scene with any other name keeps them all.
    `objects_last=True` writes the camera, gravity and environment before the objects (`parse` takes the items in
    any order): a model writing the list then chooses "one more object or the end" in one token (`- ` or the
    closing tag) and the shape in the next, instead of weighing "camera" against each shape on its own.
    """
    if not 0 <= decimals <= DECIMALS:
        raise ValueError(f"decimals = {decimals}: must be in [0, {DECIMALS}]")
    drop_names = not names and scene.names == default_names(scene.structure)
    lines: list[str] = []
    items = to_items(scene)
    if objects_last:
        n = len(scene.objects)
        items = items[n:] + items[:n]
    for item in items:
        if drop_names:
            item.pop("name", None)
        first = True
        for k, v in item.items():
            sub: list[str] = []
            _emit(v, 2, sub, k, decimals)
            if first:
                sub[0] = "- " + sub[0][2:]
                first = False
            lines.extend(sub)
    return "\n".join(lines) + "\n"
