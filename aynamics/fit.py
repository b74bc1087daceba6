"""Fitting shared physical parameters to measured trajectories, and the statistics that judge a fit.

    res = fit(scene, tracks, start={"mu": 0.4}, active=["floor_offset"])   # bounded least squares
    err = track_errors(scene, tracks, res.values, res.active)              # (n,) RMS position error, m

The residual vector is every object's position error (m) at every measured frame. Residuals along one
trajectory are strongly correlated, so information criteria and standard errors use an effective sample
size n·(1-ρ)/(1+ρ) from the lag-1 autocorrelation ρ of the residuals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from aynamics.effects import CANDIDATES, simulate_many, simulate_tracks
from aynamics.measured import Track
from aynamics.scene import Scene, is_number, is_whole

MU_BOUNDS = (0.02, 1.5)
MU_SCALE = 0.1
MAX_EVALS = 12  # least-squares iterations per fit (each costs 1 + number of parameters simulations)
STEP = 0.05  # finite-difference step in units of each parameter's typical size


@dataclass
class FitResult:
    """A fitted model: parameter values, standard errors and goodness of fit on the fit split."""

    values: dict[str, float]
    active: list[str]
    sigma: dict[str, float]
    rss: float
    n: int
    n_eff: float
    k: int
    evals: int
    cov: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))
    names: list[str] = field(default_factory=list)
    cov_by_track: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))  # `clustered_cov`

    @property
    def bic(self) -> float:
        """Bayesian information criterion on the effective sample size (up to a constant). Compare two fits with
        `d_bic`, not by subtracting: each fit's own n_eff multiplies ln(rss / n), whose size depends on the length
        unit, so the plain difference rewarded residuals that were merely less autocorrelated."""
        return self.n_eff * math.log(max(self.rss / self.n, 1e-300)) + self.k * math.log(self.n_eff)

    def d_bic(self, ref: FitResult) -> float:
        """BIC of this fit minus `ref`'s (the model it extends, fitted to the same residuals), both on ONE
        effective sample size, ref's: n_eff·ln(rss / rss_ref) + (k − k_ref)·ln n_eff. `bic` − `ref.bic` weighed
        ln(rss / n) ≈ −9 (metres) by each fit's own n_eff, so a fit whose residuals were only a little less
        autocorrelated won tens of BIC units with no better rss (on 40 real cube tosses: speed-dependent friction
        −44 for a 2.8 % lower rss, +26 for the same fit in millimetres); this difference is unit-free."""
        if self.n != ref.n:
            raise ValueError(f"d_bic: fits to {self.n} and {ref.n} residuals: BIC compares fits to the same data")
        ne = ref.n_eff
        return ne * math.log(max(self.rss, 1e-300) / max(ref.rss, 1e-300)) + (self.k - ref.k) * math.log(ne)

    def mahalanobis(self, name: str) -> float:
        """Distance (in standard errors, jointly) of a candidate's parameters from its 'absent' value."""
        c = CANDIDATES[name]
        idx = [self.names.index(p) for p in c.params]
        d = np.array([self.values[p] - z for p, z in zip(c.params, c.null, strict=True)])
        cov = self.cov[np.ix_(idx, idx)]
        try:
            return float(math.sqrt(max(d @ np.linalg.solve(cov + 1e-18 * np.eye(len(d)), d), 0.0)))
        except np.linalg.LinAlgError:
            return 0.0


def residuals(scene: Scene, tracks: list[Track], values: dict, active: list[str]) -> list[np.ndarray]:
    """Per track, (T, N, 3) simulated minus measured position (NaN where the measurement is missing)."""
    sim = simulate_tracks(scene, tracks, values, active)
    return [p - tr.position for p, tr in zip(sim.position, tracks, strict=True)]


def flat(res: list[np.ndarray]) -> np.ndarray:
    return np.nan_to_num(np.concatenate([r.ravel() for r in res]), nan=0.0)


def track_errors(scene: Scene, tracks: list[Track], values: dict, active: list[str]) -> np.ndarray:
    """(n,) RMS position error (m) of each track."""
    check_tracks(tracks, "track_errors")
    return np.array([math.sqrt(np.nanmean(np.sum(r**2, -1))) for r in residuals(scene, tracks, values, active)])


def lag1(res: list[np.ndarray]) -> float:
    """Lag-1 autocorrelation of residuals along the tracks (pooled over coordinates). A frame with a missing value
    is left out, and so are the pairs across it: frames on either side of a gap are not neighbours."""
    num = den = 0.0
    for r in res:
        x = r.reshape(len(r), -1)
        ok = np.isfinite(x).all(1)
        if ok.sum() < 3:
            continue
        pair = ok[1:] & ok[:-1]
        num += float(np.sum(x[1:][pair] * x[:-1][pair]))
        den += float(np.sum(x[ok] * x[ok]))
    return num / den if den > 0 else 0.0


def check_candidates(names, where: str) -> list[str]:
    """`names` as a list of known candidate causes (`effects.CANDIDATES`), else an error naming `where`: an unknown
    one failed on a bare KeyError, and a str was read as its letters (KeyError: 'w')."""
    if isinstance(names, (str, bytes)) or not hasattr(names, "__iter__"):
        raise TypeError(f"{where} is a {type(names).__name__} {names!r:.60}: must be a list of candidate names")
    names = list(names)
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        raise ValueError(f"{where}: unknown candidate(s) {unknown}; known: {list(CANDIDATES)}")
    return names


def check_tracks(tracks, where: str) -> None:
    """A ValueError naming `where` unless `tracks` is a non-empty list: an empty one failed on a bare IndexError
    deep in the batched simulation (`effects._run`: scenes[0])."""
    if isinstance(tracks, (str, bytes)) or not hasattr(tracks, "__len__") or not len(tracks):
        raise ValueError(f"{where}: tracks = {tracks!r:.80}: must be a non-empty list of measured Tracks")


def fit(
    scene: Scene, tracks: list[Track], start: dict[str, float], active: list[str], max_evals: int = MAX_EVALS
) -> FitResult:
    """Fit μ plus the parameters of every active candidate (others held at `start`) by bounded least squares.

    Every start is clipped into its bounds: a scene's μ of 0 or 1.8 (valid scene values, outside `MU_BOUNDS`)
    failed inside scipy ("Initial guess is outside of provided bounds")."""
    active = check_candidates(active, "fit: active")
    mu = start.get("mu") if isinstance(start, dict) else None
    if not is_number(mu) or not math.isfinite(mu):  # KeyError; NaN
        raise ValueError(f"fit: start['mu'] = {mu!r}: start must be a dict with a finite friction 'mu'")
    check_tracks(tracks, "fit")
    if not is_whole(max_evals) or max_evals < 1:
        raise ValueError(f"fit: max_evals = {max_evals!r}: must be a whole number >= 1")
    names, lo, hi, x0, scale = ["mu"], [MU_BOUNDS[0]], [MU_BOUNDS[1]], [float(np.clip(mu, *MU_BOUNDS))], [MU_SCALE]
    for a in active:
        c = CANDIDATES[a]
        for p, a_lo, a_hi, s0, sc in zip(c.params, c.lo, c.hi, c.start, c.scale, strict=True):
            names.append(p)
            lo.append(a_lo)
            hi.append(a_hi)
            x0.append(float(np.clip(start.get(p, s0), a_lo, a_hi)))
            scale.append(sc)
    lo_, hi_, x0_, sc_ = (np.array(v, dtype=float) for v in (lo, hi, x0, scale))
    fixed = {k: v for k, v in start.items() if k not in names}
    evals = 0

    def unpack(u: np.ndarray) -> dict:
        return {**fixed, **dict(zip(names, np.clip(x0_ + u * sc_, lo_, hi_), strict=True))}

    def fun(u: np.ndarray) -> np.ndarray:
        nonlocal evals
        evals += 1
        return flat(residuals(scene, tracks, unpack(u), active))

    u_lo, u_hi = (lo_ - x0_) / sc_, (hi_ - x0_) / sc_
    cache: dict[bytes, np.ndarray] = {}

    def fun_cached(u: np.ndarray) -> np.ndarray:
        key = u.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = fun(u)
        return cache[key]

    def jac(u: np.ndarray) -> np.ndarray:
        # forward differences with a fixed step of STEP typical sizes (scipy's relative step is 0 at u = 0)
        # all columns in one Batch call
        nonlocal evals
        f0 = fun_cached(u)
        steps = np.where(u + STEP <= u_hi, STEP, -STEP)
        sims = simulate_many(scene, tracks, [unpack(u + steps[j] * np.eye(len(u))[j]) for j in range(len(u))], active)
        evals += len(u)
        cols = [
            (flat([p - tr.position for p, tr in zip(sm.position, tracks, strict=True)]) - f0) / steps[j]
            for j, sm in enumerate(sims)
        ]
        return np.stack(cols, 1)

    out = least_squares(
        fun_cached,
        np.zeros(len(names)),
        jac=jac,
        bounds=(u_lo - 1e-9, u_hi + 1e-9),
        max_nfev=max_evals,
        x_scale=1.0,
        xtol=1e-4,
        ftol=1e-6,
    )
    values = unpack(out.x)
    res = residuals(scene, tracks, values, active)
    r = np.concatenate([x.ravel() for x in res])
    n, k = int(np.isfinite(r).sum()) or 1, len(names)  # measured values (a residual of exactly 0 is one too)
    r = np.nan_to_num(r, nan=0.0)
    rho = min(max(lag1(res), 0.0), 0.999)
    n_eff = max(n * (1 - rho) / (1 + rho), float(len(tracks)), k + 2.0)
    rss = float(r @ r)
    jac = out.jac / sc_[None, :]  # d r / d x
    try:
        cov = np.linalg.pinv(jac.T @ jac) * rss / max(n - k, 1) * (n / n_eff)
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.inf)
    sigma = {p: float(math.sqrt(max(cov[i, i], 0.0))) for i, p in enumerate(names)}
    robust = clustered_cov(jac, r, [x.size for x in res])
    return FitResult(values, list(active), sigma, rss, n, n_eff, k, evals, cov, names, robust)


def clustered_cov(jac: np.ndarray, r: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Cluster-robust (sandwich) covariance of least-squares parameters with one cluster per trajectory (`sizes`
    consecutive residuals each): B·(Σ_g J_gᵀ r_g r_gᵀ J_g)·B·G/(G − 1), B = (JᵀJ)⁻¹. Residuals along a trajectory
    may be correlated in any way (the curvature errors assume lag-1 at most and came out ~80 times too small on a
    hidden-effect case); trajectories are independent. NaN for fewer than 2 trajectories."""
    k, g = jac.shape[1], len(sizes)
    if not len(r) == jac.shape[0] == sum(sizes):  # a short `sizes` left residuals out of every cluster, silently
        raise ValueError(
            f"clustered_cov: {jac.shape[0]} Jacobian rows, {len(r)} residuals, sizes summing to "
            f"{sum(sizes)}: must all be equal"
        )
    if g < 2:
        return np.full((k, k), np.nan)
    bounds = np.cumsum([0, *sizes])
    scores = np.stack([jac[a:b].T @ r[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)])  # (G, k)
    try:
        bread = np.linalg.pinv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return np.full((k, k), np.inf)
    return bread @ (scores.T @ scores) @ bread * g / (g - 1)
