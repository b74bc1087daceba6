"""The reward module: unlabeled observations, simulator rewards, statistics, sampling and the candidates' batch."""

from __future__ import annotations

import math
import os
import shutil

import numpy as np
import pytest
import torch

from aynamics import reward as rw
from aynamics.flow import flow_to_color
from aynamics.observation import Observation
from aynamics.scene import dump, parse
from aynamics.scorer import EPE_INVALID, Score
from aynamics.unlabeled import (
    GeneratedVideos,
    decode_flow_colors,
    observation_from_record,
    open_videos,
    video_folders,
)

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """A real generated data set: 4 scenes at 96x64 (about 5 s); skipped when OpenGL cannot render here."""
    from aynamics.generate import GenerateConfig, generate_dataset
    from aynamics.render import gl_available

    ok, why = gl_available()
    if not ok:  # no EGL / OSMesa: rendering is another module's concern
        pytest.skip(why)
    out = tmp_path_factory.mktemp("gen") / "synth"
    return generate_dataset(out, num=4, seed=0, config=GenerateConfig(width=96, height=64, workers=0))


@pytest.fixture(scope="module")
def records(generated):
    import datasets

    dd = datasets.load_from_disk(str(generated))
    return [r for split in dd.values() for r in split]


def _moved(scene, dx=0.0, dv=0.0):
    o = scene.objects[0]
    st = o.state
    pos = (st.position[0] + dx, st.position[1], st.position[2])
    vel = (st.linear_velocity[0] + dv, st.linear_velocity[1], st.linear_velocity[2])
    o = o.model_copy(update={"state": st.model_copy(update={"position": pos, "linear_velocity": vel})})
    return scene.model_copy(update={"objects": (o, *scene.objects[1:])})


# --------------------------------------------------------------------------------------------
# Observations from unlabeled data
# --------------------------------------------------------------------------------------------
def test_decode_flow_colors_inverts_the_colour_wheel():
    """Random flows on a 20 px scale come back within 1 % of the scale; white (zero flow) decodes to 0."""
    rng = np.random.default_rng(0)
    flow = rng.normal(size=(2000, 2)) * 5
    flow[:20] = 0
    scale = float(np.hypot(flow[:, 0], flow[:, 1]).max())
    back = decode_flow_colors(flow_to_color(flow, max_norm=scale), scale)
    err = np.hypot(*(back - flow).T)
    assert err.max() < 0.01 * scale
    assert np.all(back[:20] == 0)
    with pytest.raises(ValueError, match="flow_max = -1"):
        decode_flow_colors(np.zeros((2, 3), np.uint8), -1.0)
    with pytest.raises(ValueError, match="expected"):
        decode_flow_colors(np.zeros((2, 2)), 1.0)


def test_observation_from_record_reads_masks_not_labels(records):
    """The observation is the stored 96×64 masks as they are (fewer rows than the scorer's 80: never upsampled
    by default), or resampled to a size given at their aspect (120×80); blanking every label changes nothing."""
    rec = records[0]
    masks = np.stack([np.asarray(m) for m in rec["segmentation"]]).astype(int) - 1  # (F, 64, 96)
    own = observation_from_record(rec)
    np.testing.assert_array_equal(own.segmentation, masks)
    assert (own.width, own.height) == (96, 64) and own.flow.shape == (10, 64, 96, 2)
    obs = observation_from_record(rec, width=120, height=80)
    rows = ((np.arange(80) + 0.5) * 64 / 80).astype(int)
    cols = ((np.arange(120) + 0.5) * 96 / 120).astype(int)
    np.testing.assert_array_equal(obs.segmentation, masks[:, rows][:, :, cols])
    assert obs.flow is not None and obs.flow.shape == (10, 80, 120, 2) and obs.names is None
    blank = dict(rec, scene_yaml="", reasoning="", target_answer="", target_think="", states=None, contacts=None)
    again = observation_from_record(blank, width=120, height=80)
    np.testing.assert_array_equal(again.segmentation, obs.segmentation)
    np.testing.assert_array_equal(again.flow, obs.flow)
    with pytest.raises(ValueError, match="'segmentation' is missing"):
        observation_from_record({k: v for k, v in rec.items() if k != "segmentation"})


def test_a_hand_made_records_flow_is_scaled_to_the_scoring_width():
    """A 24×16 record of one sampled frame whose flow image is a uniform (4, 0) px on its scale of 4 (flow_max):
    at its own 24×16 the flow decodes to (4, 0) px (within the colour wheel's 1 % of the scale); at 12×8, half the
    pixels across, to (2, 0) px. Masks hold object index + 1: the box of 1s is object 0, the rest background -1
    (pixel (2, 3) of 12×8 is full-size (5, 7), inside rows 4..7, columns 6..11). 2 masks for 1 frame are refused;
    without use_flow the flow is not read."""
    from PIL import Image

    flow = np.zeros((16, 24, 2))
    flow[..., 0] = 4.0
    mask = np.zeros((16, 24), np.uint8)
    mask[4:8, 6:12] = 1
    colour = Image.fromarray(flow_to_color(flow, max_norm=4.0))
    rec = {"index": 7, "segmentation": [Image.fromarray(mask)], "frame_indices": [0], "flow": [colour], "flow_max": 4}
    own = observation_from_record(rec)
    assert (own.width, own.height) == (24, 16)
    np.testing.assert_allclose(own.flow[0], flow, atol=0.04)
    half = observation_from_record(rec, width=12, height=8)
    np.testing.assert_allclose(half.flow[0], flow[::2, ::2] / 2, atol=0.02)
    assert half.segmentation[0, 2, 3] == 0 and half.segmentation[0, 0, 0] == -1
    assert observation_from_record(rec, use_flow=False).flow is None  # not decoded when not wanted
    with pytest.raises(ValueError, match=r"record 7: 2 segmentation masks for frame_indices \[0\]"):
        observation_from_record(dict(rec, segmentation=[Image.fromarray(mask)] * 2))


def test_a_folders_clip_needs_its_last_image_and_a_limit_reads_only_the_first_folders(tmp_path):
    """The default clip shows the images at 0, 0.1, ..., 0.9 s of a 30 fps video: image 27 is the last it needs. A
    folder of 28 images (masks for 28 frames) gives 10 images, 0 to 27; one of 27 is refused naming image 27 (one
    more than it holds); a folder of exactly the 10 sampled images gives them all. Of a collection whose second
    folder has no frames, limit 1 reads the first alone."""
    from PIL import Image

    from aynamics.lm import PromptSpec

    def folder(root, n, masks=None):
        (root / "frames").mkdir(parents=True)
        for k in range(n):  # each image's number in its red channel
            Image.fromarray(np.full((16, 16, 3), (k, 0, 0), np.uint8)).save(root / "frames" / f"{k}.png")
        np.save(root / "segmentation.npy", np.full((masks or n, 16, 16), -1, np.int16))

    times = PromptSpec().frame_times
    folder(tmp_path / "videos" / "a", 28)
    (tmp_path / "videos" / "b").mkdir()
    np.save(tmp_path / "videos" / "b" / "segmentation.npy", np.full((28, 16, 16), -1, np.int16))
    (video,) = open_videos(tmp_path / "videos", limit=1, clip_times=times)
    assert video.key == "a" and [f.getpixel((0, 0))[0] for f in video.frames] == list(range(0, 28, 3))
    with pytest.raises(FileNotFoundError, match=r"b' has no frames"):
        open_videos(tmp_path / "videos", clip_times=times)
    folder(tmp_path / "short", 27)
    with pytest.raises(ValueError, match=r"27 images at 30 fps .* needs the image at 0.9 s \(image 27\)"):
        open_videos(tmp_path / "short", clip_times=times)
    folder(tmp_path / "sampled", 10, masks=30)  # exactly the 10 sampled images of a 30-frame video: all of them
    sampled = open_videos(tmp_path / "sampled", clip_times=times)[0].frames
    assert [f.getpixel((0, 0))[0] for f in sampled] == list(range(10))


def test_scoring_size_keeps_the_videos_aspect():
    """480×320 -> 120×80; 112×80 stays; 96×64 (fewer rows than 80) stays; a height alone sets the width; a size
    off the aspect is refused, naming both and the width that fits."""
    from aynamics.observation import scoring_size

    assert scoring_size(480, 320) == (120, 80) and scoring_size(112, 80) == (112, 80)
    assert scoring_size(96, 64) == (96, 64) and scoring_size(480, 320, height=40) == (60, 40)
    assert scoring_size(64, 48, width=100) == (100, 75) and scoring_size(480, 320, 120, 80) == (120, 80)
    with pytest.raises(ValueError, match=r"120×80 is off the video's aspect ratio \(112×80\).*width 112"):
        scoring_size(112, 80, 120, 80)


def test_true_scene_scores_one_against_its_own_record(generated, tmp_path):
    """Generated records' own scenes, scored against the observations built from their masks, at 96×64 (3:2) and
    at 112×80 (7:5, `make train`'s size): IoU and EPE of a perfect answer. Before `scoring_size`, 112×80 videos
    were scored at 120×80 and their true scenes got IoU 0.56-0.90."""
    import datasets

    from aynamics.generate import GenerateConfig, generate_dataset

    other = generate_dataset(tmp_path / "d", num=2, seed=1, config=GenerateConfig(width=112, height=80, workers=0))
    for path, size in ((generated, (96, 64)), (other, (112, 80))):
        for rec in [r for split in datasets.load_from_disk(str(path)).values() for r in split][:2]:
            obs = observation_from_record(rec)
            assert (obs.width, obs.height) == size
            s = rw.score_completions([[rec["scene_yaml"]]], [obs])[0][0]
            assert s.iou_full > 0.98 and s.iou_first > 0.98 and s.epe_full < 0.3, (size, rec["index"], s)


def test_videos_of_another_frame_rate_are_scored_on_their_clock(tmp_path):
    """A data set generated at 60 fps: PRO's observations (`GeneratedVideos`) and the evaluation's (`eval_record`
    -> `scorable_records`) are taken at 60 fps at the record's frames, so the true scene meets its own masks
    (before: simulated at 30 fps, the true scenes of helper-37's 60 fps data set scored IoU 0.20-0.99)."""
    import datasets

    from aynamics import data, eval_records, lm
    from aynamics.callbacks import scorable_records
    from aynamics.generate import GenerateConfig, generate_dataset

    config = GenerateConfig(width=64, height=48, fps=60, workers=0)
    path = generate_dataset(tmp_path / "d", num=3, seed=0, config=config)
    name, split = next((n, s) for n, s in datasets.load_from_disk(str(path)).items() if len(s))
    videos = GeneratedVideos(path, name)
    prompt = data.with_clock(lm.PromptSpec(), path, split)
    processor = lm.load_processor(lm.ModelSpec(kind="tiny"), prompt)
    assert videos.fps == 60 and prompt.fps == 60.0
    alone = GeneratedVideos(path / name)  # a split folder given on its own: the manifest beside it (helper-40)
    assert alone.fps == 60 and data.with_clock(lm.PromptSpec(), path / name, split).fps == 60.0
    for i, rec in enumerate(split):
        obs = videos[i].observation
        assert obs.fps == 60 and obs.frames.tolist() == rec["frame_indices"]
        s = rw.score_completions([[rec["scene_yaml"]]], [obs])[0][0]
        assert s.iou_full > 0.98 and s.iou_first > 0.98 and s.epe_full < 0.3, (rec["index"], s)
        (scored,) = scorable_records([eval_records.eval_record(rec, processor, prompt, i)])
        seen = scored["observation"]
        assert seen.fps == 60 and seen.frames.tolist() == rec["frame_indices"]
        assert (seen.segmentation == obs.segmentation).mean() > 0.98


def test_reward_does_not_read_scene_yaml(generated, tmp_path, records):
    """A copy of the data set with every label blanked gives the same rewards for the same candidates."""
    import datasets

    dd = datasets.load_from_disk(str(generated))
    full = datasets.concatenate_datasets([split for split in dd.values() if len(split)])
    full.save_to_disk(str(tmp_path / "full"))
    labels = {"scene_yaml": "", "reasoning": "", "target_answer": "", "target_think": ""}
    full.map(lambda r: labels).save_to_disk(str(tmp_path / "blank"))
    a, b = GeneratedVideos(tmp_path / "full"), GeneratedVideos(tmp_path / "blank")
    assert "scene_yaml" not in a.ds.column_names and len(a) == len(records)
    truth = full["scene_yaml"]
    ra = rw.simulator_rewards(truth, [a[i].observation for i in range(len(a))])
    rb = rw.simulator_rewards(truth, [b[i].observation for i in range(len(b))])
    assert ra == rb and min(ra) > 0.5


def test_true_scene_scores_above_perturbed(records):
    """On every generated video the true YAML beats the same scene moved 0.4 m or pushed 1.5 m/s faster."""
    for rec in records:
        obs = observation_from_record(rec)
        scene = parse(rec["scene_yaml"])
        texts = [rec["scene_yaml"], dump(_moved(scene, dx=0.4)), dump(_moved(scene, dv=1.5))]
        iou = rw.simulator_rewards(texts, [obs] * 3)
        epe = rw.simulator_rewards(texts, [obs] * 3, config=rw.RewardConfig(metric="epe"))
        mix = rw.simulator_rewards(texts, [obs] * 3, config=rw.RewardConfig(metric="mix", mix_weight=0.3))
        assert iou[0] > max(iou[1:]) and iou[0] > 0.7, (rec["index"], iou)
        assert epe[0] > max(epe[1:]), (rec["index"], epe)
        assert mix[0] > max(mix[1:]), (rec["index"], mix)


def test_invalid_outputs_score_zero_with_their_reason(records):
    obs = observation_from_record(records[0])
    scene = parse(records[0]["scene_yaml"])
    bad_mass = dump(scene).replace("mass: ", "mass: -", 1)
    texts = ["", "I think the box slides.", "<answer>\n- type: box\n  size: [1, 2\n</answer>", bad_mass]
    sunk = dump(scene) + "- type: sphere\n  name: sunk\n  radius: 0.05\n  state:\n    position: [0, 1, -0.4]\n"
    texts += [sunk, f"<think>it slides</think>\n<answer>\n{dump(scene)}</answer>"]
    scores = rw.score_completions([texts], [obs])[0]
    assert [s.valid for s in scores] == [False, False, False, False, False, True]
    assert all(s.iou_full == 0 and s.epe_full == EPE_INVALID for s in scores[:5])
    kinds = ["no_yaml", "no_yaml", "no_yaml", "invalid_scene", "simulation", "valid"]
    assert [rw.reason_kind(s.reason) for s in scores] == kinds
    assert "mass = -" in scores[3].reason and "overlapping start: sunk and the floor" in scores[4].reason
    rewards = rw.rewards_of([scores])
    assert rewards.shape == (1, 6) and torch.all(rewards[0, :5] == 0) and rewards[0, 5] > 0.9
    stats = rw.RewardStats.of(rewards, [scores])
    m = stats.to_metrics()
    assert m["reward/invalid"] == pytest.approx(5 / 6) and m["reward/invalid_no_yaml"] == pytest.approx(0.5)
    assert m["reward/invalid_invalid_scene"] == pytest.approx(1 / 6)
    assert m["reward/invalid_simulation"] == pytest.approx(1 / 6)
    assert m["reward/best"] == pytest.approx(m["reward/mean"] * 6)


def test_responses_cut_at_the_token_limit_count_as_truncated(records):
    """The true scene's answer cut at 40 tokens scores as no YAML; at the limit without an end-of-turn id it is
    "truncated" instead (its own share in the statistics). Not marked: the same cut with an end-of-turn id last,
    an invalid one shorter than the limit (cut at 30 tokens), a valid one over it."""
    from aynamics import lm

    obs = observation_from_record(records[0])
    tok = lm.load_processor(lm.ModelSpec(kind="tiny"), lm.PromptSpec()).tokenizer
    full = tok(f"<answer>\n{records[0]['scene_yaml']}</answer>")["input_ids"]
    eos = tok.convert_tokens_to_ids("<|im_end|>")
    cut = full[:40]
    ids = [[cut, cut[:39] + [eos], cut[:30], full]]
    texts = [[tok.decode(c, skip_special_tokens=True) for c in ids[0]]]
    raw = rw.score_completions(texts, [obs])
    scores = rw.mark_truncated(raw, ids, 40, [eos])[0]
    assert [s.valid for s in raw[0]] == [False, False, False, True] and scores[1:] == raw[0][1:]
    assert scores[0].reason == f"truncated at max_new_tokens = 40: {raw[0][0].reason}"
    assert [rw.reason_kind(s.reason) for s in scores] == ["truncated", "no_yaml", "invalid_scene", "valid"]
    stats = rw.RewardStats.of(rw.rewards_of([scores]), [scores]).to_metrics()
    assert stats["reward/invalid_truncated"] == pytest.approx(0.25)
    assert stats["reward/invalid_no_yaml"] == stats["reward/invalid_invalid_scene"] == pytest.approx(0.25)


def test_scoring_in_parallel_matches_serial(records):
    obs = [observation_from_record(r) for r in records]
    cands = [[r["scene_yaml"], dump(_moved(parse(r["scene_yaml"]), dx=0.2)), "junk"] for r in records]
    serial = rw.score_completions(cands, obs, workers=1)
    parallel = rw.score_completions(cands, obs, workers=2)
    assert serial == parallel
    with pytest.raises(ValueError, match="3 candidate lists for 2 observations"):
        rw.score_completions(cands[:3], obs[:2])


def test_reward_of_hand_worked():
    """IoU 0.6, EPE 5 px with scale 5: epe reward 1/(1+1) = 0.5; mix 0.25: 0.25*0.6 + 0.75*0.5 = 0.525."""
    s = Score(0.8, 0.6, 1.0, 5.0, True)
    assert rw.reward_of(s) == pytest.approx(0.6)
    assert rw.reward_of(s, rw.RewardConfig(span="first")) == pytest.approx(0.8)
    assert rw.reward_of(s, rw.RewardConfig(metric="epe", epe_scale=5)) == pytest.approx(0.5)
    assert rw.reward_of(s, rw.RewardConfig(metric="mix", mix_weight=0.25)) == pytest.approx(0.525)
    assert rw.reward_of(s, rw.RewardConfig(metric="epe", span="first", epe_scale=1)) == pytest.approx(0.5)
    assert rw.reward_of(Score(0.0, 0.0, 100.0, 100.0, False, "x"), rw.RewardConfig(metric="epe")) == 0.0
    with pytest.raises(ValueError, match="needs flow"):
        rw.reward_of(Score(0.5, 0.5, None, None, True), rw.RewardConfig(metric="epe"))
    for bad, match in [({"metric": "ssim"}, "'ssim'"), ({"mix_weight": 2}, "mix_weight = 2"), ({"epe_scale": 0}, "0")]:
        with pytest.raises(ValueError, match=match):
            rw.RewardConfig(**bad)


def test_reward_config_bounds():
    """A span other than full/first is refused by name; mix_weight 0 and 1 are allowed (the ends of [0, 1]):
    Score IoU 0.6, EPE 5 px at scale 5 -> mix 0 is the EPE reward 1 / (1 + 1) = 0.5, mix 1 the IoU 0.6."""
    with pytest.raises(ValueError, match="reward span = 'last'"):
        rw.RewardConfig(span="last")
    s = Score(0.8, 0.6, 1.0, 5.0, True)
    assert rw.reward_of(s, rw.RewardConfig("mix", mix_weight=0.0)) == pytest.approx(0.5)
    assert rw.reward_of(s, rw.RewardConfig("mix", mix_weight=1.0)) == pytest.approx(0.6)


def test_reward_arguments_of_the_wrong_kind_are_named_not_scored():
    """rewards_of of one video's flat list failed on "'Score' object is not iterable" and ragged rows on torch's
    "expected sequence of length 1"; a NaN IoU or EPE was returned as the reward, an EPE of -5 px (scale 5)
    divided by zero; a config value "0.5" failed on "'<=' not supported". Nested: IoU 0.6 and 0.2 -> [[0.6, 0.2]]."""
    good, other = Score(0.8, 0.6, 1.0, 5.0, True), Score(0.1, 0.2, 1.0, 5.0, True)
    with pytest.raises(TypeError, match=r"scores\[0\] is a Score: must be a list of Scores \(one video's"):
        rw.rewards_of([good, other])
    with pytest.raises(ValueError, match=r"scores\[1\] has 1 scores, scores\[0\] 2"):
        rw.rewards_of([[good, other], [good]])
    with pytest.raises(TypeError, match=r"reward_of: s is a str, not a Score"):
        rw.reward_of("iou_full: 0.6")
    with pytest.raises(TypeError, match=r"reward_of: config is a str, not a RewardConfig"):
        rw.reward_of(good, "epe")
    with pytest.raises(ValueError, match=r"iou_full = nan: an IoU must be in \[0, 1\]"):
        rw.reward_of(Score(0.5, math.nan, None, None, True))
    for epe in (math.nan, -5.0):
        with pytest.raises(ValueError, match=rf"epe_full = {epe}: an end-point error must be >= 0"):
            rw.reward_of(Score(0.5, 0.5, 1.0, epe, True), rw.RewardConfig(metric="epe"))
    with pytest.raises(TypeError, match=r"reward mix_weight = '0.5': must be a number, not a str"):
        rw.RewardConfig(mix_weight="0.5")
    assert rw.rewards_of([[good, other]])[0].tolist() == pytest.approx([0.6, 0.2])


def test_evaluation_modes_hand_worked():
    """Video 0: samples IoU 0.2 / 0.8 (rewards pick the 2nd); video 1: 0.5 / 0.1 (rewards pick the 1st).

    greedy = mean(0.3, 0.4) = 0.35; Best@1 = mean(0.5, 0.3) = 0.4; Best@N = mean(0.8, 0.5) = 0.65.
    """

    def s(iou, epe):
        return Score(iou, iou, epe, epe, True)

    greedy = [s(0.3, 2.0), s(0.4, 4.0)]
    samples = [[s(0.2, 3.0), s(0.8, 1.0)], [s(0.5, 2.0), s(0.1, 6.0)]]
    out = rw.evaluation_modes(greedy, samples, torch.tensor([[0.2, 0.8], [0.5, 0.1]]))
    assert out["greedy/iou_full"] == pytest.approx(0.35) and out["best1/iou_first"] == pytest.approx(0.4)
    assert out["bestN/iou_full"] == pytest.approx(0.65) and out["bestN/epe_full"] == pytest.approx(1.5)
    assert out["best1/epe_first"] == pytest.approx(3.0) and len(out) == 12
    no_flow = rw.evaluation_modes(
        [Score(0.3, 0.3, None, None, True)], [[Score(0.1, 0.1, None, None, True)]], torch.tensor([[0.1]])
    )
    assert set(no_flow) == {f"{m}/{k}" for m in rw.MODES for k in ("iou_first", "iou_full")}
    # rewards tied at 0: an invalid sample (IoU 0, EPE 100) first, a valid one of IoU 0 and EPE 4 second; Best@N
    # takes the valid one (it reported EPE 100 by sampling order)
    tied = rw.evaluation_modes(
        [s(0.0, 5.0)], [[Score(0.0, 0.0, 100.0, 100.0, False, "diverged"), s(0.0, 4.0)]], torch.tensor([[0.0, 0.0]])
    )
    assert tied["bestN/epe_full"] == pytest.approx(4.0) and tied["bestN/iou_full"] == 0.0


def test_open_videos_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        open_videos(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(
        FileNotFoundError, match=r"empty' is no video folder \(frames/ beside the segmentation\), nor holds any"
    ):
        open_videos(tmp_path / "empty")


def test_video_folder_with_frames_and_masks(tmp_path, monkeypatch):
    """A folder of 30 frames + segmentation.npy: the model sees the 10 sampled frames; the true scene is exact. A
    frame missing, frames of another aspect ratio and a broken frame are named; hidden files are no frames; the
    video's key is its folder's name, also when given as "."."""
    from PIL import Image

    scene = parse(open(os.path.join(os.path.dirname(__file__), "assets", "paper_example.yaml")).read())
    obs = Observation.from_scene(scene, frames=np.arange(30))  # 120x80: the scorer's own resolution
    root = tmp_path / "vid"
    (root / "frames").mkdir(parents=True)
    np.save(root / "segmentation.npy", obs.segmentation.astype(np.int16))
    for k in range(30):
        Image.fromarray(np.full((80, 120, 3), k, np.uint8)).save(root / "frames" / f"{k:03d}.png")
    (video,) = open_videos(root)
    assert len(video.frames) == 10 and video.frames[1].getpixel((0, 0)) == (3, 3, 3)
    r = rw.simulator_rewards([dump(scene), dump(_moved(scene, dx=0.5))], [video.observation] * 2)
    assert r[0] == pytest.approx(1.0) and r[1] < 0.9
    with pytest.raises(FileNotFoundError, match=r"vid' has no flow/\*.png: colour-wheel flow images"):
        open_videos(root, inputs="flow")
    (root / "flow").mkdir()
    flows = np.zeros((29, 80, 120, 2), np.float32)  # the flow from frame k to k + 1
    flows[:, 20:40, 30:60] = np.stack([np.arange(1.0, 30.0), np.linspace(-2, 3, 29)], -1)[:, None, None]
    flows[28, 20:40, 30:60, 0] = 60.0  # the fastest flow is one the model does not see
    for k, im in enumerate(flow_to_color(flows)):  # one scale for the whole video, as `aynamics render` writes them
        Image.fromarray(im).save(root / "flow" / f"{k:03d}.png")
    (flow_video,) = open_videos(root, inputs="flow")  # a flow-trained model sees the flow images of the same frames
    seen = np.stack([np.asarray(im) for im in flow_video.frames]).astype(int)
    generated = flow_to_color(flows[0:30:3]).astype(int)  # a generated record: the sampled flows on their own scale
    assert np.abs(seen - generated).max() <= 1 and np.abs(seen - flow_to_color(flows)[0:30:3]).max() > 50
    assert (seen[:, 0, 0] == 255).all()  # still white where nothing moves
    coll = tmp_path / "collection"  # a video folder missing its frames is named, not passed over
    (coll / "b").mkdir(parents=True)
    np.save(coll / "b" / "segmentation.npy", obs.segmentation.astype(np.int16))
    shutil.copytree(root, coll / "a")
    (coll / "notes").mkdir()  # no part of a video: not one
    assert [p.name for p in video_folders(coll)] == ["a", "b"]
    with pytest.raises(FileNotFoundError, match=r"b' has no frames/\*.png"):
        open_videos(coll)
    (root / "frames" / "._000.png").write_bytes(b"\x00\x05 macOS resource fork")  # not a frame
    monkeypatch.chdir(root)
    assert open_videos(".")[0].key == "vid"  # the folder's own name, also for "."
    missing = root / "frames" / "010.png"
    kept = missing.read_bytes()
    missing.unlink()  # 29 frames: every later one would be one off
    with pytest.raises(ValueError, match=r"29 images; need one for every video frame \(30: the segmentation has 30"):
        open_videos(root)
    missing.write_bytes(kept)
    Image.fromarray(np.zeros((80, 100, 3), np.uint8)).save(root / "frames" / "000.png")  # 100×80 beside 120×80 masks
    with pytest.raises(ValueError, match=r"000\.png': 100×80 pixels, another aspect ratio than the masks' 120×80"):
        open_videos(root)
    Image.fromarray(np.full((80, 120, 3), 0, np.uint8)).save(root / "frames" / "000.png")
    Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(root / "frames" / "003.png")  # half the size of 000.png
    with pytest.raises(ValueError, match=r"003\.png': 60×40 pixels, unlike the 120×80 of '.*000\.png'"):
        open_videos(root)
    broken = root / "frames" / "003.png"
    broken.write_bytes(broken.read_bytes()[:40])  # truncated
    with pytest.raises(ValueError, match=r"cannot read frame .*003\.png"):
        open_videos(root)


def test_generated_videos_broken_data_set_named(tmp_path):
    """A data set folder whose files cannot be read: a ValueError naming the folder (was the library's own error)."""
    root = tmp_path / "ds"
    root.mkdir()
    (root / "dataset_dict.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"data set '.*ds' cannot be read"):
        open_videos(root)


# --------------------------------------------------------------------------------------------
# Sampling and the candidates' batch on the tiny model
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny():
    from aynamics.model import build_tiny_model
    from aynamics.processor import load_processor
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    return build_tiny_model(), load_processor(TINY_ASSET_DIR)


def _prompts(proc, sizes=((56, 56), (56, 84))):
    from aynamics.processor import build_prompt

    rng = np.random.default_rng(1)
    out = []
    for h, w in sizes:
        frames = [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in range(2)]
        out.append(build_prompt(proc, frames, system_prompt="You are a physicist.", user_prompt="Write YAML."))
    return out


def test_sample_completions_shapes_and_order(tiny):
    model, proc = tiny
    prompts = _prompts(proc)
    torch.manual_seed(0)
    ids, texts = rw.sample_completions(model, proc, prompts, num_samples=3, temperature=1.0, max_new_tokens=6)
    assert [len(r) for r in ids] == [3, 3] and [len(t) for t in texts] == [3, 3]
    assert all(1 <= len(c) <= 6 for row in ids for c in row)
    assert texts[1][2] == proc.tokenizer.decode(ids[1][2], skip_special_tokens=True)
    assert not model.training
    g_ids, _ = rw.sample_completions(model, proc, prompts[1:], num_samples=1, temperature=0.0, max_new_tokens=6)
    g_all, _ = rw.sample_completions(model, proc, prompts, num_samples=1, temperature=0.0, max_new_tokens=6)
    assert g_all[1] == g_ids[0]  # row b of the output belongs to prompt b
    with pytest.raises(ValueError, match="greedy gives one response"):
        rw.sample_completions(model, proc, prompts, num_samples=2, temperature=0.0)


def test_candidate_batch_keeps_images_aligned(tiny):
    """B=2 prompts (4 and 6 merged tokens per image) x N=3: visual tensors follow the rows; each row's mean
    log-prob in the padded batch equals that row's alone."""
    from aynamics.batching import collate, model_inputs
    from aynamics.logprobs import mean_token_logprob
    from aynamics.processor import append_response, response_ids

    model, proc = tiny
    prompts = _prompts(proc)
    words = [["mass: 1.5", "box", "- type: sphere"], ["radius: 0.2", "camera", "friction: [0.5, 0.1]"]]
    cands = [[response_ids(proc, w) for w in row] for row in words]
    batch = rw.candidate_batch(prompts, cands, proc.tokenizer.pad_token_id)
    assert batch["input_ids"].shape[0] == 6
    expected_pv = torch.cat([p["pixel_values"] for p in prompts for _ in range(3)])
    expected_grid = torch.cat([p["image_grid_thw"] for p in prompts for _ in range(3)])
    assert torch.equal(batch["pixel_values"], expected_pv) and torch.equal(batch["image_grid_thw"], expected_grid)
    for row in range(6):
        b, n = divmod(row, 3)
        c = len(cands[b][n])
        assert batch["mm_token_type_ids"][row, -c:].eq(0).all()
        assert batch["labels"][row, -c:].tolist() == cands[b][n]
        plen = len(prompts[b]["input_ids"])
        assert torch.equal(batch["mm_token_type_ids"][row, -c - plen : -c], prompts[b]["mm_token_type_ids"])
    with torch.no_grad():
        lp = mean_token_logprob(model(**model_inputs(batch)).logits, batch["labels"])
        for row in (0, 4, 5):
            b, n = divmod(row, 3)
            alone = collate([append_response(prompts[b], cands[b][n])], proc.tokenizer.pad_token_id)
            lp1 = mean_token_logprob(model(**model_inputs(alone)).logits, alone["labels"])
            assert lp[row].item() == pytest.approx(lp1.item(), abs=1e-4)
    with pytest.raises(ValueError, match="same N"):
        rw.candidate_batch(prompts, [cands[0], cands[1][:2]], 0)
    with pytest.raises(ValueError, match="empty"):
        rw.candidate_batch(prompts[:1], [[[]]], 0)
    assert math.isfinite(lp.sum().item())


def test_decoding_ignores_the_checkpoints_sampling_settings(tiny):
    """A checkpoint whose generation_config.json carries Qwen2.5-VL Instruct's settings (top_k 1, repetition
    penalty 1.05, sampling on) decodes as one with none: the same greedy tokens, and samples that differ (with
    top_k 1 every sample would be the one most likely response)."""
    import copy

    model, proc = tiny
    prompts = _prompts(proc)[:1]
    clean = copy.deepcopy(model.generation_config)
    greedy, _ = rw.sample_completions(model, proc, prompts, num_samples=1, temperature=0.0, max_new_tokens=12)
    torch.manual_seed(0)
    sampled, _ = rw.sample_completions(model, proc, prompts, num_samples=4, temperature=1.0, max_new_tokens=12)
    try:
        gen = model.generation_config
        gen.do_sample, gen.top_k, gen.top_p, gen.temperature, gen.repetition_penalty = True, 1, 0.001, 0.1, 1.05
        assert (
            rw.sample_completions(model, proc, prompts, num_samples=1, temperature=0.0, max_new_tokens=12)[0] == greedy
        )
        torch.manual_seed(0)
        again, _ = rw.sample_completions(model, proc, prompts, num_samples=4, temperature=1.0, max_new_tokens=12)
    finally:
        model.generation_config = clean
    assert again == sampled and len({tuple(c) for c in again[0]}) > 1
    assert rw.decoding(0.0) == {"repetition_penalty": 1.0, "no_repeat_ngram_size": 0, "do_sample": False}
    assert rw.decoding(0.7, 0.9)["top_k"] == 0  # no top-k cut: temperature and nucleus only


def test_candidate_and_sampling_arguments_checked_before_any_model_work():
    """A candidate holding a forbidden (vision) token id, and top_p = 0 (outside (0, 1]), are ValueErrors raised
    before the prompts, model or processor are touched (stand-ins here)."""
    with pytest.raises(ValueError, match=r"candidate 0 of prompt 0 holds vision token ids \[7\]: not allowed"):
        rw.candidate_batch([{}], [[[5, 7]]], 0, forbidden=[7, 8])
    with pytest.raises(ValueError, match="top_p = 0.0"):
        rw.sample_completions(None, None, [], num_samples=1, temperature=1.0, top_p=0.0)


def test_reward_stats_by_hand():
    """Two videos of two candidates, rewards [[0.2, 0.8], [0.5, 0.0]], the last one unparsable: mean 1.5 / 4 =
    0.375, best = mean of the rows' maxima (0.8 + 0.5) / 2 = 0.65 (not the batch maximum 0.8), invalid 1/4."""
    ok = Score(0.5, 0.5, None, None, True)
    bad = Score(0.0, 0.0, None, None, False, "parse: invalid scene (1 problem): camera: the scene needs one camera")
    rewards = torch.tensor([[0.2, 0.8], [0.5, 0.0]])
    m = rw.RewardStats.of(rewards, [[ok, ok], [ok, bad]]).to_metrics()
    assert m["reward/mean"] == pytest.approx(0.375) and m["reward/best"] == pytest.approx(0.65)
    assert m["reward/invalid"] == 0.25 and m["reward/invalid_invalid_scene"] == 0.25
    assert m["reward/invalid_no_yaml"] == m["reward/invalid_simulation"] == m["reward/invalid_truncated"] == 0.0


def test_reason_kinds_by_hand():
    """The kind comes from the reason's prefix and wording, not from words inside a field value: an invalid scene
    whose object is named `sim_box` is not a simulation failure."""
    assert rw.reason_kind(None) == "valid"
    assert rw.reason_kind("sim: diverged at t = 0.3 s") == "simulation"
    assert rw.reason_kind("truncated at max_new_tokens = 40: parse: ...") == "truncated"
    assert rw.reason_kind("parse: invalid scene (1 problem): text: empty text: no YAML found") == "no_yaml"
    named = "parse: invalid scene (1 problem): objects[1].name = 'sim_box': duplicate name (also objects[0])"
    assert rw.reason_kind(named) == "invalid_scene"


def test_unparsable_candidates_have_no_epe_without_observed_flow():
    """Against a video without flow an unparsable response scores EPE None (like every other score there); with
    flow, EPE_INVALID."""
    seg = np.full((1, 4, 4), -1, np.int16)
    plain = Observation(segmentation=seg, frames=np.array([0]), width=4, height=4)
    s = rw.score_completions([["junk"]], [plain])[0][0]
    assert (s.valid, s.epe_first, s.epe_full) == (False, None, None)
    flowing = Observation(
        segmentation=seg, frames=np.array([0]), width=4, height=4, flow=np.zeros((1, 4, 4, 2), np.float32)
    )
    s = rw.score_completions([["junk"]], [flowing])[0][0]
    assert (s.valid, s.epe_first, s.epe_full) == (False, EPE_INVALID, EPE_INVALID)


def test_a_text_where_a_list_of_candidates_goes_is_refused():
    """score_completions([text], [obs]) scored the text's characters as B x len(text) invalid candidates and
    simulator_rewards(text, ...) one per character; an Observation or None in place of the list of observations
    failed deep inside ("has no len()", "no attribute 'frames'")."""
    seg = np.full((1, 4, 4), -1, np.int16)
    obs = Observation(segmentation=seg, frames=np.array([0]), width=4, height=4)
    with pytest.raises(TypeError, match=r"completions\[0\] is a str: must be a list of candidate texts"):
        rw.score_completions(["- type: sphere"], [obs])
    with pytest.raises(TypeError, match=r"predictions is a str: must be a list of texts"):
        rw.simulator_rewards("ab", [obs, obs])
    with pytest.raises(TypeError, match=r"observations is a Observation: must be a list of Observations"):
        rw.simulator_rewards(["junk"], obs)
    with pytest.raises(TypeError, match=r"observations\[0\] is a NoneType, not an Observation"):
        rw.score_completions([["junk"]], [None])
    assert rw.simulator_rewards(("junk",), (obs,)) == [0.0]


def test_generated_videos_score_candidates_with_the_data_sets_own_substeps(tmp_path):
    """A data set generated with substeps=2 (recorded in generate.json) was scored by simulating candidates at the
    default round(240 / fps) = 8: its true scenes got IoU 0.59-0.99 against their own masks."""
    import datasets

    from aynamics.generate import GenerateConfig, generate_dataset
    from aynamics.render import gl_available

    if not gl_available()[0]:
        pytest.skip("no headless OpenGL")
    config = GenerateConfig(width=64, height=48, substeps=2, workers=0, splits=(1.0, 0.0, 0.0))
    path = generate_dataset(tmp_path / "d", num=3, seed=0, config=config)
    videos = GeneratedVideos(path, "train")
    assert videos.substeps == 2
    for i, rec in enumerate(datasets.load_from_disk(str(path))["train"]):
        obs = videos[i].observation
        assert obs.config.substeps == 2
        s = rw.score_completions([[rec["scene_yaml"]]], [obs])[0][0]
        assert s.iou_full > 0.98, (rec["index"], s)


def test_a_collection_never_passes_over_videos_grouped_a_level_deeper(tmp_path):
    """Videos in sub-groups of a collection (coll/a, coll/group/b): b was passed over unseen (only a read), and a
    collection of groups only said it held no videos. The group is named; hidden folders and other folders pass."""

    def video(root):
        (root / "frames").mkdir(parents=True)
        np.save(root / "segmentation.npy", np.full((1, 4, 4), -1, np.int16))

    coll = tmp_path / "coll"
    video(coll / "a")
    (coll / "notes").mkdir()
    video(coll / ".cache" / "old")  # hidden: not the user's videos
    assert [p.name for p in video_folders(coll)] == ["a"]
    video(coll / "group" / "b")
    with pytest.raises(ValueError, match=f"'{coll / 'group'}' holds video folders, a level below the collection"):
        video_folders(coll)
    video(tmp_path / "groups" / "g1" / "x")  # groups only: "holds no video" named no group
    with pytest.raises(ValueError, match="'.*g1' holds video folders"):
        video_folders(tmp_path / "groups")


def test_a_still_is_refused_where_the_model_needs_its_clip(tmp_path):
    """A 1-frame "video" (a still: its one image is also its one sampled frame) was shown to the model alone, and
    scored on that frame, where a 2- to 27-frame video is refused as shorter than the training clip (0 to 0.9 s).
    Without the clip's times (a plain read) it is still read; a still is fine for a 1-frame clip."""
    from PIL import Image

    from aynamics.unlabeled import video_from_folder

    root = tmp_path / "still"
    (root / "frames").mkdir(parents=True)
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(root / "frames" / "0.png")
    np.save(root / "segmentation.npy", np.full((1, 16, 16), -1, np.int16))
    times = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
    with pytest.raises(ValueError, match=r"1 images at 30 fps .* needs the image at 0.9 s \(image 27\)"):
        video_from_folder(root, clip_times=times)
    assert len(video_from_folder(root).frames) == 1
    assert len(video_from_folder(root, clip_times=(0.0,)).frames) == 1


def test_rewards_of_takes_a_generator_of_rows():
    """A generator of B rows was refused ("scores is a generator") since the argument checks; torch read it before."""
    good = Score(1.0, 0.5, 0.0, 0.0, True)
    rows = [[good, good], [good, good]]
    assert torch.equal(rw.rewards_of(row for row in rows), rw.rewards_of(rows))
    with pytest.raises(TypeError, match=r"rewards_of: scores\[0\] is a Score"):
        rw.rewards_of(s for s in [good])
