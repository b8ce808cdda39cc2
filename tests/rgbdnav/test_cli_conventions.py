"""CLI conventions a ROS / Unix user expects (issue 23, item 8): --version, -h, shell
completion, --quiet everywhere, and no option that is silently ignored."""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from typer.main import get_command
from typer.testing import CliRunner

from rgbdnav.cli import app

REPO = Path(__file__).resolve().parents[2]

runner = CliRunner()
VERBS = sorted(get_command(app).commands)  # type: ignore[attr-defined]


def test_version() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.output.startswith("rgbdnav ")


@pytest.mark.parametrize("verb", [None, *VERBS])
def test_dash_h_is_help_everywhere(verb: str | None) -> None:
    args = [verb] if verb else []
    short, long = runner.invoke(app, [*args, "-h"]), runner.invoke(app, [*args, "--help"])
    assert short.exit_code == long.exit_code == 0
    assert short.output == long.output and "Usage:" in short.output


@pytest.mark.parametrize("verb", VERBS)
def test_every_verb_has_quiet_and_verbose(verb: str) -> None:
    command = get_command(app).commands[verb]  # type: ignore[attr-defined]
    leaves = list(getattr(command, "commands", {}).values()) or [command]  # a group: each verb
    for leaf in leaves:
        names = {opt for p in leaf.params for opt in getattr(p, "opts", [])}
        assert {"--quiet", "-q", "--verbose", "-v"} <= names, (verb, leaf.name)


def test_shell_completion_script() -> None:
    # typer detects the shell from the parent process (`make test` runs pytest under sh, which it
    # does not support): ask from a bash that stays the parent (no exec), as a bash user would.
    cmd = f"{shlex.quote(sys.executable)} -m rgbdnav.cli --show-completion; exit $?"
    result = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "complete" in result.stdout and "COMP_WORDS" in result.stdout


def test_board_refuses_a_port_it_would_ignore_with_the_emulator() -> None:
    # With --emulator the argument names the emulator kind; a device path is not silently dropped.
    result = runner.invoke(app, ["board", "/dev/ttyUSB0", "--emulator"])
    assert result.exit_code == 1
    assert result.output.startswith("error: board 'emulator:/dev/ttyUSB0': unknown emulator")


def test_quiet_and_verbose_together_are_refused(tmp_path) -> None:
    result = runner.invoke(
        app, ["eval", str(tmp_path / "x"), "-r", str(tmp_path / "y"), "-q", "-v"]
    )
    assert result.exit_code == 1
    assert "give --verbose or --quiet, not both" in result.output


def test_a_bad_trajectory_format_is_refused_before_any_work(tmp_path) -> None:
    result = runner.invoke(
        app, ["map", str(tmp_path / "nope.clf"), "-o", str(tmp_path / "r"), "--format", "g2o"]
    )
    assert result.exit_code == 1
    assert "--format 'g2o': use one of tum, kitti, euroc" in result.output
