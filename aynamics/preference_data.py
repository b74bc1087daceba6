"""Offline PRO data: sample N responses per unlabeled video, score them with the simulator, store preference pairs.

    rows, summary = build_preferences(module, videos, num_samples=32, pairs=3, temperature=0.1)
    write_preferences(rows, summary, "data/prefs")
    ds = load_preferences("data/prefs")

The paper draws three pairs per case from 32 samples. Here the N candidates of a video are ordered by reward
(best first, sampling order among ties) and pair k is (k-th best, k-th worst) for k = 0, 1, ...: the best against
the worst, then the runners-up, so pairs share no candidate and each has the widest remaining reward gap.
A pair is kept only when the chosen candidate scores strictly higher; a video whose candidates all tie (e.g.
all invalid) gives no pair and is counted in the summary.

Stored as a Hugging Face data set on disk (`datasets.load_from_disk(OUT)`), one row per pair:
    key str (the video), frames list[Image] (what the model saw), completions [chosen, rejected] str,
    completion_ids [2][L] int32 (the sampled tokens, end-of-turn id included), rewards [2] float32,
    reasons [2] str or null (why a candidate was invalid), case_rewards [N] float32 (all candidates' rewards).
Plus `summary.json`: counts, mean/best reward, share invalid, the sampling settings.

Sampling takes hours on real models, so `build_preferences` can keep each batch in a folder as soon as it is scored
(`SamplingProgress`): run again after an interruption, it goes on from the last kept batch, giving the rows an
uninterrupted run gives. The command line, `aynamics preferences`, is `aynamics.preference_cli`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from aynamics import lm, rng
from aynamics import reward as rw
from aynamics.kept_batches import KeptBatches, content_digest, differences
from aynamics.scorer import Score
from aynamics.unlabeled import UnlabeledVideo

COLUMNS = ("key", "frames", "completions", "completion_ids", "rewards", "reasons", "case_rewards")


def select_pairs(rewards: Sequence[float], pairs: int) -> list[tuple[int, int]]:
    """(chosen, rejected) index pairs: k-th best against k-th worst, k < `pairs`, strict reward gap only.

    Example: rewards [0.2, 0.9, 0.0, 0.5], pairs 3 -> order by reward 1, 3, 0, 2 -> [(1, 2), (3, 0)].
    """
    if pairs < 1:
        raise ValueError(f"pairs = {pairs}: must be >= 1")
    order = sorted(range(len(rewards)), key=lambda i: -rewards[i])  # stable: sampling order among ties
    out = []
    for k in range(min(pairs, len(order) // 2)):
        hi, lo = order[k], order[len(order) - 1 - k]
        if rewards[hi] > rewards[lo]:
            out.append((hi, lo))
    return out


def features():
    """The `datasets.Features` of a preference row."""
    from datasets import Features, Image, List, Value

    return Features(
        {
            "key": Value("string"),
            "frames": List(Image()),
            "completions": List(Value("string")),
            "completion_ids": List(List(Value("int32"))),
            "rewards": List(Value("float32")),
            "reasons": List(Value("string")),
            "case_rewards": List(Value("float32")),
        }
    )


def build_preferences(
    module: Any,
    videos: Sequence[UnlabeledVideo],
    *,
    num_samples: int = 32,
    pairs: int = 3,
    temperature: float = 0.1,
    batch_size: int = 1,
    progress: SamplingProgress | None = None,
) -> tuple[list[dict], dict]:
    """Sample, score and pair: the rows of the preference data set and a summary.

    Args:
        module: A `pro.ProModule` (its model, processor, prompt, top_p, max_new_tokens and reward settings).
        videos: Unlabeled videos.
        num_samples: N candidates per video (>= 2).
        pairs: Pairs kept per video at most.
        temperature: Sampling temperature (> 0).
        batch_size: Videos sampled together.
        progress: Where each batch is kept once scored. Batches it already holds are read back, not sampled
            again, and the random generators continue from their states after the last one, so the rows are
            those of an uninterrupted run.

    Raises:
        ValueError: a bad argument, or a kept batch of other videos or another shape than these settings give.
    """
    if num_samples < 2 or not (0 < temperature < math.inf) or batch_size < 1:  # nan fails the comparison too
        raise ValueError(
            f"num_samples = {num_samples}, temperature = {temperature}, batch_size = {batch_size}: "
            "need num_samples >= 2, a finite temperature > 0, batch_size >= 1"
        )
    if module.processor is None:  # sampling loads it; with every batch kept, nothing is sampled: the summary needs it
        module.ensure_processor()
    starts = range(0, len(videos), batch_size)
    batches = progress.done(progress.STREAM) if progress is not None else []
    if len(batches) > len(starts):
        raise ValueError(f"{progress.folder} holds {len(batches)} batches, but these videos make {len(starts)}")
    # the images of the videos with rows: each video is read once (a generated data set decodes its images at every
    # read) and its rows share them, as before batches were kept
    frames: dict[int, tuple] = {}

    def keep_frames(start: int, chunk: Sequence[UnlabeledVideo], batch: dict) -> None:
        paired = {row["video"] for row in batch["rows"]}
        frames.update({start + b: v.frames for b, v in enumerate(chunk) if start + b in paired})

    # what shapes a batch's rows: a progress made for other settings (`SamplingProgress.settings` is the caller's)
    sampling = {"num_samples": num_samples, "pairs": pairs, "temperature": temperature, "batch_size": batch_size}

    def chunk_at(start: int) -> list[UnlabeledVideo]:
        return [videos[i] for i in range(start, min(start + batch_size, len(videos)))]

    for start, batch in zip(starts, batches, strict=False):
        chunk = chunk_at(start)
        why = _kept_mismatch(batch, chunk, sampling)
        if why is not None:
            raise ValueError(f"{progress.folder}: its batch at video {start} {why}")
        keep_frames(start, chunk, batch)
    if batches:  # the generators as they were after the last kept batch: what follows is what would have
        rng.restore({"per_rank": [batches[-1]["rng"]]}, 0)
    for start in starts[len(batches) :]:
        chunk = chunk_at(start)
        _, ids, scores, rewards = module.sample_and_score(chunk, num_samples, temperature)
        texts = module.processor.tokenizer.batch_decode([c for row in ids for c in row], skip_special_tokens=True)
        batch = {
            "start": start,
            "keys": [v.key for v in chunk],
            "digests": [video_digest(v) for v in chunk],
            "sampling": sampling,
            "rows": _pair_rows(start, [v.key for v in chunk], ids, texts, rewards, scores, pairs),
            "rewards": rewards.detach().cpu().float(),
            "scores": [[dataclasses.asdict(s) for s in row] for row in scores],
            "rng": rng.local_state(),
        }
        if progress is not None:
            progress.save(progress.STREAM, len(batches), batch)
        batches.append(batch)
        keep_frames(start, chunk, batch)
    rows = [
        {**{k: v for k, v in row.items() if k != "video"}, "frames": list(frames[row["video"]])}
        for batch in batches
        for row in batch["rows"]
    ]
    scores = [[Score(**s) for s in row] for batch in batches for row in batch["scores"]]
    stats = rw.RewardStats.of(torch.cat([b["rewards"] for b in batches]), scores) if batches else None
    cases_with_pairs = len({row["key"] for row in rows})
    summary = {
        "videos": len(videos),
        "pairs": len(rows),
        "videos_without_pairs": len(videos) - cases_with_pairs,
        "num_samples": num_samples,
        "temperature": temperature,
        "pairs_per_video": pairs,
        **(stats.to_metrics("reward/") if stats else {}),
        # what the stored frames and token ids mean: offline training checks them against its own
        "prompt": {k: getattr(module.prompt, k) for k in lm.PROMPT_KEYS},
        # the videos' clock the frames were shown on (second_per_grid_ts): offline training shows them alike
        "clock": {"fps": module.prompt.fps, "clip_frames": list(module.prompt.clip_frames)},
        "tokenizer": lm.tokenizer_fingerprint(module.processor.tokenizer),
    }
    return rows, summary


def _kept_mismatch(batch: dict, chunk: Sequence[UnlabeledVideo], sampling: dict) -> str | None:
    """Why a kept batch is not what these settings would sample from these videos now, or None."""
    kept = batch["sampling"]
    differ = differences(kept, sampling)
    if differ:
        return (
            f"was sampled with other settings ({'; '.join(differ)}): run with its settings to go on from it, or "
            "delete it to sample afresh"
        )
    keys = [v.key for v in chunk]
    if batch["keys"] != keys or batch["rewards"].shape[0] != len(keys):
        return (
            f"holds videos {batch['keys']}, but these settings give videos {keys} there: the videos changed since "
            "it was written; delete it to sample afresh"
        )
    changed = [v.key for v, d in zip(chunk, batch["digests"], strict=True) if video_digest(v) != d]
    if changed:  # the same keys (a record's index, a folder's name) in a data set made again
        return (
            f"was sampled from other images or masks of the videos {changed} than they hold now: the videos changed "
            "since it was written; delete it to sample afresh"
        )
    return None


def video_digest(video: UnlabeledVideo) -> str:
    """A short hash of what a video's candidates depend on: the images the model sees and the observation they are
    scored against (masks, flow). A key names a video (a record's index, a folder's name), not what it holds: a
    data set generated again holds other videos under the same keys."""
    obs = video.observation
    return content_digest(list(video.frames), *((obs.segmentation, obs.flow) if obs is not None else ()))


def _pair_rows(
    start: int,
    keys: Sequence[str],
    ids: Sequence[Sequence[Sequence[int]]],
    texts: Sequence[str],
    rewards: torch.Tensor,
    scores: Sequence[Sequence[Score]],
    pairs: int,
) -> list[dict]:
    """The preference rows of one batch (videos `start`, `start + 1`, ...), their frames left out: each row says
    which video it is of (`video`, its position) and the frames are taken from it when the set is written."""
    n = rewards.shape[1]
    rows = []
    for b, key in enumerate(keys):
        r = rewards[b].tolist()
        for hi, lo in select_pairs(r, pairs):
            rows.append(
                {
                    "key": key,
                    "video": start + b,
                    "completions": [texts[b * n + hi], texts[b * n + lo]],
                    "completion_ids": [list(ids[b][hi]), list(ids[b][lo])],
                    "rewards": [r[hi], r[lo]],
                    "reasons": [scores[b][hi].reason, scores[b][lo].reason],
                    "case_rewards": r,
                }
            )
    return rows


class SamplingProgress(KeptBatches):
    """The batches `build_preferences` has scored, kept in a folder as each one is done, so that an interrupted
    run goes on where it stopped (at most one batch is sampled again) and gives the rows an uninterrupted run gives.

    The folder holds `settings.json` (everything the samples depend on: a run with other settings is refused,
    naming what differs) and one `batch-NNNNNN.pt` per batch (stream "batch"), written atomically: its videos' keys
    and `video_digest`s, its sampling settings, its rows without frames (taken again from the videos), every
    candidate's score and the random generators' states after it. `aynamics preferences --out OUT` keeps it in
    `OUT.partial` and deletes it once OUT is written.

        progress = SamplingProgress("prefs.partial", {"seed": 0, "num_samples": 32, ...})
        with progress.opened():  # made or checked, and locked: a second writer is refused
            rows, summary = build_preferences(module, videos, progress=progress, ...)
            write_preferences(rows, summary, out)
            progress.remove()  # under the lock: no second writer starts on the batches meanwhile
    """

    STREAM = "batch"

    def __init__(self, folder: str | Path, settings: dict) -> None:
        fields = frozenset({"start", "keys", "digests", "sampling", "rows", "rewards", "scores", "rng"})
        super().__init__(folder, settings, run="a preference run", verb="sample", fields={self.STREAM: fields})


def stored_clock(path: str | Path) -> dict | None:
    """{"fps", "clip_frames"} of the videos a stored preference data set was sampled from (the prompt's clock, which
    sets a video's temporal positions), or None for one written without it.

    Raises:
        ValueError: a clock of values no video has (hand-edited), naming summary.json.
    """
    summary_path = Path(path) / "summary.json"
    try:
        clock = json.loads(summary_path.read_text()).get("clock")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(clock, dict) or not {"fps", "clip_frames"} <= set(clock):
        return None
    try:  # hand-edited: float('abc') or a number as clip_frames named no file
        out = {"fps": float(clock["fps"]), "clip_frames": tuple(int(k) for k in clock["clip_frames"])}
        lm.PromptSpec(**out)  # the values a prompt accepts (fps > 0, increasing frames)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{str(summary_path)!r}: clock {clock} is not the videos' clock ({e})") from None
    return out


def check_made_for(path: str | Path, prompt: Any, tokenizer) -> None:
    """Refuse a stored preference data set made under another prompt (target, modality, frames) or tokenizer than
    the training's: its completion ids would be read as other tokens, its frames shown another way.

    Raises:
        ValueError: naming the stored and the current values. Data sets without the record (older ones) pass.
    """
    summary_path = Path(path) / "summary.json"
    try:
        summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    except ValueError as e:  # truncated or hand-edited: json's message names no file
        raise ValueError(f"{str(summary_path)!r} cannot be read ({e}): it records what the preferences mean") from None
    if not isinstance(summary, dict):
        raise ValueError(f"{str(summary_path)!r} holds a {type(summary).__name__}, not the record of a preference set")
    mismatch = lm.prompt_mismatch(summary.get("prompt") or {}, prompt)
    if mismatch:
        was, now = mismatch
        raise ValueError(f"preferences {str(path)!r} were sampled with {was}, but the data are set to {now}")
    made, ours = summary.get("tokenizer"), lm.tokenizer_fingerprint(tokenizer)
    if made is not None and made != ours:
        raise ValueError(
            f"preferences {str(path)!r} hold token ids of another tokenizer (vocabulary {made}, this model's "
            f"{ours}): sample them again with this model"
        )


# What `write_preferences` puts in its folder (`datasets`' files and ours): a folder holding anything else is not a
# preference set, whatever summary.json it has, and is never replaced (a common name: a results folder may hold one)
_PREFERENCE_FILE = re.compile(r"(state\.json|dataset_info\.json|summary\.json|data-\d+-of-\d+\.arrow)")


def _other_file(out: Path) -> str | None:
    """The first entry of `out` that no preference set writes (hidden files aside), or None."""
    for p in sorted(out.iterdir()):
        if not p.name.startswith(".") and not (p.is_file() and _PREFERENCE_FILE.fullmatch(p.name)):
            return p.name
    return None


def check_out(out: str | Path) -> Path:
    """`out` resolved, if it may be (re)written: absent, or a preference set written before (`summary.json` and
    `state.json`, and only the files a preference set holds). Anything else is refused, so a mistyped `--out`
    never deletes a data set, a results folder or a home folder.

    Raises:
        ValueError: `out` exists and is not a preference data set, naming it.
    """
    out = Path(out).resolve()
    if not out.exists():
        return out
    if not (out / "summary.json").is_file():
        raise ValueError(
            f"--out {str(out)!r} exists and is not a preference data set (no summary.json): refusing to replace it; "
            "give a new folder"
        )
    other = _other_file(out)
    why = "no state.json" if not (out / "state.json").is_file() else None if other is None else f"it holds {other!r}"
    if why is not None:
        raise ValueError(
            f"--out {str(out)!r} exists and is not a preference data set ({why}): refusing to replace it; "
            "give a new folder"
        )
    return out


def _leftovers(out: Path, kind: str) -> list[Path]:
    """The hidden `.OUT.tmp-XXXXXXXX` or `.OUT.old-XXXXXXXX` folders (`kind` "tmp" or "old") beside `out` that
    `write_preferences` made (`tempfile.mkdtemp`'s 8 characters) and that hold nothing but a preference set's files:
    a folder of the user's named alike, or holding anything else, is none of them. Hidden, as the other writers'
    (`.adapter.tmp-PID`): a visible `OUT.old-20240101` is what a user names a copy of the set."""
    name = re.compile(rf"\.{re.escape(out.name)}\.{kind}-[a-z0-9_]{{8}}")
    return [
        p
        for p in sorted(out.parent.iterdir())
        if name.fullmatch(p.name) and p.is_dir() and not p.is_symlink() and _other_file(p) is None
    ]


def write_preferences(rows: list[dict], summary: dict, out: str | Path) -> Path:
    """Save the rows as a data set at `out` (atomically: written beside, then renamed) with `summary.json`.
    A folder already at `out` is replaced only if it is a preference set (`check_out`).

    What killed writes of `out` left beside it is tidied: a set moved aside (`.OUT.old-*`) with no `out` (a kill
    between the two renames) is put back first, as the only copy of what `out` held, so that this write failing
    too still leaves it there; once the new set is in place, the `.OUT.tmp-*` and `.OUT.old-*` folders of earlier
    writes (half-written sets, sets it replaces; left for good before) are deleted (`_leftovers`: never another
    folder). A process writing the same `out` at once could lose its folder to this: callers that may run
    together hold the lock of `partial_folder(out)` (`SamplingProgress.opened`), as `aynamics preferences` does.
    """
    from datasets import Dataset

    out = Path(out).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    moved_aside = _leftovers(out, "old")
    if not os.path.lexists(out) and len(moved_aside) == 1:  # several: which was `out` last is unknown, none goes back
        moved_aside[0].rename(out)
    # a new folder beside: a fixed name (`OUT.tmp`) deleted whatever folder of that name was there
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    tmp.rmdir()  # save_to_disk makes it
    columns = {c: [row[c] for row in rows] for c in COLUMNS}  # from_dict keeps the columns of 0 rows too
    Dataset.from_dict(columns, features=features()).save_to_disk(str(tmp))
    (tmp / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    try:
        check_out(out)  # checked again: the folder may have appeared while sampling
    except ValueError as e:
        raise ValueError(f"{e}; the preferences are kept in {str(tmp)!r}") from None
    # the earlier set is moved aside, not deleted, until the new one is in place: deleting it first (seconds for a
    # large set) left, if interrupted, half of it at `out` and the new set under a temporary name nobody was told
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    old.rmdir()
    try:
        out.rename(old)
    except FileNotFoundError:  # no earlier set
        old = None
    try:
        tmp.rename(out)
    except OSError as e:  # e.g. another writer's set appeared at `out` meanwhile
        if old is not None and not out.exists():
            old.rename(out)
        raise OSError(f"{e}; the preferences are kept in {str(tmp)!r}") from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    for leftover in [*_leftovers(out, "tmp"), *_leftovers(out, "old")]:  # of earlier writes: this one replaced them
        shutil.rmtree(leftover, ignore_errors=True)
    return out


def load_preferences(path: str | Path):
    """The stored preference data set (rows as dicts with PIL frames), checked for its columns.

    Raises:
        FileNotFoundError: no data set at `path`.
        ValueError: a data set without the preference columns.
    """
    import datasets

    root = Path(path)
    if not (root / "state.json").is_file():
        raise FileNotFoundError(
            2, f"preferences {str(root)!r}: no data set here (run `aynamics preferences`)", str(root)
        )
    empty = ValueError(f"preferences {str(root)!r} hold 0 pairs: every video's candidates tied")
    try:
        ds = datasets.load_from_disk(str(root))
    except IndexError:  # `datasets` cannot load back a data set of 0 rows (no table to concatenate)
        raise empty from None
    except (OSError, ValueError) as e:  # truncated .arrow or JSON files, a data file gone: arrow's words name none
        raise ValueError(
            f"preferences {str(root)!r} cannot be read ({type(e).__name__}: {e}): write them again with "
            "`aynamics preferences`"
        ) from None
    missing = [c for c in COLUMNS if c not in ds.column_names]
    if missing:
        raise ValueError(f"preferences {str(root)!r}: columns {missing} are missing (has {ds.column_names})")
    if len(ds) == 0:
        raise empty
    _check_rows(ds, root)
    return ds


def _check_rows(ds, root: Path) -> None:
    """Refuse rows that training cannot read as one (B, N) batch of candidates (a hand-edited or foreign set): the
    same N >= 2 completion ids and rewards in every row, each completion at least one token, finite rewards, frames.
    Without this, NaN rewards were skipped as ties (no loss, silently) and uneven rows stopped the run mid-training
    with torch's reshape error. Reads the columns' lengths and numbers only (no image is decoded)."""
    import numpy as np
    import pyarrow.compute as pc

    table = ds.data.table if hasattr(ds.data, "table") else ds.data

    def lengths(column) -> np.ndarray:  # a null list reads as -1
        return pc.fill_null(pc.list_value_length(column), -1).to_numpy()

    def any_per_row(bad_values: np.ndarray, counts: np.ndarray) -> np.ndarray:  # flattened values -> rows
        out = np.zeros(len(counts), bool)
        np.logical_or.at(out, np.repeat(np.arange(len(counts)), np.maximum(counts, 0)), bad_values)
        return out

    ids, rewards = table.column("completion_ids"), table.column("rewards")
    n_ids, n_rewards = lengths(ids), lengths(rewards)
    n = int(n_rewards[0])
    finite = pc.fill_null(pc.is_finite(pc.list_flatten(rewards)), False).to_numpy(zero_copy_only=False)
    checks = (
        (
            (n_rewards != n) | (n_ids != n_rewards) | (n_rewards < 2),
            f"need as many completion_ids as rewards, the same N >= 2 in every row (row 0 has {n})",
        ),
        (any_per_row(~finite, n_rewards), "rewards must be finite numbers"),
        (any_per_row(lengths(pc.list_flatten(ids)) < 1, n_ids), "every completion needs at least one token id"),
        (lengths(table.column("frames")) < 1, "no frames"),
    )
    for bad, what in checks:
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            row = ds.select_columns(["key", "rewards", "completion_ids"])[i]
            raise ValueError(
                f"preferences {str(root)!r}: row {i} (key {row['key']!r}, rewards {row['rewards']}, "
                f"{len(row['completion_ids'] or [])} completion_ids) and {int(bad.sum()) - 1} more: {what}"
            )
