"""Benchmark of the measured-data audit: seconds per audit (20 trajectories) and the identification rate over
seeded hidden-effect cases plus null cases, from the sealed generator in tests/audit_hidden.py.

    .venv/bin/python benchmarks/bench_audit.py [--cases 30] [--nulls 10]

Prints one line per case and the totals; no timed assertions.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from audit_hidden import EFFECTS, make_case  # noqa: E402

from aynamics import scene as scenelib  # noqa: E402
from aynamics.audit import audit  # noqa: E402
from aynamics.measured import read_csv  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=30, help="hidden-effect cases (effects cycle through the list)")
    ap.add_argument("--nulls", type=int, default=10, help="null cases (no hidden effect)")
    args = ap.parse_args()
    correct = false_found = 0
    seconds = []
    jobs = [(EFFECTS[k % len(EFFECTS)], 1000 + k) for k in range(args.cases)] + [
        (None, 2000 + k) for k in range(args.nulls)
    ]
    with tempfile.TemporaryDirectory() as tmp:
        for effect, seed in jobs:
            case = make_case(effect, seed, Path(tmp) / f"{effect}_{seed}")
            t0 = time.perf_counter()
            r = audit(read_csv(case.csv), scenelib.load(case.scene), max_causes=1)
            seconds.append(time.perf_counter() - t0)
            ok = r.causes == [] if effect is None else effect in r.causes
            if effect is None:
                false_found += not ok
            else:
                correct += ok
            print(
                f"{effect or 'null':26s} seed {seed}: {r.verdict:11s} {','.join(r.causes) or 'none':40s} "
                f"held-out {r.held_out_error_before * 1000:6.1f} -> {r.held_out_error_after * 1000:6.1f} mm  "
                f"{seconds[-1]:5.1f} s  {'ok' if ok else 'WRONG'}",
                flush=True,
            )
    print(f"correct causes: {correct}/{args.cases} = {correct / max(args.cases, 1):.0%}")
    print(f"false findings on nulls: {false_found}/{args.nulls}")
    print(
        f"seconds per audit (20 trajectories): median {sorted(seconds)[len(seconds) // 2]:.1f}, max {max(seconds):.1f}"
    )


if __name__ == "__main__":
    main()
