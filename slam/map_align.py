"""Where one occupancy map's frame sits in another's, with no initial guess.

1. **Global search.** A's occupied cells, rasterised at ``coarse_resolution`` and smeared into a
   likelihood field ``F = exp(-d^2 / 2 sigma^2)``, are cross-correlated (FFT) with B's occupied
   cells turned by every yaw of a full sweep: for each yaw one correlation scores every
   translation at once, the mean of ``F`` under B's points (correlative matching, Olson 2009,
   with the translation search done by FFT rather than branch-and-bound).
2. **Refinement.** The best few distinct peaks are refined by point-to-line ICP of B's wall
   cells against A's (:func:`slam.scan_matching.icp_refine` on the grid reference).
3. **Verification.** At the map resolution, each refined pose is checked both ways: of B's
   wall cells that land where A has observed, the fraction within ``agree_distance_m`` of A's
   walls (and the same of A's in B), and the wall length so matched (the overlap). A pose is
   accepted only with enough overlap, enough agreement, and no rival peak — another pose more
   than ``distinct_m`` / ``distinct_deg`` away — explaining the maps nearly as well: maps of two
   different buildings, or too little overlap, are a :class:`MapError`, never a guess.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from sensors.types import MapError
from slam.config import AlignConfig
from slam.geometry import wrap_angle
from slam.occupancy_grid import GridGeometry, OccupancyGrid, warp_to_geometry
from slam.scan_matching import build_grid_reference, icp_refine, voxel_filter

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Verification:
    agreement_ab: float  # of B's wall cells over A's known area, the fraction near A's walls
    agreement_ba: float  # of A's wall cells over B's known area, the fraction near B's walls
    overlap_m: float  # [m] wall length matched (B's agreeing cells x resolution, min both ways)

    @property
    def score(self) -> float:
        """Wall length matched less the length contradicted (walls over the other's known area
        that are not near its walls), by the worse direction."""
        return min(2 * self.agreement_ab - 1, 2 * self.agreement_ba - 1) * self.overlap_m


@dataclass(frozen=True)
class Alignment:
    T_a_b: np.ndarray  # (3,) [m, m, rad] B's map frame in A's map frame
    confidence: float  # [0, 1] min agreement x (1 - best rival / best score)
    verification: Verification
    rival: Verification | None  # the best distinct other pose, if any
    coarse_score: float  # mean likelihood of B's points at the global peak
    covariance: np.ndarray  # (3, 3) ICP covariance of T_a_b


def _walls(grid: OccupancyGrid, occupied_thresh: float) -> np.ndarray:
    """(N, 2) [m] centres of occupied cells next to a non-occupied one."""
    occ = grid.occupied_mask(occupied_thresh)
    surface = occ & (cv2.dilate((~occ).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    rows, cols = np.nonzero(surface)
    x, y = grid.geometry.cell_to_world(rows, cols)
    return np.column_stack([x, y])


def _rotate(points: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return points @ np.array([[c, s], [-s, c]])


def _global_peaks(
    a: OccupancyGrid, a_pts: np.ndarray, b_pts: np.ndarray, cfg: AlignConfig
) -> list[np.ndarray]:
    """The best ``cfg.candidates`` distinct (x, y, yaw, score) of the FFT correlation sweep.

    The score of a pose is the mean over B's wall points of ``F - free_penalty * C``, with ``C``
    1 on A's observed free space farther than two sigmas from its walls: B's walls across A's
    open floor count against a pose, so a pose laying more of B over A is not favoured for that."""
    res = cfg.coarse_resolution
    pad = 3 * cfg.smear_sigma
    lo, hi = a_pts.min(axis=0) - pad, a_pts.max(axis=0) + pad
    geom = GridGeometry.from_bounds(lo[0], lo[1], hi[0], hi[1], res)
    a_lo = np.array([geom.origin_x, geom.origin_y])
    occ = np.full(geom.shape, 255, np.uint8)
    rows, cols = geom.world_to_cell(a_pts[:, 0], a_pts[:, 1])
    occ[rows, cols] = 0
    dist = cv2.distanceTransform(occ, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res
    field = np.exp(-0.5 * (dist / cfg.smear_sigma) ** 2).astype(np.float64)
    free = warp_to_geometry(a.free_mask(), a.geometry, (0.0, 0.0, 0.0), geom)
    field -= cfg.free_penalty * (free & (dist > 2 * cfg.smear_sigma))
    b_c = b_pts - b_pts.mean(axis=0)  # rotate about B's centroid: a compact image per yaw
    radius = float(np.max(np.hypot(b_c[:, 0], b_c[:, 1]))) + res
    n_b = int(np.ceil(2 * radius / res)) + 1
    shape = (field.shape[0] + n_b, field.shape[1] + n_b)
    f_field = np.fft.rfft2(field, shape)
    yaws = np.radians(np.arange(0.0, 360.0, cfg.yaw_step_deg))
    found: list[np.ndarray] = []
    for yaw in yaws:  # one FFT correlation per yaw scores every translation
        q = np.floor((_rotate(b_c, yaw) + radius) / res).astype(int)
        img = np.zeros((n_b, n_b))
        np.add.at(img, (q[:, 1], q[:, 0]), 1.0)
        corr = np.fft.irfft2(f_field * np.conj(np.fft.rfft2(img, shape)), shape)
        # corr[dr, dc] = sum img[r, c] field[r + dr, c + dc]: B's cell (r, c) lands on A's
        # cell (r + dr, c + dc); keep each yaw's few best shifts.
        flat = np.argpartition(corr.ravel(), -cfg.candidates)[-cfg.candidates :]
        dr, dc = np.unravel_index(flat, shape)
        dr = np.where(dr > shape[0] - n_b, dr - shape[0], dr)
        dc = np.where(dc > shape[1] - n_b, dc - shape[1], dc)
        for r, c, v in zip(dr, dc, corr.ravel()[flat], strict=True):
            # B point p (centred, rotated) sits at img cell floor((p + radius)/res); adding the
            # shift lands it at A cell: p + radius + shift * res + a_lo (cell corners -> same).
            t = np.array([c, r]) * res + a_lo + radius - _rotate(b_pts.mean(axis=0)[None], yaw)[0]
            found.append(np.array([t[0], t[1], yaw, v / len(b_pts)]))
    found.sort(key=lambda p: -p[3])
    peaks: list[np.ndarray] = []
    for p in found:
        if all(not _same(p, q, cfg) for q in peaks):
            peaks.append(p)
        if len(peaks) == cfg.candidates:
            break
    return peaks


def _same(p: np.ndarray, q: np.ndarray, cfg: AlignConfig) -> bool:
    return bool(
        np.hypot(p[0] - q[0], p[1] - q[1]) < cfg.distinct_m
        and abs(wrap_angle(p[2] - q[2])) < math.radians(cfg.distinct_deg)
    )


def _transform(pose: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return _rotate(pts, pose[2]) + pose[:2]


def _agreement(pts_in_a: np.ndarray, a: OccupancyGrid, near_wall: np.ndarray) -> tuple[int, int]:
    """(cells over A's observed area, of those within the agree distance of A's walls)."""
    rows, cols = a.geometry.world_to_cell(pts_in_a[:, 0], pts_in_a[:, 1])
    inside = a.geometry.contains(rows, cols)
    rows, cols = rows[inside], cols[inside]
    known = a.observed[rows, cols]
    return int(np.count_nonzero(known)), int(np.count_nonzero(near_wall[rows, cols] & known))


def _near_walls(grid: OccupancyGrid, occupied_thresh: float, distance_m: float) -> np.ndarray:
    occ = grid.occupied_mask(occupied_thresh)
    dist = cv2.distanceTransform((~occ).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return dist * grid.geometry.resolution <= distance_m


def _inverse(p: np.ndarray) -> np.ndarray:
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([-(c * p[0] + s * p[1]), s * p[0] - c * p[1], -p[2]])


def align_maps(
    a: OccupancyGrid,
    b: OccupancyGrid,
    occupied_thresh: tuple[float, float] = (0.65, 0.65),
    cfg: AlignConfig | None = None,
) -> Alignment:
    """B's map frame in A's (see the module doc); :class:`MapError` when no pose is sure."""
    cfg = cfg or AlignConfig()
    a_walls, b_walls = _walls(a, occupied_thresh[0]), _walls(b, occupied_thresh[1])
    if min(len(a_walls), len(b_walls)) < 10:
        raise MapError("a map has fewer than 10 wall cells: nothing to align")
    a_coarse = voxel_filter(a_walls, cfg.coarse_resolution)
    b_coarse = voxel_filter(b_walls, cfg.coarse_resolution)
    peaks = _global_peaks(a, a_coarse, b_coarse, cfg)
    ref = build_grid_reference(
        a.occupied_mask(occupied_thresh[0]),
        (a.geometry.origin_x, a.geometry.origin_y),
        a.geometry.resolution,
    )
    b_icp = voxel_filter(b_walls, cfg.icp_voxel_m)
    near_a = _near_walls(a, occupied_thresh[0], cfg.agree_distance_m)
    near_b = _near_walls(b, occupied_thresh[1], cfg.agree_distance_m)
    results = []
    for peak in peaks:
        icp = icp_refine(ref, b_icp, peak[:3], cfg.icp_correspondence_m, max_iterations=30)
        pose = icp.pose if icp.converged or icp.inlier_fraction > 0 else peak[:3]
        known_ab, agree_ab = _agreement(_transform(pose, b_walls), a, near_a)
        known_ba, agree_ba = _agreement(_transform(_inverse(pose), a_walls), b, near_b)
        ver = Verification(
            agree_ab / max(known_ab, 1),
            agree_ba / max(known_ba, 1),
            min(agree_ab * b.geometry.resolution, agree_ba * a.geometry.resolution),
        )
        log.debug("peak %s score %.3f -> %s %s", peak[:3], peak[3], pose, ver)
        results.append((ver, pose, icp, peak))
    results.sort(key=lambda r: -r[0].score)
    best, pose, icp, peak = results[0]
    rival = next((r[0] for r in results[1:] if not _same(r[1], pose, cfg)), None)
    rival_ratio = 0.0 if rival is None or best.score <= 0 else max(0.0, rival.score / best.score)
    where = f"best pose x {pose[0]:.2f} m, y {pose[1]:.2f} m, yaw {math.degrees(pose[2]):.1f} deg"
    agreement = min(best.agreement_ab, best.agreement_ba)
    if best.overlap_m < cfg.min_overlap_m:
        raise MapError(
            f"cannot align the maps: they do not overlap enough: {best.overlap_m:.1f} m of wall "
            f"match at the {where} (need {cfg.min_overlap_m:g} m)"
        )
    if agreement < cfg.min_agreement:
        raise MapError(
            f"cannot align the maps: they do not overlap: at the {where} only "
            f"{agreement:.0%} of the walls over the other map's known area agree (need "
            f"{cfg.min_agreement:.0%})"
        )
    if rival_ratio > cfg.max_rival_ratio:
        raise MapError(
            f"cannot align the maps: they match in more than one place (a pose elsewhere "
            f"explains them {rival_ratio:.0%} as well as the {where}): they may not "
            "overlap, or only along a featureless corridor"
        )
    pose = np.array([pose[0], pose[1], float(wrap_angle(pose[2]))])
    return Alignment(
        pose, agreement * (1.0 - rival_ratio), best, rival, float(peak[3]), icp.covariance
    )


def merge_grids(a: OccupancyGrid, b: OccupancyGrid, T_a_b: np.ndarray) -> OccupancyGrid:
    """Both maps in A's frame at A's resolution: log-odds summed (independent evidence),
    observed where either observed."""
    gb, ga = b.geometry, a.geometry
    corners = np.array(
        [
            [gb.origin_x, gb.origin_y],
            [gb.origin_x + gb.width * gb.resolution, gb.origin_y],
            [gb.origin_x, gb.origin_y + gb.height * gb.resolution],
            [gb.origin_x + gb.width * gb.resolution, gb.origin_y + gb.height * gb.resolution],
        ]
    )
    cb = _transform(np.asarray(T_a_b, dtype=np.float64), corners)
    lo = np.minimum(cb.min(axis=0), [ga.origin_x, ga.origin_y])
    hi = np.maximum(
        cb.max(axis=0),
        [ga.origin_x + ga.width * ga.resolution, ga.origin_y + ga.height * ga.resolution],
    )
    geom = GridGeometry.from_bounds(lo[0], lo[1], hi[0], hi[1], ga.resolution)
    log_odds = warp_to_geometry(a.log_odds, ga, (0.0, 0.0, 0.0), geom)
    log_odds += warp_to_geometry(b.log_odds, gb, T_a_b, geom)
    observed = warp_to_geometry(a.observed, ga, (0.0, 0.0, 0.0), geom)
    observed |= warp_to_geometry(b.observed, gb, T_a_b, geom)
    return OccupancyGrid(geom, log_odds.astype(np.float32), observed)


__all__ = ["AlignConfig", "Alignment", "Verification", "align_maps", "merge_grids"]
