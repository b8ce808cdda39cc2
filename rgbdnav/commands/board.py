"""`rgbdnav board`: talk to an Eddie control board (or its emulator) and report what it says."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from sensors.config import BoardConfig, RobotConfig
from sensors.eddie import BoardError, EddieBoard

LATENCY_SAMPLES = 50  # DIST round trips timed
TEST_DRIVE_SPEED = 0.1  # [m/s] gentle, so a robot on the floor barely moves
TEST_DRIVE_TIME = 1.0  # [s]
COMMAND_PERIOD = 0.05  # [s] re-send the velocity well inside the 0.25 s watchdog


@dataclass
class BoardReport:
    url: str
    lines: list[tuple[str, str]] = field(default_factory=list)

    def add(self, label: str, value: str) -> None:
        self.lines.append((label, value))

    def text(self) -> str:
        width = max(len(label) for label, _ in self.lines)
        return "\n".join(f"{label:<{width}}  {value}" for label, value in self.lines)


def check_board(
    url: str, board_cfg: BoardConfig, robot: RobotConfig, test_drive: bool
) -> BoardReport:
    report = BoardReport(url)
    with EddieBoard(url, board_cfg, robot) as board:
        report.add("port", url)
        report.add("firmware", f"VER {board.version():04X}, HWVER {board.hardware_version():04X}")
        report.add("battery", _optional(lambda: f"{board.battery_voltage():.2f} V"))
        report.add("ping sensors", _optional(lambda: " ".join(str(r) for r in board.ping())))
        left, right = board.distance()
        report.add(
            "encoders", f"left {left}, right {right} positions; heading {board.heading()} deg"
        )
        rtt = []
        for _ in range(LATENCY_SAMPLES):
            t0 = time.perf_counter()
            board.distance()
            rtt.append(time.perf_counter() - t0)
        report.add("round trip", f"DIST median {1e3 * np.median(rtt):.2f} ms, "
                                 f"max {1e3 * max(rtt):.2f} ms over {LATENCY_SAMPLES}")  # fmt: skip
        if test_drive:
            l0, r0 = board.distance()
            end = time.monotonic() + TEST_DRIVE_TIME
            while time.monotonic() < end:
                cmd = board.set_velocity(TEST_DRIVE_SPEED, 0.0)
                time.sleep(COMMAND_PERIOD)
            board.stop()
            time.sleep(0.2)
            l1, r1 = board.distance()
            travelled = (l1 - l0 + r1 - r0) / 2 * robot.metres_per_tick
            report.add(
                "test drive",
                f"GOSPD {cmd[0]} {cmd[1]} positions/s for {TEST_DRIVE_TIME:.1f} s: "
                f"left {l1 - l0}, right {r1 - r0} positions = {travelled:.3f} m "
                f"(commanded {TEST_DRIVE_SPEED * TEST_DRIVE_TIME:.3f} m before ramps)",
            )
    return report


def _optional(read: object) -> str:
    try:
        return read()  # type: ignore[operator]
    except BoardError as err:
        return f"unavailable ({err})"
