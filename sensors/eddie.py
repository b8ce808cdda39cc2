"""Parallax Eddie control board: serial protocol, a thread-safe driver and an odometry poller.

Wire protocol (115200 8N1). A command is ``<CMD>[ <hex>]...\\r``; every command is answered by
exactly one line ending in ``\\r`` -- an empty line for commands that set something, hex fields
separated by one space for queries, ``ERROR\\r`` on failure (``ERROR - <reason>\\r`` in verbose
mode). Numbers are hex; signed values are two's complement at their field width.

The command table (widths, ranges, reply fields), the sources that confirm it (the firmware's
``Eddie.spin``, the ROS driver, forum reports) and what is still assumed (GOSPD units on firmware
1.3, the battery divider, the PING count) are in ``docs/design/eddie_board.md``.

Threading: one lock serialises command/reply pairs, so concurrent callers never see each other's
replies. Replies carry no command name, so after a timeout the next command first waits up to
one more ``timeout`` for the late reply and drops it (``late_replies_dropped``). A host-side
watchdog sends ``STOP 0`` when :meth:`EddieBoard.set_velocity` has not been called for
``BoardConfig.watchdog_timeout``. Serial failures close the port; the failing call
raises :class:`BoardError` ("disconnected") and a later call reopens the port once
``BoardConfig.reconnect_interval`` has passed.
"""

from __future__ import annotations

import logging
import math
import queue
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import serial

try:
    import termios  # a pty whose other side went away fails tcflush with termios.error
except ImportError:  # pragma: no cover - not POSIX
    termios = None  # type: ignore[assignment]

from sensors.config import BoardConfig, RobotConfig
from sensors.motor_board import MotorBoard
from sensors.types import NS_PER_S, SensorError, WheelTicks

log = logging.getLogger(__name__)

_LINK_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError) + (
    (termios.error,) if termios is not None else ()
)

TERMINATOR = b"\r"
MAX_LINE_BYTES = 255  # [bytes] firmware input/output buffer, terminator included
MAX_PINGS = 16  # PING-able pins 0..15
ADC_CHANNELS = 8
BATTERY_ADC_CHANNEL = 7  # last channel (eddiebot-ros wiring)
ADC_COUNTS_PER_VOLT = 819.0  # [counts/V] 12-bit converter over 5 V
BATTERY_DIVIDER = 3.21  # [-] battery voltage / ADC input voltage
DIAGNOSTICS_PERIOD_S = 1.0  # [s] ADC and PING polling period of OdometryPoller
POLLER_QUEUE_SIZE = 256  # WheelTicks kept when nobody drains the queue
WATCHDOG_CHECK_PERIOD_S = 0.02  # [s] STOP goes out within watchdog_timeout + this
LATE_REPLY_POLL_S = 0.002  # [s] a timed-out command's late reply is looked for this often


class BoardError(SensorError):
    """The control board did not answer, answered ERROR, or answered something unreadable."""


class BoardCommandError(BoardError, ValueError):
    """A command could not be encoded: unknown name, wrong parameter count or value range."""


# --- protocol tables --------------------------------------------------------------------------


@dataclass(frozen=True)
class HexField:
    """One number on the wire: two's complement over ``bits`` when signed, range [lo, hi]."""

    name: str
    bits: int  # width on the wire; a multiple of 4
    signed: bool
    lo: int
    hi: int

    @property
    def digits(self) -> int:
        return self.bits // 4

    def to_wire(self, value: int) -> int:
        return value & ((1 << self.bits) - 1)

    def from_wire(self, raw: int) -> int:
        if self.signed and raw >= 1 << (self.bits - 1):
            return raw - (1 << self.bits)
        return raw


def _signed(name: str, bits: int, lo: int | None = None, hi: int | None = None) -> HexField:
    half = 1 << (bits - 1)
    return HexField(name, bits, True, -half if lo is None else lo, half - 1 if hi is None else hi)


def _unsigned(name: str, bits: int, lo: int = 0, hi: int | None = None) -> HexField:
    return HexField(name, bits, False, lo, (1 << bits) - 1 if hi is None else hi)


@dataclass(frozen=True)
class CommandSpec:
    params: tuple[HexField, ...] = ()
    reply: tuple[HexField, ...] = ()  # fixed reply fields; empty = bare acknowledgement
    repeated_reply: bool = False  # reply is 0..MAX_PINGS copies of reply[0] (PING)


_MASK = _unsigned("pin mask", 32)
_TRAVEL_SPEED = _unsigned("speed [positions/s]", 8, lo=1, hi=127)

COMMANDS: dict[str, CommandSpec] = {
    "GO": CommandSpec((_signed("left power", 8, -127, 127), _signed("right power", 8, -127, 127))),
    "GOSPD": CommandSpec((_signed("left speed", 16), _signed("right speed", 16))),
    "STOP": CommandSpec((_unsigned("stop distance [positions]", 32, hi=2**31 - 1),)),
    "TRVL": CommandSpec((_signed("distance [positions]", 16), _TRAVEL_SPEED)),
    "TURN": CommandSpec((_signed("angle [deg]", 16), _TRAVEL_SPEED)),
    "ACC": CommandSpec((_unsigned("acceleration [positions/s^2]", 16, hi=511),)),
    "SPD": CommandSpec(reply=(_signed("left speed", 16), _signed("right speed", 16))),
    "HEAD": CommandSpec(reply=(_signed("heading [deg]", 12),)),
    "DIST": CommandSpec(reply=(_signed("left distance", 32), _signed("right distance", 32))),
    "RST": CommandSpec(),
    "VER": CommandSpec(reply=(_unsigned("firmware version", 16),)),
    "HWVER": CommandSpec(reply=(_unsigned("hardware version", 16),)),
    "VERB": CommandSpec((_unsigned("verbose", 4, hi=1),)),
    "WATCH": CommandSpec((_unsigned("kill-switch time [s]", 8, hi=26),)),
    # Open Propeller Project #8 firmware only (ddegn/EddieFirmware); Parallax's answers ERROR.
    "KILL": CommandSpec((_unsigned("kill-switch time [ms]", 16, hi=26500),)),
    "PING": CommandSpec(reply=(_unsigned("range [mm]", 12),), repeated_reply=True),
    "ADC": CommandSpec(reply=tuple(_unsigned(f"adc{i}", 12) for i in range(ADC_CHANNELS))),
    "IN": CommandSpec((_MASK,)),
    "OUT": CommandSpec((_MASK,)),
    "HIGH": CommandSpec((_MASK,)),
    "LOW": CommandSpec((_MASK,)),
    "READ": CommandSpec(reply=(_unsigned("pin states", 32),)),
}

_ERROR_LINE = re.compile(rb"ERROR(?: - ([\x20-\x7e]{1,240}))?\r")
_HEX_FIELD = {n: re.compile(rb"[0-9A-Fa-f]{%d}" % n) for n in (3, 4, 8)}
_REPR_LIMIT = 120  # [chars] of a bad reply quoted in an error message


def command_spec(cmd: str) -> CommandSpec:
    """The table entry for ``cmd``; BoardCommandError when the board has no such command."""
    try:
        return COMMANDS[cmd]
    except KeyError:
        raise BoardCommandError(f"{cmd!r}: not an Eddie board command") from None


def _quote(line: bytes) -> str:
    text = repr(bytes(line))
    return text if len(text) <= _REPR_LIMIT else text[: _REPR_LIMIT - 3] + "..."


# --- pure protocol functions ------------------------------------------------------------------


def encode_command(cmd: str, *params: int, widths: Sequence[HexField] | None = None) -> bytes:
    """``"GOSPD", 23, -23`` -> ``b"GOSPD 0017 FFE9\\r"``.

    ``widths`` overrides the table's parameter fields. Signed values are written at their full
    width (the firmware sign-extends from that width); unsigned ones without leading zeros.
    Raises BoardCommandError (a ValueError) naming the command on a bad name, count or range.
    """
    fields = tuple(widths) if widths is not None else command_spec(cmd).params
    if len(params) != len(fields):
        raise BoardCommandError(f"{cmd}: expects {len(fields)} parameter(s), got {len(params)}")
    words = [cmd]
    for field, value in zip(fields, params, strict=True):
        if isinstance(value, bool) or not isinstance(value, int):
            raise BoardCommandError(f"{cmd}: {field.name} must be an integer, got {value!r}")
        if not field.lo <= value <= field.hi:
            raise BoardCommandError(
                f"{cmd}: {field.name} {value} is out of range [{field.lo}, {field.hi}]"
            )
        if field.signed:
            words.append(f"{field.to_wire(value):0{field.digits}X}")
        else:
            words.append(f"{value:X}")
    line = " ".join(words).encode("ascii") + TERMINATOR
    if len(line) > MAX_LINE_BYTES:
        raise BoardCommandError(f"{cmd}: command is {len(line)} bytes, over {MAX_LINE_BYTES}")
    return line


def parse_reply(cmd: str, line: bytes) -> tuple[int, ...]:
    """One reply line (terminator included) -> its numbers, sign applied.

    Strict: exactly the field count and digit count the command produces, one space between
    fields, one CR at the end. ``ERROR`` lines raise BoardError ``"<cmd>: board replied ERROR -
    <reason>"``; anything else unexpected raises BoardError naming the command and quoting the
    bytes. Never raises anything but BoardError for any bytes.
    """
    spec = command_spec(cmd)
    line = bytes(line)
    if line.startswith(b"ERROR"):
        match = _ERROR_LINE.fullmatch(line)
        if match is None:
            raise BoardError(f"{cmd}: malformed ERROR reply {_quote(line)}")
        reason = match.group(1)
        suffix = f" - {reason.decode('ascii')}" if reason else ""
        raise BoardError(f"{cmd}: board replied ERROR{suffix}")
    if len(line) > MAX_LINE_BYTES:
        raise BoardError(f"{cmd}: reply of {len(line)} bytes is longer than the board can send")
    if not line.endswith(TERMINATOR) or TERMINATOR in line[:-1]:
        raise BoardError(f"{cmd}: incomplete or run-together reply {_quote(line)}")
    body = line[:-1]
    words = body.split(b" ") if body else []
    if spec.repeated_reply:
        fields: tuple[HexField, ...] = spec.reply * len(words)
        count_ok = len(words) <= MAX_PINGS
    else:
        fields = spec.reply
        count_ok = len(words) == len(fields)
    if not count_ok:
        raise BoardError(f"{cmd}: expected {_describe(spec)}, got {_quote(line)}")
    values = []
    for field, word in zip(fields, words, strict=True):
        if _HEX_FIELD[field.digits].fullmatch(word) is None:
            raise BoardError(f"{cmd}: expected {_describe(spec)}, got {_quote(line)}")
        values.append(field.from_wire(int(word, 16)))
    return tuple(values)


def _describe(spec: CommandSpec) -> str:
    if not spec.reply:
        return "an empty acknowledgement"
    digits = spec.reply[0].digits
    if spec.repeated_reply:
        return f"up to {MAX_PINGS} fields of {digits} hex digits"
    return f"{len(spec.reply)} field(s) of {digits} hex digits"


def round_half_away(x: float) -> int:
    """2.5 -> 3, -2.5 -> -3 (Python's round() would give 2 and -2)."""
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


def wheel_speeds(v: float, w: float, robot: RobotConfig) -> tuple[int, int]:
    """Body twist (v [m/s], w [rad/s], counter-clockwise positive) -> GOSPD (left, right).

    v_left = v - w*track/2 and v_right = v + w*track/2 [m/s], divided once by the travel per
    encoder position (pi*D/ticks) into [positions/s], rounded half away from zero. When a wheel
    would exceed ``robot.max_wheel_speed`` both are scaled by the same factor, which keeps the
    turning radius.
    """
    if not (math.isfinite(v) and math.isfinite(w)):
        raise BoardCommandError(f"GOSPD: velocity must be finite, got v={v!r}, w={w!r}")
    half_diff = 0.5 * w * robot.track_width  # [m/s]
    v_left, v_right = v - half_diff, v + half_diff  # [m/s]
    peak = max(abs(v_left), abs(v_right))
    if peak > robot.max_wheel_speed:
        scale = robot.max_wheel_speed / peak
        v_left, v_right = v_left * scale, v_right * scale
    limit = COMMANDS["GOSPD"].params[0].hi
    left = round_half_away(v_left / robot.metres_per_tick)
    right = round_half_away(v_right / robot.metres_per_tick)
    return max(-limit, min(limit, left)), max(-limit, min(limit, right))


def heading_degrees(raw: int) -> int:
    """HEAD field (possibly a negative 12-bit value) -> clockwise heading in 0..359 [deg]."""
    return raw % 360


def battery_voltage(adc_counts: Sequence[int]) -> float:
    """ADC reply -> battery voltage [V]."""
    return adc_counts[BATTERY_ADC_CHANNEL] / ADC_COUNTS_PER_VOLT * BATTERY_DIVIDER


# --- the driver -------------------------------------------------------------------------------


class EddieBoard(MotorBoard):
    """Typed access to the control board over pyserial (a device, ``socket://`` or ``loop://``).

    Opening is immediate: a port that cannot be opened raises BoardError. Use as a context
    manager, or call :meth:`close` (which also sends ``STOP 0`` if the watchdog is armed).
    Implements :class:`sensors.motor_board.MotorBoard`.
    """

    kind = "eddie"

    def __init__(
        self,
        port_or_url: str | None = None,
        board_cfg: BoardConfig | None = None,
        robot_cfg: RobotConfig | None = None,
    ) -> None:
        self.board_cfg = board_cfg or BoardConfig()
        self.robot_cfg = robot_cfg or RobotConfig()
        self.url = port_or_url or self.board_cfg.port
        self._lock = threading.RLock()  # one command/reply pair at a time
        self._port: Any = None
        self._down_since: float | None = None  # [s] monotonic time of the last failure
        self._closed = False
        self._last_velocity_s = 0.0  # [s] monotonic time of the last set_velocity
        self._watchdog_armed = False
        self._watchdog: threading.Thread | None = None
        self._stop_event = threading.Event()
        # [s] monotonic time a command went unanswered (timed out): its reply may still come.
        self._unanswered_at: float | None = None
        self.late_replies_dropped = 0  # replies that came after their command had timed out
        self._port = self._open()

    # -- connection ----------------------------------------------------------------------------

    def _open(self) -> Any:
        try:
            return serial.serial_for_url(
                self.url,
                baudrate=self.board_cfg.baudrate,
                timeout=self.board_cfg.timeout,
                write_timeout=self.board_cfg.timeout,
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise BoardError(f"cannot open Eddie board at {self.url}: {err}") from err

    def _ensure_open(self, cmd: str) -> Any:
        if self._closed:
            raise BoardError(f"{cmd}: board connection {self.url} is closed")
        if self._port is not None:
            return self._port
        assert self._down_since is not None
        wait = self._down_since + self.board_cfg.reconnect_interval - time.monotonic()
        if wait > 0:
            raise BoardError(f"{cmd}: disconnected from {self.url} (reconnect in {wait:.2f} s)")
        try:
            self._port = self._open()
        except BoardError as err:
            self._down_since = time.monotonic()
            raise BoardError(f"{cmd}: disconnected from {self.url}; reconnect failed") from err
        self._down_since = None
        log.info("reconnected to Eddie board at %s", self.url)
        return self._port

    def _drop_connection(self) -> None:
        port, self._port = self._port, None
        self._down_since = time.monotonic()
        if port is not None:
            # pyserial's socket close sleeps 0.3 s; do not hold the command lock for that.
            threading.Thread(target=_close_quietly, args=(port,), daemon=True).start()

    @property
    def connected(self) -> bool:
        return self._port is not None

    def close(self) -> None:
        """Stop the watchdog, send STOP 0 if motors may be running, close the port."""
        self._stop_event.set()
        if self._watchdog is not None and self._watchdog is not threading.current_thread():
            self._watchdog.join()
        with self._lock:
            if self._watchdog_armed and self._port is not None:
                try:
                    self._transact("STOP", (0,))
                except BoardError as err:
                    log.warning("could not stop the motors while closing: %s", err)
            self._watchdog_armed = False
            self._closed = True
            if self._port is not None:
                _close_quietly(self._port)
                self._port = None

    def __enter__(self) -> EddieBoard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- one transaction -----------------------------------------------------------------------

    def _read_line(self, port: Any, cmd: str) -> bytes:
        """One reply line. pyserial's ``read_until`` reads a byte per call (a select and a
        read each, holding the GIL in between: 35 % of the poller's GIL time at 50 Hz on a
        live run); this takes whatever has arrived per call instead. Bytes after the
        terminator stay unread (the next transaction flushes them)."""
        buf = bytearray()
        # The line gets the port timeout; a read under way when it runs out may add one more.
        deadline = time.monotonic() + self.board_cfg.timeout
        while len(buf) < MAX_LINE_BYTES and (not buf or time.monotonic() < deadline):
            want = min(max(port.in_waiting, 1), MAX_LINE_BYTES - len(buf))
            chunk = port.read(want)  # blocks up to the port's timeout for the first byte
            if not chunk:
                break
            end = chunk.find(TERMINATOR)
            if end >= 0:
                buf += chunk[: end + len(TERMINATOR)]
                break
            buf += chunk
        line = bytes(buf)
        if line.endswith(TERMINATOR):
            return line
        if len(line) >= MAX_LINE_BYTES:
            raise BoardError(f"{cmd}: reply longer than {MAX_LINE_BYTES} bytes: {_quote(line)}")
        if not line:
            raise BoardError(f"{cmd}: no reply within {self.board_cfg.timeout} s (timeout)")
        raise BoardError(
            f"{cmd}: incomplete reply {_quote(line)} within {self.board_cfg.timeout} s (timeout)"
        )

    def _await_late_reply(self, port: Any) -> None:
        """The board answers in order and its replies carry no command name: a reply that comes
        after its command timed out would be read as the answer to the next command (a late
        HEAD ``000`` parses as a PING). So the next command first waits, up to one more
        ``timeout`` after the timeout, for that reply and drops it (counted and logged)."""
        assert self._unanswered_at is not None
        deadline = self._unanswered_at + self.board_cfg.timeout
        self._unanswered_at = None
        while time.monotonic() < deadline:
            waiting = port.in_waiting
            if waiting and TERMINATOR in port.read(waiting):
                self.late_replies_dropped += 1
                log.warning("a reply came after its command had timed out: dropped")
                return
            time.sleep(LATE_REPLY_POLL_S)

    def _transact(
        self, cmd: str, params: tuple[int, ...], widths: Sequence[HexField] | None = None
    ) -> tuple[tuple[int, ...], int]:
        """Send one command, return (reply values, stamp_ns of when the board read it).

        The stamp is taken just before the command is written, plus the time the command takes
        on the line (10 bits a byte): the board samples (e.g. DIST's encoder counts) as the
        command's last byte arrives. Stamped when the reply had been read instead, the stamp
        also held however long this thread then waited for the GIL: on a loaded live run
        readings 20 ms apart came stamped 0.6-80 ms apart, and the rates the filter made of them
        (the same ticks over a wrong interval) spiked to 1000 deg/s."""
        line = encode_command(cmd, *params, widths=widths)
        with self._lock:
            port = self._ensure_open(cmd)
            try:
                if self._unanswered_at is not None:
                    self._await_late_reply(port)
                port.reset_input_buffer()  # stale bytes from an earlier timeout or garbage
                sent_ns = time.monotonic_ns()
                port.write(line)
                try:
                    reply = self._read_line(port, cmd)
                except BoardError:
                    self._unanswered_at = time.monotonic()
                    raise
            except _LINK_ERRORS as err:
                self._unanswered_at = None
                self._drop_connection()
                raise BoardError(f"{cmd}: disconnected from {self.url}: {err}") from err
        on_line_ns = len(line) * 10 * NS_PER_S // max(int(self.board_cfg.baudrate), 1)
        return parse_reply(cmd, reply), sent_ns + on_line_ns

    def command(
        self, cmd: str, *params: int, widths: Sequence[HexField] | None = None
    ) -> tuple[int, ...]:
        """Any command from :data:`COMMANDS`; returns the reply's numbers.

        ``widths`` overrides the parameter fields, for firmware variants with other ranges
        (e.g. ACC up to 2047 in later ports).
        """
        return self._transact(cmd, params, widths)[0]

    # -- motion --------------------------------------------------------------------------------

    def go(self, left_power: int, right_power: int) -> None:
        """Open-loop motor power, -127..127 per wheel."""
        self.command("GO", left_power, right_power)

    def go_speed(self, left: int, right: int) -> None:
        """Closed-loop wheel speeds [positions/s]; ramps at the ACC limit."""
        self.command("GOSPD", left, right)

    def stop(self, distance: int = 0) -> None:
        """Decelerate to a stop within ``distance`` [positions]; 0 cuts motor power at once."""
        self.command("STOP", distance)

    def travel(self, distance: int, speed: int) -> None:
        """Drive ``distance`` [positions] (negative = backward) at ``speed`` 1..127."""
        self.command("TRVL", distance, speed)

    def turn(self, angle_deg: int, speed: int) -> None:
        """Rotate in place by ``angle_deg`` (clockwise positive) at ``speed`` 1..127."""
        self.command("TURN", angle_deg, speed)

    def set_acceleration(self, acceleration: int) -> None:
        """Speed ramp limit [positions/s^2], 0..511 (firmware default 200)."""
        self.command("ACC", acceleration)

    def set_velocity(self, v: float, w: float) -> tuple[int, int]:
        """Drive the body twist (v [m/s], w [rad/s]); returns the GOSPD speeds sent.

        Arms the host watchdog: without another call for ``watchdog_timeout`` it sends STOP 0.
        """
        return self._go_speed_watched(*wheel_speeds(v, w, self.robot_cfg))

    def set_wheel_speeds(self, left: float, right: float) -> tuple[int, int]:
        """Wheel speeds [m/s] as GOSPD [positions/s] (both scaled down together above
        ``robot.max_wheel_speed``); arms the host watchdog as :meth:`set_velocity` does."""
        v, w = (left + right) / 2, (right - left) / self.robot_cfg.track_width
        return self.set_velocity(v, w)

    def _go_speed_watched(self, left: int, right: int) -> tuple[int, int]:
        with self._lock:
            self._last_velocity_s = time.monotonic()
            self._watchdog_armed = True  # armed before sending: the GOSPD may arrive anyway
            self._start_watchdog()
            self._transact("GOSPD", (left, right))
            # The timeout runs from when the board had the command (its reply is in), so the
            # STOP never reaches it less than watchdog_timeout after the GOSPD did, however
            # late this thread got to write it (CI: 0.2465 s with the time taken before).
            self._last_velocity_s = time.monotonic()
        return left, right

    def _start_watchdog(self) -> None:
        if self._watchdog is None:
            self._watchdog = threading.Thread(
                target=self._watchdog_loop, name="eddie-watchdog", daemon=True
            )
            self._watchdog.start()

    def _watchdog_loop(self) -> None:
        timeout = self.board_cfg.watchdog_timeout
        period = min(WATCHDOG_CHECK_PERIOD_S, timeout / 10)  # [s]
        while not self._stop_event.wait(period):
            with self._lock:
                if not self._watchdog_armed or self._closed:
                    continue
                if time.monotonic() - self._last_velocity_s < timeout:
                    continue
                try:
                    self._transact("STOP", (0,))
                except BoardError as err:
                    log.warning("watchdog STOP failed (will retry): %s", err)
                    continue
                self._watchdog_armed = False
                log.info("no velocity command for %.2f s: motors stopped", timeout)

    def arm_failsafe(self, timeout_s: float) -> str:
        """The board's kill switch for a host that dies: KILL in milliseconds where the firmware
        has it (the Open Propeller Project port), else WATCH in whole seconds (at least 1: the
        Parallax firmware cannot stop a dead host's motors sooner). The host watchdog
        (``board.watchdog_timeout``) stops a host that lives but goes quiet."""
        quiet = f"host watchdog {self.board_cfg.watchdog_timeout:.2f} s (host quiet)"
        ms = max(1, min(26500, round(timeout_s * 1000)))
        try:
            self.command("KILL", ms)
            return f"board KILL {ms} ms (host dead), {quiet}"
        except BoardError as err:
            if not self.connected:
                raise
            log.info("no KILL on this firmware (%s): WATCH in whole seconds", err)
        seconds = max(1, min(26, math.ceil(timeout_s)))
        self.watchdog(seconds)
        return f"board WATCH {seconds} s (host dead), {quiet}"

    def probe(self) -> str:
        self.distance()
        return "DIST"

    def diagnostics(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "board": "Parallax Eddie",
            "port": self.url,
            "late_replies_dropped": self.late_replies_dropped,
            "connected": self.connected,
        }
        try:
            out["firmware"] = f"VER {self.version():04X}, HWVER {self.hardware_version():04X}"
        except BoardError as err:
            out["firmware"] = f"unavailable ({err})"
        return out

    # -- queries -------------------------------------------------------------------------------

    def speed(self) -> tuple[int, int]:
        """Measured wheel speeds (left, right) [positions/s]."""
        left, right = self.command("SPD")
        return left, right

    def heading(self) -> int:
        """Heading from the encoder difference since the last reset, clockwise, 0..359 [deg]."""
        (raw,) = self.command("HEAD")
        return heading_degrees(raw)

    def distance(self) -> tuple[int, int]:
        """Cumulative encoder positions (left, right) since the last reset."""
        left, right = self.command("DIST")
        return left, right

    def ticks(self) -> WheelTicks:
        """DIST stamped (``time.monotonic_ns()``) when the board read the command."""
        (left, right), stamp_ns = self._transact("DIST", ())
        return WheelTicks(stamp_ns=stamp_ns, left=left, right=right)

    def reset(self) -> None:
        """Zero the distances and the heading."""
        self.command("RST")

    def version(self) -> int:
        return self.command("VER")[0]

    def hardware_version(self) -> int:
        return self.command("HWVER")[0]

    def verbose(self, on: bool) -> None:
        """In verbose mode ERROR replies carry a reason (`` - Invalid parameter``)."""
        self.command("VERB", int(on))

    def watchdog(self, seconds: int) -> None:
        """Board-side kill switch (WATCH, whole seconds 0..26, 0 = off)."""
        self.command("WATCH", seconds)

    def ping(self) -> tuple[int, ...]:
        """One range per active PING))) sensor [mm]; 0 = no echo."""
        return self.command("PING")

    def adc(self) -> tuple[int, ...]:
        """Eight raw 12-bit ADC readings."""
        return self.command("ADC")

    def battery_voltage(self) -> float:
        """Battery voltage [V] from the ADC."""
        return battery_voltage(self.adc())

    # -- GPIO ----------------------------------------------------------------------------------

    def gpio_input(self, mask: int) -> None:
        self.command("IN", mask)

    def gpio_output(self, mask: int) -> None:
        self.command("OUT", mask)

    def gpio_high(self, mask: int) -> None:
        self.command("HIGH", mask)

    def gpio_low(self, mask: int) -> None:
        self.command("LOW", mask)

    def gpio_read(self) -> int:
        return self.command("READ")[0]


def _close_quietly(port: Any) -> None:
    try:
        port.close()
    except _LINK_ERRORS:
        pass


# --- polling ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PollerStats:
    """A snapshot of :class:`OdometryPoller` counters and latest readings."""

    polls: int  # DIST replies received
    errors: int  # failed board transactions (all commands)
    dropped: int  # WheelTicks discarded because the queue was full
    last_error: str | None
    last_ticks: WheelTicks | None
    speeds: tuple[int, int] | None  # [positions/s]
    heading_deg: int | None  # clockwise [deg]
    battery_v: float | None  # [V]
    ping_mm: tuple[int, ...] | None  # [mm]


class OdometryPoller:
    """Polls DIST (and SPD, HEAD) at ``board_cfg.poll_rate`` into a bounded queue and/or callback.

    ADC (battery) and PING are read every ``diagnostics_period_s``. Board errors are counted and
    logged, never fatal; when the queue is full the oldest WheelTicks is dropped and counted.
    """

    def __init__(
        self,
        board: MotorBoard,
        board_cfg: BoardConfig | None = None,
        *,
        callback: Callable[[WheelTicks], None] | None = None,
        queue_size: int = POLLER_QUEUE_SIZE,
        read_speed_heading: bool = True,
        diagnostics_period_s: float | None = DIAGNOSTICS_PERIOD_S,
    ) -> None:
        self.board = board
        self.board_cfg = board_cfg or board.board_cfg  # type: ignore[attr-defined]
        self.callback = callback
        self.queue: queue.Queue[WheelTicks] = queue.Queue(maxsize=queue_size)
        self.read_speed_heading = read_speed_heading
        self.diagnostics_period_s = diagnostics_period_s
        self._stats_lock = threading.Lock()
        self._stats = PollerStats(0, 0, 0, None, None, None, None, None, None)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> OdometryPoller:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="eddie-poller", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __enter__(self) -> OdometryPoller:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stats(self) -> PollerStats:
        with self._stats_lock:
            return self._stats

    def _update(self, **changes: Any) -> None:
        with self._stats_lock:
            self._stats = replace(self._stats, **changes)

    def _count_error(self, err: SensorError) -> None:
        log.debug("poll failed: %s", err)
        with self._stats_lock:
            s = self._stats
            self._stats = replace(s, errors=s.errors + 1, last_error=str(err))

    def _push(self, ticks: WheelTicks) -> None:
        while True:
            try:
                self.queue.put_nowait(ticks)
                return
            except queue.Full:
                try:
                    self.queue.get_nowait()
                except queue.Empty:
                    continue
                with self._stats_lock:
                    self._stats = replace(self._stats, dropped=self._stats.dropped + 1)

    def _poll_once(self) -> None:
        try:
            ticks = self.board.ticks()
        except SensorError as err:
            self._count_error(err)
            return
        last = self._stats.last_ticks
        if last is not None and ticks.stamp_ns == last.stamp_ns:
            return  # a tacho board between two readings: nothing new
        with self._stats_lock:
            self._stats = replace(self._stats, polls=self._stats.polls + 1, last_ticks=ticks)
        self._push(ticks)
        if self.callback is not None:
            try:
                self.callback(ticks)
            except Exception:  # a consumer's bug must not kill odometry
                log.exception("WheelTicks callback raised")
        if self.read_speed_heading and isinstance(self.board, EddieBoard):
            try:
                self._update(speeds=self.board.speed(), heading_deg=self.board.heading())
            except SensorError as err:
                self._count_error(err)

    def _poll_diagnostics(self) -> None:
        try:
            self._update(battery_v=self.board.battery_voltage())
            if isinstance(self.board, EddieBoard):
                self._update(ping_mm=self.board.ping())
        except SensorError as err:
            self._count_error(err)

    def _run(self) -> None:
        period = 1.0 / self.board_cfg.poll_rate  # [s]
        next_poll = time.monotonic()
        next_diag = next_poll
        while not self._stop.is_set():
            self._poll_once()
            now = time.monotonic()
            if self.diagnostics_period_s is not None and now >= next_diag:
                self._poll_diagnostics()
                next_diag = now + self.diagnostics_period_s
            next_poll += period
            if next_poll < now:  # fell behind (slow link): skip missed slots, keep the phase
                next_poll += math.ceil((now - next_poll) / period) * period
            self._stop.wait(max(0.0, next_poll - time.monotonic()))
