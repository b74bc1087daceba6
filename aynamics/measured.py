"""Measured trajectories: the CSV loader, the cube-toss converter, splits, initial states and motion phases.

CSV columns (one row per measured frame, any order, header required):
    trajectory, t, object, x, y, z              required (s, m; world frame, z up)
    qw, qx, qy, qz                              optional orientation (body -> world, scalar first)
    vx, vy, vz, wx, wy, wz                      optional world linear / BODY angular velocity

    data = read_csv("tosses.csv")                # Measured, one Track per trajectory id
    fit, val, held = split(data.ids, seed=0)     # by whole trajectory
    cube_tosses_csv("../shared/data/cube_tosses/tosses.csv.gz", "cube.csv")  # ContactNets tosses -> our CSV

Irregular timestamps, dropped frames and noise are expected; rows are sorted by time per trajectory.
"""

from __future__ import annotations

import csv
import gzip
import io
import math
import os
import zlib
from dataclasses import dataclass

import numpy as np

from aynamics.scene import RANGES, is_number, is_whole
from aynamics.simulate import geom_size, quat_to_mat

REQUIRED = ("trajectory", "t", "object", "x", "y", "z")
ORIENTATION = ("qw", "qx", "qy", "qz")
LINEAR = ("vx", "vy", "vz")
ANGULAR = ("wx", "wy", "wz")
INIT_WINDOW = 0.08  # s: frames used to estimate the initial state when velocities are not measured
SPIN_FRAMES = 8  # first frames whose measured spin is averaged for the initial spin
PHASES = ("flight", "impact", "sliding", "rolling", "rest")
CONTACT_GAP = 0.006  # m: lowest point this close to the floor counts as contact
REST_SPEED = 0.05  # m/s
BOUNCE_WINDOW = 0.05  # s after a touch-down in which the rebound speed is read
ROLL_SLIP = 0.15  # m/s: contact-point slip below this (and moving) is rolling / tumbling


class MeasuredError(ValueError):
    """A measured-data file is malformed; the message names the row, column and value."""


@dataclass(frozen=True)
class Track:
    """One measured trajectory of N objects over T frames (NaN where an object is missing in a frame).

    Attributes:
        id: trajectory id from the CSV.
        t: (T,) s, increasing, first frame at 0 (shifted).
        position: (T, N, 3) m, world.
        orientation: (T, N, 4) wxyz or None.
        velocity: (T, N, 6) world linear + body angular, or None.
    """

    id: str
    t: np.ndarray
    position: np.ndarray
    orientation: np.ndarray | None
    velocity: np.ndarray | None

    @property
    def duration(self) -> float:
        return float(self.t[-1])


@dataclass(frozen=True)
class Measured:
    """All trajectories of a file, with the object names in column order of `Track` arrays."""

    objects: tuple[str, ...]
    tracks: dict[str, Track]

    @property
    def ids(self) -> list[str]:
        return list(self.tracks)

    def subset(self, ids: list[str]) -> list[Track]:
        return [self.tracks[i] for i in ids]


def _float(value: str, row: int, column: str, path: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise MeasuredError(f"{path}: row {row}, column {column!r} = {value!r}: must be a number") from None
    if not math.isfinite(x):
        raise MeasuredError(f"{path}: row {row}, column {column!r} = {value!r}: must be finite")
    return x


def read_csv(path: str) -> Measured:
    """Read measured trajectories from a CSV (optionally .gz); the cube tosses' published file (a `toss` column,
    one cube) reads as it is, as `cube_tosses_csv` would convert it.

    Raises:
        MeasuredError: missing or unreadable file, missing column, a row with more or fewer values than the
            header, non-numeric or non-finite value, duplicate timestamp.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"read_csv: path is a {type(path).__name__}: must be a file path (str or pathlib.Path)")
    path = os.fspath(path)  # a pathlib.Path failed on "'PosixPath' object has no attribute 'endswith'"
    if not isinstance(path, str):
        raise TypeError(f"read_csv: path {path!r} is bytes: must be a str or pathlib.Path")
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise MeasuredError(f"--measured {path!r}: {e.strerror or e}") from None
    if path.endswith(".gz"):
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error) as e:  # not gzip, truncated, corrupt
            raise MeasuredError(f"--measured {path!r}: not a readable gzip file ({type(e).__name__}: {e})") from None
    reader = csv.reader(io.StringIO(raw.decode("utf-8-sig", errors="replace")))  # -sig: a spreadsheet's BOM
    header = [h.strip() for h in next(reader, [])]
    if "toss" in header and "trajectory" not in header and "object" not in header:
        # the cube tosses as published (../shared/data/cube_tosses/tosses.csv.gz): one object, "cube"
        header = ["trajectory" if h == "toss" else h for h in header] + ["object"]
        reader = (line + ["cube"] if line else line for line in reader)
    twice = sorted({h for h in header if header.count(h) > 1 and h})
    if twice:  # the last of two "z" columns was read, silently
        raise MeasuredError(f"{path}: column(s) {twice} appear more than once in the header {header}")
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise MeasuredError(f"{path}: missing column(s) {missing}; header is {header}; required: {list(REQUIRED)}")
    col = {h: i for i, h in enumerate(header)}
    has_q = all(c in col for c in ORIENTATION)
    has_lin, has_ang = all(c in col for c in LINEAR), all(c in col for c in ANGULAR)
    vel_cols = (list(LINEAR) if has_lin else []) + (list(ANGULAR) if has_ang else [])
    numeric = ["t", "x", "y", "z"] + (list(ORIENTATION) if has_q else []) + vel_cols
    rows: dict[str, list[tuple[float, str, list[float]]]] = {}
    objects: list[str] = []
    for r, line in enumerate(reader, start=2):
        if not line or all(not c.strip() for c in line):
            continue
        if len(line) != len(header):
            raise MeasuredError(f"{path}: row {r} has {len(line)} values, the header has {len(header)}")
        vals = [_float(line[col[c]], r, c, path) for c in numeric]
        obj = line[col["object"]].strip()
        if obj not in objects:
            objects.append(obj)
        rows.setdefault(line[col["trajectory"]].strip(), []).append((vals[0], obj, vals[1:]))
    if not rows:
        raise MeasuredError(f"{path}: no data rows")
    tracks = {tid: _track(tid, rr, objects, has_q, (has_lin, has_ang), path) for tid, rr in rows.items()}
    return Measured(tuple(objects), tracks)


def _track(tid: str, rows: list, objects: list[str], has_q: bool, has_v: tuple[bool, bool], path: str) -> Track:
    times = np.unique(np.array([r[0] for r in rows]))
    if len(times) < 4:
        raise MeasuredError(f"{path}: trajectory {tid!r} has {len(times)} distinct times: at least 4 needed")
    n, nt = len(objects), len(times)
    pos = np.full((nt, n, 3), np.nan)
    quat = np.full((nt, n, 4), np.nan) if has_q else None
    vel = np.full((nt, n, 6), np.nan) if any(has_v) else None
    vcols = ([0, 1, 2] if has_v[0] else []) + ([3, 4, 5] if has_v[1] else [])
    seen = set()
    for time, obj, v in rows:
        k, i = int(np.searchsorted(times, time)), objects.index(obj)
        if (k, i) in seen:
            raise MeasuredError(f"{path}: trajectory {tid!r}, object {obj!r}: two rows at t = {time}")
        seen.add((k, i))
        pos[k, i] = v[:3]
        if quat is not None:
            q = np.array(v[3:7])
            norm = np.linalg.norm(q)
            if not 0.5 < norm < 1.5:
                raise MeasuredError(f"{path}: trajectory {tid!r}, t = {time}: quaternion {q.tolist()} is not unit")
            quat[k, i] = q / norm
        if vel is not None:
            off = 7 if has_q else 3
            vel[k, i, vcols] = v[off : off + len(vcols)]
    rows_of = np.isfinite(pos).all(-1).sum(0)  # (n,) measured rows of each object
    for i, obj in enumerate(objects):
        if rows_of[i] < 4:  # its initial state is a fit over its first rows (it crashed with an IndexError)
            raise MeasuredError(
                f"{path}: trajectory {tid!r}, object {obj!r}: {int(rows_of[i])} measured rows, at least 4 needed "
                "(every object of the file must be measured in every trajectory)"
            )
    return Track(tid, times - times[0], pos, quat, vel)


MAX_DURATION = 60.0  # s: longest trajectory the audit simulates (simulate.SimConfig's limit)
MAX_EXTENT = 100.0  # m: no measured position of a rigid-body toss lies farther from the origin
MAX_SPEED = RANGES["state.linear_velocity"].hi  # m/s: the scene range of each initial velocity component


def check_units(data: Measured, path: str = "the measured data") -> None:
    """Refuse trajectories whose numbers cannot be seconds and metres (a file in mm or ms): they were simulated as
    they are and ended in a confident verdict ("unexplained", a 2e4 m/s² term) or an audit running for hours.

    Raises:
        MeasuredError: a trajectory longer than `MAX_DURATION` s, a position beyond `MAX_EXTENT` m, or an initial
            velocity component beyond `MAX_SPEED` m/s, naming the trajectory, object and value.
    """
    if not isinstance(data, Measured):  # a path failed on "'str' object has no attribute 'tracks'"
        raise TypeError(f"check_units: data is a {type(data).__name__}, not Measured (read_csv reads a file)")
    for tid, tr in data.tracks.items():
        if tr.duration > MAX_DURATION:
            raise MeasuredError(
                f"{path}: trajectory {tid!r} lasts {tr.duration:g} s (t from {tr.t[0]:g} to {tr.t[-1]:g}): at most "
                f"{MAX_DURATION:g} s; column t must be in seconds (milliseconds? divide by 1000)"
            )
        for i, obj in enumerate(data.objects):
            p = tr.position[:, i]
            far = np.nanmax(np.abs(p))
            if far > MAX_EXTENT:
                raise MeasuredError(
                    f"{path}: trajectory {tid!r}, object {obj!r}: a position of {far:g} m: columns x, y, z must be in "
                    f"metres (millimetres? divide by 1000)"
                )
            speed = float(np.max(np.abs(initial_state(tr, i)["linear_velocity"])))  # the range is per component
            if speed > MAX_SPEED:
                raise MeasuredError(
                    f"{path}: trajectory {tid!r}, object {obj!r}: an initial velocity component of {speed:.4g} m/s, "
                    f"beyond the scene range of ±{MAX_SPEED:g} m/s; are t in seconds and x, y, z in metres?"
                )


def cube_tosses_csv(src: str, dst: str, tosses: list[int] | None = None) -> int:
    """Convert the ContactNets cube tosses (toss, t, qw.., x.., wx.., vx..) into our CSV; returns rows written."""
    try:
        text = gzip.open(src, "rt").read() if src.endswith(".gz") else open(src).read()
    except OSError as e:
        raise MeasuredError(f"cube tosses {src!r}: {e.strerror or e}") from None
    reader = csv.DictReader(io.StringIO(text))
    keep = None if tosses is None else {str(k) for k in tosses}
    out = ["trajectory,t,object,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz"]
    for row in reader:
        if keep is not None and row["toss"] not in keep:
            continue
        vals = [row[c] for c in ("t", "x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")]
        out.append(f"{row['toss']},{vals[0]},cube," + ",".join(vals[1:]))
    with open(dst, "w") as f:
        f.write("\n".join(out) + "\n")
    return len(out) - 1


def trajectory_ids(ids, where: str) -> list[str]:
    """`ids` as a list of distinct str trajectory ids, else an error naming `where`: a str was taken as a list of
    its characters ("10" held out trajectories 1 and 0) and a repeated id put one trajectory in two splits."""
    if isinstance(ids, (str, bytes)) or not hasattr(ids, "__iter__"):
        raise TypeError(f"{where} is a {type(ids).__name__} {ids!r:.60}: must be a list of trajectory ids")
    ids = list(ids)
    for k, i in enumerate(ids):
        if not isinstance(i, str):
            raise TypeError(f"{where}[{k}] = {i!r}: trajectory ids are str (as read_csv gives them)")
    twice = sorted({i for i in ids if ids.count(i) > 1}) if len(set(ids)) != len(ids) else []
    if twice:
        raise MeasuredError(f"{where}: trajectory id(s) {twice[:5]} appear more than once")
    return ids


def split(
    ids: list[str], seed: int = 0, fractions: tuple[float, float] = (0.5, 0.25), held_out: list[str] | None = None
) -> tuple[list, list, list]:
    """Shuffle trajectory ids and cut them into fit / validation / held-out (whole trajectories).

    With `held_out` given, those ids are the held-out split and the rest is cut into fit and validation in the
    ratio of `fractions`.
    """
    ids = trajectory_ids(ids, "split: ids")
    fr = fractions
    if (
        isinstance(fr, (str, bytes))
        or len(fr) != 2
        or not all(is_number(f) for f in fr)  # np.float32 too
        or not (fr[0] > 0 and fr[1] > 0 and fr[0] + fr[1] < 1)
    ):  # (2, 0.25) left the validation and held-out splits empty; (-1, 0.25) gave fit one trajectory
        raise ValueError(f"split: fractions = {fr!r}: must be (fit, validation), each > 0, summing to less than 1")
    if held_out is not None:
        held_out = trajectory_ids(held_out, "split: held_out")
        unknown = [h for h in held_out if h not in ids]
        if unknown:
            raise MeasuredError(f"held-out trajectories {unknown[:5]} are not in the data")
        rest = [i for i in ids if i not in set(held_out)]
        if len(rest) < 2 or not held_out:
            raise MeasuredError(
                f"{len(held_out)} held-out of {len(ids)} trajectories: at least 1 held out and 2 left to fit"
            )
        order = list(np.random.default_rng(seed).permutation(len(rest)))
        a = min(len(rest) - 1, max(1, int(round(fractions[0] / sum(fractions) * len(rest)))))
        pick = [rest[k] for k in order]
        return pick[:a], pick[a:], list(held_out)
    if len(ids) < 3:
        raise MeasuredError(f"{len(ids)} trajectories: at least 3 are needed to split fit/validation/held-out")
    order = list(np.random.default_rng(seed).permutation(len(ids)))
    n = len(ids)
    a = min(n - 2, max(1, int(round(fractions[0] * n))))  # at least one validation and one held-out trajectory
    b = max(a + 1, min(n - 1, a + int(round(fractions[1] * n))))
    pick = [ids[k] for k in order]
    return pick[:a], pick[a:b], pick[b:]


def every_nth(ids: list[str], n: int) -> list[str]:
    """The ids whose index is a multiple of n: the integer id itself when every id is an integer, else the
    position in the file (e.g. cube tosses 0, 5, 10, ... for n = 5)."""
    ids = trajectory_ids(ids, "every_nth: ids")
    if not is_whole(n):  # 2.5 held out ['0'], "2" failed on '<'
        raise TypeError(f"held-out every {n!r}: must be a whole number >= 2, not a {type(n).__name__}")
    if n < 2:
        raise MeasuredError(f"held-out every {n}: must be >= 2")
    try:
        return [i for i in ids if int(i) % n == 0]
    except ValueError:
        return [i for k, i in enumerate(ids) if k % n == 0]


def initial_state(track: Track, i: int, time_scale: float = 1.0) -> dict[str, np.ndarray]:
    """Initial position, orientation, world linear and WORLD angular velocity of object i at t = 0.

    Measured velocities are used when the file has them; otherwise a quadratic fit over the first
    `INIT_WINDOW` s gives position and velocity (spin zero without orientation). `time_scale` s converts
    data-clock velocities to physical ones (v / s) for the time-scale candidate.
    """
    t, p = track.t, track.position[:, i]
    ok = np.isfinite(p).all(-1)
    sel = ok & (t <= t[ok][0] + INIT_WINDOW)
    if sel.sum() < 4:  # a mask, not the frames' indices: np.flatnonzero below read [0, 1, 2, 3] as frames 1, 2, 3
        sel = np.zeros_like(ok)
        sel[np.flatnonzero(ok)[:4]] = True
    tt, pp = t[sel] - t[ok][0], p[sel]
    coef = np.polynomial.polynomial.polyfit(tt, pp, 2)  # (3, 3): c0, c1, c2 per axis
    k0 = int(np.flatnonzero(ok)[0])
    quat = track.orientation[k0, i] if track.orientation is not None else np.array([1.0, 0, 0, 0])
    lin, ang, pos = coef[1], np.zeros(3), coef[0]
    if track.velocity is not None and np.isfinite(track.velocity[k0, i, :3]).all():
        lin, pos = track.velocity[k0, i, :3], p[k0]
    if track.velocity is not None and np.isfinite(track.velocity[k0, i, 3:]).all():
        # world spin averaged over the first SPIN_FRAMES frames: one frame's measured spin is noisy, and a few
        # tenths of rad/s of spurious yaw or tilt decide where a sliding box ends up
        ks = [k for k in np.flatnonzero(sel)[:SPIN_FRAMES] if np.isfinite(track.velocity[k, i, 3:]).all()]
        if track.orientation is not None and ks:
            ang = np.mean([quat_to_mat(track.orientation[k, i]) @ track.velocity[k, i, 3:] for k in ks], axis=0)
        else:
            ang = quat_to_mat(quat) @ track.velocity[k0, i, 3:]
    return {"position": pos, "orientation": quat, "linear_velocity": lin / time_scale, "angular": ang / time_scale}


def object_size(obj) -> np.ndarray:
    """`support_height`'s size of a scene object: box half-extents, (r,) sphere, (r, full height) cylinder."""
    g = geom_size(obj)
    return g if obj.type == "box" else (g[:1] if obj.type == "sphere" else np.array([g[0], 2 * g[1]]))


def support_height(position: np.ndarray, orientation: np.ndarray | None, kind: str, size: np.ndarray) -> np.ndarray:
    """(T,) height of the object's lowest point above z = 0. size: box half-extents, (r,) sphere, (r, h) cylinder."""
    z = position[:, 2]
    if kind == "sphere":
        return z - size[0]
    if orientation is None:
        return z - (min(size) if kind == "box" else min(size[0], size[1] / 2))
    rz = quat_to_mat(orientation)[:, 2, :]  # (T, 3): world z row
    if kind == "box":
        return z - np.abs(rz) @ np.asarray(size)
    c = np.abs(rz[:, 2])
    return z - (c * size[1] / 2 + size[0] * np.sqrt(np.clip(1 - c * c, 0, 1)))


def phases(t: np.ndarray, position: np.ndarray, support: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """(T,) phase index into PHASES for one object from its measured motion (independent of any model)."""
    dt = np.gradient(t)
    vel = np.gradient(position, axis=0) / np.maximum(dt, 1e-6)[:, None]
    speed = np.linalg.norm(vel, axis=-1)
    contact = support - floor < CONTACT_GAP
    out = np.zeros(len(t), dtype=int)  # flight
    # slip of the contact point: horizontal speed of the lowest point is unknown without spin; use the
    # change of horizontal speed instead: sliding decelerates (friction), rolling/tumbling keeps speed
    acc_h = np.linalg.norm(np.gradient(vel[:, :2], axis=0) / np.maximum(dt, 1e-6)[:, None], axis=-1)
    out[contact & (acc_h > 1.0)] = PHASES.index("sliding")
    out[contact & (acc_h <= 1.0)] = PHASES.index("rolling")
    out[contact & (speed < REST_SPEED)] = PHASES.index("rest")
    onset = np.flatnonzero(contact[1:] & ~contact[:-1]) + 1
    for k in onset:
        out[max(0, k - 1) : k + 2] = PHASES.index("impact")
    return out


def bounces(t: np.ndarray, position: np.ndarray, support: np.ndarray, floor: float = 0.0) -> list[float]:
    """Vertical restitution at each impact after flight: (largest upward centre speed within `BOUNCE_WINDOW` s
    after the touch-down) / (downward centre speed over the last flight frames before it).

    The rebound is read as the best upward speed after the touch-down, not at one fixed frame: a soft contact
    (MuJoCo's) takes tens of milliseconds to give the energy back and a rigid one (the real cube) a few, and a
    frame counted from the bottom of the dip compares the two at different stages of the impact.
    """
    contact = support - floor < CONTACT_GAP
    onset = np.flatnonzero(contact[1:] & ~contact[:-1]) + 1
    out = []
    for k in onset:
        k = int(k)
        if k < 3 or k + 2 >= len(t):
            continue
        vz_in = (position[k - 1, 2] - position[k - 3, 2]) / (t[k - 1] - t[k - 3])
        after = np.flatnonzero((t > t[k]) & (t <= t[k] + BOUNCE_WINDOW))
        after = after[after + 2 < len(t)]
        if vz_in > -0.3 or not len(after):
            continue
        vz_out = (position[after + 2, 2] - position[after, 2]) / (t[after + 2] - t[after])  # 2-frame slopes
        out.append(float(max(np.max(vz_out), 0.0) / -vz_in))
    return out
