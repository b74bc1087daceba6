"""Dense targets for the vision tower: which objects each merged visual token holds, read from the segmentation.

A vision tower trained from scratch (the tiny model) gets almost no useful gradient from the language loss on a
few hundred scenes: its output collapses to nearly the same vector for every video and the language model learns
to ignore the frames (see the README's status). The generator already knows what is where, so with
`stage.module.vision_aux_weight > 0` a linear head on the merged visual tokens (the vectors the language model
reads) is trained to say, for every token, how many objects have their centre in its 28×28-pixel block (0, 1, 2,
3 or more) and of which shapes: summed over a frame's tokens, the objects in view. `vision_warmup_steps` trains
on this loss alone first. A pretrained tower (Qwen's) needs none of this; the default weight is 0.

Token order is the model's: per image, row-major over the (h/28, w/28) merge blocks; for a video, per frame pair
(an odd count repeats the last frame, as the processor does), an object's centre taken in the first frame of
the pair that shows it.

    t = token_targets(masks, ["box", "sphere"], grid_thw, as_video=False)   # (tokens, 4) int64
    loss, stats = aux_loss(head(visual_tokens), t)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

SHAPES = ("box", "sphere", "cylinder")
MAX_INSTANCES = 3  # count classes 0, 1, 2, 3+ per token
NUM_OUTPUTS = MAX_INSTANCES + 1 + len(SHAPES)  # count logits, then one presence logit per shape


def _mask_array(mask, size: tuple[int, int]) -> np.ndarray:
    """(H, W) integer labels resized (nearest) to `size` = (height, width)."""
    img = mask if isinstance(mask, Image.Image) else Image.fromarray(np.asarray(mask).astype(np.uint8))
    if (img.height, img.width) != size:
        img = img.resize((size[1], size[0]), Image.NEAREST)
    return np.asarray(img).astype(np.int64)


def token_targets(
    masks: Sequence,
    shapes: Sequence[str],
    grid_thw: torch.Tensor,
    *,
    as_video: bool = False,
    patch_size: int = 14,
    merge_size: int = 2,
    temporal_patch_size: int = 2,
) -> torch.Tensor:
    """Per merged visual token: [objects centred in it (clipped to 3), and whether a box / sphere / cylinder is].

    An object's centre is the mean of its pixels; summing the first column over one frame's tokens counts the
    objects seen in that frame (what the language model must write), where the tokens an object merely touches
    would count large objects several times.

    Args:
        masks: The segmentation of each frame given to the model, as stored by `aynamics generate`:
            (H, W) labels (PIL mode L or integer arrays), 0 = floor and sky, k = object k - 1 of the scene.
        shapes: Object types in scene order (the record's `shapes`).
        grid_thw: The processor's grid of these frames: one (1, h, w) row per image, or one (t, h, w) row for
            the video (h, w in 14-pixel patches).
        as_video: Whether the frames were given as one video (frames paired along time).
    """
    unknown = sorted(set(shapes) - set(SHAPES))
    if unknown:
        raise ValueError(f"shapes {unknown}: must be among {SHAPES}")
    grid = torch.as_tensor(grid_thw).reshape(-1, 3).tolist()
    n_items = len(masks) if not as_video else -(-len(masks) // temporal_patch_size)
    rows = len(masks) if not as_video else 1
    if len(grid) != rows or (as_video and grid[0][0] != n_items) or (not as_video and any(g[0] != 1 for g in grid)):
        raise ValueError(f"grid_thw = {grid} does not match {len(masks)} masks given as_video = {as_video}")
    if as_video:
        step = temporal_patch_size
        groups = [list(range(k, min(k + step, len(masks)))) for k in range(0, len(masks), step)]
        sizes = [grid[0][1:]] * len(groups)
    else:
        groups, sizes = [[k] for k in range(len(masks))], [g[1:] for g in grid]
    shape_of = np.zeros((len(shapes), len(SHAPES)), np.int64)  # object -> shape one-hot
    for k, s in enumerate(shapes):
        shape_of[k, SHAPES.index(s)] = 1
    block = patch_size * merge_size
    out = []
    for frames, (gh, gw) in zip(groups, sizes):
        labels = [_mask_array(masks[f], (gh * patch_size, gw * patch_size)) for f in frames]
        for f, m in zip(frames, labels):
            if m.max(initial=0) > len(shapes):
                raise ValueError(f"mask {f} holds label {m.max()} but the scene has {len(shapes)} objects")
        centred = np.zeros((gh // merge_size, gw // merge_size, len(shapes)), bool)  # object k centred in block?
        for k in range(len(shapes)):
            for m in labels:  # the first frame of the pair that shows the object
                rows, cols = np.nonzero(m == k + 1)
                if len(rows):
                    centred[int(rows.mean()) // block, int(cols.mean()) // block, k] = True
                    break
        count = np.minimum(centred.sum(-1), MAX_INSTANCES)
        kinds = (centred.astype(np.int64) @ shape_of) > 0
        out.append(np.concatenate([count[..., None], kinds], -1).reshape(-1, 1 + len(SHAPES)))
    return torch.from_numpy(np.concatenate(out)).long()


def aux_loss(logits: torch.Tensor, targets: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Cross-entropy of the per-token object count plus binary cross-entropy of the shape presences.

    Args:
        logits: (N, NUM_OUTPUTS) head outputs for N visual tokens.
        targets: (N, 1 + len(SHAPES)) from `token_targets`.
    Returns:
        The loss and detached statistics: `count_acc` (per-token count accuracy) and `object_recall` (share of
        tokens holding an object's centre that are predicted to hold one).
    """
    if logits.shape[0] != targets.shape[0] or logits.shape[-1] != NUM_OUTPUTS:
        raise ValueError(
            f"logits {tuple(logits.shape)} and targets {tuple(targets.shape)}: need (N, {NUM_OUTPUTS}) and (N, 4)"
        )
    count_logits, shape_logits = logits[:, : MAX_INSTANCES + 1], logits[:, MAX_INSTANCES + 1 :]
    count = targets[:, 0]
    loss = F.cross_entropy(count_logits.float(), count) + F.binary_cross_entropy_with_logits(
        shape_logits.float(), targets[:, 1:].float()
    )
    with torch.no_grad():
        pred = count_logits.argmax(-1)
        has = count > 0
        stats = {
            "count_acc": (pred == count).float().mean(),
            "object_recall": (pred[has] > 0).float().mean() if has.any() else torch.tensor(float("nan")),
        }
    return loss, stats


def warm_up(
    visual: torch.nn.Module,
    head: torch.nn.Module,
    dataset: Sequence[dict[str, torch.Tensor]],
    *,
    steps: int,
    batch_size: int,
    lr: float,
    seed: int = 0,
    warmup_steps: int = 20,
) -> list[dict[str, float]]:
    """Train the vision tower and `head` on `aux_loss` alone, before the language model sees any visual token.

    Run on its own, the dense loss teaches a from-scratch tower to find the objects within a few hundred steps;
    run only jointly with the language loss, the language model has by then learned to ignore the frames.
    Batches are drawn with a generator of `seed` (the global RNG is untouched); AdamW with a linear warm-up of
    `warmup_steps`, then constant `lr`.

    Args:
        visual: The model's vision tower (returns the merged tokens as `pooler_output`).
        head: Linear map from a merged token to NUM_OUTPUTS logits.
        dataset: Examples holding pixel_values / image_grid_thw (or the video keys) and visual_targets.
    Returns:
        The mean loss / count_acc / object_recall of each block of 50 steps (and of the last partial block).
    """
    if steps < 0 or batch_size < 1 or lr <= 0:
        raise ValueError(f"steps = {steps}, batch_size = {batch_size}, lr = {lr}: need >= 0, >= 1, > 0")
    if steps and len(dataset) == 0:
        raise ValueError("vision warm-up got an empty training set")
    params = [p for p in [*visual.parameters(), *head.parameters()] if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr)
    gen = torch.Generator().manual_seed(seed)
    history, block = [], []
    for step in range(steps):
        idx = torch.randperm(len(dataset), generator=gen)[:batch_size].tolist()
        examples = [dataset[i] for i in idx]
        video = "pixel_values_videos" in examples[0]
        pix, grid = ("pixel_values_videos", "video_grid_thw") if video else ("pixel_values", "image_grid_thw")
        out = visual(torch.cat([ex[pix] for ex in examples]), grid_thw=torch.cat([ex[grid] for ex in examples]))
        tokens = getattr(out, "pooler_output", out)
        loss, stats = aux_loss(head(tokens), torch.cat([ex["visual_targets"] for ex in examples]))
        for g in opt.param_groups:
            g["lr"] = lr * min(1.0, (step + 1) / max(1, warmup_steps))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        block.append({"loss": loss.item(), **{k: v.item() for k, v in stats.items()}})
        if len(block) == 50 or step == steps - 1:
            history.append({"step": step + 1, **{k: float(np.nanmean([b[k] for b in block])) for k in block[0]}})
            block = []
    return history
