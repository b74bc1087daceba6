"""The `aynamics` console script: `aynamics COMMAND --help` for each command's options.

    aynamics simulate SCENE.yaml --out TRAJ.npz [--json]
    aynamics ranges [--markdown]
    aynamics render SCENE.yaml --out DIR
    aynamics score PRED.yaml [PRED2.yaml ...] --observed SCENE.yaml|DIR --json
    aynamics generate --num N --out DIR --seed S [--shard k --num-shards n]   (or --scenes PATH ...)
    aynamics refine PRED.yaml --observed SCENE.yaml|DIR [--budget N] [--params ...] --json
    aynamics edit SCENE.yaml "INSTRUCTION" [--out EDITED.yaml] [--render DIR]
    aynamics audit --measured M.csv --scene S.yaml --out DIR [--json]
    aynamics predict --adapter DIR VIDEO_OR_FRAMES_DIR
    aynamics evaluate --adapter DIR --data DIR [--split test] [--refine N]   (or --videos DIR)
    aynamics preferences --data DIR --out DIR
    aynamics collect MULTIRUN_DIR

Usage errors and invalid input exit with status 2 and a one-paragraph message on stderr (no traceback).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import json
import os
import re
import sys
from collections.abc import Collection
from pathlib import Path

from aynamics.scene import SceneError


class UsageError(Exception):
    """Bad command-line input: reported on stderr, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse prints usage + exits 2; we want one paragraph, same status
        raise UsageError(f"{self.prog}: {message}. Run `{self.prog} --help` for usage.")


def check_out_folder(
    command: str, out: str | os.PathLike, *, writes: Collection[str] | None = None, flag: str = "--out"
) -> None:
    """Refuse, before a command's work, an output folder that cannot be created (a part of its path already there
    is a file) and, given the names the command `writes` there, a folder holding anything else (hidden files
    aside): the command's files would be mixed into another's (a data set, a repository). A new or empty folder,
    and one an earlier run of the command wrote (even partly), are fine."""
    path = Path(out)
    there = next((p for p in (path, *path.parents) if p.exists()), None)
    if there is not None and not there.is_dir():
        raise UsageError(f"{command}: cannot write {flag} {str(path)!r}: {str(there)!r} is a file, not a folder")
    if writes is not None and path.is_dir():
        other = sorted(p.name for p in path.iterdir() if p.name not in writes and not p.name.startswith("."))
        if other:
            raise UsageError(
                f"{command}: {flag} {str(path)!r} holds other files ({other[0]!r}, ...): give a new or empty "
                f"folder, or one an earlier {command} wrote"
            )


def load_scene(command: str, path: str, flag: str | None = None):
    """`scene.load` for a scene file given on the command line: its problems are named with the command and the
    file (and option) they came from, as `simulate: 'a.yaml': invalid scene (1 problem): ...`. Without it a
    command reading two scenes (score's, refine's, audit's) said what was wrong but not in which file."""
    from aynamics.scene import load

    try:
        return load(path)
    except SceneError as e:
        where = f"{command}: {f'{flag} ' if flag else ''}{str(path)!r}"
        if [p.path for p in e.problems] == ["file"]:  # cannot be read (missing, a folder, too large): said once
            raise UsageError(f"{where}: {e.problems[0].message}") from None
        raise UsageError(f"{where}: {e}") from None


RENDERED_SUFFIXES = (".npy", ".npz", ".png", ".gif", ".mp4", ".json")  # files a render folder holds


def refuse_rendered_file(command: str, path: str) -> None:
    """An `--observed` file of a render folder (segmentation.npy, a frame) is refused with the folder to give: it
    was read as a scene text and refused as "too large: a scene is at most 200000 characters"."""
    p = Path(path)
    if p.suffix.lower() in RENDERED_SUFFIXES and not p.is_dir():
        raise UsageError(
            f"{command}: --observed {path!r} is a {p.suffix} file, not a scene: give the scene's YAML file or the "
            f"folder `aynamics render` wrote (here perhaps {str(p.parent)!r})"
        )


@contextlib.contextmanager
def warnings_as_lines(command: str, prefix: str):
    """Within the block, a warning whose text starts with `prefix` (this project's own, about the user's input)
    is written at once to stderr as one line, `command: text` without the prefix; other warnings as usual."""
    import warnings

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        if text.startswith(prefix):
            sys.stderr.write(f"{command}: {text[len(prefix) :]}\n")
        else:
            shown(message, category, filename, lineno, file, line)

    with warnings.catch_warnings():
        shown = warnings.showwarning
        warnings.showwarning = show
        yield


def add_device_option(p: argparse.ArgumentParser, what: str = "the model") -> None:
    """The `--device` option of the commands that run a model (`lm.inference_device` reads it)."""
    choices = "auto (a GPU when there is one, default), cpu, cuda, cuda:1, ..."
    p.add_argument("--device", default="auto", help=f"device of {what}: {choices}")


def print_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=None)
    sys.stdout.write("\n")


# --------------------------------------------------------------------------------------------
# simulate
# --------------------------------------------------------------------------------------------
def _add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="simulate a scene and write its trajectory (npz)")
    p.add_argument("scene", help="scene YAML file (or model output holding one)")
    p.add_argument(
        "--out",
        help="trajectory file to write, NumPy .npz format at exactly this path (no suffix is added): names, t, "
        "position, orientation, velocities",
    )
    p.add_argument("--json", action="store_true", help="print final positions, rest times and contacts as JSON")
    p.add_argument("--duration", type=float, default=1.0, help="seconds to simulate (default 1.0)")
    p.add_argument("--fps", type=int, default=30, help="frames per second (default 30)")
    p.add_argument(
        "--substeps", type=int, default=None, help="physics steps per frame (default: round(240 / fps), 8 at 30 fps)"
    )
    p.set_defaults(run=_run_simulate)


def _run_simulate(args) -> int:
    from aynamics import simulate as sim

    scene = load_scene("simulate", args.scene)
    try:
        config = sim.SimConfig(duration=args.duration, fps=args.fps, substeps=args.substeps)
    except ValueError as e:  # "fps = 0: ..." names the option: --fps
        raise UsageError("simulate: " + re.sub(r"\b(duration|fps|substeps) = ", r"--\1 ", str(e))) from None
    if not args.out and not args.json:
        raise UsageError("simulate: nothing to do; give --out TRAJ.npz and/or --json")
    if args.out:  # checked before simulating; numpy would write DIR.npz beside a folder, so the file is opened here
        if os.path.isdir(args.out):
            raise UsageError(f"simulate: --out {args.out!r} is a folder: give the trajectory file to write (TRAJ.npz)")
        parent = os.path.dirname(args.out) or "."
        if not os.path.isdir(parent):
            raise UsageError(f"simulate: cannot write --out {args.out!r}: folder {parent!r} does not exist")
    rollout = sim.simulate(scene, config)
    if args.out:
        try:
            with open(args.out, "wb") as f:
                rollout.to_npz(f)
        except OSError as e:
            raise UsageError(f"simulate: cannot write --out {args.out!r}: {e.strerror or e}") from None
    if args.json:
        print_json(rollout.summary())
    if not rollout.valid:
        sys.stderr.write(f"simulate: the rollout is invalid: {rollout.reason}\n")
    return 0 if rollout.valid else 1


# --------------------------------------------------------------------------------------------
# ranges
# --------------------------------------------------------------------------------------------
def _add_ranges(sub) -> None:
    p = sub.add_parser("ranges", help="print the scene format's field table (units, frames, ranges)")
    p.add_argument("--markdown", action="store_true", help="as a Markdown table (the README's)")
    p.set_defaults(run=_run_ranges)


def _run_ranges(args) -> int:
    from aynamics.scene import RANGES, ranges_markdown

    if args.markdown:
        sys.stdout.write(ranges_markdown())
    else:
        print_json({k: {"lo": r.lo, "hi": r.hi, "unit": r.unit, "frame": r.frame} for k, r in RANGES.items()})
    return 0


# name -> (module, function adding the subparser, one-line help). Only the chosen command's module is imported,
# so `aynamics --help` and light commands start fast (no torch/transformers import).
COMMANDS: dict[str, tuple[str, str, str]] = {
    "simulate": ("aynamics.cli", "_add_simulate", "simulate a scene and write its trajectory (npz)"),
    "ranges": ("aynamics.cli", "_add_ranges", "print the scene format's field table (units, frames, ranges)"),
    "render": ("aynamics.observe_cli", "_add_render", "render a scene: frames, segmentation, depth, flow, camera, GIF"),
    "score": ("aynamics.observe_cli", "_add_score", "score predicted scenes against an observed scene or folder"),
    "generate": ("aynamics.generate", "add_generate_parser", "generate a dataset: scenes, videos, flow, reasoning"),
    "refine": ("aynamics.refine_cli", "add_refine_command", "refine a predicted scene with CMA-ES against a video"),
    "edit": ("aynamics.whatif", "add_edit_command", "edit a scene by instruction, re-simulate, show the what-if"),
    "audit": ("aynamics.audit", "add_audit", "audit the simulation against measured trajectories"),
    "predict": ("aynamics.predict", "add_predict_command", "write the scene YAML for a video with a trained adapter"),
    "evaluate": (
        "aynamics.evaluate_cli",
        "add_evaluate_command",
        "score a trained adapter on a data-set split by simulation",
    ),
    "export-adapter": ("aynamics.predict", "add_export_command", "write the peft adapter folder of a checkpoint"),
    "preferences": ("aynamics.preference_cli", "add_preferences_command", "sample, score, store PRO preferences"),
    "collect": ("aynamics.collect", "add_collect_command", "collect a multirun folder into one metrics table"),
}


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; the subcommand named in `argv` is built in full, the others only listed."""
    parser = _Parser(prog="aynamics", description="Infer rigid-body physics from video: scenes, simulation, tools.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    chosen = next((a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")), None)
    for name, (module, adder, help_text) in COMMANDS.items():
        if name == chosen:
            getattr(importlib.import_module(module), adder)(sub)
        else:
            sub.add_parser(name, help=help_text, add_help=False)
    return parser


def missing_file_message(e: FileNotFoundError) -> str:
    """What a FileNotFoundError says to a user: our own message (which names the path and what was expected
    there) when one was given, else `file not found: PATH`."""
    if e.filename is None:  # raised with a message only
        return str(e)
    if e.strerror and e.strerror != os.strerror(errno.ENOENT):  # raised as (errno, message, path)
        return e.strerror if str(e.filename) in e.strerror else f"{e.strerror}: {e.filename}"
    return f"file not found: {e.filename}"


# The machine's refusals to write (a full disk or quota, a read-only or foreign folder): one line, not a traceback
WRITE_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM})


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(argv)
    command = "aynamics"
    try:
        args = parser.parse_args(argv)
        command = getattr(args, "command", None) or command
        if not getattr(args, "run", None):
            raise UsageError("aynamics: give a command. Run `aynamics --help` for the list.")
        return args.run(args)
    except (UsageError, SceneError) as e:
        sys.stderr.write(" ".join(str(e).split()) + "\n")
        return 2
    except FileNotFoundError as e:
        sys.stderr.write(f"{command}: {missing_file_message(e)}\n")
        return 2
    except BrokenPipeError:  # e.g. `aynamics ... | head`
        sys.stderr.close()
        return 0
    except OSError as e:
        if e.errno not in WRITE_ERRORS:  # anything else is unexpected: its traceback helps
            raise
        sys.stderr.write(f"aynamics: {e.strerror}: {e.filename}\n" if e.filename else f"aynamics: {e}\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write("aynamics: interrupted\n")
        return 130


if __name__ == "__main__":
    # `python -m aynamics.cli` runs this file as `__main__`, a second copy of the module whose UsageError is not
    # the `aynamics.cli.UsageError` the commands raise: run the package module's main instead
    from aynamics.cli import main as package_main

    sys.exit(package_main())
