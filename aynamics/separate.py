"""Separate a scene's start: objects that start inside each other or the floor are moved apart, each as little as
MuJoCo's contacts say, before anything is simulated.

A model's scene often starts two objects at one position or a cylinder sunk into the floor. Deeper than
`simulate.MAX_START_OVERLAP` the simulation calls that an overlapping start and the rollout is invalid; shallower,
MuJoCo throws the objects apart in the first steps. `separate_start` moves every object of a contact deeper than
`tolerance` along the contact's normal (an object and the floor: the object by the whole depth; two objects:
each by half of it), finds the contacts at the new positions and repeats until none is deeper than `tolerance`.
Only positions change: orientations, velocities and the rest are kept, and objects without such a contact stay
where they are (one pushed into a third object moves that one in the next round).

    result = separate_start(scene)
    result.scene, result.moved  # the separated scene; {name: (dx, dy, dz) in m} of the objects moved

`aynamics predict --separate` prints a prediction separated; `aynamics.refine` starts from the better (by the
scorer) of a prediction and its separated start; `aynamics evaluate --separate` scores the responses separated
too (`separate_texts`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from aynamics.ranges import SceneError
from aynamics.scene import Scene, dump, from_items, is_whole, parse, require_scene
from aynamics.scene_dump import to_items
from aynamics.simulate import MAX_START_OVERLAP, Template, deep_contacts, overlap_words, prepare_batch

TOLERANCE = 1e-3  # m: a contact this deep is left alone (objects resting on each other touch at ~0)
MAX_ROUNDS = 200  # rounds of pushes; two coincident objects part in one, chains of five in ~30


@dataclass(frozen=True)
class Separation:
    """A scene with its start separated.

    Attributes:
        scene: the scene, each overlapping object moved (only `state.position` changes).
        moved: name -> (dx, dy, dz) in m of each object moved, in the scene's order.
        rounds: rounds of pushes it took (0: nothing overlapped).
    """

    scene: Scene
    moved: dict[str, tuple[float, float, float]]
    rounds: int


def separate_start(scene: Scene, tolerance: float = TOLERANCE, max_rounds: int = MAX_ROUNDS) -> Separation:
    """The scene with objects that start inside each other or the floor pushed apart (see the module's text).

    Raises:
        ValueError: a bad `tolerance` or `max_rounds`; objects still overlapping deeper than
            `simulate.MAX_START_OVERLAP` after `max_rounds` rounds (shallower, the scene is returned as the rounds
            left it: the simulation accepts it), or pushed outside the scene language's ranges (named with the
            depth, or the field and value).
    """
    scene = require_scene(scene, "scene")
    if not (isinstance(tolerance, int | float) and math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance = {tolerance!r}: must be a finite number of metres > 0")
    if not (is_whole(max_rounds) and max_rounds >= 1):
        raise ValueError(f"max_rounds = {max_rounds!r}: must be a whole number >= 1")
    if not scene.objects:
        return Separation(scene, {}, 0)
    batch, tpl = prepare_batch([scene], scene.structure, nthread=1)
    model, data = batch.get_model(0), batch.get_data(0)
    pos = np.asarray(tpl.qpos_adr)[:, None] + np.arange(3)  # (N, 3) each free joint's position in qpos
    start = data.qpos[pos].copy()
    rounds = 0
    while (push := _pushes(model, data, tpl, tolerance)) is not None:
        if rounds == max_rounds:
            names = (*scene.names, "the floor")
            (i, j), depth = max(deep_contacts(data, tpl, tolerance).items(), key=lambda p: p[1][0])
            if depth[0] <= MAX_START_OVERLAP:  # a long chain halves slowly: what is left, the simulation accepts
                break
            raise ValueError(
                f"separate_start: objects still overlap after max_rounds = {max_rounds} rounds: "
                f"{overlap_words(names[i], names[j], depth[0])}"
            )
        data.qpos[pos] += push
        rounds += 1
    shift = data.qpos[pos] - start
    moved = {name: tuple(float(x) for x in d) for name, d in zip(scene.names, shift, strict=True) if np.any(d != 0)}
    if not moved:
        return Separation(scene, {}, 0)
    objects = tuple(
        o.model_copy(update={"state": o.state.model_copy(update={"position": tuple(float(x) for x in p)})})
        for o, p in zip(scene.objects, start + shift, strict=True)
    )
    try:  # validated again: a push may leave the position table's range
        separated = from_items(to_items(scene.model_copy(update={"objects": objects})))
    except SceneError as e:
        raise ValueError(f"separate_start: the separated scene is out of range: {e}") from None
    return Separation(separated, moved, rounds)


def separate_texts(texts: list[str]) -> list[str]:
    """Each model response's scene separated (`separate_start`) as canonical YAML; a response without a valid scene,
    or one that cannot be separated, is kept as it is (it scores as invalid again)."""
    out = []
    for text in texts:
        try:
            out.append(dump(separate_start(parse(text)).scene))
        except ValueError:  # no valid scene (a SceneError), or one that cannot be separated
            out.append(text)
    return out


def _pushes(model: mujoco.MjModel, data: mujoco.MjData, tpl: Template, tolerance: float):
    """(N, 3) the move of each object this round, or None when no contact is deeper than `tolerance`."""
    mujoco.mj_kinematics(model, data)
    mujoco.mj_collision(model, data)
    deepest = deep_contacts(data, tpl, tolerance)
    if not deepest:
        return None
    n = len(tpl.geom_ids)
    push = np.zeros((n, 3))
    for (i, j), (depth, normal) in deepest.items():
        if j == n:  # the floor does not move: the object leaves it by the whole depth
            push[i] -= depth * normal
        else:
            push[i] -= 0.5 * depth * normal
            push[j] += 0.5 * depth * normal
    return push
