"""Pure helpers of the language-model stages (SFT now, PRO later): prompts, targets, model building, loss, adapters.

Nothing here is a Lightning object; `aynamics.sft` (and the preference stage) call these functions.

    model = build_model(ModelSpec(kind="tiny"))            # tiny random Qwen2.5-VL + LoRA on the language model
    loss, n = sft_loss(model(**model_inputs(batch)).logits, batch["labels"])
    save_adapter(model, "out/adapter", spec, prompt_spec)  # peft folder + aynamics.json (what `predict` rebuilds)
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from aynamics import rng
from aynamics import scene as scene_lib
from aynamics.processor import IGNORE_INDEX, build_prompt, local_path, token_logprobs

TARGETS = ("answer", "think_answer")  # stage.target: the YAML alone, or motion reasoning then the YAML
MODALITIES = ("rgb", "flow")  # data.modality: the frames shown to the model
KINDS = ("tiny", "pretrained")
ADAPTER_META = "aynamics.json"  # written next to the peft adapter: how to rebuild the base model and the prompt

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
            raise ValueError(f"model kind = {self.kind!r}: must be one of {KINDS}")
        if self.kind == "pretrained" and not self.path:
            raise ValueError("model kind = 'pretrained' needs model.path (a local directory or a hub id)")
        # before the base loads (apply_lora checks rank and dropout again); alpha 0 froze the LoRA update (its
        # gradients are scaled by alpha / r), a negative one flipped it, NaN diverged at the first step
        if isinstance(self.lora_rank, bool) or not isinstance(self.lora_rank, int) or self.lora_rank < 1:
            raise ValueError(f"model.lora_rank = {self.lora_rank!r}: must be a whole number >= 1")
        if not (isinstance(self.lora_alpha, int | float) and math.isfinite(self.lora_alpha) and self.lora_alpha > 0):
            raise ValueError(f"model.lora_alpha = {self.lora_alpha!r}: must be a finite number > 0")
        if self.dtype not in ("float32", "bfloat16"):
            raise ValueError(f"model dtype = {self.dtype!r}: must be 'float32' or 'bfloat16'")
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


def save_adapter(
    model: torch.nn.Module,
    out: str | Path,
    spec: ModelSpec,
    prompt: PromptSpec,
    state_dict: dict[str, torch.Tensor] | None = None,
) -> Path:
    """Write the peft adapter (`PeftModel.from_pretrained(base, out)` loads it) and `aynamics.json` beside it.

    `state_dict`: the weights to write instead of the model's own (sharded models: `sharding.trainable_state`).
    """
    import contextlib
    import errno
    import os
    import shutil

    from aynamics.dataset_store import exclusive

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # written whole beside it, then swapped in: replaced file by file, a kill left one checkpoint's weights with
    # another's aynamics.json (prompt) or adapter_config.json, and such a folder loads without a word
    tmp, old = (out.parent / f".{out.name}.{what}-{os.getpid()}" for what in ("tmp", "old"))
    with contextlib.ExitStack() as held:
        try:
            held.enter_context(exclusive(out.parent / f".{out.name}.lock"))  # writers of `out` in turn
        except OSError as e:
            # a file system without locks (Lustre mounted noflock: ENOSYS; NFS without its lock daemon: ENOLCK)
            # failed training at its first checkpoint: written unlocked, as before the lock, whose leftovers of
            # other processes may be a live writer's, so only this process's own are removed
            if e.errno not in (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP):
                raise
            for folder in (tmp, old):
                shutil.rmtree(folder, ignore_errors=True)
        else:
            _recover_adapter_leftovers(out)  # under the lock: the leftovers are no one's
        model.save_pretrained(str(tmp), **({"state_dict": state_dict} if state_dict is not None else {}))
        (tmp / ADAPTER_META).write_text(json.dumps(adapter_meta(spec, prompt), indent=2))
        if out.is_dir():
            for p in out.iterdir():  # files of the user's in the folder stay in it
                if not (tmp / p.name).exists():
                    os.replace(p, tmp / p.name)
            os.replace(out, old)
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    return out


def _recover_adapter_leftovers(out: Path) -> None:
    """Finish or undo what killed `save_adapter`s of `out` left beside it (`.OUT.tmp-PID`, `.OUT.old-PID`), then
    delete those folders (call it holding `out`'s lock). A kill (SIGKILL, the OOM killer) of another process left
    them for good, as each write removed only its own process's; and some hold the only copy of something:

    - no `out`, a `.old-PID` and its `.tmp-PID` (killed between the two renames): the new adapter and the user's
      files are whole in `.tmp-PID`, renamed to `out` as the write meant to; a single `.old-PID` without its
      `.tmp-PID` is the only copy of `out` and is put back; several such: all stay (which was `out` is unknown).
    - `out` and a `.tmp-PID` holding `aynamics.json` (killed while moving the user's files into it): the entries
      whose names `out` lacks (those files) go back into `out`.
    - the rest is a half-written adapter or one replaced: deleted. Only folders of those two names are touched.
    """
    import os
    import re
    import shutil

    name = re.compile(rf"\.{re.escape(out.name)}\.(tmp|old)-(\d+)")
    found: dict[tuple[str, str], Path] = {}
    for p in out.parent.iterdir():
        m = name.fullmatch(p.name)
        if m and p.is_dir() and not p.is_symlink():
            found[m[1], m[2]] = p
    olds = [pid for kind, pid in found if kind == "old"]
    if not os.path.lexists(out):
        pid = next((pid for pid in olds if ("tmp", pid) in found), None)
        if pid is not None:
            os.replace(found.pop(("tmp", pid)), out)
        elif len(olds) == 1:
            os.replace(found.pop(("old", olds[0])), out)
        elif olds:  # several moved aside, none with its new adapter: which one was `out` is unknown, all stay
            found = {}
    for (kind, _), folder in sorted(found.items()):
        if kind == "tmp" and out.is_dir() and (folder / ADAPTER_META).is_file():
            for p in folder.iterdir():
                if not os.path.lexists(out / p.name):
                    os.replace(p, out / p.name)
        shutil.rmtree(folder, ignore_errors=True)


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
    "k=new, ...") to name both in an error, or None when they agree. Keys `stored` lacks are not compared."""
    diff = [k for k in PROMPT_KEYS if k in stored and stored[k] != getattr(prompt, k)]
    if not diff:
        return None
    return ", ".join(f"{k}={stored[k]!r}" for k in diff), ", ".join(f"{k}={getattr(prompt, k)!r}" for k in diff)


def tokenizer_fingerprint(tokenizer) -> str:
    """A short hash of the vocabulary (token -> id): stored token ids are only meaningful under the same one."""
    import hashlib

    vocab = sorted(tokenizer.get_vocab().items())
    return hashlib.sha256(json.dumps(vocab, ensure_ascii=False).encode()).hexdigest()[:16]


def adapter_meta(spec: ModelSpec, prompt: PromptSpec) -> dict:
    """What `aynamics.json` holds (and a training checkpoint, under "aynamics_meta"): the two specs, plain JSON."""
    return {"model": dataclasses.asdict(spec), "prompt": dataclasses.asdict(prompt)}


def specs_of_meta(meta: dict, where: str = "adapter meta") -> tuple[ModelSpec, PromptSpec]:
    """The specs of an `adapter_meta` dict (lists back to tuples).

    Raises:
        ValueError: `meta` is not what `adapter_meta` writes (a missing key, an unknown field, a bad value),
            named with `where` (the file it came from).
    """
    try:
        if not isinstance(meta, dict) or not all(isinstance(meta.get(k), dict) for k in ("model", "prompt")):
            got = sorted(meta) if isinstance(meta, dict) else type(meta).__name__
            raise ValueError(f"must be an object with 'model' and 'prompt' objects, got {got}")
        # examples as written: PromptSpec makes the list a tuple (a string would have become its characters)
        return ModelSpec(**meta["model"]), PromptSpec(**meta["prompt"])
    except (TypeError, ValueError) as e:  # TypeError: an unknown or missing field of a spec
        raise ValueError(f"{where}: not the model and prompt specs training writes: {e}") from None


def _read_json(path: Path, what: str) -> Any:
    """The JSON of a file of an adapter folder; a file that is not UTF-8 JSON raises ValueError naming it."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{str(path)!r} ({what}) is not valid JSON: {e}") from None
    except OSError as e:
        raise ValueError(f"{str(path)!r} ({what}) cannot be read: {e.strerror or e}") from None


def read_adapter_meta(adapter_dir: str | Path) -> tuple[ModelSpec, PromptSpec]:
    """The model and prompt specs stored by `save_adapter`.

    Raises:
        FileNotFoundError: the folder has no `aynamics.json`.
        ValueError: `aynamics.json` is not JSON or not the specs training writes (the file is named).
    """
    path = Path(adapter_dir) / ADAPTER_META
    if not path.is_file():
        raise FileNotFoundError(
            f"{str(path)!r} not found: --adapter must be a folder written by training (adapter/ under the run)"
        )
    return specs_of_meta(_read_json(path, "the adapter's model and prompt specs"), where=repr(str(path)))


def check_adapter_files(adapter_dir: str | Path) -> None:
    """Check the peft files of an adapter folder before a base model is built for them: `adapter_config.json`
    is a JSON object naming its `peft_type`, and the weights file is there with a readable header.

    Raises:
        ValueError: a file is missing, not JSON or truncated (the file and the problem are named).
    """
    folder = Path(adapter_dir)
    config_path = folder / "adapter_config.json"
    if not config_path.is_file():
        raise ValueError(f"{str(config_path)!r} not found: --adapter must be a folder written by training")
    config = _read_json(config_path, "peft's adapter config")
    if not isinstance(config, dict) or "peft_type" not in config:
        raise ValueError(f"{str(config_path)!r} is not a peft adapter config: it has no 'peft_type'")
    weights = folder / "adapter_model.safetensors"
    if not weights.is_file():
        if (folder / "adapter_model.bin").is_file():
            return
        raise ValueError(f"{str(folder)!r} holds no adapter weights (adapter_model.safetensors)")
    from safetensors import safe_open

    try:
        with safe_open(str(weights), framework="pt") as f:
            f.keys()
    except Exception as e:  # safetensors raises its own SafetensorError (and OSError) for a truncated file
        raise ValueError(f"{str(weights)!r} is not a readable safetensors file (truncated?): {e}") from None


def keep_trainable_weights(checkpoint: dict, module: torch.nn.Module) -> None:
    """Keep only `module`'s trainable weights (the adapter, `modules_to_save`, a trained tower) in a Lightning
    checkpoint dict; the frozen base is rebuilt from the spec. DeepSpeed's dict has no `state_dict` (it saves the
    weights itself, `exclude_frozen_parameters` in its config)."""
    if "state_dict" in checkpoint:
        trainable = {k for k, p in module.named_parameters() if p.requires_grad}
        checkpoint["state_dict"] = {k: v for k, v in checkpoint["state_dict"].items() if k in trainable}


class ExactResume:
    """Checkpoint hooks SFT and PRO share (a mixin before `LightningModule`): a checkpoint keeps only the trainable
    weights and every process's random states; loading one checks it (`check_checkpoint`, which the module
    extends), keeps `resumed_step` (the global step it was written at; None for a fresh run) and restores the
    random states at the first training batch (Lightning draws random numbers between loading and that batch)."""

    resumed_step: int | None = None
    _rng_to_restore: dict | None = None

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        keep_trainable_weights(checkpoint, self)
        checkpoint["rng"] = rng.gathered_states()  # every process's (each draws its own dropout masks, samples)

    def check_checkpoint(self, checkpoint: dict) -> None:
        """Refuse a checkpoint written for another model (before anything loads under fsdp)."""
        check_trainable_weights(checkpoint, self)
        check_same_base(checkpoint.get("hyper_parameters", {}).get("spec"), self.spec)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.check_checkpoint(checkpoint)  # again under fsdp, whose strategy checks before loading: cheap
        self._rng_to_restore = checkpoint.get("rng")
        self.resumed_step = checkpoint.get("global_step")

    def on_train_batch_start(self, batch, batch_idx: int) -> None:
        if self._rng_to_restore is not None:
            rng.restore(self._rng_to_restore, self.global_rank)
            self._rng_to_restore = None


def check_trainable_weights(checkpoint: dict, module: torch.nn.Module) -> None:
    """Refuse a checkpoint that lacks some of `module`'s trainable weights: written for another model or LoRA
    setting (modules load with `strict_loading = False`, since checkpoints hold only the trainable weights, so the
    missing ones would silently keep their fresh values). DeepSpeed's dict has no `state_dict`: not checked."""
    stored = checkpoint.get("state_dict")
    missing = {k for k, p in module.named_parameters() if p.requires_grad} - set(stored or ())
    if stored is not None and missing:
        raise ValueError(
            f"checkpoint lacks {len(missing)} trainable weights of this model (e.g. {sorted(missing)[0]!r}): "
            "it was written for a different model.* / LoRA setting"
        )


def check_same_base(stored: dict | None, spec: ModelSpec) -> None:
    """Refuse to resume a checkpoint (its `stored` model spec) on another base or adapter: its kind, the tiny model's
    sizes or seed (its random weights), `lora_alpha`, or the adapter's rank, targets and trained modules; the trained
    weights mean nothing there or do not fit. Another
    `path` is only logged: the same weights may have moved.

    Raises:
        ValueError: the settings that differ, as the checkpoint has them and as the run builds them.
    """
    if not isinstance(stored, dict):
        return
    current = dataclasses.asdict(spec)
    if stored.get("path", current["path"]) != current["path"]:
        logging.getLogger(__name__).warning(
            f"the checkpoint was trained on model.path = {stored['path']!r}, this run loads {current['path']!r}: "
            "resuming, which is right only if both hold the same weights"
        )
    # the adapter's shape too: another lora_rank failed inside Lightning with a size-mismatch traceback, and fewer
    # targets or trained modules dropped the checkpoint's other weights without a word
    keys = ["kind", "tiny", "lora_alpha", "lora_rank", "lora_targets", "modules_to_save", "train_vision"]
    keys += ["seed"] if spec.kind == "tiny" else []

    def plain(key, value):
        if key in ("lora_targets", "modules_to_save") and isinstance(value, list | tuple):
            return sorted(set(value))  # which modules, not in which order: the same weights, in the model's order
        return list(value) if isinstance(value, list | tuple) else value

    diff = [k for k in keys if k in stored and plain(k, stored[k]) != plain(k, current[k])]
    if diff:
        raise ValueError(
            "the checkpoint was trained on model "
            + ", ".join(f"{k}={stored[k]!r}" for k in diff)
            + ", but the run builds "
            + ", ".join(f"{k}={current[k]!r}" for k in diff)
            + " (model.*; model.seed follows seed): resume with the same model"
        )


def checkpoint_stage(checkpoint: dict) -> str | None:
    """The stage ("sft" or "pro") whose module wrote a Lightning checkpoint dict, by its hyperparameters."""
    hp = checkpoint.get("hyper_parameters") or {}
    return "pro" if "num_samples" in hp else "sft" if "warmup_steps" in hp else None


def check_resume_checkpoint(path: str | Path, stage: str | None = None) -> None:
    """Refuse, before a model is built, a `ckpt_path` that Lightning could not resume from: a missing path, a file
    torch cannot read (as Lightning reads it: `weights_only`), a dict without Lightning's version key (Lightning
    then failed with `KeyError: 'pytorch-lightning_version'`), a folder that is not DeepSpeed's sharded checkpoint
    (IsADirectoryError inside Lightning) or, given `stage`, a checkpoint of the other stage (an SFT checkpoint
    went on as PRO, a PRO one as SFT, without a word). A DeepSpeed folder is left to Lightning.

    Raises:
        FileNotFoundError: nothing at `path`.
        ValueError: not a Lightning checkpoint, or another stage's (the path and the reason named).
    """
    path = Path(path)
    if path.is_dir():
        if (path / "latest").is_file():  # DeepSpeed's folder: its tag file, then the tag's shards
            return
        found = sorted(p.name for p in path.glob("*.ckpt"))
        pick = "last.ckpt" if "last.ckpt" in found else found[-1] if found else None
        raise ValueError(
            f"ckpt_path = {str(path)!r}: a folder, not a checkpoint (nor DeepSpeed's checkpoint folder): give a .ckpt"
            + (f", e.g. ckpt_path={path / pick}" if pick else " file (OUT/checkpoints/last.ckpt)")
        )
    if not path.is_file():
        raise FileNotFoundError(2, f"ckpt_path = {str(path)!r}: no such checkpoint", str(path))
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as e:  # torch raises pickle, zip and runtime errors for a file that is no checkpoint
        raise ValueError(f"ckpt_path = {str(path)!r}: not a checkpoint torch can read ({type(e).__name__})") from None
    if not isinstance(ckpt, dict) or "pytorch-lightning_version" not in ckpt:
        raise ValueError(
            f"ckpt_path = {str(path)!r}: not a Lightning training checkpoint (resume from OUT/checkpoints/last.ckpt "
            "or a stepNNNNNN.ckpt of a train.py run)"
        )
    stored = checkpoint_stage(ckpt)
    if stage is not None and stored is not None and stored != stage:
        hint = " (PRO starts from an SFT run's adapter: stage.init_adapter=OUT/adapter)" if stage == "pro" else ""
        raise ValueError(
            f"ckpt_path = {str(path)!r}: a checkpoint of stage={stored}, but the run is stage={stage}: resume it with "
            f"stage={stored}{hint}"
        )


def runnable_kernel(spec: ModelSpec, device: torch.device) -> ModelSpec:
    """`spec` with an attention kernel `device` can run, for loading a trained adapter: flash_attention_2 (which
    does not change the weights) becomes sdpa on the CPU or without the `flash_attn` package."""
    import importlib.util

    if spec.attn_implementation != "flash_attention_2":
        return spec
    if device.type == "cuda" and importlib.util.find_spec("flash_attn") is not None:
        return spec
    return dataclasses.replace(spec, attn_implementation="sdpa")


def adapter_from_checkpoint(checkpoint: str | Path, out: str | Path) -> Path:
    """Write the peft adapter folder (what `save_adapter` writes) of a training checkpoint: any step's, while
    `OUT/adapter` holds the latest. The checkpoint keeps the trained weights only (LoRA, `modules_to_save`, a
    trainable vision tower) and the specs; the base is rebuilt from the spec, as `load_adapter` does.

    Raises:
        FileNotFoundError: no such checkpoint.
        ValueError: a folder, not an aynamics training checkpoint, or its weights do not fit the model its spec
            builds.
    """
    checkpoint = Path(checkpoint)
    if checkpoint.is_dir():  # OUT/checkpoints itself was "no such checkpoint", though the folder is there
        found = sorted(p.name for p in checkpoint.glob("*.ckpt"))
        pick = "last.ckpt" if "last.ckpt" in found else found[-1] if found else None
        raise ValueError(
            f"{str(checkpoint)!r} is a folder, not a checkpoint: give a .ckpt file"
            + (f", e.g. {checkpoint / pick}" if pick else " (OUT/checkpoints/stepNNNNNN.ckpt or last.ckpt)")
        )
    if not checkpoint.is_file():
        raise FileNotFoundError(2, "no such checkpoint", str(checkpoint))
    try:
        ckpt = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises pickle, zip and runtime errors for a file that is no checkpoint
        raise ValueError(f"{str(checkpoint)!r} is not a readable checkpoint: {type(e).__name__}") from None
    if not isinstance(ckpt, dict) or "aynamics_meta" not in ckpt or "state_dict" not in ckpt:
        raise ValueError(
            f"{str(checkpoint)!r} holds no 'aynamics_meta': not a checkpoint of `train.py` with the adapter callback"
        )
    spec, prompt = specs_of_meta(ckpt["aynamics_meta"], where=f"'aynamics_meta' of {str(checkpoint)!r}")
    model = build_model(runnable_kernel(spec, torch.device("cpu")))  # the folder keeps the spec as trained
    params = dict(model.named_parameters())
    state = {k.removeprefix("model."): v for k, v in ckpt["state_dict"].items() if k.startswith("model.")}
    trainable = {k for k, p in params.items() if p.requires_grad}
    missing, unexpected = sorted(trainable - set(state)), sorted(set(state) - set(params))
    if missing or unexpected:
        raise ValueError(
            f"{str(checkpoint)!r} does not fit the model its spec builds: {len(missing)} trained weights missing "
            f"{missing[:2]}, {len(unexpected)} unknown {unexpected[:2]}"
        )
    model.load_state_dict(state, strict=False)
    return save_adapter(model, out, spec, prompt)


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


def load_adapter(
    adapter_dir: str | Path, device: str | torch.device | None = "cpu"
) -> tuple[torch.nn.Module, ModelSpec, PromptSpec]:
    """Rebuild the base model of an adapter folder and load the adapter onto it (eval mode), on `device`
    (`inference_device`: None or "auto" for a GPU when there is one).

    Raises:
        FileNotFoundError: the folder has no `aynamics.json`.
        ValueError: a file of the folder is not what training writes, peft refuses its config, or weights of
            other shapes than the base's (weights with other names load with peft's warning only).
    """
    from peft import PeftModel

    from aynamics.model import peft_quietly

    target = inference_device(None if device is None else str(device))  # a bad name before the model loads
    spec, prompt = read_adapter_meta(adapter_dir)
    check_adapter_files(adapter_dir)
    base = build_base(runnable_kernel(spec, target))
    try:
        with peft_quietly():
            # read onto the CPU, where the base is: peft's default, the first GPU, opened a CUDA context there from
            # every process and for --device cpu
            model = PeftModel.from_pretrained(base, str(adapter_dir), torch_device="cpu")
    except torch.OutOfMemoryError:
        raise
    except (OSError, KeyError, TypeError, ValueError, RuntimeError) as e:  # a peft config peft refuses, weights of
        # another base's shapes, ...
        raise ValueError(
            f"adapter {str(adapter_dir)!r} cannot be loaded (its adapter_config.json, or weights that do not fit the "
            f"base model its aynamics.json names): {type(e).__name__}: {e}"
        ) from None
    return model.to(target).eval(), spec, prompt


def greedy_texts(model: torch.nn.Module, processor, prompts: Sequence[dict], max_new_tokens: int) -> list[str]:
    """Greedy responses (special tokens dropped) to unbatched prompts from `processor.build_prompt`."""
    from aynamics.reward import sample_completions

    _, texts = sample_completions(
        model, processor, prompts, num_samples=1, temperature=0.0, max_new_tokens=max_new_tokens
    )
    return [t[0] for t in texts]
