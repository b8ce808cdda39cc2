"""Config sections owned by the sensors layer, and the tiny schema machinery every layer uses.

One frozen dataclass per YAML section. Each field is declared with :func:`param`, which records
its unit and valid range; :func:`build_section` turns a plain mapping (from YAML) into the
dataclass and rejects unknown keys, wrong types and out-of-range values with the full key path.
"""

from __future__ import annotations

import dataclasses
import math
import reprlib
import sys
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar, Union

from sensors.types import ConfigError

T = TypeVar("T")
_QUOTE_LIMIT = 80  # [chars] of a bad value quoted in an error (an alias bomb is gigabytes)
_REPR = reprlib.Repr()  # nested containers are cut short before they are ever joined
_REPR.maxstring = _REPR.maxother = _QUOTE_LIMIT


def param(
    default: Any,
    *,
    unit: str = "",
    doc: str = "",
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    length: int | None = None,
) -> Any:
    """A config field with its unit, documentation and range (applied element-wise to tuples)."""
    meta = {"unit": unit, "doc": doc, "ge": ge, "gt": gt, "le": le, "lt": lt, "length": length}
    if isinstance(default, list):
        default = tuple(default)
    return field(default=default, metadata=meta)


# --- validation -------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def short_repr(value: Any) -> str:
    """``repr`` cut to a line: errors quote bad values, which may be huge."""
    text = _REPR.repr(value)
    return text if len(text) <= _QUOTE_LIMIT else text[: _QUOTE_LIMIT - 3] + "..."


def unknown_keys(data: Mapping[Any, Any], known: Iterable[str]) -> list[str]:
    """The keys of a YAML mapping that are not ``known``, as sorted strings: YAML keys may be
    numbers or null, which cannot be sorted with strings."""
    return sorted(str(k) for k in set(data) - set(known))


def finite_float(value: Any) -> float | None:
    """``value`` as a float when it is a finite int/float (not a bool), else None: an int too
    large for a float (YAML reads ``1000...0`` as one) is not a number we can use either."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        out = float(value)
    except OverflowError:
        return None
    return out if math.isfinite(out) else None


def _check_scalar(value: Any, tp: Any, path: str) -> Any:
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true/false, got {short_repr(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {short_repr(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {short_repr(value)}")
        # NaN passes every "> 0" and "< x" check: a parameter is a finite number.
        huge_int = isinstance(value, int) and abs(value) > sys.float_info.max
        if huge_int or (isinstance(value, float) and not math.isfinite(value)):
            raise ConfigError(f"{path}: expected a finite number, got {short_repr(value)}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {short_repr(value)}")
        return value
    raise ConfigError(f"{path}: unsupported config type {_type_name(tp)}")  # pragma: no cover


def _coerce(value: Any, tp: Any, path: str) -> Any:
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):  # a nested section, e.g. vo.advanced
        return value if isinstance(value, tp) else build_section(tp, value, path)
    origin = typing.get_origin(tp)
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ConfigError(f"{path}: {short_repr(value)} is not one of {list(choices)}")
        return value
    if origin in (Union, types.UnionType):
        members = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, members[0], path)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {short_repr(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{path}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{path}: expected {len(args)} values, got {len(value)}")
        pairs = enumerate(zip(value, args, strict=True))
        return tuple(_coerce(v, a, f"{path}[{i}]") for i, (v, a) in pairs)
    return _check_scalar(value, tp, path)


def _check_range(value: Any, meta: Mapping[str, Any], path: str) -> None:
    if isinstance(value, tuple):
        n = meta.get("length")
        if n is not None and len(value) != n:
            raise ConfigError(f"{path}: expected {n} values, got {len(value)}")
        for i, v in enumerate(value):
            _check_range(v, {**meta, "length": None}, f"{path}[{i}]")
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    bounds = [
        ("ge", lambda v, b: v >= b, ">="),
        ("gt", lambda v, b: v > b, ">"),
        ("le", lambda v, b: v <= b, "<="),
        ("lt", lambda v, b: v < b, "<"),
    ]
    for key, ok, sym in bounds:
        b = meta.get(key)
        if b is not None and not ok(value, b):
            raise ConfigError(f"{path}: {value}{unit} is out of range (must be {sym} {b}{unit})")


def build_section(cls: type[T], data: Mapping[str, Any] | None, path: str) -> T:
    """Build frozen dataclass ``cls`` from ``data``; missing keys keep their defaults."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: expected a mapping of keys, got {short_repr(data)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields), key=str)
    if unknown:
        raise ConfigError(
            f"{path}.{unknown[0]}: unknown key (valid keys: {', '.join(sorted(fields))})"
        )
    kwargs = {}
    for name, value in data.items():
        key_path = f"{path}.{name}"
        coerced = _coerce(value, hints[name], key_path)
        _check_range(coerced, fields[name].metadata, key_path)
        kwargs[name] = coerced
    obj = cls(**kwargs)
    post = getattr(obj, "validate", None)
    if post is not None:
        problem = post()
        if problem:
            raise ConfigError(f"{path}: {problem}")
    return obj


def section_to_dict(obj: Any) -> dict[str, Any]:
    """Dataclass -> plain YAML-able dict (tuples become lists)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            v = section_to_dict(v)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


# --- sections owned by sensors ----------------------------------------------------------------


@dataclass(frozen=True)
class RobotConfig:
    """Robot geometry (defaults: Parallax Eddie). base_link is on the floor at the axle midpoint."""

    name: str = param("eddie", doc="robot profile name")
    wheel_diameter: float = param(0.1524, unit="m", gt=0.0, le=2.0, doc="6-inch tyres")
    ticks_per_revolution: int = param(36, unit="positions/rev", ge=1, doc="encoder positions")
    track_width: float = param(0.3, unit="m", gt=0.0, le=5.0, doc="wheel separation")
    radius: float = param(0.23, unit="m", gt=0.0, doc="footprint radius for collision checks")
    max_wheel_speed: float = param(0.9, unit="m/s", gt=0.0, doc="board speed limit")
    camera_x: float = param(0.0, unit="m", doc="camera_link x in base_link (forward)")
    camera_y: float = param(0.0, unit="m", doc="camera_link y in base_link (left)")
    camera_height: float = param(0.45, unit="m", ge=0.0, le=5.0, doc="camera_link z above floor")
    camera_pitch: float = param(0.0, unit="rad", ge=-1.2, le=1.2, doc="positive tilts down")
    camera_roll: float = param(0.0, unit="rad", ge=-0.5, le=0.5, doc="about the optical axis")
    gps_x: float = param(0.0, unit="m", doc="GPS antenna x in base_link (navsat_transform's gps)")
    gps_y: float = param(0.0, unit="m", doc="GPS antenna y in base_link (left)")
    wheel_error_left: float = param(
        0.0005, unit="m", ge=0.0, doc="odometry: left wheel travel variance per metre"
    )
    wheel_error_right: float = param(
        0.0005, unit="m", ge=0.0, doc="odometry: right wheel travel variance per metre"
    )
    wheel_error_theta: float = param(
        0.0, unit="rad", ge=0.0, doc="odometry: heading variance per radian turned"
    )

    @property
    def metres_per_tick(self) -> float:
        return 3.141592653589793 * self.wheel_diameter / self.ticks_per_revolution


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole intrinsics and depth range of the RGB-D camera (defaults: Kinect v1, VGA)."""

    width: int = param(640, unit="px", ge=1)
    height: int = param(480, unit="px", ge=1)
    fx: float = param(525.0, unit="px", gt=0.0)
    fy: float = param(525.0, unit="px", gt=0.0)
    cx: float = param(319.5, unit="px")
    cy: float = param(239.5, unit="px")
    depth_scale: float = param(5000.0, unit="counts/m", gt=0.0, doc="16-bit PNG depth scale")
    rate: float = param(30.0, unit="Hz", gt=0.0)
    depth_min: float = param(0.5, unit="m", ge=0.0)
    depth_max: float = param(4.5, unit="m", gt=0.0)
    baseline: float = param(0.075, unit="m", gt=0.0, doc="IR projector to IR camera")
    disparity_focal: float = param(580.0, unit="px", gt=0.0, doc="IR camera focal length")

    def validate(self) -> str | None:
        if self.depth_min >= self.depth_max:
            return f"depth_min ({self.depth_min}) must be below depth_max ({self.depth_max})"
        return None


@dataclass(frozen=True)
class SyncConfig:
    """Approximate-time association (ROS message_filters ApproximateTime semantics)."""

    queue_size: int = param(10, ge=1, doc="messages kept per stream")
    slop: float = param(0.02, unit="s", ge=0.0, doc="max stamp spread inside one set")
    max_interpolation_gap: float = param(0.2, unit="s", gt=0.0, doc="wheel-odometry bracket")
    camera_info_stamp_tolerance: float = param(0.1, unit="s", ge=0.0)
    warn_fraction: float = param(0.05, ge=0.0, le=1.0, doc="warn when this much is skipped")


@dataclass(frozen=True)
class TopicsConfig:
    """ROS topic per role when reading rosbags. A role left at its default falls back to the
    bag's unique topic of the right message type when the default topic is absent."""

    rgb: str = param("/camera/rgb/image_color", doc="sensor_msgs/Image or CompressedImage")
    depth: str = param("/camera/depth/image", doc="sensor_msgs/Image 16UC1 [mm] or 32FC1 [m]")
    camera_info: str = param("/camera/rgb/camera_info", doc="sensor_msgs/CameraInfo")
    odom: str = param("/odom", doc="nav_msgs/Odometry")
    imu: str = param("/imu/data", doc="sensor_msgs/Imu")
    wheels: str = param("/wheel_encoders", doc="Int32MultiArray [left, right] or JointState")
    gps: str = param("/gps/fix", doc="sensor_msgs/NavSatFix (robot_localization's gps/fix)")

    def validate(self) -> str | None:
        # An empty name matched no topic and silently dropped the role (VO off for rgb).
        for f in dataclasses.fields(self):
            if not str(getattr(self, f.name)).strip():
                return (
                    f"{f.name}: empty topic name (leave it out to use the default, which "
                    "falls back to the bag's unique topic of the right type)"
                )
        return None


@dataclass(frozen=True)
class BoardConfig:
    """Parallax Eddie control board on a serial line."""

    port: str = param("/dev/ttyUSB0")
    baudrate: int = param(115200, unit="baud", gt=0)
    timeout: float = param(0.2, unit="s", gt=0.0, doc="reply timeout per command")
    poll_rate: float = param(50.0, unit="Hz", gt=0.0, doc="encoder polling")
    watchdog_timeout: float = param(0.25, unit="s", gt=0.0, doc="STOP when no command arrives")
    reconnect_interval: float = param(1.0, unit="s", gt=0.0)


@dataclass(frozen=True)
class ThunderBorgConfig:
    """PiBorg ThunderBorg on I2C + an Arduino tacho on serial (EaseRobot); host-side PID."""

    bus: int = param(1, ge=0, doc="I2C bus number (/dev/i2c-N)")
    address: int = param(0x15, ge=0x03, le=0x77, doc="I2C address (PiBorg default 0x15)")
    tacho_port: str = param("/dev/ttyUSB0", doc="Arduino tacho serial port")
    tacho_baudrate: int = param(115200, unit="baud", gt=0)
    left_motor: int = param(1, ge=1, le=2, doc="ThunderBorg motor driving the left wheel")
    invert_right: bool = param(False, doc="the right motor is mounted mirrored")
    p: float = param(0.5, ge=0.0, doc="PID proportional gain (EaseRobot)")
    i: float = param(0.9, ge=0.0, doc="PID integral gain")
    d: float = param(0.006, ge=0.0, doc="PID derivative gain")
    use_pid: bool = param(True, doc="closed loop on tacho RPM; False: calibration only")
    inertia_level: float = param(0.1, ge=0.0, lt=1.0, doc="motor power below which nothing moves")
    slope: float = param(
        0.649776, gt=0.0, unit="m/s per power", doc="speed = slope*power + y_intercept"
    )
    y_intercept: float = param(-0.0788956, unit="m/s", doc="calibration intercept")
    pid_rate: float = param(
        20.0, unit="Hz", gt=4.0, doc="PID loop; > 4 Hz feeds the board failsafe"
    )
    rpm_timeout: float = param(0.5, unit="s", gt=0.0, doc="tacho silent this long: motors stop")
    battery_warn: float = param(11.0, unit="V", ge=0.0, doc="low-battery warning (LED orange)")
    battery_stop: float = param(10.5, unit="V", ge=0.0, doc="below this the motors are refused")


@dataclass(frozen=True)
class BridgeConfig:
    """ROSArduinoBridge firmware on a serial line: PID on the Arduino in ticks per PID frame."""

    port: str = param("/dev/ttyACM0")
    baudrate: int = param(57600, unit="baud", gt=0, doc="firmware BAUDRATE")
    timeout: float = param(0.2, unit="s", gt=0.0, doc="reply timeout per command")
    pid_rate: float = param(30.0, unit="Hz", gt=0.0, doc="firmware PID_RATE (ticks per frame)")
    auto_stop_interval: float = param(
        2.0, unit="s", gt=0.0, doc="firmware AUTO_STOP_INTERVAL (flash 0.25 for the 250 ms stop)"
    )
    kp: int = param(20, doc="firmware Kp (sent with `u` when set_pid is true)")
    kd: int = param(12, doc="firmware Kd")
    ki: int = param(0, doc="firmware Ki")
    ko: int = param(50, doc="firmware Ko (output divisor)")
    set_pid: bool = param(False, doc="send the gains above at connect")


@dataclass(frozen=True)
class SimConfig:
    """Simulated Eddie + Kinect v1: rates, motion limits and sensor error models."""

    renderer: Literal["raster", "raycast"] = param(
        "raster", doc="raster: fast scan conversion; raycast: Open3D reference"
    )
    camera_rate: float = param(30.0, unit="Hz", gt=0.0)
    wheel_rate: float = param(50.0, unit="Hz", gt=0.0, doc="board encoder polling")
    imu_rate: float = param(100.0, unit="Hz", gt=0.0)
    groundtruth_rate: float = param(100.0, unit="Hz", gt=0.0, doc="mocap-like ground truth")
    physics_rate: float = param(200.0, unit="Hz", gt=0.0)
    max_linear_speed: float = param(0.4, unit="m/s", gt=0.0, le=0.5)
    max_angular_speed: float = param(0.8, unit="rad/s", gt=0.0, le=1.0)
    max_linear_accel: float = param(0.5, unit="m/s^2", gt=0.0)
    max_angular_accel: float = param(1.5, unit="rad/s^2", gt=0.0)
    waypoint_tolerance: float = param(0.1, unit="m", gt=0.0)
    # Kinect v1 depth: Gaussian disparity noise, then 1/8-px quantisation -> sigma_z ~ z^2.
    disparity_noise: float = param(0.07, unit="px", ge=0.0)
    disparity_subpixel: int = param(8, ge=1, doc="disparity quantisation steps per pixel")
    depth_edge_threshold: float = param(0.05, ge=0.0, doc="relative depth jump invalidated")
    depth_dropout: float = param(0.002, ge=0.0, le=1.0, doc="random invalid pixel fraction")
    shadows: bool = param(True, doc="projector shadows (invalid depth) beside near objects")
    rgb_noise: float = param(2.0, unit="8-bit levels", ge=0.0)
    stamp_jitter: float = param(0.002, unit="s", ge=0.0, doc="camera stamp jitter sigma")
    frame_drop_probability: float = param(0.01, ge=0.0, lt=1.0)
    # Wheels and encoders.
    wheel_diameter_error: tuple[float, float] = param(
        (0.002, -0.001), doc="relative true-vs-nominal diameter error, left and right"
    )
    track_width_error: float = param(0.01, doc="relative true-vs-nominal track width error")
    wheel_slip: float = param(0.01, ge=0.0, le=0.5, doc="sigma of relative wheel slip")
    slip_correlation_time: float = param(0.5, unit="s", gt=0.0, doc="slip is an AR(1) process")
    backlash: float = param(0.02, unit="rad", ge=0.0, doc="gear backlash per wheel")
    blocked_wheel_slip: float = param(
        0.2,
        ge=0.0,
        le=1.0,
        doc="live robot blocked by an obstacle: fraction of the refused wheel "
        "travel the encoders still count (0 = motors stall, 1 = wheels spin freely)",
    )
    gyro_enabled: bool = param(True)
    gyro_bias: float = param(0.002, unit="rad/s")
    gyro_noise: float = param(0.005, unit="rad/s", ge=0.0)
    # GPS receiver riding base_link, in worlds with a geo anchor (consumer receivers: 2-5 m).
    gps_sigma: float = param(3.0, unit="m", gt=0.0, doc="per-axis noise of a fix")
    gps_rate: float = param(1.0, unit="Hz", gt=0.0, doc="fixes per second")
    gps_outage_probability: float = param(
        0.05, ge=0.0, le=1.0, doc="chance per fix of entering an outage"
    )
    gps_mean_outage: float = param(5.0, unit="s", gt=0.0, doc="mean outage length")
