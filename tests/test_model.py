"""The tiny Qwen2.5-VL: forward/backward, generation, LoRA placement, freezing, adapter and checkpoint round trips."""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest
import torch
from peft import PeftModel

from aynamics.batching import append_completions, collate, model_inputs
from aynamics.logprobs import mean_token_logprob
from aynamics.model import (
    DEFAULT_LORA_TARGETS,
    apply_lora,
    build_tiny_model,
    count_parameters,
    load_pretrained,
    set_vision_trainable,
)
from aynamics.processor import IGNORE_INDEX, build_prompt, build_sft_example, load_processor
from aynamics.tokenizer_build import TINY_ASSET_DIR

PROMPTS = {"system_prompt": "You are a physics expert.", "user_prompt": "Write the scene as YAML."}


@pytest.fixture(scope="module")
def proc():
    return load_processor(TINY_ASSET_DIR)


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(0)
    return [rng.integers(0, 255, (56, 84, 3), dtype=np.uint8) for _ in range(3)]


@pytest.fixture(scope="module")
def batches(proc, frames):
    """Two-example SFT batches (different lengths, left-padded): frames as images, and as one video."""
    pad = proc.tokenizer.pad_token_id
    out = {}
    for as_video in (False, True):
        a = build_sft_example(proc, frames, "<answer>\n- type: box\n</answer>", as_video=as_video, **PROMPTS)
        b = build_sft_example(
            proc, frames[:2], "<think>slides</think>\n\n<answer>x</answer>", as_video=as_video, **PROMPTS
        )
        out["video" if as_video else "images"] = ([a, b], collate([a, b], pad))
    return out


def test_tiny_model_config(proc):
    model = build_tiny_model()
    cfg = model.config
    trainable, total = count_parameters(model)
    assert trainable == total < 400_000
    assert cfg.text_config.vocab_size >= len(proc.tokenizer)
    assert cfg.image_token_id == proc.image_token_id and cfg.video_token_id == proc.video_token_id
    assert cfg.vision_config.out_hidden_size == cfg.text_config.hidden_size
    assert sum(cfg.text_config.rope_parameters["mrope_section"]) * 2 == 64 // 4  # head_dim
    assert torch.equal(build_tiny_model().lm_head.weight, model.lm_head.weight)  # seeded


@pytest.mark.parametrize("kind", ["images", "video"])
def test_forward_backward(batches, kind):
    model = build_tiny_model().train()
    _, batch = batches[kind]
    out = model(**model_inputs(batch), labels=batch["labels"])
    assert torch.isfinite(out.loss)
    out.loss.backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert model.model.visual.patch_embed.proj.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", ["images", "video"])
def test_left_padding_gives_unpadded_logits(proc, batches, kind):
    """3-D positions come from the attention mask, so a padded row reproduces its unpadded logits."""
    model = build_tiny_model()
    examples, batch = batches[kind]
    pad = proc.tokenizer.pad_token_id
    with torch.no_grad():
        logits = model(**model_inputs(batch)).logits
        for row, ex in enumerate(examples):
            alone = model(**model_inputs(collate([ex], pad))).logits[0]
            keep = batch["attention_mask"][row].bool()
            torch.testing.assert_close(logits[row][keep], alone, atol=1e-5, rtol=1e-5)
        # without mm_token_type_ids the model silently falls back to 1-D positions: different logits
        one = model_inputs(collate(examples[-1:], pad))
        no_mm = {k: v for k, v in one.items() if k != "mm_token_type_ids"}
        assert not torch.allclose(model(**no_mm).logits[0], alone, atol=1e-4)


@pytest.mark.parametrize("as_video", [False, True])
def test_generate(proc, frames, as_video):
    model = build_tiny_model()
    pad = proc.tokenizer.pad_token_id
    prompts = [build_prompt(proc, frames, as_video=as_video, **PROMPTS), build_prompt(proc, frames[:2], **PROMPTS)]
    if as_video:
        prompts[1] = build_prompt(proc, frames[:2], as_video=True, **PROMPTS)
    batch = collate(prompts, pad)
    out = model.generate(**model_inputs(batch), max_new_tokens=4, do_sample=False)
    assert out.shape == (2, batch["input_ids"].shape[1] + 4)
    alone = model.generate(**model_inputs(collate(prompts[:1], pad)), max_new_tokens=4, do_sample=False)
    assert torch.equal(out[0, -4:], alone[0, -4:])


def test_lora_hits_only_the_language_model():
    model = apply_lora(build_tiny_model(), rank=4, alpha=8, dropout=0.0)
    lora = [n for n, _ in model.named_parameters() if "lora_" in n]
    assert lora and not any("visual" in n for n in lora)
    assert all("language_model" in n for n in lora)
    assert len(lora) == 2 * len(DEFAULT_LORA_TARGETS) * 2  # A and B x 7 projections x 2 layers
    trainable = [n for n, p in model.named_parameters() if p.requires_grad]
    assert set(trainable) == set(lora)  # vision tower, embeddings, lm_head frozen
    only_q = apply_lora(build_tiny_model(), target_modules=["q_proj"])
    assert sum("lora_A" in n for n, _ in only_q.named_parameters()) == 2
    with pytest.raises(ValueError, match="nope_proj"):
        apply_lora(build_tiny_model(), target_modules=["nope_proj"])
    # peft adapted q_proj and left the misspelt 'vproj' out without a word; 'mlp' is a block, not a linear layer
    for targets, missed in [(["q_proj", "vproj"], "['vproj']"), (["mlp"], "['mlp']"), (["merger"], "['merger']")]:
        with pytest.raises(ValueError, match=rf"^model.lora_targets = .*: {re.escape(missed)} names no linear layer"):
            apply_lora(build_tiny_model(), target_modules=targets)


def test_model_spec_defaults_adapt_every_projection_at_scale_two():
    """`lm.ModelSpec()`'s adapter: LoRA rank 16, alpha 32 (scale 32 / 16 = 2) on all 7 projections of each of the
    tiny model's 2 layers: 14 LoRA A matrices of 16 rows, the tower frozen."""
    from aynamics import lm

    spec = lm.ModelSpec()
    assert spec.lora_targets == ("q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj")
    model = lm.build_model(spec)
    adapted = [m for n, m in model.named_modules() if hasattr(m, "lora_A") and "default" in m.lora_A]
    assert len(adapted) == 7 * 2
    assert {n.rsplit(".", 1)[-1] for n, m in model.named_modules() if m in adapted} == set(spec.lora_targets)
    assert all(m.lora_A["default"].weight.shape[0] == 16 and m.scaling["default"] == 2.0 for m in adapted)
    assert not any(p.requires_grad for n, p in model.named_parameters() if "visual" in n)


def test_vision_trainable_flag():
    model = apply_lora(build_tiny_model(), train_vision=True)
    vis = [(n, p) for n, p in model.named_parameters() if "visual" in n and p.requires_grad]
    assert vis and not any("lora_" in n for n, _ in vis)
    assert any("modules_to_save" in n for n, _ in vis)
    base = build_tiny_model()
    set_vision_trainable(base, False)
    assert not any(p.requires_grad for p in base.model.visual.parameters())
    assert all(p.requires_grad for p in base.model.language_model.parameters())
    set_vision_trainable(base, True)
    assert all(p.requires_grad for p in base.model.visual.parameters())


def _train_steps(model, batch, steps=2):
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-2, weight_decay=0.0)
    model.train()
    for _ in range(steps):  # two steps: LoRA's B starts at 0, so A gets a gradient only from step 2
        loss = model(**model_inputs(batch), labels=batch["labels"]).loss
        loss.backward()
        opt.step()
        opt.zero_grad()
    return model.eval()


@pytest.mark.parametrize("train_vision", [False, True])
def test_training_changes_trainable_only_and_adapter_round_trips(batches, tmp_path, train_vision):
    _, batch = batches["images"]
    model = apply_lora(build_tiny_model(), rank=4, alpha=8, dropout=0.0, train_vision=train_vision)
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    _train_steps(model, batch)
    for n, p in model.named_parameters():
        changed = not torch.equal(p, before[n])
        assert changed == p.requires_grad, n
    with torch.no_grad():
        ref = model(**model_inputs(batch)).logits
    model.save_pretrained(tmp_path)
    reloaded = PeftModel.from_pretrained(build_tiny_model(), tmp_path).eval()
    with torch.no_grad():
        torch.testing.assert_close(reloaded(**model_inputs(batch)).logits, ref, atol=0, rtol=0)


def test_gradient_checkpointing_with_lora(batches):
    _, batch = batches["video"]
    model = apply_lora(build_tiny_model(), rank=4, gradient_checkpointing=True).train()
    assert model.base_model.model.model.language_model.gradient_checkpointing
    model(**model_inputs(batch), labels=batch["labels"]).loss.backward()
    assert all(p.grad is not None for n, p in model.named_parameters() if "lora_A" in n)


def test_save_and_load_pretrained_round_trip(batches, tmp_path):
    """The real-model path (`from_pretrained` on a directory) loads a saved tiny model unchanged; under a meta
    device context it builds the same model without weights."""
    _, batch = batches["images"]
    model = build_tiny_model()
    model.save_pretrained(tmp_path)
    loaded = load_pretrained(tmp_path, dtype=torch.float32, local_files_only=True)
    assert loaded.generation_config.pad_token_id == model.generation_config.pad_token_id
    with torch.no_grad():
        torch.testing.assert_close(loaded(**model_inputs(batch)).logits, model(**model_inputs(batch)).logits)
    # under a meta device context (trainer=fsdp's ranks but 0): the same weights' names, shapes and dtypes, none read
    for dtype in (torch.float32, torch.bfloat16):
        real = load_pretrained(tmp_path, dtype=dtype, local_files_only=True)
        with torch.device("meta"):
            empty = load_pretrained(tmp_path, dtype=dtype, local_files_only=True)
        assert all(t.is_meta for t in [*empty.parameters(), *empty.buffers()])
        tensors = [(n, t.shape, t.dtype) for n, t in [*real.named_parameters(), *real.named_buffers()]]
        assert [(n, t.shape, t.dtype) for n, t in [*empty.named_parameters(), *empty.named_buffers()]] == tensors
        assert empty.generation_config.to_dict() == real.generation_config.to_dict()
        assert empty.config.to_dict() == real.config.to_dict() and not empty.training
    with pytest.raises(FileNotFoundError, match="not a directory"):
        load_pretrained(tmp_path / "missing")
    (tmp_path / "empty").mkdir()  # a folder without a checkpoint, a path that is no hub id: the path is named
    with pytest.raises(OSError, match=r"model path '.*empty': cannot load the model \("):
        load_pretrained(tmp_path / "empty", local_files_only=True)
    from aynamics.processor import load_processor

    with pytest.raises(OSError, match=r"model path 'a/b/c': cannot load the processor \(.*a local folder"):
        load_processor("a/b/c", local_files_only=True)


def test_load_pretrained_on_meta_follows_the_checkpoint(tmp_path):
    """Under a meta device context `load_pretrained` builds what it would load: dtype="auto" takes the checkpoint's
    (bfloat16 here, not float32), an `attn_implementation` given is kept ("eager", not the default "sdpa"), a
    generation config without a pad id gets the model's (0), as from_pretrained's model does; a checkpoint without
    a generation config is built too (from the model config), and a folder without a checkpoint is named."""
    model = build_tiny_model().to(torch.bfloat16)
    model.generation_config.pad_token_id = None
    model.save_pretrained(tmp_path)
    real = load_pretrained(tmp_path, attn_implementation="eager", local_files_only=True)
    with torch.device("meta"):
        empty = load_pretrained(tmp_path, attn_implementation="eager", local_files_only=True)
    assert {t.dtype for t in empty.parameters()} == {t.dtype for t in real.parameters()} == {torch.bfloat16}
    assert empty.config._attn_implementation == real.config._attn_implementation == "eager"
    assert empty.generation_config.pad_token_id == real.generation_config.pad_token_id == 0
    (tmp_path / "generation_config.json").unlink()
    real = load_pretrained(tmp_path, dtype=torch.float32, local_files_only=True)
    with torch.device("meta"):
        empty = load_pretrained(tmp_path, dtype=torch.float32, local_files_only=True)
    ids = ("pad_token_id", "bos_token_id", "eos_token_id")
    assert [getattr(empty.generation_config, k) for k in ids] == [getattr(real.generation_config, k) for k in ids]
    (tmp_path / "empty").mkdir()
    with torch.device("meta"), pytest.raises(OSError, match=r"model path '.*empty': cannot load the model \("):
        load_pretrained(tmp_path / "empty", local_files_only=True)


def test_a_home_relative_or_relative_model_path_is_a_folder(tmp_path, monkeypatch):
    """model.path '~/x' or './x' loads that folder (from_pretrained took '~/x' for a hub id) and is recorded
    absolute, so an adapter finds its base from any working directory; a hub id is kept as written. A folder
    without tokenizer files is refused, naming what is missing (it loaded a 1-token tokenizer that encoded every
    text to nothing)."""
    from aynamics.lm import ModelSpec
    from aynamics.processor import load_processor

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    build_tiny_model().save_pretrained(tmp_path / "qwen")
    for f in TINY_ASSET_DIR.iterdir():
        shutil.copy(f, tmp_path / "qwen")
    assert ModelSpec(kind="pretrained", path="~/qwen").path == str(tmp_path / "qwen")
    assert ModelSpec(kind="pretrained", path="./qwen").path == str(tmp_path / "qwen")
    assert ModelSpec(kind="pretrained", path="Qwen/Qwen2.5-VL-3B-Instruct").path == "Qwen/Qwen2.5-VL-3B-Instruct"
    assert load_pretrained("~/qwen", dtype=torch.float32, local_files_only=True).config.model_type == "qwen2_5_vl"
    tiny_id = load_processor(TINY_ASSET_DIR).image_token_id
    assert load_processor("~/qwen", local_files_only=True).image_token_id == tiny_id
    for f in ("tokenizer.json", "tokenizer_config.json"):
        (tmp_path / "qwen" / f).unlink()
    lacks = r"model path '.*qwen': cannot load the processor \(its tokenizer lacks <\|im_end\|>"
    with pytest.raises(OSError, match=lacks):
        load_processor(tmp_path / "qwen", local_files_only=True)


def test_completion_logprobs_match_the_sft_loss(proc, frames):
    """Scoring N completions of one prompt: the mean token log-prob equals minus the model's own SFT loss."""
    model = build_tiny_model()
    tok = proc.tokenizer
    prompt = build_prompt(proc, frames, **PROMPTS)
    texts = ["<answer>a</answer><|im_end|>", "<think>b</think>\n\n<answer>c</answer><|im_end|>"]
    batch = append_completions(
        prompt, [tok(t, add_special_tokens=False)["input_ids"] for t in texts], pad_token_id=tok.pad_token_id
    )
    with torch.no_grad():
        lp = mean_token_logprob(model(**model_inputs(batch)).logits, batch["labels"])
        for row in range(len(texts)):
            one = {k: v[row : row + 1] for k, v in batch.items() if v.shape[0] == len(texts) and v.dim() == 2}
            one |= {"pixel_values": prompt["pixel_values"], "image_grid_thw": prompt["image_grid_thw"]}
            loss = model(**model_inputs(one), labels=one["labels"]).loss
            assert lp[row].item() == pytest.approx(-loss.item(), abs=1e-5)
    assert (batch["labels"] != IGNORE_INDEX).sum(-1).tolist() == [
        len(tok(t, add_special_tokens=False)["input_ids"]) for t in texts
    ]


def test_attention_kernel_is_chosen_by_the_spec(tmp_path, batches):
    """model.attn_implementation reaches the built model (tiny and from_pretrained): eager and sdpa give the same
    logits (on the unpadded positions); flash_attention_2 is refused for the tiny model, an unknown kernel named."""
    from aynamics import adapters, lm

    _, batch = batches["images"]
    eager = lm.build_base(lm.ModelSpec(attn_implementation="eager"))
    sdpa = lm.build_base(lm.ModelSpec())
    assert eager.config._attn_implementation == "eager" and sdpa.config._attn_implementation == "sdpa"
    real = batch["attention_mask"].bool()  # padded positions attend to nothing: the kernels fill them differently
    with torch.no_grad():
        torch.testing.assert_close(
            eager(**model_inputs(batch)).logits[real], sdpa(**model_inputs(batch)).logits[real], rtol=1e-4, atol=1e-5
        )
    sdpa.save_pretrained(tmp_path)
    shutil.copytree(TINY_ASSET_DIR, tmp_path, dirs_exist_ok=True)
    spec = lm.ModelSpec(kind="pretrained", path=str(tmp_path), attn_implementation="eager")
    assert lm.build_base(spec).config._attn_implementation == "eager"
    with pytest.raises(
        ValueError, match=r"attn_implementation = 'flash_attention_2': must be one of \('sdpa', 'eager'\)"
    ):
        lm.ModelSpec(attn_implementation="flash_attention_2")
    with pytest.raises(ValueError, match="attn_implementation = 'flash'"):
        lm.ModelSpec(kind="pretrained", path=str(tmp_path), attn_implementation="flash")
    # an adapter trained with flash attention loads here (CPU, no flash-attn) with sdpa: the weights are the same
    flash = lm.ModelSpec(kind="pretrained", path=str(tmp_path), attn_implementation="flash_attention_2")
    assert lm.runnable_kernel(flash, torch.device("cpu")).attn_implementation == "sdpa"
    adapters.save_adapter(
        lm.build_model(lm.runnable_kernel(flash, torch.device("cpu"))), tmp_path / "adapter", flash, lm.PromptSpec()
    )
    model, spec, _ = adapters.load_adapter(tmp_path / "adapter", "cpu")
    assert spec == flash and model.base_model.model.config._attn_implementation == "sdpa"


def test_token_logprobs_in_chunks_and_of_the_kept_positions():
    """Above `chunk_entries` the log-probabilities come from checkpointed chunks (x[label] - logsumexp(x)): the
    same values and gradients as the one-pass log_softmax; logits of only the last K positions (the model's
    logits_to_keep) give the same result when every label lies in them, and a label outside them is named."""
    from aynamics.logprobs import token_logprobs

    torch.manual_seed(0)
    logits = torch.randn(3, 9, 50, requires_grad=True)
    labels = torch.full((3, 9), -100)
    for row, start in enumerate((5, 7, 3)):
        labels[row, start:] = torch.randint(0, 50, (9 - start,))
    whole, mask = token_logprobs(logits, labels)
    (grad,) = torch.autograd.grad(whole.sum(), logits)
    assert torch.equal(mask, labels[:, 1:] != -100) and whole[~mask].eq(0).all()
    expected = logits.detach().log_softmax(-1)[:, :-1].gather(-1, labels[:, 1:].clamp(min=0).unsqueeze(-1))[..., 0]
    torch.testing.assert_close(whole[mask], expected[mask])
    chunked, mask2 = token_logprobs(logits, labels, chunk_entries=150)  # 3 positions of 50 entries: 3 + 3 + 2
    (grad2,) = torch.autograd.grad(chunked.sum(), logits)
    assert torch.equal(mask, mask2)
    torch.testing.assert_close(chunked, whole)
    torch.testing.assert_close(grad2, grad)
    for entries in (10**9, 150, 100):
        kept, mask3 = token_logprobs(logits[:, -7:], labels, chunk_entries=entries)  # labels from position 3 on
        assert torch.equal(mask3, mask)
        torch.testing.assert_close(kept, whole)
    with pytest.raises(ValueError, match="labelled tokens before the last 6 positions"):
        token_logprobs(logits[:, -6:], labels)


def test_a_trained_tower_of_a_bfloat16_base_is_kept_in_float32(tmp_path, batches):
    """model.dtype=bfloat16 with train_vision: the tower's trainable copy (and LoRA) are float32 master weights,
    the frozen base stays bfloat16, and a forward and backward run with and without autocast. One AdamW step at
    lr 1e-5 moves nearly all of the tower's entries (in bfloat16, 15 % of them); PRO's policy built from the
    adapter keeps it float32 too."""
    from aynamics import adapters, lm
    from aynamics.pro import build_policy

    build_tiny_model(seed=3).save_pretrained(tmp_path / "qwen")
    shutil.copytree(TINY_ASSET_DIR, tmp_path / "qwen", dirs_exist_ok=True)
    spec = lm.ModelSpec(kind="pretrained", path=str(tmp_path / "qwen"), dtype="bfloat16", train_vision=True)
    model = lm.build_model(spec)
    trained = {n: p for n, p in model.named_parameters() if p.requires_grad}
    assert any("visual" in n for n in trained) and {p.dtype for p in trained.values()} == {torch.float32}
    assert {p.dtype for p in model.parameters() if not p.requires_grad} == {torch.bfloat16}
    _, batch = batches["images"]
    for autocast in (False, True):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            model(**model_inputs(batch)).logits.float().mean().backward()
    tower = {n: p.detach().clone() for n, p in trained.items() if "visual" in n}
    torch.optim.AdamW(trained.values(), lr=1e-5).step()
    moved = sum(int((p.detach() != tower[n]).sum()) for n, p in trained.items() if n in tower)
    assert moved > 0.99 * sum(t.numel() for t in tower.values())
    adapters.save_adapter(model, tmp_path / "adapter", spec, lm.PromptSpec())
    policy, _ = build_policy(spec, str(tmp_path / "adapter"))
    assert {p.dtype for p in policy.parameters() if p.requires_grad} == {torch.float32}


def test_tiny_config_by_hand():
    """The asset's tokenizer holds 752 tokens, specials first in Qwen's order: <|endoftext|> 0, <|im_end|> 2,
    <|vision_start|> 9, <|vision_end|> 10, <|image_pad|> 12, <|video_pad|> 13. The embedding is 752 rounded up to a
    multiple of 64: 12 · 64 = 768; with 16 tokens added the tokenizer is 768 long, already a multiple (not 832).
    M-RoPE: head_dim 64 / 4 = 16, half 8 split (t, h, w) = (8 - 2·3, 3, 3) = (2, 3, 3) with 3 = 3·8 // 8; at
    Qwen's head_dim 128 (half 64): (64 - 2·24, 24, 24) = (16, 24, 24), Qwen's own. The last vision block (index
    depth - 1 = 1) attends globally; tokens_per_second 2 as in Qwen2.5-VL-3B/7B."""
    from transformers import AutoTokenizer

    from aynamics.model import tiny_config

    tok = AutoTokenizer.from_pretrained(str(TINY_ASSET_DIR))
    cfg = tiny_config(tok)
    text = cfg.text_config
    assert len(tok) == 752 and text.vocab_size == 768
    assert (text.bos_token_id, text.eos_token_id, text.pad_token_id) == (0, 2, 0)
    assert (cfg.vision_start_token_id, cfg.vision_end_token_id, cfg.image_token_id, cfg.video_token_id) == (
        9,
        10,
        12,
        13,
    )
    assert text.rope_parameters["mrope_section"] == [2, 3, 3]
    assert tiny_config(tok, hidden_size=512).text_config.rope_parameters["mrope_section"] == [16, 24, 24]
    assert cfg.vision_config.fullatt_block_indexes == [1] and cfg.vision_config.tokens_per_second == 2
    tok.add_tokens([f"<extra_{i}>" for i in range(16)])
    assert len(tok) == 768 and tiny_config(tok).text_config.vocab_size == 768


def test_tiny_config_and_lora_refuse_bad_sizes():
    """hidden 36 / 4 heads = head_dim 9 (M-RoPE rotates pairs: odd); 4 heads over 3 key-value heads; vision 30 wide
    over 4 heads; LoRA rank 0 (no adapter) and dropout 1 (drops every input)."""
    from transformers import AutoTokenizer

    from aynamics.model import tiny_config

    tok = AutoTokenizer.from_pretrained(str(TINY_ASSET_DIR))
    with pytest.raises(ValueError, match="head_dim must be an even integer"):
        tiny_config(tok, hidden_size=36)
    with pytest.raises(ValueError, match="num_heads = 4 is not a multiple of num_kv_heads = 3"):
        tiny_config(tok, num_kv_heads=3)
    with pytest.raises(ValueError, match="vision_hidden_size = 30 is not a multiple of vision_heads = 4"):
        tiny_config(tok, vision_hidden_size=30, vision_heads=4)
    with pytest.raises(ValueError, match="lora rank = 0"):
        apply_lora(build_tiny_model(), rank=0)
    with pytest.raises(ValueError, match="lora dropout = 1.0"):
        apply_lora(build_tiny_model(), dropout=1.0)


def test_tiny_sizes_are_refused_by_the_model_spec_with_their_keys():
    """`model.tiny` is checked when the spec is made (before any model): unknown keys, sizes that are no whole
    number >= 1 and widths that do not divide, each named in full; the sizes the spec leaves out are the defaults."""
    from aynamics.lm import ModelSpec

    for tiny, message in [
        ({"num_heads": 0}, "model.tiny.num_heads = 0: must be a whole number >= 1"),
        ({"num_kv_heads": 0}, "model.tiny.num_kv_heads = 0: must be a whole number >= 1"),
        ({"num_layers": 0}, "model.tiny.num_layers = 0: must be a whole number >= 1"),
        ({"vision_depth": 1.5}, "model.tiny.vision_depth = 1.5: must be a whole number >= 1"),
        ({"hidden_size": True}, "model.tiny.hidden_size = True: must be a whole number >= 1"),
        ({"heads": 4}, "model.tiny.heads = 4: not a size of the tiny model"),
        ({"tie_word_embeddings": 1}, "model.tiny.tie_word_embeddings = 1: must be true or false"),
        ({"num_kv_heads": 3}, "model.tiny.num_heads = 4 is not a multiple of model.tiny.num_kv_heads = 3"),
        ({"hidden_size": 36}, "model.tiny.hidden_size = 36, model.tiny.num_heads = 4: head_dim must be"),
    ]:
        with pytest.raises(ValueError, match=f"^{re.escape(message)}"):
            ModelSpec(kind="tiny", tiny=tiny)
    ModelSpec(kind="tiny", tiny={"hidden_size": 32, "num_heads": 2, "tie_word_embeddings": True})  # fine
    # the adapter's settings too, before the base loads (minutes for the 3B)
    for kwargs, message in [
        ({"lora_dropout": 1.5}, "model.lora_dropout = 1.5: must be a number in [0, 1)"),
        ({"lora_targets": []}, "model.lora_targets = []: must be a list of projection names"),
        ({"lora_targets": "q_proj"}, "model.lora_targets = 'q_proj': must be a list of projection names"),
    ]:
        with pytest.raises(ValueError, match=f"^{re.escape(message)}"):
            ModelSpec(kind="tiny", **kwargs)


def test_tiny_model_generation_ids_seed_and_global_rng():
    """Generation stops on <|im_end|> (2) or <|endoftext|> (0) and pads with <|endoftext|>, as Qwen's Instruct
    generation config. The seed sets the weights, and building leaves the global torch RNG where it was."""
    model = build_tiny_model()
    gen = model.generation_config
    assert (gen.eos_token_id, gen.pad_token_id, gen.bos_token_id) == ([2, 0], 0, 0)
    assert not torch.equal(build_tiny_model(seed=1).lm_head.weight, model.lm_head.weight)
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    build_tiny_model(seed=7)
    assert torch.equal(torch.rand(3), expected)


def test_gradient_checkpointing_turns_the_kv_cache_off():
    """After `enable_gradient_checkpointing` a forward pass keeps no KV cache, in eval mode too (transformers only
    turns it off by itself while training); before, the text model's default (use_cache True) keeps one."""
    from aynamics.model import enable_gradient_checkpointing

    model = build_tiny_model()
    ids = torch.tensor([[1, 5, 7]])
    with torch.no_grad():
        assert model(input_ids=ids).past_key_values is not None
        enable_gradient_checkpointing(model)
        assert model.eval()(input_ids=ids).past_key_values is None


def test_generation_pads_with_the_text_configs_pad_id_even_when_it_is_0():
    """A pad id of 0 is an id, not a missing one (it fell through to bos, 5 here); none at all gives bos; a
    generation config's own pad id is kept."""
    from types import SimpleNamespace

    from aynamics.model import _default_pad_id

    def model(gen_pad, text_pad):
        text = SimpleNamespace(pad_token_id=text_pad, bos_token_id=5)
        return SimpleNamespace(
            generation_config=SimpleNamespace(pad_token_id=gen_pad), config=SimpleNamespace(text_config=text)
        )

    got = []
    for gen_pad, text_pad in ((None, 0), (None, None), (7, 0)):
        m = model(gen_pad, text_pad)
        _default_pad_id(m)
        got.append(m.generation_config.pad_token_id)
    assert got == [0, 5, 7]


def test_lora_scaling_and_trained_modules_that_cannot_work_are_named():
    """model.lora_alpha 0 (a LoRA that never moves: its gradients are scaled by alpha / r), negative or NaN (diverged
    at the first step), and a model.modules_to_save name no module has (peft trained nothing for it) were taken
    without a word; the spec refuses the first before the base loads."""
    from aynamics import lm

    for alpha in (0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=rf"model.lora_alpha = {alpha}: must be a finite number > 0"):
            lm.ModelSpec(kind="tiny", lora_alpha=alpha)
    with pytest.raises(ValueError, match=r"model.lora_rank = 2.5: must be a whole number >= 1"):
        lm.ModelSpec(kind="tiny", lora_rank=2.5)
    with pytest.raises(
        ValueError, match=r"modules_to_save = \['lm_head', 'lm_heads'\]: no module named \['lm_heads'\]"
    ):
        apply_lora(build_tiny_model(), modules_to_save=["lm_head", "lm_heads"])
    apply_lora(build_tiny_model(), modules_to_save=["embed_tokens", "lm_head"])  # the tiny config's: fine


def test_modules_to_save_names_that_peft_matches_are_taken():
    """peft trains every module whose name ends with a modules_to_save entry ("head": lm_head); such a name was
    refused as naming no module, though it trained lm_head before the check came."""
    model = apply_lora(build_tiny_model(), rank=4, modules_to_save=["head"])
    trained = {n for n, p in model.named_parameters() if p.requires_grad and "lora_" not in n}
    assert trained and all("lm_head" in n for n in trained)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("system_prompt", 5, "system_prompt = 5: must be a string"),  # TypeError in the prompt builder
        ("examples", [{"a": 1}], "examples: {'a': 1}: each must be a text"),  # AttributeError: no .strip
        ("examples", "- type: box", "examples = '- type: box': must be a list of example texts"),  # its characters
        ("clip_frames", [0.5, 1], "clip_frames = [0.5, 1]: must be increasing whole frame indices"),  # read [0, 1]
        ("clip_frames", None, "clip_frames = None: must be increasing whole frame indices"),  # 'not iterable'
        ("clip_frames", [True, 2], "clip_frames = [True, 2]: must be increasing whole frame indices"),
    ],
)
def test_an_adapters_prompt_spec_of_the_wrong_type_is_named(key, value, message):
    """A hand-edited aynamics.json whose prompt fields have the wrong type: named as its bad values are (predict
    printed a traceback for the first two and read the others as something else); training's own file loads back."""
    import json
    import re

    from aynamics import adapters, lm

    written = json.loads(json.dumps(adapters.adapter_meta(lm.ModelSpec(), lm.PromptSpec(examples=("- type: box",)))))
    assert adapters.specs_of_meta(written) == (lm.ModelSpec(), lm.PromptSpec(examples=("- type: box",)))
    written["prompt"][key] = value
    with pytest.raises(
        ValueError, match=re.escape(f"'a/aynamics.json': not the model and prompt specs training writes: {message}")
    ):
        adapters.specs_of_meta(written, where="'a/aynamics.json'")


def test_the_published_architectures_have_their_published_sizes():
    """`qwen_architecture_config` builds Qwen2.5-VL-3B and -7B as their model cards count them (3,754,622,976 and
    8,292,166,656 parameters; built on the meta device, nothing allocated), with Qwen's M-RoPE sections, windowed
    vision blocks but 7, 15, 23, 31, and the 3B's tied embeddings; shallower copies keep every width."""
    from transformers import AutoTokenizer, Qwen2_5_VLForConditionalGeneration

    from aynamics.model import qwen_architecture_config

    tokenizer = AutoTokenizer.from_pretrained(str(TINY_ASSET_DIR))
    for size, count, tied in (("3b", 3_754_622_976, True), ("7b", 8_292_166_656, False)):
        config = qwen_architecture_config(size, tokenizer)
        with torch.device("meta"):
            model = Qwen2_5_VLForConditionalGeneration._from_config(config, dtype=torch.bfloat16)
        assert sum(p.numel() for p in model.parameters()) == count
        assert (model.lm_head.weight is model.get_input_embeddings().weight) == tied
        assert config.text_config.rope_parameters["mrope_section"] == [16, 24, 24]
        assert config.vision_config.fullatt_block_indexes == [7, 15, 23, 31]
        assert config.image_token_id == tokenizer.convert_tokens_to_ids("<|image_pad|>")
    short = qwen_architecture_config("3b", tokenizer, text_layers=1, vision_depth=4)
    assert (short.text_config.num_hidden_layers, short.vision_config.depth) == (1, 4)
    assert short.vision_config.fullatt_block_indexes == [3] and short.text_config.hidden_size == 2048
    with pytest.raises(ValueError, match="size = '13b'"):
        qwen_architecture_config("13b", tokenizer)
    with pytest.raises(ValueError, match="text_layers = 0"):
        qwen_architecture_config("3b", tokenizer, text_layers=0)


# The published checkpoints' config.json fields that change what the model computes, besides the sizes above
# (Qwen/Qwen2.5-VL-3B-Instruct and -7B-Instruct: the same values in both)
PUBLISHED_TEXT = {"rms_norm_eps": 1e-6, "hidden_act": "silu", "max_position_embeddings": 128000}
PUBLISHED_VISION = {
    "hidden_act": "silu", "patch_size": 14, "spatial_merge_size": 2, "temporal_patch_size": 2, "window_size": 112,
    "tokens_per_second": 2, "in_channels": 3,
}  # fmt: skip


@pytest.mark.parametrize("size", ["3b", "7b"])
def test_the_published_architectures_compute_as_published(size):
    """Beyond the widths: the language model's RMSNorm eps is the checkpoints' 1e-6 in every norm (transformers'
    default is 1e-5), RoPE theta 1e6, SiLU, and the vision tower's patching, windows and video time step."""
    from transformers import AutoTokenizer, Qwen2_5_VLForConditionalGeneration

    from aynamics.model import qwen_architecture_config

    config = qwen_architecture_config(size, AutoTokenizer.from_pretrained(str(TINY_ASSET_DIR)), text_layers=1)
    assert {k: getattr(config.text_config, k) for k in PUBLISHED_TEXT} == PUBLISHED_TEXT
    assert {k: getattr(config.vision_config, k) for k in PUBLISHED_VISION} == PUBLISHED_VISION
    assert config.text_config.rope_parameters["rope_theta"] == 1_000_000.0
    with torch.device("meta"):
        model = Qwen2_5_VLForConditionalGeneration._from_config(config, dtype=torch.bfloat16)
    text_norms = [m for n, m in model.named_modules() if "language_model" in n and hasattr(m, "variance_epsilon")]
    assert len(text_norms) == 3 and {m.variance_epsilon for m in text_norms} == {1e-6}  # 2 in the layer, the last
