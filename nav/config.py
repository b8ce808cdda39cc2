"""Config sections owned by the nav layer: costmap, planner, path follower, velocity smoother.

Names and defaults follow Nav2 (nav2_costmap_2d, NavFn / global_planner, regulated pure pursuit,
nav2_velocity_smoother, SimpleGoalChecker). Where a default differs from Nav2's code default the
field's doc says so. Declared with :func:`sensors.config.param`; see ``config/<section>.yaml``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from sensors.config import param

# costmap_2d cell values.
NO_INFORMATION = 255
LETHAL_OBSTACLE = 254


@dataclass(frozen=True)
class CostmapConfig:
    """Layered costmap (static, obstacle with ray clearing, inflation) with Nav2 semantics."""

    resolution: float = param(0.05, unit="m/cell", gt=0.0, doc="cell size (Nav2 code default 0.1)")
    robot_radius: float = param(
        0.23, unit="m", gt=0.0, doc="circular footprint; keep equal to robot.radius"
    )
    footprint_padding: float = param(0.01, unit="m", ge=0.0, doc="added to the footprint")
    update_frequency: float = param(5.0, unit="Hz", gt=0.0, doc="costmap update rate")
    rolling_window: bool = param(False, doc="local costmap centred on the robot")
    width: int = param(5, unit="m", ge=1, doc="rolling window width")
    height: int = param(5, unit="m", ge=1, doc="rolling window height")
    # Static layer.
    track_unknown_space: bool = param(
        True, doc="keep unknown cells unknown (Nav2 code default false)"
    )
    lethal_cost_threshold: int = param(
        100, ge=0, le=100, doc="map occupancy at or above which a cell is lethal"
    )
    unknown_cost_value: int = param(255, ge=0, le=255, doc="map value that means unknown")
    trinary_costmap: bool = param(True, doc="map cells are free, lethal or unknown only")
    # Obstacle layer.
    obstacle_max_range: float = param(2.5, unit="m", gt=0.0, doc="mark obstacles up to here")
    obstacle_min_range: float = param(0.0, unit="m", ge=0.0, doc="mark obstacles from here")
    raytrace_max_range: float = param(3.0, unit="m", gt=0.0, doc="clear free space up to here")
    raytrace_min_range: float = param(0.0, unit="m", ge=0.0, doc="clear free space from here")
    inf_is_valid: bool = param(
        True, doc="no-return beams clear up to raytrace_max_range (Nav2 code default false)"
    )
    # Inflation layer.
    inflation_radius: float = param(
        0.55, unit="m", ge=0.0, doc="inflate lethal cells out to this distance"
    )
    cost_scaling_factor: float = param(
        3.0, unit="1/m", gt=0.0, doc="exponential cost decay (Nav2 code 10.0, nav2_params 3.0)"
    )
    inflate_unknown: bool = param(False, doc="inflate unknown cells as if lethal")
    inflate_around_unknown: bool = param(False, doc="inflate around unknown cells")
    # Keepout filter.
    inflate_keepout: bool = param(
        True,
        doc="inflate keepout zones like obstacles so the footprint stays out (Nav2 filters "
        "run after inflation: false lets the robot centre reach the zone's edge)",
    )

    def validate(self) -> str | None:
        if self.obstacle_min_range >= self.obstacle_max_range:
            return (
                f"obstacle_min_range ({self.obstacle_min_range}) must be below "
                f"obstacle_max_range ({self.obstacle_max_range})"
            )
        if self.raytrace_min_range >= self.raytrace_max_range:
            return (
                f"raytrace_min_range ({self.raytrace_min_range}) must be below "
                f"raytrace_max_range ({self.raytrace_max_range})"
            )
        if 0.0 < self.inflation_radius < self.robot_radius:
            return (
                f"inflation_radius ({self.inflation_radius}) must be at least "
                f"robot_radius ({self.robot_radius})"
            )
        return None


@dataclass(frozen=True)
class PlannerConfig:
    """Grid planner with NavFn parameters, global_planner cost mapping and Nav2 SimpleSmoother."""

    tolerance: float = param(
        0.5, unit="m", ge=0.0, doc="plan to the nearest free cell within this of the goal"
    )
    use_astar: bool = param(
        False, doc="A* instead of Dijkstra (same path cost, half the cells settled; ties differ)"
    )
    allow_unknown: bool = param(True, doc="plan through unknown space")
    use_final_approach_orientation: bool = param(
        False, doc="goal yaw = direction of the last path segment"
    )
    # Cell traversal cost = neutral_cost + cost_factor * costmap_cost (global_planner).
    neutral_cost: int = param(50, ge=1, doc="cost of a free cell")
    cost_factor: float = param(3.0, ge=0.0, doc="weight of the costmap cost")
    lethal_cost: int = param(253, ge=1, le=255, doc="costmap cost treated as impassable")
    # Path smoothing (nav2_smoother SimpleSmoother).
    smooth_path: bool = param(True, doc="smooth the grid path before following it")
    smoothing_w_data: float = param(0.2, ge=0.0, doc="weight pulling toward the raw path")
    smoothing_w_smooth: float = param(0.3, ge=0.0, doc="weight pulling toward a straight path")
    smoothing_tolerance: float = param(1.0e-10, gt=0.0, doc="stop when the update is below")
    smoothing_max_its: int = param(1000, ge=1, doc="max smoothing iterations")
    smoothing_do_refinement: bool = param(True, doc="run the smoother again on its output")

    def validate(self) -> str | None:
        if self.neutral_cost >= self.lethal_cost:
            return (
                f"neutral_cost ({self.neutral_cost}) must be below lethal_cost ({self.lethal_cost})"
            )
        return None


@dataclass(frozen=True)
class FollowerConfig:
    """Regulated pure pursuit (Nav2 parameter names and defaults) plus SimpleGoalChecker."""

    controller_frequency: float = param(20.0, unit="Hz", gt=0.0, doc="control loop rate")
    desired_linear_vel: float = param(0.5, unit="m/s", gt=0.0, doc="cruise speed")
    lookahead_dist: float = param(
        0.6, unit="m", gt=0.0, doc="carrot distance when not velocity-scaled"
    )
    min_lookahead_dist: float = param(0.3, unit="m", gt=0.0, doc="lower clamp on lookahead")
    max_lookahead_dist: float = param(0.9, unit="m", gt=0.0, doc="upper clamp on lookahead")
    lookahead_time: float = param(1.5, unit="s", gt=0.0, doc="lookahead = speed * this")
    use_velocity_scaled_lookahead_dist: bool = param(False, doc="scale lookahead with speed")
    rotate_to_heading_angular_vel: float = param(
        1.8, unit="rad/s", gt=0.0, doc="turn-in-place speed"
    )
    use_rotate_to_heading: bool = param(True, doc="turn in place toward the path first")
    rotate_to_heading_min_angle: float = param(
        0.785, unit="rad", ge=0.0, doc="turn in place above this heading error"
    )
    max_angular_accel: float = param(3.2, unit="rad/s^2", gt=0.0, doc="while turning in place")
    use_regulated_linear_velocity_scaling: bool = param(True, doc="slow down in tight turns")
    regulated_linear_scaling_min_radius: float = param(
        0.9, unit="m", gt=0.0, doc="slow down below this path curvature radius"
    )
    regulated_linear_scaling_min_speed: float = param(
        0.25, unit="m/s", ge=0.0, doc="regulation never goes below this"
    )
    use_cost_regulated_linear_velocity_scaling: bool = param(True, doc="slow down near obstacles")
    cost_scaling_dist: float = param(
        0.6, unit="m", ge=0.0, doc="start slowing within this distance of obstacles"
    )
    cost_scaling_gain: float = param(1.0, ge=0.0, le=1.0, doc="strength of the slowdown")
    inflation_cost_scaling_factor: float = param(
        3.0, unit="1/m", gt=0.0, doc="must equal costmap.cost_scaling_factor"
    )
    min_approach_linear_velocity: float = param(
        0.05, unit="m/s", ge=0.0, doc="min speed while approaching the goal"
    )
    approach_velocity_scaling_dist: float = param(
        0.6, unit="m", ge=0.0, doc="start slowing this far from the goal"
    )
    use_collision_detection: bool = param(True, doc="check the arc to the carrot")
    max_allowed_time_to_collision_up_to_carrot: float = param(
        1.0, unit="s", gt=0.0, doc="forward-simulated collision horizon"
    )
    allow_reversing: bool = param(False, doc="follow path segments backwards")
    transform_tolerance: float = param(0.1, unit="s", ge=0.0, doc="allowed pose staleness")
    # Goal checker (nav2_controller SimpleGoalChecker).
    xy_goal_tolerance: float = param(0.25, unit="m", gt=0.0, doc="goal reached within this")
    yaw_goal_tolerance: float = param(0.25, unit="rad", gt=0.0, doc="goal yaw reached within this")

    def validate(self) -> str | None:
        if self.min_lookahead_dist > self.max_lookahead_dist:
            return (
                f"min_lookahead_dist ({self.min_lookahead_dist}) must not exceed "
                f"max_lookahead_dist ({self.max_lookahead_dist})"
            )
        if self.use_rotate_to_heading and self.allow_reversing:
            return "use_rotate_to_heading and allow_reversing cannot both be true"
        if self.regulated_linear_scaling_min_speed > self.desired_linear_vel:
            return (
                f"regulated_linear_scaling_min_speed ({self.regulated_linear_scaling_min_speed})"
                f" must not exceed desired_linear_vel ({self.desired_linear_vel})"
            )
        return None


@dataclass(frozen=True)
class SmootherConfig:
    """Velocity smoother with nav2_velocity_smoother semantics; vectors are (x, y, theta)."""

    smoothing_frequency: float = param(20.0, unit="Hz", gt=0.0, doc="command output rate")
    scale_velocities: bool = param(False, doc="scale all axes together to keep the direction")
    feedback: Literal["OPEN_LOOP", "CLOSED_LOOP"] = param(
        "OPEN_LOOP", doc="current velocity from the last command or from odometry"
    )
    max_velocity: tuple[float, float, float] = param(
        (0.5, 0.0, 2.5), unit="m/s, m/s, rad/s", doc="upper velocity limits"
    )
    min_velocity: tuple[float, float, float] = param(
        (-0.5, 0.0, -2.5), unit="m/s, m/s, rad/s", doc="lower velocity limits"
    )
    max_accel: tuple[float, float, float] = param(
        (2.5, 0.0, 3.2), unit="m/s^2, m/s^2, rad/s^2", ge=0.0, doc="acceleration limits"
    )
    max_decel: tuple[float, float, float] = param(
        (-2.5, 0.0, -3.2), unit="m/s^2, m/s^2, rad/s^2", le=0.0, doc="deceleration limits"
    )
    deadband_velocity: tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), unit="m/s, m/s, rad/s", ge=0.0, doc="smaller commands become zero"
    )
    velocity_timeout: float = param(
        1.0, unit="s", gt=0.0, doc="decelerate to zero when no command arrives"
    )
    odom_duration: float = param(
        0.1, unit="s", gt=0.0, doc="odometry averaging window in CLOSED_LOOP"
    )

    def validate(self) -> str | None:
        for i, (lo, hi) in enumerate(zip(self.min_velocity, self.max_velocity, strict=True)):
            if lo > hi:
                return f"min_velocity[{i}] ({lo}) must not exceed max_velocity[{i}] ({hi})"
            # Nav2 rejects these too: the limits must bracket zero so a stop is always allowed.
            if lo > 0.0:
                return f"min_velocity[{i}] ({lo}) must not be positive"
            if hi < 0.0:
                return f"max_velocity[{i}] ({hi}) must not be negative"
        return None


@dataclass(frozen=True)
class NavigateConfig:
    """A navigate run (``rgbdnav navigate``): per-goal limits, waypoint following, localisation
    and the progress checker (nav2_waypoint_follower / nav2_controller names where they exist)."""

    localization: Literal["localizer", "groundtruth"] = param(
        "localizer", doc="localizer: scan-to-map + wheel odometry; groundtruth: the true pose"
    )
    goal_timeout: float = param(60.0, unit="s", gt=0.0, doc="simulated time allowed per goal")
    max_replans: int = param(5, ge=0, doc="replans per goal before it fails")
    replan_frequency: float = param(
        0.0,
        unit="Hz",
        ge=0.0,
        doc="plan again at this rate while driving, on the costmap as it is now (Nav2's default "
        "behaviour tree: 1 Hz); a failed periodic plan keeps the current path and does not "
        "count as a replan (0 = plan only at the start, when the path is blocked and when stuck)",
    )
    waypoint_pause_duration: float = param(
        0.0, unit="s", ge=0.0, doc="WaitAtWaypoint task at each reached goal (0 = none)"
    )
    stop_on_failure: bool = param(False, doc="skip the remaining goals after a failed one")
    required_movement_radius: float = param(
        0.5, unit="m", gt=0.0, doc="progress checker: move this far ..."
    )
    movement_time_allowance: float = param(
        10.0, unit="s", gt=0.0, doc="... within this long, or recover (clear costmap, back up)"
    )
    collision_hold_allowance: float = param(
        0.0,
        unit="s",
        ge=0.0,
        doc="the progress checker's allowance while the collision monitor holds the robot: "
        "this long cut to a stop (in total) without moving required_movement_radius, and it "
        "recovers as when stuck (clear costmap, back up: the camera, blind nearer than 0.45 m, "
        "sees what is too close again) and replans (0 = off: movement_time_allowance only; "
        "3 s was measured and not kept, docs/design/navigator.md)",
    )
    global_relocalization: bool = param(
        False,
        doc="let the localiser relocalise globally while driving (turning in place until it "
        "tracks); false: put it back on the odometry pose (wheels moving = not kidnapped)",
    )
    relocalize_spin_speed: float = param(
        0.4, unit="rad/s", gt=0.0, doc="turn in place at this while relocalising globally"
    )
    relocalize_timeout: float = param(
        30.0, unit="s", gt=0.0, doc="a goal fails after this long without a believable fix"
    )
    goal_settle_spin: float = param(
        0.0,
        unit="rad",
        ge=0.0,
        doc="at a goal the estimate says is reached, turn in place this far and correct the pose "
        "with the turn's scans stacked by odometry (a wide view, in which a moved piece of "
        "furniture weighs little), then drive on if the corrected estimate is outside "
        "follower.xy_goal_tolerance (0 = off: Nav2's goal checker; localizer mode only)",
    )
    goal_settle_spin_speed: float = param(
        1.0, unit="rad/s", gt=0.0, doc="turn-in-place speed of the goal settle (Nav2 Spin's)"
    )
    goal_settle_attempts: int = param(
        1, ge=1, doc="settles per goal (each a turn; the goal is reached after the last)"
    )
    settle_on_gated_scans: int = param(
        0,
        ge=0,
        doc="while driving, stop and settle (a goal_settle_spin turn and its wide match) after "
        "this many consecutive scans whose matches the localiser gated (its estimate and the "
        "scans disagree), then replan (0 = never)",
    )


@dataclass(frozen=True)
class CollisionMonitorConfig:
    """Nav2's collision_monitor, between any command (navigator, teleop) and the wheels.

    A stop and a slowdown zone ahead of the footprint, checked against what the camera saw in
    base_link (scans carried by wheel odometry), never against the map pose."""

    enabled: bool = param(True, doc="limit every command before it reaches the wheels")
    stop_distance: float = param(
        0.12,
        unit="m",
        ge=0.0,
        doc="stop zone: no forward motion with a point this far ahead of the footprint",
    )
    slowdown_distance: float = param(
        0.4, unit="m", ge=0.0, doc="slowdown zone: slow down with a point this far ahead"
    )
    slowdown_ratio: float = param(
        0.4, gt=0.0, le=1.0, doc="forward speed factor in the slowdown zone (Nav2's name)"
    )
    lateral_margin: float = param(
        0.05, unit="m", ge=0.0, doc="both zones this much wider than the footprint on each side"
    )
    observation_memory: float = param(
        10.0,
        unit="s",
        gt=0.0,
        doc="scans kept, carried by wheel odometry: the Kinect is blind nearer than 0.45 m and "
        "beside its 58 deg view, so a door jamb is seen seconds before the robot passes it",
    )
