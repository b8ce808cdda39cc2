"""Robot motion, encoders and gyro of the simulator."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sensors.config import RobotConfig, SimConfig
from sensors.sim.motion import (
    Trajectory,
    _backlash,
    blocked_step,
    diff_drive_step,
    drive_route,
    encoder_counts,
    gauss_markov_step,
    replay_tum,
    wheel_travel,
)
from sensors.sim.world import load_world
from sensors.types import NS_PER_S, Pose2
from slam.diff_drive import integrate_ticks, wheel_increments

REPO = Path(__file__).resolve().parents[3]
DATA = REPO.parent / "shared" / "data"
PIONEER = DATA / "tum" / "pioneer_groundtruth" / "pioneer_slam.groundtruth.txt"
ROBOT = RobotConfig()
PERFECT = replace(
    SimConfig(),
    wheel_diameter_error=(0.0, 0.0),
    track_width_error=0.0,
    wheel_slip=0.0,
    backlash=0.0,
)


@pytest.fixture(scope="module")
def house_route() -> Trajectory:
    return drive_route(load_world(REPO / "scenes" / "house.yaml"), SimConfig())


def test_route_respects_speed_and_acceleration_limits(house_route: Trajectory) -> None:
    sim = SimConfig()
    dt = 1 / sim.physics_rate
    assert np.abs(house_route.v).max() <= sim.max_linear_speed + 1e-9
    assert np.abs(house_route.w).max() <= sim.max_angular_speed + 1e-9
    assert np.abs(np.diff(house_route.v)).max() <= sim.max_linear_accel * dt + 1e-9
    assert np.abs(np.diff(house_route.w)).max() <= sim.max_angular_accel * dt + 1e-9


def test_route_visits_every_waypoint_and_ends_at_the_last(house_route: Trajectory) -> None:
    world = load_world(REPO / "scenes" / "house.yaml")
    xy = np.column_stack([house_route.x, house_route.y])
    for wp in world.route:
        assert np.min(np.linalg.norm(xy - wp, axis=1)) < SimConfig().waypoint_tolerance + 1e-6
    assert np.linalg.norm(xy[-1] - world.route[-1]) < 0.2


def test_perfect_encoders_integrate_back_to_the_ground_truth_path(house_route: Trajectory) -> None:
    left, right = encoder_counts(house_route, ROBOT, PERFECT, np.random.default_rng(0))
    x, y, yaw = integrate_ticks(
        left, right, ROBOT, Pose2(house_route.x[0], house_route.y[0], house_route.yaw[0])
    )
    # Only quantisation is left: 36 positions per turn of a 6-inch wheel = 13.3 mm per count, so
    # heading wobbles by up to 13.3 mm / 0.3 m = 0.044 rad; over 44 m that stays under 0.3 %.
    err = np.hypot(x - house_route.x, y - house_route.y)
    assert err.max() < 0.003 * house_route.length_m()
    assert abs(yaw[-1] - house_route.yaw[-1]) < 2 * ROBOT.metres_per_tick / ROBOT.track_width


def test_encoders_with_configured_errors_drift_as_configured(house_route: Trajectory) -> None:
    sim = replace(PERFECT, wheel_diameter_error=(0.01, 0.01))
    left, right = encoder_counts(house_route, ROBOT, sim, np.random.default_rng(0))
    ds, _ = wheel_increments(left, right, ROBOT)
    odom_length = ds.sum()  # the robot only drives forwards here
    # Wheels 1 % larger than nominal turn 1 % less, so odometry reports 1/1.01 of the distance.
    assert odom_length / house_route.length_m() == pytest.approx(1 / 1.01, abs=0.002)


def test_track_width_error_scales_integrated_rotation() -> None:
    # Spin in place by 4 pi.
    n = 2001
    yaw = np.linspace(0, 4 * math.pi, n)
    traj = Trajectory(
        np.arange(n, dtype=np.int64) * 5_000_000,
        np.zeros(n),
        np.zeros(n),
        yaw,
        np.zeros(n),
        np.full(n, 0.5),
    )
    sim = replace(PERFECT, track_width_error=0.05)
    left, right = encoder_counts(traj, ROBOT, sim, np.random.default_rng(0))
    _, _, odom_yaw = integrate_ticks(left, right, ROBOT)
    assert odom_yaw[-1] / yaw[-1] == pytest.approx(1.05, abs=0.01)


def test_backlash_adds_the_play_once_per_reversal() -> None:
    angle = np.concatenate([np.linspace(0, 1, 50), np.linspace(1, 0.2, 50)])
    motor = _backlash(angle, play=0.1)
    assert motor[49] - angle[49] == pytest.approx(0.05)
    assert motor[-1] - angle[-1] == pytest.approx(-0.05)
    assert np.array_equal(_backlash(angle, 0.0), angle)


def test_wheel_travel_splits_an_arc_between_the_wheels() -> None:
    n = 101
    radius, dtheta = 1.0, math.pi / 2
    th = np.linspace(0, dtheta, n)
    traj = Trajectory(
        np.arange(n, dtype=np.int64),
        radius * np.sin(th),
        radius * (1 - np.cos(th)),
        th,
        np.ones(n),
        np.ones(n),
    )
    s_left, s_right = wheel_travel(traj, track_width=0.3)
    assert s_left.sum() == pytest.approx((radius - 0.15) * dtheta, rel=1e-3)
    assert s_right.sum() == pytest.approx((radius + 0.15) * dtheta, rel=1e-3)


@pytest.mark.skipif(not PIONEER.is_file(), reason="../shared/data (TUM pioneer) not present")
def test_replayed_pioneer_trajectory_is_planar_and_plausible() -> None:
    traj = replay_tum(PIONEER, ROBOT, SimConfig())
    assert traj.t_ns[0] == 0
    assert 120 < traj.duration_s < 160
    assert 15 < traj.length_m() < 45
    # A Pioneer in a hall: under 1 m/s and 2 rad/s once mocap noise is smoothed.
    assert np.percentile(np.abs(traj.v), 99) < 1.0
    assert np.percentile(np.abs(traj.w), 99) < 2.0
    # Replayed encoders integrate back to the replayed path (no slip, no diameter error).
    left, right = encoder_counts(traj, ROBOT, PERFECT, np.random.default_rng(0))
    x, y, _ = integrate_ticks(left, right, ROBOT, Pose2(traj.x[0], traj.y[0], traj.yaw[0]))
    assert np.hypot(x[-1] - traj.x[-1], y[-1] - traj.y[-1]) < 0.1 * traj.length_m() / 10


def test_trajectory_truncation_keeps_the_start() -> None:
    traj = drive_route(load_world(REPO / "scenes" / "house.yaml"), SimConfig())
    short = traj.truncated(2.0)
    assert short.t_ns[-1] <= 2 * NS_PER_S and short.x[0] == traj.x[0]


def test_slip_noise_has_the_configured_sigma_and_correlation_time() -> None:
    from sensors.sim.motion import correlated_noise

    dt, tau = 0.005, 0.5
    x = correlated_noise(400_000, 0.01, tau, dt, np.random.default_rng(0))
    assert x.std() == pytest.approx(0.01, rel=0.05)
    lag = int(tau / dt)
    corr = np.corrcoef(x[:-lag], x[lag:])[0, 1]
    assert corr == pytest.approx(math.exp(-1), abs=0.05)


def test_slip_noise_is_scipys_lfilter_of_the_same_draws_to_the_bit() -> None:
    """correlated_noise runs the AR(1) recursion itself (importing scipy.signal cost ~1.5 s of
    a world run's start-up): the simulated wheels must stay the recordings' bit for bit."""
    from scipy.signal import lfilter

    from sensors.sim.motion import correlated_noise

    for n, tau in ((1, 0.5), (2, 0.5), (5000, 0.5), (5000, 1e-4), (5000, 1e4)):
        a = math.exp(-0.005 / tau)
        x = correlated_noise(n, 0.01, tau, 0.005, np.random.default_rng(n))
        rng = np.random.default_rng(n)
        white = rng.standard_normal(n) * 0.01 * math.sqrt(1 - a * a)
        white[0] = 0.01 * rng.standard_normal()
        assert np.array_equal(x, lfilter([1.0], [1.0, -a], white))


def test_a_route_the_robot_cannot_finish_in_time_names_the_waypoint(monkeypatch) -> None:
    import sensors.sim.motion as motion
    from sensors.types import WorldError

    monkeypatch.setattr(motion, "ROUTE_TIME_FACTOR", 0.05)  # far less time than the route needs
    stuck = r"house.yaml: the robot did not finish the route within \d+ s \(stuck before waypoint"
    with pytest.raises(WorldError, match=stuck):
        drive_route(load_world(REPO / "scenes" / "house.yaml"), SimConfig())


def test_replaying_a_single_pose_is_refused(tmp_path: Path) -> None:
    from sensors.types import WorldError

    one = tmp_path / "one.txt"
    one.write_text("1.0 0 0 0.5 0 0 0 1\n")
    with pytest.raises(WorldError, match="one.txt: a trajectory to replay needs at least 2 poses"):
        replay_tum(one, ROBOT, SimConfig())


def test_gauss_markov_steps_keep_the_stationary_sigma() -> None:
    rng = np.random.default_rng(0)
    x = np.zeros(20000)
    for _ in range(200):  # 40 correlation times of 0.5 s at 0.1 s steps
        x = gauss_markov_step(x, 0.02, 0.5, 0.1, rng.standard_normal(x.shape))
    assert float(x.std()) == pytest.approx(0.02, rel=0.05)


def test_diff_drive_step_drives_an_arc_of_the_wheel_radius() -> None:
    pose = np.zeros(3)
    track = 0.3
    # wheels 0.85 / 1.15 of 1 m: radius track / 2 * (R + L) / (R - L) = 0.15 * 2 / 0.3 = 1 m
    for _ in range(1000):
        pose = diff_drive_step(pose, 0.85 * math.pi / 2 / 1000, 1.15 * math.pi / 2 / 1000, track)
    np.testing.assert_allclose(pose, [1.0, 1.0, math.pi / 2], atol=1e-6)


def _wall_at_x(x_wall: float):
    """Free where the robot's centre keeps 0.2 m from a wall along x = ``x_wall``."""
    return lambda x, y: x <= x_wall - 0.2


def test_a_free_step_is_the_diff_drive_step_and_counts_all_travel() -> None:
    pose, left, right, outcome = blocked_step(np.zeros(3), 0.1, 0.12, 0.4, _wall_at_x(5.0), 0.2)
    assert outcome == "free" and (left, right) == (0.1, 0.12)
    np.testing.assert_allclose(pose, diff_drive_step(np.zeros(3), 0.1, 0.12, 0.4))


def test_head_on_into_a_wall_stalls_the_wheels_but_a_fraction_slips() -> None:
    start = np.array([4.8, 0.0, 0.0])  # touching the wall, facing it
    pose, left, right, outcome = blocked_step(start, 0.05, 0.05, 0.4, _wall_at_x(5.0), 0.2)
    assert outcome == "blocked"
    np.testing.assert_allclose(pose, start)
    assert left == pytest.approx(0.01) and right == pytest.approx(0.01)  # 20 % of 5 cm


def test_at_an_angle_the_robot_slides_along_the_wall_and_the_wheels_roll_its_forward_part() -> None:
    yaw = math.radians(45.0)
    start = np.array([4.8, 0.0, yaw])
    d = 0.1  # [m] straight ahead, both wheels
    pose, left, right, outcome = blocked_step(start, d, d, 0.4, _wall_at_x(5.0), 0.0)
    assert outcome == "slid"
    assert pose[0] == pytest.approx(4.8) and pose[1] == pytest.approx(d * math.sin(yaw))
    # Rolled d sin^2(45 deg) = d / 2 along the heading; with no slip the rest is not counted.
    assert left == pytest.approx(d / 2) and right == pytest.approx(d / 2)
    _, left_s, _, _ = blocked_step(start, d, d, 0.4, _wall_at_x(5.0), 1.0)
    assert left_s == pytest.approx(d)  # full slip: the old freely spinning wheels


def test_a_blocked_robot_still_turns_in_place() -> None:
    start = np.array([4.8, 0.0, 0.0])
    pose, left, right, outcome = blocked_step(start, 0.0, 0.04, 0.4, _wall_at_x(4.8), 0.2)
    assert outcome == "blocked"
    assert pose[:2] == pytest.approx(start[:2]) and pose[2] == pytest.approx(0.1)
    # The turn happened, so its wheel travel counts in full: ds_a = 0, right = +0.02, left = -0.02
    # achieved, plus 20 % of the refused forward 0.02 m.
    assert right == pytest.approx(0.02 + 0.2 * 0.02) and left == pytest.approx(-0.02 + 0.2 * 0.02)
