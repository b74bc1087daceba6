"""Adapter folders and training checkpoints: what a run leaves, what `predict`, `evaluate` and a resumed run read.

An adapter folder is peft's (`PeftModel.from_pretrained(base, DIR)` loads it) plus `aynamics.json`, the model and
prompt specs that rebuild the base model and show the frames as training did. A training checkpoint holds the
trainable weights only, with the same specs, and resumes exactly (`ExactResume`).

    save_adapter(model, "out/adapter", spec, prompt)         # written whole, then swapped in (kill-safe)
    model, spec, prompt = load_adapter("out/adapter", "cpu")  # the base rebuilt, the adapter on it
    adapter_from_checkpoint("run/checkpoints/last.ckpt", "out/adapter")
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import torch

from aynamics import rng
from aynamics.lm import (
    ModelSpec,
    PromptSpec,
    build_base,
    build_model,
    inference_device,
    prompt_mismatch,
    runnable_kernel,
)

ADAPTER_META = "aynamics.json"  # written next to the peft adapter: how to rebuild the base model and the prompt


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


def _suggested_checkpoint(folder: Path) -> str | None:
    """The checkpoint of `folder` to name when a folder was given for one: last.ckpt, else the last by name."""
    found = sorted(p.name for p in folder.glob("*.ckpt"))
    return "last.ckpt" if "last.ckpt" in found else found[-1] if found else None


def check_resume_settings(path: str | Path, spec: ModelSpec, prompt: PromptSpec | None = None) -> None:
    """Refuse, before the model is built, a `ckpt_path` written for another base or adapter (`check_same_base`) or,
    given `prompt`, another prompt (target, modality, frames: `lm.prompt_mismatch`). The modules check both again
    as Lightning loads the checkpoint, which is after the model has loaded: minutes for the 3B. A path that is no
    checkpoint file (a DeepSpeed folder) is left to them."""
    path = Path(path)
    if not path.is_file():
        return
    ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    check_same_base(ckpt.get("hyper_parameters", {}).get("spec"), spec)
    stored = (ckpt.get("aynamics_meta") or {}).get("prompt")
    if isinstance(stored, dict) and prompt is not None and (mismatch := prompt_mismatch(stored, prompt)):
        raise ValueError(f"the checkpoint was trained with {mismatch[0]}, but the data are set to {mismatch[1]}")


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
        pick = _suggested_checkpoint(path)
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
        pick = _suggested_checkpoint(checkpoint)
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
