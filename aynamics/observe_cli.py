"""The `render` and `score` subcommands of the `aynamics` console script.

    aynamics render SCENE.yaml --out DIR [--seed 0] [--width 480 --height 320] [--textures DIR]
    aynamics score PRED.yaml [PRED2.yaml ...] --observed SCENE.yaml|DIR [--json]

`render` writes, for the 30 video frames (rollout states 0..29):
    frames/frame_0000.png ...   RGB
    flow/flow_0000.png ...      flow maps 0..28 on the standard colour wheel (the model's flow input)
    segmentation.npy            (T, H, W) int16, -1 floor and sky, else object index
    depth.npy                   (T, H, W) float32 metres along the optical axis, inf for sky
    flow.npy, occlusion.npy     (T-1, H, W, 2) float32 pixels and (T-1, H, W) bool
    camera.json                 OpenCV K, R, t (x_cam = R x_world + t)
    meta.json                   object names, fps, states, seed, validity of the rollout
    scene.yaml                  the scene (canonical YAML)
    video.gif                   RGB next to colour-coded flow, for people
The folder is accepted by `aynamics score --observed DIR`.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np

from aynamics.cli import UsageError, check_out_folder, load_scene, refuse_rendered_file

# What `render --out DIR` writes (see the module docstring): a folder holding anything else is refused.
RENDER_FILES = frozenset(
    {"frames", "flow", "segmentation.npy", "depth.npy", "flow.npy", "occlusion.npy", "camera.json", "meta.json"}
    | {"scene.yaml", "video.gif"}
)


RENDER_IMAGE = {"frames": re.compile(r"frame_\d{4}\.png"), "flow": re.compile(r"flow_\d{4}\.png")}


def check_earlier_render(out: Path) -> None:
    """Refuse a folder of RENDER_FILES' names that no render wrote: a video folder of the user's in the observed
    layout (frames/ of their own names, segmentation.npy of their own masks, which `evaluate --videos` and PRO
    read). Its masks were overwritten and the render's frames mixed into theirs. A render writes depth.npy right
    after segmentation.npy, and names its images frame_NNNN.png / flow_NNNN.png.

    Raises:
        UsageError: naming the file that shows the folder is not an earlier render.
    """
    if not out.is_dir():
        return
    for folder, pattern in RENDER_IMAGE.items():
        if (out / folder).is_dir():
            other = next(
                (
                    p.name
                    for p in sorted((out / folder).iterdir())
                    if not p.name.startswith(".") and not pattern.fullmatch(p.name)
                ),
                None,
            )
            if other is not None:
                raise UsageError(
                    f"render: --out {str(out)!r} is no earlier render: {folder}/{other} is not a file render writes "
                    "(a video folder of yours?); give a new or empty folder"
                )
    if (out / "segmentation.npy").exists() and not (out / "depth.npy").exists():
        raise UsageError(
            f"render: --out {str(out)!r} is no earlier render: it holds segmentation.npy without depth.npy (a video "
            "folder of yours, whose masks would be overwritten?); give a new or empty folder"
        )


def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render a scene: RGB, segmentation, depth, exact flow, camera, GIF")
    p.add_argument("scene", help="scene YAML file")
    p.add_argument("--out", required=True, help="folder to write: new, empty, or an earlier render (created)")
    p.add_argument("--seed", type=int, default=0, help="appearance seed: lights, textures, floor and sky (default 0)")
    p.add_argument("--width", type=int, default=480, help="image width in pixels (default 480)")
    p.add_argument("--height", type=int, default=320, help="image height in pixels (default 320)")
    p.add_argument("--textures", help="folder of photographs for floor and sky (default: scikit-image's samples)")
    p.add_argument("--no-gif", action="store_true", help="skip the preview video.gif")
    p.set_defaults(run=_run_render)


def _run_render(args) -> int:
    from aynamics import appearance
    from aynamics import flow as flowlib
    from aynamics import render as renderlib
    from aynamics import simulate as sim

    scene = load_scene("render", args.scene)
    if not (16 <= args.width <= 4096 and 16 <= args.height <= 4096):
        raise UsageError(f"render: --width {args.width} --height {args.height}: each must be in [16, 4096]")
    if args.seed < 0:
        raise UsageError(f"render: --seed {args.seed}: must be >= 0")
    if args.textures is not None:
        try:
            appearance.texture_images(args.textures)
        except (FileNotFoundError, ValueError) as e:
            raise UsageError(f"render: --textures {args.textures!r}: {getattr(e, 'strerror', None) or e}") from None
    out = Path(args.out)
    check_out_folder("render", out, writes=RENDER_FILES)  # before the work; the folders are made after it
    check_earlier_render(out)
    rollout = sim.simulate(scene)
    try:
        frames = renderlib.render(
            scene, rollout, width=args.width, height=args.height, seed=args.seed, textures_dir=args.textures
        )
    except (renderlib.RenderError, ValueError) as e:  # e.g. no headless OpenGL, a texture image that cannot be read
        raise UsageError(f"render: {e}") from None
    try:
        (out / "frames").mkdir(parents=True, exist_ok=True)
        (out / "flow").mkdir(exist_ok=True)
    except OSError as e:
        raise UsageError(f"render: cannot create --out {str(out)!r}: {e.strerror or e}") from None
    flow, occluded = flowlib.motion_flow(scene, rollout, frames.depth, frames.camera, frames.segmentation)
    colours = flowlib.flow_to_color(flow)
    _write_outputs(out, scene, rollout, frames, flow, occluded, colours, args.seed, not args.no_gif)
    sys.stdout.write(f"wrote {len(frames.rgb)} frames and {len(flow)} flow maps to {out}\n")
    if not rollout.valid:
        sys.stderr.write(f"render: the rollout is invalid: {rollout.reason}\n")
    return 0 if rollout.valid else 1


def _write_outputs(out: Path, scene, rollout, frames, flow, occluded, colours, seed: int, gif: bool) -> None:
    import imageio.v3 as iio

    from aynamics import scene as scenelib

    for k, img in enumerate(frames.rgb):
        iio.imwrite(out / "frames" / f"frame_{k:04d}.png", img)
    for k, img in enumerate(colours):
        iio.imwrite(out / "flow" / f"flow_{k:04d}.png", img)
    np.save(out / "segmentation.npy", frames.segmentation)
    np.save(out / "depth.npy", frames.depth)
    np.save(out / "flow.npy", flow)
    np.save(out / "occlusion.npy", occluded)
    (out / "camera.json").write_text(json.dumps(frames.camera.to_json(), indent=1))
    meta = {
        "names": list(scene.names),
        "fps": int(round(1 / (rollout.t[1] - rollout.t[0]))) if len(rollout.t) > 1 else 30,
        "states": frames.states.tolist(),
        "seed": seed,
        "width": frames.camera.width,
        "height": frames.camera.height,
        "valid": rollout.valid,
        "reason": rollout.reason,
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    (out / "scene.yaml").write_text(scenelib.dump(scene))
    if gif:
        pad = np.concatenate([colours, colours[-1:]]) if len(colours) else np.full_like(frames.rgb, 255)
        video = np.concatenate([frames.rgb, pad], axis=2)  # RGB | flow, side by side
        iio.imwrite(out / "video.gif", video, duration=1000 / meta["fps"], loop=0)
    else:  # an earlier render's preview would show another scene beside these files
        (out / "video.gif").unlink(missing_ok=True)


def _add_score(sub) -> None:
    p = sub.add_parser("score", help="score predicted scenes against an observed scene or rendered folder")
    p.add_argument("predictions", nargs="+", help="predicted scene YAML files (model outputs are fine)")
    p.add_argument("--observed", required=True, help="observed scene YAML, or a folder written by `aynamics render`")
    p.add_argument("--json", action="store_true", help="print a JSON list, one object per prediction, in order")
    p.add_argument(
        "--width", type=int, help="scoring resolution width (default: the observed folder's aspect at 80 rows; 120)"
    )
    p.add_argument("--height", type=int, help="scoring resolution height (default 80)")
    p.set_defaults(run=_run_score)


def _run_score(args) -> int:
    from aynamics import observation, scorer
    from aynamics import scene as scenelib

    if not (
        8 <= (8 if args.width is None else args.width) <= 1920
        and 8 <= (8 if args.height is None else args.height) <= 1280
    ):
        given = " ".join(f"--{k} {v}" for k, v in (("width", args.width), ("height", args.height)) if v is not None)
        raise UsageError(f"score: {given}: must be in [8, 1920] × [8, 1280] (width × height)")
    missing = [p for p in args.predictions if not Path(p).exists()]
    if missing:  # a mistyped path, not a prediction to score 0 (a file that exists but cannot be read still is)
        raise UsageError(f"score: prediction file(s) not found: {', '.join(map(repr, missing))}")
    observed = Path(args.observed)
    refuse_rendered_file("score", args.observed)
    try:
        if observed.is_dir():
            obs = observation.Observation.from_dir(observed, width=args.width, height=args.height)
        else:  # a scene has no image size of its own: the scorer's 120×80 unless given (its aspect: 3:2)
            width, height = observation.scoring_size(observation.WIDTH, observation.HEIGHT, args.width, args.height)
            obs = observation.Observation.from_scene(scenelib.load(args.observed), width=width, height=height)
    except ValueError as e:  # SceneError is a ValueError too: named with --observed, as the folder's problems
        raise UsageError(f"score: --observed {args.observed!r}: {e}") from None
    # read as `simulate` reads a scene (scene.load: its size cap, UTF-8); a file that cannot be read or parsed
    # scores 0 with the reason, as an invalid prediction does
    candidates, problems = [], {}
    for k, path in enumerate(args.predictions):
        try:
            candidates.append(scenelib.load(path))
        except scenelib.SceneError as e:
            problems[k] = str(e)
    scored = iter(scorer.score(candidates, obs))
    scores = [
        scorer._invalid(problems[k], obs.flow is not None) if k in problems else next(scored)
        for k in range(len(args.predictions))
    ]
    if args.json:
        json.dump([s.to_json() for s in scores], sys.stdout)
        sys.stdout.write("\n")
    else:
        for path, s in zip(args.predictions, scores, strict=True):
            j = s.to_json()
            sys.stdout.write(
                f"{path}: iou {j['iou_first']}/{j['iou_full']} epe {j['epe_first']}/{j['epe_full']}"
                + ("" if s.valid else f" INVALID: {s.reason}")
                + "\n"
            )
    return 0
