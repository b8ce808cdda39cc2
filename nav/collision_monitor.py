"""A last line of defence between any controller and the wheels, after Nav2's collision_monitor:
a *stop* box and a *slowdown* box ahead of the robot, checked against recent obstacle points.

A Kinect sees nothing nearer than ~0.5 m, exactly where a door frame is when the robot is about
to hit it; so the points are a short memory of recent scans carried along by odometry
(:class:`ObstacleMemory`), not only the current scan. Boxes (base_link, x forward):

    stop:      -radius <= x <= radius + stop_distance,      |y| <= radius + lateral_margin
    slowdown:  -radius <= x <= radius + slowdown_distance,  |y| <= radius + lateral_margin

(x from -radius: a door frame beside the robot counts while the robot still turns towards it.)

Forward motion with a point in the stop box is cut to 0 (turning in place stays allowed); in the
slowdown box it is scaled by ``slowdown_ratio``. Reversing is not limited: the camera looks
forward only, so there is nothing to check against.

:class:`CollisionMonitor` is the one stage both drivers put between their command and the wheels
(``rgbdnav navigate``'s simulated robot and ``rgbdnav live``'s board): the navigator plans and
follows on the map pose, which the localiser may have wrong by a door jamb's width; the monitor
judges on what the camera saw relative to the robot, which odometry keeps right over seconds.
Why: docs/design/navigator.md ("Grazing a door jamb").
"""

from __future__ import annotations

from collections import Counter, deque

import numpy as np

from nav.config import CollisionMonitorConfig
from sensors.types import LaserScan
from slam.geometry import ominus, oplus
from slam.scan_matching import scan_points, transform_points


def limit_twist(
    points_base: np.ndarray,
    v: float,
    w: float,
    radius: float,
    stop_distance: float,
    slowdown_distance: float,
    slowdown_ratio: float,
    lateral_margin: float = 0.0,
) -> tuple[float, float, str]:
    """(v, w, action) with action "" (free), "slowdown" or "stop"; ``points_base`` (N, 2) [m]."""
    if v <= 0.0 or len(points_base) == 0:
        return v, w, ""
    x, y = points_base[:, 0], points_base[:, 1]
    ahead = (x >= -radius) & (np.abs(y) <= radius + lateral_margin)
    if np.any(ahead & (x <= radius + stop_distance)):
        return 0.0, w, "stop"
    if np.any(ahead & (x <= radius + slowdown_distance)):
        return v * slowdown_ratio, w, "slowdown"
    return v, w, ""


class ObstacleMemory:
    """Scan end points of the last ``keep_s`` seconds, stored in the odom frame and handed back
    in base_link at the current odometry pose."""

    def __init__(self, keep_s: float) -> None:
        self.keep_ns = int(keep_s * 1e9)
        self._scans: deque[tuple[int, np.ndarray]] = deque()

    def add(self, stamp_ns: int, odom_pose: np.ndarray, points_base: np.ndarray) -> None:
        pts = oplus(
            np.asarray(odom_pose, dtype=np.float64),
            np.column_stack([points_base, np.zeros(len(points_base))]),
        )[:, :2]
        self._scans.append((stamp_ns, pts))
        while self._scans and self._scans[0][0] < stamp_ns - self.keep_ns:
            self._scans.popleft()

    def points_in_base(self, odom_pose: np.ndarray) -> np.ndarray:
        if not self._scans:
            return np.zeros((0, 2))
        pts = np.vstack([p for _, p in self._scans])
        rel = ominus(
            np.asarray(odom_pose, dtype=np.float64), np.column_stack([pts, np.zeros(len(pts))])
        )
        return rel[:, :2]


class CollisionMonitor:
    """Scans in (:meth:`add_scan`, base_link points at an odom pose), commands out limited
    (:meth:`limit`); ``counts`` has the stops and slowdowns, each counted when it begins."""

    def __init__(self, cfg: CollisionMonitorConfig, radius: float) -> None:
        self.cfg, self.radius = cfg, radius
        self.memory = ObstacleMemory(cfg.observation_memory)
        self.counts: Counter[str] = Counter()
        self.action = ""  # the last command's action: "", "slowdown" or "stop"

    def add_scan(self, odom_pose: np.ndarray, scan: LaserScan, scan_in_base: np.ndarray) -> None:
        """A scan taken at the odom pose ``odom_pose``, in the frame at ``scan_in_base`` (x, y,
        yaw) in base_link: ``rgbdnav navigate``'s laser at the camera, ``rgbdnav live``'s
        ``depth_to_scan.output_frame`` (:func:`slam.depth_to_scan.scan_frame_in_base`)."""
        pts = transform_points(np.asarray(scan_in_base, dtype=np.float64), scan_points(scan))
        self.add_points(scan.stamp_ns, odom_pose, pts)

    def add_points(self, stamp_ns: int, odom_pose: np.ndarray, points_base: np.ndarray) -> None:
        """Obstacle points (N, 2) in base_link seen at the odom pose ``odom_pose``."""
        self.memory.add(stamp_ns, odom_pose, points_base)

    def limit(self, v: float, w: float, odom_pose: np.ndarray) -> tuple[float, float, str]:
        """(v, w, action) for the wheels at the odom pose ``odom_pose``."""
        c = self.cfg
        if not c.enabled:
            return v, w, ""
        pts = self.memory.points_in_base(odom_pose) if v > 0.0 else np.zeros((0, 2))
        v, w, action = limit_twist(
            pts,
            v,
            w,
            self.radius,
            c.stop_distance,
            c.slowdown_distance,
            c.slowdown_ratio,
            c.lateral_margin,
        )
        if action and action != self.action:
            self.counts[f"collision_monitor_{action}s"] += 1
        self.action = action
        return v, w, action


__all__ = ["CollisionMonitor", "ObstacleMemory", "limit_twist"]
