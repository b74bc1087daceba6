"""Work kept as it is done, so that a long command goes on after an interruption where it stopped.

Sampling preferences (`aynamics preferences`) and scoring a real model (`aynamics evaluate`, with CMA-ES refinement
a minute a scene) take hours; an interruption lost all of it. Both keep each finished batch in a folder beside
their output, `OUT.partial` (`partial_folder`), and read the kept batches back when the same command runs again:

    kept = KeptBatches(partial_folder(out), settings, run="an evaluation", verb="score", fields={"responses": keys})
    with kept.opened():  # made, or checked to hold these settings' batches; locked: a second writer is refused
        done = kept.done("responses")
        for k, batch in enumerate(batches):
            if k < len(done):
                ...  # checked against `batch` and used, not made again
                continue
            ...
            kept.save("responses", k, {...})  # atomically: a half-written file is never read back
        write(out)
        kept.remove()  # under the lock: no second writer starts on the batches meanwhile

`settings.json` holds everything the batches depend on: a run with other settings is refused, naming what differs
(a run that kept no batch binds nothing: a mistyped option is not held against the next run). Each batch records
what it was made from (keys, digests) for its caller to check.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import re
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch


def partial_folder(out: str | Path) -> Path:
    """Where a command writing `out` keeps its batches meanwhile: `OUT.partial`, beside OUT."""
    out = Path(out).resolve()
    return out.with_name(out.name + ".partial")


def file_digest(path: str | Path) -> str | None:
    """A short hash of a file's bytes (None for no file): a folder names an adapter, not what it holds (one trained
    again into the same folder writes other responses)."""
    path = Path(path)
    if not path.is_file():
        return None
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def content_digest(*values: Any) -> str:
    """A short hash of what `values` hold: arrays and tensors by dtype, shape and bytes, images by mode, size and
    pixels, dataclasses, mappings and sequences item by item, numbers and strings by type and value. A key names a
    record (an index, a folder's name), not what it holds: a data set generated again holds other videos under the
    same keys, and a kept batch made from them must not be read back as this run's.

    Raises:
        TypeError: a value of another kind, naming its type.
    """
    h = hashlib.sha256()
    for v in values:
        _feed(h, v)
    return h.hexdigest()[:16]


def _feed(h, v: Any) -> None:
    from PIL import Image

    if isinstance(v, torch.Tensor):
        h.update(f"tensor {v.dtype} {tuple(v.shape)};".encode())
        h.update(v.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(v, np.ndarray):
        h.update(f"array {v.dtype} {v.shape};".encode())
        h.update(np.ascontiguousarray(v).tobytes())
    elif isinstance(v, Image.Image):
        h.update(f"image {v.mode} {v.size};".encode())
        h.update(v.tobytes())
    elif dataclasses.is_dataclass(v) and not isinstance(v, type):
        h.update(f"{type(v).__name__}({len(dataclasses.fields(v))});".encode())
        for f in dataclasses.fields(v):
            h.update(f"{f.name}=".encode())
            _feed(h, getattr(v, f.name))
    elif isinstance(v, Mapping):
        h.update(f"mapping {len(v)};".encode())
        for key in sorted(v, key=str):
            _feed(h, key)
            _feed(h, v[key])
    elif isinstance(v, (list, tuple)):
        h.update(f"sequence {len(v)};".encode())
        for item in v:
            _feed(h, item)
    elif v is None or isinstance(v, (str, bytes, bool, int, float, np.generic)):
        h.update(f"{type(v).__name__} {v!r};".encode())
    else:
        raise TypeError(f"content_digest: a {type(v).__name__} cannot be hashed by its contents")


def differences(there: dict, now: dict, keys: list[str] | None = None) -> list[str]:
    """ "k X there, Y now" for each of `keys` (default: `now`'s) whose value differs: what a refusal of kept work
    made with other settings names."""
    return [
        f"{k} {there.get(k)!r} there, {now.get(k)!r} now"
        for k in (now if keys is None else keys)
        if there.get(k) != now.get(k)
    ]


def _index(path: Path) -> int:
    """The number of a batch file `STREAM-NNNNNN.pt`."""
    return int(path.stem.rsplit("-", 1)[1])


class KeptBatches:
    """A folder of numbered batches (`STREAM-NNNNNN.pt`, one series per stream name) and the settings they were
    made with.

    Args:
        folder: The folder (`partial_folder(out)`).
        settings: What the batches depend on, JSON-able (compared as `settings.json` reads it back).
        run: What made the folder, for messages ("a preference run").
        verb: What the command does to make a batch ("sample"), for messages.
        fields: Keys every batch of a stream holds (stream -> keys): a file without them is from another version.
        redone_on: Settings that only some streams depend on (setting -> those streams). Kept batches made with
            other values of these alone are not refused: those streams are forgotten and done again (`redone` says
            which), the rest gone on from. Any other difference refuses the folder.
    """

    SETTINGS = "settings.json"
    _SETTINGS_TMP = "settings.tmp"  # settings.json as it is written

    def __init__(
        self,
        folder: str | Path,
        settings: dict,
        *,
        run: str,
        verb: str,
        fields: dict[str, frozenset[str]],
        redone_on: dict[str, tuple[str, ...]] | None = None,
    ) -> None:
        self.folder = Path(folder)
        self.settings = json.loads(json.dumps(settings))  # as settings.json reads back (tuples as lists)
        self.run, self.verb, self.fields = run, verb, fields
        self.redone_on = redone_on or {}
        self.redone: tuple[list[str], list[str]] | None = None  # `opened` dropped: (the differences, the streams)

    @contextlib.contextmanager
    def opened(self) -> Iterator[KeptBatches]:
        """Make the folder (or check the one there was made with these settings) and hold its lock.

        A folder that holds no batch when the block ends (an option refused, a failure before the first batch) is
        deleted.

        Raises:
            ValueError: the folder is a link or holds other files, other settings, or another process holds its lock.
        """
        from aynamics.dataset_store import exclusive

        if self.folder.is_symlink():  # removing a link at the end leaves its batches to be gone on from next time
            raise ValueError(
                f"{str(self.folder)!r} is a link (to {os.readlink(self.folder)!r}): the kept batches need a folder of "
                "their own; remove the link"
            )
        if self.folder.exists() and not (self.folder / self.SETTINGS).is_file():
            # (a run killed while writing its first settings.json left settings.tmp: no batch, nothing to lose)
            there = self.folder.iterdir() if self.folder.is_dir() else ()
            other = [p.name for p in there if p.name not in (".lock", self._SETTINGS_TMP)]
            if other or not self.folder.is_dir():
                raise ValueError(
                    f"{str(self.folder)!r} exists and is not the kept batches of {self.run} (no {self.SETTINGS}): "
                    "move it away, or write --out elsewhere"
                )
        self.folder.mkdir(parents=True, exist_ok=True)
        with contextlib.ExitStack() as stack:
            try:
                stack.enter_context(exclusive(self.folder / ".lock", wait=False))
            except BlockingIOError:
                raise ValueError(
                    f"another process is {self.verb.removesuffix('e')}ing into {str(self.folder)!r} (it holds its "
                    "lock): wait for it, or write --out elsewhere"
                ) from None
            self._check_theirs()
            self._check_settings()
            try:
                yield self
            finally:  # a run that kept no batch (refused, failed or interrupted before one) leaves no folder behind
                if self.folder.is_dir() and not len(self):
                    self.remove()

    def _check_theirs(self) -> None:
        """Refuse a folder holding files this run does not keep: another command's batches kept under the same OUT
        (an interrupted `aynamics preferences --out OUT`, then `aynamics evaluate --out OUT`) counted as no batch,
        so its settings were overwritten and the folder deleted at the end, with that command's hours of work."""
        streams = "|".join(re.escape(s) for s in self.fields)
        ours = re.compile(rf"(?:{streams})-\d{{6}}\.(?:pt|tmp)")  # (.tmp: a save a crash cut short)
        other = sorted(
            p.name
            for p in self.folder.iterdir()
            if p.name not in (self.SETTINGS, self._SETTINGS_TMP)
            and not p.name.startswith(".")
            and not ours.fullmatch(p.name)
        )
        if other:
            more = f" and {len(other) - 1} more files" if len(other) > 1 else ""
            raise ValueError(
                f"{str(self.folder)!r} holds {other[0]!r}{more}, which {self.run} does not keep (another command's "
                "work kept for the same OUT?): finish that command, or move the folder away, or write --out elsewhere"
            )

    def _check_settings(self) -> None:
        path = self.folder / self.SETTINGS
        # no batch kept, nothing to go on from: a run that failed before its first one (a mistyped option, a first
        # batch too large for the GPU) does not bind the next to its settings
        if not path.is_file() or not len(self):
            self._write_settings()
            return
        try:
            kept = json.loads(path.read_text())
        except ValueError as e:
            raise ValueError(
                f"{str(path)!r} cannot be read ({e}): delete {str(self.folder)!r} to {self.verb} afresh"
            ) from None
        if kept != self.settings:
            keys = sorted(set(kept) | set(self.settings)) if isinstance(kept, dict) else []
            changed = [k for k in keys if kept.get(k) != self.settings.get(k)]
            diff = differences(kept, self.settings, changed) if changed else []
            if changed and all(k in self.redone_on for k in changed):
                # settings only some streams depend on (a refinement's budget): those streams are done again, the
                # rest (hours of responses) kept; any other difference refuses all, as a mistyped option may
                self.redone = diff, self._drop_for(changed)
                self._write_settings()
                return
            raise ValueError(
                f"{str(self.folder)!r} holds the batches of an interrupted run with other settings "
                f"({'; '.join(diff) or repr(kept)}): run with its settings to go on from it, or delete it to "
                f"{self.verb} afresh"
            )

    def _write_settings(self) -> None:
        tmp = self.folder / self._SETTINGS_TMP
        tmp.write_text(json.dumps(self.settings, indent=1, sort_keys=True) + "\n")
        os.replace(tmp, self.folder / self.SETTINGS)

    def _drop_for(self, changed: list[str]) -> list[str]:
        """Forget every batch of the streams that the settings `changed` are redone on; their names."""
        streams = sorted({s for k in changed for s in self.redone_on[k]})
        for stream in streams:
            self.drop(stream, 0)
        return streams

    def done(self, stream: str) -> list[dict]:
        """The kept batches of `stream` in order (its first `count(stream)` batches).

        Raises:
            ValueError: a batch file that cannot be read, or a gap in their numbers, naming the file.
        """
        batches = []
        for k, path in enumerate(self._files(stream)):
            if _index(path) != k:
                raise ValueError(
                    f"{str(path)!r}: batch {k} is missing before it; delete it and later ones to {self.verb} them again"
                )
            try:
                batch = torch.load(path, weights_only=True)
            except Exception as e:  # torch names no file; bytes of anything else raise KeyError, ValueError, ...
                raise ValueError(
                    f"{str(path)!r} cannot be read ({type(e).__name__}: {e}): delete it to {self.verb} it again"
                ) from None
            need = self.fields[stream]
            if not isinstance(batch, dict) or not need <= batch.keys():
                held = sorted(batch) if isinstance(batch, dict) else type(batch).__name__
                raise ValueError(
                    f"{str(path)!r} is not a batch this version keeps (it holds {held}, not {sorted(need)}): "
                    f"delete it to {self.verb} it again"
                )
            batches.append(batch)
        return batches

    def __len__(self) -> int:
        """Batches kept, of every stream (not read)."""
        return sum(self.count(s) for s in self.fields)

    def count(self, stream: str) -> int:
        """Batches of `stream` kept (not read)."""
        return len(self._files(stream))

    def _files(self, stream: str) -> list[Path]:
        pattern = re.compile(rf"{re.escape(stream)}-(\d{{6}})\.pt")
        return sorted(p for p in self.folder.glob(f"{stream}-*.pt") if pattern.fullmatch(p.name))

    def save(self, stream: str, index: int, batch: dict) -> Path:
        """Keep batch `index` of `stream` (atomically: a half-written file is never read back)."""
        path = self.folder / f"{stream}-{index:06d}.pt"
        tmp = path.with_suffix(".tmp")
        torch.save(batch, tmp)
        os.replace(tmp, path)
        return path

    def drop(self, stream: str, start: int) -> None:
        """Forget the kept batches of `stream` numbered `start` and on (made from what has changed since)."""
        for path in self._files(stream):
            if _index(path) >= start:
                path.unlink()

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
