"""The scene language's records: `Scene` and its items (box, sphere, cylinder, camera, gravity, environment),
each field checked against the range table (`ranges.RANGES`) when a record is made.

`scene.py` builds them from parsed YAML (`from_items`, `parse`) and re-exports them; `scene_dump.py` writes
them back as canonical YAML. Numbers are kept rounded to `DECIMALS`, so that `parse(dump(s)) == s`.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field
from pydantic_core import PydanticCustomError

from aynamics.ranges import RANGES, fmt_number

DECIMALS = 4  # canonical precision of every number: 0.1 mm, 0.1 mrad, 0.1 g
MAX_OBJECTS = 32


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
                msg = f"must be in [{fmt_number(a)}, {fmt_number(b)}] {rng.unit}".rstrip(" -")
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
