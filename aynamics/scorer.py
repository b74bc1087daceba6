"""The fast scorer: K candidate scenes against one observed video, without OpenGL.

Candidates are grouped by structure and simulated together on MuJoCo's threaded `Batch`; the same Batch then
ray-casts every candidate's segmentation and depth (`Batch.ray`, one ray per scorer pixel) at a reduced
resolution at the sampled frames (`observation.scoring_size`: the video's aspect ratio at 80 rows, 120×80 for
480×320 and for a scene), each candidate from its OWN camera; the exact motion field follows from depth and the
poses at frames k and k + 1 (see `aynamics.raycast` and `aynamics.flow`). Metrics are computed from the object hits
alone, equal to `aynamics.metrics` on dense arrays. IoU and EPE are the definitions in `aynamics.metrics`. EPE is
reported in pixels of a 480-pixel-wide image (the paper's resolution): flow measured at width w is multiplied by
480 / w.

    obs = Observation.from_scene(scene)         # or Observation.from_dir("render_out/")
    scores = score([text1, scene2, ...], obs)   # list[Score], in order; never raises on bad candidates

A candidate that cannot be parsed, validated or simulated gets `Score(iou 0, EPE = EPE_INVALID, valid=False,
reason=...)`; the others in the batch are scored normally.

The observed video (`Observation`, `scoring_size`, the observed folder layout) is `aynamics.observation`;
`Observation` is re-exported here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from aynamics import metrics
from aynamics.observation import Observation  # re-exported: `from aynamics.scorer import Observation, score`
from aynamics.raycast import Cast, cast_group
from aynamics.scene import Scene, SceneError, parse

REFERENCE_WIDTH = 480  # EPE is reported in pixels of an image this wide
EPE_INVALID = 100.0  # px (at 480 wide): the EPE of a candidate that cannot be parsed or simulated


@dataclass(frozen=True)
class Score:
    """One candidate's score. EPE fields are None when the observation has no flow."""

    iou_first: float
    iou_full: float
    epe_first: float | None
    epe_full: float | None
    valid: bool
    reason: str | None = None
    overlap: float = 0.0  # invalid for an overlapping start: its depth in m (a search's way out), else 0

    def to_json(self) -> dict:
        def r(x):
            return None if x is None else round(float(x), 4)

        return {
            "iou_first": r(self.iou_first),
            "iou_full": r(self.iou_full),
            "epe_first": r(self.epe_first),
            "epe_full": r(self.epe_full),
            "valid": self.valid,
            "reason": self.reason,
        }


# --------------------------------------------------------------------------------------------
# Scoring
# --------------------------------------------------------------------------------------------
def _invalid(reason: str, has_flow: bool) -> Score:
    return Score(0.0, 0.0, EPE_INVALID if has_flow else None, EPE_INVALID if has_flow else None, False, reason)


@dataclass(frozen=True)
class _ObservedSums:
    """Per-frame quantities of the observation that every candidate's sparse metrics reuse."""

    seg: np.ndarray  # (F, h*w)
    area: np.ndarray  # (F, No) pixels of each observed object
    flow: np.ndarray | None  # (F, h*w, 2)
    valid: np.ndarray | None  # (F, h*w) flow not occluded
    fg_index: np.ndarray | None  # (M,) flat f * h*w + pixel of observed object pixels whose flow is not occluded
    fg_norm: np.ndarray | None  # (M,) |observed flow| there (float64)
    fg_count: np.ndarray | None  # (F,) such pixels per frame: what EPE averages over where > 0 (`metrics.epe_mask`)

    @classmethod
    def of(cls, obs: Observation) -> _ObservedSums:
        f_count = len(obs.frames)
        seg = obs.segmentation.reshape(f_count, -1)
        n_obs = _n_observed(obs)
        ids = np.where(seg >= 0, seg, n_obs).astype(np.int64)
        area = np.stack([np.bincount(row, minlength=n_obs + 1)[:n_obs] for row in ids])
        if obs.flow is None:
            return cls(seg, area, None, None, None, None, None)
        flow = obs.flow.reshape(f_count, -1, 2).astype(np.float64)
        valid = np.ones(seg.shape, bool) if obs.occluded is None else ~obs.occluded.reshape(f_count, -1)
        index = np.flatnonzero((seg >= 0) & valid)
        fl = flow.reshape(-1, 2)[index]
        count = np.bincount(index // seg.shape[1], minlength=f_count)
        return cls(seg, area, flow, valid, index, np.hypot(fl[:, 0], fl[:, 1]), count)


def _score_hits(
    cast: Cast, sel: slice, reason: str | None, scene: Scene, obs: Observation, sums: _ObservedSums, overlap: float
) -> Score:
    """Metrics of one candidate from its hits alone; equal to `metrics` on the dense arrays (see tests)."""
    if reason is not None:
        return replace(_invalid(reason, obs.flow is not None), overlap=overlap)
    f_count = len(obs.frames)
    f, pix, p = cast.hits.f[sel], cast.hits.pix[sel], cast.hits.obj[sel].astype(np.int64)
    o = sums.seg[f, pix].astype(np.int64)  # observed id under each predicted object pixel
    n_pred, n_obs = len(scene.objects), sums.area.shape[1]
    code = (f * (n_pred + 1) + p + 1) * (n_obs + 1) + np.clip(o + 1, 0, n_obs)
    counts = np.bincount(code, minlength=f_count * (n_pred + 1) * (n_obs + 1)).reshape(f_count, n_pred + 1, n_obs + 1)
    counts[:, 0, 1:] = sums.area - counts[:, 1:, 1:].sum(1)  # observed object pixels the prediction leaves empty
    per_frame = metrics.iou_from_counts(counts, scene.names, obs.names)
    epe_first = epe_full = None
    if sums.flow is not None:
        # `metrics.epe_mask`: the observed object pixels (flow not occluded), or in a frame without any the predicted
        ok = sums.valid[f, pix]
        shows = sums.fg_count > 0
        keep = ok & np.where(shows[f], o >= 0, True)  # predicted pixels that count: on an observed object, or all
        d = cast.flow[sel][keep] - sums.flow[f[keep], pix[keep]]
        err = np.bincount(f[keep], weights=np.hypot(d[:, 0], d[:, 1]), minlength=f_count).astype(float)  # int if empty
        # observed object pixels the prediction leaves empty: predicted flow 0 there, error |observed flow|
        hw = sums.seg.shape[1]
        empty = ~np.isin(sums.fg_index, f * hw + pix, assume_unique=True)
        err += np.bincount(sums.fg_index[empty] // hw, weights=sums.fg_norm[empty], minlength=f_count)
        cnt = np.where(shows, sums.fg_count, np.bincount(f[keep], minlength=f_count)).astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            per = np.where(cnt > 0, err / np.maximum(cnt, 1), np.nan) * (REFERENCE_WIDTH / obs.width)
        finite = per[np.isfinite(per)]
        epe_first = float(per[0]) if np.isfinite(per[0]) else 0.0
        epe_full = float(finite.mean()) if len(finite) else 0.0
    return Score(float(per_frame[0]), float(per_frame.mean()), epe_first, epe_full, True, None)


def _n_observed(obs: Observation) -> int:
    n = int(obs.segmentation.max(initial=-1)) + 1
    return max(n, len(obs.names)) if obs.names is not None else n


def score(candidates: Sequence[Scene | str], observed: Observation, *, nthread: int | None = None) -> list[Score]:
    """Score candidate scenes (or YAML texts) against one observation; one `Score` per candidate, in order.

    Never raises for a bad candidate: parse/validation errors and diverging simulations give an invalid Score
    with the reason. Candidates of one structure are simulated and ray-cast in one batch; if a batch fails as a
    whole, its candidates are retried one by one so a single broken candidate cannot spoil the others.

    Raises:
        TypeError: `candidates` is one scene or text rather than a list of them (a text was scored as its
            characters, each an invalid candidate), or `observed` is not an `Observation`.
    """
    if isinstance(candidates, (Scene, str, bytes)) or not hasattr(candidates, "__len__"):
        raise TypeError(
            f"score: candidates is a {type(candidates).__name__}: must be a list of scenes or texts "
            "(one candidate: [candidate])"
        )
    if not isinstance(observed, Observation):
        raise TypeError(
            f"score: observed is a {type(observed).__name__}, not an Observation "
            "(Observation.from_scene(scene) or Observation.from_dir(path))"
        )
    out: list[Score | None] = [None] * len(candidates)
    scenes: dict[int, Scene] = {}
    for k, c in enumerate(candidates):
        if isinstance(c, Scene):
            scenes[k] = c
            continue
        try:
            scenes[k] = parse(c)
        except SceneError as e:
            out[k] = _invalid(str(e), observed.flow is not None)
    groups: dict[tuple[str, ...], list[int]] = {}
    for k, s in scenes.items():
        groups.setdefault(s.structure, []).append(k)
    sums = _ObservedSums.of(observed)
    for structure, idx in groups.items():
        try:
            cast = cast_group(
                [scenes[k] for k in idx],
                structure,
                observed.frames,
                observed.width,
                observed.height,
                observed.config,
                nthread,
                grid=observed.grid,
            )
            bounds = np.searchsorted(cast.hits.c, np.arange(len(idx) + 1))  # hits are sorted by candidate
            for j, k in enumerate(idx):
                sel = slice(bounds[j], bounds[j + 1])
                out[k] = _score_hits(cast, sel, cast.reasons[j], scenes[k], observed, sums, cast.overlaps[j])
        except (mujoco.FatalError, RuntimeError, ValueError, FloatingPointError) as e:
            if len(idx) == 1:
                out[idx[0]] = _invalid(f"simulation failed: {type(e).__name__}: {e}", observed.flow is not None)
                continue
            for k in idx:  # isolate the broken candidate
                out[k] = score([scenes[k]], observed, nthread=1)[0]
    return out  # type: ignore[return-value]
