"""The PRO stage's data: unlabeled videos (online mode) or a stored preference data set (offline mode, written by
`aynamics preferences`, read by `preference_data.py`) for training; held-out videos for validation. The prompt
settings are the SFT stage's, on the videos' clock.

    data = ProDataModule("data/synth", processor_path=TINY_ASSET_DIR, batch_size=1)   # conf/data/unlabeled.yaml

`pro.ProModule` trains on it (and `pro` re-exports it). `has_flow` and `without_flow` say whether videos carry the
observed flow that EPE rewards and validation's EPE columns need.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from collections.abc import Sequence

import lightning as L
import torch
from torch.utils.data import DataLoader

from aynamics import lm
from aynamics.unlabeled import GeneratedVideos, UnlabeledVideo, collate_videos, is_generated, open_videos


def has_flow(videos: Sequence[UnlabeledVideo]) -> bool:
    """Whether every video has observed flow (validation's EPE columns need it): a generated data set's flow column
    read (`use_flow`), or each folder's flow.npy."""
    if isinstance(videos, GeneratedVideos):
        return videos.use_flow and "flow" in videos.ds.column_names
    return all(v.observation.flow is not None for v in videos)


def without_flow(videos: Sequence[UnlabeledVideo]) -> str | None:
    """The key of the first video without observed flow (an EPE reward cannot score it), or None: a generated data
    set's flow column read (`use_flow`), or each folder's flow.npy."""
    if isinstance(videos, GeneratedVideos):
        return None if has_flow(videos) else "(every record: data.use_flow = false or no flow column)"
    return next((v.key for v in videos if v.observation.flow is None), None)


@contextlib.contextmanager
def _named(key: str):
    """Errors of the reader inside put after the config key that named its path ("stage.preferences_dir: ...")."""
    try:
        yield
    except FileNotFoundError as e:
        raise FileNotFoundError(e.errno, f"{key}: {e.strerror or e}", e.filename) from None
    except ValueError as e:
        raise ValueError(f"{key}: {e}") from None


class ProDataModule(L.LightningDataModule):
    """Unlabeled videos (online) or a stored preference data set (offline) for training; videos for validation.

    The prompt settings are the SFT data module's (`data/default.yaml`), so an SFT adapter sees what it learnt on.

    Args:
        dir: A generated data set (its labels are never read) or a folder of video folders.
        processor_path: Tokenizer + image processor (filled in by train.py from the model).
        target: "answer" or "think_answer": the instruction of the prompt.
        modality: "rgb" or "flow": the images the model sees.
        as_video, num_frames, min_pixels, max_pixels: How the frames are given (see `lm.PromptSpec`).
        preferences_dir: The offline preference data set (`aynamics preferences`); None in online mode.
        train_split, val_split: Splits of a generated data set (validation falls back to the first training videos).
        val_dir: Held-out videos for validation (a generated data set, whose `val_split` is read, or a folder of
            video folders). A folder of video folders as `dir` has no splits: without `val_dir` its first videos,
            trained on, are validated on too (with a warning).
        batch_size: Videos (online) or preference rows (offline) per step per process.
        limit_train, limit_val: Keep only the first videos of each split (None: all).
        use_flow: Decode the observed flow (needed for EPE rewards and the EPE columns of validation).
        num_workers: DataLoader workers (0: in the training process; None: by device, `data.loader_workers`).
        seed: Shuffling seed.
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
        preferences_dir: str | None = None,
        train_split: str = "train",
        val_split: str = "validation",
        val_dir: str | None = None,
        batch_size: int = 1,
        limit_train: int | None = None,
        limit_val: int | None = 4,
        use_flow: bool = True,
        num_workers: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if batch_size < 1 or (num_workers is not None and num_workers < 0):
            raise ValueError(f"batch_size = {batch_size}, num_workers = {num_workers}: need >= 1 and >= 0 (or null)")
        self.save_hyperparameters()
        self.prompt = lm.PromptSpec(target, modality, as_video, num_frames, min_pixels, max_pixels)  # checks values
        self.processor = None

    def setup(self, stage: str | None = None) -> None:
        if self.processor is not None:
            return
        hp = self.hparams
        # video folders: the images at the clip's times on each video's clock (the default clip: 0 to 0.9 s)
        kw = {"inputs": hp.modality, "use_flow": hp.use_flow, "clip_times": self.prompt.frame_times}
        if hp.preferences_dir is not None:
            from aynamics.preference_data import load_preferences, stored_clock

            with _named("stage.preferences_dir"):
                self.train_set = load_preferences(hp.preferences_dir)
            clock = stored_clock(hp.preferences_dir)  # the clock the rows were sampled on, as online mode would
            if clock is not None:
                self.prompt = dataclasses.replace(self.prompt, **clock)
            elif is_generated(hp.dir):  # written before the clock was recorded: data.dir's
                from aynamics.data import with_clock

                ref = open_videos(hp.dir, hp.train_split, limit=1, **kw)
                self.prompt = with_clock(self.prompt, hp.dir, ref.ds)
        else:
            with _named("data.dir"):  # a preference set given as data.dir: "columns [...] are missing"
                self.train_set = open_videos(hp.dir, hp.train_split, limit=hp.limit_train, **kw)
            if isinstance(self.train_set, GeneratedVideos):  # video folders: every third of 30 frames, the default
                from aynamics.data import with_clock

                self.prompt = with_clock(self.prompt, hp.dir, self.train_set.ds)
        self.processor = lm.prompt_processor(hp.processor_path, self.prompt)  # with the videos' clock
        if hp.preferences_dir is not None:
            from aynamics.preference_data import check_made_for

            check_made_for(hp.preferences_dir, self.prompt, self.processor.tokenizer)
        if len(self.train_set) == 0:
            raise ValueError(f"data.dir = {hp.dir!r}: split {hp.train_split!r} holds no videos")
        held_out = hp.val_dir if hp.val_dir is not None else hp.dir
        try:
            self.val_set = open_videos(held_out, hp.val_split, limit=hp.limit_val, **kw)
        except ValueError:  # a generated data set without that split; a folder's errors name what is wrong
            if not is_generated(held_out):
                raise
            self.val_set = []
        if hp.val_dir is not None and len(self.val_set) == 0:
            raise ValueError(f"data.val_dir = {hp.val_dir!r}: holds no videos (split {hp.val_split!r})")
        if hp.val_dir is None and (len(self.val_set) == 0 or not is_generated(hp.dir)):
            warnings.warn(
                f"PRO validation scores the first training videos of data.dir = {hp.dir!r} (no {hp.val_split!r} "
                "split there): give held-out videos as data.val_dir",
                stacklevel=2,
            )
            self.val_set = open_videos(hp.dir, hp.train_split, limit=hp.limit_val or 1, **kw)
        self.val_flow = has_flow(self.val_set)

    def transfer_batch_to_device(self, batch: list, device: torch.device, dataloader_idx: int) -> list:
        """Batches are videos / rows of PIL frames; the module builds the tensors and moves them itself."""
        return batch

    def train_dataloader(self) -> DataLoader:
        """Each process its own shard of the videos (or preference rows), resumable mid-epoch, as in SFT."""
        from aynamics.data import resumable_loader

        hp = self.hparams
        return resumable_loader(
            self.train_set,
            self.trainer,
            batch_size=hp.batch_size,
            seed=hp.seed,
            collate_fn=list,
            num_workers=hp.num_workers,
        )

    def val_dataloader(self) -> DataLoader:
        """This process's share of the validation videos (`data.eval_shard`: all of them for one process)."""
        from aynamics.data import eval_shard, loader_options

        hp = self.hparams
        return DataLoader(
            self.val_set,
            batch_size=hp.batch_size,
            sampler=eval_shard(len(self.val_set), self.trainer),
            collate_fn=collate_videos,
            # its own generator: an iterator draws a worker base seed, from torch's global RNG without one
            generator=torch.Generator().manual_seed(hp.seed),
            **loader_options(hp.num_workers, self.trainer),
        )
