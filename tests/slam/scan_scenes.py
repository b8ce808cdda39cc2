"""Synthetic 2D laser scenes for scan-matching and mapper tests: exact ray casting on segments."""

from __future__ import annotations

import math

import numpy as np

from sensors.types import LaserScan

# An 8 m x 6 m room with an inner wall stub, a pillar and a cabinet: enough structure in x, y and
# yaw for a unique match.
ROOM = np.array(
    [
        [0, 0, 8, 0],
        [8, 0, 8, 6],
        [8, 6, 0, 6],
        [0, 6, 0, 0],
        [3, 0, 3, 2.5],
        [5.5, 3.5, 6.0, 3.5],
        [6.0, 3.5, 6.0, 4.0],
        [6.0, 4.0, 5.5, 4.0],
        [5.5, 4.0, 5.5, 3.5],
        [1.0, 5.0, 2.2, 5.0],
        [2.2, 5.0, 2.2, 6.0],
    ],
    dtype=np.float64,
)


def raycast(
    segments: np.ndarray,
    pose: np.ndarray,
    n_beams: int = 361,
    fov: float = math.pi,
    range_max: float = 20.0,
    noise_m: float = 0.0,
    seed: int = 0,
    stamp_ns: int = 0,
) -> LaserScan:
    """A LaserScan from ``pose`` (x, y, yaw) against segments (S, 4) = x0 y0 x1 y1."""
    angle_min = -fov / 2
    inc = fov / (n_beams - 1)
    a = pose[2] + angle_min + inc * np.arange(n_beams)
    d = np.column_stack([np.cos(a), np.sin(a)])  # (B, 2)
    p0 = segments[:, :2]
    e = segments[:, 2:] - p0  # (S, 2)
    w = p0 - pose[:2]  # (S, 2)
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (B, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / den
        u = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    r = np.where(hit, t, np.inf).min(axis=1)
    if noise_m > 0:
        r = r + np.random.default_rng(seed).normal(0, noise_m, n_beams)
    r = np.where(r > range_max, np.inf, r)
    return LaserScan(stamp_ns, angle_min, inc, r.astype(np.float32), 0.02, range_max)


def write_flaser_log(
    path, truth: np.ndarray, odom: np.ndarray, t0: float = 100.0, segments: np.ndarray = ROOM
):  # type: ignore[no-untyped-def]
    """A CARMEN log of FLASER lines (361 beams, 0.5 deg, 5 mm noise, 5 Hz) ray-cast at the
    ``truth`` poses, with ``odom`` in the pose fields; returns ``path``."""
    lines = []
    for k, (p, o) in enumerate(zip(truth, odom, strict=True)):
        scan = raycast(segments, p, noise_m=0.005, seed=k)
        r = np.where(np.isfinite(scan.ranges), scan.ranges, 81.91)
        t = t0 + 0.2 * k
        pose = f"{o[0]:.6f} {o[1]:.6f} {o[2]:.6f}"
        lines.append(
            f"FLASER 361 {' '.join(f'{v:.3f}' for v in r)} {pose} {pose} {t:.6f} h {t:.6f}"
        )
    path.write_text("\n".join(lines) + "\n")
    return path


def corrupt_steps(truth: np.ndarray, scale: float, yaw_bias_per_step: float) -> np.ndarray:
    """Odometry from the truth's increments with a translation scale error and a yaw bias."""
    out = [truth[0].copy()]
    for a, b in zip(truth[:-1], truth[1:], strict=True):
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        lx, ly, dyaw = scale * (c * dx + s * dy), scale * (-s * dx + c * dy), b[2] - a[2]
        p = out[-1]
        cp, sp = math.cos(p[2]), math.sin(p[2])
        out.append(
            np.array(
                [
                    p[0] + cp * lx - sp * ly,
                    p[1] + sp * lx + cp * ly,
                    p[2] + dyaw + yaw_bias_per_step,
                ]
            )
        )
    return np.array(out)
