"""FreenectSource without a Kinect: a fake ``freenect`` module stands in for libfreenect's binding
(sync API and tilt state), and ``rgbdnav info freenect://`` is run against the real library when
it is installed (no Kinect on a CI machine: one clean error line)."""

from __future__ import annotations

import importlib
import json
import math
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from sensors.freenect_source import FreenectSource, parse_target, pitch_from_tilt
from sensors.source import SourceOptions, open_source
from sensors.types import SensorError

runner = CliRunner()
H, W = 480, 640  # [px]


def _fake_freenect(
    devices: int, frames: int, tilt_degs: float = 10.0, period_s: float = 0.0
) -> types.ModuleType:
    fn = types.ModuleType("freenect")
    fn.VIDEO_RGB, fn.DEPTH_REGISTERED = 0, 4
    state = {"video": 0, "stopped": False}
    fn.init = lambda: object()
    fn.num_devices = lambda ctx: devices
    fn.open_device = lambda ctx, index: object()
    fn.close_device = lambda dev: None
    fn.shutdown = lambda ctx: None
    fn.update_tilt_state = lambda dev: 0
    fn.get_tilt_state = lambda dev: "state"
    fn.get_tilt_degs = lambda st: tilt_degs

    def video(index: int, fmt: int):
        assert fmt == fn.VIDEO_RGB
        if state["video"] >= frames:
            return None
        state["video"] += 1
        time.sleep(period_s)  # a Kinect's 30 Hz
        return np.full((H, W, 3), state["video"], np.uint8), 123

    def depth(index: int, fmt: int):
        assert fmt == fn.DEPTH_REGISTERED  # depth aligned to the colour camera, in mm
        return np.full((H, W), 1500, np.uint16), 456

    fn.sync_get_video, fn.sync_get_depth = video, depth
    fn.sync_stop = lambda: state.update(stopped=True)
    fn.state = state
    return fn


def test_targets() -> None:
    assert parse_target("freenect://") == 0 and parse_target("freenect://1") == 1
    assert parse_target("openni://") is None
    with pytest.raises(SensorError, match="freenect://INDEX"):
        parse_target("freenect://kinect")


def test_frames_are_registered_mm_depth_with_the_accelerometer_pitch(monkeypatch) -> None:
    fake = _fake_freenect(devices=1, frames=3, tilt_degs=-12.0)
    monkeypatch.setitem(sys.modules, "freenect", fake)
    clock = iter(range(1_000, 10_000, 1_000))
    src = FreenectSource.open(0, clock=lambda: next(clock))
    assert src.camera_pitch == pytest.approx(math.radians(12.0))  # tilted 12 deg down
    assert "camera pitch 12.0 deg from the accelerometer" in src.describe()
    with pytest.raises(SensorError, match="stopped sending frames"):
        frames = []
        for frame in src.frames():
            frames.append(frame)
    assert [f.stamp_ns for f in frames] == [1_000, 2_000, 3_000]
    assert frames[2].rgb[0, 0, 0] == 3 and frames[0].depth_m[0, 0] == pytest.approx(1.5)
    assert frames[0].intrinsics.fx == 525.0  # the Kinect v1 colour camera (camera config)
    src.close()
    assert fake.state["stopped"]


def test_live_run_stamps_on_the_monotonic_clock(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "freenect", _fake_freenect(devices=1, frames=1))
    import time

    src = open_source("freenect://", SourceOptions(realtime=True))
    stamp = next(iter(src.frames())).stamp_ns
    assert abs(stamp - time.monotonic_ns()) < 1e9
    src.close()


@pytest.mark.parametrize(
    ("devices", "uri", "match"),
    [(0, "freenect://", "no Kinect v1 found"), (1, "freenect://1", r"no Kinect 1 \(1 found\)")],
)
def test_no_kinect_names_the_udev_rules(monkeypatch, devices: int, uri: str, match: str) -> None:
    monkeypatch.setitem(sys.modules, "freenect", _fake_freenect(devices=devices, frames=0))
    with pytest.raises(SensorError, match=match) as err:
        open_source(uri)
    assert "60-libfreenect0.5.rules" in str(err.value)


def test_without_the_binding_the_error_says_what_to_install(monkeypatch) -> None:
    real = importlib.import_module

    def fake(name: str, *args):
        if name == "freenect":
            raise ImportError("libfreenect_sync.so.0.5: cannot open shared object file")
        return real(name, *args)

    monkeypatch.setattr(importlib, "import_module", fake)
    with pytest.raises(SensorError, match=r"apt-get install libfreenect-dev && pip install"):
        open_source("freenect://")


def test_info_without_a_kinect_is_one_error_line() -> None:
    res = runner.invoke(app, ["info", "freenect://"])
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert res.output.count("error:") == 1
    assert "no Kinect v1 found" in res.output or "libfreenect" in res.output


def test_pitch_sign() -> None:
    assert pitch_from_tilt(15.0) == pytest.approx(-math.radians(15.0))  # tilted up: negative


def test_info_says_whether_the_accelerometer_pitch_or_the_config_wins(monkeypatch) -> None:
    """As a bag's /tf_static mount: the accelerometer's pitch unless the config sets
    robot.camera_pitch (another camera key, e.g. the height, does not stop it)."""
    monkeypatch.setitem(
        sys.modules, "freenect", _fake_freenect(devices=1, frames=0, tilt_degs=-12.0)
    )
    cases = [
        ([], "from accelerometer (Kinect tilt -12.0 deg): camera_pitch=0.2094"),
        (["robot.camera_height=0.3"], "from accelerometer (Kinect tilt -12.0 deg)"),
        (
            ["robot.camera_pitch=0.05"],
            "from config (accelerometer Kinect tilt -12.0 deg not used: the config sets "
            "robot.camera_pitch)",
        ),
    ]
    for sets, want in cases:
        res = runner.invoke(app, ["info", "freenect://", *[a for x in sets for a in ("--set", x)]])
        assert res.exit_code == 0, res.output
        assert f"extrinsics  {want}" in res.output, res.output


@pytest.mark.realtime  # a live run / playback against the wall clock
def test_live_takes_the_accelerometer_pitch_unless_the_config_sets_it(
    monkeypatch, tmp_path
) -> None:
    import yaml

    for sets, source, pitch in (
        ([], "accelerometer", math.radians(12.0)),
        (["robot.camera_pitch=0.05"], "config", 0.05),
    ):
        fake = _fake_freenect(devices=1, frames=10**6, tilt_degs=-12.0, period_s=1 / 30)
        monkeypatch.setitem(sys.modules, "freenect", fake)
        out = tmp_path / source
        args = ["live", "--camera", "freenect://", "--board", "none", "--out", str(out)]
        args += ["--duration", "1", "-q", *[a for x in sets for a in ("--set", x)]]
        res = runner.invoke(app, args)
        assert res.exit_code == 0, res.output
        summary = json.loads((out / "summary.json").read_text())
        assert summary["extrinsics"]["source"] == source, summary["extrinsics"]
        assert summary["counts"]["frames_received"] > 0 and fake.state["stopped"]
        robot = yaml.safe_load(Path(out / "config.yaml").read_text())["robot"]
        assert robot["camera_pitch"] == pytest.approx(pitch, abs=1e-6)  # what the run used
