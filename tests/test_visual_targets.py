"""Dense visual targets: per-token counts, shapes and pixel shares by hand, the loss by hand, alignment with the
visual tokens, the augmentation equal to processing mirrored / recoloured frames, and the warm-up actually
lowering the loss."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from train_fixtures import tiny_dataset

from aynamics.data import SceneDataModule
from aynamics.lm import ModelSpec
from aynamics.model import find_visual
from aynamics.processor import IMAGE, VIDEO, load_processor, sample_frames
from aynamics.sft import SFTModule
from aynamics.visual_targets import (
    MAX_INSTANCES,
    NUM_OUTPUTS,
    NUM_TARGETS,
    Augment,
    aux_loss,
    frame_tokens,
    token_targets,
    warm_up,
)


def _mask() -> np.ndarray:
    """56×56 labels = 2×2 merged tokens of 28 px. The box (1) sits in the top-left token; the sphere (2) spans both
    bottom tokens, centred in the bottom-right one (80 of its 300 pixels are bottom-left: share 4/15); the
    cylinder (3) lies in the bottom-right token too."""
    m = np.zeros((56, 56), np.uint8)
    m[2:10, 3:9] = 1
    m[40:50, 20:50] = 2  # columns 20..49: mean 34.5 -> token column 1
    m[52:55, 50:55] = 3
    return m


SHAPES3 = ["box", "sphere", "cylinder"]


# rows: tokens in row-major order; columns: objects centred there, box, sphere, cylinder, pixel share
BY_HAND = [[1, 1, 0, 0, 1], [0, 0, 0, 0, 0], [0, 0, 0, 0, 4 / 15], [2, 0, 1, 1, 1 + 11 / 15]]


def test_token_targets_by_hand():
    t = token_targets([_mask()], SHAPES3, torch.tensor([[1, 4, 4]]))
    assert t.shape == (4, NUM_TARGETS)
    torch.testing.assert_close(t, torch.tensor(BY_HAND))
    assert t[:, 0].sum() == 3 and t[:, -1].sum().item() == pytest.approx(3)  # both count the objects in view
    # two images: the same rows, then an empty frame
    two = token_targets([_mask(), np.zeros((56, 56), np.uint8)], SHAPES3, torch.tensor([[1, 4, 4]] * 2))
    torch.testing.assert_close(two, torch.tensor(BY_HAND + [[0, 0, 0, 0, 0]] * 4))


def test_video_tokens_take_the_first_frame_that_shows_an_object():
    a, b = np.zeros((56, 56), np.uint8), np.zeros((56, 56), np.uint8)
    a[5, 5] = 1  # the cylinder moves from the top-left token to the top-right one
    b[5, 40] = 1
    t = token_targets([a, b, b], ["cylinder"], torch.tensor([[2, 4, 4]]), as_video=True)
    # pair 1 (a, b): centred top-left in a; pair 2 (b, b repeated): top-right
    empty = [0, 0, 0, 0, 0]
    assert t.tolist() == [[1, 0, 0, 1, 1], empty, empty, empty] + [empty, [1, 0, 0, 1, 1], empty, empty]


def test_masks_are_resized_to_the_processed_frame():
    """A 28×28 mask given for a 56×56 processed frame: nearest resize keeps each centre in its token (and here
    every pixel share: each object's pixels come back in the same tokens)."""
    small = _mask()[::2, ::2]
    torch.testing.assert_close(token_targets([small], SHAPES3, torch.tensor([[1, 4, 4]])), torch.tensor(BY_HAND))


def test_bad_input_is_named():
    grid = torch.tensor([[1, 4, 4]])
    with pytest.raises(ValueError, match="'cone'"):
        token_targets([_mask()], ["box", "cone", "box"], grid)
    with pytest.raises(ValueError, match="label 3 but the scene has 1 objects"):
        token_targets([_mask()], ["box"], grid)
    with pytest.raises(ValueError, match="does not match 2 masks"):
        token_targets([_mask(), _mask()], SHAPES3, grid)
    with pytest.raises(ValueError, match=r"need \(N, 8\) and \(N, 5\)"):
        aux_loss(torch.zeros(3, 5), torch.zeros(3, 4))
    with pytest.raises(ValueError, match="frame_tokens sum to 4, but there are 3 tokens"):
        aux_loss(torch.zeros(3, NUM_OUTPUTS), torch.zeros(3, NUM_TARGETS), frame_tokens=[2, 2])


def test_aux_loss_by_hand():
    """Zero logits: cross-entropy over 4 counts = log 4, binary cross-entropy = log 2, and 10 × the mean squared
    share (0 + 1 + 0.09 + 0) / 4 = 2.725: loss log 8 + 2.725."""
    targets = torch.tensor([[0, 0, 0, 0, 0], [1, 1, 0, 0, 1], [3, 1, 1, 1, 0.3], [0, 0, 0, 0, 0]])
    loss, stats = aux_loss(torch.zeros(4, NUM_OUTPUTS), targets, frame_tokens=[2, 2])
    assert loss.item() == pytest.approx(math.log(8) + 2.725)
    assert stats["count_acc"].item() == 0.5  # argmax of equal logits is class 0: right on the two empty tokens
    assert stats["object_recall"].item() == 0.0
    # frames: shares sum to 1 (predicted 0: wrong) and to 0.3 (rounds to 0 objects: right)
    assert stats["frame_count_acc"].item() == 0.5
    perfect = torch.full((4, NUM_OUTPUTS), -30.0)
    perfect[torch.arange(4), targets[:, 0].long()] = 30.0
    perfect[:, 4:7] = torch.where(targets[:, 1:4] > 0, 30.0, -30.0)
    perfect[:, 7] = targets[:, 4]
    loss, stats = aux_loss(perfect, targets, frame_tokens=[2, 2])
    assert loss.item() < 1e-6 and stats["count_acc"].item() == 1.0 and stats["object_recall"].item() == 1.0
    assert stats["frame_count_acc"].item() == 1.0
    assert "frame_count_acc" not in aux_loss(perfect, targets)[1]
    # share_weight 0: counts and shapes only; the frame count is then the sum of predicted centres: zero logits
    # give 0 and 0, perfect centre logits 1 and 3, against 1 and 0 objects in view (summed target shares)
    perfect[:, 7] = 0.0
    loss, stats = aux_loss(torch.zeros(4, NUM_OUTPUTS), targets, frame_tokens=[2, 2], share_weight=0.0)
    assert loss.item() == pytest.approx(math.log(8)) and stats["frame_count_acc"].item() == 0.5
    assert aux_loss(perfect, targets, frame_tokens=[2, 2], share_weight=0.0)[1]["frame_count_acc"].item() == 0.5


def test_frame_tokens_from_the_grid():
    assert frame_tokens(torch.tensor([[1, 4, 4], [1, 4, 6]])) == [4, 6]  # two images
    assert frame_tokens(torch.tensor([[2, 4, 6]])) == [6, 6]  # a video of two frame pairs


@pytest.mark.parametrize("as_video", [False, True])
def test_augment_equals_processing_mirrored_and_recoloured_frames(as_video):
    """Mirroring / permuting the channels of the processed patches gives what the processor gives for the
    mirrored / recoloured frames, and the targets follow: those of the mirrored masks."""
    proc = load_processor(ModelSpec(kind="tiny").processor_path)
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (56, 84, 3), dtype=np.uint8) for _ in range(2)]
    masks = [np.zeros((56, 84), np.uint8), np.zeros((56, 84), np.uint8)]
    masks[0][5:9, 3:20], masks[1][30:40, 60:70] = 1, 2

    def processed(fr):
        if as_video:
            out = proc.process_video(fr)
            return out["pixel_values_videos"], out["video_grid_thw"]
        out = proc.process_images(fr)
        return out["pixel_values"], out["image_grid_thw"]

    pixels, grid = processed(frames)
    assert grid.tolist() == ([[1, 4, 6]] if as_video else [[1, 4, 6]] * 2)
    targets = token_targets(masks, ["box", "sphere"], grid, as_video=as_video)
    augment = Augment.of(proc.image_processor)
    got_p, got_t = augment(pixels, grid, targets, mirror=True, channels=[2, 0, 1])
    want_p, _ = processed([np.ascontiguousarray(f[:, ::-1][..., [2, 0, 1]]) for f in frames])
    want_t = token_targets(
        [np.ascontiguousarray(m[:, ::-1]) for m in masks], ["box", "sphere"], grid, as_video=as_video
    )
    torch.testing.assert_close(got_p, want_p, atol=1e-5, rtol=1e-5)
    assert torch.equal(got_t, want_t)
    same_p, same_t = augment(pixels, grid, targets, mirror=False, channels=[0, 1, 2])
    torch.testing.assert_close(same_p, pixels, atol=1e-5, rtol=1e-5)
    assert torch.equal(same_t, targets)
    with pytest.raises(ValueError, match="covers"):
        augment(pixels[:-4], grid, targets, mirror=False, channels=[0, 1, 2])


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return tiny_dataset(tmp_path_factory)


@pytest.mark.parametrize("as_video", [False, True])
def test_one_target_row_per_visual_token(dataset_dir, as_video):
    path = ModelSpec(kind="tiny").processor_path
    dm = SceneDataModule(str(dataset_dir), path, num_frames=3, batch_size=2, as_video=as_video, visual_targets=True)
    dm.setup("fit")
    ds = dm.dataset("train")
    for i in range(len(ds)):
        ex = ds[i]
        kind = VIDEO if as_video else IMAGE
        assert ex["visual_targets"].shape == (int((ex["mm_token_type_ids"] == kind).sum()), NUM_TARGETS)
        assert (ex["visual_targets"][:, 0] <= ds.split[i]["num_objects"]).all()
        if not as_video:  # each image's shares sum to the objects that show in it
            masks = sample_frames(ds.split[i]["segmentation"], 3)
            shown = [len(set(np.unique(np.asarray(m)).tolist()) - {0}) for m in masks]
            sums = [t[:, -1].sum().item() for t in ex["visual_targets"].split(frame_tokens(ex["image_grid_thw"]))]
            assert sums == pytest.approx(shown)
    # at least one token covers an object in every training scene whose objects are visible in the frames
    visible = [any(any(v) for v in ds.split[i]["states"]["visible"]) for i in range(len(ds))]
    assert all(ds[i]["visual_targets"][:, 0].any() for i in range(len(ds)) if visible[i])
    batch = next(iter(dm.train_dataloader()))
    assert batch["visual_targets"].shape[0] == int((batch["mm_token_type_ids"] > 0).sum())


def test_warm_up_lowers_the_dense_loss(dataset_dir):
    spec = ModelSpec(kind="tiny", train_vision=True)
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=4, visual_targets=True)
    dm.setup("fit")
    ds = dm.dataset("train")
    module = SFTModule(spec, vision_aux_weight=1.0)
    visual, head = find_visual(module.model), module.visual_head

    def loss() -> float:
        with torch.no_grad():
            pv = torch.cat([ds[i]["pixel_values"] for i in range(len(ds))])
            grid = torch.cat([ds[i]["image_grid_thw"] for i in range(len(ds))])
            tokens = visual(pv, grid_thw=grid).pooler_output
            return aux_loss(head(tokens), torch.cat([ds[i]["visual_targets"] for i in range(len(ds))]))[0].item()

    before = loss()
    state = {k: v.clone() for k, v in module.state_dict().items() if "lora" in k}
    augment = Augment.of(dm.processor.image_processor)  # as SFTModule runs it (vision_augment: true)
    history = warm_up(visual, head, ds, steps=60, batch_size=4, lr=3e-3, seed=0, augment=augment)
    assert [h["step"] for h in history] == [50, 60]
    assert set(history[0]) == {"step", "loss", "count_acc", "object_recall", "frame_count_acc"}
    assert loss() < 0.7 * before
    assert all(torch.equal(v, module.state_dict()[k]) for k, v in state.items())  # the language model is untouched


def test_warm_up_of_a_bfloat16_tower(dataset_dir):
    """A pretrained tower in bfloat16 (model.dtype) before the float32 head: the warm-up runs outside autocast
    and casts the tokens to the head's dtype (it failed: "mat1 and mat2 must have the same dtype")."""
    spec = ModelSpec(kind="tiny", train_vision=True)
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=2, visual_targets=True)
    dm.setup("fit")
    module = SFTModule(spec, vision_aux_weight=1.0)
    visual = find_visual(module.model).to(torch.bfloat16)
    history = warm_up(visual, module.visual_head, dm.dataset("train"), steps=2, batch_size=2, lr=1e-3, seed=0)
    assert module.visual_head.weight.dtype == torch.float32 and np.isfinite(history[-1]["loss"])


def test_aux_loss_without_objects_has_nan_recall():
    """Tokens without any object centre (an empty batch, frames showing no object): the loss is finite, the
    count accuracy that of the zero counts, and the object recall NaN (a float on the logits' device; its
    integer argmax broke it)."""
    torch.manual_seed(0)
    logits = torch.randn(6, NUM_OUTPUTS)
    loss, stats = aux_loss(logits, torch.zeros(6, NUM_TARGETS), [3, 3])
    assert (
        torch.isfinite(loss) and torch.isnan(stats["object_recall"]) and stats["object_recall"].dtype == torch.float32
    )
    assert stats["count_acc"] == (logits[:, : MAX_INSTANCES + 1].argmax(-1) == 0).float().mean()


def test_dense_loss_takes_bfloat16_tokens(dataset_dir):
    """In a training step the tower's tokens reach the float32 head in the tower's dtype: bfloat16 tokens (a
    pretrained tower outside autocast) give the float32 tokens' loss, to bfloat16's precision."""
    spec = ModelSpec(kind="tiny", train_vision=True)
    dm = SceneDataModule(str(dataset_dir), spec.processor_path, num_frames=2, batch_size=2, visual_targets=True)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    module = SFTModule(spec, vision_aux_weight=1.0)
    module._loss(batch)  # the forward keeps the tower's tokens
    tokens = module._visual_tokens
    full = module._vision_aux(batch, 2, "train")
    module._visual_tokens = tokens.to(torch.bfloat16)
    half = module._vision_aux(batch, 2, "train")
    assert half.dtype == torch.float32 and half.item() == pytest.approx(full.item(), rel=2e-2)


def test_centred_count_is_clipped_at_three():
    """Four 3×3-pixel boxes all in the top-left token: count class 3 (3+), not 4 (which the 4-way cross-entropy
    could not even take); box present; pixel share 4 (each object's pixels all in that token)."""
    m = np.zeros((56, 56), np.uint8)
    for k, (r, c) in enumerate([(2, 2), (2, 10), (10, 2), (10, 10)]):
        m[r : r + 3, c : c + 3] = k + 1
    t = token_targets([m], ["box"] * 4, torch.tensor([[1, 4, 4]]))
    assert t.tolist() == [[3, 1, 0, 0, 4]] + [[0, 0, 0, 0, 0]] * 3
    loss, _ = aux_loss(torch.zeros(4, NUM_OUTPUTS), t)
    assert torch.isfinite(loss)


def test_mask_labels_past_the_scenes_objects_are_refused():
    """`_mask` holds labels 1..3; a scene of two objects has no object 3."""
    with pytest.raises(ValueError, match="label 3 but the scene has 2 objects"):
        token_targets([_mask()], ["box", "sphere"], torch.tensor([[1, 4, 4]]))


def test_object_recall_and_frame_count_by_hand():
    """Targets of `test_aux_loss_by_hand`; predicted count classes [0, 1, 1, 0]: tokens 1 and 2 hold centres, both
    predicted to hold some (recall 1) though token 2's count (3) is wrong (count_acc 3/4). With share_weight 0 the
    frame count is the predicted centres' (1 and 1 against 1 and 0 objects in view: 0.5), whatever the predicted
    shares say (here the true ones, which would give 1.0)."""
    targets = torch.tensor([[0, 0, 0, 0, 0], [1, 1, 0, 0, 1], [3, 1, 1, 1, 0.3], [0, 0, 0, 0, 0]])
    logits = torch.zeros(4, NUM_OUTPUTS)
    logits[torch.arange(4), torch.tensor([0, 1, 1, 0])] = 5.0
    logits[:, -1] = targets[:, -1]
    _, stats = aux_loss(logits, targets, frame_tokens=[2, 2], share_weight=0.0)
    assert stats["object_recall"].item() == 1.0 and stats["count_acc"].item() == 0.75
    assert stats["frame_count_acc"].item() == 0.5
    assert aux_loss(logits, targets, frame_tokens=[2, 2])[1]["frame_count_acc"].item() == 1.0
