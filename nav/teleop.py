"""Manual driving: teleop_twist_keyboard's key map and a joystick axis mapping with a dead zone.

Keyboard (ros-teleop/teleop_twist_keyboard, holonomic keys not included); (x, th) is the sign
of (v, w), w counter-clockwise positive::

    u (1, 1)    i (1, 0)    o (1, -1)
    j (0, 1)    k stop      l (0, -1)
    m (-1, -1)  , (-1, 0)   . (-1, 1)

``q``/``z`` scale both speeds by 1.1 / 0.9, ``w``/``x`` only the linear one, ``e``/``c`` only the
angular one; any other key stops (as ``k``). Defaults: speed 0.5 m/s, turn 1.0 rad/s.

Joystick: an axis value in [-1, 1] inside ``dead_zone`` gives 0; past it the speed starts at
``min_speed`` (not at 0) and rises linearly to ``max_speed`` at full deflection. This is the
EaseRobot fix: a plain ``value * max_speed`` never commands less than the motors' stall speed,
and a plain dead zone jumps from 0 to ``dead_zone * max_speed``; with slope
``(max - min) / (1 - dead_zone)`` and intercept ``min - slope * dead_zone`` the first value past
the dead zone maps to exactly ``min_speed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from sensors.types import ConfigError

# key -> (linear sign, angular sign), teleop_twist_keyboard's moveBindings (x, th)
MOVE_BINDINGS: dict[str, tuple[int, int]] = {
    "i": (1, 0),
    "o": (1, -1),
    "j": (0, 1),
    "l": (0, -1),
    "u": (1, 1),
    ",": (-1, 0),
    ".": (-1, 1),
    "m": (-1, -1),
}
# key -> (linear factor, angular factor), speedBindings
SPEED_BINDINGS: dict[str, tuple[float, float]] = {
    "q": (1.1, 1.1),
    "z": (0.9, 0.9),
    "w": (1.1, 1.0),
    "x": (0.9, 1.0),
    "e": (1.0, 1.1),
    "c": (1.0, 0.9),
}


@dataclass(frozen=True)
class TeleopState:
    """The keyboard's current speeds and the last motion key's direction."""

    speed: float = 0.5  # [m/s] teleop_twist_keyboard default
    turn: float = 1.0  # [rad/s]
    x: int = 0  # -1, 0, 1
    th: int = 0
    speed_limit: float = 1000.0  # [m/s] the tool's speed_limit parameter
    turn_limit: float = 1000.0  # [rad/s]


def teleop_key(key: str, state: TeleopState) -> tuple[tuple[float, float], TeleopState]:
    """One key press -> ((v [m/s], w [rad/s]), new state), as teleop_twist_keyboard publishes.

    A speed key keeps the current direction and rescales it (clamped to the limits); any key
    that is neither a move nor a speed key stops the robot.
    """
    if key in MOVE_BINDINGS:
        x, th = MOVE_BINDINGS[key]
        state = replace(state, x=x, th=th)
    elif key in SPEED_BINDINGS:
        fs, ft = SPEED_BINDINGS[key]
        state = replace(
            state,
            speed=min(state.speed_limit, state.speed * fs),
            turn=min(state.turn_limit, state.turn * ft),
        )
    else:
        state = replace(state, x=0, th=0)
    return (state.x * state.speed, state.th * state.turn), state


@dataclass(frozen=True)
class JoystickAxis:
    """One axis' mapping: |value| <= dead_zone -> 0, else min_speed .. max_speed."""

    dead_zone: float = 0.1  # [-] of full deflection
    min_speed: float = 0.05  # [m/s or rad/s] at the first value past the dead zone
    max_speed: float = 0.5  # [m/s or rad/s] at full deflection

    def __post_init__(self) -> None:
        if not 0.0 <= self.dead_zone < 1.0:
            raise ConfigError(f"joystick dead_zone must be in [0, 1), got {self.dead_zone}")
        if not 0.0 <= self.min_speed <= self.max_speed:
            raise ConfigError(
                f"joystick speeds need 0 <= min_speed <= max_speed, got "
                f"{self.min_speed} and {self.max_speed}"
            )

    @property
    def slope(self) -> float:
        return (self.max_speed - self.min_speed) / (1.0 - self.dead_zone)

    @property
    def intercept(self) -> float:
        return self.min_speed - self.slope * self.dead_zone


def joystick_speed(value: float, axis: JoystickAxis) -> float:
    """Axis value in [-1, 1] (clamped) -> signed speed."""
    if not math.isfinite(value):
        raise ConfigError(f"joystick axis value must be finite, got {value}")
    a = min(abs(value), 1.0)
    if a <= axis.dead_zone:
        return 0.0
    return math.copysign(axis.slope * a + axis.intercept, value)


def joystick_twist(
    forward: float, turn: float, linear: JoystickAxis, angular: JoystickAxis
) -> tuple[float, float]:
    """Stick deflections (forward, left-turn) -> (v [m/s], w [rad/s])."""
    return joystick_speed(forward, linear), joystick_speed(turn, angular)


__all__ = [
    "MOVE_BINDINGS",
    "SPEED_BINDINGS",
    "JoystickAxis",
    "TeleopState",
    "joystick_speed",
    "joystick_twist",
    "teleop_key",
]
