"""One navigator, ticked by simulated time (``rgbdnav navigate``) or wall time (``rgbdnav live``).

Goal -> plan -> follow -> progress check -> replan -> recoveries -> outcome, Nav2's
``navigate_to_pose_w_replanning_and_recovery`` behaviour tree flattened into a state machine
that never blocks: each :meth:`Navigator.tick` decides one command and returns it smoothed
(nav2_velocity_smoother), so the caller's loop, clock, sensing and robot stay the caller's.

- **Plan** on the costmap the caller keeps up to date; a failed first plan clears what the camera
  saw once, and a robot standing in the inscribed band runs the recovery round to get out; a
  goal still without a path is *refused*.
- **Follow** with regulated pure pursuit (controller_server at ``follower.controller_frequency``);
  the follower's goal checker (``xy_goal_tolerance``, ``yaw_goal_tolerance``) says *reached*.
  An estimate in the inscribed band is no refusal: the planner plans out of it (NavFn's
  ``clearRobotCell``), and on that way out the arc check only stops the robot for walls.
- **Replan** when the path ahead is blocked (checked as the costmap changes), when the arc is
  blocked (FollowPath fails: the next recovery of the round first), when no progress is made
  (SimpleProgressChecker: ``required_movement_radius`` within ``movement_time_allowance``, or
  ``collision_hold_allowance`` of the caller's collision monitor stopping it: clear, back up),
  and every ``1 / navigate.replan_frequency`` s. A replan whose plans fail runs the round (clear,
  spin, wait, back up) one behaviour per failure; a goal that looks blocked fails at once.
  ``navigate.max_replans`` replans, an exhausted round or ``navigate.goal_timeout`` fail the goal.
- **Settle** (optional, :class:`PoseCorrector`): at a goal the estimate reaches, when the
  localiser keeps disagreeing with its scans, and when the caller's collision monitor stopped the
  robot (``collision_stop``), turn in place and let the caller correct the pose.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from nav.behaviors import RECOVERY_SEQUENCE, Behavior, ProgressChecker, behavior_twist
from nav.config import (
    CostmapConfig,
    FollowerConfig,
    NavigateConfig,
    PlannerConfig,
    SmootherConfig,
)
from nav.costmap import INSCRIBED, LETHAL, Costmap, inscribed_radius
from nav.path_follower import compute_velocity
from nav.planner import GridPlanner, PlanResult, points_passable, replan_needed
from nav.velocity_smoother import VelocitySmoother
from sensors.types import NS_PER_S, Pose2
from slam.occupancy_grid import GridGeometry

log = logging.getLogger(__name__)

STUCK_BEHAVIORS = (RECOVERY_SEQUENCE[0], RECOVERY_SEQUENCE[3])  # clear the costmap, back up
STOP_EPS = 1e-3  # [m/s, rad/s] smoothed speeds below this count as at rest
MAX_STOP_S = 10.0  # [s] longest braking waited for before going on anyway
SETTLE_SEGMENT_RAD = 3.0  # [rad] longest spin of a goal settle (a Spin turns less than pi)
SETTLE_TIME_FACTOR = 2.0  # [-] a settle spin's time allowance: this x its nominal duration, +1 s
MAX_ACTIONS_PER_TICK = 64  # instant actions (clear costmap, immediate plans) chained in one tick

OutcomeStatus = Literal["reached", "failed", "refused"]
OutcomeCode = Literal[
    "reached",
    "no_path",
    "timeout",
    "max_replans",
    "goal_blocked",
    "recoveries_exhausted",
    "cancelled",
]


class NavSections(Protocol):
    """The config sections the navigator reads (``rgbdnav.config.Config`` has them all)."""

    @property
    def costmap(self) -> CostmapConfig: ...
    @property
    def planner(self) -> PlannerConfig: ...
    @property
    def follower(self) -> FollowerConfig: ...
    @property
    def smoother(self) -> SmootherConfig: ...
    @property
    def navigate(self) -> NavigateConfig: ...


class Planning(Protocol):
    """Where plans are made: at once (:class:`ImmediatePlanning`) or on a planner thread."""

    def request(
        self,
        costs: np.ndarray,
        geometry: GridGeometry,
        start: tuple[float, float],
        goal: tuple[float, float],
    ) -> int: ...
    def poll(self, ticket: int) -> PlanResult | None: ...


class PoseCorrector(Protocol):
    """The localisation side of a goal settle (``navigate.goal_settle_spin``)."""

    def settle_due(self, gated_scans: int) -> bool:
        """A scan since the last call made the run of gated matches reach ``gated_scans``."""
        ...

    def begin_settle(self) -> None:
        """The settle turn starts now (the robot is at rest)."""
        ...

    def finish_settle(self) -> str:
        """The turn is over: correct the pose from its scans; the reason."""
        ...


class ImmediatePlanning:
    """Plans on the caller's thread: the answer is there as soon as it is asked for."""

    def __init__(self, planner: GridPlanner) -> None:
        self.planner = planner
        self._ticket = 0
        self._answer: tuple[int, PlanResult] | None = None
        self.plan_ms: deque[float] = deque(maxlen=1000)  # recent planning times

    def request(
        self,
        costs: np.ndarray,
        geometry: GridGeometry,
        start: tuple[float, float],
        goal: tuple[float, float],
    ) -> int:
        self._ticket += 1
        t0 = time.perf_counter()
        self._answer = (self._ticket, self.planner.plan(costs, geometry, start, goal))
        self.plan_ms.append(1e3 * (time.perf_counter() - t0))
        return self._ticket

    def poll(self, ticket: int) -> PlanResult | None:
        if self._answer is None or self._answer[0] != ticket:
            return None
        return self._answer[1]


@dataclass(frozen=True)
class Drive:
    """One tick's smoothed command and what the navigator is doing."""

    v: float  # [m/s]
    w: float  # [rad/s]
    status: str  # idle, planning, driving, stopping, settling, behavior:<name>


@dataclass(frozen=True)
class Outcome:
    """How a goal ended, and why (Nav2's NavigateToPose result with the reason spelled out)."""

    goal: tuple[float, float]  # [m] in the map
    status: OutcomeStatus
    code: OutcomeCode
    reason: str  # "" when reached
    replans: int
    recoveries: tuple[str, ...]  # behaviours run as recoveries, in order
    settles: tuple[str, ...]  # the pose corrector's reasons, one per settle
    first_plan: np.ndarray | None  # (N, 2) [m] the first path followed
    start_ns: int
    end_ns: int
    end_pose: np.ndarray | None  # (3,) the pose estimate when the goal ended (None: never ticked)

    @property
    def planned_length_m(self) -> float | None:
        if self.first_plan is None or len(self.first_plan) < 2:
            return None
        return float(np.hypot(*np.diff(self.first_plan, axis=0).T).sum())


def path_ahead(path_xy: np.ndarray, xy: np.ndarray, skip_m: float) -> np.ndarray:
    """The part of a path after the point nearest ``xy``, without points within ``skip_m`` of it
    (the robot's own inflated footprint would invalidate them)."""
    d = np.hypot(path_xy[:, 0] - xy[0], path_xy[:, 1] - xy[1])
    k = int(np.argmin(d))
    rest = path_xy[k:]
    return rest[d[k:] > skip_m]


def past_escape(path_xy: np.ndarray, passable: np.ndarray) -> np.ndarray:
    """``path_xy`` without its leading run of points where ``passable`` (N,) is false: the
    planner's way out of the inflated band when the robot's estimate stands in it (blocked
    when planned, so no new obstacle)."""
    if passable.all():
        return path_xy
    return path_xy[int(np.argmax(passable)) if passable.any() else len(path_xy) :]


def settle_spins(angle: float, speed: float) -> list[Behavior]:
    """A settle turn of ``angle`` [rad] at ``speed`` [rad/s] as Spin behaviours (each < pi)."""
    n = math.ceil(angle / SETTLE_SEGMENT_RAD)
    seg = angle / n
    return [
        Behavior(
            "spin", target=seg, speed=speed, time_allowance=SETTLE_TIME_FACTOR * seg / speed + 1.0
        )
    ] * n


# The action queue: what runs before following resumes. Each kind is a small record.
@dataclass
class _Stop:
    t0_ns: int | None = None


@dataclass
class _Run:
    behavior: Behavior
    role: Literal["recovery", "settle", "task"]
    start: np.ndarray | None = None
    t0_ns: int = 0


@dataclass
class _Settle:
    begin: bool  # True: the turn starts; False: it is over, correct the pose


@dataclass
class _Plan:
    kind: Literal["first", "first_cleared", "first_round", "replan", "settle"]
    why: str = ""
    round: int = 0  # recovery behaviours run so far in this attempt
    ticket: int | None = None


_Action = _Stop | _Run | _Settle | _Plan


@dataclass
class _Goal:
    xy: tuple[float, float]
    start_ns: int
    replans: int = 0
    recoveries: list[str] = field(default_factory=list)
    settles: list[str] = field(default_factory=list)
    first_plan: np.ndarray | None = None
    controller_failures: int = 0  # recovery round-robin position of FollowPath failures
    goal_settles: int = 0
    collision_settles: int = 0  # settles after a collision-monitor stop


class Navigator:
    """Drives to one goal at a time; :meth:`tick` once per smoother period with the pose
    estimate (x, y, yaw) in the costmap's frame. ``moving``: the caller's wheels still turn
    though the smoothed command is zero (a stop waits for them)."""

    def __init__(
        self,
        cfg: NavSections,
        costmap: Costmap,
        planning: Planning | None = None,
        corrector: PoseCorrector | None = None,
    ) -> None:
        self.cfg = cfg
        self.costmap = costmap  # the caller may swap in a new one (live: a new static layer)
        self.planning = planning or ImmediatePlanning(GridPlanner(cfg.planner))
        self.corrector = corrector
        self.smoother = VelocitySmoother(cfg.smoother)
        self.progress = ProgressChecker(
            cfg.navigate.required_movement_radius, cfg.navigate.movement_time_allowance
        )
        self.inscribed = inscribed_radius(cfg.costmap)  # [m]
        self.ctrl_ns = round(NS_PER_S / cfg.follower.controller_frequency)
        f = cfg.navigate.replan_frequency
        self.replan_ns = round(NS_PER_S / f) if f > 0.0 else None
        nav = cfg.navigate
        can_settle = corrector is not None and nav.goal_settle_spin > 0.0
        self.settle_max = nav.goal_settle_attempts if can_settle else 0
        self.counts: Counter[str] = Counter()
        self.controller_cycles = 0
        self.velocity = (0.0, 0.0)  # [m/s, rad/s] the last smoothed output
        self.target = (0.0, 0.0)  # [m/s, rad/s] the last command before smoothing
        self.path: np.ndarray | None = None  # (N, 3) the path being followed
        self.outcome: Outcome | None = None  # of the last goal, once it has ended
        self._goal: _Goal | None = None
        self._actions: deque[_Action] = deque()
        self._cmd = (0.0, 0.0)  # the controller's last command, held between cycles
        self._next_ctrl_ns = 0
        # Progress checker: (pose, time, held_ns then); held_ns: how long the collision monitor
        # has cut the command to a stop in all (the tick intervals it reported a stop for).
        self._anchor: tuple[np.ndarray, int, int] | None = None
        self.held_ns = 0
        self._tick_ns: int | None = None  # the last tick's time
        hold = cfg.navigate.collision_hold_allowance
        self.hold_ns = round(hold * NS_PER_S) if hold > 0.0 else None
        self._escape = False  # the path starts with the planner's way out of the band
        self._planned_ns = 0  # last (re)plan, for replan_frequency
        self._periodic: int | None = None  # ticket of a periodic plan in flight
        self._pose: np.ndarray | None = None  # the last estimate ticked with
        self._path_checked: tuple[int, int, int] | None = None  # (costmap, revision, path) ids
        self._collision_stop = False  # the caller's collision monitor stopped the last command

    # 1. Goals.

    @property
    def active(self) -> bool:
        """A goal is being driven to."""
        return self._goal is not None

    @property
    def busy(self) -> bool:
        """A goal, or a behaviour started with :meth:`run_task`, is still running."""
        return self._goal is not None or bool(self._actions)

    def set_goal(self, goal: tuple[float, float], now_ns: int) -> None:
        """Drive to ``goal`` (x, y) [m] from now on; a goal still running is replaced."""
        self._goal = _Goal((float(goal[0]), float(goal[1])), now_ns)
        self._actions.clear()
        self._actions.append(_Plan("first"))
        self.path, self.outcome, self._anchor, self._periodic = None, None, None, None
        self._escape = False
        self._next_ctrl_ns = self._planned_ns = now_ns
        self._cmd = (0.0, 0.0)

    def cancel(self, now_ns: int, reason: str) -> Outcome | None:
        """End the running goal as failed with ``reason`` (the caller's: lost localisation)."""
        if self._goal is None:
            return None
        return self._finish(now_ns, "failed", "cancelled", reason)

    def run_task(self, behavior: Behavior) -> None:
        """Run a behaviour outside any goal (a waypoint task); :attr:`busy` until it ends."""
        self._actions.append(_Run(behavior, "task"))

    def reset_motion(self) -> None:
        """After the caller drove by other means: the smoother from rest, progress afresh."""
        self.smoother = VelocitySmoother(self.cfg.smoother)
        self.velocity = (0.0, 0.0)
        self._anchor = None

    # 2. The tick.

    def tick(
        self, now_ns: int, pose: np.ndarray, moving: bool = False, collision_stop: bool = False
    ) -> Drive:
        """The smoothed command for now at the estimated ``pose``. ``collision_stop``: the
        collision monitor cut the last command's forward motion (what the camera saw is in the
        way, where the map pose saw free space)."""
        self._pose = np.asarray(pose, dtype=np.float64).copy()
        self._collision_stop = collision_stop
        if collision_stop and self._tick_ns is not None:
            self.held_ns += now_ns - self._tick_ns
        self._tick_ns = now_ns
        v, w, status = self._decide(now_ns, self._pose, moving)
        return self._smooth(now_ns, v, w, status)

    def hold(self, now_ns: int, twist: tuple[float, float], status: str) -> Drive:
        """Command ``twist`` for the caller this tick (turning in place to relocalise): smoothed,
        no decision taken but the goal timeout, progress judged afresh afterwards."""
        self._anchor = None
        g, timeout = self._goal, self.cfg.navigate.goal_timeout
        if g is not None and (now_ns - g.start_ns) / NS_PER_S > timeout:
            self._finish(now_ns, "failed", "timeout", f"timeout after {timeout:g} s")
            twist = (0.0, 0.0)
        return self._smooth(now_ns, twist[0], twist[1], status)

    def _smooth(self, now_ns: int, v: float, w: float, status: str) -> Drive:
        self.target = (v, w)
        self.smoother.set_target((v, 0.0, w), now_ns)
        out = self.smoother.tick(now_ns)
        self.velocity = (out[0], out[2])
        return Drive(out[0], out[2], status)

    def at_rest(self, moving: bool = False) -> bool:
        return max(abs(self.velocity[0]), abs(self.velocity[1])) < STOP_EPS and not moving

    def _decide(self, now_ns: int, pose: np.ndarray, moving: bool) -> tuple[float, float, str]:
        for _ in range(MAX_ACTIONS_PER_TICK):
            if self._actions:
                twist = self._act(now_ns, pose, moving)
                if twist is not None:
                    return twist
                if self._actions:
                    continue  # an instant action ended: the next one
                # The queue ran empty: follow again, progress judged afresh, control now.
                self._set_anchor(pose, now_ns)
                self._next_ctrl_ns = now_ns
            if self._goal is None:
                return 0.0, 0.0, "idle"
            if not self._follow(now_ns, pose):
                continue  # something to do first (a replan, a settle) or the goal ended
            return *self._cmd, "driving"
        return 0.0, 0.0, "planning"  # instant actions keep coming: go on next tick

    # 3. Following.

    def _follow(self, now_ns: int, pose: np.ndarray) -> bool:
        """One follow step: True when the held command stands, False when actions were queued
        (or the goal ended)."""
        g = self._goal
        assert g is not None and self.path is not None
        nav = self.cfg.navigate
        if (now_ns - g.start_ns) / NS_PER_S > nav.goal_timeout:
            self._finish(now_ns, "failed", "timeout", f"timeout after {nav.goal_timeout:g} s")
            return False
        if (
            self.corrector is not None
            and self.settle_max > 0
            and nav.settle_on_gated_scans > 0
            and self.corrector.settle_due(nav.settle_on_gated_scans)
        ):
            # The localiser's estimate and its scans disagree: a wide look decides before the
            # robot drives on, on a pose that may be drifting; then plan again from there.
            self._queue_settle()
            self._actions.append(_Plan("settle"))
            return False
        if self._collision_stop and self.settle_max > 0 and g.collision_settles < self.settle_max:
            # The collision monitor stopped the robot before something the camera saw and the
            # costmap, at the estimated pose, did not have: the estimate is off (a door jamb
            # where the map pose puts the middle of the door). A wide look corrects it; then
            # plan again from there (docs/design/navigator.md, "Grazing a door jamb").
            g.collision_settles += 1
            self.counts["collision_stop_settles"] += 1
            self._queue_settle()
            self._actions.append(_Plan("settle"))
            return False
        self._periodic_replan(now_ns, pose)
        seen = (id(self.costmap), self.costmap.revision, id(self.path))
        if seen != self._path_checked and self._path_blocked(pose):
            self.counts["replans_blocked_path"] += 1
            return self._replan(now_ns, "path blocked by a new obstacle", "path")
        if self._anchor is None or self.progress.moved(self._anchor[0], pose):
            self._set_anchor(pose, now_ns)
        elif self.progress.stuck((now_ns - self._anchor[1]) / NS_PER_S):
            pc = self.progress
            self.counts["no_progress"] += 1
            self._set_anchor(pose, now_ns)
            return self._replan(
                now_ns,
                f"no progress: moved less than "
                f"{pc.required_movement_radius} m in "
                f"{pc.movement_time_allowance:g} s",
                "stuck",
            )
        elif self.hold_ns is not None and self.held_ns - self._anchor[2] >= self.hold_ns:
            # The collision monitor keeps cutting the command to a stop (a wall or a piece of
            # furniture too close beside or ahead): no progress can come of waiting for the full
            # allowance. Back up, so the camera sees it again, and plan around it.
            # (docs/design/navigator.md, "Held by the collision monitor")
            self.counts["no_progress_held"] += 1
            self._set_anchor(pose, now_ns)
            return self._replan(
                now_ns,
                f"no progress: the collision monitor held the robot for "
                f"{self.cfg.navigate.collision_hold_allowance:g} s",
                "stuck",
            )
        if now_ns < self._next_ctrl_ns - self.ctrl_ns // 2:
            return True
        self._next_ctrl_ns = max(self._next_ctrl_ns + self.ctrl_ns, now_ns - self.ctrl_ns)
        cmd = compute_velocity(
            Pose2(*(float(v) for v in pose)),
            self.path,
            self.velocity,
            self.cfg.follower,
            cost_fn=lambda x, y: float(self.costmap.cost_at(x, y)),
            is_free=self._arc_free_fn(pose),
            inscribed_radius_m=self.inscribed,
        )
        self.controller_cycles += 1
        if cmd.status == "goal_reached":
            self._cmd = (0.0, 0.0)
            if g.goal_settles < self.settle_max:
                # Reached as far as the estimate says: settle (a wide look corrects it), then
                # the next control cycle checks the goal again.
                g.goal_settles += 1
                self._queue_settle()
                return False
            self._finish(now_ns, "reached", "reached", "")
            return False
        if cmd.status == "blocked":
            # Nav2: FollowPath failed -> the next behaviour of the recovery round, then replan.
            self.counts["follower_blocked"] += 1
            self._cmd = (0.0, 0.0)
            return self._replan(now_ns, cmd.reason, "blocked")
        self._cmd = (cmd.v, cmd.w)
        return True

    def _periodic_replan(self, now_ns: int, pose: np.ndarray) -> None:
        """Nav2's rate-controlled ComputePathToPose: the costmap has changed since (obstacles
        seen, furniture where the map does not have it). A failed plan keeps the path."""
        if self._periodic is not None:
            res = self.planning.poll(self._periodic)
            if res is not None:
                self._periodic = None
                self._on_plan_counts(res)
                if res.success:
                    self._adopt(res)
        if (
            self._periodic is None
            and self.replan_ns is not None
            and now_ns - self._planned_ns >= self.replan_ns
        ):
            self._planned_ns = now_ns
            self._periodic = self._request(pose)
            res = self.planning.poll(self._periodic)
            if res is not None:
                self._periodic = None
                self._on_plan_counts(res)
                if res.success:
                    self._adopt(res)

    def _path_blocked(self, pose: np.ndarray) -> bool:
        """A cell of the path ahead (past the robot's own footprint and past the way out of
        the band it is escaping) is one the planner may no longer enter."""
        assert self.path is not None
        cm, pc = self.costmap, self.cfg.planner
        self._path_checked = (id(cm), cm.revision, id(self.path))
        ahead = path_ahead(self.path[:, :2], pose[:2], self.inscribed)
        if self._escaping(pose):
            ahead = past_escape(ahead, points_passable(ahead, cm.master(), cm.geometry, pc))
        return replan_needed(ahead, cm.master(), cm.geometry, pc)

    def _replan(self, now_ns: int, why: str, cause: Literal["path", "stuck", "blocked"]) -> bool:
        """A replan event: give up, or queue the recoveries its cause calls for and a plan."""
        g = self._goal
        assert g is not None
        nav = self.cfg.navigate
        if g.replans >= nav.max_replans:
            self._finish(
                now_ns,
                "failed",
                "max_replans",
                f"gave up after {nav.max_replans} replans; last: {why}",
            )
            return False
        if int(self.costmap.cost_at(*g.xy)) in (INSCRIBED, LETHAL):
            # Every plan would end there, so replanning cannot help.
            self._finish(
                now_ns,
                "failed",
                "goal_blocked",
                f"the camera sees an obstacle within the robot radius of the goal ({why})",
            )
            return False
        g.replans += 1
        self.counts["replans"] += 1
        log.debug("goal (%.2f, %.2f): replanning (%s)", *g.xy, why)
        if cause == "stuck":
            self._actions.append(_Stop())
            self._actions.extend(_Run(b, "recovery") for b in STUCK_BEHAVIORS)
        elif cause == "blocked":
            b = RECOVERY_SEQUENCE[g.controller_failures % len(RECOVERY_SEQUENCE)]
            g.controller_failures += 1
            self._actions.extend((_Stop(), _Run(b, "recovery")))
        self._actions.append(_Plan("replan", why))
        return False

    # 4. Actions: stops, behaviours, settles and plans, one tick at a time.

    def _act(self, now_ns: int, pose: np.ndarray, moving: bool) -> tuple[float, float, str] | None:
        """Run the first action; its twist, or None when it ended this tick (popped) and the next
        may run now (a settle's correction ends the tick: the pose must be read again)."""
        a = self._actions[0]
        if isinstance(a, _Stop):
            if a.t0_ns is None:
                a.t0_ns = now_ns
            if self.at_rest(moving) or (now_ns - a.t0_ns) / NS_PER_S > MAX_STOP_S:
                self._actions.popleft()
                return None
            return 0.0, 0.0, "stopping"
        if isinstance(a, _Run):
            b = a.behavior
            if a.start is None:
                a.start, a.t0_ns = pose.copy(), now_ns
                self.counts[f"behavior_{b.name}"] += 1
                if a.role == "recovery" and self._goal is not None:
                    self._goal.recoveries.append(b.name)
                if b.clears_costmap:
                    self.costmap.reset_obstacles()
                    self._actions.popleft()
                    return None
            twist = behavior_twist(b, a.start, pose, (now_ns - a.t0_ns) / NS_PER_S, self._free)
            if twist is not None:
                return *twist, f"behavior:{b.name}"
            self._actions.popleft()
            self._actions.appendleft(_Stop())  # a behaviour that moved ends at rest
            return None
        if isinstance(a, _Settle):
            self._actions.popleft()
            assert self.corrector is not None
            if a.begin:
                self.corrector.begin_settle()
            elif self._goal is not None:
                self._goal.settles.append(self.corrector.finish_settle())
                self.counts["settles"] += 1
                # The correction moved the estimate: this tick's pose is stale. What comes
                # next (the goal check, a plan from here) waits for the next tick's pose.
                if not self._actions:
                    self._anchor = None
                    self._next_ctrl_ns = now_ns
                return 0.0, 0.0, "settling"
            return None
        return self._plan_action(a, now_ns, pose)

    def _set_anchor(self, pose: np.ndarray, now_ns: int) -> None:
        self._anchor = (pose.copy(), now_ns, self.held_ns)

    def _queue_settle(self) -> None:
        nav = self.cfg.navigate
        self._actions.extend((_Stop(), _Settle(begin=True)))
        self._actions.extend(
            _Run(b, "settle")
            for b in settle_spins(nav.goal_settle_spin, nav.goal_settle_spin_speed)
        )
        self._actions.append(_Settle(begin=False))

    def _request(self, pose: np.ndarray) -> int:
        g = self._goal
        assert g is not None
        self.counts["plans"] += 1
        return self.planning.request(
            self.costmap.master().copy(),
            self.costmap.geometry,
            (float(pose[0]), float(pose[1])),
            g.xy,
        )

    def _on_plan_counts(self, res: PlanResult) -> None:
        if not res.success:
            self.counts["plan_failures"] += 1

    def _plan_action(
        self, a: _Plan, now_ns: int, pose: np.ndarray
    ) -> tuple[float, float, str] | None:
        """Ask for a plan, wait for it (at rest), then follow it or go on with the recoveries."""
        g = self._goal
        if g is None:
            self._actions.popleft()
            return None
        if a.ticket is None:
            self._periodic = None  # this plan supersedes one in flight
            a.ticket = self._request(pose)
        res = self.planning.poll(a.ticket)
        if res is None:
            return 0.0, 0.0, "planning"
        self._actions.popleft()
        self._on_plan_counts(res)
        self._planned_ns = now_ns
        if res.success:
            self._adopt(res)
            if g.first_plan is None:
                g.first_plan = res.poses[:, :2].copy()
            return None
        round_ = RECOVERY_SEQUENCE
        if a.kind == "settle":
            return None  # the old path stays
        if a.kind == "first" and self.costmap.obstacle_count() > 0:
            # Maybe only what the camera saw blocks it: forget that once, as Nav2's recovery
            # would; no motion before a first plan.
            self._actions.extendleft([_Plan("first_cleared"), _Run(round_[0], "recovery")])
            return None
        if a.kind in ("first", "first_cleared"):
            if res.reason.startswith("start"):
                # The robot stands in an inflated (or lethal) cell: moving may free it.
                a = _Plan("first_round")
            else:
                self._finish(now_ns, "refused", "no_path", f"no path: {res.reason}")
                return None
        if a.round >= len(round_):
            if a.kind == "first_round":
                self._finish(now_ns, "refused", "no_path", f"no path: {res.reason}")
            else:
                self._finish(
                    now_ns,
                    "failed",
                    "recoveries_exhausted",
                    f"replan failed ({a.why}) after recoveries: {res.reason}",
                )
            return None
        # Nav2: a failing planner runs the recovery round, one behaviour per failure.
        self._actions.extendleft(
            [_Plan(a.kind, a.why, a.round + 1), _Run(round_[a.round], "recovery"), _Stop()]
        )
        return None

    def _adopt(self, plan: PlanResult) -> None:
        """Follow a new plan; note whether it starts with the planner's way out of an inscribed
        (or otherwise impassable, non-lethal) cell the estimate stands in."""
        cm = self.costmap
        self._escape = not bool(
            points_passable(plan.poses[:1, :2], cm.master(), cm.geometry, self.cfg.planner).all()
        )
        self.path = plan.poses

    def _escaping(self, pose: np.ndarray) -> bool:
        """Following a plan's way out of the cell the estimate stood in when it was made, and
        not out yet. (An estimate that drifts into the band while following an ordinary plan is
        not escaping: the controller's collision check stops it and the recoveries run.)"""
        if self._escape:
            self._escape = not self._free(float(pose[0]), float(pose[1]))
        return self._escape

    def _free(self, x: float, y: float) -> bool:
        return bool(self.costmap.is_free(x, y, allow_unknown=self.cfg.planner.allow_unknown))

    def _arc_free_fn(self, pose: np.ndarray) -> Callable[[float, float], bool]:
        """The controller's collision test. On the way out of the band the usual test (cost
        below INSCRIBED) would call every sample a collision, so only walls count."""
        if self._escaping(pose):
            return lambda x, y: int(self.costmap.cost_at(x, y)) < LETHAL
        return self._free

    def _finish(
        self, now_ns: int, status: OutcomeStatus, code: OutcomeCode, reason: str
    ) -> Outcome:
        g = self._goal
        assert g is not None
        self.outcome = Outcome(
            g.xy,
            status,
            code,
            reason,
            g.replans,
            tuple(g.recoveries),
            tuple(g.settles),
            g.first_plan,
            g.start_ns,
            now_ns,
            self._pose,
        )
        self.counts[f"goals_{status}"] += 1
        self._goal, self.path, self._periodic = None, None, None
        self._actions.clear()
        self._cmd = (0.0, 0.0)
        return self.outcome


__all__ = [
    "MAX_STOP_S",
    "STUCK_BEHAVIORS",
    "Drive",
    "ImmediatePlanning",
    "NavSections",
    "Navigator",
    "Outcome",
    "Planning",
    "PoseCorrector",
    "past_escape",
    "path_ahead",
    "settle_spins",
]
