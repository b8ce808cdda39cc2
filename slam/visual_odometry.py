"""RGB-D visual odometry: frame-to-frame (or frame-to-keyframe) camera motion with a success flag.

Default pipeline (``method="orb_pnp"``), one step per line as in :func:`estimate_motion`:

1. ORB features on a grid (best responses per cell) so matches spread over the image;
2. previous keypoints back-projected with their depth (3D, previous optical frame);
3. Hamming matching, Lowe ratio test (``cor_nndr``) and a mutual (cross) check;
4. ``cv2.solvePnPRansac`` (USAC MAGSAC) on 3D(prev) -> 2D(curr) for a robust initial motion;
5. refinement by Gauss-Newton on a joint reprojection + depth error ("RGB-D stereo" residuals,
   as ORB-SLAM2 does for RGB-D): for every inlier with depth in the current frame, besides
   ``(u, v)`` we predict a virtual right-image column ``u_r = u - bf / z`` with ``bf = fx *
   KINECT_BASELINE``; a Kinect's depth noise is constant in disparity, so the three residuals
   share one pixel noise model; Huber weights, inliers re-selected by a chi-square gate;
6. acceptance tests (inliers, inlier ratio, motion magnitude) -> ``success=False`` + reason
   otherwise, never a silent garbage pose.

Covariance: the Gauss-Newton normal matrix ``H = J^T W J`` of step 5 at the solution, scaled by
the a-posteriori variance of unit weight ``s^2 = sum(w r^2) / (m - 6)``: ``cov = s^2 H^-1``,
over the left perturbation ``T_true = exp(d) T`` of ``T_curr_prev``, re-expressed for the camera
motion ``T_prev_curr`` and ordered ``(x, y, z, roll, pitch, yaw)`` (ROS pose covariance order).
It is a lower bound (it ignores correlated errors such as depth calibration) and is floored by
``VoTuning.min_sigma_*``.

Planar mode (``force_3dof``, RTAB-Map Reg/Force3DoF): the camera motion is moved to base_link
through the camera extrinsics, ``T_base = A T_opt A^-1`` with ``A = T_base_optical``, and
projected to ``(dx, dy, dyaw)``; the 6x6 covariance is propagated through the adjoint of ``A``
and the same projection (3x3 over x, y, yaw).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np

from sensors.config import RobotConfig
from sensors.extrinsics import optical_in_base_4x4
from sensors.types import CameraIntrinsics, ConfigError, Pose2, RgbdFrame
from slam.config import VoConfig

log = logging.getLogger(__name__)

KINECT_BASELINE = 0.075  # [m] IR projector - IR camera baseline, sets the disparity scale
CHI2_3DOF_95 = 7.815  # chi-square 95 % gate for 3 residuals (u, v, u_r)
CHI2_2DOF_95 = 5.991  # chi-square 95 % gate for 2 residuals (u, v)
CHI2_GATE_SCALE = 2.0  # the gates are widened: keypoint errors have heavier tails than Gaussian
HAMMING_BLOCK_ROWS = 128  # descriptor rows per block of the Hamming table (~1 MB for M = 1000)

Reason = Literal[
    "ok",
    "too_few_features",
    "too_few_matches",
    "pnp_failed",
    "too_few_inliers",
    "implausible_motion",
    "no_previous_frame",
]


@dataclass(frozen=True)
class VoTuning:
    """Constants of the ORB + PnP pipeline that are not (yet) in :class:`VoConfig`."""

    grid_rows: int = 6  # feature bucketing grid (cells)
    grid_cols: int = 8
    detect_factor: float = 1.5  # detect this many times max_features, then bucket
    clahe_clip: float = 0.0  # CLAHE contrast limit before detection (0 = off; it hurt on TUM)
    clahe_tiles: int = 8  # CLAHE tiles per image side
    depth_as_mask: bool = True  # detect only where depth is in range (RTAB-Map Vis/DepthAsMask)
    fast_threshold: int = 5  # [8-bit levels] ORB's FAST threshold (OpenCV default 20)
    orb_levels: int = 8  # ORB-SLAM / OpenCV default; 6 measured worse on TUM, equal in sim
    orb_scale: float = 1.2
    cross_check: bool = False  # keep mutual best matches only (cost a 2nd matching, hurt here)
    knn: int = 3  # candidates kept per feature for the guided (projection) search
    guided_radius_px: float = 20.0  # [px] guided search window around the PnP projection
    guided_max_hamming: int = 64  # [bits] descriptor distance accepted in the guided search
    min_pnp_inliers: int = 8  # RANSAC seed size accepted before the guided search
    pnp_method: Literal["magsac", "ransac", "ap3p", "prosac"] = "ap3p"  # MAGSAC: 3-8x slower here
    ransac_confidence: float = 0.999
    refine: Literal["none", "lm", "rgbd"] = "rgbd"
    refine_iterations: int = 6  # Gauss-Newton steps (converges in 3-4 from the PnP seed)
    pixel_sigma: float = 1.0  # [px] keypoint localisation noise at pyramid level 0
    disparity_sigma: float = 0.5  # [px] virtual right-column noise (depth incl. registration)
    huber_px: float = 2.0  # [sigma] Huber threshold of the refinement
    min_inlier_ratio: float = 0.1  # inliers / matches below this -> too_few_inliers
    min_sigma_m: float = 0.002  # [m] covariance floor per translation axis
    min_sigma_rad: float = 0.002  # [rad] covariance floor per rotation axis


@dataclass(frozen=True, eq=False)
class VoResult:
    """Outcome of one motion estimate. ``T_prev_curr`` is identity whenever ``success`` is False."""

    success: bool
    reason: str  # one of :data:`Reason`
    T_prev_curr: np.ndarray  # 4x4 float64: current camera pose in the previous optical frame
    inliers: int
    covariance: np.ndarray  # 6x6 (x y z roll pitch yaw) or 3x3 (x y yaw, planar mode)
    ms: float  # [ms] wall time of the estimate
    matches: int = 0
    delta_base: Pose2 | None = None  # planar mode: base_link motion (dx, dy, dyaw)

    @property
    def inlier_ratio(self) -> float:
        return self.inliers / self.matches if self.matches else 0.0


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints of one frame with their descriptors and back-projected 3D points."""

    uv: np.ndarray  # (N, 2) float64 [px]
    octave: np.ndarray  # (N,) int pyramid level
    desc: np.ndarray  # (N, 32) uint8 ORB descriptors
    xyz: np.ndarray  # (N, 3) float64 [m] optical frame; NaN where depth is invalid

    def __len__(self) -> int:
        return len(self.uv)


# --------------------------------------------------------------------------------------------
# Small SE(3) kernels
# --------------------------------------------------------------------------------------------


def camera_matrix(intr: CameraIntrinsics) -> np.ndarray:
    return np.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]])


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def se3_exp(d: np.ndarray) -> np.ndarray:
    """(w, v) 6-vector -> 4x4 (rotation by Rodrigues, translation by the left Jacobian)."""
    w, v = d[:3], d[3:]
    theta = float(np.linalg.norm(w))
    wx = _hat(w)
    if theta < 1e-9:
        r, jl = np.eye(3) + wx, np.eye(3) + 0.5 * wx
    else:
        a, b = math.sin(theta) / theta, (1 - math.cos(theta)) / theta**2
        c = (1 - a) / theta**2
        r = np.eye(3) + a * wx + b * wx @ wx
        jl = np.eye(3) + b * wx + c * wx @ wx
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = r, jl @ v
    return t


def inverse(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def adjoint(t: np.ndarray) -> np.ndarray:
    """Adjoint of T for (w, v) ordered twists: exp(Ad d) = T exp(d) T^-1."""
    r, p = t[:3, :3], t[:3, 3]
    ad = np.zeros((6, 6))
    ad[:3, :3] = r
    ad[3:, 3:] = r
    ad[3:, :3] = _hat(p) @ r
    return ad


def rotation_angle(t: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(t[:3, :3])) - 1.0) / 2.0)))


def base_from_optical(robot: RobotConfig) -> np.ndarray:
    """4x4 pose of the optical frame in base_link from the robot's camera extrinsics."""
    return optical_in_base_4x4(robot)


# --------------------------------------------------------------------------------------------
# 1-2. Features
# --------------------------------------------------------------------------------------------


def _bucket(
    uv: np.ndarray, response: np.ndarray, shape: tuple[int, int], n: int, tuning: VoTuning
) -> np.ndarray:
    """Indices of the best responses per grid cell so that at most ~n keypoints remain, spread
    out (cell rank 0 of every cell first, then rank 1, ...)."""
    if len(uv) <= n:
        return np.arange(len(uv))
    h, w = shape
    row = np.minimum((uv[:, 1] * tuning.grid_rows / h).astype(int), tuning.grid_rows - 1)
    col = np.minimum((uv[:, 0] * tuning.grid_cols / w).astype(int), tuning.grid_cols - 1)
    cell = row * tuning.grid_cols + col
    order = np.lexsort((-response, cell))  # by cell, best first within a cell
    sorted_cell = cell[order]
    start = np.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = np.arange(len(order)) - start  # rank within the cell
    # Round-robin over the cells: rank 0 of every cell first, then rank 1, ...
    return order[np.lexsort((-response[order], rank))][:n]


def _orb(n: int, tuning: VoTuning) -> cv2.ORB:
    return cv2.ORB_create(  # type: ignore[attr-defined]
        nfeatures=n, scaleFactor=tuning.orb_scale, nlevels=tuning.orb_levels,
        fastThreshold=tuning.fast_threshold,
    )  # fmt: skip


def extract_features(
    rgb: np.ndarray, depth_m: np.ndarray, k: np.ndarray, cfg: VoConfig, tuning: VoTuning
) -> Features:
    """Grid-bucketed ORB keypoints with descriptors and depth back-projection."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    if tuning.clahe_clip > 0:
        clahe = cv2.createCLAHE(tuning.clahe_clip, (tuning.clahe_tiles, tuning.clahe_tiles))
        gray = clahe.apply(gray)
    orb = _orb(int(cfg.max_features * tuning.detect_factor), tuning)
    # NaN depth is outside every range: masked out.
    mask = cv2.inRange(depth_m, cfg.min_depth, cfg.max_depth) if tuning.depth_as_mask else None
    # One call builds the image pyramid once; describing the keypoints the bucketing drops
    # costs less than a second pyramid (detect + compute). The descriptors are identical.
    kps, desc = orb.detectAndCompute(gray, mask)
    if desc is None or len(kps) == 0:
        return Features(np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 32), np.uint8),
                        np.zeros((0, 3)))  # fmt: skip
    uv = np.asarray(cv2.KeyPoint_convert(kps), np.float64)  # type: ignore[attr-defined]
    octave = np.fromiter((kp.octave & 0xFF for kp in kps), int, len(kps))
    if len(kps) > cfg.max_features:
        response = np.fromiter((kp.response for kp in kps), np.float64, len(kps))
        keep = _bucket(uv, response, gray.shape[:2], cfg.max_features, tuning)
    else:
        keep = np.arange(len(kps))
    # Pyramid level order, as ORB's compute() returns given keypoints: the same feature order
    # (hence matching ties and RANSAC samples) as describing only the kept keypoints.
    keep = keep[np.argsort(octave[keep], kind="stable")]
    uv = uv[keep]
    return Features(uv, octave[keep], desc[keep], backproject(uv, depth_m, k, cfg))


def backproject(uv: np.ndarray, depth_m: np.ndarray, k: np.ndarray, cfg: VoConfig) -> np.ndarray:
    """(N, 2) pixels -> (N, 3) optical points; NaN rows where depth is invalid/out of range."""
    h, w = depth_m.shape
    col = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    z = depth_m[row, col].astype(np.float64)
    ok = np.isfinite(z) & (z >= max(cfg.min_depth, 1e-6)) & (z <= cfg.max_depth)
    z = np.where(ok, z, np.nan)
    x = (uv[:, 0] - k[0, 2]) / k[0, 0] * z
    y = (uv[:, 1] - k[1, 2]) / k[1, 1] * z
    return np.column_stack([x, y, z])


# --------------------------------------------------------------------------------------------
# 3. Matching
# --------------------------------------------------------------------------------------------


def hamming_knn(a: np.ndarray, b: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest rows of ``b`` for every row of ``a`` by Hamming distance.

    ``a`` (N, B) and ``b`` (M, B) uint8 binary descriptors with B a multiple of 8, ``k <= M``.
    Returns (N, k) distances [bits] and (N, k) indices into ``b``, nearest first, ties to the
    lower index: the same as ``cv2.batchDistance(..., NORM_HAMMING, K=k)`` (which BFMatcher runs),
    in about 0.7 of its single-thread time here (64-bit XOR + popcount in NumPy; the pip OpenCV
    build's baseline is SSE3).
    """
    n, m = len(a), len(b)
    wa = np.ascontiguousarray(a).view(np.uint64)  # (N, B/8)
    wb = np.ascontiguousarray(np.ascontiguousarray(b).view(np.uint64).T)  # (B/8, M)
    dist = np.empty((n, k), np.int64)
    idx = np.empty((n, k), np.int64)
    # Blocks of query rows keep the (rows, M) tables in cache; buffers are reused.
    x = np.empty((HAMMING_BLOCK_ROWS, m), np.uint64)
    bits = np.empty((HAMMING_BLOCK_ROWS, m), np.uint8)
    d = np.empty((HAMMING_BLOCK_ROWS, m), np.uint16)
    taken = np.iinfo(np.uint16).max  # above any distance (at most 8 B bits)
    for s in range(0, n, HAMMING_BLOCK_ROWS):
        e = min(s + HAMMING_BLOCK_ROWS, n)
        xb, bb, db = x[: e - s], bits[: e - s], d[: e - s]
        for w in range(wa.shape[1]):
            np.bitwise_xor(wa[s:e, w, None], wb[w], out=xb)
            np.bitwise_count(xb, out=bb)
            if w == 0:
                db[...] = bb
            else:
                db += bb
        rows = np.arange(e - s)
        for j in range(k):  # k passes of argmin: cheaper than a partial sort for k = 2-3
            i = np.argmin(db, axis=1)  # first minimum: ties to the lower index
            idx[s:e, j] = i
            dist[s:e, j] = db[rows, i]
            db[rows, i] = taken
    return dist, idx


def knn_candidates(prev: Features, curr: Features, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, k) indices into curr and (N, k) Hamming distances, best first; -1 / inf padding."""
    idx = np.full((len(prev), k), -1)
    dist = np.full((len(prev), k), np.inf)
    if len(prev) == 0 or len(curr) == 0:
        return idx, dist
    kk = min(k, len(curr))
    dist[:, :kk], idx[:, :kk] = hamming_knn(prev.desc, curr.desc, kk)
    return idx, dist


def match(prev: Features, curr: Features, nndr: float, cross_check: bool,
          cand: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:  # fmt: skip
    """(M, 2) index pairs (prev, curr): ratio test, optionally mutual best matches only."""
    if len(prev) < 2 or len(curr) < 2:
        return np.zeros((0, 2), int)
    idx, dist = cand if cand is not None else knn_candidates(prev, curr, 2)
    good = (idx[:, 1] >= 0) & (dist[:, 0] < nndr * dist[:, 1])
    pairs = np.column_stack([np.flatnonzero(good), idx[good, 0]])
    if cross_check and len(pairs):
        back = cv2.BFMatcher(cv2.NORM_HAMMING).match(curr.desc, prev.desc)
        best_prev = np.full(len(curr), -1)
        best_prev[[m.queryIdx for m in back]] = [m.trainIdx for m in back]
        pairs = pairs[best_prev[pairs[:, 1]] == pairs[:, 0]]
    return pairs


def guided_matches(t_cp: np.ndarray, prev_xyz: np.ndarray, curr_uv: np.ndarray, idx: np.ndarray,
                   dist: np.ndarray, k: np.ndarray, tuning: VoTuning) -> np.ndarray:  # fmt: skip
    """Re-match with the PnP motion: per previous point, the best of its k descriptor candidates
    that lands within ``guided_radius_px`` of its projection; one previous point per current
    keypoint (the closest descriptor wins). Returns (M, 2) (prev, curr) index pairs."""
    q = prev_xyz @ t_cp[:3, :3].T + t_cp[:3, 3]
    front = q[:, 2] > 1e-3
    zs = np.where(front, q[:, 2], 1.0)[:, None]
    proj = q[:, :2] / zs * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]
    valid = idx >= 0
    cuv = curr_uv[np.where(valid, idx, 0)]  # (N, k, 2)
    near = np.linalg.norm(cuv - proj[:, None, :], axis=2) < tuning.guided_radius_px
    ok = valid & near & (dist <= tuning.guided_max_hamming) & front[:, None]
    first = np.argmax(ok, axis=1)  # candidates are sorted by distance: first hit is the best
    has = ok[np.arange(len(ok)), first]
    ip = np.flatnonzero(has)
    ic = idx[ip, first[has]]
    d = dist[ip, first[has]]
    order = np.lexsort((d, ic))  # unique current keypoints, lowest distance kept
    keep = order[np.r_[True, ic[order][1:] != ic[order][:-1]]] if len(order) else order
    return np.column_stack([ip[keep], ic[keep]])


# --------------------------------------------------------------------------------------------
# 5. Refinement: joint reprojection + disparity Gauss-Newton
# --------------------------------------------------------------------------------------------


def _residuals(
    t_cp: np.ndarray, p_prev: np.ndarray, obs: np.ndarray, has_z: np.ndarray, k: np.ndarray,
    bf: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Unweighted residuals (N, 3) [px] and Jacobians (N, 3, 6) w.r.t. a left perturbation.

    ``obs`` holds (u, v, u_r) of the current frame; the u_r residual is zeroed where the current
    depth is missing. With q = R p + t: du/dq = [fx/z, 0, -fx x/z^2], dv/dq = [0, fy/z, -fy y/z^2],
    d(u_r)/dq = du/dq + [0, 0, bf/z^2]; dq/dd = [-[q]x, I].
    """
    q = p_prev @ t_cp[:3, :3].T + t_cp[:3, 3]
    x, y, z = q[:, 0], q[:, 1], np.maximum(q[:, 2], 1e-6)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    u = fx * x / z + cx
    v = fy * y / z + cy
    ur = u - bf / z
    r = np.column_stack([u - obs[:, 0], v - obs[:, 1], np.where(has_z, ur - obs[:, 2], 0.0)])
    # Row a of d(proj)/dq times [-[q]x, I] is [q x a, a]: written out per component instead of
    # N small matrix products (the same numbers, a fraction of the time).
    dproj = np.zeros((len(q), 3, 3))
    dproj[:, 0, 0] = fx / z
    dproj[:, 0, 2] = -fx * x / z**2
    dproj[:, 1, 1] = fy / z
    dproj[:, 1, 2] = -fy * y / z**2
    dproj[:, 2] = dproj[:, 0]
    dproj[:, 2, 2] += bf / z**2
    dproj[~has_z, 2] = 0.0
    qx, qy, qz = q[:, 0, None], q[:, 1, None], q[:, 2, None]
    ax, ay, az = dproj[:, :, 0], dproj[:, :, 1], dproj[:, :, 2]
    j = np.empty((len(q), 3, 6))
    j[:, :, 0] = qy * az - qz * ay
    j[:, :, 1] = qz * ax - qx * az
    j[:, :, 2] = qx * ay - qy * ax
    j[:, :, 3:] = dproj
    return r, j


def refine_rgbd(
    t_cp: np.ndarray, p_prev: np.ndarray, uv_curr: np.ndarray, z_curr: np.ndarray,
    octave: np.ndarray, k: np.ndarray, tuning: VoTuning,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Gauss-Newton with Huber weights on (u, v, u_r) residuals.

    Returns (T_curr_prev, inlier mask, 6x6 covariance over the left perturbation (w, v)).
    """
    bf = k[0, 0] * KINECT_BASELINE
    has_z = np.isfinite(z_curr)
    obs = np.column_stack([uv_curr, uv_curr[:, 0] - bf / np.where(has_z, z_curr, 1.0)])
    scale = tuning.orb_scale ** octave.astype(float)  # coarser levels localise worse
    px = tuning.pixel_sigma * scale
    sig = np.column_stack([px, px, np.hypot(px, tuning.disparity_sigma)])
    gate = np.where(has_z, CHI2_3DOF_95, CHI2_2DOF_95) * CHI2_GATE_SCALE
    inl = np.ones(len(p_prev), bool)
    t = t_cp.copy()
    for it in range(tuning.refine_iterations):
        r, j = _residuals(t, p_prev, obs, has_z, k, bf)
        rw = r / sig
        jw = j / sig[:, :, None]
        chi2 = np.einsum("ij,ij->i", rw, rw)
        if it >= 2:  # re-select inliers once the estimate has settled
            inl = chi2 < gate
        e = np.sqrt(chi2)
        w = np.where(e <= tuning.huber_px, 1.0, tuning.huber_px / np.maximum(e, 1e-12)) * inl
        jf = jw.reshape(-1, 6)
        jtw = (jf * np.repeat(w, 3)[:, None]).T  # J^T W
        h = jtw @ jf
        g = jtw @ rw.ravel()
        try:
            d = -np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            break
        t = se3_exp(d) @ t
        if np.linalg.norm(d) < 1e-6 and it >= 2:
            break
    r, j = _residuals(t, p_prev, obs, has_z, k, bf)
    rw, jw = r / sig, j / sig[:, :, None]
    dof = int(inl.sum() * 2 + (inl & has_z).sum()) - 6
    s2 = float(np.einsum("ij,ij->", rw[inl], rw[inl])) / max(dof, 1)
    jf = jw[inl].reshape(-1, 6)
    h = jf.T @ jf
    cov = np.linalg.pinv(h) * max(s2, 1e-12)
    return t, inl, cov


def _cov_prev_curr(cov_cp: np.ndarray, t_cp: np.ndarray) -> np.ndarray:
    """Left-perturbation covariance of T_curr_prev -> (x y z roll pitch yaw) of T_prev_curr.

    exp(d) T  ->  (exp(d) T)^-1 = T^-1 exp(-d) = exp(-Ad(T^-1) d) T^-1: a left perturbation
    ``-Ad(T^-1) d`` of T_prev_curr, reordered from (w, v) to (v, w).
    """
    a = -adjoint(inverse(t_cp))
    c = a @ cov_cp @ a.T
    perm = [3, 4, 5, 0, 1, 2]
    return c[np.ix_(perm, perm)]


def _floor_cov(cov: np.ndarray, tuning: VoTuning) -> np.ndarray:
    floor = np.array([tuning.min_sigma_m] * 3 + [tuning.min_sigma_rad] * 3) ** 2
    return cov + np.diag(floor)


# --------------------------------------------------------------------------------------------
# Planar projection
# --------------------------------------------------------------------------------------------


def to_planar(
    t_prev_curr: np.ndarray, cov6: np.ndarray, t_base_opt: np.ndarray
) -> tuple[Pose2, np.ndarray, np.ndarray]:
    """Optical-frame motion -> (base_link (dx, dy, dyaw), 3x3 covariance, planar optical 4x4).

    ``T_base = A T A^-1``; a left perturbation d of T maps to ``Ad(A) d`` on T_base. Projection
    to (x, y, yaw) linearised at T_base: d(x, y) = v_xy + (w x t)_xy, d yaw = w_z.
    """
    a = t_base_opt
    tb = a @ t_prev_curr @ inverse(a)
    dx, dy = float(tb[0, 3]), float(tb[1, 3])
    dyaw = math.atan2(tb[1, 0], tb[0, 0])
    perm = [3, 4, 5, 0, 1, 2]  # (x y z r p y) -> (w, v)
    c_wv = np.empty((6, 6))
    c_wv[np.ix_(perm, perm)] = cov6
    ad = adjoint(a)
    c_base = ad @ c_wv @ ad.T
    jp = np.zeros((3, 6))
    jp[:2, :3] = -_hat(tb[:3, 3])[:2]
    jp[:2, 3:5] = np.eye(2)
    jp[2, 2] = 1.0
    cov3 = jp @ c_base @ jp.T
    planar = np.eye(4)
    c, s = math.cos(dyaw), math.sin(dyaw)
    planar[:2, :2] = [[c, -s], [s, c]]
    planar[:2, 3] = [dx, dy]
    return Pose2(dx, dy, dyaw), cov3, inverse(a) @ planar @ a


# --------------------------------------------------------------------------------------------
# 4 + 6. Motion from two feature sets
# --------------------------------------------------------------------------------------------


def _fail(reason: str, t0: float, n_match: int = 0, inliers: int = 0, planar: bool = False
          ) -> VoResult:  # fmt: skip
    n = 3 if planar else 6
    return VoResult(False, reason, np.eye(4), inliers, np.full((n, n), np.inf),
                    (time.perf_counter() - t0) * 1e3, n_match)  # fmt: skip


_PNP_FLAGS = {
    "magsac": cv2.USAC_MAGSAC,
    "ransac": cv2.SOLVEPNP_EPNP,
    "ap3p": cv2.SOLVEPNP_AP3P,
    "prosac": cv2.USAC_PROSAC,
}


def motion_from_features(
    prev: Features, curr: Features, k: np.ndarray, cfg: VoConfig, tuning: VoTuning,
    t_base_opt: np.ndarray | None = None, t0: float | None = None,
) -> VoResult:  # fmt: skip
    """Steps 3-6 of the pipeline on already extracted features."""
    t0 = time.perf_counter() if t0 is None else t0
    planar = cfg.force_3dof and t_base_opt is not None
    if min(len(prev), len(curr)) < cfg.min_inliers:
        return _fail("too_few_features", t0, planar=planar)
    # 3. Match the previous keypoints that have depth.
    with_depth = np.flatnonzero(np.isfinite(prev.xyz[:, 2]))
    sub = Features(prev.uv[with_depth], prev.octave[with_depth], prev.desc[with_depth],
                   prev.xyz[with_depth])  # fmt: skip
    cand = knn_candidates(sub, curr, max(2, tuning.knn))
    pairs = match(sub, curr, cfg.cor_nndr, tuning.cross_check, cand)
    n_match = len(pairs)
    if n_match < cfg.min_inliers:
        return _fail("too_few_matches", t0, n_match, planar=planar)
    ip, ic = pairs[:, 0], pairs[:, 1]
    obj = sub.xyz[ip]
    img = curr.uv[ic]
    # 4. Robust PnP: 3D points of the previous frame seen in the current image.
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, k, None, iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.pnp_reproj_error, confidence=tuning.ransac_confidence,
            flags=_PNP_FLAGS[tuning.pnp_method],
        )  # fmt: skip
    except cv2.error as err:
        log.debug("solvePnPRansac failed: %s", err)
        ok = False
    if not ok or inl is None:
        return _fail("pnp_failed", t0, n_match, planar=planar)
    inl = inl.ravel()
    # The guided search + refinement must still reach min_inliers; the seed may be smaller.
    need = (
        min(cfg.min_inliers, tuning.min_pnp_inliers) if tuning.refine == "rgbd" else cfg.min_inliers
    )
    if len(inl) < need:
        return _fail("too_few_inliers", t0, n_match, len(inl), planar=planar)
    t_cp = np.eye(4)
    t_cp[:3, :3] = cv2.Rodrigues(rvec)[0]
    t_cp[:3, 3] = tvec.ravel()
    # 5. Refinement.
    cov_cp = None
    n_inl = len(inl)
    if tuning.refine == "lm":
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], k, None, rvec, tvec)
        t_cp[:3, :3] = cv2.Rodrigues(rvec)[0]
        t_cp[:3, 3] = tvec.ravel()
    if tuning.refine in ("rgbd", "lm"):
        # The RANSAC inliers under a looser gate seed the refinement; it re-selects its own.
        if tuning.refine == "rgbd" and tuning.guided_radius_px > 0:
            # 5a. Guided search: many more correspondences than the ratio test lets through.
            gp = guided_matches(t_cp, sub.xyz, curr.uv, *cand, k, tuning)
            gi, gc = gp[:, 0], gp[:, 1]
            n_match = max(n_match, len(gp))
        else:
            q = obj @ t_cp[:3, :3].T + t_cp[:3, 3]
            proj = q[:, :2] / np.maximum(q[:, 2:], 1e-6) * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]
            sel = np.flatnonzero(np.linalg.norm(proj - img, axis=1) < 3 * cfg.pnp_reproj_error)
            gi, gc = ip[sel], ic[sel]
        z_curr = curr.xyz[gc, 2]
        if tuning.refine == "lm":
            z_curr = np.full(len(gc), np.nan)  # covariance from reprojection only
            tun = replace(tuning, refine_iterations=1)
        else:
            tun = tuning
        t_cp, mask, cov_cp = refine_rgbd(t_cp, sub.xyz[gi], curr.uv[gc], z_curr,
                                         curr.octave[gc], k, tun)  # fmt: skip
        n_inl = int(mask.sum())
    if n_inl < cfg.min_inliers or n_inl < tuning.min_inlier_ratio * n_match:
        return _fail("too_few_inliers", t0, n_match, n_inl, planar=planar)
    # 6. Motion sanity.
    t_pc = inverse(t_cp)
    if (np.linalg.norm(t_pc[:3, 3]) > cfg.max_translation
            or rotation_angle(t_pc) > cfg.max_rotation):  # fmt: skip
        return _fail("implausible_motion", t0, n_match, n_inl, planar=planar)
    if cov_cp is None:
        cov6 = np.diag([1e-4] * 3 + [1e-4] * 3)  # no refinement: a conservative 1 cm / 0.6 deg
    else:
        cov6 = _cov_prev_curr(cov_cp, t_cp)
    cov6 = _floor_cov(cov6, tuning)
    delta = None
    if planar:
        assert t_base_opt is not None
        delta, cov, t_pc = to_planar(t_pc, cov6, t_base_opt)
    else:
        cov = cov6
    ms = (time.perf_counter() - t0) * 1e3
    return VoResult(True, "ok", t_pc, n_inl, cov, ms, n_match, delta)


def estimate_motion(
    prev_rgb: np.ndarray,
    prev_depth: np.ndarray,
    curr_rgb: np.ndarray,
    curr_depth: np.ndarray,
    K: np.ndarray,
    params: VoConfig | None = None,
    tuning: VoTuning | None = None,  # noqa: N803
    t_base_opt: np.ndarray | None = None,
) -> VoResult:
    """Camera motion between two RGB-D frames (pure; see the module docstring for the steps).

    ``params.force_3dof`` applies only when ``t_base_opt`` (pose of the optical frame in
    base_link, :func:`base_from_optical`) is given.
    """
    cfg = params or VoConfig(force_3dof=False)
    tun = tuning or VoTuning()
    t0 = time.perf_counter()
    if cfg.method != "orb_pnp":
        # Open3D RGB-D odometry measured 39 % / 8.7 cm on TUM cabinet (16 wrong poses accepted)
        # and 18 cm on a textureless simulated pair: it wins nowhere, so it is bench-only.
        raise ConfigError(f"vo.method: {cfg.method!r} is not implemented (use 'orb_pnp')")
    prev = extract_features(prev_rgb, prev_depth, K, cfg, tun)
    curr = extract_features(curr_rgb, curr_depth, K, cfg, tun)
    return motion_from_features(prev, curr, K, cfg, tun, t_base_opt, t0)


# --------------------------------------------------------------------------------------------
# Stateful shell
# --------------------------------------------------------------------------------------------


@dataclass
class _Keyframe:
    features: Features
    T_kf_last: np.ndarray = field(default_factory=lambda: np.eye(4))  # last frame in kf frame


class VisualOdometry:
    """Frame-to-keyframe RGB-D odometry holding the keyframe's features and the chained pose.

    Every frame is matched against the current keyframe (features are extracted once per
    frame); a new keyframe is taken when the inlier ratio drops below ``keyframe_thr``, the
    motion since the keyframe exceeds ``keyframe_translation``/``keyframe_rotation``, or
    tracking fails (the failed frame becomes the keyframe so the next one can recover; the
    chained pose then misses that motion, and the result says so). ``keyframes=False`` gives
    plain frame-to-frame odometry.
    """

    def __init__(self, intrinsics: CameraIntrinsics, cfg: VoConfig | None = None,
                 robot: RobotConfig | None = None, tuning: VoTuning | None = None,
                 keyframes: bool = True) -> None:  # fmt: skip
        self.cfg = cfg or VoConfig()
        if self.cfg.method != "orb_pnp":
            raise ConfigError(f"vo.method: {self.cfg.method!r} is not implemented (use 'orb_pnp')")
        self.tuning = tuning or VoTuning()
        self.k = camera_matrix(intrinsics)
        self.keyframes = keyframes
        self.t_base_opt = base_from_optical(robot or RobotConfig()) if self.cfg.force_3dof else None
        self._kf: _Keyframe | None = None
        self.T_odom_cam = np.eye(4)  # chained optical-frame pose of the latest frame

    def reset(self) -> None:
        self._kf = None
        self.T_odom_cam = np.eye(4)

    def process(self, frame: RgbdFrame) -> VoResult:
        t0 = time.perf_counter()
        feats = extract_features(frame.rgb, frame.depth_m, self.k, self.cfg, self.tuning)
        if self._kf is None:
            self._kf = _Keyframe(feats)
            n = 3 if self.t_base_opt is not None else 6
            return VoResult(False, "no_previous_frame", np.eye(4), 0, np.full((n, n), np.inf),
                            (time.perf_counter() - t0) * 1e3)  # fmt: skip
        # The keyframe may be up to a keyframe span behind: widen the sanity limits for the
        # keyframe-relative estimate and apply the configured ones to the frame-to-frame motion.
        cfg6 = replace(self.cfg, force_3dof=False,
                       max_translation=self.cfg.max_translation + self.cfg.keyframe_translation,
                       max_rotation=self.cfg.max_rotation + self.cfg.keyframe_rotation)  # fmt: skip
        res = motion_from_features(self._kf.features, feats, self.k, cfg6, self.tuning, None, t0)
        if res.success:
            t_kf_curr = res.T_prev_curr
            t_last_curr = inverse(self._kf.T_kf_last) @ t_kf_curr
            if (np.linalg.norm(t_last_curr[:3, 3]) > self.cfg.max_translation
                    or rotation_angle(t_last_curr) > self.cfg.max_rotation):  # fmt: skip
                res = replace(res, success=False, reason="implausible_motion",
                              T_prev_curr=np.eye(4))  # fmt: skip
        if not res.success:
            self._kf = _Keyframe(feats)
            return self._finish(res, None, t0)
        new_kf = (not self.keyframes or res.inlier_ratio < self.cfg.keyframe_thr
                  or np.linalg.norm(t_kf_curr[:3, 3]) > self.cfg.keyframe_translation
                  or rotation_angle(t_kf_curr) > self.cfg.keyframe_rotation)  # fmt: skip
        self._kf = _Keyframe(feats) if new_kf else _Keyframe(self._kf.features, t_kf_curr)
        return self._finish(res, t_last_curr, t0)

    def _finish(self, res: VoResult, t_last_curr: np.ndarray | None, t0: float) -> VoResult:
        """Express the keyframe-relative estimate against the previous frame; chain the pose."""
        ms = (time.perf_counter() - t0) * 1e3
        if t_last_curr is None:
            n = 3 if self.t_base_opt is not None else 6
            return replace(res, covariance=np.full((n, n), np.inf), ms=ms)
        cov = res.covariance  # keyframe-relative: an upper bound for the frame-to-frame motion
        delta = None
        if self.t_base_opt is not None:
            delta, cov, t_last_curr = to_planar(t_last_curr, cov, self.t_base_opt)
        self.T_odom_cam = self.T_odom_cam @ t_last_curr
        return replace(res, T_prev_curr=t_last_curr, covariance=cov, ms=ms, delta_base=delta)
