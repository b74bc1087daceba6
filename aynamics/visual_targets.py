"""Dense targets for the vision tower: which objects each merged visual token holds, read from the segmentation.

A vision tower trained from scratch (the tiny model) gets almost no useful gradient from the language loss on a
few hundred scenes: its output collapses to nearly the same vector for every video and the language model learns
to ignore the frames (see the README's status). The generator already knows what is where, so with
`stage.module.vision_aux_weight > 0` a linear head on the merged visual tokens (the vectors the language model
reads) is trained to say, for every token, how many objects have their centre in its 28×28-pixel block (0, 1, 2,
3 or more), of which shapes, and what share of each object's pixels it holds (a density map: summed over a
frame's tokens it is the number of objects in view, with no block-boundary ambiguity — the usual way to count
with dense maps). `vision_warmup_steps` trains on this loss alone first, optionally on mirrored and recoloured
frames (`Augment`): ~1 200 scenes are few for a tower learnt from zero. A pretrained tower (Qwen's) needs none of this;
the default weight is 0.

Token order is the model's: per image, row-major over the (h/28, w/28) merge blocks; for a video, per frame pair
(an odd count repeats the last frame, as the processor does), an object's centre taken in the first frame of
the pair that shows it.

    t = token_targets(masks, ["box", "sphere"], grid_thw, as_video=False)   # (tokens, 5) float32
    loss, stats = aux_loss(head(visual_tokens), t, frame_tokens=[48, 48])
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

SHAPES = ("box", "sphere", "cylinder")
MAX_INSTANCES = 3  # count classes 0, 1, 2, 3+ per token
NUM_TARGETS = 2 + len(SHAPES)  # centred count, one presence per shape, pixel share
NUM_OUTPUTS = MAX_INSTANCES + 1 + len(SHAPES) + 1  # count logits, one presence logit per shape, pixel share
SHARE_WEIGHT = 10.0  # the share's squared error is small (most tokens hold 0): weighted to matter next to the rest


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
    """Per merged visual token: [objects centred in it (clipped to 3), whether a box / sphere / cylinder is,
    the summed share of each object's pixels that it holds].

    An object's centre is the mean of its pixels. Summed over one frame's tokens, the first column (up to the
    clip) and the last one both count the objects seen in that frame — what the language model must write;
    the share (a density map) spreads each object over every token it covers, so a centre near a block edge is
    not an all-or-nothing call.

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
        share = np.zeros((gh // merge_size, gw // merge_size))
        for k in range(len(shapes)):
            for m in labels:  # the first frame of the pair that shows the object
                rows, cols = np.nonzero(m == k + 1)
                if len(rows):
                    centred[int(rows.mean()) // block, int(cols.mean()) // block, k] = True
                    np.add.at(share, (rows // block, cols // block), 1.0 / len(rows))
                    break
        count = np.minimum(centred.sum(-1), MAX_INSTANCES)
        kinds = (centred.astype(np.int64) @ shape_of) > 0
        out.append(np.concatenate([count[..., None], kinds, share[..., None]], -1).reshape(-1, NUM_TARGETS))
    return torch.from_numpy(np.concatenate(out)).float()


class Head(torch.nn.Linear):
    """The dense head: one linear map from each visual token to `NUM_OUTPUTS` logits, in the head's own dtype
    (float32 beside a bfloat16 tower: the tokens are cast on the way in, in training steps and the warm-up,
    with or without autocast)."""

    def __init__(self, width: int) -> None:
        super().__init__(width, NUM_OUTPUTS)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return super().forward(tokens.to(self.weight.dtype))


def aux_loss(
    logits: torch.Tensor,
    targets: torch.Tensor,
    frame_tokens: Sequence[int] | None = None,
    share_weight: float = SHARE_WEIGHT,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Cross-entropy of the per-token object count, binary cross-entropy of the shape presences, and
    `share_weight` × the squared error of the pixel share (0: the share is left out).

    Args:
        logits: (N, NUM_OUTPUTS) head outputs for N visual tokens.
        targets: (N, NUM_TARGETS) from `token_targets`.
        frame_tokens: Tokens per frame (per frame pair for a video), in order, summing to N (`frame_tokens`);
            with it, `frame_count_acc` is reported.
        share_weight: Weight of the share's squared error (default SHARE_WEIGHT).
    Returns:
        The loss and detached statistics: `count_acc` (per-token count accuracy), `object_recall` (share of
        tokens holding an object's centre that are predicted to hold one) and `frame_count_acc` (share of frames
        whose rounded sum of predicted shares — of predicted centre counts when `share_weight` is 0 — is the
        number of objects in view: the count the tokens imply).
    """
    if logits.shape[0] != targets.shape[0] or logits.shape[-1] != NUM_OUTPUTS or targets.shape[-1] != NUM_TARGETS:
        raise ValueError(
            f"logits {tuple(logits.shape)} and targets {tuple(targets.shape)}: need (N, {NUM_OUTPUTS}) and "
            f"(N, {NUM_TARGETS})"
        )
    if frame_tokens is not None and sum(frame_tokens) != logits.shape[0]:
        raise ValueError(f"frame_tokens sum to {sum(frame_tokens)}, but there are {logits.shape[0]} tokens")
    logits, targets = logits.float(), targets.float()
    k = MAX_INSTANCES + 1
    count_logits, shape_logits, share = logits[:, :k], logits[:, k:-1], logits[:, -1]
    count = targets[:, 0].long()
    loss = (
        F.cross_entropy(count_logits, count)
        + F.binary_cross_entropy_with_logits(shape_logits, targets[:, 1:-1])
        + share_weight * F.mse_loss(share, targets[:, -1])
    )
    with torch.no_grad():
        pred = count_logits.argmax(-1)
        has = count > 0
        stats = {
            "count_acc": (pred == count).float().mean(),
            "object_recall": (pred[has] > 0).float().mean() if has.any() else count_logits.new_full((), float("nan")),
        }
        if frame_tokens is not None:  # the count the tokens imply: summed shares, or centres when shares are off
            sizes = list(frame_tokens)
            implied = share if share_weight > 0 else pred.float()
            got = torch.stack([p.sum() for p in implied.split(sizes)]).round()
            want = torch.stack([t.sum() for t in targets[:, -1].split(sizes)]).round()
            stats["frame_count_acc"] = (got == want).float().mean()
    return loss, stats


def frame_tokens(grid_thw: torch.Tensor, merge_size: int = 2) -> list[int]:
    """Merged tokens of each frame (each frame pair of a video), in the model's order, from the processor's grid."""
    return [h * w // merge_size**2 for t, h, w in torch.as_tensor(grid_thw).reshape(-1, 3).tolist() for _ in range(t)]


@dataclasses.dataclass(frozen=True)
class Augment:
    """Random mirror and colour-channel permutation applied to processed frames and their targets alike.

    Works on the processor's output (rows of patches, (channels, time, patch, patch) each; rows ordered by
    frame, merge block row, merge block column, then the 2×2 patches in a block), so the cached examples are
    reused: mirroring reverses the block columns, the patches in a block and the pixels in a patch;
    recolouring undoes the normalisation, permutes the channels and normalises again. Both equal processing
    the mirrored / recoloured frames (tested), and neither changes what the targets count.
    """

    image_mean: tuple[float, ...]
    image_std: tuple[float, ...]
    patch_size: int = 14
    merge_size: int = 2
    temporal_patch_size: int = 2

    @classmethod
    def of(cls, image_processor) -> Augment:
        ip = image_processor
        return cls(tuple(ip.image_mean), tuple(ip.image_std), ip.patch_size, ip.merge_size, ip.temporal_patch_size)

    def __call__(
        self,
        pixels: torch.Tensor,
        grid_thw: torch.Tensor,
        targets: torch.Tensor,
        *,
        mirror: bool,
        channels: Sequence[int],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        m, p, c = self.merge_size, self.patch_size, len(self.image_mean)
        rows = torch.as_tensor(grid_thw).reshape(-1, 3).tolist()
        patches = sum(t * h * w for t, h, w in rows)
        if patches != pixels.shape[0] or patches // m**2 != targets.shape[0]:
            raise ValueError(
                f"grid_thw {rows} covers {patches} patches / {patches // m**2} tokens, got {pixels.shape[0]} / "
                f"{targets.shape[0]}"
            )
        mean = torch.tensor(self.image_mean, dtype=pixels.dtype).view(c, 1, 1, 1)
        std = torch.tensor(self.image_std, dtype=pixels.dtype).view(c, 1, 1, 1)
        order = torch.as_tensor(list(channels))
        out_p, out_t, row, trow = [], [], 0, 0
        for t, h, w in rows:
            n, nt = t * h * w, t * h * w // m**2
            x = pixels[row : row + n].reshape(t, h // m, w // m, m, m, c, self.temporal_patch_size, p, p)
            y = targets[trow : trow + nt].reshape(t, h // m, w // m, -1)
            x = (x * std + mean)[..., order, :, :, :]
            x = (x - mean) / std
            if mirror:
                x, y = x.flip(2, 4, 8), y.flip(2)
            out_p.append(x.reshape(n, -1))
            out_t.append(y.reshape(nt, -1))
            row, trow = row + n, trow + nt
        return torch.cat(out_p), torch.cat(out_t)


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
    augment: Augment | None = None,
    share_weight: float = SHARE_WEIGHT,
) -> list[dict[str, float]]:
    """Train the vision tower and `head` on `aux_loss` alone, before the language model sees any visual token.

    Run on its own, the dense loss teaches a from-scratch tower to find the objects within a few hundred steps;
    run only jointly with the language loss, the language model has by then learned to ignore the frames.
    Batches are drawn with a generator of `seed` (the global RNG is untouched); AdamW with a linear warm-up of
    `warmup_steps`, then constant `lr`. With `augment`, each example is mirrored with probability 1/2 and its
    colour channels permuted at random (the same generator). Measured (1 232 plain-backdrop scenes, the
    `make train` model, 4 000 steps, batch 8): the frame-pair count the shares imply was right for 0.46 of the
    171 held-out scenes without and 0.50 with augmentation (train split 0.71 and 0.66: less memorised); with
    augmentation, 1 000 / 3 000 / 8 000 steps gave 0.35 / 0.39 / 0.58 (~17 ms per step on 2 cores).

    Args:
        visual: The model's vision tower (returns the merged tokens as `pooler_output`).
        head: The dense `Head` (a merged token to NUM_OUTPUTS logits, in its own dtype).
        dataset: Examples holding pixel_values / image_grid_thw (or the video keys) and visual_targets.
    Returns:
        The mean loss / count_acc / object_recall / frame_count_acc of each block of 50 steps (and of the last
        partial block).
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
        pixels, targets = [ex[pix] for ex in examples], [ex["visual_targets"] for ex in examples]
        if augment is not None:
            for i, ex in enumerate(examples):
                mirror = bool(torch.rand(1, generator=gen).item() < 0.5)
                channels = torch.randperm(len(augment.image_mean), generator=gen).tolist()
                pixels[i], targets[i] = augment(pixels[i], ex[grid], targets[i], mirror=mirror, channels=channels)
        grid_thw = torch.cat([ex[grid] for ex in examples])
        device = next(head.parameters()).device  # the examples live on the CPU; the model may be on a GPU
        out = visual(torch.cat(pixels).to(device), grid_thw=grid_thw.to(device))
        tokens = getattr(out, "pooler_output", out)
        merge = getattr(visual, "spatial_merge_size", 2)
        targets = torch.cat(targets).to(device)
        loss, stats = aux_loss(head(tokens), targets, frame_tokens(grid_thw, merge), share_weight)
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
