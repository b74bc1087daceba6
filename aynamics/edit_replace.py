"""The replace clause of the edit language (`aynamics.edit`): "replace box_0 with a sphere", "swap the cylinder for
a box", "turn box_0 into a ball of radius 0.1 m", "replace the boxes with spheres".

    replace|swap (out)|turn|change TARGETS with|by|for|into|to a|an KIND [phrases]   (KINDS for several targets)

The new object takes the replaced one's place in the object list, its velocity and spin and its physics (mass,
friction, damping, restitution, magnus, friction slope). Its shape is that of the phrases the add clause reads
(`aynamics.edit_add`): 'of radius R', 'of height H', 'of size [a, b, c]', 'like OBJECT' (that object's shape only:
the physics stay the replaced object's), 'of mass M', 'moving at [vx, vy, vz]', 'named NAME'; a shape they do not
give has the replaced object's extent: its half-extents along its own axes e = (ex, ey, ez) (a box's size, a
sphere's (r, r, r), a cylinder's (r, r, h/2)) are a new box's size, a new cube's size their mean (three times), a new
sphere's radius their mean, and a new cylinder's radius (ex + ey) / 2 and height 2 ez. So a box of size
[0.1, 0.2, 0.3] becomes a sphere of radius 0.2, and an object replaced by its own kind keeps its shape.

Pose: the new object keeps the old one's orientation, but a box or cylinder replacing a sphere (whose orientation
shows nothing) stands upright as an added object does (leaning with a tilted floor when it rests on it). If the old
object rested on the floor (its lowest point along the floor's normal within `REST_TOLERANCE` of the floor plane),
the new one moves along the normal so that its own lowest point is where the old one's was: on a level floor the
same [x, y], its lowest point on the floor, as 'add ... at [x, y]' places it. Otherwise its centre is the old one.

Name: 'named NAME', else `{type}_{k}` with the first k free, as the add clause names; the replaced object's name is
free for an object of its own kind ("replace box_0 with a box of size [...]" keeps box_0 and reads as box_0's
fields changing), never for another kind (`aynamics.edit_diff.diff` tells objects apart by name and shape). The same
kind is allowed: it changes what the phrases say and nothing else. Several targets take a plural kind ('spheres',
'two spheres': as many as the targets) and no 'named'; 'at [...]' is refused (a replacement goes where the old
object was). 'it', 'its', 'them' in the next clause are the new objects.
"""

from __future__ import annotations

import copy
import math

from aynamics.edit_add import (
    COUNT,
    CUBES,
    KIND_WORDS,
    KINDS,
    PLURAL,
    like_object,
    new_name,
    noun,
    read_count,
    read_phrases,
    set_shape,
    velocity,
)
from aynamics.edit_targets import REMOVED, ObjectView, check_not_removed, find_targets, gone
from aynamics.edit_words import EditError

REPLACE_VERBS = r"(?:replace|swap(?: out)?|turn|change)"
# "replace box_0 with a sphere ...", "swap the boxes for spheres ...": the targets, the count (none: one, or one per
# target for a plural kind), the kind, then the add clause's phrases
WITH_KIND = rf"(?:with|by|for|into|to) (?:(?P<n>{COUNT})(?: new| other)? )?(?P<k>{KIND_WORDS})\b"  # "with two spheres"
REPLACE_CLAUSE = rf"{REPLACE_VERBS} (?P<t>.+?) {WITH_KIND}(?P<rest>.*)"
REPLACE_WORDS = (
    "'replace|swap|turn|change TARGETS with|for|into a|an box|cube|sphere|ball|cylinder' (several targets: "
    "'spheres'), then any of: 'named NAME', 'like OBJECT' (its shape), 'moving at [vx, vy, vz] m/s', 'of radius R', "
    "'of height H', 'of size [a, b, c]' (half-extents), 'of mass M kg'; the new object takes the old one's place, "
    "velocity and physics, and a shape of the old one's extent where none is given; 'replace box_0 with a sphere "
    "and cylinder_0 with a box' is two replacements"
)
REST_TOLERANCE = 1e-3  # m: an object whose lowest point is this close to the floor plane rests on it


def replace_objects(
    target: str,
    count_word: str | None,
    kind_word: str,
    rest: str,
    items: list[dict],
    objs: ObjectView,
    clause: str,
    previous: list[int] | str | None = None,
    raw: str = "",
) -> list[int]:
    """Replace the objects a target phrase names with new objects of a kind (in place; see the module docstring);
    the new objects' indices. Each old item is marked `REMOVED` (so its name stays taken for later clauses, as a
    removed object's does) and its replacement goes right after it, where it is once the removed items are dropped."""
    idx = find_targets(target, objs, previous, gone(items))
    check_not_removed(items, idx, clause)
    kind, names = KINDS[kind_word], [objs.names[i] for i in idx]
    count = read_count(count_word, clause) if count_word else len(idx) if kind_word in PLURAL else 1
    if count != len(idx):
        raise EditError(
            f"{clause!r}: {noun(kind, count)} for {len(idx)} object{'s' if len(idx) != 1 else ''} {names}: one "
            f"replaces each; say '{f'a {kind}' if len(idx) == 1 else noun(kind, 2).split(' ', 1)[1]}'"
        )
    given = read_phrases(rest, clause, REPLACE_WORDS)
    if "position" in given:
        raise EditError(
            f"{clause!r}: a replacement goes where the object it replaces was, not 'at {given['position']}'; "
            "move it in a later clause, or remove the object and add the new one"
        )
    if len(idx) > 1 and "name" in given:
        raise EditError(
            f"{clause!r}: 'named {given['name']}' names one object, not the {len(idx)} new ones; replace {names} "
            "one clause at a time to name each"
        )
    like = like_object(given, kind, items, objs, clause, previous) if "like" in given else None
    moving = velocity(given, clause)  # None: each keeps its old one's
    out = []
    for j, i in enumerate(idx):
        at = i + j  # each replacement before this one was inserted after its old item
        old = items[at]
        if "name" in given and given["name"] == old["name"].lower() and old["type"] != kind:
            raise EditError(
                f"{clause!r}: {old['name']} is a {old['type']}, so the {kind} replacing it needs another name "
                "(a name keeps its shape through an edit)"
            )
        free = old["name"] if old["type"] == kind else ""  # a box replacing box_0 may be box_0
        item = {"type": kind, "name": new_name(kind, given, items, clause, raw, free)}
        item |= _shape(kind, kind_word, old, like)
        item["physics"] = copy.deepcopy(old["physics"])
        set_shape(item, given, kind_word, clause)
        position, orientation = pose_after(old, item, items)
        state = old["state"]
        item["state"] = {
            "angular_velocity": list(state["angular_velocity"]),
            "linear_velocity": list(moving or state["linear_velocity"]),
            "orientation": orientation,
            "position": position,
        }
        old[REMOVED] = True
        items.insert(at + 1, item)
        out.append(at + 1)
    return out


def half_extents(item: dict) -> list[float]:
    """An object item's half-extents along its own axes: a box's size, a sphere's (r, r, r), a cylinder's (r, r,
    h/2)."""
    if item["type"] == "box":
        return [float(v) for v in item["size"]]
    if item["type"] == "sphere":
        return [float(item["radius"])] * 3
    return [float(item["radius"]), float(item["radius"]), float(item["height"]) / 2]


def _shape(kind: str, kind_word: str, old: dict, like: dict | None) -> dict:
    """The shape fields of a replacement: `like`'s, else those of the old object's extent (the module docstring)."""
    if like is not None:
        return {k: copy.deepcopy(like[k]) for k in ("size", "radius", "height") if k in like}
    ex, ey, ez = half_extents(old)
    mean = (ex + ey + ez) / 3
    if kind == "box":
        return {"size": [mean] * 3 if kind_word in CUBES else [ex, ey, ez]}
    if kind == "sphere":
        return {"radius": mean}
    return {"radius": (ex + ey) / 2, "height": 2 * ez}


def pose_after(old: dict, item: dict, items: list[dict]) -> tuple[list[float], list[float]]:
    """The position and orientation of a replacement `item` of `old` (the module docstring); for an object whose
    shape an edit changed (`aynamics.edit`: "double the size of box_0"), `old` is it before: one that rested on the
    floor rests on it still, one in the air keeps its centre."""
    import numpy as np

    from aynamics.mujoco_model import quat_to_mat, tilt_quaternion

    env = next((it for it in items if it["type"] == "environment"), {})
    offset, tilt = float(env.get("floor_offset") or 0.0), env.get("floor_tilt") or [0.0, 0.0]
    floor = tilt_quaternion(*tilt) if any(tilt) else np.array([1.0, 0.0, 0.0, 0.0])
    normal = quat_to_mat(floor)[:, 2]  # (3,) the floor's up
    centre = np.array(old["state"]["position"], dtype=float)
    depth = _depth(old, np.asarray(old["state"]["orientation"], dtype=float), normal)
    rests = abs(float((centre - [0.0, 0.0, offset]) @ normal) - depth) <= REST_TOLERANCE
    orientation = np.asarray(old["state"]["orientation"], dtype=float)
    if old["type"] == "sphere" and item["type"] != "sphere":  # a ball's turn would tip a box onto its corner
        orientation = floor if rests else np.array([1.0, 0.0, 0.0, 0.0])
    if rests:  # its lowest point where the old one's was
        centre = centre + (_depth(item, orientation, normal) - depth) * normal
    return [float(v) for v in centre], [float(v) for v in orientation]


def _depth(item: dict, orientation, normal) -> float:
    """How far an object's lowest point along `normal` (3,) lies below its centre, turned by `orientation` (wxyz)."""
    from aynamics.mujoco_model import quat_to_mat

    n = quat_to_mat(orientation).T @ normal  # (3,) the normal in the object's frame
    ex, ey, ez = half_extents(item)
    if item["type"] == "box":
        return float(abs(n[0]) * ex + abs(n[1]) * ey + abs(n[2]) * ez)
    if item["type"] == "sphere":
        return ex
    c = min(abs(float(n[2])), 1.0)  # a cylinder: its cap's rim, or its side when it lies
    return c * ez + ex * math.sqrt(1.0 - c * c)
