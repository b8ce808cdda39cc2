"""Simulated depth-camera scans: beams ray-marched through a world's floor plan, with the range
noise of a Kinect v1 (structured light: disparity noise through z = f b / d grows with z^2).

`rgbdnav navigate` senses with these in simulated time; they stand in for depth -> scan of a
rendered frame at a fraction of the cost (no image, one beam per few image columns).
"""

from __future__ import annotations

import math

import numpy as np

from sensors.sim.world import FloorPlan

RAY_STEP_CELLS = 0.5  # [cells] ray-marching step in the floor plan


def cast_scan(
    plan: FloorPlan,
    pose: np.ndarray,
    angles: np.ndarray,
    range_min: float,
    range_max: float,
) -> np.ndarray:
    """(N,) float32 ranges [m] of beams at ``angles`` [rad, laser frame] from ``pose`` (x, y, yaw)
    marched through the occupied cells of ``plan``: +inf = no return within ``range_max``, NaN =
    a return closer than ``range_min`` (a depth camera sees nothing there). Outside the floor plan
    is free space."""
    step = RAY_STEP_CELLS * plan.resolution  # [m]
    s = np.arange(1, math.ceil(range_max / step) + 2) * step  # (S,) [m] sample distances
    a = pose[2] + angles
    x = pose[0] + np.cos(a)[:, None] * s  # (N, S)
    y = pose[1] + np.sin(a)[:, None] * s
    col = np.floor((x - plan.origin_x) / plan.resolution).astype(np.int64)
    row = np.floor((y - plan.origin_y) / plan.resolution).astype(np.int64)
    h, w = plan.occupied.shape
    inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    hit = np.zeros(x.shape, dtype=bool)
    hit[inside] = plan.occupied[row[inside], col[inside]]
    any_hit = hit.any(axis=1)
    r = np.where(any_hit, s[np.argmax(hit, axis=1)], np.inf)
    r = np.where(r > range_max, np.inf, r)
    r = np.where(r < range_min, np.nan, r)
    return r.astype(np.float32)


def depth_range_sigma(
    ranges: np.ndarray,
    focal_px: float,
    baseline_m: float,
    disparity_sigma_px: float,
    subpixel: int,
) -> np.ndarray:
    """Kinect v1 range noise [m]: disparity noise and 1/``subpixel``-px quantisation through
    z = f b / d give sigma_z = z^2 sigma_d / (f b), sigma_d^2 = sigma_n^2 + (1/subpixel)^2 / 12."""
    sigma_d = math.sqrt(disparity_sigma_px**2 + (1.0 / subpixel) ** 2 / 12.0)  # [px]
    return np.asarray(ranges, dtype=np.float64) ** 2 * sigma_d / (focal_px * baseline_m)


__all__ = ["RAY_STEP_CELLS", "cast_scan", "depth_range_sigma"]
