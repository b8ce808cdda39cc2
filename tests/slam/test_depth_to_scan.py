"""Depth -> scan against analytic scenes rendered by the simulator (noise-free "raster")."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.sim.render import KinectRenderer
from sensors.sim.world import world_from_dict
from sensors.types import CameraIntrinsics
from slam.config import DepthToScanConfig
from slam.depth_to_scan import (
    DepthToScan,
    DepthToScanError,
    nearest_per_beam_reference,
)
from tests.sim_worlds import room, wall_ahead

CAMERA = CameraConfig()
ROBOT = RobotConfig()
CFG = DepthToScanConfig()
INTRINSICS = CameraIntrinsics(
    CAMERA.width, CAMERA.height, CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, CAMERA.depth_scale
)
TILT_RAD = 0.35  # [rad] nose down
RANGE_TOL_M = 0.01  # [m]


def true_depth(world: dict, robot: RobotConfig = ROBOT) -> np.ndarray:
    r = KinectRenderer(world_from_dict(world), CAMERA, robot, SimConfig(), backend="raster")
    return r.true_depth(0.0, 0.0, 0.0)


def line_ranges(
    scan_angles: np.ndarray, inc: float, dist_m: float, normal_rad: float
) -> np.ndarray:
    """Nearest point of the line {p : p . n = dist} within each beam's +-inc/2 sector."""
    off = np.clip(normal_rad, scan_angles - inc / 2, scan_angles + inc / 2) - normal_rad
    return dist_m / np.cos(off)


def test_wall_ahead_gives_two_over_cos_theta_across_the_fov() -> None:
    conv = DepthToScan(INTRINSICS, ROBOT, CFG)
    out = conv(true_depth(room([wall_ahead(2.05)])))  # near face at 2.0 m
    a = out.scan.angles()
    half_fov = math.atan(CAMERA.cx / CAMERA.fx)
    assert a[0] == pytest.approx(-half_fov, abs=1e-6)
    assert a[-1] == pytest.approx(half_fov, abs=CFG.angle_increment / 2)
    assert np.all(np.isfinite(out.scan.ranges))
    expect = line_ranges(a, conv.angle_increment, 2.0, 0.0)
    np.testing.assert_allclose(out.scan.ranges, expect, atol=RANGE_TOL_M)
    np.testing.assert_allclose(out.scan.ranges, 2.0 / np.cos(a), atol=RANGE_TOL_M + 0.0025)


def test_increment_derived_from_fx_gives_no_empty_beam_on_the_exact_curve() -> None:
    conv = DepthToScan(INTRINSICS, ROBOT, replace(CFG, angle_increment=0.0))
    out = conv(true_depth(room([wall_ahead(2.05)])))
    assert conv.angle_increment == pytest.approx(1.0 / CAMERA.fx)
    assert np.all(np.isfinite(out.scan.ranges))
    np.testing.assert_allclose(out.scan.ranges, 2.0 / np.cos(out.scan.angles()), atol=0.005)


def test_wall_turned_by_30_degrees_gives_the_analytic_line() -> None:
    out = DepthToScan(INTRINSICS, ROBOT, CFG)(true_depth(room([wall_ahead(2.0, 30.0)])))
    a = out.scan.angles()
    phi = math.radians(30.0)
    expect = line_ranges(a, CFG.angle_increment, 2.0 * math.cos(phi) - 0.05, phi)
    assert np.all(np.isfinite(out.scan.ranges))
    np.testing.assert_allclose(out.scan.ranges, expect, atol=RANGE_TOL_M)


def test_tilted_camera_over_an_empty_floor_sees_nothing() -> None:
    robot = replace(ROBOT, camera_pitch=TILT_RAD)
    depth = true_depth(room([wall_ahead(25.0), wall_ahead(-25.0)]), robot)
    out = DepthToScan(INTRINSICS, robot, CFG)(depth)
    near_floor = np.count_nonzero(depth < CFG.range_max)
    assert near_floor > 0.5 * depth.size  # a naive depth->scan would report the floor
    assert np.all(np.isposinf(out.scan.ranges))
    assert out.in_band_points == 0


def test_tilted_camera_sees_a_wall_at_its_true_distance() -> None:
    robot = replace(ROBOT, camera_pitch=TILT_RAD)
    out = DepthToScan(INTRINSICS, robot, CFG)(true_depth(room([wall_ahead(2.05)]), robot))
    a, r = out.scan.angles(), out.scan.ranges
    assert np.all(np.isfinite(r[np.abs(a) < 0.45]))
    seen = np.isfinite(r)
    expect = line_ranges(a, CFG.angle_increment, 2.0, 0.0)
    np.testing.assert_allclose(r[seen], expect[seen], atol=RANGE_TOL_M)


def box(near_m: float, half_width_m: float, height_m: float, elevation_m: float = 0.0) -> dict:
    depth_m = 0.5
    return {
        "center": [near_m + depth_m / 2, 0.0],
        "size": [depth_m, 2 * half_width_m, height_m],
        "elevation": elevation_m,
    }


def sector(a: np.ndarray, inc: float, near_m: float, half_width_m: float) -> np.ndarray:
    """Beams whose whole sector sees the box's near face."""
    return np.abs(a) + inc / 2 < math.atan(half_width_m / near_m)


def test_box_below_min_height_is_ignored_and_a_taller_one_is_seen() -> None:
    conv = DepthToScan(INTRINSICS, ROBOT, CFG)
    a, inc = conv.angles(), conv.angle_increment
    wall = line_ranges(a, inc, 3.0, 0.0)
    low = conv(true_depth(room([wall_ahead(3.05)], [box(1.5, 0.3, 0.03)])))
    np.testing.assert_allclose(low.scan.ranges, wall, atol=RANGE_TOL_M)
    tall = conv(true_depth(room([wall_ahead(3.05)], [box(1.5, 0.3, 0.4)])))
    inside = sector(a, inc, 1.5, 0.3)
    assert np.count_nonzero(inside) >= 15
    np.testing.assert_allclose(
        tall.scan.ranges[inside], line_ranges(a, inc, 1.5, 0.0)[inside], atol=RANGE_TOL_M
    )


def test_height_band_sees_a_table_top_the_centre_rows_miss() -> None:
    depth = true_depth(room([wall_ahead(3.05)], [box(1.0, 0.4, 0.05, elevation_m=0.6)]))
    narrow = DepthToScan(INTRINSICS, ROBOT, replace(CFG, scan_height=10))(depth)
    band = DepthToScan(INTRINSICS, ROBOT, CFG)(depth)  # scan_height 0: every row
    a = band.scan.angles()
    inside = sector(a, CFG.angle_increment, 1.0, 0.4)
    assert np.all(narrow.scan.ranges[inside] > 2.9)  # straight through to the wall
    expect = line_ranges(a, CFG.angle_increment, 1.0, 0.0)
    np.testing.assert_allclose(band.scan.ranges[inside], expect[inside], atol=RANGE_TOL_M)


def test_invalid_pixels_never_produce_returns() -> None:
    conv = DepthToScan(INTRINSICS, ROBOT, CFG)
    depth = true_depth(room([wall_ahead(2.05)]))
    junk = np.zeros_like(depth)
    junk[::2] = np.nan
    empty = conv(junk)
    assert np.all(np.isposinf(empty.scan.ranges))
    assert (empty.valid_pixels, empty.in_band_points) == (0, 0)
    half = depth.copy()
    half[:, : CAMERA.width // 2] = 0.0  # left half of the image = positive bearings
    half[::3, : CAMERA.width // 2] = np.nan
    out = conv(half)
    a = out.scan.angles()
    assert np.all(np.isposinf(out.scan.ranges[a > CFG.angle_increment]))
    assert np.all(np.isfinite(out.scan.ranges[a < -CFG.angle_increment]))
    assert out.valid_pixels == depth.size // 2


def test_range_limits_are_respected() -> None:
    cfg = replace(CFG, range_min=2.05, range_max=2.1)
    out = DepthToScan(INTRINSICS, ROBOT, cfg)(true_depth(room([wall_ahead(2.05)])))
    a, r = out.scan.angles(), out.scan.ranges
    assert (out.scan.range_min, out.scan.range_max) == (2.05, 2.1)
    finite = r[np.isfinite(r)]
    assert np.all((finite >= 2.05) & (finite <= 2.1))
    assert np.all(np.isposinf(r[np.abs(a) < 0.2]))  # 2/cos(0.21) < 2.05
    assert np.all(np.isposinf(r[np.abs(a) > 0.33]))  # 2/cos(0.32) > 2.1
    assert np.all(np.isfinite(r[(np.abs(a) > 0.24) & (np.abs(a) < 0.29)]))


def test_camera_ahead_of_the_axle_reports_ranges_from_base_link_or_the_camera() -> None:
    robot = replace(ROBOT, camera_x=0.2)
    depth = true_depth(room([wall_ahead(2.05)]), robot)
    base = DepthToScan(INTRINSICS, robot, CFG)
    assert not base.fixed_bearing
    out = base(depth)
    seen = np.isfinite(out.scan.ranges)
    # Seen from the axle, the camera's field of view narrows to atan(1.8 tan(half_fov) / 2).
    assert np.all(seen[np.abs(out.scan.angles()) < 0.49])
    expect = line_ranges(out.scan.angles(), CFG.angle_increment, 2.0, 0.0)
    np.testing.assert_allclose(out.scan.ranges[seen], expect[seen], atol=RANGE_TOL_M)
    cam = DepthToScan(INTRINSICS, robot, replace(CFG, output_frame="camera_link"))
    assert cam.fixed_bearing
    expect_cam = line_ranges(cam.angles(), CFG.angle_increment, 1.8, 0.0)
    np.testing.assert_allclose(cam(depth).scan.ranges, expect_cam, atol=RANGE_TOL_M)


def test_sorted_and_minimum_at_reductions_agree_exactly() -> None:
    world = room([wall_ahead(3.05, 20.0)], [box(1.2, 0.3, 0.4), box(2.0, 0.5, 0.05, 0.6)])
    robot = replace(ROBOT, camera_pitch=0.2, camera_roll=0.05)
    depth = true_depth(world, robot)
    depth[np.random.default_rng(0).random(depth.shape) < 0.1] = 0.0
    fast = DepthToScan(INTRINSICS, robot, CFG)(depth)
    ref = DepthToScan(INTRINSICS, robot, CFG, reduction="minimum_at")(depth)
    np.testing.assert_array_equal(fast.scan.ranges, ref.scan.ranges)
    assert fast.in_band_points == ref.in_band_points > 0


def test_sorted_cluster_averaging_agrees_with_the_reference_kernel() -> None:
    # Noisy depth, holes, a box in front of a wall and beams with no return at all: the sorted
    # kernel (branch-free sums over beam groups) gives the reference's means.
    world = room([wall_ahead(3.05, 20.0)], [box(1.2, 0.3, 0.4), box(2.0, 0.5, 0.05, 0.6)])
    robot = replace(ROBOT, camera_pitch=0.2, camera_roll=0.05)
    rng = np.random.default_rng(1)
    depth = true_depth(world, robot)
    depth = depth + rng.normal(0.0, 0.0018, depth.shape).astype(np.float32) * depth**2
    depth[rng.random(depth.shape) < 0.1] = 0.0
    depth[:, :40] = np.nan  # a band of columns with no return
    cfg = replace(CFG, return_averaging_window=0.01)
    fast = DepthToScan(INTRINSICS, robot, cfg)(depth).scan.ranges
    ref = DepthToScan(INTRINSICS, robot, cfg, reduction="minimum_at")(depth).scan.ranges
    nearest = DepthToScan(INTRINSICS, robot, CFG)(depth).scan.ranges
    np.testing.assert_array_equal(np.isfinite(fast), np.isfinite(ref))
    assert np.count_nonzero(np.isinf(ref)) > 0 and np.count_nonzero(fast > nearest) > 10
    np.testing.assert_allclose(fast, ref, rtol=1e-6)


def test_reference_kernel_keeps_the_nearest_and_leaves_empty_beams_inf() -> None:
    out = nearest_per_beam_reference(np.array([0, 2, 2, 5]), np.array([3.0, 2.0, 1.0, 9.0]), 4)
    np.testing.assert_array_equal(out, [3.0, np.inf, 1.0, np.inf])


def test_unknown_output_frame_and_wrong_image_size_are_errors() -> None:
    with pytest.raises(DepthToScanError, match="output_frame: 'laser'"):
        DepthToScan(INTRINSICS, ROBOT, replace(CFG, output_frame="laser"))
    with pytest.raises(DepthToScanError, match=r"depth image is \(4, 4\)"):
        DepthToScan(INTRINSICS, ROBOT, CFG)(np.ones((4, 4), np.float32))


def test_noisy_kinect_scan_stays_within_three_sigma_of_the_wall() -> None:
    sim = SimConfig()
    r = KinectRenderer(
        world_from_dict(room([wall_ahead(2.05)])), CAMERA, ROBOT, sim, backend="raster"
    )
    _, depth = r.render(0.0, 0.0, 0.0, np.random.default_rng(3))
    out = DepthToScan(INTRINSICS, ROBOT, replace(CFG, scan_height=1))(depth)
    a = out.scan.angles()
    expect = line_ranges(a, CFG.angle_increment, 2.0, 0.0)
    step = 2.0**2 / (CAMERA.disparity_focal * CAMERA.baseline) / sim.disparity_subpixel
    tol = 3 * float(r.depth_sigma(2.0 / math.cos(a.max()))) + step
    seen = np.isfinite(out.scan.ranges)
    assert np.count_nonzero(seen) >= 0.9 * len(a)
    assert np.max(np.abs(out.scan.ranges[seen] - expect[seen])) <= tol


def test_nearest_return_of_noisy_depth_is_biased_short_and_cluster_averaging_removes_it() -> None:
    # Kinect-like noise at 3 m: sigma = 0.0018 * z^2 = 16 mm per pixel. The nearest of the ~100
    # pixels in a beam sits ~2.5 sigma short; the near-cluster mean does not.
    depth = true_depth(room([wall_ahead(3.05)]))
    rng = np.random.default_rng(0)
    noisy = depth + rng.normal(0.0, 0.0018 * 3.0**2, depth.shape).astype(np.float32)
    nearest = DepthToScan(INTRINSICS, ROBOT, CFG)(noisy).scan
    averaged = DepthToScan(INTRINSICS, ROBOT, replace(CFG, return_averaging_window=0.01))(noisy)
    truth = 3.0 / np.cos(nearest.angles())
    bias_nearest = float(np.median(nearest.ranges - truth))
    bias_averaged = float(np.median(averaged.scan.ranges - truth))
    assert bias_nearest < -0.025
    assert abs(bias_averaged) < 0.006


def test_cluster_averaging_keeps_a_nearer_obstacle_in_the_beam() -> None:
    from slam.depth_to_scan import near_cluster_mean

    beam = np.array([0, 0, 0, 1, 1])
    r = np.array([1.00, 1.004, 2.0, 3.0, np.inf], np.float32)
    nearest = nearest_per_beam_reference(beam, r, 3)
    out = near_cluster_mean(beam, r, nearest, 0.01)
    np.testing.assert_allclose(out, [1.002, 3.0, np.inf], rtol=1e-6)


def test_scan_pose_and_base_pose_move_a_pose_by_the_scan_frames_offset_and_back() -> None:
    from slam.depth_to_scan import base_pose, scan_frame_in_base, scan_pose

    at = scan_frame_in_base(
        RobotConfig(camera_x=0.2, camera_y=0.05), replace(CFG, output_frame="camera_link")
    )
    base = np.array([[1.0, 2.0, np.pi / 2], [0.0, 0.0, 0.0]])
    cam = scan_pose(base, at)
    np.testing.assert_allclose(cam, [[0.95, 2.2, np.pi / 2], [0.2, 0.05, 0.0]], atol=1e-12)
    np.testing.assert_allclose(base_pose(cam, at), base, atol=1e-12)
    # base_link scans: the pose itself, bit for bit (the mapper's results do not move by an ulp)
    yaw = np.array([0.3, 0.4, 3.141592653589793])
    assert np.array_equal(scan_pose(yaw, np.zeros(3)), yaw)
    assert np.array_equal(base_pose(yaw, np.zeros(3)), yaw)


def test_base_covariance_is_the_spread_of_base_pose_over_samples_of_the_scan_frames_pose() -> None:
    """A camera-frame pose known to 1 mm but 3 deg in yaw puts base_link, 0.2 m behind, 1 cm
    across the lever: the scan frame's covariance given for base_link's (as before) is 10x
    too tight there."""
    from slam.depth_to_scan import base_covariance, base_pose, scan_frame_in_base

    at = scan_frame_in_base(
        RobotConfig(camera_x=0.2, camera_y=0.05), replace(CFG, output_frame="camera_link")
    )
    cam = np.array([1.0, 2.0, 0.7])
    cov = np.array([[1e-6, 5e-7, 0.0], [5e-7, 2e-6, 1e-6], [0.0, 1e-6, np.radians(3.0) ** 2]])
    rng = np.random.default_rng(0)
    samples = base_pose(rng.multivariate_normal(cam, cov, 20000), at)
    spread = np.cov(samples.T)
    got = base_covariance(cam, cov, at)
    np.testing.assert_allclose(got, spread, rtol=0.05, atol=2e-7)
    lever_sigma = np.hypot(*at[:2]) * np.radians(3.0)  # 1.08 cm
    assert abs(np.sqrt(np.trace(got[:2, :2]) - np.trace(cov[:2, :2])) - lever_sigma) < 1e-4
    assert np.sqrt(np.trace(got[:2, :2])) > 5 * np.sqrt(np.trace(cov[:2, :2]))
    # broadcast over poses, and a scan in base_link keeps its covariance bit for bit
    many = base_covariance(np.stack([cam, cam]), np.stack([cov, cov]), at)
    np.testing.assert_allclose(many, [got, got], atol=1e-15)
    assert np.array_equal(base_covariance(cam, cov, np.zeros(3)), cov)
