"""The MotorBoard drivers against their emulators: protocol, PID, odometry, failsafes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rgbdnav.config import load_config
from sensors.arduino_bridge import ArduinoBridgeBoard, ticks_per_frame
from sensors.board_emulators import BridgeEmulator, ThunderBorgEmulator
from sensors.boards import open_board
from sensors.config import BridgeConfig, RobotConfig, ThunderBorgConfig
from sensors.motor_board import (
    MotorBoard,
    MotorBoardError,
    RpmIntegrator,
    WheelRpm,
    parse_device_spec,
)
from sensors.thunderborg import ThunderBorgBoard, parse_tacho_line, speed_to_power
from sensors.types import ConfigError
from slam.diff_drive import WheelOdometry

REPO = Path(__file__).resolve().parents[2]
EASE = RobotConfig(wheel_diameter=0.317 / np.pi, ticks_per_revolution=1000, track_width=0.242)


def test_device_specs_name_the_board_and_reject_bad_ones() -> None:
    d = parse_device_spec("thunderborg:/dev/i2c-1@0x15,/dev/ttyUSB1")
    assert (d.kind, d.path, d.option, d.extra) == (
        "thunderborg",
        "/dev/i2c-1",
        "0x15",
        "/dev/ttyUSB1",
    )
    assert parse_device_spec("/dev/ttyUSB0").kind == "eddie"
    assert parse_device_spec("socket://127.0.0.1:5000").kind == "eddie"
    assert parse_device_spec("arduino-bridge:/dev/ttyACM0@57600").option == "57600"
    assert parse_device_spec("emulator:thunderborg").emulator
    for bad in (
        "emulator:roomba",
        "thunderborg:/dev/ttyUSB0",
        "thunderborg:/dev/i2c-1@0x99",
        "arduino-bridge:/dev/ttyACM0@fast",
        "arduino-bridge:/dev/a,/dev/b",
    ):
        with pytest.raises(ConfigError):
            parse_device_spec(bad)


def test_calibration_inverts_the_speed_fit_and_respects_inertia() -> None:
    cfg = ThunderBorgConfig()
    p = speed_to_power(0.3, cfg)
    assert cfg.slope * p + cfg.y_intercept == pytest.approx(0.3)
    assert speed_to_power(-0.3, cfg) == pytest.approx(-p)
    assert speed_to_power(0.0, cfg) == 0.0
    assert speed_to_power(5.0, cfg) == 1.0
    lazy = ThunderBorgConfig(inertia_level=0.5)
    assert speed_to_power(0.05, lazy) == 0.0  # would need power 0.2 < 0.5: no motion


def test_tacho_lines_parse_strictly() -> None:
    assert parse_tacho_line(b"tacho 12.5 -3\r\n") == (12.5, -3.0)
    for bad in (b"tacho 1\r\n", b"rpm 1 2\r\n", b"tacho nan 1\r\n", b"tacho a b\r\n"):
        assert parse_tacho_line(bad) is None


def test_rpm_odometry_integrates_distance_and_grows_covariance() -> None:
    tacho = RpmIntegrator(EASE)
    rpm = 0.2 / 0.317 * 60  # 0.2 m/s
    ticks = tacho.update(WheelRpm(0, rpm, rpm))
    odo = WheelOdometry(EASE, ticks)
    for i in range(1, 21):
        ticks = tacho.update(WheelRpm(i * 100_000_000, rpm, rpm))
        odo.update(ticks)
    assert tacho.pos == pytest.approx([0.4 / EASE.metres_per_tick] * 2, rel=1e-9)  # 2 s, 0.2 m/s
    assert ticks.left == ticks.right == int(np.floor(0.4 / EASE.metres_per_tick + 1e-9))
    assert odo.pose[0] == pytest.approx(0.4, abs=EASE.metres_per_tick)  # floored counts
    assert odo.covariance[1, 1] > 0 and odo.covariance[0, 0] > 0


def _tb_board(emu: ThunderBorgEmulator, cfg: ThunderBorgConfig) -> ThunderBorgBoard:
    return ThunderBorgBoard(emu.bus(), emu.serve_tacho(), cfg, robot_cfg=EASE)


def _drive(board: MotorBoard, left: float, right: float, seconds: float) -> float:
    """Command the wheels every 50 ms for ``seconds``; returns when the last command went."""
    end = time.monotonic() + seconds
    while True:
        board.set_wheel_speeds(left, right)
        last = time.monotonic()
        if last >= end:
            return last
        time.sleep(0.05)


def _eventually(pred, timeout_s: float = 1.0) -> bool:
    """The watchdog counts its stop after the board acknowledged it: allow it that moment."""
    end = time.monotonic() + timeout_s
    while not pred() and time.monotonic() < end:
        time.sleep(0.005)
    return pred()


QUIET_STOP_S = 0.25 + 0.03  # the watchdog stops by 0.25 s; slack for a loaded machine


def test_thunderborg_pid_reaches_the_target_the_open_loop_misses() -> None:
    errors = {}
    for use_pid in (True, False):
        cfg = ThunderBorgConfig(use_pid=use_pid)
        emu = ThunderBorgEmulator(cfg, EASE, gain_error=(-0.15, 0.10))
        board = _tb_board(emu, cfg)
        try:
            _drive(board, 0.25, 0.25, 2.5)
            errors[use_pid] = np.abs(np.array(emu.wheel_speeds()) - 0.25).max()
            assert min(board.ticks().left, board.ticks().right) * EASE.metres_per_tick > 0.4
            assert emu.led == (0, 255, 0)  # green: driving
            assert isinstance(board.odometry_input(), WheelRpm)
        finally:
            board.close()
            emu.close()
    assert errors[True] < 0.02 < errors[False]


def test_thunderborg_host_watchdog_stops_a_quiet_host() -> None:
    cfg = ThunderBorgConfig()
    emu = ThunderBorgEmulator(cfg, EASE)
    board = _tb_board(emu, cfg)
    try:
        quiet = _drive(board, 0.3, 0.3, 1.0)
        while any(emu.power) and time.monotonic() - quiet < 2.0:
            time.sleep(0.002)
        assert time.monotonic() - quiet <= QUIET_STOP_S
        assert _eventually(lambda: board.watchdog.fired == 1) and emu.failsafe_trips == 0
    finally:
        board.close()
        emu.close()


def test_thunderborg_board_failsafe_stops_a_dead_host_within_250_ms() -> None:
    cfg = ThunderBorgConfig()
    emu = ThunderBorgEmulator(cfg, EASE)
    board = _tb_board(emu, cfg)
    try:
        board.arm_failsafe(0.25)
        _drive(board, 0.3, 0.3, 1.0)
        board.halt_threads_for_test()  # as kill -9: not another byte on the bus
        dead = time.monotonic()
        assert any(emu.power)
        while any(emu.power):
            emu.wheel_speeds()  # the model advances when looked at
            time.sleep(0.005)
        assert time.monotonic() - dead <= 0.25 + 0.06  # one PID period + polling
        assert emu.failsafe_trips == 1
    finally:
        emu.close()


def test_thunderborg_low_battery_warns_then_stops() -> None:
    cfg = ThunderBorgConfig(battery_warn=11.0, battery_stop=10.5)
    emu = ThunderBorgEmulator(cfg, EASE, battery_v=10.8)
    board = _tb_board(emu, cfg)
    try:
        _drive(board, 0.2, 0.2, 0.5)
        assert board.state == "battery_low" and emu.led == (255, 128, 0)
        assert any(emu.power)
        emu.battery_v = 10.2
        _drive(board, 0.2, 0.2, 1.3)
        assert board.state == "battery_stop" and emu.led == (255, 0, 0)
        assert not any(emu.power)
    finally:
        board.close()
        emu.close()


def test_thunderborg_stops_when_the_tacho_goes_silent() -> None:
    cfg = ThunderBorgConfig(rpm_timeout=0.3)
    emu = ThunderBorgEmulator(cfg, EASE)
    board = _tb_board(emu, cfg)
    try:
        _drive(board, 0.2, 0.2, 0.6)
        assert any(emu.power)
        emu.tacho_silent = True
        _drive(board, 0.2, 0.2, 0.6)
        assert board.state == "tacho_lost" and not any(emu.power)
        assert emu.led == (255, 0, 255) and board.diagnostics()["tacho_stale"] > 0
        emu.tacho_silent = False
        _drive(board, 0.2, 0.2, 0.4)
        assert board.state == "driving" and any(emu.power)
    finally:
        board.close()
        emu.close()


def test_thunderborg_absent_device_is_a_clear_error() -> None:
    emu = ThunderBorgEmulator()
    from sensors.board_emulators import FakeSMBus

    with pytest.raises(MotorBoardError, match="no ThunderBorg at 0x16"):
        ThunderBorgBoard(FakeSMBus(emu), "loop://", address=0x16)


def test_bridge_speaks_pid_frames() -> None:
    cfg = BridgeConfig()
    assert ticks_per_frame(0.3, EASE, 30.0) == round(0.3 / EASE.metres_per_tick / 30)
    emu = BridgeEmulator(cfg)
    board = ArduinoBridgeBoard(emu.serve_pty(), cfg, robot_cfg=EASE)
    try:
        assert board.reported_baud == "57600"
        assert board.command("u 10:5:0:40", expect_ok=True) == "OK"
        assert emu.pid == (10, 5, 0, 40)
        with pytest.raises(MotorBoardError, match="Invalid Command"):
            board.command("x")
        sent = board.set_wheel_speeds(0.3, -0.3)
        assert emu.target.tolist() == [sent[0], sent[1]]
        _drive(board, 0.3, -0.3, 1.0)
        t = board.ticks()
        assert t.left > 0 > t.right
        board.reset()
        assert abs(board.ticks().left) < 50
        assert board.set_wheel_speeds(0.001, 0.0) == (0, 0)  # under one tick per frame
        assert board.diagnostics()["speeds_rounded_to_zero"] == 1
    finally:
        board.close()
        emu.close()


def test_bridge_firmware_auto_stop_stops_a_killed_host() -> None:
    """A host process opens the pty, drives, and is killed -9: the firmware's AUTO_STOP
    (flashed at 250 ms) stops the motors within 250 ms of its last command."""
    emu = BridgeEmulator(BridgeConfig(auto_stop_interval=0.25))
    path = emu.serve_pty()
    host = subprocess.Popen(
        [
            sys.executable,
            "-c",
            (
                "import serial, time, sys\n"
                f"p = serial.Serial({path!r}, 57600, timeout=0.5)\n"
                "while True:\n"
                "    p.write(b'm 20 20\\r'); p.readline(); time.sleep(0.05)\n"
            ),
        ]
    )
    try:
        deadline = time.monotonic() + 10
        while emu.wheel_rates()[0] < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert emu.wheel_rates()[0] >= 10
        host.kill()
        host.wait()
        killed = time.monotonic()
        while emu.wheel_rates() != (0.0, 0.0):
            time.sleep(0.005)
        assert time.monotonic() - killed <= 0.25 + 0.05
        assert emu.auto_stops == 1
    finally:
        host.kill()
        emu.close()


def test_bridge_host_watchdog_stops_a_quiet_host() -> None:
    emu = BridgeEmulator(BridgeConfig())  # shipped 2 s AUTO_STOP: the host watchdog must act
    board = ArduinoBridgeBoard(emu.serve_pty(), robot_cfg=EASE)
    try:
        quiet = _drive(board, 0.3, 0.3, 0.5)
        while emu.wheel_rates() != (0.0, 0.0) and time.monotonic() - quiet < 2:
            time.sleep(0.002)
        assert time.monotonic() - quiet <= QUIET_STOP_S
        assert _eventually(lambda: board.watchdog.fired == 1) and emu.auto_stops == 0
    finally:
        board.close()
        emu.close()


@pytest.mark.parametrize("kind", ["eddie", "thunderborg", "arduino-bridge"])
def test_every_emulator_opens_behind_the_interface(kind: str) -> None:
    cfg = load_config([], ["robot.ticks_per_revolution=1000"])
    with open_board(f"emulator:{kind}", cfg) as board:
        assert isinstance(board, MotorBoard) and board.kind == kind
        _drive(board, 0.2, 0.2, 0.6)
        time.sleep(0.1)
        assert board.ticks().left > 0


def _eddie_host_drives_then_dies(emu_path: str, timeout_s: float = 0.25) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-c",
            (
                "import time\n"
                "from sensors.eddie import EddieBoard\n"
                f"b = EddieBoard({emu_path!r})\n"
                f"print(b.arm_failsafe({timeout_s}), flush=True)\n"
                "while True:\n"
                "    b.set_velocity(0.3, 0.0); time.sleep(0.05)\n"
            ),
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=str(REPO),
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


@pytest.mark.parametrize(("kill_ms", "limit_s"), [(True, 0.25), (False, 1.0)])
def test_eddie_kill_switch_stops_a_killed_host(kill_ms: bool, limit_s: float) -> None:
    """A host process drives and is killed -9: firmware with KILL [ms] stops the wheels within
    250 ms; the Parallax firmware only has WATCH [s], so within 1 s."""
    from sensors.eddie_emulator import EddieEmulator

    emu = EddieEmulator(kill_ms_command=kill_ms)
    host = _eddie_host_drives_then_dies(emu.serve_pty())
    try:
        armed = host.stdout.readline()
        assert ("KILL 250 ms" if kill_ms else "WATCH 1 s") in armed
        deadline = time.monotonic() + 10
        while emu.speeds()[0] < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert emu.speeds()[0] >= 5
        host.kill()
        host.wait()
        killed = time.monotonic()
        while emu.speeds() != (0.0, 0.0):
            time.sleep(0.005)
        assert time.monotonic() - killed <= limit_s + 0.05
    finally:
        host.kill()
        emu.close()
