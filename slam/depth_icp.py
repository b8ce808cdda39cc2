"""Geometry-only odometry on the depth cloud: KISS-ICP's registration behind the VO interface.

For rooms where colour features fail (dim light, blank walls) the depth image still shows
corners, furniture and the floor. One step per line, as ``KissICP.register_frame``:

1. depth -> points in the optical frame (:func:`depth_to_points`, vectorised), in range only;
2. KISS-ICP's double voxel down-sampling (the map gets the fine cloud, ICP the coarse one);
3. its point-to-map ICP from the constant-velocity guess, correspondences within 3 sigma of
   its adaptive threshold;
4. on a strided grid of the organised cloud with normals: a point-to-plane polish against the
   previous frame (:func:`point_to_plane_refine`; KISS-ICP is point-to-point, made for dense
   LiDAR sweeps), then the checks (:func:`icp_check`): the share of points with a partner in
   the previous frame (``icp_min_overlap``), the point-to-plane information of the matched
   points (smallest eigenvalue per point, ``icp_min_constraint``: a blank wall with floor
   leaves the sideways slide unconstrained) and the motion limits -> ``success=False`` +
   reason, never a silent garbage pose; the local map is updated only with an accepted pose
   (a rejected frame restarts the map from itself);
5. the covariance ``s^2 H^-1`` of the point-to-plane problem at the solution (left perturbation
   of ``T_prev_curr``), in the VO's (x, y, z, roll, pitch, yaw) order, and the planar
   projection (:func:`slam.visual_odometry.to_planar`) when ``vo.force_3dof``.

Measurements and the choice of defaults: docs/design/kiss_icp_and_filterpy.md.
"""

from __future__ import annotations

import logging
import math
import time

import cv2
import numpy as np
from scipy.spatial import cKDTree

from sensors.config import RobotConfig
from sensors.types import CameraIntrinsics, ConfigError, RgbdFrame
from slam.config import VoConfig
from slam.visual_odometry import (
    VoResult,
    _fail,
    base_from_optical,
    inverse,
    rotation_angle,
    se3_exp,
    to_planar,
)

log = logging.getLogger(__name__)

ICP_DEPTH_EDGE = 0.05  # [-] neighbours further apart than this share of depth: no normal
ICP_SUPPORT_COS = 0.5  # [-] a normal within 60 deg of a direction constrains a slide along it
ICP_BLOCK_VALID = 0.75  # [-] share of a block's pixels with depth for it to have a point


def orthonormalised(t: np.ndarray) -> np.ndarray:
    """``t`` with its rotation projected onto SO(3) (SVD). KISS-ICP's Sophus aborts the whole
    process (not an exception) on a rotation off orthogonal by ~1e-10, which products of a few
    hundred motions reach."""
    u, _, vt = np.linalg.svd(t[:3, :3])
    out = np.array(t, dtype=np.float64, copy=True)
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def depth_to_points(
    depth_m: np.ndarray, intr: CameraIntrinsics, min_depth: float, max_depth: float, stride: int = 1
) -> np.ndarray:
    """(N, 3) float64 optical-frame points of the pixels on a ``stride`` grid with a depth in
    [min_depth, max_depth] (0 and NaN are no return)."""
    d = depth_m[::stride, ::stride].astype(np.float64)
    v, u = np.mgrid[0 : depth_m.shape[0] : stride, 0 : depth_m.shape[1] : stride]
    ok = np.isfinite(d) & (d >= max(min_depth, 1e-6)) & (d <= max_depth)
    z = d[ok]
    return np.column_stack([(u[ok] - intr.cx) / intr.fx * z, (v[ok] - intr.cy) / intr.fy * z, z])


def organised_normals(
    depth_m: np.ndarray, intr: CameraIntrinsics, min_depth: float, max_depth: float, stride: int
) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit normals of the organised cloud on ``stride`` x ``stride`` pixel blocks.

    Each block's depth is the mean of its in-range pixels (blocks with less than
    ``ICP_BLOCK_VALID`` of them are holes): Kinect depth noise (~1 cm at 2 m) would otherwise
    tilt the normals so much that a blank wall looks constrained in every direction. Normals are
    the cross product of the central differences along the block rows and columns, where all
    four neighbours have depth and none is across a depth edge. Returns (N, 3) points at the
    block centres, (N, 3) normals facing the camera."""
    h, w = depth_m.shape[:2]
    hb, wb = h // stride, w // stride
    if hb < 3 or wb < 3:  # no block with four neighbours: no normal
        return np.zeros((0, 3)), np.zeros((0, 3))
    d = depth_m[: hb * stride, : wb * stride].astype(np.float32)
    ok = np.isfinite(d) & (d >= max(min_depth, 1e-6)) & (d <= max_depth)
    size = (wb, hb)
    share = cv2.resize(ok.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    mean = cv2.resize(np.where(ok, d, 0.0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    z = np.where(share >= ICP_BLOCK_VALID, mean / np.maximum(share, 1e-6), np.nan).astype(
        np.float64
    )
    v, u = np.mgrid[0:hb, 0:wb] * stride + (stride - 1) / 2.0
    p = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=-1)
    du = p[1:-1, 2:] - p[1:-1, :-2]
    dv = p[2:, 1:-1] - p[:-2, 1:-1]
    n = np.cross(du, dv)
    c = p[1:-1, 1:-1]
    edge = ICP_DEPTH_EDGE * 2 * c[..., 2]  # central differences span two blocks
    good = np.isfinite(n).all(-1) & (np.abs(du[..., 2]) < edge) & (np.abs(dv[..., 2]) < edge)
    n, c = n[good], c[good]
    norm = np.linalg.norm(n, axis=1)
    keep = norm > 0
    n, c = n[keep] / norm[keep, None], c[keep]
    n *= -np.sign(np.einsum("ij,ij->i", n, c))[:, None]  # face the camera
    return c, n


def point_to_plane_information(p: np.ndarray, n: np.ndarray, scale_m: float) -> np.ndarray:
    """6x6 ``H = sum J^T J`` of the residuals ``n . (exp(d) p - q)`` over a left perturbation
    ``d = (w, v)`` of the motion: ``J = [(p x n)^T, n^T]``. ``p`` are the current points moved
    into the previous frame, ``n`` their partners' normals; the rotation rows are divided by
    ``scale_m`` so both halves are per metre (comparable eigenvalues)."""
    j = np.hstack([np.cross(p, n) / scale_m, n])
    return j.T @ j


def point_to_plane_refine(
    t_prev_curr: np.ndarray,
    curr: np.ndarray,
    prev: np.ndarray,
    prev_normals: np.ndarray,
    prev_tree: cKDTree,
    max_dist: float,
    iterations: int,
) -> np.ndarray:
    """Gauss-Newton on the point-to-plane residuals ``r = n . (T p - q)`` of the current check
    points against the previous frame's, nearest partners within ``max_dist`` re-found every
    step, Huber weights at ``max_dist / 3``; ``T <- exp(d) T`` (:func:`point_to_plane_information`'s
    Jacobian). KISS-ICP's point-to-point ICP on a sparse depth cloud leaves 5-20 mm per frame on
    exact synthetic planes (the sampling), this polish brings it under a millimetre."""
    t = t_prev_curr
    huber = max_dist / 3
    for _ in range(iterations):
        q = curr @ t[:3, :3].T + t[:3, 3]
        dist, idx = prev_tree.query(q, distance_upper_bound=max_dist)
        hit = np.isfinite(dist)
        if hit.sum() < 7:
            break
        q, nn = q[hit], prev_normals[idx[hit]]
        r = np.einsum("ij,ij->i", nn, q - prev[idx[hit]])
        w = np.minimum(1.0, huber / np.maximum(np.abs(r), 1e-12))
        j = np.hstack([np.cross(q, nn), nn])
        h = (j * w[:, None]).T @ j
        g = (j * w[:, None]).T @ r
        try:
            d = -np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            break
        t = se3_exp(d) @ t
        if np.linalg.norm(d) < 1e-6:
            break
    return t


def weakest_direction_support(normals: np.ndarray) -> float:
    """Share of ``normals`` (N, 3) that push against the least constrained translation: those
    with ``|n . e| > ICP_SUPPORT_COS`` for ``e`` the eigenvector of the smallest eigenvalue of
    ``sum n n^T``. A blank wall with the floor has none (the slide along the wall); a room corner
    or furniture, a few per cent. (The smallest eigenvalue itself does not separate them: the
    residual normal noise alone gives a wall + floor half the cabinet scene's.)"""
    if len(normals) == 0:
        return 0.0
    e = np.linalg.eigh(normals.T @ normals)[1][:, 0]
    return float(np.mean(np.abs(normals @ e) > ICP_SUPPORT_COS))


def icp_check(
    t_prev_curr: np.ndarray,
    curr: np.ndarray,
    prev: np.ndarray,
    prev_normals: np.ndarray,
    prev_tree: cKDTree,
    max_dist: float,
) -> tuple[int, float, np.ndarray, float]:
    """Correspondences of the current check points ``curr`` moved by ``t_prev_curr`` with the
    previous frame's (``prev``, its normals, its k-d tree) within ``max_dist``.

    Returns (matched count, smallest eigenvalue of the per-point information (rotations per
    ``scale``), 6x6 covariance over the left perturbation (w, v) of ``t_prev_curr``, the
    point-to-plane residual RMS [m]). The covariance is ``s^2 H^-1`` with the residual variance
    ``s^2`` (m - 6 degrees of freedom); infinite when fewer than 7 points match or H is singular.
    """
    q = curr @ t_prev_curr[:3, :3].T + t_prev_curr[:3, 3]
    dist, idx = prev_tree.query(q, distance_upper_bound=max_dist)
    hit = np.isfinite(dist)
    m = int(hit.sum())
    inf = np.full((6, 6), np.inf)
    if m < 7:
        return m, 0.0, inf, math.inf
    q, nn = q[hit], prev_normals[idx[hit]]
    r = np.einsum("ij,ij->i", nn, q - prev[idx[hit]])
    scale = float(np.median(q[:, 2]))
    h = point_to_plane_information(q, nn, scale)
    lam = weakest_direction_support(nn)
    s2 = float(r @ r) / (m - 6)
    try:
        h_inv = np.linalg.inv(h)
    except np.linalg.LinAlgError:
        return m, lam, inf, math.sqrt(s2)
    # Back from the scaled rotation (w / scale) to radians: d_scaled = D d with D = diag(1/s, 1).
    back = np.diag([1.0 / scale] * 3 + [1.0] * 3)
    return m, lam, s2 * back @ h_inv @ back, math.sqrt(s2)


class DepthIcpOdometry:
    """KISS-ICP on the depth cloud, giving per frame the camera motion as :class:`VoResult`.

    The local voxel map lives in the first accepted frame's optical frame; the chained pose
    ``T_odom_cam`` as VisualOdometry's. ``reset`` forgets the map (the next frame starts anew).
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        cfg: VoConfig | None = None,
        robot: RobotConfig | None = None,
    ) -> None:
        try:  # optional and heavy: imported where used
            from kiss_icp.config import KISSConfig
        except ImportError as err:  # pragma: no cover - a dependency of the package
            raise ConfigError("vo.method depth_icp needs the kiss-icp package") from err
        self.cfg = cfg or VoConfig()
        self._tuning = self.cfg.advanced  # its covariance floors
        self.intrinsics = intrinsics
        self.t_base_opt = base_from_optical(robot or RobotConfig()) if self.cfg.force_3dof else None
        c = self.cfg
        self._kiss_cfg = KISSConfig(
            data={"max_range": c.max_depth, "min_range": c.min_depth, "deskew": False},
            mapping={"voxel_size": c.icp_voxel_size, "max_points_per_voxel": 20},
            # One thread: TBB's parallel reductions sum in a varying order (one input, one
            # answer), and the VO's second thread is busy with ORB when it falls back.
            registration={"max_num_threads": 1},
            adaptive_threshold={
                "initial_threshold": c.icp_initial_threshold,
                "min_motion_th": c.icp_min_motion,
            },
        )
        self.T_odom_cam = np.eye(4)
        self.reset()

    def reset(self) -> None:
        from kiss_icp.mapping import get_voxel_hash_map
        from kiss_icp.registration import get_registration
        from kiss_icp.threshold import get_threshold_estimator

        self._map = get_voxel_hash_map(self._kiss_cfg)
        self._registration = get_registration(self._kiss_cfg)
        self._threshold = get_threshold_estimator(self._kiss_cfg)
        self._pose = np.eye(4)  # in the map's frame
        self._delta = np.eye(4)  # the last accepted motion: the constant-velocity guess
        self._prev: tuple[np.ndarray, np.ndarray, cKDTree] | None = None

    def process(self, frame: RgbdFrame) -> VoResult:
        from kiss_icp.voxelization import voxel_down_sample

        t0 = time.perf_counter()
        c, planar = self.cfg, self.t_base_opt is not None
        # 1. Depth -> optical-frame points; the check grid with normals.
        pts = depth_to_points(
            frame.depth_m, self.intrinsics, c.min_depth, c.max_depth, c.icp_pixel_stride
        )
        chk, nrm = organised_normals(
            frame.depth_m, self.intrinsics, c.min_depth, c.max_depth, c.icp_check_stride
        )
        # 2. KISS-ICP's voxelisation: the fine cloud for the map, the coarse one for ICP.
        fine = voxel_down_sample(pts, c.icp_voxel_size * 0.5) if len(pts) else pts
        source = voxel_down_sample(fine, c.icp_voxel_size * 1.5) if len(fine) else fine
        prev, self._prev = self._prev, (chk, nrm, cKDTree(chk)) if len(chk) else None
        if len(source) < c.icp_min_points or len(chk) < c.icp_min_points:
            self.reset()
            return _fail("too_few_points", t0, len(source), planar=planar)
        if prev is None or self._map.empty():
            self._map.update(fine, self._pose)
            return _fail("no_previous_frame", t0, len(source), planar=planar)
        # 3. Point-to-map ICP from the constant-velocity guess.
        sigma = self._threshold.get_threshold()
        guess = orthonormalised(self._pose @ self._delta)
        pose = self._registration.align_points_to_map(
            points=source,
            voxel_map=self._map,
            initial_guess=guess,
            max_correspondance_distance=3 * sigma,
            kernel=sigma,
        )
        t_pc = inverse(self._pose) @ pose
        if c.icp_refine_iterations > 0:  # point-to-plane polish against the previous frame
            t_pc = point_to_plane_refine(
                t_pc, chk, *prev, c.icp_check_distance, c.icp_refine_iterations
            )
            pose = orthonormalised(self._pose @ t_pc)
        # 4. Checks against the previous frame: overlap, constraint, motion limits.
        matched, lam, cov_wv, _ = icp_check(t_pc, chk, *prev, max_dist=c.icp_check_distance)
        reason = None
        if matched < c.icp_min_overlap * len(chk):
            reason = "too_few_inliers"
        elif lam < c.icp_min_constraint:
            reason = "degenerate"
        elif (
            np.linalg.norm(t_pc[:3, 3]) > c.max_translation or rotation_angle(t_pc) > c.max_rotation
        ):
            reason = "implausible_motion"
        elif (
            c.icp_max_deviation > 0
            and np.linalg.norm(t_pc[:3, 3] - self._delta[:3, 3]) > c.icp_max_deviation
        ):
            reason = "implausible_motion"  # a jump off the constant velocity: a wrong minimum
        if reason is not None:
            log.debug(
                "depth ICP rejected a frame: %s (overlap %d/%d, constraint %.4f)",
                reason,
                matched,
                len(chk),
                lam,
            )
            self.reset()  # a rejected frame starts the map anew, as a lost VO takes a keyframe
            self._prev = (chk, nrm, cKDTree(chk))
            self._map.update(fine, self._pose)
            return _fail(reason, t0, len(chk), matched, planar=planar)
        # KISS-ICP's update step: threshold, local map, constant-velocity model, pose.
        self._threshold.update_model_deviation(orthonormalised(inverse(guess) @ pose))
        self._map.update(fine, pose)
        self._delta, self._pose = t_pc, pose
        # 5. Covariance in (x y z roll pitch yaw) order, planar projection.
        perm = [3, 4, 5, 0, 1, 2]
        cov6 = cov_wv[np.ix_(perm, perm)]
        floor = np.array([self._tuning.min_sigma_m] * 3 + [self._tuning.min_sigma_rad] * 3) ** 2
        cov6 = cov6 + np.diag(floor)
        delta, cov = None, cov6
        if planar:
            assert self.t_base_opt is not None
            delta, cov, t_pc = to_planar(t_pc, cov6, self.t_base_opt)
        self.T_odom_cam = self.T_odom_cam @ t_pc
        ms = (time.perf_counter() - t0) * 1e3
        return VoResult(True, "ok", t_pc, matched, cov, ms, len(chk), delta)
