"""The SFT data module: label masks, modalities, frames as images or video, the resumable order, the mean scene."""

from __future__ import annotations

import os
import warnings

import pytest
import torch
from train_fixtures import tiny_dataset

from aynamics import lm
from aynamics.average_scene import mean_scene
from aynamics.data import ResumableSampler, SceneDataModule, WarmupViews, frame_windows, load_splits
from aynamics.processor import IGNORE_INDEX, IMAGE, TEXT, VIDEO
from aynamics.scene import parse
from aynamics.tokenizer_build import TINY_ASSET_DIR
from aynamics.visual_targets import token_targets


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return tiny_dataset(tmp_path_factory)


def _dm(dataset_dir, **kw) -> SceneDataModule:
    dm = SceneDataModule(str(dataset_dir), str(TINY_ASSET_DIR), num_frames=2, batch_size=2, **kw)
    dm.setup("fit")
    return dm


@pytest.mark.parametrize("target", lm.TARGETS)
def test_labels_cover_exactly_the_response(dataset_dir, target):
    """Labels are -100 on the prompt and the image tokens; the labelled ids decode to the response + <|im_end|>."""
    dm = _dm(dataset_dir, target=target)
    ex = dm.dataset("train")[0]
    record = dm.splits["train"][0]
    response = lm.response_text(record, target)
    tok = dm.processor.tokenizer
    labelled = ex["labels"][ex["labels"] != IGNORE_INDEX]
    assert tok.decode(labelled) == response + "<|im_end|>"
    # the labelled span is the tail of input_ids, and identical to it
    n = len(labelled)
    assert torch.equal(ex["input_ids"][-n:], labelled)
    assert (ex["labels"][:-n] == IGNORE_INDEX).all()
    # images sit in the masked prompt; mm_token_type_ids marks exactly the image pads
    is_image = ex["input_ids"] == dm.processor.image_token_id
    assert is_image.sum() > 0 and (ex["labels"][is_image] == IGNORE_INDEX).all()
    assert torch.equal(ex["mm_token_type_ids"] == IMAGE, is_image)
    assert (ex["mm_token_type_ids"][-n:] == TEXT).all()
    assert response.startswith("<think>") == (target == "think_answer")


@pytest.mark.parametrize("target", lm.TARGETS)
def test_rounded_targets_hold_the_same_scene_to_fewer_decimals(dataset_dir, target):
    dm = _dm(dataset_dir, target=target, decimals=1)
    record = dm.splits["train"][0]
    full, short = lm.response_text(record, target), lm.response_text(record, target, decimals=1)
    assert len(short) < len(full) and short.endswith("</answer>")
    scene, rounded = parse(record["scene_yaml"]), parse(short)
    assert rounded.names == scene.names
    assert rounded.camera.fovy == round(scene.camera.fovy, 1)
    assert rounded.objects[0].state.position == tuple(round(x, 1) for x in scene.objects[0].state.position)
    labelled = dm.dataset("train")[0]["labels"]
    assert dm.processor.tokenizer.decode(labelled[labelled != IGNORE_INDEX]) == short + "<|im_end|>"
    with pytest.raises(ValueError, match="decimals = 7"):
        _dm(dataset_dir, decimals=7)


def test_targets_without_object_names_read_back_as_the_same_scene(dataset_dir):
    dm = _dm(dataset_dir, object_names=False)
    for i, record in enumerate(dm.splits["train"]):
        text = lm.response_text(record, "answer", names=False)
        assert "name:" not in text and parse(text) == parse(record["scene_yaml"])
        labelled = dm.dataset("train")[i]["labels"]
        assert dm.processor.tokenizer.decode(labelled[labelled != IGNORE_INDEX]) == text + "<|im_end|>"


def test_objects_last_targets_and_examples_put_camera_and_gravity_first(dataset_dir):
    dm = _dm(dataset_dir, objects_last=True, object_names=False, decimals=2, num_examples=1)
    for i, record in enumerate(dm.splits["train"]):
        text = lm.response_text(record, "answer", 2, names=False, objects_last=True)
        types = [line.split(": ")[1] for line in text.splitlines() if line.startswith("- type: ")]
        objects = [o.type for o in parse(record["scene_yaml"]).objects]
        assert types == ["camera", "gravity", *objects]
        assert parse(text) == parse(lm.response_text(record, "answer", 2, names=False))  # the same scene
        labelled = dm.dataset("train")[i]["labels"]
        assert dm.processor.tokenizer.decode(labelled[labelled != IGNORE_INDEX]) == text + "<|im_end|>"
    (example,) = dm.prompt.examples  # in-context examples are written the way the targets are
    assert example == lm.scene_text(dm.splits["train"][0]["scene_yaml"], 2, False, True)
    assert example.startswith("- type: camera") and "name:" not in example


def test_type_weights_cover_the_response_types_only(dataset_dir):
    """`data.type_weight` weighs the tokens spelling each entry's type (and only those); `type_tokens` marks them."""
    dm = _dm(dataset_dir, type_weight=4.0, object_names=False)
    tok = dm.processor.tokenizer
    for i, record in enumerate(dm.splits["train"]):
        ex = dm.dataset("train")[i]
        w, labels = ex["loss_weights"], ex["labels"]
        assert w.shape == labels.shape and (w[labels == IGNORE_INDEX] == 0).all()  # the prompt weighs nothing
        types = [tok.decode([int(t)]).strip() for t in ex["input_ids"][w == 4.0]]
        assert types == [o.type for o in parse(record["scene_yaml"]).objects] + ["camera", "gravity"]
        assert set(w[labels != IGNORE_INDEX].tolist()) == {1.0, 4.0}
        assert torch.equal(ex["type_tokens"], w == 4.0)
    batch = next(iter(dm.train_dataloader()))
    assert batch["loss_weights"].shape == batch["labels"].shape
    assert (batch["loss_weights"][batch["attention_mask"] == 0] == 0).all()  # padding weighs nothing
    plain = _dm(dataset_dir).dataset("train")[0]
    assert "loss_weights" not in plain and plain["type_tokens"].sum() >= 3  # weight 1: no weights, types marked
    with pytest.raises(ValueError, match="type_weight = 0"):
        _dm(dataset_dir, type_weight=0)


def test_cached_examples_are_built_once_and_equal(dataset_dir):
    plain, cached = _dm(dataset_dir).dataset("train"), _dm(dataset_dir, cache=True).dataset("train")
    first = cached[1]
    assert cached[1] is first  # built once
    for k, v in plain[1].items():
        assert torch.equal(v, first[k]), k
    dm = _dm(dataset_dir, cache=True)
    ds = dm.dataset("train")
    batch = dm._collate([ds[0], ds[1]])
    for v in batch.values():
        v.zero_()  # a batch holds fresh tensors: zeroing it leaves the cached examples untouched
    for k, v in plain[0].items():
        assert torch.equal(v, ds[0][k]), k


def test_hand_made_label_mask():
    """A hand-made prompt + response: 'ab' response tokens get labels, everything before them -100.

    With the tiny tokenizer the response "<answer>\\nx\\n</answer>" is 5 tokens, plus <|im_end|> = 6 labelled.
    """
    from PIL import Image

    from aynamics.processor import build_sft_example, load_processor

    proc = load_processor(TINY_ASSET_DIR)
    frame = Image.new("RGB", (56, 56), (120, 30, 200))
    response = "<answer>\nx\n</answer>"
    ex = build_sft_example(proc, [frame], response, system_prompt="s", user_prompt="u")
    ids = proc.tokenizer(response, add_special_tokens=False)["input_ids"]
    assert len(ids) == 5
    expected = [IGNORE_INDEX] * (len(ex["input_ids"]) - 6) + ids + [proc.tokenizer.convert_tokens_to_ids("<|im_end|>")]
    assert ex["labels"].tolist() == expected


def test_modality_and_video(dataset_dir):
    """flow frames differ from rgb frames; as_video gives one video with half the visual tokens of 2 images."""
    rgb = _dm(dataset_dir, modality="rgb").dataset("train")[0]
    flow = _dm(dataset_dir, modality="flow").dataset("train")[0]
    dm = _dm(dataset_dir, modality="rgb", as_video=True)
    video = dm.dataset("train")[0]
    assert not torch.equal(rgb["pixel_values"], flow["pixel_values"])
    # the two frames shown are the first and last stored, 0.9 s apart at 30 fps: temporal patches (two frames each)
    # are 2 × 0.9 s apart (Qwen2.5-VL's second_per_grid_ts = temporal patch / fps; it was 1.0 for any data)
    assert video["second_per_grid_ts"].tolist() == pytest.approx([1.8])
    assert dm.processor.video_fps == pytest.approx(dm.prompt.shown_fps)
    assert "pixel_values_videos" in video and "pixel_values" not in video
    n_img = int((rgb["mm_token_type_ids"] == IMAGE).sum())
    n_vid = int((video["mm_token_type_ids"] == VIDEO).sum())
    assert n_vid * 2 == n_img


def test_evaluation_scores_in_the_view_of_the_video(dataset_dir):
    """The evaluation records carry their frames' size, and the scene evaluation observes each true scene at that
    aspect ratio (64×48 here: the scorer's default 120×80 would show a wider view than the model saw)."""
    from types import SimpleNamespace

    from aynamics.callbacks import SceneEvaluation

    dm = SceneDataModule(str(dataset_dir), lm.ModelSpec(kind="tiny").processor_path, num_frames=2)
    dm.setup("fit")
    evaluation = SceneEvaluation(num_samples=2, baseline=False)
    evaluation._prepare(SimpleNamespace(datamodule=dm))
    assert [r["size"] for r in evaluation._records] == [(64, 48)] * 2
    assert {(r["observation"].width, r["observation"].height) for r in evaluation._records} == {(64, 48)}


def test_in_context_examples_enter_the_prompt(dataset_dir):
    dm = _dm(dataset_dir, num_examples=1)
    assert dm.prompt.examples == (dm.splits["train"][0]["scene_yaml"],)
    ex = dm.dataset("train")[1]
    text = dm.processor.tokenizer.decode(ex["input_ids"][ex["labels"] == IGNORE_INDEX])
    assert "Example 1:" in text and dm.splits["train"][0]["scene_yaml"].strip() in text


def test_batches_are_left_padded(dataset_dir):
    batch = next(iter(_dm(dataset_dir).train_dataloader()))
    assert batch["input_ids"].shape[0] == 2
    assert (batch["attention_mask"][:, -1] == 1).all()  # left padding: every row ends with a real token
    assert batch["input_ids"].shape == batch["labels"].shape == batch["mm_token_type_ids"].shape


def test_resumable_sampler_order():
    """Skipping k indices of an epoch continues the uninterrupted order; ranks split an epoch without overlap."""
    full = list(ResumableSampler(10, seed=3))
    assert sorted(full) == list(range(10))
    assert list(ResumableSampler(10, seed=3, skip=4)) == full[4:]
    s = ResumableSampler(10, seed=3, start_epoch=1, skip=2)
    s.set_epoch(1)
    tail = list(s)
    s.set_epoch(2)
    assert len(tail) == 8 and len(list(s)) == 10
    s0, s1 = ResumableSampler(10, seed=3, rank=0, world=2), ResumableSampler(10, seed=3, rank=1, world=2)
    assert sorted(list(s0) + list(s1)) == list(range(10))
    other = ResumableSampler(10, seed=3)
    other.set_epoch(1)
    assert list(other) != full


def test_train_loader_shards_over_the_trainers_ranks(dataset_dir):
    """Under a 2-process trainer the data module's loader gives rank 0 and rank 1 disjoint halves of the training
    split (5 records: 3 and 3, the sampler padding one as DDP does); after 1 step of batch 2 each rank resumes
    past its own first batch."""
    from types import SimpleNamespace

    dm = SceneDataModule(str(dataset_dir), str(TINY_ASSET_DIR), num_frames=2, batch_size=2)
    dm.setup("fit")

    def order(rank: int, step: int = 0) -> list[int]:
        dm.trainer = SimpleNamespace(global_rank=rank, world_size=2, global_step=step, accumulate_grad_batches=1)
        return list(dm.train_dataloader().sampler)

    r0, r1 = order(0), order(1)
    assert len(r0) == len(r1) == 3 and set(r0) | set(r1) == set(range(5)) and len(set(r0) & set(r1)) <= 1
    assert order(0, step=1) == r0[2:] and order(1, step=1) == r1[2:]


def test_resume_position_with_gradient_accumulation(dataset_dir):
    """5 records at batch 1 with 2 batches per optimizer step: Lightning steps on batches 2, 4 and the epoch's last
    (5), so an epoch is 3 steps. After step 3 the resumed run starts epoch 1 from its first example, after step 4
    two examples into it (counting 2 batches per step, it skipped 1 example of epoch 1 after step 3)."""
    from types import SimpleNamespace

    dm = SceneDataModule(str(dataset_dir), str(TINY_ASSET_DIR), num_frames=2, batch_size=1)
    dm.setup("fit")
    n = len(dm.dataset("train"))

    def order(step: int) -> list[int]:
        dm.trainer = SimpleNamespace(global_rank=0, world_size=1, global_step=step, accumulate_grad_batches=2)
        sampler = dm.train_dataloader().sampler
        return sampler.start_epoch, list(sampler)

    epoch1 = list(ResumableSampler(n, seed=dm.seed, start_epoch=1))
    assert n == 5
    assert order(2) == (0, list(ResumableSampler(n, seed=dm.seed))[4:])
    assert order(3) == (1, epoch1)
    assert order(4) == (1, epoch1[2:])


def test_length_grouped_order_pads_less_and_still_resumes():
    lengths = [1, 4, 2, 3] * 16  # 64 examples, object counts 1-4
    kw = dict(seed=5, lengths=lengths, batch_size=4)
    grouped = list(ResumableSampler(64, **kw))
    assert sorted(grouped) == list(range(64))  # every example once per epoch
    assert grouped == list(ResumableSampler(64, **kw))  # a function of (seed, epoch)
    assert list(ResumableSampler(64, **kw, skip=8)) == grouped[8:]  # a resume skips whole batches

    def padding(order):  # tokens of padding per epoch if a scene's length is its object count
        batches = [[lengths[i] for i in order[k : k + 4]] for k in range(0, 64, 4)]
        return sum(max(b) * len(b) - sum(b) for b in batches)

    assert padding(grouped) < padding(list(ResumableSampler(64, seed=5))) / 3
    s0 = ResumableSampler(64, **kw, rank=0, world=2)
    s1 = ResumableSampler(64, **kw, rank=1, world=2)
    assert sorted(list(s0) + list(s1)) == list(range(64))
    with pytest.raises(ValueError, match="lengths has 3 entries for 64"):
        ResumableSampler(64, seed=5, lengths=[1, 2, 3])


def test_shifted_visuals_hand_example():
    """Example k gets example k+1's patches (the last gets the first's); text and grids stay; odd sizes refuse."""
    a, b = torch.full((4, 3), 1.0), torch.full((4, 3), 2.0)  # 4 patches of 3 values each
    grid = torch.tensor([[1, 2, 2], [1, 2, 2]])
    batch = {
        "input_ids": torch.zeros(2, 5, dtype=torch.long),
        "pixel_values": torch.cat([a, b]),
        "image_grid_thw": grid,
    }
    shifted = lm.shifted_visuals(batch)
    assert torch.equal(shifted["pixel_values"], torch.cat([b, a]))
    assert shifted["input_ids"] is batch["input_ids"] and torch.equal(shifted["image_grid_thw"], grid)
    assert lm.shifted_visuals({**batch, "image_grid_thw": torch.tensor([[1, 2, 2], [1, 2, 4]])}) is None
    one = {"input_ids": torch.zeros(1, 5), "pixel_values": a, "image_grid_thw": grid[:1]}
    assert lm.shifted_visuals(one) is None


def test_mean_scene_by_hand():
    """Two one-box scenes (x = 0 and 1, mass 1 and 3) and one sphere scene: the box structure wins (2 of 3),
    position x averages to 0.5, mass to 2.0; the sphere scene is ignored."""
    box = """
- type: box
  size: [0.2, 0.2, 0.2]
  state: {position: [X, 0, 0.2], orientation: [1, 0, 0, 0], linear_velocity: [1, 0, 0], angular_velocity: [0, 0, 0]}
  physics: {friction: [0.5, 0.0], mass: M, damping: -3}
- type: camera
  fovy: 45
  orientation: 45
  position: [0, -2, 3]
"""
    sphere = box.replace("type: box", "type: sphere").replace("size: [0.2, 0.2, 0.2]", "radius: 0.2")
    scenes = [parse(box.replace("X", "0").replace("M", "1")), parse(box.replace("X", "1").replace("M", "3"))]
    scenes.append(parse(sphere.replace("X", "5").replace("M", "9")))
    avg = mean_scene(scenes)
    assert avg.structure == ("box",)
    assert avg.objects[0].state.position[0] == pytest.approx(0.5)
    assert avg.objects[0].physics.mass == pytest.approx(2.0)


def test_mean_scene_keeps_an_optional_field_only_when_more_than_half_have_it():
    """Two box scenes, one with restitution 0.4 and an environment item: 1 of 2 is not more than half, so the
    average has neither. A third scene with restitution 0.6: 2 of 3 have it, kept as (0.4 + 0.6) / 2 = 0.5."""
    box = (
        "- {type: box, size: [0.2, 0.2, 0.2], state: {position: [0, 0, 0.2]}PHYS}\n"
        "- {type: camera, position: [0, -2, 3]}\n"
    )
    env = "- {type: environment, air_density: 1.2}\n"
    plain = parse(box.replace("PHYS", ""))
    bouncy = parse(box.replace("PHYS", ", physics: {restitution: 0.4}") + env)
    half = mean_scene([plain, bouncy])
    assert half.objects[0].physics.restitution is None and half.environment is None
    more = mean_scene([plain, bouncy, parse(box.replace("PHYS", ", physics: {restitution: 0.6}"))])
    assert more.objects[0].physics.restitution == pytest.approx(0.5)


def test_bad_input_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no data set"):
        load_splits(tmp_path / "nothing")
    with pytest.raises(ValueError, match="modality = 'depth'"):
        SceneDataModule(str(tmp_path), str(TINY_ASSET_DIR), modality="depth")
    with pytest.raises(ValueError, match="target = 'yaml'"):
        SceneDataModule(str(tmp_path), str(TINY_ASSET_DIR), target="yaml")


def test_a_data_dir_that_is_not_a_data_set_says_what_it_is(dataset_dir, tmp_path):
    """A split's folder, a file or a folder of other files was told to run `aynamics generate --out` on that same
    path, which generate refuses: each is now named for what it is; only a missing or empty folder gets that hint."""
    split = dataset_dir / "validation"
    with pytest.raises(FileNotFoundError, match=f"is the 'validation' split of the data set '{dataset_dir}': give"):
        load_splits(split, what="--data")
    (tmp_path / "s.yaml").write_text("- type: box\n")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("x")
    (tmp_path / "empty").mkdir()
    for path, message in [
        (tmp_path / "s.yaml", "is a file: point --data at a data set folder"),
        (tmp_path / "other", "is a folder holding no data set"),
        (tmp_path / "empty", "holds no data set .*aynamics generate --num 12 --out"),
        (tmp_path / "missing", "holds no data set .*aynamics generate --num 12 --out"),
    ]:
        with pytest.raises(FileNotFoundError, match=f"--data = '{path}' {message}"):
            load_splits(path, what="--data")


def test_a_file_or_a_missing_name_inside_a_data_set_is_not_called_a_split(dataset_dir):
    """data.dir = DS/dataset_dict.json was "the 'dataset_dict.json' split of the data set DS", and a mistyped
    DS/trian "the 'trian' split": only a folder there is a split."""
    for path, message in [
        (dataset_dir / "dataset_dict.json", "is a file: point --data at a data set folder"),
        (dataset_dir / "trian", "holds no data set .*aynamics generate --num 12 --out"),
    ]:
        with pytest.raises(FileNotFoundError, match=f"--data = '{path}' {message}"):
            load_splits(path, what="--data")


def test_frame_windows_by_hand():
    pairs = frame_windows(10, 2)  # every window of >= 5 frame steps, the model's (0, 9) left out
    assert len(pairs) == 14 and (0, 9) not in pairs
    assert pairs[:2] == [(0, 5), (0, 6)] and pairs[-1] == (4, 9)
    triples = frame_windows(10, 3)  # linspace(0, 5, 3) = 0, 2.5, 5: rounded half to even
    assert len(triples) == 14 and triples[0] == (0, 2, 5) and (0, 4, 9) not in triples
    # 5 stored frames, 4 steps: a window spanning exactly half of them (2 steps) counts, "at least half":
    # (0, 2), (0, 3), (1, 3), (1, 4), (2, 4); (0, 4) is the model's (only (0, 3) and (1, 4) with more than half)
    assert frame_windows(5, 2) == [(0, 2), (0, 3), (1, 3), (1, 4), (2, 4)]
    assert frame_windows(1, 1) == []
    with pytest.raises(ValueError, match="num_frames = 0"):
        frame_windows(10, 0)


@pytest.mark.parametrize("as_video", [False, True])
def test_warmup_views_are_other_frames_with_their_targets(dataset_dir, as_video):
    dm = _dm(dataset_dir, as_video=as_video, visual_targets=True, warmup_views=2, cache=True)
    train, ds = dm.dataset("train"), dm.warmup_dataset()
    views = ds.datasets[1]
    assert isinstance(views, WarmupViews) and ds.datasets[0] is train and len(ds) == 3 * len(train)
    n_stored = len(train.split[0]["rgb"])
    for scene in range(len(train)):
        w = [views.window(2 * scene), views.window(2 * scene + 1)]
        assert w[0] != w[1] and all(x in frame_windows(n_stored, 2) for x in w)
    rec, w = train.split[1], views.window(3)  # scene 1, view 1: the processor on those frames, by hand
    frames, masks = [rec["rgb"][f] for f in w], [rec["segmentation"][f] for f in w]
    if as_video:
        want = dm.processor.process_video(frames)
        pix, grid = want["pixel_values_videos"], want["video_grid_thw"]
    else:
        want = dm.processor.process_images(frames)
        pix, grid = want["pixel_values"], want["image_grid_thw"]
    ex = ds[len(train) + 3]
    assert torch.equal(ex["pixel_values_videos" if as_video else "pixel_values"], pix)
    assert torch.equal(ex["visual_targets"], token_targets(masks, rec["shapes"], grid, as_video=as_video))
    assert ds[len(train) + 3] is ex  # cached
    again = _dm(dataset_dir, as_video=as_video, visual_targets=True, warmup_views=2).warmup_dataset().datasets[1]
    assert [again.window(i) for i in range(len(again))] == [views.window(i) for i in range(len(views))]


def test_warmup_views_are_drawn_from_the_data_seed():
    """Each scene's views are a permutation of its frame windows drawn from (data.seed, scene): 5 stored frames,
    2 a view: the 5 windows (0, 2), (0, 3), (1, 3), (1, 4), (2, 4) (`frame_windows(5, 2)`), all 5 views of a scene
    each once, in the order of `default_rng([seed, scene]).permutation(5)`; another seed, another order (a seed
    left out of the draw gave every data.seed the same views)."""
    import datasets
    import numpy as np

    split = datasets.Dataset.from_dict({"rgb": [[0] * 5] * 3, "segmentation": [[0] * 5] * 3, "shapes": [["box"]] * 3})
    windows = [(0, 2), (0, 3), (1, 3), (1, 4), (2, 4)]
    prompt = lm.PromptSpec(num_frames=2)
    drawn = {}
    for seed in (0, 1):
        views = WarmupViews(split, None, prompt, views=5, seed=seed)
        assert views.windows == windows and len(views) == 15
        drawn[seed] = [views.window(i) for i in range(15)]
        for scene in range(3):
            order = np.random.default_rng([seed, scene]).permutation(5)
            assert drawn[seed][5 * scene : 5 * scene + 5] == [windows[k] for k in order]
    assert drawn[0] != drawn[1]


def test_loaders_serve_their_own_split_and_limits(dataset_dir):
    """The tiny data set holds 5 train, 4 validation and 3 test scenes (records say their split). The test loader
    serves the 3 test records (batches of 2: 2 + 1), the validation loader the 4 validation ones; data.limit_val = 3
    keeps the first min(3, 4) = 3 validation records, limit 2 the first 2 train ones, a limit past the split all."""
    dm = _dm(dataset_dir)
    sizes = {s: len(dm.splits[s]) for s in ("train", "validation", "test")}
    assert sizes == {"train": 5, "validation": 4, "test": 3}
    for split, loader in (("test", dm.test_dataloader()), ("validation", dm.val_dataloader())):
        assert set(loader.dataset.split["split"]) == {split}
        assert loader.dataset.split["index"] == dm.splits[split]["index"]
    assert [len(b["input_ids"]) for b in dm.test_dataloader()] == [2, 1]
    limited = _dm(dataset_dir, limit_val=3).val_dataloader().dataset
    assert len(limited) == 3 and limited.split["index"] == dm.splits["validation"]["index"][:3]
    assert len(dm.dataset("train", 2)) == 2 and dm.dataset("train", 2).split["index"] == dm.splits["train"]["index"][:2]
    assert len(dm.dataset("train", 99)) == 5


def test_warmup_views_misconfigurations_are_named(dataset_dir):
    with pytest.raises(ValueError, match="data.warmup_views = 2: .*visual_targets=true"):
        _dm(dataset_dir, warmup_views=2)
    with pytest.raises(ValueError, match=r"data.warmup_views = 99: must be in \[1, 14\]"):
        _dm(dataset_dir, visual_targets=True, warmup_views=99).warmup_dataset()


def test_validation_is_split_over_the_processes(dataset_dir):
    """5 items over 2 processes: [0, 2, 4] and [1, 3, 0] (padded to equal shares, as DistributedSampler pads),
    3 over 3 one each, fewer items than processes or one process: all of them. The data module's validation
    loader serves its process's share under a 2-process trainer."""
    from types import SimpleNamespace

    from aynamics.data import eval_shard

    def trainer(rank: int, world: int):
        return SimpleNamespace(global_rank=rank, world_size=world)

    assert [eval_shard(5, trainer(r, 2)) for r in (0, 1)] == [[0, 2, 4], [1, 3, 0]]
    assert [eval_shard(3, trainer(r, 3)) for r in range(3)] == [[0], [1], [2]]
    # 4 over 3: ceil(4 / 3) = 2 each, 6 slots, padded with the first 6 - 4 = 2 items: [0, 1, 2, 3, 0, 1], then
    # every 3rd from the rank (a pad of 4 % 3 = 1 item gave rank 2 one item and the others two)
    assert [eval_shard(4, trainer(r, 3)) for r in range(3)] == [[0, 3], [1, 0], [2, 1]]
    assert eval_shard(2, trainer(1, 3)) is None and eval_shard(5, trainer(0, 1)) is None and eval_shard(5, None) is None
    # the padding is last and not the process's own: [0, 3] holds 2 of them, [1, 0] and [2, 1] one each
    assert [eval_shard(4, trainer(r, 3)).real for r in range(3)] == [2, 1, 1]
    assert [eval_shard(5, trainer(r, 2)).real for r in (0, 1)] == [3, 2]
    dm = _dm(dataset_dir)
    n = len(dm.dataset("validation"))
    assert n >= 2
    shares = []
    for rank in (0, 1):
        dm.trainer = trainer(rank, 2)
        loader = dm.val_dataloader()
        shares.append(list(loader.sampler))
        assert sum(len(b["input_ids"]) for b in loader) == -(-n // 2)  # the examples it serves
    dm.trainer = None
    assert shares == [eval_shard(n, trainer(r, 2)) for r in (0, 1)] and list(dm.val_dataloader().sampler) == list(
        range(n)
    )


def test_real_rows_leave_out_the_padding_of_each_batch():
    """5 items over 2 processes, batches of 2: rank 1 evaluates [1, 3 | 0], 0 padding: batch 0 has 2 real rows,
    batch 1 none (0 of 1); rank 0 [0, 2 | 4]: 2 and 1. 7 over 4, batches of 1: rank 3 [3, 0]: 1 then 0. A loader
    without `eval_shard` (one process, a plain sampler) counts every row."""
    from types import SimpleNamespace

    from aynamics.data import eval_shard, real_rows

    def loader(n, rank, world, batch):
        return SimpleNamespace(
            sampler=eval_shard(n, SimpleNamespace(global_rank=rank, world_size=world)), batch_size=batch
        )

    assert [real_rows(loader(5, 1, 2, 2), b, r) for b, r in ((0, 2), (1, 1))] == [2, 0]
    assert [real_rows(loader(5, 0, 2, 2), b, r) for b, r in ((0, 2), (1, 1))] == [2, 1]
    assert [real_rows(loader(7, 3, 4, 1), b, 1) for b in (0, 1)] == [1, 0]
    assert (
        real_rows(loader(5, 0, 1, 2), 1, 2) == 2
        and real_rows(SimpleNamespace(sampler=range(4), batch_size=2), 1, 2) == 2
    )


def test_loader_workers_follow_the_device(dataset_dir, monkeypatch):
    """data.num_workers null: 0 workers and plain memory on the CPU or with cached examples; on GPUs up to 4
    workers per process from the cores this process may use, one left per process (16 cores, 2 GPUs: 4; 6 cores:
    2; 2 cores: 0; when srun started each process as a task, its 3 cores give 2), pinned memory, workers kept between
    epochs and started deaf to SIGTERM. A number given is used as is."""
    import signal
    from types import SimpleNamespace

    from lightning.pytorch.accelerators import CPUAccelerator

    from aynamics.data import init_worker, loader_options, loader_workers

    cpu = SimpleNamespace(accelerator=CPUAccelerator(), num_devices=2)
    gpu = SimpleNamespace(accelerator=object(), num_devices=2, global_rank=1, world_size=2, global_step=0)
    gpu.accumulate_grad_batches = 1
    assert loader_workers(None, cpu) == loader_workers(None, None) == 0 and loader_workers(3, cpu) == 3
    monkeypatch.delenv("SLURM_CPUS_PER_TASK", raising=False)
    for cores, workers in ((16, 4), (6, 2), (2, 0)):
        monkeypatch.setattr(os, "sched_getaffinity", lambda _, n=cores: set(range(n)), raising=False)
        assert loader_workers(None, gpu) == workers, cores
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "3")
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: set(range(3)), raising=False)
    assert loader_workers(None, gpu) == 0  # one SLURM task per node, Lightning starting the processes: shared
    srun = SimpleNamespace(**vars(gpu), strategy=SimpleNamespace(cluster_environment=SimpleNamespace()))
    srun.strategy.cluster_environment.creates_processes_externally = True  # a task per process: its own cores
    assert loader_workers(None, srun) == 2 and loader_workers(None, srun, cache=True) == 0
    monkeypatch.delenv("SLURM_CPUS_PER_TASK")
    assert loader_options(None, cpu) == {"num_workers": 0, "persistent_workers": False, "pin_memory": False}
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: set(range(16)), raising=False)
    options = loader_options(None, gpu)
    init = options.pop("worker_init_fn")
    assert options == {"num_workers": 4, "persistent_workers": True, "pin_memory": True}
    assert init.func is init_worker and init.keywords["rank"] == 1
    before = signal.getsignal(signal.SIGTERM)
    try:
        init(0)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before)
    dm = SceneDataModule(str(dataset_dir), str(TINY_ASSET_DIR), num_frames=2, batch_size=2)
    dm.setup("fit")
    dm.trainer = gpu
    loaders = [dm.train_dataloader(), dm.val_dataloader()]
    assert [(d.num_workers, d.pin_memory, d.persistent_workers) for d in loaders] == [(4, True, True)] * 2
    dm.cache = True
    assert [d.num_workers for d in (dm.train_dataloader(), dm.val_dataloader())] == [0, 0]
    dm.cache, dm.trainer = False, SimpleNamespace(**{**vars(gpu), "accelerator": CPUAccelerator()})
    loaders = [dm.train_dataloader(), dm.val_dataloader()]
    assert [(d.num_workers, d.pin_memory) for d in loaders] == [(0, False)] * 2


def test_evaluation_records_read_only_the_columns_the_model_sees(dataset_dir, tmp_path):
    """A broken image in a column the model does not read (flow, for an rgb prompt) leaves the record in the
    evaluation, as `aynamics evaluate` keeps it; a broken frame of its own modality leaves it out, named."""
    import datasets

    splits = datasets.load_from_disk(str(dataset_dir))
    broken = splits["validation"].cast_column("flow", datasets.List(datasets.Image(decode=False)))
    garbage = [{"bytes": b"\x89PNG not really", "path": None}]
    broken = broken.map(lambda r, i: {"flow": garbage} if i == 0 else {}, with_indices=True)
    splits["validation"] = broken.cast_column("flow", datasets.List(datasets.Image()))
    splits.save_to_disk(str(tmp_path / "ds"))
    dm = SceneDataModule(str(tmp_path / "ds"), str(TINY_ASSET_DIR), num_frames=2)
    dm.setup("fit")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no record left out
        assert len(dm.eval_records("validation", 2)) == 2
    dm = SceneDataModule(str(tmp_path / "ds"), str(TINY_ASSET_DIR), num_frames=2, modality="flow")
    dm.setup("fit")
    with pytest.warns(UserWarning, match=r"record 0 of the validation records of data.dir = .* is left out"):
        assert len(dm.eval_records("validation", 2)) == 1
