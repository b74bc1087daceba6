"""A rollout's records: how it is timed (`SimConfig`: duration, frame rate, physics steps per frame) and what it
gives back (`Rollout`: states, contacts, rest and view per frame; `RawRollout`: a batch's raw states, the scorer's
hot path). `aynamics.simulate` makes them and re-exports them.

    config = SimConfig(duration=2.0, fps=15)   # config.frames 30, config.substeps 16 (a physics step near 1/240 s)
    rollout = simulate(scene, config)          # a Rollout: rollout.position (31, N, 3), rollout.contacts, ...
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from mujoco import batch as mjbatch

from aynamics.mujoco_model import FPS, PHYSICS_HZ, SUBSTEPS, Template

DURATION = 1.0


@dataclass(frozen=True)
class Contact:
    """A contact interval between two objects or an object and the floor (`other == "floor"`)."""

    a: str
    b: str
    start: float  # s, first frame time at which the pair touches
    end: float  # s, last frame time at which it touches

    def to_json(self) -> dict:
        return {"with": self.b, "start": round(self.start, 4), "end": round(self.end, 4)}


@dataclass(frozen=True)
class Rollout:
    """One simulated scene. Frame 0 is the initial state; T = duration · fps + 1 frames.

    Attributes:
        names: (N,) object names.
        t: (T,) frame times, s.
        position, linear_velocity, angular_velocity: (T, N, 3), world frame (angular velocity in world axes).
        orientation: (T, N, 4) unit quaternions w, x, y, z.
        touching: (T, N, N + 1) bool: object i touches object j (j < N) or the floor (j = N) at any physics step
            in (t[k-1], t[k]] (frame 0: in the first half frame).
        in_view: (T, N) bool: the object's bounding sphere meets the camera's view frustum (at a 480×320 image's
            aspect, `camera.matrices`' default: a generated record stores it for its own size).
        rest_time: (N,) s at which each object is at rest for the rest of the rollout, or None.
        valid: False when the rollout diverged (NaN, blow-up, tunnelling); `reason` says where.
    """

    names: tuple[str, ...]
    t: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
    touching: np.ndarray
    in_view: np.ndarray
    rest_time: tuple[float | None, ...]
    valid: bool = True
    reason: str | None = None
    contacts: tuple[Contact, ...] = field(default=())

    def to_npz(self, path: str) -> None:
        np.savez_compressed(
            path,
            names=np.array(self.names),
            t=self.t,
            position=self.position,
            orientation=self.orientation,
            linear_velocity=self.linear_velocity,
            angular_velocity=self.angular_velocity,
            touching=self.touching,
            in_view=self.in_view,
            rest_time=np.array([np.nan if r is None else r for r in self.rest_time]),
            valid=np.array(self.valid),
        )

    def summary(self) -> dict:
        """The `aynamics simulate --json` record."""
        objects = {}
        for i, name in enumerate(self.names):
            objects[name] = {
                "final_position": [round(float(x), 4) for x in self.position[-1, i]],
                "rest_time": self.rest_time[i],
                "contacts": [c.to_json() for c in self.contacts if c.a == name],
            }
        return {"objects": objects, "valid": self.valid, "reason": self.reason}


MAX_STEPS = 200_000  # physics steps of one rollout (each recorded): e.g. 60 s at 30 fps with 100 substeps


def whole_in_range(value, name: str) -> int:
    """`value` as an int in [1, 1000] (30, 30.0 and numpy's 30 alike), else a ValueError naming it."""
    try:
        ok = float(value).is_integer() and 1 <= value <= 1000 and not isinstance(value, bool)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{name} = {value!r}: must be a whole number in [1, 1000]")
    return int(value)


@dataclass(frozen=True)
class SimConfig:
    """Timing of a rollout: `duration` s at `fps` frames per second, `substeps` physics steps per frame.

    `substeps` None (the default) keeps the physics step near 1 / `PHYSICS_HZ` s at any frame rate:
    round(240 / fps) steps per frame (8 at 30 fps, 16 at 15, 10 at 25). A fixed number of steps per frame would
    simulate a 15 fps video at 1/120 s, another physics (softer contacts, other bounces and stops).
    """

    duration: float = DURATION
    fps: int = FPS
    substeps: int | None = None

    def __post_init__(self):
        if isinstance(self.duration, np.ndarray) and self.duration.ndim == 0 and self.duration.dtype.kind in "iuf":
            object.__setattr__(self, "duration", self.duration.item())  # a 0-d array, as np.float64(...) is taken
        if isinstance(self.duration, bool) or not isinstance(self.duration, (int, float, np.integer, np.floating)):
            raise ValueError(f"duration = {self.duration!r}: must be a number of seconds in (0, 60]")
        if not (0 < self.duration <= 60):
            raise ValueError(f"duration = {self.duration}: must be in (0, 60] s")
        object.__setattr__(self, "fps", whole_in_range(self.fps, "fps"))
        per_frame = max(1, round(PHYSICS_HZ / self.fps)) if self.substeps is None else self.substeps
        object.__setattr__(self, "substeps", whole_in_range(per_frame, "substeps"))
        steps = self.frames * self.substeps
        if steps > MAX_STEPS:  # every step's state is recorded: 60 s at 1000 fps x 1000 substeps needed > 6 GB
            raise ValueError(
                f"duration = {self.duration} s at fps = {self.fps} with substeps = {self.substeps} is {steps} physics "
                f"steps: at most {MAX_STEPS} (the default is {DURATION:g} s x {FPS} x {SUBSTEPS})"
            )
        if self.frames < 1:  # MuJoCo's rollout needs at least one step
            raise ValueError(
                f"duration = {self.duration} s at fps = {self.fps} is {self.frames} frames: need at least 1 "
                f"(duration >= {0.5 / self.fps:.3g} s)"
            )

    @property
    def frames(self) -> int:
        return int(round(self.duration * self.fps))

    @property
    def timestep(self) -> float:
        """Physics step, s: 1 / (fps · substeps)."""
        return 1.0 / (self.fps * self.substeps)


@dataclass(frozen=True)
class RawRollout:
    """Frame-rate states of a batch of same-structure scenes (the scorer's hot path skips `Rollout`).

    Attributes:
        qpos: (n, T, nq), qvel: (n, T, nv) per frame, frame 0 the initial state.
        sensor: (n, S, nsensordata) contact counts after every physics step.
        warnings: (n,) MuJoCo warning counts (instability).
        batch: the (cached) Batch it ran on, holding the scenes' parameters: valid for ray casts until the next
            call with the same structure and size.
        overlap: per scene, the deepest interpenetration at t = 0 as (depth m, object i, object j or N for the
            floor), or None when nothing interpenetrates by more than `MAX_START_OVERLAP`.
    """

    template: Template
    qpos: np.ndarray
    qvel: np.ndarray
    sensor: np.ndarray
    warnings: np.ndarray
    batch: mjbatch.Batch | None = None
    overlap: tuple | None = None
