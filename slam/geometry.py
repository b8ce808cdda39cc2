"""Planar (SE(2)) pose helpers, vectorised: poses are (x [m], y [m], yaw [rad]) scalars or arrays
that broadcast together."""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike

from sensors.types import Pose2

A = TypeVar("A", float, np.ndarray)


def wrap_angle(a: A) -> A:
    """Angle(s) into [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def compose(
    x1: ArrayLike, y1: ArrayLike, yaw1: ArrayLike, x2: ArrayLike, y2: ArrayLike, yaw2: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose 1 (+) pose 2: pose 2, given in frame 1, expressed where frame 1 is expressed.
    Yaw is summed, not wrapped, so a chain of compositions stays continuous."""
    ax, ay, ayaw, bx, by, byaw = (
        np.asarray(v, dtype=np.float64) for v in (x1, y1, yaw1, x2, y2, yaw2)
    )
    c, s = np.cos(ayaw), np.sin(ayaw)
    return ax + c * bx - s * by, ay + s * bx + c * by, ayaw + byaw


def between(a: Pose2, b: Pose2) -> Pose2:
    """a^-1 (+) b: pose b expressed in frame a (yaw wrapped)."""
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    dx, dy = b.x - a.x, b.y - a.y
    return Pose2(c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(b.yaw - a.yaw)))


def oplus(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """a (+) b for pose arrays (..., 3) of (x, y, yaw) that broadcast together, yaw wrapped."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap_angle(a[..., 2] + b[..., 2]),
        ],
        axis=-1,
    )


def ominus(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """a^-1 (+) b for pose arrays (..., 3): pose b in the frame of pose a, yaw wrapped."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def rotate_covariance(cov: np.ndarray, yaw: float) -> np.ndarray:
    """A planar (x, y, yaw) covariance with its (x, y) axes turned by ``yaw``: ``R cov R^T``.
    ``yaw`` = the heading of a body frame takes it from that frame to the map; ``-yaw`` back."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot @ cov @ rot.T


def lever_jacobian(lever: ArrayLike) -> np.ndarray:
    """(..., 3, 3) d(point pose)/d(pose) for a point rigidly ``lever`` (..., 2) [m] from a pose's
    origin, the lever in the world frame: ``[[1, 0, -ly], [0, 1, lx], [0, 0, 1]]``. A covariance
    carried to that point is ``J C J^T``: a yaw sigma adds lever x sigma of position across it."""
    lever = np.asarray(lever, dtype=np.float64)
    j = np.broadcast_to(np.eye(3), (*lever.shape[:-1], 3, 3)).copy()
    j[..., 0, 2] = -lever[..., 1]
    j[..., 1, 2] = lever[..., 0]
    return j


def path_length(xy: ArrayLike) -> float:
    """Length [m] of the polyline through the points (N, 2); 0 for fewer than two."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return float(np.hypot(*np.diff(xy, axis=0).T).sum()) if len(xy) > 1 else 0.0
