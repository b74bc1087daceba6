"""The words of the edit language (`aynamics.edit`): the quantities it edits and their units, directions,
verbs, factors, planets, and the reading of a quantity phrase, a value and a factor.

    quantity("x-velocity")            # (Quantity linear_velocity, 0)
    read_value("50 cm", BY_KEY["position"])   # (0.5, "abs")
    subject("mass of box_0")          # ("mass", "box_0")
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

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
    Quantity("tilt", r"tilt|pitch", "camera", ("orientation",), unit="angle"),  # degrees from straight down
)

BY_KEY = {q.key: q for q in QUANTITIES}

# the camera's fields, once a clause names the camera ("move the camera 1 m back", "set the camera height to 3 m",
# "set the orientation of the camera to 30"); "height" is its position's z
CAMERA_POSITION = Quantity(
    "camera position", r"position|location|place", "camera", ("position",), dims=3, unit="length", signed=True
)
CAMERA_QUANTITIES: tuple[Quantity, ...] = (
    CAMERA_POSITION,
    Quantity("tilt", r"tilt|pitch|orientation|angle", "camera", ("orientation",), unit="angle"),
    BY_KEY["fovy"],
)
CAMERA_FIELDS = (
    "position ([x, y, z], or its x-, y-, z-position), height, tilt (degrees from straight down), field of view"
)

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
    "clause before, or the camera after a clause that edited it): "
    "'increase|raise|decrease|reduce|lower QUANTITY [of TARGETS] by N% | by N UNIT'; "
    "'set|change QUANTITY [of TARGETS] to N [UNIT] | to [x, y, z]'; "
    "'double|triple|halve QUANTITY [of TARGETS]'; 'multiply|scale QUANTITY [of TARGETS] by K'; "
    "'increase|decrease QUANTITY [of TARGETS] by a factor of K'; "
    "'make TARGETS twice|half|N times as heavy|fast|bouncy'; 'make TARGETS heavier|lighter|faster|slower|bouncier "
    "by N% | by N UNIT'; 'make TARGETS twice|N times heavier|lighter|faster|slower|bouncier'; "
    "'moon|mars|earth|jupiter gravity' or 'set the gravity to the moon's'; 'turn off gravity' | 'zero gravity'; "
    "'reverse QUANTITY [of TARGETS]'; 'move TARGETS N m DIRECTION' (left -x, right +x, forward/away +y, "
    "back/toward the camera -y, up +z, down -z); 'move TARGETS to [x, y(, z)]', 'put|place TARGETS at [x, y(, z)]'; "
    "'stop TARGETS'; "
    "'remove|delete TARGETS'; 'add|put|place|drop a|another box|cube|sphere|ball|cylinder at [x, y] | at [x, y, z] "
    "[named NAME] [like OBJECT] [moving at [vx, vy, vz]] [of radius|height R] [of size [a, b, c]] [of mass M kg]'; "
    "'add two|3 spheres|boxes|... at [x, y] and [x, y]' (one position each); 'replace|swap|turn TARGETS "
    "with|for|into a sphere|box|... [named NAME] [like OBJECT] [of radius|height R] [of size [a, b, c]] "
    "[of mass M kg]' (its place, velocity and physics; several TARGETS: 'spheres'). "
    "QUANTITY: [x-|y-|z-]velocity, [x-|y-|z-]angular velocity (spin), [x-|y-|z-]position, mass, friction, "
    "rolling resistance, damping, restitution, radius, height, size, [x-|y-|z-]gravity, field of view, tilt; "
    "of the camera ('move the camera 1 m back', 'set the camera height to 3 m', 'raise|lower the camera by N m', "
    "'tilt the camera up|down by N degrees'): "
    f"{CAMERA_FIELDS}. "
    "TARGETS: object names (box_0, sphere_1 and cylinder_0), 'the box', 'all spheres', 'all objects'; "
    "none named means every object"
)

NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?"
FACTORS = {"double": 2.0, "triple": 3.0, "quadruple": 4.0, "halve": 0.5}
UP = ("increase", "raise", "boost")
DOWN = ("decrease", "reduce", "lower", "cut")


class EditError(ValueError):
    """An instruction that can't be read, or an edit refused (the message says which and why)."""


class FieldError(EditError):
    """A field's own value refuses the edit; `aynamics.edit` puts the clause and the field's path in front."""


def quantity(text: str, among: tuple[Quantity, ...] = QUANTITIES) -> tuple[Quantity, int | None]:
    """The quantity a phrase names (`x-velocity`, `velocity along z`, `mass`) and its component or None."""
    text = re.sub(r"^(?:the|its|their)\s+", "", text.strip())
    for q in among:
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


def camera_quantity(text: str) -> tuple[Quantity, int | None]:
    """The camera's field a phrase names once the clause named the camera ('position', 'x-position', 'height',
    'tilt', 'field of view') and its component or None; a field the camera lacks ('mass') is named in the error."""
    if re.fullmatch(r"(?:the |its )?(?:height|elevation)", text.strip()):
        return CAMERA_POSITION, 2
    try:
        return quantity(text, CAMERA_QUANTITIES)
    except EditError:
        raise EditError(f"the camera has no {text.strip()!r}: its fields are {CAMERA_FIELDS}") from None


def is_quantity(text: str) -> bool:
    try:
        quantity(text)
    except EditError:
        return False
    return True


def subject(text: str) -> tuple[str, str | None]:
    """Split 'x-velocity of box_0' / "box_0's x-velocity" into (quantity phrase, targets phrase or None). A
    quantity whose own name holds "of" ("field of view") is split at the first "of" / "for" after it."""
    m = re.fullmatch(r"(?:the )?(?P<t>[\w ,]+?)'s (?P<q>.+)", text)
    if m:
        return m.group("q"), m.group("t")
    if m := re.fullmatch(r"(?:the )?camera (?P<q>.+)", text):  # "the camera height", "camera position"
        return m.group("q"), "the camera"
    splits = [(text[: m.start()], text[m.end() :]) for m in re.finditer(r" (?:of|for) ", text)]
    for q, t in splits:
        try:
            quantity(q)
        except EditError:
            continue
        return q, t
    try:
        quantity(text)
    except EditError:
        return splits[0] if splits else (text, None)  # its error names the quantity ("x-mass": no x component)
    return text, None


def read_value(text: str, q: Quantity) -> tuple[float | list[float], str]:
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
    m = re.fullmatch(rf"(?P<n>{NUM})\s*(?P<u>.*)", text)
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


VERBS_BY = "|".join((*UP, *DOWN))

# surface gravity, m/s² (NASA planetary fact sheets): "moon gravity", "set the gravity to mars"
PLANET_GRAVITY = {"earth": 9.81, "moon": 1.62, "mars": 3.71, "jupiter": 24.79}
PLANET_NAMES = {name: name for name in PLANET_GRAVITY} | {"lunar": "moon", "martian": "mars"}
PLANET = rf"(?:that of )?(?:the )?({'|'.join(PLANET_NAMES)})(?:'s)?"


# "make box_0 twice as heavy": adjective -> quantity; "make box_0 heavier by 20%": comparative -> (quantity, sign)
AS_WORDS = {"heavy": "mass", "massive": "mass", "fast": "velocity", "quick": "velocity", "bouncy": "restitution"}
ER_WORDS = {
    "heavier": ("mass", 1.0),
    "lighter": ("mass", -1.0),
    "faster": ("velocity", 1.0),
    "slower": ("velocity", -1.0),
    "bouncier": ("restitution", 1.0),
}
AS_OF = {"mass": "heavy", "velocity": "fast", "restitution": "bouncy"}  # the "as ADJ" word of a quantity

TIMES_WORDS = {"twice": 2.0, "thrice": 3.0, "half": 0.5, "a third": 1 / 3, "a quarter": 0.25, "one third": 1 / 3}
TIMES_WORDS |= {f"{w} times": k for w, k in (("two", 2.0), ("three", 3.0), ("four", 4.0), ("ten", 10.0))}
TIMES = rf"{'|'.join(TIMES_WORDS)}|{NUM} times"


# "by a factor of three": the number words a factor is written with
FACTOR_WORDS = {"two": 2.0, "three": 3.0, "four": 4.0, "five": 5.0, "ten": 10.0, "a hundred": 100.0}
FACTOR = rf"{NUM}|{'|'.join(FACTOR_WORDS)}"


def read_factor(text: str, clause: str, positive: bool = True) -> float:
    """The K of 'by a factor of K' or 'multiply ... by K' (a number or a number word): finite, and > 0 when
    `positive` ("multiply the x-velocity by -1" reverses it)."""
    k = FACTOR_WORDS.get(text)
    if k is None:
        k = float(text)
    if not math.isfinite(k) or (positive and k <= 0):
        raise EditError(f"{clause!r}: a factor is a finite number{' > 0' if positive else ''}, not {text}")
    return k


def read_times(text: str) -> float:
    """The factor of 'twice', 'half', 'three times', '2.5 times' (> 0)."""
    k = TIMES_WORDS.get(text)
    if k is None:
        k = float(text.removesuffix(" times"))
    if not (0 < k < math.inf):
        raise EditError(f"{text!r}: a factor is a finite number > 0, not {k:g}")
    return k
