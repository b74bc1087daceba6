"""The constant "average scene" predictor, the baseline every validation table shows beside the model: the most
common structure (object types in order) among the training scenes, with every number averaged.

    baseline = mean_scene_of_split(splits["train"])   # a Scene: e.g. one box at the mean pose, speed and mass
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from aynamics.scene import Scene, SceneError, from_items, parse, to_items


def _mean_value(values: list[Any]) -> Any:
    """Element-wise mean of numbers / equal-length lists / dicts; the most common value of anything else."""
    if all(isinstance(v, dict) for v in values):
        keys = Counter(k for v in values for k in v)
        return {k: _mean_value([v[k] for v in values if k in v]) for k, c in keys.items() if 2 * c > len(values)}
    if all(isinstance(v, list) for v in values) and len({len(v) for v in values}) == 1:
        return [_mean_value([v[i] for v in values]) for i in range(len(values[0]))]
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return float(np.mean(values))
    top = Counter(map(repr, values)).most_common(1)[0][0]
    return next(v for v in values if repr(v) == top)


def mean_scene(scenes: list[Scene]) -> Scene:
    """The "average scene": the most common structure (object types in order) with every number averaged.

    Averages run over the scenes of that structure, object k with object k; an optional field (restitution,
    the environment item) is kept when more than half of them have it. Quaternions are renormalised.
    """
    if not scenes:
        raise ValueError("mean_scene got 0 scenes")
    structure = Counter(s.structure for s in scenes).most_common(1)[0][0]
    same = [to_items(s) for s in scenes if s.structure == structure]
    by_type: dict[str, list[dict]] = {}
    for items in same:
        for k, item in enumerate(items):
            key = f"{k}:{item['type']}" if k < len(structure) else item["type"]
            by_type.setdefault(key, []).append(item)
    items = []
    for key, group in by_type.items():
        if 2 * len(group) <= len(same):
            continue
        item = _mean_value(group)
        if "state" in item:
            q = np.array(item["state"]["orientation"])
            norm = np.linalg.norm(q)
            item["state"]["orientation"] = (q / norm).tolist() if norm > 1e-6 else [1.0, 0.0, 0.0, 0.0]
        items.append(item)
    return from_items(items)


def mean_scene_of_split(split) -> Scene:
    """`mean_scene` of the `scene_yaml` column of a data-set split (records that do not parse are left out)."""
    scenes = []
    for text in split["scene_yaml"]:
        try:
            scenes.append(parse(text))
        except SceneError:
            continue
    return mean_scene(scenes)
