"""CMA-ES (the `cmaes` package) with IPOP-style restarts under a budget of simulations and seconds.

The objective is batched: one call per generation with every candidate scene, higher is better.

    budget = Budget(simulations=1000, seconds=60)
    found = cmaes_search(objective, space, space.encode(scene), objective([scene])[0], budget)
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from cmaes import CMA

from aynamics.refine_space import ParamSpace
from aynamics.scene import Scene, SceneError

Objective = Callable[[list[Scene]], list[float]]  # higher is better; one call per generation


@dataclass
class Budget:
    """Simulations and seconds left to a whole refinement (shared by its stages)."""

    simulations: int
    seconds: float
    used: int = 0
    start: float = field(default_factory=time.perf_counter)

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def left(self) -> int:
        return 0 if self.elapsed >= self.seconds else max(0, self.simulations - self.used)


@dataclass
class Search:
    """Outcome of `cmaes_search`: best point and value, and the trace (simulations, seconds, best value)."""

    x: np.ndarray
    value: float
    scene: Scene
    trace: list[tuple[int, float, float]]
    restarts: int
    generations: int


def cmaes_search(
    objective: Objective,
    space: ParamSpace,
    x0: np.ndarray,
    value0: float,
    budget: Budget,
    *,
    sigma_scale: float = 1.0,
    seed: int = 0,
    stop_at: float | None = None,
    patience: int = 8,
    min_improvement: float = 1e-3,
    max_sims: int | None = None,
    max_seconds: float | None = None,
) -> Search:
    """Maximise `objective` over the space from x0 (whose value is value0) with IPOP-style CMA-ES restarts.

    Each generation is one `objective` call. A run restarts from the best point so far when CMA-ES reports
    convergence or the best value has not improved by `min_improvement` for `patience` generations; restarts
    alternate a wider search with a doubled population and a narrower local one. Candidates that do not decode
    to a valid scene count as the generation's worst. `max_sims` and `max_seconds` cap this search's own share of
    the shared `budget` (a stage of a refinement).
    """
    started = time.perf_counter()
    rng = np.random.default_rng(seed)
    best_x, best_v = np.asarray(x0, float).copy(), float(value0)
    best_scene = space.decode(best_x)
    trace = [(budget.used, budget.elapsed, best_v)]
    steps = np.maximum(space.steps * sigma_scale, 1e-4)
    dim = len(steps)
    base_pop = 4 + int(3 * math.log(dim))
    restarts = generations = 0
    spent = 0
    while True:
        wide = restarts % 2 == 1
        pop = base_pop * (2 ** ((restarts + 1) // 2))
        scale = (2.0 if wide else 1.0) * (0.5 ** (restarts // 4))
        sigma = float(steps.max() * scale)
        cov = np.diag((steps * scale / sigma) ** 2)
        es = CMA(
            mean=np.clip(best_x, 1e-6, 1 - 1e-6),
            sigma=sigma,
            bounds=np.tile([0.0, 1.0], (dim, 1)),
            seed=int(rng.integers(2**31)),
            population_size=pop,
            cov=cov,
        )
        run_best, stall = best_v, 0
        while True:
            left = budget.left() if max_sims is None else min(budget.left(), max_sims - spent)
            out_of_time = max_seconds is not None and time.perf_counter() - started >= max_seconds
            if left < pop or out_of_time or (stop_at is not None and best_v >= stop_at):
                return Search(best_x, best_v, best_scene, trace, restarts, generations)
            xs = [es.ask() for _ in range(pop)]
            scenes, ok = [], []
            for x in xs:
                try:
                    scenes.append(space.decode(x))
                    ok.append(True)
                except SceneError:
                    ok.append(False)
            values = list(objective(scenes)) if scenes else []
            budget.used += len(scenes)
            spent += len(scenes)
            generations += 1
            it = iter(zip(scenes, values, strict=True))
            full = [next(it) if good else (None, -math.inf) for good in ok]
            finite = [v for _, v in full if math.isfinite(v)]
            worst = min(finite) - 1.0 if finite else -1e6
            es.tell([(x, -(v if math.isfinite(v) else worst)) for x, (_, v) in zip(xs, full, strict=True)])
            k = int(np.argmax([v for _, v in full]))
            if full[k][1] > best_v:
                best_x, best_v, best_scene = xs[k].copy(), float(full[k][1]), full[k][0]
            trace.append((budget.used, budget.elapsed, best_v))
            if best_v > run_best + min_improvement:
                run_best, stall = best_v, 0
            else:
                stall += 1
            if es.should_stop() or stall >= patience:
                restarts += 1
                break
