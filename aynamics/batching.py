"""Batches of examples (`processor.build_prompt`, `build_sft_example`): padding, the model's inputs, completions.

`collate` pads a list of examples into a batch, LEFT-padded by default: generation needs left padding, and
training is indifferent to it because Qwen2.5-VL derives its 3-D positions from the attention mask.
`append_completions` makes one prompt and N generated completions a batch whose labels are the completions.

    batch = collate([ex, ...], pad_token_id=proc.tokenizer.pad_token_id)
    out = model(**model_inputs(batch))
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator, Sequence

import torch

from aynamics.processor import IGNORE_INDEX, TEXT, append_response

# Keys of a collated batch that the model's forward takes.
MODEL_KEYS = (
    "input_ids",
    "attention_mask",
    "mm_token_type_ids",
    "pixel_values",
    "image_grid_thw",
    "pixel_values_videos",
    "video_grid_thw",
    "second_per_grid_ts",
)

_PAD_VALUES = {
    "input_ids": None,
    "attention_mask": 0,
    "labels": IGNORE_INDEX,
    "mm_token_type_ids": TEXT,
    "type_tokens": False,  # per token (`type_tokens`), added by the data module
    "loss_weights": 0.0,  # per token, when the data module has a type_weight
}
_CAT_KEYS = (
    "pixel_values",
    "image_grid_thw",
    "pixel_values_videos",
    "video_grid_thw",
    "second_per_grid_ts",
    "visual_targets",  # per visual token (aynamics.visual_targets), when the data module adds them
)


def collate(
    examples: Sequence[dict[str, torch.Tensor]], pad_token_id: int, padding_side: str = "left"
) -> dict[str, torch.Tensor]:
    """Pad per-token tensors to the longest example and concatenate the visual tensors in example order.

    Args:
        examples: Unbatched examples from `build_prompt` / `build_sft_example` / `append_response`.
        pad_token_id: Id written into padded input_ids (labels get -100, masks 0).
        padding_side: "left" (default; what `generate` needs, and fine for training) or "right".
    """
    if not examples:
        raise ValueError("collate got 0 examples")
    if padding_side not in ("left", "right"):
        raise ValueError(f"padding_side = {padding_side!r}: must be 'left' or 'right'")
    length = max(len(ex["input_ids"]) for ex in examples)
    batch: dict[str, torch.Tensor] = {}
    for key, value in _PAD_VALUES.items():
        if key not in examples[0]:
            continue
        value = pad_token_id if value is None else value
        rows = []
        for ex in examples:
            pad = ex[key].new_full((length - len(ex[key]),), value)
            rows.append(torch.cat([pad, ex[key]] if padding_side == "left" else [ex[key], pad]))
        batch[key] = torch.stack(rows)
    for key in _CAT_KEYS:
        present = [key in ex for ex in examples]
        if any(present) and not all(present):
            raise ValueError(f"collate: {key} in {sum(present)} of {len(examples)} examples: images and videos mixed")
        if all(present):
            batch[key] = torch.cat([ex[key] for ex in examples])
    if "second_per_grid_ts" in batch:
        batch[SECONDS_BITS] = batch["second_per_grid_ts"].to(torch.float32).view(torch.int32)
    return batch


# A video's seconds per temporal patch as the bits of its float32 value: a precision plugin casts every floating
# tensor of a batch to the model's dtype before the step (`bf16-true`, and DeepSpeed even with bf16-mixed), and
# in bfloat16 2 / 3.75 s reads 0.5352 s, which moves Qwen2.5-VL's temporal positions (floor(t · seconds · tokens per
# second): 15 for 14 at the 15th patch) away from those generation gives (its inputs are not cast). Integers are
# not cast; `model_inputs` reads the value back exactly.
SECONDS_BITS = "second_per_grid_ts_bits"


# The summed label weight of the batches of one optimizer step (`with_window_weights`), as the bits of a float64:
# an integer tensor, which precision plugins do not cast (bfloat16 holds whole numbers exactly only up to 256).
WINDOW_WEIGHT_BITS = "window_weight_bits"


def label_weight(batch: dict[str, torch.Tensor]) -> float:
    """What the SFT loss of `batch` is a mean over (`lm.sft_loss`): its labelled tokens, or their summed
    `loss_weights` when it has them."""
    mask = batch["labels"][:, 1:] != IGNORE_INDEX
    if "loss_weights" in batch:
        return float((batch["loss_weights"][:, 1:].double() * mask).sum())
    return float(mask.sum())


def with_window_weights(batches: Iterable[dict[str, torch.Tensor]], size: int) -> Iterator[dict[str, torch.Tensor]]:
    """The batches, each of every `size` consecutive ones (an optimizer step's under gradient accumulation; the
    last window of an epoch may be shorter) holding the window's summed `label_weight` (`WINDOW_WEIGHT_BITS`), so
    that the SFT step can be the mean over all of the step's tokens, not a mean of its micro-batches' means."""
    if size < 1:
        raise ValueError(f"size = {size}: must be >= 1")
    it = iter(batches)
    while chunk := list(itertools.islice(it, size)):
        total = torch.tensor([sum(label_weight(b) for b in chunk)], dtype=torch.float64).view(torch.int64)
        for b in chunk:
            yield {**b, WINDOW_WEIGHT_BITS: total}


def window_weight(batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
    """The summed label weight of the optimizer step `batch` belongs to (float64, (1,)), or None when the loader
    did not record it (`with_window_weights`)."""
    bits = batch.get(WINDOW_WEIGHT_BITS)
    return None if bits is None else bits.view(torch.float64)


def model_inputs(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The subset of `batch` the model's forward/generate takes (drops labels and extras), with a collated video's
    `second_per_grid_ts` as collated, whatever dtype a precision plugin cast it to (`SECONDS_BITS`)."""
    out = {k: v for k, v in batch.items() if k in MODEL_KEYS}
    if SECONDS_BITS in batch:
        out["second_per_grid_ts"] = batch[SECONDS_BITS].view(torch.float32)
    return out


def append_completions(
    prompt: dict[str, torch.Tensor],
    completions: Sequence[Sequence[int]] | torch.Tensor,
    *,
    pad_token_id: int,
    eos_token_ids: Sequence[int] = (),
    padding_side: str = "left",
) -> dict[str, torch.Tensor]:
    """Batch of N rows = one prompt + each of N completions, sharing the prompt's frames.

    The visual tensors are repeated N times (the model consumes one copy per row), image/video grids likewise,
    and mm_token_type_ids is 0 on the completions. Labels hold the completion tokens, -100 elsewhere, ready
    for `mean_token_logprob`.

    Args:
        prompt: Unbatched prompt from `build_prompt`.
        completions: N lists of token ids, or an (N, T) tensor of generated tokens (as `generate` returns after
            slicing off the prompt); each row is cut after its first id in `eos_token_ids` and trailing
            `pad_token_id`s are dropped.
        pad_token_id: Id used for padding.
        eos_token_ids: End-of-turn ids (e.g. <|im_end|>, <|endoftext|>): kept, anything after is dropped.
        padding_side: Passed to `collate`.
    """
    rows = [trim_completion(c, pad_token_id=pad_token_id, eos_token_ids=eos_token_ids) for c in completions]
    if not rows:
        raise ValueError("append_completions got 0 completions")
    return collate([append_response(prompt, r) for r in rows], pad_token_id, padding_side)


def trim_completion(
    ids: Sequence[int] | torch.Tensor, *, pad_token_id: int | None = None, eos_token_ids: Sequence[int] = ()
) -> list[int]:
    """Ids up to and including the first end-of-turn id; without one, trailing pad ids are removed."""
    out = [int(i) for i in (ids.tolist() if isinstance(ids, torch.Tensor) else ids)]
    stop = set(eos_token_ids)
    for k, i in enumerate(out):
        if i in stop:
            return out[: k + 1]
    while out and out[-1] == pad_token_id:
        out.pop()
    return out
