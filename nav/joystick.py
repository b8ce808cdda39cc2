"""Joystick teleop from Linux input events (evdev): configurable axes, a dead zone whose output
ramps up from zero at its edge, a deadman button, a button toggling manual / auto.

The logic (:class:`JoystickTeleop`) takes ``(type, code, value)`` events as evdev gives them
(EV_KEY 1, EV_ABS 3), so it is tested with recorded sequences and needs no evdev; only
:func:`read_device` imports evdev (optional extra ``joystick``). Axis values are normalised
from ``[axis_min, axis_max]`` to [-1, 1]; inside ``dead_zone`` the speed is 0, past it the
speed rises linearly from 0 at the edge to the maximum at full deflection
(:func:`nav.teleop.joystick_speed` with ``min_speed`` 0). Without the deadman held the output is
(0, 0) whatever the sticks say. Defaults: left stick (ABS_Y forward, pushed up is negative;
ABS_X turn, left is negative), deadman BTN_TL (310), mode BTN_START (315).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

from nav.teleop import JoystickAxis, joystick_speed
from sensors.types import ConfigError

EV_KEY, EV_ABS = 1, 3


@dataclass(frozen=True)
class JoystickConfig:
    axis_linear: int = 1  # ABS_Y
    axis_angular: int = 0  # ABS_X
    invert_linear: bool = True  # stick up reads negative
    invert_angular: bool = True  # stick left reads negative; w is counter-clockwise positive
    axis_min: int = -32768
    axis_max: int = 32767
    dead_zone: float = 0.1
    max_linear: float = 0.4  # [m/s]
    max_angular: float = 1.0  # [rad/s]
    deadman_button: int | None = 310  # BTN_TL; None: no deadman
    mode_button: int = 315  # BTN_START
    axes: tuple[JoystickAxis, JoystickAxis] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.axis_max <= self.axis_min:
            raise ConfigError(f"joystick axis range [{self.axis_min}, {self.axis_max}] is empty")
        object.__setattr__(
            self,
            "axes",
            (
                JoystickAxis(self.dead_zone, 0.0, self.max_linear),
                JoystickAxis(self.dead_zone, 0.0, self.max_angular),
            ),
        )


class JoystickTeleop:
    """Feed events; read :attr:`twist`; ``on_toggle`` is called on each mode-button press."""

    def __init__(
        self, cfg: JoystickConfig | None = None, on_toggle: Callable[[], None] | None = None
    ) -> None:
        self.cfg = cfg or JoystickConfig()
        self.on_toggle = on_toggle
        self.values = {self.cfg.axis_linear: 0.0, self.cfg.axis_angular: 0.0}  # [-1, 1]
        self.deadman = self.cfg.deadman_button is None
        self.toggles = 0

    def normalise(self, raw: int) -> float:
        lo, hi = self.cfg.axis_min, self.cfg.axis_max
        return max(-1.0, min(1.0, 2.0 * (raw - lo) / (hi - lo) - 1.0))

    def feed(self, ev_type: int, code: int, value: int) -> None:
        if ev_type == EV_ABS and code in self.values:
            self.values[code] = self.normalise(value)
        elif ev_type == EV_KEY and code == self.cfg.deadman_button:
            self.deadman = value != 0  # 1 press, 2 autorepeat, 0 release
        elif ev_type == EV_KEY and code == self.cfg.mode_button and value == 1:
            self.toggles += 1
            if self.on_toggle is not None:
                self.on_toggle()

    def feed_all(self, events: Iterable[tuple[int, int, int]]) -> tuple[float, float]:
        for ev in events:
            self.feed(*ev)
        return self.twist

    @property
    def twist(self) -> tuple[float, float]:
        """(v [m/s], w [rad/s]) now; (0, 0) without the deadman."""
        if not self.deadman:
            return 0.0, 0.0
        fwd = self.values[self.cfg.axis_linear] * (-1 if self.cfg.invert_linear else 1)
        turn = self.values[self.cfg.axis_angular] * (-1 if self.cfg.invert_angular else 1)
        lin, ang = self.cfg.axes
        return joystick_speed(fwd, lin) + 0.0, joystick_speed(turn, ang) + 0.0


def read_device(path: str) -> Iterator[tuple[int, int, int]]:
    """(type, code, value) events from ``/dev/input/eventN`` (needs the ``joystick`` extra)."""
    try:
        from evdev import InputDevice
    except ImportError:
        raise ConfigError("joystick teleop needs evdev: pip install 'rgbdnav[joystick]'") from None
    try:
        device = InputDevice(path)
    except OSError as err:
        raise ConfigError(f"cannot open joystick {path}: {err}") from err
    for event in device.read_loop():
        yield event.type, event.code, event.value
