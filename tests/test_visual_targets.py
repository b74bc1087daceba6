"""Dense visual targets: per-token counts and shapes by hand, the loss by hand, alignment with the visual tokens,
and the warm-up actually lowering the loss."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from train_fixtures import tiny_dataset

from aynamics.data import SceneDataModule
from aynamics.lm import ModelSpec
from aynamics.model import find_visual
from aynamics.processor import IMAGE, VIDEO
from aynamics.sft import SFTModule
from aynamics.visual_targets import NUM_OUTPUTS, aux_loss, token_targets, warm_up


def _mask() -> np.ndarray:
    """56×56 labels = 2×2 merged tokens of 28 px. The box (1) sits in the top-left token; the sphere (2) spans both
    bottom tokens, centred in the bottom-right one; the cylinder (3) lies in the bottom-right token too."""
    m = np.zeros((56, 56), np.uint8)
    m[2:10, 3:9] = 1
    m[40:50, 20:50] = 2  # columns 20..49: mean 34.5 -> token column 1
    m[52:55, 50:55] = 3
    return m


SHAPES3 = ["box", "sphere", "cylinder"]


def test_token_targets_by_hand():
    t = token_targets([_mask()], SHAPES3, torch.tensor([[1, 4, 4]]))
    # rows: tokens in row-major order; columns: objects centred there, box, sphere, cylinder
    assert t.tolist() == [[1, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [2, 0, 1, 1]]
    assert t[:, 0].sum() == 3  # summed over the frame: the objects in view
    # two images: the same rows, then an empty frame
    two = token_targets([_mask(), np.zeros((56, 56), np.uint8)], SHAPES3, torch.tensor([[1, 4, 4]] * 2))
    assert two.tolist() == t.tolist() + [[0, 0, 0, 0]] * 4


def test_video_tokens_take_the_first_frame_that_shows_an_object():
    a, b = np.zeros((56, 56), np.uint8), np.zeros((56, 56), np.uint8)
    a[5, 5] = 1  # the cylinder moves from the top-left token to the top-right one
    b[5, 40] = 1
    t = token_targets([a, b, b], ["cylinder"], torch.tensor([[2, 4, 4]]), as_video=True)
    # pair 1 (a, b): centred top-left in a; pair 2 (b, b repeated): top-right
    assert (
        t.tolist()
        == [[1, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]] + [[0, 0, 0, 0], [1, 0, 0, 1]] + [[0, 0, 0, 0]] * 2
    )


def test_masks_are_resized_to_the_processed_frame():
    """A 28×28 mask given for a 56×56 processed frame: nearest resize keeps each centre in its token."""
    small = _mask()[::2, ::2]
    assert token_targets([small], SHAPES3, torch.tensor([[1, 4, 4]])).tolist() == [
        [1, 1, 0, 0],
        [0, 0, 0, 0],
        [0, 0, 0, 0],
        [2, 0, 1, 1],
    ]


def test_bad_input_is_named():
    grid = torch.tensor([[1, 4, 4]])
    with pytest.raises(ValueError, match="'cone'"):
        token_targets([_mask()], ["box", "cone", "box"], grid)
    with pytest.raises(ValueError, match="label 3 but the scene has 1 objects"):
        token_targets([_mask()], ["box"], grid)
    with pytest.raises(ValueError, match="does not match 2 masks"):
        token_targets([_mask(), _mask()], SHAPES3, grid)
    with pytest.raises(ValueError, match=r"need \(N, 7\)"):
        aux_loss(torch.zeros(3, 5), torch.zeros(3, 4, dtype=torch.long))


def test_aux_loss_by_hand():
    """Zero logits: cross-entropy over 4 counts = log 4, binary cross-entropy = log 2: loss log 8."""
    targets = torch.tensor([[0, 0, 0, 0], [1, 1, 0, 0], [3, 1, 1, 1], [0, 0, 0, 0]])
    loss, stats = aux_loss(torch.zeros(4, NUM_OUTPUTS), targets)
    assert loss.item() == pytest.approx(math.log(8))
    assert stats["count_acc"].item() == 0.5  # argmax of equal logits is class 0: right on the two empty tokens
    assert stats["object_recall"].item() == 0.0
    perfect = torch.full((4, NUM_OUTPUTS), -30.0)
    perfect[torch.arange(4), targets[:, 0]] = 30.0
    perfect[:, 4:] = torch.where(targets[:, 1:] > 0, 30.0, -30.0)
    loss, stats = aux_loss(perfect, targets)
    assert loss.item() < 1e-6 and stats["count_acc"].item() == 1.0 and stats["object_recall"].item() == 1.0


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
        assert ex["visual_targets"].shape == (int((ex["mm_token_type_ids"] == kind).sum()), 4)
        assert (ex["visual_targets"][:, 0] <= ds.split[i]["num_objects"]).all()
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
    history = warm_up(visual, head, ds, steps=60, batch_size=4, lr=3e-3, seed=0)
    assert [h["step"] for h in history] == [50, 60]
    assert loss() < 0.7 * before
    assert all(torch.equal(v, module.state_dict()[k]) for k, v in state.items())  # the language model is untouched
