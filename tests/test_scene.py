"""The scene language: parsing, validation errors, model-output extraction, canonical round trip."""

from __future__ import annotations

import math
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from aynamics import cli
from aynamics import scene as S
from aynamics import scene_dump as D
from aynamics import scene_text as T

ASSETS = Path(__file__).parent / "assets"
EXAMPLE = (ASSETS / "paper_example.yaml").read_text()


def test_paper_example_parses_with_documented_meaning():
    s = S.parse(EXAMPLE)
    assert s.names == ("box_0", "cylinder_0")
    box, cyl = s.objects
    assert isinstance(box, S.Box) and box.size == (1.0, 0.5, 0.4)
    assert box.state.orientation == (0.97, 0.0, 0.0, 0.23)
    assert box.physics.friction == (1.1, 0.3) and box.physics.damping == -4.0
    assert isinstance(cyl, S.Cylinder) and (cyl.radius, cyl.height) == (0.3, 0.5)
    assert s.camera.fovy == 45.0 and s.camera.orientation == 45.0 and s.camera.position == (0.0, -2.0, 3.5)
    assert s.gravity == (0.0, 0.0, -7.0)
    assert s.environment is None


def test_paper_example_round_trips_and_canonical_text_is_stable():
    s = S.parse(EXAMPLE)
    text = S.dump(s)
    assert S.parse(text) == s
    assert S.dump(S.parse(text)) == text
    # the canonical form keeps the paper's key order; only number formatting differs
    assert text.splitlines()[:4] == ["- type: box", "  name: box_0", "  size: [1.0, 0.5, 0.4]", "  state:"]
    assert "    damping: -4.0" in text and "  gravity: [0.0, 0.0, -7.0]" in text


def test_fewer_decimals_round_every_number_and_stay_valid():
    s = S.parse(EXAMPLE.replace("0.97, 0.0, 0.0, 0.23", "0.9701, 0.0, 0.0, 0.2427"))
    text = S.dump(s, decimals=1)
    assert "orientation: [1.0, 0.0, 0.0, 0.2]" in text and "damping: -4.0" in text
    assert S.parse(text).objects[0].state.orientation == (1.0, 0.0, 0.0, 0.2)
    assert S.dump(s, decimals=S.DECIMALS) == S.dump(s)
    with pytest.raises(ValueError, match="decimals = 5"):
        S.dump(s, decimals=5)


def test_quaternions_are_normalised_like_mujoco():
    """Any quaternion MuJoCo's compiler accepts names a rotation: [0.5, 0, 0, 0.5] is the same yaw as the unit one."""
    from aynamics import simulate

    half = S.parse(EXAMPLE.replace("0.97, 0.0, 0.0, 0.23", "0.5, 0.0, 0.0, 0.5"))
    unit = S.parse(EXAMPLE.replace("0.97, 0.0, 0.0, 0.23", "0.7071, 0.0, 0.0, 0.7071"))
    assert half.objects[0].state.orientation == (0.5, 0.0, 0.0, 0.5)  # kept as written: parse(dump(s)) == s
    tpl = simulate.template(half.structure)
    for x, y in zip(simulate.initial_qpos_qvel(half, tpl), simulate.initial_qpos_qvel(unit, tpl), strict=True):
        assert abs(x - y).max() < 1e-12  # the same initial state (this tipping box then amplifies 1e-16 to mm)
    with pytest.raises(S.SceneError, match=r"orientation = \[0.01, 0.0, 0.0, 0.05\]: must be a rotation quaternion"):
        S.parse(EXAMPLE.replace("0.97, 0.0, 0.0, 0.23", "0.01, 0.0, 0.0, 0.05"))


def test_a_quaternion_just_below_the_norm_bound_shows_a_norm_below_it():
    """[0.07071, 0.07071, 0, 0], read at 4 decimals as [0.0707, 0.0707, 0, 0], has norm 0.0707·√2 = 0.099985: it
    read "(norm 0.1 < 0.1)" at 3 digits."""
    with pytest.raises(S.SceneError) as err:
        S.parse(EXAMPLE.replace("0.97, 0.0, 0.0, 0.23", "0.07071, 0.07071, 0, 0"))
    assert "(norm 0.09998 < 0.1)" in str(err.value)
    with pytest.raises(S.SceneError, match=r"\(norm 0.05 < 0.1\)"):  # a short norm stays short
        S.parse(EXAMPLE.replace("0.97, 0.0, 0.0, 0.23", "0.05, 0, 0, 0"))


def test_defaults_names_and_gravity_filled_in():
    s = S.parse(
        """
- type: sphere
  radius: 0.2
  state: {position: [0, 0, 0.2]}
- type: sphere
  radius: 0.2
  state: {position: [1, 0, 0.2]}
- type: sphere
  name: sphere_0
  radius: 0.2
  state: {position: [2, 0, 0.2]}
- type: camera
  position: [0, -3, 3]
"""
    )
    # unnamed objects get {type}_{k}, skipping names already taken
    assert s.names == ("sphere_1", "sphere_2", "sphere_0")
    assert s.gravity == (0.0, 0.0, -9.81)
    assert s.objects[0].physics == S.Physics()


def test_extension_item_round_trips_and_is_absent_by_default():
    text = EXAMPLE + "- type: environment\n  floor_offset: 0.01\n  wind: [1, 0, 0]\n"
    s = S.parse(text)
    assert s.environment.floor_offset == 0.01 and s.environment.wind == (1.0, 0.0, 0.0)
    assert S.parse(S.dump(s)) == s
    assert "environment" not in S.dump(S.parse(EXAMPLE))


# --------------------------------------------------------------------------------------------
# Model output
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "wrap",
    [
        lambda y: f"<answer>{y}</answer>",
        lambda y: (
            f"<think>box_0 moves right and stops at t=0.4s.\n- type: box is tricky</think>\n\n<answer>\n{y}</answer>"
        ),
        lambda y: f"Here is the scene:\n```yaml\n{y}```\nHope this helps!",
        lambda y: f"Sure! The scene is:\n{y}\nThat is all.",
        lambda y: f"<think>reasoning</think><answer>{y}",  # unclosed answer runs to the end
    ],
)
def test_model_output_wrappers(wrap):
    assert S.parse(wrap(EXAMPLE)) == S.parse(EXAMPLE)


# --------------------------------------------------------------------------------------------
# Malformed and absurd input: one SceneError naming the path, through the API and the CLI
# --------------------------------------------------------------------------------------------
OK_BOX = "- type: box\n  name: b\n  size: [0.2, 0.2, 0.2]\n  state: {position: [0, 0, 0.2]}\n"
CAMERA = "- type: camera\n  position: [0, -3, 3]\n"


def _box(**fields) -> str:
    state = fields.pop("state", "{position: [0, 0, 0.2]}")
    physics = fields.pop("physics", "{mass: 1.0}")
    size = fields.pop("size", "[0.2, 0.2, 0.2]")
    return f"- type: box\n  name: b\n  size: {size}\n  state: {state}\n  physics: {physics}\n" + CAMERA


BILLION_LAUGHS = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}]\n"
    for i in range(20)
)

MALFORMED = [
    ("string size", _box(size="big"), "objects[0].size"),
    ("size not a list of 3", _box(size="[0.2, 0.2]"), "objects[0].size"),
    ("missing state", "- type: box\n  size: [0.2, 0.2, 0.2]\n" + CAMERA, "objects[0].state"),
    ("missing position", _box(state="{linear_velocity: [0, 0, 0]}"), "objects[0].state.position"),
    ("NaN", _box(state="{position: [0, .nan, 0.2]}"), "objects[0].state.position[1]"),
    ("inf", _box(physics="{mass: .inf}"), "objects[0].physics.mass"),
    ("negative mass", _box(physics="{mass: -2}"), "objects[0].physics.mass"),
    ("zero mass", _box(physics="{mass: 0}"), "objects[0].physics.mass"),
    ("zero size", _box(size="[0.2, 0, 0.2]"), "objects[0].size[1]"),
    ("negative radius", "- type: sphere\n  radius: -1\n  state: {position: [0, 0, 1]}\n" + CAMERA, "objects[0].radius"),
    ("unknown type", "- type: pyramid\n  size: 1\n" + OK_BOX + CAMERA, "items[0].type"),
    ("type as a list", "- type: [box]\n  size: 1\n" + OK_BOX + CAMERA, "items[0].type"),  # unhashable: no TypeError
    ("type as a mapping", OK_BOX + "- type: {camera: 1}\n" + CAMERA, "items[1].type"),
    ("missing type", OK_BOX + "- size: 1\n" + CAMERA, "items[1].type"),
    ("unknown field", _box(physics="{mass: 1, bounciness: 3}"), "objects[0].physics.bounciness"),
    ("duplicate names", OK_BOX + OK_BOX + CAMERA, "objects[1].name"),
    ("two cameras", OK_BOX + CAMERA + CAMERA, "camera"),
    ("no camera", OK_BOX, "camera"),
    ("no objects", CAMERA, "objects"),
    ("huge velocity", _box(state="{position: [0, 0, 0.2], linear_velocity: [1e6, 0, 0]}"), "linear_velocity[0]"),
    ("zero quaternion", _box(state="{position: [0, 0, 0.2], orientation: [0, 0, 0, 0]}"), "state.orientation"),
    ("quaternion past 1", _box(state="{position: [0, 0, 0.2], orientation: [5, 0, 0, 0]}"), "state.orientation[0]"),
    (
        "quaternion overflowing the norm",
        _box(state="{position: [0, 0, 0.2], orientation: [1" + "0" * 155 + ", 1" + "0" * 155 + ", 0, 0]}"),
        "state.orientation[0]",
    ),
    ("repeated key", "- type: sphere\n  radius: 0.2\n  radius: 1.4\n" + CAMERA, "yaml"),
    ("repeated key in flow style", _box(state="{position: [0, 0, 0.2], position: [0, 0, 5]}"), "yaml"),
    ("object named floor", OK_BOX.replace("name: b", "name: floor") + CAMERA, "objects[0].name"),
    ("bool as number", _box(physics="{mass: yes}"), "objects[0].physics.mass"),
    ("quoted number", _box(physics="{mass: '1.0'}"), "objects[0].physics.mass"),
    ("friction with one value", _box(physics="{friction: [0.5]}"), "objects[0].physics.friction"),
    ("bad name", OK_BOX.replace("name: b", "name: 'two words'") + CAMERA, "objects[0].name"),
    ("fovy out of range", OK_BOX + "- type: camera\n  fovy: 500\n  position: [0, -3, 3]\n", "camera.fovy"),
    ("absurd gravity", OK_BOX + CAMERA + "- type: gravity\n  gravity: [0, 0, -1000]\n", "gravity.gravity[2]"),
    ("item not a mapping", "- just a string\n" + OK_BOX + CAMERA, "items[0]"),
    ("top level mapping", "type: box\nsize: [1, 1, 1]\n", "scene"),
    ("python tag", "- !!python/object/apply:os.system ['echo pwned']\n", "yaml"),
    ("alias bomb", BILLION_LAUGHS, "yaml"),
    ("empty text", "", "text"),
    ("whitespace only", "   \n\n", "text"),
    ("binary garbage", b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe", "text"),
    ("yaml syntax error", "- type: box\n  size: [1, 2\n", "yaml"),
    ("too many objects", "".join(OK_BOX.replace("name: b", f"name: b{i}") for i in range(40)) + CAMERA, "objects"),
]


@pytest.mark.parametrize("text, path", [m[1:] for m in MALFORMED], ids=[m[0] for m in MALFORMED])
def test_malformed_input_names_the_path(text, path):
    with pytest.raises(S.SceneError) as err:
        S.parse(text)
    assert any(p.path.endswith(path) or p.path == path for p in err.value.problems), str(err.value)


@pytest.mark.parametrize("text, path", [m[1:] for m in MALFORMED], ids=[m[0] for m in MALFORMED])
def test_malformed_input_through_the_cli_exits_2_without_traceback(text, path, tmp_path, capsys):
    f = tmp_path / "scene.yaml"
    f.write_bytes(text if isinstance(text, bytes) else text.encode())
    assert cli.main(["simulate", str(f), "--json"]) == 2
    err = capsys.readouterr().err
    assert path in err and "Traceback" not in err
    assert err.count("\n") == 1  # one paragraph


def test_any_value_swapped_for_junk_gives_a_scene_error_or_a_scene():
    """Model output puts anything anywhere: every `key: value` line of the paper's example with its value
    replaced by a list, mapping, null, non-finite number, string, date, ... parses or raises SceneError, never
    another exception (`type: [box]` once raised TypeError: a list does not hash)."""
    junk = ["[box]", "{a: 1}", "null", "", "[]", "[[1, 2], [3]]", "1e999", "1.0e+999", "1" + "0" * 400, ".nan"]
    junk += ["'str'", "yes", "2001-12-14", "1" * 5000, "[" * 3000 + "]" * 3000]
    lines = EXAMPLE.splitlines()
    tried = 0
    for i, line in enumerate(lines):
        if ":" not in line or line.lstrip().startswith("#"):
            continue
        key = line.split(":", 1)[0]
        for value in junk:
            text = "\n".join([*lines[:i], f"{key}: {value}", *lines[i + 1 :]])
            try:
                S.parse(text)
            except S.SceneError:
                pass
            tried += 1
    assert tried > 200


def test_all_problems_reported_at_once():
    text = _box(size="[-1, 0.2, 0.2]", physics="{mass: -2, damping: 99}", state="{position: [0, 0, 50]}")
    with pytest.raises(S.SceneError) as err:
        S.parse(text)
    paths = {p.path for p in err.value.problems}
    assert paths == {
        "objects[0].size[0]",
        "objects[0].physics.mass",
        "objects[0].physics.damping",
        "objects[0].state.position[2]",
    }
    assert "objects[0].physics.mass = -2: must be > 0" in str(err.value)


@pytest.mark.parametrize(
    ("size", "message"),
    [
        ("[]", "objects[0].size = []: must have 3 values, got 0"),
        ("[0.2]", "objects[0].size = [0.2]: must have 3 values, got 1"),
        ("[0.2, 0.2, 0.2, 0.2]", "objects[0].size = [0.2, 0.2, 0.2, 0.2]: must have 3 values, got 4"),
    ],
)
def test_a_vector_of_the_wrong_length_is_one_problem_with_its_length(size, message):
    """A box's size needs 3 half-extents: `[]` is one problem (pydantic reports each of the 3 missing elements),
    naming how many it must have and how many it has."""
    with pytest.raises(S.SceneError) as err:
        S.parse(_box(size=size))
    assert [str(p) for p in err.value.problems] == [message]


def test_an_item_or_scene_of_the_wrong_kind_is_shown_with_its_kind():
    """The value itself is shown (not '<list>'), and its kind named."""
    with pytest.raises(S.SceneError) as err:
        S.parse("a: 1\n")
    assert (
        str(err.value)
        == "invalid scene (1 problem): scene = {'a': 1}: must be a YAML list of items (- type: ...), got a mapping"
    )
    with pytest.raises(S.SceneError) as err:
        S.parse("- [1, 2]\n" + OK_BOX + CAMERA)
    assert [str(p) for p in err.value.problems] == ["items[0] = [1, 2]: must be a mapping with a 'type' key, got list"]
    with pytest.raises(S.SceneError, match=r"^invalid scene \(1 problem\): text: must be a string, got int$"):
        S.parse(12)


def test_alias_bomb_is_refused_quickly():
    t = time.perf_counter()
    with pytest.raises(S.SceneError, match="aliases are not allowed"):
        S.parse(BILLION_LAUGHS)
    assert time.perf_counter() - t < 1.0


def test_missing_file_is_a_scene_error(tmp_path):
    with pytest.raises(S.SceneError, match="No such file"):
        S.load(str(tmp_path / "nope.yaml"))


def test_a_file_too_large_is_named_with_its_size(tmp_path):
    """Only 4 × MAX_TEXT_CHARS + 1 bytes are read, so a file of 2-byte characters was refused as 'not UTF-8' when
    the read stopped inside one, or by the characters read; it is refused by its size (1 000 021 bytes: the 21
    bytes of `- type: box\n  name: ` and `\n`, and 500 000 two-byte é)."""
    big = tmp_path / "big.yaml"
    big.write_text("- type: box\n  name: " + "é" * 500_000 + "\n", encoding="utf-8")
    with pytest.raises(S.SceneError) as err:
        S.load(str(big))
    assert str(err.value.problems[0]) == (
        f"file = '{big}': too large: 1000021 bytes, and a scene is at most {S.MAX_TEXT_CHARS} characters"
    )


def test_unreadable_characters_are_located_by_line_and_column():
    """A control character in the third line, after a line of 2-byte characters (PyYAML's C loader gives its
    offset in bytes, 37 here, the Python one in characters, 32; a `*` in a comment sends the text to the Python
    one), and a lone surrogate (no UTF-8 form) in the second line."""
    for comment in ("", "  # *\n"):
        with pytest.raises(S.SceneError) as err:
            S.parse("- type: box\n  name: ééééé\n  x: a\x07b\n" + comment)
        assert re.fullmatch(
            r"yaml: unacceptable character #x0007: (control|special) characters are not allowed \(line 3, column 7\)",
            str(err.value.problems[0]),
        )
    with pytest.raises(S.SceneError) as err:
        S.parse("- type: box\n  name: a\ud800b\n")
    assert str(err.value.problems[0]) == (
        "text: contains a lone surrogate character '\\ud800' (line 2, column 10): not valid Unicode text"
    )


def test_cli_subprocess_reports_invalid_scene_cleanly(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text(_box(physics="{mass: -2}"))
    p = subprocess.run(
        [sys.executable, "-m", "aynamics.cli", "simulate", str(f), "--json"], capture_output=True, text=True
    )
    assert p.returncode == 2
    assert "objects[0].physics.mass = -2: must be > 0" in p.stderr and "Traceback" not in p.stderr


def test_cli_usage_error_exits_2(capsys):
    assert cli.main(["simulate"]) == 2
    assert cli.main(["no-such-command"]) == 2
    assert "Traceback" not in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# Property-based round trip
# --------------------------------------------------------------------------------------------
def _in(key: str, i: int = 0):
    lo, hi = S.RANGES[key].bounds(3)
    return st.floats(lo[i], hi[i], allow_nan=False)


def _vec(key: str, n: int):
    return st.tuples(*[_in(key, i) for i in range(n)]).map(list)


_state = st.fixed_dictionaries(
    {
        "position": _vec("state.position", 3),
        "orientation": st.tuples(*[st.floats(-1, 1)] * 4)
        .filter(lambda q: sum(x * x for x in q) > 0.05)
        .map(lambda q: [x / sum(y * y for y in q) ** 0.5 for x in q]),
        "linear_velocity": _vec("state.linear_velocity", 3),
        "angular_velocity": _vec("state.angular_velocity", 3),
    }
)
_physics = st.fixed_dictionaries(
    {"friction": _vec("physics.friction", 2), "mass": _in("physics.mass"), "damping": _in("physics.damping")},
    optional={"restitution": _in("physics.restitution")},
)
_object = st.one_of(
    st.fixed_dictionaries({"type": st.just("box"), "size": _vec("box.size", 3), "state": _state, "physics": _physics}),
    st.fixed_dictionaries(
        {"type": st.just("sphere"), "radius": _in("sphere.radius"), "state": _state, "physics": _physics}
    ),
    st.fixed_dictionaries(
        {
            "type": st.just("cylinder"),
            "radius": _in("cylinder.radius"),
            "height": _in("cylinder.height"),
            "state": _state,
            "physics": _physics,
        }
    ),
)
_camera = st.fixed_dictionaries(
    {
        "type": st.just("camera"),
        "fovy": _in("camera.fovy"),
        "orientation": _in("camera.orientation"),
        "position": _vec("camera.position", 3),
    }
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(objects=st.lists(_object, min_size=1, max_size=5), camera=_camera, gravity=_vec("gravity.gravity", 3))
def test_round_trip_random_scenes(objects, camera, gravity):
    s = S.from_items([*objects, camera, {"type": "gravity", "gravity": gravity}])
    text = S.dump(s)
    assert S.parse(text) == s
    assert S.dump(S.parse(text)) == text


def test_readme_holds_the_range_table():
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    assert S.ranges_markdown() in readme, "README's scene-format table is stale: paste `aynamics ranges --markdown`"


def test_dump_without_names_keeps_the_scene():
    """Default names are left out and filled back in; a scene with any other name keeps every name."""
    items = S.to_items(S.parse(EXAMPLE))  # box_0, cylinder_0, camera, gravity
    second_box = {k: v for k, v in items[0].items() if k != "name"}
    scene = S.from_items([items[0], items[1], second_box, *items[2:]])
    assert scene.names == ("box_0", "cylinder_0", "box_1") == S.default_names(scene.structure)
    short = S.dump(scene, names=False)
    assert "name:" not in short and S.parse(short) == scene
    renamed = S.from_items([items[0], {**items[1], "name": "can"}, second_box, *items[2:]])
    assert S.dump(renamed, names=False) == S.dump(renamed) and "name: can" in S.dump(renamed)


def test_dump_objects_last_writes_camera_and_gravity_first():
    scene = S.parse(EXAMPLE)  # box_0, cylinder_0, camera, gravity
    text = S.dump(scene, objects_last=True)
    assert [line for line in text.splitlines() if line.startswith("- ")] == [
        "- type: camera",
        "- type: gravity",
        "- type: box",
        "- type: cylinder",
    ]
    assert S.parse(text) == scene and sorted(text.splitlines()) == sorted(S.dump(scene).splitlines())


def _load_with(text, loader):
    try:
        return yaml.load(text, Loader=loader)  # noqa: S506 - the two safe loaders compared
    except yaml.YAMLError as e:
        return type(e).__name__


@pytest.mark.skipif(T._FAST_LOADER is None, reason="PyYAML built without libyaml")
@pytest.mark.parametrize("text", [m[1] for m in MALFORMED if isinstance(m[1], str)] + [OK_BOX + CAMERA])
def test_fast_loader_reads_what_the_safe_python_loader_reads(text):
    # libyaml is used for texts without anchors or aliases: the same data (or the same error) as the checked loader
    if "&" in text or "*" in text:
        assert T._loader_for(text) is T._NoAliasLoader
    else:
        assert T._loader_for(text) is T._FAST_LOADER
        assert _load_with(text, T._FAST_LOADER) == _load_with(text, T._NoAliasLoader)


def test_text_with_an_ampersand_takes_the_checked_loader():
    text = "# boxes & cylinders\n" + OK_BOX + CAMERA
    assert T._loader_for(text) is T._NoAliasLoader
    assert S.parse(text) == S.parse(OK_BOX + CAMERA)


@pytest.mark.parametrize(
    "text",
    ["[" * 30_000 + "]" * 30_000, "- " * 30_000 + "x", "{a: " * 20_000 + "1" + "}" * 20_000],
    ids=["flow lists", "block lists", "flow mappings"],
)
def test_deep_nesting_is_a_scene_error_not_a_crash(text):
    """~25 000 nested levels crashed libyaml's C loader (a segmentation fault took the process down, score and
    refine runs included); such texts take the Python loader, which reports the depth."""
    assert len(text) < S.MAX_TEXT_CHARS and T._loader_for(text) is T._NoAliasLoader
    with pytest.raises(S.SceneError, match="nested too deeply"):
        S.load_yaml(text)


def test_deep_flow_nesting_is_refused_at_once_naming_where():
    """PyYAML's Python scanner walks every open `[` at each token: 2 001 nested `[` (4 kB, a model's repetition loop)
    took 6 s to refuse and 300 lines of 300 (181 kB) 18 s, per parse (`evaluate_texts` parses a response 4 times).
    More than 32 levels are refused before loading; the 33rd `[` is at column 33, or 35 after `- `."""
    cases = [("[" * 2001 + "]" * 2001, 1, 33), (("- " + "[" * 300 + "1" + "]" * 300 + "\n") * 300, 1, 35)]
    cases.append((OK_BOX + "  # " + "[" * 40 + "\n" + CAMERA, 5, 37))  # in a comment too: 37 = 4 + 33
    for text, line, column in cases:
        t = time.perf_counter()
        with pytest.raises(S.SceneError) as err:
            S.parse(text)
        assert time.perf_counter() - t < 0.5
        assert str(err.value) == (
            f"invalid scene (1 problem): yaml: nested too deeply: more than 32 levels of [ and {{ "
            f"(line {line}, column {column})"
        )
    with pytest.raises(
        S.SceneError, match=r"items\[0\] = \[\[\[.*\]\]\]: must be a mapping with a 'type' key, got list"
    ):  # 32 levels are read (and then refused)
        S.parse("[" * 32 + "]" * 32)
    flow = "[{type: box, size: [0.2, 0.2, 0.2], state: {position: [0, 0, 0.2]}}, {type: camera, position: [0, -3, 3]}]"
    assert S.parse(flow) == S.parse(OK_BOX.replace("name: b", "name: box_0") + CAMERA)  # 3 levels: a scene


def test_numbers_are_read_as_yaml_1_2():
    """`1e-1`, `2E5`, `1.0e5` are numbers (YAML 1.1 read them as strings: "must be a number, got str"); `1:00` is
    not 60 (1.1's base 60) and `010` is 10, not octal 8 (`09` was an unreadable octal); `0x1F` and `0o17` are 31
    and 15, as in YAML 1.2. Both loaders agree."""
    text = "a: 1e-1\nb: 2E5\nc: 1.0e5\nd: 1:00\ne: 0x1F\nf: 10\ng: -.5\nh: .inf\ni: true\nj: 010\nk: 09\nl: 0o17\n"
    want = {"a": 0.1, "b": 2e5, "c": 1e5, "d": "1:00", "e": 31, "f": 10, "g": -0.5, "h": math.inf, "i": True}
    want |= {"j": 10, "k": 9, "l": 15}
    assert S.load_yaml(text) == want and yaml.load(text, Loader=T._NoAliasLoader) == want  # noqa: S506
    box = OK_BOX + "  physics: {mass: 1e-1}\n" + CAMERA
    assert S.parse(box).objects[0].physics.mass == pytest.approx(0.1)
    with pytest.raises(S.SceneError, match=r"camera\.fovy.*number"):
        S.parse(OK_BOX + "- type: camera\n  fovy: 1:00\n")


def test_only_plain_yaml_types_are_read():
    """`!!set {1.0, 0.5, 0.4}` was read as a reordered size and `!!binary Ym94XzA=` as the name box_0: both tags are
    refused by name, in both loaders; a date-like value is a string the field then names."""
    for loader in (T._NoAliasLoader, T._FAST_LOADER):
        for text, tag in (("a: !!set {1.0, 0.5}\n", "set"), ("a: !!binary Ym94XzA=\n", "binary")):
            with pytest.raises(yaml.YAMLError, match=f"constructor for the tag 'tag:yaml.org,2002:{tag}'"):
                yaml.load(text, Loader=loader)  # noqa: S506
    with pytest.raises(S.SceneError, match=r"yaml: refused YAML tag: .*tag:yaml.org,2002:set' \(line 3"):
        S.parse(OK_BOX.replace("size: [0.2, 0.2, 0.2]", "size: !!set {0.2, 0.3, 0.4}") + CAMERA)
    assert S.load_yaml("a: 2024-01-01\n") == {"a": "2024-01-01"}


def test_prose_of_blank_lines_is_read_in_linear_time():
    """A text of 200 000 lines, blank but for the first, took 35 s to be found no scene (the `- type:` search
    backtracked over every blank line for each); the same message comes at once."""
    t = time.perf_counter()
    with pytest.raises(S.SceneError, match="must be a YAML list of items"):
        S.parse("a\n" + "\n" * 199_990)
    assert time.perf_counter() - t < 5.0
    split_items = S.dump(S.parse(OK_BOX + CAMERA)).replace("- type:", "-\n  type:")  # `-` alone, then the keys
    assert S.parse(f"The scene:\n{split_items}\nThat's all.") == S.parse(OK_BOX + CAMERA)


def test_the_message_names_the_first_problems_and_counts_the_rest():
    """45 000 bad items made a 2.7 MB message (and a reward `reason` as long): it names 20, every one stays in
    `problems`."""
    with pytest.raises(S.SceneError) as err:
        S.parse("- 1\n" * 45_000)
    assert len(err.value.problems) == 45_002 and len(str(err.value)) < 2_000
    assert str(err.value).startswith(
        "invalid scene (45002 problems): items[0] = 1: must be a mapping with a 'type' key, got int"
    )
    assert str(err.value).endswith("; and 44982 more")


def test_unhashable_key_is_not_called_a_tag():
    with pytest.raises(S.SceneError, match="found unhashable key") as err:
        S.load_yaml("[a]: 1\n")
    assert "tag" not in str(err.value)


def test_whole_numbers_at_zero_decimals_keep_their_digits():
    """`dump(decimals=0)` wrote 10.0 as `1` and 0.0 as an empty value (trailing zeros stripped without a point)."""
    assert [D._num(x, 0) for x in (10.0, 0.0, -0.2, 250.0)] == ["10", "0", "0", "250"]
    assert [D._num(x) for x in (10.0, 0.0, -0.0, 0.25)] == ["10.0", "0.0", "0.0", "0.25"]


def test_load_counts_characters_not_bytes(tmp_path):
    """A valid file of non-ASCII text longer than MAX_TEXT_CHARS bytes but not characters loads (it was cut at
    MAX_TEXT_CHARS + 1 bytes, mid-character: "not UTF-8 text")."""
    text = OK_BOX + CAMERA + "# " + "é" * (S.MAX_TEXT_CHARS // 2 + 100) + "\n"
    assert len(text) < S.MAX_TEXT_CHARS < len(text.encode())
    path = tmp_path / "accents.yaml"
    path.write_text(text, encoding="utf-8")
    assert S.load(str(path)) == S.parse(OK_BOX + CAMERA)


def test_load_reads_model_output_files(tmp_path):
    """A file holding a model's response (tags, or prose around a fence) loads as `parse` reads the same text:
    its bytes are decoded and checked, not parsed as YAML first (that refused every wrapped file)."""
    for k, text in enumerate(
        [
            f"<think>one box</think>\n<answer>\n{OK_BOX}{CAMERA}</answer>\n",
            f"Here is the scene:\n```yaml\n{OK_BOX}{CAMERA}```\nDone.\n",
        ]
    ):
        path = tmp_path / f"response{k}.txt"
        path.write_text(text, encoding="utf-8")
        assert S.load(str(path)) == S.parse(OK_BOX + CAMERA)
    (tmp_path / "binary").write_bytes(b"- type: box\x00\n")
    with pytest.raises(S.SceneError, match="NUL bytes"):
        S.load(str(tmp_path / "binary"))


def test_default_names_skip_every_taken_name():
    """Chosen names box_1 and box_0, then an unnamed box: box_0 and box_1 are both taken, so it gets box_2."""
    s = S.parse(
        OK_BOX.replace("name: b", "name: box_1")
        + OK_BOX.replace("name: b", "name: box_0")
        + OK_BOX.replace("  name: b\n", "")
        + CAMERA
    )
    assert s.names == ("box_1", "box_0", "box_2")


def test_last_answer_block_is_parsed():
    """Of two <answer> blocks the last is the scene: an invalid first one (`type: nope`) does not matter."""
    assert S.parse(f"<answer>- type: nope\n</answer><answer>{OK_BOX}{CAMERA}</answer>") == S.parse(OK_BOX + CAMERA)


def test_field_defaults_pinned():
    """A box with only size and position, a camera with only position: the README's defaults are filled in:
    friction [0.5, 0] (no rolling resistance), mass 1 kg, damping -4, orientation [1, 0, 0, 0], zero velocities,
    no extension fields; camera fovy 45 and tilt 45 degrees; gravity [0, 0, -9.81]; no environment item."""
    s = S.parse("- {type: box, size: [0.2, 0.2, 0.2], state: {position: [0, 0, 0.2]}}\n" + CAMERA)
    box = s.objects[0]
    assert box.physics.friction == (0.5, 0.0) and box.physics.mass == 1.0 and box.physics.damping == -4.0
    assert box.physics.restitution is None and box.physics.magnus is None and box.physics.friction_slope is None
    assert box.state.orientation == (1.0, 0.0, 0.0, 0.0)
    assert box.state.linear_velocity == box.state.angular_velocity == (0.0, 0.0, 0.0)
    assert s.camera.fovy == 45.0 and s.camera.orientation == 45.0
    assert s.gravity == (0.0, 0.0, -9.81) and s.environment is None


def test_object_count_limit_is_32():
    """MAX_OBJECTS = 32: 32 objects parse, 33 give one problem `objects = 33: at most 32 objects`."""
    boxes = [OK_BOX.replace("name: b", f"name: b{i}") for i in range(33)]
    assert len(S.parse("".join(boxes[:32]) + CAMERA).objects) == 32
    with pytest.raises(S.SceneError, match="objects = 33: at most 32 objects"):
        S.parse("".join(boxes) + CAMERA)


def test_text_length_limit_is_inclusive():
    """MAX_TEXT_CHARS characters load (a YAML comment: None); one more is refused as too long."""
    assert S.load_yaml("#" * S.MAX_TEXT_CHARS) is None
    with pytest.raises(S.SceneError, match="too long"):
        S.load_yaml("#" * (S.MAX_TEXT_CHARS + 1))


def test_quaternion_norm_limit_is_inclusive():
    """A norm of exactly MIN_QUATERNION_NORM = 0.1 names a rotation (the table: "norm must be ≥ 0.1"):
    [0.06, 0, 0, 0.08] has norm √(0.0036 + 0.0064) = 0.1 and is kept as written; [0.0999, 0, 0, 0] is refused."""
    box = "- {type: box, size: [0.2, 0.2, 0.2], state: {position: [0, 0, 0.2], orientation: [%s, 0, 0, %s]}}\n"
    assert S.parse(box % (0.06, 0.08) + CAMERA).objects[0].state.orientation == (0.06, 0.0, 0.0, 0.08)
    with pytest.raises(S.SceneError, match=r"norm 0.0999 < 0.1"):
        S.parse(box % (0.0999, 0) + CAMERA)


def test_dump_at_zero_decimals_reparses():
    """decimals = 0 is allowed (-1 is not): whole numbers written without a point; friction 0.4 rounds to 0, the
    gravity -9.81 to -10; the text parses back to those values."""
    box = "- {type: box, size: [1, 2, 1], state: {position: [0, 1, 2]}, physics: {friction: [0.4, 0]}}\n"
    s = S.parse(box + CAMERA)
    text = S.dump(s, decimals=0)
    assert "  size: [1, 2, 1]" in text and "    friction: [0, 0]" in text
    back = S.parse(text)
    assert back.objects[0].size == (1.0, 2.0, 1.0) and back.objects[0].physics.friction == (0.0, 0.0)
    assert back.gravity == (0.0, 0.0, -10.0)
    with pytest.raises(ValueError, match="decimals = -1"):
        S.dump(s, decimals=-1)


def test_zero_mass_message():
    """Mass 0 is refused as not positive (not as out of range): `objects[0].physics.mass = 0: must be > 0`."""
    with pytest.raises(S.SceneError, match=r"objects\[0\]\.physics\.mass = 0: must be > 0"):
        S.parse(_box(physics="{mass: 0}"))


def test_a_first_item_after_other_text_on_its_line_is_kept():
    """A response whose first item follows other text on its line (a stray NUL from a model, 'Scene: - type:
    box') lost that object without a word (the line was cut as prose: one object fewer, a wrong count). It is read
    from its `-`; a `- type:` mentioned in prose before the list (not followed by indented keys) still is prose."""
    whole = S.parse(OK_BOX + CAMERA)
    assert S.parse("\x00" + OK_BOX + CAMERA) == whole
    assert S.parse("Here is the scene: " + OK_BOX + CAMERA + "That's all.") == whole
    assert S.parse("Each entry starts with - type: and a shape.\n\nThe scene:\n" + OK_BOX + CAMERA) == whole


def test_a_control_character_before_an_inline_items_keys_is_refused_not_the_item_dropped():
    """'Scene: - type: box' whose next line opens with a form feed (or another character YAML refuses) before its
    indented keys: the item was cut as prose and the rest parsed, one object fewer without a word (before the
    lines broke only where YAML breaks them, the form feed was read as a line break and both objects kept)."""
    for char in ("\x0c", "\x0b", "\x1c"):
        text = "Scene: " + OK_BOX.replace("\n", "\n" + char, 1) + OK_BOX.replace("name: b", "name: c") + CAMERA
        with pytest.raises(S.SceneError, match=rf"unacceptable character #x{ord(char):04x}: .*\(line 2, column 1\)"):
            S.parse(text)


def test_yaml_errors_after_a_leading_comment_name_the_lines_of_the_file(tmp_path):
    """A scene file that opens with a comment (or blank lines) is parsed from its first item: its YAML errors still
    name the file's lines, not lines counted from that item (a control character on line 4 was 'line 2')."""
    cases = [  # body, its error's line and column without and with two lines before it
        ("- type: box\n  name: a\x01b\n", "line 2, column 10", "line 4, column 10"),  # the reader's offset
        ("- type: box\n  name: x\n   bad: 1\n", "line 3, column 7", "line 5, column 7"),  # the loader's mark
        ("- type: box\r\n  name: x\r\n   bad: 1\r\n", "line 3, column 7", "line 5, column 7"),
    ]
    path = tmp_path / "scene.yaml"
    for body, alone, after in cases:
        with pytest.raises(S.SceneError, match=f"yaml: .*\\({alone}\\)"):
            S.parse(body)
        for head in ("# my scene\n\n", "\n\n"):
            path.write_bytes((head + body).encode())
            for parsed in (lambda: S.parse(head + body), lambda: S.load(str(path))):
                with pytest.raises(S.SceneError, match=f"yaml: .*\\({after}\\)"):
                    parsed()
    assert S.extract_yaml("# my scene\n\n- type: box\n  name: x\n   bad: 1\n") == "- type: box\n  name: x\n   bad: 1"


def test_yaml_errors_in_a_model_response_name_the_lines_of_the_response():
    """The YAML inside `<answer>`, a fence, or after `<think>` was parsed from the block's start, so its errors
    named lines counted from there (line 3 for the response's line 7). Lines break where YAML breaks them (also at
    a lone \\r); a form feed is refused as YAML refuses it, not read as a line break (it was: a scene with one
    went through)."""
    bad = "- type: box\n  name: x\n   bad: 1\n"  # the error is on the body's line 3, column 7
    cases = [
        (bad, 3),
        ("<think>I see\none box\n</think>\n<answer>\n" + bad + "</answer>", 7),
        ("<answer>old</answer>\n\n<answer>\n" + bad + "</answer>", 6),  # the last answer block
        ("Thinking...\n\n```yaml\n" + bad + "```\nDone.", 6),
        ("<think>a\nb</think>" + bad, 4),  # line 2 holds `</think>- type: box`
        ("a\rb\r" + bad.replace("\n", "\r"), 5),
        ("a\r\n\u2028" + bad, 5),  # YAML breaks at U+2028 too
    ]
    for text, line in cases:
        with pytest.raises(S.SceneError, match=f"yaml: mapping values .*\\(line {line}, column 7\\)"):
            S.parse(text)
    with pytest.raises(S.SceneError, match=r"unacceptable character #x000c: .*\(line 2, column 12\)"):
        S.parse("prose\n- type: box\x0c  name: b\n  size: [1, 1, 1]\n")


def test_a_list_indented_under_prose_is_read_as_written_at_the_margin():
    """A response that indents its YAML under a line of prose (each line 2 or 4 spaces in) gave "mapping values
    are not allowed": only the first line lost its indentation."""
    import textwrap

    whole = S.parse(OK_BOX + CAMERA)
    for pad in ("  ", "    ", "\t"):
        assert S.parse("Here is the scene:\n" + textwrap.indent(OK_BOX + CAMERA, pad) + "\nThat's all.") == whole
