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
