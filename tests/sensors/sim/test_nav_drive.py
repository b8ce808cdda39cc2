"""The simulated drive train of `rgbdnav navigate`: twists go to the Eddie board emulator as GOSPD
lines, the ground follows the wheels with the simulator's error model, and wheel odometry reads
the encoder counts back."""

from __future__ import annotations

import numpy as np
import pytest

from sensors.config import RobotConfig, SimConfig
from sensors.sim.nav_drive import EmulatedDrive
from slam.diff_drive import WheelOdometry

ROBOT = RobotConfig()  # Eddie: 0.1524 m wheels, 36 positions/rev, 0.3 m track
EXACT = SimConfig(wheel_diameter_error=(0.0, 0.0), track_width_error=0.0, wheel_slip=0.0)
STEP_NS = 50_000_000  # [ns] one smoother period at 20 Hz


def _drive(
    sim: SimConfig, v: float, w: float, seconds: float, seed: int = 0
) -> tuple[EmulatedDrive, WheelOdometry]:
    drive = EmulatedDrive(ROBOT, sim, np.zeros(3), np.random.default_rng(seed))
    odo = WheelOdometry(ROBOT, drive.ticks())
    for _ in range(round(seconds * 1e9 / STEP_NS)):
        drive.command(v, w)
        drive.advance(STEP_NS)
        odo.update(drive.ticks())
    return drive, odo


def test_twists_reach_the_board_as_gospd_in_positions_per_second() -> None:
    drive = EmulatedDrive(ROBOT, EXACT, np.zeros(3), np.random.default_rng(0))
    assert drive.command(0.5, 0.0) == (38, 38)  # 0.5 / (pi 0.1524 / 36) = 37.6
    assert drive.command(0.5, 0.0) == (38, 38)  # unchanged: no second line
    assert drive.command(0.0, 1.0) == (-11, 11)  # wheels -+ 0.15 m/s
    lines = [line for _, line in drive.board.commands()]
    assert lines == ["GOSPD 0026 0026", "GOSPD FFF5 000B"]
    assert drive.gospd_lines == 2


def test_wheel_speeds_are_capped_at_the_board_limit_keeping_the_turn_radius() -> None:
    drive = EmulatedDrive(ROBOT, EXACT, np.zeros(3), np.random.default_rng(0))
    left, right = drive.command(2.0, 2.0)  # wheels 1.7 / 2.3 m/s, robot.max_wheel_speed 0.9
    assert right == round(0.9 / ROBOT.metres_per_tick)
    assert left / right == pytest.approx(1.7 / 2.3, abs=0.02)


def test_without_errors_the_odometry_follows_the_true_pose_to_a_count() -> None:
    drive, odo = _drive(EXACT, 0.3, 0.4, 6.0)
    tick = ROBOT.metres_per_tick  # [m] one encoder position
    assert np.hypot(*(drive.pose[:2] - odo.pose[:2])) < 2 * tick
    assert abs(drive.pose[2] - odo.pose[2]) < 2 * tick / ROBOT.track_width
    # the board's speeds are whole positions/s: the commanded arc to within that quantisation
    r = drive.pose[:2]
    assert np.hypot(*r) > 1.0  # it moved along an arc of radius ~0.75 m


def test_a_larger_true_wheel_diameter_drives_further_than_the_odometry_says() -> None:
    sim = SimConfig(wheel_diameter_error=(0.02, 0.02), track_width_error=0.0, wheel_slip=0.0)
    drive, odo = _drive(sim, 0.4, 0.0, 5.0)
    assert drive.pose[0] == pytest.approx(1.02 * odo.pose[0], rel=5e-3)
    assert odo.distance_m == pytest.approx(odo.pose[0], abs=1e-9)


def test_slip_makes_the_odometry_drift_reproducibly_per_seed() -> None:
    sim = SimConfig(wheel_slip=0.05)
    a, odo_a = _drive(sim, 0.4, 0.2, 5.0, seed=3)
    b, _ = _drive(sim, 0.4, 0.2, 5.0, seed=3)
    c, _ = _drive(sim, 0.4, 0.2, 5.0, seed=4)
    np.testing.assert_array_equal(a.pose, b.pose)
    assert not np.allclose(a.pose, c.pose)
    assert np.hypot(*(a.pose[:2] - odo_a.pose[:2])) > ROBOT.metres_per_tick
