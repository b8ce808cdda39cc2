"""Differential-drive wheel odometry: cumulative encoder counts -> planar poses.

For each interval between two encoder readings (nominal geometry)::

    dL, dR = dcounts * pi * wheel_diameter / ticks_per_revolution      [m]
    ds     = (dR + dL) / 2                                              [m]
    dtheta = (dR - dL) / track_width                                    [rad]
    x     += ds * cos(theta + dtheta / 2)        (midpoint integration)
    y     += ds * sin(theta + dtheta / 2)
    theta += dtheta

Everything is a cumulative sum, so a whole log integrates without a Python loop; so does the
covariance (:func:`propagate_covariance`), whose Jacobians telescope into prefix sums.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from sensors.config import RobotConfig, build_section, param
from sensors.types import NS_PER_S, Pose2, WheelTicks
from slam.geometry import wrap_angle

ORIGIN = Pose2(0.0, 0.0, 0.0)


def wheel_increments(
    left: np.ndarray, right: np.ndarray, robot: RobotConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(ds [m], dtheta [rad]) for each interval between consecutive encoder readings."""
    m_per_tick = robot.metres_per_tick
    d_left = np.diff(np.asarray(left, dtype=np.int64)) * m_per_tick
    d_right = np.diff(np.asarray(right, dtype=np.int64)) * m_per_tick
    return (d_right + d_left) / 2, (d_right - d_left) / robot.track_width


def integrate_increments(
    ds: np.ndarray, dtheta: np.ndarray, start: Pose2 = ORIGIN
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoint-integrate increments; returns N+1 poses (the first is ``start``)."""
    theta = start.yaw + np.concatenate([[0.0], np.cumsum(dtheta)])
    heading = theta[:-1] + dtheta / 2
    x = start.x + np.concatenate([[0.0], np.cumsum(ds * np.cos(heading))])
    y = start.y + np.concatenate([[0.0], np.cumsum(ds * np.sin(heading))])
    return x, y, theta


def integrate_ticks(
    left: np.ndarray, right: np.ndarray, robot: RobotConfig, start: Pose2 = ORIGIN
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pose per encoder reading: (x [m], y [m], yaw [rad], unwrapped)."""
    ds, dtheta = wheel_increments(left, right, robot)
    return integrate_increments(ds, dtheta, start)


GLITCH_SPEED_FACTOR = 5.0  # [-] a wheel faster than this times robot.max_wheel_speed is a glitch
GLITCH_SLACK_TICKS = 2  # [ticks] per interval, for stamps that bunch up


@dataclass(frozen=True)
class EncoderCleanup:
    """Encoder readings with implausible jumps taken out (:func:`reject_encoder_glitches`)."""

    stamps_ns: np.ndarray  # (M,) int64 [ns]
    left: np.ndarray  # (M,) int64 cumulative counts, jumps removed
    right: np.ndarray  # (M,) int64
    glitches_dropped: int  # single readings off and back (a spike): removed
    jumps_zeroed: int  # steps that stayed (a counter reset): taken as no motion


def reject_encoder_glitches(
    stamps_ns: np.ndarray, left: np.ndarray, right: np.ndarray, robot: RobotConfig
) -> EncoderCleanup:
    """A reading whose step from the previous one would need a wheel faster than
    ``GLITCH_SPEED_FACTOR * robot.max_wheel_speed`` is not motion: one glitched reading sent a
    wheel trajectory 300 km away. A spike (off, then back within the next step) drops the
    reading; a step that stays (a counter reset) is integrated as no motion. Vectorised."""
    t = np.asarray(stamps_ns, dtype=np.int64)
    counts = np.column_stack([np.asarray(left, np.int64), np.asarray(right, np.int64)])
    if len(t) < 2:
        return EncoderCleanup(t, counts[:, 0], counts[:, 1], 0, 0)
    dt_s = np.maximum(np.diff(t), 0) / NS_PER_S
    limit = (
        GLITCH_SPEED_FACTOR * robot.max_wheel_speed * dt_s / robot.metres_per_tick
        + GLITCH_SLACK_TICKS
    )[:, None]  # [ticks] per interval
    step = np.diff(counts, axis=0)
    bad = np.asarray((np.abs(step) > limit).any(axis=1))
    # 1. Spikes: interval i and i+1 both implausible, their sum plausible -> reading i+1 off.
    pair_ok = (np.abs(step[:-1] + step[1:]) <= limit[:-1] + limit[1:]).all(axis=1)
    spike = np.flatnonzero(bad[:-1] & bad[1:] & pair_ok) + 1
    spike = spike[np.diff(np.concatenate([[-2], spike])) > 1]  # a reading, not its neighbour
    keep = np.ones(len(t), bool)
    keep[spike] = False
    t, counts = t[keep], counts[keep]
    # 2. Steps that stayed: no motion over that interval, the counts after it shifted back.
    step = np.diff(counts, axis=0)
    dt_s = np.maximum(np.diff(t), 0) / NS_PER_S
    limit = (
        GLITCH_SPEED_FACTOR * robot.max_wheel_speed * dt_s / robot.metres_per_tick
        + GLITCH_SLACK_TICKS
    )[:, None]
    jump = (np.abs(step) > limit).any(axis=1)
    step[jump] = 0
    counts = counts[0] + np.vstack([np.zeros((1, 2), np.int64), np.cumsum(step, axis=0)])
    return EncoderCleanup(t, counts[:, 0], counts[:, 1], int(len(spike)), int(jump.sum()))


class EncoderGate:
    """:func:`reject_encoder_glitches` for readings as they arrive (the live run, the front end).

    A reading whose step from the last accepted one is implausible is held: if the next one
    agrees with the last accepted reading, the held one was a spike and is dropped; if it agrees
    with the held one, the counters jumped and stayed (a reset), taken as no motion over that
    interval from then on. Normal readings pass with no delay; a suspect one waits one reading.
    """

    def __init__(self, robot: RobotConfig) -> None:
        self.robot = robot
        self.glitches_dropped = 0
        self.jumps_zeroed = 0
        self._last: WheelTicks | None = None  # the last accepted reading, offset applied
        self._held: WheelTicks | None = None  # a suspect raw reading
        self._offset = (0, 0)  # raw - accepted counts, from the resets so far

    def _plausible(self, a: WheelTicks, b: WheelTicks) -> bool:
        dt_s = max(b.stamp_ns - a.stamp_ns, 0) / NS_PER_S
        limit = (
            GLITCH_SPEED_FACTOR * self.robot.max_wheel_speed * dt_s / self.robot.metres_per_tick
            + GLITCH_SLACK_TICKS
        )
        return abs(b.left - a.left) <= limit and abs(b.right - a.right) <= limit

    def _shifted(self, t: WheelTicks) -> WheelTicks:
        return WheelTicks(t.stamp_ns, t.left - self._offset[0], t.right - self._offset[1])

    def push(self, raw: WheelTicks) -> list[WheelTicks]:
        """The readings (offset applied) that ``raw`` releases, oldest first."""
        t = self._shifted(raw)
        if self._last is None or self._plausible(self._last, t):
            if self._held is not None:
                self.glitches_dropped += 1  # off and back: a spike
                self._held = None
            self._last = t
            return [t]
        if self._held is None:
            self._held = raw
            return []
        if self._plausible(self._held, raw):  # it stayed: a counter jump, not motion
            held = self._held
            self._offset = (held.left - self._last.left, held.right - self._last.right)
            self.jumps_zeroed += 1
            self._held = None
            self._last = self._shifted(raw)
            return [self._shifted(held), self._last]
        self.glitches_dropped += 1  # neither agrees: drop the older suspect, hold this one
        self._held = raw
        return []


def wheel_twist(
    stamps_ns: np.ndarray, left: np.ndarray, right: np.ndarray, robot: RobotConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Body velocities (v [m/s], w [rad/s]) over each interval (N-1 values)."""
    ds, dtheta = wheel_increments(left, right, robot)
    dt = np.diff(np.asarray(stamps_ns, dtype=np.int64)) / NS_PER_S
    dt = np.where(dt > 0, dt, np.nan)
    return ds / dt, dtheta / dt


# --- covariance -------------------------------------------------------------------------------


@dataclass(frozen=True)
class WheelErrorModel:
    """Wheel odometry error model (Siegwart & Nourbakhsh, *Introduction to Autonomous Mobile
    Robots*, eq. 5.9): each wheel's travel error is zero-mean, independent between wheels and
    steps, with variance proportional to the distance that wheel travelled::

        Sigma_wheel = diag(k_right |dR|, k_left |dL|)           [m^2]

    plus an optional heading error for unmodelled turn slip, variance ``k_theta |dtheta|``
    [rad^2]. Defaults: k = 0.0005 m gives sigma = sqrt(0.0005 * 1) = 2.2 cm after 1 m of travel.
    """

    k_left: float = param(0.0005, unit="m", ge=0.0, doc="left wheel variance per metre travelled")
    k_right: float = param(0.0005, unit="m", ge=0.0, doc="right wheel variance per metre")
    k_theta: float = param(0.0, unit="rad", ge=0.0, doc="heading variance per radian turned")

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any] | None, path: str = "wheel_error"
    ) -> WheelErrorModel:
        """From a YAML mapping; unknown keys and negative values raise ConfigError."""
        return build_section(cls, data, path)

    @classmethod
    def from_robot(cls, robot: RobotConfig) -> WheelErrorModel:
        return cls(robot.wheel_error_left, robot.wheel_error_right, robot.wheel_error_theta)


def _increment_jacobians(
    ds: np.ndarray, dtheta: np.ndarray, theta_start: float, track_width: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step: the pose-increment lever ``a`` (N, 3), ``F_rl`` (N, 3, 2) and ``g`` (N, 3).

    See :func:`propagate_covariance` for the derivation.
    """
    theta = theta_start + np.concatenate([[0.0], np.cumsum(dtheta)])[:-1]  # at each step's start
    phi = theta + dtheta / 2
    c, s = np.cos(phi), np.sin(phi)
    h = ds / (2 * track_width)
    n = ds.size
    a = np.stack([-ds * s, ds * c, np.zeros(n)], axis=-1)
    f_rl = np.empty((n, 3, 2))
    f_rl[:, 0, 0] = c / 2 - h * s
    f_rl[:, 0, 1] = c / 2 + h * s
    f_rl[:, 1, 0] = s / 2 + h * c
    f_rl[:, 1, 1] = s / 2 - h * c
    f_rl[:, 2, 0] = 1 / track_width
    f_rl[:, 2, 1] = -1 / track_width
    g = np.stack([-ds * s / 2, ds * c / 2, np.ones(n)], axis=-1)
    return a, f_rl, g


def increment_covariance(
    ds: np.ndarray,
    dtheta: np.ndarray,
    theta_start: float,
    robot: RobotConfig,
    model: WheelErrorModel = WheelErrorModel(),
) -> np.ndarray:
    """Q_i = F_rl Sigma_wheel F_rl^T + k_theta |dtheta| g g^T for each step, (N, 3, 3)."""
    ds = np.asarray(ds, dtype=np.float64).reshape(-1)
    dtheta = np.asarray(dtheta, dtype=np.float64).reshape(-1)
    b = robot.track_width
    _, f_rl, g = _increment_jacobians(ds, dtheta, theta_start, b)
    d_right, d_left = ds + b * dtheta / 2, ds - b * dtheta / 2
    sigma = np.stack([model.k_right * np.abs(d_right), model.k_left * np.abs(d_left)], axis=-1)
    q = (f_rl * sigma[:, None, :]) @ f_rl.transpose(0, 2, 1)  # F_rl Sigma F_rl^T, batched
    q += (model.k_theta * np.abs(dtheta))[:, None, None] * np.einsum("ni,nk->nik", g, g)
    return q


def propagate_covariance(
    ds: np.ndarray,
    dtheta: np.ndarray,
    theta_start: float,
    robot: RobotConfig,
    model: WheelErrorModel = WheelErrorModel(),
    cov0: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance of the midpoint-integrated pose (x, y, theta) at every reading, (N+1, 3, 3).

    Model, per step i with wheel travels dR, dL [m], track b [m], phi = theta + dtheta/2::

        ds = (dR + dL)/2,  dtheta = (dR - dL)/b (+ e_theta)
        x' = x + ds cos(phi),  y' = y + ds sin(phi),  theta' = theta + dtheta

    Jacobians (d ds/d dR = d ds/d dL = 1/2, d dtheta/d dR = -d dtheta/d dL = 1/b, h = ds/(2b))::

        F_p  = d(x', y', theta')/d(x, y, theta) = [[1, 0, -ds sin(phi)],
                                                   [0, 1,  ds cos(phi)],
                                                   [0, 0,  1          ]]
        F_rl = d(x', y', theta')/d(dR, dL) = [[cos(phi)/2 - h sin(phi), cos(phi)/2 + h sin(phi)],
                                              [sin(phi)/2 + h cos(phi), sin(phi)/2 - h cos(phi)],
                                              [1/b,                     -1/b                   ]]
        g    = d(x', y', theta')/d e_theta = [-ds sin(phi)/2, ds cos(phi)/2, 1]

        P_{i+1} = F_p P_i F_p^T + Q_i
        Q_i     = F_rl diag(k_r |dR|, k_l |dL|) F_rl^T + k_theta |dtheta| g g^T

    Closed form (no loop). F_p = I + a e3^T with a = (-dy, dx, 0) the step's displacement turned
    by 90 deg; since e3^T a = 0, products telescope: F_{k-1}...F_j = I + (r_k - r_j) e3^T with
    r_j = (-y_j, x_j, 0) (r_k - r_j is the lever arm from pose j to pose k, turned by 90 deg).
    Index each noise term by the pose it enters at, N_0 = P_0 and N_{i+1} = Q_i, and write
    q = N e3, s = N[2, 2] and c = r_k - r_j::

        P_k = sum_{j <= k} (I + c e3^T) N_j (I + c e3^T)^T
            = sum_j [N_j + c q_j^T + q_j c^T + s_j c c^T]
            = M_k + r_k v_k^T + v_k r_k^T + S_k r_k r_k^T

    with prefix sums M_k = sum (N_j - r_j q_j^T - q_j r_j^T + s_j r_j r_j^T),
    v_k = sum (q_j - s_j r_j) and S_k = sum s_j: one ``cumsum`` each. Positions are taken
    relative to the start, so the terms stay of the size of the result. Cross-checked against
    :func:`propagate_covariance_reference`.
    """
    ds = np.asarray(ds, dtype=np.float64).reshape(-1)
    dtheta = np.asarray(dtheta, dtype=np.float64).reshape(-1)
    p0 = np.zeros((3, 3)) if cov0 is None else np.asarray(cov0, dtype=np.float64).reshape(3, 3)
    x, y, _ = integrate_increments(ds, dtheta, Pose2(0.0, 0.0, theta_start))
    r = np.stack([-y, x, np.zeros_like(x)], axis=-1)  # (N+1, 3), r_0 = 0
    noise = np.concatenate([p0[None], increment_covariance(ds, dtheta, theta_start, robot, model)])

    q = noise[:, :, 2]  # N e3
    s = noise[:, 2, 2]
    rq = np.einsum("ni,nk->nik", r, q)
    m = np.cumsum(
        noise - rq - rq.transpose(0, 2, 1) + s[:, None, None] * np.einsum("ni,nk->nik", r, r),
        axis=0,
    )
    v = np.cumsum(q - s[:, None] * r, axis=0)
    big_s = np.cumsum(s)
    rv = np.einsum("ni,nk->nik", r, v)
    p = m + rv + rv.transpose(0, 2, 1) + big_s[:, None, None] * np.einsum("ni,nk->nik", r, r)
    return (p + p.transpose(0, 2, 1)) / 2  # exact symmetry despite round-off


def propagate_covariance_reference(
    ds: np.ndarray,
    dtheta: np.ndarray,
    theta_start: float,
    robot: RobotConfig,
    model: WheelErrorModel = WheelErrorModel(),
    cov0: np.ndarray | None = None,
) -> np.ndarray:
    """Step-by-step P_{i+1} = F_p P_i F_p^T + Q_i: the readable kernel the closed form is checked
    against (a Python loop over steps; for tests, not for logs)."""
    ds = np.asarray(ds, dtype=np.float64).reshape(-1)
    dtheta = np.asarray(dtheta, dtype=np.float64).reshape(-1)
    a, _, _ = _increment_jacobians(ds, dtheta, theta_start, robot.track_width)
    q = increment_covariance(ds, dtheta, theta_start, robot, model)
    out = np.empty((ds.size + 1, 3, 3))
    out[0] = np.zeros((3, 3)) if cov0 is None else np.asarray(cov0, dtype=np.float64)
    for i in range(ds.size):
        f_p = np.eye(3)
        f_p[:, 2] += a[i]
        out[i + 1] = f_p @ out[i] @ f_p.T + q[i]
    return out


class WheelOdometry:
    """Encoder counts one reading at a time -> the odom-frame base_link pose and its covariance.

    For a board or simulator that reports counts as it drives (the simulated drive train of
    ``navigate``, ``rgbdnav board``'s test drive, a tacho board's integrated RPM): nominal
    geometry, midpoint rule, the robot's wheel error model (``robot.wheel_error_*``). A whole log
    integrates at once with :func:`integrate_ticks` and :func:`propagate_covariance`.
    """

    def __init__(self, robot: RobotConfig, first: WheelTicks) -> None:
        self.robot = robot
        self.model = WheelErrorModel.from_robot(robot)
        self.last = first
        self.pose = np.zeros(3)  # odom starts at the robot's start (REP-105)
        self.covariance = np.zeros((3, 3))
        self.distance_m = 0.0

    def update(self, ticks: WheelTicks) -> np.ndarray:
        left = np.array([self.last.left, ticks.left])
        right = np.array([self.last.right, ticks.right])
        ds, dth = wheel_increments(left, right, self.robot)
        self.covariance = propagate_covariance(
            ds, dth, float(self.pose[2]), self.robot, self.model, cov0=self.covariance
        )[-1]
        x, y, yaw = integrate_increments(ds, dth, Pose2(*self.pose.tolist()))
        self.pose = np.array([x[-1], y[-1], float(wrap_angle(yaw[-1]))])
        self.distance_m += float(abs(ds[0]))
        self.last = ticks
        return self.pose
