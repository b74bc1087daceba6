"""Reading a user's frames and videos: image files in time order, one image as the camera showed it, and the
frames of a video (a file or a folder of images) at given times.

    files = image_files("frames/")                  # frame_2.png before frame_10.png; hidden files left out
    rgb = read_image(files[0])                      # (H, W, 3) uint8, EXIF rotation applied, 16-bit scaled
    video = open_video("clip.mp4")                  # its frame rate from the file (or fps=... for a folder)
    frames = video.frames_at([0.0, 0.1, 0.2])       # the frames on screen at those times, decoding stops there

Frame times: a video file's own (FFmpeg through PyAV: each frame's presentation time, so a phone's variable frame
rate is followed; a GIF's per-frame durations), or a constant `fps` passed, which a folder of images needs and
which overrides a file's timing. A file's display rotation (a phone held upright) is applied. Everything here
raises `ValueError` naming the file and the problem, or `FileNotFoundError` for a missing path.
"""

from __future__ import annotations

import errno
import os
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")
PILLOW_SUFFIXES = (*IMAGE_SUFFIXES, ".gif", ".apng", ".tif", ".tiff")  # images and animations: per-frame durations


def natural_key(name: str) -> list:
    """Sort key of a file name with its numbers compared as numbers: frame_2 before frame_10."""
    return [(0, int(s), s) if s.isdigit() else (1, 0, s.lower()) for s in re.split(r"(\d+)", name) if s]


def image_files(folder: str | Path, suffixes: Sequence[str] = IMAGE_SUFFIXES) -> list[Path]:
    """The image files of a folder in natural name order (0.png, 1.png, ..., 10.png), hidden ones (`.thumb.png`,
    macOS `._0.png`) and sub-folders left out; [] for a folder without any (or no folder)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [p for p in folder.iterdir() if p.suffix.lower() in suffixes and not p.name.startswith(".") and p.is_file()]
    return sorted(found, key=lambda p: natural_key(p.name))


def rgb8(image) -> np.ndarray:
    """A Pillow image as (H, W, 3) uint8 RGB: grey, palette, CMYK and alpha images converted (alpha dropped),
    16-bit and 32-bit grey scaled to 8 bits (not wrapped), float images taken as [0, 1]."""
    if image.mode in ("I;16", "I;16L", "I;16B", "I;16N", "I", "F"):
        a = np.asarray(image).astype(np.float64)
        if image.mode == "F":
            a = a * 255.0
        elif image.mode == "I" and a.max(initial=0) > 65535:  # a true 32-bit image: its own range
            a = a * (255.0 / a.max())
        elif image.mode != "I" or a.max(initial=0) > 255:  # 16-bit values
            a = a / 257.0
        grey = np.clip(np.round(a), 0, 255).astype(np.uint8)
        return np.repeat(grey[..., None], 3, axis=-1)
    return np.asarray(image.convert("RGB"))


def read_image(path: str | Path) -> np.ndarray:
    """One image file as (H, W, 3) uint8 RGB, as the camera showed it (EXIF orientation applied, see `rgb8`).

    Raises:
        ValueError: the file cannot be read as an image (truncated, not an image, unreadable), named.
    """
    from PIL import Image, ImageOps

    try:
        with Image.open(path) as image:
            return rgb8(ImageOps.exif_transpose(image))
    except Exception as e:  # Pillow raises OSError, ValueError, SyntaxError and more for a broken image
        raise ValueError(f"cannot read frame {str(path)!r}: {type(e).__name__}: {e}") from None


@dataclass(frozen=True)
class Video:
    """A video's frames, read lazily: a file (its frame rate and durations from the file) or a folder of images.

    Attributes:
        path: The file or folder.
        starts: (N,) the time each frame comes on screen, s, from the first frame; None for a file whose frame
            count is not known before decoding (its stored presentation times, or `fps`, give the times).
        fps: The nominal frame rate (frames per second).
        files: A folder's image files, in time order (None for a file).
        end: When the last frame leaves the screen, s (an animation's last duration); None: half a frame after
            it comes (a constant rate: the nearest frame must exist).
        pillow: A file Pillow reads (an image or an animation), else one FFmpeg decodes.
        timed: A file FFmpeg decodes whose frames are placed by their stored presentation times (a variable rate
            followed); False: frame k at k / `fps` (a rate given by the user).
    """

    path: Path
    starts: np.ndarray | None
    fps: float
    files: tuple[Path, ...] | None = None
    end: float | None = None
    pillow: bool = False
    timed: bool = False

    def describe(self) -> str:
        n = len(self.starts) if self.starts is not None else None
        count = "frames" if n is None else f"{n} frame{'s' * (n != 1)}"
        return f"{str(self.path)!r} ({count} at {self.fps:.3g} fps)"

    def indices_at(self, times: Sequence[float]) -> list[int]:
        """The frame on screen at each time (s from the first frame; the nearest frame at a constant rate).

        Raises:
            ValueError: a time past the video's end, naming how long it is.
        """
        times = np.asarray(times, float)
        if self.starts is None:
            return [int(k) for k in np.round(times * self.fps + 1e-9)]
        durations = np.diff(self.starts, append=self.starts[-1] + 1.0 / self.fps)
        tolerance = 0.5 * float(np.median(durations))  # half a frame: at a constant rate, the nearest frame
        picked = np.searchsorted(self.starts, times + tolerance + 1e-9, side="right") - 1
        end = self.end if self.end is not None else self.starts[-1] + tolerance  # constant rate: the nearest frame
        if (times > end + 1e-9).any():
            length = self.end if self.end is not None else self.starts[-1] + 1.0 / self.fps
            # at a constant rate the frame nearest each time must exist: its last frame's start is what counts
            last = "" if self.end is not None else f" (its last frame comes at {self.starts[-1]:.3g} s)"
            raise ValueError(
                f"{self.describe()} lasts {length:.3g} s{last}, but frames up to {times.max():.3g} s are "
                "needed: give a longer video, or the right frame rate with --fps"
            )
        return [int(k) for k in np.maximum(picked, 0)]

    def frames_at(self, times: Sequence[float]) -> list[np.ndarray]:
        """(H, W, 3) uint8 frames on screen at `times`; a file is decoded only up to the last one needed."""
        if self.timed:
            return self._timed_frames_at(times)
        want = self.indices_at(times)
        if self.files is not None:
            cache = {k: read_image(self.files[k]) for k in sorted(set(want))}
        else:
            cache, n = _decode(self.path, set(want), self.pillow)
            if max(want) not in cache:
                raise ValueError(
                    f"{self.describe()} has {n} frames ({n / self.fps:.3g} s, the last coming at "
                    f"{(n - 1) / self.fps:.3g} s), but frames up to {max(times):.3g} s "
                    "are needed: give a longer video, or the right frame rate with --fps"
                )
        return same_size([cache[k] for k in want], [self.name(k) for k in want])

    def _timed_frames_at(self, times: Sequence[float]) -> list[np.ndarray]:
        """`frames_at` by the frames' presentation times: the frame on screen at t is the last one to come at or
        before t + half a nominal frame (at a constant rate, the nearest). Decoding stops at the first frame that
        comes after the last time needed; only the frames picked are kept. Stored times that go backwards are no
        clock (a container of `UNTIMED_FORMATS` under another name): the frames are then read by count, frame k at
        k / `fps`."""
        times = np.asarray(times, float)
        tolerance = 0.5 / self.fps + 1e-9
        order = list(np.argsort(times, kind="stable"))
        out: list[np.ndarray | None] = [None] * len(times)
        picked: list[int] = [0] * len(times)
        first = last = None
        n, backwards = 0, False
        for k, (start, frame) in enumerate(_readable_frames(self.path, False)):
            if start is None:  # a stream without presentation times: at the nominal rate
                start = k / self.fps
            first = start if first is None else first
            start -= first
            if last is not None and start < last[0] - 1e-9:
                backwards = True
                break
            while order and times[order[0]] + tolerance < start:  # on screen before this frame: the last one
                i = order.pop(0)  # (a time before the first frame: the first frame)
                out[i], picked[i] = (last[1], k - 1) if last is not None else (frame, k)
            if not order:
                break
            last, n = (start, frame), k + 1
        if backwards:
            return replace(self, timed=False).frames_at(times)
        if order:
            end = last[0] + tolerance if last is not None else 0.0
            if last is None or times[order[-1]] > end:
                came = f"the last coming at {last[0]:.3g} s" if last is not None else "none decoded"
                raise ValueError(
                    f"{self.describe()} has {n} frames ({came}), but frames up to {times.max():.3g} s "
                    "are needed: give a longer video, or the right frame rate with --fps"
                )
            for i in order:
                out[i], picked[i] = last[1], n - 1
        return same_size(out, [self.name(k) for k in picked])

    def name(self, k: int) -> str:
        """Frame `k` as an error message names it: its file, or its place in the video file."""
        return repr(str(self.files[k])) if self.files is not None else f"frame {k} of {str(self.path)!r}"


def open_video(path: str | Path, fps: float | None = None) -> Video:
    """A video file (MP4, WebM, AVI, ...: what FFmpeg decodes; GIF and animated WebP/PNG with their own frame
    durations), a single image (a one-frame video), or a folder of images (in `image_files` order, consecutive
    frames at `fps`).

    Args:
        fps: The frame rate; required for a folder, and for a file overrides the rate stored in it.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: a folder without images, a file that is no readable video, or a bad `fps`.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(path))
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps = {fps}: must be a finite number > 0")
    if path.is_dir():
        files = image_files(path)
        if not files:
            raise ValueError(f"{str(path)!r} holds no frames (looked for {', '.join(IMAGE_SUFFIXES)})")
        if fps is None:
            raise ValueError(f"{str(path)!r} is a folder of frames: its frame rate (fps) must be given")
        return Video(path, np.arange(len(files)) / fps, float(fps), tuple(files))
    if path.stat().st_size == 0:
        raise ValueError(f"{str(path)!r} is an empty file, not a video")
    durations = _pillow_durations(path) if path.suffix.lower() in PILLOW_SUFFIXES else None
    if durations is not None:  # an image (one frame) or an animation: its own timing
        if len(durations) == 1 or not (durations > 0).all():  # no timing stored: 10 fps unless fps is given
            rate = fps or 10.0
            return Video(path, np.arange(len(durations)) / rate, rate, pillow=True)
        if fps is not None:  # its typical frame lasts 1 / fps; a long one (still frames merged on saving) longer
            durations = durations / (float(np.median(durations)) * fps)
        starts = np.concatenate([[0.0], np.cumsum(durations[:-1])])
        rate = 1.0 / float(np.median(durations))
        return Video(path, starts, rate, end=float(starts[-1] + durations[-1]), pillow=True)
    rate, timed = _file_clock(path)
    if fps is not None:  # the user's constant rate: frame k at k / fps
        return Video(path, None, float(fps))
    if rate is None:
        raise ValueError(f"video {str(path)!r} states no frame rate: give it with --fps")
    return Video(path, None, rate, timed=timed)


def read_frames(path: str | Path) -> list[np.ndarray]:
    """Every frame of a video file, or of a folder of images, as (H, W, 3) uint8 (`Video.frames_at` reads only
    those it needs).

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: nothing to read, a file that cannot be decoded (named), frames of different sizes.
    """
    video = open_video(path, fps=1.0 if Path(path).is_dir() else None)
    if video.files is not None:
        return video.frames_at(video.starts)
    got, n = _decode(video.path, None, video.pillow)
    if not n:
        raise ValueError(f"video {str(video.path)!r} has no frames")
    return same_size([got[k] for k in range(n)], [video.name(k) for k in range(n)])


def _pillow_durations(path: Path) -> np.ndarray | None:
    """Per-frame durations (s) of an image or animation Pillow reads; None when Pillow cannot open it."""
    from PIL import Image, ImageSequence

    try:
        with Image.open(path) as image:
            durations = []
            for frame in ImageSequence.Iterator(image):
                frame.load()  # WebP sets the duration on loading, GIF and APNG on seeking
                durations.append(frame.info.get("duration", 0) / 1000.0)
            return np.array(durations)
    except Exception:  # not an image Pillow knows: a video, or a broken file that FFmpeg will name
        return None


def _video_stream(container):
    """The video stream of an open PyAV container to read, as FFmpeg picks it (`av_find_best_stream`: a stream of
    several frames before a one-frame thumbnail), never an attached picture (an audio file's cover); None if none."""
    import av

    moving = [s for s in container.streams.video if not s.disposition & av.stream.Disposition.attached_pic]
    best = container.streams.best("video")
    return best if best in moving else (moving[0] if moving else None)


# Containers that store no presentation times: FFmpeg's are made up (an AVI's come in decoding order, wrong with
# B-frames), so their frames are placed by count at the stated rate.
UNTIMED_FORMATS = {"avi", "h264", "hevc", "mjpeg", "rawvideo"}


def _file_clock(path: Path) -> tuple[float | None, bool]:
    """The frame rate a video file states (FFmpeg through PyAV; None if it states none), and whether its frames
    carry presentation times to place them by (not in `UNTIMED_FORMATS`).

    Raises:
        ValueError: the file is no video FFmpeg reads, or holds no video stream (audio only), named.
    """
    import av

    try:
        with av.open(str(path)) as container:
            stream = _video_stream(container)
            fps = float(stream.guessed_rate) if stream is not None and stream.guessed_rate else None
            timed = not set(container.format.name.split(",")) & UNTIMED_FORMATS
    except Exception as e:  # PyAV raises its own error types for a file that is no video
        raise _unreadable(path, e, 0) from None
    if stream is None:
        raise ValueError(f"{str(path)!r} holds no video stream (audio only?)")
    return (fps if fps and np.isfinite(fps) and fps > 0 else None), timed


def _frames(path: Path, pillow: bool) -> Iterator[tuple[float | None, np.ndarray]]:
    """A video file's frames as (H, W, 3) uint8, one at a time, in display order, each with the time it comes on
    screen (s, on the file's clock; None where none is stored: Pillow's, or a stream without timestamps). Pillow
    reads images and animations, PyAV the rest, with the stream's display rotation applied (a phone video filmed
    upright is stored sideways with a rotation to show it)."""
    if pillow:
        from PIL import Image, ImageSequence

        with Image.open(path) as image:
            for frame in ImageSequence.Iterator(image):
                yield None, rgb8(frame)
        return
    import av

    with av.open(str(path)) as container:
        stream = _video_stream(container)
        if stream is None:
            raise ValueError("no video stream")
        for frame in container.decode(stream):
            yield frame.time, np.ascontiguousarray(_upright(frame.to_ndarray(format="rgb24"), frame))


def _upright(image: np.ndarray, frame) -> np.ndarray:
    """A decoded frame's (H, W, 3) pixels as its display matrix shows them, turned and flipped as the `ffmpeg` tool
    turns them (autorotate): quarter turns clockwise by the matrix's angle (`-av_display_rotation_get`; a phone
    filmed upright: 90), the mirrored matrices (transposed, flipped) flipped too; a singular matrix turns nothing."""
    from av.sidedata.sidedata import Type

    data = frame.side_data.get(Type.DISPLAYMATRIX)
    if data is None:
        return image
    m = np.frombuffer(bytes(data), np.int32)[:9] / 65536.0  # a, b, u, c, d, v, x, y, w: a..d in 16.16
    scale = np.hypot(m[0], m[3]), np.hypot(m[1], m[4])
    if not (scale[0] > 0 and scale[1] > 0):
        return image
    turns = int(round(np.degrees(np.arctan2(m[1] / scale[1], m[0] / scale[0])) / 90)) % 4  # clockwise
    if turns == 1:
        return image.transpose(1, 0, 2) if m[3] > 0 else np.rot90(image, -1)
    if turns == 3:
        return np.rot90(image, 2).transpose(1, 0, 2) if m[3] < 0 else np.rot90(image, 1)
    return image[:: -1 if m[4] < 0 else 1, :: -1 if m[0] < 0 else 1]


def _readable_frames(path: Path, pillow: bool) -> Iterator[tuple[float | None, np.ndarray]]:
    """`_frames`, a file that cannot be decoded named in a `ValueError` (PyAV and Pillow raise many types), with
    how many frames it gave before (a truncated recording)."""
    n = 0
    try:
        for item in _frames(path, pillow):
            yield item
            n += 1
    except Exception as e:
        raise _unreadable(path, e, n) from None


def _unreadable(path: Path, error: Exception, frames: int) -> ValueError:
    """The error naming a video file that failed to decode after `frames` frames (0: to open)."""
    at = f" after {frames} frame{'s' * (frames != 1)}" if frames else ""
    if not frames and Path(path).suffix.lower() in {".mp4", ".mov", ".m4v"}:
        at = " (one cut off while recording has no index)"
    return ValueError(f"cannot read video {str(path)!r}{at}: {type(error).__name__}: {error}")


def _decode(path: Path, want: set[int] | None, pillow: bool) -> tuple[dict[int, np.ndarray], int]:
    """The frames of `want` (indices; None: all) of a video file (`pillow`: one Pillow reads), decoding no further
    than the last of them, and how many frames were decoded."""
    last, got, n = (max(want) if want is not None else None), {}, 0
    for k, (_, frame) in enumerate(_readable_frames(path, pillow)):
        n = k + 1
        if want is None or k in want:
            got[k] = frame
        if last is not None and k >= last:
            break
    return got, n


def same_size(frames: Sequence[np.ndarray], names: Sequence[str]) -> Sequence[np.ndarray]:
    """`frames` (H, W, 3), checked to share one size; `names` say where each came from (a file's repr).

    Raises:
        ValueError: the first frame of another size than the first, named with both sizes.
    """
    h, w = frames[0].shape[:2]
    for name, frame in zip(names, frames, strict=True):
        if frame.shape[:2] != (h, w):
            raise ValueError(f"{name}: {frame.shape[1]}×{frame.shape[0]} pixels, unlike the {w}×{h} of {names[0]}")
    return frames
