"""Generation with sharded weights (`trainer=fsdp`): `sharding.gathered` (each unit gathered once per `generate`
call) against gathering every layer again for every token, on 2 CPU processes (gloo) with the tiny model.

    python benchmarks/bench_fsdp_generate.py [--tokens 128] [--repeats 3]

The scene evaluation and PRO's sampling generate under fsdp on every rank. On the CPU the transfers are memory
copies; across GPUs each token's gathers move the whole model, so the ratio here is a floor, not the GPU figure.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from timing import timed


def _worker(rank: int, rendezvous: str, tokens: int, repeats: int, out: dict) -> None:
    # a file, not a free port found beforehand, which another job may take meanwhile (a run beside other
    # distributed tests aborted once with SIGABRT; a taken port is the likely cause, not proven)
    dist.init_process_group("gloo", init_method=f"file://{rendezvous}", rank=rank, world_size=2)
    torch.set_num_threads(1)
    from torch.distributed.device_mesh import init_device_mesh

    from aynamics import lm, sharding

    torch.manual_seed(0)
    model = lm.build_model(lm.ModelSpec(kind="tiny")).eval()
    sharding.shard_model(model, init_device_mesh("cpu", (2,)))
    ids = torch.tensor([[1, 2, 3, 4] * 8])

    def generate(context):
        with torch.no_grad(), context(model):
            return model.generate(
                input_ids=ids, max_new_tokens=tokens, min_new_tokens=tokens, do_sample=False, synced_gpus=True
            )

    per_token = timed(lambda: generate(lambda _m: contextlib.nullcontext()), repeats)
    gathered = timed(lambda: generate(sharding.gathered), repeats)
    if rank == 0:
        out.update(
            per_token=per_token.median,
            gathered=gathered.median,
            same=bool(torch.equal(per_token.result, gathered.result)),
            sharded_after=sharding.is_sharded(model),
        )
    dist.destroy_process_group()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tokens", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as folder, mp.Manager() as manager:
        out = manager.dict()
        mp.spawn(_worker, args=(os.path.join(folder, "rendezvous"), args.tokens, args.repeats, out), nprocs=2)
        r = dict(out)
    print(f"{args.tokens} greedy tokens, tiny model, 2 CPU processes (median of {args.repeats}):")
    print(f"  gathered per token  {r['per_token']:.3f} s")
    print(f"  gathered per call   {r['gathered']:.3f} s   ({r['per_token'] / r['gathered']:.2f}x faster)")
    print(f"  same tokens: {r['same']}; weights sharded again after: {r['sharded_after']}")


if __name__ == "__main__":
    main()
