"""`rgbdnav navigate`: drive to goals on a saved map, closed loop in a 2D simulation.

The robot lives in a simulator world (``sensors.sim.world``); the navigator only knows the map.
Each simulation step, in simulated time (never wall time): a depth-camera scan is ray-cast
against the world's floor plan at the true camera pose (one beam per ``SCAN_COLUMNS_PER_BEAM``
image columns, Kinect range noise), in ``depth_to_scan.output_frame`` as live's scans are; the
localiser (``localization="localizer"``, the default) or ground truth gives the navigator its
pose; the scan marks and clears the costmap's obstacle layer; the navigator
(:class:`nav.navigator.Navigator`, the one ``rgbdnav live`` ticks in wall time) plans, follows,
checks progress, replans, recovers and smooths the command; the collision monitor
(:class:`nav.collision_monitor.CollisionMonitor`, as in ``live``) limits it on what the camera saw;
it goes to the wheels as ``GOSPD`` through the Eddie board emulator. Why each step is as it is
(the localiser's gates, settles, replanning on moved furniture) and the run
directory's files are in ``docs/design/navigate_simulation.md``.

A goal in a wall, a keepout zone, outside the map or unreachable is refused with a reason;
after every goal (reached or not) the robot is brought to rest, then the waypoint task (a pause)
runs. A collision is a step at which the true circular footprint (``costmap.robot_radius``)
overlaps an occupied floor-plan cell; a keepout entry a step at which the true robot centre is
in a keepout cell (the filter's semantics: the planner never puts the centre there).
The run directory holds ``trajectory.tum`` (true pose), ``estimated.tum``, ``commands.csv``,
``summary.json``, ``map.png``, ``velocity.png`` and ``config.yaml``.
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

from nav.behaviors import Behavior, next_waypoint, wait_at_waypoint, waypoints
from nav.collision_monitor import CollisionMonitor
from nav.config import NavigateConfig
from nav.costmap import INSCRIBED, LETHAL, NO_INFORMATION, Costmap
from nav.navigator import MAX_STOP_S, Navigator
from rgbdnav.config import Config, load_config
from rgbdnav.nav_charts import velocity_chart
from rgbdnav.report import plot_trajectories
from rgbdnav.run_dir import RunDir
from rgbdnav.scan_stream import NAVIGATE_PROFILE, RGBD_PROFILE
from rgbdnav.visualize import Visualizer, log_run, make_visualizer, occupied_cells_xy
from sensors.atomic import atomic_write_text
from sensors.sim.nav_drive import EmulatedDrive
from sensors.sim.scan import cast_scan, depth_range_sigma
from sensors.sim.world import FloorPlan, floor_plan, load_world
from sensors.tum import write_tum_trajectory
from sensors.types import NS_PER_S, ConfigError, LaserScan, MapError, Pose2
from slam.depth_to_scan import (
    beam_index,
    nearest_per_beam_reference,
    scan_frame_in_base,
    scan_pose,
)
from slam.diff_drive import WheelOdometry
from slam.geometry import oplus, path_length, wrap_angle
from slam.localization import Localizer, MapModel
from slam.map_bundle import LoadedMap, load_map, load_map_yaml
from slam.occupancy_grid import OccupancyGrid

log = logging.getLogger(__name__)

LOCALIZATION_MODES: tuple[str, ...] = ("groundtruth", "localizer")
SCAN_COLUMNS_PER_BEAM = 2  # [px] image columns per simulated scan beam (640 px -> 320 beams)
CSV_HEADER = (
    "t_s",
    "goal",
    "status",
    "cmd_v_mps",
    "cmd_w_radps",
    "smoothed_v_mps",
    "smoothed_w_radps",
    "gospd_left",
    "gospd_right",
)


# 1. Ground truth of the simulation ----------------------------------------------------------


def clearance_map(plan: FloorPlan) -> np.ndarray:
    """(H, W) distance [m] from each floor-plan cell centre to the nearest occupied cell centre."""
    from scipy.ndimage import distance_transform_edt

    return np.asarray(distance_transform_edt(~plan.occupied), dtype=np.float64) * plan.resolution


def clearance_at(plan: FloorPlan, dist: np.ndarray, x: float, y: float) -> float:
    """Clearance [m] of a point; outside the floor plan counts as unbounded free space."""
    row, col = plan.cell_of(np.array([[x, y]]))[0]
    h, w = dist.shape
    return float(dist[row, col]) if 0 <= row < h and 0 <= col < w else math.inf


def rebase_scan(
    ranges: np.ndarray,
    angles: np.ndarray,
    origin_xy: np.ndarray,
    range_min: float,
    range_max: float,
) -> np.ndarray:
    """(N,) float32 ranges of beams at ``angles`` (ascending, evenly spaced) from the scan
    frame's origin, from those cast at the same angles from ``origin_xy`` [m] in that frame
    (axes parallel): each return goes to the beam of its bearing from the origin, nearest
    kept, as depth -> scan does for a camera that is not above the scan origin. Returns
    outside [range_min, range_max] are dropped; a beam left without one is +inf (REP-117)."""
    r = np.asarray(ranges, dtype=np.float64)
    ok = np.isfinite(r)
    x = origin_xy[0] + r[ok] * np.cos(angles[ok])
    y = origin_xy[1] + r[ok] * np.sin(angles[ok])
    dist = np.hypot(x, y)
    keep = (dist >= range_min) & (dist <= range_max)
    inc = float(angles[1] - angles[0])
    beam = beam_index(np.arctan2(y[keep], x[keep]), float(angles[0]), inc)
    return nearest_per_beam_reference(beam, dist[keep], len(angles))


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
    """The world, the robot (board emulator + slip), its sensing and localisation, and the
    simulated clock around one :class:`nav.navigator.Navigator`; one instance per run. It is
    also the navigator's pose corrector for goal settles (localizer mode)."""

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
        self.dist = clearance_map(plan)
        self.radius = cfg.costmap.robot_radius  # [m]
        self.dt_ns = round(NS_PER_S / cfg.smoother.smoothing_frequency)
        self.scan_ns = round(NS_PER_S / cfg.costmap.update_frequency)
        cam = cfg.camera
        fov = 2.0 * math.atan(cam.width / (2.0 * cam.fx))  # [rad] horizontal field of view
        n = max(2, cam.width // SCAN_COLUMNS_PER_BEAM)
        self.angles = np.linspace(fov / 2, -fov / 2, n)[::-1].copy()  # ascending, REP-117
        # The laser is cast where the camera is; the scan it stands for is in the frame of
        # depth_to_scan.output_frame, as live's depth scans are (rebase_scan between the two).
        d2s = cfg.depth_to_scan
        self.camera_in_base = scan_frame_in_base(cfg.robot, replace(d2s, output_frame="camera"))
        self.scan_in_base = scan_frame_in_base(cfg.robot, d2s)
        r = cfg.robot
        # The robot: GOSPD into the board emulator, slip, encoder counts back.
        self.drive = EmulatedDrive(r, cfg.sim, start, rng)
        self.odometry = WheelOdometry(r, self.drive.ticks())
        self.localizer = localizer
        # odom starts at the start pose; the localiser is told the start (an initial pose).
        self.T_map_odom = np.asarray(start, dtype=np.float64).copy()
        if localizer is not None:
            localizer.set_initial_pose(scan_pose(start, self.scan_in_base))
        self.localized = True  # the localiser tracks (always, with ground truth)
        self.last_fix_ns = 0  # [ns] of the last believed localiser answer
        self.loc_covariance: np.ndarray | None = None  # of the last tracking answer
        self.reseeds = 0
        self.fresh_scan = False  # a scan was localised since the navigator last asked
        self._settle_scans0 = 0
        self.navigator = Navigator(
            replace(cfg, navigate=nav), costmap, corrector=self if localizer is not None else None
        )
        # Between the navigator and the wheels, as in `rgbdnav live`: what the camera saw, carried
        # by odometry, has the last word (the map pose may be off by a door jamb's width).
        self.monitor = CollisionMonitor(cfg.collision_monitor, self.radius)
        self.keepout_dist: np.ndarray | None = None
        self.keepout_geometry = None if keepout is None else keepout.geometry
        if keepout is not None:
            from scipy.ndimage import distance_transform_edt

            mask = keepout.occupied_mask()
            self.keepout_dist = (
                np.asarray(distance_transform_edt(~mask)) * keepout.geometry.resolution
            )
        self.next_scan_ns = 0
        self.cmd = (0.0, 0.0)  # the navigator's command before smoothing (v, w)
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
        self.control_s = 0.0  # [s] wall time of the driving steps: sensing + controller
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
        true_camera = scan_pose(self.pose, self.camera_in_base)
        ranges = cast_scan(self.plan, true_camera, self.angles, cam.depth_min, cam.depth_max)
        sigma = depth_range_sigma(
            ranges, cam.disparity_focal, cam.baseline, sim.disparity_noise, sim.disparity_subpixel
        )
        finite = np.isfinite(ranges)
        ranges[finite] += (sigma[finite] * self.rng.standard_normal(int(finite.sum()))).astype(
            np.float32
        )
        if np.any(self.scan_in_base != self.camera_in_base):
            at = (self.camera_in_base - self.scan_in_base)[:2]
            ranges = rebase_scan(ranges, self.angles, at, cam.depth_min, cam.depth_max)
        inc = float(self.angles[1] - self.angles[0])
        scan = LaserScan(
            self.t_ns, float(self.angles[0]), inc, ranges, cam.depth_min, cam.depth_max
        )
        if self.localizer is not None:
            self.localize(scan)
        self.monitor.add_scan(self.odometry.pose, scan, self.scan_in_base)
        self.costmap.update_scan(scan, Pose2(*scan_pose(self.estimate, self.scan_in_base).tolist()))
        self.scans += 1
        return True

    def localize(self, scan: LaserScan) -> None:
        """One scan into the localiser; T_map_odom from its answer while it tracks (see
        :class:`nav.config.NavigateConfig` ``global_relocalization`` for when it does not).
        Whether a match far from the odometry prediction is believed is the localiser's call
        (``localizer.match_gate``, ``localizer.jump_confirm_scans``)."""
        assert self.localizer is not None
        result = self.localizer.update(scan, scan_pose(self.odometry.pose, self.scan_in_base))
        self.fresh_scan = True
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
            self.localizer.set_initial_pose(
                scan_pose(self.estimate, self.scan_in_base), self.loc_covariance
            )
            self.reseeds += 1

    # 3b. The navigator's pose corrector (nav.navigator.PoseCorrector): goal settles.
    def settle_due(self, gated_scans: int) -> bool:
        """A scan since the last call left the localiser with ``gated_scans`` gated matches in
        a row (``navigate.settle_on_gated_scans``)."""
        fresh, self.fresh_scan = self.fresh_scan, False
        return fresh and self.localizer is not None and self.localizer.gated_streak >= gated_scans

    def begin_settle(self) -> None:
        self._settle_scans0 = self.scans

    def finish_settle(self) -> str:
        """Correct the pose with the settle turn's scans stacked by odometry
        (:meth:`Localizer.match_recent`); the localiser's reason."""
        assert self.localizer is not None
        result = self.localizer.match_recent(self.scans - self._settle_scans0)
        if result.status == "tracking":
            self.T_map_odom = result.map_to_odom
            self.last_fix_ns = self.t_ns
            self.loc_covariance = result.covariance
        return result.reason

    # 3c. One smoother period: sense, decide, move, check against the world.
    def step(
        self, goal: int, status: str | None = None, hold: tuple[float, float] | None = None
    ) -> None:
        """``status`` labels the step in commands.csv (default: the navigator's); ``hold``
        commands that twist instead of the navigator's decision."""
        w0 = time.perf_counter()
        self.sense()
        nav = self.navigator
        if hold is not None:
            d = nav.hold(self.t_ns, hold, status or "holding")
        else:
            d = nav.tick(
                self.t_ns,
                self.estimate,
                moving=bool(np.any(self.drive.speeds)),
                collision_stop=self.monitor.action == "stop",
            )
        if d.status == "driving":
            self.control_s += time.perf_counter() - w0
        v, w, _ = self.monitor.limit(d.v, d.w, self.odometry.pose)
        self.cmd, self.vel = nav.target, (v, w)
        self.drive.command(v, w)
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
            d_k = float(self.keepout_dist[row, col]) if bool(g.contains(row, col)) else math.inf
            self.min_keepout_distance = min(self.min_keepout_distance, d_k)
            inside = d_k == 0.0
            self.keepout_steps += inside
            self.keepout_events += inside and not self.in_keepout
            self.in_keepout = inside
        self._record(goal, status or d.status)

    def _record(self, goal: int, status: str) -> None:
        self.log.stamps_ns.append(self.t_ns)
        self.log.poses.append(self.pose.copy())
        self.log.estimates.append(self.estimate)
        self.log.rows.append(
            (self.t_ns / NS_PER_S, goal, status, *self.cmd, *self.vel, *self.drive.sent)
        )

    def stop(self, goal: int) -> None:
        """Command zero and let the smoother and the board bring the wheels to rest."""
        for _ in range(math.ceil(MAX_STOP_S * NS_PER_S / self.dt_ns)):
            if self.navigator.at_rest(bool(np.any(self.drive.speeds))):
                break
            self.step(goal, "stopping")

    def run_task(self, k: int, behavior: Behavior) -> str:
        """A waypoint task, run by the navigator to its end; its name."""
        self.navigator.run_task(behavior)
        while self.navigator.busy:
            self.step(k)
        return behavior.name

    def drive_to(self, k: int, goal: tuple[float, float]) -> dict[str, Any]:
        """Tick the navigator to one goal; its outcome (reached / failed / refused) and why."""
        t0, travelled0 = self.t_ns, len(self.log.poses)
        self.last_fix_ns = max(self.last_fix_ns, t0)  # each goal gets relocalize_timeout
        nav = self.navigator
        nav.set_goal(goal, self.t_ns)
        while nav.active:
            if self.localizer is not None:
                if (self.t_ns - self.last_fix_ns) / NS_PER_S > self.nav.relocalize_timeout:
                    nav.cancel(
                        self.t_ns,
                        f"no believable localiser answer for "
                        f"{self.nav.relocalize_timeout:g} s (last status "
                        f"{self.log.loc_status[-1]})",
                    )
                    break
                if not self.localized:
                    # Never drive on a pose the localiser does not vouch for: turn in place
                    # (new views for the global relocalisation) until it tracks again.
                    self.step(k, "relocalising", hold=(0.0, self.nav.relocalize_spin_speed))
                    continue
            self.step(k)
        result = nav.outcome
        assert result is not None
        outcome: dict[str, Any] = {
            "goal": list(goal),
            "status": result.status,
            "reason": result.reason,
            "replans": result.replans,
            "recoveries": list(result.recoveries),
        }
        if result.settles:
            outcome["settles"] = list(result.settles)
        if result.first_plan is not None:
            outcome["first_plan"] = result.first_plan
            outcome["planned_length_m"] = round(result.planned_length_m or 0.0, 3)
        self.stop(k)
        if result.status == "refused":
            return outcome
        driven = np.array(self.log.poses[travelled0 - 1 :])[:, :2]
        # The estimate's error as the navigator judged the goal (its goal checker's verdict).
        est = self.estimate if result.end_pose is None else result.end_pose
        outcome.update(
            time_s=round((self.t_ns - t0) / NS_PER_S, 2),
            driven_m=round(path_length(driven), 3),
            final_error_m=round(float(np.hypot(*(self.pose[:2] - np.asarray(goal)))), 3),
            estimated_error_m=round(float(np.hypot(*(est[:2] - np.asarray(goal)))), 3),
        )
        return outcome


# 4. The run ---------------------------------------------------------------------------------


def _check_goals(goals: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
    if not goals:
        raise ConfigError("give at least one --goal X,Y")
    out = []
    for g in goals:
        if len(g) != 2 or not all(math.isfinite(v) for v in g):
            raise ConfigError(f"--goal needs two finite numbers X,Y, got {list(g)}")
        out.append((float(g[0]), float(g[1])))
    return out


def commands_csv(
    rows: Sequence[tuple[float, int, str, float, float, float, float, int, int]],
) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_HEADER)
    for t, goal, status, cv, cw, sv, sw, gl, gr in rows:
        w.writerow(
            [f"{t:.3f}", goal, status, f"{cv:.4f}", f"{cw:.4f}", f"{sv:.4f}", f"{sw:.4f}", gl, gr]
        )
    return buf.getvalue()


def pose_errors(truth: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-step position error [m] and absolute heading error [rad] of (N, 3) pose arrays."""
    d = np.hypot(*(estimate[:, :2] - truth[:, :2]).T)
    return d, np.abs(wrap_angle(estimate[:, 2] - truth[:, 2]))


def _stats(a: np.ndarray, digits: int = 3) -> dict[str, float | None]:
    if len(a) == 0:
        return {"mean": None, "p95": None, "max": None}
    return {
        "mean": round(float(a.mean()), digits),
        "p95": round(float(np.percentile(a, 95)), digits),
        "max": round(float(a.max()), digits),
    }


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
    given: dict[str, Any] = {
        "localization": localization,
        "goal_timeout": goal_timeout_s,
        "max_replans": max_replans,
        "waypoint_pause_duration": waypoint_pause_s,
    }
    nav: NavigateConfig = replace(base, **{k: v for k, v in given.items() if v is not None})
    if nav.localization not in LOCALIZATION_MODES:
        raise ConfigError(
            f"--localization must be one of {', '.join(LOCALIZATION_MODES)}, got "
            f"{nav.localization!r}"
        )
    if not nav.waypoint_pause_duration >= 0.0:
        raise ConfigError(f"--waypoint-pause must be >= 0, got {nav.waypoint_pause_duration}")
    if not nav.goal_timeout > 0.0 or nav.max_replans < 0:
        raise ConfigError(
            f"need --goal-timeout > 0 and --max-replans >= 0, got "
            f"{nav.goal_timeout} and {nav.max_replans}"
        )
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
    costmap = Costmap.from_grid(
        loaded.grid, cfg.costmap, loaded.occupied_thresh, loaded.free_thresh
    )
    keepout = None
    if keepout_path is not None:
        keepout = load_map_yaml(keepout_path)
        costmap.set_keepout(keepout)
    localizer = None
    if nav.localization == "localizer":
        model = MapModel.from_grid(
            loaded.grid, cfg.localizer, loaded.occupied_thresh, loaded.free_thresh
        )
        localizer = Localizer(model, cfg.localizer)
    sim = _Sim(cfg, fp, costmap, s, localizer, keepout, np.random.default_rng(seed), nav)
    if clearance_at(fp, sim.dist, s[0], s[1]) < sim.radius:
        raise MapError(
            f"start ({s[0]:.2f}, {s[1]:.2f}) puts the robot inside an obstacle of "
            f"the world {world_path}"
        )
    run = RunDir(out)
    outputs = {"config": run.write_config(cfg)}

    # 2. Drive to each goal in turn; a refused or failed goal moves on to the next one.
    sim.sense()  # look (and localise) before planning the first goal
    outcomes: list[dict[str, Any]] = []
    route = waypoints(goal_list, wait_at_waypoint(nav.waypoint_pause_duration))
    for k, wp in enumerate(route):
        goal = (wp.x, wp.y)
        if next_waypoint([o["status"] for o in outcomes], len(route), nav.stop_on_failure) is None:
            outcomes.append(
                {
                    "goal": list(goal),
                    "status": "skipped",
                    "replans": 0,
                    "recoveries": [],
                    "reason": "an earlier goal failed and stop_on_failure is set",
                }
            )
            continue
        problem = goal_problem(goal, costmap, loaded, keepout, cfg.planner.allow_unknown)
        if problem is not None:
            outcome = {
                "goal": list(goal),
                "status": "refused",
                "reason": problem,
                "replans": 0,
                "recoveries": [],
            }
        else:
            outcome = sim.drive_to(k, goal)
        sim.stop(k)  # refused or not, the robot ends every goal at rest
        if wp.task is not None and outcome["status"] == "reached":
            outcome["task"] = sim.run_task(k, wp.task)
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
    paths = [
        (f"plan {i + 1}", o["first_plan"][:, 0], o["first_plan"][:, 1])
        for i, o in enumerate(outcomes)
        if "first_plan" in o
    ]
    paths.append(("driven (true)", poses[:, 0], poses[:, 1]))
    if localizer is not None:
        paths.append(("estimated (localiser)", estimates[:, 0], estimates[:, 1]))
    plot_trajectories(
        run.file("map.png"),
        paths,
        f"navigate in {map_path.name}",
        occupied=loaded.grid.occupied_mask(loaded.occupied_thresh),
        origin=(g.origin_x, g.origin_y),
        resolution=g.resolution,
    )
    outputs["picture"] = run.file("map.png")
    velocity_chart(run.file("velocity.png"), sim.log.rows, cfg.smoother)
    outputs["velocity chart"] = run.file("velocity.png")
    if rrd is not None or viewer:
        _visualize(
            make_visualizer("navigate", rrd, viewer),
            stamps,
            poses,
            estimates,
            outcomes,
            loaded,
            costmap,
        )
        if rrd is not None:
            outputs["rerun recording"] = rrd
    for o in outcomes:
        o.pop("first_plan", None)
    err_m, err_yaw = pose_errors(poses, estimates)
    statuses = sim.log.loc_status
    sim_s = sim.t_ns / NS_PER_S
    wall_s = time.perf_counter() - wall0
    summary: dict[str, Any] = {
        "command": "navigate",
        "map": str(map_path),
        "map_kind": loaded.kind,
        "world": str(world_path),
        "keepout": None if keepout_path is None else str(keepout_path),
        "start": s.tolist(),
        "seed": seed,
        "navigate": asdict(nav),
        "localization": {
            "mode": nav.localization,
            "description": (
                "the localiser (scan-to-map tracking from the given start pose) "
                "fused with wheel odometry from the board's encoder counts (match "
                f"gate {cfg.localizer.match_gate} sigma, jump confirmation "
                f"{cfg.localizer.jump_confirm_scans} scans, dead reckoning up to "
                f"{cfg.localizer.dead_reckoning_max_sigma} m sigma)"
                + (
                    ""
                    if nav.global_relocalization
                    else ", and a localiser that loses track is put back on the "
                    "odometry pose (no global relocalisation while driving)"
                )
                + (
                    ""
                    if nav.goal_settle_spin == 0.0
                    else f"; settles (a {nav.goal_settle_spin:g} rad turn in place and a "
                    "match of its scans stacked) at each goal"
                    + (
                        ""
                        if nav.settle_on_gated_scans == 0
                        else f" and after {nav.settle_on_gated_scans} gated matches in a row"
                    )
                )
                if localizer is not None
                else "ground truth: the navigator is given the true simulated pose"
            ),
            "position_error_m": _stats(err_m),
            "heading_error_deg": _stats(np.degrees(err_yaw), 2),
            "scans": {st: statuses.count(st) for st in ("tracking", "lost", "relocalising")},
            "confidence_mean": (
                round(float(np.mean(sim.log.loc_confidence)), 3) if sim.log.loc_confidence else None
            ),
            "odometry_distance_m": round(sim.odometry.distance_m, 3),
            "matches_gated": 0 if localizer is None else localizer.stats.gated,
            "tracking_jumps_rejected": 0 if localizer is None else localizer.stats.gated,
            "tracking_jumps_confirmed": 0 if localizer is None else localizer.stats.jumps,
            "reseeded_from_odometry": sim.reseeds,
            "settles": sum(len(o.get("settles", [])) for o in outcomes),
        },
        "goals": outcomes,
        "counts": {
            st: sum(o["status"] == st for o in outcomes)
            for st in ("reached", "failed", "refused", "skipped")
        },
        "collisions": {
            "events": sim.collision_events,
            "steps": sim.collision_steps,
            "seconds": round(sim.collision_steps * sim.dt_ns / NS_PER_S, 2),
            "robot_radius_m": sim.radius,
            "min_clearance_m": round(sim.min_clearance, 3),
        },
        "keepout_entries": {
            "events": sim.keepout_events,
            "steps": sim.keepout_steps,
            "min_distance_m": (
                round(sim.min_keepout_distance, 3)
                if math.isfinite(sim.min_keepout_distance)
                else None
            ),
        },
        "recoveries": sum(len(o["recoveries"]) for o in outcomes),
        "collision_monitor": {
            "enabled": cfg.collision_monitor.enabled,
            "stops": sim.monitor.counts["collision_monitor_stops"],
            "slowdowns": sim.monitor.counts["collision_monitor_slowdowns"],
        },
        "path_length_m": round(path_length(poses[:, :2]), 3),
        "sim_time_s": round(sim_s, 2),
        "scans": sim.scans,
        "gospd_lines": sim.drive.gospd_lines,
        "rates_hz": {
            "controller": cfg.follower.controller_frequency,
            "smoother": cfg.smoother.smoothing_frequency,
            "costmap": cfg.costmap.update_frequency,
        },
        "control": {
            "steps": sim.navigator.controller_cycles,
            "ms_per_step": (
                round(1e3 * sim.control_s / sim.navigator.controller_cycles, 3)
                if sim.navigator.controller_cycles
                else None
            ),
            "what": "wall time per controller cycle incl. due scans: localiser, "
            "costmap update, path check, follower",
        },
        "wall_s": round(wall_s, 3),
        "real_time_factor": round(sim_s / wall_s, 1) if wall_s > 0 else None,
    }
    outputs["summary"] = run.write_summary(summary)
    return outputs, summary


def _visualize(
    vis: Visualizer,
    stamps: np.ndarray,
    poses: np.ndarray,
    estimates: np.ndarray,
    outcomes: list[dict[str, Any]],
    loaded: LoadedMap,
    costmap: Costmap,
) -> None:
    """The run on rerun's time line: the estimated pose and path (world/robot), the true path
    (world/truth), each goal's first plan, the map and the final costmap's lethal cells."""
    try:
        log_run(
            vis,
            stamps,
            estimates,
            None,
            occupied_cells_xy(
                loaded.grid.occupied_mask(loaded.occupied_thresh),
                (loaded.grid.geometry.origin_x, loaded.grid.geometry.origin_y),
                loaded.grid.geometry.resolution,
            ),
            poses[:, :2],
        )
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
    return (
        f"{c['reached']}/{n} goals reached, {c['failed']} failed, {c['refused']} refused; "
        f"{summary['collisions']['events']} collision(s), "
        f"{summary['keepout_entries']['events']} keepout entr(ies), "
        f"{summary['path_length_m']:.2f} m in {summary['sim_time_s']:.1f} s simulated "
        f"({summary['localization']['mode']} localisation)"
    )


__all__ = [
    "LOCALIZATION_MODES",
    "clearance_map",
    "commands_csv",
    "describe",
    "goal_problem",
    "navigate_settings",
    "pose_errors",
    "rebase_scan",
    "run_navigate",
]
