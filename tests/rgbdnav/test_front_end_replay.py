"""One front end: a recording replayed through the live run's front-end thread and through the
offline path (:func:`slam.front_end.replay`, what `odometry`, `map` and `localize` drive) gives
the same poses."""

from __future__ import annotations

import queue
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rgbdnav.live.run import LiveOptions, LiveRun
from sensors.source import open_source
from sensors.types import NO_RGB, RgbdFrame, WheelTicks
from slam.config import EkfConfig
from slam.front_end import STAGE_FRAMES_AHEAD, FrontEnd, options_for, replay
from slam.geometry import wrap_angle


@pytest.fixture(scope="module")
def recording(house_recording: Path) -> Path:
    return house_recording  # tests/rgbdnav/conftest.py: rendered once per session


def test_live_front_end_thread_and_offline_replay_give_the_same_poses(
    recording: Path, tmp_path: Path
) -> None:
    # The live run as on the robot (its profiles, optical-flow VO, pose before VO), with a
    # board (not opened here) and the recording for a camera. VO is not skipped: the whole
    # recording is queued at once, which would otherwise look like a front end far behind.
    live = LiveRun(
        LiveOptions(
            out=tmp_path / "live",
            camera=str(recording),
            board="/dev/null",
            drive="idle",
            overrides=["live.frame_queue_size=100", "live.skip_vo_when_behind=false"],
        )
    )
    cfg = live.cfg
    with open_source(recording) as src:
        frames = list(src.frames())
        wheels = src.wheels()
        assert wheels is not None
        # 1. Live: every wheel reading arrives before the first frame is taken, so every VO
        #    motion reaches the EKF late and is fused by re-filtering its history.
        for t, left, right in zip(wheels.stamps_ns, wheels.left, wheels.right, strict=True):
            live.ticks_q.put(WheelTicks(int(t), int(left), int(right)))
        for f in frames:
            live.frame_q.put_nowait(f)
        live.frame_q.put(None)
        live._front_end_loop()
        live.odom_track.close()
        online = live.odom_track.load()
        assert isinstance(live.scan_q.get_nowait(), tuple)  # scans went to the mapper
        # 2. Offline: the source's streams in time order (the live robot has no gyro).
        opts = replace(
            options_for(src, camera_rate_hz=cfg.camera.rate),
            imu=False,
            pose_before_vo=cfg.live.pose_before_vo,
        )
        fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, opts)
        steps = [s for s in replay(src, fe) if s.odom is not None]
    offline = np.array(
        [
            (s.stamp_ns, s.odom.pose.x, s.odom.pose.y, s.odom.pose.yaw)
            for s in steps
            if s.odom is not None
        ]
    )
    assert len(online) == len(offline) >= 40
    np.testing.assert_array_equal(online[:, 0], offline[:, 0])
    assert np.abs(online[:, 1:3] - offline[:, 1:3]).max() <= 1e-3  # [m]
    assert np.abs(wrap_angle(online[:, 3] - offline[:, 3])).max() <= 1e-4  # [rad]
    # The poses moved with the robot (a front end stuck at the origin would also agree).
    assert np.hypot(*(offline[-1, 1:3] - offline[0, 1:3])) > 0.2
    assert live.ekf_stats.sensors["vo0"]["refiltered"] > 10  # the live path did re-filter
    with pytest.raises(queue.Empty):
        live.ticks_q.get_nowait()


def test_without_wheels_or_odom_the_vo_carries_the_ekf_of_a_ground_robot(recording: Path) -> None:
    from slam.front_end import odom_origin
    from slam.geometry import oplus
    from slam.metrics import drift_report

    cfg = LiveRun(
        LiveOptions(out=recording.parent / "unused", camera=str(recording), board="none")
    ).cfg
    with open_source(recording) as src:
        opts = replace(options_for(src, camera_rate_hz=cfg.camera.rate), wheels=False, imu=False)
        fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, opts)
        assert fe.inputs == ("vo0",) and fe.vo_carries
        steps = list(replay(src, fe))
        start = odom_origin(src)
        truth = src.groundtruth()
    assert truth is not None
    # The filter starts at the first frame (the odom origin), not at the first VO pair's end.
    assert all(s.odom is not None and s.scan is not None for s in steps)
    first = steps[0].odom
    assert first is not None and (first.pose.x, first.pose.y, first.pose.yaw) == (0.0, 0.0, 0.0)
    p = np.array(
        [
            oplus([start.x, start.y, start.yaw], [s.odom.pose.x, s.odom.pose.y, s.odom.pose.yaw])
            for s in steps
            if s.odom is not None
        ]
    )
    t = np.array([s.stamp_ns for s in steps], np.int64)
    rep = drift_report(
        t, (p[:, 0], p[:, 1], p[:, 2]), truth.stamps_ns, (truth.x, truth.y, truth.yaw)
    ).as_dict()
    assert rep["path_length_m"] > 0.3
    assert rep["final_position_error_m"] < 0.03 and rep["ate_rmse_m"] < 0.03


def test_live_frames_before_the_boards_first_motion_get_the_start_pose_and_are_mapped(
    recording: Path, tmp_path: Path
) -> None:
    # On a loaded machine the board's first readings were stamped after the first frames but
    # delivered before the front end took them: the filter started at the readings' motion,
    # every frame was older ("without odometry"), nothing was mapped and no map was saved.
    live = LiveRun(
        LiveOptions(
            out=tmp_path / "live",
            camera=str(recording),
            board="/dev/null",
            drive="idle",
            overrides=["live.frame_queue_size=100"],
        )
    )
    with open_source(recording) as src:
        frames = list(src.frames())[:5]
        wheels = src.wheels()
    assert wheels is not None
    late = np.flatnonzero(wheels.stamps_ns > frames[-1].stamp_ns)[:3]
    for k in late:
        live.ticks_q.put(WheelTicks(int(wheels.stamps_ns[k]), int(wheels.left[k]), int(k)))
    for f in frames:
        live.frame_q.put_nowait(f)
    live.frame_q.put(None)
    live._front_end_loop()
    live.odom_track.close()
    counts = live.counts.as_dict()
    assert counts.get("frames_without_filter_pose", 0) == 0
    assert counts["frames_processed"] == len(frames)
    assert isinstance(live.scan_q.get_nowait(), tuple)  # scans went to the mapper
    posed = live.odom_track.load()
    assert len(posed) == len(frames) and np.abs(posed[:, 1:]).max() < 0.05  # near the start


def test_features_and_scans_made_ahead_on_the_stage_thread_give_the_sequential_steps(
    recording: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import itertools
    import threading

    from rgbdnav.scan_stream import source_config
    from slam.visual_odometry import VisualOdometry

    where: list[str] = []
    extract = VisualOdometry.extract

    def spy(self: VisualOdometry, frame: object) -> object:
        where.append(threading.current_thread().name)
        return extract(self, frame)  # type: ignore[arg-type]

    monkeypatch.setattr(VisualOdometry, "extract", spy)
    runs = {}
    for ahead in (False, True):
        where.clear()
        with open_source(recording) as src:
            # `rgbdnav map`'s config with ORB on every frame (its default, every 2nd: below)
            cfg = source_config(src, [], ["vo.every_n_frames=1"])[2]
            fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, options_for(src))
            runs[ahead] = list(itertools.islice(replay(src, fe, ahead=ahead), 25))
        n = len(runs[ahead])
        on_main = where.count(threading.main_thread().name)
        # Sequential: every frame's features on the caller's thread; ahead: on the stage's,
        # and up to STAGE_FRAMES_AHEAD frames more (read ahead when the 25th was processed,
        # their work maybe still queued).
        if ahead:
            assert n <= len(where) <= n + STAGE_FRAMES_AHEAD and on_main == 0, where
        else:
            assert (len(where), on_main) == (n, n), where
    seq, pipe = runs[False], runs[True]
    assert len(seq) == len(pipe) == 25
    tracked = 0
    for a, b in zip(seq, pipe, strict=True):
        assert a.stamp_ns == b.stamp_ns and a.timed_out == b.timed_out
        assert (a.odom is None) == (b.odom is None)
        if a.odom is not None and b.odom is not None:
            assert a.odom.pose == b.odom.pose
            assert np.array_equal(a.odom.covariance, b.odom.covariance)
        assert a.scan is not None and b.scan is not None
        assert np.array_equal(a.scan.ranges, b.scan.ranges)
        assert a.vo is not None and b.vo is not None
        assert (a.vo.success, a.vo.reason, a.vo.inliers) == (
            b.vo.success,
            b.vo.reason,
            b.vo.inliers,
        )
        assert np.array_equal(a.vo.T_prev_curr, b.vo.T_prev_curr)
        tracked += a.vo.success
    assert tracked >= 22  # the comparison covers tracked frames, not failures


def test_vo_on_every_second_frame_with_wheels_spans_the_frame_between(
    recording: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from rgbdnav.scan_stream import source_config
    from slam.visual_odometry import VisualOdometry

    made: list[int] = []
    colour: list[bool] = []  # per frame given to the front end: it came with its colour
    extract, step = VisualOdometry.extract, FrontEnd.frame

    def spy(self: VisualOdometry, frame: RgbdFrame) -> object:
        made.append(frame.stamp_ns)
        assert frame.rgb is not NO_RGB
        return extract(self, frame)

    def seen(self: FrontEnd, frame: RgbdFrame, skip_vo: bool = False) -> object:
        colour.append(frame.rgb is not NO_RGB)
        return step(self, frame, skip_vo)

    monkeypatch.setattr(VisualOdometry, "extract", spy)
    monkeypatch.setattr(FrontEnd, "frame", seen)
    with open_source(recording) as src:
        # the RGB-D profile's vo.every_n_frames=2, from the first frame (the gyro-bias rule off)
        cfg = source_config(src, [], ["vo.stride_below_bias_sigma=0"])[2]
        fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, options_for(src))
        assert fe.vo_cfg.max_translation == pytest.approx(2 * cfg.vo.max_translation)
        steps = list(replay(src, fe))
        truth = src.groundtruth()
    assert truth is not None
    # VO (and the features made ahead for it) on frames 0, 2, 4, ... only.
    assert [s.vo is not None for s in steps] == [k % 2 == 0 for k in range(len(steps))]
    assert sorted(made) == [s.stamp_ns for s in steps[::2]]
    # The recording decoded no colour for the frames VO skips (and all for the others).
    assert colour == [k % 2 == 0 for k in range(len(steps))]
    assert fe.counts["vo_skipped_stride"] == len(steps) // 2
    assert sum(s.vo.success for s in steps if s.vo is not None) >= 20  # pairs 2 frames apart
    assert all(s.odom is not None and s.scan is not None for s in steps)  # a pose every frame
    p = np.array([[s.odom.pose.x, s.odom.pose.y] for s in steps if s.odom is not None])
    moved = np.hypot(*(p[-1] - p[0]))
    true = np.hypot(truth.x[-1] - truth.x[0], truth.y[-1] - truth.y[0])
    assert moved > 0.3 and abs(moved - true) < 0.03


def test_vo_strides_only_once_the_gyro_bias_is_known_to_the_configured_sigma(
    recording: Path,
) -> None:
    # vo.stride_below_bias_sigma: VO on every frame while the EKF's gyro-bias sigma is above
    # the limit (the heading it turns then turns the whole map), on every 2nd frame after.
    # 3 mrad/s takes ~20 s of driving: 1.5 s never strides; a limit the bias passes
    # mid-recording switches there, once.
    from rgbdnav.scan_stream import source_config
    from slam.ekf import GYRO_BIAS

    def run(limit: float) -> tuple[FrontEnd, list[bool], float]:
        with open_source(recording) as src:
            cfg = source_config(src, [], [f"vo.stride_below_bias_sigma={limit}"])[2]
            fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, options_for(src))
            vo = [s.vo is not None for s in replay(src, fe)]
        assert fe.ekf is not None and "imu0" in fe.inputs
        return fe, vo, float(np.sqrt(fe.ekf.P[GYRO_BIAS, GYRO_BIAS]))

    fe, vo, sigma = run(0.003)
    assert all(vo) and "vo_skipped_stride" not in fe.counts and sigma > 0.003
    limit = (sigma + float(np.sqrt(EkfConfig().imu0_gyro_bias_initial_variance))) / 2
    fe, vo, sigma = run(limit)
    k0 = fe.counts["vo_stride_from_frame"]
    assert 0 < k0 < len(vo) - 4 and sigma < limit
    assert vo == [k < k0 or k % 2 == 0 for k in range(len(vo))]
    assert fe.counts["vo_skipped_stride"] == sum(not v for v in vo) > 0


def test_live_frames_whose_vo_is_skipped_get_the_wheels_pose_and_go_to_the_mapper(
    recording: Path, tmp_path: Path
) -> None:
    # A front end behind (every frame finds another waiting) skips VO on all but the first:
    # the wheels carry the EKF, and every frame's scan still reaches the mapper with a pose.
    live = LiveRun(
        LiveOptions(
            out=tmp_path / "live",
            camera=str(recording),
            board="/dev/null",
            drive="idle",
            overrides=["live.frame_queue_size=100", "live.mapper_rate=0"],
        )
    )
    assert live.cfg.live.skip_vo_when_behind
    with open_source(recording) as src:
        frames = list(src.frames())
        wheels, truth = src.wheels(), src.groundtruth()
    assert wheels is not None and truth is not None
    for t, left, right in zip(wheels.stamps_ns, wheels.left, wheels.right, strict=True):
        live.ticks_q.put(WheelTicks(int(t), int(left), int(right)))
    for f in frames:
        live.frame_q.put_nowait(f)
    live.frame_q.put(None)
    live._front_end_loop()
    live.odom_track.close()
    counts = live.counts.as_dict()
    assert counts["vo_skipped_behind"] == len(frames) - 1  # (the end marker waits too)
    assert counts["frames_processed"] == len(frames)
    assert counts.get("frames_without_filter_pose", 0) == 0
    mapped = []
    while (item := live.scan_q.get_nowait()) is not None:
        mapped.append(item)
    assert len(mapped) == len(frames)  # each with its scan and pose
    # The poses are the wheels': they follow the ground truth's path (start at the origin).
    p = live.odom_track.load()[:, 1:3]
    moved = np.hypot(*(p[-1] - p[0]))
    true = np.hypot(truth.x[-1] - truth.x[0], truth.y[-1] - truth.y[0])
    assert moved > 0.3 and abs(moved - true) < 0.03


def test_a_frame_that_fails_to_read_raises_after_the_frames_read_ahead_before_it() -> None:
    from sensors.config import RobotConfig
    from sensors.source import SourceBase
    from sensors.types import CameraIntrinsics, SensorError
    from slam.config import DepthToScanConfig, EkfConfig, VoConfig
    from slam.front_end import FrontEndOptions

    k = CameraIntrinsics(width=8, height=6, fx=10.0, fy=10.0, cx=3.5, cy=2.5)

    class Failing(SourceBase):
        path, skipped = "failing", {}

        def stream_stamps(self) -> dict[str, np.ndarray]:
            return {"rgb": np.arange(6) * 33_000_000}

        def frames(self):  # type: ignore[no-untyped-def]
            for j in range(5):
                yield RgbdFrame(j * 33_000_000, np.zeros((6, 8, 3), np.uint8), np.ones((6, 8)), k)
            raise SensorError("frame 5: broken")

    opts = FrontEndOptions(vo=False, scan=False, planar=False)
    fe = FrontEnd(RobotConfig(), EkfConfig(), VoConfig(), DepthToScanConfig(), opts)
    got: list[int] = []
    with pytest.raises(SensorError, match="frame 5: broken"):
        for step in replay(Failing(), fe):
            got.append(step.stamp_ns)
    assert got == [j * 33_000_000 for j in range(5)]  # every frame before it, then the error
