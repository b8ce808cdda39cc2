"""Trajectory error metrics over planar poses (pure functions, no I/O).

Conventions follow the TUM RGB-D benchmark and evo: the estimate is compared to the reference at
the estimate's stamps (reference interpolated), ATE is the RMSE of position differences after an
optional rigid alignment, drift is end-point error per distance travelled.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from slam.geometry import wrap_angle


def interpolate_poses(
    t_ref: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, t_query: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reference poses at ``t_query`` (linear, yaw unwrapped); also a mask of queries inside the
    reference's time span (outside it nothing is extrapolated)."""
    t_ref = np.asarray(t_ref, dtype=np.float64)
    tq = np.asarray(t_query, dtype=np.float64)
    inside = (tq >= t_ref[0]) & (tq <= t_ref[-1])
    yaw_u = np.unwrap(yaw)
    return (np.interp(tq, t_ref, x), np.interp(tq, t_ref, y), np.interp(tq, t_ref, yaw_u), inside)


def align_se2(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation R (2x2) and translation t with dst ~ R src + t (Umeyama, no scale).
    ``src``, ``dst``: (N, 2)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s)
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, d]) @ vt
    return r, mu_d - r @ mu_s


@dataclass(frozen=True)
class DriftReport:
    matched: int  # poses compared
    path_length_m: float  # [m] reference path length over the compared span
    ate_rmse_m: float  # [m] position RMSE, start-aligned (as odometry is)
    ate_rmse_aligned_m: float  # [m] position RMSE after the best SE(2) alignment
    final_position_error_m: float  # [m]
    final_heading_error_deg: float  # [deg]
    drift_percent: float  # final position error / path length * 100
    drift_per_10m_m: float  # [m] final position error per 10 m travelled

    def as_dict(self) -> dict[str, float]:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def drift_report(
    t_est: np.ndarray,
    est: tuple[np.ndarray, np.ndarray, np.ndarray],
    t_ref: np.ndarray,
    ref: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> DriftReport:
    """Compare an estimate that starts at the reference's start pose (dead reckoning)."""
    rx, ry, ryaw, inside = interpolate_poses(t_ref, *ref, t_est)
    if inside.sum() < 2:
        raise ValueError("estimate and reference do not overlap in time")
    ex, ey, eyaw = (np.asarray(a)[inside] for a in est)
    rx, ry, ryaw = rx[inside], ry[inside], ryaw[inside]
    err = np.hypot(ex - rx, ey - ry)
    r, t = align_se2(np.column_stack([ex, ey]), np.column_stack([rx, ry]))
    aligned = np.column_stack([ex, ey]) @ r.T + t
    err_aligned = np.hypot(aligned[:, 0] - rx, aligned[:, 1] - ry)
    length = float(np.hypot(np.diff(rx), np.diff(ry)).sum())
    final = float(err[-1])
    return DriftReport(
        matched=int(inside.sum()),
        path_length_m=length,
        ate_rmse_m=float(np.sqrt(np.mean(err**2))),
        ate_rmse_aligned_m=float(np.sqrt(np.mean(err_aligned**2))),
        final_position_error_m=final,
        final_heading_error_deg=float(np.degrees(np.abs(wrap_angle(eyaw[-1] - ryaw[-1])))),
        drift_percent=100 * final / length if length > 0 else float("nan"),
        drift_per_10m_m=10 * final / length if length > 0 else float("nan"),
    )


def drift_summary(
    t_est: np.ndarray,
    est: tuple[np.ndarray, np.ndarray, np.ndarray],
    t_ref: np.ndarray,
    ref: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> dict[str, Any]:
    """:func:`drift_report` for a run's summary: when the two do not overlap in time (a source
    whose every frame was unusable leaves an estimate of 0 or 1 poses), a summary that says so
    rather than an exception after the run's work is done."""
    try:
        return drift_report(t_est, est, t_ref, ref).as_dict()
    except ValueError as err:
        return {"matched": 0, "not_compared": str(err), "estimate_poses": int(len(t_est))}
