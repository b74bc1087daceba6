"""The PRO stage: label-free adaptation of the model from the simulator's judgement of its own samples.

Online mode, per training step and per video: sample N responses (`reward.sample_completions`), score them
against the observed segmentation (and flow) with the fast scorer (`reward.score_completions`), then one
forward pass over the B x N (prompt, response) rows gives the length-normalised log-likelihoods ℓ (B, N) and

    loss = soft_preference_loss(ℓ, s, τ)  [or pro_ranking_loss(ℓ, s)]  + sft_weight * sft_on_best(...)

(`aynamics.preference`; s = simulator rewards). Offline mode trains the same loss on stored candidates and rewards
(`aynamics.preference_data`, e.g. three (chosen, rejected) pairs per video drawn from 32 samples). Validation
runs the paper's Table 10 modes on unlabeled videos: greedy, Best@1 (mean over samples) and Best@N (best by
simulator score), for IoU and EPE, first frame and full sequence.

    data = ProDataModule("data/synth", processor_path=TINY_ASSET_DIR, batch_size=1)
    module = ProModule(ModelSpec(kind="tiny"), num_samples=4)     # or init_adapter="sft_run/adapter"
    lightning.Trainer(max_steps=2).fit(module, data)            # python train.py stage=pro does this

Logged: train/loss, train/margin (ℓ of the best- minus the worst-scored candidate), train/informative (share of
videos whose candidates do not all tie), reward/mean, reward/best,
reward/invalid (+ reward/invalid_<kind>), val/<mode>/<metric> (val/iou_full = greedy). Checkpoints hold only the
trainable (adapter) weights; `run_callbacks.AdapterExport` writes the peft adapter, as in the SFT stage. The data
module, `ProDataModule`, is `pro_datamodule.py`'s (re-exported here).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch

from aynamics import adapters, lm, sharding
from aynamics import reward as rw
from aynamics.batching import model_inputs
from aynamics.data import real_rows
from aynamics.logprobs import token_logprobs
from aynamics.preference import check_finite_rewards, pro_ranking_loss, sft_on_best, soft_preference_loss
from aynamics.pro_datamodule import ProDataModule as ProDataModule  # re-export: older configs' _target_
from aynamics.pro_datamodule import without_flow
from aynamics.sft import check_gradients
from aynamics.unlabeled import UnlabeledVideo

LOSSES = ("soft", "ranking")
MODES = ("online", "offline")


# How the policy is trained, taken from the run's `model` config; the rest of a spec is what the adapter is.
RUN_SETTINGS = ("gradient_checkpointing", "dtype", "attn_implementation", "lora_dropout")


def build_policy(spec: lm.ModelSpec, init_adapter: str | None = None) -> tuple[torch.nn.Module, lm.ModelSpec]:
    """The policy: `lm.build_model(spec)` (fresh LoRA), or the SFT adapter at `init_adapter` loaded trainable.

    An adapter carries its own model spec (`aynamics.json`); it must name the same base model as `spec`. Its
    architecture (base seed and size, LoRA rank, alpha and targets, trained modules) is the adapter's: a run value
    that differs is named in a warning. How it is trained (`RUN_SETTINGS`: gradient checkpointing, dtype,
    attention kernel, LoRA dropout) is the run's, as for a fresh LoRA: PRO samples N long responses per video, and
    checkpointing is what fits them in memory.

    Raises:
        FileNotFoundError: `init_adapter` is not an adapter folder written by training.
        ValueError: the adapter was trained on another base model.
    """
    if init_adapter is None:
        return lm.build_model(spec), spec
    from peft import PeftConfig, PeftModel

    if not Path(init_adapter, "adapter_config.json").is_file():
        raise FileNotFoundError(2, f"stage.init_adapter = {init_adapter!r} holds no adapter_config.json", init_adapter)
    adapter_spec, _ = adapters.read_adapter_meta(init_adapter)
    if (adapter_spec.kind, adapter_spec.path) != (spec.kind, spec.path):
        raise ValueError(
            f"stage.init_adapter = {init_adapter!r} was trained on model kind={adapter_spec.kind!r} "
            f"path={adapter_spec.path!r}, but model is kind={spec.kind!r} path={spec.path!r}"
        )
    ignored = [
        f"model.{f.name} = {getattr(spec, f.name)!r} (the adapter's: {getattr(adapter_spec, f.name)!r})"
        for f in dataclasses.fields(spec)
        if f.name not in RUN_SETTINGS and getattr(spec, f.name) != getattr(adapter_spec, f.name)
    ]
    if ignored:
        warnings.warn(
            f"stage.init_adapter = {init_adapter!r} defines the model: {'; '.join(ignored)} ignored", stacklevel=2
        )
    used = dataclasses.replace(adapter_spec, **{k: getattr(spec, k) for k in RUN_SETTINGS})
    from aynamics.model import enable_gradient_checkpointing, float32_trained_tower, peft_quietly

    base = lm.build_base(used)
    if used.gradient_checkpointing:
        enable_gradient_checkpointing(base)  # before the adapter, as `apply_lora` does
    config = PeftConfig.from_pretrained(str(init_adapter))
    config.lora_dropout = used.lora_dropout
    with peft_quietly(), warnings.catch_warnings():
        # a base on the meta device (a process but rank 0 under trainer=fsdp: `sharding.model_init_context`) takes
        # no adapter weights here, but rank 0's once sharded: torch's note on each of them says nothing
        warnings.filterwarnings("ignore", "for .*: copying from a non-meta parameter", UserWarning)
        # read onto the CPU, where the base is (peft's default, the first GPU, opened a context there from every rank)
        model = PeftModel.from_pretrained(base, str(init_adapter), is_trainable=True, config=config, torch_device="cpu")
    float32_trained_tower(model)  # the adapter's tower is loaded in the base dtype: trained in float32, as in SFT
    return model.train(), used


class ProModule(adapters.ExactResume, L.LightningModule):
    """PRO on unlabeled videos (online) or on a stored preference data set (offline).

    Args:
        spec: The base model and adapter settings (plain values; the model is built here, as in the SFT stage).
        init_adapter: Folder of an SFT adapter (`OUT/adapter` of an SFT run) to start from; None: a fresh LoRA.
        mode: "online" (sample and score in the loop) or "offline" (batches of stored candidates and rewards).
        num_samples: N responses sampled per video (online training and Best@N evaluation), >= 2.
        temperature, top_p: Sampling settings (the paper: N = 32 at temperature 0.1).
        max_new_tokens: Response length limit in tokens (an invalid response that reached it is counted as
            "truncated": raise it when `reward/invalid_truncated` is not 0).
        loss: "soft" (reward-weighted soft-label CE) or "ranking" (the original hard-ranking PRO).
        tau: Temperature τ of the soft targets softmax(s / τ), >= 0 (0: all weight on the best).
        sft_weight: Weight of the SFT term on each video's best candidate (0: off).
        skip_ties: Videos whose candidates all score the same (e.g. all invalid) give no loss.
        reward_metric, reward_span, mix_weight, epe_scale: The reward (`reward.RewardConfig`).
        lr, weight_decay: AdamW settings (constant learning rate).
        nthread: MuJoCo threads per scoring batch (None: the cores divided by the ranks on this machine);
            score_workers: videos scored at once (threads).
        processor, prompt: The processor and `lm.PromptSpec`; None: taken from the data module at setup
            (standalone use: given here, or built from `spec` and the default prompt).
    """

    def __init__(
        self,
        spec: lm.ModelSpec | dict,
        *,
        init_adapter: str | None = None,
        mode: str = "online",
        num_samples: int = 4,
        temperature: float = 1.0,
        top_p: float = 1.0,
        max_new_tokens: int = 1800,
        loss: str = "soft",
        tau: float = 0.1,
        sft_weight: float = 0.0,
        skip_ties: bool = True,
        reward_metric: str = "iou",
        reward_span: str = "full",
        mix_weight: float = 0.5,
        epe_scale: float = 5.0,
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        nthread: int | None = None,
        score_workers: int = 1,
        processor: Any = None,
        prompt: lm.PromptSpec | None = None,
    ) -> None:
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"stage.mode = {mode!r}: must be one of {MODES}")
        if loss not in LOSSES:
            raise ValueError(f"stage.module.loss = {loss!r}: must be one of {LOSSES}")
        if num_samples < 2:
            raise ValueError(f"stage.num_samples = {num_samples}: a preference needs at least 2 candidates")
        if not all(math.isfinite(x) for x in (tau, sft_weight, lr)) or tau < 0 or sft_weight < 0 or lr <= 0:
            raise ValueError(
                f"tau = {tau}, sft_weight = {sft_weight}, lr = {lr}: need finite tau >= 0, sft_weight >= 0, lr > 0"
            )
        # before the model loads: sampling refused these only at the first step (NaN with transformers' traceback)
        if not (math.isfinite(temperature) and temperature > 0):
            raise ValueError(
                f"stage.temperature = {temperature}: must be a finite number > 0 (stage.num_samples = {num_samples} "
                "responses are sampled per video; greedy gives one)"
            )
        if not 0 < top_p <= 1:
            raise ValueError(f"stage.module.top_p = {top_p}: must be in (0, 1]")
        if max_new_tokens < 1 or score_workers < 1:
            raise ValueError(
                f"stage.module.max_new_tokens = {max_new_tokens}, stage.module.score_workers = {score_workers}: "
                "both must be >= 1"
            )
        self.reward_config = rw.RewardConfig(reward_metric, reward_span, mix_weight, epe_scale)
        spec = spec if isinstance(spec, lm.ModelSpec) else lm.ModelSpec(**spec)
        self.model, self.spec = build_policy(spec, init_adapter)
        self.save_hyperparameters(ignore=["spec", "processor", "prompt"])
        self.hparams["spec"] = dataclasses.asdict(self.spec)
        self.processor, self.prompt = processor, prompt
        self.strict_loading = False  # checkpoints hold only the trainable weights; the base is rebuilt from spec

    def configure_model(self) -> None:
        """Under `trainer=fsdp` (a device mesh is set): shard the policy (`aynamics.sharding`)."""
        sharding.shard_module(self)

    def setup(self, stage: str) -> None:
        """Processor and prompt from the data module (the frames it serves are shown the way the prompt says)."""
        dm = self.trainer.datamodule if self._trainer is not None else None
        if self.prompt is None and dm is not None:
            self.prompt, self.processor = dm.prompt, dm.processor
        stored = getattr(dm, "hparams", {}).get("preferences_dir") if dm is not None else None
        if dm is not None and (self.hparams.mode == "offline") != (stored is not None):
            raise ValueError(
                f"stage.mode = {self.hparams.mode!r} with preferences_dir = {stored!r}: offline mode trains on a "
                "stored preference data set (set stage.preferences_dir), online mode samples (leave it null)"
            )
        if dm is not None and self.reward_config.needs_flow and not getattr(dm, "hparams", {}).get("use_flow", True):
            raise ValueError(
                f"stage.reward_metric = {self.reward_config.metric!r} scores the flow, but data.use_flow = false: "
                "set data.use_flow=true or stage.reward_metric=iou"
            )
        if dm is not None and self.reward_config.needs_flow:  # else the first valid candidate stops the run
            sets = [("data.val_dir" if dm.hparams.get("val_dir") else "data.dir", getattr(dm, "val_set", []))]
            if self.hparams.mode == "online":
                sets.insert(0, ("data.dir", dm.train_set))
            for key, videos in sets:
                missing = without_flow(videos)
                if missing is not None:
                    raise ValueError(
                        f"stage.reward_metric = {self.reward_config.metric!r} scores the flow, but {key} video "
                        f"{missing!r} has no observed flow (flow.npy): add it or set stage.reward_metric=iou"
                    )
        self.ensure_processor()
        if self.hparams.init_adapter is not None:
            _, trained = adapters.read_adapter_meta(self.hparams.init_adapter)
            mismatch = lm.prompt_mismatch({k: getattr(trained, k) for k in lm.PROMPT_KEYS}, self.prompt)
            if mismatch:
                was, now = mismatch
                raise ValueError(f"stage.init_adapter was trained with {was}, but the data are set to {now}")
            clock = ("fps", "clip_frames")
            if any(getattr(trained, k) != getattr(self.prompt, k) for k in clock):
                warnings.warn(
                    f"stage.init_adapter was trained on clips of frames {list(trained.clip_frames)} at "
                    f"{trained.fps:g} fps, PRO's videos hold frames {list(self.prompt.clip_frames)} at "
                    f"{self.prompt.fps:g} fps: the model learns two timings (the adapter written records PRO's)",
                    stacklevel=2,
                )
            if trained.examples != self.prompt.examples:
                raise ValueError(
                    f"stage.init_adapter was trained with {len(trained.examples)} in-context examples in its prompt, "
                    f"but PRO's prompts hold {len(self.prompt.examples)}: train the SFT adapter with "
                    "data.num_examples=0"
                )

    def ensure_processor(self) -> None:
        """Standalone use: the default prompt and the spec's processor when none was given."""
        self.prompt = self.prompt or lm.PromptSpec()
        if self.processor is None:
            self.processor = lm.load_processor(self.spec, self.prompt)

    # ----------------------------------------------------------------------------------------
    def prompts(self, clips: Sequence[Sequence[Any]]) -> list[dict[str, torch.Tensor]]:
        """Generation prompts of B clips (each a sequence of frames), as the SFT stage builds them."""
        self.ensure_processor()
        return [lm.prompt_inputs(self.processor, self.prompt, frames) for frames in clips]

    def sample_and_score(
        self, videos: Sequence[UnlabeledVideo], num_samples: int, temperature: float
    ) -> tuple[list[dict[str, torch.Tensor]], list[list[list[int]]], list[list[rw.Score]], torch.Tensor]:
        """Prompts, B x N sampled ids, their scores and (B, N) rewards."""
        hp = self.hparams
        prompts = self.prompts([v.frames for v in videos])
        ids, texts = rw.sample_completions(
            self.model,
            self.processor,
            prompts,
            num_samples=num_samples,
            temperature=temperature,
            top_p=hp.top_p,
            max_new_tokens=hp.max_new_tokens,
        )
        scores = rw.score_completions(
            texts, [v.observation for v in videos], nthread=self.score_threads(), workers=hp.score_workers
        )
        scores = rw.mark_truncated(scores, ids, hp.max_new_tokens, rw.eos_ids(self.model))
        return prompts, ids, scores, rw.rewards_of(scores, self.reward_config)

    def score_threads(self) -> int:
        """MuJoCo threads per scoring batch: `nthread`, else this machine's cores shared by the local ranks."""
        if self.hparams.nthread is not None:
            return int(self.hparams.nthread)
        from aynamics.simulate import usable_cores

        ranks = self.trainer.world_size // max(1, self.trainer.num_nodes) if self._trainer is not None else 1
        return max(1, usable_cores() // max(1, ranks))

    def preference_loss(
        self,
        prompts: Sequence[dict[str, torch.Tensor]],
        completions: Sequence[Sequence[Sequence[int]]],
        rewards: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(loss, seq_logps (B, N)) of the candidates given their rewards (B, N)."""
        hp = self.hparams
        pad = self.processor.tokenizer.pad_token_id
        batch = rw.candidate_batch(prompts, completions, pad, forbidden=rw.vision_token_ids(self.model))
        batch = {k: v.to(self.device) for k, v in batch.items()}
        # Rows are left-padded, so every candidate ends at the right edge: only the last (longest + 1) positions'
        # logits are needed (a 7B vocabulary makes them the largest tensor of the step).
        keep = max(len(c) for row in completions for c in row) + 1
        logits = self.model(**model_inputs(batch), logits_to_keep=keep, use_cache=False).logits
        tok_lp, mask = token_logprobs(logits, batch["labels"])  # (B*N, L-1)
        b, n = rewards.shape
        seq = (tok_lp.sum(-1) / mask.sum(-1).clamp(min=1)).view(b, n)
        r = rewards.to(seq.device, seq.dtype)
        check_finite_rewards(r)  # before the ties: NaN fails `amax > amin`, and the video was skipped silently
        # a video whose candidates all score the same (e.g. all invalid) says nothing about which is better
        keep = r.amax(1) > r.amin(1) if hp.skip_ties else torch.ones(b, dtype=torch.bool, device=seq.device)
        if not keep.any():
            return seq.sum() * 0.0, seq  # zero loss that still reaches every parameter (DDP-friendly)
        s, rk = seq[keep], r[keep]
        # a mean over the batch's B videos, a skipped one adding 0 (not over the kept ones): a video's weight is then
        # the same whether it shares its batch with tied videos or is a micro-batch (accumulation) or rank of its own
        loss = soft_preference_loss(s, rk, hp.tau) if hp.loss == "soft" else pro_ranking_loss(s, rk)
        loss = loss * (len(s) / b)
        # SFT only where the best candidate is valid (an invalid one scores 0): with skip_ties=false an all-invalid
        # video's `argmax` is its first candidate, whose broken text the term would teach
        good = rk.amax(1) > 0
        if hp.sft_weight > 0 and good.any():
            lp, m = tok_lp.view(b, n, -1)[keep][good], mask.view(b, n, -1)[keep][good]
            loss = loss + hp.sft_weight * sft_on_best(lp, m, rk[good]) * (int(good.sum()) / b)
        return loss, seq

    def training_step(self, batch: list, batch_idx: int) -> torch.Tensor:
        if self.hparams.mode == "online":
            prompts, ids, scores, rewards = self.sample_and_score(
                batch, self.hparams.num_samples, self.hparams.temperature
            )
            stats = rw.RewardStats.of(rewards, scores)  # this rank's samples; the logged value is the mean over ranks
            self.log_dict(stats.to_metrics("reward/"), batch_size=len(batch), sync_dist=True)
        else:  # rows of the preference data set: frames, completion ids, rewards
            prompts = self.prompts([r["frames"] for r in batch])
            ids = [r["completion_ids"] for r in batch]
            rewards = torch.tensor([r["rewards"] for r in batch], dtype=torch.float32)
        loss, seq = self.preference_loss(prompts, ids, rewards)
        margin = _margin(seq.detach(), rewards)
        informative = (rewards.amax(1) > rewards.amin(1)).float().mean()  # share of videos with a preference
        logs = {"train/loss": loss.detach(), "train/margin": margin, "train/informative": informative}
        self.log_dict(logs, batch_size=len(batch), prog_bar=True)
        return loss

    def validation_step(self, batch: list[UnlabeledVideo], batch_idx: int) -> None:
        hp = self.hparams
        # its own random stream: the checkpoint of a step is written before that step's validation, which a resumed
        # run skips, so draws here moved every later training sample (and dropout mask) of the straight run only
        with own_random_stream(self.device, VAL_SEED + 1_000_003 * self.global_rank + batch_idx):
            _, _, greedy, _ = self.sample_and_score(batch, 1, 0.0)
            _, _, scores, rewards = self.sample_and_score(batch, hp.num_samples, hp.temperature)
        # the rows of `eval_shard`'s padding (repeats, last) ran with the others (the same calls in every process)
        # but are not counted: the means are over the held-out videos, each once, whatever the number of processes
        real = real_rows(getattr(self.trainer, "val_dataloaders", None), batch_idx, len(batch))
        if real == 0:
            return
        greedy, scores, rewards = greedy[:real], scores[:real], rewards[:real]
        modes = rw.evaluation_modes([row[0] for row in greedy], scores, rewards)
        metrics = {f"val/{k}": v for k, v in modes.items()}
        metrics |= {f"val/{k.split('/')[1]}": v for k, v in modes.items() if k.startswith("greedy/")}
        metrics |= rw.RewardStats.of(rewards, scores).to_metrics("val/reward_")
        if not getattr(self.trainer.datamodule, "val_flow", True):  # the same keys from every batch and process
            metrics = {k: v for k, v in metrics.items() if "/epe_" not in k}
        self.log_dict(metrics, batch_size=real, sync_dist=True)

    def on_train_start(self) -> None:
        self.model.train()  # the tiny model is built in eval mode; sampling switches modes itself

    def on_before_optimizer_step(self, optimizer) -> None:
        check_gradients(self, optimizer)  # a NaN gradient stops the run before it reaches the weights

    def configure_optimizers(self) -> torch.optim.Optimizer:
        params = [p for p in self.model.parameters() if p.requires_grad]
        if not params:
            raise ValueError("the policy has no trainable parameters: apply LoRA or load the adapter trainable")
        return torch.optim.AdamW(params, lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)


VAL_SEED = 20_260_601  # validation's sampling seed (per process and batch): the same candidates at every validation


@contextlib.contextmanager
def own_random_stream(device: torch.device, seed: int):
    """Run the body on torch's generators seeded with `seed` (the CPU's and `device`'s), restored after."""
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.random.default_generator.manual_seed(seed)
        if devices:
            torch.cuda.manual_seed(seed)  # the current device's
        yield


def _margin(seq: torch.Tensor, rewards: torch.Tensor) -> torch.Tensor:
    """Mean over rows of ℓ(best-scored) - ℓ(worst-scored) candidate (0 where all rewards tie)."""
    r = rewards.to(seq.device)
    rows = torch.arange(len(seq), device=seq.device)
    diff = seq[rows, r.argmax(1)] - seq[rows, r.argmin(1)]
    return torch.where(r.max(1).values > r.min(1).values, diff, torch.zeros_like(diff)).mean()
