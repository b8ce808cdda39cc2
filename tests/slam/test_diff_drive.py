"""Wheel odometry kinematics against analytic straight lines, arcs and spins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.config import RobotConfig
from sensors.types import Pose2
from slam.diff_drive import (
    integrate_increments,
    integrate_ticks,
    reject_encoder_glitches,
    wheel_twist,
)

ROBOT = RobotConfig()
TICK = ROBOT.metres_per_tick  # [m] 13.3 mm on Eddie


def test_eddie_resolution_is_pi_d_over_36() -> None:
    assert TICK == pytest.approx(math.pi * 0.1524 / 36)


def test_equal_counts_drive_straight_along_the_heading() -> None:
    ticks = np.arange(0, 101)
    x, y, yaw = integrate_ticks(ticks, ticks, ROBOT, Pose2(1.0, 2.0, math.pi / 2))
    assert x[-1] == pytest.approx(1.0) and y[-1] == pytest.approx(2.0 + 100 * TICK)
    assert yaw[-1] == pytest.approx(math.pi / 2)


def test_opposite_counts_spin_in_place() -> None:
    n = round(math.pi * ROBOT.track_width / 2 / TICK)  # counts for a half turn... per wheel
    ticks = np.arange(0, n + 1)
    x, y, yaw = integrate_ticks(-ticks, ticks, ROBOT)
    assert abs(x[-1]) < 1e-12 and abs(y[-1]) < 1e-12
    assert yaw[-1] == pytest.approx(2 * n * TICK / ROBOT.track_width)


def test_constant_ratio_counts_follow_a_circle_of_the_analytic_radius() -> None:
    # Wheel speeds in ratio (R - b/2) : (R + b/2) drive a circle of radius R.
    radius, steps = 1.0, 4000
    dtheta = 2 * math.pi / steps
    ds = radius * dtheta
    x, y, yaw = integrate_increments(np.full(steps, ds), np.full(steps, dtheta))
    assert x[-1] == pytest.approx(0.0, abs=1e-9) and y[-1] == pytest.approx(0.0, abs=1e-9)
    assert np.hypot(x, y - radius) == pytest.approx(np.full(steps + 1, radius), abs=1e-6)


def test_midpoint_integration_is_exact_for_a_single_arc_chord() -> None:
    # One big increment of a quarter circle lands on the chord end point exactly.
    radius, dtheta = 2.0, math.pi / 2
    chord = 2 * radius * math.sin(dtheta / 2)
    x, y, _ = integrate_increments(np.array([chord]), np.array([dtheta]))
    assert x[-1] == pytest.approx(radius) and y[-1] == pytest.approx(radius)


def test_twist_is_distance_over_time() -> None:
    stamps = np.array([0, 100_000_000, 200_000_000])
    v, w = wheel_twist(stamps, np.array([0, 10, 20]), np.array([0, 10, 30]), ROBOT)
    assert v[0] == pytest.approx(10 * TICK / 0.1)
    assert w[1] == pytest.approx(10 * TICK / ROBOT.track_width / 0.1)


def test_one_glitched_encoder_reading_is_dropped_not_integrated_as_300_km() -> None:
    robot = RobotConfig()
    t = np.arange(10, dtype=np.int64) * 20_000_000  # [ns] 50 Hz
    ticks = np.arange(10, dtype=np.int64)  # 1 tick per 20 ms: 0.67 m/s, under the 0.9 limit
    glitched = ticks.copy()
    glitched[4] += 2**31 - 5  # one reading with a flipped high bit
    clean = reject_encoder_glitches(t, glitched, ticks, robot)
    assert (clean.glitches_dropped, clean.jumps_zeroed) == (1, 0)
    assert list(clean.left) == [0, 1, 2, 3, 5, 6, 7, 8, 9] and len(clean.stamps_ns) == 9
    x, _, _ = integrate_ticks(clean.left, clean.right, robot)
    assert abs(x[-1] - 9 * robot.metres_per_tick) < 1e-9


def test_an_encoder_step_that_stays_is_taken_as_no_motion_and_counted() -> None:
    robot = RobotConfig()
    t = np.arange(10, dtype=np.int64) * 20_000_000
    ticks = np.arange(10, dtype=np.int64)
    reset = ticks.copy()
    reset[6:] -= 1000  # the board's counter was reset
    clean = reject_encoder_glitches(t, reset, ticks, robot)
    assert (clean.glitches_dropped, clean.jumps_zeroed) == (0, 1)
    assert list(clean.left) == [0, 1, 2, 3, 4, 5, 5, 6, 7, 8]
    same = reject_encoder_glitches(t, ticks, ticks, robot)  # nothing to clean: untouched
    assert (same.glitches_dropped, same.jumps_zeroed) == (0, 0) and (same.left == ticks).all()
