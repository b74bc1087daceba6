"""Reading a user's frames and videos (`aynamics.video_io`), and the clip `aynamics predict` takes from them: the
frames training showed the model, at the times it showed them."""

from __future__ import annotations

import dataclasses

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from aynamics import adapters, flow, lm, video_io
from aynamics.predict import clip_of


def _stamped(k: int, size=(24, 32)) -> np.ndarray:
    """A frame whose pixels all hold 8·(k mod 32): which frame a reader returned survives JPEG and H.264."""
    return np.full((*size, 3), 8 * (k % 32), np.uint8)


def _stamps(frames) -> list[int]:
    return [int(round(float(np.median(f)) / 8)) for f in frames]  # the median: a corner mark left out


def _folder(path, n: int, name=lambda k: f"{k}.png"):
    path.mkdir()
    for k in range(n):
        iio.imwrite(path / name(k), _stamped(k))
    return path


def test_image_files_in_natural_order_without_hidden_files(tmp_path):
    """0.png … 11.png without zero-padding come in number order (name order put 10 and 11 after 1); hidden files
    (a macOS `._0.png`, a `.thumb.png`), sub-folders and other files are not frames."""
    folder = _folder(tmp_path / "f", 12)
    (folder / "._0.png").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
    iio.imwrite(folder / ".thumb.png", _stamped(31))
    (folder / "notes.txt").write_text("x")
    (folder / "sub.png").mkdir()
    assert [p.name for p in video_io.image_files(folder)] == [f"{k}.png" for k in range(12)]
    assert [p.name for p in video_io.image_files(tmp_path / "none")] == []
    names = ["frame_10.png", "frame_9.png", "Frame_11.PNG", "frame_1.jpg"]
    assert sorted(names, key=video_io.natural_key) == ["frame_1.jpg", "frame_9.png", "frame_10.png", "Frame_11.PNG"]


def test_read_image_gives_rgb8_as_the_camera_showed_it(tmp_path):
    """16-bit grey is scaled (40000 -> 156; it was wrapped to its low byte), CMYK is converted (its channels were
    taken as RGBA), the EXIF rotation of a phone JPEG is applied, grey + alpha and palette images come as RGB."""
    grey16 = np.full((4, 6), 40000, np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    out = video_io.read_image(tmp_path / "g16.png")
    assert out.dtype == np.uint8 and out.shape == (4, 6, 3) and (out == 156).all()  # 40000 / 257 = 155.6
    Image.new("RGB", (6, 4), (255, 0, 0)).convert("CMYK").save(tmp_path / "cmyk.jpg", quality=100)
    red = video_io.read_image(tmp_path / "cmyk.jpg").astype(int)
    assert (np.abs(red - [255, 0, 0]) <= 3).all()
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: rotate 90° clockwise to show
    Image.new("RGB", (6, 4), (0, 0, 0)).save(tmp_path / "phone.jpg", exif=exif)
    assert video_io.read_image(tmp_path / "phone.jpg").shape == (6, 4, 3)  # shown 4 wide, 6 high
    Image.new("LA", (6, 4), (200, 10)).save(tmp_path / "la.png")
    assert (video_io.read_image(tmp_path / "la.png") == 200).all()
    Image.new("RGB", (6, 4), (10, 20, 30)).convert("P", palette=Image.Palette.ADAPTIVE).save(tmp_path / "p.png")
    assert video_io.read_image(tmp_path / "p.png")[0, 0].tolist() == [10, 20, 30]
    (tmp_path / "bad.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(ValueError, match=r"cannot read frame '.*bad\.png'"):
        video_io.read_image(tmp_path / "bad.png")


def test_the_clip_is_the_frames_training_showed(tmp_path):
    """A default adapter was trained on records holding every third frame of a 30 fps video (0, 0.1, ... 0.9 s).
    From 30 frames predict takes frames 0, 3, ..., 27 (it spread its frames over all 30 before: 0 and 29 for
    two); from a 60 fps folder the frames at the same times; a folder of exactly 10 is the clip itself; a GIF
    by its frame durations; an MP4 by its frame rate. Too short a video is named with its length."""
    prompt = lm.PromptSpec()
    assert prompt.frame_times == tuple(flow.sample_frames(30) / 30)
    assert _stamps(clip_of(_folder(tmp_path / "v30", 30), prompt)) == list(range(0, 30, 3))
    v60 = _folder(tmp_path / "v60", 60, name=lambda k: f"f{k}.jpg")
    assert _stamps(clip_of(v60, prompt, fps=60)) == [k % 32 for k in range(0, 60, 6)]
    assert _stamps(clip_of(_folder(tmp_path / "v10", 10), prompt)) == list(range(10))
    with pytest.raises(
        ValueError, match=r"v20' \(20 frames at 30 fps\) lasts 0.667 s \(its last frame comes at 0.633 s\)"
    ):
        clip_of(_folder(tmp_path / "v20", 20), prompt)
    assert _stamps(clip_of(tmp_path / "v20", prompt, fps=20)) == [0, 2, 4, 6, 8, 10, 12, 14, 16, 18]
    with pytest.raises(ValueError, match="fps = 0: must be"):  # --fps 0 was taken as no --fps
        clip_of(tmp_path / "v20", prompt, fps=0)
    with pytest.raises(ValueError, match=r"lasts 0.9 s \(its last frame comes at 0.867 s\), but frames up to 0.9 s"):
        clip_of(_folder(tmp_path / "v27", 27), prompt)  # 0.9 s long, but the frame on screen at 0.9 s is the 28th
    gif = [Image.fromarray(_stamped(k)) for k in range(12)]  # 100 ms each: 10 fps, 1.2 s
    gif[0].save(tmp_path / "a.gif", save_all=True, append_images=gif[1:], duration=100, loop=0)
    assert _stamps(clip_of(tmp_path / "a.gif", prompt)) == list(range(10))
    still = [Image.fromarray(_stamped(min(k, 7))) for k in range(12)]  # at rest from 0.7 s: Pillow merges 7..11
    still[0].save(tmp_path / "still.gif", save_all=True, append_images=still[1:], duration=100, loop=0)
    assert len(video_io.open_video(tmp_path / "still.gif").starts) == 8  # the last frame lasts 0.5 s
    assert _stamps(clip_of(tmp_path / "still.gif", prompt)) == [0, 1, 2, 3, 4, 5, 6, 7, 7, 7]  # was "ends at 0.75 s"
    assert _stamps(clip_of(tmp_path / "still.gif", prompt, fps=4)) == [0, 0, 1, 1, 2, 2, 2, 3, 3, 4]  # 0.25 s each
    with pytest.raises(ValueError, match=r"still.gif' \(8 frames at 20 fps\) lasts 0.6 s"):  # the still: 0.25 s
        clip_of(tmp_path / "still.gif", prompt, fps=20)
    webp = [Image.fromarray(_stamped(k)) for k in range(20)]  # 50 ms each: WebP sets durations on loading
    webp[0].save(tmp_path / "a.webp", save_all=True, append_images=webp[1:], duration=50, lossless=True)
    assert _stamps(clip_of(tmp_path / "a.webp", prompt)) == list(range(0, 20, 2))  # read as 10 fps before: 0..9
    iio.imwrite(
        tmp_path / "a.mp4", np.stack([_stamped(k, (48, 64)) for k in range(31)]), plugin="pyav", codec="libx264", fps=30
    )
    assert _stamps(clip_of(tmp_path / "a.mp4", prompt)) == list(range(0, 30, 3))


def _count_decoded(monkeypatch) -> list:
    """A list that grows by one for every frame `video_io` decodes from now on."""
    decoded, frames = [], video_io._frames

    def counting(path, pillow):
        for f in frames(path, pillow):
            decoded.append(1)
            yield f

    monkeypatch.setattr(video_io, "_frames", counting)
    return decoded


def test_a_video_file_is_decoded_only_as_far_as_the_clip_needs(tmp_path, monkeypatch):
    """The clip of a 300-frame video ends at frame 27: decoding stops at the next frame, the first to come after
    the clip's last time (the whole file was decoded into memory before: 1.7 GB for 10 s of 720p)."""
    iio.imwrite(
        tmp_path / "long.mp4",
        np.stack([_stamped(k % 30, (48, 64)) for k in range(300)]),
        plugin="pyav",
        codec="libx264",
        fps=30,
    )
    decoded = _count_decoded(monkeypatch)
    assert _stamps(clip_of(tmp_path / "long.mp4", lm.PromptSpec())) == list(range(0, 30, 3))
    assert len(decoded) == 29
    assert len(video_io.read_frames(tmp_path / "long.mp4")) == 300


def _write_timed(path, stamps_ms, size=(48, 64), matrix=None):
    """An MP4 of `_stamped(k)` frames shown at `stamps_ms` (a variable rate; the stream states 30 fps), with the
    track's display matrix set to `matrix` (9 ints, 16.16 fixed point: how a phone stores its rotation)."""
    import struct
    from fractions import Fraction

    import av

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = size[1], size[0], "yuv420p"
        stream.time_base = Fraction(1, 1000)
        for k, ms in enumerate(stamps_ms):
            image = _stamped(k, size)
            image[:8, :8] = 255  # a corner mark that shows the rotation
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts, frame.time_base = ms, Fraction(1, 1000)
            out.mux(stream.encode(frame))
        out.mux(stream.encode())
    if matrix is not None:  # the MP4 track header (version 0): 32 bytes after its type, then the 3x3 matrix
        data = bytearray(path.read_bytes())
        at = data.find(b"tkhd") + 4 + 4 + 20 + 8 + 8
        data[at : at + 36] = struct.pack(">9i", *matrix)
        path.write_bytes(data)
    return path


def test_a_variable_rate_video_is_read_by_its_frames_times(tmp_path):
    """A phone records at a variable rate: frames at 0, 33, 67, 200, 233, 500, 533 ms while the stream states
    30 fps. The frame on screen at 0.1 s is the one from 67 ms, at 0.3 s the one from 233 ms, at 0.5 s the one
    from 500 ms (by frame count at 30 fps these were frames 3, 9 and 15: the one from 200 ms, then errors:
    'has 7 frames'); a time before the next frame by less than half a nominal frame takes the next one, as at a
    constant rate. A rate the user gives places frame k at k / fps. Past the last frame, the error names it."""
    path = _write_timed(tmp_path / "vfr.mp4", [0, 33, 67, 200, 233, 500, 533])
    video = video_io.open_video(path)
    assert video.timed and video.fps == 30
    assert _stamps(video.frames_at([0.0, 0.1, 0.3, 0.5, 0.19])) == [0, 2, 4, 5, 3]
    assert _stamps(video.frames_at([0.5, 0.0])) == [5, 0]  # any order
    assert _stamps(video_io.open_video(path, fps=10).frames_at([0.0, 0.1, 0.3])) == [0, 1, 3]
    with pytest.raises(ValueError, match=r"has 7 frames \(the last coming at 0.533 s\), but frames up to 0.6 s"):
        video.frames_at([0.0, 0.6])
    assert _stamps(video.frames_at([0.545])) == [6]  # within half a frame of the last


def test_a_phone_video_filmed_upright_is_read_upright(tmp_path):
    """A phone stores an upright video's frames sideways with a display rotation; they are read as shown: a 64x48
    stored frame with a mark in its top-left corner, rotated 90° clockwise for display, reads 48x64 with the mark
    top-right (it was read sideways). Without a rotation it reads as stored."""
    plain = video_io.read_frames(_write_timed(tmp_path / "plain.mp4", [0, 33]))[0]
    assert plain.shape == (48, 64, 3) and plain[:8, :8].min() > 200
    upright = _write_timed(tmp_path / "upright.mp4", [0, 33], matrix=(0, 65536, 0, -65536, 0, 0, 0, 0, 1 << 30))
    shown = video_io.read_frames(upright)[0]
    assert shown.shape == (64, 48, 3) and shown[:8, -8:].min() > 200 and shown[:8, :8].max() < 100
    assert video_io.open_video(upright).frames_at([0.0])[0].shape == (64, 48, 3)


def test_display_matrices_are_applied_as_ffmpeg_applies_them(tmp_path):
    """The mark of the top-left stored corner lands where the `ffmpeg` tool's autorotate puts it: a 180° matrix
    bottom-right, a 90° counter-clockwise one (270° clockwise) bottom-left; a mirrored matrix (-1, 0, 0, 1) only
    flips left-right (mark top-right; it was turned 180°: bottom-right), a transposing one (0, 1, 1, 0) transposes
    (mark top-left; it was turned clockwise: top-right); a singular (all-zero) matrix leaves the frame as stored (it
    was turned clockwise: PyAV's rotation of it is INT_MIN)."""
    u, w = 65536, 1 << 30
    cases = {
        "r180": ((-u, 0, 0, 0, -u, 0, 0, 0, w), (48, 64), np.s_[-8:, -8:]),
        "r270": ((0, -u, 0, u, 0, 0, 0, 0, w), (64, 48), np.s_[-8:, :8]),
        "hflip": ((-u, 0, 0, 0, u, 0, 0, 0, w), (48, 64), np.s_[:8, -8:]),
        "transpose": ((0, u, 0, u, 0, 0, 0, 0, w), (64, 48), np.s_[:8, :8]),
        "singular": ((0, 0, 0, 0, 0, 0, 0, 0, w), (48, 64), np.s_[:8, :8]),
    }
    for name, (matrix, shape, mark) in cases.items():
        frame = video_io.read_frames(_write_timed(tmp_path / f"{name}.mp4", [0, 33], matrix=matrix))[0]
        assert frame.shape[:2] == shape and frame[mark].min() > 200 and np.median(frame) < 100, name


def test_an_avi_with_b_frames_is_read_by_count(tmp_path):
    """An AVI stores no presentation times: FFmpeg numbers its H.264 frames in decoding order, so with B-frames
    the times of the frames shown go 1, 4, 3, 5, 2, ... (/30 s). Its frames are read by count at the stated rate,
    frames 0, 3, ..., 27 (by those times: 0, 2, 4, 8, 12, 14, 17, 19, 23, 27), a short clip's too (0.05 s: frame 2,
    where the first times gave frame 0, helper-52). Times that go backwards in a container not known to lack them
    are caught while reading: the frames are read by count."""
    import av

    with av.open(str(tmp_path / "b.avi"), "w") as out:
        stream = out.add_stream("libx264", rate=30)  # B-frames by default
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        for k in range(31):
            out.mux(stream.encode(av.VideoFrame.from_ndarray(_stamped(k, (48, 64)), format="rgb24")))
        out.mux(stream.encode())
    video = video_io.open_video(tmp_path / "b.avi")
    assert not video.timed
    assert _stamps(clip_of(tmp_path / "b.avi", lm.PromptSpec())) == list(range(0, 30, 3))
    assert _stamps(video.frames_at([0.0, 0.05])) == [0, 2]
    as_if_timed = dataclasses.replace(video, timed=True)
    assert _stamps(as_if_timed.frames_at(lm.PromptSpec().frame_times)) == list(range(0, 30, 3))


def test_the_moving_video_stream_is_read_and_audio_is_no_video(tmp_path):
    """A file whose first video stream is a one-frame thumbnail gives the frames of its moving stream (it gave the
    thumbnail: 'has 1 frames'); an audio file, with a cover picture or without, is named as holding no video (it
    was 'has 1 frames at 9e+04 fps ... give a longer video', or 'unknown error ... initializing plugin')."""
    import av

    with av.open(str(tmp_path / "two.mkv"), "w") as out:
        thumb = out.add_stream("mjpeg", rate=1)
        thumb.width, thumb.height, thumb.pix_fmt = 32, 24, "yuvj420p"
        stream = out.add_stream("libx264", rate=30)  # streams are added before any is written
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        out.mux(thumb.encode(av.VideoFrame.from_ndarray(_stamped(31), format="rgb24")))
        out.mux(thumb.encode())
        for k in range(31):
            out.mux(stream.encode(av.VideoFrame.from_ndarray(_stamped(k, (48, 64)), format="rgb24")))
        out.mux(stream.encode())
    assert _stamps(clip_of(tmp_path / "two.mkv", lm.PromptSpec())) == list(range(0, 30, 3))
    with av.open(str(tmp_path / "song.mp4"), "w", format="mp4") as out:
        audio = out.add_stream("aac", rate=8000)
        cover = out.add_stream("png")
        cover.width, cover.height, cover.pix_fmt = 32, 24, "rgb24"
        cover.disposition = av.stream.Disposition.attached_pic
        for packet in cover.encode(av.VideoFrame.from_ndarray(_stamped(5), format="rgb24")):
            packet.pts = packet.dts = 0
            out.mux(packet)
        for k in range(8):
            samples = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
            samples.sample_rate, samples.pts = 8000, 1024 * k
            out.mux(audio.encode(samples))
        out.mux(audio.encode())
    with av.open(str(tmp_path / "song.wav"), "w") as out:
        audio = out.add_stream("pcm_s16le", rate=8000)
        samples = av.AudioFrame.from_ndarray(np.zeros((1, 800), np.int16), format="s16", layout="mono")
        samples.sample_rate, samples.pts = 8000, 0
        out.mux(audio.encode(samples))
        out.mux(audio.encode())
    for name in ("song.mp4", "song.wav"):
        with pytest.raises(ValueError, match=rf"{name}' holds no video stream"):
            clip_of(tmp_path / name, lm.PromptSpec())


def test_flow_clips_are_recoloured_on_their_own_scale(tmp_path):
    """A flow-trained adapter: the 29 flow images of `aynamics render` share one scale, a generated record's
    sampled ones theirs; the clip gets the generated colours (within 2 levels of 255), and images already on their own
    scale come back unchanged."""
    flows = np.zeros((29, 24, 32, 2), np.float32)
    flows[:, 8:16, 8:20, 0] = np.arange(1.0, 30.0)[:, None, None]
    flows[28, 8:16, 8:20, 0] = 80.0  # the fastest, not in the clip
    folder = tmp_path / "flow"
    folder.mkdir()
    for k, im in enumerate(flow.flow_to_color(flows)):
        iio.imwrite(folder / f"flow_{k:04d}.png", im)
    got = np.stack(clip_of(folder, lm.PromptSpec(modality="flow"))).astype(int)
    want = flow.flow_to_color(flows[0:30:3]).astype(int)
    assert np.abs(got - want).max() <= 2
    same = flow.flow_to_color(flows[:3])
    assert flow.on_own_scale(same) is same


def test_prompt_clock_checks_and_old_adapters(tmp_path):
    """The clock is checked; an adapter written before it existed reads as the generator's default; a data set's
    clock comes from its manifest and records."""
    import datasets

    from aynamics.data import with_clock

    with pytest.raises(ValueError, match="fps = 0: must be a finite number > 0"):
        lm.PromptSpec(fps=0)
    with pytest.raises(ValueError, match=r"clip_frames = \[0, 3, 3\]: must be increasing"):
        lm.PromptSpec(clip_frames=(0, 3, 3))
    meta = adapters.adapter_meta(lm.ModelSpec(), lm.PromptSpec())
    for key in ("fps", "clip_frames"):
        del meta["prompt"][key]
    old = adapters.specs_of_meta(meta)[1]
    assert old.fps == 30 and old.clip_frames == tuple(range(0, 30, 3))
    (tmp_path / "generate.json").write_text('{"config": {"fps": 60, "physics": 2}}')
    split = datasets.Dataset.from_dict({"frame_indices": [[0, 2, 4, 6]]})
    clocked = with_clock(lm.PromptSpec(), tmp_path, split)
    assert clocked.fps == 60 and clocked.clip_frames == (0, 2, 4, 6) and clocked.frame_times[-1] == 0.1


def test_frame_times_count_from_the_first_stored_frame():
    """Frames 3, 6, 9 of a 30 fps video: shown at 0, 0.1 and 0.2 s (not 0.1, 0.2, 0.3), so 3 frames over 0.2 s are
    10 frames per second. Pixel bounds below one 28×28 block are refused, 784 is allowed."""
    prompt = lm.PromptSpec(num_frames=3, fps=30, clip_frames=(3, 6, 9))
    assert prompt.frame_times == pytest.approx((0.0, 0.1, 0.2))
    assert prompt.shown_fps == pytest.approx(10.0)
    assert lm.PromptSpec(min_pixels=28 * 28).min_pixels == 784
    with pytest.raises(ValueError, match="min_pixels = 783: must be >= 784"):
        lm.PromptSpec(min_pixels=783)


def test_mirrored_flipped_and_rounded_display_matrices(tmp_path):
    """The matrices `test_display_matrices_are_applied_as_ffmpeg_applies_them` leaves out, by FFmpeg's autorotate:
    an anti-transposing one (0, -1, -1, 0; 270° with c < 0: `transpose=clock_flip`) puts the top-left mark
    bottom-right in a 64-high frame; a vertical flip (1, 0, 0, -1; 0° with d < 0: `vflip`) bottom-left; one a unit
    off 90° ((1, 1, -1, 1) in 16.16: 89.999°, rounded to 90: `transpose=clock`) top-right, as the exact 90°; one
    with a zero column (scale 0, no angle: FFmpeg's theta is NaN, nothing applied) leaves the frame as stored."""
    u, w = 65536, 1 << 30
    cases = {
        "antitranspose": ((0, -u, 0, -u, 0, 0, 0, 0, w), (64, 48), np.s_[-8:, -8:]),
        "vflip": ((u, 0, 0, 0, -u, 0, 0, 0, w), (48, 64), np.s_[-8:, :8]),
        "r90_off_by_a_unit": ((1, u, 0, -u, 1, 0, 0, 0, w), (64, 48), np.s_[:8, -8:]),
        "zero_column": ((u, 0, 0, 0, 0, 0, 0, 0, w), (48, 64), np.s_[:8, :8]),
    }
    for name, (matrix, shape, mark) in cases.items():
        frame = video_io.read_frames(_write_timed(tmp_path / f"{name}.mp4", [0, 33], matrix=matrix))[0]
        assert frame.shape[:2] == shape and frame[mark].min() > 200 and np.median(frame) < 100, name


def test_a_video_whose_clock_starts_late_counts_from_its_first_frame(tmp_path):
    """The frames of `test_a_variable_rate_video_is_read_by_its_frames_times` stored 0.5 s later (0.5, 0.533, 0.567,
    0.7, 0.733, 1.0, 1.033 s: a stream cut from a longer one, an MPEG-TS's start) are read at the same times from
    the first frame: 0.1 s is the frame from 0.567 s, 0.3 s the one from 0.733 s, 0.5 s the one from 1.0 s (on the
    file's clock every time before 0.5 s is frame 0)."""
    path = _write_timed(tmp_path / "late.mp4", [500, 533, 567, 700, 733, 1000, 1033])
    assert _stamps(video_io.open_video(path).frames_at([0.0, 0.1, 0.3, 0.5])) == [0, 2, 4, 5]


def test_timed_frames_without_times_and_frames_named_by_place(tmp_path, monkeypatch):
    """Frames a timed container gives without presentation times come at k / fps: at 10 fps the frames on screen at
    0, 0.2 and 0.4 s are 0, 2 and 4 (at time 0 each, the 0.4 s was past the video). A frame of another size is
    named by its place: of frames at 0, 0.1 and 0.2 s, 0.0 s is frame 0 (picked when frame 1 came) and 0.2 s frame
    2 (the last decoded), not frames 1 and 3."""
    video = video_io.Video(tmp_path / "x.mp4", None, 10.0, timed=True)
    monkeypatch.setattr(video_io, "_frames", lambda path, pillow: ((None, _stamped(k)) for k in range(6)))
    assert _stamps(video.frames_at([0.0, 0.2, 0.4])) == [0, 2, 4]
    sizes = [(24, 32), (24, 32), (12, 16)]
    monkeypatch.setattr(
        video_io, "_frames", lambda path, pillow: ((k / 10, _stamped(k, s)) for k, s in enumerate(sizes))
    )
    with pytest.raises(ValueError, match=r"frame 2 of '.*x\.mp4': 16×12 pixels, unlike the 32×24 of frame 0 of"):
        video.frames_at([0.0, 0.2])


def test_a_video_at_a_given_rate_is_decoded_only_as_far_as_needed_and_too_short_named(tmp_path, monkeypatch):
    """Read by count (`--fps` given): the clip of 40 frames at 30 fps ends at frame 27, and decoding stops there (28
    frames decoded, not 29). Seven frames at 10 fps last 0.7 s: the frame at 0.7 s (the 8th) is named missing, with
    the count and the last frame's time (it was a KeyError)."""
    iio.imwrite(
        tmp_path / "a.mp4", np.stack([_stamped(k, (48, 64)) for k in range(40)]), plugin="pyav", codec="libx264", fps=30
    )
    decoded = _count_decoded(monkeypatch)
    assert _stamps(clip_of(tmp_path / "a.mp4", lm.PromptSpec(), fps=30)) == list(range(0, 30, 3))
    assert len(decoded) == 28
    monkeypatch.undo()  # the plain reader again
    path = _write_timed(tmp_path / "vfr.mp4", [0, 33, 67, 200, 233, 500, 533])
    with pytest.raises(ValueError, match=r"has 7 frames \(0.7 s, the last coming at 0.6 s\), but frames up to 0.7 s"):
        video_io.open_video(path, fps=10).frames_at([0.0, 0.7])


def test_rates_and_files_open_video_refuses(tmp_path, monkeypatch):
    """An infinite `fps` is refused like 0 (a folder's frames all came at 0 s); an empty file is named as one (not
    'cannot read video'); a file stating no frame rate asks for --fps, and reads by count at the one given."""
    folder = _folder(tmp_path / "f", 3)
    with pytest.raises(ValueError, match="fps = inf: must be a finite number > 0"):
        video_io.open_video(folder, fps=float("inf"))
    (tmp_path / "empty.mp4").write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.mp4' is an empty file, not a video"):
        video_io.open_video(tmp_path / "empty.mp4")
    path = _write_timed(tmp_path / "v.mp4", [0, 33, 67, 200])
    monkeypatch.setattr(video_io, "_file_clock", lambda path: (None, True))
    with pytest.raises(ValueError, match=r"v\.mp4' states no frame rate: give it with --fps"):
        video_io.open_video(path)
    video = video_io.open_video(path, fps=10)
    assert not video.timed and _stamps(video.frames_at([0.0, 0.3])) == [0, 3]


def test_an_animation_without_durations_plays_at_10_fps(tmp_path):
    """A GIF saved with no frame durations (all 0) plays at 10 fps, frame k at k / 10 s, like a single image (a
    zero median duration gave an infinite rate); a given fps places frame k at k / fps."""
    gif = [Image.fromarray(_stamped(k)) for k in range(12)]
    gif[0].save(tmp_path / "z.gif", save_all=True, append_images=gif[1:], duration=0, loop=0)
    video = video_io.open_video(tmp_path / "z.gif")
    assert video.fps == 10 and video.starts.tolist() == pytest.approx([k / 10 for k in range(12)])
    assert _stamps(clip_of(tmp_path / "z.gif", lm.PromptSpec())) == list(range(10))
    assert video_io.open_video(tmp_path / "z.gif", fps=20).starts[-1] == pytest.approx(0.55)


def test_a_folder_with_a_given_rate_is_read_by_time(tmp_path):
    """A folder of exactly 10 frames is the clip itself only when no fps is given: at 20 fps it lasts 0.5 s and
    the clip's 0.9 s is past it. Five frames at 5 fps (0, 0.2, ..., 0.8 s): a time halfway between two frames
    takes the later (0.1 s: frame 1), and 0.9 s, half a frame after the last, is still the last frame."""
    v10 = _folder(tmp_path / "v10", 10)
    with pytest.raises(
        ValueError, match=r"v10' \(10 frames at 20 fps\) lasts 0.5 s \(its last frame comes at 0.45 s\)"
    ):
        clip_of(v10, lm.PromptSpec(), fps=20)
    assert _stamps(clip_of(_folder(tmp_path / "v5", 5), lm.PromptSpec(), fps=5)) == [0, 1, 1, 2, 2, 3, 3, 4, 4, 4]


def test_32_bit_and_float_grey_images_are_scaled_to_8_bits():
    """Pillow's 32-bit grey ('I'): values up to 255 are 8-bit already (200 stays 200), up to 65535 16-bit (300 ->
    1, 65535 -> 255), beyond that scaled by its own maximum (50000 of 100000 -> 128); float grey ('F') is [0, 1]
    (0.5 -> 128)."""

    def grey(values, dtype) -> list[int]:
        return video_io.rgb8(Image.fromarray(np.array([values], dtype)))[0, :, 0].tolist()

    assert grey([0, 200], np.int32) == [0, 200]
    assert grey([0, 300, 65535], np.int32) == [0, 1, 255]
    # 16-bit to 8: / 257 (65535 / 255), so 51400 = 200 * 257 -> 200 exactly (/ 256 gave 200.8 -> 201)
    assert grey([0, 51400, 65535], np.uint16) == grey([0, 51400, 65535], np.int32) == [0, 200, 255]
    assert grey([0, 50000, 100000], np.int32) == [0, 128, 255]
    assert grey([0.0, 0.5, 1.0], np.float32) == [0, 128, 255]


def test_broken_video_is_named_with_the_frames_it_gave(tmp_path, monkeypatch):
    """A video whose decoding fails part-way is named with how many frames came before; an MP4 cut off before
    its index was written (a recording stopped by a crash) says so."""
    frames = np.stack([_stamped(k, (48, 64)) for k in range(20)])
    iio.imwrite(tmp_path / "a.mp4", frames, plugin="pyav", codec="libx264", fps=30)
    whole = (tmp_path / "a.mp4").read_bytes()
    (tmp_path / "cut.mp4").write_bytes(whole[: len(whole) // 2])  # the index (moov) comes last: it is lost
    with pytest.raises(ValueError, match=r"cannot read video .*cut\.mp4' \(one cut off while recording has no index\)"):
        video_io.open_video(tmp_path / "cut.mp4", fps=None).frames_at([0.0])

    plain = video_io._frames

    def failing(path, pillow):
        for k, item in enumerate(plain(path, pillow)):
            if k == 3:
                raise OSError("corrupt packet")
            yield item

    monkeypatch.setattr(video_io, "_frames", failing)
    with pytest.raises(ValueError, match=r"cannot read video .*a\.mp4' after 3 frames: OSError: corrupt packet"):
        video_io.open_video(tmp_path / "a.mp4", fps=None).frames_at([0.0, 0.5])
