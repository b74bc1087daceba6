"""Residual analysis: smoothed accelerations, an open-ended sparse regression of flight-phase residual
accelerations on a small library of terms, and residual tests (bias, whiteness, phases, drift).

    terms = sparse_terms(scene, tracks, values, active)  # [] when nothing significant is left
"""

from __future__ import annotations

import math

import numpy as np

from aynamics.effects import simulate_tracks
from aynamics.measured import Track, object_size, phases, quat_to_mat, support_height
from aynamics.scene import Scene, is_whole

WINDOW = 7  # frames of the local quadratic fit for derivatives
FLIGHT_GAP = 0.03  # m: lowest point this far above the floor counts as flight for the regression
T_MIN = 6.0  # |t| a library term needs to stay in the sparse model (after correlation inflation)
LIBRARY = ("const_x", "const_y", "const_z", "v", "|v|v", "w×v", "z")


def derivatives(t: np.ndarray, x: np.ndarray, window: int = WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration (T, 3) from local quadratic fits over `window` frames (irregular t)."""
    t, x = np.asarray(t, float), np.asarray(x, float)
    if t.ndim != 1 or x.shape != (len(t), 3):  # a 1-D x was broadcast into all three columns, a short one failed
        raise ValueError(f"derivatives: t {t.shape}, x {x.shape}: need t (T,) and x (T, 3)")
    if not is_whole(window) or window < 3 or window % 2 == 0:
        raise ValueError(f"derivatives: window = {window!r}: must be an odd whole number >= 3 (a centred quadratic)")
    n, half = len(t), window // 2
    vel, acc = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    for k in range(half, n - half):
        sl = slice(k - half, k + half + 1)
        tt = t[sl] - t[k]
        a = np.stack([np.ones_like(tt), tt, tt * tt], 1)
        coef, *_ = np.linalg.lstsq(a, x[sl], rcond=None)
        vel[k], acc[k] = coef[1], 2 * coef[2]
    return vel, acc


def sparse_terms(scene: Scene, tracks: list[Track], values: dict, active: list[str]) -> list[dict]:
    """Terms that explain the residual acceleration in flight (sequential thresholded least squares).

    Returns one dict per surviving term: name, coefficient (per unit mass, SI), t statistic.
    """
    sim = simulate_tracks(scene, tracks, values, active)
    rows_a, rows_x = [], []
    for tr, sp in zip(tracks, sim.position, strict=True):
        for i, obj in enumerate(scene.objects):
            p = tr.position[:, i]
            ok = np.isfinite(p).all(-1)
            t, p, ps = tr.t[ok], p[ok], sp[ok, i]
            if len(t) < 2 * WINDOW:
                continue
            q = tr.orientation[ok, i] if tr.orientation is not None else None
            gap = support_height(p, q, obj.type, object_size(obj))
            v, a = derivatives(t, p)
            _, a_sim = derivatives(t, ps)
            flight = gap > FLIGHT_GAP
            flight &= np.convolve(flight, np.ones(WINDOW), "same") >= WINDOW  # whole window in flight
            if tr.velocity is not None and q is not None and np.isfinite(tr.velocity[ok, i, 3:]).all():
                w = np.einsum("tij,tj->ti", quat_to_mat(q), tr.velocity[ok, i, 3:])
            else:
                w = np.zeros_like(v)
            sel = flight & np.isfinite(a).all(-1) & np.isfinite(a_sim).all(-1)
            for k in np.flatnonzero(sel)[::2]:  # every other frame: neighbours share most of their window
                speed = np.linalg.norm(v[k])
                lib = np.stack(
                    [
                        np.eye(3)[0],
                        np.eye(3)[1],
                        np.eye(3)[2],
                        v[k],
                        speed * v[k],
                        np.cross(w[k], v[k]),
                        np.array([0, 0, p[k, 2]]),
                    ],
                    1,
                )  # (3, L)
                rows_a.append(a[k] - a_sim[k])
                rows_x.append(lib)
    if len(rows_a) < 30:
        return []
    y = np.concatenate(rows_a)
    x = np.concatenate(rows_x)
    keep = [j for j in range(x.shape[1]) if np.any(np.abs(x[:, j]) > 1e-9)]
    while keep:
        coef, *_ = np.linalg.lstsq(x[:, keep], y, rcond=None)
        r = y - x[:, keep] @ coef
        dof = max(len(y) - len(keep), 1)
        cov = np.linalg.pinv(x[:, keep].T @ x[:, keep]) * float(r @ r) / dof * 2.0  # ×2: overlapping windows
        tstat = coef / np.sqrt(np.maximum(np.diag(cov), 1e-300))
        worst = int(np.argmin(np.abs(tstat)))
        if abs(tstat[worst]) >= T_MIN:
            return [
                {"term": LIBRARY[j], "coefficient": float(c), "t": float(s)}
                for j, c, s in zip(keep, coef, tstat, strict=True)
            ]
        keep.pop(worst)
    return []


def phase_errors(scene: Scene, tracks: list[Track], sim_pos: list[np.ndarray]) -> dict[str, float]:
    """RMS position error (m) per motion phase of the measured motion."""
    from aynamics.measured import PHASES

    sq = {p: [] for p in PHASES}
    for tr, sp in zip(tracks, sim_pos, strict=True):
        for i, obj in enumerate(scene.objects):
            p = tr.position[:, i]
            ok = np.isfinite(p).all(-1)
            q = tr.orientation[ok, i] if tr.orientation is not None else None
            ph = phases(tr.t[ok], p[ok], support_height(p[ok], q, obj.type, object_size(obj)))
            err = np.sum((sp[ok, i] - p[ok]) ** 2, -1)
            for k, name in enumerate(PHASES):
                sq[name].extend(err[ph == k])
    return {k: (math.sqrt(float(np.mean(v))) if v else float("nan")) for k, v in sq.items()}
