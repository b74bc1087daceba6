"""OpenGL rendering (skipped with a message where no headless OpenGL works), and the render/score commands."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aynamics import appearance, cli, observation, raycast
from aynamics import flow as flowlib
from aynamics import render as renderlib
from aynamics import scene as scenelib
from aynamics import simulate as sim

GL_OK, GL_WHY = renderlib.gl_available()
needs_gl = pytest.mark.skipif(not GL_OK, reason=f"no headless OpenGL: {GL_WHY}")
PAPER = "tests/assets/paper_example.yaml"
SCENE = scenelib.parse(
    """
- {type: box, name: box_0, size: [0.3, 0.25, 0.2], state: {position: [-0.4, 1.0, 0.2], linear_velocity: [1.5, 0.5, 0]}}
- {type: sphere, name: sphere_0, radius: 0.2, state: {position: [0.6, 1.5, 0.2], linear_velocity: [-0.5, 0, 0]}}
- {type: cylinder, name: cyl_0, radius: 0.15, height: 0.5,
   state: {position: [0.0, 2.3, 0.25], angular_velocity: [0, 0, 3]}}
- type: camera
  position: [0, -2, 3.5]
"""
)


@pytest.fixture(scope="module")
def rollout():
    return sim.simulate(SCENE)


@needs_gl
def test_render_shapes_and_determinism(rollout):
    with renderlib.Renderer(96, 64) as r:
        a = r.render(SCENE, rollout, seed=1, states=[0, 10])
        b = r.render(SCENE, rollout, seed=1, states=[0, 10])
        c = r.render(SCENE, rollout, seed=2, states=[0, 10], segmentation=False, depth=False)
    assert a.rgb.shape == (2, 64, 96, 3) and a.rgb.dtype == np.uint8
    assert a.segmentation.dtype == np.int16 and a.depth.dtype == np.float32
    assert set(np.unique(a.segmentation).tolist()) == {-1, 0, 1, 2}
    assert np.isfinite(a.depth).all()  # the floor fills the view: no sky pixel here
    assert (a.depth > 0).all()
    np.testing.assert_array_equal(a.rgb, b.rgb)
    assert np.abs(a.rgb.astype(int) - c.rgb).mean() > 5  # another seed, another look
    assert c.segmentation is None and c.depth is None


@needs_gl
def test_render_refuses_another_scenes_rollout_and_sizes_that_are_not_whole(rollout):
    """A rollout of the 3-object SCENE drawn for its first object alone was rendered (with that object's poses, no
    error); the other way round an IndexError. A width of 20.5 failed in MuJoCo's MjrRect, True ran as 1 pixel
    until MuJoCo refused it, seed -1 failed in NumPy."""
    items = scenelib.to_items(SCENE)
    one = scenelib.from_items([items[0], *(i for i in items if i["type"] == "camera")])
    with pytest.raises(ValueError, match=r"rollout \(of 3 object\(s\)\) is not a rollout of this scene \(of 1"):
        renderlib.render(one, rollout, width=8, height=8)
    with pytest.raises(ValueError, match=r"render: rollout \(a NoneType\) is not a rollout of this scene"):
        renderlib.render(SCENE, None, width=8, height=8)
    for w in (20.5, True, "20"):
        with pytest.raises(ValueError, match=r"width and height must be whole numbers in \[1, 4096\]"):
            renderlib.render(SCENE, rollout, width=w, height=8)
    with pytest.raises(ValueError, match=r"render: seed = -1: must be a whole number >= 0"):
        renderlib.render(SCENE, rollout, width=8, height=8, seed=-1)
    with pytest.raises(TypeError, match=r"render: scene is a list, not a Scene"):
        renderlib.render([SCENE], rollout, width=8, height=8)


@needs_gl
def test_default_render_has_30_frames_and_29_flows(rollout):
    frames = renderlib.render(SCENE, rollout, width=64, height=48, rgb=False)
    assert frames.segmentation.shape == (30, 48, 64) and frames.states.tolist() == list(range(30))
    flow, occluded = flowlib.motion_flow(SCENE, rollout, frames.depth, frames.camera, frames.segmentation)
    assert flow.shape == (29, 48, 64, 2) and occluded.shape == (29, 48, 64)


@needs_gl
@pytest.mark.parametrize("size", [(120, 80), (480, 320)])
def test_raycast_segmentation_agrees_with_opengl(rollout, size):
    """Ray-cast (scorer) and OpenGL segmentation agree on >= 99.5 % of pixels; depth on objects within 1 cm."""
    w, h = size
    obs = observation.Observation.from_scene(SCENE, width=w, height=h)
    cast = raycast.cast_group([SCENE], SCENE.structure, obs.frames, w, h, obs.config, 1)
    with renderlib.Renderer(w, h) as r:
        frames = r.render(SCENE, rollout, rgb=False, states=obs.frames)
    agree = (frames.segmentation == obs.segmentation).mean()
    assert agree >= 0.995, agree
    both = (frames.segmentation >= 0) & (obs.segmentation >= 0)
    assert np.median(np.abs(frames.depth[both] - cast.depth[0][both])) < 0.01


@needs_gl
def test_opengl_flow_matches_raycast_flow(rollout):
    """Flow from OpenGL depth equals the scorer's ray-cast flow where both see the same object (< 0.1 px)."""
    w, h = 120, 80
    obs = observation.Observation.from_scene(SCENE, width=w, height=h)
    with renderlib.Renderer(w, h) as r:
        frames = r.render(SCENE, rollout, rgb=False)
    flow, _ = flowlib.motion_flow(SCENE, rollout, frames.depth, frames.camera, frames.segmentation)
    gl = flow[obs.frames]
    same = (frames.segmentation[obs.frames] == obs.segmentation) & (obs.segmentation >= 0)
    err = np.linalg.norm(gl[same] - obs.flow[same], axis=-1)
    assert same.sum() > 500 and np.mean(err) < 0.1, np.mean(err)


def test_appearance_from_user_folder(tmp_path):
    import imageio.v3 as iio

    assert appearance.sample_appearance(3) == appearance.sample_appearance(3)
    assert appearance.sample_appearance(3) != appearance.sample_appearance(4)
    with pytest.raises(FileNotFoundError, match="not a folder"):
        appearance.sample_appearance(0, tmp_path / "nope")
    with pytest.raises(ValueError, match="no images"):
        appearance.sample_appearance(0, tmp_path)
    iio.imwrite(tmp_path / "a.png", np.zeros((8, 8, 3), np.uint8))
    look = appearance.sample_appearance(0, tmp_path)
    assert look.floor_image == look.sky_image == tmp_path / "a.png"
    assert 1 <= len(look.lights) <= 3 and {o.kind for o in appearance.sample_appearance(0).objects} == {
        "checker",
        "gradient",
        "plain",
    }


@needs_gl
def test_plain_backdrop_is_one_flat_colour(rollout):
    look = appearance.sample_appearance(5, backdrop="plain")
    assert look.floor_image is None and look.sky_image is None
    with pytest.raises(ValueError, match="backdrop = 'tiles'"):
        appearance.sample_appearance(5, backdrop="tiles")
    with renderlib.Renderer(96, 64) as r:
        plain = r.render(SCENE, rollout, seed=5, backdrop="plain", states=[0])
        photo = r.render(SCENE, rollout, seed=5, states=[0])
    floor = plain.segmentation[0] == -1  # floor pixels: shading varies (lights, shadows), texture does not
    assert floor.sum() > 1000

    # a flat floor has almost no pixel-to-pixel texture; a photograph has plenty
    def texture(frames):
        rgb = frames.rgb[0].astype(float)
        d = np.abs(np.diff(rgb, axis=1)).sum(-1)
        return np.median(d[floor[:, 1:] & floor[:, :-1]])

    assert texture(plain) <= 3 < texture(photo)


def test_bad_backend_gives_clear_message(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "glx-please")
    with pytest.raises(renderlib.RenderError, match="MUJOCO_GL = 'glx-please'"):
        renderlib.gl_backend()


def _main(argv: list[str]) -> int:
    """The real `main`, error handling included (only the named subcommand's module is imported)."""
    return cli.main(argv)


@needs_gl
def test_cli_render_then_score(tmp_path, capsys):
    out = tmp_path / "obs"
    assert _main(["render", PAPER, "--out", str(out), "--width", "96", "--height", "64", "--no-gif"]) == 0
    for name in ("segmentation.npy", "depth.npy", "flow.npy", "occlusion.npy", "camera.json", "meta.json"):
        assert (out / name).is_file(), name
    assert len(list((out / "frames").glob("*.png"))) == 30 and len(list((out / "flow").glob("*.png"))) == 29
    assert json.loads((out / "camera.json").read_text())["K"][0][2] == 48.0
    meta = json.loads((out / "meta.json").read_text())  # 1 s at 30 FPS: 31 states, frames show states 0..29
    assert meta["states"] == list(range(30)) and meta["fps"] == 30 and (meta["width"], meta["height"]) == (96, 64)
    (out / "video.gif").write_bytes(b"an earlier render's preview")  # of another scene: not left beside these
    assert _main(["render", PAPER, "--out", str(out), "--width", "96", "--height", "64", "--no-gif"]) == 0
    assert not (out / "video.gif").exists()
    capsys.readouterr()
    bad = tmp_path / "bad.yaml"
    bad.write_text("- type: box\n  size: [1, -1, 1]\n")
    assert _main(["score", PAPER, str(bad), "--observed", str(out), "--json", "--width", "48", "--height", "32"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [r["valid"] for r in result] == [True, False]
    assert result[0]["iou_full"] > 0.8 and result[1]["iou_full"] == 0.0 and "size" in result[1]["reason"]


def test_cli_errors(tmp_path, capsys):
    assert _main(["score", PAPER, "--observed", str(tmp_path / "none")]) == 2
    assert "none" in capsys.readouterr().err
    assert _main(["render", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert "No such file" in capsys.readouterr().err
    assert _main(["score", PAPER, "--observed", PAPER, "--width", "2"]) == 2
    assert "--width 2" in capsys.readouterr().err
    # a mistyped prediction path is a usage error (it printed an INVALID score and exited 0)
    assert _main(["score", str(tmp_path / "nosuch.yaml"), "--observed", PAPER]) == 2
    assert f"prediction file(s) not found: '{tmp_path / 'nosuch.yaml'}'" in capsys.readouterr().err


@needs_gl
def test_ambient_light_reaches_the_picture(monkeypatch):
    """The appearance's ambient light lifts faces the lights do not reach: with it at 0 the paper scene's objects
    show 97 of 213 pixels pure black at 120x80 (seed 1; what every render looked like while the ambient sat on an
    inactive headlight), at the sampler's 0.35 none."""
    import dataclasses

    scene = scenelib.load(PAPER)
    rollout = sim.simulate(scene)
    sample = renderlib.sample_appearance

    def first_frame(ambient):
        monkeypatch.setattr(
            renderlib, "sample_appearance", lambda *a, **k: dataclasses.replace(sample(*a, **k), ambient=ambient)
        )
        frames = renderlib.render(scene, rollout, width=120, height=80, seed=1, backdrop="plain", depth=False)
        return frames.rgb[0].astype(int), frames.segmentation[0] >= 0

    (dark, objects), (lit, _) = first_frame(0.0), first_frame(0.35)
    assert objects.sum() > 150
    black = lambda img: int((img[objects].max(-1) < 8).sum())  # noqa: E731
    assert black(dark) > 50 and black(lit) == 0
    assert (lit >= dark).all() and np.abs(lit - dark).max() > 50


def test_texture_photographs_are_read_as_shown(tmp_path):
    """A textures_dir takes WebP photographs too (the frames' image types: render kept a shorter list), and a phone
    photograph is used as it shows (EXIF orientation applied: red on top, not on the left); a broken file is named."""
    import numpy as np
    from PIL import Image

    from aynamics.appearance import texture_images
    from aynamics.render import _load_texture

    img = Image.new("RGB", (16, 16), (0, 0, 255))
    img.paste((255, 0, 0), (0, 0, 8, 16))  # red left half; orientation 6 shows it rotated 90° clockwise: on top
    exif = Image.Exif()
    exif[0x0112] = 6
    img.save(tmp_path / "phone.jpg", exif=exif, quality=100)
    Image.new("RGB", (4, 4), (0, 255, 0)).save(tmp_path / "leaf.webp", lossless=True)
    assert [p.name for p in texture_images(tmp_path)] == ["leaf.webp", "phone.jpg"]
    shown = np.frombuffer(_load_texture(tmp_path / "phone.jpg", 4), np.uint8).reshape(4, 4, 3)
    assert shown[0, :, 0].min() > 200 and shown[3, :, 0].max() < 60  # red on top, not in the bottom row
    (tmp_path / "broken.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="texture image .*broken.png.* cannot be read"):
        _load_texture(tmp_path / "broken.png", 4)
