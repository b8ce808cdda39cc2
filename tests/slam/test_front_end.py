"""FrontEnd kernels of the inputs: wheel readings one at a time as the whole log at once, and
odometry messages (nav_msgs/Odometry) with a twist or with a pose only."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sensors.config import RobotConfig
from sensors.types import CameraIntrinsics, ImuSample, Pose2, RgbdFrame, WheelTicks
from slam.config import DepthToScanConfig, EkfConfig, VoConfig
from slam.diff_drive import WheelErrorModel, reject_encoder_glitches
from slam.ekf import PoseInput, TwistInput, fuse, wheel_twist_inputs
from slam.front_end import FrontEnd, FrontEndOptions, pose_only_odom0, vo_for_interval
from slam.geometry import between

ROBOT = RobotConfig()
INTR = CameraIntrinsics(4, 3, 5.0, 5.0, 2.0, 1.5)
DT_NS = 8_000_000  # [ns] encoder readings at 125 Hz


def _blank(stamp_ns: int) -> RgbdFrame:
    return RgbdFrame(stamp_ns, np.zeros((3, 4, 3), np.uint8), np.ones((3, 4), np.float32), INTR)


def _front_end(**kw: object) -> FrontEnd:
    opts = FrontEndOptions(vo=False, scan=False, **kw)  # type: ignore[arg-type]
    return FrontEnd(ROBOT, EkfConfig(), VoConfig(), DepthToScanConfig(), opts)


def test_wheel_readings_one_at_a_time_give_the_poses_of_the_whole_log_fused_at_once() -> None:
    rng = np.random.default_rng(4)
    n = 400
    stamps = np.cumsum(rng.integers(DT_NS // 2, 2 * DT_NS, n)).astype(np.int64)
    stamps[200:] += 300_000_000  # a reading 0.3 s late: spread over its span
    left = np.cumsum(rng.integers(0, 3, n))
    right = np.cumsum(rng.integers(0, 4, n))
    fe = _front_end(wheels=True)
    outs = stamps[10::37] + 1
    poses = []
    k = 0
    for t_out in outs:
        while k < n and stamps[k] <= t_out:
            fe.wheels(WheelTicks(int(stamps[k]), int(left[k]), int(right[k])))
            k += 1
        od = fe.frame(_blank(int(t_out))).odom
        assert od is not None
        poses.append((od.pose.x, od.pose.y, od.pose.yaw))
    ref = fuse(
        {
            "odom0": wheel_twist_inputs(
                stamps, left, right, ROBOT, WheelErrorModel.from_robot(ROBOT), max_interval_s=1 / 30
            )
        },
        fe.ekf_cfg,
        output_stamps_ns=outs,
    )
    got = np.array(poses)
    np.testing.assert_allclose(got[:, :2], np.column_stack([ref.x, ref.y]), atol=1e-9)
    np.testing.assert_allclose(got[:, 2], ref.yaw, atol=1e-9)
    assert np.hypot(*got[-1, :2]) > 0.5  # it drove
    assert not fe.wheels(WheelTicks(int(stamps[k - 1]), 0, 0))  # a repeated reading: refused
    assert fe.counts["wheel_readings_repeated"] == 1


def test_a_glitched_or_reset_encoder_reading_is_gated_online_as_the_offline_cleanup_does() -> None:
    # One reading a million ticks off and back (a spike), then the counters jumping and staying
    # (a board reset): the live path must not drive 300 km either (#16). The online gate must
    # release exactly the readings the batch cleanup keeps.
    rng = np.random.default_rng(7)
    n = 400
    stamps = np.cumsum(rng.integers(DT_NS // 2, 2 * DT_NS, n)).astype(np.int64)
    left = np.cumsum(rng.integers(0, 3, n))
    right = np.cumsum(rng.integers(0, 4, n))
    left[150] += 1_000_000  # spike
    left[300:] -= 40_000  # reset that stays
    right[300:] -= 55_000
    fe = _front_end(wheels=True)
    for k in range(n):
        fe.wheels(WheelTicks(int(stamps[k]), int(left[k]), int(right[k])))
    od = fe.frame(_blank(int(stamps[-1]) + 1)).odom
    assert od is not None
    assert fe.counts["wheel_readings_dropped_glitch"] == 1
    assert fe.counts["wheel_jumps_taken_as_no_motion"] == 1
    clean = reject_encoder_glitches(stamps, left, right, ROBOT)
    assert (clean.glitches_dropped, clean.jumps_zeroed) == (1, 1)
    ref = fuse(
        {
            "odom0": wheel_twist_inputs(
                clean.stamps_ns,
                clean.left,
                clean.right,
                ROBOT,
                WheelErrorModel.from_robot(ROBOT),
                max_interval_s=1 / 30,
            )
        },
        fe.ekf_cfg,
        output_stamps_ns=np.array([stamps[-1] + 1]),
    )
    got = [od.pose.x, od.pose.y, od.pose.yaw]
    np.testing.assert_allclose(got, [ref.x[0], ref.y[0], ref.yaw[0]], atol=1e-9)
    assert np.hypot(od.pose.x, od.pose.y) < 5.0  # the robot drove about a metre, not 300 km


@pytest.mark.parametrize("kind", ["twist", "pose"])
def test_odometry_messages_with_a_twist_or_only_a_pose_carry_the_filter_round_a_circle(
    kind: str,
) -> None:
    v, w = 0.2, 0.4  # [m/s], [rad/s]: a circle of radius 0.5 m
    fe = _front_end(odometry=kind)
    assert fe.inputs == ("odom0",)
    t = np.arange(1, 301) * 20_000_000  # [ns] 50 Hz for 6 s
    for s in t:
        a = w * s / 1e9
        if kind == "twist":
            fe.odometry(TwistInput(int(s), v, 0.0, w, np.diag([1e-4, 1e-4, 1e-4])))
        else:
            pose = Pose2(v / w * math.sin(a), v / w * (1 - math.cos(a)), a)
            fe.odometry(PoseInput(int(s), pose, np.diag([1e-4, 1e-4, 1e-4])))
    od = fe.frame(_blank(int(t[-1]))).odom
    assert od is not None

    def truth(s: int) -> Pose2:
        a = w * s / 1e9
        return Pose2(v / w * math.sin(a), v / w * (1 - math.cos(a)), a)

    # The filter starts at its first measurement: the first twist, or the first pose
    # difference (the second pose).
    want = between(truth(int(t[0] if kind == "twist" else t[1])), truth(int(t[-1])))
    assert math.hypot(od.pose.x - want.x, od.pose.y - want.y) < 0.01
    assert abs(math.remainder(od.pose.yaw - want.yaw, math.tau)) < 0.01


def test_a_pose_only_odom_is_differenced_into_the_velocities_the_config_asks_for() -> None:
    cfg = pose_only_odom0(EkfConfig())
    names = ("x", "y", "yaw")
    from slam.config import STATE_NAMES

    assert cfg.odom0_differential
    assert [cfg.odom0_config[STATE_NAMES.index(n)] for n in names] == [True, True, True]
    assert not any(cfg.odom0_config[STATE_NAMES.index(n)] for n in ("vx", "vy", "vyaw"))


def test_vo_sanity_limits_grow_for_frames_further_apart_than_the_camera_rate() -> None:
    vo = VoConfig()
    assert vo_for_interval(vo, 1 / 30, 30.0) == vo
    far = vo_for_interval(vo, 0.67, 30.0)
    assert far.max_translation == pytest.approx(vo.max_translation * 20.1)
    assert far.max_rotation == pytest.approx(math.pi)
    assert replace(far, max_translation=vo.max_translation, max_rotation=vo.max_rotation) == vo


def test_a_streaming_imu_is_fed_as_the_same_samples_read_whole() -> None:
    """MessageFeed.extend_imu (a live camera's gyro, arriving in bursts, some after the frame they
    precede) feeds fe.imu the same samples, in the same order, as a recorded stream read whole."""
    from types import SimpleNamespace

    from sensors.source import ImuStream
    from slam.front_end import MessageFeed

    rng = np.random.default_rng(7)
    stamps = np.arange(0, 2_000_000_000, 5_000_000, dtype=np.int64)
    rates = rng.normal(0.0, 0.1, len(stamps))
    frames = np.arange(0, 2_000_000_000, 33_333_333, dtype=np.int64)
    offset = 1_000_000_000  # [ns] device clock -> the frames' clock

    def fed(streaming: bool) -> list[tuple[int, float]]:
        got: list[tuple[int, float]] = []
        fe = SimpleNamespace(
            options=FrontEndOptions(vo=False, scan=False, wheels=False, imu=True),
            imu=lambda s: got.append((s.stamp_ns, s.gyro_z)),
        )
        whole = None if streaming else ImuStream(stamps, rates)
        src = SimpleNamespace(imu=lambda: whole)
        feed = MessageFeed(src, fe, offset, kinds=("imu",))  # type: ignore[arg-type]
        cut = np.sort(rng.integers(0, len(stamps), 40))  # bursts of any size
        for a, b in zip(np.r_[0, cut], np.r_[cut, len(stamps)], strict=True):
            if streaming:
                feed.extend_imu(ImuStream(stamps[a:b], rates[a:b]))
            if b < len(stamps):
                feed.until(int(stamps[b]) + offset - 20_000_000)  # a frame 20 ms behind
        for t in frames:
            feed.until(int(t) + offset)
        feed.until(2**62)
        return got

    whole, streamed = fed(False), fed(True)
    assert len(whole) == len(stamps) and streamed == whole
    assert [t for t, _ in streamed] == sorted(t for t, _ in streamed)


@pytest.mark.parametrize("window", [1.0, 0.0])
def test_a_robot_standing_at_start_up_learns_its_gyro_bias_and_keeps_its_heading(
    window: float,
) -> None:
    # Switched on and standing 3 s (encoder counts unchanged) with a gyro 0.01 rad/s off, then
    # driving slowly (a tick every 0.4 s). Standing, the mean gyro reading is the bias; without
    # that (window 0) the wheels' quantised zero twists leave the bias unknown and the standing
    # robot turns with the gyro: 0.029 rad in 3 s.
    from slam.ekf import GYRO_BIAS

    rng = np.random.default_rng(2)
    opts = FrontEndOptions(wheels=True, imu=True, vo=False, scan=False)
    cfg = replace(EkfConfig(), odom0_still_window=window)
    fe = FrontEnd(ROBOT, cfg, VoConfig(), DepthToScanConfig(), opts)
    bias, ticks, standing_yaw, standing_updates = 0.01, 0, math.nan, -1
    for k in range(500):  # 5 s at 100 Hz
        t = k * 10_000_000
        ticks += k >= 300 and k % 40 == 20  # from 3 s on
        fe.imu(ImuSample(t + 1, bias + 0.005 * float(rng.standard_normal())))
        if k % 2 == 0:
            fe.wheels(WheelTicks(t, ticks, ticks))
        if k == 299:
            od = fe.frame(_blank(t + 2)).odom
            assert od is not None
            standing_yaw = od.pose.yaw
            standing_updates = fe.counts["gyro_bias_still_updates"]
    assert fe.ekf is not None
    bias_error = abs(fe.ekf.x[GYRO_BIAS] - bias)
    if window == 0.0:
        assert bias_error > 5e-3 and abs(standing_yaw) > 0.02  # what the bias update fixes
        return
    assert bias_error < 1e-3 and abs(standing_yaw) < 2e-3  # [rad/s], [rad]
    # ticks 0.4 s apart are not standing: no bias update while it drives
    assert standing_updates > 10 and fe.counts["gyro_bias_still_updates"] == standing_updates


def test_vo_and_scan_prepared_before_the_first_frame_are_kept_or_rebuilt_for_its_camera() -> None:
    """A live run builds VO and depth -> scan before the camera's first frame (their set-up
    would otherwise delay it); the first frame keeps them if they are for its camera and has
    them rebuilt for its own intrinsics if not."""
    intr = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)

    def frame(stamp_ns: int) -> RgbdFrame:
        rgb = np.zeros((48, 64, 3), np.uint8)
        return RgbdFrame(stamp_ns, rgb, np.full((48, 64), 2.0, np.float32), intr)

    def front_end() -> FrontEnd:
        return FrontEnd(ROBOT, EkfConfig(), VoConfig(), DepthToScanConfig(), FrontEndOptions())

    same = front_end()
    same.prepare(intr)
    vo, d2s = same._vo, same._d2s
    assert vo is not None and d2s is not None
    same.frame(frame(0))
    assert same._vo is vo and same._d2s is d2s

    other = front_end()
    other.prepare(replace(intr, fx=90.0, fy=90.0))
    stale = other._vo
    other.frame(frame(0))
    assert other._vo is not stale and other._vo is not None
    assert other._d2s is not None and other._d2s.intrinsics == intr

    plain = front_end()  # never prepared: the first frame builds them, as before
    step, step_prepared = plain.frame(frame(0)), front_end()
    step_prepared.prepare(intr)
    again = step_prepared.frame(frame(0))
    assert (step.scan is None) == (again.scan is None)
    if step.scan is not None and again.scan is not None:
        np.testing.assert_array_equal(step.scan.ranges, again.scan.ranges)
