"""Fully sharded data parallel training (FSDP2) of the LoRA-wrapped model: `trainer=fsdp`.

    python train.py stage=sft model=qwen2_5_vl_7b trainer=fsdp              # every visible GPU
    python train.py stage=sft trainer=fsdp trainer.accelerator=cpu trainer.devices=2   # 2 CPU processes (gloo)

Each decoder layer, each vision block, the vision tower, the model and the dense visual head become
`torch.distributed.fsdp.fully_shard` units (FSDP2) in the modules' `configure_model`, on Lightning's
`ModelParallelStrategy` with one data-parallel dimension over all processes (`FullyShardedDataParallel` below).
A layer's weights are gathered for its forward and backward only, so no GPU holds the whole model at once.
Only rank 0 loads the base (host memory: ~16 GB for the 7B in bfloat16); every other process builds the model on
the meta device (`model_init_context`, no weights read or allocated) and, once sharded, receives rank 0's weights
and buffers, the LoRA weights' initialisation and an `init_adapter` included (`shard_from_rank0`).

Why FSDP2 and not Lightning's `FSDPStrategy` (FSDP1): FSDP1 flattens a unit's parameters into one tensor and
refuses mixed dtypes (`Must flatten tensors with uniform dtype but got torch.bfloat16 and torch.float32`), which
is what a bfloat16 base with peft's float32 LoRA weights is; FSDP2 keeps every parameter a DTensor shard of its
own dtype. FSDP2 also runs on the CPU (gloo), so this path is tested here (`tests/test_train.py`, slow).

Sharded weights change three things elsewhere, all handled through this module:
- generation: every forward gathers weights from every process, so all processes generate together
  (`synced_gpus`, `generation_kwargs`), also for the scene evaluation (each process its share of the prompts,
  padded to the same calls), with the units kept gathered for the whole call (`gathered`: 2.6x faster for 128
  tokens on 2 idle CPU processes, `benchmarks/bench_fsdp_generate.py`; across GPUs each token's gathers would
  move the whole model);
- the adapter: its weights are gathered on every process before rank 0 writes it (`trainable_state`);
- checkpoints: only the trainable weights are gathered (the frozen base is rebuilt from the spec).
"""

from __future__ import annotations

import contextlib
import itertools
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.strategies import ModelParallelStrategy
from torch.distributed.tensor import DTensor

# Module classes that become their own shard unit (besides the tower, the model and the head).
UNIT_CLASSES = ("Qwen2_5_VLDecoderLayer", "Qwen2_5_VLVisionBlock")


def is_sharded(module: torch.nn.Module) -> bool:
    """Whether `module`'s weights are DTensor shards (a `fully_shard` model)."""
    return any(isinstance(p, DTensor) for p in module.parameters())


def generation_kwargs(model: torch.nn.Module) -> dict[str, Any]:
    """`generate` arguments for `model`: with sharded weights, `synced_gpus=True`, so a process whose responses
    ended keeps taking part in the others' forwards (each gathers weights from every process)."""
    return {"synced_gpus": True} if is_sharded(model) else {}


def data_parallel_mesh(mesh):
    """The 1-D data-parallel mesh to shard over (`ModelParallelStrategy`'s mesh is 2-D: data x tensor
    parallel; `fully_shard` on a 2-D mesh would replicate over the first dimension instead of sharding)."""
    return mesh["data_parallel"] if mesh.ndim > 1 else mesh


@contextlib.contextmanager
def gathered(model: torch.nn.Module):
    """Keep a sharded model's units gathered from their first forward to the end of the block, then shard them
    again (a no-op for a model that is not sharded). For `generate`: otherwise every new token gathers every
    layer's weights from every process again (the 7B model: ~15 GB of transfers a token); inside, a process
    holds the whole model (the 7B: ~16 GB in bfloat16), as an unsharded one would."""
    from torch.distributed.fsdp import FSDPModule

    units = [m for m in model.modules() if isinstance(m, FSDPModule)]
    for m in units:
        m.set_reshard_after_forward(False, recurse=False)
    try:
        yield
    finally:
        for m in units:
            m.set_reshard_after_forward(True, recurse=False)
            m.reshard()


def trainable_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The trainable weights of `module` as full CPU tensors, keyed as in its `state_dict`.

    With sharded weights every process must call it (each weight is gathered from all of them, in the same
    order); every process gets the full tensors.
    """
    from torch.distributed.fsdp import FSDPModule

    for m in module.modules():  # a unit left gathered after a forward (the root, after generation) holds plain
        if isinstance(m, FSDPModule):  # tensors on some ranks and shards on others: shard every unit first
            m.reshard()
    out = {}
    for name, p in module.named_parameters():
        if p.requires_grad:
            full = p.full_tensor() if isinstance(p, DTensor) else p
            # a copy: full_tensor() may return a wrapper awaiting the gather (no storage of its own: safetensors
            # and peft's alias check crashed on it), and an unsharded weight must not alias the live parameter
            out[name] = full.detach().to("cpu", copy=True)
    return out


def shard_model(
    model: torch.nn.Module, mesh, extra: tuple[torch.nn.Module | None, ...] = (), *, vision: bool = True
) -> None:
    """Make `model` (a peft-wrapped Qwen2.5-VL) fully sharded over `mesh`'s processes, in place.

    Units, innermost first: every decoder layer and vision block (by class name, so the copies peft makes for
    `modules_to_save` are included), the vision tower (called on its own by the vision warm-up and the dense
    loss), then the Hugging Face model under peft (the module whose `forward` and `generate` run), and each
    module of `extra` (trainable modules outside the model, e.g. the dense visual head: every trainable weight
    must be in a unit, or its gradients would not be averaged over the processes).
    """
    from torch.distributed.fsdp import fully_shard, register_fsdp_forward_method

    from aynamics.model import find_visual

    for m in list(model.modules()):
        if type(m).__name__ in UNIT_CLASSES:
            fully_shard(m, mesh=mesh)
    if vision:
        fully_shard(find_visual(model), mesh=mesh)
    root = hf_model(model)
    fully_shard(root, mesh=mesh)
    # `generate` gathers the root's own weights like `forward` does: a first call before any forward (PRO's
    # first step samples) otherwise ran the vision tower as a root of its own and failed
    register_fsdp_forward_method(root, "generate")
    for m in extra:
        if m is not None:
            fully_shard(m, mesh=mesh)


def shard_module(module, extra: tuple[torch.nn.Module | None, ...] = ()) -> None:
    """A LightningModule's `configure_model` under `trainer=fsdp`: shard its `model` (and `extra`) over the
    strategy's data-parallel processes with rank 0's weights (`shard_from_rank0`); nothing without a device mesh
    (other strategies) or when already done."""
    if module.device_mesh is not None and not is_sharded(module.model):
        shard_from_rank0(module, data_parallel_mesh(module.device_mesh), extra)


def model_init_context(trainer) -> contextlib.AbstractContextManager:
    """Where a module builds its model before `trainer` fits it: under `trainer=fsdp` on the meta device on every
    process but rank 0 (no weights read or allocated; `shard_from_rank0` gives it rank 0's), else as usual (every
    process builds its own). The trainer knows its rank before the process group exists (Lightning's launcher
    and torchrun set it in the environment)."""
    if isinstance(trainer.strategy, FullyShardedDataParallel) and trainer.global_rank != 0:
        return torch.device("meta")
    return contextlib.nullcontext()


def shard_from_rank0(module: torch.nn.Module, mesh, extra: tuple[torch.nn.Module | None, ...] = ()) -> None:
    """Shard `module.model` (and `extra`, `shard_model`) over `mesh`, every process with rank 0's weights and
    buffers: all of `module`'s parameters, the non-persistent buffers (rotary `inv_freq`) that no state dict holds
    too. A process whose module is on the meta device (`model_init_context`) allocates its shards here; the
    others' values are replaced by rank 0's (equal where built from the same seed). `mesh` spans every process.
    Rank 0 holds its full weights until they are broadcast, beside its shards (on the GPU; in host memory on the
    CPU: 1 + 1 / processes times the model there, against about 1 for sharding alone).

    Raises:
        ValueError: a process built another model than rank 0 (a weight's name, shape or dtype differs).
    """
    import torch.distributed as dist
    from torch.distributed.checkpoint.state_dict import StateDictOptions, set_model_state_dict

    _check_same_model(module)
    full = module.state_dict() if dist.get_rank() == 0 else {}  # references: the sharding would free the weights
    shard_model(module.model, mesh, extra)
    tensors = itertools.chain(module.parameters(), module.buffers())
    if any(t.is_meta for t in tensors):
        if mesh.device_type == "cpu":
            device = torch.device("cpu")
        else:  # the device FSDP2 moved rank 0's shards to: the process's current one
            device = torch.device(mesh.device_type, torch.get_device_module(mesh.device_type).current_device())
        module.to_empty(device=device)
    options = StateDictOptions(full_state_dict=True, broadcast_from_rank0=True)
    set_model_state_dict(module, full, options=options)
    del full
    for buffer in module.buffers():  # unsharded: the same on every process
        dist.broadcast(buffer, src=0)


def _check_same_model(module: torch.nn.Module) -> None:
    """Raise on every process when one built another model than rank 0 (a meta-device build that drifted from
    `from_pretrained`): its weights would be cast or misplaced silently, its buffers' broadcast could hang."""
    import torch.distributed as dist

    named = itertools.chain(module.named_parameters(), module.named_buffers())
    mine = [(name, tuple(t.shape), str(t.dtype).removeprefix("torch.")) for name, t in named]
    rank0 = [mine]
    dist.broadcast_object_list(rank0, src=0)
    diff = next((f"{a} (rank 0: {b})" for a, b in itertools.zip_longest(mine, rank0[0]) if a != b), None)
    diffs: list[str | None] = [None] * dist.get_world_size()
    dist.all_gather_object(diffs, diff)
    bad = next(((rank, d) for rank, d in enumerate(diffs) if d is not None), None)
    if bad is not None:
        raise ValueError(f"rank {bad[0]} built another model than rank 0: weight (name, shape, dtype) {bad[1]}")


def hf_model(model: torch.nn.Module) -> torch.nn.Module:
    """The Hugging Face model under a peft wrapper (the model itself when not wrapped)."""
    base = getattr(model, "base_model", None)  # PeftModel -> LoraModel
    return getattr(base, "model", model) if base is not None else model


class FullyShardedDataParallel(ModelParallelStrategy):
    """Lightning's `ModelParallelStrategy` as plain FSDP2 data parallelism: one data-parallel dimension over all
    processes (no tensor parallelism), checkpoints as one file holding the trainable weights (gathered on every
    process, written by rank 0). The modules shard themselves in `configure_model` (`shard_from_rank0`), built on
    the meta device on every process but rank 0 (`model_init_context`)."""

    def __init__(self, process_group_backend: str | None = None, **kwargs: Any) -> None:
        super().__init__(
            data_parallel_size="auto",
            tensor_parallel_size=1,
            save_distributed_checkpoint=False,
            process_group_backend=process_group_backend,
            **kwargs,
        )

    def setup_environment(self) -> None:
        self._data_parallel_size = self.num_nodes * self.num_processes  # every process is a data-parallel rank
        super().setup_environment()

    def lightning_module_state_dict(self) -> dict[str, Any]:
        """The trainable weights only (Lightning's gathers the whole model, frozen base included, each time)."""
        state = trainable_state(self.lightning_module)
        return state if self.global_rank == 0 else {}

    def load_checkpoint(self, checkpoint_path, weights_only: bool | None = None) -> dict[str, Any]:
        """Load a one-file checkpoint written under any strategy (fsdp, ddp, cpu) into the sharded model.

        Lightning's loader reads integer optimizer-state keys as positions among all the model's parameters
        (frozen ones included), which is how FSDP checkpoints number them but not how a cpu / ddp checkpoint does
        (0..n-1 over the optimizer's own): resuming one of those under fsdp failed with a size mismatch. Here
        the saved ids are named by their position in the saved parameter groups, which both layouts keep in the
        optimizer's order. The module's `check_checkpoint(checkpoint)`, when it has one, runs first, so a
        checkpoint of another model is named before anything loads (Lightning calls `on_load_checkpoint` only
        after loading the weights and optimizer).
        """
        from lightning.fabric.strategies.model_parallel import _load_raw_module_state
        from torch.distributed.checkpoint.state_dict import StateDictOptions, set_optimizer_state_dict

        path = Path(self.broadcast(checkpoint_path))
        if not path.is_file():  # a distributed checkpoint folder: Lightning's own loader
            return super().load_checkpoint(path, weights_only=weights_only)
        checkpoint = torch.load(path, mmap=True, map_location="cpu", weights_only=weights_only)
        module = self.lightning_module
        check = getattr(module, "check_checkpoint", None)
        if check is not None:
            check(checkpoint)
        _load_raw_module_state(checkpoint["state_dict"], module, world_size=self.world_size, strict=False)
        options = StateDictOptions(full_state_dict=True, broadcast_from_rank0=True)
        for optimizer, state in zip(self.optimizers, checkpoint.get("optimizer_states", ()), strict=False):
            named = named_optimizer_state(state, optimizer, module)
            set_optimizer_state_dict(module, optimizer, optim_state_dict=named, options=options)
        return checkpoint


def named_optimizer_state(state: dict[str, Any], optimizer: torch.optim.Optimizer, module: torch.nn.Module) -> dict:
    """A saved optimizer state dict keyed by `module`'s parameter names: the j-th id of saved group i is the
    j-th parameter of the optimizer's group i (as `torch.optim.Optimizer.load_state_dict` pairs them).

    Raises:
        ValueError: the saved groups do not have the optimizer's sizes (another model or stage setting).
    """
    saved = [list(g["params"]) for g in state["param_groups"]]
    current = [list(g["params"]) for g in optimizer.param_groups]
    if [len(g) for g in saved] != [len(g) for g in current]:
        raise ValueError(
            f"checkpoint optimizer groups of {[len(g) for g in saved]} parameters, this run's of "
            f"{[len(g) for g in current]}: resume with the model.* and stage settings it was written with"
        )
    names = {id(p): n for n, p in module.named_parameters()}
    key = {pid: names[id(p)] for ids, params in zip(saved, current, strict=True) for pid, p in zip(ids, params)}
    return {
        "state": {key[k]: v for k, v in state["state"].items()},
        "param_groups": [{**g, "params": [key[i] for i in g["params"]]} for g in state["param_groups"]],
    }
