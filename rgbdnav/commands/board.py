"""`rgbdnav board`: talk to a motor board (or its emulator) through the MotorBoard interface and
report what it says: which board, firmware, battery, odometry, round-trip time, a test drive
(with the wheel odometry pose and its 1-sigma)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sensors.motor_board import MotorBoard
from sensors.types import NS_PER_S, SensorError
from slam.diff_drive import WheelOdometry

LATENCY_SAMPLES = 50  # board round trips timed
TEST_DRIVE_SPEED = 0.1  # [m/s] gentle, so a robot on the floor barely moves
TEST_DRIVE_TIME = 1.0  # [s]
COMMAND_PERIOD = 0.05  # [s] re-send the velocity well inside the 0.25 s watchdog
FIRST_READING_TIMEOUT_S = 2.0  # [s] a tacho board's first RPM line


@dataclass
class BoardReport:
    url: str
    lines: list[tuple[str, str]] = field(default_factory=list)

    def add(self, label: str, value: str) -> None:
        self.lines.append((label, value))

    def text(self) -> str:
        width = max(len(label) for label, _ in self.lines)
        return "\n".join(f"{label:<{width}}  {value}" for label, value in self.lines)


def _first_ticks(board: MotorBoard) -> Any:
    deadline = time.monotonic() + FIRST_READING_TIMEOUT_S
    while True:
        try:
            return board.ticks()
        except SensorError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def check_board(board: MotorBoard, spec: str, test_drive: bool) -> BoardReport:
    report = BoardReport(spec)
    diag = board.diagnostics()
    report.add("board", f"{diag.pop('board')} ({board.kind})")
    report.add("port", str(diag.pop("port", spec)))
    if "firmware" in diag:
        report.add("firmware", str(diag.pop("firmware")))
    report.add("battery", _optional(lambda: f"{board.battery_voltage():.2f} V"))
    t0 = _first_ticks(board)
    report.add(
        "odometry",
        f"left {t0.left}, right {t0.right} positions; input "
        f"{type(board.odometry_input()).__name__}",
    )
    rtt = []
    for _ in range(LATENCY_SAMPLES):
        t = time.perf_counter()
        what = board.probe()
        rtt.append(time.perf_counter() - t)
    report.add(
        "round trip",
        f"{what} median {1e3 * np.median(rtt):.2f} ms, max {1e3 * max(rtt):.2f} ms "
        f"over {LATENCY_SAMPLES}",
    )
    if test_drive:
        report.add("failsafe", board.arm_failsafe(0.25))
        a = board.ticks()
        odometry = WheelOdometry(board.robot_cfg, a)
        end = time.monotonic() + TEST_DRIVE_TIME
        while time.monotonic() < end:
            cmd = board.set_velocity(TEST_DRIVE_SPEED, 0.0)
            time.sleep(COMMAND_PERIOD)
            odometry.update(board.ticks())
        board.stop()
        time.sleep(0.3)
        b = board.ticks()
        odometry.update(b)
        m = board.robot_cfg.metres_per_tick
        travelled = (b.left - a.left + b.right - a.right) / 2 * m
        span = (b.stamp_ns - a.stamp_ns) / NS_PER_S
        report.add(
            "test drive",
            f"sent {cmd} for {TEST_DRIVE_TIME:.1f} s: left {b.left - a.left}, right "
            f"{b.right - a.right} positions = {travelled:.3f} m over {span:.2f} s "
            f"(commanded {TEST_DRIVE_SPEED * TEST_DRIVE_TIME:.3f} m before ramps)",
        )
        report.add("wheel odometry", _pose_summary(odometry.pose, odometry.covariance))
    extra = {k: v for k, v in board.diagnostics().items() if k not in ("board", "port", "firmware")}
    if extra:
        report.add("diagnostics", ", ".join(f"{k} {v}" for k, v in extra.items()))
    return report


def _pose_summary(pose: np.ndarray, covariance: np.ndarray) -> str:
    sd = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    return (
        f"x {pose[0]:.3f} m, y {pose[1]:.3f} m, yaw {math.degrees(pose[2]):.1f} deg "
        f"(1-sigma {sd[0]:.4f} m, {sd[1]:.4f} m, {math.degrees(sd[2]):.2f} deg)"
    )


def _optional(read: Any) -> str:
    try:
        return read()
    except SensorError as err:
        return f"unavailable ({err})"
