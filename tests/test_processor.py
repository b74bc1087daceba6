"""Processor, chat formatting, batching and log-prob helpers on the tiny tokenizer asset (offline, CPU)."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

from aynamics.batching import append_completions, collate, trim_completion
from aynamics.lm import sft_loss, token_accuracy
from aynamics.logprobs import mean_token_logprob, token_logprobs
from aynamics.processor import (
    IGNORE_INDEX,
    IMAGE,
    VIDEO,
    build_messages,
    build_prompt,
    build_sft_example,
    load_processor,
    response_ids,
    sample_frames,
    type_tokens,
)
from aynamics.tokenizer_build import SPECIAL_TOKENS, TAG_TOKENS, TINY_ASSET_DIR, build_tokenizer

PROMPTS = {"system_prompt": "You are a physics expert.", "user_prompt": "Write the scene as YAML."}
RESPONSE = "<answer>\n- type: box\n  mass: 1.25\n</answer>"


@pytest.fixture(scope="module")
def proc():
    return load_processor(TINY_ASSET_DIR)


@pytest.fixture(scope="module")
def frames():
    """Three 56x84 RGB frames: 2x3 merged tokens each (56/28 x 84/28)."""
    rng = np.random.default_rng(0)
    return [rng.integers(0, 255, (56, 84, 3), dtype=np.uint8) for _ in range(3)]


def test_tokenizer_asset(proc):
    tok = proc.tokenizer
    assert sum(p.stat().st_size for p in TINY_ASSET_DIR.iterdir()) < 1_000_000
    assert len(tok) < 4096
    for t in SPECIAL_TOKENS + TAG_TOKENS:
        assert len(tok(t, add_special_tokens=False)["input_ids"]) == 1, t
    assert tok.eos_token == "<|im_end|>" and tok.pad_token == "<|endoftext|>"
    # digits are single tokens, as in Qwen
    pieces = tok.convert_ids_to_tokens(tok("mass: -12.75", add_special_tokens=False)["input_ids"])
    assert [p for p in pieces if p.strip("Ġ").isdigit()] == ["1", "2", "7", "5"]
    # <think>/<answer> survive skip_special_tokens (they are added, not special); <|im_end|> does not
    text = "<think>a</think>\n\n<answer>b</answer>"
    assert tok.decode(tok(text + "<|im_end|>")["input_ids"], skip_special_tokens=True) == text


def test_tokenizer_build_is_reproducible():
    """The committed asset is what `python -m aynamics.tokenizer_build` produces."""
    import json

    saved = json.loads((TINY_ASSET_DIR / "tokenizer.json").read_text())["model"]["vocab"]
    assert build_tokenizer().get_vocab(with_added_tokens=False) == saved


def test_tokenizer_build_cli_rewrites_every_asset_file_unchanged(tmp_path, capsys):
    """`python -m aynamics.tokenizer_build --out DIR` writes the four files of the committed asset byte for byte:
    the whole tokenizer (normaliser, pre-tokeniser, added tags that are not special), its config (eos <|im_end|>,
    pad <|endoftext|>, 32768 tokens), the chat template and the image processor's pixel bounds (56², 112²)."""
    from aynamics import tokenizer_build

    tokenizer_build.main(["--out", str(tmp_path / "tok")])
    names = sorted(p.name for p in TINY_ASSET_DIR.iterdir())
    assert names == ["chat_template.jinja", "preprocessor_config.json", "tokenizer.json", "tokenizer_config.json"]
    assert sorted(p.name for p in (tmp_path / "tok").iterdir()) == names
    for name in names:
        assert (tmp_path / "tok" / name).read_bytes() == (TINY_ASSET_DIR / name).read_bytes(), name
    assert f"wrote {tmp_path / 'tok'}:" in capsys.readouterr().out


def test_chat_template(proc):
    messages = build_messages(2, examples=["- type: box"], **PROMPTS)
    text = proc.apply_chat_template(messages, tokenize=False, add_generation_prompt=True)
    assert text == (
        "<|im_start|>system\nYou are a physics expert.<|im_end|>\n<|im_start|>user\nExample 1:\n- type: box\n\n"
        + "<|vision_start|><|image_pad|><|vision_end|>" * 2
        + "Write the scene as YAML.<|im_end|>\n<|im_start|>assistant\n"
    )
    video = build_messages(3, as_video=True, **PROMPTS)
    assert "<|vision_start|><|video_pad|><|vision_end|>" in proc.apply_chat_template(video, tokenize=False)


def test_video_has_half_the_visual_tokens(proc, frames):
    four = frames + frames[:1]
    images = build_prompt(proc, four, **PROMPTS)
    video = build_prompt(proc, four, as_video=True, **PROMPTS)
    n_img = int((images["mm_token_type_ids"] == IMAGE).sum())
    n_vid = int((video["mm_token_type_ids"] == VIDEO).sum())
    assert n_img == 4 * 6 and n_vid == 2 * 6
    assert images["image_grid_thw"].tolist() == [[1, 4, 6]] * 4
    assert video["video_grid_thw"].tolist() == [[2, 4, 6]]
    assert video["pixel_values_videos"].shape == (2 * 24, 3 * 2 * 14 * 14)
    assert video["second_per_grid_ts"].tolist() == [1.0]  # temporal patch 2 / video_fps 2
    assert "pixel_values" not in video and "pixel_values_videos" not in images


def test_video_temporal_positions_follow_the_shown_frames_clock(frames):
    """4 of the 10 stored frames (every third of 30 at 30 fps) are shown at 0, 0.3, 0.6, 0.9 s: the two temporal
    patches (frames 0-1 and 2-3) start 0.6 s apart, which Qwen2.5-VL's temporal positions read from
    `second_per_grid_ts` (it was 1.0 whatever the data: the processor's default 2 fps). Training, evaluation, PRO
    and predict build it alike."""
    from aynamics.lm import ModelSpec, PromptSpec
    from aynamics.lm import load_processor as load_for

    prompt = PromptSpec(as_video=True, num_frames=4)
    assert prompt.shown_fps == pytest.approx(10 / 3)
    four = frames + frames[:1]
    video = build_prompt(load_for(ModelSpec(kind="tiny"), prompt), four, as_video=True, **PROMPTS)
    assert video["second_per_grid_ts"].tolist() == pytest.approx([0.6])
    # a 60 fps data set storing frames 0, 6, ..., 54 shows 4 frames 0.3 s apart too; 2 frames: 0.9 s apart
    assert PromptSpec(num_frames=4, fps=60, clip_frames=tuple(range(0, 60, 6))).shown_fps == pytest.approx(10 / 3)
    assert PromptSpec(num_frames=2).shown_fps == pytest.approx(1 / 0.9)
    assert PromptSpec(num_frames=1).shown_fps == 2.0
    # 4 of 5 stored frames (15 fps, every third): the processor shows 0, 3, 9, 12 (0, 0.2, 0.6, 0.8 s), patches
    # starting at 0 and 0.6 s: 2 / 0.6 (the frames' mean spacing, 0.267 s, would put the second patch at 0.533 s)
    uneven = PromptSpec(num_frames=4, fps=15, clip_frames=(0, 3, 6, 9, 12))
    assert uneven.shown_fps == pytest.approx(2 / 0.6)


def test_video_patch_layout_matches_qwen_video_processor(proc, frames):
    """Rebuild the frames from image patches, then patchify them with the code of Qwen2VLVideoProcessor.patchify."""
    t, p, m = 2, 14, 2
    padded = frames + frames[-1:]  # odd frame count: the last frame is repeated
    img = proc.process_images(padded)
    _, gh, gw = img["image_grid_thw"][0].tolist()
    x = img["pixel_values"].view(4, gh // m, gw // m, m, m, 3, t, p, p)[..., 0, :, :]
    video = x.permute(0, 5, 1, 3, 6, 2, 4, 7).reshape(1, 4, 3, gh * p, gw * p)  # (B, F, C, H, W)
    ref = video.view(1, 2, t, 3, gh // m, m, p, gw // m, m, p).permute(0, 1, 4, 7, 5, 8, 3, 2, 6, 9)
    ref = ref.reshape(2 * gh * gw, 3 * t * p * p)
    out = proc.process_video(frames)
    assert torch.equal(out["pixel_values_videos"], ref)
    assert out["video_grid_thw"].tolist() == [[2, gh, gw]]


def test_sft_labels_mask_prompt_and_images(proc, frames):
    """Hand count: the response tokenises to R ids; labels keep exactly R + 1 (<|im_end|>) tokens."""
    tok = proc.tokenizer
    ex = build_sft_example(proc, frames, RESPONSE, **PROMPTS)
    prompt = build_prompt(proc, frames, **PROMPTS)
    r = tok(RESPONSE, add_special_tokens=False)["input_ids"]
    n_prompt = len(prompt["input_ids"])
    assert torch.equal(ex["input_ids"][:n_prompt], prompt["input_ids"])
    keep = ex["labels"] != IGNORE_INDEX
    assert int(keep.sum()) == len(r) + 1
    assert not keep[:n_prompt].any()  # system, user text and every <|image_pad|> are masked
    assert ex["labels"][keep].tolist() == r + [tok.convert_tokens_to_ids("<|im_end|>")]
    assert torch.equal(ex["labels"][keep], ex["input_ids"][keep])
    assert ((ex["mm_token_type_ids"] == IMAGE) == (ex["input_ids"] == proc.image_token_id)).all()
    assert int((ex["mm_token_type_ids"] == IMAGE).sum()) == 3 * 6
    assert tok.decode(ex["input_ids"][keep]) == RESPONSE + "<|im_end|>"


def test_collate_pads_left_and_concatenates_pixels(proc, frames):
    a = build_sft_example(proc, frames, RESPONSE, **PROMPTS)
    b = build_sft_example(proc, frames[:2], "<answer>x</answer>", examples=["- type: sphere"], **PROMPTS)
    pad = proc.tokenizer.pad_token_id
    batch = collate([a, b], pad)
    n = batch["input_ids"].shape[1]
    assert n == max(len(a["input_ids"]), len(b["input_ids"]))
    short = 0 if len(a["input_ids"]) < n else 1
    k = n - len((a, b)[short]["input_ids"])
    assert (batch["input_ids"][short, :k] == pad).all() and (batch["attention_mask"][short, :k] == 0).all()
    assert (batch["labels"][short, :k] == IGNORE_INDEX).all() and (batch["mm_token_type_ids"][short, :k] == 0).all()
    assert batch["pixel_values"].shape[0] == a["pixel_values"].shape[0] + b["pixel_values"].shape[0]
    assert batch["image_grid_thw"].shape == (5, 3)
    right = collate([a, b], pad, padding_side="right")
    assert (right["attention_mask"][short, -k:] == 0).all()
    video = build_sft_example(proc, frames, RESPONSE, as_video=True, **PROMPTS)
    with pytest.raises(ValueError, match="mixed"):
        collate([a, video], pad)


def test_a_videos_seconds_survive_the_precision_plugins_input_cast(proc, frames):
    """A 30-fps video shown every 8th frame (3.75 fps: `second_per_grid_ts` 2 / 3.75 = 0.5333 s a temporal patch of
    2 frames): under bf16-true (and DeepSpeed) Lightning casts the batch's floating tensors to bfloat16, where it
    reads 0.53515625, and Qwen2.5-VL's temporal position of the 15th patch (transformers' `get_vision_position_ids`:
    (arange(T) · tokens_per_second · seconds).long(), tokens_per_second 2) became 15, against the 14 generation
    (inputs not cast) gives. `model_inputs` now hands the model the collated float32 value."""
    from lightning.pytorch.plugins.precision import HalfPrecision

    from aynamics.batching import model_inputs

    ex = build_sft_example(proc, frames, RESPONSE, as_video=True, **PROMPTS)
    ex["second_per_grid_ts"] = torch.tensor([2 / 3.75])
    batch = collate([ex], proc.tokenizer.pad_token_id)
    cast = HalfPrecision("bf16-true").convert_input(batch)
    assert cast["second_per_grid_ts"].item() == 0.53515625  # what the model read before
    seconds = model_inputs(cast)["second_per_grid_ts"]
    assert seconds.dtype == torch.float32 and torch.equal(seconds, torch.tensor([2 / 3.75]))
    assert torch.equal(model_inputs(batch)["second_per_grid_ts"], seconds)  # no cast: the same

    def positions(s):
        return (torch.arange(15) * (2 * s[0])).long()[-1].item()

    assert (positions(seconds), positions(cast["second_per_grid_ts"])) == (14, 15)


def test_append_completions_keeps_visual_inputs_aligned(proc, frames):
    tok = proc.tokenizer
    pad, im_end = tok.pad_token_id, tok.convert_tokens_to_ids("<|im_end|>")
    prompt = build_prompt(proc, frames, **PROMPTS)
    c = [tok("<answer>a</answer>", add_special_tokens=False)["input_ids"], [5, 6, 7, 8, 9, 10, 11]]
    generated = torch.tensor([c[0] + [im_end, pad, pad, pad], [5, 6, im_end, 9, 9, 9, 9], c[1]])
    batch = append_completions(prompt, generated, pad_token_id=pad, eos_token_ids=[im_end, pad])
    n = 3
    assert batch["input_ids"].shape[0] == n
    assert torch.equal(batch["pixel_values"], prompt["pixel_values"].repeat(n, 1))
    assert torch.equal(batch["image_grid_thw"], prompt["image_grid_thw"].repeat(n, 1))
    for row in range(n):
        ids, mm = batch["input_ids"][row], batch["mm_token_type_ids"][row]
        assert ((mm == IMAGE) == (ids == proc.image_token_id)).all()
        assert int((mm == IMAGE).sum()) == int((prompt["mm_token_type_ids"] == IMAGE).sum())
    keep = batch["labels"] != IGNORE_INDEX
    assert keep.sum(-1).tolist() == [len(c[0]) + 1, 3, len(c[1])]
    assert batch["labels"][1][keep[1]].tolist() == [5, 6, im_end]
    assert (batch["mm_token_type_ids"][keep] == 0).all()


def test_trim_completion():
    assert trim_completion([4, 5, 2, 7], eos_token_ids=[2]) == [4, 5, 2]
    assert trim_completion(torch.tensor([4, 5, 0, 0]), pad_token_id=0) == [4, 5]
    assert trim_completion([4, 5], pad_token_id=0, eos_token_ids=[2]) == [4, 5]


def test_mean_token_logprob_hand_computed():
    """Row 0: labels [-, 1, 0]. logits[0] = [0, 0] gives log p(1) = log 1/2; logits[1] = [ln 3, 0] gives
    log p(0) = log 3/4. Mean = (log 0.5 + log 0.75) / 2 = -0.4904. Row 1 has no labels: 0."""
    logits = torch.tensor([[[0.0, 0.0], [math.log(3.0), 0.0], [5.0, -5.0]]] * 2)
    labels = torch.tensor([[IGNORE_INDEX, 1, 0], [IGNORE_INDEX] * 3])
    expected = (math.log(0.5) + math.log(0.75)) / 2
    out = mean_token_logprob(logits, labels)
    assert out.shape == (2,)
    assert out[0].item() == pytest.approx(expected, abs=1e-6) and out[1].item() == 0.0
    lp, mask = token_logprobs(logits, labels)
    assert mask.tolist() == [[True, True], [False, False]]
    assert lp[0].tolist() == pytest.approx([math.log(0.5), math.log(0.75)], abs=1e-6)


def test_weighted_sft_loss_by_hand():
    """The logits of the test above: token NLLs log 2 and log 4/3. Weights 1 and 3 on the two labelled tokens:
    (1 · log 2 + 3 · log 4/3) / 4; the unweighted mean is (log 2 + log 4/3) / 2."""
    logits = torch.tensor([[[0.0, 0.0], [math.log(3.0), 0.0], [5.0, -5.0]]])
    labels = torch.tensor([[IGNORE_INDEX, 1, 0]])
    plain, n = sft_loss(logits, labels)
    assert plain.item() == pytest.approx((math.log(2) + math.log(4 / 3)) / 2, abs=1e-6) and n.item() == 2
    weighted, n = sft_loss(logits, labels, torch.tensor([[0.0, 1.0, 3.0]]))
    assert weighted.item() == pytest.approx((math.log(2) + 3 * math.log(4 / 3)) / 4, abs=1e-6) and n.item() == 2
    assert sft_loss(logits, labels, torch.ones(1, 3))[0].item() == pytest.approx(plain.item())
    with pytest.raises(ValueError, match=r"loss weights \(1, 2\) do not match labels \(1, 3\)"):
        sft_loss(logits, labels, torch.ones(1, 2))


def test_sft_loss_divides_by_labelled_tokens_only():
    """Labels [-, -, 1, 0]: after the shift 3 positions, 2 labelled: logits[1] = [0, 0] gives log p(1) = log 1/2,
    logits[2] = [ln 3, 0] gives log p(0) = log 3/4; loss = (log 2 + log 4/3) / 2 = 0.4904 (not / 3), n = 2."""
    logits = torch.tensor([[[0.0, 0.0], [0.0, 0.0], [math.log(3.0), 0.0], [5.0, -5.0]]])
    labels = torch.tensor([[IGNORE_INDEX, IGNORE_INDEX, 1, 0]])
    loss, n = sft_loss(logits, labels)
    assert loss.item() == pytest.approx((math.log(2) + math.log(4 / 3)) / 2, abs=1e-6) and n.item() == 2


def test_type_tokens_mark_the_type_values(proc):
    response = "<answer>- type: sphere\n  radius: 0.1\n- type: camera\n  fovy: 50.0\n</answer>"
    mask = type_tokens(proc, response)
    ids = response_ids(proc, response)
    assert mask.dtype == torch.bool and len(mask) == len(ids)
    assert [proc.tokenizer.decode([i]) for i, m in zip(ids, mask.tolist()) if m] == [" sphere", " camera"]
    assert not type_tokens(proc, "<answer>no types here</answer>").any()


def test_token_accuracy_by_hand():
    """Labels [-, 1, 0, 1]; greedy predictions from logits[0..2]: 1, 1, 0. The mask keeps tokens 1 and 3:
    1 right (token 1), 1 wrong (token 3: predicted 0): 0.5. Token 2 alone: wrong, 0.0."""
    logits = torch.tensor([[[0.0, 1.0], [0.0, 2.0], [3.0, 0.0], [0.0, 0.0]]])
    labels = torch.tensor([[IGNORE_INDEX, 1, 0, 1]])
    assert token_accuracy(logits, labels, torch.tensor([[False, True, False, True]])).item() == 0.5
    assert token_accuracy(logits, labels, torch.tensor([[False, False, True, False]])).item() == 0.0
    assert math.isnan(token_accuracy(logits, labels, torch.zeros(1, 4, dtype=torch.bool)).item())
    with pytest.raises(ValueError, match=r"mask \(1, 3\)"):
        token_accuracy(logits, labels, torch.ones(1, 3, dtype=torch.bool))


def test_errors_name_the_bad_value(proc, frames):
    with pytest.raises(ValueError, match="2 <\\|image_pad\\|> placeholders but 1"):
        proc(text="<|image_pad|><|image_pad|>", images=frames[:1])
    with pytest.raises(ValueError, match="different sizes"):
        proc.process_video([frames[0], np.zeros((28, 28, 3), np.uint8)])
    with pytest.raises(ValueError, match="padding_side = 'middle'"):
        collate([build_prompt(proc, frames, **PROMPTS)], 0, padding_side="middle")


def test_sample_frames_and_processor_options(proc, frames, tmp_path):
    assert sample_frames(list(range(10)), 4) == [0, 3, 6, 9]
    assert sample_frames(list(range(3)), None) == [0, 1, 2]
    small = load_processor(TINY_ASSET_DIR, min_pixels=28 * 28, max_pixels=28 * 28, num_frames=2)
    ex = build_prompt(small, frames, **PROMPTS)
    assert ex["image_grid_thw"].tolist() == [[1, 2, 2]] * 2  # two frames, each squeezed to 28x28
    small.save_pretrained(tmp_path)
    again = load_processor(tmp_path)
    assert again.num_frames == 2 and again.image_processor.size["longest_edge"] == 28 * 28
    assert torch.equal(build_prompt(again, frames, **PROMPTS)["input_ids"], ex["input_ids"])
    assert "torchvision" not in sys.modules


def test_a_saved_processor_keeps_its_video_frame_rate(frames, tmp_path):
    """Frames given at 5 fps: a frame pair (temporal patch 2) lasts 2 / 5 = 0.4 s, and still does after a save
    and load (the adapter's processor; at the default 2 fps it would be 2 / 2 = 1 s)."""
    fast = load_processor(TINY_ASSET_DIR, video_fps=5)
    fast.save_pretrained(tmp_path)
    again = load_processor(tmp_path)
    assert again.video_fps == 5.0
    assert again.process_video(frames[:2])["second_per_grid_ts"].tolist() == pytest.approx([0.4])


def test_apply_chat_template_tokenize_matches_build_prompt(proc, frames):
    """transformers' own path (images inside the messages) gives the same ids and pixels as `build_prompt`."""
    from PIL import Image

    messages = build_messages(len(frames), **PROMPTS)
    it = iter(frames)
    for part in messages[1]["content"]:
        if part["type"] == "image":
            part["image"] = Image.fromarray(next(it))
    out = proc.apply_chat_template(messages, tokenize=True, return_dict=True, add_generation_prompt=True)
    ref = build_prompt(proc, frames, **PROMPTS)
    assert torch.equal(out["input_ids"][0], ref["input_ids"])
    assert torch.equal(out["mm_token_type_ids"][0], ref["mm_token_type_ids"])
    torch.testing.assert_close(out["pixel_values"], ref["pixel_values"])


def test_pixel_bounds_out_of_order_are_named_as_a_setting_not_a_broken_checkpoint():
    """min_pixels above max_pixels (or above the checkpoint's max when max is null) is the data.* setting's fault:
    the error said 'cannot load the processor ... give a local folder holding a Qwen2.5-VL checkpoint'."""
    with pytest.raises(ValueError, match=r"min_pixels = 20000 > max_pixels = 12544 .*need min_pixels <= max_pixels"):
        load_processor(TINY_ASSET_DIR, min_pixels=20000)
    with pytest.raises(ValueError) as info:
        load_processor(TINY_ASSET_DIR, min_pixels=20000, max_pixels=10000)
    assert "checkpoint" not in str(info.value) and not isinstance(info.value, OSError)


def test_sft_loss_is_a_mean_over_the_batchs_tokens_not_its_rows():
    """Row 0: the labels of `test_mean_token_logprob_hand_computed`, NLLs ln 2 and ln 4/3; row 1: one labelled token
    of probability 1/4 (logits [ln 3, 0], label 1), NLL ln 4. Token mean (ln 2 + ln 4/3 + ln 4) / 3 = ln(32/3) / 3
    = 0.7890, n = 3 (a mean of the row means would give (ln(8/3)/2 + ln 4) / 2 = 0.9383)."""
    logits = torch.tensor(
        [[[0.0, 0.0], [math.log(3.0), 0.0], [5.0, -5.0]], [[5.0, -5.0], [math.log(3.0), 0.0], [5.0, -5.0]]]
    )
    labels = torch.tensor([[IGNORE_INDEX, 1, 0], [IGNORE_INDEX, IGNORE_INDEX, 1]])
    loss, n = sft_loss(logits, labels)
    assert loss.item() == pytest.approx(math.log(32 / 3) / 3, abs=1e-6) and n.item() == 3


def test_weighted_sft_loss_ignores_weights_on_unlabelled_tokens():
    """Labels [-, -, 1, 0] (NLLs ln 2 and ln 4/3, `test_sft_loss_divides_by_labelled_tokens_only`), weight 1 on every
    position, the unlabelled ones too: the plain mean (ln 2 + ln 4/3) / 2, not / 3."""
    logits = torch.tensor([[[0.0, 0.0], [0.0, 0.0], [math.log(3.0), 0.0], [5.0, -5.0]]])
    labels = torch.tensor([[IGNORE_INDEX, IGNORE_INDEX, 1, 0]])
    loss, _ = sft_loss(logits, labels, torch.ones(1, 4))
    assert loss.item() == pytest.approx((math.log(2) + math.log(4 / 3)) / 2, abs=1e-6)


def test_token_accuracy_skips_unlabelled_tokens_inside_the_mask():
    """Labels [-, 1, -, 1], mask all True: only tokens 1 (predicted 1 from logits[0]: right) and 3 (predicted 0 from
    logits[2]: wrong) are scored: 0.5 over 2 tokens (with the unlabelled token 2 it would be 1/3 over 3)."""
    from aynamics.lm import token_count

    logits = torch.tensor([[[0.0, 1.0], [0.0, 2.0], [3.0, 0.0], [0.0, 0.0]]])
    labels = torch.tensor([[IGNORE_INDEX, 1, IGNORE_INDEX, 1]])
    mask = torch.ones(1, 4, dtype=torch.bool)
    assert token_accuracy(logits, labels, mask).item() == 0.5 and token_count(labels, mask) == 2
