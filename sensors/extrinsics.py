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


# RobotConfig keys the camera mount sets, in the order robot_mount_from_tf returns them.
MOUNT_KEYS = ("camera_x", "camera_y", "camera_height", "camera_pitch", "camera_roll")
MAX_CAMERA_YAW = 0.05  # [rad] a camera turned further than this on the robot is not modelled
ROBOT_ROOTS = ("base_footprint", "base_link")  # REP-120: base_footprint is on the floor


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Rotation matrix of a (not necessarily unit) quaternion."""
    q = np.array([x, y, z, w], dtype=np.float64)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def chain_to_root(
    edges: dict[str, tuple[str, np.ndarray]], frame: str, roots: tuple[str, ...] = ROBOT_ROOTS
) -> tuple[str, np.ndarray] | None:
    """(root, T_root_frame 4x4) composing ``child -> (parent, T_parent_child)`` edges up from
    ``frame`` to the first of ``roots`` met (base_footprint preferred over base_link)."""
    chain: list[tuple[str, np.ndarray]] = []  # (frame, T_frame_start) while walking up
    t = np.eye(4)
    current, seen = frame, {frame}
    while True:
        chain.append((current, t))
        if current not in edges:
            break
        parent, t_parent_child = edges[current]
        if parent in seen:  # a cycle in a broken tf tree
            break
        seen.add(parent)
        t = t_parent_child @ t
        current = parent
    for root in roots:
        for name, t_root in chain:
            if name == root:
                return root, t_root
    return None


def robot_mount_from_tf(t_base_camera: np.ndarray, optical: bool) -> dict[str, float]:
    """RobotConfig camera keys from T_base_camera (camera = optical frame or camera_link).

    R_base_link = Ry(pitch) Rx(roll) (see :func:`optical_in_base`); a yawed camera is refused.
    """
    if not np.isfinite(t_base_camera).all():  # a zero quaternion or NaN in /tf_static
        raise ValueError("the transform is not finite (a zero quaternion or a NaN/inf value)")
    r = t_base_camera[:3, :3]
    r_link = r @ R_LINK_OPTICAL.T if optical else r
    pitch = math.atan2(-r_link[2, 0], math.hypot(r_link[0, 0], r_link[1, 0]))
    yaw = math.atan2(r_link[1, 0], r_link[0, 0])
    if abs(yaw) > MAX_CAMERA_YAW:
        raise ValueError(
            f"the camera is turned {math.degrees(yaw):.1f} deg on the robot; rgbdnav models a "
            "forward-looking camera (pitch and roll only)"
        )
    roll = math.atan2(r_link[2, 1], r_link[2, 2])
    x, y, z = (float(v) for v in t_base_camera[:3, 3])
    return dict(zip(MOUNT_KEYS, (x, y, z, pitch, roll), strict=True))
