"""Peak memory and time of `logprobs.token_logprobs` (forward + backward) at Qwen2.5-VL's vocabulary (151 936):
the one-pass float32 log_softmax against checkpointed chunks (`CHUNK_ENTRIES`), on bfloat16 logits as a GPU run
holds them. PRO scores N candidates per video this way (and SFT its targets); each variant runs in its own process
so that its peak resident memory is its own.

    python benchmarks/bench_logprobs.py [--rows 4] [--positions 513]

rows x positions are the candidates x the longest candidate + 1 (PRO keeps only those positions' logits). The
CPU figures stand in for GPU memory: the same tensors are allocated; the time ratio on a GPU is not measured.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

VOCAB = 151_936


def _one(rows: int, positions: int, chunk_entries: int) -> dict:
    import torch

    from aynamics.logprobs import token_logprobs

    torch.manual_seed(0)
    logits = torch.randn(rows, positions, VOCAB, dtype=torch.bfloat16).requires_grad_()
    labels = torch.full((rows, positions), -100)
    labels[:, 1:] = torch.randint(0, VOCAB, (rows, positions - 1))
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB, with the logits allocated
    start = time.perf_counter()
    logp, _ = token_logprobs(logits, labels, chunk_entries=chunk_entries)
    logp.sum().backward()
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"extra_gb": (peak - base) * 1024 / 1e9, "seconds": seconds, "sum": float(logp.sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=4)
    ap.add_argument("--positions", type=int, default=513)
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # child: run one variant
    args = ap.parse_args()
    if args.one is not None:
        print(json.dumps(_one(args.rows, args.positions, args.one)))
        return
    from aynamics.logprobs import CHUNK_ENTRIES

    logits_gb = args.rows * args.positions * VOCAB * 2 / 1e9
    print(
        f"token_logprobs forward + backward, {args.rows} x {args.positions} positions x {VOCAB} (bf16 logits "
        f"{logits_gb:.2f} GB), peak resident memory above the logits:"
    )
    results = {}
    for name, entries in (("one pass", 1 << 62), ("chunks", CHUNK_ENTRIES)):
        cmd = [sys.executable, __file__, "--rows", str(args.rows), "--positions", str(args.positions)]
        done = subprocess.run([*cmd, "--one", str(entries)], capture_output=True, text=True, check=True)
        results[name] = json.loads(done.stdout.strip().splitlines()[-1])
        r = results[name]
        print(f"  {name:8s}: {r['extra_gb']:.2f} GB, {r['seconds']:.1f} s")
    a, b = results["one pass"], results["chunks"]
    assert abs(a["sum"] - b["sum"]) <= 1e-3 * abs(a["sum"]), (a["sum"], b["sum"])
    print(
        f"  chunks / one pass: memory {b['extra_gb'] / a['extra_gb']:.2f}x, time {b['seconds'] / a['seconds']:.2f}x "
        "(the same sum of log-probabilities)"
    )


if __name__ == "__main__":
    main()
