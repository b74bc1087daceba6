"""Observed object tracks for refinement: mask centroids, ground tracks, a kinematic fit, and a track objective.

Far from the answer (position errors of metres) predicted and observed masks do not overlap, IoU is flat at zero
and CMA-ES gets no signal. The observed segmentation still says where each object is: per observed object, the
mask centroid at every sampled frame (`Tracks`). Back-projecting each centroid's ray onto the horizontal plane at
the matched object's centre height (the candidate's own camera) gives a ground track in metres; a sliding-with-
friction model fitted to it by robust least squares gives the object's initial horizontal position and velocity
(`fit_kinematics`). Objects are paired with observed ids by chosen name when both sides have names (not the
default `box_0`-style ones), else by an optimal assignment on ground-track distance (`match_tracks`).
`track_start` writes the fits into a scene; the `track_objective` (projected centres against centroids, physics
only) then polishes them with CMA-ES.

    tracks = Tracks.from_segmentation(obs.segmentation, obs.frames, n_observed)
    start = track_start(prediction, tracks, obs.names, params=["position", "linear_velocity"], fps=obs.fps)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from aynamics import camera as camlib
from aynamics.metrics import match_objects
from aynamics.raycast import SampleGrid
from aynamics.refine_objectives import by_structure, raw_positions
from aynamics.refine_search import Objective
from aynamics.scene import RANGES, Scene, from_items, to_items

MAX_DECELERATION = 30.0  # m/s²: upper bound of the fitted friction deceleration (μ g with μ <= 1, |g| <= 30)
FIT_SCALE = 0.05  # m: residual scale of the robust (soft L1) loss; larger residuals (collisions) count less


@dataclass(frozen=True)
class Tracks:
    """Observed object tracks: mask centroids (F, N, 2) in pixels, visible (F, N), frame indices (F,), size.

    `border` (F, N) marks masks touching the image border (their centroid is biased inwards), or is None.
    """

    centroids: np.ndarray
    visible: np.ndarray
    frames: np.ndarray
    width: int
    height: int
    border: np.ndarray | None = None

    @classmethod
    def from_segmentation(
        cls, segmentation: np.ndarray, frames: Sequence[int], n_objects: int, grid: SampleGrid | None = None
    ) -> Tracks:
        """Centroids of each object's mask (object index i in `segmentation`, -1 background); >= 2 pixels = visible.

        With the `grid` of masks taken from a larger video (`Observation.grid`), centroids are in that video's
        pixels, at the points the masks were taken from, and the tracks' size is the video's (its cameras see it).
        """
        seg = np.asarray(segmentation)
        f, h, w = seg.shape
        grid = SampleGrid.centres(w, h) if grid is None else grid
        vv, uu = np.meshgrid(grid.v, grid.u, indexing="ij")  # pixel centres, as `CameraMatrices.project`
        cent = np.zeros((f, n_objects, 2))
        vis = np.zeros((f, n_objects), bool)
        border = np.zeros((f, n_objects), bool)
        for i in range(n_objects):
            mask = seg == i  # (F, h, w)
            count = mask.sum(axis=(1, 2))
            vis[:, i] = count >= 2
            safe = np.maximum(count, 1)
            cent[:, i, 0] = (mask * uu).sum(axis=(1, 2)) / safe
            cent[:, i, 1] = (mask * vv).sum(axis=(1, 2)) / safe
            border[:, i] = mask[:, 0].any(1) | mask[:, -1].any(1) | mask[:, :, 0].any(1) | mask[:, :, -1].any(1)
        return cls(cent, vis, np.asarray(frames, int), grid.full_w, grid.full_h, border)

    def first(self, k: int) -> Tracks:
        """The tracks at the first k sampled frames."""
        border = None if self.border is None else self.border[:k]
        return Tracks(self.centroids[:k], self.visible[:k], self.frames[:k], self.width, self.height, border)

    def select(self, columns: Sequence[int]) -> Tracks:
        """The tracks of the observed objects `columns`, in that order."""
        cols = list(columns)
        border = None if self.border is None else self.border[:, cols]
        return Tracks(self.centroids[:, cols], self.visible[:, cols], self.frames, self.width, self.height, border)


def ground_points(cam: camlib.CameraMatrices, uv: np.ndarray, height: np.ndarray | float) -> np.ndarray:
    """World points (..., 3) where the rays through pixels uv (..., 2) meet the planes z = height (...).

    Rays that point up or meet the plane behind the camera give nan.
    """
    uv = np.asarray(uv, float)
    pix = np.concatenate([uv, np.ones((*uv.shape[:-1], 1))], axis=-1)  # (..., 3)
    d = np.linalg.solve(cam.K, pix.reshape(-1, 3).T).T @ cam.R  # (M, 3) world ray directions (R^T d_cam)
    d = d.reshape(pix.shape)
    c = cam.position
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (np.asarray(height, float) - c[2]) / d[..., 2]
    s = np.where((d[..., 2] < -1e-9) & (s > 0), s, np.nan)
    return c + s[..., None] * d


def slide(params: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(T, 2) horizontal positions of a body sliding from p0 with velocity v0 under a constant deceleration a
    along its motion until it stops: params = (px, py, vx, vy, a), t (T,) seconds."""
    p0, v0, a = params[:2], params[2:4], max(float(params[4]), 0.0)
    speed = float(np.hypot(*v0))
    stop = speed / a if a > 1e-9 else np.inf
    tau = np.minimum(t, stop)[:, None]  # (T, 1)
    u = v0 / speed if speed > 1e-9 else np.zeros(2)
    return p0 + v0 * tau - 0.5 * a * u * tau**2


def fit_kinematics(t: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Fit `slide` to a ground track by robust least squares.

    Args:
        t: (T,) seconds of the observed points (at least one).
        xy: (T, 2) observed horizontal positions (m).

    Returns:
        Initial position (2,), initial velocity (2,), deceleration (m/s²) and the RMS residual (m).
    """
    t, xy = np.asarray(t, float), np.asarray(xy, float)
    if len(t) == 1:
        return xy[0].copy(), np.zeros(2), 0.0, 0.0
    k = min(len(t), 3)  # initial velocity from the first few points
    v0 = np.polyfit(t[:k], xy[:k], 1)[0] if t[k - 1] > t[0] else np.zeros(2)
    p0 = xy[0] - v0 * t[0]
    vmax = RANGES["state.linear_velocity"].hi
    best = None
    for a0 in (0.5, 4.0):
        x0 = np.clip(np.array([*p0, *v0, a0]), [-np.inf] * 2 + [-vmax] * 2 + [0.0], [np.inf] * 2 + [vmax] * 2 + [30.0])
        res = least_squares(
            lambda x: (slide(x, t) - xy).ravel(),
            x0,
            bounds=([-np.inf] * 2 + [-vmax] * 2 + [0.0], [np.inf] * 2 + [vmax] * 2 + [MAX_DECELERATION]),
            loss="soft_l1",
            f_scale=FIT_SCALE,
        )
        if best is None or res.cost < best.cost:
            best = res
    rms = float(np.sqrt(np.mean(best.fun**2)))
    return best.x[:2], best.x[2:4], float(best.x[4]), rms


def match_tracks(
    scene: Scene,
    tracks: Tracks,
    obs_names: Sequence[str] | None,
    fps: float,
    heights: np.ndarray | None = None,
) -> list[tuple[int, int]]:
    """Pair the scene's objects i with observed objects j: by chosen name when both sides have names
    (`metrics.match_objects`), the rest by an optimal assignment on the mean distance between each object's
    straight-line ground track (initial position plus velocity × time) and j's centroids back-projected onto i's
    centre height (`heights` (F, N) per frame, e.g. from `centre_heights`; default: the initial height)."""
    n_obs = tracks.centroids.shape[1]
    cam = camlib.matrices(scene.camera, tracks.width, tracks.height)
    t = tracks.frames / fps
    cost = np.full((len(scene.objects), n_obs), 1e6)
    for i, obj in enumerate(scene.objects):
        p, v = np.asarray(obj.state.position), np.asarray(obj.state.linear_velocity)
        line = p[:2] + t[:, None] * v[:2]  # (F, 2)
        z = p[2] if heights is None else heights[:, i, None]  # (F, 1): every observed object at i's height
        g = ground_points(cam, tracks.centroids, z)[..., :2]  # (F, No, 2)
        d = np.linalg.norm(g - line[:, None], axis=-1)  # (F, No)
        ok = tracks.visible & np.isfinite(d)
        with np.errstate(invalid="ignore"):
            mean = np.where(ok, d, 0).sum(0) / ok.sum(0)
        cost[i] = np.where(ok.any(0), mean, 1e6)
    return match_objects(scene.names, obs_names, -cost - 1.0)


def track_start(
    scene: Scene,
    tracks: Tracks,
    obs_names: Sequence[str] | None,
    *,
    params: Sequence[str] = ("position", "linear_velocity"),
    fps: float = 30.0,
    rolling: Sequence[str] = (),
    heights: np.ndarray | None = None,
    usable: np.ndarray | None = None,
) -> Scene:
    """The scene with each matched object's horizontal initial position and velocity fitted to its observed track.

    Only the groups named in `params` change (`position`, `linear_velocity`, or `NAME.group` for one object);
    heights, vertical velocities and everything else are kept. Objects that are not matched or never visible keep
    their values. The spheres whose angular velocity is searched (`rolling`: `angular_velocity` for all or
    `NAME.angular_velocity`, as in `params`) are set to roll without slipping at their new velocity (ω = z × v / r),
    as the sampler draws them; the others keep their spin. `heights` (F, N) are the centre heights of the objects at the
    tracks' frames (from the scene's own rollout, `centre_heights`: a falling object's centroid moves down the
    image, which the initial height would read as motion towards the camera); default: the initial heights.
    `usable` (F, N) restricts the frames each object's fit uses (e.g. the fall before its first impact).
    """
    allowed = {g: set() for g in ("position", "linear_velocity", "angular_velocity")}
    for spec in (*params, *rolling):
        name, _, group = spec.rpartition(".")
        if group in allowed:
            allowed[group] |= {name} if name else set(scene.names)
    items = to_items(scene)
    cam = camlib.matrices(scene.camera, tracks.width, tracks.height)
    t = tracks.frames / fps
    lo, hi = RANGES["state.position"].bounds(3)
    w_max = RANGES["state.angular_velocity"].hi
    for i, j in match_tracks(scene, tracks, obs_names, fps, heights):
        obj, state = scene.objects[i], items[i]["state"]
        use = tracks.visible[:, j] & (True if usable is None else usable[:, i])
        if tracks.border is not None and (use & ~tracks.border[:, j]).sum() >= 2:
            use &= ~tracks.border[:, j]  # clipped masks have biased centroids
        z = obj.state.position[2] if heights is None else heights[use, i]
        g = ground_points(cam, tracks.centroids[use, j], z)[:, :2]
        keep = np.isfinite(g).all(1)
        if not keep.any():
            continue
        p0, v0, _, _ = fit_kinematics(t[use][keep], g[keep])
        if obj.name in allowed["position"]:
            state["position"][:2] = np.clip(p0, lo[:2], hi[:2]).round(4).tolist()
        if obj.name in allowed["linear_velocity"]:
            state["linear_velocity"][:2] = v0.round(4).tolist()
            if obj.name in allowed["angular_velocity"] and obj.type == "sphere":
                w = np.array([-v0[1], v0[0]]) / obj.radius
                w *= min(1.0, w_max / max(np.abs(w).max(), 1e-12))
                state["angular_velocity"] = [*w.round(4).tolist(), 0.0]
    return from_items(items)


def centre_heights(scene: Scene, frames: np.ndarray, config=None, nthread: int | None = None) -> np.ndarray | None:
    """(F, N) heights of the object centres at `frames` in the scene's own rollout, or None when it diverges."""
    from aynamics.rollout import SimConfig

    pos, ok = raw_positions([scene], config or SimConfig(), nthread)
    return pos[0, np.minimum(frames, pos.shape[1] - 1), :, 2] if ok[0] else None


def ballistic_frames(heights: np.ndarray, drop: float = 0.01) -> np.ndarray:
    """(F, N) frames of each falling object up to its first impact (the first minimum of its height), where its
    height does not depend on its horizontal motion; all frames for objects that do not start falling."""
    heights = np.asarray(heights, float)
    out = np.ones(heights.shape, bool)
    for i in range(heights.shape[1]):
        z = heights[:, i]
        if len(z) < 2 or z[1] > z[0] - drop:
            continue
        rising = np.flatnonzero(np.diff(z) >= 0)  # first k with z[k + 1] >= z[k]: the impact is at k
        out[(rising[0] if len(rising) else len(z) - 1) + 1 :, i] = False
    return out


def track_distances(
    tracks: Tracks, scenes: list[Scene], config=None, nthread: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(n, F, N) image distances (in image heights, at most 1) between the scenes' projected object centres and
    the observed centroids (object i against track column i), and (n,) whether each rollout is valid.

    Physics only (no rendering). A centre behind the camera counts as 1 image height off; scenes of another
    object count or structure than the first, or that diverge, are invalid (distance 1).
    """
    from aynamics.rollout import SimConfig

    n, (f_count, n_obj) = len(scenes), tracks.visible.shape
    dist, valid = np.ones((n, f_count, n_obj)), np.zeros(n, bool)
    for _, idx in by_structure(scenes).items():
        group = [scenes[k] for k in idx]
        if len(group[0].objects) != n_obj:
            continue
        pos, good = raw_positions(group, config or SimConfig(), nthread)
        pos = pos[:, np.minimum(tracks.frames, pos.shape[1] - 1)]  # (n, F, N, 3)
        for j, (k, scene) in enumerate(zip(idx, group, strict=True)):
            if not good[j]:
                continue
            cam = camlib.matrices(scene.camera, tracks.width, tracks.height)
            uv, z = cam.project(pos[j])
            d = np.linalg.norm(np.nan_to_num(uv - tracks.centroids, nan=1e6), axis=-1) / tracks.height
            dist[k], valid[k] = np.where(z > 1e-3, np.minimum(d, 1.0), 1.0), True
    return dist, valid


def track_objective(tracks: Tracks, config=None, nthread: int | None = None) -> Objective:
    """Minus the mean image distance (in image heights) between projected object centres and observed centroids
    over the visible (frame, object) pairs (see `track_distances`); diverging candidates score -10.

    Physics only (no rendering): a smooth signal far from the answer, where masks do not overlap and IoU is 0.
    """
    if not tracks.visible.any():
        raise ValueError("track_objective: no object is visible in any observed frame")
    weight = tracks.visible / tracks.visible.sum()  # (F, N)

    def objective(scenes: list[Scene]) -> list[float]:
        dist, valid = track_distances(tracks, scenes, config, nthread)
        return np.where(valid, -(dist * weight).sum(axis=(1, 2)), -10.0).tolist()

    return objective


def compose_per_object(scenes: list[Scene], dist: np.ndarray, visible: np.ndarray) -> Scene:
    """The first scene with each object's state taken from the scene where that object's mean track distance
    (`track_distances` (n, F, N), over its visible frames) is smallest."""
    w = visible / np.maximum(visible.sum(0), 1)  # (F, N)
    best = np.argmin((dist * w).sum(1), axis=0)  # (N,)
    items = to_items(scenes[0])
    for i, k in enumerate(best):
        items[i]["state"] = to_items(scenes[int(k)])[i]["state"]
    return from_items(items)
