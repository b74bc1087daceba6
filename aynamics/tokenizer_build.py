"""Build the tiny test tokenizer kept in `aynamics/assets/tokenizer/` (offline, deterministic, a few seconds).

The tiny Qwen2.5-VL (`model=tiny`) needs a tokenizer that is small, has Qwen's special tokens and a Qwen-style
chat template, and splits numbers digit by digit as Qwen does. This script trains a byte-level BPE with
`tokenizers` on procedurally generated scene YAML and reasoning sentences, adds the special tokens, and writes
`tokenizer.json`, `tokenizer_config.json`, `chat_template.jinja` and the image processor's
`preprocessor_config.json`, so `ImageOnlyQwenProcessor.from_pretrained(TINY_ASSET_DIR)` loads it like a real
checkpoint directory.

    python -m aynamics.tokenizer_build            # rewrite the asset in place
    python -m aynamics.tokenizer_build --out DIR  # write elsewhere
"""

from __future__ import annotations

import argparse
import json
import random
from collections.abc import Iterator
from pathlib import Path

from tokenizers import AddedToken, Regex, Tokenizer, decoders, models, normalizers, pre_tokenizers, trainers

TINY_ASSET_DIR = Path(__file__).parent / "assets" / "tokenizer"

# Qwen2's pre-tokenizer regex: `\p{N}` alone means every digit is its own pre-token.
PRETOKENIZE_REGEX = (
    r"""(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}"""
    r"""| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+"""
)

# Special tokens, in Qwen2.5-VL's order (ids 0.. here; Qwen's start at 151643). The vision ones are what the
# processor and the model config need; the rest keep prompts written for the real model tokenisable.
SPECIAL_TOKENS = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|object_ref_start|>",
    "<|object_ref_end|>",
    "<|box_start|>",
    "<|box_end|>",
    "<|quad_start|>",
    "<|quad_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|vision_pad|>",
    "<|image_pad|>",
    "<|video_pad|>",
]
# Added but not special: `decode(..., skip_special_tokens=True)` keeps them, so answers stay parseable.
TAG_TOKENS = ["<think>", "</think>", "<answer>", "</answer>"]

# Qwen2-VL / Qwen2.5-VL chat template (the one shipped with the Instruct checkpoints).
CHAT_TEMPLATE = (
    "{% set image_count = namespace(value=0) %}{% set video_count = namespace(value=0) %}"
    "{% for message in messages %}{% if loop.first and message['role'] != 'system' %}"
    "<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n{% endif %}"
    "<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}<|im_end|>\n"
    "{% else %}{% for content in message['content'] %}"
    "{% if content['type'] == 'image' or 'image' in content or 'image_url' in content %}"
    "{% set image_count.value = image_count.value + 1 %}"
    "{% if add_vision_id %}Picture {{ image_count.value }}: {% endif %}"
    "<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif content['type'] == 'video' or 'video' in content %}"
    "{% set video_count.value = video_count.value + 1 %}"
    "{% if add_vision_id %}Video {{ video_count.value }}: {% endif %}"
    "<|vision_start|><|video_pad|><|vision_end|>"
    "{% elif 'text' in content %}{{ content['text'] }}{% endif %}{% endfor %}<|im_end|>\n"
    "{% endif %}{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)

# Image processor defaults of the tiny asset: small frames (min 56x56, max 112x112 pixels before patching).
TINY_MIN_PIXELS = 56 * 56
TINY_MAX_PIXELS = 112 * 112

VOCAB_SIZE = 1024  # bytes (256) + specials + merges; the model rounds its embedding up to a multiple of 64


def _num(rng: random.Random, lo: float, hi: float, decimals: int) -> str:
    return f"{round(rng.uniform(lo, hi), decimals):.{decimals}f}"


def _vec(rng: random.Random, n: int, lo: float, hi: float, decimals: int) -> str:
    return "[" + ", ".join(_num(rng, lo, hi, decimals) for _ in range(n)) + "]"


def scene_yaml(rng: random.Random) -> str:
    """One random scene in the model's YAML format (values plausible, not validated)."""
    d = rng.choice([1, 2, 2, 3, 4])
    lines: list[str] = []
    counts = {"box": 0, "sphere": 0, "cylinder": 0}
    for _ in range(rng.randint(1, 4)):
        kind = rng.choice(list(counts))
        lines += [f"- type: {kind}", f"  name: {kind}_{counts[kind]}"]
        counts[kind] += 1
        if kind == "box":
            lines.append(f"  size: {_vec(rng, 3, 0.05, 2.0, d)}")
        else:
            lines.append(f"  radius: {_num(rng, 0.05, 1.5, d)}")
            if kind == "cylinder":
                lines.append(f"  height: {_num(rng, 0.05, 2.0, d)}")
        lines += [
            "  state:",
            f"    angular_velocity: {_vec(rng, 3, -5, 5, d)}",
            f"    linear_velocity: {_vec(rng, 3, -6, 6, d)}",
            f"    orientation: {_vec(rng, 4, -1, 1, d)}",
            f"    position: {_vec(rng, 3, -6, 6, d)}",
            "  physics:",
            f"    friction: {_vec(rng, 2, 0, 1.5, d)}",
            f"    mass: {_num(rng, 0.1, 10, d)}",
            f"    damping: {_num(rng, -8, 0, d)}",
        ]
        if rng.random() < 0.3:
            lines.append(f"    restitution: {_num(rng, 0, 1, d)}")
    lines += [
        "- type: camera",
        f"  fovy: {_num(rng, 20, 90, 1)}",
        f"  orientation: {_num(rng, 0, 90, 1)}",
        f"  position: {_vec(rng, 3, -8, 8, d)}",
        "- type: gravity",
        "  gravity: [0.0, 0.0, -9.81]" if rng.random() < 0.7 else f"  gravity: {_vec(rng, 3, -10, 10, d)}",
    ]
    if rng.random() < 0.3:
        lines += [
            "- type: environment",
            f"  air_density: {_num(rng, 0, 1.3, d)}",
            f"  air_viscosity: {_num(rng, 0, 0.1, d)}",
            f"  wind: {_vec(rng, 3, -3, 3, d)}",
            f"  floor_offset: {_num(rng, -0.5, 0.5, d)}",
            f"  floor_tilt: {_vec(rng, 2, -0.2, 0.2, d)}",
        ]
    return "\n".join(lines) + "\n"


_SIDES = ["far left", "left", "centre", "right", "far right"]
_DEPTHS = ["near the camera", "mid-distance", "far from the camera"]
_HEIGHTS = ["close to the surface", "slightly above the ground", "high above the ground"]
_DIRS = ["rightward", "leftward", "forward", "backward", "upward", "downward"]
_SHAPES = {"box": "A cuboid", "sphere": "A sphere", "cylinder": "A cylinder"}


def reasoning(rng: random.Random) -> str:
    """Short motion-reasoning sentences like the ones in the paper's <think> blocks."""
    out = []
    for _ in range(rng.randint(1, 3)):
        kind = rng.choice(list(_SHAPES))
        name = f"{kind}_{rng.randint(0, 3)}"
        if kind == "box":
            dims = f"dimensions {_num(rng, 0.1, 2, 1)} x {_num(rng, 0.1, 2, 1)} x {_num(rng, 0.1, 2, 1)} m"
        elif kind == "sphere":
            dims = f"radius {_num(rng, 0.1, 1.5, 2)} m"
        else:
            dims = f"radius {_num(rng, 0.1, 1.5, 2)} m and height {_num(rng, 0.1, 2, 2)} m"
        dirs = " and ".join(rng.sample(_DIRS, 2))
        other = f"{rng.choice(list(_SHAPES))}_{rng.randint(0, 3)}"
        t0, t1 = sorted(rng.uniform(0, 3) for _ in range(2))
        text = (
            f"{name.capitalize()}: {_SHAPES[kind]} with {dims}, mass {_num(rng, 0.1, 10, 1)} kg, positioned "
            f"{rng.choice(_SIDES)} and {rng.choice(_DEPTHS)}, {rng.choice(_HEIGHTS)}. It moves at "
            f"{_num(rng, 0, 8, 2)} m/s ({dirs}), "
        )
        text += rng.choice(
            [
                f"stops at t={t1:.1f}s, and stays grounded from {t0:.2f}-{t1:.2f}s. ",
                f"bounces at t={t0:.1f}s and slides until t={t1:.1f}s. ",
                f"rolls without stopping and leaves the view at t={t1:.1f}s. ",
                "stays at rest for the whole sequence. ",
            ]
        )
        if rng.random() < 0.6:
            text += f"Collides with {other} at t={t0:.1f}s. "
        if rng.random() < 0.3:
            level = rng.choice(["low", "high", "moderate"])
            text += f"Friction looks {level}; it decelerates by {_num(rng, 0, 9, 1)} m/s^2. "
        out.append(text.strip())
    return "\n".join(out)


_PROMPTS = [
    "You are a physics expert. Watch the video frames and write the scene as YAML.",
    "Describe every object in the scene with its shape, size, initial state and physical parameters.",
    "Think about the motion first, then answer with the scene inside <answer></answer> tags.",
    "The frames below show rigid objects moving on a floor. Estimate positions, velocities, mass and friction.",
    "Here is an example of the expected output format.",
    "Reason step by step about collisions, sliding, rolling and bouncing before you answer.",
    "Segmentation masks and optical flow of the first frame are shown. Use them to locate each object.",
]


def corpus(n_scenes: int = 600, seed: int = 0) -> Iterator[str]:
    """Procedural training text: scenes, reasoning, chat-formatted targets and prompt sentences."""
    rng = random.Random(seed)
    yield from _PROMPTS
    for i in range(n_scenes):
        y = scene_yaml(rng)
        if i % 3 == 0:
            yield f"<think>{reasoning(rng)}</think>\n\n<answer>\n{y}</answer>"
        else:
            yield f"<answer>\n{y}</answer>"
        yield rng.choice(_PROMPTS) + " " + reasoning(rng)


def build_tokenizer(vocab_size: int = VOCAB_SIZE, seed: int = 0) -> Tokenizer:
    """Train the byte-level BPE with Qwen2's normaliser, pre-tokeniser and decoder; specials get ids 0..17."""
    tok = Tokenizer(models.BPE(unk_token=None, fuse_unk=False, byte_fallback=False))
    tok.normalizer = normalizers.NFC()
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(PRETOKENIZE_REGEX), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        min_frequency=2,
        special_tokens=[AddedToken(t, special=True, normalized=False) for t in SPECIAL_TOKENS],
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tok.train_from_iterator(corpus(seed=seed), trainer=trainer)
    tok.add_tokens([AddedToken(t, special=False, normalized=False) for t in TAG_TOKENS])
    return tok


def write_asset(out: Path = TINY_ASSET_DIR, vocab_size: int = VOCAB_SIZE) -> Path:
    """Write tokenizer, chat template and image-processor config to `out`; returns `out`."""
    from transformers import PreTrainedTokenizerFast
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    out.mkdir(parents=True, exist_ok=True)
    hf_tok = PreTrainedTokenizerFast(
        tokenizer_object=build_tokenizer(vocab_size),
        eos_token="<|im_end|>",  # chat models stop on <|im_end|> (Qwen Instruct's eos)
        pad_token="<|endoftext|>",
        unk_token=None,
        bos_token=None,
        clean_up_tokenization_spaces=False,
        model_max_length=32768,
        chat_template=CHAT_TEMPLATE,
    )
    hf_tok.save_pretrained(out)
    Qwen2VLImageProcessorPil(min_pixels=TINY_MIN_PIXELS, max_pixels=TINY_MAX_PIXELS).save_pretrained(out)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=TINY_ASSET_DIR, help="output directory")
    parser.add_argument("--vocab-size", type=int, default=VOCAB_SIZE, help="BPE vocabulary size incl. specials")
    args = parser.parse_args(argv)
    out = write_asset(args.out, args.vocab_size)
    sizes = {p.name: p.stat().st_size for p in sorted(out.iterdir())}
    print(f"wrote {out}: {json.dumps(sizes)}")


if __name__ == "__main__":
    main()
