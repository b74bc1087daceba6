"""Random states of every process, saved in checkpoints and restored for an exact resume.

LoRA dropout, PRO's sampling and data augmentation draw from torch's, NumPy's and Python's generators (and the
current GPU's). Under ddp or fsdp each process draws its own numbers, so each one's states are saved (gathered
into the checkpoint rank 0 writes) and each process restores its own:

    checkpoint["rng"] = rng.gathered_states()        # in on_save_checkpoint, on every process (it gathers)
    rng.restore(checkpoint["rng"], self.global_rank)  # at the first batch after resuming
"""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch
import torch.distributed as dist


def local_state() -> dict[str, Any]:
    """This process's generator states, as plain types and tensors (checkpoints load with weights_only=True)."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, gauss],
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():  # the current device's (LoRA dropout on a GPU)
        state["cuda"] = torch.cuda.get_rng_state()
    return state


def gathered_states() -> dict[str, list[dict[str, Any]]]:
    """Every process's `local_state`, by rank. Called on every process when several run (it gathers)."""
    mine = local_state()
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return {"per_rank": [mine]}
    states: list = [None] * dist.get_world_size()
    dist.all_gather_object(states, mine)
    return {"per_rank": states}


def restore(saved: dict[str, Any], rank: int) -> None:
    """Set this process's generators to the states `gathered_states` saved for `rank`.

    A checkpoint of another number of processes gives rank r the states of rank r mod its count (an exact
    resume needs the same count anyway: the data are split by it). Checkpoints written before the states were
    kept per rank hold one set (rank 0's), and their "cuda" entry a list over all devices."""
    states = saved.get("per_rank", [saved])
    state = states[rank % len(states)]
    torch.set_rng_state(state["torch"])
    kind, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    random.setstate(state["python"])
    cuda = state.get("cuda")
    if cuda is not None and torch.cuda.is_available():
        if isinstance(cuda, list | tuple):  # older checkpoints: every device's state from rank 0's process
            device = torch.cuda.current_device()
            cuda = cuda[device] if device < len(cuda) else None
        if cuda is not None:
            torch.cuda.set_rng_state(cuda)
