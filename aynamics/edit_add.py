"""The add clause of the edit language (`aynamics.edit`): "add a sphere at [1, 2] moving at [-1, 0, 0] m/s",
"add another box at [0, 1, 2] like box_0 of mass 2 kg", "put a ball at [1, 2]", "add two spheres at [1, 2] and
[0, 3]"; its phrases are read here for the replace clause (`aynamics.edit_replace`) too.

'put', 'place', 'drop' and 'insert' are 'add'. An added object goes after the others, named `{type}_{k}` (the first
k free) unless 'named NAME' says; 'at [x, y]' rests it upright on the floor with its lowest point there (leaning with
a tilted floor), 'at [x, y, z]' puts its centre there upright. Its shape and physics are those of 'like OBJECT', else
of the scene's first object of its kind, else 0.2 m, 1 kg, friction [0.5, 0.05], damping -4 (`ADD_DEFAULTS`); the
phrases set any of them and its velocity; it starts at rest otherwise. A count ('two spheres', '3 boxes': a number
word up to ten or digits) adds that many, one per position given ('at [0, 0], [1, 0] and [2, 0]', in order), each
with the other phrases, and no single 'named'. An object added inside another is refused when the edit finishes
(`aynamics.edit.check_start` names the pair).
"""

from __future__ import annotations

import copy
import re

from aynamics.edit_targets import REMOVED, ObjectView, find_targets, gone
from aynamics.edit_words import BY_KEY, NUM, UNITS, EditError, read_value
from aynamics.scene import OBJECT_TYPES

SINGULAR = {"box": "box", "cube": "box", "sphere": "sphere", "ball": "sphere", "cylinder": "cylinder"}
PLURAL = {"boxes": "box", "cubes": "box", "spheres": "sphere", "balls": "sphere", "cylinders": "cylinder"}
KINDS = SINGULAR | PLURAL  # a kind word (singular or plural) -> its object type
KIND_WORDS = "|".join(sorted(KINDS, key=len, reverse=True))
CUBES = ("cube", "cubes")  # kind words that ask for equal half-extents
# how many: an article or ordinal is one ("a second box"), a number word or digits that many ("add two spheres")
COUNTS = {"a": 1, "an": 1, "another": 1, "a second": 1, "a third": 1, "one": 1}
COUNTS |= {w: k for k, w in enumerate(("two", "three", "four", "five", "six", "seven", "eight", "nine", "ten"), 2)}
COUNT = rf"{'|'.join(sorted(COUNTS, key=len, reverse=True))}|\d+"
# "add a sphere ...", "put another box ...", "add two more spheres ...": the count, the kind, then the phrases of
# `_ADD_PHRASES` in any order
ADD_VERBS = r"(?:add|insert|put|place|drop)"
ADD_CLAUSE = rf"{ADD_VERBS} (?P<n>{COUNT})(?: (?:more|new|other))? (?P<k>{KIND_WORDS})\b(?P<rest>.*)"
_VEC = r"\[[^\]]*\]"
# a number and its unit; the word after a bare number is the next phrase's ("of radius 0.1 and height 0.3" read
# "and" as the radius' unit)
_NEXT = r"(?:and|with|of|a|an|named|called|like|copied|at|moving|going|travell?ing|sliding|rolling|velocity|radius|"
_NEXT += r"height|size|half-extents|mass|weighing)\b"
PHRASE_START = _NEXT  # a word that starts a phrase of an add or replace clause (`aynamics.edit`)
_AMOUNT = rf"{NUM}(?: ?(?!{_NEXT})[a-z/]+)?"
_UNIT_WORDS = "|".join(sorted({re.escape(u) for table in UNITS.values() for u in table}, key=len, reverse=True))
_VEC_UNIT = rf"{_VEC}(?: ?(?:{_UNIT_WORDS}))?"  # "[1, 0, 0] cm/s", "[10, 10, 10] cm", "[1, 2]"
_ADD_PHRASES: tuple[tuple[str, str], ...] = (  # (what, regex of its value `v`), matched at the start of the rest
    ("name", r"(?:named|called) (?P<v>[a-z_][\w.-]*)"),
    ("like", r"(?:like|copied from) (?P<v>(?:the )?[\w.-]+)"),  # "like box_0", "like the box", "like it"
    # one position, or one per object of a count: "at [1, 2] and [0, 3]", "at [0, 0], [1, 0] and [2, 0]"
    ("position", rf"at (?:positions? )?(?P<v>{_VEC_UNIT}(?:(?: ?, ?(?:and )?| and ){_VEC_UNIT})*)"),
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
    "'add a|another box|cube|sphere|ball|cylinder at [x, y] (resting on the floor) | at [x, y, z]' (or 'put', "
    "'place', 'drop'), or 'add two|3 spheres at [x, y] and [x, y]' (one position each), then any of: "
    "'named NAME', 'like OBJECT' (its shape and physics), 'moving at [vx, vy, vz] m/s', 'of radius R', "
    "'of height H', 'of size [a, b, c]' (half-extents), 'of mass M kg'; the shape and physics not given are "
    "those of the scene's first object of the kind, else a 0.2 m object of 1 kg, friction [0.5, 0.05]"
)


def read_count(word: str, clause: str) -> int:
    """How many objects a count word names ('a' 1, 'two' 2, '3' 3), at least one."""
    n = COUNTS[word] if word in COUNTS else int(word)
    if n < 1:
        raise EditError(f"{clause!r}: a count is at least 1, not {word!r}")
    return n


def noun(kind: str, n: int) -> str:
    """'1 sphere', '2 spheres', '2 boxes'."""
    return f"{n} {kind}" if n == 1 else f"{n} {'boxes' if kind == 'box' else kind + 's'}"


def read_phrases(rest: str, clause: str, words: str = ADD_WORDS) -> dict[str, str]:
    """The phrases of an add (or replace) clause after its kind word, by what they give ('position', 'mass', ...);
    `words` is what the refusal of text it cannot read lists."""
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
            raise EditError(f"{clause!r}: {rest!r} not understood. {words}")
    return given


def positions(text: str, clause: str = "") -> list[str]:
    """The positions of an 'at' phrase, each with its unit: '[100, 0] and [200, 0] cm' -> ['[100, 0] cm',
    '[200, 0] cm']. A unit written once, after any position, is that of every position without its own ('[100, 0]
    cm and [200, 0]' read the second in metres); two units and a position without one is refused (which?)."""
    found = [(v, u or "") for v, u in re.findall(rf"({_VEC})(?: ?({_UNIT_WORDS})(?=[ ,]|$))?", text)]
    units = sorted({u for _, u in found if u})
    if len(units) > 1 and any(not u for _, u in found):
        raise EditError(f"{clause!r}: positions in {' and '.join(units)} and one without a unit: give each its unit")
    return [f"{v} {u or (units[0] if units else '')}".strip() for v, u in found]


def like_object(given: dict[str, str], kind: str, items: list[dict], objs: ObjectView, clause: str, previous) -> dict:
    """The item 'like OBJECT' names; it must be one object of the kind."""
    like = find_targets(given["like"], objs, previous, gone(items))
    if len(like) != 1 or objs.structure[like[0]] != kind:
        names = [objs.names[i] for i in like]
        raise EditError(f"{clause!r}: 'like {given['like']}' must name one {kind}, not {names}")
    return items[like[0]]


def set_shape(item: dict, given: dict[str, str], kind_word: str, clause: str) -> None:
    """Write the radius, height, size and mass phrases into an object item (in place); a cube's size must be one
    half-extent three times."""
    kind = KINDS[kind_word]
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
        if kind_word in CUBES and what == "size" and len(set(value)) != 1:
            raise EditError(f"{clause!r}: a cube has equal half-extents, not {value}; say 'a box'")
        (item["physics"] if what == "mass" else item)[q.path[-1]] = value


def new_name(kind: str, given: dict[str, str], items: list[dict], clause: str, raw: str, free: str = "") -> str:
    """A new object's name: 'named NAME' (in the case `raw`, the instruction as typed, gives it), else `{kind}_{k}`
    with the first k free. Every object's name is taken, those removed so far included, but `free` (a replaced
    object's name)."""
    names = [it["name"] for it in items if it["type"] in OBJECT_TYPES]
    taken = {n.lower() for n in names} - {free.lower()}
    name = given.get("name") or next(f"{kind}_{k}" for k in range(len(taken) + 1) if f"{kind}_{k}" not in taken)
    if "name" in given and (typed := re.search(rf"\b(?:named|called)\s+({re.escape(name)})(?![\w.-])", raw, re.I)):
        name = typed.group(1)  # "named Ball" named it ball
    if name.lower() in ("camera", "gravity", "environment"):  # diff read the camera's fields as removed
        raise EditError(
            f"{clause!r}: {name!r} is the name of the scene's {name.lower()} item; name the {kind} otherwise"
        )
    if name.lower() in taken:
        raise EditError(f"{clause!r}: the scene already has an object named {name!r} (its objects: {names})")
    return name


def velocity(given: dict[str, str], clause: str) -> list[float] | None:
    """The velocity phrase in m/s ('[1, 0, 0] cm/s' too), or None when there is none."""
    if "velocity" not in given:
        return None
    vector, unit = _vector_and_unit(given["velocity"])  # "[1, 0, 0] cm/s" was "'cm/s' not understood"
    return [v * _unit(unit, "velocity", "velocity", clause) for v in read_value(vector, BY_KEY["linear_velocity"])[0]]


def add_objects(
    count_word: str,
    kind_word: str,
    rest: str,
    items: list[dict],
    objs: ObjectView,
    clause: str,
    previous: list[int] | str | None = None,
    raw: str = "",
) -> list[int]:
    """Insert the objects an 'add' clause describes after the objects (in place); their indices. `objs`: the items'
    objects (`object_view`). 'like it' is the object of the clause before (`previous`); 'named NAME' keeps the case
    NAME has in `raw`, the instruction as typed."""
    kind, count = KINDS[kind_word], read_count(count_word, clause)
    given = read_phrases(rest, clause)
    if "position" not in given:
        goes = f"the {kind} goes" if count == 1 else f"the {noun(kind, count)} go (one position each)"
        raise EditError(f"{clause!r}: say where {goes}: 'at [x, y]' (resting on the floor) or 'at [x, y, z]'")
    at = positions(given["position"], clause)
    if len(at) != count:
        raise EditError(
            f"{clause!r}: {noun(kind, count)} take{'s' if count == 1 else ''} {count} position"
            f"{'' if count == 1 else 's'} (one each, in order), not {len(at)}: {', '.join(at)}"
        )
    if count > 1 and "name" in given:
        raise EditError(
            f"{clause!r}: 'named {given['name']}' names one object, not {count}; add them one clause at a time "
            "to name each"
        )
    if "like" in given:
        template = like_object(given, kind, items, objs, clause, previous)
    else:
        template = next((it for it in items if it["type"] == kind and not it.get(REMOVED)), None)
    if template is None:
        # deep copies: "set its friction to 0.9" wrote 0.9 into ADD_DEFAULTS' friction list (every later default too)
        shape = {"type": kind, **copy.deepcopy(ADD_DEFAULTS[kind]), "physics": copy.deepcopy(ADD_DEFAULTS["physics"])}
    else:
        shape = {k: copy.deepcopy(v) for k, v in template.items() if k not in ("name", "state", REMOVED)}
    if kind_word in CUBES and "size" not in given and len(set(shape["size"])) != 1:  # the scene's box is no cube
        shape["size"] = list(ADD_DEFAULTS["box"]["size"])
    set_shape(shape, given, kind_word, clause)
    moving = velocity(given, clause) or [0.0, 0.0, 0.0]
    added = []
    for where in at:
        item = copy.deepcopy(shape)
        name = new_name(kind, given, items, clause, raw)
        position, orientation = _placement(where, item, items, clause)
        state = {"angular_velocity": [0.0, 0.0, 0.0], "linear_velocity": list(moving)}
        item = {"type": kind, "name": name, **item, "state": state | {"orientation": orientation, "position": position}}
        index = sum(it["type"] in OBJECT_TYPES for it in items)  # objects come first, the camera and the rest after
        items.insert(index, item)
        added.append(index)
    return added


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
