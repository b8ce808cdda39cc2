"""A last line of defence between any controller and the wheels, after Nav2's collision_monitor:
a *stop* zone and a *slowdown* zone, checked against recent obstacle points.

A Kinect sees nothing nearer than ~0.5 m, exactly where a door frame is when the robot is about
to hit it; so the points are a short memory of recent scans carried along by odometry
(:class:`ObstacleMemory`), not only the current scan. The zones are the circular footprint
(radius + ``lateral_margin``) swept along the commanded arc (v, w) for ``stop_distance`` and for
``slowdown_distance`` (Nav2's approach model projects the footprint along the twist the same
way): a point the sweep comes within reach of, and nearer than it is now, stops the forward
motion (turning in place stays allowed: the footprint is a circle) or scales it by
``slowdown_ratio``. A point the motion moves away from (a jamb already beside or behind the
robot) limits nothing, so a robot that came too close can drive out. Reversing is not limited:
the camera looks forward only, so there is nothing to check against.

:class:`CollisionMonitor` is the one stage both drivers put between their command and the wheels
(``rgbdnav navigate``'s simulated robot and ``rgbdnav live``'s board): the navigator plans and
follows on the map pose, which the localiser may have wrong by a door jamb's width; the monitor
judges on what the camera saw relative to the robot, which odometry keeps right over seconds.
Why: docs/design/navigator.md ("Grazing a door jamb").
"""

from __future__ import annotations

import math
from collections import Counter, deque

import numpy as np

from nav.config import CollisionMonitorConfig
from slam.geometry import ominus, oplus

ARC_STEP_M = 0.02  # [m] spacing of the footprint positions along a swept arc


def swept_hits(points: np.ndarray, v: float, w: float, distance: float, reach: float) -> bool:
    """A point (N, 2) that a circle of ``reach`` [m], its centre driven ``distance`` [m] along
    the arc of (v > 0, w), comes within reach of and nearer than it is now."""
    d0 = np.hypot(points[:, 0], points[:, 1])
    near = points[d0 < distance + reach]
    if len(near) == 0:
        return False
    n = max(1, math.ceil(distance / ARC_STEP_M))
    s = np.linspace(distance / n, distance, n)
    k = w / v  # [1/m] curvature
    if abs(k) < 1e-9:
        cx, cy = s, np.zeros(n)
    else:
        cx, cy = np.sin(k * s) / k, (1.0 - np.cos(k * s)) / k
    d = np.hypot(near[:, :1] - cx, near[:, 1:] - cy).min(axis=1)
    return bool(np.any((d < reach) & (d < d0[d0 < distance + reach])))


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
    reach = radius + lateral_margin
    if swept_hits(points_base, v, w, stop_distance, reach):
        return 0.0, w, "stop"
    if swept_hits(points_base, v, w, slowdown_distance, reach):
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

    def add_scan(self, stamp_ns: int, odom_pose: np.ndarray, points_base: np.ndarray) -> None:
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


__all__ = ["CollisionMonitor", "ObstacleMemory", "limit_twist", "swept_hits"]
