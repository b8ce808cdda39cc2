"""Our recording folders (and anything with the same layout) as a :class:`Source`."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from sensors.gps import GpsStream
from sensors.recording import Recording
from sensors.source import ImuStream, PoseStream, SourceBase, SourceOptions, WheelStream
from sensors.types import CameraIntrinsics, RgbdFrame


class RecordingSource(SourceBase):
    def __init__(self, recording: Recording, skip_bad: bool = True) -> None:
        self.recording = recording
        self.path = str(recording.path)
        self.skip_bad = skip_bad
        self.skipped: dict[str, int] = {}

    @classmethod
    def try_open(
        cls, path: Path | str, options: SourceOptions | None = None
    ) -> RecordingSource | None:
        path = Path(path)
        if path.is_dir() and (path / "scene.yaml").is_file() and (path / "rgb.txt").is_file():
            return cls(Recording.open(path), skip_bad=not (options and options.strict))
        return None

    def describe(self) -> str:
        k = self.recording.intrinsics
        world = self.recording.scene.get("world")
        sim = (
            f", simulated world {world} (seed {self.recording.scene.get('seed')})" if world else ""
        )
        return (
            f"rgbdnav recording, camera {k.width}x{k.height} fx={k.fx:g} fy={k.fy:g} "
            f"cx={k.cx:g} cy={k.cy:g}, {len(self.recording)} rgb/depth pairs{sim}"
        )

    def stream_stamps(self) -> dict[str, np.ndarray]:
        rec = self.recording
        out = {"rgb": rec.rgb_stamps_ns, "depth": rec.depth_stamps_ns}
        wheels = rec.wheels()[0]
        if len(wheels):
            out["wheels"] = wheels
        imu = rec.imu()
        if imu is not None:
            out["imu"] = imu[0]
        gt = rec.groundtruth()
        if gt is not None:
            out["groundtruth"] = gt[0]
        return out

    def intrinsics(self) -> CameraIntrinsics | None:
        return self.recording.intrinsics

    def frames(self) -> Iterator[RgbdFrame]:
        yield from self.recording.frames(skip_bad=self.skip_bad)
        self.skipped = dict(self.recording.skipped)

    def frames_for(self, rgb_wanted: Callable[[int], bool]) -> Iterator[RgbdFrame]:
        yield from self.recording.frames(skip_bad=self.skip_bad, rgb_wanted=rgb_wanted)
        self.skipped = dict(self.recording.skipped)

    def gps(self) -> GpsStream | None:
        """The recording's gps.txt fixes, or None without one."""
        return self.recording.gps()

    def wheels(self) -> WheelStream | None:
        stamps, left, right = self.recording.wheels()
        return WheelStream(stamps, left, right) if len(stamps) else None

    def imu(self) -> ImuStream | None:
        imu = self.recording.imu()
        return None if imu is None else ImuStream(*imu)

    def groundtruth(self) -> PoseStream | None:
        gt = self.recording.groundtruth_planar()
        frame = str(self.recording.scene.get("groundtruth_frame", "base_link"))
        return None if gt is None else PoseStream(*gt, frame=frame)
