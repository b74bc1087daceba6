"""Your own scenes for `aynamics generate --scenes PATH ...`: the scene files of files and folders, each validated
and simulated before anything is written, with its split (a train/, validation/ or test/ folder, else the hash
split) and its hash, so that a resumed run refuses changed scenes and accepts the same files typed another way.

    scenes = scene_files(["my_scenes/"], config)   # [SceneFile(path, scene, split, digest), ...]
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from aynamics.dataset_store import MANIFEST, SPLITS, split_of
from aynamics.generate_config import GenerateConfig
from aynamics.scene import SceneError, dump
from aynamics.simulate import simulate

SCENE_SUFFIXES = (".yaml", ".yml")
MAX_LISTED = 10  # problems of scene files named in one error


@dataclass(frozen=True)
class SceneFile:
    """One of your own scenes for `generate(scenes=...)` (`aynamics generate --scenes`).

    Attributes:
        path: the file, as found (named in messages).
        text: its scene in canonical YAML (`scene.dump`).
        split: "train", "validation" or "test" when the file's folder has that name (in any case); None: the hash
            split (`split_of`).
    """

    path: str
    text: str
    split: str | None = None

    @property
    def sha256(self) -> str:
        """The hash of the scene (its canonical YAML: comments and formatting of the file aside)."""
        return hashlib.sha256(self.text.encode()).hexdigest()


def _is_scene_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in SCENE_SUFFIXES and not path.name.startswith(".")


def split_of_folder(path: Path) -> str | None:
    """The split a scene file's folder names ("train", "validation", "test", in any case), else None. The folder
    is taken from the absolute path, so `c.yaml` typed inside `test/` and `scenes/test/c.yaml` agree."""
    name = Path(os.path.abspath(path)).parent.name.lower()
    return name if name in SPLITS else None


def _hidden(path: Path, root: Path) -> bool:
    return any(part.startswith(".") for part in path.relative_to(root).parts)


def _scene_paths(paths: Sequence[str | os.PathLike]) -> list[Path]:
    """The files of `paths`: a file as given; a folder's scene files (*.yaml / *.yml, not hidden) and then those of
    its train/, validation/ and test/ subfolders (any case; in that order), each sorted by name. A scene file
    under a given folder that none of the paths reads (another subfolder) is refused rather than left out unseen."""
    found: list[Path] = []
    folders: list[Path] = []
    for given in paths:
        path = Path(given)
        if not path.exists():
            raise FileNotFoundError(errno.ENOENT, f"--scenes {str(path)!r} does not exist", str(path))
        if path.is_file():
            found.append(path)
            continue
        subfolders = [d for d in path.iterdir() if d.is_dir() and d.name.lower() in SPLITS]
        subfolders.sort(key=lambda d: (SPLITS.index(d.name.lower()), d.name))
        files = [f for d in (path, *subfolders) for f in sorted(d.iterdir()) if _is_scene_file(f)]
        if not files:
            raise ValueError(
                f"--scenes {str(path)!r} holds no scene files (*.yaml, *.yml; also looked in its "
                f"{', '.join(s + '/' for s in SPLITS)} subfolders)"
            )
        found += files
        folders.append(path)
    read = {f.resolve() for f in found}
    for folder in folders:
        unread = sorted(
            f for f in folder.rglob("*") if _is_scene_file(f) and not _hidden(f, folder) and f.resolve() not in read
        )
        if unread:
            raise ValueError(
                f"--scenes {str(folder)!r}: {str(unread[0])!r} is in a subfolder that is not train/, validation/ or "
                f"test/ ({len(unread)} such file(s)); move them, or give their folder as a --scenes path too"
            )
    first: dict[Path, Path] = {}
    for p in found:
        other = first.setdefault(p.resolve(), p)
        if other is not p:
            raise ValueError(f"--scenes lists the file {str(p)!r} twice (as {str(other)!r} too): each scene once")
    return found


def scene_files(paths: Sequence[str | os.PathLike], config: GenerateConfig | None = None) -> list[SceneFile]:
    """Your own scenes for a data set: each path a scene YAML file or a folder of them (its *.yaml / *.yml files,
    then those of its train/, validation/ and test/ subfolders). A file in a folder named train, validation or
    test is in that split; the others take the hash split.

    Every file is read, validated and simulated (`config`'s timing) before anything is written, so a bad one
    cannot stop a run half-way.

    Raises:
        FileNotFoundError: a path does not exist.
        ValueError: no scene file, a file listed twice, a scene file in a subfolder that is not a split's, or files
            that do not load or whose rollout is invalid (diverged, objects starting inside each other): up to
            `MAX_LISTED` named at once, each with the field, value and what is allowed, or the rollout's reason.
    """
    config = config or GenerateConfig()
    from aynamics.scene import load

    out: list[SceneFile] = []
    problems: list[str] = []
    for path in _scene_paths(paths):
        try:
            scene = load(str(path))
        except SceneError as e:
            problems.append(f"{path}: {e}")
            continue
        rollout = simulate(scene, config.sim)
        if not rollout.valid:
            problems.append(f"{path}: the rollout is invalid: {rollout.reason}")
            continue
        out.append(SceneFile(str(path), dump(scene), split_of_folder(path)))
    if problems:
        more = f" (and {len(problems) - MAX_LISTED} more)" if len(problems) > MAX_LISTED else ""
        raise ValueError(f"{len(problems)} scene file(s) cannot be used{more}: " + "; ".join(problems[:MAX_LISTED]))
    return out


def warn_repeated_scenes(scenes: Sequence[SceneFile], seed: int, config: GenerateConfig) -> None:
    """Warn when one scene lands in two splits (a test scene seen in training), by the split each record gets."""
    seen: dict[str, tuple[SceneFile, str]] = {}
    for i, f in enumerate(scenes):
        split = f.split or split_of(seed, i, config.splits)
        other, other_split = seen.setdefault(f.sha256, (f, split))
        if other is not f and other_split != split:
            warnings.warn(
                f"--scenes: {other.path!r} ({other_split} split) and {f.path!r} ({split} split) hold the same scene",
                stacklevel=2,
            )


def check_scene_run(out: Path, scenes: Sequence[SceneFile] | None) -> None:
    """Refuse to add records to a run in `out` made from other scenes: sampled ones (`scenes` None) to a run of
    scene files or the reverse, or scene files to a run of others, naming the first whose content or split differs
    (the manifest keeps each scene's hash and split by position, not its path, so the same files typed another
    way, from another folder or on another machine's mount resume)."""
    path = out / MANIFEST
    if not path.is_file():
        return
    old = json.loads(path.read_text())
    stored = old.get("config", {}).get("scenes")
    if (stored is None) != (scenes is None):
        was, now = ("sampled scenes", "scene files") if stored is None else ("scene files", "sampled scenes")
        raise ValueError(f"--out {str(out)!r} holds a run of {was}, this run makes {now}; use another folder")
    names = old.get("scene_files", [])
    for i, (was, f) in enumerate(zip(stored or [], scenes or [], strict=False)):
        if was != {"sha256": f.sha256, "split": f.split}:
            where = f" ({names[i]!r} then)" if i < len(names) else ""
            raise ValueError(
                f"--out {str(out)!r} holds a run whose scene {i}{where} had another content or split than "
                f"{f.path!r} now; use another folder, or the same scene files to resume"
            )
