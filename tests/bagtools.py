"""Writing real ROS bags in tests: rosbag1 (.bag) and rosbag2 (sqlite3 or mcap) with `rosbags`.

One writer for every test that needs a bag (sources, ROS drivers, GPS, ROS params, odometry);
the default camera is a tiny 8x6 pinhole so frames stay small.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from sensors.types import CameraIntrinsics

MS = 1_000_000  # [ns]
T0 = 1_700_000_000 * 1_000_000_000  # [ns] an epoch-like start
H, W = 6, 8  # [px]
K = (52.5, 0.0, 3.5, 0.0, 50.0, 2.5, 0.0, 0.0, 1.0)  # row-major pinhole matrix
INTR = CameraIntrinsics(W, H, 52.5, 50.0, 3.5, 2.5)
KINDS = ("bag", "db3", "mcap")


@dataclass
class Bag:
    """A rosbag being written: rosbag1 (.bag) or rosbag2 (sqlite3 or mcap folder)."""

    kind: str
    typestore: Any
    writer: Any
    connections: dict[str, Any] = field(default_factory=dict)

    @property
    def types(self) -> Any:
        return self.typestore.types

    def write(self, topic: str, msgtype: str, receive_ns: int, msg: Any) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore
            )
        if self.kind == "bag":
            raw = self.typestore.serialize_ros1(msg, msgtype)
        else:
            raw = self.typestore.serialize_cdr(msg, msgtype)
        self.writer.write(self.connections[topic], receive_ns, raw)

    def header(self, stamp_ns: int, frame_id: str = "camera_rgb_optical_frame") -> Any:
        stamp = self.types["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
        )
        if self.kind == "bag":
            return self.types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def image(self, stamp_ns: int, encoding: str, pixels: np.ndarray) -> Any:
        h, w = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        return self.types["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=data.size // h,
            data=data,
        )

    def compressed(self, stamp_ns: int, fmt: str, data: bytes) -> Any:
        return self.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp_ns), format=fmt, data=np.frombuffer(data, dtype=np.uint8)
        )

    def camera_info(self, stamp_ns: int, k: CameraIntrinsics = INTR) -> Any:
        T = self.types
        upper = self.kind == "bag"  # ROS 1 names the matrices D, K, R, P
        mats = {
            "D": np.zeros(5),
            "K": np.array([k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]),
            "R": np.eye(3).reshape(-1),
            "P": np.zeros(12),
        }
        return T["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns),
            height=k.height,
            width=k.width,
            distortion_model="plumb_bob",
            **{(k if upper else k.lower()): v for k, v in mats.items()},
            binning_x=0,
            binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
            ),
        )

    def odometry(
        self,
        stamp_ns: int,
        x: float,
        y: float,
        yaw: float,
        v: float = 0.1,
        w: float = 0.2,
        pose_cov: np.ndarray | None = None,
        twist_cov: np.ndarray | None = None,
    ) -> Any:
        """nav_msgs/Odometry as a base driver publishes it: pose and twist with covariance
        (row-major 6x6; zeros unless given)."""
        T = self.types
        vec = T["geometry_msgs/msg/Vector3"]
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        )
        twist = T["geometry_msgs/msg/Twist"](
            linear=vec(x=v, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=w)
        )
        pose_cov = np.zeros(36) if pose_cov is None else pose_cov
        twist_cov = np.zeros(36) if twist_cov is None else twist_cov
        return T["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, "odom"),
            child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=pose_cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=twist_cov),
        )

    def imu(self, stamp_ns: int, gyro_z: float) -> Any:
        T = self.types
        vec = T["geometry_msgs/msg/Vector3"]
        return T["sensor_msgs/msg/Imu"](
            header=self.header(stamp_ns, "imu"),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9),
            angular_velocity=vec(x=0.0, y=0.0, z=gyro_z),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.zeros(9),
        )

    def wheels(self, left: int, right: int) -> Any:
        T = self.types
        layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        return T["std_msgs/msg/Int32MultiArray"](
            layout=layout, data=np.array([left, right], dtype=np.int32)
        )

    def joint_state(self, stamp_ns: int, names: list[str], angles: list[float]) -> Any:
        return self.types["sensor_msgs/msg/JointState"](
            header=self.header(stamp_ns, ""),
            name=names,
            position=np.array(angles, dtype=np.float64),
            velocity=np.zeros(len(angles)),
            effort=np.zeros(len(angles)),
        )


@contextmanager
def write_bag(path: Path, kind: str) -> Iterator[Bag]:
    writer: Any
    if kind == "bag":
        store, writer = Stores.ROS1_NOETIC, Writer1(path)
    else:
        plugin = StoragePlugin.SQLITE3 if kind == "db3" else StoragePlugin.MCAP
        store, writer = Stores.ROS2_HUMBLE, Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        yield Bag(kind, get_typestore(store), writer)


def bag_path(tmp_path: Path, kind: str) -> Path:
    return tmp_path / ("run.bag" if kind == "bag" else f"run_{kind}")


def frame_pixels(k: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(k)
    rgb = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    depth_mm = rng.integers(500, 4500, size=(H, W), dtype=np.uint16)
    depth_mm[0, 0] = 0  # invalid
    return rgb, depth_mm
