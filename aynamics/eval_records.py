"""A data-set record as the scene evaluation needs it (`eval_record`): the prompt the model gets, the true scene,
the view it is scored in and the times of the frames the model saw; `frames_of` reads a record's frames, here and
for training (`data.SFTDataset`).

    records = [readable_eval_record(split, i, processor, prompt, "validation") for i in range(8)]  # None: unreadable
"""

from __future__ import annotations

import warnings
from typing import Any

from aynamics import lm


def frames_of(record: dict[str, Any], modality: str) -> list:
    """The frames of one record for `modality` ("rgb" or "flow")."""
    if modality not in lm.MODALITIES:
        raise ValueError(f"modality = {modality!r}: must be one of {lm.MODALITIES}")
    frames = record.get(modality)
    if not frames:
        raise ValueError(f"record {record.get('index', '?')} has no {modality!r} frames")
    return list(frames)


def readable_eval_record(
    split, i: int, processor, prompt: lm.PromptSpec, where: str, substeps: int | None = None
) -> dict[str, Any] | None:
    """`eval_record` of row `i` of `split`, or None with a warning naming it among `where` when its frames cannot be
    read (none stored, a broken image): one bad record never stops a training run or an evaluation."""
    try:
        return eval_record(split[i], processor, prompt, i, substeps)
    except (ValueError, OSError) as e:  # PIL's UnidentifiedImageError is an OSError
        warnings.warn(f"scene evaluation: record {i} of the {where} is left out: its frames cannot be read ({e})")
        return None


def eval_record(
    record: dict[str, Any], processor, prompt: lm.PromptSpec, position: int = 0, substeps: int | None = None
) -> dict[str, Any]:
    """What generating for and scoring one data-set record needs: its `index` (`position` in the split when the
    record has none), the unbatched `prompt`, the `scene_yaml`, the frames' (width, height) `size` in pixels (the
    view the scene is scored in), and when they were taken: the video `frames` the model sees (the record's
    `frame_indices`, None when it has none: the scorer's default) at `fps` (the prompt's clock: `with_clock` sets
    it to the data set's rate), simulated with the data set's `substeps` (`dataset_store.dataset_substeps`; None:
    the default for `fps`). The scene is scored at those frames, the times the model saw."""
    frames = frames_of(record, prompt.modality)
    shown = record.get("frame_indices")
    return {
        "index": record.get("index", position),
        "prompt": lm.prompt_inputs(processor, prompt, frames),
        "scene_yaml": record["scene_yaml"],
        "size": tuple(frames[0].size),
        "frames": None if shown is None else tuple(int(k) for k in shown),
        "fps": round(prompt.fps),
        "substeps": substeps,
    }
