"""RGB-D visual odometry: frame-to-frame (or frame-to-keyframe) camera motion with a success flag.

Default pipeline (``method="orb_pnp"``, :func:`motion_from_features`):

1. ORB features bucketed on a grid, pyramid halves detected in two threads;
2. previous keypoints back-projected with their depth;
3. Hamming k-NN within ``level_window`` pyramid levels and Lowe's ratio test (``cor_nndr``);
4. seeded rigid 3-point RANSAC (:func:`rigid_ransac`, LO-RANSAC refits), keeping a few distinct
   hypotheses, since a repeated structure can outscore the true motion;
5. per hypothesis a guided search and a Gauss-Newton refinement on reprojection + virtual
   stereo (depth as disparity) residuals, as ORB-SLAM2 does for RGB-D; the most inliers wins;
6. acceptance tests -> ``success=False`` with a reason, never a silent garbage pose.

:class:`VisualOdometry` seeds step 5 with the last frame's pose while it predicts well (as
ORB-SLAM's motion model). Optical flow (``cor_type="optical_flow"``) tracks keyframe points by
Lucas-Kanade between ORB keyframes. With ``fallback="depth_icp"`` a frame the features lose gets
KISS-ICP's motion on the depth cloud (:mod:`slam.depth_icp`). The covariance is the refinement's
``s^2 H^-1``, floored by ``vo.advanced.min_sigma_*``; planar mode (``force_3dof``) moves it to
base_link as (x, y, yaw). The inner constants are ``vo.advanced`` (docs/design/vo_tuning.md);
the full derivation: docs/design/visual_odometry.md.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any, Literal

import cv2
import numpy as np
from scipy.spatial import cKDTree

from sensors.config import RobotConfig
from sensors.extrinsics import optical_in_base_4x4
from sensors.types import CameraIntrinsics, ConfigError, Pose2, RgbdFrame
from slam.config import VoConfig, VoTuning

log = logging.getLogger(__name__)

KINECT_BASELINE = 0.075  # [m] IR projector - IR camera baseline, sets the disparity scale
CHI2_3DOF_95 = 7.815  # chi-square 95 % gate for 3 residuals (u, v, u_r)
CHI2_2DOF_95 = 5.991  # chi-square 95 % gate for 2 residuals (u, v)
CHI2_GATE_SCALE = 2.0  # the gates are widened: keypoint errors have heavier tails than Gaussian
RIGID_CHUNK = 256  # rigid RANSAC samples checked at a time, until enough have passed

Reason = Literal[
    "ok",
    "too_few_features",
    "too_few_matches",
    "pnp_failed",
    "too_few_inliers",
    "implausible_motion",
    "no_previous_frame",
    "too_few_points",  # depth_icp: too little in-range depth
    "degenerate",  # depth_icp: the geometry leaves a motion unconstrained (a blank wall)
]


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
    prior: bool = False  # tracked from the last frame's pose: its refinement seeded without
    # RANSAC, the window search around it, or optical flow
    fallback: bool = False  # the features failed on this frame and the motion is depth ICP's
    # (``vo.fallback: depth_icp``; counted in ``VisualOdometry.stats``)

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


_I3 = np.eye(3)
_I3.flags.writeable = False


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def se3_exp(d: np.ndarray) -> np.ndarray:
    """(w, v) 6-vector -> 4x4 (rotation by Rodrigues, translation by the left Jacobian)."""
    w0, w1, w2 = float(d[0]), float(d[1]), float(d[2])
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    wx = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    if theta < 1e-9:
        r = _I3 + wx
        jl = _I3 + 0.5 * wx
    else:
        a, b = math.sin(theta) / theta, (1 - math.cos(theta)) / theta**2
        c = (1 - a) / theta**2
        wx2 = wx @ wx
        r = _I3 + a * wx + b * wx2
        jl = _I3 + b * wx + c * wx2
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = r, jl @ d[3:]
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


def _orb(n: int, tuning: VoTuning, levels: int) -> cv2.ORB:
    return cv2.ORB_create(  # type: ignore[attr-defined]
        nfeatures=n,
        scaleFactor=tuning.orb_scale,
        nlevels=levels,
        fastThreshold=tuning.fast_threshold,
    )


_WORKER: list[ThreadPoolExecutor] = []  # one worker thread, made on first use
_WORKER_LOCK = threading.Lock()  # the front end's stage thread extracts too (prefetch)
if hasattr(os, "register_at_fork"):  # a forked child has no threads: it makes its own worker
    os.register_at_fork(after_in_child=_WORKER.clear)


def _worker() -> ThreadPoolExecutor:
    """The second thread of the pipeline (ORB's upper pyramid levels)."""
    with _WORKER_LOCK:
        if not _WORKER:
            _WORKER.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="vo-worker"))
        return _WORKER[0]


def _keypoints(kps: Sequence[Any], desc: Any, scale: float, level0: int) -> tuple[np.ndarray, ...]:
    """OpenCV keypoints -> (uv (N, 2) [px] times ``scale``, pyramid level (N,) plus ``level0``,
    response (N,), descriptors (N, 32))."""
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2)), np.zeros(0, int), np.zeros(0), np.zeros((0, 32), np.uint8)
    uv = np.asarray(cv2.KeyPoint_convert(kps), np.float64) * scale  # type: ignore[attr-defined]
    attr = np.array([(kp.octave & 0xFF, kp.response) for kp in kps])
    return uv, attr[:, 0].astype(int) + level0, attr[:, 1], desc


def _detect(
    gray: np.ndarray, mask: np.ndarray | None, n: int, tuning: VoTuning
) -> tuple[np.ndarray, ...]:
    """ORB keypoints and descriptors: (uv (N, 2) [px], pyramid level (N,), response (N,),
    descriptors (N, 32)). One call per pyramid part builds its levels once; describing the
    keypoints the bucketing drops costs less than a second pyramid (detect + compute).

    With ``orb_split_level`` s, levels [0, s) and [s, L) are two ORB calls at once (OpenCV
    releases the GIL): the second on the level-s image built as ORB builds it (successive
    linear resizes), with the per-level feature budgets of one L-level ORB (OpenCV gives level
    l the share ``(1 - f) f^l / (1 - f^L)``, f = 1 / scale); its keypoints are scaled back by
    ``scale^s`` and their levels shifted by s.
    """
    levels, s = tuning.orb_levels, tuning.orb_split_level
    f = 1.0 / tuning.orb_scale
    n_low = round(n * (1 - f**s) / (1 - f**levels)) if 0 < s < levels else n
    if n_low >= n or n_low < 1:
        return _keypoints(*_orb(n, tuning, levels).detectAndCompute(gray, mask), 1.0, 0)
    high = _worker().submit(_detect_upper, gray, mask, n - n_low, tuning)
    low = _keypoints(*_orb(n_low, tuning, s).detectAndCompute(gray, mask), 1.0, 0)
    up = _keypoints(*high.result(), tuning.orb_scale**s, s)
    return tuple(np.concatenate([a, b]) for a, b in zip(low, up, strict=True))


def _detect_upper(
    gray: np.ndarray, mask: np.ndarray | None, n: int, tuning: VoTuning
) -> tuple[Any, Any]:
    """ORB levels [s, L) of ``gray`` (s = ``orb_split_level``) with ``n`` features: the level-s
    image and mask built as ORB builds them (successive linear resizes; the mask thresholded to
    full-weight pixels). Runs in the worker thread, resizes included (0.9 ms per frame)."""
    s, f = tuning.orb_split_level, 1.0 / tuning.orb_scale
    img, msk = gray, mask
    h, w = gray.shape[:2]
    for i in range(1, s + 1):
        size = (round(w * f**i), round(h * f**i))
        img = cv2.resize(img, size, interpolation=cv2.INTER_LINEAR_EXACT)
        if msk is not None:
            msk = cv2.resize(msk, size, interpolation=cv2.INTER_LINEAR_EXACT)
            msk = cv2.threshold(msk, 254, 0, cv2.THRESH_TOZERO)[1]
    return _orb(n, tuning, tuning.orb_levels - s).detectAndCompute(img, msk)  # type: ignore[no-any-return]


def _lookup(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Values of ``image`` at the nearest pixels of (N, 2) ``uv`` (clipped to the image)."""
    h, w = image.shape[:2]
    col = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    return image[row, col]


def depth_mask(depth_m: np.ndarray, cfg: VoConfig, tuning: VoTuning) -> np.ndarray:
    """Where to detect (uint8, 255 = yes): in-range depth, grown by ``depth_margin_px`` into holes.

    Holes are pixels without a return (0 or NaN, as at a Kinect's depth edges): keypoints there
    are still matched 2D-only. Measured depth out of range is never grown into: noisy depth
    near ``max_depth`` leaves in-range specks all over a far wall, and growing those handed its
    depthless texture ORB's budget (house route: 69 of 1000 keypoints with depth on some
    frames, VO-only drift 7x HEAD's).
    """
    mask = cv2.inRange(depth_m, cfg.min_depth, cfg.max_depth)  # NaN is out of range
    if tuning.depth_margin_px <= 0:
        return mask
    side = 2 * tuning.depth_margin_px + 1
    grown = cv2.dilate(mask, np.ones((side, side), np.uint8))
    above = cv2.compare(depth_m, 0.0, cv2.CMP_GT)  # type: ignore[call-overload]
    hole = cv2.bitwise_not(above)  # NaN compares False: a hole
    # where(hole, grown, mask) as byte operations (grown covers mask): 0.3 ms instead of 1.2 ms
    return cv2.bitwise_or(mask, cv2.bitwise_and(grown, hole))


def grey(rgb: np.ndarray) -> np.ndarray:
    """The 8-bit grey image ORB detects on and Lucas-Kanade tracks on. (OpenCV 5's Python
    binding takes no prebuilt pyramid, so Lucas-Kanade builds both pyramids on every call.)"""
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb


def extract_features(
    rgb: np.ndarray, depth_m: np.ndarray, k: np.ndarray, cfg: VoConfig, tuning: VoTuning
) -> Features:
    """Grid-bucketed ORB keypoints with descriptors and depth back-projection."""
    gray = grey(rgb)
    if tuning.clahe_clip > 0:
        clahe = cv2.createCLAHE(tuning.clahe_clip, (tuning.clahe_tiles, tuning.clahe_tiles))
        gray = clahe.apply(gray)
    n = int(cfg.max_features * tuning.detect_factor)
    if not tuning.depth_as_mask:
        uv, octave, response, desc = _detect(gray, None, n, tuning)
    else:
        mask = depth_mask(depth_m, cfg, tuning)
        # ORB's mask argument costs 3-10 ms more (OpenCV 4.x), even a mask of all ones. Where
        # the mask covers nearly the image and nearly every keypoint lands on it, dropping the
        # others keeps nearly the set the mask would: that is tried first.
        found = False
        if cv2.countNonZero(mask) >= tuning.unmasked_share * mask.size:
            uv, octave, response, desc = _detect(gray, None, n, tuning)
            on = _lookup(mask, uv) > 0
            found = bool(on.sum() >= tuning.unmasked_share * len(uv))
            uv, octave, response, desc = uv[on], octave[on], response[on], desc[on]
        if not found:  # texture off depth (near floor, far wall) would take ORB's budget
            uv, octave, response, desc = _detect(gray, mask, n, tuning)
    if len(uv) == 0:
        return Features(
            np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 32), np.uint8), np.zeros((0, 3))
        )
    keep = np.arange(len(uv))
    if len(uv) > cfg.max_features:
        keep = _bucket(uv, response, gray.shape[:2], cfg.max_features, tuning)
    # Pyramid level order, as ORB's compute() returns given keypoints: the same feature order
    # (hence matching ties and RANSAC samples) as describing only the kept keypoints.
    keep = keep[np.argsort(octave[keep], kind="stable")]
    uv = uv[keep]
    return Features(uv, octave[keep], desc[keep], backproject(uv, depth_m, k, cfg))


def backproject(uv: np.ndarray, depth_m: np.ndarray, k: np.ndarray, cfg: VoConfig) -> np.ndarray:
    """(N, 2) pixels -> (N, 3) optical points; NaN rows where depth is invalid/out of range."""
    z = _lookup(depth_m, uv).astype(np.float64)
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

    ``a`` (N, B) and ``b`` (M, B) uint8 binary descriptors, ``k <= M``. Returns (N, k) distances
    [bits] and (N, k) indices into ``b``, nearest first, ties to the lower index. OpenCV's
    ``batchDistance`` (what BFMatcher runs): one call that releases the GIL and spreads its rows
    over OpenCV's threads (a NumPy XOR + popcount took 0.7 of its single-thread time, but ran in
    many short GIL-holding calls: in a second Python thread it waited on the first).
    """
    dist, idx = cv2.batchDistance(a, b, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=k)
    return dist.astype(np.int64), idx.astype(np.int64)


def knn_candidates(
    prev: Features, curr: Features, k: int, level_window: int = -1
) -> tuple[np.ndarray, np.ndarray]:
    """(N, k) indices into curr and (N, k) Hamming distances, best first; -1 / inf padding.

    With ``level_window >= 0`` a previous keypoint is compared only with current keypoints at
    most that many pyramid levels away (the scale changes little between nearby frames, as
    ORB-SLAM's search windows assume); both feature sets must be sorted by pyramid level.
    """
    idx = np.full((len(prev), k), -1)
    dist = np.full((len(prev), k), np.inf)
    if len(prev) == 0 or len(curr) == 0:
        return idx, dist
    if level_window < 0:
        blocks = [(0, len(prev), 0, len(curr))]
    else:
        levels = np.unique(prev.octave)
        p_lo = np.searchsorted(prev.octave, levels, "left")
        p_hi = np.searchsorted(prev.octave, levels, "right")
        c_lo = np.searchsorted(curr.octave, levels - level_window, "left")
        c_hi = np.searchsorted(curr.octave, levels + level_window, "right")
        blocks = list(zip(p_lo, p_hi, c_lo, c_hi, strict=True))
    for a, b, c, d in blocks:
        kk = min(k, d - c)
        if kk > 0:
            dist[a:b, :kk], idx[a:b, :kk] = hamming_knn(prev.desc[a:b], curr.desc[c:d], kk)
            idx[a:b, :kk] += c
    return idx, dist


def match(
    prev: Features,
    curr: Features,
    nndr: float,
    cross_check: bool,
    cand: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
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


def guided_matches(
    t_cp: np.ndarray,
    prev_xyz: np.ndarray,
    curr_uv: np.ndarray,
    idx: np.ndarray,
    dist: np.ndarray,
    k: np.ndarray,
    radius_px: float,
    max_hamming: int,
) -> np.ndarray:
    """Re-match with the PnP motion: per previous point, the best of its k descriptor candidates
    that lands within ``radius_px`` of its projection; one previous point per current
    keypoint (the closest descriptor wins). Returns (M, 2) (prev, curr) index pairs."""
    q = prev_xyz @ t_cp[:3, :3].T + t_cp[:3, 3]
    front = q[:, 2] > 1e-3
    zs = np.where(front, q[:, 2], 1.0)[:, None]
    proj = q[:, :2] / zs * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]
    valid = idx >= 0
    cuv = curr_uv[np.where(valid, idx, 0)]  # (N, k, 2)
    near = np.linalg.norm(cuv - proj[:, None, :], axis=2) < radius_px
    ok = valid & near & (dist <= max_hamming) & front[:, None]
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
    t_cp: np.ndarray,
    p_prev: np.ndarray,
    obs: np.ndarray,
    has_z: np.ndarray,
    k: np.ndarray,
    bf: float,
) -> tuple[np.ndarray, np.ndarray]:
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


def _whitened(
    t_cp: np.ndarray, p_prev: np.ndarray, obs: np.ndarray, iw: np.ndarray, k: np.ndarray, bf: float
) -> tuple[np.ndarray, np.ndarray]:
    """Fast :func:`_residuals` (cross-checked in the tests): residuals (3, N) and Jacobians
    (6, 3, N) (parameter-major: every write below is one contiguous row) over (u, v, u_r), rows
    already divided by their sigma (``iw`` (3, N) = 1/sigma, 0 for a missing u_r). ``obs``
    (3, N) holds the observed (u, v, u_r), finite everywhere."""
    q = p_prev @ t_cp[:3, :3].T + t_cp[:3, 3]
    qx, qy, qz = q[:, 0], q[:, 1], q[:, 2]
    iz = 1.0 / np.maximum(qz, 1e-6)
    a, b, bz = k[0, 0] * iz, k[1, 1] * iz, bf * iz
    u = a * qx + k[0, 2]
    r = np.empty((3, len(q)))
    r[0] = u - obs[0]
    r[1] = b * qy + k[1, 2] - obs[1]
    r[2] = u - bz - obs[2]
    r *= iw
    # d(u, v, u_r)/dq rows (a, 0, au), (0, b, av), (a, 0, au + bz/z); J row = [q x row, row].
    au, av = -a * qx * iz, -b * qy * iz
    ar = au + bz * iz
    j = np.zeros((6, 3, len(q)))
    for row, az in ((0, au), (2, ar)):
        j[0, row] = qy * az
        j[1, row] = qz * a - qx * az
        j[2, row] = -qy * a
        j[3, row] = a
        j[5, row] = az
    j[0, 1] = qy * av - qz * b
    j[1, 1] = -qx * av
    j[2, 1] = qx * b
    j[4, 1] = b
    j[5, 1] = av
    j *= iw
    return r, j


def refine_rgbd(
    t_cp: np.ndarray,
    p_prev: np.ndarray,
    uv_curr: np.ndarray,
    z_curr: np.ndarray,
    octave: np.ndarray,
    k: np.ndarray,
    tuning: VoTuning,
    iterations: int | None = None,
    gate_from: int = 2,
    covariance: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Gauss-Newton with Huber weights on (u, v, u_r) residuals; inliers are re-selected by the
    chi-square gate from iteration ``gate_from`` on (once a rough start has settled).

    Returns (T_curr_prev, inlier mask, 6x6 covariance over the left perturbation (w, v), or
    None without ``covariance``: a candidate that is refined again or loses needs none).
    """
    bf = k[0, 0] * KINECT_BASELINE
    has_z = np.isfinite(z_curr)
    obs = np.stack(
        [uv_curr[:, 0], uv_curr[:, 1], uv_curr[:, 0] - bf / np.where(has_z, z_curr, 1.0)]
    )
    px = tuning.pixel_sigma * tuning.orb_scale ** octave.astype(float)  # coarser: worse
    iw = np.stack([1.0 / px, 1.0 / px, has_z / np.hypot(px, tuning.disparity_sigma)])
    gate = np.where(has_z, CHI2_3DOF_95, CHI2_2DOF_95) * CHI2_GATE_SCALE
    inl = np.ones(len(p_prev), bool)
    t = t_cp.copy()
    for it in range(tuning.refine_iterations if iterations is None else iterations):
        r, j = _whitened(t, p_prev, obs, iw, k, bf)
        chi2 = np.einsum("ij,ij->j", r, r)
        if it >= gate_from:
            inl = chi2 < gate
        e = np.sqrt(chi2)
        w = np.where(e <= tuning.huber_px, 1.0, tuning.huber_px / np.maximum(e, 1e-12)) * inl
        jf = j.reshape(6, -1)
        jtw = (j * w).reshape(6, -1)  # J^T W
        try:
            d = -np.linalg.solve(jtw @ jf.T, jtw @ r.ravel())
        except np.linalg.LinAlgError:
            break
        t = se3_exp(d) @ t
        if it >= gate_from and np.linalg.norm(d) < tuning.converged:
            break
    if not covariance:
        return t, inl, None
    r, j = _whitened(t, p_prev, obs, iw, k, bf)
    dof = int(inl.sum() * 2 + (inl & has_z).sum()) - 6
    s2 = float(np.einsum("ij,ij->", r[:, inl], r[:, inl])) / max(dof, 1)
    jf = j[:, :, inl].reshape(6, -1)
    h = jf @ jf.T
    try:  # H is positive definite once six independent residuals are in: inv, not pinv's SVD
        h_inv = np.linalg.inv(h)
    except np.linalg.LinAlgError:
        h_inv = np.linalg.pinv(h)
    return t, inl, h_inv * max(s2, 1e-12)


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


def _fail(
    reason: str, t0: float, n_match: int = 0, inliers: int = 0, planar: bool = False
) -> VoResult:
    n = 3 if planar else 6
    return VoResult(
        False,
        reason,
        np.eye(4),
        inliers,
        np.full((n, n), np.inf),
        (time.perf_counter() - t0) * 1e3,
        n_match,
    )


def kabsch(
    p: np.ndarray, q: np.ndarray, w: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Batched weighted least-squares rigid motion ``q ~ R p + t`` (Kabsch).

    p, q (H, n, 3) or broadcastable; w (H, n) weights or None. Returns R (H, 3, 3), t (H, 3):
    ``R = U diag(1, 1, det(U V^T)) V^T`` from the SVD of ``sum w (q - q_m)(p - p_m)^T``.
    """
    if w is None:
        w = np.ones(np.broadcast_shapes(p.shape, q.shape)[:2])
    w = w / w.sum(1, keepdims=True)
    pm = np.matmul(w[:, None], p)[:, 0]  # weighted means (H, 3)
    qm = np.matmul(w[:, None], q)[:, 0]
    c = np.matmul(((q - qm[:, None]) * w[..., None]).transpose(0, 2, 1), p - pm[:, None])
    u, _, vt = np.linalg.svd(c)
    u[:, :, 2] *= np.sign(np.linalg.det(u @ vt))[:, None]
    r = u @ vt
    return r, qm - np.matmul(r, pm[..., None])[..., 0]


@lru_cache(maxsize=4)
def _uniform_samples(seed: int, count: int) -> np.ndarray:
    """(count, 3) uniform [0, 1) numbers of a seeded generator, made once per seed: scaled by
    the number of matches they pick sample triples (the same draw for the same input)."""
    out = np.random.default_rng(seed).random((count, 3))
    out.flags.writeable = False
    return out


def rigid_ransac(
    p: np.ndarray,
    q: np.ndarray,
    uv: np.ndarray,
    scale: np.ndarray,
    k: np.ndarray,
    thr_px: float,
    tuning: VoTuning,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Motion hypotheses from matched 3D points p (prev) and q (curr) by 3-point rigid samples.

    Samples whose side lengths disagree beyond the depth noise cannot be all inliers and are
    dropped before solving (a rigid motion keeps distances); the rest are solved by Kabsch at
    once and scored by a truncated (MSAC) cost: the reprojection error of p in the current
    image (``uv``; pixel error over the keypoint's pyramid ``scale`` times ``thr_px``). The best
    ``rigid_refits`` are refitted by Kabsch on their inliers (LO-RANSAC) and rescored.
    Returns up to ``verify_hypotheses`` distinct (T_curr_prev, inlier mask), best first.
    """
    n = len(p)
    if n < 3:
        return []
    # 4a. Seeded samples of three distinct matches with a rigid-consistent, well spread triangle.
    s = (_uniform_samples(tuning.ransac_seed, tuning.rigid_samples) * n).astype(np.intp)
    s = s[(s[:, 0] != s[:, 1]) & (s[:, 1] != s[:, 2]) & (s[:, 0] != s[:, 2])]
    # The three sides of each sample only (not all n^2 pairs: most are never drawn), in chunks
    # until rigid_max_hypotheses samples have passed: the same first passing samples as checking
    # them all.
    z2 = p[:, 2] ** 2
    passed, found = [], 0
    for c0 in range(0, len(s), RIGID_CHUNK):
        chunk = s[c0 : c0 + RIGID_CHUNK]
        ok = np.ones(len(chunk), bool)
        for a, b in ((0, 1), (1, 2), (2, 0)):
            i, j = chunk[:, a], chunk[:, b]
            ep, eq = p[i] - p[j], q[i] - q[j]
            dp = np.sqrt(np.einsum("ij,ij->i", ep, ep))
            dq = np.sqrt(np.einsum("ij,ij->i", eq, eq))
            tol = tuning.rigid_tol_m + tuning.rigid_tol_z2 * (z2[i] + z2[j])
            ok &= (np.abs(dp - dq) < tol) & (dp > tuning.rigid_min_span_m)
        passed.append(chunk[ok])
        found += int(ok.sum())
        if found >= tuning.rigid_max_hypotheses:
            break
    s = np.concatenate(passed)[: tuning.rigid_max_hypotheses] if passed else s
    if len(s) == 0:
        return []
    # 4b. Kabsch on every sample at once; MSAC score on all matches.
    r, t = kabsch(p[s], q[s])
    pt = p.T.copy()
    inv_s2 = 1.0 / (scale * thr_px) ** 2
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]

    def score(r: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        qq = np.matmul(r, pt) + t[:, :, None]  # (H, 3, n)
        iz = 1.0 / np.maximum(qq[:, 2], 1e-6)
        e2 = (
            (qq[:, 0] * iz * fx + cx - uv[:, 0]) ** 2 + (qq[:, 1] * iz * fy + cy - uv[:, 1]) ** 2
        ) * inv_s2
        return np.minimum(e2, 1.0).sum(1), e2 < 1.0

    cost, inl = score(r, t)
    # 4c. LO step: the best hypotheses refitted on their inliers, rescored with the rest.
    best = np.argsort(cost)[: tuning.rigid_refits]
    w = inl[best].astype(float)
    fit = w.sum(1) >= 3
    if fit.any():
        rr, tt = kabsch(p[None], q[None], w[fit])
        c2, i2 = score(rr, tt)
        r, t = np.concatenate([r, rr]), np.concatenate([t, tt])
        cost, inl = np.concatenate([cost, c2]), np.concatenate([inl, i2])
    # Distinct hypotheses, best first: a repeated structure can outscore the true motion on
    # the ratio-test matches; the guided search + refinement decides between them.
    out: list[tuple[np.ndarray, np.ndarray]] = []
    left = np.ones(len(cost), bool)
    while left.any() and len(out) < tuning.verify_hypotheses:
        b = int(np.argmin(np.where(left, cost, np.inf)))
        t_cp = np.eye(4)
        t_cp[:3, :3], t_cp[:3, 3] = r[b], t[b]
        out.append((t_cp, inl[b]))
        left &= np.linalg.norm(t - t[b], axis=1) >= tuning.distinct_m
    return out


_PNP_FLAGS = {
    "magsac": cv2.USAC_MAGSAC,
    "ransac": cv2.SOLVEPNP_EPNP,
    "ap3p": cv2.SOLVEPNP_AP3P,
    "prosac": cv2.USAC_PROSAC,
}


def initial_motions(
    obj: np.ndarray,
    img: np.ndarray,
    curr_xyz: np.ndarray,
    curr_octave: np.ndarray,
    k: np.ndarray,
    cfg: VoConfig,
    tuning: VoTuning,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate (T_curr_prev, inlier indices), best first, from matched previous 3D points
    ``obj`` and current pixels ``img`` (with the current 3D points where depth exists)."""
    if tuning.pnp_method == "rigid":
        has = np.flatnonzero(np.isfinite(curr_xyz[:, 2]))
        scale = tuning.orb_scale ** curr_octave[has].astype(float)
        hyps = rigid_ransac(
            obj[has], curr_xyz[has], img[has], scale, k, cfg.pnp_reproj_error, tuning
        )
        return [(t, has[m]) for t, m in hyps]
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            k,
            None,
            iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.pnp_reproj_error,
            confidence=tuning.ransac_confidence,
            flags=_PNP_FLAGS[tuning.pnp_method],
        )
    except cv2.error as err:
        log.debug("solvePnPRansac failed: %s", err)
        return []
    if not ok or inl is None:
        return []
    t_cp = np.eye(4)
    t_cp[:3, :3] = cv2.Rodrigues(rvec)[0]
    t_cp[:3, 3] = tvec.ravel()
    return [(t_cp, inl.ravel())]


def _refine(
    t_cp: np.ndarray,
    inl: np.ndarray,
    sub: Features,
    curr: Features,
    pairs: np.ndarray,
    cand: tuple[np.ndarray, np.ndarray],
    k: np.ndarray,
    cfg: VoConfig,
    tuning: VoTuning,
    radius_px: float,
    max_hamming: int,
    second: bool = False,
    covariance: bool = True,
) -> tuple[np.ndarray, int, np.ndarray | None, int]:
    """Step 5 for one initial motion: (T_curr_prev, inliers, covariance or None, matches)."""
    ip, ic = pairs[:, 0], pairs[:, 1]
    if tuning.refine == "none":
        return t_cp, len(inl), None, len(pairs)
    if tuning.refine == "lm":
        rvec, tvec = cv2.Rodrigues(t_cp[:3, :3])[0], t_cp[:3, 3:].copy()
        rvec, tvec = cv2.solvePnPRefineLM(sub.xyz[ip[inl]], curr.uv[ic[inl]], k, None, rvec, tvec)
        t_cp = np.eye(4)
        t_cp[:3, :3], t_cp[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        # The RANSAC inliers under a looser gate; covariance from reprojection only.
        q = sub.xyz[ip] @ t_cp[:3, :3].T + t_cp[:3, 3]
        proj = q[:, :2] / np.maximum(q[:, 2:], 1e-6) * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]
        err = np.linalg.norm(proj - curr.uv[ic], axis=1)
        sel = np.flatnonzero(err < 3 * cfg.pnp_reproj_error)
        gi, gc = ip[sel], ic[sel]
        t_cp, mask, cov = refine_rgbd(
            t_cp,
            sub.xyz[gi],
            curr.uv[gc],
            np.full(len(gc), np.nan),
            curr.octave[gc],
            k,
            replace(tuning, refine_iterations=1),
        )
        return t_cp, int(mask.sum()), cov, len(pairs)
    # 5a. Guided search: many more correspondences than the ratio test lets through.
    gp = guided_matches(t_cp, sub.xyz, curr.uv, *cand, k, radius_px, max_hamming)
    gi, gc = gp[:, 0], gp[:, 1]
    # 5b. Gauss-Newton on the reprojection + disparity residuals.
    # The second search starts from a refined motion: gate at once, fewer steps.
    t_cp, mask, cov = refine_rgbd(
        t_cp,
        sub.xyz[gi],
        curr.uv[gc],
        curr.xyz[gc, 2],
        curr.octave[gc],
        k,
        tuning,
        tuning.second_iterations if second else None,
        0 if second else 2,
        covariance,
    )
    return t_cp, int(mask.sum()), cov, max(len(pairs), len(gp))


def motion_from_features(
    prev: Features,
    curr: Features,
    k: np.ndarray,
    cfg: VoConfig,
    tuning: VoTuning,
    t_base_opt: np.ndarray | None = None,
    t0: float | None = None,
    t_seed: np.ndarray | None = None,
) -> VoResult:
    """Steps 3-6 of the pipeline on already extracted features. ``t_seed`` (T_curr_prev, e.g.
    the last frame's pose) is refined first, through the same guided search; RANSAC runs only
    if its inliers fall below ``prior_min_inlier_ratio`` of its guided matches."""
    t0 = time.perf_counter() if t0 is None else t0
    planar = cfg.force_3dof and t_base_opt is not None
    if min(len(prev), len(curr)) < cfg.min_inliers:
        return _fail("too_few_features", t0, planar=planar)
    # 3. Match the previous keypoints that have depth.
    with_depth = np.flatnonzero(np.isfinite(prev.xyz[:, 2]))
    sub = Features(
        prev.uv[with_depth], prev.octave[with_depth], prev.desc[with_depth], prev.xyz[with_depth]
    )
    cand = knn_candidates(sub, curr, max(2, tuning.knn), tuning.level_window)
    pairs = match(sub, curr, cfg.cor_nndr, tuning.cross_check, cand)
    n_match = len(pairs)
    if n_match < cfg.min_inliers:
        return _fail("too_few_matches", t0, n_match, planar=planar)
    ip, ic = pairs[:, 0], pairs[:, 1]
    second = tuning.refine == "rgbd" and tuning.second_radius_px > 0  # recomputes covariances
    if t_seed is not None and tuning.refine == "rgbd":
        seeded = _refine(
            t_seed,
            np.zeros(0, int),
            sub,
            curr,
            pairs,
            cand,
            k,
            cfg,
            tuning,
            tuning.guided_radius_px,
            tuning.guided_max_hamming,
            covariance=not second,
        )
        if seeded[1] >= max(cfg.min_inliers, tuning.prior_min_inlier_ratio * seeded[3]):
            res = _verified(
                [seeded],
                sub,
                curr,
                pairs,
                cand,
                k,
                cfg,
                tuning,
                second,
                t_base_opt if planar else None,
                t0,
                prior=True,
            )
            if res.success:  # else (the second search lost it, a sanity test): RANSAC decides
                return res
    # 4. Robust initial motions: 3D points of the previous frame seen in the current frame.
    hyps = initial_motions(sub.xyz[ip], curr.uv[ic], curr.xyz[ic], curr.octave[ic], k, cfg, tuning)
    if not hyps:
        return _fail("pnp_failed", t0, n_match, planar=planar)
    # The guided search + refinement must still reach min_inliers; the seed may be smaller.
    need = (
        min(cfg.min_inliers, tuning.min_pnp_inliers) if tuning.refine == "rgbd" else cfg.min_inliers
    )
    hyps = [h for h in hyps if len(h[1]) >= need]
    if not hyps:
        return _fail("too_few_inliers", t0, n_match, planar=planar)
    # 5. Refinement of every candidate (one that lies near an already refined motion would
    # converge to it: skipped); the one with the most inliers wins. Close calls (a repeated
    # structure) are decided after a narrower second search around each.
    best_n = len(hyps[0][1])
    refined: list[tuple[np.ndarray, int, np.ndarray | None, int]] = []
    for t, inl in hyps:
        if len(inl) < tuning.verify_ratio * best_n or any(
            np.linalg.norm(t[:3, 3] - r[0][:3, 3]) < tuning.distinct_m for r in refined
        ):
            continue
        refined.append(
            _refine(
                t,
                inl,
                sub,
                curr,
                pairs,
                cand,
                k,
                cfg,
                tuning,
                tuning.guided_radius_px,
                tuning.guided_max_hamming,
                covariance=not second,
            )
        )
    return _verified(
        refined, sub, curr, pairs, cand, k, cfg, tuning, second, t_base_opt if planar else None, t0
    )


def _verified(
    refined: list[tuple[np.ndarray, int, np.ndarray | None, int]],
    sub: Features,
    curr: Features,
    pairs: np.ndarray,
    cand: tuple[np.ndarray, np.ndarray],
    k: np.ndarray,
    cfg: VoConfig,
    tuning: VoTuning,
    second: bool,
    t_base_opt: np.ndarray | None,
    t0: float,
    prior: bool = False,
) -> VoResult:
    """Step 5's close calls decided by the second, narrower search around each refined motion
    (``second``); the most inliers win and go to the tests of step 6."""
    if second:
        kept: list[tuple[np.ndarray, int, np.ndarray | None, int]] = []
        for r in sorted(refined, key=lambda r: -r[1]):  # most inliers first; drop converged
            if all(np.linalg.norm(r[0][:3, 3] - o[0][:3, 3]) >= tuning.distinct_m for o in kept):
                kept.append(r)
        top = kept[0][1]
        refined = [
            (
                *_refine(
                    t,
                    np.zeros(0, int),
                    sub,
                    curr,
                    pairs,
                    cand,
                    k,
                    cfg,
                    tuning,
                    tuning.second_radius_px,
                    tuning.second_max_hamming,
                    True,
                )[:3],
                m,
            )
            for t, n, _, m in kept
            if n >= tuning.close_call * top
        ]
    t_cp, n_inl, cov_cp, n_match = max(refined, key=lambda r: r[1])
    res = _accept(t_cp, n_inl, cov_cp, n_match, cfg, tuning, t_base_opt, t0)
    return replace(res, prior=True) if prior and res.success else res


def _accept(
    t_cp: np.ndarray,
    n_inl: int,
    cov_cp: np.ndarray | None,
    n_match: int,
    cfg: VoConfig,
    tuning: VoTuning,
    t_base_opt: np.ndarray | None,
    t0: float,
) -> VoResult:
    """Step 6: inlier and motion sanity tests, covariance of T_prev_curr, planar projection."""
    planar = t_base_opt is not None
    if n_inl < cfg.min_inliers or n_inl < tuning.min_inlier_ratio * n_match:
        return _fail("too_few_inliers", t0, n_match, n_inl, planar=planar)
    # 6. Motion sanity.
    t_pc = inverse(t_cp)
    if np.linalg.norm(t_pc[:3, 3]) > cfg.max_translation or rotation_angle(t_pc) > cfg.max_rotation:
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
    tun = tuning or cfg.advanced
    t0 = time.perf_counter()
    if cfg.method != "orb_pnp":
        # Open3D RGB-D odometry measured 39 % / 8.7 cm on TUM cabinet (16 wrong poses accepted)
        # and 18 cm on a textureless simulated pair: it wins nowhere, so it is bench-only.
        raise ConfigError(f"vo.method: {cfg.method!r} is not implemented (use 'orb_pnp')")
    prev = extract_features(prev_rgb, prev_depth, K, cfg, tun)
    curr = extract_features(curr_rgb, curr_depth, K, cfg, tun)
    return motion_from_features(prev, curr, K, cfg, tun, t_base_opt, t0)


# --------------------------------------------------------------------------------------------
# Tracking from a pose prior (ORB-SLAM's reference-keyframe tracking)
# --------------------------------------------------------------------------------------------


def _with_depth(f: Features) -> Features:
    """The keypoints of ``f`` that have a 3D point (the ones a motion can be measured with)."""
    keep = np.flatnonzero(np.isfinite(f.xyz[:, 2]))
    return Features(f.uv[keep], f.octave[keep], f.desc[keep], f.xyz[keep])


def window_matches(
    t_cp: np.ndarray,
    prev: Features,
    curr: Features,
    curr_tree: cKDTree,
    k: np.ndarray,
    radius_px: float,
    max_hamming: int,
    level_window: int,
) -> np.ndarray:
    """Search by projection: every previous 3D point projected by ``t_cp`` is matched to the
    current keypoint within ``radius_px`` of its projection (and ``level_window`` pyramid
    levels) with the smallest Hamming distance, at most ``max_hamming``; one previous point per
    current keypoint (the closest descriptor wins). ``curr_tree`` indexes ``curr.uv``.
    Returns (M, 2) (prev, curr) index pairs. Only the pairs in the windows are compared:
    a few thousand instead of the N x M of a global search."""
    q = prev.xyz @ t_cp[:3, :3].T + t_cp[:3, 3]
    front = np.flatnonzero(q[:, 2] > 1e-3)
    proj = q[front, :2] / q[front, 2:] * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]
    near = cKDTree(proj).sparse_distance_matrix(curr_tree, radius_px, output_type="ndarray")
    ip, ic = front[near["i"]], near["j"].astype(np.intp)
    if level_window >= 0:
        same = np.abs(prev.octave[ip] - curr.octave[ic]) <= level_window
        ip, ic = ip[same], ic[same]
    wp = np.ascontiguousarray(prev.desc).view(np.uint64)
    wc = np.ascontiguousarray(curr.desc).view(np.uint64)
    d = np.bitwise_count(wp[ip] ^ wc[ic]).sum(1, dtype=np.int64)
    ok = d <= max_hamming
    ip, ic, d = ip[ok], ic[ok], d[ok]
    if len(ip) == 0:
        return np.zeros((0, 2), np.intp)
    o = np.lexsort((ic, d, ip))  # best current keypoint per previous point (ties: lower index)
    o = o[np.r_[True, ip[o][1:] != ip[o][:-1]]]
    o = o[np.lexsort((ip[o], d[o], ic[o]))]  # then one previous point per current keypoint
    o = o[np.r_[True, ic[o][1:] != ic[o][:-1]]]
    return np.column_stack([ip[o], ic[o]])


def motion_from_prior(
    prev: Features,
    curr: Features,
    t_cp_prior: np.ndarray,
    k: np.ndarray,
    cfg: VoConfig,
    tuning: VoTuning,
    t0: float | None = None,
) -> VoResult | None:
    """Steps 3-6 around a predicted motion ``t_cp_prior`` (T_curr_prev), as ORB-SLAM tracks a
    keyframe from the last pose: window search around the predicted projections (instead of
    the global Hamming k-NN and RANSAC), then the refinement, second search and tests of the
    verified hypotheses. None when the prior does not hold (too few matches or inliers, or
    inliers below ``prior_min_inlier_ratio`` of the window matches): the caller falls back to
    global matching."""
    t0 = time.perf_counter() if t0 is None else t0
    sub = _with_depth(prev)
    if len(sub) < cfg.min_inliers or len(curr) < cfg.min_inliers:
        return None
    tree = cKDTree(curr.uv)
    found = 0
    t_cp, radius, max_ham, its, gate_from = (
        t_cp_prior,
        tuning.prior_radius_px,
        tuning.guided_max_hamming,
        None,
        2,
    )
    for step in range(2 if tuning.second_radius_px > 0 else 1):
        pairs = window_matches(t_cp, sub, curr, tree, k, radius, max_ham, tuning.level_window)
        if len(pairs) < cfg.min_inliers:
            return None
        gi, gc = pairs[:, 0], pairs[:, 1]
        last = step == 1 or tuning.second_radius_px <= 0
        t_cp, mask, cov = refine_rgbd(
            t_cp,
            sub.xyz[gi],
            curr.uv[gc],
            curr.xyz[gc, 2],
            curr.octave[gc],
            k,
            tuning,
            its,
            gate_from,
            last,
        )
        n_inl = int(mask.sum())
        if n_inl < tuning.prior_min_inlier_ratio * len(pairs):
            return None
        found = max(found, len(pairs))
        # The second, narrower search starts from a refined motion: gate at once, fewer steps.
        radius, max_ham = tuning.second_radius_px, tuning.second_max_hamming
        its, gate_from = tuning.second_iterations, 0
    res = _accept(t_cp, n_inl, cov, found, cfg, tuning, None, t0)
    return res if res.success else None


def prior_error_px(t_pred: np.ndarray, t_est: np.ndarray, fx: float, depth_m: float) -> float:
    """[px] rough image displacement between two motions at ``depth_m``: rotation angle times
    fx plus translation times fx / depth (the scale of the window the prior must hit)."""
    e = inverse(t_pred) @ t_est
    return (rotation_angle(e) + float(np.linalg.norm(e[:3, 3])) / depth_m) * fx


# --------------------------------------------------------------------------------------------
# Optical-flow tracking between keyframes (RTAB-Map Vis/CorType 1)
# --------------------------------------------------------------------------------------------


def motion_from_flow(
    kf: Features,
    idx: np.ndarray,
    uv_last: np.ndarray,
    gray_kf: np.ndarray,
    gray: np.ndarray,
    depth_m: np.ndarray,
    t_cp_pred: np.ndarray,
    k: np.ndarray,
    cfg: VoConfig,
    tuning: VoTuning,
    t0: float | None = None,
) -> tuple[VoResult, np.ndarray, np.ndarray]:
    """Keyframe-relative motion from the keyframe's 3D points ``kf.xyz[idx]`` tracked by
    pyramidal Lucas-Kanade from the keyframe's image ``gray_kf`` into this one, each search
    starting where the point was in the last frame (``uv_last``; RTAB-Map's flow with an
    initial guess). Anchored to the keyframe, a track does not drift as a frame-to-frame chain
    of Lucas-Kanade steps does (0.03 px median after 14 frames out and back, 0.3 mm of pose;
    on the house route: fused odometry 0.127 -> 0.076 m, the mapped grid's IoU 0.60 -> 0.76).
    The motion is refined from the last frame's pose ``t_cp_pred`` (T_curr_kf) by the joint
    reprojection + disparity Gauss-Newton of step 5 (Huber weights, chi-square gate: lost or
    drifted tracks are its outliers) and accepted by the tests of step 6. Fewer inliers than
    ``prior_min_inlier_ratio`` of the tracks fail (``too_few_inliers``): a motion too large for
    the flow (TUM cabinet keyframes 0.15 m apart: 20-24 % inliers where it went wrong, 45 % and
    more where it did not; 97 % at 30 Hz in the simulated house). ``matches`` is the keyframe's
    point count, so the inlier ratio is the share of the keyframe still tracked
    (Odom/KeyFrameThr).
    Returns (result, idx, uv) of the inlier tracks, to be tracked into the next frame."""
    t0 = time.perf_counter() if t0 is None else t0
    n_kf = int(np.isfinite(kf.xyz[:, 2]).sum())
    none = np.zeros(0, np.intp), np.zeros((0, 2), np.float32)
    if len(uv_last) < cfg.min_inliers:  # (OpenCV returns None for no points at all)
        return _fail("too_few_matches", t0, n_kf, len(uv_last)), *none
    win = (cfg.cor_flow_win_size, cfg.cor_flow_win_size)
    crit = (
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
        cfg.cor_flow_iterations,
        cfg.cor_flow_eps,
    )
    pts, status, _ = cv2.calcOpticalFlowPyrLK(
        gray_kf,
        gray,
        kf.uv[idx].astype(np.float32).reshape(-1, 1, 2),
        uv_last.reshape(-1, 1, 2).copy(),
        winSize=win,
        maxLevel=cfg.cor_flow_max_level,
        criteria=crit,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )  # type: ignore[call-overload]
    uv = pts.reshape(-1, 2).astype(np.float64)
    h, w = depth_m.shape[:2]
    ok = (
        (status.ravel() == 1)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] <= w - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= h - 1)
    )
    idx, uv = idx[ok], uv[ok]
    if len(idx) < cfg.min_inliers:
        return _fail("too_few_matches", t0, n_kf, len(idx)), *none
    z = _lookup(depth_m, uv).astype(np.float64)
    z = np.where(np.isfinite(z) & (z >= cfg.min_depth) & (z <= cfg.max_depth), z, np.nan)
    t_cp, inl, cov = refine_rgbd(
        t_cp_pred, kf.xyz[idx], uv, z, np.zeros(len(idx), int), k, tuning, gate_from=1
    )
    if inl.sum() < tuning.prior_min_inlier_ratio * len(uv_last):  # a jump flow cannot follow
        return _fail("too_few_inliers", t0, n_kf, int(inl.sum())), *none
    res = _accept(t_cp, int(inl.sum()), cov, n_kf, cfg, tuning, None, t0)
    if not res.success:
        return res, *none
    return res, idx[inl], uv[inl].astype(np.float32)


# --------------------------------------------------------------------------------------------
# Stateful shell
# --------------------------------------------------------------------------------------------


@dataclass
class _Keyframe:
    features: Features
    T_kf_last: np.ndarray = field(default_factory=lambda: np.eye(4))  # last frame in kf frame

    @property
    def depth_m(self) -> float:
        """[m] median depth of the keyframe's points (1 m without any)."""
        z = self.features.xyz[:, 2]
        return float(np.nanmedian(z)) if np.isfinite(z).any() else 1.0


class VisualOdometry:
    """Frame-to-keyframe RGB-D odometry holding the keyframe's features and the chained pose.

    Every frame is matched against the current keyframe (features are extracted once per
    frame); a new keyframe is taken when the inlier ratio drops below ``keyframe_thr`` or the
    inliers below ``VoTuning.keyframe_inliers``, the motion since the keyframe exceeds
    ``keyframe_translation``/``keyframe_rotation``, or tracking fails (the failed frame becomes
    the keyframe so the next one can recover; the chained pose then misses that motion, and the
    result says so). ``keyframes=False`` gives plain frame-to-frame odometry.

    Pose prior (off by default: ``VoTuning.prior_radius_px`` says why; as ORB-SLAM tracks its
    reference keyframe from the last pose): the last frame's keyframe-relative pose predicts
    the current one (at 30 Hz the motion in between is a few pixels); :func:`motion_from_prior`
    searches windows around the predicted projections first and the global search runs only
    when that fails. The prior is tried only while it holds:
    after a frame it tracked, or whose global estimate it predicted within
    ``prior_max_error_px`` (``VoResult.prior`` says which path tracked a frame). No
    constant-velocity extrapolation: it fed each estimate's error into the next prediction and
    ran away in a weakly constrained stretch of the house route (VO-only drift 9.4 m per 10 m;
    0.12 m with this prior, as without one).
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        cfg: VoConfig | None = None,
        robot: RobotConfig | None = None,
        tuning: VoTuning | None = None,
        keyframes: bool = True,
    ) -> None:
        self.cfg = cfg or VoConfig()
        if self.cfg.method not in ("orb_pnp", "depth_icp"):
            raise ConfigError(
                f"vo.method: {self.cfg.method!r} is not implemented (use 'orb_pnp' or 'depth_icp')"
            )
        # Geometry-only odometry: the whole job (vo.method) or the fallback (vo.fallback).
        self._icp = None
        if self.cfg.method == "depth_icp" or self.cfg.fallback == "depth_icp":
            from slam.depth_icp import DepthIcpOdometry  # imports kiss_icp

            self._icp = DepthIcpOdometry(intrinsics, self.cfg, robot)
        self._icp_live = False  # the fallback's map holds the last frame (it is running)
        self._last_frame: RgbdFrame | None = None  # the fallback starts from it
        # Per-run counts: feature failures the fallback bridged, and those it could not.
        self.stats: dict[str, int] = {"fallback_used": 0, "fallback_failed": 0}
        self.tuning = tuning or self.cfg.advanced
        self.k = camera_matrix(intrinsics)
        self.keyframes = keyframes
        self.t_base_opt = base_from_optical(robot or RobotConfig()) if self.cfg.force_3dof else None
        self._kf: _Keyframe | None = None
        self.T_odom_cam = np.eye(4)  # chained optical-frame pose of the latest frame
        self._prior_holds = False  # try the pose prior on the next frame
        # Optical flow: (keyframe point indices, their pixels in the last frame)
        self._tracks: tuple[np.ndarray, np.ndarray] | None = None
        self._gray: np.ndarray | None = None  # the keyframe's grey image (optical flow)
        self._given: tuple[RgbdFrame, Features] | None = None  # give_features

    def reset(self) -> None:
        if self._icp is not None:
            self._icp.reset()
        self._icp_live, self._last_frame = False, None
        self._kf = None
        self.T_odom_cam = np.eye(4)
        self._prior_holds = False
        self._tracks, self._gray = None, None
        self._given = None

    def process(self, frame: RgbdFrame) -> VoResult:
        if self._icp is not None and self.cfg.method == "depth_icp":
            res = self._icp.process(frame)
            self.T_odom_cam = self._icp.T_odom_cam
            return res
        res = self._process_features(frame)
        if self._icp is not None:
            res = self._fall_back(frame, res)
        return res

    def _fall_back(self, frame: RgbdFrame, res: VoResult) -> VoResult:
        """``vo.fallback: depth_icp``: a frame the features lost gets depth ICP's motion from
        the last frame (the ICP runs only while the features fail: its map starts from the last
        frame on the first failure and goes on while they keep failing)."""
        last, self._last_frame = self._last_frame, frame
        if res.success or res.reason == "no_previous_frame" or last is None:
            self._icp_live = False
            return res
        assert self._icp is not None
        t0 = time.perf_counter()
        if not self._icp_live:
            self._icp.reset()
            self._icp.process(last)
        icp = self._icp.process(frame)
        self._icp_live = icp.success
        if not icp.success:
            self.stats["fallback_failed"] += 1
            return res
        self.stats["fallback_used"] += 1
        log.debug("VO %s: depth ICP fallback (%d points matched)", res.reason, icp.inliers)
        # The features' keyframe is this frame already (a failed frame becomes the keyframe).
        self.T_odom_cam = self.T_odom_cam @ icp.T_prev_curr
        return replace(icp, fallback=True, ms=res.ms + (time.perf_counter() - t0) * 1e3)

    def _process_features(self, frame: RgbdFrame) -> VoResult:
        t0 = time.perf_counter()
        flow = self.cfg.cor_type == "optical_flow"
        gray = grey(frame.rgb) if flow else None
        feats = None if flow else self._features(frame)
        if self._kf is None:
            self._new_keyframe(self._features(frame) if feats is None else feats, gray)
            n = 3 if self.t_base_opt is not None else 6
            return VoResult(
                False,
                "no_previous_frame",
                np.eye(4),
                0,
                np.full((n, n), np.inf),
                (time.perf_counter() - t0) * 1e3,
            )
        # The keyframe may be up to a keyframe span behind: widen the sanity limits for the
        # keyframe-relative estimate and apply the configured ones to the frame-to-frame motion.
        cfg6 = replace(
            self.cfg,
            force_3dof=False,
            max_translation=self.cfg.max_translation + self.cfg.keyframe_translation,
            max_rotation=self.cfg.max_rotation + self.cfg.keyframe_rotation,
        )
        t_kf_pred = self._kf.T_kf_last  # the last frame's pose: the prediction
        res, tracks, lost = None, None, False
        if gray is not None and self._tracks is not None and self._gray is not None:
            res, *tracks = motion_from_flow(
                self._kf.features,
                *self._tracks,
                self._gray,
                gray,
                frame.depth_m,
                inverse(t_kf_pred),
                self.k,
                cfg6,
                self.tuning,
                t0,
            )
            res = replace(res, prior=True) if res.success else None
            lost = res is None  # the keyframe's points are lost: match globally, start anew
        elif self._prior_holds and self.tuning.prior_radius_px > 0:
            assert feats is not None
            res = motion_from_prior(
                self._kf.features, feats, inverse(t_kf_pred), self.k, cfg6, self.tuning, t0
            )
            res = None if res is None else replace(res, prior=True)
        if res is None:
            feats = self._features(frame) if feats is None else feats
            seed = self._prior_holds and self.tuning.prior_seed
            res = motion_from_features(
                self._kf.features,
                feats,
                self.k,
                cfg6,
                self.tuning,
                None,
                t0,
                inverse(t_kf_pred) if seed else None,
            )
            # Try the prior next time only if it would have hit this frame's window.
            self._prior_holds = (
                res.success
                and prior_error_px(t_kf_pred, res.T_prev_curr, self.k[0, 0], self._kf.depth_m)
                < self.tuning.prior_max_error_px
            )
        if res.success:
            t_kf_curr = res.T_prev_curr
            t_last_curr = inverse(self._kf.T_kf_last) @ t_kf_curr
            if (
                np.linalg.norm(t_last_curr[:3, 3]) > self.cfg.max_translation
                or rotation_angle(t_last_curr) > self.cfg.max_rotation
            ):
                res = replace(
                    res, success=False, reason="implausible_motion", T_prev_curr=np.eye(4)
                )
        if not res.success:
            self._new_keyframe(self._features(frame) if feats is None else feats, gray)
            self._prior_holds = False
            return self._finish(res, None, t0)
        new_kf = (
            not self.keyframes
            or lost
            or res.inlier_ratio < self.cfg.keyframe_thr
            or res.inliers < self.tuning.keyframe_inliers
            or np.linalg.norm(t_kf_curr[:3, 3]) > self.cfg.keyframe_translation
            or rotation_angle(t_kf_curr) > self.cfg.keyframe_rotation
        )
        if new_kf:
            self._new_keyframe(self._features(frame) if feats is None else feats, gray)
        else:
            self._kf = _Keyframe(self._kf.features, t_kf_curr)
            self._tracks = (tracks[0], tracks[1]) if tracks else None
        return self._finish(res, t_last_curr, t0)

    @property
    def features_every_frame(self) -> bool:
        """Every frame's ORB features are extracted (not optical flow, not depth ICP alone)."""
        return self.cfg.method == "orb_pnp" and self.cfg.cor_type == "features"

    def extract(self, frame: RgbdFrame) -> Features:
        """``frame``'s features: a pure function of the frame and the config, so a caller may
        compute them ahead on another thread and hand them in with :meth:`give_features`."""
        return extract_features(frame.rgb, frame.depth_m, self.k, self.cfg, self.tuning)

    def give_features(self, frame: RgbdFrame, feats: Features) -> None:
        """``frame``'s features, made ahead by :meth:`extract`: the next :meth:`process` of
        this very frame uses them instead of extracting again."""
        self._given = (frame, feats)

    def _features(self, frame: RgbdFrame) -> Features:
        given, self._given = self._given, None
        if given is not None and given[0] is frame:
            return given[1]
        return self.extract(frame)

    def _new_keyframe(self, feats: Features, gray: np.ndarray | None) -> None:
        """``feats`` become the keyframe; with optical flow (``gray``, this frame's grey image)
        its points with depth are tracked from here on."""
        self._kf = _Keyframe(feats)
        self._gray = gray
        self._tracks = None
        if gray is not None:
            idx = np.flatnonzero(np.isfinite(feats.xyz[:, 2]))
            self._tracks = (idx, feats.uv[idx].astype(np.float32))

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
