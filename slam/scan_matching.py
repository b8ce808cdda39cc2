"""2D scan matching: correlative search on a smeared likelihood grid, then point-to-line ICP.

Two stages, in the spirit of Olson's real-time correlative scan matching and Cartographer's
real-time CSM + Ceres refinement:

1. **Correlative search** (:func:`correlative_match`): the reference points are rasterised on a
   grid of ``resolution`` and smeared into a likelihood field ``F = exp(-d^2 / 2 sigma^2)`` (``d``
   from ``cv2.distanceTransform``). Every candidate pose in a window of (x, y, yaw) around a prior
   is scored by the mean of ``F`` at its transformed scan points. The search is exact over the
   window's lattice (translation steps of one cell, yaw steps of ``angle_step``) but prunes with
   branch-and-bound: a pyramid of max-pooled fields (level ``k`` holds the maximum over
   ``2^k x 2^k`` cells, ``cv2.dilate`` with the anchor at the corner) bounds the score of every
   candidate in a block, and whole levels of candidates are expanded at once (numpy), best-first.
   This finds the global optimum in a wide window, so it is the loop-closure matcher too.
2. **Point-to-line ICP** (:func:`icp_refine`): Gauss-Newton on ``r_i = n_i . (R p_i + t - q_i)``
   with nearest neighbours from a k-d tree and Huber weights. The Jacobian of one residual in
   (x, y, yaw) is ``[n_x, n_y, n . (dR/dyaw p_i)]`` with ``dR/dyaw p = (-s p_x - c p_y,
   c p_x - s p_y)``. Sub-cell accuracy comes from here; the covariance is ``sigma^2 (J^T W J)^-1``
   with ``sigma^2`` the weighted residual variance, floored so a perfect synthetic match is not
   infinitely certain.
3. **Sub-cell polish** (:func:`refine_on_field`), as Cartographer's Ceres scan matcher: Newton
   steps on a bicubic, blurred map of the wall cells, whose ridge is the centroid of a wall's
   cells where ICP snaps to cell centres (why and measurements: docs/design/localization.md).

All functions are pure: arrays in, results out. Poses are (x [m], y [m], yaw [rad]).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.linalg.lapack import dgesv as gesv
from scipy.spatial import cKDTree

from sensors.types import LaserScan
from slam.geometry import lever_jacobian, wrap_angle

NORMAL_NEIGHBOURS = 5  # points used to fit each reference point's line (incl. itself)
NORMAL_TIE_EXTRA = 3  # further neighbours looked at for a tie with the k-th
NORMAL_TIE_RTOL = 1e-9  # a neighbour this much (relative) farther than the k-th still ties
MIN_POINTS = 10  # fewer matched points than this is not a match
SCORE_CHUNK_ELEMENTS = 2**17  # candidate x scan point indices per gather (1 MiB: in cache)
PLANARITY_MAX = 0.2  # smaller/larger eigenvalue ratio above which a neighbourhood is no line
DEGENERATE_EIGENVALUE = 1e-9  # information floor relative to the strongest direction
GRID_GRADIENT_SIGMA_CELLS = 1.0  # [cells] occupancy blur before the gradient (grid normals)
GRID_TENSOR_SIGMA_CELLS = 1.5  # [cells] structure tensor window (grid normals)
# Uniqueness of a match (rival_score): the window sampled every 4 cells at the match's yaw and
# +-2 deg (aliased corridor stretches are parallel), the best 5 far samples refined per cell.
AMBIGUITY_STRIDE_CELLS = 4
AMBIGUITY_ANGLES = np.radians([-2.0, 0.0, 2.0])  # [rad] yaw offsets from the match
AMBIGUITY_REFINED = 5
AMBIGUITY_CHUNK = 2048  # far samples scored per gather (x scan points x 2 x 8 bytes)
EYE3 = np.eye(3)
EYE3.setflags(write=False)


# 1. Scan points ---------------------------------------------------------------------------------


def scan_points(scan: LaserScan, max_range_m: float = math.inf) -> np.ndarray:
    """(N, 2) float64 end points of the valid returns, in the scan frame.

    REP-117: NaN and ranges outside [range_min, range_max] (and +inf, "no return") are dropped,
    and so are returns beyond ``max_range_m``."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    a = scan.angles()
    limit = min(scan.range_max, max_range_m)
    ok = np.isfinite(r) & (r >= scan.range_min) & (r <= limit)
    return np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])


def voxel_filter(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Keep one point (the first) per ``voxel_m`` square cell, order preserved."""
    if len(points) == 0 or voxel_m <= 0:
        return points
    keys = np.floor(points / voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    flat = keys[:, 0] * (int(keys[:, 1].max()) + 1) + keys[:, 1]
    # Sort (cell, index) packed into one integer: distinct keys, so the fast unstable sort
    # orders each cell's points by index and the first of a run is the cell's first point.
    n = len(points)
    packed = np.sort(flat * n + np.arange(n))
    cell = packed // n
    starts = np.empty(n, bool)
    starts[0] = True
    np.not_equal(cell[1:], cell[:-1], out=starts[1:])
    return points[np.sort(packed[starts] % n)]


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 2) given in frame ``pose`` expressed in the frame ``pose`` is given in."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return points @ np.array([[c, s], [-s, c]]) + pose[:2]


# 2. Likelihood field with its max-pooled pyramid -----------------------------------------------


@dataclass(frozen=True, eq=False)
class LikelihoodField:
    """Smeared occupancy likelihood of reference points; ``levels[k][r, c]`` is the maximum of
    ``levels[0]`` over rows r..r+2^k-1 and cols c..c+2^k-1 (an upper bound for a block)."""

    origin: np.ndarray  # (2,) [m] world (x, y) of the corner of cell (0, 0); row = y, col = x
    resolution: float  # [m/cell]
    levels: tuple[np.ndarray, ...]  # each (H, W) float32 in [0, 1]; border rows/cols are 0
    flat_levels: tuple[np.ndarray, ...]  # each levels[k].ravel() followed by a tail of zeros
    max_window_cells: int  # widest search lattice (cells per axis) the zero tail supports

    @property
    def field(self) -> np.ndarray:
        return self.levels[0]

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Field value at world points (N, 2), 0 outside the grid (nearest cell)."""
        return self.lookup_xy(points[:, 0], points[:, 1])

    def lookup_xy(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Field value at world points given as two arrays of one shape (e.g. candidate poses x
        scan points), 0 outside the grid (nearest cell)."""
        h, w = self.field.shape
        col = self.cell_index(x, 0, w)
        row = self.cell_index(y, 1, h)
        row *= w
        row += col
        return np.take(self.flat_levels[0], row)

    def cell_index(self, v: np.ndarray, axis: int, size: int) -> np.ndarray:
        """Column (``axis`` 0, x) or row (1, y) index of world coordinates ``v``, clamped to the
        grid: the border cell (0) holds what lies beyond it."""
        i = np.floor((v - self.origin[axis]) / self.resolution).astype(np.int64)
        return np.minimum(np.maximum(i, 0, out=i), size - 1, out=i)  # np.clip, without overhead


def build_likelihood_field(
    points: np.ndarray, resolution: float, smear_sigma: float, margin_m: float, n_levels: int
) -> LikelihoodField:
    """Rasterise world points (M, 2) and smear them; ``margin_m`` pads the bounding box so scans
    moved by the search window still land on the grid."""
    if len(points) == 0:
        raise ValueError("no reference points to build a likelihood field from")
    # Twice the margin: a scan point that some shift of the window moves off the grid is then
    # at least a margin plus 3 sigma from every reference point at every shift (field ~ 0), so
    # sending it to the zero tail keeps the search exact.
    pad = 2.0 * margin_m + 3.0 * smear_sigma + 2 * resolution
    origin = points.min(axis=0) - pad
    size = np.ceil((points.max(axis=0) + pad - origin) / resolution).astype(int) + 1
    w, h = int(size[0]), int(size[1])
    rc = np.floor((points - origin) / resolution).astype(np.int64)
    free = np.full((h, w), 255, np.uint8)
    free[rc[:, 1], rc[:, 0]] = 0
    # Off-grid points are pointed at the zero tail, where every shift of the window stays.
    # Each level is the head of its flat array (a view), so the flat form costs no copy.
    max_cells = 2 * int(math.ceil(margin_m / resolution)) + 1
    tail = (max_cells + 1) * (w + 1)
    flat = tuple(np.zeros(h * w + tail, np.float32) for _ in range(n_levels))
    levels = tuple(f[: h * w].reshape(h, w) for f in flat)
    # Distance [cells] from each cell centre to the nearest occupied cell centre, then the field
    # exp(-d^2 / 2 sigma^2) computed in place.
    dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    np.divide(dist, smear_sigma / resolution, out=dist)
    np.square(dist, out=dist)
    np.multiply(dist, -0.5, out=dist)
    field = levels[0]
    np.exp(dist, out=field)
    field[0, :] = field[-1, :] = 0.0
    field[:, 0] = field[:, -1] = 0.0
    cols_max = np.empty_like(field)
    for k in range(1, n_levels):
        # The maximum over a 2^k block is that of the 2 x 2 blocks of level k - 1 half a block
        # apart (columns, then rows); beyond the border the field is 0, below every value.
        prev, pooled, half = levels[k - 1], levels[k], 2 ** (k - 1)
        np.maximum(prev[:, :-half], prev[:, half:], out=cols_max[:, :-half])
        cols_max[:, -half:] = prev[:, -half:]
        np.maximum(cols_max[:-half], cols_max[half:], out=pooled[:-half])
        pooled[-half:] = cols_max[-half:]
    return LikelihoodField(
        origin=origin,
        resolution=resolution,
        levels=levels,
        flat_levels=flat,
        max_window_cells=max_cells,
    )


# 3. Correlative search (batched branch-and-bound) ----------------------------------------------


@dataclass(frozen=True)
class CorrelativeResult:
    pose: np.ndarray  # (3,) best (x, y, yaw) on the search lattice
    score: float  # mean likelihood of the scan points at ``pose`` in [0, 1] (before penalty)
    penalised_score: float  # score times the prior-distance penalties
    evaluated: int  # candidate blocks and leaves scored (how much work the pruning left)


def _block_scores(
    flat_level: np.ndarray, w: int, base: np.ndarray, a: np.ndarray, di: np.ndarray, dj: np.ndarray
) -> np.ndarray:
    """Mean of a level over the points of angle ``a[c]`` shifted by (di[c], dj[c]) cells.

    ``base`` (A, N) holds each point's flat cell index at shift (0, 0), or the start of the zero
    tail for points that some shift of the window would move off the grid (they score 0)."""
    out = np.empty(len(a), np.float64)
    # Chunks of candidates small enough for the index and value buffers to stay in cache; the
    # indices are valid by construction, and mode="clip" lets np.take write to ``out`` unbuffered.
    chunk = max(1, min(len(a), SCORE_CHUNK_ELEMENTS // max(base.shape[1], 1)))
    flat = np.empty((chunk, base.shape[1]), np.intp)
    values = np.empty((chunk, base.shape[1]), flat_level.dtype)
    for lo in range(0, len(a), chunk):
        hi = min(lo + chunk, len(a))
        idx, val = flat[: hi - lo], values[: hi - lo]
        np.take(base, a[lo:hi], axis=0, out=idx, mode="clip")
        idx += (di[lo:hi] * w + dj[lo:hi])[:, None]
        np.take(flat_level, idx, out=val, mode="clip")
        out[lo:hi] = val.mean(axis=1)
    return out


def correlative_match(
    field: LikelihoodField,
    points: np.ndarray,
    prior: np.ndarray,
    linear_window_m: float,
    angular_window_rad: float,
    angle_step_rad: float,
    distance_variance_penalty: float = math.inf,
    angle_variance_penalty: float = math.inf,
    minimum_distance_penalty: float = 0.0,
    minimum_angle_penalty: float = 0.0,
    min_score: float = 0.0,
) -> CorrelativeResult:
    """Best pose of scan ``points`` (N, 2, scan frame) within +-``linear_window_m`` and
    +-``angular_window_rad`` of ``prior`` (exact on the lattice, branch-and-bound pruned).

    The penalties are slam_toolbox's: a candidate's score is multiplied by
    ``max(exp(-d^2 / distance_variance_penalty), minimum_distance_penalty)`` and the same for the
    yaw offset; they favour the prior when the field is ambiguous (e.g. along a corridor).
    Blocks that cannot reach ``min_score`` are pruned (Cartographer's ``min_score``); when no
    candidate reaches it the result has ``score`` 0 and the prior as pose."""
    if len(points) == 0:
        raise ValueError("no scan points to match")
    res = field.resolution
    n_half = max(int(math.ceil(linear_window_m / res)), 0)
    n_ang_half = max(int(math.floor(angular_window_rad / angle_step_rad + 1e-9)), 0)
    dyaw = angle_step_rad * np.arange(-n_ang_half, n_ang_half + 1)
    # 3a. Rotate the scan once per angle; the translation lattice then shifts whole cells.
    yaws = prior[2] + dyaw
    c, s = np.cos(yaws), np.sin(yaws)
    wx = c[:, None] * points[:, 0] - s[:, None] * points[:, 1] + prior[0]
    wy = s[:, None] * points[:, 0] + c[:, None] * points[:, 1] + prior[1]
    cols = np.floor((wx - field.origin[0]) / res).astype(np.int64) - n_half
    rows = np.floor((wy - field.origin[1]) / res).astype(np.int64) - n_half
    n_cells = 2 * n_half + 1  # leaf offsets 0..n_cells-1 per axis (minus n_half in metres)
    h, w = field.field.shape
    if n_cells > field.max_window_cells:
        raise ValueError(
            f"search window of {n_cells} cells exceeds the field's margin "
            f"({field.max_window_cells} cells)"
        )
    # Points that some shift would move off the grid (unmapped territory beyond the margin,
    # where the field is 0 anyway) point at the zero tail.
    on_grid = (rows >= 0) & (cols >= 0) & (rows + n_cells <= h) & (cols + n_cells <= w)
    base = np.where(on_grid, rows * w + cols, h * w)
    top = min(max(int(math.ceil(math.log2(n_cells))), 0), len(field.levels) - 1)
    step = 2**top
    # 3b. All top-level blocks: (angle, row offset, col offset).
    starts = np.arange(0, n_cells, step)
    a, di, dj = (
        v.ravel() for v in np.meshgrid(np.arange(len(yaws)), starts, starts, indexing="ij")
    )
    bound = _block_scores(field.flat_levels[top], w, base, a, di, dj)
    evaluated = len(a)

    def penalty(a_: np.ndarray, di_: np.ndarray, dj_: np.ndarray) -> np.ndarray:
        d2 = ((di_ - n_half) ** 2 + (dj_ - n_half) ** 2) * res**2
        pd = np.maximum(np.exp(-d2 / distance_variance_penalty), minimum_distance_penalty)
        pa = np.maximum(np.exp(-(dyaw[a_] ** 2) / angle_variance_penalty), minimum_angle_penalty)
        return pd * pa

    # 3c. Greedy descent from the best top block gives a first exact leaf score to prune with.
    best_leaf = (-1.0, 0, 0, 0, 0.0)  # penalised, a, di, dj, raw
    ga, gi, gj = int(a[np.argmax(bound)]), int(di[np.argmax(bound)]), int(dj[np.argmax(bound)])
    for lvl in range(top, 0, -1):
        half = 2 ** (lvl - 1)
        ci = np.array([gi, gi, gi + half, gi + half])
        cj = np.array([gj, gj + half, gj, gj + half])
        keep = (ci < n_cells) & (cj < n_cells)
        ci, cj = ci[keep], cj[keep]
        sc = _block_scores(field.flat_levels[lvl - 1], w, base, np.full(len(ci), ga), ci, cj)
        evaluated += len(ci)
        k = int(np.argmax(sc))
        gi, gj = int(ci[k]), int(cj[k])
    raw = float(
        _block_scores(
            field.flat_levels[0], w, base, np.array([ga]), np.array([gi]), np.array([gj])
        )[0]
    )
    pen = raw * float(penalty(np.array([ga]), np.array([gi]), np.array([gj]))[0])
    best_leaf = (pen, ga, gi, gj, raw) if pen >= min_score else (min_score, -1, 0, 0, 0.0)
    # 3d. Level by level: drop blocks whose bound cannot beat the best leaf, split the rest.
    for lvl in range(top, -1, -1):
        keep = bound > best_leaf[0]
        a, di, dj, bound = a[keep], di[keep], dj[keep], bound[keep]
        if len(a) == 0:
            break
        if lvl == 0:
            # Leaves: the bound is the exact score; apply the penalty and take the best.
            pen_scores = bound * penalty(a, di, dj)
            k = int(np.argmax(pen_scores))
            if pen_scores[k] > best_leaf[0]:
                best_leaf = (
                    float(pen_scores[k]),
                    int(a[k]),
                    int(di[k]),
                    int(dj[k]),
                    float(bound[k]),
                )
            break
        half = 2 ** (lvl - 1)
        a = np.repeat(a, 4)
        di = np.repeat(di, 4) + np.tile([0, 0, half, half], len(di))
        dj = np.repeat(dj, 4) + np.tile([0, half, 0, half], len(dj))
        inside = (di < n_cells) & (dj < n_cells)
        a, di, dj = a[inside], di[inside], dj[inside]
        bound = _block_scores(field.flat_levels[lvl - 1], w, base, a, di, dj)
        evaluated += len(a)
    pen, ba, bi, bj, raw = best_leaf
    if ba < 0:
        return CorrelativeResult(
            pose=np.asarray(prior, float).copy(),
            score=0.0,
            penalised_score=0.0,
            evaluated=evaluated,
        )
    pose = np.array(
        [
            prior[0] + (bj - n_half) * res,
            prior[1] + (bi - n_half) * res,
            float(wrap_angle(prior[2] + dyaw[ba])),
        ]
    )
    return CorrelativeResult(pose=pose, score=raw, penalised_score=pen, evaluated=evaluated)


def rival_score(
    field: LikelihoodField,
    points: np.ndarray,
    pose: np.ndarray,
    linear_window_m: float,
    exclude_m: float,
    angles_rad: np.ndarray = AMBIGUITY_ANGLES,
    stride_cells: int = AMBIGUITY_STRIDE_CELLS,
) -> float:
    """Best mean likelihood of scan ``points`` at a pose within +-``linear_window_m`` of
    ``pose`` but more than ``exclude_m`` away from it (0 when the window has no such pose).

    Compared with the score at ``pose`` it says whether a match is unique: along a corridor
    with a repeating pattern of doors the scan fits about as well one period further on, and
    a correlative matcher with a wide window picks either. The window is sampled every
    ``stride_cells`` cells at the yaw offsets ``angles_rad``, then the best few far samples are
    refined on the full-resolution lattice around them."""
    res = field.resolution
    n = int(math.ceil(linear_window_m / res))
    offs = np.arange(-n, n + 1, stride_cells, dtype=np.float64) * res
    kx, ky = (v.ravel() for v in np.meshgrid(np.arange(len(offs)), np.arange(len(offs))))
    dx, dy = offs[kx], offs[ky]
    far = np.hypot(dx, dy) > exclude_m
    if len(points) == 0 or not far.any():
        return 0.0
    dx, dy, kx, ky = dx[far], dy[far], kx[far], ky[far]
    # Coarse: every stride-th cell, a few yaw offsets, all at once per yaw (bounded chunks). A
    # sample's cell is (row of wy + dy, column of wx + dx): both are computed once per offset
    # and point, with lookup_xy's arithmetic, and a sample adds its row and column indices.
    yaws = pose[2] + np.asarray(angles_rad, dtype=np.float64)
    best: list[tuple[float, float, float, float]] = []  # (score, dx, dy, yaw)
    height, width = field.field.shape
    flat = field.flat_levels[0]
    for yaw in yaws:
        c, s = math.cos(yaw), math.sin(yaw)
        wx = c * points[:, 0] - s * points[:, 1] + pose[0]
        wy = s * points[:, 0] + c * points[:, 1] + pose[1]
        col = field.cell_index(wx[None, :] + offs[:, None], 0, width)  # (offsets, points)
        row = field.cell_index(wy[None, :] + offs[:, None], 1, height)
        row *= width
        for lo in range(0, len(dx), AMBIGUITY_CHUNK):
            sx, sy = dx[lo : lo + AMBIGUITY_CHUNK], dy[lo : lo + AMBIGUITY_CHUNK]
            idx = row[ky[lo : lo + AMBIGUITY_CHUNK]]
            idx += col[kx[lo : lo + AMBIGUITY_CHUNK]]
            sc = flat.take(idx).mean(axis=1)
            top = np.argsort(sc)[-AMBIGUITY_REFINED:]
            best.extend((float(sc[t]), float(sx[t]), float(sy[t]), float(yaw)) for t in top)
    best.sort(reverse=True)
    # Fine: the full-resolution lattice around the best few far samples.
    h = stride_cells // 2
    fine = np.arange(-h, h + 1, dtype=np.float64) * res
    fx, fy = (v.ravel() for v in np.meshgrid(fine, fine))
    rival = 0.0
    for score, bx, by, yaw in best[:AMBIGUITY_REFINED]:
        rival = max(rival, score)
        ox, oy = bx + fx, by + fy
        keep = np.hypot(ox, oy) > exclude_m
        c, s = math.cos(yaw), math.sin(yaw)
        wx = c * points[:, 0] - s * points[:, 1] + pose[0]
        wy = s * points[:, 0] + c * points[:, 1] + pose[1]
        if keep.any():
            sc = field.lookup_xy(wx[None, :] + ox[keep][:, None], wy[None, :] + oy[keep][:, None])
            rival = max(rival, float(sc.mean(axis=1).max()))
    return rival


# 4. Point-to-line ICP ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ReferenceCloud:
    """Reference points with unit normals (from a line fit to their neighbours) and a k-d tree.

    ``points`` and ``normals`` carry one extra all-zero row at index M: the k-d tree reports a
    missing neighbour as index M, which so contributes a zero residual and Jacobian row."""

    points: np.ndarray  # (M + 1, 2) [m]
    normals: np.ndarray  # (M + 1, 2) unit; (0, 0) where the neighbourhood is no line
    tree: cKDTree

    @cached_property
    def columns(self) -> np.ndarray:
        """(5, M + 1) float64 rows q_x [m], q_y [m], n_x, n_y, has-a-normal (1.0 or 0.0): all
        that ICP needs of a neighbour, gathered with one ``np.take`` per iteration."""
        has_normal = np.any(self.normals != 0, axis=1)
        return np.vstack([self.points.T, self.normals.T, has_normal])

    @property
    def size(self) -> int:
        return len(self.points) - 1


def build_reference(points: np.ndarray) -> ReferenceCloud:
    """Normals by PCA of each point's ``NORMAL_NEIGHBOURS`` nearest neighbours (vectorised)."""
    tree = cKDTree(points)
    m, k = len(points), min(NORMAL_NEIGHBOURS, len(points))
    # The k nearest, and any further neighbour exactly as near as the k-th: a laser's equally
    # spaced returns tie often (three beams of equal range), and which tied point the tree lists
    # first is decided by rounding, so a fixed k flipped normals between CPUs (issue #12).
    kq = min(k + NORMAL_TIE_EXTRA, m)
    dist, idx = tree.query(points, k=kq)
    dist, idx = np.asarray(dist).reshape(m, kq), np.asarray(idx).reshape(m, kq)
    tied = dist <= dist[:, k - 1 : k] * (1 + NORMAL_TIE_RTOL)
    tied[:, :k] = True
    w = tied.astype(np.float64)
    n_nb = w.sum(axis=1)
    # Neighbourhoods as (M, kq) planes of x and of y: the sums run along contiguous rows; without
    # a tie the extra columns weigh 0 and the sums are those over the k nearest.
    nbx, nby = points[:, 0][idx], points[:, 1][idx]
    dx = (nbx - ((w * nbx).sum(axis=1) / n_nb)[:, None]) * w
    dy = (nby - ((w * nby).sum(axis=1) / n_nb)[:, None]) * w
    sxx, syy, sxy = (
        (dx * dx).sum(axis=1) / n_nb,
        (dy * dy).sum(axis=1) / n_nb,
        (dx * dy).sum(axis=1) / n_nb,
    )
    # Closed-form 2x2 eigen-decomposition: the line direction is at angle phi, the normal at
    # phi + 90 deg; the eigenvalues are mean -+ radius.
    phi = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    mean, radius = 0.5 * (sxx + syy), np.hypot(0.5 * (sxx - syy), sxy)
    linear = (mean - radius) <= PLANARITY_MAX * np.maximum(mean + radius, 1e-12)
    padded, normals = np.zeros((m + 1, 2)), np.zeros((m + 1, 2))
    padded[:m] = points
    normals[:m][linear] = np.column_stack([-np.sin(phi[linear]), np.cos(phi[linear])])
    return ReferenceCloud(padded, normals, tree)


def surface_mask(occupied: np.ndarray) -> np.ndarray:
    """The occupied cells next to a non-occupied one (8-neighbourhood): all a scan can hit."""
    occ = np.asarray(occupied, dtype=bool)
    return occ & (cv2.dilate((~occ).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)


def build_grid_reference(
    occupied: np.ndarray, origin_xy: tuple[float, float], resolution: float
) -> ReferenceCloud:
    """ICP reference of an occupancy grid (row 0 at the bottom, Nav2 origin): the occupied cells
    next to a non-occupied one (a scan only ever hits those), with nearest-neighbour PCA normals
    where those cells form a line and the grid's structure tensor where they do not.

    Nearest-neighbour PCA fails on maps: the k nearest cells of a wall two or more cells thick
    form a blob, not a line, so every normal came out zero and ICP had nothing to pull on (maps
    from floor plans, from other tools, or any Nav2 map with thick walls). The structure tensor
    ``J = G_s * [gx^2, gx gy; gx gy, gy^2]`` of the blurred occupancy has its dominant eigenvector
    across the wall whatever its thickness; its coherence ``sqrt((Jxx - Jyy)^2 + 4 Jxy^2) /
    (Jxx + Jyy)`` rejects corners and clutter with the same eigenvalue-ratio rule as
    :func:`build_reference` (ratio <= PLANARITY_MAX <=> coherence >= (1 - r) / (1 + r))."""
    occ = np.asarray(occupied, dtype=bool)
    rows, cols = np.nonzero(surface_mask(occ))
    if len(rows) == 0:
        raise ValueError("the grid has no occupied cell next to free or unknown space")
    img = cv2.GaussianBlur(occ.astype(np.float32), (0, 0), GRID_GRADIENT_SIGMA_CELLS)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)  # along columns = +x
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)  # along rows = +y (row 0 at the bottom)
    jxx, jxy, jyy = (
        cv2.GaussianBlur(g, (0, 0), GRID_TENSOR_SIGMA_CELLS)[rows, cols]
        for g in (gx * gx, gx * gy, gy * gy)
    )
    phi = 0.5 * np.arctan2(2 * jxy, jxx - jyy)  # dominant gradient direction = the normal
    coherence = np.hypot(jxx - jyy, 2 * jxy) / np.maximum(jxx + jyy, 1e-12)
    linear = coherence >= (1 - PLANARITY_MAX) / (1 + PLANARITY_MAX)
    normals = np.where(linear[:, None], np.column_stack([np.cos(phi), np.sin(phi)]), 0.0)
    pts = np.column_stack(
        [origin_xy[0] + (cols + 0.5) * resolution, origin_xy[1] + (rows + 0.5) * resolution]
    )
    # Where the surface cells themselves form a line (a one-cell wall, as scans draw them), the
    # local PCA normal follows it more closely than the smoothed tensor (measured: a 3 cm bias
    # on mapped grids otherwise); the tensor fills in where PCA sees a blob.
    pca = build_reference(pts)
    has = np.any(pca.normals[:-1] != 0, axis=1, keepdims=True)
    normals = np.where(has, pca.normals[:-1], normals)
    zero = np.zeros((1, 2))
    return ReferenceCloud(pca.points, np.vstack([normals, zero]), pca.tree)


@dataclass(frozen=True)
class IcpResult:
    pose: np.ndarray  # (3,) refined (x, y, yaw)
    covariance: np.ndarray  # (3, 3) in (x, y, yaw)
    rmse: float  # [m] weighted point-to-line residual at convergence
    inlier_fraction: float  # scan points with a neighbour within max_correspondence_m
    iterations: int
    converged: bool


def icp_refine(
    ref: ReferenceCloud,
    points: np.ndarray,
    initial: np.ndarray,
    max_correspondence_m: float,
    max_iterations: int = 20,
    huber_m: float = 0.05,
    min_sigma_m: float = 0.01,
    tolerance: float = 5e-4,
    polish: float | None = None,
) -> IcpResult:
    """Point-to-line Gauss-Newton from ``initial`` (see module docstring).

    ``converged``: the last step was below ``tolerance`` [m, rad]. With ``polish`` (< tolerance)
    a converged ICP goes on until its step is below ``polish`` (or ``max_iterations``): stopped
    at ``tolerance`` the result still depends on where ICP started by up to about that much, so
    the two paths of the mapper (ICP from odometry, or from the correlative optimum) and two
    CPUs' rounding gave poses 0.1-1 mm apart that the next matches amplified (issue #12).

    Per iteration this is one k-d tree query, one gather of the neighbours' rows and a few
    vector operations on preallocated buffers (the ICP is a third of the mapper's time); the
    arithmetic is the one of the straightforward kernel, operation for operation, so the result
    is bit-identical to it (``tests/slam/test_scan_matching.py`` keeps that kernel as reference)."""
    if not huber_m > 0:
        raise ValueError(f"huber_m must be > 0, got {huber_m}")
    pose = np.asarray(initial, dtype=np.float64).copy()
    n = max(len(points), 1)
    failed = IcpResult(pose.copy(), np.diag([1e6, 1e6, 1e6]), math.inf, 0.0, 0, False)
    px, py = points[:, 0], points[:, 1]
    world = np.empty((len(points), 2))  # scan points in the reference frame (tree query input)
    wx, wy = world[:, 0], world[:, 1]
    jac = np.empty((len(points), 3))  # rows [n_x, n_y, n . (dR/dyaw p)]
    it, converged = 0, False
    for it in range(1, max_iterations + 1):  # noqa: B007 - it is reported
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rx, ry = c * px - s * py, s * px + c * py  # R p; dR/dyaw p = (-ry, rx)
        np.add(rx, pose[0], out=wx)
        np.add(ry, pose[1], out=wy)
        _, idx = ref.tree.query(world, distance_upper_bound=max_correspondence_m)
        # A missing neighbour (index M) has zero normal and point: zero residual and Jacobian.
        qx, qy, nx, ny, has_normal = ref.columns.take(idx, axis=1)
        r = nx * (wx - qx) + ny * (wy - qy)
        jac[:, 0], jac[:, 1] = nx, ny
        np.subtract(ny * rx, nx * ry, out=jac[:, 2])
        # Huber: 1 inside the width, width / |r| beyond (huber_m > 0); 0 without a normal.
        wts = huber_m / np.maximum(np.abs(r), huber_m)
        wts *= has_normal
        n_used = int(np.count_nonzero(wts))
        if n_used < MIN_POINTS:
            return failed
        jw = jac * wts[:, None]
        hess = jw.T @ jac
        # LAPACK's gesv, which np.linalg.solve wraps, without the wrapper's overhead.
        _, _, step, info = gesv(hess + 1e-9 * hess.trace() * EYE3, jw.T @ r)
        if info != 0:  # exactly singular
            return failed
        pose -= step
        moved, turned = abs(step[0]) + abs(step[1]), abs(step[2])
        converged = moved < tolerance and turned < tolerance
        if converged and (polish is None or (moved < polish and turned < polish)):
            break
    pose[2] = float(wrap_angle(pose[2]))
    wsum = float(np.sum(wts))
    rmse = math.sqrt(float(np.sum(wts * r**2)) / max(wsum, 1e-12))
    sigma2 = max(float(np.sum(wts * r**2)) / max(n_used - 3, 1), min_sigma_m**2)
    # Invert through a clamped eigen-decomposition: an exactly degenerate direction (a straight
    # corridor) gets a huge variance instead of failing the whole match.
    evals, evecs = np.linalg.eigh(0.5 * (hess + hess.T))
    evals = np.maximum(evals, DEGENERATE_EIGENVALUE * max(float(evals[-1]), 1e-12))
    cov = sigma2 * (evecs / evals) @ evecs.T
    inliers = float(np.count_nonzero(idx < ref.size)) / n
    return IcpResult(pose, 0.5 * (cov + cov.T), rmse, inliers, it, converged)


# 5. Sub-cell polish on a smooth field (Cartographer's Ceres scan matcher) -----------------------


@dataclass(frozen=True, eq=False)
class SmoothField:
    """A grid's surface cells blurred and normalised to a peak of 1, sampled bicubically.

    ``values[r, c]`` is the field at world (origin_x + c res, origin_y + r res): samples sit at
    cell centres, with a zero border of ``SMOOTH_PAD`` cells so the 4 x 4 stencil of any point
    of the map stays inside."""

    origin: np.ndarray  # (2,) [m] world (x, y) of sample (0, 0), a cell centre
    resolution: float  # [m/cell]
    values: np.ndarray  # (H, W) float64 in [0, 1]

    def sample(self, xy: np.ndarray) -> tuple[np.ndarray, ...]:
        """Value, gradient [1/m] (x, y) and Hessian [1/m^2] (xx, xy, yy) at world points (N, 2);
        all 0 beyond the field.

        Catmull-Rom (Keys, a = -1/2) along x then y, as ``ceres::BiCubicInterpolator``: the
        value is C1, so Newton sees a gradient that does not jump at cell edges, and the maximum
        between two equal samples lies half way (bilinear would be flat there)."""
        h, w = self.values.shape
        u = (xy[:, 0] - self.origin[0]) / self.resolution
        v = (xy[:, 1] - self.origin[1]) / self.resolution
        iu, iv = np.floor(u), np.floor(v)
        i, j = iu.astype(np.int64), iv.astype(np.int64)
        inside = (i >= 1) & (j >= 1) & (i < w - 2) & (j < h - 2)
        corner = np.where(inside, (j - 1) * w + (i - 1), 0)
        patch = self.values.take(corner[:, None] + _stencil(w)).reshape(-1, 4, 4)
        ku = _keys_weights(u - iu)  # (3, N, 4): weights, d/dt, d2/dt2
        kv = _keys_weights(v - iv)
        rows = np.einsum("nrc,knc->knr", patch, ku)  # per stencil row: value, d/du, d2/du2
        f = np.einsum("nr,nr->n", rows[0], kv[0])
        fx = np.einsum("nr,nr->n", rows[1], kv[0])
        fy = np.einsum("nr,nr->n", rows[0], kv[1])
        fxx = np.einsum("nr,nr->n", rows[2], kv[0])
        fxy = np.einsum("nr,nr->n", rows[1], kv[1])
        fyy = np.einsum("nr,nr->n", rows[0], kv[2])
        res, res2 = self.resolution, self.resolution**2
        return (
            f * inside,
            fx * inside / res,
            fy * inside / res,
            fxx * inside / res2,
            fxy * inside / res2,
            fyy * inside / res2,
        )


def _stencil(w: int) -> np.ndarray:
    """Flat offsets of a 4 x 4 stencil from its corner in an array ``w`` wide (row-major)."""
    return (np.arange(4)[:, None] * w + np.arange(4)[None, :]).ravel()


def _keys_weights(t: np.ndarray) -> np.ndarray:
    """(3, N, 4) Catmull-Rom weights of samples -1, 0, 1, 2 at fraction ``t``, their d/dt and
    d2/dt2 (written in place: a nested ``np.array`` of the twelve rows cost a third more)."""
    t2 = t * t
    t3 = t2 * t
    out = np.empty((3, len(t), 4))
    w, d, h = out
    w[:, 0], w[:, 1] = -t3 + 2.0 * t2 - t, 3.0 * t3 - 5.0 * t2 + 2.0
    w[:, 2], w[:, 3] = -3.0 * t3 + 4.0 * t2 + t, t3 - t2
    d[:, 0], d[:, 1] = -3.0 * t2 + 4.0 * t - 1.0, 9.0 * t2 - 10.0 * t
    d[:, 2], d[:, 3] = -9.0 * t2 + 8.0 * t + 1.0, 3.0 * t2 - 2.0 * t
    h[:, 0], h[:, 1] = -6.0 * t + 4.0, 18.0 * t - 10.0
    h[:, 2], h[:, 3] = -18.0 * t + 8.0, 6.0 * t - 2.0
    out *= 0.5
    return out


SMOOTH_PAD = 3  # [cells] zero border of a SmoothField (the bicubic stencil reaches 2)
LM_DAMPING_DOWN = 0.1  # Levenberg-Marquardt damping after a step that lowered the cost
LM_DAMPING_UP = 10.0  # ... and after one that did not (the step is retried, shorter)


def build_smooth_field(
    mask: np.ndarray, origin_xy: tuple[float, float], resolution: float, sigma_m: float
) -> SmoothField:
    """The Gaussian blur (``sigma_m``) of a cell mask (row 0 at the bottom, Nav2 origin at the
    corner of cell (0, 0)), normalised to a maximum of 1. Its ridge across a wall is the centroid
    of the wall's cells: on the boundary of a two-cell wall, at the centre of a one-cell one."""
    pad = SMOOTH_PAD
    img = np.zeros((mask.shape[0] + 2 * pad, mask.shape[1] + 2 * pad), np.float32)
    img[pad:-pad, pad:-pad] = mask
    sigma = sigma_m / resolution
    if sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    values = img.astype(np.float64)
    peak = float(values.max())
    if peak > 0:
        values /= peak
    origin = np.array(origin_xy, dtype=np.float64) + (0.5 - pad) * resolution
    return SmoothField(origin, resolution, values)


@dataclass(frozen=True)
class RefineResult:
    pose: np.ndarray  # (3,) the polished pose, or ``initial`` when not ``ok``
    ok: bool
    reason: str  # why the initial pose was kept ("" when ok)
    iterations: int
    cost: float  # mean (1 - F)^2 at ``pose``


def near_surface(reference: ReferenceCloud, world: np.ndarray, radius: float) -> np.ndarray:
    """(N,) bool: the world points within ``radius`` of a reference point (for a grid's
    reference, a wall cell next to free or unknown space)."""
    dist, _ = reference.tree.query(world, distance_upper_bound=radius)
    return np.isfinite(dist)


def refine_on_field(
    field: SmoothField,
    points: np.ndarray,
    initial: np.ndarray,
    max_iterations: int = 10,
    max_shift_m: float = math.inf,
    max_turn_rad: float = math.inf,
    tolerance: float = 1e-4,
    covariance: np.ndarray | None = None,
    degeneracy_ratio: float = math.inf,
) -> RefineResult:
    """Damped Newton on ``sum r_i^2``, ``r_i = 1 - F(R p_i + t)``, from ``initial``.

    **Frame-invariant**: the pose turns about the scan points' centroid, not the scan frame's
    origin, and the basin test and weak axes are measured there, so the same points give the
    same world pose whether the scan is in base_link or in a camera frame 0.2 m ahead. Give it
    only the points on the map's walls (:func:`near_surface`): one in a gap of a mapped wall is
    pulled along the wall onto the gap's end. The Hessian is Newton's (``J^T J`` plus ``r_i``
    times the second derivatives of ``r_i``; Gauss-Newton alone overshoots a wall's ridge),
    Gauss-Newton's where that is not positive definite; a step is kept only if it lowers the
    cost; the polish stops below ``tolerance`` [m, rad]. **Weak axes**: the match's
    ``covariance`` (at ``initial``), carried to the centroid with the yaw in metres (times the
    points' RMS radius); along its axes with a variance over ``degeneracy_ratio`` times the
    smallest (a corridor) ``initial`` is kept. It falls back to ``initial`` (``ok`` False, with
    the reason) when fewer than ``MIN_POINTS`` points see a gradient, or when the centroid moves
    farther than ``max_shift_m`` or the yaw ``max_turn_rad``: it left the match's basin. Sums
    are numpy's (no BLAS): the result does not depend on OpenBLAS's kernels."""
    start = np.asarray(initial, dtype=np.float64)
    mean = points.mean(axis=0) if len(points) else np.zeros(2)
    centred = points - mean
    px, py = centred[:, 0], centred[:, 1]
    c0, s0 = math.cos(start[2]), math.sin(start[2])
    lever = np.array([c0 * mean[0] - s0 * mean[1], s0 * mean[0] + c0 * mean[1]])
    origin = np.array([start[0] + lever[0], start[1] + lever[1], start[2]])  # the centroid's

    def evaluate(p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        c, s = math.cos(p[2]), math.sin(p[2])
        qx, qy = c * px - s * py, s * px + c * py
        f, fx, fy, fxx, fxy, fyy = field.sample(np.column_stack([qx + p[0], qy + p[1]]))
        r = 1.0 - f
        jac = np.vstack([-fx, -fy, fx * qy - fy * qx])
        # Second derivatives of r_i (upper triangle: xx, xy, x-yaw, yy, y-yaw, yaw-yaw).
        d2 = np.vstack(
            [
                -fxx,
                -fxy,
                fxx * qy - fxy * qx,
                -fyy,
                fxy * qy - fyy * qx,
                -(fxx * qy * qy - 2.0 * fxy * qx * qy + fyy * qx * qx) + fx * qx + fy * qy,
            ]
        )
        return float(np.einsum("n,n->", r, r)), r, jac, d2

    def at_scan_origin(p: np.ndarray) -> np.ndarray:
        c, s = math.cos(p[2]), math.sin(p[2])
        out = p - np.array([c * mean[0] - s * mean[1], s * mean[0] + c * mean[1], 0.0])
        out[2] = float(wrap_angle(out[2]))
        return out

    pose = origin.copy()
    cost, r, jac, d2 = evaluate(pose)
    n = max(len(points), 1)
    if int(np.count_nonzero(jac[0] != 0.0)) < MIN_POINTS:
        return RefineResult(start.copy(), False, "too few points on the smooth field", 0, cost / n)
    damping, it = 1e-6, 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - it is reported
        hess = np.einsum("in,jn->ij", jac, jac)  # numpy's own loops: no BLAS
        grad = np.einsum("in,n->i", jac, r)
        second = np.einsum("kn,n->k", d2, r)
        full = hess + second[_UPPER_TO_FULL]
        if np.linalg.eigvalsh(full)[0] > 0.0:
            hess = full
        improved, step = False, np.zeros(3)
        while damping <= 1e6:
            lhs = hess + damping * np.diag(np.diag(hess) + 1e-12)
            _, _, sol, info = gesv(lhs, -grad)
            if info != 0:
                break
            step = sol
            trial = pose + step
            trial_cost, trial_r, trial_jac, trial_d2 = evaluate(trial)
            if trial_cost < cost:
                pose, cost, r, jac, d2 = trial, trial_cost, trial_r, trial_jac, trial_d2
                damping = max(damping * LM_DAMPING_DOWN, 1e-9)
                improved = True
                break
            damping = max(damping * LM_DAMPING_UP, 1e-4)
        if not improved or (abs(step[0]) + abs(step[1]) < tolerance and abs(step[2]) < tolerance):
            break
    move = pose - origin
    move[2] = float(wrap_angle(move[2]))
    if covariance is not None and math.isfinite(degeneracy_ratio):
        move = _drop_weak_axes(move, covariance, lever, centred, degeneracy_ratio)
        pose = origin + move
        cost = evaluate(pose)[0]
    if math.hypot(move[0], move[1]) > max_shift_m or abs(move[2]) > max_turn_rad:
        return RefineResult(start.copy(), False, "left the match's basin", it, cost / n)
    return RefineResult(at_scan_origin(pose), True, "", it, cost / n)


def _drop_weak_axes(
    move: np.ndarray, covariance: np.ndarray, lever: np.ndarray, centred: np.ndarray, ratio: float
) -> np.ndarray:
    """``move`` (x, y, yaw about the centroid) without its part along the weak axes of
    ``covariance`` (x, y, yaw at the scan origin): the covariance carried to the centroid
    (``lever``: scan origin -> centroid in the world) with yaw in metres of the points' RMS
    radius, its eigenvectors with a variance over ``ratio`` times the smallest projected out."""
    radius = max(math.sqrt(float(np.einsum("ij,ij->", centred, centred)) / len(centred)), 1e-3)
    carry = lever_jacobian(lever)
    carry[2, 2] = radius
    cov = np.einsum("ij,jk,lk->il", carry, np.asarray(covariance, dtype=np.float64), carry)
    evals, evecs = np.linalg.eigh(0.5 * (cov + cov.T))
    well = evecs[:, evals <= ratio * max(float(evals[0]), 1e-18)]
    scaled = np.array([move[0], move[1], move[2] * radius])
    kept = np.einsum("ik,jk,j->i", well, well, scaled)
    return np.array([kept[0], kept[1], kept[2] / radius])


_UPPER_TO_FULL = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])  # 3 x 3 from its upper triangle


def release_degenerate_axis(
    covariance: np.ndarray, degeneracy_ratio: float, unobserved_variance: float
) -> tuple[np.ndarray, bool]:
    """A match covariance with its weak translational axis set to ``unobserved_variance``.

    ICP's covariance claims information along every axis, including along a featureless
    corridor where noisy wall normals fake it. A translational direction whose variance is
    ``degeneracy_ratio`` times that of the best-constrained one is treated as unobserved (its
    coupling to yaw dropped), so a filter keeps its prediction along it."""
    cov = np.array(covariance, dtype=np.float64)
    evals, evecs = np.linalg.eigh(cov[:2, :2])
    if evals[1] <= degeneracy_ratio * max(float(evals[0]), 1e-12):
        return cov, False
    well, weak = evecs[:, :1], evecs[:, 1:]
    cov[:2, :2] = well @ np.diag(evals[:1]) @ well.T + weak @ weak.T * unobserved_variance
    cov[:2, 2] = cov[2, :2] = 0.0
    return cov, True


__all__ = [
    "CorrelativeResult",
    "IcpResult",
    "LikelihoodField",
    "ReferenceCloud",
    "RefineResult",
    "SmoothField",
    "build_grid_reference",
    "build_likelihood_field",
    "build_reference",
    "build_smooth_field",
    "correlative_match",
    "icp_refine",
    "near_surface",
    "refine_on_field",
    "rival_score",
    "release_degenerate_axis",
    "scan_points",
    "surface_mask",
    "transform_points",
    "voxel_filter",
]
