"""The fast scorer: self-consistency, monotonicity, invalid candidates, observed folders."""

from __future__ import annotations

import json
import re

import imageio.v3 as iio
import numpy as np
import pytest

from aynamics import observation, raycast, scorer
from aynamics import scene as scenelib

SCENE = scenelib.parse(
    """
- type: box
  name: box_0
  size: [0.3, 0.25, 0.2]
  state: {position: [-0.4, 1.0, 0.2], linear_velocity: [1.5, 0.5, 0.0]}
  physics: {friction: [0.3, 0.0]}
- type: sphere
  name: sphere_0
  radius: 0.2
  state: {position: [0.6, 1.5, 0.2], linear_velocity: [-0.5, 0.0, 0.0]}
- type: camera
  position: [0, -2, 3.5]
"""
)
W, H = 96, 64


@pytest.fixture(scope="module")
def observed() -> observation.Observation:
    return observation.Observation.from_scene(SCENE, width=W, height=H)


def _moved(scene: scenelib.Scene, dx: float) -> scenelib.Scene:
    box = scene.objects[0]
    x, y, z = box.state.position
    box = box.model_copy(update={"state": box.state.model_copy(update={"position": (x + dx, y, z)})})
    return scene.model_copy(update={"objects": (box, *scene.objects[1:])})


def test_self_score_is_perfect(observed):
    assert len(observed.frames) == 10 and observed.segmentation.shape == (10, H, W)
    assert {0, 1} <= set(np.unique(observed.segmentation).tolist())
    (s,) = scorer.score([SCENE], observed)
    assert (s.iou_first, s.iou_full, s.epe_first, s.epe_full, s.valid, s.reason) == (1.0, 1.0, 0.0, 0.0, True, None)
    (t,) = scorer.score([scenelib.dump(SCENE)], observed)  # text candidates are parsed
    assert t == s


def test_one_candidate_or_a_scene_as_observed_is_refused(observed):
    """A YAML text given where the list of candidates goes was scored as its characters (one invalid Score per
    character, no error); a Scene where the Observation goes failed inside with "no attribute 'frames'"."""
    text = scenelib.dump(SCENE)
    with pytest.raises(TypeError, match=r"score: candidates is a str: must be a list of scenes or texts"):
        scorer.score(text, observed)
    with pytest.raises(TypeError, match=r"score: candidates is a Scene: must be a list"):
        scorer.score(SCENE, observed)
    with pytest.raises(TypeError, match=r"score: observed is a Scene, not an Observation"):
        scorer.score([SCENE], SCENE)
    assert scorer.score((text,), observed)[0].iou_full == 1.0 and scorer.score([], observed) == []


def test_observation_from_scene_names_a_bad_size_rate_or_frame_list():
    """width 0 gave an observation with no pixels (scoring against it: a ZeroDivisionError), -5 NumPy's "negative
    dimensions", fps 0 a ZeroDivisionError, frames [1.7] was frame 1 and [[0, 3]]
    a broadcasting error inside the ray cast; a YAML text "no attribute 'structure'"."""
    for kw, message in [
        ({"width": 0}, r"width = 0: must be a whole number in \[1, 4096\]"),
        ({"height": -5}, r"height = -5: must be a whole number in \[1, 4096\]"),
        ({"width": 1.5}, r"width = 1.5: must be a whole number"),
        ({"fps": 0}, r"fps = 0: must be a whole number in \[1, 1000\]"),
        ({"frames": [1.7]}, r"frames = \[1.7\]: must be a list of whole frame indices"),
        ({"frames": [[0, 3]]}, r"frames = \[\[0, 3\]\]: must be a list of whole frame indices"),
    ]:
        with pytest.raises(ValueError, match=f"Observation.from_scene: {message}"):
            observation.Observation.from_scene(SCENE, **kw)
    with pytest.raises(TypeError, match=r"Observation.from_scene: scene is a str, not a Scene"):
        observation.Observation.from_scene(scenelib.dump(SCENE))
    assert observation.Observation.from_scene(SCENE, width=6, height=4, frames=[3.0]).frames.tolist() == [3]


def test_a_batch_that_fails_is_scored_one_by_one(observed, monkeypatch):
    """When simulating a structure group raises (a MuJoCo error on one candidate), each candidate is scored alone:
    the good ones get their solo scores, the broken one is invalid naming the error."""
    good = [_moved(SCENE, 0.1), _moved(SCENE, -0.2)]
    solo = [scorer.score([g], observed)[0] for g in good]
    broken = _moved(SCENE, 0.3)
    original = scorer.cast_group

    def cast_group(scenes, *args, **kw):
        if any(s is broken for s in scenes):
            raise RuntimeError("mj_step: bad state")
        return original(scenes, *args, **kw)

    monkeypatch.setattr(scorer, "cast_group", cast_group)
    batch = scorer.score([good[0], broken, good[1]], observed)
    assert [s.valid for s in batch] == [True, False, True]
    assert batch[0] == solo[0] and batch[2] == solo[1]
    assert batch[1].reason == "simulation failed: RuntimeError: mj_step: bad state" and batch[1].iou_full == 0.0


def test_observed_folder_flow_is_resampled_and_rescaled(tmp_path):
    """A folder at 240×160 (every frame: masks, flow, occlusion, as `aynamics render` writes) loads at the scorer's
    120×80: masks taken at the nearest pixel centres, flow vectors halved with the width, occlusion kept; it then
    agrees with the scene observed directly at 120×80 (measured: masks 99.9 % equal, flow 1.2 % of its mean length
    off; asserted: 99 % and 5 %)."""
    full = observation.Observation.from_scene(SCENE, width=240, height=160, frames=np.arange(30))
    folder = tmp_path / "observed"
    folder.mkdir()
    np.save(folder / "segmentation.npy", full.segmentation)
    np.save(folder / "flow.npy", full.flow[:29])
    np.save(folder / "occlusion.npy", full.occluded[:29])
    obs = observation.Observation.from_dir(folder)
    direct = observation.Observation.from_scene(SCENE)
    assert (obs.width, obs.height) == (120, 80) and obs.frames.tolist() == direct.frames.tolist()
    rows, cols = np.arange(80) * 2 + 1, np.arange(120) * 2 + 1  # nearest full-resolution pixel centres
    frames = obs.frames
    np.testing.assert_array_equal(obs.segmentation, full.segmentation[frames][:, rows][:, :, cols])
    np.testing.assert_array_equal(obs.flow, full.flow[frames][:, rows][:, :, cols] * 0.5)
    np.testing.assert_array_equal(obs.occluded, full.occluded[frames][:, rows][:, :, cols])
    assert (obs.segmentation == direct.segmentation).mean() > 0.99
    on = (obs.segmentation >= 0) & (direct.segmentation >= 0)
    err = np.linalg.norm(obs.flow[on] - direct.flow[on], axis=-1).mean()
    assert err < 0.05 * np.linalg.norm(direct.flow[on], axis=-1).mean()


@pytest.mark.parametrize("full", [(480, 320), (300, 200)])
def test_true_scene_meets_its_own_masks_read_from_a_larger_video(tmp_path, full):
    """A folder of the scene's masks and flow at 480×320 (or 300×200: 2.5 video pixels per scorer pixel), read at
    the scorer's 120×80, keeps the video pixel nearest each scorer pixel; candidates are cast at those pixels'
    centres, so the true scene scores IoU 1 and EPE 0 against it. Cast at the 120×80 pixel centres it scored full
    IoU 0.961 / 0.957 and EPE 0.035 / 0.027 px (measured on this scene before the sample grid)."""
    obs_full = observation.Observation.from_scene(SCENE, width=full[0], height=full[1], frames=np.arange(30))
    np.save(tmp_path / "segmentation.npy", obs_full.segmentation)
    np.save(tmp_path / "flow.npy", obs_full.flow[:29])
    np.save(tmp_path / "occlusion.npy", obs_full.occluded[:29])
    obs = observation.Observation.from_dir(tmp_path)
    assert (obs.width, obs.height) == (120, 80)
    np.testing.assert_array_equal(obs.grid.columns, ((np.arange(120) + 0.5) * full[0] / 120).astype(int))
    (got,) = scorer.score([SCENE], obs)
    assert got.valid and got.iou_first == got.iou_full == 1.0
    assert got.epe_first < 1e-4 and got.epe_full < 1e-4


def test_iou_falls_monotonically_with_position_error(observed):
    scores = scorer.score([_moved(SCENE, dx) for dx in (0.0, 0.05, 0.1, 0.2, 0.4, 0.8)], observed)
    ious = [s.iou_full for s in scores]
    assert ious[0] == 1.0
    assert all(a > b for a, b in zip(ious, ious[1:], strict=False)), ious
    assert scores[-1].epe_full > scores[1].epe_full > 0


def test_invalid_candidates_score_zero_with_reason_and_do_not_spoil_others(observed):
    tunnelled = SCENE.model_copy(
        update={
            "objects": (
                SCENE.objects[0],
                SCENE.objects[1].model_copy(
                    update={
                        "radius": 0.05,
                        "state": SCENE.objects[1].state.model_copy(update={"position": (0, 1, -0.4)}),
                    }
                ),
            )
        }
    )
    good = _moved(SCENE, 0.1)
    alone = scorer.score([good], observed)[0]
    batch = scorer.score(["- type: box\n  size: [1, 1, 1]\n", good, "{{{", tunnelled, SCENE], observed)
    assert [s.valid for s in batch] == [False, True, False, False, True]
    for s in (batch[0], batch[2], batch[3]):
        assert s.iou_first == s.iou_full == 0.0 and s.epe_full == scorer.EPE_INVALID and s.reason
    assert "objects[0].state" in batch[0].reason
    assert "overlapping start: sphere_0 and the floor" in batch[3].reason  # it starts under the floor
    assert batch[1] == alone  # same numbers as when scored alone
    assert batch[4].iou_full == 1.0
    assert json.loads(json.dumps([s.to_json() for s in batch]))[2]["valid"] is False


def test_candidate_with_other_structure_and_camera(observed):
    """A candidate missing the sphere scores below 1; one seen from another camera differs too."""
    only_box = SCENE.model_copy(update={"objects": SCENE.objects[:1]})
    other_cam = SCENE.model_copy(update={"camera": SCENE.camera.model_copy(update={"position": (0.3, -2.0, 3.5)})})
    a, b = scorer.score([only_box, other_cam], observed)
    assert a.valid and b.valid and 0 < a.iou_full < 1 and 0 < b.iou_full < 1


def test_observation_from_dir_npy_and_png(tmp_path, observed):
    """A folder of the full video's masks (every frame) scores the scene perfectly, as .npy and as PNG."""
    full = observation.Observation.from_scene(SCENE, width=W, height=H, frames=range(30))
    npy = tmp_path / "npy"
    npy.mkdir()
    np.save(npy / "segmentation.npy", full.segmentation)
    (npy / "meta.json").write_text(json.dumps({"names": list(SCENE.names), "fps": 30}))
    png = tmp_path / "png" / "segmentation"
    png.mkdir(parents=True)
    for k, m in enumerate(full.segmentation):
        iio.imwrite(png / f"{k:03d}.png", (m + 1).astype(np.uint8))
    la = tmp_path / "la" / "segmentation"  # grey + alpha PNGs, as some editors save masks
    la.mkdir(parents=True)
    for k, m in enumerate(full.segmentation):
        grey = (m + 1).astype(np.uint8)
        iio.imwrite(la / f"{k:03d}.png", np.stack([grey, np.full_like(grey, 255)], -1))
    for root in (npy, tmp_path / "png", tmp_path / "la"):
        obs = observation.Observation.from_dir(root, width=W, height=H)
        np.testing.assert_array_equal(obs.segmentation, observed.segmentation)
        assert obs.flow is None
        (s,) = scorer.score([SCENE], obs)
        assert (s.iou_first, s.iou_full, s.epe_full, s.valid) == (1.0, 1.0, None, True)


def test_observation_from_dir_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        observation.Observation.from_dir(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="segmentation"):
        observation.Observation.from_dir(tmp_path)
    np.save(tmp_path / "segmentation.npy", np.zeros((30, 8, 8), np.float32))
    with pytest.raises(ValueError, match="segmentation.npy.*expected"):
        observation.Observation.from_dir(tmp_path, width=8, height=8)
    np.save(tmp_path / "segmentation.npy", np.zeros((30, 8, 8), np.int16))
    np.save(tmp_path / "flow.npy", np.zeros((29, 8, 4, 2), np.float32))
    with pytest.raises(ValueError, match="flow.npy"):
        observation.Observation.from_dir(tmp_path, width=8, height=8)
    (tmp_path / "flow.npy").unlink()
    for fps in (0, -30, 29.97, "30", True):  # a zero frame rate divided the duration by zero
        (tmp_path / "meta.json").write_text(json.dumps({"fps": fps}))
        with pytest.raises(ValueError, match=rf"meta.json: fps = {re.escape(repr(fps))}: must be a whole number"):
            observation.Observation.from_dir(tmp_path, width=8, height=8)
    (tmp_path / "meta.json").write_text(json.dumps({"names": "box_0"}))  # was split into 5 one-letter names
    with pytest.raises(ValueError, match="names = 'box_0': must be a list"):
        observation.Observation.from_dir(tmp_path, width=8, height=8)
    (tmp_path / "meta.json").unlink()
    flow = np.zeros((29, 8, 8, 2), np.float32)
    flow[3, 2, 2] = np.nan  # sampled flow 3: NaN dropped out of the averages, so any prediction scored EPE 0
    np.save(tmp_path / "flow.npy", flow)
    with pytest.raises(
        ValueError, match=r"flow.npy: 1 sampled pixels hold NaN or infinite flow \(the first in flow 3\)"
    ):
        observation.Observation.from_dir(tmp_path, width=8, height=8)
    occluded = np.zeros((29, 8, 8), bool)
    occluded[3, 2, 2] = True  # ... unless occlusion.npy marks the pixel: it is never read
    np.save(tmp_path / "occlusion.npy", occluded)
    obs = observation.Observation.from_dir(tmp_path, width=8, height=8)
    assert np.isfinite(obs.flow).all() and obs.occluded[1, 2, 2]
    # a pixel moving more than 10 image sizes (10 × 8 = 80 px here) in one frame is refused, named with its
    # place and value (one object pixel of 1e38 px gave the true scene an EPE of 1.9e36 px); 80 px exactly is kept
    flow[6, 4, 5] = (80.0, 0.0)
    np.save(tmp_path / "flow.npy", flow)
    assert observation.Observation.from_dir(tmp_path, width=8, height=8).flow[2, 4, 5, 0] == 80.0
    flow[6, 4, 5] = (3.0, 1e38)
    np.save(tmp_path / "flow.npy", flow)
    with pytest.raises(ValueError) as err:
        observation.Observation.from_dir(tmp_path, width=8, height=8)
    assert str(err.value).endswith(
        "flow.npy: 1 sampled pixels move more than 10 image sizes in one frame (the first in flow 6, row 4, "
        f"column 5: [3.0, {float(np.float32(1e38))}] px): is it in pixels per frame?"
    )
    occluded[6, 4, 5] = True  # where occlusion.npy marks it, never read
    np.save(tmp_path / "occlusion.npy", occluded)
    assert observation.Observation.from_dir(tmp_path, width=8, height=8).occluded[2, 4, 5]


def test_observed_masks_without_frames_or_pixels_are_named(tmp_path):
    """A segmentation.npy of 0 frames read "sample_frames(n_frames=0, stride=3): both must be >= 1", naming no file."""
    for shape, what in (((0, 8, 8), "0 frame(s) of 8×8 pixels"), ((30, 0, 8), "30 frame(s) of 8×0 pixels")):
        np.save(tmp_path / "segmentation.npy", np.zeros(shape, np.int16))
        message = f"segmentation: {what}: need at least one frame of at least 1×1"
        with pytest.raises(ValueError, match=re.escape(message)):
            observation.Observation.from_dir(tmp_path)


def test_observed_ids_beyond_int16_are_refused(tmp_path):
    """Ids the int16 masks cannot hold wrapped silently (40000 -> -25536: background; 65536 -> object 0)."""
    for bad in (40000, 65536, -5):
        seg = np.full((30, 8, 8), -1, np.int64)
        seg[:, 2:4, 2:4] = bad
        np.save(tmp_path / "segmentation.npy", seg)
        with pytest.raises(ValueError, match=rf"segmentation: object id {bad}: ids must be -1"):
            observation.Observation.from_dir(tmp_path, width=8, height=8)
    (tmp_path / "segmentation.npy").unlink()
    (tmp_path / "segmentation").mkdir()
    for k in range(30):  # a 16-bit grey mask, v = id + 1
        iio.imwrite(tmp_path / "segmentation" / f"{k:03d}.png", np.full((8, 8), 40001, np.uint16))
    with pytest.raises(ValueError, match="object id 40000"):
        observation.Observation.from_dir(tmp_path, width=8, height=8)


def test_unreadable_mask_png_is_named(tmp_path):
    import imageio.v3 as iio

    (tmp_path / "segmentation").mkdir()
    for k in range(30):
        iio.imwrite(tmp_path / "segmentation" / f"{k:03d}.png", np.zeros((8, 8), np.uint8))
    bad = tmp_path / "segmentation" / "007.png"
    bad.write_bytes(bad.read_bytes()[:30])  # truncated
    with pytest.raises(ValueError, match=r"007.png: not a readable PNG mask"):
        observation.Observation.from_dir(tmp_path, width=8, height=8)


@pytest.mark.parametrize("empty_frame", [False, True], ids=["as observed", "frame 2 shows nothing"])
def test_sparse_scores_equal_dense_metrics(observed, empty_frame):
    """The scorer's sparse metrics equal `aynamics.metrics` on the dense arrays of the same candidates, also in a
    frame where the video shows no object (EPE then averages over the predicted pixels)."""
    import dataclasses

    from aynamics import metrics

    if empty_frame:
        seg = observed.segmentation.copy()
        seg[2] = -1
        observed = dataclasses.replace(observed, segmentation=seg)
    cands = [_moved(SCENE, dx) for dx in (0.03, 0.15, 0.5)]
    cast = raycast.cast_group(cands, SCENE.structure, observed.frames, W, H, observed.config, 1)
    seg, flow = cast.seg, cast.dense_flow
    assert (seg[:, 2] >= 0).any()
    for k, s in enumerate(scorer.score(cands, observed)):
        iou = metrics.segmentation_iou(seg[k], observed.segmentation, pred_names=SCENE.names, obs_names=SCENE.names)
        epe = metrics.flow_epe(flow[k], observed.flow, seg[k], observed.segmentation, observed.occluded)
        assert (s.iou_first, s.iou_full) == pytest.approx(iou, abs=1e-12)
        assert (s.epe_first, s.epe_full) == pytest.approx(tuple(x * 480 / W for x in epe), abs=1e-6)


def test_observed_flow_and_occlusion_shapes_are_checked(tmp_path):
    """30 frames sample 0, 3, ..., 27, whose flow targets need 28 flows: 28 load; 27 (one short) is a ValueError
    naming flow.npy and its shape; an occlusion.npy not of the flow's (T-1, H, W) shape likewise."""
    np.save(tmp_path / "segmentation.npy", np.zeros((30, 8, 8), np.int16))
    np.save(tmp_path / "flow.npy", np.zeros((28, 8, 8, 2), np.float32))
    assert observation.Observation.from_dir(tmp_path, width=8, height=8).flow.shape == (10, 8, 8, 2)
    np.save(tmp_path / "flow.npy", np.zeros((27, 8, 8, 2), np.float32))
    with pytest.raises(ValueError, match=re.escape("flow.npy: shape (27, 8, 8, 2), expected (>= 28, 8, 8, 2)")):
        observation.Observation.from_dir(tmp_path, width=8, height=8)
    np.save(tmp_path / "flow.npy", np.zeros((29, 8, 8, 2), np.float32))
    np.save(tmp_path / "occlusion.npy", np.zeros((29, 8, 4), bool))
    with pytest.raises(ValueError, match=re.escape("occlusion.npy: shape (29, 8, 4), expected (29, 8, 8)")):
        observation.Observation.from_dir(tmp_path, width=8, height=8)


def test_colour_png_masks(tmp_path):
    """RGB masks: black is background, each other colour one object in colour-code order (green 0x00FF00 before
    red 0xFF0000): ids -1, 0, 1. A video without any black pixel has no background: red and green are 1 and 0."""
    black, red, green = (0, 0, 0), (255, 0, 0), (0, 255, 0)
    for name, colours in (("bg", (black, red, green)), ("nobg", (red, green, red))):
        folder = tmp_path / name / "segmentation"
        folder.mkdir(parents=True)
        img = np.zeros((8, 8, 3), np.uint8)
        for k, c in enumerate(colours):
            img[:, 3 * k :] = c  # columns 0-2, 3-5, 6-7
        for k in range(30):
            iio.imwrite(folder / f"{k:03d}.png", img)
        seg = observation.Observation.from_dir(tmp_path / name, width=8, height=8).segmentation
        expected = [-1] * 3 + [1] * 3 + [0] * 2 if name == "bg" else [1] * 3 + [0] * 3 + [1] * 2
        assert seg.shape == (10, 8, 8) and (seg == np.array(expected)).all()


def test_named_observed_object_never_visible_is_not_stolen():
    """meta names (a, b, c) with c never visible; the candidate draws a exactly and names its sphere c, on top of
    observed b. c pairs with the invisible c (IoU 0), not with b by overlap: per frame visible are predicted a and
    c, observed a and b, the a pair counted once -> 3, IoU = 1 / 3 (pairing c with b would give 1)."""
    import dataclasses

    cam = "- type: camera\n  position: [0, -2, 3.5]\n"
    box = "- {type: box, name: a, size: [0.15, 0.15, 0.15], state: {position: [-0.5, 1, 0.15]}}\n"
    sphere = "- {{type: sphere, name: {}, radius: 0.2, state: {{position: [0.5, 1, 0.2]}}}}\n"
    obs = observation.Observation.from_scene(scenelib.parse(box + sphere.format("b") + cam), width=48, height=32)
    assert all(np.unique(m).tolist() == [-1, 0, 1] for m in obs.segmentation)  # both in view, apart, every frame
    obs = dataclasses.replace(obs, names=("a", "b", "c"))
    (s,) = scorer.score([scenelib.parse(box + sphere.format("c") + cam)], obs)
    assert s.iou_first == pytest.approx(1 / 3) and s.iou_full == pytest.approx(1 / 3)


def test_epe_first_is_zero_when_frame_0_shows_nothing():
    """A sphere entering the view from x = -4 (8 m/s observed, 7 m/s predicted): frame 0 shows no object on either
    side, so its EPE is 0, as `metrics.flow_epe`'s first-frame figure; later frames differ (EPE > 0)."""
    from aynamics import metrics

    cam = "- type: camera\n  position: [0, -2, 3.5]\n"
    text = "- {{type: sphere, radius: 0.2, state: {{position: [-4, 1, 0.2], linear_velocity: [{}, 0, 0]}}}}\n" + cam
    obs = observation.Observation.from_scene(scenelib.parse(text.format(8)), width=48, height=32)
    cand = scenelib.parse(text.format(7))
    cast = raycast.cast_group([cand], cand.structure, obs.frames, 48, 32, obs.config, 1)
    assert not (obs.segmentation[0] >= 0).any() and not (cast.seg[0, 0] >= 0).any()
    first, full = metrics.flow_epe(cast.dense_flow[0], obs.flow, cast.seg[0], obs.segmentation, obs.occluded)
    (s,) = scorer.score([cand], obs)
    assert s.epe_first == first == 0.0 and s.iou_first == 1.0
    assert s.epe_full == pytest.approx(full * 480 / 48) and s.epe_full > 0


def test_observation_simulates_up_to_its_last_frame():
    """The rollout covers the last sampled frame and its flow target: frames [0, 40] need 41 frames, 41 / 30 s;
    frames [0, 3] still simulate the whole 30-frame video (1 s)."""
    seg = np.zeros((2, 4, 4), np.int16)
    assert observation.Observation(seg, np.array([0, 40]), 4, 4).config.duration == pytest.approx(41 / 30)
    assert observation.Observation(seg, np.array([0, 3]), 4, 4).config.duration == pytest.approx(1.0)


def test_an_observation_built_directly_is_checked_as_from_dir_checks_its_files():
    """Observation(...) built directly took NaN flow (it dropped out of the EPE averages: a wrong candidate scored
    EPE 0), float ids (truncated: 0.7 was object 0), ids below -1 and int 0/1 occlusion (~ made it -1/-2: every
    pixel seen). NaN or infinite flow where `occluded` marks the pixel passes (never read), and so do int flow and
    int64 ids."""
    seg, frames = np.zeros((1, 4, 4), np.int16), np.array([0])
    flow = np.zeros((1, 4, 4, 2), np.float32)
    assert observation.Observation(seg.astype(np.int64), frames, 4, 4, flow.astype(int)).flow is not None
    occluded = np.zeros((1, 4, 4), bool)
    occluded[0, 1, 2] = True
    for value, shown in (((np.nan, 0.0), r"\[nan, 0.0\]"), ((1.0, -np.inf), r"\[1.0, -inf\]")):
        bad = flow.copy()
        bad[0, 1, 2] = value
        with pytest.raises(ValueError, match=rf"flow\[0, 1, 2\] = {shown}: 1 pixels not occluded hold NaN or infinite"):
            observation.Observation(seg, frames, 4, 4, bad)
        assert observation.Observation(seg, frames, 4, 4, bad, occluded).occluded[0, 1, 2]
    with pytest.raises(ValueError, match=r"segmentation dtype float64: must be signed int ids, -1 background"):
        observation.Observation(seg + 0.7, frames, 4, 4)
    with pytest.raises(ValueError, match=r"segmentation dtype int16, lowest id -2: must be signed int ids"):
        observation.Observation(seg - 2, frames, 4, 4)
    with pytest.raises(ValueError, match=r"occluded ndarray of shape \(1, 4, 4\) dtype int64: must be a bool array"):
        observation.Observation(seg, frames, 4, 4, flow, occluded.astype(int))
    with pytest.raises(ValueError, match=r"occluded ndarray of shape \(1, 4, 2\) dtype bool: must be a bool array"):
        observation.Observation(seg, frames, 4, 4, flow, occluded[:, :, :2])


def test_unsigned_segmentation_npy_is_refused_naming_the_file(tmp_path):
    """uint8 masks (0 background, as most tools save them) cannot hold -1: min(initial=-1) raised OverflowError (a
    traceback from `refine`/`score`); now a ValueError naming the file and the fix."""
    np.save(tmp_path / "segmentation.npy", np.zeros((30, 8, 8), np.uint8))
    with pytest.raises(ValueError, match=r"segmentation.npy: dtype uint8 cannot hold the background id -1"):
        observation.Observation.from_dir(tmp_path, width=8, height=8)


def test_colour_and_palette_masks_follow_the_names_in_meta_json(tmp_path):
    """Names in meta.json pair by index with mask ids. RGB masks number objects by colour code, so red 'a' and
    green 'b' were read as ids 1 and 0 and the names swapped: refused without "colours", right with them.
    A palette PNG (DAVIS-style) is read by its indices, like grey (index 1 is object 0)."""
    from PIL import Image

    red, green = (255, 0, 0), (0, 255, 0)
    img = np.zeros((8, 8, 3), np.uint8)
    img[:, :4], img[:, 4:] = red, green
    rgb = tmp_path / "rgb"
    (rgb / "segmentation").mkdir(parents=True)
    for k in range(30):
        iio.imwrite(rgb / "segmentation" / f"{k:03d}.png", img)
    (rgb / "meta.json").write_text(json.dumps({"names": ["a", "b"]}))
    with pytest.raises(ValueError, match=r"colour masks.*add \"colours\""):
        observation.Observation.from_dir(rgb, width=8, height=8)
    (rgb / "meta.json").write_text(json.dumps({"names": ["a", "b"], "colours": [list(red), list(green)]}))
    seg = observation.Observation.from_dir(rgb, width=8, height=8).segmentation
    assert (seg[:, :, :4] == 0).all() and (seg[:, :, 4:] == 1).all()
    pal = tmp_path / "pal"
    (pal / "segmentation").mkdir(parents=True)
    index = np.zeros((8, 8), np.uint8)
    index[:, :4], index[:, 4:] = 1, 2
    for k in range(30):
        im = Image.fromarray(index, mode="P")
        im.putpalette([0, 0, 0, 128, 0, 0, 0, 128, 0])  # index 2's colour sorts before index 1's
        im.save(pal / "segmentation" / f"{k:03d}.png")
    seg = observation.Observation.from_dir(pal, width=8, height=8).segmentation
    assert (seg[:, :, :4] == 0).all() and (seg[:, :, 4:] == 1).all()


def test_scoring_size_keeps_the_videos_aspect_from_either_side():
    """A 480×320 video (3:2): by default 80 rows and 80 · 480 / 320 = 120 columns; given the width 60 alone, the
    height is 60 · 320 / 480 = 40; given the height 40 alone, the width is 40 · 480 / 320 = 60. A 100×50 video
    smaller than 80 rows keeps its own 50 rows. 120×90 is off 3:2 by 15 columns: refused."""
    from aynamics.observation import scoring_size

    assert scoring_size(480, 320) == (120, 80)
    assert scoring_size(480, 320, width=60) == (60, 40)
    assert scoring_size(480, 320, height=40) == (60, 40)
    assert scoring_size(100, 50) == (100, 50)
    with pytest.raises(ValueError, match="off the video's aspect ratio"):
        scoring_size(480, 320, 120, 90)


@pytest.mark.parametrize("fps", [0, 1001, 100000, 30.5])
def test_a_meta_json_frame_rate_out_of_range_is_refused_with_the_range(tmp_path, fps):
    """meta.json's fps must be a whole number in [1, 1000] (a rollout's limit); 100000 was refused with 'must be
    a whole number of frames per second >= 1', which it is. 1000 itself is taken."""
    np.save(tmp_path / "segmentation.npy", np.full((3, 4, 4), -1, np.int16))
    (tmp_path / "meta.json").write_text(json.dumps({"fps": fps}))
    with pytest.raises(
        ValueError, match=re.escape(f"fps = {fps!r}: must be a whole number of frames per second in [1, 1000]")
    ):
        observation.Observation.from_dir(tmp_path)
    (tmp_path / "meta.json").write_text(json.dumps({"fps": 1000}))
    assert observation.Observation.from_dir(tmp_path).fps == 1000


def test_from_scene_takes_a_whole_frame_rate_given_as_a_float(observed):
    """fps 30.0 (a clock read from JSON) or numpy's 30.0 was refused as "not a whole number" since the argument checks,
    though `SimConfig` takes 30, 30.0 and numpy's 30 alike (and from_scene did before)."""
    for fps in (30.0, np.float64(30.0), np.int64(30)):
        obs = observation.Observation.from_scene(SCENE, width=W, height=H, fps=fps)
        assert obs.fps == 30 and type(obs.fps) is int
        assert np.array_equal(obs.segmentation, observed.segmentation)
    with pytest.raises(ValueError, match=r"Observation.from_scene: fps = 29.5: must be a whole number in \[1, 1000\]"):
        observation.Observation.from_scene(SCENE, width=W, height=H, fps=29.5)
