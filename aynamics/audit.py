"""Measured-data audit: what the simulation gets wrong, the cause, the extended model and the gain.

    aynamics audit --measured M.csv --scene S.yaml --out DIR [--json]

1. split the trajectories (whole ones) into fit / validation / held-out;
2. refit the baseline (sliding μ, the only scene field every object has) on the fit split;
3. fit each candidate cause (`aynamics.effects.CANDIDATES`) on top of the current model and accept the best
   one only when all three say so: the information criterion (BIC on the effective sample size) drops by
   more than `BIC_MARGIN`, the validation RMS falls by `VAL_DROP` or more, and the fitted value is at least
   `Z_MIN` standard errors from "absent"; two that explain the data equally are reported as ambiguous;
   repeat on top of the accepted cause (up to `max_causes`);
4. with nothing accepted, a sparse regression of flight-phase residual accelerations on a small library of
   terms decides between "none" and "unexplained" (and gives the form of the unexplained effect);
5. the extended scene is re-simulated on the held-out split; the gain has a bootstrap interval over tracks.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from aynamics import scene as scenelib
from aynamics.effects import CANDIDATES, NAMES, scene_with
from aynamics.fit import FitResult, fit, track_errors
from aynamics.measured import Measured, MeasuredError, Track, split
from aynamics.residuals import sparse_terms

BIC_MARGIN = 10.0
VAL_DROP = 0.40  # validation RMS must fall by >= 40 %: a 1 ms vs 1/240 s integrator alone gives up to ~33 %
Z_MIN = 3.0
AMBIGUOUS = 0.10  # a runner-up reaching 90 % of the best's validation improvement is as good
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


@dataclass
class AuditResult:
    verdict: str  # found | none | ambiguous | unexplained
    causes: list[str]
    parameters: dict[str, float]
    held_out_error_before: float  # m, RMS over held-out frames
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
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(before), (BOOTSTRAP, len(before)))
    b = np.sqrt(np.mean(before[idx] ** 2, axis=1))
    a = np.sqrt(np.mean(after[idx] ** 2, axis=1))
    diff = np.percentile(b - a, [2.5, 97.5])
    ratio = np.percentile(a / np.maximum(b, 1e-12), [2.5, 97.5])
    return (float(diff[0]), float(diff[1])), (float(ratio[0]), float(ratio[1]))


def _candidate(
    scene: scenelib.Scene, fit_t: list[Track], val_t: list[Track], cur: FitResult, cur_val: float, name: str, rnd: int
) -> tuple[CandidateRow, FitResult]:
    res = fit(scene, fit_t, dict(cur.values), cur.active + [name])
    alt = CANDIDATES[name].alt_start
    if alt is not None:
        other = fit(scene, fit_t, {**cur.values, **dict(zip(CANDIDATES[name].params, alt, strict=True))}, res.active)
        res = other if other.rss < res.rss else res
    val = _rms(track_errors(scene, val_t, res.values, res.active))
    d_bic = res.bic - cur.bic
    drop = 1 - val / cur_val if cur_val > 0 else 0.0
    z = res.mahalanobis(name)
    sig = d_bic < -BIC_MARGIN and drop >= VAL_DROP and z >= Z_MIN
    vals = {p: res.values[p] for p in CANDIDATES[name].params}
    sigma = {p: res.sigma[p] for p in CANDIDATES[name].params}
    return CandidateRow(name, rnd, vals, sigma, d_bic, val, drop, z, sig), res


def audit(
    measured: Measured,
    scene: scenelib.Scene,
    seed: int = 0,
    max_causes: int = 2,
    candidates: tuple[str, ...] = NAMES,
    log=None,
) -> AuditResult:
    """Run the whole audit on measured trajectories and the nominal scene (its objects' shapes and physics)."""
    t0 = time.perf_counter()
    say = log or (lambda msg: None)
    scene = check_objects(measured, scene)
    fit_ids, val_ids, held_ids = split(measured.ids, seed)
    fit_t, val_t, held_t = measured.subset(fit_ids), measured.subset(val_ids), measured.subset(held_ids)
    mu0 = float(np.mean([o.physics.friction[0] for o in scene.objects]))
    base = fit(scene, fit_t, {"mu": mu0}, [])
    cur, cur_val = base, _rms(track_errors(scene, val_t, base.values, []))
    say(f"baseline: mu = {base.values['mu']:.4f}, validation RMS {cur_val:.4g} m")
    rows: list[CandidateRow] = []
    causes: list[str] = []
    ambiguous: list[str] = []
    for rnd in range(max_causes):
        tried = []
        for name in candidates:
            if name in cur.active:
                continue
            row, res = _candidate(scene, fit_t, val_t, cur, cur_val, name, rnd)
            rows.append(row)
            tried.append((row, res))
            say(
                f"round {rnd} {name}: dBIC {row.d_bic:.1f}, val {row.val_rms:.4g} m ({row.val_drop:+.0%}), "
                f"z {row.z:.1f} {'*' if row.significant else ''}"
            )
        sig = sorted([tr for tr in tried if tr[0].significant], key=lambda tr: tr[0].val_rms)
        if not sig:
            break
        best, best_res = sig[0]
        gain = cur_val**2 - best.val_rms**2
        if rnd == 0:
            ambiguous = [r.name for r, _ in sig[1:] if r.val_rms**2 - best.val_rms**2 <= AMBIGUOUS * gain]
        causes.append(best.name)
        cur, cur_val = best_res, best.val_rms
    unexplained: list[dict] = []
    if not causes:
        unexplained = sparse_terms(scene, fit_t + val_t, base.values, [])
    verdict = "none"
    if causes:
        verdict = "ambiguous" if ambiguous else "found"
    elif unexplained:
        verdict = "unexplained"
    held_before = track_errors(scene, held_t, base.values, [])
    held_after = track_errors(scene, held_t, cur.values, cur.active) if causes else held_before
    gain_ci, ratio_ci = bootstrap(held_before, held_after, seed)
    params = {"mu": cur.values["mu"]}
    for c in causes:
        params.update({p: cur.values[p] for p in CANDIDATES[c].params})
    extended = scenelib.from_items(scenelib.to_items(scene_with(scene, cur.values, cur.active)))
    notes = [
        f"{c} has no scene field yet: its value is reported as a parameter only"
        for c in causes
        if c in ("magnus", "speed_dependent_friction", "time_scale")
    ]
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
    p.add_argument("--seed", type=int, default=0, help="seed of the fit / validation / held-out split")
    p.add_argument("--max-causes", type=int, default=2, help="most causes accepted one after another (default 2)")
    p.add_argument("--max-trajectories", type=int, default=0, help="use at most this many (0: all), evenly spaced")
    p.set_defaults(run=run_audit)


def run_audit(args) -> int:
    import json
    import sys

    from aynamics.audit_report import write_report
    from aynamics.cli import UsageError
    from aynamics.measured import Measured, read_csv

    if args.max_causes < 0 or args.max_trajectories < 0:
        raise UsageError(f"audit: --max-causes {args.max_causes}, --max-trajectories {args.max_trajectories}: >= 0")
    scene = scenelib.load(args.scene)
    try:
        measured = read_csv(args.measured)
        if args.max_trajectories and len(measured.ids) > args.max_trajectories:
            ids = measured.ids
            keep = [ids[int(k)] for k in np.linspace(0, len(ids) - 1, args.max_trajectories)]
            measured = Measured(measured.objects, {k: measured.tracks[k] for k in keep})
        result = audit(
            measured,
            scene,
            seed=args.seed,
            max_causes=args.max_causes,
            log=None if args.json else lambda m: print(m, file=sys.stderr),
        )
        write_report(result, measured, check_objects(measured, scene), args.out)
    except MeasuredError as e:
        raise UsageError(f"audit: {e}") from None
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
