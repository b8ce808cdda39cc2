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
2. **Navigator** (:class:`nav.navigator.Navigator`, the one ``rgbdnav navigate`` ticks in
   simulated time): the waypoint is its goal; it plans, follows (regulated pure pursuit on the
   estimate, speeds capped at ``live.max_linear_speed`` / ``live.max_angular_speed``), checks
   progress, replans and runs Nav2's recovery round, and smooths the command. The live run's
   settings on top: ``live.waypoint_timeout`` is the goal timeout, ``live.replan_period`` the
   replanning period; a waypoint the navigator fails or refuses is skipped and counted.
3. **Planner** on its own thread, like Nav2's planner server: the navigator asks and polls; it
   follows the old path meanwhile (periodic replan) or rests (first plan, blocked path, recovery).

The caller puts the collision monitor after the smoother; it keeps the last word before the board.
Nothing here blocks: behaviours are run one tick at a time, so the board always gets a command.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, replace

import numpy as np

from nav.costmap import Costmap, grid_values, resample_nearest
from nav.navigator import ImmediatePlanning, Navigator
from nav.planner import GridPlanner, PlanResult
from rgbdnav.config import Config
from sensors.types import NS_PER_S, LaserScan, Pose2
from slam.geometry import wrap_angle
from slam.occupancy_grid import UNKNOWN, GridGeometry, OccupancyGrid, integrate_scans

log = logging.getLogger(__name__)

REGROW_SLACK_M = 1.0  # [m] the costmap is regrown when the robot or a goal comes this near its edge


@dataclass(frozen=True)
class MapSnapshot:
    """The live map as the mapper holds it: keyframe scans and their optimised poses."""

    poses: np.ndarray  # (K, 3) [m, m, rad] scan-frame poses in the map
    scans: tuple[LaserScan, ...]


def nav_geometry(points_xy: np.ndarray, resolution: float, margin: float) -> GridGeometry:
    """The grid covering ``points_xy`` (N, 2) [m] grown by ``margin`` [m]."""
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    return GridGeometry.from_bounds(
        float(p[:, 0].min()),
        float(p[:, 1].min()),
        float(p[:, 0].max()),
        float(p[:, 1].max()),
        resolution=resolution,
        margin=margin,
    )


def near_edge(geometry: GridGeometry, xy: np.ndarray, slack: float) -> bool:
    """Whether any point (N, 2) [m] lies outside ``geometry`` shrunk by ``slack`` [m]."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    x0, y0 = geometry.origin_x + slack, geometry.origin_y + slack
    x1 = geometry.origin_x + geometry.width * geometry.resolution - slack
    y1 = geometry.origin_y + geometry.height * geometry.resolution - slack
    return bool(np.any((p[:, 0] < x0) | (p[:, 0] > x1) | (p[:, 1] < y0) | (p[:, 1] > y1)))


def live_nav_config(cfg: Config) -> Config:
    """The nav sections with the live run's speed limits on top (``live.max_linear_speed``,
    ``live.max_angular_speed``), the smoother stepped at the controller rate, and the live
    run's goal timeout and replanning period (``live.waypoint_timeout``, ``live.replan_period``)."""
    lc = cfg.live
    v, w = lc.max_linear_speed, lc.max_angular_speed
    fol = cfg.follower
    desired = min(fol.desired_linear_vel, v)
    follower = replace(
        fol,
        desired_linear_vel=desired,
        regulated_linear_scaling_min_speed=min(fol.regulated_linear_scaling_min_speed, desired),
        rotate_to_heading_angular_vel=min(fol.rotate_to_heading_angular_vel, w),
        controller_frequency=lc.control_rate,
    )
    sm = cfg.smoother
    smoother = replace(
        sm,
        smoothing_frequency=lc.control_rate,
        max_velocity=(min(sm.max_velocity[0], v), 0.0, min(sm.max_velocity[2], w)),
        min_velocity=(max(sm.min_velocity[0], -v), 0.0, max(sm.min_velocity[2], -w)),
    )
    navigate = replace(
        cfg.navigate, goal_timeout=lc.waypoint_timeout, replan_frequency=1.0 / lc.replan_period
    )
    return replace(cfg, follower=follower, smoother=smoother, navigate=navigate)


class ThreadPlanning:
    """The navigator's plans made on a planner thread (:class:`nav.navigator.Planning`): the
    latest request wins, its answer waits for the navigator's poll; the tick never waits."""

    def __init__(self, planner: GridPlanner) -> None:
        self.planner = planner
        self.plan_ms: deque[float] = deque(maxlen=1000)  # recent planning times
        self._lock = threading.Lock()
        self._ticket = 0
        self._request: (
            tuple[int, np.ndarray, GridGeometry, tuple[float, float], tuple[float, float]] | None
        ) = None
        self._answer: tuple[int, PlanResult] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="live-nav-plan", daemon=True)

    def request(
        self,
        costs: np.ndarray,
        geometry: GridGeometry,
        start: tuple[float, float],
        goal: tuple[float, float],
    ) -> int:
        with self._lock:
            self._ticket += 1
            self._request = (self._ticket, costs, geometry, start, goal)
            ticket = self._ticket
        self._wake.set()
        return ticket

    def poll(self, ticket: int) -> PlanResult | None:
        with self._lock:
            if self._answer is None or self._answer[0] != ticket:
                return None
            return self._answer[1]

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                req, self._request = self._request, None
            if req is None or self._stop.is_set():
                continue
            t0 = time.perf_counter()
            res = self.planner.plan(*req[1:])
            self.plan_ms.append(1e3 * (time.perf_counter() - t0))
            with self._lock:
                self._answer = (req[0], res)


class LiveNavigator:
    """Route waypoints, one after the other, as goals of one :class:`nav.navigator.Navigator`
    on a costmap built from the live map.

    Threads: :meth:`add_scan` (front end) and :meth:`set_map` (mapper) only queue their input;
    :meth:`tick` (controller) does the work; a builder thread turns map snapshots into costmaps
    and a planner thread makes the plans.
    """

    def __init__(
        self,
        cfg: Config,
        route: np.ndarray,
        start_pose: np.ndarray,
        repeat: bool = False,
        static_map: tuple[OccupancyGrid, float, float] | None = None,
        plan_in_thread: bool = True,
        keepout: OccupancyGrid | None = None,
    ) -> None:
        self.cfg = live_nav_config(cfg)
        self.route = np.asarray(route, dtype=np.float64).reshape(-1, 2)
        self.repeat = repeat
        self._counts: Counter[str] = Counter()  # waypoints, map builds
        self.build_ms: deque[float] = deque(maxlen=1000)  # recent costmap builds
        self.tick_ms: deque[float] = deque(maxlen=1000)  # recent controller ticks
        self.tick_ms_max = 0.0
        self.i = 0  # the waypoint being driven to
        self.done = len(self.route) == 0
        self._lock = threading.Lock()
        self._scans: deque[tuple[int, LaserScan, Pose2]] = deque(
            maxlen=max(1, math.ceil(cfg.live.obstacle_memory * cfg.costmap.update_frequency))
        )
        self._new_scans: deque[tuple[int, LaserScan, Pose2]] = deque(maxlen=self._scans.maxlen)
        self._snapshot: MapSnapshot | None = None
        self._built: Costmap | None = None  # a new costmap from the builder, not yet in use
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._static = static_map
        self._keepout = keepout  # Nav2 keepout filter mask, in the map frame
        self._last_grid: tuple[OccupancyGrid, np.ndarray] | None = None  # (grid, its poses)
        pts = np.vstack([np.asarray(start_pose, dtype=np.float64)[:2], self.route])
        if static_map is not None:
            g = static_map[0].geometry
            corners = np.array(
                [
                    [g.origin_x, g.origin_y],
                    [g.origin_x + g.width * g.resolution, g.origin_y + g.height * g.resolution],
                ]
            )
            pts = np.vstack([pts, corners])
        self.geometry = nav_geometry(pts, self.cfg.costmap.resolution, cfg.live.nav_map_margin)
        self._last_scan_ns = -(2**62)
        self._builder = threading.Thread(target=self._build_loop, name="live-nav-map", daemon=True)
        planner = GridPlanner(self.cfg.planner)
        self.planning: ThreadPlanning | ImmediatePlanning = (
            ThreadPlanning(planner) if plan_in_thread else ImmediatePlanning(planner)
        )
        # All unknown until a map comes.
        self.nav = Navigator(self.cfg, self._costmap(), self.planning)
        if static_map is not None:
            self._install(self._costmap_from_grid(*static_map))

    @property
    def counts(self) -> Counter[str]:
        """The waypoint and map-building counts, and the navigator's (``nav_`` + its name)."""
        nav = Counter(
            {f"nav_{k}": v for k, v in self.nav.counts.items() if not k.startswith("goals_")}
        )
        return self._counts + nav

    @property
    def costmap(self) -> Costmap:
        return self.nav.costmap

    @property
    def path(self) -> np.ndarray | None:
        """(N, 3) the path being followed, None before the first plan to a waypoint."""
        return self.nav.path

    @property
    def plan_ms(self) -> deque[float]:
        return self.planning.plan_ms

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
        if isinstance(self.planning, ThreadPlanning):
            self.planning.start()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._builder.is_alive():
            self._builder.join(timeout=10.0)
        if isinstance(self.planning, ThreadPlanning):
            self.planning.close()

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
                log.warning(
                    "live navigation: map snapshot not integrated (%s: %s)", type(err).__name__, err
                )
                with self._lock:
                    self._counts["nav_map_build_errors"] += 1
                continue
            cm = self._costmap_from_grid(
                grid, self.cfg.mapper.occupied_thresh, self.cfg.mapper.free_thresh
            )
            self.build_ms.append(1e3 * (time.perf_counter() - t0))
            with self._lock:
                self._built = cm
                self._counts["nav_map_builds"] += 1

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
                grid = integrate_scans(
                    geom,
                    poses[len(old) :],
                    snap.scans[len(old) :],
                    self.cfg.mapper,
                    initial=last[0],
                )
                self._last_grid = (grid, np.vstack([old, poses[len(old) :]]))
                self._counts["nav_map_builds_incremental"] += 1
                return grid
        grid = integrate_scans(geom, poses, snap.scans, self.cfg.mapper)
        self._last_grid = (grid, poses.copy())
        return grid

    def _costmap_from_grid(
        self, grid: OccupancyGrid, occupied_thresh: float, free_thresh: float
    ) -> Costmap:
        values = grid_values(grid, self.cfg.costmap, occupied_thresh, free_thresh)
        if grid.geometry != self.geometry:
            values, _ = resample_nearest(values, grid.geometry, self.geometry, UNKNOWN)
        return self._costmap(values)

    def _costmap(self, values: np.ndarray | None = None) -> Costmap:
        """A costmap over the current geometry with the keepout filter (if any), inflated
        here, not on the controller thread."""
        cm = Costmap(self.geometry, self.cfg.costmap, values)
        if self._keepout is not None:
            cm.set_keepout(self._keepout)
        cm.master()
        return cm

    def _install(self, cm: Costmap) -> None:
        """A new static layer: the recent scans go into its obstacle layer again."""
        with self._lock:
            scans = list(self._scans)
            self._new_scans.clear()
        for _, scan, pose in scans:
            cm.update_scan(scan, pose)
        self.nav.costmap = cm

    def _regrow(self, xy: np.ndarray) -> None:
        """The robot or a goal neared the costmap's edge: cover it (a new, larger costmap)."""
        g = self.geometry
        corners = np.array(
            [
                [g.origin_x, g.origin_y],
                [g.origin_x + g.width * g.resolution, g.origin_y + g.height * g.resolution],
            ]
        )
        self.geometry = nav_geometry(
            np.vstack([corners, xy]), g.resolution, self.cfg.live.nav_map_margin
        )
        self._counts["nav_costmap_regrown"] += 1
        if self._static is not None:
            self._install(self._costmap_from_grid(*self._static))
        else:
            self._install(self._costmap())
            self._wake.set()  # the next snapshot is built on the new geometry

    # 3. The controller tick.

    def tick(
        self, now_ns: int, pose: np.ndarray | None, collision_stop: bool = False
    ) -> tuple[float, float]:
        """The smoothed (v, w) to command now for the estimated ``pose`` (None: unknown, stop);
        ``collision_stop``: the collision monitor cut the last command to a stop."""
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
        if pose is None or self.done:
            d = self.nav.hold(now_ns, (0.0, 0.0), "idle")
        else:
            pose = np.asarray(pose, dtype=np.float64)
            ends = np.vstack([pose[:2], self.route[self.i]])
            if near_edge(self.geometry, ends, REGROW_SLACK_M):
                self._regrow(ends)
            if not self.nav.active:
                goal = self.route[self.i]
                self.nav.set_goal((float(goal[0]), float(goal[1])), now_ns)
            d = self.nav.tick(now_ns, pose, collision_stop=collision_stop)
            if not self.nav.active:
                self._goal_ended()
        ms = 1e3 * (time.perf_counter() - t0)
        self.tick_ms.append(ms)
        self.tick_ms_max = max(self.tick_ms_max, ms)
        return d.v, d.w

    def _goal_ended(self) -> None:
        """Count how the navigator ended the waypoint and go on to the next one."""
        out = self.nav.outcome
        assert out is not None
        if out.status == "reached":
            self._counts["waypoints_reached"] += 1
        else:
            kind = {
                "timeout": "timeout",
                "no_path": "no_plan",
                "recoveries_exhausted": "no_plan",
            }.get(out.code, "failed")
            self._counts[f"waypoints_skipped_{kind}"] += 1
            log.warning("waypoint %d (%.2f, %.2f) skipped: %s", self.i, *out.goal, out.reason)
        self.i += 1
        if self.i >= len(self.route):
            if self.repeat:
                self.i = 0
                self._counts["route_laps"] += 1
            else:
                self.done = True

    def reset_motion(self) -> None:
        """Back to auto after manual driving: the smoother starts from rest, progress afresh."""
        self.nav.reset_motion()

    def stats(self) -> dict[str, object]:
        """Counts and timings for the run's summary."""
        out: dict[str, object] = dict(sorted(self.counts.items()))
        for name, ms in (
            ("nav_plan_ms_median", self.plan_ms),
            ("nav_map_build_ms_median", self.build_ms),
            ("nav_tick_ms_median", self.tick_ms),
        ):
            if ms:
                out[name] = round(float(np.median(np.fromiter(ms, float))), 2)
        out["nav_tick_ms_max"] = round(self.tick_ms_max, 2)
        out["nav_costmap_shape"] = list(self.geometry.shape)
        return out


__all__ = [
    "LiveNavigator",
    "MapSnapshot",
    "ThreadPlanning",
    "live_nav_config",
    "nav_geometry",
    "near_edge",
]
