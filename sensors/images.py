"""Reading the colour and depth images of recorded frames, with a reason for every failure."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from sensors.types import SensorError

PNG_IEND = b"IEND"  # type of the last chunk of every complete PNG
JPEG_EOI = b"\xff\xd9"  # end-of-image marker of every complete JPEG


class ImageError(SensorError):
    """A missing or bad image. ``reason`` (missing, unreadable, truncated, wrong_size,
    wrong_dtype) is what sources count skipped frames by."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


def read_image(file: Path, size: tuple[int, int], depth: bool) -> np.ndarray:
    """A colour image as (H, W, 3) uint8 RGB, or a depth image as (H, W) uint16 counts, of
    ``size`` = (width, height); anything else raises :class:`ImageError` naming the file."""
    try:
        data = file.read_bytes()
    except FileNotFoundError as err:
        raise ImageError(f"{file}: image is missing", "missing") from err
    except OSError as err:
        raise ImageError(f"{file}: cannot read: {err.strerror or err}", "unreadable") from err
    # OpenCV decodes a truncated PNG or JPEG partially without an error: check the end marker.
    suffix = file.suffix.lower()
    if (suffix == ".png" and data[-8:-4] != PNG_IEND) or (
        suffix in (".jpg", ".jpeg") and data.rstrip(b"\0\r\n")[-2:] != JPEG_EOI
    ):
        raise ImageError(f"{file}: truncated {suffix[1:].upper()}", "truncated")
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageError(f"{file}: not a readable image", "unreadable")
    w, h = size
    if image.shape[:2] != (h, w):
        raise ImageError(
            f"{file}: image is {image.shape[1]}x{image.shape[0]}, camera is {w}x{h}", "wrong_size"
        )
    want = ((h, w), np.uint16) if depth else ((h, w, 3), np.uint8)
    if image.shape != want[0] or image.dtype != want[1]:
        raise ImageError(
            f"{file}: expected {want[0]} {np.dtype(want[1]).name}, got {image.shape} {image.dtype}",
            "wrong_dtype",
        )
    return image if depth else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
