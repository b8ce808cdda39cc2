"""Reading the colour and depth images of recorded frames, with a reason for every failure."""

from __future__ import annotations

import itertools
import re
import struct
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from sensors.bounded_read import read_bounded
from sensors.types import SensorError

T = TypeVar("T")

PNG_IEND = b"IEND"  # type of the last chunk of every complete PNG
JPEG_EOI = b"\xff\xd9"  # end-of-image marker of every complete JPEG
MAX_IMAGE_FILE_BYTES = 256 * 2**20  # [bytes] an image file larger than this is not read


class ImageError(SensorError):
    """A missing or bad image. ``reason`` (missing, unreadable, truncated, wrong_size,
    wrong_dtype) is what sources count skipped frames by."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


class _Unreadable(ImageError):
    def __init__(self, message: str) -> None:
        super().__init__(message, "unreadable")


def read_image(file: Path, size: tuple[int, int], depth: bool) -> np.ndarray:
    """A colour image as (H, W, 3) uint8 RGB, or a depth image as (H, W) uint16 counts, of
    ``size`` = (width, height); anything else raises :class:`ImageError` naming the file."""
    data = check_image_file(file, size)
    w, h = size
    image = decode_image(data, file, _Unreadable)
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


def check_image_file(file: Path, size: tuple[int, int]) -> bytes:
    """The bytes of an image file of ``size`` = (width, height) after the checks that need no
    decoding (present, readable, complete, the size its header declares, a PNG's chunk layout);
    :class:`ImageError` otherwise. A frame whose colour is not needed is checked this far only
    (:meth:`sensors.recording.Recording.frames`)."""
    if not file.exists():
        raise ImageError(f"{file}: image is missing", "missing")
    data = read_bounded(file, MAX_IMAGE_FILE_BYTES, _Unreadable, "image")
    # OpenCV decodes a truncated PNG or JPEG partially without an error: check the end marker.
    suffix = file.suffix.lower()
    if (suffix == ".png" and data[-8:-4] != PNG_IEND) or (
        suffix in (".jpg", ".jpeg") and data.rstrip(b"\0\r\n")[-2:] != JPEG_EOI
    ):
        raise ImageError(f"{file}: truncated {suffix[1:].upper()}", "truncated")
    w, h = size
    declared = declared_size(data)
    if declared is not None and declared != (w, h):  # before decoding what it claims
        raise ImageError(
            f"{file}: image is {declared[0]}x{declared[1]}, camera is {w}x{h}", "wrong_size"
        )
    if data.startswith(_PNG_SIGNATURE) and (problem := png_chunk_problem(data)) is not None:
        raise _Unreadable(f"{file}: corrupt PNG ({problem})")
    return data


def decoded_ahead(
    decode: Callable[[int], T], n: int, workers: int, name: str = "decode"
) -> Iterator[tuple[int, Future[T]]]:
    """``(k, future of decode(k))`` for k = 0..n-1 in order, ``workers`` threads decoding up to
    ``2 * workers`` frames ahead (cv2 releases the GIL, so decoding overlaps the consumer's
    work). The caller takes ``future.result()``: a bad frame raises there, in its place."""
    with ThreadPoolExecutor(workers, thread_name_prefix=name) as pool:
        todo = iter(range(n))
        pending: deque[tuple[int, Future[T]]] = deque(
            (k, pool.submit(decode, k)) for k in itertools.islice(todo, 2 * workers)
        )
        try:
            while pending:
                k, future = pending.popleft()
                nxt = next(todo, None)
                if nxt is not None:
                    pending.append((nxt, pool.submit(decode, nxt)))
                yield k, future
        finally:  # an error or a consumer that stops early: drop the read-ahead
            for _, future in pending:
                future.cancel()


# --- decoding bytes safely ---------------------------------------------------------------------

MAX_IMAGE_PIXELS = 2**26  # [pixels] largest image decoded (8192 x 8192; a map 410 m square)
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNM_HEADER = re.compile(rb"P[1-7](?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)")
# JPEG start-of-frame markers (baseline, progressive, lossless...), not DHT/JPG/DAC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def declared_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) an image's header declares, read without decoding (PNG, JPEG, PNM);
    None for other formats or a header that does not parse."""
    if data.startswith(_PNG_SIGNATURE) and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    m = _PNM_HEADER.match(data)
    if m is not None:
        return int(m.group(1)), int(m.group(2))
    if data[:2] == b"\xff\xd8":
        i = 2
        while i + 9 <= len(data):
            if data[i] != 0xFF:
                return None
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in _JPEG_SOF:
                h, w = struct.unpack(">HH", data[i + 5 : i + 9])
                return int(w), int(h)
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
                i += 2
                continue
            (length,) = struct.unpack(">H", data[i + 2 : i + 4])
            i += 2 + length
    return None


def png_chunk_problem(data: bytes) -> str | None:
    """Why a PNG's chunk layout is broken (a chunk running past the end of the data), or None.
    OpenCV spends seconds on a chunk whose length field claims gigabytes (the fuzz benchmark
    found 6-36 s for one flipped byte); walking the length fields costs microseconds."""
    i = len(_PNG_SIGNATURE)
    while i + 12 <= len(data):
        (length,) = struct.unpack(">I", data[i : i + 4])
        if length > len(data) - i - 12:
            return f"PNG chunk {data[i + 4 : i + 8]!r} at byte {i} claims {length} bytes"
        if data[i + 4 : i + 8] == PNG_IEND:
            return None
        i += 12 + length
    return "PNG ends without an IEND chunk"


def decode_image(
    data: bytes,
    name: str | Path,
    error: Callable[[str], Exception],
    max_pixels: int = MAX_IMAGE_PIXELS,
) -> np.ndarray:
    """``cv2.imdecode(data, IMREAD_UNCHANGED)`` that never allocates for a size only declared
    (a 100-byte PNG may claim 30000 x 30000), never raises ``cv2.error`` (an empty buffer does),
    and never returns None: every failure is ``error(message)``."""
    if not data:
        raise error(f"{name}: empty image file")
    if data.startswith(_PNG_SIGNATURE) and (problem := png_chunk_problem(data)) is not None:
        raise error(f"{name}: corrupt PNG ({problem})")
    size = declared_size(data)
    if size is not None and size[0] * size[1] > max_pixels:
        raise error(
            f"{name}: image declares {size[0]}x{size[1]} pixels, more than the "
            f"{max_pixels} read here"
        )
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as err:
        raise error(f"{name}: not a readable image ({str(err).strip().splitlines()[-1]})") from None
    if image is None:
        raise error(f"{name}: not a readable image")
    return image
