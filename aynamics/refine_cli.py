"""The `aynamics refine` command and the before/after animation of a refinement.

    aynamics refine PRED.yaml [PRED2.yaml ...] --observed SCENE.yaml|DIR [--budget 1000] [--seconds 60]
        [--params position,linear_velocity] [--seed 0] [--stop-at 0.95] [--out REFINED.yaml]
        [--animation before_after.gif] --json         # or .mp4

`--json` prints `{"iou_full_before", "iou_full_after", "iou_first_after", "simulations", "refined_yaml", ...}`.
"""

from __future__ import annotations

import math

import numpy as np

from aynamics.refine_space import DEFAULT_PARAMS, DEFAULT_SIGMA_SCALE, OBJECT_GROUPS, SCENE_GROUPS

# --------------------------------------------------------------------------------------------
# Before/after animation and the CLI
# --------------------------------------------------------------------------------------------
_PALETTE = np.array(
    [[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180], [70, 240, 240], [240, 50, 230]]
)


def colour_segmentation(segmentation: np.ndarray) -> np.ndarray:
    """(F, h, w) object indices (-1 background) -> (F, h, w, 3) uint8: one colour per object, dark background."""
    seg = np.asarray(segmentation)
    out = np.full((*seg.shape, 3), 30, np.uint8)
    fg = seg >= 0
    out[fg] = _PALETTE[seg[fg] % len(_PALETTE)]
    return out


def write_refine_animation(result, observed, path, scale: int = 3) -> str:
    """Animation (.gif or .mp4) of the observed segmentation next to the start's and the refined scene's (`result`, a
    `aynamics.refine.RefineResult`), at the sampled frames.

    Raises:
        aynamics.render.RenderError: no headless OpenGL.
    """
    from aynamics.render import Renderer
    from aynamics.simulate import simulate_batch
    from aynamics.whatif import write_animation

    rollouts = simulate_batch([result.start, result.scene], observed.config, nthread=1)
    panels = [colour_segmentation(observed.segmentation)]
    with Renderer(observed.width, observed.height) as r:
        for scene, rollout in zip((result.start, result.scene), rollouts, strict=True):
            frames = r.render(scene, rollout, rgb=False, depth=False, states=observed.frames)
            panels.append(colour_segmentation(frames.segmentation))
    panels = [p.repeat(scale, axis=1).repeat(scale, axis=2) for p in panels]
    labels = [
        "observed",
        f"before IoU {result.before.iou_full:.2f}",
        f"after IoU {result.after.iou_full:.2f}",
    ]
    return str(write_animation(path, [panels], [labels], fps=5))


def add_refine_command(sub) -> None:
    """Register `aynamics refine`."""
    p = sub.add_parser("refine", help="fit a predicted scene to an observed video with CMA-ES")
    p.add_argument("pred", nargs="+", help="predicted scene YAML (several: warm start from the best)")
    p.add_argument("--observed", required=True, help="ground-truth scene YAML, or a folder with segmentation.npy")
    p.add_argument("--budget", type=int, default=1000, help="simulations in all (default 1000)")
    p.add_argument("--seconds", type=float, default=60.0, help="wall-time budget in seconds (default 60)")
    p.add_argument(
        "--params",
        default=",".join(DEFAULT_PARAMS),
        help=f"comma-separated groups from {', '.join(OBJECT_GROUPS + SCENE_GROUPS)}, or NAME.group "
        f"(default {','.join(DEFAULT_PARAMS)})",
    )
    p.add_argument("--seed", type=int, default=0, help="CMA-ES seed (default 0)")
    p.add_argument(
        "--sigma-scale",
        type=float,
        default=DEFAULT_SIGMA_SCALE,
        help="multiplies the initial CMA-ES steps (0.3 m, 0.5 m/s, ...): lower for a prediction already close to "
        f"the video (e.g. 0.1 when its IoU is high and the objects are small; default {DEFAULT_SIGMA_SCALE:g})",
    )
    p.add_argument(
        "--stop-at",
        type=float,
        default=None,
        help="stop once the objective reaches this: IoU_full - 0.01 x EPE_full (px at 480 wide) when the video has "
        "flow, IoU_full alone when not (default: spend the budget)",
    )
    p.add_argument(
        "--no-separate",
        action="store_true",
        help="start from the prediction as it is, even when it starts objects inside each other or the floor "
        "(default: score it separated too, `aynamics.separate`, and start from the better)",
    )
    p.add_argument("--out", help="write the refined scene YAML here")
    p.add_argument(
        "--animation", help="write a before/after segmentation animation here, .gif or .mp4 (needs headless OpenGL)"
    )
    p.add_argument("--json", action="store_true", help="print scores before/after, simulations and the YAML")
    p.set_defaults(run=run_refine_command)


def run_refine_command(args) -> int:
    """`aynamics refine`: refine, then print/write; usage errors exit 2 with a one-paragraph message."""
    from pathlib import Path

    from aynamics.cli import UsageError, load_scene, refuse_rendered_file
    from aynamics.observation import Observation
    from aynamics.refine import refine
    from aynamics.scene import load

    if args.budget < 1 or not args.seconds > 0:  # nan fails the comparison; inf seconds: the budget alone
        raise UsageError(f"refine: --budget {args.budget} and --seconds {args.seconds:g} must be > 0")
    if not 0 < args.sigma_scale < math.inf:
        raise UsageError(f"refine: --sigma-scale {args.sigma_scale:g} must be a finite number > 0")
    if args.seed < 0:  # NumPy refused it deep in the search ('expected non-negative integer'), or the track stage
        raise UsageError(f"refine: --seed {args.seed}: must be >= 0")  # took seed + 1 and ran: -1 was sometimes fine
    if args.stop_at is not None and math.isnan(args.stop_at):
        raise UsageError("refine: --stop-at nan: must be a number (an objective value such as 0.95)")
    if args.animation:  # before the search, not after its whole budget (helper-38)
        from aynamics.render import gl_available
        from aynamics.whatif import animation_kind

        try:
            animation_kind(args.animation)
        except ValueError as e:
            raise UsageError(f"refine --animation {args.animation!r}: {e}") from None
        ok, why = gl_available()
        if not ok:
            raise UsageError(f"refine --animation {args.animation!r}: needs headless OpenGL, which fails here: {why}")
    if args.out:  # before the search, not after its whole budget: a refined scene is not lost for a typo
        out = Path(args.out)
        if out.is_dir():
            raise UsageError(f"refine: --out {args.out!r} is a folder: give the scene file to write (REFINED.yaml)")
        if not out.parent.is_dir():
            raise UsageError(f"refine: cannot write --out {args.out!r}: folder {str(out.parent)!r} does not exist")
    preds = [load_scene("refine", p) for p in args.pred]
    odd = next((k for k, s in enumerate(preds) if s.structure != preds[0].structure), None)
    if odd is not None:  # the search starts from the best of them: one set of objects (named with their files)
        first, other = (f"{args.pred[k]!r} has {list(preds[k].structure)}" for k in (0, odd))
        raise UsageError(
            f"refine: the predicted scenes must hold the same objects in the same order (a warm start from the "
            f"best): {first}, {other}"
        )
    obs_path = Path(args.observed)
    refuse_rendered_file("refine", args.observed)
    try:
        if obs_path.is_dir():
            observed = Observation.from_dir(obs_path)
        else:
            observed = Observation.from_scene(load(str(obs_path)))
    except ValueError as e:
        raise UsageError(f"refine: --observed {args.observed!r}: {e}") from None
    params = [x.strip() for x in args.params.split(",") if x.strip()]
    try:
        result = refine(
            preds,
            observed,
            params=params,
            budget=args.budget,
            seconds=args.seconds,
            seed=args.seed,
            stop_at=args.stop_at,
            sigma_scale=args.sigma_scale,
            separate=not args.no_separate,
        )
    except ValueError as e:  # refine's own messages start with "refine: " already
        raise UsageError(f"refine: {str(e).removeprefix('refine: ')}") from None
    if args.out:
        try:
            Path(args.out).write_text(result.yaml)
        except OSError as e:
            raise UsageError(f"refine: cannot write --out {args.out!r}: {e.strerror or e}") from None
    record = result.to_json()
    if args.animation:
        from aynamics.render import RenderError

        try:
            record["animation"] = write_refine_animation(result, observed, args.animation)
        except (RenderError, ValueError, OSError) as e:
            raise UsageError(f"refine --animation {args.animation!r}: {e}") from None
    if args.json:
        import json
        import sys

        json.dump({k: v for k, v in record.items() if k != "trace"} | {"trace": record["trace"]}, sys.stdout)
        sys.stdout.write("\n")
    elif not args.out:
        print(result.yaml, end="")
    return 0
