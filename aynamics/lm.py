"""Pure helpers of the language-model stages (SFT and PRO): prompts, targets, model building, loss, generation.

Nothing here is a Lightning object; `aynamics.sft` and `aynamics.pro` call these functions. Adapter folders and
training checkpoints (save, load, resume checks) are `aynamics.adapters`.

    model = build_model(ModelSpec(kind="tiny"))            # tiny random Qwen2.5-VL + LoRA on the language model
    loss, n = sft_loss(model(**model_inputs(batch)).logits, batch["labels"])
    texts = greedy_texts(model, processor, prompts, max_new_tokens=760)
"""

from __future__ import annotations

import dataclasses
import json
import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from aynamics import scene as scene_lib
from aynamics.logprobs import token_logprobs
from aynamics.processor import IGNORE_INDEX, build_prompt, local_path

TARGETS = ("answer", "think_answer")  # stage.target: the YAML alone, or motion reasoning then the YAML
MODALITIES = ("rgb", "flow")  # data.modality: the frames shown to the model
KINDS = ("tiny", "pretrained")

SYSTEM_PROMPT = (
    "You are a physics expert. You watch a short video of rigid objects (boxes, spheres, cylinders) moving on a "
    "floor and write the scene as YAML: every object with its shape, size, initial state and physical parameters, "
    "then the camera and gravity."
)
USER_PROMPTS = {
    "answer": "Write the scene as YAML inside <answer></answer> tags.",
    "think_answer": (
        "Think about the motion first inside <think></think> tags, then write the scene as YAML inside "
        "<answer></answer> tags."
    ),
}
MODALITY_NOTE = {
    "rgb": "The frames are video frames in time order.",
    "flow": "The frames are optical flow images (colour = direction, saturation = speed) in time order.",
}


CLIP_FRAMES = tuple(range(0, 30, 3))  # the frames of a generated record: every third of a 30-frame video

# What a trained adapter / stored data must agree on (the in-context examples are checked apart: long texts).
PROMPT_KEYS = ("target", "modality", "as_video", "num_frames", "min_pixels", "max_pixels")


@dataclass(frozen=True)
class PromptSpec:
    """What the model is shown and asked: the same at training, evaluation and `aynamics predict`.

    Attributes:
        target: "answer" (the YAML in <answer> tags) or "think_answer" (<think> reasoning first).
        modality: "rgb" (video frames) or "flow" (optical-flow images).
        as_video: Give the frames as one video (half the visual tokens) instead of separate images.
        num_frames: Frames sampled evenly from the clip (first and last kept), >= 1.
        min_pixels, max_pixels: Pixel bounds per frame after the processor's resize (None: the processor's).
        system_prompt: The system message.
        examples: In-context example texts placed before the frames (usually scenes in YAML).
        fps: Frame rate of the training videos (frames per second).
        clip_frames: The video frames (at `fps`) that a training record holds, from which `num_frames` are taken
            evenly: `aynamics predict` takes a video's frames at these times. The default is the generator's: every
            third of 30, `flow.sample_frames(30)`.
    """

    target: str = "answer"
    modality: str = "rgb"
    as_video: bool = False
    num_frames: int = 4
    min_pixels: int | None = None
    max_pixels: int | None = None
    system_prompt: str = SYSTEM_PROMPT
    examples: tuple[str, ...] = ()
    fps: float = 30.0
    clip_frames: tuple[int, ...] = CLIP_FRAMES

    def __post_init__(self) -> None:
        if self.target not in TARGETS:
            raise ValueError(f"target = {self.target!r}: must be one of {TARGETS}")
        if self.modality not in MODALITIES:
            raise ValueError(f"modality = {self.modality!r}: must be one of {MODALITIES}")
        if self.num_frames < 1:
            raise ValueError(f"num_frames = {self.num_frames}: must be >= 1")
        for key in ("min_pixels", "max_pixels"):
            value = getattr(self, key)
            if value is not None and value < 28 * 28:
                raise ValueError(f"{key} = {value}: must be >= {28 * 28} (one 2x2 block of 14-pixel patches) or null")
        # types too: a hand-edited aynamics.json's system_prompt 5 or examples [{...}] failed with a traceback
        # in the prompt builder, and clip_frames [0.5, 1] was cut to [0, 1] without a word
        if not isinstance(self.system_prompt, str):
            raise ValueError(f"system_prompt = {self.system_prompt!r}: must be a string")
        if isinstance(self.examples, str) or not isinstance(self.examples, Sequence):
            raise ValueError(f"examples = {self.examples!r}: must be a list of example texts")
        bad = next((e for e in self.examples if not isinstance(e, str)), None)
        if bad is not None:
            raise ValueError(f"examples: {bad!r}: each must be a text (a scene in YAML)")
        object.__setattr__(self, "examples", tuple(self.examples))
        try:
            if isinstance(self.clip_frames, str) or any(isinstance(k, bool) for k in self.clip_frames):
                raise TypeError
            object.__setattr__(self, "clip_frames", tuple(operator.index(k) for k in self.clip_frames))
        except TypeError:  # None, a number, or a frame that is not a whole number (0.5, "3")
            raise ValueError(
                f"clip_frames = {self.clip_frames!r}: must be increasing whole frame indices >= 0, at least one"
            ) from None
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps = {self.fps}: must be a finite number > 0")
        frames = self.clip_frames
        if not frames or frames[0] < 0 or any(b <= a for a, b in zip(frames, frames[1:])):
            raise ValueError(f"clip_frames = {list(frames)}: must be increasing frame indices >= 0, at least one")

    @property
    def frame_times(self) -> tuple[float, ...]:
        """Seconds from the first frame of each frame a training record holds."""
        return tuple((k - self.clip_frames[0]) / self.fps for k in self.clip_frames)

    @property
    def shown_fps(self) -> float:
        """Frames per second of the frames handed to the model (`num_frames` of `clip_frames`, evenly, ends kept),
        as a video's temporal positions read it: Qwen2.5-VL puts temporal patch g (frames 2g, 2g + 1) at
        g · 2 / fps s (`second_per_grid_ts`), so this is 2 / the mean time between the shown patches' first
        frames (1 / the frame spacing for evenly spaced frames; 4 of 5 stored frames are picked unevenly). One
        patch: 1 / the mean frame spacing; one frame: 2.0, Qwen's default."""
        from aynamics.processor import sample_frames

        shown = sample_frames(self.frame_times, self.num_frames)
        starts = shown[::2]
        if len(starts) > 1:
            return 2 * (len(starts) - 1) / (starts[-1] - starts[0])
        return (len(shown) - 1) / (shown[-1] - shown[0]) if len(shown) > 1 else 2.0

    @property
    def user_prompt(self) -> str:
        return f"{MODALITY_NOTE[self.modality]} {USER_PROMPTS[self.target]}"


def response_text(
    record: dict[str, Any], target: str, decimals: int | None = None, names: bool = True, objects_last: bool = False
) -> str:
    """The SFT target of one data-set record: its `target_answer` or `target_think` column.

    `decimals` (None: as stored, the canonical 4) rounds every number of the YAML in the target: a shorter
    target whose last digits are not noise the model has to fit (`data.decimals`). `names=False` leaves out
    the default object names (`box_0`, `box_1`, ...), which the parser fills back in (`data.object_names`).
    `objects_last=True` writes the camera and gravity before the objects (`scene.dump`; `data.objects_last`).
    """
    column = {"answer": "target_answer", "think_answer": "target_think"}.get(target)
    if column is None:
        raise ValueError(f"target = {target!r}: must be one of {TARGETS}")
    if column not in record:
        raise ValueError(f"data-set record lacks the column {column!r} (has {sorted(record)})")
    text = record[column]
    if _as_stored(decimals, names, objects_last):
        return text
    yaml_text = record["scene_yaml"]
    if yaml_text not in text:
        raise ValueError(f"record {record.get('index')!r}: its {column!r} does not hold its scene_yaml verbatim")
    return text.replace(yaml_text, scene_text(yaml_text, decimals, names, objects_last))


def _as_stored(decimals: int | None, names: bool, objects_last: bool) -> bool:
    return (decimals is None or decimals == scene_lib.DECIMALS) and names and not objects_last


def scene_text(yaml_text: str, decimals: int | None = None, names: bool = True, objects_last: bool = False) -> str:
    """A stored scene YAML as a target or in-context example writes it (see `response_text`); unchanged by default."""
    if _as_stored(decimals, names, objects_last):
        return yaml_text
    out = scene_lib.dump(
        scene_lib.parse(yaml_text), scene_lib.DECIMALS if decimals is None else decimals, names, objects_last
    )
    scene_lib.parse(out)  # rounding must keep the scene valid (SceneError names the field otherwise)
    return out


@dataclass(frozen=True)
class ModelSpec:
    """Which base model and which adapter; plain values, stored with every adapter so it can be rebuilt.

    Attributes:
        kind: "tiny" (random Qwen2.5-VL from a config, tokenizer asset in the repo) or "pretrained".
        path: Local directory or hub id of a pretrained checkpoint (kind "pretrained"); the processor comes
            from the same place. Unused for "tiny" (the repo's tokenizer asset).
        seed: Seed of the tiny model's random weights (the adapter's base must be rebuilt identically).
        tiny: Overrides of `aynamics.model.tiny_config` (hidden_size, num_layers, ...).
        lora_rank, lora_alpha, lora_dropout, lora_targets: LoRA on the language model's projections.
        train_vision: Train the vision tower's full weights too (saved with the adapter).
        modules_to_save: More modules trained in full and saved with the adapter (the tiny model, trained from
            scratch, needs its random "embed_tokens" and "lm_head" trainable to learn quickly).
        gradient_checkpointing: Non-reentrant activation checkpointing (less memory, more compute).
        dtype: "float32" or "bfloat16" (pretrained only; the tiny model stays float32).
        attn_implementation: Attention kernel: "sdpa", "eager", "flash_attention_2" (needs the `flash-attn`
            package and a GPU; pretrained only) or None for transformers' default (sdpa).
    """

    kind: str = "tiny"
    path: str | None = None
    seed: int = 0
    tiny: dict[str, int] = field(default_factory=dict)
    lora_rank: int = 16
    lora_alpha: float = 32.0
    lora_dropout: float = 0.05
    lora_targets: tuple[str, ...] = ("q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj")
    train_vision: bool = False
    modules_to_save: tuple[str, ...] = ()
    gradient_checkpointing: bool = False
    dtype: str = "float32"
    attn_implementation: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"model.kind = {self.kind!r}: must be one of {KINDS}")
        if self.kind == "pretrained" and not self.path:
            raise ValueError("model.kind = 'pretrained' needs model.path (a local directory or a hub id)")
        # before the base loads (apply_lora checks rank and dropout again); alpha 0 froze the LoRA update (its
        # gradients are scaled by alpha / r), a negative one flipped it, NaN diverged at the first step
        if isinstance(self.lora_rank, bool) or not isinstance(self.lora_rank, int) or self.lora_rank < 1:
            raise ValueError(f"model.lora_rank = {self.lora_rank!r}: must be a whole number >= 1")
        if not (isinstance(self.lora_alpha, int | float) and math.isfinite(self.lora_alpha) and self.lora_alpha > 0):
            raise ValueError(f"model.lora_alpha = {self.lora_alpha!r}: must be a finite number > 0")
        if self.kind == "tiny":  # before the data and the model load: 0 heads divided by zero inside tiny_config
            from aynamics.model import check_tiny_sizes

            if not isinstance(self.tiny, dict):
                raise ValueError(f"model.tiny = {self.tiny!r}: must be a mapping of sizes (e.g. hidden_size: 64)")
            check_tiny_sizes(self.tiny, "model.tiny.")
        # before the base loads (minutes for the 3B): apply_lora refused these only once the weights were there
        if not (isinstance(self.lora_dropout, int | float) and 0 <= self.lora_dropout < 1):
            raise ValueError(f"model.lora_dropout = {self.lora_dropout!r}: must be a number in [0, 1)")
        targets = self.lora_targets
        if isinstance(targets, str) or not targets or not all(isinstance(t, str) and t for t in targets):
            raise ValueError(
                f"model.lora_targets = {targets!r}: must be a list of projection names, e.g. [q_proj, v_proj]"
            )
        if self.dtype not in ("float32", "bfloat16"):
            raise ValueError(f"model.dtype = {self.dtype!r}: must be 'float32' or 'bfloat16'")
        kernels = ("sdpa", "eager", "flash_attention_2") if self.kind == "pretrained" else ("sdpa", "eager")
        if self.attn_implementation is not None and self.attn_implementation not in kernels:
            raise ValueError(
                f"model attn_implementation = {self.attn_implementation!r}: must be one of {kernels} or null "
                f"(transformers' default) for kind = {self.kind!r}"
            )
        if self.path is not None:
            object.__setattr__(self, "path", local_path(self.path))
        object.__setattr__(self, "lora_targets", tuple(self.lora_targets))
        object.__setattr__(self, "modules_to_save", tuple(self.modules_to_save))
        object.__setattr__(self, "tiny", dict(self.tiny))

    @property
    def processor_path(self) -> str:
        from aynamics.tokenizer_build import TINY_ASSET_DIR

        return str(TINY_ASSET_DIR) if self.kind == "tiny" else str(self.path)


def build_base(spec: ModelSpec) -> torch.nn.Module:
    """The base model of `spec` without adapters (tiny: random from `spec.seed`; pretrained: `from_pretrained`)."""
    from aynamics import model as modellib

    if spec.kind == "tiny":
        return modellib.build_tiny_model(
            seed=spec.seed, attn_implementation=spec.attn_implementation or "sdpa", **spec.tiny
        )
    dtype = torch.bfloat16 if spec.dtype == "bfloat16" else torch.float32
    return modellib.load_pretrained(spec.path, dtype=dtype, attn_implementation=spec.attn_implementation)


def build_model(spec: ModelSpec) -> torch.nn.Module:
    """Base model + LoRA on the language model (a `peft.PeftModel`), in train mode; only the adapter trains."""
    from aynamics import model as modellib

    base = build_base(spec)
    model = modellib.apply_lora(
        base,
        rank=spec.lora_rank,
        alpha=spec.lora_alpha,
        dropout=spec.lora_dropout,
        target_modules=spec.lora_targets,
        train_vision=spec.train_vision,
        gradient_checkpointing=spec.gradient_checkpointing,
        modules_to_save=spec.modules_to_save,
    )
    modellib.float32_trained_tower(model)
    return model.train()


def load_processor(spec: ModelSpec, prompt: PromptSpec):
    """The image-only processor of the model, with the prompt's frame count, frame rate and pixel bounds."""
    return prompt_processor(spec.processor_path, prompt)


def prompt_processor(path: str | Path, prompt: PromptSpec):
    """The image-only processor at `path` (a tokenizer + preprocessor folder or hub id) set up for `prompt`: its
    frame count, its shown frames' rate (a video's temporal positions) and its pixel bounds. The one place the
    prompt's settings reach a processor (SFT, PRO, evaluate and predict alike)."""
    from aynamics.processor import load_processor as _load

    p = prompt
    return _load(
        path,
        min_pixels=p.min_pixels,
        max_pixels=p.max_pixels,
        num_frames=p.num_frames,
        video_fps=p.shown_fps,
    )


def sft_loss(
    logits: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Token-mean negative log-likelihood of the labelled tokens (the usual next-token shift).

    Args:
        logits: (B, L, V) model outputs.
        labels: (B, L), -100 where no loss (prompt, images, padding).
        weights: Optional (B, L) per-token weights aligned with `labels` (`data.type_weight` on the
            `processor.type_tokens`): the loss is then the weighted mean, sum(w · nll) / sum(w), over the
            labelled tokens.

    Returns:
        (loss, n_tokens): the mean over all labelled tokens of the batch, and their count (a 0-d long tensor).
        With no labelled token the loss is 0 (still attached to the graph).
    """
    logp, mask = token_logprobs(logits, labels)  # (B, L-1) each
    n = mask.sum()
    if weights is None:
        return -(logp.sum() / n.clamp(min=1)), n
    if weights.shape != labels.shape:
        raise ValueError(f"loss weights {tuple(weights.shape)} do not match labels {tuple(labels.shape)}")
    w = weights[:, 1:].to(logp.dtype) * mask
    return -((w * logp).sum() / w.sum().clamp(min=1e-12)), n


def token_accuracy(logits: torch.Tensor, labels: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Teacher-forced accuracy of the greedy next token on the labelled tokens where `mask` is True (with the
    usual shift: labels[:, t] is predicted by logits[:, t - 1]); NaN when there are none.

    On the type tokens (`processor.type_tokens`) with the true frames, and again with another example's frames
    (`shifted_visuals`), it says whether the model reads what is in the video: the two are equal when it
    does not.
    """
    if logits.shape[:2] != labels.shape or mask.shape != labels.shape:
        raise ValueError(
            f"logits {tuple(logits.shape)}, labels {tuple(labels.shape)}, mask {tuple(mask.shape)} disagree on (B, L)"
        )
    keep = _scored(labels, mask)
    if not keep.any():
        return torch.tensor(float("nan"))
    return (logits[:, :-1][keep].argmax(-1) == labels[:, 1:][keep]).float().mean()


def _scored(labels: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, L-1): the shifted positions `token_accuracy` scores: labelled and in `mask`."""
    return mask[:, 1:] & (labels[:, 1:] != IGNORE_INDEX)


def token_count(labels: torch.Tensor, mask: torch.Tensor) -> int:
    """How many tokens `token_accuracy(logits, labels, mask)` scores (its weight in a mean over batches)."""
    return int(_scored(labels, mask).sum())


def shifted_visuals(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor] | None:
    """The batch with every example's frames replaced by the next example's (the last takes the first's).

    The loss on this batch minus the loss on the true one is the model's *image reliance* (`val/image_gap`):
    about 0 means it writes the same answer whatever it sees. None where the batch cannot be shifted (one
    example, or examples whose frames have different patch counts).
    """
    n = batch["input_ids"].shape[0]
    for values, grid in (("pixel_values", "image_grid_thw"), ("pixel_values_videos", "video_grid_thw")):
        if values not in batch:
            continue
        sizes = batch[grid].prod(-1)
        if n < 2 or len(sizes) % n or len(set(sizes.tolist())) != 1:
            return None
        per_example = int(sizes.sum()) // n
        return {**batch, values: torch.roll(batch[values], per_example, 0)}
    return None


def prompt_inputs(processor, prompt: PromptSpec, frames: Sequence[Any]) -> dict[str, torch.Tensor]:
    """The generation input for `frames` as training built it: the frames sampled evenly to the trained count,
    the system and user prompt, the in-context examples, images or one video (the same at evaluation, PRO
    sampling and `aynamics predict`)."""
    return build_prompt(
        processor,
        list(frames),
        system_prompt=prompt.system_prompt,
        user_prompt=prompt.user_prompt,
        examples=prompt.examples,
        as_video=prompt.as_video,
    )


def prompt_mismatch(stored: dict[str, Any], prompt: PromptSpec) -> tuple[str, str] | None:
    """Where `stored` (PROMPT_KEYS values something was made under) differs from `prompt`: ("k=old, ...",
    "data.k=new, ..."; the run's side with its config keys, `stage.target` and `data.*`) to name both in an error,
    or None when they agree. Keys `stored` lacks are not compared."""
    diff = [k for k in PROMPT_KEYS if k in stored and stored[k] != getattr(prompt, k)]
    if not diff:
        return None
    config = {k: "stage.target" if k == "target" else f"data.{k}" for k in diff}
    return ", ".join(f"{k}={stored[k]!r}" for k in diff), ", ".join(f"{config[k]}={getattr(prompt, k)!r}" for k in diff)


def tokenizer_fingerprint(tokenizer) -> str:
    """A short hash of the vocabulary (token -> id): stored token ids are only meaningful under the same one."""
    import hashlib

    vocab = sorted(tokenizer.get_vocab().items())
    return hashlib.sha256(json.dumps(vocab, ensure_ascii=False).encode()).hexdigest()[:16]


def runnable_kernel(spec: ModelSpec, device: torch.device) -> ModelSpec:
    """`spec` with an attention kernel `device` can run, for loading a trained adapter: flash_attention_2 (which
    does not change the weights) becomes sdpa on the CPU or without the `flash_attn` package."""
    import importlib.util

    if spec.attn_implementation != "flash_attention_2":
        return spec
    if device.type == "cuda" and importlib.util.find_spec("flash_attn") is not None:
        return spec
    return dataclasses.replace(spec, attn_implementation="sdpa")


def inference_device(name: str | None = None) -> torch.device:
    """The device to run a model on for inference: `name` ("cpu", "cuda", "cuda:1", ...), or None / "auto" for
    the first GPU when there is one, else the CPU.

    Raises:
        ValueError: not a device name, or a GPU that this machine does not have (named).
    """
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"device = {name!r}: not a torch device name (cpu, cuda, cuda:1, auto): {e}") from None
    if device.type == "cuda" and (not torch.cuda.is_available() or (device.index or 0) >= torch.cuda.device_count()):
        raise ValueError(f"device = {name!r}: this machine has {torch.cuda.device_count()} CUDA devices")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"device = {name!r}: only cpu and cuda are supported")
    return device


def greedy_texts(model: torch.nn.Module, processor, prompts: Sequence[dict], max_new_tokens: int) -> list[str]:
    """Greedy responses (special tokens dropped) to unbatched prompts from `processor.build_prompt`."""
    from aynamics.reward import sample_completions

    _, texts = sample_completions(
        model, processor, prompts, num_samples=1, temperature=0.0, max_new_tokens=max_new_tokens
    )
    return [t[0] for t in texts]
