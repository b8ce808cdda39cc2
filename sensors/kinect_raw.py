"""Raw Kinect v1 depth: the 11-bit disparity values libfreenect delivers, and metres from them.

The Kinect v1 reports depth as an 11-bit "raw disparity" d in [0, 2047], 2047 meaning no
measurement. Metres follow from Nicolas Burrus' calibration (Burrus 2011, "Kinect calibration";
quoted with the fit below on the OpenKinect wiki, "Imaging Information"):

    z = 1 / (d * -0.0030711016 + 3.3309495161)        [m]

Stéphane Magnenat's fit (OpenKinect mailing list, 2010), ``z = 0.1236 * tan(d / 2842.5 + 1.1863)``,
is kept as a cross-check (:func:`disparity_to_depth_tan`). The two are independent fits to
different devices and agree to 5 %, not 2 %: between 0.5 and 4 m the tangent fit reads up to
5.0 % longer (at 0.5-2 m) and up to 2.1 % shorter (near 4 m) — the size of unit-to-unit Kinect
differences, so calibrate the device where that matters.

The denominator of Burrus' formula vanishes at d ~ 1084.6, so raw values near and beyond it are
not depths; such values, and depths outside what a Kinect v1 can measure, become 0 (invalid, the
convention of ``RgbdFrame.depth_m``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from sensors.types import SensorError

KINECT_RAW_INVALID = 2047  # raw value of "no measurement" (all 11 bits set)
KINECT_RAW_BITS = 11
BURRUS_SCALE = -0.0030711016  # [1/(m * count)] Burrus 2011
BURRUS_OFFSET = 3.3309495161  # [1/m]
MAGNENAT_K = 0.1236  # [m] Magnenat 2010
MAGNENAT_DIVISOR = 2842.5  # [counts/rad]
MAGNENAT_OFFSET = 1.1863  # [rad]
MIN_PLAUSIBLE_DEPTH_M = 0.4  # [m] Kinect v1 sees from ~0.5 m; raw 0 already means 0.30 m
MAX_PLAUSIBLE_DEPTH_M = 10.0  # [m] beyond this the 11-bit disparity has no resolution left
PGM_MAGIC = b"P5"


def disparity_to_depth(
    raw: np.ndarray,
    min_depth_m: float = MIN_PLAUSIBLE_DEPTH_M,
    max_depth_m: float = MAX_PLAUSIBLE_DEPTH_M,
) -> np.ndarray:
    """Raw 11-bit Kinect v1 disparity (any integer array) -> float32 depth [m] (Burrus 2011).

    0 where ``raw >= 2047`` (no measurement) or where the depth falls outside
    ``[min_depth_m, max_depth_m]`` (including raw values past the pole of the formula).
    """
    d = np.asarray(raw).astype(np.float64)
    with np.errstate(divide="ignore"):
        z = 1.0 / (d * BURRUS_SCALE + BURRUS_OFFSET)
    valid = (d < KINECT_RAW_INVALID) & (z >= min_depth_m) & (z <= max_depth_m)
    return np.where(valid, z, 0.0).astype(np.float32)


def disparity_to_depth_tan(raw: np.ndarray) -> np.ndarray:
    """Magnenat's tangent fit, float64 [m] without validity masking (a reference for tests)."""
    d = np.asarray(raw).astype(np.float64)
    return MAGNENAT_K * np.tan(d / MAGNENAT_DIVISOR + MAGNENAT_OFFSET)


def _pgm_header(data: bytes, where: str) -> tuple[int, int, int, int]:
    """(width, height, maxval, offset of the pixel data) of a binary PGM (P5), comments allowed."""
    if data[:2] != PGM_MAGIC:
        raise SensorError(f"{where}: not a binary PGM (P5) file")
    fields: list[int] = []
    pos = 2
    while len(fields) < 3:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.find(b"\n", pos)
            if pos < 0:
                break
            continue
        end = pos
        while end < len(data) and data[end : end + 1].isdigit():
            end += 1
        if end == pos:
            raise SensorError(f"{where}: bad PGM header near byte {pos}")
        fields.append(int(data[pos:end]))
        pos = end
    if len(fields) < 3:
        raise SensorError(f"{where}: PGM header is incomplete")
    # Exactly one whitespace byte separates the header from the pixels.
    return fields[0], fields[1], fields[2], pos + 1


def read_raw_disparity_pgm(path: str | os.PathLike[str]) -> np.ndarray:
    """A raw Kinect v1 disparity frame stored as a 16-bit PGM -> (H, W) uint16 in [0, 2047].

    PGM stores 16-bit samples big-endian, but frames dumped straight from libfreenect (the NYU
    Depth raw frames, for one) hold little-endian bytes under that header. The byte order that
    keeps every value within 11 bits wins; a frame that fits neither is an error.
    """
    file = Path(path)
    try:
        data = file.read_bytes()
    except OSError as err:
        raise SensorError(f"{file}: cannot read: {err.strerror or err}") from err
    width, height, maxval, offset = _pgm_header(data, str(file))
    if maxval < 256:
        raise SensorError(f"{file}: 8-bit PGM (maxval {maxval}); raw Kinect disparity is 16-bit")
    size = width * height * 2
    if len(data) - offset < size:
        raise SensorError(f"{file}: truncated PGM: {len(data) - offset} of {size} pixel bytes")
    pixels = data[offset : offset + size]
    limit = (1 << KINECT_RAW_BITS) - 1
    for order in (">u2", "<u2"):  # the standard first, then the swapped libfreenect dump
        raw = np.frombuffer(pixels, dtype=order).reshape(height, width)
        if int(raw.max(initial=0)) <= limit:
            return raw.astype(np.uint16)
    raise SensorError(f"{file}: values exceed {KINECT_RAW_BITS} bits in either byte order")


__all__ = [
    "KINECT_RAW_INVALID",
    "disparity_to_depth",
    "disparity_to_depth_tan",
    "read_raw_disparity_pgm",
]
