"""The console script: every command is wired, help is fast, errors exit 2."""

from __future__ import annotations

import subprocess
import sys

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
    assert "has neither segmentation.npy nor segmentation/*.png" in capsys.readouterr().err
    # an adapter folder without aynamics.json (lm.read_adapter_meta raises with a message only)
    assert (
        cli.main(["preferences", "--data", str(tmp_path), "--out", str(tmp_path / "p"), "--adapter", str(tmp_path)])
        == 2
    )
    err = capsys.readouterr().err
    assert "None" not in err and "--adapter must be a folder written by training" in err
