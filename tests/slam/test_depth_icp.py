"""Depth ICP (KISS-ICP on the depth cloud) behind the VO interface: a known motion recovered on
synthetic depth, the failure paths, the feature-VO fallback, and real Kinect frames."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sensors.types import CameraIntrinsics, RgbdFrame
from slam.config import VoConfig
from slam.depth_icp import DepthIcpOdometry, orthonormalised, weakest_direction_support
from slam.visual_odometry import VisualOdometry, inverse, rotation_angle, se3_exp

INTR = CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5, 1000.0)
# Planes n . p = c in the first camera's optical frame (x right, y down, z ahead): a room.
ROOM = (((0, 0, 1), 3.0), ((1, 0, 0), -1.5), ((1, 0, 0), 1.2), ((0, 1, 0), 0.8), ((0, 1, 0), -1.5))
WALL = (((0, 0, 1), 2.0),)
ICP = replace(VoConfig(), method="depth_icp", force_3dof=False)
DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "kinect"


def render_depth(
    t_w_c: np.ndarray, planes: tuple = ROOM, noise_m: float = 0.0, seed: int = 0
) -> np.ndarray:
    """Depth [m] of the nearest plane along every pixel's ray from camera pose ``t_w_c``; 0 where
    no plane is hit; ``noise_m`` times z^2 Gaussian noise (Kinect-like)."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width]
    ray = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1)
    ray_w, origin = ray @ t_w_c[:3, :3].T, t_w_c[:3, 3]
    z = np.full(u.shape, np.inf)
    for n, c in planes:
        n = np.asarray(n, float)
        den = ray_w @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (c - origin @ n) / den
        z = np.minimum(z, np.where((s > 0) & np.isfinite(s), s, np.inf))  # z = s: ray_z is 1
    z = np.where(np.isfinite(z), z, 0.0)
    z += noise_m * z**2 * np.random.default_rng(seed).standard_normal(z.shape) * (z > 0)
    return z.astype(np.float32)


def frame(depth: np.ndarray, stamp: int = 0) -> RgbdFrame:
    """A frame without any colour texture (black): only the depth has something to show."""
    return RgbdFrame(stamp, np.zeros((INTR.height, INTR.width, 3), np.uint8), depth, INTR)


MOTIONS = [se3_exp(np.array([0.0, 0.01 * i, 0.0, 0.01 * i, 0.0, 0.02 * i])) for i in range(6)]


def test_known_motion_on_a_synthetic_room_is_recovered_within_a_millimetre() -> None:
    vo = VisualOdometry(INTR, ICP)
    results = [vo.process(frame(render_depth(t))) for t in MOTIONS]
    assert results[0].reason == "no_previous_frame" and not results[0].success
    for i, res in enumerate(results[1:], start=1):
        truth = inverse(MOTIONS[i - 1]) @ MOTIONS[i]
        assert res.success, (i, res.reason)
        assert np.linalg.norm(res.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.002, i
        assert math.degrees(rotation_angle(inverse(truth) @ res.T_prev_curr)) < 0.2, i
        assert res.covariance.shape == (6, 6) and np.all(np.isfinite(res.covariance))
    np.testing.assert_allclose(vo.T_odom_cam, MOTIONS[-1], atol=0.005)


def test_kinect_like_noise_leaves_the_motion_within_a_centimetre() -> None:
    vo = VisualOdometry(INTR, ICP)
    results = [
        vo.process(frame(render_depth(t, noise_m=0.0028, seed=i)))
        for i, t in enumerate(MOTIONS[:3])
    ]
    for i, res in enumerate(results[1:], start=1):
        truth = inverse(MOTIONS[i - 1]) @ MOTIONS[i]
        assert res.success, (i, res.reason)
        assert np.linalg.norm(res.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.01, i


def test_planar_mode_gives_the_base_link_motion_and_a_3x3_covariance() -> None:
    vo = VisualOdometry(INTR, replace(ICP, force_3dof=True))
    vo.process(frame(render_depth(MOTIONS[0])))
    res = vo.process(frame(render_depth(MOTIONS[1])))
    assert res.success and res.delta_base is not None
    assert res.covariance.shape == (3, 3) and np.all(np.isfinite(res.covariance))


def test_empty_depth_fails_with_too_few_points_and_an_identity_pose() -> None:
    vo = VisualOdometry(INTR, ICP)
    vo.process(frame(render_depth(MOTIONS[0])))
    res = vo.process(frame(np.zeros((INTR.height, INTR.width), np.float32)))
    assert not res.success and res.reason == "too_few_points"
    np.testing.assert_array_equal(res.T_prev_curr, np.eye(4))
    assert np.all(np.isinf(res.covariance))


def test_a_blank_wall_is_degenerate_not_a_silent_pose() -> None:
    vo = VisualOdometry(INTR, ICP)
    assert vo.process(frame(render_depth(MOTIONS[0], WALL))).reason == "no_previous_frame"
    res = vo.process(frame(render_depth(MOTIONS[1], WALL)))
    assert not res.success and res.reason == "degenerate"
    np.testing.assert_array_equal(res.T_prev_curr, np.eye(4))


def test_wall_and_floor_leave_the_slide_along_the_wall_without_support() -> None:
    wall_floor = np.array([[0.0, 0.0, -1.0]] * 50 + [[0.0, -1.0, 0.0]] * 50)
    corner = np.vstack([wall_floor, [[-1.0, 0.0, 0.0]] * 5])
    assert weakest_direction_support(wall_floor) == 0.0
    assert weakest_direction_support(corner) == pytest.approx(5 / 105)


def test_orthonormalised_projects_a_drifted_rotation_onto_so3() -> None:
    t = np.eye(4)
    for i in range(500):  # round-off of a long chain of motions
        t = t @ se3_exp(np.array([0.01, -0.02, 0.03, 0.1, 0.0, 0.05]) * (1 + i % 7))
    t[:3, :3] *= 1 + 1e-9
    o = orthonormalised(t)
    np.testing.assert_allclose(o[:3, :3] @ o[:3, :3].T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(o[:3, 3], t[:3, 3], atol=0)
    np.testing.assert_allclose(o[:3, :3], t[:3, :3], atol=1e-8)


def test_feature_vo_falls_back_to_depth_icp_on_a_textureless_room_and_counts_it() -> None:
    cfg = replace(VoConfig(), force_3dof=False, fallback="depth_icp")
    vo = VisualOdometry(INTR, cfg)
    plain = VisualOdometry(INTR, replace(cfg, fallback="none"))
    results, plain_results = [], []
    for t in MOTIONS[:4]:
        f = frame(render_depth(t))
        results.append(vo.process(f))
        plain_results.append(plain.process(f))
    assert all(not r.success for r in plain_results)  # black images: no features at all
    for i, res in enumerate(results[1:], start=1):
        truth = inverse(MOTIONS[i - 1]) @ MOTIONS[i]
        assert res.success and res.fallback, (i, res.reason)
        assert np.linalg.norm(res.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.002, i
    assert vo.stats == {"fallback_used": 3, "fallback_failed": 0}
    np.testing.assert_allclose(vo.T_odom_cam, MOTIONS[3], atol=0.005)


def test_an_unknown_vo_method_is_a_config_error() -> None:
    from sensors.types import ConfigError

    with pytest.raises(ConfigError, match="vo.method: 'nope' is not implemented"):
        VisualOdometry(INTR, replace(VoConfig(), method="nope"))  # type: ignore[arg-type]


@pytest.mark.skipif(not (DATA / "odometry.log").exists(), reason="../shared/data absent")
def test_open3d_kinect_sequence_agrees_with_its_odometry_log_within_a_centimetre() -> None:
    import cv2

    lines = (DATA / "odometry.log").read_text().split("\n")
    poses = [
        np.loadtxt(lines[j + 1 : j + 5]) for j in range(0, len(lines) - 4, 5) if lines[j].strip()
    ]
    vo = VisualOdometry(INTR, ICP)
    for i in range(len(poses)):
        rgb = cv2.cvtColor(cv2.imread(str(DATA / "color" / f"{i:05d}.jpg")), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(DATA / "depth" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED)
        res = vo.process(RgbdFrame(i, rgb, depth.astype(np.float32) / 1000.0, INTR))
        if i:
            ref = inverse(poses[i - 1]) @ poses[i]
            assert res.success, (i, res.reason)
            assert np.linalg.norm(res.T_prev_curr[:3, 3] - ref[:3, 3]) < 0.01, i


@pytest.mark.skipif(
    not (DATA / "tum_fr3_cabinet_keyframes").exists(), reason="../shared/data absent"
)
def test_tum_cabinet_fallback_keeps_the_feature_vo_score() -> None:
    """The wide-baseline keyframes (0.15 m apart) are where ICP is weakest: the fallback, taken
    only when ORB fails, must not lower ORB's share of pairs under 5 cm."""
    from scipy.spatial.transform import Rotation

    from sensors.source import open_source

    folder = DATA / "tum_fr3_cabinet_keyframes"
    frames = list(open_source(folder).frames())
    d = np.loadtxt(folder / "truth_cam_poses.txt")  # TUM: t x y z qx qy qz qw
    truth = np.tile(np.eye(4), (len(d), 1, 1))
    truth[:, :3, :3] = Rotation.from_quat(d[:, 4:8]).as_matrix()
    truth[:, :3, 3] = d[:, 1:4]
    wide = replace(VoConfig(), force_3dof=False, max_translation=0.5, max_rotation=math.radians(45))
    scores = []
    for fallback in ("none", "depth_icp"):
        vo = VisualOdometry(frames[0].intrinsics, replace(wide, fallback=fallback), keyframes=False)
        err = []
        for i, f in enumerate(frames):
            res = vo.process(f)
            if i:
                t = inverse(truth[i - 1]) @ truth[i]
                ok = res.success and np.linalg.norm(res.T_prev_curr[:3, 3] - t[:3, 3]) < 0.05
                err.append(ok)
        scores.append(float(np.mean(err)))
    assert scores[1] >= scores[0] >= 0.85


def test_an_image_smaller_than_three_check_blocks_has_too_few_points_not_an_error():
    intr = CameraIntrinsics(4, 3, 5.0, 5.0, 2.0, 1.5)
    odo = DepthIcpOdometry(intr, VoConfig())
    frame = RgbdFrame(0, np.zeros((3, 4, 3), np.uint8), np.ones((3, 4), np.float32), intr)
    res = odo.process(frame)
    assert not res.success and res.reason == "too_few_points"
