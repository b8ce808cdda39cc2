"""One front end for every caller: wheel ticks, odometry messages (``/odom``), IMU and RGB-D
frames in, per frame the ``odom -> base_link`` pose with its covariance, the depth scan and the
VO result out.

The offline commands (:func:`replay` over a :class:`~sensors.source.Source`) and the live run's
front-end thread (messages as they arrive) drive the same :class:`FrontEnd`, so an offline
figure vouches for the live path. Inputs are whatever the source has, in any subset:

* wheel ticks -> body twists (:func:`slam.ekf.wheel_twist_inputs`) as EKF sensor ``odom0``;
* odometry messages (nav_msgs/Odometry) as ``odom0`` when there are no wheels: the twist with
  its covariance as robot_localization fuses ``odom0``, or a pose-only stream differenced
  (``odom0_differential``); with wheels too, the wheels win (both usually count the same ticks);
* gyro z as ``imu0``; VO frame-pair motions as ``vo0`` (:func:`slam.ekf.spanning_motion_twists`).

With no wheels and no odometry messages the robot's VO carries the EKF (planar mode). Without
``planar`` (a handheld camera) there is no EKF and no scan: the VO's 6-DoF camera motions are
chained into camera poses (``FrontEndStep.camera_pose``).
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, replace

import numpy as np

from sensors.config import RobotConfig
from sensors.source import ImuStream, Source, SourceBase
from sensors.types import (
    NS_PER_S,
    CameraIntrinsics,
    ImuSample,
    LaserScan,
    Odometry2D,
    Pose2,
    RgbdFrame,
    WheelTicks,
)
from slam.config import STATE_NAMES, DepthToScanConfig, EkfConfig, VoConfig
from slam.depth_to_scan import DepthToScan, scan_frame_in_base
from slam.diff_drive import EncoderGate, WheelErrorModel
from slam.ekf import (
    GYRO_BIAS,
    WHEEL_VARIANCE_WINDOW_S,
    EkfError,
    GyroBiasInput,
    PlanarEkf,
    PoseInput,
    TwistInput,
    spanning_motion_twists,
    wheel_twist_inputs,
)
from slam.metrics import interpolate_poses
from slam.visual_odometry import Features, VisualOdometry, VoResult

log = logging.getLogger(__name__)

OdometryMessage = PoseInput | TwistInput
GAP_PERIODS = 1.5  # a VO pair longer than this many camera frame periods spans a lost frame
MIN_HISTORY_S = 1.0  # [s] EKF history for spans fused late (a gap of up to ~1 s)
STILL_PERIOD_NS = 100_000_000  # [ns] a still robot's gyro bias updates at most this often
# [s] Python's GIL switch interval while replay() runs the frame stage (default 5 ms): a stage
# thread back from a GIL-free OpenCV call waits up to this for the main thread to let go, many
# times a frame (docs/design/speed.md)
STAGE_SWITCH_INTERVAL_S = 0.0005
# Frames whose own work (features, scan) is queued on the stage thread beyond the one being
# processed. With VO on every 2nd frame the two threads' loads alternate (the stage's ORB falls
# on the frames where the main thread only fuses and maps, the main thread's matching on the
# others): one frame ahead, each waited for the other every frame (docs/design/speed.md).
STAGE_FRAMES_AHEAD = 3

_STAGE: list[ThreadPoolExecutor] = []  # the frame stage's thread (FrontEnd.prefetch), made once
if hasattr(os, "register_at_fork"):  # a forked child has no threads: it makes its own
    os.register_at_fork(after_in_child=_STAGE.clear)


def _stage() -> ThreadPoolExecutor:
    if not _STAGE:
        _STAGE.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-stage"))
    return _STAGE[0]


@dataclass(frozen=True)
class FrontEndOptions:
    """What a caller decides about the front end (the tunables are in the config sections)."""

    wheels: bool = False  # the source has wheel encoder readings
    odometry: str = ""  # odometry messages: "twist" (with or without pose), "pose" or "" (none)
    imu: bool = False  # the source has a gyro
    vo: bool = True  # run visual odometry on the frames
    scan: bool = True  # turn each frame's depth into a scan (planar mode only)
    planar: bool = True  # a ground robot; False: a handheld camera, 6-DoF VO poses, no EKF
    pose_before_vo: bool = False  # live: a frame's pose leaves before its VO is fused
    frame_interval_s: float = 0.0  # [s] median frame interval when longer than the camera's
    camera_rate_hz: float = 30.0  # [Hz] the rate VO's per-frame sanity limits are meant for


@dataclass(frozen=True, eq=False)
class FrontEndStep:
    """What the front end made of one RGB-D frame."""

    stamp_ns: int  # [ns] the frame's stamp
    odom: Odometry2D | None  # odom -> base_link at the frame, 3x3 covariance; None: no estimate
    timed_out: bool  # the pose is predicted only: no input for longer than ekf.sensor_timeout
    scan: LaserScan | None  # depth -> scan in its frame, FrontEnd.scan_in_base (planar, scans on)
    vo: VoResult | None  # None: VO off, or skipped on this frame
    camera_pose: np.ndarray | None  # (4, 4) handheld: camera in the first camera's optical frame
    vo_ms: float = math.nan  # [ms] VO time (incl. fusing its twist, and the features made ahead)
    scan_ms: float = math.nan  # [ms] depth -> scan time (made ahead or not)
    ekf_ms: float = math.nan  # [ms] the pose query


def vo_for_interval(vo: VoConfig, interval_s: float, rate_hz: float) -> VoConfig:
    """VO's per-frame sanity limits (``max_translation``, ``max_rotation``) are meant for frames
    at the camera's rate; frames further apart (a keyframe set, a thinned recording) may move
    that much further between them, so the limits grow with the interval (rotation up to pi)."""
    factor = interval_s * rate_hz
    if factor <= 1.0:
        return vo
    return replace(
        vo,
        max_translation=vo.max_translation * factor,
        max_rotation=min(vo.max_rotation * factor, math.pi),
    )


def pose_only_odom0(cfg: EkfConfig) -> EkfConfig:
    """``odom0`` for odometry messages that carry a pose but no twist: the pose differenced
    into the velocities the config asks for (robot_localization: ``odom0_differential`` with
    the x, y, yaw flags)."""
    flags = list(cfg.odom0_config)
    for pose_name, rate_name in (("x", "vx"), ("y", "vy"), ("yaw", "vyaw")):
        flags[STATE_NAMES.index(pose_name)] = flags[STATE_NAMES.index(rate_name)]
        flags[STATE_NAMES.index(rate_name)] = False
    return replace(cfg, odom0_config=tuple(flags), odom0_differential=True)


@dataclass(frozen=True, eq=False)
class _OwnWork:
    """What :meth:`FrontEnd.prefetch` made of a frame ahead, with the times it took."""

    features: Features | None
    features_ms: float
    scan: LaserScan | None
    scan_ms: float


class FrontEnd:
    """Feed messages in time order (live: as they arrive; late ones are re-filtered when
    ``ekf.smooth_lagged_data`` is on); :meth:`frame` gives the step of each RGB-D frame."""

    def __init__(
        self,
        robot: RobotConfig,
        ekf: EkfConfig,
        vo: VoConfig,
        depth_to_scan: DepthToScanConfig,
        options: FrontEndOptions,
    ) -> None:
        self.options = options
        self.robot = robot
        vo_given, vo = vo, vo_for_interval(vo, options.frame_interval_s, options.camera_rate_hz)
        self.vo_cfg = vo if options.planar else replace(vo, force_3dof=False)
        self.d2s_cfg = depth_to_scan
        # The scans' frame (depth_to_scan.output_frame) in base_link: a scan goes to the mapper,
        # the localiser and the costmap with the pose odom (+) scan_in_base (slam.depth_to_scan).
        scans = options.scan and options.planar
        self.scan_in_base = scan_frame_in_base(robot, depth_to_scan) if scans else np.zeros(3)
        if options.odometry == "pose" and not options.wheels:
            ekf = pose_only_odom0(ekf)
        # A reading or VO pair that came after a gap is fused spread over its span
        # (slam.ekf.interval_twists): its pieces are older than messages of other sensors in
        # that span, so the filter re-filters from its history rather than drop them.
        ekf = replace(
            ekf, smooth_lagged_data=True, history_length=max(ekf.history_length, MIN_HISTORY_S)
        )
        self.ekf_cfg = ekf
        self.ekf = PlanarEkf(ekf, ekf.imu0_angular_velocity_variance) if options.planar else None
        self.model = WheelErrorModel.from_robot(robot)
        # Which EKF sensors get messages: available, and selected by their <sensor>_config.
        self.inputs: tuple[str, ...] = ()
        if self.ekf is not None:
            odom0 = options.wheels or bool(options.odometry)
            wanted = {"odom0": odom0, "imu0": options.imu, "vo0": options.vo}
            self.inputs = tuple(
                sorted(n for n, on in wanted.items() if on and any(getattr(ekf, f"{n}_config")))
            )
        if self.vo_cfg.every_n_frames > 1 and self._wheels_carry:  # pairs n frames apart
            period = max(options.frame_interval_s, 1.0 / options.camera_rate_hz)
            span = period * self.vo_cfg.every_n_frames
            self.vo_cfg = replace(
                vo_for_interval(vo_given, span, options.camera_rate_hz),
                force_3dof=self.vo_cfg.force_3dof,
            )
        self.counts: Counter[str] = Counter()
        self._recent: deque[WheelTicks] = deque()
        self._gate = EncoderGate(robot)
        self._last_wheel_ns: int | None = None
        self._moved_ns: int | None = None  # the last reading whose counts changed (or the first)
        self._ever_moved = False  # counts changed since the first reading
        self._still_ns: int | None = None  # gyro samples up to here went into a bias update
        self._gyro: deque[tuple[int, float]] = deque()  # the last still window's gyro samples
        self._window_ns = int(WHEEL_VARIANCE_WINDOW_S * NS_PER_S)
        self._vo: VisualOdometry | None = None
        self._d2s: DepthToScan | None = None
        self._prepared_for: CameraIntrinsics | None = None  # the camera VO and the scan are for
        self._staged = False  # the first frame went through _stages
        self._vo_prev_ns: int | None = None  # the frame VO last ran on
        self._vo_skipped: list[int] = []  # frames VO skipped since then
        # prefetch: the frames whose own work runs ahead on the stage thread, and that work
        self._ahead: deque[tuple[RgbdFrame, Future[_OwnWork]]] = deque()
        self._n_frames = 0  # frames through frame() so far
        # vo.stride_below_bias_sigma reached (see _bias_learned); settled from the start when
        # that rule is off or has no gyro, so needs_rgb (which only reads it) strides at once
        rule = self.vo_cfg.stride_below_bias_sigma > 0 and self.ekf is not None
        self._bias_settled = not (rule and "imu0" in self.inputs)

    @property
    def vo_stats(self) -> dict[str, int]:
        """The VO's own counters (depth ICP fallbacks used / failed), empty before any frame."""
        return dict(self._vo.stats) if self._vo is not None else {}

    @property
    def _wheels_carry(self) -> bool:
        """Wheel encoders are in the filter: what ``vo.every_n_frames`` needs to skip VO. Not
        odometry messages: fused with ``/odom``, VO on every 2nd frame measured worse than on
        every frame, while the same frames with wheel ticks mapped alike (measurements:
        docs/design/speed.md, session 18)."""
        return self.options.wheels and "odom0" in self.inputs

    @property
    def vo_carries(self) -> bool:
        """VO is the filter's only motion input (no wheels, no odometry messages)."""
        return "vo0" in self.inputs and "odom0" not in self.inputs

    # 1. Messages other than frames.

    def wheels(self, t: WheelTicks) -> bool:
        """One encoder reading: the twist of the interval it ends, its variance from the travel
        over the last WHEEL_VARIANCE_WINDOW_S (as :func:`wheel_twist_inputs` over the whole
        log). False: a repeated or older reading, which says nothing new (counted)."""
        if self._last_wheel_ns is not None and t.stamp_ns <= self._last_wheel_ns:
            self.counts["wheel_readings_repeated"] += 1
            return False
        self._last_wheel_ns = t.stamp_ns
        released = self._gate.push(t)  # implausible jumps out (a suspect waits one reading)
        self.counts["wheel_readings_dropped_glitch"] = self._gate.glitches_dropped
        self.counts["wheel_jumps_taken_as_no_motion"] = self._gate.jumps_zeroed
        for reading in released:
            self._wheel_step(reading)
        return True

    def _wheel_step(self, t: WheelTicks) -> None:
        last = self._recent[-1] if self._recent else None
        if last is None or (t.left, t.right) != (last.left, last.right):
            self._ever_moved |= last is not None
            self._moved_ns = t.stamp_ns
        self._recent.append(t)
        while len(self._recent) > 2 and self._recent[1].stamp_ns <= t.stamp_ns - self._window_ns:
            self._recent.popleft()
        if self.ekf is not None and "odom0" in self.inputs and len(self._recent) >= 2:
            r = self._recent
            self.ekf.process_span(
                "odom0",
                wheel_twist_inputs(
                    np.array([x.stamp_ns for x in r]),
                    np.array([x.left for x in r]),
                    np.array([x.right for x in r]),
                    self.robot,
                    self.model,
                    vy_variance=self.ekf_cfg.odom0_vy_variance,
                    last_only=True,
                    max_interval_s=1.0 / self.ekf_cfg.frequency,
                ),
            )
            if "imu0" in self.inputs:
                self._still_gyro(t.stamp_ns)

    def _still_gyro(self, now_ns: int) -> None:
        """Counts unchanged for ``odom0_still_window``: the robot stood still in that window
        except, at most, its ends (from rest it needs about half the window to move one tick
        unseen), so the mean gyro reading over the middle is the gyro's bias, fused as a direct
        measurement of it (docs/design/gyro_bias.md) - the IMU drivers' start-up calibration,
        and a zero-velocity update's gyro half. Each sample is used once, every
        STILL_PERIOD_NS. A robot that has not moved yet (switched on and standing) also takes
        back the heading the unknown bias turned (``GyroBiasInput.moves_pose``)."""
        window = int(round(self.ekf_cfg.odom0_still_window * NS_PER_S))
        if window <= 0 or self._moved_ns is None or now_ns - self._moved_ns < window:
            return
        lo = self._moved_ns + window // 2
        if self._still_ns is not None:
            lo = max(lo, self._still_ns)
        hi = now_ns - window // 2
        if hi - lo < STILL_PERIOD_NS:
            return
        t = np.fromiter((s[0] for s in self._gyro), np.int64, len(self._gyro))
        g = np.fromiter((s[1] for s in self._gyro), np.float64, len(self._gyro))
        used = (t > lo) & (t <= hi)
        self._still_ns = hi
        if not used.any():
            return
        assert self.ekf is not None and self.ekf.t_ns is not None
        var = self.ekf_cfg.imu0_angular_velocity_variance / int(used.sum())
        stamp = max(now_ns, self.ekf.t_ns)  # now: the bias is constant over the window
        bias = GyroBiasInput(stamp, float(g[used].mean()), var, moves_pose=not self._ever_moved)
        self.ekf.process("imu0", bias)
        self.counts["gyro_bias_still_updates"] += 1

    def odometry(self, msg: OdometryMessage) -> None:
        """One odometry message (nav_msgs/Odometry twist, or pose when it has no twist)."""
        if self.ekf is not None and "odom0" in self.inputs and not self.options.wheels:
            self.ekf.process("odom0", msg)

    def imu(self, s: ImuSample) -> None:
        if self.ekf is not None and "imu0" in self.inputs:
            self.ekf.process("imu0", s)
            self._gyro.append((s.stamp_ns, s.gyro_z))
            keep = int(self.ekf_cfg.odom0_still_window * NS_PER_S)
            while self._gyro and self._gyro[0][0] < s.stamp_ns - keep:
                self._gyro.popleft()

    # 2. Frames.

    def prepare(self, intrinsics: CameraIntrinsics) -> None:
        """Build VO and depth -> scan for this camera now, before its first frame: a live run
        calls it before the camera starts, so their set-up (~0.45 s here, kiss-icp's import
        among it) does not land on the first frame and the frames queued behind it."""
        if self._vo is None and self.options.vo:
            self._vo = VisualOdometry(intrinsics, self.vo_cfg, self.robot)
        if self._d2s is None and self.options.scan and self.options.planar:
            self._d2s = DepthToScan(intrinsics, self.robot, self.d2s_cfg)
        self._prepared_for = intrinsics

    def _stages(self, frame: RgbdFrame) -> None:
        """VO and depth -> scan for the camera of the first frame seen (rebuilt if they were
        prepared for other intrinsics than that frame's)."""
        if self._staged:
            return
        self._staged = True
        if self._prepared_for is not None and self._prepared_for != frame.intrinsics:
            self._vo = self._d2s = None
        self.prepare(frame.intrinsics)

    def prefetch(self, frame: RgbdFrame) -> None:
        """Start the work of ``frame`` that depends on nothing but the frame (its ORB features,
        its depth scan) on the stage thread, to run while the frame before it goes through VO
        matching, the EKF and the mapper; the next :meth:`frame` of this very frame takes the
        results. Both are pure functions of the frame and the config, so the output is bit for
        bit the sequential one; ORB, OpenCV's resizes and numpy's large-array kernels release
        the GIL, so the two stages share the two cores (docs/design/speed.md)."""
        self._stages(frame)
        due = self._vo_due(self._n_frames + len(self._ahead))  # frames come in order
        feats = due and self._vo is not None and self._vo.features_every_frame
        if feats or self._d2s is not None:
            self._ahead.append((frame, _stage().submit(self._own_work, frame, feats)))

    def drop_ahead(self) -> None:
        """Cancel the work queued by :meth:`prefetch` for frames that will not be processed (a
        replay its consumer stopped early) and wait for the one already running, so no work of
        this front end is left on the shared stage thread."""
        while self._ahead:
            _, work = self._ahead.popleft()
            if not work.cancel():
                wait([work])

    def _own_work(self, frame: RgbdFrame, feats: bool) -> _OwnWork:
        t0 = time.perf_counter()
        f = self._vo.extract(frame) if feats and self._vo is not None else None
        t1 = time.perf_counter()
        scan = self._d2s.from_frame(frame).scan if self._d2s is not None else None
        return _OwnWork(f, 1e3 * (t1 - t0), scan, 1e3 * (time.perf_counter() - t1))

    def frame(self, frame: RgbdFrame, skip_vo: bool = False) -> FrontEndStep:
        """VO (unless ``skip_vo``: a live front end behind), the pose at the frame's stamp and
        the scan. A skipped frame's motion is fused with the next VO pair, spread over both."""
        self._stages(frame)
        stride = not self._vo_due(self._n_frames)  # vo.every_n_frames: not this one
        self._n_frames += 1
        own = None
        if any(f is frame for f, _ in self._ahead):
            while own is None:  # (work made ahead for frames never processed is dropped)
                f, work = self._ahead.popleft()
                own = work.result() if f is frame else None
        if own is not None and own.features is not None and self._vo is not None:
            self._vo.give_features(frame, own.features)
        if self.ekf is not None and (self.vo_carries or self.options.wheels):
            # The odom frame is where the robot starts; with wheels, where it stands at the
            # first frame unless their first motion came before it. Frames before the board's
            # first motion had no pose, and a short live run then mapped nothing (#16).
            self.ekf.start(frame.stamp_ns)
        res, vo_ms = (None, math.nan)
        if not self.options.pose_before_vo:
            res, vo_ms = self._visual_odometry(frame, skip_vo, stride)
        t0 = time.perf_counter()
        odom, timed_out = self._pose_at(frame.stamp_ns)
        ekf_ms = 1e3 * (time.perf_counter() - t0)
        scan, scan_ms = None, math.nan
        if self._d2s is not None and odom is not None:
            if own is not None and own.scan is not None:
                scan, scan_ms = own.scan, own.scan_ms
            else:
                t0 = time.perf_counter()
                scan = self._d2s.from_frame(frame).scan
                scan_ms = 1e3 * (time.perf_counter() - t0)
        if self.options.pose_before_vo:  # VO corrects the filter for the frames that follow
            res, vo_ms = self._visual_odometry(frame, skip_vo, stride)
        if res is not None and own is not None and own.features is not None:
            vo_ms += own.features_ms
        camera = None
        if not self.options.planar and self._vo is not None:
            camera = self._vo.T_odom_cam.copy()
        return FrontEndStep(
            frame.stamp_ns, odom, timed_out, scan, res, camera, vo_ms, scan_ms, ekf_ms
        )

    def needs_rgb(self, index: int) -> bool:
        """Frame ``index`` (0 = the first given to :meth:`frame`) is read for its colour: VO
        runs on it. The others' colour images need not be decoded (:func:`replay`). Readers
        ask from their decode threads, so this only reads the gyro-bias latch: the filter is
        judged on the frame loop's thread alone, and the stride stays deterministic."""
        return self.options.vo and self._vo_due(index, judge_bias=False)

    def _vo_due(self, index: int, judge_bias: bool = True) -> bool:
        """VO runs on frame ``index`` (0 = the first): every frame, or with ``vo.every_n_frames``
        n > 1 every n-th one while the wheel encoders carry the filter between."""
        n = self.vo_cfg.every_n_frames
        learned = self._bias_learned() if judge_bias else self._bias_settled
        return n <= 1 or not self._wheels_carry or not learned or index % n == 0

    def _bias_learned(self) -> bool:
        """The EKF's gyro bias is known to ``vo.stride_below_bias_sigma`` (latched once true), or
        that rule is off or has no gyro. Until then VO runs on every frame: the heading the
        bias turns while it is learned turns the whole map (docs/design/gyro_bias.md)."""
        limit = self.vo_cfg.stride_below_bias_sigma
        if not self._bias_settled and self.ekf is not None:
            self._bias_settled = self.ekf.P[GYRO_BIAS, GYRO_BIAS] < limit * limit
            if self._bias_settled:
                self.counts["vo_stride_from_frame"] = self._n_frames
        return self._bias_settled

    def _pose_at(self, stamp_ns: int) -> tuple[Odometry2D | None, bool]:
        if self.ekf is None:
            return None, False
        try:
            od = self.ekf.state_at(stamp_ns)
        except EkfError:  # no input yet, or the frame is older than the kept history
            self.counts["frames_without_filter_pose"] += 1
            return None, False
        return od, self.ekf.is_timed_out(stamp_ns)

    def _visual_odometry(
        self, frame: RgbdFrame, skip: bool, stride: bool = False
    ) -> tuple[VoResult | None, float]:
        """VO between ``frame`` and the last frame VO ran on, fused as the pair's mean twist
        over every frame it spans; (result or None when skipped or off, ms)."""
        if self._vo is None:
            return None, math.nan
        if (skip or stride) and self._vo_prev_ns is not None:
            self.counts["vo_skipped_behind" if skip else "vo_skipped_stride"] += 1
            self._vo_skipped.append(frame.stamp_ns)
            return None, math.nan
        t0 = time.perf_counter()
        res = self._vo.process(frame)
        prev, self._vo_prev_ns = self._vo_prev_ns, frame.stamp_ns
        if prev is not None:
            dt = (frame.stamp_ns - prev) / NS_PER_S
            d = res.delta_base
            ok = res.success and dt > 0 and (d is not None or not self.options.planar)
            if not ok:
                # (vo.force_3dof off on a ground robot: no planar motion for the EKF)
                self.counts[f"vo_failures_{res.reason if not res.success else 'not_planar'}"] += 1
            elif res.fallback:
                self.counts["vo_fallbacks"] += 1  # the features failed, depth ICP tracked
            elif self.ekf is not None and d is not None and "vo0" in self.inputs:
                # Spread over its span when it spans skipped or dropped frames; a pair a few
                # ms longer than a frame period (camera jitter) is one twist at its end.
                gap = dt > GAP_PERIODS / self.options.camera_rate_hz
                step = 1.0 / self.ekf_cfg.frequency if self._vo_skipped or gap else None
                out = self.ekf.process_span(
                    "vo0",
                    spanning_motion_twists(
                        self._vo_skipped, frame.stamp_ns, d, res.covariance, dt, step
                    ),
                )
                if out and out[0].reason == "span_rejected":
                    self.counts["vo_spans_rejected"] += 1
        self._vo_skipped.clear()
        return res, 1e3 * (time.perf_counter() - t0)


# --- offline: a source's streams in time order ----------------------------------------------


def options_for(
    src: Source, use_vo: bool = True, force_3dof: bool = False, camera_rate_hz: float = 30.0
) -> FrontEndOptions:
    """What ``src`` offers the front end. A source with neither wheels nor odometry messages is
    a handheld camera unless ``force_3dof`` says it rides on a ground robot."""
    wheels, odo, imu = src.wheels(), src.odometry(), src.imu()
    rgb = np.asarray(src.stream_stamps().get("rgb", ()), np.int64)
    interval = float(np.median(np.diff(rgb))) / NS_PER_S if len(rgb) > 1 else 0.0
    has_wheels = wheels is not None and len(wheels.stamps_ns) >= 2
    kind = ""
    if odo is not None and len(odo.stamps_ns) >= 2:
        kind = "twist" if odo.twist is not None else "pose"
    if has_wheels and kind:
        log.info("%s: wheel encoders and odometry messages: fusing the wheels only", src.path)
    return FrontEndOptions(
        wheels=has_wheels,
        odometry=kind,
        imu=imu is not None and len(imu.stamps_ns) > 0,
        vo=use_vo and src.intrinsics() is not None,
        planar=has_wheels or bool(kind) or force_3dof,
        frame_interval_s=interval,
        camera_rate_hz=camera_rate_hz,
    )


def odom_origin(src: Source) -> Pose2:
    """Where the odom frame sits in the world: the source's base_link ground truth at its first
    wheel reading (else odometry message, else frame), or the origin without ground truth."""
    gt = src.groundtruth()
    if gt is None or gt.frame != "base_link" or len(gt.stamps_ns) == 0:
        return Pose2(0.0, 0.0, 0.0)
    wheels, odo = src.wheels(), src.odometry()
    firsts = [s.stamps_ns for s in (wheels, odo) if s is not None and len(s.stamps_ns)]
    firsts.append(np.asarray(src.stream_stamps().get("rgb", gt.stamps_ns[:1])))
    t = np.asarray(firsts[0][:1], np.int64)
    gx, gy, gyaw, _ = interpolate_poses(gt.stamps_ns, gt.x, gt.y, gt.yaw, t)
    return Pose2(float(gx[0]), float(gy[0]), float(gyaw[0]))


def _odometry_messages(src: Source, kind: str, fallback_variance: float) -> list[OdometryMessage]:
    """A source's odometry stream as EKF messages: twists (with their covariance) or poses. An
    all-zero covariance (many drivers leave it unset) is replaced by ``fallback_variance``."""
    odo = src.odometry()
    if odo is None or not kind:
        return []
    n = len(odo.stamps_ns)

    def covariances(c: np.ndarray | None) -> np.ndarray:
        out = np.zeros((n, 3, 3)) if c is None else np.array(c, dtype=np.float64).reshape(n, 3, 3)
        unset = ~np.any(out != 0, axis=(1, 2))
        out[unset] = np.eye(3) * fallback_variance
        return out

    if kind == "twist":
        assert odo.twist is not None
        tw, cov = np.asarray(odo.twist, np.float64), covariances(odo.twist_covariance)
        return [
            TwistInput(int(t), float(v[0]), float(v[1]), float(v[2]), c)
            for t, v, c in zip(odo.stamps_ns, tw, cov, strict=True)
        ]
    cov = covariances(odo.pose_covariance)
    return [
        PoseInput(int(t), Pose2(float(x), float(y), float(a)), c)
        for t, x, y, a, c in zip(odo.stamps_ns, odo.x, odo.y, odo.yaw, cov, strict=True)
    ]


class MessageFeed:
    """A source's non-frame streams (wheels, odometry, IMU, as ``fe.options`` enables them) in
    one time order, fed to ``fe`` up to each frame's stamp: the one interleaving the offline
    :func:`replay` and the live run share. ``offset_ns`` moves the source's clock onto the
    frames' (the live run's monotonic clock: ``RealSenseSource.stamp_offset_ns``); ``kinds``
    narrows the streams (live: the camera's ``imu`` only, the board gives the wheels)."""

    def __init__(
        self,
        src: Source,
        fe: FrontEnd,
        offset_ns: int = 0,
        kinds: tuple[str, ...] = ("wheels", "odometry", "imu"),
    ) -> None:
        opts = replace(
            fe.options,
            wheels=fe.options.wheels and "wheels" in kinds,
            odometry=fe.options.odometry if "odometry" in kinds else "",
            imu=fe.options.imu and "imu" in kinds,
        )
        stamps: list[np.ndarray] = []
        feed: list[Callable[[int], object]] = []  # each feeds message i; results unused
        wheels = src.wheels() if opts.wheels else None
        if wheels is not None:
            w = wheels
            stamps.append(np.asarray(w.stamps_ns, np.int64))
            feed.append(
                lambda i: fe.wheels(
                    WheelTicks(int(w.stamps_ns[i]) + offset_ns, int(w.left[i]), int(w.right[i]))
                )
            )
        if opts.odometry and not fe.options.wheels:
            msgs = _odometry_messages(src, opts.odometry, fe.ekf_cfg.odom0_default_variance)
            stamps.append(np.array([m.stamp_ns for m in msgs], np.int64))
            msgs = (
                [replace(m, stamp_ns=m.stamp_ns + offset_ns) for m in msgs] if offset_ns else msgs
            )
            feed.append(lambda i: fe.odometry(msgs[i]))
        imu = src.imu() if opts.imu else None
        # The IMU stream is held here (extend_imu replaces it); -1: none.
        self._imu = imu if imu is not None else ImuStream(np.zeros(0, np.int64), np.zeros(0))
        self._imu_slot = -1
        if imu is not None or opts.imu:
            self._imu_slot = len(feed)
            stamps.append(np.asarray(self._imu.stamps_ns, np.int64))
            feed.append(
                lambda i: fe.imu(
                    ImuSample(int(self._imu.stamps_ns[i]) + offset_ns, float(self._imu.gyro_z[i]))
                )
            )
        # One time-ordered merge (stable: ties keep the order above).
        all_t = np.concatenate(stamps) if stamps else np.zeros(0, np.int64)
        which = (
            np.concatenate([np.full(len(s), k) for k, s in enumerate(stamps)]) if stamps else all_t
        )
        index = np.concatenate([np.arange(len(s)) for s in stamps]) if stamps else all_t
        order = np.argsort(all_t, kind="stable")
        self._t = all_t[order] + offset_ns
        self._which, self._index, self._feed = which[order], index[order], feed
        self._k = 0
        self._offset_ns = offset_ns

    def extend_imu(self, imu: ImuStream) -> None:
        """IMU samples that arrived since (a live camera's gyro, streaming): merged with the
        ones not fed yet, then fed by :meth:`until` as the recorded ones. Fed samples are let
        go, so an hours-long run holds only the few waiting for their frame."""
        if self._imu_slot < 0 or len(imu.stamps_ns) == 0:
            return
        k, slot = self._k, self._imu_slot
        t, which, index = self._t[k:], self._which[k:], self._index[k:].copy()
        waiting = which == slot
        kept = index[waiting]
        self._imu = ImuStream(
            np.concatenate([np.asarray(self._imu.stamps_ns)[kept], imu.stamps_ns]).astype(np.int64),
            np.concatenate([np.asarray(self._imu.gyro_z)[kept], imu.gyro_z]),
        )
        index[waiting] = np.arange(len(kept))
        n = len(imu.stamps_ns)
        t = np.concatenate([t, np.asarray(imu.stamps_ns, np.int64) + self._offset_ns])
        which = np.concatenate([which, np.full(n, slot)])
        index = np.concatenate([index, np.arange(len(kept), len(kept) + n)])
        order = np.argsort(t, kind="stable")
        self._t, self._which, self._index, self._k = t[order], which[order], index[order], 0

    def until(self, stamp_ns: int) -> None:
        """Every message stamped at or before ``stamp_ns`` not fed yet (ties: before the frame,
        as :func:`slam.ekf.fuse` orders a message at an output's stamp before the output)."""
        end = int(np.searchsorted(self._t, stamp_ns, side="right"))
        for m in range(self._k, end):
            self._feed[self._which[m]](int(self._index[m]))
        self._k = max(self._k, end)


def replay(
    src: Source,
    fe: FrontEnd,
    progress: Callable[[int, int], None] | None = None,
    ahead: bool = True,
) -> Iterator[FrontEndStep]:
    """``src``'s streams through ``fe`` in time order: before each frame every wheel reading,
    odometry message and IMU sample stamped at or before it (:class:`MessageFeed`). With
    ``ahead`` the next STAGE_FRAMES_AHEAD frames are read before this one is processed and their
    own work (features, scan) runs on the stage thread meanwhile (:meth:`FrontEnd.prefetch`;
    the same steps)."""
    messages = MessageFeed(src, fe)
    n = len(src.stream_stamps().get("rgb", ()))
    # (a recording does not decode the colour of the frames VO skips: half its RGB decode)
    frames = src.frames_for(fe.needs_rgb) if isinstance(src, SourceBase) else src.frames()
    if not ahead:
        for j, frame in enumerate(frames):
            messages.until(frame.stamp_ns)
            yield fe.frame(frame)
            if progress is not None:
                progress(j + 1, n)
        return
    switch = sys.getswitchinterval()
    sys.setswitchinterval(min(switch, STAGE_SWITCH_INTERVAL_S))
    try:
        yield from _replay_pending(frames, messages, fe, progress, n)
    finally:  # (a consumer that stops early leaves no work queued)
        fe.drop_ahead()
        sys.setswitchinterval(switch)


def _replay_pending(
    frames: Iterator[RgbdFrame],
    messages: MessageFeed,
    fe: FrontEnd,
    progress: Callable[[int, int], None] | None,
    n: int,
) -> Iterator[FrontEndStep]:
    pending: deque[RgbdFrame] = deque()  # read, their own work started, not processed yet
    error: Exception | None = None
    done = False
    j = 0
    while True:
        while not done and len(pending) <= STAGE_FRAMES_AHEAD:  # (frames come in order)
            try:
                nxt = next(frames, None)
            except Exception as err:  # a bad frame: raised where it was, after those before it
                nxt, error = None, err
            done = nxt is None
            if nxt is not None:
                fe.prefetch(nxt)
                pending.append(nxt)
        if not pending:
            break
        frame = pending.popleft()
        messages.until(frame.stamp_ns)
        yield fe.frame(frame)
        j += 1
        if progress is not None:
            progress(j, n)
    if error is not None:
        raise error


__all__ = [
    "odom_origin",
    "FrontEnd",
    "FrontEndOptions",
    "FrontEndStep",
    "MessageFeed",
    "options_for",
    "pose_only_odom0",
    "replay",
]
