"""``rgbdnav live --record DIR``: what the robot saw, written as an rgbdnav recording.

The camera frames and the encoder readings the live run used go into a recording folder
(:class:`sensors.recording.RecordingWriter`: PNGs, index files, ``scene.yaml`` with the
camera and robot; with the simulated robot also its world, so ``rgbdnav map`` scores the map
against the floor plan). ``rgbdnav map DIR`` / ``odometry DIR`` then rebuild the run offline:
record on the robot, map at the desk, or compare a live map with one made without the clock.

Recording never holds up the front end: frames go through a bounded queue to a writer thread
(the PNGs are encoded on the writer's pool, which releases the GIL; colour stored without
compression, ~10 ms of CPU a frame in all) and a frame that finds the queue full is left out of
the recording and counted. The folder is swapped in when the run
ends (SIGINT and SIGTERM included); a run killed with -9 leaves only a staging folder.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sensors.recording import RecordingWriter
from sensors.types import RgbdFrame, SensorError, WheelTicks

log = logging.getLogger(__name__)

FRAME_QUEUE_SIZE = 8  # frames waiting for the writer before one is left out


class LiveRecorder:
    """Frames (``frame``) and encoder readings (``wheels``) of a live run into ``path``."""

    def __init__(self, path: Path, scene: Mapping[str, Any]) -> None:
        self.path = path
        self.scene = dict(scene)
        self.frames = 0  # written (queued to the writer)
        self.frames_dropped = 0  # the queue was full: not in the recording
        self._q: queue.Queue[RgbdFrame | None] = queue.Queue(FRAME_QUEUE_SIZE)
        self._writer: RecordingWriter | None = None
        self._thread: threading.Thread | None = None
        self._error: str | None = None
        self._ticks: list[tuple[int, int, int]] = []

    def frame(self, frame: RgbdFrame) -> None:
        """Called by the front end for every frame it takes; never blocks."""
        if self._error is not None:
            return
        if self._writer is None:  # the intrinsics come with the first frame
            try:
                self._writer = RecordingWriter(
                    self.path, frame.intrinsics, self.scene, rgb_compression=0
                )
            except SensorError as err:
                self._fail(str(err))
                return
            self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
            self._thread.start()
        try:
            self._q.put_nowait(frame)
            self.frames += 1
        except queue.Full:
            self.frames_dropped += 1

    def wheels(self, ticks: WheelTicks) -> None:
        """An encoder reading the front end took (strictly later than the last one)."""
        self._ticks.append((int(ticks.stamp_ns), int(ticks.left), int(ticks.right)))

    def _run(self) -> None:
        assert self._writer is not None
        while (frame := self._q.get()) is not None:
            if self._error is not None:
                continue  # drain: the front end must not block on a full queue
            try:
                self._writer.add_frame(frame)
            except (SensorError, OSError) as err:
                self._fail(f"frame {frame.stamp_ns}: {err}")

    def _fail(self, why: str) -> None:
        if self._error is None:
            self._error = why
            log.error("recording %s stopped: %s", self.path, why)

    def close(self, groundtruth: np.ndarray | None = None) -> dict[str, Any]:
        """Finish the images, write the indexes and swap the folder in; ``groundtruth`` (N, 4)
        stamp_ns, x, y, yaw of base_link (the simulated robot's truth). Returns the summary."""
        if self._thread is not None:
            self._q.put(None)
            self._thread.join()
        out: dict[str, Any] = {
            "path": str(self.path),
            "frames": self.frames,
            "frames_dropped": self.frames_dropped,
            "wheel_readings": len(self._ticks),
        }
        writer = self._writer
        if writer is None:
            out["error"] = self._error or "no camera frame arrived: nothing recorded"
            return out
        try:
            if self._error is not None:
                raise SensorError(self._error)
            t = np.array(self._ticks, dtype=np.int64).reshape(-1, 3)
            writer.add_wheels(t[:, 0], t[:, 1], t[:, 2])
            if groundtruth is not None and len(groundtruth):
                g = np.asarray(groundtruth, dtype=np.float64)
                stamps = g[:, 0].astype(np.int64)
                keep = np.r_[True, np.diff(stamps) > 0]  # the truth file may repeat a stamp
                writer.set_groundtruth(stamps[keep], g[keep, 1], g[keep, 2], g[keep, 3])
            writer.close()
        except (SensorError, OSError) as err:
            writer.abort()
            out["error"] = f"not written: {err}"
            log.error("recording %s not written: %s", self.path, err)
        return out


__all__ = ["LiveRecorder"]
