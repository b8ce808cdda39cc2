"""OpenNISource without hardware: a fake ``openni.openni2`` module feeds numpy buffers through the
adapter, and the pure stamp/format/pairing helpers are checked directly."""

from __future__ import annotations

import ctypes
import itertools
import math
import sys
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sensors.config import CameraConfig
from sensors.openni_source import (
    COLOUR,
    DEPTH,
    FramePairer,
    OpenNISource,
    OpenNITarget,
    RawFrame,
    depth_from_frame,
    intrinsics_from_fov,
    parse_target,
    rgb_from_frame,
    stamp_ns,
)
from sensors.source import Source
from sensors.types import SensorError

RGB888, GRAY8, DEPTH_1_MM, DEPTH_100_UM, YUV422 = 200, 202, 100, 101, 201
REGISTRATION_DEPTH_TO_COLOR = 1
H, W = 6, 8  # [px]
HOST_NS = 1_700_000_000_000_000_000  # [ns] what the injected clock says at the first frame
PERIOD_US = 33_333  # [us] 30 Hz


# --- a fake openni2 module ---------------------------------------------------------------------


class FakeOpenNIError(Exception):
    pass


class FakeInitializationError(Exception):
    pass


class FakeVideoFrame:
    """Looks like openni2.VideoFrame: OniFrame fields, a ctypes buffer, close()."""

    def __init__(self, ts_us: int, index: int, pixels: np.ndarray, fmt: int, pad: int = 0):
        h, w = pixels.shape[:2]
        rows = np.ascontiguousarray(pixels).view(np.uint8).reshape(h, -1)
        padded = np.zeros((h, rows.shape[1] + pad), dtype=np.uint8)
        padded[:, : rows.shape[1]] = rows
        self._bytes = bytearray(padded.tobytes())
        self.timestamp, self.frameIndex, self.width, self.height = ts_us, index, w, h
        self.stride = padded.shape[1]
        self.videoMode = types.SimpleNamespace(pixelFormat=fmt)
        self.closed = False

    def get_buffer_as_uint8(self) -> Any:
        return (ctypes.c_uint8 * len(self._bytes)).from_buffer(self._bytes)

    def close(self) -> None:
        self.closed = True


@dataclass
class FakeStream:
    frames: list[FakeVideoFrame]
    fail_on_create: bool = False
    mode: Any = None
    started: bool = False
    closed: bool = False
    total: int = 0
    read: list[FakeVideoFrame] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.total = len(self.frames)

    def set_video_mode(self, mode: Any) -> None:
        self.mode = mode

    def get_video_mode(self) -> Any:
        return types.SimpleNamespace(resolutionX=W, resolutionY=H)

    def get_horizontal_fov(self) -> float:
        return math.radians(62.7)

    def get_vertical_fov(self) -> float:
        return math.radians(48.6)

    def get_number_of_frames(self) -> int:
        return self.total

    def start(self) -> None:
        self.started = True

    def stop(self) -> None:
        self.started = False

    def close(self) -> None:
        self.closed, self.started = True, False

    def read_frame(self) -> FakeVideoFrame:
        frame = self.frames.pop(0)
        self.read.append(frame)
        return frame


class FakeDevice:
    def __init__(self, uri: bytes | None, colour: FakeStream, depth: FakeStream, fail_depth=False):
        self.uri, self.colour, self.depth, self.fail_depth = uri, colour, depth, fail_depth
        self.registration = 0
        self.sync = False
        self.closed = False
        self.is_file = False
        self.playback = types.SimpleNamespace(speed=1.0, repeat=True)
        self.playback.set_speed = lambda v: setattr(self.playback, "speed", v)
        self.playback.set_repeat_enabled = lambda v: setattr(self.playback, "repeat", v)

    def create_color_stream(self) -> FakeStream:
        return self.colour

    def create_depth_stream(self) -> FakeStream:
        if self.fail_depth:
            raise FakeOpenNIError(3, "depth stream failed", "")
        return self.depth

    def is_image_registration_mode_supported(self, mode: int) -> bool:
        return True

    def set_image_registration_mode(self, mode: int) -> None:
        self.registration = mode

    def get_image_registration_mode(self) -> int:
        return REGISTRATION_DEPTH_TO_COLOR if self.is_file else self.registration

    def set_depth_color_sync_enabled(self, enable: bool) -> None:
        self.sync = enable

    def get_device_info(self) -> Any:
        return types.SimpleNamespace(uri=b"1d27/0600@2/3", vendor=b"PrimeSense", name=b"PS1080")

    def close(self) -> None:
        self.closed = True


def frame_pixels(k: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(k)
    rgb = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    depth_mm = rng.integers(500, 4500, size=(H, W), dtype=np.uint16)
    depth_mm[0, 0] = 0
    return rgb, depth_mm


def make_streams(n: int, depth_lag_us: int = 1_000) -> tuple[FakeStream, FakeStream]:
    colour, depth = [], []
    for k in range(n):
        rgb, depth_mm = frame_pixels(k)
        t = 1_000_000 + k * PERIOD_US
        colour.append(FakeVideoFrame(t, k + 1, rgb, RGB888))
        depth.append(FakeVideoFrame(t + depth_lag_us, k + 1, depth_mm, DEPTH_1_MM, pad=4))
    return FakeStream(colour), FakeStream(depth)


def fake_openni2(device: FakeDevice | None, init_error: bool = False) -> types.ModuleType:
    mod = types.ModuleType("openni.openni2")
    mod.OpenNIError = FakeOpenNIError  # type: ignore[attr-defined]
    mod.InitializationError = FakeInitializationError  # type: ignore[attr-defined]
    mod.PIXEL_FORMAT_RGB888 = RGB888  # type: ignore[attr-defined]
    mod.PIXEL_FORMAT_DEPTH_1_MM = DEPTH_1_MM  # type: ignore[attr-defined]
    mod.IMAGE_REGISTRATION_DEPTH_TO_COLOR = REGISTRATION_DEPTH_TO_COLOR  # type: ignore[attr-defined]
    mod.VideoMode = types.SimpleNamespace  # type: ignore[attr-defined]
    mod.initialized_with = None  # type: ignore[attr-defined]

    def initialize(dirs: list[str]) -> None:
        if init_error:
            raise FakeInitializationError("OpenNI2 could not be loaded")
        mod.initialized_with = dirs  # type: ignore[attr-defined]

    def open_device(uri: bytes | None, is_file: bool = False) -> FakeDevice:
        if device is None:
            raise FakeOpenNIError(1, "DeviceOpen using default: no devices found", "")
        device.uri, device.is_file = uri, is_file
        return device

    def wait_for_any_stream(streams: list[FakeStream], timeout: float) -> FakeStream | None:
        pending = [s for s in streams if s.frames]
        return min(pending, key=lambda s: s.frames[0].timestamp) if pending else None

    class Device:
        def __new__(cls, uri: bytes) -> FakeDevice:  # type: ignore[misc]
            return open_device(uri)

        open_any = staticmethod(lambda: open_device(None))
        open_file = staticmethod(lambda name: open_device(name, is_file=True))

    mod.initialize = initialize  # type: ignore[attr-defined]
    mod.wait_for_any_stream = wait_for_any_stream  # type: ignore[attr-defined]
    mod.Device = Device  # type: ignore[attr-defined]
    return mod


@pytest.fixture
def install(monkeypatch):
    """Make ``import openni.openni2`` return the given fake module."""

    def _install(mod: types.ModuleType) -> types.ModuleType:
        pkg = types.ModuleType("openni")
        pkg.openni2 = mod  # type: ignore[attr-defined]
        monkeypatch.setitem(sys.modules, "openni", pkg)
        monkeypatch.setitem(sys.modules, "openni.openni2", mod)
        return mod

    return _install


# --- missing pieces: one clear error -----------------------------------------------------------


def test_without_the_binding_one_error_says_what_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "openni", None)  # makes `import openni...` fail
    monkeypatch.delitem(sys.modules, "openni.openni2", raising=False)
    with pytest.raises(SensorError, match="binding 'openni' is not installed") as info:
        OpenNISource.open("openni://")
    text = str(info.value)
    assert "pip install openni" in text and "apt-get install libopenni2-0" in text
    assert "libFreenectDriver.so" in text
    oni = tmp_path / "capture.oni"
    oni.write_bytes(b"\0")
    with pytest.raises(SensorError, match="pip install openni"):
        OpenNISource.try_open(oni)


def test_without_the_runtime_library_the_error_names_it(install):
    install(fake_openni2(None, init_error=True))
    with pytest.raises(SensorError, match="runtime library could not be loaded .*libopenni2-dev"):
        OpenNISource.open("openni://")


def test_without_a_device_the_error_points_at_drivers(install):
    install(fake_openni2(None))
    with pytest.raises(SensorError, match="found no device .*no devices found.*driver installed"):
        OpenNISource.open("openni://")


# --- a live device -----------------------------------------------------------------------------


def test_a_live_device_is_configured_and_yields_registered_frames_on_the_host_clock(install):
    colour, depth = make_streams(3)
    device = FakeDevice(None, colour, depth)
    mod = install(fake_openni2(device))

    src = OpenNISource.open("openni://1d27/0600@2/3", clock=lambda: HOST_NS)
    assert isinstance(src, Source)
    assert device.uri == b"1d27/0600@2/3" and "/usr/lib" in mod.initialized_with
    assert device.registration == REGISTRATION_DEPTH_TO_COLOR and device.sync
    assert (colour.mode.resolutionX, colour.mode.resolutionY, colour.mode.fps) == (640, 480, 30)
    assert colour.mode.pixelFormat == RGB888 and depth.mode.pixelFormat == DEPTH_1_MM
    assert colour.started and depth.started
    k = src.intrinsics()
    assert k is not None and (k.width, k.height) == (W, H)
    assert k.fx == pytest.approx(0.5 * W / math.tan(math.radians(62.7) / 2))  # from the FOV
    assert "PrimeSense PS1080" in src.describe() and "registered to colour" in src.describe()

    frames = list(itertools.islice(src.frames(), 3))
    for i, frame in enumerate(frames):
        rgb, depth_mm = frame_pixels(i)
        assert frame.stamp_ns == HOST_NS + i * PERIOD_US * 1000
        np.testing.assert_array_equal(frame.rgb, rgb)
        np.testing.assert_allclose(frame.depth_m, depth_mm / 1000.0, atol=1e-6)
        assert frame.depth_m.dtype == np.float32 and frame.depth_m[0, 0] == 0.0
    assert src.skipped == {}
    assert all(f.closed for f in colour.read + depth.read)  # buffers handed back

    src.close()
    assert colour.closed and depth.closed and device.closed


def test_the_live_run_gets_frames_on_its_monotonic_clock(install):
    """``rgbdnav live`` opens cameras with ``realtime``: stamps on time.monotonic_ns, as the
    board's readings and the live run's latency clock, not wall time."""
    import time

    from sensors.source import SourceOptions

    colour, depth = make_streams(1)
    install(fake_openni2(FakeDevice(None, colour, depth)))
    src = OpenNISource.try_open("openni://", SourceOptions(realtime=True))
    assert src is not None
    stamp = next(iter(src.frames())).stamp_ns
    assert abs(stamp - time.monotonic_ns()) < 1e9
    src.close()


def test_a_silent_live_device_is_an_error_not_a_hang(install):
    colour, depth = make_streams(1)
    install(fake_openni2(FakeDevice(None, colour, depth)))
    with OpenNISource.open("openni://") as src:
        with pytest.raises(SensorError, match="no frames for 2 s; was the camera unplugged"):
            list(src.frames())


def test_configured_intrinsics_override_the_field_of_view(install):
    colour, depth = make_streams(1)
    install(fake_openni2(FakeDevice(None, colour, depth)))
    camera = CameraConfig(width=W, height=H, fx=10.0, fy=11.0, cx=3.5, cy=2.5)
    with OpenNISource.open("openni://", camera=camera) as src:
        (frame,) = itertools.islice(src.frames(), 1)
    assert (frame.intrinsics.fx, frame.intrinsics.fy) == (10.0, 11.0)


def test_opening_is_transactional(install):
    colour, depth = make_streams(1)
    device = FakeDevice(None, colour, depth, fail_depth=True)
    install(fake_openni2(device))
    with pytest.raises(SensorError, match="depth stream failed"):
        OpenNISource.open("openni://")
    assert colour.closed and device.closed and not colour.started


# --- .oni playback -----------------------------------------------------------------------------


def test_an_oni_file_plays_back_on_the_device_clock_until_its_last_frame(install, tmp_path):
    oni = tmp_path / "capture.oni"
    oni.write_bytes(b"\0")
    colour, depth = make_streams(3)
    device = FakeDevice(None, colour, depth)
    install(fake_openni2(device))

    src = OpenNISource.try_open(oni)
    assert src is not None
    with src:
        frames = list(src.frames())
        assert "OpenNI2 recording" in src.describe() and "3 color frames" in src.describe()
    assert device.uri == str(oni).encode() and device.playback.speed == -1.0
    assert device.playback.repeat is False and colour.mode is None  # recorded modes kept
    assert [f.stamp_ns for f in frames] == [(1_000_000 + i * PERIOD_US) * 1000 for i in range(3)]


# --- pure helpers ------------------------------------------------------------------------------


def test_targets_are_parsed_from_pseudo_paths_and_oni_files():
    assert parse_target("openni://") == OpenNITarget(None, is_file=False)
    assert parse_target(Path("openni://")) == OpenNITarget(None, is_file=False)
    assert parse_target(Path("openni://1d27/0601@1/5")) == OpenNITarget("1d27/0601@1/5", False)
    assert parse_target(Path("openni://freenect://0")) == OpenNITarget("freenect://0", False)
    assert parse_target("run/cap.ONI") == OpenNITarget("run/cap.ONI", is_file=True)
    assert parse_target("run.bag") is None and parse_target(Path("/data/openni")) is None


def test_try_open_ignores_other_paths_without_importing_openni(tmp_path):
    (tmp_path / "x.bag").write_bytes(b"")
    assert OpenNISource.try_open(tmp_path / "x.bag") is None
    assert "openni" not in sys.modules


def test_microsecond_stamps_become_nanoseconds():
    assert stamp_ns(1_234_567) == 1_234_567_000
    assert stamp_ns(2**40, offset_ns=-5) == 2**40 * 1000 - 5


def raw(sensor: str, ts_us: int, pixels: np.ndarray, fmt: int, pad: int = 0) -> RawFrame:
    vf = FakeVideoFrame(ts_us, 0, pixels, fmt, pad)
    return RawFrame(
        sensor,
        ts_us,
        0,
        vf.width,
        vf.height,
        vf.stride,
        fmt,
        np.frombuffer(vf.get_buffer_as_uint8(), dtype=np.uint8).copy(),
    )


def test_frame_formats_convert_to_rgb_and_metres():
    rgb, depth_mm = frame_pixels(0)
    np.testing.assert_array_equal(rgb_from_frame(raw(COLOUR, 0, rgb, RGB888, pad=5)), rgb)
    grey = rgb[..., 0]
    np.testing.assert_array_equal(
        rgb_from_frame(raw(COLOUR, 0, grey, GRAY8)), np.dstack([grey] * 3)
    )
    depth = depth_from_frame(raw(DEPTH, 0, depth_mm, DEPTH_100_UM))
    np.testing.assert_allclose(depth, depth_mm / 10000.0, atol=1e-6)
    with pytest.raises(SensorError, match="colour stream delivers YUV422"):
        rgb_from_frame(raw(COLOUR, 0, rgb[..., :2], YUV422))
    with pytest.raises(SensorError, match="depth stream delivers RGB888"):
        depth_from_frame(raw(DEPTH, 0, rgb, RGB888))


def test_pairer_matches_within_the_window_and_counts_what_it_drops():
    px = np.zeros((1, 1, 3), dtype=np.uint8)
    d = np.zeros((1, 1), dtype=np.uint16)
    pairer = FramePairer(max_difference_ns=20_000_000)
    assert pairer.push(raw(COLOUR, 0, px, RGB888)) is None
    assert pairer.push(raw(COLOUR, 33_000, px, RGB888)) is None  # replaces the unpaired one
    pair = pairer.push(raw(DEPTH, 40_000, d, DEPTH_1_MM))
    assert pair is not None and pair[0].timestamp_us == 33_000
    assert pairer.push(raw(DEPTH, 70_000, d, DEPTH_1_MM)) is None
    assert pairer.push(raw(COLOUR, 100_000, px, RGB888)) is None  # 30 ms apart: depth too old
    assert pairer.skipped == {"unpaired_color": 1, "unpaired_depth": 1}


def test_kinect_field_of_view_gives_the_familiar_focal_length():
    k = intrinsics_from_fov(640, 480, math.radians(62.7), math.radians(48.6), 5000.0)
    assert k.fx == pytest.approx(525.0, abs=1.0) and k.fy == pytest.approx(531.5, abs=0.1)
    assert (k.cx, k.cy) == (319.5, 239.5)
