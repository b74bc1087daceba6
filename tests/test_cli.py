"""The console script: every command is wired, help is fast, errors exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from aynamics import cli


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_every_command_builds_its_parser(name, capsys):
    parser = cli.build_parser([name])
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args([name, "--help"])
    assert exit_.value.code == 0
    assert "usage: aynamics " + name in capsys.readouterr().out


def test_help_lists_every_command_without_heavy_imports():
    code = "import sys; from aynamics import cli; cli.build_parser(['--help']); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
    help_text = subprocess.run([sys.executable, "-m", "aynamics.cli", "--help"], capture_output=True, text=True).stdout
    assert all(name in help_text for name in cli.COMMANDS)


def test_no_command_is_a_usage_error(capsys):
    assert cli.main([]) == 2
    assert "give a command" in capsys.readouterr().err


def test_missing_file_messages_say_what_was_expected(tmp_path, capsys):
    """A missing path reads `file not found: PATH`; a check of ours that raised with its own message (what the
    folder lacks) shows that message, not `file not found: None` or the bare folder name."""
    import errno
    import os

    assert cli.missing_file_message(FileNotFoundError("model path 'x' is not a directory")) == (
        "model path 'x' is not a directory"
    )
    assert cli.missing_file_message(FileNotFoundError(2, "'d' has no frames/*.png", "d")) == "'d' has no frames/*.png"
    assert (
        cli.missing_file_message(FileNotFoundError(2, "no such checkpoint", "c.ckpt")) == "no such checkpoint: c.ckpt"
    )
    assert cli.missing_file_message(FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), "f")) == (
        "file not found: f"
    )
    try:
        open(tmp_path / "nope.yaml")
    except FileNotFoundError as e:
        assert cli.missing_file_message(e) == f"file not found: {tmp_path / 'nope.yaml'}"

    # an observed folder that exists but holds no masks: the reason, not "file not found: DIR"
    (tmp_path / "pred.yaml").write_text("- {type: sphere, radius: 0.2, state: {position: [0, 1, 0.2]}}\n")
    (tmp_path / "empty").mkdir()
    assert cli.main(["score", str(tmp_path / "pred.yaml"), "--observed", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err  # the command's name, not "aynamics: "
    assert err.startswith("score: ") and "has neither segmentation.npy nor segmentation/*.png" in err
    # an adapter folder without aynamics.json (adapters.read_adapter_meta raises with a message only)
    assert (
        cli.main(["preferences", "--data", str(tmp_path), "--out", str(tmp_path / "p"), "--adapter", str(tmp_path)])
        == 2
    )
    err = capsys.readouterr().err
    assert "None" not in err and "--adapter must be a folder written by training" in err


ASSET = str(Path(__file__).parent / "assets" / "paper_example.yaml")


def test_python_dash_m_reports_usage_errors_without_a_traceback(tmp_path):
    """`python -m aynamics.cli` runs cli.py as `__main__`: its UsageError was another class than the
    `aynamics.cli.UsageError` the command modules raise, so their errors escaped as tracebacks."""
    argv = [sys.executable, "-m", "aynamics.cli", "render", ASSET, "--out", str(tmp_path / "r"), "--width", "3"]
    run = subprocess.run(argv, capture_output=True, text=True)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.startswith("render: --width 3")


@pytest.mark.parametrize(
    "option, message",
    [
        (["--fps", "0"], "simulate: --fps 0: must be a whole number in [1, 1000]"),
        (["--substeps", "0"], "simulate: --substeps 0: must be a whole number in [1, 1000]"),
        (["--duration", "-1"], "simulate: --duration -1.0: must be in (0, 60] s"),
        (
            ["--fps", "1000", "--duration", "60", "--substeps", "1000"],
            "simulate: --duration 60.0 s at --fps 1000 with --substeps 1000 is 60000000 physics steps: at most 200000 "
            "(the default is 1 s x 30 x 8)",
        ),
    ],
)
def test_simulate_names_a_bad_option_and_its_value(capsys, option, message):
    """The configuration's check said "fps = 0: ...", naming neither the command nor the option."""
    assert cli.main(["simulate", ASSET, "--json", *option]) == 2
    assert capsys.readouterr().err.strip() == message


def test_simulate_out_is_exactly_the_path_given(tmp_path, capsys):
    """A folder as --out is refused (numpy wrote FOLDER.npz beside it and exited 0); a path without .npz is
    written as given, not with .npz appended."""
    import numpy as np

    folder = tmp_path / "runs"
    folder.mkdir()
    assert cli.main(["simulate", ASSET, "--out", str(folder)]) == 2
    assert f"--out {str(folder)!r} is a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"] and not any(folder.iterdir())
    assert cli.main(["simulate", ASSET, "--out", str(tmp_path / "traj"), "--duration", "0.2"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs", "traj"]
    assert np.load(tmp_path / "traj")["position"].shape == (7, 2, 3)  # 0.2 s at 30 FPS: states 0..6
    assert cli.main(["simulate", ASSET, "--out", str(tmp_path / "no" / "t.npz")]) == 2
    assert "folder" in capsys.readouterr().err


def test_simulate_names_why_a_rollout_is_invalid(tmp_path, capsys):
    """Two boxes at one place: exit status 1 and the reason on stderr (the exit status alone said nothing)."""
    box = "- type: box\n  size: [0.2, 0.2, 0.2]\n  state: {position: [0, 0, 0.1]}\n"
    path = tmp_path / "overlap.yaml"
    path.write_text(box + box + "- type: camera\n  position: [0, -3, 3]\n")
    assert cli.main(["simulate", str(path), "--out", str(tmp_path / "t.npz")]) == 1
    assert "simulate: the rollout is invalid: overlapping start" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("command", "named"),
    [
        (["simulate", "BAD", "--json"], "simulate: 'BAD'"),
        (["render", "BAD", "--out", "OUT"], "render: 'BAD'"),
        (["edit", "BAD", "stop box_0"], "edit: 'BAD'"),
        (["refine", "GOOD", "BAD", "--observed", "GOOD"], "refine: 'BAD'"),
        (["score", "GOOD", "--observed", "BAD"], "score: --observed 'BAD'"),
        (["audit", "--measured", "M.csv", "--scene", "BAD", "--out", "OUT"], "audit: --scene 'BAD'"),
    ],
)
def test_a_bad_scene_file_is_named_with_its_problem(tmp_path, capsys, command, named):
    """An invalid scene file given on the command line: the problem came without the file ("invalid scene (1
    problem): objects[0].physics.mass = -1.0: must be > 0"), so a command reading two scenes (refine's
    predictions, score's --observed beside its predictions, audit's --scene beside its CSV) did not say which.
    Now the command and the file (with its option) come first; a file that cannot be read is named once."""
    good = Path(ASSET).read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(good.replace("mass: 1.0", "mass: -1.0", 1))
    assert good.count("mass: 1.0") >= 1
    paths = {"BAD": str(bad), "GOOD": ASSET, "OUT": str(tmp_path / "out")}
    assert cli.main([paths.get(a, a) for a in command]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err
        == named.replace("BAD", str(bad)) + ": invalid scene (1 problem): objects[0].physics.mass = -1.0: must be > 0"
    )
    assert not (tmp_path / "out").exists()
    assert cli.main(["simulate", str(tmp_path / "none.yaml"), "--json"]) == 2  # unreadable: the file named once
    assert capsys.readouterr().err.strip() == f"simulate: {str(tmp_path / 'none.yaml')!r}: No such file or directory"


def test_render_checks_its_arguments_before_making_folders(tmp_path, capsys):
    """--seed -1 is named (the message blamed "--textures None"); a bad --textures is named; neither leaves
    --out/frames or --out/flow behind."""
    out = tmp_path / "r"
    assert cli.main(["render", ASSET, "--out", str(out), "--seed", "-1"]) == 2
    err = capsys.readouterr().err
    assert "--seed -1: must be >= 0" in err and "--textures" not in err
    assert cli.main(["render", ASSET, "--out", str(out), "--textures", str(tmp_path / "none")]) == 2
    assert f"--textures {str(tmp_path / 'none')!r}" in capsys.readouterr().err
    (tmp_path / "f").write_text("x")
    assert cli.main(["render", ASSET, "--out", str(tmp_path / "f" / "r")]) == 2
    assert "is a file" in capsys.readouterr().err
    assert not out.exists()


def test_render_and_edit_refuse_a_folder_of_other_files(tmp_path, capsys):
    """`render --out` (and `edit --render`) into a folder of other files, e.g. a data set, mixed the frames and
    arrays into it with exit 0; now refused before any work, naming a file there. A new folder, an empty one or
    an earlier render is written."""
    data = tmp_path / "dataset"
    data.mkdir()
    (data / "dataset_dict.json").write_text("{}")
    assert cli.main(["render", ASSET, "--out", str(data), "--width", "32", "--height", "32"]) == 2
    assert f"--out {str(data)!r} holds other files ('dataset_dict.json', ...)" in capsys.readouterr().err
    assert cli.main(["edit", ASSET, "stop box_0", "--render", str(data)]) == 2
    assert f"edit: --render {str(data)!r} holds other files" in capsys.readouterr().err
    assert sorted(p.name for p in data.iterdir()) == ["dataset_dict.json"]
    from aynamics.observe_cli import RENDER_FILES

    cli.check_out_folder("render", tmp_path / "new", writes=RENDER_FILES)  # new: fine
    folder = tmp_path / "earlier"
    (folder / "frames").mkdir(parents=True)  # a render that stopped after making its folders, a hidden file
    (folder / ".DS_Store").write_text("")
    cli.check_out_folder("render", folder, writes=RENDER_FILES)
    (folder / "meta.json").write_text("{}")
    (folder / "video.gif").write_text("")
    cli.check_out_folder("render", folder, writes=RENDER_FILES)
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(cli.UsageError, match="holds other files \\('notes.txt', ...\\)"):
        cli.check_out_folder("render", folder, writes=RENDER_FILES)


def test_score_reads_predictions_with_the_scene_loaders_limit(tmp_path, capsys):
    """A prediction file past the scene loader's size cap scores 0 with the reason `simulate` gives for it (the
    file was read whole); a binary one is "not UTF-8" (it was decoded with replacement characters)."""
    import json

    from aynamics.scene import MAX_TEXT_CHARS, SceneError, load

    long, binary = tmp_path / "long.yaml", tmp_path / "bin.yaml"
    long.write_text("#" * (MAX_TEXT_CHARS + 10))
    binary.write_bytes(b"\xff\xfe\x00")
    assert cli.main(["score", ASSET, str(long), str(binary), "--observed", ASSET, "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert [g["valid"] for g in got] == [True, False, False] and got[0]["iou_full"] == 1.0
    with pytest.raises(SceneError) as refused:
        load(str(long))
    assert got[1]["reason"] == str(refused.value) and f"at most {MAX_TEXT_CHARS} characters" in got[1]["reason"]
    assert "not UTF-8" in got[2]["reason"]


@pytest.mark.parametrize("flag", ["--width", "--height"])
def test_score_refuses_a_zero_scoring_size(capsys, flag):
    """0 is refused with the other sizes out of range (it passed the check as "not given" before); only the size
    given is named (the other read "None")."""
    assert cli.main(["score", ASSET, "--observed", ASSET, flag, "0"]) == 2
    assert f"score: {flag} 0: must be in [8, 1920] × [8, 1280] (width × height)" in capsys.readouterr().err


def test_score_against_a_scene_takes_the_scoring_size_given(monkeypatch, capsys):
    """A scene has no image size of its own: it is observed at the scorer's 120×80 (3:2) unless a size is given.
    --height 40 alone is 60×40 (40·120/80), --width 60 alone 60×40 (60·80/120), neither 120×80; --width 100
    --height 80 is off 3:2 by 20 pixels (100 against 80·120/80 = 120) and refused, naming width 120."""
    from aynamics import observation

    seen, observe = [], observation.Observation.from_scene

    def spy(scene, *, width, height):
        seen.append((width, height))
        return observe(scene, width=width, height=height)

    monkeypatch.setattr(observation.Observation, "from_scene", spy)
    for size in (["--height", "40"], ["--width", "60"], []):
        assert cli.main(["score", ASSET, "--observed", ASSET, *size]) == 0
        assert capsys.readouterr().out == f"{ASSET}: iou 1.0/1.0 epe 0.0/0.0\n"
    assert seen == [(60, 40), (60, 40), (120, 80)]
    assert cli.main(["score", ASSET, "--observed", ASSET, "--width", "100", "--height", "80"]) == 2
    err = capsys.readouterr().err
    assert "scoring size 100×80 is off the video's aspect ratio (120×80)" in err and "(width 120)" in err


def test_hidden_files_in_an_earlier_renders_images_are_not_the_users(tmp_path):
    """An earlier render whose frames/ and flow/ hold hidden files (a .DS_Store the file browser left, a copy's
    ._flow_0000.png) besides frame_0000.png and flow_0000.png is written over, as hidden files beside its other
    outputs are; a visible image of another name (IMG_0.png) still shows a video folder of the user's."""
    from aynamics.observe_cli import check_earlier_render

    out = tmp_path / "earlier"
    (out / "frames").mkdir(parents=True)
    (out / "flow").mkdir()
    for name in ("frames/.DS_Store", "frames/frame_0000.png", "flow/._flow_0000.png", "flow/flow_0000.png"):
        (out / name).write_bytes(b"")
    check_earlier_render(out)
    (out / "frames" / "IMG_0.png").write_bytes(b"")
    with pytest.raises(cli.UsageError, match="frames/IMG_0.png is not a file render writes"):
        check_earlier_render(out)


def test_an_unknown_option_before_the_command_is_the_one_named(tmp_path, capsys):
    """`aynamics --verbose render SCENE --out DIR`: the command is the first word that is no option, so render's
    own arguments are known and only --verbose is named (not "--verbose SCENE --out DIR"); nothing is written."""
    assert cli.main(["--verbose", "render", ASSET, "--out", str(tmp_path / "r")]) == 2
    assert capsys.readouterr().err == "aynamics: unrecognized arguments: --verbose. Run `aynamics --help` for usage.\n"
    assert not (tmp_path / "r").exists()


def test_render_refuses_a_video_folder_of_the_users(tmp_path, capsys):
    """A video folder in the observed layout (frames/ of its own names, segmentation.npy: what `evaluate --videos`
    and PRO read) has only names render writes: its masks were overwritten by the render's and 30 frame_NNNN.png
    mixed into its frames, exit 0. Now refused, untouched; an earlier render is still written over."""
    import numpy as np

    video = tmp_path / "myvideo"
    (video / "frames").mkdir(parents=True)
    (video / "frames" / "IMG_0.png").write_bytes(b"")
    np.save(video / "segmentation.npy", np.zeros((30, 8, 8), np.int16))
    before = (video / "segmentation.npy").read_bytes()
    size = ["--width", "32", "--height", "32", "--no-gif"]
    assert cli.main(["render", ASSET, "--out", str(video), *size]) == 2
    assert "frames/IMG_0.png is not a file render writes" in capsys.readouterr().err
    (video / "frames" / "IMG_0.png").unlink()
    assert cli.main(["render", ASSET, "--out", str(video), *size]) == 2
    assert "segmentation.npy without depth.npy" in capsys.readouterr().err
    assert (video / "segmentation.npy").read_bytes() == before and not any((video / "frames").iterdir())
    earlier = tmp_path / "earlier"
    assert cli.main(["render", ASSET, "--out", str(earlier), *size]) == 0
    assert cli.main(["render", ASSET, "--out", str(earlier), *size, "--seed", "1"]) == 0


def test_render_of_an_invalid_rollout_exits_1_and_the_smallest_size_is_taken(tmp_path, capsys):
    """Two boxes at one place rendered at 16×16 (the smallest size render takes): the files are written, the
    reason is named on stderr and the exit status is 1, as `simulate` gives."""
    from aynamics.render import gl_available

    if not gl_available()[0]:
        pytest.skip("render needs headless OpenGL")
    box = "- type: box\n  size: [0.2, 0.2, 0.2]\n  state: {position: [0, 0, 0.1]}\n"
    path = tmp_path / "overlap.yaml"
    path.write_text(box + box + "- type: camera\n  position: [0, -3, 3]\n")
    assert cli.main(["render", str(path), "--out", str(tmp_path / "r"), "--width", "16", "--height", "16"]) == 1
    assert "render: the rollout is invalid: overlapping start" in capsys.readouterr().err
    assert (tmp_path / "r" / "segmentation.npy").is_file()


def test_score_prints_first_frame_then_full_and_why_a_prediction_is_invalid(tmp_path, capsys):
    """Text output, one line a prediction: "PATH: iou FIRST/FULL epe FIRST/FULL", then " INVALID: reason" for one
    that is no scene. The true scene scores 1.0/1.0 and 0.0/0.0; its cylinder 1.2 m/s faster keeps frame 0 (IoU
    first 1.0) but not the rest (full < 1); a box size of -1 scores 0.0 IoU and is named."""
    import json

    from aynamics.scene import dump, from_items, load, to_items

    items = to_items(load(ASSET))
    items[1]["state"]["linear_velocity"][0] += 1.2
    faster, bad = tmp_path / "faster.yaml", tmp_path / "bad.yaml"
    faster.write_text(dump(from_items(items)))
    bad.write_text("- type: box\n  size: [1, -1, 1]\n")
    paths = [ASSET, str(faster), str(bad)]
    assert cli.main(["score", *paths, "--observed", ASSET]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert cli.main(["score", *paths, "--observed", ASSET, "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got[1]["iou_first"] == 1.0 and got[1]["iou_full"] < 1.0
    for line, path, g in zip(lines, paths, got, strict=True):
        assert line.startswith(f"{path}: iou {g['iou_first']}/{g['iou_full']} epe {g['epe_first']}/{g['epe_full']}")
    assert lines[0] == f"{ASSET}: iou 1.0/1.0 epe 0.0/0.0"
    assert lines[2].startswith(f"{bad}: iou 0.0/0.0 epe ") and " INVALID: " in lines[2] and "size" in lines[2]


def test_main_gives_refusals_to_write_and_interrupts_their_exit_statuses(monkeypatch, capsys):
    """A command stopped by the machine's refusal to write (full disk ENOSPC or quota EDQUOT, read-only EROFS, not
    allowed EACCES / EPERM): one line "aynamics: REASON: FILE", exit 1; Ctrl-C: "aynamics: interrupted", exit 130;
    a closed pipe (`| head`): exit 0; any other OSError (EIO) keeps its traceback."""
    import errno
    import io
    import os

    raised = []

    def run(args):
        raise raised[-1]

    monkeypatch.setattr(cli, "_run_ranges", run)
    for code in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM):
        raised.append(OSError(code, os.strerror(code), "/x/f"))
        assert cli.main(["ranges"]) == 1
        assert capsys.readouterr().err == f"aynamics: {os.strerror(code)}: /x/f\n"
    raised.append(KeyboardInterrupt())
    assert cli.main(["ranges"]) == 130 and capsys.readouterr().err == "aynamics: interrupted\n"
    raised.append(OSError(errno.EIO, os.strerror(errno.EIO)))
    with pytest.raises(OSError):
        cli.main(["ranges"])
    raised.append(BrokenPipeError())
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # closed by main
    assert cli.main(["ranges"]) == 0


def test_warnings_as_lines_writes_the_projects_own_warnings_as_one_line(capsys):
    """Within the block a warning starting with the prefix is written at once as "COMMAND: text" without it."""
    import warnings

    with cli.warnings_as_lines("evaluate", "scene evaluation: "):
        warnings.warn("scene evaluation: video folder 'v' is left out: no frames", stacklevel=1)
    assert capsys.readouterr().err == "evaluate: video folder 'v' is left out: no frames\n"
