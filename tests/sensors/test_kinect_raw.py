from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sensors.kinect_raw import (
    KINECT_RAW_INVALID,
    disparity_to_depth,
    disparity_to_depth_tan,
    read_raw_disparity_pgm,
)
from sensors.types import SensorError

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
NYU = DATA / "kinect" / "other_formats" / "NYU_depth.pgm"
needs_nyu = pytest.mark.skipif(not NYU.is_file(), reason="../shared/data/kinect is absent")


def write_pgm(path: Path, raw: np.ndarray, byteorder: str, header: bytes | None = None) -> Path:
    h, w = raw.shape
    head = header if header is not None else f"P5\n{w} {h}\n65535\n".encode()
    path.write_bytes(head + raw.astype(f"{byteorder}u2").tobytes())
    return path


def test_known_disparities_convert_by_burrus_formula():
    raw = np.array([[434, 600], [1000, KINECT_RAW_INVALID]], dtype=np.uint16)
    depth = disparity_to_depth(raw)
    assert depth.dtype == np.float32 and depth.shape == (2, 2)
    want = 1.0 / (np.array([434.0, 600.0, 1000.0]) * -0.0030711016 + 3.3309495161)
    np.testing.assert_allclose(depth.ravel()[:3], want, rtol=1e-6)
    assert depth[1, 1] == 0.0
    assert depth[0, 0] == pytest.approx(0.500, abs=0.002)  # raw 434 is half a metre


def test_invalid_and_implausible_raw_values_become_zero():
    raw = np.array([0, 200, 1084, 1085, 1500, 2047, 4095])  # too close, past the pole, invalid
    np.testing.assert_array_equal(disparity_to_depth(raw), 0.0)


def test_burrus_and_magnenat_fits_agree_within_5_percent_from_half_a_metre_to_4m():
    raw = np.arange(0, 1084)
    burrus = disparity_to_depth(raw, min_depth_m=0.5, max_depth_m=4.0).astype(np.float64)
    inside = burrus > 0
    assert inside.sum() > 500
    ratio = disparity_to_depth_tan(raw[inside]) / burrus[inside]
    np.testing.assert_allclose(ratio, 1.0, atol=0.055)  # measured: -2.1 % .. +5.0 %


@pytest.mark.parametrize("byteorder", [">", "<"])
def test_pgm_reads_in_either_byte_order(tmp_path, byteorder):
    raw = np.array([[839, 1000, 2047], [0, 5, 1024]], dtype=np.uint16)
    got = read_raw_disparity_pgm(write_pgm(tmp_path / "d.pgm", raw, byteorder))
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, raw)


def test_pgm_header_comments_are_skipped(tmp_path):
    raw = np.full((2, 3), 900, dtype=np.uint16)
    header = b"P5\n# raw kinect\n3 2\n# 11 bits\n65535\n"
    np.testing.assert_array_equal(
        read_raw_disparity_pgm(write_pgm(tmp_path / "d.pgm", raw, ">", header)), raw
    )


def test_bad_pgms_are_errors_naming_the_file(tmp_path):
    path = tmp_path / "bad.pgm"
    path.write_bytes(b"P2\n1 1\n65535\n0\n")
    with pytest.raises(SensorError, match=r"bad\.pgm: not a binary PGM"):
        read_raw_disparity_pgm(path)
    path.write_bytes(b"P5\n2 2\n255\n\0\0\0\0")
    with pytest.raises(SensorError, match=r"bad\.pgm: 8-bit PGM"):
        read_raw_disparity_pgm(path)
    write_pgm(path, np.zeros((2, 2), np.uint16), ">")
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(SensorError, match=r"bad\.pgm: truncated PGM: 5 of 8 pixel bytes"):
        read_raw_disparity_pgm(path)
    write_pgm(path, np.array([[0x0FFF, 0x0FFF]], np.uint16), ">")
    with pytest.raises(SensorError, match=r"bad\.pgm: values exceed 11 bits"):
        read_raw_disparity_pgm(path)


@needs_nyu
def test_nyu_raw_frame_is_swapped_11_bit_disparity_with_indoor_depths():
    raw = read_raw_disparity_pgm(NYU)
    assert raw.shape == (480, 640)
    assert (int(raw.min()), int(raw.max())) == (839, 2047)
    depth = disparity_to_depth(raw)
    valid = depth[depth > 0]
    assert valid.size > 0.5 * depth.size
    assert 1.0 < float(np.median(valid)) < 5.0
    assert float(valid.min()) == pytest.approx(1.33, abs=0.01)  # raw 839
