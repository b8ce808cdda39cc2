"""One protocol for everything rgbdnav reads: recordings, TUM folders, rosbags, CARMEN logs,
live cameras. Adapters implement :class:`Source`; :func:`open_source` picks one from a path.

A source says which streams it holds (``stream_stamps``) for ``rgbdnav info``, and yields what it
has: RGB-D frames, wheel encoder readings, IMU samples, laser scans, odometry, ground truth.
Methods for streams a source does not have return ``None`` (or yield nothing).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np

from sensors.config import CameraConfig, RobotConfig, SyncConfig
from sensors.types import CameraIntrinsics, LaserScan, RgbdFrame, SensorError


@dataclass(frozen=True, eq=False)
class WheelStream:
    stamps_ns: np.ndarray  # (N,) int64 [ns]
    left: np.ndarray  # (N,) int64 cumulative encoder positions
    right: np.ndarray  # (N,) int64


@dataclass(frozen=True, eq=False)
class PoseStream:
    """Planar poses over time: ground truth, or raw odometry from a log or bag."""

    stamps_ns: np.ndarray  # (N,) int64 [ns]
    x: np.ndarray  # (N,) [m]
    y: np.ndarray  # (N,) [m]
    yaw: np.ndarray  # (N,) [rad]
    frame: str = "base_link"  # which frame the poses describe (base_link, camera, laser)
    # nav_msgs/Odometry extras (None when the source has no such field):
    twist: np.ndarray | None = None  # (N, 3) vx [m/s], vy [m/s], vyaw [rad/s] in the child frame
    pose_covariance: np.ndarray | None = None  # (N, 3, 3) over x, y, yaw
    twist_covariance: np.ndarray | None = None  # (N, 3, 3) over vx, vy, vyaw


@dataclass(frozen=True, eq=False)
class ImuStream:
    stamps_ns: np.ndarray  # (N,) int64 [ns]
    gyro_z: np.ndarray  # (N,) [rad/s]


@runtime_checkable
class Source(Protocol):
    """What every input adapter offers. ``skipped`` counts bad records by reason."""

    path: str
    skipped: dict[str, int]

    def describe(self) -> str:
        """One line: kind of source, camera/laser, sizes."""
        ...

    def stream_stamps(self) -> dict[str, np.ndarray]:
        """Stamps [ns] of every stream present, e.g. {"rgb": ..., "depth": ..., "wheels": ...}."""
        ...

    def intrinsics(self) -> CameraIntrinsics | None: ...

    def frames(self) -> Iterator[RgbdFrame]: ...

    def scans(self) -> Iterator[LaserScan]: ...

    def wheels(self) -> WheelStream | None: ...

    def imu(self) -> ImuStream | None: ...

    def odometry(self) -> PoseStream | None: ...

    def groundtruth(self) -> PoseStream | None: ...

    def close(self) -> None: ...


_S = TypeVar("_S", bound="SourceBase")


class SourceBase:
    """What a source lacks, said once: adapters inherit it and override the streams they have.
    Also a context manager that closes the source."""

    path: str
    skipped: dict[str, int]

    def intrinsics(self) -> CameraIntrinsics | None:
        return None

    def frames(self) -> Iterator[RgbdFrame]:
        return iter(())

    def frames_for(self, rgb_wanted: Callable[[int], bool]) -> Iterator[RgbdFrame]:
        """:meth:`frames`, where the i-th frame may come without its colour
        (:data:`sensors.types.NO_RGB`) when ``rgb_wanted(i)`` is False and the source can save
        work by it (a recording: the PNG is not decoded). Here: every frame in full."""
        return self.frames()

    def scans(self) -> Iterator[LaserScan]:
        return iter(())

    def wheels(self) -> WheelStream | None:
        return None

    def imu(self) -> ImuStream | None:
        return None

    def odometry(self) -> PoseStream | None:
        return None

    def groundtruth(self) -> PoseStream | None:
        return None

    def close(self) -> None:
        return None

    def __enter__(self: _S) -> _S:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class SourceOptions:
    """What the user's configuration tells adapters; each adapter uses what applies to it."""

    topics: Mapping[str, str] | None = None  # rosbag topic per role (TopicsConfig fields)
    robot: RobotConfig | None = None  # wheel geometry, e.g. for JointState wheel angles
    camera: CameraConfig | None = None  # intrinsics when a source carries none
    strict: bool = False  # raise on the first bad record instead of counting skips
    sync: SyncConfig | None = None  # association windows (rosbag and OpenNI readers)
    require_topics: bool = False  # a bag's missing/ambiguous topic is an error, not a skip
    realtime: bool = False  # device recordings play in real time, stamped like a camera (live)


Opener = Callable[[Path | str, SourceOptions], "Source | None"]
_URI = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")  # pseudo-paths such as openni://
# The same after Path() collapsed its "//" (a CLI argument typed as a path): realsense:/x.db3
_COLLAPSED_URI = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]+:/")
_OPENERS: list[tuple[str, Opener, bool]] = []


def register_opener(name: str, opener: Opener, uri: bool = False) -> None:
    """Adapters register a function that returns a Source for paths it recognises, else None.
    Only adapters registered with ``uri=True`` are offered device URIs (as strings); the others
    only ever see existing paths."""
    _OPENERS.append((name, opener, uri))


def is_device_uri(path: str | Path) -> bool:
    """A device URI such as ``openni://`` or ``realsense://x.db3``, even after Path() collapsed
    its ``//``: not a file path to check for existence."""
    text = str(path)
    return bool(_URI.match(text) or (isinstance(path, Path) and _COLLAPSED_URI.match(text)))


def open_source(path: str | Path, options: SourceOptions | None = None) -> Source:
    """The first registered adapter that recognises ``path``; a clear error if none does."""
    import sensors.adapters  # noqa: F401  (registers the built-in adapters)

    opts = options or SourceOptions()
    kinds = ", ".join(name for name, _, _ in _OPENERS)
    text = str(path)
    if is_device_uri(path):
        # A device URI: no file to check, and Path() would collapse its double slashes.
        for _name, opener, uri in _OPENERS:
            src = opener(text, opts) if uri else None
            if src is not None:
                return src
        raise SensorError(f"{text}: no adapter for this URI (known: {kinds})")
    p = Path(path)
    if not p.exists():
        raise SensorError(f"{p}: no such file or folder")
    for _name, opener, _uri in _OPENERS:
        src = opener(p, opts)
        if src is not None:
            return src
    raise SensorError(f"{p}: not a source rgbdnav can read (known: {kinds})")
