"""Bags with the topic sets real camera drivers publish, and their /tf_static, written with
``rosbags`` into tmp_path: the registered depth, its colour image and camera_info are found
without --set; ambiguity and missing topics are one error line; the camera mount comes from
/tf_static unless the config sets it.

Topic names are the drivers' own (realsense2_camera 4.x, Azure_Kinect_ROS_Driver, iai_kinect2
kinect2_bridge, openni_launch with depth registration, OrbbecSDK_ROS2, zed-ros2-wrapper).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.config import camera_mount, load_config, source_options
from sensors.source import open_source
from sensors.types import SensorError
from tests.bagtools import MS, T0, Bag, frame_pixels, write_bag

FRAMES = 3
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMAGE, INFO, IMU, ODOM = (
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CameraInfo",
    "sensor_msgs/msg/Imu",
    "nav_msgs/msg/Odometry",
)
# driver -> (bag kind, [(topic, content)]), content: rgb | depth (registered) | raw_depth
# (unregistered) | ir | info | imu | odom. The registered depth is the first depth listed.
DRIVERS: dict[str, tuple[str, list[tuple[str, str]]]] = {
    "realsense": (
        "mcap",
        [
            ("/camera/camera/color/image_raw", "rgb"),
            ("/camera/camera/color/camera_info", "info"),
            ("/camera/camera/aligned_depth_to_color/image_raw", "depth"),
            ("/camera/camera/aligned_depth_to_color/camera_info", "info"),
            ("/camera/camera/depth/image_rect_raw", "raw_depth"),
            ("/camera/camera/depth/camera_info", "info"),
            ("/camera/camera/infra1/image_rect_raw", "ir"),
            ("/camera/camera/infra1/camera_info", "info"),
            ("/camera/camera/infra2/image_rect_raw", "ir"),
            ("/camera/camera/infra2/camera_info", "info"),
            ("/camera/camera/imu", "imu"),
            ("/camera/camera/gyro/sample", "imu"),
            ("/camera/camera/accel/sample", "imu"),
        ],
    ),
    "azure_kinect": (
        "bag",
        [
            ("/rgb/image_raw", "rgb"),
            ("/rgb/camera_info", "info"),
            ("/depth_to_rgb/image_raw", "depth"),
            ("/depth_to_rgb/camera_info", "info"),
            ("/depth/image_raw", "raw_depth"),
            ("/depth/camera_info", "info"),
            ("/rgb_to_depth/image_raw", "rgb"),
            ("/rgb_to_depth/camera_info", "info"),
            ("/ir/image_raw", "ir"),
            ("/ir/camera_info", "info"),
            ("/imu", "imu"),
        ],
    ),
    "kinect2": (
        "bag",
        [
            ("/kinect2/qhd/image_color_rect", "rgb"),
            ("/kinect2/qhd/image_depth_rect", "depth"),
            ("/kinect2/qhd/camera_info", "info"),
            ("/kinect2/hd/image_color", "rgb"),
            ("/kinect2/hd/image_color_rect", "rgb"),
            ("/kinect2/hd/image_depth_rect", "raw_depth"),
            ("/kinect2/hd/camera_info", "info"),
            ("/kinect2/sd/image_color_rect", "rgb"),
            ("/kinect2/sd/image_depth", "raw_depth"),
            ("/kinect2/sd/image_depth_rect", "raw_depth"),
            ("/kinect2/sd/image_ir", "ir"),
            ("/kinect2/sd/camera_info", "info"),
        ],
    ),
    "openni": (
        "bag",
        [
            ("/camera/rgb/image_rect_color", "rgb"),
            ("/camera/depth_registered/image_raw", "depth"),
            ("/camera/rgb/camera_info", "info"),
            ("/camera/rgb/image_raw", "rgb"),
            ("/camera/rgb/image_color", "rgb"),
            ("/camera/depth/image_raw", "raw_depth"),
            ("/camera/depth/image", "raw_depth"),  # our default depth topic: unregistered here
            ("/camera/depth/camera_info", "info"),
            ("/camera/depth_registered/camera_info", "info"),
            ("/camera/ir/image_raw", "ir"),
            ("/camera/ir/camera_info", "info"),
        ],
    ),
    "orbbec": (
        "db3",
        [
            ("/camera/color/image_raw", "rgb"),
            ("/camera/depth/image_raw", "depth"),
            ("/camera/color/camera_info", "info"),
            ("/camera/depth/camera_info", "info"),
            ("/camera/ir/image_raw", "ir"),
            ("/camera/ir/camera_info", "info"),
            ("/camera/gyro_accel/sample", "imu"),
        ],
    ),
    "zed": (
        "mcap",
        [
            ("/zed/zed_node/rgb/image_rect_color", "rgb"),
            ("/zed/zed_node/depth/depth_registered", "depth"),
            ("/zed/zed_node/rgb/camera_info", "info"),
            ("/zed/zed_node/depth/camera_info", "info"),
            ("/zed/zed_node/left/image_rect_color", "rgb"),
            ("/zed/zed_node/left/camera_info", "info"),
            ("/zed/zed_node/right/image_rect_color", "rgb"),
            ("/zed/zed_node/right/camera_info", "info"),
            ("/zed/zed_node/imu/data", "imu"),
            ("/zed/zed_node/odom", "odom"),
        ],
    ),
}
EXPECTED = {  # driver -> (rgb, depth, camera_info) the resolver must pick
    "realsense": (
        "/camera/camera/color/image_raw",
        "/camera/camera/aligned_depth_to_color/image_raw",
        "/camera/camera/color/camera_info",
    ),
    "azure_kinect": ("/rgb/image_raw", "/depth_to_rgb/image_raw", "/rgb/camera_info"),
    "kinect2": (
        "/kinect2/qhd/image_color_rect",
        "/kinect2/qhd/image_depth_rect",
        "/kinect2/qhd/camera_info",
    ),
    "openni": (
        "/camera/rgb/image_rect_color",
        "/camera/depth_registered/image_raw",
        "/camera/rgb/camera_info",
    ),
    "orbbec": ("/camera/color/image_raw", "/camera/depth/image_raw", "/camera/color/camera_info"),
    "zed": (
        "/zed/zed_node/rgb/image_rect_color",
        "/zed/zed_node/depth/depth_registered",
        "/zed/zed_node/rgb/camera_info",
    ),
}
# base_link -> camera_link (pitched down 0.2 rad) -> camera_color_frame -> optical frame, as
# realsense2_camera (camera_link -> *_frame -> *_optical_frame) plus a robot's mount.
MOUNT = {"x": 0.12, "y": 0.0, "z": 0.31, "pitch": 0.2}
COLOR_Y = 0.015  # [m] camera_link -> camera_color_frame
OPTICAL = "camera_color_optical_frame"


def _with_frame(msg: Any, bag: Bag, stamp_ns: int, frame: str) -> Any:
    return dataclasses.replace(msg, header=bag.header(stamp_ns, frame))


def _transform(bag: Bag, parent: str, child: str, xyz: tuple, quat_xyzw: tuple) -> Any:
    T = bag.types
    return T["geometry_msgs/msg/TransformStamped"](
        header=bag.header(T0, parent),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](
                x=quat_xyzw[0], y=quat_xyzw[1], z=quat_xyzw[2], w=quat_xyzw[3]
            ),
        ),
    )


def write_tf_static(bag: Bag) -> None:
    pitch = Rotation.from_euler("y", MOUNT["pitch"]).as_quat()  # x y z w
    optical = Rotation.from_euler("xyz", [-math.pi / 2, 0.0, -math.pi / 2]).as_quat()
    transforms = [
        _transform(bag, "base_footprint", "base_link", (0.0, 0.0, 0.05), (0, 0, 0, 1)),
        _transform(
            bag, "base_link", "camera_link", (MOUNT["x"], MOUNT["y"], MOUNT["z"] - 0.05), pitch
        ),
        _transform(bag, "camera_link", "camera_color_frame", (0.0, COLOR_Y, 0.0), (0, 0, 0, 1)),
        _transform(bag, "camera_color_frame", OPTICAL, (0.0, 0.0, 0.0), tuple(optical)),
    ]
    if "tf2_msgs/msg/TFMessage" not in bag.types:  # rosbags' ROS 1 store lacks tf2_msgs
        bag.typestore.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE)
        )
    msg = bag.types[TF_MESSAGE](transforms=transforms)
    bag.write("/tf_static", TF_MESSAGE, T0, msg)


def write_driver_bag(
    path: Path, driver: str, tf_static: bool = False, odom: bool = False, prefix: str = ""
) -> None:
    kind, topics = DRIVERS[driver]
    with write_bag(path, kind) as bag:
        if tf_static:
            write_tf_static(bag)
        for k in range(FRAMES):
            t = T0 + k * 100 * MS
            rgb, depth_mm = frame_pixels(k)
            for topic, content in topics:
                topic = prefix + topic
                if content == "rgb":
                    bag.write(topic, IMAGE, t + MS, bag.image(t, "rgb8", rgb))
                elif content in ("depth", "raw_depth"):
                    mm = depth_mm if content == "depth" else depth_mm // 2
                    msg = _with_frame(bag.image(t, "16UC1", mm), bag, t, OPTICAL)
                    bag.write(topic, IMAGE, t + 2 * MS, msg)
                elif content == "ir":
                    bag.write(topic, IMAGE, t + MS, bag.image(t, "mono8", rgb[..., :1].copy()))
                elif content == "info":
                    bag.write(topic, INFO, t, bag.camera_info(t))
                elif content == "imu":
                    bag.write(topic, IMU, t, bag.imu(t, 0.5))
                elif content == "odom":
                    bag.write(topic, ODOM, t, bag.odometry(t, 9.0, 9.0, 0.0))
            if odom:  # the robot's wheel odometry
                bag.write("/odom", ODOM, t + 3 * MS, bag.odometry(t, 0.1 * k, 0.0, 0.0))


def bag_file(tmp_path: Path, driver: str) -> Path:
    kind = DRIVERS[driver][0]
    return tmp_path / (f"{driver}.bag" if kind == "bag" else driver)


@pytest.mark.parametrize("driver", list(DRIVERS))
def test_each_drivers_registered_depth_colour_and_info_are_found(tmp_path, driver):
    path = bag_file(tmp_path, driver)
    write_driver_bag(path, driver)
    with open_source(path, source_options(load_config())) as src:
        picked = tuple(src.choices[r].topic for r in ("rgb", "depth", "camera_info"))
        assert picked == EXPECTED[driver]
        # The camera's own gyro / visual odometry is not taken for the robot's.
        assert src.choices["imu"].topic is None and src.choices["odom"].topic is None
        frames = list(src.frames())
    assert len(frames) == FRAMES
    _, depth_mm = frame_pixels(0)
    # The registered depth (not the unregistered one at half the range) was read.
    np.testing.assert_allclose(frames[0].depth_m[1:, 1:], depth_mm[1:, 1:] / 1000.0, rtol=1e-6)


def test_a_depth_topic_flag_and_the_cameras_imu_can_still_be_chosen(tmp_path):
    path = bag_file(tmp_path, "realsense")
    write_driver_bag(path, "realsense")
    topic = "/camera/camera/depth/image_rect_raw"
    cfg = load_config(overrides=[f"topics.depth={topic}", "topics.imu=/camera/camera/imu"])
    with open_source(path, source_options(cfg)) as src:
        assert src.choices["depth"].topic == topic
        assert src.choices["imu"].topic == "/camera/camera/imu"
        assert src.choices["rgb"].topic is not None


def test_two_cameras_are_one_error_listing_both(tmp_path):
    path = tmp_path / "two"
    with write_bag(path, "mcap") as bag:
        for ns in ("/front/camera/", "/rear/camera/"):
            rgb, depth_mm = frame_pixels(0)
            bag.write(ns + "color/image_raw", IMAGE, T0, bag.image(T0, "rgb8", rgb))
            bag.write(
                ns + "aligned_depth_to_color/image_raw", IMAGE, T0, bag.image(T0, "16UC1", depth_mm)
            )
    with pytest.raises(SensorError) as err:
        open_source(path, source_options(load_config()))
    text = str(err.value)
    assert "/front/camera/aligned_depth_to_color/image_raw" in text
    assert "/rear/camera/aligned_depth_to_color/image_raw" in text
    assert "--rgb-topic" in text and "\n" not in text


def run_cli(*args: str) -> Any:
    return CliRunner().invoke(app, [str(a) for a in args])


def test_cli_ambiguity_and_a_missing_topic_are_one_error_line_and_no_run_folder(tmp_path):
    path = tmp_path / "two"
    with write_bag(path, "mcap") as bag:
        for topic in ("/imu_a", "/imu_b"):
            bag.write(topic, IMU, T0, bag.imu(T0, 0.1))
        bag.write("/odom", ODOM, T0, bag.odometry(T0, 0.0, 0.0, 0.0))
    for verb in ("odometry", "map"):
        out = tmp_path / f"out_{verb}"
        result = run_cli(verb, path, "-o", out, "-q")
        assert result.exit_code == 1, result.output
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ")
        assert "imu is ambiguous: /imu_a, /imu_b; choose one with --imu-topic" in lines[0]
        assert result.exception is None or isinstance(result.exception, SystemExit)
        assert not out.exists()
    result = run_cli("odometry", path, "-o", tmp_path / "o", "-q", "--imu-topic", "/imu_c")
    assert result.exit_code == 1
    assert "imu topic /imu_c is not in the bag (sensor_msgs/Imu topics: /imu_a, /imu_b)" in (
        result.output
    )


def test_a_failed_run_still_leaves_a_summary_saying_why(tmp_path):
    path = tmp_path / "imu_only"
    with write_bag(path, "mcap") as bag:
        bag.write("/imu/data", IMU, T0, bag.imu(T0, 0.1))
    out = tmp_path / "run"
    result = run_cli("odometry", path, "-o", out, "-q")
    assert result.exit_code == 1 and result.output.startswith("error: ")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and "no odometry input" in summary["error"]


def test_info_names_the_driver_topics_and_the_flags_choose_others(tmp_path):
    path = bag_file(tmp_path, "zed")
    write_driver_bag(path, "zed")
    result = run_cli("info", path)
    assert result.exit_code == 0, result.output
    assert "depth /zed/zed_node/depth/depth_registered" in result.output
    assert "ZED driver topics" in result.output
    result = run_cli("info", path, "--rgb-topic", "/zed/zed_node/left/image_rect_color")
    assert "rgb /zed/zed_node/left/image_rect_color" in result.output


# --- /tf_static --------------------------------------------------------------------------------


def expected_mount() -> dict[str, float]:
    """The mount the tf tree was built from (its quaternions made by scipy, not by us):
    base_footprint is 5 cm below base_link, and the colour frame's 1.5 cm to the left is not
    changed by the pitch (a rotation about y)."""
    return {
        "camera_x": MOUNT["x"],
        "camera_y": COLOR_Y,
        "camera_height": MOUNT["z"],
        "camera_pitch": MOUNT["pitch"],
        "camera_roll": 0.0,
    }


@pytest.mark.parametrize("driver", ["realsense", "openni"])  # rosbag2 mcap, rosbag1
def test_the_camera_mount_is_composed_from_tf_static(tmp_path, driver):
    path = bag_file(tmp_path, driver)
    write_driver_bag(path, driver, tf_static=True)
    with open_source(path, source_options(load_config())) as src:
        found = src.static_extrinsics()
    assert found is not None
    mount, chain = found
    assert chain == f"base_footprint -> {OPTICAL}"
    for key, value in expected_mount().items():
        assert mount[key] == pytest.approx(value, abs=1e-9), key


def test_a_yawed_camera_in_tf_static_is_refused(tmp_path):
    path = tmp_path / "yawed"
    with write_bag(path, "mcap") as bag:
        yaw = tuple(Rotation.from_euler("z", 0.5).as_quat())
        tf = _transform(bag, "base_link", "cam", (0.0, 0.0, 0.3), yaw)
        bag.write(
            "/tf_static",
            "tf2_msgs/msg/TFMessage",
            T0,
            bag.types["tf2_msgs/msg/TFMessage"](transforms=[tf]),
        )  # noqa: E501
        rgb, depth_mm = frame_pixels(0)
        bag.write("/camera/rgb/image_color", IMAGE, T0, bag.image(T0, "rgb8", rgb))
        depth = _with_frame(bag.image(T0, "16UC1", depth_mm), bag, T0, "cam")
        bag.write("/camera/depth/image", IMAGE, T0, depth)
    with open_source(path, source_options(load_config())) as src:
        with pytest.raises(SensorError, match="turned 28.6 deg"):
            src.static_extrinsics()
        with pytest.raises(SensorError, match="turned 28.6 deg"):
            camera_mount(src, [], [])
        # ... unless the config says where the camera is: then it wins, and says why.
        base, entry = camera_mount(src, [], ["robot.camera_height=0.4"])
    assert entry["source"] == "config" and "turned 28.6 deg" in entry["note"]
    assert base == {}


def test_odometry_summary_says_tf_static_won_unless_the_config_sets_the_mount(tmp_path):
    path = bag_file(tmp_path, "realsense")
    write_driver_bag(path, "realsense", tf_static=True, odom=True)
    out = tmp_path / "run"
    result = run_cli("odometry", path, "-o", out, "-q", "--no-vo")
    assert result.exit_code == 0, result.output
    ext = json.loads((out / "summary.json").read_text())["extrinsics"]
    assert ext["source"] == "tf_static" and ext["chain"] == f"base_footprint -> {OPTICAL}"
    assert ext["camera_pitch"] == pytest.approx(MOUNT["pitch"], abs=1e-4)
    config = (out / "config.yaml").read_text()
    assert f"camera_height: {MOUNT['z']}" in config
    out2 = tmp_path / "run2"
    result = run_cli(
        "odometry", path, "-o", out2, "-q", "--no-vo", "--set", "robot.camera_height=0.5"
    )
    assert result.exit_code == 0, result.output
    ext = json.loads((out2 / "summary.json").read_text())["extrinsics"]
    assert ext["source"] == "config" and "robot.camera_height" in ext["note"]
    assert "camera_height: 0.5" in (out2 / "config.yaml").read_text()
    result = run_cli("info", path)
    assert "extrinsics  from tf_static (base_footprint -> camera_color_optical_frame)" in (
        result.output
    )


def test_a_failure_writes_nothing_into_a_folder_that_is_not_a_started_run(tmp_path):
    path = tmp_path / "imu_only"
    with write_bag(path, "mcap") as bag:
        bag.write("/imu_a", IMU, T0, bag.imu(T0, 0.1))
        bag.write("/imu_b", IMU, T0, bag.imu(T0, 0.1))
    out = tmp_path / "home"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    result = run_cli("odometry", path, "-o", out, "-q")
    assert result.exit_code == 1 and "imu is ambiguous" in result.output
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
