"""`rgbdnav navigate`: drive to goals on a saved map, closed loop in a 2D kinematic simulation.

The robot lives in a simulator world (``sensors.sim.world``); the navigator only knows the map.
Each simulation step, in simulated time (never wall time):

1. At ``costmap.update_frequency`` a depth-camera scan (the camera's horizontal field of view
   and depth range, one beam per ``SCAN_COLUMNS_PER_BEAM`` image columns) is ray-cast against the
   world's floor plan at the true camera pose and fed to the costmap's obstacle layer, so
   obstacles that are in the world but not in the map appear; the path ahead is re-checked.
2. At ``follower.controller_frequency`` the regulated pure pursuit follower turns the path and
   the pose into (v, w); ``blocked`` or an invalidated path triggers a replan (at most
   ``--max-replans`` per goal).
3. At ``smoother.smoothing_frequency`` the velocity smoother limits the command and the true
   robot, a unicycle, integrates the *smoothed* command over one smoother period.

Localisation is ground truth in this version: the navigator is handed the true pose (the
localiser is not wired in). A goal in a wall, a keepout zone, outside the map or unreachable is
refused with a reason; after every goal (reached or not) the robot is brought to rest. A
collision is a step at which the true circular footprint (``costmap.robot_radius``) overlaps an
occupied floor-plan cell. The run directory holds:

``trajectory.tum``   the true base_link pose at every simulation step.
``commands.csv``     ``t_s,goal,status,cmd_v_mps,cmd_w_radps,smoothed_v_mps,smoothed_w_radps``.
``summary.json``     per-goal outcome with reason, collisions, distance driven, simulated time.
``map.png``          the map with each goal's first plan and the driven path.
``config.yaml``      the resolved configuration.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nav.costmap import INSCRIBED, LETHAL, NO_INFORMATION, Costmap, inscribed_radius
from nav.path_follower import compute_velocity
from nav.planner import GridPlanner, PlanResult, replan_needed
from nav.velocity_smoother import VelocitySmoother
from rgbdnav.config import Config, load_config
from rgbdnav.localize_run import LoadedMap, load_map
from rgbdnav.report import plot_trajectories
from rgbdnav.run_dir import RunDir
from sensors.atomic import atomic_write_text
from sensors.sim.world import FloorPlan, floor_plan, load_world
from sensors.tum import write_tum_trajectory
from sensors.types import ConfigError, LaserScan, MapError, Pose2
from slam.map_bundle import load_map_yaml
from slam.occupancy_grid import OccupancyGrid

log = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
SCAN_COLUMNS_PER_BEAM = 2  # [px] image columns per simulated scan beam (640 px -> 320 beams)
RAY_STEP_CELLS = 0.5  # [cells] ray-marching step in the floor plan
STOP_EPS = 1e-3  # [m/s, rad/s] smoothed speeds below this count as at rest
MAX_STOP_S = 10.0  # [s] longest braking we simulate before giving up on "at rest"
DEFAULT_GOAL_TIMEOUT_S = 60.0  # [s] simulated time allowed per goal
DEFAULT_MAX_REPLANS = 5  # replans per goal before it fails
CSV_HEADER = ("t_s", "goal", "status", "cmd_v_mps", "cmd_w_radps", "smoothed_v_mps",
              "smoothed_w_radps")  # fmt: skip


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


def unicycle_step(pose: np.ndarray, v: float, w: float, dt: float) -> np.ndarray:
    """Midpoint integration of (v [m/s], w [rad/s]) over dt [s]: x += v dt cos(yaw + w dt / 2)."""
    mid = pose[2] + 0.5 * w * dt
    yaw = math.atan2(math.sin(pose[2] + w * dt), math.cos(pose[2] + w * dt))
    return np.array([pose[0] + v * dt * math.cos(mid), pose[1] + v * dt * math.sin(mid), yaw])


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


def polyline_length(xy: np.ndarray) -> float:
    return float(np.hypot(*np.diff(xy, axis=0).T).sum()) if len(xy) > 1 else 0.0


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
    poses: list[np.ndarray] = field(default_factory=list)
    rows: list[tuple[float, int, str, float, float, float, float]] = field(default_factory=list)


class _Sim:
    """Holds the world, the navigator's costmap and the clocks; one instance per run."""

    def __init__(self, cfg: Config, plan: FloorPlan, costmap: Costmap, start: np.ndarray) -> None:
        self.cfg, self.plan, self.costmap = cfg, plan, costmap
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
        self.t_ns = 0
        self.next_ctrl_ns = 0
        self.next_scan_ns = 0
        self.pose = start.astype(np.float64)
        self.cmd = (0.0, 0.0)  # last controller command (v, w)
        self.vel = (0.0, 0.0)  # smoothed command being executed (v, w)
        self.collision_steps = 0
        self.collision_events = 0
        self.in_collision = False
        self.min_clearance = math.inf
        self.scans = 0
        self.log = _Log()
        self._record(-1, "start")

    # 3a. Sensing.
    def laser_pose(self) -> Pose2:
        r = self.cfg.robot
        x, y, yaw = self.pose
        c, s = math.cos(yaw), math.sin(yaw)
        return Pose2(x + c * r.camera_x - s * r.camera_y, y + s * r.camera_x + c * r.camera_y, yaw)

    def sense(self) -> bool:
        """Scan into the costmap when one is due; True when it did."""
        if self.t_ns < self.next_scan_ns:
            return False
        self.next_scan_ns += self.scan_ns
        lp = self.laser_pose()
        cam = self.cfg.camera
        ranges = cast_scan(self.plan, lp.as_array(), self.angles, cam.depth_min, cam.depth_max)
        inc = float(self.angles[1] - self.angles[0])
        scan = LaserScan(self.t_ns, float(self.angles[0]), inc, ranges, cam.depth_min,
                         cam.depth_max)  # fmt: skip
        self.costmap.update_scan(scan, lp)
        self.scans += 1
        return True

    # 3b. Acting: one smoother period of motion.
    def command(self, v: float, w: float) -> None:
        """A controller output: the smoother's new target."""
        self.cmd = (v, w)
        self.smoother.set_target((v, 0.0, w), self.t_ns)

    def step(self, goal: int, status: str) -> None:
        out = self.smoother.tick(self.t_ns)
        self.vel = (out[0], out[2])
        self.pose = unicycle_step(self.pose, out[0], out[2], self.dt_ns / NS_PER_S)
        self.t_ns += self.dt_ns
        clear = clearance_at(self.plan, self.dist, self.pose[0], self.pose[1])
        self.min_clearance = min(self.min_clearance, clear)
        hit = clear < self.radius
        self.collision_steps += hit
        self.collision_events += hit and not self.in_collision
        self.in_collision = hit
        self._record(goal, status)

    def _record(self, goal: int, status: str) -> None:
        self.log.stamps_ns.append(self.t_ns)
        self.log.poses.append(self.pose.copy())
        self.log.rows.append((self.t_ns / NS_PER_S, goal, status, *self.cmd, *self.vel))

    def stop(self, goal: int) -> None:
        """Command zero and let the smoother bring the robot to rest."""
        self.command(0.0, 0.0)
        for _ in range(math.ceil(MAX_STOP_S * NS_PER_S / self.dt_ns)):
            if max(abs(self.vel[0]), abs(self.vel[1])) < STOP_EPS:
                break
            self.step(goal, "stopping")
        self.vel = (0.0, 0.0)

    # 3c. Planning.
    def make_plan(self, goal: tuple[float, float]) -> PlanResult:
        return self.planner.plan(self.costmap.master().copy(), self.costmap.geometry,
                                 (float(self.pose[0]), float(self.pose[1])), goal)  # fmt: skip

    def drive(
        self, k: int, goal: tuple[float, float], timeout_s: float, max_replans: int
    ) -> dict[str, Any]:
        """Plan to and follow one goal; its outcome (reached / failed) with a reason."""
        cfg = self.cfg
        t0, travelled0 = self.t_ns, len(self.log.poses)
        outcome: dict[str, Any] = {"goal": list(goal), "replans": 0}
        plan = self.make_plan(goal)
        if not plan.success:
            outcome.update(status="refused", reason=f"no path: {plan.reason}")
            return outcome
        outcome["first_plan"] = plan.poses[:, :2]
        outcome["planned_length_m"] = round(plan.length_m, 3)
        path = plan.poses
        status, reason = "failed", ""
        while True:
            if (self.t_ns - t0) / NS_PER_S > timeout_s:
                reason = f"timeout after {timeout_s:g} s"
                break
            replan_why = ""
            if self.sense():
                ahead = path_ahead(path[:, :2], self.pose[:2], self.inscribed)
                if replan_needed(ahead, self.costmap.master(), self.costmap.geometry,
                                 cfg.planner):  # fmt: skip
                    replan_why = "path blocked by a new obstacle"
            if not replan_why and self.t_ns >= self.next_ctrl_ns:
                self.next_ctrl_ns += self.ctrl_ns
                cmd = compute_velocity(
                    Pose2(*self.pose), path, self.vel, cfg.follower,
                    cost_fn=lambda x, y: float(self.costmap.cost_at(x, y)),
                    is_free=lambda x, y: bool(self.costmap.is_free(x, y)),
                    inscribed_radius_m=self.inscribed,
                )  # fmt: skip
                if cmd.status == "goal_reached":
                    status, reason = "reached", ""
                    break
                if cmd.status == "blocked":
                    replan_why = cmd.reason
                self.command(cmd.v, cmd.w)
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
                plan = self.make_plan(goal)
                if not plan.success:
                    reason = f"replan failed ({replan_why}): {plan.reason}"
                    break
                path = plan.poses
            self.step(k, "driving")
        self.stop(k)
        driven = np.array(self.log.poses[travelled0 - 1 :])[:, :2]
        outcome.update(
            status=status, reason=reason, time_s=round((self.t_ns - t0) / NS_PER_S, 2),
            driven_m=round(polyline_length(driven), 3),
            final_error_m=round(float(np.hypot(*(self.pose[:2] - np.asarray(goal)))), 3),
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


def commands_csv(rows: Sequence[tuple[float, int, str, float, float, float, float]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_HEADER)
    for t, goal, status, cv, cw, sv, sw in rows:
        w.writerow([f"{t:.3f}", goal, status, f"{cv:.4f}", f"{cw:.4f}", f"{sv:.4f}", f"{sw:.4f}"])
    return buf.getvalue()


def run_navigate(
    map_path: Path,
    goals: Sequence[Sequence[float]],
    world_path: Path,
    out: Path,
    config_files: Sequence[Path] = (),
    overrides: Sequence[str] = (),
    start: Sequence[float] | None = None,
    keepout_path: Path | None = None,
    goal_timeout_s: float = DEFAULT_GOAL_TIMEOUT_S,
    max_replans: int = DEFAULT_MAX_REPLANS,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[dict[str, Path], dict[str, Any]]:
    """Drive to every goal in turn; (files written, summary)."""
    wall0 = time.perf_counter()
    # 1. Inputs first: a bad map, world, goal or start fails before anything is written.
    loaded = load_map(map_path)
    goal_list = _check_goals(goals)
    if not goal_timeout_s > 0.0 or max_replans < 0:
        raise ConfigError(f"need --goal-timeout > 0 and --max-replans >= 0, got "
                          f"{goal_timeout_s} and {max_replans}")  # fmt: skip
    world = load_world(world_path)
    cfg = load_config(config_files, overrides)
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
    sim = _Sim(cfg, fp, costmap, s)
    if clearance_at(fp, sim.dist, s[0], s[1]) < sim.radius:
        raise MapError(f"start ({s[0]:.2f}, {s[1]:.2f}) puts the robot inside an obstacle of "
                       f"the world {world_path}")  # fmt: skip
    run = RunDir(out)
    outputs = {"config": run.write_config(cfg)}

    # 2. Drive to each goal in turn; a refused or failed goal moves on to the next one.
    sim.sense()  # look before planning the first goal
    outcomes: list[dict[str, Any]] = []
    for k, goal in enumerate(goal_list):
        problem = goal_problem(goal, costmap, loaded, keepout, cfg.planner.allow_unknown)
        if problem is not None:
            outcome = {"goal": list(goal), "status": "refused", "reason": problem, "replans": 0}
        else:
            outcome = sim.drive(k, goal, goal_timeout_s, max_replans)
        sim.stop(k)  # refused or not, the robot ends every goal at rest
        log.info("goal %d (%.2f, %.2f): %s %s", k, *goal, outcome["status"], outcome["reason"])
        outcomes.append(outcome)
        if progress is not None:
            progress(k + 1, len(goal_list))

    # 3. Trajectory, commands, picture, summary.
    stamps = np.array(sim.log.stamps_ns, dtype=np.int64)
    poses = np.array(sim.log.poses, dtype=np.float64)
    write_tum_trajectory(run.file("trajectory.tum"), stamps, poses[:, 0], poses[:, 1],
                         poses[:, 2])  # fmt: skip
    outputs["trajectory"] = run.file("trajectory.tum")
    atomic_write_text(run.file("commands.csv"), commands_csv(sim.log.rows))
    outputs["commands"] = run.file("commands.csv")
    g = loaded.grid.geometry
    paths = [(f"plan {i + 1}", o["first_plan"][:, 0], o["first_plan"][:, 1])
             for i, o in enumerate(outcomes) if "first_plan" in o]  # fmt: skip
    paths.append(("driven", poses[:, 0], poses[:, 1]))
    plot_trajectories(run.file("map.png"), paths, f"navigate in {map_path.name}",
                      occupied=loaded.grid.occupied_mask(loaded.occupied_thresh),
                      origin=(g.origin_x, g.origin_y), resolution=g.resolution)  # fmt: skip
    outputs["picture"] = run.file("map.png")
    for o in outcomes:
        o.pop("first_plan", None)
    sim_s = sim.t_ns / NS_PER_S
    wall_s = time.perf_counter() - wall0
    summary: dict[str, Any] = {
        "command": "navigate", "map": str(map_path), "map_kind": loaded.kind,
        "world": str(world_path), "keepout": None if keepout_path is None else str(keepout_path),
        "start": s.tolist(),
        "localisation": "ground truth: the navigator is given the true simulated pose "
                        "(the localiser is not wired in this version)",
        "goals": outcomes,
        "counts": {st: sum(o["status"] == st for o in outcomes)
                   for st in ("reached", "failed", "refused")},
        "collisions": {"events": sim.collision_events, "steps": sim.collision_steps,
                       "seconds": round(sim.collision_steps * sim.dt_ns / NS_PER_S, 2),
                       "robot_radius_m": sim.radius,
                       "min_clearance_m": round(sim.min_clearance, 3)},
        "path_length_m": round(polyline_length(poses[:, :2]), 3),
        "sim_time_s": round(sim_s, 2),
        "scans": sim.scans,
        "rates_hz": {"controller": cfg.follower.controller_frequency,
                     "smoother": cfg.smoother.smoothing_frequency,
                     "costmap": cfg.costmap.update_frequency},
        "wall_s": round(wall_s, 3),
        "real_time_factor": round(sim_s / wall_s, 1) if wall_s > 0 else None,
    }  # fmt: skip
    outputs["summary"] = run.write_summary(summary)
    return outputs, summary


def describe(summary: dict[str, Any]) -> str:
    """One line for the terminal."""
    c = summary["counts"]
    n = len(summary["goals"])
    return (f"{c['reached']}/{n} goals reached, {c['failed']} failed, {c['refused']} refused; "
            f"{summary['collisions']['events']} collision(s), {summary['path_length_m']:.2f} m "
            f"in {summary['sim_time_s']:.1f} s simulated")  # fmt: skip


__all__ = ["cast_scan", "clearance_map", "commands_csv", "describe", "goal_problem",
           "parse_goal_args", "path_ahead", "run_navigate", "unicycle_step"]  # fmt: skip
