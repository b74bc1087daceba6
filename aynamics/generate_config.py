"""The dataset generator's settings (`GenerateConfig`): from a YAML file (`--config`, conf/generate/default.yaml)
and Hydra-style `key=value` overrides (`width=112 sampler.max_objects=2`), as plain dataclasses; the package never
imports Hydra. Values are YAML 1.2 (`duration=5e-1` is a number), and a wrong key or value is named.

    config = apply_overrides(load_config("conf/generate/default.yaml"), ["width=112", "height=80"])
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path

from aynamics import sampler as smp
from aynamics.scene import SceneError
from aynamics.simulate import PHYSICS_VERSION, SimConfig

# Raise when the same rollout gets other labels (rest_time, reasoning text): a run whose chunks were labelled by
# other code is neither resumed nor assembled with this one (absent: 1). 2: rest from the frame's mean speed (a
# resting object's contact jitter is not motion), occlusion told apart from leaving the view, heights above the
# floor plane. 3: a scene whose rollout gains energy with no push (an upright cylinder launched by MuJoCo's
# plane-cylinder contact, `simulate.unpushed_energy_gain`) is resampled; an object in flight (touching nothing in
# the frame) is moving at its instant speed, not at rest at the top of a bounce.
LABELS_VERSION = 3
OPTIONAL_INTEGERS = ("substeps",)  # config fields that are an integer or None (the others None by default: paths)


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


def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


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
