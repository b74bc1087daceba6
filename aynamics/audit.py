"""Measured-data audit: what the simulation gets wrong, the cause, the extended model and the gain.

    aynamics audit --measured M.csv --scene S.yaml --out DIR [--json]

1. split the trajectories (whole ones) into fit / validation / held-out;
2. refit the baseline (sliding μ, the only scene field every object has) on the fit split;
3. screen every candidate cause (`aynamics.effects.CANDIDATES`) with a coarse fit on top of the current
   model, fit the `FINALISTS` with the lowest screened BIC fully, and accept the best one only when all three
   say so: the information criterion (BIC on the effective sample size) drops by more than `BIC_MARGIN`, the
   validation RMS falls by `VAL_DROP` or more on most validation trajectories (`VAL_MAJORITY`), and the
   fitted value is at least `Z_MIN` standard errors from
   "absent"; two that explain the data equally are reported as ambiguous; repeat on top of the accepted
   cause (up to `max_causes`);
4. with nothing accepted, a sparse regression of flight-phase residual accelerations on a small library of
   terms decides between "none" and "unexplained" (and gives the form of the unexplained effect);
5. the extended scene is re-simulated on the held-out split; the gain has a bootstrap interval over tracks.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np

from aynamics import scene as scenelib
from aynamics.effects import CANDIDATES, GRIDS, NAMES, STEP_HZ, physics_rate, scene_with, simulate_many
from aynamics.fit import FitResult, check_candidates, fit, flat, track_errors
from aynamics.measured import Measured, MeasuredError, Track, check_units, split
from aynamics.residuals import sparse_terms

BIC_MARGIN = 10.0
VAL_DROP = 0.30  # validation RMS must fall by >= 30 % (nulls: at most ~15 % from fitting the integrator's bias)
Z_MIN = 10.0  # standard errors: the effective-sample-size errors of contact-rich fits are optimistic (a null reached 7)
AMBIGUOUS = 0.10  # a runner-up reaching 90 % of the best's validation improvement is as good ...
AMBIGUOUS_RESIDUAL = 1.25  # ... when it also leaves at most this times the best's validation RMS
SCREEN_EVALS = 4  # least-squares iterations of the coarse screening fit of every candidate
FINALISTS = 3  # candidates with the lowest screened BIC that are fitted fully and judged
VAL_MAJORITY = 0.6  # ... and at least this share of the validation trajectories must improve (not a lucky few)
PAIR_POOL = 5  # with no single cause accepted, pairs of this many best-screened candidates are fitted jointly
# (3 lost floor tilt + linear drag once ΔBIC is on one n_eff: floor tilt alone screens 5th, validation only 5 % better)
PAIR_GRID = 32  # most starting points of a pair's product grid
BOOTSTRAP = 2000


@dataclass
class CandidateRow:
    """One candidate fitted on top of a model: its values and the three pieces of evidence."""

    name: str
    round: int
    values: dict[str, float]
    sigma: dict[str, float]
    d_bic: float
    val_rms: float
    val_drop: float
    z: float
    significant: bool
    screened_out: bool = False  # judged on the coarse screening fit only (not among the finalists)
    pair: str = ""  # "a + b" when fitted jointly with another candidate
    val_errors: np.ndarray | None = field(default=None, repr=False)  # (n_val,) per-track RMS, m


@dataclass
class AuditResult:
    verdict: str  # found | none | ambiguous | unexplained
    causes: list[str]
    parameters: dict[str, float]
    held_out_error_before: float  # m, RMS over held-out trajectories of each one's RMS (every trajectory counts alike)
    held_out_error_after: float
    gain_interval: tuple[float, float]  # 95 % bootstrap interval of before - after, m
    ratio_interval: tuple[float, float]  # of after / before
    extended_scene: str
    baseline: FitResult
    final: FitResult
    rows: list[CandidateRow]
    splits: dict[str, list[str]]
    held_before: np.ndarray  # (n_held,) per-track RMS, m
    held_after: np.ndarray
    unexplained: list[dict] = field(default_factory=list)
    ambiguous_with: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0
    step_hz: int = STEP_HZ  # physics rate the audit simulated at

    @property
    def cause(self) -> str:
        return self.causes[0] if self.causes else "none"

    def to_json(self) -> dict:
        return {
            "cause": self.cause,
            "causes": list(self.causes),
            "verdict": self.verdict,
            "parameters": {k: round(float(v), 6) for k, v in self.parameters.items()},
            "held_out_error_before": round(self.held_out_error_before, 6),
            "held_out_error_after": round(self.held_out_error_after, 6),
            "held_out_gain_interval": [round(x, 6) for x in self.gain_interval],
            "extended_scene": self.extended_scene,
        }


def _rms(errors: np.ndarray) -> float:
    return float(math.sqrt(np.mean(errors**2)))


def check_objects(measured: Measured, scene: scenelib.Scene) -> scenelib.Scene:
    """Match the CSV's objects to the scene's (by name, or one to one when each has a single object)."""
    names = scene.names
    if len(measured.objects) != len(names):
        raise MeasuredError(
            f"the measured data has objects {list(measured.objects)}, the scene has {list(names)}: counts differ"
        )
    if len(names) == 1 or tuple(measured.objects) == names:
        return scene
    missing = [o for o in measured.objects if o not in names]
    if missing:
        raise MeasuredError(f"measured object(s) {missing} are not in the scene, whose objects are {list(names)}")
    order = [names.index(o) for o in measured.objects]
    return scene.model_copy(update={"objects": tuple(scene.objects[k] for k in order)})


def bootstrap(before: np.ndarray, after: np.ndarray, seed: int = 0) -> tuple[tuple, tuple]:
    """95 % intervals of RMS(before) - RMS(after) and RMS(after) / RMS(before), resampling whole tracks."""
    before, after = np.asarray(before, float), np.asarray(after, float)
    if before.ndim != 1 or before.shape != after.shape or not len(before) or not np.isfinite([before, after]).all():
        # unequal lengths failed on an IndexError; none, or a NaN, gave a NaN interval
        raise ValueError(
            f"bootstrap: before {before.shape}, after {after.shape}: need two equal, non-empty 1-D "
            "arrays of finite per-track errors"
        )
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(before), (BOOTSTRAP, len(before)))
    b = np.sqrt(np.mean(before[idx] ** 2, axis=1))
    a = np.sqrt(np.mean(after[idx] ** 2, axis=1))
    diff = np.percentile(b - a, [2.5, 97.5])
    ratio = np.percentile(a / np.maximum(b, 1e-12), [2.5, 97.5])
    return (float(diff[0]), float(diff[1])), (float(ratio[0]), float(ratio[1]))


def _baseline(scene: scenelib.Scene, fit_t: list[Track]) -> FitResult:
    """The baseline: μ fitted from the scene's own μ (the only field every object has)."""
    return fit(scene, fit_t, {"mu": float(np.mean([o.physics.friction[0] for o in scene.objects]))}, [])


def _screen(scene: scenelib.Scene, fit_t: list[Track], cur: FitResult, name: str) -> FitResult:
    """Coarse screening of one candidate on top of the current model: every point of its grid (`GRIDS`) in one
    batch, then a short least-squares fit from the best point."""
    c = CANDIDATES[name]
    starts = [{**cur.values, **dict(zip(c.params, g, strict=True))} for g in GRIDS[name]]
    sims = simulate_many(scene, fit_t, starts, cur.active + [name])
    rss = [float(np.sum(flat([p - tr.position for p, tr in zip(sm.position, fit_t, strict=True)]) ** 2)) for sm in sims]
    return fit(scene, fit_t, starts[int(np.argmin(rss))], cur.active + [name], max_evals=SCREEN_EVALS)


def _screened_row(res: FitResult, cur: FitResult, name: str, rnd: int) -> CandidateRow:
    vals = {p: res.values[p] for p in CANDIDATES[name].params}
    sigma = {p: res.sigma[p] for p in CANDIDATES[name].params}
    nan = float("nan")
    return CandidateRow(name, rnd, vals, sigma, res.d_bic(cur), nan, nan, res.mahalanobis(name), False, True)


def _candidate(
    scene: scenelib.Scene,
    fit_t: list[Track],
    val_t: list[Track],
    cur: FitResult,
    cur_err: np.ndarray,
    name: str,
    rnd: int,
    start: FitResult | None = None,
) -> tuple[CandidateRow, FitResult]:
    """Fit one candidate fully (from its screening fit when given) and weigh the evidence."""
    res = fit(scene, fit_t, dict((start or cur).values), cur.active + [name])
    if start is not None and start.rss < res.rss:
        res = start
    err = track_errors(scene, val_t, res.values, res.active)
    val, drop, most = _validation(err, cur_err)
    d_bic = res.d_bic(cur)
    z = res.mahalanobis(name)
    sig = d_bic < -BIC_MARGIN and drop >= VAL_DROP and most and z >= Z_MIN
    vals = {p: res.values[p] for p in CANDIDATES[name].params}
    sigma = {p: res.sigma[p] for p in CANDIDATES[name].params}
    return CandidateRow(name, rnd, vals, sigma, d_bic, val, drop, z, sig, val_errors=err), res


def _validation(err: np.ndarray, cur_err: np.ndarray) -> tuple[float, float, bool]:
    """Validation RMS, its drop against the current model, and whether most validation tracks improved."""
    val, cur_val = _rms(err), _rms(cur_err)
    drop = 1 - val / cur_val if cur_val > 0 else 0.0
    return val, drop, bool(np.mean(err < cur_err) >= VAL_MAJORITY)


def ambiguous_with(best: CandidateRow, others: list[CandidateRow], cur_val: float) -> list[str]:
    """The significant runners-up that explain the validation data about as well as `best`: within `AMBIGUOUS` of
    its improvement in mean squared error over the current model (RMS `cur_val`) AND leaving at most
    `AMBIGUOUS_RESIDUAL` times its validation RMS. The first test alone called a cause leaving 5 cm "as good" as
    one leaving 2.7 mm whenever the baseline was far off (17 cm: 90 % of the improvement is all but 5.4 cm)."""
    gain = cur_val**2 - best.val_rms**2
    return [
        r.name
        for r in others
        if r.val_rms**2 - best.val_rms**2 <= AMBIGUOUS * gain and r.val_rms <= AMBIGUOUS_RESIDUAL * best.val_rms
    ]


def _pairs(
    scene: scenelib.Scene,
    fit_t: list[Track],
    val_t: list[Track],
    cur: FitResult,
    cur_err: np.ndarray,
    ranked: list[str],
    rows: list[CandidateRow],
    say,
) -> FitResult | None:
    """Two causes that only together explain the data (each alone passes no test): the pairs of the
    `PAIR_POOL` best-screened candidates, each started from the best point of its product grid and fitted
    jointly; the best pair whose every part is significant is returned."""
    best: tuple[float, FitResult] | None = None
    for a, b in itertools.combinations(ranked[:PAIR_POOL], 2):
        ca, cb = CANDIDATES[a], CANDIDATES[b]
        grid = [(ga, gb) for ga in GRIDS[a] for gb in GRIDS[b]]
        grid = grid[:: max(1, math.ceil(len(grid) / PAIR_GRID))]
        starts = [
            {**cur.values, **dict(zip(ca.params, ga, strict=True)), **dict(zip(cb.params, gb, strict=True))}
            for ga, gb in grid
        ]
        active = cur.active + [a, b]
        sims = simulate_many(scene, fit_t, starts, active)
        rss = [
            float(np.sum(flat([p - tr.position for p, tr in zip(sm.position, fit_t, strict=True)]) ** 2)) for sm in sims
        ]
        res = fit(scene, fit_t, starts[int(np.argmin(rss))], active)
        err = track_errors(scene, val_t, res.values, res.active)
        val, drop, most = _validation(err, cur_err)
        d_bic = res.d_bic(cur)
        ok = d_bic < -BIC_MARGIN and drop >= VAL_DROP and most
        for name in (a, b):
            z = res.mahalanobis(name)
            vals = {p: res.values[p] for p in CANDIDATES[name].params}
            sigma = {p: res.sigma[p] for p in CANDIDATES[name].params}
            ok &= z >= Z_MIN
            rows.append(CandidateRow(f"{name}", 0, vals, sigma, d_bic, val, drop, z, False, False, f"{a} + {b}"))
        if ok:
            for r in rows[-2:]:
                r.significant = True
        say(f"pair {a} + {b}: dBIC {d_bic:.1f}, val {val:.4g} m ({drop:+.0%}) {'*' if ok else ''}")
        if ok and (best is None or val < best[0]):
            best = (val, res)
    return None if best is None else best[1]


def audit(
    measured: Measured,
    scene: scenelib.Scene,
    seed: int = 0,
    max_causes: int = 2,
    candidates: tuple[str, ...] = NAMES,
    log=None,
    held_out: list[str] | None = None,
    step_hz: int = STEP_HZ,
) -> AuditResult:
    """Run the whole audit on measured trajectories and the nominal scene (its objects' shapes and physics).

    `held_out` fixes the held-out trajectories (the rest is split into fit / validation by `seed`); `step_hz`
    is the physics rate of every simulation (see `aynamics.effects.physics_rate`).
    """
    if not isinstance(measured, Measured):  # a path failed on "'str' object has no attribute 'objects'"
        raise TypeError(
            f"audit: measured is a {type(measured).__name__}, not Measured (measured.read_csv reads a file)"
        )
    scenelib.require_scene(scene, "audit: scene")
    candidates = tuple(check_candidates(candidates, "audit: candidates"))
    for name, value in (("max_causes", max_causes), ("step_hz", step_hz), ("seed", seed)):
        if not scenelib.is_whole(value) or value < 0:
            raise ValueError(f"audit: {name} = {value!r}: must be a whole number >= 0")
    with physics_rate(step_hz):
        result = _audit(measured, scene, seed, max_causes, candidates, log, held_out)
    result.step_hz = step_hz
    return result


def _audit(
    measured: Measured,
    scene: scenelib.Scene,
    seed: int,
    max_causes: int,
    candidates: tuple[str, ...],
    log,
    held_out: list[str] | None,
) -> AuditResult:
    t0 = time.perf_counter()
    say = log or (lambda msg: None)
    scene = check_objects(measured, scene)
    check_units(measured)
    fit_ids, val_ids, held_ids = split(measured.ids, seed, held_out=held_out)
    fit_t, val_t, held_t = measured.subset(fit_ids), measured.subset(val_ids), measured.subset(held_ids)
    base = _baseline(scene, fit_t)
    cur_err = track_errors(scene, val_t, base.values, [])
    cur, cur_val = base, _rms(cur_err)
    say(f"baseline: mu = {base.values['mu']:.4f}, validation RMS {cur_val:.4g} m")
    rows: list[CandidateRow] = []
    causes: list[str] = []
    ambiguous: list[str] = []
    for rnd in range(max_causes):
        tried = []
        screened = {name: _screen(scene, fit_t, cur, name) for name in candidates if name not in cur.active}
        by_bic = sorted(screened, key=lambda n: screened[n].d_bic(cur))
        finalists = by_bic[:FINALISTS]
        say(f"round {rnd} screening: " + ", ".join(f"{n} {screened[n].d_bic(cur):.1f}" for n in screened))
        for name in screened:
            if name not in finalists:
                rows.append(_screened_row(screened[name], cur, name, rnd))
        for name in finalists:
            row, res = _candidate(scene, fit_t, val_t, cur, cur_err, name, rnd, screened[name])
            rows.append(row)
            tried.append((row, res))
            say(
                f"round {rnd} {name} {', '.join(f'{k}={v:.4g}' for k, v in row.values.items())}: dBIC "
                f"{row.d_bic:.1f}, val {row.val_rms:.4g} m ({row.val_drop:+.0%}), z {row.z:.1f} "
                f"{'*' if row.significant else ''}"
            )
        sig = sorted([tr for tr in tried if tr[0].significant], key=lambda tr: tr[0].val_rms)
        if not sig and rnd == 0 and max_causes >= 2:
            pair = _pairs(scene, fit_t, val_t, cur, cur_err, by_bic, rows, say)
            if pair is not None:
                causes += pair.active
                cur, cur_val = pair, _rms(track_errors(scene, val_t, pair.values, pair.active))
            break
        if not sig:
            break
        best, best_res = sig[0]
        if rnd == 0:
            ambiguous = ambiguous_with(best, [r for r, _ in sig[1:]], cur_val)
        causes.append(best.name)
        cur, cur_val, cur_err = best_res, best.val_rms, best.val_errors
    unexplained: list[dict] = []
    if not causes:
        unexplained = sparse_terms(scene, fit_t + val_t, base.values, [])
    verdict = "none"
    if causes:
        verdict = "ambiguous" if ambiguous else "found"
    elif unexplained:
        verdict = "unexplained"
    # the extended scene as written (canonical YAML, 4 decimals) is what is re-simulated on the held-out split
    extended = scenelib.parse(scenelib.dump(scene_with(scene, cur.values, cur.active)))
    held_before = track_errors(scene, held_t, base.values, [])
    held_after = track_errors(extended, held_t, {}, []) if causes else held_before
    gain_ci, ratio_ci = bootstrap(held_before, held_after, seed)
    params = {"mu": float(extended.objects[0].physics.friction[0])}  # the scene's μ (at v = 0)
    for c in causes:
        params.update({p: cur.values[p] for p in CANDIDATES[c].params})
    notes: list[str] = []
    return AuditResult(
        verdict=verdict,
        causes=causes + [a for a in ambiguous if a not in causes],
        parameters=params,
        held_out_error_before=_rms(held_before),
        held_out_error_after=_rms(held_after),
        gain_interval=gain_ci,
        ratio_interval=ratio_ci,
        extended_scene=scenelib.dump(extended),
        baseline=base,
        final=cur,
        rows=rows,
        splits={"fit": fit_ids, "validation": val_ids, "held_out": held_ids},
        held_before=held_before,
        held_after=held_after,
        unexplained=unexplained,
        ambiguous_with=ambiguous,
        notes=notes,
        seconds=time.perf_counter() - t0,
    )


# --------------------------------------------------------------------------------------------
# CLI: aynamics audit
# --------------------------------------------------------------------------------------------
def add_audit(sub) -> None:
    p = sub.add_parser("audit", help="audit the simulation against measured trajectories: cause, extension, gain")
    p.add_argument("--measured", required=True, help="CSV: trajectory, t, object, x, y, z [, qw.., vx.., wx..]")
    p.add_argument("--scene", required=True, help="scene YAML describing the objects (shape, size, mass, physics)")
    p.add_argument("--out", required=True, help="folder for report.md, plots and extended_scene.yaml")
    p.add_argument("--json", action="store_true", help="print the verdict, causes, parameters and errors as JSON")
    p.add_argument(
        "--step-hz", type=int, default=STEP_HZ, help=f"physics steps per second (default {STEP_HZ}; finer is slower)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the fit / validation / held-out split")
    p.add_argument("--max-causes", type=int, default=2, help="most causes accepted one after another (default 2)")
    p.add_argument(
        "--max-trajectories",
        type=int,
        default=0,
        help="use at most this many trajectories besides a --held-out-every split, which stays whole (0: all; evenly "
        "spaced); with the random split the held-out trajectories are cut from these too",
    )
    p.add_argument(
        "--held-out-every",
        type=int,
        default=0,
        help="hold out the trajectories whose index (integer id, else position) is a multiple of N (0: random)",
    )
    p.set_defaults(run=run_audit)


def run_audit(args) -> int:
    import json
    import sys

    from aynamics.audit_report import AUDIT_FILES, write_report
    from aynamics.cli import UsageError, check_out_folder, load_scene
    from aynamics.measured import Measured, check_units, every_nth, read_csv

    if not 30 <= args.step_hz <= 10_000:
        raise UsageError(f"audit: --step-hz {args.step_hz}: must be in [30, 10000] physics steps per second")
    if args.max_causes < 0 or args.max_trajectories < 0:
        raise UsageError(
            f"audit: --max-causes {args.max_causes}, --max-trajectories {args.max_trajectories}: each must be >= 0"
        )
    if args.seed < 0:
        raise UsageError(f"audit: --seed {args.seed}: must be >= 0")
    if args.held_out_every < 0 or args.held_out_every == 1:
        raise UsageError(f"audit: --held-out-every {args.held_out_every}: must be 0 (a random split) or >= 2")
    check_out_folder("audit", args.out, writes=AUDIT_FILES)  # before the audit's minutes; not mixed into a folder
    scene = load_scene("audit", args.scene, "--scene")
    try:
        measured = read_csv(args.measured)
        check_units(measured, args.measured)
        held = every_nth(measured.ids, args.held_out_every) if args.held_out_every else None
        rest = [i for i in measured.ids if held is None or i not in set(held)]
        if args.max_trajectories and len(rest) > args.max_trajectories:  # a fixed held-out split is kept whole
            keep = {rest[int(k)] for k in np.linspace(0, len(rest) - 1, args.max_trajectories)} | set(held or [])
            measured = Measured(measured.objects, {k: v for k, v in measured.tracks.items() if k in keep})
        result = audit(
            measured,
            scene,
            seed=args.seed,
            max_causes=args.max_causes,
            log=None if args.json else lambda m: print(m, file=sys.stderr),
            held_out=held,
            step_hz=args.step_hz,
        )
        matched = check_objects(measured, scene)
    except MeasuredError as e:
        raise UsageError(f"audit: {e}") from None
    try:
        write_report(result, measured, matched, args.out)
    except OSError as e:
        raise UsageError(f"audit: cannot write --out {args.out!r}: {e.strerror or e}") from None
    if args.json:
        json.dump(result.to_json(), sys.stdout)
        sys.stdout.write("\n")
    else:
        print(
            f"{result.verdict}: {', '.join(result.causes) or 'none'}; held-out RMS "
            f"{result.held_out_error_before:.4f} -> {result.held_out_error_after:.4f} m; report in {args.out}"
        )
    return 0
