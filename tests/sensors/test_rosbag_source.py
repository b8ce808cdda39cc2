"""RosbagSource: real rosbag1 / rosbag2 (sqlite3, mcap) files written into tmp_path, read back."""

from __future__ import annotations

import logging
import math
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sensors.config import CameraConfig
from sensors.rosbag_source import (
    RosbagSource,
    RosbagTopics,
    depth_from_compressed,
    fix_camera_info_stamps,
    header_stamp_ns_from_raw,
    looks_like_rosbag,
    pair_rgb_depth,
    resolve_topics,
    rgb_from_image,
    ticks_from_wheel_angles,
    wheel_joint_indices,
)
from sensors.source import Source, open_source
from sensors.types import SensorError
from tests.bagtools import INTR, KINDS, MS, T0, H, W, bag_path, frame_pixels, write_bag

REPO = Path(__file__).resolve().parents[2]
TOPICS = RosbagTopics()


def write_scene(path: Path, kind: str, frames: int = 4) -> None:
    """rgb (rgb8) + depth (16UC1) at 10 Hz, CameraInfo, Odometry, Imu and wheels (Int32)."""
    with write_bag(path, kind) as bag:
        for k in range(frames):
            t = T0 + k * 100 * MS
            rgb, depth_mm = frame_pixels(k)
            bag.write(
                TOPICS.camera_info, "sensor_msgs/msg/CameraInfo", t + 1 * MS, bag.camera_info(t)
            )
            bag.write(TOPICS.rgb, "sensor_msgs/msg/Image", t + 2 * MS, bag.image(t, "rgb8", rgb))
            bag.write(
                TOPICS.depth,
                "sensor_msgs/msg/Image",
                t + 3 * MS,
                bag.image(t + 5 * MS, "16UC1", depth_mm),
            )
            bag.write(
                TOPICS.odom,
                "nav_msgs/msg/Odometry",
                t + 4 * MS,
                bag.odometry(t, 0.1 * k, -0.05 * k, 0.3 * k),
            )
            bag.write(TOPICS.imu, "sensor_msgs/msg/Imu", t + 5 * MS, bag.imu(t, 0.25 * k))
            bag.write(
                TOPICS.wheels,
                "std_msgs/msg/Int32MultiArray",
                t + 6 * MS,
                bag.wheels(10 * k, -12 * k),
            )


# --- round trips -------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_a_bag_round_trips_frames_intrinsics_odometry_imu_and_wheels(tmp_path, kind):
    path = bag_path(tmp_path, kind)
    write_scene(path, kind)

    src = open_source(path)
    try:
        assert isinstance(src, RosbagSource) and isinstance(src, Source)
        assert src.intrinsics() == INTR
        frames = list(src.frames())
        assert len(frames) == 4 and src.skipped == {}
        for k, frame in enumerate(frames):
            rgb, depth_mm = frame_pixels(k)
            assert frame.stamp_ns == T0 + k * 100 * MS
            np.testing.assert_array_equal(frame.rgb, rgb)
            assert frame.depth_m.dtype == np.float32
            np.testing.assert_allclose(frame.depth_m, depth_mm / 1000.0, atol=1e-3)
            assert frame.depth_m[0, 0] == 0.0
            assert frame.intrinsics == INTR

        odom = src.odometry()
        assert odom is not None
        np.testing.assert_array_equal(odom.stamps_ns, T0 + np.arange(4) * 100 * MS)
        np.testing.assert_allclose(odom.x, 0.1 * np.arange(4), atol=1e-12)
        np.testing.assert_allclose(odom.y, -0.05 * np.arange(4), atol=1e-12)
        np.testing.assert_allclose(odom.yaw, 0.3 * np.arange(4), atol=1e-9)

        imu = src.imu()
        assert imu is not None
        np.testing.assert_allclose(imu.gyro_z, 0.25 * np.arange(4))

        wheels = src.wheels()
        assert wheels is not None
        np.testing.assert_array_equal(wheels.left, 10 * np.arange(4))
        np.testing.assert_array_equal(wheels.right, -12 * np.arange(4))
        # Int32MultiArray has no header: its stamps are the bag receive times.
        np.testing.assert_array_equal(wheels.stamps_ns, T0 + np.arange(4) * 100 * MS + 6 * MS)

        stamps = src.stream_stamps()
        assert set(stamps) == {"rgb", "depth", "camera_info", "odometry", "imu", "wheels"}
        np.testing.assert_array_equal(stamps["depth"], T0 + np.arange(4) * 100 * MS + 5 * MS)
        assert list(src.scans()) == [] and src.groundtruth() is None
        assert f"rgb {TOPICS.rgb} (sensor_msgs/Image, 4 messages)" in src.describe()
    finally:
        src.close()


@pytest.mark.parametrize("kind", ["db3", "mcap"])
def test_a_storage_file_opens_its_folder_or_alone(tmp_path, kind):
    folder = bag_path(tmp_path, kind)
    write_scene(folder, kind, frames=2)
    (storage,) = folder.glob(f"*.{kind}")
    with RosbagSource.open(storage) as src:
        assert src.path == str(storage) and len(list(src.frames())) == 2
    alone = tmp_path / f"alone.{kind}"
    shutil.copy(storage, alone)  # no metadata.yaml beside it
    with RosbagSource.open(alone) as src:
        assert len(list(src.frames())) == 2 and src.wheels() is not None


def test_bgr8_colour_and_32fc1_depth_are_read_exactly(tmp_path):
    path = tmp_path / "bgr.bag"
    rgb, depth_mm = frame_pixels(3)
    depth_m = (depth_mm / 1000.0).astype(np.float32)
    depth_m[1, 1] = np.inf  # not a depth: becomes NaN (invalid)
    with write_bag(path, "bag") as bag:
        bag.write(TOPICS.rgb, "sensor_msgs/msg/Image", T0, bag.image(T0, "bgr8", rgb[..., ::-1]))
        bag.write(TOPICS.depth, "sensor_msgs/msg/Image", T0, bag.image(T0, "32FC1", depth_m))
        bag.write(TOPICS.camera_info, "sensor_msgs/msg/CameraInfo", T0, bag.camera_info(T0))
    with RosbagSource.open(path) as src:
        (frame,) = src.frames()
    np.testing.assert_array_equal(frame.rgb, rgb)
    assert np.isnan(frame.depth_m[1, 1])
    depth_m[1, 1] = np.nan
    np.testing.assert_array_equal(frame.depth_m, depth_m)


def compressed_depth(depth_mm: np.ndarray) -> bytes:
    ok, png = cv2.imencode(".png", depth_mm)
    assert ok
    return struct.pack("<iff", 0, 0.0, 0.0) + png.tobytes()


def test_compressed_png_colour_and_compressed_depth_are_decoded(tmp_path):
    path = tmp_path / "compressed"
    rgb, depth_mm = frame_pixels(1)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    with write_bag(path, "mcap") as bag:
        bag.write(
            "/camera/rgb/image_color/compressed",
            "sensor_msgs/msg/CompressedImage",
            T0,
            bag.compressed(T0, "rgb8; png compressed bgr8", png.tobytes()),
        )
        bag.write(
            "/camera/depth/image/compressedDepth",
            "sensor_msgs/msg/CompressedImage",
            T0,
            bag.compressed(T0, "16UC1; compressedDepth png", compressed_depth(depth_mm)),
        )

    camera = CameraConfig(width=W, height=H, fx=INTR.fx, fy=INTR.fy, cx=INTR.cx, cy=INTR.cy)
    with RosbagSource.open(path, camera=camera) as src:
        (frame,) = src.frames()
        assert "auto-detected" in src.describe()
        assert "intrinsics from config: fx=52.5 fy=50 cx=3.5 cy=2.5" in src.describe()
    assert frame.intrinsics == INTR
    np.testing.assert_array_equal(frame.rgb, rgb)
    np.testing.assert_allclose(frame.depth_m, depth_mm / 1000.0, atol=1e-6)


def test_32fc1_compressed_depth_inverts_the_quantisation():
    quant_a, quant_b = 100.0, 10.0
    inv = np.array([[0, 60, 110]], dtype=np.uint16)  # z = A / (v - B); 0 = invalid
    ok, png = cv2.imencode(".png", inv)
    assert ok
    data = struct.pack("<iff", 0, quant_a, quant_b) + png.tobytes()
    z = depth_from_compressed("32FC1; compressedDepth png", data)
    assert np.isnan(z[0, 0])
    np.testing.assert_allclose(z[0, 1:], [2.0, 1.0])
    with pytest.raises(SensorError, match="RVL"):
        depth_from_compressed("32FC1; compressedDepth rvl", data)


# --- bad data ----------------------------------------------------------------------------------


def write_yuv_scene(path: Path) -> None:
    rgb, depth_mm = frame_pixels(0)
    with write_bag(path, "db3") as bag:
        for k in range(3):
            t = T0 + k * 100 * MS
            encoding = "yuv422" if k == 1 else "rgb8"
            pixels = rgb[..., :2] if k == 1 else rgb
            bag.write(TOPICS.rgb, "sensor_msgs/msg/Image", t, bag.image(t, encoding, pixels))
            bag.write(TOPICS.depth, "sensor_msgs/msg/Image", t, bag.image(t, "16UC1", depth_mm))
            bag.write(TOPICS.camera_info, "sensor_msgs/msg/CameraInfo", t, bag.camera_info(t))


def test_a_wrong_encoding_is_a_counted_skip_naming_the_topic(tmp_path, caplog):
    path = tmp_path / "yuv"
    write_yuv_scene(path)
    with caplog.at_level(logging.WARNING), RosbagSource.open(path) as src:
        frames = list(src.frames())
    assert [f.stamp_ns for f in frames] == [T0, T0 + 200 * MS]
    assert src.skipped == {"unsupported_encoding": 1}
    assert TOPICS.rgb in caplog.text and "yuv422" in caplog.text


def test_a_wrong_encoding_in_strict_mode_names_topic_and_encoding(tmp_path):
    path = tmp_path / "yuv"
    write_yuv_scene(path)
    with RosbagSource.open(path, strict=True) as src:
        with pytest.raises(SensorError, match=f"topic {TOPICS.rgb}: encoding 'yuv422'"):
            list(src.frames())


@pytest.mark.parametrize("kind", KINDS)
def test_a_truncated_bag_is_a_sensor_error_naming_the_file(tmp_path, kind):
    good = bag_path(tmp_path, kind)
    write_scene(good, kind, frames=2)
    file = good if kind == "bag" else next(good.glob(f"*.{kind}"))
    bad = tmp_path / f"broken.{kind}"
    data = file.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(SensorError, match=f"{bad}: cannot read as a rosbag"):
        open_source(bad)


def test_garbage_with_a_bag_suffix_is_a_sensor_error(tmp_path):
    bad = tmp_path / "notes.bag"
    bad.write_text("not a bag at all")
    with pytest.raises(SensorError, match="notes.bag: cannot read as a rosbag: .*magic"):
        RosbagSource.open(bad)


def test_missing_topics_are_reported_with_what_the_bag_holds(tmp_path):
    path = tmp_path / "other.bag"
    with write_bag(path, "bag") as bag:
        bag.write("/robot/odom", "nav_msgs/msg/Odometry", T0, bag.odometry(T0, 1.0, 2.0, 0.5))
        bag.write(
            "/chatter", "std_msgs/msg/String", T0, bag.types["std_msgs/msg/String"](data="hi")
        )
    with RosbagSource.open(path) as src:
        text = src.describe()
        assert list(src.frames()) == [] and src.wheels() is None and src.intrinsics() is None
        odom = src.odometry()
    assert text.startswith("rosbag1 other.bag")
    assert "odom /robot/odom (nav_msgs/Odometry, 1 messages, auto-detected; /odom absent)" in text
    assert f"rgb: none ({TOPICS.rgb} absent; no sensor_msgs/Image or" in text
    assert "other topics: /chatter (std_msgs/String, 1)" in text
    assert odom is not None and odom.x.tolist() == [1.0]


def test_an_explicit_topic_is_never_substituted(tmp_path):
    path = tmp_path / "odom.bag"
    with write_bag(path, "bag") as bag:
        bag.write("/robot/odom", "nav_msgs/msg/Odometry", T0, bag.odometry(T0, 1.0, 2.0, 0.5))
    with RosbagSource.open(path, RosbagTopics(odom="/base/odom")) as src:
        assert src.odometry() is None
        assert "odom: none (configured topic /base/odom absent)" in src.describe()


def test_zero_header_stamps_fall_back_to_receive_time_and_camera_info_stamps_are_fixed(tmp_path):
    path = tmp_path / "stamps.bag"
    rgb, depth_mm = frame_pixels(0)
    with write_bag(path, "bag") as bag:
        for k in range(2):
            t = T0 + k * 100 * MS
            bag.write(TOPICS.rgb, "sensor_msgs/msg/Image", t, bag.image(t, "rgb8", rgb))
            bag.write(
                TOPICS.depth, "sensor_msgs/msg/Image", t + 1 * MS, bag.image(0, "16UC1", depth_mm)
            )
            # A driver stamping CameraInfo from another clock: 1000 s off.
            bag.write(
                TOPICS.camera_info,
                "sensor_msgs/msg/CameraInfo",
                t,
                bag.camera_info(t - 1000 * 10**9),
            )
    with RosbagSource.open(path) as src:
        np.testing.assert_array_equal(src.stream_stamps()["depth"], T0 + np.array([1, 101]) * MS)
        frames = list(src.frames())
        assert len(frames) == 2 and frames[0].intrinsics == INTR
        assert src.skipped == {"zero_header_stamp": 2, "camera_info_stamp_fixed": 2}
        list(src.frames())
        assert src.skipped == {"zero_header_stamp": 2, "camera_info_stamp_fixed": 2}


def test_joint_state_wheel_angles_become_encoder_positions(tmp_path):
    path = tmp_path / "joints"
    with write_bag(path, "db3") as bag:
        for k in range(3):
            angle = k * math.pi  # half a revolution per message
            msg = bag.joint_state(
                T0 + k * MS, ["right_wheel_joint", "left_wheel_joint"], [angle, -angle]
            )
            bag.write("/joint_states", "sensor_msgs/msg/JointState", T0 + k * MS, msg)
    with RosbagSource.open(path) as src:
        wheels = src.wheels()
        assert "wheels /joint_states (sensor_msgs/JointState" in src.describe()
    assert wheels is not None
    np.testing.assert_array_equal(wheels.left, [0, -18, -36])  # 36 positions per revolution
    np.testing.assert_array_equal(wheels.right, [0, 18, 36])
    np.testing.assert_array_equal(wheels.stamps_ns, T0 + np.arange(3) * MS)


def test_opening_is_transactional(tmp_path, monkeypatch):
    from rosbags.highlevel import AnyReader

    path = tmp_path / "t.bag"
    write_scene(path, "bag", frames=1)
    closed: list[bool] = []
    original_close = AnyReader.close

    def spy_close(self: AnyReader) -> None:
        closed.append(True)
        original_close(self)

    def boom(*_args: object) -> None:
        raise RuntimeError("boom")

    monkeypatch.setattr(AnyReader, "close", spy_close)
    monkeypatch.setattr("sensors.rosbag_source.resolve_topics", boom)
    with pytest.raises(RuntimeError, match="boom"):
        RosbagSource.open(path)
    assert closed == [True]


# --- pure helpers ------------------------------------------------------------------------------


def test_header_stamp_is_read_from_raw_bytes_in_both_encodings():
    ros1 = struct.pack("<III", 7, 12, 345) + b"\0" * 8
    cdr_le = bytes([0, 1, 0, 0]) + struct.pack("<iI", 12, 345) + b"\0" * 8
    cdr_be = bytes([0, 0, 0, 0]) + struct.pack(">iI", 12, 345) + b"\0" * 8
    assert header_stamp_ns_from_raw(ros1, is_ros2=False) == 12_000_000_345
    assert header_stamp_ns_from_raw(cdr_le, is_ros2=True) == 12_000_000_345
    assert header_stamp_ns_from_raw(cdr_be, is_ros2=True) == 12_000_000_345
    assert header_stamp_ns_from_raw(bytes([0, 3]) + cdr_le[2:], is_ros2=True) is None
    assert header_stamp_ns_from_raw(b"\0" * 8, is_ros2=False) is None


def test_row_padding_is_dropped():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.zeros((2, 12), dtype=np.uint8)
    padded[:, :9] = rgb.reshape(2, 9)
    np.testing.assert_array_equal(rgb_from_image("rgb8", 2, 3, 12, padded.reshape(-1)), rgb)
    with pytest.raises(SensorError, match="needs 24 bytes, has 20"):
        rgb_from_image("rgb8", 2, 3, 12, padded.reshape(-1)[:20])


def test_topics_are_auto_detected_only_when_unique():
    available = {
        "/kinect/rgb/image_raw": "sensor_msgs/msg/Image",
        "/kinect/rgb/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
        "/kinect/depth/image_raw": "sensor_msgs/msg/Image",
        "/kinect/depth_registered/image_raw": "sensor_msgs/msg/Image",
        "/kinect/rgb/camera_info": "sensor_msgs/CameraInfo",
        "/kinect/depth/camera_info": "sensor_msgs/CameraInfo",
        "/imu_a": "sensor_msgs/msg/Imu",
        "/imu_b": "sensor_msgs/msg/Imu",
    }
    chosen = resolve_topics(available, RosbagTopics())
    assert chosen["rgb"].topic == "/kinect/rgb/image_raw"
    assert chosen["depth"].topic == "/kinect/depth_registered/image_raw"
    assert chosen["camera_info"].topic == "/kinect/rgb/camera_info"
    assert chosen["imu"].topic is None and "ambiguous: /imu_a, /imu_b" in chosen["imu"].note
    assert chosen["wheels"].topic is None


def test_pairing_sorts_dedups_and_counts_the_unpaired():
    rgb = np.array([200, 100, 100, 300, 900]) * MS
    depth = np.array([105, 205, 310]) * MS
    ri, di, counts = pair_rgb_depth(rgb, depth, 20 * MS)
    assert ri.tolist() == [1, 0, 3] and di.tolist() == [0, 1, 2]
    assert counts == {"duplicate_stamp": 1, "rgb_without_depth": 1}


def test_camera_info_stamps_far_from_every_image_take_the_nearest_received_image_stamp():
    fixed, was = fix_camera_info_stamps(
        np.array([100, 5]), np.array([1000, 2050]), np.array([100, 200]), np.array([1000, 2000]), 10
    )
    assert fixed.tolist() == [100, 200] and was.tolist() == [False, True]


def test_wheel_helpers():
    assert wheel_joint_indices(["r_wheel_right", "wheel_left"]) == (1, 0)
    assert wheel_joint_indices(["a", "b", "c"]) == (0, 1)
    np.testing.assert_array_equal(
        ticks_from_wheel_angles(np.array([2 * math.pi, -0.1]), 36), [36, -1]
    )


def test_only_bag_like_paths_are_claimed(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "metadata.yaml").write_text("name: not a bag\n")
    assert not looks_like_rosbag(tmp_path / "notes.txt")
    assert not looks_like_rosbag(tmp_path / "cfg")
    assert RosbagSource.try_open(tmp_path / "cfg") is None


def test_try_open_does_not_import_rosbags_for_other_paths(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    code = (
        "import sys; from pathlib import Path; from sensors.rosbag_source import RosbagSource; "
        f"assert RosbagSource.try_open(Path({str(tmp_path / 'notes.txt')!r})) is None; "
        "assert not any(m.startswith('rosbags') for m in sys.modules), 'rosbags imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


def test_topics_from_the_user_config_reach_the_adapter_through_open_source(tmp_path):
    from rgbdnav.config import load_config, source_options
    from sensors.source import open_source

    path = tmp_path / "two_odoms.bag"
    with write_bag(path, "bag") as bag:
        bag.write("/a/odom", "nav_msgs/msg/Odometry", T0, bag.odometry(T0, 1.0, 0.0, 0.0))
        bag.write("/b/odom", "nav_msgs/msg/Odometry", T0, bag.odometry(T0, 2.0, 0.0, 0.0))
    # Two candidates: auto-detection must not guess; a command stops with both listed ...
    with pytest.raises(SensorError, match=r"odom is ambiguous: /a/odom, /b/odom.*--odom-topic"):
        open_source(path, source_options(load_config()))
    # ... `info` (require_topics=False) describes the bag without the stream ...
    with open_source(path, source_options(load_config(), require_topics=False)) as src:
        assert src.odometry() is None
    # ... and `--set topics.odom=/b/odom` picks one.
    cfg = load_config(overrides=["topics.odom=/b/odom"])
    with open_source(path, source_options(cfg)) as src:
        odom = src.odometry()
        assert odom is not None and odom.x.tolist() == [2.0]


def test_set_sync_slop_reaches_the_bag_reader_through_the_source_options(tmp_path):
    from rgbdnav.config import load_config, source_options

    path = bag_path(tmp_path, "db3")
    write_scene(path, "db3")  # depth stamped 5 ms after its rgb image
    with open_source(path, source_options(load_config([], []))) as src:
        assert len(list(src.frames())) == 4  # default slop 20 ms
    with open_source(path, source_options(load_config([], ["sync.slop=0.001"]))) as src:
        assert list(src.frames()) == []  # --set sync.slop=0.001: 5 ms apart is no pair
