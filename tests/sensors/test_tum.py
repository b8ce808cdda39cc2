from __future__ import annotations

import numpy as np
import pytest

from sensors.tum import (
    load_tum_trajectory,
    quaternion_from_yaw,
    write_tum_trajectory,
    yaw_from_quaternion,
)
from sensors.types import SensorError


def test_yaw_survives_quaternion_round_trip():
    yaw = np.array([0.0, 0.3, -1.2, np.pi / 2, 3.1, -3.1])
    quat = quaternion_from_yaw(yaw)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(yaw_from_quaternion(quat), yaw, atol=1e-12)


def test_yaw_of_negated_quaternion_is_the_same():
    quat = quaternion_from_yaw(np.array([0.7]))
    np.testing.assert_allclose(yaw_from_quaternion(-quat), [0.7], atol=1e-12)


def test_yaw_of_known_quaternion_about_z():
    # 90 degrees about z: (x, y, z, w) = (0, 0, sin 45, cos 45)
    s = np.sqrt(0.5)
    assert yaw_from_quaternion(np.array([0.0, 0.0, s, s])) == pytest.approx(np.pi / 2, abs=1e-12)


def test_trajectory_round_trip_keeps_exact_stamps_and_poses(tmp_path):
    stamps = np.array([1_305_031_102_175_304_000, 1_305_031_102_211_214_123], dtype=np.int64)
    x, y, yaw = np.array([0.1, -2.5]), np.array([1.0 / 3.0, 4.0]), np.array([0.25, -2.0])
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, stamps, x, y, yaw)

    t, xyz, quat = load_tum_trajectory(path)
    assert t.dtype == np.int64
    np.testing.assert_array_equal(t, stamps)
    np.testing.assert_array_equal(xyz, np.stack([x, y, np.zeros(2)], axis=1))
    np.testing.assert_allclose(yaw_from_quaternion(quat), yaw, atol=1e-12)


def test_trajectory_with_wrong_field_count_names_the_line(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(SensorError, match=r"traj\.txt:3: expected 8 fields"):
        load_tum_trajectory(path)


def test_trajectory_with_non_numeric_value_names_the_line(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 zero 0 0 0 0 1\n")
    with pytest.raises(SensorError, match=r"traj\.txt:2: .* is not valid pose"):
        load_tum_trajectory(path)


def test_trajectory_going_back_in_time_names_the_line(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(SensorError, match=r"traj\.txt:2: non-monotonic timestamp"):
        load_tum_trajectory(path)


@pytest.mark.parametrize("stamp", ["1e10", "1e30", "100000000000000000000", "-4611686019"])
def test_a_stamp_beyond_int64_nanoseconds_is_an_error_naming_the_line(tmp_path, stamp):
    path = tmp_path / "traj.txt"
    path.write_text(f"1.0 0 0 0 0 0 0 1\n{stamp} 0 0 0 0 0 0 1\n")
    with pytest.raises(SensorError, match=r"traj\.txt:2: bad timestamp: .* is out of range"):
        load_tum_trajectory(path)


def test_a_stamp_a_digit_string_long_enough_to_stall_int_is_refused_at_once(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("9" * 100_000 + " 0 0 0 0 0 0 1\n")
    with pytest.raises(SensorError, match=r"traj\.txt:1: bad timestamp"):
        load_tum_trajectory(path)


@pytest.mark.parametrize(
    ("row", "match"),
    [
        ("1e30 0 0 0 0 0 1", r"position \[1e\+30, 0\.0, 0\.0\] is farther than 1e\+08 m"),
        ("0 0 0 0 0 0 0", "quaternion has zero length"),
    ],
)
def test_a_pose_no_robot_can_have_is_an_error_naming_the_line(tmp_path, row, match):
    path = tmp_path / "traj.txt"
    path.write_text(f"1.0 0 0 0 0 0 0 1\n2.0 {row}\n")
    with pytest.raises(SensorError, match=rf"traj\.txt:2: {match}"):
        load_tum_trajectory(path)
