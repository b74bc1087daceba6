"""Scene parsing (`scene.parse`): scenes per second with libyaml's safe loader (used for texts without anchors or
aliases) against the pure-Python checked loader, on canonical 4-object scenes as the data sets store them.

    python benchmarks/bench_parse.py [--scenes 200] [--repeats 5]

Every SFT example, reward and evaluation parses YAML: building a `make train` example parses its scene twice.
"""

from __future__ import annotations

import argparse

import numpy as np
from timing import timed

from aynamics import sampler
from aynamics import scene as S
from aynamics import scene_text as T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    config = sampler.SamplerConfig(min_objects=4, max_objects=4)
    rng = np.random.default_rng(0)
    texts = [S.dump(sampler.sample_scene(rng, config)) for _ in range(args.scenes)]
    fast_loader = T._FAST_LOADER
    if fast_loader is None:
        print("PyYAML has no libyaml here: only the pure-Python loader is available")
        return
    fast = timed(lambda: [S.parse(t) for t in texts], args.repeats)
    T._FAST_LOADER = None
    try:
        slow = timed(lambda: [S.parse(t) for t in texts], args.repeats)
    finally:
        T._FAST_LOADER = fast_loader
    assert fast.result == slow.result, "the two loaders read different scenes"
    n = len(texts)
    print(f"{n} 4-object scenes, {sum(map(len, texts)) // n} characters each; best of {args.repeats}")
    print(f"libyaml safe loader:      {n / fast.best:8.0f} scenes/s ({fast.best / n * 1e3:.2f} ms each)")
    print(f"pure-Python safe loader:  {n / slow.best:8.0f} scenes/s ({slow.best / n * 1e3:.2f} ms each)")
    print(f"speed-up: {slow.best / fast.best:.1f}x")


if __name__ == "__main__":
    main()
