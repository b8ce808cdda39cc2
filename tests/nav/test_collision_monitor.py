"""The collision monitor: stop and slowdown boxes ahead, and an obstacle memory that keeps what
the camera saw before it came too close to see it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nav.collision_monitor import ObstacleMemory, limit_twist

R, STOP, SLOW, RATIO = 0.23, 0.12, 0.4, 0.4  # [m, m, m, -]


@pytest.mark.parametrize(
    ("point", "expected_v", "action"),
    [
        ((0.30, 0.0), 0.0, "stop"),  # inside radius + stop distance, straight ahead
        ((0.50, 0.1), 0.3 * RATIO, "slowdown"),
        ((0.50, 0.4), 0.3, ""),  # beside the footprint's path
        ((0.0, 0.26), 0.0, "stop"),  # a door frame at the robot's side, within the margin
        ((-0.5, 0.0), 0.3, ""),  # behind: the robot drives away from it
        ((1.5, 0.0), 0.3, ""),
    ],
)
def test_forward_motion_is_stopped_or_slowed_by_a_point_ahead(
    point: tuple[float, float], expected_v: float, action: str
) -> None:
    v, w, act = limit_twist(np.array([point]), 0.3, 0.2, R, STOP, SLOW, RATIO, 0.05)
    assert v == pytest.approx(expected_v) and w == 0.2 and act == action


def test_turning_in_place_and_reversing_are_never_limited() -> None:
    wall = np.array([[0.25, y] for y in np.linspace(-0.3, 0.3, 7)])
    assert limit_twist(wall, 0.0, 0.5, R, STOP, SLOW, RATIO) == (0.0, 0.5, "")
    assert limit_twist(wall, -0.1, 0.0, R, STOP, SLOW, RATIO) == (-0.1, 0.0, "")


def test_memory_keeps_a_wall_seen_from_afar_in_the_robots_frame_as_it_drives_up() -> None:
    mem = ObstacleMemory(keep_s=2.0)
    mem.add(0, np.array([0.0, 0.0, 0.0]), np.array([[1.0, 0.0]]))  # seen 1 m ahead
    # 0.75 m later, too close for the camera: the memory still has it 0.25 m ahead.
    pts = mem.points_in_base(np.array([0.75, 0.0, 0.0]))
    np.testing.assert_allclose(pts, [[0.25, 0.0]], atol=1e-12)
    assert limit_twist(pts, 0.3, 0.0, R, STOP, SLOW, RATIO)[2] == "stop"
    # Turned left by 90 deg: the point is now on the robot's right.
    np.testing.assert_allclose(
        mem.points_in_base(np.array([0.75, 0.0, math.pi / 2])), [[0.0, -0.25]], atol=1e-12
    )


def test_memory_forgets_scans_older_than_its_window() -> None:
    mem = ObstacleMemory(keep_s=1.0)
    mem.add(0, np.zeros(3), np.array([[1.0, 0.0]]))
    mem.add(int(1.5e9), np.zeros(3), np.array([[2.0, 0.0]]))
    np.testing.assert_allclose(mem.points_in_base(np.zeros(3)), [[2.0, 0.0]])


@pytest.mark.parametrize(("frame", "x_base"), [("base_link", 0.5), ("camera_link", 0.6)])
def test_a_scan_lands_in_base_link_through_its_frames_offset(frame: str, x_base: float) -> None:
    # One return 0.5 m straight ahead of the scan frame's origin; the camera sits 0.1 m forward,
    # so in a camera-frame scan the point is 0.6 m ahead of base_link (rgbdnav live once
    # stored it at 0.5 m, without the offset).
    from nav.collision_monitor import CollisionMonitor
    from nav.config import CollisionMonitorConfig
    from sensors.config import RobotConfig
    from sensors.types import LaserScan
    from slam.config import DepthToScanConfig
    from slam.depth_to_scan import scan_frame_in_base

    robot = RobotConfig(camera_x=0.1)
    at = scan_frame_in_base(robot, DepthToScanConfig(output_frame=frame))
    monitor = CollisionMonitor(CollisionMonitorConfig(), radius=R)
    scan = LaserScan(0, 0.0, 0.0, np.array([0.5], dtype=np.float32), 0.1, 4.0)
    monitor.add_scan(np.zeros(3), scan, at)
    assert monitor.memory.points_in_base(np.zeros(3)) == pytest.approx(np.array([[x_base, 0.0]]))
