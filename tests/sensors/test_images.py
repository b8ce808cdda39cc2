"""Decoding images: a size is checked from the header before anything is allocated."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from sensors.images import ImageError, declared_size, decode_image, read_image
from sensors.types import SensorError


def _encoded(ext: str, image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(ext, image)
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("ext", [".png", ".jpg", ".pgm", ".ppm"])
def test_the_declared_size_is_read_from_the_header(ext: str) -> None:
    image = np.zeros((7, 13, 3) if ext in (".jpg", ".ppm") else (7, 13), np.uint8)
    assert declared_size(_encoded(ext, image)) == (13, 7)


def test_a_size_that_is_only_declared_is_never_allocated() -> None:
    data = bytearray(_encoded(".png", np.zeros((2, 2), np.uint8)))
    data[16:24] = (30000).to_bytes(4, "big") * 2
    with pytest.raises(SensorError, match="declares 30000x30000 pixels"):
        decode_image(bytes(data), "x.png", SensorError)


def test_empty_and_garbage_bytes_are_errors_not_cv2_errors() -> None:
    with pytest.raises(SensorError, match="x: empty image file"):
        decode_image(b"", "x", SensorError)
    with pytest.raises(SensorError, match="x: not a readable image"):
        decode_image(b"\0" * 64, "x", SensorError)


def test_a_frame_image_of_another_size_is_refused_from_its_header(tmp_path: Path) -> None:
    data = bytearray(_encoded(".png", np.zeros((2, 2), np.uint16)))
    data[16:24] = (30000).to_bytes(4, "big") * 2
    (tmp_path / "d.png").write_bytes(bytes(data))
    with pytest.raises(ImageError, match="image is 30000x30000, camera is 640x480") as info:
        read_image(tmp_path / "d.png", (640, 480), depth=True)
    assert info.value.reason == "wrong_size"


def test_a_frame_image_that_is_a_device_is_unreadable_not_read(tmp_path: Path) -> None:
    (tmp_path / "rgb.png").symlink_to("/dev/zero")
    with pytest.raises(ImageError, match="not a regular file") as info:
        read_image(tmp_path / "rgb.png", (640, 480), depth=False)
    assert info.value.reason == "unreadable"


def test_a_png_chunk_claiming_gigabytes_is_refused_without_handing_it_to_opencv() -> None:
    # One byte of the IDAT length field changed: OpenCV took 6-11 s to give up on it.
    png = _encoded(".png", np.arange(48, dtype=np.uint8).reshape(4, 4, 3))
    bad = png[:33] + b"\xac" + png[34:]
    t0 = time.perf_counter()
    with pytest.raises(SensorError, match=r"x\.png: corrupt PNG \(PNG chunk b'IDAT' at byte 33"):
        decode_image(bad, "x.png", SensorError)
    assert time.perf_counter() - t0 < 0.5
    with pytest.raises(SensorError, match="ends without an IEND"):
        decode_image(png[:-12], "x.png", SensorError)
