"""Motor boards against their emulators: speed tracking (host PID vs calibration only on the
ThunderBorg, the bridge's PID frames) and how long each failsafe takes to stop the wheels.

    PYTHONPATH=. python bench/bench_boards.py [--repeats 5]

Stop times are measured from the host's last command (quiet host: the host watchdog) or from
its last I2C write before it died (threads halted: the board's own failsafe). Wall-clock figures:
inflated by machine load; compare within one run.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from sensors.arduino_bridge import ArduinoBridgeBoard
from sensors.board_emulators import BridgeEmulator, ThunderBorgEmulator
from sensors.config import BridgeConfig, RobotConfig, ThunderBorgConfig
from sensors.thunderborg import ThunderBorgBoard

EASE = RobotConfig(wheel_diameter=0.317 / np.pi, ticks_per_revolution=1000, track_width=0.242)
TARGET = 0.25  # [m/s]


def drive(board, seconds: float) -> float:
    """Command every 50 ms; returns when the last command went (the host goes quiet then)."""
    end = time.monotonic() + seconds
    while True:
        board.set_wheel_speeds(TARGET, TARGET)
        last = time.monotonic()
        if last >= end:
            return last
        time.sleep(0.05)


def wait_stopped(still_moving, since: float) -> float:
    while still_moving():
        time.sleep(0.002)
    return time.monotonic() - since


def thunderborg(use_pid: bool, death: bool) -> tuple[float, float]:
    cfg = ThunderBorgConfig(use_pid=use_pid)
    emu = ThunderBorgEmulator(cfg, EASE, gain_error=(-0.15, 0.10))
    board = ThunderBorgBoard(emu.bus(), emu.serve_tacho(), cfg, robot_cfg=EASE)
    board.arm_failsafe(0.25)
    drive(board, 3.0)
    err = float(np.abs(np.array(emu.wheel_speeds()) - TARGET).max())
    if death:
        board.halt_threads_for_test()
    t = wait_stopped(lambda: emu.wheel_speeds() and any(emu.power), time.monotonic())
    if not death:
        board.close()
    emu.close()
    return err, t


def bridge() -> tuple[float, float]:
    emu = BridgeEmulator(BridgeConfig())
    board = ArduinoBridgeBoard(emu.serve_pty(), robot_cfg=EASE)
    quiet = drive(board, 1.5)
    rate = emu.wheel_rates()[0] * 30 * EASE.metres_per_tick  # [m/s]
    t = wait_stopped(lambda: emu.wheel_rates() != (0.0, 0.0), quiet)
    board.close()
    emu.close()
    return abs(rate - TARGET), t


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    n = ap.parse_args().repeats
    rows = {
        "thunderborg PID, quiet host": [thunderborg(True, False) for _ in range(n)],
        "thunderborg open loop, quiet host": [thunderborg(False, False) for _ in range(n)],
        "thunderborg PID, dead host": [thunderborg(True, True) for _ in range(n)],
        "arduino-bridge, quiet host": [bridge() for _ in range(n)],
    }
    print(f"load average {os.getloadavg()[0]:.1f}; {n} runs each; target {TARGET} m/s")
    print(f"{'case':36s} {'speed error max [m/s]':>22s} {'stop after [ms] median/max':>28s}")
    for name, res in rows.items():
        err = max(r[0] for r in res)
        stop = np.array([r[1] for r in res]) * 1e3
        print(f"{name:36s} {err:22.3f} {np.median(stop):19.0f} / {stop.max():.0f}")


if __name__ == "__main__":
    main()
