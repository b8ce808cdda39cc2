"""Where the camera sits on the robot (REP-103/105): ``base_link -> camera_link -> camera_optical``.

base_link lies on the floor at the axle midpoint; camera_link is at (camera_x, camera_y,
camera_height) in it, pitched (positive = nose down) and rolled; the optical frame has x right,
y down, z forward. One definition for the simulator, depth -> scan and visual odometry.
"""

from __future__ import annotations

import math

import numpy as np

from sensors.config import RobotConfig

# Optical axes (x right, y down, z forward) expressed in camera_link (x forward, y left, z up).
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def optical_in_base(robot: RobotConfig) -> tuple[np.ndarray, np.ndarray]:
    """(R_base_optical 3x3, t_base_optical 3): R = Ry(pitch) Rx(roll) R_LINK_OPTICAL."""
    r = rot_y(robot.camera_pitch) @ rot_x(robot.camera_roll) @ R_LINK_OPTICAL
    return r, np.array([robot.camera_x, robot.camera_y, robot.camera_height])


def optical_in_base_4x4(robot: RobotConfig) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = optical_in_base(robot)
    return out


def camera_pose_in_world(
    x: float, y: float, yaw: float, robot: RobotConfig
) -> tuple[np.ndarray, np.ndarray]:
    """base_link pose on the floor -> (R_world_optical 3x3, t_world_optical 3)."""
    r_world_base = rot_z(yaw)
    r_base_opt, t_base_opt = optical_in_base(robot)
    return r_world_base @ r_base_opt, np.array([x, y, 0.0]) + r_world_base @ t_base_opt
