"""ROSArduinoBridge (Patrick Goebel's firmware for the Pi Robot / HBRC) on a serial line.

Protocol (the firmware's ``runCommand``; 57600 baud by default): a single-letter command,
space-separated decimal arguments, CR ends it; every reply is one line ending in CR LF.

    e                -> "<left> <right>"   cumulative encoder counts
    m <left> <right> -> "OK"               target speed in ticks per PID frame (PID_RATE 30 Hz);
                                           0 0 stops and resets the PID; restarts AUTO_STOP
    r                -> "OK"               zero the encoders (and the PID)
    u Kp:Kd:Ki:Ko    -> "OK"               PID gains (integers; Ko divides the output)
    b                -> "<baud>"           the baud rate
    other            -> "Invalid Command"

Speeds in m/s become ticks per frame: ``v / metres_per_tick / pid_rate``, rounded (the firmware
takes integers, so the smallest non-zero speed is one tick per frame). The firmware stops the
motors AUTO_STOP_INTERVAL after the last ``m`` (2000 ms as shipped: flash 250 to meet the 250 ms
requirement for a dead host); the host watchdog sends ``m 0 0`` after ``board.watchdog_timeout``.
The board has no battery reading.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from typing import Any

import serial

from sensors.config import BoardConfig, BridgeConfig, RobotConfig
from sensors.motor_board import HostWatchdog, MotorBoard, MotorBoardError
from sensors.types import NS_PER_S, WheelTicks

log = logging.getLogger(__name__)

MAX_REPLY = 64  # [bytes]


def ticks_per_frame(speed: float, robot: RobotConfig, pid_rate: float) -> int:
    """Wheel speed [m/s] -> the firmware's target [ticks per PID frame], rounded."""
    return int(round(speed / robot.metres_per_tick / pid_rate))


_COUNT = re.compile(r"-?[0-9]{1,10}")


def parse_encoder_reply(text: str) -> tuple[int, int] | None:
    """``"123 -45"`` (the reply to ``e``) -> (123, -45); None for anything but two ASCII
    integers in the firmware's ``long`` range (int() would also take "1_0", "٣" or a garbled
    40-digit count that later overflows an int64 array)."""
    words = text.split()
    if len(words) != 2 or not all(_COUNT.fullmatch(w) for w in words):
        return None
    left, right = int(words[0]), int(words[1])
    ok = all(-(2**31) <= c < 2**31 for c in (left, right))
    return (left, right) if ok else None


class ArduinoBridgeBoard(MotorBoard):
    kind = "arduino-bridge"

    def __init__(
        self,
        url: str,
        cfg: BridgeConfig | None = None,
        board_cfg: BoardConfig | None = None,
        robot_cfg: RobotConfig | None = None,
        baudrate: int | None = None,
    ) -> None:
        self.cfg = cfg or BridgeConfig()
        self.board_cfg = board_cfg or BoardConfig()
        self.robot_cfg = robot_cfg or RobotConfig()
        self.url = url
        self.baudrate = baudrate or self.cfg.baudrate
        self._lock = threading.Lock()
        try:
            self._port = serial.serial_for_url(
                url, baudrate=self.baudrate, timeout=self.cfg.timeout
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise MotorBoardError(f"cannot open the Arduino bridge at {url}: {err}") from err
        self.errors = 0
        self.rounded_to_zero = 0  # wheel commands under one tick per frame, sent as 0
        self.reported_baud = self.command("b")
        if self.cfg.set_pid:
            self.command(
                f"u {self.cfg.kp}:{self.cfg.kd}:{self.cfg.ki}:{self.cfg.ko}", expect_ok=True
            )
        self.sent = (0, 0)
        self.watchdog = HostWatchdog(self.board_cfg.watchdog_timeout, self._halt, "bridge-watchdog")

    def command(self, line: str, expect_ok: bool = False) -> str:
        """Send one command, return its reply line (without CR LF)."""
        with self._lock:
            try:
                self._port.reset_input_buffer()
                sent_ns = time.monotonic_ns()
                self._port.write(line.encode("ascii") + b"\r")
                reply = self._port.read_until(b"\n", MAX_REPLY)
            except (serial.SerialException, OSError) as err:
                self.errors += 1
                raise MotorBoardError(f"{line!r}: Arduino bridge link failed: {err}") from err
        self._last_sent_ns = sent_ns
        if not reply.endswith(b"\r\n"):
            self.errors += 1
            raise MotorBoardError(f"{line!r}: no reply within {self.cfg.timeout} s ({reply!r})")
        text = reply[:-2].decode("ascii", "replace")
        if text == "Invalid Command" or (expect_ok and text != "OK"):
            self.errors += 1
            raise MotorBoardError(f"{line!r}: the bridge replied {text!r}")
        return text

    def set_wheel_speeds(self, left: float, right: float) -> tuple[int, int]:
        rate = self.cfg.pid_rate
        cmd = (
            ticks_per_frame(left, self.robot_cfg, rate),
            ticks_per_frame(right, self.robot_cfg, rate),
        )
        if (left and not cmd[0]) or (right and not cmd[1]):
            if not self.rounded_to_zero:
                log.warning(
                    "%.3f / %.3f m/s is under one tick per PID frame: sent as 0 (check "
                    "robot.ticks_per_revolution)",
                    left,
                    right,
                )
            self.rounded_to_zero += 1
        self.watchdog.feed()
        self.command(f"m {cmd[0]} {cmd[1]}", expect_ok=True)
        self.sent = cmd
        return cmd

    def ticks(self) -> WheelTicks:
        text = self.command("e")
        counts = parse_encoder_reply(text)
        if counts is None:
            self.errors += 1
            raise MotorBoardError(f"'e': expected two 32-bit counts, got {text[:80]!r}")
        left, right = counts
        # the firmware reads the counters as the command's last byte arrives
        on_line = 2 * 10 * NS_PER_S // self.baudrate
        return WheelTicks(self._last_sent_ns + on_line, left, right)

    def probe(self) -> str:
        self.command("e")
        return "e (encoders)"

    def battery_voltage(self) -> float:
        raise MotorBoardError("the ROSArduinoBridge firmware reports no battery voltage")

    def _halt(self) -> None:
        self.command("m 0 0", expect_ok=True)

    def stop(self) -> None:
        self.watchdog.disarm()
        self._halt()

    def reset(self) -> None:
        self.command("r", expect_ok=True)

    def arm_failsafe(self, timeout_s: float) -> str:
        note = (
            f"board AUTO_STOP_INTERVAL {self.cfg.auto_stop_interval:.2f} s (host dead; set in "
            f"the firmware), host watchdog {self.board_cfg.watchdog_timeout:.2f} s (host quiet)"
        )
        if self.cfg.auto_stop_interval > timeout_s:
            log.warning(
                "the bridge firmware stops a dead host's motors only after %.2f s; flash "
                "AUTO_STOP_INTERVAL %d",
                self.cfg.auto_stop_interval,
                timeout_s * 1000,
            )
        return note

    def diagnostics(self) -> dict[str, Any]:
        return {
            "board": "ROSArduinoBridge",
            "port": self.url,
            "firmware": f"baud {self.reported_baud}",
            "errors": self.errors,
            "speeds_rounded_to_zero": self.rounded_to_zero,
            "watchdog_stops": self.watchdog.fired,
        }

    def close(self) -> None:
        self.watchdog.close()
        try:
            self._halt()
        except MotorBoardError as err:
            log.warning("could not stop the motors while closing: %s", err)
        self._port.close()
