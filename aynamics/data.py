"""The generated data set as SFT batches: a LightningDataModule (its loaders: `loaders.py`; the records its scene
evaluation scores: `eval_records.py`; the "average scene" baseline: `average_scene.py`, re-exported).

The data set is the folder written by `aynamics generate` (`datasets.load_from_disk`: train / validation / test,
columns `scene_yaml`, `target_answer`, `target_think`, `rgb` and `flow` (lists of PIL frames), ...). One example
is the chat prompt (system prompt, optional in-context scenes, the frames as images or one video, the instruction)
followed by the response; labels cover only the response (see `aynamics.processor.build_sft_example`).

    dm = SceneDataModule("data/generated/tiny", processor_path=TINY_ASSET_DIR, target="think_answer")
    dm.setup("fit"); batch = next(iter(dm.train_dataloader()))
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import ConcatDataset, DataLoader, Dataset

from aynamics import lm
from aynamics import scene as scene_lib
from aynamics.average_scene import mean_scene as mean_scene  # the baseline: the README named data.mean_scene
from aynamics.average_scene import mean_scene_of_split as mean_scene_of_split
from aynamics.batching import collate
from aynamics.eval_records import frames_of, readable_eval_record
from aynamics.loaders import (  # noqa: F401 - re-exported: the loaders the data module builds
    EvalShard,
    ResumableLoader,
    ResumableSampler,
    eval_shard,
    init_worker,
    loader_options,
    loader_workers,
    real_rows,
    resumable_loader,
)
from aynamics.processor import IGNORE_INDEX, build_sft_example, sample_frames, type_tokens
from aynamics.visual_targets import token_targets

SPLITS = ("train", "validation", "test")


def load_splits(path: str | Path, what: str = "data.dir", require_train: bool = True):
    """`datasets.load_from_disk(path)` with a clear error for a missing or wrong folder, naming it as `what` (the
    config key or command-line option that gave it); with `require_train`, it must have a train split."""
    from datasets import DatasetDict, load_from_disk

    path = Path(path)
    if not (path / "dataset_dict.json").is_file():
        if path.is_dir() and (path.parent / "dataset_dict.json").is_file():  # one split's folder: the hint below
            # would be refused (a file beside dataset_dict.json, that file itself, or a missing name is no split)
            why = f"is the {path.name!r} split of the data set {str(path.parent)!r}: give that folder"
        elif path.is_file() or (path.is_dir() and any(path.iterdir())):  # generate refuses to write there
            kind = "a file" if path.is_file() else "a folder holding no data set (no dataset_dict.json)"
            why = f"is {kind}: point {what} at a data set folder (`aynamics generate --out` writes one)"
        else:
            why = (
                f"holds no data set (no dataset_dict.json); make one with `aynamics generate --num 12 --out {path} "
                f"width=64 height=48`, or point {what} at one (`make train` writes data/generated/make_train_plain)"
            )
        raise FileNotFoundError(f"{what} = {str(path)!r} {why}")
    try:
        dd = load_from_disk(str(path))
    except (OSError, ValueError, IndexError) as e:  # truncated or foreign .arrow files, a broken dataset_info.json,
        # a split saved with no shard at all (IndexError), ...
        hint = "" if isinstance(e, PermissionError) else "; generate it again"
        raise ValueError(
            f"{what} = {str(path)!r}: the data set cannot be read ({type(e).__name__}: {e}){hint}"
        ) from None
    if not isinstance(dd, DatasetDict):
        raise ValueError(f"{what} = {str(path)!r}: expected a DatasetDict of splits, got a {type(dd).__name__}")
    if require_train and "train" not in dd:
        raise ValueError(f"{what} = {str(path)!r}: the data set has no 'train' split (splits: {list(dd)})")
    return dd


def with_clock(prompt: lm.PromptSpec, path: str | Path, split) -> lm.PromptSpec:
    """`prompt` with the frame rate and clip frames of a generated data set's videos (its manifest's `config.fps`,
    the first record's `frame_indices`): what `aynamics predict` picks from a user's video."""
    import dataclasses
    import warnings

    from aynamics.dataset_store import dataset_fps, stale_physics

    stale = stale_physics(path)
    if stale:
        warnings.warn(stale, stacklevel=2)
    fps = float(dataset_fps(path) or prompt.fps)  # a data set made otherwise: the generator's rate
    frames = used_columns(split, ("frame_indices",))[0].get("frame_indices") if len(split) else None
    return dataclasses.replace(prompt, fps=fps, clip_frames=tuple(frames) if frames else prompt.clip_frames)


def used_columns(split, names: tuple[str, ...]):
    """`split` with only the columns `names` that it has: reading a record then decodes only those (the frame
    lists and the states of the columns left out would be decoded for nothing: 3-5 ms per record at 112×80)."""
    return split.select_columns([c for c in names if c in split.column_names])


class SFTDataset(Dataset):
    """Tokenised SFT examples of one split, built on access (PNG decode + processor: ~ms per record)."""

    def __init__(
        self,
        split,
        processor,
        prompt: lm.PromptSpec,
        limit: int | None = None,
        decimals: int | None = None,
        cache: bool = False,
        visual_targets: bool = False,
        object_names: bool = True,
        type_weight: float = 1.0,
        objects_last: bool = False,
    ) -> None:
        self.split = split if limit is None else split.select(range(min(limit, len(split))))
        used = ("index", "scene_yaml", "target_answer", "target_think", prompt.modality)
        self._rows = used_columns(self.split, used + (("segmentation", "shapes") if visual_targets else ()))
        self.processor = processor
        self.prompt = prompt
        self.decimals = decimals
        self.visual_targets = visual_targets
        self.object_names = object_names
        self.type_weight = type_weight
        self.objects_last = objects_last
        self._cache: dict[int, dict[str, torch.Tensor]] | None = {} if cache else None

    def __len__(self) -> int:
        return len(self.split)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        i = int(i)
        if self._cache is None:
            return self._build(i)
        if i not in self._cache:  # the same tensors every epoch: build once (a worker keeps its own copy)
            self._cache[i] = self._build(i)
        return self._cache[i]

    def _build(self, i: int) -> dict[str, torch.Tensor]:
        record = self._rows[i]
        p = self.prompt
        response = lm.response_text(record, p.target, self.decimals, self.object_names, self.objects_last)
        ex = build_sft_example(
            self.processor,
            frames_of(record, p.modality),
            response,
            system_prompt=p.system_prompt,
            user_prompt=p.user_prompt,
            examples=p.examples,
            as_video=p.as_video,
        )
        types = type_tokens(self.processor, response)
        ex["type_tokens"] = torch.cat([torch.zeros(len(ex["input_ids"]) - len(types), dtype=torch.bool), types])
        if self.type_weight != 1.0:  # 0 on the prompt (no loss there anyway), 1 or type_weight on the response
            ex["loss_weights"] = (ex["labels"] != IGNORE_INDEX) * (1.0 + (self.type_weight - 1.0) * ex["type_tokens"])
        if self.visual_targets:  # flow frame f is the motion from frame f: the same masks for both modalities
            masks = sample_frames(record["segmentation"], self.processor.num_frames)
            grid = ex["video_grid_thw"] if p.as_video else ex["image_grid_thw"]
            ex["visual_targets"] = _token_targets(self.processor, masks, record["shapes"], grid, p.as_video)
        return ex


def _token_targets(processor, masks: list, shapes: list[str], grid: torch.Tensor, as_video: bool) -> torch.Tensor:
    ip = processor.image_processor
    return token_targets(
        masks,
        shapes,
        grid,
        as_video=as_video,
        patch_size=ip.patch_size,
        merge_size=ip.merge_size,
        temporal_patch_size=ip.temporal_patch_size,
    )


def frame_windows(n_stored: int, num_frames: int) -> list[tuple[int, ...]]:
    """Other choices of `num_frames` frames than the model's (evenly spaced, first to last stored frame):
    evenly spaced over every window [a, b] of the stored frames that spans at least half of them, ends included.

    With 10 stored frames and 2 per clip: (0, 5), (0, 6), ..., (4, 9) — 14 pairs, (0, 9) left out.
    """
    if n_stored < 1 or num_frames < 1:
        raise ValueError(f"n_stored = {n_stored}, num_frames = {num_frames}: both must be >= 1")
    model = tuple(sample_frames(range(n_stored), num_frames))  # the processor's own choice
    out: list[tuple[int, ...]] = []
    for a in range(n_stored):
        for b in range(a, n_stored):
            w = tuple(np.linspace(a, b, num_frames).round().astype(int).tolist())
            if 2 * (b - a) >= n_stored - 1 and w != model and w not in out:
                out.append(w)
    return out


class WarmupViews(Dataset):
    """Visual-only examples for the vision tower's warm-up: each training scene seen in `views` other choices of
    its stored frames (`frame_windows`, drawn per scene from (seed, index)), with their `visual_targets`.

    The objects stand elsewhere in those frames (some leave the view, the targets follow the masks), so a tower
    learnt from zero on ~1 200 scenes sees more layouts without new scenes being generated. Measured (`make
    train` data and model, 4 000 warm-up steps): the frame count implied on the held-out scenes rose from
    0.37 to 0.49 with 4 views per scene (README: status). Examples hold pixels, grid and targets only; with
    `cache` they are built once (~5 ms each at 112×80).
    """

    def __init__(self, split, processor, prompt: lm.PromptSpec, views: int, seed: int = 0, cache: bool = False):
        self.split = used_columns(split, (prompt.modality, "segmentation", "shapes"))
        self.processor, self.prompt, self.views, self.seed = processor, prompt, views, seed
        n_stored = len(self.split[0][prompt.modality]) if len(split) else 0
        self.windows = frame_windows(n_stored, prompt.num_frames) if n_stored else []
        if not 1 <= views <= len(self.windows):
            raise ValueError(
                f"data.warmup_views = {views}: must be in [1, {len(self.windows)}] for {n_stored} stored frames "
                f"and num_frames = {prompt.num_frames}"
            )
        self._cache: dict[int, dict[str, torch.Tensor]] | None = {} if cache else None

    def __len__(self) -> int:
        return len(self.split) * self.views

    def window(self, i: int) -> tuple[int, ...]:
        """The frames of example `i`: view `i % views` of scene `i // views`."""
        scene, view = divmod(int(i), self.views)
        rng = np.random.default_rng([self.seed, scene])
        return self.windows[rng.permutation(len(self.windows))[view]]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        i = int(i)
        if self._cache is not None and i in self._cache:
            return self._cache[i]
        record, w, p = self.split[i // self.views], self.window(i), self.prompt
        stored = frames_of(record, p.modality)
        frames, masks = [stored[f] for f in w], [record["segmentation"][f] for f in w]
        if p.as_video:
            v = self.processor.process_video(frames)
            ex = {"pixel_values_videos": v["pixel_values_videos"], "video_grid_thw": v["video_grid_thw"]}
        else:
            ex = self.processor.process_images(frames)
        grid = ex["video_grid_thw"] if p.as_video else ex["image_grid_thw"]
        ex["visual_targets"] = _token_targets(self.processor, masks, record["shapes"], grid, p.as_video)
        if self._cache is not None:
            self._cache[i] = ex
        return ex


class SceneDataModule(L.LightningDataModule):
    """Train / validation / test batches of a generated data set.

    Args:
        dir: Folder of the data set (`datasets.load_from_disk`).
        processor_path: Tokenizer + image processor (the tiny asset or the pretrained checkpoint's folder).
        target: "answer" or "think_answer" (reasoning first).
        modality: "rgb" or "flow" frames.
        as_video: Frames as one video (half the visual tokens) instead of separate images.
        num_frames: Frames per clip given to the model (evenly spaced, of the 10 stored).
        min_pixels, max_pixels: Pixel bounds per frame after the processor's resize (None: processor's default).
        num_examples: In-context examples: the YAML of this many training scenes put before the frames.
        batch_size: Training examples per step per process.
        eval_batch_size: Examples per validation step (default batch_size).
        num_workers: DataLoader worker processes (0: in the training process; None: 0 on the CPU, up to 4 per
            process on GPUs, `loader_workers`).
        seed: Seed of the shuffling (the order is a function of seed and epoch only).
        limit_train, limit_val: Use only the first examples of the split (None: all).
        decimals: Round the numbers of the target YAML to this many decimals (None: the stored 4).
        cache: Keep every built example (decoded frames + tokens) in memory after its first use: later epochs
            skip PNG decoding and the processor (~15 ms per example at 112×80; memory ~0.5 MB per example there).
        group_by_length: Batch scenes with similar object counts together (less padding; see ResumableSampler).
        visual_targets: Add per-visual-token targets from the segmentation to every example (`visual_targets`:
            objects and shapes each merged token covers), for `SFTModule(vision_aux_weight > 0)`.
        object_names: Write the objects' names in the target YAML. False leaves out the default names
            (`box_0`, `box_1`, ...), which the parser fills back in: the same scene, and one thing less for a
            small model to get wrong (a repeated name makes the scene invalid).
        type_weight: Training-loss weight of the tokens that spell each entry's type (`processor.type_tokens`):
            > 1 stresses the few choices that set the object count and shapes. 1: no weights (plain mean).
        objects_last: Write the camera and gravity before the objects in the target YAML and the in-context
            examples (`scene.dump`): "one more object or the end" is then one token, not "camera" weighed
            against each shape, which greedy decoding picks too early.
        warmup_views: For the vision tower's warm-up (`SFTModule(vision_warmup_steps > 0)`), add this many
            other frame choices of every training scene (`WarmupViews`); 0: the training examples only.
    """

    def __init__(
        self,
        dir: str,
        processor_path: str,
        target: str = "answer",
        modality: str = "rgb",
        as_video: bool = False,
        num_frames: int = 4,
        min_pixels: int | None = None,
        max_pixels: int | None = None,
        num_examples: int = 0,
        batch_size: int = 4,
        eval_batch_size: int | None = None,
        num_workers: int | None = None,
        seed: int = 0,
        limit_train: int | None = None,
        limit_val: int | None = None,
        decimals: int | None = None,
        cache: bool = False,
        group_by_length: bool = False,
        visual_targets: bool = False,
        object_names: bool = True,
        type_weight: float = 1.0,
        objects_last: bool = False,
        warmup_views: int = 0,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        if warmup_views < 0 or (warmup_views and not visual_targets):
            raise ValueError(
                f"data.warmup_views = {warmup_views}: must be >= 0, and > 0 only with data.visual_targets=true"
            )
        self.warmup_views = warmup_views
        if batch_size < 1 or num_examples < 0 or (num_workers is not None and num_workers < 0):
            raise ValueError(
                f"batch_size = {batch_size}, num_examples = {num_examples}, num_workers = {num_workers}: "
                "need batch_size >= 1, num_examples >= 0, num_workers >= 0 (or null: by device)"
            )
        for key, value in (
            ("eval_batch_size", eval_batch_size),
            ("limit_train", limit_train),
            ("limit_val", limit_val),
        ):
            if value is not None and value < 1:
                raise ValueError(f"data.{key} = {value}: must be >= 1, or null for the default (all / batch_size)")
        self.dir, self.processor_path = str(dir), str(processor_path)
        self.batch_size, self.eval_batch_size = batch_size, eval_batch_size or batch_size
        self.num_workers, self.seed = num_workers, seed
        self.limit_train, self.limit_val = limit_train, limit_val
        self.num_examples = num_examples
        if decimals is not None and not 0 <= decimals <= scene_lib.DECIMALS:
            raise ValueError(f"decimals = {decimals}: must be in [0, {scene_lib.DECIMALS}] or null")
        self.decimals, self.cache, self.group_by_length = decimals, cache, group_by_length
        self.visual_targets, self.object_names = visual_targets, object_names
        if not (type_weight > 0 and math.isfinite(type_weight)):
            raise ValueError(f"type_weight = {type_weight}: must be a finite number > 0")
        self.type_weight, self.objects_last = type_weight, objects_last
        self.prompt = lm.PromptSpec(target, modality, as_video, num_frames, min_pixels, max_pixels)  # checks values
        self.splits = None
        self.processor = None
        self._datasets: dict[tuple[str, int | None], SFTDataset] = {}

    def setup(self, stage: str | None = None) -> None:
        if self.splits is not None:
            return
        self.splits = load_splits(self.dir)
        if len(self.splits["train"]) == 0:
            raise ValueError(f"data.dir = {self.dir!r}: the train split is empty")
        self.prompt = with_clock(self.prompt, self.dir, self.splits["train"])  # no image decoded
        n_stored = len(self.prompt.clip_frames)  # the frames a record stores
        if self.prompt.num_frames > n_stored:
            raise ValueError(
                f"data.num_frames = {self.prompt.num_frames}: the scenes in data.dir = {self.dir!r} store {n_stored} "
                f"frames each; choose at most {n_stored}"
            )
        if self.num_examples:
            stored = self.splits["train"].select(range(min(self.num_examples, len(self.splits["train"]))))["scene_yaml"]
            examples = tuple(lm.scene_text(y, self.decimals, self.object_names, self.objects_last) for y in stored)
            self.prompt = lm.PromptSpec(**{**self.prompt.__dict__, "examples": examples})
        self.processor = lm.prompt_processor(self.processor_path, self.prompt)  # with the data's clock

    @property
    def pad_token_id(self) -> int:
        return self.processor.tokenizer.pad_token_id

    def _collate(self, examples: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
        return collate(examples, self.pad_token_id)

    def dataset(self, split: str, limit: int | None = None) -> SFTDataset:
        """The examples of `split` (the same object on every call when `cache`: built examples are shared)."""
        if split not in self.splits or len(self.splits[split]) == 0:
            raise ValueError(
                f"data.dir = {self.dir!r} has no {split!r} examples (splits: {dict(self.splits.num_rows)})"
            )
        if (split, limit) in self._datasets:
            return self._datasets[(split, limit)]
        ds = SFTDataset(
            self.splits[split],
            self.processor,
            self.prompt,
            limit,
            decimals=self.decimals,
            cache=self.cache,
            visual_targets=self.visual_targets,
            object_names=self.object_names,
            type_weight=self.type_weight,
            objects_last=self.objects_last,
        )
        if self.cache:
            self._datasets[(split, limit)] = ds
        return ds

    def warmup_dataset(self) -> Dataset:
        """What the vision warm-up trains on: the training examples, plus `warmup_views` other frame choices of
        each training scene."""
        train = self.dataset("train", self.limit_train)
        if not self.warmup_views:
            return train
        views = WarmupViews(train.split, self.processor, self.prompt, self.warmup_views, self.seed, self.cache)
        return ConcatDataset([train, views])

    def train_dataloader(self) -> DataLoader:
        ds = self.dataset("train", self.limit_train)
        lengths = list(ds.split["num_objects"]) if self.group_by_length else None  # objects set the target length
        return resumable_loader(
            ds,
            self.trainer,
            batch_size=self.batch_size,
            seed=self.seed,
            lengths=lengths,
            collate_fn=self._collate,
            num_workers=self.num_workers,
            cache=self.cache,
            window_weights=True,  # the step's loss is the mean over all its tokens (SFTModule.training_step)
        )

    def _eval_loader(self, split: str) -> DataLoader:
        """This process's share of the split (`eval_shard`: all of it for one process)."""
        ds = self.dataset(split, self.limit_val)
        return DataLoader(
            ds,
            batch_size=self.eval_batch_size,
            sampler=eval_shard(len(ds), self.trainer),
            collate_fn=self._collate,
            # its own generator: each iterator draws a worker base seed, from torch's global RNG without one,
            # which moved training's random state (LoRA dropout) at every validation, and a resumed run skips
            # the validation of the step it resumes from
            generator=torch.Generator().manual_seed(self.seed),
            **loader_options(self.num_workers, self.trainer, self.cache),
        )

    def val_dataloader(self) -> DataLoader | list:
        """The validation loader; none (Lightning then skips validation, with a warning) when the data set holds no
        validation scene: e.g. a dozen generated scenes can all fall into the train split."""
        if "validation" not in self.splits or len(self.splits["validation"]) == 0:
            warnings.warn(
                f"data.dir = {self.dir!r} holds no validation scenes (splits: {dict(self.splits.num_rows)}): "
                "training without validation or scene evaluation; generate more scenes for them",
                stacklevel=2,
            )
            return []
        return self._eval_loader("validation")

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader("test")

    def eval_records(self, split: str = "validation", n: int = 8) -> list[dict[str, Any]]:
        """A fixed subset for generation: the first `n` records' prompt (unbatched), scene text and the frames'
        (width, height) in pixels (`size`: the view the scene is scored in). A record whose frames cannot be read is
        left out with a warning (`readable_eval_record`)."""
        columns = ("index", "scene_yaml", "frame_indices", self.prompt.modality)  # decode only these
        ds, where = used_columns(self.splits[split], columns), f"{split} records of data.dir = {self.dir!r}"
        from aynamics.dataset_store import dataset_substeps

        steps = dataset_substeps(self.dir)
        found = (readable_eval_record(ds, i, self.processor, self.prompt, where, steps) for i in range(min(n, len(ds))))
        return [r for r in found if r is not None]
