"""Wheel odometry covariance: growth with distance and turn, closed form vs loop, Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.config import RobotConfig
from sensors.types import ConfigError, Pose2
from slam.diff_drive import (
    WheelErrorModel,
    increment_covariance,
    integrate_increments,
    propagate_covariance,
    propagate_covariance_reference,
)

ROBOT = RobotConfig()
B = ROBOT.track_width  # [m]
MODEL = WheelErrorModel(k_left=0.0005, k_right=0.0007, k_theta=0.001)


def straight(length_m: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    return np.full(steps, length_m / steps), np.zeros(steps)


def test_default_model_gives_about_2_cm_per_wheel_after_one_metre() -> None:
    m = WheelErrorModel()
    assert math.sqrt(m.k_left * 1.0) == pytest.approx(0.02236, abs=1e-5)
    assert m.k_theta == 0.0


def test_straight_line_variance_along_the_heading_grows_linearly_with_distance() -> None:
    ds, dth = straight(2.0, 2000)
    p = propagate_covariance(ds, dth, 0.0, ROBOT, MODEL)
    # var_x = sum (k_r |ds| + k_l |ds|) / 4, exactly (x is along the heading).
    expected = (MODEL.k_right + MODEL.k_left) / 4 * np.cumsum(ds)
    np.testing.assert_allclose(p[1:, 0, 0], expected, rtol=1e-9)
    assert p[2000, 0, 0] / p[1000, 0, 0] == pytest.approx(2.0, rel=1e-9)


def test_straight_line_lateral_variance_grows_cubically_with_distance() -> None:
    model = WheelErrorModel(k_left=0.0005, k_right=0.0005, k_theta=0.0)
    ds, dth = straight(2.0, 2000)
    p = propagate_covariance(ds, dth, 0.0, ROBOT, model)
    # Heading variance grows as 2k s/b^2; the lateral lever integrates it: 2k L^3 / (3 b^2).
    for k, length in ((1000, 1.0), (2000, 2.0)):
        assert p[k, 1, 1] == pytest.approx(2 * 0.0005 * length**3 / (3 * B**2), rel=0.01)
    assert p[2000, 1, 1] / p[1000, 1, 1] == pytest.approx(8.0, rel=0.01)
    assert p[2000, 2, 2] / p[1000, 2, 2] == pytest.approx(2.0, rel=1e-9)


def test_heading_variance_grows_linearly_with_rotation_when_spinning_in_place() -> None:
    steps = 400
    dth = np.full(steps, 2 * math.pi / steps)
    p = propagate_covariance(np.zeros(steps), dth, 0.0, ROBOT, MODEL)
    turned = np.cumsum(dth)
    # Each wheel travels b/2 per radian: var_theta = ((k_r + k_l) / (2 b) + k_theta) * theta.
    expected = ((MODEL.k_right + MODEL.k_left) / (2 * B) + MODEL.k_theta) * turned
    np.testing.assert_allclose(p[1:, 2, 2], expected, rtol=1e-9)
    assert np.all(np.diff(p[:, 2, 2]) > 0)
    # Wheel errors while spinning also shift the axle centre a little.
    assert 0 < p[-1, 0, 0] < 1e-3


def test_covariance_is_symmetric_positive_semidefinite() -> None:
    rng = np.random.default_rng(0)
    ds = rng.uniform(-0.02, 0.05, 3000)
    dth = rng.normal(0.0, 0.05, 3000)
    p = propagate_covariance(ds, dth, 0.3, ROBOT, MODEL, cov0=np.diag([1e-4, 1e-4, 1e-3]))
    np.testing.assert_array_equal(p, p.transpose(0, 2, 1))
    eig = np.linalg.eigvalsh(p)
    assert eig.min() >= -1e-12 * eig.max()
    # Heading variance only accumulates; position variance may shrink when driving back
    # along a correlated heading error, so only theta is monotonic.
    assert np.all(np.diff(p[:, 2, 2]) >= 0)


def test_closed_form_matches_the_step_by_step_reference() -> None:
    rng = np.random.default_rng(1)
    ds = rng.uniform(-0.01, 0.04, 500)
    dth = rng.normal(0.0, 0.1, 500)
    cov0 = np.array([[2e-4, 1e-5, 3e-5], [1e-5, 1e-4, -2e-5], [3e-5, -2e-5, 5e-4]])
    fast = propagate_covariance(ds, dth, -1.0, ROBOT, MODEL, cov0=cov0)
    slow = propagate_covariance_reference(ds, dth, -1.0, ROBOT, MODEL, cov0=cov0)
    np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=1e-15)


def test_initial_heading_uncertainty_swings_the_position_along_the_lever_arm() -> None:
    ds, dth = straight(3.0, 30)
    zero = WheelErrorModel(0.0, 0.0, 0.0)
    p = propagate_covariance(ds, dth, math.pi / 2, ROBOT, zero, cov0=np.diag([0.0, 0.0, 0.01]))
    # Driving 3 m along +y with sigma_theta = 0.1 rad: sigma_x = 0.3 m, fully correlated.
    assert p[-1, 0, 0] == pytest.approx(9 * 0.01, rel=1e-12)
    assert p[-1, 1, 1] == pytest.approx(0.0, abs=1e-15)
    assert p[-1, 0, 2] == pytest.approx(-3 * 0.01, rel=1e-12)


def test_no_motion_adds_no_uncertainty() -> None:
    p = propagate_covariance(np.zeros(5), np.zeros(5), 0.0, ROBOT, MODEL)
    assert p.shape == (6, 3, 3) and np.all(p == 0.0)
    assert propagate_covariance(np.zeros(0), np.zeros(0), 0.0, ROBOT).shape == (1, 3, 3)


def test_monte_carlo_end_pose_covariance_matches_the_propagated_one() -> None:
    # A 1.5 m arc turning 90 deg, 150 steps; wheel travel errors drawn from the model itself.
    steps, samples = 150, 500
    ds = np.full(steps, 1.5 / steps)
    dth = np.full(steps, (math.pi / 2) / steps)
    d_right, d_left = ds + B * dth / 2, ds - B * dth / 2
    rng = np.random.default_rng(42)
    ends = np.empty((samples, 3))
    for n in range(samples):
        nr = d_right + rng.standard_normal(steps) * np.sqrt(MODEL.k_right * np.abs(d_right))
        nl = d_left + rng.standard_normal(steps) * np.sqrt(MODEL.k_left * np.abs(d_left))
        e_th = rng.standard_normal(steps) * np.sqrt(MODEL.k_theta * np.abs(dth))
        x, y, th = integrate_increments((nr + nl) / 2, (nr - nl) / B + e_th, Pose2(0, 0, 0))
        ends[n] = x[-1], y[-1], th[-1]
    empirical = np.cov(ends.T)
    predicted = propagate_covariance(ds, dth, 0.0, ROBOT, MODEL)[-1]
    np.testing.assert_allclose(np.diag(empirical), np.diag(predicted), rtol=0.15)


def test_increment_covariance_of_a_straight_step_is_diagonal_in_the_body_frame() -> None:
    q = increment_covariance(np.array([0.1]), np.array([0.0]), 0.0, ROBOT, MODEL)[0]
    kr, kl = MODEL.k_right * 0.1, MODEL.k_left * 0.1
    assert q[0, 0] == pytest.approx((kr + kl) / 4)
    assert q[2, 2] == pytest.approx((kr + kl) / B**2)
    assert q[0, 2] == pytest.approx((kr - kl) / (2 * B))
    assert q[1, 1] == pytest.approx((0.1 / (2 * B)) ** 2 * (kr + kl))


def test_closed_form_matches_the_step_by_step_reference_over_a_long_run() -> None:
    # Speed belongs in bench/; here the closed form only has to stay exact over many steps.
    rng = np.random.default_rng(2)
    ds, dth = rng.uniform(0.0, 0.02, 10_000), rng.normal(0.0, 0.02, 10_000)
    fast = propagate_covariance(ds, dth, 0.0, ROBOT, MODEL)
    slow = propagate_covariance_reference(ds, dth, 0.0, ROBOT, MODEL)
    assert np.allclose(fast, slow, rtol=1e-9, atol=1e-15)


def test_wheel_error_model_from_dict_fills_defaults_and_rejects_bad_keys() -> None:
    assert WheelErrorModel.from_dict({"k_theta": 0.002}) == WheelErrorModel(k_theta=0.002)
    assert WheelErrorModel.from_dict(None) == WheelErrorModel()
    with pytest.raises(ConfigError, match="wheel_error.k_up: unknown key"):
        WheelErrorModel.from_dict({"k_up": 1.0})
    with pytest.raises(ConfigError, match="wheel_error.k_left: -0.1 m is out of range"):
        WheelErrorModel.from_dict({"k_left": -0.1})
