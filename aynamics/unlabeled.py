"""Unlabeled videos for the PRO stage: the frames the model sees and the observation the simulator is scored against.

Two sources, neither of which needs (or reads) a scene label:

- a generated data set (`aynamics generate`, HF datasets on disk): per record the model sees `rgb` (or the `flow`
  colour images), and the observation is built from the stored `segmentation` masks and the decoded `flow` images
  only. `scene_yaml`, `reasoning`, `target_*`, `states` and `contacts` are dropped on loading, by design.
- a folder of frames plus segmentation masks: `frames/*.png` (the video frames in name order: every frame of the
  video, or exactly the sampled ones; for a flow-trained model `flow/*.png`, colour-wheel flow images, as
  `aynamics render` writes both) next to the scorer's observed-folder layout (`segmentation.npy` or
  `segmentation/*.png`, optional `flow.npy`, `occlusion.npy`, `meta.json`; see `aynamics.scorer`). A folder whose
  sub-folders hold that layout is a collection of videos.

    videos = load_generated("data/synth", split="train")          # list-like of UnlabeledVideo
    videos = load_folders("videos/")                               # one UnlabeledVideo per folder
    video.frames, video.observation                                 # PIL frames, observation.Observation
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from aynamics.dataset_store import dataset_fps, dataset_substeps
from aynamics.flow import decode_flow_colors, on_own_scale
from aynamics.observation import Observation, scoring_size
from aynamics.raycast import SampleGrid
from aynamics.simulate import FPS
from aynamics.video_io import IMAGE_SUFFIXES, image_files, read_image, same_size

# Columns of a generated record that the PRO stage may read; everything else (the labels) is dropped on loading.
OBSERVED_COLUMNS = ("index", "rgb", "flow", "flow_max", "segmentation", "frame_indices")
INPUTS = ("rgb", "flow")  # what the model sees: the RGB frames or the flow colour images


@dataclass(frozen=True)
class UnlabeledVideo:
    """One video without a label.

    Attributes:
        key: Where it came from (record index or folder name), for logs and the preference data set.
        frames: The images the model sees (PIL RGB), in time order.
        observation: The observed segmentation (and flow) at the scorer's resolution.
    """

    key: str
    frames: tuple[Image.Image, ...]
    observation: Observation


def observation_from_record(
    record: dict,
    *,
    width: int | None = None,
    height: int | None = None,
    use_flow: bool = True,
    fps: int = FPS,
    substeps: int | None = None,
) -> Observation:
    """The observation of a generated record from its `segmentation` masks (and `flow` images) alone, of a video
    at `fps` (the data set's rate: `dataset_store.dataset_fps`; candidates are simulated on that clock, with the
    data set's `substeps`: `dataset_store.dataset_substeps`, None: the default for `fps`).

    Masks hold object index + 1 (0 = floor and sky) at the sampled video frames `frame_indices`; flow images
    are decoded with the record's `flow_max` and scaled to the scorer's width. Object names are not used
    (candidates are matched to observed objects by overlap).

    Raises:
        ValueError: a missing column or masks / flow images of inconsistent size, naming the record.
    """
    key = record.get("index", "?")
    for col in ("segmentation", "frame_indices"):
        if col not in record or record[col] is None:
            raise ValueError(f"record {key}: column {col!r} is missing; an unlabeled video needs its masks")
    masks = [np.asarray(m) for m in record["segmentation"]]
    frames = np.asarray(record["frame_indices"], int)
    if len(masks) != len(frames) or not masks:
        raise ValueError(f"record {key}: {len(masks)} segmentation masks for frame_indices {frames.tolist()}")
    if len({m.shape for m in masks}) != 1 or masks[0].ndim != 2:
        raise ValueError(f"record {key}: segmentation masks must be grey images of one size, got {masks[0].shape}")
    full_h, full_w = masks[0].shape
    width, height = scoring_size(full_w, full_h, width, height)
    grid = SampleGrid.nearest(full_w, full_h, width, height)  # as `Observation.from_dir`
    rows, cols = grid.rows, grid.columns
    seg = np.stack(masks)[:, rows][:, :, cols].astype(np.int16) - 1  # (F, h, w), -1 background
    flow = None
    if use_flow and record.get("flow"):
        images = np.stack(
            [np.asarray(im.convert("RGB") if isinstance(im, Image.Image) else im) for im in record["flow"]]
        )
        if images.shape[:3] != (len(frames), full_h, full_w):
            raise ValueError(f"record {key}: flow images {images.shape[:3]} != masks {(len(frames), full_h, full_w)}")
        sub = images[:, rows][:, :, cols]
        flow = decode_flow_colors(sub, float(record.get("flow_max") or 0.0)) * (width / full_w)
    return Observation(seg, frames, width, height, flow, fps=fps, grid=grid, substeps=substeps)


def video_from_record(
    record: dict,
    *,
    inputs: str = "rgb",
    width: int | None = None,
    height: int | None = None,
    use_flow: bool = True,
    fps: int = FPS,
    substeps: int | None = None,
) -> UnlabeledVideo:
    """An `UnlabeledVideo` of a generated record of a video at `fps`; `inputs` picks the model's images ("rgb" or
    "flow")."""
    if inputs not in INPUTS:
        raise ValueError(f"inputs = {inputs!r}: must be one of {INPUTS}")
    images = record.get(inputs)
    if not images:
        raise ValueError(f"record {record.get('index', '?')}: column {inputs!r} holds no images")
    frames = tuple(
        im.convert("RGB") if isinstance(im, Image.Image) else Image.fromarray(np.asarray(im)) for im in images
    )
    obs = observation_from_record(record, width=width, height=height, use_flow=use_flow, fps=fps, substeps=substeps)
    return UnlabeledVideo(str(record.get("index", "?")), frames, obs)


class GeneratedVideos(torch.utils.data.Dataset):
    """Map-style data set of `UnlabeledVideo`s over one split of a generated data set; the labels are dropped.

    Args:
        path: Folder written by `aynamics generate` (a DatasetDict) or one split saved on its own.
        split: Split name when `path` holds a DatasetDict.
        inputs: "rgb" or "flow": the images the model sees.
        width, height: Scorer resolution of the observation (default: `observation.scoring_size`, the video's aspect).
        use_flow: Decode the flow images into the observation (needed for EPE rewards).
        limit: Keep only the first `limit` records.
    """

    def __init__(
        self,
        path: str | Path,
        split: str = "train",
        *,
        inputs: str = "rgb",
        width: int | None = None,
        height: int | None = None,
        use_flow: bool = True,
        limit: int | None = None,
    ) -> None:
        import datasets

        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(2, f"data set folder {str(root)!r} does not exist", str(root))
        if inputs not in INPUTS:
            raise ValueError(f"inputs = {inputs!r}: must be one of {INPUTS}")
        try:
            ds = datasets.load_from_disk(str(root))
        except (OSError, ValueError) as e:  # no dataset_dict.json / state.json, truncated .arrow files, bad JSON
            raise ValueError(f"data set {str(root)!r} cannot be read ({type(e).__name__}: {e})") from None
        if isinstance(ds, datasets.DatasetDict):
            if split not in ds:
                raise ValueError(f"split = {split!r}: {str(root)!r} holds the splits {sorted(ds)}")
            ds = ds[split]
        missing = [c for c in ("segmentation", "frame_indices", inputs) if c not in ds.column_names]
        if missing:
            raise ValueError(f"{str(root)!r}: columns {missing} are missing (has {ds.column_names})")
        keep = [c for c in OBSERVED_COLUMNS if c in ds.column_names]
        ds = ds.select_columns(keep)  # the labels (scene_yaml, states, ...) are never read
        if limit is not None:
            ds = ds.select(range(min(limit, len(ds))))
        self.ds, self.inputs, self.width, self.height, self.use_flow = ds, inputs, width, height, use_flow
        self.fps = dataset_fps(root) or FPS  # the videos' rate (a data set made otherwise: the generator's)
        self.substeps = dataset_substeps(root)  # the physics they were made with (e.g. substeps=4 at 30 fps)

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, i: int) -> UnlabeledVideo:
        rec = self.ds[int(i)]
        return video_from_record(
            rec,
            inputs=self.inputs,
            width=self.width,
            height=self.height,
            use_flow=self.use_flow,
            fps=self.fps,
            substeps=self.substeps,
        )


def video_from_folder(
    path: str | Path,
    *,
    inputs: str = "rgb",
    width: int | None = None,
    height: int | None = None,
    clip_times: Sequence[float] | None = None,
) -> UnlabeledVideo:
    """An `UnlabeledVideo` from `frames/*.png` (or, with `inputs="flow"`, the colour-wheel flow images
    `flow/*.png` that `aynamics render` writes, image f the flow from frame f to f + 1) plus the scorer's observed
    layout (see the module docstring).

    When the folder holds every image of the video (as many frames as the segmentation, one flow image fewer), the
    model sees those at `clip_times` (s from the first frame, on the video's clock: meta.json's fps; the adapter's
    `PromptSpec.frame_times`, as `aynamics predict` reads a video), or without them those of the sampled frames
    (those the observation uses, over the whole video); when it holds exactly as many as are sampled, it sees them
    all. Images are taken in natural name order (`2.png` before `10.png`); hidden files
    (`._0.png`) are not images of the video. Frames may be PNG or JPEG (read as the camera showed them, see
    `aynamics.video_io.read_image`); flow images, PNG, are re-coloured on the scale of those the model sees, as
    generated records are (`aynamics.flow.on_own_scale`: `aynamics render` colours all 29 on one scale).

    Raises:
        FileNotFoundError: the folder, its images or its segmentation is missing.
        ValueError: an unknown `inputs`, image counts that fit neither case (one missing would shift every later
            one), images of another aspect ratio than the masks or of different sizes, or one Pillow cannot read
            (named).
    """
    if inputs not in INPUTS:
        raise ValueError(f"inputs = {inputs!r}: must be one of {INPUTS}")
    root = Path(os.path.abspath(path))  # its name is the video's key, also for "."
    obs = Observation.from_dir(root, width=width, height=height)  # raises for a missing folder / masks
    folder = root / ("frames" if inputs == "rgb" else "flow")
    files = image_files(folder, IMAGE_SUFFIXES if inputs == "rgb" else (".png",))  # flow: lossless only
    if not files:
        what = "frames" if inputs == "rgb" else "colour-wheel flow images (a flow-trained model's input)"
        also = f" (or {', '.join(IMAGE_SUFFIXES[1:])})" if inputs == "rgb" else ""
        raise FileNotFoundError(
            2, f"{str(root)!r} has no {folder.name}/*.png{also}: {what} for the model to see", str(folder)
        )
    n_video, full_h, full_w = obs.video_shape
    every = n_video if inputs == "rgb" else n_video - 1  # flow images: f -> f + 1 for every frame but the last
    picked = [int(round(t * obs.fps + 1e-9)) for t in clip_times] if clip_times is not None else None
    if picked is not None and max(picked) >= max(every, 1) and len(files) in (len(obs.frames), every):
        # a video shorter than the clip; a still (1 frame: its one image is also "the sampled ones") was shown alone,
        # the simulator scoring that one frame
        raise ValueError(
            f"{str(folder)!r}: {every} images at {obs.fps} fps (meta.json), but the clip the model was trained "
            f"on needs the image at {max(clip_times):.3g} s (image {max(picked)}): give a longer video"
        )
    if len(files) == len(obs.frames):
        chosen = files
    elif len(files) == every and picked is not None:  # the adapter's clip, on the video's own clock
        chosen = [files[k] for k in picked]
    elif len(files) == every:
        chosen = [files[int(k)] for k in obs.frames]
    else:
        raise ValueError(
            f"{str(folder)!r}: {len(files)} images; need one for every video frame ({every}: the segmentation has "
            f"{n_video} frames) or exactly the {len(obs.frames)} sampled ones"
        )
    images = [read_image(f) for f in chosen]  # (H, W, 3) uint8 RGB each
    h, w = images[0].shape[:2]
    if abs(w * full_h / full_w - h) > 1:
        raise ValueError(
            f"{str(chosen[0])!r}: {w}×{h} pixels, another aspect ratio than the masks' {full_w}×{full_h}: the scenes "
            "would be scored in another view than the model saw"
        )
    same_size(images, [repr(str(f)) for f in chosen])
    if inputs == "flow":  # on the scale of the images the model sees, as generated records are
        images = list(on_own_scale(np.stack(images)))
    frames = tuple(Image.fromarray(im) for im in images)
    return UnlabeledVideo(root.name, frames, obs)


VIDEO_PARTS = ("frames", "flow", "segmentation", "segmentation.npy")  # what makes a folder a video folder


def _is_video_folder(path: Path) -> bool:
    return path.is_dir() and any((path / part).exists() for part in VIDEO_PARTS)


def _holds_videos(path: Path) -> bool:
    """A sub-folder of a collection that is no video but holds video folders (hidden ones aside)."""
    if path.name.startswith(".") or not path.is_dir() or _is_video_folder(path):
        return False
    try:
        return any(_is_video_folder(p) for p in path.iterdir())
    except OSError:  # unreadable: not a video of the collection either way
        return False


def video_folders(path: str | Path) -> list[Path]:
    """One video folder, or every sub-folder (in name order) of a collection that holds one. A sub-folder is a
    video when it holds any part of one (frames/, flow/, segmentation), so one missing its images or masks is named
    when it is read rather than passed over unseen; a sub-folder holding videos a level deeper is refused (named).

    Raises:
        FileNotFoundError: `path` is missing, or neither a video nor a collection of them.
        ValueError: `path` is a file, or a sub-folder groups videos a level deeper."""
    root = Path(path)
    if not root.exists():
        raise FileNotFoundError(2, f"video folder {str(root)!r} does not exist", str(root))
    if not root.is_dir():
        raise ValueError(f"{str(root)!r} is a file, not a video folder (frames/ beside the segmentation)")
    if _is_video_folder(root):
        return [root]
    subs = sorted(p for p in root.iterdir() if _is_video_folder(p))
    # a sub-folder that is no video but holds videos (videos grouped a level deeper) was passed over unseen
    nested = next((p for p in sorted(root.iterdir()) if _holds_videos(p)), None)
    if nested is not None:
        raise ValueError(
            f"{str(nested)!r} holds video folders, a level below the collection {str(root)!r}: a collection's videos "
            f"are its sub-folders (frames/ beside the segmentation); give {str(nested)!r} on its own or move them up"
        )
    if not subs:
        raise FileNotFoundError(
            2, f"{str(root)!r} is no video folder (frames/ beside the segmentation), nor holds any", str(root)
        )
    return subs


def load_folders(
    path: str | Path,
    *,
    inputs: str = "rgb",
    width: int | None = None,
    height: int | None = None,
    limit: int | None = None,
    clip_times: Sequence[float] | None = None,
) -> list[UnlabeledVideo]:
    """The videos of `video_folders(path)` (the first `limit` only are read), the model seeing `inputs` ("rgb"
    frames or "flow" images) at `clip_times` (`video_from_folder`)."""
    folders = video_folders(path)[:limit]
    return [video_from_folder(p, inputs=inputs, width=width, height=height, clip_times=clip_times) for p in folders]


def is_generated(path: str | Path) -> bool:
    """Whether `path` is a generated data set (with splits) rather than a folder of video folders."""
    root = Path(path)
    return (root / "dataset_dict.json").is_file() or (root / "state.json").is_file()


def open_videos(
    path: str | Path,
    split: str = "train",
    *,
    inputs: str = "rgb",
    width: int | None = None,
    height: int | None = None,
    use_flow: bool = True,
    limit: int | None = None,
    clip_times: Sequence[float] | None = None,
) -> Sequence[UnlabeledVideo]:
    """Unlabeled videos from a generated data set (a folder with `dataset_dict.json` or `state.json`) or folders
    (the model seeing each folder's images at `clip_times`: `video_from_folder`)."""
    root = Path(path)
    if is_generated(root):
        return GeneratedVideos(root, split, inputs=inputs, width=width, height=height, use_flow=use_flow, limit=limit)
    return load_folders(root, inputs=inputs, width=width, height=height, limit=limit, clip_times=clip_times)


def collate_videos(items: Sequence[UnlabeledVideo]) -> list[UnlabeledVideo]:
    """DataLoader collate: keep the videos as a list (prompts are built per video, rows padded later)."""
    return list(items)
