"""teleop_twist_keyboard's keys as a pure function, and the joystick dead zone that starts at the
minimum speed (the EaseRobot slope/intercept fix)."""

from __future__ import annotations

import math

import pytest

from nav.teleop import JoystickAxis, TeleopState, joystick_speed, joystick_twist, teleop_key
from sensors.types import ConfigError


@pytest.mark.parametrize(
    ("key", "twist"),
    [
        ("u", (0.5, 1.0)),
        ("i", (0.5, 0.0)),
        ("o", (0.5, -1.0)),
        ("j", (0.0, 1.0)),
        ("k", (0.0, 0.0)),
        ("l", (0.0, -1.0)),
        ("m", (-0.5, -1.0)),
        (",", (-0.5, 0.0)),
        (".", (-0.5, 1.0)),
    ],
)
def test_motion_keys_map_like_teleop_twist_keyboard(key: str, twist: tuple) -> None:
    out, _ = teleop_key(key, TeleopState())
    assert out == twist


def test_speed_keys_rescale_the_current_motion() -> None:
    _, s = teleop_key("u", TeleopState())
    (v, w), s = teleop_key("q", s)  # both x1.1, still moving forward-left
    assert (v, w) == pytest.approx((0.55, 1.1))
    (v, w), s = teleop_key("x", s)  # linear x0.9
    assert (v, w) == pytest.approx((0.495, 1.1))
    (v, w), s = teleop_key("c", s)  # angular x0.9
    assert (v, w) == pytest.approx((0.495, 0.99))
    for key, factor in (("w", (1.1, 1.0)), ("e", (1.0, 1.1)), ("z", (0.9, 0.9))):
        (v2, w2), s = teleop_key(key, s)
        assert (v2, w2) == pytest.approx((v * factor[0], w * factor[1]))
        v, w = v2, w2


def test_any_other_key_stops_but_keeps_the_speeds() -> None:
    _, s = teleop_key("i", TeleopState(speed=0.3))
    out, s = teleop_key("?", s)
    assert out == (0.0, 0.0)
    assert teleop_key("i", s)[0] == (0.3, 0.0)


def test_speed_keys_respect_the_limits() -> None:
    s = TeleopState(speed=0.95, turn=1.0, speed_limit=1.0, turn_limit=1.05)
    _, s = teleop_key("q", s)
    assert (s.speed, s.turn) == (1.0, 1.05)


def test_joystick_dead_zone_gives_zero_and_the_first_value_past_it_the_minimum_speed() -> None:
    axis = JoystickAxis(dead_zone=0.2, min_speed=0.1, max_speed=0.6)
    assert joystick_speed(0.2, axis) == 0.0
    assert joystick_speed(-0.15, axis) == 0.0
    assert joystick_speed(0.2 + 1e-9, axis) == pytest.approx(0.1, abs=1e-8)
    assert joystick_speed(-(0.2 + 1e-9), axis) == pytest.approx(-0.1, abs=1e-8)
    assert joystick_speed(1.0, axis) == pytest.approx(0.6)
    assert joystick_speed(-1.7, axis) == pytest.approx(-0.6)  # clamped deflection
    assert joystick_speed(0.6, axis) == pytest.approx(0.1 + 0.5 * 0.4 / 0.8)  # linear between
    assert axis.slope == pytest.approx(0.625) and axis.intercept == pytest.approx(-0.025)


def test_joystick_twist_maps_both_axes() -> None:
    lin = JoystickAxis(0.1, 0.05, 0.5)
    ang = JoystickAxis(0.1, 0.2, 1.0)
    assert joystick_twist(1.0, -1.0, lin, ang) == pytest.approx((0.5, -1.0))
    assert joystick_twist(0.05, 0.0, lin, ang) == (0.0, 0.0)


def test_bad_joystick_settings_are_refused() -> None:
    with pytest.raises(ConfigError, match="dead_zone"):
        JoystickAxis(dead_zone=1.0)
    with pytest.raises(ConfigError, match="min_speed <= max_speed"):
        JoystickAxis(min_speed=0.6, max_speed=0.5)
    with pytest.raises(ConfigError, match="finite"):
        joystick_speed(math.nan, JoystickAxis())
