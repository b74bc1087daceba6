"""Data loaders that resume exactly and shard evaluation over processes (Lightning, DDP, FSDP alike).

`ResumableSampler` draws a shuffled order per epoch from (seed, epoch) alone, sharded over ranks, and starts
mid-epoch after a resume; `eval_shard` gives each process its share of an evaluation split, padded to equal
length (`real_rows` says which rows of a batch are padding); `loader_options` picks worker processes that suit
the accelerator. `data.SceneDataModule` builds its loaders from these.

    loader = resumable_loader(dataset, batch_size=8, seed=0, collate_fn=collate, trainer=trainer)
"""

from __future__ import annotations

import functools
import itertools
import math
import os
import signal
from typing import Any

import torch
from lightning.fabric.utilities.seed import pl_worker_init_function
from lightning.pytorch.accelerators import CPUAccelerator
from torch.utils.data import DataLoader, Sampler

MAX_AUTO_WORKERS = 4  # loader worker processes a process takes by itself (`loader_workers`)


class ResumableSampler(Sampler[int]):
    """A shuffled order per epoch from (seed, epoch) alone, sharded over ranks, that can start mid-epoch.

    Lightning calls `set_epoch`; `skip` drops the first indices of `start_epoch` (the examples a resumed run
    already trained on), so a resumed run sees exactly the batches an uninterrupted run would. `len` is always a
    whole epoch's (Lightning's restored batch count covers the skipped part).

    With `lengths` (e.g. objects per scene, which sets the target's length), consecutive runs of `batch_size`
    indices hold examples of similar length: each window of `GROUP_BATCHES` batches of the shuffled order is
    sorted by length, cut into batches, and the batches are shuffled again. Less padding per batch, the same
    examples per epoch, still a function of (seed, epoch) alone.
    """

    GROUP_BATCHES = 8

    def __init__(
        self,
        n: int,
        *,
        seed: int,
        shuffle: bool = True,
        rank: int = 0,
        world: int = 1,
        start_epoch: int = 0,
        skip: int = 0,
        lengths: list[int] | None = None,
        batch_size: int = 1,
    ) -> None:
        if not 0 <= rank < world:
            raise ValueError(f"rank = {rank}, world = {world}: need 0 <= rank < world")
        if lengths is not None and len(lengths) != n:
            raise ValueError(f"lengths has {len(lengths)} entries for {n} examples")
        self.n, self.seed, self.shuffle, self.rank, self.world = n, seed, shuffle, rank, world
        self.epoch, self.start_epoch, self.skip = start_epoch, start_epoch, skip
        self.lengths, self.batch_size = lengths, batch_size

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _order(self) -> list[int]:
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
            order = torch.randperm(self.n, generator=g).tolist()
        else:
            order = list(range(self.n))
        per_rank = math.ceil(self.n / self.world)
        order += order[: per_rank * self.world - self.n]  # pad so every rank gets the same count
        order = order[self.rank :: self.world]
        if self.lengths is None or not self.shuffle:
            return order
        g = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch + 7_919 * (self.rank + 1))
        window, grouped = self.GROUP_BATCHES * self.batch_size, []
        for start in range(0, len(order), window):
            chunk = sorted(order[start : start + window], key=lambda i: self.lengths[i])
            batches = [chunk[k : k + self.batch_size] for k in range(0, len(chunk), self.batch_size)]
            for b in torch.randperm(len(batches), generator=g).tolist():
                grouped += batches[b]
        return grouped

    def __iter__(self):
        order = self._order()
        return iter(order[self.skip :] if self.epoch == self.start_epoch else order)

    def __len__(self) -> int:
        # The whole epoch's length, also for the resumed one that yields only what is left: Lightning reads the
        # length once and counts the restored batches of that epoch as done (a shorter length cut the resumed
        # epoch, and every later one, short by the skipped batches).
        return math.ceil(self.n / self.world)


class ResumableLoader(DataLoader):
    """A DataLoader Lightning treats as resumable: its position lives in the sampler (see `ResumableSampler`).

    With `window` > 0, every batch also holds the summed label weight of the `window` consecutive batches of its
    optimizer step (`batching.with_window_weights`; `window` = the trainer's `accumulate_grad_batches`): what the
    SFT step's loss is normalised by. An epoch (and a resumed one: the sampler starts at a step's first batch)
    starts a window, as Lightning's accumulation does.
    """

    def __init__(self, *args: Any, window: int = 0, epoch_batches: int | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.window, self.epoch_batches = window, epoch_batches

    def __iter__(self):
        batches = super().__iter__()
        if not self.window:
            return batches
        from aynamics.batching import with_window_weights

        # Lightning's epoch ends after `epoch_batches` (limit_train_batches) with an optimizer step: the last
        # window ends there too, not with batches that epoch never trains on (a resumed epoch: fewer are left)
        left = self.epoch_batches
        if left is not None and self.sampler.epoch == self.sampler.start_epoch:
            left -= self.sampler.skip // self.batch_size
        return with_window_weights(batches if left is None else itertools.islice(batches, max(left, 0)), self.window)

    def state_dict(self) -> dict[str, int]:
        return {"seed": self.sampler.seed, "n": self.sampler.n}

    def load_state_dict(self, state: dict[str, int]) -> None:
        if state.get("n") != self.sampler.n:
            raise ValueError(f"resumed data set has {self.sampler.n} training examples, the checkpoint's had {state}")
        if "seed" in state and state["seed"] != self.sampler.seed:  # the order is a function of (seed, epoch)
            raise ValueError(
                f"data.seed = {self.sampler.seed}, but the checkpoint was trained with {state['seed']}: the resumed "
                "epoch would skip the first examples of another order; resume with the same seed"
            )


class EvalShard(list):
    """`eval_shard`'s indices: the first `real` are this process's own items, the rest padding."""

    def __init__(self, indices: list[int], real: int) -> None:
        super().__init__(indices)
        self.real = real


def eval_shard(n: int, trainer) -> EvalShard | None:
    """The indices of `n` validation items this process evaluates under ddp / fsdp: every world-th from its
    rank, the list padded with the first items to ceil(n / world) for each process (as torch's
    DistributedSampler pads: every process runs the same batches, which sharded weights need). The padding comes
    last in each list and is not counted (`real_rows`), so the logged means are over the n items, each once.
    None (all items, every process) for one process or fewer items than processes.
    """
    if trainer is None or trainer.world_size == 1 or n < trainer.world_size:
        return None
    world, rank = trainer.world_size, trainer.global_rank
    padded = list(range(n)) + list(range(math.ceil(n / world) * world - n))
    return EvalShard(padded[rank::world], len(range(rank, n, world)))


def real_rows(loader, batch_idx: int, rows: int) -> int:
    """How many of the `rows` rows of batch `batch_idx` of an evaluation `loader` are items of its own, not the
    padding of `eval_shard` (which comes last): all of them for a loader without padding. E.g. 5 items over 2
    processes, batches of 2: rank 1 evaluates items 1, 3 and 0 (padding), so its batch 1 has 0 real rows of 1."""
    real = getattr(getattr(loader, "sampler", None), "real", None)
    if real is None:
        return rows
    return max(0, min(rows, real - batch_idx * loader.batch_size))


def loader_workers(num_workers: int | None, trainer, cache: bool = False) -> int:
    """DataLoader worker processes: `num_workers`, or for None (`data.num_workers: null`, the default) 0 when the
    model trains on the CPU (its threads use the cores: loading in the training process was fastest on 2 cores) or
    examples are cached (`data.cache`: each worker would hold its own copy of the data set), and on GPUs up to
    `MAX_AUTO_WORKERS` per process, one core left to the process: from the cores it may use (`sched_getaffinity`)
    shared among the node's processes, or all of them when srun started each process as a task with its own
    (`SLURM_CPUS_PER_TASK`, and the processes created outside Lightning).
    A container's CPU quota is not seen: set the number there. Building an example at 480×320 with 4 frames (PNG
    decoding, the processor) took 58 ms on one core here: 0.23 s per batch of 4 in the training process."""
    if num_workers is not None:
        return num_workers
    if _on_cpu(trainer) or cache:
        return 0
    from aynamics.simulate import usable_cores

    cores = usable_cores()
    environment = getattr(getattr(trainer, "strategy", None), "cluster_environment", None)
    own = bool(os.environ.get("SLURM_CPUS_PER_TASK")) and getattr(environment, "creates_processes_externally", False)
    share = cores if own else cores // max(trainer.num_devices, 1)  # srun's task per GPU has its own cores
    return max(0, min(MAX_AUTO_WORKERS, share - 1))


def loader_options(num_workers: int | None, trainer, cache: bool = False) -> dict[str, Any]:
    """DataLoader keywords for this trainer: the workers (`loader_workers`), kept between epochs and deaf to
    SIGTERM (the training process saves and stops on it, `run_callbacks.StepCheckpoint`; a worker running Lightning's
    handler, inherited at the fork, failed), and pinned host memory when the model is on a GPU."""
    workers = loader_workers(num_workers, trainer, cache)
    options = {"num_workers": workers, "persistent_workers": workers > 0, "pin_memory": not _on_cpu(trainer)}
    if workers:
        rank, seeded = getattr(trainer, "global_rank", 0), os.environ.get("PL_SEED_WORKERS", "0") == "1"
        options["worker_init_fn"] = functools.partial(init_worker, rank=rank, seeded=seeded)
    return options


def init_worker(worker_id: int, rank: int, seeded: bool) -> None:
    """A DataLoader worker's start: SIGTERM ignored (the training process acts on it; the worker ends with it),
    then Lightning's seeding of the worker when `seed_everything(workers=True)` asked for it (our own
    `worker_init_fn` replaces Lightning's)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if seeded:
        pl_worker_init_function(worker_id, rank=rank)


def _on_cpu(trainer) -> bool:
    accelerator = getattr(trainer, "accelerator", None)  # none: no trainer (yet), one process on the CPU
    return accelerator is None or isinstance(accelerator, CPUAccelerator)


def resumable_loader(
    ds,
    trainer,
    *,
    batch_size: int,
    seed: int,
    lengths=None,
    collate_fn=None,
    num_workers: int | None = 0,
    cache: bool = False,
    window_weights: bool = False,
) -> ResumableLoader:
    """The training loader of `ds` for this process: its shard of every epoch's order (`ResumableSampler`), and
    after a resume (`trainer.global_step` is restored before loaders are built) past what was trained on.
    `trainer` None: one process from the start. `num_workers` None: see `loader_workers`. `window_weights`: each
    batch holds its optimizer step's summed label weight (`ResumableLoader`; SFT batches of dicts with labels)."""
    rank, world, start_epoch, skip, accum, batches = 0, 1, 0, 0, 1, None
    if trainer is not None:
        rank, world = trainer.global_rank, trainer.world_size
        # Lightning steps the optimizer on each epoch's last batch too, so an epoch is ceil(batches / accum) steps;
        # its last batch is the one `limit_train_batches` leaves (a count, or a share of the loader's batches)
        batches = epoch_batches(
            math.ceil(math.ceil(len(ds) / world) / batch_size), getattr(trainer, "limit_train_batches", 1.0)
        )
        accum = trainer.accumulate_grad_batches
        start_epoch, steps = divmod(trainer.global_step, math.ceil(batches / accum)) if batches else (0, 0)
        skip = steps * accum * batch_size
    sampler = ResumableSampler(
        len(ds),
        seed=seed,
        rank=rank,
        world=world,
        start_epoch=start_epoch,
        skip=skip,
        lengths=lengths,
        batch_size=batch_size,
    )
    return ResumableLoader(
        ds,
        batch_size=batch_size,
        sampler=sampler,
        collate_fn=collate_fn,
        generator=torch.Generator().manual_seed(seed),  # worker seeds: not from the global RNG
        window=accum if window_weights else 0,
        epoch_batches=batches,
        **loader_options(num_workers, trainer, cache),
    )


def epoch_batches(batches: int, limit) -> int:
    """The batches of a training epoch that Lightning runs of a loader of `batches` under `limit_train_batches`
    `limit` (a count, or a share: Lightning's `_parse_num_batches`)."""
    if isinstance(limit, int) and not isinstance(limit, bool):
        return min(batches, limit)
    return int(batches * limit) if isinstance(limit, float) else batches
