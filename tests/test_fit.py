"""The fit's statistics by hand: BIC, lag-1 autocorrelation, effective sample size, standard errors, Mahalanobis
distance. The simulator is replaced by a linear model (every coordinate of every frame = μ), so least squares
finds μ exactly and each number below follows from the residuals alone."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from aynamics import fit as fitlib
from aynamics.fit import FitResult


def _linear_model(monkeypatch):
    """simulate_tracks / simulate_many: every track's position = μ in x, y and z at every frame."""

    def sim(values, tracks):
        pos = [np.full(tr.position.shape, float(values["mu"])) for tr in tracks]
        return types.SimpleNamespace(position=pos)

    monkeypatch.setattr(fitlib, "simulate_tracks", lambda scene, tracks, values, active: sim(values, tracks))
    monkeypatch.setattr(fitlib, "simulate_many", lambda scene, tracks, sets, active: [sim(v, tracks) for v in sets])


def _track(mu: float, r) -> types.SimpleNamespace:
    """A one-object track measured at mu - r (the same in x, y, z): its residuals at μ = mu are r."""
    r = np.asarray(r, float)
    return types.SimpleNamespace(position=np.repeat((mu - r)[:, None, None], 3, axis=2))


def test_bic_by_hand():
    """rss 0.6 over n = 24, n_eff 14.4, k = 1: 14.4 ln(0.025) + ln 14.4 = -50.4527."""
    r = FitResult({}, [], {}, 0.6, 24, 14.4, 1, 0)
    assert r.bic == pytest.approx(14.4 * math.log(0.025) + math.log(14.4))
    assert r.bic == pytest.approx(-50.4527, abs=1e-4)
    two = FitResult({}, [], {}, 0.6, 24, 14.4, 3, 0)  # two more parameters cost 2 ln 14.4 = 5.3345
    assert two.bic - r.bic == pytest.approx(2 * math.log(14.4))


def test_lag1_by_hand():
    """Track 1 residuals [0.1, 0.1, -0.1, -0.1], track 2 [0.2, 0.2, -0.2, -0.2] (one coordinate): lag-1 products
    0.01 - 0.01 + 0.01 and 0.04 - 0.04 + 0.04, squares 0.04 and 0.16: ρ = 0.05 / 0.2 = 0.25. A row with a missing
    value is left out; a track shorter than 3 rows adds nothing."""
    a = np.array([0.1, 0.1, -0.1, -0.1]).reshape(4, 1, 1)
    b = np.array([0.2, 0.2, -0.2, -0.2, np.nan]).reshape(5, 1, 1)
    assert fitlib.lag1([a, b]) == pytest.approx(0.25)
    assert fitlib.lag1([a, b, np.ones((2, 1, 1))]) == pytest.approx(0.25)
    assert fitlib.lag1([np.ones((2, 1, 1))]) == 0.0
    # a dropped frame inside a track: the frames on either side of it are not neighbours. [1, 1, nan, -1, -1]:
    # pairs (1, 1) and (-1, -1) only, products 1 + 1 over squares 4: ρ = 0.5 (pairing across the gap gave 0.25)
    gap = np.array([1.0, 1.0, np.nan, -1.0, -1.0]).reshape(5, 1, 1)
    assert fitlib.lag1([gap]) == pytest.approx(0.5)


def test_fit_statistics_by_hand(monkeypatch):
    """μ = 0.5 fits exactly; residuals r = [0.1, 0.1, -0.1, -0.1] and [0.2, 0.2, -0.2, -0.2] (x, y, z alike) plus a
    fifth frame of track 2 that is missing (NaN: not counted). n = 24 residuals, rss = 3 (0.04 + 0.16) = 0.6,
    ρ = 0.25 (`test_lag1_by_hand`), n_eff = 24 · 0.75 / 1.25 = 14.4. d r / d μ = 1 on the 24 residuals: JᵀJ = 24,
    var μ = (1/24) · (0.6 / 23) · (24 / 14.4) = 0.6 / 331.2, σ = 0.04256. Each track's residuals sum to 0: the
    clustered covariance is 0."""
    _linear_model(monkeypatch)
    tracks = [_track(0.5, [0.1, 0.1, -0.1, -0.1]), _track(0.5, [0.2, 0.2, -0.2, -0.2, np.nan])]
    res = fitlib.fit(None, tracks, {"mu": 0.4}, [])
    assert res.values["mu"] == pytest.approx(0.5, abs=1e-6)
    assert (res.n, res.k) == (24, 1)
    assert res.rss == pytest.approx(0.6)
    assert res.n_eff == pytest.approx(14.4)
    assert res.cov[0, 0] == pytest.approx(0.6 / 331.2)
    assert res.sigma["mu"] == pytest.approx(math.sqrt(0.6 / 331.2)) and res.sigma["mu"] == pytest.approx(0.042563, 1e-4)
    assert res.bic == pytest.approx(14.4 * math.log(0.025) + math.log(14.4))
    assert res.cov_by_track == pytest.approx(np.zeros((1, 1)), abs=1e-12)


def test_fit_counts_a_residual_of_exactly_zero_as_measured(monkeypatch):
    """Residuals [0.1, 0, -0.1, 0] and [-0.1, 0, 0.1, 0] in x, y, z: 24 measured values, 12 of them exactly 0 (they
    were counted as missing: n = 12), rss = 3 · 4 · 0.01 = 0.12."""
    _linear_model(monkeypatch)
    tracks = [_track(0.5, [0.1, 0.0, -0.1, 0.0]), _track(0.5, [-0.1, 0.0, 0.1, 0.0])]
    res = fitlib.fit(None, tracks, {"mu": 0.4}, [])
    assert res.n == 24 and res.rss == pytest.approx(0.12)


def test_fit_effective_size_is_at_least_the_number_of_tracks(monkeypatch):
    """Four tracks of 6 frames with residuals ±0.1 sin(tπ/7), t = 1..6 (two +, two -: μ = 0.5 fits). For a sine that
    vanishes just outside the track, Σ r_t r_(t-1) = cos(π/7) Σ r_t², so ρ = cos(π/7) and n (1 - ρ)/(1 + ρ) =
    72 tan²(π/14) = 3.75: fewer than the 4 independent trajectories, so n_eff = 4 (not k + 2 = 3, not 3.75)."""
    _linear_model(monkeypatch)
    bump = 0.1 * np.sin(np.arange(1, 7) * math.pi / 7)
    tracks = [_track(0.5, s * bump) for s in (1, 1, -1, -1)]
    assert fitlib.lag1(fitlib.residuals(None, tracks, {"mu": 0.5}, [])) == pytest.approx(math.cos(math.pi / 7))
    assert 72 * math.tan(math.pi / 14) ** 2 == pytest.approx(3.75, abs=1e-3)
    res = fitlib.fit(None, tracks, {"mu": 0.45}, [])
    assert res.values["mu"] == pytest.approx(0.5, abs=1e-6)
    assert res.n == 72 and res.n_eff == pytest.approx(4.0)
    assert res.rss == pytest.approx(12 * 0.01 * 3.5)  # Σ sin²(tπ/7) over t = 1..6 = 7/2


def test_fit_starting_at_the_upper_bound_steps_inward(monkeypatch):
    """μ starts at its upper bound 1.5: the finite-difference step must go down (a step up is clipped back to 1.5,
    a zero Jacobian column, and the fit would never move); the optimum 1.4 is found."""
    _linear_model(monkeypatch)
    tracks = [_track(1.4, [0.1, 0.1, -0.1, -0.1]), _track(1.4, [0.2, 0.2, -0.2, -0.2])]
    res = fitlib.fit(None, tracks, {"mu": fitlib.MU_BOUNDS[1]}, [])
    assert res.values["mu"] == pytest.approx(1.4, abs=1e-6)


def test_mahalanobis_by_hand():
    """wind (0.1, 0.1) from its null (0, 0) with covariance 0.01 [[1, 0.5], [0.5, 1]]: d ᵀC⁻¹d = (1 + 1 - 0.5 - 0.5) /
    0.75 = 4/3, distance 2/√3; restitution 0.33 from its null 0.13 with σ 0.04: 5 standard errors."""
    names = ["mu", "wind_x", "wind_y", "restitution"]
    cov = np.diag([1.0, 0.01, 0.01, 0.0016])
    cov[1, 2] = cov[2, 1] = 0.005
    values = {"mu": 0.5, "wind_x": 0.1, "wind_y": 0.1, "restitution": 0.33}
    r = FitResult(values, ["wind", "restitution"], {}, 1.0, 10, 10.0, 4, 0, cov, names)
    assert r.mahalanobis("wind") == pytest.approx(2 / math.sqrt(3))
    assert r.mahalanobis("restitution") == pytest.approx(5.0)


def test_fit_arguments_of_the_wrong_kind_are_named():
    """No 'mu' in start failed on a bare KeyError, a NaN μ inside scipy, an unknown or str candidate on KeyError
    ('w' for "wind"), no tracks on an IndexError and max_evals 0 in scipy; clustered_cov with sizes summing to 2
    of 4 residuals left two out of every cluster, silently."""
    with pytest.raises(ValueError, match=r"fit: start\['mu'\] = None: start must be a dict with a finite"):
        fitlib.fit(None, [_track(0.5, [0.1] * 4)], {}, [])
    with pytest.raises(ValueError, match=r"fit: start\['mu'\] = nan"):
        fitlib.fit(None, [_track(0.5, [0.1] * 4)], {"mu": math.nan}, [])
    with pytest.raises(ValueError, match=r"fit: active: unknown candidate\(s\) \['nope'\]; known: \['rolling"):
        fitlib.fit(None, [_track(0.5, [0.1] * 4)], {"mu": 0.4}, ["nope"])
    with pytest.raises(TypeError, match=r"fit: active is a str 'wind'"):
        fitlib.fit(None, [_track(0.5, [0.1] * 4)], {"mu": 0.4}, "wind")
    with pytest.raises(ValueError, match=r"fit: tracks = \[\]: must be a non-empty list"):
        fitlib.fit(None, [], {"mu": 0.4}, [])
    with pytest.raises(ValueError, match=r"fit: max_evals = 0: must be a whole number >= 1"):
        fitlib.fit(None, [_track(0.5, [0.1] * 4)], {"mu": 0.4}, [], max_evals=0)
    with pytest.raises(ValueError, match=r"clustered_cov: 4 Jacobian rows, 4 residuals, sizes summing to 2"):
        fitlib.clustered_cov(np.ones((4, 1)), np.ones(4), [1, 1])
    # two clusters of 2, J = 1: scores 2 and 2, B = 1/4: 1/4 · 8 · 1/4 · 2/1 = 1
    assert fitlib.clustered_cov(np.ones((4, 1)), np.ones(4), [2, 2]) == pytest.approx(np.ones((1, 1)))


def test_track_errors_by_hand_and_no_tracks_named(monkeypatch):
    """Residuals 0.1 in x, y and z at every frame: RMS sqrt(3 · 0.01) = 0.173205 m; residuals [0.2, 0.2, NaN]
    (a missing frame is left out): sqrt(3 · 0.04) = 0.346410 m. No tracks failed on a bare IndexError deep in the
    batched simulation (effects._run: scenes[0])."""
    _linear_model(monkeypatch)
    tracks = [_track(0.5, [0.1] * 4), _track(0.5, [0.2, 0.2, np.nan])]
    err = fitlib.track_errors(None, tracks, {"mu": 0.5}, [])
    assert err == pytest.approx([0.173205, 0.346410], abs=1e-6)
    for empty in ([], ()):
        with pytest.raises(ValueError, match=r"track_errors: tracks = (\[\]|\(\)): must be a non-empty list"):
            fitlib.track_errors(None, empty, {"mu": 0.5}, [])


@pytest.mark.parametrize("mu0", [0.0, 1.8])
def test_fit_from_a_scene_mu_outside_its_bounds_starts_at_the_bound(monkeypatch, mu0):
    """A scene's μ of 0 or 1.8 (valid scene values, outside MU_BOUNDS [0.02, 1.5]) made the audit's baseline fail
    inside scipy ("Initial guess is outside of provided bounds"); clipped to the bound, the optimum 0.5 is found."""
    _linear_model(monkeypatch)
    tracks = [_track(0.5, [0.1, 0.1, -0.1, -0.1]), _track(0.5, [0.2, 0.2, -0.2, -0.2])]
    res = fitlib.fit(None, tracks, {"mu": mu0}, [])
    assert res.values["mu"] == pytest.approx(0.5, abs=1e-6)


def test_fit_takes_numpy_numbers(monkeypatch):
    """A start μ of np.float32(0.45) and max_evals np.int64(50) were refused ("start must be a dict with a finite
    friction", "must be a whole number") since the argument checks; they fit as 0.45 and 50 do."""
    _linear_model(monkeypatch)
    tracks = [_track(0.5, [0.1, 0.1, -0.1, -0.1]), _track(0.5, [0.2, 0.2, -0.2, -0.2])]
    plain = fitlib.fit(None, tracks, {"mu": 0.45}, [], max_evals=50)
    res = fitlib.fit(None, tracks, {"mu": np.float32(0.45)}, [], max_evals=np.int64(50))
    assert res.values["mu"] == pytest.approx(plain.values["mu"], abs=1e-6)
    with pytest.raises(ValueError, match=r"fit: start\['mu'\] = np.True_"):
        fitlib.fit(None, tracks, {"mu": np.True_}, [])


def test_d_bic_is_on_one_effective_sample_size_and_does_not_depend_on_the_length_unit():
    """The current model: rss 100 over n = 1000, n_eff 50, k = 1. An extension (k = 2) lowers rss by 3 % and its
    residuals come out a little less autocorrelated (n_eff 80). On ref's n_eff: 50 ln 0.97 + ln 50 = +2.389, no
    evidence. Each fit's own n_eff gave 80 ln 0.097 - 50 ln 0.1 + 2 ln 80 - ln 50 = -66.68 (in metres) and, for the
    same fits in millimetres (rss × 10^6), 80 ln 97000 - 50 ln 100000 + 2 ln 80 - ln 50 = +348.0."""
    cur = FitResult({}, [], {}, 100.0, 1000, 50.0, 1, 0)
    ext = FitResult({}, [], {}, 97.0, 1000, 80.0, 2, 0)
    assert ext.d_bic(cur) == pytest.approx(50 * math.log(0.97) + math.log(50))
    assert ext.d_bic(cur) == pytest.approx(2.389, abs=1e-3)
    mm = [FitResult({}, [], {}, f.rss * 1e6, f.n, f.n_eff, f.k, 0) for f in (cur, ext)]
    assert mm[1].d_bic(mm[0]) == pytest.approx(ext.d_bic(cur))
    same = FitResult({}, [], {}, 100.0, 1000, 80.0, 1, 0)  # whiter residuals, nothing else: no difference
    assert same.d_bic(cur) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="same data"):
        FitResult({}, [], {}, 97.0, 999, 80.0, 2, 0).d_bic(cur)
