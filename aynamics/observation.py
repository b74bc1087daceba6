"""An observed video at the scorer's resolution: `Observation`, from a scene or from a folder of masks and flow.

    obs = Observation.from_scene(scene)         # the scene's own video, by the scorer's ray casting
    obs = Observation.from_dir("render_out/")   # masks (and flow) on disk, at `scoring_size`

Observed folder layout (what `aynamics render --out DIR` writes; all frames are the full video, frame k = state k):
    segmentation.npy    (T, H, W) int, -1 background, else object index   -- or --
    segmentation/*.png  one mask per frame in natural name order (2.png before 10.png): 0 background, v > 0
                        object v - 1 (8/16-bit grey, or a palette PNG's index, as DAVIS-style annotations), or
                        colour masks where each distinct non-black colour is one object (numbered in increasing
                        0xRRGGBB order; with names in meta.json, give "colours" too)
    flow.npy            optional (T-1, H, W, 2) float pixels at H×W (dx right, dy down), flow k: frame k -> k+1;
                        NaN, infinite or longer than MAX_FLOW_SIZES image sizes only where occlusion.npy marks it
    occlusion.npy       optional (T-1, H, W) bool, True where the observed flow is occluded
    meta.json           optional {"names": [...], "fps": 30}: object names for matching by name; with colour
                        masks also "colours": [[r, g, b], ...], the colour of each named object
The sampled frames are `sample_frames(T)`; masks and flow are resampled to the scorer's resolution by taking the
pixel nearest each low-resolution pixel centre (flow vectors scaled by the width ratio), and candidates are cast
through those video pixels' centres (`raycast.SampleGrid`), so a true scene meets its own masks exactly; a video
of fewer than 80 rows is scored at its own size. `aynamics.scorer` scores candidates against an Observation.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aynamics import simulate as sim
from aynamics.flow import sample_frames
from aynamics.raycast import SampleGrid, cast_group
from aynamics.scene import Scene, is_whole, require_scene
from aynamics.video_io import image_files

WIDTH, HEIGHT = 120, 80  # scorer resolution: a quarter of 480×320 per side
VIDEO_FRAMES = 30  # frames of an observed video (states 0..29 of a 1 s rollout at 30 FPS)
MAX_FLOW_SIZES = 10  # observed flow longer than this many image sizes (width or height, the larger) is refused
MAX_OBJECT_ID = int(np.iinfo(np.int16).max) - 1  # observed masks are held as int16 (-1 background)


@dataclass(frozen=True)
class Observation:
    """An observed video at the scorer's resolution.

    Attributes:
        segmentation: (F, h, w) int16 at the sampled frames, -1 background.
        frames: (F,) video frame index of each sampled frame (default 0, 3, ..., 27).
        width, height: resolution (w, h) of the arrays.
        flow: (F, h, w, 2) float32 flow from each sampled frame k to k + 1, pixels at this resolution, or None.
        occluded: (F, h, w) bool, True where the observed flow is occluded, or None.
        names: object names for matching by name, or None.
        fps: frames per second of the video.
        substeps: physics steps per frame candidates are simulated with (a generated data set's own), or None:
            `SimConfig`'s default for `fps`.
        video_shape: (T, H, W) of the full video it was read from (`from_dir`: every frame's masks), or None.
        grid: where each pixel was taken from a larger video (`raycast.SampleGrid`: candidates are cast at the same
            points), or None: at its own pixel centres.
    """

    segmentation: np.ndarray
    frames: np.ndarray
    width: int
    height: int
    flow: np.ndarray | None = None
    occluded: np.ndarray | None = None
    names: tuple[str, ...] | None = None
    fps: int = sim.FPS
    video_shape: tuple[int, int, int] | None = None
    grid: SampleGrid | None = None
    substeps: int | None = None  # physics steps per frame of the video's simulation (None: round(240 / fps))

    def __post_init__(self):
        f = len(self.frames)
        if self.grid is not None and (len(self.grid.u), len(self.grid.v)) != (self.width, self.height):
            raise ValueError(f"sample grid of {len(self.grid.u)}×{len(self.grid.v)} for {self.width}×{self.height}")
        if self.segmentation.shape != (f, self.height, self.width):
            raise ValueError(
                f"segmentation shape {self.segmentation.shape} != (frames, h, w) = {(f, self.height, self.width)}"
            )
        if self.flow is not None and self.flow.shape != (f, self.height, self.width, 2):
            raise ValueError(f"flow shape {self.flow.shape} != (frames, h, w, 2) = {(f, self.height, self.width, 2)}")
        if f == 0 or int(np.min(self.frames)) < 0:
            raise ValueError(f"frames {list(self.frames)}: need at least one frame, all >= 0")
        self._check_values()

    def _check_values(self) -> None:
        """What `from_dir` checks in the files, for an Observation built directly (~0.07 ms at 120×80×10): float ids
        were truncated (0.7 counted as object 0), int 0/1 occlusion inverted to -1/-2 marked every pixel as seen,
        and NaN flow dropped out of the EPE averages (a wrong candidate scored EPE 0). Flow beyond `MAX_FLOW_SIZES`
        is refused in files only (a unit error there); a generated record's exact flow may be that large."""
        seg, flow, occ = self.segmentation, self.flow, self.occluded
        if seg.dtype.kind != "i" or (seg.size and int(seg.min()) < -1):
            low = f", lowest id {int(seg.min())}" if seg.dtype.kind == "i" else ""
            raise ValueError(
                f"segmentation dtype {seg.dtype}{low}: must be signed int ids, -1 background, >= 0 objects"
            )
        if occ is not None and (not isinstance(occ, np.ndarray) or occ.dtype != bool or occ.shape != seg.shape):
            raise ValueError(
                f"occluded {type(occ).__name__} of shape {np.shape(occ)} dtype {getattr(occ, 'dtype', None)}: must be "
                f"a bool array of the segmentation's shape {seg.shape}"
            )
        if flow is None:
            return
        if flow.dtype.kind not in "iuf":
            raise ValueError(f"flow dtype {flow.dtype}: must be numbers (pixels per frame)")
        if np.isfinite(flow.sum(dtype=np.float64)):  # the common case at one pass (float32 cannot overflow it)
            return
        bad = ~np.isfinite(flow).all(-1)
        if occ is not None:
            bad &= ~occ  # occluded flow is never read
        if bad.any():
            k, v, u = (int(i) for i in np.argwhere(bad)[0])
            raise ValueError(
                f"flow[{k}, {v}, {u}] = {flow[k, v, u].tolist()}: {int(bad.sum())} pixels not occluded hold NaN or "
                "infinite flow: mark pixels without flow occluded"
            )

    @property
    def config(self) -> sim.SimConfig:
        """Simulation long enough for the last sampled frame and its flow target (frame + 1)."""
        frames = max(int(np.max(self.frames)) + 1, VIDEO_FRAMES)
        return sim.SimConfig(duration=frames / self.fps, fps=self.fps, substeps=self.substeps)

    @classmethod
    def from_scene(
        cls,
        scene: Scene,
        *,
        width: int = WIDTH,
        height: int = HEIGHT,
        frames: Sequence[int] | None = None,
        fps: int = sim.FPS,
        nthread: int | None = None,
        substeps: int | None = None,
    ) -> Observation:
        """Observe a scene by the scorer's own ray casting (so a scene scored against itself is exact), at video
        `frames` (default `sample_frames(30)`) of a video at `fps`, simulated with `substeps` physics steps per
        frame (None: the default for `fps`; a generated data set's own: `dataset_store.dataset_substeps`).

        Raises:
            ValueError: the scene's rollout is invalid (diverged), with the simulator's reason; a size, frame
                rate or frame list that is not whole numbers in range, naming it.
            TypeError: `scene` is not a Scene.
        """
        require_scene(scene, "Observation.from_scene: scene")  # a YAML text failed on "... no attribute 'structure'"
        for name, v, top in (("width", width, 4096), ("height", height, 4096)):
            if not is_whole(v) or not 1 <= v <= top:  # width 0: empty
                raise ValueError(f"Observation.from_scene: {name} = {v!r}: must be a whole number in [1, {top}]")
        try:  # 30, 30.0 and numpy's 30 alike, as `SimConfig` takes them (a clock read from JSON is a float)
            fps = sim.whole_in_range(fps, "fps")
        except ValueError as e:
            raise ValueError(f"Observation.from_scene: {e}") from None
        if frames is not None:  # [1.7] was taken as frame 1, [[0, 3]] failed broadcasting in the ray cast
            given = np.asarray(frames)
            if given.ndim != 1 or not (
                np.issubdtype(given.dtype, np.integer) or (given.dtype.kind == "f" and (given == np.round(given)).all())
            ):
                raise ValueError(f"Observation.from_scene: frames = {frames!r}: must be a list of whole frame indices")
        frames = sample_frames(VIDEO_FRAMES) if frames is None else np.asarray(frames, int)
        shell = cls(np.zeros((len(frames), height, width), np.int16), frames, width, height, fps=fps, substeps=substeps)
        out = cast_group([scene], scene.structure, frames, width, height, shell.config, nthread, with_next=True)
        if out.reasons[0] is not None:
            raise ValueError(f"observed scene cannot be simulated: {out.reasons[0]}")
        return cls(
            out.seg[0], frames, width, height, out.dense_flow[0], out.occluded[0], scene.names, fps, substeps=substeps
        )

    @classmethod
    def from_dir(cls, path: str | Path, *, width: int | None = None, height: int | None = None) -> Observation:
        """Load an observed video folder (layout in the module docstring), at `scoring_size` (default: HEIGHT rows
        at the video's aspect ratio).

        Raises:
            FileNotFoundError: the folder or its segmentation is missing.
            ValueError: arrays of the wrong shape or type, naming the file; a size off the video's aspect ratio.
        """
        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(2, f"observed folder {str(root)!r} does not exist", str(root))
        seg, colours = _load_segmentation(root)  # (T, H, W); colour masks: each id's 0xRRGGBB code
        lo, hi = int(seg.min(initial=-1)), int(seg.max(initial=-1))
        if lo < -1 or hi > MAX_OBJECT_ID:  # the int16 masks below wrapped 40000 to -25536: silently background
            bad = lo if lo < -1 else hi
            raise ValueError(
                f"{root / 'segmentation'}: object id {bad}: ids must be -1 (background) or 0..{MAX_OBJECT_ID} "
                "(a grey PNG mask: 0 background, v = id + 1)"
            )
        n_frames, full_h, full_w = seg.shape
        if seg.size == 0:  # 0 frames read "sample_frames(n_frames=0, stride=3): both must be >= 1", naming no file
            raise ValueError(
                f"{root / 'segmentation'}: {n_frames} frame(s) of {full_w}×{full_h} pixels: need at least one frame "
                "of at least 1×1"
            )
        width, height = scoring_size(full_w, full_h, width, height)
        frames = sample_frames(n_frames)
        grid = SampleGrid.nearest(full_w, full_h, width, height)
        sub = np.ix_(frames, grid.rows, grid.columns)
        flow = occluded = None
        if (root / "flow.npy").is_file():
            full_flow = _load_npy(root / "flow.npy", float)
            if full_flow.ndim != 4 or full_flow.shape[1:] != (full_h, full_w, 2) or len(full_flow) < frames[-1] + 1:
                raise ValueError(
                    f"{root / 'flow.npy'}: shape {full_flow.shape}, "
                    f"expected (>= {frames[-1] + 1}, {full_h}, {full_w}, 2)"
                )
            flow = (full_flow[sub] * (width / full_w)).astype(np.float32)
            if (root / "occlusion.npy").is_file():
                occ = _load_npy(root / "occlusion.npy", bool)
                if occ.shape != full_flow.shape[:-1]:
                    raise ValueError(f"{root / 'occlusion.npy'}: shape {occ.shape}, expected {full_flow.shape[:-1]}")
                occluded = occ[sub]
            bad = ~np.isfinite(flow).all(-1)
            if occluded is not None:  # no flow where occlusion.npy says so: never read
                flow[bad & occluded] = 0.0
                bad &= ~occluded
            if bad.any():  # NaN would drop out of the EPE averages: every prediction would score 0 there
                f = int(np.argwhere(bad)[0][0])
                raise ValueError(
                    f"{root / 'flow.npy'}: {int(bad.sum())} sampled pixels hold NaN or infinite flow "
                    f"(the first in flow {frames[f]}): mark pixels without flow in occlusion.npy instead"
                )
            # a pixel cannot move MAX_FLOW_SIZES image sizes in a frame: such a value is a unit or file error, and
            # it swamps every candidate's EPE (one pixel of 1e38 px gave the true scene an EPE of 1.9e36 px)
            limit = MAX_FLOW_SIZES * max(width, height)
            huge = np.hypot(flow[..., 0].astype(np.float64), flow[..., 1]) > limit
            if occluded is not None:
                huge &= ~occluded
            if huge.any():
                f, v, u = (int(k) for k in np.argwhere(huge)[0])
                value = full_flow[frames[f], grid.rows[v], grid.columns[u]].tolist()
                raise ValueError(
                    f"{root / 'flow.npy'}: {int(huge.sum())} sampled pixels move more than {MAX_FLOW_SIZES} image "
                    f"sizes in one frame (the first in flow {frames[f]}, row {grid.rows[v]}, column "
                    f"{grid.columns[u]}: {value} px): is it in pixels per frame?"
                )
        names, fps = None, sim.FPS
        if (root / "meta.json").is_file():
            try:
                meta = json.loads((root / "meta.json").read_text())
                names = meta.get("names")
                fps = meta.get("fps", sim.FPS)
            except (ValueError, TypeError, AttributeError) as e:
                raise ValueError(f"{root / 'meta.json'}: not a JSON object with names/fps ({e})") from None
            if names is not None:
                if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
                    raise ValueError(f"{root / 'meta.json'}: names = {names!r}: must be a list of object names")
                names = tuple(names)
                if colours is not None:  # ids of colour masks follow the colour codes, not the names' order
                    seg = _colour_ids(root / "meta.json", meta.get("colours"), names, colours, seg)
            if not (isinstance(fps, int) and not isinstance(fps, bool) and 1 <= fps <= 1000):
                raise ValueError(
                    f"{root / 'meta.json'}: fps = {fps!r}: must be a whole number of frames per second in [1, 1000]"
                )
        return cls(seg[sub].astype(np.int16), frames, width, height, flow, occluded, names, fps, seg.shape, grid)


def scoring_size(full_w: int, full_h: int, width: int | None = None, height: int | None = None) -> tuple[int, int]:
    """The scorer's (width, height) for a video of full_w × full_h pixels: the video's aspect ratio, HEIGHT rows
    (the video's own size when smaller) unless `height` (or `width`) is given. Candidates are ray-cast through
    their camera, whose field of view is vertical: at another aspect ratio they would see a wider or narrower view
    than the video and score low even when right (112×80 videos scored at 120×80 gave their own true scenes IoU
    0.56-0.90; at 112×80, 0.99-1.00).

    Raises:
        ValueError: a size that is not positive, or a width and height off the video's aspect by more than a pixel.
    """
    if full_w < 1 or full_h < 1:
        raise ValueError(f"video size {full_w}×{full_h}: must be positive")
    if width is None and height is None:
        height = min(HEIGHT, full_h)  # a smaller video at its own size: upsampling its masks adds only errors
    if height is None:
        height = max(1, round(width * full_h / full_w))
    if width is None:
        width = max(1, round(height * full_w / full_h))
    if width < 1 or height < 1:
        raise ValueError(f"scoring size {width}×{height}: must be positive")
    if abs(width - height * full_w / full_h) > 1.0:
        raise ValueError(
            f"scoring size {width}×{height} is off the video's aspect ratio ({full_w}×{full_h}): candidates would be "
            f"seen through a wider or narrower view; give the height alone (width {round(height * full_w / full_h)})"
        )
    return width, height


def _load_npy(path: Path, kind: type) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable .npy array ({e})") from None
    if kind is bool:
        return a.astype(bool)
    if not np.issubdtype(a.dtype, np.number):
        raise ValueError(f"{path}: dtype {a.dtype}, expected numbers")
    return a


def _colour_ids(meta: Path, listed, names: tuple[str, ...], codes: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Renumber colour-mask ids (`codes[j]`: 0xRRGGBB of id j) so that id k is the object of `listed[k]`, the colour
    meta.json gives `names[k]`."""
    if listed is None:
        raise ValueError(
            f"{meta}: names {list(names)} with colour masks: the masks number their objects by colour code "
            f'(0xRRGGBB: {", ".join(f"#{c:06x}" for c in codes)}), not in the names\' order; add "colours": '
            "[[r, g, b], ...], one per name, or use grey masks (value v = object v - 1)"
        )
    ok = isinstance(listed, list) and len(listed) == len(names)
    ok = ok and all(
        isinstance(c, list) and len(c) == 3 and all(isinstance(x, int) and 0 <= x <= 255 for x in c) for c in listed
    )
    if not ok:
        raise ValueError(f"{meta}: colours = {listed!r}: must be one [r, g, b] (0-255) per name ({len(names)})")
    want = [(r << 16) | (g << 8) | b for r, g, b in listed]
    missing = [f"#{c:06x}" for c in codes if c not in want]
    if missing:
        raise ValueError(f'{meta}: the masks hold colour(s) {missing} that "colours" does not list')
    lut = np.array([want.index(int(c)) for c in codes] + [-1])  # id -1 (background) stays -1
    return lut[seg]


def _load_segmentation(root: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(T, H, W) object ids (-1 background) and, for colour masks, the 0xRRGGBB code of each id (else None)."""
    if (root / "segmentation.npy").is_file():
        seg = _load_npy(root / "segmentation.npy", int)
        if seg.ndim != 3 or not np.issubdtype(seg.dtype, np.integer):
            raise ValueError(
                f"{root / 'segmentation.npy'}: shape {seg.shape} dtype {seg.dtype}, expected (T, H, W) int"
            )
        if np.issubdtype(seg.dtype, np.unsignedinteger):  # no -1: 0 would be object 0, background everywhere
            raise ValueError(
                f"{root / 'segmentation.npy'}: dtype {seg.dtype} cannot hold the background id -1: save signed "
                "ids (-1 background, 0, 1, ... objects), e.g. (masks.astype(int) - 1) for masks with 0 background, "
                "or write segmentation/*.png (0 background)"
            )
        return seg, None
    folder = root / "segmentation"
    files = image_files(folder, (".png",))  # natural order: 2.png before 10.png
    if not files:
        raise FileNotFoundError(2, f"{str(root)!r} has neither segmentation.npy nor segmentation/*.png", str(root))
    import imageio.v3 as iio
    from PIL import Image

    masks = []
    for p in files:
        try:
            with Image.open(p) as im:  # a palette PNG (DAVIS-style): its indices, as grey (0 background)
                masks.append(np.asarray(im) if im.mode == "P" else iio.imread(p))
        except (OSError, ValueError, SyntaxError) as e:  # truncated or not a PNG
            raise ValueError(f"{p}: not a readable PNG mask ({e})") from None
    if len({m.shape for m in masks}) != 1:
        raise ValueError(f"{folder}: masks differ in size: {sorted({m.shape for m in masks})}")
    stack = np.stack(masks)
    if stack.ndim == 4 and stack.shape[-1] in (1, 2):  # grey (+ alpha): the grey channel
        stack = stack[..., 0]
    if stack.ndim == 3:  # grey: value v > 0 is object v - 1
        return stack.astype(np.int32) - 1, None
    if stack.ndim != 4 or stack.shape[-1] not in (3, 4):
        raise ValueError(f"{folder}: masks of shape {masks[0].shape}: need grey, grey + alpha, RGB or RGBA images")
    rgb = stack[..., :3].astype(np.int64)
    code = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    colours, ids = np.unique(code, return_inverse=True)
    ids = ids.reshape(code.shape).astype(np.int32)
    if colours[0] == 0:  # black is background
        return ids - 1, colours[1:]
    return ids, colours
