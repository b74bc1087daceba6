"""A process of `test_train.test_fsdp_gradients_equal_data_parallel_ones` (spawned twice, gloo on the CPU)."""

from __future__ import annotations

import contextlib
import os
import sys

import torch
import torch.distributed as dist


def main(rank: int, dataset: str, out: str) -> None:
    from torch.distributed.device_mesh import init_device_mesh

    from aynamics import lm, sharding
    from aynamics.data import SceneDataModule
    from aynamics.sft import SFTModule

    # the two processes meet in a file, not on a port: a free port chosen by the test could be taken before use
    dist.init_process_group("gloo", init_method=f"file://{os.environ['FSDP_TEST_STORE']}", rank=rank, world_size=2)
    torch.set_num_threads(1)
    spec = lm.ModelSpec(kind="tiny", lora_dropout=0.0, train_vision=True)
    dm = SceneDataModule(dataset, spec.processor_path, num_frames=2, batch_size=2, visual_targets=True)
    dm.setup("fit")
    batches = iter(dm.train_dataloader())
    batch = [next(batches) for _ in range(rank + 1)][-1]  # a different batch on each rank

    def grads(shard: bool) -> dict[str, torch.Tensor]:
        torch.manual_seed(0)
        # sharded: rank 1 builds on the meta device, as under trainer=fsdp, and takes rank 0's weights
        with torch.device("meta") if shard and rank else contextlib.nullcontext():
            module = SFTModule(spec, vision_aux_weight=1.0)
        assert all(p.is_meta == (shard and rank == 1) for p in module.parameters())
        if shard:
            mesh = init_device_mesh("cpu", (2,))
            sharding.shard_from_rank0(module, mesh, (module.visual_head,))
            assert not any(t.is_meta for t in [*module.parameters(), *module.buffers()])
        loss, _, _ = module._loss(batch)
        (loss + module._vision_aux(batch, 2, "train")).backward()
        out = {}
        for name, p in module.named_parameters():
            if p.requires_grad:
                g = p.grad.full_tensor() if shard else p.grad.clone()
                if not shard:
                    dist.all_reduce(g)  # data parallel: the mean over the ranks
                    g /= 2
                out[name] = g.detach().to("cpu", copy=True)
        return out

    data_parallel, sharded = grads(False), grads(True)
    if rank == 0:
        torch.save({"ddp": data_parallel, "fsdp": sharded}, out)
    dist.barrier()  # neither process tears gloo down while the other still uses it (one aborted under load)
    dist.destroy_process_group()


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2], sys.argv[3])
