"""A run as a rosbag2 folder with MCAP storage (``metadata.yaml`` + ``.mcap``), via ``rosbags``.

Foxglove opens the folder (or its ``.mcap``) directly; ``ros2 bag play`` replays it into RViz.
Every message carries the data's own stamp (header and bag record time alike). Topics follow
what a ROS 2 robot publishes (REP-105 frames, Nav2 / slam_toolbox names):

- ``/tf`` (tf2_msgs/TFMessage): ``map -> odom`` and ``odom -> base_link`` over time;
- ``/tf_static``: the mounts (``base_link -> camera_link -> camera_color_optical_frame``,
  ``base_link -> laser``), once, transient-local like robot_state_publisher's;
- ``/map`` (nav_msgs/OccupancyGrid: 0 free, 100 occupied, -1 unknown), transient-local like
  map_server's; ``/scan`` (sensor_msgs/LaserScan); ``/odom`` (nav_msgs/Odometry);
- a nav_msgs/Path of the trajectory, transient-local so it shows from the start of playback;
- ``/camera/color/image_raw/compressed`` (the recording's PNG/JPEG bytes as they are, no
  re-encoding), ``/camera/color/camera_info`` and the registered depth as 16UC1 millimetres on
  ``/camera/aligned_depth_to_color/image_raw`` (what RViz, Foxglove and our own reader show).

This module only serialises plain arrays (:class:`BagContent`); deciding what a run holds and
composing the transforms is the caller's job (``rgbdnav.commands.export``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sensors.types import CameraIntrinsics, LaserScan, SensorError

NS_PER_S = 1_000_000_000
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
MAP_TOPIC = "/map"
SCAN_TOPIC = "/scan"
ODOM_TOPIC = "/odom"
IMAGE_TOPIC = "/camera/color/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/color/camera_info"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"  # RealSense's name for registered depth
MM_PER_M = 1000.0  # [mm/m] 16UC1 depth is in millimetres (REP-118)


@dataclass(frozen=True, eq=False)
class PlanarTrack:
    """Poses of ``child`` in ``parent`` over time."""

    parent: str
    child: str
    stamps_ns: np.ndarray  # (N,) int64 [ns], increasing
    poses: np.ndarray  # (N, 3) float64 [m, m, rad]


@dataclass(frozen=True, eq=False)
class OdometryTrack:
    """nav_msgs/Odometry: the pose of ``child`` in ``parent`` and its velocity in ``child``."""

    track: PlanarTrack
    twist: np.ndarray  # (N, 2) float64 [m/s, rad/s] forward speed and yaw rate


@dataclass(frozen=True)
class StaticTransform:
    parent: str
    child: str
    xyz: tuple[float, float, float]  # [m]
    quat_xyzw: tuple[float, float, float, float]


@dataclass(frozen=True, eq=False)
class GridMessage:
    stamp_ns: int  # [ns]
    frame: str
    resolution: float  # [m/cell]
    origin_xy: tuple[float, float]  # [m] lower-left corner of cell (0, 0)
    values: np.ndarray  # (H, W) int8 nav_msgs values, row 0 = lowest y


@dataclass(frozen=True, eq=False)
class ImageStream:
    """Compressed colour images: the files' bytes go into the bag as they are."""

    stamps_ns: np.ndarray  # (N,) int64 [ns]
    files: Sequence[Path]
    frame: str
    intrinsics: CameraIntrinsics  # depth_scale: [counts/m] of the depth PNGs
    depth_stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    depth_files: Sequence[Path] = ()  # 16-bit PNGs registered to colour


@dataclass(frozen=True, eq=False)
class BagContent:
    transforms: Sequence[PlanarTrack]  # each published on /tf at its own stamps
    static: Sequence[StaticTransform] = ()
    static_stamp_ns: int = 0  # [ns] the run's first stamp
    grid: GridMessage | None = None
    scans: Sequence[LaserScan] = ()
    scan_frame: str = "laser"
    odometry: OdometryTrack | None = None
    paths: dict[str, PlanarTrack] = field(default_factory=dict)  # topic -> track
    images: ImageStream | None = None


def quaternion_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the fixed-axis roll-pitch-yaw rotation (tf2's ``setRPY``)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def _latched_qos() -> list[Any]:
    """Transient-local, reliable, keep-last 1: what /tf_static and /map publishers offer, so
    ``ros2 bag play`` republishes them to late subscribers (RViz opened after the start)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return [
        Qos(
            QosHistory.KEEP_LAST,
            1,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
            zero,
            zero,
            QosLiveliness.AUTOMATIC,
            zero,
            False,
        )
    ]


class _Messages:
    """Builders of the ROS 2 messages we write, from one typestore."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_HUMBLE)
        self.t = self.store.types

    def stamp(self, ns: int) -> Any:
        return self.t["builtin_interfaces/msg/Time"](
            sec=int(ns) // NS_PER_S, nanosec=int(ns) % NS_PER_S
        )

    def header(self, ns: int, frame: str) -> Any:
        return self.t["std_msgs/msg/Header"](stamp=self.stamp(ns), frame_id=frame)

    def pose(self, x: float, y: float, yaw: float) -> Any:
        t = self.t
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
            orientation=self.quaternion((0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))),
        )

    def quaternion(self, q: Sequence[float]) -> Any:
        return self.t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])

    def transform(
        self, ns: int, parent: str, child: str, xyz: Sequence[float], quat: Sequence[float]
    ) -> Any:
        t = self.t
        return t["geometry_msgs/msg/TransformStamped"](
            header=self.header(ns, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](
                    x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])
                ),
                rotation=self.quaternion([float(v) for v in quat]),
            ),
        )

    def planar_transform(self, ns: int, parent: str, child: str, p: np.ndarray) -> Any:
        yaw = float(p[2])
        quat = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        return self.transform(ns, parent, child, (p[0], p[1], 0.0), quat)

    def tf(self, transforms: list[Any]) -> Any:
        return self.t["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def grid(self, g: GridMessage) -> Any:
        t = self.t
        h, w = g.values.shape
        info = t["nav_msgs/msg/MapMetaData"](
            map_load_time=self.stamp(g.stamp_ns),
            resolution=float(g.resolution),
            width=w,
            height=h,
            origin=self.pose(g.origin_xy[0], g.origin_xy[1], 0.0),
        )
        data = np.ascontiguousarray(g.values, dtype=np.int8).reshape(-1)
        return t["nav_msgs/msg/OccupancyGrid"](
            header=self.header(g.stamp_ns, g.frame), info=info, data=data
        )

    def scan(self, s: LaserScan, frame: str) -> Any:
        n = len(s.ranges)
        return self.t["sensor_msgs/msg/LaserScan"](
            header=self.header(s.stamp_ns, frame),
            angle_min=float(s.angle_min),
            angle_max=float(s.angle_min + s.angle_increment * (n - 1)),
            angle_increment=float(s.angle_increment),
            time_increment=0.0,
            scan_time=0.0,
            range_min=float(s.range_min),
            range_max=float(s.range_max),
            ranges=np.asarray(s.ranges, dtype=np.float32),
            intensities=np.zeros(0, np.float32),
        )

    def odometry(self, ns: int, parent: str, child: str, p: np.ndarray, v: np.ndarray) -> Any:
        t = self.t
        vec = t["geometry_msgs/msg/Vector3"]
        zeros = np.zeros(36, dtype=np.float64)  # covariance not recorded by the run
        twist = t["geometry_msgs/msg/Twist"](
            linear=vec(x=float(v[0]), y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=float(v[1]))
        )
        return t["nav_msgs/msg/Odometry"](
            header=self.header(ns, parent),
            child_frame_id=child,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(*p), covariance=zeros),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=zeros.copy()),
        )

    def path(self, track: PlanarTrack) -> Any:
        stamped = self.t["geometry_msgs/msg/PoseStamped"]
        poses = [
            stamped(header=self.header(ns, track.parent), pose=self.pose(*p))
            for ns, p in zip(track.stamps_ns.tolist(), track.poses, strict=True)
        ]
        return self.t["nav_msgs/msg/Path"](
            header=self.header(int(track.stamps_ns[0]), track.parent), poses=poses
        )

    def compressed_image(self, ns: int, frame: str, file: Path) -> Any:
        fmt = "jpeg" if file.suffix.lower() in (".jpg", ".jpeg") else "png"
        try:
            data = np.frombuffer(file.read_bytes(), dtype=np.uint8)
        except OSError as err:
            raise SensorError(f"{file}: cannot read image: {err.strerror or err}") from err
        return self.t["sensor_msgs/msg/CompressedImage"](
            header=self.header(ns, frame), format=fmt, data=data
        )

    def depth_image(self, ns: int, frame: str, file: Path, k: CameraIntrinsics) -> Any:
        from sensors.images import read_image

        counts = read_image(file, (k.width, k.height), depth=True)
        mm = np.rint(counts * (MM_PER_M / k.depth_scale)).clip(0, np.iinfo(np.uint16).max)
        return self.t["sensor_msgs/msg/Image"](
            header=self.header(ns, frame),
            height=k.height,
            width=k.width,
            encoding="16UC1",
            is_bigendian=0,
            step=2 * k.width,
            data=mm.astype("<u2").reshape(-1).view(np.uint8),
        )

    def camera_info(self, ns: int, frame: str, k: CameraIntrinsics) -> Any:
        t = self.t
        roi = t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        kk = np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], dtype=np.float64)
        pp = np.array([k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0], dtype=np.float64)
        return t["sensor_msgs/msg/CameraInfo"](
            header=self.header(ns, frame),
            height=k.height,
            width=k.width,
            distortion_model="plumb_bob",
            d=np.zeros(5, dtype=np.float64),
            k=kk,
            r=np.eye(3, dtype=np.float64).reshape(-1),
            p=pp,
            binning_x=0,
            binning_y=0,
            roi=roi,
        )


def _records(content: BagContent, m: _Messages) -> dict[tuple[str, str], list[tuple[int, Any]]]:
    """(topic, msgtype) -> [(stamp_ns, message)] in stamp order."""
    out: dict[tuple[str, str], list[tuple[int, Any]]] = {}
    tf_by_stamp: dict[int, list[Any]] = {}
    for tr in content.transforms:
        for ns, p in zip(tr.stamps_ns.tolist(), tr.poses, strict=True):
            tf_by_stamp.setdefault(ns, []).append(m.planar_transform(ns, tr.parent, tr.child, p))
    if tf_by_stamp:
        tf_type = "tf2_msgs/msg/TFMessage"
        out[(TF_TOPIC, tf_type)] = [(ns, m.tf(tf_by_stamp[ns])) for ns in sorted(tf_by_stamp)]
    if content.static:
        ns = content.static_stamp_ns
        msg = m.tf([m.transform(ns, s.parent, s.child, s.xyz, s.quat_xyzw) for s in content.static])
        out[(TF_STATIC_TOPIC, "tf2_msgs/msg/TFMessage")] = [(ns, msg)]
    if content.grid is not None:
        g = content.grid
        out[(MAP_TOPIC, "nav_msgs/msg/OccupancyGrid")] = [(g.stamp_ns, m.grid(g))]
    if content.scans:
        out[(SCAN_TOPIC, "sensor_msgs/msg/LaserScan")] = [
            (s.stamp_ns, m.scan(s, content.scan_frame)) for s in content.scans
        ]
    if content.odometry is not None:
        tr, tw = content.odometry.track, content.odometry.twist
        out[(ODOM_TOPIC, "nav_msgs/msg/Odometry")] = [
            (ns, m.odometry(ns, tr.parent, tr.child, p, v))
            for ns, p, v in zip(tr.stamps_ns.tolist(), tr.poses, tw, strict=True)
        ]
    for topic, track in content.paths.items():
        out[(topic, "nav_msgs/msg/Path")] = [(int(track.stamps_ns[0]), m.path(track))]
    if content.images is not None:
        im = content.images
        out[(IMAGE_TOPIC, "sensor_msgs/msg/CompressedImage")] = [
            (ns, m.compressed_image(ns, im.frame, f))
            for ns, f in zip(im.stamps_ns.tolist(), im.files, strict=True)
        ]
        out[(CAMERA_INFO_TOPIC, "sensor_msgs/msg/CameraInfo")] = [
            (ns, m.camera_info(ns, im.frame, im.intrinsics)) for ns in im.stamps_ns.tolist()
        ]
        if len(im.depth_files):
            out[(DEPTH_TOPIC, "sensor_msgs/msg/Image")] = [
                (ns, m.depth_image(ns, im.frame, f, im.intrinsics))
                for ns, f in zip(im.depth_stamps_ns.tolist(), im.depth_files, strict=True)
            ]
    return out


LATCHED_TOPICS = (TF_STATIC_TOPIC, MAP_TOPIC)


def write_mcap_bag(content: BagContent, path: Path) -> dict[str, int]:
    """Write ``content`` as a new rosbag2 folder ``path`` (MCAP storage); message count per
    topic. ``path`` must not exist (rosbags' Writer only creates): write into a staging folder
    and rename it into place (:func:`sensors.atomic.commit_staging_dir`)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.errors import WriterError

    m = _Messages()
    records = _records(content, m)
    counts: dict[str, int] = {}
    try:
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            for (topic, msgtype), msgs in records.items():
                latched = topic in LATCHED_TOPICS or msgtype == "nav_msgs/msg/Path"
                conn = writer.add_connection(
                    topic,
                    msgtype,
                    typestore=m.store,
                    offered_qos_profiles=_latched_qos() if latched else (),
                )
                for ns, msg in msgs:
                    writer.write(conn, ns, m.store.serialize_cdr(msg, msgtype))
                counts[topic] = len(msgs)
    except WriterError as err:
        raise SensorError(f"{path}: cannot write the bag: {err}") from err
    return counts


__all__ = [
    "BagContent",
    "GridMessage",
    "ImageStream",
    "OdometryTrack",
    "PlanarTrack",
    "StaticTransform",
    "quaternion_rpy",
    "write_mcap_bag",
]
