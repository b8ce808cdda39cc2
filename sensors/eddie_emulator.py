"""A software Eddie control board: the firmware's command parser plus a motor model.

The parser follows the Parallax firmware source (``docs/design/eddie_board.md``): bytes
are buffered until CR, BS deletes, other control bytes stay in the buffer (so ``"\\r\\n"`` makes
the *next* command invalid, as on the board), an empty line gets no reply, 255 bytes without CR
is an overflow. The command word is case-insensitive; parameters are at most 8 hex digits
separated by spaces or tabs; replies are ``OutputHex`` fields joined by one space and a CR; an
error is ``ERROR`` with `` - <reason>`` only in verbose mode. Checksum mode (NUL-terminated
commands) is not modelled.

Motor model, per wheel, in encoder positions: GOSPD sets a target speed [positions/s] that the
wheel approaches at the ACC limit [positions/s^2] (firmware default 200); GO sets power, modelled
as a target speed proportional to power (:data:`FULL_POWER_SPEED` at 127, assumed); TRVL/TURN
drive to a goal with a trapezoidal profile; ``STOP d`` decelerates to rest within ``d``
positions and ``STOP 0`` cuts power, modelled as an instant stop. Encoder counts are the floor of
the integrated position; SPD reports the current speed; HEAD is the firmware formula with the
positions-per-turn derived from the track: a full turn in place makes ``L - R`` equal
``2*pi*track / (pi*D/ticks)``. The board-side kill switch (WATCH [s]; KILL [ms] with
``kill_ms_command``, as the Open Propeller Project port has it) stops the wheels when no command
parsed for that long. Time comes from ``time_source`` (default ``time.monotonic``);
the model is integrated lazily when a command arrives or the state is read, so tests with a fake
clock are deterministic. Transports, one thread each: :meth:`EddieEmulator.serve_pty` (a raw
pseudo-terminal for pyserial) and :meth:`EddieEmulator.serve_socket` (``socket://127.0.0.1:PORT``);
:meth:`EddieEmulator.inject` adds faults, :meth:`EddieEmulator.reconnect` restores a disconnected
transport (same URL for sockets; a pty usually gets a new path).
"""

from __future__ import annotations

import collections
import logging
import math
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

from sensors.config import RobotConfig
from sensors.eddie import (
    ADC_CHANNELS,
    ADC_COUNTS_PER_VOLT,
    BATTERY_ADC_CHANNEL,
    BATTERY_DIVIDER,
    COMMANDS,
    HexField,
)

log = logging.getLogger(__name__)

CR, BS, HT, SPACE, NUL = 0x0D, 0x08, 0x09, 0x20, 0x00
BUFFER_LENGTH = 255  # [bytes] firmware input buffer; a full buffer is an overflow
MAX_PARAM_DIGITS = 8  # hex digits ParseHex accepts
FIRMWARE_VERSION = 0x000C  # VER reported by a board in the Parallax forum thread 143502
HARDWARE_VERSION = 0xFFFF  # HWVER read from unprogrammed EEPROM on the same board
DEFAULT_ACCELERATION = 200  # [positions/s^2] firmware MaxPosAccel at power-up
MAX_ACCELERATION = 511  # [positions/s^2] largest ACC the firmware accepts
MIN_TRAVEL_SPEED, MAX_TRAVEL_SPEED = 1, 127  # [positions/s] TRVL / TURN speed range
MAX_KILL_SWITCH_S = 26  # [s] largest WATCH
MAX_POWER = 127  # GO range
FULL_POWER_SPEED = 64.0  # [positions/s] assumed steady wheel speed at GO 127
GPIO_MASK = 0x0007_FFF0  # pins 4..18: outputable and not PING))) pins (assumed default)
DEFAULT_BATTERY_V = 12.6  # [V] charged 12 V lead-acid pack
DEFAULT_PING_MM = (500, 1200)  # [mm] two sensors
SUBSTEP_S = 0.005  # [s] integration step of the trapezoidal profiles
POLL_S = 0.02  # [s] transport threads check for shutdown this often
ERROR = b"ERROR"

Reason = Literal[
    "Invalid command",
    "Invalid parameter",
    "Too few parameters",
    "Too many parameters",
    "Overflow",
]


class FirmwareAbort(Exception):
    """The firmware's ``abort @Reason``: turns into an ERROR reply, never leaves the emulator."""

    def __init__(self, reason: Reason) -> None:
        super().__init__(reason)
        self.reason = reason


# --- pure helpers -----------------------------------------------------------------------------


def sign_extend(raw: int, bits: int) -> int:
    """Spin's ``~`` (8 bits) and ``~~`` (16 bits): the low ``bits`` of ``raw`` as signed."""
    raw &= (1 << bits) - 1
    return raw - (1 << bits) if raw >= 1 << (bits - 1) else raw


def parse_hex_param(word: bytes) -> int:
    """Firmware ParseHex: 1..8 hex digits (either case) -> unsigned 32-bit value."""
    if not word or len(word) > MAX_PARAM_DIGITS:
        raise FirmwareAbort("Invalid parameter")
    try:
        text = word.decode("ascii")
    except UnicodeDecodeError:
        raise FirmwareAbort("Invalid parameter") from None
    if any(c not in "0123456789abcdefABCDEF" for c in text):
        raise FirmwareAbort("Invalid parameter")
    return int(text, 16)


def split_command(line: bytes) -> tuple[str, list[bytes]]:
    """A buffered line (no CR) -> (upper-cased command word, parameter words).

    The command word ends at the first space or tab; parameters are separated by runs of
    spaces, tabs or NULs. Other bytes stay part of their word (and later fail to match).
    """
    cut = len(line)
    for i, byte in enumerate(line):
        if byte in (SPACE, HT):
            cut = i
            break
    word = line[:cut].decode("latin-1")
    cmd = "".join(c.upper() if "a" <= c <= "z" else c for c in word)
    rest = line[cut:].replace(b"\t", b" ").replace(b"\x00", b" ")
    return cmd, rest.split()


def format_fields(values: Sequence[int], fields: Sequence[HexField]) -> bytes:
    """Firmware OutputHex: each value as exactly ``digits`` upper-case hex digits (low bits),
    joined by one space, CR-terminated."""
    words = [f"{v & ((1 << f.bits) - 1):0{f.digits}X}" for v, f in zip(values, fields, strict=True)]
    return " ".join(words).encode("ascii") + b"\r"


def ramp(v0: float, target: float, accel: float, dt: float) -> tuple[float, float]:
    """Speed ``v0`` approaching ``target`` at most ``accel`` for ``dt``: (v1, distance), exact."""
    gap = target - v0
    if abs(gap) <= accel * dt:
        t_reach = abs(gap) / accel if accel > 0 else 0.0  # [s]
        return target, 0.5 * (v0 + target) * t_reach + target * (dt - t_reach)
    v1 = v0 + math.copysign(accel * dt, gap)
    return v1, 0.5 * (v0 + v1) * dt


@dataclass
class _Wheel:
    """Mutable motor state of one wheel, in encoder positions."""

    pos: float = 0.5  # [positions] integrated travel, starting mid-way between two counts
    vel: float = 0.0  # [positions/s]
    mode: Literal["idle", "power", "speed", "position", "stopping"] = "idle"
    target: float = 0.0  # [positions/s] speed/power modes
    goal: float = 0.0  # [positions] position mode
    cruise: float = 0.0  # [positions/s] position mode
    decel: float = 0.0  # [positions/s^2] stopping mode
    offset: int = 0  # [positions] counts at the last RST

    @property
    def count(self) -> int:
        return math.floor(self.pos + 1e-9)

    def halt(self) -> None:
        self.vel, self.target, self.mode = 0.0, 0.0, "idle"

    def step(self, dt: float, accel: float) -> None:
        if self.mode in ("speed", "power"):
            self.vel, d = ramp(self.vel, self.target, accel, dt)
            self.pos += d
        elif self.mode == "stopping":
            self.vel, d = ramp(self.vel, 0.0, self.decel, dt)
            self.pos += d
            if self.vel == 0.0:
                self.mode = "idle"
        elif self.mode == "position":
            self._step_position(dt, accel)

    def _step_position(self, dt: float, accel: float) -> None:
        remaining = self.goal - self.pos
        if abs(remaining) < 0.5 and abs(self.vel) <= accel * dt + 1e-9:
            self.pos, self.vel, self.mode = self.goal, 0.0, "idle"
            return
        brake = math.sqrt(2.0 * accel * abs(remaining))  # [positions/s] still able to stop
        wanted = math.copysign(min(self.cruise, brake), remaining)
        self.vel, d = ramp(self.vel, wanted, accel, dt)
        if abs(d) >= abs(remaining) and d * remaining > 0:
            self.pos, self.vel, self.mode = self.goal, 0.0, "idle"
        else:
            self.pos += d


# --- the emulator -----------------------------------------------------------------------------


class EddieEmulator:
    """Replies like an Eddie control board; thread-safe; see the module docstring."""

    def __init__(
        self,
        robot_cfg: RobotConfig | None = None,
        *,
        time_source: Callable[[], float] = time.monotonic,
        battery_v: float = DEFAULT_BATTERY_V,
        ping_mm: Sequence[int] = DEFAULT_PING_MM,
        firmware_version: int = FIRMWARE_VERSION,
        kill_ms_command: bool = False,
        hardware_version: int = HARDWARE_VERSION,
    ) -> None:
        self.robot_cfg = robot_cfg or RobotConfig()
        self.time_source = time_source
        # Encoder difference L - R for one full turn in place (the firmware's constant).
        self.positions_per_turn = (
            2.0 * math.pi * self.robot_cfg.track_width / self.robot_cfg.metres_per_tick
        )
        self._lock = threading.RLock()
        self._left, self._right = _Wheel(), _Wheel()
        self._t = time_source()  # [s] model time integrated up to
        self._last_command_t = self._t  # [s] last successfully parsed command (kill switch)
        self._accel = float(DEFAULT_ACCELERATION)  # [positions/s^2]
        self._kill_switch_s: float = 0  # [s] 0 = off
        self.kill_ms_command = kill_ms_command  # the OPP #8 port's KILL [ms]; Parallax: none
        self._verbose = False
        self._dira = 0
        self._outa = 0
        self._battery_v = battery_v
        self._ping_mm = tuple(ping_mm)
        self._versions = (firmware_version, hardware_version)
        self._buffer = bytearray()
        self._overflow = False
        self._garbage = b""
        self._drop_replies = 0
        self._late_replies: list[float] = []  # [s] delays of the next replies, in order
        self._held: list[tuple[float, bytes]] = []  # (monotonic release time, reply) queued
        self._log: collections.deque[tuple[float, str]] = collections.deque(maxlen=4096)
        # transport state
        self._kind: Literal["pty", "socket"] | None = None
        self._server: threading.Thread | None = None
        self._server_stop = threading.Event()
        self._master: int | None = None
        self._slave: int | None = None
        self._listener: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._socket_port = 0

    # -- model ---------------------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        """Integrate both wheels up to ``now``, applying the kill switch on the way."""
        if self._kill_switch_s and self._moving():
            kill_t = self._last_command_t + self._kill_switch_s
            if kill_t <= now:
                self._integrate(max(kill_t, self._t))
                self._left.halt()
                self._right.halt()
        self._integrate(now)

    def _integrate(self, now: float) -> None:
        while self._t < now:
            dt = min(SUBSTEP_S, now - self._t)
            self._left.step(dt, self._accel)
            self._right.step(dt, self._accel)
            self._t += dt
        self._t = max(self._t, now)

    def _moving(self) -> bool:
        return self._left.mode != "idle" or self._right.mode != "idle"

    def _counts(self) -> tuple[int, int]:
        return self._left.count - self._left.offset, self._right.count - self._right.offset

    def _heading_deg(self) -> int:
        left, right = self._counts()
        ppt = self.positions_per_turn
        return int(((left - right) % ppt) * 360.0 / ppt) % 360

    def distances(self) -> tuple[int, int]:
        """Encoder counts (left, right) as DIST would report them now."""
        with self._lock:
            self._advance(self.time_source())
            return self._counts()

    def positions(self) -> tuple[float, float]:
        """Integrated wheel travel (left, right) [positions], not floored: what the wheels really
        did, for a simulator that moves a robot by them."""
        with self._lock:
            self._advance(self.time_source())
            return self._left.pos, self._right.pos

    def wheel_positions(self) -> tuple[float, float]:
        """As :meth:`positions`: the name every board emulator gives the simulator."""
        return self.positions()

    def speeds(self) -> tuple[float, float]:
        """Current wheel speeds (left, right) [positions/s]."""
        with self._lock:
            self._advance(self.time_source())
            return self._left.vel, self._right.vel

    def heading(self) -> int:
        """HEAD now [deg], clockwise."""
        with self._lock:
            self._advance(self.time_source())
            return self._heading_deg()

    def commands(self) -> list[tuple[float, str]]:
        """Every command line received, with the model time [s] it arrived."""
        with self._lock:
            return list(self._log)

    # -- firmware: bytes in, bytes out -----------------------------------------------------------

    def feed(self, data: bytes) -> bytes:
        """Process received bytes like the firmware's main loop; return the bytes it would send."""
        out = bytearray()
        with self._lock:
            for byte in data:
                reply = self._on_byte(byte)
                if reply is None:
                    continue
                if self._drop_replies:
                    self._drop_replies -= 1
                    continue
                if self._late_replies or self._held:  # replies leave in order: queue behind
                    delay = self._late_replies.pop(0) if self._late_replies else 0.0
                    release = max([time.monotonic() + delay] + [t for t, _ in self._held])
                    self._held.append((release, self._garbage + reply))
                    self._garbage = b""
                    continue
                out += self._garbage + reply
                self._garbage = b""
        return bytes(out)

    def due_replies(self) -> bytes:
        """Held (late) replies whose time has come; the transports send them."""
        with self._lock:
            now = time.monotonic()
            due = [r for t, r in self._held if t <= now]
            self._held = [(t, r) for t, r in self._held if t > now]
        return b"".join(due)

    def _on_byte(self, byte: int) -> bytes | None:
        if self._overflow:
            if byte != CR:
                return None
            self._overflow = False
            return self._error("Overflow")
        self._buffer.append(byte)
        if len(self._buffer) == BUFFER_LENGTH:
            self._buffer.clear()
            self._overflow = True
            return None
        if byte == BS:
            del self._buffer[-2:]
            return None
        if byte != CR:
            return None
        line = bytes(self._buffer[:-1])
        self._buffer.clear()
        if not line:
            return None
        now = self.time_source()
        self._advance(now)
        self._log.append((now, line.decode("latin-1")))
        try:
            reply = self._execute(line)
        except FirmwareAbort as abort:
            return self._error(abort.reason)
        self._last_command_t = now
        return reply

    def _error(self, reason: Reason) -> bytes:
        return ERROR + (f" - {reason}".encode("ascii") if self._verbose else b"") + b"\r"

    def _execute(self, line: bytes) -> bytes:
        cmd, words = split_command(line)
        spec = COMMANDS.get(cmd)
        if spec is None or (cmd == "KILL" and not self.kill_ms_command):
            raise FirmwareAbort("Invalid command")
        if len(words) < len(spec.params):
            raise FirmwareAbort("Too few parameters")
        raw = [parse_hex_param(w) for w in words[: len(spec.params)]]
        if len(words) > len(spec.params):
            raise FirmwareAbort("Too many parameters")
        values = self._run(cmd, raw)
        if spec.repeated_reply:
            return format_fields(values, spec.reply * len(values))
        return format_fields(values, spec.reply)

    def _run(self, cmd: str, raw: list[int]) -> tuple[int, ...]:
        handler = getattr(self, f"_cmd_{cmd.lower()}")
        result: tuple[int, ...] = handler(*raw)
        return result

    # One method per command; arguments are the raw 32-bit parameters.

    def _cmd_go(self, left: int, right: int) -> tuple[int, ...]:
        for wheel, raw in ((self._left, left), (self._right, right)):
            power = max(-MAX_POWER, min(MAX_POWER, sign_extend(raw, 8)))
            wheel.mode, wheel.target = "power", power / MAX_POWER * FULL_POWER_SPEED
        return ()

    def _cmd_gospd(self, left: int, right: int) -> tuple[int, ...]:
        for wheel, raw in ((self._left, left), (self._right, right)):
            wheel.mode, wheel.target = "speed", float(sign_extend(raw, 16))
        return ()

    def _cmd_stop(self, distance: int) -> tuple[int, ...]:
        for wheel in (self._left, self._right):
            if distance == 0 or wheel.vel == 0.0:
                wheel.halt()
            else:
                wheel.mode, wheel.decel = "stopping", wheel.vel**2 / (2.0 * distance)
        return ()

    def _travel(self, left_delta: float, right_delta: float, speed: int) -> None:
        if not MIN_TRAVEL_SPEED <= speed <= MAX_TRAVEL_SPEED:
            raise FirmwareAbort("Invalid parameter")
        for wheel, delta in ((self._left, left_delta), (self._right, right_delta)):
            wheel.mode, wheel.goal, wheel.cruise = "position", wheel.pos + delta, float(speed)

    def _cmd_trvl(self, distance: int, speed: int) -> tuple[int, ...]:
        d = sign_extend(distance, 16)
        self._travel(d, d, speed)
        return ()

    def _cmd_turn(self, angle: int, speed: int) -> tuple[int, ...]:
        per_wheel = sign_extend(angle, 16) * (self.positions_per_turn / 2.0) / 360.0
        self._travel(per_wheel, -per_wheel, speed)
        return ()

    def _cmd_acc(self, accel: int) -> tuple[int, ...]:
        if accel > MAX_ACCELERATION:
            raise FirmwareAbort("Invalid parameter")
        self._accel = float(accel)
        return ()

    def _cmd_spd(self) -> tuple[int, ...]:
        return round(self._left.vel), round(self._right.vel)

    def _cmd_head(self) -> tuple[int, ...]:
        return (self._heading_deg(),)

    def _cmd_dist(self) -> tuple[int, ...]:
        return self._counts()

    def _cmd_rst(self) -> tuple[int, ...]:
        self._left.offset, self._right.offset = self._left.count, self._right.count
        return ()

    def _cmd_ver(self) -> tuple[int, ...]:
        return (self._versions[0],)

    def _cmd_hwver(self) -> tuple[int, ...]:
        return (self._versions[1],)

    def _cmd_verb(self, on: int) -> tuple[int, ...]:
        if on > 1:
            raise FirmwareAbort("Invalid parameter")
        self._verbose = bool(on)
        return ()

    def _cmd_watch(self, seconds: int) -> tuple[int, ...]:
        if seconds > MAX_KILL_SWITCH_S:
            raise FirmwareAbort("Invalid parameter")
        self._kill_switch_s = seconds
        return ()

    def _cmd_kill(self, ms: int) -> tuple[int, ...]:
        if ms > MAX_KILL_SWITCH_S * 1000 + 500:
            raise FirmwareAbort("Invalid parameter")
        self._kill_switch_s = ms / 1000.0
        return ()

    def _cmd_ping(self) -> tuple[int, ...]:
        return self._ping_mm

    def _cmd_adc(self) -> tuple[int, ...]:
        counts = [0] * ADC_CHANNELS
        battery = round(self._battery_v / BATTERY_DIVIDER * ADC_COUNTS_PER_VOLT)
        counts[BATTERY_ADC_CHANNEL] = max(0, min(0xFFF, battery))
        return tuple(counts)

    def _cmd_in(self, mask: int) -> tuple[int, ...]:
        self._dira &= ~(mask & GPIO_MASK)
        return ()

    def _cmd_out(self, mask: int) -> tuple[int, ...]:
        self._dira |= mask & GPIO_MASK
        return ()

    def _cmd_high(self, mask: int) -> tuple[int, ...]:
        self._outa |= mask & GPIO_MASK
        return ()

    def _cmd_low(self, mask: int) -> tuple[int, ...]:
        self._outa &= ~(mask & GPIO_MASK)
        return ()

    def _cmd_read(self) -> tuple[int, ...]:
        return (self._outa & self._dira & GPIO_MASK,)  # inputs float low

    # -- fault injection -----------------------------------------------------------------------

    def inject(
        self,
        garbage: bytes | None = None,
        drop_next_replies: int = 0,
        disconnect: bool = False,
        late_reply_s: float = 0.0,
    ) -> None:
        """``garbage`` is sent just before the next reply; the next ``drop_next_replies`` commands
        are executed but not answered; ``late_reply_s`` holds the next reply back that long (a
        board busy past the host's timeout); ``disconnect`` closes the pty or socket now."""
        with self._lock:
            if garbage:
                self._garbage += garbage
            self._drop_replies += drop_next_replies
            if late_reply_s > 0:
                self._late_replies.append(late_reply_s)
        if disconnect:
            self._shutdown_transport()

    # -- transports ----------------------------------------------------------------------------

    def serve_pty(self) -> str:
        """Serve a raw pseudo-terminal; returns the device path to open with pyserial."""
        if self._server is not None:
            raise RuntimeError("the emulator is already serving a transport")
        master, slave = os.openpty()
        tty.setraw(slave)
        self._master, self._slave, self._kind = master, slave, "pty"
        self._start_server(self._serve_pty, master)
        return os.ttyname(slave)

    def serve_socket(self) -> str:
        """Serve TCP on 127.0.0.1 (ephemeral port, kept across reconnects); returns its URL."""
        if self._server is not None:
            raise RuntimeError("the emulator is already serving a transport")
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self._socket_port))
        listener.listen(1)
        self._socket_port = listener.getsockname()[1]
        self._listener, self._kind = listener, "socket"
        self._start_server(self._serve_listener, listener)
        return f"socket://127.0.0.1:{self._socket_port}"

    def reconnect(self) -> str:
        """Bring a disconnected transport back; returns its (possibly new) path or URL."""
        kind = self._kind
        self._shutdown_transport()
        if kind == "socket":
            return self.serve_socket()
        if kind == "pty":
            return self.serve_pty()
        raise RuntimeError("the emulator has never served a transport")

    def close(self) -> None:
        self._shutdown_transport()
        self._kind = None

    def __enter__(self) -> EddieEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _start_server(self, target: Callable[..., None], *args: object) -> None:
        self._server_stop = threading.Event()
        self._server = threading.Thread(
            target=target, args=(*args, self._server_stop), name="eddie-emulator", daemon=True
        )
        self._server.start()

    def _shutdown_transport(self) -> None:
        """Stop the server thread first, then close what it used (no fd reuse races)."""
        self._server_stop.set()
        if self._server is not None:
            self._server.join()
            self._server = None
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None
        for sock in (self._conn, self._listener):
            if sock is not None:
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()
        self._conn = self._listener = None

    def _serve_pty(self, master: int, stop: threading.Event) -> None:
        while not stop.is_set():
            ready, _, _ = select.select([master], [], [], POLL_S)
            reply = self.due_replies()
            if ready:
                try:
                    data = os.read(master, 4096)
                except OSError:  # EIO: no slave side open any more
                    return
                reply += self.feed(data)
            while reply:
                reply = reply[os.write(master, reply) :]

    def _serve_listener(self, listener: socket.socket, stop: threading.Event) -> None:
        while not stop.is_set():
            ready, _, _ = select.select([listener], [], [], POLL_S)
            if not ready:
                continue
            conn, _ = listener.accept()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conn = conn
            self._serve_connection(conn, stop)
            if not stop.is_set():  # the client left; wait for the next one
                conn.close()
                self._conn = None

    def _serve_connection(self, conn: socket.socket, stop: threading.Event) -> None:
        while not stop.is_set():
            ready, _, _ = select.select([conn], [], [], POLL_S)
            reply = self.due_replies()
            if ready:
                try:
                    data = conn.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                reply += self.feed(data)
            if reply:
                try:
                    conn.sendall(reply)
                except OSError:
                    return
