"""Velocity smoother with nav2_velocity_smoother semantics.

The controller publishes commands at its own rate (often jerky, sometimes late); the smoother runs
on its own timer at ``smoothing_frequency`` and moves the output toward the latest command within
velocity and acceleration limits, so the wheels see a ramp instead of a step. Per tick, as in Nav2:

1. clamp the target to ``[min_velocity, max_velocity]`` per axis;
2. per axis, pick the limit: the speed magnitude *grows* (``|target| >= |current|`` and no sign
   change) -> ``max_accel``, otherwise (slowing down or passing through zero) -> ``max_decel``;
3. with ``scale_velocities``, find the most-limited axis and scale every axis' change by that
   ``eta``, so the output keeps the direction of the requested (vx, vy, wz) change; the per-axis
   limits are applied again afterwards so no axis ever breaks its own limit;
4. remember the result as the current velocity (OPEN_LOOP) and zero outputs inside the deadband
   (Nav2 applies the deadband after storing, so tiny commands still ramp internally);
5. after ``velocity_timeout`` without a command the target becomes zero: the robot decelerates to
   a stop within ``max_decel`` and, once stopped, stays at zero until a new command arrives.

Nav2 uses the nominal period ``1 / smoothing_frequency`` as the step, whatever the real timer
jitter; :class:`VelocitySmoother` does the same. The kernels take ``dt`` explicitly.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from nav.config import SmootherConfig

logger = logging.getLogger(__name__)

Twist = tuple[float, float, float]  # (vx [m/s], vy [m/s], wz [rad/s]) in base_link
ZERO_TWIST: Twist = (0.0, 0.0, 0.0)
NS_PER_S = 1_000_000_000


def eddie_profile(max_wheel_speed: float | None = None) -> SmootherConfig:
    """Eddie's tuning: differential drive (vy = 0), 1.4 m/s top speed, gentle 0.2 rad/s turns.

    The 1.4 m/s comes from the issue's Eddie profile; the board driver never lets a wheel go
    faster than ``robot.max_wheel_speed`` (0.9 m/s in ``config/robots/eddie.yaml``) and scales
    both wheels down together above it, so a smoother allowing 1.4 m/s would ramp past what the
    wheels do. Give ``max_wheel_speed`` [m/s] to clamp the linear limits to it (a straight run
    at that speed; turning at the same time makes the driver scale the twist down further).
    """
    v_max = 1.4 if max_wheel_speed is None else min(1.4, max_wheel_speed)  # [m/s]
    if not v_max > 0.0:
        raise ValueError(f"max_wheel_speed must be > 0, got {max_wheel_speed}")
    return SmootherConfig(
        smoothing_frequency=20.0,
        scale_velocities=True,
        feedback="OPEN_LOOP",
        max_velocity=(v_max, 0.0, 0.2),
        min_velocity=(-v_max, 0.0, -0.2),
        max_accel=(1.125, 0.0, 1.125),
        max_decel=(-1.125, 0.0, -1.125),
        deadband_velocity=(0.0, 0.0, 0.0),
    )


EDDIE_PROFILE: SmootherConfig = eddie_profile()


def _step_bounds(
    v_curr: np.ndarray, v_cmd: np.ndarray, dt: float, config: SmootherConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis allowed change (dv_min, dv_max) over one step of ``dt`` seconds.

    Accelerating iff |v_cmd| >= |v_curr| and the sign does not flip (v_curr * v_cmd >= 0);
    anything else, including a zero crossing, counts as decelerating."""
    accel = np.asarray(config.max_accel, dtype=np.float64)
    decel = np.asarray(config.max_decel, dtype=np.float64)  # <= 0
    accelerating = (np.abs(v_cmd) >= np.abs(v_curr)) & (v_curr * v_cmd >= 0.0)
    dv_max = np.where(accelerating, accel, -decel) * dt
    dv_min = np.where(accelerating, -accel, decel) * dt
    return dv_min, dv_max


def find_eta(v_curr: np.ndarray, v_cmd: np.ndarray, dt: float, config: SmootherConfig) -> float:
    """The common scale eta in (0, 1] that brings the most-limited axis within its limit.

    Axes within their limit (or not moving) do not constrain eta; 1.0 when none is limited."""
    dv = v_cmd - v_curr
    dv_min, dv_max = _step_bounds(v_curr, v_cmd, dt, config)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        eta_axis = np.where(dv > dv_max, dv_max / dv, np.where(dv < dv_min, dv_min / dv, np.nan))
    # Nav2 keeps the eta furthest from 1 among positive candidates; an axis with a zero limit and
    # a non-zero request gives eta = 0, which Nav2 ignores (the per-axis clamp handles it).
    candidates = eta_axis[np.isfinite(eta_axis) & (eta_axis > 0.0)]
    if candidates.size == 0:
        return 1.0
    return float(candidates[np.argmax(np.abs(1.0 - candidates))])


def limit_step(last_cmd: Twist, target: Twist, dt: float, config: SmootherConfig) -> Twist:
    """One smoothing step without the deadband: the velocity the robot is commanded to have.

    ``last_cmd`` is the current velocity (the previous output in OPEN_LOOP, measured odometry in
    CLOSED_LOOP); ``target`` the controller's latest command; ``dt`` [s] the step."""
    v_curr = np.asarray(last_cmd, dtype=np.float64)
    # 1. Absolute velocity limits.
    v_cmd = np.clip(
        np.asarray(target, dtype=np.float64),
        np.asarray(config.min_velocity, dtype=np.float64),
        np.asarray(config.max_velocity, dtype=np.float64),
    )
    # 2./3. Acceleration limits, optionally scaled together to keep the direction.
    eta = find_eta(v_curr, v_cmd, dt, config) if config.scale_velocities else 1.0
    dv_min, dv_max = _step_bounds(v_curr, v_cmd, dt, config)
    out = v_curr + np.clip(eta * (v_cmd - v_curr), dv_min, dv_max)
    return (float(out[0]), float(out[1]), float(out[2]))


def apply_deadband(cmd: Twist, config: SmootherConfig) -> Twist:
    """Zero each axis whose magnitude is below its ``deadband_velocity``."""
    v = np.asarray(cmd, dtype=np.float64)
    v = np.where(np.abs(v) < np.asarray(config.deadband_velocity, dtype=np.float64), 0.0, v)
    return (float(v[0]), float(v[1]), float(v[2]))


def smooth_step(last_cmd: Twist, target: Twist, dt: float, config: SmootherConfig) -> Twist:
    """One smoothing step as published: :func:`limit_step` followed by the deadband."""
    return apply_deadband(limit_step(last_cmd, target, dt, config), config)


class VelocitySmoother:
    """Stateful shell: holds the latest command, the last output and recent odometry.

    Call :meth:`tick` at ``smoothing_frequency``; it returns the command to send to the wheels.
    Before the first command (and once stopped after a timeout) it returns zeros; Nav2 publishes
    nothing then, which for a wheel driver amounts to the same."""

    def __init__(self, config: SmootherConfig) -> None:
        self.config = config
        self.period_s = 1.0 / config.smoothing_frequency  # [s] nominal step, as in Nav2
        self._target: Twist | None = None
        self._target_stamp_ns = 0
        self._last_cmd: Twist = ZERO_TWIST  # before the deadband
        self._stopped = True
        self._odom: deque[tuple[int, Twist]] = deque()

    @property
    def stopped(self) -> bool:
        """True when timed out and at rest (Nav2 stops publishing in this state)."""
        return self._stopped

    @property
    def last_cmd(self) -> Twist:
        """The internal current velocity (OPEN_LOOP), before the deadband."""
        return self._last_cmd

    def set_target(self, cmd: Twist, stamp_ns: int) -> None:
        """A new controller command; non-finite commands are ignored, as in Nav2."""
        if not all(np.isfinite(cmd)):
            logger.warning("ignoring non-finite velocity command %s", cmd)
            return
        self._target = (float(cmd[0]), float(cmd[1]), float(cmd[2]))
        self._target_stamp_ns = stamp_ns

    def set_odometry(self, twist: Twist, stamp_ns: int) -> None:
        """Measured velocity for CLOSED_LOOP; averaged over the last ``odom_duration``."""
        self._odom.append((stamp_ns, (float(twist[0]), float(twist[1]), float(twist[2]))))
        horizon_ns = stamp_ns - int(self.config.odom_duration * NS_PER_S)
        while self._odom and self._odom[0][0] < horizon_ns:
            self._odom.popleft()

    def current_velocity(self) -> Twist:
        """The velocity the next step starts from (last output, or averaged odometry)."""
        if self.config.feedback == "OPEN_LOOP":
            return self._last_cmd
        if not self._odom:
            return ZERO_TWIST  # Nav2's odometry smoother also starts from rest
        mean = np.mean(np.array([t for _, t in self._odom]), axis=0)
        return (float(mean[0]), float(mean[1]), float(mean[2]))

    def tick(self, now_ns: int) -> Twist:
        """One timer step at ``now_ns``: the smoothed command to send."""
        # 1. Nothing to follow before the first command.
        if self._target is None:
            return ZERO_TWIST
        # 2. Timeout: the target becomes zero; once at rest, stay there without stepping.
        timed_out = (now_ns - self._target_stamp_ns) > self.config.velocity_timeout * NS_PER_S
        if timed_out:
            if self._stopped or self._last_cmd == ZERO_TWIST:
                self._stopped = True
                return ZERO_TWIST
            self._target = ZERO_TWIST
        self._stopped = False
        # 3. Limit the step from the current velocity toward the target.
        self._last_cmd = limit_step(
            self.current_velocity(), self._target, self.period_s, self.config
        )
        # 4. Deadband on the published command only.
        return apply_deadband(self._last_cmd, self.config)
