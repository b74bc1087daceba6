"""Physics editing: change an inferred scene with a plain-English instruction and ask "what if".

A small deterministic instruction language covers the paper's edits and their kin; several clauses can be
joined with ";", "then" or "and", and "it", "its", "them", "their" name the objects of the clause before:

    reduce the x-velocity of box_0 by 80%        decrease gravity by 50%
    increase the y-velocity by 50%  (no object named: every object)
    set the mass of sphere_1 to 2 kg             double the friction of cylinder_0
    move box_0 0.5 m left                        reverse the z-velocity of the sphere
    stop box_0                                   set the velocity of box_0 to [1, 0, 0]
    make the box twice as heavy                  make sphere_1 slower by 1 m/s
    moon gravity                                 increase the mass by a factor of 3
    double the mass of box_0 and halve its friction
    make the sphere 3 times faster               remove box_0

Directions are world axes as the default camera sees them: "left" is -x, "right" +x, "forward"/"away" +y
(the camera looks along +y), "back"/"toward the camera" -y, "up" +z, "down" -z. A percentage or factor on a
vector without a component ("the velocity") scales the whole vector; an amount with a unit ("by 1 m/s") changes
its magnitude along its direction; on a component ("the x-velocity", "the z-gravity") it adds along that axis,
signs included: "increase the x-velocity by 1 m/s" takes -1 to 0 and "reduce the z-gravity by 2 m/s^2" takes -7
to -9 (stronger), where "by 50%" scales the component's size (-1 to -0.5: "reduce ... by 50%").
`damping` is log10 of a decay rate, so "double the damping" doubles the rate and "set the damping to 0.5 /s" sets
the rate (a plain number sets the log10 value).

    result = apply_instruction(scene, "reduce the x-velocity of box_0 by 80%")
    result.scene, result.changes   # the validated edited scene; every leaf that changed, every object removed

`aynamics edit SCENE.yaml "INSTRUCTION" [--out EDITED.yaml] [--render DIR] [--llm MODEL]` runs it; the optional
language-model editor lives in `aynamics.edit_llm`, rendering of the what-if in `aynamics.whatif`.
Instructions it cannot read raise `EditError` listing what it understands; an edit that makes the scene invalid
is refused with the validation error, and nothing is written.
"""

from __future__ import annotations

import copy
import math
import re
from dataclasses import dataclass
from typing import Any

from aynamics.scene import Environment, Scene, SceneError, from_items, require_scene, to_items

# --------------------------------------------------------------------------------------------
# Vocabulary
# --------------------------------------------------------------------------------------------
UNITS: dict[str, dict[str, float]] = {
    "length": {"m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0, "cm": 0.01, "mm": 0.001},
    "velocity": {"m/s": 1.0, "cm/s": 0.01, "km/h": 1 / 3.6},
    "angular": {"rad/s": 1.0, "deg/s": math.pi / 180, "rpm": 2 * math.pi / 60},
    "mass": {"kg": 1.0, "g": 0.001, "kilogram": 1.0, "kilograms": 1.0, "gram": 0.001, "grams": 0.001},
    "acceleration": {"m/s^2": 1.0, "m/s²": 1.0, "m/s2": 1.0},
    "angle": {"deg": 1.0, "degree": 1.0, "degrees": 1.0, "°": 1.0},
    "none": {},
}


@dataclass(frozen=True)
class Quantity:
    """An editable field: where it lives in a scene item and how edits act on it."""

    key: str  # canonical name, e.g. "linear_velocity"
    words: str  # regex alternatives that name it in an instruction
    scope: str  # "object" (per object item) or "gravity" / "camera" (the scene item of that type)
    path: tuple[str, ...]  # keys inside the item
    index: int | None = None  # element of a vector field (friction[0])
    dims: int = 1  # 3 for vectors
    unit: str = "none"
    signed: bool = False  # may be reversed
    log_rate: bool = False  # stored as log10 of a rate (damping)


QUANTITIES: tuple[Quantity, ...] = (  # longest phrases first: "angular velocity" before "velocity"
    Quantity(
        "angular_velocity",
        r"angular velocity|angular speed|rotational velocity|rotation speed|spin",
        "object",
        ("state", "angular_velocity"),
        dims=3,
        unit="angular",
        signed=True,
    ),
    Quantity(
        "linear_velocity",
        r"linear velocity|velocity|speed",
        "object",
        ("state", "linear_velocity"),
        dims=3,
        unit="velocity",
        signed=True,
    ),
    Quantity("position", r"position|location", "object", ("state", "position"), dims=3, unit="length", signed=True),
    Quantity("rolling_resistance", r"rolling resistance|rolling friction", "object", ("physics", "friction"), 1),
    Quantity("friction", r"sliding friction|friction coefficient|friction", "object", ("physics", "friction"), 0),
    Quantity("mass", r"mass|weight", "object", ("physics", "mass"), unit="mass"),
    Quantity("damping", r"damping", "object", ("physics", "damping"), log_rate=True),
    Quantity("restitution", r"restitution|bounciness", "object", ("physics", "restitution")),
    Quantity("radius", r"radius", "object", ("radius",), unit="length"),
    Quantity("height", r"height", "object", ("height",), unit="length"),
    Quantity("size", r"size|half-extents", "object", ("size",), dims=3, unit="length"),
    Quantity(
        "gravity",
        r"gravity|gravitational acceleration",
        "gravity",
        ("gravity",),
        dims=3,
        unit="acceleration",
        signed=True,
    ),
    Quantity("fovy", r"field of view|fovy|fov", "camera", ("fovy",), unit="angle"),
)

_BY_KEY = {q.key: q for q in QUANTITIES}

DIRECTIONS: dict[str, tuple[int, float]] = {  # word -> (axis, sign); see the module docstring
    "left": (0, -1.0),
    "right": (0, 1.0),
    "forward": (1, 1.0),
    "forwards": (1, 1.0),
    "away": (1, 1.0),
    "away from the camera": (1, 1.0),
    "back": (1, -1.0),
    "backward": (1, -1.0),
    "backwards": (1, -1.0),
    "toward the camera": (1, -1.0),
    "towards the camera": (1, -1.0),
    "up": (2, 1.0),
    "upward": (2, 1.0),
    "upwards": (2, 1.0),
    "down": (2, -1.0),
    "downward": (2, -1.0),
    "downwards": (2, -1.0),
}

UNDERSTOOD = (
    "I understand (clauses joined by ';', 'then' or 'and'; 'it', 'its', 'them', 'their' name the objects of the "
    "clause before): "
    "'increase|raise|decrease|reduce|lower QUANTITY [of TARGETS] by N% | by N UNIT'; "
    "'set|change QUANTITY [of TARGETS] to N [UNIT] | to [x, y, z]'; "
    "'double|triple|halve QUANTITY [of TARGETS]'; 'multiply|scale QUANTITY [of TARGETS] by K'; "
    "'increase|decrease QUANTITY [of TARGETS] by a factor of K'; "
    "'make TARGETS twice|half|N times as heavy|fast|bouncy'; 'make TARGETS heavier|lighter|faster|slower|bouncier "
    "by N% | by N UNIT'; 'make TARGETS twice|N times heavier|lighter|faster|slower|bouncier'; "
    "'moon|mars|earth|jupiter gravity' or 'set the gravity to the moon's'; "
    "'reverse QUANTITY [of TARGETS]'; 'move TARGETS N m DIRECTION' (left -x, right +x, forward/away +y, "
    "back/toward the camera -y, up +z, down -z); 'move TARGETS to [x, y, z]'; 'stop TARGETS'; "
    "'remove|delete TARGETS'. "
    "QUANTITY: [x-|y-|z-]velocity, [x-|y-|z-]angular velocity (spin), [x-|y-|z-]position, mass, friction, "
    "rolling resistance, damping, restitution, radius, height, size, [x-|y-|z-]gravity, field of view. "
    "TARGETS: object names (box_0, sphere_1 and cylinder_0), 'the box', 'all spheres', 'all objects'; "
    "none named means every object"
)

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?"
_FACTORS = {"double": 2.0, "triple": 3.0, "quadruple": 4.0, "halve": 0.5}
_UP = ("increase", "raise", "boost")
_DOWN = ("decrease", "reduce", "lower", "cut")


class EditError(ValueError):
    """An instruction that can't be read, or an edit refused (the message says which and why)."""


class _FieldError(EditError):
    """A field's own value refuses the edit; `_edit_field` puts the clause and the field's path in front."""


@dataclass(frozen=True)
class Change:
    """One leaf of the scene that an edit changed. `path` uses object names: `box_0.state.position[0]`. An object
    the edit removed is one change: its name as the path, its type before, None after."""

    path: str
    before: Any
    after: Any

    @property
    def removed(self) -> bool:
        return self.after is None and "." not in self.path and self.before in ("box", "sphere", "cylinder")

    def __str__(self) -> str:
        if self.removed:
            return f"{self.path}: removed ({self.before})"
        return f"{self.path}: {self.before} -> {self.after}"


@dataclass(frozen=True)
class EditResult:
    """The validated edited scene and every leaf that changed."""

    scene: Scene
    changes: tuple[Change, ...]


# --------------------------------------------------------------------------------------------
# Reading an instruction
# --------------------------------------------------------------------------------------------
def _quantity(text: str) -> tuple[Quantity, int | None]:
    """The quantity a phrase names (`x-velocity`, `velocity along z`, `mass`) and its component or None."""
    text = re.sub(r"^(?:the|its|their)\s+", "", text.strip())
    for q in QUANTITIES:
        m = re.fullmatch(
            rf"(?:(?P<c1>[xyz])[- ]?|(?P<vert>vertical) )?(?:{q.words})"
            rf"(?: (?:in|along) (?:the )?(?P<c2>[xyz])(?:[- ]?(?:axis|direction))?)?",
            text,
        )
        if m:
            comp = m.group("c1") or m.group("c2") or ("z" if m.group("vert") else None)
            if comp is not None and q.dims != 3:
                raise EditError(f"{text!r}: {q.key} has no {comp} component")
            return q, None if comp is None else "xyz".index(comp)
    raise EditError(f"quantity {text!r} not understood. {UNDERSTOOD}")


def _targets(
    text: str | None, scene: Scene, previous: list[int] | str | None = None, gone: frozenset[int] = frozenset()
) -> list[int]:
    """Indices of the objects a target phrase names; None or 'all objects' means every object; 'it' / 'them' the
    objects of the clause before (`previous`), unless an object has that name ("stop it" stops an object named it).
    Every object and the objects of a kind ('all boxes', 'the box') leave out those an earlier clause removed
    (`gone`): "remove box_0 and double the mass of all objects" was refused as editing box_0."""
    lower = {n.lower(): i for i, n in enumerate(scene.names)}
    if text is not None and re.fullmatch(r"it|them", text) and text not in lower:
        return _previous(text, previous, scene)
    if text is None or re.fullmatch(r"(?:all|every|each)(?: (?:the )?objects?)?|everything|the objects", text):
        return [i for i in range(len(scene.objects)) if i not in gone]
    out: list[int] = []
    for part in re.split(r"\s*,\s*(?:and\s+)?|\s+and\s+", text.strip()):
        part = part.strip()
        bare = re.sub(r"^the ", "", part)  # "the crate" for an object named crate
        if part in lower or bare in lower:
            out.append(lower[part if part in lower else bare])
            continue
        m = re.fullmatch(r"(?:(all|every|each|the) )?(box|boxes|sphere|spheres|cylinder|cylinders)", part)
        if m is None:
            if _is_quantity(part):  # "double the mass of box_0 and the friction": a second quantity, not an object
                raise EditError(
                    f"{part!r} is a quantity, not an object of the scene {list(scene.names)}: one clause changes one "
                    f"quantity; repeat a verb before {part!r} (e.g. 'double the mass of {scene.names[0]} and halve "
                    "its friction')"
                )
            raise EditError(f"object {part!r} not found; the scene has {list(scene.names)}. {UNDERSTOOD}")
        kind = {"boxes": "box", "spheres": "sphere", "cylinders": "cylinder"}.get(m.group(2), m.group(2))
        idx = [i for i, o in enumerate(scene.objects) if o.type == kind and i not in gone]
        if not idx:
            left = [n for i, n in enumerate(scene.names) if i not in gone]
            raise EditError(f"{part!r}: the scene has no {kind}{' left' if gone else ''}; its objects are {left}")
        singular = m.group(2) == kind and m.group(1) in (None, "the")
        if singular and len(idx) > 1:
            names = [scene.names[i] for i in idx]
            plural = "boxes" if kind == "box" else f"{kind}s"  # it said "2 spherees"
            raise EditError(f"{part!r} is ambiguous: the scene has {len(idx)} {plural} {names}; name one")
        out.extend(idx)
    return sorted(set(out))


def _is_quantity(text: str) -> bool:
    try:
        _quantity(text)
    except EditError:
        return False
    return True


def _previous(word: str, previous: list[int] | str | None, scene: Scene) -> list[int]:
    """The objects an earlier clause named, for 'it', 'its', 'them', 'their' (alone they meant every object:
    "double the mass of box_0; halve its friction" halved every object's friction); in a scene of one object,
    before any clause named one, that object. After a clause that edited the camera (`previous` is its text) the
    word could mean the camera: "set the fov to 60 and move it 1 m back" moved the object."""
    if isinstance(previous, str):
        raise EditError(
            f"{word!r} follows {previous!r}, which edited the camera, so it could mean the camera; name the object "
            f"(e.g. {scene.names[0]})"
        )
    if previous is None and len(scene.objects) == 1:
        return [0]
    if previous is None:
        raise EditError(
            f"{word!r} refers to no object named before it in the instruction; name the object (e.g. {scene.names[0]})"
        )
    return previous


def _subject(text: str) -> tuple[str, str | None]:
    """Split 'x-velocity of box_0' / "box_0's x-velocity" into (quantity phrase, targets phrase or None). A
    quantity whose own name holds "of" ("field of view") is split at the first "of" / "for" after it."""
    m = re.fullmatch(r"(?:the )?(?P<t>[\w ,]+?)'s (?P<q>.+)", text)
    if m:
        return m.group("q"), m.group("t")
    splits = [(text[: m.start()], text[m.end() :]) for m in re.finditer(r" (?:of|for) ", text)]
    for q, t in splits:
        try:
            _quantity(q)
        except EditError:
            continue
        return q, t
    try:
        _quantity(text)
    except EditError:
        return splits[0] if splits else (text, None)  # its error names the quantity ("x-mass": no x component)
    return text, None


def _value(text: str, q: Quantity) -> tuple[float | list[float], str]:
    """Parse 'N [UNIT]' or '[x, y, z]' into SI numbers; returns (value, kind) with kind 'percent', 'abs', 'rate'."""
    text = text.strip()
    if text in ("half", "a half"):
        return 50.0, "percent"
    if text.startswith("["):
        parts = text.strip("[] ").split(",")
        try:
            vec = [float(p) for p in parts]
        except ValueError:
            raise EditError(f"value {text!r}: a vector must be [x, y, z] numbers") from None
        if len(vec) != 3 or q.dims != 3:
            raise EditError(f"value {text!r}: {q.key} takes {'[x, y, z]' if q.dims == 3 else 'one number'}")
        return vec, "abs"
    m = re.fullmatch(rf"(?P<n>{_NUM})\s*(?P<u>.*)", text)
    if m is None:
        raise EditError(f"value {text!r} not understood: expected a number, N%, or [x, y, z]. {UNDERSTOOD}")
    n, unit = float(m.group("n")), m.group("u").strip()
    if unit in ("%", "percent", "per cent"):
        return n, "percent"
    if q.log_rate and unit in ("/s", "1/s", "per second"):
        return n, "rate"
    table = UNITS[q.unit]
    if unit == "":
        return n, "abs"
    if unit not in table:
        allowed = ", ".join(table) if table else "no unit"
        raise EditError(f"unit {unit!r} does not fit {q.key}: allowed {allowed}")
    return n * table[unit], "abs"


# --------------------------------------------------------------------------------------------
# Applying
# --------------------------------------------------------------------------------------------
def _items_of(q: Quantity, items: list[dict], targets: list[int], scene: Scene, named: bool) -> list[dict]:
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
    if item.get(_REMOVED):
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
    except _FieldError as e:
        raise EditError(f"{label}: {field}: {e}") from None


def _magnitude(vec: list[float], new: float, setting: bool = False) -> list[float]:
    norm = math.sqrt(sum(x * x for x in vec))
    if new < 0 and setting:  # "set the gravity to -9.81" was called "this decrease would leave -9.81"
        raise _FieldError(
            f"a magnitude is >= 0, not {new:g}; to point it the other way give [x, y, z], set one component "
            "(x-, y- or z-) or 'reverse' it"
        )
    if new < 0:  # scaling by a negative length would turn the vector around, not shorten it
        raise _FieldError(
            f"its magnitude is {norm:.4g}, so this decrease would leave {new:.4g}, below zero; "
            "decrease by at most the magnitude, or set it to 0"
        )
    if norm == 0.0 and new == 0.0:
        return list(vec)
    if norm == 0.0:
        raise _FieldError("it is zero, so it has no direction to scale along; give [x, y, z] or a component")
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
        raise _FieldError("it is not set, so it can't be changed relatively; use 'set ... to N'")
    return x


def _log_rate(rate: float) -> float:
    if rate <= 0:
        raise _FieldError(f"damping is log10 of a decay rate, so the rate must stay > 0 (got {rate:g} /s)")
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


_VERBS_BY = "|".join((*_UP, *_DOWN))
# surface gravity, m/s² (NASA planetary fact sheets): "moon gravity", "set the gravity to mars"
PLANET_GRAVITY = {"earth": 9.81, "moon": 1.62, "mars": 3.71, "jupiter": 24.79}
_PLANET_NAMES = {name: name for name in PLANET_GRAVITY} | {"lunar": "moon", "martian": "mars"}
_PLANET = rf"(?:that of )?(?:the )?({'|'.join(_PLANET_NAMES)})(?:'s)?"
# "make box_0 twice as heavy": adjective -> quantity; "make box_0 heavier by 20%": comparative -> (quantity, sign)
_AS = {"heavy": "mass", "massive": "mass", "fast": "velocity", "quick": "velocity", "bouncy": "restitution"}
_ER = {
    "heavier": ("mass", 1.0),
    "lighter": ("mass", -1.0),
    "faster": ("velocity", 1.0),
    "slower": ("velocity", -1.0),
    "bouncier": ("restitution", 1.0),
}
_AS_OF = {"mass": "heavy", "velocity": "fast", "restitution": "bouncy"}  # the "as ADJ" word of a quantity
_TIMES_WORDS = {"twice": 2.0, "thrice": 3.0, "half": 0.5, "a third": 1 / 3, "a quarter": 0.25, "one third": 1 / 3}
_TIMES_WORDS |= {f"{w} times": k for w, k in (("two", 2.0), ("three", 3.0), ("four", 4.0), ("ten", 10.0))}
_TIMES = rf"{'|'.join(_TIMES_WORDS)}|{_NUM} times"
# "by a factor of three": the number words a factor is written with
_FACTOR_WORDS = {"two": 2.0, "three": 3.0, "four": 4.0, "five": 5.0, "ten": 10.0, "a hundred": 100.0}
_FACTOR = rf"{_NUM}|{'|'.join(_FACTOR_WORDS)}"


def _factor(text: str, clause: str, positive: bool = True) -> float:
    """The K of 'by a factor of K' or 'multiply ... by K' (a number or a number word): finite, and > 0 when
    `positive` ("multiply the x-velocity by -1" reverses it)."""
    k = _FACTOR_WORDS.get(text)
    if k is None:
        k = float(text)
    if not math.isfinite(k) or (positive and k <= 0):
        raise EditError(f"{clause!r}: a factor is a finite number{' > 0' if positive else ''}, not {text}")
    return k


def _times(text: str) -> float:
    """The factor of 'twice', 'half', 'three times', '2.5 times' (> 0)."""
    k = _TIMES_WORDS.get(text)
    if k is None:
        k = float(text.removesuffix(" times"))
    if not (0 < k < math.inf):
        raise EditError(f"{text!r}: a factor is a finite number > 0, not {k:g}")
    return k


_ITEM_WORDS = {"camera": r"(?:the )?camera", "gravity": r"(?:the )?(?:scene|world)"}  # targets naming the item
_MOVE = r"(?:move|shift|push|translate)"
_DIRS = "|".join(sorted(DIRECTIONS, key=len, reverse=True))


def _clause(
    clause: str, scene: Scene, items: list[dict], previous: list[int] | str | None = None
) -> list[int] | str | None:
    """Apply one clause to the items (in place); the objects it edited, which 'it', 'its', 'them' and 'their' in the
    next clause refer to (`previous`: the last clause's). A clause that edited the gravity passes `previous` on; one
    that edited the camera gives its own text, which a pronoun after it is refused with."""
    c, q_text = clause, ""
    if m := re.fullmatch(rf"(?:set|change) (?:the )?gravity to {_PLANET}(?: gravity)?", c) or re.fullmatch(
        rf"(?:use |switch to |apply )?{_PLANET} gravity", c
    ):
        q, comp, t_text = _BY_KEY["gravity"], None, None
        g = PLANET_GRAVITY[_PLANET_NAMES[m.group(1)]]
        fn = _absolute(q, None, g, "abs", clause)  # the magnitude, along gravity's direction
    elif m := re.fullmatch(rf"(?P<v>{_VERBS_BY}) (?:the )?(?P<s>.+?) by a factor of (?P<k>{_FACTOR})", c):
        q_text, t_text = _subject(m.group("s"))
        q, comp = _quantity(q_text)
        k = _factor(m.group("k"), clause)
        up = m.group("v") in _UP
        if k < 1:  # "reduce the mass by a factor of 0.5" doubled it, "increase ... by a factor of 0.5" halved it
            raise EditError(
                f"{clause!r}: a factor of {k:g} < 1 would {'decrease' if up else 'increase'} it; "
                f"'{m.group('v')} ... by a factor of K' takes K >= 1 (or 'multiply ... by {k:g}')"
            )
        fn = _scale(q, k if up else 1.0 / k)
    elif m := re.fullmatch(rf"(?P<v>{_VERBS_BY}) (?:the )?(?P<s>.+?) by (?P<a>.+)", c):
        q_text, t_text = _subject(m.group("s"))
        q, comp = _quantity(q_text)
        amount, kind = _value(m.group("a"), q)
        sign = 1.0 if m.group("v") in _UP else -1.0
        fn = _relative(q, comp, sign, amount, kind, clause)
    elif m := re.fullmatch(
        rf"make (?P<t>.+?) (?P<f>{_TIMES}) as (?P<adj>{'|'.join(_AS)})(?: as (?:before|now|it is))?", c
    ):
        q, comp, t_text = _quantity(_AS[m.group("adj")])[0], None, m.group("t")
        fn = _scale(q, _times(m.group("f")))
    elif m := re.fullmatch(rf"make (?P<t>.+?) (?P<f>{_TIMES}) (?P<adj>{'|'.join(_ER)})", c):
        # "3 times faster" is 3 times as fast; "3 times slower" / "twice lighter" divide by the factor, as
        # everyday English means them (a factor of 1 or less has no such reading)
        (q_text, sign), t_text = _ER[m.group("adj")], m.group("t")
        q, comp = _quantity(q_text)
        k = _times(m.group("f"))
        if k <= 1:
            raise EditError(
                f"{clause!r}: '{m.group('f')} {m.group('adj')}' needs a factor > 1 (e.g. 'twice {m.group('adj')}'); "
                f"for a factor of {k:g} say 'make ... {m.group('f')} as {_AS_OF[q_text]}'"
            )
        fn = _scale(q, k if sign > 0 else 1.0 / k)
    elif m := re.fullmatch(rf"make (?P<t>.+?) (?P<adj>{'|'.join(_ER)}) by (?P<a>.+)", c):
        (q_text, sign), t_text = _ER[m.group("adj")], m.group("t")
        q, comp = _quantity(q_text)
        amount, kind = _value(m.group("a"), q)
        fn = _relative(q, comp, sign, amount, kind, clause)
    elif m := re.fullmatch(r"(?:set|change) (?:the )?(?P<s>.+?) (?:to|=) (?P<a>.+)", c):
        q_text, t_text = _subject(m.group("s"))
        q, comp = _quantity(q_text)
        value, kind = _value(m.group("a"), q)
        fn = _absolute(q, comp, value, kind, clause)
    elif m := re.fullmatch(r"(?P<v>double|triple|quadruple|halve) (?:the )?(?P<s>.+)", c):
        q_text, t_text = _subject(m.group("s"))
        q, comp = _quantity(q_text)
        fn = _scale(q, _FACTORS[m.group("v")])
    elif m := re.fullmatch(rf"(?:multiply|scale) (?:the )?(?P<s>.+?) by (?:a factor of )?(?P<k>{_FACTOR})", c):
        q_text, t_text = _subject(m.group("s"))
        q, comp = _quantity(q_text)
        fn = _scale(q, _factor(m.group("k"), clause, positive=False))
    elif m := re.fullmatch(r"(?:reverse|negate|flip) (?:the )?(?P<s>.+)", c):
        q_text, t_text = _subject(m.group("s"))
        q, comp = _quantity(q_text)
        if not q.signed:
            raise EditError(f"{clause!r}: only velocity, spin, position and gravity can be reversed, not {q.key}")
        fn = _scale(q, -1.0)
    elif m := re.fullmatch(rf"{_MOVE} (?P<t>.+?) to (?P<a>\[.*\])", c):
        q, comp, t_text = QUANTITIES[2], None, m.group("t")
        value, _ = _value(m.group("a"), q)
        fn = _absolute(q, None, value, "abs", clause)
    elif (m := re.fullmatch(rf"{_MOVE} (?P<t>.+?) (?:by )?(?P<n>{_NUM} ?[a-z]*) (?:to the )?(?P<d>{_DIRS})", c)) or (
        m := re.fullmatch(rf"{_MOVE} (?P<t>.+?) (?:to the )?(?P<d>{_DIRS}) by (?P<n>{_NUM} ?[a-z]*)", c)
    ):
        q, t_text = QUANTITIES[2], m.group("t")
        comp, sign = DIRECTIONS[m.group("d")]
        amount, kind = _value(m.group("n"), q)
        if kind != "abs":
            raise EditError(f"{clause!r}: a move takes a distance like '0.5 m', not {m.group('n')!r}")
        fn = _relative(q, comp, sign, amount, "abs", clause)
    elif m := re.fullmatch(r"(?:stop|freeze) (?P<t>.+)", c):
        idx = _targets(m.group("t"), scene, previous, _gone(items))
        _not_removed(items, idx, clause)
        for i in idx:
            items[i]["state"]["linear_velocity"] = [0.0, 0.0, 0.0]
            items[i]["state"]["angular_velocity"] = [0.0, 0.0, 0.0]
        return idx
    elif m := re.fullmatch(_REMOVE, c):
        idx = _targets(m.group("t"), scene, previous, _gone(items))
        _not_removed(items, idx, clause)
        for i in idx:
            items[i][_REMOVED] = True
        return idx
    else:
        raise EditError(f"instruction {clause!r} not understood. {UNDERSTOOD}")
    if q.scope != "object" and t_text is not None and re.fullmatch(_ITEM_WORDS[q.scope], t_text):
        t_text = None  # "the field of view of the camera", "the gravity of the scene" name the item itself
    owner = re.match(r"(its|their) ", q_text) if t_text is None and q.scope == "object" else None
    idx = _previous(owner.group(1), previous, scene) if owner else _targets(t_text, scene, previous, _gone(items))
    for item in _items_of(q, items, idx, scene, t_text is not None or owner is not None):
        _edit_field(item, q, comp, fn, repr(clause))
    return idx if q.scope == "object" else clause if q.scope == "camera" else previous


_REMOVED = "__removed__"  # marks an object item a clause removed; `apply_instruction` drops it at the end
_REMOVE = r"(?:remove|delete|take away|take out) (?P<t>.+?)(?: from the scene)?"  # a removal clause


def _gone(items: list[dict]) -> frozenset[int]:
    return frozenset(i for i, item in enumerate(items) if item.get(_REMOVED))


def _not_removed(items: list[dict], idx: list[int], clause: str) -> None:
    for i in idx:
        if items[i].get(_REMOVED):
            raise EditError(f"{clause!r}: {items[i]['name']} was removed by an earlier clause")


# the words a clause starts with: "and" before one of them joins two clauses ("double the mass of box_0 and halve its
# friction"); elsewhere it joins objects ("box_0 and sphere_1")
_CLAUSE_START = (
    rf"(?:{_VERBS_BY}|set|change|double|triple|quadruple|halve|multiply|scale|reverse|negate|flip|stop|freeze|make|"
    rf"use|switch to|apply|remove|delete|take away|take out|{_MOVE})\b"
)


def _normalise(instruction: str, names: tuple[str, ...] = ()) -> list[str]:
    """The clauses of an instruction, lower-cased; "and" before an object's name joins objects even where the name is
    a clause verb ("stop box_0 and scale" for an object named scale was refused as the clause "scale")."""
    text = " ".join(instruction.strip().split()).rstrip(".!").lower()
    text = text.replace("per cent", "percent")
    not_name = rf"(?!(?:{'|'.join(re.escape(n.lower()) for n in names)})\b)" if names else ""
    clauses = [c.strip(" ,") for c in re.split(rf";|,? then |,? and then |,? and {not_name}(?={_CLAUSE_START})", text)]
    return [re.sub(r"^(?:please|now) ", "", c) for c in clauses if c.strip(" ,")]


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
    clauses = _normalise(instruction, scene.names)
    if not clauses:  # ";" or "." was an edit that changed nothing (exit 0)
        raise EditError(f"empty instruction {instruction!r}: no clause in it. {UNDERSTOOD}")
    items = copy.deepcopy(to_items(scene))
    previous = None  # the objects the last clause edited ("its", "it", "their", "them"), or a camera clause
    for clause in clauses:
        previous = _clause(clause, scene, items, previous)
    return finish(scene, [it for it in items if not it.get(_REMOVED)], instruction)


def finish(scene: Scene, items: list[dict], instruction: str) -> EditResult:
    """Validate edited items into a scene; a scene that fails validation refuses the edit."""
    try:
        edited = from_items(items)
    except SceneError as e:
        problems = "; ".join(str(p) for p in e.problems)
        raise EditError(f"edit refused: {instruction!r} makes the scene invalid: {problems}") from None
    return EditResult(edited, tuple(diff(scene, edited)))


# --------------------------------------------------------------------------------------------
# Comparing scenes
# --------------------------------------------------------------------------------------------
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
    """Every leaf that differs between two scenes of the same objects (paths use object names), and each object
    `after` leaves out (`Change(name, type, None)`, `Change.removed`). A scene without an environment item compares
    as one with the default item (no air, wind or tilt, time_scale 1), and an object without `magnus` or
    `friction_slope` as one with 0, as they simulate.

    Raises:
        EditError: `after` adds, renames, reorders or reshapes objects (an edit keeps the objects or removes some).
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
    kept = dict(zip(after.names, after.structure, strict=True))
    pairs = list(zip(before.names, before.structure, strict=True))
    if [p for p in pairs if p[0] in kept] != list(kept.items()):
        raise EditError(
            f"the edit changed the objects: {pairs} -> {list(kept.items())}; edits keep the objects (or remove some) "
            "and only change numbers"
        )
    gone = [(name, kind) for name, kind in pairs if name not in kept]
    out = [Change(name, before.object(name).type, None) for name, _ in gone]
    a, b = _flatten(before), _flatten(after)
    a = {k: v for k, v in a.items() if not k.startswith(tuple(f"{name}." for name, _ in gone))}
    for key in [*a, *(k for k in b if k not in a)]:
        va, vb = a.get(key), b.get(key)
        same = va == vb or (
            isinstance(va, float | int) and isinstance(vb, float | int) and abs(float(va) - float(vb)) <= tol
        )
        if not same:
            out.append(Change(key, va, vb))
    return out


# Words a free-form instruction uses for a quantity without naming it (for `named_fields` only: the deterministic
# language above names quantities)
DESCRIBED: tuple[tuple[str, tuple[str, ...]], ...] = (
    (r"heav(?:y|ier|iest)|light(?:er|est)?|weigh(?:s|t)?|massive", ("physics.mass",)),
    (r"fast(?:er|est)?|slow(?:er|est)?|quick(?:er|ly)?|rapid(?:ly)?", ("state.linear_velocity",)),
    (r"spin(?:s|ning)?|rotat(?:e|es|ing|ion)|roll(?:s|ing)?", ("state.angular_velocity",)),
    (r"bounc(?:e|es|y|ier|iest|ing)|elastic", ("physics.restitution",)),
    (r"slipp(?:ery|erier)|grip(?:py|pier)?|sticky|stickier|rough(?:er)?|smooth(?:er)?", ("physics.friction",)),
    (
        r"big(?:ger)?|large(?:r)?|small(?:er)?|tiny|tall(?:er)?|short(?:er)?|wide(?:r)?|grow|shrink",
        ("size", "radius", "height"),
    ),
)


# Words for the camera's fields once the camera is named ("rotate the camera", "move the camera back"); "zoom" names
# the field of view wherever it stands
CAMERA_WORDS: tuple[tuple[str, str], ...] = (
    (
        r"mov(?:e|es|ing)|shift|push|pull|translat\w*|rais(?:e|es|ing)|lower|higher|closer|further|farther|"
        r"position|location|place|put",
        "camera.position",
    ),
    (r"rotat\w*|tilt\w*|pitch\w*|turn\w*|angle\w*|orientation|look\w*|point\w*|aim\w*", "camera.orientation"),
)


def named_fields(instruction: str, scene: Scene) -> set[str]:
    """Path prefixes of the fields an instruction names (by the vocabulary above), for checking a free editor.

    Objects named in the text (or 'the box', 'all spheres') restrict the per-object fields; none named means
    every object, unless the camera is named ("rotate the camera": its fields, no object's; "toward the camera" is a
    direction, not the camera). A component named ('x-velocity') restricts a vector to that element. Moves name
    positions, 'stop' names both velocities; a removal clause ('remove box_0') names the object by its bare name,
    which allows its removal and none of its fields (`aynamics.edit_llm.check_output`).
    """
    require_scene(scene, "named_fields: scene")
    if not isinstance(instruction, str):  # None / bytes failed on "'NoneType' object has no attribute 'lower'"
        raise TypeError(f"named_fields: instruction is a {type(instruction).__name__}, not a str")
    text = " ".join(instruction.lower().split())
    lower = {n.lower(): n for n in scene.names}
    objs = [n for low, n in lower.items() if re.search(rf"(?<![\w]){re.escape(low)}(?![\w])", text)]
    for kind in ("box", "sphere", "cylinder"):
        if re.search(rf"\b{kind}(?:e?s)?\b", text):
            objs.extend(o.name for o in scene.objects if o.type == kind)
    # "rotate the camera" named every object's spin and "move the camera back" every position (a free editor that
    # spun the box passed the check, one that turned the camera was refused)
    camera = re.search(r"\bcamera\b", re.sub(r"\b(?:towards?|away from) the camera\b", " ", text)) is not None
    every = re.search(r"\b(?:all|every|each|everything|objects)\b", text) is not None
    objs = sorted(set(objs)) or ([] if camera and not every else list(scene.names))
    fields: set[str] = set()
    if re.search(r"\bzoom\w*", text):
        fields.add("camera.fovy")
    if camera:
        fields.update(path for words, path in CAMERA_WORDS if re.search(rf"\b(?:{words})\b", text))
        if any(re.search(rf"\b{re.escape(d)}\b", text) for d in DIRECTIONS):
            fields.add("camera.position")
    for q in QUANTITIES:
        for m in re.finditer(rf"(?:\b(?P<c>[xyz])[- ]?)?\b(?:{q.words})\b", text):
            text_q = m.group(0)
            comp = m.group("c")
            suffix = f"[{q.index}]" if q.index is not None else (f"[{'xyz'.index(comp)}]" if comp else "")
            field = ".".join(q.path) + suffix
            fields.update(f"{h}.{field}" for h in (objs if q.scope == "object" else [q.scope]))
            text = text.replace(text_q, " ")  # "angular velocity" must not also count as "velocity"
    for words, paths in DESCRIBED:
        if re.search(rf"\b(?:{words})\b", text):
            fields.update(f"{o}.{path}" for o in objs for path in paths)
    if re.search(r"\b(?:move|shift|push|translate)\b", text) or any(f" {d}" in text for d in DIRECTIONS):
        fields.update(f"{o}.state.position" for o in objs)
    if re.search(r"\b(?:stop|freeze)\b", text):
        fields.update(f"{o}.state.{k}" for o in objs for k in ("linear_velocity", "angular_velocity"))
    # a removal names each object of a removal clause by its bare name: its removal, none of its fields
    # (`check_output` keeps the two apart). "remove" anywhere named every field of every object the text named:
    # "double the mass of cylinder_0 and remove box_0" let a free editor move cylinder_0, "remove the spin of box_0"
    # delete box_0
    for clause in _normalise(instruction, scene.names):
        m = re.fullmatch(_REMOVE, clause)
        if m is None:
            continue
        if re.fullmatch(r"it|them", m.group("t")) and m.group("t") not in lower:
            fields.update(objs)  # "stop box_0 and remove it": the objects the text names
            continue
        try:
            fields.update(scene.names[i] for i in _targets(m.group("t"), scene))
        except EditError:  # "remove the spin of box_0" removes no object
            pass
    return fields


_PATHS = "set of str field paths (named_fields gives one)"


def outside(changes: list[Change] | tuple[Change, ...], allowed: set[str]) -> list[Change]:
    """The changes whose path does not start with one of the allowed prefixes.

    Raises:
        TypeError: `changes` is not a list of `Change`s, or `allowed` not a collection of str path prefixes (a str
            was read as its letters: every change was outside "box_0.mass", and "b.x" inside "box_0").
    """
    for name, value, want in (("changes", changes, "list of Changes (diff gives one)"), ("allowed", allowed, _PATHS)):
        if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
            raise TypeError(f"outside: {name} is a {type(value).__name__} {value!r:.60}: must be a {want}")
    changes, allowed = list(changes), tuple(allowed)  # a generator of paths was spent on the first change
    for k, c in enumerate(changes):
        if not isinstance(c, Change):
            raise TypeError(f"outside: changes[{k}] is a {type(c).__name__} {c!r:.60}: must be a Change")
    for a in allowed:
        if not isinstance(a, str):
            raise TypeError(f"outside: allowed holds a {type(a).__name__} {a!r:.60}: must be a {_PATHS}")
    return [c for c in changes if not any(c.path == a or c.path.startswith((a + ".", a + "[")) for a in allowed)]
