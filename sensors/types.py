"""Messages that flow through rgbdnav.

Frozen dataclasses with shape, dtype and units in the field comments. Time is integer
nanoseconds (``stamp_ns``) everywhere; float seconds appear only at file and CLI edges.
Frames follow REP-103/105: ``map -> odom -> base_link -> camera_link -> camera_optical``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

NS_PER_S = 1_000_000_000  # [ns/s]
# [ns] largest |stamp| read from a file (year 2116 since 1970): the sum or difference of two
# stamps still fits an int64, where numpy would wrap around silently.
MAX_STAMP_NS = 2**62


class RgbdNavError(Exception):
    """Root of every error rgbdnav raises on purpose; the CLI turns these into one line."""


class SensorError(RgbdNavError):
    """A sensor, recording or log could not be read or does not make sense."""


class SyncError(RgbdNavError):
    """Streams could not be associated in time."""


class ConfigError(RgbdNavError):
    """A configuration file or override is invalid."""


class MapError(RgbdNavError):
    """A map or map bundle could not be read, written or used."""


class WorldError(RgbdNavError):
    """A simulator world description is invalid."""


def seconds_to_ns(t_s: float) -> int:
    """Float seconds -> integer nanoseconds (rounded)."""
    return int(round(t_s * NS_PER_S))


def _check_stamp_range(ns: int, text: str) -> int:
    if not -MAX_STAMP_NS <= ns <= MAX_STAMP_NS:
        limit = MAX_STAMP_NS // NS_PER_S
        raise ValueError(f"timestamp {text!r} is out of range (|t| <= {limit} s)")
    return ns


def ns_to_seconds(t_ns: int | np.ndarray) -> float | np.ndarray:
    return t_ns / NS_PER_S


def format_stamp(t_ns: int) -> str:
    """Exact decimal seconds with 9 digits, e.g. ``12.033333333`` (TUM-compatible)."""
    sign = "-" if t_ns < 0 else ""
    t_ns = abs(int(t_ns))
    return f"{sign}{t_ns // NS_PER_S}.{t_ns % NS_PER_S:09d}"


def parse_stamp(text: str) -> int:
    """Decimal seconds string -> integer nanoseconds without float round-off.

    Accepts ``"1305031102.175304"``, ``"12"``, ``"-0.5"`` and exponent forms (via float).
    Raises ValueError on anything else.
    """
    s = text.strip()
    if "e" in s or "E" in s:
        value = float(s)
        if not math.isfinite(value):
            raise ValueError(f"timestamp {text!r} is not finite")
        if abs(value) > MAX_STAMP_NS / NS_PER_S:
            return _check_stamp_range(MAX_STAMP_NS + 1, text)
        return _check_stamp_range(seconds_to_ns(value), text)
    neg = s.startswith("-")
    if neg or s.startswith("+"):
        s = s[1:]
    whole, _, frac = s.partition(".")
    if not (whole.isdigit() or (whole == "" and frac)) or (frac and not frac.isdigit()):
        raise ValueError(f"timestamp {text!r} is not a decimal number of seconds")
    frac9 = (frac + "000000000")[:9]
    rounding = 1 if len(frac) > 9 and frac[9] >= "5" else 0
    if len(whole) > len(str(MAX_STAMP_NS // NS_PER_S)):  # no 10^6-digit int() to find out
        return _check_stamp_range(MAX_STAMP_NS + 1, text)
    ns = int(whole or "0") * NS_PER_S + int(frac9 or "0") + rounding
    return _check_stamp_range(-ns if neg else ns, text)


@dataclass(frozen=True)
class CameraIntrinsics:
    width: int  # [px]
    height: int  # [px]
    fx: float  # [px]
    fy: float  # [px]
    cx: float  # [px]
    cy: float  # [px]
    depth_scale: float = 5000.0  # [counts/m] of 16-bit depth PNGs (TUM convention)

    def __post_init__(self) -> None:
        # Every reader builds its intrinsics here: a NaN passes a "> 0" check written as
        # "<= 0 is an error", and then every frame fails downstream (issue #16).
        positive = (self.width, self.height, self.fx, self.fy, self.depth_scale)
        if not (
            all(math.isfinite(v) and v > 0 for v in positive)
            and math.isfinite(self.cx)
            and math.isfinite(self.cy)
        ):
            raise SensorError(
                f"camera intrinsics {self.width}x{self.height} fx={self.fx} fy={self.fy} "
                f"cx={self.cx} cy={self.cy} depth_scale={self.depth_scale}: width, height, fx, "
                "fy and depth_scale must be finite and > 0, cx and cy finite"
            )

    def matrix(self) -> np.ndarray:
        """3x3 pinhole matrix K (float64)."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )


@dataclass(frozen=True, eq=False)
class RgbdFrame:
    stamp_ns: int  # [ns] capture time of the colour image
    rgb: np.ndarray  # HxWx3 uint8, RGB order; NO_RGB when the reader was told it is not needed
    depth_m: np.ndarray  # HxW float32 [m], registered to rgb; 0 or NaN = invalid
    intrinsics: CameraIntrinsics


# The colour of a frame read without it (Recording.frames' rgb_wanted): empty and read-only, so
# any use of it as an image fails at once rather than passing as a black one.
NO_RGB = np.zeros((0, 0, 3), np.uint8)
NO_RGB.flags.writeable = False


@dataclass(frozen=True)
class WheelTicks:
    stamp_ns: int  # [ns]
    left: int  # cumulative encoder positions as the board reports them
    right: int  # cumulative encoder positions


@dataclass(frozen=True)
class ImuSample:
    stamp_ns: int  # [ns]
    gyro_z: float  # [rad/s] yaw rate about base_link z (REP-103: counter-clockwise positive)


@dataclass(frozen=True)
class Pose2:
    """Planar pose of a frame: position [m] and heading [rad] (counter-clockwise from x)."""

    x: float  # [m]
    y: float  # [m]
    yaw: float  # [rad]

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw], dtype=np.float64)


@dataclass(frozen=True, eq=False)
class Odometry2D:
    stamp_ns: int  # [ns]
    pose: Pose2  # odom -> base_link
    twist: tuple[float, float]  # (v [m/s], w [rad/s]) in base_link
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # 3x3 over x,y,yaw


@dataclass(frozen=True, eq=False)
class LaserScan:
    """REP-117: ranges outside [range_min, range_max] are invalid (+inf = no return)."""

    stamp_ns: int  # [ns]
    angle_min: float  # [rad] angle of ranges[0], counter-clockwise from x of the scan frame
    angle_increment: float  # [rad]
    ranges: np.ndarray  # (N,) float32 [m]
    range_min: float  # [m]
    range_max: float  # [m]

    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges))
