"""Pure metric functions comparing a predicted scene (its segmentation, flow, state) with an observed one.

Everything here is a plain function of arrays or scenes, with no rendering or simulation inside, so the scorer,
evaluation and rewards share one definition of each number.

Matching. Predicted objects are paired with observed ones once per video: objects whose chosen names appear on
both sides are paired by name; the rest are paired by an optimal assignment (Hungarian, `scipy.optimize.
linear_sum_assignment`) that maximises mask overlap (IoU over the whole sequence), or, for state errors, minimises
the distance between initial positions. Pairs the assignment finds with zero overlap count as unmatched (a
pair by chosen name is kept: one object, placed wrong, counted once). Names of the form `{type}_{k}`
(what `parse` gives an unnamed object, and what generated scenes carry) only number the objects in list order,
which a video does not show: they are not paired by name, so a model that lists two boxes in the other order is
not scored as if it had swapped them.

Segmentation IoU. For frame k, every object visible in frame k on either side contributes its IoU with its
partner (0 when unmatched or when its partner is not visible); the frame's score is the mean of those, and 1 when
no object is visible on either side. `iou_first` is frame 0, `iou_full` the mean over all frames.

Flow EPE. The end-point error ‖f_pred − f_obs‖ in pixels, averaged over the observed object pixels whose flow
is not occluded (the video's foreground), and in a frame showing no object over the predicted object pixels.
The pixels averaged over do not depend on the prediction, so objects drawn where the video has none neither dilute
the error nor, through a small divisor, inflate it; the IoU scores them. (Averaged over both sides' object pixels,
a still wall filling the view scored 0.09 px against 1.77 px for the true scene with its velocities zeroed; now
2.57 and 2.56, the error of no motion: 12 generated scenes, the scorer's 480-wide pixels.) Frames without any
such pixel are skipped; `epe_first` is frame 0, `epe_full` the mean over the remaining frames; either is 0 when
it has no such pixel (nothing shown on either side: nothing to get wrong), as in the scorer and the rewards.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from aynamics.scene import Scene, SceneError, is_default_name, parse, require_scene

MAX_HISTOGRAM = 2**24  # cells of the joint id histogram (F × (Np + 1) × (No + 1)): 128 MB of counts
POSITION_MAE_INVALID = 10.0  # m: state MAE given to a prediction that cannot be parsed (half the position range)
VELOCITY_MAE_INVALID = 20.0  # m/s: likewise (the velocity range's bound)


# --------------------------------------------------------------------------------------------
# Matching
# --------------------------------------------------------------------------------------------
def match_objects(
    pred_names: Sequence[str] | None,
    obs_names: Sequence[str] | None,
    score: np.ndarray,
    *,
    pred_rank: Sequence[int] | None = None,
    obs_rank: Sequence[int] | None = None,
) -> list[tuple[int, int]]:
    """Pair predicted objects i with observed objects j: equal chosen names first, the rest by optimal assignment.

    Args:
        pred_names, obs_names: object names, or None when a side has none (e.g. masks from a folder). Default
            names (`scene.is_default_name`: `box_0`, `sphere_1`, ...) are list positions, not identities, and
            are left to the assignment.
        score: (Np, No) how well i fits j, higher better (mask IoU, or minus a distance); pairs whose score is
            0 after assignment (no overlap) are dropped (distances: pass `-dist - eps`, so that none is).
        pred_rank, obs_rank: each object's place in an order of the objects' contents (`content_rank`), in which
            they enter the assignment: where several assignments score alike, the one it returns then does not
            depend on the order the objects are listed in (default: list order).

    Returns:
        (i, j) pairs, sorted by i, each index at most once.
    """
    score = _score_matrix(score)
    n_pred, n_obs = score.shape
    for side, names, n in (("pred_names", pred_names, n_pred), ("obs_names", obs_names, n_obs)):
        if isinstance(names, (str, bytes)) or (names is not None and len(names) > n):  # names past the matrix
            raise ValueError(f"match_objects: {side} = {names!r}: must be a list of at most {n} names (score's shape)")
        # None in pred_names failed on a bare TypeError in the default-name regex; in obs_names it matched nothing
        for k, name in enumerate(() if names is None else names):
            if not isinstance(name, str):
                raise ValueError(f"match_objects: {side}[{k}] = {name!r}: object names must be str")
    for side, rank, n in (("pred_rank", pred_rank, n_pred), ("obs_rank", obs_rank, n_obs)):
        if rank is not None and len(rank) != n:
            raise ValueError(f"match_objects: {side} has {len(rank)} entries for {n} objects (score's shape)")
    pairs: list[tuple[int, int]] = []
    free_p, free_o = list(range(n_pred)), list(range(n_obs))
    if pred_rank is not None:  # ties of the assignment are broken by content, not by list order
        free_p.sort(key=lambda i: pred_rank[i])
    if obs_rank is not None:
        free_o.sort(key=lambda j: obs_rank[j])
    if pred_names is not None and obs_names is not None:
        where = {name: j for j, name in enumerate(obs_names)}
        for i, name in enumerate(pred_names):
            j = None if is_default_name(name) else where.get(name)
            if j is not None and j in free_o:
                pairs.append((i, j))
                free_p.remove(i)
                free_o.remove(j)
    if free_p and free_o:
        sub = score[np.ix_(free_p, free_o)]
        rows, cols = linear_sum_assignment(sub, maximize=True)
        pairs += [(free_p[r], free_o[c]) for r, c in zip(rows, cols, strict=True) if sub[r, c] != 0]
    return sorted(pairs)


def content_rank(rows) -> np.ndarray:
    """rank[i]: the place of row i of `rows` (N, K) in lexicographic order of the rows (equal rows by index).

    Objects described by their rows (masks' pixel counts, initial states) enter `match_objects`' assignment in
    this order, so that which of several equally good assignments it picks follows the objects, not their order
    in the list: objects with equal rows are interchangeable in the metric."""
    a = np.asarray(rows, float)
    a = a.reshape(len(a), -1) if a.size else np.zeros((len(a), 0))  # no objects (a prediction out of view)
    order = np.lexsort(a.T[::-1]) if a.shape[1] else np.arange(len(a))
    rank = np.empty(len(a), np.int64)
    rank[order] = np.arange(len(a))
    return rank


def _score_matrix(score) -> np.ndarray:
    """`score` as a finite float (Np, No) array, else a ValueError naming it: a 1-D or 3-D one failed on "not
    enough values to unpack", NaN or infinity inside scipy ("matrix contains invalid numeric entries")."""
    try:
        a = np.asarray(score, float)
    except (TypeError, ValueError):
        raise ValueError(f"match_objects: score = {score!r:.80}: must be an (Np, No) array of numbers") from None
    if a.ndim != 2:
        raise ValueError(f"match_objects: score has shape {a.shape}: must be (predicted objects, observed objects)")
    if not np.isfinite(a).all():
        i, j = (int(k) for k in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"match_objects: score[{i}, {j}] = {a[i, j]}: scores must be finite")
    return a


# --------------------------------------------------------------------------------------------
# Segmentation IoU
# --------------------------------------------------------------------------------------------
def _segmentation(name: str, seg) -> np.ndarray:
    """`seg` as an int64 (F, H, W) array of ids -1 (background) or >= 0, F >= 1, else a ValueError naming it.

    A (H, W) mask was read as H frames of one row each, float ids were truncated (0.7 counted as object 0) and
    NaN failed inside NumPy; ids below -1 were silently background."""
    a = np.asarray(seg)
    if a.ndim != 3 or a.shape[0] < 1:
        raise ValueError(f"{name}: shape {a.shape}: must be (frames, height, width) with at least one frame")
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"{name}: dtype {a.dtype}: must hold integer object ids (-1 background)")
    if np.issubdtype(a.dtype, np.floating):
        bad = ~(np.isfinite(a) & (a == np.round(a)))
        if bad.any():
            f, v, u = (int(k) for k in np.argwhere(bad)[0])
            raise ValueError(f"{name}: value {a[f, v, u]} at frame {f}, row {v}, column {u}: ids must be whole numbers")
    a = a.astype(np.int64)
    if a.size and a.min() < -1:
        f, v, u = (int(k) for k in np.argwhere(a < -1)[0])
        raise ValueError(f"{name}: id {a[f, v, u]} at frame {f}, row {v}, column {u}: must be -1 (background) or >= 0")
    return a


def overlap_counts(pred_seg: np.ndarray, obs_seg: np.ndarray, n_pred: int, n_obs: int) -> np.ndarray:
    """Joint histogram (F, Np + 1, No + 1) of predicted and observed ids per frame; index 0 is background (-1)."""
    pred_seg, obs_seg = np.asarray(pred_seg), np.asarray(obs_seg)
    if pred_seg.shape != obs_seg.shape:
        raise ValueError(f"segmentation shapes differ: predicted {pred_seg.shape}, observed {obs_seg.shape}")
    f = pred_seg.shape[0]
    fg = (pred_seg >= 0) | (obs_seg >= 0)  # background-background pixels do not enter any IoU
    frame, *_ = np.nonzero(fg)
    p = np.clip(pred_seg[fg].astype(np.int64) + 1, 0, n_pred)
    o = np.clip(obs_seg[fg].astype(np.int64) + 1, 0, n_obs)
    code = (frame * (n_pred + 1) + p) * (n_obs + 1) + o
    counts = np.bincount(code, minlength=f * (n_pred + 1) * (n_obs + 1)).reshape(f, n_pred + 1, n_obs + 1)
    counts[:, 0, 0] = (~fg).reshape(f, -1).sum(1)
    return counts


def iou_from_counts(
    counts: np.ndarray,
    pred_names: Sequence[str] | None = None,
    obs_names: Sequence[str] | None = None,
) -> np.ndarray:
    """Per-frame matched mean IoU (F,) from a joint histogram (see the module docstring for the definition)."""
    inter = counts[:, 1:, 1:].astype(float)  # (F, Np, No)
    area_p = counts[:, 1:, :].sum(axis=2).astype(float)  # (F, Np)
    area_o = counts[:, :, 1:].sum(axis=1).astype(float)  # (F, No)
    total_i = inter.sum(0)
    total_u = area_p.sum(0)[:, None] + area_o.sum(0)[None, :] - total_i
    with np.errstate(invalid="ignore", divide="ignore"):
        seq_iou = np.where(total_u > 0, total_i / total_u, 0.0)
    # ties (two predicted objects overlapping the video's alike over the sequence) broken by each predicted
    # object's pixel counts per frame and observed id: the same pairs whatever order the prediction lists them in
    rank = content_rank(counts[:, 1:, :].transpose(1, 0, 2))
    pairs = match_objects(pred_names, obs_names, seq_iou, pred_rank=rank)
    n_frames = counts.shape[0]
    score = np.zeros(n_frames)
    n_visible = (area_p > 0).sum(1) + (area_o > 0).sum(1)  # (F,) objects visible on either side
    for i, j in pairs:
        u = area_p[:, i] + area_o[:, j] - inter[:, i, j]
        with np.errstate(invalid="ignore", divide="ignore"):
            score += np.where(u > 0, inter[:, i, j] / u, 0.0)
        n_visible -= (area_p[:, i] > 0) & (area_o[:, j] > 0)  # a visible pair counts once
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n_visible > 0, score / np.maximum(n_visible, 1), 1.0)


def segmentation_iou(
    pred_seg: np.ndarray,
    obs_seg: np.ndarray,
    *,
    pred_names: Sequence[str] | None = None,
    obs_names: Sequence[str] | None = None,
) -> tuple[float, float]:
    """Matched mean IoU of two instance segmentations (F, H, W) (-1 background): (first frame, full sequence).

    Worked case: one object each, predicted mask 4 pixels, observed 4 pixels, 2 shared: IoU = 2 / 6 = 1/3.
    """
    pred_seg, obs_seg = _segmentation("pred_seg", pred_seg), _segmentation("obs_seg", obs_seg)
    n_pred = int(pred_seg.max(initial=-1)) + 1
    n_obs = int(obs_seg.max(initial=-1)) + 1
    if pred_names is not None:
        n_pred = max(n_pred, len(pred_names))
    if obs_names is not None:
        n_obs = max(n_obs, len(obs_names))
    if pred_seg.shape[0] * (n_pred + 1) * (n_obs + 1) > MAX_HISTOGRAM:  # one id of 10**9 asked for 16 GB
        raise ValueError(
            f"object ids up to {n_pred - 1} (predicted) and {n_obs - 1} (observed) over {pred_seg.shape[0]} frames: "
            f"the id histogram would have more than {MAX_HISTOGRAM} cells; number the objects 0, 1, 2, ..."
        )
    per_frame = iou_from_counts(overlap_counts(pred_seg, obs_seg, n_pred, n_obs), pred_names, obs_names)
    return float(per_frame[0]), float(per_frame.mean())


# --------------------------------------------------------------------------------------------
# Flow EPE
# --------------------------------------------------------------------------------------------
def epe_mask(pred_seg: np.ndarray, obs_seg: np.ndarray, obs_occluded: np.ndarray | None = None) -> np.ndarray:
    """(F, H, W) the pixels EPE averages over: per frame, the observed object pixels whose flow is not occluded;
    in a frame without any, the predicted object pixels (not occluded)."""
    pred, obs = _segmentation("pred_seg", pred_seg) >= 0, _segmentation("obs_seg", obs_seg) >= 0
    if pred.shape != obs.shape:  # a (1, H, W) prediction was broadcast over every frame
        raise ValueError(f"segmentation shapes differ: predicted {pred.shape}, observed {obs.shape}")
    if obs_occluded is not None:
        occ = np.asarray(obs_occluded)
        if occ.shape != obs.shape:  # an (H, W) or (F, H, 1) mask was broadcast
            raise ValueError(f"obs_occluded: shape {occ.shape}, expected the segmentations' {obs.shape}")
        if occ.dtype != bool and not np.isin(occ, (0, 1)).all():  # 0.5 read as True: every pixel occluded
            raise ValueError(f"obs_occluded: dtype {occ.dtype} with values other than 0 and 1: must be a bool mask")
        valid = ~occ.astype(bool)
        pred, obs = pred & valid, obs & valid
    shows = obs.reshape(obs.shape[0], -1).any(1)[:, None, None]
    return np.where(shows, obs, pred)


def flow_epe_frames(
    pred_flow: np.ndarray,
    obs_flow: np.ndarray,
    pred_seg: np.ndarray,
    obs_seg: np.ndarray,
    obs_occluded: np.ndarray | None = None,
) -> np.ndarray:
    """Per-frame EPE (F,) in pixels of flows (F, H, W, 2) with segmentations (F, H, W) (-1 where no object): the
    mean error over `epe_mask`; nan for frames where it is empty."""
    pred_flow, obs_flow = np.asarray(pred_flow), np.asarray(obs_flow)
    mask = epe_mask(pred_seg, obs_seg, obs_occluded)
    if pred_flow.shape != obs_flow.shape or pred_flow.shape != (*mask.shape, 2):
        raise ValueError(
            f"flow shapes differ: predicted {pred_flow.shape}, observed {obs_flow.shape}, masks {mask.shape} "
            "(flows are (frames, height, width, 2))"
        )
    f, *_ = np.nonzero(mask)
    vectors = {"pred_flow": pred_flow[mask], "obs_flow": obs_flow[mask]}  # only the masked pixels: (M, 2)
    for name, vec in vectors.items():  # NaN dropped its frame: EPE 0
        bad = ~np.isfinite(vec).all(-1)  # checked on the masked vectors only: the whole flows cost 3 times the EPE
        if bad.any():
            k, v, u = (int(x) for x in np.argwhere(mask)[np.flatnonzero(bad)[0]])
            raise ValueError(
                f"{name}: {int(bad.sum())} NaN or infinite vectors on the pixels EPE averages over (the first "
                f"{vec[bad][0].tolist()} at frame {k}, row {v}, column {u})"
            )
    d = vectors["pred_flow"].astype(np.float64) - vectors["obs_flow"]
    err = np.bincount(f, weights=np.hypot(d[:, 0], d[:, 1]), minlength=mask.shape[0])
    n = np.bincount(f, minlength=mask.shape[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, err / np.maximum(n, 1), np.nan)


def flow_epe(
    pred_flow: np.ndarray,
    obs_flow: np.ndarray,
    pred_seg: np.ndarray,
    obs_seg: np.ndarray,
    obs_occluded: np.ndarray | None = None,
) -> tuple[float, float]:
    """End-point error of two flow sequences (F, H, W, 2) with their segmentations: (first frame, full sequence).

    Worked case: 4 observed object pixels, one off by (3, 4), the rest exact: EPE = 5 / 4 = 1.25 px, whatever the
    prediction draws elsewhere.
    """
    per_frame = flow_epe_frames(pred_flow, obs_flow, pred_seg, obs_seg, obs_occluded)
    finite = per_frame[np.isfinite(per_frame)]
    first = float(per_frame[0]) if np.isfinite(per_frame[0]) else 0.0
    return first, float(finite.mean()) if len(finite) else 0.0


# --------------------------------------------------------------------------------------------
# State errors and composition
# --------------------------------------------------------------------------------------------
def _as_scene(x: Scene | str) -> Scene:
    return x if isinstance(x, Scene) else parse(x)


def state_mae(pred: Scene, obs: Scene) -> tuple[float, float]:
    """Mean absolute error of initial position (m) and linear velocity (m/s), every object of the video counted.

    Objects are paired by chosen name (`match_objects`), the rest by nearest initial position (optimal
    assignment); a video object left without a partner (the prediction has fewer) is compared with the nearest
    predicted object. The MAE is the mean over those pairs and the three components, so leaving out the objects
    one would place badly does not lower it (a 4-object video predicted as one of its objects, exactly, scores the
    other three against it, not 0). Extra predicted objects are not scored here (pairing them too would let copies
    of a well-placed object lower the mean); the count and composition accuracies and the IoU see them.
    """
    require_scene(pred, "state_mae: pred")
    require_scene(obs, "state_mae: obs")
    p_pos = np.array([o.state.position for o in pred.objects])
    o_pos = np.array([o.state.position for o in obs.objects])
    if not len(p_pos) or not len(o_pos):
        return POSITION_MAE_INVALID, VELOCITY_MAE_INVALID
    dist = np.linalg.norm(p_pos[:, None] - o_pos[None], axis=-1)
    p_vel = np.array([o.state.linear_velocity for o in pred.objects])
    o_vel = np.array([o.state.linear_velocity for o in obs.objects])
    # ties (objects at equal distances) broken by the objects' states, not their places in the lists
    p_rank, o_rank = content_rank(np.hstack([p_pos, p_vel])), content_rank(np.hstack([o_pos, o_vel]))
    pairs = match_objects(pred.names, obs.names, -dist - 1.0, pred_rank=p_rank, obs_rank=o_rank)  # all < 0: kept
    paired = {j for _, j in pairs}
    for j in (j for j in range(len(o_pos)) if j not in paired):  # the nearest prediction, the first by state on a tie
        pairs.append((min(range(len(p_pos)), key=lambda i, j=j: (dist[i, j], p_rank[i])), j))
    i, j = np.array(pairs).T
    return float(np.abs(p_pos[i] - o_pos[j]).mean()), float(np.abs(p_vel[i] - o_vel[j]).mean())


def _check_pairs(where: str, predictions, targets) -> None:
    """Predictions (texts or Scenes) and target Scenes of equal count, else a TypeError / ValueError naming them: a
    YAML text passed as the list was scored as its characters (each an invalid prediction), targets given as text
    scored every prediction invalid, and unequal lengths failed on zip's "argument 2 is shorter"."""
    for name, seq in (("predictions", predictions), ("targets", targets)):
        if isinstance(seq, (str, bytes)) or not hasattr(seq, "__len__"):
            raise TypeError(f"{where}: {name} is a {type(seq).__name__}: must be a list")
    if len(predictions) != len(targets):
        raise ValueError(f"{where}: {len(predictions)} predictions for {len(targets)} targets: must match")
    for k, t in enumerate(targets):
        require_scene(t, f"{where}: targets[{k}]")


def state_mae_batch(predictions: Sequence[Scene | str], targets: Sequence[Scene]) -> list[tuple[float, float]]:
    """`state_mae` for each (prediction, target); unparsable predictions get the invalid penalties."""
    _check_pairs("state_mae_batch", predictions, targets)
    out = []
    for p, t in zip(predictions, targets, strict=True):
        try:
            out.append(state_mae(_as_scene(p), t))
        except SceneError:
            out.append((POSITION_MAE_INVALID, VELOCITY_MAE_INVALID))
    return out


def composition_accuracy(
    predictions: Sequence[Scene | str], targets: Sequence[Scene]
) -> tuple[list[float], list[float]]:
    """Whether each prediction has the target's object count, and its multiset of shapes: (count, shapes) as 1/0.

    An unparsable prediction scores 0 on both.
    """
    _check_pairs("composition_accuracy", predictions, targets)
    count, shapes = [], []
    for p, t in zip(predictions, targets, strict=True):
        try:
            scene = _as_scene(p)
        except SceneError:
            count.append(0.0)
            shapes.append(0.0)
            continue
        count.append(float(len(scene.objects) == len(t.objects)))
        shapes.append(float(sorted(scene.structure) == sorted(t.structure)))
    return count, shapes


def mean_finite(values: Sequence[float]) -> float:
    """Mean of the finite values (nan when none): for averaging per-video metrics."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__"):
        raise TypeError(f"mean_finite: values is a {type(values).__name__}: must be a list of numbers")
    v = []
    for k, x in enumerate(values):
        if x is None:
            continue
        try:  # str, complex and arrays are refused here, not by math.isfinite's bare "must be real number"
            if isinstance(x, (str, bytes)):
                raise TypeError
            f = float(x)
        except (TypeError, ValueError):
            raise TypeError(f"mean_finite: values[{k}] = {x!r:.80}: must be a number or None") from None
        if math.isfinite(f):
            v.append(f)
    return float(np.mean(v)) if v else float("nan")
