"""ATE / RPE kernels on hand-built and seeded trajectories, and the TUM check value."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sensors.tum import load_tum_trajectory
from sensors.types import SensorError
from slam.trajectory_eval import (
    Alignment,
    TrajectoryEvalError,
    align,
    associate,
    ate_errors,
    delta_pairs,
    evaluate,
    poses_from_tum,
    quaternion_from_rotation,
    read_relations,
    relations_error,
    rotation_angle,
    rotation_from_quaternion,
    rpe_errors,
    umeyama,
)

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
TUM = DATA / "tum"
needs_tum = pytest.mark.skipif(not TUM.is_dir(), reason="shared TUM data not available")
MS = 1_000_000  # [ns]


def _wobbly_path(n: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Seeded 3-D path: stamps [ns] at 30 Hz and (n, 4, 4) poses with varied orientation."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 4 * np.pi, n)
    xyz = np.column_stack([np.cos(s) * 2.0, np.sin(s), 0.1 * s]) + rng.normal(0, 0.01, (n, 3))
    quat = Rotation.from_rotvec(np.column_stack([0.1 * np.sin(s), 0.2 * np.cos(s), s])).as_quat()
    stamps = (np.arange(n) * 33.3 * MS).astype(np.int64)
    return stamps, poses_from_tum(xyz, quat)


def _random_rigid(seed: int) -> Alignment:
    rng = np.random.default_rng(seed)
    return Alignment(Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 5.0, 3))


# Rotations ----------------------------------------------------------------------------------


def test_quaternion_to_rotation_matches_scipy_for_unnormalised_quaternions() -> None:
    q = np.random.default_rng(1).normal(size=(500, 4))
    expected = Rotation.from_quat(q).as_matrix()
    np.testing.assert_allclose(rotation_from_quaternion(q), expected, atol=1e-12)


def test_rotation_to_quaternion_round_trips_including_half_turns() -> None:
    q = np.random.default_rng(2).normal(size=(500, 4))
    q[:3] = np.eye(4)[:3]  # 180 deg about x, y, z: w = 0
    rot = rotation_from_quaternion(q)
    back = quaternion_from_rotation(rot)
    assert np.all(back[:, 3] >= 0)
    np.testing.assert_allclose(rotation_from_quaternion(back), rot, atol=1e-12)


def test_rotation_angle_of_a_known_rotation() -> None:
    rot = Rotation.from_rotvec([[0.0, 0.0, 0.3], [np.pi, 0.0, 0.0], [0.0, 0.0, 0.0]]).as_matrix()
    np.testing.assert_allclose(rotation_angle(rot), [0.3, np.pi, 0.0], atol=1e-7)


# Association --------------------------------------------------------------------------------


def test_association_is_one_to_one_closest_first() -> None:
    a = np.array([0, 100, 200]) * MS
    b = np.array([5, 9, 195]) * MS
    ia, ib = associate(a, b, 20 * MS)
    # 0 takes 5 (the closest pair); 9 is then left without a partner in the window.
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 2]


def test_association_window_is_strict() -> None:
    a = np.array([0, 1000]) * MS
    b = np.array([20, 1000 + 19]) * MS
    ia, ib = associate(a, b, 20 * MS)
    assert ia.tolist() == [1] and ib.tolist() == [1]


def test_no_matches_due_to_offset() -> None:
    stamps, poses = _wobbly_path(50)
    with pytest.raises(TrajectoryEvalError, match="no estimate stamp is within the window"):
        evaluate(stamps + 100 * 10**9, poses, stamps, poses)


def test_non_positive_window_is_rejected() -> None:
    with pytest.raises(TrajectoryEvalError, match="must be > 0"):
        associate(np.arange(3), np.arange(3), 0)


# Alignment and ATE --------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trajectory_vs_itself_under_a_random_rigid_transform_has_zero_se3_ate(seed: int) -> None:
    stamps, ref = _wobbly_path(seed=seed)
    moved = _random_rigid(seed + 10).apply_poses(ref)
    result = evaluate(stamps, moved, stamps, ref, align_mode="se3")
    assert result.matched == len(stamps)
    assert result.ate.rmse == pytest.approx(0.0, abs=1e-9)
    assert result.rpe_trans is not None and result.rpe_rot is not None
    assert result.rpe_trans.max == pytest.approx(0.0, abs=1e-9)
    assert result.rpe_rot.max == pytest.approx(0.0, abs=1e-6)  # arccos near 1 is coarse


def test_scaled_copy_has_error_under_se3_and_none_under_sim3() -> None:
    stamps, ref = _wobbly_path()
    scaled = Alignment(np.eye(3), np.array([1.0, -2.0, 0.5]), 0.6).apply_poses(ref)
    moved = _random_rigid(7).apply_poses(scaled)
    se3 = evaluate(stamps, moved, stamps, ref, align_mode="se3")
    sim3 = evaluate(stamps, moved, stamps, ref, align_mode="sim3")
    assert se3.ate.rmse > 0.1
    assert sim3.ate.rmse == pytest.approx(0.0, abs=1e-9)
    assert sim3.alignment.scale == pytest.approx(1 / 0.6, rel=1e-9)
    assert sim3.rpe_trans is not None and sim3.rpe_trans.max == pytest.approx(0.0, abs=1e-9)


def test_umeyama_recovers_a_known_similarity() -> None:
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    rot = Rotation.random(random_state=4).as_matrix()
    dst = 2.5 * src @ rot.T + [1.0, 2.0, 3.0]
    r, t, s = umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, 2.0, 3.0], atol=1e-12)
    assert s == pytest.approx(2.5, rel=1e-12)


def test_se2_alignment_removes_planar_motion_but_not_a_height_offset() -> None:
    rng = np.random.default_rng(5)
    ref = np.column_stack([rng.normal(size=(40, 2)), np.zeros(40)])
    yaw = 0.7
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    est = ref @ rz.T + [3.0, -1.0, 0.0]
    assert ate_errors(est, ref, align(est, ref, "se2")).max() == pytest.approx(0.0, abs=1e-12)
    lifted = est + [0.0, 0.0, 0.25]
    errors = ate_errors(lifted, ref, align(lifted, ref, "se2"))
    np.testing.assert_allclose(errors, 0.25, atol=1e-12)


def test_no_alignment_keeps_a_constant_offset() -> None:
    ref = np.random.default_rng(6).normal(size=(20, 3))
    errors = ate_errors(ref + [0.3, 0.4, 0.0], ref, align(ref, ref, "none"))
    np.testing.assert_allclose(errors, 0.5, atol=1e-12)


def test_ate_statistics_of_known_errors() -> None:
    ref = np.zeros((4, 3))
    est = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 2.0], [0, 0, 3.0]])
    stamps = np.arange(4) * 100 * MS
    identity = np.tile([0, 0, 0, 1.0], (4, 1))
    result = evaluate(
        stamps,
        poses_from_tum(est, identity),
        stamps,
        poses_from_tum(ref, identity),
        align_mode="none",
    )
    assert result.ate.rmse == pytest.approx(np.sqrt((1 + 4 + 4 + 9) / 4), abs=1e-12)
    assert (result.ate.mean, result.ate.median) == pytest.approx((2.0, 2.0), abs=1e-12)
    assert (result.ate.min, result.ate.max) == pytest.approx((1.0, 3.0), abs=1e-12)
    assert result.ate.std == pytest.approx(np.std([1, 2, 2, 3]), abs=1e-12)


def test_too_few_matches_for_the_alignment_is_an_error() -> None:
    with pytest.raises(TrajectoryEvalError, match="needs at least 3 matched poses, got 2"):
        align(np.zeros((2, 3)), np.zeros((2, 3)), "se3")


def test_unknown_alignment_is_an_error() -> None:
    with pytest.raises(TrajectoryEvalError, match="unknown alignment 'se4'"):
        align(np.zeros((5, 3)), np.zeros((5, 3)), "se4")  # type: ignore[arg-type]


# RPE ----------------------------------------------------------------------------------------


def _straight_line(n: int = 101, step_m: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.column_stack([np.arange(n) * step_m, np.zeros(n), np.zeros(n)])
    return (np.arange(n) * 100 * MS).astype(np.int64), xyz


def test_rpe_of_a_two_percent_scale_drift_is_two_cm_per_metre() -> None:
    stamps, xyz = _straight_line()
    identity = np.tile([0, 0, 0, 1.0], (len(xyz), 1))
    ref, est = poses_from_tum(xyz, identity), poses_from_tum(1.02 * xyz, identity)
    result = evaluate(stamps, est, stamps, ref, align_mode="none", delta=1.0, delta_unit="m")
    assert result.rpe_trans is not None and result.rpe_rot is not None
    assert result.rpe_trans.count == 91  # pairs from x = 0.0 .. 9.0 m
    assert result.rpe_trans.min == pytest.approx(0.02, abs=1e-9)
    assert result.rpe_trans.max == pytest.approx(0.02, abs=1e-9)
    assert result.rpe_rot.max == pytest.approx(0.0, abs=1e-6)


def test_rpe_of_a_constant_heading_drift_per_metre() -> None:
    stamps, xyz = _straight_line()
    drift = np.radians(1.5)  # [rad/m]
    yaw = drift * xyz[:, 0]
    quat = Rotation.from_rotvec(np.outer(yaw, [0.0, 0.0, 1.0])).as_quat()
    ref = poses_from_tum(xyz, np.tile([0, 0, 0, 1.0], (len(xyz), 1)))
    i, j = delta_pairs(xyz, 1.0, "m")
    _, rot = rpe_errors(poses_from_tum(xyz, quat), ref, i, j)
    np.testing.assert_allclose(rot, drift * 1.0, atol=1e-7)


def test_delta_in_frames_pairs_every_pose_with_the_one_k_later() -> None:
    i, j = delta_pairs(np.zeros((6, 3)), 2, "frames")
    assert i.tolist() == [0, 1, 2, 3] and j.tolist() == [2, 3, 4, 5]


def test_delta_in_metres_takes_the_first_pose_at_least_that_far() -> None:
    xyz = np.column_stack([[0.0, 0.4, 0.9, 1.0, 1.6, 2.5], np.zeros(6), np.zeros(6)])
    i, j = delta_pairs(xyz, 1.0, "m")
    assert i.tolist() == [0, 1, 2, 3] and j.tolist() == [3, 4, 5, 5]


def test_delta_longer_than_the_trajectory_leaves_rpe_empty() -> None:
    stamps, xyz = _straight_line(n=5)
    poses = poses_from_tum(xyz, np.tile([0, 0, 0, 1.0], (5, 1)))
    result = evaluate(stamps, poses, stamps, poses, delta=10.0)
    assert result.rpe_trans is None and result.rpe_rot is None


@pytest.mark.parametrize(
    ("delta", "unit", "message"),
    [(0.0, "m", "delta must be > 0"), (1.5, "frames", "whole number"), (1.0, "s", "unknown delta")],
)
def test_bad_deltas_are_errors(delta: float, unit: str, message: str) -> None:
    with pytest.raises(TrajectoryEvalError, match=message):
        delta_pairs(np.zeros((3, 3)), delta, unit)  # type: ignore[arg-type]


# Real data ----------------------------------------------------------------------------------


@needs_tum
def test_fr1_xyz_rgbdslam_reproduces_the_tum_ate_check_value() -> None:
    te, xe, qe = load_tum_trajectory(TUM / "freiburg1_xyz-rgbdslam.txt")
    tg, xg, qg = load_tum_trajectory(TUM / "freiburg1_xyz-groundtruth.txt")
    result = evaluate(
        te,
        poses_from_tum(xe, qe),
        tg,
        poses_from_tum(xg, qg),
        align_mode="se3",
        max_diff_ns=20 * MS,
    )
    assert result.ate.rmse == pytest.approx(0.01347, abs=1e-5)
    assert result.matched == 786


# Relations metric ---------------------------------------------------------------------------


def _planar_walk(n: int = 60, seed: int = 8) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 0.2, n))
    xy = np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]) * 0.3, axis=0)
    return (np.arange(n) * 100 * MS).astype(np.int64), np.column_stack([xy, yaw])


def _true_relations(poses: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    a, b = poses[i], poses[j]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, b[:, 2] - a[:, 2]])


def test_relations_of_the_true_trajectory_score_zero() -> None:
    stamps, poses = _planar_walk()
    i, j = np.arange(0, 50), np.arange(5, 55)
    r = relations_error(
        stamps, poses, stamps[i] + 3 * MS, stamps[j] - 2 * MS, _true_relations(poses, i, j)
    )
    assert r["count"] == 50 and r["skipped"] == 0
    assert r["trans_mean_m"] == pytest.approx(0.0, abs=1e-12)
    assert r["rot_mean_deg"] == pytest.approx(0.0, abs=1e-9)


def test_relations_error_of_known_perturbations() -> None:
    stamps, poses = _planar_walk()
    i, j = np.arange(0, 4), np.arange(10, 14)
    rel = _true_relations(poses, i, j)
    # Reference relations off by 0.1 m along the relative pose's own x axis, and by 2 deg.
    rel_off = rel.copy()
    rel_off[:, 0] += 0.1 * np.cos(rel[:, 2])
    rel_off[:, 1] += 0.1 * np.sin(rel[:, 2])
    rel_off[:2, 2] += np.radians(2.0)
    r = relations_error(stamps, poses, stamps[i], stamps[j], rel_off)
    assert r["trans_mean_m"] == pytest.approx(0.1, abs=1e-12)
    assert r["trans_std_m"] == pytest.approx(0.0, abs=1e-12)
    assert r["rot_mean_deg"] == pytest.approx(1.0, abs=1e-9)  # 2, 2, 0, 0 deg
    assert r["rot_std_deg"] == pytest.approx(1.0, abs=1e-9)
    assert r["rot_sq_mean_deg2"] == pytest.approx(2.0, abs=1e-9)


def test_relations_without_poses_nearby_are_skipped() -> None:
    stamps, poses = _planar_walk()
    rel = _true_relations(poses, np.array([0, 1]), np.array([5, 6]))
    r = relations_error(stamps, poses, np.array([stamps[0], 10**12]), stamps[[5, 6]], rel)
    assert (r["count"], r["skipped"]) == (1, 1)


CARMEN = DATA / "carmen"


@pytest.mark.skipif(not CARMEN.is_dir(), reason="shared CARMEN data not available")
def test_raw_odometry_of_mit_csail_reproduces_the_published_relations_score() -> None:
    from sensors.carmen import read_carmen_log
    from sensors.types import parse_stamp

    odom = read_carmen_log(CARMEN / "mit-csail.clf").robot_pose
    rows = [r.split() for r in (CARMEN / "mit-csail.relations").read_text().splitlines() if r]
    t1 = np.array([parse_stamp(r[0]) for r in rows])
    t2 = np.array([parse_stamp(r[1]) for r in rows])
    rel = np.array([[float(r[2]), float(r[3]), float(r[7])] for r in rows])  # x y yaw
    poses = np.column_stack([odom.x, odom.y, odom.yaw])
    r = relations_error(odom.stamps_ns, poses, t1, t2, rel, max_diff_ns=MS)
    assert r["count"] == 1172
    # Kümmerle et al. 2009: raw odometry 1.6815 +- 5.2922 m, 5.072 +- 8.241 deg.
    assert (r["trans_mean_m"], r["trans_std_m"]) == pytest.approx((1.6815, 5.2922), abs=1e-4)
    assert (r["rot_mean_deg"], r["rot_std_deg"]) == pytest.approx((5.072, 8.241), abs=1e-3)


# Relations files ----------------------------------------------------------------------------


def test_read_relations_keeps_exact_stamps_and_the_planar_part(tmp_path: Path) -> None:
    path = tmp_path / "rel.txt"
    path.write_text(
        "# t1 t2 x y z roll pitch yaw\n"
        "1134864645.90321 1134864646.32420 0.31293 0.02935 0 0 0 0.24198\n"
        "\n"
        "# a relation backwards in time is still a relation\n"
        "2.5 1.000000001 -1.0 0.5 0.3 0.01 0.02 -3.0\n"
    )
    rel = read_relations(path)
    assert rel.t1_ns.tolist() == [1134864645903210000, 2_500_000_000]
    assert rel.t2_ns.tolist() == [1134864646324200000, 1_000_000_001]
    np.testing.assert_allclose(rel.xyyaw, [[0.31293, 0.02935, 0.24198], [-1.0, 0.5, -3.0]])
    assert rel.lines.tolist() == [2, 5]


@pytest.mark.parametrize(
    ("line", "match"),
    [
        ("1.0 2.0 0.1 0 0 0 0", r"rel.txt:3: expected 8 fields"),
        ("1.0 2.0 0.1 nan 0 0 0 0.2", r"rel.txt:3: .* is not valid relation"),
        ("1.0 2.0 0.1 0 0 0 0 inf", r"rel.txt:3: .* is not valid relation"),
        ("1.0 two 0.1 0 0 0 0 0.2", r"rel.txt:3: bad timestamp t2"),
        ("nan 2.0 0.1 0 0 0 0 0.2", r"rel.txt:3: bad timestamp"),
    ],
)
def test_a_malformed_relation_names_file_and_line(tmp_path: Path, line: str, match: str) -> None:
    path = tmp_path / "rel.txt"
    path.write_text(f"# t1 t2 x y z roll pitch yaw\n0.0 1.0 1 0 0 0 0 0\n{line}\n")
    with pytest.raises(SensorError, match=match):
        read_relations(path)


def test_a_relations_file_without_relations_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "rel.txt"
    path.write_text("# t1 t2 x y z roll pitch yaw\n")
    with pytest.raises(SensorError, match=r"rel.txt: no relations"):
        read_relations(path)


@pytest.mark.skipif(not CARMEN.is_dir(), reason="shared CARMEN data not available")
def test_read_relations_of_mit_csail_reads_all_1172() -> None:
    rel = read_relations(CARMEN / "mit-csail.relations")
    assert len(rel.t1_ns) == 1172 and rel.t1_ns[0] == 1134864645903210000
    np.testing.assert_allclose(rel.xyyaw[0], [0.31293, 0.02935, 0.24198])
