"""Property tests for the readers the two other fuzz modules left out (issue 28's "every parser"):
world files, map bundles (graph.json, map.yaml, scans.npz, grid.npz), recording folders (index
files, wheels, IMU, scene.yaml), TUM camera YAML, g2o graphs, relations files and rosbag message
fields. Whatever the bytes, each returns a valid result or raises its documented RgbdNavError
subclass: never another exception, a hang or a silently wrong value."""

from __future__ import annotations

import io
import math
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sensors.recording import Recording
from sensors.rosbag_source import (
    depth_from_compressed,
    depth_from_image,
    header_stamp_ns_from_raw,
    intrinsics_from_camera_info,
    rgb_from_compressed,
    rgb_from_image,
)
from sensors.sim.world import WorldError, load_world
from sensors.tum_folder import read_camera_yaml
from sensors.types import MapError, RgbdNavError, SensorError
from slam.map_bundle import load_bundle, save_bundle
from slam.pose_graph import PoseGraphError, read_g2o
from slam.trajectory_eval import TrajectoryEvalError, read_relations
from tests.rgbdnav.test_new_parsers_fuzz import NUM_ALPHABET, examples, rejects_cleanly
from tests.rgbdnav.test_parsers_fuzz import YAML_ALPHABET, mutations
from tests.sensors.test_recording import write_recording
from tests.slam.test_map_bundle import make_bundle

WORLD = (
    b"name: w\nwall_thickness: 0.1\nwall_height: 2.5\ndoor_height: 2.0\n"
    b"floor: {texture: wood, scale: 1.0}\nceiling: {texture: plaster, scale: 2.0}\nwalls:\n"
    b"  - {from: [0, 0], to: [6, 0], texture: brick, texture_scale: 1.2}\n"
    b"  - {from: [6, 0], to: [6, 4], doors: [{at: 2.0, width: 0.9}]}\n"
    b"  - {from: [6, 4], to: [0, 4]}\n  - {from: [0, 4], to: [0, 0]}\n"
    b"furniture:\n  - {name: box, center: [2, 1], size: [0.5, 0.5, 0.8], yaw: 0.3}\n"
    b"start: [1.0, 2.0, 0.0]\nroute:\n  - [4.0, 2.0]\n  - [4.5, 3.0]\n"
)


@examples(60)
@given(mutations(WORLD, YAML_ALPHABET + b"\x00\xff"))
def test_a_mutated_world_file_loads_or_is_a_world_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "world.yaml"
    path.write_bytes(data)
    world = rejects_cleanly(load_world, path, errors=(WorldError,))
    if world is not None:  # what loads is a world the simulator can render and drive in
        assert all(math.isfinite(v) for v in world.start) and np.isfinite(world.route).all()
        for b in world.boxes:
            assert np.isfinite([b.cx, b.cy, b.yaw, b.z_min, b.z_max]).all()
            assert b.half_length > 0 and b.half_width > 0 and b.texture_scale > 0


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("bundle") / "map"
    save_bundle(make_bundle(3), path)
    return path


def _copy(src: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst)
    return Path(shutil.copytree(src, dst))


@examples(60)
@given(st.sampled_from(["graph.json", "map.yaml", "scans.npz", "grid.npz"]), st.data())
def test_a_bundle_with_one_mutated_file_loads_or_is_a_map_error(
    tmp_path: Path, bundle_dir: Path, name: str, data: st.DataObject
) -> None:
    folder = _copy(bundle_dir, tmp_path / "map")
    base = (folder / name).read_bytes()
    alphabet = YAML_ALPHABET if name.endswith((".json", ".yaml")) else b"\x00\xff\x7f"
    (folder / name).write_bytes(data.draw(mutations(base, alphabet)))
    bundle = rejects_cleanly(load_bundle, folder, errors=(MapError,))
    if bundle is not None:
        assert np.isfinite(bundle.keyframe_poses).all()
        assert len(bundle.scans) == len(bundle.keyframe_ids)


SCAN_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**62), 2**62)
)


@examples(40)
@given(
    st.sampled_from(["angle_min", "angle_increment", "range_min", "range_max", "stamp_ns"]),
    SCAN_VALUES,
    st.sampled_from(["f8", "i8", "U3", "O"]),
)
def test_scans_npz_values_of_any_kind_load_or_are_a_map_error(
    tmp_path: Path, bundle_dir: Path, key: str, value, dtype: str
) -> None:
    # A bundle written by another tool: any value, any dtype (pickled objects refused).
    folder = _copy(bundle_dir, tmp_path / "map")
    with np.load(folder / "scans.npz") as z:
        arrays = {k: z[k] for k in z.files}
    try:
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            arrays[key] = np.full(arrays[key].shape, value).astype(dtype)
    except (ValueError, OverflowError, TypeError):
        return  # numpy cannot hold it in that dtype: nothing a file could contain
    np.savez(folder / "scans.npz", **arrays)
    bundle = rejects_cleanly(load_bundle, folder, errors=(MapError,))
    if bundle is not None:
        for scan in bundle.scans:
            assert math.isfinite(scan.angle_min) and math.isfinite(scan.angle_increment)


@pytest.fixture(scope="module")
def recording_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "rec"
    write_recording(path)
    (path / "wheels.txt").write_text("# t left right\n1.0 0 0\n1.033 3 4\n1.066 7 9\n")
    (path / "imu.txt").write_text("# t gyro_z\n1.0 0.01\n1.033 0.02\n1.066 -0.01\n")
    return path


@examples(50)
@given(st.sampled_from(["rgb.txt", "depth.txt", "wheels.txt", "imu.txt", "scene.yaml"]), st.data())
def test_a_recording_with_one_mutated_index_or_scene_file_reads_or_is_a_sensor_error(
    tmp_path: Path, recording_dir: Path, name: str, data: st.DataObject
) -> None:
    folder = _copy(recording_dir, tmp_path / "rec")
    base = (folder / name).read_bytes()
    alphabet = YAML_ALPHABET if name.endswith(".yaml") else NUM_ALPHABET + b"/rgbdepthn"
    (folder / name).write_bytes(data.draw(mutations(base, alphabet)))

    def read_all() -> None:
        rec = Recording.open(folder)
        intr = rec.intrinsics
        assert intr.fx > 0 and intr.fy > 0 and math.isfinite(intr.cx) and math.isfinite(intr.cy)
        for frame in rec.frames(skip_bad=True):
            assert frame.rgb.shape[:2] == frame.depth_m.shape
        for stream in (rec.wheels(), rec.imu()):
            if stream is not None:
                assert stream[0].dtype == np.int64 and np.all(np.diff(stream[0]) > 0)

    rejects_cleanly(read_all, errors=(SensorError,))


TUM_CAMERA = (
    b"%YAML:1.0\n# TUM fr3\nCamera.fx: 535.4\nCamera.fy: 539.2\nCamera.cx: 320.1\n"
    b"Camera.cy: 247.6\nCamera.width: 640\nCamera.height: 480\nDepthMapFactor: 5000.0\n"
)


@examples(60)
@given(mutations(TUM_CAMERA, YAML_ALPHABET + b"\x00"))
def test_a_mutated_tum_camera_yaml_gives_usable_intrinsics_or_none(
    tmp_path: Path, data: bytes
) -> None:
    path = tmp_path / "TUM3.yaml"
    path.write_bytes(data)
    cam = rejects_cleanly(read_camera_yaml, path, errors=(SensorError,))
    if cam is not None:  # never a NaN or non-positive focal length passed on
        assert all(math.isfinite(v) for v in cam.values())
        assert cam.get("fx", 1.0) > 0 and cam.get("fy", 1.0) > 0


G2O = (
    b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.0 0.1 0.2\nVERTEX_SE2 2 2.0 0.2 0.3\n"
    b"EDGE_SE2 0 1 1.0 0.1 0.2 500 0 0 500 0 5000\n"
    b"EDGE_SE2 1 2 1.0 0.1 0.1 500 0 0 500 0 5000\n"
    b"EDGE_SE2 2 0 -2.0 -0.2 -0.3 500 0 0 500 0 5000\n"
)


@examples(60)
@given(mutations(G2O, NUM_ALPHABET + b"VERTEX_SE2"))
def test_a_mutated_g2o_file_reads_or_is_a_pose_graph_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "g.g2o"
    path.write_bytes(data)
    read = rejects_cleanly(read_g2o, path, errors=(PoseGraphError,))
    if read is not None:
        poses, edges = read
        assert np.isfinite(poses).all()


RELATIONS = b"1.0 2.0 0.5 0.0 0 0 0 0.1\n2.0 3.0 0.5 0.1 0 0 0 -0.1\n3.0 4.5 0.4 0.0 0 0 0 0.0\n"


@examples(60)
@given(mutations(RELATIONS, NUM_ALPHABET))
def test_a_mutated_relations_file_reads_or_is_an_eval_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "r.relations"
    path.write_bytes(data)
    rel = rejects_cleanly(read_relations, path, errors=(TrajectoryEvalError, SensorError))
    if rel is not None:
        assert np.isfinite(rel.xyyaw).all() and rel.t1_ns.dtype == np.int64


RAW_ENCODINGS = st.sampled_from(
    ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "16UC1", "mono16", "32FC1", "8UC3", "", "yuv422"]
)


@examples(120)
@given(
    RAW_ENCODINGS,
    st.integers(-3, 9),
    st.integers(-3, 9),
    st.integers(-8, 64),
    st.binary(max_size=400),
    st.booleans(),
)
def test_raw_image_fields_of_any_value_give_an_image_or_a_counted_bad_message(
    encoding: str, height: int, width: int, step: int, data: bytes, big_endian: bool
) -> None:
    for fn in (rgb_from_image, depth_from_image):
        img = rejects_cleanly(
            fn, encoding, height, width, step, data, big_endian, errors=(SensorError,)
        )
        if img is not None:
            assert img.shape[:2] == (height, width)
            assert img.dtype == (np.uint8 if fn is rgb_from_image else np.float32)


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


PNG16 = _png(np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000)
PNG8 = _png(np.arange(36, dtype=np.uint8).reshape(3, 4, 3))
DEPTH_HEADER = b"\x00\x00\x00\x00" + np.array([1.0, 2.0], "<f4").tobytes()


@examples(120)
@given(
    st.sampled_from(
        [
            "png",
            "jpeg",
            "16UC1; compressedDepth png",
            "32FC1; compressedDepth",
            "rvl compresseddepth",
        ]
    ),
    st.sampled_from([PNG16, PNG8, DEPTH_HEADER + PNG16, DEPTH_HEADER + PNG8, b""]),
    st.data(),
)
def test_compressed_image_bytes_give_an_image_or_a_counted_bad_message(
    fmt: str, base: bytes, data: st.DataObject
) -> None:
    blob = data.draw(mutations(base, b"\x00\xff\x89PNG") if base else st.binary(max_size=64))
    for fn in (rgb_from_compressed, depth_from_compressed):
        img = rejects_cleanly(fn, fmt, io.BytesIO(blob).getvalue(), errors=(SensorError,))
        if img is not None:
            assert img.ndim == (3 if fn is rgb_from_compressed else 2) and img.size > 0


@examples(80)
@given(
    st.integers(-(2**31), 2**31),
    st.integers(-(2**31), 2**31),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=12),
)
def test_camera_info_of_any_values_gives_usable_intrinsics_or_a_counted_bad_message(
    width: int, height: int, k: list[float]
) -> None:
    intr = rejects_cleanly(
        intrinsics_from_camera_info, width, height, k, 1000.0, errors=(RgbdNavError,)
    )
    if intr is not None:
        assert intr.fx > 0 and intr.fy > 0 and intr.width > 0 and intr.height > 0
        assert math.isfinite(intr.cx) and math.isfinite(intr.cy)


@examples(80)
@given(st.binary(max_size=40), st.booleans())
def test_a_header_stamp_of_any_bytes_is_an_int64_or_none(raw: bytes, is_ros2: bool) -> None:
    stamp = header_stamp_ns_from_raw(raw, is_ros2)
    assert stamp is None or -(2**63) <= stamp < 2**63
