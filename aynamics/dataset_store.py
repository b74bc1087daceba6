"""On-disk storage of a generated data set: record schema, chunks, shards, the run manifest, final assembly.

A run of `num` scenes is cut into chunks of `chunk_size` consecutive indices. Shard k of n makes the chunks c with
c % n == k and writes each one atomically (a temporary folder renamed to `chunks/NNNNNN`), so a killed run started
again skips finished chunks and redoes the partial one; while it writes it holds its shard's lock, and a second
process making any of its chunks is refused (`claim_shard`). `generate.json` (the manifest) records the settings that
decide the records; a folder refuses chunks of a different run. `assemble` concatenates every chunk in index order
and splits the rows by their `split` column into the DatasetDict that `datasets.load_from_disk` opens.

    write_manifest(out, {"format": 1, "num": 8, "seed": 0, "config": {...}})
    write_chunk(out, 0, records)          # records: dicts of `features()`
    assemble(out)                         # or assemble(out, [shard_dir_0, shard_dir_1])
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
from pathlib import Path

FORMAT_VERSION = 1
SPLITS = ("train", "validation", "test")


def split_of(seed: int, index: int, shares: tuple[float, float, float] = (0.8, 0.1, 0.1)) -> str:
    """The split of scene `index`: a hash of (seed, index), so independent of sharding and order."""
    digest = hashlib.sha256(f"{seed}:{index}".encode()).digest()
    u = int.from_bytes(digest[:8], "big") / 2**64
    return SPLITS[0] if u < shares[0] else SPLITS[1] if u < shares[0] + shares[1] else SPLITS[2]


MANIFEST = "generate.json"


def _manifest_config(path: str | Path) -> dict | None:
    """The `config` of a generated data set's manifest (for a split folder given on its own, the manifest of the
    data set holding it), or None for a data set made otherwise (no readable manifest)."""
    for folder in (Path(path), Path(path).parent):
        try:
            config = json.loads((folder / MANIFEST).read_text())["config"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        return config if isinstance(config, dict) else {}
    return None


def _whole(value) -> int | None:
    return int(value) if isinstance(value, int | float) and not isinstance(value, bool) and value >= 1 else None


def dataset_fps(path: str | Path) -> int | None:
    """The frame rate of a generated data set's videos (its manifest's `config.fps`; for a split folder given on its
    own, the manifest of the data set holding it), or None for a data set made otherwise."""
    return _whole((_manifest_config(path) or {}).get("fps"))


def stale_physics(path: str | Path) -> str | None:
    """Why a generated data set's records were simulated by other physics than this code's (its manifest's
    `config.physics`, absent before version 2), or None (current, or no manifest: made otherwise)."""
    from aynamics.simulate import PHYSICS_VERSION

    if (made := _other_version(path, "physics", PHYSICS_VERSION)) is None:
        return None
    return (
        f"data set {str(path)!r} was simulated with physics version {made}, this code simulates version "
        f"{PHYSICS_VERSION}: scenes re-simulated here (true scenes, candidates) can move apart from its videos "
        "and stored states; generate it again into a new folder"
    )


def stale_labels(path: str | Path) -> str | None:
    """Why a generated data set's records were labelled (rest times, reasoning text, the scenes kept) by other code
    than this (its manifest's `config.labels`, absent before version 2), or None (current, or no manifest)."""
    from aynamics.generate_config import LABELS_VERSION

    if (made := _other_version(path, "labels", LABELS_VERSION)) is None:
        return None
    return f"data set {str(path)!r} was labelled by labels version {made}, this code writes version {LABELS_VERSION}"


def _other_version(path: str | Path, key: str, current: int) -> int | None:
    """A generated data set's manifest `config[key]` version (1 when absent: written from version 2 on) when it is
    not `current`; None when it is, or when there is no manifest (a data set made otherwise)."""
    config = _manifest_config(path)
    made = None if config is None else config.get(key, 1)
    return None if made == current else made


def dataset_substeps(path: str | Path) -> int | None:
    """The physics steps per frame a generated data set's videos were simulated with (its manifest's
    `config.substeps`, written by every generate), or None for a data set made otherwise."""
    return _whole((_manifest_config(path) or {}).get("substeps"))


def features():
    """The `datasets.Features` of a record (see `aynamics.generate` for what each column holds)."""
    from datasets import Features, Image, List, Value

    f32, f64 = Value("float32"), Value("float64")
    vec = List(List(List(f32)))
    return Features(
        {
            "index": Value("int64"),
            "seed": Value("int64"),
            "attempt": Value("int32"),
            "split": Value("string"),
            "scene_yaml": Value("string"),
            "reasoning": Value("string"),
            "target_answer": Value("string"),
            "target_think": Value("string"),
            "rgb": List(Image()),
            "flow": List(Image()),
            "flow_max": f32,
            "segmentation": List(Image()),
            "frame_indices": List(Value("int32")),
            "frame_times": List(f32),
            "states": {
                "names": List(Value("string")),
                "t": List(f32),
                "position": vec,
                "orientation": vec,
                "linear_velocity": vec,
                "angular_velocity": vec,
                "in_view": List(List(Value("bool"))),
                "visible": List(List(Value("bool"))),
                "rest_time": List(f64),
            },
            "contacts": List({"a": Value("string"), "b": Value("string"), "start": f32, "end": f32}),
            "camera": {
                "fovy": f64,
                "orientation": f64,
                "position": List(f64),
                "width": Value("int32"),
                "height": Value("int32"),
                "K": List(List(f64)),
                "R": List(List(f64)),
                "t": List(f64),
            },
            "num_objects": Value("int32"),
            "shapes": List(Value("string")),
            "has_collision": Value("bool"),
        }
    )


# --------------------------------------------------------------------------------------------
# Chunks and shards
# --------------------------------------------------------------------------------------------
def chunk_ranges(num: int, chunk_size: int) -> list[range]:
    """Index ranges of the chunks of a run of `num` scenes."""
    return [range(a, min(a + chunk_size, num)) for a in range(0, num, chunk_size)]


def shard_chunks(num: int, chunk_size: int, shard: int = 0, num_shards: int = 1) -> list[int]:
    """Chunk ids made by shard `shard` of `num_shards` (c % num_shards == shard): disjoint, covering all."""
    if num_shards < 1 or not 0 <= shard < num_shards:
        raise ValueError(
            f"shard = {shard}, num_shards = {num_shards}: need num_shards >= 1 and 0 <= shard < num_shards"
        )
    return [c for c in range(len(chunk_ranges(num, chunk_size))) if c % num_shards == shard]


def chunk_dir(out: Path, c: int) -> Path:
    """Folder of chunk `c` of the run in `out` (it exists only once the chunk is complete)."""
    return out / "chunks" / f"{c:06d}"


def remove_partial_chunks(out: Path, chunks: list[int]) -> None:
    """Delete the temporary folders that a killed run left while writing these chunks (call it holding their
    shard's lock, `claim_shard`: then no live process is writing them)."""
    for c in chunks:
        for tmp in (out / "chunks").glob(f".tmp-{c:06d}-*"):
            shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def quiet_datasets():
    """Hide `datasets`' own "Saving the dataset" bars under ours."""
    import datasets

    was = datasets.is_progress_bar_enabled()
    datasets.disable_progress_bars()
    try:
        yield
    finally:
        if was:
            datasets.enable_progress_bars()


def write_chunk(out: Path, c: int, records: list[dict]) -> None:
    """Write chunk `c` atomically: a temporary folder renamed to `chunks/NNNNNN` once complete."""
    from datasets import Dataset

    final = chunk_dir(out, c)
    tmp = final.parent / f".tmp-{c:06d}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    with quiet_datasets():
        Dataset.from_list(records, features=features()).save_to_disk(str(tmp))
    os.replace(tmp, final)  # atomic: a chunk folder exists only when complete


# --------------------------------------------------------------------------------------------
# The run manifest
# --------------------------------------------------------------------------------------------
def first_difference(a, b, prefix: str = "") -> str | None:
    """The first differing key of two nested mappings, as 'key.sub = old (this run: new)'; None when equal."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            d = first_difference(a.get(k), b.get(k), f"{prefix}.{k}" if prefix else k)
            if d:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return next((d for i, (x, y) in enumerate(zip(a, b)) if (d := first_difference(x, y, f"{prefix}[{i}]"))), None)
    return None if a == b else f"{prefix} = {a!r} (this run: {b!r})"


INFO_KEYS = ("scene_files",)  # manifest entries for the reader only: the paths of --scenes as typed on each machine


def _compared(manifest: dict) -> dict:
    """The entries of a manifest that decide the records (two runs agree on these)."""
    return {k: v for k, v in manifest.items() if k not in INFO_KEYS}


def write_manifest(out: Path, manifest: dict) -> None:
    """Write `generate.json`, or check that an existing one describes the same run (else nothing is mixed).

    Args:
        out: the run's folder (created if missing).
        manifest: {"format", "num", "seed", "config": the JSON of the settings that decide the records}.

    Raises:
        ValueError: the folder holds a run with other settings (the first difference is named).
    """
    manifest = json.loads(json.dumps(manifest))  # tuples -> lists: compare as stored
    path = out / MANIFEST
    if path.exists():
        old = json.loads(path.read_text())
        for key in ("format", "num", "seed"):
            if old.get(key) != manifest[key]:
                raise ValueError(
                    f"--out {str(out)!r} holds a run with {key} = {old.get(key)!r}, this run has {manifest[key]!r}; "
                    "use another folder or the same settings to resume"
                )
        diff = first_difference(old.get("config", {}), manifest["config"])
        if diff:
            raise ValueError(
                f"--out {str(out)!r} holds a run with config {diff}; use another folder or the same config"
            )
        return
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{MANIFEST}.{os.getpid()}"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, path)


_SHARD_LOCK = re.compile(r"\.shard-(\d+)-of-(\d+)\.lock")


@contextlib.contextmanager
def claim_shard(out: Path, manifest: dict, shard: int = 0, num_shards: int = 1):
    """Write or check the manifest (`write_manifest`) and hold shard `shard` of `num_shards` of the run in `out`
    for the block: no other live process makes any of its chunks meanwhile.

    Shards of one run may write into one folder at once, each holding the lock of its own (`.shard-K-of-N.lock`).
    Two processes making the same chunks raced: the second redid the first's chunks and stopped with OSError
    ENOTEMPTY renaming its copy onto one the first had finished (its copy left behind), or deleted the first's
    half-written chunk as a leftover. So a second writer of any of these chunks (the same shard, or a shard of
    another count sharing a chunk) is refused here, before anything is rendered. The manifest, the look at the
    other shards' locks and the taking of this one happen under `.generate.lock`, so that two writers starting
    together cannot both pass, nor write two manifests. While it is held, the temporary folders of this shard's
    chunks are leftovers of dead processes (`remove_partial_chunks`).

    Raises:
        ValueError: the folder holds another run (`write_manifest`), or a live process holds the lock of a shard
            that shares a chunk with this one (named, with the folder).
    """
    num, chunk_size = manifest["num"], manifest["config"]["chunk_size"]
    mine = set(shard_chunks(num, chunk_size, shard, num_shards))
    out.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as held:
        with exclusive(out / ".generate.lock"):
            write_manifest(out, manifest)
            for lock in sorted(out.iterdir()):
                m = _SHARD_LOCK.fullmatch(lock.name)
                k, n = (int(m[1]), int(m[2])) if m else (shard, num_shards)
                if (k, n) == (shard, num_shards) or not 0 <= k < n:
                    continue  # not a shard's lock, or this shard's own (taken below)
                if not mine & set(shard_chunks(num, chunk_size, k, n)):
                    continue
                try:
                    with exclusive(lock, wait=False):
                        pass  # its writer is gone
                except BlockingIOError:
                    raise ValueError(
                        f"--out {str(out)!r}: another process is writing shard {k}/{n} of this run into it (it holds "
                        f"{lock.name}), which makes chunks that shard {shard}/{num_shards} makes too: wait for it to "
                        "finish, or give shards of one count"
                    ) from None
            lock = out / f".shard-{shard}-of-{num_shards}.lock"
            try:
                held.enter_context(exclusive(lock, wait=False))
            except BlockingIOError:
                raise ValueError(
                    f"--out {str(out)!r}: another process is writing shard {shard}/{num_shards} of this run into "
                    f"it (it holds {lock.name}): wait for it to finish, or give another --out"
                ) from None
        yield


# --------------------------------------------------------------------------------------------
# Assembly
# --------------------------------------------------------------------------------------------
def assemble(out_dir: str | os.PathLike, sources: list[str | os.PathLike] | None = None) -> Path:
    """Concatenate every chunk (of `out_dir`, or of the `sources` folders of shard runs) into the DatasetDict.

    Raises:
        ValueError: chunks are missing, or the sources describe different runs.
    """
    from datasets import DatasetDict, concatenate_datasets, load_from_disk

    out = Path(out_dir)
    folders = [Path(s) for s in sources] if sources else [out]
    manifests = []
    for folder in folders:
        path = folder / MANIFEST
        if not path.is_file():
            raise ValueError(f"{str(folder)!r}: no {MANIFEST}: not a `aynamics generate` output folder")
        manifests.append(json.loads(path.read_text()))
    for folder, m in zip(folders[1:], manifests[1:], strict=True):
        diff = first_difference(_compared(manifests[0]), _compared(m))
        if diff:
            raise ValueError(f"{str(folder)!r} belongs to a different run than {str(folders[0])!r}: {diff}")
    manifest = manifests[0]
    num, chunk_size = manifest["num"], manifest["config"]["chunk_size"]
    parts, missing = [], []
    for c in range(len(chunk_ranges(num, chunk_size))):
        found = [chunk_dir(f, c) for f in folders if chunk_dir(f, c).is_dir()]
        if not found:
            missing.append(c)
        else:
            with quiet_datasets():
                parts.append(load_from_disk(str(found[0])))
    if missing:
        raise ValueError(f"cannot assemble {str(out)!r}: chunks {missing[:10]} of {len(parts) + len(missing)} missing")
    full = concatenate_datasets(parts)
    split_col = full["split"]
    dd = DatasetDict({s: full.select([i for i, v in enumerate(split_col) if v == s]) for s in SPLITS})
    if sources:
        write_manifest(out, manifest)
    tmp = out / f".assemble-{os.getpid()}"
    with contextlib.ExitStack() as held:
        with exclusive(out / ".assemble.lock"):
            remove_dead_assemblies(out)
            tmp.mkdir()
            held.enter_context(exclusive(tmp / ".lock", wait=False))  # ours while we live (`remove_dead_assemblies`)
        try:
            with quiet_datasets():
                dd.save_to_disk(str(tmp), num_shards={s: 1 for s in SPLITS if len(dd[s]) == 0})  # empty splits: 1 file
        except BaseException:  # a full disk or an interrupt: no hidden copy of the data set left holding the space
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        with exclusive(out / ".assemble.lock"):  # shards that finish together move their (equal) splits in turn
            (out / "dataset_dict.json").unlink(missing_ok=True)  # the folder is not a data set while splits move
            for s in SPLITS:
                shutil.rmtree(out / s, ignore_errors=True)
                os.replace(tmp / s, out / s)
            os.replace(tmp / "dataset_dict.json", out / "dataset_dict.json")
        shutil.rmtree(tmp, ignore_errors=True)
    return out


_ASSEMBLY = re.compile(r"\.assemble-\d+")


def remove_dead_assemblies(out: Path) -> None:
    """Delete the `.assemble-PID` folders in `out` that no live process is writing (call it holding
    `.assemble.lock`).

    Each is a hidden copy of the whole data set: a run killed (SIGKILL, the OOM killer) while saving it left it
    holding the space for good, as no later run looked at another process's. Shards finishing together assemble
    at once, each into its own, so a folder is removed only when the lock its writer holds on its `.lock` (taken
    under `.assemble.lock`, with the folder made) can be had: its writer is gone. Only folders of that name.
    """
    for folder in sorted(out.iterdir()):
        if not _ASSEMBLY.fullmatch(folder.name) or folder.is_symlink() or not folder.is_dir():
            continue
        try:
            with exclusive(folder / ".lock", wait=False):
                pass
        except BlockingIOError:
            continue  # another shard is assembling into it
        except FileNotFoundError:  # its writer, done, deleted it meanwhile (after giving `.assemble.lock` back)
            continue
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def exclusive(path: Path, *, wait: bool = True):
    """Hold an exclusive lock on `path` (POSIX `flock`; processes and threads alike) for the block; where `fcntl`
    is missing (Windows) the block runs unlocked.

    Raises:
        BlockingIOError: with `wait=False`, another holds the lock.
    """
    try:
        import fcntl
    except ImportError:
        yield
        return
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
