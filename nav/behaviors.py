"""Behaviours: Nav2's recovery actions (clear costmap, spin, wait, back up) and waypoint tasks.

Nav2 runs these from its behaviour tree when the planner or the controller fails
(``navigate_to_pose_w_replanning_and_recovery.xml``: clear the costmaps, ``Spin`` 1.57 rad,
``Wait`` 5 s, ``BackUp`` 0.30 m at 0.05 m/s, in round-robin) and from the waypoint follower's
task executors at each waypoint (``WaitAtWaypoint``, ``waypoint_pause_duration``). Here each
behaviour is a frozen description and :func:`behavior_twist` is a pure kernel: given where the
behaviour started, where the robot is now and how long it has run, the twist to command now, or
``None`` when it is over (done, out of ``time_allowance``, or blocked). The caller owns the loop,
the clock and the robot, as with the controller.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from sensors.types import ConfigError

BehaviorName = Literal["clear_costmap", "spin", "wait", "backup"]
FreeFn = Callable[[float, float], bool]

BACKUP_CHECK_AHEAD_M = 0.05  # [m] how far behind the robot a back-up step checks the costmap
SPIN_TOLERANCE_RAD = 0.02  # [rad] a spin within this of its target is done


@dataclass(frozen=True)
class Behavior:
    """One Nav2 behaviour with its parameters (names from nav2_behaviors' actions).

    ``target``: spin_dist [rad] (signed, |target| < pi, counter-clockwise positive), backup_dist
    [m] (positive), wait_duration [s]; unused for clear_costmap. ``speed``: the spin's angular
    speed [rad/s] or the back-up speed [m/s] (a magnitude). ``time_allowance`` [s] ends the
    behaviour even when the target is not reached.
    """

    name: BehaviorName
    target: float = 0.0
    speed: float = 0.0
    time_allowance: float = 10.0  # [s]

    def __post_init__(self) -> None:
        if self.name not in ("clear_costmap", "spin", "wait", "backup"):
            raise ConfigError(
                f"unknown behaviour {self.name!r} (clear_costmap, spin, wait, backup)"
            )
        if not self.time_allowance > 0.0:
            raise ConfigError(f"{self.name}: time_allowance must be > 0, got {self.time_allowance}")
        if self.name == "spin" and not (0.0 < abs(self.target) < math.pi and self.speed > 0.0):
            raise ConfigError(
                f"spin: need 0 < |spin_dist| < pi and speed > 0, got "
                f"{self.target} rad at {self.speed} rad/s"
            )
        if self.name == "backup" and not (self.target > 0.0 and self.speed > 0.0):
            raise ConfigError(
                f"backup: need backup_dist > 0 and backup_speed > 0, got "
                f"{self.target} m at {self.speed} m/s"
            )
        if self.name == "wait" and not self.target > 0.0:
            raise ConfigError(f"wait: wait_duration must be > 0, got {self.target}")

    @property
    def clears_costmap(self) -> bool:
        return self.name == "clear_costmap"


# Nav2's default recovery round (navigate_to_pose_w_replanning_and_recovery.xml).
RECOVERY_SEQUENCE: tuple[Behavior, ...] = (
    Behavior("clear_costmap"),
    Behavior("spin", target=1.57, speed=1.0, time_allowance=10.0),
    Behavior("wait", target=5.0, time_allowance=10.0),
    Behavior("backup", target=0.30, speed=0.05, time_allowance=10.0),
)


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def behavior_twist(
    behavior: Behavior,
    start: np.ndarray,
    pose: np.ndarray,
    elapsed_s: float,
    is_free: FreeFn | None = None,
) -> tuple[float, float] | None:
    """(v [m/s], w [rad/s]) to command now, or None when the behaviour is over.

    ``start`` and ``pose`` are (x, y, yaw) in one frame (the behaviour's start and now);
    ``is_free`` vets the ground just behind the robot before each back-up step (Nav2's
    collision check), a blocked back-up ends the behaviour.
    """
    b = behavior
    if b.name == "clear_costmap" or elapsed_s >= b.time_allowance:
        return None
    if b.name == "wait":
        return None if elapsed_s >= b.target else (0.0, 0.0)
    if b.name == "spin":
        turned = _wrap(float(pose[2] - start[2]))
        remaining = b.target - turned
        if abs(remaining) <= SPIN_TOLERANCE_RAD or remaining * b.target < 0.0:
            return None
        return 0.0, math.copysign(b.speed, b.target)
    # backup: straight back along the start heading
    travelled = math.hypot(float(pose[0] - start[0]), float(pose[1] - start[1]))
    if travelled >= b.target:
        return None
    if is_free is not None:
        yaw = float(pose[2])
        x = float(pose[0]) - BACKUP_CHECK_AHEAD_M * math.cos(yaw)
        y = float(pose[1]) - BACKUP_CHECK_AHEAD_M * math.sin(yaw)
        if not is_free(x, y):
            return None
    return -b.speed, 0.0


# --- waypoint following -----------------------------------------------------------------------


@dataclass(frozen=True)
class Waypoint:
    """A goal (x, y) [m] in the map and the task to run on arrival (nav2_waypoint_follower's
    task executor: ``None``, a wait of ``waypoint_pause_duration`` or a spin)."""

    x: float
    y: float
    task: Behavior | None = None


def wait_at_waypoint(pause_s: float) -> Behavior | None:
    """Nav2's WaitAtWaypoint plugin: pause ``waypoint_pause_duration`` [s] (0 = no task)."""
    if pause_s < 0.0:
        raise ConfigError(f"waypoint_pause_duration must be >= 0, got {pause_s}")
    return (
        None if pause_s == 0.0 else Behavior("wait", target=pause_s, time_allowance=pause_s + 1.0)
    )


def waypoints(goals: Sequence[Sequence[float]], task: Behavior | None = None) -> list[Waypoint]:
    """Goals [(x, y), ...] -> waypoints, each with the same task."""
    return [Waypoint(float(g[0]), float(g[1]), task) for g in goals]


def next_waypoint(statuses: Sequence[str], n: int, stop_on_failure: bool) -> int | None:
    """Index of the waypoint to drive next given the outcomes so far (nav2 waypoint follower):
    in order; after a failure only when ``stop_on_failure`` is false; None when done."""
    k = len(statuses)
    if k >= n:
        return None
    if stop_on_failure and any(s != "reached" for s in statuses):
        return None
    return k


# --- progress checking ------------------------------------------------------------------------


@dataclass(frozen=True)
class ProgressChecker:
    """nav2_controller SimpleProgressChecker: the robot must move ``required_movement_radius``
    [m] from where progress was last made within ``movement_time_allowance`` [s]."""

    required_movement_radius: float = 0.5  # [m]
    movement_time_allowance: float = 10.0  # [s]

    def moved(self, anchor: np.ndarray, pose: np.ndarray) -> bool:
        """Progress: the robot is outside the radius around ``anchor`` (re-anchor there)."""
        return (
            math.hypot(float(pose[0] - anchor[0]), float(pose[1] - anchor[1]))
            > self.required_movement_radius
        )

    def stuck(self, since_anchor_s: float) -> bool:
        return since_anchor_s > self.movement_time_allowance


__all__ = [
    "RECOVERY_SEQUENCE",
    "Behavior",
    "ProgressChecker",
    "Waypoint",
    "behavior_twist",
    "next_waypoint",
    "wait_at_waypoint",
    "waypoints",
]
