"""Bounded bookkeeping for long live runs: nothing here grows with the run's length.

- :class:`Reservoir`: a uniform random sample (Vitter's algorithm R) of at most ``capacity``
  values, with the exact count, mean and maximum, for percentiles of latency-like streams.
- :class:`TrackWriter`: a trajectory streamed to a TUM file as it is made, with a thinned copy
  in memory (a point per ``spacing`` metres of travel, halved whenever it reaches ``capacity``)
  for drawing.
- :class:`Timeline`: (t, value) samples, halved whenever they reach ``capacity``.
- :class:`FrameWindows`: frames processed and dropped so far and the latency p99 of each
  sampling window, on a :class:`Timeline`: whether a long run falls behind as it goes on.
- :func:`tame_malloc`: glibc's allocator, told not to keep what a long run frees.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import threading
import time
from pathlib import Path
from typing import IO, Any

import numpy as np

from sensors.tum import PLANAR_TUM_HEADER, load_tum_trajectory, planar_tum_row, yaw_from_quaternion

log = logging.getLogger(__name__)

M_MMAP_THRESHOLD = -3  # glibc mallopt parameters (malloc.h)
M_ARENA_MAX = -8
DEFAULT_TRACK_POINTS = 20000  # thinned trajectory points kept in memory at most
TRACK_FLUSH_PERIOD_S = 1.0  # [s] streamed rows reach the OS this often: a kill -9 loses <= this
DEFAULT_TIMELINE_POINTS = 720  # e.g. an hour of 5 s samples before the first halving


class Reservoir:
    """At most ``capacity`` values, a uniform sample of all added (seeded: reproducible)."""

    def __init__(self, capacity: int, seed: int = 0) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self._values = np.empty(capacity, dtype=np.float64)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self.count = 0
        self.total = 0.0
        self.max = -math.inf

    def add(self, value: float) -> None:
        with self._lock:
            if self.count < self.capacity:
                self._values[self.count] = value
            else:
                j = int(self._rng.integers(0, self.count + 1))
                if j < self.capacity:
                    self._values[j] = value
            self.count += 1
            self.total += value
            self.max = max(self.max, value)

    def values(self) -> np.ndarray:
        with self._lock:
            return self._values[: min(self.count, self.capacity)].copy()

    def percentile(self, q: float) -> float:
        v = self.values()
        return float(np.percentile(v, q)) if len(v) else math.nan

    def __len__(self) -> int:
        return self.count


class TrackWriter:
    """Planar poses streamed to ``path`` (TUM, as :func:`sensors.tum.write_tum_trajectory`
    writes them) and a thinned in-memory track for pictures. Rows are flushed to the OS at
    least every ``TRACK_FLUSH_PERIOD_S``, so a process killed with -9 leaves what it tracked."""

    def __init__(self, path: Path, spacing_m: float, capacity: int = DEFAULT_TRACK_POINTS) -> None:
        self.path = path
        self.spacing_m = spacing_m
        self.capacity = capacity
        self._file: IO[str] | None = None
        self._thin: list[tuple[float, float]] = []
        self._last: tuple[float, float] | None = None
        self._flushed_at = -math.inf  # [s] monotonic
        self.count = 0

    def add(self, stamp_ns: int, x: float, y: float, yaw: float) -> None:
        if self._file is None:
            self._file = open(self.path, "w", buffering=1 << 16)  # closed by close()
            self._file.write(PLANAR_TUM_HEADER)
        self._file.write(planar_tum_row(stamp_ns, x, y, yaw))
        self.count += 1
        now = time.monotonic()
        if now - self._flushed_at >= TRACK_FLUSH_PERIOD_S:
            self._file.flush()
            self._flushed_at = now
        if self._last is None or math.hypot(x - self._last[0], y - self._last[1]) >= self.spacing_m:
            self._last = (float(x), float(y))
            self._thin.append(self._last)
            if len(self._thin) >= self.capacity:
                self._thin = self._thin[::2]

    def thinned(self) -> np.ndarray:
        """(N, 2) [m] the kept points (N <= capacity)."""
        return np.array(self._thin, dtype=np.float64).reshape(-1, 2)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def load(self) -> np.ndarray:
        """(N, 4) stamp [ns], x, y, yaw of everything written (after :meth:`close`)."""
        if self.count == 0:
            return np.zeros((0, 4))
        return load_track(self.path)


def load_track(path: Path) -> np.ndarray:
    """(N, 4) stamp [ns], x, y, yaw of a planar TUM trajectory."""
    t_ns, xyz, quat = load_tum_trajectory(path)
    return np.column_stack(
        [t_ns.astype(np.float64), xyz[:, 0], xyz[:, 1], yaw_from_quaternion(quat)]
    )


class Timeline:
    """(t, value) samples; every other one is dropped when ``capacity`` is reached."""

    def __init__(self, capacity: int = DEFAULT_TIMELINE_POINTS) -> None:
        self.capacity = capacity
        self.points: list[tuple[float, Any]] = []

    def add(self, t: float, value: Any) -> None:
        self.points.append((t, value))
        if len(self.points) >= self.capacity:
            self.points = self.points[::2]


class FrameWindows:
    """Per sampling window: [frames processed so far, frames dropped so far, frame-to-pose
    latency p99 of the window (ms; None when none was processed)], on a :class:`Timeline`.
    The counts are cumulative, so the windows dropped by the timeline's halving lose nothing:
    the drops between any two kept points are their difference."""

    def __init__(self, capacity: int = DEFAULT_TIMELINE_POINTS) -> None:
        self.timeline = Timeline(capacity)
        self._lock = threading.Lock()
        self._window: list[float] = []

    def add(self, latency_ms: float) -> None:
        """One processed frame's latency (the front end's thread)."""
        with self._lock:
            self._window.append(latency_ms)

    def sample(self, t: float, processed: int, dropped: int) -> None:
        """Close the window at ``t`` [s into the run] with the run's counts so far."""
        with self._lock:
            window, self._window = self._window, []
        p99 = round(float(np.percentile(window, 99)), 2) if window else None
        self.timeline.add(t, [int(processed), int(dropped), p99])

    @property
    def points(self) -> list[tuple[float, list[int | float | None]]]:
        return self.timeline.points


def tame_malloc(arena_max: int, mmap_threshold: int) -> bool:
    """Bound glibc's malloc for a long multi-threaded run; True when it was applied.

    By default glibc gives busy threads arenas of their own (up to 8 per core) and, after a
    large block is freed, raises its mmap threshold (up to 32 MB), so later large transient
    arrays (checkpoint grids, planner graphs, images) come from the arenas and what they free
    stays resident: RSS creeps up for as long as the run lasts. A fixed threshold (large blocks
    are mmap'ed and handed back on free) and a few arenas stop that. ``0`` leaves a setting at
    glibc's default. Must run before the threads start; a no-op (False) without glibc."""
    name = ctypes.util.find_library("c")
    if name is None or (arena_max <= 0 and mmap_threshold <= 0):
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    ok = True
    if arena_max > 0:
        ok &= bool(mallopt(M_ARENA_MAX, int(arena_max)))
    if mmap_threshold > 0:
        ok &= bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)))
    if not ok:
        log.debug("mallopt refused arena_max=%d mmap_threshold=%d", arena_max, mmap_threshold)
    return ok


__all__ = ["FrameWindows", "Reservoir", "Timeline", "TrackWriter", "load_track", "tame_malloc"]
