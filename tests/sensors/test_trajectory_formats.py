"""TUM, KITTI (+ times file) and EuRoC/ASL CSV trajectories: detected on reading, written on
request, round trips exact to float precision (issue 23, item 6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sensors.tum import (
    EUROC_HEADER,
    convert_tum_files,
    detect_trajectory_format,
    load_trajectory,
    load_tum_trajectory,
    read_pose_table,
    write_trajectory,
    write_tum_trajectory,
)
from sensors.types import SensorError

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
GT = DATA / "tum" / "fr2_desk_groundtruth.txt"
needs_tum = pytest.mark.skipif(not GT.is_file(), reason="shared TUM data not available")


def _poses(n: int = 20, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    stamps = 1_305_031_102_000_000_000 + np.cumsum(rng.integers(10_000_000, 40_000_000, n))
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    quat[quat[:, 3] < 0] *= -1  # one sign, so the round trip compares equal
    return stamps.astype(np.int64), rng.normal(size=(n, 3)) * 5, quat


def _same_rotation(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_allclose(np.abs(np.sum(a * b, axis=1)), 1.0, atol=1e-12)


@pytest.mark.parametrize("fmt", ["tum", "kitti", "euroc"])
def test_each_format_round_trips_and_is_detected(tmp_path, fmt) -> None:
    stamps, xyz, quat = _poses()
    path = tmp_path / f"traj.{fmt}"
    written = write_trajectory(path, stamps, xyz, quat, fmt)
    assert detect_trajectory_format(path) == fmt
    t, p, q = load_trajectory(path)
    np.testing.assert_array_equal(t, stamps)
    np.testing.assert_allclose(p, xyz, atol=1e-12)
    _same_rotation(q, quat)
    if fmt == "kitti":
        assert [w.name for w in written] == ["traj.kitti", "traj.times.txt"]
        assert len(path.read_text().split("\n")[0].split()) == 12


def test_euroc_reads_the_asl_ground_truth_layout_with_w_first(tmp_path) -> None:
    """The EuRoC state_groundtruth_estimate0/data.csv: 17 columns, quaternion w x y z."""
    header = (
        EUROC_HEADER + ", v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
        "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
        "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
    )
    rows = [
        "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,"
        "-0.082152,-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,"
        "0.136696,0.075593",
        "1403636580843555328,4.688177,-1.786770,0.787350,0.534640,-0.152990,-0.826976,"
        "-0.082863,-0.029272,0.033992,0.804771,-0.003172,0.021267,0.078502,-0.025266,"
        "0.136696,0.075593",
    ]
    path = tmp_path / "data.csv"
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    table = read_pose_table(path)
    assert table.format == "euroc"
    assert table.stamps_ns.tolist() == [1403636580838555648, 1403636580843555328]
    xyz_xyzw = [4.688319, -1.786938, 0.783338, -0.153029, -0.827383, -0.082152, 0.534108]
    np.testing.assert_allclose(table.poses[0], xyz_xyzw)


def test_kitti_times_file_beside_or_given_or_frame_index(tmp_path) -> None:
    stamps, xyz, quat = _poses(5)
    write_trajectory(tmp_path / "00.txt", stamps, xyz, quat, "kitti")  # + 00.times.txt
    assert load_trajectory(tmp_path / "00.txt")[0].tolist() == stamps.tolist()
    (tmp_path / "00.times.txt").rename(tmp_path / "times.txt")  # the KITTI odometry name
    assert load_trajectory(tmp_path / "00.txt")[0].tolist() == stamps.tolist()
    other = tmp_path / "t.txt"
    other.write_text("".join(f"{i * 0.1:e}\n" for i in range(5)))  # KITTI writes 0.000000e+00
    got = load_trajectory(tmp_path / "00.txt", times=other)[0]
    assert got.tolist() == [i * 100_000_000 for i in range(5)]
    (tmp_path / "times.txt").unlink()
    assert load_trajectory(tmp_path / "00.txt")[0].tolist() == [i * 10**9 for i in range(5)]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1 2 3\n", "3 fields is no trajectory format known here"),
        ("", "no poses"),
        ("1,2,3\n", "expected at least 8 comma-separated fields"),
        ("1.5,0,0,0,1,0,0,0\n", "timestamp '1.5' is not integer ns"),
        ("10,0,0,0,1,0,0,0\n5,0,0,0,1,0,0,0\n", "non-monotonic timestamp"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 x 0\n", ":2: .* is not valid KITTI"),
        ("2 0 0 0 0 1 0 0 0 0 1 0\n", "not a rotation"),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 0\n", ":2: quaternion has zero length"),
    ],
)
def test_bad_trajectory_files_are_one_error_naming_file_and_line(tmp_path, text, match) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(SensorError, match=match):
        read_pose_table(path)


def test_kitti_times_count_must_match(tmp_path) -> None:
    stamps, xyz, quat = _poses(4)
    write_trajectory(tmp_path / "a.txt", stamps, xyz, quat, "kitti")
    (tmp_path / "a.times.txt").write_text("0\n1\n")
    with pytest.raises(SensorError, match="2 times for the 4 poses"):
        load_trajectory(tmp_path / "a.txt")


@needs_tum
def test_real_ground_truth_survives_every_format(tmp_path) -> None:
    t0, p0, q0 = load_tum_trajectory_lenient(GT)
    for fmt in ("kitti", "euroc"):
        path = tmp_path / f"gt.{fmt}"
        write_trajectory(path, t0, p0, q0, fmt)
        t, p, q = load_trajectory(path)
        np.testing.assert_array_equal(t, t0)
        np.testing.assert_allclose(p, p0, atol=1e-12)
        _same_rotation(
            q / np.linalg.norm(q, axis=1)[:, None], q0 / np.linalg.norm(q0, axis=1)[:, None]
        )


def load_tum_trajectory_lenient(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """fr2/desk's ground truth repeats one stamp: keep the first of each."""
    table = read_pose_table(path, check_order=False)
    _, first = np.unique(table.stamps_ns, return_index=True)
    return table.stamps_ns[first], table.poses[first, :3], table.poses[first, 3:]


def test_run_folder_trajectories_are_converted_beside_the_tum(tmp_path) -> None:
    write_tum_trajectory(
        tmp_path / "trajectory.tum",
        np.array([0, 10**9]),
        np.array([0.0, 1.0]),
        np.array([0.0, 0.5]),
        np.array([0.0, 0.3]),
    )
    written = convert_tum_files(tmp_path, "kitti")
    assert [p.name for p in written] == ["trajectory.kitti.txt", "trajectory.times.txt"]
    t, p, _ = load_trajectory(tmp_path / "trajectory.kitti.txt")
    t0, p0, _ = load_tum_trajectory(tmp_path / "trajectory.tum")
    np.testing.assert_array_equal(t, t0)
    np.testing.assert_allclose(p, p0, atol=1e-12)
    assert [p.name for p in convert_tum_files(tmp_path, "euroc")] == ["trajectory.euroc.csv"]
    assert convert_tum_files(tmp_path, "tum") == []
