"""The scene language: YAML text <-> validated `Scene` <-> canonical YAML.

A scene is a YAML list of items, as written by the model (the ΔYNAMICS format):

    - type: box | sphere | cylinder   # objects, any number (at least one)
    - type: camera                    # exactly one
    - type: gravity                   # optional, default [0, 0, -9.81]
    - type: environment               # optional extension item (air, wind, floor), absent in the paper

Meaning of every field (units, frames) and its plausible range live in one table, `RANGES`
(`ranges.py`), which validation uses, the dataset sampler and CMA-ES bounds use later, and the README
reproduces (`aynamics ranges --markdown`). Text is read by `scene_text.py` (safe YAML, the YAML inside a
model's response), the records (`Scene` and its items) are `scene_records.py`'s and the canonical dump is
`scene_dump.py`'s; this module validates the parsed items into a `Scene` and reads scene files. It re-exports all
four, so that `scene.parse`, `scene.dump`, `scene.Scene` and `scene.RANGES` are one API.

    scene = parse(text)        # plain YAML, or model output with <think>/<answer> and stray text
    text = dump(scene)         # canonical: fixed key order, fixed decimals; parse(dump(s)) == s

Every problem in a text is reported at once in one `SceneError`, each as
`objects[1].physics.mass = -2.0: must be > 0`.
"""

from __future__ import annotations

import numbers
import os
from typing import Any

import numpy as np
from pydantic import ValidationError

# the range table and the errors, the records, the text reader and the dump are part of the scene language's API:
# scene.RANGES, scene.Scene, scene.dump etc.
from aynamics.ranges import NO_VALUE
from aynamics.ranges import RANGES as RANGES
from aynamics.ranges import Problem as Problem
from aynamics.ranges import Range as Range
from aynamics.ranges import SceneError as SceneError
from aynamics.ranges import ranges_markdown as ranges_markdown
from aynamics.scene_dump import default_names as default_names
from aynamics.scene_dump import dump as dump
from aynamics.scene_dump import is_default_name as is_default_name
from aynamics.scene_dump import to_items as to_items
from aynamics.scene_records import _ITEM_TYPES
from aynamics.scene_records import DECIMALS as DECIMALS
from aynamics.scene_records import DEFAULT_GRAVITY as DEFAULT_GRAVITY
from aynamics.scene_records import MAX_OBJECTS as MAX_OBJECTS
from aynamics.scene_records import OBJECT_TYPES as OBJECT_TYPES
from aynamics.scene_records import Box as Box
from aynamics.scene_records import Camera as Camera
from aynamics.scene_records import Cylinder as Cylinder
from aynamics.scene_records import Environment as Environment
from aynamics.scene_records import Gravity as Gravity
from aynamics.scene_records import Object as Object
from aynamics.scene_records import Physics as Physics
from aynamics.scene_records import Scene as Scene
from aynamics.scene_records import Sphere as Sphere
from aynamics.scene_records import State as State
from aynamics.scene_text import MAX_TEXT_CHARS as MAX_TEXT_CHARS
from aynamics.scene_text import checked_text, extract_with_list
from aynamics.scene_text import extract_yaml as extract_yaml
from aynamics.scene_text import load_yaml as load_yaml

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
            return NO_VALUE
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
        value = NO_VALUE if e["type"] == "missing" else e.get("input", NO_VALUE)
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
        raise SceneError([Problem("", NO_VALUE, "empty scene: no YAML items found")])
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
        problems.append(Problem("objects", NO_VALUE, "the scene needs at least one box, sphere or cylinder"))
    if n_obj > MAX_OBJECTS:
        problems.append(Problem("objects", n_obj, f"at most {MAX_OBJECTS} objects"))
    if counts["camera"] == 0:
        problems.append(Problem("camera", NO_VALUE, "the scene needs one camera item (- type: camera)"))
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


def parse(text: str | bytes) -> Scene:
    """Parse a scene from YAML text or a model response.

    Raises:
        SceneError: naming every problem (path, value, what is allowed).
    """
    if isinstance(text, bytes):  # a file's contents: decoded and checked, not parsed (it may wrap the YAML)
        text = checked_text(text)
    if not isinstance(text, str):
        raise SceneError([Problem("text", NO_VALUE, f"must be a string, got {_type_name(text)}")])
    if not text.strip():
        raise SceneError([Problem("text", NO_VALUE, "empty text: no YAML found")])
    body, data = extract_with_list(text)
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
