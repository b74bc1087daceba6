"""Synthetic training data: sampled scenes, simulated, rendered, described, stored as a Hugging Face data set.

    aynamics generate --num 1000 --out data/synth --seed 0 [--shard k --num-shards n] [--config FILE] [key=value ...]
    aynamics generate --scenes my_scenes/ --out data/mine [key=value ...]    # your own scene files instead
    path = generate_dataset("data/tiny", num=8, seed=0, config=GenerateConfig(width=96, height=64))
    ds = datasets.load_from_disk(path)   # DatasetDict: train / validation / test

Scene i is drawn from `sampler.scene_seed(seed, i, attempt)` alone, so a record does not depend on the shard
that made it, on the number of workers or on earlier runs. Work is cut into chunks of `chunk_size` consecutive
indices; shard k of n makes the chunks c with c % n == k and writes each one atomically (a temporary folder
renamed to `chunks/NNNNNN`), so a killed run started again skips finished chunks and redoes the partial one
(same records): nothing is lost or duplicated. A second process started on chunks a live one is making (the same
command twice) is refused before it renders anything; shards of one run still write into one folder at once. When
every chunk of the run is on disk (from one run or from all shards writing into the same folder, or folders joined
with `assemble(out, sources)`) the chunks are concatenated in index order and split by a hash of (seed, index)
into the DatasetDict at `out` (storage: `dataset_store.py`).

With `--scenes` (`scene_files`, `generate(scenes=...)`) record i is made from the i-th of your scene files instead
of a sampled scene (`attempt` 0; the sampler's settings play no part): a file in a folder named train, validation
or test (any case) is in that split, the others
take the hash split; every file is validated and simulated before anything is written, and the run's manifest
holds each scene's hash and split by position (paths only for the reader), so a changed scene is refused as
another run instead of being mixed in, while the same files typed another way, or on another machine, resume.

Per record the only OpenGL work is one pass over the F sampled frames (RGB, segmentation, depth: `render_sampled`);
the flow of frame f to f + 1 comes from that depth and the poses at f and f + 1, so frames f + 1 are never drawn.
Images are PNG-encoded in the workers by `png_encode.png_bytes` (lossless; ~1.7× faster than Pillow's encoder).
`benchmarks/bench_generate.py` measures scenes per minute next to the render-only bound.

Columns (one row per scene; T = 31 states at 30 FPS, F = 10 sampled frames, N objects):
- `index` int64, `seed` int64 (global), `attempt` int32 (resamples after a diverged simulation), `split` str.
- `scene_yaml` str: canonical YAML (`scene.dump`); `reasoning` str: motion-reasoning text (`reasoning.py`);
  `target_answer` = `<answer>YAML</answer>`; `target_think` = `<think>REASONING</think>\\n\\n<answer>YAML</answer>`.
- `rgb`: list of F images (PNG, RGB, width × height) of video frames `frame_indices`.
- `flow`: list of F images: the exact forward flow from frame f to f + 1 on the Middlebury colour wheel, one
  magnitude scale per scene; `flow_max` float32 is that scale in pixels (saturation 1 = `flow_max`).
- `segmentation`: list of F images (PNG, mode L): pixel value = object index in `scene.objects` order + 1,
  0 = floor and sky.
- `frame_indices` list[int32] and `frame_times` list[float32] (s) of the sampled frames.
- `states`: struct of the rollout: `names` [N] str, `t` [T] s, `position` [T][N][3] m (world),
  `orientation` [T][N][4] wxyz, `linear_velocity` [T][N][3] m/s and `angular_velocity` [T][N][3] rad/s (world),
  `in_view` [T][N] bool (bounding sphere in the frustum), `visible` [F][N] bool (from segmentation),
  `rest_time` [N] s or null (still moving at the end).
- `contacts`: list of {`a`, `b` ("floor" or an object name), `start`, `end` (s)}: contact intervals per frame.
- `camera`: {`fovy` deg, `orientation` deg, `position` [3] m, `width`, `height`, `K` [3][3], `R` [3][3], `t` [3]}:
  OpenCV convention, x_cam = R @ x_world + t, pixel = K @ x_cam / z.
- `num_objects` int32, `shapes` list[str], `has_collision` bool (two objects touch at some frame).
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import os
import shlex
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from aynamics import reasoning as rs
from aynamics import sampler as smp
from aynamics.camera import sphere_in_view
from aynamics.dataset_store import (  # noqa: F401 - re-exported: the storage half of `generate`
    FORMAT_VERSION,
    MANIFEST,
    SPLITS,
    assemble,
    chunk_dir,
    chunk_ranges,
    claim_shard,
    features,
    remove_partial_chunks,
    shard_chunks,
    split_of,
    write_chunk,
    write_manifest,
)
from aynamics.generate_config import (  # noqa: F401 - re-exported: generate's settings
    LABELS_VERSION,
    GenerateConfig,
    apply_overrides,
    config_from_dict,
    load_config,
)
from aynamics.png_encode import png_bytes
from aynamics.scene import Scene, dump, parse
from aynamics.scene_files import (  # noqa: F401 - re-exported: the scenes of `generate --scenes`
    SceneFile,
    check_scene_run,
    scene_files,
    split_of_folder,
    warn_repeated_scenes,
)
from aynamics.simulate import MAX_UNPUSHED_GAIN, Rollout, bounding_radius, simulate, unpushed_energy_gain

if TYPE_CHECKING:  # rendering is imported inside the workers only
    from aynamics.render import Frames, Renderer


# --------------------------------------------------------------------------------------------
# One record
# --------------------------------------------------------------------------------------------
def sample_simulated(index: int, seed: int, config: GenerateConfig) -> tuple[Scene, Rollout, int]:
    """Scene `index` and its rollout; resampled (attempt 1, 2, ...) when placement fails, the simulation diverges, or
    an object gains energy with no other object touching it (`simulate.unpushed_energy_gain`: an upright cylinder
    launched by MuJoCo's plane-cylinder contact).

    Raises:
        RuntimeError: every attempt failed (the reasons are listed).
    """
    reasons = []
    for attempt in range(config.max_attempts):
        rng = np.random.default_rng(smp.scene_seed(seed, index, attempt))
        try:
            scene = smp.sample_scene(rng, config.sampler)
        except RuntimeError as e:
            reasons.append(str(e))
            continue
        rollout = simulate(scene, config.sim)
        if not rollout.valid:
            reasons.append(str(rollout.reason))
            continue
        gain = unpushed_energy_gain(scene, rollout)
        if gain.max() <= MAX_UNPUSHED_GAIN:
            return scene, rollout, attempt
        i = int(gain.argmax())  # MuJoCo's plane-cylinder contact launched it: not the scene's physics
        reasons.append(f"{rollout.names[i]} gained {gain[i]:.3g} J/kg with no object touching it")
    raise RuntimeError(f"scene {index} (seed {seed}): all {config.max_attempts} attempts failed: {'; '.join(reasons)}")


def appearance_seed(seed: int, index: int, attempt: int) -> int:
    """The seed of scene `index`'s randomised look (lights, textures): a function of (seed, index, attempt) alone."""
    return int(smp.scene_seed(seed, index, attempt).generate_state(1)[0])


def _png(image: np.ndarray) -> dict:
    return {"bytes": png_bytes(image), "path": None}


def _arr(x: np.ndarray) -> list:
    return np.asarray(x, np.float32).tolist()


def render_sampled(scene: Scene, rollout: Rollout, renderer: Renderer, config: GenerateConfig, seed: int) -> Frames:
    """The only OpenGL work of a record: RGB, segmentation and depth of the sampled video frames (`Frames`).

    The flow of sampled frame f to f + 1 needs the depth and segmentation at f and the poses at f and f + 1 only:
    frames f + 1 are not rendered (the record keeps no occlusion mask, the one thing they would add).
    """
    from aynamics.flow import sample_frames

    frames = sample_frames(len(rollout.t) - 1, config.stride)  # video frames 0..T-2
    return renderer.render(
        scene, rollout, seed=seed, textures_dir=config.textures_dir, backdrop=config.backdrop, states=frames
    )


def flow_images(frames: Frames, rollout: Rollout) -> tuple[np.ndarray, float]:
    """Colour-coded exact flow of each rendered frame f to f + 1 on one magnitude scale, and that scale (px).

    Returns:
        (F, H, W, 3) uint8 images (white where nothing moves) and the largest flow magnitude in pixels.
    """
    from aynamics import flow as flowlib

    flows = np.empty((*frames.segmentation.shape, 2), np.float32)  # (F, H, W, 2)
    for k, f in enumerate(frames.states):
        flows[k] = flowlib.motion_field(
            frames.depth[k],
            frames.segmentation[k],
            frames.camera,
            rollout.position[[f, f + 1]],
            rollout.orientation[[f, f + 1]],
            occlusion=False,
        )[0]
    on_object = frames.segmentation >= 0  # (F, H, W): the only pixels with flow (floor and sky are exactly zero)
    moving = flows[on_object]  # (P, 2)
    flow_max = float(np.hypot(moving[:, 0], moving[:, 1]).max()) if len(moving) else 0.0
    colours = np.full((*on_object.shape, 3), 255, np.uint8)  # zero flow is white
    colours[on_object] = flowlib.flow_to_color(moving, max_norm=flow_max)
    return colours, flow_max


def render_record_frames(scene: Scene, rollout: Rollout, renderer: Renderer, config: GenerateConfig, seed: int) -> dict:
    """RGB, segmentation and colour-coded exact flow (one magnitude scale per scene) of the sampled frames."""
    main = render_sampled(scene, rollout, renderer, config, seed)
    flow_color, flow_max = flow_images(main, rollout)
    return {
        "frames": main.states,
        "rgb": main.rgb,
        "segmentation": main.segmentation,
        "flow_color": flow_color,
        "flow_max": flow_max,
        "camera": main.camera,
    }


def make_record(index: int, seed: int, config: GenerateConfig, renderer, given: SceneFile | None = None) -> dict:
    """The full record of scene `index` (images PNG-encoded, ready for `datasets`): sampled, or the `given` scene
    file's (`scene_files`; its folder's split, else the hash split)."""
    if given is None:
        scene, rollout, attempt = sample_simulated(index, seed, config)
        split = split_of(seed, index, config.splits)
    else:
        scene, attempt = parse(given.text), 0
        rollout = simulate(scene, config.sim)
        if not rollout.valid:  # checked by scene_files before anything was written
            raise RuntimeError(f"{given.path}: the rollout is invalid: {rollout.reason}")
        split = given.split or split_of(seed, index, config.splits)
    scene_seed = appearance_seed(seed, index, attempt)
    fr = render_record_frames(scene, rollout, renderer, config, scene_seed)
    n = len(scene.objects)
    visible = rs.visibility(fr["segmentation"], n, config.min_pixels)
    times = rollout.t[fr["frames"]]
    inside = rs.centres_in_picture(fr["camera"], rollout.position[fr["frames"]])
    text = rs.reasoning_text(scene, rollout, visible, times, seed=scene_seed, in_picture=inside)
    yaml_text = dump(scene)
    cam = fr["camera"]
    radii = np.array([bounding_radius(o) for o in scene.objects])
    in_view = sphere_in_view(cam, rollout.position, radii)  # in the rendered view (the rollout's is 480×320)
    return {
        "index": index,
        "seed": seed,
        "attempt": attempt,
        "split": split,
        "scene_yaml": yaml_text,
        "reasoning": text,
        "target_answer": rs.answer_target(yaml_text),
        "target_think": rs.think_target(text, yaml_text),
        "rgb": [_png(im) for im in fr["rgb"]],
        "flow": [_png(im) for im in fr["flow_color"]],
        "flow_max": fr["flow_max"],
        "segmentation": [_png((s + 1).astype(np.uint8)) for s in fr["segmentation"]],
        "frame_indices": fr["frames"].tolist(),
        "frame_times": _arr(times),
        "states": {
            "names": list(rollout.names),
            "t": _arr(rollout.t),
            "position": _arr(rollout.position),
            "orientation": _arr(rollout.orientation),
            "linear_velocity": _arr(rollout.linear_velocity),
            "angular_velocity": _arr(rollout.angular_velocity),
            "in_view": in_view.tolist(),
            "visible": visible.tolist(),
            "rest_time": list(rollout.rest_time),
        },
        "contacts": [{"a": c.a, "b": c.b, "start": c.start, "end": c.end} for c in rollout.contacts],
        "camera": {
            "fovy": scene.camera.fovy,
            "orientation": scene.camera.orientation,
            "position": list(scene.camera.position),
            "width": cam.width,
            "height": cam.height,
            "K": cam.K.tolist(),
            "R": cam.R.tolist(),
            "t": cam.t.tolist(),
        },
        "num_objects": n,
        "shapes": list(scene.structure),
        "has_collision": any(c.b != "floor" for c in rollout.contacts),
    }


_WORKER: dict = {}


def _worker_init(config: GenerateConfig) -> None:
    from aynamics.render import Renderer

    _WORKER["renderer"] = Renderer(config.width, config.height)
    _WORKER["config"] = config


def _worker_record(job: tuple[int, int, SceneFile | None]) -> dict:
    index, seed, given = job
    return make_record(index, seed, _WORKER["config"], _WORKER["renderer"], given)


def _records(jobs: list[tuple[int, int, SceneFile | None]], config: GenerateConfig) -> Iterator[dict]:
    """Records of the jobs in order, made in `config.workers` processes (or here when 0)."""
    if not jobs:
        return
    if config.workers == 0:
        _worker_init(config)
        try:
            yield from map(_worker_record, jobs)
        finally:
            _WORKER.pop("renderer").close()
        return
    ctx = mp.get_context("spawn")  # a fresh interpreter per worker: no OpenGL state crosses a fork
    with ctx.Pool(min(config.workers, len(jobs)), initializer=_worker_init, initargs=(config,)) as pool:
        yield from pool.imap(_worker_record, jobs, chunksize=1)


def generate(
    out_dir: str | os.PathLike,
    num: int,
    seed: int = 0,
    config: GenerateConfig | None = None,
    shard: int = 0,
    num_shards: int = 1,
    progress: bool = True,
    scenes: Sequence[SceneFile] | None = None,
) -> Path | None:
    """Make this shard's missing chunks of a run; assemble the DatasetDict when every chunk is on disk.

    With `scenes` (`scene_files`: your own scenes) record i is made from scenes[i] instead of a sampled scene, and
    `num` must be their number.

    Returns:
        The data set folder (`datasets.load_from_disk(path)`), or None while other shards' chunks are missing.
    """
    from tqdm.auto import tqdm

    config = config or GenerateConfig()
    if num < 1 or seed < 0:
        raise ValueError(f"num = {num}, seed = {seed}: need num >= 1 and seed >= 0")
    if scenes is not None and len(scenes) != num:
        raise ValueError(f"num = {num} with {len(scenes)} scene files: must be their number")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file, not a folder")
    if out.is_dir() and not (out / MANIFEST).is_file():  # not a run of ours: assembly replaces train/ test/ ...
        other = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
        if other:
            raise ValueError(
                f"--out {str(out)!r} holds other files ({other[0]!r}, ...) and no {MANIFEST}: give a new or empty "
                "folder, or one an earlier generate wrote"
            )
    mine = shard_chunks(num, config.chunk_size, shard, num_shards)  # checked before anything is written
    settings = config.to_json()
    manifest = {"format": FORMAT_VERSION, "num": num, "seed": seed, "config": settings}
    check_scene_run(out, scenes)
    if scenes is not None:
        warn_repeated_scenes(
            scenes, seed, config
        )  # the scenes decide the records (a changed or reordered one is another run), not the sampler
        settings.pop("sampler")
        settings["scenes"] = [{"sha256": f.sha256, "split": f.split} for f in scenes]
        manifest["scene_files"] = [f.path for f in scenes]  # for the reader; not compared on a resume
    with claim_shard(out, manifest, shard, num_shards):  # a second writer of these chunks is refused here
        (out / "chunks").mkdir(exist_ok=True)
        ranges = chunk_ranges(num, config.chunk_size)
        remove_partial_chunks(out, mine)  # leftovers of a killed run of this shard
        todo = [c for c in mine if not chunk_dir(out, c).exists()]
        jobs = [(i, seed, None if scenes is None else scenes[i]) for c in todo for i in ranges[c]]
        bar = tqdm(
            total=sum(len(ranges[c]) for c in mine),
            initial=sum(len(ranges[c]) for c in mine) - len(jobs),
            unit="scene",
            desc=f"generate shard {shard}/{num_shards}",
            disable=not progress,
            smoothing=0.1,
        )
        pending: list[dict] = []
        chunks = iter(todo)
        current = next(chunks, None)
        with bar:
            for record in _records(jobs, config):
                pending.append(record)
                bar.update(1)
                if current is not None and len(pending) == len(ranges[current]):
                    write_chunk(out, current, pending)
                    pending, current = [], next(chunks, None)
        if all(chunk_dir(out, c).exists() for c in range(len(ranges))):
            return assemble(out)
    return None


def generate_dataset(
    out_dir: str | os.PathLike, num: int, seed: int = 0, config: GenerateConfig | None = None, progress: bool = False
) -> Path:
    """Generate a whole data set in one call (e.g. a tiny one for tests) and return its folder."""
    path = generate(out_dir, num, seed, config, progress=progress)
    assert path is not None  # one shard makes every chunk
    return path


# --------------------------------------------------------------------------------------------
# Command line: aynamics generate
# --------------------------------------------------------------------------------------------
def add_generate_parser(sub) -> None:
    """Register `aynamics generate` on the CLI's subparsers."""
    p = sub.add_parser(
        "generate",
        help="generate the synthetic data set (scenes, frames, flow, masks, states, reasoning) with HF datasets",
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--num", type=int, help="number of sampled scenes of the whole run (all shards)")
    what.add_argument(
        "--scenes",
        nargs="+",
        metavar="PATH",
        help="your own scenes instead: YAML files or folders of them (a folder's train/, validation/, test/ "
        "subfolders set the split; other files take the hash split)",
    )
    p.add_argument("--out", required=True, help="output folder (chunks, then the DatasetDict for load_from_disk)")
    p.add_argument("--seed", type=int, default=0, help="global seed; scene i depends only on (seed, i) (default 0)")
    p.add_argument("--shard", type=int, default=0, help="this shard's number k in [0, n) (default 0)")
    p.add_argument("--num-shards", type=int, default=1, help="number of shards n (default 1)")
    p.add_argument("--config", help="YAML config file (see conf/generate/default.yaml)")
    p.add_argument("--workers", type=int, help="rendering processes (default: config, 2)")
    p.add_argument("--assemble", nargs="*", metavar="DIR", help="only assemble: join chunks of --out or of DIRs")
    p.add_argument("--in-context", action="store_true", help="also write in_context/ (3 prompt examples)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", help="config overrides key=value, e.g. width=96 sampler.max_objects=2")
    p.set_defaults(run=run_generate)


def run_generate(args) -> int:
    """Run `aynamics generate` (errors become `UsageError`: exit 2 with one message)."""
    from aynamics.cli import UsageError, missing_file_message, warnings_as_lines

    sampled = [o for o in args.overrides if o.startswith(("sampler.", "sampler="))]  # sampler.x=1, sampler={...}
    if args.scenes is not None and sampled:  # taken without a word, and changing nothing
        raise UsageError(
            f"generate: {' '.join(sampled)} sets the scene sampler, which --scenes does not use (the scene files are "
            "the scenes); drop it"
        )
    try:
        config = load_config(args.config) if args.config else GenerateConfig()
        config = apply_overrides(config, args.overrides)
        if args.workers is not None:
            config = dataclasses.replace(config, workers=args.workers)
        if args.assemble is not None:  # the chunks hold the records: the scene files are not read again
            path = assemble(args.out, args.assemble or None)
        else:
            scenes = None if args.scenes is None else scene_files(args.scenes, config)
            num = len(scenes) if scenes is not None else args.num
            with warnings_as_lines("generate", "--scenes: "):  # the same scene in two splits
                path = generate(args.out, num, args.seed, config, args.shard, args.num_shards, not args.quiet, scenes)
        if path is None:
            which = f"--num {args.num}" if args.scenes is None else "--scenes " + shlex.join(args.scenes)
            print(f"shard {args.shard}/{args.num_shards} done; the data set is assembled by the last shard to finish")
            print(f"(or run: aynamics generate {which} --out {shlex.quote(args.out)} --assemble)")
            return 0
        if args.in_context:
            from aynamics.incontext import write_in_context

            print(f"in-context examples: {write_in_context(path)}")
        print(f"data set: {path} (datasets.load_from_disk)")
    except FileNotFoundError as e:
        raise UsageError(f"generate: {missing_file_message(e)}") from None
    except (ValueError, RuntimeError) as e:
        raise UsageError(f"generate: {e}") from None
    return 0
