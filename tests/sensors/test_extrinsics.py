"""Camera extrinsics: base_link -> optical, against hand-computed poses."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from sensors.config import RobotConfig
from sensors.extrinsics import camera_pose_in_world, optical_in_base, optical_in_base_4x4

ROBOT = RobotConfig()


def test_level_camera_looks_along_base_x_with_image_down_as_floor_down() -> None:
    r, t = optical_in_base(replace(ROBOT, camera_x=0.1, camera_y=-0.05, camera_height=0.4))
    np.testing.assert_allclose(r[:, 2], [1.0, 0.0, 0.0], atol=1e-12)  # optical z = base x
    np.testing.assert_allclose(r[:, 0], [0.0, -1.0, 0.0], atol=1e-12)  # image right = base -y
    np.testing.assert_allclose(r[:, 1], [0.0, 0.0, -1.0], atol=1e-12)  # image down = base -z
    np.testing.assert_allclose(t, [0.1, -0.05, 0.4])


def test_positive_pitch_tilts_the_optical_axis_down() -> None:
    pitch = 0.3
    r, _ = optical_in_base(replace(ROBOT, camera_pitch=pitch))
    np.testing.assert_allclose(r[:, 2], [math.cos(pitch), 0.0, -math.sin(pitch)], atol=1e-12)


def test_positive_roll_about_the_forward_axis_dips_image_right() -> None:
    # REP-103: right-handed about x (forward), so base y (left) rises and image right sinks.
    roll = 0.2
    r, _ = optical_in_base(replace(ROBOT, camera_roll=roll))
    np.testing.assert_allclose(r[:, 2], [1.0, 0.0, 0.0], atol=1e-12)  # roll keeps the axis
    np.testing.assert_allclose(r[:, 0], [0.0, -math.cos(roll), -math.sin(roll)], atol=1e-12)


def test_world_pose_composes_robot_pose_and_extrinsics() -> None:
    robot = replace(ROBOT, camera_x=0.1, camera_height=0.4, camera_pitch=0.2)
    r, t = camera_pose_in_world(1.0, 2.0, math.pi / 2, robot)
    np.testing.assert_allclose(t, [1.0, 2.1, 0.4], atol=1e-12)
    np.testing.assert_allclose(r[:, 2], [0.0, math.cos(0.2), -math.sin(0.2)], atol=1e-12)
    t4 = optical_in_base_4x4(robot)
    np.testing.assert_allclose(t4[:3, :3] @ t4[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t4[3], [0.0, 0.0, 0.0, 1.0])
