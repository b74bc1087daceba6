"""The one timing helper of the benchmark scripts (imported by them; not a benchmark itself)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np


class Timing(NamedTuple):
    best: float  # seconds of the fastest call
    median: float  # seconds of the median call
    result: Any  # what the last call returned


def timed(fn: Callable[[], Any], repeats: int) -> Timing:
    """Call `fn` `repeats` times (at least once) and time each call with `time.perf_counter`."""
    times, out = [], None
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return Timing(float(np.min(times)), float(np.median(times)), out)
