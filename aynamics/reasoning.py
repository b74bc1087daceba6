"""Motion-reasoning text: a natural-language account of a simulated scene (the paper's supplement).

Every motion fact comes from the simulation, none from the YAML alone: positions and velocities from the
rollout's states, stop times from `Rollout.rest_time`, ground contact and collisions from `Rollout.contacts`,
visibility from segmentation masks (`visibility`). Shape, size and mass are the object's own attributes.

Position bins (seven per axis, metres, world frame; the camera looks along +y):

| bin | x                | y (depth from the camera) | z (height above the floor) |
| --- | ---------------- | ------------------------- | ----------------------- |
| v < -2          | far left         | far in the foreground     | far below the surface   |
| -2 <= v < -1    | moderately left  | in the foreground         | below the surface       |
| -1 <= v < -0.5  | slightly left    | slightly in the foreground| slightly below the surface |
| -0.5 <= v <= 0.5| near center      | at mid-depth              | close to the surface    |
| 0.5 < v <= 1    | slightly right   | slightly in the background| slightly raised         |
| 1 < v <= 2      | moderately right | in the background         | raised                  |
| v > 2           | far right        | far in the background     | high above the surface  |

Directions: +x rightward, -x leftward, +y forward (away from the camera), -y backward (toward the camera),
+z upward, -z downward; a component is named when it is at least a quarter of the speed.

Each fact has several paraphrase templates; `seed` picks one per fact, the order of facts stays fixed:

    text = reasoning_text(scene, rollout, visible, frame_times, seed=3)
    target = think_target(text, dump(scene))   # "<think>...</think>\\n\\n<answer>...</answer>"
"""

from __future__ import annotations

import numpy as np

from aynamics.scene import Box, Cylinder, Scene, Sphere
from aynamics.simulate import REST_ANGULAR, REST_LINEAR, Rollout

THRESHOLDS = (-2.0, -1.0, -0.5, 0.5, 1.0, 2.0)  # m, bin edges shared by x, y and z
BIN_WORDS = {
    "x": (
        "far left",
        "moderately left",
        "slightly left",
        "near center",
        "slightly right",
        "moderately right",
        "far right",
    ),
    "y": (
        "far in the foreground",
        "in the foreground",
        "slightly in the foreground",
        "at mid-depth",
        "slightly in the background",
        "in the background",
        "far in the background",
    ),
    "z": (
        "far below the surface",
        "below the surface",
        "slightly below the surface",
        "close to the surface",
        "slightly raised",
        "raised",
        "high above the surface",
    ),
}
DIRECTION_SHARE = 0.25  # a velocity component is named when |v_i| >= this share of the speed
MIN_PIXELS = 1  # an object is visible in a frame when its mask has at least this many pixels


def position_bin(value: float) -> int:
    """Bin index 0..6 of a coordinate: <-2, [-2,-1), [-1,-0.5), [-0.5,0.5], (0.5,1], (1,2], >2."""
    v = float(value)
    if v < -0.5:
        return 0 if v < -2 else 1 if v < -1 else 2
    if v <= 0.5:
        return 3
    return 4 if v <= 1 else 5 if v <= 2 else 6


def position_words(position: np.ndarray) -> tuple[str, str, str]:
    """The x, y and z bin words of a position (3,)."""
    return tuple(BIN_WORDS[a][position_bin(position[i])] for i, a in enumerate("xyz"))  # type: ignore[return-value]


def floor_heights(scene: Scene, position: np.ndarray) -> np.ndarray:
    """Heights (..., ) m of points (..., 3) above the scene's floor plane (`environment.floor_offset`, tilted by
    `floor_tilt`), along its normal: the world z when the scene has no environment item."""
    from aynamics.simulate import quat_to_mat, tilt_quaternion

    env = scene.environment
    pos = np.asarray(position, dtype=float)
    if env is None:
        return pos[..., 2]
    normal = quat_to_mat(tilt_quaternion(*env.floor_tilt))[:, 2]
    return (pos - np.array([0.0, 0.0, env.floor_offset])) @ normal


def direction_words(velocity: np.ndarray) -> list[str]:
    """Named directions of a velocity (3,), e.g. ['rightward', 'forward']; empty when at rest."""
    speed = float(np.linalg.norm(velocity))
    if speed < REST_LINEAR:
        return []
    names = (("leftward", "rightward"), ("backward", "forward"), ("downward", "upward"))
    return [names[i][int(velocity[i] > 0)] for i in range(3) if abs(velocity[i]) >= DIRECTION_SHARE * speed]


def visibility(segmentation: np.ndarray, num_objects: int, min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """(F, N) bool: object i has at least `min_pixels` pixels in frame f of a (F, H, W) mask (-1 = background)."""
    seg = np.asarray(segmentation)
    if seg.ndim != 3:
        raise ValueError(f"segmentation shape {seg.shape}: must be (frames, height, width)")
    flat = seg.reshape(seg.shape[0], -1).astype(np.int64) + 1  # 0 = background
    if flat.size and (flat.min() < 0 or flat.max() > num_objects):
        raise ValueError(
            f"segmentation values in [{flat.min() - 1}, {flat.max() - 1}]: must be in [-1, {num_objects - 1}]"
        )
    counts = np.stack([np.bincount(row, minlength=num_objects + 1) for row in flat]) if len(flat) else None
    if counts is None:
        return np.zeros((0, num_objects), dtype=bool)
    return counts[:, 1:] >= min_pixels


def centres_in_picture(camera, position: np.ndarray) -> np.ndarray:
    """(F, N) bool: the centre of object i at sampled state f (`position` (F, N, 3), world) projects inside the
    image of `camera` (`camera.CameraMatrices`) in front of it."""
    pos = np.asarray(position, dtype=float)
    uv, z = camera.project(pos.reshape(-1, 3))
    u, v = uv[:, 0], uv[:, 1]
    inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return inside.reshape(pos.shape[:2])


# --------------------------------------------------------------------------------------------
# Templates: {slots} are filled from the facts; the index is drawn from the seed per fact
# --------------------------------------------------------------------------------------------
_SHAPE = {
    "box": (
        "{Name}: A cuboid with dimensions {dims} m, mass {mass} kg",
        "{Name}: A box measuring {dims} m, mass {mass} kg",
        "{Name}: A rectangular block of {dims} m weighing {mass} kg",
    ),
    "sphere": (
        "{Name}: A sphere with radius {radius} m, mass {mass} kg",
        "{Name}: A ball of radius {radius} m, mass {mass} kg",
        "{Name}: A sphere of radius {radius} m weighing {mass} kg",
    ),
    "cylinder": (
        "{Name}: A cylinder with radius {radius} m and height {height} m, {pose}, mass {mass} kg",
        "{Name}: A cylinder of radius {radius} m and height {height} m, {pose}, mass {mass} kg",
        "{Name}: A {pose} cylinder with radius {radius} m and height {height} m weighing {mass} kg",
    ),
}
_POSITION = (
    ", positioned {x}, {y}, {z}.",
    ", located {x}, {y}, {z}.",
    ", placed {x}, {y}, {z}.",
)
_MOVES = (
    "It moves at {speed} m/s ({dirs})",
    "It starts moving at {speed} m/s ({dirs})",
    "Its initial speed is {speed} m/s ({dirs})",
)
_STILL = ("It starts at rest", "It is initially stationary", "It begins motionless")
_SPINS = (  # no linear velocity at the start, but turning (it may still fall: no "in place")
    "It starts with no linear velocity, spinning at {spin} rad/s",
    "It has no initial speed but spins at {spin} rad/s",
    "It starts without moving along, turning at {spin} rad/s",
)
_STOPS = (", stops at t={t}s", ", comes to rest at t={t}s", ", halts at t={t}s")
_NEVER_STOPS = (", keeps moving until the end", ", is still moving at the end", ", never comes to rest")
_STAYS = (", stays at rest throughout", ", never moves", ", remains still the whole time")
_GROUND = (
    ", and stays grounded from {intervals}.",
    ", and touches the ground from {intervals}.",
    ", and is in contact with the floor from {intervals}.",
)
_NO_GROUND = (", and never touches the ground.", ", and stays off the ground.", ", and never meets the floor.")
_COLLIDES = ("Collides with {other} at t={t}s.", "Hits {other} at t={t}s.", "Makes contact with {other} at t={t}s.")
_VISIBLE = ("{name} visible in {k}/{n} frames", "{name} is seen in {k}/{n} frames", "{name} appears in {k}/{n} frames")
_LEAVES = ("leaves the view at t={t}s", "exits the frame at t={t}s", "goes out of view at t={t}s")
_ENTERS = ("enters the view at t={t}s", "comes into the frame at t={t}s", "becomes visible at t={t}s")
_HIDES = (  # no pixels while its centre is inside the picture: another object covers it, it did not leave
    "is hidden behind another object at t={t}s",
    "disappears behind another object at t={t}s",
    "is covered by another object at t={t}s",
)
_REAPPEARS = ("reappears at t={t}s", "comes out from behind another object at t={t}s", "is uncovered at t={t}s")
_SUMMARY_HITS = ("Interactions: {hits}.", "Summary of interactions: {hits}.", "Collisions: {hits}.")
_SUMMARY_NONE = (
    "Interactions: no collisions between objects.",
    "Summary of interactions: the objects never touch each other.",
    "Collisions: none.",
)
_REST_SUMMARY = (
    "{k} of {n} objects are at rest by the end.",
    "By the end, {k} of {n} objects have stopped.",
    "{k}/{n} objects end at rest.",
)


def _f(x: float, d: int = 2) -> str:
    return f"{x:.{d}f}"


def _pick(rng: np.random.Generator, options: tuple[str, ...]) -> str:
    return options[int(rng.integers(len(options)))]


def _intervals_text(intervals: list[tuple[float, float]]) -> str:
    parts = [f"{_f(a)}-{_f(b)}s" for a, b in intervals]
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]


def _shape_slots(obj) -> dict:
    if isinstance(obj, Box):
        return {"dims": " x ".join(_f(2 * s) for s in obj.size)}  # full edge lengths = 2 × half-extents
    if isinstance(obj, Sphere):
        return {"radius": _f(obj.radius)}
    assert isinstance(obj, Cylinder)
    return {"radius": _f(obj.radius), "height": _f(obj.height), "pose": ""}


def _cylinder_pose(orientation: np.ndarray) -> str:
    """'upright' when the cylinder's axis is within 45° of vertical at t=0, else 'lying'."""
    w, x, y, _ = orientation
    axis_z = 1 - 2 * (x * x + y * y)  # z component of the body z axis in the world
    return "upright" if abs(axis_z) >= np.cos(np.pi / 4) else "lying"


def reasoning_text(
    scene: Scene,
    rollout: Rollout,
    visible: np.ndarray,
    frame_times: np.ndarray,
    seed: int = 0,
    in_picture: np.ndarray | None = None,
) -> str:
    """The motion-reasoning text of a simulated scene.

    Args:
        scene: the scene (shape, size and mass of the objects).
        rollout: its simulation; every motion fact comes from here.
        visible: (F, N) bool per sampled frame, from `visibility(segmentation, N)`.
        frame_times: (F,) s, time of each sampled frame.
        seed: picks one paraphrase template per fact.
        in_picture: (F, N) bool, the object's centre projects inside the image (`centres_in_picture`): an object
            that has no pixels there is hidden behind another one, not out of view. None: every change of
            `visible` is told as leaving or entering the view.
    """
    n = len(scene.objects)
    visible = np.asarray(visible, dtype=bool)
    frame_times = np.asarray(frame_times, dtype=float)
    if visible.shape != (len(frame_times), n):
        raise ValueError(f"visible shape {visible.shape}: must be (frames, objects) = ({len(frame_times)}, {n})")
    inside = np.zeros_like(visible) if in_picture is None else np.asarray(in_picture, dtype=bool)
    if inside.shape != visible.shape:
        raise ValueError(f"in_picture shape {inside.shape}: must be the shape of visible, {visible.shape}")
    if not rollout.valid:
        raise ValueError(f"rollout is invalid ({rollout.reason}): no reasoning text for a diverged simulation")
    rng = np.random.default_rng(seed)
    lines = []
    for i, obj in enumerate(scene.objects):
        name = rollout.names[i]
        slots = {"Name": name[:1].upper() + name[1:], "mass": _f(obj.physics.mass), **_shape_slots(obj)}
        if isinstance(obj, Cylinder):
            slots["pose"] = _cylinder_pose(rollout.orientation[0, i])
        x, y, _ = position_words(rollout.position[0, i])
        z = BIN_WORDS["z"][position_bin(floor_heights(scene, rollout.position[0, i : i + 1])[0])]
        text = _pick(rng, _SHAPE[obj.type]).format(**slots) + _pick(rng, _POSITION).format(x=x, y=y, z=z)
        v0 = rollout.linear_velocity[0, i]
        dirs = direction_words(v0)
        rest = rollout.rest_time[i]
        spin = float(np.linalg.norm(rollout.angular_velocity[0, i]))
        if dirs:
            text += " " + _pick(rng, _MOVES).format(speed=_f(float(np.linalg.norm(v0))), dirs=" and ".join(dirs))
        elif spin > REST_ANGULAR:  # not "at rest": it turns (the flow shows it)
            text += " " + _pick(rng, _SPINS).format(spin=_f(spin))
        else:
            text += " " + _pick(rng, _STILL)
        if rest is None:
            text += _pick(rng, _NEVER_STOPS)
        elif rest == 0.0:
            text += _pick(rng, _STAYS)
        else:
            text += _pick(rng, _STOPS).format(t=_f(rest))
        ground = [(c.start, c.end) for c in rollout.contacts if c.a == name and c.b == "floor"]
        if ground:
            text += _pick(rng, _GROUND).format(intervals=_intervals_text(ground))
        else:
            text += _pick(rng, _NO_GROUND)
        for c in rollout.contacts:
            if c.a == name and c.b != "floor":
                text += " " + _pick(rng, _COLLIDES).format(other=c.b, t=_f(c.start))
        lines.append(text)

    lines.append("")
    seen = []
    for i, name in enumerate(rollout.names):
        vis = visible[:, i]
        sentence = _pick(rng, _VISIBLE).format(name=name, k=int(vis.sum()), n=len(vis))
        events = []
        for k in range(1, len(vis)):
            if vis[k - 1] and not vis[k]:
                events.append(_pick(rng, _HIDES if inside[k, i] else _LEAVES).format(t=_f(frame_times[k])))
            elif vis[k] and not vis[k - 1]:
                events.append(_pick(rng, _REAPPEARS if inside[k - 1, i] else _ENTERS).format(t=_f(frame_times[k])))
        seen.append(sentence + ("; " + ", ".join(events) if events else "") + ".")
    lines.append("Visibility: " + " ".join(seen))

    hits = [
        f"{c.a} and {c.b} at t={_f(c.start)}s"
        for c in rollout.contacts
        if c.b != "floor" and rollout.names.index(c.a) < rollout.names.index(c.b)
    ]
    summary = _pick(rng, _SUMMARY_HITS).format(hits="; ".join(hits)) if hits else _pick(rng, _SUMMARY_NONE)
    resting = sum(r is not None for r in rollout.rest_time)
    lines.append(summary + " " + _pick(rng, _REST_SUMMARY).format(k=resting, n=n))
    return "\n".join(lines)


def answer_target(scene_yaml: str) -> str:
    """The plain target: `<answer>YAML</answer>`."""
    return f"<answer>\n{scene_yaml.strip()}\n</answer>"


def think_target(reasoning: str, scene_yaml: str) -> str:
    """The reasoning target: `<think>REASONING</think>\\n\\n<answer>YAML</answer>`."""
    return f"<think>\n{reasoning.strip()}\n</think>\n\n{answer_target(scene_yaml)}"
