from __future__ import annotations

import math
import time

import pytest

from sensors.config import BoardConfig, RobotConfig
from sensors.eddie import BoardError, EddieBoard, HexField, parse_reply
from sensors.eddie_emulator import EddieEmulator, ramp

EDDIE = RobotConfig()


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0  # [s]

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock():
    return FakeClock()


@pytest.fixture
def emu(clock):
    return EddieEmulator(time_source=clock)


def ask(emu: EddieEmulator, cmd: str) -> tuple[int, ...]:
    return parse_reply(cmd.split()[0], emu.feed(cmd.encode() + b"\r"))


# --- firmware parser --------------------------------------------------------------------------


def test_set_commands_are_acknowledged_with_an_empty_line(emu):
    assert emu.feed(b"GOSPD 10 10\r") == b"\r"
    assert emu.feed(b"RST\rACC C8\r") == b"\r\r"


def test_errors_carry_a_reason_only_in_verbose_mode(emu):
    assert emu.feed(b"FLY\r") == b"ERROR\r"
    assert emu.feed(b"VERB 1\r") == b"\r"
    assert emu.feed(b"FLY\r") == b"ERROR - Invalid command\r"
    assert emu.feed(b"GO 1\r") == b"ERROR - Too few parameters\r"
    assert emu.feed(b"GO 1 2 3\r") == b"ERROR - Too many parameters\r"
    assert emu.feed(b"GO 1 XY\r") == b"ERROR - Invalid parameter\r"
    assert emu.feed(b"ACC 200\r") == b"ERROR - Invalid parameter\r"  # 1FF is the largest
    assert emu.feed(b"TRVL 10 0\r") == b"ERROR - Invalid parameter\r"
    assert emu.feed(b"GOSPD 123456789 0\r") == b"ERROR - Invalid parameter\r"  # 9 digits
    assert emu.feed(b"VERB 0\r") == b"\r"
    assert emu.feed(b"FLY\r") == b"ERROR\r"


def test_commands_are_case_insensitive_and_tab_separated(emu):
    assert emu.feed(b"gospd\t17   ffe9\r") == b"\r"
    assert emu.feed(b"ver\r") == b"000C\r"


def test_line_feed_after_cr_spoils_the_next_command_like_the_firmware(emu):
    # The firmware keeps control bytes in its buffer: "\n" becomes part of the next command.
    assert emu.feed(b"VER\r\nVER\r") == b"000C\rERROR\r"


def test_backspace_edits_and_empty_lines_get_no_reply(emu):
    assert emu.feed(b"VEX\x08R\r") == b"000C\r"
    assert emu.feed(b"\r\r") == b""


def test_overflow_is_reported_when_the_line_finally_ends(emu):
    emu.feed(b"VERB 1\r")
    assert emu.feed(b"A" * 300) == b""
    assert emu.feed(b"\r") == b"ERROR - Overflow\r"
    assert emu.feed(b"VER\r") == b"000C\r"


def test_replies_are_fixed_width_hex(emu, clock):
    emu.feed(b"GOSPD FFF6 FFF6\r")
    clock.t += 5.0
    line = emu.feed(b"DIST\r")
    assert len(line) == 18 and line[8:9] == b" "
    left, right = parse_reply("DIST", line)
    assert left == right < 0
    assert emu.feed(b"SPD\r") == b"FFF6 FFF6\r"
    assert emu.feed(b"ADC\r").count(b" ") == 7


# --- motor model ------------------------------------------------------------------------------


def test_ramp_is_exact_for_a_linear_speed_change():
    assert ramp(0.0, 10.0, 100.0, 1.0) == pytest.approx((10.0, 0.5 * 10.0 * 0.1 + 10.0 * 0.9))
    assert ramp(0.0, 10.0, 5.0, 1.0) == pytest.approx((5.0, 2.5))
    assert ramp(4.0, -4.0, 8.0, 1.0) == pytest.approx((-4.0, 0.0))


def test_distance_grows_at_the_commanded_rate_after_the_acceleration_ramp(emu, clock):
    emu.feed(b"GOSPD 17 17\r")  # 23 positions/s; default ACC 200 positions/s^2
    clock.t += 2.0
    expected = 23 * 2.0 - 23 * (23 / 200) / 2  # [positions] ramp, then cruise
    left, right = ask(emu, "DIST")
    assert left == right
    assert left == pytest.approx(expected, abs=1.0)
    assert ask(emu, "SPD") == (23, 23)


def test_acc_limits_the_ramp(emu, clock):
    emu.feed(b"ACC A\rGOSPD 32 32\r")  # 10 positions/s^2 towards 50 positions/s
    clock.t += 1.0
    assert ask(emu, "SPD") == (10, 10)
    assert ask(emu, "DIST")[0] == pytest.approx(5.0, abs=1.0)


def test_heading_follows_the_encoder_difference_clockwise(emu, clock):
    turn = 2 * math.pi * EDDIE.track_width / EDDIE.metres_per_tick  # L - R for 360 degrees
    emu.feed(b"ACC 1FF\rGOSPD A FFF6\r")  # left forward, right back: clockwise
    clock.t += turn / 4 / 20  # L - R grows at 20 positions/s: a quarter turn
    assert ask(emu, "HEAD")[0] == pytest.approx(90, abs=2)


def test_trvl_and_turn_reach_their_goal_and_rst_zeroes(emu, clock):
    emu.feed(b"TRVL 64 32\r")  # 100 positions at 50 positions/s
    clock.t += 5.0
    assert ask(emu, "DIST") == (100, 100)
    assert ask(emu, "SPD") == (0, 0)
    emu.feed(b"RST\rTURN 5A 14\r")  # 90 degrees clockwise at 20 positions/s
    clock.t += 10.0
    left, right = ask(emu, "DIST")
    quarter_turn = EDDIE.track_width * math.pi / 4 / EDDIE.metres_per_tick  # [positions/wheel]
    assert left == -right == pytest.approx(quarter_turn, abs=1)
    assert ask(emu, "HEAD")[0] == pytest.approx(90, abs=1)


def test_stop_with_a_distance_decelerates_within_it(emu, clock):
    emu.feed(b"GOSPD 28 28\r")  # 40 positions/s
    clock.t += 1.0
    before = ask(emu, "DIST")[0]
    emu.feed(b"STOP A\r")
    clock.t += 2.0
    assert ask(emu, "SPD") == (0, 0)
    assert ask(emu, "DIST")[0] - before == pytest.approx(10, abs=1)


def test_board_kill_switch_stops_the_wheels(emu, clock):
    emu.feed(b"WATCH 1\rGOSPD 17 17\r")
    clock.t += 3.0
    assert emu.speeds() == (0.0, 0.0)
    assert emu.distances()[0] == pytest.approx(23 * 1.0 - 23 * (23 / 200) / 2, abs=1)


# --- through pyserial -------------------------------------------------------------------------


@pytest.fixture
def live():
    emulator = EddieEmulator()
    yield emulator
    emulator.close()


def test_gospd_then_dist_over_a_pty(live):
    with EddieBoard(live.serve_pty(), BoardConfig(timeout=0.2)) as board:
        board.set_acceleration(511)
        board.go_speed(40, 40)
        time.sleep(0.15)  # past the 0.08 s ramp
        (l0, r0), t0 = board.distance(), time.monotonic()
        time.sleep(0.4)
        (l1, r1), t1 = board.distance(), time.monotonic()
    rate = (l1 - l0) / (t1 - t0)  # [positions/s]
    assert rate == pytest.approx(40, abs=5)
    assert r1 - r0 == pytest.approx(l1 - l0, abs=1)


def test_error_reply_raises_board_error_naming_the_command(live):
    with EddieBoard(live.serve_pty(), BoardConfig(timeout=0.2)) as board:
        board.verbose(True)
        wide = [HexField("acceleration", 16, False, 0, 0xFFFF)]
        with pytest.raises(BoardError, match=r"^ACC: board replied ERROR - Invalid parameter$"):
            board.command("ACC", 0x200, widths=wide)
        board.verbose(False)
        with pytest.raises(BoardError, match=r"^ACC: board replied ERROR$"):
            board.command("ACC", 0x200, widths=wide)
        assert board.version() == 0x000C


def test_garbage_then_the_next_command_works(live):
    with EddieBoard(live.serve_pty(), BoardConfig(timeout=0.2)) as board:
        live.inject(garbage=b"\x00\xfe#~")
        with pytest.raises(BoardError, match=r"DIST: expected 2 field\(s\).*\\x00\\xfe#~"):
            board.distance()
        live.inject(garbage=b"junk\r")
        with pytest.raises(BoardError, match="DIST: expected .* got b'junk\\\\r'"):
            board.distance()
        assert board.distance() == (0, 0)


def test_dropped_reply_times_out_then_the_next_command_works(live):
    with EddieBoard(live.serve_pty(), BoardConfig(timeout=0.1)) as board:
        live.inject(drop_next_replies=1)
        t0 = time.monotonic()
        with pytest.raises(BoardError, match=r"^HEAD: no reply within 0.1 s \(timeout\)$"):
            board.heading()
        assert time.monotonic() - t0 < 1.0
        assert board.heading() == 0


def test_disconnect_then_reconnect_over_a_socket(live):
    url = live.serve_socket()
    cfg = BoardConfig(timeout=0.2, reconnect_interval=0.05)
    with EddieBoard(url, cfg) as board:
        board.go_speed(40, 40)
        # Let the wheels turn before the cable is pulled, so the counters have something to keep.
        deadline = time.monotonic() + 2.0
        while (before := board.distance()[0]) <= 0:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        live.inject(disconnect=True)
        with pytest.raises(BoardError, match="DIST: disconnected from socket://127.0.0.1"):
            board.distance()
        assert not board.connected
        with pytest.raises(BoardError, match="DIST: disconnected"):
            board.distance()  # the port is still down
        assert live.reconnect() == url
        deadline = time.monotonic() + 2.0
        while True:
            try:
                left, _ = board.distance()
                break
            except BoardError:
                assert time.monotonic() < deadline
                time.sleep(0.02)
        assert left >= before > 0  # the same board: its counters survived the reconnect
        assert board.connected


def test_pty_disconnect_is_a_board_error(live):
    with EddieBoard(live.serve_pty(), BoardConfig(timeout=0.2)) as board:
        live.inject(disconnect=True)
        with pytest.raises(BoardError, match="VER: disconnected from /dev/"):
            board.version()


def test_watchdog_stops_the_motors_after_the_last_velocity_command(live):
    cfg = BoardConfig(timeout=0.2, watchdog_timeout=0.25)
    with EddieBoard(live.serve_pty(), cfg) as board:
        for _ in range(5):  # a controller at 20 Hz: the watchdog must stay quiet
            time.sleep(0.05)
            board.set_velocity(0.3, 0.0)
            last = time.monotonic()
        while live.speeds() != (0.0, 0.0):
            assert time.monotonic() - last < 1.5
            time.sleep(0.005)
        stopped_after = time.monotonic() - last
        sent = live.commands()
    # Never early; the upper bound only guards against "never" on a loaded CI machine.
    assert 0.25 <= stopped_after <= 1.0
    assert [text for _, text in sent].count("STOP 0") == 1
    gospd_t = max(t for t, text in sent if text.startswith("GOSPD"))
    stop_t = next(t for t, text in sent if text == "STOP 0")
    assert 0.25 <= stop_t - gospd_t <= 1.0
