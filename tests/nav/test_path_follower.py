"""Regulated pure pursuit: geometry, regulation, rotate-to-heading, goal, collision, closed loop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nav.config import FollowerConfig, SmootherConfig
from nav.path_follower import (
    compute_velocity,
    cost_constraint,
    find_carrot,
    lookahead_distance,
    pure_pursuit_curvature,
)
from nav.velocity_smoother import VelocitySmoother
from sensors.types import Pose2

CFG = FollowerConfig()
STEP = 0.05  # [m] path sampling


def polyline(*vertices: tuple[float, float], step: float = STEP) -> np.ndarray:
    """Densely sampled (N, 3) path through the vertices; yaw along each segment."""
    pts: list[np.ndarray] = []
    for (x0, y0), (x1, y1) in zip(vertices, vertices[1:], strict=False):
        n = max(int(round(math.hypot(x1 - x0, y1 - y0) / step)), 1)
        t = np.linspace(0.0, 1.0, n, endpoint=False)[:, None]
        seg = np.hstack((x0 + t * (x1 - x0), y0 + t * (y1 - y0)))
        yaw = np.full((n, 1), math.atan2(y1 - y0, x1 - x0))
        pts.append(np.hstack((seg, yaw)))
    last_yaw = pts[-1][-1, 2]
    pts.append(np.array([[vertices[-1][0], vertices[-1][1], last_yaw]]))
    return np.vstack(pts)


def arc_path(radius: float, length: float) -> np.ndarray:
    """Left-turning circular arc from the origin heading +x."""
    s = np.arange(0.0, length, STEP)
    th = s / radius
    return np.column_stack((radius * np.sin(th), radius * (1 - np.cos(th)), th))


def test_straight_path_drives_at_desired_speed_without_turning() -> None:
    path = polyline((0.0, 0.0), (5.0, 0.0))
    cmd = compute_velocity(Pose2(0.0, 0.0, 0.0), path, 0.5, CFG)
    assert cmd.status == "following"
    assert cmd.v == pytest.approx(CFG.desired_linear_vel)
    assert cmd.w == pytest.approx(0.0, abs=1e-9)
    assert cmd.carrot == pytest.approx((CFG.lookahead_dist, 0.0), abs=1e-9)


def test_curve_turns_at_pure_pursuit_curvature_of_the_carrot() -> None:
    cfg = FollowerConfig(use_regulated_linear_velocity_scaling=False)
    path = arc_path(radius=2.0, length=3.0)
    cmd = compute_velocity(Pose2(0.0, 0.0, 0.0), path, 0.5, cfg)
    assert cmd.carrot is not None
    x, y = cmd.carrot
    assert math.hypot(x, y) == pytest.approx(cfg.lookahead_dist, abs=1e-6)
    assert cmd.w == pytest.approx(cmd.v * 2.0 * y / cfg.lookahead_dist**2, rel=1e-9)
    # A carrot on a circle through the robot tangent to its heading gives that circle's curvature.
    assert cmd.w / cmd.v == pytest.approx(1.0 / 2.0, rel=1e-3)


def test_pure_pursuit_formula_on_hand_carrot() -> None:
    assert pure_pursuit_curvature(np.array([0.3, 0.4])) == pytest.approx(2 * 0.4 / 0.25)
    assert pure_pursuit_curvature(np.array([0.0, 0.0])) == 0.0


def test_regulation_slows_in_tight_curves() -> None:
    wide = compute_velocity(Pose2(0, 0, 0), arc_path(3.0, 3.0), 0.5, CFG)
    tight = compute_velocity(Pose2(0, 0, 0), arc_path(0.6, 1.5), 0.5, CFG)
    assert wide.v == pytest.approx(CFG.desired_linear_vel)
    assert tight.status == "following"
    radius = abs(tight.v / tight.w)
    expected = max(
        CFG.desired_linear_vel * radius / CFG.regulated_linear_scaling_min_radius,
        CFG.regulated_linear_scaling_min_speed,
    )
    assert tight.v == pytest.approx(expected, rel=1e-6)
    assert tight.v < wide.v


def test_cost_regulation_slows_near_obstacles() -> None:
    path = polyline((0.0, 0.0), (5.0, 0.0))
    near = compute_velocity(Pose2(0, 0, 0), path, 0.5, CFG, cost_fn=lambda x, y: 200.0)
    free = compute_velocity(Pose2(0, 0, 0), path, 0.5, CFG, cost_fn=lambda x, y: 0.0)
    assert free.v == pytest.approx(CFG.desired_linear_vel)
    assert near.v < free.v
    assert near.v >= CFG.regulated_linear_scaling_min_speed - 1e-12
    # The inverse of the inflation decay: cost 252 is the inscribed radius, here 0.
    assert cost_constraint(1.0, 252.0, 0.0, CFG) == pytest.approx(0.0)


def test_velocity_scaled_lookahead_is_clamped() -> None:
    cfg = FollowerConfig(use_velocity_scaled_lookahead_dist=True)
    assert lookahead_distance(0.0, cfg) == cfg.min_lookahead_dist
    assert lookahead_distance(0.4, cfg) == pytest.approx(0.4 * cfg.lookahead_time)
    assert lookahead_distance(5.0, cfg) == cfg.max_lookahead_dist


def test_carrot_is_last_point_when_path_ends_inside_lookahead() -> None:
    pts = np.array([[0.1, 0.0], [0.2, 0.1]])
    assert find_carrot(pts, 1.0) == pytest.approx([0.2, 0.1])


def test_rotates_in_place_when_facing_away_from_the_path() -> None:
    path = polyline((0.0, 0.0), (5.0, 0.0))
    cmd = compute_velocity(Pose2(0.0, 0.0, math.pi / 2), path, 0.0, CFG)
    assert cmd.status == "rotating"
    assert cmd.v == 0.0
    assert cmd.w < 0.0  # clockwise, toward +x
    assert abs(cmd.w) <= CFG.rotate_to_heading_angular_vel + 1e-12


def test_rotation_respects_angular_acceleration_from_current_twist() -> None:
    path = polyline((0.0, 0.0), (5.0, 0.0))
    cmd = compute_velocity(Pose2(0.0, 0.0, math.pi / 2), path, (0.0, 0.0), CFG)
    assert cmd.w == pytest.approx(-CFG.max_angular_accel / CFG.controller_frequency)


def test_small_heading_error_does_not_trigger_rotation() -> None:
    path = polyline((0.0, 0.0), (5.0, 0.0))
    cmd = compute_velocity(Pose2(0.0, 0.0, 0.3), path, 0.5, CFG)
    assert cmd.status == "following"
    assert cmd.w < 0.0


def test_goal_reached_within_tolerances() -> None:
    path = polyline((0.0, 0.0), (2.0, 0.0))
    cmd = compute_velocity(Pose2(1.9, 0.05, 0.1), path, 0.1, CFG)
    assert cmd.status == "goal_reached"
    assert (cmd.v, cmd.w) == (0.0, 0.0)


def test_at_goal_position_with_wrong_heading_rotates_to_goal_yaw() -> None:
    path = polyline((0.0, 0.0), (2.0, 0.0))
    cmd = compute_velocity(Pose2(1.95, 0.0, 1.0), path, 0.0, CFG)
    assert cmd.status == "rotating"
    assert cmd.v == 0.0 and cmd.w < 0.0


def test_approach_scaling_slows_near_goal() -> None:
    path = polyline((0.0, 0.0), (1.0, 0.0))
    far = compute_velocity(Pose2(0.0, 0.0, 0.0), path, 0.5, CFG)
    near = compute_velocity(Pose2(0.7, 0.0, 0.0), path, 0.5, CFG)
    assert far.v == pytest.approx(CFG.desired_linear_vel)
    remaining = 0.3
    assert near.v == pytest.approx(
        CFG.desired_linear_vel * remaining / CFG.approach_velocity_scaling_dist
    )


def test_blocked_when_the_arc_hits_an_obstacle() -> None:
    path = polyline((0.0, 0.0), (5.0, 0.0))

    def wall_at_half_metre(x: float, y: float) -> bool:
        return x < 0.4

    cmd = compute_velocity(Pose2(0.0, 0.0, 0.0), path, 0.5, CFG, is_free=wall_at_half_metre)
    assert cmd.status == "blocked"
    assert (cmd.v, cmd.w) == (0.0, 0.0)
    assert "collision" in cmd.reason


def test_obstacle_beyond_the_carrot_does_not_block() -> None:
    path = polyline((0.0, 0.0), (5.0, 0.0))
    cmd = compute_velocity(Pose2(0.0, 0.0, 0.0), path, 0.5, CFG, is_free=lambda x, y: x < 0.7)
    assert cmd.status == "following"


def test_malformed_path_is_rejected() -> None:
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        compute_velocity(Pose2(0, 0, 0), np.zeros((0, 3)), 0.0, CFG)


def _distance_to_polyline(p: np.ndarray, vertices: np.ndarray) -> float:
    a, b = vertices[:-1], vertices[1:]
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    q = a + t[:, None] * d
    return float(np.min(np.hypot(*(q - p).T)))


def test_closed_loop_follows_an_l_shaped_path_to_the_goal() -> None:
    vertices = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 3.0]])
    path = polyline((0.0, 0.0), (3.0, 0.0), (3.0, 3.0))
    follower_cfg = FollowerConfig()
    smoother = VelocitySmoother(SmootherConfig())
    dt = 1.0 / follower_cfg.controller_frequency  # [s] both loops at 20 Hz
    corridor = 0.3  # [m]

    x, y, th = 0.0, 0.0, 0.0
    v, w = 0.0, 0.0
    status = ""
    worst = 0.0
    for k in range(1, 2000):
        now_ns = int(k * dt * 1e9)
        cmd = compute_velocity(Pose2(x, y, th), path, (v, w), follower_cfg)
        status = cmd.status
        smoother.set_target((cmd.v, 0.0, cmd.w), now_ns)
        v, _, w = smoother.tick(now_ns)
        # Unicycle, midpoint integration.
        x += v * dt * math.cos(th + w * dt / 2)
        y += v * dt * math.sin(th + w * dt / 2)
        th += w * dt
        worst = max(worst, _distance_to_polyline(np.array([x, y]), vertices))
        if status == "goal_reached" and v == 0.0 and w == 0.0:
            break
    assert status == "goal_reached"
    assert math.hypot(x - 3.0, y - 3.0) <= follower_cfg.xy_goal_tolerance + 0.02
    assert abs((th - math.pi / 2 + math.pi) % (2 * math.pi) - math.pi) <= (
        follower_cfg.yaw_goal_tolerance + 0.02
    )
    assert worst < corridor
