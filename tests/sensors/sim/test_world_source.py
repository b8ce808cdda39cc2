"""A world rendered on demand gives what its recording on disk gives, bit for bit."""

from __future__ import annotations

import multiprocessing as mp
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.recording import Recording
from sensors.recording_source import RecordingSource
from sensors.sim import world_source
from sensors.sim.simulator import simulate
from sensors.sim.world_source import open_world
from sensors.types import SensorError

REPO = Path(__file__).resolve().parents[3]
HOUSE = REPO / "scenes" / "house.yaml"
FRAMES = 6


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The house with a 1 m route: planning drives the whole route, so keep it short."""
    w = yaml.safe_load(HOUSE.read_text())
    w["route"] = [[2.5, 2.5]]
    path = tmp_path_factory.mktemp("world") / "house_short.yaml"
    path.write_text(yaml.safe_dump(w))
    return path


def _args() -> tuple[RobotConfig, CameraConfig, SimConfig]:
    return RobotConfig(), CameraConfig(), SimConfig()


def test_streamed_world_equals_its_recording_on_disk(tmp_path: Path, world: Path) -> None:
    simulate(world, tmp_path / "rec", *_args(), seed=3, frames=FRAMES)
    disk = RecordingSource(Recording.open(tmp_path / "rec"))
    live = open_world(world, *_args(), seed=3, frames=FRAMES, render_ahead=True)
    try:
        want, got = list(disk.frames()), list(live.frames())
        assert len(got) == len(want) == FRAMES
        for a, b in zip(want, got, strict=True):
            assert a.stamp_ns == b.stamp_ns and a.intrinsics == b.intrinsics
            assert a.rgb.dtype == b.rgb.dtype and np.array_equal(a.rgb, b.rgb)
            assert a.depth_m.dtype == b.depth_m.dtype and np.array_equal(a.depth_m, b.depth_m)
        # Random access (odometry's contact sheet) renders the same frame in this process.
        assert np.array_equal(live.recording.frame(4).depth_m, want[4].depth_m)
        assert np.array_equal(live.recording.frame(4).rgb, want[4].rgb)
        for name in ("wheels", "imu", "groundtruth", "gps"):
            a, b = getattr(disk, name)(), getattr(live, name)()
            assert (a is None) == (b is None), name
            if a is not None:
                for x, y in zip(a.__dict__.values(), b.__dict__.values(), strict=True):
                    assert np.array_equal(x, y), name
        assert live.recording.scene == disk.recording.scene
    finally:
        live.close()


def test_a_renderer_started_ahead_and_never_read_ends_with_its_source(world: Path) -> None:
    src = open_world(world, *_args(), seed=3, frames=2, render_ahead=True)
    started = src.recording._started
    assert started is not None and started.proc.is_alive()
    src.close()
    assert not started.proc.is_alive() and src.recording._started is None


def test_a_daemonic_process_renders_in_itself(world: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = open_world(world, *_args(), seed=3, frames=2)
    first = list(src.frames())
    monkeypatch.setattr(mp.current_process(), "daemon", True)  # as in a Dask worker
    again = list(src.frames())
    pairs = list(zip(first, again, strict=True))
    assert all(np.array_equal(a.depth_m, b.depth_m) for a, b in pairs)
    assert all(np.array_equal(a.rgb, b.rgb) for a, b in pairs)


def test_a_renderer_that_fails_is_a_one_line_error(world: Path) -> None:
    src = open_world(world, *_args(), seed=3, frames=2)
    src.recording.plan.noise_seed = -1  # the child's renderer refuses its noise seed
    try:
        with pytest.raises(SensorError, match=r"rendering \S+ failed: ValueError"):
            list(src.frames())
    finally:
        src.close()


class _DiesInSpawn:
    """A renderer target that ends the spawned child while it unpickles its task: as a script
    without the main guard ends it (multiprocessing refuses to start the child's own
    renderer), before the renderer runs."""

    def __reduce__(self) -> tuple:
        return (sys.exit, (1,))

    def __call__(self, *args: object) -> None:
        raise AssertionError("never runs")


def test_a_renderer_that_dies_in_its_spawn_says_the_script_needs_the_main_guard(
    world: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    src = open_world(world, *_args(), seed=3, frames=2)
    monkeypatch.setattr(world_source, "_render_worker", _DiesInSpawn())
    try:
        with pytest.raises(SensorError, match=r"exit code 1\) before it started: a script"):
            list(src.frames())
    finally:
        src.close()


def test_a_spawned_process_importing_its_script_starts_no_renderer(
    world: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(mp.current_process(), "_inheriting", True, raising=False)
    with pytest.raises(SensorError, match="must keep its code under `if __name__"):
        open_world(world, *_args(), seed=3, frames=2, render_ahead=True)
