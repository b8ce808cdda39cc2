"""RealSense SDK recordings written with librealsense's software device (no camera): a simulated
route rendered with non-default intrinsics and depth units is recorded as ``rs.recorder`` would
record a D435, then read back offline (``rgbdnav odometry`` / ``map``) and as a live camera."""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.realsense_source import (
    FramePairing,
    RealSenseSource,
    RealSenseTarget,
    load_recording,
    parse_target,
    start_sensors,
    write_sdk_recording,
)
from sensors.source import ImuStream, SourceOptions, open_source
from sensors.types import CameraIntrinsics, RgbdFrame, SensorError

pytest.importorskip("pyrealsense2")

REPO = Path(__file__).resolve().parents[2]
CAMERA = CameraConfig(fx=570.0, fy=568.0, cx=322.5, cy=236.5)  # not the Kinect defaults (525)
DEPTH_UNITS = 0.0005  # [m/count] not the D400 default (1 mm)
N_FRAMES = 45
STEP_M, TURN_RAD = 0.015, 0.004  # per frame: forward along the start heading, and yaw
PERIOD_NS = 33_333_333  # [ns] 30 Hz
START_NS = 5_000_000_000  # [ns] device clock of the first frame
GYRO_PERIOD_NS = 5_000_000  # [ns] 200 Hz
YAW_RATE = TURN_RAD * 1e9 / PERIOD_NS  # [rad/s]
runner = CliRunner()


def _route_frames() -> list[RgbdFrame]:
    from sensors.sim.render import KinectRenderer
    from sensors.sim.world import load_world

    world = load_world(REPO / "scenes" / "house.yaml")
    renderer = KinectRenderer(world, CAMERA, RobotConfig(), SimConfig())
    rng = np.random.default_rng(0)
    x0, y0, yaw0 = world.start
    frames = []
    for i in range(N_FRAMES):
        x, y = x0 + i * STEP_M * math.cos(yaw0), y0 + i * STEP_M * math.sin(yaw0)
        rgb, depth = renderer.render(x, y, yaw0 + i * TURN_RAD, rng)
        frames.append(RgbdFrame(START_NS + i * PERIOD_NS, rgb, depth, renderer.intrinsics))
    return frames  # rendered first, so the recording's capture times keep the 30 Hz spacing


def _route_recording(shared: Path, request: pytest.FixtureRequest, with_gyro: bool = True) -> Path:
    """The route's SDK recording, as a D435i (``with_gyro``) or a D435 records it, in
    ``shared`` (both passes of `make test` see it), keyed by the route's parameters: written
    from ``route_frames`` (rendered only then) if not there yet."""
    params = (N_FRAMES, CAMERA, DEPTH_UNITS, STEP_M, TURN_RAD, PERIOD_NS, START_NS, GYRO_PERIOD_NS)
    key = hashlib.sha256(repr((params, with_gyro)).encode()).hexdigest()[:12]
    path = shared / f"realsense-route-{key}" / "route.db3"
    if path.exists():
        return path
    frames = request.getfixturevalue("route_frames")
    part = Path(tempfile.mkdtemp(prefix=f"{path.parent.name}.", dir=shared))
    gyro = None
    if with_gyro:  # a D435i's gyro, turning left
        stamps = np.arange(START_NS, frames[-1].stamp_ns, GYRO_PERIOD_NS, dtype=np.int64)
        gyro = ImuStream(stamps, np.full(len(stamps), YAW_RATE))
    n = write_sdk_recording(part / path.name, frames, depth_units=DEPTH_UNITS, gyro=gyro, pace=True)
    assert n == N_FRAMES
    part.rename(path.parent)  # whole or absent: a pass cut short leaves no half recording
    return path


@pytest.fixture(scope="module")
def route_frames() -> list[RgbdFrame]:
    return _route_frames()


@pytest.fixture(scope="module")
def route(
    passes_dir: Path, route_frames: list[RgbdFrame], request: pytest.FixtureRequest
) -> tuple[Path, list[RgbdFrame]]:
    """The route's recording and the frames it was written from (the non-realtime tests). The
    realtime pass's recordings are written here too, from the same frames: that pass, run
    alone after this one, then renders nothing."""
    _route_recording(passes_dir, request, with_gyro=False)
    return _route_recording(passes_dir, request), route_frames


@pytest.fixture(scope="module")
def route_recording(passes_dir: Path, request: pytest.FixtureRequest) -> Path:
    """The route's recording alone (the realtime tests): the first pass's, not made again."""
    return _route_recording(passes_dir, request)


@pytest.fixture(scope="module")
def route_without_gyro(passes_dir: Path, request: pytest.FixtureRequest) -> Path:
    """The same frames as a D435 (no IMU) records them."""
    return _route_recording(passes_dir, request, with_gyro=False)


def test_the_realtime_pass_finds_the_recordings_this_pass_made(
    route, passes_dir: Path, request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`make test`'s realtime pass renders no route: the recordings it reads are made here."""
    monkeypatch.setattr(request, "getfixturevalue", lambda name: pytest.fail("rendered again"))
    assert _route_recording(passes_dir, request) == route[0]
    plain = _route_recording(passes_dir, request, with_gyro=False)
    assert plain != route[0] and plain.is_file()


def test_targets_name_a_camera_a_serial_or_a_recording() -> None:
    assert parse_target("realsense://") == RealSenseTarget()
    assert parse_target("realsense://123456789012") == RealSenseTarget(serial="123456789012")
    assert parse_target("realsense:///data/run.db3") == RealSenseTarget(file=Path("/data/run.db3"))
    assert parse_target("realsense://run.bag") == RealSenseTarget(file=Path("run.bag"))
    assert parse_target("openni://") is None and parse_target("run.db3") is None


def test_a_recording_reads_its_own_intrinsics_depth_units_and_frames(route) -> None:
    path, truth = route
    with open_source(f"realsense://{path}") as src:
        k = src.intrinsics()
        assert (k.fx, k.fy, k.cx, k.cy) == (570.0, 568.0, 322.5, 236.5)
        assert src.depth_units == pytest.approx(DEPTH_UNITS)
        text = src.describe()
        assert "from the recording's colour stream" in text
        assert "depth units 0.5 mm from the recording's depth_units option" in text
        frames = list(src.frames())
        skipped = dict(src.skipped)
    # The recorded clock, offline: every frame, the first too (played not in real time from its
    # start, and colour and depth paired across the syncer's framesets).
    recorded = {f.stamp_ns: f for f in truth}
    assert [f.stamp_ns for f in frames] == list(recorded) and skipped == {}, skipped
    for got in (frames[0], frames[-1]):
        want = recorded[got.stamp_ns]
        np.testing.assert_array_equal(got.rgb, want.rgb)
        valid = np.isfinite(want.depth_m) & (want.depth_m > 0) & (want.depth_m < 30.0)
        err = np.abs(got.depth_m[valid] - want.depth_m[valid])
        assert np.median(err) <= DEPTH_UNITS  # quantised to the recording's units, not mm


def test_a_playback_loses_no_frame_however_late_its_sensors_start(route) -> None:
    """A playback reads from its first sensor's start and drops what a sensor not started yet
    is sent: a reader descheduled between two starts (a loaded machine) lost the first colour
    frames. Started paused and rewound, each sensor gets every frame, whichever starts late."""
    import pyrealsense2 as rs

    path, truth = route

    class Late:  # a sensor whose start returns 0.3 s late, as on a starved machine
        def __init__(self, sensor) -> None:
            self.sensor = sensor

        def start(self, callback) -> None:
            self.sensor.start(callback)
            time.sleep(0.3)

    device = load_recording(rs, path)
    playback, got = device.as_playback(), {}
    sensors = [s for s in device.query_sensors() if not s.is_motion_sensor()]
    for sensor in sensors:
        sensor.open(sensor.get_stream_profiles()[0])
    try:
        start_sensors(
            playback,
            [
                (
                    Late(s),
                    lambda f: got.setdefault(f.get_profile().stream_name(), []).append(
                        f.get_timestamp()
                    ),
                )
                for s in sensors
            ],
        )
        deadline = time.monotonic() + 60.0
        while playback.current_status() == rs.playback_status.playing:
            assert time.monotonic() < deadline, "playback did not end"
            time.sleep(0.05)
    finally:
        for sensor in sensors:
            sensor.stop()
            sensor.close()
    want = [f.stamp_ns / 1e6 for f in truth]
    assert sorted(got) == ["Color", "Depth"]
    for stream, stamps in got.items():
        assert stamps == pytest.approx(want, abs=1e-3), stream


def test_a_source_left_open_does_not_crash_the_interpreter_at_exit(route) -> None:
    """A failed test's or a Ctrl-C'd run's source still playing at exit: librealsense's threads
    called into the dying interpreter ("FATAL: exception not rethrown", SIGABRT or SIGSEGV)."""
    path, _ = route
    script = (
        "from sensors.realsense_source import RealSenseSource\n"
        f"src = RealSenseSource.open('realsense://{path}', realtime=True)\n"
        "next(iter(src.frames()))\n"
        "print('left open', flush=True)\n"
    )
    res = subprocess.run(
        [sys.executable, "-X", "faulthandler", "-c", script],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0 and "left open" in res.stdout, res.stderr[-2000:]
    assert "Fatal" not in res.stderr, res.stderr[-2000:]


def test_colour_and_depth_pair_by_stamp_whichever_comes_first() -> None:
    class F:  # a librealsense frame: its stamp [ms]
        def __init__(self, ms: float) -> None:
            self.ms = ms

        def get_timestamp(self) -> float:
            return self.ms

    pairing = FramePairing(max_gap_ns=20_000_000)
    c0, d0, c1, c2, d2, d3, c3 = (F(t) for t in (0.0, 0.5, 33.3, 66.7, 66.7, 100.0, 100.2))
    assert pairing.add(c0, None) is None  # depth 0 comes after, alone
    assert pairing.add(None, d0) == (c0, d0)
    assert pairing.add(c1, None) is None  # depth 1 never comes
    assert pairing.add(c2, d2) == (c2, d2) and pairing.take_skips() == {"unpaired_color": 1}
    assert pairing.add(None, d3) is None  # depth first, its colour after
    assert pairing.add(c3, None) == (c3, d3) and pairing.take_skips() == {}


def test_a_recordings_gyro_is_the_imu_yaw_rate(route) -> None:
    path, truth = route
    with open_source(f"realsense://{path}") as src:
        imu = src.imu()
    assert imu is not None and len(imu.stamps_ns) >= 0.9 * (N_FRAMES - 1) * PERIOD_NS / 5e6
    assert imu.stamps_ns[0] == START_NS and np.all(np.diff(imu.stamps_ns) == GYRO_PERIOD_NS)
    np.testing.assert_allclose(imu.gyro_z, YAW_RATE, rtol=1e-6)  # -gyro_y: yaw about "up"


def test_a_recording_reads_its_depth_to_colour_extrinsics(tmp_path: Path) -> None:
    intr = CameraIntrinsics(640, 480, 600.0, 601.0, 320.5, 240.5)
    frames = [
        RgbdFrame(
            i * PERIOD_NS,
            np.full((480, 640, 3), 9 * i, np.uint8),
            np.full((480, 640), 2.0, np.float32),
            intr,
        )
        for i in range(3)
    ]
    path = tmp_path / "ex.db3"
    write_sdk_recording(path, frames, depth_to_colour_m=(-0.015, 0.0, 0.0))
    with RealSenseSource.open(f"realsense://{path}") as src:
        rotation, translation = src.extrinsics
        assert translation == pytest.approx((-0.015, 0.0, 0.0))
        assert rotation == pytest.approx((1, 0, 0, 0, 1, 0, 0, 0, 1))
        assert "translation (-15.0, +0.0, +0.0) mm" in src.describe().replace("-0.0", "+0.0")


def test_odometry_and_map_of_a_recording_follow_the_route(route, tmp_path: Path) -> None:
    path, _ = route
    out = tmp_path / "odo"
    res = runner.invoke(
        app, ["odometry", f"realsense://{path}", "-o", str(out), "-q", "--force-3dof"]
    )
    assert res.exit_code == 0, res.output
    last = np.loadtxt(out / "vo.tum")[-1]
    travelled = (N_FRAMES - 1) * STEP_M
    assert math.hypot(last[1], last[2]) == pytest.approx(travelled, rel=0.1)
    yaw = 2.0 * math.atan2(last[6], last[7])
    assert yaw == pytest.approx((N_FRAMES - 1) * TURN_RAD, abs=0.03)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == N_FRAMES and "fx=570.0" in summary["source_kind"]
    assert summary["ekf"]["stats"]["sensors"]["imu0"]["fused"] > 0, summary["ekf"]  # the gyro
    res = runner.invoke(
        app, ["map", f"realsense://{path}", "-o", str(tmp_path / "map"), "-q", "--force-3dof"]
    )
    assert res.exit_code == 0, res.output
    assert "map bundle" in res.output and (tmp_path / "map" / "summary.json").exists()


@pytest.mark.realtime  # a live run / playback against the wall clock
def test_a_recording_played_as_a_camera_keeps_its_timing(route_recording: Path) -> None:
    path = route_recording
    t0 = time.monotonic()
    with open_source(f"realsense://{path}", SourceOptions(realtime=True)) as src:
        arrivals, stamps = [], []
        for frame in src.frames():
            arrivals.append(time.monotonic_ns())
            stamps.append(frame.stamp_ns)
    wall = time.monotonic() - t0
    assert len(stamps) >= N_FRAMES // 2  # a loaded machine may drop frames, as a camera would
    recorded = {k * PERIOD_NS for k in range(N_FRAMES)}
    assert all(s - stamps[0] in recorded for s in stamps)  # spacing kept: the device clock
    assert abs(arrivals[0] - stamps[0]) < 0.2e9  # stamped on the live run's clock (monotonic)
    assert wall >= 0.9 * (N_FRAMES - 1) * PERIOD_NS / 1e9  # paced in real time


def _live(path: Path, out: Path) -> dict:
    """``rgbdnav live`` for 3 s on the recording ``path`` played as the camera (no board); its
    summary."""
    res = runner.invoke(
        app,
        [
            "live",
            "--camera",
            f"realsense://{path}",
            "--board",
            "none",
            "--out",
            str(out),
            "--duration",
            "3",
            "-q",
        ],
    )
    assert res.exit_code == 0, res.output
    return json.loads((out / "summary.json").read_text())


@pytest.fixture(scope="module")
def live_run(route_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`_live` on the route's recording (with its gyro): the run's folder, read by two tests."""
    out = tmp_path_factory.mktemp("rs_live") / "gyro"
    _live(route_recording, out)
    return out


@pytest.mark.realtime  # a live run / playback against the wall clock
def test_live_maps_from_a_recording_played_as_the_camera(live_run: Path) -> None:
    s = json.loads((live_run / "summary.json").read_text())
    assert s["errors"] == [] and s["counts"]["frames_processed"] >= 5
    # Scans reach the mapper. This route's scans are nearly all empty (the camera sees little
    # at scan height within range: 0 and 2 returns in the offline map's keyframes), and the
    # map starts at the first scan with a return: the frames a loaded machine lets through may
    # all be skipped before it.
    counts = s["counts"]
    assert counts.get("scans_mapped", 0) + counts.get("scans_skipped_by_mapper", 0) >= 1
    # One clock with the host, not 1970. The stamp offset is fixed at the first frame, so a first
    # frame that arrived late (playback starting on a loaded machine) puts later frames a few ms
    # "before" their stamps.
    assert -100.0 < s["camera_to_host_ms_p50"] < 10_000.0
    assert s["ekf"]["sensors"]["imu0"]["fused"] > 0, s["ekf"]  # the D435i's gyro


def _yaw_error(out: Path) -> tuple[float, dict]:
    """Of the live run in ``out`` on a recording of the route: |odometry yaw - true yaw| at the
    last frame, and the summary. The route turns at YAW_RATE from its first frame (odom.tum's
    first row)."""
    summary = json.loads((out / "summary.json").read_text())
    odom = np.loadtxt(out / "odom.tum", ndmin=2)
    yaw = 2.0 * math.atan2(odom[-1, 6], odom[-1, 7])
    truth = YAW_RATE * (odom[-1, 0] - odom[0, 0])
    return abs(yaw - truth), {**summary, "odom_span_s": odom[-1, 0] - odom[0, 0]}


@pytest.mark.realtime  # a live run / playback against the wall clock
def test_live_fuses_the_streaming_gyro_and_turns_as_the_route(
    route_without_gyro: Path, live_run: Path, tmp_path: Path
) -> None:
    """The recording played as the camera goes through a live D435i's code: the motion sensor
    streams beside the pipeline (take_imu), stamped as the frames."""
    plain = route_without_gyro  # the same frames, as a D435 (no IMU) records them
    with_gyro, summary = _yaw_error(live_run)  # `_live` on the recording with the gyro
    _live(plain, tmp_path / "plain")
    without, summary_plain = _yaw_error(tmp_path / "plain")
    imu0, imu0_plain = (s["ekf"]["sensors"]["imu0"] for s in (summary, summary_plain))
    assert summary["camera_imu"] == "gyro 200 Hz as imu0"
    assert summary_plain["camera_imu"] == "no IMU (the recording has no gyro stream)"
    # Fed up to the last frame processed: every sample, as a camera delivers them (the recording
    # is paced by the reader; librealsense's real-time playback dropped a third to a half).
    span_s = summary["odom_span_s"]
    assert imu0["received"] >= span_s * 1e9 / GYRO_PERIOD_NS, (imu0, span_s)
    assert imu0["fused"] > 0 and imu0["dropped_late"] == 0, imu0
    assert imu0_plain["received"] == 0  # no gyro: the live run as before
    assert with_gyro < 0.03, with_gyro  # the gyro's yaw, on the frames' clock
    # No worse than VO alone beyond noise: on this short route both end within a few mrad
    # (CI: 2.4 vs 1.0 mrad), so the comparison allows 5 mrad.
    assert with_gyro <= without + 5e-3, (with_gyro, without)


@pytest.mark.parametrize(
    ("uri", "match"),
    [
        ("realsense://", "no RealSense camera found"),
        ("realsense://123", "no RealSense camera"),
        ("realsense:///no/such.db3", "no such RealSense recording"),
    ],
)
def test_no_camera_or_file_is_one_error_line(uri: str, match: str) -> None:
    res = runner.invoke(app, ["info", uri])
    assert res.exit_code == 1
    assert match in res.output and "Traceback" not in res.output
    assert res.output.count("error:") == 1


def test_without_pyrealsense2_the_error_says_what_to_install(monkeypatch) -> None:
    import importlib

    real = importlib.import_module

    def fake(name: str, *args):
        if name == "pyrealsense2":
            raise ImportError(name)
        return real(name, *args)

    monkeypatch.setattr(importlib, "import_module", fake)
    with pytest.raises(SensorError, match=r"pip install 'rgbdnav\[realsense\]'"):
        RealSenseSource.open("realsense://")


def test_the_recording_opened_as_a_plain_rosbag_reads_its_own_camera(route) -> None:
    """The SDK topics (/device_0/sensor_N/...) are found, camera_info is the colour stream's (not
    "ambiguous"), and 16-bit depth is scaled by the recording's depth units, not read as mm."""
    path, truth = route
    with open_source(path) as bag:
        assert bag.choices["camera_info"].topic == "/device_0/sensor_1/Color_0/image/camera_info"
        k = bag.intrinsics()
        assert (k.fx, k.fy, k.cx, k.cy) == (570.0, 568.0, 322.5, 236.5)
        text = bag.describe()
        assert "depth units 0.5 mm from /device_0/sensor_0/option/Depth_Units/value" in text
        assert "NOT registered" not in text  # same intrinsics, no offset: registered already
        first = next(iter(bag.frames()))

    def error(want: np.ndarray) -> float:
        valid = np.isfinite(want) & (want > 0) & (want < 30.0)
        return float(np.median(np.abs(first.depth_m[valid] - want[valid])))

    # The bag pairs by recorded capture time, which a loaded machine may skew by a frame.
    assert min(error(f.depth_m) for f in truth[:3]) <= DEPTH_UNITS


def test_a_rosbag_with_unregistered_sdk_depth_says_how_to_align_it(tmp_path: Path) -> None:
    intr = CameraIntrinsics(640, 480, 600.0, 601.0, 320.5, 240.5)
    frames = [
        RgbdFrame(
            i * PERIOD_NS,
            np.zeros((480, 640, 3), np.uint8),
            np.full((480, 640), 2.0, np.float32),
            intr,
        )
        for i in range(2)
    ]
    path = tmp_path / "offset.db3"
    write_sdk_recording(path, frames, depth_to_colour_m=(-0.015, 0.0, 0.0))
    with open_source(path) as bag:
        text = bag.describe()
    assert "translation (-15.0, +0.0, +0.0) mm from /device_0/sensor_1/Color_0/tf/ref_1" in text
    assert f"open it as realsense://{path}" in text


@pytest.mark.parametrize(
    ("camera", "match"),
    [("realsense://", "no RealSense camera found"), ("freenect://", "freenect")],
)
def test_live_without_the_camera_fails_in_one_line(tmp_path: Path, camera: str, match: str) -> None:
    res = runner.invoke(
        app,
        [
            "live",
            "--camera",
            camera,
            "--board",
            "none",
            "--duration",
            "3",
            "--out",
            str(tmp_path / "x"),
            "-q",
        ],
    )
    assert res.exit_code == 1, res.output
    assert match in res.output and "Traceback" not in res.output
