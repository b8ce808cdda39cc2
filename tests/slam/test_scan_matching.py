"""Scan matching on seeded synthetic scenes: correlative search against an exhaustive reference
search over the same lattice, point-to-line ICP against ground truth, and the error paths."""

from __future__ import annotations

import math

import numpy as np
import pytest

# tests/ is no package: pytest's default (prepend) import mode puts tests/slam on sys.path.
from scan_scenes import ROOM, raycast
from scipy.spatial import cKDTree

from sensors.types import LaserScan
from slam.geometry import compose, wrap_angle
from slam.scan_matching import (
    NORMAL_TIE_RTOL,
    IcpResult,
    LikelihoodField,
    ReferenceCloud,
    build_likelihood_field,
    build_reference,
    correlative_match,
    icp_refine,
    rival_score,
    scan_points,
    transform_points,
    voxel_filter,
)

RES = 0.05  # [m/cell] likelihood grid
SMEAR = 0.05  # [m] likelihood smear sigma
N_LEVELS = 5  # pyramid levels (top block 16 x 16 cells)
WINDOW = 0.5  # [m] linear search half-width, also the field margin
ANGLE_STEP = math.radians(1.0)  # [rad]
MAX_CORRESPONDENCE = 0.3  # [m] ICP neighbour gate

REF_POSE = np.array([4.0, 3.0, 0.0])  # (x [m], y [m], yaw [rad]) of the reference scan
# Two parallel walls 2 m apart and 100 m long: nothing constrains motion along x.
CORRIDOR = np.array([[-50.0, 0.0, 50.0, 0.0], [-50.0, 2.0, 50.0, 2.0]])


def world_points(
    segments: np.ndarray,
    pose: np.ndarray,
    n_beams: int = 360,
    fov: float = 2 * math.pi,
    range_max: float = 20.0,
    noise_m: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """End points of a synthetic scan from ``pose``, in the world frame."""
    scan = raycast(
        segments, pose, n_beams=n_beams, fov=fov, range_max=range_max, noise_m=noise_m, seed=seed
    )
    return transform_points(pose, scan_points(scan))


def body_points(
    segments: np.ndarray,
    pose: np.ndarray,
    n_beams: int = 181,
    fov: float = math.pi,
    range_max: float = 20.0,
    noise_m: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """End points of a synthetic scan from ``pose``, in the scan frame."""
    scan = raycast(
        segments, pose, n_beams=n_beams, fov=fov, range_max=range_max, noise_m=noise_m, seed=seed
    )
    return scan_points(scan)


def room_field(margin_m: float = WINDOW, resolution: float = RES) -> LikelihoodField:
    return build_likelihood_field(
        world_points(ROOM, REF_POSE), resolution, max(SMEAR, resolution), margin_m, N_LEVELS
    )


def brute_force_match(
    field: LikelihoodField,
    points: np.ndarray,
    prior: np.ndarray,
    linear_window_m: float,
    angular_window_rad: float,
    angle_step_rad: float,
    distance_variance_penalty: float = math.inf,
    angle_variance_penalty: float = math.inf,
    minimum_distance_penalty: float = 0.0,
    minimum_angle_penalty: float = 0.0,
) -> tuple[float, float, np.ndarray]:
    """Reference search: every lattice angle, every integer cell shift, the mean of
    ``field.field`` at the shifted cells (0 off the grid). Returns (penalised, raw, pose)."""
    res = field.resolution
    n_half = math.ceil(linear_window_m / res)
    n_ang_half = math.floor(angular_window_rad / angle_step_rad + 1e-9)
    shifts = np.arange(-n_half, n_half + 1)
    h, w = field.field.shape
    d2 = (shifts[:, None] ** 2 + shifts[None, :] ** 2) * res**2  # [row shift, col shift]
    p_dist = np.maximum(np.exp(-d2 / distance_variance_penalty), minimum_distance_penalty)
    best: tuple[float, float, np.ndarray] = (-1.0, 0.0, np.asarray(prior, float))
    for k in range(-n_ang_half, n_ang_half + 1):
        dyaw = k * angle_step_rad
        world = transform_points(np.array([prior[0], prior[1], prior[2] + dyaw]), points)
        col0 = np.floor((world[:, 0] - field.origin[0]) / res).astype(np.int64)
        row0 = np.floor((world[:, 1] - field.origin[1]) / res).astype(np.int64)
        rows = row0[None, None, :] + shifts[:, None, None]
        cols = col0[None, None, :] + shifts[None, :, None]
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        values = field.field[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)]
        raw = np.where(inside, values, 0.0).mean(axis=2)
        p_ang = max(math.exp(-(dyaw**2) / angle_variance_penalty), minimum_angle_penalty)
        penalised = raw * p_dist * p_ang
        i, j = np.unravel_index(int(np.argmax(penalised)), penalised.shape)
        if penalised[i, j] > best[0]:
            pose = np.array(
                [
                    prior[0] + shifts[j] * res,
                    prior[1] + shifts[i] * res,
                    wrap_angle(prior[2] + dyaw),
                ]
            )
            best = (float(penalised[i, j]), float(raw[i, j]), pose)
    return best


def assert_same_pose(a: np.ndarray, b: np.ndarray, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(a[:2], b[:2], atol=atol)
    assert abs(float(wrap_angle(a[2] - b[2]))) <= atol


# 1. Scan points, voxel filter, transform ---------------------------------------------------------


def test_scan_points_drops_nan_no_return_and_out_of_range_beams() -> None:
    # Beams at -90, -45, 0, 45, 90, 135, 180 deg.
    ranges = np.array([np.nan, np.inf, 1.0, 0.01, 2.0, 6.0, 3.0], np.float32)
    scan = LaserScan(0, -math.pi / 2, math.pi / 4, ranges, range_min=0.02, range_max=5.0)
    pts = scan_points(scan)
    np.testing.assert_allclose(pts, [[1.0, 0.0], [0.0, 2.0], [-3.0, 0.0]], atol=1e-12)
    assert pts.dtype == np.float64


def test_scan_points_drops_returns_beyond_max_range() -> None:
    ranges = np.array([1.0, 2.0, 3.0], np.float32)
    scan = LaserScan(0, 0.0, math.pi / 2, ranges, range_min=0.02, range_max=5.0)
    np.testing.assert_allclose(
        scan_points(scan, max_range_m=2.5), [[1.0, 0.0], [0.0, 2.0]], atol=1e-12
    )


def test_scan_points_puts_a_beam_at_plus_90_deg_on_the_positive_y_axis() -> None:
    scan = LaserScan(0, math.pi / 2, 0.1, np.array([1.5], np.float32), 0.02, 5.0)
    np.testing.assert_allclose(scan_points(scan), [[0.0, 1.5]], atol=1e-12)


def test_voxel_filter_keeps_the_first_point_of_each_cell_in_order() -> None:
    pts = np.array(
        [[0.05, 0.05], [1.02, 0.01], [0.09, 0.02], [-0.48, 0.32], [1.05, 0.08], [-0.42, 0.38]]
    )
    out = voxel_filter(pts, 0.1)
    np.testing.assert_array_equal(out, pts[[0, 1, 3]])


def test_voxel_filter_leaves_one_point_per_cell_on_a_random_cloud() -> None:
    pts = np.random.default_rng(7).uniform(-3.0, 3.0, (2000, 2))
    out = voxel_filter(pts, 0.25)
    cells = np.floor(out / 0.25).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(out) == len(np.unique(np.floor(pts / 0.25), axis=0))
    idx = [int(np.flatnonzero((pts == p).all(axis=1))[0]) for p in out]
    assert idx == sorted(idx)


def test_voxel_filter_is_a_no_op_for_voxel_zero() -> None:
    pts = np.random.default_rng(8).normal(size=(50, 2))
    np.testing.assert_array_equal(voxel_filter(pts, 0.0), pts)


def test_transform_points_agrees_with_compose() -> None:
    rng = np.random.default_rng(9)
    pose = np.array([1.3, -0.7, 2.4])
    pts = rng.uniform(-5.0, 5.0, (40, 2))
    x, y, _ = compose(pose[0], pose[1], pose[2], pts[:, 0], pts[:, 1], 0.0)
    np.testing.assert_allclose(transform_points(pose, pts), np.column_stack([x, y]), atol=1e-12)


# 2. Correlative search ----------------------------------------------------------------------------


@pytest.mark.parametrize("penalised", [False, True], ids=["plain", "penalised"])
def test_correlative_match_equals_brute_force_search_on_the_same_lattice(penalised: bool) -> None:
    rng = np.random.default_rng(11)
    penalties = dict(
        distance_variance_penalty=0.3,
        angle_variance_penalty=0.02,
        minimum_distance_penalty=0.5,
        minimum_angle_penalty=0.9,
    )
    for trial in range(4):
        ref_pose = np.array([rng.uniform(2.0, 6.0), rng.uniform(1.5, 4.5), rng.uniform(-3, 3)])
        field = build_likelihood_field(world_points(ROOM, ref_pose), RES, SMEAR, WINDOW, N_LEVELS)
        truth = ref_pose + np.array([*rng.uniform(-0.4, 0.4, 2), rng.uniform(-0.5, 0.5)])
        pts = body_points(ROOM, truth, n_beams=91, noise_m=0.01, seed=trial)
        # Prior within 0.2 m of the truth: see test_correlative_match_is_exact_for_a_far_prior.
        prior = truth + np.array([*rng.uniform(-0.2, 0.2, 2), rng.uniform(-0.05, 0.05)])
        kw = penalties if penalised else {}
        got = correlative_match(field, pts, prior, WINDOW, math.radians(5), ANGLE_STEP, **kw)
        want_pen, want_raw, want_pose = brute_force_match(
            field, pts, prior, WINDOW, math.radians(5), ANGLE_STEP, **kw
        )
        assert got.penalised_score == pytest.approx(want_pen, abs=1e-6)
        assert got.score == pytest.approx(want_raw, abs=1e-6)
        assert_same_pose(got.pose, want_pose)


def test_correlative_match_prunes_most_of_the_lattice_in_a_distinctive_scene() -> None:
    field = room_field()
    truth = REF_POSE + np.array([0.3, 0.1, math.radians(8)])
    pts = body_points(ROOM, truth)
    res = correlative_match(field, pts, REF_POSE, WINDOW, math.radians(12), ANGLE_STEP)
    lattice = (2 * math.ceil(WINDOW / RES) + 1) ** 2 * (2 * 12 + 1)
    assert res.evaluated < lattice / 10


def test_correlative_match_recovers_a_known_offset_within_one_cell_and_one_angle_step() -> None:
    field = room_field()
    truth = REF_POSE + np.array([0.3, 0.1, math.radians(8)])
    pts = body_points(ROOM, truth, noise_m=0.01, seed=3)
    res = correlative_match(field, pts, REF_POSE, WINDOW, math.radians(12), ANGLE_STEP)
    np.testing.assert_allclose(res.pose[:2], truth[:2], atol=RES)
    assert abs(float(wrap_angle(res.pose[2] - truth[2]))) <= ANGLE_STEP
    assert res.score > 0.6


def test_wide_correlative_search_finds_the_true_pose_from_a_reversed_heading() -> None:
    res_m, step = 0.1, math.radians(2.0)
    field = room_field(margin_m=3.0, resolution=res_m)
    truth = np.array([4.3, 3.1, math.radians(8)])
    pts = body_points(ROOM, truth)
    prior = truth + np.array([0.15, -0.1, math.radians(170)])
    res = correlative_match(field, pts, prior, 3.0, math.pi, step)
    np.testing.assert_allclose(res.pose[:2], truth[:2], atol=res_m)
    assert abs(float(wrap_angle(res.pose[2] - truth[2]))) <= step


def test_wide_correlative_search_finds_the_true_pose_from_a_far_prior() -> None:
    res_m, step = 0.1, math.radians(2.0)
    field = room_field(margin_m=3.0, resolution=res_m)
    truth = np.array([4.3, 3.1, math.radians(8)])
    pts = body_points(ROOM, truth)
    prior = np.array([6.5, 4.5, -2.0])  # 2.8 m and 123 deg off
    res = correlative_match(field, pts, prior, 3.0, math.pi, step)
    # Returns about (6.1, 3.8, -1.41) with score 0.43; the truth scores 0.89 on this lattice.
    np.testing.assert_allclose(res.pose[:2], truth[:2], atol=res_m)
    assert abs(float(wrap_angle(res.pose[2] - truth[2]))) <= step


def test_correlative_match_is_exact_for_a_far_prior() -> None:
    field = room_field()
    truth = REF_POSE + np.array([0.3, 0.1, math.radians(8)])
    pts = body_points(ROOM, truth)
    prior = truth + np.array([0.45, -0.45, math.radians(3)])
    got = correlative_match(field, pts, prior, WINDOW, math.radians(5), ANGLE_STEP)
    _, want_raw, want_pose = brute_force_match(
        field, pts, prior, WINDOW, math.radians(5), ANGLE_STEP
    )
    # Brute force: 0.886 at the truth; correlative_match reports 0.427 there.
    assert got.score == pytest.approx(want_raw, abs=1e-6)
    assert_same_pose(got.pose, want_pose)


def test_correlative_match_with_unreachable_min_score_returns_the_prior_and_score_zero() -> None:
    field = room_field()
    pts = body_points(ROOM, REF_POSE + np.array([0.1, 0.0, 0.05]))
    prior = REF_POSE + np.array([0.02, -0.03, 0.01])
    res = correlative_match(field, pts, prior, WINDOW, math.radians(5), ANGLE_STEP, min_score=1.01)
    assert res.score == 0.0 and res.penalised_score == 0.0
    np.testing.assert_array_equal(res.pose, prior)


def test_correlative_match_scores_low_against_an_unrelated_scene() -> None:
    field = build_likelihood_field(
        world_points(CORRIDOR, np.array([0.0, 1.0, 0.0]), range_max=8.0),
        RES,
        SMEAR,
        WINDOW,
        N_LEVELS,
    )
    pts = body_points(ROOM, REF_POSE)
    prior = np.array([0.0, 1.0, 0.0])
    res = correlative_match(field, pts, prior, WINDOW, math.radians(10), ANGLE_STEP)
    assert res.score < 0.4
    pruned = correlative_match(
        field, pts, prior, WINDOW, math.radians(10), ANGLE_STEP, min_score=0.6
    )
    assert pruned.score == 0.0
    np.testing.assert_array_equal(pruned.pose, prior)


def test_correlative_match_rejects_a_window_wider_than_the_field_margin() -> None:
    field = room_field(margin_m=0.5)
    pts = body_points(ROOM, REF_POSE)
    with pytest.raises(ValueError, match="exceeds the field's margin"):
        correlative_match(field, pts, REF_POSE, 0.6, math.radians(5), ANGLE_STEP)


def test_correlative_match_rejects_empty_points() -> None:
    with pytest.raises(ValueError, match="no scan points"):
        correlative_match(room_field(), np.empty((0, 2)), REF_POSE, WINDOW, 0.1, ANGLE_STEP)


def test_build_likelihood_field_rejects_empty_points() -> None:
    with pytest.raises(ValueError, match="no reference points"):
        build_likelihood_field(np.empty((0, 2)), RES, SMEAR, WINDOW, N_LEVELS)


def test_pyramid_level_bounds_every_block_of_the_base_field() -> None:
    field = room_field()
    base = field.field
    for k in range(1, N_LEVELS):
        size = 2**k
        padded = np.pad(base, ((0, size), (0, size)))
        h, w = base.shape
        block_max = np.max(
            [padded[i : i + h, j : j + w] for i in range(size) for j in range(size)], axis=0
        )
        np.testing.assert_array_equal(field.levels[k], block_max)


# 3. Point-to-line ICP -----------------------------------------------------------------------------

ICP_TRUTH = np.array([4.3, 3.1, math.radians(8)])
ICP_PERTURBATION = np.array([0.05, -0.05, math.radians(2)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_icp_refine_converges_to_the_truth_on_noiseless_scans(seed: int) -> None:
    ref = build_reference(world_points(ROOM, REF_POSE, n_beams=720))
    pts = body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270))
    sign = np.random.default_rng(seed).choice([-1.0, 1.0], 3)
    res = icp_refine(ref, pts, ICP_TRUTH + sign * ICP_PERTURBATION, MAX_CORRESPONDENCE)
    assert res.converged
    np.testing.assert_allclose(res.pose[:2], ICP_TRUTH[:2], atol=0.005)
    assert abs(float(wrap_angle(res.pose[2] - ICP_TRUTH[2]))) < math.radians(0.2)
    assert res.rmse < 0.005
    assert res.inlier_fraction > 0.9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_icp_refine_stays_within_two_cm_with_one_cm_range_noise(seed: int) -> None:
    ref = build_reference(world_points(ROOM, REF_POSE, n_beams=720, noise_m=0.01, seed=100 + seed))
    pts = body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270), noise_m=0.01, seed=seed)
    res = icp_refine(ref, pts, ICP_TRUTH + ICP_PERTURBATION, MAX_CORRESPONDENCE)
    assert res.converged
    np.testing.assert_allclose(res.pose[:2], ICP_TRUTH[:2], atol=0.02)
    assert abs(float(wrap_angle(res.pose[2] - ICP_TRUTH[2]))) < math.radians(0.5)
    assert 0.005 < res.rmse < 0.02


def test_icp_covariance_is_symmetric_positive_definite_and_small() -> None:
    ref = build_reference(world_points(ROOM, REF_POSE, n_beams=720, noise_m=0.01, seed=5))
    pts = body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270), noise_m=0.01, seed=6)
    cov = icp_refine(ref, pts, ICP_TRUTH + ICP_PERTURBATION, MAX_CORRESPONDENCE).covariance
    np.testing.assert_array_equal(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0.0)
    assert math.sqrt(cov[0, 0]) < 0.005  # [m]
    assert math.sqrt(cov[2, 2]) < math.radians(0.1)


def test_icp_covariance_grows_along_a_featureless_corridor() -> None:
    ref = build_reference(
        world_points(CORRIDOR, np.array([0.0, 1.0, 0.0]), n_beams=720, range_max=10.0)
    )
    truth = np.array([0.5, 0.9, 0.05])
    pts = body_points(CORRIDOR, truth, n_beams=361, fov=math.radians(270), range_max=10.0)
    res = icp_refine(ref, pts, truth + np.array([0.03, 0.03, 0.02]), MAX_CORRESPONDENCE)
    assert res.converged
    assert res.pose[1] == pytest.approx(truth[1], abs=0.005)  # across: recovered
    assert res.covariance[0, 0] > 1e4 * res.covariance[1, 1]  # along: unconstrained


def test_icp_covariance_grows_along_an_exactly_axis_aligned_corridor() -> None:
    xs = np.arange(-10.0, 10.0, 0.05)
    walls = np.vstack(
        [np.column_stack([xs, np.zeros_like(xs)]), np.column_stack([xs, np.full_like(xs, 2.0)])]
    )
    res = icp_refine(
        build_reference(walls),
        walls[::3] - [0.0, 1.0],
        np.array([0.0, 1.02, 0.0]),
        MAX_CORRESPONDENCE,
    )
    assert res.converged
    assert res.covariance[0, 0] > 1e4 * res.covariance[1, 1]


def test_icp_refine_failing_after_an_iteration_returns_the_initial_pose() -> None:
    # A short wall y = 0 (x in [0, 1]) and a wall x = 0 (y in [1, 2]). Ten scan points lie on y = 0
    # just past the end of the first wall, five lie 0.28 m left of the second: the first step
    # moves x by +0.28, which takes the ten beyond the correspondence gate, leaving 5 < MIN_POINTS.
    t = np.linspace(0.0, 1.0, 51)
    ref = build_reference(
        np.vstack(
            [np.column_stack([t, np.zeros_like(t)]), np.column_stack([np.zeros_like(t), 1.0 + t])]
        )
    )
    near_end = np.column_stack([np.linspace(1.1, 1.28, 10), np.zeros(10)])
    left_of_wall = np.column_stack([np.full(5, -0.28), np.linspace(1.2, 1.8, 5)])
    initial = np.zeros(3)
    res = icp_refine(ref, np.vstack([near_end, left_of_wall]), initial, MAX_CORRESPONDENCE)
    assert not res.converged and res.rmse == math.inf
    np.testing.assert_array_equal(res.pose, initial)


def test_icp_refine_without_correspondences_fails_without_raising() -> None:
    ref = build_reference(world_points(ROOM, REF_POSE) + 100.0)
    pts = body_points(ROOM, REF_POSE)
    res = icp_refine(ref, pts, REF_POSE, MAX_CORRESPONDENCE)
    assert not res.converged
    assert res.rmse == math.inf
    assert res.inlier_fraction == 0.0
    np.testing.assert_array_equal(res.pose, REF_POSE)


def test_icp_refine_rejects_a_huber_width_that_is_not_positive() -> None:
    ref = build_reference(world_points(ROOM, REF_POSE))
    with pytest.raises(ValueError, match="huber_m must be > 0"):
        icp_refine(ref, body_points(ROOM, REF_POSE), REF_POSE, MAX_CORRESPONDENCE, huber_m=0.0)


def test_build_reference_normals_are_perpendicular_to_a_straight_wall() -> None:
    direction = np.array([math.cos(0.4), math.sin(0.4)])
    pts = np.array([1.0, -2.0]) + np.linspace(0.0, 3.0, 31)[:, None] * direction
    ref = build_reference(pts)
    assert ref.size == len(pts)
    normals = ref.normals[: ref.size]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(normals @ direction, 0.0, atol=1e-9)
    np.testing.assert_array_equal(ref.normals[ref.size], [0.0, 0.0])


def test_release_degenerate_axis_frees_the_weak_direction_and_keeps_a_well_posed_one() -> None:
    from slam.scan_matching import release_degenerate_axis

    # A corridor along x: along-track variance 400 times the across-track one.
    corridor = np.diag([0.02**2 * 400, 0.02**2, 0.001**2])
    corridor[0, 2] = corridor[2, 0] = 1e-6
    out, degenerate = release_degenerate_axis(corridor, 20.0, 1e6)
    assert degenerate
    assert out[0, 0] == pytest.approx(1e6) and out[1, 1] == pytest.approx(0.02**2)
    assert out[0, 2] == 0.0 and out[2, 2] == corridor[2, 2]
    room = np.diag([0.01**2, 0.02**2, 0.001**2])  # variance ratio 4: both axes observed
    same, degenerate = release_degenerate_axis(room, 20.0, 1e6)
    assert not degenerate
    np.testing.assert_array_equal(same, room)


def _thick_walled_room(res: float = 0.05, origin: float = -0.5) -> np.ndarray:
    """ROOM as a grid a map server would hold: 0.3 m outer walls, a 0.2 m stub wall, the pillar
    and the corner cabinet filled (faces where ROOM's segments are), row 0 at the bottom."""
    n_x, n_y = int(9.0 / res), int(7.0 / res)
    x = origin + (np.arange(n_x) + 0.5) * res
    y = origin + (np.arange(n_y) + 0.5) * res
    gx, gy = np.meshgrid(x, y)
    outside = (gx < 0) | (gx > 8) | (gy < 0) | (gy > 6)
    walls = outside & (gx > -0.3) & (gx < 8.3) & (gy > -0.3) & (gy < 6.3)
    stub = (gx > 2.8) & (gx < 3.0) & (gy > 0) & (gy < 2.5)
    pillar = (gx > 5.5) & (gx < 6.0) & (gy > 3.5) & (gy < 4.0)
    cabinet = (gx > 1.0) & (gx < 2.2) & (gy > 5.0) & (gy < 6.0)
    return walls | stub | pillar | cabinet


def test_grid_reference_has_normals_across_walls_of_any_thickness() -> None:
    from slam.scan_matching import build_grid_reference

    occ = _thick_walled_room()
    ref = build_grid_reference(occ, (-0.5, -0.5), 0.05)
    pts, normals = ref.points[: ref.size], ref.normals[: ref.size]
    # Cells along the long bottom wall's inner face (y just below 0), away from corners.
    face = (np.abs(pts[:, 1] + 0.025) < 1e-9) & (pts[:, 0] > 3.5) & (pts[:, 0] < 7.5)
    assert face.sum() > 50
    np.testing.assert_allclose(np.abs(normals[face, 1]), 1.0, atol=1e-3)
    # Only cells a scan can hit: none from the inside of the 0.3 m walls.
    assert ref.size < 0.6 * occ.sum()
    # Nearest-neighbour PCA on the same cells finds no line at all: the bug this replaces.
    rows, cols = np.nonzero(occ)
    pca = build_reference(np.column_stack([-0.5 + (cols + 0.5) * 0.05, -0.5 + (rows + 0.5) * 0.05]))
    assert np.count_nonzero(np.any(pca.normals != 0, axis=1)) < 0.05 * pca.size


@pytest.mark.parametrize("seed", [0, 1])
def test_icp_against_a_thick_walled_grid_map_recovers_the_pose(seed: int) -> None:
    from slam.scan_matching import build_grid_reference

    ref = build_grid_reference(_thick_walled_room(), (-0.5, -0.5), 0.05)
    pts = body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270))
    sign = np.random.default_rng(seed).choice([-1.0, 1.0], 3)
    res = icp_refine(ref, pts, ICP_TRUTH + sign * ICP_PERTURBATION, MAX_CORRESPONDENCE)
    assert res.converged
    np.testing.assert_allclose(res.pose[:2], ICP_TRUTH[:2], atol=0.02)  # cells: 2.5 cm bias
    assert abs(float(wrap_angle(res.pose[2] - ICP_TRUTH[2]))) < math.radians(0.5)


def test_grid_reference_of_a_grid_without_walls_is_an_error() -> None:
    from slam.scan_matching import build_grid_reference

    with pytest.raises(ValueError, match="no occupied cell"):
        build_grid_reference(np.zeros((10, 10), bool), (0.0, 0.0), 0.05)


# 5. Uniqueness of a match (rival_score) -----------------------------------------------------------


def _periodic_corridor(period: float = 4.0, door: float = 1.0) -> np.ndarray:
    """A 2 m wide corridor along x whose lower wall has a 1 m door gap every ``period`` m:
    one stretch looks exactly like the next (aliasing)."""
    segs = [[-30.0, 2.0, 30.0, 2.0]]
    for x0 in np.arange(-30.0, 30.0, period):
        segs.append([x0, 0.0, x0 + period - door, 0.0])
        segs.append([x0 + period - door, 0.0, x0 + period - door, -1.0])  # door jamb
    return np.array(segs)


def _segment_points(segments: np.ndarray, step: float = 0.02) -> np.ndarray:
    """Points every ``step`` m along each segment: a map as many scans would have built it."""
    out = []
    for x0, y0, x1, y1 in segments:
        t = np.linspace(0.0, 1.0, max(int(math.hypot(x1 - x0, y1 - y0) / step), 2))
        out.append(np.column_stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)]))
    return np.vstack(out)


def test_rival_score_finds_the_aliased_twin_one_period_along_a_periodic_corridor() -> None:
    corridor = _periodic_corridor()
    ref_pose = np.array([0.0, 1.0, 0.0])
    field = build_likelihood_field(_segment_points(corridor), RES, SMEAR, 6.0, N_LEVELS)
    pts = body_points(corridor, ref_pose, range_max=6.0)
    best = float(field.lookup(transform_points(ref_pose, pts)).mean())
    rival = rival_score(field, pts, ref_pose, 5.0, 1.0)
    assert best > 0.5
    assert rival > 0.9 * best, (rival, best)  # one period on, the scan fits about as well


def test_rival_score_of_a_distinctive_room_is_well_below_the_match() -> None:
    field = build_likelihood_field(world_points(ROOM, REF_POSE), RES, SMEAR, 3.0, N_LEVELS)
    pts = body_points(ROOM, REF_POSE)
    best = float(field.lookup(transform_points(REF_POSE, pts)).mean())
    rival = rival_score(field, pts, REF_POSE, 2.5, 1.0)
    assert 0.0 <= rival < 0.6 * best, (rival, best)


def _crossing(arm: float = 8.0, half: float = 1.0) -> np.ndarray:
    """Two 2 m wide corridors crossing at the origin: the same place turned a quarter."""
    segs = []
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        segs.append([sx * half, sy * half, sx * arm, sy * half])
        segs.append([sx * half, sy * half, sx * half, sy * arm])
    return np.array(segs)


def test_rival_score_at_turned_yaws_finds_the_quarter_turned_twin_of_a_junction() -> None:
    # The mapper's loop test for a wide angular window (issue #12: infinite-corridor seed 1
    # closed loops 90 deg off at such a junction): the turned pose at the same place counts.
    from slam.mapper import ROTATED_RIVAL_ANGLES

    crossing, pose = _crossing(), np.array([0.0, 0.0, 0.3])
    field = build_likelihood_field(_segment_points(crossing), RES, SMEAR, 6.0, N_LEVELS)
    pts = body_points(crossing, pose, range_max=6.0)
    best = float(field.lookup(transform_points(pose, pts)).mean())
    turned = rival_score(field, pts, pose, 1.0, -1.0, angles_rad=ROTATED_RIVAL_ANGLES)
    assert best > 0.5
    assert turned > 0.9 * best, (turned, best)
    room = room_field()
    room_pts = body_points(ROOM, REF_POSE)
    room_best = float(room.lookup(transform_points(REF_POSE, room_pts)).mean())
    room_turned = rival_score(room, room_pts, REF_POSE, 1.0, -1.0, angles_rad=ROTATED_RIVAL_ANGLES)
    assert room_turned < 0.7 * room_best, (room_turned, room_best)


def test_rival_score_is_zero_when_the_window_holds_no_far_pose() -> None:
    field = room_field()
    pts = body_points(ROOM, REF_POSE)
    assert rival_score(field, pts, REF_POSE, 0.5, 1.0) == 0.0
    assert rival_score(field, np.zeros((0, 2)), REF_POSE, 2.0, 1.0) == 0.0


# 6. Fast kernels against their straightforward references ----------------------------------------
# The kernels above are tuned for speed (buffers, one gather, LAPACK directly); these are the
# plain versions they replaced, kept to pin down that the tuning changed no result.


def reference_normals(points: np.ndarray) -> np.ndarray:
    """PCA normals of the ``k`` nearest neighbours and any tied with the k-th, written as
    per-point loops over the neighbourhood; (M, 2)."""
    k = min(5, len(points))
    dist, idx = cKDTree(points).query(points, k=min(k + 3, len(points)))
    dist, idx = dist.reshape(len(points), -1), idx.reshape(len(points), -1)
    sxx, syy, sxy = (np.empty(len(points)) for _ in range(3))
    for m in range(len(points)):
        nb = points[idx[m][dist[m] <= dist[m, k - 1] * (1 + NORMAL_TIE_RTOL)]]
        d = nb - nb.mean(axis=0)
        sxx[m], syy[m], sxy[m] = (d[:, 0] @ d[:, 0], d[:, 1] @ d[:, 1], d[:, 0] @ d[:, 1])
        sxx[m], syy[m], sxy[m] = sxx[m] / len(nb), syy[m] / len(nb), sxy[m] / len(nb)
    phi = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    normals = np.column_stack([-np.sin(phi), np.cos(phi)])
    mean, radius = 0.5 * (sxx + syy), np.hypot(0.5 * (sxx - syy), sxy)
    linear = (mean - radius) <= 0.2 * np.maximum(mean + radius, 1e-12)
    return np.where(linear[:, None], normals, 0.0)


def reference_icp(
    ref: ReferenceCloud,
    points: np.ndarray,
    initial: np.ndarray,
    max_correspondence_m: float,
    max_iterations: int = 20,
    huber_m: float = 0.05,
    min_sigma_m: float = 0.01,
    tolerance: float = 5e-4,
) -> IcpResult:
    """Point-to-line Gauss-Newton with a fresh (N, 3) Jacobian and np.linalg.solve per
    iteration."""
    pose = np.asarray(initial, dtype=np.float64).copy()
    failed = IcpResult(pose.copy(), np.diag([1e6, 1e6, 1e6]), math.inf, 0.0, 0, False)
    px, py = points[:, 0], points[:, 1]
    it, converged = 0, False
    for it in range(1, max_iterations + 1):  # noqa: B007 - it is reported
        c, s = math.cos(pose[2]), math.sin(pose[2])
        wx, wy = c * px - s * py + pose[0], s * px + c * py + pose[1]
        _, idx = ref.tree.query(
            np.column_stack([wx, wy]), distance_upper_bound=max_correspondence_m
        )
        nx, ny = ref.normals[idx, 0], ref.normals[idx, 1]
        r = nx * (wx - ref.points[idx, 0]) + ny * (wy - ref.points[idx, 1])
        jac = np.column_stack([nx, ny, nx * (-s * px - c * py) + ny * (c * px - s * py)])
        absr = np.abs(r)
        wts = np.where(absr <= huber_m, 1.0, huber_m / np.maximum(absr, 1e-12))
        wts *= (nx != 0) | (ny != 0)
        n_used = int(np.count_nonzero(wts))
        if n_used < 10:
            return failed
        jw = jac * wts[:, None]
        hess = jw.T @ jac
        delta = -np.linalg.solve(hess + 1e-9 * np.trace(hess) * np.eye(3), jw.T @ r)
        pose += delta
        if abs(delta[0]) + abs(delta[1]) < tolerance and abs(delta[2]) < tolerance:
            converged = True
            break
    pose[2] = float(wrap_angle(pose[2]))
    rmse = math.sqrt(float(np.sum(wts * r**2)) / max(float(np.sum(wts)), 1e-12))
    sigma2 = max(float(np.sum(wts * r**2)) / max(n_used - 3, 1), min_sigma_m**2)
    evals, evecs = np.linalg.eigh(0.5 * (hess + hess.T))
    evals = np.maximum(evals, 1e-9 * max(float(evals[-1]), 1e-12))
    cov = sigma2 * (evecs / evals) @ evecs.T
    inliers = float(np.count_nonzero(idx < ref.size)) / len(points)
    return IcpResult(pose, 0.5 * (cov + cov.T), rmse, inliers, it, converged)


def test_build_reference_normals_equal_the_per_point_reference_on_random_clouds() -> None:
    rng = np.random.default_rng(11)
    clouds = [
        world_points(ROOM, REF_POSE, n_beams=720, noise_m=0.01, seed=3),
        rng.normal(size=(400, 2)) * 3.0,
        np.column_stack([np.arange(40) * 0.05, np.zeros(40)]),  # exact ties, axis-aligned
        rng.normal(size=(3, 2)),
    ]
    for pts in clouds:
        ref = build_reference(pts)
        np.testing.assert_allclose(ref.normals[:-1], reference_normals(pts), atol=1e-9)
        np.testing.assert_array_equal(ref.points[:-1], pts)
        np.testing.assert_array_equal(ref.columns[:, -1], 0.0)  # the missing-neighbour row


@pytest.mark.parametrize("seed", range(6))
def test_icp_refine_equals_the_reference_kernel_from_random_starts(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref = build_reference(world_points(ROOM, REF_POSE, n_beams=720, noise_m=0.01, seed=seed))
    pts = body_points(
        ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270), noise_m=0.01, seed=50 + seed
    )
    start = ICP_TRUTH + rng.normal(size=3) * [0.1, 0.1, math.radians(3)]
    iterations = int(rng.integers(1, 21))
    fast = icp_refine(ref, pts, start, MAX_CORRESPONDENCE, max_iterations=iterations)
    plain = reference_icp(ref, pts, start, MAX_CORRESPONDENCE, max_iterations=iterations)
    # The same operations in the same order, so equal to the last bit with this build's LAPACK;
    # the tolerance keeps the test about behaviour rather than about one LAPACK build.
    assert (fast.iterations, fast.converged) == (plain.iterations, plain.converged)
    assert fast.inlier_fraction == plain.inlier_fraction
    np.testing.assert_allclose(fast.pose, plain.pose, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(fast.covariance, plain.covariance, rtol=1e-9, atol=0.0)
    assert fast.rmse == pytest.approx(plain.rmse, rel=1e-9)


def test_icp_refine_equals_the_reference_kernel_when_too_few_points_match() -> None:
    ref = build_reference(world_points(ROOM, REF_POSE))
    pts = body_points(ROOM, REF_POSE)[:8]
    fast = icp_refine(ref, pts, REF_POSE, MAX_CORRESPONDENCE)
    plain = reference_icp(ref, pts, REF_POSE, MAX_CORRESPONDENCE)
    assert (fast.rmse, fast.converged, fast.iterations) == (plain.rmse, plain.converged, 0)
    np.testing.assert_array_equal(fast.pose, plain.pose)


def reference_rival(
    field: LikelihoodField,
    points: np.ndarray,
    pose: np.ndarray,
    linear_window_m: float,
    exclude_m: float,
    angles_rad: np.ndarray,
    stride: int = 4,
    refined: int = 5,
    chunk: int = 2048,
) -> float:
    """rival_score with every coarse sample looked up point by point (``lookup_xy`` of the
    shifted points), in the same chunks."""
    n = int(math.ceil(linear_window_m / field.resolution))
    offs = np.arange(-n, n + 1, stride, dtype=np.float64) * field.resolution
    dx, dy = (v.ravel() for v in np.meshgrid(offs, offs))
    far = np.hypot(dx, dy) > exclude_m
    if len(points) == 0 or not far.any():
        return 0.0
    dx, dy = dx[far], dy[far]
    best = []
    for yaw in pose[2] + angles_rad:
        c, s = math.cos(yaw), math.sin(yaw)
        wx = c * points[:, 0] - s * points[:, 1] + pose[0]
        wy = s * points[:, 0] + c * points[:, 1] + pose[1]
        for lo in range(0, len(dx), chunk):
            sx, sy = dx[lo : lo + chunk], dy[lo : lo + chunk]
            sc = field.lookup_xy(wx[None, :] + sx[:, None], wy[None, :] + sy[:, None]).mean(axis=1)
            best.extend((float(sc[t]), sx[t], sy[t], yaw) for t in np.argsort(sc)[-refined:])
    best.sort(reverse=True)
    fine = np.arange(-(stride // 2), stride // 2 + 1, dtype=np.float64) * field.resolution
    fx, fy = (v.ravel() for v in np.meshgrid(fine, fine))
    rival = 0.0
    for score, bx, by, yaw in best[:refined]:
        rival = max(rival, score)
        ox, oy = bx + fx, by + fy
        keep = np.hypot(ox, oy) > exclude_m
        c, s = math.cos(yaw), math.sin(yaw)
        wx = c * points[:, 0] - s * points[:, 1] + pose[0]
        wy = s * points[:, 0] + c * points[:, 1] + pose[1]
        if keep.any():
            sc = field.lookup_xy(wx[None, :] + ox[keep][:, None], wy[None, :] + oy[keep][:, None])
            rival = max(rival, float(sc.mean(axis=1).max()))
    return rival


def test_rival_score_equals_the_point_by_point_reference_to_the_bit() -> None:
    # rival_score adds per-offset row and column indices instead of looking every sample up:
    # the same cells, so the same score; one window reaches past the grid.
    from slam.mapper import ROTATED_RIVAL_ANGLES
    from slam.scan_matching import AMBIGUITY_ANGLES

    corridor = _periodic_corridor()
    near = _segment_points(corridor)
    near = near[np.abs(near[:, 0]) < 6.0]
    field = build_likelihood_field(near, RES, SMEAR, 3.0, N_LEVELS)
    pose = np.array([0.3, 1.1, 0.05])
    pts = body_points(corridor, pose, range_max=8.0, noise_m=0.01, seed=7)
    for window, exclude, angles in (
        (3.0, 1.0, AMBIGUITY_ANGLES),
        (2.0, -1.0, ROTATED_RIVAL_ANGLES),
    ):
        plain = reference_rival(field, pts, pose, window, exclude, angles)
        assert plain > 0.0
        assert rival_score(field, pts, pose, window, exclude, angles_rad=angles) == plain


def test_voxel_filter_equals_np_unique_first_occurrence_on_random_clouds() -> None:
    rng = np.random.default_rng(4)
    for n, voxel in ((1, 0.1), (50, 0.5), (2000, 0.05), (2000, 0.3)):
        pts = rng.uniform(-5.0, 5.0, size=(n, 2))
        keys = np.floor(pts / voxel).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        np.testing.assert_array_equal(voxel_filter(pts, voxel), pts[np.sort(first)])


def test_lookup_xy_on_a_batch_equals_lookup_of_the_stacked_points() -> None:
    field = room_field()
    rng = np.random.default_rng(8)
    x, y = rng.uniform(-2.0, 12.0, size=(2, 7, 30))  # some off the grid
    stacked = field.lookup(np.column_stack([x.ravel(), y.ravel()])).reshape(7, 30)
    np.testing.assert_array_equal(field.lookup_xy(x, y), stacked)
    rows = np.clip(np.floor((y - field.origin[1]) / RES).astype(int), 0, field.field.shape[0] - 1)
    cols = np.clip(np.floor((x - field.origin[0]) / RES).astype(int), 0, field.field.shape[1] - 1)
    np.testing.assert_array_equal(stacked, field.field[rows, cols])


def test_flat_levels_hold_the_levels_followed_by_a_zero_tail() -> None:
    field = room_field()
    h, w = field.field.shape
    for level, flat in zip(field.levels, field.flat_levels, strict=True):
        np.testing.assert_array_equal(flat[: h * w], level.ravel())
        assert len(flat) >= h * w + (field.max_window_cells + 1) * (w + 1)
        assert not flat[h * w :].any()
    assert field.field.dtype == np.float32 and field.field.max() == 1.0  # exp(0)


def test_reference_normals_do_not_depend_on_which_tied_neighbour_the_tree_lists_first() -> None:
    # Point 0's 5th-nearest neighbour is a tie at 0.1 m: (0, 0.1) off the wall and (-0.1, 0)
    # on it. A fixed k took whichever the k-d tree listed first, so the input order (and, on
    # real scans, the rounding of a CPU's BLAS kernels) decided whether 0 had a normal (issue
    # #12: aces mapped 0.27 m vs 0.39 m under two OpenBLAS core types). Both tied points count.
    pts = np.array(
        [[0, 0], [0.05, 0], [-0.05, 0], [0.08, 0], [0, 0.1], [-0.1, 0]]
        + [[3 + 0.05 * i, 3.0] for i in range(5)]
    )
    normals = []
    for order in (list(range(11)), [0, 1, 2, 3, 5, 4, *range(6, 11)], list(range(10, -1, -1))):
        ref = build_reference(pts[order])
        normals.append(ref.normals[order.index(0)])
    assert all(np.array_equal(n, normals[0]) for n in normals)


def test_reference_normals_without_ties_are_the_k_nearest_fit() -> None:
    rng = np.random.default_rng(3)
    pts = np.column_stack([np.linspace(0, 2, 40), 0.002 * rng.standard_normal(40)])
    ref = build_reference(pts)
    # A straight wall: every normal is +-y, from exactly 5 neighbours (no ties in random data).
    assert np.all(np.abs(np.abs(ref.normals[:-1, 1]) - 1.0) < 0.05)


def test_a_polished_icp_ends_where_it_ends_whatever_its_start() -> None:
    # Stopped at a step < 5e-4, ICP's pose still carries its start (the odometry prior or the
    # correlative optimum, and a CPU's rounding) at the 0.1 mm level; polished to 1e-5 two
    # starts land together (issue #12: the mapper's two tracking paths flipped maps).
    ref = build_reference(world_points(ROOM, REF_POSE, n_beams=720, noise_m=0.03, seed=5))
    pts = body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270), noise_m=0.03, seed=6)
    offset = np.array([0.08, -0.08, math.radians(3)])
    starts = [ICP_TRUTH + offset, ICP_TRUTH - offset]
    plain = [icp_refine(ref, pts, s, MAX_CORRESPONDENCE) for s in starts]
    polished = [icp_refine(ref, pts, s, MAX_CORRESPONDENCE, 30, polish=1e-5) for s in starts]
    assert all(r.converged for r in plain + polished)
    assert np.abs(plain[0].pose - plain[1].pose).max() > 1e-4
    assert np.abs(polished[0].pose - polished[1].pose).max() < 1e-6


def _two_cell_walls(res: float = 0.05, origin: float = -0.5) -> np.ndarray:
    """ROOM as a mapper draws it when its walls lie on cell boundaries: range noise puts hits on
    both sides of each wall, so every wall is the two cells straddling its line."""
    n_x, n_y = int(9.0 / res), int(7.0 / res)
    gx, gy = np.meshgrid(
        origin + (np.arange(n_x) + 0.5) * res, origin + (np.arange(n_y) + 0.5) * res
    )
    occ = np.zeros(gx.shape, bool)
    for x0, y0, x1, y1 in ROOM:
        across, along, (lo, hi) = (gx - x0, gy, (y0, y1)) if x0 == x1 else (gy - y0, gx, (x0, x1))
        occ |= (np.abs(across) < res) & (along > min(lo, hi) - res) & (along < max(lo, hi) + res)
    return occ


@pytest.mark.parametrize(
    "truth", [ICP_TRUTH, np.array([2.0, 4.0, 1.0]), np.array([6.7, 1.2, -2.0])], ids=str
)
def test_the_sub_cell_polish_recovers_the_pose_icp_snaps_to_cell_centres(
    truth: np.ndarray,
) -> None:
    from slam.scan_matching import (
        build_grid_reference,
        build_smooth_field,
        refine_on_field,
        surface_mask,
    )

    occ = _two_cell_walls()
    ref = build_grid_reference(occ, (-0.5, -0.5), 0.05)
    field = build_smooth_field(surface_mask(occ), (-0.5, -0.5), 0.05, 0.0375)
    pts = body_points(ROOM, truth, n_beams=361, fov=math.radians(270), noise_m=0.005)
    icp = icp_refine(ref, pts, truth + ICP_PERTURBATION, MAX_CORRESPONDENCE)
    # ICP's references are cell centres 2.5 cm either side of each wall: it ends on them.
    assert math.hypot(*(icp.pose[:2] - truth[:2])) > 0.015
    res = refine_on_field(field, pts, icp.pose, max_shift_m=0.05, max_turn_rad=0.0175)
    assert res.ok and res.reason == ""
    assert math.hypot(*(res.pose[:2] - truth[:2])) < 0.005
    assert abs(float(wrap_angle(res.pose[2] - truth[2]))) < math.radians(0.05)


def test_the_sub_cell_polish_falls_back_to_its_start_outside_the_basin_or_the_map() -> None:
    from slam.scan_matching import build_smooth_field, refine_on_field, surface_mask

    occ = _two_cell_walls()
    field = build_smooth_field(surface_mask(occ), (-0.5, -0.5), 0.05, 0.0375)
    pts = body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270))
    # It converges 1.5 cm away, beyond a 1 cm basin: the start is kept and the reason given.
    start = ICP_TRUTH + np.array([0.015, 0.0, 0.0])
    res = refine_on_field(field, pts, start, max_shift_m=0.01)
    assert not res.ok and res.reason == "left the match's basin"
    np.testing.assert_array_equal(res.pose, start)
    # Far outside the map no point sees the field.
    away = refine_on_field(field, pts, np.array([50.0, 50.0, 0.0]))
    assert not away.ok and away.reason == "too few points on the smooth field"
    assert away.iterations == 0


def _polish_setup(holes: bool) -> tuple:
    """The two-cell-wall ROOM, with three 0.3 m gaps cut in its mapped walls if ``holes``: its
    ICP reference (the wall cells) and the polish's smooth field."""
    from slam.scan_matching import build_grid_reference, build_smooth_field, surface_mask

    occ = _two_cell_walls()
    if holes:
        occ[:, 40:46] = occ[:, 100:106] = occ[60:66, :] = False
    ref = build_grid_reference(occ, (-0.5, -0.5), 0.05)
    return ref, build_smooth_field(surface_mask(occ), (-0.5, -0.5), 0.05, 0.0375)


def test_near_surface_leaves_out_the_scan_points_in_a_gap_of_the_mapped_walls() -> None:
    # The polish's points: a scan point in a gap of a mapped wall would be pulled along the
    # wall onto the gap's end (test_scan_frame's 160x120 scan turned 0.6 deg that way).
    from slam.scan_matching import near_surface

    ref, _ = _polish_setup(holes=True)
    world = transform_points(
        ICP_TRUTH, body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270))
    )
    on_wall = near_surface(ref, world, 0.05)
    # The gaps: columns 40-45 and 100-105 (x from 1.5 and 4.5 m), rows 60-65 (y from 2.5 m).
    gap_x = ((world[:, 0] > 1.5) & (world[:, 0] < 1.8)) | (
        (world[:, 0] > 4.5) & (world[:, 0] < 4.8)
    )
    gap = gap_x | ((world[:, 1] > 2.5) & (world[:, 1] < 2.8))
    inner = (
        ((world[:, 0] > 1.6) & (world[:, 0] < 1.7))
        | ((world[:, 0] > 4.6) & (world[:, 0] < 4.7))
        | ((world[:, 1] > 2.6) & (world[:, 1] < 2.7))
    )
    assert np.count_nonzero(inner) >= 5 and not on_wall[inner].any()
    assert on_wall[~gap].all()


def test_the_sub_cell_polish_gives_one_world_pose_whatever_the_scan_frame() -> None:
    # The same points in base_link and in a frame 0.2 m ahead (a camera-frame depth scan),
    # from a start turned 0.86 deg about their centroid. The polish turns about the centroid and
    # tests its basin there: both land on one pose. (Measured at the scan frame's origin, the
    # move was 1.6 cm in base_link and 1.3 cm in the camera frame: only one kept it.)
    from slam.geometry import ominus, oplus
    from slam.scan_matching import refine_on_field

    ref, field = _polish_setup(holes=False)
    pts = body_points(ROOM, ICP_TRUTH, n_beams=361, fov=math.radians(270), noise_m=0.005)
    mount = np.array([0.2, 0.05, 0.0])
    centroid = np.array([*pts.mean(axis=0), 0.0])
    turned = oplus(oplus(ICP_TRUTH, centroid), np.array([0.0, 0.0, 0.015]))
    start = oplus(turned, ominus(centroid, np.zeros(3)))
    kw = {"max_shift_m": 0.014, "max_turn_rad": 0.0175}
    base = refine_on_field(field, pts, start, **kw)
    cam = refine_on_field(field, pts - mount[:2], oplus(start, mount), **kw)
    assert base.ok and cam.ok
    assert np.abs(oplus(cam.pose, ominus(mount, np.zeros(3))) - base.pose).max() < 1e-9
    assert math.hypot(*(base.pose[:2] - ICP_TRUTH[:2])) < 0.002
    assert abs(float(wrap_angle(base.pose[2] - ICP_TRUTH[2]))) < math.radians(0.05)  # from 0.86
