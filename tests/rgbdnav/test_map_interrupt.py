"""Ctrl-C or SIGTERM during `rgbdnav map`, `localize` or `odometry` keeps the work: the outputs of
what was read, saved whole."""

from __future__ import annotations

import json
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.stop_signals import StopSignals
from sensors.recording_source import RecordingSource
from slam.map_bundle import load_bundle

runner = CliRunner()

pytestmark = pytest.mark.skipif(
    threading.current_thread() is not threading.main_thread(),
    reason="signal handlers can only be set from the main thread",
)


def _signal_at_frame(monkeypatch: pytest.MonkeyPatch, at: dict[int, signal.Signals]) -> list[int]:
    """Send this process a signal when the reader reaches a frame (index -> signal)."""
    frames_for = RecordingSource.frames_for
    read: list[int] = []

    def reading(self: RecordingSource, rgb_wanted):  # type: ignore[no-untyped-def]
        for f in frames_for(self, rgb_wanted):
            if len(read) in at:
                os.kill(os.getpid(), at[len(read)])
            read.append(f.stamp_ns)
            yield f

    monkeypatch.setattr(RecordingSource, "frames_for", reading)
    return read


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_the_reading_and_saves_the_map_of_what_was_read(
    house_recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, sig: signal.Signals
) -> None:
    read = _signal_at_frame(monkeypatch, {20: sig})
    out = tmp_path / "map"
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    result = runner.invoke(app, ["map", str(house_recording), "--out", str(out), "-q"])
    assert result.exit_code == 128 + sig, result.output
    assert f"interrupted by {sig.name}" in result.output
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    summary = json.loads((out / "summary.json").read_text())
    stopped = summary["interrupted"]
    assert stopped["signal"] == sig.name and stopped["of"] == 45
    # The frame stage reads a few frames ahead of the mapper; none past those is read.
    assert 15 <= stopped["scans_read"] <= len(read) < 30
    assert summary["counts"]["scans"] == stopped["scans_read"]
    odom = np.loadtxt(out / "odom.tum", ndmin=2)
    assert len(odom) == stopped["scans_read"]  # the front end's own file is written too
    bundle = load_bundle(out / "map")
    assert len(bundle.keyframe_ids) > 0 and np.isfinite(bundle.keyframe_poses).all()


def test_a_second_signal_aborts_and_the_run_folder_says_so(
    house_recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from slam.mapper import Mapper

    _signal_at_frame(monkeypatch, {10: signal.SIGINT})
    finish = Mapper.finish

    def impatient(self: Mapper):  # type: ignore[no-untyped-def]
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C again while the map is being finished
        return finish(self)

    monkeypatch.setattr(Mapper, "finish", impatient)
    out = tmp_path / "map"
    before = signal.getsignal(signal.SIGINT)
    result = runner.invoke(app, ["map", str(house_recording), "--out", str(out), "-q"])
    assert result.exit_code == 130 and "Traceback" not in result.output
    assert signal.getsignal(signal.SIGINT) == before
    assert json.loads((out / "summary.json").read_text())["error"] == "interrupted"
    assert not (out / "map").exists()


def test_stop_signals_restores_the_handlers_and_names_the_first_signal() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with StopSignals("test") as stop:
        assert not stop.is_set() and stop.exit_code == 0
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.is_set() and stop.name == "SIGTERM" and stop.exit_code == 143
    assert signal.getsignal(signal.SIGTERM) == before


def test_localize_stopped_by_a_signal_keeps_the_poses_it_made(
    orebro_map: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from rgbdnav.runners import localize
    from tests.rgbdnav.conftest import OREBRO

    update = localize.Localizer.update
    calls = []

    def counted(self, scan, odom):  # type: ignore[no-untyped-def]
        calls.append(1)
        if len(calls) == 30:
            os.kill(os.getpid(), signal.SIGTERM)
        return update(self, scan, odom)

    monkeypatch.setattr(localize.Localizer, "update", counted)
    out = tmp_path / "loc"
    args = ["localize", str(OREBRO), "--map", str(orebro_map / "map"), "--out", str(out), "-q"]
    result = runner.invoke(app, args)
    assert result.exit_code == 143, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] == {"signal": "SIGTERM", "scans_read": 30, "of": 237}
    rows = (out / "localization.csv").read_text().splitlines()
    assert len(rows) == 31  # a header and the 30 scans read
    assert len(np.loadtxt(out / "trajectory.tum", ndmin=2)) > 20


def test_odometry_stopped_by_a_signal_writes_the_trajectories_of_what_was_read(
    house_recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    read = _signal_at_frame(monkeypatch, {20: signal.SIGINT})
    out = tmp_path / "odom"
    result = runner.invoke(app, ["odometry", str(house_recording), "--out", str(out), "-q"])
    assert result.exit_code == 130, result.output
    summary = json.loads((out / "summary.json").read_text())
    stopped = summary["interrupted"]
    assert stopped["signal"] == "SIGINT" and stopped["of"] == 45
    assert 15 <= stopped["frames_read"] == summary["frames"] <= len(read) < 30
    vo = np.loadtxt(out / "vo.tum", ndmin=2)
    fused = np.loadtxt(out / "fused.tum", ndmin=2)
    assert len(vo) == len(fused) == stopped["frames_read"]
