"""Our recording format: a TUM RGB-D style folder.

```
rgb.txt, depth.txt   TUM index files: "timestamp filename" lines after "#" comments
rgb/*.png            8-bit colour (BGR on disk, as OpenCV writes it; RGB in memory)
depth/*.png          16-bit depth, depth_scale counts per metre (5000 by default), 0 = invalid
wheels.txt           "t left right", cumulative integer encoder counts
imu.txt              optional, "t gyro_z" [rad/s]
gps.txt              optional, "t latitude longitude altitude sigma_h" (sensors/gps.py)
groundtruth.txt      optional, TUM "t tx ty tz qx qy qz qw": base_link in the world, planar
scene.yaml           free-form dict; "camera:" holds the intrinsics
```
:class:`RecordingWriter` builds a folder in a staging directory and commits it atomically;
:class:`Recording` reads one back.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import cv2
import numpy as np
import yaml

from sensors.atomic import atomic_write_text, commit_staging_dir, make_staging_dir
from sensors.gps import GPS_TXT, GpsStream, read_gps_txt, write_gps_txt
from sensors.images import ImageError, check_image_file, decoded_ahead, read_image
from sensors.safe_yaml import read_yaml
from sensors.tum import (
    load_trajectory,
    read_stamped_text,
    write_tum_trajectory,
    yaw_from_quaternion,
)
from sensors.types import (
    NO_RGB,
    CameraIntrinsics,
    RgbdFrame,
    SensorError,
    format_stamp,
)

log = logging.getLogger(__name__)
T = TypeVar("T")

DEFAULT_MAX_DIFFERENCE_NS = 20_000_000  # [ns] rgb/depth association window (TUM associate.py)
PNG_COMPRESSION = 1  # fast zlib level: recording speed matters more than disk here
UINT16_MAX = np.iinfo(np.uint16).max
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "depth_scale")
FOLDER_CONTENTS = (
    "a recording folder holds rgb.txt, depth.txt, scene.yaml, rgb/ and depth/ "
    "(optionally wheels.txt, imu.txt, groundtruth.txt)"
)


# --- pure helpers ------------------------------------------------------------------------------


def depth_to_counts(
    depth_m: np.ndarray, depth_scale: float, out: np.ndarray | None = None
) -> np.ndarray:
    """Depth [m] -> uint16 counts; NaN, <= 0 and values beyond the uint16 range become 0.
    ``out``: a uint16 array of the image's shape to write them into (a shared frame slot).

    In place on one float64 buffer: 1.2 -> 0.8 ms a rendered frame against isfinite + where,
    the same counts (NaN fails both comparisons, +-inf one of them)."""
    with np.errstate(invalid="ignore", over="ignore"):
        counts = np.asarray(depth_m, dtype=np.float64) * depth_scale
        np.rint(counts, out=counts)
        invalid = ~(counts > 0)
        invalid |= ~(counts <= UINT16_MAX)
    np.copyto(counts, 0.0, where=invalid)
    if out is None:
        return counts.astype(np.uint16)
    np.copyto(out, counts, casting="unsafe")
    return out


def counts_to_depth(counts: np.ndarray, depth_scale: float) -> np.ndarray:
    """uint16 counts -> float32 depth [m]; 0 stays 0 (invalid)."""
    return counts.astype(np.float32) / np.float32(depth_scale)


def _nearest(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of sorted ``src``, the index of the nearest of sorted ``dst`` (ties to the lower
    index) and the absolute difference."""
    j = np.searchsorted(dst, src)
    left = np.clip(j - 1, 0, len(dst) - 1)
    right = np.clip(j, 0, len(dst) - 1)
    d_left = np.abs(src - dst[left])
    d_right = np.abs(dst[right] - src)
    take_right = d_right < d_left
    return np.where(take_right, right, left), np.where(take_right, d_right, d_left)


def associate(
    a_ns: np.ndarray, b_ns: np.ndarray, max_difference_ns: int = DEFAULT_MAX_DIFFERENCE_NS
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one association of two strictly increasing stamp arrays (TUM associate.py).

    associate.py greedily takes the pair with the smallest ``|a - b| < max_difference`` first.
    The same matching results from repeatedly taking every mutual-nearest pair among the stamps
    still unmatched (each such pair is locally the smallest edge), which vectorises with
    ``searchsorted``; rounds are few (one, in the usual case of similar rates).
    Returns index arrays (ia, ib), sorted by ``a``.
    """
    a = np.asarray(a_ns, dtype=np.int64)
    b = np.asarray(b_ns, dtype=np.int64)
    ia, ib = np.arange(len(a)), np.arange(len(b))
    found_a: list[np.ndarray] = []
    found_b: list[np.ndarray] = []
    while ia.size and ib.size:
        nb, dist = _nearest(a[ia], b[ib])
        na, dist_b = _nearest(b[ib], a[ia])
        # A stamp whose nearest partner is out of the window can never be matched.
        reachable = dist < max_difference_ns
        mutual = reachable & (na[nb] == np.arange(ia.size))
        if not mutual.any():
            break
        found_a.append(ia[mutual])
        found_b.append(ib[nb[mutual]])
        keep_b = dist_b < max_difference_ns
        keep_b[nb[mutual]] = False
        ia, ib = ia[reachable & ~mutual], ib[keep_b]
    if not found_a:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    out_a, out_b = np.concatenate(found_a), np.concatenate(found_b)
    order = np.argsort(out_a, kind="stable")
    return out_a[order].astype(np.int64), out_b[order].astype(np.int64)


def _plain(value: Any) -> Any:
    """numpy scalars/arrays and tuples -> plain YAML-safe Python values."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def intrinsics_from_scene(scene: Mapping[str, Any], where: str = "scene.yaml") -> CameraIntrinsics:
    """The ``camera:`` section of a scene as intrinsics (``depth_scale`` defaults to 5000)."""
    camera = scene.get("camera")
    if not isinstance(camera, Mapping):
        raise SensorError(f"{where}: needs a 'camera:' mapping with keys {', '.join(CAMERA_KEYS)}")
    missing = [k for k in CAMERA_KEYS[:-1] if k not in camera]
    if missing:
        raise SensorError(f"{where}: camera is missing {', '.join(missing)}")
    try:
        intr = CameraIntrinsics(
            width=int(camera["width"]),
            height=int(camera["height"]),
            fx=float(camera["fx"]),
            fy=float(camera["fy"]),
            cx=float(camera["cx"]),
            cy=float(camera["cy"]),
            depth_scale=float(camera.get("depth_scale", CameraIntrinsics.depth_scale)),
        )
    except (TypeError, ValueError, OverflowError) as err:
        raise SensorError(f"{where}: camera intrinsics are not numbers: {err}") from err
    except SensorError as err:  # not finite, or not > 0
        raise SensorError(f"{where}: {err}") from None
    return intr


def _stamp_lines(stamps_ns: np.ndarray, *columns: np.ndarray) -> str:
    cols = [np.asarray(c) for c in columns]
    return "".join(
        format_stamp(int(t)) + "".join(f" {c[i]!s}" for c in cols) + "\n"
        for i, t in enumerate(stamps_ns)
    )


# --- writer ------------------------------------------------------------------------------------


class RecordingWriter:
    """Write a recording folder; use as a context manager.

    Images are PNG-encoded on a small thread pool (cv2.imencode releases the GIL) with at most
    ``2 * workers`` frames in flight. Everything goes to a staging folder beside ``path``;
    :meth:`close` writes the index files and swaps the folder in. If the ``with`` body raises,
    the staging folder is removed and an existing recording at ``path`` is left untouched.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        intrinsics: CameraIntrinsics,
        scene: Mapping[str, Any],
        workers: int = 2,
        rgb_compression: int = PNG_COMPRESSION,
        images: bool = True,
    ) -> None:
        """``rgb_compression``: zlib level of the colour PNGs; 0 stores them (4 ms instead of
        20-30 ms a frame, 0.9 MB instead of 0.55 MB: noisy colour compresses little), for a
        live run that must not fall behind. Depth is always compressed (7 ms, 70 kB).
        ``images=False`` writes everything but the PNGs (index files name them all): the
        streams of a world rendered on demand (:mod:`sensors.sim.world_source`)."""
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.path = Path(path)
        self.intrinsics = intrinsics
        camera = dict(scene.get("camera") or {}) | dataclasses.asdict(intrinsics)
        self._scene = _plain({**scene, "camera": camera})
        self._max_pending = 2 * workers
        self._rgb_compression = rgb_compression
        self._images = images
        try:
            self._staging = make_staging_dir(self.path)
            (self._staging / "rgb").mkdir()
            (self._staging / "depth").mkdir()
        except OSError as err:
            raise SensorError(
                f"{self.path}: cannot create a recording there ({err.strerror or err})"
            ) from err
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="png")
        self._pending: deque[Future[None]] = deque()
        self._frame_stamps: list[int] = []
        self._wheels: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._imu: list[tuple[np.ndarray, np.ndarray]] = []
        self._groundtruth: tuple[np.ndarray, ...] | None = None
        self._gps: GpsStream | None = None
        self._closed = False

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # 1. Frames: convert on the caller's thread (so the caller may reuse its buffers), encode
    #    and write on the pool.
    def add_frame(self, frame: RgbdFrame) -> None:
        self._check_open()
        h, w = self.intrinsics.height, self.intrinsics.width
        if frame.rgb.shape != (h, w, 3) or frame.rgb.dtype != np.uint8:
            raise SensorError(
                f"frame {frame.stamp_ns}: rgb must be {h}x{w}x3 uint8, got "
                f"{frame.rgb.shape} {frame.rgb.dtype}"
            )
        if frame.depth_m.shape != (h, w):
            raise SensorError(
                f"frame {frame.stamp_ns}: depth must be {h}x{w}, got {frame.depth_m.shape}"
            )
        stamp = self._add_stamp(frame.stamp_ns)
        if not self._images:
            return
        name = f"{format_stamp(stamp)}.png"
        bgr = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
        counts = depth_to_counts(frame.depth_m, self.intrinsics.depth_scale)
        self._submit(self._staging / "rgb" / name, bgr, self._rgb_compression)
        self._submit(self._staging / "depth" / name, counts)

    def add_frame_stamp(self, stamp_ns: int) -> None:
        """A frame's stamp alone (its index lines), for a writer made with ``images=False``."""
        self._check_open()
        if self._images:
            raise SensorError("add_frame_stamp needs a writer made with images=False")
        self._add_stamp(stamp_ns)

    def _add_stamp(self, stamp_ns: int) -> int:
        stamp = int(stamp_ns)
        if self._frame_stamps and stamp <= self._frame_stamps[-1]:
            raise SensorError(
                f"frame stamps must strictly increase: {format_stamp(stamp)} after "
                f"{format_stamp(self._frame_stamps[-1])}"
            )
        self._frame_stamps.append(stamp)
        return stamp

    def _submit(self, path: Path, image: np.ndarray, level: int = PNG_COMPRESSION) -> None:
        self._pending.append(self._pool.submit(_write_png, path, image, level))
        while len(self._pending) > self._max_pending:
            self._pending.popleft().result()

    # 2. Low-rate streams are kept in memory and written by close().
    def add_wheels(self, stamps_ns: np.ndarray, left: np.ndarray, right: np.ndarray) -> None:
        self._check_open()
        stamps = self._checked_stamps("wheels", stamps_ns, [s for s, _, _ in self._wheels])
        ticks = []
        for name, values in (("left", left), ("right", right)):
            arr = np.asarray(values)
            if arr.shape != stamps.shape or not np.array_equal(arr, np.rint(arr)):
                raise SensorError(f"wheels: {name} must be integer counts, one per stamp")
            ticks.append(arr.astype(np.int64))
        self._wheels.append((stamps, ticks[0], ticks[1]))

    def add_imu(self, stamps_ns: np.ndarray, gyro_z: np.ndarray) -> None:
        self._check_open()
        stamps = self._checked_stamps("imu", stamps_ns, [s for s, _ in self._imu])
        gyro = np.asarray(gyro_z, dtype=np.float64)
        if gyro.shape != stamps.shape or not np.isfinite(gyro).all():
            raise SensorError("imu: gyro_z must be finite, one per stamp")
        self._imu.append((stamps, gyro))

    def set_gps(self, gps: GpsStream) -> None:
        """GPS fixes, written as gps.txt; replaces any earlier call."""
        self._check_open()
        self._gps = gps

    def set_groundtruth(
        self, stamps_ns: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray
    ) -> None:
        """base_link pose in the world (planar); replaces any earlier call."""
        self._check_open()
        stamps = self._checked_stamps("groundtruth", stamps_ns, [])
        poses = [np.asarray(v, dtype=np.float64) for v in (x, y, yaw)]
        if any(p.shape != stamps.shape or not np.isfinite(p).all() for p in poses):
            raise SensorError("groundtruth: x, y, yaw must be finite, one per stamp")
        self._groundtruth = (stamps, *poses)

    def _checked_stamps(
        self, what: str, stamps_ns: np.ndarray, before: list[np.ndarray]
    ) -> np.ndarray:
        stamps = np.asarray(stamps_ns)
        if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
            raise SensorError(f"{what}: stamps_ns must be a 1-D integer array [ns]")
        stamps = stamps.astype(np.int64)
        previous = [b[-1:] for b in before if b.size]
        joined = np.concatenate([previous[-1], stamps]) if previous else stamps
        if np.any(np.diff(joined) <= 0):
            raise SensorError(f"{what}: stamps must strictly increase (also across calls)")
        return stamps

    def _check_open(self) -> None:
        if self._closed:
            raise SensorError(f"recording {self.path} is already closed")

    # 3. Commit: finish the images, write the index files, swap the folder in.
    def close(self) -> None:
        if self._closed:
            return
        try:
            while self._pending:
                self._pending.popleft().result()
            self._pool.shutdown(wait=True)
            self._write_indexes()
            commit_staging_dir(self._staging, self.path)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        log.log(
            logging.INFO if self._images else logging.DEBUG,  # no images: an internal step
            "wrote recording %s (%d frames)",
            self.path,
            len(self._frame_stamps),
        )

    def abort(self) -> None:
        """Drop everything written so far; an existing recording at ``path`` stays as it was."""
        if self._closed:
            return
        self._closed = True
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._pending.clear()
        shutil.rmtree(self._staging, ignore_errors=True)

    def _write_indexes(self) -> None:
        st = self._staging
        stamps = np.array(self._frame_stamps, dtype=np.int64)
        for kind, title in (("rgb", "color images"), ("depth", "depth maps")):
            names = np.array([f"{kind}/{format_stamp(int(t))}.png" for t in stamps], dtype=object)
            body = _stamp_lines(stamps, names)
            atomic_write_text(st / f"{kind}.txt", f"# {title}\n# timestamp filename\n{body}")
        w = [np.concatenate(c) for c in zip(*self._wheels, strict=True)] or [
            np.zeros(0, np.int64)
        ] * 3
        atomic_write_text(
            st / "wheels.txt", "# wheel encoders\n# timestamp left right\n" + _stamp_lines(*w)
        )
        if self._imu:
            t, g = (np.concatenate(c) for c in zip(*self._imu, strict=True))
            atomic_write_text(
                st / "imu.txt",
                "# imu\n# timestamp gyro_z\n"
                + _stamp_lines(t, np.array([repr(float(v)) for v in g])),
            )
        if self._groundtruth is not None:
            write_tum_trajectory(st / "groundtruth.txt", *self._groundtruth)
        if self._gps is not None:
            write_gps_txt(st / GPS_TXT, self._gps)
        atomic_write_text(st / "scene.yaml", yaml.safe_dump(self._scene, sort_keys=False))


def _write_png(path: Path, image: np.ndarray, level: int = PNG_COMPRESSION) -> None:
    # Measured on 640x480 simulated frames: 16-bit depth compresses best and fastest without a
    # row filter (6 ms, ~110 kB); noisy colour with the SUB filter (20 ms vs 45 ms by default).
    row_filter = (
        cv2.IMWRITE_PNG_FILTER_NONE if image.dtype == np.uint16 else cv2.IMWRITE_PNG_FILTER_SUB
    )
    params = [cv2.IMWRITE_PNG_COMPRESSION, level, cv2.IMWRITE_PNG_FILTER, row_filter]
    ok, buf = cv2.imencode(".png", image, params)
    if not ok:
        raise SensorError(f"{path}: PNG encoding failed")
    path.write_bytes(buf.tobytes())


# --- reader ------------------------------------------------------------------------------------


class Recording:
    """A recording folder opened for reading. Index files are read at open; images lazily,
    ``workers`` threads decoding ahead of the consumer in :meth:`frames`."""

    workers = 2  # decode threads: the 2 cores of the robot's and CI's machines

    def __init__(
        self,
        path: Path,
        scene: dict[str, Any],
        rgb: tuple[np.ndarray, list[str]],
        depth: tuple[np.ndarray, list[str]],
        max_difference_ns: int = DEFAULT_MAX_DIFFERENCE_NS,
    ) -> None:
        self.path = path
        self.scene = scene
        self.intrinsics = intrinsics_from_scene(scene, str(path / "scene.yaml"))
        self.rgb_stamps_ns, self._rgb_files = rgb
        self.depth_stamps_ns, self._depth_files = depth
        self.max_difference_ns = max_difference_ns
        self.rgb_index, self.depth_index = associate(
            self.rgb_stamps_ns, self.depth_stamps_ns, max_difference_ns
        )
        self.skipped: dict[str, int] = {}
        self._streams_read: dict[str, Any] = {}  # _parsed

    @classmethod
    def open(
        cls, path: str | os.PathLike[str], max_difference_ns: int = DEFAULT_MAX_DIFFERENCE_NS
    ) -> Recording:
        path = Path(path)
        if not path.is_dir():
            raise SensorError(f"{path}: not a recording folder; {FOLDER_CONTENTS}")
        for name in ("rgb.txt", "depth.txt", "scene.yaml"):
            if not (path / name).is_file():
                raise SensorError(f"{path}: missing {name}; {FOLDER_CONTENTS}")
        scene = read_yaml(path / "scene.yaml", SensorError)
        if not isinstance(scene, dict):
            raise SensorError(f"{path / 'scene.yaml'}: must be a mapping")
        return cls(
            path,
            scene,
            _read_index(path / "rgb.txt"),
            _read_index(path / "depth.txt"),
            max_difference_ns,
        )

    def __len__(self) -> int:
        return int(self.rgb_index.size)

    def _parsed(self, name: str, parse: Callable[[], T]) -> T:
        """``parse()``'s result for stream ``name``, parsed once: a run asks for the same
        streams several times (stamps, options, feed, scoring), ~30 ms of text parsing each."""
        if name not in self._streams_read:
            self._streams_read[name] = parse()
        return self._streams_read[name]  # type: ignore[no-any-return]

    def wheels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(stamps_ns, left, right), all int64; empty when the recording has no wheels.txt."""
        t, left, right = self._parsed("wheels", self._read_wheels)
        return t.copy(), left.copy(), right.copy()

    def _read_wheels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        file = self.path / "wheels.txt"
        if not file.is_file():
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty.copy(), empty.copy()
        table = read_stamped_text(file, ("timestamp", "left", "right"))
        ticks = table.numeric(np.int64, "integer encoder counts (left right)").reshape(-1, 2)
        return table.stamps_ns, ticks[:, 0].copy(), ticks[:, 1].copy()

    def imu(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(stamps_ns, gyro_z [rad/s]) or None without imu.txt."""
        imu = self._parsed("imu", self._read_imu)
        return None if imu is None else (imu[0].copy(), imu[1].copy())

    def _read_imu(self) -> tuple[np.ndarray, np.ndarray] | None:
        file = self.path / "imu.txt"
        if not file.is_file():
            return None
        table = read_stamped_text(file, ("timestamp", "gyro_z"))
        return table.stamps_ns, table.numeric(np.float64, "gyro_z [rad/s]").reshape(-1)

    def gps(self) -> GpsStream | None:
        """GPS fixes, or None without gps.txt."""
        file = self.path / GPS_TXT
        return read_gps_txt(file) if file.is_file() else None

    def groundtruth(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(stamps_ns, xyz (N, 3) [m], quat_xyzw (N, 4)) of base_link in the world, or None."""
        file = self.path / "groundtruth.txt"
        gt = self._parsed("groundtruth", lambda: load_trajectory(file) if file.is_file() else None)
        return None if gt is None else (gt[0].copy(), gt[1].copy(), gt[2].copy())

    def groundtruth_planar(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """(stamps_ns, x [m], y [m], yaw [rad]) or None."""
        gt = self.groundtruth()
        if gt is None:
            return None
        stamps, xyz, quat = gt
        return stamps, xyz[:, 0].copy(), xyz[:, 1].copy(), yaw_from_quaternion(quat)

    def frames(
        self, skip_bad: bool = False, rgb_wanted: Callable[[int], bool] | None = None
    ) -> Iterator[RgbdFrame]:
        """Associated frames in rgb-stamp order, stamped with the rgb stamp.

        A missing or bad image raises :class:`SensorError` naming the file; with ``skip_bad``
        the pair is skipped with a warning and counted in ``self.skipped`` (reset per call).
        ``rgb_wanted(i)`` False: the i-th frame yielded (from 0) may come without its colour
        (``rgb`` empty, :data:`NO_RGB`): its PNG is checked but not decoded. The front end's VO
        stride needs no colour on the frames it skips (:func:`slam.front_end.replay`).
        """
        self.skipped = {}
        bad = 0  # frames skipped so far: frame k is likely the (k - bad)-th yielded

        def decode(k: int) -> RgbdFrame:
            return self.frame(k, rgb_wanted is None or rgb_wanted(k - bad))

        yielded = 0
        for k, future in decoded_ahead(decode, len(self), self.workers, "png-decode"):
            try:
                frame = future.result()
                if frame.rgb is NO_RGB and rgb_wanted is not None and rgb_wanted(yielded):
                    frame = self.frame(k)  # a skipped frame before it moved the count
            except ImageError as err:
                if not skip_bad:
                    raise
                stamp = format_stamp(int(self.rgb_stamps_ns[self.rgb_index[k]]))
                log.warning("skipping frame %s: %s", stamp, err)
                self.skipped[err.reason] = self.skipped.get(err.reason, 0) + 1
                bad += 1
                continue
            yielded += 1
            yield frame

    def frame(self, k: int, rgb: bool = True) -> RgbdFrame:
        """The k-th associated frame (0 <= k < len(self)); raises SensorError on a bad image.
        Without ``rgb`` the colour PNG is only checked (:func:`sensors.images.check_image_file`)
        and the frame's ``rgb`` is :data:`NO_RGB`."""
        i, j = int(self.rgb_index[k]), int(self.depth_index[k])
        size = (self.intrinsics.width, self.intrinsics.height)
        rgb_file = self.path / self._rgb_files[i]
        colour = read_image(rgb_file, size, depth=False) if rgb else NO_RGB
        if not rgb:
            check_image_file(rgb_file, size)
        counts = read_image(self.path / self._depth_files[j], size, depth=True)
        return RgbdFrame(
            stamp_ns=int(self.rgb_stamps_ns[i]),
            rgb=colour,
            depth_m=counts_to_depth(counts, self.intrinsics.depth_scale),
            intrinsics=self.intrinsics,
        )


def _read_index(file: Path) -> tuple[np.ndarray, list[str]]:
    table = read_stamped_text(file, ("timestamp", "filename"))
    return table.stamps_ns, [row[0] for row in table.values]


__all__ = [
    "DEFAULT_MAX_DIFFERENCE_NS",
    "Recording",
    "RecordingWriter",
    "associate",
    "counts_to_depth",
    "depth_to_counts",
    "intrinsics_from_scene",
]
