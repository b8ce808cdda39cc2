"""Fixtures shared by the CLI tests: a short house recording rendered once per session (it was
rendered once per module that needed it) and only read by the tests that use it."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app

HOUSE = Path(__file__).resolve().parents[2] / "scenes" / "house.yaml"


@pytest.fixture(scope="session")
def house_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """45 frames (1.5 s) of the house route, seed 2: `rgbdnav simulate` as a user runs it."""
    out = tmp_path_factory.mktemp("rec") / "house"
    result = CliRunner().invoke(
        app, ["simulate", str(HOUSE), "--out", str(out), "--frames", "45", "--seed", "2", "--quiet"]
    )
    assert result.exit_code == 0, result.output
    return out
