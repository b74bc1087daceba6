"""The PRO stage: the gradient favours better-scored candidates, pairs, offline data, and `train.py stage=pro`."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from PIL import Image
from train_fixtures import run_two_processes, tiny_dataset

from aynamics import adapters, lm
from aynamics import reward as rw
from aynamics.cli import main as cli_main
from aynamics.preference_data import (
    SamplingProgress,
    build_preferences,
    load_preferences,
    select_pairs,
    write_preferences,
)
from aynamics.pro import ProModule
from aynamics.processor import load_processor, response_ids
from aynamics.scene import dump, parse
from aynamics.scorer import Score
from aynamics.unlabeled import GeneratedVideos, UnlabeledVideo

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from train import train  # noqa: E402

FAST = [
    "model=tiny",
    "logger=none",
    "data.num_frames=2",
    "data.limit_val=1",
    "data.use_flow=false",
    "stage.num_samples=2",
    "stage.module.max_new_tokens=12",
    "trainer.max_steps=2",
    "trainer.val_check_interval=2",
]
PROMPT = lm.PromptSpec(num_frames=2, min_pixels=3136, max_pixels=3136)
SPEC = lm.ModelSpec(kind="tiny", lora_rank=8, lora_alpha=16.0, lora_dropout=0.0)


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return tiny_dataset(tmp_path_factory)


def _cfg(out: Path, *overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=[f"output_dir={out}", "stage=pro", *FAST, *overrides])


def test_select_pairs_hand_worked():
    """Rewards [0.2, 0.9, 0.0, 0.5]: order 1, 3, 0, 2 -> (1 best, 2 worst), (3, 0); a third pair does not exist."""
    assert select_pairs([0.2, 0.9, 0.0, 0.5], 3) == [(1, 2), (3, 0)]
    assert select_pairs([0.0] * 32, 3) == []  # all tied (e.g. all invalid): no preference
    assert select_pairs([0.5, 0.5, 0.1, 0.5], 2) == [(0, 2)]  # the runners-up tie: no second pair
    r = list(np.linspace(0, 1, 32))
    assert select_pairs(r, 3) == [(31, 0), (30, 1), (29, 2)]  # the paper: three pairs from 32 samples
    with pytest.raises(ValueError, match="pairs = 0"):
        select_pairs(r, 0)


def _first_moved(scene, dx: float):
    """The scene with its first object `dx` m further along x."""
    o = scene.objects[0]
    state = o.state.model_copy(update={"position": (o.state.position[0] + dx, *o.state.position[1:])})
    return scene.model_copy(update={"objects": (o.model_copy(update={"state": state}), *scene.objects[1:])})


def _fixed_candidates(module: ProModule, dataset_dir: Path):
    videos = GeneratedVideos(dataset_dir, "train", use_flow=False, limit=2)
    texts = ["- type: box\n  mass: 1.0", "- type: sphere\n  radius: 0.2", "camera: 45", "gravity: [0, 0, -9.81]"]
    ids = [[response_ids(module.processor, t) for t in texts]] * len(videos)
    prompts = module.prompts([v.frames for v in videos])
    rewards = torch.tensor([[0.9, 0.5, 0.2, 0.0], [0.8, 0.0, 0.6, 0.3]])  # best 0; worst 3 and 1
    return prompts, ids, rewards


@pytest.mark.parametrize("loss", ["soft", "ranking"])
def test_gradient_moves_probability_toward_better_candidates(dataset_dir, loss):
    """A few AdamW steps on fixed candidates: ℓ(best-scored) - ℓ(worst-scored) rises in both videos, for the
    soft objective (τ = 0.1) and the hard-ranking PRO loss; only trainable weights change."""
    module = ProModule(SPEC, prompt=PROMPT, loss=loss, tau=0.1, lr=5e-3, num_samples=4)
    module.ensure_processor()
    prompts, ids, rewards = _fixed_candidates(module, dataset_dir)
    frozen = {n: p.detach().clone() for n, p in module.model.named_parameters() if not p.requires_grad}
    start = {n: p.detach().clone() for n, p in module.model.named_parameters() if p.requires_grad}
    opt = module.configure_optimizers()
    margins, rows = [], torch.arange(2)
    for _ in range(4):
        loss_value, seq = module.preference_loss(prompts, ids, rewards)
        margins.append((seq[:, 0] - seq[rows, rewards.argmin(1)]).detach())  # ℓ(best) - ℓ(worst) per video
        opt.zero_grad()
        loss_value.backward()
        opt.step()
    assert torch.all(margins[-1] > margins[0] + 0.05), margins
    assert all(torch.equal(frozen[n], p) for n, p in module.model.named_parameters() if not p.requires_grad)
    assert all(not torch.equal(start[n], p) for n, p in module.model.named_parameters() if p.requires_grad)


def test_all_tied_rewards_give_a_zero_loss_that_keeps_the_graph(dataset_dir):
    module = ProModule(SPEC, prompt=PROMPT, num_samples=4)
    module.ensure_processor()
    prompts, ids, _ = _fixed_candidates(module, dataset_dir)
    loss, seq = module.preference_loss(prompts, ids, torch.zeros(2, 4))
    assert loss.item() == 0.0 and loss.requires_grad and seq.shape == (2, 4)
    loss.backward()  # every trainable parameter is reached (DDP needs it), with a zero gradient
    grads = [p.grad for p in module.model.parameters() if p.requires_grad]
    assert grads and all(g is not None and not g.any() for g in grads)


def test_sequence_scores_are_length_normalised_per_candidate(dataset_dir):
    """Each candidate's sequence score in the padded B x N batch is its mean token log-probability computed alone
    (candidates of 7, 13, 13 and 17 tokens here: a sum would differ by their lengths), from the logits of the
    last longest + 1 positions only."""
    from aynamics.batching import model_inputs
    from aynamics.logprobs import mean_token_logprob

    module = ProModule(SPEC, prompt=PROMPT, num_samples=4).eval()
    module.ensure_processor()
    prompts, ids, rewards = _fixed_candidates(module, dataset_dir)
    assert len({len(c) for c in ids[0]}) > 2
    pad = module.processor.tokenizer.pad_token_id
    shapes = []
    hook = module.model.register_forward_hook(lambda m, args, out: shapes.append(tuple(out.logits.shape)))
    with torch.no_grad():
        _, seq = module.preference_loss(prompts, ids, rewards)
    hook.remove()
    longest = max(len(c) for row in ids for c in row)
    assert shapes[0][:2] == (8, longest + 1)  # only the positions that predict candidate tokens (logits_to_keep)
    with torch.no_grad():
        for b, n in [(0, 0), (0, 3), (1, 1)]:
            one = rw.candidate_batch([prompts[b]], [[ids[b][n]]], pad, forbidden=rw.vision_token_ids(module.model))
            alone = mean_token_logprob(module.model(**model_inputs(one)).logits, one["labels"])[0]
            assert seq[b, n].item() == pytest.approx(alone.item(), abs=1e-4), (b, n)


def test_margin_and_best_by_hand():
    """Margin: row 0 best-scored (0.9, ℓ 1) minus worst (0.1, ℓ 0) = 1, row 1 tied = 0: mean 0.5. Rewards
    [[0.2, 0.6], [0.9, 0.1]]: mean 0.45, best = mean of each video's best (0.6 + 0.9) / 2 = 0.75, not the
    batch's 0.9."""
    from aynamics.pro import _margin
    from aynamics.scorer import Score

    seq = torch.tensor([[0.0, 1.0, 2.0], [5.0, 4.0, 3.0]])
    assert _margin(seq, torch.tensor([[0.1, 0.9, 0.5], [0.3, 0.3, 0.3]])).item() == pytest.approx(0.5)
    assert _margin(seq, torch.tensor([[0.9, 0.1, 0.5], [0.1, 0.2, 0.9]])).item() == pytest.approx((-1 - 2) / 2)
    ok = Score(0.5, 0.5, None, None, True)
    stats = rw.RewardStats.of(torch.tensor([[0.2, 0.6], [0.9, 0.1]]), [[ok, ok], [ok, ok]])
    assert (stats.mean, stats.best, stats.invalid) == pytest.approx((0.45, 0.75, 0.0))


def test_build_preferences_pairs_each_videos_own_candidates(dataset_dir, monkeypatch):
    """Two videos sampled together (batch_size 2), 4 candidates each, sampling swapped for fixed ones: video 0's
    rewards all tie (no pair), video 1's [0.2, 0.9, 0.0, 0.5] give (1 best, 2 worst) and (3, 0), each row holding
    video 1's own texts, ids and rewards in (chosen, rejected) order."""
    from aynamics.preference_data import build_preferences
    from aynamics.scorer import Score

    module = ProModule(SPEC, prompt=PROMPT, num_samples=4)
    module.ensure_processor()
    videos = GeneratedVideos(dataset_dir, "train", use_flow=False, limit=2)
    texts = [[f"video {b} candidate {n}" for n in range(4)] for b in range(2)]
    rewards = torch.tensor([[0.3, 0.3, 0.3, 0.3], [0.2, 0.9, 0.0, 0.5]])

    def fixed(chunk, num_samples, temperature):
        assert len(chunk) == 2 and num_samples == 4
        ids = [[response_ids(module.processor, t) for t in row] for row in texts]
        scores = [[Score(float(r), float(r), None, None, True) for r in row] for row in rewards]
        return module.prompts([v.frames for v in chunk]), ids, scores, rewards

    monkeypatch.setattr(module, "sample_and_score", fixed)
    rows, summary = build_preferences(module, [videos[0], videos[1]], num_samples=4, pairs=3, batch_size=2)
    assert [r["key"] for r in rows] == [videos[1].key] * 2
    assert [r["completions"] for r in rows] == [[texts[1][1], texts[1][2]], [texts[1][3], texts[1][0]]]
    assert [r["rewards"] for r in rows] == [pytest.approx([0.9, 0.0]), pytest.approx([0.5, 0.2])]
    assert rows[0]["completion_ids"] == [response_ids(module.processor, texts[1][k]) for k in (1, 2)]
    assert [r["case_rewards"] for r in rows] == [pytest.approx([0.2, 0.9, 0.0, 0.5])] * 2  # all 4 of video 1
    assert (summary["pairs"], summary["videos_without_pairs"]) == (2, 1)
    with pytest.raises(ValueError, match="temperature = nan.*a finite temperature > 0"):  # was transformers' error
        build_preferences(module, [videos[0]], num_samples=4, temperature=float("nan"))


def test_preference_arguments_and_stored_sets_are_checked(tmp_path, dataset_dir, capsys):
    """Sampling needs 2 candidates a video (1 gives no pair) and 1 video a batch, refused before any sampling (no
    module needed); a stored set without the preference columns, or whose summary.json has half a clock, is named
    or read as clockless; `aynamics preferences --limit 0` is refused, and `--split test` samples the 3 test videos
    of the tiny data set (12 scenes split 6 / 3 / 3), not the 6 training ones."""
    import datasets

    from aynamics.preference_data import build_preferences, stored_clock

    for kwargs, named in (({"num_samples": 1}, "num_samples = 1"), ({"batch_size": 0}, "batch_size = 0")):
        with pytest.raises(ValueError, match=named):
            build_preferences(None, [], **kwargs)
    datasets.Dataset.from_dict({"key": ["a"], "rewards": [[1.0, 0.0]]}).save_to_disk(str(tmp_path / "other"))
    with pytest.raises(ValueError, match=r"columns \['frames', 'completions', 'completion_ids', 'reasons', 'case_re"):
        load_preferences(tmp_path / "other")
    (tmp_path / "other" / "summary.json").write_text(json.dumps({"clock": {"fps": 15.0}}))
    assert stored_clock(tmp_path / "other") is None
    (tmp_path / "other" / "summary.json").write_text(json.dumps({"clock": {"fps": 15, "clip_frames": [0, 3]}}))
    assert stored_clock(tmp_path / "other") == {"fps": 15.0, "clip_frames": (0, 3)}
    args = ["preferences", "--data", str(dataset_dir), "--num-samples", "2", "--max-new-tokens", "3"]
    assert cli_main([*args, "--out", str(tmp_path / "p"), "--limit", "0"]) == 2
    assert "preferences: --limit 0: must be >= 1" in capsys.readouterr().err and not (tmp_path / "p").exists()
    assert cli_main([*args, "--out", str(tmp_path / "p"), "--split", "test", "--device", "cpu"]) == 0
    assert json.loads(capsys.readouterr().out)["videos"] == 3
    assert len(GeneratedVideos(dataset_dir, "test", use_flow=False, limit=100)) == 3  # all there are


def test_online_pro_scores_logs_and_prefers_fixed_candidates(tmp_path, dataset_dir, monkeypatch):
    """`train.py stage=pro` with the sampler swapped for two fixed candidates of training video 0 (its true scene
    and the scene with its first object 0.5 m off along x): the logged reward mean / best and the validation's
    greedy, Best@1 and Best@N IoU are those candidates' scores, computed here independently, and the loss is > 0
    (that it moves probability toward the better one: `test_gradient_moves_probability_toward_better_candidates`).
    With stage.reward_metric=epe and data.use_flow=false the run stops at setup, naming both keys."""
    from datasets import load_from_disk

    scene = parse(load_from_disk(str(dataset_dir))["train"][0]["scene_yaml"])
    texts = [dump(scene), dump(_first_moved(scene, 0.5))]
    video = GeneratedVideos(dataset_dir, "train", use_flow=False, limit=1)[0]
    r = rw.rewards_of(rw.score_completions([texts], [video.observation]))[0].tolist()
    assert r[0] > 0.9 and r[0] - r[1] > 0.2  # the true scene scores (nearly) 1, the moved one clearly less

    def fixed(model, processor, prompts, *, num_samples, **kw):
        chosen = texts[:num_samples]
        return [[response_ids(processor, t) for t in chosen] for _ in prompts], [list(chosen) for _ in prompts]

    monkeypatch.setattr(rw, "sample_completions", fixed)
    common = [f"data.dir={dataset_dir}", "data.limit_train=1", "data.val_split=train", "stage.module.lr=5e-3"]
    metrics = train(_cfg(tmp_path / "run", *common, "trainer.max_steps=4", "trainer.val_check_interval=4"))
    assert metrics["reward/mean"] == pytest.approx(sum(r) / 2, abs=1e-6)
    assert metrics["reward/best"] == pytest.approx(r[0], abs=1e-6) and metrics["reward/invalid"] == 0.0
    assert metrics["val/greedy/iou_full"] == pytest.approx(r[0], abs=1e-6)  # greedy: the first candidate
    assert metrics["val/best1/iou_full"] == pytest.approx(sum(r) / 2, abs=1e-6)
    assert metrics["val/bestN/iou_full"] == pytest.approx(r[0], abs=1e-6)
    assert metrics["train/loss"] > 0 and metrics["train/informative"] == 1.0
    with pytest.raises(ValueError, match="reward_metric = 'epe'.*data.use_flow = false"):
        train(_cfg(tmp_path / "epe", *common, "stage.module.reward_metric=epe"))


def test_module_arguments_are_checked():
    for kw, match in [
        ({"mode": "both"}, "stage.mode = 'both'"),
        ({"loss": "dpo"}, "stage.module.loss = 'dpo'"),
        ({"num_samples": 1}, "num_samples = 1"),
        ({"reward_metric": "ssim"}, "'ssim'"),
        ({"lr": float("nan")}, "lr = nan"),
        ({"tau": float("inf")}, "tau = inf"),
    ]:
        with pytest.raises(ValueError, match=match):
            ProModule(SPEC, **kw)
    with pytest.raises(FileNotFoundError, match="no adapter_config.json"):
        ProModule(SPEC, init_adapter="/nonexistent/adapter")


def test_sampling_settings_that_cannot_sample_are_refused_before_the_model_loads(monkeypatch):
    """stage.temperature 0 or NaN, top_p 0, max_new_tokens 0 and score_workers 0 failed only at the first training
    step, once the model had loaded (NaN with transformers' traceback on greedy decoding)."""
    import aynamics.pro

    def no_model(*args, **kwargs):
        raise AssertionError("the model was built")

    monkeypatch.setattr(aynamics.pro, "build_policy", no_model)
    for kw, match in [
        ({"temperature": 0.0}, r"stage.temperature = 0.0: must be a finite number > 0"),
        ({"temperature": float("nan")}, r"stage.temperature = nan: must be a finite number > 0"),
        ({"top_p": 0.0}, r"stage.module.top_p = 0.0: must be in \(0, 1\]"),
        ({"max_new_tokens": 0}, r"stage.module.max_new_tokens = 0, .*: both must be >= 1"),
        ({"score_workers": 0}, r"stage.module.score_workers = 0: both must be >= 1"),
    ]:
        with pytest.raises(ValueError, match=match):
            ProModule(SPEC, num_samples=2, **kw)
    with pytest.raises(ValueError, match="temperature = nan"):
        rw.sample_completions(None, None, [], num_samples=1, temperature=float("nan"))


def _no_device_guess(monkeypatch) -> None:
    """peft reads an adapter onto `infer_device()` (the first GPU of a GPU machine: a CUDA context there from every
    process, and for --device cpu) unless told where: make a guess fail loudly."""
    import peft.peft_model
    import peft.utils.save_and_load

    def guess():
        raise AssertionError("peft chose the device the adapter is read onto")

    monkeypatch.setattr(peft.peft_model, "infer_device", guess)
    monkeypatch.setattr(peft.utils.save_and_load, "infer_device", guess)


def test_policy_from_an_adapter_is_trained_with_the_runs_settings(tmp_path, monkeypatch):
    """An SFT adapter saved without checkpointing and dropout, loaded by a PRO run that asks for both (and names
    another LoRA rank): checkpointing is on in the decoder and vision blocks and the LoRA dropout is the run's (both
    were the adapter's before: helper-37), the rank stays the adapter's and the run's is named as ignored; in eval
    mode the policy gives the adapter's outputs. The adapter is read onto the CPU, beside its base, by PRO and by
    `adapters.load_adapter` (predict, evaluate), never onto peft's guess (the first GPU, from every rank)."""
    from aynamics.pro import build_policy

    saved = lm.build_model(SPEC).eval()
    adapters.save_adapter(saved, tmp_path / "adapter", SPEC, lm.PromptSpec(num_frames=2))
    _no_device_guess(monkeypatch)
    adapters.load_adapter(tmp_path / "adapter", "cpu")
    run = dataclasses.replace(SPEC, lora_rank=4, lora_dropout=0.3, gradient_checkpointing=True)
    with pytest.warns(UserWarning, match=r"model.lora_rank = 4 \(the adapter's: 8\) ignored"):
        policy, used = build_policy(run, str(tmp_path / "adapter"))
    assert (used.lora_rank, used.lora_dropout, used.gradient_checkpointing) == (8, 0.3, True)
    checkpointed = {type(m).__name__ for m in policy.modules() if getattr(m, "gradient_checkpointing", False) is True}
    assert {"Qwen2_5_VLDecoderLayer", "Qwen2_5_VLVisionBlock"} <= checkpointed
    drops = [m.lora_dropout["default"] for m in policy.modules() if hasattr(m, "lora_dropout")]
    assert drops and all(isinstance(d, torch.nn.Dropout) and d.p == 0.3 for d in drops)
    assert all(m.r["default"] == 8 for m in policy.modules() if hasattr(m, "lora_dropout"))
    ids = torch.tensor([[1, 2, 3, 4]])
    with torch.no_grad():
        torch.testing.assert_close(policy.eval()(input_ids=ids).logits, saved(input_ids=ids).logits)


def test_train_stage_pro_online_end_to_end(tmp_path, dataset_dir):
    """`train.py stage=pro` on the tiny model: mostly invalid samples never crash a step; reward statistics and
    the Table 10 modes are logged; the checkpoint holds only trainable weights; the adapter restarts a run."""
    out = tmp_path / "run"
    metrics = train(_cfg(out, f"data.dir={dataset_dir}"))
    for key in ("reward/mean", "reward/best", "reward/invalid", "train/loss", "val/greedy/iou_full"):
        assert key in metrics, sorted(metrics)
    assert 0.0 <= metrics["reward/invalid"] <= 1.0
    assert {"val/best1/iou_first", "val/bestN/iou_full", "val/iou_full"} <= set(metrics)
    record = json.loads((out / "metrics.json").read_text())
    assert record["global_step"] == 2
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)
    module = ProModule(lm.ModelSpec(**ckpt["hyper_parameters"]["spec"]), init_adapter=str(out / "adapter"))
    trainable = {f"model.{n}" for n, p in module.model.named_parameters() if p.requires_grad}
    assert set(ckpt["state_dict"]) == trainable
    for k, v in ckpt["state_dict"].items():  # the exported adapter is the checkpoint's weights
        assert torch.equal(module.state_dict()[k], v), k
    # starting from the adapter (as from an SFT one) composes and trains
    again = train(_cfg(tmp_path / "again", f"data.dir={dataset_dir}", f"stage.init_adapter={out / 'adapter'}"))
    assert "reward/mean" in again
    with pytest.raises(ValueError, match="modality='rgb'"):
        train(
            _cfg(
                tmp_path / "bad",
                f"data.dir={dataset_dir}",
                f"stage.init_adapter={out / 'adapter'}",
                "data.modality=flow",
            )
        )
    # the frames' pixel limits are part of the prompt too (other limits: other visual tokens than in training)
    with pytest.raises(ValueError, match="trained with max_pixels=None, but the data are set to data.max_pixels=5000"):
        train(
            _cfg(
                tmp_path / "bad2",
                f"data.dir={dataset_dir}",
                f"stage.init_adapter={out / 'adapter'}",
                "data.max_pixels=5000",
            )
        )


def summary_keys(summary: dict, **prompt) -> dict:
    """The command's record of what it sampled under, with `prompt` keys changed."""
    return {"prompt": summary["prompt"] | prompt, "tokenizer": summary["tokenizer"]}


def _handmade_preferences(dataset_dir: Path, out: Path) -> Path:
    """Two pairs (true scene vs the scene moved 0.5 m) on two training videos, scored by the real reward."""
    import datasets

    split = datasets.load_from_disk(str(dataset_dir))["train"]
    rows = []
    for k in range(2):
        rec = split[k]
        scene = parse(rec["scene_yaml"])
        texts = [f"<answer>\n{rec['scene_yaml']}</answer>", f"<answer>\n{dump(_first_moved(scene, 0.5))}</answer>"]
        videos = GeneratedVideos(dataset_dir, "train", use_flow=False, limit=2)
        r = rw.simulator_rewards(texts, [videos[k].observation] * 2)
        assert r[0] > r[1]
        proc = load_processor(lm.ModelSpec().processor_path)
        rows.append(
            {
                "key": str(k),
                "frames": list(rec["rgb"]),
                "completions": texts,
                "completion_ids": [response_ids(proc, t) for t in texts],
                "rewards": r,
                "reasons": [None, None],
                "case_rewards": r,
            }
        )
    return write_preferences(rows, {"pairs": 2}, out)


def test_preferences_never_replace_another_folder(tmp_path, dataset_dir, capsys):
    """--out may be new or a preference set written before; anything else (the data set itself, a folder of
    the user's) is refused before sampling, and, if it appeared while sampling, the preferences are kept beside."""
    before = sorted(p.name for p in dataset_dir.iterdir())
    args = ["preferences", "--data", str(dataset_dir), "--num-samples", "2", "--max-new-tokens", "4", "--limit", "1"]
    assert cli_main(args + ["--out", str(dataset_dir)]) == 2
    assert "is not a preference data set (no summary.json): refusing to replace it" in capsys.readouterr().err
    assert sorted(p.name for p in dataset_dir.iterdir()) == before  # untouched

    first = _handmade_preferences(dataset_dir, tmp_path / "prefs")
    assert _handmade_preferences(dataset_dir, tmp_path / "prefs") == first  # a preference set is replaced
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    with pytest.raises(ValueError, match="preferences are kept in") as err:
        _handmade_preferences(dataset_dir, mine)
    assert (mine / "notes.txt").read_text() == "keep"
    (kept,) = tmp_path.glob(".mine.tmp-*")
    assert str(kept) in str(err.value) and (kept / "summary.json").is_file()


def test_preferences_leave_a_folder_named_like_their_temporary_one(tmp_path, dataset_dir):
    """Writing --out prefs never deletes a folder of the user's called prefs.tmp (it did: a fixed scratch name)."""
    (tmp_path / "prefs.tmp").mkdir()
    (tmp_path / "prefs.tmp" / "keep.txt").write_text("keep")
    _handmade_preferences(dataset_dir, tmp_path / "prefs")
    assert (tmp_path / "prefs.tmp" / "keep.txt").read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prefs", "prefs.tmp"]


def test_preferences_with_a_model_folder_that_holds_no_checkpoint_is_one_line(tmp_path, dataset_dir, capsys):
    """--model naming a folder without weights is a usage error (status 2, one line), not a traceback."""
    (tmp_path / "empty").mkdir()
    args = ["preferences", "--data", str(dataset_dir), "--out", str(tmp_path / "p"), "--model", str(tmp_path / "empty")]
    assert cli_main([*args, "--num-samples", "2", "--limit", "1", "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert f"model path {str(tmp_path / 'empty')!r}: cannot load the model" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "p").exists()


def test_preferences_command_and_offline_training(tmp_path, dataset_dir, capsys):
    """`aynamics preferences` samples, scores and stores (the tiny model's samples tie at 0: no pairs); hand-made
    pairs of real scenes scored by the real reward train the offline stage."""
    code = cli_main(
        ["preferences", "--data", str(dataset_dir), "--out", str(tmp_path / "prefs"), "--num-samples", "2"]
        + ["--max-new-tokens", "8", "--limit", "2", "--temperature", "1.0"]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["videos"] == 2 and summary["pairs"] + summary["videos_without_pairs"] >= 2
    assert (tmp_path / "prefs" / "summary.json").is_file()
    assert cli_main(["preferences", "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "x")]) == 2
    assert f"video folder '{tmp_path / 'nope'}' does not exist" in capsys.readouterr().err

    _handmade_preferences(dataset_dir, tmp_path / "handmade")
    assert len(load_preferences(tmp_path / "handmade")) == 2
    metrics = train(
        _cfg(
            tmp_path / "offline",
            f"data.dir={dataset_dir}",
            "stage.mode=offline",
            f"stage.preferences_dir={tmp_path / 'handmade'}",
            "+trainer.limit_val_batches=0",
        )
    )
    assert metrics["train/loss"] > 0 and "train/margin" in metrics and "reward/mean" not in metrics
    with pytest.raises(ValueError, match="offline mode trains on a stored preference data set"):
        train(_cfg(tmp_path / "mismatch", f"data.dir={dataset_dir}", "stage.mode=offline"))
    # stored data say what they were sampled under: the command's 4 frames are not these runs' 2, and token ids of
    # another vocabulary are refused
    assert summary["prompt"]["num_frames"] == 4 and len(summary["tokenizer"]) == 16
    offline = ["stage.mode=offline", "+trainer.limit_val_batches=0", f"data.dir={dataset_dir}"]
    assert summary["pairs"] == 0  # 8 tokens of a random model never hold a scene: every candidate scores 0
    with pytest.raises(ValueError, match="hold 0 pairs"):  # loading an empty set raised IndexError in `datasets`
        load_preferences(tmp_path / "prefs")
    stored = json.loads((tmp_path / "handmade" / "summary.json").read_text())
    (tmp_path / "handmade" / "summary.json").write_text(json.dumps(stored | summary_keys(summary, num_frames=4)))
    with pytest.raises(ValueError, match="sampled with num_frames=4, but the data are set to data.num_frames=2"):
        train(_cfg(tmp_path / "frames", *offline, f"stage.preferences_dir={tmp_path / 'handmade'}"))
    (tmp_path / "handmade" / "summary.json").write_text(json.dumps(stored | {"tokenizer": "0" * 16}))
    with pytest.raises(ValueError, match="token ids of another tokenizer"):
        train(_cfg(tmp_path / "vocab", *offline, f"stage.preferences_dir={tmp_path / 'handmade'}"))


def test_pro_resume_continues_exactly(tmp_path, dataset_dir):
    """Offline PRO on two stored pairs with LoRA dropout (its masks draw from the random state, as online
    sampling does): resumed from the step-2 checkpoint, step 3 ends on the straight run's adapter, bit for bit
    (the random states are in the checkpoint; without them the resumed run drew other masks). So does a run
    stopped by SIGTERM during step 1, resumed from the step-1 checkpoint that the signal saved."""
    from safetensors.torch import load_file

    prefs = _handmade_preferences(dataset_dir, tmp_path / "prefs")
    three = [f"data.dir={dataset_dir}", "stage.mode=offline", f"stage.preferences_dir={prefs}"]
    three += ["trainer.max_steps=3", "trainer.val_check_interval=3", "callbacks.checkpoint.every_n_train_steps=2"]
    three += ["model.lora_dropout=0.3"]
    train(_cfg(tmp_path / "straight", *three))
    step2 = tmp_path / "straight" / "checkpoints" / "step000002.ckpt"
    train(_cfg(tmp_path / "resumed", *three, f"ckpt_path={step2}"))
    straight = load_file(tmp_path / "straight" / "adapter" / "adapter_model.safetensors")
    resumed = load_file(tmp_path / "resumed" / "adapter" / "adapter_model.safetensors")
    at_step2 = torch.load(step2, weights_only=True)["state_dict"]
    b = next(k for k in straight if "lora_B" in k)
    assert not torch.equal(straight[b], at_step2["model." + b.replace(".weight", ".default.weight")])  # step 3 moved
    assert set(straight) == set(resumed) and all(torch.equal(straight[k], resumed[k]) for k in straight)
    # SIGTERM during step 1 (off the cadence): step 1 is saved and the run stops; resumed, it ends the same
    sigterm = ["+callbacks.sigterm._target_=train_fixtures.SigtermAt", "+callbacks.sigterm.step=1"]
    with pytest.raises(SystemExit):  # Lightning's SIGTERMException
        train(_cfg(tmp_path / "stopped", *three, *sigterm))
    last = tmp_path / "stopped" / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False)["global_step"] == 1
    train(_cfg(tmp_path / "after_sigterm", *three, f"ckpt_path={last}"))
    resumed = load_file(tmp_path / "after_sigterm" / "adapter" / "adapter_model.safetensors")
    assert set(straight) == set(resumed) and all(torch.equal(straight[k], resumed[k]) for k in straight)
    # a NaN gradient in step 2 stops the run there, before the optimizer writes it into the weights
    nan = ["+callbacks.nan._target_=train_fixtures.NanGradientAt", "+callbacks.nan.step=2"]
    with pytest.raises(FloatingPointError, match="the gradient norm is nan at step 2"):
        train(_cfg(tmp_path / "nan", *three, *nan))


def _two_processes(out: Path, trainer: str, *overrides: str) -> dict:
    cmd = [sys.executable, "train.py", "stage=pro", f"trainer={trainer}", "trainer.accelerator=cpu"]
    cmd += ["trainer.devices=2", f"hydra.run.dir={out}", *FAST, "trainer.enable_progress_bar=false", *overrides]
    if trainer == "ddp":  # ddp.yaml is for GPUs (bf16-mixed); float32 on the CPU
        cmd.append("trainer.precision=32-true")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    done = run_two_processes(cmd, out, cwd=ROOT, capture_output=True, text=True, timeout=900, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
def test_ddp_two_processes_offline_on_cpu(tmp_path, dataset_dir):
    """Two CPU ranks (gloo), one stored pair each: the loss is not zero, so gradients really synchronise.
    trainer=fsdp (FSDP2, aynamics.sharding) gives the same adapter, also from that adapter as `init_adapter`
    (which only rank 0 loads onto its base: rank 1 takes rank 0's weights); online, its ranks sample responses
    of different lengths together (`synced_gpus`) and its first step samples before any forward."""
    from safetensors.torch import load_file

    prefs = _handmade_preferences(dataset_dir, tmp_path / "prefs")
    offline = [f"data.dir={dataset_dir}", "stage.mode=offline", f"stage.preferences_dir={prefs}"]
    record = _two_processes(tmp_path / "ddp", "ddp", *offline)
    assert record["global_step"] == 2 and record["metrics"]["train/loss"] > 0
    sharded = _two_processes(tmp_path / "fsdp", "fsdp", *offline)
    assert sharded["metrics"]["train/loss"] == pytest.approx(record["metrics"]["train/loss"], rel=1e-3)
    a = load_file(tmp_path / "ddp" / "adapter" / "adapter_model.safetensors")
    b = load_file(tmp_path / "fsdp" / "adapter" / "adapter_model.safetensors")
    # an entry whose true gradient is 0 carries float noise that Adam scales to ±lr (1e-4) a step: 2 steps apart
    # at most 4e-4 (see tests/test_train.py::test_fsdp_matches_ddp_and_resumes_exactly)
    assert set(a) == set(b) and all(torch.allclose(a[k], b[k], atol=4.5e-4) for k in a)
    init = [*offline, f"stage.init_adapter={tmp_path / 'ddp' / 'adapter'}"]
    for strategy in ("ddp", "fsdp"):
        _two_processes(tmp_path / f"{strategy}_init", strategy, *init)
    a = load_file(tmp_path / "ddp_init" / "adapter" / "adapter_model.safetensors")
    b = load_file(tmp_path / "fsdp_init" / "adapter" / "adapter_model.safetensors")
    assert set(a) == set(b) and all(torch.allclose(a[k], b[k], atol=4.5e-4) for k in a)
    online = _two_processes(tmp_path / "online", "fsdp", f"data.dir={dataset_dir}")
    assert online["global_step"] == 2 and "val/greedy/iou_full" in online["metrics"]


def test_pro_loader_shards_over_the_trainers_ranks(dataset_dir):
    """Under a 2-process trainer each rank samples its own videos (the same loader for every rank did N times the
    work of one), and a resumed run continues past its first batch; validation videos are shared out too."""
    from types import SimpleNamespace

    from aynamics.pro_datamodule import ProDataModule
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    dm = ProDataModule(str(dataset_dir), str(TINY_ASSET_DIR), batch_size=1, num_frames=2)
    dm.setup("fit")

    def keys(rank: int, step: int = 0) -> list:
        dm.trainer = SimpleNamespace(global_rank=rank, world_size=2, global_step=step, accumulate_grad_batches=1)
        return [batch[0].key for batch in dm.train_dataloader()]

    r0, r1 = keys(0), keys(1)
    n = len(dm.train_set)
    assert len(r0) == len(r1) == -(-n // 2) and set(r0) | set(r1) == {v.key for v in dm.train_set}
    assert len(set(r0) & set(r1)) <= 1  # at most the one padding video, as DDP pads
    assert keys(0, step=1) == r0[1:] and keys(1, step=1) == r1[1:]
    from aynamics.data import eval_shard

    n_val = len(dm.val_set)
    assert n_val >= 2
    dm.trainer = SimpleNamespace(global_rank=1, world_size=2)  # validation videos: this process's share too
    assert list(dm.val_dataloader().sampler) == (eval_shard(n_val, dm.trainer) or list(range(n_val)))


def _video_folder(root, value: int) -> None:
    """A 30-frame video folder (frames/*.png, segmentation.npy) of 16×16 pixels, every frame of colour `value`."""
    import numpy as np
    from PIL import Image

    (root / "frames").mkdir(parents=True)
    seg = np.full((30, 16, 16), -1, np.int16)
    seg[:, 4:8, 4:8] = 0
    np.save(root / "segmentation.npy", seg)
    for k in range(30):
        Image.fromarray(np.full((16, 16, 3), value, np.uint8)).save(root / "frames" / f"{k:03d}.png")


def test_folder_videos_validate_on_val_dir_or_say_they_do_not(tmp_path):
    """A folder of video folders has no splits: with data.val_dir, validation reads those held-out videos; without,
    it scores the first training videos, as before, but now says so."""
    from aynamics.pro_datamodule import ProDataModule
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    for name, value in (("a", 10), ("b", 20)):
        _video_folder(tmp_path / "train" / name, value)
    _video_folder(tmp_path / "held_out" / "c", 30)
    kw = {"batch_size": 1, "num_frames": 2, "use_flow": False}
    dm = ProDataModule(str(tmp_path / "train"), str(TINY_ASSET_DIR), val_dir=str(tmp_path / "held_out"), **kw)
    dm.setup("fit")
    assert [v.frames[0].getpixel((0, 0)) for v in dm.val_set] == [(30, 30, 30)]
    dm = ProDataModule(str(tmp_path / "train"), str(TINY_ASSET_DIR), **kw)
    with pytest.warns(UserWarning, match="PRO validation scores the first training videos"):
        dm.setup("fit")
    assert [v.frames[0].getpixel((0, 0)) for v in dm.val_set] == [(10, 10, 10), (20, 20, 20)]
    (tmp_path / "empty").mkdir()
    dm = ProDataModule(str(tmp_path / "train"), str(TINY_ASSET_DIR), val_dir=str(tmp_path / "empty"), **kw)
    with pytest.raises(FileNotFoundError, match="empty"):
        dm.setup("fit")
    _flow_logged_keys(tmp_path, kw)
    sorted((tmp_path / "held_out" / "c" / "frames").iterdir())[5].unlink()  # the reason, not "holds no videos"
    dm = ProDataModule(str(tmp_path / "train"), str(TINY_ASSET_DIR), val_dir=str(tmp_path / "held_out"), **kw)
    with pytest.raises(ValueError, match=r"frames': 29 images; need one for every video frame \(30"):
        dm.setup("fit")


def _flow_logged_keys(tmp_path, kw) -> None:
    """Held-out folders of which one has flow.npy: validation logs no EPE columns, also for a batch of the video
    with flow (each process logged the keys its own batch had: under DDP's synced logging, a hang); with flow in
    every folder, it logs them."""
    import types

    from aynamics.pro_datamodule import ProDataModule
    from aynamics.scorer import Score
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    _video_folder(tmp_path / "mixed" / "c", 30)
    _video_folder(tmp_path / "mixed" / "d", 40)
    np.save(tmp_path / "mixed" / "d" / "flow.npy", np.zeros((29, 16, 16, 2), np.float32))
    logged = []
    for drop in (False, True):
        if drop:
            shutil.rmtree(tmp_path / "mixed" / "c")
        args = {**kw, "use_flow": True, "val_dir": str(tmp_path / "mixed")}
        dm = ProDataModule(str(tmp_path / "train"), str(TINY_ASSET_DIR), **args)
        dm.setup("fit")
        assert dm.val_flow is drop
        module = ProModule(SPEC, prompt=PROMPT, num_samples=2)
        module._trainer = types.SimpleNamespace(datamodule=dm, global_rank=0)
        score = Score(0.5, 0.5, 1.0, 2.0, True)
        module.sample_and_score = lambda videos, n, t: (None, None, [[score] * n], torch.ones(1, n))
        module.log_dict = lambda metrics, **_: logged.append(set(metrics))
        module.validation_step([v for v in dm.val_set if v.key == "d"], 0)
    assert not any("epe" in k for k in logged[0]) and "val/iou_full" in logged[0]
    assert {"val/epe_full", "val/bestN/epe_first"} <= logged[1]


def test_validation_leaves_out_the_padding_of_its_share():
    """Rank 1 of 2 over 5 videos evaluates [1, 3 | 0]: the repeat of video 0 (padding, so that both processes run
    the same batches) runs but is not counted. Greedy IoUs 0.2, 0.4 and 1.0 (the padding): val/iou_full =
    (0.2 + 0.4) / 2 = 0.3 over 2 videos, not 1.6 / 3; a batch of padding alone logs nothing."""
    import types

    from aynamics.data import EvalShard
    from aynamics.scorer import Score

    module = ProModule(SPEC, prompt=PROMPT, num_samples=2)
    loader = types.SimpleNamespace(sampler=EvalShard([1, 3, 0], 2), batch_size=3)
    module._trainer = types.SimpleNamespace(
        datamodule=types.SimpleNamespace(val_flow=True), global_rank=1, val_dataloaders=loader
    )
    ious = [0.2, 0.4, 1.0]
    module.sample_and_score = lambda videos, n, t: (
        None,
        None,
        [[Score(v, v, 1.0, 2.0, True)] * n for v in ious[: len(videos)]],
        torch.ones(len(videos), n),
    )
    logged = []
    module.log_dict = lambda metrics, **kw: logged.append((metrics, kw["batch_size"]))
    module.validation_step([None] * 3, 0)
    ((metrics, batch_size),) = logged
    assert batch_size == 2 and metrics["val/iou_full"] == pytest.approx(0.3)
    assert metrics["val/bestN/iou_full"] == pytest.approx(0.3) and metrics["val/reward_invalid"] == 0.0
    loader.batch_size = 1  # batches of one: [1], [3], [0]: the third is padding alone
    module.validation_step([None], 2)
    assert len(logged) == 1


def test_offline_pro_shows_the_frames_on_the_clock_they_were_sampled_on(tmp_path, dataset_dir):
    """Preferences sampled from a data set's videos (`aynamics preferences`: the prompt takes the videos' clock) are
    trained offline on the same clock: the offline data module kept the default 30 fps clip, so a video's temporal
    positions (second_per_grid_ts) differed from sampling and SFT whenever the data were at another rate."""
    from aynamics.pro_datamodule import ProDataModule

    tiny = lm.ModelSpec().processor_path
    prefs = _handmade_preferences(dataset_dir, tmp_path / "prefs")
    summary = json.loads((prefs / "summary.json").read_text())
    summary["clock"] = {"fps": 15.0, "clip_frames": [0, 3, 6, 9, 12]}  # as sampled from a 15 fps data set
    (prefs / "summary.json").write_text(json.dumps(summary))
    dm = ProDataModule(str(dataset_dir), tiny, as_video=True, num_frames=4, preferences_dir=str(prefs))
    dm.setup()
    assert dm.prompt.fps == 15.0 and dm.prompt.clip_frames == (0, 3, 6, 9, 12)
    assert dm.processor.video_fps == pytest.approx(dm.prompt.shown_fps) == pytest.approx(2 / 0.6)  # frames 0,3,9,12
    del summary["clock"]  # written before the clock was recorded: data.dir's, as online mode takes
    (prefs / "summary.json").write_text(json.dumps(summary))
    online = ProDataModule(str(dataset_dir), tiny, as_video=True, num_frames=4)
    online.setup()
    dm = ProDataModule(str(dataset_dir), tiny, as_video=True, num_frames=4, preferences_dir=str(prefs))
    dm.setup()
    assert (dm.prompt.fps, dm.prompt.clip_frames) == (online.prompt.fps, online.prompt.clip_frames)


def test_preferences_never_replace_a_folder_that_merely_holds_a_summary_json(tmp_path, dataset_dir, capsys):
    """A results folder with a summary.json of its own (a common name) is no preference set: it was deleted whole,
    sub-folders and all, and replaced by the preferences."""
    results = tmp_path / "results"
    (results / "exp1").mkdir(parents=True)
    (results / "summary.json").write_text('{"acc": 0.9}')
    (results / "exp1" / "notes.txt").write_text("keep")
    args = ["preferences", "--data", str(dataset_dir), "--num-samples", "2", "--max-new-tokens", "4", "--limit", "1"]
    assert cli_main([*args, "--out", str(results)]) == 2
    assert "is not a preference data set (no state.json)" in capsys.readouterr().err
    (results / "state.json").write_text("{}")
    assert cli_main([*args, "--out", str(results)]) == 2
    assert "is not a preference data set (it holds 'exp1')" in capsys.readouterr().err
    assert (results / "exp1" / "notes.txt").read_text() == "keep"
    first = _handmade_preferences(dataset_dir, tmp_path / "prefs")  # a preference set is still replaced
    assert _handmade_preferences(dataset_dir, tmp_path / "prefs") == first


def test_an_epe_reward_on_videos_without_flow_is_refused_before_sampling(tmp_path, capsys):
    """Video folders without flow.npy (the flow is optional) and an EPE or mix reward: training started and stopped
    at the first valid candidate, steps (hours on a real model) later, and `aynamics preferences` after sampling
    every video; a weak model's all-invalid candidates never reached the check. Now both stop before sampling,
    naming the video."""
    import types

    from aynamics.pro_datamodule import ProDataModule
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    _video_folder(tmp_path / "videos" / "a", 10)
    dm = ProDataModule(str(tmp_path / "videos"), str(TINY_ASSET_DIR), num_frames=2)
    with pytest.warns(UserWarning, match="PRO validation scores the first training videos"):
        dm.setup("fit")
    for metric in ("epe", "mix"):
        module = ProModule(SPEC, prompt=PROMPT, num_samples=2, reward_metric=metric)
        module._trainer = types.SimpleNamespace(datamodule=dm, global_rank=0)
        with pytest.raises(ValueError, match=f"reward_metric = '{metric}' scores the flow, but data.dir video 'a'"):
            module.setup("fit")
    module = ProModule(SPEC, prompt=PROMPT, num_samples=2)  # iou: no flow needed
    module._trainer = types.SimpleNamespace(datamodule=dm)
    module.setup("fit")
    args = ["preferences", "--data", str(tmp_path / "videos"), "--out", str(tmp_path / "p"), "--num-samples", "2"]
    assert cli_main([*args, "--metric", "epe"]) == 2
    assert "--metric epe scores the flow, but the video 'a' of --data has no observed flow" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()
    assert cli_main([*args, "--split", "test"]) == 2  # video folders have no splits: it was silently ignored
    assert "--split test: --data" in capsys.readouterr().err and not (tmp_path / "p").exists()


def test_folder_videos_show_the_model_the_clip_at_the_adapters_times(tmp_path):
    """A video folder longer than the training clip (90 frames at 30 fps), or at another rate (60 frames at 60 fps,
    meta.json): `evaluate --videos` and PRO showed the model every third image of the whole video (0 to 2.9 s, 3×
    the training clip's pace), while `aynamics predict` on the same frames reads 0 to 0.9 s. With the clip's times
    they see what predict sees; a folder too short for them is named."""
    import json

    from PIL import Image

    from aynamics.predict import clip_of
    from aynamics.unlabeled import video_from_folder

    def folder(name, n, fps):
        root = tmp_path / name
        (root / "frames").mkdir(parents=True)
        for k in range(n):  # each image's number in its red channel
            Image.fromarray(np.full((16, 16, 3), (k, 0, 0), np.uint8)).save(root / "frames" / f"{k}.png")
        np.save(root / "segmentation.npy", np.full((n, 16, 16), -1, np.int16))
        (root / "meta.json").write_text(json.dumps({"fps": fps}))
        return root

    times = lm.PromptSpec().frame_times  # 0, 0.1, ..., 0.9 s
    red = lambda frames: [int(np.asarray(f)[0, 0, 0]) for f in frames]  # noqa: E731
    long = folder("long", 90, 30)
    assert red(video_from_folder(long, clip_times=times).frames) == list(range(0, 30, 3))
    assert red(video_from_folder(long, clip_times=times).frames) == red(clip_of(long / "frames", lm.PromptSpec()))
    assert red(video_from_folder(long).frames) == list(range(0, 90, 3))  # without times: the sampled frames
    assert red(video_from_folder(folder("fast", 60, 60), clip_times=times).frames) == list(range(0, 60, 6))
    with pytest.raises(ValueError, match="needs the image at 0.9 s"):
        video_from_folder(folder("short", 20, 30), clip_times=times)


def test_preferences_take_the_adapters_base_model(tmp_path, dataset_dir, capsys):
    """`aynamics preferences --adapter A` without --model built the tiny model: an adapter of a real base was
    refused naming train.py's keys (stage.init_adapter, model is kind='tiny'), and a tiny adapter warned that
    model settings nobody gave (lora_rank 16, ...) were ignored. Now the adapter's base is used."""
    import warnings

    adapter = tmp_path / "adapter"
    adapters.save_adapter(lm.build_model(SPEC), adapter, SPEC, PROMPT)
    args = ["preferences", "--data", str(dataset_dir), "--num-samples", "2", "--max-new-tokens", "3", "--limit", "1"]
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert cli_main([*args, "--out", str(tmp_path / "p"), "--adapter", str(adapter)]) == 0
    assert not [w for w in seen if "ignored" in str(w.message)]
    meta = json.loads((adapter / "aynamics.json").read_text())
    meta["model"] |= {"kind": "pretrained", "path": str(tmp_path / "qwen3b")}  # a real base, not on this machine
    (adapter / "aynamics.json").write_text(json.dumps(meta))
    assert cli_main([*args, "--out", str(tmp_path / "q"), "--adapter", str(adapter)]) == 2
    err = capsys.readouterr().err
    assert f"model path {str(tmp_path / 'qwen3b')!r}" in err and "stage.init_adapter" not in err
    assert cli_main([*args, "--out", str(tmp_path / "q"), "--adapter", str(adapter), "--model", "tiny"]) == 2
    assert "but --model is 'tiny': leave --model out" in capsys.readouterr().err


def test_pro_resume_is_exact_across_a_validation_at_the_checkpoint_step(tmp_path, dataset_dir):
    """The checkpoint of step 2 is written before step 2's validation, which samples (and draws a DataLoader seed);
    a resumed run skips that validation. Training's random state (LoRA dropout here, online sampling alike) must
    not depend on it: resumed from step 2, step 3 ends on the straight run's adapter, bit for bit."""
    from safetensors.torch import load_file

    prefs = _handmade_preferences(dataset_dir, tmp_path / "prefs")
    three = [f"data.dir={dataset_dir}", "stage.mode=offline", f"stage.preferences_dir={prefs}"]
    three += ["trainer.max_steps=3", "trainer.val_check_interval=2", "callbacks.checkpoint.every_n_train_steps=2"]
    three += ["model.lora_dropout=0.3", "stage.temperature=1.0"]
    train(_cfg(tmp_path / "straight", *three))
    step2 = tmp_path / "straight" / "checkpoints" / "step000002.ckpt"
    train(_cfg(tmp_path / "resumed", *three, f"ckpt_path={step2}"))
    straight = load_file(tmp_path / "straight" / "adapter" / "adapter_model.safetensors")
    resumed = load_file(tmp_path / "resumed" / "adapter" / "adapter_model.safetensors")
    assert set(straight) == set(resumed) and all(torch.equal(straight[k], resumed[k]) for k in straight)


def test_validation_leaves_the_training_random_state_alone(dataset_dir):
    """A validation step (greedy + N samples) and iterating the validation loader draw nothing from torch's
    global generator, and a validation step samples the same candidates whatever that generator's state."""
    from types import SimpleNamespace

    from aynamics.pro_datamodule import ProDataModule
    from aynamics.tokenizer_build import TINY_ASSET_DIR

    dm = ProDataModule(str(dataset_dir), str(TINY_ASSET_DIR), batch_size=1, num_frames=2, use_flow=False)
    dm.setup("fit")
    dm.trainer = SimpleNamespace(global_rank=0, world_size=1)
    before = torch.get_rng_state()
    batch = next(iter(dm.val_dataloader()))
    assert torch.equal(torch.get_rng_state(), before)
    module = ProModule(
        SPEC, prompt=dm.prompt, processor=dm.processor, num_samples=2, max_new_tokens=6, temperature=1.0, nthread=1
    )
    module._trainer = SimpleNamespace(datamodule=dm, global_rank=0, world_size=1, num_nodes=1)
    logged = []
    module.log_dict = lambda metrics, **kw: logged.append(metrics)
    sampled = []
    real = rw.sample_completions

    def recording(*args, **kw):
        ids, texts = real(*args, **kw)
        sampled.append(ids)
        return ids, texts

    import aynamics.reward

    aynamics.reward.sample_completions = recording
    try:
        torch.manual_seed(1)
        before = torch.get_rng_state()
        module.validation_step(batch, 0)
        assert torch.equal(torch.get_rng_state(), before)
        torch.manual_seed(2)
        module.validation_step(batch, 0)
    finally:
        aynamics.reward.sample_completions = real
    assert sampled[1] == sampled[3]  # the N samples: the same at every validation


def test_sft_term_never_imitates_an_invalid_candidate(dataset_dir):
    """skip_ties=false, sft_weight=1: a video whose candidates are all invalid (rewards 0) adds its soft-preference
    term (uniform targets) but no SFT term (argmax of the zeros is candidate 0, an invalid text); a video with a
    valid best candidate adds the SFT term on it."""
    from aynamics.logprobs import token_logprobs
    from aynamics.preference import sft_on_best, soft_preference_loss

    module = ProModule(SPEC, prompt=PROMPT, num_samples=4, skip_ties=False, sft_weight=1.0, tau=0.1).eval()
    module.ensure_processor()
    prompts, ids, rewards = _fixed_candidates(module, dataset_dir)
    with torch.no_grad():
        zeros = torch.zeros(2, 4)
        loss, seq = module.preference_loss(prompts, ids, zeros)
        assert loss.item() == pytest.approx(soft_preference_loss(seq, zeros, 0.1).item(), abs=1e-5)
        mixed = torch.stack([zeros[0], rewards[1]])
        loss, seq = module.preference_loss(prompts, ids, mixed)
        pad = module.processor.tokenizer.pad_token_id
        one = rw.candidate_batch(prompts[1:], ids[1:], pad, forbidden=rw.vision_token_ids(module.model))
        from aynamics.batching import model_inputs

        lp, m = token_logprobs(module.model(**model_inputs(one)).logits, one["labels"])
        sft = sft_on_best(lp.view(1, 4, -1), m.view(1, 4, -1), rewards[1:])
    # the SFT term is a mean over the batch's 2 videos, the all-invalid one adding 0
    assert loss.item() == pytest.approx(soft_preference_loss(seq, mixed, 0.1).item() + sft.item() / 2, abs=1e-4)


def test_sft_term_with_skipped_ties_is_on_the_kept_videos_best(dataset_dir):
    """skip_ties=true (the default) with sft_weight=1: video 0's candidates all tie (skipped), video 1's best is valid
    (0.8). The SFT mask of valid bests is over the kept videos (one), so the term is video 1's, and both terms are
    means over the batch's 2 videos: loss = soft(ℓ₁, r₁) / 2 + sft(video 1) / 2."""
    from aynamics.batching import model_inputs
    from aynamics.logprobs import token_logprobs
    from aynamics.preference import sft_on_best, soft_preference_loss

    module = ProModule(SPEC, prompt=PROMPT, num_samples=4, skip_ties=True, sft_weight=1.0, tau=0.1).eval()
    module.ensure_processor()
    prompts, ids, rewards = _fixed_candidates(module, dataset_dir)
    mixed = torch.stack([torch.zeros(4), rewards[1]])
    with torch.no_grad():
        loss, seq = module.preference_loss(prompts, ids, mixed)
        pad = module.processor.tokenizer.pad_token_id
        one = rw.candidate_batch(prompts[1:], ids[1:], pad, forbidden=rw.vision_token_ids(module.model))
        lp, m = token_logprobs(module.model(**model_inputs(one)).logits, one["labels"])
        sft = sft_on_best(lp.view(1, 4, -1), m.view(1, 4, -1), rewards[1:])
    expected = soft_preference_loss(seq[1:], mixed[1:], 0.1).item() / 2 + sft.item() / 2
    assert loss.item() == pytest.approx(expected, abs=1e-4)


def test_training_step_logs_the_share_of_informative_videos(monkeypatch):
    """Offline rows with rewards [0.1, 0.9, 0.5] (a preference) and [0.3, 0.3, 0.3] (all tied): train/informative =
    1/2; train/margin = (ℓ(best, index 1) 1 - ℓ(worst, index 0) 0 + 0 for the tie) / 2 = 0.5 with ℓ = [[0, 1, 2],
    [5, 4, 3]]; train/loss is the preference loss returned."""
    module = ProModule(SPEC, prompt=PROMPT, mode="offline", num_samples=3)
    monkeypatch.setattr(module, "prompts", lambda clips: [None] * len(clips))
    seq = torch.tensor([[0.0, 1.0, 2.0], [5.0, 4.0, 3.0]])
    monkeypatch.setattr(module, "preference_loss", lambda prompts, ids, rewards: (torch.tensor(0.25), seq))
    logged = {}
    monkeypatch.setattr(module, "log_dict", lambda metrics, **kw: logged.update(metrics))
    rows = [
        {"frames": None, "completion_ids": [[1], [2], [3]], "rewards": [0.1, 0.9, 0.5]},
        {"frames": None, "completion_ids": [[1], [2], [3]], "rewards": [0.3, 0.3, 0.3]},
    ]
    assert module.training_step(rows, 0).item() == 0.25
    got = {k: float(v) for k, v in logged.items()}
    assert got == pytest.approx({"train/loss": 0.25, "train/margin": 0.5, "train/informative": 0.5})


@pytest.mark.parametrize("loss", ["soft", "ranking"])
def test_a_videos_weight_does_not_depend_on_how_videos_are_batched(dataset_dir, loss):
    """Two videos, one whose candidates all tie (skipped) and one informative: one batch of both gives the loss that
    two micro-batches of one video each give under accumulate_grad_batches=2 (Lightning: the mean of their losses)
    or two ddp ranks (the mean of their gradients): 0 and the informative video's loss, averaged."""
    module = ProModule(SPEC, prompt=PROMPT, num_samples=4, loss=loss, tau=0.1).eval()
    module.ensure_processor()
    prompts, ids, rewards = _fixed_candidates(module, dataset_dir)
    rewards = torch.stack([torch.zeros(4), rewards[1]])
    with torch.no_grad():
        together, _ = module.preference_loss(prompts, ids, rewards)
        apart = [module.preference_loss(prompts[k : k + 1], ids[k : k + 1], rewards[k : k + 1])[0] for k in (0, 1)]
    assert apart[0].item() == 0.0 and apart[1].item() > 0
    assert together.item() == pytest.approx((apart[0] + apart[1]).item() / 2, rel=1e-5)


def test_scoring_threads_follow_the_cores_this_job_may_use(monkeypatch):
    """MuJoCo's scoring threads come from the cores the process may run on (its affinity: a cluster job's
    allocation), shared by the node's ranks, not from the node's count: 8 ranks of a 16-core job on a 128-core node
    each started 16 threads (helper-64). `stage.module.nthread` still wins."""
    from types import SimpleNamespace

    from aynamics.simulate import default_threads

    monkeypatch.setattr(os, "cpu_count", lambda: 128)
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: set(range(16)), raising=False)
    trainer = SimpleNamespace(world_size=8, num_nodes=1)
    module = SimpleNamespace(hparams=SimpleNamespace(nthread=None), _trainer=trainer, trainer=trainer)
    assert ProModule.score_threads(module) == 2
    module.hparams.nthread = 5
    assert ProModule.score_threads(module) == 5
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: {0, 1, 2}, raising=False)
    assert default_threads() == 3  # the scene evaluation's and the CLI's default


def test_hand_edited_or_damaged_preference_sets_are_named_on_loading(tmp_path, dataset_dir):
    """A stored set training cannot use is refused when it is loaded, naming the folder and the row: NaN rewards
    were skipped as ties (no loss, no word) and uneven rows stopped training mid-run with torch's reshape error;
    a truncated .arrow, state.json or summary.json raised arrow's or json's words, which name no file. A NaN
    reward reaching `preference_loss` is refused too (skip_ties skipped it as a tie)."""
    import datasets

    from aynamics.preference_data import check_made_for

    good = _handmade_preferences(dataset_dir, tmp_path / "good")
    rows = datasets.load_from_disk(str(good)).to_list()
    summary = (good / "summary.json").read_text()
    edits = {
        "rewards must be finite numbers": lambda r: r | {"rewards": [float("nan"), 0.0]},
        r"as many completion_ids as rewards, the same N >= 2": lambda r: r | {"rewards": [0.9, 0.1, 0.0]},
        r"the same N >= 2 in every row \(row 0 has 2\)": lambda r: r | {"completion_ids": r["completion_ids"][:1]},
        "at least one token id": lambda r: r | {"completion_ids": [r["completion_ids"][0], []]},
        "no frames": lambda r: r | {"frames": []},
    }
    for k, (named, edit) in enumerate(edits.items()):
        out = write_preferences([rows[0], edit(dict(rows[1]))], json.loads(summary), tmp_path / f"e{k}")
        with pytest.raises(ValueError, match=rf"preferences '{out}': row 1 \(key '1'.*{named}"):
            load_preferences(out)
    damaged = tmp_path / "damaged"
    shutil.copytree(good, damaged)
    (arrow,) = damaged.glob("data-*.arrow")
    os.truncate(arrow, arrow.stat().st_size // 2)  # an interrupted copy
    with pytest.raises(ValueError, match=f"preferences '{damaged}' cannot be read .*aynamics preferences"):
        load_preferences(damaged)
    for text, named in (('{"prompt": {"tar', "cannot be read"), ("[1]", "holds a list")):
        (damaged / "summary.json").write_text(text)
        with pytest.raises(ValueError, match=f"'{damaged / 'summary.json'}' {named}"):
            check_made_for(damaged, PROMPT, None)
    module = ProModule(SPEC, prompt=PROMPT, num_samples=4)
    module.ensure_processor()
    prompts, ids, rewards = _fixed_candidates(module, dataset_dir)
    rewards[1, 2] = float("nan")
    with pytest.raises(ValueError, match="simulator scores must be finite"):
        module.preference_loss(prompts, ids, rewards)


def test_a_hand_edited_clock_in_summary_json_is_named(tmp_path):
    """summary.json's clock of values no video has: float('abc'), int('x') or iterating a number raised Python's
    words, and fps 0 or frames out of order PromptSpec's, none naming the file."""
    from aynamics.preference_data import stored_clock

    for clock, why in (
        ({"fps": "abc", "clip_frames": [0, 3]}, "could not convert"),
        ({"fps": 30, "clip_frames": 5}, "not iterable"),
        ({"fps": 0, "clip_frames": [0, 3]}, "fps = 0.0"),
        ({"fps": 30, "clip_frames": [3, 0]}, "must be increasing"),
    ):
        (tmp_path / "summary.json").write_text(json.dumps({"clock": clock}))
        with pytest.raises(
            ValueError, match=rf"'{tmp_path / 'summary.json'}': clock .* is not the videos' clock .*{why}"
        ):
            stored_clock(tmp_path)
    (tmp_path / "summary.json").write_text(json.dumps({"clock": {"fps": 15, "clip_frames": [0, 3]}}))
    assert stored_clock(tmp_path) == {"fps": 15.0, "clip_frames": (0, 3)}


def test_an_interrupted_rewrite_of_preferences_leaves_a_whole_set_at_out(tmp_path, dataset_dir, monkeypatch):
    """Writing over an earlier set deleted it first, then renamed the new one in: interrupted while deleting (a large
    set takes seconds), `out` held half of the old set (refused by a rerun as no preference set) and the new one
    lay under a temporary name. Now `out` holds a whole set whenever it stops; a failed rename names where the
    new set is and puts the earlier one back."""
    from aynamics import preference_data

    out = _handmade_preferences(dataset_dir, tmp_path / "prefs")
    real_rmtree = shutil.rmtree

    def interrupted(path, *args, **kwargs):  # one file gone, then Ctrl-C
        next(Path(path).glob("*.arrow")).unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(preference_data.shutil, "rmtree", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _handmade_preferences(dataset_dir, out)
    monkeypatch.setattr(preference_data.shutil, "rmtree", real_rmtree)
    assert len(load_preferences(out)) == 2
    real_rename = Path.rename

    def refused(self, target):
        if ".tmp-" in self.name:
            raise OSError(39, "Directory not empty")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", refused)
    with pytest.raises(OSError, match="the preferences are kept in '.*prefs.tmp-"):
        _handmade_preferences(dataset_dir, out)
    assert len(load_preferences(out)) == 2  # the earlier set, back in place


def test_preferences_go_on_after_an_interruption(tmp_path, dataset_dir, monkeypatch, capsys):
    """Interrupted during its third batch (of 3 videos, one a batch), `aynamics preferences` keeps the two scored
    batches in OUT.partial; the same command then samples only the third video and writes the rows, rewards and
    summary of an uninterrupted run, token for token (the generators go on from their kept states), and deletes
    OUT.partial. Other settings, and a second writer, are refused, naming what differs. Rewards here are a
    function of the sampled ids (the tiny model's samples all score 0), so that the rows show the sampling."""
    from aynamics.dataset_store import exclusive

    real, calls, stop = ProModule.sample_and_score, [], {"after": None}

    def scored_by_ids(self, chunk, num_samples, temperature):
        calls.append([v.key for v in chunk])
        if stop["after"] is not None and len(calls) > stop["after"]:
            raise KeyboardInterrupt
        prompts, ids, scores, _ = real(self, chunk, num_samples, temperature)
        return prompts, ids, scores, torch.tensor([[sum(c) % 97 / 97 for c in row] for row in ids])

    monkeypatch.setattr(ProModule, "sample_and_score", scored_by_ids)
    args = ["preferences", "--data", str(dataset_dir), "--limit", "3", "--num-samples", "4", "--pairs", "2"]
    args += ["--max-new-tokens", "6", "--temperature", "1.0", "--device", "cpu"]
    whole, part = tmp_path / "whole", tmp_path / "part"
    assert cli_main([*args, "--out", str(whole)]) == 0 and not (tmp_path / "whole.partial").exists()
    keys = calls[:]
    assert len(keys) == 3
    capsys.readouterr()
    calls.clear()
    stop["after"] = 2
    assert cli_main([*args, "--out", str(part)]) == 130
    kept = tmp_path / "part.partial"
    assert sorted(p.name for p in kept.glob("batch-*")) == ["batch-000000.pt", "batch-000001.pt"]
    assert not part.exists() and "2 batches kept in" in capsys.readouterr().err

    assert cli_main([*args, "--out", str(part), "--seed", "1"]) == 2  # other settings: refused, nothing sampled
    assert "with other settings (seed 0 there, 1 now)" in capsys.readouterr().err
    with exclusive(kept / ".lock"):  # another process sampling into it
        assert cli_main([*args, "--out", str(part)]) == 2
        assert "another process is sampling into" in capsys.readouterr().err
    calls.clear()
    stop["after"] = None
    assert cli_main([*args, "--out", str(part)]) == 0
    assert calls == [keys[2]] and "(2 batches kept)" in capsys.readouterr().err  # only the third video sampled
    assert not kept.exists()
    a, b = load_preferences(whole), load_preferences(part)
    assert len(a) >= 3  # pairs from every video
    for column in ("key", "completions", "completion_ids", "rewards", "reasons", "case_rewards"):
        assert a[column] == b[column]
    assert json.loads((whole / "summary.json").read_text()) == json.loads((part / "summary.json").read_text())


def test_preferences_interrupted_while_writing_are_written_from_the_kept_batches(tmp_path, dataset_dir, monkeypatch):
    """Interrupted in write_preferences, after all 3 batches were scored and kept: the same command samples nothing
    and writes the rows of an uninterrupted run. It stopped with an AttributeError (the processor, loaded only by
    sampling, was None when the summary named its tokenizer), as after the 'cannot write --out' failure whose
    message promises that the same command writes them."""
    from aynamics import preference_cli

    calls, real_write = [], preference_cli.write_preferences
    real = ProModule.sample_and_score

    def counted(self, chunk, num_samples, temperature):
        calls.append([v.key for v in chunk])
        return real(self, chunk, num_samples, temperature)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ProModule, "sample_and_score", counted)
    args = ["preferences", "--data", str(dataset_dir), "--limit", "3", "--num-samples", "2", "--pairs", "1"]
    args += ["--max-new-tokens", "4", "--device", "cpu"]
    assert cli_main([*args, "--out", str(tmp_path / "whole")]) == 0
    monkeypatch.setattr(preference_cli, "write_preferences", interrupted)
    assert cli_main([*args, "--out", str(tmp_path / "part")]) == 130
    assert len(list((tmp_path / "part.partial").glob("batch-*.pt"))) == 3
    monkeypatch.setattr(preference_cli, "write_preferences", real_write)
    calls.clear()
    assert cli_main([*args, "--out", str(tmp_path / "part")]) == 0
    assert calls == [] and not (tmp_path / "part.partial").exists()  # nothing sampled again
    whole, part = (json.loads((tmp_path / p / "summary.json").read_text()) for p in ("whole", "part"))
    assert part == whole and whole["videos"] == 3


def test_preferences_that_kept_no_batch_do_not_bind_the_next_run(tmp_path, dataset_dir, monkeypatch, capsys):
    """A run refused before its first batch (--num-samples 1), or failing in it (as a GPU out of memory at
    --batch-size 3), keeps no batch: the corrected command samples afresh. OUT.partial held the failed run's
    settings, and the corrected one was refused ("num_samples 1 there, 2 now"), until the user deleted it."""
    real = ProModule.sample_and_score

    def out_of_memory(self, chunk, num_samples, temperature):
        if len(chunk) > 1:
            raise RuntimeError("CUDA out of memory")
        return real(self, chunk, num_samples, temperature)

    monkeypatch.setattr(ProModule, "sample_and_score", out_of_memory)
    args = ["preferences", "--data", str(dataset_dir), "--limit", "2", "--pairs", "1", "--max-new-tokens", "4"]
    args += ["--device", "cpu", "--out", str(tmp_path / "prefs")]
    assert cli_main([*args, "--num-samples", "1"]) == 2
    assert "num_samples = 1" in capsys.readouterr().err
    with pytest.raises(RuntimeError, match="out of memory"):
        cli_main([*args, "--num-samples", "2", "--batch-size", "3"])
    assert cli_main([*args, "--num-samples", "2"]) == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "prefs" / "summary.json").read_text())["videos"] == 2
    assert not (tmp_path / "prefs.partial").exists()


class _DrawnCandidates:
    """A stand-in for ProModule in build_preferences, with no model (a run takes milliseconds): each candidate is 3
    token ids drawn from torch's generator, its reward a function of them (sum % 97 / 97), every one invalid."""

    prompt = PROMPT

    def __init__(self, stop_after: int | None = None) -> None:
        decode = lambda ids, skip_special_tokens: [" ".join(map(str, c)) for c in ids]  # noqa: E731
        self.processor = SimpleNamespace(tokenizer=SimpleNamespace(get_vocab=lambda: {"a": 0}, batch_decode=decode))
        self.calls, self.stop_after = [], stop_after

    def sample_and_score(self, chunk, num_samples, temperature):
        if self.stop_after is not None and len(self.calls) == self.stop_after:
            raise KeyboardInterrupt
        self.calls.append([v.key for v in chunk])
        ids = torch.randint(1, 1000, (len(chunk), num_samples, 3)).tolist()
        scores = [[Score(0.0, 0.0, None, None, False, "truncated") for _ in row] for row in ids]
        return None, ids, scores, torch.tensor([[sum(c) % 97 / 97 for c in row] for row in ids])


class _CountedVideos(Sequence):
    """`n` one-image videos keyed "0", "1", ..., counting the reads of each (a generated data set decodes its
    images at every read); `shade` sets their images."""

    def __init__(self, n: int, shade: int = 0) -> None:
        self.n, self.shade, self.reads = n, shade, [0] * n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):
        self.reads[i] += 1
        return UnlabeledVideo(str(i), (Image.new("RGB", (4, 4), (i, self.shade, 0)),), None)


def _drawn_preferences(videos, module, progress=None, **kwargs):
    torch.manual_seed(0)
    kwargs = {"num_samples": 4, "pairs": 2, "batch_size": 2, **kwargs}
    return build_preferences(module, videos, progress=progress, **kwargs)


def test_build_preferences_reads_each_video_once(tmp_path):
    """4 videos, 2 a batch, 4 candidates and 2 pairs each: every video is read once, uninterrupted or going on
    from the first kept batch, and its rows share its images. Each row read its video again (1 + its rows reads
    of a video: a generated data set's images decoded 3 times and held twice over), the kept ones once more."""
    videos = _CountedVideos(4)
    whole, _ = _drawn_preferences(videos, _DrawnCandidates())
    assert videos.reads == [1, 1, 1, 1] and len(whole) == 8  # 4 distinct rewards a video: 2 pairs each
    assert whole[0]["frames"][0] is whole[1]["frames"][0]  # video 0's two rows: its images once
    progress = SamplingProgress(tmp_path / "p", {})
    with progress.opened(), pytest.raises(KeyboardInterrupt):
        _drawn_preferences(_CountedVideos(4), _DrawnCandidates(stop_after=1), progress)
    videos, module = _CountedVideos(4), _DrawnCandidates()
    with progress.opened():
        rows, _ = _drawn_preferences(videos, module, progress)
    assert module.calls == [["2", "3"]] and videos.reads == [1, 1, 1, 1]
    assert [r["completion_ids"] for r in rows] == [r["completion_ids"] for r in whole]


def test_build_preferences_refuses_kept_batches_of_other_videos_under_the_same_keys(tmp_path):
    """The first batch (videos "0" and "1") is kept; the videos are then made again with other images under the
    same keys (a data set generated again: keys are record indices): going on is refused, naming both. Only the
    keys were compared, and the kept candidates were paired with the new videos' images."""
    progress = SamplingProgress(tmp_path / "p", {})
    with progress.opened(), pytest.raises(KeyboardInterrupt):
        _drawn_preferences(_CountedVideos(4), _DrawnCandidates(stop_after=1), progress)
    with progress.opened(), pytest.raises(ValueError, match=r"videos \['0', '1'\] than they hold now"):
        _drawn_preferences(_CountedVideos(4, shade=9), _DrawnCandidates(), progress)
    with progress.opened():  # the same videos: it goes on
        assert len(_drawn_preferences(_CountedVideos(4), _DrawnCandidates(), progress)[0]) == 8


def test_build_preferences_refuses_a_progress_kept_with_other_settings(tmp_path):
    """`SamplingProgress.settings` is the caller's (the CLI's name every setting; these name none): a batch kept
    with 1 pair a video, resumed with 2, is refused naming pairs, and another batch size names batch_size (it read
    as 'the videos changed'). Pairs and temperature were not compared, and the rows mixed 1 and 2 pairs a video.
    A batch file of other contents (another version's) is named, not a KeyError."""
    progress = SamplingProgress(tmp_path / "p", {})
    with progress.opened(), pytest.raises(KeyboardInterrupt):
        _drawn_preferences(_CountedVideos(4), _DrawnCandidates(stop_after=1), progress, pairs=1)
    for kwargs, named in (({"pairs": 2}, "pairs 1 there, 2 now"), ({"batch_size": 1}, "batch_size 2 there, 1 now")):
        with progress.opened(), pytest.raises(ValueError, match=f"sampled with other settings \\({named}\\)"):
            _drawn_preferences(_CountedVideos(4), _DrawnCandidates(), progress, **{"pairs": 1, **kwargs})
    with progress.opened(), pytest.raises(ValueError, match="sampled with other settings .temperature 0.1 there"):
        _drawn_preferences(_CountedVideos(4), _DrawnCandidates(), progress, pairs=1, temperature=0.5)
    torch.save({"keys": ["0", "1"]}, tmp_path / "p" / "batch-000000.pt")
    with progress.opened(), pytest.raises(ValueError, match="batch-000000.pt' is not a batch this version keeps"):
        _drawn_preferences(_CountedVideos(4), _DrawnCandidates(), progress, pairs=1)


def test_preferences_go_on_with_the_same_split_spelled_otherwise(tmp_path, dataset_dir, monkeypatch, capsys):
    """Interrupted after its first batch, the run goes on with `--split train` given, the split it read without
    one (refused before: "split None there, 'train' now"), and only the second video is sampled."""
    real, calls = ProModule.sample_and_score, []

    def stopped_at_second(self, chunk, num_samples, temperature):
        calls.append([v.key for v in chunk])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(self, chunk, num_samples, temperature)

    monkeypatch.setattr(ProModule, "sample_and_score", stopped_at_second)
    args = ["preferences", "--data", str(dataset_dir), "--limit", "2", "--num-samples", "2", "--pairs", "1"]
    args += ["--max-new-tokens", "4", "--device", "cpu", "--out", str(tmp_path / "prefs")]
    assert cli_main(args) == 130
    calls.append("interrupted")
    assert cli_main([*args, "--split", "train"]) == 0, capsys.readouterr().err
    assert len(calls) == 4 and calls[3] == calls[1]  # the second video sampled again, the first not


def test_kept_batches_need_a_folder_of_their_own(tmp_path):
    """OUT.partial as a link is refused: removed at the end, the link went and its batches stayed, to be gone on from
    by the next run into another OUT pointing there."""
    from aynamics.preference_data import SamplingProgress

    (tmp_path / "real").mkdir()
    (tmp_path / "p.partial").symlink_to(tmp_path / "real")
    with pytest.raises(ValueError, match=r"p\.partial' is a link \(to .*real'\)"):
        with SamplingProgress(tmp_path / "p.partial", {"seed": 0}).opened():
            pass
    assert list((tmp_path / "real").iterdir()) == []


def test_preferences_are_refused_before_the_model_is_loaded(tmp_path, dataset_dir, monkeypatch, capsys):
    """A second writer into OUT.partial, or its batches kept with other settings, were refused only after the model
    was built and moved to the device (minutes for a real checkpoint): now before it is built."""
    from aynamics.dataset_store import exclusive

    def loaded(self, *args, **kwargs):
        raise AssertionError("the model was loaded")

    monkeypatch.setattr(ProModule, "__init__", loaded)
    args = ["preferences", "--data", str(dataset_dir), "--limit", "1", "--device", "cpu"]
    args += ["--out", str(tmp_path / "prefs")]
    kept = SamplingProgress(tmp_path / "prefs.partial", {"seed": 5})
    with kept.opened():
        kept.save("batch", 0, {})  # one batch kept: its settings bind
    with exclusive(kept.folder / ".lock"):  # another process sampling into it
        assert cli_main(args) == 2
        assert "another process is sampling into" in capsys.readouterr().err
    assert cli_main(args) == 2
    assert "seed 5 there, 0 now" in capsys.readouterr().err


def test_preferences_with_an_adapter_trained_again_into_its_folder_are_refused(tmp_path):
    """The settings named --adapter by its folder only: an interrupted run went on with an adapter trained again into
    the same folder, and the data set mixed two policies' candidates. They hold a hash of its weights file now
    (sha256 of b"abc": ba7816bf8f01cfea..., of b"": e3b0c44298fc1c14...; no adapter: None)."""
    from aynamics.preference_cli import _settings

    adapter = tmp_path / "adapter"
    adapter.mkdir()
    args = SimpleNamespace(data=str(tmp_path), adapter=str(adapter), limit=None, num_samples=2, pairs=1)
    args.__dict__.update(temperature=0.1, top_p=1.0, max_new_tokens=4, metric="iou", span="full", batch_size=1, seed=0)

    def settings() -> dict:
        return _settings(args, model="tiny", dtype="float32", split="train", inputs="rgb")

    (adapter / "adapter_model.safetensors").write_bytes(b"abc")
    kept = SamplingProgress(tmp_path / "prefs.partial", settings())
    assert kept.settings["adapter_weights"] == "ba7816bf8f01cfea"
    with kept.opened():
        kept.save("batch", 0, {})
    (adapter / "adapter_model.safetensors").write_bytes(b"")  # trained again
    with pytest.raises(ValueError, match="adapter_weights 'ba7816bf8f01cfea' there, 'e3b0c44298fc1c14' now"):
        with SamplingProgress(kept.folder, settings()).opened():
            pass
    args.adapter = None
    assert settings()["adapter_weights"] is None


def test_pro_data_errors_name_their_config_keys(tmp_path, dataset_dir):
    """A missing preference set and a preference set given as data.dir named no config key (helper-109's sweep):
    "preferences '/x': no data set here", "'/x': columns [...] are missing"."""
    from aynamics.pro_datamodule import ProDataModule

    tiny = lm.ModelSpec().processor_path
    nowhere = str(tmp_path / "nope")
    with pytest.raises(
        FileNotFoundError, match=r"^\[Errno 2\] stage.preferences_dir: preferences .*nope.*: no data set"
    ):
        ProDataModule(str(dataset_dir), tiny, preferences_dir=nowhere).setup()
    prefs = _handmade_preferences(dataset_dir, tmp_path / "prefs")
    with pytest.raises(ValueError, match=r"^data.dir: .*prefs.*: columns \[.*\] are missing"):
        ProDataModule(str(prefs), tiny).setup()
