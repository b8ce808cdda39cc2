"""Property tests for every reader a run reads through (config, YAML, stamps, TUM, CARMEN,
images, Nav2 maps; here because this layer wires all three): whatever the bytes, each one returns a
valid result or raises its documented error (an RgbdNavError subclass; ValueError for
parse_stamp) -- never another exception, a hang or an allocation the input only claimed."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rgbdnav.config import Config, load_config
from sensors.carmen import read_carmen_log
from sensors.images import MAX_IMAGE_PIXELS, decode_image
from sensors.safe_yaml import load_yaml
from sensors.tum import load_tum_trajectory
from sensors.types import MAX_STAMP_NS, MapError, RgbdNavError, SensorError, parse_stamp
from slam.map_bundle import load_map_yaml


def examples(n: int) -> settings:
    """``n`` examples, no deadline, no example database, one tmp_path reused per example."""
    return settings(
        max_examples=n,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )


def mutations(base: bytes, alphabet: bytes) -> st.SearchStrategy[bytes]:
    """``base`` with a few bytes replaced, inserted, deleted or a span repeated."""
    op = st.tuples(
        st.sampled_from(["replace", "insert", "delete", "repeat", "cut"]),
        st.integers(0, max(len(base) - 1, 0)),
        st.one_of(st.sampled_from(list(alphabet)), st.integers(0, 255)),
        st.integers(1, 64),
    )

    def apply(ops: list[tuple[str, int, int, int]]) -> bytes:
        data = bytearray(base)
        for kind, pos, byte, n in ops:
            pos = min(pos, len(data))
            if kind == "replace" and pos < len(data):
                data[pos] = byte
            elif kind == "insert":
                data[pos:pos] = bytes([byte]) * n
            elif kind == "delete":
                del data[pos : pos + n]
            elif kind == "repeat":
                data[pos:pos] = bytes(data[pos : pos + 16]) * n
            elif kind == "cut":
                del data[pos:]
        return bytes(data)

    return st.lists(op, min_size=1, max_size=6).map(apply)


CONFIG = (
    b"ekf:\n  frequency: 30.0\n  sensor_timeout: 0.1\n"
    b"camera: &cam\n  fx: 525.0\n  fy: 525.0\n  width: 640\n"
    b"mapper:\n  resolution: 0.05\n  minimum_travel_distance: 0.5\n"
    b"live: {checkpoint_period: 30.0, frame_queue_size: 4}\n"
)
YAML_ALPHABET = b" \n:-[]{},&*!#|>'\"0123456789.eE+nanif<"


@examples(60)
@given(mutations(CONFIG, YAML_ALPHABET))
def test_a_mutated_config_file_loads_or_is_a_config_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "c.yaml"
    path.write_bytes(data)
    try:
        cfg = load_config([path])
    except RgbdNavError:
        return
    assert isinstance(cfg, Config)


OVERRIDE_VALUES = st.one_of(
    st.text(max_size=30),
    st.sampled_from(
        [
            ".nan",
            ".inf",
            "-.inf",
            "1e12",
            "1e400",
            "1" + "0" * 400,
            "[1, 2",
            "~",
            "&a [*a]",
            "{a: 1, a: 2}",
            "0x1F",
            "1_000",
            "yes",
            "!!binary AAAA",
        ]
    ),
)
KEYS = st.sampled_from(
    [
        "ekf.frequency",
        "camera.fx",
        "camera.width",
        "mapper.resolution",
        "topics.rgb",
        "ekf.odom0_config",
        "nope.nope",
        "ekf",
    ]
)


@examples(80)
@given(KEYS, OVERRIDE_VALUES)
def test_any_set_override_loads_or_is_a_config_error(key: str, value: str) -> None:
    try:
        cfg = load_config(overrides=[f"{key}={value}"])
    except RgbdNavError as err:
        assert len(str(err)) < 1000  # one readable line, whatever was typed
        return
    assert isinstance(cfg, Config)


@examples(80)
@given(st.text(max_size=200))
def test_any_text_is_yaml_or_a_config_error(text: str) -> None:
    try:
        load_yaml(text, "fuzz")
    except RgbdNavError:
        pass


STAMP_TEXT = st.one_of(
    st.text("0123456789.-+eE", max_size=30),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
)


@examples(150)
@given(STAMP_TEXT)
def test_a_stamp_is_an_int64_in_range_or_a_value_error(text: str) -> None:
    try:
        ns = parse_stamp(text)
    except ValueError:
        return
    assert isinstance(ns, int) and -MAX_STAMP_NS <= ns <= MAX_STAMP_NS


TUM = (
    b"# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.5 1.5 -2 0 0 0 0.7071 0.7071\n3.0 2 0 0 0 0 1 0\n"
)


@examples(60)
@given(mutations(TUM, b" \n.-+e0123456789#naif"))
def test_a_mutated_tum_file_loads_or_is_a_sensor_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "t.txt"
    path.write_bytes(data)
    try:
        stamps, xyz, quat = load_tum_trajectory(path)
    except SensorError:
        return
    assert stamps.dtype == np.int64 and np.isfinite(xyz).all() and np.isfinite(quat).all()
    assert len(stamps) == len(xyz) == len(quat)


def _flaser(t: float) -> bytes:
    ranges = " ".join(["1.5"] * 181)
    return f"FLASER 181 {ranges} 1 2 0.5 0.1 0.2 0.3 {t} host {t + 0.01}\n".encode()


CARMEN = b"# log\nPARAM robot_front_laser_max 81.9\n" + b"".join(map(_flaser, (1.0, 1.2, 1.4)))


@examples(60)
@given(mutations(CARMEN, b" \n.-e0123456789FLASERODOMnaif"))
def test_a_mutated_carmen_log_reads_or_is_a_sensor_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "a.clf"
    path.write_bytes(data)
    try:
        log = read_carmen_log(path)
    except SensorError:
        return
    assert all(np.isfinite(s.angle_min) and np.isfinite(s.angle_increment) for s in log.scans)
    assert sum(log.skipped.values()) >= 0


def _encoded(ext: str) -> bytes:
    image = np.arange(48, dtype=np.uint8).reshape(4, 4, 3) * 5
    ok, buf = cv2.imencode(ext, image if ext != ".pgm" else image[..., 0])
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("ext", [".png", ".jpg", ".pgm"])
def test_mutated_image_bytes_decode_or_are_an_error_never_a_huge_allocation(ext: str) -> None:
    @examples(60)
    @given(mutations(_encoded(ext), b"\x00\xff\x01\x7f\x80"))
    def check(data: bytes) -> None:
        try:
            image = decode_image(data, f"x{ext}", SensorError)
        except SensorError:
            return
        assert image.shape[0] * image.shape[1] <= MAX_IMAGE_PIXELS

    check()


MAP_YAML = (
    b"image: map.pgm\nmode: trinary\nresolution: 0.05\norigin: [-1.0, -0.5, 0.0]\n"
    b"negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
)
PGM = b"P5\n4 3\n255\n" + bytes([0, 254, 205, 0] * 3)


@examples(60)
@given(
    st.one_of(
        st.tuples(mutations(MAP_YAML, YAML_ALPHABET + b"/abcdefgimnop"), st.just(PGM)),
        st.tuples(st.just(MAP_YAML), mutations(PGM, b"P5 \n0123456789\x00\xff")),
    )
)
def test_a_mutated_nav2_map_loads_or_is_a_map_error(
    tmp_path: Path, files: tuple[bytes, bytes]
) -> None:
    (tmp_path / "map.yaml").write_bytes(files[0])
    (tmp_path / "map.pgm").write_bytes(files[1])
    try:
        grid = load_map_yaml(tmp_path / "map.yaml")
    except MapError:
        return
    assert grid.geometry.width * grid.geometry.height <= MAX_IMAGE_PIXELS
