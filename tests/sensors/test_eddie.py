from __future__ import annotations

import math
import queue
import threading
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sensors.config import BoardConfig, RobotConfig
from sensors.eddie import (
    COMMANDS,
    BoardCommandError,
    BoardError,
    EddieBoard,
    HexField,
    OdometryPoller,
    battery_voltage,
    encode_command,
    heading_degrees,
    parse_reply,
    round_half_away,
    wheel_speeds,
)
from sensors.eddie_emulator import (
    EddieEmulator,
    format_fields,
    parse_hex_param,
    sign_extend,
    split_command,
)
from sensors.types import SensorError

EDDIE = RobotConfig()
REPLY_COMMANDS = sorted(c for c, s in COMMANDS.items() if s.reply)
PARAM_COMMANDS = sorted(c for c, s in COMMANDS.items() if s.params)


# --- encode_command ---------------------------------------------------------------------------


def test_signed_speeds_are_sent_as_full_width_twos_complement():
    assert encode_command("GOSPD", 23, -23) == b"GOSPD 0017 FFE9\r"
    assert encode_command("GO", -1, 127) == b"GO FF 7F\r"
    assert encode_command("TRVL", -256, 100) == b"TRVL FF00 64\r"


def test_unsigned_and_bare_commands():
    assert encode_command("DIST") == b"DIST\r"
    assert encode_command("ACC", 511) == b"ACC 1FF\r"
    assert encode_command("OUT", 0x70000) == b"OUT 70000\r"
    assert encode_command("STOP", 0) == b"STOP 0\r"


def test_out_of_range_parameter_names_the_command_and_is_a_value_error():
    with pytest.raises(BoardCommandError, match=r"ACC: acceleration .* 512 is out of range"):
        encode_command("ACC", 512)
    with pytest.raises(ValueError, match="GO: left power -128"):
        encode_command("GO", -128, 0)
    with pytest.raises(BoardError, match=r"TRVL: speed .* 0 is out of range \[1, 127\]"):
        encode_command("TRVL", 10, 0)


def test_wrong_parameter_count_type_or_name_is_rejected():
    with pytest.raises(BoardCommandError, match="GOSPD: expects 2 parameter"):
        encode_command("GOSPD", 1)
    with pytest.raises(BoardCommandError, match="VERB: verbose must be an integer"):
        encode_command("VERB", True)
    with pytest.raises(BoardCommandError, match="'FLY': not an Eddie board command"):
        encode_command("FLY")


def test_widths_override_the_table():
    wide = [HexField("acceleration", 16, False, 0, 2047)]
    assert encode_command("ACC", 0x7FF, widths=wide) == b"ACC 7FF\r"


# --- parse_reply ------------------------------------------------------------------------------


def test_distances_are_signed_32_bit():
    assert parse_reply("DIST", b"0000002A FFFFFFD6\r") == (42, -42)
    assert parse_reply("DIST", b"7FFFFFFF 80000000\r") == (2**31 - 1, -(2**31))


def test_speed_heading_versions_and_acknowledgements():
    assert parse_reply("SPD", b"0017 FFE9\r") == (23, -23)
    assert parse_reply("HEAD", b"10E\r") == (270,)
    assert parse_reply("VER", b"000C\r") == (12,)
    assert parse_reply("GOSPD", b"\r") == ()
    assert parse_reply("PING", b"\r") == ()
    assert parse_reply("PING", b"1F4 4B0\r") == (500, 1200)
    assert parse_reply("ADC", b"000 000 000 000 000 000 000 C8F\r")[7] == 0xC8F


def test_error_reply_names_the_command_and_the_reason():
    with pytest.raises(BoardError, match=r"^GOSPD: board replied ERROR$"):
        parse_reply("GOSPD", b"ERROR\r")
    with pytest.raises(BoardError, match=r"^TRVL: board replied ERROR - Invalid parameter$"):
        parse_reply("TRVL", b"ERROR - Invalid parameter\r")
    with pytest.raises(BoardError, match="DIST: malformed ERROR reply"):
        parse_reply("DIST", b"ERROR -\r")


@pytest.mark.parametrize(
    "line",
    [
        b"0000002A\r",  # one field short
        b"0000002A FFFFFFD6",  # half line: no terminator
        b"0000002A  FFFFFFD6\r",  # two spaces
        b"0000002a FFFFFFD6 \r",  # trailing space
        b"000002A FFFFFFD6\r",  # seven digits
        b"0000002G FFFFFFD6\r",  # not hex
        b"\x00\xff0000002A FFFFFFD6\r",  # line noise in front
        b"+000002A FFFFFFD6\r",  # int() would accept this
        b"0000002A FFFFFFD6\r0000002A FFFFFFD6\r",  # two replies run together
        b"\r",  # an acknowledgement where numbers were asked for
    ],
)
def test_garbage_reply_names_the_command_and_quotes_the_bytes(line):
    with pytest.raises(BoardError, match="^DIST: ") as info:
        parse_reply("DIST", line)
    assert repr(line)[:40] in str(info.value)


def test_numbers_where_an_acknowledgement_was_expected_are_an_error():
    with pytest.raises(BoardError, match="GOSPD: expected an empty acknowledgement"):
        parse_reply("GOSPD", b"0017\r")


def test_too_many_ping_fields_is_an_error():
    with pytest.raises(BoardError, match="PING: expected up to 16 fields"):
        parse_reply("PING", b" ".join([b"001"] * 17) + b"\r")


def test_board_error_is_a_sensor_error():
    assert issubclass(BoardError, SensorError)


def test_negative_heading_from_a_12_bit_field_folds_into_0_to_359():
    (raw,) = parse_reply("HEAD", b"FA6\r")  # -90 printed as 12-bit two's complement
    assert raw == -90
    assert heading_degrees(raw) == 270
    assert heading_degrees(359) == 359


def test_battery_voltage_from_the_last_adc_channel():
    assert battery_voltage((0,) * 7 + (819,)) == pytest.approx(3.21)


# --- property tests ---------------------------------------------------------------------------
# Each example checks a batch of BATCH inputs: 10,000 generated inputs in all.

BATCH = 25


def examples(n: int) -> settings:
    """``n`` examples, no deadline, no example database written into the repository."""
    return settings(
        max_examples=n, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
    )


def _values(fields: tuple[HexField, ...]) -> st.SearchStrategy[tuple[int, ...]]:
    return st.tuples(*(st.integers(f.lo, f.hi) for f in fields))


def _reply_case(cmd: str) -> st.SearchStrategy[tuple[str, tuple[int, ...]]]:
    spec = COMMANDS[cmd]
    if spec.repeated_reply:
        values = st.lists(st.integers(spec.reply[0].lo, spec.reply[0].hi), max_size=16).map(tuple)
    else:
        values = _values(spec.reply)
    return st.tuples(st.just(cmd), values)


REPLY_CASES = st.one_of([_reply_case(c) for c in REPLY_COMMANDS])
COMMAND_CASES = st.one_of(
    [st.tuples(st.just(c), _values(COMMANDS[c].params)) for c in PARAM_COMMANDS]
)
VALID_REPLY = b"0000002A FFFFFFD6\r"
NOISY_BYTES = st.one_of(
    st.binary(max_size=300),
    st.integers(0, len(VALID_REPLY)).map(lambda cut: VALID_REPLY[:cut]),
    st.tuples(st.integers(0, len(VALID_REPLY) - 1), st.integers(0, 255)).map(
        lambda ib: VALID_REPLY[: ib[0]] + bytes([ib[1]]) + VALID_REPLY[ib[0] + 1 :]
    ),
    st.binary(max_size=8).map(lambda noise: noise + VALID_REPLY),
    st.text("0123456789ABCDEFR -\r", max_size=40).map(lambda t: t.encode("ascii")),
    st.sampled_from([b"ERROR", b"ERROR - ", b"ERROR - \xff\r", b"ERROR\r\r", b"\r"]),
)
NOISY_CASES = st.tuples(st.sampled_from(sorted(COMMANDS)), NOISY_BYTES)


@examples(160)
@given(st.lists(REPLY_CASES, min_size=BATCH, max_size=BATCH))
def test_emulator_formatted_replies_parse_back_to_the_same_numbers(cases):
    for cmd, values in cases:
        spec = COMMANDS[cmd]
        fields = spec.reply * len(values) if spec.repeated_reply else spec.reply
        assert parse_reply(cmd, format_fields(values, fields)) == values


@examples(120)
@given(st.lists(COMMAND_CASES, min_size=BATCH, max_size=BATCH))
def test_encoded_commands_decode_to_the_same_numbers_in_the_firmware_parser(cases):
    for cmd, params in cases:
        line = encode_command(cmd, *params)
        assert line.endswith(b"\r") and b"\r" not in line[:-1]
        word, words = split_command(line[:-1])
        assert word == cmd
        fields = COMMANDS[cmd].params
        raw = [parse_hex_param(w) for w in words]
        decoded = tuple(
            sign_extend(r, f.bits) if f.signed else r for r, f in zip(raw, fields, strict=True)
        )
        assert decoded == params


@examples(120)
@given(st.lists(NOISY_CASES, min_size=BATCH, max_size=BATCH))
def test_arbitrary_bytes_never_raise_anything_but_board_error(cases):
    for cmd, line in cases:
        try:
            values = parse_reply(cmd, line)
        except BoardError:
            continue
        assert all(isinstance(v, int) for v in values)


# --- wheel speeds -----------------------------------------------------------------------------


def test_forward_speed_is_divided_once_by_the_travel_per_position():
    mpt = math.pi * 0.1524 / 36  # [m/position]
    assert EDDIE.metres_per_tick == pytest.approx(mpt)
    assert 0.3 / mpt == pytest.approx(22.557, abs=1e-3)
    assert wheel_speeds(0.3, 0.0, EDDIE) == (23, 23)


def test_spin_in_place_turns_the_wheels_in_opposite_directions():
    # w = 1 rad/s, track 0.3 m: each wheel 0.15 m/s = 11.28 positions/s, left backwards.
    assert 0.15 / EDDIE.metres_per_tick == pytest.approx(11.28, abs=0.01)
    assert wheel_speeds(0.0, 1.0, EDDIE) == (-11, 11)
    assert wheel_speeds(0.0, -1.0, EDDIE) == (11, -11)


def test_too_fast_commands_are_scaled_to_the_wheel_limit_keeping_the_turn_radius():
    limit = round_half_away(EDDIE.max_wheel_speed / EDDIE.metres_per_tick)  # 68 positions/s
    assert wheel_speeds(2.0, 0.0, EDDIE) == (limit, limit)
    left, right = wheel_speeds(2.0, 2.0, EDDIE)  # 1.7 and 2.3 m/s before scaling
    assert right == limit
    assert left / right == pytest.approx(1.7 / 2.3, abs=0.02)


def test_non_finite_velocity_is_rejected():
    with pytest.raises(BoardCommandError, match="GOSPD: velocity must be finite"):
        wheel_speeds(float("nan"), 0.0, EDDIE)


def test_rounding_is_half_away_from_zero():
    assert [round_half_away(x) for x in (2.5, -2.5, 0.49, -0.5, 22.557)] == [3, -3, 0, -1, 23]


# --- the driver against the emulator ----------------------------------------------------------


@pytest.fixture
def emulator():
    emu = EddieEmulator()
    yield emu
    emu.close()


@pytest.fixture
def board(emulator):
    with EddieBoard(emulator.serve_pty(), BoardConfig(timeout=0.2)) as b:
        yield b


def test_set_velocity_sends_gospd_with_the_pinned_numbers(board, emulator):
    assert board.set_velocity(0.3, 0.0) == (23, 23)
    assert board.set_velocity(0.0, 1.0) == (-11, 11)
    sent = [text for _, text in emulator.commands()]
    assert sent[-2:] == ["GOSPD 0017 0017", "GOSPD FFF5 000B"]


def test_typed_queries(board):
    assert board.version() == 0x000C
    assert board.hardware_version() == 0xFFFF
    assert board.distance() == (0, 0)
    assert board.speed() == (0, 0)
    assert board.heading() == 0
    assert board.ping() == (500, 1200)
    assert board.battery_voltage() == pytest.approx(12.6, abs=0.01)
    board.gpio_output(0x10000)
    board.gpio_high(0x10000)
    assert board.gpio_read() == 0x10000
    board.gpio_low(0x10000)
    assert board.gpio_read() == 0


def test_concurrent_callers_never_get_each_others_replies(board, emulator):
    board.go_speed(40, 40)
    results: dict[str, list[tuple[int, ...]]] = {"a": [], "b": [], "ver": []}
    errors: list[BaseException] = []

    def run(name: str, fn) -> None:
        try:
            for _ in range(150):
                results[name].append(fn())
        except BaseException as err:  # noqa: BLE001 - reported below
            errors.append(err)

    threads = [
        threading.Thread(target=run, args=("a", board.distance)),
        threading.Thread(target=run, args=("b", board.distance)),
        threading.Thread(target=run, args=("ver", lambda: (board.version(),))),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    for name in ("a", "b"):
        lefts = [left for left, _ in results[name]]
        assert lefts == sorted(lefts)  # driving forward: each caller sees its own DIST, in order
    assert set(results["ver"]) == {(0x000C,)}
    assert sum(1 for _, text in emulator.commands() if text == "DIST") == 300


@pytest.mark.parametrize("late_s", [0.25, 0.35])
def test_a_reply_that_comes_after_its_command_timed_out_is_not_the_next_commands_answer(
    board, emulator, late_s
):
    # HEAD's "000" would parse as a PING of one 0 mm echo: the late line must be dropped.
    emulator.inject(late_reply_s=late_s)  # past the 0.2 s timeout, within one more
    with pytest.raises(BoardError, match=r"HEAD: no reply within 0.2 s \(timeout\)"):
        board.heading()
    assert board.ping() == (500, 1200)
    assert board.late_replies_dropped == 1
    assert board.distance() == (0, 0) and board.late_replies_dropped == 1


def test_a_reply_that_never_comes_delays_only_the_next_command_by_one_timeout(board, emulator):
    emulator.inject(drop_next_replies=1)
    with pytest.raises(BoardError, match="HEAD: no reply"):
        board.heading()
    t0 = time.monotonic()
    assert board.ping() == (500, 1200)
    assert time.monotonic() - t0 < 0.2 + 0.15 and board.late_replies_dropped == 0


def test_open_failure_is_a_board_error():
    with pytest.raises(BoardError, match="cannot open Eddie board at /nonexistent/tty"):
        EddieBoard("/nonexistent/tty")


def test_commands_after_close_fail_cleanly(emulator):
    board = EddieBoard(emulator.serve_pty(), BoardConfig(timeout=0.2))
    board.close()
    with pytest.raises(BoardError, match="DIST: board connection .* is closed"):
        board.distance()


# --- the odometry poller ----------------------------------------------------------------------


def _drain(q: queue.Queue) -> list:
    items = []
    while True:
        try:
            items.append(q.get_nowait())
        except queue.Empty:
            return items


def test_poller_delivers_stamped_ticks_and_diagnostics(board):
    board.set_acceleration(511)
    board.go_speed(40, 40)
    seen = []
    poller = OdometryPoller(board, callback=seen.append, diagnostics_period_s=0.1)
    t0 = time.monotonic()
    with poller:
        time.sleep(0.3)  # 50 Hz: about 15 polls
        deadline = time.monotonic() + 3.0  # a loaded machine may poll late, never early
        while poller.stats().polls < 5 or poller.stats().battery_v is None:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        elapsed = time.monotonic() - t0
    ticks = _drain(poller.queue)
    stats = poller.stats()
    # Never faster than the configured 50 Hz (one poll of slack for the first one).
    assert 5 <= len(ticks) <= 50 * elapsed + 2
    assert ticks == seen
    assert stats.polls == len(ticks) and stats.errors == 0 and stats.dropped == 0
    stamps = [t.stamp_ns for t in ticks]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    lefts = [t.left for t in ticks]
    assert lefts == sorted(lefts) and lefts[-1] > lefts[0]
    assert stats.speeds == (40, 40)
    assert stats.heading_deg == 0
    assert stats.battery_v == pytest.approx(12.6, abs=0.01)
    assert stats.ping_mm == (500, 1200)


def test_poller_counts_errors_and_keeps_going(emulator):
    # 0.25 s: long enough that a loaded 2-core machine never times out a real reply (0.05 s
    # did, once, in CI), short enough that the one dropped reply costs little.
    with EddieBoard(emulator.serve_pty(), BoardConfig(timeout=0.25)) as board:
        poller = OdometryPoller(board, read_speed_heading=False, diagnostics_period_s=None)
        emulator.inject(drop_next_replies=1)
        with poller:
            deadline = time.monotonic() + 3.0
            while poller.stats().polls < 4:
                assert time.monotonic() < deadline
                time.sleep(0.02)
        stats = poller.stats()
    assert stats.errors == 1
    assert stats.last_error is not None and "no reply" in stats.last_error
    assert stats.polls >= 4


def test_full_queue_drops_the_oldest_ticks(board):
    poller = OdometryPoller(board, queue_size=3, read_speed_heading=False)
    with poller:
        deadline = time.monotonic() + 3.0
        while poller.stats().polls < 6:
            assert time.monotonic() < deadline
            time.sleep(0.02)
    stats = poller.stats()
    kept = _drain(poller.queue)
    assert len(kept) == 3
    assert stats.dropped == stats.polls - 3
    assert kept[-1] == stats.last_ticks


class _BurstPort:
    """A port whose reply has fully arrived: counts the read calls the driver makes."""

    def __init__(self, data: bytes) -> None:
        self.data, self.reads = bytearray(data), 0

    @property
    def in_waiting(self) -> int:
        return len(self.data)

    def read(self, n: int) -> bytes:
        self.reads += 1
        out = bytes(self.data[:n])
        del self.data[:n]
        return out


def test_a_reply_line_is_read_in_one_call_and_what_follows_it_is_left() -> None:
    # pyserial's read_until took one call (a select and a read) per byte.
    from types import SimpleNamespace

    port = _BurstPort(b"0000012C 0000012D\r" + b"00")
    line = EddieBoard._read_line(SimpleNamespace(board_cfg=BoardConfig()), port, "DIST")  # type: ignore[arg-type]
    assert line == b"0000012C 0000012D\r"
    assert port.reads == 1


def test_a_reply_without_terminator_is_an_incomplete_reply() -> None:
    from types import SimpleNamespace

    port = _BurstPort(b"0000012C")
    with pytest.raises(BoardError, match="incomplete reply"):
        EddieBoard._read_line(SimpleNamespace(board_cfg=BoardConfig(timeout=0.05)), port, "DIST")  # type: ignore[arg-type]


def test_ticks_are_stamped_when_the_board_read_the_command_not_when_the_reply_was_read(
    board, monkeypatch
):
    """A loaded host may take the reply long after the board sent it (the reading thread
    waits for the GIL): the encoder counts are as old as the command, and so is the stamp."""
    read_line = board._read_line

    def late(port, cmd):
        line = read_line(port, cmd)
        time.sleep(0.05)  # the thread got the GIL back 50 ms after the reply arrived
        return line

    monkeypatch.setattr(board, "_read_line", late)
    before = time.monotonic_ns()
    t = board.ticks()
    after = time.monotonic_ns()
    assert after - before >= 50_000_000
    on_line = len(b"DIST\r") * 10 * 1_000_000_000 // board.board_cfg.baudrate
    assert before + on_line <= t.stamp_ns < before + on_line + 20_000_000
