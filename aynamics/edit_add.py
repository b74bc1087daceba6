"""The add clause of the edit language (`aynamics.edit`): "add a sphere at [1, 2] moving at [-1, 0, 0] m/s",
"add another box at [0, 1, 2] like box_0 of mass 2 kg".

An added object goes after the others, named `{type}_{k}` (the first k free) unless 'named NAME' says; 'at [x, y]'
rests it upright on the floor with its lowest point there (leaning with a tilted floor), 'at [x, y, z]' puts its
centre there upright. Its shape and physics are those of 'like OBJECT', else of the scene's first object of its kind,
else 0.2 m, 1 kg, friction [0.5, 0.05], damping -4 (`ADD_DEFAULTS`); the phrases set any of them and its velocity; it
starts at rest otherwise. An object added inside another is the simulation's to refuse (its rollout names the pair).
"""

from __future__ import annotations

import copy
import re

from aynamics.edit_targets import REMOVED, ObjectView, find_targets, gone
from aynamics.edit_words import BY_KEY, NUM, UNITS, EditError, read_value
from aynamics.scene import OBJECT_TYPES

KINDS = {"box": "box", "cube": "box", "sphere": "sphere", "ball": "sphere", "cylinder": "cylinder"}
# "add a sphere ...", "add another box ...": the kind, then the phrases of `_ADD_PHRASES` in any order
ADD_CLAUSE = rf"(?:add|insert) (?:a|an|another|one more|a new|a second|a third) (?P<k>{'|'.join(KINDS)})(?P<rest>.*)"
_VEC = r"\[[^\]]*\]"
# a number and its unit; the word after a bare number is the next phrase's ("of radius 0.1 and height 0.3" read
# "and" as the radius' unit)
_NEXT = r"(?:and|with|of|a|an|named|called|like|copied|at|moving|going|travell?ing|sliding|rolling|velocity|radius|"
_NEXT += r"height|size|half-extents|mass|weighing)\b"
_AMOUNT = rf"{NUM}(?: ?(?!{_NEXT})[a-z/]+)?"
_UNIT_WORDS = "|".join(sorted({re.escape(u) for table in UNITS.values() for u in table}, key=len, reverse=True))
_VEC_UNIT = rf"{_VEC}(?: ?(?:{_UNIT_WORDS}))?"  # "[1, 0, 0] cm/s", "[10, 10, 10] cm", "[1, 2]"
_ADD_PHRASES: tuple[tuple[str, str], ...] = (  # (what, regex of its value `v`), matched at the start of the rest
    ("name", r"(?:named|called) (?P<v>[a-z_][\w.-]*)"),
    ("like", r"(?:like|copied from) (?P<v>(?:the )?[\w.-]+)"),  # "like box_0", "like the box", "like it"
    ("position", rf"at (?:position )?(?P<v>{_VEC_UNIT})"),
    ("velocity", rf"(?:moving|going|travell?ing|sliding|rolling) (?:at |with )?(?P<v>{_VEC_UNIT})"),
    ("velocity", rf"(?:with )?(?:a |an initial )?velocity (?:of )?(?P<v>{_VEC_UNIT})"),
    ("radius", rf"(?:of |with )?(?:a )?radius (?:of )?(?P<v>{_AMOUNT})"),
    ("height", rf"(?:of |with )?(?:a )?height (?:of )?(?P<v>{_AMOUNT})"),
    ("size", rf"(?:of |with )?(?:a )?(?:size|half-extents) (?:of )?(?P<v>{_VEC_UNIT})"),
    ("mass", rf"(?:of |with )?(?:a )?mass (?:of )?(?P<v>{_AMOUNT})"),
    ("mass", rf"weighing (?P<v>{_AMOUNT})"),
)
ADD_DEFAULTS = {  # an added object's shape and physics when the scene has no object of its kind and no "like"
    "box": {"size": [0.2, 0.2, 0.2]},
    "sphere": {"radius": 0.2},
    "cylinder": {"radius": 0.2, "height": 0.4},
    "physics": {"friction": [0.5, 0.05], "mass": 1.0, "damping": -4.0},
}
ADD_WORDS = (
    "'add a|another box|cube|sphere|ball|cylinder at [x, y] (resting on the floor) | at [x, y, z]', then any of: "
    "'named NAME', 'like OBJECT' (its shape and physics), 'moving at [vx, vy, vz] m/s', 'of radius R', "
    "'of height H', 'of size [a, b, c]' (half-extents), 'of mass M kg'; the shape and physics not given are "
    "those of the scene's first object of the kind, else a 0.2 m object of 1 kg, friction [0.5, 0.05]"
)


def add_object(
    kind_word: str,
    rest: str,
    items: list[dict],
    objs: ObjectView,
    clause: str,
    previous: list[int] | str | None = None,
    raw: str = "",
) -> int:
    """Insert the object an 'add' clause describes after the objects (in place); its index. `objs`: the items'
    objects (`object_view`). 'like it' is the object of the clause before (`previous`); 'named NAME' keeps the case
    NAME has in `raw`, the instruction as typed."""
    kind = KINDS[kind_word]
    given: dict[str, str] = {}
    rest = rest.strip(" ,")
    while rest:
        rest = re.sub(r"^(?:and|with|,)\s*", "", rest)
        for what, pattern in _ADD_PHRASES:
            if m := re.match(rf"{pattern}(?=[ ,]|$)", rest):
                if what in given:
                    raise EditError(f"{clause!r}: the {what} is given twice ({given[what]!r}, {m.group('v')!r})")
                given[what] = m.group("v")
                rest = rest[m.end() :].strip(" ,")
                break
        else:
            raise EditError(f"{clause!r}: {rest!r} not understood. {ADD_WORDS}")
    if "position" not in given:
        raise EditError(f"{clause!r}: say where the {kind} goes: 'at [x, y]' (resting on the floor) or 'at [x, y, z]'")
    if "like" in given:
        like = find_targets(given["like"], objs, previous, gone(items))
        if len(like) != 1 or objs.structure[like[0]] != kind:
            names = [objs.names[i] for i in like]
            raise EditError(f"{clause!r}: 'like {given['like']}' must name one {kind}, not {names}")
        template = items[like[0]]
    else:
        template = next((it for it in items if it["type"] == kind and not it.get(REMOVED)), None)
    if template is None:
        # deep copies: "set its friction to 0.9" wrote 0.9 into ADD_DEFAULTS' friction list (every later default too)
        item = {"type": kind, **copy.deepcopy(ADD_DEFAULTS[kind]), "physics": copy.deepcopy(ADD_DEFAULTS["physics"])}
    else:
        item = {k: copy.deepcopy(v) for k, v in template.items() if k not in ("name", "state", REMOVED)}
    if kind_word == "cube" and "size" not in given and len(set(item["size"])) != 1:  # the scene's box is no cube
        item["size"] = list(ADD_DEFAULTS["box"]["size"])
    for what in ("radius", "height", "size", "mass"):
        if what not in given:
            continue
        q = BY_KEY[what]
        if q.path[0] != "physics" and q.path[-1] not in item:
            raise EditError(f"{clause!r}: a {kind} has no {what}")
        vector, unit = _vector_and_unit(given[what])  # "[10, 10, 10] cm"; "10 cm" is read_value's
        value, unit_kind = read_value(vector, q)
        if unit_kind != "abs":
            raise EditError(f"{clause!r}: the {what} takes a value, not {given[what]!r}")
        if unit:
            value = [v * _unit(unit, "length", what, clause) for v in value]
        if kind_word == "cube" and what == "size" and len(set(value)) != 1:
            raise EditError(f"{clause!r}: a cube has equal half-extents, not {value}; say 'a box'")
        (item["physics"] if what == "mass" else item)[q.path[-1]] = value
    taken = {it["name"].lower() for it in items if it["type"] in OBJECT_TYPES}
    name = given.get("name") or next(f"{kind}_{k}" for k in range(len(taken) + 1) if f"{kind}_{k}" not in taken)
    if "name" in given and (typed := re.search(rf"\b(?:named|called)\s+({re.escape(name)})(?![\w.-])", raw, re.I)):
        name = typed.group(1)  # "named Ball" named it ball
    if name.lower() in ("camera", "gravity", "environment"):  # diff read the camera's fields as removed
        raise EditError(
            f"{clause!r}: {name!r} is the name of the scene's {name.lower()} item; name the {kind} otherwise"
        )
    if name.lower() in taken:
        raise EditError(f"{clause!r}: the scene already has an object named {name!r} (its objects: {list(objs.names)})")
    position, orientation = _placement(given["position"], item, items, clause)
    velocity = [0.0, 0.0, 0.0]
    if "velocity" in given:  # "[1, 0, 0] cm/s" was "'cm/s' not understood"
        vector, unit = _vector_and_unit(given["velocity"])
        velocity = [
            v * _unit(unit, "velocity", "velocity", clause) for v in read_value(vector, BY_KEY["linear_velocity"])[0]
        ]
    state = {"angular_velocity": [0.0, 0.0, 0.0], "linear_velocity": velocity}
    item = {"type": kind, "name": name, **item, "state": state | {"orientation": orientation, "position": position}}
    at = len(objs.names)  # objects come first in the items, the camera and the rest after them
    items.insert(at, item)
    return at


def _vector_and_unit(text: str) -> tuple[str, str]:
    """'[10, 10, 10] cm' -> ('[10, 10, 10]', 'cm'); a value that is no vector is returned whole, with no unit."""
    m = re.fullmatch(r"(\[.*\])\s*([a-z/]*)", text)
    return (m.group(1), m.group(2)) if m else (text, "")


def _unit(unit: str, kind: str, what: str, clause: str) -> float:
    """The SI factor of a unit of `UNITS[kind]` ('' is SI)."""
    if unit and unit not in UNITS[kind]:
        raise EditError(f"{clause!r}: unit {unit!r} does not fit {what}: allowed {', '.join(UNITS[kind])}")
    return UNITS[kind][unit] if unit else 1.0


def _placement(text: str, item: dict, items: list[dict], clause: str) -> tuple[list[float], list[float]]:
    """The position and orientation of an added object: '[x, y, z]' upright there, '[x, y]' resting upright on the
    floor plane (`environment.floor_offset`, tilted by `floor_tilt`: the object then leans with the floor) with
    its lowest point at x, y; a length unit may follow ('[100, 50] cm')."""
    text, unit = _vector_and_unit(text)
    factor = _unit(unit, "length", "position", clause)
    try:
        at = [float(v) * factor for v in text.strip("[] ").split(",")]
    except ValueError:
        raise EditError(f"{clause!r}: a position is [x, y] or [x, y, z] numbers, not {text}") from None
    if len(at) == 3:
        return at, [1.0, 0.0, 0.0, 0.0]
    if len(at) != 2:
        raise EditError(f"{clause!r}: a position is [x, y] (resting on the floor) or [x, y, z], not {text}")
    env = next((it for it in items if it["type"] == "environment"), {})
    offset, tilt = float(env.get("floor_offset") or 0.0), env.get("floor_tilt") or [0.0, 0.0]
    half = (
        item["size"][2] if item["type"] == "box" else item["radius"] if item["type"] == "sphere" else item["height"] / 2
    )
    if not any(tilt):
        return [at[0], at[1], offset + half], [1.0, 0.0, 0.0, 0.0]
    from aynamics.mujoco_model import quat_to_mat, tilt_quaternion

    q = tilt_quaternion(*tilt)
    n = quat_to_mat(q)[:, 2]
    z = offset - (n[0] * at[0] + n[1] * at[1]) / n[2]  # the floor plane below x, y
    return [float(v) for v in (at[0], at[1], z) + half * n], [float(v) for v in q]
