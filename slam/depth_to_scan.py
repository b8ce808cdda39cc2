"""Depth image -> planar LaserScan, tilt-compensated through the camera extrinsics.

Like pointcloud_to_laserscan (points whose height lies in [min_height, max_height], binned by
bearing, nearest return per beam), but on the depth image directly: everything that does not
depend on depth is precomputed once per camera, so a pixel's height test and range are one
precomputed depth interval and one multiply, and its beam is fixed. A frame is then a gather,
an interval test and one ``np.minimum.reduceat`` over pixels sorted by beam. A camera whose
optical centre is not above the scan origin takes an exact general path.

Beams span the horizontal bearings of the row band's pixel rays; beam k is at ``angle_min +
k * inc`` with REP-117 semantics (+inf for no return); ``angle_increment`` <= 0 derives inc
from the intrinsics (1 / fx, about one beam per column). ``output_frame`` "base_link" measures
ranges from the base_link origin, a "camera*" frame from the optical centre's floor projection;
range is always horizontal distance.

The derivation, the frames and the kernel measurements: docs/design/depth_to_scan.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from sensors.config import RobotConfig
from sensors.extrinsics import optical_in_base
from sensors.types import CameraIntrinsics, ConfigError, LaserScan, RgbdFrame
from slam.config import DepthToScanConfig
from slam.geometry import lever_jacobian, ominus, oplus

ROBOT_FRAMES = ("base_link", "base_footprint")  # base_link lies on the floor (ARCHITECTURE.md)
CAMERA_FRAME_PREFIX = "camera"
COLINEAR_TOL = 1e-9  # [m] optical centre this close above the scan origin: fixed bearings
_F32_INF = np.float32(np.inf)
_F32_TINY = np.finfo(np.float32).tiny  # smallest positive depth that counts as a return


class DepthToScanError(ConfigError):
    """The depth->scan configuration cannot be used with this camera."""


# --- pure kernels ----------------------------------------------------------------------------


def base_from_optical(robot: RobotConfig) -> tuple[np.ndarray, np.ndarray]:
    """(R_base_optical 3x3, t_base_optical 3) from the robot's camera extrinsics."""
    return optical_in_base(robot)


def scan_frame_in_base(robot: RobotConfig, cfg: DepthToScanConfig) -> np.ndarray:
    """(x, y, yaw = 0): the pose in base_link of the frame the scans of ``cfg.output_frame`` are
    in, base_link itself or the optical centre's floor projection (axes along base_link's).
    Whoever carries a scan into base_link or pairs it with a pose (the collision monitor, the
    costmap, the mapper and the localiser through :func:`scan_pose`) takes it from here."""
    if cfg.output_frame in ROBOT_FRAMES:
        return np.zeros(3)
    if cfg.output_frame.startswith(CAMERA_FRAME_PREFIX):
        t_base_opt = base_from_optical(robot)[1]
        return np.array([t_base_opt[0], t_base_opt[1], 0.0])
    raise DepthToScanError(
        f"depth_to_scan.output_frame: {cfg.output_frame!r} is not one of "
        f"{list(ROBOT_FRAMES)} or a '{CAMERA_FRAME_PREFIX}*' frame"
    )


def scan_pose(base_pose: np.ndarray, scan_in_base: np.ndarray) -> np.ndarray:
    """Pose(s) (..., 3) of the scan frame from base_link's in any frame (odom, map): what the
    mapper and the localiser are given with the scan, whose poses are the scan frame's. A scan
    in base_link takes the pose as it is (bit for bit: no second wrap of the yaw)."""
    if not np.any(scan_in_base):
        return np.asarray(base_pose, dtype=np.float64)
    return oplus(base_pose, scan_in_base)


def base_pose(scan_frame_pose: np.ndarray, scan_in_base: np.ndarray) -> np.ndarray:
    """Pose(s) (..., 3) of base_link from the scan frame's (:func:`scan_pose` undone): what a
    trajectory compared with base_link ground truth or driven on reports."""
    if not np.any(scan_in_base):
        return np.asarray(scan_frame_pose, dtype=np.float64)
    return oplus(scan_frame_pose, ominus(scan_in_base, np.zeros(3)))


def base_covariance(
    scan_frame_pose: np.ndarray, covariance: np.ndarray, scan_in_base: np.ndarray
) -> np.ndarray:
    """Covariance(s) (..., 3, 3) over base_link's (x, y, yaw) from the scan frame's pose(s)
    (..., 3) and covariance(s), both in one world frame (map, odom): what goes with
    :func:`base_pose`. base_link is the scan frame (+) a fixed offset, so C' = J C J^T with
    J = [[1, 0, -ly], [0, 1, lx], [0, 0, 1]], (lx, ly) the lever from the scan frame's origin
    to base_link's in that frame: a yaw sigma adds lever x sigma of position across the lever.
    A scan in base_link keeps the covariance as it is."""
    if not np.any(scan_in_base):
        return np.asarray(covariance, dtype=np.float64)
    pose = np.asarray(scan_frame_pose, dtype=np.float64)
    j = lever_jacobian(base_pose(pose, scan_in_base)[..., :2] - pose[..., :2])
    return j @ np.asarray(covariance, dtype=np.float64) @ np.swapaxes(j, -1, -2)


def row_band(height_px: int, cy: float, scan_height: int) -> tuple[int, int]:
    """Rows [start, stop) used: depthimage_to_laserscan's ``offset = int(cy - scan_height / 2)``
    and ``scan_height`` rows from there, clipped to the image; 0 = every row."""
    if scan_height <= 0:
        return 0, height_px
    start = min(max(int(cy - scan_height / 2), 0), height_px - 1)
    return start, min(start + scan_height, height_px)


def pixel_rays(
    intrinsics: CameraIntrinsics, rows: tuple[int, int], r_base_opt: np.ndarray
) -> np.ndarray:
    """(N, 3) float64 rays in base_link for the pixels of ``rows``, row-major, scaled so the
    optical z component is 1 (the point at depth z is ``t + z * ray``)."""
    k = intrinsics
    v, u = np.mgrid[rows[0] : rows[1], 0 : k.width].astype(np.float64)
    d_opt = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    return d_opt.reshape(-1, 3) @ r_base_opt.T


def linear_interval(
    slope: np.ndarray, offset: float, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-element interval of z with ``lo <= offset + z * slope <= hi`` (empty: z_lo > z_hi)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (lo - offset) / slope
        b = (hi - offset) / slope
    z_lo = np.where(slope > 0, a, b)
    z_hi = np.where(slope > 0, b, a)
    inside = lo <= offset <= hi  # slope 0: all z or none
    z_lo = np.where(slope == 0, -np.inf if inside else np.inf, z_lo)
    z_hi = np.where(slope == 0, np.inf if inside else -np.inf, z_hi)
    return z_lo, z_hi


def beam_index(bearing_rad: np.ndarray, angle_min: float, increment: float) -> np.ndarray:
    """Beam whose half-increment neighbourhood holds each bearing (may be outside the scan)."""
    return np.rint((bearing_rad - angle_min) / increment).astype(np.intp)


def nearest_per_beam_reference(beam: np.ndarray, range_m: np.ndarray, n_beams: int) -> np.ndarray:
    """Reference kernel: nearest range per beam by ``np.minimum.at``; +inf where empty."""
    out = np.full(n_beams, _F32_INF, np.float32)
    ok = (beam >= 0) & (beam < n_beams)
    np.minimum.at(out, beam[ok], range_m[ok].astype(np.float32))
    return out


def nearest_per_beam_sorted(
    range_sorted_m: np.ndarray, starts: np.ndarray, beams: np.ndarray, n_beams: int
) -> np.ndarray:
    """Fast kernel: ranges already grouped by beam (group i starts at ``starts[i]`` and belongs
    to ``beams[i]``; no group is empty); +inf where a beam has no group or no return."""
    out = np.full(n_beams, _F32_INF, np.float32)
    if len(starts):
        out[beams] = np.minimum.reduceat(range_sorted_m, starts)
    return out


def near_cluster_mean(
    beam: np.ndarray, range_m: np.ndarray, nearest: np.ndarray, window_per_m2: float
) -> np.ndarray:
    """Mean range per beam of the returns within ``window_per_m2 * r^2`` of the beam's nearest
    one (``nearest``, +inf where empty).

    The nearest of many noisy returns is biased short by a few sigma of the depth noise (the
    minimum of N samples); Kinect noise grows with r^2, so averaging the near cluster in a
    window that grows the same way removes that bias while a closer obstacle still wins."""
    ok = np.isfinite(range_m) & (beam >= 0) & (beam < len(nearest))
    b, r = beam[ok], range_m[ok].astype(np.float64)
    near = nearest[b].astype(np.float64)
    inside = r <= near + window_per_m2 * near * near
    total = np.bincount(b[inside], weights=r[inside], minlength=len(nearest))
    count = np.bincount(b[inside], minlength=len(nearest))
    return np.where(count > 0, total / np.maximum(count, 1), nearest).astype(np.float32)


def near_cluster_mean_sorted(
    range_sorted_m: np.ndarray,
    starts: np.ndarray,
    beams: np.ndarray,
    n_beams: int,
    window_per_m2: float,
) -> np.ndarray:
    """:func:`near_cluster_mean` of ranges already grouped by beam (the layout of
    :func:`nearest_per_beam_sorted`, +inf where a pixel does not count), without a per-pixel
    gather or mask: with L the group's window limit, the returns inside it (r <= L) sum to
    sum(min(r, L)) - L * (pixels - inside), which is branch-free (the mask is random, 3x
    slower to apply, as ``np.where``)."""
    out = np.full(n_beams, _F32_INF, np.float32)
    if not len(starts):
        return out
    near = np.minimum.reduceat(range_sorted_m, starts).astype(np.float64)
    empty = ~np.isfinite(near)
    limit = near + window_per_m2 * near * near
    # The largest float32 <= each limit: comparing float32 ranges with it is comparing them
    # with the float64 limit, without widening every pixel. An empty group gets 0: nothing
    # (all +inf) lies inside, and min(r, 0) sums to 0.
    limit32 = limit.astype(np.float32)
    limit32 = np.where(limit32 > limit, np.nextafter(limit32, np.float32(-np.inf)), limit32)
    limit32[empty] = 0.0
    size = np.diff(starts, append=len(range_sorted_m))
    per_pixel = np.repeat(limit32, size)
    inside = range_sorted_m <= per_pixel
    count = np.add.reduceat(inside.view(np.uint8), starts, dtype=np.int32)
    clipped = np.minimum(range_sorted_m, per_pixel, out=per_pixel)
    total = np.add.reduceat(clipped, starts, dtype=np.float64)
    total -= limit32.astype(np.float64) * (size - count)
    out[beams] = np.where(count > 0, total / np.maximum(count, 1), near)
    return out


# --- result and the stateful shell -----------------------------------------------------------


@dataclass(frozen=True, eq=False)
class DepthScan:
    scan: LaserScan  # in cfg.output_frame, REP-117 (+inf = no return)
    valid_pixels: int  # pixels of the row band with a finite depth > 0
    in_band_points: int  # of those, inside [min_height, max_height] and [range_min, range_max]


class DepthToScan:
    """Precomputed depth -> scan converter for one camera, mounting and config.

    ``reduction`` picks the per-beam minimum: "sorted" (pixels pre-sorted by beam, one
    ``reduceat``) or "minimum_at" (the reference ``np.minimum.at``); both give identical scans.
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        robot: RobotConfig,
        cfg: DepthToScanConfig | None = None,
        reduction: Literal["sorted", "minimum_at"] = "sorted",
    ) -> None:
        cfg = cfg or DepthToScanConfig()
        if reduction not in ("sorted", "minimum_at"):
            raise DepthToScanError(f"reduction: {reduction!r} is not 'sorted' or 'minimum_at'")
        self.intrinsics, self.robot, self.cfg, self.reduction = intrinsics, robot, cfg, reduction
        # 1. Extrinsics and the scan origin (base_link or the camera's floor projection).
        r_base_opt, t_base_opt = base_from_optical(robot)
        origin = scan_frame_in_base(robot, cfg)[:2]
        self._offset_xy = t_base_opt[:2] - origin  # optical centre in the scan frame
        self.camera_z_m = float(t_base_opt[2])
        # 2. Rays of the row band, their horizontal scale and bearing at infinity.
        self.rows = row_band(intrinsics.height, intrinsics.cy, cfg.scan_height)
        rays = pixel_rays(intrinsics, self.rows, r_base_opt)
        horiz = np.hypot(rays[:, 0], rays[:, 1])
        bearing = np.arctan2(rays[:, 1], rays[:, 0])
        # 3. Beams spanning the bearings of the band.
        lo_rad, hi_rad = float(bearing.min()), float(bearing.max())
        inc = cfg.angle_increment
        if inc <= 0:
            inc = 1.0 / intrinsics.fx
        self.angle_min, self.angle_increment = lo_rad, float(inc)
        self.n_beams = int(np.rint((hi_rad - lo_rad) / inc)) + 1
        # 4. Per-pixel depth interval of the height band (and of the range limits when the
        #    bearing is fixed), including z > 0 so 0, NaN and inf never pass.
        z_lo, z_hi = linear_interval(rays[:, 2], self.camera_z_m, cfg.min_height, cfg.max_height)
        self.fixed_bearing = bool(np.all(np.abs(self._offset_xy) < COLINEAR_TOL))
        if self.fixed_bearing:
            r_lo, r_hi = linear_interval(horiz, 0.0, cfg.range_min, cfg.range_max)
            z_lo, z_hi = np.maximum(z_lo, r_lo), np.minimum(z_hi, r_hi)
        z_lo = np.maximum(z_lo, _F32_TINY)
        z_hi = np.minimum(z_hi, np.finfo(np.float32).max)
        beam = beam_index(bearing, self.angle_min, self.angle_increment)
        if self.fixed_bearing and reduction == "sorted":
            # Store pixels grouped by beam so one reduceat finds every beam's nearest return.
            self._perm = np.argsort(beam, kind="stable")
            beam_sorted = beam[self._perm]
            self._starts = np.flatnonzero(np.r_[True, beam_sorted[1:] != beam_sorted[:-1]])
            self._group_beam = beam_sorted[self._starts]
            order = self._perm
        else:
            order = np.arange(len(beam))
        self._z_lo = z_lo[order].astype(np.float32)
        self._z_hi = z_hi[order].astype(np.float32)
        self._horiz = horiz[order].astype(np.float32)
        self._beam = beam[order]
        self._rays_xy = rays[order, :2].astype(np.float32)

    def angles(self) -> np.ndarray:
        """Bearing of each beam [rad] in the output frame."""
        return self.angle_min + self.angle_increment * np.arange(self.n_beams)

    def from_frame(self, frame: RgbdFrame) -> DepthScan:
        return self(frame.depth_m, frame.stamp_ns)

    def __call__(self, depth_m: np.ndarray, stamp_ns: int = 0) -> DepthScan:
        """Depth image [m] (HxW, 0 or NaN = invalid) -> the nearest return per beam."""
        k = self.intrinsics
        if depth_m.shape != (k.height, k.width):
            raise DepthToScanError(
                f"depth image is {depth_m.shape}, intrinsics say {(k.height, k.width)}"
            )
        z = np.ascontiguousarray(depth_m[self.rows[0] : self.rows[1]], np.float32).ravel()
        # 1. Diagnostics: what the sensor returned at all.
        valid = int(np.count_nonzero((z > 0) & (z < _F32_INF)))
        if self.fixed_bearing:
            ranges, kept = self._fixed_bearing_scan(z)
        else:
            ranges, kept = self._general_scan(z)
        scan = LaserScan(
            stamp_ns=stamp_ns,
            angle_min=self.angle_min,
            angle_increment=self.angle_increment,
            ranges=ranges,
            range_min=self.cfg.range_min,
            range_max=self.cfg.range_max,
        )
        return DepthScan(scan, valid, kept)

    def _fixed_bearing_scan(self, z: np.ndarray) -> tuple[np.ndarray, int]:
        # 2. One interval test = valid depth, height band and range limits together.
        if self.reduction == "sorted":
            z = z.take(self._perm)
        keep = (z >= self._z_lo) & (z <= self._z_hi)
        # 3. Horizontal range, +inf where the point does not count.
        r = np.where(keep, z * self._horiz, _F32_INF)
        # 4. Nearest return per beam.
        window = self.cfg.return_averaging_window
        if self.reduction == "sorted" and window > 0:
            ranges = near_cluster_mean_sorted(
                r, self._starts, self._group_beam, self.n_beams, window
            )
        elif self.reduction == "sorted":
            ranges = nearest_per_beam_sorted(r, self._starts, self._group_beam, self.n_beams)
        else:
            ranges = nearest_per_beam_reference(self._beam[keep], r[keep], self.n_beams)
            if window > 0:
                ranges = near_cluster_mean(self._beam[keep], r[keep], ranges, window)
        return ranges, int(np.count_nonzero(keep))

    def _general_scan(self, z: np.ndarray) -> tuple[np.ndarray, int]:
        # 2. Height band (and valid depth) by the interval, then only those points go on.
        idx = np.flatnonzero((z >= self._z_lo) & (z <= self._z_hi))
        zi = z[idx]
        # 3. Exact position in the scan frame, range and bearing from its origin.
        x = self._offset_xy[0] + zi * self._rays_xy[idx, 0]
        y = self._offset_xy[1] + zi * self._rays_xy[idx, 1]
        r = np.hypot(x, y)
        beam = beam_index(np.arctan2(y, x), self.angle_min, self.angle_increment)
        ok = (r >= self.cfg.range_min) & (r <= self.cfg.range_max)
        ok &= (beam >= 0) & (beam < self.n_beams)
        # 4. Nearest return per beam (and the mean of its near cluster, when asked).
        ranges = nearest_per_beam_reference(beam[ok], r[ok], self.n_beams)
        if self.cfg.return_averaging_window > 0:
            ranges = near_cluster_mean(beam[ok], r[ok], ranges, self.cfg.return_averaging_window)
        return ranges, int(np.count_nonzero(ok))
