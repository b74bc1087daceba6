"""`aynamics predict`: write the scene (and the reasoning) of a video with a trained adapter.

    aynamics predict --adapter OUT/adapter VIDEO.mp4            # MP4, WebM, AVI, GIF...: FFmpeg (PyAV) / Pillow
    aynamics predict --adapter OUT/adapter FRAMES_DIR/          # a folder of PNG/JPEG frames (30 fps unless --fps)
    aynamics predict --adapter OUT/adapter FRAMES_DIR/ --json   # {"reasoning", "yaml", "valid", "problems"}
    aynamics export-adapter OUT/checkpoints/step000200.ckpt --out step200/   # any step's adapter folder

The adapter folder (written by training: peft files + `aynamics.json`) says which base model to rebuild and how
the prompt was made (modality, number of frames, images or one video, target) and when the training frames were
taken (`fps`, `clip_frames`: every third frame of a 30 fps video for generated data). The model reads the video's
frames at those times from its first frame, whatever the video's own rate (`clip_of`; a file's frames by their
stored presentation times, so a phone's variable rate is followed, and upright as its rotation shows them), then
the trained number of them evenly, as in training. Flow-trained adapters expect flow images (Middlebury
colours), e.g. the `flow/` PNGs of `aynamics render`. The process exits 0 when the response holds a valid
scene, 1 when it does not.
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import numpy as np

_THINK = re.compile(r"<think>(.*?)(?:</think>|$)", re.S)


def clip_of(path: str | Path, prompt, fps: float | None = None) -> list[np.ndarray]:
    """The frames of a video (a file, or a folder of frames) that the adapter was trained on: those on screen at
    the times of the frames a training record holds (`prompt.frame_times`: every third of 30 at 30 fps, 0 to
    0.9 s, for the generator's data), from the video's first frame. The processor then takes the trained number
    of them evenly, as in training.

    Args:
        path: A video file (its own frame rate) or a folder of consecutive frames (at `fps`, default the training
            videos' rate); a folder holding exactly as many images as a training record (no `fps` given) is taken
            as those frames, the way `aynamics evaluate --videos` reads one.
        prompt: The adapter's `lm.PromptSpec` (`adapters.read_adapter_meta`).
        fps: The video's frame rate, when its file states none or states it wrong, or for a folder.

    Returns:
        (H, W, 3) uint8 frames; flow images (a flow-trained adapter) re-coloured on their own scale, as generated
        records are.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: no frames, a video too short for the clip's times (named with its length and rate), an image
            or video that cannot be read, frames of different sizes.
    """
    from aynamics import video_io
    from aynamics.flow import on_own_scale

    path = Path(path)
    own = prompt.fps if path.is_dir() else None  # a folder's rate unless given (a given 0 is refused, not dropped)
    video, times = video_io.open_video(path, fps=own if fps is None else fps), prompt.frame_times
    if fps is None and video.files is not None and len(video.files) == len(prompt.clip_frames):
        times = video.starts  # the clip itself: every image
    frames = video.frames_at(times)
    if prompt.modality == "flow":
        frames = list(on_own_scale(np.stack(frames)))
    return frames


def predict(
    adapter: str | Path,
    frames: list[np.ndarray],
    max_new_tokens: int = 2048,
    device: str = "auto",
    separate: bool = False,
) -> dict:
    """Greedy response of the adapter's model for `frames`: {"response", "reasoning", "yaml", "valid", "problems"}.
    `device`: "auto" (a GPU when there is one), "cpu", "cuda", "cuda:1", ...

    With `separate`, the scene's objects that start inside each other or the floor are pushed apart
    (`aynamics.separate.separate_start`): "yaml" is the separated scene, "moved" {name: [dx, dy, dz] in m} what
    moved; a scene that cannot be separated keeps its YAML, with the reason as a problem and "valid" False."""
    from aynamics import adapters, lm
    from aynamics.scene import SceneError, dump, parse

    model, spec, prompt = adapters.load_adapter(adapter, device)
    processor = lm.load_processor(spec, prompt)
    inputs = lm.prompt_inputs(processor, prompt, frames)
    response = lm.greedy_texts(model, processor, [inputs], max_new_tokens)[0]
    think = _THINK.search(response)
    result = {"response": response, "reasoning": think.group(1).strip() if think else None}
    try:
        scene = parse(response)
    except SceneError as e:
        return result | {"yaml": None, "valid": False, "problems": [str(p) for p in e.problems]}
    result |= {"yaml": dump(scene), "valid": True, "problems": []}
    if separate:
        from aynamics.separate import separate_start

        try:
            separated = separate_start(scene)
        except ValueError as e:
            return result | {"valid": False, "problems": [str(e)], "moved": {}}
        result |= {"yaml": dump(separated.scene), "moved": {k: list(v) for k, v in separated.moved.items()}}
    return result


def add_predict_command(sub) -> None:
    """Register `aynamics predict` on the CLI's subparsers."""
    from aynamics.cli import add_device_option

    p = sub.add_parser("predict", help="write the scene YAML (and reasoning) of a video with a trained adapter")
    p.add_argument("input", help="a video file or a folder of frames (PNG/JPEG, natural name order: 2 before 10)")
    p.add_argument("--adapter", required=True, help="adapter folder written by training (OUT/adapter)")
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="the video's frame rate: for a folder of frames (default: the training videos' rate, 30 for generated "
        "data), or a file that states none or a wrong one (frame k is then at k / FPS; otherwise a file's frames "
        "come at their stored times). The model reads the frames at the times training showed "
        "it (0 to 0.9 s of the video for generated data)",
    )
    p.add_argument("--max-new-tokens", type=int, default=2048, help="response length limit (default 2048)")
    p.add_argument(
        "--separate",
        action="store_true",
        help="push apart objects the scene starts inside each other or the floor (each as little as their "
        "contacts say; what moved is printed as a comment)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    add_device_option(p)
    p.set_defaults(run=run_predict)


def run_predict(args) -> int:
    from aynamics import adapters
    from aynamics.cli import UsageError, missing_file_message

    if args.max_new_tokens < 1:
        raise UsageError(f"predict: --max-new-tokens = {args.max_new_tokens}: must be >= 1")
    if not Path(args.adapter).is_dir():
        raise UsageError(f"predict: --adapter {args.adapter!r} is not a folder (give OUT/adapter of a training run)")
    if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
        raise UsageError(f"predict: --fps {args.fps}: must be a finite number > 0")
    try:
        frames = clip_of(args.input, adapters.read_adapter_meta(args.adapter)[1], args.fps)
        result = predict(args.adapter, frames, args.max_new_tokens, args.device, args.separate)
    except FileNotFoundError as e:
        raise UsageError(f"predict: {missing_file_message(e)}") from None
    except ValueError as e:
        raise UsageError(f"predict: {e}") from None
    if args.json:
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
    else:
        if result["reasoning"]:
            sys.stdout.write(f"# reasoning\n{result['reasoning']}\n\n")
        for name, d in result.get("moved", {}).items():
            sys.stdout.write(f"# separated: {name} moved by [{', '.join(f'{x:.4g}' for x in d)}] m\n")
        if result["valid"]:
            sys.stdout.write(result["yaml"])
        elif result["yaml"] is not None:  # a scene that could not be separated
            sys.stdout.write(f"# {result['problems'][0]}\n{result['yaml']}")
        else:
            sys.stdout.write(f"# the response holds no valid scene: {'; '.join(result['problems'][:5])}\n")
            sys.stdout.write(result["response"] + "\n")
    return 0 if result["valid"] else 1


def add_export_command(sub) -> None:
    """Register `aynamics export-adapter` on the CLI's subparsers."""
    p = sub.add_parser(
        "export-adapter",
        help="write the peft adapter folder of a training checkpoint (OUT/adapter holds the latest only)",
    )
    p.add_argument("checkpoint", help="a checkpoint written by train.py (OUT/checkpoints/stepNNNNNN.ckpt)")
    p.add_argument(
        "--out",
        required=True,
        help="folder to write (PeftModel.from_pretrained and --adapter read it): new, empty, or an adapter folder "
        "(holding adapter_config.json) to overwrite; any other folder with files in it is refused",
    )
    p.set_defaults(run=run_export)


def check_export_folder(out: str | Path) -> None:
    """Refuse an `export-adapter --out` that would overwrite files of something other than an adapter folder.

    peft writes README.md, adapter_config.json and the weights into the folder: a folder that is new, empty, or
    already an adapter folder (holding adapter_config.json) may take them; another folder's files would be lost.

    Raises:
        ValueError: `out` is a file, or a non-empty folder that is not an adapter folder (the path is named).
    """
    out = Path(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file, not a folder")
    if any(out.iterdir()) and not (out / "adapter_config.json").is_file():
        raise ValueError(
            f"--out {str(out)!r} is a folder with files in it and not an adapter folder (no adapter_config.json): "
            "its files could be overwritten; give a new or empty folder"
        )


def run_export(args) -> int:
    from aynamics import adapters
    from aynamics.cli import UsageError

    try:
        check_export_folder(args.out)
    except ValueError as e:
        raise UsageError(f"export-adapter: {e}") from None
    try:
        out = adapters.adapter_from_checkpoint(args.checkpoint, args.out)
    except FileNotFoundError:
        raise  # the CLI names the missing checkpoint
    except (OSError, ValueError) as e:
        raise UsageError(f"export-adapter: {e}") from None
    sys.stdout.write(f"{out}\n")
    return 0
