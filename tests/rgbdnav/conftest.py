"""Fixtures shared by the CLI tests, each made once per session and only read by the tests that
use it: a short house recording (it was rendered once per module that needed it), the map of
a real Radish log (it was mapped by two modules) and a short `live --record` run (two modules
each drove one)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app

HOUSE = Path(__file__).resolve().parents[2] / "scenes" / "house.yaml"
DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
OREBRO = DATA / "radish" / "orebro-corrected.log.gz"


@pytest.fixture(scope="session")
def house_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """45 frames (1.5 s) of the house route, seed 2: `rgbdnav simulate` as a user runs it."""
    out = tmp_path_factory.mktemp("rec") / "house"
    result = CliRunner().invoke(
        app, ["simulate", str(HOUSE), "--out", str(out), "--frames", "45", "--seed", "2", "--quiet"]
    )
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="session")
def orebro_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`rgbdnav map` of the Radish orebro log (../shared/data; skipped where it is absent): the
    run's folder. Copy its ``map`` before changing it."""
    if not OREBRO.is_file():
        pytest.skip("../shared/data/radish is absent")
    out = tmp_path_factory.mktemp("orebro") / "run"
    result = CliRunner().invoke(app, ["map", str(OREBRO), "--out", str(out), "-q"])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="session")
def live_recorded_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """5 s of `rgbdnav live` on the simulated house with ``--record``: the run's folder and its
    recording's. Export it with ``--out`` elsewhere; map the recording into another folder."""
    root = tmp_path_factory.mktemp("live_rec")
    out, rec = root / "live", root / "rec"
    args = ["live", "--out", str(out), "--sim-world", str(HOUSE), "-q", "--duration", "5"]
    result = CliRunner().invoke(app, [*args, "--record", str(rec)])
    assert result.exit_code == 0, result.output
    return out, rec
