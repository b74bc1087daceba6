"""In-context examples for prompting off-the-shelf VLMs (the paper's recipe).

Three examples that together cover every primitive shape and the minimum and maximum of each parameter
range: a record covers the minimum (maximum) of a parameter when one of its values lies within `TOLERANCE`
of the span from the smallest (largest) value in the data set. The best triple is found exhaustively among
the records that cover the most targets; the targets no triple reaches are reported, not hidden.

    folder = write_in_context("data/synth")   # in_context/prompt.md, examples.json, frames and flow PNGs
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from aynamics.dataset_store import dataset_fps
from aynamics.scene import Box, Cylinder, Scene, Sphere, parse
from aynamics.simulate import FPS

TOLERANCE = 0.05  # share of a parameter's span counted as "at" its minimum or maximum
POOL = 40  # records kept for the exhaustive search over triples (40 choose 3 = 9,880)


def _per_object(get: Callable, kind: type | None = None) -> Callable[[Scene], list[float]]:
    return lambda s: [float(v) for o in s.objects if kind is None or isinstance(o, kind) for v in np.atleast_1d(get(o))]


# parameter -> values of one scene (a record may have several, one per object or component)
PARAMETERS: dict[str, Callable[[Scene], list[float]]] = {
    "num_objects": lambda s: [float(len(s.objects))],
    "box.size": _per_object(lambda o: o.size, Box),
    "sphere.radius": _per_object(lambda o: o.radius, Sphere),
    "cylinder.radius": _per_object(lambda o: o.radius, Cylinder),
    "cylinder.height": _per_object(lambda o: o.height, Cylinder),
    "physics.mass": _per_object(lambda o: o.physics.mass),
    "physics.friction.sliding": _per_object(lambda o: o.physics.friction[0]),
    "physics.friction.rolling": _per_object(lambda o: o.physics.friction[1]),
    "physics.damping": _per_object(lambda o: o.physics.damping),
    "physics.restitution": lambda s: [o.physics.restitution for o in s.objects if o.physics.restitution is not None],
    "state.speed": _per_object(lambda o: np.linalg.norm(o.state.linear_velocity)),
    "state.position.x": _per_object(lambda o: o.state.position[0]),
    "state.position.y": _per_object(lambda o: o.state.position[1]),
    "camera.fovy": lambda s: [s.camera.fovy],
    "camera.orientation": lambda s: [s.camera.orientation],
    "camera.position.z": lambda s: [s.camera.position[2]],
    "gravity.z": lambda s: [s.gravity[2]],
}
SHAPES = ("box", "sphere", "cylinder")


def coverage_targets(scenes: list[Scene]) -> tuple[list[str], list[set[str]]]:
    """All targets ('shape:box', 'min:physics.mass', ...) and the set each scene covers."""
    values = [{k: f(s) for k, f in PARAMETERS.items()} for s in scenes]
    targets = [f"shape:{k}" for k in SHAPES]
    covered: list[set[str]] = [{f"shape:{t}" for t in s.structure} for s in scenes]
    for key in PARAMETERS:
        flat = [v for vs in values for v in vs[key]]
        if not flat:
            continue
        lo, hi = min(flat), max(flat)
        tol = TOLERANCE * (hi - lo)
        targets += [f"min:{key}", f"max:{key}"]
        for k, vs in enumerate(values):
            if any(v <= lo + tol for v in vs[key]):
                covered[k].add(f"min:{key}")
            if any(v >= hi - tol for v in vs[key]):
                covered[k].add(f"max:{key}")
    return targets, covered


def select_in_context(scenes: list[Scene], k: int = 3) -> tuple[list[int], list[str]]:
    """Indices of the `k` scenes that together cover the most targets (ties: lowest indices), and what they miss."""
    if len(scenes) < k:
        raise ValueError(f"{len(scenes)} scenes: need at least k = {k} to choose in-context examples")
    targets, covered = coverage_targets(scenes)
    pool = sorted(range(len(scenes)), key=lambda i: (-len(covered[i]), i))[:POOL]
    best: tuple[int, tuple[int, ...]] = (-1, ())
    for combo in itertools.combinations(sorted(pool), k):
        n = len(set().union(*(covered[i] for i in combo)))
        if n > best[0]:
            best = (n, combo)
    chosen = list(best[1])
    union = set().union(*(covered[i] for i in chosen))
    return chosen, [t for t in targets if t not in union]


def write_in_context(
    dataset_path: str | os.PathLike, out: str | os.PathLike | None = None, split: str = "train"
) -> Path:
    """Choose three examples from a generated data set and write them prompt-ready.

    Writes `out` (default `<dataset>/in_context`): `example_{k}/frame_{ii}.png` and `flow_{ii}.png`,
    `examples.json` (image paths, YAML, reasoning, targets covered) and `prompt.md` (instructions, then each
    example's frames followed by its `<think>...</think>\\n\\n<answer>...</answer>` target).
    """
    from datasets import concatenate_datasets, load_from_disk

    dd = load_from_disk(str(dataset_path))
    ds = dd[split] if split in dd else dd[next(iter(dd))]
    if len(ds) < 3:  # a tiny data set: choose among every split
        ds = concatenate_datasets([dd[s] for s in dd])
    scenes = [parse(text) for text in ds["scene_yaml"]]
    chosen, missed = select_in_context(scenes)
    folder = Path(out) if out is not None else Path(dataset_path) / "in_context"
    folder.mkdir(parents=True, exist_ok=True)
    examples = []
    shown = list(ds[int(chosen[0])]["frame_indices"]) if chosen else []
    fps = dataset_fps(dataset_path) or FPS  # what the examples show, from the data set (it said 10 at 30 FPS)
    lines = [
        "# In-context examples",
        "",
        f"Each example shows {len(shown)} frames of a video at {fps} FPS (video frames {shown}) and their optical",
        "flow, then the reasoning and the scene YAML. Answer a new video in the same format.",
        "",
    ]
    for n, i in enumerate(chosen):
        row = ds[int(i)]
        sub = folder / f"example_{n}"
        sub.mkdir(exist_ok=True)
        frames, flows = [], []
        for j, (im, fl) in enumerate(zip(row["rgb"], row["flow"], strict=True)):
            im.save(sub / f"frame_{j:02d}.png")
            fl.save(sub / f"flow_{j:02d}.png")
            frames.append(f"example_{n}/frame_{j:02d}.png")
            flows.append(f"example_{n}/flow_{j:02d}.png")
        covers = sorted(coverage_targets(scenes)[1][i])
        examples.append(
            {
                "index": row["index"],
                "frames": frames,
                "flow": flows,
                "scene_yaml": row["scene_yaml"],
                "reasoning": row["reasoning"],
                "target": row["target_think"],
                "covers": covers,
            }
        )
        lines += [f"## Example {n + 1}", "", "Frames: " + " ".join(f"![]({p})" for p in frames), ""]
        lines += ["Flow: " + " ".join(f"![]({p})" for p in flows), "", row["target_think"], ""]
    (folder / "examples.json").write_text(json.dumps({"examples": examples, "not_covered": missed}, indent=1))
    (folder / "prompt.md").write_text("\n".join(lines))
    return folder
