"""Auto mode of `rgbdnav live` through the navigation stack, as `rgbdnav navigate` wires it.

The route's waypoints are goals, one after the other; every controller tick (the live
controller thread, ``live.control_rate``):

1. **Costmap** (:class:`nav.costmap.Costmap`): the static layer is the map as it is now -- the
   live mapper's keyframe scans integrated into an occupancy grid by a background thread every
   ``live.nav_map_period`` (the mapper thread only hands over its keyframe poses and scans, so
   mapping never waits for it), or the loaded map with ``--map``. The obstacle layer marks and
   clears the live depth scans (at ``costmap.update_frequency``); on every new static layer the
   scans of the last ``live.obstacle_memory`` seconds are replayed into it. Unknown space stays
   unknown (``costmap.track_unknown_space``) and is traversable for the planner
   (``planner.allow_unknown``) and for the follower's arc check, as in Nav2 while mapping.
   The costmap covers the start, the route and the robot, grown by ``live.nav_map_margin``.
2. **Planner** (:class:`nav.planner.GridPlanner`) on its own thread, like Nav2's planner
   server beside the controller server: a path from the estimated pose to the waypoint, again
   every ``live.replan_period`` (Nav2's replanning behaviour tree) and whenever the path ahead
   is blocked by something the camera saw; the follower keeps the old path meanwhile.
3. **Follower**: regulated pure pursuit (:func:`nav.path_follower.compute_velocity`) on the
   estimate, speeds capped at ``live.max_linear_speed`` / ``live.max_angular_speed``.
4. **Behaviours** (:mod:`nav.behaviors`): a blocked arc runs the next of Nav2's recovery round
   (clear costmap, spin, wait, back up); no progress (``navigate.required_movement_radius`` in
   ``navigate.movement_time_allowance``) clears the costmap and backs up; a plan that fails runs
   the round until it succeeds. A waypoint not reached within ``live.waypoint_timeout``, or whose
   plans keep failing (``navigate.max_replans``), is skipped and counted.
5. **Smoother** (:class:`nav.velocity_smoother.VelocitySmoother`) ticked at the controller rate
   (its period is the controller's); the caller puts the collision monitor after it, which
   keeps the last word before the board.

Nothing here blocks: behaviours are run one tick at a time, so the board always gets a command.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from nav.behaviors import RECOVERY_SEQUENCE, Behavior, ProgressChecker, behavior_twist
from nav.costmap import Costmap, grid_values, inscribed_radius, resample_nearest
from nav.path_follower import compute_velocity
from nav.planner import GridPlanner, PlanResult, replan_needed
from nav.velocity_smoother import VelocitySmoother
from rgbdnav.config import Config
from sensors.types import LaserScan, Pose2
from slam.geometry import wrap_angle
from slam.occupancy_grid import UNKNOWN, GridGeometry, OccupancyGrid, integrate_scans

log = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
STUCK_BEHAVIORS = (RECOVERY_SEQUENCE[0], RECOVERY_SEQUENCE[3])  # clear the costmap, back up
REGROW_SLACK_M = 1.0  # [m] the costmap is regrown when the robot or a goal comes this near its edge


@dataclass(frozen=True)
class MapSnapshot:
    """The live map as the mapper holds it: keyframe scans and their optimised poses."""

    poses: np.ndarray  # (K, 3) [m, m, rad] scan-frame poses in the map
    scans: tuple[LaserScan, ...]


def nav_geometry(points_xy: np.ndarray, resolution: float, margin: float) -> GridGeometry:
    """The grid covering ``points_xy`` (N, 2) [m] grown by ``margin`` [m]."""
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    return GridGeometry.from_bounds(float(p[:, 0].min()), float(p[:, 1].min()),
                                    float(p[:, 0].max()), float(p[:, 1].max()),
                                    resolution=resolution, margin=margin)  # fmt: skip


def near_edge(geometry: GridGeometry, xy: np.ndarray, slack: float) -> bool:
    """Whether any point (N, 2) [m] lies outside ``geometry`` shrunk by ``slack`` [m]."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    x0, y0 = geometry.origin_x + slack, geometry.origin_y + slack
    x1 = geometry.origin_x + geometry.width * geometry.resolution - slack
    y1 = geometry.origin_y + geometry.height * geometry.resolution - slack
    return bool(np.any((p[:, 0] < x0) | (p[:, 0] > x1) | (p[:, 1] < y0) | (p[:, 1] > y1)))


def live_nav_config(cfg: Config) -> Config:
    """The nav sections with the live run's speed limits on top (``live.max_linear_speed``,
    ``live.max_angular_speed``) and the smoother stepped at the controller rate."""
    lc = cfg.live
    v, w = lc.max_linear_speed, lc.max_angular_speed
    fol = cfg.follower
    desired = min(fol.desired_linear_vel, v)
    follower = replace(fol, desired_linear_vel=desired,
                       regulated_linear_scaling_min_speed=min(
                           fol.regulated_linear_scaling_min_speed, desired),
                       rotate_to_heading_angular_vel=min(fol.rotate_to_heading_angular_vel, w),
                       controller_frequency=lc.control_rate)  # fmt: skip
    sm = cfg.smoother
    smoother = replace(sm, smoothing_frequency=lc.control_rate,
                       max_velocity=(min(sm.max_velocity[0], v), 0.0, min(sm.max_velocity[2], w)),
                       min_velocity=(max(sm.min_velocity[0], -v), 0.0,
                                     max(sm.min_velocity[2], -w)))  # fmt: skip
    return replace(cfg, follower=follower, smoother=smoother)


class LiveNavigator:
    """Route waypoints through costmap, planner, follower, behaviours and smoother.

    Threads: :meth:`add_scan` (front end) and :meth:`set_map` (mapper) only queue their input;
    :meth:`tick` (controller) does the work; a builder thread turns map snapshots into costmaps.
    """

    def __init__(self, cfg: Config, route: np.ndarray, start_pose: np.ndarray,
                 repeat: bool = False, static_map: tuple[OccupancyGrid, float, float] | None = None,
                 plan_in_thread: bool = True) -> None:  # fmt: skip
        self.cfg = live_nav_config(cfg)
        self.route = np.asarray(route, dtype=np.float64).reshape(-1, 2)
        self.repeat = repeat
        self.counts: Counter[str] = Counter()
        self.plan_ms: deque[float] = deque(maxlen=1000)  # recent planning times
        self.build_ms: deque[float] = deque(maxlen=1000)  # recent costmap builds
        self.tick_ms: deque[float] = deque(maxlen=1000)  # recent controller ticks
        self.tick_ms_max = 0.0
        self.i = 0  # the waypoint being driven to
        self.done = len(self.route) == 0
        self.path: np.ndarray | None = None  # (N, 3) current plan
        self._lock = threading.Lock()
        self._scans: deque[tuple[int, LaserScan, Pose2]] = deque(
            maxlen=max(1, math.ceil(cfg.live.obstacle_memory * cfg.costmap.update_frequency)))
        self._new_scans: deque[tuple[int, LaserScan, Pose2]] = deque(maxlen=self._scans.maxlen)
        self._snapshot: MapSnapshot | None = None
        self._built: Costmap | None = None  # a new costmap from the builder, not yet in use
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._static = static_map
        self._last_grid: tuple[OccupancyGrid, np.ndarray] | None = None  # (grid, its poses)
        pts = np.vstack([np.asarray(start_pose, dtype=np.float64)[:2], self.route])
        if static_map is not None:
            g = static_map[0].geometry
            corners = np.array([[g.origin_x, g.origin_y],
                                [g.origin_x + g.width * g.resolution,
                                 g.origin_y + g.height * g.resolution]])  # fmt: skip
            pts = np.vstack([pts, corners])
        self.geometry = nav_geometry(pts, self.cfg.costmap.resolution, cfg.live.nav_map_margin)
        self.costmap = Costmap(self.geometry, self.cfg.costmap)  # all unknown until a map comes
        self.planner = GridPlanner(self.cfg.planner)
        self.smoother = VelocitySmoother(self.cfg.smoother)
        self.progress = ProgressChecker(cfg.navigate.required_movement_radius,
                                        cfg.navigate.movement_time_allowance)  # fmt: skip
        self.inscribed = inscribed_radius(self.cfg.costmap)
        self._behaviors: list[Behavior] = []
        self._behavior: tuple[Behavior, np.ndarray, float] | None = None  # (what, start, t0 [s])
        self._goal_t0: float | None = None  # [s] when the current waypoint was started
        self._plan_t = -math.inf  # [s] last plan
        self._plan_failures = 0  # consecutive, for the current waypoint
        self._controller_failures = 0  # recovery round-robin position
        self._anchor: tuple[np.ndarray, float] | None = None  # progress checker
        self._last_scan_ns = -(2**62)
        self._builder = threading.Thread(target=self._build_loop, name="live-nav-map",
                                         daemon=True)  # fmt: skip
        # Planning: a request (goal tag, costs, geometry, start, goal) and its answer.
        self._plan_in_thread = plan_in_thread
        self._goal_tag = 0  # changes with the waypoint: answers for an old one are dropped
        self._plan_request: tuple[int, np.ndarray, GridGeometry, tuple[float, float],
                                  tuple[float, float]] | None = None  # fmt: skip
        self._plan_answer: tuple[int, PlanResult] | None = None
        self._plan_pending = False
        self._plan_wake = threading.Event()
        self._planner_thread = threading.Thread(target=self._plan_loop, name="live-nav-plan",
                                                daemon=True)  # fmt: skip
        if static_map is not None:
            self._install(self._costmap_from_grid(*static_map))

    # 1. Inputs from the other threads.

    def add_scan(self, scan: LaserScan, laser_pose_map: np.ndarray) -> None:
        """A live scan and its laser pose in the map, kept at ``costmap.update_frequency``."""
        if scan.stamp_ns - self._last_scan_ns < NS_PER_S / self.cfg.costmap.update_frequency:
            return
        self._last_scan_ns = scan.stamp_ns
        item = (scan.stamp_ns, scan, Pose2(*(float(v) for v in laser_pose_map)))
        with self._lock:
            self._scans.append(item)
            self._new_scans.append(item)

    def set_map(self, snapshot: MapSnapshot) -> None:
        """The mapper's keyframes now; the builder thread makes the next costmap from them."""
        with self._lock:
            self._snapshot = snapshot
        self._wake.set()

    def start(self) -> None:
        if self._static is None:
            self._builder.start()
        if self._plan_in_thread:
            self._planner_thread.start()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._plan_wake.set()
        for th in (self._builder, self._planner_thread):
            if th.is_alive():
                th.join(timeout=10.0)

    def _plan_loop(self) -> None:
        while not self._stop.is_set():
            self._plan_wake.wait()
            self._plan_wake.clear()
            with self._lock:
                req, self._plan_request = self._plan_request, None
            if req is None or self._stop.is_set():
                continue
            res = self._run_plan(*req[1:])
            with self._lock:
                self._plan_answer = (req[0], res)

    def _run_plan(self, costs: np.ndarray, geometry: GridGeometry, start: tuple[float, float],
                  goal: tuple[float, float]) -> PlanResult:  # fmt: skip
        t0 = time.perf_counter()
        res = self.planner.plan(costs, geometry, start, goal)
        self.plan_ms.append(1e3 * (time.perf_counter() - t0))
        return res

    # 2. The builder thread: snapshot -> occupancy grid -> costmap (static layer).

    def _build_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                snap, self._snapshot = self._snapshot, None
            if snap is None or self._stop.is_set() or not snap.scans:
                continue
            t0 = time.perf_counter()
            try:
                grid = self._integrate(snap)
            except Exception as err:  # a bad snapshot must not end the builder: counted, logged
                log.warning("live navigation: map snapshot not integrated (%s: %s)",
                            type(err).__name__, err)  # fmt: skip
                with self._lock:
                    self.counts["nav_map_build_errors"] += 1
                continue
            cm = self._costmap_from_grid(grid, self.cfg.mapper.occupied_thresh,
                                         self.cfg.mapper.free_thresh)  # fmt: skip
            self.build_ms.append(1e3 * (time.perf_counter() - t0))
            with self._lock:
                self._built = cm
                self.counts["nav_map_builds"] += 1

    def _integrate(self, snap: MapSnapshot) -> OccupancyGrid:
        """The snapshot as an occupancy grid on the costmap's geometry: only the new keyframes
        go into the last grid when the older ones have not moved (by half a cell or a
        comparable turn); a loop closure that moved them, or a new geometry, rebuilds it all."""
        geom, last = self.geometry, self._last_grid
        poses = np.asarray(snap.poses, dtype=np.float64).reshape(-1, 3)
        if last is not None and last[0].geometry == geom and 0 < len(last[1]) <= len(poses):
            old = last[1]
            d = poses[: len(old)] - old
            tol = 0.5 * geom.resolution  # [m]
            yaw_tol = tol / max(self.cfg.costmap.raytrace_max_range, 1.0)  # [rad] ~ tol at range
            turned = np.abs(wrap_angle(d[:, 2]))
            if np.all(np.hypot(d[:, 0], d[:, 1]) <= tol) and np.all(turned <= yaw_tol):
                if len(old) == len(poses):
                    return last[0]
                grid = integrate_scans(geom, poses[len(old):], snap.scans[len(old):],
                                       self.cfg.mapper, initial=last[0])  # fmt: skip
                self._last_grid = (grid, np.vstack([old, poses[len(old):]]))
                self.counts["nav_map_builds_incremental"] += 1
                return grid
        grid = integrate_scans(geom, poses, snap.scans, self.cfg.mapper)
        self._last_grid = (grid, poses.copy())
        return grid

    def _costmap_from_grid(self, grid: OccupancyGrid, occupied_thresh: float,
                           free_thresh: float) -> Costmap:  # fmt: skip
        values = grid_values(grid, self.cfg.costmap, occupied_thresh, free_thresh)
        if grid.geometry != self.geometry:
            values, _ = resample_nearest(values, grid.geometry, self.geometry, UNKNOWN)
        cm = Costmap(self.geometry, self.cfg.costmap, values)
        cm.master()  # inflate here, not on the controller thread
        return cm

    def _install(self, cm: Costmap) -> None:
        """A new static layer: the recent scans go into its obstacle layer again."""
        with self._lock:
            scans = list(self._scans)
            self._new_scans.clear()
        for _, scan, pose in scans:
            cm.update_scan(scan, pose)
        self.costmap = cm

    def _regrow(self, xy: np.ndarray) -> None:
        """The robot or a goal neared the costmap's edge: cover it (a new, larger costmap)."""
        g = self.geometry
        corners = np.array([[g.origin_x, g.origin_y],
                            [g.origin_x + g.width * g.resolution,
                             g.origin_y + g.height * g.resolution]])  # fmt: skip
        self.geometry = nav_geometry(np.vstack([corners, xy]), g.resolution,
                                     self.cfg.live.nav_map_margin)  # fmt: skip
        self.counts["nav_costmap_regrown"] += 1
        if self._static is not None:
            self._install(self._costmap_from_grid(*self._static))
        else:
            self._install(Costmap(self.geometry, self.cfg.costmap))
            self._wake.set()  # the next snapshot is built on the new geometry

    # 3. The controller tick.

    def is_free(self, x: float, y: float) -> bool:
        return bool(self.costmap.is_free(x, y, allow_unknown=self.cfg.planner.allow_unknown))

    def tick(self, now_ns: int, pose: np.ndarray | None) -> tuple[float, float]:
        """The smoothed (v, w) to command now for the estimated ``pose`` (None: unknown, stop)."""
        t0 = time.perf_counter()
        with self._lock:
            built, self._built = self._built, None
            new = list(self._new_scans)
            self._new_scans.clear()
        if built is not None and built.geometry == self.geometry:
            self._install(built)
        else:
            for _, scan, p in new:
                self.costmap.update_scan(scan, p)
        v, w = self._decide(now_ns / NS_PER_S, pose) if pose is not None else (0.0, 0.0)
        self.smoother.set_target((v, 0.0, w), now_ns)
        out = self.smoother.tick(now_ns)
        ms = 1e3 * (time.perf_counter() - t0)
        self.tick_ms.append(ms)
        self.tick_ms_max = max(self.tick_ms_max, ms)
        return out[0], out[2]

    def _decide(self, now: float, pose: np.ndarray) -> tuple[float, float]:
        """The controller's (v, w) before smoothing: behaviour, waypoint, plan, follow."""
        if self.done:
            return 0.0, 0.0
        if near_edge(self.geometry, np.vstack([pose[:2], self.route[self.i]]), REGROW_SLACK_M):
            self._regrow(np.vstack([pose[:2], self.route[self.i]]))
        # a. A behaviour (recovery) runs to its end before anything else.
        twist = self._behavior_step(now, pose)
        if twist is not None:
            return twist
        # b. The waypoint: reached, or given up after live.waypoint_timeout.
        goal = self.route[self.i]
        if self._goal_t0 is None:
            self._goal_t0 = now
        if math.hypot(*(goal - pose[:2])) <= self.cfg.follower.xy_goal_tolerance:
            self.counts["waypoints_reached"] += 1
            self._next_waypoint(now)
            return 0.0, 0.0
        if now - self._goal_t0 > self.cfg.live.waypoint_timeout:
            log.warning("waypoint %d (%.2f, %.2f) not reached in %.0f s: skipped", self.i, *goal,
                        self.cfg.live.waypoint_timeout)  # fmt: skip
            self.counts["waypoints_skipped_timeout"] += 1
            self._next_waypoint(now)
            return 0.0, 0.0
        # c. Progress: stuck for movement_time_allowance -> clear the costmap and back up.
        if self._anchor is None or self.progress.moved(self._anchor[0], pose):
            self._anchor = (pose.copy(), now)
        elif self.progress.stuck(now - self._anchor[1]):
            self.counts["nav_no_progress"] += 1
            self._anchor = (pose.copy(), now)
            self._start_behaviors(list(STUCK_BEHAVIORS), now, pose)
            self.path = None
            return 0.0, 0.0
        # d. Plan: periodically, when there is none, or when the path ahead got blocked.
        if self.path is not None and self._path_blocked(pose):
            self.counts["nav_replans_blocked_path"] += 1
            self.path = None
        tag = self._goal_tag
        self._plan_step(now, pose, goal)
        if self._goal_tag != tag:  # the waypoint was given up
            return 0.0, 0.0
        twist = self._behavior_step(now, pose)  # a failed plan starts a recovery
        if twist is not None:
            return twist
        if self.path is None:
            return 0.0, 0.0  # waiting for the first plan to this waypoint
        # e. Follow.
        cur = self.smoother.last_cmd
        cmd = compute_velocity(Pose2(*(float(v) for v in pose)), self.path, (cur[0], cur[2]),
                               self.cfg.follower,
                               cost_fn=lambda x, y: float(self.costmap.cost_at(x, y)),
                               is_free=self.is_free,
                               inscribed_radius_m=self.inscribed)  # fmt: skip
        if cmd.status == "blocked":
            # Nav2: FollowPath failed -> the next behaviour of the recovery round, then replan.
            self.counts["nav_follower_blocked"] += 1
            b = RECOVERY_SEQUENCE[self._controller_failures % len(RECOVERY_SEQUENCE)]
            self._controller_failures += 1
            self._start_behaviors([b], now, pose)
            self.path = None
            return 0.0, 0.0
        if cmd.status == "goal_reached":
            self.counts["waypoints_reached"] += 1
            self._next_waypoint(now)
            return 0.0, 0.0
        return cmd.v, cmd.w

    def _plan_step(self, now: float, pose: np.ndarray, goal: np.ndarray) -> None:
        """Ask for a plan when one is due; take the planner's answer when there is one."""
        due = self.path is None or now - self._plan_t >= self.cfg.live.replan_period
        if due and not self._plan_pending:
            self._plan_t = now
            req = (self._goal_tag, self.costmap.master().copy(), self.geometry,
                   (float(pose[0]), float(pose[1])), (float(goal[0]), float(goal[1])))  # fmt: skip
            self.counts["nav_plans"] += 1
            if not self._plan_in_thread:
                self._on_plan(self._run_plan(*req[1:]), now, pose, goal)
                return
            with self._lock:
                self._plan_request = req
            self._plan_pending = True
            self._plan_wake.set()
        if self._plan_in_thread:
            with self._lock:
                answer, self._plan_answer = self._plan_answer, None
            if answer is not None:
                self._plan_pending = False
                if answer[0] == self._goal_tag:
                    self._on_plan(answer[1], now, pose, goal)

    def _on_plan(self, res: PlanResult, now: float, pose: np.ndarray, goal: np.ndarray) -> None:
        if res.success:
            self.path, self._plan_failures = res.poses, 0
            return
        self.counts["nav_plan_failures"] += 1
        self._plan_failures += 1
        self.path = None
        log.debug("live navigation: no plan to waypoint %d: %s", self.i, res.reason)
        if self._plan_failures > self.cfg.navigate.max_replans:
            log.warning("waypoint %d (%.2f, %.2f): no plan after %d tries (%s): skipped", self.i,
                        *goal, self._plan_failures, res.reason)  # fmt: skip
            self.counts["waypoints_skipped_no_plan"] += 1
            self._next_waypoint(now)
        else:
            # Nav2: a failing planner runs the recovery round, one behaviour per failure.
            b = RECOVERY_SEQUENCE[(self._plan_failures - 1) % len(RECOVERY_SEQUENCE)]
            self._behaviors.append(b)

    def _path_blocked(self, pose: np.ndarray) -> bool:
        assert self.path is not None
        xy = self.path[:, :2]
        d = np.hypot(xy[:, 0] - pose[0], xy[:, 1] - pose[1])
        k = int(np.argmin(d))
        ahead = xy[k:][d[k:] > self.inscribed]  # the robot's own inflated footprint excepted
        return replan_needed(ahead, self.costmap.master(), self.geometry, self.cfg.planner)

    def _start_behaviors(self, behaviors: Sequence[Behavior], now: float,
                         pose: np.ndarray) -> None:  # fmt: skip
        self._behaviors.extend(behaviors)
        self._behavior_step(now, pose)

    def _behavior_step(self, now: float, pose: np.ndarray) -> tuple[float, float] | None:
        """The running behaviour's twist, starting queued ones as the last ends; None when idle."""
        while True:
            if self._behavior is None:
                if not self._behaviors:
                    return None
                b = self._behaviors.pop(0)
                self.counts[f"nav_behavior_{b.name}"] += 1
                if b.clears_costmap:
                    self.costmap.reset_obstacles()
                    continue
                self._behavior = (b, pose.copy(), now)
            b, start, t0 = self._behavior
            twist = behavior_twist(b, start, pose, now - t0, self.is_free)
            if twist is not None:
                return twist
            self._behavior = None
            self._anchor = (pose.copy(), now)  # progress is judged afresh after a behaviour

    def _next_waypoint(self, now: float) -> None:
        self.i += 1
        self._goal_tag += 1
        self.path, self._goal_t0, self._plan_failures = None, now, 0
        self._controller_failures = 0
        self._behaviors.clear()
        self._behavior = None
        if self.i >= len(self.route):
            if self.repeat:
                self.i = 0
                self.counts["route_laps"] += 1
            else:
                self.done = True

    def reset_motion(self) -> None:
        """Back to auto after manual driving: the smoother starts from rest, progress afresh."""
        self.smoother = VelocitySmoother(self.cfg.smoother)
        self._anchor = None

    def stats(self) -> dict[str, object]:
        """Counts and timings for the run's summary."""
        out: dict[str, object] = dict(sorted(self.counts.items()))
        for name, ms in (("nav_plan_ms_median", self.plan_ms),
                         ("nav_map_build_ms_median", self.build_ms),
                         ("nav_tick_ms_median", self.tick_ms)):  # fmt: skip
            if ms:
                out[name] = round(float(np.median(np.fromiter(ms, float))), 2)
        out["nav_tick_ms_max"] = round(self.tick_ms_max, 2)
        out["nav_costmap_shape"] = list(self.geometry.shape)
        return out


__all__ = ["LiveNavigator", "MapSnapshot", "live_nav_config", "nav_geometry", "near_edge"]
