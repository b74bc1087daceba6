"""Test-time refinement: CMA-ES over a scene's continuous parameters so that its simulation matches a video.

The object count and shapes stay fixed; the user picks which parameters move (`params`, see
`aynamics.refine_space.param_space`): per-object groups `position`, `orientation`, `linear_velocity`,
`angular_velocity`, `friction`, `mass`, `damping`, `restitution` (every object, or one object as `box_0.position`)
and scene groups `camera`, `gravity`, each bounded by the scene language's range table.

The search is coarse to fine (see `refine`):

1. warm start: the best of the given scenes (a model's prediction, or N samples), scored in one batch;
2. track stage (when the start's IoU is below `track_below` and positions or velocities are searched): each
   object's horizontal initial position and velocity are fitted to its observed mask-centroid track
   back-projected onto the ground (`aynamics.refine_tracks`: least squares, no ray casting; several height
   hypotheses), the scorer picks the best fit, and while its IoU is still low a CMA-ES polish on the projected-
   centre distance to the centroids (physics only) follows; this pulls predictions metres off into the basin
   where masks overlap, where CMA-ES then starts with smaller steps (`track_sigma`). Objects that start on the
   floor keep their height and vertical velocity (`fix_grounded`);
3. score stages: positions and velocities first, then every chosen parameter, against the fast scorer's
   full-sequence IoU (minus a little flow EPE when the observation has flow), one batched `score` call per
   generation, with IPOP restarts when a run stalls, until the budget in simulations or seconds is spent.

    result = refine(prediction, observation, budget=1000, seconds=60)
    result.scene, result.before, result.after, result.trace

`aynamics refine PRED.yaml --observed SCENE.yaml|DIR [--budget N] [--params ...] [--out REFINED.yaml] --json`
(`aynamics.refine_cli`). Files: `refine_space` (parameters), `refine_search` (CMA-ES), `refine_objectives`,
`refine_tracks` (observed tracks), this one (the stages).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aynamics.refine_cli import add_refine_command, write_refine_animation
from aynamics.refine_objectives import objective_value, score_objective, trajectory_objective
from aynamics.refine_search import Budget, Objective, Search, cmaes_search
from aynamics.refine_space import DEFAULT_PARAMS, DEFAULT_SIGMA_SCALE, ParamSpace, grounded_dims, param_space
from aynamics.refine_tracks import (
    Tracks,
    ballistic_frames,
    centre_heights,
    compose_per_object,
    match_tracks,
    track_distances,
    track_objective,
    track_start,
)
from aynamics.scene import Scene, is_whole, require_scene

__all__ = [
    "DEFAULT_PARAMS",
    "DEFAULT_SIGMA_SCALE",
    "Budget",
    "Objective",
    "ParamSpace",
    "RefineResult",
    "Search",
    "Tracks",
    "add_refine_command",
    "cmaes_search",
    "param_space",
    "refine",
    "score_objective",
    "track_objective",
    "trajectory_objective",
    "write_refine_animation",
]

KINEMATIC = ("position", "linear_velocity")  # the groups the track stage fits
EARLY_FRAMES = 4  # sampled frames (0.4 s at the default stride) of the early-only track fit
POLISH_BELOW = 0.6  # polish the best track fit on the track objective only while its IoU is below this
TRACK_TIE = 0.05  # weight of the track objective (image heights) breaking near-ties of IoU between track fits
# Simulations the track stage spends before its CMA-ES polish, at most: 3 rollouts for centre heights, and up to 7
# fits each traced once, scored once and tracked once (+ 1 to score the polish). It runs only with that many left.
TRACK_STAGE_SIMS = 3 + 6 + 7 + 7 + 1


def _separated_start(start: Scene, value: float, observed, left: Budget, flow_weight: float, nthread, trace: list):
    """The start and its objective value, or its separated version's (`separate_start`) when that scores
    higher; the one simulation is counted in `left` and the switch in `trace`. A start that nothing overlaps, or
    that cannot be separated (still overlapping after the rounds, or pushed out of range), stays."""
    from aynamics.scorer import score
    from aynamics.separate import separate_start

    try:
        separated = separate_start(start)
    except ValueError:
        return start, value
    if not separated.moved:
        return start, value
    s = score([separated.scene], observed, nthread=nthread)[0]
    left.used += 1
    v = objective_value(s, flow_weight)
    if v <= value:
        return start, value
    trace.append((left.used, left.elapsed, v, "separated"))
    return separated.scene, v


# --------------------------------------------------------------------------------------------
# Refinement
# --------------------------------------------------------------------------------------------
@dataclass
class RefineResult:
    """A refined scene with its scores before and after, and the search's trace.

    Attributes:
        scene: the refined scene (same objects and shapes as the start).
        start: the warm-start scene: the best of the given ones, or it separated (see `refine`'s `separate`).
        before, after: `aynamics.scorer.Score` of the best given scene and of the refined scene.
        trace: (simulations used, seconds, best objective value, stage) after every generation.
        simulations: candidates simulated in all (scoring the start included).
        seconds: wall time.
        restarts: CMA-ES restarts over all stages.
    """

    scene: Scene
    start: Scene
    before: object
    after: object
    trace: list[tuple[int, float, float, str]]
    simulations: int
    seconds: float
    restarts: int

    @property
    def yaml(self) -> str:
        from aynamics.scene import dump

        return dump(self.scene)

    def to_json(self) -> dict:
        """The `aynamics refine --json` record."""
        return {
            "iou_full_before": round(float(self.before.iou_full), 4),
            "iou_full_after": round(float(self.after.iou_full), 4),
            "iou_first_before": round(float(self.before.iou_first), 4),
            "iou_first_after": round(float(self.after.iou_first), 4),
            "epe_full_before": None if self.before.epe_full is None else round(float(self.before.epe_full), 4),
            "epe_full_after": None if self.after.epe_full is None else round(float(self.after.epe_full), 4),
            "simulations": self.simulations,
            "seconds": round(self.seconds, 3),
            "restarts": self.restarts,
            "trace": [[n, round(t, 3), round(v, 4), stage] for n, t, v, stage in self.trace],
            "refined_yaml": self.yaml,
        }


def _groups(params: Sequence[str], keep: tuple[str, ...]) -> list[str]:
    """The entries of `params` (`group` or `NAME.group`) whose group is in `keep`."""
    return [p for p in params if p.rpartition(".")[2] in keep]


def _n_observed(observed) -> int:
    """Observed object ids: the largest in the segmentation + 1, or the number of names when larger."""
    n = int(observed.segmentation.max(initial=-1)) + 1
    return max(n, len(observed.names)) if observed.names is not None else n


def _track_fits(
    best: Scene, observed, params: Sequence[str], left: Budget, nthread: int | None
) -> tuple[list[Scene], Tracks | None]:
    """Least-squares fits of the objects' horizontal initial states to the observed tracks, and the tracks
    re-indexed to the scene's objects (None when no matched object is visible).

    The ground projection needs each object's centre height per frame, which the observation does not give, so
    several fits are made: at the initial heights (all frames, and the first frames only, before collisions);
    at the start's rollout heights for a fall before its first impact (where the height does not depend on the
    horizontal motion), and for all frames; at the heights of those fits' own rollouts; and one that takes
    each object from the fit whose projected centres follow its track best.
    """
    kinematic = _groups(params, KINEMATIC)
    tracks = Tracks.from_segmentation(observed.segmentation, observed.frames, _n_observed(observed), observed.grid)
    if not tracks.visible.any():
        return [], None
    names, fps, config = observed.names, observed.fps, observed.config
    rolling = _groups(params, ("angular_velocity",))  # the spheres whose spin is searched roll with their fit

    def fit(trk: Tracks, heights: np.ndarray | None, usable: np.ndarray | None = None) -> Scene:
        return track_start(best, trk, names, params=kinematic, fps=fps, rolling=rolling, heights=heights, usable=usable)

    fits = [fit(tracks, None), fit(tracks.first(EARLY_FRAMES), None)]
    heights = centre_heights(best, tracks.frames, config, nthread)
    left.used += 1
    if heights is not None:
        falling = ballistic_frames(heights)  # rollout heights for a fall before its impact, else the initial height
        flat = np.where(falling & ~falling.all(0), heights, heights[:1])
        fits += [fit(tracks, flat, falling), fit(tracks, heights)]
        for k in (2, 3):  # again at the heights of the fit's own rollout
            again = centre_heights(fits[k], tracks.frames, config, nthread)
            left.used += 1
            if again is not None:
                fits.append(fit(tracks, again))
    n = len(best.objects)
    cent = np.zeros((len(tracks.frames), n, 2))
    vis = np.zeros((len(tracks.frames), n), bool)
    for i, j in match_tracks(fits[0], tracks, names, fps):
        cent[:, i], vis[:, i] = tracks.centroids[:, j], tracks.visible[:, j]
    if not vis.any():
        return fits, None
    matched = Tracks(cent, vis, tracks.frames, tracks.width, tracks.height)
    dist, _ = track_distances(matched, fits, config, nthread)
    left.used += len(fits)
    fits.append(compose_per_object(fits, dist, vis))  # each object from the fit that follows its track best
    return fits, matched


def _track_stage(
    best: Scene,
    best_v: float,
    observed,
    params: Sequence[str],
    frozen: set[str],
    left: Budget,
    cap: int,
    cap_seconds: float,
    seed: int,
    flow_weight: float,
    nthread: int | None,
    trace: list,
) -> tuple[Scene, float, int]:
    """The best track fit by the scorer (near-ties, e.g. IoU 0 everywhere, broken by the track objective), then,
    when its IoU is still below `POLISH_BELOW`, a CMA-ES polish of its positions and velocities on the track
    objective (physics only, at most `cap` simulations and `cap_seconds`). Returns the scene, its objective value,
    restarts."""
    from aynamics.scorer import score

    fits, matched = _track_fits(best, observed, params, left, nthread)
    if not fits:
        return best, -np.inf, 0
    values = [objective_value(s, flow_weight) for s in score(fits, observed, nthread=nthread)]
    left.used += len(fits)
    rank = list(values)
    if matched is not None:
        track = track_objective(matched, observed.config, nthread)
        track_values = track(fits)
        left.used += len(fits)
        rank = [v + TRACK_TIE * t for v, t in zip(values, track_values, strict=True)]
    j = int(np.argmax(rank))
    scene, value = fits[j], values[j]
    trace.append((left.used, left.elapsed, max(best_v, value), "track-fit"))
    if matched is None or cap < 8 or value >= POLISH_BELOW:
        return scene, value, 0
    space = _space(scene, _groups(params, KINEMATIC), frozen)
    found = cmaes_search(
        track,
        space,
        space.encode(scene),
        track_values[j],
        left,
        seed=seed,
        max_sims=cap,
        max_seconds=cap_seconds,
        stop_at=-0.003,
    )
    polished = objective_value(score([found.scene], observed, nthread=nthread)[0], flow_weight)
    left.used += 1
    if polished > value:
        scene, value = found.scene, polished
    trace.append((left.used, left.elapsed, max(best_v, value), "track-polish"))
    return scene, value, found.restarts


def _space(scene: Scene, groups: Sequence[str], frozen: set[str]) -> ParamSpace:
    """`param_space` without the frozen dimensions, or with them when nothing else would be left."""
    try:
        return param_space(scene, groups, frozen)
    except ValueError:
        return param_space(scene, groups)


def _check_arguments(**values) -> None:
    """refine's numbers, as `aynamics refine` checks its options: a negative budget, seconds or sigma_scale, a NaN
    flow_weight or a share of 5 ran a search that could not move (its result the start) or failed inside CMA-ES."""

    def number(name: str) -> float:
        v = values[name]
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or math.isnan(v):
            raise ValueError(f"refine: {name} = {v!r}: must be a number")
        return float(v)

    for name in ("budget", "seed"):
        v = values[name]
        if not is_whole(v):
            raise ValueError(f"refine: {name} = {v!r}: must be a whole number")
    if values["budget"] < 1:
        raise ValueError(f"refine: budget = {values['budget']}: must be >= 1 simulation")
    if values["seed"] < 0:  # NumPy's generators refuse it, some stages only (the track stage's seed + 1 passed at -1)
        raise ValueError(f"refine: seed = {values['seed']}: must be >= 0")
    if not number("seconds") > 0:  # inf: the budget alone
        raise ValueError(f"refine: seconds = {values['seconds']}: must be > 0")
    for name in ("track_share", "kinematic_share"):
        if not 0 <= number(name) <= 1:
            raise ValueError(f"refine: {name} = {values[name]}: must be in [0, 1]")
    for name in ("track_sigma", "sigma_scale"):
        if not 0 < number(name) < math.inf:
            raise ValueError(f"refine: {name} = {values[name]}: must be a finite number > 0")
    if not 0 <= number("flow_weight") < math.inf:
        raise ValueError(f"refine: flow_weight = {values['flow_weight']}: must be a finite number >= 0")
    number("track_below")
    if values["stop_at"] is not None:
        number("stop_at")


def refine(
    initial: Scene | Sequence[Scene],
    observed,
    *,
    params: Sequence[str] = DEFAULT_PARAMS,
    budget: int = 1000,
    seconds: float = 60.0,
    seed: int = 0,
    nthread: int | None = None,
    track_below: float = 0.5,
    track_share: float = 0.2,
    kinematic_share: float = 0.5,
    track_sigma: float = 0.3,
    sigma_scale: float = DEFAULT_SIGMA_SCALE,
    flow_weight: float = 0.01,
    stop_at: float | None = None,
    fix_grounded: bool = True,
    separate: bool = True,
) -> RefineResult:
    """Refine a predicted scene against an observed video (an `aynamics.observation.Observation`).

    Args:
        initial: the prediction, or several (e.g. N samples): the best-scoring one is the warm start.
        observed: the observation (segmentation, optional flow) to match.
        params: parameter groups to search (see `param_space`); a string names one or more (comma-separated).
        budget: simulations in all (each scored or track candidate is one); the track stage runs only when
            `TRACK_STAGE_SIMS` (24) are left for it, so a small budget goes to the score stages alone.
        seconds: wall-time budget; the search stops at the first generation past it.
        seed: CMA-ES seed (results are deterministic for a seed, up to the time budget).
        nthread: simulation threads (default: all cores, at most 8).
        track_below: run the track stage when the start's full IoU is below this.
        track_share: at most this share of the budget (simulations and seconds) goes to the track stage's CMA-ES.
        kinematic_share: share of the remaining budget (simulations and seconds) for a first IoU stage over
            positions and velocities only (when `params` has more groups).
        track_sigma: multiplies the score stages' CMA-ES steps when the track stage found the start.
        sigma_scale: multiplies the initial CMA-ES steps (`param_space`'s 0.3 m, 0.5 m/s, 0.15 per quaternion
            component, ...; see `DEFAULT_SIGMA_SCALE`).
        flow_weight: objective = IoU_full - flow_weight × EPE_full (px) when the observation has flow.
        stop_at: stop once the objective reaches this value (e.g. 0.98); None spends the budget.
        fix_grounded: keep the height and vertical velocity of objects that start on the floor (`grounded_dims`).
        separate: when the best given scene starts objects inside each other or the floor, score it separated
            too (`aynamics.separate.separate_start`, one simulation) and start from the better of the two.

    Raises:
        ValueError: no initial scene, initial scenes of different structures, bad `params`, or a number out of
            its range (a budget < 1, seconds <= 0, a seed < 0, a share outside [0, 1], a NaN, ...), naming it.
        TypeError: `initial` holds something other than Scenes, or `observed` is not an Observation.
    """
    from aynamics.observation import Observation
    from aynamics.scorer import score

    start_t = time.perf_counter()
    if isinstance(params, str):  # "position" or "position, mass": one string, not its characters
        params = params.replace(",", " ").split()
    _check_arguments(
        budget=budget,
        seconds=seconds,
        seed=seed,
        track_below=track_below,
        track_share=track_share,
        kinematic_share=kinematic_share,
        track_sigma=track_sigma,
        sigma_scale=sigma_scale,
        flow_weight=flow_weight,
        stop_at=stop_at,
    )
    scenes = [initial] if isinstance(initial, Scene) else None if isinstance(initial, (str, bytes)) else list(initial)
    for k, s in enumerate(scenes or [initial]):  # a YAML text failed on "'str' object has no attribute 'structure'"
        require_scene(s, "refine: initial" if scenes is None else f"refine: initial[{k}]")
    if not isinstance(observed, Observation):
        raise TypeError(f"refine: observed is a {type(observed).__name__}, not an aynamics.scorer.Observation")
    if not scenes:
        raise ValueError("refine: no initial scene given")
    if len({s.structure for s in scenes}) > 1:
        raise ValueError(f"refine: initial scenes differ in objects: {sorted({s.structure for s in scenes})}")
    param_space(scenes[0], params)  # validate params early
    left = Budget(budget, seconds, start=start_t)
    first = score(scenes, observed, nthread=nthread)
    left.used += len(scenes)
    values = [objective_value(s, flow_weight) for s in first]
    k = int(np.argmax(values))
    start, before, best_v = scenes[k], first[k], values[k]
    trace: list[tuple[int, float, float, str]] = [(left.used, left.elapsed, best_v, "start")]
    if separate and left.left() > 0:
        start, best_v = _separated_start(start, best_v, observed, left, flow_weight, nthread, trace)
    best = start
    restarts = 0

    ground = fix_grounded and left.left() > 0  # one simulation, within the budget
    frozen = grounded_dims(start, observed.config) if ground else set()
    left.used += int(ground)
    kinematic = _groups(params, KINEMATIC)
    if kinematic and before.iou_full < track_below and left.left() >= TRACK_STAGE_SIMS:
        scene, value, r = _track_stage(
            best,
            best_v,
            observed,
            params,
            frozen,
            left,
            int(track_share * budget),
            track_share * seconds,
            seed,
            flow_weight,
            nthread,
            trace,
        )
        restarts += r
        if value > best_v:
            best, best_v = scene, value
            sigma_scale *= track_sigma  # the fit is close: search near it first

    objective = score_objective(observed, flow_weight=flow_weight, nthread=nthread)
    stages = [("score", list(params), None, None)]
    if kinematic and len(kinematic) < len(params):  # coarse to fine: positions and velocities first
        # its share of what is left in simulations AND in seconds: a budget in simulations that time cuts short
        # (a large --budget with --seconds) must still leave the other groups their turn
        share_s = kinematic_share * max(seconds - left.elapsed, 0.0)
        stages.insert(0, ("score-kinematic", kinematic, int(kinematic_share * left.left()), share_s))
    for k, (stage, groups, cap, cap_s) in enumerate(stages):
        if left.left() <= 0 or (stop_at is not None and best_v >= stop_at):
            break
        space = _space(best, groups, frozen)
        found = cmaes_search(
            objective,
            space,
            space.encode(best),
            best_v,
            left,
            seed=seed + 1 + k,
            stop_at=stop_at,
            max_sims=cap,
            max_seconds=cap_s,
            sigma_scale=sigma_scale,
        )
        restarts += found.restarts
        trace += [(n, t, v, stage) for n, t, v in found.trace[1:]]
        if found.value > best_v:
            best, best_v = found.scene, found.value
    after = score([best], observed, nthread=nthread)[0]
    return RefineResult(best, start, before, after, trace, left.used, time.perf_counter() - start_t, restarts)
