"""ROS bags as a :class:`~sensors.source.Source`, read with the pure-Python ``rosbags`` library.

No ROS install is needed. Accepted inputs: a rosbag1 ``.bag`` file, a rosbag2 folder (with its
``metadata.yaml``), or a bare rosbag2 storage file ``.db3`` (sqlite3) or ``.mcap``; a storage file
inside a rosbag2 folder opens the whole folder.

Topics come from :class:`RosbagTopics`. When a *default* topic is absent, the unique topic of the
right message type is used instead and :meth:`RosbagSource.describe` says so; a topic the caller
named explicitly is never substituted.

Roles and message types: rgb/depth (``sensor_msgs/Image``, ``CompressedImage``), camera_info,
odom (``nav_msgs/Odometry``), imu, wheels (``Int32/Int64MultiArray`` counts or ``JointState``
angles) and gps (``NavSatFix``). Stamps are ``header.stamp`` in integer nanoseconds (the receive
time when a header is missing or zero, counted); rgb and depth are associated like TUM's
associate.py (``SyncConfig.slop``). The encodings each role accepts, what it becomes and the
stamp rules in full are in ``docs/design/rosbag_source.md``.

Bad messages (unsupported encoding, undecodable data, rgb/depth size mismatch) are skipped with a
warning naming the topic and counted in ``skipped`` by reason; with ``strict=True`` they raise
:class:`SensorError` instead. Errors from ``rosbags`` itself become :class:`SensorError` naming the
file.
"""

from __future__ import annotations

import logging
import math
import re
import struct
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from sensors.config import CameraConfig, RobotConfig, SyncConfig
from sensors.gps import GpsStream, check_fixes, navsatfix_sigma
from sensors.images import decode_image
from sensors.recording import associate
from sensors.source import ImuStream, PoseStream, SourceBase, SourceOptions, WheelStream
from sensors.tum import yaw_from_quaternion
from sensors.types import (
    NS_PER_S,
    CameraIntrinsics,
    RgbdFrame,
    SensorError,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)

ROSBAG1_SUFFIX = ".bag"
ROSBAG2_SUFFIXES = (".db3", ".mcap")
ROSBAG2_METADATA = "metadata.yaml"
ROSBAG2_MARKER = "rosbag2_bagfile_information"  # top-level key of every rosbag2 metadata.yaml
METADATA_PEEK_BYTES = 4096  # [bytes] enough of metadata.yaml to find its top-level key

MM_PER_M = 1000.0  # [mm/m] 16UC1 depth is in millimetres (REP-118)
# ``std_msgs/Header`` starts every stamped message. Its stamp (sec, nanosec) sits at bytes 4..12 of
# the raw message in both encodings: after ``uint32 seq`` in ROS 1, after the 4-byte CDR
# encapsulation header in ROS 2. Reading it there avoids deserialising whole images.
HEADER_STAMP_OFFSET = 4  # [bytes]
HEADER_STAMP_END = 12  # [bytes]
CDR_BIG_ENDIAN, CDR_LITTLE_ENDIAN = 0, 1  # second byte of the CDR encapsulation header
# compressed_depth_image_transport prefixes its PNG with ConfigHeader {int32 format; float[2]}.
COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
INT32_MULTI_ARRAY = "std_msgs/msg/Int32MultiArray"
INT64_MULTI_ARRAY = "std_msgs/msg/Int64MultiArray"
JOINT_STATE = "sensor_msgs/msg/JointState"
HEADERLESS_TYPES = frozenset({INT32_MULTI_ARRAY, INT64_MULTI_ARRAY})
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC = "/tf_static"

ROLE_TYPES: Mapping[str, tuple[str, ...]] = {
    "rgb": (IMAGE, COMPRESSED_IMAGE),
    "depth": (IMAGE, COMPRESSED_IMAGE),
    "camera_info": (CAMERA_INFO,),
    "odom": (ODOMETRY,),
    "imu": (IMU,),
    "gps": (NAVSATFIX,),
    "wheels": (INT32_MULTI_ARRAY, INT64_MULTI_ARRAY, JOINT_STATE),
}
# (x, y, yaw) rows and columns of a ROS 6x6 covariance (x, y, z, roll, pitch, yaw), row-major.
PLANAR_COV = (np.array([0, 1, 5])[:, None] * 6 + np.array([0, 1, 5])).ravel()
STREAM_NAMES: Mapping[str, str] = {"odom": "odometry"}  # role -> stream_stamps() key if different

COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


@dataclass(frozen=True)
class RosbagTopics:
    """Topic per role. Defaults follow openni_launch / a typical differential-drive robot."""

    rgb: str = "/camera/rgb/image_color"
    depth: str = "/camera/depth/image"
    camera_info: str = "/camera/rgb/camera_info"
    odom: str = "/odom"
    imu: str = "/imu/data"
    wheels: str = "/wheel_encoders"
    gps: str = "/gps/fix"


ROLES: tuple[str, ...] = tuple(f.name for f in fields(RosbagTopics))

# RealSense SDK recordings (rs.recorder, RealSense Viewer): /device_N/sensor_M/<Stream>_K/...
SDK_TOPIC = re.compile(r"^/device_\d+/sensor_\d+/")
SDK_DEPTH_UNITS = re.compile(r"^/device_\d+/sensor_\d+/option/Depth[ _]Units/value$")
SDK_STREAM = re.compile(r"^(/device_\d+/sensor_\d+/[A-Za-z]+_\d+)/")


@dataclass(frozen=True)
class SdkMeta:
    """What a RealSense SDK recording says about itself, and the topic each value came from."""

    depth_units: float | None  # [m/count] of 16-bit depth
    depth_units_topic: str | None
    extrinsics: tuple[tuple[float, ...], tuple[float, ...]] | None  # colour rel. depth (R, t)
    extrinsics_topic: str | None
    depth_k: tuple[float, ...] | None  # depth stream's own K (row-major)


@dataclass(frozen=True)
class TopicChoice:
    """Which topic serves a role, and why (``note`` is empty for the configured topic)."""

    role: str
    topic: str | None  # None: the bag has nothing usable for this role
    msgtype: str | None  # e.g. "sensor_msgs/msg/Image"
    note: str = ""


class _BadMessage(SensorError):
    """One message cannot be used; ``reason`` keys ``RosbagSource.skipped``."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


# --- pure helpers ------------------------------------------------------------------------------


def short_type(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs/Image`` (how ROS 1 users know it)."""
    return msgtype.replace("/msg/", "/")


def normalize_type(msgtype: str) -> str:
    """``sensor_msgs/Image`` or ``sensor_msgs/msg/Image`` -> ``sensor_msgs/msg/Image``."""
    pkg, _, name = msgtype.rpartition("/")
    return msgtype if pkg.endswith("/msg") or not pkg else f"{pkg}/msg/{name}"


def looks_like_rosbag(path: Path) -> bool:
    """Cheap check (no rosbags import): a .bag/.db3/.mcap file or a rosbag2 folder."""
    if path.is_file():
        return path.suffix.lower() in (ROSBAG1_SUFFIX, *ROSBAG2_SUFFIXES)
    meta = path / ROSBAG2_METADATA
    if not (path.is_dir() and meta.is_file()):
        return False
    try:
        with meta.open("rb") as f:
            head = f.read(METADATA_PEEK_BYTES)
    except OSError:
        return False
    return ROSBAG2_MARKER.encode() in head


def bag_reader_path(path: Path) -> Path:
    """A storage file inside a rosbag2 folder opens the folder (metadata, all split files)."""
    if path.is_file() and path.suffix.lower() in ROSBAG2_SUFFIXES:
        if looks_like_rosbag(path.parent):
            return path.parent
    return path


def header_stamp_ns_from_raw(raw: bytes | memoryview, is_ros2: bool) -> int | None:
    """``header.stamp`` [ns] of a raw message that starts with std_msgs/Header, or None when the
    bytes are too short or use a CDR variant this shortcut does not know."""
    if len(raw) < HEADER_STAMP_END:
        return None
    if is_ros2:
        if raw[0] != 0 or raw[1] not in (CDR_BIG_ENDIAN, CDR_LITTLE_ENDIAN):
            return None
        fmt = "<iI" if raw[1] == CDR_LITTLE_ENDIAN else ">iI"
    else:
        fmt = "<II"
    sec, nanosec = struct.unpack_from(fmt, raw, HEADER_STAMP_OFFSET)
    return int(sec) * NS_PER_S + int(nanosec)


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (``sec``, ``nanosec``; ROS 1 ``time`` maps to the same) -> ns."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def _pixels(
    encoding: str,
    height: int,
    width: int,
    step: int,
    data: Any,
    dtype: np.dtype[Any],
    channels: int,
    big_endian: bool,
) -> np.ndarray:
    """Raw image bytes -> (H, W, C) array of native ``dtype``, honouring row padding."""
    row_bytes = width * channels * dtype.itemsize
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    buf = buf.reshape(-1).view(np.uint8)
    if height <= 0 or width <= 0 or step < row_bytes or buf.size < height * step:
        raise _BadMessage(
            "truncated_image",
            f"{encoding} image {width}x{height} with step {step} needs {height * step} bytes, "
            f"has {buf.size}",
        )
    rows = np.ascontiguousarray(buf[: height * step].reshape(height, step)[:, :row_bytes])
    wire = dtype.newbyteorder(">" if big_endian else "<")
    return rows.view(wire).reshape(height, width, channels).astype(dtype, copy=True)


def rgb_from_image(
    encoding: str, height: int, width: int, step: int, data: Any, big_endian: bool = False
) -> np.ndarray:
    """sensor_msgs/Image fields -> HxWx3 uint8 RGB (rgb8, bgr8, rgba8, bgra8, mono8)."""
    u8 = np.dtype(np.uint8)
    if encoding == "rgb8":
        return _pixels(encoding, height, width, step, data, u8, 3, big_endian)
    if encoding == "bgr8":
        return np.ascontiguousarray(
            _pixels(encoding, height, width, step, data, u8, 3, big_endian)[..., ::-1]
        )
    if encoding in ("rgba8", "bgra8"):
        px = _pixels(encoding, height, width, step, data, u8, 4, big_endian)[..., :3]
        return np.ascontiguousarray(px if encoding == "rgba8" else px[..., ::-1])
    if encoding == "mono8":
        px = _pixels(encoding, height, width, step, data, u8, 1, big_endian)
        return np.repeat(px, 3, axis=2)
    raise _BadMessage(
        "unsupported_encoding",
        f"encoding {encoding!r} is not a colour encoding rgbdnav reads "
        f"({', '.join(COLOUR_ENCODINGS)})",
    )


def depth_from_image(
    encoding: str, height: int, width: int, step: int, data: Any, big_endian: bool = False
) -> np.ndarray:
    """sensor_msgs/Image fields -> HxW float32 depth [m]; 16UC1/mono16 are mm (0 = invalid),
    32FC1 is metres (non-finite becomes NaN = invalid)."""
    if encoding in ("16UC1", "mono16"):
        mm = _pixels(encoding, height, width, step, data, np.dtype(np.uint16), 1, big_endian)
        return (mm[..., 0].astype(np.float32) / np.float32(MM_PER_M)).astype(np.float32)
    if encoding == "32FC1":
        m = _pixels(encoding, height, width, step, data, np.dtype(np.float32), 1, big_endian)
        m = m[..., 0]
        m[~np.isfinite(m)] = np.nan
        return m
    raise _BadMessage(
        "unsupported_encoding",
        f"encoding {encoding!r} is not a depth encoding rgbdnav reads "
        f"({', '.join(DEPTH_ENCODINGS)})",
    )


def _imdecode(data: Any, what: str) -> np.ndarray:
    def undecodable(message: str) -> _BadMessage:
        return _BadMessage("undecodable", message)

    return decode_image(bytes(data), what, undecodable)


def rgb_from_compressed(fmt: str, data: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage (png/jpeg; OpenCV decodes to BGR) -> HxWx3 uint8 RGB."""
    if "compresseddepth" in fmt.lower():
        raise _BadMessage(
            "unsupported_encoding", f"format {fmt!r} is compressed depth, not a colour image"
        )
    img = _imdecode(data, f"compressed image ({fmt or 'no format'})")
    if img.dtype != np.uint8:
        raise _BadMessage(
            "unsupported_encoding",
            f"format {fmt!r} decodes to {img.dtype} pixels; colour images must be 8-bit",
        )
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    code = cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
    return cv2.cvtColor(img, code)


def depth_from_compressed(fmt: str, data: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage depth -> HxW float32 [m].

    ``compressedDepth`` (compressed_depth_image_transport, PNG flavour): a 12-byte ConfigHeader
    then a PNG of uint16 mm for 16UC1, or of quantised inverse depth for 32FC1, where
    ``z = depthQuantA / (v - depthQuantB)`` and v = 0 is invalid. A plain 16-bit PNG is mm.
    """
    lowered = fmt.lower()
    if "compresseddepth" in lowered:
        if "rvl" in lowered:
            raise _BadMessage(
                "unsupported_encoding",
                f"format {fmt!r}: RVL compressed depth is not supported; republish as "
                "compressedDepth png or raw 16UC1",
            )
        raw = bytes(data)
        start = raw.find(PNG_SIGNATURE, 0, COMPRESSED_DEPTH_HEADER.size + len(PNG_SIGNATURE))
        if start < COMPRESSED_DEPTH_HEADER.size:
            raise _BadMessage("undecodable", f"format {fmt!r}: no PNG after the depth header")
        _fmt_id, quant_a, quant_b = COMPRESSED_DEPTH_HEADER.unpack_from(raw, 0)
        img = _imdecode(raw[start:], f"compressed depth ({fmt})")
        if img.dtype != np.uint16 or img.ndim != 2:
            raise _BadMessage("undecodable", f"format {fmt!r}: expected a 16-bit 1-channel PNG")
        source_encoding = fmt.split(";")[0].strip()
        if source_encoding == "32FC1":
            v = img.astype(np.float32)
            with np.errstate(divide="ignore"):
                z = np.float32(quant_a) / (v - np.float32(quant_b))
            return np.where(img > 0, z, np.nan).astype(np.float32)
        return (img.astype(np.float32) / np.float32(MM_PER_M)).astype(np.float32)
    img = _imdecode(data, f"compressed depth ({fmt or 'no format'})")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise _BadMessage(
            "unsupported_encoding",
            f"format {fmt!r} decodes to {img.dtype} x{1 if img.ndim == 2 else img.shape[2]}; "
            "depth must be a 16-bit single-channel image in mm",
        )
    return (img.astype(np.float32) / np.float32(MM_PER_M)).astype(np.float32)


def intrinsics_from_camera_info(
    width: int, height: int, k: Sequence[float], depth_scale: float
) -> CameraIntrinsics:
    """Row-major 3x3 K of sensor_msgs/CameraInfo -> CameraIntrinsics."""
    kk = np.asarray(k, dtype=np.float64).reshape(-1)
    if kk.size != 9 or not np.all(np.isfinite(kk)) or kk[0] <= 0 or kk[4] <= 0:
        raise _BadMessage("uncalibrated_camera_info", f"CameraInfo K {kk.tolist()} is unusable")
    try:
        return CameraIntrinsics(
            width=int(width),
            height=int(height),
            fx=float(kk[0]),
            fy=float(kk[4]),
            cx=float(kk[2]),
            cy=float(kk[5]),
            depth_scale=depth_scale,
        )
    except SensorError as err:  # e.g. width 0: counted like an uncalibrated K
        raise _BadMessage("uncalibrated_camera_info", f"CameraInfo: {err}") from None


def ticks_from_wheel_angles(angles_rad: np.ndarray, ticks_per_revolution: int) -> np.ndarray:
    """Wheel angles [rad] -> cumulative encoder positions (int64), 2 pi = one revolution."""
    scale = ticks_per_revolution / (2.0 * math.pi)  # [positions/rad]
    return np.rint(np.asarray(angles_rad, dtype=np.float64) * scale).astype(np.int64)


def wheel_joint_indices(names: Sequence[str]) -> tuple[int, int]:
    """(left, right) indices of JointState joints: by *left*/*right* in the name, else (0, 1)."""
    lowered = [n.lower() for n in names]
    left = [i for i, n in enumerate(lowered) if "left" in n]
    right = [i for i, n in enumerate(lowered) if "right" in n]
    if len(left) == 1 and len(right) == 1:
        return left[0], right[0]
    return 0, 1


def _narrow(candidates: list[str], preferences: Sequence[Callable[[str], bool]]) -> str | None:
    """The unique candidate, narrowing a tie with each preference in turn; None if none/tied."""
    for prefer in (lambda _t: True, *preferences):
        narrowed = [t for t in candidates if prefer(t)]
        if len(narrowed) == 1:
            return narrowed[0]
        if narrowed:
            candidates = narrowed
    return None


def _namespace(topic: str | None) -> str:
    return topic.rsplit("/", 1)[0] if topic else "\0"


# Camera drivers' (rgb, registered depth, camera_info) topic triples, relative to the driver's
# namespace, most preferred first. Depth registered (aligned) to the colour image is what
# rgbdnav needs; the unregistered depth the same drivers also publish is never auto-picked.
DRIVER_TRIPLES: tuple[tuple[str, str, str, str], ...] = (
    # realsense2_camera 4.x (ROS 2, namespace /camera/camera), align_depth.enable:=true
    ("RealSense", "color/image_raw", "aligned_depth_to_color/image_raw", "color/camera_info"),
    # Azure_Kinect_ROS_Driver: depth_to_rgb is depth registered to the colour camera
    ("Azure Kinect", "rgb/image_raw", "depth_to_rgb/image_raw", "rgb/camera_info"),
    # iai_kinect2 kinect2_bridge: qhd, hd and sd rectified colour with registered depth
    ("Kinect v2", "qhd/image_color_rect", "qhd/image_depth_rect", "qhd/camera_info"),
    ("Kinect v2", "hd/image_color_rect", "hd/image_depth_rect", "hd/camera_info"),
    ("Kinect v2", "sd/image_color_rect", "sd/image_depth_rect", "sd/camera_info"),
    # openni_launch / openni2_launch with depth_registration:=true
    ("OpenNI", "rgb/image_rect_color", "depth_registered/image_raw", "rgb/camera_info"),
    ("OpenNI", "rgb/image_color", "depth_registered/image_raw", "rgb/camera_info"),
    ("OpenNI", "rgb/image_raw", "depth_registered/image_raw", "rgb/camera_info"),
    ("OpenNI", "rgb/image_rect_color", "depth_registered/image", "rgb/camera_info"),
    ("OpenNI", "rgb/image_color", "depth_registered/image", "rgb/camera_info"),
    ("OpenNI", "rgb/image_raw", "depth_registered/image_rect_raw", "rgb/camera_info"),
    # zed_wrapper (ZED ROS 2 wrapper, namespace /zed/zed_node)
    ("ZED", "rgb/image_rect_color", "depth/depth_registered", "rgb/camera_info"),
    # OrbbecSDK_ROS2 / OrbbecSDK_ROS1 (depth_registration:=true aligns depth to colour)
    ("Orbbec", "color/image_raw", "depth/image_raw", "color/camera_info"),
)
# The drivers' own IMU / odometry topics (relative to their namespace): an optical-frame gyro or
# visual odometry, never auto-picked as the robot's imu/odom (--imu-topic can still name one).
DRIVER_OWN_MOTION: Mapping[str, tuple[str, ...]] = {
    "RealSense": ("imu", "gyro/sample", "accel/sample"),
    "Azure Kinect": ("imu",),
    "ZED": ("imu/data", "imu/data_raw", "odom"),
    "Orbbec": ("gyro_accel/sample", "gyro/sample", "accel/sample"),
}
IMAGE_ROLES = ("rgb", "depth", "camera_info")
ROLE_FLAGS: Mapping[str, str] = {
    "rgb": "--rgb-topic",
    "depth": "--depth-topic",
    "camera_info": "--info-topic",
    "odom": "--odom-topic",
    "imu": "--imu-topic",
    "wheels": "--set topics.wheels=",
    "gps": "--set topics.gps=",
}


def match_driver(types: Mapping[str, str]) -> tuple[str, str, tuple[str, str, str]] | None:
    """(driver, namespace, (rgb, depth, info)) of the first driver triple the bag holds.

    Raises SensorError when two namespaces (two cameras) hold the same preferred triple.
    """
    for driver, rgb, depth, info in DRIVER_TRIPLES:
        spaces = sorted(
            t[: -len(rgb)]
            for t, ty in types.items()
            if t.endswith("/" + rgb)
            and ty in ROLE_TYPES["rgb"]
            and types.get(t[: -len(rgb)] + depth) in ROLE_TYPES["depth"]
        )
        if len(spaces) > 1:
            found = ", ".join(ns + depth for ns in spaces)
            raise SensorError(
                f"{driver} registered depth from {len(spaces)} cameras ({found}): "
                "choose one with --rgb-topic and --depth-topic"
            )
        if spaces:
            ns = spaces[0]
            return driver, ns, (ns + rgb, ns + depth, ns + info)
    return None


def resolve_topics(available: Mapping[str, str], wanted: RosbagTopics) -> dict[str, TopicChoice]:
    """Pick the topic for every role from ``available`` (topic -> message type).

    A configured topic of an accepted type is used as is. The image roles left at their defaults
    come from a known camera driver's topic set (:data:`DRIVER_TRIPLES`) when the bag holds
    one: registered depth with its colour image and colour camera_info. Otherwise, when a role's
    *default* topic is absent (or of the wrong type), the unique remaining topic of an accepted
    type is auto-detected, with name hints breaking ties (depth topics contain "depth";
    "registered" depth, raw Image over CompressedImage, camera_info beside the rgb topic, wheels
    named wheel/encoder). A camera driver's own IMU and odometry (optical-frame gyro, visual
    odometry) are never auto-picked for the robot's imu/odom roles.
    """
    types = {t: normalize_type(ty) for t, ty in available.items()}
    defaults = RosbagTopics()
    chosen: dict[str, TopicChoice] = {}
    for role in ROLES:
        topic = getattr(wanted, role)
        if types.get(topic) in ROLE_TYPES[role]:
            chosen[role] = TopicChoice(role, topic, types[topic])
    camera_own: set[str] = set()  # the matched driver's own IMU / odometry topics
    # Image roles the user did not name come from a driver's topic set: its registered depth
    # wins even over openni_launch's unregistered /camera/depth/image that our defaults name.
    if any(getattr(wanted, r) == getattr(defaults, r) for r in IMAGE_ROLES):
        try:
            driver = match_driver(types)
        except SensorError as err:  # two cameras: both image roles stay unresolved
            driver = None
            for role in ("rgb", "depth"):
                chosen[role] = TopicChoice(role, None, None, f"ambiguous: {err}")
        if driver is not None:
            name, camera_ns, triple = driver
            camera_own = {camera_ns + t for t in DRIVER_OWN_MOTION.get(name, ())}
            for role, topic in zip(IMAGE_ROLES, triple, strict=True):
                configured = getattr(wanted, role) != getattr(defaults, role)
                if not configured and types.get(topic) in ROLE_TYPES[role]:
                    chosen[role] = TopicChoice(
                        role, topic, types[topic], f"{name} driver topics under {camera_ns}"
                    )
    taken = {c.topic for c in chosen.values()}
    for role in ROLES:
        if role in chosen:
            continue
        topic = getattr(wanted, role)
        why = f"{topic} absent" if topic not in types else f"{topic} is {short_type(types[topic])}"
        if topic != getattr(defaults, role):
            chosen[role] = TopicChoice(role, None, None, f"configured topic {why}")
            continue
        candidates = sorted(
            t for t, ty in types.items() if ty in ROLE_TYPES[role] and t not in taken
        )
        if role in ("imu", "odom"):
            own = [t for t in candidates if t in camera_own]
            candidates = [t for t in candidates if t not in camera_own]
            if own and not candidates:
                why += f"; the camera's own {', '.join(own)} not used for the robot (set it)"
        pick = _auto_pick(role, candidates, types, chosen)
        if pick is not None:
            chosen[role] = TopicChoice(role, pick, types[pick], f"auto-detected; {why}")
            taken.add(pick)
        elif candidates:
            chosen[role] = TopicChoice(
                role, None, None, f"{why}; ambiguous: {', '.join(candidates)} (set the topic)"
            )
        else:
            kinds = " or ".join(short_type(t) for t in ROLE_TYPES[role])
            chosen[role] = TopicChoice(role, None, None, f"{why}; no {kinds} topic")
    return chosen


def check_topics(
    available: Mapping[str, str], wanted: RosbagTopics, chosen: Mapping[str, TopicChoice]
) -> None:
    """Refuse, in one line, a configured topic the bag lacks and any ambiguous role.

    Commands that process a bag call this (``info`` only describes): a missing stream must not
    silently turn VO, the IMU or odometry off.
    """
    types = {t: normalize_type(ty) for t, ty in available.items()}
    defaults = RosbagTopics()
    problems = []
    for role in ROLES:
        c = chosen[role]
        if c.topic is not None:
            continue
        kinds = ROLE_TYPES[role]
        candidates = sorted(t for t, ty in types.items() if ty in kinds)
        listed = ", ".join(candidates) if candidates else "none"
        kind = " or ".join(short_type(k) for k in kinds)
        flag = ROLE_FLAGS[role]
        if getattr(wanted, role) != getattr(defaults, role):
            problems.append(
                f"{role} topic {getattr(wanted, role)} is not in the bag ({kind} topics: {listed})"
            )
        elif c.note.startswith("ambiguous: "):
            problems.append(c.note.removeprefix("ambiguous: "))
        elif "ambiguous" in c.note:
            problems.append(f"{role} is ambiguous: {listed}; choose one with {flag}")
    if problems:
        raise SensorError("; ".join(dict.fromkeys(problems)))


def _auto_pick(
    role: str, candidates: list[str], types: Mapping[str, str], chosen: Mapping[str, TopicChoice]
) -> str | None:
    def is_depth(t: str) -> bool:
        return "depth" in t.lower()

    def raw_image(t: str) -> bool:
        return types[t] == IMAGE

    if role == "rgb":
        return _narrow([t for t in candidates if not is_depth(t)], [raw_image])
    if role == "depth":
        return _narrow(
            [t for t in candidates if is_depth(t)], [lambda t: "registered" in t, raw_image]
        )
    if role == "camera_info":
        rgb, depth = chosen.get("rgb"), chosen.get("depth")
        return _narrow(
            candidates,
            [
                lambda t: _namespace(t) == _namespace(rgb.topic if rgb else None),
                lambda t: _namespace(t) == _namespace(depth.topic if depth else None),
                # RealSense SDK recordings: .../Color_0/image/camera_info (or info/camera_info)
                # shares the most path components with .../Color_0/image/data
                lambda t: (
                    _shared_depth(t, rgb.topic if rgb else None)
                    == max(_shared_depth(c, rgb.topic if rgb else None) for c in candidates)
                ),
            ],
        )
    if role == "wheels":
        return _narrow(candidates, [lambda t: "wheel" in t.lower() or "encoder" in t.lower()])
    return _narrow(candidates, [])


def _shared_depth(a: str, b: str | None) -> int:
    """How many leading path components two topics share."""
    if b is None:
        return 0
    n = 0
    for x, y in zip(a.strip("/").split("/"), b.strip("/").split("/"), strict=False):
        if x != y:
            break
        n += 1
    return n


def parse_sdk_transform(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """RealSense SDK ``tf`` string ``rotation=r0,...,r8;translation=x,y,z`` -> (R row-major, t)."""
    fields_ = dict(part.split("=", 1) for part in text.strip(";").split(";") if "=" in part)
    try:
        rotation = tuple(float(v) for v in fields_["rotation"].split(","))
        translation = tuple(float(v) for v in fields_["translation"].split(","))
    except (KeyError, ValueError) as err:
        raise SensorError(f"RealSense SDK transform {text!r} is unreadable") from err
    if len(rotation) != 9 or len(translation) != 3:
        raise SensorError(f"RealSense SDK transform {text!r} is not 3x3 + 3")
    rot = np.array(rotation).reshape(3, 3)
    if not (np.isfinite(rot).all() and np.isfinite(translation).all()) or not np.allclose(
        rot @ rot.T, np.eye(3), atol=1e-2
    ):  # NaN / inf or a non-rotation would be taken as the camera extrinsics silently
        raise SensorError(f"RealSense SDK transform {text[:120]!r} is not a finite rotation")
    return rotation, translation


def _nearest_sorted(sorted_values: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Index into ascending ``sorted_values`` of the nearest value to each query."""
    j = np.searchsorted(sorted_values, queries)
    lo = np.clip(j - 1, 0, len(sorted_values) - 1)
    hi = np.clip(j, 0, len(sorted_values) - 1)
    take_hi = np.abs(sorted_values[hi] - queries) < np.abs(queries - sorted_values[lo])
    return np.where(take_hi, hi, lo)


def fix_camera_info_stamps(
    info_ns: np.ndarray,
    info_receive_ns: np.ndarray,
    rgb_ns: np.ndarray,
    rgb_receive_ns: np.ndarray,
    tolerance_ns: int,
) -> tuple[np.ndarray, np.ndarray]:
    """CameraInfo stamps further than ``tolerance_ns`` from every rgb stamp take the stamp of the
    rgb image received closest to them. Returns (fixed stamps, mask of fixed ones)."""
    info_ns = np.asarray(info_ns, dtype=np.int64)
    if len(rgb_ns) == 0 or len(info_ns) == 0:
        return info_ns.copy(), np.zeros(len(info_ns), dtype=bool)
    order = np.argsort(rgb_ns, kind="stable")
    sorted_rgb = np.asarray(rgb_ns, dtype=np.int64)[order]
    nearest = sorted_rgb[_nearest_sorted(sorted_rgb, info_ns)]
    bad = np.abs(nearest - info_ns) > tolerance_ns
    recv_order = np.argsort(rgb_receive_ns, kind="stable")
    sorted_recv = np.asarray(rgb_receive_ns, dtype=np.int64)[recv_order]
    closest = recv_order[_nearest_sorted(sorted_recv, np.asarray(info_receive_ns)[bad])]
    fixed = info_ns.copy()
    fixed[bad] = np.asarray(rgb_ns, dtype=np.int64)[closest]
    return fixed, bad


def pair_rgb_depth(
    rgb_ns: np.ndarray, depth_ns: np.ndarray, max_difference_ns: int
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """One-to-one rgb/depth pairs from stamps in file order (possibly unsorted or repeated).

    Returns message ordinals (rgb_i, depth_i), in rgb-stamp order, and counts of what was left:
    ``duplicate_stamp`` (repeated stamps, first kept), ``rgb_without_depth``,
    ``depth_without_rgb``.
    """
    counts: dict[str, int] = {}

    def unique_sorted(stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        order = np.argsort(stamps, kind="stable")
        s = np.asarray(stamps, dtype=np.int64)[order]
        keep = np.ones(len(s), dtype=bool)
        keep[1:] = s[1:] != s[:-1]
        dup = int(np.count_nonzero(~keep))
        if dup:
            counts["duplicate_stamp"] = counts.get("duplicate_stamp", 0) + dup
        return s[keep], order[keep]

    rgb_sorted, rgb_order = unique_sorted(np.asarray(rgb_ns, dtype=np.int64))
    depth_sorted, depth_order = unique_sorted(np.asarray(depth_ns, dtype=np.int64))
    ia, ib = associate(rgb_sorted, depth_sorted, max_difference_ns)
    if len(rgb_sorted) > len(ia):
        counts["rgb_without_depth"] = len(rgb_sorted) - len(ia)
    if len(depth_sorted) > len(ib):
        counts["depth_without_rgb"] = len(depth_sorted) - len(ib)
    return rgb_order[ia].astype(np.int64), depth_order[ib].astype(np.int64), counts


# --- the adapter -------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Index:
    """Stamps of one topic, in file order."""

    stamps_ns: np.ndarray  # (N,) int64 [ns] header stamps (receive time where zero/absent)
    receive_ns: np.ndarray  # (N,) int64 [ns] bag receive times


@dataclass(frozen=True, eq=False)
class _CameraInfos:
    stamps_ns: np.ndarray  # (M,) int64 [ns], ascending, after fixing
    intrinsics: list[CameraIntrinsics]


def _rosbags_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that ``rosbags`` raises on unreadable bags (imported lazily)."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.typesys import TypesysError

    return (
        AnyReaderError,
        Reader1Error,
        Reader2Error,
        TypesysError,
        OSError,
        EOFError,
        struct.error,
        ValueError,
    )


class RosbagSource(SourceBase):
    """A rosbag1/rosbag2 file or folder opened for reading. Use :meth:`open` or ``open_source``."""

    def __init__(
        self,
        path: Path,
        reader: AnyReader,
        choices: dict[str, TopicChoice],
        *,
        strict: bool,
        robot: RobotConfig,
        camera: CameraConfig,
        sync: SyncConfig,
    ) -> None:
        self.path = str(path)
        self.skipped: dict[str, int] = {}
        self.choices = choices
        self.strict = strict
        self._reader: AnyReader | None = reader
        self._robot = robot
        self._camera = camera
        self._max_difference_ns = seconds_to_ns(sync.slop)
        self._info_tolerance_ns = seconds_to_ns(sync.camera_info_stamp_tolerance)
        self._errors = _rosbags_errors()
        self._decode_errors: tuple[type[BaseException], ...] = (
            *self._errors,
            IndexError,
            TypeError,
        )
        self._connections = {c.topic: c for c in reader.connections}
        self._topic_types = {t: normalize_type(i.msgtype or "") for t, i in reader.topics.items()}
        self._topic_counts = {t: int(i.msgcount) for t, i in reader.topics.items()}
        self._is_ros2 = bool(reader.is2)
        self._duration_ns = int(reader.duration) if reader.message_count else 0
        self._message_count = int(reader.message_count)
        self._cache: dict[str, Any] = {}
        self._base_counts: dict[str, int] = {}  # from cached per-stream reads; counted once
        self._zero_counted: set[str] = set()  # roles whose zero header stamps were counted
        self._warned: set[tuple[str, str]] = set()

    # --- opening ------------------------------------------------------------------------------

    @classmethod
    def try_open(
        cls, path: Path | str, options: SourceOptions | None = None
    ) -> RosbagSource | None:
        p = Path(path)
        if not looks_like_rosbag(p):
            return None
        if options is None:
            return cls.open(p)
        topics = RosbagTopics(**options.topics) if options.topics else None
        # Intrinsics from the user's camera config only stand in when the bag has no CameraInfo.
        return cls.open(
            p,
            topics,
            strict=options.strict,
            require_topics=options.require_topics,
            robot=options.robot,
            camera=options.camera,
            sync=options.sync,
        )

    @classmethod
    def open(
        cls,
        path: str | Path,
        topics: RosbagTopics | None = None,
        *,
        strict: bool = False,
        robot: RobotConfig | None = None,
        camera: CameraConfig | None = None,
        sync: SyncConfig | None = None,
        require_topics: bool = False,
    ) -> RosbagSource:
        """Open a bag; the reader is closed again if anything after opening it fails.

        ``require_topics``: refuse a missing configured topic or an ambiguous role
        (:func:`check_topics`) instead of reading on without that stream."""
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        path = Path(path)
        if not path.exists():
            raise SensorError(f"{path}: no such file or folder")
        reader_path = bag_reader_path(path)
        errors = _rosbags_errors()
        # Bags written without message definitions (rosbag2 before Iron) need a typestore;
        # rosbag1 always embeds its definitions.
        typestore = get_typestore(Stores.ROS2_HUMBLE)
        try:
            reader = AnyReader([reader_path], default_typestore=typestore)
            reader.open()
        except errors as err:
            raise SensorError(f"{path}: cannot read as a rosbag: {err}") from err
        try:
            available = {t: info.msgtype or "" for t, info in reader.topics.items()}
            choices = resolve_topics(available, topics or RosbagTopics())
            if require_topics:
                try:
                    check_topics(available, topics or RosbagTopics(), choices)
                except SensorError as err:
                    raise SensorError(f"{path}: {err}") from None
            return cls(
                path,
                reader,
                choices,
                strict=strict,
                robot=robot or RobotConfig(),
                camera=camera or CameraConfig(),
                sync=sync or SyncConfig(),
            )
        except BaseException as err:
            reader.close()
            if isinstance(err, errors):
                raise SensorError(f"{path}: cannot read as a rosbag: {err}") from err
            raise

    def close(self) -> None:
        if self._reader is not None:
            reader, self._reader = self._reader, None
            reader.close()

    # --- Source -------------------------------------------------------------------------------

    def describe(self) -> str:
        kind = self._kind()
        parts = [f"{kind}, {self._duration_ns / NS_PER_S:.1f} s, {self._message_count} messages"]
        used = set()
        for role in ROLES:
            c = self.choices[role]
            if c.topic is None:
                parts.append(f"{role}: none ({c.note})")
                continue
            used.add(c.topic)
            count = self._topic_counts.get(c.topic, 0)
            note = f", {c.note}" if c.note else ""
            parts.append(
                f"{role} {c.topic} ({short_type(c.msgtype or '')}, {count} messages{note})"
            )
        if self.choices["camera_info"].topic is None and self._has_images():
            k = self._config_intrinsics()
            parts.append(f"intrinsics from config: fx={k.fx:g} fy={k.fy:g} cx={k.cx:g} cy={k.cy:g}")
        parts += self._describe_sdk()
        others = [
            f"{t} ({short_type(ty)}, {self._topic_counts.get(t, 0)})"
            for t, ty in sorted(self._topic_types.items())
            if t not in used
        ]
        if others:
            parts.append("other topics: " + ", ".join(others))
        elif not self._topic_types:
            parts.append("the bag has no topics")
        return "; ".join(parts)

    def stream_stamps(self) -> dict[str, np.ndarray]:
        """Header stamps per stream, in file order, read without deserialising images."""
        out: dict[str, np.ndarray] = {}
        for role in ROLES:
            if self.choices[role].topic is not None:
                out[STREAM_NAMES.get(role, role)] = self._index(role).stamps_ns
        return out

    def intrinsics(self) -> CameraIntrinsics | None:
        infos = self._camera_infos()
        if infos is not None and infos.intrinsics:
            return infos.intrinsics[0]
        return self._config_intrinsics() if self._has_images() else None

    def frames(self) -> Iterator[RgbdFrame]:
        """Associated rgb/depth frames in rgb-stamp order, stamped with the rgb stamp.

        ``skipped`` then holds this call's frame skips plus what reading the other streams
        (once each, cached) skipped or fixed.
        """
        self.skipped = dict(self._base_counts)
        if not self._has_images():
            missing = [r for r in ("rgb", "depth") if self.choices[r].topic is None]
            log.warning("%s: no frames: no %s topic", self.path, " or ".join(missing))
            return
        rgb_idx, depth_idx = self._index("rgb"), self._index("depth")
        rgb_i, depth_i, counts = pair_rgb_depth(
            rgb_idx.stamps_ns, depth_idx.stamps_ns, self._max_difference_ns
        )
        for reason, n in counts.items():
            self._add(reason, n, frame=True)
        pair_of = {
            "rgb": np.full(len(rgb_idx.stamps_ns), -1, dtype=np.int64),
            "depth": np.full(len(depth_idx.stamps_ns), -1, dtype=np.int64),
        }
        pair_of["rgb"][rgb_i] = np.arange(len(rgb_i))
        pair_of["depth"][depth_i] = np.arange(len(depth_i))
        stamps = rgb_idx.stamps_ns[rgb_i]
        intrinsics = self._intrinsics_for(stamps)
        # Pairs complete in file order; a small reorder buffer yields them in rgb-stamp order.
        halves: dict[int, dict[str, np.ndarray]] = {}
        finished: dict[int, RgbdFrame | None] = {}
        ordinal = {"rgb": 0, "depth": 0}
        next_k = 0
        for role, _receive_ns, raw in self._raw_messages(("rgb", "depth")):
            n = ordinal[role]
            ordinal[role] += 1
            k = int(pair_of[role][n]) if n < len(pair_of[role]) else -1
            if k < next_k or k in finished:  # unpaired (-1), or its pair is already settled
                continue
            image = self._decode_image(role, raw)
            if image is None:
                finished[k] = None
                halves.pop(k, None)
            else:
                half = halves.setdefault(k, {})
                half[role] = image
                if len(half) == 2:
                    del halves[k]
                    finished[k] = self._assemble(int(stamps[k]), half, intrinsics[k])
            while next_k in finished:
                frame = finished.pop(next_k)
                next_k += 1
                if frame is not None:
                    yield frame
        for k in sorted(finished):
            frame = finished[k]
            if frame is not None:
                yield frame

    def wheels(self) -> WheelStream | None:
        if self.choices["wheels"].topic is None:
            return None
        if "wheels" not in self._cache:
            self._cache["wheels"] = self._read_wheels()
        stream: WheelStream = self._cache["wheels"]
        return stream

    def imu(self) -> ImuStream | None:
        if self.choices["imu"].topic is None:
            return None
        if "imu" not in self._cache:
            stamps, gz = self._read_stamped("imu", lambda m: (float(m.angular_velocity.z),))
            self._cache["imu"] = ImuStream(stamps, gz[:, 0].copy())
        stream: ImuStream = self._cache["imu"]
        return stream

    def gps(self) -> GpsStream | None:
        """NavSatFix messages with a fix (status >= STATUS_FIX) and a known covariance, as a
        :class:`GpsStream`; the others are counted in ``skipped``."""
        if self.choices["gps"].topic is None:
            return None
        if "gps" not in self._cache:

            def fix(m: Any) -> tuple[float, ...]:
                if int(m.status.status) < 0:
                    raise _BadMessage("gps_no_fix", "NavSatFix without a fix (status -1)")
                sigma = navsatfix_sigma(m.position_covariance, int(m.position_covariance_type))
                if not sigma > 0:
                    raise _BadMessage("gps_no_covariance", "NavSatFix with unknown covariance")
                out = (float(m.latitude), float(m.longitude), float(m.altitude), sigma)
                if not (all(map(math.isfinite, out)) and abs(out[0]) <= 90 and abs(out[1]) <= 180):
                    raise _BadMessage(
                        "gps_bad_fix", "NavSatFix with a non-finite or impossible fix"
                    )
                return out

            stamps, v = self._read_stamped("gps", fix)
            self._cache["gps"] = check_fixes(
                GpsStream(stamps, v[:, 0].copy(), v[:, 1].copy(), v[:, 2].copy(), v[:, 3].copy()),
                f"{self.path} {self.choices['gps'].topic}",
            )
        stream: GpsStream = self._cache["gps"]
        return stream

    def odometry(self) -> PoseStream | None:
        if self.choices["odom"].topic is None:
            return None
        if "odom" not in self._cache:

            def pose(m: Any) -> tuple[float, ...]:
                p, q = m.pose.pose.position, m.pose.pose.orientation
                lin, ang = m.twist.twist.linear, m.twist.twist.angular
                return (
                    float(p.x),
                    float(p.y),
                    float(q.x),
                    float(q.y),
                    float(q.z),
                    float(q.w),
                    float(lin.x),
                    float(lin.y),
                    float(ang.z),
                    *np.asarray(m.pose.covariance, np.float64)[PLANAR_COV],
                    *np.asarray(m.twist.covariance, np.float64)[PLANAR_COV],
                )

            stamps, v = self._read_stamped("odom", pose)
            v = v.reshape(-1, 27)
            yaw = yaw_from_quaternion(v[:, 2:6]) if len(v) else np.zeros(0)
            self._cache["odom"] = PoseStream(
                stamps,
                v[:, 0].copy(),
                v[:, 1].copy(),
                yaw,
                frame="base_link",
                twist=v[:, 6:9].copy(),
                pose_covariance=v[:, 9:18].reshape(-1, 3, 3).copy(),
                twist_covariance=v[:, 18:27].reshape(-1, 3, 3).copy(),
            )
        stream: PoseStream = self._cache["odom"]
        return stream

    def static_extrinsics(self) -> tuple[dict[str, float], str] | None:
        """Camera mount (RobotConfig camera_* keys) from ``/tf_static``, and where it came from
        (``"base_link -> camera_color_optical_frame"``), or None without a usable chain.

        The camera frame is the depth image's ``header.frame_id``; the chain is composed up to
        base_footprint, else base_link. A chain that exists but cannot be used (a camera yawed
        on the robot) raises SensorError: the config must then say where the camera is.
        """
        if "tf_static" not in self._cache:  # a refused chain raises again, uncached
            self._cache["tf_static"] = self._read_static_extrinsics()
        cached: tuple[dict[str, float], str] | None = self._cache["tf_static"]
        return cached

    def _read_static_extrinsics(self) -> tuple[dict[str, float], str] | None:
        from sensors.extrinsics import chain_to_root, quaternion_matrix, robot_mount_from_tf

        if self._reader is None or self.choices["depth"].topic is None:
            return None
        tf_conns = [
            c
            for c in self._reader.connections
            if c.topic == TF_STATIC and normalize_type(c.msgtype) == TF_MESSAGE
        ]
        if not tf_conns:
            return None
        depth_conns = [
            c for c in self._reader.connections if c.topic == self.choices["depth"].topic
        ]
        frame = None
        try:
            for conn, _t, raw in self._reader.messages(connections=depth_conns):
                image: Any = self._reader.deserialize(raw, conn.msgtype)
                frame = str(image.header.frame_id)
                break
            edges: dict[str, tuple[str, np.ndarray]] = {}
            for conn, _t, raw in self._reader.messages(connections=tf_conns):
                tf_message: Any = self._reader.deserialize(raw, conn.msgtype)
                for tf in tf_message.transforms:
                    tr, q = tf.transform.translation, tf.transform.rotation
                    t = np.eye(4)
                    t[:3, :3] = quaternion_matrix(q.x, q.y, q.z, q.w)
                    t[:3, 3] = (tr.x, tr.y, tr.z)
                    edges[str(tf.child_frame_id).lstrip("/")] = (
                        str(tf.header.frame_id).lstrip("/"),
                        t,
                    )
        except self._decode_errors as err:
            raise SensorError(f"{self.path}: reading {TF_STATIC} failed: {err}") from err
        if not frame:
            return None
        found = chain_to_root(edges, frame.lstrip("/"))
        if found is None:
            return None
        root, t_root_camera = found
        try:
            mount = robot_mount_from_tf(t_root_camera, optical="optical" in frame)
        except ValueError as err:
            raise SensorError(f"{self.path}: {TF_STATIC} {root} -> {frame}: {err}") from None
        return mount, f"{root} -> {frame.lstrip('/')}"

    # --- internals ----------------------------------------------------------------------------

    def _kind(self) -> str:
        p = Path(self.path)
        if not self._is_ros2:
            return f"rosbag1 {p.name}"
        if p.is_file():
            return f"rosbag2 ({p.suffix.lstrip('.').replace('db3', 'sqlite3')}) {p.name}"
        storage = "mcap" if any(p.glob("*.mcap")) else "sqlite3"
        return f"rosbag2 ({storage}) {p.name}"

    def _has_images(self) -> bool:
        return self.choices["rgb"].topic is not None and self.choices["depth"].topic is not None

    def _config_intrinsics(self) -> CameraIntrinsics:
        c = self._camera
        return CameraIntrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.depth_scale)

    def _add(self, reason: str, n: int = 1, frame: bool = False) -> None:
        """Count a skip or fix; frame-level ones are recounted by every frames() call."""
        if not frame:
            self._base_counts[reason] = self._base_counts.get(reason, 0) + n
        self.skipped[reason] = self.skipped.get(reason, 0) + n

    def _bad(self, role: str, err: _BadMessage) -> None:
        """A bad message: raise in strict mode, else warn (once per topic and reason) and count."""
        topic = self.choices[role].topic
        if self.strict:
            raise SensorError(f"{self.path}: topic {topic}: {err}") from err
        key = (str(topic), err.reason)
        if key not in self._warned:
            self._warned.add(key)
            log.warning("%s: skipping messages on %s: %s", self.path, topic, err)
        self._add(err.reason, frame=role in ("rgb", "depth"))

    def _raw_messages(self, roles: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        """(role, receive time [ns], raw bytes) of the roles' topics, in file order."""
        if self._reader is None:
            raise SensorError(f"{self.path}: the bag is closed")
        role_of = {
            str(self.choices[r].topic): r for r in roles if self.choices[r].topic is not None
        }
        connections = [c for c in self._reader.connections if c.topic in role_of]
        if not connections:  # an empty filter would mean every message
            return
        try:
            for conn, receive_ns, raw in self._reader.messages(connections=connections):
                yield role_of[conn.topic], int(receive_ns), raw
        except self._errors as err:
            raise SensorError(f"{self.path}: reading {', '.join(role_of)} failed: {err}") from err

    def _deserialize(self, role: str, raw: bytes) -> Any:
        assert self._reader is not None
        msgtype = self._connections[str(self.choices[role].topic)].msgtype
        try:
            return self._reader.deserialize(raw, msgtype)
        except self._decode_errors as err:
            raise _BadMessage(
                "undecodable", f"cannot deserialise {short_type(msgtype)}: {err}"
            ) from err

    def _index(self, role: str) -> _Index:
        """Stamps of a role's topic; header stamps read straight from the raw bytes."""
        key = f"index:{role}"
        if key in self._cache:
            index: _Index = self._cache[key]
            return index
        msgtype = self.choices[role].msgtype
        headerless = msgtype in HEADERLESS_TYPES
        stamps: list[int] = []
        receive: list[int] = []
        for _role, receive_ns, raw in self._raw_messages((role,)):
            stamp = receive_ns if headerless else header_stamp_ns_from_raw(raw, self._is_ros2)
            if stamp is None:
                try:
                    stamp = stamp_to_ns(self._deserialize(role, raw).header.stamp)
                except _BadMessage:
                    stamp = receive_ns  # the message is skipped (and counted) when decoded
            stamps.append(stamp)
            receive.append(receive_ns)
        index = self._fallback_stamps(role, np.array(stamps, np.int64), np.array(receive, np.int64))
        self._cache[key] = index
        return index

    def _fallback_stamps(self, role: str, stamps: np.ndarray, receive: np.ndarray) -> _Index:
        zero = stamps == 0
        if zero.any():
            n = int(np.count_nonzero(zero))
            if role not in self._zero_counted:
                self._zero_counted.add(role)
                log.warning(
                    "%s: %d messages on %s have a zero header stamp; using the bag receive time",
                    self.path,
                    n,
                    self.choices[role].topic,
                )
                self._add("zero_header_stamp", n)
            stamps = np.where(zero, receive, stamps)
        return _Index(stamps, receive)

    def _decode_image(self, role: str, raw: bytes) -> np.ndarray | None:
        image = self._decode_image_as_is(role, raw)
        sdk = self._sdk_meta() if role == "depth" else None
        if image is None or sdk is None or sdk.depth_units is None:
            return image
        msg_encoding = self._cache.setdefault("depth_encoding", self._depth_encoding(raw))
        if "32FC1" in msg_encoding:
            return image  # metres already
        # the decoders read 16-bit depth as mm; the SDK's counts are depth_units metres
        return (image * np.float32(sdk.depth_units * MM_PER_M)).astype(np.float32)

    def _depth_encoding(self, raw: bytes) -> str:
        msg = self._deserialize("depth", raw)
        return str(getattr(msg, "format", None) or getattr(msg, "encoding", ""))

    def _first_message(self, topic: str) -> Any:
        assert self._reader is not None
        conn = self._connections[topic]
        for c, _t, raw in self._reader.messages(connections=[conn]):
            return self._reader.deserialize(raw, c.msgtype)
        return None

    def _sdk_meta(self) -> SdkMeta | None:
        """Depth units, colour-depth extrinsics and the depth stream's K of an SDK recording."""
        if "sdk" in self._cache:
            return self._cache["sdk"]
        meta = None
        if any(SDK_TOPIC.match(t) for t in self._topic_types):
            units = units_topic = extr = extr_topic = depth_k = None
            for topic in sorted(self._topic_types):
                if SDK_DEPTH_UNITS.match(topic):
                    value: Any = getattr(self._first_message(topic), "data", None)
                    try:
                        units, units_topic = float(value), topic  # String or Float32
                    except (TypeError, ValueError):
                        log.warning("%s: depth units %r unreadable", topic, value)
            rgb, depth = self.choices["rgb"].topic, self.choices["depth"].topic
            colour = SDK_STREAM.match(rgb or "")
            if colour:
                for topic, ty in sorted(self._topic_types.items()):
                    if topic.startswith(f"{colour.group(1)}/tf/") and ty == "std_msgs/msg/String":
                        extr = parse_sdk_transform(str(self._first_message(topic).data))
                        extr_topic = topic
                        break
            stream = SDK_STREAM.match(depth or "")
            if stream:
                for topic, ty in sorted(self._topic_types.items()):
                    if topic.startswith(f"{stream.group(1)}/") and ty == CAMERA_INFO:
                        depth_k = tuple(float(v) for v in self._first_message(topic).k)
                        break
            meta = SdkMeta(units, units_topic, extr, extr_topic, depth_k)
        self._cache["sdk"] = meta
        return meta

    def _describe_sdk(self) -> list[str]:
        sdk = self._sdk_meta()
        if sdk is None:
            return []
        parts = []
        if sdk.depth_units is not None:
            parts.append(
                f"depth units {sdk.depth_units * MM_PER_M:g} mm from {sdk.depth_units_topic}"
            )
        if sdk.extrinsics is not None:
            t = ", ".join(f"{v * MM_PER_M:+.1f}" for v in sdk.extrinsics[1])
            parts.append(
                f"colour-depth extrinsics: translation ({t}) mm from {sdk.extrinsics_topic}"
            )
        infos = self._camera_infos()
        colour_k = infos.intrinsics[0] if infos is not None and infos.intrinsics else None
        if sdk.depth_k is not None and colour_k is not None:
            same_k = np.allclose(sdk.depth_k, colour_k.matrix().ravel())
            moved = sdk.extrinsics is not None and np.any(np.abs(sdk.extrinsics[1]) > 1e-4)
            if not same_k or moved:
                parts.append(
                    "depth is NOT registered to colour (own intrinsics or offset): open it as "
                    f"realsense://{self.path} to align depth to colour"
                )
        return parts

    def _decode_image_as_is(self, role: str, raw: bytes) -> np.ndarray | None:
        try:
            msg = self._deserialize(role, raw)
            if self.choices[role].msgtype == COMPRESSED_IMAGE:
                decode_c = rgb_from_compressed if role == "rgb" else depth_from_compressed
                return decode_c(str(msg.format), msg.data)
            decode = rgb_from_image if role == "rgb" else depth_from_image
            return decode(
                str(msg.encoding),
                int(msg.height),
                int(msg.width),
                int(msg.step),
                msg.data,
                bool(msg.is_bigendian),
            )
        except _BadMessage as err:
            self._bad(role, err)
            return None

    def _assemble(
        self, stamp_ns: int, half: dict[str, np.ndarray], k: CameraIntrinsics
    ) -> RgbdFrame | None:
        rgb, depth = half["rgb"], half["depth"]
        if k.width == 0 or k.height == 0:  # some drivers leave CameraInfo's size unset
            k = replace(k, width=depth.shape[1], height=depth.shape[0])
        try:
            if rgb.shape[:2] != depth.shape:
                raise _BadMessage(
                    "size_mismatch",
                    f"rgb is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                    f"{depth.shape[1]}x{depth.shape[0]}; depth must be registered to rgb",
                )
            if (k.height, k.width) != depth.shape:
                raise _BadMessage(
                    "size_mismatch",
                    f"images are {depth.shape[1]}x{depth.shape[0]} but the intrinsics are "
                    f"for {k.width}x{k.height}",
                )
        except _BadMessage as err:
            self._bad("depth", err)
            return None
        return RgbdFrame(stamp_ns, rgb, depth, k)

    def _camera_infos(self) -> _CameraInfos | None:
        if self.choices["camera_info"].topic is None:
            return None
        if "camera_info" in self._cache:
            infos: _CameraInfos = self._cache["camera_info"]
            return infos
        stamps: list[int] = []
        receive: list[int] = []
        intrinsics: list[CameraIntrinsics] = []
        depth_scale = self._camera.depth_scale
        for _role, receive_ns, raw in self._raw_messages(("camera_info",)):
            try:
                msg = self._deserialize("camera_info", raw)
                k = msg.k if hasattr(msg, "k") else msg.K  # ROS 2 / ROS 1 field names
                intrinsics.append(
                    intrinsics_from_camera_info(int(msg.width), int(msg.height), k, depth_scale)
                )
            except _BadMessage as err:
                self._bad("camera_info", err)
                continue
            stamps.append(stamp_to_ns(msg.header.stamp))
            receive.append(receive_ns)
        index = self._fallback_stamps(
            "camera_info", np.array(stamps, np.int64), np.array(receive, np.int64)
        )
        fixed = index.stamps_ns
        if self.choices["rgb"].topic is not None and len(fixed):
            rgb = self._index("rgb")
            fixed, was_fixed = fix_camera_info_stamps(
                fixed, index.receive_ns, rgb.stamps_ns, rgb.receive_ns, self._info_tolerance_ns
            )
            if was_fixed.any():
                self._add("camera_info_stamp_fixed", int(np.count_nonzero(was_fixed)))
        order = np.argsort(fixed, kind="stable")
        infos = _CameraInfos(fixed[order], [intrinsics[i] for i in order])
        self._cache["camera_info"] = infos
        return infos

    def _intrinsics_for(self, stamps_ns: np.ndarray) -> list[CameraIntrinsics]:
        """The latest CameraInfo at or before each stamp (within tolerance), else the first."""
        infos = self._camera_infos()
        if infos is None or not infos.intrinsics:
            return [self._config_intrinsics()] * len(stamps_ns)
        i = np.searchsorted(infos.stamps_ns, stamps_ns + self._info_tolerance_ns, side="right")
        return [infos.intrinsics[j] for j in np.clip(i - 1, 0, len(infos.intrinsics) - 1)]

    def _read_stamped(
        self, role: str, extract: Callable[[Any], tuple[float, ...]]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns, values (N, F) float64) of a header-stamped topic, bad messages skipped."""
        stamps: list[int] = []
        receive: list[int] = []
        rows: list[tuple[float, ...]] = []
        for _role, receive_ns, raw in self._raw_messages((role,)):
            try:
                msg = self._deserialize(role, raw)
                row = extract(msg)
            except _BadMessage as err:
                self._bad(role, err)
                continue
            stamps.append(stamp_to_ns(msg.header.stamp))
            receive.append(receive_ns)
            rows.append(row)
        index = self._fallback_stamps(role, np.array(stamps, np.int64), np.array(receive, np.int64))
        values = np.array(rows, dtype=np.float64).reshape(len(rows), -1)
        return index.stamps_ns, values

    def _read_wheels(self) -> WheelStream:
        msgtype = self.choices["wheels"].msgtype
        stamps: list[int] = []
        receive: list[int] = []
        ticks: list[tuple[int, int]] = []
        for _role, receive_ns, raw in self._raw_messages(("wheels",)):
            try:
                msg = self._deserialize("wheels", raw)
                if msgtype == JOINT_STATE:
                    left, right = wheel_joint_indices(list(msg.name))
                    pos = np.asarray(msg.position, dtype=np.float64)
                    if pos.size <= max(left, right):
                        raise _BadMessage("bad_wheel_message", f"JointState has {pos.size} joints")
                    lr = ticks_from_wheel_angles(
                        pos[[left, right]], self._robot.ticks_per_revolution
                    )
                    stamp = stamp_to_ns(msg.header.stamp)
                else:
                    data = np.asarray(msg.data)
                    if data.size < 2:
                        raise _BadMessage(
                            "bad_wheel_message", f"data has {data.size} values, need [left, right]"
                        )
                    lr, stamp = data[:2].astype(np.int64), receive_ns
            except _BadMessage as err:
                self._bad("wheels", err)
                continue
            stamps.append(stamp)
            receive.append(receive_ns)
            ticks.append((int(lr[0]), int(lr[1])))
        index = self._fallback_stamps(
            "wheels", np.array(stamps, np.int64), np.array(receive, np.int64)
        )
        t = np.array(ticks, dtype=np.int64).reshape(-1, 2)
        return WheelStream(index.stamps_ns, t[:, 0].copy(), t[:, 1].copy())
