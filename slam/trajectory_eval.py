"""Trajectory evaluation against a reference: ATE and RPE in 3-D (pure functions, no I/O).

Conventions follow the TUM RGB-D benchmark tools (``associate.py``, ``evaluate_ate.py``,
``evaluate_rpe.py``) and evo:

- Association: one-to-one, closest pair first, ``|t_est - t_ref| < max_diff`` (strict).
- Alignment: least-squares ``ref ~ s R est + t`` (Horn / Umeyama) over the associated positions;
  ``se3`` fixes ``s = 1`` (TUM ATE), ``sim3`` also fits ``s`` (monocular), ``se2`` rotates about
  z and shifts in x, y only (planar robots), ``none`` leaves the estimate as it is.
- ATE: statistics of ``|p_ref_i - (s R p_est_i + t)|``.
- RPE: for pose pairs (i, j) a fixed delta apart, the error pose
  ``E = (P_i^-1 P_j)^-1 (Q_i^-1 Q_j)`` (P estimate, Q reference); translational error ``|t(E)|``
  [m], rotational error ``angle(R(E))`` [rad]. The delta is counted in frames, or in metres
  travelled along the reference (evo; TUM measures along the estimate, which a scale error biases).

Poses are (N, 4, 4) homogeneous matrices; quaternions are (x, y, z, w) as in TUM files.

The one exception to "no I/O" is :func:`read_relations`, the reader of the relations files that
:func:`relations_error` scores against; it lives beside its kernel so the format is documented once.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from sensors.recording import associate as _associate_stamps
from sensors.tum import StampedText, read_stamped_text
from sensors.types import RgbdNavError, SensorError, parse_stamp
from slam.geometry import ominus

AlignMode = Literal["se3", "sim3", "se2", "none"]
DeltaUnit = Literal["m", "frames"]
ALIGN_MODES: tuple[str, ...] = ("se3", "sim3", "se2", "none")
DELTA_UNITS: tuple[str, ...] = ("m", "frames")
MIN_POINTS = {"se3": 3, "sim3": 3, "se2": 2, "none": 1}  # poses needed to fix the alignment
PATH_ROUNDOFF_M = 1e-9  # [m] slack so a pair exactly delta apart survives cumulative-sum round-off
DEGENERATE_SPREAD_M = 1e-12  # [m^2] position variance below which no scale can be fitted
RELATION_COLUMNS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")


class TrajectoryEvalError(RgbdNavError):
    """Trajectories cannot be compared (too few matches, bad options, degenerate geometry)."""


# 1. Rotations and poses ----------------------------------------------------------------------


def rotation_from_quaternion(quat_xyzw: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (x, y, z, w); normalised first."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def quaternion_from_rotation(rot: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w), w >= 0, of (..., 3, 3) rotation matrices.

    Uses the largest of the four candidate denominators per matrix (Shepperd), so it is stable
    for every rotation, including half turns."""
    r = np.asarray(rot, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # 4 q_k^2 for k = w, x, y, z: pick the largest to divide by.
    cand = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )
    k = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], -1)[..., 0], 1e-300))
    d_zy = r[..., 2, 1] - r[..., 1, 2]
    d_xz = r[..., 0, 2] - r[..., 2, 0]
    d_yx = r[..., 1, 0] - r[..., 0, 1]
    s_xy = r[..., 0, 1] + r[..., 1, 0]
    s_xz = r[..., 0, 2] + r[..., 2, 0]
    s_yz = r[..., 1, 2] + r[..., 2, 1]
    by_k = np.stack(
        [
            np.stack([d_zy, d_xz, d_yx, 0.25 * s * s], -1),  # w largest
            np.stack([0.25 * s * s, s_xy, s_xz, d_zy], -1),  # x largest
            np.stack([s_xy, 0.25 * s * s, s_yz, d_xz], -1),  # y largest
            np.stack([s_xz, s_yz, 0.25 * s * s, d_yx], -1),  # z largest
        ],
        axis=-2,
    )
    q = np.take_along_axis(by_k, k[..., None, None], -2)[..., 0, :] / s[..., None]
    return q * np.where(q[..., 3:] < 0, -1.0, 1.0)


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """Angle [rad] in [0, pi] of (..., 3, 3) rotation matrices (clipped against round-off)."""
    trace = np.trace(np.asarray(rot, dtype=np.float64), axis1=-2, axis2=-1)
    return np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))


def poses_from_tum(xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4, 4) homogeneous poses from TUM positions (N, 3) [m] and quaternions (N, 4)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    poses = np.zeros((len(xyz), 4, 4))
    poses[:, :3, :3] = rotation_from_quaternion(quat_xyzw)
    poses[:, :3, 3] = xyz
    poses[:, 3, 3] = 1.0
    return poses


def invert_poses(poses: np.ndarray) -> np.ndarray:
    """(..., 4, 4) inverses of rigid poses, without a general matrix inverse."""
    r_t = np.swapaxes(poses[..., :3, :3], -1, -2)
    out = np.zeros_like(poses)
    out[..., :3, :3] = r_t
    out[..., :3, 3] = -(r_t @ poses[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def relative_poses(poses: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``P_i^-1 P_j`` for index arrays ``i``, ``j`` (evo's ``relative_se3``)."""
    return invert_poses(poses[i]) @ poses[j]


# 2. Association -----------------------------------------------------------------------------


def associate(
    t_a_ns: np.ndarray, t_b_ns: np.ndarray, max_diff_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays (ia, ib) of one-to-one matches ``|t_a - t_b| < max_diff_ns``, closest pairs
    first (TUM ``associate.py``); both inputs strictly increasing [ns], output sorted by ``a``."""
    if max_diff_ns <= 0:
        raise TrajectoryEvalError(f"max difference must be > 0 ns, got {max_diff_ns}")
    return _associate_stamps(t_a_ns, t_b_ns, int(max_diff_ns))


# 3. Alignment -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Alignment:
    """``x_ref = scale * rotation @ x_est + translation``."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,) [m]
    scale: float = 1.0  # [-]

    def apply_points(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) positions [m] mapped into the reference frame."""
        return self.scale * np.asarray(xyz) @ self.rotation.T + self.translation

    def apply_poses(self, poses: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses mapped into the reference frame; the scale applies to positions only,
        so rotations stay orthonormal."""
        out = np.array(poses, dtype=np.float64, copy=True)
        out[:, :3, :3] = self.rotation @ out[:, :3, :3]
        out[:, :3, 3] = self.apply_points(out[:, :3, 3])
        return out

    def as_dict(self) -> dict[str, object]:
        return {
            "scale": float(self.scale),
            "translation_m": [float(v) for v in self.translation],
            "rotation_quat_xyzw": [float(v) for v in quaternion_from_rotation(self.rotation)],
            "rotation_deg": float(np.degrees(rotation_angle(self.rotation))),
        }


IDENTITY = Alignment(np.eye(3), np.zeros(3), 1.0)


def umeyama(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (R, t, s) with ``dst ~ s R src + t`` for (N, d) point sets (Umeyama 1991).

    With Sigma = (dst - mu_d)^T (src - mu_s) / N = U D V^T and S = diag(1, ..., 1, det(U V^T)):
    R = U S V^T, s = tr(D S) / var(src), t = mu_d - s R mu_s. Without scale this is Horn's
    closed form that TUM ``evaluate_ate.py`` uses."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_s, dst - mu_d
    sigma = dst_c.T @ src_c / len(src)
    u, d, vt = np.linalg.svd(sigma)
    s_diag = np.ones(src.shape[1])
    s_diag[-1] = np.sign(np.linalg.det(u @ vt)) or 1.0  # reflection -> proper rotation
    rot = (u * s_diag) @ vt
    scale = 1.0
    if with_scale:
        var_src = float(np.mean(np.sum(src_c**2, axis=1)))
        if var_src < DEGENERATE_SPREAD_M:
            raise TrajectoryEvalError("cannot fit a scale: the estimate positions do not spread")
        scale = float(np.sum(d * s_diag) / var_src)
    return rot, mu_d - scale * rot @ mu_s, scale


def align(est_xyz: np.ndarray, ref_xyz: np.ndarray, mode: AlignMode = "se3") -> Alignment:
    """The alignment of matched estimate positions onto reference positions, both (N, 3) [m]."""
    if mode not in ALIGN_MODES:
        raise TrajectoryEvalError(
            f"unknown alignment {mode!r}; use one of {', '.join(ALIGN_MODES)}"
        )
    if len(est_xyz) < MIN_POINTS[mode]:
        raise TrajectoryEvalError(
            f"{mode} alignment needs at least {MIN_POINTS[mode]} matched poses, got {len(est_xyz)}"
        )
    if mode == "none":
        return IDENTITY
    if mode == "se2":
        r2, t2, _ = umeyama(np.asarray(est_xyz)[:, :2], np.asarray(ref_xyz)[:, :2])
        rot = np.eye(3)
        rot[:2, :2] = r2
        return Alignment(rot, np.array([t2[0], t2[1], 0.0]), 1.0)
    rot, t, s = umeyama(est_xyz, ref_xyz, with_scale=mode == "sim3")
    return Alignment(rot, t, s)


# 4. Error statistics ------------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a set of non-negative errors, in the errors' unit."""

    count: int
    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64)
        if e.size == 0:
            raise TrajectoryEvalError("no errors to summarise")
        return cls(
            count=int(e.size),
            rmse=float(np.sqrt(np.mean(e**2))),
            mean=float(e.mean()),
            median=float(np.median(e)),
            std=float(e.std()),
            min=float(e.min()),
            max=float(e.max()),
        )

    def scaled(self, factor: float) -> ErrorStats:
        """The same statistics in another unit (e.g. rad -> deg)."""
        f = float(factor)
        return ErrorStats(
            self.count,
            f * self.rmse,
            f * self.mean,
            f * self.median,
            f * self.std,
            f * self.min,
            f * self.max,
        )

    def as_dict(self) -> dict[str, float | int]:
        return dict(vars(self))


# 5. ATE and RPE -----------------------------------------------------------------------------


def ate_errors(est_xyz: np.ndarray, ref_xyz: np.ndarray, alignment: Alignment) -> np.ndarray:
    """(N,) translational errors [m] of matched positions after ``alignment``."""
    return np.linalg.norm(alignment.apply_points(est_xyz) - np.asarray(ref_xyz), axis=1)


def delta_pairs(
    ref_xyz: np.ndarray, delta: float, unit: DeltaUnit = "m"
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) for RPE: from every pose i, the first pose j at least ``delta`` metres
    further along the reference path, or exactly ``delta`` frames later. Pairs whose j would fall
    past the end are dropped."""
    n = len(ref_xyz)
    if unit not in DELTA_UNITS:
        raise TrajectoryEvalError(
            f"unknown delta unit {unit!r}; use one of {', '.join(DELTA_UNITS)}"
        )
    if not delta > 0:
        raise TrajectoryEvalError(f"delta must be > 0, got {delta}")
    if unit == "frames":
        if delta != int(delta):
            raise TrajectoryEvalError(f"a delta in frames must be a whole number, got {delta}")
        i = np.arange(max(n - int(delta), 0))
        return i, i + int(delta)
    steps = np.linalg.norm(np.diff(np.asarray(ref_xyz, dtype=np.float64), axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])  # [m]
    j = np.searchsorted(travelled, travelled + (delta - PATH_ROUNDOFF_M), side="left")
    i = np.arange(n)
    keep = j < n
    return i[keep], j[keep]


def rpe_errors(
    est_poses: np.ndarray, ref_poses: np.ndarray, i: np.ndarray, j: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Translational [m] and rotational [rad] relative pose errors of matched (N, 4, 4) poses over
    the pairs (i, j)."""
    if len(i) == 0:
        raise TrajectoryEvalError("no pose pairs for RPE: the delta is longer than the trajectory")
    rel_est = relative_poses(est_poses, i, j)
    rel_ref = relative_poses(ref_poses, i, j)
    err = invert_poses(rel_est) @ rel_ref
    return np.linalg.norm(err[:, :3, 3], axis=1), rotation_angle(err[:, :3, :3])


@dataclass(frozen=True)
class TrajectoryEvaluation:
    """Everything ``evaluate`` computes; arrays are over the matched poses."""

    matched: int
    alignment: Alignment
    ate: ErrorStats  # [m]
    rpe_trans: ErrorStats | None  # [m] per delta; None when no pair fits
    rpe_rot: ErrorStats | None  # [rad] per delta
    ate_per_pose_m: np.ndarray  # (matched,)
    est_aligned_xyz: np.ndarray  # (matched, 3) [m]
    ref_xyz: np.ndarray  # (matched, 3) [m]
    est_index: np.ndarray  # (matched,) rows of the estimate used
    ref_index: np.ndarray  # (matched,) rows of the reference used


def evaluate(
    est_stamps_ns: np.ndarray,
    est_poses: np.ndarray,
    ref_stamps_ns: np.ndarray,
    ref_poses: np.ndarray,
    *,
    align_mode: AlignMode = "se3",
    max_diff_ns: int = 20_000_000,
    delta: float = 1.0,
    delta_unit: DeltaUnit = "m",
) -> TrajectoryEvaluation:
    """ATE and RPE of an estimate against a reference, both as stamps [ns] and (N, 4, 4) poses."""
    # 1. Match poses in time.
    ie, ir = associate(est_stamps_ns, ref_stamps_ns, max_diff_ns)
    if ie.size == 0:
        raise TrajectoryEvalError("no estimate stamp is within the window of a reference stamp")
    est, ref = est_poses[ie], ref_poses[ir]
    # 2. Align the estimate onto the reference, then 3. score absolute positions.
    alignment = align(est[:, :3, 3], ref[:, :3, 3], align_mode)
    aligned = alignment.apply_poses(est)
    ate = ate_errors(est[:, :3, 3], ref[:, :3, 3], alignment)
    # 4. Relative errors over the delta (scale matters, the rigid part does not).
    pi, pj = delta_pairs(ref[:, :3, 3], delta, delta_unit)
    rpe_t = rpe_r = None
    if pi.size:
        trans, rot = rpe_errors(aligned, ref, pi, pj)
        rpe_t, rpe_r = ErrorStats.of(trans), ErrorStats.of(rot)
    return TrajectoryEvaluation(
        matched=int(ie.size),
        alignment=alignment,
        ate=ErrorStats.of(ate),
        rpe_trans=rpe_t,
        rpe_rot=rpe_r,
        ate_per_pose_m=ate,
        est_aligned_xyz=aligned[:, :3, 3],
        ref_xyz=ref[:, :3, 3],
        est_index=ie,
        ref_index=ir,
    )


# 6. Relations metric (Kümmerle et al. 2009) ---------------------------------------------------


def _nearest_index(stamps_ns: np.ndarray, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest of sorted ``stamps_ns`` for each query, and |difference| [ns]."""
    j = np.clip(np.searchsorted(stamps_ns, query_ns), 1, len(stamps_ns) - 1)
    left_closer = np.abs(query_ns - stamps_ns[j - 1]) <= np.abs(stamps_ns[j] - query_ns)
    idx = np.where(left_closer, j - 1, j) if len(stamps_ns) > 1 else np.zeros_like(j)
    return idx, np.abs(stamps_ns[idx] - query_ns)


def relations_error(
    stamps_ns: np.ndarray,
    poses_xyyaw: np.ndarray,
    t1_ns: np.ndarray,
    t2_ns: np.ndarray,
    relations_xyyaw: np.ndarray,
    max_diff_ns: int = 20_000_000,
) -> dict[str, float | int]:
    """Kümmerle 2009 relations metric of planar poses (N, 3) (x [m], y [m], yaw [rad]).

    For each reference relation (pose at t2 in the frame of the pose at t1) the estimate's
    relative pose is formed from its poses nearest in time (within ``max_diff_ns``; relations
    without both poses are skipped and counted), and the error pose ``E = d_est^-1 d_ref`` scores
    ``|t(E)|`` [m] and ``|yaw(E)|`` [deg]. Returns mean and std of these and of their squares."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    poses = np.asarray(poses_xyyaw, dtype=np.float64)
    if len(stamps) == 0:
        raise TrajectoryEvalError("no poses to evaluate relations on")
    i1, d1 = _nearest_index(stamps, np.asarray(t1_ns, dtype=np.int64))
    i2, d2 = _nearest_index(stamps, np.asarray(t2_ns, dtype=np.int64))
    ok = (d1 < max_diff_ns) & (d2 < max_diff_ns)
    if not ok.any():
        raise TrajectoryEvalError("no relation has estimate poses within the window at both ends")
    d_est = ominus(poses[i1[ok]], poses[i2[ok]])
    d_ref = np.asarray(relations_xyyaw, dtype=np.float64)[ok]
    # E = d_est^-1 d_ref: d_ref expressed in the frame of d_est.
    err = ominus(d_est, d_ref)
    trans = np.hypot(err[:, 0], err[:, 1])
    rot = np.degrees(np.abs(err[:, 2]))
    return {
        "count": int(ok.sum()),
        "skipped": int((~ok).sum()),
        "trans_mean_m": float(trans.mean()),
        "trans_std_m": float(trans.std()),
        "trans_sq_mean_m2": float((trans**2).mean()),
        "trans_sq_std_m2": float((trans**2).std()),
        "rot_mean_deg": float(rot.mean()),
        "rot_std_deg": float(rot.std()),
        "rot_sq_mean_deg2": float((rot**2).mean()),
        "rot_sq_std_deg2": float((rot**2).std()),
    }


@dataclass(frozen=True, eq=False)
class Relations:
    """Reference relations as read: the pose at ``t2`` expressed in the frame of the pose at
    ``t1``, planar part only, in file order."""

    path: Path
    t1_ns: np.ndarray  # (M,) int64 [ns]
    t2_ns: np.ndarray  # (M,) int64 [ns]
    xyyaw: np.ndarray  # (M, 3) x [m], y [m], yaw [rad]
    lines: np.ndarray  # (M,) int64, 1-based line number of each relation


def read_relations(path: str | os.PathLike[str]) -> Relations:
    """Read a Kümmerle 2009 relations file: lines ``t1 t2 x y z roll pitch yaw``.

    Stamps become exact integer nanoseconds; blank lines and ``#`` lines are skipped. Any order
    of lines and of ``t1``, ``t2`` is accepted (``t2 < t1`` and ``t2 == t1`` are well-defined
    relations; the published files happen to have ``t1 < t2``), and repeated relations are kept,
    since the metric averages over relations. ``z``, ``roll`` and ``pitch`` must be numbers but
    are ignored: the metric is planar. A missing file, a wrong field count, a bad stamp or a
    non-finite value raises :class:`~sensors.types.SensorError` naming file and line; a file
    without relations is an error too."""
    table = read_stamped_text(path, RELATION_COLUMNS, check_order=False)
    if not len(table.stamps_ns):
        raise SensorError(
            f"{table.path}: no relations (expected lines '{' '.join(RELATION_COLUMNS)}')"
        )
    t2_ns = np.empty(len(table.values), dtype=np.int64)
    for k, (row, line) in enumerate(zip(table.values, table.lines, strict=True)):
        try:
            t2_ns[k] = parse_stamp(row[0])
        except ValueError as err:
            raise SensorError(f"{table.path}:{line}: bad timestamp t2: {err}") from err
    after_t2 = StampedText(table.path, table.stamps_ns, [r[1:] for r in table.values], table.lines)
    numbers = after_t2.numeric(np.float64, "relation (x y z roll pitch yaw)")
    return Relations(table.path, table.stamps_ns, t2_ns, numbers[:, [0, 1, 5]], table.lines)
