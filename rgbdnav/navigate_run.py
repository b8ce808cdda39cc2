"""`rgbdnav navigate`: drive to goals on a saved map, closed loop in a 2D simulation.

The robot lives in a simulator world (``sensors.sim.world``); the navigator only knows the map.
Each simulation step, in simulated time (never wall time):

1. At ``costmap.update_frequency`` a depth-camera scan (the camera's horizontal field of view
   and depth range, one beam per ``SCAN_COLUMNS_PER_BEAM`` image columns, Kinect range noise
   growing with z^2) is ray-cast against the world's floor plan at the true camera pose. With
   ``localization="localizer"`` (the default) it goes to the localiser
   (:class:`slam.localization.Localizer`, tracking against the map from the start pose it is
   given) with the wheel-odometry pose, which gives ``T_map_odom``; the navigator's pose is
   ``T_map_odom (+) odometry``. Whether a match far from the odometry prediction is believed
   is the localiser's call (``localizer.match_gate``: a jump hypothesis, confirmed by
   ``localizer.jump_confirm_scans`` agreeing matches and the recent scans stacked by odometry;
   ``localizer.dead_reckoning_max_sigma``: failing matches dead-reckon on odometry before
   "lost"). When the localiser does lose track the navigator puts it back on the odometry pose
   with its last covariance (``set_initial_pose``, as an operator would) instead of letting
   it search the whole map, since turning wheels mean the robot was not kidnapped -- or, with
   ``navigate.global_relocalization``, turns in place until the global search settles. A goal
   fails after ``relocalize_timeout`` without a believable answer. With ``"groundtruth"`` the
   navigator is handed the true pose.
   The scan then marks and clears the costmap's obstacle layer at the *estimated* pose, so
   obstacles that are in the world but not in the map appear; the path ahead is re-checked.
   With ``navigate.replan_frequency`` > 0 (Nav2's behaviour tree replans at 1 Hz) the path is
   also planned again at that rate on the costmap as it now is, so that it keeps the
   inflation's distance from what the camera has seen since (furniture moved since the map).
2. At ``follower.controller_frequency`` the regulated pure pursuit follower turns the path and
   the estimated pose into (v, w); ``blocked``, an invalidated path or no progress
   (:class:`nav.behaviors.ProgressChecker`) triggers a replan (at most ``max_replans`` per
   goal); a blocked arc (the controller failing) first runs the next behaviour of Nav2's
   recovery round-robin (clear the costmap, spin, wait, back up), a replan that fails runs the
   round until one succeeds, and being stuck clears the costmap and backs up. An estimate in the
   inscribed band is not a refusal: the planner plans out of it (NavFn's ``clearRobotCell``),
   and while the robot follows that way out the controller's collision check only stops it for
   walls (lethal cells).
   **Settle** (``navigate.goal_settle_spin`` > 0, localizer mode): when the goal checker says
   "reached" (on the estimate), the robot stops, turns in place and the localiser fuses one
   match of the turn's scans stacked by odometry (:meth:`Localizer.match_recent`); the next
   control cycle checks the goal again and drives on to the corrected goal if needed (at most
   ``goal_settle_attempts`` settles per goal). A narrow depth scan fits moved furniture
   confidently off and the localiser's gate then holds the estimate there; the walls all round
   outweigh one piece of furniture. ``navigate.settle_on_gated_scans`` settles (and replans)
   while driving too, after that many gated matches in a row.
3. At ``smoother.smoothing_frequency`` the velocity smoother limits the command, which goes to
   the wheels as a ``GOSPD`` line through the Eddie board emulator; the true pose follows the
   wheels with diameter/track errors and slip, and wheel odometry integrates the encoder counts
   (:mod:`rgbdnav.nav_drive`).

A goal in a wall, a keepout zone, outside the map or unreachable is refused with a reason;
after every goal (reached or not) the robot is brought to rest, then the waypoint task (a pause)
runs. A collision is a step at which the true circular footprint (``costmap.robot_radius``)
overlaps an occupied floor-plan cell; a keepout entry a step at which the true robot centre is
in a keepout cell (the filter's semantics: the planner never puts the centre there). The run
directory holds:

``trajectory.tum``   the true base_link pose at every simulation step.
``estimated.tum``    the navigator's base_link pose (localiser or ground truth) at every step.
``commands.csv``     ``t_s,goal,status,cmd_v_mps,cmd_w_radps,smoothed_v_mps,smoothed_w_radps,
                     gospd_left,gospd_right`` (GOSPD in encoder positions/s).
``summary.json``     per-goal outcome with reason, collisions, keepout entries, localisation
                     error, distance driven, simulated time, control-step cost.
``map.png``          the map with each goal's first plan, the driven and the estimated path.
``velocity.png``     commanded vs smoothed velocity and acceleration with the smoother's limits.
``config.yaml``      the resolved configuration.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from nav.behaviors import (
    RECOVERY_SEQUENCE,
    Behavior,
    ProgressChecker,
    behavior_twist,
    next_waypoint,
    wait_at_waypoint,
    waypoints,
)
from nav.config import NavigateConfig
from nav.costmap import INSCRIBED, LETHAL, NO_INFORMATION, Costmap, inscribed_radius
from nav.path_follower import compute_velocity
from nav.planner import GridPlanner, PlanResult, points_passable, replan_needed
from nav.velocity_smoother import VelocitySmoother
from rgbdnav.config import Config, load_config
from rgbdnav.localize_run import LoadedMap, load_map
from rgbdnav.nav_charts import velocity_chart
from rgbdnav.nav_drive import EmulatedDrive, WheelOdometry
from rgbdnav.report import plot_trajectories
from rgbdnav.run_dir import RunDir
from rgbdnav.scan_stream import RGBD_PROFILE
from rgbdnav.visualize import Visualizer, log_run, make_visualizer, occupied_cells_xy
from sensors.atomic import atomic_write_text
from sensors.sim.world import FloorPlan, floor_plan, load_world
from sensors.tum import write_tum_trajectory
from sensors.types import ConfigError, LaserScan, MapError, Pose2
from slam.geometry import oplus, path_length, wrap_angle
from slam.localization import Localizer, MapModel
from slam.map_bundle import load_map_yaml
from slam.occupancy_grid import OccupancyGrid

log = logging.getLogger(__name__)

LOCALIZATION_MODES: tuple[str, ...] = ("groundtruth", "localizer")
NS_PER_S = 1_000_000_000
NAVIGATE_PROFILE = RGBD_PROFILE.with_name("navigate.yaml")  # localising on the robot's wheels
SCAN_COLUMNS_PER_BEAM = 2  # [px] image columns per simulated scan beam (640 px -> 320 beams)
RAY_STEP_CELLS = 0.5  # [cells] ray-marching step in the floor plan
STOP_EPS = 1e-3  # [m/s, rad/s] smoothed speeds below this count as at rest
MAX_STOP_S = 10.0  # [s] longest braking we simulate before giving up on "at rest"
STUCK_BEHAVIORS = (RECOVERY_SEQUENCE[0], RECOVERY_SEQUENCE[3])  # clear the costmap, back up
SETTLE_SEGMENT_RAD = 3.0  # [rad] longest spin of a goal settle (a Spin turns less than pi)
SETTLE_TIME_FACTOR = 2.0  # [-] a settle spin's time allowance: this x its nominal duration, +1 s
CSV_HEADER = ("t_s", "goal", "status", "cmd_v_mps", "cmd_w_radps", "smoothed_v_mps",
              "smoothed_w_radps", "gospd_left", "gospd_right")  # fmt: skip


# 1. Pure kernels ----------------------------------------------------------------------------


def cast_scan(
    plan: FloorPlan,
    pose: np.ndarray,
    angles: np.ndarray,
    range_min: float,
    range_max: float,
) -> np.ndarray:
    """(N,) float32 ranges [m] of beams at ``angles`` [rad, laser frame] from ``pose`` (x, y, yaw)
    marched through the occupied cells of ``plan``: +inf = no return within ``range_max``, NaN =
    a return closer than ``range_min`` (a depth camera sees nothing there). Outside the floor plan
    is free space."""
    step = RAY_STEP_CELLS * plan.resolution  # [m]
    s = np.arange(1, math.ceil(range_max / step) + 2) * step  # (S,) [m] sample distances
    a = pose[2] + angles
    x = pose[0] + np.cos(a)[:, None] * s  # (N, S)
    y = pose[1] + np.sin(a)[:, None] * s
    col = np.floor((x - plan.origin_x) / plan.resolution).astype(np.int64)
    row = np.floor((y - plan.origin_y) / plan.resolution).astype(np.int64)
    h, w = plan.occupied.shape
    inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    hit = np.zeros(x.shape, dtype=bool)
    hit[inside] = plan.occupied[row[inside], col[inside]]
    any_hit = hit.any(axis=1)
    r = np.where(any_hit, s[np.argmax(hit, axis=1)], np.inf)
    r = np.where(r > range_max, np.inf, r)
    r = np.where(r < range_min, np.nan, r)
    return r.astype(np.float32)


def depth_range_sigma(
    ranges: np.ndarray, focal_px: float, baseline_m: float, disparity_sigma_px: float,
    subpixel: int,
) -> np.ndarray:  # fmt: skip
    """Kinect v1 range noise [m]: disparity noise and 1/``subpixel``-px quantisation through
    z = f b / d give sigma_z = z^2 sigma_d / (f b), sigma_d^2 = sigma_n^2 + (1/subpixel)^2 / 12."""
    sigma_d = math.sqrt(disparity_sigma_px**2 + (1.0 / subpixel) ** 2 / 12.0)  # [px]
    return np.asarray(ranges, dtype=np.float64) ** 2 * sigma_d / (focal_px * baseline_m)


def clearance_map(plan: FloorPlan) -> np.ndarray:
    """(H, W) distance [m] from each floor-plan cell centre to the nearest occupied cell centre."""
    from scipy.ndimage import distance_transform_edt

    return np.asarray(distance_transform_edt(~plan.occupied), dtype=np.float64) * plan.resolution


def clearance_at(plan: FloorPlan, dist: np.ndarray, x: float, y: float) -> float:
    """Clearance [m] of a point; outside the floor plan counts as unbounded free space."""
    row, col = plan.cell_of(np.array([[x, y]]))[0]
    h, w = dist.shape
    return float(dist[row, col]) if 0 <= row < h and 0 <= col < w else math.inf


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


# 2. Goal vetting ----------------------------------------------------------------------------


def goal_problem(
    goal: tuple[float, float],
    costmap: Costmap,
    loaded: LoadedMap,
    keepout: OccupancyGrid | None,
    allow_unknown: bool,
) -> str | None:
    """Why a goal must be refused before planning (wall, keepout, outside, unknown), or None."""
    x, y = goal
    g = costmap.geometry
    row, col = g.world_to_cell(x, y)
    if not bool(g.contains(row, col)):
        return f"goal ({x:.2f}, {y:.2f}) is outside the map"
    if bool(loaded.grid.occupied_mask(loaded.occupied_thresh)[row, col]):
        return f"goal ({x:.2f}, {y:.2f}) is in a wall (an occupied map cell)"
    if keepout is not None:
        kr, kc = keepout.geometry.world_to_cell(x, y)
        if bool(keepout.geometry.contains(kr, kc)) and bool(keepout.occupied_mask()[kr, kc]):
            return f"goal ({x:.2f}, {y:.2f}) is in a keepout zone"
    cost = int(costmap.cost_at(x, y))
    if cost == LETHAL:
        return f"goal ({x:.2f}, {y:.2f}) is on an obstacle seen by the camera"
    if cost == NO_INFORMATION and not allow_unknown:
        return f"goal ({x:.2f}, {y:.2f}) is in unknown space and planner.allow_unknown is false"
    return None


# 3. The simulation --------------------------------------------------------------------------


@dataclass
class _Log:
    stamps_ns: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)  # true base_link in the world
    estimates: list[np.ndarray] = field(default_factory=list)  # what the navigator believes
    rows: list[tuple[float, int, str, float, float, float, float, int, int]] = field(
        default_factory=list
    )
    loc_status: list[str] = field(default_factory=list)  # one per scan (localizer mode)
    loc_confidence: list[float] = field(default_factory=list)


class _Sim:
    """Holds the world, the robot (board emulator + slip), the navigator's costmap, localiser
    and clocks; one instance per run."""

    def __init__(
        self,
        cfg: Config,
        plan: FloorPlan,
        costmap: Costmap,
        start: np.ndarray,
        localizer: Localizer | None,
        keepout: OccupancyGrid | None,
        rng: np.random.Generator,
        nav: NavigateConfig,
    ) -> None:
        self.cfg, self.plan, self.costmap, self.rng, self.nav = cfg, plan, costmap, rng, nav
        self.progress = ProgressChecker(nav.required_movement_radius, nav.movement_time_allowance)
        self.dist = clearance_map(plan)
        self.radius = cfg.costmap.robot_radius  # [m]
        self.inscribed = inscribed_radius(cfg.costmap)  # [m]
        self.planner = GridPlanner(cfg.planner)
        self.smoother = VelocitySmoother(cfg.smoother)
        self.dt_ns = round(NS_PER_S / cfg.smoother.smoothing_frequency)
        self.ctrl_ns = round(NS_PER_S / cfg.follower.controller_frequency)
        self.scan_ns = round(NS_PER_S / cfg.costmap.update_frequency)
        cam = cfg.camera
        fov = 2.0 * math.atan(cam.width / (2.0 * cam.fx))  # [rad] horizontal field of view
        n = max(2, cam.width // SCAN_COLUMNS_PER_BEAM)
        self.angles = np.linspace(fov / 2, -fov / 2, n)[::-1].copy()  # ascending, REP-117
        r = cfg.robot
        self.T_base_laser = np.array([r.camera_x, r.camera_y, 0.0])
        # The robot: GOSPD into the board emulator, slip, encoder counts back.
        self.drive = EmulatedDrive(r, cfg.sim, start, rng)
        self.odometry = WheelOdometry(r, self.drive.ticks())
        self.localizer = localizer
        # odom starts at the start pose; the localiser is told the start (an initial pose).
        self.T_map_odom = np.asarray(start, dtype=np.float64).copy()
        if localizer is not None:
            localizer.set_initial_pose(oplus(start, self.T_base_laser))
        self.localized = True  # the localiser tracks (always, with ground truth)
        self.last_fix_ns = 0  # [ns] of the last believed localiser answer
        self.loc_covariance: np.ndarray | None = None  # of the last tracking answer
        self.reseeds = 0
        self.keepout_dist: np.ndarray | None = None
        self.keepout_geometry = None if keepout is None else keepout.geometry
        if keepout is not None:
            from scipy.ndimage import distance_transform_edt

            mask = keepout.occupied_mask()
            self.keepout_dist = np.asarray(distance_transform_edt(~mask)) * \
                keepout.geometry.resolution  # fmt: skip
        self.next_ctrl_ns = 0
        self.escape_plan = False  # the path followed starts with a way out of the band
        self.next_scan_ns = 0
        self.cmd = (0.0, 0.0)  # last controller command (v, w)
        self.vel = (0.0, 0.0)  # smoothed command being executed (v, w)
        self.collision_steps = 0
        self.collision_events = 0
        self.in_collision = False
        self.keepout_steps = 0
        self.keepout_events = 0
        self.in_keepout = False
        self.min_clearance = math.inf
        self.min_keepout_distance = math.inf
        self.scans = 0
        self.control_steps = 0
        self.control_s = 0.0  # [s] wall time in costmap updates + controller cycles
        self.log = _Log()
        self._record(-1, "start")

    @property
    def t_ns(self) -> int:
        return self.drive.t_ns

    @property
    def pose(self) -> np.ndarray:
        """The true base_link pose (the world's; the navigator never reads it in localizer
        mode)."""
        return self.drive.pose

    @property
    def estimate(self) -> np.ndarray:
        """The navigator's base_link pose in the map: T_map_odom (+) odometry, or the truth."""
        if self.localizer is None:
            return self.drive.pose.copy()
        return oplus(self.T_map_odom, self.odometry.pose)

    # 3a. Sensing.
    def sense(self) -> bool:
        """Scan when one is due: localise (localizer mode), then mark/clear the costmap at the
        estimated laser pose. True when it scanned."""
        if self.t_ns < self.next_scan_ns:
            return False
        self.next_scan_ns += self.scan_ns
        cam, sim = self.cfg.camera, self.cfg.sim
        true_laser = oplus(self.pose, self.T_base_laser)
        ranges = cast_scan(self.plan, true_laser, self.angles, cam.depth_min, cam.depth_max)
        sigma = depth_range_sigma(ranges, cam.disparity_focal, cam.baseline,
                                  sim.disparity_noise, sim.disparity_subpixel)  # fmt: skip
        finite = np.isfinite(ranges)
        ranges[finite] += (sigma[finite] * self.rng.standard_normal(int(finite.sum()))).astype(
            np.float32
        )
        inc = float(self.angles[1] - self.angles[0])
        scan = LaserScan(self.t_ns, float(self.angles[0]), inc, ranges, cam.depth_min,
                         cam.depth_max)  # fmt: skip
        if self.localizer is not None:
            self.localize(scan)
        self.costmap.update_scan(scan, Pose2(*oplus(self.estimate, self.T_base_laser).tolist()))
        self.scans += 1
        return True

    def localize(self, scan: LaserScan) -> None:
        """One scan into the localiser; T_map_odom from its answer while it tracks (see
        :class:`nav.config.NavigateConfig` ``global_relocalization`` for when it does not).
        Whether a match far from the odometry prediction is believed is the localiser's call
        (``localizer.match_gate``, ``localizer.jump_confirm_scans``)."""
        assert self.localizer is not None
        result = self.localizer.update(scan, oplus(self.odometry.pose, self.T_base_laser))
        self.log.loc_status.append(result.status)
        self.log.loc_confidence.append(result.confidence)
        if result.status == "tracking":
            self.T_map_odom = result.map_to_odom
            self.last_fix_ns = self.t_ns
            self.localized = True
            self.loc_covariance = result.covariance
        elif self.nav.global_relocalization:
            self.localized = False  # drive_to turns in place until it tracks again
        else:
            # The wheels report continuous motion, so the robot was not kidnapped: put the
            # localiser back on the odometry-propagated pose, with the covariance it last had
            # (a fresh, search-window-wide one would let the next match, maybe of moved
            # furniture, pull the estimate anywhere inside the window).
            self.localizer.set_initial_pose(oplus(self.estimate, self.T_base_laser),
                                            self.loc_covariance)  # fmt: skip
            self.reseeds += 1

    # 3b. Acting: one smoother period of motion.
    def command(self, v: float, w: float) -> None:
        """A controller output: the smoother's new target."""
        self.cmd = (v, w)
        self.smoother.set_target((v, 0.0, w), self.t_ns)

    def step(self, goal: int, status: str) -> None:
        out = self.smoother.tick(self.t_ns)
        self.vel = (out[0], out[2])
        self.drive.command(out[0], out[2])
        self.drive.advance(self.dt_ns)
        self.odometry.update(self.drive.ticks())
        x, y = float(self.pose[0]), float(self.pose[1])
        clear = clearance_at(self.plan, self.dist, x, y)
        self.min_clearance = min(self.min_clearance, clear)
        hit = clear < self.radius
        self.collision_steps += hit
        self.collision_events += hit and not self.in_collision
        self.in_collision = hit
        if self.keepout_dist is not None and self.keepout_geometry is not None:
            g = self.keepout_geometry
            row, col = g.world_to_cell(x, y)
            d = float(self.keepout_dist[row, col]) if bool(g.contains(row, col)) else math.inf
            self.min_keepout_distance = min(self.min_keepout_distance, d)
            inside = d == 0.0
            self.keepout_steps += inside
            self.keepout_events += inside and not self.in_keepout
            self.in_keepout = inside
        self._record(goal, status)

    def _record(self, goal: int, status: str) -> None:
        self.log.stamps_ns.append(self.t_ns)
        self.log.poses.append(self.pose.copy())
        self.log.estimates.append(self.estimate)
        self.log.rows.append((self.t_ns / NS_PER_S, goal, status, *self.cmd, *self.vel,
                              *self.drive.sent))  # fmt: skip

    def at_rest(self) -> bool:
        return max(abs(self.vel[0]), abs(self.vel[1])) < STOP_EPS and not np.any(
            self.drive.speeds
        )

    def stop(self, goal: int) -> None:
        """Command zero and let the smoother and the board bring the wheels to rest."""
        self.command(0.0, 0.0)
        for _ in range(math.ceil(MAX_STOP_S * NS_PER_S / self.dt_ns)):
            if self.at_rest():
                break
            self.step(goal, "stopping")

    # 3c. Planning.
    def make_plan(self, goal: tuple[float, float]) -> PlanResult:
        est = self.estimate
        return self.planner.plan(self.costmap.master().copy(), self.costmap.geometry,
                                 (float(est[0]), float(est[1])), goal)  # fmt: skip

    def run_behavior(self, k: int, behavior: Behavior) -> str:
        """Run one behaviour (a recovery or a waypoint task) to its end; its name."""
        if behavior.clears_costmap:
            self.costmap.reset_obstacles()
            return behavior.name
        start, t0 = self.estimate, self.t_ns
        while True:
            self.sense()
            twist = behavior_twist(behavior, start, self.estimate, (self.t_ns - t0) / NS_PER_S,
                                   lambda x, y: bool(self.costmap.is_free(x, y)))  # fmt: skip
            if twist is None:
                break
            self.command(*twist)
            self.step(k, f"behavior:{behavior.name}")
        self.stop(k)
        return behavior.name

    def settle_due(self) -> bool:
        """The localiser has gated ``navigate.settle_on_gated_scans`` matches in a row (and
        settling is on)."""
        n = self.nav.settle_on_gated_scans
        return (self.localizer is not None and n > 0 and self.nav.goal_settle_spin > 0.0
                and self.localizer.gated_streak >= n)  # fmt: skip

    def settle(self, k: int) -> str:
        """Goal settle (``navigate.goal_settle_spin``): stop, turn in place, and correct the
        pose with the turn's scans stacked by odometry (:meth:`Localizer.match_recent`); the
        localiser's reason."""
        assert self.localizer is not None
        self.stop(k)
        scans0 = self.scans
        angle, speed = self.nav.goal_settle_spin, self.nav.goal_settle_spin_speed
        n_seg = math.ceil(angle / SETTLE_SEGMENT_RAD)
        for _ in range(n_seg):
            seg = angle / n_seg
            spin = Behavior("spin", target=seg, speed=speed,
                            time_allowance=SETTLE_TIME_FACTOR * seg / speed + 1.0)  # fmt: skip
            self.run_behavior(k, spin)
        result = self.localizer.match_recent(self.scans - scans0)
        if result.status == "tracking":
            self.T_map_odom = result.map_to_odom
            self.last_fix_ns = self.t_ns
            self.loc_covariance = result.covariance
        return result.reason

    def adopt(self, plan: PlanResult) -> np.ndarray:
        """The poses of a new plan to follow; notes whether it starts with the planner's way out
        of an inscribed (or otherwise impassable, non-lethal) cell the estimate stands in."""
        self.escape_plan = not bool(
            points_passable(plan.poses[:1, :2], self.costmap.master(), self.costmap.geometry,
                            self.cfg.planner).all()  # fmt: skip
        )
        return plan.poses

    def escaping(self) -> bool:
        """Following a plan's way out of the cell the estimate stood in when it was made, and
        not out yet. (An estimate that drifts into the band while following an ordinary plan is
        not escaping: the controller's collision check stops it and the recoveries run.)"""
        if self.escape_plan:
            x, y = float(self.estimate[0]), float(self.estimate[1])
            allow = self.cfg.planner.allow_unknown
            self.escape_plan = not bool(self.costmap.is_free(x, y, allow_unknown=allow))
        return self.escape_plan

    def arc_free_fn(self) -> Callable[[float, float], bool]:
        """The controller's collision test. On the way out of the band the usual test (cost
        below INSCRIBED) would call every sample a collision, so only walls count."""
        if self.escaping():
            return lambda x, y: int(self.costmap.cost_at(x, y)) < LETHAL
        return lambda x, y: bool(self.costmap.is_free(x, y))

    def costmap_has_obstacles(self) -> bool:
        return bool(self.costmap.obstacle_count() > 0)

    def recover_and_replan(
        self, k: int, goal: tuple[float, float], outcome: dict[str, Any]
    ) -> PlanResult:
        """Plan again; while that fails, run Nav2's recovery round one behaviour at a time."""
        plan = self.make_plan(goal)
        for behavior in RECOVERY_SEQUENCE:
            if plan.success:
                break
            self.stop(k)
            outcome["recoveries"].append(self.run_behavior(k, behavior))
            plan = self.make_plan(goal)
        return plan

    def drive_to(
        self, k: int, goal: tuple[float, float], timeout_s: float, max_replans: int
    ) -> dict[str, Any]:
        """Plan to and follow one goal; its outcome (reached / failed / refused) with a reason."""
        cfg = self.cfg
        t0, travelled0 = self.t_ns, len(self.log.poses)
        outcome: dict[str, Any] = {"goal": list(goal), "replans": 0, "recoveries": []}
        self.last_fix_ns = max(self.last_fix_ns, t0)  # each goal gets relocalize_timeout
        plan = self.make_plan(goal)
        if not plan.success and self.costmap_has_obstacles():
            # Maybe only what the camera saw blocks it: forget that once, as Nav2's recovery
            # would; no motion before a first plan.
            outcome["recoveries"].append(self.run_behavior(k, RECOVERY_SEQUENCE[0]))
            plan = self.make_plan(goal)
        if not plan.success and plan.reason.startswith("start"):
            # The robot stands in an inflated (or lethal) cell: moving may free it.
            plan = self.recover_and_replan(k, goal, outcome)
        if not plan.success:
            outcome.update(status="refused", reason=f"no path: {plan.reason}")
            return outcome
        outcome["first_plan"] = plan.poses[:, :2]
        outcome["planned_length_m"] = round(plan.length_m, 3)
        path = self.adopt(plan)
        status, reason = "failed", ""
        anchor, anchor_ns = self.estimate, self.t_ns  # progress checker
        replan_ns = (round(NS_PER_S / self.nav.replan_frequency)
                     if self.nav.replan_frequency > 0.0 else None)  # fmt: skip
        planned_ns = self.t_ns
        controller_failures = 0  # recovery round-robin position
        settles = 0  # goal settles so far (navigate.goal_settle_spin)
        can_settle = self.localizer is not None and self.nav.goal_settle_spin > 0.0
        settle_max = self.nav.goal_settle_attempts if can_settle else 0
        while True:
            if (self.t_ns - t0) / NS_PER_S > timeout_s:
                reason = f"timeout after {timeout_s:g} s"
                break
            replan_why = ""
            w0 = time.perf_counter()
            if self.sense():
                if self.settle_due():
                    # The localiser's estimate and its scans disagree: a wide look decides
                    # before the robot drives on, on a pose that may be drifting.
                    self.control_s += time.perf_counter() - w0  # the scan, not the settle
                    outcome.setdefault("settles", []).append(self.settle(k))
                    plan = self.make_plan(goal)
                    if plan.success:
                        path = self.adopt(plan)
                    anchor, anchor_ns = self.estimate, self.t_ns
                    self.next_ctrl_ns = planned_ns = self.t_ns
                    continue
                if replan_ns is not None and self.t_ns - planned_ns >= replan_ns:
                    # Nav2's rate-controlled ComputePathToPose: the costmap has changed since
                    # (obstacles seen, furniture where the map does not have it).
                    planned_ns = self.t_ns
                    fresh = self.make_plan(goal)
                    if fresh.success:
                        path = self.adopt(fresh)
                ahead = path_ahead(path[:, :2], self.estimate[:2], self.inscribed)
                if self.escaping():
                    ok = points_passable(ahead, self.costmap.master(), self.costmap.geometry,
                                         cfg.planner)  # fmt: skip
                    ahead = past_escape(ahead, ok)
                if replan_needed(ahead, self.costmap.master(), self.costmap.geometry,
                                 cfg.planner):  # fmt: skip
                    replan_why = "path blocked by a new obstacle"
            est = self.estimate
            fix_age_s = (self.t_ns - self.last_fix_ns) / NS_PER_S
            if self.localizer is not None and fix_age_s > self.nav.relocalize_timeout:
                reason = (f"no believable localiser answer for {self.nav.relocalize_timeout:g} s "
                          f"(last status {self.log.loc_status[-1]})")  # fmt: skip
                self.control_s += time.perf_counter() - w0
                break
            if not self.localized:
                # Never drive on a pose the localiser does not vouch for: turn in place (new
                # views for the global relocalisation) until it tracks again.
                self.command(0.0, self.nav.relocalize_spin_speed)
                self.control_s += time.perf_counter() - w0
                self.step(k, "relocalising")
                anchor, anchor_ns = self.estimate, self.t_ns
                continue
            if self.progress.moved(anchor, est):
                anchor, anchor_ns = est, self.t_ns
            elif self.progress.stuck((self.t_ns - anchor_ns) / NS_PER_S):
                pc = self.progress
                replan_why = (f"no progress: moved less than {pc.required_movement_radius} m in "
                              f"{pc.movement_time_allowance:g} s")  # fmt: skip
                anchor, anchor_ns = est, self.t_ns
            if not replan_why and self.t_ns >= self.next_ctrl_ns:
                self.next_ctrl_ns += self.ctrl_ns
                cmd = compute_velocity(
                    Pose2(*est.tolist()), path, self.vel, cfg.follower,
                    cost_fn=lambda x, y: float(self.costmap.cost_at(x, y)),
                    is_free=self.arc_free_fn(),
                    inscribed_radius_m=self.inscribed,
                )  # fmt: skip
                self.control_steps += 1
                if cmd.status == "goal_reached" and settles < settle_max:
                    # Reached as far as the estimate says: settle (a wide look corrects it),
                    # then the next control cycle checks the goal again.
                    self.control_s += time.perf_counter() - w0  # the settle is no control cycle
                    settles += 1
                    outcome.setdefault("settles", []).append(self.settle(k))
                    anchor, anchor_ns = self.estimate, self.t_ns
                    self.next_ctrl_ns = self.t_ns
                    continue
                if cmd.status == "goal_reached":
                    status, reason = "reached", ""
                    self.control_s += time.perf_counter() - w0
                    break
                if cmd.status == "blocked":
                    replan_why = cmd.reason
                self.command(cmd.v, cmd.w)
            self.control_s += time.perf_counter() - w0
            if replan_why:
                if outcome["replans"] >= max_replans:
                    reason = f"gave up after {max_replans} replans; last: {replan_why}"
                    break
                if int(self.costmap.cost_at(*goal)) in (INSCRIBED, LETHAL):
                    # Every plan would end there, so replanning cannot help.
                    reason = (f"the camera sees an obstacle within the robot radius of the goal "
                              f"({replan_why})")  # fmt: skip
                    break
                outcome["replans"] += 1
                log.debug("goal %d: replanning (%s)", k, replan_why)
                if replan_why.startswith("no progress"):
                    self.stop(k)
                    for behavior in STUCK_BEHAVIORS:
                        outcome["recoveries"].append(self.run_behavior(k, behavior))
                elif replan_why.startswith("collision ahead"):
                    # The controller failed (Nav2: FollowPath fails): the next behaviour of the
                    # recovery round-robin before planning again.
                    self.stop(k)
                    behavior = RECOVERY_SEQUENCE[controller_failures % len(RECOVERY_SEQUENCE)]
                    controller_failures += 1
                    outcome["recoveries"].append(self.run_behavior(k, behavior))
                plan = self.recover_and_replan(k, goal, outcome)
                if not plan.success:
                    reason = f"replan failed ({replan_why}) after recoveries: {plan.reason}"
                    break
                path = self.adopt(plan)
                anchor, anchor_ns = self.estimate, self.t_ns
                planned_ns = self.t_ns
            self.step(k, "driving")
        self.stop(k)
        driven = np.array(self.log.poses[travelled0 - 1 :])[:, :2]
        est = self.estimate
        outcome.update(
            status=status, reason=reason, time_s=round((self.t_ns - t0) / NS_PER_S, 2),
            driven_m=round(path_length(driven), 3),
            final_error_m=round(float(np.hypot(*(self.pose[:2] - np.asarray(goal)))), 3),
            estimated_error_m=round(float(np.hypot(*(est[:2] - np.asarray(goal)))), 3),
        )  # fmt: skip
        return outcome


# 4. The run ---------------------------------------------------------------------------------


def parse_goal_args(args: Sequence[str]) -> list[tuple[float, float]]:
    """``--goal X Y [--goal X Y ...]`` (or ``-g``) tokens -> goals; :class:`ConfigError` on
    anything else (an unknown option ends up here too)."""
    goals: list[tuple[float, float]] = []
    k = 0
    while k < len(args):
        if args[k] not in ("--goal", "-g"):
            raise ConfigError(f"unexpected argument {args[k]!r} (goals are --goal X Y)")
        pair = args[k + 1 : k + 3]
        try:
            x, y = (float(v) for v in pair)
        except ValueError:
            raise ConfigError(f"--goal needs two numbers X Y, got {' '.join(pair)!r}") from None
        goals.append((x, y))
        k += 3
    return goals


def _check_goals(goals: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
    if not goals:
        raise ConfigError("give at least one --goal X Y")
    out = []
    for g in goals:
        if len(g) != 2 or not all(math.isfinite(v) for v in g):
            raise ConfigError(f"--goal needs two finite numbers X Y, got {list(g)}")
        out.append((float(g[0]), float(g[1])))
    return out


def commands_csv(
    rows: Sequence[tuple[float, int, str, float, float, float, float, int, int]],
) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_HEADER)
    for t, goal, status, cv, cw, sv, sw, gl, gr in rows:
        w.writerow([f"{t:.3f}", goal, status, f"{cv:.4f}", f"{cw:.4f}", f"{sv:.4f}", f"{sw:.4f}",
                    gl, gr])  # fmt: skip
    return buf.getvalue()


def pose_errors(truth: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-step position error [m] and absolute heading error [rad] of (N, 3) pose arrays."""
    d = np.hypot(*(estimate[:, :2] - truth[:, :2]).T)
    return d, np.abs(wrap_angle(estimate[:, 2] - truth[:, 2]))


def _stats(a: np.ndarray, digits: int = 3) -> dict[str, float | None]:
    if len(a) == 0:
        return {"mean": None, "p95": None, "max": None}
    return {"mean": round(float(a.mean()), digits),
            "p95": round(float(np.percentile(a, 95)), digits),
            "max": round(float(a.max()), digits)}  # fmt: skip


def navigate_settings(
    cfg: Config,
    localization: str | None = None,
    goal_timeout_s: float | None = None,
    max_replans: int | None = None,
    waypoint_pause_s: float | None = None,
) -> NavigateConfig:
    """The ``navigate`` section with the command line's explicit values on top; ConfigError
    naming the option on a bad value."""
    base = cfg.navigate
    given: dict[str, Any] = {"localization": localization, "goal_timeout": goal_timeout_s,
             "max_replans": max_replans, "waypoint_pause_duration": waypoint_pause_s}  # fmt: skip
    nav: NavigateConfig = replace(base, **{k: v for k, v in given.items() if v is not None})
    if nav.localization not in LOCALIZATION_MODES:
        raise ConfigError(f"--localization must be one of {', '.join(LOCALIZATION_MODES)}, got "
                          f"{nav.localization!r}")  # fmt: skip
    if not nav.waypoint_pause_duration >= 0.0:
        raise ConfigError(f"--waypoint-pause must be >= 0, got {nav.waypoint_pause_duration}")
    if not nav.goal_timeout > 0.0 or nav.max_replans < 0:
        raise ConfigError(f"need --goal-timeout > 0 and --max-replans >= 0, got "
                          f"{nav.goal_timeout} and {nav.max_replans}")  # fmt: skip
    return nav


def run_navigate(
    map_path: Path,
    goals: Sequence[Sequence[float]],
    world_path: Path,
    out: Path,
    config_files: Sequence[Path] = (),
    overrides: Sequence[str] = (),
    start: Sequence[float] | None = None,
    keepout_path: Path | None = None,
    goal_timeout_s: float | None = None,
    max_replans: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    *,
    localization: str | None = None,
    seed: int = 0,
    waypoint_pause_s: float | None = None,
    rrd: Path | None = None,
    viewer: bool = False,
) -> tuple[dict[str, Path], dict[str, Any]]:
    """Drive to every goal in turn; (files written, summary). ``seed`` seeds the wheel slip and
    the depth noise; the other keywords override the ``navigate`` settings
    (:func:`navigate_settings`); ``rrd``/``viewer`` log the run to rerun."""
    wall0 = time.perf_counter()
    # 1. Inputs first: a bad map, world, goal or start fails before anything is written.
    loaded = load_map(map_path)
    goal_list = _check_goals(goals)
    # The navigator's scans are depth-camera scans and it localises on its own wheels: the
    # RGB-D and navigate profiles first, yours still win.
    files = [p for p in (RGBD_PROFILE, NAVIGATE_PROFILE) if p.is_file()] + list(config_files)
    cfg = load_config(files, overrides)
    nav = navigate_settings(cfg, localization, goal_timeout_s, max_replans, waypoint_pause_s)
    world = load_world(world_path)
    fp = floor_plan(world, resolution=loaded.grid.geometry.resolution)
    s = np.asarray(world.start if start is None else start, dtype=np.float64)
    if s.shape != (3,) or not np.all(np.isfinite(s)):
        raise ConfigError(f"--start needs three finite numbers X Y YAW, got {list(s.ravel())}")
    costmap = Costmap.from_grid(loaded.grid, cfg.costmap, loaded.occupied_thresh,
                                loaded.free_thresh)  # fmt: skip
    keepout = None
    if keepout_path is not None:
        keepout = load_map_yaml(keepout_path)
        costmap.set_keepout(keepout)
    localizer = None
    if nav.localization == "localizer":
        model = MapModel.from_grid(loaded.grid, cfg.localizer, loaded.occupied_thresh,
                                   loaded.free_thresh)  # fmt: skip
        localizer = Localizer(model, cfg.localizer)
    sim = _Sim(cfg, fp, costmap, s, localizer, keepout, np.random.default_rng(seed), nav)
    if clearance_at(fp, sim.dist, s[0], s[1]) < sim.radius:
        raise MapError(f"start ({s[0]:.2f}, {s[1]:.2f}) puts the robot inside an obstacle of "
                       f"the world {world_path}")  # fmt: skip
    run = RunDir(out)
    outputs = {"config": run.write_config(cfg)}

    # 2. Drive to each goal in turn; a refused or failed goal moves on to the next one.
    sim.sense()  # look (and localise) before planning the first goal
    outcomes: list[dict[str, Any]] = []
    route = waypoints(goal_list, wait_at_waypoint(nav.waypoint_pause_duration))
    for k, wp in enumerate(route):
        goal = (wp.x, wp.y)
        if next_waypoint([o["status"] for o in outcomes], len(route),
                         nav.stop_on_failure) is None:  # fmt: skip
            outcomes.append({"goal": list(goal), "status": "skipped", "replans": 0,
                             "recoveries": [],
                             "reason": "an earlier goal failed and stop_on_failure is set"})
            continue
        problem = goal_problem(goal, costmap, loaded, keepout, cfg.planner.allow_unknown)
        if problem is not None:
            outcome = {"goal": list(goal), "status": "refused", "reason": problem, "replans": 0,
                       "recoveries": []}  # fmt: skip
        else:
            outcome = sim.drive_to(k, goal, nav.goal_timeout, nav.max_replans)
        sim.stop(k)  # refused or not, the robot ends every goal at rest
        if wp.task is not None and outcome["status"] == "reached":
            outcome["task"] = sim.run_behavior(k, wp.task)
        log.info("goal %d (%.2f, %.2f): %s %s", k, *goal, outcome["status"], outcome["reason"])
        outcomes.append(outcome)
        if progress is not None:
            progress(k + 1, len(route))

    # 3. Trajectories, commands, pictures, summary.
    stamps = np.array(sim.log.stamps_ns, dtype=np.int64)
    poses = np.array(sim.log.poses, dtype=np.float64)
    estimates = np.array(sim.log.estimates, dtype=np.float64)
    for name, p in (("trajectory", poses), ("estimated", estimates)):
        write_tum_trajectory(run.file(f"{name}.tum"), stamps, p[:, 0], p[:, 1], p[:, 2])
        outputs[name] = run.file(f"{name}.tum")
    atomic_write_text(run.file("commands.csv"), commands_csv(sim.log.rows))
    outputs["commands"] = run.file("commands.csv")
    g = loaded.grid.geometry
    paths = [(f"plan {i + 1}", o["first_plan"][:, 0], o["first_plan"][:, 1])
             for i, o in enumerate(outcomes) if "first_plan" in o]  # fmt: skip
    paths.append(("driven (true)", poses[:, 0], poses[:, 1]))
    if localizer is not None:
        paths.append(("estimated (localiser)", estimates[:, 0], estimates[:, 1]))
    plot_trajectories(run.file("map.png"), paths, f"navigate in {map_path.name}",
                      occupied=loaded.grid.occupied_mask(loaded.occupied_thresh),
                      origin=(g.origin_x, g.origin_y), resolution=g.resolution)  # fmt: skip
    outputs["picture"] = run.file("map.png")
    velocity_chart(run.file("velocity.png"), sim.log.rows, cfg.smoother)
    outputs["velocity chart"] = run.file("velocity.png")
    if rrd is not None or viewer:
        _visualize(make_visualizer("navigate", rrd, viewer), stamps, poses, estimates, outcomes,
                   loaded, costmap)  # fmt: skip
        if rrd is not None:
            outputs["rerun recording"] = rrd
    for o in outcomes:
        o.pop("first_plan", None)
    err_m, err_yaw = pose_errors(poses, estimates)
    statuses = sim.log.loc_status
    sim_s = sim.t_ns / NS_PER_S
    wall_s = time.perf_counter() - wall0
    summary: dict[str, Any] = {
        "command": "navigate", "map": str(map_path), "map_kind": loaded.kind,
        "world": str(world_path), "keepout": None if keepout_path is None else str(keepout_path),
        "start": s.tolist(), "seed": seed, "navigate": asdict(nav),
        "localization": {
            "mode": nav.localization,
            "description": ("the localiser (scan-to-map tracking from the given start pose) "
                            "fused with wheel odometry from the board's encoder counts (match "
                            f"gate {cfg.localizer.match_gate} sigma, jump confirmation "
                            f"{cfg.localizer.jump_confirm_scans} scans, dead reckoning up to "
                            f"{cfg.localizer.dead_reckoning_max_sigma} m sigma)"
                            + ("" if nav.global_relocalization else
                               ", and a localiser that loses track is put back on the "
                               "odometry pose (no global relocalisation while driving)")
                            + ("" if nav.goal_settle_spin == 0.0 else
                               f"; settles (a {nav.goal_settle_spin:g} rad turn in place and a "
                               "match of its scans stacked) at each goal"
                               + ("" if nav.settle_on_gated_scans == 0 else
                                  f" and after {nav.settle_on_gated_scans} gated matches in a "
                                  "row"))
                            if localizer is not None else
                            "ground truth: the navigator is given the true simulated pose"),
            "position_error_m": _stats(err_m), "heading_error_deg": _stats(np.degrees(err_yaw),
                                                                           2),
            "scans": {st: statuses.count(st) for st in ("tracking", "lost", "relocalising")},
            "confidence_mean": (round(float(np.mean(sim.log.loc_confidence)), 3)
                                if sim.log.loc_confidence else None),
            "odometry_distance_m": round(sim.odometry.distance_m, 3),
            "matches_gated": 0 if localizer is None else localizer.stats.gated,
            "tracking_jumps_rejected": 0 if localizer is None else localizer.stats.gated,
            "tracking_jumps_confirmed": 0 if localizer is None else localizer.stats.jumps,
            "reseeded_from_odometry": sim.reseeds,
            "settles": sum(len(o.get("settles", [])) for o in outcomes),
        },
        "goals": outcomes,
        "counts": {st: sum(o["status"] == st for o in outcomes)
                   for st in ("reached", "failed", "refused", "skipped")},
        "collisions": {"events": sim.collision_events, "steps": sim.collision_steps,
                       "seconds": round(sim.collision_steps * sim.dt_ns / NS_PER_S, 2),
                       "robot_radius_m": sim.radius,
                       "min_clearance_m": round(sim.min_clearance, 3)},
        "keepout_entries": {"events": sim.keepout_events, "steps": sim.keepout_steps,
                            "min_distance_m": (round(sim.min_keepout_distance, 3)
                                               if math.isfinite(sim.min_keepout_distance)
                                               else None)},
        "recoveries": sum(len(o["recoveries"]) for o in outcomes),
        "path_length_m": round(path_length(poses[:, :2]), 3),
        "sim_time_s": round(sim_s, 2),
        "scans": sim.scans,
        "gospd_lines": sim.drive.gospd_lines,
        "rates_hz": {"controller": cfg.follower.controller_frequency,
                     "smoother": cfg.smoother.smoothing_frequency,
                     "costmap": cfg.costmap.update_frequency},
        "control": {"steps": sim.control_steps,
                    "ms_per_step": (round(1e3 * sim.control_s / sim.control_steps, 3)
                                    if sim.control_steps else None),
                    "what": "wall time per controller cycle incl. due scans: localiser, "
                            "costmap update, path check, follower"},
        "wall_s": round(wall_s, 3),
        "real_time_factor": round(sim_s / wall_s, 1) if wall_s > 0 else None,
    }  # fmt: skip
    outputs["summary"] = run.write_summary(summary)
    return outputs, summary


def _visualize(vis: Visualizer, stamps: np.ndarray, poses: np.ndarray, estimates: np.ndarray,
               outcomes: list[dict[str, Any]], loaded: LoadedMap, costmap: Costmap) -> None:
    """The run on rerun's time line: the estimated pose and path (world/robot), the true path
    (world/truth), each goal's first plan, the map and the final costmap's lethal cells."""
    try:
        log_run(vis, stamps, estimates, None,
                occupied_cells_xy(loaded.grid.occupied_mask(loaded.occupied_thresh),
                                  (loaded.grid.geometry.origin_x, loaded.grid.geometry.origin_y),
                                  loaded.grid.geometry.resolution),
                poses[:, :2])  # fmt: skip
        t_end = int(stamps[-1]) if len(stamps) else 0
        for o in outcomes:
            if "first_plan" in o:
                vis.plan(t_end, o["first_plan"][:, :2])
        cg = costmap.geometry
        lethal = (costmap.master() >= INSCRIBED) & (costmap.master() != NO_INFORMATION)
        vis.costmap(t_end, occupied_cells_xy(lethal, (cg.origin_x, cg.origin_y), cg.resolution))
    finally:
        vis.close()


def describe(summary: dict[str, Any]) -> str:
    """One line for the terminal."""
    c = summary["counts"]
    n = len(summary["goals"])
    return (f"{c['reached']}/{n} goals reached, {c['failed']} failed, {c['refused']} refused; "
            f"{summary['collisions']['events']} collision(s), "
            f"{summary['keepout_entries']['events']} keepout entr(ies), "
            f"{summary['path_length_m']:.2f} m in {summary['sim_time_s']:.1f} s simulated "
            f"({summary['localization']['mode']} localisation)")  # fmt: skip


__all__ = ["LOCALIZATION_MODES", "cast_scan", "clearance_map", "commands_csv",
           "depth_range_sigma", "describe", "goal_problem", "navigate_settings",
           "parse_goal_args", "path_ahead", "pose_errors", "run_navigate"]  # fmt: skip
