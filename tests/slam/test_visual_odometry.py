"""Visual odometry: known simulated motions, failure reasons, planar projection, real TUM pairs."""

from __future__ import annotations

import math
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.sim.render import KinectRenderer, camera_pose_in_world
from sensors.sim.world import world_from_dict
from sensors.types import RgbdFrame
from slam.config import VoConfig
from slam.visual_odometry import (
    KINECT_BASELINE,
    Features,
    VisualOdometry,
    VoResult,
    VoTuning,
    _bucket,
    _residuals,
    _whitened,
    base_from_optical,
    camera_matrix,
    depth_mask,
    estimate_motion,
    extract_features,
    hamming_knn,
    inverse,
    kabsch,
    knn_candidates,
    rigid_ransac,
    rotation_angle,
    se3_exp,
)
from tests.sim_worlds import NOISELESS

CAMERA = CameraConfig()
ROBOT = RobotConfig()
VO6 = VoConfig(force_3dof=False)
CABINET = (
    Path(__file__).resolve().parents[3]
    / "shared"
    / "data"
    / "kinect"
    / ("tum_fr3_cabinet_keyframes")
)
FAILURE_REASONS = {
    "too_few_features",
    "too_few_matches",
    "pnp_failed",
    "too_few_inliers",
    "implausible_motion",
}


def room(texture: str, furniture_texture: str) -> dict:
    """A 5 m x 4 m room around the origin with two boxes in view of a robot looking along +x."""
    walls = [
        {"from": [-1.0, -2.0], "to": [3.0, -2.0], "texture": texture},
        {"from": [3.0, -2.0], "to": [3.0, 2.0], "texture": texture},
        {"from": [3.0, 2.0], "to": [-1.0, 2.0], "texture": texture},
        {"from": [-1.0, 2.0], "to": [-1.0, -2.0], "texture": texture},
    ]
    boxes = [
        {"name": "a", "center": [2.0, 0.8], "size": [0.5, 0.5, 0.9], "texture": furniture_texture},
        {"name": "b", "center": [1.8, -0.9], "size": [0.4, 0.6, 1.2], "texture": furniture_texture},
    ]
    return {
        "name": "vo-test",
        "walls": walls,
        "furniture": boxes,
        "start": [0.0, 0.0, 0.0],
        "route": [[1.0, 0.0]],
        "floor": {"texture": texture, "scale": 1.0},
        "ceiling": {"texture": texture, "scale": 1.0},
    }


@lru_cache(maxsize=4)
def renderer(texture: str = "astronaut", furniture: str = "coffee") -> KinectRenderer:
    world = world_from_dict(room(texture, furniture))
    return KinectRenderer(world, CAMERA, ROBOT, NOISELESS, backend="raster")


def frame(r: KinectRenderer, pose: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    return r.render(*pose, np.random.default_rng(0))


def true_motion(a: tuple[float, float, float], b: tuple[float, float, float]) -> np.ndarray:
    ta, tb = np.eye(4), np.eye(4)
    ta[:3, :3], ta[:3, 3] = camera_pose_in_world(*a, ROBOT)
    tb[:3, :3], tb[:3, 3] = camera_pose_in_world(*b, ROBOT)
    return inverse(ta) @ tb


def assert_pair_motions(poses: list, results: list[VoResult], max_m: float, max_deg: float) -> None:
    """Each result's T_prev_curr against the true motion between consecutive ``poses``."""
    for a, b, res in zip(poses[:-1], poses[1:], results, strict=True):
        truth = true_motion(a, b)
        assert np.linalg.norm(res.T_prev_curr[:3, 3] - truth[:3, 3]) < max_m
        assert math.degrees(rotation_angle(inverse(truth) @ res.T_prev_curr)) < max_deg


def count_calls(monkeypatch: pytest.MonkeyPatch, name: str) -> list[int]:
    """Calls of ``slam.visual_odometry.<name>`` from now on (one entry each)."""
    import slam.visual_odometry as vo_module

    calls: list[int] = []
    real = getattr(vo_module, name)

    def counted(*args: object, **kw: object) -> object:
        calls.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(vo_module, name, counted)
    return calls


K = camera_matrix(renderer().intrinsics)
START = (0.0, 0.0, 0.0)
MOVED = (0.06, 0.01, math.radians(3.0))


def test_known_simulated_motion_is_recovered_within_1cm_and_half_a_degree() -> None:
    r = renderer()
    res = estimate_motion(*frame(r, START), *frame(r, MOVED), K, VO6)
    assert res.success, res.reason
    truth = true_motion(START, MOVED)
    assert np.linalg.norm(res.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(inverse(truth) @ res.T_prev_curr)) < 0.5
    assert res.inliers >= VO6.min_inliers
    assert res.reason == "ok"


def test_covariance_is_symmetric_positive_definite_and_small_for_a_good_estimate() -> None:
    r = renderer()
    res = estimate_motion(*frame(r, START), *frame(r, MOVED), K, VO6)
    cov = res.covariance
    assert cov.shape == (6, 6)
    assert np.allclose(cov, cov.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.all(np.sqrt(np.diag(cov))[:3] < 0.01)  # [m]


def test_identical_frames_give_identity() -> None:
    r = renderer()
    rgb, depth = frame(r, START)
    res = estimate_motion(rgb, depth, rgb, depth, K, VO6)
    assert res.success
    assert np.linalg.norm(res.T_prev_curr[:3, 3]) < 1e-3
    assert math.degrees(rotation_angle(res.T_prev_curr)) < 0.05


def test_textureless_scene_fails_with_a_reason_and_no_pose() -> None:
    r = renderer("plaster", "plaster")
    (_, d0), (_, d1) = frame(r, START), frame(r, MOVED)
    flat = np.full((CAMERA.height, CAMERA.width, 3), 128, np.uint8)  # geometry but no texture
    res = estimate_motion(flat, d0, flat, d1, K, VO6)
    assert not res.success
    assert res.reason in FAILURE_REASONS
    assert res.reason == "too_few_features"
    assert np.array_equal(res.T_prev_curr, np.eye(4))
    assert np.all(np.isinf(res.covariance))


def test_faint_procedural_plaster_is_tracked_correctly_or_rejected_never_garbage() -> None:
    world = world_from_dict(room("plaster", "plaster"))
    r = KinectRenderer(world, CAMERA, ROBOT, SimConfig(), backend="raster")  # with sensor noise
    a = r.render(*START, np.random.default_rng(0))
    b = r.render(*MOVED, np.random.default_rng(1))
    res = estimate_motion(*a, *b, K, VO6)
    if res.success:
        assert np.linalg.norm(res.T_prev_curr[:3, 3] - true_motion(START, MOVED)[:3, 3]) < 0.01
    else:
        assert res.reason in FAILURE_REASONS


def test_a_jump_beyond_max_translation_is_rejected_as_implausible() -> None:
    r = renderer()
    res = estimate_motion(*frame(r, START), *frame(r, MOVED), K, replace(VO6, max_translation=0.02))
    assert not res.success and res.reason == "implausible_motion"


def test_planar_mode_gives_base_link_dx_dy_dyaw() -> None:
    r = renderer()
    res = estimate_motion(
        *frame(r, START),
        *frame(r, MOVED),
        K,
        VoConfig(force_3dof=True),
        t_base_opt=base_from_optical(ROBOT),
    )
    assert res.success and res.delta_base is not None
    d = res.delta_base
    assert d.x == pytest.approx(MOVED[0], abs=0.01)
    assert d.y == pytest.approx(MOVED[1], abs=0.01)
    assert math.degrees(d.yaw) == pytest.approx(math.degrees(MOVED[2]), abs=0.5)
    assert res.covariance.shape == (3, 3)
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_stateful_planar_odometry_chains_a_short_drive() -> None:
    r = renderer()
    vo = VisualOdometry(r.intrinsics, VoConfig(), ROBOT)
    poses = [(0.02 * i, 0.0, math.radians(0.5 * i)) for i in range(6)]
    results = [vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    assert results[0].reason == "no_previous_frame" and not results[0].success
    assert all(res.success for res in results[1:])
    total = np.zeros(3)
    for res in results[1:]:
        d = res.delta_base
        assert d is not None
        c, s = math.cos(total[2]), math.sin(total[2])
        total += [c * d.x - s * d.y, s * d.x + c * d.y, d.yaw]
    end = np.array(poses[-1])
    assert np.hypot(*(total[:2] - end[:2])) < 0.01
    assert abs(math.degrees(total[2] - end[2])) < 0.5


def test_a_keyframe_is_taken_when_the_inliers_drop_below_keyframe_inliers() -> None:
    r = renderer()
    poses = [(0.01 * i, 0.0, 0.0) for i in range(3)]
    for keyframe_inliers, renewed in ((0, False), (10**6, True)):
        vo = VisualOdometry(r.intrinsics, VO6, tuning=VoTuning(keyframe_inliers=keyframe_inliers))
        results = [
            vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)
        ]
        assert all(res.success for res in results[1:])
        assert vo._kf is not None
        # Renewed: the last frame is the keyframe itself; kept: it sits 1 cm ahead of it.
        assert np.allclose(vo._kf.T_kf_last, np.eye(4)) == renewed


def test_the_last_pose_seeds_a_slow_drive_in_place_of_ransac(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ransac = count_calls(monkeypatch, "initial_motions")
    r = renderer()
    vo = VisualOdometry(r.intrinsics, VO6)
    poses = [(0.015 * i, 0.0, math.radians(0.4 * i)) for i in range(6)]
    results = [vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    # Frame 1 runs RANSAC (no prior yet); its estimate shows the prior holds: seeded from then.
    assert results[1].success and not results[1].prior
    assert all(res.success and res.prior for res in results[2:])
    assert len(ransac) == 1
    assert_pair_motions(poses[1:], results[2:], 0.005, 0.3)
    # Off, every frame runs RANSAC, to the same motions.
    ransac.clear()
    off = VisualOdometry(r.intrinsics, VO6, tuning=VoTuning(prior_seed=False))
    plain = [off.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    assert len(ransac) == 5 and not any(res.prior for res in plain)
    for a, b in zip(results[2:], plain[2:], strict=True):
        np.testing.assert_allclose(a.T_prev_curr, b.T_prev_curr, atol=1e-3)


def test_a_wrong_seed_falls_back_to_ransac_and_finds_the_right_motion() -> None:
    r = renderer()
    vo = VisualOdometry(r.intrinsics, VO6)
    poses = [START, (0.01, 0.0, 0.0), (0.02, 0.0, 0.0), (0.12, 0.03, math.radians(6.0))]
    results = [vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    assert results[2].prior  # the slow start set the seed up ...
    jump = results[3]  # ... and the jump (~60 px) is not where it predicts: RANSAC
    assert jump.success and not jump.prior
    truth = true_motion(poses[2], poses[3])
    assert np.linalg.norm(jump.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(inverse(truth) @ jump.T_prev_curr)) < 0.5


def test_a_seeded_estimate_that_fails_its_acceptance_tests_goes_to_ransac(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The seed's refinement had the inliers, but the second search or a sanity test rejects
    it: RANSAC still decides the frame instead of the frame being lost."""
    import slam.visual_odometry as vo_module

    verified = vo_module._verified

    def reject_seeded(*args: object, prior: bool = False, **kw: object) -> VoResult:
        res = verified(*args, prior=prior, **kw)  # type: ignore[arg-type]
        return replace(res, success=False, reason="implausible_motion") if prior else res

    monkeypatch.setattr(vo_module, "_verified", reject_seeded)
    ransac = count_calls(monkeypatch, "initial_motions")
    r = renderer()
    vo = VisualOdometry(r.intrinsics, VO6)
    poses = [(0.015 * i, 0.0, math.radians(0.4 * i)) for i in range(4)]
    results = [vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    assert all(res.success and not res.prior for res in results[1:])
    assert len(ransac) == 3
    assert_pair_motions(poses, results[1:], 0.005, 0.3)


PRIOR = VoTuning(prior_radius_px=15.0)  # the window search around the pose prior is off by default


def test_pose_prior_tracks_a_slow_drive_with_window_search_only() -> None:
    r = renderer()
    vo = VisualOdometry(r.intrinsics, VO6, tuning=PRIOR)
    poses = [(0.015 * i, 0.0, math.radians(0.4 * i)) for i in range(6)]
    results = [vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    # Frame 1 is matched globally (no prior yet); its estimate shows the prior would hold.
    assert results[1].success and not results[1].prior
    assert all(res.success and res.prior for res in results[2:])
    assert_pair_motions(poses[1:], results[2:], 0.005, 0.3)


def test_a_wrong_pose_prior_falls_back_to_global_matching_and_finds_the_right_motion() -> None:
    r = renderer()
    vo = VisualOdometry(r.intrinsics, VO6, tuning=PRIOR)
    poses = [START, (0.01, 0.0, 0.0), (0.02, 0.0, 0.0), (0.12, 0.03, math.radians(6.0))]
    results = [vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    assert results[2].prior  # the slow start set the prior up ...
    jump = results[3]  # ... and the jump (~60 px) leaves every window: global matching
    assert jump.success and not jump.prior
    truth = true_motion(poses[2], poses[3])
    assert np.linalg.norm(jump.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(inverse(truth) @ jump.T_prev_curr)) < 0.5


def test_motion_from_prior_declines_a_prior_that_misses_the_windows() -> None:
    from slam.visual_odometry import motion_from_prior

    r = renderer()
    (rgb0, d0), (rgb1, d1) = frame(r, START), frame(r, MOVED)
    tuning = PRIOR
    a = extract_features(rgb0, d0, K, VO6, tuning)
    b = extract_features(rgb1, d1, K, VO6, tuning)
    good = motion_from_prior(a, b, inverse(true_motion(START, MOVED)), K, VO6, tuning)
    assert good is not None and good.success
    truth = true_motion(START, MOVED)
    assert np.linalg.norm(good.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.01
    assert motion_from_prior(a, b, np.eye(4), K, VO6, tuning) is None  # 3 deg + 6 cm off


FLOW = replace(VO6, cor_type="optical_flow")


def test_optical_flow_tracks_a_slow_drive_with_orb_only_on_the_keyframe(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls = count_calls(monkeypatch, "extract_features")
    r = renderer()
    vo = VisualOdometry(r.intrinsics, FLOW)
    poses = [(0.015 * i, 0.0, math.radians(0.4 * i)) for i in range(6)]  # 7.5 cm: one keyframe
    results = [vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses)]
    assert len(calls) == 1  # the first frame, the keyframe: the others are tracked by flow
    assert all(res.success and res.prior for res in results[1:])
    # ORB matching: 2.6-4.6 mm, flow 2.2-5.0 mm on these frames
    assert_pair_motions(poses, results[1:], 0.006, 0.3)
    assert all(res.inlier_ratio > FLOW.keyframe_thr for res in results[1:])


def test_optical_flow_that_loses_its_points_falls_back_to_global_matching() -> None:
    r = renderer()
    # Lucas-Kanade on the full-resolution image alone follows a few pixels of motion: the jump
    # (~60 px) loses the tracks, and the frame is matched by ORB against the keyframe instead.
    vo = VisualOdometry(r.intrinsics, replace(FLOW, cor_flow_max_level=0))
    poses = [
        START,
        (0.005, 0.0, 0.0),
        (0.12, 0.03, math.radians(6.0)),
        (0.125, 0.03, math.radians(6.0)),
    ]
    results = [
        vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics)) for i, p in enumerate(poses[:3])
    ]
    assert results[1].success and results[1].prior
    jump = results[2]
    assert jump.success and not jump.prior
    truth = true_motion(poses[1], poses[2])
    assert np.linalg.norm(jump.T_prev_curr[:3, 3] - truth[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(inverse(truth) @ jump.T_prev_curr)) < 0.5
    assert vo._kf is not None and np.allclose(vo._kf.T_kf_last, np.eye(4))  # a new keyframe
    after = vo.process(RgbdFrame(3, *frame(r, poses[3]), r.intrinsics))
    assert after.success and after.prior  # ... whose points are tracked again


def test_optical_flow_after_a_keyframe_without_depth_fails_cleanly_and_recovers() -> None:
    # A keyframe with no point in depth range (facing a wall nearer than min_depth) leaves no
    # point to track: the next frame must fail with a reason (it crashed the live front end:
    # OpenCV's Lucas-Kanade returns None for no points), and tracking must come back.
    r = renderer()
    vo = VisualOdometry(r.intrinsics, FLOW)
    rgb, depth = frame(r, START)
    vo.process(RgbdFrame(0, rgb, np.zeros_like(depth), r.intrinsics))  # no depth at all
    lost = vo.process(RgbdFrame(1, *frame(r, (0.005, 0.0, 0.0)), r.intrinsics))
    assert not lost.success and lost.reason in FAILURE_REASONS
    back = [
        vo.process(RgbdFrame(2 + i, *frame(r, (0.01 + 0.005 * i, 0.0, 0.0)), r.intrinsics))
        for i in range(2)
    ]
    assert back[-1].success and back[-1].prior


def _tum_poses(path: Path) -> np.ndarray:
    d = np.loadtxt(path)
    out = np.tile(np.eye(4), (len(d), 1, 1))
    for i, (x, y, z, w) in enumerate(d[:, 4:8]):
        out[i, :3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    out[:, :3, 3] = d[:, 1:4]
    return out


@pytest.mark.skipif(not CABINET.exists(), reason="shared TUM data absent")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_real_cabinet_keyframes_reach_the_measured_success_rate_for_any_ransac_seed(
    seed: int,
) -> None:
    from sensors.source import open_source

    frames = list(open_source(CABINET).frames())
    gt = _tum_poses(CABINET / "truth_cam_poses.txt")
    cfg = replace(VO6, max_translation=0.5, max_rotation=math.radians(45), pnp_reproj_error=3.0)
    tuning = VoTuning(ransac_seed=seed)
    k = camera_matrix(frames[0].intrinsics)
    errors = []
    for i in range(len(frames) - 1):
        a, b = frames[i], frames[i + 1]
        res: VoResult = estimate_motion(a.rgb, a.depth_m, b.rgb, b.depth_m, k, cfg, tuning)
        truth = inverse(gt[i]) @ gt[i + 1]
        errors.append(
            np.linalg.norm(res.T_prev_curr[:3, 3] - truth[:3, 3]) if res.success else math.inf
        )
    errors_a = np.array(errors)
    # Measured over seeds 1-10: 100 % for every seed, median 1.28 cm (max 1.30) and 96 % /
    # 1.25 cm for seed 0 (bench/sweep_vo.py); pinned at the 90 % and 1.5 cm targets.
    assert np.mean(errors_a < 0.05) >= 0.9
    assert np.median(errors_a) < 0.015


# --------------------------------------------------------------------------------------------
# Kernels of the fast path, cross-checked against slow references
# --------------------------------------------------------------------------------------------


def test_residual_jacobian_matches_finite_differences_of_a_left_perturbation() -> None:
    rng = np.random.default_rng(3)
    p = rng.uniform([-1.0, -0.8, 1.0], [1.0, 0.8, 4.0], (12, 3))
    t = se3_exp(np.array([0.02, -0.05, 0.01, 0.1, -0.03, 0.05]))
    obs = np.column_stack(
        [rng.uniform(0, 640, 12), rng.uniform(0, 480, 12), rng.uniform(0, 640, 12)]
    )
    has_z = np.arange(12) % 3 != 0  # some observations without depth: no u_r residual
    bf = K[0, 0] * KINECT_BASELINE
    _, jac = _residuals(t, p, obs, has_z, K, bf)
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        r_plus, _ = _residuals(se3_exp(d) @ t, p, obs, has_z, K, bf)
        r_minus, _ = _residuals(se3_exp(-d) @ t, p, obs, has_z, K, bf)
        np.testing.assert_allclose(jac[:, :, i], (r_plus - r_minus) / (2 * eps), atol=1e-4)


def test_fast_whitened_residuals_equal_the_reference_kernel_divided_by_sigma() -> None:
    rng = np.random.default_rng(7)
    n = 15
    p = rng.uniform([-1.0, -0.8, 1.0], [1.0, 0.8, 4.0], (n, 3))
    t = se3_exp(np.array([0.02, -0.05, 0.01, 0.1, -0.03, 0.05]))
    obs = np.column_stack([rng.uniform(0, 640, n), rng.uniform(0, 480, n), rng.uniform(0, 640, n)])
    has_z = np.arange(n) % 4 != 0
    sig = rng.uniform(0.5, 3.0, (n, 3))
    bf = K[0, 0] * KINECT_BASELINE
    r_ref, j_ref = _residuals(t, p, obs, has_z, K, bf)
    iw = (1.0 / sig).T * np.array([1.0, 1.0, 0.0])[:, None]
    iw[2, has_z] = 1.0 / sig[has_z, 2]
    r, j = _whitened(t, p, obs.T, iw, K, bf)
    np.testing.assert_allclose(r, (r_ref / sig).T, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(
        j, (j_ref / sig[:, :, None]).transpose(2, 1, 0), rtol=1e-12, atol=1e-9
    )


def test_kabsch_recovers_a_known_motion_per_batch_and_ignores_zero_weight_outliers() -> None:
    rng = np.random.default_rng(8)
    truth = [se3_exp(rng.normal(0, 0.3, 6)) for _ in range(4)]
    p = rng.uniform(-2, 2, (4, 10, 3))
    q = np.stack([pi @ ti[:3, :3].T + ti[:3, 3] for pi, ti in zip(p, truth, strict=True)])
    q[:, :3] += rng.normal(0, 1.0, (4, 3, 3))  # three gross outliers per batch ...
    w = np.ones((4, 10))
    w[:, :3] = 0.0  # ... weighted out
    r, t = kabsch(p, q, w)
    for i, ti in enumerate(truth):
        np.testing.assert_allclose(r[i], ti[:3, :3], atol=1e-9)
        np.testing.assert_allclose(t[i], ti[:3, 3], atol=1e-9)
        assert np.linalg.det(r[i]) == pytest.approx(1.0)


def _rigid_scene(seed: int, n: int, outliers: float) -> tuple[np.ndarray, ...]:
    """Matches of a known motion: p (prev 3D), q (curr 3D), uv (curr pixels), scale, truth."""
    rng = np.random.default_rng(seed)
    truth = se3_exp(np.array([0.05, -0.1, 0.03, 0.12, 0.02, -0.08]))
    p = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1, 1, n), rng.uniform(1, 4, n)])
    q = p @ truth[:3, :3].T + truth[:3, 3]
    bad = rng.random(n) < outliers
    q[bad] = np.column_stack(
        [rng.uniform(-1.5, 1.5, n), rng.uniform(-1, 1, n), rng.uniform(1, 4, n)]
    )[bad]
    q += rng.normal(0, 0.003, q.shape)
    uv = q[:, :2] / q[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    uv += rng.normal(0, 0.5, uv.shape)
    return p, q, uv, np.ones(n), truth, bad


@pytest.mark.parametrize("seed", range(5))
def test_rigid_ransac_finds_the_motion_among_60_percent_outliers_for_every_seed(
    seed: int,
) -> None:
    p, q, uv, scale, truth, bad = _rigid_scene(11, 80, 0.6)
    hyps = rigid_ransac(p, q, uv, scale, K, 3.0, VoTuning(ransac_seed=seed))
    assert hyps
    t_cp, inl = hyps[0]
    assert np.linalg.norm(t_cp[:3, 3] - truth[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(inverse(truth) @ t_cp)) < 0.5
    assert np.mean(inl[~bad]) > 0.9 and np.mean(inl[bad]) < 0.1


def test_rigid_ransac_is_repeatable_for_one_seed_and_empty_for_too_few_matches() -> None:
    p, q, uv, scale, _, _ = _rigid_scene(12, 50, 0.3)
    a = rigid_ransac(p, q, uv, scale, K, 3.0, VoTuning(ransac_seed=3))
    b = rigid_ransac(p, q, uv, scale, K, 3.0, VoTuning(ransac_seed=3))
    assert len(a) == len(b) and all(np.array_equal(x[0], y[0]) for x, y in zip(a, b, strict=True))
    assert rigid_ransac(p[:2], q[:2], uv[:2], scale[:2], K, 3.0, VoTuning()) == []


def test_level_window_compares_only_nearby_pyramid_levels_and_covers_all_when_wide() -> None:
    rng = np.random.default_rng(9)
    prev = _features(rng.integers(0, 256, (30, 32), dtype=np.uint8))
    curr = _features(rng.integers(0, 256, (40, 32), dtype=np.uint8))
    prev = replace(prev, octave=np.sort(rng.integers(0, 6, 30)))
    curr = replace(curr, octave=np.sort(rng.integers(0, 6, 40)))
    idx, dist = knn_candidates(prev, curr, 3, level_window=1)
    ref = _hamming_reference(prev.desc, curr.desc).astype(float)
    ref[np.abs(prev.octave[:, None] - curr.octave[None]) > 1] = np.inf
    ok = idx >= 0
    assert np.all(np.abs(prev.octave[:, None] - curr.octave[np.where(ok, idx, 0)])[ok] <= 1)
    np.testing.assert_array_equal(dist, np.sort(ref, axis=1)[:, :3])
    full, _ = knn_candidates(prev, curr, 3)
    wide, _ = knn_candidates(prev, curr, 3, level_window=5)
    np.testing.assert_array_equal(full, wide)


def _hamming_reference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)


def _features(desc: np.ndarray) -> Features:
    n = len(desc)
    return Features(np.zeros((n, 2)), np.zeros(n, int), desc, np.ones((n, 3)))


def test_knn_candidates_are_the_k_nearest_hamming_neighbours_best_first() -> None:
    rng = np.random.default_rng(4)
    prev = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    curr = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    curr[7] = prev[0]  # an exact match
    idx, dist = knn_candidates(_features(prev), _features(curr), 3)
    ref = _hamming_reference(prev, curr)
    assert idx[0, 0] == 7 and dist[0, 0] == 0
    np.testing.assert_array_equal(dist, np.sort(ref, axis=1)[:, :3])
    np.testing.assert_array_equal(dist, np.take_along_axis(ref, idx, axis=1))


def test_hamming_knn_equals_a_brute_force_bit_count_including_ties() -> None:
    rng = np.random.default_rng(6)
    a = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (90, 32), dtype=np.uint8)
    b[10] = b[50] = b[70] = a[3]  # a three-way tie at distance 0
    b[20] = b[21] = a[4] ^ 1  # a two-way tie 32 bits away (bit 0 of every byte flipped)
    dist, idx = hamming_knn(a, b, 3)
    full = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(2)  # (300, 90) bits
    ref_idx = np.argsort(full, axis=1, kind="stable")[:, :3]  # ties: the lower index first
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_array_equal(dist, np.take_along_axis(full, ref_idx, axis=1))
    assert idx[3].tolist() == [10, 50, 70] and idx[4, :2].tolist() == [20, 21]


def test_knn_candidates_pad_with_minus_one_and_inf_when_the_current_frame_has_fewer() -> None:
    rng = np.random.default_rng(5)
    prev = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    curr = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    idx, dist = knn_candidates(_features(prev), _features(curr), 3)
    assert idx.shape == (4, 3)
    assert np.all(idx[:, 2] == -1) and np.all(np.isinf(dist[:, 2]))
    assert np.all(np.isfinite(dist[:, :2])) and set(idx[0, :2]) == {0, 1}


def test_bucketing_takes_the_best_response_of_every_cell_before_any_second_best() -> None:
    tuning = VoTuning(grid_rows=1, grid_cols=2)
    # Cell 0 (left half) holds three strong keypoints, cell 1 (right half) two weak ones.
    uv = np.array([[10.0, 5.0], [20.0, 5.0], [30.0, 5.0], [70.0, 5.0], [80.0, 5.0]])
    response = np.array([0.9, 0.8, 0.7, 0.2, 0.1])
    keep = _bucket(uv, response, (10, 100), 3, tuning)
    assert sorted(keep.tolist()) == [0, 1, 3]
    assert _bucket(uv, response, (10, 100), 5, tuning).tolist() == [0, 1, 2, 3, 4]


def test_depth_mask_grows_into_holes_but_not_into_out_of_range_depth() -> None:
    cfg, tuning = VoConfig(min_depth=0.5, max_depth=4.0), VoTuning(depth_margin_px=2)
    depth = np.full((5, 12), 2.0, np.float32)
    depth[:, 4:] = 0.0  # a hole (no return) right of the in-range block ...
    depth[:, 8:] = 5.0  # ... then a far wall beyond max_depth
    depth[2, 10] = 3.9  # with one in-range speck of depth noise
    depth[0, 0] = np.nan
    mask = depth_mask(depth, cfg, tuning) > 0
    assert mask[:, :6].all()  # in range, or a hole within 2 px of it (NaN too)
    assert not mask[:, 6:8].any()  # holes farther away
    assert mask.sum(0)[8:].tolist() == [0, 0, 1, 0]  # the speck itself, not grown
    plain = depth_mask(depth, cfg, replace(tuning, depth_margin_px=0)) > 0
    assert plain.sum(0).tolist() == [4] + [5] * 3 + [0] * 6 + [1, 0]


def test_features_equal_describing_only_the_kept_keypoints_in_a_second_orb_pass() -> None:
    import cv2

    r = renderer()
    rgb, depth = frame(r, START)
    # Few enough features that bucketing acts; the plain in-range depth mask; one ORB call.
    cfg, tuning = replace(VO6, max_features=300), VoTuning(depth_margin_px=0, orb_split_level=0)
    feats = extract_features(rgb, depth, K, cfg, tuning)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    orb = cv2.ORB_create(
        nfeatures=int(cfg.max_features * tuning.detect_factor),
        scaleFactor=tuning.orb_scale,
        nlevels=tuning.orb_levels,
        fastThreshold=tuning.fast_threshold,
    )
    with np.errstate(invalid="ignore"):
        mask = ((depth >= cfg.min_depth) & (depth <= cfg.max_depth)).astype(np.uint8)
    kps = orb.detect(gray, mask)
    assert len(kps) > cfg.max_features
    uv = cv2.KeyPoint_convert(kps)
    response = np.array([kp.response for kp in kps])
    kept = [kps[i] for i in _bucket(uv, response, gray.shape, cfg.max_features, tuning)]
    kps2, desc2 = orb.compute(gray, kept)
    assert len(feats) == len(kps2) == cfg.max_features
    np.testing.assert_array_equal(feats.uv, cv2.KeyPoint_convert(kps2))
    np.testing.assert_array_equal(feats.desc, desc2)
    np.testing.assert_array_equal(feats.octave, [kp.octave & 0xFF for kp in kps2])


@pytest.mark.parametrize("masked", [False, True])
def test_orb_split_over_two_threads_finds_nearly_the_keypoints_of_one_call(masked: bool) -> None:
    import cv2

    from slam.visual_odometry import _detect

    rgb, depth = frame(renderer(), START)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    mask = depth_mask(depth, VO6, VoTuning()) if masked else None
    one = _detect(gray, mask, 1200, VoTuning(orb_split_level=0))
    two = _detect(gray, mask, 1200, VoTuning(orb_split_level=2))
    # Every level present, about as many keypoints.
    np.testing.assert_array_equal(np.bincount(two[1]) > 0, np.bincount(one[1]) > 0)
    assert abs(len(two[0]) - len(one[0])) <= 0.05 * len(one[0])

    # Levels 0-3 (sizes 640x480 ... 370x278 either way) give the same keypoints and
    # descriptors; from level 4 on OpenCV's rounded level sizes differ by a pixel (308 vs 309
    # columns), so the resampled images and their keypoints do too.
    def keyed(feats: tuple[np.ndarray, ...], level: int) -> set:
        sel = feats[1] == level
        return {
            (round(u, 2), round(v, 2), d.tobytes())
            for (u, v), d in zip(feats[0][sel], feats[3][sel], strict=True)
        }

    for level in range(4):  # the per-level budgets may round one apart
        a, b = keyed(two, level), keyed(one, level)
        assert (a <= b or b <= a) and abs(len(a) - len(b)) <= 1
    if masked:
        assert (
            mask[np.rint(two[0][:, 1]).astype(int), np.rint(two[0][:, 0]).astype(int)] > 0
        ).mean() > 0.97


def test_optical_flow_tracks_stay_anchored_to_the_keyframe_out_and_back() -> None:
    # Fourteen frames out (3 cm, 2 deg) and back to the keyframe's pose within one keyframe.
    # Tracked from the keyframe's image (seeded by the last positions) the points come back to
    # their keyframe pixels and the pose to the keyframe's; chained frame-to-frame Lucas-Kanade
    # steps drifted here by 0.03 px median (0.1 px p90) and 0.3 mm.
    r = renderer()
    vo = VisualOdometry(r.intrinsics, FLOW)
    out = [(0.004 * i, 0.002 * i, math.radians(0.3 * i)) for i in range(8)]
    for i, p in enumerate(out + out[-2::-1]):
        res = vo.process(RgbdFrame(i, *frame(r, p), r.intrinsics))
        assert i == 0 or (res.success and res.prior), res.reason
    assert vo._kf is not None and vo._tracks is not None
    idx, uv = vo._tracks
    assert len(idx) > 100
    drift = np.linalg.norm(uv - vo._kf.features.uv[idx], axis=1)
    assert np.percentile(drift, 90) < 0.01
    assert np.linalg.norm(vo._kf.T_kf_last[:3, 3]) < 1e-4
    assert math.degrees(rotation_angle(vo._kf.T_kf_last)) < 0.002
