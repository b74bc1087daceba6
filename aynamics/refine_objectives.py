"""Objectives of test-time refinement: pure, batched `list[Scene] -> list[float]`, higher is better.

- `trajectory_objective`: distance of object centres to a known target rollout (physics only; tests, benchmarks).
- `aynamics.refine_tracks.track_objective`: projected centres against observed mask centroids (physics only).
- `score_objective`: the fast scorer's full-sequence IoU (minus a little flow EPE), one `score` call per batch.
"""

from __future__ import annotations

import numpy as np

from aynamics.refine_search import Objective
from aynamics.scene import Scene


def raw_positions(scenes: list[Scene], config, nthread: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(n, T, N, 3) positions of same-structure scenes from one batched rollout, and (n,) validity.

    A batch that MuJoCo refuses as a whole (e.g. a fatal error) comes back invalid (nan), never as an exception.
    """
    import mujoco

    from aynamics.simulate import MAX_DISTANCE, rollout_raw

    try:
        raw = rollout_raw(scenes, scenes[0].structure, config, nthread)
    except (mujoco.FatalError, RuntimeError, ValueError, FloatingPointError):
        n_obj = len(scenes[0].objects)
        return np.full((len(scenes), config.frames + 1, n_obj, 3), np.nan), np.zeros(len(scenes), bool)
    cols = raw.template.qpos_adr[:, None] + np.arange(3)  # (N, 3)
    pos = raw.qpos[:, :, cols]  # (n, T, N, 3)
    ok = np.isfinite(pos).all(axis=(1, 2, 3)) & (raw.warnings == 0)
    with np.errstate(invalid="ignore"):
        ok &= (np.abs(np.nan_to_num(pos, nan=np.inf)) < MAX_DISTANCE).all(axis=(1, 2, 3))
    return pos, ok


def by_structure(scenes: list[Scene]) -> dict[tuple[str, ...], list[int]]:
    """Indices of the scenes grouped by structure (object types in order), each group simulated as one batch."""
    groups: dict[tuple[str, ...], list[int]] = {}
    for k, s in enumerate(scenes):
        groups.setdefault(s.structure, []).append(k)
    return groups


def trajectory_objective(target: Scene, config=None, nthread: int | None = None) -> Objective:
    """Minus the mean distance (m) between a candidate's object centres and the target's, over all frames.

    A physics-only objective for known ground truth (tests, benchmarks of the search itself); diverging or
    differently built candidates score -100.
    """
    from aynamics.rollout import SimConfig

    config = config or SimConfig()
    ref, ok = raw_positions([target], config, 1)
    if not ok[0]:
        raise ValueError("trajectory_objective: the target scene's own simulation diverges")

    def objective(scenes: list[Scene]) -> list[float]:
        out = [-100.0] * len(scenes)
        for structure, idx in by_structure(scenes).items():
            if structure != target.structure:
                continue
            pos, good = raw_positions([scenes[k] for k in idx], config, nthread)
            err = np.linalg.norm(pos - ref, axis=-1).mean(axis=(1, 2))  # (n,)
            for j, k in enumerate(idx):
                out[k] = -float(err[j]) if good[j] else -100.0
        return out

    return objective


def score_objective(observed, *, flow_weight: float = 0.01, nthread: int | None = None) -> Objective:
    """Full-sequence IoU from the fast scorer (one batched `score` call per generation), minus
    `flow_weight` × full-sequence EPE (px at 480 wide) when the observation has flow. Invalid candidates: 0 IoU."""
    from aynamics.scorer import score

    def objective(scenes: list[Scene]) -> list[float]:
        return [objective_value(s, flow_weight) for s in score(scenes, observed, nthread=nthread)]

    return objective


def objective_value(s, flow_weight: float) -> float:
    """Objective of one Score: IoU_full - flow_weight × EPE_full (invalid scores have IoU 0 and the EPE penalty),
    minus the depth in metres of an overlapping start (`Score.overlap`): every invalid candidate scored alike, so
    the search had no way out of a start sunk into the floor or another object; shallower is now better."""
    epe = float(s.epe_full) if s.epe_full is not None else 0.0
    return float(s.iou_full) - flow_weight * epe - float(s.overlap)
