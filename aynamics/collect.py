"""Collect the runs of a Hydra multirun folder into one table of their final metrics.

    python train.py -m data.modality=rgb,flow stage.target=answer,think_answer
    aynamics collect multirun/2026-11-21/18-00-00            # prints a Markdown table, writes summary.csv there
    python -m aynamics.collect multirun/... --out table.csv

Every run folder holds `metrics.json` (written by `train.py`) and `.hydra/overrides.yaml` (the overrides that
make the run differ); a run without `metrics.json` (crashed, still running) is listed with status "missing", one
whose file cannot be read as train.py's record with status "unreadable metrics.json".
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import yaml

from aynamics.video_io import natural_key

DEFAULT_METRICS = (
    "val/yaml_valid",
    "val/sim_valid",
    "val/count_acc",
    "val/composition_acc",
    "val/iou_first",
    "val/iou_full",
    "val/epe_first",
    "val/epe_full",
    "val/position_mae",
    "val/velocity_mae",
    "val/loss",
    "val/type_acc",
    "val/baseline/iou_full",
    "train/loss",  # the last step's: a run that never validated still shows how far it trained
)


def run_folders(root: str | Path) -> list[Path]:
    """Run folders under `root`: those holding `.hydra/overrides.yaml` or train.py's `metrics.json` (with its
    `global_step`; `aynamics evaluate --out OUT/test` writes another kind inside a run), in name order."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise FileNotFoundError(f"{str(root)!r} is a file, not a multirun folder (multirun/DATE/TIME)")
    if not root.is_dir():
        raise FileNotFoundError(f"multirun folder {str(root)!r} does not exist")
    found = {p.parent.parent for p in root.rglob(".hydra/overrides.yaml")} | {
        p.parent for p in root.rglob("metrics.json") if _is_training_record(p)
    }
    # each part by its numbers (2 before 10), words and numbers comparable: a folder "best" or "3_rerun" beside
    # Hydra's 0, 1, ... compared a str with an int
    return sorted(found, key=lambda p: [natural_key(s) for s in p.relative_to(root).parts])


def _is_training_record(path: Path) -> bool:
    """False for another tool's record (a JSON object without `global_step`); an unreadable one is listed, and
    said so."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return True
    return not isinstance(record, dict) or "global_step" in record


def collect(root: str | Path, metrics: tuple[str, ...] = DEFAULT_METRICS) -> list[dict]:
    """One row per run: "run" (folder name), its overrides as columns, "status", "step" and the final metrics."""
    rows = []
    for folder in run_folders(root):
        row: dict = {"run": str(folder.relative_to(root)) if folder != Path(root) else "."}
        overrides_file = folder / ".hydra" / "overrides.yaml"
        if overrides_file.is_file():
            try:
                overrides = yaml.safe_load(overrides_file.read_text(errors="replace")) or []
            except yaml.YAMLError:  # a file cut short or edited by hand: the run is still listed
                overrides = []
                row["overrides"] = "unreadable .hydra/overrides.yaml"
            for item in overrides if isinstance(overrides, list) else []:
                key, _, value = str(item).partition("=")
                if not key.startswith("hydra."):
                    row[key.lstrip("+~")] = value
        metrics_file = folder / "metrics.json"
        if metrics_file.is_file():
            try:
                record = json.loads(metrics_file.read_text())
                values = record.get("metrics", {})
                # val_step: the step of the val/ metrics (the last validation's; earlier records: the final step;
                # a run that never validated: none)
                step = record.get("global_step")
                validated = any(str(k).startswith("val/") for k in values)
                row |= {"status": "done", "step": step, "val_step": record.get("val_step", step if validated else None)}
                row |= {m: values.get(m) for m in metrics}
            except (ValueError, AttributeError):  # not JSON, or not train.py's {"global_step", "metrics": {...}}
                row |= {"status": "unreadable metrics.json", "step": None, "val_step": None}
                row |= {m: None for m in metrics}
        else:
            log = folder / "train.log"
            failed = log.is_file() and "Traceback" in log.read_text(errors="replace")
            row |= {"status": "failed (train.log)" if failed else "missing", "step": None, "val_step": None}
            row |= {m: None for m in metrics}
        rows.append(row)
    if not rows:
        raise ValueError(f"no runs under {str(root)!r}: expected folders with .hydra/overrides.yaml or metrics.json")
    return rows


def _columns(rows: list[dict]) -> list[str]:
    cols: list[str] = []
    for row in rows:
        cols += [k for k in row if k not in cols]
    return cols


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4f}"
    return str(value)


def to_markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table (columns in first-seen order)."""
    cols = _columns(rows)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_cell(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def write_csv(rows: list[dict], path: str | Path) -> Path:
    """Write the rows as CSV. An existing file is replaced only when empty or a table this wrote (a header "run",
    ..., "status", ...): `--out train.py` or a run's metrics.json was overwritten without a word.

    Raises:
        FileExistsError: `path` holds something else.
    """
    path = Path(path)
    if path.is_file() and path.stat().st_size and not _is_table(path):
        raise FileExistsError(
            f"{str(path)!r} exists and is not a table that collect wrote (its header is not run,...,status,...): "
            "choose another --out, or remove the file first"
        )
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=_columns(rows))
        writer.writeheader()
        writer.writerows(rows)
    return path


def _is_table(path: Path) -> bool:
    try:
        with open(path, newline="", errors="replace") as f:
            header = next(csv.reader([f.readline(1 << 16)]), [])
    except OSError:
        return False
    return header[:1] == ["run"] and "status" in header


def add_collect_command(sub) -> None:
    """Register `aynamics collect` on the CLI's subparsers."""
    p = sub.add_parser("collect", help="collect a multirun folder into one table of final metrics")
    p.add_argument("folder", help="the multirun folder (multirun/DATE/TIME)")
    p.add_argument("--out", help="CSV to write (default FOLDER/summary.csv)")
    p.set_defaults(run=run_collect)


def run_collect(args) -> int:
    from aynamics.cli import UsageError

    try:
        rows = collect(args.folder)
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(f"collect: {e}") from None
    dest = args.out or Path(args.folder) / "summary.csv"
    try:
        out = write_csv(rows, dest)
    except FileExistsError as e:
        raise UsageError(f"collect: --out {e}") from None
    except OSError as e:
        raise UsageError(f"collect: cannot write {dest}: {e}") from None
    sys.stdout.write(to_markdown(rows) + f"\n\n(written to {out})\n")
    return 0


if __name__ == "__main__":
    from aynamics.cli import main

    sys.exit(main(["collect", *sys.argv[1:]]))
