"""Visualisation as a side channel: one :class:`Visualizer` protocol, a do-nothing default, a rerun
implementation, and a bounded asynchronous wrapper that drops (and counts) what it cannot draw.

Entity paths (all world geometry in metres, ``map`` frame, z = 0 on the floor):

==========================  ==========================================================
``world/map``               occupied cells of the occupancy grid (Points3D)
``world/costmap``           lethal/inscribed cells of the costmap (Points3D)
``world/plan``              the global plan (LineStrips3D)
``world/robot/trajectory``  the estimated path so far (LineStrips3D)
``world/robot/pose``        the robot, an arrow along base_link x (Arrows3D)
``world/robot/scan``        the current scan's end points in the map (Points3D)
``world/truth``             ground truth path when the source has it (LineStrips3D)
``camera/rgb``              colour image (Image)
``camera/depth``            depth image [m] (DepthImage)
==========================  ==========================================================

Time lines: ``time`` (seconds since the first logged stamp) and ``frame`` (a counter).
Algorithms never import this module; ``rgbdnav`` runs call it.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from sensors.types import RgbdNavError

log = logging.getLogger(__name__)

ARROW_LENGTH_M = 0.3  # [m] drawn robot heading
MAP_COLOUR = (40, 40, 40)
SCAN_COLOUR = (230, 60, 40)
PATH_COLOUR = (30, 120, 230)
TRUTH_COLOUR = (40, 170, 60)
PLAN_COLOUR = (200, 60, 200)
PATH_EVERY = 25  # offline runs log the whole path every this many poses
COSTMAP_COLOUR = (250, 170, 40)


class VisualizerError(RgbdNavError):
    """The viewer could not be started or the recording could not be written."""


class Visualizer(Protocol):
    def frame(self, stamp_ns: int, rgb: np.ndarray | None, depth_m: np.ndarray | None) -> None: ...

    def scan(self, stamp_ns: int, points_map: np.ndarray) -> None: ...

    def pose(
        self, stamp_ns: int, pose: np.ndarray, trajectory: np.ndarray | None = None
    ) -> None: ...

    def truth(self, stamp_ns: int, trajectory: np.ndarray) -> None: ...

    def occupied(self, stamp_ns: int, cells_xy: np.ndarray) -> None: ...

    def costmap(self, stamp_ns: int, cells_xy: np.ndarray) -> None: ...

    def plan(self, stamp_ns: int, path_xy: np.ndarray) -> None: ...

    def close(self) -> None: ...


class NullVisualizer:
    """The default: draws nothing, costs nothing."""

    def frame(self, stamp_ns: int, rgb: np.ndarray | None, depth_m: np.ndarray | None) -> None:
        pass

    def scan(self, stamp_ns: int, points_map: np.ndarray) -> None:
        pass

    def pose(self, stamp_ns: int, pose: np.ndarray, trajectory: np.ndarray | None = None) -> None:
        pass

    def truth(self, stamp_ns: int, trajectory: np.ndarray) -> None:
        pass

    def occupied(self, stamp_ns: int, cells_xy: np.ndarray) -> None:
        pass

    def costmap(self, stamp_ns: int, cells_xy: np.ndarray) -> None:
        pass

    def plan(self, stamp_ns: int, path_xy: np.ndarray) -> None:
        pass

    def close(self) -> None:
        pass


def _xyz(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
    return np.column_stack([xy, np.zeros(len(xy), np.float32)])


class RerunVisualizer:
    """Logs to a rerun recording stream: ``rrd`` saves it to a file, ``viewer`` spawns the
    viewer (both may be given; at least one must be)."""

    def __init__(self, app: str, rrd: Path | None = None, viewer: bool = False) -> None:
        try:
            import rerun as rr
        except ImportError as err:  # pragma: no cover - rerun-sdk is a dependency
            raise VisualizerError("visualisation needs rerun-sdk (pip install rerun-sdk)") from err
        if rrd is None and not viewer:
            raise VisualizerError("RerunVisualizer needs --rrd FILE and/or --viewer")
        self._rr = rr
        self._rec = rr.RecordingStream(f"rgbdnav_{app}")
        self._t0: int | None = None
        self._n = 0
        try:
            if viewer:
                self._rec.spawn(connect=True)
            if rrd is not None:
                rrd.parent.mkdir(parents=True, exist_ok=True)
                self._rec.save(str(rrd))
        except Exception as err:  # rerun raises its own types for a missing viewer binary etc.
            raise VisualizerError(f"cannot start rerun output: {err}") from err
        self._rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rrd = rrd

    def _at(self, stamp_ns: int) -> None:
        if self._t0 is None:
            self._t0 = stamp_ns
        self._rec.set_time("time", duration=(stamp_ns - self._t0) / 1e9)
        self._rec.set_time("frame", sequence=self._n)

    def frame(self, stamp_ns: int, rgb: np.ndarray | None, depth_m: np.ndarray | None) -> None:
        self._n += 1
        self._at(stamp_ns)
        if rgb is not None:
            self._rec.log("camera/rgb", self._rr.Image(rgb))
        if depth_m is not None:
            self._rec.log("camera/depth", self._rr.DepthImage(depth_m, meter=1.0))

    def scan(self, stamp_ns: int, points_map: np.ndarray) -> None:
        self._at(stamp_ns)
        self._rec.log(
            "world/robot/scan", self._rr.Points3D(_xyz(points_map), colors=SCAN_COLOUR, radii=0.02)
        )

    def pose(self, stamp_ns: int, pose: np.ndarray, trajectory: np.ndarray | None = None) -> None:
        self._at(stamp_ns)
        x, y, yaw = (float(v) for v in pose)
        vec = [[ARROW_LENGTH_M * np.cos(yaw), ARROW_LENGTH_M * np.sin(yaw), 0.0]]
        self._rec.log(
            "world/robot/pose",
            self._rr.Arrows3D(origins=[[x, y, 0.0]], vectors=vec, colors=PATH_COLOUR),
        )
        if trajectory is not None and len(trajectory) > 1:
            self._rec.log(
                "world/robot/trajectory",
                self._rr.LineStrips3D([_xyz(trajectory)], colors=PATH_COLOUR),
            )

    def truth(self, stamp_ns: int, trajectory: np.ndarray) -> None:
        self._at(stamp_ns)
        if len(trajectory) > 1:
            self._rec.log(
                "world/truth", self._rr.LineStrips3D([_xyz(trajectory)], colors=TRUTH_COLOUR)
            )

    def occupied(self, stamp_ns: int, cells_xy: np.ndarray) -> None:
        self._at(stamp_ns)
        self._rec.log(
            "world/map", self._rr.Points3D(_xyz(cells_xy), colors=MAP_COLOUR, radii=0.025)
        )

    def costmap(self, stamp_ns: int, cells_xy: np.ndarray) -> None:
        self._at(stamp_ns)
        self._rec.log(
            "world/costmap", self._rr.Points3D(_xyz(cells_xy), colors=COSTMAP_COLOUR, radii=0.025)
        )

    def plan(self, stamp_ns: int, path_xy: np.ndarray) -> None:
        self._at(stamp_ns)
        if len(path_xy) > 1:
            self._rec.log("world/plan", self._rr.LineStrips3D([_xyz(path_xy)], colors=PLAN_COLOUR))

    def close(self) -> None:
        self._rec.flush()
        self._rec.disconnect()


class AsyncVisualizer:
    """Draws on its own thread from a bounded queue; when the queue is full the call is dropped
    and counted, so drawing never holds up the caller (the live run drops visualisation first)."""

    def __init__(self, inner: Any, maxsize: int = 8) -> None:
        self.inner = inner
        self.dropped = 0
        self.drawn = 0
        self._q: queue.Queue[tuple[Callable[..., None], tuple[Any, ...]] | None] = queue.Queue(
            maxsize=maxsize
        )
        self._thread = threading.Thread(target=self._run, name="visualizer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (item := self._q.get()) is not None:
            fn, args = item
            try:
                fn(*args)
                self.drawn += 1
            except Exception:  # a drawing bug must not take the run down
                log.exception("visualisation failed")

    def _put(self, name: str, *args: Any) -> None:
        try:
            self._q.put_nowait((getattr(self.inner, name), args))
        except queue.Full:
            self.dropped += 1

    def frame(self, stamp_ns: int, rgb: np.ndarray | None, depth_m: np.ndarray | None) -> None:
        self._put("frame", stamp_ns, rgb, depth_m)

    def scan(self, stamp_ns: int, points_map: np.ndarray) -> None:
        self._put("scan", stamp_ns, points_map)

    def pose(self, stamp_ns: int, pose: np.ndarray, trajectory: np.ndarray | None = None) -> None:
        self._put("pose", stamp_ns, pose, trajectory)

    def truth(self, stamp_ns: int, trajectory: np.ndarray) -> None:
        self._put("truth", stamp_ns, trajectory)

    def occupied(self, stamp_ns: int, cells_xy: np.ndarray) -> None:
        self._put("occupied", stamp_ns, cells_xy)

    def costmap(self, stamp_ns: int, cells_xy: np.ndarray) -> None:
        self._put("costmap", stamp_ns, cells_xy)

    def plan(self, stamp_ns: int, path_xy: np.ndarray) -> None:
        self._put("plan", stamp_ns, path_xy)

    def close(self) -> None:
        self._q.put(None)  # blocks until there is room: everything queued is drawn
        self._thread.join()
        self.inner.close()


def make_visualizer(app: str, rrd: Path | None, viewer: bool) -> Visualizer:
    """The rerun visualiser when asked for (``--rrd``/``--viewer``), else the no-op one."""
    if rrd is None and not viewer:
        return NullVisualizer()
    return RerunVisualizer(app, rrd, viewer)


def occupied_cells_xy(
    occupied: np.ndarray, origin_xy: tuple[float, float], resolution: float
) -> np.ndarray:
    """Centres [m] of the True cells of a row-0-at-bottom grid mask."""
    rows, cols = np.nonzero(occupied)
    return np.column_stack(
        [origin_xy[0] + (cols + 0.5) * resolution, origin_xy[1] + (rows + 0.5) * resolution]
    )


def log_run(
    vis: Visualizer,
    stamps_ns: np.ndarray,
    poses: np.ndarray,
    scans_map: list[np.ndarray] | None = None,
    occupied_xy: np.ndarray | None = None,
    truth_xy: np.ndarray | None = None,
) -> None:
    """An offline run (map, localize) as a rerun time line: pose, path so far and scan per stamp,
    then the final map and truth."""
    for k in range(len(stamps_ns)):
        t = int(stamps_ns[k])
        # The path so far every few poses (all of it each time would be quadratic).
        last = k == len(stamps_ns) - 1
        vis.pose(t, poses[k], poses[: k + 1, :2] if k % PATH_EVERY == 0 or last else None)
        if scans_map is not None and k < len(scans_map):
            vis.scan(t, scans_map[k])
    if len(stamps_ns):
        t_end = int(stamps_ns[-1])
        if occupied_xy is not None:
            vis.occupied(t_end, occupied_xy)
        if truth_xy is not None:
            vis.truth(t_end, truth_xy)


__all__ = [
    "AsyncVisualizer",
    "NullVisualizer",
    "RerunVisualizer",
    "Visualizer",
    "VisualizerError",
    "log_run",
    "make_visualizer",
    "occupied_cells_xy",
]


def save_fleet_recording(
    path: Path, layers: Sequence[Any], tints_rgb: Sequence[tuple[int, ...]]
) -> None:
    """A static rerun recording of a fleet: per robot a ``world/<name>/map`` transform (the
    static ``world -> <name>/map`` TF) with its wall cells, and its keepout cells under it."""
    try:
        import rerun as rr
    except ImportError as err:  # pragma: no cover - rerun-sdk is a dependency
        raise VisualizerError("visualisation needs rerun-sdk (pip install rerun-sdk)") from err
    rec = rr.RecordingStream("rgbdnav_fleet")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(path))
    except Exception as err:  # rerun raises its own types
        raise VisualizerError(f"cannot start rerun output: {err}") from err
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for ly, tint in zip(layers, tints_rgb, strict=True):
        x, y, yaw = ly.T_world_map
        rot = rr.RotationAxisAngle(axis=[0.0, 0.0, 1.0], radians=yaw)
        rec.log(
            f"world/{ly.name}/map",
            rr.Transform3D(translation=[x, y, 0.0], rotation=rot),
            static=True,
        )
        g = ly.grid.geometry
        walls = occupied_cells_xy(
            ly.grid.occupied_mask(ly.occupied_thresh), (g.origin_x, g.origin_y), g.resolution
        )
        rec.log(
            f"world/{ly.name}/map/walls",
            rr.Points3D(_xyz(walls), colors=tint, radii=0.5 * g.resolution),
            static=True,
        )
        if ly.keepout is not None:
            k = ly.keepout.geometry
            zone = occupied_cells_xy(
                ly.keepout.occupied_mask(0.65), (k.origin_x, k.origin_y), k.resolution
            )
            rec.log(
                f"world/{ly.name}/map/keepout_mask",
                rr.Points3D(_xyz(zone), colors=tint, radii=0.5 * k.resolution),
                static=True,
            )
    rec.flush()
    rec.disconnect()
