"""Velocity smoother: Nav2 limits, direction-preserving scaling, deadband, timeout, feedback."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nav.config import SmootherConfig
from nav.velocity_smoother import (
    EDDIE_PROFILE,
    VelocitySmoother,
    eddie_profile,
    limit_step,
    smooth_step,
)

DT = 0.05  # [s] one tick at 20 Hz
TOL = 1e-9
NS = 1_000_000_000

HOLONOMIC = SmootherConfig(
    max_velocity=(0.5, 0.3, 2.5),
    min_velocity=(-0.5, -0.3, -2.5),
    max_accel=(2.5, 1.0, 3.2),
    max_decel=(-2.0, -1.5, -4.0),
)

speed = st.floats(-3.0, 3.0, allow_nan=False)
twist = st.tuples(speed, speed, speed)


def _within_limits(prev: np.ndarray, out: np.ndarray, cfg: SmootherConfig) -> None:
    lo, hi = np.array(cfg.min_velocity), np.array(cfg.max_velocity)
    assert np.all(out >= lo - TOL) and np.all(out <= hi + TOL)
    # The largest change allowed on any axis is the larger of |accel| and |decel|, per tick;
    # growing-magnitude steps must respect accel, everything else decel.
    dv = out - prev
    grow = (np.abs(out) > np.abs(prev)) & (prev * out >= 0.0)
    acc, dec = np.array(cfg.max_accel) * DT, -np.array(cfg.max_decel) * DT
    assert np.all(np.abs(dv[grow]) <= acc[grow] + TOL)
    assert np.all(np.abs(dv[~grow]) <= np.maximum(acc, dec)[~grow] + TOL)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(targets=st.lists(twist, min_size=1, max_size=40), scale=st.booleans())
def test_output_never_exceeds_velocity_or_acceleration_limits(
    targets: list[tuple[float, float, float]], scale: bool
) -> None:
    cfg = SmootherConfig(
        max_velocity=HOLONOMIC.max_velocity,
        min_velocity=HOLONOMIC.min_velocity,
        max_accel=HOLONOMIC.max_accel,
        max_decel=HOLONOMIC.max_decel,
        scale_velocities=scale,
    )
    prev: tuple[float, float, float] = (0.0, 0.0, 0.0)
    for target in targets:
        out = limit_step(prev, target, DT, cfg)
        _within_limits(np.array(prev), np.array(out), cfg)
        prev = out


def test_speeding_up_uses_accel_and_slowing_down_uses_decel() -> None:
    up = limit_step((0.2, 0.0, 0.0), (0.5, 0.0, 0.0), DT, HOLONOMIC)
    assert up[0] == pytest.approx(0.2 + 2.5 * DT, abs=TOL)
    down = limit_step((0.4, 0.0, 0.0), (0.0, 0.0, 0.0), DT, HOLONOMIC)
    assert down[0] == pytest.approx(0.4 - 2.0 * DT, abs=TOL)


def test_sign_reversal_counts_as_deceleration() -> None:
    out = limit_step((0.0, 0.0, 1.0), (0.0, 0.0, -2.0), DT, HOLONOMIC)
    assert out[2] == pytest.approx(1.0 - 4.0 * DT, abs=TOL)


def test_target_is_clamped_to_velocity_limits_before_ramping() -> None:
    v = (0.49, 0.0, 0.0)
    assert limit_step(v, (9.0, 0.0, 0.0), DT, HOLONOMIC)[0] == pytest.approx(0.5)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    target=st.tuples(
        st.floats(-0.5, 0.5, allow_nan=False),
        st.floats(-0.3, 0.3, allow_nan=False),
        st.floats(-2.5, 2.5, allow_nan=False),
    )
)
def test_scale_velocities_keeps_the_direction_of_the_change(
    target: tuple[float, float, float],
) -> None:
    cfg = SmootherConfig(
        max_velocity=HOLONOMIC.max_velocity,
        min_velocity=HOLONOMIC.min_velocity,
        max_accel=HOLONOMIC.max_accel,
        max_decel=HOLONOMIC.max_decel,
        scale_velocities=True,
    )
    # From rest every axis accelerates, so one eta scales them all: out is parallel to target.
    out = np.array(limit_step((0.0, 0.0, 0.0), target, DT, cfg))
    t = np.array(target)
    if np.linalg.norm(t) < 1e-6:
        return
    cross = np.cross(out, t)
    assert float(np.linalg.norm(cross)) <= 1e-9 * max(1.0, float(np.linalg.norm(t)))
    assert float(out @ t) >= 0.0


def test_without_scaling_each_axis_saturates_independently() -> None:
    out = limit_step((0.0, 0.0, 0.0), (0.5, 0.0, 0.1), DT, HOLONOMIC)
    assert out == pytest.approx((2.5 * DT, 0.0, 0.1))


def test_scaling_slows_the_unlimited_axis_in_proportion() -> None:
    cfg = SmootherConfig(scale_velocities=True)  # Nav2 defaults: accel 2.5 m/s^2, 3.2 rad/s^2
    out = limit_step((0.0, 0.0, 0.0), (0.5, 0.0, 0.1), DT, cfg)
    eta = 2.5 * DT / 0.5
    assert out == pytest.approx((0.5 * eta, 0.0, 0.1 * eta))


def test_deadband_zeroes_small_outputs_but_keeps_ramping_internally() -> None:
    cfg = SmootherConfig(deadband_velocity=(0.2, 0.0, 0.0))
    assert smooth_step((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), DT, cfg)[0] == 0.0
    s = VelocitySmoother(cfg)
    s.set_target((0.5, 0.0, 0.0), 0)
    outs = [s.tick(k * NS // 20)[0] for k in range(1, 6)]
    assert outs[0] == 0.0  # 0.125 m/s is inside the band
    assert outs[1] == pytest.approx(0.25)  # the hidden 0.125 carried over
    assert outs[-1] == pytest.approx(0.5)


def test_timeout_ramps_down_to_zero_within_decel_then_stays_stopped() -> None:
    cfg = SmootherConfig(velocity_timeout=0.5)
    s = VelocitySmoother(cfg)
    s.set_target((0.5, 0.0, 1.0), 0)
    ticks = [s.tick(k * NS // 20) for k in range(1, 11)]  # up to 0.5 s: still following
    assert ticks[-1] == pytest.approx((0.5, 0.0, 1.0))
    after = [s.tick(k * NS // 20) for k in range(11, 30)]
    vx = [a[0] for a in after]
    assert vx[0] == pytest.approx(0.5 - 2.5 * DT)  # first step of the ramp, not a jump
    assert all(b <= a + TOL for a, b in zip(vx, vx[1:], strict=False))
    assert after[-1] == (0.0, 0.0, 0.0)
    assert s.stopped
    # A fresh command wakes it up again.
    s.set_target((0.5, 0.0, 0.0), 30 * NS // 20)
    assert s.tick(31 * NS // 20)[0] == pytest.approx(2.5 * DT)
    assert not s.stopped


def test_tick_before_any_command_is_zero() -> None:
    assert VelocitySmoother(SmootherConfig()).tick(NS) == (0.0, 0.0, 0.0)


def test_non_finite_command_is_ignored() -> None:
    s = VelocitySmoother(SmootherConfig())
    s.set_target((0.3, 0.0, 0.0), 0)
    s.set_target((math.nan, 0.0, 0.0), 1)
    assert s.tick(NS // 20)[0] == pytest.approx(0.125)


def test_interpolates_between_slow_controller_updates() -> None:
    # Controller at 5 Hz, smoother at 20 Hz: four small steps per controller output.
    s = VelocitySmoother(SmootherConfig())
    s.set_target((0.5, 0.0, 0.0), 0)
    out = [s.tick(k * NS // 20)[0] for k in range(1, 5)]
    assert out == pytest.approx([0.125, 0.25, 0.375, 0.5])


def test_closed_loop_starts_from_averaged_odometry() -> None:
    cfg = SmootherConfig(feedback="CLOSED_LOOP", odom_duration=0.1)
    s = VelocitySmoother(cfg)
    s.set_odometry((0.9, 0.0, 0.0), 0)  # falls outside the 0.1 s window below
    s.set_odometry((0.2, 0.0, 0.0), NS // 10 + NS // 20)
    s.set_odometry((0.3, 0.0, 0.0), NS // 10 + NS // 10)
    s.set_target((0.5, 0.0, 0.0), NS // 5)
    assert s.current_velocity()[0] == pytest.approx(0.25)
    assert s.tick(NS // 5 + 1)[0] == pytest.approx(0.25 + 0.125)
    # The robot did not follow: the next step starts from odometry again, not from the output.
    s.set_odometry((0.25, 0.0, 0.0), NS // 5 + NS // 20)
    assert s.tick(NS // 5 + NS // 20)[0] == pytest.approx(0.375, abs=0.03)


def test_open_loop_starts_from_the_last_output() -> None:
    s = VelocitySmoother(SmootherConfig())
    s.set_odometry((0.4, 0.0, 0.0), 0)  # ignored in OPEN_LOOP
    s.set_target((0.5, 0.0, 0.0), 0)
    assert s.tick(1)[0] == pytest.approx(0.125)


def test_defaults_match_nav2() -> None:
    cfg = SmootherConfig()
    assert cfg.smoothing_frequency == 20.0
    assert cfg.scale_velocities is False
    assert cfg.feedback == "OPEN_LOOP"
    assert cfg.max_velocity == (0.5, 0.0, 2.5)
    assert cfg.min_velocity == (-0.5, 0.0, -2.5)
    assert cfg.max_accel == (2.5, 0.0, 3.2)
    assert cfg.max_decel == (-2.5, 0.0, -3.2)
    assert cfg.deadband_velocity == (0.0, 0.0, 0.0)
    assert cfg.velocity_timeout == 1.0
    assert cfg.odom_duration == 0.1
    assert cfg.validate() is None


def test_eddie_profile_values() -> None:
    for cfg in (EDDIE_PROFILE, eddie_profile()):
        assert cfg.max_velocity == (1.4, 0.0, 0.2)
        assert cfg.min_velocity == (-1.4, 0.0, -0.2)
        assert cfg.max_accel == (1.125, 0.0, 1.125)
        assert cfg.max_decel == (-1.125, 0.0, -1.125)
        assert cfg.deadband_velocity == (0.0, 0.0, 0.0)
        assert cfg.scale_velocities is True
        assert cfg.feedback == "OPEN_LOOP"
        assert cfg.smoothing_frequency == 20.0
        assert cfg.validate() is None


def test_eddie_never_strafes() -> None:
    out = limit_step((0.0, 0.0, 0.0), (0.5, 0.7, 0.1), DT, EDDIE_PROFILE)
    assert out[1] == 0.0
    assert abs(out[0]) <= 1.125 * DT + TOL


def test_config_rejects_limits_that_do_not_bracket_zero() -> None:
    bad = SmootherConfig(min_velocity=(0.1, 0.0, -2.5))
    assert bad.validate() is not None and "min_velocity[0]" in bad.validate()  # type: ignore[operator]


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    events=st.lists(st.tuples(twist, st.integers(1, 30)), min_size=1, max_size=15),
)
def test_shell_respects_limits_through_gaps_and_timeouts(
    events: list[tuple[tuple[float, float, float], int]],
) -> None:
    cfg = SmootherConfig(scale_velocities=True, velocity_timeout=0.5)
    s = VelocitySmoother(cfg)
    tick = 0
    prev: tuple[float, float, float] = (0.0, 0.0, 0.0)
    for target, gap_ticks in events:
        s.set_target(target, tick * NS // 20)
        for _ in range(gap_ticks):  # the controller may go quiet past the timeout
            tick += 1
            out = s.tick(tick * NS // 20)
            _within_limits(np.array(prev), np.array(out), cfg)
            prev = out
    # Left alone, it always ends at rest.
    for _ in range(200):
        tick += 1
        prev = s.tick(tick * NS // 20)
    assert prev == (0.0, 0.0, 0.0) and s.stopped


def test_eddie_profile_clamps_to_the_wheel_speed_limit() -> None:
    cfg = eddie_profile(max_wheel_speed=0.9)  # config/robots/eddie.yaml robot.max_wheel_speed
    assert cfg.max_velocity == (0.9, 0.0, 0.2)
    assert cfg.min_velocity == (-0.9, 0.0, -0.2)
    assert eddie_profile(max_wheel_speed=2.0).max_velocity[0] == 1.4  # never above the profile
    with pytest.raises(ValueError, match="max_wheel_speed"):
        eddie_profile(max_wheel_speed=0.0)
