"""Benchmark of the measured-data audit: seconds per audit (20 trajectories) and the identification rate over
seeded hidden-effect cases plus null cases, from the sealed generator in tests/audit_hidden.py.

    .venv/bin/python benchmarks/bench_audit.py [--cases 30] [--nulls 10] [--first 0]

A case counts as correct when the hidden effect is named; the line also shows whether its size came back within
25 % and the held-out error at least halved. Prints the machine load (1-minute load average) with the timings:
the audit is CPU-bound, so its seconds scale with how many cores it actually gets. No timed assertions.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from audit_hidden import EFFECTS, make_case  # noqa: E402
from test_audit import recovered  # noqa: E402

from aynamics import scene as scenelib  # noqa: E402
from aynamics.audit import audit  # noqa: E402
from aynamics.measured import read_csv  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=30, help="hidden-effect cases (effects cycle through the list)")
    ap.add_argument("--nulls", type=int, default=10, help="null cases (no hidden effect)")
    ap.add_argument("--first", type=int, default=0, help="index of the first hidden-effect case (to split runs)")
    args = ap.parse_args()
    correct = sized = halved = false_found = 0
    seconds, loads = [], []
    jobs = [(EFFECTS[k % len(EFFECTS)], 1000 + k) for k in range(args.first, args.first + args.cases)]
    jobs += [(None, 2000 + k) for k in range(args.nulls)]
    print(f"cpu cores: {os.cpu_count()}, load average at start: {os.getloadavg()[0]:.1f}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for effect, seed in jobs:
            case = make_case(effect, seed, Path(tmp) / f"{effect}_{seed}")
            t0 = time.perf_counter()
            r = audit(read_csv(case.csv), scenelib.load(case.scene), max_causes=1)
            seconds.append(time.perf_counter() - t0)
            loads.append(os.getloadavg()[0])
            size_ok = half_ok = False
            if effect is None:
                ok = r.causes == []
                false_found += not ok
            else:
                ok = effect in r.causes
                correct += ok
                if ok:
                    got, want = recovered(effect, r.parameters), case.sizes[effect]
                    size_ok = abs(got - want) <= 0.25 * abs(want)
                    half_ok = r.held_out_error_after <= 0.5 * r.held_out_error_before
                    sized += size_ok
                    halved += half_ok
            extra = "" if effect is None else f" size {'ok' if size_ok else 'off'}, halved {'yes' if half_ok else 'no'}"
            print(
                f"{effect or 'null':26s} seed {seed}: {r.verdict:11s} {','.join(r.causes) or 'none':28s} "
                f"held-out {r.held_out_error_before * 1000:6.1f} -> {r.held_out_error_after * 1000:6.1f} mm  "
                f"{seconds[-1]:5.1f} s (load {loads[-1]:.1f})  {'ok' if ok else 'WRONG'}{extra}",
                flush=True,
            )
    n = max(args.cases, 1)
    print(f"correct causes: {correct}/{args.cases} = {correct / n:.0%}")
    print(f"  of those, size within 25 %: {sized}; held-out error at least halved: {halved}")
    print(f"false findings on nulls: {false_found}/{args.nulls}")
    s = sorted(seconds)
    print(
        f"seconds per audit (20 trajectories): median {s[len(s) // 2]:.1f}, max {s[-1]:.1f}; "
        f"mean load average {sum(loads) / len(loads):.1f} on {os.cpu_count()} cores"
    )


if __name__ == "__main__":
    main()
