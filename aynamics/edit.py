"""Physics editing: change an inferred scene with a plain-English instruction and ask "what if".

A small deterministic instruction language covers the paper's edits and their kin; several clauses can be
joined with ";", "then" or "and", and "it", "its", "them", "their" name the objects of the clause before (or the
camera, after a clause that edited it):

    reduce the x-velocity of box_0 by 80%        decrease gravity by 50%
    increase the y-velocity by 50%  (no object named: every object)
    set the mass of sphere_1 to 2 kg             double the friction of cylinder_0
    move box_0 0.5 m left                        reverse the z-velocity of the sphere
    put box_0 at [1, 2, 0.4]                     place the cylinder at [0, 1]  (its height kept)
    stop box_0                                   set the velocity of box_0 to [1, 0, 0]
    make the box twice as heavy                  make sphere_1 slower by 1 m/s
    moon gravity                                 increase the mass by a factor of 3
    move the camera 1 m back                     set the camera height to 3 m
    put the camera at [0, -4, 3]                 increase the tilt of the camera by 10 degrees
    raise the camera by 1 m                      tilt the camera up by 10 degrees  (from straight down)
    turn off gravity                             zero gravity
    double the mass of box_0 and halve its friction
    make the sphere 3 times faster               remove box_0
    add a sphere at [1, 2] moving at [-1, 0, 0] m/s        add another box at [0, 1, 2] like box_0 of mass 2 kg
    put a ball at [1, 2]  (put, place, drop: add)          add two spheres at [1, 2] and [0, 3]
    replace box_0 with a sphere and double its mass        swap the cylinder for a box named crate
    turn box_0 into a ball of radius 0.1 m                 replace the boxes with spheres
    replace box_0 with a sphere and cylinder_0 with a box  (one replacement each)

Directions are world axes as the default camera sees them: "left" is -x, "right" +x, "forward"/"away" +y
(the camera looks along +y), "back"/"toward the camera" -y, "up" +z, "down" -z. A percentage or factor on a
vector without a component ("the velocity") scales the whole vector; an amount with a unit ("by 1 m/s") changes
its magnitude along its direction; on a component ("the x-velocity", "the z-gravity") it adds along that axis,
signs included: "increase the x-velocity by 1 m/s" takes -1 to 0 and "reduce the z-gravity by 2 m/s^2" takes -7
to -9 (stronger), where "by 50%" scales the component's size (-1 to -0.5: "reduce ... by 50%").
A shape change ("double the size of box_0") keeps an object that rests on the floor resting on it (its lowest point
stays), one in the air its centre.
`damping` is log10 of a decay rate, so "double the damping" doubles the rate and "set the damping to 0.5 /s" sets
the rate (a plain number sets the log10 value).

An 'add' clause is read in `aynamics.edit_add` (where an added object goes, its name, shape and physics; a count
takes one position each: the "and" between positions joins positions, not clauses), a 'replace' clause in
`aynamics.edit_replace` (the new object takes the old one's place, pose, velocity and physics, and its extent unless
the phrases give a shape), the objects a target phrase or a pronoun names in `aynamics.edit_targets`, where one
clause ends and the next starts in `aynamics.edit_clauses`.

    result = apply_instruction(scene, "reduce the x-velocity of box_0 by 80%")
    result.scene, result.changes   # the validated edited scene; every leaf that changed, every object removed or
                                   # added

`aynamics edit SCENE.yaml "INSTRUCTION" [--out EDITED.yaml] [--render DIR] [--llm MODEL]` runs it; the optional
language-model editor lives in `aynamics.edit_llm`, rendering of the what-if in `aynamics.whatif`.
Instructions it cannot read raise `EditError` listing what it understands; an edit that makes the scene invalid
is refused with the validation error, one that makes objects start inside each other or the floor with the pair and
the depth (`check_start`), and nothing is written.
"""

from __future__ import annotations

import copy
import math
import re
from dataclasses import dataclass

from aynamics.edit_add import ADD_CLAUSE, COUNT, KIND_WORDS, add_objects
from aynamics.edit_add import ADD_DEFAULTS as ADD_DEFAULTS
from aynamics.edit_clauses import MOVE_VERBS, NO_GRAVITY, REMOVE_CLAUSE
from aynamics.edit_clauses import split_clauses as split_clauses
from aynamics.edit_diff import Change as Change
from aynamics.edit_diff import diff as diff
from aynamics.edit_replace import REPLACE_CLAUSE, pose_after, replace_objects
from aynamics.edit_targets import (
    REMOVED,
    ObjectView,
    check_not_removed,
    find_targets,
    gone,
    object_view,
    previous_targets,
)
from aynamics.edit_words import (
    AS_OF,
    AS_WORDS,
    BY_KEY,
    CAMERA_FIELDS,
    CAMERA_POSITION,
    ER_WORDS,
    FACTOR,
    FACTORS,
    NUM,
    PLANET,
    PLANET_NAMES,
    TIMES,
    UP,
    VERBS_BY,
    FieldError,
    camera_quantity,
    quantity,
    read_factor,
    read_times,
    read_value,
    subject,
)
from aynamics.edit_words import DIRECTIONS as DIRECTIONS
from aynamics.edit_words import PLANET_GRAVITY as PLANET_GRAVITY
from aynamics.edit_words import QUANTITIES as QUANTITIES
from aynamics.edit_words import UNDERSTOOD as UNDERSTOOD
from aynamics.edit_words import UNITS as UNITS
from aynamics.edit_words import EditError as EditError
from aynamics.edit_words import Quantity as Quantity
from aynamics.scene import Scene, SceneError, from_items, require_scene, to_items


@dataclass(frozen=True)
class EditResult:
    """The validated edited scene and every leaf that changed."""

    scene: Scene
    changes: tuple[Change, ...]


# --------------------------------------------------------------------------------------------
# Applying
# --------------------------------------------------------------------------------------------
def _items_of(q: Quantity, items: list[dict], targets: list[int], scene: ObjectView, named: bool) -> list[dict]:
    if q.scope == "object":
        return [items[i] for i in targets]
    if named:
        owner = "the camera" if q.scope == "camera" else "the whole scene"
        raise EditError(f"{q.key} is a property of {owner}, not of {[scene.names[i] for i in targets]}")
    for it in items:
        if it["type"] == q.scope:
            return [it]
    raise EditError(f"the scene has no {q.scope} item")


def _edit_field(item: dict, q: Quantity, comp: int | None, fn, label: str) -> None:
    """Replace the field (or its element/component) with fn(old) -> new, in place."""
    *parents, leaf = q.path
    holder = item
    for k in parents:
        holder = holder[k]
    name = item.get("name", q.scope)
    if item.get(REMOVED):
        raise EditError(f"{label}: {name} was removed by an earlier clause")
    at = q.index if q.index is not None else comp
    field = f"{name}.{'.'.join(q.path)}" + ("" if at is None else f"[{at}]")  # as `diff` names it
    try:  # the refusal names the object and field (it named the clause: "'set the spin ... to 2' is zero")
        if leaf not in holder or holder[leaf] is None:
            if q.key == "restitution":
                holder[leaf] = fn(None)
                return
            raise EditError(f"{name} has no {q.key} ({item['type']}); {label} does not apply to it")
        if at is not None:
            holder[leaf][at] = fn(holder[leaf][at])
        else:
            holder[leaf] = fn(holder[leaf])
    except FieldError as e:
        raise EditError(f"{label}: {field}: {e}") from None


def _magnitude(vec: list[float], new: float, setting: bool = False) -> list[float]:
    norm = math.sqrt(sum(x * x for x in vec))
    if new < 0 and setting:  # "set the gravity to -9.81" was called "this decrease would leave -9.81"
        raise FieldError(
            f"a magnitude is >= 0, not {new:g}; to point it the other way give [x, y, z], set one component "
            "(x-, y- or z-) or 'reverse' it"
        )
    if new < 0:  # scaling by a negative length would turn the vector around, not shorten it
        raise FieldError(
            f"its magnitude is {norm:.4g}, so this decrease would leave {new:.4g}, below zero; "
            "decrease by at most the magnitude, or set it to 0"
        )
    if norm == 0.0 and new == 0.0:
        return list(vec)
    if norm == 0.0:
        raise FieldError("it is zero, so it has no direction to scale along; give [x, y, z] or a component")
    return [x * new / norm for x in vec]


def _relative(q: Quantity, comp: int | None, sign: float, amount: float | list[float], kind: str, what: str):
    """The update function for 'increase/decrease by amount'."""
    if kind == "percent":
        if 1.0 + sign * amount / 100.0 < 0:  # "increase by -150%" flipped it too (4.3 -> -2.15) and said nothing
            change = "a decrease" if sign < 0 else "an increase"
            raise EditError(f"{what}: {change} of {amount:g}% would flip the sign; use 'reverse' or 'set'")
        return _scale(q, 1.0 + sign * amount / 100.0)
    if isinstance(amount, list):
        raise EditError(f"{what}: increase/decrease takes N% or N UNIT, not a vector; use 'set ... to [x, y, z]'")
    if q.log_rate:
        if kind == "rate":
            return lambda d: _log_rate(10.0**d + sign * amount)
        return lambda d: d + sign * amount
    if q.dims == 3 and comp is None:
        return lambda v: _magnitude(v, math.sqrt(sum(x * x for x in v)) + sign * amount)
    return lambda x: _require(x) + sign * amount


def _require(x: float | None) -> float:
    if x is None:
        raise FieldError("it is not set, so it can't be changed relatively; use 'set ... to N'")
    return x


def _log_rate(rate: float) -> float:
    if rate <= 0:
        raise FieldError(f"damping is log10 of a decay rate, so the rate must stay > 0 (got {rate:g} /s)")
    return math.log10(rate)


def _scale(q: Quantity, factor: float):
    if q.log_rate:
        return lambda d: _log_rate(10.0**d * factor)
    return lambda x: [v * factor for v in x] if isinstance(x, list) else _require(x) * factor


def _absolute(q: Quantity, comp: int | None, value: float | list[float], kind: str, what: str):
    if kind == "percent":
        raise EditError(f"{what}: 'set' takes a value, not a percentage; use 'increase/decrease ... by N%'")
    if comp is not None and isinstance(value, list):  # the validation named a list in one component
        raise EditError(f"{what}: one component takes one number, not {value}; [x, y, z] sets the whole {q.key}")
    if q.log_rate:
        return (lambda _: _log_rate(value)) if kind == "rate" else (lambda _: value)
    if q.dims == 3 and comp is None and not isinstance(value, list):
        return lambda v: _magnitude(v, value, setting=True)
    return lambda _: list(value) if isinstance(value, list) else value


_ITEM_WORDS = {"camera": r"(?:the )?camera", "gravity": r"(?:the )?(?:scene|world)"}  # targets naming the item


def _quantity_of(
    q_text: str, t_text: str | None, previous: list[int] | str | None = None
) -> tuple[Quantity, int | None]:
    """The quantity (and component) a clause names: one of the camera's fields where its target is the camera, or
    where 'its' follows a clause that edited the camera ("move the camera 1 m back and set its height to 4")."""
    if t_text is not None and re.fullmatch(_ITEM_WORDS["camera"], t_text):
        return camera_quantity(q_text)
    if t_text is None and isinstance(previous, str) and (its := re.match(r"its ", q_text)):
        try:
            return camera_quantity(q_text)
        except EditError:  # "move the camera 1 m back and double its mass"
            raise EditError(
                f"{its.group(0).strip()!r} follows {previous!r}, which edited the camera, and the camera has no "
                f"{q_text[its.end() :]!r} (its fields are {CAMERA_FIELDS}); name the object"
            ) from None
    return quantity(q_text)


def _camera_pronoun(t_text: str, previous: list[int] | str | None) -> str:
    """'it' after a clause that edited the camera is the camera ("set the fov to 60 and move it 1 m back")."""
    return "the camera" if isinstance(previous, str) and re.fullmatch(r"it|them", t_text) else t_text


# "put box_0 at [1, 2, 0.4]", "place the cylinder at [...]": a move to there ("put a ball at [1, 2]" adds one)
_PUT_AT = rf"(?:put|place) (?!(?:{COUNT})(?: (?:more|new|other))? (?:{KIND_WORDS})\b)(?P<t>.+?) (?:at|to) (?P<a>\[.*\])"
_DIRS = "|".join(sorted(DIRECTIONS, key=len, reverse=True))
# "move box_0 0.5 m left", "shift the camera to the right by 1 m"
_MOVE_BY = rf"{MOVE_VERBS} (?P<t>.+?) (?:by )?(?P<n>{NUM} ?[a-z]*) (?:to the )?(?P<d>{_DIRS})"
_MOVE_TOWARD = rf"{MOVE_VERBS} (?P<t>.+?) (?:to the )?(?P<d>{_DIRS}) by (?P<n>{NUM} ?[a-z]*)"


def _clause(
    clause: str, items: list[dict], previous: list[int] | str | None = None, raw: str = ""
) -> list[int] | str | None:
    """Apply one clause to the items (in place); the objects it edited or added, which 'it', 'its', 'them' and
    'their' in the next clause refer to (`previous`: the last clause's). A clause that edited the gravity passes
    `previous` on; one that edited the camera gives its own text, which a pronoun after it is refused with. `raw`: the
    instruction as typed (the clauses are lower-cased), where an added object's name keeps its case."""
    c, q_text, one_point = clause, "", False  # one_point: the clause puts its objects at one place
    scene = object_view(items)  # names and types as the clauses before left them (added objects included)
    if m := re.fullmatch(rf"(?:set|change) (?:the )?gravity to {PLANET}(?: gravity)?", c) or re.fullmatch(
        rf"(?:use |switch to |apply )?{PLANET} gravity", c
    ):
        q, comp, t_text = BY_KEY["gravity"], None, None
        g = PLANET_GRAVITY[PLANET_NAMES[m.group(1)]]
        along = _absolute(q, None, g, "abs", clause)  # the magnitude, along gravity's direction
        fn = lambda v: along(v) if any(v) else [0.0, 0.0, -g]  # noqa: E731  none ("turn off gravity then ..."): down
    elif re.fullmatch(NO_GRAVITY, c):  # "turn off gravity": weightless (the zero vector)
        if re.match(r"make (?:it|them) ", c) and isinstance(previous, list) and previous:
            names = [scene.names[i] for i in previous]  # "add a ball at [1, 2] and make it weightless"
            raise EditError(
                f"{clause!r}: 'it' is {names}, but gravity is the whole scene's: an object cannot be made weightless "
                "alone; say 'turn off gravity' to make every object weightless"
            )
        q, comp, t_text = BY_KEY["gravity"], None, None
        fn = _absolute(q, None, [0.0, 0.0, 0.0], "abs", clause)
    elif m := re.fullmatch(rf"(?P<v>raise|lower) (?:the )?camera (?:by )?(?P<n>{NUM} ?[a-z]*)", c):
        q, comp, t_text = CAMERA_POSITION, 2, None  # "raise the camera by 1 m": its height
        amount, _ = read_value(m.group("n"), q)
        fn = _relative(q, comp, 1.0 if m.group("v") == "raise" else -1.0, amount, "abs", clause)
    elif m := re.fullmatch(rf"tilt (?:the )?camera (?P<d>up|down) (?:by )?(?P<n>{NUM} ?[a-z]*)", c):
        q, comp, t_text = BY_KEY["tilt"], None, None  # "tilt the camera up by 10 degrees": from straight down
        amount, _ = read_value(m.group("n"), q)
        fn = _relative(q, comp, 1.0 if m.group("d") == "up" else -1.0, amount, "abs", clause)
    elif m := re.fullmatch(REPLACE_CLAUSE, c):  # before 'set|change ... to': "change box_0 to a sphere"
        t, n, k, rest = m.group("t", "n", "k", "rest")
        return replace_objects(t, n, k, rest, items, scene, clause, previous, raw)
    elif m := re.fullmatch(rf"(?P<v>{VERBS_BY}) (?:the )?(?P<s>.+?) by a factor of (?P<k>{FACTOR})", c):
        q_text, t_text = subject(m.group("s"))
        q, comp = _quantity_of(q_text, t_text, previous)
        k = read_factor(m.group("k"), clause)
        up = m.group("v") in UP
        if k < 1:  # "reduce the mass by a factor of 0.5" doubled it, "increase ... by a factor of 0.5" halved it
            raise EditError(
                f"{clause!r}: a factor of {k:g} < 1 would {'decrease' if up else 'increase'} it; "
                f"'{m.group('v')} ... by a factor of K' takes K >= 1 (or 'multiply ... by {k:g}')"
            )
        fn = _scale(q, k if up else 1.0 / k)
    elif m := re.fullmatch(rf"(?P<v>{VERBS_BY}) (?:the )?(?P<s>.+?) by (?P<a>.+)", c):
        q_text, t_text = subject(m.group("s"))
        q, comp = _quantity_of(q_text, t_text, previous)
        amount, kind = read_value(m.group("a"), q)
        sign = 1.0 if m.group("v") in UP else -1.0
        fn = _relative(q, comp, sign, amount, kind, clause)
    elif m := re.fullmatch(
        rf"make (?P<t>.+?) (?P<f>{TIMES}) as (?P<adj>{'|'.join(AS_WORDS)})(?: as (?:before|now|it is))?", c
    ):
        q, comp, t_text = quantity(AS_WORDS[m.group("adj")])[0], None, m.group("t")
        fn = _scale(q, read_times(m.group("f")))
    elif m := re.fullmatch(rf"make (?P<t>.+?) (?P<f>{TIMES}) (?P<adj>{'|'.join(ER_WORDS)})", c):
        # "3 times faster" is 3 times as fast; "3 times slower" / "twice lighter" divide by the factor, as
        # everyday English means them (a factor of 1 or less has no such reading)
        (q_text, sign), t_text = ER_WORDS[m.group("adj")], m.group("t")
        q, comp = _quantity_of(q_text, t_text, previous)
        k = read_times(m.group("f"))
        if k <= 1:
            raise EditError(
                f"{clause!r}: '{m.group('f')} {m.group('adj')}' needs a factor > 1 (e.g. 'twice {m.group('adj')}'); "
                f"for a factor of {k:g} say 'make ... {m.group('f')} as {AS_OF[q_text]}'"
            )
        fn = _scale(q, k if sign > 0 else 1.0 / k)
    elif m := re.fullmatch(rf"make (?P<t>.+?) (?P<adj>{'|'.join(ER_WORDS)}) by (?P<a>.+)", c):
        (q_text, sign), t_text = ER_WORDS[m.group("adj")], m.group("t")
        q, comp = _quantity_of(q_text, t_text, previous)
        amount, kind = read_value(m.group("a"), q)
        fn = _relative(q, comp, sign, amount, kind, clause)
    elif m := re.fullmatch(r"(?:set|change) (?:the )?(?P<s>.+?) (?:to|=) (?P<a>.+)", c):
        q_text, t_text = subject(m.group("s"))
        q, comp = _quantity_of(q_text, t_text, previous)
        positional = comp is None and (q.path == ("state", "position") or q is CAMERA_POSITION)
        if positional and (xy := re.fullmatch(rf"\[\s*({NUM})\s*,\s*({NUM})\s*\]", m.group("a"))):
            x, y = float(xy.group(1)), float(xy.group(2))  # "set the camera position to [0, -4]": its height kept
            fn, one_point = (lambda v: [x, y, v[2]]), q.key == "position"
        else:
            value, kind = read_value(m.group("a"), q)
            fn = _absolute(q, comp, value, kind, clause)
            one_point = q.key == "position" and isinstance(value, list)  # "set the position of ... to [x, y, z]"
    elif m := re.fullmatch(r"(?P<v>double|triple|quadruple|halve) (?:the )?(?P<s>.+)", c):
        q_text, t_text = subject(m.group("s"))
        q, comp = _quantity_of(q_text, t_text, previous)
        fn = _scale(q, FACTORS[m.group("v")])
    elif m := re.fullmatch(rf"(?:multiply|scale) (?:the )?(?P<s>.+?) by (?:a factor of )?(?P<k>{FACTOR})", c):
        q_text, t_text = subject(m.group("s"))
        q, comp = _quantity_of(q_text, t_text, previous)
        fn = _scale(q, read_factor(m.group("k"), clause, positive=False))
    elif m := re.fullmatch(r"(?:reverse|negate|flip) (?:the )?(?P<s>.+)", c):
        q_text, t_text = subject(m.group("s"))
        q, comp = _quantity_of(q_text, t_text, previous)
        if not q.signed:
            raise EditError(f"{clause!r}: only velocity, spin, position and gravity can be reversed, not {q.key}")
        fn = _scale(q, -1.0)
    elif m := re.fullmatch(rf"{MOVE_VERBS} (?P<t>.+?) to (?P<a>\[.*\])", c) or re.fullmatch(_PUT_AT, c):
        t_text, comp, one_point = _camera_pronoun(m.group("t"), previous), None, True
        q = _quantity_of("position", t_text)[0]  # an object's, or the camera's ("put the camera at [0, -4, 3]")
        if xy := re.fullmatch(rf"\[\s*({NUM})\s*,\s*({NUM})\s*\]", m.group("a")):  # "put box_0 at [1, 2]"
            x, y = float(xy.group(1)), float(xy.group(2))  # there on the floor plan, at its height
            fn = lambda v: [x, y, v[2]]  # noqa: E731
        else:
            if m.group("a").count(",") != 2:  # "[1]": read_value's "position takes [x, y, z]" hid [x, y]
                raise EditError(f"{clause!r}: a move takes [x, y] (its height kept) or [x, y, z], not {m.group('a')}")
            value, _ = read_value(m.group("a"), q)
            fn = _absolute(q, None, value, "abs", clause)
    elif (m := re.fullmatch(_MOVE_BY, c)) or (m := re.fullmatch(_MOVE_TOWARD, c)):
        t_text = _camera_pronoun(m.group("t"), previous)
        q = _quantity_of("position", t_text)[0]  # "move the camera 1 m back"
        comp, sign = DIRECTIONS[m.group("d")]
        amount, kind = read_value(m.group("n"), q)
        if kind != "abs":
            raise EditError(f"{clause!r}: a move takes a distance like '0.5 m', not {m.group('n')!r}")
        fn = _relative(q, comp, sign, amount, "abs", clause)
    elif m := re.fullmatch(r"(?:stop|freeze) (?P<t>.+)", c):
        idx = find_targets(m.group("t"), scene, previous, gone(items))
        check_not_removed(items, idx, clause)
        for i in idx:
            items[i]["state"]["linear_velocity"] = [0.0, 0.0, 0.0]
            items[i]["state"]["angular_velocity"] = [0.0, 0.0, 0.0]
        return idx
    elif m := re.fullmatch(REMOVE_CLAUSE, c):
        idx = find_targets(m.group("t"), scene, previous, gone(items))
        check_not_removed(items, idx, clause)
        for i in idx:
            items[i][REMOVED] = True
        return idx
    elif m := re.fullmatch(ADD_CLAUSE, c):
        return add_objects(m.group("n"), m.group("k"), m.group("rest"), items, scene, clause, previous, raw)
    elif re.match(r"tilt (?:the )?camera\b", c):  # "tilt the camera by 10 degrees": which way?
        raise EditError(
            f"{clause!r}: say which way, 'tilt the camera up|down by N degrees' (up from straight down), or set it: "
            "'set the camera's tilt to N degrees'"
        )
    elif re.match(r"(?:pan|yaw|rotate|swivel|turn|aim|point) (?:the )?camera\b", c):
        raise EditError(
            f"{clause!r}: the camera does not turn: it faces +y, its tilt the angle from straight down; move it "
            f"('move the camera 1 m left', 'put the camera at [x, y, z]') or tilt it up|down. Its fields are "
            f"{CAMERA_FIELDS}"
        )
    else:
        raise EditError(f"instruction {clause!r} not understood. {UNDERSTOOD}")
    if q.scope == "object" and t_text is not None and re.fullmatch(_ITEM_WORDS["camera"], t_text):
        raise EditError(f"{clause!r}: the camera has no {q.key}; its fields are {CAMERA_FIELDS}")  # "... as heavy"
    its = q.scope != "object" and t_text is None and re.match(r"(its|their) ", q_text)
    if its and isinstance(previous, list) and previous:  # "double the mass of box_0 and increase its tilt"
        owner = "camera" if q.scope == "camera" else "scene"  # (the camera's tilt was edited)
        raise EditError(
            f"{clause!r}: {q_text.split()[0]!r} is {[scene.names[i] for i in previous]}, but the {q.key} is "
            f"{'the camera' if owner == 'camera' else 'the whole scene'}'s; name it (e.g. 'the {q.key} of the {owner}')"
        )
    if q.scope != "object" and t_text is not None and re.fullmatch(_ITEM_WORDS[q.scope], t_text):
        t_text = None  # "the field of view of the camera", "the gravity of the scene" name the item itself
    owner = re.match(r"(its|their) ", q_text) if t_text is None and q.scope == "object" else None
    idx = (
        previous_targets(owner.group(1), previous, scene)
        if owner
        else find_targets(t_text, scene, previous, gone(items))
    )
    if one_point and q.scope == "object" and len(idx) > 1:  # they overlapped, left to the simulation to refuse
        names = [scene.names[i] for i in idx]
        raise EditError(f"{clause!r} puts {len(idx)} objects {names} at one place; move one object at a time")
    for item in _items_of(q, items, idx, scene, t_text is not None or owner is not None):
        before = copy.deepcopy(item) if q.key in SHAPE_KEYS else None
        _edit_field(item, q, comp, fn, repr(clause))
        if before is not None:  # "double the size of box_0": a resting box grew into the floor (overlapping start)
            item["state"]["position"] = pose_after(before, item, items)[0]
    return idx if q.scope == "object" else clause if q.scope == "camera" else previous


SHAPE_KEYS = ("size", "radius", "height")  # an object on the floor keeps resting on it when they change


def apply_instruction(scene: Scene, instruction: str) -> EditResult:
    """Apply an instruction of the edit language (see the module docstring) to a scene.

    Raises:
        EditError: the instruction is not understood (the message lists what is), or the edit makes the
            scene invalid (the message carries the validation problems).
    """
    require_scene(scene, "apply_instruction: scene")  # YAML text failed on "'str' ... has no attribute 'objects'"
    if not isinstance(instruction, str):  # bytes were called an "empty instruction"
        raise TypeError(f"apply_instruction: instruction is a {type(instruction).__name__}, not a str")
    if not instruction.strip():
        raise EditError(f"empty instruction. {UNDERSTOOD}")
    clauses = split_clauses(instruction, scene.names)
    if not clauses:  # ";" or "." was an edit that changed nothing (exit 0)
        raise EditError(f"empty instruction {instruction!r}: no clause in it. {UNDERSTOOD}")
    items = copy.deepcopy(to_items(scene))
    previous = None  # the objects the last clause edited ("its", "it", "their", "them"), or a camera clause
    for clause in clauses:
        previous = _clause(clause, items, previous, instruction)
    return finish(scene, [it for it in items if not it.get(REMOVED)], instruction)


def finish(scene: Scene, items: list[dict], instruction: str) -> EditResult:
    """Validate edited items into a scene; a scene that fails validation, or whose objects the edit made start
    inside each other or the floor (`check_start`), refuses the edit."""
    try:
        edited = from_items(items)
    except SceneError as e:
        problems = "; ".join(str(p) for p in e.problems)
        raise EditError(f"edit refused: {instruction!r} makes the scene invalid: {problems}") from None
    check_start(scene, edited, f"edit refused: {instruction!r}")
    return EditResult(edited, tuple(diff(scene, edited)))


OVERLAP_TOLERANCE = 1e-6  # m: an overlap the scene had, unchanged by the edit, may differ by float noise


def check_start(scene: Scene, edited: Scene, what: str) -> None:
    """Refuse an edited scene whose objects start inside each other or the floor (deeper than the simulation
    allows) where the scene's did not, or deeper than they did ('add a sphere at [x, y]' where a box stands, 'move
    box_0 0.5 m down'): the simulation refused it as an overlapping start, after the edit was written. Overlaps the
    scene had are kept as they were (the edit did not cause them); pairs are named by the objects' names, so an
    overlapping object replaced by one of another name is a new pair. 0.9 ms a scene."""
    from aynamics.simulate import MAX_START_OVERLAP, overlap_words, start_overlap_pairs

    after = start_overlap_pairs(edited)
    if not after:
        return
    before = start_overlap_pairs(scene)
    worse = {pair: depth for pair, depth in after.items() if depth > before.get(pair, 0.0) + OVERLAP_TOLERANCE}
    if not worse:
        return
    (a, b), depth = max(worse.items(), key=lambda p: p[1])
    was = f", {before[a, b]:.3g} m before" if (a, b) in before else ""
    raise EditError(
        f"{what} makes objects start inside each other or the floor: {overlap_words(a, b, depth)}{was} (more "
        f"than {MAX_START_OVERLAP} m), which the simulation refuses; place them apart"
    )
