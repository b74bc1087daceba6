"""Turning frames + text into Qwen2.5-VL inputs: an image-only processor and SFT chat formatting.

transformers' `Qwen2_5_VLProcessor` needs torchvision's video processor, which has no CPU build here.
`ImageOnlyQwenProcessor` keeps the stock PIL image processor (`Qwen2VLImageProcessorPil`) and builds video
patches from its per-frame output (frames paired along time: temporal patch 2, half the visual tokens of the
same frames given as separate images). Nothing imports torchvision.

One example is a dict of tensors without a batch dimension (`build_prompt`, `build_sft_example`):

    input_ids, attention_mask, labels, mm_token_type_ids   # (L,)  labels = -100 outside the response
    pixel_values, image_grid_thw                           # (P, 1176), (n_images, 3)   frames as images
    pixel_values_videos, video_grid_thw, second_per_grid_ts  # (P, 1176), (1, 3), (1,)  frames as one video

`aynamics.batching` pads them into batches and `aynamics.logprobs` scores their labelled tokens.

    proc = load_processor(TINY_ASSET_DIR)
    ex = build_sft_example(proc, frames, "<answer>...</answer>", system_prompt=..., user_prompt=...)
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from transformers import AutoTokenizer, BatchFeature, Qwen2_5_VLProcessor
from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil
from transformers.processing_utils import ProcessorMixin

IGNORE_INDEX = -100  # label of tokens that carry no loss (prompt, images, padding)
TEXT, IMAGE, VIDEO = 0, 1, 2  # mm_token_type_ids values the model expects

Frame = Image.Image | np.ndarray  # (H, W, 3) uint8 or PIL image


class PixelBoundsError(ValueError):
    """min_pixels above max_pixels: a setting to fix, not a checkpoint that could not be loaded."""


# tokens every Qwen2.5-VL tokenizer holds: the chat turn end and the vision markers the processor writes
VISION_TOKENS = ("<|im_end|>", "<|vision_start|>", "<|vision_end|>", "<|image_pad|>", "<|video_pad|>")


class ImageOnlyQwenProcessor(Qwen2_5_VLProcessor):
    """Qwen2.5-VL processor whose videos are built from the PIL image processor (no torchvision).

    Args:
        image_processor: A `Qwen2VLImageProcessorPil` (min/max pixels live in its `size`).
        tokenizer: The model's tokenizer, holding <|image_pad|>, <|video_pad|> and the vision start/end tokens.
        chat_template: Jinja chat template; defaults to the tokenizer's.
        num_frames: Frames kept from each clip by `sample_frames` (evenly spaced); None keeps all.
        video_fps: Frames per second of the frames handed to the model; a video's temporal positions advance
            by `tokens_per_second * temporal_patch_size / video_fps` per frame pair.
    """

    def __init__(
        self,
        image_processor: Qwen2VLImageProcessorPil | None = None,
        tokenizer: Any = None,
        chat_template: str | None = None,
        num_frames: int | None = None,
        video_fps: float = 2.0,
    ) -> None:
        if num_frames is not None and num_frames < 1:
            raise ValueError(f"num_frames = {num_frames}: must be >= 1 or None")
        if video_fps <= 0:
            raise ValueError(f"video_fps = {video_fps}: must be > 0")
        self.image_token = getattr(tokenizer, "image_token", None) or "<|image_pad|>"
        self.video_token = getattr(tokenizer, "video_token", None) or "<|video_pad|>"
        self.image_token_id = tokenizer.convert_tokens_to_ids(self.image_token)
        self.video_token_id = tokenizer.convert_tokens_to_ids(self.video_token)
        # Skip Qwen2_5_VLProcessor.__init__: it expects a video processor.
        chat_template = chat_template or tokenizer.chat_template
        ProcessorMixin.__init__(self, image_processor, tokenizer, chat_template=chat_template)
        self.num_frames = num_frames
        self.video_fps = float(video_fps)

    @classmethod
    def from_pretrained(  # type: ignore[override]
        cls,
        name_or_path: str | Path,
        *,
        min_pixels: int | None = None,
        max_pixels: int | None = None,
        num_frames: int | None = None,
        video_fps: float | None = None,
        local_files_only: bool = False,
    ) -> ImageOnlyQwenProcessor:
        """Tokenizer + PIL image processor from a checkpoint directory or hub id (never a video processor).

        Arguments left as None take the values saved by `save_pretrained` (processor_config.json), else defaults.
        """
        kw = {"local_files_only": local_files_only}
        where = local_path(name_or_path)
        saved = _saved_processor_config(where)
        num_frames = num_frames if num_frames is not None else saved.get("num_frames")
        video_fps = video_fps if video_fps is not None else saved.get("video_fps", 2.0)
        tokenizer = AutoTokenizer.from_pretrained(where, **kw)
        missing = [t for t in VISION_TOKENS if t not in tokenizer.get_vocab()]
        if missing:  # a folder without tokenizer files loads a 1-token tokenizer that encodes every text to nothing
            raise ValueError(
                f"its tokenizer lacks {', '.join(missing)} (no Qwen2.5-VL tokenizer files: tokenizer.json or "
                "vocab.json + merges.txt, with tokenizer_config.json)"
            )
        image_processor = Qwen2VLImageProcessorPil.from_pretrained(where, **kw)
        size = dict(image_processor.size)
        size["shortest_edge"] = min_pixels or size["shortest_edge"]
        size["longest_edge"] = max_pixels or size["longest_edge"]
        if size["shortest_edge"] > size["longest_edge"]:
            raise PixelBoundsError(
                f"min_pixels = {size['shortest_edge']} > max_pixels = {size['longest_edge']} (a bound left null "
                f"takes the value of {str(name_or_path)!r}'s preprocessor_config.json): need min_pixels <= max_pixels"
            )
        image_processor.size = size
        template = _saved_chat_template(where) or tokenizer.chat_template
        if template is None:
            raise ValueError(f"{str(name_or_path)!r} holds no chat template (chat_template.jinja/.json or tokenizer's)")
        return cls(image_processor, tokenizer, chat_template=template, num_frames=num_frames, video_fps=video_fps)

    @property
    def merge_length(self) -> int:
        return self.image_processor.merge_size**2

    def process_images(self, images: Sequence[Frame]) -> dict[str, torch.Tensor]:
        """pixel_values (P, C*2*14*14) and image_grid_thw (n, 3), one grid row per image."""
        out = self.image_processor(images=list(images), return_tensors="pt")
        return {"pixel_values": out["pixel_values"], "image_grid_thw": out["image_grid_thw"]}

    def process_video(self, frames: Sequence[Frame]) -> dict[str, torch.Tensor]:
        """One video: pixel_values_videos (P, C*2*14*14), video_grid_thw (1, 3), second_per_grid_ts (1,).

        Frames are resized and normalised like images, then paired along time (an odd count repeats the last
        frame, as Qwen's video processor does). Patch order per frame pair is the video processor's:
        (h/2, w/2, 2, 2) merge blocks, each patch flattened as (C, T=2, 14, 14).
        """
        if len(frames) == 0:
            raise ValueError("process_video got 0 frames: need at least 1")
        sizes = {_frame_hw(f) for f in frames}
        if len(sizes) != 1:
            raise ValueError(f"video frames have different sizes {sorted(sizes)}: all must match")
        t = self.image_processor.temporal_patch_size
        p = self.image_processor.patch_size
        frames = list(frames) + [frames[-1]] * (-len(frames) % t)
        img = self.process_images(frames)
        _, gh, gw = (int(v) for v in img["image_grid_thw"][0])
        n = gh * gw
        # (F*n, C*T*p*p) -> (F, n, C, T, p, p); the image processor repeats each frame along T, keep one copy
        x = img["pixel_values"].view(len(frames), n, -1, t, p, p)[:, :, :, 0]
        x = x.view(len(frames) // t, t, n, -1, p, p).permute(0, 2, 3, 1, 4, 5)  # (F/T, n, C, T, p, p)
        return {
            "pixel_values_videos": x.reshape(len(frames) // t * n, -1).contiguous(),
            "video_grid_thw": torch.tensor([[len(frames) // t, gh, gw]]),
            "second_per_grid_ts": torch.tensor([t / self.video_fps]),
        }

    def __call__(  # type: ignore[override]
        self,
        text: str | Sequence[str],
        images: Sequence[Frame] | None = None,
        videos: Sequence[Sequence[Frame]] | None = None,
        *,
        padding: bool = False,
        padding_side: str = "left",
        return_tensors: str = "pt",
        **kwargs: Any,
    ) -> BatchFeature:
        """Tokenise `text` after expanding each <|image_pad|> / <|video_pad|> into its number of visual tokens.

        `images` are taken in order by the image placeholders of all texts, `videos` by the video
        placeholders. Returns input_ids, attention_mask, mm_token_type_ids and the pixel tensors.
        `audio=None` and `return_mm_token_type_ids` (always on) are accepted for `apply_chat_template(tokenize=True)`.
        """
        if kwargs.pop("audio", None) is not None:
            raise ValueError("ImageOnlyQwenProcessor got audio: Qwen2.5-VL takes only images and videos")
        kwargs.pop("return_mm_token_type_ids", None)
        if kwargs:
            raise TypeError(f"ImageOnlyQwenProcessor.__call__ got unsupported arguments {sorted(kwargs)}")
        texts = [text] if isinstance(text, str) else list(text)
        data: dict[str, torch.Tensor] = {}
        counts: dict[str, list[int]] = {self.image_token: [], self.video_token: []}
        if images:
            data |= self.process_images(images)
            counts[self.image_token] = (data["image_grid_thw"].prod(-1) // self.merge_length).tolist()
        if videos:
            parts = [self.process_video(v) for v in videos]
            for key in ("pixel_values_videos", "video_grid_thw", "second_per_grid_ts"):
                data[key] = torch.cat([part[key] for part in parts])
            counts[self.video_token] = (data["video_grid_thw"].prod(-1) // self.merge_length).tolist()
        for token, per_item in counts.items():
            found = sum(t.count(token) for t in texts)
            if found != len(per_item):
                raise ValueError(f"text holds {found} {token} placeholders but {len(per_item)} visual inputs given")
            it = iter(per_item)
            texts = [_expand(t, token, it) for t in texts]
        enc = self.tokenizer(
            texts, padding=padding, padding_side=padding_side, return_tensors=return_tensors, add_special_tokens=False
        )
        ids = enc["input_ids"]
        data["input_ids"] = ids
        data["attention_mask"] = enc["attention_mask"]
        is_image, is_video = (ids == self.image_token_id).long(), (ids == self.video_token_id).long()
        data["mm_token_type_ids"] = is_image * IMAGE + is_video * VIDEO
        return BatchFeature(data=data)


def _saved_processor_config(name_or_path: str | Path) -> dict[str, Any]:
    """processor_config.json of a local directory ({} for hub ids or when absent)."""
    path = Path(name_or_path) / "processor_config.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def _saved_chat_template(name_or_path: str | Path) -> str | None:
    """Processor-level chat template of a local checkpoint (Qwen ships chat_template.json), else None."""
    root = Path(name_or_path)
    if (root / "chat_template.jinja").is_file():
        return (root / "chat_template.jinja").read_text()
    if (root / "chat_template.json").is_file():
        return json.loads((root / "chat_template.json").read_text()).get("chat_template")
    return None


def _expand(text: str, token: str, counts: Any) -> str:
    pieces = text.split(token)
    return pieces[0] + "".join(token * next(counts) + piece for piece in pieces[1:])


def _frame_hw(frame: Frame) -> tuple[int, int]:
    if isinstance(frame, Image.Image):
        return frame.height, frame.width
    return tuple(np.asarray(frame).shape[:2])  # type: ignore[return-value]


def load_processor(
    name_or_path: str | Path,
    *,
    min_pixels: int | None = None,
    max_pixels: int | None = None,
    num_frames: int | None = None,
    video_fps: float | None = None,
    local_files_only: bool = False,
) -> ImageOnlyQwenProcessor:
    """`ImageOnlyQwenProcessor.from_pretrained`: the tiny asset (`TINY_ASSET_DIR`), a checkpoint dir or a hub id.

    Args:
        name_or_path: Directory or hub id holding tokenizer files and `preprocessor_config.json`.
        min_pixels: Lower bound of pixels per frame after resizing (Qwen default 56*56); None keeps the saved one.
        max_pixels: Upper bound of pixels per frame (Qwen default 28*28*1280); a frame of h*w pixels costs about
            h*w / 784 visual tokens as an image, half that in a video.
        num_frames: Frames kept per clip by `sample_frames`; None keeps all.
        video_fps: Frame rate of the frames given to the model (sets video temporal positions); None: saved or 2.0.
        local_files_only: Never touch the network.
    """
    try:
        return ImageOnlyQwenProcessor.from_pretrained(
            name_or_path,
            min_pixels=min_pixels,
            max_pixels=max_pixels,
            num_frames=num_frames,
            video_fps=video_fps,
            local_files_only=local_files_only,
        )
    except PixelBoundsError:
        raise
    except (OSError, ValueError) as e:  # not found, no hub, not a repo id, broken files
        raise checkpoint_error(name_or_path, "processor", e) from None


class CheckpointError(FileNotFoundError):
    """A model checkpoint that cannot be loaded (a folder without weights, a hub id out of reach, broken files):
    a FileNotFoundError with a message only, which the `aynamics` commands report in one line, status 2."""


def local_path(name_or_path: str | Path) -> str:
    """Where `from_pretrained` should look: a checkpoint folder as an absolute path with `~` expanded
    (from_pretrained takes '~/models/x' for a hub id; an adapter records its base so and is loaded from any working
    directory), a hub id ('Qwen/Qwen2.5-VL-3B-Instruct', no such folder here) unchanged. A Path, or a string
    starting with '.', '/' or '~', is a folder whether it exists or not."""
    folder = Path(name_or_path).expanduser()
    if isinstance(name_or_path, Path) or str(name_or_path).startswith((".", "/", "~")) or folder.is_dir():
        return str(folder.resolve())
    return str(name_or_path)


def checkpoint_error(name_or_path: str | Path, what: str, error: Exception) -> OSError:
    """The error for a checkpoint `from_pretrained` could not load: the path named, the cause's first line, and
    what to give instead (the library's message alone says neither which setting nor what would work)."""
    cause = (str(error).strip().splitlines() or [type(error).__name__])[0]
    return CheckpointError(
        f"model path {str(name_or_path)!r}: cannot load the {what} ({cause}); give a local folder holding a "
        "Qwen2.5-VL checkpoint (e.g. model.path=/models/Qwen2.5-VL-3B-Instruct), or a hub id on a machine that "
        "reaches the Hugging Face hub"
    )


def sample_frames(frames: Sequence[Frame], num_frames: int | None) -> list[Frame]:
    """`num_frames` evenly spaced frames, first and last included; all frames when None or more than available."""
    if num_frames is None or num_frames >= len(frames):
        return list(frames)
    if num_frames < 1:
        raise ValueError(f"num_frames = {num_frames}: must be >= 1")
    idx = np.linspace(0, len(frames) - 1, num_frames).round().astype(int)
    return [frames[i] for i in idx]


# --------------------------------------------------------------------------------------------
# Chat formatting
# --------------------------------------------------------------------------------------------
def build_messages(
    num_frames: int,
    *,
    system_prompt: str,
    user_prompt: str,
    examples: Sequence[str] = (),
    as_video: bool = False,
) -> list[dict[str, Any]]:
    """Chat messages of the prompt: system, then one user turn = in-context examples, frames, instruction.

    Args:
        num_frames: Number of frames (image placeholders), ignored when `as_video` (one video placeholder).
        system_prompt: The system message.
        user_prompt: Instruction text placed after the frames.
        examples: In-context examples as text (e.g. a scene in YAML), each inserted as "Example k:\\n...".
        as_video: Give the frames as one video instead of separate images.
    """
    content: list[dict[str, Any]] = [
        {"type": "text", "text": f"Example {k}:\n{ex.strip()}\n\n"} for k, ex in enumerate(examples, 1)
    ]
    if as_video:
        content.append({"type": "video"})
    else:
        content += [{"type": "image"} for _ in range(num_frames)]
    content.append({"type": "text", "text": user_prompt})
    return [{"role": "system", "content": system_prompt}, {"role": "user", "content": content}]


def build_prompt(
    processor: ImageOnlyQwenProcessor,
    frames: Sequence[Frame],
    *,
    system_prompt: str,
    user_prompt: str,
    examples: Sequence[str] = (),
    as_video: bool = False,
) -> dict[str, torch.Tensor]:
    """Generation input of one example: the prompt ending in "<|im_start|>assistant\\n", no batch dimension.

    Frames are first subsampled to `processor.num_frames`. `labels` is all -100.
    """
    frames = sample_frames(frames, processor.num_frames)
    if not frames:
        raise ValueError("build_prompt got 0 frames: need at least 1")
    messages = build_messages(
        len(frames), system_prompt=system_prompt, user_prompt=user_prompt, examples=examples, as_video=as_video
    )
    text = processor.apply_chat_template(messages, tokenize=False, add_generation_prompt=True)
    if as_video:
        enc = processor(text=text, videos=[frames])
    else:
        enc = processor(text=text, images=frames)
    ex = {k: v[0] if k in ("input_ids", "attention_mask", "mm_token_type_ids") else v for k, v in enc.items()}
    ex["labels"] = torch.full_like(ex["input_ids"], IGNORE_INDEX)
    return ex


def response_ids(processor: ImageOnlyQwenProcessor, response: str) -> list[int]:
    """Token ids of an assistant response followed by <|im_end|> (the turn's end, which the model must learn)."""
    ids = processor.tokenizer(response, add_special_tokens=False)["input_ids"]
    return list(ids) + [processor.tokenizer.convert_tokens_to_ids("<|im_end|>")]


TYPE_VALUE = re.compile(r"\btype:[ \t]*([A-Za-z_]+)")


def type_tokens(processor: ImageOnlyQwenProcessor, response: str) -> torch.Tensor:
    """Which tokens of `response_ids(processor, response)` spell an entry's type (the `box` of `type: box`, and
    `camera`, `gravity`, ...): a bool mask, <|im_end|> included (False).

    Those few tokens are the choices that decide how many objects a scene has and of which shapes: among ~450
    number and format tokens they carry little of the mean loss (`data.type_weight` stresses them), and the
    model's accuracy on them says whether it reads the frames (`val/type_acc`).
    """
    enc = processor.tokenizer(response, add_special_tokens=False, return_offsets_mapping=True)
    spans = [m.span(1) for m in TYPE_VALUE.finditer(response)]
    out = torch.zeros(len(enc["input_ids"]) + 1, dtype=torch.bool)  # + <|im_end|>
    for k, (a, b) in enumerate(enc["offset_mapping"]):
        out[k] = any(a < e and b > s for s, e in spans)
    return out


def build_sft_example(
    processor: ImageOnlyQwenProcessor,
    frames: Sequence[Frame],
    response: str,
    *,
    system_prompt: str,
    user_prompt: str,
    examples: Sequence[str] = (),
    as_video: bool = False,
) -> dict[str, torch.Tensor]:
    """Prompt + response of one SFT example; labels are -100 except on the response tokens and <|im_end|>.

    `response` is the target text, e.g. "<answer>YAML</answer>" or "<think>...</think>\\n\\n<answer>...</answer>".
    The response is tokenised on its own and appended to the prompt ids, so training sees exactly the ids that
    generation from `build_prompt` would continue from.
    """
    prompt = build_prompt(
        processor, frames, system_prompt=system_prompt, user_prompt=user_prompt, examples=examples, as_video=as_video
    )
    return append_response(prompt, response_ids(processor, response))


def append_response(prompt: dict[str, torch.Tensor], completion: Sequence[int]) -> dict[str, torch.Tensor]:
    """`prompt` (unbatched) + completion ids: labels = completion, mm_token_type_ids = 0 on it."""
    c = torch.as_tensor(list(completion), dtype=prompt["input_ids"].dtype)
    ex = dict(prompt)
    ex["input_ids"] = torch.cat([prompt["input_ids"], c])
    ex["attention_mask"] = torch.cat([prompt["attention_mask"], torch.ones_like(c)])
    ex["labels"] = torch.cat([prompt["labels"], c])
    ex["mm_token_type_ids"] = torch.cat([prompt["mm_token_type_ids"], torch.zeros_like(c)])
    return ex
