"""CARMEN log files (``.clf``, ``.log``, either gzipped) as laser scans and odometry.

Messages read (one per line, whitespace-separated; ``#`` starts a comment line)::

    FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp
    ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
                n r1..rn m e1..em laser_x laser_y laser_theta robot_x robot_y robot_theta
                tv rv forward_safety_dist side_safety_dist turn_axis
                ipc_timestamp hostname logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp hostname logger_timestamp
    PARAM name value hostname logger_timestamp

FLASER carries no laser geometry: like CARMEN's ``carmen_laser_guess_angle_increment`` it starts
at -90 deg with 1 deg (180/181 beams), 0.5 deg (360/361) or 0.25 deg (400/401) steps, unless
``PARAM laser_front_laser_fov`` / ``laser_front_laser_resolution`` [deg] say otherwise. Ranges at
or beyond ``range_max`` (``PARAM robot_front_laser_max``, else 81.9 m — the SICK LMS "no return"
code is 81.91 m) become +inf (REP-117: no return); negative and NaN ranges become NaN (invalid).
ROBOTLASER1 states its own geometry and range limit. Other message types are counted in
``ignored`` and skipped.

The x y theta / odom_* pose fields are what the logging robot believed: raw wheel odometry in
the Kümmerle et al. benchmark logs (mit-csail), a SLAM-corrected trajectory in the Radish
``*-corrected`` logs. :meth:`CarmenSource.odometry` reports the odom_* (robot) pose of each scan.
"""

from __future__ import annotations

import gzip
import logging
import math
import os
import re
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensors.config import short_repr
from sensors.source import PoseStream, SourceBase, SourceOptions
from sensors.types import (
    NS_PER_S,
    LaserScan,
    RgbdFrame,
    SensorError,
    format_stamp,
    parse_stamp,
)

log = logging.getLogger(__name__)

NO_RETURN_RANGE_M = 81.9  # [m] SICK LMS reports 81.91 m (8191 cm) when nothing returns
DEFAULT_RANGE_MIN_M = 0.01  # [m] SICK readings below 1 cm are error codes, not distances
SYNTHETIC_SCAN_PERIOD_NS = 200_000_000  # [ns] 5 Hz, used only when a log has no usable time
# A log whose ipc stamps would drop more than this fraction of its scans (stamps printed with
# 6 digits, 10 s apart; 32-bit wrap-arounds) has no usable clock: the logger's or synthesised.
MAX_UNORDERED_FRACTION = 0.5
FLASER_EXTRA_FIELDS = 11  # FLASER n [n ranges] + 6 pose + ipc_timestamp hostname logger_ts
ROBOTLASER_EXTRA_FIELDS = 24  # 9 header + n + 1 + m + 6 pose + 5 motion + 3 stamp/host
ODOM_FIELDS = 10
MAX_WARNINGS = 5  # per log; the rest are summarised once
MAX_POSE_SPEED = 10.0  # [m/s] faster between two scans and back again is a glitched pose
POSE_JUMP_SLACK_M = 1.0  # [m] per step, for stamps that bunch up
GZIP_MAGIC = b"\x1f\x8b"
SNIFF_BYTES = 65_536  # bytes looked at by try_open
CARMEN_SUFFIXES = (".clf", ".log", ".gz")
KNOWN_MESSAGES = ("FLASER", "ROBOTLASER1", "ODOM", "PARAM", "RLASER", "RAWLASER1", "SYNC")
RANGE_MAX_PARAM = "robot_front_laser_max"  # [m]
FOV_PARAM = "laser_front_laser_fov"  # [deg]
RESOLUTION_PARAM = "laser_front_laser_resolution"  # [deg]
BAD_STAMP = np.iinfo(np.int64).min  # marks a timestamp that did not parse
MESSAGE_NAME = re.compile(r"[A-Z][A-Z0-9_]{0,31}")  # FLASER, ROBOTLASER1, NMEAGGA, ...


class _LineError(Exception):
    """A malformed line: ``reason`` keys ``skipped``."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass
class _RawLaser:
    """The tokens of one laser line, converted in batches later."""

    line: int
    kind: str  # FLASER or ROBOTLASER1
    numbers: list[str]  # n ranges, 6 pose values, then (ROBOTLASER1) start fov res max_range
    stamp: str  # ipc_timestamp token
    logger_stamp: str  # logger_timestamp token


@dataclass(frozen=True, eq=False)
class CarmenLog:
    """Everything read from one log. Streams hold one entry per kept scan, in file order."""

    path: Path
    scans: list[LaserScan]
    scan_lines: np.ndarray  # (N,) int64, 1-based line of each scan
    laser_pose: PoseStream  # the laser's pose per scan (x y theta), frame "laser"
    robot_pose: PoseStream  # the robot's pose per scan (FLASER odom_*), frame "base_link"
    odom: PoseStream | None  # ODOM messages, frame "base_link"
    odom_twist: np.ndarray  # (M, 2) ODOM (tv [m/s], rv [rad/s])
    params: dict[str, str]
    skipped: dict[str, int]  # malformed or dropped lines by reason
    ignored: dict[str, int]  # lines of message types not read, by type
    stamp_source: str  # "ipc_timestamp", "logger_timestamp" or "synthesised"


# --- pure kernels ------------------------------------------------------------------------------


def guess_angle_increment(n: int) -> float:
    """CARMEN's ``carmen_laser_guess_angle_increment`` [rad] for a SICK with ``n`` beams."""
    if n in (180, 181):
        return math.pi / 180.0
    if n in (360, 361):
        return math.pi / 360.0
    if n in (400, 401):
        return math.pi / 720.0
    return math.pi / (n - 1) if n > 1 else 0.0


def flaser_geometry(
    n: int, fov_deg: float | None = None, resolution_deg: float | None = None
) -> tuple[float, float]:
    """(angle_min, angle_increment) [rad] of an ``n``-beam FLASER scan (REP-117, x forward)."""
    angle_min = -0.5 * math.radians(fov_deg) if fov_deg is not None else -0.5 * math.pi
    if resolution_deg is not None:
        return angle_min, math.radians(resolution_deg)
    if fov_deg is not None:
        return angle_min, math.radians(fov_deg) / (n - 1) if n > 1 else 0.0
    return angle_min, guess_angle_increment(n)


def carmen_ranges(raw: np.ndarray, range_max: float) -> np.ndarray:
    """Logged ranges [m] -> float32 REP-117 ranges: >= range_max -> +inf, < 0 or NaN -> NaN."""
    r = np.asarray(raw, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        out = np.where(r >= range_max, np.inf, r)
        out = np.where(np.isnan(r) | (r < 0), np.nan, out)
    return out.astype(np.float32)


def first_time_increase(stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks (keep, duplicate) for stamps read in order: keep those later than all before them.

    Dropping each backwards stamp one by one keeps exactly these, since a dropped stamp never
    raises the running maximum.
    """
    s = np.asarray(stamps_ns, dtype=np.int64)
    if s.size == 0:
        return np.zeros(0, bool), np.zeros(0, bool)
    previous_max = np.maximum.accumulate(s)[:-1]
    keep = np.concatenate([[True], s[1:] > previous_max])
    duplicate = np.concatenate([[False], s[1:] == previous_max])
    return keep, duplicate


def _floats(rows: list[list[str]]) -> list[np.ndarray | None]:
    """Rows of numeric tokens -> float64 arrays; None for a row with a non-numeric token.

    One vectorised conversion per batch of equally long rows; row by row only to find a bad one.
    """
    out: list[np.ndarray | None] = [None] * len(rows)
    by_width: dict[int, list[int]] = {}
    for i, row in enumerate(rows):
        by_width.setdefault(len(row), []).append(i)
    for idx in by_width.values():
        try:
            block = np.array([rows[i] for i in idx], dtype=np.float64)
        except (ValueError, OverflowError):
            for i in idx:
                try:
                    out[i] = np.array(rows[i], dtype=np.float64)
                except (ValueError, OverflowError):
                    out[i] = None
            continue
        for k, i in enumerate(idx):
            out[i] = block[k]
    return out


# --- line splitting ----------------------------------------------------------------------------


def _count(token: str, what: str) -> int:
    try:
        n = int(token)
    except ValueError:
        raise _LineError("bad_count", f"{what} {token!r} is not an integer") from None
    if n < 0:
        raise _LineError("bad_count", f"{what} {n} is negative")
    return n


def _split_flaser(tokens: list[str], line: int) -> _RawLaser:
    if len(tokens) < 2:
        raise _LineError("field_count", "FLASER without a beam count")
    n = _count(tokens[1], "beam count")
    if n == 0:
        raise _LineError("bad_count", "FLASER with 0 beams")
    if len(tokens) != n + FLASER_EXTRA_FIELDS:
        raise _LineError(
            "field_count",
            f"FLASER with {n} beams needs {n + FLASER_EXTRA_FIELDS} fields, got {len(tokens)}",
        )
    return _RawLaser(line, "FLASER", tokens[2 : 8 + n], tokens[8 + n], tokens[10 + n])


def _split_robotlaser(tokens: list[str], line: int) -> _RawLaser:
    if len(tokens) < 10:
        raise _LineError("field_count", f"ROBOTLASER1 with only {len(tokens)} fields")
    n = _count(tokens[8], "beam count")
    if n == 0:
        raise _LineError("bad_count", "ROBOTLASER1 with 0 beams")
    if len(tokens) < 10 + n:
        raise _LineError("field_count", f"ROBOTLASER1 with {n} beams has {len(tokens)} fields")
    m = _count(tokens[9 + n], "remission count")
    want = ROBOTLASER_EXTRA_FIELDS + n + m
    if len(tokens) != want:
        raise _LineError(
            "field_count",
            f"ROBOTLASER1 with {n} beams and {m} remissions needs {want} fields, got {len(tokens)}",
        )
    pose = 10 + n + m
    numbers = tokens[9 : 9 + n] + tokens[pose : pose + 6] + tokens[2:6]
    return _RawLaser(line, "ROBOTLASER1", numbers, tokens[pose + 11], tokens[pose + 13])


def _split_odom(tokens: list[str]) -> tuple[list[str], str]:
    if len(tokens) != ODOM_FIELDS:
        raise _LineError("field_count", f"ODOM needs {ODOM_FIELDS} fields, got {len(tokens)}")
    return tokens[1:6], tokens[7]


def _split_param(tokens: list[str]) -> tuple[str, str]:
    if len(tokens) < 3:
        raise _LineError("field_count", "PARAM needs a name and a value")
    # PARAM name value [hostname logger_timestamp]; a value may contain spaces.
    value = " ".join(tokens[2:-2]) if len(tokens) >= 5 else tokens[2]
    return tokens[1], value


# --- reading -----------------------------------------------------------------------------------


class _Problems:
    """Malformed or dropped lines: counted by reason, a few logged; strict mode raises the first
    (in file order) at :meth:`check`."""

    def __init__(self, path: Path, strict: bool) -> None:
        self.path, self.strict = path, strict
        self.found: list[tuple[int, str, str]] = []

    def add(self, line: int, reason: str, message: str) -> None:
        self.found.append((line, reason, message))

    def check(self) -> dict[str, int]:
        self.found.sort()
        if self.strict and self.found:
            line, _, message = self.found[0]
            raise SensorError(f"{self.path}:{line}: {message}")
        counts: dict[str, int] = {}
        for k, (line, reason, message) in enumerate(self.found):
            counts[reason] = counts.get(reason, 0) + 1
            if k < MAX_WARNINGS:
                log.warning("%s:%d: skipped: %s", self.path, line, message)
        if len(self.found) > MAX_WARNINGS:
            log.warning("%s: skipped %d lines in all: %s", self.path, len(self.found), counts)
        return counts


def _read_text(path: Path) -> str:
    try:
        data = path.read_bytes()
        if data[:2] == GZIP_MAGIC:
            data = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as err:
        raise SensorError(f"{path}: cannot read: {err}") from err
    return data.decode("utf-8", errors="replace")


def _stamps(tokens: list[str], lines: list[int], problems: _Problems, what: str) -> np.ndarray:
    """Timestamp tokens -> int64 ns; a bad one is reported and becomes INT64 min (dropped)."""
    out = np.empty(len(tokens), dtype=np.int64)
    for i, token in enumerate(tokens):
        try:
            out[i] = parse_stamp(token)
        except ValueError as err:
            problems.add(lines[i], "bad_timestamp", f"{what} timestamp: {err}")
            out[i] = BAD_STAMP
    return out


def read_carmen_log(
    path: str | os.PathLike[str],
    strict: bool = False,
    range_min_m: float = DEFAULT_RANGE_MIN_M,
) -> CarmenLog:
    """Read a CARMEN log once, in full.

    A malformed line (wrong field count, bad count, non-numeric or non-finite pose, bad
    timestamp) and a scan whose time does not advance are skipped and counted in
    ``skipped`` by reason (a few logged); with ``strict`` the first is a SensorError naming
    ``file:line``. A log whose ipc timestamps would drop most of its scans (all equal, printed
    too coarsely, wrapped) uses the logger timestamps, or synthesises 5 Hz stamps when those
    are no better (``stamp_source`` says which).
    """
    path = Path(path)
    text = _read_text(path)
    problems = _Problems(path, strict)

    # 1. Split lines by message type; numbers are converted in batches below.
    lasers: list[_RawLaser] = []
    odom_rows: list[list[str]] = []
    odom_stamps: list[str] = []
    odom_lines: list[int] = []
    params: dict[str, str] = {}
    ignored: dict[str, int] = {}
    for number, text_line in enumerate(text.splitlines(), start=1):
        tokens = text_line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        kind = tokens[0]
        try:
            if kind == "FLASER":
                lasers.append(_split_flaser(tokens, number))
            elif kind == "ROBOTLASER1":
                lasers.append(_split_robotlaser(tokens, number))
            elif kind == "ODOM":
                odom_values, odom_stamp = _split_odom(tokens)
                odom_rows.append(odom_values)
                odom_stamps.append(odom_stamp)
                odom_lines.append(number)
            elif kind == "PARAM":
                key, value = _split_param(tokens)
                params[key] = value
            elif MESSAGE_NAME.fullmatch(kind):
                ignored[kind] = ignored.get(kind, 0) + 1
            else:  # not a message at all: a bad record, not a type we do not read
                raise _LineError("not_a_message", f"not a CARMEN message: {short_repr(kind)}")
        except _LineError as err:
            problems.add(number, err.reason, str(err))

    # 2. Laser numbers, vectorised per batch of equal width; then per-scan checks.
    values = _floats([raw.numbers for raw in lasers])
    good: list[int] = []
    for i, (raw, row) in enumerate(zip(lasers, values, strict=True)):
        if row is None:
            problems.add(raw.line, "non_numeric", f"{raw.kind} has a non-numeric field")
            continue
        n = len(row) - (6 if raw.kind == "FLASER" else 10)
        if not np.isfinite(row[n : n + 6]).all():
            problems.add(raw.line, "non_finite", f"{raw.kind} pose is not finite")
            continue
        good.append(i)
    lines = [lasers[i].line for i in good]
    stamps = _stamps([lasers[i].stamp for i in good], lines, problems, "ipc")
    stamp_source = "ipc_timestamp"
    ok = stamps != BAD_STAMP
    keep, duplicate = first_time_increase(stamps)
    unordered = np.count_nonzero(ok & ~keep)
    if len(good) > 1 and ok[0] and unordered > MAX_UNORDERED_FRACTION * len(good):
        stamps, stamp_source = _fallback_stamps(lasers, good, lines, stamps)
        log.warning(
            "%s: the ipc timestamps of %d of %d scans do not advance: using %s stamps",
            path,
            unordered,
            len(good),
            stamp_source.split("_")[0],
        )
        keep, duplicate = first_time_increase(stamps)
    keep &= ok
    # The scan each dropped one failed to follow: the last kept before it.
    last_kept = np.maximum.accumulate(np.where(keep, np.arange(len(keep)), 0))
    for k in np.flatnonzero(ok & ~keep):
        j = int(last_kept[k])
        reason = "duplicate_stamp" if duplicate[k] else "non_monotonic"
        problems.add(
            lines[k],
            reason,
            f"scan time {format_stamp(int(stamps[k]))} does not advance past "
            f"{format_stamp(int(stamps[j]))} (line {lines[j]})",
        )
    kept = [(good[k], int(stamps[k])) for k in np.flatnonzero(keep)]
    kept = _drop_pose_spikes(lasers, values, kept, problems)

    # 3. ODOM messages.
    odom, odom_twist = _odometry(odom_rows, odom_stamps, odom_lines, problems)

    skipped = problems.check()
    scans, laser_pose, robot_pose = _build_scans(lasers, values, kept, params, range_min_m)
    return CarmenLog(
        path=path,
        scans=scans,
        scan_lines=np.array([lasers[i].line for i, _ in kept], dtype=np.int64),
        laser_pose=laser_pose,
        robot_pose=robot_pose,
        odom=odom,
        odom_twist=odom_twist,
        params=params,
        skipped=skipped,
        ignored=ignored,
        stamp_source=stamp_source,
    )


def _drop_pose_spikes(
    lasers: list[_RawLaser],
    values: list[np.ndarray | None],
    kept: list[tuple[int, int]],
    problems: _Problems,
) -> list[tuple[int, int]]:
    """A scan whose laser or odometry pose is off by more than ``MAX_POSE_SPEED`` from both its
    neighbours while they agree with each other is a glitched line (one 1 km off blew the
    grid up 20x): skipped and counted as ``pose_jump``. Vectorised over the log."""
    if len(kept) < 3:
        return kept
    poses = np.array(
        [
            _row(values, i)[-6:] if lasers[i].kind == "FLASER" else _row(values, i)[-10:-4]
            for i, _ in kept
        ]
    )
    t_s = np.array([t for _, t in kept], dtype=np.int64) / NS_PER_S
    spike = np.zeros(len(kept), bool)
    for xy in (poses[:, 0:2], poses[:, 3:5]):  # laser pose, odometry pose
        step = np.hypot(*np.diff(xy, axis=0).T)
        limit = MAX_POSE_SPEED * np.diff(t_s) + POSE_JUMP_SLACK_M
        bad = step > limit
        skip = np.hypot(*(xy[2:] - xy[:-2]).T) <= limit[:-1] + limit[1:]
        spike[1:-1] |= bad[:-1] & bad[1:] & skip
    for k in np.flatnonzero(spike):
        problems.add(
            lasers[kept[k][0]].line,
            "pose_jump",
            f"{lasers[kept[k][0]].kind} pose jumps more than {MAX_POSE_SPEED:g} m/s "
            "away from both neighbouring scans",
        )
    return [kv for kv, s in zip(kept, spike, strict=True) if not s]


def _fallback_stamps(
    lasers: list[_RawLaser],
    good: list[int],
    lines: list[int],
    ipc: np.ndarray,
) -> tuple[np.ndarray, str]:
    """Stamps for a log whose ipc timestamps cannot order it: the logger's, else synthesised."""
    quiet = _Problems(Path(), strict=False)
    logger = _stamps([lasers[i].logger_stamp for i in good], lines, quiet, "logger")
    if not quiet.found and np.all(np.diff(logger) > 0):
        return logger, "logger_timestamp"
    start = ipc[0] if ipc[0] != BAD_STAMP else 0
    synthetic = start + np.arange(len(good), dtype=np.int64) * SYNTHETIC_SCAN_PERIOD_NS
    return synthetic, "synthesised"


def _odometry(
    rows: list[list[str]], stamp_tokens: list[str], lines: list[int], problems: _Problems
) -> tuple[PoseStream | None, np.ndarray]:
    values = _floats(rows)
    good = []
    for i, row in enumerate(values):
        if row is None or not np.isfinite(row).all():
            problems.add(lines[i], "odom_non_numeric", "ODOM has a non-numeric or non-finite field")
        else:
            good.append(i)
    stamps = _stamps([stamp_tokens[i] for i in good], [lines[i] for i in good], problems, "ODOM")
    ok = stamps != BAD_STAMP
    keep, _ = first_time_increase(stamps)
    keep &= ok
    for k in np.flatnonzero(ok & ~keep):
        problems.add(
            lines[good[k]],
            "odom_non_monotonic",
            f"ODOM time {format_stamp(int(stamps[k]))} does not advance",
        )
    sel = np.flatnonzero(keep)
    if sel.size == 0:
        return None, np.zeros((0, 2))
    table = np.stack([values[good[k]] for k in sel])  # type: ignore[misc]
    pose = PoseStream(
        stamps[sel].copy(),
        table[:, 0].copy(),
        table[:, 1].copy(),
        table[:, 2].copy(),
        frame="base_link",
    )
    return pose, table[:, 3:5].copy()


def _param_float(params: dict[str, str], key: str) -> float | None:
    try:
        value = float(params[key])
    except (KeyError, ValueError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def _row(values: list[np.ndarray | None], i: int) -> np.ndarray:
    row = values[i]
    if row is None:  # pragma: no cover (kept scans all parsed)
        raise AssertionError(f"scan {i} was kept without numbers")
    return row


def _build_scans(
    lasers: list[_RawLaser],
    values: list[np.ndarray | None],
    kept: list[tuple[int, int]],
    params: dict[str, str],
    range_min_m: float,
) -> tuple[list[LaserScan], PoseStream, PoseStream]:
    flaser_max = _param_float(params, RANGE_MAX_PARAM) or NO_RETURN_RANGE_M
    fov_deg = _param_float(params, FOV_PARAM)
    resolution_deg = _param_float(params, RESOLUTION_PARAM)
    # 1. Geometry per scan; scans sharing beam count and range limit form one batch.
    geometry: list[tuple[int, float, float, float]] = []  # n, angle_min, increment, range_max
    batches: dict[tuple[int, float], list[int]] = {}
    poses = np.zeros((len(kept), 6))
    for k, (i, _stamp) in enumerate(kept):
        row = _row(values, i)
        if lasers[i].kind == "FLASER":
            n = len(row) - 6
            angle_min, increment = flaser_geometry(n, fov_deg, resolution_deg)
            range_max = flaser_max
        else:
            n = len(row) - 10
            angle_min, _fov, increment, range_max = (float(v) for v in row[n + 6 :])
        poses[k] = row[n : n + 6]
        geometry.append((n, angle_min, increment, range_max))
        batches.setdefault((n, range_max), []).append(k)

    # 2. Ranges converted batch by batch, then one LaserScan per row.
    ranges: list[np.ndarray] = [np.zeros(0, np.float32)] * len(kept)
    for (n, range_max), members in batches.items():
        raw = np.stack([_row(values, kept[k][0])[:n] for k in members])
        block = carmen_ranges(raw, range_max)
        for row_index, k in enumerate(members):
            ranges[k] = block[row_index]
    scans = [
        LaserScan(
            stamp_ns=stamp,
            angle_min=angle_min,
            angle_increment=increment,
            ranges=r,
            range_min=range_min_m,
            range_max=range_max,
        )
        for (_, stamp), (_, angle_min, increment, range_max), r in zip(
            kept, geometry, ranges, strict=True
        )
    ]
    t = np.array([s for _, s in kept], dtype=np.int64)
    laser = PoseStream(t, poses[:, 0].copy(), poses[:, 1].copy(), poses[:, 2].copy(), "laser")
    robot = PoseStream(t.copy(), poses[:, 3].copy(), poses[:, 4].copy(), poses[:, 5].copy())
    return scans, laser, robot


# --- source ------------------------------------------------------------------------------------


def _sniff(path: Path) -> bool:
    """Does the start of ``path`` (gzipped or not) look like a CARMEN log?"""
    try:
        with path.open("rb") as f:
            head = f.read(SNIFF_BYTES)
        if head[:2] == GZIP_MAGIC:
            with gzip.open(path, "rb") as g:
                head = g.read(SNIFF_BYTES)
    except (OSError, EOFError, zlib.error):
        return False
    for raw in head.decode("utf-8", errors="replace").splitlines()[:-1]:
        tokens = raw.split(maxsplit=1)
        if tokens and not tokens[0].startswith("#"):
            return tokens[0] in KNOWN_MESSAGES
    return False


class CarmenSource(SourceBase):
    """A CARMEN log as a :class:`~sensors.source.Source`: laser scans and per-scan odometry."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        strict: bool = False,
        range_min_m: float = DEFAULT_RANGE_MIN_M,
    ) -> None:
        self.log = read_carmen_log(path, strict=strict, range_min_m=range_min_m)
        self.path = str(self.log.path)
        self.skipped: dict[str, int] = dict(self.log.skipped)
        self.ignored: dict[str, int] = dict(self.log.ignored)  # messages of types not read

    @classmethod
    def try_open(
        cls, path: Path | str, options: SourceOptions | None = None
    ) -> CarmenSource | None:
        path = Path(path)
        suffix_ok = path.suffix.lower() in CARMEN_SUFFIXES
        if not (path.is_file() and suffix_ok and _sniff(path)):
            return None
        return cls(path, strict=options.strict if options else False)

    def describe(self) -> str:
        lg = self.log
        name = lg.path.name
        if not lg.scans:
            return f"CARMEN log {name}: no laser scans, {self._odom_text()}{self._skip_text()}"
        beams = sorted({len(s.ranges) for s in lg.scans})
        first = lg.scans[0]
        fov = math.degrees(first.angle_increment * (len(first.ranges) - 1))
        span = (lg.scans[-1].stamp_ns - first.stamp_ns) / 1e9
        stamps = "" if lg.stamp_source == "ipc_timestamp" else f", stamps {lg.stamp_source}"
        return (
            f"CARMEN log {name}: {len(lg.scans)} laser scans of {'/'.join(map(str, beams))} "
            f"beams, {fov:.1f} deg at {math.degrees(first.angle_increment):.2f} deg steps "
            f"from {math.degrees(first.angle_min):.1f} deg, range_max {first.range_max:g} m, "
            f"{span:.1f} s{stamps}; per-scan odometry from the odom pose fields, "
            f"{self._odom_text()}{self._skip_text()}"
        )

    def _odom_text(self) -> str:
        return f"{0 if self.log.odom is None else len(self.log.odom.stamps_ns)} ODOM messages"

    def _skip_text(self) -> str:
        parts = []
        if self.log.skipped:
            parts.append(f"skipped {self.log.skipped}")
        if self.log.ignored:
            parts.append(f"ignored {self.log.ignored}")
        return "; " + "; ".join(parts) if parts else ""

    def stream_stamps(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        if self.log.scans:
            out["scans"] = self.log.robot_pose.stamps_ns
            out["odometry"] = self.log.robot_pose.stamps_ns
        if self.log.odom is not None:
            out["odom"] = self.log.odom.stamps_ns
        return out

    def frames(self) -> Iterator[RgbdFrame]:
        return iter(())

    def scans(self) -> Iterator[LaserScan]:
        return iter(self.log.scans)

    def odometry(self) -> PoseStream | None:
        """One robot pose per scan (FLASER odom_x odom_y odom_theta; ROBOTLASER1 robot pose)."""
        return self.log.robot_pose if self.log.scans else None

    def laser_poses(self) -> PoseStream | None:
        """One laser pose per scan (FLASER x y theta; ROBOTLASER1 laser pose), frame "laser"."""
        return self.log.laser_pose if self.log.scans else None

    def odom_messages(self) -> PoseStream | None:
        """The ODOM messages of the log (their own rate), or None."""
        return self.log.odom


__all__ = [
    "CarmenLog",
    "CarmenSource",
    "carmen_ranges",
    "first_time_increase",
    "flaser_geometry",
    "guess_angle_increment",
    "read_carmen_log",
]
