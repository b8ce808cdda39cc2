"""Joystick teleop from recorded (type, code, value) event sequences; no evdev needed."""

from __future__ import annotations

import pytest

from nav.joystick import EV_ABS, EV_KEY, JoystickConfig, JoystickTeleop
from sensors.types import ConfigError

SYN = (0, 0, 0)
DEADMAN, START, ABS_X, ABS_Y = 310, 315, 0, 1


def test_without_the_deadman_the_sticks_do_nothing() -> None:
    joy = JoystickTeleop()
    assert joy.feed_all([(EV_ABS, ABS_Y, -32768), SYN]) == (0.0, 0.0)
    v, w = joy.feed_all([(EV_KEY, DEADMAN, 1), SYN])
    assert v == pytest.approx(0.4) and w == 0.0
    assert joy.feed_all([(EV_KEY, DEADMAN, 0), SYN]) == (0.0, 0.0)  # released: stop


def test_dead_zone_ramps_up_from_zero_at_its_edge() -> None:
    cfg = JoystickConfig(axis_min=-100, axis_max=100, dead_zone=0.2, max_linear=0.5)
    joy = JoystickTeleop(cfg)
    joy.feed(EV_KEY, DEADMAN, 1)
    speeds = []
    for raw in (0, -10, -20, -21, -60, -100):  # pushed up = forward
        joy.feed(EV_ABS, ABS_Y, raw)
        speeds.append(joy.twist[0])
    assert speeds[:3] == [0.0, 0.0, 0.0]  # inside the dead zone
    assert 0.0 < speeds[3] < 0.01  # just past the edge: barely moving, no jump
    assert speeds[4] == pytest.approx(0.5 * (0.6 - 0.2) / 0.8)
    assert speeds[5] == pytest.approx(0.5)
    joy.feed(EV_ABS, ABS_Y, 100)  # pulled back: reverse
    assert joy.twist[0] == pytest.approx(-0.5)


def test_configurable_axes_and_turn_sign() -> None:
    cfg = JoystickConfig(axis_linear=4, axis_angular=3, axis_min=0, axis_max=255, deadman_button=-1)
    joy = JoystickTeleop(cfg)
    v, w = joy.feed_all([(EV_ABS, 3, 0), (EV_ABS, 4, 128), (EV_ABS, ABS_Y, 0), SYN])
    assert v == 0.0 and w == pytest.approx(1.0)  # stick left: turn counter-clockwise


def test_mode_button_toggles_once_per_press() -> None:
    toggled = []
    joy = JoystickTeleop(on_toggle=lambda: toggled.append(1))
    joy.feed_all(
        [
            (EV_KEY, START, 1),
            (EV_KEY, START, 2),
            (EV_KEY, START, 0),
            SYN,
            (EV_KEY, START, 1),
            (EV_KEY, START, 0),
        ]
    )
    assert len(toggled) == 2 == joy.toggles


def test_bad_axis_range_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="range"):
        JoystickConfig(axis_min=10, axis_max=10)


def test_without_evdev_the_device_reader_says_what_to_install() -> None:
    pytest.importorskip("sys")
    try:
        import evdev  # noqa: F401

        pytest.skip("evdev is installed")
    except ImportError:
        pass
    from nav.joystick import read_device

    with pytest.raises(ConfigError, match="pip install"):
        next(read_device("/dev/input/event0"))


def test_a_recording_replays_with_its_timing_and_bad_lines_are_named(tmp_path) -> None:
    from nav.joystick import parse_events, read_device

    rec = tmp_path / "drive.events"
    rec.write_text("# t type code value\n0.0 1 310 1\n0.05 3 1 -32768\n0.1 0 0 0\n")
    joy = JoystickTeleop()
    t0 = __import__("time").monotonic()
    v, _ = joy.feed_all(read_device(f"replay:{rec}"))
    assert v == pytest.approx(0.4) and __import__("time").monotonic() - t0 >= 0.09
    with pytest.raises(ConfigError, match="x.events:2: expected SECONDS TYPE CODE VALUE"):
        parse_events("0 1 310 1\n0 1 310\n", "x.events")
    with pytest.raises(ConfigError, match="backwards"):
        parse_events("1 1 310 1\n0 1 310 0\n", "x.events")
