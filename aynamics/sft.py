"""The SFT stage: teach the vision-language model to write the scene (optionally after its motion reasoning).

A LightningModule around `lm.build_model(spec)` (a Qwen2.5-VL with LoRA on the language model). The loss is
the token-mean negative log-likelihood of the response tokens only (`lm.sft_loss`), over every response token of an
optimizer step (all its micro-batches under gradient accumulation, all processes: `_step_mean`). Checkpoints hold the
trainable weights (the adapter) plus the optimizer, scheduler, loop counters and RNG states, so a resumed run
continues exactly; `run_callbacks.AdapterExport` writes the peft folder that `PeftModel.from_pretrained` loads.

    module = SFTModule(ModelSpec(kind="tiny"), lr=1e-3, warmup_steps=10)
    Trainer(max_steps=20).fit(module, datamodule=SceneDataModule(...))
"""

from __future__ import annotations

import dataclasses
import logging
import math

import lightning as L
import torch

from aynamics import adapters, lm, sharding, visual_targets
from aynamics.batching import label_weight, model_inputs, window_weight
from aynamics.data import real_rows
from aynamics.model import find_visual
from aynamics.processor import IGNORE_INDEX

SCHEDULES = ("cosine", "constant")
log = logging.getLogger(__name__)


def lr_factor(step: int, *, warmup_steps: int, total_steps: int, schedule: str, min_ratio: float) -> float:
    """Learning-rate multiplier at optimizer step `step`: linear warm-up, then cosine decay to `min_ratio` (or flat)."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    if schedule == "constant" or total_steps <= warmup_steps:
        return 1.0
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


def training_steps(trainer: L.Trainer) -> int:
    """The optimizer steps the fit will take (the learning-rate schedule's length).

    Raises:
        ValueError: neither trainer.max_steps nor trainer.max_epochs limits training (both -1).
    """
    total = trainer.estimated_stepping_batches
    if not math.isfinite(total):
        raise ValueError(
            f"trainer.max_steps = {trainer.max_steps}, trainer.max_epochs = {trainer.max_epochs}: training has no end, "
            "so the learning-rate schedule has no length; set trainer.max_steps (or trainer.max_epochs) to a count >= 1"
        )
    return int(total)


def check_gradients(module: L.LightningModule, optimizer: torch.optim.Optimizer) -> None:
    """Log the gradient norm before clipping (`train/grad_norm`) and stop the run when it is not finite; called
    from `on_before_optimizer_step` (after fp16's unscaling, before clipping).

    A NaN or inf gradient (a diverged step) would be written into the weights by the optimizer step that follows,
    then into the next checkpoint, `last.ckpt` and the adapter folder: stopped here, with the step named, every
    file written so far keeps finite weights. Every process stops together: under ddp the gradients are the same
    on every process after the all-reduce, under fsdp the norm is global. Under fp16 loss scaling the norm is
    logged but an inf is the scaler's cue to skip the step, not an error; under DeepSpeed (which keeps the
    gradients itself) nothing is checked.

    Raises:
        FloatingPointError: the gradient norm is NaN or inf.
    """
    from lightning.pytorch.strategies import DeepSpeedStrategy

    try:
        trainer = module.trainer
    except RuntimeError:  # a module not attached to a Trainer, stepped by hand: nothing to log to or stop
        return
    if isinstance(trainer.strategy, DeepSpeedStrategy):
        return
    grads = [p.grad for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
    if not grads:
        return
    norm = torch.nn.utils.get_total_norm(grads)
    if hasattr(norm, "full_tensor"):  # fsdp: each process holds a shard; the norm of all of them
        norm = norm.full_tensor()
    module.log("train/grad_norm", norm.detach().float(), on_step=True, on_epoch=False, batch_size=1)
    if not torch.isfinite(norm) and getattr(trainer.precision_plugin, "scaler", None) is None:
        raise FloatingPointError(
            f"the gradient norm is {norm.item()} at step {trainer.global_step + 1}: training diverged (the step "
            "was not taken; the checkpoints written so far hold finite weights). Resume from the last one with a lower "
            "stage.module.lr, or check the data of this step"
        )


class SFTModule(adapters.ExactResume, L.LightningModule):
    """Supervised fine-tuning on (frames, response) pairs.

    Args:
        spec: The base model and adapter (plain values: the model is built here, never passed in).
        lr: Peak learning rate of AdamW.
        weight_decay: AdamW weight decay.
        warmup_steps: Optimizer steps of linear warm-up.
        schedule: "cosine" (decay to `min_lr_ratio * lr` at the last step) or "constant".
        min_lr_ratio: Final learning rate as a share of `lr` (cosine), in [0, 1].
        betas: AdamW betas.
        vision_aux_weight: Weight of the dense visual loss (`aynamics.visual_targets`): a linear head on the
            merged visual tokens learns what each token covers. For vision towers trained from scratch (the
            tiny model), which the language loss alone does not teach to see; needs `data.visual_targets=true`
            and a trainable vision tower. 0 (default): off.
        vision_warmup_steps: Steps of the dense visual loss alone (vision tower + head, batches of the data's
            batch size, peak `lr`) at the start of a fresh run, before the language model trains: learnt only
            jointly, the visual tokens become informative after the language model has learned to ignore them.
            Needs vision_aux_weight > 0. Skipped on resume (the checkpoint holds the warmed-up tower). Trains on
            the data module's `warmup_dataset()`: the training examples, plus `data.warmup_views` other frame
            choices of each scene.
        vision_augment: Mirror and recolour the frames during that warm-up (`visual_targets.Augment`).
        vision_share_weight: Weight of the pixel-share term of the dense loss (`visual_targets.aux_loss`).
        vision_lr_scale: Learning rate of a trainable vision tower (and of the dense head) in training, as a
            share of `lr` (a vision warm-up itself uses `lr`): below 1 for a pretrained tower fine-tuned beside
            the adapter; 0 keeps a warmed-up tower as it is while the language model learns to read it (its
            gradients are dropped before clipping). 1 (default): one parameter group. A run resumes only with
            the value it was trained with. Measured (`make train` data and model, count accuracy on 32 held-out
            scenes, ±0.08): after a 4000-step warm-up with `data.warmup_views=4`, 0 gave 0.56 and 0.38 (seeds 0,
            1) against 0.31 with the tower trained on (seed 0), and `make train`'s 0.47 and 0.41 (README: status).
    """

    def __init__(
        self,
        spec: lm.ModelSpec | dict,
        lr: float = 2e-4,
        weight_decay: float = 0.0,
        warmup_steps: int = 0,
        schedule: str = "cosine",
        min_lr_ratio: float = 0.1,
        betas: tuple[float, float] = (0.9, 0.999),
        vision_aux_weight: float = 0.0,
        vision_warmup_steps: int = 0,
        vision_augment: bool = True,
        vision_share_weight: float = visual_targets.SHARE_WEIGHT,
        vision_lr_scale: float = 1.0,
    ) -> None:
        super().__init__()
        finite = all(math.isfinite(x) for x in (lr, weight_decay))  # inf trained to NaN, nan failed inside torch
        if not finite or lr <= 0 or weight_decay < 0 or warmup_steps < 0 or not 0 <= min_lr_ratio <= 1:
            raise ValueError(
                f"lr = {lr}, weight_decay = {weight_decay}, warmup_steps = {warmup_steps}, min_lr_ratio = "
                f"{min_lr_ratio}: need finite lr > 0 and weight_decay >= 0, warmup_steps >= 0, 0 <= min_lr_ratio <= 1"
            )
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule = {schedule!r}: must be one of {SCHEDULES}")
        if len(betas) != 2 or not all(isinstance(b, int | float) and 0 <= b < 1 for b in betas):
            # torch refused them only when the optimizer was made, inside fit: a traceback once the model had loaded
            raise ValueError(f"stage.module.betas = {list(betas)}: need two numbers in [0, 1)")
        if not (vision_aux_weight >= 0 and math.isfinite(vision_aux_weight)):
            raise ValueError(f"vision_aux_weight = {vision_aux_weight}: must be a finite number >= 0")
        if not (vision_share_weight >= 0 and math.isfinite(vision_share_weight)):
            raise ValueError(f"vision_share_weight = {vision_share_weight}: must be a finite number >= 0")
        if not (vision_lr_scale >= 0 and math.isfinite(vision_lr_scale)):
            raise ValueError(f"vision_lr_scale = {vision_lr_scale}: must be a finite number >= 0")
        if vision_warmup_steps < 0 or (vision_warmup_steps and not vision_aux_weight):
            raise ValueError(
                f"vision_warmup_steps = {vision_warmup_steps}: must be >= 0, and > 0 only with vision_aux_weight > 0"
                f" (got {vision_aux_weight})"
            )
        spec = spec if isinstance(spec, lm.ModelSpec) else lm.ModelSpec(**spec)  # a dict: from a checkpoint
        self.save_hyperparameters(
            {
                "spec": dataclasses.asdict(spec),
                "lr": lr,
                "weight_decay": weight_decay,
                "warmup_steps": warmup_steps,
                "schedule": schedule,
                "min_lr_ratio": min_lr_ratio,
                "betas": list(betas),
                "vision_aux_weight": vision_aux_weight,
                "vision_warmup_steps": vision_warmup_steps,
                "vision_augment": vision_augment,
                "vision_share_weight": vision_share_weight,
                "vision_lr_scale": vision_lr_scale,
            }
        )
        self.spec = spec
        self.model = lm.build_model(spec)
        self.visual_head: visual_targets.Head | None = None
        self._visual_tokens: torch.Tensor | None = None
        self._merge_size = 2
        if vision_aux_weight > 0:
            if not spec.train_vision:
                raise ValueError(
                    f"vision_aux_weight = {vision_aux_weight} trains the vision tower: set model.train_vision=true"
                )
            visual = find_visual(self.model)
            self._merge_size = visual.spatial_merge_size  # tokens per frame, for the frame-count statistic
            self.visual_head = visual_targets.Head(visual.config.out_hidden_size)
            visual.register_forward_hook(self._keep_visual_tokens)
        self.strict_loading = False  # checkpoints hold only the trainable weights; the base is rebuilt from spec

    def configure_model(self) -> None:
        """Under `trainer=fsdp` (a device mesh is set): shard the model and the dense visual head."""
        sharding.shard_module(self, (self.visual_head,))

    # ------------------------------------------------------------------ steps
    def _keep_visual_tokens(self, module, args, output) -> None:
        self._visual_tokens = getattr(output, "pooler_output", output)  # merged tokens, in the processor's order

    def _loss(
        self, batch: dict[str, torch.Tensor], weighted: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Mean response NLL, token count, logits; `weighted`: with the data's `loss_weights` if any (training)."""
        logits = self.model(**model_inputs(batch), use_cache=False).logits
        return *lm.sft_loss(logits, batch["labels"], batch.get("loss_weights") if weighted else None), logits

    def _no_targets(self) -> ValueError:
        return ValueError(
            f"stage.module.vision_aux_weight = {self.hparams.vision_aux_weight} needs per-token targets: set "
            "data.visual_targets=true"
        )

    def _vision_aux(
        self, batch: dict[str, torch.Tensor], bs: int, prefix: str, real: int | None = None
    ) -> torch.Tensor | None:
        """The dense visual loss of the forward just run (None when off), with its statistics logged; with `real`,
        of the batch's first `real` examples only (the rest `eval_shard`'s padding; none: nothing logged)."""
        if self.visual_head is None:
            return None
        if "visual_targets" not in batch:
            raise self._no_targets()
        tokens, targets = self._visual_tokens, batch["visual_targets"]
        if tokens is None or tokens.shape[0] != targets.shape[0]:
            got = None if tokens is None else tuple(tokens.shape)
            raise ValueError(f"visual tokens {got} do not match visual_targets {tuple(targets.shape)}")
        grid = batch["video_grid_thw"] if "video_grid_thw" in batch else batch["image_grid_thw"]
        self._visual_tokens = None
        if real is not None and real < bs:  # an example's grid rows (its frames, or its video) are consecutive
            if real == 0:
                return None
            grid = grid[: real * (grid.shape[0] // bs)]
            keep = sum(visual_targets.frame_tokens(grid, self._merge_size))
            tokens, targets, bs = tokens[:keep], targets[:keep], real
        aux, stats = visual_targets.aux_loss(
            self.visual_head(tokens),
            targets,
            visual_targets.frame_tokens(grid, self._merge_size),
            self.hparams.vision_share_weight,
        )
        self.log(f"{prefix}/vision_aux", aux, batch_size=bs, sync_dist=prefix != "train")
        for k, v in stats.items():
            self.log(f"{prefix}/vision_{k}", v, batch_size=bs, sync_dist=prefix != "train")
        return aux

    def on_fit_start(self) -> None:
        """With the dense visual loss: check the data has its targets; on a fresh run with vision_warmup_steps > 0,
        train the vision tower on that loss alone first."""
        if self.visual_head is None:
            return
        datamodule = self.trainer.datamodule
        if datamodule is None or not getattr(datamodule, "visual_targets", False):
            raise self._no_targets()
        steps = self.hparams.vision_warmup_steps
        # Resuming (global_step is restored only after this hook): the checkpoint holds the warmed-up weights.
        if not steps or self.trainer.ckpt_path is not None:
            return
        if sharding.is_sharded(self.model):
            raise ValueError(
                f"stage.module.vision_warmup_steps = {steps} with sharded weights (trainer=fsdp): the warm-up runs "
                "the vision tower outside the model's forward, which FSDP2 cannot order; set it to 0, or warm up "
                "under trainer=cpu / ddp"
            )
        history = visual_targets.warm_up(
            find_visual(self.model),
            self.visual_head,
            datamodule.warmup_dataset(),
            steps=steps,
            batch_size=datamodule.batch_size,
            lr=self.hparams.lr,
            seed=datamodule.seed,
            augment=visual_targets.Augment.of(datamodule.processor.image_processor)
            if self.hparams.vision_augment
            else None,
            share_weight=self.hparams.vision_share_weight,
        )
        if self.trainer.world_size > 1:  # every rank ran the same steps; make sure they hold rank 0's weights
            # on the CPU: CUDA tensors pickled by the broadcast would unpickle onto rank 0's GPU on every rank
            warmed = {k: v.detach().cpu() for k, v in self.state_dict().items() if "visual" in k}
            self.load_state_dict(self.trainer.strategy.broadcast(warmed), strict=False)
        for row in history:
            for k, v in row.items():
                if k != "step" and self.logger is not None:
                    self.logger.log_metrics({f"warmup/vision_{k}": v}, step=row["step"])
        last = history[-1]
        log.info(
            "vision warm-up: %d steps, token count accuracy %.3f, object recall %.3f, frame count accuracy %.3f",
            steps,
            last["count_acc"],
            last["object_recall"],
            last["frame_count_acc"],
        )

    def _step_mean(self, loss: torch.Tensor, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The micro-batch's share of the optimizer step's token mean: Lightning divides each micro-batch's loss
        by `accumulate_grad_batches` and ddp / fsdp average the processes' gradients, which of per-micro-batch means
        weighed a token of a short response more than one of a long response. Scaled here by this batch's label
        weight over the step's (every micro-batch, every process: `batching.with_window_weights`), the step's
        gradient is that of sum(nll) / sum(weights) over all its tokens, as one batch of them all gives. A batch
        of a loader that does not record its step's weight keeps its own mean."""
        total = window_weight(batch)
        if total is None or self._trainer is None:
            return loss
        trainer = self.trainer
        if trainer.world_size > 1:  # every process's window (float64 on the device: NCCL and gloo reduce it)
            total = trainer.strategy.reduce(total.to(loss.device).clone(), reduce_op="sum").cpu()
        scale = label_weight(batch) * trainer.accumulate_grad_batches * trainer.world_size / total.clamp(min=1e-12)
        return loss * scale.to(loss.device, loss.dtype).reshape(())  # exactly 1 for one process without accumulation

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        loss, n, _ = self._loss(batch, weighted=True)  # validation and test report the plain mean
        bs = batch["input_ids"].shape[0]
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        aux = self._vision_aux(batch, bs, "train")
        if aux is not None:
            self.log("train/total_loss", loss + self.hparams.vision_aux_weight * aux, batch_size=bs)
        self.log("train/response_tokens", n.float(), batch_size=bs, reduce_fx="sum", on_step=True, on_epoch=False)
        self.log("train/lr", self.optimizers().param_groups[0]["lr"], batch_size=bs, on_step=True, on_epoch=False)
        loss = self._step_mean(loss, batch)  # logged above as this batch's mean; trained as its share of the step's
        return loss if aux is None else loss + self.hparams.vision_aux_weight * aux

    def _without_padding(
        self, batch: dict[str, torch.Tensor], loader, batch_idx: int
    ) -> tuple[dict[str, torch.Tensor], int]:
        """The batch with the labels of `eval_shard`'s padding rows (repeats, which come last) masked, so that the
        token-weighted means count each held-out item once whatever the number of processes, and how many rows are
        real. The padding rows still run (every process makes the same calls)."""
        real = real_rows(loader, batch_idx, batch["labels"].shape[0])
        if real == batch["labels"].shape[0]:
            return batch, real
        labels = batch["labels"].clone()
        labels[real:] = IGNORE_INDEX
        return {**batch, "labels": labels}, real

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        batch, real = self._without_padding(batch, getattr(self.trainer, "val_dataloaders", None), batch_idx)
        loss, n, logits = self._loss(batch)
        bs = batch["input_ids"].shape[0]
        # Weighted by token counts, the epoch values are means over every response token of the split (not means
        # of batch means: a batch of short answers would weigh as much as one of long answers).
        tokens = int(n)
        if tokens:  # a batch without response tokens has no loss to average in
            self.log("val/loss", loss, prog_bar=True, batch_size=tokens, sync_dist=True)
        self._vision_aux(batch, bs, "val", real)
        types = batch.get("type_tokens")
        n_types = 0 if types is None else lm.token_count(batch["labels"], types)
        if n_types:  # teacher-forced: which shape comes next, or the camera (no more)
            acc = lm.token_accuracy(logits, batch["labels"], types)
            self.log("val/type_acc", acc, batch_size=n_types, sync_dist=True)
        shifted = lm.shifted_visuals(batch)
        if shifted is not None and tokens:  # does the model look? the same with another example's frames
            other_loss, _, other = self._loss(shifted)
            self.log("val/image_gap", other_loss - loss, batch_size=tokens, sync_dist=True)
            if n_types:
                acc = lm.token_accuracy(other, batch["labels"], types)
                self.log("val/type_acc_other_frames", acc, batch_size=n_types, sync_dist=True)

    def test_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        loss, n, _ = self._loss(
            self._without_padding(batch, getattr(self.trainer, "test_dataloaders", None), batch_idx)[0]
        )
        if int(n):  # a mean over the split's tokens, as val/loss
            self.log("test/loss", loss, batch_size=int(n), sync_dist=True)

    def configure_optimizers(self):
        params = [p for p in self.parameters() if p.requires_grad]  # the model's, and the visual head's
        if not params:
            raise ValueError("no trainable parameters: check model.lora_* and model.train_vision")
        hp = self.hparams
        scale = hp.vision_lr_scale
        groups: list[dict] = [{"params": params}]
        if scale != 1.0:  # a second group only when it differs: optimizer states of earlier runs still load
            vision = {id(p) for p in find_visual(self.model).parameters()}
            if self.visual_head is not None:
                vision |= {id(p) for p in self.visual_head.parameters()}
            rest = [p for p in params if id(p) not in vision]
            tower = [p for p in params if id(p) in vision]
            groups = [g for g in ({"params": rest}, {"params": tower, "lr": hp.lr * scale}) if g["params"]]
        opt = torch.optim.AdamW(groups, lr=hp.lr, weight_decay=hp.weight_decay, betas=tuple(hp.betas))
        total = training_steps(self.trainer) if self._trainer is not None else 1
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt,
            lambda step: lr_factor(
                step,
                warmup_steps=hp.warmup_steps,
                total_steps=total,
                schedule=hp.schedule,
                min_ratio=hp.min_lr_ratio,
            ),
        )
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # ------------------------------------------------------------------ checkpoints
    def check_checkpoint(self, checkpoint: dict) -> None:
        """Refuse a checkpoint written for another model, optimizer layout or prompt (target, modality, frames:
        the adapter would have learnt two; before anything loads under fsdp)."""
        super().check_checkpoint(checkpoint)
        stored = (checkpoint.get("aynamics_meta") or {}).get("prompt")
        prompt = getattr(getattr(self._trainer, "datamodule", None), "prompt", None) if self._trainer else None
        mismatch = lm.prompt_mismatch(stored, prompt) if isinstance(stored, dict) and prompt is not None else None
        if mismatch:
            raise ValueError(f"the checkpoint was trained with {mismatch[0]}, but the data are set to {mismatch[1]}")
        if isinstance(stored, dict) and prompt is not None and "examples" in stored:
            if tuple(stored["examples"]) != tuple(prompt.examples):
                raise ValueError(
                    f"the checkpoint was trained with {len(stored['examples'])} in-context examples in its prompt, but "
                    f"the data are set to {len(prompt.examples)} (data.num_examples, decimals, object_names, "
                    "objects_last): resume with the same ones"
                )
        saved = checkpoint.get("hyper_parameters", {}).get("vision_lr_scale", 1.0)
        if saved != self.hparams.vision_lr_scale:  # other parameter groups: the optimizer state would not fit
            raise ValueError(
                f"stage.module.vision_lr_scale = {self.hparams.vision_lr_scale}, but the checkpoint was trained with "
                f"{saved}: resume with the same value"
            )

    def on_train_start(self) -> None:
        # A resumed run restores the optimizer's rates of the step it stopped at, while the scheduler follows this
        # run's schedule (a larger max_steps stretches the cosine): the first step takes the schedule's rate too
        # (it took the old run's last one). A fresh run or one resumed on its own schedule: the same rates.
        for config in self.trainer.lr_scheduler_configs:
            sch = config.scheduler
            if isinstance(sch, torch.optim.lr_scheduler.LambdaLR):
                for group, fn, base in zip(sch.optimizer.param_groups, sch.lr_lambdas, sch.base_lrs, strict=True):
                    group["lr"] = base * fn(sch.last_epoch)

    def on_before_optimizer_step(self, optimizer) -> None:
        # Before clipping: a group at lr 0 (vision_lr_scale = 0) is fixed, so its gradients must not count in the
        # clipped norm (they would shrink the adapter's steps), nor reach AdamW (which skips a None gradient).
        for group in optimizer.param_groups:
            if group.get("initial_lr", group["lr"]) == 0:  # its base rate (schedulers keep it as initial_lr)
                for p in group["params"]:
                    p.grad = None
        check_gradients(self, optimizer)  # without the groups dropped here
