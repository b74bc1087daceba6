"""Dataset generation: records, determinism, sharding, resume, load_from_disk, CLI, in-context examples."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import warnings
from pathlib import Path

import datasets
import numpy as np
import pytest

from aynamics import generate as gen
from aynamics import reasoning as rs
from aynamics.cli import main
from aynamics.incontext import coverage_targets, select_in_context, write_in_context
from aynamics.sampler import SamplerConfig
from aynamics.scene import parse

try:
    from aynamics.render import gl_available

    GL, WHY = gl_available()
except Exception as e:  # noqa: BLE001 - any import/GL failure means: no rendering here
    GL, WHY = False, str(e)
needs_gl = pytest.mark.skipif(not GL, reason=f"no headless OpenGL: {WHY}")

CFG = gen.GenerateConfig(width=64, height=48, chunk_size=2, workers=0, sampler=SamplerConfig(max_objects=3))
NUM, SEED = 4, 11


def _rows(path) -> dict:
    """Every split's rows as Arrow tables (image bytes included), for exact comparison."""
    dd = datasets.load_from_disk(str(path))
    return {s: dd[s].with_format("arrow")[:] for s in dd}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    return gen.generate_dataset(out, NUM, SEED, CFG)


@needs_gl
def test_records_load_with_load_from_disk(reference):
    dd = datasets.load_from_disk(str(reference))
    assert set(dd) == {"train", "validation", "test"}
    assert sum(len(dd[s]) for s in dd) == NUM
    rows = [r for s in dd for r in dd[s]]
    assert sorted(r["index"] for r in rows) == list(range(NUM))
    for s in dd:  # chunks joined in index order: seed 11 puts scenes 0-3 (chunks [0, 1], [2, 3]) all in train
        assert dd[s]["index"] == [i for i in range(NUM) if gen.split_of(SEED, i, CFG.splits) == s]
    assert dd["train"]["index"] == [0, 1, 2, 3]
    for r in rows:
        assert r["split"] in gen.SPLITS and gen.split_of(SEED, r["index"], CFG.splits) == r["split"]
        scene = parse(r["scene_yaml"])
        assert parse(r["target_think"]) == scene and parse(r["target_answer"]) == scene
        assert r["target_think"].startswith("<think>\n" + r["reasoning"])
        assert len(r["rgb"]) == len(r["flow"]) == len(r["segmentation"]) == 10
        assert r["rgb"][0].size == (64, 48) and r["rgb"][0].mode == "RGB" and r["segmentation"][0].mode == "L"
        seg = np.stack([np.asarray(im, np.int16) - 1 for im in r["segmentation"]])
        vis = rs.visibility(seg, len(scene.objects))
        assert vis.tolist() == r["states"]["visible"]  # visibility stored = visibility of the stored masks
        for i, name in enumerate(scene.names):
            assert (
                f"{name} visible in {vis[:, i].sum()}/10" in r["reasoning"] or f"{vis[:, i].sum()}/10" in r["reasoning"]
            )
        assert r["frame_indices"] == list(range(0, 30, 3))
        pos = np.array(r["states"]["position"])
        assert pos.shape == (31, len(scene.objects), 3)
        assert np.allclose(pos[0], [o.state.position for o in scene.objects], atol=1e-4)
        assert r["camera"]["width"] == 64 and np.array(r["camera"]["K"]).shape == (3, 3)
        assert r["has_collision"] == any(c["b"] != "floor" for c in r["contacts"])
        flow = np.stack([np.asarray(im) for im in r["flow"]])
        moving = (seg >= 0).any() and r["flow_max"] > 0
        assert (flow != 255).any() == moving  # colour only where something moves; white elsewhere


@needs_gl
def test_deterministic_and_sharded(reference, tmp_path):
    """Same seed and config: identical records; two shards in two folders assemble into the same data set."""
    again = gen.generate_dataset(tmp_path / "again", NUM, SEED, dataclasses.replace(CFG))
    assert _rows(again) == _rows(reference)
    assert gen.generate(tmp_path / "s0", NUM, SEED, CFG, shard=0, num_shards=2, progress=False) is None
    assert gen.generate(tmp_path / "s1", NUM, SEED, CFG, shard=1, num_shards=2, progress=False) is None
    assert sorted(p.name for p in (tmp_path / "s0" / "chunks").iterdir()) == ["000000"]
    joined = gen.assemble(tmp_path / "joined", [tmp_path / "s0", tmp_path / "s1"])
    assert _rows(joined) == _rows(reference)


@needs_gl
def test_resume_after_interruption(reference, tmp_path, monkeypatch):
    """A run killed in its second chunk restarts, keeps the first chunk, and ends identical to one clean run."""
    made: list[int] = []
    real = gen.make_record

    def dying(index, seed, config, renderer, given):
        if index == 2:
            raise KeyboardInterrupt
        made.append(index)
        return real(index, seed, config, renderer, given)

    monkeypatch.setattr(gen, "make_record", dying)
    with pytest.raises(KeyboardInterrupt):
        gen.generate(tmp_path / "run", NUM, SEED, CFG, progress=False)
    assert (tmp_path / "run" / "chunks" / "000000").is_dir() and not (tmp_path / "run" / "chunks" / "000001").exists()
    (tmp_path / "run" / "chunks" / ".tmp-000001-999").mkdir()  # debris of a kill during a write
    made.clear()
    monkeypatch.setattr(gen, "make_record", lambda *a: (made.append(a[0]), real(*a))[1])
    path = gen.generate(tmp_path / "run", NUM, SEED, CFG, progress=False)
    assert made == [2, 3]  # chunk 0 (scenes 0, 1) was not redone
    assert not list((tmp_path / "run" / "chunks").glob(".tmp-*"))
    assert _rows(path) == _rows(reference)


@needs_gl
def test_a_full_disk_during_assembly_leaves_no_hidden_copy(reference, tmp_path, monkeypatch, capsys):
    """Assembly writes the data set beside its place first: a full disk there left that hidden `.assemble-PID`
    copy, which no later run removed (it kept the space); the command says so in one line, exit 1."""
    import errno

    from datasets import DatasetDict

    from aynamics.cli import main

    out = tmp_path / "copy"
    shutil.copytree(reference, out)
    (out / "dataset_dict.json").unlink()

    def full(self, path, **kwargs):
        Path(path, "train").mkdir(parents=True)
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(DatasetDict, "save_to_disk", full)
    with pytest.raises(OSError):
        gen.assemble(out)
    assert not list(out.glob(".assemble-*"))
    assert main(["generate", "--num", str(NUM), "--out", str(out), "--assemble"]) == 1
    assert capsys.readouterr().err == f"aynamics: No space left on device: {out / '.assemble-'}{os.getpid()}\n"
    assert not list(out.glob(".assemble-*"))


@needs_gl
def test_resume_refuses_a_different_run(reference, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(reference, out)
    with pytest.raises(ValueError, match="seed = 11, this run has 12"):
        gen.generate(out, NUM, 12, CFG, progress=False)
    with pytest.raises(ValueError, match=r"config max_attempts = 10 \(this run: 5\)"):
        gen.generate(out, NUM, SEED, dataclasses.replace(CFG, max_attempts=5), progress=False)
    shutil.rmtree(out / "chunks" / "000001")
    with pytest.raises(ValueError, match=r"chunks \[1\] of 2 missing"):
        gen.assemble(out)


def test_config_files_and_overrides(tmp_path):
    cfg = gen.apply_overrides(
        gen.GenerateConfig(), ["width=96", "height=64", "sampler.max_objects=2", "sampler.speed=[1, 2]"]
    )
    assert (cfg.width, cfg.sampler.max_objects, cfg.sampler.speed, cfg.sampler.aspect) == (96, 2, (1, 2), 1.5)
    with pytest.raises(ValueError, match="override.sampler.bogus: unknown key"):
        gen.apply_overrides(cfg, ["sampler.bogus=1"])
    with pytest.raises(ValueError, match=r"sampler.box_size|box_size = \[0.1, 9.0\]"):
        gen.apply_overrides(cfg, ["sampler.box_size=[0.1, 9.0]"])
    with pytest.raises(ValueError, match="must be key=value"):
        gen.apply_overrides(cfg, ["width"])
    # values of the wrong kind are named with their key, not left to a TypeError inside the sampler
    for override, message in [
        ("sampler.speed=2", r"override.sampler.speed = 2: must be a list of 2 numbers, e.g. \[1, 2\]"),
        ("sampler.speed=[1, 2, 3]", r"override.sampler.speed = \[1, 2, 3\]: must be a list of 2 numbers"),
        ("sampler.mass=[1, heavy]", r"override.sampler.mass = \[1, 'heavy'\]: must be a list of 2 numbers"),
        ("width=abc", "override.width = 'abc': must be an integer"),
        ("width=96.5", "override.width = 96.5: must be an integer"),
        ("sampler.aspect=wide", "override.sampler.aspect = 'wide': must be a number"),
        ("backdrop=3", "override.backdrop = 3: must be text"),
        ("textures_dir=[1]", r"override.textures_dir = \[1\]: must be a path or null"),
        ("width.x=1", "override 'width.x=1': width is a value, not a group of keys"),
        # the sampler's copies of the view's aspect and the duration (an override was silently replaced: helper-39)
        ("sampler.aspect=2", r"override.sampler.aspect = 2: it is set from width / height \(1.5\); set width"),
        ("sampler.duration=3", r"override.sampler.duration = 3: it is set from duration \(1\); set duration"),
    ]:
        with pytest.raises(ValueError, match=message):
            gen.apply_overrides(cfg, ["width=96", override] if override.startswith("width.") else [override])
    assert gen.apply_overrides(cfg, ["sampler.max_distance=8"]).sampler.max_distance == 8.0  # an integer is a number
    with pytest.raises(FileNotFoundError):
        gen.load_config(tmp_path / "missing.yaml")
    path = tmp_path / "c.yaml"
    path.write_text("width: 128\nsampler:\n  collision_share: 0.2\n")
    assert gen.load_config(path).sampler.collision_share == 0.2
    default = gen.load_config("conf/generate/default.yaml")
    assert default == gen.GenerateConfig()  # the documented file is the defaults


def test_overrides_and_config_files_read_yaml_1_2_numbers(tmp_path):
    """`duration=5e-1` is a number, as in scenes (the README: YAML 1.2, `1e-3` is a number): PyYAML's 1.1 read it
    as the string '5e-1', refused as "must be a number"."""
    cfg = gen.apply_overrides(gen.GenerateConfig(), ["duration=5e-1", "sampler.speed=[5e-1, 3]"])
    assert (cfg.duration, cfg.sampler.speed) == (0.5, (0.5, 3.0))
    with pytest.raises(ValueError, match=r"override 'width=\[1,': value '\[1,' is not valid YAML"):
        gen.apply_overrides(cfg, ["width=[1,"])
    path = tmp_path / "c.yaml"
    path.write_text("duration: 5e-1\nsampler:\n  speed: [1e-1, 2]\n")
    assert (gen.load_config(path).duration, gen.load_config(path).sampler.speed) == (0.5, (0.1, 2.0))
    path.write_text("width: [1,\n")
    with pytest.raises(ValueError, match=r"--config '.*c.yaml': invalid YAML: .*\(line 2, column 1\)"):
        gen.load_config(path)


def test_each_resample_draws_from_its_own_attempts_seed(monkeypatch):
    """Attempt a of scene i of a run with seed s samples from `default_rng(scene_seed(s, i, a))`: a scene that
    fails is resampled from new numbers, not the same scene again (3 attempts: 3 different first draws, each that
    of its attempt's generator; all failing, the error names the count)."""
    from aynamics import sampler as smp

    first_draws = []

    def failing(rng, config):
        first_draws.append(int(rng.integers(2**31)))
        raise RuntimeError("no room")

    monkeypatch.setattr(gen.smp, "sample_scene", failing)
    config = dataclasses.replace(CFG, max_attempts=3)
    with pytest.raises(RuntimeError, match="scene 5 .seed 7.: all 3 attempts failed: no room; no room; no room"):
        gen.sample_simulated(5, 7, config)
    want = [int(np.random.default_rng(smp.scene_seed(7, 5, a)).integers(2**31)) for a in range(3)]
    assert first_draws == want and len(set(want)) == 3


def test_a_chunk_interrupted_while_written_is_not_taken_as_done(tmp_path, monkeypatch):
    """A kill while a chunk is saved leaves no `chunks/000003` (the folder a resume takes as finished), only a
    temporary one that the next run of that chunk removes."""
    from types import SimpleNamespace

    from aynamics import dataset_store

    def killed(path, *args, **kwargs):
        Path(path).mkdir(parents=True)
        (Path(path) / "data-00000-of-00001.arrow").write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(datasets.Dataset, "from_list", lambda *a, **k: SimpleNamespace(save_to_disk=killed))
    with pytest.raises(KeyboardInterrupt):
        dataset_store.write_chunk(tmp_path, 3, [])
    assert not dataset_store.chunk_dir(tmp_path, 3).exists()
    assert [p.name for p in (tmp_path / "chunks").iterdir()] == [f".tmp-000003-{os.getpid()}"]
    dataset_store.remove_partial_chunks(tmp_path, [3])
    assert list((tmp_path / "chunks").iterdir()) == []


def test_shards_are_disjoint_and_cover():
    chunks = [gen.shard_chunks(50, 4, k, 3) for k in range(3)]
    assert sorted(c for cs in chunks for c in cs) == list(range(13))
    with pytest.raises(ValueError, match="shard = 3, num_shards = 3"):
        gen.shard_chunks(50, 4, 3, 3)


@needs_gl
def test_cli_generate(tmp_path, capsys):
    out = tmp_path / "cli"
    argv = ["generate", "--num", "2", "--out", str(out), "--seed", "1", "--workers", "0", "--quiet"]
    assert main([*argv, "width=48", "height=32", "chunk_size=1"]) == 0
    assert sum(len(d) for d in datasets.load_from_disk(str(out)).values()) == 2
    assert json.loads((out / "generate.json").read_text())["num"] == 2
    assert main([*argv, "sampler.nope=1"]) == 2
    assert "sampler.nope: unknown key" in capsys.readouterr().err
    assert main(["generate", "--num", "0", "--out", str(tmp_path / "x"), "--workers", "0"]) == 2


def test_cli_generate_bad_arguments_write_nothing(tmp_path, capsys):
    """A folder as --config is named (not an IsADirectoryError traceback); a bad --shard is refused before
    generate.json is written, so a correct rerun into the same folder with other overrides still works."""
    (tmp_path / "confdir").mkdir()
    out = tmp_path / "g"
    argv = ["generate", "--num", "2", "--out", str(out), "--workers", "0", "--quiet"]
    assert main([*argv, "--config", str(tmp_path / "confdir")]) == 2
    assert f"--config {str(tmp_path / 'confdir')!r} is a folder" in capsys.readouterr().err
    assert main([*argv, "--shard", "3", "--num-shards", "2"]) == 2
    assert "shard = 3, num_shards = 2" in capsys.readouterr().err
    assert not out.exists()  # nothing written: a rerun with other overrides is not refused as another run
    (tmp_path / "bad.yaml").write_bytes(b"\xff\xfe: 1\n")
    assert main([*argv, "--config", str(tmp_path / "bad.yaml")]) == 2
    assert "--config" in capsys.readouterr().err and not out.exists()


def test_in_context_selection_covers_shapes_and_extremes():
    from aynamics.sampler import sample_scene, scene_seed

    scenes = [sample_scene(np.random.default_rng(scene_seed(3, i))) for i in range(40)]
    chosen, missed = select_in_context(scenes)
    assert len(set(chosen)) == 3
    targets, covered = coverage_targets(scenes)
    union = set().union(*(covered[i] for i in chosen))
    assert {"shape:box", "shape:sphere", "shape:cylinder"} <= union
    assert set(missed) == set(targets) - union
    greedy_best = max(len(c) for c in covered)
    assert len(union) >= greedy_best  # at least as good as the single best record


def test_coverage_counts_values_within_five_percent_of_the_span():
    """Camera fovy 40, 41, 50, 59, 60 in five scenes: span 20, tolerance 0.05 * 20 = 1, so 40 and 41 (<= 41) are at
    the minimum and 59 and 60 (>= 59) at the maximum, 50 at neither; shapes are covered by the structure."""
    from types import SimpleNamespace

    def scene(fovy: float, shapes: list[str]):
        camera = SimpleNamespace(fovy=fovy, orientation=0.0, position=[0.0, -5.0, 2.0])
        return SimpleNamespace(objects=[], structure=shapes, camera=camera, gravity=[0.0, 0.0, -9.81])

    scenes = [scene(40, ["box"]), scene(41, []), scene(50, ["sphere"]), scene(59, []), scene(60, ["cylinder"])]
    targets, covered = coverage_targets(scenes)
    assert {"min:camera.fovy", "max:camera.fovy", "shape:box"} <= set(targets)
    fovy = [sorted(t for t in c if t.endswith("camera.fovy")) for c in covered]
    assert fovy == [["min:camera.fovy"], ["min:camera.fovy"], [], ["max:camera.fovy"], ["max:camera.fovy"]]
    assert [sorted(t for t in c if t.startswith("shape:")) for c in covered] == [
        ["shape:box"],
        [],
        ["shape:sphere"],
        [],
        ["shape:cylinder"],
    ]


def test_in_context_examples_come_from_the_train_split(tmp_path_factory, tmp_path):
    """The shared tiny data set holds 5 train, 4 validation and 3 test scenes: the 3 examples written into every
    prompt are train scenes (a held-out scene shown as an example would leak it into its own evaluation)."""
    from train_fixtures import tiny_dataset

    data = tiny_dataset(tmp_path_factory)
    dd = datasets.load_from_disk(str(data))
    assert (len(dd["train"]), len(dd["validation"]), len(dd["test"])) == (5, 4, 3)
    examples = json.loads((write_in_context(data, tmp_path / "ic") / "examples.json").read_text())["examples"]
    assert len(examples) == 3 and {e["index"] for e in examples} <= set(dd["train"]["index"])


@needs_gl
def test_write_in_context(reference, tmp_path):
    folder = write_in_context(reference, tmp_path / "ic")
    data = json.loads((folder / "examples.json").read_text())
    assert len(data["examples"]) == 3
    for ex in data["examples"]:
        assert (folder / ex["frames"][0]).is_file() and (folder / ex["flow"][9]).is_file()
        assert parse(ex["target"]) == parse(ex["scene_yaml"])
    assert (folder / "prompt.md").read_text().count("<answer>") == 3
    assert (
        "shows 10 frames of a video at 30 FPS (video frames [0, 3, 6, 9, 12, 15, 18, 21, 24, 27])"
        in (folder / "prompt.md").read_text()
    )


@needs_gl
def test_in_context_text_says_what_the_examples_show(tmp_path):
    """At 20 fps with every sixth frame the examples hold 3 frames: the prompt says so (it always said 10 frames
    at 30 FPS: helper-39)."""
    config = dataclasses.replace(CFG, fps=20, stride=6)
    folder = write_in_context(gen.generate_dataset(tmp_path / "d", 4, 3, config), tmp_path / "ic")
    assert "shows 3 frames of a video at 20 FPS (video frames [0, 6, 12])" in (folder / "prompt.md").read_text()


@pytest.mark.parametrize("shape", [(1, 1), (5, 7), (48, 64), (6, 4, 1), (6, 4, 2), (32, 48, 3), (9, 3, 4)])
def test_png_bytes_round_trip(shape):
    """Any PNG reader (Pillow here) decodes `png_bytes` to the exact pixels, for every channel count."""
    import io

    from PIL import Image

    from aynamics.png_encode import png_bytes

    image = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)
    for level in (0, 1, 9):
        decoded = np.asarray(Image.open(io.BytesIO(png_bytes(image, level))))
        np.testing.assert_array_equal(decoded, image.reshape(decoded.shape))
        assert decoded.size == image.size


def test_png_bytes_errors():
    from aynamics.png_encode import png_bytes

    with pytest.raises(ValueError, match="dtype float64"):
        png_bytes(np.zeros((4, 4)))
    with pytest.raises(ValueError, match=r"shape \(4, 4, 5\)"):
        png_bytes(np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(ValueError, match=r"shape \(0, 4\)"):
        png_bytes(np.zeros((0, 4), np.uint8))
    with pytest.raises(ValueError, match="level = 10"):
        png_bytes(np.zeros((4, 4), np.uint8), level=10)
    with pytest.raises(ValueError, match="level = -1"):
        png_bytes(np.zeros((4, 4), np.uint8), level=-1)  # zlib would take -1 as its default level
    with pytest.raises(ValueError, match="dtype int8"):
        png_bytes(np.zeros((4, 4), np.int8))  # one byte per sample, but -1 would be written as 255


def test_png_bytes_chunks_by_hand():
    """A 2×3 grey image [[1, 2, 3], [5, 5, 0]]: signature, IHDR (width 3, height 2, 8 bits, colour type 0, default
    compression, filter and interlace), IDAT holding the deflated rows, each led by filter byte 2 (up): [2, 1, 2, 3]
    (the row above the first is zeros) and [2, 4, 3, 253] (0 - 3 wraps to 253), then IEND, whose 12 bytes are fixed:
    length 0, the tag, CRC-32 of "IEND" = 0xAE426082. Each chunk is big-endian length, tag, payload, CRC of tag and
    payload."""
    import struct
    import zlib

    from aynamics.png_encode import png_bytes

    data = png_bytes(np.array([[1, 2, 3], [5, 5, 0]], np.uint8))
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    chunks, at = [], 8
    while at < len(data):
        (n,) = struct.unpack(">I", data[at : at + 4])
        tag, payload = data[at + 4 : at + 8], data[at + 8 : at + 8 + n]
        assert data[at + 8 + n : at + 12 + n] == struct.pack(">I", zlib.crc32(tag + payload))
        chunks.append((tag, payload))
        at += 12 + n
    assert [tag for tag, _ in chunks] == [b"IHDR", b"IDAT", b"IEND"]
    assert chunks[0][1] == bytes([0, 0, 0, 3, 0, 0, 0, 2, 8, 0, 0, 0, 0])
    assert list(zlib.decompress(chunks[1][1])) == [2, 1, 2, 3, 2, 4, 3, 253]
    assert data[-12:] == b"\x00\x00\x00\x00IEND\xaeB`\x82"


@needs_gl
def test_record_flow_equals_flow_of_the_full_video():
    """The record renders only the sampled frames, yet its flow images equal those of the full 30-frame video's
    exact flow (rendered frame by frame, flow with next-frame occlusion) at the sampled indices, on one scale."""
    from aynamics import flow as flowlib
    from aynamics.render import Renderer

    config = dataclasses.replace(CFG, width=64, height=48)
    scene, rollout, attempt = gen.sample_simulated(1, SEED, config)
    look = gen.appearance_seed(SEED, 1, attempt)
    with Renderer(64, 48) as r:
        record = gen.render_record_frames(scene, rollout, r, config, look)
        video = r.render(scene, rollout, seed=look)
    assert record["frames"].tolist() == list(range(0, 30, 3))
    flow, _ = flowlib.motion_flow(scene, rollout, video.depth, video.camera, video.segmentation)
    sampled = flow[record["frames"]]
    assert record["flow_max"] == pytest.approx(float(np.hypot(sampled[..., 0], sampled[..., 1]).max()))
    np.testing.assert_array_equal(record["flow_color"], flowlib.flow_to_color(sampled, record["flow_max"]))
    np.testing.assert_array_equal(record["rgb"], video.rgb[record["frames"]])
    np.testing.assert_array_equal(record["segmentation"], video.segmentation[record["frames"]])
    assert (record["flow_color"] != 255).any()  # something moves in view: the comparison means something


@needs_gl
def test_own_scene_files_make_a_data_set(tmp_path, capsys):
    """`generate --scenes FOLDER`: one record per scene file, in file order (the folder's files, then its test/
    subfolder's, whose split is test; the others take the hash split), each the file's scene; a rerun resumes, a
    changed file is refused as another run, bad files are all named before anything is written."""
    from aynamics.scene import dump, from_items, to_items

    folder = tmp_path / "scenes"
    (folder / "test").mkdir(parents=True)
    scenes = [gen.sample_simulated(i, SEED, CFG)[0] for i in range(3)]
    paths = [folder / "a.yaml", folder / "b.yml", folder / "test" / "c.yaml"]
    for scene, path in zip(scenes, paths, strict=True):
        path.write_text(dump(scene))
    (folder / "notes.txt").write_text("not a scene")
    out = tmp_path / "own"
    argv = ["generate", "--scenes", str(folder), "--out", str(out), "--workers", "0", "--quiet"]
    argv += ["width=64", "height=48", "chunk_size=2"]
    assert main(argv) == 0
    rows = sorted((r for split in datasets.load_from_disk(str(out)).values() for r in split), key=lambda r: r["index"])
    assert [r["index"] for r in rows] == [0, 1, 2]
    assert [r["scene_yaml"] for r in rows] == [dump(s) for s in scenes]
    assert [r["split"] for r in rows] == [gen.split_of(0, 0), gen.split_of(0, 1), "test"]
    assert rows[0]["rgb"][0].size == (64, 48) and len(rows[0]["rgb"]) == 10
    before = _rows(out)
    assert main(argv) == 0 and _rows(out) == before  # resumed: every chunk was there
    items = to_items(scenes[1])
    items[0]["physics"]["mass"] *= 2
    paths[1].write_text(dump(from_items(items)))
    capsys.readouterr()
    assert main(argv) == 2
    message = f"holds a run whose scene 1 ({str(paths[1])!r} then) had another content or split than {str(paths[1])!r}"
    assert message in capsys.readouterr().err and _rows(out) == before

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "mass.yaml").write_text(dump(scenes[0]).replace("mass: ", "mass: -", 1))
    items = to_items(scenes[0])
    items[0]["state"]["position"][2] = 0.0  # half inside the floor: an overlapping start
    (bad / "floor.yaml").write_text(dump(from_items(items)))
    new = tmp_path / "never"
    assert main(["generate", "--scenes", str(bad), "--out", str(new), "--workers", "0", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert (
        "2 scene file(s) cannot be used" in err
        and "mass.yaml: invalid scene (1 problem): objects[0].physics.mass = -" in err
    )
    assert "floor.yaml: the rollout is invalid: overlapping start" in err and not new.exists()
    assert main(["generate", "--scenes", str(tmp_path / "none"), "--out", str(new)]) == 2
    assert f"--scenes {str(tmp_path / 'none')!r} does not exist" in capsys.readouterr().err
    assert main(["generate", "--scenes", str(folder), "--num", "3", "--out", str(new)]) == 2
    assert "not allowed with argument" in capsys.readouterr().err
    # a sampler setting does nothing with --scenes: it was taken without a word
    assert main(["generate", "--scenes", str(folder), "--out", str(new), "width=64", "sampler.max_objects=2"]) == 2
    err = capsys.readouterr().err
    assert "generate: sampler.max_objects=2 sets the scene sampler, which --scenes does not use" in err
    assert main(["generate", "--scenes", str(folder), "--out", str(new), "sampler={max_objects: 2}"]) == 2
    assert "generate: sampler={max_objects: 2} sets the scene sampler" in capsys.readouterr().err
    assert not new.exists()


def test_scene_file_splits_and_resume_do_not_depend_on_how_paths_are_typed(tmp_path, monkeypatch, capsys):
    """The split is the file's folder's (absolute path, any case), so `c.yaml` typed inside `Test/` is a test
    scene; a scene file in another subfolder is refused, not left out unseen; hidden files are skipped; the same
    scene in two splits (by the split each record gets) is warned about; a rerun with the folder typed another way,
    from another working folder,
    and --assemble after the files are gone, all take the run as the same."""
    from aynamics.scene import dump

    folder = tmp_path / "s"
    (folder / "Test").mkdir(parents=True)
    scenes = [gen.sample_simulated(i, SEED, CFG)[0] for i in range(2)]
    (folder / "a.yaml").write_text(dump(scenes[0]))
    (folder / "Test" / "c.yaml").write_text(dump(scenes[1]))
    (folder / "Test" / "._c.yaml").write_bytes(b"\x00\x05 resource fork")  # macOS debris
    monkeypatch.chdir(folder / "Test")
    assert [f.split for f in gen.scene_files(["c.yaml", "../a.yaml"], CFG)] == ["test", None]
    assert [(f.path, f.split) for f in gen.scene_files([folder], CFG)] == [
        (str(folder / "a.yaml"), None),
        (str(folder / "Test" / "c.yaml"), "test"),
    ]
    (folder / "nested").mkdir()
    (folder / "nested" / "d.yaml").write_text(dump(scenes[0]))
    with pytest.raises(ValueError, match=r"nested/d.yaml' is in a subfolder that is not train/, validation/ or test/"):
        gen.scene_files([folder], CFG)
    assert len(gen.scene_files([folder, folder / "nested"], CFG)) == 3  # given as a path of its own: read
    shutil.rmtree(folder / "nested")
    (folder / ".ipynb_checkpoints").mkdir()
    (folder / ".ipynb_checkpoints" / "a-checkpoint.yaml").write_text("not read")
    assert len(gen.scene_files([folder], CFG)) == 2  # a hidden folder is not a subfolder of scenes

    # One scene in two splits, by the split each record gets (indices 0, 1, 2 hash to train, test, train):
    a, c = gen.SceneFile("a.yaml", dump(scenes[0])), gen.SceneFile("c.yaml", dump(scenes[0]), "test")
    with pytest.warns(UserWarning, match=r"--scenes: 'a.yaml' \(train split\) and 'c.yaml' \(test split\) hold"):
        gen.warn_repeated_scenes([a, c], 0, CFG)
    with pytest.warns(UserWarning, match=r"'a.yaml' \(train split\) and 'b.yaml' \(test split\) hold the same"):
        gen.warn_repeated_scenes([a, dataclasses.replace(a, path="b.yaml")], 0, CFG)  # both by the hash
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gen.warn_repeated_scenes([a, gen.SceneFile("x.yaml", dump(scenes[1])), a], 0, CFG)  # train and train
    (folder / "Test" / "c.yaml").write_text(dump(scenes[1]))

    out = tmp_path / "out"
    argv = ["generate", "--out", str(out), "--workers", "0", "--quiet", "width=64", "height=48", "chunk_size=1"]
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--scenes", "s", "--shard", "0", "--num-shards", "2"]) == 0  # chunk 0 only
    monkeypatch.chdir(folder)
    assert main([*argv, "--scenes", str(folder) + "/", "--shard", "1", "--num-shards", "2"]) == 0  # the rest
    splits = datasets.load_from_disk(str(out))
    assert (len(splits["test"]), splits["test"][0]["scene_yaml"]) == (1, dump(scenes[1]))
    assert json.loads((out / "generate.json").read_text())["scene_files"] == ["s/a.yaml", "s/Test/c.yaml"]
    shutil.rmtree(folder)
    before = _rows(out)
    assert main([*argv, "--scenes", "gone", "--assemble"]) == 0 and _rows(out) == before
    capsys.readouterr()
    assert main([*argv[:3], "--num", "2", "--workers", "0", "--quiet"]) == 2  # sampled scenes into this run
    assert "holds a run of scene files, this run makes sampled scenes" in capsys.readouterr().err


@needs_gl
def test_in_view_is_stored_for_the_records_own_view(tmp_path):
    """A portrait data set (48×64): each record's `states.in_view` is the bounding-sphere test in its own camera
    (the stored K, R, t at 48×64), not in the simulator's default 480×320 view (helper-39: 3 of 32 records said an
    object was in view after it had left the picture)."""
    from aynamics import camera as camlib
    from aynamics.simulate import bounding_radius

    config = dataclasses.replace(CFG, width=48, height=64)
    dd = datasets.load_from_disk(str(gen.generate_dataset(tmp_path / "d", 4, 1, config)))
    for r in (r for s in dd.values() for r in s):
        c = r["camera"]
        assert (c["width"], c["height"]) == (48, 64)
        cam = camlib.CameraMatrices(np.array(c["K"]), np.array(c["R"]), np.array(c["t"]), 48, 64)
        radii = np.array([bounding_radius(o) for o in parse(r["scene_yaml"]).objects])
        expected = camlib.sphere_in_view(cam, np.array(r["states"]["position"]), radii)
        assert r["states"]["in_view"] == expected.tolist()


@needs_gl
def test_shards_finishing_together_assemble_in_turn(reference, monkeypatch):
    """Three assembles of one folder at once (shards finishing together), each move of a split slowed down so that
    they would interleave: they take turns, and the folder ends as the data set (interleaved, one split folder was
    replaced while another process filled it: OSError ENOTEMPTY, helper-39)."""
    import os
    import threading
    import time

    from aynamics import dataset_store

    real = os.replace

    def slow(a, b):
        time.sleep(0.05)
        return real(a, b)

    monkeypatch.setattr(dataset_store.os, "replace", slow)
    before, errors = _rows(reference), []
    monkeypatch.setattr(dataset_store.os, "getpid", lambda: threading.get_ident())  # a temporary folder each

    def run():
        try:
            dataset_store.assemble(reference)
        except Exception as e:  # noqa: BLE001 - collected for the assertion
            errors.append(e)

    threads = [threading.Thread(target=run) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and _rows(reference) == before


def test_cli_generate_refuses_a_folder_of_other_files(tmp_path, capsys):
    """--out a folder that is not an earlier run (here the scene folder itself, whose test/ assembly would replace)
    is refused before anything is written, and the user's files stay."""
    folder = tmp_path / "mine"
    (folder / "test").mkdir(parents=True)
    scene = Path(__file__).parent / "assets" / "paper_example.yaml"
    (folder / "test" / "c.yaml").write_text(scene.read_text())
    argv = ["generate", "--scenes", str(folder), "--out", str(folder), "--workers", "0", "--quiet"]
    assert main(argv) == 2
    assert f"--out {str(folder)!r} holds other files ('test', ...)" in capsys.readouterr().err
    assert sorted(p.name for p in folder.rglob("*")) == ["c.yaml", "test"]
    assert main(["generate", "--num", "2", "--out", str(folder), "--workers", "0", "--quiet"]) == 2
    assert (folder / "test" / "c.yaml").exists() and not (folder / "generate.json").exists()


@needs_gl
def test_a_run_made_by_other_physics_is_neither_resumed_nor_read_silently(tmp_path):
    """A manifest written before the physics changed (5330873's exact damping moves chaotic rollouts by up to metres:
    28 of make train's 171 validation records re-simulate > 1 mm off their stored states) has no `physics`: a resume
    into it is refused (it mixed old and new chunks into one data set), and reading it for training warns."""
    from aynamics.data import with_clock
    from aynamics.lm import PromptSpec
    from aynamics.simulate import PHYSICS_VERSION

    out = tmp_path / "run"
    assert gen.generate(out, 4, SEED, CFG, shard=0, num_shards=2, progress=False) is None
    manifest = json.loads((out / "generate.json").read_text())
    assert manifest["config"]["physics"] == PHYSICS_VERSION and manifest["config"]["substeps"] == 8
    del manifest["config"]["physics"]  # as the code before wrote it
    (out / "generate.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=rf"config physics = None \(this run: {PHYSICS_VERSION}\)"):
        gen.generate(out, 4, SEED, CFG, shard=1, num_shards=2, progress=False)
    split = datasets.Dataset.from_dict({"frame_indices": [[0, 3]]})
    with pytest.warns(
        UserWarning, match=f"simulated with physics version 1, this code simulates version {PHYSICS_VERSION}"
    ):
        with_clock(PromptSpec(), out, split)


@needs_gl
def test_an_occluded_object_is_hidden_not_out_of_view():
    """Record 15 of seed 0 (64×48): sphere_0 passes behind cylinder_0 in the middle of the picture (its centre
    projects to about pixel (31, 15), covered by cylinder_0's mask). The text said it "leaves the view" / "exits
    the frame" at 0.40 s and 0.70 s."""
    from aynamics.render import Renderer

    cfg = gen.GenerateConfig(width=64, height=48, workers=0)
    with Renderer(64, 48) as renderer:
        rec = gen.make_record(15, 0, cfg, renderer)
    vis_line = rec["reasoning"].split("Visibility: ")[1].split("\n")[0]
    sphere = vis_line.split("sphere_0 ")[1].split(" box_0 ")[0]
    assert not rec["states"]["visible"][4][1]  # the record has the occlusion this test is about
    assert "t=0.40s" in sphere and not re.search(r"leaves the view|exits the frame|goes out of view", sphere), sphere


def test_a_run_labelled_by_older_code_is_not_resumed(tmp_path):
    """The manifest records the labels version; a folder whose manifest has none (labels 1) is another run."""
    assert CFG.to_json()["labels"] == gen.LABELS_VERSION
    old = {"format": gen.FORMAT_VERSION, "num": 2, "seed": 0, "config": {**CFG.to_json()}}
    del old["config"]["labels"]
    (tmp_path / gen.MANIFEST).write_text(json.dumps(old))
    with pytest.raises(ValueError, match="labels"):
        gen.write_manifest(tmp_path, {"format": gen.FORMAT_VERSION, "num": 2, "seed": 0, "config": CFG.to_json()})


def test_a_second_writer_of_a_shards_chunks_is_refused_and_other_shards_are_not(tmp_path):
    """Shards of one run share a folder, each holding `.shard-K-of-N.lock` while it writes. With num = 4 and
    chunk_size = 2 (chunks 0 and 1), shard 0/2 makes chunk 0, shard 1/2 chunk 1 and shard 0/1 both: while 0/2
    writes, a second 0/2 and a 0/1 (sharing chunk 0) are refused, naming the folder and the shard; 1/2 is not.
    Once 0/2 is done its lock file stays but is no one's: 0/1 goes ahead."""
    from aynamics import dataset_store

    out = tmp_path / "run"
    manifest = {"format": 1, "num": 4, "seed": 0, "config": {"chunk_size": 2}}
    with dataset_store.claim_shard(out, manifest, 0, 2):
        with pytest.raises(ValueError, match=rf"--out '{re.escape(str(out))}': another process is writing shard 0/2"):
            with dataset_store.claim_shard(out, manifest, 0, 2):
                pass
        with pytest.raises(ValueError, match=r"writing shard 0/2 .*\.shard-0-of-2\.lock.*that shard 0/1 makes too"):
            with dataset_store.claim_shard(out, manifest, 0, 1):
                pass
        with dataset_store.claim_shard(out, manifest, 1, 2):
            pass
    with dataset_store.claim_shard(out, manifest, 0, 1):
        pass
    assert sorted(p.name for p in out.iterdir()) == [
        ".generate.lock",
        ".shard-0-of-1.lock",
        ".shard-0-of-2.lock",
        ".shard-1-of-2.lock",
        "generate.json",
    ]


@needs_gl
def test_two_generates_of_one_shard_into_one_folder(reference, tmp_path, monkeypatch):
    """Two `aynamics generate --num 40 --out X` started 1.5 s apart (helper-86): the second redid the first's
    chunks, stopped with OSError ENOTEMPTY renaming its chunk 1 onto the first's and left its copy
    `chunks/.tmp-000001-PID` behind (or, started while the first saved a chunk, deleted it as a leftover). Now,
    with shard 0/2 of a run paused in its first scene, a second 0/2 and a 0/1 are refused before they render
    anything; shard 1/2 then writes beside it, and the folder ends as the one-run data set."""
    import threading

    out = tmp_path / "run"
    real, paused, go, made = gen.make_record, threading.Event(), threading.Event(), []

    def pausing(index, seed, config, renderer, given):
        made.append(index)
        if threading.current_thread() is not threading.main_thread():
            paused.set()
            go.wait(60)
        return real(index, seed, config, renderer, given)

    monkeypatch.setattr(gen, "make_record", pausing)
    first = threading.Thread(target=gen.generate, args=(out, NUM, SEED, CFG, 0, 2, False))
    first.start()
    try:
        assert paused.wait(60)
        refused = rf"--out '{re.escape(str(out))}': another process is writing shard 0/2"
        for shard, num_shards in ((0, 2), (0, 1)):
            with pytest.raises(ValueError, match=refused):
                gen.generate(out, NUM, SEED, CFG, shard, num_shards, progress=False)
        assert made == [0]  # the first writer's scene only
    finally:
        go.set()
        first.join()
    assert gen.generate(out, NUM, SEED, CFG, 1, 2, progress=False) == out
    assert made == [0, 1, 2, 3] and _rows(out) == _rows(reference)
    assert sorted(p.name for p in (out / "chunks").iterdir()) == ["000000", "000001"]


@needs_gl
def test_an_assembly_killed_while_saved_is_removed_by_the_next(reference, tmp_path):
    """`kill -9` of `aynamics generate --assemble` while it saved left `.assemble-PID` (a hidden copy of the data
    set, here with its train/ started) that no later run removed. The next assembly removes such folders whose
    `.lock` no one holds; one another shard holds (assembling at once) and other names stay."""
    from aynamics.dataset_store import exclusive

    out = tmp_path / "copy"
    shutil.copytree(reference, out)
    (out / ".assemble-999999" / "train").mkdir(parents=True)  # killed: old code made no .lock
    (out / ".assemble-999998").mkdir()
    (out / ".assemble-999998" / ".lock").touch()  # killed: its lock went with its process
    (out / ".assemble-999997").mkdir()
    (out / ".assemble-notes").mkdir()
    with exclusive(out / ".assemble-999997" / ".lock"):  # alive
        gen.assemble(out)
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".assemble")) == [
        ".assemble-999997",
        ".assemble-notes",
        ".assemble.lock",
    ]
    assert _rows(out) == _rows(reference)


def test_an_assembly_deleted_by_its_writer_while_looked_at_is_passed_over(tmp_path, monkeypatch):
    """A finished assembly deletes its `.assemble-PID` after giving `.assemble.lock` back, so the next one may find
    the folder and see it gone before it opens its `.lock`: that one's assembly stopped with FileNotFoundError
    (`open(.assemble-PID/.lock, "a")`). It is passed over; a dead one beside it is still removed."""
    from aynamics import dataset_store

    (tmp_path / ".assemble-101").mkdir()
    (tmp_path / ".assemble-102").mkdir()
    real = dataset_store.exclusive

    def finishing(path, **kwargs):
        if path.parent.name == ".assemble-101":  # its writer's rmtree, between the look and the open
            shutil.rmtree(path.parent)
        return real(path, **kwargs)

    monkeypatch.setattr(dataset_store, "exclusive", finishing)
    dataset_store.remove_dead_assemblies(tmp_path)
    assert not any(p.name.startswith(".assemble-") for p in tmp_path.iterdir())


def _highest_reachable(scene, rollout) -> np.ndarray:
    """(N,) m: the highest each object's centre can rise with no other object touching it: its start height plus its
    start energy per kg, ½|v|² + ½ω·(I/m)ω, over g (the floor, friction and damping only take energy away)."""
    from aynamics.simulate import inertia

    out = []
    for i, obj in enumerate(scene.objects):
        w_world = np.asarray(obj.state.angular_velocity, float)
        energy = 0.5 * float(np.sum(np.square(obj.state.linear_velocity))) + 0.5 * float(w_world @ w_world) * float(
            inertia(obj).max() / obj.physics.mass
        )
        out.append(rollout.position[0, i, 2] + energy / abs(scene.gravity[2]))
    return np.array(out)


def test_a_scene_whose_cylinder_jumps_by_itself_is_resampled():
    """Scene 8 of seed 11 first draws a cylinder dropped from z = 0.94 m at 1.41 m/s, spinning 1.38 rad/s about its
    upright axis, that never touches another object: it can rise to z0 + (½v² + ½Iω²/m)/g = 1.05 m at most, yet
    MuJoCo's plane-cylinder contact launches it off the floor to 5.6 m. That draw is resampled: in what
    `sample_simulated` gives, no object untouched by another rises above its reachable height."""
    from aynamics import sampler as smp
    from aynamics.simulate import simulate

    first = smp.sample_scene(np.random.default_rng(smp.scene_seed(SEED, 8, 0)), CFG.sampler)
    launched = simulate(first, CFG.sim)
    assert launched.valid and launched.position[:, 0, 2].max() > _highest_reachable(first, launched)[0] + 4.0
    scene, rollout, attempt = gen.sample_simulated(8, SEED, CFG)
    assert attempt >= 1
    n = len(scene.objects)
    untouched = ~rollout.touching[:, :, :n].any(axis=(0, 2))
    assert (rollout.position[:, :, 2].max(axis=0) <= _highest_reachable(scene, rollout) + 0.01)[untouched].all()


def test_make_train_names_a_data_set_of_other_physics_or_labels(tmp_path):
    """`make train` makes its data set again when its manifest names other physics or labels than this code's
    (`stale_physics`, `stale_labels`); a current one, or a folder without a manifest (made otherwise), stays."""
    from aynamics.dataset_store import MANIFEST, stale_labels, stale_physics
    from aynamics.generate_config import LABELS_VERSION
    from aynamics.simulate import PHYSICS_VERSION

    def made(physics, labels):
        (tmp_path / MANIFEST).write_text(json.dumps({"config": {"physics": physics, "labels": labels}}))
        return stale_physics(tmp_path), stale_labels(tmp_path)

    assert made(PHYSICS_VERSION, LABELS_VERSION) == (None, None)
    physics, labels = made(PHYSICS_VERSION, LABELS_VERSION - 1)
    assert (
        physics is None and f"labels version {LABELS_VERSION - 1}, this code writes version {LABELS_VERSION}" in labels
    )
    physics, labels = made(PHYSICS_VERSION - 1, LABELS_VERSION)
    assert labels is None and f"physics version {PHYSICS_VERSION - 1}" in physics
    (tmp_path / MANIFEST).unlink()
    assert (stale_physics(tmp_path), stale_labels(tmp_path)) == (None, None)
    makefile = (Path(__file__).resolve().parents[1] / "Makefile").read_text()
    assert "stale_labels" in makefile and "stale_physics" in makefile
