"""Differential-drive wheel odometry: cumulative encoder counts -> planar poses.

For each interval between two encoder readings (nominal geometry)::

    dL, dR = dcounts * pi * wheel_diameter / ticks_per_revolution      [m]
    ds     = (dR + dL) / 2                                              [m]
    dtheta = (dR - dL) / track_width                                    [rad]
    x     += ds * cos(theta + dtheta / 2)        (midpoint integration)
    y     += ds * sin(theta + dtheta / 2)
    theta += dtheta

Everything is a cumulative sum, so a whole log integrates without a Python loop.
"""

from __future__ import annotations

import numpy as np

from sensors.config import RobotConfig
from sensors.types import NS_PER_S, Pose2

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


def wheel_twist(
    stamps_ns: np.ndarray, left: np.ndarray, right: np.ndarray, robot: RobotConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Body velocities (v [m/s], w [rad/s]) over each interval (N-1 values)."""
    ds, dtheta = wheel_increments(left, right, robot)
    dt = np.diff(np.asarray(stamps_ns, dtype=np.int64)) / NS_PER_S
    dt = np.where(dt > 0, dt, np.nan)
    return ds / dt, dtheta / dt
