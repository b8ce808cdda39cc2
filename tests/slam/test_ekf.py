"""Planar EKF: kernels against hand-computed cases and filterpy, consistency on simulated data,
and the robot_localization behaviours (gating, differential/relative, timeouts, lagged data)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from filterpy.kalman import predict as fp_predict
from filterpy.kalman import update as fp_update
from scipy.stats import chi2

from sensors.config import RobotConfig
from sensors.types import NS_PER_S, ImuSample, Pose2
from slam.config import STATE_NAMES, EkfConfig
from slam.ekf import (
    PLANAR_INDEX,
    EkfError,
    PlanarEkf,
    PoseInput,
    TwistInput,
    angle_residual,
    fuse,
    interval_twists,
    motion_twist,
    passes_gate,
    predict,
    se2_between,
    sensor_specs,
    spanning_motion_twists,
    transition,
    update,
    wheel_twist_inputs,
    wrap_angle,
)

DT_NS = NS_PER_S // 30  # [ns] 30 Hz sensors
V, W = 0.3, 0.2  # [m/s], [rad/s] the simulated circle
SIGMA_V, SIGMA_W = 0.01, 0.02  # [m/s], [rad/s] wheel twist noise
SIGMA_VO = 0.002  # [m] and [rad] VO pose noise per frame


def mask(*names: str) -> tuple[bool, ...]:
    return tuple(n in names for n in STATE_NAMES)


def planar15(x: float, y: float, yaw: float, vx: float, vy: float, vyaw: float) -> tuple:
    """A 15-vector with the planar entries set and tiny values elsewhere."""
    out = [1e-9] * 15
    for i, v in zip(PLANAR_INDEX, (x, y, yaw, vx, vy, vyaw), strict=True):
        out[i] = v
    return tuple(out)


def cfg_with(**kw: Any) -> EkfConfig:
    return dataclasses.replace(EkfConfig(), **kw)


def pose_vo_config(**kw: Any) -> EkfConfig:
    """robot_localization's usual VO set-up: an absolute VO pose fused differentially, ungated
    (the shipped default fuses VO as a gated twist instead)."""
    base = {
        "vo0_config": mask("x", "y", "yaw"),
        "vo0_differential": True,
        "vo0_twist_rejection_threshold": 1e9,
    }
    return dataclasses.replace(EkfConfig(), **{**base, **kw})


def compose(a: Pose2, b: Pose2) -> Pose2:
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    return Pose2(a.x + c * b.x - s * b.y, a.y + s * b.x + c * b.y, wrap_angle(a.yaw + b.yaw))


def circle(n: int, seed: int = 0, dt_ns: int = DT_NS):
    """Truth on a circle, noisy wheel twists and noisy cumulative VO poses (same stamps)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt_ns
    ts = t / NS_PER_S
    yaw = W * ts
    x, y = V / W * np.sin(yaw), V / W * (1 - np.cos(yaw))
    twist_cov = np.diag([SIGMA_V**2, 1e-4, SIGMA_W**2])
    twists = [
        TwistInput(
            int(t[i]),
            V + SIGMA_V * rng.standard_normal(),
            0.01 * rng.standard_normal(),
            W + SIGMA_W * rng.standard_normal(),
            twist_cov,
        )
        for i in range(n)
    ]
    vo_cov = np.eye(3) * SIGMA_VO**2
    noise = SIGMA_VO * rng.standard_normal((n, 3))
    poses = [
        PoseInput(
            int(t[i]),
            Pose2(x[i] + noise[i, 0], y[i] + noise[i, 1], wrap_angle(yaw[i] + noise[i, 2])),
            vo_cov,
        )
        for i in range(n)
    ]
    return t, (x, y, yaw), twists, poses


# --- kernels ----------------------------------------------------------------------------------


def test_predict_moves_along_the_heading_and_adds_dt_times_q() -> None:
    x = np.array([1.0, 2.0, math.pi / 2, 1.0, 0.0, 0.5])
    q = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    xn, pn = predict(x, np.zeros((6, 6)), 0.1, q)
    np.testing.assert_allclose(xn, [1.0, 2.1, math.pi / 2 + 0.05, 1.0, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(pn, 0.1 * q, atol=1e-15)


def test_predict_covariance_matches_filterpy_with_the_jacobian() -> None:
    rng = np.random.default_rng(1)
    a = rng.standard_normal((6, 6))
    p = a @ a.T
    q = np.diag(rng.uniform(0.01, 0.1, 6))
    x = np.array([0.5, -0.2, 0.7, 0.4, 0.1, -0.3])
    _, f = transition(x, 0.05)
    _, ref = fp_predict(x, p, f, 0.05 * q)
    np.testing.assert_allclose(predict(x, p, 0.05, q)[1], ref, rtol=1e-12, atol=1e-12)


def test_jacobian_matches_finite_differences() -> None:
    x = np.array([0.5, -0.2, 0.7, 0.4, 0.1, -0.3])
    _, f = transition(x, 0.1)
    eps = 1e-7
    num = np.column_stack(
        [
            (transition(x + eps * e, 0.1)[0] - transition(x - eps * e, 0.1)[0]) / (2 * eps)
            for e in np.eye(6)
        ]
    )
    np.testing.assert_allclose(f, num, atol=1e-7)


def test_update_1d_matches_hand_computed_values() -> None:
    # K = 4 / (4 + 1) = 0.8; x = 1 + 0.8 * 2; P = (1 - 0.8)^2 4 + 0.8^2 1 = 0.8
    x, p, y, s, nis = update(
        np.array([1.0]), np.array([[4.0]]), np.array([3.0]), np.array([[1.0]]), np.array([[1.0]])
    )
    assert x[0] == pytest.approx(2.6, abs=1e-12)
    assert p[0, 0] == pytest.approx(0.8, abs=1e-12)
    assert y[0] == pytest.approx(2.0) and s[0, 0] == pytest.approx(5.0)
    assert nis == pytest.approx(4.0 / 5.0, abs=1e-12)


def test_update_2d_matches_filterpy_joseph_form() -> None:
    rng = np.random.default_rng(2)
    a = rng.standard_normal((4, 4))
    p = a @ a.T + np.eye(4)
    h = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    r = np.array([[0.5, 0.1], [0.1, 0.3]])
    x = rng.standard_normal(4)
    z = rng.standard_normal(2)
    xn, pn, _, s, nis = update(x, p, z, h, r)
    x_ref, p_ref = fp_update(x, p, z, r, h)
    np.testing.assert_allclose(xn, x_ref, atol=1e-12)
    np.testing.assert_allclose(pn, p_ref, atol=1e-12)
    y = z - h @ x
    assert nis == pytest.approx(y @ np.linalg.inv(s) @ y, rel=1e-12)


def test_rows_updated_as_if_a_state_were_known_take_none_of_its_correction() -> None:
    # States (p, r, b): p correlated with the measured r only through b, as a heading integrated
    # a gyro bias. With b known, r's innovation says nothing about p: p stays, r and b move, and
    # P is the Joseph-form covariance of that gain (symmetric, PSD).
    p = np.array([[4.0, 0.4, 0.5], [0.4, 0.2, 0.1], [0.5, 0.1, 0.125]])
    x, z, h, r = np.zeros(3), np.array([1.0]), np.array([[0.0, 1.0, 0.0]]), np.array([[0.1]])
    xn, pn, *_ = update(x, p, z, h, r, rows=np.array([0]), known=2)
    x_tb, *_ = update(x, p, z, h, r)
    assert x_tb[0] == pytest.approx(0.4 / 0.3)  # textbook: p moves with the bias's correlation
    assert xn[0] == pytest.approx(0.0, abs=1e-12)
    assert xn[1:] == pytest.approx(x_tb[1:])
    k = np.array([0.0, *(p @ h.T / (h @ p @ h.T + r))[1:, 0]])[:, None]
    ikh = np.eye(3) - k @ h
    np.testing.assert_allclose(pn, ikh @ p @ ikh.T + k @ r @ k.T, atol=1e-12)
    assert np.linalg.eigvalsh(pn).min() > 0


def test_joseph_form_keeps_covariance_symmetric_psd_under_near_exact_measurements() -> None:
    rng = np.random.default_rng(3)
    a = rng.standard_normal((6, 6)) * 100
    p = a @ a.T
    x = np.zeros(6)
    for k in range(50):
        rows = rng.choice(6, size=3, replace=False)
        h = np.eye(6)[rows]
        x, p, *_ = update(x, p, rng.standard_normal(3), h, np.eye(3) * 1e-9)
        x, p = predict(x, p, 0.01, np.eye(6) * 1e-6)
        assert np.array_equal(p, p.T), k
        assert np.linalg.eigvalsh(p).min() >= -1e-12 * np.abs(p).max(), k


def test_yaw_residual_wraps_across_pi() -> None:
    res = angle_residual(np.array([False, True]))
    r = res(np.array([1.0, -math.pi + 0.05]), np.array([0.5, math.pi - 0.05]))
    np.testing.assert_allclose(r, [0.5, 0.1], atol=1e-12)
    x = np.array([0.0, 0.0, math.pi - 0.05, 0.0, 0.0, 0.0])
    h = np.eye(6)[[2]]
    xn, _, y, _, _ = update(
        x, np.eye(6), np.array([-math.pi + 0.05]), h, np.eye(1), angle_residual(np.array([True]))
    )
    assert y[0] == pytest.approx(0.1, abs=1e-12)
    assert wrap_angle(xn[2]) == pytest.approx(-math.pi + 0.0, abs=1e-12)  # halfway, across pi


def test_gate_rejects_at_threshold_squared_in_sigma() -> None:
    assert passes_gate(3.99, 2.0)
    assert not passes_gate(4.0, 2.0)  # robot_localization: reject when sq. distance >= t^2


def test_config_vectors_map_onto_the_planar_state() -> None:
    specs = sensor_specs(EkfConfig())
    np.testing.assert_array_equal(specs["odom0"].twist_mask, [True, True, True])
    np.testing.assert_array_equal(specs["odom0"].pose_mask, [False, False, False])
    np.testing.assert_array_equal(specs["vo0"].twist_mask, [True, True, True])
    assert not specs["vo0"].differential
    specs = sensor_specs(pose_vo_config())
    np.testing.assert_array_equal(specs["vo0"].pose_mask, [True, True, True])
    assert specs["vo0"].differential
    np.testing.assert_array_equal(specs["imu0"].twist_mask, [False, False, True])
    with pytest.raises(EkfError, match="two_d_mode"):
        sensor_specs(cfg_with(two_d_mode=False, odom0_config=mask("vx", "vz")))


# --- consistency ------------------------------------------------------------------------------


def _consistency_run(
    n: int,
    rng: np.random.Generator,
    ekf: PlanarEkf,
    q: np.ndarray,
    r_twist: np.ndarray,
    r_pose: np.ndarray,
    dt: float,
):
    """Truth follows the filter's own model with process noise Q dt; yields NIS and NEES."""
    s = np.array([0.0, 0.0, 0.0, V, 0.0, W])
    nis: dict[str, list[float]] = {"twist": [], "pose": []}
    nees = []
    lq, lt, lp = (np.linalg.cholesky(m) for m in (q * dt, r_twist, r_pose))
    for k in range(n):
        if k:
            s = transition(s, dt)[0] + lq @ rng.standard_normal(6)
        stamp = k * int(dt * NS_PER_S)
        zt = s[3:] + lt @ rng.standard_normal(3)
        for res in ekf.process("odom0", TwistInput(stamp, zt[0], zt[1], zt[2], r_twist)):
            if res.reason == "":
                nis["twist"].append(res.nis)
        if k % 5 == 0:
            zp = s[:3] + lp @ rng.standard_normal(3)
            pose = PoseInput(stamp, Pose2(zp[0], zp[1], wrap_angle(zp[2])), r_pose)
            for res in ekf.process("vo0", pose):
                if res.reason == "":
                    nis["pose"].append(res.nis)
        e = s - ekf.x[:6]  # the planar state; no gyro here, so its bias state stays at its prior
        e[2] = wrap_angle(e[2])
        nees.append(float(e @ np.linalg.solve(ekf.P[:6, :6], e)))
    return nis, np.array(nees)


def _consistency_filter() -> tuple[PlanarEkf, np.ndarray, np.ndarray, np.ndarray]:
    q6 = (1e-4, 1e-4, 1e-4, 1e-3, 1e-4, 1e-3)
    r_twist = np.diag([SIGMA_V**2, 1e-4, SIGMA_W**2])
    r_pose = np.diag([0.05**2, 0.05**2, 0.03**2])
    # The first (twist) measurement sets the velocities, so their P0 is its noise.
    cfg = pose_vo_config(
        odom0_config=mask("vx", "vy", "vyaw"),
        vo0_config=mask("x", "y", "yaw"),
        vo0_differential=False,
        process_noise_covariance=planar15(*q6),
        initial_estimate_covariance=planar15(1e-9, 1e-9, 1e-9, SIGMA_V**2, 1e-4, SIGMA_W**2),
    )
    return PlanarEkf(cfg), np.diag(q6), r_twist, r_pose


def test_average_nis_of_twist_and_pose_updates_is_within_the_95_percent_chi2_interval() -> None:
    ekf, q, r_twist, r_pose = _consistency_filter()
    nis, _ = _consistency_run(600, np.random.default_rng(4), ekf, q, r_twist, r_pose, 0.05)
    for kind, values in nis.items():
        n = len(values)
        lo, hi = chi2.ppf([0.025, 0.975], 3 * n) / n
        assert lo <= np.mean(values) <= hi, (kind, n, np.mean(values), lo, hi)


def test_average_nees_over_monte_carlo_runs_is_within_the_95_percent_chi2_interval() -> None:
    runs, steps = 40, 100
    rng = np.random.default_rng(5)
    nees = []
    for _ in range(runs):
        ekf, q, r_twist, r_pose = _consistency_filter()
        nees.append(_consistency_run(steps, rng, ekf, q, r_twist, r_pose, 0.05)[1])
    mean = np.mean(nees, axis=0)  # average over runs, per step
    lo, hi = chi2.ppf([0.025, 0.975], 6 * runs) / runs
    for k in (25, 50, 99):
        assert lo <= mean[k] <= hi, (k, mean[k], lo, hi)


# --- robot_localization behaviours --------------------------------------------------------------


def test_vo_jump_of_one_metre_is_rejected_by_the_mahalanobis_gate_and_counted() -> None:
    n = 90
    t, (x, y, _), twists, poses = circle(n, seed=6)
    jumped = [
        p
        if i < 45
        else PoseInput(p.stamp_ns, Pose2(p.pose.x + 1.0, p.pose.y, p.pose.yaw), p.covariance)
        for i, p in enumerate(poses)
    ]
    cfg = pose_vo_config(vo0_pose_rejection_threshold=5.0, vo0_twist_rejection_threshold=5.0)
    out = fuse({"odom0": twists, "vo0": jumped}, cfg, output_stamps_ns=t)
    assert out.stats.sensors["vo0"]["rejected"] == 1
    assert out.stats.sensors["vo0"]["fused"] == n - 2  # first pose only seeds the differencing
    assert abs(out.x[-1] - x[-1]) < 0.02 and abs(out.y[-1] - y[-1]) < 0.02


def test_default_config_gates_a_wild_vo_twist_and_keeps_the_good_ones() -> None:
    n = 90
    t, (x, y, _), twists, _ = circle(n, seed=8)
    cov = np.diag([0.02**2, 0.02**2, 0.02**2])
    vo = [TwistInput(tw.stamp_ns, V, 0.0, W, cov) for tw in twists]
    vo[50] = TwistInput(vo[50].stamp_ns, 30.0, 0.0, W, cov)  # a 1 m jump in one 1/30 s pair
    out = fuse({"odom0": twists, "vo0": vo}, EkfConfig(), output_stamps_ns=t)
    assert out.stats.sensors["vo0"]["rejected"] == 1
    assert out.stats.sensors["vo0"]["fused"] == n - 1
    assert abs(out.x[-1] - x[-1]) < 0.05 and abs(out.y[-1] - y[-1]) < 0.05


def test_vo_failure_frames_are_skipped_and_counted() -> None:
    t, _, twists, poses = circle(30, seed=7)
    lost = [dataclasses.replace(p, valid=(i % 3 != 1)) for i, p in enumerate(poses)]
    out = fuse({"odom0": twists, "vo0": lost}, pose_vo_config())
    assert out.stats.sensors["vo0"]["invalid"] == 10
    assert out.stats.sensors["vo0"]["received"] == 30


def test_vo_that_stops_halfway_times_out_and_the_estimate_continues_from_the_wheels() -> None:
    n = 300  # 10 s
    t, (x, y, yaw), twists, poses = circle(n, seed=8)
    out = fuse({"odom0": twists, "vo0": poses[: n // 2]}, pose_vo_config(), output_stamps_ns=t)
    assert out.stats.sensors["vo0"]["timeouts"] == 1
    assert out.stats.stale_sensors == ("vo0",)
    assert not out.timed_out.any()  # the wheels keep the filter corrected
    assert np.hypot(out.x - x, out.y - y).max() < 0.05
    assert abs(wrap_angle(out.yaw[-1] - yaw[-1])) < 0.05
    assert out.cov[-1, 0, 0] > out.cov[n // 2 - 1, 0, 0]  # uncertainty grows on wheels alone


def test_no_data_for_sensor_timeout_gives_predict_only_outputs_that_are_flagged() -> None:
    t, _, twists, _ = circle(30, seed=9)
    late = int(t[-1] + 0.5 * NS_PER_S)
    out = fuse(
        {"odom0": twists}, pose_vo_config(sensor_timeout=0.1), output_stamps_ns=[t[-1], late]
    )
    assert out.timed_out.tolist() == [False, True]
    assert out.stats.timed_out_outputs == 1
    assert out.cov[1, 0, 0] > out.cov[0, 0, 0]


def _streams_for_lag():
    t, _, twists, poses = circle(60, seed=10)
    noisy_abs = [p for i, p in enumerate(poses) if i % 6 == 0]  # 5 Hz absolute pose
    return twists, noisy_abs


def _lag_cfg(**kw: Any) -> EkfConfig:
    args: dict[str, Any] = dict(vo0_differential=False, smooth_lagged_data=True, history_length=1.0)
    return pose_vo_config(**(args | kw))


def test_late_measurement_within_history_is_refiltered_to_the_in_order_result() -> None:
    twists, poses = _streams_for_lag()
    msgs = sorted(
        [("odom0", m) for m in twists] + [("vo0", m) for m in poses], key=lambda sm: sm[1].stamp_ns
    )
    in_order = PlanarEkf(_lag_cfg())
    for s, m in msgs:
        in_order.process(s, m)
    late_msg = poses[5]  # t = 1.0 s, arrives 0.3 s late
    shuffled = [sm for sm in msgs if sm[1] is not late_msg]
    at = next(i for i, sm in enumerate(shuffled) if sm[1].stamp_ns > late_msg.stamp_ns + 0.3e9)
    shuffled.insert(at, ("vo0", late_msg))
    late = PlanarEkf(_lag_cfg())
    for s, m in shuffled:
        late.process(s, m)
    np.testing.assert_allclose(late.x, in_order.x, atol=1e-9)
    np.testing.assert_allclose(late.P, in_order.P, atol=1e-9)
    assert late.stats.sensors["vo0"]["refiltered"] == 1
    assert late.stats.sensors["vo0"]["fused"] == in_order.stats.sensors["vo0"]["fused"]
    assert late.stats.sensors["odom0"]["fused"] == in_order.stats.sensors["odom0"]["fused"]


@pytest.mark.parametrize("smooth", [True, False])
def test_late_measurement_outside_history_is_dropped_and_counted(smooth: bool) -> None:
    twists, poses = _streams_for_lag()
    ekf = PlanarEkf(_lag_cfg(history_length=0.5, smooth_lagged_data=smooth))
    for m in twists:
        ekf.process("odom0", m)
    x_before = ekf.x.copy()
    res = ekf.process("vo0", dataclasses.replace(poses[1], stamp_ns=twists[0].stamp_ns + 1))
    assert [r.reason for r in res] == ["dropped_late"]
    assert ekf.stats.sensors["vo0"]["dropped_late"] == 1
    np.testing.assert_array_equal(ekf.x, x_before)


def test_differential_mode_makes_a_constant_offset_disappear() -> None:
    t, _, twists, poses = circle(60, seed=11)
    offset = Pose2(5.0, -3.0, 1.0)
    shifted = [dataclasses.replace(p, pose=compose(offset, p.pose)) for p in poses]
    cfg = pose_vo_config()  # vo0 as a differential pose
    a = fuse({"odom0": twists, "vo0": poses}, cfg)
    b = fuse({"odom0": twists, "vo0": shifted}, cfg)
    assert a.stats.sensors["vo0"]["fused"] == 59
    for u, v in ((a.x, b.x), (a.y, b.y), (a.yaw, b.yaw), (a.cov, b.cov)):
        np.testing.assert_allclose(u, v, atol=1e-9)


def test_relative_mode_equals_absolute_fusion_of_poses_relative_to_the_first() -> None:
    t, _, twists, poses = circle(60, seed=12)
    offset = Pose2(5.0, -3.0, 1.0)
    shifted = [dataclasses.replace(p, pose=compose(offset, p.pose)) for p in poses]
    rel = [dataclasses.replace(p, pose=se2_between(poses[0].pose, p.pose)) for p in poses]
    a = fuse(
        {"vo0": shifted, "odom0": twists}, pose_vo_config(vo0_differential=False, vo0_relative=True)
    )
    b = fuse({"vo0": rel, "odom0": twists}, pose_vo_config(vo0_differential=False))
    for u, v in ((a.x, b.x), (a.y, b.y), (a.yaw, b.yaw), (a.cov, b.cov)):
        np.testing.assert_allclose(u, v, atol=1e-9)
    assert abs(a.x[-1] - poses[-1].pose.x) < 0.02  # the circle starts at the origin


def test_gyro_fuses_yaw_rate_only() -> None:
    ekf = PlanarEkf(pose_vo_config(odom0_config=mask("vx")))
    ekf.process("odom0", TwistInput(0, 0.2, 0.0, 0.0, np.eye(3) * 1e-4))
    res = ekf.process("imu0", ImuSample(NS_PER_S // 10, 0.5))
    assert res[0].accepted and res[0].dof == 1
    assert ekf.x[5] > 0.1 and ekf.x[4] == pytest.approx(0.0, abs=1e-12)


def test_wheel_twist_inputs_from_equal_counts_drive_straight_with_quantisation_noise() -> None:
    robot = RobotConfig()
    stamps = np.arange(31) * DT_NS
    ticks = np.arange(31) * 2
    tw = wheel_twist_inputs(stamps, ticks, ticks, robot)
    assert len(tw) == 30
    v = 2 * robot.metres_per_tick / (DT_NS / NS_PER_S)
    assert tw[0].vx == pytest.approx(v) and tw[0].vyaw == pytest.approx(0.0)
    assert tw[0].covariance[0, 0] > (robot.metres_per_tick / (DT_NS / NS_PER_S)) ** 2 / 12
    out = fuse({"odom0": tw}, pose_vo_config(), output_stamps_ns=[stamps[-1]])
    assert out.x[0] == pytest.approx(v * (stamps[-1] - stamps[1]) / NS_PER_S, rel=1e-6)
    assert out.y[0] == pytest.approx(0.0, abs=1e-9)


def test_wheel_twist_inputs_last_only_is_the_last_of_the_full_list() -> None:
    robot = RobotConfig()
    rng = np.random.default_rng(3)
    stamps = np.cumsum(rng.integers(15, 25, 64)) * 1_000_000
    left, right = np.cumsum(rng.integers(0, 4, 64)), np.cumsum(rng.integers(0, 5, 64))
    full = wheel_twist_inputs(stamps, left, right, robot)
    last = wheel_twist_inputs(stamps, left, right, robot, last_only=True)
    assert len(last) == 1 and last[0].stamp_ns == full[-1].stamp_ns
    assert (last[0].vx, last[0].vyaw) == (full[-1].vx, full[-1].vyaw)
    assert np.array_equal(last[0].covariance, full[-1].covariance)
    assert wheel_twist_inputs(stamps[:1], left[:1], right[:1], robot, last_only=True) == []


@pytest.mark.parametrize("speed", [0.05, 0.3])
def test_wheel_only_filter_keeps_the_distance_of_quantised_encoder_counts(speed: float) -> None:
    """A wheel twist's variance grows with travel. Taken from the interval's own count, an
    interval that happened to count fewer ticks (or none, crawling) is trusted more than one
    that counted more, and the filter's distance comes out short (over 10 % here with
    ``variance_window_s=0``; an Eddie tick is 13 mm, most 20 ms intervals count 0 or 1)."""
    robot = RobotConfig()
    cfg = EkfConfig()  # the shipped defaults: wheel vx, vy, vyaw
    dt = 0.02  # [s] 50 Hz board polls
    t = np.arange(0.0, 10.0 + dt / 2, dt)
    moving = t < 8.0  # then stopped: the filter's lag does not count as lost distance
    jitter = np.cumsum(np.random.default_rng(3).normal(0.0, 2e-4, len(t)) * moving)
    ticks = np.floor((speed * np.minimum(t, 8.0) + jitter) / robot.metres_per_tick)
    stamps = (t * NS_PER_S).astype(np.int64)
    true_m = (ticks[-1] - ticks[0]) * robot.metres_per_tick

    def distance(**kw: float) -> float:
        tw = wheel_twist_inputs(stamps, ticks, ticks, robot, **kw)
        return float(fuse({"odom0": tw}, cfg, output_stamps_ns=stamps[-1:]).x[0])

    assert distance() == pytest.approx(true_m, rel=0.01)
    assert distance(variance_window_s=0.0) < 0.95 * true_m  # the interval's own count


def test_state_at_earlier_than_history_raises() -> None:
    ekf = PlanarEkf(pose_vo_config())
    with pytest.raises(EkfError, match="no measurement"):
        ekf.state_at(0)
    ekf.process("odom0", TwistInput(NS_PER_S, 0.1, 0.0, 0.0, np.eye(3) * 1e-4))
    with pytest.raises(EkfError, match="older than the kept history"):
        ekf.state_at(0)


def test_gyro_bias_is_estimated_from_wheel_yaw_rates() -> None:
    # A gyro reading 0.01 rad/s high beside unbiased wheels: the bias state absorbs it and the
    # fused heading stays on the wheels' yaw, instead of turning with the biased gyro.
    n, bias = 600, 0.01
    t, (_, _, yaw), twists, _ = circle(n, seed=9)
    gyro = [ImuSample(tw.stamp_ns + 1, W + bias) for tw in twists]
    out = fuse(
        {"odom0": twists, "imu0": gyro}, EkfConfig(), output_stamps_ns=t, gyro_z_variance=1e-5
    )
    assert abs(wrap_angle(out.yaw[-1] - yaw[-1])) < 0.05  # [rad] (unestimated: 0.2 rad)


def test_motion_twist_divides_the_motion_by_dt_and_its_covariance_by_dt_squared() -> None:
    from slam.ekf import motion_twist

    cov = np.diag([1e-4, 4e-4, 9e-4])
    tw = motion_twist(7, Pose2(0.03, -0.01, 0.02), cov, 0.1)
    assert tw.stamp_ns == 7 and tw.valid
    assert (tw.vx, tw.vy, tw.vyaw) == pytest.approx((0.3, -0.1, 0.2))
    np.testing.assert_allclose(tw.covariance, cov * 100.0)


def test_a_vo_motion_spanning_skipped_frames_is_fused_at_each_of_them() -> None:
    # A turn at 0.5 rad/s; the wheels (50 Hz) say 0.4 rad/s (a track-width error); VO (30 Hz)
    # is right but ran on every third frame only (a live front end behind). One twist at the
    # end of each span only corrects the velocity from there on: the filter's heading follows
    # the wheels over the gaps. Spread over the frames it spans, the VO motion carries it.
    cfg = EkfConfig()  # the shipped fusion: wheel and VO twists
    true_w, wheel_w, t_end = 0.5, 0.4, 6.0
    wheel_cov = np.diag([1e-3, 1e-4, 1e-2])
    vo_cov = np.diag([1e-7, 1e-7, 1e-7])  # per-pair delta covariance [m^2, m^2, rad^2]
    frames = np.arange(0, int(t_end * 30) + 1) * DT_NS
    ran = frames[::3]
    wheel_t = np.arange(1, int(t_end * 50) + 1) * (NS_PER_S // 50)

    def final_yaw(split: bool) -> float:
        ekf = PlanarEkf(cfg)
        msgs = [
            (int(t), "odom0", TwistInput(int(t), 0.2, 0.0, wheel_w, wheel_cov)) for t in wheel_t
        ]
        for a, b in zip(ran[:-1], ran[1:], strict=True):
            dt = (b - a) / NS_PER_S
            delta = Pose2(0.2 * dt, 0.0, true_w * dt)
            skipped = [int(t) for t in frames if a < t < b] if split else []
            for tw in spanning_motion_twists(skipped, int(b), delta, vo_cov, dt):
                msgs.append((tw.stamp_ns, "vo0", tw))
        for _, sensor, m in sorted(msgs, key=lambda x: x[0]):
            ekf.process(sensor, m)
        assert ekf.t_ns is not None
        return ekf.state_at(ekf.t_ns).pose.yaw - true_w * ekf.t_ns / NS_PER_S

    err_end = abs(final_yaw(False))
    err_split = abs(final_yaw(True))
    assert err_split < 0.6 * err_end  # measured: 0.23 vs 0.44 rad after 6 s


def test_spanning_motion_twists_without_skipped_frames_is_one_motion_twist() -> None:
    d, cov = Pose2(0.01, 0.0, 0.02), np.diag([1e-6, 1e-6, 1e-6])
    (one,) = spanning_motion_twists([], 5, d, cov, 0.1)
    assert (one.stamp_ns, one.vx, one.vyaw) == (5, pytest.approx(0.1), pytest.approx(0.2))
    three = spanning_motion_twists([1, 3], 5, d, cov, 0.1)
    assert [t.stamp_ns for t in three] == [1, 3, 5]
    assert all(t.vyaw == pytest.approx(0.2) for t in three)
    assert np.allclose(three[0].covariance, 3 * one.covariance)


def test_interval_twists_cut_long_gaps_and_keep_the_information_of_one_measurement() -> None:
    mean = TwistInput(100, 0.2, 0.0, 0.5, np.diag([1e-3, 1e-4, 2e-3]))
    ms = 1_000_000
    out = interval_twists(0, 100 * ms, mean, marks_ns=[30 * ms, 150 * ms], max_step_s=0.025)
    # (0, 30] in 2 steps, (30, 100] in 3; a mark outside the interval is ignored
    assert [t.stamp_ns for t in out] == [
        15 * ms,
        30 * ms,
        53 * ms + ms // 3,
        76 * ms + 2 * ms // 3,
        100 * ms,
    ]
    assert all((t.vx, t.vyaw) == (0.2, 0.5) for t in out)
    info = sum(np.linalg.inv(t.covariance) for t in out)
    assert np.allclose(info, np.linalg.inv(mean.covariance))
    (same,) = interval_twists(0, 20 * ms, mean, max_step_s=0.025)
    assert same.stamp_ns == 20 * ms and np.array_equal(same.covariance, mean.covariance)


def test_wheel_twist_inputs_spread_a_late_reading_over_its_interval() -> None:
    robot = RobotConfig()
    ms = 1_000_000
    stamps = np.array([0, 20, 40, 1040, 1060]) * ms  # the fourth reading came a second late
    ticks = np.array([0, 1, 2, 50, 51])
    tw = wheel_twist_inputs(stamps, ticks, ticks, robot, max_interval_s=1 / 30)
    assert len(tw) == 2 + 8 + 1  # at most MAX_SPREAD_STEPS pieces: each may cost a re-filter
    gap = tw[2:10]
    assert gap[-1].stamp_ns == 1040 * ms and gap[0].stamp_ns == 40 * ms + 1000 * ms // 8
    assert all(t.vx == pytest.approx(48 * robot.metres_per_tick) for t in gap)
    plain = wheel_twist_inputs(stamps, ticks, ticks, robot)
    assert np.allclose(gap[0].covariance, 8 * plain[2].covariance)
    last = wheel_twist_inputs(
        stamps[:4], ticks[:4], ticks[:4], robot, last_only=True, max_interval_s=1 / 30
    )
    assert [t.stamp_ns for t in last] == [t.stamp_ns for t in gap]


def test_a_turn_made_while_wheel_readings_were_late_is_in_the_heading() -> None:
    """A live soak: the board's replies stalled for a second while the robot spun. The one
    reading after the gap holds the whole turn; fused as one twist at its end the filter had
    predicted the gap at its old (zero) yaw rate and the turn was lost from the heading."""
    robot = RobotConfig()
    cfg = EkfConfig()
    ms = 1_000_000
    w = 0.6  # [rad/s] the spin starts when the replies stall
    t = np.concatenate([np.arange(0, 1000, 20), np.arange(2000, 3001, 20)]) * ms
    turn = np.clip(t / NS_PER_S - 1.0, 0.0, None) * w  # [rad]
    half = turn * robot.track_width / 2 / robot.metres_per_tick
    right, left = np.floor(half), -np.floor(half)

    def heading_error(step: float | None) -> float:
        tw = wheel_twist_inputs(t, left, right, robot, max_interval_s=step)
        out = fuse({"odom0": tw}, cfg, output_stamps_ns=t[-1:])
        return abs(float(out.yaw[0]) - wrap_angle(turn[-1]))

    assert heading_error(None) > 0.3  # measured 0.56 rad: nearly the whole second's turn
    assert heading_error(1 / cfg.frequency) < 0.1  # measured 0.05 rad


def test_a_wrong_motion_spread_over_its_span_is_gated_as_one_measurement() -> None:
    """Spread over k frames, each piece of a wrong VO motion carries k times the covariance and
    passes a gate sqrt(k) times wider: the span must be gated once, as one measurement."""
    # Live settings: VO arrives after the wheel readings past its stamp (re-filtered).
    cfg = dataclasses.replace(EkfConfig(), smooth_lagged_data=True, history_length=1.0)
    ekf = PlanarEkf(cfg)
    wheel_cov = np.diag([1e-3, 1e-4, 1e-2])
    vo_cov = np.diag([1e-6, 1e-6, 1e-6])  # per-pair delta covariance
    for k in range(1, 91):  # 3 s turning at 0.5 rad/s, wheels and VO agree
        t = int(k * DT_NS)
        ekf.process("odom0", TwistInput(t, 0.2, 0.0, 0.5, wheel_cov))
        ekf.process("vo0", motion_twist(t, Pose2(0.2 / 30, 0.0, 0.5 / 30), vo_cov, 1 / 30))
    for k in range(91, 101):  # VO skipped 10 frames; the wheels went on
        ekf.process("odom0", TwistInput(int(k * DT_NS), 0.2, 0.0, 0.5, wheel_cov))
    # Then a pair over those 10 frames claiming twice the turn.
    start, end, dt = 90 * DT_NS, 100 * DT_NS, 10 / 30
    wrong = Pose2(0.2 * dt, 0.0, 1.0 * dt)
    pieces = spanning_motion_twists([], int(end), wrong, vo_cov, dt, max_step_s=1 / 30)
    assert len(pieces) == 8 and abs(pieces[0].stamp_ns - (start + (end - start) // 8)) < 1000
    x0, p0 = ekf.x.copy(), ekf.P.copy()
    ok, nis = ekf.twist_gate("vo0", motion_twist(int(end), wrong, vo_cov, dt))
    assert not ok and nis > cfg.vo0_twist_rejection_threshold**2
    assert np.array_equal(ekf.x, x0) and np.array_equal(ekf.P, p0)  # nothing fused
    # Each piece alone is gated against a threshold sqrt(8) times wider: the first passes.
    assert ekf.twist_gate("vo0", pieces[0])[0]
    # process_span gates the span once: nothing fused, one rejection counted.
    rejected = ekf.stats.sensors["vo0"]["rejected"]
    (res,) = ekf.process_span("vo0", pieces)
    assert (res.accepted, res.reason) == (False, "span_rejected")
    assert np.array_equal(ekf.x, x0) and np.array_equal(ekf.P, p0)
    assert ekf.stats.sensors["vo0"]["rejected"] == rejected + 1
    # The right motion over the same span passes and is fused piece by piece.
    right = Pose2(0.2 * dt, 0.0, 0.5 * dt)
    assert ekf.twist_gate("vo0", motion_twist(int(end), right, vo_cov, dt))[0]
    good = spanning_motion_twists([], int(end), right, vo_cov, dt, max_step_s=1 / 30)
    out = ekf.process_span("vo0", good)
    assert len(out) == len(good) and all(r.accepted for r in out)


def filterpy_sequence(steps: int, seed: int) -> tuple[list[np.ndarray], ...]:
    """One fused run twice: slam.ekf's kernels and filterpy's ExtendedKalmanFilter (the
    reference) on the same constant-velocity model, 30 Hz predictions, alternately a twist update
    (vx, vyaw) and a pose update (x, y, yaw, angle residual). Returns the states and
    covariances of both after every step."""
    from filterpy.kalman import ExtendedKalmanFilter

    rng = np.random.default_rng(seed)
    dt = 1.0 / 30
    q = np.diag([1e-4, 1e-4, 1e-4, 1e-2, 1e-2, 1e-2])
    truth = np.array([0.0, 0.0, math.pi - 0.2, 0.3, 0.0, 0.4])  # yaw crosses +-pi
    x, p = truth + 0.1, np.diag([0.1, 0.1, 0.05, 0.1, 0.1, 0.1])
    ref = ExtendedKalmanFilter(dim_x=6, dim_z=3)
    ref.x, ref.P = x.copy(), p.copy()

    def predict_x(u: Any = 0) -> None:  # the nonlinear motion (filterpy's hook for it)
        ref.x = transition(ref.x, dt)[0]

    ref.predict_x = predict_x
    twist_h, pose_h = np.eye(6)[[3, 5]], np.eye(6)[:3]
    twist_r, pose_r = np.diag([0.01, 0.02]), np.diag([0.02, 0.02, 0.01])
    yaw_res = angle_residual(np.array([False, False, True]))
    out: tuple[list[np.ndarray], ...] = ([], [], [], [])
    for k in range(steps):
        truth = transition(truth, dt)[0]
        ref.F, ref.Q = transition(ref.x, dt)[1], dt * q
        ref.predict()
        x, p = predict(x, p, dt, q)
        h, r, res = (twist_h, twist_r, np.subtract) if k % 2 else (pose_h, pose_r, yaw_res)
        z = h @ truth + rng.multivariate_normal(np.zeros(len(r)), r)
        if h is pose_h:
            z[2] = wrap_angle(z[2])
        ref.update(z, lambda s, h=h: h, lambda s, h=h: h @ s, R=r, residual=res)
        x, p, *_ = update(x, p, z, h, r, res)
        for lst, v in zip(out, (x, p, ref.x, ref.P), strict=True):
            lst.append(np.array(v, dtype=np.float64))
    return out


def test_a_whole_fused_run_matches_filterpys_extended_kalman_filter() -> None:
    xs, ps, ref_xs, ref_ps = filterpy_sequence(300, seed=4)
    for k in range(300):
        np.testing.assert_allclose(xs[k], ref_xs[k], rtol=0, atol=1e-9, err_msg=f"x step {k}")
        np.testing.assert_allclose(ps[k], ref_ps[k], rtol=0, atol=1e-12, err_msg=f"P step {k}")
    yaws = [x[2] for x in xs]
    assert max(yaws) > 3.0 and min(yaws) < -2.0  # the yaw crossed +-pi: the wraps were exercised


def test_a_gyro_sample_at_the_bare_start_instant_is_not_read_as_bias() -> None:
    # A robot already turning when the filter starts (a live run started mid-turn): the start
    # prior holds it still to 1e-9, so a gyro sample stamped at that very instant could only be
    # explained as gyro bias (prior 1e-4), which then stuck and slowed the heading by a third.
    from slam.ekf import GYRO_BIAS, YAW

    rate, period = 0.12, NS_PER_S // 200
    ekf = PlanarEkf(pose_vo_config(odom0_config=mask("vx")))
    ekf.start(0)
    for k in range(201):  # 1 s of a 200 Hz gyro, the first sample at the start instant
        ekf.process("imu0", ImuSample(k * period, rate))
    assert ekf.stats.sensors["imu0"]["before_start"] == 1  # counted apart from late ones
    x, _ = ekf.predicted(NS_PER_S)
    assert abs(x[GYRO_BIAS]) < 5e-3  # [rad/s] (0.06 when the first sample was read as bias)
    assert x[YAW] == pytest.approx(rate, abs=2e-3)  # [rad] after 1 s


def test_a_straight_drive_with_quantised_ticks_gyro_and_vo_makes_no_sideways_step() -> None:
    """A differential drive cannot move sideways. With wheels (one 13 mm tick per 20 ms or
    none), a biased gyro and noisy VO, each VO or wheel yaw-rate innovation told the gyro bias
    state a little, and the textbook update moved the pose by the bias's whole history through
    its cross-covariance: sideways jumps of up to 9 mm between frames here (1-3.4 cm on the
    house route). The pose's gain is now the one it would have with the bias known."""
    from slam.geometry import ominus

    robot, rng = RobotConfig(), np.random.default_rng(0)
    v, end = 0.3, 10.0  # [m/s], [s]
    wheel_t = np.arange(0.0, end, 0.02)  # 50 Hz board
    ticks = np.floor(v * wheel_t / robot.metres_per_tick)

    def ns(t: np.ndarray) -> np.ndarray:
        return (t * NS_PER_S).round().astype(np.int64)

    wheels = wheel_twist_inputs(ns(wheel_t), ticks, ticks, robot)
    gyro = [
        ImuSample(int(s), 0.002 + 0.005 * rng.standard_normal())
        for s in ns(np.arange(0, end, 0.01))
    ]
    frames = ns(np.arange(0.0, end, 1 / 30))
    sigma = np.array([0.002, 0.002, 0.003])  # [m, m, rad] per frame, as the house's VO
    vo = [
        motion_twist(
            int(b),
            Pose2(*(np.array([v / 30, 0.0, 0.0]) + sigma * rng.standard_normal(3))),
            np.diag(sigma**2),
            1 / 30,
        )
        for b in frames[1:]
    ]
    out = fuse({"odom0": wheels, "imu0": gyro, "vo0": vo}, EkfConfig(), frames[1:], 1e-4)
    poses = np.column_stack([out.x, out.y, out.yaw])
    sideways = ominus(poses[:-1], poses[1:])[:, 1]
    assert np.abs(sideways).max() < 0.002  # [m] (0.0094 with PlanarEkf.twist_moves_pose)
