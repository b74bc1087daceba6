"""The scene language: YAML text <-> validated `Scene` <-> canonical YAML.

A scene is a YAML list of items, as written by the model (the ΔYNAMICS format):

    - type: box | sphere | cylinder   # objects, any number (at least one)
    - type: camera                    # exactly one
    - type: gravity                   # optional, default [0, 0, -9.81]
    - type: environment               # optional extension item (air, wind, floor), absent in the paper

Meaning of every field (units, frames) and its plausible range live in one table, `RANGES`,
which validation uses here, the dataset sampler and CMA-ES bounds use later, and the README
reproduces (`aynamics ranges --markdown`).

    scene = parse(text)        # plain YAML, or model output with <think>/<answer> and stray text
    text = dump(scene)         # canonical: fixed key order, fixed decimals; parse(dump(s)) == s

Every problem in a text is reported at once in one `SceneError`, each as
`objects[1].physics.mass = -2.0: must be > 0`.
"""

from __future__ import annotations

import math
import numbers
import os
import re
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, ValidationError
from pydantic_core import PydanticCustomError

DECIMALS = 4  # canonical precision of every number: 0.1 mm, 0.1 mrad, 0.1 g
MAX_TEXT_CHARS = 200_000  # a scene is a few kB; longer text is refused before parsing
MAX_OBJECTS = 32


# --------------------------------------------------------------------------------------------
# The range table
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Range:
    """Plausible range of one scene field (per component for vectors)."""

    lo: float | tuple[float, ...]
    hi: float | tuple[float, ...]
    unit: str
    frame: str
    meaning: str
    default: Any = None  # value used when the field is absent (optional fields only)

    def bounds(self, n: int = 1) -> tuple[list[float], list[float]]:
        """Lower and upper bounds as lists of length n (scalars broadcast)."""
        lo = list(self.lo) if isinstance(self.lo, tuple) else [self.lo] * n
        hi = list(self.hi) if isinstance(self.hi, tuple) else [self.hi] * n
        return lo, hi


RANGES: dict[str, Range] = {
    "box.size": Range(0.05, 2.0, "m", "body", "half-extents along the box's own x, y, z axes (MuJoCo's convention)"),
    "sphere.radius": Range(0.05, 1.5, "m", "-", "radius"),
    "cylinder.radius": Range(0.05, 1.5, "m", "-", "radius of the circular faces"),
    "cylinder.height": Range(
        0.05, 3.0, "m", "body", "FULL length along the cylinder's own z axis (MuJoCo half-length ×2)"
    ),
    "state.position": Range(
        (-10.0, -10.0, -0.5), (10.0, 10.0, 10.0), "m", "world, z up", "centre of the object (of its bounding box)"
    ),
    "state.orientation": Range(
        -1.0,
        1.0,
        "-",
        "body→world",
        "quaternion [w, x, y, z], w first; normalised like MuJoCo's compiler (norm must be ≥ 0.1)",
    ),
    "state.linear_velocity": Range(-20.0, 20.0, "m/s", "world", "initial velocity of the centre"),
    "state.angular_velocity": Range(-50.0, 50.0, "rad/s", "world", "initial spin, world axes"),
    "physics.mass": Range(0.01, 100.0, "kg", "-", "mass; inertia is that of a uniform solid of the shape"),
    "physics.friction": Range(
        (0.0, 0.0),
        (2.0, 1.0),
        "-",
        "-",
        "[sliding μ, rolling-resistance coefficient c_rr]: Coulomb friction against floor and objects, and a "
        "rolling-resistance torque of at most c_rr·r·N (less when c_rr > μ/2: one friction cone) that slows rolling "
        "and tumbling (r: sphere/cylinder radius, box smallest half-extent). The object's values are used against the "
        "floor; two objects use the larger of each",
    ),
    "physics.damping": Range(
        -8.0,
        2.0,
        "log10(1/s)",
        "-",
        "log10 of the linear damping rate k: in free motion v and ω decay as exp(-k·t) (k = 10^damping); -4 → 1e-4/s",
    ),
    "physics.restitution": Range(
        0.0,
        0.95,
        "-",
        "-",
        "optional: normal bounce coefficient, off the floor and objects alike (rebound 0.50-0.60 at e = 0.5, above e "
        "at low e: it varies with the impact's phase in the physics step); two objects take the less bouncy one's (an "
        "object without one: the other's); absent: MuJoCo's soft contact (rebound 0.09-0.15)",
    ),
    "physics.magnus": Range(
        -0.05,
        0.05,
        "kg",
        "world",
        "optional: spin lift (Magnus) F = k·ω×v on the object in flight and on the floor (absent: none)",
    ),
    "physics.friction_slope": Range(
        -0.5,
        1.0,
        "s/m",
        "-",
        "optional: speed-dependent sliding friction μ(v) = max(μ + κ·v_h, 0), v_h the horizontal speed (absent: 0)",
    ),
    "camera.position": Range((-20.0, -20.0, 0.1), (20.0, 20.0, 20.0), "m", "world", "optical centre"),
    "camera.orientation": Range(
        0.0,
        89.0,
        "deg",
        "world",
        "pitch: angle between the optical axis and straight down; the camera looks along +y tilted down "
        "(0 = looking straight down, 90 = horizontal). MuJoCo euler='θ 0 0'",
    ),
    "camera.fovy": Range(10.0, 120.0, "deg", "-", "vertical field of view"),
    "gravity.gravity": Range(-30.0, 30.0, "m/s²", "world", "gravitational acceleration vector", (0.0, 0.0, -9.81)),
    "environment.air_density": Range(
        0.0,
        5.0,
        "kg/m³",
        "-",
        "optional: quadratic air drag on every object, MuJoCo's inertia-box fluid model: ½ρA_i·v_i² against each "
        "velocity component v_i along the axes of the object's equivalent-inertia box (A_i its face: a box's own; a "
        "sphere 2.4r² along its axes, 1.39r² along a body diagonal), and a torque on spin",
        0.0,
    ),
    "environment.air_viscosity": Range(
        0.0,
        5.0,
        "Pa·s",
        "-",
        "optional: linear air drag on every object (MuJoCo <option viscosity>): -3πη·d·v, d the mean side of the "
        "equivalent-inertia box (a sphere: 0.775 of Stokes' 6πηrv), and a torque on spin",
        0.0,
    ),
    "environment.wind": Range(
        -20.0, 20.0, "m/s", "world", "optional: air velocity; acts through the drag terms only", (0.0, 0.0, 0.0)
    ),
    "environment.floor_offset": Range(-0.5, 0.5, "m", "world", "optional: height of the floor plane", 0.0),
    "environment.floor_tilt": Range(
        -20.0, 20.0, "deg", "world", "optional: floor rotation about world x then y", (0.0, 0.0)
    ),
    "environment.time_scale": Range(
        0.5,
        2.0,
        "-",
        "-",
        "optional: clock of the recording: a frame stamped t shows the physical instant s·t (a wrong frame rate); "
        "velocities stay physical",
        1.0,
    ),
}


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Problem:
    """One validation problem: where, what value, what is allowed."""

    path: str
    value: Any
    message: str

    def __str__(self) -> str:
        if self.value is _NO_VALUE:
            return f"{self.path}: {self.message}" if self.path else self.message
        return f"{self.path} = {_show(self.value)}: {self.message}"


_NO_VALUE = object()


def _fmt(x: float) -> str:
    return f"{x:g}"


MAX_PROBLEMS_SHOWN = 20  # in the message (all are in `problems`): 45 000 bad items made a 2.7 MB line


class SceneError(ValueError):
    """A scene text or record is invalid. `problems` lists every problem found."""

    def __init__(self, problems: list[Problem]):
        self.problems = list(problems)
        n = len(self.problems)
        head = f"invalid scene ({n} problem{'s' if n != 1 else ''}): "
        shown = "; ".join(str(p) for p in self.problems[:MAX_PROBLEMS_SHOWN])
        more = f"; and {n - MAX_PROBLEMS_SHOWN} more" if n > MAX_PROBLEMS_SHOWN else ""
        super().__init__(head + shown + more)


def _show(value: Any, limit: int = 200) -> str:
    try:
        text = repr(value) if isinstance(value, str) else str(value)
    except RecursionError:  # a list nested thousands deep
        return f"<{type(value).__name__} nested too deeply to print>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------
def _number(value: Any) -> float:
    # YAML gives int/float; refuse bool ('yes' → True) and strings ('1.0' quoted) explicitly
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"must be a number, got {type(value).__name__}")
    try:
        value = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise ValueError("must be finite") from None
    if not math.isfinite(value):
        raise ValueError("must be finite")
    return round(value, DECIMALS)


Num = Annotated[float, BeforeValidator(_number)]
Vec2 = tuple[Num, Num]
Vec3 = tuple[Num, Num, Num]
Vec4 = tuple[Num, Num, Num, Num]
Name = Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")]


def _ranged(key: str, positive: bool = False) -> AfterValidator:
    """Validator checking a number or vector against `RANGES[key]` (and > 0 first when `positive`)."""
    rng = RANGES[key]

    def check(value: float | tuple[float, ...]) -> float | tuple[float, ...]:
        values = value if isinstance(value, tuple) else (value,)
        lo, hi = rng.bounds(len(values))
        for i, (v, a, b) in enumerate(zip(values, lo, hi, strict=True)):
            if positive and v <= 0:
                msg = "must be > 0"
            elif not a <= v <= b:
                msg = f"must be in [{_fmt(a)}, {_fmt(b)}] {rng.unit}".rstrip(" -")
            else:
                continue
            index = i if isinstance(value, tuple) else -1
            raise PydanticCustomError("range", "{msg}", {"msg": msg, "index": index, "value": v})
        return value

    return AfterValidator(check)


MIN_QUATERNION_NORM = 0.1  # below: too close to [0, 0, 0, 0] to name a rotation
IDENTITY = (1.0, 0.0, 0.0, 0.0)  # w, x, y, z: no rotation


def _unit_quaternion(q: tuple[float, ...]) -> tuple[float, ...]:
    # MuJoCo's compiler normalises any non-zero `quat`; so does `simulate` (the text keeps the numbers as written,
    # so that parse(dump(s)) == s). Only a near-zero quaternion, which names no rotation, is refused.
    norm = math.sqrt(sum(x * x for x in q))
    if norm < MIN_QUATERNION_NORM:
        # as many digits as show it below the bound: at 3 ([0.07071, 0.07071, 0, 0]) it read "norm 0.1 < 0.1"
        shown = next(t for p in range(3, 18) if float(t := f"{norm:.{p}g}") < MIN_QUATERNION_NORM)
        raise PydanticCustomError(
            "range",
            "{msg}",
            {"msg": f"must be a rotation quaternion [w, x, y, z] (norm {shown} < {MIN_QUATERNION_NORM})"},
        )
    return q


class _Record(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=False)


class State(_Record):
    """Initial state of an object (t = 0)."""

    angular_velocity: Annotated[Vec3, _ranged("state.angular_velocity")] = (0.0, 0.0, 0.0)
    linear_velocity: Annotated[Vec3, _ranged("state.linear_velocity")] = (0.0, 0.0, 0.0)
    # components in the table's [-1, 1] first (larger ones also overflowed the norm to inf: q / inf = 0, no rotation)
    orientation: Annotated[Vec4, _ranged("state.orientation"), AfterValidator(_unit_quaternion)] = IDENTITY
    position: Annotated[Vec3, _ranged("state.position")]


class Physics(_Record):
    """Physical properties of an object. `restitution`, `magnus`, `friction_slope` are optional extension fields."""

    friction: Annotated[Vec2, _ranged("physics.friction")] = (0.5, 0.0)
    mass: Annotated[Num, _ranged("physics.mass", positive=True)] = 1.0
    damping: Annotated[Num, _ranged("physics.damping")] = -4.0
    restitution: Annotated[Num, _ranged("physics.restitution")] | None = None
    magnus: Annotated[Num, _ranged("physics.magnus")] | None = None
    friction_slope: Annotated[Num, _ranged("physics.friction_slope")] | None = None


class _Object(_Record):
    name: Name | None = None
    state: State
    physics: Physics = Physics()


class Box(_Object):
    type: Literal["box"] = "box"
    size: Annotated[Vec3, _ranged("box.size", positive=True)]


class Sphere(_Object):
    type: Literal["sphere"] = "sphere"
    radius: Annotated[Num, _ranged("sphere.radius", positive=True)]


class Cylinder(_Object):
    type: Literal["cylinder"] = "cylinder"
    radius: Annotated[Num, _ranged("cylinder.radius", positive=True)]
    height: Annotated[Num, _ranged("cylinder.height", positive=True)]


Object = Box | Sphere | Cylinder


class Camera(_Record):
    type: Literal["camera"] = "camera"
    fovy: Annotated[Num, _ranged("camera.fovy")] = 45.0
    orientation: Annotated[Num, _ranged("camera.orientation")] = 45.0
    position: Annotated[Vec3, _ranged("camera.position")]


class Environment(_Record):
    """Optional extension item: air drag, wind, floor geometry and the recording's clock (defaults: none of them)."""

    type: Literal["environment"] = "environment"
    air_density: Annotated[Num, _ranged("environment.air_density")] = 0.0
    air_viscosity: Annotated[Num, _ranged("environment.air_viscosity")] = 0.0
    wind: Annotated[Vec3, _ranged("environment.wind")] = (0.0, 0.0, 0.0)
    floor_offset: Annotated[Num, _ranged("environment.floor_offset")] = 0.0
    floor_tilt: Annotated[Vec2, _ranged("environment.floor_tilt")] = (0.0, 0.0)
    time_scale: Annotated[Num, _ranged("environment.time_scale", positive=True)] = 1.0


class Gravity(_Record):
    type: Literal["gravity"] = "gravity"
    gravity: Annotated[Vec3, _ranged("gravity.gravity")]


DEFAULT_GRAVITY: tuple[float, float, float] = (0.0, 0.0, -9.81)


class Scene(_Record):
    """A validated scene. Object names are always filled in (`{type}_{k}` when absent in the text)."""

    objects: tuple[Object, ...]
    camera: Camera
    gravity: Vec3 = DEFAULT_GRAVITY
    environment: Environment | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)

    def object(self, name: str) -> Object:
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(f"no object named {name!r}; the scene has {list(self.names)}")

    @property
    def structure(self) -> tuple[str, ...]:
        """Object types in order: scenes with equal structure share one MuJoCo model layout."""
        return tuple(o.type for o in self.objects)


_ITEM_TYPES: dict[str, type[_Record]] = {
    "box": Box,
    "sphere": Sphere,
    "cylinder": Cylinder,
    "camera": Camera,
    "gravity": Gravity,
    "environment": Environment,
}
OBJECT_TYPES = ("box", "sphere", "cylinder")


# --------------------------------------------------------------------------------------------
# From plain Python data (the YAML list) to a Scene
# --------------------------------------------------------------------------------------------
_PYDANTIC_MESSAGES = {
    "missing": "required field is missing",
    "extra_forbidden": "unknown field",
    "tuple_type": "must be a list",
    "string_type": "must be a string",
    "string_pattern_mismatch": "must be a name of letters, digits and _ (not starting with a digit), at most 64 chars",
    "literal_error": "wrong type",
    "model_type": "must be a mapping",
    "model_attributes_type": "must be a mapping",
}


def _lookup(data: Any, loc: tuple) -> Any:
    for key in loc:
        try:
            data = data[key]
        except (KeyError, IndexError, TypeError):
            return _NO_VALUE
    return data


def _pydantic_problems(prefix: str, err: ValidationError, item: Any = None) -> list[Problem]:
    out = []
    short: dict[str, int] = {}  # vector path -> its place in `out`
    for e in err.errors(include_url=False):
        loc = e["loc"]
        if e["type"] == "missing" and loc and isinstance(loc[-1], int):
            # a vector with too few values: report the vector once (pydantic names each missing element), with
            # its length; the last missing element's index + 1 is the length it must have
            path = prefix + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc[:-1])
            value = _lookup(item, loc[:-1])
            got = f", got {len(value)}" if isinstance(value, list | tuple) else ""
            problem = Problem(path, value, f"must have {loc[-1] + 1} values{got}")
            if path in short:
                out[short[path]] = problem
            else:
                short[path] = len(out)
                out.append(problem)
            continue
        path = prefix + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc)
        msg = e["msg"]
        value = _NO_VALUE if e["type"] == "missing" else e.get("input", _NO_VALUE)
        if e["type"] == "range":
            ctx = e["ctx"]
            if ctx.get("index", -1) >= 0:
                path, value = f"{path}[{ctx['index']}]", ctx["value"]
            out.append(Problem(path, value, ctx["msg"]))
            continue
        if e["type"] == "value_error":
            msg = str(e.get("ctx", {}).get("error", msg))
        elif e["type"] in ("too_short", "too_long"):
            ctx = e.get("ctx", {})
            msg = f"must have {ctx.get('expected', ctx.get('max_length', ctx.get('min_length')))} values"
            if ctx.get("actual_length") is not None:
                msg += f", got {ctx['actual_length']}"
        else:
            msg = _PYDANTIC_MESSAGES.get(e["type"], msg)
        out.append(Problem(path, value, msg))
    return out


def from_items(items: Any) -> Scene:
    """Validate the parsed YAML (a list of item mappings) into a `Scene`.

    Raises:
        SceneError: with every problem found (types, ranges, duplicates, missing camera, ...).
    """
    problems: list[Problem] = []
    if items is None:
        raise SceneError([Problem("", _NO_VALUE, "empty scene: no YAML items found")])
    if not isinstance(items, list):
        raise SceneError(
            [Problem("scene", items, f"must be a YAML list of items (- type: ...), got {_type_name(items)}")]
        )
    objects: list[Object] = []
    cameras: list[Camera] = []
    gravities: list[tuple[float, float, float]] = []
    environments: list[Environment] = []
    counts = {"camera": 0, "gravity": 0, "environment": 0}
    n_obj = 0
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            problems.append(
                Problem(f"items[{i}]", item, f"must be a mapping with a 'type' key, got {_type_name(item)}")
            )
            continue
        kind = item.get("type")
        known = isinstance(kind, str)  # a list or mapping (`type: [box]`) would not even hash: an unknown type
        if known and kind in OBJECT_TYPES:
            path = f"objects[{n_obj}]"
            n_obj += 1
        elif known and kind in counts:
            counts[kind] += 1
            path = kind if counts[kind] == 1 else f"{kind}[{counts[kind] - 1}]"
        else:
            allowed = ", ".join([*OBJECT_TYPES, "camera", "gravity", "environment"])
            problems.append(Problem(f"items[{i}].type", kind, f"unknown type; allowed: {allowed}"))
            continue
        try:
            rec = _ITEM_TYPES[kind].model_validate(item)
        except ValidationError as e:
            problems.extend(_pydantic_problems(path, e, item))
            continue
        if kind in OBJECT_TYPES:
            objects.append(rec)
        elif kind == "camera":
            cameras.append(rec)
        elif kind == "gravity":
            gravities.append(rec.gravity)
        else:
            environments.append(rec)

    if n_obj == 0:
        problems.append(Problem("objects", _NO_VALUE, "the scene needs at least one box, sphere or cylinder"))
    if n_obj > MAX_OBJECTS:
        problems.append(Problem("objects", n_obj, f"at most {MAX_OBJECTS} objects"))
    if counts["camera"] == 0:
        problems.append(Problem("camera", _NO_VALUE, "the scene needs one camera item (- type: camera)"))
    for kind, n in counts.items():
        if n > 1:
            problems.append(Problem(kind, n, f"at most one {kind} item, found {n}"))

    # names: fill in {type}_{k} for unnamed objects, refuse duplicates
    named = [o.name for o in objects if o.name is not None]
    for i, o in enumerate(objects):
        if o.name == "floor":  # contacts name the floor "floor": an object so named could not be told apart
            problems.append(Problem(f"objects[{i}].name", o.name, "reserved for the floor; choose another name"))
    for name in sorted({n for n in named if named.count(n) > 1}):
        idx = [i for i, o in enumerate(objects) if o.name == name]
        problems.append(Problem(f"objects[{idx[1]}].name", name, f"duplicate name (also objects[{idx[0]}])"))
    taken = set(named)
    filled: list[Object] = []
    per_type: dict[str, int] = {}
    for o in objects:
        if o.name is None:
            k = per_type.get(o.type, 0)
            while f"{o.type}_{k}" in taken:
                k += 1
            per_type[o.type] = k + 1
            taken.add(f"{o.type}_{k}")
            o = o.model_copy(update={"name": f"{o.type}_{k}"})
        filled.append(o)

    parts = {
        "objects": filled,
        "camera": cameras[0] if cameras else None,
        "gravity": gravities[0] if gravities else DEFAULT_GRAVITY,
        "environment": environments[0] if environments else None,
    }
    if problems:
        raise SceneError(problems)
    return Scene(
        objects=tuple(filled), camera=parts["camera"], gravity=parts["gravity"], environment=parts["environment"]
    )


def _type_name(value: Any) -> str:
    return "a mapping" if isinstance(value, dict) else type(value).__name__


# --------------------------------------------------------------------------------------------
# Safe YAML
# --------------------------------------------------------------------------------------------
class _DuplicateKey(yaml.constructor.ConstructorError):
    """A mapping repeats a key (reported as is; other constructor errors are refused tags)."""


def _core_schema_numbers(table: dict) -> dict:
    """The implicit-resolver table `table` (PyYAML's, YAML 1.1) with YAML 1.2 core-schema numbers: `1e-1` and
    `2E5` are floats (1.1 reads them as strings, then "must be a number, got str"), `1:00` is not 60 (1.1's
    base 60), `010` is 10 (1.1: octal 8; `_construct_int`), `0o17` and `0x1F` are 15 and 31; `.inf` and `.nan`
    stay floats (the fields then refuse them by name); `2024-01-01` is a string, not a date."""
    int_tag, float_tag = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
    dropped = (int_tag, float_tag, "tag:yaml.org,2002:timestamp")  # a date is a string here (then named)
    out = {k: [(tag, rx) for tag, rx in v if tag not in dropped] for k, v in table.items()}
    numbers = (
        (int_tag, re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"), "-+0123456789"),
        (
            float_tag,
            re.compile(
                r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
            ),
            "-+0123456789.",
        ),
    )
    for tag, rx, first in numbers:  # integers appended first: "10" also matches the float pattern
        for ch in first:
            out.setdefault(ch, []).append((tag, rx))
    return out


def _construct_int(loader, node) -> int:
    """A YAML 1.2 integer: decimal (leading zeros included), or `0o` octal / `0x` hexadecimal."""
    text = loader.construct_scalar(node)
    body = text.lstrip("+-")
    base = {"0o": 8, "0x": 16}.get(body[:2], 10)
    value = int(body[2:] if base != 10 else body, base)
    return -value if text.startswith("-") else value


class _UniqueKeys:
    """Refuses a mapping that repeats a key (PyYAML keeps the last silently: `radius: 0.2` then `radius: 1.4` read
    as 1.4). The constructor is Python in both loaders, so the C one gets this check too."""

    def construct_mapping(self, node, deep=False):  # noqa: D102
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, str | int | float | bool):
                continue
            if key in seen:
                line = key_node.start_mark.line + 1
                msg = f"key {key!r} given twice (lines {seen[key]} and {line})"
                raise _DuplicateKey(None, None, msg, key_node.start_mark)
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


_PLAIN_TAGS = {f"tag:yaml.org,2002:{t}" for t in ("null", "bool", "int", "float", "str", "seq", "map")}


class _NoAliasLoader(_UniqueKeys, yaml.SafeLoader):
    """SafeLoader that refuses anchors/aliases (no alias bombs) and python/* tags (SafeLoader already does)."""

    yaml_implicit_resolvers = _core_schema_numbers(yaml.SafeLoader.yaml_implicit_resolvers)
    # plain YAML only: the tags !!binary, !!set, !!omap, !!pairs and !!timestamp made values no scene field takes
    # (!!set {1.0, 0.5, 0.4} became a reordered size, !!binary a name); an unknown tag is a YAML error
    yaml_constructors = {
        **{k: v for k, v in yaml.SafeLoader.yaml_constructors.items() if k in _PLAIN_TAGS or k is None},
        "tag:yaml.org,2002:int": _construct_int,
    }

    def compose_node(self, parent, index):  # noqa: D102
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.YAMLError(f"YAML aliases are not allowed (*{event.anchor} at line {event.start_mark.line + 1})")
        return super().compose_node(parent, index)


# libyaml's safe loader (PyYAML's C extension) parses a scene ~6x faster than the pure-Python one
# (benchmarks/bench_parse.py); it can't refuse aliases itself, so it only reads texts without `&` and `*`, in which
# no anchor or alias can occur. Its recursion is unbounded: ~25 000 nested `[` crash the process (segmentation
# fault) where the Python loader raises RecursionError; so it only reads texts with few characters that can open a
# level (`[`, `{`, `-`, `?`; deeper indentation alone needs more than MAX_TEXT_CHARS), a scene of ~100 objects.
_FAST_LOADER = (
    type(
        "_FastLoader",
        (_UniqueKeys, yaml.CSafeLoader),
        {
            "yaml_implicit_resolvers": _NoAliasLoader.yaml_implicit_resolvers,
            "yaml_constructors": _NoAliasLoader.yaml_constructors,
        },
    )
    if hasattr(yaml, "CSafeLoader")
    else None
)
_FAST_MAX_OPENERS = 2_000


def _loader_for(text: str) -> type:
    if _FAST_LOADER is None or "&" in text or "*" in text:
        return _NoAliasLoader
    if sum(text.count(c) for c in "[{-?") > _FAST_MAX_OPENERS:
        return _NoAliasLoader
    return _FAST_LOADER


_SURROGATE = re.compile("[\ud800-\udfff]")
# a line break as YAML (PyYAML and libyaml alike) counts them: not str.splitlines, which also breaks at \x0b, \x0c
# and \x1c-\x1e, characters YAML refuses in a scene
_BREAK = re.compile("\r\n|[\n\r\x85\u2028\u2029]")


def _line_breaks(text: str) -> int:
    return len(_BREAK.findall(text))


def _line_column(text: str, offset: int) -> str:
    """`offset` in `text` as YAML names a place: "line L, column C", both from 1."""
    last = max((m.end() for m in _BREAK.finditer(text, 0, offset)), default=0)
    return f"line {_line_breaks(text[:offset]) + 1}, column {offset - last + 1}"


def _checked_text(text: str | bytes) -> str:
    """`text` as a string (bytes decoded as UTF-8), refused when binary or longer than MAX_TEXT_CHARS."""
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as e:
            raise SceneError([Problem("text", _NO_VALUE, f"not UTF-8 text (byte {e.start}): binary input?")]) from None
    if "\x00" in text:
        raise SceneError([Problem("text", _NO_VALUE, "contains NUL bytes: binary input?")])
    surrogate = _SURROGATE.search(text)
    if surrogate is not None:  # no UTF-8 form: the YAML reader would refuse it by its offset in the text
        where = _line_column(text, surrogate.start())
        msg = f"contains a lone surrogate character {surrogate.group()!r} ({where}): not valid Unicode text"
        raise SceneError([Problem("text", _NO_VALUE, msg)])
    if len(text) > MAX_TEXT_CHARS:
        raise SceneError([Problem("text", len(text), f"too long: at most {MAX_TEXT_CHARS} characters")])
    return text


MAX_FLOW_DEPTH = 32  # levels of `[` / `{`: a scene needs 3 even in flow style, [{state: {position: [0, 0, 1]}}]
_BRACKET = re.compile(r"[\[\]{}]")


def _too_deep(text: str) -> Problem | None:
    """A problem when `[` / `{` nest more than MAX_FLOW_DEPTH levels, else None. PyYAML's Python scanner keeps
    one possible key per open flow level and walks them all at every token: 2 001 nested `[` (4 kB, a model's
    repetition loop) took 6 s to refuse, 300 lines of 300 levels (181 kB) 18 s. Brackets in quotes and comments
    count too (never 32 deep in a scene); closers there can only hide depth, which the loaders still bound."""
    depth = 0
    for m in _BRACKET.finditer(text):
        depth = depth + 1 if m.group() in "[{" else max(depth - 1, 0)
        if depth > MAX_FLOW_DEPTH:
            msg = f"nested too deeply: more than {MAX_FLOW_DEPTH} levels of [ and {{ ({_line_column(text, m.start())})"
            return Problem("yaml", _NO_VALUE, msg)
    return None


def load_yaml(text: str | bytes) -> Any:
    """Parse YAML text safely: no tags that build Python objects, no aliases, bounded size and flow nesting."""
    text = _checked_text(text)
    deep = _too_deep(text)
    if deep is not None:
        raise SceneError([deep])
    try:
        return yaml.load(text, Loader=_loader_for(text))  # noqa: S506 - safe loaders only
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        if isinstance(e, yaml.reader.ReaderError) and isinstance(e.character, int):
            # a control character, located by an offset (in bytes with the C loader): by line and column instead;
            # the reader stops at the first unacceptable character, so its first occurrence is the one
            offset = text.find(chr(e.character))
            problem = f"unacceptable character #x{e.character:04x}: {e.reason}"
            where = f" ({_line_column(text, offset if offset >= 0 else e.position)})"
        if isinstance(e, yaml.constructor.ConstructorError) and problem.startswith("could not determine a constructor"):
            problem = f"refused YAML tag: {problem}"
        raise SceneError([Problem("yaml", _NO_VALUE, f"{problem}{where}")]) from None
    except RecursionError:
        raise SceneError([Problem("yaml", _NO_VALUE, "nested too deeply")]) from None
    except ValueError as e:  # e.g. an integer past Python's 4300-digit conversion limit
        raise SceneError([Problem("yaml", _NO_VALUE, f"unreadable value: {e}")]) from None


_ANSWER = re.compile(r"<answer>(.*?)(?:</answer>|$)", re.S)
_THINK = re.compile(r"<think>.*?(?:</think>|$)", re.S)
_FENCE = re.compile(r"```(?:ya?ml)?\s*\n(.*?)(?:```|$)", re.S)
# `- type:`, or `-` alone then `type:` on the next line; not \s*: runs of blank lines made the search quadratic
_FIRST_ITEM = re.compile(r"^[ \t]*-(?:[ \t]+|[ \t]*\n[ \t]+)type[ \t]*:", re.M)
_INLINE_ITEM = re.compile(r"-[ \t]+type[ \t]*:")  # an item after other text on its line


def _strip_wrappers(text: str) -> str:
    """The last `<answer>` block (an unclosed one runs to the end), else the text without `<think>`; then a fence.
    What is left out before it is left as its line breaks, so that a YAML error names the line of the response."""
    answers = list(_ANSWER.finditer(text))
    if answers:
        body = "\n" * _line_breaks(text[: answers[-1].start(1)]) + answers[-1].group(1)
    else:
        body = _THINK.sub(lambda m: "\n" * _line_breaks(m.group()), text)
    fence = _FENCE.search(body)
    return "\n" * _line_breaks(body[: fence.start(1)]) + fence.group(1) if fence else body


def _cut_prose(body: str) -> tuple[int, str] | None:
    """Where in `body` the list starts, and the part of `body` from the first `- type:` line to the last line of
    that list; or None. A first item after other text on its line ("Scene: - type: box", a stray control
    character), followed by its indented keys, starts the list there: cut with its line, it was an object dropped
    without a word."""
    m = _FIRST_ITEM.search(body)
    start = None if m is None else m.start()
    before = body if start is None else body[:start]
    inline = None
    for inline in _INLINE_ITEM.finditer(before):  # the last one before the first line-start item
        pass
    if inline is not None:  # its own keys follow it, indented, up to the next item
        keys = [line for line in _BREAK.split(body[inline.start() : start])[1:] if line.strip()]
        # indented as the list's lines below are measured (str.lstrip): a form feed or another control character
        # before a key leaves the item in, for YAML to refuse, rather than dropping the object without a word
        if keys and keys[0][:1].isspace() and (start is None or all(line[:1].isspace() for line in keys)):
            start = inline.start()
    if start is None:
        return None
    lines = _BREAK.split(body[start:])
    indent = len(lines[0]) - len(lines[0].lstrip())
    keep = []
    for line in lines:
        stripped = line.strip()
        # list items and their indented children belong; an unindented non-item line is prose
        if stripped and (len(line) - len(line.lstrip())) <= indent and not stripped.startswith("-"):
            break
        keep.append(line)
    if indent:  # a list indented under prose ("Here is the scene:\n  - type: box"): as if written at the margin
        keep = [line[indent:] if len(line) - len(line.lstrip()) >= indent else line.lstrip() for line in keep]
    return start, "\n".join(keep)


def extract_yaml(text: str) -> str:
    """Return the YAML part of a model response.

    Takes the last `<answer>...</answer>` block when there is one, otherwise drops `<think>...</think>`;
    then the inside of a ```yaml fence if any. When that is not a YAML list by itself, stray prose before the
    first `- type:` line and after the list is cut away.
    """
    return _extract(text)[0].strip()


def _extract(text: str) -> tuple[str, Any]:
    """`extract_yaml`'s text and, when it already parsed as a YAML list there, the list (else None). Without the
    list, the text comes after blank lines in place of the prose cut before it, so that a YAML error's line is the
    line of the YAML body (a scene file's own, after a comment: before, it was counted from the first item)."""
    body = _strip_wrappers(text)
    try:
        data = load_yaml(body)
        if isinstance(data, list):
            return body.strip(), data
    except SceneError:
        pass
    start, part = _cut_prose(body) or (0, body)
    lead = len(part) - len(part.lstrip())
    return "\n" * _line_breaks(body[:start] + part[:lead]) + part.strip(), None


def parse(text: str | bytes) -> Scene:
    """Parse a scene from YAML text or a model response.

    Raises:
        SceneError: naming every problem (path, value, what is allowed).
    """
    if isinstance(text, bytes):  # a file's contents: decoded and checked, not parsed (it may wrap the YAML)
        text = _checked_text(text)
    if not isinstance(text, str):
        raise SceneError([Problem("text", _NO_VALUE, f"must be a string, got {_type_name(text)}")])
    if not text.strip():
        raise SceneError([Problem("text", _NO_VALUE, "empty text: no YAML found")])
    body, data = _extract(text)
    return from_items(data if data is not None else load_yaml(body))


def load(path: str) -> Scene:
    """Read and parse a scene file; a missing file raises SceneError naming the path."""
    try:
        with open(path, "rb") as f:
            data = f.read(4 * MAX_TEXT_CHARS + 1)  # UTF-8: up to 4 bytes a character; the length check is in chars
            size = max(os.fstat(f.fileno()).st_size, len(data))  # a pipe has no size: what was read
    except OSError as e:
        raise SceneError([Problem("file", path, e.strerror or str(e))]) from None
    if size > 4 * MAX_TEXT_CHARS:  # refused by its size, not by a decoding error where the read stopped
        msg = f"too large: {size} bytes, and a scene is at most {MAX_TEXT_CHARS} characters"
        raise SceneError([Problem("file", path, msg)])
    return parse(data)


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


def is_whole(value: Any) -> bool:
    """Whether `value` is a whole number as a count, size or seed takes it: an int or a numpy integer, not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """Whether `value` is a real number as a rate, share or coefficient takes it: an int, a float or a numpy number
    (`numbers.Real`), not a bool (numpy's bool is no `numbers.Real`), a str or an array."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def require_scene(value: Any, where: str) -> Scene:
    """`value` if it is a Scene, else a TypeError naming `where` (e.g. "state_mae: pred") and what was passed: YAML
    text or None failed deep inside on "'str' object has no attribute 'objects'"."""
    if not isinstance(value, Scene):
        raise TypeError(f"{where} is a {type(value).__name__}, not a Scene (scene.parse reads YAML text)")
    return value


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


def ranges_markdown() -> str:
    """The range table as Markdown (the README's scene-format reference)."""
    rows = ["| field | unit | frame | range | meaning |", "| --- | --- | --- | --- | --- |"]
    for key, r in RANGES.items():
        if isinstance(r.lo, tuple):
            rng = ", ".join(f"[{_fmt(a)}, {_fmt(b)}]" for a, b in zip(r.lo, r.hi, strict=True))
        else:
            rng = f"[{_fmt(r.lo)}, {_fmt(r.hi)}]"
        rows.append(f"| `{key}` | {r.unit} | {r.frame} | {rng} | {r.meaning} |")
    return "\n".join(rows) + "\n"
