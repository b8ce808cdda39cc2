"""Software boards for tests and ``rgbdnav board --emulator``: the ThunderBorg on a fake SMBus
with motor dynamics plus its Arduino tacho on a pty, and the ROSArduinoBridge firmware on a pty.

ThunderBorg model: each wheel's speed [m/s] follows its motor power with a first-order lag
(``tau_s``) toward ``true_slope * |power| + y_intercept`` (0 below ``inertia_level``), where the
true slopes differ from the calibration by ``gain_error`` (left, right), so the host PID has
work to do. The board's failsafe, when on, turns both motors off 0.25 s after the last I2C
write. The tacho thread prints ``tacho L R`` [RPM] at ``tacho_rate`` on a raw pty.

ROSArduinoBridge model (the firmware's parser: a command letter, space-separated arguments,
CR ends a command; replies end in CR LF): ``e`` -> ``L R``, ``m L R`` -> ``OK`` (targets in
ticks per PID frame at ``pid_rate``; both 0 stops and resets the PID), ``r`` -> ``OK``, ``u
Kp:Kd:Ki:Ko`` -> ``OK``, ``b`` -> the baud rate, anything else ``Invalid Command``. The wheels
reach the target ticks per frame with a first-order lag; AUTO_STOP_INTERVAL stops them when no
``m`` came for ``auto_stop_interval``.
"""

from __future__ import annotations

import ctypes
import math
import os
import select
import threading
import time
import tty
from collections.abc import Callable

import numpy as np

from sensors.config import BridgeConfig, RobotConfig, ThunderBorgConfig
from sensors.thunderborg import (
    ALL_OFF,
    ANALOG_MAX,
    BOARD_FAILSAFE_S,
    GET_A,
    GET_B,
    GET_BATT_VOLT,
    GET_FAILSAFE,
    GET_ID,
    I2C_ID_THUNDERBORG,
    I2C_MAX_LEN,
    PWM_MAX,
    SET_A_FWD,
    SET_A_REV,
    SET_B_FWD,
    SET_B_REV,
    SET_FAILSAFE,
    SET_LED_BATT_MON,
    SET_LEDS,
    VALUE_FWD,
    VALUE_REV,
    VOLTAGE_PIN_MAX,
)

POLL_S = 0.01  # [s]
I2C_M_RD = 0x0001


class _Pty:
    """A raw pseudo-terminal served by one thread: ``on_bytes`` gets what the host wrote and
    returns the reply; ``periodic`` (if any) is called every ``period_s`` and its bytes sent."""

    def __init__(
        self,
        on_bytes: Callable[[bytes], bytes],
        periodic: Callable[[], bytes] | None = None,
        period_s: float = 0.05,
    ) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.on_bytes, self.periodic, self.period_s = on_bytes, periodic, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="emulator-pty", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], POLL_S)
            out = b""
            if ready:
                try:
                    out += self.on_bytes(os.read(self.master, 4096))
                except OSError:
                    self._stop.wait(POLL_S)
            if self.periodic is not None and time.monotonic() >= next_t:
                next_t += self.period_s
                out += self.periodic()
            while out:
                try:
                    out = out[os.write(self.master, out) :]
                except OSError:
                    break

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        os.close(self.master)
        os.close(self.slave)


# --- ThunderBorg ------------------------------------------------------------------------------


class ThunderBorgEmulator:
    """The board's registers and two motors; :meth:`bus` gives an smbus2-like bus object."""

    def __init__(
        self,
        cfg: ThunderBorgConfig | None = None,
        robot: RobotConfig | None = None,
        *,
        battery_v: float = 12.4,
        tau_s: float = 0.12,
        gain_error: tuple[float, float] = (-0.08, 0.05),
        tacho_rate: float = 20.0,
        time_source: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg or ThunderBorgConfig()
        self.robot = robot or RobotConfig()
        self.battery_v, self.tau_s, self.tacho_rate = battery_v, tau_s, tacho_rate
        self.true_slope = np.array([self.cfg.slope * (1 + g) for g in gain_error])
        self.time_source = time_source
        self._lock = threading.RLock()
        self.power = np.zeros(2)  # motor 1 (A), motor 2 (B) in [-1, 1]
        self.speed = np.zeros(2)  # [m/s] wheel on motor 1, motor 2 (mounting applied later)
        self.travel = np.zeros(2)  # [m]
        self._t = time_source()
        self._last_write = self._t
        self.failsafe = False
        self.failsafe_trips = 0
        self.led = (0, 0, 0)
        self.led_battery_monitor = True
        self.writes = 0
        self._reply = [0] * I2C_MAX_LEN
        self._tacho: _Pty | None = None
        self.tacho_silent = False  # fault injection: the Arduino stops printing

    # model
    def _steady(self, power: np.ndarray) -> np.ndarray:
        s = self.true_slope * np.abs(power) + self.cfg.y_intercept
        s = np.where((np.abs(power) >= self.cfg.inertia_level) & (s > 0), s, 0.0)
        return np.copysign(s, power)

    def _advance(self, now: float) -> None:
        if self.failsafe and any(self.power) and now - self._last_write > BOARD_FAILSAFE_S:
            self._integrate(self._last_write + BOARD_FAILSAFE_S)
            self.power[:] = 0.0
            self.failsafe_trips += 1
        self._integrate(now)

    def _integrate(self, now: float) -> None:
        while self._t < now:
            dt = min(0.005, now - self._t)
            target = self._steady(self.power)
            new = target + (self.speed - target) * math.exp(-dt / self.tau_s)
            self.travel += 0.5 * (self.speed + new) * dt
            self.speed = new
            self._t += dt

    def wheel_speeds(self) -> tuple[float, float]:
        """(left, right) [m/s] of the robot, after the motor mapping and mounting."""
        with self._lock:
            self._advance(self.time_source())
            left_k = self.cfg.left_motor - 1
            sign = -1.0 if self.cfg.invert_right else 1.0
            return float(self.speed[left_k]), float(sign * self.speed[1 - left_k])

    def wheel_travel(self) -> tuple[float, float]:
        with self._lock:
            self._advance(self.time_source())
            left_k = self.cfg.left_motor - 1
            sign = -1.0 if self.cfg.invert_right else 1.0
            return float(self.travel[left_k]), float(sign * self.travel[1 - left_k])

    def wheel_positions(self) -> tuple[float, float]:
        """Wheel travel (left, right) in encoder positions of ``robot`` (for the simulator)."""
        left, right = self.wheel_travel()
        return left / self.robot.metres_per_tick, right / self.robot.metres_per_tick

    # the I2C side
    def write(self, data: list[int]) -> None:
        if not data:
            return
        with self._lock:
            now = self.time_source()
            self._advance(now)
            self._last_write = now
            self.writes += 1
            cmd, args = data[0], data[1:]
            arg = args[0] if args else 0
            motor = {SET_A_FWD: (0, 1), SET_A_REV: (0, -1), SET_B_FWD: (1, 1), SET_B_REV: (1, -1)}
            if cmd in motor:
                k, sign = motor[cmd]
                self.power[k] = sign * min(arg, PWM_MAX) / PWM_MAX
                self._reply = [cmd] + [0] * (I2C_MAX_LEN - 1)
            elif cmd == ALL_OFF:
                self.power[:] = 0.0
            elif cmd == SET_FAILSAFE:
                self.failsafe = bool(arg)
            elif cmd == SET_LEDS and len(args) >= 3:
                self.led = (args[0], args[1], args[2])
            elif cmd == SET_LED_BATT_MON:
                self.led_battery_monitor = bool(arg)
            reply = {GET_ID: [I2C_ID_THUNDERBORG], GET_FAILSAFE: [int(self.failsafe)]}.get(cmd)
            if cmd in (GET_A, GET_B):
                p = self.power[0 if cmd == GET_A else 1]
                reply = [VALUE_REV if p < 0 else VALUE_FWD, int(round(abs(p) * PWM_MAX))]
            elif cmd == GET_BATT_VOLT:
                raw = int(round(self.battery_v / VOLTAGE_PIN_MAX * ANALOG_MAX))
                reply = [raw >> 8, raw & 0xFF]
            if reply is not None:
                self._reply = ([cmd] + reply + [0] * I2C_MAX_LEN)[:I2C_MAX_LEN]

    def read(self, length: int) -> list[int]:
        with self._lock:
            return (self._reply + [0] * length)[:length]

    def bus(self) -> FakeSMBus:
        return FakeSMBus(self)

    # the tacho Arduino
    def serve_tacho(self) -> str:
        circumference = math.pi * self.robot.wheel_diameter

        def line() -> bytes:
            if self.tacho_silent:
                return b""
            left, right = self.wheel_speeds()
            return b"tacho %.2f %.2f\r\n" % (left / circumference * 60, right / circumference * 60)

        self._tacho = _Pty(lambda data: b"", line, 1.0 / self.tacho_rate)
        return self._tacho.path

    def close(self) -> None:
        if self._tacho is not None:
            self._tacho.close()
            self._tacho = None


class FakeSMBus:
    """``smbus2.SMBus`` as far as the driver goes: ``i2c_rdwr`` with write and read messages."""

    def __init__(self, emulator: ThunderBorgEmulator, address: int = I2C_ID_THUNDERBORG) -> None:
        self.emulator, self.address = emulator, address
        self.closed = False

    def i2c_rdwr(self, *msgs: object) -> None:
        for msg in msgs:
            if self.closed or msg.addr != self.address:  # type: ignore[attr-defined]
                raise OSError(121, "Remote I/O error")  # what an absent device gives
            if msg.flags & I2C_M_RD:  # type: ignore[attr-defined]
                data = bytes(self.emulator.read(msg.len))  # type: ignore[attr-defined]
                ctypes.memmove(msg.buf, data, len(data))  # type: ignore[attr-defined]
            else:
                self.emulator.write(list(msg))  # type: ignore[call-overload]

    def close(self) -> None:
        self.closed = True


# --- ROSArduinoBridge ---------------------------------------------------------------------------


class BridgeEmulator:
    """ROSArduinoBridge firmware with two motors and encoders; see the module docstring."""

    def __init__(
        self,
        cfg: BridgeConfig | None = None,
        *,
        tau_s: float = 0.1,
        time_source: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg or BridgeConfig()
        self.tau_s = tau_s
        self.time_source = time_source
        self._lock = threading.RLock()
        self.target = np.zeros(2)  # [ticks per frame]
        self.rate = np.zeros(2)  # [ticks per frame] what the wheels do now
        self.counts = np.zeros(2)  # [ticks] fractional
        self.pid = (20, 12, 0, 50)
        self.moving = False
        self.auto_stops = 0
        self._t = time_source()
        self._last_motor_command = self._t
        self._buf = bytearray()
        self._pty: _Pty | None = None

    def _advance(self, now: float) -> None:
        if self.moving and now - self._last_motor_command > self.cfg.auto_stop_interval:
            self._integrate(self._last_motor_command + self.cfg.auto_stop_interval)
            self.target[:] = 0.0
            self.rate[:] = 0.0  # setMotorSpeeds(0, 0): power cut
            self.moving = False
            self.auto_stops += 1
        self._integrate(now)

    def _integrate(self, now: float) -> None:
        while self._t < now:
            dt = min(0.005, now - self._t)
            new = self.target + (self.rate - self.target) * math.exp(-dt / self.tau_s)
            self.counts += 0.5 * (self.rate + new) * self.cfg.pid_rate * dt
            self.rate = new
            self._t += dt

    def wheel_rates(self) -> tuple[float, float]:
        """Current wheel speeds [ticks per PID frame]."""
        with self._lock:
            self._advance(self.time_source())
            return float(self.rate[0]), float(self.rate[1])

    def wheel_positions(self) -> tuple[float, float]:
        """Wheel travel (left, right) [ticks], not floored (for the simulator)."""
        with self._lock:
            self._advance(self.time_source())
            return float(self.counts[0]), float(self.counts[1])

    def feed(self, data: bytes) -> bytes:
        out = b""
        for byte in data:
            if byte == 13:
                out += self._execute(bytes(self._buf))
                self._buf.clear()
            elif byte != 10:
                self._buf.append(byte)
        return out

    def _execute(self, line: bytes) -> bytes:
        words = line.split(b" ")
        cmd = words[0][:1] if words and words[0] else b""
        args = words[1:]

        def arg(i: int) -> int:
            try:  # atoi(): leading digits, 0 when none
                word = args[i].decode("ascii", "replace")
                num = ""
                for ch in word:
                    if ch.isdigit() or (ch == "-" and not num):
                        num += ch
                    else:
                        break
                return int(num) if num.strip("-") else 0
            except IndexError:
                return 0

        with self._lock:
            now = self.time_source()
            self._advance(now)
            if cmd == b"e":
                return b"%d %d\r\n" % (math.floor(self.counts[0]), math.floor(self.counts[1]))
            if cmd == b"m":
                self._last_motor_command = now
                self.target[:] = (arg(0), arg(1))
                self.moving = bool(arg(0) or arg(1))
                if not self.moving:
                    self.rate[:] = 0.0
                return b"OK\r\n"
            if cmd == b"r":
                self.counts[:] = 0.0
                return b"OK\r\n"
            if cmd == b"u":
                gains = (args[0] if args else b"").split(b":")
                self.pid = tuple(int(g) if g.lstrip(b"-").isdigit() else 0 for g in gains[:4])  # type: ignore[assignment]
                return b"OK\r\n"
            if cmd == b"b":
                return b"%d\r\n" % self.cfg.baudrate
            return b"Invalid Command\r\n"

    def serve_pty(self) -> str:
        self._pty = _Pty(self.feed)
        return self._pty.path

    def close(self) -> None:
        if self._pty is not None:
            self._pty.close()
            self._pty = None
