"""A live OpenNI2 camera (Kinect v1, Asus Xtion, PrimeSense Carmine) or an ``.oni`` recording as a
:class:`~sensors.source.Source`.

Uses the optional PyPI binding ``openni`` (``from openni import openni2``, imported only when a
device or file is opened) over the OpenNI2 runtime library. Live devices stream colour (RGB888) and
depth (1 mm) at 640x480 @ 30 Hz with depth registered to colour
(``IMAGE_REGISTRATION_DEPTH_TO_COLOR``) and depth/colour frame sync on. ``.oni`` files play back
their recorded modes as fast as they are read.

Stamps are the device's hardware timestamps (microseconds, converted to integer nanoseconds). For a
live device they are shifted by one constant, fixed at the first frame, so that frame carries the
host time it arrived: stamps stay jitter-free and monotonic yet compare with host-stamped wheel
readings. ``.oni`` playback keeps the recorded device clock.

Targets: ``path/to/file.oni``, ``openni://`` (the first device) and ``openni://<uri>`` (a device
URI as OpenNI2 lists it, e.g. ``openni://1d27/0601@1/5`` or ``openni://freenect://0``).

Installing (Debian bookworm): ``pip install openni`` for the binding, and
``apt-get install libopenni2-0 libopenni2-dev`` for the runtime. The binding loads the unversioned
``libOpenNI2.so``, which only ``libopenni2-dev`` provides as a symlink (``libopenni2-0`` ships
``libOpenNI2.so.0``). libopenni2-0's drivers (PS1080, PSLink) cover PrimeSense-based cameras (Xtion,
Carmine); a Kinect v1 needs libfreenect's OpenNI2 driver, which Debian's libfreenect packages do
not ship: build libfreenect with ``-DBUILD_OPENNI2_DRIVER=ON`` and copy ``libFreenectDriver.so``
into ``/usr/lib/x86_64-linux-gnu/OpenNI2/Drivers/``.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import re
import sysconfig
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from sensors.config import CameraConfig, SyncConfig
from sensors.source import SourceBase, SourceOptions
from sensors.types import CameraIntrinsics, RgbdFrame, SensorError, seconds_to_ns

log = logging.getLogger(__name__)

ONI_SUFFIX = ".oni"
SCHEME = "openni:"
NS_PER_US = 1000  # [ns/us] OpenNI2 frame timestamps are microseconds
LIVE_MODE = (640, 480, 30)  # [px], [px], [Hz] VGA at the Kinect's full rate
FRAME_TIMEOUT = 2.0  # [s] a live device silent this long is gone
PLAYBACK_AS_FAST_AS_READ = -1.0  # OpenNI2 playback speed: no real-time pacing
LIBRARY = "libOpenNI2.so"  # what the binding dlopens
# OniPixelFormat values from the OpenNI2 C API (OniCTypes.h).
PIXEL_FORMATS = {
    100: "DEPTH_1_MM",
    101: "DEPTH_100_UM",
    102: "SHIFT_9_2",
    103: "SHIFT_9_3",
    200: "RGB888",
    201: "YUV422",
    202: "GRAY8",
    203: "GRAY16",
    204: "JPEG",
    205: "YUYV",
}
DEPTH_UNITS_PER_M = {"DEPTH_1_MM": 1000.0, "DEPTH_100_UM": 10000.0}  # [counts/m]
COLOUR = "color"
DEPTH = "depth"

INSTALL_HELP = (
    "to use an OpenNI2 camera or .oni file: `pip install openni` (Python binding) and "
    "`apt-get install libopenni2-0 libopenni2-dev` (runtime; -dev adds the libOpenNI2.so the "
    "binding loads), or point OPENNI2_REDIST at a folder holding libOpenNI2.so; a Kinect v1 also "
    "needs libfreenect's OpenNI2 driver (not packaged by Debian: build libfreenect with "
    "-DBUILD_OPENNI2_DRIVER=ON and copy libFreenectDriver.so into "
    "/usr/lib/x86_64-linux-gnu/OpenNI2/Drivers/)"
)


@dataclass(frozen=True, eq=False)
class RawFrame:
    """One OpenNI2 video frame, copied out of the driver's buffer."""

    sensor: str  # "color" or "depth"
    timestamp_us: int  # [us] device clock
    index: int  # frame number as the device counts it
    width: int  # [px]
    height: int  # [px]
    stride: int  # [bytes] per row, >= width * bytes per pixel
    pixel_format: int  # OniPixelFormat value (see PIXEL_FORMATS)
    data: np.ndarray  # (stride * height,) uint8


@dataclass(frozen=True)
class OpenNITarget:
    """What to open: a live device (``uri`` None = the first one) or an .oni file."""

    uri: str | None
    is_file: bool


# --- pure helpers ------------------------------------------------------------------------------


def parse_target(path: Path | str) -> OpenNITarget | None:
    """``x.oni`` -> file; ``openni://`` / ``openni://<uri>`` -> device; anything else -> None.

    ``Path`` collapses ``//``, so ``openni://freenect://0`` may arrive as ``openni:/freenect:/0``;
    the scheme separator of such an inner URI is restored.
    """
    text = str(path)
    if text.lower().startswith(SCHEME):
        uri = text[len(SCHEME) :].lstrip("/")
        uri = re.sub(r"^([A-Za-z][A-Za-z0-9+.-]*):/(?!/)", r"\1://", uri)
        return OpenNITarget(uri or None, is_file=False)
    if Path(text).suffix.lower() == ONI_SUFFIX:
        return OpenNITarget(text, is_file=True)
    return None


def stamp_ns(timestamp_us: int, offset_ns: int = 0) -> int:
    """Device timestamp [us] -> integer nanoseconds, plus a clock offset [ns]."""
    return int(timestamp_us) * NS_PER_US + offset_ns


def pixel_format_name(value: int) -> str:
    return PIXEL_FORMATS.get(int(value), f"format {int(value)}")


def _rows(frame: RawFrame, bytes_per_pixel: int) -> np.ndarray:
    """(H, W * bytes_per_pixel) uint8 view of the frame without row padding."""
    row = frame.width * bytes_per_pixel
    if frame.stride < row or frame.data.size < frame.stride * frame.height:
        raise SensorError(
            f"OpenNI2 {frame.sensor} frame {frame.index}: {frame.width}x{frame.height} with stride "
            f"{frame.stride} needs {frame.stride * frame.height} bytes, has {frame.data.size}"
        )
    return frame.data[: frame.stride * frame.height].reshape(frame.height, frame.stride)[:, :row]


def rgb_from_frame(frame: RawFrame) -> np.ndarray:
    """RGB888 (or GRAY8) frame -> HxWx3 uint8 RGB."""
    name = pixel_format_name(frame.pixel_format)
    if name == "RGB888":
        return np.ascontiguousarray(_rows(frame, 3)).reshape(frame.height, frame.width, 3)
    if name == "GRAY8":
        return np.repeat(np.ascontiguousarray(_rows(frame, 1))[..., None], 3, axis=2)
    raise SensorError(f"OpenNI2 colour stream delivers {name}; rgbdnav reads RGB888 or GRAY8")


def depth_from_frame(frame: RawFrame) -> np.ndarray:
    """DEPTH_1_MM / DEPTH_100_UM frame -> HxW float32 [m]; 0 stays 0 (invalid)."""
    name = pixel_format_name(frame.pixel_format)
    units = DEPTH_UNITS_PER_M.get(name)
    if units is None:
        raise SensorError(
            f"OpenNI2 depth stream delivers {name}; rgbdnav reads DEPTH_1_MM or DEPTH_100_UM"
        )
    counts = np.ascontiguousarray(_rows(frame, 2)).view("<u2").reshape(frame.height, frame.width)
    return (counts.astype(np.float32) / np.float32(units)).astype(np.float32)


def intrinsics_from_fov(
    width: int, height: int, hfov_rad: float, vfov_rad: float, depth_scale: float
) -> CameraIntrinsics:
    """Pinhole intrinsics of an ideal camera with these fields of view, centred principal point.

    fx = (W / 2) / tan(hfov / 2); the Kinect v1's 62.7 deg gives fx ~ 525 px at 640 px.
    """
    fx = 0.5 * width / math.tan(0.5 * hfov_rad)
    fy = 0.5 * height / math.tan(0.5 * vfov_rad)
    return CameraIntrinsics(
        width, height, fx, fy, (width - 1) / 2.0, (height - 1) / 2.0, depth_scale
    )


class FramePairer:
    """Pairs each colour frame with a depth frame within ``max_difference_ns`` of device time.

    Keeps only the latest unpaired frame per sensor: a frame replaced before it found a partner
    is counted in ``skipped`` as ``unpaired_color`` / ``unpaired_depth``.
    """

    def __init__(self, max_difference_ns: int) -> None:
        self.max_difference_ns = max_difference_ns
        self.skipped: dict[str, int] = {}
        self._latest: dict[str, RawFrame] = {}

    def _drop(self, sensor: str) -> None:
        if self._latest.pop(sensor, None) is not None:
            key = f"unpaired_{sensor}"
            self.skipped[key] = self.skipped.get(key, 0) + 1

    def push(self, frame: RawFrame) -> tuple[RawFrame, RawFrame] | None:
        """Add a frame; returns (colour, depth) once a pair is complete."""
        self._drop(frame.sensor)
        self._latest[frame.sensor] = frame
        colour, depth = self._latest.get(COLOUR), self._latest.get(DEPTH)
        if colour is None or depth is None:
            return None
        gap_ns = (colour.timestamp_us - depth.timestamp_us) * NS_PER_US
        if abs(gap_ns) <= self.max_difference_ns:
            self._latest.clear()
            return colour, depth
        self._drop(DEPTH if gap_ns > 0 else COLOUR)  # the older one can no longer pair
        return None


def assemble_frame(
    colour: RawFrame, depth: RawFrame, intrinsics: CameraIntrinsics, offset_ns: int
) -> RgbdFrame:
    """A colour/depth pair (depth registered to colour) -> RgbdFrame at the colour stamp."""
    rgb, depth_m = rgb_from_frame(colour), depth_from_frame(depth)
    if rgb.shape[:2] != depth_m.shape:
        raise SensorError(
            f"OpenNI2 colour is {colour.width}x{colour.height} but depth is "
            f"{depth.width}x{depth.height}; both streams must use the same resolution"
        )
    return RgbdFrame(stamp_ns(colour.timestamp_us, offset_ns), rgb, depth_m, intrinsics)


def raw_frame(video_frame: Any, sensor: str) -> RawFrame:
    """Copy an ``openni2.VideoFrame`` (fields of OniFrame) into a :class:`RawFrame`."""
    data = np.array(np.frombuffer(video_frame.get_buffer_as_uint8(), dtype=np.uint8))
    return RawFrame(
        sensor=sensor,
        timestamp_us=int(video_frame.timestamp),
        index=int(video_frame.frameIndex),
        width=int(video_frame.width),
        height=int(video_frame.height),
        stride=int(video_frame.stride),
        pixel_format=int(video_frame.videoMode.pixelFormat),
        data=data,
    )


def library_dirs() -> list[str]:
    """Where to look for libOpenNI2.so: $OPENNI2_REDIST64/$OPENNI2_REDIST, then the system's."""
    dirs = [os.environ[v] for v in ("OPENNI2_REDIST64", "OPENNI2_REDIST") if os.environ.get(v)]
    multiarch = sysconfig.get_config_var("MULTIARCH")
    if multiarch:
        dirs += [f"/usr/lib/{multiarch}", f"/lib/{multiarch}"]
    dirs += ["/usr/local/lib", "/usr/lib", "/lib"]
    return list(dict.fromkeys(dirs))


def _library_hint(dirs: list[str]) -> str:
    versioned = [d for d in dirs if list(Path(d).glob(f"{LIBRARY}.*"))]
    if versioned:
        return (
            f"{versioned[0]} has only a versioned {LIBRARY}.N; the binding loads {LIBRARY} "
            "(apt-get install libopenni2-dev adds it)"
        )
    return f"{LIBRARY} not found in {', '.join(dirs)}"


def load_openni2() -> ModuleType:
    """Import the ``openni`` binding and initialise the runtime, or raise one clear SensorError."""
    try:
        openni2 = importlib.import_module("openni.openni2")
    except ImportError as err:
        raise SensorError(
            f"OpenNI2 is not available: the Python binding 'openni' is not installed; "
            f"{INSTALL_HELP}"
        ) from err
    dirs = library_dirs()
    try:
        openni2.initialize(dirs)
    except (openni2.InitializationError, OSError) as err:
        raise SensorError(
            f"OpenNI2 is not available: the runtime library could not be loaded "
            f"({_library_hint(dirs)}); {INSTALL_HELP}"
        ) from err
    return openni2


# --- the adapter -------------------------------------------------------------------------------


class OpenNISource(SourceBase):
    """A live OpenNI2 device or an .oni recording. Use :meth:`open` or :meth:`try_open`."""

    def __init__(
        self,
        target: OpenNITarget,
        openni2: ModuleType,
        device: Any,
        streams: dict[str, Any],
        resources: ExitStack,
        intrinsics: CameraIntrinsics,
        *,
        registered: bool,
        sync: SyncConfig,
        clock: Callable[[], int],
    ) -> None:
        self.path = str(target.uri) if target.is_file else f"openni://{target.uri or ''}"
        self.skipped: dict[str, int] = {}
        self.target = target
        self.registered = registered
        self._openni2 = openni2
        self._device = device
        self._streams = streams
        self._resources: ExitStack | None = resources
        self._intrinsics = intrinsics
        self._max_difference_ns = seconds_to_ns(sync.slop)
        self._clock = clock

    # --- opening ------------------------------------------------------------------------------

    @classmethod
    def try_open(
        cls, path: Path | str, options: SourceOptions | None = None
    ) -> OpenNISource | None:
        target = parse_target(path)
        camera = options.camera if options else None
        sync = options.sync if options else None
        if target is None:
            return None
        # The live run (realtime) stamps everything on time.monotonic_ns, as the board does.
        clock = time.monotonic_ns if options and options.realtime else time.time_ns
        return cls.open(target, camera=camera, sync=sync, clock=clock)

    @classmethod
    def open(
        cls,
        target: OpenNITarget | Path | str,
        *,
        camera: CameraConfig | None = None,
        sync: SyncConfig | None = None,
        clock: Callable[[], int] = time.time_ns,
    ) -> OpenNISource:
        """Open a device or file; whatever was opened is closed again if a later step fails.

        ``camera`` overrides the intrinsics, which otherwise follow from the colour stream's
        fields of view.
        """
        if not isinstance(target, OpenNITarget):
            parsed = parse_target(target)
            if parsed is None:
                raise SensorError(f"{target}: not an .oni file or openni:// device")
            target = parsed
        what = target.uri if target.is_file else f"OpenNI2 device {target.uri or '(first found)'}"
        openni2 = load_openni2()
        with ExitStack() as resources:
            try:
                device = cls._open_device(openni2, target)
                resources.callback(device.close)
                streams = {}
                for sensor, create in (
                    (COLOUR, device.create_color_stream),
                    (DEPTH, device.create_depth_stream),
                ):
                    stream = create()
                    if stream is None:
                        raise SensorError(f"{what}: has no {sensor} sensor")
                    resources.callback(stream.close)
                    streams[sensor] = stream
                registered = cls._configure(openni2, device, streams, target)
                for stream in streams.values():
                    stream.start()  # VideoStream.close() stops it again
                intrinsics = cls._intrinsics_of(streams[COLOUR], camera)
            except openni2.OpenNIError as err:
                raise SensorError(f"{what}: {err}") from err
            source = cls(
                target,
                openni2,
                device,
                streams,
                resources.pop_all(),
                intrinsics,
                registered=registered,
                sync=sync or SyncConfig(),
                clock=clock,
            )
        return source

    @staticmethod
    def _open_device(openni2: ModuleType, target: OpenNITarget) -> Any:
        try:
            if target.is_file:
                return openni2.Device.open_file(str(target.uri).encode())
            if target.uri is None:
                return openni2.Device.open_any()
            return openni2.Device(target.uri.encode())
        except openni2.OpenNIError as err:
            if target.is_file:
                raise SensorError(f"{target.uri}: OpenNI2 cannot play it: {err}") from err
            raise SensorError(
                f"OpenNI2 found no device {target.uri or ''}({err}); is it plugged in, and is "
                f"its driver installed? {INSTALL_HELP}"
            ) from err

    @staticmethod
    def _configure(
        openni2: ModuleType, device: Any, streams: dict[str, Any], target: OpenNITarget
    ) -> bool:
        """Live: VGA @ 30 Hz, depth registered to colour, frame sync. Returns registration."""
        registration = openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR
        if target.is_file:
            if device.playback is not None:  # None if the driver does not support seeking
                device.playback.set_speed(PLAYBACK_AS_FAST_AS_READ)
                device.playback.set_repeat_enabled(False)
            return bool(device.get_image_registration_mode() == registration)
        width, height, fps = LIVE_MODE
        modes = {COLOUR: openni2.PIXEL_FORMAT_RGB888, DEPTH: openni2.PIXEL_FORMAT_DEPTH_1_MM}
        for sensor, pixel_format in modes.items():
            streams[sensor].set_video_mode(
                openni2.VideoMode(
                    pixelFormat=pixel_format, resolutionX=width, resolutionY=height, fps=fps
                )
            )
        registered = bool(device.is_image_registration_mode_supported(registration))
        if registered:
            device.set_image_registration_mode(registration)
        else:
            log.warning("OpenNI2 device cannot register depth to colour; depth stays unregistered")
        device.set_depth_color_sync_enabled(True)
        return registered

    @staticmethod
    def _intrinsics_of(colour: Any, camera: CameraConfig | None) -> CameraIntrinsics:
        if camera is not None:
            c = camera
            return CameraIntrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.depth_scale)
        mode = colour.get_video_mode()
        return intrinsics_from_fov(
            int(mode.resolutionX),
            int(mode.resolutionY),
            float(colour.get_horizontal_fov()),
            float(colour.get_vertical_fov()),
            CameraConfig().depth_scale,
        )

    def close(self) -> None:
        """Stop the streams and close the device (the OpenNI2 runtime stays loaded)."""
        if self._resources is not None:
            resources, self._resources = self._resources, None
            resources.close()

    # --- Source -------------------------------------------------------------------------------

    def describe(self) -> str:
        k = self._intrinsics
        reg = "depth registered to colour" if self.registered else "depth NOT registered to colour"
        camera = f"camera {k.width}x{k.height} fx={k.fx:.1f} fy={k.fy:.1f} cx={k.cx:g} cy={k.cy:g}"
        if self.target.is_file:
            counts = ", ".join(
                f"{s.get_number_of_frames()} {sensor} frames" for sensor, s in self._streams.items()
            )
            return f"OpenNI2 recording {self.path}, {camera}, {counts}, {reg}"
        info = self._device.get_device_info()
        name = " ".join(_text(getattr(info, f, b"")) for f in ("vendor", "name")).strip()
        return (
            f"OpenNI2 device {_text(getattr(info, 'uri', b''))} ({name or 'unknown'}), {camera}, "
            f"{LIVE_MODE[2]} Hz, {reg}, frame sync on"
        )

    def stream_stamps(self) -> dict[str, np.ndarray]:
        """Nothing is known before reading: a live device (or .oni) has no index of stamps."""
        return {}

    def intrinsics(self) -> CameraIntrinsics | None:
        return self._intrinsics

    def frames(self) -> Iterator[RgbdFrame]:
        """Colour/depth pairs as they arrive; a live device runs until :meth:`close`, an .oni
        file until its last frame. ``skipped`` counts unpaired frames."""
        pairer = FramePairer(self._max_difference_ns)
        self.skipped = pairer.skipped
        offset_ns: int | None = 0 if self.target.is_file else None
        for frame in self._raw_frames():
            pair = pairer.push(frame)
            if pair is None:
                continue
            colour, depth = pair
            if offset_ns is None:  # host time of the first frame, in device-clock terms
                offset_ns = self._clock() - stamp_ns(colour.timestamp_us)
            yield assemble_frame(colour, depth, self._intrinsics, offset_ns)

    def _raw_frames(self) -> Iterator[RawFrame]:
        openni2 = self._openni2
        named = [(sensor, stream) for sensor, stream in self._streams.items()]
        remaining = (
            {s: int(stream.get_number_of_frames()) for s, stream in named}
            if self.target.is_file
            else None
        )
        while self._resources is not None:
            try:
                ready = openni2.wait_for_any_stream([s for _, s in named], FRAME_TIMEOUT)
                if ready is None:
                    if self.target.is_file:
                        return  # playback ran out (frame counts may be approximate)
                    raise SensorError(
                        f"{self.path}: no frames for {FRAME_TIMEOUT:g} s; was the camera unplugged?"
                    )
                sensor = next(s for s, stream in named if stream is ready)
                video_frame = ready.read_frame()
                try:
                    frame = raw_frame(video_frame, sensor)
                finally:
                    video_frame.close()  # hand the driver its buffer back
            except openni2.OpenNIError as err:
                raise SensorError(f"{self.path}: reading frames failed: {err}") from err
            yield frame
            if remaining is not None:
                remaining[sensor] -= 1
                if all(n <= 0 for n in remaining.values()):
                    return


def _text(value: Any) -> str:
    return value.decode(errors="replace") if isinstance(value, bytes) else str(value)
