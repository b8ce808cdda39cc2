"""open_source picks the adapter; every adapter meets the Source protocol."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.recording_source import RecordingSource
from sensors.sim.simulator import simulate
from sensors.source import Source, open_source
from sensors.types import SensorError

REPO = Path(__file__).resolve().parents[2]


def test_a_missing_path_is_named() -> None:
    with pytest.raises(SensorError, match="no/such/thing: no such file or folder"):
        open_source("no/such/thing")


def test_an_unknown_file_lists_what_can_be_read(tmp_path: Path) -> None:
    f = tmp_path / "notes.xyz"
    f.write_text("hello")
    with pytest.raises(
        SensorError, match="not a source rgbdnav can read .known: rgbdnav recording"
    ):
        open_source(f)


def test_a_recording_opens_as_a_source_with_all_its_streams(tmp_path: Path) -> None:
    simulate(
        REPO / "scenes" / "house.yaml",
        tmp_path / "r",
        RobotConfig(),
        CameraConfig(),
        SimConfig(),
        frames=3,
    )
    src = open_source(tmp_path / "r")
    assert isinstance(src, RecordingSource) and isinstance(src, Source)
    assert set(src.stream_stamps()) == {"rgb", "depth", "wheels", "imu", "groundtruth"}
    frames = list(src.frames())
    assert len(frames) == 3 and src.skipped == {}
    wheels, gt = src.wheels(), src.groundtruth()
    assert wheels is not None and gt is not None and gt.frame == "base_link"
    assert np.all(np.diff(wheels.stamps_ns) > 0)
    assert list(src.scans()) == [] and src.odometry() is None


def test_a_device_uri_reaches_the_openni_adapter_with_install_advice() -> None:
    # No OpenNI2 here (or no device): one clear error, never a traceback from file adapters.
    with pytest.raises(SensorError, match="(?i)openni"):
        open_source("openni://")


def test_an_unknown_uri_scheme_is_refused_by_name() -> None:
    with pytest.raises(SensorError, match="gopher://x: no adapter for this URI"):
        open_source("gopher://x")
