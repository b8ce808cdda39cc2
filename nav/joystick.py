"""Joystick teleop from Linux input events (evdev): configurable axes, a dead zone whose output
ramps up from zero at its edge, a deadman button, a button toggling manual / auto.

The logic (:class:`JoystickTeleop`) takes ``(type, code, value)`` events as evdev gives them
(EV_KEY 1, EV_ABS 3), so it is tested with recorded sequences and needs no evdev; only
:func:`read_device` imports evdev (optional extra ``joystick``). Axis values are normalised
from ``[axis_min, axis_max]`` to [-1, 1]; inside ``dead_zone`` the speed is 0, past it the
speed rises linearly from 0 at the edge to the maximum at full deflection
(:func:`nav.teleop.joystick_speed` with ``min_speed`` 0). Without the deadman held the output is
(0, 0) whatever the sticks say. Defaults: left stick (ABS_Y forward, pushed up is negative;
ABS_X turn, left is negative), deadman BTN_TL (310), mode BTN_START (315). ``replay:FILE``
plays a recorded sequence instead of a device (the joystick's emulator, for demos and tests).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from nav.teleop import JoystickAxis, joystick_speed
from sensors.config import param
from sensors.types import ConfigError

EV_KEY, EV_ABS = 1, 3


@dataclass(frozen=True)
class JoystickConfig:
    """Joystick teleop (evdev): axes, dead zone, speeds and buttons."""

    axis_linear: int = param(1, ge=0, doc="EV_ABS code driving forward/back (ABS_Y)")
    axis_angular: int = param(0, ge=0, doc="EV_ABS code turning (ABS_X)")
    invert_linear: bool = param(True, doc="stick up reads negative on most pads")
    invert_angular: bool = param(True, doc="stick left reads negative; w is CCW positive")
    axis_min: int = param(-32768, doc="raw axis value at full deflection one way")
    axis_max: int = param(32767, doc="... and the other way")
    dead_zone: float = param(0.1, ge=0.0, lt=1.0, doc="of full deflection: output 0 inside")
    max_linear: float = param(0.4, unit="m/s", gt=0.0, doc="at full deflection")
    max_angular: float = param(1.0, unit="rad/s", gt=0.0, doc="at full deflection")
    deadman_button: int = param(
        310, ge=-1, doc="EV_KEY code to hold while driving (BTN_TL); -1: none"
    )
    mode_button: int = param(315, ge=0, doc="EV_KEY code toggling manual/auto (BTN_START)")

    def __post_init__(self) -> None:
        if self.axis_max <= self.axis_min:
            raise ConfigError(f"joystick axis range [{self.axis_min}, {self.axis_max}] is empty")

    @property
    def axes(self) -> tuple[JoystickAxis, JoystickAxis]:
        return (
            JoystickAxis(self.dead_zone, 0.0, self.max_linear),
            JoystickAxis(self.dead_zone, 0.0, self.max_angular),
        )


class JoystickTeleop:
    """Feed events; read :attr:`twist`; ``on_toggle`` is called on each mode-button press."""

    def __init__(
        self, cfg: JoystickConfig | None = None, on_toggle: Callable[[], None] | None = None
    ) -> None:
        self.cfg = cfg or JoystickConfig()
        self.on_toggle = on_toggle
        self.values = {self.cfg.axis_linear: 0.0, self.cfg.axis_angular: 0.0}  # [-1, 1]
        self.deadman = self.cfg.deadman_button < 0  # no deadman: always enabled
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


MAX_REPLAY_S = 86400.0  # a day: longer is a typo, not a recording


def parse_events(text: str, source: str) -> list[tuple[float, int, int, int]]:
    """A recorded event file: one ``SECONDS TYPE CODE VALUE`` per line (``#`` comments), the
    times from the start, non-decreasing. ConfigError naming the line otherwise."""
    events: list[tuple[float, int, int, int]] = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            t, ev_type, code, value = line.split()
            event = (float(t), int(ev_type), int(code), int(value))
        except ValueError:
            raise ConfigError(
                f"{source}:{n}: expected SECONDS TYPE CODE VALUE, got {line!r}"
            ) from None
        if not 0.0 <= event[0] <= MAX_REPLAY_S:
            # NaN slips past the "backwards" check and inf sleeps for ever: both refused.
            raise ConfigError(f"{source}:{n}: time {t!r} is not 0..{MAX_REPLAY_S:g} s")
        if not all(-(2**31) <= v < 2**31 for v in event[1:]):
            raise ConfigError(f"{source}:{n}: TYPE CODE VALUE must fit a 32-bit input event")
        if events and event[0] < events[-1][0]:
            raise ConfigError(f"{source}:{n}: time goes backwards")
        events.append(event)
    return events


def replay(
    events: list[tuple[float, int, int, int]], sleep: Callable[[float], None] = time.sleep
) -> Iterator[tuple[int, int, int]]:
    """A recorded sequence with its timing: the joystick's stand-in for a test or a demo."""
    start = time.monotonic()
    for t, ev_type, code, value in events:
        sleep(max(0.0, start + t - time.monotonic()))
        yield ev_type, code, value


def read_device(path: str) -> Iterator[tuple[int, int, int]]:
    """(type, code, value) events from ``/dev/input/eventN`` (needs the ``joystick`` extra), or
    from a recording, ``replay:FILE`` (see :func:`parse_events`)."""
    if path.startswith("replay:"):
        name = path.split(":", 1)[1]
        try:
            text = open(name, encoding="utf-8").read()
        except OSError as err:
            raise ConfigError(f"cannot read joystick recording {name}: {err}") from err
        yield from replay(parse_events(text, name))
        return
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
