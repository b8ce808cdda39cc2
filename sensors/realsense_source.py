"""An Intel RealSense camera (D415/D435/D435i/D455) or a RealSense SDK recording as a
:class:`~sensors.source.Source`, through the optional PyPI wheel ``pyrealsense2`` (SDK inside).

Targets: ``realsense://`` (the first camera), ``realsense://SERIAL``, ``realsense://FILE.db3`` /
``.bag`` (RealSense Viewer or ``rs.recorder``; SDK 2.59 writes rosbag2 ``.db3``, older SDKs
rosbag1 ``.bag``). A camera streams colour (RGB8) and depth (Z16) at 640x480 @ 30 Hz, a recording
its recorded streams, through the same code: the colour and depth sensors' frames are paired by
stamp here (a playback not in real time waits for the reader, so no frame is lost) and depth is
aligned to colour with ``rs.align``. Intrinsics are the colour stream's, depth units
the ``depth_units`` option, extrinsics the device's (or recording's); ``describe`` says so.

Stamps: live (``SourceOptions.realtime``) device stamps are shifted by a constant, fixed at the
first frame, onto the live run's clock (``time.monotonic_ns``, as the board's). A recording then
plays in real time (paced here: the SDK's real-time playback drops frames and gyro samples),
stamped the same way: the live run cannot tell it from a camera. Offline, a
recording plays as fast as it is read with its recorded clock, and a camera's ``global_time``
stamps (D400 default: host wall time) are kept.

The D435i/D455 gyro is the IMU (yaw rate -gyro_y; the IMU frame is x right, y down, z forward).
Offline, ``imu()`` reads a recording's gyro in a second pass. Live, the motion sensor (if any;
D415/D435 have none) streams beside colour and depth into :meth:`take_imu`, stamped as the frames.

Installing: ``pip install 'rgbdnav[realsense]'``; for a non-root user on Linux, librealsense's udev
rules (``99-realsense-libusb.rules``) must be installed, see docs/guide.md.
"""

from __future__ import annotations

import atexit
import importlib
import itertools
import logging
import math
import queue
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from sensors.config import SyncConfig
from sensors.source import ImuStream, SourceBase, SourceOptions
from sensors.types import CameraIntrinsics, RgbdFrame, SensorError, seconds_to_ns

GYRO_FPS = 200  # [Hz] the D435i/D455 gyro rate taken when the motion sensor offers several

log = logging.getLogger(__name__)

SCHEME = "realsense:"
FRAME_QUEUE = 4  # [frames] colour and depth frames between librealsense's threads and frames()
RECORDING_SUFFIXES = (".db3", ".bag")
LIVE_MODE = (640, 480, 30)  # [px], [px], [Hz]
FRAME_TIMEOUT_MS = 2000  # [ms] a camera silent this long is gone
PLAYBACK_STALL_MS = 30_000  # [ms] a playback "playing" yet silent this long is taken as ended
NS_PER_MS = 1_000_000  # [ns/ms] librealsense stamps are milliseconds
GYRO_POLL_MS = 50  # [ms] read_gyro looks at its samples this often
GYRO_SETTLE_MS = 200  # [ms] and takes a stopped playback as ended after this long without one
GYRO_QUEUE = 10 * GYRO_FPS  # [samples] live gyro held between two take_imu() (10 s)
# librealsense colour formats -> channel order to RGB
COLOUR_FORMATS = {"rgb8": [0, 1, 2], "bgr8": [2, 1, 0], "rgba8": [0, 1, 2], "bgra8": [2, 1, 0]}
UDEV_HELP = (
    "without librealsense's udev rules only root can open the camera: `sudo curl -o "
    "/etc/udev/rules.d/99-realsense-libusb.rules https://raw.githubusercontent.com/IntelRealSense/"
    "librealsense/master/config/99-realsense-libusb.rules && sudo udevadm control --reload-rules "
    "&& sudo udevadm trigger`, then replug the camera"
)
INSTALL_HELP = "pip install 'rgbdnav[realsense]' (or pip install pyrealsense2)"


@dataclass(frozen=True)
class RealSenseTarget:
    """A camera (``serial`` None = the first one) or a recording file."""

    serial: str | None = None
    file: Path | None = None


def parse_target(path: Path | str) -> RealSenseTarget | None:
    """``realsense://``, ``realsense://SERIAL``, ``realsense://FILE.db3|.bag``; else None."""
    text = str(path)
    if not text.lower().startswith(SCHEME):
        return None
    rest = text[len(SCHEME) :]
    if Path(rest).suffix.lower() in RECORDING_SUFFIXES:
        if rest.startswith("//"):
            return RealSenseTarget(file=Path(rest[2:]))
        # realsense:/a/b.db3 (Path collapsed "//"): absolute if that exists, else relative
        absolute = Path(rest)
        return RealSenseTarget(file=absolute if absolute.exists() else Path(rest.lstrip("/")))
    return RealSenseTarget(serial=rest.strip("/") or None)


def load_pyrealsense2() -> ModuleType:
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as err:
        raise SensorError(f"RealSense needs the pyrealsense2 wheel: {INSTALL_HELP}") from err


def depth_to_metres(counts: np.ndarray, depth_units: float) -> np.ndarray:
    """Z16 counts -> float32 [m]; 0 stays 0 (invalid)."""
    return (counts.astype(np.float32) * np.float32(depth_units)).astype(np.float32)


def host_offset_ns(stamp_ms: float, host_ns: int) -> int:
    """Constant that maps a device stamp [ms] onto the host clock at one frame."""
    return host_ns - round(stamp_ms * NS_PER_MS)


def _stamp_ns(stamp_ms: float, offset_ns: int) -> int:
    return round(stamp_ms * NS_PER_MS) + offset_ns


def _info(rs: ModuleType, device: Any, field: str) -> str:
    info = getattr(rs.camera_info, field)
    return str(device.get_info(info)) if device.supports(info) else "?"


def _describe_extrinsics(rotation: Sequence[float], translation: Sequence[float]) -> str:
    r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    angle = np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))
    t = ", ".join(f"{v * 1000.0:+.1f}" for v in translation)
    return f"translation ({t}) mm, rotation {angle:.2f} deg"


def yaw_rate(motion: Any) -> float:
    """A gyro motion frame's yaw rate [rad/s] about "up": -gyro_y (the IMU's y points down)."""
    return -float(motion.get_motion_data().y)


def gyro_sensor(rs: ModuleType, device: Any) -> tuple[Any, Any] | None:
    """(motion sensor, gyro profile) of a D435i/D455 or a recording holding a gyro; None for a
    device without a motion module (D415/D435) or a recording without a gyro stream."""
    for sensor in device.query_sensors():
        gyros = [p for p in sensor.get_stream_profiles() if p.stream_type() == rs.stream.gyro]
        if gyros:
            return sensor, min(gyros, key=lambda p: abs(p.fps() - GYRO_FPS))
    return None


class GyroSamples:
    """Gyro motion frames as librealsense's thread delivers them (a deque append is
    thread-safe) -> :class:`ImuStream` yaw rates on the device clock, in stamp order.

    Live (``rs`` given) the samples go to librealsense's own ``frame_queue`` (GYRO_QUEUE deep)
    and are converted in :meth:`take`: the motion sensor's thread, which holds one sample at a
    time, never waits for the GIL (held by the live run's VO) to hand it over. :meth:`sink` is
    what the sensor is started with."""

    def __init__(self, rs: ModuleType | None = None) -> None:
        self._samples: deque[tuple[int, float]] = deque()  # (device stamp [ns], yaw rate)
        self._queue = rs.frame_queue(GYRO_QUEUE, keep_frames=True) if rs is not None else None

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def sink(self) -> Any:
        """The sensor's frame callback: the frame queue, else :meth:`on_frame`."""
        return self._queue if self._queue is not None else self.on_frame

    def on_frame(self, frame: Any) -> None:
        motion = frame.as_motion_frame()
        if motion:
            self._samples.append((round(motion.get_timestamp() * NS_PER_MS), yaw_rate(motion)))

    def take(self) -> ImuStream:
        """The samples that arrived since the last call."""
        if self._queue is not None:
            while frame := self._queue.poll_for_frame():
                self.on_frame(frame)
        got = [self._samples.popleft() for _ in range(len(self._samples))]
        stamps = np.array([t for t, _ in got], dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        return ImuStream(stamps[order], np.array([r for _, r in got], dtype=np.float64)[order])


def load_recording(rs: ModuleType, file: Path) -> Any:
    """An SDK recording's playback device, played as fast as it is read: librealsense's
    real-time playback reads ahead and drops a frame or gyro sample whenever a sensor's
    one-deep dispatch queue is still full (a third to a half of a 200 Hz gyro, more under
    load), so a recording played live is paced by the reader instead (``RealSenseSource``).
    Set before streaming: a playback starts in real time."""
    try:
        device = rs.context().load_device(str(file))
    except RuntimeError as err:
        raise SensorError(f"{file}: RealSense SDK cannot read it: {err}") from err
    device.as_playback().set_real_time(False)
    return device


def start_sensors(playback: Any, starts: Sequence[tuple[Any, Callable[[Any], None]]]) -> None:
    """Start opened sensors with their frame callbacks. A playback starts reading when its first
    sensor starts and silently drops the frames of a sensor not started yet (under load, or while
    the first sensor's callbacks hold the GIL, the first colour frames): so it is paused while
    they start, then resumed, which rewinds it to its start with every sensor listening."""
    if playback is not None:
        playback.pause()  # paused: the one read at start is dropped, resume() reads it again
    for sensor, callback in starts:
        sensor.start(callback)
    if playback is not None:
        playback.resume()


def playback_ended(rs: ModuleType, playback: Any, silent_ms: int, where: str) -> bool:
    """Whether a playback that has delivered nothing for ``silent_ms`` is over: it stopped
    playing, or it still says "playing" but has been silent for PLAYBACK_STALL_MS (shorter
    silences are a loaded machine keeping the reader waiting)."""
    if playback.current_status() != rs.playback_status.playing:
        return True
    if silent_ms >= PLAYBACK_STALL_MS:
        log.warning("%s: playback silent for %d s: ended", where, silent_ms // 1000)
        return True
    return False


def _pick_streams(rs: ModuleType, device: Any, *, live: bool, where: str) -> dict[Any, Any]:
    """{rs.stream.color / .depth: (sensor, profile)}: a camera's LIVE_MODE rgb8 / z16 profiles,
    a recording's recorded streams; a clear error if one is missing."""
    width, height, fps = LIVE_MODE
    want = {rs.stream.color: rs.format.rgb8, rs.stream.depth: rs.format.z16}
    found: dict[Any, Any] = {}
    for sensor in device.query_sensors():
        for p in sensor.get_stream_profiles():
            kind = p.stream_type()
            if kind not in want or kind in found:
                continue
            if live:
                v = p.as_video_stream_profile()
                if (p.format(), v.width(), v.height(), p.fps()) != (want[kind], width, height, fps):
                    continue
            found[kind] = (sensor, p)
    missing = [str(k).rsplit(".", 1)[-1] for k in want if k not in found]
    if missing:
        what = f"{width}x{height} @ {fps} Hz " if live else ""
        raise SensorError(f"{where}: no {what}{' or '.join(missing)} stream (rgbdnav needs both)")
    return found


class FramePairing:
    """Colour and depth frames, as the two sensors deliver them, into pairs: each colour frame
    once, with the latest depth frame within ``max_gap_ns`` of it; a colour frame replaced
    before one came is skipped (``unpaired_color``)."""

    def __init__(self, max_gap_ns: int) -> None:
        self.max_gap_ns = max_gap_ns
        self.colour: Any = None  # the latest colour frame not paired yet
        self.depth: Any = None  # the latest depth frame
        self._skips: dict[str, int] = {}

    def add(self, colour: Any, depth: Any) -> tuple[Any, Any] | None:
        """A colour or a depth frame (the other None), or both; a new (colour, depth) or None."""
        if colour:
            if self.colour is not None:
                self._skips["unpaired_color"] = self._skips.get("unpaired_color", 0) + 1
            self.colour = colour
        if depth:
            self.depth = depth
        if self.colour is None or self.depth is None:
            return None
        gap_ms = abs(self.colour.get_timestamp() - self.depth.get_timestamp())
        if gap_ms * NS_PER_MS > self.max_gap_ns:
            return None  # the depth frame for this colour frame may come next
        pair, self.colour = (self.colour, self.depth), None
        return pair

    def take_skips(self) -> dict[str, int]:
        skips, self._skips = self._skips, {}
        return skips


_UNREAD = object()  # RealSenseSource's gyro before it is read
# Sources not closed yet. librealsense's threads calling into an interpreter that is shutting
# down abort or segfault it (a failed test's source, a Ctrl-C): they are closed at exit.
_OPEN: weakref.WeakSet[RealSenseSource] = weakref.WeakSet()


@atexit.register
def _close_open_sources() -> None:
    for src in list(_OPEN):
        src.close()


class RealSenseSource(SourceBase):
    """A camera or an SDK recording, depth aligned to colour. Use :meth:`open`."""

    def __init__(
        self,
        rs: ModuleType,
        target: RealSenseTarget,
        device: Any,
        streams: dict[Any, tuple[Any, Any]],
        *,
        realtime: bool,
        clock: Callable[[], int],
        max_difference_ns: int,
    ) -> None:
        """``streams``: {rs.stream.color / .depth: (sensor, profile)} to stream (not started)."""
        self.path = f"realsense://{target.file or target.serial or ''}"
        self.skipped: dict[str, int] = {}
        self.target = target
        self._rs = rs
        self._sensors: list[Any] = []  # started, stopped by close()
        _OPEN.add(self)
        # Colour and depth frames from the sensors' threads; None once closed.
        self._frames_q: queue.Queue[Any] | None = queue.Queue(FRAME_QUEUE)
        self._closing = threading.Event()
        self._realtime = realtime
        # A recording played live: (first device stamp [ms], host time [ns]) its frames are
        # delivered on, set by the first frame (see load_recording).
        self._pace = realtime and target.file is not None
        self._pace_base: tuple[float, int] | None = None
        self._pace_lock = threading.Lock()
        self._clock = clock
        self._max_difference_ns = max_difference_ns
        # [ns] added to device stamps to give the frames' (fixed at the first frame): the live
        # run moves the recording's gyro onto its clock with it (slam.front_end.MessageFeed).
        self.stamp_offset_ns = 0
        self._gyro: ImuStream | None | object = _UNREAD  # imu(): read once
        self._gyro_samples = GyroSamples(rs)  # live (realtime): the streaming gyro
        self._gyro_sensor: Any = None
        gyro = gyro_sensor(rs, device)
        self.gyro_fps = int(gyro[1].fps()) if gyro is not None else 0  # [Hz] 0: no IMU
        self.device_name = _info(rs, device, "name")
        self.serial = _info(rs, device, "serial_number")
        self._playback = device.as_playback() if target.file is not None else None
        colour = streams[rs.stream.color][1].as_video_stream_profile()
        depth = streams[rs.stream.depth][1].as_video_stream_profile()
        k = colour.get_intrinsics()
        sensor = device.first_depth_sensor()
        has_units = sensor.supports(rs.option.depth_units)
        units = float(sensor.get_option(rs.option.depth_units)) if has_units else 0.001
        self.depth_units = units  # [m/count]
        self.depth_units_from = "depth_units option" if has_units else "(no option: 1 mm assumed)"
        self._intrinsics = CameraIntrinsics(
            int(k.width),
            int(k.height),
            float(k.fx),
            float(k.fy),
            float(k.ppx),
            float(k.ppy),
            1.0 / units,
        )
        ex = depth.get_extrinsics_to(colour)
        self.extrinsics = (tuple(ex.rotation), tuple(ex.translation))  # depth -> colour
        self._align = rs.align(rs.stream.color)
        self._colour_format = str(colour.format()).rsplit(".", 1)[-1]
        if self._colour_format not in COLOUR_FORMATS or depth.format() != rs.format.z16:
            raise SensorError(
                f"{self.path}: colour is {self._colour_format}, depth {depth.format()}; rgbdnav "
                f"reads colour as {', '.join(COLOUR_FORMATS)} and depth as z16"
            )
        where = "the recording" if target.file is not None else "the camera"
        self.origins = {
            "intrinsics": f"{where}'s colour stream",
            "depth_units": f"{where}'s {self.depth_units_from}",
            "extrinsics": f"{where}'s depth-to-colour calibration",
        }
        # A colour/depth pair is composed into one frameset for rs.align (_compose).
        self._pair: list[Any] = []
        self._composer = rs.processing_block(
            lambda _f, source: source.frame_ready(source.allocate_composite_frame(self._pair))
        )
        self._composed = rs.frame_queue(1)
        self._composer.start(self._composed)
        # Colour and depth sensors into _frames_q; the gyro (live) beside them.
        by_sensor: dict[int, tuple[Any, list[Any]]] = {}
        for sensor, profile in streams.values():
            by_sensor.setdefault(id(sensor), (sensor, []))[1].append(profile)
        self.gyro_streams = realtime and gyro is not None  # take_imu() delivers it
        try:
            for sensor, profiles in by_sensor.values():
                sensor.open(profiles)
                self._sensors.append(sensor)
            if self.gyro_streams:
                assert gyro is not None
                gyro[0].open(gyro[1])
                self._gyro_sensor = gyro[0]
            starts = [(sensor, self._on_frame) for sensor in self._sensors]
            if self._gyro_sensor is not None:
                starts.append((self._gyro_sensor, self._gyro_samples.sink))
            start_sensors(self._playback, starts)
        except RuntimeError:
            self.close()
            raise

    @property
    def imu_note(self) -> str:
        """The IMU in one phrase, for ``info`` and the live summary."""
        if self.gyro_fps:
            return f"gyro {self.gyro_fps} Hz as imu0"
        what = "recording has no gyro stream" if self.target.file else "camera has no motion module"
        return f"no IMU (the {what})"

    # --- opening ------------------------------------------------------------------------------

    @classmethod
    def try_open(
        cls, path: Path | str, options: SourceOptions | None = None
    ) -> RealSenseSource | None:
        target = parse_target(path)
        realtime = bool(options and options.realtime)
        sync = (options.sync if options else None) or SyncConfig()
        if target is None:
            return None
        return cls.open(
            target,
            realtime=realtime,
            clock=time.monotonic_ns if realtime else time.time_ns,
            max_difference_ns=seconds_to_ns(sync.slop),
        )

    @classmethod
    def open(
        cls,
        target: RealSenseTarget | str,
        *,
        realtime: bool = False,
        clock: Callable[[], int] = time.time_ns,
        max_difference_ns: int = seconds_to_ns(SyncConfig().slop),
    ) -> RealSenseSource:
        if not isinstance(target, RealSenseTarget):
            parsed = parse_target(target)
            if parsed is None:
                raise SensorError(f"{target}: not a realsense:// camera or recording")
            target = parsed
        if target.file is not None and not target.file.is_file():
            raise SensorError(f"{target.file}: no such RealSense recording")
        rs = load_pyrealsense2()
        if target.file is not None:
            device = load_recording(rs, target.file)
            where = f"{target.file}"
        else:
            device = cls._find_camera(rs, rs.context(), target.serial)
            where = f"RealSense camera {_info(rs, device, 'serial_number')}"
        streams = _pick_streams(rs, device, live=target.file is None, where=where)
        try:
            return cls(
                rs,
                target,
                device,
                streams,
                realtime=realtime,
                clock=clock,
                max_difference_ns=max_difference_ns,
            )
        except RuntimeError as err:
            hint = UDEV_HELP if "permission" in str(err).lower() else "is another program using it?"
            what = "cannot play it" if target.file is not None else f"cannot start it; {hint}"
            raise SensorError(f"{where}: RealSense SDK {what} ({err})") from err

    @staticmethod
    def _find_camera(rs: ModuleType, ctx: Any, serial: str | None) -> Any:
        devices = list(ctx.query_devices())
        serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
        if not serials:
            raise SensorError(
                "no RealSense camera found: is it plugged into a USB 3 port? On Linux, " + UDEV_HELP
            )
        if serial is None:
            return devices[0]
        if serial not in serials:
            raise SensorError(
                f"no RealSense camera with serial {serial}; connected: {', '.join(serials)}"
            )
        return devices[serials.index(serial)]

    def close(self) -> None:
        """Stop and close the sensors (again: nothing); at exit for a source left open."""
        _OPEN.discard(self)
        sensors = [self._gyro_sensor] if self._gyro_sensor is not None else []
        sensors += self._sensors
        self._gyro_sensor, self._sensors, self._frames_q = None, [], None
        self._closing.set()  # a callback waiting on a full queue returns
        for sensor in sensors:
            try:
                sensor.stop()
            except RuntimeError:
                pass  # opened, never started (opening failed part-way)
            sensor.close()

    # --- Source -------------------------------------------------------------------------------

    def describe(self) -> str:
        k = self._intrinsics
        what = (
            f"RealSense SDK recording {self.target.file} ({self.device_name})"
            if self.target.file is not None
            else f"RealSense {self.device_name} serial {self.serial}, {LIVE_MODE[2]} Hz"
        )
        return (
            f"{what}, depth aligned to colour; camera {k.width}x{k.height} fx={k.fx:.1f} "
            f"fy={k.fy:.1f} cx={k.cx:g} cy={k.cy:g} from {self.origins['intrinsics']}; "
            f"depth units {self.depth_units * 1000.0:g} mm from {self.origins['depth_units']}; "
            f"depth-to-colour extrinsics {_describe_extrinsics(*self.extrinsics)} from "
            f"{self.origins['extrinsics']}; {self.imu_note}"
        )

    def stream_stamps(self) -> dict[str, np.ndarray]:
        """Nothing is known before reading: a camera (or a recording played back) has no index."""
        return {}

    def intrinsics(self) -> CameraIntrinsics | None:
        return self._intrinsics

    def frames(self) -> Iterator[RgbdFrame]:
        """Aligned colour/depth pairs until :meth:`close` (camera) or the recording's end."""
        rs = self._rs
        offset_ns: int | None = None
        pairing = FramePairing(self._max_difference_ns)
        colour_kind = rs.stream.color
        silent_ms = 0  # [ms] waited for a frame so far
        while (frames_q := self._frames_q) is not None:
            try:
                frame = frames_q.get(timeout=FRAME_TIMEOUT_MS / 1000)
                silent_ms = 0
            except queue.Empty:
                silent_ms += FRAME_TIMEOUT_MS
                if self._frames_q is None:
                    return  # closed while waiting
                if self._playback is not None:
                    if playback_ended(rs, self._playback, silent_ms, self.path):
                        return
                    continue
                raise SensorError(
                    f"{self.path}: no frames for {FRAME_TIMEOUT_MS / 1000:g} s; was the camera "
                    "unplugged?"
                ) from None
            is_colour = frame.get_profile().stream_type() == colour_kind
            pair = pairing.add(frame if is_colour else None, None if is_colour else frame)
            for reason, n in pairing.take_skips().items():
                self.skipped[reason] = self.skipped.get(reason, 0) + n
            if pair is None:
                continue
            aligned = self._align.process(self._compose(*pair))
            colour, depth = aligned.get_color_frame(), aligned.get_depth_frame()
            stamp_ms = float(colour.get_timestamp())
            if offset_ns is None:
                global_time = rs.timestamp_domain.global_time
                if self._realtime:  # the live run's clock: monotonic host time
                    keep = False
                elif self._playback is not None:  # offline: the recorded clock
                    keep = True
                else:  # global_time is host wall time already
                    keep = colour.get_frame_timestamp_domain() == global_time
                offset_ns = 0 if keep else host_offset_ns(stamp_ms, self._clock())
                self.stamp_offset_ns = offset_ns
            channels = COLOUR_FORMATS[self._colour_format]
            rgb = np.ascontiguousarray(np.asanyarray(colour.get_data())[..., channels])
            counts = np.asanyarray(depth.get_data())
            yield RgbdFrame(
                _stamp_ns(stamp_ms, offset_ns),
                rgb,
                depth_to_metres(counts, self.depth_units),
                self._intrinsics,
            )

    def _compose(self, colour: Any, depth: Any) -> Any:
        """One frameset of a colour and a depth frame (from two framesets maybe), for rs.align."""
        self._pair = [colour, depth]
        self._composer.invoke(colour)
        return self._composed.wait_for_frame().as_frameset()

    def _on_frame(self, frame: Any) -> None:
        """librealsense's threads: a colour or depth frame. Offline it waits while the queue is
        full, so a playback not in real time waits for the reader; live a frame the reader has
        no room for is dropped (``queue_full``), as a camera's. A recording played live is
        delivered at its recorded pace: the playback (not in real time) waits meanwhile."""
        if self._pace and not self._wait_until_due(frame.get_timestamp()):
            return  # closed while waiting
        while not self._closing.is_set() and (frames_q := self._frames_q) is not None:
            try:
                frames_q.put(
                    frame, timeout=None if self._realtime else 0.1, block=not self._realtime
                )
                return
            except queue.Full:
                if self._realtime:
                    self.skipped["queue_full"] = self.skipped.get("queue_full", 0) + 1
                    return

    def _wait_until_due(self, stamp_ms: float) -> bool:
        """Sleep until a frame's recorded time, counted from the first frame's arrival; False
        if closed meanwhile."""
        with self._pace_lock:
            if self._pace_base is None:
                self._pace_base = (stamp_ms, time.monotonic_ns())
            base_ms, base_ns = self._pace_base
        wait_ns = base_ns + round((stamp_ms - base_ms) * NS_PER_MS) - time.monotonic_ns()
        return not (wait_ns > 0 and self._closing.wait(wait_ns / 1e9))

    def take_imu(self) -> ImuStream:
        """Live: the gyro samples (yaw rates) that arrived since the last call, on the device
        clock (``stamp_offset_ns`` moves them onto the frames'), as the camera delivers them."""
        return self._gyro_samples.take()

    def imu(self) -> ImuStream | None:
        """A recording's gyro as yaw rate, read in a second pass, once; None without one, and
        live (the gyro streams: :meth:`take_imu`)."""
        if self.target.file is None or self.gyro_streams:
            return None
        if self._gyro is _UNREAD:
            self._gyro = read_gyro(self._rs, self.target.file)
        return self._gyro  # type: ignore[return-value]


def read_gyro(rs: ModuleType, file: Path) -> ImuStream | None:
    """A recording's gyro stream as yaw rates (-gyro_y), as fast as it reads; None without one.
    The same playback, gyro callback and end-of-playback test as the frame reader's."""
    try:
        device = load_recording(rs, file)
    except SensorError:
        return None
    found = gyro_sensor(rs, device)
    if found is None:
        return None
    sensor, profile = found
    playback, samples = device.as_playback(), GyroSamples()
    sensor.open(profile)
    try:
        start_sensors(playback, [(sensor, samples.on_frame)])
        silent_ms, seen = 0, 0
        while True:
            time.sleep(GYRO_POLL_MS / 1000)
            if len(samples) != seen:
                seen, silent_ms = len(samples), 0
                continue
            silent_ms += GYRO_POLL_MS
            if silent_ms >= GYRO_SETTLE_MS and playback_ended(rs, playback, silent_ms, str(file)):
                break
    finally:
        sensor.stop()
        sensor.close()
    imu = samples.take()
    return imu if len(imu.stamps_ns) else None


# --- writing SDK recordings (librealsense's software device) -----------------------------------


def write_sdk_recording(
    path: Path,
    frames: Iterable[RgbdFrame],
    *,
    depth_units: float = 0.001,
    depth_to_colour_m: Sequence[float] = (0.0, 0.0, 0.0),
    gyro: ImuStream | None = None,
    pace: bool = False,
) -> int:
    """Record RGB-D frames as a RealSense SDK recording (``.db3``), as ``rs.recorder`` writes a
    camera's, with no camera attached: a software device streams them with the frames' own
    intrinsics (colour and depth), ``depth_units`` [m/count] and a depth-to-colour translation.
    Device stamps are the frames' stamps; ``pace`` sleeps between frames so the recorded capture
    times (what real-time playback follows) keep the frames' spacing. ``gyro`` adds a D435i-style
    200 Hz gyro stream holding the yaw rates (as -gyro_y). Returns the frame count."""
    rs = load_pyrealsense2()
    frames = iter(frames)
    first = next(frames, None)
    if first is None:
        raise SensorError(f"{path}: no frames to record")
    k = first.intrinsics
    device = rs.software_device()
    sensors, profiles = {}, {}
    for uid, (name, stream, fmt, bpp) in enumerate(
        (
            ("Depth", rs.stream.depth, rs.format.z16, 2),
            ("Color", rs.stream.color, rs.format.rgb8, 3),
        )
    ):
        intr = rs.intrinsics()
        intr.width, intr.height, intr.fx, intr.fy = k.width, k.height, k.fx, k.fy
        intr.ppx, intr.ppy, intr.model, intr.coeffs = k.cx, k.cy, rs.distortion.none, [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height = stream, 0, uid, k.width, k.height
        vs.fps, vs.bpp, vs.fmt, vs.intrinsics = LIVE_MODE[2], bpp, fmt, intr
        sensors[name] = device.add_sensor(name)
        profiles[name] = sensors[name].add_video_stream(vs)
    if gyro is not None:
        ms = rs.motion_stream()
        ms.type, ms.index, ms.uid, ms.fps, ms.fmt = (
            rs.stream.gyro,
            0,
            2,
            200,
            rs.format.motion_xyz32f,
        )
        ms.intrinsics = rs.motion_device_intrinsic()
        sensors["Motion Module"] = device.add_sensor("Motion Module")
        profiles["Motion Module"] = sensors["Motion Module"].add_motion_stream(ms)
    sensors["Depth"].add_read_only_option(rs.option.depth_units, depth_units)
    ex = rs.extrinsics()
    ex.rotation, ex.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], list(depth_to_colour_m)
    profiles["Depth"].register_extrinsics_to(profiles["Color"], ex)
    device.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(path), device)
    queue = rs.frame_queue(64)
    for name in sensors:
        sensors[name].open(profiles[name])
        sensors[name].start(queue)
    count, t0_ns, wall0 = 0, first.stamp_ns, time.monotonic()
    n_gyro = 0

    def wait_until(stamp_ns: int) -> None:
        if pace:
            time.sleep(max(0.0, (stamp_ns - t0_ns) / 1e9 - (time.monotonic() - wall0)))

    def send_gyro(until_ns: float) -> None:
        nonlocal n_gyro
        while (
            gyro is not None and n_gyro < len(gyro.stamps_ns) and gyro.stamps_ns[n_gyro] <= until_ns
        ):
            wait_until(int(gyro.stamps_ns[n_gyro]))  # a burst would be lost in real-time playback
            f = rs.software_motion_frame()
            v = rs.vector()
            v.x, v.y, v.z = 0.0, -float(gyro.gyro_z[n_gyro]), 0.0
            f.data, f.timestamp = v, int(gyro.stamps_ns[n_gyro]) / NS_PER_MS
            f.domain, f.frame_number = rs.timestamp_domain.hardware_clock, n_gyro
            f.profile = profiles["Motion Module"].as_motion_stream_profile()
            sensors["Motion Module"].on_motion_frame(f)
            n_gyro += 1

    try:
        for frame in itertools.chain((first,), frames):
            send_gyro(frame.stamp_ns)
            wait_until(frame.stamp_ns)
            counts = np.round(np.nan_to_num(frame.depth_m, nan=0.0) / depth_units)
            pixels = {
                "Depth": np.clip(counts, 0, 65535).astype(np.uint16),
                "Color": np.ascontiguousarray(frame.rgb, dtype=np.uint8),
            }
            for name, bpp in (("Depth", 2), ("Color", 3)):
                f = rs.software_video_frame()
                f.pixels, f.bpp, f.stride = pixels[name], bpp, k.width * bpp
                f.timestamp, f.frame_number = frame.stamp_ns / NS_PER_MS, count
                f.domain = rs.timestamp_domain.hardware_clock
                f.profile = profiles[name].as_video_stream_profile()
                if name == "Depth":
                    f.depth_units = depth_units
                sensors[name].on_video_frame(f)
            while queue.poll_for_frame():
                pass  # the recorder has it; keep the queue from filling
            count += 1
        send_gyro(math.inf)
    finally:
        for sensor in sensors.values():
            sensor.stop()
            sensor.close()
        del recorder  # closes the file
    return count
