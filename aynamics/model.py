"""The vision-language model: a tiny random Qwen2.5-VL for tests, the real checkpoints, LoRA and freezing.

Three models, all `Qwen2_5_VLForConditionalGeneration`:

- `build_tiny_model()`: random weights from a config (64-wide, 2 text layers, 2 vision blocks) with the
  tokenizer kept in `aynamics/assets/tokenizer/` (see `aynamics.tokenizer_build`); offline, CPU, ms per step.
- `load_pretrained(QWEN2_5_VL_3B)` (the paper's model) or `load_pretrained(QWEN2_5_VL_7B)`: a hub id or a local
  directory with the checkpoint; nothing is downloaded when `local_files_only=True` (or `HF_HUB_OFFLINE=1`).

Then `apply_lora(model)` puts LoRA on the language model only (a regex on `language_model`, so the vision
MLPs that share the projection names stay untouched) and freezes or trains the vision tower by a flag.

    model = build_tiny_model()
    model = apply_lora(model, rank=8, alpha=16, train_vision=False, gradient_checkpointing=True)
"""

from __future__ import annotations

import contextlib
import inspect
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import torch
from peft import LoraConfig, PeftModel, get_peft_model
from transformers import (
    PreTrainedTokenizerBase,
    Qwen2_5_VLConfig,
    Qwen2_5_VLForConditionalGeneration,
)

from aynamics.processor import checkpoint_error, local_path
from aynamics.tokenizer_build import TINY_ASSET_DIR

QWEN2_5_VL_3B = "Qwen/Qwen2.5-VL-3B-Instruct"  # the paper's model
QWEN2_5_VL_7B = "Qwen/Qwen2.5-VL-7B-Instruct"

# The seven projections of every decoder layer. The vision blocks' MLPs are also called gate/up/down_proj,
# hence `lora_target_regex` restricts matching to `language_model`.
DEFAULT_LORA_TARGETS = ("q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj")


def check_tiny_sizes(sizes: dict, prefix: str = "") -> None:
    """Refuse tiny-model sizes `tiny_config` cannot build, naming each key with `prefix` ("model.tiny." for the
    config): an unknown key (a TypeError in `tiny_config`), a size that is no whole number >= 1 (0 heads divided by
    zero, a negative width failed inside torch, 0 layers left LoRA nothing to adapt), head widths that do not divide.
    Keys left out take `TINY_SIZES`' defaults."""
    unknown = sorted(set(sizes) - set(TINY_SIZES) - {"tie_word_embeddings"})
    if unknown:
        raise ValueError(
            f"{prefix}{unknown[0]} = {sizes[unknown[0]]!r}: not a size of the tiny model (its keys: "
            f"{', '.join([*TINY_SIZES, 'tie_word_embeddings'])})"
        )
    tie = sizes.get("tie_word_embeddings", False)
    if not isinstance(tie, bool):
        raise ValueError(f"{prefix}tie_word_embeddings = {tie!r}: must be true or false")
    for key, value in sizes.items():
        if key != "tie_word_embeddings" and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{prefix}{key} = {value!r}: must be a whole number >= 1")
    s = TINY_SIZES | sizes
    hidden, heads, kv, vision, vision_heads = (
        s[k] for k in ("hidden_size", "num_heads", "num_kv_heads", "vision_hidden_size", "vision_heads")
    )
    if hidden % heads or (hidden // heads) % 2:
        raise ValueError(
            f"{prefix}hidden_size = {hidden}, {prefix}num_heads = {heads}: head_dim must be an even integer"
        )
    if heads % kv:
        raise ValueError(f"{prefix}num_heads = {heads} is not a multiple of {prefix}num_kv_heads = {kv}")
    if vision % vision_heads:
        raise ValueError(
            f"{prefix}vision_hidden_size = {vision} is not a multiple of {prefix}vision_heads = {vision_heads}"
        )


def tiny_config(
    tokenizer: PreTrainedTokenizerBase,
    *,
    hidden_size: int = 64,
    num_layers: int = 2,
    num_heads: int = 4,
    num_kv_heads: int = 2,
    intermediate_size: int = 128,
    vision_hidden_size: int = 32,
    vision_depth: int = 2,
    vision_heads: int = 2,
    vision_intermediate_size: int = 64,
    tie_word_embeddings: bool = False,
) -> Qwen2_5_VLConfig:
    """Config of a tiny Qwen2.5-VL whose special-token ids come from `tokenizer`.

    Keeps Qwen's patch geometry (14 px patches, 2x2 merge, temporal patch 2), so the processor is the real one.
    The embedding is the tokenizer's length rounded up to a multiple of 64.
    """
    sizes = {k: v for k, v in locals().items() if k in TINY_SIZES}
    check_tiny_sizes(sizes | {"tie_word_embeddings": tie_word_embeddings})
    head_dim = hidden_size // num_heads
    # M-RoPE splits head_dim/2 rotary frequencies over (t, h, w); Qwen uses [16, 24, 24] of 64.
    half = head_dim // 2
    mrope_section = [half - 2 * (3 * half // 8), 3 * half // 8, 3 * half // 8]
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in ("<|endoftext|>", "<|im_end|>")}
    ids |= {t: tokenizer.convert_tokens_to_ids(t) for t in ("<|image_pad|>", "<|video_pad|>")}
    ids |= {t: tokenizer.convert_tokens_to_ids(t) for t in ("<|vision_start|>", "<|vision_end|>")}
    missing = [t for t, i in ids.items() if i is None or i == tokenizer.unk_token_id]
    if missing:
        raise ValueError(f"tokenizer lacks the special tokens {missing}; rebuild it with aynamics.tokenizer_build")
    vocab_size = -(-len(tokenizer) // 64) * 64
    text_config = {
        "vocab_size": vocab_size,
        "hidden_size": hidden_size,
        "intermediate_size": intermediate_size,
        "num_hidden_layers": num_layers,
        "num_attention_heads": num_heads,
        "num_key_value_heads": num_kv_heads,
        "max_position_embeddings": 4096,
        "rope_parameters": {"rope_type": "default", "rope_theta": 1_000_000.0, "mrope_section": mrope_section},
        "bos_token_id": ids["<|endoftext|>"],
        "eos_token_id": ids["<|im_end|>"],
        "pad_token_id": ids["<|endoftext|>"],
        "tie_word_embeddings": tie_word_embeddings,
    }
    vision_config = {
        "depth": vision_depth,
        "hidden_size": vision_hidden_size,
        "intermediate_size": vision_intermediate_size,
        "num_heads": vision_heads,
        "out_hidden_size": hidden_size,  # must equal the text width: merged patches become token embeddings
        "fullatt_block_indexes": [vision_depth - 1],  # indexes must be < depth
        "window_size": 112,  # pixels: 4x4 merged patches per attention window, as in Qwen2.5-VL
        "tokens_per_second": 2,  # Qwen2.5-VL-3B/7B value: temporal position step per second of video
    }
    return Qwen2_5_VLConfig(
        text_config=text_config,
        vision_config=vision_config,
        image_token_id=ids["<|image_pad|>"],
        video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"],
        vision_end_token_id=ids["<|vision_end|>"],
        tie_word_embeddings=tie_word_embeddings,
    )


# `tiny_config`'s sizes (`model.tiny` in the config), each a whole number >= 1, with its signature's defaults
TINY_SIZES = {
    name: arg.default
    for name, arg in inspect.signature(tiny_config).parameters.items()
    if arg.kind is arg.KEYWORD_ONLY and name != "tie_word_embeddings"
}


# The published architectures (the checkpoints' config.json): the language model's width, layers, attention and
# key/value heads, MLP width, vocabulary and tied embeddings (both: RMSNorm eps 1e-6, RoPE theta 1e6). Both share
# one vision tower: 32 blocks 1280 wide, 16 heads, MLP 3420, full attention in blocks 7, 15, 23 and 31 (windows of
# 112 px elsewhere).
QWEN_ARCHITECTURES = {
    "3b": {"hidden_size": 2048, "num_layers": 36, "num_heads": 16, "num_kv_heads": 2, "intermediate_size": 11008,
           "vocab_size": 151936, "tie_word_embeddings": True},
    "7b": {"hidden_size": 3584, "num_layers": 28, "num_heads": 28, "num_kv_heads": 4, "intermediate_size": 18944,
           "vocab_size": 152064, "tie_word_embeddings": False},
}  # fmt: skip
QWEN_VISION = {"vision_hidden_size": 1280, "vision_depth": 32, "vision_heads": 16, "vision_intermediate_size": 3420}
QWEN_FULL_ATTENTION_BLOCKS = (7, 15, 23, 31)


def qwen_architecture_config(
    size: str,
    tokenizer: PreTrainedTokenizerBase,
    *,
    text_layers: int | None = None,
    vision_depth: int | None = None,
) -> Qwen2_5_VLConfig:
    """The config of the published Qwen2.5-VL-3B or -7B (`size` "3b" / "7b"), with `tokenizer`'s special-token ids
    (the repo's tokenizer has Qwen's tokens, at other ids) and optionally fewer layers or vision blocks: every
    width, head count, the vocabulary, M-RoPE sections [16, 24, 24] and the window layout are the real ones.

    Raises:
        ValueError: an unknown size, or a layer count < 1 (named).
    """
    if size not in QWEN_ARCHITECTURES:
        raise ValueError(f"size = {size!r}: must be one of {sorted(QWEN_ARCHITECTURES)}")
    arch = {**QWEN_ARCHITECTURES[size], **QWEN_VISION}
    vocab_size = arch.pop("vocab_size")
    for name, value in (("text_layers", text_layers), ("vision_depth", vision_depth)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} = {value!r}: must be a whole number >= 1 (or None: the published count)")
    arch["num_layers"] = text_layers or arch["num_layers"]
    arch["vision_depth"] = depth = vision_depth or arch["vision_depth"]
    config = tiny_config(tokenizer, **arch)
    config.text_config.vocab_size = vocab_size
    config.text_config.max_position_embeddings = 128000
    config.text_config.rms_norm_eps = 1e-6  # the checkpoints' (transformers' default is 1e-5)
    full = [i for i in QWEN_FULL_ATTENTION_BLOCKS if i < depth]
    config.vision_config.fullatt_block_indexes = full or [depth - 1]
    return config


def random_checkpoint(
    folder: str | Path,
    size: str = "3b",
    *,
    text_layers: int | None = None,
    vision_depth: int | None = None,
    seed: int = 0,
) -> Path:
    """Write a checkpoint folder of the published Qwen2.5-VL architecture (`qwen_architecture_config`) with random
    bfloat16 weights, the repo's tokenizer and chat template, and Qwen's image processor settings (min / max pixels
    3136 / 12845056): `model=qwen2_5_vl_3b model.path=FOLDER` then runs every command at the real model's size
    without its weights (none can be downloaded here). For memory, speed and shape checks; it writes no scene.

    The 3B folder holds 3.75 B parameters, 7.5 GB; the 7B one 8.3 B, 16.6 GB (and as much memory to build it).
    """
    import json

    from transformers import AutoTokenizer

    folder = Path(folder)
    tokenizer = AutoTokenizer.from_pretrained(str(TINY_ASSET_DIR))
    config = qwen_architecture_config(size, tokenizer, text_layers=text_layers, vision_depth=vision_depth)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = Qwen2_5_VLForConditionalGeneration._from_config(config, dtype=torch.bfloat16)
    _set_generation_ids(model, tokenizer)
    model.save_pretrained(folder)
    tokenizer.save_pretrained(folder)  # with its chat template (chat_template.jinja)
    image = json.loads((TINY_ASSET_DIR / "preprocessor_config.json").read_text())
    image |= {"min_pixels": 3136, "max_pixels": 12845056, "size": {"shortest_edge": 3136, "longest_edge": 12845056}}
    (folder / "preprocessor_config.json").write_text(json.dumps(image, indent=2) + "\n")
    return folder


def build_tiny_model(
    tokenizer_dir: str | Path = TINY_ASSET_DIR,
    *,
    seed: int = 0,
    attn_implementation: str = "sdpa",
    **config_kwargs: int | bool,
) -> Qwen2_5_VLForConditionalGeneration:
    """Randomly initialised tiny Qwen2.5-VL (~0.2 M parameters) matching the tokenizer in `tokenizer_dir`.

    Args:
        tokenizer_dir: Directory holding the tokenizer (default: the repo's asset).
        seed: Seed of the initialisation; the global RNG state is left as it was.
        attn_implementation: "sdpa" or "eager".
        **config_kwargs: Overrides passed to `tiny_config` (hidden_size, num_layers, ...).
    """
    from transformers import AutoTokenizer

    tokenizer = AutoTokenizer.from_pretrained(str(tokenizer_dir))
    config = tiny_config(tokenizer, **config_kwargs)
    config._attn_implementation = attn_implementation
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = Qwen2_5_VLForConditionalGeneration(config)
    _set_generation_ids(model, tokenizer)
    return model.eval()


def load_pretrained(
    name_or_path: str | Path,
    *,
    dtype: str | torch.dtype = "auto",
    attn_implementation: str | None = None,
    device_map: str | dict | None = None,
    local_files_only: bool = False,
) -> Qwen2_5_VLForConditionalGeneration:
    """Load a Qwen2.5-VL checkpoint (`QWEN2_5_VL_3B`, `QWEN2_5_VL_7B`, or a local directory) with `from_pretrained`.

    Args:
        name_or_path: Hub id or local directory (also one written by `save_pretrained` of the tiny model).
        dtype: "auto" keeps the checkpoint's dtype (bfloat16 for Qwen), or e.g. torch.float32.
        attn_implementation: "sdpa", "eager", "flash_attention_2" or None for transformers' default.
        device_map: Passed through (e.g. "auto" or "cuda:0"); None loads on the CPU.
        local_files_only: Never touch the network (the machines here have no hub access).

    Under a meta device context (`with torch.device("meta")`) the model is built from the checkpoint's config and
    generation config only, its weights neither read nor allocated (`from_pretrained` refuses that context): what
    every process but rank 0 builds under `trainer=fsdp`, to be given rank 0's weights once sharded
    (`aynamics.sharding`).
    """
    where = local_path(name_or_path)  # absolute: a folder (a hub id is never one)
    if Path(where).is_absolute() and not Path(where).is_dir():
        raise FileNotFoundError(f"model path {str(name_or_path)!r} is not a directory (or pass a hub id)")
    if torch.get_default_device().type == "meta":
        return _empty_pretrained(where, dtype, attn_implementation, local_files_only)
    try:
        model = Qwen2_5_VLForConditionalGeneration.from_pretrained(
            where,
            dtype=dtype,
            attn_implementation=attn_implementation,
            device_map=device_map,
            local_files_only=local_files_only,
        )
    except (OSError, ValueError) as e:  # not found, no hub, not a repo id, broken files
        raise checkpoint_error(name_or_path, "model", e) from None
    _default_pad_id(model)
    return model


def _empty_pretrained(
    name_or_path: str | Path, dtype: str | torch.dtype, attn_implementation: str | None, local_files_only: bool
) -> Qwen2_5_VLForConditionalGeneration:
    """`load_pretrained`'s model on the meta device: its config and generation config as `from_pretrained` reads
    them, no weights."""
    from transformers import AutoConfig, GenerationConfig

    try:
        config = AutoConfig.from_pretrained(str(name_or_path), local_files_only=local_files_only)
    except (OSError, ValueError) as e:
        raise checkpoint_error(name_or_path, "model", e) from None
    dtype = (getattr(config, "dtype", None) or torch.float32) if dtype == "auto" else dtype
    kernel = {} if attn_implementation is None else {"attn_implementation": attn_implementation}
    model = Qwen2_5_VLForConditionalGeneration._from_config(config, dtype=dtype, **kernel)
    try:  # as from_pretrained: the checkpoint's generation config, else the one made from the model config
        model.generation_config = GenerationConfig.from_pretrained(str(name_or_path), local_files_only=local_files_only)
    except OSError:
        pass
    _default_pad_id(model)
    return model.eval()


def _default_pad_id(model: Qwen2_5_VLForConditionalGeneration) -> None:
    """Generation pads with the generation config's pad id, else the text config's (0 is an id), else bos."""
    gen, text = model.generation_config, model.config.text_config
    if gen.pad_token_id is None:
        gen.pad_token_id = text.pad_token_id if text.pad_token_id is not None else text.bos_token_id


def _set_generation_ids(model: Qwen2_5_VLForConditionalGeneration, tokenizer: PreTrainedTokenizerBase) -> None:
    """Stop on <|im_end|> or <|endoftext|> and pad with <|endoftext|>, as Qwen's Instruct generation config does."""
    im_end, eot = tokenizer.convert_tokens_to_ids(["<|im_end|>", "<|endoftext|>"])
    model.generation_config.eos_token_id = [im_end, eot]
    model.generation_config.pad_token_id = eot
    model.generation_config.bos_token_id = eot


def lora_target_regex(target_modules: Sequence[str] = DEFAULT_LORA_TARGETS) -> str:
    """Regex (peft full-matches it against module names) selecting `target_modules` inside the language model."""
    if not target_modules:
        raise ValueError("model.lora_targets = []: name at least one projection, e.g. 'q_proj'")
    names = "|".join(re.escape(m) for m in target_modules)
    return rf"(.*\.)?language_model\.(.*\.)?({names})"


def set_vision_trainable(model: torch.nn.Module, trainable: bool) -> None:
    """Freeze (`trainable=False`) or unfreeze the vision tower (`model.visual`, patch merger included)."""
    visual = find_visual(model)
    for p in visual.parameters():
        p.requires_grad_(trainable)


def find_visual(model: torch.nn.Module) -> torch.nn.Module:
    """The vision tower of a Qwen2.5-VL model, bare or wrapped by peft."""
    for name, module in model.named_modules():
        if name == "visual" or name.endswith(".visual"):
            return module
    raise ValueError(f"{type(model).__name__} has no `visual` module: not a Qwen2.5-VL model")


def enable_gradient_checkpointing(model: torch.nn.Module) -> None:
    """Non-reentrant activation checkpointing (works with frozen embeddings and LoRA); disables the KV cache."""
    if hasattr(model, "activation_checkpointing_enable"):  # transformers >= 5.x name
        model.activation_checkpointing_enable(activation_checkpointing_kwargs={"use_reentrant": False})
    else:
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs={"use_reentrant": False})
    model.config.use_cache = False
    model.config.get_text_config().use_cache = False  # what the language model reads (a composite config)


def apply_lora(
    model: Qwen2_5_VLForConditionalGeneration,
    *,
    rank: int = 16,
    alpha: float = 32.0,
    dropout: float = 0.05,
    target_modules: Sequence[str] = DEFAULT_LORA_TARGETS,
    train_vision: bool = False,
    gradient_checkpointing: bool = False,
    modules_to_save: Sequence[str] = (),
) -> PeftModel:
    """Wrap `model` with LoRA adapters on the language model's projections; everything else is frozen.

    Args:
        model: A Qwen2.5-VL model (tiny or pretrained).
        rank: LoRA rank r (> 0).
        alpha: LoRA scaling numerator; the update is scaled by alpha / rank.
        dropout: Dropout on the LoRA input, in [0, 1).
        target_modules: Projection names inside `language_model` to adapt.
        train_vision: Also train the whole vision tower (full weights). peft saves it with the adapter
            (`modules_to_save=["visual"]`), so `PeftModel.from_pretrained` restores it.
        gradient_checkpointing: Enable non-reentrant activation checkpointing first.
        modules_to_save: More modules trained in full and saved with the adapter (e.g. "embed_tokens", "lm_head"
            for a model trained from scratch).
    """
    if rank <= 0:
        raise ValueError(f"lora rank = {rank}: must be > 0")
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"lora dropout = {dropout}: must be in [0, 1)")
    pattern = re.compile(lora_target_regex(target_modules))
    language = {n: m for n, m in model.named_modules() if "language_model" in n}
    adapted = {
        n.rsplit(".", 1)[-1] for n, m in language.items() if isinstance(m, torch.nn.Linear) and pattern.fullmatch(n)
    }
    if missed := [m for m in target_modules if m not in adapted]:
        # peft adapted the names it found and left a misspelt one ('vproj' beside 'q_proj') out without a word;
        # a block's name ('mlp'), not a linear layer's, failed inside peft
        linear = sorted({n.rsplit(".", 1)[-1] for n, m in language.items() if isinstance(m, torch.nn.Linear)})
        raise ValueError(
            f"model.lora_targets = {list(target_modules)}: {missed} names no linear layer of the language model "
            f"(its linear layers: {', '.join(linear) or 'none'})"
        )
    names = [name for name, _ in model.named_modules(remove_duplicate=False)]
    unknown = [m for m in modules_to_save if not any(n.endswith(m) for n in names)]  # peft's own test of a name
    if unknown:  # peft trained nothing for such a name, without a word
        raise ValueError(f"model.modules_to_save = {list(modules_to_save)}: no module named {unknown} in the model")
    if gradient_checkpointing:
        enable_gradient_checkpointing(model)
    config = LoraConfig(
        r=rank,
        lora_alpha=alpha,
        lora_dropout=dropout,
        target_modules=lora_target_regex(target_modules),
        modules_to_save=(["visual"] if train_vision else []) + list(modules_to_save) or None,
        bias="none",
        task_type="CAUSAL_LM",
    )
    try:
        with peft_quietly():
            return get_peft_model(model, config)
    except ValueError as e:  # peft: "Target modules ... not found in the base model"
        raise ValueError(f"model.lora_targets = {list(target_modules)}: no such module in language_model") from e


@contextlib.contextmanager
def peft_quietly():
    """peft reads transformers' deprecated `is_gradient_checkpointing` when it wraps or loads a model: a
    FutureWarning on every run and command, not ours to act on."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", ".*is_gradient_checkpointing.* is deprecated", FutureWarning)
        yield


def float32_trained_tower(model: torch.nn.Module) -> None:
    """Keep a trained vision tower's weights (peft's trainable copy) in float32 when the base is in bfloat16.

    AdamW steps of ~lr on bfloat16 weights (8 bits of mantissa) round away: one step of the tiny tower changes
    85 % of its bfloat16 entries at lr 1e-4 and 15 % at 1e-5 (the end of a cosine schedule from 1e-4), all of
    them in float32; and mixed precision expects float32 weights (autocast computes in bfloat16). Safe without
    autocast too: the tower casts the pixels to its own dtype and the model casts the image embeddings to the
    text's. The LoRA weights are float32 already (peft); other `modules_to_save` keep the base dtype (float32
    copies of embed_tokens / lm_head would need autocast).
    """
    for name, p in model.named_parameters():
        if p.requires_grad and "visual" in name.split(".") and p.dtype != torch.float32:
            p.data = p.data.float()


def count_parameters(model: torch.nn.Module) -> tuple[int, int]:
    """(trainable, total) parameter counts."""
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    return trainable, sum(p.numel() for p in model.parameters())
