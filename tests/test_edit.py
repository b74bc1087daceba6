"""Physics editing: the instruction grammar on a table of cases, refusals, the LLM editor's checks, what-if files.

Expected values are worked out by hand from tests/assets/paper_example.yaml: box_0 has linear velocity
[4.3, 2.5, 0], position [-5, -0.3, 0.4], mass 1, friction [1.1, 0.3], damping -4; cylinder_0 has velocity
[-0.1, -0.5, 0], position [-0.5, 0.8, 0.3]; gravity is [0, 0, -7].
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from aynamics import cli
from aynamics import simulate as sim
from aynamics.edit import EditError, apply_instruction, diff, split_clauses
from aynamics.edit_llm import LLMEditor, build_messages, check_output, named_fields, outside
from aynamics.scene import dump, load, parse, to_items

ASSET = Path(__file__).parent / "assets" / "paper_example.yaml"


@pytest.fixture(scope="module")
def scene():
    return load(str(ASSET))


CASES = [
    # the paper's three edits
    ("reduce the x-velocity of box_0 by 80%", {"box_0.state.linear_velocity[0]": 0.86}),  # 4.3 × 0.2
    ("decrease gravity by 50%", {"gravity.gravity[2]": -3.5}),  # -7 × 0.5
    (
        "increase the y-velocity by 50%",  # every object: 2.5 × 1.5, -0.5 × 1.5
        {"box_0.state.linear_velocity[1]": 3.75, "cylinder_0.state.linear_velocity[1]": -0.75},
    ),
    # their kin
    ("set the mass of cylinder_0 to 2 kg", {"cylinder_0.physics.mass": 2.0}),
    ("set the mass of cylinder_0 to 500 g", {"cylinder_0.physics.mass": 0.5}),
    ("halve the friction of cylinder_0", {"cylinder_0.physics.friction[0]": 0.55}),
    ("double the rolling resistance of the box", {"box_0.physics.friction[1]": 0.6}),
    ("move box_0 0.5 m left", {"box_0.state.position[0]": -5.5}),  # left = -x
    ("move box_0 right by 20 cm", {"box_0.state.position[0]": -4.8}),
    ("move the cylinder 1 m away from the camera", {"cylinder_0.state.position[1]": 1.8}),  # away = +y
    ("move the cylinder 0.3 m toward the camera", {"cylinder_0.state.position[1]": 0.5}),
    ("move box_0 0.1 m up", {"box_0.state.position[2]": 0.5}),
    ("Reverse the x-velocity of box_0.", {"box_0.state.linear_velocity[0]": -4.3}),
    (
        "set the velocity of cylinder_0 to [1, 0, 0]",
        {"cylinder_0.state.linear_velocity[0]": 1.0, "cylinder_0.state.linear_velocity[1]": 0.0},
    ),
    ("stop box_0", {"box_0.state.linear_velocity[0]": 0.0, "box_0.state.linear_velocity[1]": 0.0}),
    ("set the damping of box_0 to 0.01 /s", {"box_0.physics.damping": -2.0}),  # log10(0.01)
    ("multiply the damping of box_0 by 10", {"box_0.physics.damping": -3.0}),  # rate 1e-4 × 10
    ("set the restitution of box_0 to 0.5", {"box_0.physics.restitution": 0.5}),  # absent before
    ("increase the x-velocity of box_0 by 0.7 m/s", {"box_0.state.linear_velocity[0]": 5.0}),
    (
        "decrease gravity by 50%; move box_0 1 m right",
        {"gravity.gravity[2]": -3.5, "box_0.state.position[0]": -4.0},
    ),
    # a quantity named with "of" (it was split into "field" of "view": helper-38)
    ("set the field of view to 60", {"camera.fovy": 60.0}),
    ("increase the field of view by 10%", {"camera.fovy": 49.5}),
    # a resting object keeps resting as its shape changes (box_0 [-5, -0.3, 0.4] of size [1, 0.5, 0.4] grew into
    # the floor: an overlapping start); cylinder_0 lies on its side at z 0.3 = its radius, so its height is level
    (
        "double the size of box_0",
        {"box_0.size[0]": 2.0, "box_0.size[1]": 1.0, "box_0.size[2]": 0.8, "box_0.state.position[2]": 0.8},
    ),
    ("double the radius of cylinder_0", {"cylinder_0.radius": 0.6, "cylinder_0.state.position[2]": 0.6}),
    ("set the height of cylinder_0 to 1", {"cylinder_0.height": 1.0}),
    (  # in the air (1 m up) it keeps its centre
        "move box_0 1 m up and halve its size",
        {"box_0.size[0]": 0.5, "box_0.size[1]": 0.25, "box_0.size[2]": 0.2, "box_0.state.position[2]": 1.4},
    ),
    # the camera's pose (at [0, -2, 3.5], 45 degrees from straight down): a what-if from another view
    ("move the camera 1 m back", {"camera.position[1]": -3.0}),
    ("move the camera up by 50 cm", {"camera.position[2]": 4.0}),
    (
        "put the camera at [1, -3, 2]",
        {"camera.position[0]": 1.0, "camera.position[1]": -3.0, "camera.position[2]": 2.0},
    ),
    ("set the camera height to 3 m", {"camera.position[2]": 3.0}),
    ("increase the height of the camera by 1 m", {"camera.position[2]": 4.5}),
    ("set the x-position of the camera to 1", {"camera.position[0]": 1.0}),
    ("raise the camera by 1 m", {"camera.position[2]": 4.5}),
    ("lower the camera by 50 cm", {"camera.position[2]": 3.0}),
    ("tilt the camera up by 10 degrees", {"camera.orientation": 55.0}),  # from straight down: toward the horizon
    (
        "move the camera 1 m back and tilt the camera down by 5",
        {"camera.position[1]": -3.0, "camera.orientation": 40.0},
    ),
    ("set the camera position to [0, -4]", {"camera.position[1]": -4.0}),  # [x, y]: its height kept
    ("set the position of box_0 to [1, 2]", {"box_0.state.position[0]": 1.0, "box_0.state.position[1]": 2.0}),
    # [x, y]: there on the floor plan, at its height (box_0 at [-5, -0.3, 0.3])
    ("put box_0 at [1, 2]", {"box_0.state.position[0]": 1.0, "box_0.state.position[1]": 2.0}),
    ("move the camera to [1, -3]", {"camera.position[0]": 1.0, "camera.position[1]": -3.0}),
    ("set the camera's tilt to 30 degrees", {"camera.orientation": 30.0}),
    ("increase the tilt by 10 degrees", {"camera.orientation": 55.0}),  # only the camera has a tilt
    ("set the orientation of the camera to 20", {"camera.orientation": 20.0}),
    ("move the camera 1 m back and double the mass of box_0", {"camera.position[1]": -3.0, "box_0.physics.mass": 2.0}),
    # 'it' / 'its' after a camera clause: the camera
    ("set the fov to 60 and move it 1 m back", {"camera.fovy": 60.0, "camera.position[1]": -3.0}),
    ("move the camera 1 m back and set its height to 4", {"camera.position[1]": -3.0, "camera.position[2]": 4.0}),
    (
        "set the field of view to 50 and increase its tilt by 10 degrees",
        {"camera.fovy": 50.0, "camera.orientation": 55.0},
    ),
    # an amount on a component adds along the axis, signs included (documented: no jump at zero)
    ("reduce the y-velocity of cylinder_0 by 0.2 m/s", {"cylinder_0.state.linear_velocity[1]": -0.7}),
    ("reduce the z-gravity by 2 m/s^2", {"gravity.gravity[2]": -9.0}),
    ("increase the z-velocity of box_0 by 1 m/s", {"box_0.state.linear_velocity[2]": 1.0}),
    # a rate added to the decay rate, not subtracted: log10(1e-4 + 1e-4) = log10(2e-4) = -3.69897
    ("increase the damping of box_0 by 0.0001 /s", {"box_0.physics.damping": -3.69897}),
    ("move the cylinder 0.2 m back", {"cylinder_0.state.position[1]": 0.6}),  # back = -y: 0.8 - 0.2
    # put / place an object of the scene somewhere moves it ("put a ball at ..." adds one)
    ("place box_0 at [1, 2, 0.4]", {"box_0.state.position[0]": 1.0, "box_0.state.position[1]": 2.0}),
    ("put the cylinder at [0, 0.8, 0.3]", {"cylinder_0.state.position[0]": 0.0}),
    # stop zeroes the spin too: the spin set first is gone again, so only the velocity changes
    (
        "set the spin of box_0 to [0, 0, 2]; stop box_0",
        {"box_0.state.linear_velocity[0]": 0.0, "box_0.state.linear_velocity[1]": 0.0},
    ),
    # everyday phrasings (they were "not understood"): a planet's gravity along gravity's direction (-7 -> -1.62),
    # "N times as ADJ", "ADJ-er by", "by a factor of K", clauses joined by "and", "it" / "its" for the object before
    ("moon gravity", {"gravity.gravity[2]": -1.62}),
    ("set the gravity to that of mars", {"gravity.gravity[2]": -3.71}),
    # weightless (they were "not understood"; "remove gravity" a removal of no object)
    ("turn off gravity", {"gravity.gravity[2]": 0.0}),
    ("zero gravity and double the mass of box_0", {"gravity.gravity[2]": 0.0, "box_0.physics.mass": 2.0}),
    (
        "remove the gravity, then stop cylinder_0",  # its velocity [-0.1, -0.5, 0]
        {
            "gravity.gravity[2]": 0.0,
            "cylinder_0.state.linear_velocity[0]": 0.0,
            "cylinder_0.state.linear_velocity[1]": 0.0,
        },
    ),
    ("make everything weightless", {"gravity.gravity[2]": 0.0}),
    ("make it weightless", {"gravity.gravity[2]": 0.0}),  # no object before: 'it' is the scene
    ("turn off gravity then moon gravity", {"gravity.gravity[2]": -1.62}),  # no direction left: down (was refused)
    ("make the box twice as heavy", {"box_0.physics.mass": 2.0}),
    (
        "make cylinder_0 half as fast",  # [-0.1, -0.5, 0] × 0.5
        {"cylinder_0.state.linear_velocity[0]": -0.05, "cylinder_0.state.linear_velocity[1]": -0.25},
    ),
    ("make box_0 lighter by 20%", {"box_0.physics.mass": 0.8}),
    ("increase the mass of box_0 by a factor of 3", {"box_0.physics.mass": 3.0}),
    ("reduce the mass of cylinder_0 by a factor of 4", {"cylinder_0.physics.mass": 0.25}),
    ("double the mass of box_0 and halve its friction", {"box_0.physics.mass": 2.0, "box_0.physics.friction[0]": 0.55}),
    (
        "set the mass of box_0 to 2 kg and move it 0.5 m left",
        {"box_0.physics.mass": 2.0, "box_0.state.position[0]": -5.5},
    ),
    # "and" between objects still joins objects, not clauses
    ("increase the mass of box_0 and cylinder_0 by 10%", {"box_0.physics.mass": 1.1, "cylinder_0.physics.mass": 1.1}),
    # "massive" names the mass for the LLM editor's check too (named_fields gave none: the mass was "outside")
    ("make box_0 twice as massive", {"box_0.physics.mass": 2.0}),
    # "N times ADJ-er" (it was "not understood"): faster multiplies, slower / lighter divide, as English means them
    ("make box_0 3 times heavier", {"box_0.physics.mass": 3.0}),
    ("make the box twice lighter", {"box_0.physics.mass": 0.5}),
    (
        "make cylinder_0 four times slower",  # [-0.1, -0.5, 0] / 4
        {"cylinder_0.state.linear_velocity[0]": -0.025, "cylinder_0.state.linear_velocity[1]": -0.125},
    ),
    # a factor as a word ("value 'a factor of three' not understood")
    ("increase the mass of box_0 by a factor of three", {"box_0.physics.mass": 3.0}),
    ("multiply the mass of cylinder_0 by two", {"cylinder_0.physics.mass": 2.0}),
    ("multiply the x-velocity of box_0 by -1", {"box_0.state.linear_velocity[0]": -4.3}),
]


@pytest.mark.parametrize("instruction, expected", CASES, ids=[c[0] for c in CASES])
def test_instruction_table(scene, instruction, expected):
    result = apply_instruction(scene, instruction)
    got = {c.path: c.after for c in result.changes}
    assert got.keys() == expected.keys()
    for path, value in expected.items():
        assert got[path] == pytest.approx(value, abs=1e-4), path
    # the changes are exactly what the instruction names (the check the LLM editor relies on)
    assert not outside(result.changes, named_fields(instruction, scene))


def test_speed_by_amount_keeps_direction(scene):
    """|v| = sqrt(4.3² + 2.5²) = 4.974; +1 m/s along the same direction scales v by 5.974 / 4.974."""
    result = apply_instruction(scene, "increase the speed of box_0 by 1 m/s")
    v = np.array(result.scene.object("box_0").state.linear_velocity)
    assert np.linalg.norm(v) == pytest.approx(math.hypot(4.3, 2.5) + 1, abs=1e-3)
    assert v[0] / v[1] == pytest.approx(4.3 / 2.5, rel=1e-3)


REFUSED = [
    # several objects at one place overlap (the simulation refused them later, 'overlapping start')
    ("put box_0 and cylinder_0 at [1, 2, 0.4]", "puts 2 objects ['box_0', 'cylinder_0'] at one place"),
    ("move all objects to [1, 2]", "puts 2 objects ['box_0', 'cylinder_0'] at one place"),
    ("set the position to [1, 2, 0.5]", "puts 2 objects ['box_0', 'cylinder_0'] at one place"),
    ("set the position to [1, 2]", "puts 2 objects ['box_0', 'cylinder_0'] at one place"),
    ("move box_0 to [1]", "'move box_0 to [1]': a move takes [x, y] (its height kept) or [x, y, z], not [1]"),
    ("put box_0 at [1, 2, 3, 4]", "a move takes [x, y] (its height kept) or [x, y, z], not [1, 2, 3, 4]"),
    ("double the mass of the camera", "the camera has no 'mass': its fields are position"),
    ("make the camera twice as heavy", "the camera has no mass; its fields are position"),
    ("make the camera faster by 1 m/s", "the camera has no 'velocity'"),
    ("set the tilt of box_0 to 30", "tilt is a property of the camera, not of ['box_0']"),
    ("double the mass of box_0 and increase its tilt by 10", "'its' is ['box_0'], but the tilt is the camera's"),
    ("stop box_0 and halve its gravity", "'its' is ['box_0'], but the gravity is the whole scene's"),
    ("set the camera position to [0, -30, 2]", "camera.position[1] = -30.0: must be in [-20, 20] m"),
    (
        "move the camera 1 m back and double its mass",
        "'its' follows 'move the camera 1 m back', which edited the camera, and the camera has no 'mass'",
    ),
    ("make it fly", "not understood"),
    ("increase the mass of box_9 by 10%", "box_9"),
    ("reduce the x-velocity of box_0 by 150%", "flip the sign"),
    ("set the mass of box_0 to 3 furlongs", "unit 'furlongs'"),
    ("double the friction of box_0", "friction[0] = 2.2"),  # 1.1 × 2 > 2: the validation error
    ("set the mass of box_0 to -1 kg", "must be > 0"),
    ("set gravity of box_0 to 3", "whole scene"),
    ("move box_0 1 m sideways", "not understood"),
    ("reverse the mass of box_0", "can be reversed"),
    # |v| = |[4.3, 2.5, 0]| = 4.974: 6 m/s less would turn the velocity around (it did: -1.03 m/s backwards)
    ("decrease the velocity of box_0 by 6 m/s", "its magnitude is 4.974, so this decrease would leave -1.026"),
    ("", "empty instruction"),
    (" ; .", "empty instruction ' ; .': no clause in it"),  # no clause: it was an edit that changed nothing
    ("increase the x-mass of box_0 by 1 kg", "'x-mass': mass has no x component"),
    # "its" alone edited every object (both frictions halved); in a scene of two objects it names none
    ("halve its friction", "'its' refers to no object named before it in the instruction; name the object"),
    ("make it twice as heavy", "'it' refers to no object named before it"),
    # a second quantity after "and" read as an object: "object 'the friction' not found"
    ("double the mass of box_0 and the friction", "'the friction' is a quantity, not an object of the scene"),
    ("make box_0 0 times as heavy", "'0 times': a factor is a finite number > 0, not 0"),
    ("increase the mass of box_0 by a factor of 0", "a factor is a finite number > 0, not 0"),
    # 1e400 reads inf: it was refused as "a number > 0", which it is
    ("increase the mass of box_0 by a factor of 1e400", "a factor is a finite number > 0, not 1e400"),
    ("make box_0 1e400 times as heavy", "'1e400 times': a factor is a finite number > 0, not inf"),
    # a factor below 1 turned the verb around: "reduce" by 1/0.5 doubled the mass (1 -> 2), "increase" halved it
    ("reduce the mass of box_0 by a factor of 0.5", "a factor of 0.5 < 1 would increase it"),
    ("increase the mass of box_0 by a factor of 0.5", "a factor of 0.5 < 1 would decrease it"),
    ("make box_0 half heavier", "'half heavier' needs a factor > 1 (e.g. 'twice heavier'); for a factor of 0.5 say"),
    ("multiply the mass of box_0 by 1e400", "a factor is a finite number, not 1e400"),
    # a removed object can't be edited afterwards, by name or pronoun
    ("remove box_0 and stop it", "'stop it': box_0 was removed by an earlier clause"),
    ("delete box_0; double the mass of box_0", "'double the mass of box_0': box_0 was removed by an earlier clause"),
    ("remove box_0 and cylinder_0", "the scene needs at least one box, sphere or cylinder"),
    ("remove the sphere", "'the sphere': the scene has no sphere"),
    # after a camera clause "it" is the camera, where an object's field is asked for refused (it moved box_0,
    # position[1] -0.3 -> -1.3, as the object before)
    ("double the mass of box_0; set the fov to 60 and stop it", "'it' follows 'set the fov to 60', which edited the"),
    # gravity is the scene's: 'it' naming an object cannot be made weightless alone (every object was)
    ("add a ball at [1, 2] and make it weightless", "gravity is the whole scene's"),
    ("stop box_0 and make it weightless", "gravity is the whole scene's"),
]


@pytest.mark.parametrize("instruction, message", REFUSED, ids=[r[0] or "empty" for r in REFUSED])
def test_refused(scene, instruction, message):
    before = dump(scene)
    with pytest.raises(EditError) as err:
        apply_instruction(scene, instruction)
    assert message in str(err.value)
    assert dump(scene) == before


def test_its_names_the_only_object_of_a_one_object_scene(scene):
    """With one object, "its" before any object is named is that object (as a reader takes it); after a clause
    that edited the gravity, "it" still has no object to refer to in a scene of two."""
    one = scene.model_copy(update={"objects": scene.objects[:1]})
    assert {c.path: c.after for c in apply_instruction(one, "halve its mass").changes} == {"box_0.physics.mass": 0.5}
    with pytest.raises(EditError, match="'it' refers to no object"):
        apply_instruction(scene, "moon gravity and stop it")
    # "it" after a camera clause is the camera (the only object was moved 1 m back: -0.3 -> -1.3)
    moved = apply_instruction(one, "set the fov to 60 and move it 1 m back").changes
    assert {c.path: c.after for c in moved} == {"camera.fovy": 60.0, "camera.position[1]": -3.0}


def _renamed(scene, names):
    """The scene with its objects renamed (names are letters, digits and _: "it" and "scale" are names)."""
    objects = tuple(o.model_copy(update={"name": n}) for o, n in zip(scene.objects, names, strict=True))
    return scene.model_copy(update={"objects": objects})


def _check(scene, cases):
    for instruction, expected in cases.items():
        result = apply_instruction(scene, instruction)
        assert {c.path: c.after for c in result.changes} == pytest.approx(expected), instruction
        assert not outside(result.changes, named_fields(instruction, scene)), instruction


def test_an_object_named_it_keeps_its_name(scene):
    """Before pronouns, "stop it" stopped the object named it; it was refused ("'it' refers to no object named
    before it"). box_0 is renamed it: velocity [4.3, 2.5, 0], friction 1.1."""
    _check(
        _renamed(scene, ("it", "cylinder_0")),
        {
            "stop it": {"it.state.linear_velocity[0]": 0.0, "it.state.linear_velocity[1]": 0.0},
            "stop it and halve its friction": {  # "its": the objects of the clause before, the object it
                "it.state.linear_velocity[0]": 0.0,
                "it.state.linear_velocity[1]": 0.0,
                "it.physics.friction[0]": 0.55,
            },
        },
    )


def test_and_before_an_object_named_like_a_verb_joins_objects(scene):
    """Before "and" joined clauses, "double the mass of box_0 and scale" doubled both masses (1 -> 2); it was
    refused as the clause "scale". A clause verb that is no object's name still starts a clause."""
    _check(
        _renamed(scene, ("box_0", "scale")),
        {
            "double the mass of box_0 and scale": {"box_0.physics.mass": 2.0, "scale.physics.mass": 2.0},
            "stop box_0 and scale": {
                "box_0.state.linear_velocity[0]": 0.0,
                "box_0.state.linear_velocity[1]": 0.0,
                "scale.state.linear_velocity[0]": 0.0,
                "scale.state.linear_velocity[1]": 0.0,
            },
            "double the mass of box_0 and halve its friction": {
                "box_0.physics.mass": 2.0,
                "box_0.physics.friction[0]": 0.55,
            },
        },
    )


def test_what_is_not_a_scene_or_an_instruction_text_is_named(scene):
    """An instruction as bytes was refused as an "empty instruction"; the scene as YAML text failed with "'str'
    object has no attribute 'objects'" from inside to_items."""
    with pytest.raises(TypeError, match=r"apply_instruction: instruction is a bytes, not a str"):
        apply_instruction(scene, b"reduce the x-velocity of box_0 by 80%")
    with pytest.raises(TypeError, match=r"apply_instruction: scene is a str, not a Scene"):
        apply_instruction(dump(scene), "reduce the x-velocity of box_0 by 80%")


def test_unknown_instruction_lists_what_it_understands(scene):
    with pytest.raises(EditError) as err:
        apply_instruction(scene, "paint the box red")
    assert "I understand" in str(err.value) and "move TARGETS" in str(err.value)


def test_ambiguous_target(scene):
    two = load(str(ASSET)).model_copy(
        update={"objects": (scene.objects[0], scene.objects[0].model_copy(update={"name": "box_1"}))}
    )
    with pytest.raises(EditError, match="ambiguous"):
        apply_instruction(two, "double the mass of the box")
    assert len(apply_instruction(two, "double the mass of all boxes").changes) == 2


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------
def test_cli_edit_writes_out(tmp_path, capsys):
    out = tmp_path / "edited.yaml"
    rc = cli.main(["edit", str(ASSET), "reduce the x-velocity of box_0 by 80%", "--out", str(out), "--json"])
    assert rc == 0
    record = json.loads(capsys.readouterr().out)
    assert record["changes"] == [{"path": "box_0.state.linear_velocity[0]", "before": 4.3, "after": 0.86}]
    assert load(str(out)).object("box_0").state.linear_velocity[0] == 0.86
    same = tmp_path / "same.yaml"
    assert cli.main(["edit", str(ASSET), "double the spin of box_0", "--out", str(same)]) == 0  # its spin is zero
    assert "edit: 'double the spin of box_0' changes no value of the scene" in capsys.readouterr().err


@pytest.mark.parametrize("instruction", ["make it fly", "double the friction of box_0"])
def test_cli_edit_refusal_leaves_input_untouched(tmp_path, capsys, instruction):
    src = tmp_path / "scene.yaml"
    src.write_text(ASSET.read_text())
    out = tmp_path / "edited.yaml"
    rc = cli.main(["edit", str(src), instruction, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("edit: ") and "\n" not in err.strip()
    assert src.read_text() == ASSET.read_text() and not out.exists()


def test_cli_edit_render_reports_an_invalid_rollout(tmp_path, capsys):
    """The camera put inside box_0 (x [-6, -4], y [-0.8, 0.2], z [0, 0.8]): text mode says the edited rollout is
    invalid with the simulator's reason on stderr and exits 1 (it exited 0 saying nothing); the edited YAML is still
    written; --json exits 1 as well and reports edited_valid false. (Objects the edit makes overlap are refused
    before: `test_an_edit_that_makes_objects_overlap_is_refused_and_writes_nothing`.)"""
    from aynamics.render import gl_available

    ok, why = gl_available()
    if not ok:
        pytest.skip(why)
    out = tmp_path / "edited.yaml"
    argv = ["edit", str(ASSET), "put the camera at [-5, -0.3, 0.4]", "--render", str(tmp_path / "d"), "--width", "32"]
    assert cli.main([*argv, "--height", "32", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "edit: the edited scene's rollout is invalid: camera inside box_0" in err
    assert "original scene" not in err
    assert load(str(out)).camera.position == (-5.0, -0.3, 0.4)
    assert cli.main([*argv, "--height", "32", "--json"]) == 1
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["edited_valid"] is False and report["original_valid"] is True
    assert "camera inside box_0" in report["edited_reason"] and "camera inside box_0" in captured.err
    # the edit that repairs it: the original's invalid rollout is reported, the edit succeeds
    argv = ["edit", str(out), "move the camera 3 m back", "--render", str(tmp_path / "e"), "--width", "32"]
    assert cli.main([*argv, "--height", "32"]) == 0
    assert "edit: the original scene's rollout is invalid: camera inside box_0" in capsys.readouterr().err


def test_an_edit_that_makes_objects_overlap_is_refused_and_writes_nothing(tmp_path, capsys, scene):
    """box_0 (z 0.4, half-height 0.4) moved 0.5 m down starts 0.5 m into the floor, a sphere added where box_0 stands
    0.4 m into it: the edit is refused (exit 2, nothing written) naming the pair and the depth; the simulation
    refused them as an overlapping start after the edit was written. A scene that overlapped before may be edited,
    its overlaps kept; a new one, or one made deeper, is refused there too.
    A free editor's answer is checked alike."""
    out = tmp_path / "edited.yaml"
    assert cli.main(["edit", str(ASSET), "move box_0 0.5 m down", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert (
        "'move box_0 0.5 m down' makes objects start inside each other or the floor: box_0 and the floor by 0.5 m"
        in err
    )
    assert not out.exists()
    with pytest.raises(EditError, match=r"box_0 and sphere_0 by 0.4 m \(more than 0.05 m\)"):
        apply_instruction(scene, "add a sphere at [-5, -0.3]")
    sunk = _answer(scene, {(0, "state", "position"): [-5.0, -0.3, -0.1]})  # box_0 0.5 m into the floor
    assert [str(c) for c in apply_instruction(parse(sunk), "double the mass of cylinder_0").changes] == [
        "cylinder_0.physics.mass: 1.0 -> 2.0"
    ]
    with pytest.raises(
        EditError, match=r"LLM edit refused: the model's answer makes objects start inside .* box_0 and"
    ):
        check_output(scene, "move box_0 0.5 m down", sunk)
    # in a scene that overlapped before, a new overlap or a deeper one is refused all the same (both were taken)
    # a sphere of radius 0.2 at z 0.2 under cylinder_0's axis (z 0.3, radius 0.3, lying): 0.3 + 0.2 - 0.1 m deep
    with pytest.raises(EditError, match=r"cylinder_0 and sphere_0 by 0.4 m \(more than"):
        apply_instruction(parse(sunk), "add a sphere at [-0.5, 0.8]")
    with pytest.raises(EditError, match=r"box_0 and the floor by 0.7 m, 0.5 m before \(more than"):
        apply_instruction(parse(sunk), "move box_0 0.2 m down")
    lifted = apply_instruction(parse(sunk), "move box_0 0.2 m up").scene  # 0.3 m in: better, taken
    assert sim.start_overlap_pairs(lifted) == {("box_0", "the floor"): pytest.approx(0.3)}


@pytest.mark.parametrize(
    ("instruction", "message"),
    [
        ("tilt the camera by 10 degrees", r"say which way, 'tilt the camera up\|down by N degrees'"),
        (
            "stop box_0 and pan the camera left by 10 degrees",
            r"'pan the camera left by 10 degrees': the camera does not",
        ),
        ("rotate the camera 90 degrees", r"the camera does not turn: it faces \+y"),
    ],
)
def test_camera_turns_the_camera_cannot_make_are_named(scene, instruction, message):
    """A tilt without up or down, and a pan or turn (the camera has no yaw: it faces +y), get their own message, not
    the whole list of what is understood; 'pan' starts a clause after 'and'."""
    with pytest.raises(EditError, match=message) as caught:
        apply_instruction(scene, instruction)
    assert "I understand" not in str(caught.value)


def test_cli_edit_missing_file(capsys):
    assert cli.main(["edit", "no/such.yaml", "stop box_0"]) == 2
    assert "no/such.yaml" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--llm", "MODEL", "--max-new-tokens", "0"], "edit: --max-new-tokens 0: must be >= 1"),
        (["--llm", "MODEL", "--max-new-tokens", "-1"], "edit: --max-new-tokens -1: must be >= 1"),
        (["--render", "RENDER", "--seed", "-1"], "edit: --seed -1: must be >= 0"),
        (["--render", "RENDER", "--width", "0"], "edit: --width 0 --height 160: each must be in [16, 4096]"),
        (["--render", "RENDER", "--height", "5000"], "edit: --width 240 --height 5000: each must be in [16, 4096]"),
    ],
)
def test_cli_edit_bad_numbers_are_named_before_anything_is_loaded_or_written(tmp_path, capsys, options, message):
    """--max-new-tokens 0 with --llm gave transformers' traceback after loading the model; --seed -1 with --render
    was refused by NumPy ('expected non-negative integer', naming no option) after --out was written and the
    --render folder made. Each is named first: exit 2, no --out, no --render folder (MODEL does not exist: the
    number is refused before the model is looked for)."""
    out, render = tmp_path / "edited.yaml", tmp_path / "what_if"
    options = [{"MODEL": str(tmp_path / "no_model"), "RENDER": str(render)}.get(o, o) for o in options]
    assert cli.main(["edit", str(ASSET), "stop box_0", "--out", str(out), *options]) == 2
    assert capsys.readouterr().err.strip() == message
    assert not out.exists() and not render.exists()


def test_llm_editor_refuses_max_new_tokens_below_one_before_loading(tmp_path):
    with pytest.raises(EditError, match=r"--max-new-tokens 0: must be >= 1"):
        LLMEditor(str(tmp_path / "nothing"), max_new_tokens=0)


# --------------------------------------------------------------------------------------------
# LLM editor: the validation every answer passes through, and the real loading path on a tiny model
# --------------------------------------------------------------------------------------------
def _answer(scene, changes: dict) -> str:
    items = to_items(scene)
    for (i, *keys), value in changes.items():
        d = items[i]
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    from aynamics.scene import from_items

    return f"Here is the scene:\n```yaml\n{dump(from_items(items))}```"


def test_check_output_accepts_named_change(scene):
    text = _answer(scene, {(0, "physics", "mass"): 2.0})
    result = check_output(scene, "double the mass of box_0", text)
    assert [c.path for c in result.changes] == ["box_0.physics.mass"]


def test_check_output_reads_weightless_as_the_gravity_only_where_no_object_is_named(scene):
    """'make everything weightless' names the gravity; 'make box_0 weightless' (one object cannot be, and the edit
    language refuses it) named it too, so a free editor's answer that zeroed every object's gravity passed."""
    weightless = _answer(scene, {(3, "gravity"): [0.0, 0.0, 0.0]})
    named = ("make everything weightless", "make it weightless", "stop box_0 and make everything weightless")
    named += ("moon gravity then make it weightless", "double the fov and make it weightless")  # 'it': no object
    for instruction in named:
        assert [c.path for c in check_output(scene, instruction, weightless).changes] == ["gravity.gravity[2]"]
    for instruction in ("make box_0 weightless", "make the boxes weightless", "stop box_0 and make it weightless"):
        with pytest.raises(EditError, match=r"does not name: gravity.gravity\[2\]"):
            check_output(scene, instruction, weightless)


def test_check_output_reads_words_for_quantities(scene):
    """The free editor's instructions describe quantities ("twice as heavy", "faster"): the check lets those
    fields change (it refused its own docstring's example: helper-38), and still nothing else."""
    text = _answer(scene, {(1, "physics", "mass"): 2.0})
    result = check_output(scene, "make the cylinder twice as heavy", text)
    assert [c.path for c in result.changes] == ["cylinder_0.physics.mass"]
    text = _answer(scene, {(0, "state", "linear_velocity"): [8.6, 5.0, 0.0]})
    assert len(check_output(scene, "make box_0 go twice as fast", text).changes) == 2
    with pytest.raises(EditError, match="box_0.physics.mass"):
        check_output(scene, "make box_0 faster", _answer(scene, {(0, "physics", "mass"): 2.0}))


def test_setting_a_zero_vector_to_zero_is_no_change(scene):
    """The box's spin is [0, 0, 0]: setting its size to 0 changes nothing (it was refused as having no
    direction); a size other than 0 still needs one."""
    assert apply_instruction(scene, "set the spin of box_0 to 0").changes == ()
    with pytest.raises(EditError, match="is zero, so it has no direction"):
        apply_instruction(scene, "set the spin of box_0 to 2")


def test_check_output_refuses_unnamed_fields(scene):
    text = _answer(scene, {(0, "physics", "mass"): 2.0, (1, "physics", "mass"): 5.0})
    with pytest.raises(EditError, match="cylinder_0.physics.mass"):
        check_output(scene, "double the mass of box_0", text)
    text = _answer(scene, {(0, "state", "linear_velocity"): [0.86, 0.0, 0.0]})  # y is not named
    with pytest.raises(EditError, match=r"linear_velocity\[1\]"):
        check_output(scene, "reduce the x-velocity of box_0 by 80%", text)


def test_check_output_refuses_bad_answers(scene):
    with pytest.raises(EditError, match="not a valid scene"):
        check_output(scene, "double the mass of box_0", "I cannot do that.")
    with pytest.raises(EditError, match="changes nothing"):
        check_output(scene, "double the mass of box_0", dump(scene))
    one = dump(scene.model_copy(update={"objects": scene.objects[:1]}))  # cylinder_0 removed unasked
    with pytest.raises(EditError, match=r"does not name: cylinder_0: removed \(cylinder\)"):
        check_output(scene, "double the mass of box_0", one)
    swapped = dump(scene.model_copy(update={"objects": scene.objects[::-1]}))
    with pytest.raises(EditError, match="changed the objects"):
        check_output(scene, "double the mass of box_0", swapped)


def test_remove_objects(scene):
    """ "remove box_0" drops the object (one change naming it), keeps the other's numbers, and a clause after it edits
    the objects left; the free editor's answer that removes the named object passes the check, one that removes
    another does not."""
    result = apply_instruction(scene, "remove box_0, then double the mass of the cylinder")
    assert result.scene.names == ("cylinder_0",)
    assert [str(c) for c in result.changes] == ["box_0: removed (box)", "cylinder_0.physics.mass: 1.0 -> 2.0"]
    assert result.changes[0].removed and not result.changes[1].removed
    assert result.scene.objects[0].state == scene.objects[1].state
    assert not outside(result.changes, named_fields("remove box_0", scene) | {"cylinder_0.physics.mass"})
    assert [c.path for c in apply_instruction(scene, "take away the cylinder").changes] == ["cylinder_0"]
    without_box = f"```yaml\n{dump(scene.model_copy(update={'objects': scene.objects[1:]}))}```"
    assert [str(c) for c in check_output(scene, "delete box_0", without_box).changes] == ["box_0: removed (box)"]
    with pytest.raises(EditError, match=r"does not name: box_0: removed \(box\)"):
        check_output(scene, "delete cylinder_0", without_box)


def test_check_output_accepts_a_replacement_the_instruction_asks_for(scene):
    """A free editor's answer to 'replace box_0 with a sphere' may remove box_0 and add one sphere (the deterministic
    edit's own answer passes), and no more: a second sphere, box_0's removal without 'replace' naming it, or the
    cylinder's mass changed beside it are refused. 'replace the objects with spheres' adds one per object named
    (2 here); without a scene named_additions cannot count them (0)."""
    from aynamics.edit_llm import named_additions

    edited = apply_instruction(scene, "replace box_0 with a sphere").scene
    answer = f"```yaml\n{dump(edited)}```"
    changes = check_output(scene, "replace box_0 with a sphere", answer).changes
    assert [str(c) for c in changes] == ["box_0: removed (box)", "sphere_0: added (sphere)"]
    assert "box_0" in named_fields("replace box_0 with a sphere", scene)
    with pytest.raises(EditError, match=r"does not name: box_0: removed \(box\)"):
        check_output(scene, "replace cylinder_0 with a sphere", answer)
    two = apply_instruction(scene, "replace box_0 with a sphere; add a ball at [2, 2]").scene
    with pytest.raises(EditError, match=r"does not name: sphere_1: added \(sphere\)"):
        check_output(scene, "replace box_0 with a sphere", f"```yaml\n{dump(two)}```")
    heavier = apply_instruction(scene, "replace box_0 with a sphere; double the mass of cylinder_0").scene
    with pytest.raises(EditError, match=r"does not name: cylinder_0.physics.mass"):
        check_output(scene, "replace box_0 with a sphere", f"```yaml\n{dump(heavier)}```")
    both = apply_instruction(scene, "replace the objects with spheres").scene
    assert len(check_output(scene, "replace the objects with spheres", f"```yaml\n{dump(both)}```").changes) == 4
    assert named_additions("replace the objects with spheres", scene) == {"sphere": 2}
    assert named_additions("replace the objects with spheres") == {"sphere": 0}
    assert named_additions("swap box_0 and cylinder_0 for two balls; turn it into a box") == {"sphere": 2, "box": 1}


def test_check_output_lets_a_replacement_add_only_in_place_of_its_targets(scene):
    """'replace box_0 with a box' let a free editor keep box_0 and add box_1 beside it (the addition was counted
    whatever happened to box_0); the box may be added where box_0 is removed."""
    kept = apply_instruction(scene, "add a box at [2, 2] of size [0.2, 0.2, 0.2]").scene
    with pytest.raises(EditError, match=r"does not name: box_1: added \(box\)"):
        check_output(scene, "replace box_0 with a box of size [0.2, 0.2, 0.2]", f"```yaml\n{dump(kept)}```")
    moved = apply_instruction(scene, "remove box_0 and add a box at [2, 2] of size [0.2, 0.2, 0.2] named crate").scene
    changes = check_output(scene, "replace box_0 with a box of size [0.2, 0.2, 0.2]", f"```yaml\n{dump(moved)}```")
    assert [str(c) for c in changes.changes] == ["box_0: removed (box)", "crate: added (box)"]


def test_check_output_accepts_the_deterministic_answer_to_a_same_kind_replacement(scene):
    """'replace box_0 with a box of size [...]' (or 'with a cube', '... and double its mass') keeps the name box_0
    and changes its fields (`aynamics.edit_replace`): that answer from a free editor passes; the cylinder's fields
    stay unnamed."""
    for instruction in (
        "replace box_0 with a box of size [0.1, 0.1, 0.1]",
        "replace box_0 with a cube",
        "replace box_0 with a box and double its mass",
    ):
        edited = apply_instruction(scene, instruction).scene
        assert check_output(scene, instruction, f"```yaml\n{dump(edited)}```").changes
    moved = apply_instruction(scene, "replace box_0 with a cube; move cylinder_0 1 m left").scene
    with pytest.raises(EditError, match=r"does not name: cylinder_0.state.position"):
        check_output(scene, "replace box_0 with a cube", f"```yaml\n{dump(moved)}```")


def _tiny_chat_model(folder: Path) -> Path:
    """`folder` holding a random-weight Qwen2 (seed 0) built from a config, with the project's tiny tokenizer."""
    torch = pytest.importorskip("torch")
    from transformers import AutoTokenizer, Qwen2Config, Qwen2ForCausalLM

    tok = AutoTokenizer.from_pretrained(Path(__file__).parents[1] / "aynamics" / "assets" / "tokenizer")
    cfg = Qwen2Config(
        vocab_size=len(tok),
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=1,
        num_attention_heads=2,
        num_key_value_heads=1,
        max_position_embeddings=4096,
        eos_token_id=tok.eos_token_id,
        pad_token_id=tok.pad_token_id,
    )
    torch.manual_seed(0)
    Qwen2ForCausalLM(cfg).save_pretrained(folder)
    tok.save_pretrained(folder)
    return folder


def test_llm_editor_real_loading_path(tmp_path, scene):
    """A random-weight Qwen2 built from a config with the project's tiny tokenizer: loads through
    AutoModelForCausalLM/AutoTokenizer, applies the chat template, generates, and its (garbage) answer is refused."""
    editor = LLMEditor(str(_tiny_chat_model(tmp_path)), max_new_tokens=12)
    prompt = editor.tokenizer.apply_chat_template(
        build_messages(scene, "stop box_0"), tokenize=False, add_generation_prompt=True
    )
    assert "stop box_0" in prompt and prompt.rstrip().endswith("assistant")
    assert isinstance(editor.generate(scene, "stop box_0"), str)
    with pytest.raises(EditError, match="LLM edit refused"):
        editor.edit(scene, "stop box_0")


def test_the_chat_editor_asks_with_the_scene_and_answers_greedily_with_its_own_tokens(tmp_path, scene):
    """The chat: the rules (system) first, then the scene's canonical YAML and the instruction (user). The answer
    is the greedy continuation alone: the same twice, none of the prompt (no "Instruction:"), at most
    max_new_tokens = 12 tokens (24 after decoding and encoding again, to spare the tokenizer's round trip). A
    tokenizer without a chat template is refused naming the model, before any generation."""
    from aynamics.edit_llm import SYSTEM_PROMPT

    folder = _tiny_chat_model(tmp_path / "chat")
    messages = build_messages(scene, "stop box_0")
    assert [m["role"] for m in messages] == ["system", "user"] and messages[0]["content"] == SYSTEM_PROMPT
    assert messages[1]["content"] == f"Scene:\n```yaml\n{dump(scene)}```\nInstruction: stop box_0"
    editor = LLMEditor(str(folder), max_new_tokens=12)
    answer = editor.generate(scene, "stop box_0")
    assert answer == editor.generate(scene, "stop box_0") and "Instruction:" not in answer
    assert len(editor.tokenizer(answer)["input_ids"]) <= 24
    editor.tokenizer.chat_template = None
    editor.tokenizer.save_pretrained(tmp_path / "plain")
    editor.model.save_pretrained(tmp_path / "plain")
    (tmp_path / "plain" / "chat_template.jinja").unlink(missing_ok=True)
    with pytest.raises(EditError, match="the tokenizer has no chat template"):
        LLMEditor(str(tmp_path / "plain"))


def test_llm_editor_missing_model(tmp_path):
    with pytest.raises(EditError, match="cannot load"):
        LLMEditor(str(tmp_path / "nothing"))
    # an empty folder: transformers' message is several lines; its first alone ended at "... from one of:"
    (tmp_path / "empty").mkdir()
    with pytest.raises(EditError, match="cannot load a chat model with transformers") as err:
        LLMEditor(str(tmp_path / "empty"))
    assert "\n" not in str(err.value) and not str(err.value).endswith(":")


def test_llm_editor_device_is_checked_before_loading(tmp_path, capsys):
    """`edit --llm MODEL --device cuda:N` on a machine without that GPU: the device is named, exit 2, before the
    model path is even looked at."""
    import torch

    from aynamics.cli import main

    gpus = torch.cuda.device_count()
    code = main(["edit", str(ASSET), "stop box_0", "--llm", str(tmp_path / "nothing"), "--device", f"cuda:{gpus}"])
    assert code == 2 and f"device = 'cuda:{gpus}'" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# What-if rendering
# --------------------------------------------------------------------------------------------
def test_render_what_if(tmp_path, scene):
    from aynamics.render import gl_available

    ok, why = gl_available()
    if not ok:
        pytest.skip(why)
    import imageio.v3 as iio

    from aynamics.whatif import render_what_if

    edited = apply_instruction(scene, "increase the y-velocity of cylinder_0 by 2 m/s").scene
    calls = []

    def synthesize(first, flow, prompt):  # the documented hook's contract; returns the first frame held
        calls.append((first.shape, flow.shape, prompt))
        return np.repeat(first[None], len(flow) + 1, axis=0)

    report = render_what_if(scene, edited, tmp_path, width=96, height=64, instruction="faster", synthesize=synthesize)
    assert report["edited_valid"] and report["original_valid"]
    assert calls == [((64, 96, 3), (29, 64, 96, 2), "faster")]
    gif = iio.imread(report["files"]["side_by_side"])
    assert gif.shape[1:] == (128, 192, 3)  # 2×2 tiles
    flow = np.load(report["files"]["edited_flow"])["flow"]
    assert flow.shape == (29, 64, 96, 2) and np.abs(flow).max() > 0  # the cylinder moves in view
    assert load(report["files"]["edited_yaml"]) == edited


def test_diff_names_leaves(scene):
    edited = apply_instruction(scene, "set the mass of box_0 to 3").scene
    assert [str(c) for c in diff(scene, edited)] == ["box_0.physics.mass: 1.0 -> 3.0"]


def test_diff_and_named_fields_name_what_is_not_a_scene(scene):
    """diff(YAML text, scene) failed on "'str' object has no attribute 'names'" and a NaN tol was ignored (every
    float compared exactly); named_fields of a text scene on AttributeError too."""
    with pytest.raises(TypeError, match=r"diff: before is a str, not a Scene"):
        diff(dump(scene), scene)
    with pytest.raises(TypeError, match=r"diff: after is a NoneType, not a Scene"):
        diff(scene, None)
    with pytest.raises(ValueError, match=r"diff: tol = nan: must be a finite number >= 0"):
        diff(scene, scene, tol=math.nan)
    with pytest.raises(TypeError, match=r"named_fields: scene is a str, not a Scene"):
        named_fields("make it heavier", dump(scene))
    assert diff(scene, scene, tol=0) == []


def test_outside_names_a_str_where_a_collection_goes():
    """outside(changes, "box_0.physics") read the str as its letters: every change was outside it (no path is "b"
    or starts with "b." ...), and one of "b.x" would have passed as inside; a generator of paths was spent on the
    first change, so the friction change below came out as outside. The mass change is under box_0.physics, the
    friction change under physics, the position change under neither."""
    from aynamics.edit import Change

    mass = Change("box_0.physics.mass", 1.0, 3.0)
    friction = Change("physics.friction", 0.5, 0.2)
    moved = Change("box_0.state.position[0]", -5.0, -4.0)
    assert outside([mass, friction, moved], {"box_0.physics", "physics"}) == [moved]
    assert outside((mass, friction), (p for p in ("physics", "box_0.physics"))) == []
    assert outside([mass, friction], {"box_0.physics": 1}) == [friction]  # a mapping: its keys
    with pytest.raises(TypeError, match=r"outside: allowed is a str 'box_0.physics': must be a set of str field"):
        outside([mass, friction], "box_0.physics")
    with pytest.raises(TypeError, match=r"outside: allowed is a NoneType None: must be a set"):
        outside([mass], None)
    with pytest.raises(TypeError, match=r"outside: allowed holds a NoneType None: must be a set of str"):
        outside([mass], {"physics", None})
    with pytest.raises(TypeError, match=r"outside: changes is a str 'box_0.physics.mass': must be a list of Changes"):
        outside("box_0.physics.mass", {"physics"})
    with pytest.raises(TypeError, match=r"outside: changes\[1\] is a str 'physics.friction': must be a Change"):
        outside([mass, "physics.friction"], {"physics"})


def test_write_animation_gif_and_mp4_read_back(tmp_path):
    """Two tiles of a square moving right by 4 px per frame, side by side; odd sizes (15 × 21 per tile) make
    the MP4 pad to 16 × 42. Both files read back (the MP4 through PyAV, as `aynamics predict` reads a video)
    with the frames' count, size and content: the square's column in the GIF exactly, in the lossy MP4 to 1 px."""
    from aynamics.video_io import read_frames
    from aynamics.whatif import write_animation

    video = np.zeros((6, 15, 21, 3), np.uint8)
    for k in range(6):
        video[k, 8:13, 4 * k : 4 * k + 4] = 255  # below the caption band
    for name in ("a.gif", "a.mp4"):
        out = write_animation(tmp_path / name, [[video, video]], [["", ""]], fps=10)
        frames = read_frames(out)
        assert len(frames) == 6
        assert frames[0].shape == ((15, 42, 3) if name.endswith("gif") else (16, 42, 3))
        for k, f in enumerate(frames):
            cols = np.nonzero(f[8:13, :21].mean(axis=(0, 2)) > 128)[0]
            assert abs(cols.min() - 4 * k) <= (0 if name.endswith("gif") else 1), (name, k, cols)
    with pytest.raises(ValueError, match="'a.avi'.*.gif or .mp4"):
        write_animation("a.avi", [[video]], [[""]])


def test_a_named_object_after_the():
    """'set the mass of the crate to 3 kg' for an object named crate: 'the crate' was looked up as a name and
    refused ("object 'the crate' not found; the scene has ['crate']"), though 'the box' worked."""
    from aynamics.scene import parse

    crate = parse(
        "- {type: box, name: crate, size: [0.2, 0.2, 0.2], state: {position: [0, 1, 0.2]}}\n"
        "- {type: camera, position: [0, -2, 3]}\n"
    )
    (change,) = apply_instruction(crate, "set the mass of the crate to 3 kg").changes
    assert (change.path, change.after) == ("crate.physics.mass", 3.0)


def test_what_if_files_hold_the_edited_flow_and_tiles_in_place(tmp_path, scene):
    """The edited flow saved and given to the synthesiser is the edited scene's own (motion_flow on its rendering,
    which differs from the original's: the cylinder is 2 m/s faster in y), and the animation's tiles stand as
    labelled: at frame 20 the top-left tile is nearer the original's frame, the top-right the edited one's."""
    from aynamics.render import Renderer, gl_available

    ok, why = gl_available()
    if not ok:
        pytest.skip(why)
    import imageio.v3 as iio

    from aynamics.flow import motion_flow
    from aynamics.simulate import simulate_batch
    from aynamics.whatif import render_what_if

    edited = apply_instruction(scene, "increase the y-velocity of cylinder_0 by 2 m/s").scene
    given = []
    report = render_what_if(
        scene, edited, tmp_path, width=96, height=64, synthesize=lambda f, flow, p: given.append(flow) or f[None]
    )
    rollouts = simulate_batch([scene, edited], nthread=1)
    with Renderer(96, 64) as r:
        frames = [r.render(s, ro, seed=0) for s, ro in zip((scene, edited), rollouts, strict=True)]
    flows = [
        motion_flow(s, ro, f.depth, f.camera, f.segmentation)[0]
        for s, ro, f in zip((scene, edited), rollouts, frames, strict=True)
    ]
    assert not np.allclose(flows[0], flows[1], equal_nan=True)
    saved = np.load(report["files"]["edited_flow"])["flow"]
    np.testing.assert_array_equal(saved, flows[1])
    np.testing.assert_array_equal(given[0], flows[1])
    gif = iio.imread(report["files"]["side_by_side"]).astype(float)[20][..., :3]
    original, changed = (f.rgb[20].astype(float) for f in frames)
    assert np.abs(original - changed).mean() > 1  # the two videos differ at frame 20
    left, right = gif[:64, :96], gif[:64, 96:]
    assert np.abs(left - original).mean() < np.abs(left - changed).mean()
    assert np.abs(right - changed).mean() < np.abs(right - original).mean()


def test_diff_takes_numpy_tolerances(scene):
    """tol = np.float32(1e-6), np.int64(0) or a 0-d array (numbers everywhere else) was refused as "must be a finite
    number" since the argument checks; a str, bool or NaN still is."""
    edited = apply_instruction(scene, "reduce the x-velocity of box_0 by 80%").scene
    expected = diff(scene, edited)
    for tol in (np.float32(1e-6), np.int64(0), np.array(1e-9)):
        assert diff(scene, edited, tol=tol) == expected
    for tol in ("0.1", True, math.nan, -1.0):
        with pytest.raises(ValueError, match=r"diff: tol = .*: must be a finite number >= 0"):
            diff(scene, edited, tol=tol)


# --------------------------------------------------------------------------------------------
# helper-85's review
# --------------------------------------------------------------------------------------------
def test_an_increase_by_a_negative_percentage_may_not_flip_the_sign(scene):
    """'reduce ... by 150%' was refused as flipping the sign, but 'increase ... by -150%' flipped it in silence:
    box_0's x-velocity 4.3 × (1 - 1.5) = -2.15. -50% and -100% keep the sign (4.3 × 0.5 = 2.15; 0)."""
    with pytest.raises(EditError, match=r"an increase of -150% would flip the sign; use 'reverse' or 'set'"):
        apply_instruction(scene, "increase the x-velocity of box_0 by -150%")
    with pytest.raises(EditError, match=r"an increase of -300% would flip the sign"):
        apply_instruction(scene, "increase the z-gravity by -300%")  # -7 × -2 = +14: gravity pointing up
    (change,) = apply_instruction(scene, "increase the x-velocity of box_0 by -50%").changes
    assert change.after == pytest.approx(2.15)
    (change,) = apply_instruction(scene, "increase the x-velocity of box_0 by -100%").changes
    assert change.after == 0.0


def test_refusals_name_the_object_and_field_whose_value_refuses(scene):
    """A value's refusal named the clause as if it were the field ("'set the spin of box_0 to 2' is zero"), said
    "the field is not set" without naming which object's, and called a negative size set a decrease ("its magnitude
    is 7, so this decrease would leave -9.81"). A list for one component was a validation error ("... = [1.0, 2.0,
    3.0]: must be a number, got list")."""
    cylinder = scene.objects[1]
    bouncy = scene.model_copy(
        update={
            "objects": (
                scene.objects[0],
                cylinder.model_copy(update={"physics": cylinder.physics.model_copy(update={"restitution": 0.5})}),
            )
        }
    )
    cases = [
        (bouncy, "increase the restitution by 50%", "box_0.physics.restitution: it is not set"),
        (scene, "set the spin of box_0 to 2", "box_0.state.angular_velocity: it is zero, so it has no direction"),
        (scene, "set the gravity to -9.81", "gravity.gravity: a magnitude is >= 0, not -9.81"),
        (scene, "set the velocity of cylinder_0 to -1 m/s", "cylinder_0.state.linear_velocity: a magnitude is >= 0"),
        # rate 1e-4 /s - 2e-4 /s = -1e-4 /s
        (scene, "reduce the damping of cylinder_0 by 2e-4 /s", "cylinder_0.physics.damping: damping is log10"),
        (scene, "set the x-velocity of box_0 to [1, 2, 3]", "one component takes one number, not [1.0, 2.0, 3.0]"),
    ]
    for s, instruction, message in cases:
        with pytest.raises(EditError) as err:
            apply_instruction(s, instruction)
        assert message in str(err.value), (instruction, str(err.value))
        assert "decrease" not in str(err.value) or "decrease" in instruction or "reduce" in instruction


def test_the_camera_and_the_scene_named_as_targets_and_singular_units(scene):
    """'set the field of view of the camera to 60' was refused: "object 'the camera' not found" (so was 'the gravity
    of the scene'); 'degree', 'gram' and 'kilogram' were refused units where 'degrees', 'grams', 'kilograms' were
    read. A camera field of an object is still refused."""
    table = [
        ("set the field of view of the camera to 60 degree", "camera.fovy", 60.0),
        ("set the camera's fov to 50", "camera.fovy", 50.0),
        ("decrease the gravity of the world by 50%", "gravity.gravity[2]", -3.5),  # -7 × 0.5
        ("set the mass of box_0 to 500 gram", "box_0.physics.mass", 0.5),
        ("set the mass of box_0 to 2 kilogram", "box_0.physics.mass", 2.0),
    ]
    for instruction, path, value in table:
        (change,) = apply_instruction(scene, instruction).changes
        assert (change.path, change.after) == (path, value), instruction
    with pytest.raises(EditError, match=r"fovy is a property of the camera, not of \['box_0'\]"):
        apply_instruction(scene, "set the fov of box_0 to 60")


def test_ambiguity_names_the_plural():
    """Two spheres were "2 spherees" in the ambiguity message."""
    from aynamics.scene import parse

    two = parse(
        "- {type: sphere, radius: 0.2, state: {position: [0, 1, 0.2]}}\n"
        "- {type: sphere, radius: 0.2, state: {position: [1, 1, 0.2]}}\n"
        "- {type: camera, position: [0, -2, 3]}\n"
    )
    with pytest.raises(EditError, match=r"the scene has 2 spheres \['sphere_0', 'sphere_1'\]; name one"):
        apply_instruction(two, "double the mass of the sphere")


def test_diff_reads_no_environment_as_the_default_one(scene):
    """A scene without an environment item simulates as one with the default item, but diff listed writing it out
    as 8 changes ("environment.air_density: None -> 0.0", ...), so the free editor's answer that wrote it was
    refused; and a clock set back to 1 (dumped only when not 1) was "environment.time_scale: 1.5 -> None"."""
    from aynamics.edit import Change
    from aynamics.scene import Environment

    with_default = scene.model_copy(update={"environment": Environment()})
    assert diff(scene, with_default) == [] and diff(with_default, scene) == []
    slow = scene.model_copy(update={"environment": Environment(time_scale=1.5, air_density=1.2)})
    assert diff(slow, with_default) == [
        Change("environment.air_density", 1.2, 0.0),
        Change("environment.time_scale", 1.5, 1.0),
    ]
    assert diff(scene, slow) == [
        Change("environment.air_density", 0.0, 1.2),
        Change("environment.time_scale", 1.0, 1.5),
    ]
    heavier = apply_instruction(scene, "double the mass of box_0").scene.model_copy(
        update={"environment": Environment()}
    )
    result = check_output(scene, "double the mass of box_0", dump(heavier))
    assert [str(c) for c in result.changes] == ["box_0.physics.mass: 1.0 -> 2.0"]


def test_diff_reads_no_magnus_or_friction_slope_as_zero(scene):
    """An object without magnus / friction_slope simulates as one with 0, but diff listed writing them out as
    changes ("box_0.physics.magnus: None -> 0.0"); restitution's absence (MuJoCo's soft contact) is not 0."""
    from aynamics.edit import Change

    box = scene.objects[0]
    zeros = box.model_copy(update={"physics": box.physics.model_copy(update={"magnus": 0.0, "friction_slope": 0})})
    written = scene.model_copy(update={"objects": [zeros, *scene.objects[1:]]})
    assert diff(scene, written) == [] and diff(written, scene) == []
    lift = box.model_copy(update={"physics": box.physics.model_copy(update={"magnus": 0.01, "restitution": 0.0})})
    lifted = scene.model_copy(update={"objects": [lift, *scene.objects[1:]]})
    assert diff(scene, lifted) == [  # keys of both scenes first, then those only the second has
        Change("box_0.physics.magnus", 0.0, 0.01),
        Change("box_0.physics.restitution", None, 0.0),
    ]


def test_named_fields_of_the_camera(scene):
    """'rotate the camera' named every object's spin and 'move the camera 1 m back' every position: the free
    editor's check passed an answer that spun or moved box_0 and refused one that turned or moved the camera.
    'toward the camera' is still a direction, not the camera."""
    assert named_fields("rotate the camera by 10 degrees", scene) == {"camera.orientation"}
    assert named_fields("move the camera 1 m back", scene) == {"camera.position"}
    assert named_fields("zoom in", scene) == {"camera.fovy"}
    assert named_fields("move the cylinder 0.3 m toward the camera", scene) == {"cylinder_0.state.position"}
    assert named_fields("move everything 1 m away from the camera", scene) == {
        "box_0.state.position",
        "cylinder_0.state.position",
    }
    turned = dump(scene.model_copy(update={"camera": scene.camera.model_copy(update={"orientation": 55.0})}))
    assert [c.path for c in check_output(scene, "rotate the camera by 10 degrees", turned).changes] == [
        "camera.orientation"
    ]
    spun = _answer(scene, {(0, "state", "angular_velocity"): [0.0, 0.0, 5.0]})
    with pytest.raises(EditError, match=r"box_0.state.angular_velocity\[2\]"):
        check_output(scene, "rotate the camera by 10 degrees", spun)
    with pytest.raises(TypeError, match=r"named_fields: instruction is a NoneType, not a str"):
        named_fields(None, scene)


def test_a_removal_allows_the_free_editor_no_other_change(scene):
    """named_fields gave every field of every object the text named once "remove" was anywhere in it: a model that
    kept box_0 and moved it, or moved cylinder_0, passed "double the mass of cylinder_0 and remove box_0", and one
    that deleted box_0 passed "remove the spin of box_0". A removal clause now allows that object's removal alone."""
    box, cyl = scene.objects
    moved_box = box.model_copy(update={"state": box.state.model_copy(update={"position": [3.0, 3.0, 0.4]})})
    moved_cyl = cyl.model_copy(update={"state": cyl.state.model_copy(update={"position": [3.0, 3.0, 0.3]})})

    def answer(objects):
        return f"```yaml\n{dump(scene.model_copy(update={'objects': objects}))}```"

    instruction = "double the mass of cylinder_0 and remove box_0"
    with pytest.raises(EditError, match=r"does not name: cylinder_0.state.position\[0\]"):
        check_output(scene, instruction, answer([moved_cyl]))
    with pytest.raises(EditError, match=r"does not name: box_0.state.position\[0\]"):
        check_output(scene, instruction, answer([moved_box, cyl]))
    with pytest.raises(EditError, match=r"does not name: box_0: removed \(box\)"):
        check_output(scene, "remove the spin of box_0", answer([cyl]))
    assert [c.path for c in check_output(scene, "stop cylinder_0 and remove it", answer([box])).changes] == [
        "cylinder_0"
    ]
    assert named_fields("remove box_0", scene) == {"box_0"}


def test_every_object_after_a_removal_is_every_object_left(scene):
    """ "remove box_0 and double the mass of all objects" was refused ("box_0 was removed by an earlier clause"): every
    object and the objects of a kind are those left; a removed object named again is still refused."""
    for instruction in (
        "remove box_0 and double the mass of all objects",
        "remove box_0, then double the mass of everything",
        "delete the box and double the mass",
    ):
        result = apply_instruction(scene, instruction)
        assert [str(c) for c in result.changes] == ["box_0: removed (box)", "cylinder_0.physics.mass: 1.0 -> 2.0"]
    stopped = apply_instruction(scene, "remove box_0 and stop everything")
    assert stopped.scene.names == ("cylinder_0",)
    assert tuple(stopped.scene.objects[0].state.linear_velocity) == (0.0, 0.0, 0.0)
    with pytest.raises(EditError, match="'the box': the scene has no box left; its objects are"):
        apply_instruction(scene, "remove box_0 and double the mass of the box")
    with pytest.raises(EditError, match="box_0 was removed by an earlier clause"):
        apply_instruction(scene, "remove box_0 and double the mass of box_0")


# --------------------------------------------------------------------------------------------
# Adding objects
# --------------------------------------------------------------------------------------------
def test_add_an_object_resting_on_the_floor(scene):
    """'add a sphere at [1, 2]': the scene has no sphere, so the defaults (radius 0.2 m, 1 kg, friction
    [0.5, 0.05], damping -4), upright at rest with its centre one radius above the floor (z = 0.2); the other
    objects keep every number, and the rollout is valid with the sphere still there (nothing pushes it)."""
    from aynamics.simulate import simulate

    result = apply_instruction(scene, "add a sphere at [1, 2]")
    assert [str(c) for c in result.changes] == ["sphere_0: added (sphere)"] and result.changes[0].added
    assert result.scene.names == ("box_0", "cylinder_0", "sphere_0")
    assert result.scene.objects[:2] == scene.objects
    sphere = result.scene.object("sphere_0")
    assert sphere.radius == 0.2
    assert sphere.state.position == (1.0, 2.0, 0.2) and sphere.state.orientation == (1.0, 0.0, 0.0, 0.0)
    assert sphere.state.linear_velocity == (0.0, 0.0, 0.0) == sphere.state.angular_velocity
    assert (sphere.physics.mass, sphere.physics.friction, sphere.physics.damping) == (1.0, (0.5, 0.05), -4.0)
    rollout = simulate(result.scene)
    assert rollout.valid, rollout.reason
    np.testing.assert_allclose(rollout.position[-1, 2], [1.0, 2.0, 0.2], atol=2e-3)


def test_add_takes_shape_physics_and_motion_from_the_clause(scene):
    """'like box_0' (or a first object of the kind) gives the shape and physics, never the state; the phrases
    override them; 'it' in the next clause is the new object; a removed object is no template."""
    box = apply_instruction(scene, "add another box at [3, 1] like box_0 moving at [-1, 0, 0] m/s").scene.objects[-1]
    assert (box.name, box.size, box.physics.friction) == ("box_1", (1.0, 0.5, 0.4), (1.1, 0.3))
    assert box.state.position == (3.0, 1.0, 0.4)  # half-height 0.4 above the floor
    assert box.state.linear_velocity == (-1.0, 0.0, 0.0) and box.state.orientation == (1.0, 0.0, 0.0, 0.0)
    result = apply_instruction(scene, "add a cylinder at [0, 0, 1] of radius 10 cm and mass 2 kg")
    cyl = result.scene.object("cylinder_1")  # cylinder_0's height 0.5 and friction, the radius and mass given
    assert (cyl.radius, cyl.height, cyl.physics.mass, cyl.physics.friction) == (0.1, 0.5, 2.0, (1.1, 0.3))
    assert cyl.state.position == (0.0, 0.0, 1.0)
    result = apply_instruction(scene, "add a ball at [0, 2] named ball and make it twice as heavy")
    assert [str(c) for c in result.changes] == ["ball: added (sphere)"]  # the doubling is the new object's own mass
    assert result.scene.object("ball").physics.mass == 2.0
    both = apply_instruction(scene, "add a sphere at [1, 2]; double the mass of all objects").scene
    assert [o.physics.mass for o in both.objects] == [2.0, 2.0, 2.0]
    swap = apply_instruction(scene, "remove box_0 and add a box at [0, 2]")
    assert [str(c) for c in swap.changes] == ["box_0: removed (box)", "box_1: added (box)"]
    assert swap.scene.objects[-1].size == (0.2, 0.2, 0.2)  # the default: the scene's box was removed
    cube = apply_instruction(scene, "add a cube at [0, 1] of size [10, 10, 10] cm").scene.objects[-1]
    assert cube.size == (0.1, 0.1, 0.1) and cube.state.position == (0.0, 1.0, 0.1)
    cube = apply_instruction(scene, "add a cube at [0, 1]").scene.objects[-1]  # box_0 is no cube: 0.2 m, its physics
    assert (cube.size, cube.physics.friction) == ((0.2, 0.2, 0.2), (1.1, 0.3))


def test_add_rests_on_a_tilted_floor(scene):
    """Floor tilted 10° about x: its normal is n = (0, -sin 10°, cos 10°), and the plane passes below (0, 1) at
    z = tan 10° = 0.17633. A sphere of radius 0.2 added 'at [0, 1]' touches it there: its centre is
    (0, 1, 0.17633) + 0.2 n = (0, 0.96527, 0.37329), 0.2 m above the floor along the normal, leaning with it."""
    from aynamics.reasoning import floor_heights
    from aynamics.scene import from_items

    tilted = from_items([*to_items(scene), {"type": "environment", "floor_tilt": [10.0, 0.0]}])
    sphere = apply_instruction(tilted, "add a sphere at [0, 1]").scene.objects[-1]
    np.testing.assert_allclose(sphere.state.position, [0.0, 0.96527, 0.37329], atol=5e-5)  # scenes keep 4 decimals
    assert float(floor_heights(tilted, np.array(sphere.state.position))) == pytest.approx(0.2, abs=1e-4)


@pytest.mark.parametrize(
    "instruction, message",
    [
        ("add a sphere", r"'add a sphere': say where the sphere goes: 'at \[x, y\]'"),
        ("add a sphere at [1, 2] painted red", r"'painted red' not understood. 'add a\|another box"),
        ("add a box at [1, 2] of radius 0.2", "a box has no radius"),
        ("add a sphere at [1, 2] named box_0", "the scene already has an object named 'box_0'"),
        ("add a sphere at [1, 2] like box_0", r"'like box_0' must name one sphere, not \['box_0'\]"),
        ("add a cube at [0, 1] of size [0.1, 0.2, 0.1]", "a cube has equal half-extents"),
        ("add a sphere at [1, 2, 3, 4]", r"a position is \[x, y\] \(resting on the floor\) or \[x, y, z\]"),
        ("add a sphere at [1, 2] of radius 2 kg", "unit 'kg' does not fit radius"),
        ("add a box at [1, 2] of size [1, 1, 1] kg", "unit 'kg' does not fit size"),
        ("add a sphere at [1, 2] of mass 1 kg of mass 2 kg", "the mass is given twice"),
        (
            "add a sphere at [1, 2] of radius -1",
            r"makes the scene invalid: .*objects\[2\]\.radius = -1\.0: must be > 0",
        ),
    ],
)
def test_add_refusals_name_the_problem(scene, instruction, message):
    with pytest.raises(EditError, match=message):
        apply_instruction(scene, instruction)


def test_diff_and_the_free_editor_check_additions(scene):
    """diff names an added object once; the free editor may add what the 'add' clauses add (kind and count), no
    more, and still change nothing else; reordering the kept objects is still refused."""
    added = apply_instruction(scene, "add a sphere at [1, 2]").scene
    assert [str(c) for c in diff(scene, added)] == ["sphere_0: added (sphere)"]
    answer = f"```yaml\n{dump(added)}```"
    assert [str(c) for c in check_output(scene, "add a sphere at [1, 2]", answer).changes] == [
        "sphere_0: added (sphere)"
    ]
    with pytest.raises(EditError, match=r"does not name: sphere_0: added \(sphere\)"):
        check_output(scene, "double the mass of box_0", answer)
    with pytest.raises(EditError, match=r"does not name: sphere_0: added \(sphere\)"):
        check_output(scene, "add a box at [1, 2]", answer)
    two = apply_instruction(scene, "add a sphere at [1, 2]; add a sphere at [2, 2]").scene
    with pytest.raises(EditError, match=r"does not name: sphere_1: added \(sphere\)\. The instruction names"):
        check_output(scene, "add a sphere at [1, 2]", f"```yaml\n{dump(two)}```")
    heavier = apply_instruction(scene, "add a cylinder at [1, 2] like cylinder_0; double the mass of cylinder_0")
    with pytest.raises(EditError, match=r"does not name: cylinder_0.physics.mass: 1.0 -> 2.0"):  # 'like' names no field
        check_output(scene, "add a cylinder at [1, 2] like cylinder_0 of mass 2 kg", dump(heavier.scene))
    moved = apply_instruction(scene, "add a sphere at [1, 2]; move box_0 1 m left").scene
    with pytest.raises(EditError, match=r"box_0.state.position\[0\]"):
        check_output(scene, "add a sphere at [1, 2]", f"```yaml\n{dump(moved)}```")
    from aynamics.scene import from_items

    items = to_items(added)
    reordered = from_items([items[2], items[0], items[1], *items[3:]])  # the new sphere first is an addition too
    assert [str(c) for c in diff(scene, reordered)] == ["sphere_0: added (sphere)"]
    with pytest.raises(EditError, match="changed the objects"):
        diff(scene, from_items([items[1], items[0], *items[2:]]))


def test_cli_edit_adds_and_renders(tmp_path, capsys):
    from aynamics.render import gl_available

    ok, why = gl_available()
    if not ok:
        pytest.skip(why)
    out = tmp_path / "whatif"
    argv = ["edit", str(ASSET), "add a sphere at [-3, 0.5] moving at [2, 0, 0]", "--render", str(out), "--json"]
    argv += ["--width", "48", "--height", "32"]
    assert cli.main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["changes"] == [{"path": "sphere_0", "before": None, "after": "sphere"}]
    assert report["edited_valid"] and report["original_valid"]
    assert load(str(out / "edited.yaml")).names == ("box_0", "cylinder_0", "sphere_0")


def test_add_defaults_are_not_changed_by_an_edit_of_the_added_object(scene):
    """'add a sphere ...; set its friction to 0.9' edited the friction list of `ADD_DEFAULTS` in place (a shallow
    copy): every later default sphere had friction 0.9."""
    from aynamics.edit_add import ADD_DEFAULTS

    edited = apply_instruction(scene, "add a sphere at [1, 2] and set its friction to 0.9").scene.objects[-1]
    assert edited.physics.friction == (0.9, 0.05)
    assert ADD_DEFAULTS["physics"]["friction"] == [0.5, 0.05]
    assert apply_instruction(scene, "add a sphere at [3, 2]").scene.objects[-1].physics.friction == (0.5, 0.05)


@pytest.mark.parametrize(
    "instruction",
    [
        "add a cylinder at [1, 2] of radius 0.1 and height 0.3",
        "add a cylinder at [1, 2] of radius 0.1 with height 0.3",
        "add a cylinder at [1, 2] of height 0.3 m and radius 10 cm",
        "add a cylinder at [1, 2] of radius 0.1 height 0.3",
    ],
)
def test_add_a_bare_number_leaves_the_next_phrase_alone(scene, instruction):
    """'of radius 0.1 and height 0.3' was refused with "unit 'and' does not fit radius": a bare number took the
    next word as its unit."""
    cyl = apply_instruction(scene, instruction).scene.objects[-1]
    assert (cyl.radius, cyl.height) == (0.1, 0.3)
    with pytest.raises(EditError, match="unit 'kg' does not fit radius"):
        apply_instruction(scene, "add a cylinder at [1, 2] of radius 2 kg and height 0.3")


def test_add_like_it_and_like_the_kind(scene):
    """'like it' after a clause is its object ("'it' refers to no object named before it"), and 'like the box' the
    scene's box ("'box' not understood")."""
    two = apply_instruction(scene, "add a sphere at [1, 2] of radius 0.1 then add another sphere at [2, 2] like it")
    assert [o.radius for o in two.scene.objects[2:]] == [0.1, 0.1]
    box = apply_instruction(scene, "add a box at [1, 2] like the box").scene.objects[-1]
    assert (box.name, box.size) == ("box_1", (1.0, 0.5, 0.4))
    with pytest.raises(EditError, match="'like it' must name one box, not \\['cylinder_0'\\]"):
        apply_instruction(scene, "stop cylinder_0 and add a box at [1, 2] like it")


def test_add_vectors_take_units(scene):
    """'moving at [50, 0, 0] cm/s' was "'cm/s' not understood" (only m/s was read), 'at [100, 200] cm' "'cm' not
    understood", and 'of size [0.3, 0.3, 0.3] named b' read "named" as the size's unit ("'b' not understood")."""
    result = apply_instruction(scene, "add a sphere at [100, 200] cm moving at [50, 0, 0] cm/s named b")
    ball = result.scene.object("b")
    assert ball.state.position == (1.0, 2.0, 0.2) and ball.state.linear_velocity == (0.5, 0.0, 0.0)
    fast = apply_instruction(scene, "add a sphere at [1, 2, 0.5] m moving at [36, 0, 0] km/h").scene.objects[-1]
    assert fast.state.position == (1.0, 2.0, 0.5) and fast.state.linear_velocity == pytest.approx((10.0, 0.0, 0.0))
    box = apply_instruction(scene, "add a box at [1, 2] of size [0.3, 0.3, 0.3] named b").scene.object("b")
    assert box.size == (0.3, 0.3, 0.3)
    with pytest.raises(EditError, match="unit 'kg' does not fit position: allowed m, "):
        apply_instruction(scene, "add a sphere at [1, 2] kg")
    with pytest.raises(EditError, match="unit 'm' does not fit velocity: allowed m/s, cm/s, km/h"):
        apply_instruction(scene, "add a sphere at [1, 2] moving at [1, 0, 0] m")


def test_add_named_keeps_the_case_and_refuses_the_scene_items_names(scene):
    """'named Ball' named the sphere ball (the clauses are lower-cased); 'named camera' added a sphere whose fields
    hid the camera's in `diff` ("camera.fovy: 45.0 -> None")."""
    result = apply_instruction(scene, "add a ball at [1, 2] named Ball and double the mass of ball")
    assert [str(c) for c in result.changes] == ["Ball: added (sphere)"]
    assert result.scene.object("Ball").physics.mass == 2.0
    with pytest.raises(EditError, match="already has an object named 'Box_0'"):
        apply_instruction(scene, "add a box at [1, 2] named Box_0")
    for name in ("camera", "Gravity", "environment"):
        with pytest.raises(EditError, match=f"'{name}' is the name of the scene's {name.lower()} item"):
            apply_instruction(scene, f"add a sphere at [1, 2] named {name}")


@pytest.mark.parametrize(
    "instruction, unasked",
    [
        ("add a sphere at [1, 2] and double its mass", "double the mass of box_0"),
        ("add a sphere at [1, 2] and make it twice as heavy", "make cylinder_0 twice as heavy"),
        ("add a sphere at [1, 2] then move it 1 m left", "move box_0 1 m left"),
        ("add a sphere at [1, 2]; add a box at [3, 3]; stop them", "stop box_0"),
        ("add a ball at [1, 2] named b; double the mass of b", "double the mass of cylinder_0"),
        ("add a sphere at [1, 2]; double the mass of sphere_0", "double the mass of cylinder_0"),
        ("add a sphere at [1, 2]; double the mass of the sphere", "double the mass of cylinder_0"),
        ("add a sphere at [1, 2] and remove it", "remove box_0"),
    ],
)
def test_the_free_editor_check_reads_pronouns_and_names_of_added_objects(scene, instruction, unasked):
    """A clause after an 'add' that edits the new object ('its', 'it', its name, 'the sphere' where the scene has
    none) named no object, so every object: a free editor's answer that also edited box_0 (or removed it) passed.
    The answer the instruction asks for still passes; so do edits of objects the text names or 'all objects'."""
    if "remove it" not in instruction:  # that one changes nothing
        check_output(scene, instruction, dump(apply_instruction(scene, instruction).scene))
    head = instruction.split(" and ")[0].split(" then ")[0].split(";")[0]
    answer = apply_instruction(scene, f"{head}; {unasked}").scene
    with pytest.raises(EditError, match="does not name: (box_0|cylinder_0)"):
        check_output(scene, instruction, dump(answer))
    for fine in ("add a sphere at [1, 2]; double the mass of all objects", "add a sphere at [1, 2]; double the mass"):
        check_output(scene, fine, dump(apply_instruction(scene, fine).scene))
    kept = "add a sphere at [1, 2]; double the mass of box_0 and halve its friction"
    check_output(scene, kept, dump(apply_instruction(scene, kept).scene))


# --------------------------------------------------------------------------------------------
# Replacing objects; put / place / drop; a count of objects to add
# --------------------------------------------------------------------------------------------
def _with_box(scene, **state):
    """The paper's scene with box_0 of half-extents [0.1, 0.2, 0.3], upright at rest on the floor at [1, 2, 0.3]
    (or as `state` says), of mass 2 kg and restitution 0.5; its velocity [4.3, 2.5, 0] and friction [1.1, 0.3]."""
    from aynamics.scene import from_items

    items = to_items(scene)
    items[0]["size"] = [0.1, 0.2, 0.3]
    items[0]["state"] |= {"position": [1.0, 2.0, 0.3], "orientation": [1, 0, 0, 0], "angular_velocity": [0, 0, 2]}
    items[0]["state"] |= state
    items[0]["physics"] |= {"mass": 2.0, "restitution": 0.5}
    return from_items(items)


def test_replace_a_resting_box_with_a_sphere_keeps_its_place_motion_and_physics(scene):
    """A sphere's radius is the box's mean half-extent, (0.1 + 0.2 + 0.3) / 3 = 0.2; the box rested on the floor
    (z 0.3 = its half-height), so the sphere rests at the same x, y with its centre one radius up (z 0.2). It is
    first in the objects, where box_0 was, with box_0's velocity, spin, mass, friction, damping and restitution;
    the scene validates and simulates."""
    from aynamics.simulate import simulate

    box = _with_box(scene)
    result = apply_instruction(box, "replace box_0 with a sphere")
    assert [str(c) for c in result.changes] == ["box_0: removed (box)", "sphere_0: added (sphere)"]
    assert result.scene.names == ("sphere_0", "cylinder_0") and result.scene.objects[1] == scene.objects[1]
    sphere = result.scene.objects[0]
    assert sphere.radius == pytest.approx(0.2)
    assert sphere.state.position == pytest.approx((1.0, 2.0, 0.2))
    assert sphere.state.linear_velocity == (4.3, 2.5, 0.0) and sphere.state.angular_velocity == (0.0, 0.0, 2.0)
    assert sphere.physics == box.objects[0].physics  # mass 2, friction [1.1, 0.3], damping -4, restitution 0.5
    rollout = simulate(result.scene)
    assert rollout.valid, rollout.reason
    # a cylinder: radius the mean of the x and y half-extents, (0.1 + 0.2) / 2 = 0.15, height 2 × 0.3 = 0.6, z 0.3
    cyl = apply_instruction(box, "turn box_0 into a cylinder").scene.objects[0]
    assert (cyl.name, cyl.radius, cyl.height) == ("cylinder_1", pytest.approx(0.15), pytest.approx(0.6))
    assert cyl.state.position == pytest.approx((1.0, 2.0, 0.3))
    # a cube: the mean half-extent three times, resting at z 0.2; 'swap ... for' and 'change ... to' read the same
    for instruction in ("swap box_0 for a cube", "change the box to a cube"):
        cube = apply_instruction(box, instruction).scene.objects[0]
        assert (cube.name, cube.size) == ("box_0", pytest.approx((0.2, 0.2, 0.2)))
        assert cube.state.position == pytest.approx((1.0, 2.0, 0.2))


def test_replace_in_the_air_keeps_the_centre_and_the_orientation(scene):
    """box_0 1 m up, turned 90° about z (w = z = 0.7071): not on the floor, so a cylinder takes its centre and its
    orientation; 'of radius 10 cm' and 'of mass 3 kg' override the extent's radius 0.15 and the mass 2."""
    box = _with_box(scene, position=[1.0, 2.0, 1.0], orientation=[0.7071, 0.0, 0.0, 0.7071])
    cyl = apply_instruction(box, "replace box_0 with a cylinder of radius 10 cm and mass 3 kg").scene.objects[0]
    assert (cyl.radius, cyl.height, cyl.physics.mass) == (0.1, pytest.approx(0.6), 3.0)
    assert cyl.state.position == (1.0, 2.0, 1.0) and cyl.state.orientation == (0.7071, 0.0, 0.0, 0.7071)


def test_replace_names_pronouns_and_the_paper_scene(scene):
    """box_0 of the paper's scene ([1, 0.5, 0.4], turned about z only, at z 0.4: resting) replaced by a ball of
    radius 0.1 rests at z 0.4 + 0.1 - 0.4 = 0.1; 'its' after the clause is the ball's (mass 1 -> 2), not the
    cylinder's. The lying cylinder_0 (axis horizontal, radius 0.3, height 0.5, at z 0.3) swapped for a box gets
    half-extents [0.3, 0.3, 0.25] in its frame, lying the same way: its lowest point is again 0.3 below the centre."""
    result = apply_instruction(scene, "replace box_0 with a ball of radius 0.1 m and double its mass")
    ball, cyl = result.scene.objects
    assert (ball.name, ball.radius, ball.physics.mass, cyl.physics.mass) == ("sphere_0", 0.1, 2.0, 1.0)
    assert ball.state.position == pytest.approx((-5.0, -0.3, 0.1)) and ball.state.linear_velocity == (4.3, 2.5, 0.0)
    result = apply_instruction(scene, "swap the cylinder for a box named Crate then move it 1 m left")
    assert [str(c) for c in result.changes] == ["cylinder_0: removed (cylinder)", "Crate: added (box)"]
    crate = result.scene.object("Crate")
    assert crate.size == (0.3, 0.3, 0.25) and crate.state.orientation == scene.objects[1].state.orientation
    assert crate.state.position == pytest.approx((-1.5, 0.8, 0.3), abs=1e-4)
    # the same kind keeps the name and changes what the phrases say: a lower box_0 rests lower (half-height 0.2)
    assert apply_instruction(scene, "replace box_0 with a box").changes == ()
    lower = apply_instruction(scene, "replace box_0 with a box of size [1, 0.5, 0.2]")
    assert [str(c) for c in lower.changes] == ["box_0.size[2]: 0.4 -> 0.2", "box_0.state.position[2]: 0.4 -> 0.2"]
    # replacing an added object: the sphere resting on a floor tilted 10° about x (the add test's) becomes a cube
    # of half-extent 0.1, its lowest point where the sphere's was: (0, 1, tan 10°) + 0.1 n, n = (0, -sin 10°,
    # cos 10°), = (0, 0.98264, 0.27481), leaning with the floor (cos 5°, sin 5°, 0, 0)
    from aynamics.scene import from_items

    tilted = from_items([*to_items(scene), {"type": "environment", "floor_tilt": [10.0, 0.0]}])
    result = apply_instruction(tilted, "add a sphere at [0, 1] and replace it with a cube of size [0.1, 0.1, 0.1]")
    assert [str(c) for c in result.changes] == ["box_1: added (box)"]
    cube = result.scene.object("box_1")
    np.testing.assert_allclose(cube.state.position, [0.0, 0.98264, 0.27481], atol=5e-5)
    np.testing.assert_allclose(cube.state.orientation, [0.99619, 0.08716, 0.0, 0.0], atol=5e-5)
    # a smaller sphere in its place (the same kind: its orientation, the floor's, is kept) lies there as well
    ball = apply_instruction(tilted, "add a sphere at [0, 1] and replace it with a sphere of radius 0.1").scene
    assert ball.names[-1] == "sphere_0" and ball.objects[-1].radius == 0.1
    np.testing.assert_allclose(ball.objects[-1].state.position, [0.0, 0.98264, 0.27481], atol=5e-5)
    np.testing.assert_allclose(ball.objects[-1].state.orientation, [0.99619, 0.08716, 0.0, 0.0], atol=5e-5)


def test_replace_several_objects(scene):
    """'the objects' are box_0 and cylinder_0: each becomes a sphere in its place, named in order; radii the mean
    half-extents (1 + 0.5 + 0.4) / 3 = 0.63333 and (0.3 + 0.3 + 0.25) / 3 = 0.28333, resting (z = radius)."""
    for instruction in ("replace the objects with spheres", "replace box_0 and cylinder_0 with two balls"):
        result = apply_instruction(scene, instruction)
        assert result.scene.names == ("sphere_0", "sphere_1")
        assert [o.radius for o in result.scene.objects] == pytest.approx([0.6333, 0.2833], abs=1e-4)
        assert [o.state.position[2] for o in result.scene.objects] == pytest.approx([0.6333, 0.2833], abs=1e-4)
    stopped = apply_instruction(scene, "replace all objects with spheres and stop them").scene.objects
    assert [o.state.linear_velocity for o in stopped] == [(0.0, 0.0, 0.0)] * 2


def test_one_replace_clause_with_several_replacements(scene):
    """'replace box_0 with a sphere and cylinder_0 with a box' is two replacements, the verb repeated (the second
    was read as the first's phrases and refused: "'cylinder_0 with a box' not understood"); each keeps its own
    phrases, an 'and' inside the targets still joins objects, and the free editor's check reads both."""
    from aynamics.edit_llm import named_additions

    assert split_clauses("swap box_0 for a ball named b, and the cylinder for a cube of mass 2 kg and stop it") == [
        "swap box_0 for a ball named b",
        "swap the cylinder for a cube of mass 2 kg",
        "stop it",
    ]
    assert split_clauses("replace box_0 and cylinder_0 with spheres") == ["replace box_0 and cylinder_0 with spheres"]
    for instruction in (
        "replace box_0 with a sphere and cylinder_0 with a box",
        "turn box_0 into a ball and the cylinder into a box",
        "change box_0 to a sphere, and cylinder_0 to a cube",
    ):
        result = apply_instruction(scene, instruction)
        assert [(o.name, o.type) for o in result.scene.objects] == [("sphere_0", "sphere"), ("box_1", "box")]
        assert named_additions(instruction, scene) == {"sphere": 1, "box": 1}
        assert check_output(scene, instruction, f"```yaml\n{dump(result.scene)}```").changes == result.changes
    heavy = apply_instruction(scene, "replace box_0 with a sphere of mass 3 kg and cylinder_0 with a box named crate")
    assert [(o.name, o.physics.mass) for o in heavy.scene.objects] == [("sphere_0", 3.0), ("crate", 1.0)]


@pytest.mark.parametrize(
    "instruction, message",
    [
        ("replace box_7 with a sphere", r"object 'box_7' not found; the scene has \['box_0', 'cylinder_0'\]"),
        ("replace box_0 and cylinder_0 with a sphere", r"1 sphere for 2 objects \['box_0', 'cylinder_0'\]"),
        ("replace all objects with three spheres", r"3 spheres for 2 objects .*; say 'spheres'"),
        ("replace box_0 with two balls", r"2 spheres for 1 object \['box_0'\]: one replaces each; say 'a sphere'"),
        ("replace box_0 with a sphere at [1, 2]", r"a replacement goes where the object it replaces was"),
        ("replace box_0 with a sphere named box_0", "box_0 is a box, so the sphere replacing it needs another name"),
        ("replace box_0 with a sphere named cylinder_0", "the scene already has an object named 'cylinder_0'"),
        ("replace the objects with spheres named b", r"'named b' names one object, not the 2 new ones"),
        ("replace box_0 with a sphere like box_0", r"'like box_0' must name one sphere"),
        ("replace box_0 with a sphere painted red", r"'painted red' not understood. 'replace\|swap"),
        ("remove box_0 and replace it with a sphere", "box_0 was removed by an earlier clause"),
        ("replace box_0 with a sphere; double the mass of box_0", "box_0 was removed by an earlier clause"),
        # the replaced box_0 was listed beside the new one: "['box_0', 'box_0', 'cylinder_0']"
        ("replace box_0 with a cube; stop box_9", r"'box_9' not found; the scene has \['box_0', 'cylinder_0'\]"),
        ("remove box_0; double the mass of box_9", r"'box_9' not found; the scene has \['cylinder_0'\]"),
    ],
)
def test_replace_refusals_name_the_problem(scene, instruction, message):
    with pytest.raises(EditError, match=message):
        apply_instruction(scene, instruction)


@pytest.mark.parametrize(
    "instruction",
    ["put a ball at [1, 2]", "place a sphere at [1, 2]", "drop a sphere at [1, 2]", "add one sphere at [1, 2]"],
)
def test_put_place_and_drop_add(scene, instruction):
    """They add as 'add a sphere at [1, 2]' does: radius 0.2, resting at z 0.2."""
    result = apply_instruction(scene, instruction)
    assert result == apply_instruction(scene, "add a sphere at [1, 2]")
    assert result.scene.object("sphere_0").state.position == (1.0, 2.0, 0.2)


def test_put_with_velocity_and_after_another_clause(scene):
    box = apply_instruction(scene, "place a box at [2, 1, 0.5] moving at [1, 0, 0] m/s").scene.object("box_1")
    assert box.state.position == (2.0, 1.0, 0.5) and box.state.linear_velocity == (1.0, 0.0, 0.0)
    result = apply_instruction(scene, "stop box_0 and drop a sphere at [0, 0, 1] and double its mass")
    assert result.scene.object("sphere_0").physics.mass == 2.0 and result.scene.object("box_0").physics.mass == 1.0


def test_add_a_count_of_objects_one_position_each(scene):
    """'two spheres at [1, 2] and [0, 3]': two default spheres (radius 0.2) resting there, in order; '3 boxes' take
    box_0's shape ([1, 0.5, 0.4]: z 0.4) and each the velocity; 'their' is the three new boxes (mass 1 -> 2, box_0
    keeps 1); a unit after the last position is every position's: [100, 0] and [200, 0] cm are 1 m and 2 m."""
    two = apply_instruction(scene, "add two spheres at [1, 2] and [0, 3]")
    assert [str(c) for c in two.changes] == ["sphere_0: added (sphere)", "sphere_1: added (sphere)"]
    assert [o.state.position for o in two.scene.objects[2:]] == [(1.0, 2.0, 0.2), (0.0, 3.0, 0.2)]
    three = apply_instruction(
        scene, "add 3 boxes at [0, -3], [3, -3] and [6, -3] moving at [1, 0, 0]; double their mass"
    )
    boxes = three.scene.objects[2:]
    assert [o.name for o in boxes] == ["box_1", "box_2", "box_3"]
    assert [o.state.position for o in boxes] == [(0.0, -3.0, 0.4), (3.0, -3.0, 0.4), (6.0, -3.0, 0.4)]
    assert {(o.size, o.state.linear_velocity, o.physics.mass) for o in boxes} == {((1, 0.5, 0.4), (1, 0, 0), 2)}
    assert three.scene.object("box_0").physics.mass == 1.0
    balls = apply_instruction(scene, "add two more balls at [100, 0] and [200, 0] cm").scene.objects[2:]
    assert [o.state.position for o in balls] == [(1.0, 0.0, 0.2), (2.0, 0.0, 0.2)]
    # a unit written once is every position's, wherever it stands (the second was read in metres: 200 m, refused)
    balls = apply_instruction(scene, "add two more balls at [100, 0] cm and [200, 0]").scene.objects[2:]
    assert [o.state.position for o in balls] == [(1.0, 0.0, 0.2), (2.0, 0.0, 0.2)]
    balls = apply_instruction(scene, "add two balls at [1, 0] m and [300, 0] cm").scene.objects[2:]
    assert [o.state.position for o in balls] == [(1.0, 0.0, 0.2), (3.0, 0.0, 0.2)]
    with pytest.raises(EditError, match="positions in cm and m and one without a unit: give each its unit"):
        apply_instruction(scene, "add 3 balls at [100, 0] cm, [2, 0] m and [3, 1]")


@pytest.mark.parametrize(
    "instruction, message",
    [
        ("add two spheres at [1, 2]", r"2 spheres take 2 positions \(one each, in order\), not 1: \[1, 2\]"),
        ("add 3 boxes at [0, 0] and [1, 0]", r"3 boxes take 3 positions \(one each, in order\), not 2"),
        ("add a sphere at [1, 2] and [0, 3]", r"1 sphere takes 1 position \(one each, in order\), not 2"),
        ("add two spheres", r"say where the 2 spheres go \(one position each\)"),
        ("add two spheres at [1, 2] and [0, 3] named b", "'named b' names one object, not 2"),
        ("add 0 spheres at [1, 2]", "a count is at least 1, not '0'"),
    ],
)
def test_add_count_refusals_name_both_numbers(scene, instruction, message):
    with pytest.raises(EditError, match=message):
        apply_instruction(scene, instruction)


def test_positions_and_after_a_count_join_positions_not_clauses():
    """An "and" between positions is no clause break; one before a verb still is (put, place, drop, replace too)."""
    from aynamics.edit import split_clauses
    from aynamics.edit_llm import named_additions

    text = "add two spheres at [1, 2] and [0, 3] and double their mass and replace box_0 with a cube"
    assert split_clauses(text) == [
        "add two spheres at [1, 2] and [0, 3]",
        "double their mass",
        "replace box_0 with a cube",
    ]
    assert split_clauses("stop box_0 and put a ball at [1, 2]") == ["stop box_0", "put a ball at [1, 2]"]
    assert named_additions("add 3 boxes at [0, 0], [1, 0] and [2, 0]; put a ball at [1, 2]") == {"box": 3, "sphere": 1}


def test_several_replacements_split_only_before_a_target():
    """'and of mass 2 kg' is the first replacement's phrase (it was split off as 'replace of mass 2 kg'); a second
    replacement's targets may be joined by 'and' ('box_0 and box_1 with cylinders' was split as 'replace box_0')."""
    from aynamics.edit import split_clauses

    assert split_clauses("replace box_0 with a sphere of radius 0.2 and of mass 2 kg and cylinder_0 with a box") == [
        "replace box_0 with a sphere of radius 0.2 and of mass 2 kg",
        "replace cylinder_0 with a box",
    ]
    assert split_clauses("replace cylinder_0 with a sphere and box_0 and box_1 with cylinders") == [
        "replace cylinder_0 with a sphere",
        "replace box_0 and box_1 with cylinders",
    ]


def test_camera_position_errors_name_no_internal_key():
    from aynamics.edit import EditError, apply_instruction
    from aynamics.scene import load

    scene = load(str(Path(__file__).parent / "assets" / "paper_example.yaml"))
    for text in ("set the camera position to [0, -4, 1, 2]", "set the camera height to 3 kg"):
        with pytest.raises(EditError) as e:
            apply_instruction(scene, text)
        assert "camera_position" not in str(e.value) and "camera position" in str(e.value)
