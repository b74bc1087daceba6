"""`aynamics predict`: write the scene (and the reasoning) of a video with a trained adapter.

    aynamics predict --adapter OUT/adapter VIDEO.mp4            # MP4, WebM, AVI, GIF...: what FFmpeg (PyAV) decodes
    aynamics predict --adapter OUT/adapter FRAMES_DIR/          # a folder of PNG/JPEG frames, in name order
    aynamics predict --adapter OUT/adapter FRAMES_DIR/ --json   # {"reasoning", "yaml", "valid", "problems"}
    aynamics export-adapter OUT/checkpoints/step000200.ckpt --out step200/   # any step's adapter folder

The adapter folder (written by training: peft files + `aynamics.json`) says which base model to rebuild and how
the prompt was made (modality, number of frames, images or one video, target). Frames are sampled evenly to the
trained count. Flow-trained adapters expect flow images (Middlebury colours), e.g. the `flow/` PNGs of
`aynamics render`. The process exits 0 when the response holds a valid scene, 1 when it does not.
"""

from __future__ import annotations

import errno
import json
import os
import re
import sys
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")
_THINK = re.compile(r"<think>(.*?)(?:</think>|$)", re.S)


def read_image(path: str | Path) -> np.ndarray:
    """One image file as an array, its path named when it cannot be read (truncated, not an image, unreadable)."""
    import imageio.v3 as iio

    try:
        return iio.imread(path)
    except Exception as e:  # Pillow and imageio raise OSError, ValueError and more for a broken image
        raise ValueError(f"cannot read frame {str(path)!r}: {type(e).__name__}: {e}") from None


def read_frames(path: str | Path) -> list[np.ndarray]:
    """RGB frames (H, W, 3) uint8 of a folder of images (name order) or a video file.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the folder holds no images, the video cannot be decoded, or the frames differ in size.
    """
    import imageio.v3 as iio

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(path))
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise ValueError(f"{str(path)!r} holds no frames (looked for {', '.join(IMAGE_SUFFIXES)})")
        frames = [read_image(p) for p in files]
    else:
        try:
            frames = list(iio.imiter(path))
        except Exception as e:  # imageio raises many types for an unreadable or plugin-less video
            raise ValueError(f"cannot read video {str(path)!r}: {type(e).__name__}: {e}") from None
        if not frames:
            raise ValueError(f"video {str(path)!r} has no frames")
    out = []
    for k, f in enumerate(frames):
        f = np.asarray(f)
        if f.ndim == 2:
            f = np.repeat(f[..., None], 3, axis=-1)
        if f.ndim != 3 or f.shape[-1] not in (3, 4):
            raise ValueError(f"frame {k} of {str(path)!r} has shape {f.shape}: need (H, W, 3) RGB")
        out.append(np.ascontiguousarray(f[..., :3].astype(np.uint8)))
    sizes = {f.shape for f in out}
    if len(sizes) > 1:
        raise ValueError(f"frames of {str(path)!r} differ in size: {sorted(sizes)}")
    return out


def predict(adapter: str | Path, frames: list[np.ndarray], max_new_tokens: int = 2048, device: str = "auto") -> dict:
    """Greedy response of the adapter's model for `frames`: {"response", "reasoning", "yaml", "valid", "problems"}.
    `device`: "auto" (a GPU when there is one), "cpu", "cuda", "cuda:1", ..."""
    from aynamics import lm
    from aynamics.scene import SceneError, dump, parse

    model, spec, prompt = lm.load_adapter(adapter, device)
    processor = lm.load_processor(spec, prompt)
    inputs = lm.prompt_inputs(processor, prompt, frames)
    response = lm.greedy_texts(model, processor, [inputs], max_new_tokens)[0]
    think = _THINK.search(response)
    result = {"response": response, "reasoning": think.group(1).strip() if think else None}
    try:
        result |= {"yaml": dump(parse(response)), "valid": True, "problems": []}
    except SceneError as e:
        result |= {"yaml": None, "valid": False, "problems": [str(p) for p in e.problems]}
    return result


def add_predict_command(sub) -> None:
    """Register `aynamics predict` on the CLI's subparsers."""
    from aynamics.cli import add_device_option

    p = sub.add_parser("predict", help="write the scene YAML (and reasoning) of a video with a trained adapter")
    p.add_argument("input", help="a video file or a folder of frames (PNG/JPEG, name order)")
    p.add_argument("--adapter", required=True, help="adapter folder written by training (OUT/adapter)")
    p.add_argument("--max-new-tokens", type=int, default=2048, help="response length limit (default 2048)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    add_device_option(p)
    p.set_defaults(run=run_predict)


def run_predict(args) -> int:
    from aynamics.cli import UsageError, missing_file_message

    if args.max_new_tokens < 1:
        raise UsageError(f"predict: --max-new-tokens = {args.max_new_tokens}: must be >= 1")
    if not Path(args.adapter).is_dir():
        raise UsageError(f"predict: --adapter {args.adapter!r} is not a folder (give OUT/adapter of a training run)")
    try:
        frames = read_frames(args.input)
        result = predict(args.adapter, frames, args.max_new_tokens, args.device)
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
        if result["valid"]:
            sys.stdout.write(result["yaml"])
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
    from aynamics import lm
    from aynamics.cli import UsageError

    try:
        check_export_folder(args.out)
    except ValueError as e:
        raise UsageError(f"export-adapter: {e}") from None
    try:
        out = lm.adapter_from_checkpoint(args.checkpoint, args.out)
    except FileNotFoundError:
        raise  # the CLI names the missing checkpoint
    except (OSError, ValueError) as e:
        raise UsageError(f"export-adapter: {e}") from None
    sys.stdout.write(f"{out}\n")
    return 0
