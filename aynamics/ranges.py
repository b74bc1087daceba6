"""The range table of every scene field (unit, frame, plausible range, meaning), and how a scene is refused.

`RANGES` is the one source of the fields' meanings and bounds: `scene_records.py` validates against it, the dataset
sampler and CMA-ES take their bounds from it, and the README's field reference is `ranges_markdown()` (`aynamics
ranges --markdown`; a test keeps the README in sync). Every problem found in a scene is a `Problem` (where, what
value, what is allowed), and all of them are raised at once in one `SceneError`:

    objects[1].physics.mass = -2.0: must be > 0
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


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
        if self.value is NO_VALUE:
            return f"{self.path}: {self.message}" if self.path else self.message
        return f"{self.path} = {_show(self.value)}: {self.message}"


NO_VALUE = object()  # a Problem's value when there is none to show ("empty text")


def fmt_number(x: float) -> str:
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


def ranges_markdown() -> str:
    """The range table as Markdown (the README's scene-format reference)."""
    rows = ["| field | unit | frame | range | meaning |", "| --- | --- | --- | --- | --- |"]
    for key, r in RANGES.items():
        if isinstance(r.lo, tuple):
            rng = ", ".join(f"[{fmt_number(a)}, {fmt_number(b)}]" for a, b in zip(r.lo, r.hi, strict=True))
        else:
            rng = f"[{fmt_number(r.lo)}, {fmt_number(r.hi)}]"
        rows.append(f"| `{key}` | {r.unit} | {r.frame} | {rng} | {r.meaning} |")
    return "\n".join(rows) + "\n"
