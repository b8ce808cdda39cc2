"""A Kinect v1 (Xbox 360 model 1414/1473, Kinect for Windows) through libfreenect as a
:class:`~sensors.source.Source`: ``freenect://`` (the first Kinect) or ``freenect://INDEX``.

Uses libfreenect's Python binding ``freenect`` (PyPI source package, built against Debian's
``libfreenect-dev``) and its sync API: colour (RGB, 640x480 @ 30 Hz) and depth registered to colour
in millimetres (``DEPTH_REGISTERED``: libfreenect reprojects depth with the factory calibration the
Kinect stores), so the intrinsics are the colour camera's (``camera`` config, Kinect v1 defaults).
Each call waits for the next frame; a colour frame is paired with the depth frame read after it.

Stamps are host time at arrival (``time.monotonic_ns`` for ``rgbdnav live``, like the board's):
libfreenect's frame timestamps are a 32-bit device counter that wraps and has no host mapping.

Camera pitch: before streaming, the Kinect's accelerometer gives its tilt against the horizon
(``freenect_get_tilt_degs``): ``static_extrinsics`` offers it as ``robot.camera_pitch`` (positive
down), taken as a bag's /tf_static mount is (``rgbdnav.config.camera_mount``): unless the user's
config sets ``robot.camera_pitch``.

Installing (Debian bookworm): ``apt-get install libfreenect-dev`` (library, headers and the udev
rules that let a non-root user open the Kinect) and ``pip install 'rgbdnav[freenect]'``.
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from sensors.config import CameraConfig
from sensors.source import SourceBase, SourceOptions
from sensors.types import CameraIntrinsics, RgbdFrame, SensorError

SCHEME = "freenect:"
MM_PER_M = 1000.0  # [counts/m] DEPTH_REGISTERED is millimetres, 0 = no reading
LIVE_MODE = (640, 480, 30)  # [px], [px], [Hz] the sync API's default (RESOLUTION_MEDIUM)
INSTALL_HELP = "apt-get install libfreenect-dev && pip install 'rgbdnav[freenect]'"
UDEV_HELP = (
    "if it is plugged in (and on its own 12 V supply), a non-root user needs libfreenect's udev "
    "rules: apt-get install libfreenect0.5 (installs /lib/udev/rules.d/60-libfreenect0.5.rules), "
    "then `sudo udevadm control --reload-rules && sudo udevadm trigger` and replug the Kinect"
)


def parse_target(path: Path | str) -> int | None:
    """``freenect://`` -> 0, ``freenect://N`` -> N; anything else -> None."""
    text = str(path)
    if not text.lower().startswith(SCHEME):
        return None
    rest = text[len(SCHEME) :].strip("/")
    if not rest:
        return 0
    if not rest.isdigit():
        raise SensorError(f"{text}: expected freenect:// or freenect://INDEX (0, 1, ...)")
    return int(rest)


def load_freenect() -> ModuleType:
    try:
        return importlib.import_module("freenect")
    except ImportError as err:  # the binding, or libfreenect.so.0.5 it links, is missing
        raise SensorError(
            f"Kinect v1 via libfreenect is not available ({err}): {INSTALL_HELP}"
        ) from err


def pitch_from_tilt(tilt_degs: float) -> float:
    """libfreenect's tilt [deg, positive up] -> robot.camera_pitch [rad, positive down]."""
    return -math.radians(float(tilt_degs))


class FreenectSource(SourceBase):
    """A live Kinect v1 via libfreenect's sync API. Use :meth:`open`."""

    mount_source = "accelerometer"  # what static_extrinsics measures (rgbdnav.config.camera_mount)

    def __init__(
        self,
        fn: ModuleType,
        index: int,
        intrinsics: CameraIntrinsics,
        pitch_rad: float | None,
        clock: Callable[[], int],
    ) -> None:
        self.path = f"freenect://{index}"
        self.skipped: dict[str, int] = {}
        self.index = index
        self.camera_pitch = pitch_rad  # [rad] positive down; None if the tilt was unreadable
        self._fn: ModuleType | None = fn
        self._intrinsics = intrinsics
        self._clock = clock

    @classmethod
    def try_open(
        cls, path: Path | str, options: SourceOptions | None = None
    ) -> FreenectSource | None:
        index = parse_target(path)
        if index is None:
            return None
        realtime = bool(options and options.realtime)
        camera = options.camera if options else None
        return cls.open(index, camera=camera, clock=time.monotonic_ns if realtime else time.time_ns)

    @classmethod
    def open(
        cls,
        index: int = 0,
        *,
        camera: CameraConfig | None = None,
        clock: Callable[[], int] = time.time_ns,
    ) -> FreenectSource:
        fn = load_freenect()
        pitch = cls._read_tilt(fn, index)
        c = camera or CameraConfig()
        intrinsics = CameraIntrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy, MM_PER_M)
        return cls(fn, index, intrinsics, pitch, clock)

    @staticmethod
    def _read_tilt(fn: ModuleType, index: int) -> float | None:
        """Find the Kinect and read its accelerometer tilt; a clear error if there is none."""
        ctx = fn.init()
        if ctx is None:
            raise SensorError(f"libfreenect could not start (no USB access?); {UDEV_HELP}")
        try:
            found = int(fn.num_devices(ctx))
            if found <= index:
                what = "no Kinect v1 found" if found == 0 else f"no Kinect {index} ({found} found)"
                raise SensorError(f"freenect://{index}: {what}; {UDEV_HELP}")
            dev = fn.open_device(ctx, index)
            if dev is None:
                raise SensorError(f"freenect://{index}: cannot open the Kinect; {UDEV_HELP}")
            try:
                fn.update_tilt_state(dev)
                tilt = fn.get_tilt_degs(fn.get_tilt_state(dev))
            finally:
                fn.close_device(dev)
        finally:
            fn.shutdown(ctx)
        return pitch_from_tilt(tilt) if math.isfinite(tilt) else None

    def static_extrinsics(self) -> tuple[dict[str, float], str] | None:
        """The camera mount the Kinect measures: its pitch, and where it came from; None if the
        tilt was unreadable."""
        if self.camera_pitch is None:
            return None
        tilt = -math.degrees(self.camera_pitch)
        return {"camera_pitch": self.camera_pitch}, f"Kinect tilt {tilt:+.1f} deg"

    def close(self) -> None:
        if self._fn is not None:
            fn, self._fn = self._fn, None
            fn.sync_stop()

    def describe(self) -> str:
        k = self._intrinsics
        pitch = (
            f"camera pitch {math.degrees(self.camera_pitch):.1f} deg from the accelerometer "
            f"(robot.camera_pitch={self.camera_pitch:.3f})"
            if self.camera_pitch is not None
            else "camera pitch unreadable"
        )
        return (
            f"Kinect v1 {self.index} via libfreenect, {LIVE_MODE[2]} Hz, depth registered to "
            f"colour (mm); camera {k.width}x{k.height} fx={k.fx:.1f} fy={k.fy:.1f} cx={k.cx:g} "
            f"cy={k.cy:g} from the camera config; {pitch}"
        )

    def stream_stamps(self) -> dict[str, np.ndarray]:
        return {}

    def intrinsics(self) -> CameraIntrinsics | None:
        return self._intrinsics

    def frames(self) -> Iterator[RgbdFrame]:
        while self._fn is not None:
            fn = self._fn
            video = fn.sync_get_video(self.index, fn.VIDEO_RGB)
            stamp = self._clock()
            depth = fn.sync_get_depth(self.index, fn.DEPTH_REGISTERED)
            if video is None or depth is None:
                if self._fn is None:
                    return  # closed while waiting
                raise SensorError(f"{self.path}: the Kinect stopped sending frames (unplugged?)")
            yield self._frame(stamp, video[0], depth[0])

    def _frame(self, stamp_ns: int, rgb: Any, depth_mm: Any) -> RgbdFrame:
        depth_m = (np.asarray(depth_mm, dtype=np.float32) / np.float32(MM_PER_M)).astype(np.float32)
        return RgbdFrame(
            stamp_ns, np.ascontiguousarray(rgb, dtype=np.uint8), depth_m, self._intrinsics
        )
