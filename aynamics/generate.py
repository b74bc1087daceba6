"""Synthetic training data: sampled scenes, simulated, rendered, described, stored as a Hugging Face data set.

    aynamics generate --num 1000 --out data/synth --seed 0 [--shard k --num-shards n] [--config FILE] [key=value ...]
    aynamics generate --scenes my_scenes/ --out data/mine [key=value ...]    # your own scene files instead
    path = generate_dataset("data/tiny", num=8, seed=0, config=GenerateConfig(width=96, height=64))
    ds = datasets.load_from_disk(path)   # DatasetDict: train / validation / test

Scene i is drawn from `sampler.scene_seed(seed, i, attempt)` alone, so a record does not depend on the shard
that made it, on the number of workers or on earlier runs. Work is cut into chunks of `chunk_size` consecutive
indices; shard k of n makes the chunks c with c % n == k and writes each one atomically (a temporary folder
renamed to `chunks/NNNNNN`), so a killed run started again skips finished chunks and redoes the partial one
(same records): nothing is lost or duplicated. A second process started on chunks a live one is making (the same
command twice) is refused before it renders anything; shards of one run still write into one folder at once. When
every chunk of the run is on disk (from one run or from all shards writing into the same folder, or folders joined
with `assemble(out, sources)`) the chunks are concatenated in index order and split by a hash of (seed, index)
into the DatasetDict at `out` (storage: `dataset_store.py`).

With `--scenes` (`scene_files`, `generate(scenes=...)`) record i is made from the i-th of your scene files instead
of a sampled scene (`attempt` 0; the sampler's settings play no part): a file in a folder named train, validation
or test (any case) is in that split, the others
take the hash split; every file is validated and simulated before anything is written, and the run's manifest
holds each scene's hash and split by position (paths only for the reader), so a changed scene is refused as
another run instead of being mixed in, while the same files typed another way, or on another machine, resume.

Per record the only OpenGL work is one pass over the F sampled frames (RGB, segmentation, depth: `render_sampled`);
the flow of frame f to f + 1 comes from that depth and the poses at f and f + 1, so frames f + 1 are never drawn.
Images are PNG-encoded in the workers by `png_encode.png_bytes` (lossless; ~1.7× faster than Pillow's encoder).
`benchmarks/bench_generate.py` measures scenes per minute next to the render-only bound.

Columns (one row per scene; T = 31 states at 30 FPS, F = 10 sampled frames, N objects):
- `index` int64, `seed` int64 (global), `attempt` int32 (resamples after a diverged simulation), `split` str.
- `scene_yaml` str: canonical YAML (`scene.dump`); `reasoning` str: motion-reasoning text (`reasoning.py`);
  `target_answer` = `<answer>YAML</answer>`; `target_think` = `<think>REASONING</think>\\n\\n<answer>YAML</answer>`.
- `rgb`: list of F images (PNG, RGB, width × height) of video frames `frame_indices`.
- `flow`: list of F images: the exact forward flow from frame f to f + 1 on the Middlebury colour wheel, one
  magnitude scale per scene; `flow_max` float32 is that scale in pixels (saturation 1 = `flow_max`).
- `segmentation`: list of F images (PNG, mode L): pixel value = object index in `scene.objects` order + 1,
  0 = floor and sky.
- `frame_indices` list[int32] and `frame_times` list[float32] (s) of the sampled frames.
- `states`: struct of the rollout: `names` [N] str, `t` [T] s, `position` [T][N][3] m (world),
  `orientation` [T][N][4] wxyz, `linear_velocity` [T][N][3] m/s and `angular_velocity` [T][N][3] rad/s (world),
  `in_view` [T][N] bool (bounding sphere in the frustum), `visible` [F][N] bool (from segmentation),
  `rest_time` [N] s or null (still moving at the end).
- `contacts`: list of {`a`, `b` ("floor" or an object name), `start`, `end` (s)}: contact intervals per frame.
- `camera`: {`fovy` deg, `orientation` deg, `position` [3] m, `width`, `height`, `K` [3][3], `R` [3][3], `t` [3]}:
  OpenCV convention, x_cam = R @ x_world + t, pixel = K @ x_cam / z.
- `num_objects` int32, `shapes` list[str], `has_collision` bool (two objects touch at some frame).
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import multiprocessing as mp
import os
import shlex
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from aynamics import reasoning as rs
from aynamics import sampler as smp
from aynamics.camera import sphere_in_view
from aynamics.dataset_store import (  # noqa: F401 - re-exported: the storage half of `generate`
    FORMAT_VERSION,
    MANIFEST,
    SPLITS,
    assemble,
    chunk_dir,
    chunk_ranges,
    claim_shard,
    features,
    remove_partial_chunks,
    shard_chunks,
    write_chunk,
    write_manifest,
)
from aynamics.png_encode import png_bytes
from aynamics.scene import Scene, SceneError, dump, parse
from aynamics.simulate import PHYSICS_VERSION, Rollout, SimConfig, bounding_radius, simulate

if TYPE_CHECKING:  # rendering is imported inside the workers only
    from aynamics.render import Frames, Renderer


# Raise when the same rollout gets other labels (rest_time, reasoning text): a run whose chunks were labelled by
# other code is neither resumed nor assembled with this one (absent: 1). 2: rest from the frame's mean speed (a
# resting object's contact jitter is not motion), occlusion told apart from leaving the view, heights above the
# floor plane.
LABELS_VERSION = 2


@dataclass(frozen=True)
class GenerateConfig:
    """How records are made (not which ones: that is `seed` and `num`).

    Attributes:
        sampler: scene sampler ranges and shares.
        width, height: image size in pixels.
        duration, fps, substeps: simulation timing (1 s at 30 FPS gives 31 states, a 30-frame video; substeps
            None: round(240 / fps), a physics step near 1/240 s).
        stride: every `stride`-th video frame is sampled (3: 10 of 30).
        splits: train / validation / test shares, summing to 1.
        chunk_size: scenes per stored chunk (the unit of resume and sharding).
        max_attempts: resamples of one index whose simulation diverged before giving up.
        textures_dir: folder of photographs for floor and sky (None: scikit-image's samples).
        backdrop: "photos" (floor and sky photographs) or "plain" (a random flat colour each).
        workers: processes rendering in parallel (each holds one OpenGL context); 0 = in this process.
        min_pixels: mask pixels for an object to count as visible in a frame.
    """

    sampler: smp.SamplerConfig = field(default_factory=smp.SamplerConfig)
    width: int = 480
    height: int = 320
    duration: float = 1.0
    fps: int = 30
    substeps: int | None = None
    stride: int = 3
    splits: tuple[float, float, float] = (0.8, 0.1, 0.1)
    chunk_size: int = 16
    max_attempts: int = 10
    textures_dir: str | None = None
    backdrop: str = "photos"
    workers: int = 2
    min_pixels: int = 1

    def __post_init__(self):
        if not (8 <= self.width <= 4096 and 8 <= self.height <= 4096):
            raise ValueError(f"width = {self.width}, height = {self.height}: must be in [8, 4096] pixels")
        SimConfig(self.duration, self.fps, self.substeps)  # raises ValueError naming the bad value
        if self.stride < 1 or self.chunk_size < 1 or self.max_attempts < 1 or self.min_pixels < 1:
            raise ValueError(
                f"stride = {self.stride}, chunk_size = {self.chunk_size}, max_attempts = {self.max_attempts}, "
                f"min_pixels = {self.min_pixels}: must be >= 1"
            )
        if len(self.splits) != 3 or min(self.splits) < 0 or abs(sum(self.splits) - 1) > 1e-6:
            raise ValueError(f"splits = {list(self.splits)}: need 3 shares (train, validation, test) >= 0 summing to 1")
        if not 0 <= self.workers <= 64:
            raise ValueError(f"workers = {self.workers}: must be in [0, 64]")
        if self.backdrop not in ("photos", "plain"):
            raise ValueError(f"backdrop = {self.backdrop!r}: must be 'photos' or 'plain'")
        if abs(self.sampler.aspect - self.width / self.height) > 1e-6 or self.sampler.duration != self.duration:
            object.__setattr__(
                self,
                "sampler",
                dataclasses.replace(self.sampler, aspect=self.width / self.height, duration=self.duration),
            )

    @property
    def sim(self) -> SimConfig:
        return SimConfig(self.duration, self.fps, self.substeps)

    def to_json(self) -> dict:
        """The fields that decide the records (not `workers`, which only changes speed)."""
        data = dataclasses.asdict(self)
        data.pop("workers")
        data["substeps"] = self.sim.substeps  # the steps the records were made with (None: from fps)
        data["physics"] = PHYSICS_VERSION  # chunks simulated by other code are not mixed in (absent: before 2)
        data["labels"] = LABELS_VERSION  # chunks whose rest times / reasoning were derived otherwise are not mixed in
        return data


# --------------------------------------------------------------------------------------------
# Config from a file and Hydra-style overrides (plain dataclasses; the package never imports Hydra)
# --------------------------------------------------------------------------------------------
def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


OPTIONAL_INTEGERS = ("substeps",)  # config fields that are an integer or None (the others None by default: paths)


def _typed(name: str, old, value):
    """`value` for a config field whose current value is `old`, checked to be of the same kind (a number, an
    integer, a flag, text, or a list of as many numbers), as a tuple for lists.

    Raises:
        ValueError: naming the field, the value and what it must be.
    """
    if isinstance(old, tuple):
        if not (isinstance(value, list | tuple) and len(value) == len(old) and all(map(_is_number, value))):
            raise ValueError(f"{name} = {value!r}: must be a list of {len(old)} numbers, e.g. {list(old)}")
        return tuple(value)
    if isinstance(old, bool):
        ok, kind = isinstance(value, bool), "true or false"
    elif isinstance(old, int):
        ok, kind = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif isinstance(old, float):
        ok, kind = _is_number(value), "a number"
    elif isinstance(old, str):
        ok, kind = isinstance(value, str), "text"
    elif name.rsplit(".", 1)[-1] in OPTIONAL_INTEGERS:
        ok, kind = value is None or (isinstance(value, int) and not isinstance(value, bool)), "an integer or null"
    else:  # optional fields (None by default): a path or None
        ok, kind = value is None or isinstance(value, str), "a path or null"
    if not ok:
        raise ValueError(f"{name} = {value!r}: must be {kind}")
    return float(value) if isinstance(old, float) else value


def config_from_dict(data: dict, base: GenerateConfig | None = None, where: str = "config") -> GenerateConfig:
    """A config from a nested mapping ({width: 96, sampler: {max_objects: 2}}), on top of `base`.

    Raises:
        ValueError: an unknown key (named, with the allowed ones) or a bad value.
    """
    base = base or GenerateConfig()
    if not isinstance(data, dict):
        raise ValueError(f"{where}: must be a mapping of config keys, got {type(data).__name__}")
    top = {f.name for f in dataclasses.fields(GenerateConfig)}
    sub = {f.name for f in dataclasses.fields(smp.SamplerConfig)}
    updates, sampler_updates = {}, {}
    for key, value in data.items():
        if key == "sampler":
            if not isinstance(value, dict):
                raise ValueError(f"{where}.sampler = {value!r}: must be a mapping")
            for k, v in value.items():
                if k not in sub:
                    raise ValueError(f"{where}.sampler.{k}: unknown key; allowed: {', '.join(sorted(sub))}")
                sampler_updates[k] = _typed(f"{where}.sampler.{k}", getattr(base.sampler, k), v)
        elif key not in top:
            raise ValueError(f"{where}.{key}: unknown key; allowed: {', '.join(sorted(top))}")
        else:
            updates[key] = _typed(f"{where}.{key}", getattr(base, key), value)
    try:
        sampler = dataclasses.replace(base.sampler, **sampler_updates)
        config = dataclasses.replace(base, sampler=sampler, **updates)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {e}") from None
    derived = {"aspect": (config.width / config.height, "width / height"), "duration": (config.duration, "duration")}
    for key, (value, source) in derived.items():  # the sampler's copies follow these (it was silently replaced)
        if key in sampler_updates and abs(sampler_updates[key] - value) > 1e-6:
            raise ValueError(
                f"{where}.sampler.{key} = {sampler_updates[key]:g}: it is set from {source} ({value:g}); "
                f"set {source} instead"
            )
    return config


def apply_overrides(config: GenerateConfig, overrides: list[str]) -> GenerateConfig:
    """Apply `key=value` overrides (`width=96`, `sampler.max_objects=2`, `sampler.speed=[0.5,3]`); values are YAML,
    with YAML 1.2 numbers as in scenes (`duration=5e-1` is a number)."""
    from aynamics.scene_text import load_yaml

    data: dict = {}
    for text in overrides:
        key, sep, raw = text.partition("=")
        if not sep or not key:
            raise ValueError(f"override {text!r}: must be key=value, e.g. sampler.max_objects=3")
        try:
            value = load_yaml(raw)
        except SceneError:
            raise ValueError(f"override {text!r}: value {raw!r} is not valid YAML") from None
        parts = key.split(".")
        node = data
        for k, p in enumerate(parts[:-1]):
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ValueError(f"override {text!r}: {'.'.join(parts[: k + 1])} is a value, not a group of keys")
        node[parts[-1]] = value
    return config_from_dict(data, config, where="override")


def load_config(path: str | os.PathLike) -> GenerateConfig:
    """A config from a YAML file (see conf/generate/default.yaml); a missing file raises FileNotFoundError.

    Raises:
        ValueError: the path is a folder or unreadable, or the file is not valid YAML or not a config.
    """
    from aynamics.scene_text import load_yaml

    if Path(path).is_dir():
        raise ValueError(f"--config {str(path)!r} is a folder: give a YAML file (see conf/generate/default.yaml)")
    try:
        with open(path, encoding="utf-8") as f:
            data = load_yaml(f.read()) or {}  # YAML 1.2 numbers, as in scenes: `duration: 5e-1` is a number
    except FileNotFoundError:
        raise
    except SceneError as e:
        raise ValueError(f"--config {str(path)!r}: invalid YAML: {e.problems[0].message}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"--config {str(path)!r}: cannot read: {getattr(e, 'strerror', None) or e}") from None
    return config_from_dict(data, where=str(path))


# --------------------------------------------------------------------------------------------
# One record
# --------------------------------------------------------------------------------------------
def split_of(seed: int, index: int, shares: tuple[float, float, float] = (0.8, 0.1, 0.1)) -> str:
    """The split of scene `index`: a hash of (seed, index), so independent of sharding and order."""
    digest = hashlib.sha256(f"{seed}:{index}".encode()).digest()
    u = int.from_bytes(digest[:8], "big") / 2**64
    return SPLITS[0] if u < shares[0] else SPLITS[1] if u < shares[0] + shares[1] else SPLITS[2]


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


SCENE_SUFFIXES = (".yaml", ".yml")
MAX_LISTED = 10  # problems of scene files named in one error


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


def sample_simulated(index: int, seed: int, config: GenerateConfig) -> tuple[Scene, Rollout, int]:
    """Scene `index` and its rollout; resampled (attempt 1, 2, ...) when placement fails or the simulation diverges.

    Raises:
        RuntimeError: every attempt failed (the reasons are listed).
    """
    reasons = []
    for attempt in range(config.max_attempts):
        rng = np.random.default_rng(smp.scene_seed(seed, index, attempt))
        try:
            scene = smp.sample_scene(rng, config.sampler)
        except RuntimeError as e:
            reasons.append(str(e))
            continue
        rollout = simulate(scene, config.sim)
        if rollout.valid:
            return scene, rollout, attempt
        reasons.append(str(rollout.reason))
    raise RuntimeError(f"scene {index} (seed {seed}): all {config.max_attempts} attempts failed: {'; '.join(reasons)}")


def appearance_seed(seed: int, index: int, attempt: int) -> int:
    """The seed of scene `index`'s randomised look (lights, textures): a function of (seed, index, attempt) alone."""
    return int(smp.scene_seed(seed, index, attempt).generate_state(1)[0])


def _png(image: np.ndarray) -> dict:
    return {"bytes": png_bytes(image), "path": None}


def _arr(x: np.ndarray) -> list:
    return np.asarray(x, np.float32).tolist()


def render_sampled(scene: Scene, rollout: Rollout, renderer: Renderer, config: GenerateConfig, seed: int) -> Frames:
    """The only OpenGL work of a record: RGB, segmentation and depth of the sampled video frames (`Frames`).

    The flow of sampled frame f to f + 1 needs the depth and segmentation at f and the poses at f and f + 1 only:
    frames f + 1 are not rendered (the record keeps no occlusion mask, the one thing they would add).
    """
    from aynamics.flow import sample_frames

    frames = sample_frames(len(rollout.t) - 1, config.stride)  # video frames 0..T-2
    return renderer.render(
        scene, rollout, seed=seed, textures_dir=config.textures_dir, backdrop=config.backdrop, states=frames
    )


def flow_images(frames: Frames, rollout: Rollout) -> tuple[np.ndarray, float]:
    """Colour-coded exact flow of each rendered frame f to f + 1 on one magnitude scale, and that scale (px).

    Returns:
        (F, H, W, 3) uint8 images (white where nothing moves) and the largest flow magnitude in pixels.
    """
    from aynamics import flow as flowlib

    flows = np.empty((*frames.segmentation.shape, 2), np.float32)  # (F, H, W, 2)
    for k, f in enumerate(frames.states):
        flows[k] = flowlib.motion_field(
            frames.depth[k],
            frames.segmentation[k],
            frames.camera,
            rollout.position[[f, f + 1]],
            rollout.orientation[[f, f + 1]],
            occlusion=False,
        )[0]
    on_object = frames.segmentation >= 0  # (F, H, W): the only pixels with flow (floor and sky are exactly zero)
    moving = flows[on_object]  # (P, 2)
    flow_max = float(np.hypot(moving[:, 0], moving[:, 1]).max()) if len(moving) else 0.0
    colours = np.full((*on_object.shape, 3), 255, np.uint8)  # zero flow is white
    colours[on_object] = flowlib.flow_to_color(moving, max_norm=flow_max)
    return colours, flow_max


def render_record_frames(scene: Scene, rollout: Rollout, renderer: Renderer, config: GenerateConfig, seed: int) -> dict:
    """RGB, segmentation and colour-coded exact flow (one magnitude scale per scene) of the sampled frames."""
    main = render_sampled(scene, rollout, renderer, config, seed)
    flow_color, flow_max = flow_images(main, rollout)
    return {
        "frames": main.states,
        "rgb": main.rgb,
        "segmentation": main.segmentation,
        "flow_color": flow_color,
        "flow_max": flow_max,
        "camera": main.camera,
    }


def make_record(index: int, seed: int, config: GenerateConfig, renderer, given: SceneFile | None = None) -> dict:
    """The full record of scene `index` (images PNG-encoded, ready for `datasets`): sampled, or the `given` scene
    file's (`scene_files`; its folder's split, else the hash split)."""
    if given is None:
        scene, rollout, attempt = sample_simulated(index, seed, config)
        split = split_of(seed, index, config.splits)
    else:
        scene, attempt = parse(given.text), 0
        rollout = simulate(scene, config.sim)
        if not rollout.valid:  # checked by scene_files before anything was written
            raise RuntimeError(f"{given.path}: the rollout is invalid: {rollout.reason}")
        split = given.split or split_of(seed, index, config.splits)
    scene_seed = appearance_seed(seed, index, attempt)
    fr = render_record_frames(scene, rollout, renderer, config, scene_seed)
    n = len(scene.objects)
    visible = rs.visibility(fr["segmentation"], n, config.min_pixels)
    times = rollout.t[fr["frames"]]
    inside = rs.centres_in_picture(fr["camera"], rollout.position[fr["frames"]])
    text = rs.reasoning_text(scene, rollout, visible, times, seed=scene_seed, in_picture=inside)
    yaml_text = dump(scene)
    cam = fr["camera"]
    radii = np.array([bounding_radius(o) for o in scene.objects])
    in_view = sphere_in_view(cam, rollout.position, radii)  # in the rendered view (the rollout's is 480×320)
    return {
        "index": index,
        "seed": seed,
        "attempt": attempt,
        "split": split,
        "scene_yaml": yaml_text,
        "reasoning": text,
        "target_answer": rs.answer_target(yaml_text),
        "target_think": rs.think_target(text, yaml_text),
        "rgb": [_png(im) for im in fr["rgb"]],
        "flow": [_png(im) for im in fr["flow_color"]],
        "flow_max": fr["flow_max"],
        "segmentation": [_png((s + 1).astype(np.uint8)) for s in fr["segmentation"]],
        "frame_indices": fr["frames"].tolist(),
        "frame_times": _arr(times),
        "states": {
            "names": list(rollout.names),
            "t": _arr(rollout.t),
            "position": _arr(rollout.position),
            "orientation": _arr(rollout.orientation),
            "linear_velocity": _arr(rollout.linear_velocity),
            "angular_velocity": _arr(rollout.angular_velocity),
            "in_view": in_view.tolist(),
            "visible": visible.tolist(),
            "rest_time": list(rollout.rest_time),
        },
        "contacts": [{"a": c.a, "b": c.b, "start": c.start, "end": c.end} for c in rollout.contacts],
        "camera": {
            "fovy": scene.camera.fovy,
            "orientation": scene.camera.orientation,
            "position": list(scene.camera.position),
            "width": cam.width,
            "height": cam.height,
            "K": cam.K.tolist(),
            "R": cam.R.tolist(),
            "t": cam.t.tolist(),
        },
        "num_objects": n,
        "shapes": list(scene.structure),
        "has_collision": any(c.b != "floor" for c in rollout.contacts),
    }


_WORKER: dict = {}


def _worker_init(config: GenerateConfig) -> None:
    from aynamics.render import Renderer

    _WORKER["renderer"] = Renderer(config.width, config.height)
    _WORKER["config"] = config


def _worker_record(job: tuple[int, int, SceneFile | None]) -> dict:
    index, seed, given = job
    return make_record(index, seed, _WORKER["config"], _WORKER["renderer"], given)


def _records(jobs: list[tuple[int, int, SceneFile | None]], config: GenerateConfig) -> Iterator[dict]:
    """Records of the jobs in order, made in `config.workers` processes (or here when 0)."""
    if not jobs:
        return
    if config.workers == 0:
        _worker_init(config)
        try:
            yield from map(_worker_record, jobs)
        finally:
            _WORKER.pop("renderer").close()
        return
    ctx = mp.get_context("spawn")  # a fresh interpreter per worker: no OpenGL state crosses a fork
    with ctx.Pool(min(config.workers, len(jobs)), initializer=_worker_init, initargs=(config,)) as pool:
        yield from pool.imap(_worker_record, jobs, chunksize=1)


def generate(
    out_dir: str | os.PathLike,
    num: int,
    seed: int = 0,
    config: GenerateConfig | None = None,
    shard: int = 0,
    num_shards: int = 1,
    progress: bool = True,
    scenes: Sequence[SceneFile] | None = None,
) -> Path | None:
    """Make this shard's missing chunks of a run; assemble the DatasetDict when every chunk is on disk.

    With `scenes` (`scene_files`: your own scenes) record i is made from scenes[i] instead of a sampled scene, and
    `num` must be their number.

    Returns:
        The data set folder (`datasets.load_from_disk(path)`), or None while other shards' chunks are missing.
    """
    from tqdm.auto import tqdm

    config = config or GenerateConfig()
    if num < 1 or seed < 0:
        raise ValueError(f"num = {num}, seed = {seed}: need num >= 1 and seed >= 0")
    if scenes is not None and len(scenes) != num:
        raise ValueError(f"num = {num} with {len(scenes)} scene files: must be their number")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file, not a folder")
    if out.is_dir() and not (out / MANIFEST).is_file():  # not a run of ours: assembly replaces train/ test/ ...
        other = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
        if other:
            raise ValueError(
                f"--out {str(out)!r} holds other files ({other[0]!r}, ...) and no {MANIFEST}: give a new or empty "
                "folder, or one an earlier generate wrote"
            )
    mine = shard_chunks(num, config.chunk_size, shard, num_shards)  # checked before anything is written
    settings = config.to_json()
    manifest = {"format": FORMAT_VERSION, "num": num, "seed": seed, "config": settings}
    check_scene_run(out, scenes)
    if scenes is not None:
        warn_repeated_scenes(
            scenes, seed, config
        )  # the scenes decide the records (a changed or reordered one is another run), not the sampler
        settings.pop("sampler")
        settings["scenes"] = [{"sha256": f.sha256, "split": f.split} for f in scenes]
        manifest["scene_files"] = [f.path for f in scenes]  # for the reader; not compared on a resume
    with claim_shard(out, manifest, shard, num_shards):  # a second writer of these chunks is refused here
        (out / "chunks").mkdir(exist_ok=True)
        ranges = chunk_ranges(num, config.chunk_size)
        remove_partial_chunks(out, mine)  # leftovers of a killed run of this shard
        todo = [c for c in mine if not chunk_dir(out, c).exists()]
        jobs = [(i, seed, None if scenes is None else scenes[i]) for c in todo for i in ranges[c]]
        bar = tqdm(
            total=sum(len(ranges[c]) for c in mine),
            initial=sum(len(ranges[c]) for c in mine) - len(jobs),
            unit="scene",
            desc=f"generate shard {shard}/{num_shards}",
            disable=not progress,
            smoothing=0.1,
        )
        pending: list[dict] = []
        chunks = iter(todo)
        current = next(chunks, None)
        with bar:
            for record in _records(jobs, config):
                pending.append(record)
                bar.update(1)
                if current is not None and len(pending) == len(ranges[current]):
                    write_chunk(out, current, pending)
                    pending, current = [], next(chunks, None)
        if all(chunk_dir(out, c).exists() for c in range(len(ranges))):
            return assemble(out)
    return None


def generate_dataset(
    out_dir: str | os.PathLike, num: int, seed: int = 0, config: GenerateConfig | None = None, progress: bool = False
) -> Path:
    """Generate a whole data set in one call (e.g. a tiny one for tests) and return its folder."""
    path = generate(out_dir, num, seed, config, progress=progress)
    assert path is not None  # one shard makes every chunk
    return path


# --------------------------------------------------------------------------------------------
# Command line: aynamics generate
# --------------------------------------------------------------------------------------------
def add_generate_parser(sub) -> None:
    """Register `aynamics generate` on the CLI's subparsers."""
    p = sub.add_parser(
        "generate",
        help="generate the synthetic data set (scenes, frames, flow, masks, states, reasoning) with HF datasets",
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--num", type=int, help="number of sampled scenes of the whole run (all shards)")
    what.add_argument(
        "--scenes",
        nargs="+",
        metavar="PATH",
        help="your own scenes instead: YAML files or folders of them (a folder's train/, validation/, test/ "
        "subfolders set the split; other files take the hash split)",
    )
    p.add_argument("--out", required=True, help="output folder (chunks, then the DatasetDict for load_from_disk)")
    p.add_argument("--seed", type=int, default=0, help="global seed; scene i depends only on (seed, i) (default 0)")
    p.add_argument("--shard", type=int, default=0, help="this shard's number k in [0, n) (default 0)")
    p.add_argument("--num-shards", type=int, default=1, help="number of shards n (default 1)")
    p.add_argument("--config", help="YAML config file (see conf/generate/default.yaml)")
    p.add_argument("--workers", type=int, help="rendering processes (default: config, 2)")
    p.add_argument("--assemble", nargs="*", metavar="DIR", help="only assemble: join chunks of --out or of DIRs")
    p.add_argument("--in-context", action="store_true", help="also write in_context/ (3 prompt examples)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", help="config overrides key=value, e.g. width=96 sampler.max_objects=2")
    p.set_defaults(run=run_generate)


def run_generate(args) -> int:
    """Run `aynamics generate` (errors become `UsageError`: exit 2 with one message)."""
    from aynamics.cli import UsageError, missing_file_message, warnings_as_lines

    try:
        config = load_config(args.config) if args.config else GenerateConfig()
        config = apply_overrides(config, args.overrides)
        if args.workers is not None:
            config = dataclasses.replace(config, workers=args.workers)
        if args.assemble is not None:  # the chunks hold the records: the scene files are not read again
            path = assemble(args.out, args.assemble or None)
        else:
            scenes = None if args.scenes is None else scene_files(args.scenes, config)
            num = len(scenes) if scenes is not None else args.num
            with warnings_as_lines("generate", "--scenes: "):  # the same scene in two splits
                path = generate(args.out, num, args.seed, config, args.shard, args.num_shards, not args.quiet, scenes)
        if path is None:
            which = f"--num {args.num}" if args.scenes is None else "--scenes " + shlex.join(args.scenes)
            print(f"shard {args.shard}/{args.num_shards} done; the data set is assembled by the last shard to finish")
            print(f"(or run: aynamics generate {which} --out {shlex.quote(args.out)} --assemble)")
            return 0
        if args.in_context:
            from aynamics.incontext import write_in_context

            print(f"in-context examples: {write_in_context(path)}")
        print(f"data set: {path} (datasets.load_from_disk)")
    except FileNotFoundError as e:
        raise UsageError(f"generate: {missing_file_message(e)}") from None
    except (ValueError, RuntimeError) as e:
        raise UsageError(f"generate: {e}") from None
    return 0
