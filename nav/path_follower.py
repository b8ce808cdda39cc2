"""Regulated pure pursuit (Nav2 nav2_regulated_pure_pursuit_controller semantics) as a pure kernel.

One call of :func:`compute_velocity` is one controller cycle:

1. goal check (SimpleGoalChecker): within ``xy_goal_tolerance`` and ``yaw_goal_tolerance`` -> done;
   within xy but not yaw -> turn in place toward the goal heading;
2. project the robot onto the path and pick the lookahead ``L`` (fixed, or ``speed *
   lookahead_time`` clamped to [min, max]);
3. the carrot is where the path leaves the circle of radius ``L`` around the robot (interpolated
   on the crossing segment; the goal itself when the path ends inside the circle);
4. rotate to heading: if the carrot's bearing exceeds ``rotate_to_heading_min_angle`` turn in place;
5. pure pursuit curvature ``kappa = 2 y / (x^2 + y^2)`` of the carrot (x, y) in base_link;
6. regulate the speed: curvature (slow when ``1/|kappa|`` < min radius), cost (slow near
   obstacles, distance recovered from the inflation cost), floored at the min regulated speed,
   then approach scaling near the goal (floored at ``min_approach_linear_velocity``);
7. ``w = v * kappa``; forward-simulate that arc for ``max_allowed_time_to_collision_up_to_carrot``
   (never past the carrot) and stop with status ``blocked`` if ``is_free`` rejects a sample.

Expected failures (blocked arc) are return values with a reason, never exceptions.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from nav.config import NO_INFORMATION, FollowerConfig
from sensors.types import Pose2

FollowerStatus = Literal["following", "rotating", "goal_reached", "blocked"]
CostFn = Callable[[float, float], float]  # (x [m], y [m]) in the path frame -> costmap cost 0..255
FreeFn = Callable[[float, float], bool]  # (x [m], y [m]) in the path frame -> traversable

FREE_SPACE = 0  # costmap_2d cell value
INSCRIBED_INFLATED_OBSTACLE = 253  # costmap_2d cell value: the robot centre touches an obstacle
MIN_CARROT_DIST2 = 1e-3  # [m^2] below this the carrot is on the robot: no curvature (as Nav2)
COLLISION_CHECK_STEP_M = 0.05  # [m] arc sampling step; about one costmap cell


@dataclass(frozen=True)
class FollowerCommand:
    """One controller output in base_link."""

    v: float  # [m/s] forward speed
    w: float  # [rad/s] yaw rate, counter-clockwise positive
    status: FollowerStatus
    reason: str = ""
    carrot: tuple[float, float] | None = None  # [m] carrot (x, y) in base_link, for display
    lookahead_m: float = 0.0  # [m] lookahead used this cycle


# --- geometry ----------------------------------------------------------------------------------


def _to_robot_frame(pose: Pose2, xy: np.ndarray) -> np.ndarray:
    """(N, 2) points in the path frame -> (N, 2) in base_link."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    d = xy - np.array([pose.x, pose.y])
    return np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def project_onto_path(xy_r: np.ndarray) -> tuple[int, np.ndarray]:
    """Closest point of the polyline (base_link, robot at the origin) to the robot.

    Returns (k, p): the point p lies on segment k (between vertices k and k+1)."""
    if len(xy_r) == 1:
        return 0, xy_r[0]
    a, b = xy_r[:-1], xy_r[1:]
    d = b - a
    len2 = np.einsum("ij,ij->i", d, d)
    t = np.clip(-np.einsum("ij,ij->i", a, d) / np.maximum(len2, 1e-12), 0.0, 1.0)
    p = a + t[:, None] * d
    k = int(np.argmin(np.einsum("ij,ij->i", p, p)))
    return k, p[k]


def lookahead_distance(speed: float, config: FollowerConfig) -> float:
    """Fixed lookahead, or ``|speed| * lookahead_time`` clamped to [min, max] (Nav2's rule)."""
    if not config.use_velocity_scaled_lookahead_dist:
        return config.lookahead_dist
    return float(
        np.clip(
            abs(speed) * config.lookahead_time, config.min_lookahead_dist, config.max_lookahead_dist
        )
    )


def find_carrot(points_r: np.ndarray, lookahead: float) -> np.ndarray:
    """The point where the polyline ``points_r`` (starting at the robot's projection) first leaves
    the circle of radius ``lookahead`` around the robot; its last point if it never does."""
    dist = np.hypot(points_r[:, 0], points_r[:, 1])
    beyond = np.flatnonzero(dist >= lookahead)
    if beyond.size == 0:
        return points_r[-1]
    j = int(beyond[0])
    if j == 0:
        return points_r[0]  # off the path by more than L: head for the closest point
    # Solve |a + t (b - a)| = L for the root in [0, 1] on the crossing segment.
    a, d = points_r[j - 1], points_r[j] - points_r[j - 1]
    qa, qb, qc = float(d @ d), 2.0 * float(a @ d), float(a @ a) - lookahead**2
    if qa < 1e-12:
        return points_r[j]
    t = (-qb + math.sqrt(max(qb * qb - 4.0 * qa * qc, 0.0))) / (2.0 * qa)
    return a + min(max(t, 0.0), 1.0) * d


def pure_pursuit_curvature(carrot: np.ndarray) -> float:
    """kappa = 2 y / L^2 for a carrot (x, y) at distance L in base_link."""
    dist2 = float(carrot @ carrot)
    return 2.0 * float(carrot[1]) / dist2 if dist2 > MIN_CARROT_DIST2 else 0.0


# --- regulation --------------------------------------------------------------------------------


def curvature_constraint(v: float, curvature: float, config: FollowerConfig) -> float:
    """Scale v by radius / min_radius when the turn radius is below min_radius."""
    if not config.use_regulated_linear_velocity_scaling or curvature == 0.0:
        return v
    radius = abs(1.0 / curvature)
    min_radius = config.regulated_linear_scaling_min_radius
    return v * radius / min_radius if radius < min_radius else v


def cost_constraint(
    v: float, pose_cost: float, inscribed_radius_m: float, config: FollowerConfig
) -> float:
    """Slow down near obstacles: invert the inflation decay to get the obstacle distance.

    cost = 252 exp(-factor (d - r_inscribed))  =>  d = -ln(cost / 252) / factor + r_inscribed."""
    if not config.use_cost_regulated_linear_velocity_scaling:
        return v
    if pose_cost in (NO_INFORMATION, FREE_SPACE):
        return v
    ratio = min(pose_cost, INSCRIBED_INFLATED_OBSTACLE - 1) / (INSCRIBED_INFLATED_OBSTACLE - 1)
    dist = -math.log(ratio) / config.inflation_cost_scaling_factor + inscribed_radius_m
    if dist < config.cost_scaling_dist:
        return v * config.cost_scaling_gain * dist / config.cost_scaling_dist
    return v


def approach_constraint(v: float, remaining_m: float, config: FollowerConfig) -> float:
    """Scale v by remaining / approach_velocity_scaling_dist near the goal, floored."""
    if (
        config.approach_velocity_scaling_dist <= 0.0
        or remaining_m >= config.approach_velocity_scaling_dist
    ):
        return v
    scaled = v * remaining_m / config.approach_velocity_scaling_dist
    return min(v, max(scaled, config.min_approach_linear_velocity))


def regulated_speed(
    curvature: float,
    pose_cost: float | None,
    remaining_m: float,
    inscribed_radius_m: float,
    config: FollowerConfig,
) -> float:
    """Nav2 applyConstraints: min(curvature, cost) floored at the min speed, then approach."""
    v = config.desired_linear_vel
    v_curv = curvature_constraint(v, curvature, config)
    v_cost = v if pose_cost is None else cost_constraint(v, pose_cost, inscribed_radius_m, config)
    v = max(min(v_curv, v_cost), config.regulated_linear_scaling_min_speed)
    v = approach_constraint(v, remaining_m, config)
    return float(np.clip(v, 0.0, config.desired_linear_vel))


def rotate_to_heading(angle: float, current_w: float | None, config: FollowerConfig) -> float:
    """Turn-in-place rate toward ``angle`` [rad]: the configured rate, slowed so it can stop at
    the heading under ``max_angular_accel``, and reachable from ``current_w`` within one cycle."""
    a_max = config.max_angular_accel
    w = math.copysign(
        min(config.rotate_to_heading_angular_vel, math.sqrt(2.0 * a_max * abs(angle))), angle
    )
    if current_w is not None:
        dw = a_max / config.controller_frequency
        w = min(max(w, current_w - dw), current_w + dw)
    return w


def arc_samples(pose: Pose2, v: float, w: float, horizon_m: float, step_m: float) -> np.ndarray:
    """(M, 2) points in the path frame along the arc driven at (v, w) for ``horizon_m`` metres."""
    n = max(int(math.ceil(horizon_m / step_m)), 1)
    s = np.linspace(horizon_m / n, horizon_m, n) * math.copysign(1.0, v)
    kappa = w / v
    if abs(kappa) < 1e-9:
        xr, yr = s, np.zeros_like(s)
    else:
        xr, yr = np.sin(kappa * s) / kappa, (1.0 - np.cos(kappa * s)) / kappa
    c, sn = math.cos(pose.yaw), math.sin(pose.yaw)
    return np.column_stack((pose.x + c * xr - sn * yr, pose.y + sn * xr + c * yr))


# --- the controller cycle ----------------------------------------------------------------------


def compute_velocity(
    pose: Pose2,
    path: np.ndarray,
    current_speed: float | tuple[float, float],
    config: FollowerConfig,
    cost_fn: CostFn | None = None,
    is_free: FreeFn | None = None,
    *,
    inscribed_radius_m: float = 0.0,
    collision_step_m: float = COLLISION_CHECK_STEP_M,
) -> FollowerCommand:
    """One regulated-pure-pursuit cycle.

    ``path`` is (N, 3) (x [m], y [m], yaw [rad]) in the frame of ``pose``; its last row is the goal.
    ``current_speed`` is v [m/s] or the odometry twist (v, w); with w, turn-in-place respects
    ``max_angular_accel``. ``cost_fn`` gives the costmap cost at the robot (cost regulation,
    ``inscribed_radius_m`` is the costmap's inscribed radius); ``is_free`` vets the arc."""
    path = np.asarray(path, dtype=np.float64)
    if path.ndim != 2 or path.shape[1] != 3 or len(path) == 0:
        raise ValueError(f"path must be a non-empty (N, 3) array, got shape {path.shape}")
    v_now, w_now = (
        (current_speed, None) if isinstance(current_speed, int | float) else current_speed
    )

    # 1. Goal check; inside the xy tolerance only the heading is left to fix.
    gx, gy, gyaw = path[-1]
    yaw_err = _wrap(float(gyaw) - pose.yaw)
    if math.hypot(gx - pose.x, gy - pose.y) <= config.xy_goal_tolerance:
        if abs(yaw_err) <= config.yaw_goal_tolerance:
            return FollowerCommand(0.0, 0.0, "goal_reached", "within xy and yaw tolerance")
        w = rotate_to_heading(yaw_err, w_now, config)
        return FollowerCommand(0.0, w, "rotating", f"goal heading off by {yaw_err:+.2f} rad")

    # 2. Project onto the path; what lies ahead starts at the projection.
    xy_r = _to_robot_frame(pose, path[:, :2])
    k, proj = project_onto_path(xy_r)
    ahead = np.vstack((proj, xy_r[k + 1 :]))
    remaining_m = float(np.sum(np.hypot(*np.diff(ahead, axis=0).T))) if len(ahead) > 1 else 0.0
    lookahead = lookahead_distance(v_now, config)

    # 3. Carrot on the lookahead circle.
    carrot = find_carrot(ahead, lookahead)
    carrot_xy = (float(carrot[0]), float(carrot[1]))
    bearing = math.atan2(carrot[1], carrot[0])

    # 4. Turn in place first when the carrot is too far off the nose.
    if config.use_rotate_to_heading and abs(bearing) > config.rotate_to_heading_min_angle:
        w = rotate_to_heading(bearing, w_now, config)
        return FollowerCommand(
            0.0, w, "rotating", f"path bearing {bearing:+.2f} rad", carrot_xy, lookahead
        )

    # 5. Pure pursuit curvature; drive backwards to a carrot behind when reversing is allowed.
    curvature = pure_pursuit_curvature(carrot)
    direction = -1.0 if config.allow_reversing and carrot[0] < 0.0 else 1.0

    # 6. Regulated linear speed.
    pose_cost = None if cost_fn is None else float(cost_fn(pose.x, pose.y))
    v = direction * regulated_speed(curvature, pose_cost, remaining_m, inscribed_radius_m, config)
    w = v * curvature

    # 7. Collision check of the arc, up to the carrot and the time horizon.
    if config.use_collision_detection and is_free is not None and v != 0.0:
        horizon = min(
            abs(v) * config.max_allowed_time_to_collision_up_to_carrot, math.hypot(*carrot_xy)
        )
        if horizon > 0.0:
            for x, y in arc_samples(pose, v, w, horizon, collision_step_m):
                if not is_free(float(x), float(y)):
                    return FollowerCommand(
                        0.0,
                        0.0,
                        "blocked",
                        f"collision ahead at ({x:.2f}, {y:.2f}) within {horizon:.2f} m",
                        carrot_xy,
                        lookahead,
                    )
    return FollowerCommand(v, w, "following", "", carrot_xy, lookahead)
