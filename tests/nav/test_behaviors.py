"""Recovery behaviours (spin, back up, wait, clear), waypoint following and progress checking as
pure kernels: fed a pose, they say what to command and when they are done."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nav.behaviors import (
    RECOVERY_SEQUENCE,
    Behavior,
    ProgressChecker,
    behavior_twist,
    next_waypoint,
    wait_at_waypoint,
    waypoints,
)
from sensors.types import ConfigError

START = np.array([1.0, 2.0, 0.5])
DT = 0.05  # [s]


def _run(behavior: Behavior, free: bool = True, max_steps: int = 2000) -> tuple[np.ndarray, float]:
    """Integrate a behaviour's twists on a unicycle from START; (final pose, elapsed [s])."""
    pose, t = START.copy(), 0.0
    for _ in range(max_steps):
        twist = behavior_twist(behavior, START, pose, t, lambda x, y: free)
        if twist is None:
            return pose, t
        v, w = twist
        pose = pose + [v * DT * math.cos(pose[2]), v * DT * math.sin(pose[2]), w * DT]
        t += DT
    raise AssertionError("the behaviour never ended")


def test_nav2_default_recovery_round_is_clear_spin_wait_backup() -> None:
    assert [b.name for b in RECOVERY_SEQUENCE] == ["clear_costmap", "spin", "wait", "backup"]
    spin, wait, backup = RECOVERY_SEQUENCE[1:]
    assert (spin.target, wait.target, backup.target, backup.speed) == (1.57, 5.0, 0.30, 0.05)
    assert RECOVERY_SEQUENCE[0].clears_costmap and not spin.clears_costmap


def test_spin_turns_by_spin_dist_in_place() -> None:
    pose, t = _run(Behavior("spin", target=-1.2, speed=0.8))
    assert pose[:2] == pytest.approx(START[:2], abs=1e-12)
    assert pose[2] - START[2] == pytest.approx(-1.2, abs=0.8 * DT + 0.02)
    assert t == pytest.approx(1.2 / 0.8, abs=2 * DT)


def test_backup_drives_backup_dist_straight_back() -> None:
    pose, _ = _run(Behavior("backup", target=0.3, speed=0.05))
    d = pose[:2] - START[:2]
    assert float(np.hypot(*d)) == pytest.approx(0.3, abs=0.05 * DT + 1e-9)
    heading = np.array([math.cos(START[2]), math.sin(START[2])])
    assert float(d @ heading) < 0.0  # behind the robot
    assert pose[2] == START[2]


def test_backup_stops_when_the_ground_behind_is_not_free() -> None:
    pose, t = _run(Behavior("backup", target=0.3, speed=0.05), free=False)
    np.testing.assert_array_equal(pose, START)
    assert t == 0.0


def test_wait_commands_zero_for_wait_duration() -> None:
    b = Behavior("wait", target=2.0)
    assert behavior_twist(b, START, START, 1.99) == (0.0, 0.0)
    assert behavior_twist(b, START, START, 2.0) is None


def test_time_allowance_ends_a_spin_that_cannot_turn() -> None:
    b = Behavior("spin", target=1.0, speed=0.5, time_allowance=3.0)
    assert behavior_twist(b, START, START, 2.9) == (0.0, 0.5)
    assert behavior_twist(b, START, START, 3.0) is None  # never turned (stuck wheels)


def test_clear_costmap_has_no_motion() -> None:
    assert behavior_twist(Behavior("clear_costmap"), START, START, 0.0) is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"name": "dance"}, "unknown behaviour"),
        ({"name": "spin", "target": 4.0, "speed": 1.0}, "spin_dist"),
        ({"name": "backup", "target": 0.3, "speed": 0.0}, "backup_speed"),
        ({"name": "wait", "target": 0.0}, "wait_duration"),
        ({"name": "wait", "target": 1.0, "time_allowance": 0.0}, "time_allowance"),
    ],
)
def test_bad_behaviour_parameters_are_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        Behavior(**kwargs)


def test_waypoints_carry_the_wait_at_waypoint_task() -> None:
    task = wait_at_waypoint(3.0)
    assert task is not None and task.name == "wait" and task.target == 3.0
    assert wait_at_waypoint(0.0) is None
    wps = waypoints([(1, 2), (3.5, -1)], task)
    assert [(w.x, w.y, w.task) for w in wps] == [(1.0, 2.0, task), (3.5, -1.0, task)]
    with pytest.raises(ConfigError, match="waypoint_pause_duration"):
        wait_at_waypoint(-1.0)


def test_next_waypoint_goes_on_after_a_failure_unless_stop_on_failure() -> None:
    assert next_waypoint([], 3, stop_on_failure=True) == 0
    assert next_waypoint(["reached", "failed"], 3, stop_on_failure=False) == 2
    assert next_waypoint(["reached", "failed"], 3, stop_on_failure=True) is None
    assert next_waypoint(["reached"] * 3, 3, stop_on_failure=False) is None


def test_progress_checker_needs_the_radius_within_the_allowance() -> None:
    pc = ProgressChecker(required_movement_radius=0.5, movement_time_allowance=10.0)
    anchor = np.array([0.0, 0.0, 0.0])
    assert not pc.moved(anchor, np.array([0.3, 0.39, 1.0]))  # 0.495 m
    assert pc.moved(anchor, np.array([0.3, 0.41, 0.0]))
    assert not pc.stuck(10.0) and pc.stuck(10.01)
