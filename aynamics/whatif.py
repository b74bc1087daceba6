"""What-if videos: re-simulate an edited scene, render it, compute its flow, and animate it next to the original.

    paths = render_what_if(original, edited, "out/")   # original/edited YAML, rollouts, flow, side_by_side.gif

The side-by-side animation has the original on the left and the edited scene on the right, RGB on top and the
exact optical flow (one colour scale for both) below. The paper then turns the edited flow into a photorealistic
video with a flow-conditioned video-diffusion model; those weights are far too large to ship, so that last step
is a hook: pass any `VideoSynthesizer` (first RGB frame + flow -> video) and its output is written as
`synthesized.gif`. Nothing is faked when no synthesiser is given.

The `aynamics edit` subcommand lives here too:

    aynamics edit SCENE.yaml "reduce the x-velocity of box_0 by 80%" --out EDITED.yaml --render DIR [--llm MODEL]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Protocol

import numpy as np

from aynamics.scene import Scene, dump

ANIMATION_FPS = 15  # playback speed of the animations (the video is 30 FPS; half speed is easier to follow)


class VideoSynthesizer(Protocol):
    """A flow-conditioned video model (the paper's last step), e.g. a video-diffusion model with motion control.

    Called with the first RGB frame (H, W, 3) uint8 of the original, the edited scene's forward flow
    (T-1, H, W, 2) float32 pixels (dx right, dy down) and a text prompt; returns a video (T, H, W, 3) uint8.
    """

    def __call__(self, first_frame: np.ndarray, flow: np.ndarray, prompt: str) -> np.ndarray: ...


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """Write a small caption in the top-left corner of each frame (T, H, W, 3)."""
    from PIL import Image, ImageDraw

    out = np.empty_like(image)
    for k, frame in enumerate(image):
        pil = Image.fromarray(frame)
        draw = ImageDraw.Draw(pil)
        x0, y0, x1, y1 = draw.textbbox((3, 2), text)
        draw.rectangle((x0 - 2, y0 - 1, x1 + 2, y1 + 1), fill=(0, 0, 0))
        draw.text((3, 2), text, fill=(255, 255, 255))
        out[k] = np.asarray(pil)
    return out


def animation_kind(path: str | Path) -> str:
    """The animation format of `path` by its suffix, ".gif" or ".mp4" (checked before work that ends in one).

    Raises:
        ValueError: any other suffix.
    """
    kind = Path(path).suffix.lower()
    if kind not in (".gif", ".mp4"):
        raise ValueError(f"animation path {str(path)!r}: the suffix must be .gif or .mp4")
    return kind


def write_animation(path: str | Path, grid: list[list[np.ndarray]], labels: list[list[str]], fps: int = ANIMATION_FPS):
    """Tile videos into one animation, a looping GIF or an H.264 MP4 by the path's suffix: `grid[row][col]` is
    (T, H, W, 3) uint8 (T may differ: shorter ones hold their last frame); `labels` caption each tile. An MP4's
    frames are padded to even sizes with black (H.264 in yuv420p, what players expect, needs them).

    Raises:
        ValueError: the suffix is neither .gif nor .mp4, or tiles differ in size.
    """
    import imageio.v3 as iio

    path = Path(path)
    kind = animation_kind(path)
    t = max(v.shape[0] for row in grid for v in row)
    rows = []
    for row, names in zip(grid, labels, strict=True):
        tiles = []
        for video, name in zip(row, names, strict=True):
            if video.shape[1:] != grid[0][0].shape[1:]:
                raise ValueError(f"tile {name!r} is {video.shape[1:]}, the first tile {grid[0][0].shape[1:]}")
            pad = np.repeat(video[-1:], t - video.shape[0], axis=0)
            tiles.append(_label(np.concatenate([video, pad]), name))
        rows.append(np.concatenate(tiles, axis=2))
    frames = np.concatenate(rows, axis=1)  # (T, rows·H, cols·W, 3)
    path.parent.mkdir(parents=True, exist_ok=True)
    if kind == ".gif":
        iio.imwrite(path, frames, duration=1000 / fps, loop=0)
    else:
        h, w = frames.shape[1:3]
        frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)))
        iio.imwrite(path, frames, plugin="pyav", codec="libx264", fps=fps, out_pixel_format="yuv420p")
    return path


# What `render_what_if` writes (`edit --render DIR`): a folder holding anything else is refused.
WHAT_IF_FILES = frozenset(
    {"original.yaml", "edited.yaml", "original_rollout.npz", "edited_rollout.npz", "edited_flow.npz"}
    | {"side_by_side.gif", "synthesized.gif"}
)


def render_what_if(
    original: Scene,
    edited: Scene,
    out_dir: str | Path,
    *,
    width: int = 240,
    height: int = 160,
    seed: int = 0,
    instruction: str = "",
    synthesize: VideoSynthesizer | None = None,
) -> dict[str, object]:
    """Simulate both scenes, render them with the same appearance, compute flow, write the files.

    Writes `original.yaml`, `edited.yaml`, `original_rollout.npz`, `edited_rollout.npz`, `edited_flow.npz`
    (flow (T-1, H, W, 2), occluded), `side_by_side.gif`, and `synthesized.gif` when `synthesize` is given.

    Returns:
        A summary: written paths, and whether each rollout is valid (with the reason when not).

    Raises:
        aynamics.render.RenderError: no headless OpenGL (the message says what to install).
    """
    from aynamics.flow import flow_to_color, motion_flow
    from aynamics.render import Renderer
    from aynamics.simulate import simulate_batch

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rollouts = simulate_batch([original, edited], nthread=1)
    videos, flows = [], []
    with Renderer(width, height) as r:
        for scene, rollout in zip((original, edited), rollouts, strict=True):
            frames = r.render(scene, rollout, seed=seed)
            flow, occluded = motion_flow(scene, rollout, frames.depth, frames.camera, frames.segmentation)
            videos.append(frames.rgb)
            flows.append((flow, occluded))
    scale = max(float(np.nanmax(np.hypot(f[..., 0], f[..., 1]), initial=0.0)) for f, _ in flows)
    colours = [flow_to_color(f, max_norm=scale) for f, _ in flows]
    written = {}
    for name, scene, rollout in (("original", original, rollouts[0]), ("edited", edited, rollouts[1])):
        (out / f"{name}.yaml").write_text(dump(scene))
        rollout.to_npz(str(out / f"{name}_rollout.npz"))
        written[f"{name}_yaml"] = str(out / f"{name}.yaml")
        written[f"{name}_rollout"] = str(out / f"{name}_rollout.npz")
    np.savez_compressed(out / "edited_flow.npz", flow=flows[1][0], occluded=flows[1][1])
    written["edited_flow"] = str(out / "edited_flow.npz")
    grid = [[videos[0], videos[1]], [colours[0], colours[1]]]
    labels = [["original", "edited"], ["original flow", "edited flow"]]
    written["side_by_side"] = str(write_animation(out / "side_by_side.gif", grid, labels))
    if synthesize is not None:
        video = np.asarray(synthesize(videos[0][0], flows[1][0], instruction))
        if video.ndim != 4 or video.shape[-1] != 3 or video.dtype != np.uint8:
            raise ValueError(f"the video synthesiser returned {video.shape} {video.dtype}: need (T, H, W, 3) uint8")
        written["synthesized"] = str(write_animation(out / "synthesized.gif", [[video]], [["synthesized"]]))
    return {
        "files": written,
        "original_valid": rollouts[0].valid,
        "original_reason": rollouts[0].reason,
        "edited_valid": rollouts[1].valid,
        "edited_reason": rollouts[1].reason,
    }


# --------------------------------------------------------------------------------------------
# aynamics edit
# --------------------------------------------------------------------------------------------
def add_edit_command(sub) -> None:
    """Register `aynamics edit`."""
    from aynamics.cli import add_device_option

    p = sub.add_parser("edit", help="edit a scene with an instruction ('reduce the x-velocity of box_0 by 80%%')")
    p.add_argument("scene", help="scene YAML file")
    p.add_argument("instruction", help="the edit, e.g. 'decrease gravity by 50%%; move box_0 0.5 m left'")
    p.add_argument("--out", help="write the edited scene YAML here (default: print it)")
    p.add_argument(
        "--render",
        metavar="DIR",
        help="re-simulate, render, compute flow, write side_by_side.gif; exit status 1 when the edited scene's rollout "
        "is invalid (e.g. the edit starts objects overlapping), the reason on stderr (also the original's)",
    )
    p.add_argument("--llm", metavar="MODEL", help="edit with a transformers chat model (checked against the text)")
    p.add_argument("--max-new-tokens", type=int, default=2048, help="generation limit for --llm (default 2048)")
    add_device_option(p, "--llm")
    p.add_argument("--width", type=int, default=240, help="render width in pixels (default 240)")
    p.add_argument("--height", type=int, default=160, help="render height in pixels (default 160)")
    p.add_argument("--seed", type=int, default=0, help="appearance seed for --render (default 0)")
    p.add_argument("--json", action="store_true", help="print changes, validity and the edited YAML as JSON")
    p.set_defaults(run=run_edit_command)


def run_edit_command(args) -> int:
    """`aynamics edit`: nothing is written unless the edit is understood and the edited scene is valid.

    Exit status 1 (as `simulate` and `render`) when `--render` finds the edited scene's rollout invalid, e.g. an
    edit that moves an object into the floor; the edited YAML is still written to `--out` and the files to
    `--render DIR`. An invalid original is reported on stderr too, without failing an edit that repairs it.
    """
    from aynamics.cli import UsageError, check_out_folder, load_scene
    from aynamics.edit import EditError, apply_instruction

    scene = load_scene("edit", args.scene)
    if args.render:  # before --out is written: the renderer refused these after it, NumPy's seed naming no option
        if not (16 <= args.width <= 4096 and 16 <= args.height <= 4096):  # as `render`: a 5-pixel GIF is no what-if
            raise UsageError(f"edit: --width {args.width} --height {args.height}: each must be in [16, 4096]")
        if args.seed < 0:
            raise UsageError(f"edit: --seed {args.seed}: must be >= 0")
        check_out_folder("edit", args.render, writes=WHAT_IF_FILES, flag="--render")
    try:
        if args.llm:
            from aynamics.edit_llm import LLMEditor

            editor = LLMEditor(args.llm, max_new_tokens=args.max_new_tokens, device=args.device)
            result = editor.edit(scene, args.instruction)
        else:
            result = apply_instruction(scene, args.instruction)
    except EditError as e:
        raise UsageError(f"edit: {e}") from None
    text = dump(result.scene)
    report: dict[str, object] = {
        "changes": [{"path": c.path, "before": c.before, "after": c.after} for c in result.changes]
    }
    if args.out:
        try:
            Path(args.out).write_text(text)
        except OSError as e:
            raise UsageError(f"edit: cannot write --out {args.out!r}: {e.strerror or e}") from None
    if args.render:
        from aynamics.render import RenderError

        try:
            report.update(
                render_what_if(
                    scene,
                    result.scene,
                    args.render,
                    width=args.width,
                    height=args.height,
                    seed=args.seed,
                    instruction=args.instruction,
                )
            )
        except (RenderError, ValueError, OSError) as e:
            raise UsageError(f"edit --render {args.render!r}: {e}") from None
    invalid = [  # (which, reason) of the rollouts --render found invalid
        (which, report.get(f"{which}_reason"))
        for which in ("original", "edited")
        if f"{which}_valid" in report and not report[f"{which}_valid"]
    ]
    if args.json:
        report["edited_yaml"] = text
        json.dump(report, sys.stdout)
        sys.stdout.write("\n")
    else:
        for c in result.changes:
            sys.stderr.write(f"changed {c}\n")
        if not result.changes:  # e.g. doubling a zero spin: said, not passed over in silence
            sys.stderr.write(f"edit: {args.instruction!r} changes no value of the scene\n")
        if not args.out:
            sys.stdout.write(text)
    for which, reason in invalid:
        sys.stderr.write(f"edit: the {which} scene's rollout is invalid: {reason}\n")
    return 1 if any(which == "edited" for which, _ in invalid) else 0  # an edit that repairs a scene succeeded
