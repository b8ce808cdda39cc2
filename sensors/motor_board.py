"""One interface for the robot's motor boards, the device spec that names one, and the pieces
every driver shares (host watchdog, wheel split, encoder positions from RPM).

A :class:`MotorBoard` takes wheel speeds in m/s (or a body twist), gives its odometry input
(cumulative encoder positions stamped with ``time.monotonic_ns()``; boards that measure RPM
integrate it into positions at ``robot.ticks_per_revolution`` and also expose the raw
:class:`WheelRpm`), the battery voltage, ``stop()``, ``arm_failsafe()`` and ``diagnostics()``.
The live run, teleop and ``rgbdnav board`` use only this interface.

Device specs (``--board`` / ``rgbdnav board SPEC``)::

    eddie:/dev/ttyUSB0                    Parallax Eddie (a bare path or pyserial URL is Eddie)
    thunderborg:/dev/i2c-1@0x15           ThunderBorg on I2C bus 1, address 0x15; the tacho
                                          Arduino's port comes from thunderborg.tacho_port
    thunderborg:/dev/i2c-1@0x15,/dev/ttyUSB1   ... with the tacho port given here
    arduino-bridge:/dev/ttyACM0@57600     ROSArduinoBridge at 57600 baud (default: config)
    emulator:eddie | emulator:thunderborg | emulator:arduino-bridge   the built-in emulators
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from sensors.config import RobotConfig
from sensors.types import NS_PER_S, ConfigError, SensorError, WheelTicks

log = logging.getLogger(__name__)

BOARD_KINDS = ("eddie", "thunderborg", "arduino-bridge")
WATCHDOG_LEAD_S = 0.02  # [s] the host watchdog's stop leaves this long before the timeout
WATCHDOG_IDLE_WAIT_S = 0.05  # [s] longest wait before looking again (stop requests, feeds)
WATCHDOG_RETRY_S = 0.01  # [s] after a failed stop


class MotorBoardError(SensorError):
    """A motor board did not answer, or answered something unreadable."""


@dataclass(frozen=True)
class WheelRpm:
    """One tacho reading: wheel speeds [rev/min], signed (forward positive)."""

    stamp_ns: int  # [ns] time.monotonic_ns() when the reading arrived
    left: float
    right: float


@dataclass(frozen=True)
class DeviceSpec:
    kind: str  # one of BOARD_KINDS
    path: str  # serial port / URL, or /dev/i2c-N
    option: str | None = None  # "@..." part: I2C address or baud rate
    extra: str | None = None  # ",..." part: the ThunderBorg's tacho port
    emulator: bool = False


_SPEC = re.compile(r"(?P<path>[^@,]+)(?:@(?P<option>[^,]+))?(?:,(?P<extra>.+))?")


def parse_device_spec(spec: str) -> DeviceSpec:
    """``KIND:PATH[@OPTION][,EXTRA]``, ``emulator:KIND`` or a bare Eddie port; see the module
    docstring. Raises ConfigError with the expected forms."""
    if spec.startswith("emulator:"):
        kind = spec.split(":", 1)[1]
        if kind not in BOARD_KINDS:
            raise ConfigError(f"board {spec!r}: unknown emulator (valid: {', '.join(BOARD_KINDS)})")
        return DeviceSpec(kind, "", emulator=True)
    kind, sep, rest = spec.partition(":")
    if not sep or kind not in BOARD_KINDS or rest.startswith("//"):
        return DeviceSpec("eddie", spec)  # /dev/ttyUSB0, socket://..., loop://
    match = _SPEC.fullmatch(rest)
    if match is None:
        raise ConfigError(f"board {spec!r}: expected {kind}:PATH[@OPTION][,TACHO_PORT]")
    option, extra = match.group("option"), match.group("extra")
    if kind == "thunderborg":
        if not re.fullmatch(r"/dev/i2c-\d+", match.group("path")):
            raise ConfigError(f"board {spec!r}: expected thunderborg:/dev/i2c-N[@0xADDR]")
        if option is not None:
            try:
                if not 0x03 <= int(option, 0) <= 0x77:
                    raise ValueError
            except ValueError:
                raise ConfigError(
                    f"board {spec!r}: I2C address {option!r} is not 0x03..0x77"
                ) from None
    elif option is not None and not option.isdigit():
        raise ConfigError(f"board {spec!r}: baud rate {option!r} is not a number")
    if extra is not None and kind != "thunderborg":
        raise ConfigError(f"board {spec!r}: only thunderborg takes a second (tacho) port")
    return DeviceSpec(kind, match.group("path"), option, extra)


def split_twist(v: float, w: float, robot: RobotConfig) -> tuple[float, float]:
    """Body twist (v [m/s], w [rad/s], CCW positive) -> wheel speeds (left, right) [m/s]; both
    scaled down together above ``robot.max_wheel_speed`` (keeps the turning radius)."""
    if not (math.isfinite(v) and math.isfinite(w)):
        raise ConfigError(f"velocity must be finite, got v={v!r}, w={w!r}")
    left, right = v - 0.5 * w * robot.track_width, v + 0.5 * w * robot.track_width
    peak = max(abs(left), abs(right))
    if peak > robot.max_wheel_speed:
        left, right = left * robot.max_wheel_speed / peak, right * robot.max_wheel_speed / peak
    return left, right


class MotorBoard(ABC):
    """What the live run, teleop and ``rgbdnav board`` need from a motor board."""

    kind: str = ""
    url: str = ""
    robot_cfg: RobotConfig

    @abstractmethod
    def set_wheel_speeds(self, left: float, right: float) -> Any:
        """Drive each wheel at [m/s]; arms the host watchdog (stop without another call)."""

    def set_velocity(self, v: float, w: float) -> Any:
        """Drive the body twist (v [m/s], w [rad/s])."""
        return self.set_wheel_speeds(*split_twist(v, w, self.robot_cfg))

    @abstractmethod
    def ticks(self) -> WheelTicks:
        """Cumulative wheel positions (at ``robot.ticks_per_revolution``), stamped."""

    def probe(self) -> str:
        """One round trip to the board (timed by ``rgbdnav board``); returns what it was."""
        self.ticks()
        return "odometry read"

    def odometry_input(self) -> WheelTicks | WheelRpm:
        """The board's own odometry reading: encoder ticks, or RPM for tacho boards."""
        return self.ticks()

    @abstractmethod
    def battery_voltage(self) -> float:
        """[V]; raises MotorBoardError / BoardError when the board cannot tell."""

    @abstractmethod
    def stop(self) -> None:
        """Motors off now."""

    @abstractmethod
    def arm_failsafe(self, timeout_s: float) -> str:
        """Make the motors stop when the host goes quiet; returns what was armed."""

    @abstractmethod
    def diagnostics(self) -> dict[str, Any]:
        """Board name, firmware, link counters: what ``rgbdnav board`` and the summary show."""

    @abstractmethod
    def close(self) -> None:
        """Stop the motors if they may run, end threads, release the port."""

    def __enter__(self) -> MotorBoard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class HostWatchdog:
    """Calls ``on_timeout`` once when :meth:`feed` has not been called for ``timeout_s`` (armed
    by the first feed); retries when ``on_timeout`` raises SensorError. It fires
    :data:`WATCHDOG_LEAD_S` early, waiting for the exact instant rather than polling, so the
    stop has reached the board by ``timeout_s`` after the last command."""

    def __init__(self, timeout_s: float, on_timeout: Callable[[], None], name: str) -> None:
        self.timeout_s = timeout_s
        self.fire_after_s = max(timeout_s - WATCHDOG_LEAD_S, timeout_s / 2)
        self.on_timeout = on_timeout
        self.fired = 0
        self._last = 0.0
        self._armed = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def feed(self) -> None:
        with self._lock:
            self._last, self._armed = time.monotonic(), True

    def disarm(self) -> None:
        with self._lock:
            self._armed = False

    @property
    def armed(self) -> bool:
        return self._armed

    def _run(self) -> None:
        while True:
            with self._lock:
                armed, last = self._armed, self._last
            wait = (
                WATCHDOG_IDLE_WAIT_S if not armed else last + self.fire_after_s - time.monotonic()
            )
            if wait > 0:
                if self._stop.wait(min(wait, WATCHDOG_IDLE_WAIT_S)):
                    return
                continue
            try:
                self.on_timeout()
            except SensorError as err:
                log.warning("watchdog stop failed (will retry): %s", err)
                if self._stop.wait(WATCHDOG_RETRY_S):
                    return
                continue
            with self._lock:
                if self._last == last:  # no command came meanwhile
                    self._armed = False
                    self.fired += 1
            log.info("no wheel command for %.2f s: motors stopped", self.timeout_s)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()


class RpmIntegrator:
    """Tacho RPM -> cumulative wheel positions, as an encoder board would report them.

    Each new reading's RPM is held since the previous reading (trapezoid over the interval);
    positions are kept fractional and reported floored, so no travel is lost to rounding. The
    pose and its covariance are wheel odometry's job (:class:`slam.diff_drive.WheelOdometry`
    on these counts), as for any encoder board: sensors import nothing of ours.
    """

    def __init__(self, robot: RobotConfig) -> None:
        self.robot = robot
        self.pos = np.zeros(2)  # [positions] left, right
        self.last: WheelRpm | None = None

    def update(self, rpm: WheelRpm) -> WheelTicks:
        if self.last is not None and rpm.stamp_ns > self.last.stamp_ns:
            dt = (rpm.stamp_ns - self.last.stamp_ns) / NS_PER_S
            mean_rpm = 0.5 * (np.array([rpm.left, rpm.right]) + [self.last.left, self.last.right])
            self.pos += mean_rpm / 60.0 * dt * self.robot.ticks_per_revolution  # [positions]
        if self.last is None or rpm.stamp_ns > self.last.stamp_ns:
            self.last = rpm
        return WheelTicks(rpm.stamp_ns, int(math.floor(self.pos[0])), int(math.floor(self.pos[1])))
