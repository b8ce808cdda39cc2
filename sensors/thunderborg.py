"""PiBorg ThunderBorg on I2C plus an Arduino tacho on serial (the EaseRobot drive), host PID.

I2C protocol (PiBorg's ThunderBorg library, read for this; address 0x15 by default): a command
is one write ``[command, data...]``; a query is the write ``[command]`` then a 6-byte read whose
first byte echoes the command (the library retries up to 3 times when it does not). Motor
power is a byte 0..255 (PWM_MAX) with the direction in the command: SET_A_FWD 8 / SET_A_REV 9
(motor 1), SET_B_FWD 11 / SET_B_REV 12 (motor 2); ALL_OFF 14; SET_FAILSAFE 19 / GET_FAILSAFE 20
(the board turns the motors off unless commanded at least every 1/4 s); GET_BATT_VOLT 21
(``(b1 << 8 | b2) / 0x3FF * 36.3`` V); SET_LEDS 5 (r, g, b bytes), SET_LED_BATT_MON 6 (LEDs
show the battery when on, so it is switched off to show our state); GET_ID 0x99 (b1 = 0x15).

Tacho: the Arduino prints one line per reading, ``tacho <lwheelrpm> <rwheelrpm>\\r\\n``
(signed decimal RPM, forward positive; EaseRobot's ``tacho`` message as text).

Host side (EaseRobot's defaults): per wheel a PID (p 0.5, i 0.9, d 0.006) on the speed error
[m/s] corrects the target; ``speed = slope * power + y_intercept`` (0.649776, -0.0788956) is
inverted to the motor power; below ``inertia_level`` the motors cannot move the robot and get 0.
The loop runs at ``pid_rate`` (> 4 Hz, so it also feeds the board's 250 ms failsafe). The host
watchdog zeroes the target when no wheel command came for ``board.watchdog_timeout``; a host
that dies leaves the board's failsafe to stop the motors. Battery below ``battery_warn`` logs a
warning (LED orange), below ``battery_stop`` the motors are refused (LED red). LED: blue idle,
green driving, orange low battery, red stopped for the battery, magenta tacho lost (no RPM
for ``rpm_timeout`` while driving closed loop: the motors stop rather than drive blind).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Protocol

import serial

from sensors.config import BoardConfig, RobotConfig, ThunderBorgConfig
from sensors.motor_board import HostWatchdog, MotorBoard, MotorBoardError, RpmIntegrator, WheelRpm
from sensors.types import WheelTicks

log = logging.getLogger(__name__)

I2C_ID_THUNDERBORG = 0x15
I2C_MAX_LEN = 6
PWM_MAX = 255
VOLTAGE_PIN_MAX = 36.3  # [V] at analog full scale
ANALOG_MAX = 0x3FF
SET_LEDS, SET_LED_BATT_MON = 5, 6
SET_A_FWD, SET_A_REV, GET_A = 8, 9, 10
SET_B_FWD, SET_B_REV, GET_B = 11, 12, 13
ALL_OFF = 14
SET_FAILSAFE, GET_FAILSAFE = 19, 20
GET_BATT_VOLT = 21
GET_ID = 0x99
VALUE_FWD, VALUE_REV = 1, 2
READ_RETRIES = 3
BOARD_FAILSAFE_S = 0.25  # [s] the board's own communications failsafe
BATTERY_CHECK_S = 1.0  # [s]
LED_COLOURS = {
    "idle": (0, 0, 255),
    "driving": (0, 255, 0),
    "battery_low": (255, 128, 0),
    "battery_stop": (255, 0, 0),
    "tacho_lost": (255, 0, 255),
}


class I2CBus(Protocol):
    """The part of smbus2.SMBus the driver uses."""

    def i2c_rdwr(self, *msgs: Any) -> None: ...

    def close(self) -> None: ...


class ThunderBorgI2C:
    """The register protocol over an smbus2-like bus (``i2c_rdwr`` with ``i2c_msg``)."""

    def __init__(self, bus: I2CBus, address: int = I2C_ID_THUNDERBORG) -> None:
        from smbus2 import i2c_msg

        self.bus, self.address, self._msg = bus, address, i2c_msg
        self.lock = threading.Lock()
        self.retries = 0

    def write(self, command: int, data: tuple[int, ...] = ()) -> None:
        try:
            with self.lock:
                self.bus.i2c_rdwr(self._msg.write(self.address, [command, *data]))
        except OSError as err:
            raise MotorBoardError(
                f"ThunderBorg 0x{self.address:02X}: write {command} failed: {err}"
            ) from err

    def read(self, command: int) -> list[int]:
        for _ in range(READ_RETRIES):
            msg = self._msg.read(self.address, I2C_MAX_LEN)
            try:
                with self.lock:
                    self.bus.i2c_rdwr(self._msg.write(self.address, [command]))
                    self.bus.i2c_rdwr(msg)
            except OSError as err:
                raise MotorBoardError(
                    f"ThunderBorg 0x{self.address:02X}: read {command} failed: {err}"
                ) from err
            reply = list(bytes(msg.buf[: msg.len]))
            if reply and reply[0] == command:
                return reply
            self.retries += 1
        raise MotorBoardError(f"ThunderBorg 0x{self.address:02X}: no valid reply to {command}")

    def set_motor(self, motor: int, power: float) -> None:
        """Motor 1 (A) or 2 (B) at ``power`` in [-1, 1]."""
        pwm = min(PWM_MAX, int(PWM_MAX * abs(power)))
        fwd, rev = (SET_A_FWD, SET_A_REV) if motor == 1 else (SET_B_FWD, SET_B_REV)
        self.write(rev if power < 0 else fwd, (pwm,))

    def get_motor(self, motor: int) -> float:
        reply = self.read(GET_A if motor == 1 else GET_B)
        power = reply[2] / PWM_MAX
        return -power if reply[1] == VALUE_REV else power

    def motors_off(self) -> None:
        self.write(ALL_OFF, (0,))

    def battery_voltage(self) -> float:
        reply = self.read(GET_BATT_VOLT)
        return ((reply[1] << 8) + reply[2]) / ANALOG_MAX * VOLTAGE_PIN_MAX

    def set_failsafe(self, on: bool) -> None:
        self.write(SET_FAILSAFE, (int(on),))

    def get_failsafe(self) -> bool:
        return self.read(GET_FAILSAFE)[1] != 0

    def set_leds(self, rgb: tuple[int, int, int]) -> None:
        self.write(SET_LED_BATT_MON, (0,))
        self.write(SET_LEDS, rgb)

    def board_id(self) -> int:
        return self.read(GET_ID)[1]


def speed_to_power(speed: float, cfg: ThunderBorgConfig) -> float:
    """Wheel speed [m/s] -> motor power [-1, 1] by the inverted calibration
    ``speed = slope * power + y_intercept``; 0 below ``inertia_level``."""
    if speed == 0.0:
        return 0.0
    power = min(1.0, (abs(speed) - cfg.y_intercept) / cfg.slope)
    return 0.0 if power < cfg.inertia_level else math.copysign(power, speed)


class Pid:
    """Textbook PID on the speed error [m/s], integral clamped to +-1 m/s of output."""

    def __init__(self, p: float, i: float, d: float) -> None:
        self.p, self.i, self.d = p, i, d
        self.reset()

    def reset(self) -> None:
        self.integral = 0.0
        self.prev: float | None = None

    def step(self, error: float, dt: float) -> float:
        self.integral += error * dt
        if self.i > 0:
            self.integral = max(-1.0 / self.i, min(1.0 / self.i, self.integral))
        deriv = 0.0 if self.prev is None or dt <= 0 else (error - self.prev) / dt
        self.prev = error
        return self.p * error + self.i * self.integral + self.d * deriv


def parse_tacho_line(line: bytes) -> tuple[float, float] | None:
    """``b"tacho 12.5 -3\\r\\n"`` -> (12.5, -3.0); None for anything else."""
    words = line.strip().split()
    if len(words) != 3 or words[0] != b"tacho":
        return None
    try:
        left, right = float(words[1]), float(words[2])
    except ValueError:
        return None
    return (left, right) if math.isfinite(left) and math.isfinite(right) else None


class ThunderBorgBoard(MotorBoard):
    """ThunderBorg motors + tacho RPM behind :class:`MotorBoard`; see the module docstring."""

    kind = "thunderborg"

    def __init__(
        self,
        bus: I2CBus,
        tacho_url: str,
        cfg: ThunderBorgConfig | None = None,
        board_cfg: BoardConfig | None = None,
        robot_cfg: RobotConfig | None = None,
        *,
        address: int | None = None,
        bus_name: str = "",
    ) -> None:
        self.cfg = cfg or ThunderBorgConfig()
        self.board_cfg = board_cfg or BoardConfig()
        self.robot_cfg = robot_cfg or RobotConfig()
        addr = self.cfg.address if address is None else address
        self.url = f"{bus_name or 'i2c'}@0x{addr:02X},{tacho_url}"
        self.i2c = ThunderBorgI2C(bus, addr)
        self._bus = bus
        try:
            ident = self.i2c.board_id()
        except MotorBoardError as err:
            raise MotorBoardError(f"no ThunderBorg at 0x{addr:02X} on {bus_name}: {err}") from err
        if ident != I2C_ID_THUNDERBORG:
            raise MotorBoardError(f"device at 0x{addr:02X} is not a ThunderBorg (id 0x{ident:02X})")
        try:
            self._tacho = serial.serial_for_url(
                tacho_url, baudrate=self.cfg.tacho_baudrate, timeout=0.05
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise MotorBoardError(f"cannot open the tacho Arduino at {tacho_url}: {err}") from err
        self.i2c.motors_off()
        self.i2c.set_failsafe(True)
        self.odometry = RpmIntegrator(self.robot_cfg)
        self._lock = threading.Lock()
        self._target = (0.0, 0.0)  # [m/s]
        self._rpm: WheelRpm | None = None
        self._ticks: WheelTicks | None = None
        self._pids = (
            Pid(self.cfg.p, self.cfg.i, self.cfg.d),
            Pid(self.cfg.p, self.cfg.i, self.cfg.d),
        )
        self.power = (0.0, 0.0)
        self.battery_v: float | None = None
        self.state = "idle"
        self.counts = {
            "tacho_lines": 0,
            "tacho_bad_lines": 0,
            "i2c_errors": 0,
            "tacho_stale": 0,
            "battery_stops": 0,
        }
        self.battery = "ok"  # ok, battery_low, battery_stop
        self._led: tuple[int, int, int] | None = None
        self._stop = threading.Event()
        self._drive_lock = threading.Lock()  # a control step and a watchdog stop never interleave
        self.watchdog = HostWatchdog(
            self.board_cfg.watchdog_timeout, self._watchdog_stop, "thunderborg-watchdog"
        )
        self._threads = [
            threading.Thread(target=self._tacho_loop, name="tacho", daemon=True),
            threading.Thread(target=self._pid_loop, name="thunderborg-pid", daemon=True),
        ]
        for th in self._threads:
            th.start()

    # -- MotorBoard ----------------------------------------------------------------------------

    def set_wheel_speeds(self, left: float, right: float) -> tuple[float, float]:
        with self._lock:
            self._target = (float(left), float(right))
        self.watchdog.feed()
        return self._target

    def ticks(self) -> WheelTicks:
        with self._lock:
            if self._ticks is None:
                raise MotorBoardError("no tacho reading yet")
            return self._ticks

    def probe(self) -> str:
        self.i2c.board_id()
        return "I2C GET_ID"

    def odometry_input(self) -> WheelRpm:
        with self._lock:
            if self._rpm is None:
                raise MotorBoardError("no tacho reading yet")
            return self._rpm

    def battery_voltage(self) -> float:
        return self.i2c.battery_voltage()

    def stop(self) -> None:
        self.watchdog.disarm()
        self._watchdog_stop()

    def arm_failsafe(self, timeout_s: float) -> str:
        self.i2c.set_failsafe(True)
        if not self.i2c.get_failsafe():
            raise MotorBoardError("the ThunderBorg did not enable its communications failsafe")
        return (
            f"board failsafe {BOARD_FAILSAFE_S:.2f} s (host dead), host watchdog "
            f"{self.board_cfg.watchdog_timeout:.2f} s (host quiet)"
        )

    def diagnostics(self) -> dict[str, Any]:
        return {
            "board": "PiBorg ThunderBorg + Arduino tacho",
            "port": self.url,
            "state": self.state,
            "power": tuple(round(p, 3) for p in self.power),
            "battery_v": None if self.battery_v is None else round(self.battery_v, 2),
            "i2c_read_retries": self.i2c.retries,
            "watchdog_stops": self.watchdog.fired,
            **self.counts,
        }

    def close(self) -> None:
        self._stop.set()
        self.watchdog.close()
        for th in self._threads:
            if th is not threading.current_thread():
                th.join()
        try:
            self.i2c.motors_off()
            self.i2c.set_leds(LED_COLOURS["idle"])
        except MotorBoardError as err:
            log.warning("could not stop the motors while closing: %s", err)
        self._tacho.close()
        self._bus.close()

    def halt_threads_for_test(self) -> None:
        """Stop every host thread without a word to the board, as a host killed -9 would."""
        self._stop.set()
        self.watchdog._stop.set()
        for th in self._threads:
            th.join()

    # -- threads -------------------------------------------------------------------------------

    def _zero_target(self) -> None:
        with self._lock:
            self._target = (0.0, 0.0)

    def _watchdog_stop(self) -> None:
        """Motors off at once (not at the next PID step, up to 1 / pid_rate later)."""
        with self._drive_lock:
            self._zero_target()
            self.i2c.motors_off()
            self.power = (0.0, 0.0)

    def _tacho_loop(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                buf += self._tacho.read(max(1, self._tacho.in_waiting))
            except (serial.SerialException, OSError) as err:
                log.warning("tacho link failed: %s", err)
                self._stop.wait(0.1)
                continue
            *lines, buf = buf.split(b"\n")
            buf = buf[-256:]
            for line in lines:
                rpm = parse_tacho_line(line)
                if rpm is None:
                    self.counts["tacho_bad_lines"] += 1
                    continue
                reading = WheelRpm(time.monotonic_ns(), *rpm)
                with self._lock:
                    self._rpm = reading
                    self._ticks = self.odometry.update(reading)
                self.counts["tacho_lines"] += 1

    def _pid_loop(self) -> None:
        period = 1.0 / self.cfg.pid_rate
        next_battery = 0.0
        last = time.monotonic()
        while not self._stop.wait(period):
            now = time.monotonic()
            dt, last = now - last, now
            try:
                if now >= next_battery:
                    next_battery = now + BATTERY_CHECK_S
                    self._check_battery()
                with self._drive_lock:
                    self._drive(self._control_step(dt))
            except MotorBoardError as err:
                self.counts["i2c_errors"] += 1
                log.warning("ThunderBorg: %s", err)

    def _control_step(self, dt: float) -> tuple[float, float]:
        """One PID step: motor powers (left, right) for the current target and tacho reading;
        sets :attr:`state` (idle, driving, battery_low, battery_stop, tacho_lost) and the LED."""
        with self._lock:
            target, rpm = self._target, self._rpm
        moving = target != (0.0, 0.0)
        stale = rpm is None or (time.monotonic_ns() - rpm.stamp_ns) / 1e9 > self.cfg.rpm_timeout
        powers = (0.0, 0.0)
        if self.battery == "battery_stop":
            state = "battery_stop"
        elif moving and stale and self.cfg.use_pid:
            self.counts["tacho_stale"] += 1
            state = "tacho_lost"  # closed loop without a measurement: do not drive blind
        elif moving:
            circumference = math.pi * self.robot_cfg.wheel_diameter  # [m]
            out = []
            for k, pid in enumerate(self._pids):
                u = target[k]
                if self.cfg.use_pid and rpm is not None:
                    u += pid.step(target[k] - (rpm.left, rpm.right)[k] * circumference / 60.0, dt)
                out.append(speed_to_power(u, self.cfg))
            powers = (out[0], out[1])
            state = "battery_low" if self.battery == "battery_low" else "driving"
        else:
            state = "battery_low" if self.battery == "battery_low" else "idle"
        if not any(powers):
            for pid in self._pids:
                pid.reset()
        self.state = state
        self._show(state)
        return powers

    def _drive(self, powers: tuple[float, float]) -> None:
        left_motor = self.cfg.left_motor
        right_motor = 3 - left_motor
        right = -powers[1] if self.cfg.invert_right else powers[1]
        self.i2c.set_motor(left_motor, powers[0])
        self.i2c.set_motor(right_motor, right)
        self.power = powers

    def _check_battery(self) -> None:
        v = self.i2c.battery_voltage()
        self.battery_v = v
        if v < self.cfg.battery_stop:
            if self.battery != "battery_stop":
                self.counts["battery_stops"] += 1
                log.error("battery %.2f V below %.2f V: motors stopped", v, self.cfg.battery_stop)
            self.battery = "battery_stop"
        elif v < self.cfg.battery_warn:
            if self.battery == "ok":
                log.warning("battery low: %.2f V (warning at %.2f V)", v, self.cfg.battery_warn)
            self.battery = "battery_low"
        else:
            self.battery = "ok"

    def _show(self, state: str) -> None:
        colour = LED_COLOURS.get(state, LED_COLOURS["idle"])
        if colour != self._led:
            self.i2c.set_leds(colour)
            self._led = colour
