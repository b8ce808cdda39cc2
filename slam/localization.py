"""Localisation-only mode: track the pose against a saved map, relocalise globally when lost.

The map is never modified. :class:`MapModel` derives from an :class:`OccupancyGrid` (ours or any
Nav2 map) what matching needs; :class:`Localizer` is a thin stateful shell over pure kernels.
Per scan (:meth:`Localizer.update`):

1. **predict** from the last estimate and the odometry increment (AMCL's ``alpha1..4`` noise);
2. **match**: point-to-line ICP from the prediction, else an exact correlative search in the
   search window refined by ICP; then a sub-cell polish of the points on the map's walls on
   the smoothed map (Cartographer's Ceres scan matcher), kept within a cell of ICP's pose;
3. **fuse** prediction and match in a Kalman update; a match far outside the prediction is
   gated and held as a jump hypothesis until consecutive scans confirm it;
4. **confidence** from the scan's likelihood at the fused pose; low for ``lost_time`` means
   "lost" (unless dead reckoning is allowed), and a sudden drop runs a kidnap check;
5. ``map_to_odom = pose (+) odom^-1``: the odom frame stays continuous, the map frame jumps.

**Global relocalisation** (no initial pose, or lost): :func:`global_search`, an exact
multi-resolution branch-and-bound over the free cells and a full turn, gives a few distinct
hypotheses; each is refined, propagated by odometry and accepted only after consecutive
agreeing matches on scans taken after real motion, and only when no rival scores within
``relocalization_ambiguity_ratio`` (a symmetric map stays "relocalising" rather than guess).

Poses are those of the scan frame in ``map``; odometry is given for the same frame. The full
rules (gate, kidnap check, narrow-scan safeguards, memory): docs/design/localization.md.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from sensors.gps import antenna_xy
from sensors.types import LaserScan, MapError
from slam.config import LocalizerConfig
from slam.depth_to_scan import base_pose
from slam.ekf import pose_update as kalman_update
from slam.geometry import ominus, oplus, wrap_angle
from slam.occupancy_grid import OccupancyGrid
from slam.scan_matching import (
    LikelihoodField,
    ReferenceCloud,
    SmoothField,
    build_grid_reference,
    build_likelihood_field,
    build_smooth_field,
    correlative_match,
    icp_refine,
    near_surface,
    refine_on_field,
    release_degenerate_axis,
    scan_points,
    surface_mask,
    transform_points,
    voxel_filter,
)

log = logging.getLogger(__name__)

MIN_SCAN_POINTS = 20  # valid returns a scan needs to be matched at all
MIN_MAP_POINTS = 20  # occupied cells a map needs to be matched against
GLOBAL_TOP_LEVEL = 5  # global pyramid: top blocks of 2^5 = 32 cells (3.2 m at 0.1 m)
GLOBAL_BEAM_WIDTH = 256  # blocks per level of the beam descent to a first leaf
GLOBAL_THRESHOLD_RATIOS = (0.95, 0.9, 0.85, 0.8)  # [x best] global search thresholds
MAX_HISTORY_SCANS = 50  # scans stacked for relocalisation evidence (memory bound)
SCORE_CHUNK = 16384  # global candidates scored per gather (x points x 8 bytes of indices)
UINT8_SCALE = 255.0  # likelihood in [0, 1] stored as uint8
UNKNOWN_VARIANCE = 1.0e6  # [m^2, rad^2] covariance diagonal of a pose that is not established
MIN_MATCH_SIGMA = (0.005, 0.002)  # [m, rad] floor of a scan match's sigmas in the fusion
MIN_PREDICT_SIGMA = (0.002, 0.001)  # [m, rad] floor of the odometry noise per scan

Status = Literal["tracking", "lost", "relocalising"]


# 1. Pose algebra and the filter kernels ---------------------------------------------------------


def inverse(a: np.ndarray) -> np.ndarray:
    return ominus(a, np.zeros(3))


def motion_noise(u: np.ndarray, config: LocalizerConfig) -> np.ndarray:
    """(3, 3) covariance of an odometry increment ``u`` in the frame it starts from (AMCL's
    diff-drive model): var_trans = alpha3 d^2 + alpha4 dtheta^2, var_rot = alpha1 dtheta^2 +
    alpha2 d^2, the translation variance applied along and across the motion."""
    d2, r2 = u[0] ** 2 + u[1] ** 2, float(wrap_angle(u[2])) ** 2
    var_t = max(config.alpha3 * d2 + config.alpha4 * r2, MIN_PREDICT_SIGMA[0] ** 2)
    var_r = max(config.alpha1 * r2 + config.alpha2 * d2, MIN_PREDICT_SIGMA[1] ** 2)
    return np.diag([var_t, var_t, var_r])


def predict(
    x: np.ndarray, p: np.ndarray, u: np.ndarray, q_u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """x' = x (+) u; P' = F P F^T + G Q_u G^T with F = d(x (+) u)/dx = [[1, 0, -s u_x - c u_y],
    [0, 1, c u_x - s u_y], [0, 0, 1]] and G = d(x (+) u)/du = blockdiag(R(yaw), 1)."""
    c, s = math.cos(x[2]), math.sin(x[2])
    f = np.array(
        [[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0.0, 0.0, 1.0]]
    )
    g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    p_new = f @ p @ f.T + g @ q_u @ g.T
    return oplus(x, u), 0.5 * (p_new + p_new.T)


def mahalanobis2(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> float:
    """Squared Mahalanobis distance of a pose measurement ``z`` (covariance ``r``) from the
    estimate ``x`` (covariance ``p``): nu^T (P + R)^-1 nu, the yaw residual wrapped."""
    nu = np.asarray(z, dtype=np.float64) - x
    nu[2] = wrap_angle(nu[2])
    return float(nu @ np.linalg.solve(p + r, nu))


def moved_enough(before: np.ndarray, now: np.ndarray, min_d: float, min_a: float) -> bool:
    """AMCL's update_min_d / update_min_a test: moved ``min_d`` or turned ``min_a`` from pose
    ``before`` to ``now`` (always, with both 0)."""
    step = ominus(before, now)
    return math.hypot(step[0], step[1]) >= min_d or abs(float(step[2])) >= min_a


def position_sigma(p: np.ndarray) -> float:
    """[m] standard deviation of a pose covariance's position along its worst axis."""
    return math.sqrt(max(float(np.linalg.eigvalsh(p[:2, :2])[-1]), 0.0))


# 2. The map model ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class GlobalField:
    """Coarse uint8 likelihood pyramid for the global search, padded by the scan's reach.

    ``levels[k][r, c]`` is the maximum of ``levels[0]`` over rows r..r+2^k-1 and cols
    c..c+2^k-1; ``free[k]`` likewise says whether such a block holds a free cell (a candidate
    scan origin). Cell (pad, pad) is the map's lower-left coarse cell."""

    origin: np.ndarray  # (2,) [m] world (x, y) of the corner of padded cell (0, 0)
    resolution: float  # [m/cell]
    pad: int  # [cells] zero border on every side (scan reach + one top block)
    map_cells: tuple[int, int]  # (rows, cols) of the map region inside the padding
    reach_m: float  # [m] scan points farther than this from the origin are not scored
    levels: tuple[np.ndarray, ...]  # each (Hp, Wp) uint8, likelihood x 255
    free: tuple[np.ndarray, ...]  # each (Hp, Wp) bool

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.levels) + sum(a.nbytes for a in self.free)


@dataclass(frozen=True, eq=False)
class MapModel:
    """What localisation needs from a map: occupied points, the fine likelihood field (tracking
    search and confidence), the ICP reference, the smooth field of the sub-cell polish, the
    global-search pyramid and the free mask."""

    grid: OccupancyGrid
    points: np.ndarray  # (M, 2) [m] centres of occupied cells
    field: LikelihoodField  # fine field, smear sigma_hit, margin linear_search_window
    reference: ReferenceCloud  # occupied cell centres with normals, for ICP
    smooth: SmoothField  # blurred wall cells, bicubic: the sub-cell polish after ICP
    global_field: GlobalField
    free: np.ndarray  # (H, W) bool free cells of the grid (free_thresh)
    occupied: np.ndarray  # (H, W) bool occupied cells of the grid (occupied_thresh)

    @classmethod
    def from_grid(
        cls,
        grid: OccupancyGrid,
        config: LocalizerConfig,
        occupied_thresh: float = 0.65,
        free_thresh: float = 0.25,
    ) -> MapModel:
        """Raises :class:`MapError` for a map without occupied cells or without free space."""
        geom = grid.geometry
        occ = grid.occupied_mask(occupied_thresh)
        free = grid.free_mask(free_thresh) & ~occ
        n_occ, n_free = int(np.count_nonzero(occ)), int(np.count_nonzero(free))
        if n_occ < MIN_MAP_POINTS:
            raise MapError(
                f"the map has {n_occ} occupied cells (occupied_thresh "
                f"{occupied_thresh}); need at least {MIN_MAP_POINTS} to localise "
                f"against"
            )
        if n_free == 0:
            raise MapError(
                f"the map has no free cells (free_thresh {free_thresh}): there is "
                f"nowhere the robot could be"
            )
        rows, cols = np.nonzero(occ)
        pts = np.column_stack(geom.cell_to_world(rows, cols))
        window_cells = 2 * config.linear_search_window / geom.resolution + 1
        n_levels = int(math.ceil(math.log2(window_cells))) + 1
        fine = build_likelihood_field(
            pts, geom.resolution, config.sigma_hit, config.linear_search_window, n_levels
        )
        # ICP's reference: the cells a scan can hit (beside a non-occupied one), with normals
        # from the grid's structure tensor: nearest-neighbour PCA finds no line in a wall two
        # or more cells thick (a CAD floor plan, a thick Nav2 wall) and ICP would get nothing.
        ref = build_grid_reference(occ, (geom.origin_x, geom.origin_y), geom.resolution)
        # The polish's field: wall cells a scan can hit (not the inside of a thick wall, whose
        # blur would pull the points into it), blurred so its ridge is their centroid.
        smooth = build_smooth_field(
            surface_mask(occ),
            (geom.origin_x, geom.origin_y),
            geom.resolution,
            config.refine_smoothing_sigma,
        )
        gfield = build_global_field(grid, occ, free, config)
        log.debug(
            "map model: %d occupied, %d free cells; global field %.1f MB",
            n_occ,
            n_free,
            gfield.nbytes / 1e6,
        )
        return cls(grid, pts, fine, ref, smooth, gfield, free, occ)

    def score(self, points: np.ndarray, pose: np.ndarray) -> float:
        """Confidence: mean fine likelihood of scan ``points`` (scan frame) at ``pose``."""
        if len(points) == 0:
            return 0.0
        return float(self.field.lookup(transform_points(pose, points)).mean())

    def cell_class(self, xy: np.ndarray) -> str:
        """ "free", "occupied", "unknown" or "outside" for a world position."""
        geom = self.grid.geometry
        r, c = geom.world_to_cell(xy[0], xy[1])
        if not bool(geom.contains(r, c)):
            return "outside"
        if self.occupied[r, c]:
            return "occupied"
        return "free" if self.free[r, c] else "unknown"


def _block_max(a: np.ndarray, k: int) -> np.ndarray:
    """Max over the 2^k x 2^k block anchored (top-left) at each cell, zero beyond the array."""
    if k == 0:
        return a
    kernel = np.ones((2**k, 2**k), np.uint8)
    return cv2.dilate(a, kernel, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT, borderValue=0)


def build_global_field(
    grid: OccupancyGrid, occupied: np.ndarray, free: np.ndarray, config: LocalizerConfig
) -> GlobalField:
    """The coarse likelihood pyramid of the global search (see :class:`GlobalField`)."""
    geom = grid.geometry
    res = max(config.global_search_resolution, geom.resolution)
    reach = config.laser_max_range
    top = GLOBAL_TOP_LEVEL
    pad = int(math.ceil(reach / res)) + 2 + 2**top
    mh = int(math.ceil(geom.height * geom.resolution / res))
    mw = int(math.ceil(geom.width * geom.resolution / res))
    hp, wp = mh + 2 * pad, mw + 2 * pad
    origin = np.array([geom.origin_x, geom.origin_y]) - pad * res

    def coarse(mask: np.ndarray) -> np.ndarray:
        rows, cols = np.nonzero(mask)
        x, y = geom.cell_to_world(rows, cols)
        out = np.zeros((hp, wp), np.uint8)
        out[
            np.floor((y - origin[1]) / res).astype(np.int64),
            np.floor((x - origin[0]) / res).astype(np.int64),
        ] = 1
        return out

    occ_c = coarse(occupied)
    # 1. Smear: the distance [m] from each coarse cell centre to the nearest occupied coarse cell.
    dist = cv2.distanceTransform((1 - occ_c) * 255, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res
    lik = np.exp(-0.5 * (dist / config.global_search_sigma) ** 2)
    field0 = np.round(lik * UINT8_SCALE).astype(np.uint8)
    # 2. Candidate origins: coarse cells holding a free fine cell, and not an occupied one.
    free_c = coarse(free) & (1 - occ_c)
    levels = tuple(_block_max(field0, k) for k in range(top + 1))
    frees = tuple(_block_max(free_c, k).astype(bool) for k in range(top + 1))
    return GlobalField(origin, res, pad, (mh, mw), reach, levels, frees)


# 3. Global search (batched branch-and-bound over the whole map) --------------------------------


def coarse_score(gf: GlobalField, points: np.ndarray, pose: np.ndarray) -> float:
    """Mean coarse likelihood (0..1) of scan ``points`` at ``pose``, the global search's score
    (points beyond the field count 0)."""
    pts = points[np.hypot(points[:, 0], points[:, 1]) <= gf.reach_m]
    if len(pts) == 0:
        return 0.0
    w = transform_points(pose, pts)
    c = np.floor((w[:, 0] - gf.origin[0]) / gf.resolution).astype(np.int64)
    r = np.floor((w[:, 1] - gf.origin[1]) / gf.resolution).astype(np.int64)
    hp, wp = gf.levels[0].shape
    ok = (r >= 0) & (r < hp) & (c >= 0) & (c < wp)
    return float(gf.levels[0][r[ok], c[ok]].sum(dtype=np.int64)) / (len(pts) * UINT8_SCALE)


@dataclass(frozen=True)
class GlobalCandidate:
    pose: np.ndarray  # (3,) lattice pose of the scan origin in map
    score: float  # coarse mean likelihood in [0, 1]


def _global_scores(
    flat: np.ndarray, offsets: np.ndarray, a: np.ndarray, r: np.ndarray, c: np.ndarray, w: int
) -> np.ndarray:
    """Mean coarse likelihood (0..1) of the points rotated by angle ``a[i]`` with the scan origin
    at padded cell (r[i], c[i]); ``offsets`` (A, N) are the points' flat cell offsets."""
    out = np.empty(len(a), np.float64)
    n = offsets.shape[1]
    for lo in range(0, len(a), SCORE_CHUNK):  # bounded memory: SCORE_CHUNK x N indices at once
        hi = lo + SCORE_CHUNK
        idx = offsets[a[lo:hi]] + (r[lo:hi] * w + c[lo:hi]).astype(np.int32)[:, None]
        out[lo:hi] = np.take(flat, idx).sum(axis=1, dtype=np.int64) / (n * UINT8_SCALE)
    return out


def global_search(
    gf: GlobalField,
    points: np.ndarray,
    angle_step_rad: float,
    min_score: float,
    candidate_ratio: float,
    max_hypotheses: int,
    separation_m: float,
    separation_rad: float,
    region: tuple[float, float, float] | None = None,
) -> tuple[list[GlobalCandidate], int]:
    """Distinct lattice poses of scan ``points`` (N, 2, scan frame) over every free cell of the
    map and a full turn, best first, with the number of blocks and leaves scored.

    Exact on the lattice: a block's score bound is the mean of the max-pooled level at the
    points' cells (a point's cell shifts by whole cells with the origin, because origins are cell
    centres: ``index = origin cell + floor(0.5 + p / res)``). Every leaf scoring at least
    ``max(min_score, candidate_ratio x best)`` is kept; non-maximum suppression then keeps up to
    ``max_hypotheses`` separated by ``separation_m`` or ``separation_rad``. With ``region``
    (x [m], y [m], radius [m]: a GPS fix and its uncertainty) only scan origins in that disk are
    searched: top blocks that cannot reach it are never opened."""
    res, top = gf.resolution, len(gf.levels) - 1
    pts = points[np.hypot(points[:, 0], points[:, 1]) <= gf.reach_m]
    if len(pts) < MIN_SCAN_POINTS:
        return [], 0
    hp, wp = gf.levels[0].shape
    n_ang = max(int(round(2 * math.pi / angle_step_rad)), 1)
    yaws = 2 * math.pi * np.arange(n_ang) / n_ang
    # 3a. Each angle's flat cell offsets of the points from the origin cell.
    c_, s_ = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    qx = c_ * pts[:, 0] - s_ * pts[:, 1]
    qy = s_ * pts[:, 0] + c_ * pts[:, 1]
    offsets = np.floor(0.5 + qy / res).astype(np.int32) * np.int32(wp) + np.floor(
        0.5 + qx / res
    ).astype(np.int32)
    flats = [lv.ravel() for lv in gf.levels]
    # 3b. Top-level blocks that hold a free cell, at every angle.
    mh, mw = gf.map_cells
    step = 2**top
    grid_r, grid_c = np.meshgrid(
        np.arange(gf.pad, gf.pad + mh, step), np.arange(gf.pad, gf.pad + mw, step), indexing="ij"
    )
    br, bc = grid_r.ravel(), grid_c.ravel()
    keep = gf.free[top][br, bc]
    if region is not None:  # the block's centre within radius + half its diagonal
        half = 0.5 * step * res
        bx = gf.origin[0] + bc * res + half
        by = gf.origin[1] + br * res + half
        keep &= np.hypot(bx - region[0], by - region[1]) <= region[2] + math.sqrt(2) * half
    br, bc = br[keep], bc[keep]
    a = np.repeat(np.arange(n_ang), len(br))
    r, c = np.tile(br, n_ang), np.tile(bc, n_ang)
    bound = _global_scores(flats[top], offsets, a, r, c, wp)
    evaluated = len(a)
    # 3c. Beam descent from the best top blocks: a first leaf score to prune with (the higher,
    #     the fewer blocks the exact search opens).
    best = min_score
    ba, br, bc, bb = a, r, c, bound
    for lvl in range(top, 0, -1):
        sel = np.argsort(bb)[::-1][:GLOBAL_BEAM_WIDTH]
        ba, br, bc = _children(gf, lvl, ba[sel], br[sel], bc[sel])
        bb = _global_scores(flats[lvl - 1], offsets, ba, br, bc, wp)
        evaluated += len(ba)
    if len(bb):
        best = max(best, float(bb.max()))
    # 3d. Branch and bound, from a high threshold down to the floor. Greedy non-maximum
    #     suppression takes leaves best first, so when the leaves at or above a threshold already
    #     give max_hypotheses picks, the leaves below it cannot change them: the lower
    #     thresholds (and the blocks only they would open) are never needed. Blocks pruned at a
    #     threshold wait at their level, so lowering it resumes rather than restarts.
    pending: list[tuple[np.ndarray, ...]] = [
        (np.zeros(0, np.int64),) * 3 + (np.zeros(0),) for _ in range(top)
    ]
    pending.append((a, r, c, bound))
    cands: list[GlobalCandidate] = []
    for ratio in _threshold_ratios(candidate_ratio):
        floor = max(min_score, candidate_ratio * best)
        threshold = max(floor, ratio * best)
        for lvl in range(top, 0, -1):
            a, r, c, bound = pending[lvl]
            go = bound >= threshold
            wait = ~go & (bound >= floor)
            pending[lvl] = (a[wait], r[wait], c[wait], bound[wait])
            a, r, c = _children(gf, lvl, a[go], r[go], c[go])
            bound = _global_scores(flats[lvl - 1], offsets, a, r, c, wp)
            evaluated += len(a)
            pa, pr, pc, pb = pending[lvl - 1]
            pending[lvl - 1] = (
                np.concatenate([pa, a]),
                np.concatenate([pr, r]),
                np.concatenate([pc, c]),
                np.concatenate([pb, bound]),
            )
        a, r, c, score = pending[0]
        if len(score):
            best = max(best, float(score.max()))  # an exact leaf beats the greedy one
            threshold = max(threshold, max(min_score, candidate_ratio * best))
        keep = score >= threshold
        if region is not None:
            lx, ly = gf.origin[0] + (c + 0.5) * res, gf.origin[1] + (r + 0.5) * res
            keep &= np.hypot(lx - region[0], ly - region[1]) <= region[2]
        cands = _suppress(
            gf,
            yaws,
            a[keep],
            r[keep],
            c[keep],
            score[keep],
            max_hypotheses,
            separation_m,
            separation_rad,
        )
        if len(cands) >= max_hypotheses:
            break
    return cands, evaluated


def _children(
    gf: GlobalField, lvl: int, a: np.ndarray, r: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The level ``lvl - 1`` sub-blocks (same angle) of level-``lvl`` blocks that hold a free
    cell."""
    h = 2 ** (lvl - 1)
    a = np.repeat(a, 4)
    r = np.repeat(r, 4) + np.tile([0, 0, h, h], len(r))
    c = np.repeat(c, 4) + np.tile([0, h, 0, h], len(c))
    inside = gf.free[lvl - 1][r, c]
    return a[inside], r[inside], c[inside]


def _threshold_ratios(candidate_ratio: float) -> list[float]:
    """Thresholds of the global search as fractions of the best score, high to low."""
    return [q for q in GLOBAL_THRESHOLD_RATIOS if q > candidate_ratio] + [candidate_ratio]


def _suppress(
    gf: GlobalField,
    yaws: np.ndarray,
    a: np.ndarray,
    r: np.ndarray,
    c: np.ndarray,
    score: np.ndarray,
    max_hypotheses: int,
    separation_m: float,
    separation_rad: float,
) -> list[GlobalCandidate]:
    """Greedy non-maximum suppression of lattice leaves into distinct hypotheses, best first."""
    res = gf.resolution
    x = gf.origin[0] + (c + 0.5) * res
    y = gf.origin[1] + (r + 0.5) * res
    yaw = wrap_angle(yaws[a])
    out: list[GlobalCandidate] = []
    alive = np.ones(len(score), bool)
    while alive.any() and len(out) < max_hypotheses:
        i = int(np.flatnonzero(alive)[np.argmax(score[alive])])
        out.append(GlobalCandidate(np.array([x[i], y[i], float(yaw[i])]), float(score[i])))
        near = (np.hypot(x - x[i], y - y[i]) <= separation_m) & (
            np.abs(wrap_angle(yaw - yaw[i])) <= separation_rad
        )
        alive &= ~near
    return out


# 4. Matching one scan against the map ----------------------------------------------------------


@dataclass(frozen=True)
class MatchOutcome:
    ok: bool
    reason: str  # "" when ok
    pose: np.ndarray  # (3,) matched pose (the prior when not ok)
    covariance: np.ndarray  # (3, 3)
    score: float  # confidence at ``pose``
    method: str  # "icp", "correlative" or "none"
    refined: str = "off"  # sub-cell polish: "polished", "fallback: <why>" or "off"


def match_scan(
    model: MapModel,
    points: np.ndarray,
    prior: np.ndarray,
    config: LocalizerConfig,
    linear_window: float | None = None,
    angular_window: float | None = None,
) -> MatchOutcome:
    """ICP from ``prior``; when it does not hold, a correlative search around ``prior`` then ICP.
    A match is ok when its confidence reaches ``min_score``."""
    cfg = config
    lin = cfg.linear_search_window if linear_window is None else linear_window
    ang = cfg.angular_search_window if angular_window is None else angular_window
    if len(points) < MIN_SCAN_POINTS:
        return MatchOutcome(
            False,
            f"too few scan points ({len(points)})",
            prior,
            np.eye(3) * UNKNOWN_VARIANCE,
            0.0,
            "none",
        )

    def icp(start: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool]:
        res = icp_refine(
            model.reference,
            points,
            start,
            cfg.icp_max_correspondence_distance,
            max_iterations=cfg.icp_max_iterations,
            min_sigma_m=cfg.scan_match_min_sigma,
        )
        if not (np.all(np.isfinite(res.pose)) and math.isfinite(res.rmse)):
            return start, np.eye(3) * UNKNOWN_VARIANCE, model.score(points, start), False
        return res.pose, res.covariance, model.score(points, res.pose), res.converged

    tol = model.field.resolution  # one lattice cell of slack for ICP's sub-cell refinement

    def within(p: np.ndarray) -> bool:
        d = ominus(prior, p)
        return math.hypot(d[0], d[1]) <= lin + tol and abs(d[2]) <= ang + tol

    def polish(pose: np.ndarray, score: float, cov: np.ndarray) -> tuple[np.ndarray, float, str]:
        """4c. The sub-cell polish of a match; ICP's pose when it leaves ICP's cell. Along
        ICP's weak axes (a corridor; a lateral shift traded for a turn) the polish would only
        slide to a ripple of the blurred wall cells: its move there is dropped."""
        if cfg.refine_max_iterations == 0:
            return pose, score, "off"
        # Only the points on the map's walls: one in a gap of a mapped wall would be pulled
        # along the wall onto the gap's end (test_scan_frame's room: 0.6 deg, 2 cm).
        on_wall = near_surface(
            model.reference, transform_points(pose, points), model.field.resolution
        )
        res = refine_on_field(
            model.smooth,
            points[on_wall],
            pose,
            cfg.refine_max_iterations,
            max_shift_m=model.field.resolution,
            max_turn_rad=cfg.angular_search_step,
            covariance=cov,
            degeneracy_ratio=cfg.scan_match_degeneracy_ratio,
        )
        if not res.ok:
            return pose, score, f"fallback: {res.reason}"
        return res.pose, model.score(points, res.pose), "polished"

    # 4a. ICP straight from the prior: most scans follow odometry closely.
    pose, cov, score, converged = icp(prior)
    step = ominus(prior, pose)
    inside = math.hypot(step[0], step[1]) <= lin / 2 and abs(step[2]) <= ang / 2
    if converged and inside and score >= cfg.min_score:
        pose, score, refined = polish(pose, score, cov)
        return MatchOutcome(True, "", pose, cov, score, "icp", refined)
    # 4b. Exact correlative search in the window, then ICP from its best lattice pose. Only
    #     poses inside the window compete: ICP can slide far off (a mirror-image room) and the
    #     filter would follow a confident jump.
    coarse = correlative_match(
        model.field, points, prior, lin, ang, min(cfg.angular_search_step, ang)
    )
    start = coarse.pose if coarse.score > 0.0 else prior
    pose2, cov2, score2, converged2 = icp(start)
    candidates = [(score, pose, cov)] if converged and within(pose) else []
    if converged2 and within(pose2):
        candidates.append((score2, pose2, cov2))
    elif coarse.score > 0.0:
        candidates.append((coarse.score, coarse.pose, cov2))  # ICP slid off: the lattice pose
    if not candidates:
        return MatchOutcome(
            False, "no match inside the search window", prior, cov, 0.0, "correlative"
        )
    score, pose, cov = max(candidates, key=lambda c: c[0])
    pose, score, refined = polish(pose, score, cov)
    if score < cfg.min_score:
        return MatchOutcome(
            False,
            f"match score {score:.2f} below min_score {cfg.min_score}",
            pose,
            cov,
            score,
            "correlative",
            refined,
        )
    return MatchOutcome(True, "", pose, cov, score, "correlative", refined)


def _floored(cov: np.ndarray) -> np.ndarray:
    return cov + np.diag(
        [MIN_MATCH_SIGMA[0] ** 2, MIN_MATCH_SIGMA[0] ** 2, MIN_MATCH_SIGMA[1] ** 2]
    )


# 5. The localiser ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LocalizationResult:
    stamp_ns: int  # [ns] of the scan
    pose: np.ndarray  # (3,) [m, m, rad] scan frame in map (odometry-propagated when not tracking)
    covariance: np.ndarray  # (3, 3) over (x, y, yaw); UNKNOWN_VARIANCE diagonal when unknown
    confidence: float  # [0, 1] mean scan likelihood at ``pose``; 0 while relocalising
    status: Status
    reason: str  # why (match method, rejection, ambiguity, ...)
    map_to_odom: np.ndarray  # (3,) T_map_odom = pose (+) odom^-1


@dataclass
class _Hypothesis:
    pose: np.ndarray  # (3,) map pose at the last scan
    covariance: np.ndarray
    scores: list[float] = field(default_factory=list)  # confidence at each matched scan
    unique: int = 0  # consecutive scans it led without a rival within the ambiguity ratio
    agreed: bool = True  # its last match agreed with its odometry prediction
    window: int = 1  # scores averaged for ranking: the last relocalization_verification_scans
    tracked: bool = False  # the pose tracked before a kidnap check: it has the prior on its side
    since_ns: int = 0  # [ns] stamp of the kidnap check (``tracked`` only)
    evidence: float | None = None  # confidence of the recent scans stacked by odometry
    counted_at: np.ndarray | None = None  # odometry pose of the last scan ``unique`` counted

    @property
    def mean_score(self) -> float:
        """Mean confidence over the last ``window`` scans: a rival that keeps fitting worse
        drops out of the ambiguity ratio however well it fitted at first."""
        return float(np.mean(self.scores[-self.window :])) if self.scores else 0.0

    @property
    def rank_score(self) -> float:
        """What hypotheses are ranked by: the mean score, capped by the stacked evidence."""
        return self.mean_score if self.evidence is None else min(self.mean_score, self.evidence)

    def rivals(self, best: _Hypothesis, ratio: float) -> bool:
        """Scores within ``ratio`` of ``best``, on the last scans and on the stacked ones: a
        place that fits each narrow scan on its own, but not the scans together where
        odometry puts them, is no rival."""
        if self.mean_score < ratio * best.mean_score:
            return False
        return (
            self.evidence is None
            or best.evidence is None
            or (self.evidence >= ratio * best.evidence)
        )


@dataclass
class LocalizerStats:
    scans: int = 0
    global_searches: int = 0
    relocalisations: int = 0
    lost: int = 0
    kidnap_checks: int = 0  # global searches run on a sudden confidence drop while tracking
    gated: int = 0  # tracking matches beyond match_gate of the prediction (not fused)
    jumps: int = 0  # jump hypotheses confirmed: the estimate jumped to them
    matches: dict[str, int] = field(default_factory=dict)
    refined: int = 0  # tracking matches moved by the sub-cell polish
    refine_fallbacks: int = 0  # ... where the polish left the match's cell: ICP's pose kept


class Localizer:
    """Thin stateful shell: the pose estimate, the lost timer and the relocalisation hypotheses.

    Without ``initial_pose`` the first scans relocalise globally. With it, tracking starts there;
    when the first scan does not match there (or the pose is not in free space) the status is
    ``"lost"`` with the reason and the following scans relocalise globally."""

    def __init__(
        self, model: MapModel, config: LocalizerConfig, initial_pose: np.ndarray | None = None
    ) -> None:
        self.model = model
        self.config = config
        self.stats = LocalizerStats()
        self._pose: np.ndarray | None = None  # map pose estimate at the last scan
        self._cov = np.eye(3) * UNKNOWN_VARIANCE
        self._odom: np.ndarray | None = None  # odometry pose at the last scan
        self._last_stamp: int | None = None
        self._low_since: int | None = None  # [ns] first scan of the current low-confidence run
        self._low_scans = 0  # scans in the current low-confidence run
        self._status: Status = "relocalising"
        self._hypotheses: list[_Hypothesis] = []
        self._contested = False  # the hypotheses were ambiguous at some scan since the search
        self._since_search = 0  # ambiguous scans since the last global search
        self._history: list[tuple[np.ndarray, np.ndarray]] = []  # (odom, points) relocalising
        self._initial_check = False  # the next scan checks the given initial pose
        self._match_pose: np.ndarray | None = None  # pose of the last match (update_min_d/a)
        self._recent: deque[float] = deque(maxlen=config.kidnap_check_scans)  # confidences
        self._drop_checked = False  # the current confidence drop was searched already
        self._jump: _Hypothesis | None = None  # gated matches waiting for confirmation
        self._gated_streak = 0  # consecutive gated matches (a fused match ends the run)
        self._gps: tuple[np.ndarray, float, np.ndarray] | None = None  # (xy, sigma, odom then)
        if initial_pose is not None:
            self.set_initial_pose(initial_pose)

    @property
    def status(self) -> Status:
        return self._status

    @property
    def gated_streak(self) -> int:
        """Consecutive tracking matches beyond ``match_gate`` (not fused) up to the last scan:
        the estimate and the scans disagree, and the prediction alone carries the pose."""
        return self._gated_streak

    def set_initial_pose(self, pose: np.ndarray, covariance: np.ndarray | None = None) -> None:
        """Start tracking from ``pose`` (like RViz's /initialpose); checked on the next scan."""
        self._pose = np.asarray(pose, dtype=np.float64).copy()
        self._cov = (
            np.diag(
                [self.config.linear_search_window**2] * 2 + [self.config.angular_search_window**2]
            )
            if covariance is None
            else np.asarray(covariance, float)
        )
        self._status = "tracking"
        self._initial_check = True
        self._jump = None
        self._gated_streak = 0
        self._hypotheses = []
        self._low_since = None
        self._low_scans = 0
        self._match_pose = None
        self._recent.clear()
        self._drop_checked = False
        self._contested = False
        self._since_search = 0
        self._history = []

    def set_gps_fix(self, xy_map: np.ndarray, sigma_m: float, odom_pose: np.ndarray) -> None:
        """A GPS fix in the map frame (through the map's geo anchor) with its horizontal sigma,
        and the receiver's odometry pose when it was taken: the next global searches only look
        within ``gps_prior_sigmas`` sigmas of it, widened by the odometry distance from the
        receiver then to the scan frame now (one rigid robot in one odom frame, so the scan's
        origin is at most that far from where the receiver was; :class:`GpsPrior`)."""
        self._gps = (
            np.asarray(xy_map, float).copy(),
            float(sigma_m),
            np.asarray(odom_pose, float).copy(),
        )

    @property
    def gps_region(self) -> tuple[float, float, float] | None:
        """(x, y, radius) [m] in the map: the disk of scan-frame origins the global search
        covers after the last scan (None without a fix)."""
        if self._gps is None or self._odom is None:
            return None
        xy, sigma, odom_then = self._gps
        driven = float(np.hypot(*(self._odom[:2] - odom_then[:2])))
        return (float(xy[0]), float(xy[1]), self.config.gps_prior_sigmas * sigma + driven)

    def _points(self, scan: LaserScan) -> np.ndarray:
        pts = scan_points(scan, self.config.laser_max_range)
        return voxel_filter(pts, self.config.scan_voxel_size)

    def _result(
        self,
        stamp: int,
        odom: np.ndarray,
        reason: str,
        confidence: float,
        status: Status | None = None,
    ) -> LocalizationResult:
        pose = self._pose if self._pose is not None else np.zeros(3)
        return LocalizationResult(
            stamp_ns=stamp,
            pose=pose.copy(),
            covariance=self._cov.copy(),
            confidence=float(confidence),
            status=status or self._status,
            reason=reason,
            map_to_odom=oplus(pose, inverse(odom)),
        )

    def update(self, scan: LaserScan, odom_pose: np.ndarray) -> LocalizationResult:
        """One scan with the odometry pose of its frame (see the module docstring)."""
        odom = np.asarray(odom_pose, dtype=np.float64)
        if odom.shape != (3,) or not np.all(np.isfinite(odom)):
            return self._result(scan.stamp_ns, np.zeros(3), "rejected: non-finite odometry", 0.0)
        if self._last_stamp is not None and scan.stamp_ns <= self._last_stamp:
            return self._result(scan.stamp_ns, odom, "rejected: time not increasing", 0.0)
        self.stats.scans += 1
        self._last_stamp = scan.stamp_ns
        u = ominus(self._odom, odom) if self._odom is not None else np.zeros(3)
        self._odom = odom
        pts = self._points(scan)
        # 1. Predict every pose we hold with the odometry increment.
        if self._pose is not None:
            self._pose, self._cov = predict(self._pose, self._cov, u, motion_noise(u, self.config))
        for h in [*self._hypotheses, *([self._jump] if self._jump is not None else [])]:
            h.pose, h.covariance = predict(h.pose, h.covariance, u, motion_noise(u, self.config))
        if self._status == "lost":
            self._status = "relocalising"  # with the hypotheses a kidnap check left, if any
        if self._status == "relocalising":
            return self._relocalise(scan.stamp_ns, odom, pts)
        return self._track(scan.stamp_ns, odom, pts)

    # 5a. Tracking ------------------------------------------------------------------------------

    def _track(self, stamp: int, odom: np.ndarray, pts: np.ndarray) -> LocalizationResult:
        cfg = self.config
        assert self._pose is not None
        checking, self._initial_check = self._initial_check, False
        if checking:
            where = self.model.cell_class(self._pose[:2])
            # Unknown is allowed: a depth camera never sees the floor under its own start.
            if where in ("occupied", "outside"):
                return self._declare_lost(
                    stamp,
                    odom,
                    f"initial pose rejected: it lies in {where} space; relocalising globally",
                )
        # 2. Skip matching until the robot has moved (AMCL update_min_d / update_min_a).
        still = self._match_pose is not None and not moved_enough(
            self._match_pose, self._pose, cfg.update_min_d, cfg.update_min_a
        )
        if still:
            conf = self.model.score(pts, self._pose)
            return self._result(stamp, odom, "not moved enough to match", conf)
        if len(pts) < MIN_SCAN_POINTS:
            # A scan with nothing in range (a depth camera facing open space) is no evidence
            # either way: dead-reckon, and neither start nor stop the lost timer (nor check a
            # given initial pose: that waits for the next scan).
            self._initial_check = checking
            what = "initial pose kept unchecked" if checking else "dead reckoning"
            return self._result(stamp, odom, f"too few scan points ({len(pts)}): {what}", 0.0)
        match = match_scan(self.model, pts, self._pose, cfg)
        self.stats.matches[match.method] = self.stats.matches.get(match.method, 0) + 1
        self.stats.refined += match.refined == "polished"
        self.stats.refine_fallbacks += match.refined.startswith("fallback")
        # What a jump hypothesis must explain too, and what match_recent stacks.
        self._remember(odom, pts, stack=False)
        if not match.ok and checking:
            return self._declare_lost(
                stamp,
                odom,
                f"initial pose rejected: {match.reason}; relocalising globally",
                match.score,
            )
        gated = False
        if match.ok:
            # 3. Fuse the prediction and the match -- unless the match lies beyond the gate: a
            #    narrow scan of moved furniture fits confidently somewhere else, and one such
            #    answer must not move the estimate. It becomes a jump hypothesis, propagated by
            #    odometry (see _jump_hypothesis); meanwhile the covariance grows with odometry.
            r_cov, _ = release_degenerate_axis(
                match.covariance
                + np.diag([cfg.match_sigma_floor**2] * 2 + [cfg.match_sigma_floor_yaw**2]),
                cfg.scan_match_degeneracy_ratio,
                UNKNOWN_VARIANCE,
            )
            d2 = mahalanobis2(self._pose, self._cov, match.pose, r_cov)
            if cfg.match_gate > 0.0 and d2 > cfg.match_gate**2:
                reason = self._jump_hypothesis(match, r_cov, d2, odom)
                gated = self._jump is not None  # still waiting: no fix on this scan
            else:
                self._jump = None
                self._pose, self._cov = kalman_update(self._pose, self._cov, match.pose, r_cov)
                self._match_pose = self._pose.copy()
                reason = f"matched ({match.method})"
        else:
            reason = f"match rejected: {match.reason}; dead reckoning"
        self._gated_streak = (
            self._gated_streak + 1 if gated else (0 if match.ok else self._gated_streak)
        )
        conf = self.model.score(pts, self._pose)
        # 4. Kidnapped? A sudden drop in confidence searches the whole map on this scan; a pose
        #    elsewhere that fits clearly better means the robot is not where we track it.
        kidnapped = self._kidnap_check(stamp, pts, conf)
        if kidnapped is not None:
            hyps, why = kidnapped
            return self._declare_lost(stamp, odom, why, conf, hyps)
        # 5. Lost when the confidence stays below lost_score, or matches keep being rejected,
        #    for lost_time (a scan fitting 30-50 % of a wrong place must not keep it "tracking").
        #    A sparse log (a scan every 2-3 s) also needs lost_min_scans such scans in a row.
        if conf < cfg.lost_score or not match.ok or gated:
            self._low_since = stamp if self._low_since is None else self._low_since
            self._low_scans += 1
            if (
                stamp - self._low_since
            ) * 1e-9 >= cfg.lost_time and self._low_scans >= cfg.lost_min_scans:
                why = (
                    f"confidence {conf:.2f} below lost_score {cfg.lost_score} or matches "
                    f"rejected for {cfg.lost_time} s ({self._low_scans} scans)"
                )
                sigma = position_sigma(self._cov)
                if sigma >= cfg.dead_reckoning_max_sigma:
                    return self._declare_lost(stamp, odom, why, conf)
                # Odometry still vouches for the pose: keep predicting from it (AMCL never
                # stops); the covariance grows until dead_reckoning_max_sigma says lost.
                reason = (
                    f"{reason}; {why}: dead reckoning, position sigma {sigma:.2f} m < "
                    f"dead_reckoning_max_sigma {cfg.dead_reckoning_max_sigma}"
                )
        else:
            self._low_since = None
            self._low_scans = 0
        return self._result(stamp, odom, reason, conf)

    def _jump_hypothesis(
        self, match: MatchOutcome, r_cov: np.ndarray, d2: float, odom: np.ndarray
    ) -> str:
        """A gated match: start or extend the jump hypothesis; jump to it when it is confirmed
        by ``jump_confirm_scans`` consecutive gated matches that agree with each other (each
        within the gate of the previous one propagated by odometry) and by independent
        evidence: the scans of the recent history from before this run of gated matches,
        stacked by odometry, must fit it clearly better (``relocalization_ambiguity_ratio``)
        than the prediction. Consecutive narrow scans of one moved piece of furniture agree
        with each other, but the walls seen on the way there do not agree with them. The
        reason."""
        cfg = self.config
        self.stats.gated += 1
        jump = self._jump
        if (
            jump is not None
            and mahalanobis2(jump.pose, jump.covariance, match.pose, r_cov) <= cfg.match_gate**2
        ):
            jump.unique += 1
        else:
            jump = _Hypothesis(match.pose, r_cov, unique=1)
        jump.pose, jump.covariance = match.pose.copy(), r_cov.copy()
        jump.scores.append(match.score)
        self._jump = jump
        d = ominus(self._pose, match.pose) if self._pose is not None else np.zeros(3)
        what = (
            f"match ({match.method}) {math.hypot(d[0], d[1]):.2f} m / "
            f"{math.degrees(abs(d[2])):.0f} deg from the prediction, Mahalanobis "
            f"{math.sqrt(d2):.1f} > match_gate {cfg.match_gate}"
        )
        if cfg.jump_confirm_scans == 0:
            return f"{what}: not fused (jumps off: waiting for the covariance to admit it)"
        if jump.unique < cfg.jump_confirm_scans:
            return f"{what}: jump hypothesis {jump.unique}/{cfg.jump_confirm_scans}"
        assert self._pose is not None
        before = self._stacked(odom, max(len(self._history) - jump.unique, 0))
        if len(before) < MIN_SCAN_POINTS:
            return f"{what}: jump hypothesis held back, no earlier scans to check it against"
        s_jump, s_pred = self.model.score(before, jump.pose), self.model.score(before, self._pose)
        if s_jump * cfg.relocalization_ambiguity_ratio < s_pred:
            return (
                f"{what}: jump hypothesis held back, the earlier scans fit it {s_jump:.2f} "
                f"against {s_pred:.2f} at the prediction"
            )
        # Jump: the prediction's covariance grown by the innovation (so the jump lies within
        # one sigma of it), then fused as usual; an axis the match cannot see (released as
        # degenerate) keeps the prediction.
        nu = jump.pose - self._pose
        nu[2] = wrap_angle(nu[2])
        self._pose, self._cov = kalman_update(
            self._pose, self._cov + np.outer(nu, nu), jump.pose, jump.covariance
        )
        self._match_pose = self._pose.copy()
        self._jump = None
        self.stats.jumps += 1
        return f"{what}: jumped, {cfg.jump_confirm_scans} matches agree"

    def match_recent(self, n_scans: int) -> LocalizationResult:
        """Match the last ``n_scans`` tracked scans, stacked by odometry in the frame of the last
        scan, against the map from the estimate and fuse the match without ``match_gate``.

        For a robot standing still and turning in place (a goal "settle"): a narrow scan of a
        moved piece of furniture fits it confidently off, and the gate then holds the estimate
        where those matches left it; the scans of a full turn see the walls all around, in which
        one piece of furniture weighs little. Like a confirmed jump, the prediction's covariance
        is grown by the innovation before the update, so the wide match is adopted along every
        axis it constrains. Not tracking, too few points or a failed match leave the estimate as
        it is (the reason says why)."""
        stamp = self._last_stamp if self._last_stamp is not None else 0
        odom = self._odom if self._odom is not None else np.zeros(3)
        if self._status != "tracking" or self._pose is None:
            return self._result(stamp, odom, f"no wide match while {self._status}", 0.0)
        self._gated_streak = 0  # the disagreement has been looked at
        n = min(max(n_scans, 0), len(self._history))
        if n == 0:
            return self._result(stamp, odom, "no tracked scans to match", 0.0)
        recent = self._history[len(self._history) - n :]
        cloud = voxel_filter(
            np.concatenate([transform_points(ominus(odom, o), p) for o, p in recent]),
            self.config.scan_voxel_size,
        )
        match = match_scan(self.model, cloud, self._pose, self.config)
        if not match.ok:
            conf = self.model.score(cloud, self._pose)
            return self._result(
                stamp, odom, f"wide match of {n} scans rejected: {match.reason}", conf
            )
        cfg = self.config
        r_cov, _ = release_degenerate_axis(
            match.covariance
            + np.diag([cfg.match_sigma_floor**2] * 2 + [cfg.match_sigma_floor_yaw**2]),
            cfg.scan_match_degeneracy_ratio,
            UNKNOWN_VARIANCE,
        )
        nu = match.pose - self._pose
        nu[2] = wrap_angle(nu[2])
        self._pose, self._cov = kalman_update(
            self._pose, self._cov + np.outer(nu, nu), match.pose, r_cov
        )
        self._match_pose = self._pose.copy()
        self._jump = None
        d = math.hypot(nu[0], nu[1])
        return self._result(
            stamp,
            odom,
            f"wide match of {n} scans ({match.method}): moved "
            f"{d:.2f} m / {math.degrees(abs(nu[2])):.1f} deg",
            self.model.score(cloud, self._pose),
        )

    def _kidnap_check(
        self, stamp: int, pts: np.ndarray, conf: float
    ) -> tuple[list[_Hypothesis], str] | None:
        """The relocalisation hypotheses and a reason when this scan's confidence fell below
        ``kidnap_check_ratio`` x the median of the last ``kidnap_check_scans`` tracked scans and
        the global search finds a pose that scores ``global_localization_min_score``, more than
        the tracked one by the ambiguity ratio and at least that ratio of the median; None
        otherwise (also when the drop was searched already: one search per drop, not per
        scan)."""
        cfg = self.config
        assert self._pose is not None
        ref = float(np.median(self._recent)) if len(self._recent) else 0.0
        if conf >= cfg.kidnap_check_ratio * ref:
            self._recent.append(conf)
            self._drop_checked = False
            return None
        if self._drop_checked or len(self._recent) < cfg.kidnap_check_scans:
            return None
        self._drop_checked = True
        self.stats.kidnap_checks += 1
        hyps, _ = self._search(pts, self._pose)  # only places fitting at least as well
        # Clearly better: beyond the ambiguity ratio of the tracked pose, and within it of the
        # confidence tracking had (a drop in a poorly mapped stretch can leave a far corridor
        # fitting better than the right pose, though not as well as the map fitted before).
        floor = max(
            cfg.global_localization_min_score,
            conf / cfg.relocalization_ambiguity_ratio,
            cfg.relocalization_ambiguity_ratio * ref,
        )
        better = [h for h in hyps if h.mean_score > floor and not _agree(h.pose, self._pose, cfg)]
        if not better:
            return None
        d = ominus(self._pose, better[0].pose)
        # The tracked pose stays a hypothesis: if the drop was an occlusion it can win again.
        tracked = _Hypothesis(
            self._pose.copy(),
            self._cov.copy(),
            [conf],
            window=cfg.relocalization_verification_scans,
            tracked=True,
            since_ns=stamp,
        )
        return _merge([*hyps, tracked], cfg), (
            f"kidnapped? confidence fell to {conf:.2f} from a median {ref:.2f}; a pose "
            f"{math.hypot(d[0], d[1]):.2f} m / {math.degrees(abs(d[2])):.0f} deg away scores "
            f"{better[0].mean_score:.2f}; relocalising"
        )

    def _declare_lost(
        self,
        stamp: int,
        odom: np.ndarray,
        reason: str,
        conf: float = 0.0,
        hypotheses: list[_Hypothesis] | None = None,
    ) -> LocalizationResult:
        self.stats.lost += 1
        self._status = "lost"
        self._hypotheses = hypotheses or []
        self._jump = None
        self._gated_streak = 0
        self._contested = False
        self._since_search = 0
        self._history = []
        self._low_since = None
        self._low_scans = 0
        self._match_pose = None
        self._recent.clear()
        self._drop_checked = False
        self._cov = np.eye(3) * UNKNOWN_VARIANCE
        log.info("lost: %s", reason)
        return self._result(stamp, odom, reason, conf)

    # 5b. Global relocalisation -----------------------------------------------------------------

    def _search(
        self, pts: np.ndarray, rival_of: np.ndarray | None = None, ratio: float = 1.0
    ) -> tuple[list[_Hypothesis], str]:
        """Global search on this scan; each distinct candidate refined on the fine field. With
        ``rival_of`` (a leader's or the tracked pose) only places whose coarse score reaches
        ``ratio`` x that pose's are wanted, which prunes the search from its first level."""
        cfg = self.config
        self.stats.global_searches += 1
        gf = self.model.global_field
        gpts = voxel_filter(pts, gf.resolution)
        if len(gpts) > cfg.max_beams:
            gpts = gpts[np.linspace(0, len(gpts) - 1, cfg.max_beams).round().astype(int)]
        min_score = cfg.global_search_min_score
        if rival_of is not None:
            lead = coarse_score(gf, gpts, rival_of)
            min_score = max(min_score, ratio * lead)
        cands, _ = global_search(
            gf,
            gpts,
            cfg.global_search_angular_resolution,
            min_score,
            cfg.global_search_candidate_ratio,
            cfg.global_search_max_hypotheses,
            cfg.relocalization_agreement_distance,
            cfg.relocalization_agreement_angle,
            self.gps_region,
        )
        if not cands:
            return [], (
                f"no global candidate reaches global_search_min_score {cfg.global_search_min_score}"
            )
        hyps: list[_Hypothesis] = []
        best_score = 0.0
        for cand in cands:
            m = match_scan(
                self.model,
                pts,
                cand.pose,
                cfg,
                linear_window=1.5 * self.model.global_field.resolution,
                angular_window=cfg.global_search_angular_resolution,
            )
            best_score = max(best_score, m.score)
            if m.score < cfg.global_localization_min_score:
                continue
            hyps.append(
                _Hypothesis(
                    m.pose,
                    _floored(m.covariance),
                    [m.score],
                    window=cfg.relocalization_verification_scans,
                )
            )
        hyps = _merge(hyps, cfg)
        if not hyps:
            return [], (
                f"best global candidate scores {best_score:.2f} < "
                f"global_localization_min_score {cfg.global_localization_min_score}"
            )
        return hyps, f"{len(hyps)} hypotheses"

    def _relocalise(self, stamp: int, odom: np.ndarray, pts: np.ndarray) -> LocalizationResult:
        cfg = self.config
        reason = ""
        if self._hypotheses:
            # 1. Verify: re-match each propagated hypothesis; it must still fit the map
            #    (min_score); a match that disagrees with the odometry prediction is not counted.
            alive: list[_Hypothesis] = []
            for h in self._hypotheses:
                m = match_scan(self.model, pts, h.pose, cfg)
                if m.ok:
                    # A jump (e.g. along a corridor) does not kill the hypothesis; it only
                    # restarts its streak, so it stays a rival.
                    h.agreed = _agree(h.pose, m.pose, cfg)
                    h.pose, h.covariance = m.pose, _floored(m.covariance)
                    h.scores.append(m.score)
                    alive.append(h)
                elif h.tracked and (stamp - h.since_ns) * 1e-9 < cfg.lost_time:
                    # Like tracking, the pose tracked before the kidnap check dead-reckons
                    # through rejected matches for lost_time.
                    h.scores.append(self.model.score(pts, h.pose))
                    h.agreed = True
                    alive.append(h)
            self._hypotheses = _merge(alive, cfg)
            if not alive:
                reason = "no hypothesis fits this scan any more; searching again"
        if not self._hypotheses:
            # 2. Search the whole map on this scan.
            self._hypotheses, why = self._search(pts)
            self._contested = False
            self._since_search = 0
            reason = f"{reason}; {why}" if reason else why
        hyps = self._hypotheses
        if not hyps:
            self._remember(odom, pts)
            return self._result(stamp, odom, f"relocalising: {reason}", 0.0)
        # 2b. Score every hypothesis on the recent scans stacked by odometry (a wider view).
        cloud = self._remember(odom, pts)
        for h in hyps:
            h.evidence = None if cloud is None else self.model.score(cloud, h.pose)
        hyps.sort(key=lambda h: h.rank_score, reverse=True)
        # 3. The leader counts a scan only while no other hypothesis scores within the ambiguity
        #    ratio of it: rivals that die leave a leader that must still earn its streak.
        n_needed = cfg.relocalization_verification_scans
        best = hyps[0]
        rivals = [h for h in hyps[1:] if h.rivals(best, cfg.relocalization_ambiguity_ratio)]
        if not best.agreed or rivals:
            best.unique = 0
        elif (
            best.unique == 0
            or best.counted_at is None
            or moved_enough(
                best.counted_at,
                odom,
                cfg.relocalization_update_min_d,
                cfg.relocalization_update_min_a,
            )
        ):
            best.unique += 1
            best.counted_at = odom.copy()
        for h in hyps[1:]:
            h.unique = 0
        # 3b. After a kidnap check the pose tracked before it wins every tie: it was verified on
        #     many scans, and a kidnapping is rare. It still had to fit this scan (min_score)
        #     and agree with its odometry; only a place that fits clearly better replaces it.
        held = next((h for h in hyps if h.tracked), None)
        if (
            held is not None
            and held.agreed
            and held.mean_score >= cfg.global_localization_min_score
            and held.rivals(best, cfg.relocalization_ambiguity_ratio)
        ):
            return self._accept(
                stamp,
                odom,
                pts,
                held,
                f"relocalised: the pose tracked before "
                f"the kidnap check holds (mean score {held.mean_score:.2f}, "
                f"best elsewhere {best.mean_score:.2f})",
            )
        if rivals:
            self._contested = True
            self._since_search += 1
            if self._since_search >= n_needed:
                # Rivals that keep fitting may all be wrong (the true place ranked below
                # max_hypotheses on the searched scan): search the current scan again and let
                # its places compete too.
                self._add_searched(pts, hyps)
            return self._result(
                stamp,
                odom,
                f"relocalising: ambiguous, {len(rivals) + 1} "
                f"hypotheses score within {cfg.relocalization_ambiguity_ratio} "
                f"of the best ({best.mean_score:.2f})",
                0.0,
            )
        weak = best.evidence is not None and best.evidence < cfg.global_localization_min_score
        if best.unique < n_needed or best.mean_score < cfg.global_localization_min_score or weak:
            return self._result(
                stamp,
                odom,
                f"relocalising: {len(hyps)} hypotheses, best "
                f"unique on {best.unique}/{n_needed} scans (one counts per "
                f"{cfg.relocalization_update_min_d} m or "
                f"{cfg.relocalization_update_min_a} rad of motion), mean score "
                f"{best.mean_score:.2f}",
                0.0,
            )
        # 4. A leader left alone because its rivals died was only compared with the places the
        #    first search found: search this scan again before trusting it (with a narrow
        #    depth camera the true place can rank below max_hypotheses on the first scan).
        if self._contested:
            self._contested = False
            fresh, _ = self._search(pts, best.pose, cfg.relocalization_ambiguity_ratio)
            last = best.scores[-1]
            new = [h for h in fresh if not any(_covers(o.pose, h.pose, cfg) for o in hyps)]
            strong = [h for h in new if h.mean_score >= cfg.relocalization_ambiguity_ratio * last]
            if strong:
                # Not accepted on this scan; the next one decides (the streak stands).
                self._hypotheses = _merge([*hyps, *new], cfg)
                return self._result(
                    stamp,
                    odom,
                    f"relocalising: a new search finds "
                    f"{len(strong)} other place(s) fitting this scan within "
                    f"{cfg.relocalization_ambiguity_ratio} of the leader "
                    f"({last:.2f})",
                    0.0,
                )
        # 5. Accept the one verified hypothesis and track from it.
        return self._accept(
            stamp,
            odom,
            pts,
            best,
            f"relocalised: unique on {best.unique} scans, mean score {best.mean_score:.2f}",
        )

    def _remember(self, odom: np.ndarray, pts: np.ndarray, stack: bool = True) -> np.ndarray | None:
        """Add this scan to the history and (``stack``) return the history's points in this
        scan's frame (odometry-stacked, voxel-filtered); None for a single scan. The history
        keeps the scans within ``relocalization_history_m`` of this one (straight-line odometry
        distance), at most ``MAX_HISTORY_SCANS``."""
        cfg = self.config
        self._history.append((odom.copy(), pts))
        while len(self._history) > MAX_HISTORY_SCANS or (
            len(self._history) > 1
            and math.hypot(*(self._history[0][0][:2] - odom[:2])) > cfg.relocalization_history_m
        ):
            self._history.pop(0)
        if not stack or len(self._history) < 2 or cfg.relocalization_history_m <= 0.0:
            return None
        return self._stacked(odom, len(self._history))

    def _stacked(self, odom: np.ndarray, n: int) -> np.ndarray:
        """The first ``n`` scans of the history in the frame of odometry pose ``odom``,
        voxel-filtered ((0, 2) when there are none)."""
        clouds = [transform_points(ominus(odom, o), p) for o, p in self._history[:n]]
        if not clouds:
            return np.zeros((0, 2))
        return voxel_filter(np.concatenate(clouds), self.config.scan_voxel_size)

    def _add_searched(self, pts: np.ndarray, hyps: list[_Hypothesis]) -> None:
        """Search this scan and add the places no hypothesis holds yet; keep the best
        ``2 x global_search_max_hypotheses`` (and the tracked pose, if held)."""
        cfg = self.config
        self._since_search = 0
        fresh, _ = self._search(pts, hyps[0].pose, cfg.relocalization_ambiguity_ratio)
        new = [h for h in fresh if not any(_covers(o.pose, h.pose, cfg) for o in hyps)]
        merged = _merge([*hyps, *new], cfg)
        cap = 2 * cfg.global_search_max_hypotheses
        self._hypotheses = merged[:cap] + [h for h in merged[cap:] if h.tracked]

    def _accept(
        self, stamp: int, odom: np.ndarray, pts: np.ndarray, h: _Hypothesis, reason: str
    ) -> LocalizationResult:
        self._pose, self._cov = h.pose.copy(), h.covariance.copy()
        self._status = "tracking"
        self._hypotheses = []
        self._history = []
        self._jump = None
        self._gated_streak = 0
        self._match_pose = self._pose.copy()
        self._low_since = None
        self._low_scans = 0
        self.stats.relocalisations += 1
        return self._result(stamp, odom, reason, self.model.score(pts, self._pose))


GPS_ODOM_HISTORY = 256  # scans of odometry kept to place a late fix (minutes at live rates)


class GpsPrior:
    """GPS fixes (in the map frame, through its geo anchor) handed to a :class:`Localizer` as
    the prior of its global search, the one way `localize --gps` and `live` do it: before each
    scan, the newest fix stamped at or before the scan goes in with the odometry pose of the
    last scan at or before the fix (the localiser widens the fix's disk by the distance driven
    since). Fixes are added in time order, all at once (a log) or as they come (live).

    The receiver sits at ``gps_in_base`` (x, y) in base_link (navsat_transform_node's
    ``base_link -> gps`` transform; the robot's ``gps_x`` / ``gps_y``, 0: on base_link); the
    localiser's odometry is its scan frame's, ``scan_in_base``
    (:func:`slam.depth_to_scan.scan_frame_in_base`) from base_link, so the fix goes in with
    the receiver's odometry pose: base_link's (:func:`slam.depth_to_scan.base_pose`) moved by
    the mount (:func:`sensors.gps.antenna_xy`)."""

    def __init__(
        self,
        localizer: Localizer,
        scan_in_base: np.ndarray | None = None,
        gps_in_base: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        self.localizer = localizer
        self.scan_in_base = np.zeros(3) if scan_in_base is None else np.asarray(scan_in_base)
        self.gps_in_base = gps_in_base
        self._pending: deque[tuple[int, np.ndarray, float]] = deque()  # (stamp, xy, sigma)
        self._odom: deque[tuple[int, np.ndarray]] = deque(maxlen=GPS_ODOM_HISTORY)
        self.fixes_used = 0

    def add_fix(self, stamp_ns: int, xy_map: np.ndarray, sigma_m: float) -> None:
        self._pending.append((int(stamp_ns), np.asarray(xy_map, float), float(sigma_m)))

    def before_scan(self, stamp_ns: int, odom: np.ndarray) -> None:
        """Call with each scan's stamp and odometry pose (the scan frame's, as given to
        :meth:`Localizer.update`) before the update."""
        self._odom.append((int(stamp_ns), np.asarray(odom, float)))
        newest = None
        while self._pending and self._pending[0][0] <= stamp_ns:
            newest = self._pending.popleft()
        if newest is None:
            return
        t_fix, xy, sigma = newest
        at = self._odom[0][1]  # a fix older than the history: the oldest pose kept
        for t, pose in reversed(self._odom):
            if t <= t_fix:
                at = pose
                break
        base = base_pose(at, self.scan_in_base)
        x, y = antenna_xy(base[0], base[1], base[2], self.gps_in_base)
        self.localizer.set_gps_fix(xy, sigma, np.array([x, y, base[2]]))
        self.fixes_used += 1


def _merge(hyps: list[_Hypothesis], config: LocalizerConfig) -> list[_Hypothesis]:
    """Best first (by mean score); a hypothesis that converged onto a better one is dropped."""
    out: list[_Hypothesis] = []
    for h in sorted(hyps, key=lambda h: h.mean_score, reverse=True):
        same = next((o for o in out if _agree(o.pose, h.pose, config)), None)
        if same is None:
            out.append(h)
        else:
            same.tracked |= h.tracked
    return out


def _covers(a: np.ndarray, b: np.ndarray, config: LocalizerConfig) -> bool:
    """Pose ``b`` is within reach of hypothesis ``a``'s own matching (its correlative window,
    which it searches on every scan, and as far again): a searched place there is no new
    place (along a corridor it is the same place, slid)."""
    d = ominus(a, b)
    return (
        math.hypot(d[0], d[1]) <= 2 * config.linear_search_window
        and abs(d[2]) <= config.angular_search_window
    )


def _agree(a: np.ndarray, b: np.ndarray, config: LocalizerConfig) -> bool:
    d = ominus(a, b)
    return (
        math.hypot(d[0], d[1]) <= config.relocalization_agreement_distance
        and abs(d[2]) <= config.relocalization_agreement_angle
    )


__all__ = [
    "GlobalCandidate",
    "GlobalField",
    "GpsPrior",
    "LocalizationResult",
    "Localizer",
    "MapModel",
    "MatchOutcome",
    "build_global_field",
    "global_search",
    "kalman_update",
    "mahalanobis2",
    "match_scan",
    "motion_noise",
    "position_sigma",
    "predict",
]
