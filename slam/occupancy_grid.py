"""Log-odds occupancy grid built from 2D laser scans (OctoMap / ROS semantics).

Conventions: arrays are ``(height, width)`` with **row 0 the lowest y** (like
``nav_msgs/OccupancyGrid.data``; only the PGM writer/reader in :mod:`slam.map_bundle` flips);
``origin`` is the world position of the lower-left corner of cell (0, 0), exactly Nav2's
map.yaml ``origin``; unknown is explicit (an ``observed`` mask beside the log-odds).

The update (:func:`integrate_scans`) per scan, as OctoMap's ``insertPointCloud``: cells a beam
crosses get ``logit(prob_miss)`` (no-return beams clear up to the usable range), end cells get
``logit(prob_hit)`` (endpoint wins within a scan), each cell is updated at most once per scan
and clamped. Rays are rasterised in C by ``cv2.polylines`` into a mask over the scan's bounding
box. Details: docs/design/occupancy_grid.md.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from sensors.types import LaserScan, MapError
from slam.config import MapperConfig

log = logging.getLogger(__name__)

# nav_msgs/OccupancyGrid cell values.
OCCUPIED = 100
FREE = 0
UNKNOWN = -1

# A map read from an image carries only 0..100 occupancy values; they become probabilities clamped
# to the MapperConfig default clamping band so that trinary() with the default thresholds gives back
# the same classes and a loaded map can be extended by integrate_scans without saturating.
MAX_GRID_CELLS = 2**28  # [cells] largest grid allocated (1 GiB of float32 log-odds alone)
GRID_BYTES_PER_CELL = 4 + 1 + 1  # [bytes] log-odds float32, observed flag, occupancy int8
LOADED_P_MIN = 0.12  # [probability] same as MapperConfig.clamping_thres_min
LOADED_P_MAX = 0.97  # [probability] same as MapperConfig.clamping_thres_max

# Per-scan cell labels of the rasterisation.
_UNTOUCHED, _FREE, _HIT = 0, 1, 2


def logit(p: float) -> float:
    """log(p / (1 - p)), the log-odds of probability ``p``."""
    return math.log(p) - math.log1p(-p)


def check_grid_size(width: float, height: float, resolution: float) -> None:
    """MapError, before anything is allocated, for a grid over ``MAX_GRID_CELLS`` cells (a
    resolution typed too fine, or a pose or landmark absurdly far away)."""
    cells = width * height
    if not cells <= MAX_GRID_CELLS:  # also NaN / inf
        gib = cells * GRID_BYTES_PER_CELL / 2**30
        raise MapError(
            f"a {width:.3g} x {height:.3g} cell grid at {resolution:g} m/cell would need "
            f"{gib:.3g} GiB (more than {MAX_GRID_CELLS} cells): a coarser resolution "
            "(mapper.resolution), or a pose or point far outside the mapped area"
        )


@dataclass(frozen=True)
class GridGeometry:
    """Where a grid lies in the map frame."""

    resolution: float  # [m/cell]
    origin_x: float  # [m] world x of the lower-left corner of cell (row 0, col 0)
    origin_y: float  # [m] world y of that corner
    width: int  # [cells] number of columns (x)
    height: int  # [cells] number of rows (y)

    def __post_init__(self) -> None:
        if not (self.resolution > 0.0 and math.isfinite(self.resolution)):
            raise MapError(f"grid resolution must be positive, got {self.resolution}")
        if self.width < 1 or self.height < 1:
            raise MapError(f"grid size must be at least 1x1, got {self.width}x{self.height}")
        if not (math.isfinite(self.origin_x) and math.isfinite(self.origin_y)):
            raise MapError(f"grid origin must be finite, got ({self.origin_x}, {self.origin_y})")
        check_grid_size(self.width, self.height, self.resolution)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the grid's arrays."""
        return (self.height, self.width)

    @classmethod
    def from_bounds(
        cls,
        xmin: float,
        ymin: float,
        xmax: float,
        ymax: float,
        resolution: float,
        margin: float = 0.0,
    ) -> GridGeometry:
        """The smallest grid covering ``[xmin, xmax] x [ymin, ymax]`` grown by ``margin`` [m].

        The origin is snapped to a multiple of the resolution so grids of the same map built
        from different bounds share cell boundaries.
        """
        if not all(math.isfinite(v) for v in (xmin, ymin, xmax, ymax)):
            raise MapError(f"grid bounds must be finite, got {(xmin, ymin, xmax, ymax)}")
        if xmax < xmin or ymax < ymin:
            raise MapError(f"grid bounds are inverted: {(xmin, ymin, xmax, ymax)}")
        if not resolution > 0.0:
            raise MapError(f"grid resolution must be positive, got {resolution}")
        # The size first, in floats: a 1e300 m extent or a 0.2 mm cell must not reach floor().
        check_grid_size(
            (xmax - xmin + 2 * margin) / resolution + 2,
            (ymax - ymin + 2 * margin) / resolution + 2,
            resolution,
        )
        ox = math.floor((xmin - margin) / resolution) * resolution
        oy = math.floor((ymin - margin) / resolution) * resolution
        width = max(1, math.floor((xmax + margin - ox) / resolution) + 1)
        height = max(1, math.floor((ymax + margin - oy) / resolution) + 1)
        return cls(resolution, ox, oy, width, height)

    def world_to_cell(
        self, x: float | np.ndarray, y: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World [m] -> (row, col) int64 indices of the containing cell (may be out of bounds)."""
        col = np.floor((np.asarray(x, dtype=np.float64) - self.origin_x) / self.resolution)
        row = np.floor((np.asarray(y, dtype=np.float64) - self.origin_y) / self.resolution)
        return row.astype(np.int64), col.astype(np.int64)

    def cell_to_world(
        self, row: int | np.ndarray, col: int | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) -> world (x, y) [m] of the cell centres."""
        x = self.origin_x + (np.asarray(col, dtype=np.float64) + 0.5) * self.resolution
        y = self.origin_y + (np.asarray(row, dtype=np.float64) + 0.5) * self.resolution
        return x, y

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) arrays of the x and y [m] of every cell centre."""
        rows, cols = np.indices(self.shape)
        return self.cell_to_world(rows, cols)

    def contains(self, row: int | np.ndarray, col: int | np.ndarray) -> np.ndarray:
        """Boolean mask: which (row, col) lie inside the grid."""
        r = np.asarray(row)
        c = np.asarray(col)
        return (r >= 0) & (r < self.height) & (c >= 0) & (c < self.width)


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """Log-odds occupancy over a :class:`GridGeometry`; ``observed`` marks cells ever updated."""

    geometry: GridGeometry
    log_odds: np.ndarray  # (H, W) float32, log(p / (1 - p)); exactly 0 where never observed
    observed: np.ndarray  # (H, W) bool, True where at least one beam has updated the cell

    def __post_init__(self) -> None:
        shape = self.geometry.shape
        if self.log_odds.shape != shape or self.observed.shape != shape:
            raise MapError(
                f"grid arrays {self.log_odds.shape} / {self.observed.shape} do not match the "
                f"geometry {shape} (height, width)"
            )
        if self.log_odds.dtype != np.float32 or self.observed.dtype != np.bool_:
            raise MapError(
                f"grid arrays must be float32 log-odds and bool observed, got "
                f"{self.log_odds.dtype} / {self.observed.dtype}"
            )

    @classmethod
    def empty(cls, geometry: GridGeometry) -> OccupancyGrid:
        return cls(
            geometry,
            np.zeros(geometry.shape, dtype=np.float32),
            np.zeros(geometry.shape, dtype=bool),
        )

    @classmethod
    def from_occupancy_values(cls, geometry: GridGeometry, values: np.ndarray) -> OccupancyGrid:
        """From nav_msgs-style int values (H, W), row 0 = lowest y: 0..100 occupancy percent,
        anything else unknown. Probabilities are clamped to [LOADED_P_MIN, LOADED_P_MAX]."""
        v = np.asarray(values)
        known = (v >= 0) & (v <= 100)
        p = np.clip(v.astype(np.float64) / 100.0, LOADED_P_MIN, LOADED_P_MAX)
        lo = np.where(known, np.log(p) - np.log1p(-p), 0.0).astype(np.float32)
        return cls(geometry, lo, known)

    def probability(self) -> np.ndarray:
        """(H, W) float32 P(occupied) in [0, 1]; 0.5 where never observed."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)

    def occupied_mask(self, occupied_thresh: float = 0.65) -> np.ndarray:
        """Observed cells with P(occupied) >= occupied_thresh (map.yaml semantics)."""
        return self.observed & (self.log_odds >= np.float32(logit(occupied_thresh)))

    def free_mask(self, free_thresh: float = 0.25) -> np.ndarray:
        """Observed cells with P(occupied) < free_thresh."""
        return self.observed & (self.log_odds < np.float32(logit(free_thresh)))

    def unknown_mask(self, occupied_thresh: float = 0.65, free_thresh: float = 0.25) -> np.ndarray:
        """Cells neither occupied nor free: never observed, or in between the thresholds."""
        return ~(self.occupied_mask(occupied_thresh) | self.free_mask(free_thresh))

    def trinary(self, occupied_thresh: float = 0.65, free_thresh: float = 0.25) -> np.ndarray:
        """(H, W) int8 nav_msgs values: 100 occupied, 0 free, -1 unknown."""
        if not 0.0 < free_thresh < occupied_thresh < 1.0:
            raise MapError(
                f"need 0 < free_thresh ({free_thresh}) < occupied_thresh ({occupied_thresh}) < 1"
            )
        out = np.full(self.geometry.shape, UNKNOWN, dtype=np.int8)
        out[self.free_mask(free_thresh)] = FREE
        out[self.occupied_mask(occupied_thresh)] = OCCUPIED
        return out


# --- scan geometry ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Rays:
    """One scan's beams in the map frame, split by what they do to the grid."""

    origin: np.ndarray  # (2,) [m] laser position
    ends: np.ndarray  # (M, 2) [m] where each used beam stops (hit or clearing length)
    is_hit: np.ndarray  # (M,) bool, True when the beam ends in a valid return


def _scan_rays(pose_xyyaw: np.ndarray, scan: LaserScan, max_laser_range: float) -> _Rays:
    """Classify beams per REP-117 and return their end points in the map frame."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    usable_max = min(scan.range_max, max_laser_range)  # [m]
    # NaN and below range_min (incl. -inf "too close") carry no information.
    is_hit = (r >= scan.range_min) & (r <= usable_max)
    no_return = r > usable_max  # +inf, or beyond what we trust / the sensor reports
    used = is_hit | no_return
    length = np.where(is_hit, r, usable_max)[used]  # [m]
    angle = pose_xyyaw[2] + scan.angles()[used]  # [rad] in the map frame
    origin = np.asarray(pose_xyyaw[:2], dtype=np.float64)
    ends = origin + length[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return _Rays(origin, ends, is_hit[used])


def scan_end_points(pose_xyyaw: np.ndarray, scan: LaserScan, max_laser_range: float) -> np.ndarray:
    """(K, 2) [m] map-frame end points of ``scan``'s valid returns from ``pose_xyyaw``."""
    rays = _scan_rays(np.asarray(pose_xyyaw, dtype=np.float64), scan, max_laser_range)
    return rays.ends[rays.is_hit]


def bounds_of_scans(
    poses_xyyaw: np.ndarray, scans: Sequence[LaserScan], max_range: float
) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) [m] of laser origins and every used beam end, no-return beams
    counted at their clearing length ``min(range_max, max_range)``."""
    poses = _check_poses(poses_xyyaw, scans)
    if len(scans) == 0:
        raise MapError("cannot size a grid from zero scans")
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for pose, scan in zip(poses, scans, strict=True):
        rays = _scan_rays(pose, scan, max_range)
        pts = np.vstack([rays.origin[None, :], rays.ends])
        lo = np.minimum(lo, pts.min(axis=0))
        hi = np.maximum(hi, pts.max(axis=0))
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _check_poses(poses_xyyaw: np.ndarray, scans: Sequence[LaserScan]) -> np.ndarray:
    poses = np.asarray(poses_xyyaw, dtype=np.float64).reshape(-1, 3)
    if len(poses) != len(scans):
        raise MapError(f"{len(poses)} poses for {len(scans)} scans; need one laser pose per scan")
    if not np.all(np.isfinite(poses)):
        raise MapError("laser poses must be finite")
    return poses


# --- integration ------------------------------------------------------------------------------


def integrate_scans(
    geometry: GridGeometry,
    poses_xyyaw: np.ndarray,
    scans: Sequence[LaserScan],
    config: MapperConfig,
    initial: OccupancyGrid | None = None,
) -> OccupancyGrid:
    """Integrate scans taken from laser poses ``(K, 3)`` [m, m, rad] in the map frame.

    Starts from ``initial`` (same geometry; not modified) or an empty grid and returns a new
    grid. Beams leaving the grid are rasterised up to its border; end cells outside are dropped.
    """
    poses = _check_poses(poses_xyyaw, scans)
    if initial is not None and initial.geometry != geometry:
        raise MapError(f"initial grid geometry {initial.geometry} differs from {geometry}")
    delta_lut = np.zeros((1, 256), dtype=np.float32)  # log-odds increment per cell label
    delta_lut[0, _FREE] = logit(config.prob_miss)
    delta_lut[0, _HIT] = logit(config.prob_hit)
    l_min = float(np.float32(logit(config.clamping_thres_min)))
    l_max = float(np.float32(logit(config.clamping_thres_max)))
    # The initial grid is brought into this config's clamping band first, so the per-scan clamp
    # of a region never changes cells the scan did not touch.
    log_odds = (
        np.clip(initial.log_odds, l_min, l_max)
        if initial
        else np.zeros(geometry.shape, dtype=np.float32)
    )
    observed = (
        initial.observed.astype(np.uint8) if initial else np.zeros(geometry.shape, dtype=np.uint8)
    )
    for pose, scan in zip(poses, scans, strict=True):
        _integrate_one(
            geometry,
            log_odds,
            observed,
            _scan_rays(pose, scan, config.max_laser_range),
            delta_lut,
            l_min,
            l_max,
        )
    return OccupancyGrid(geometry, log_odds, observed.astype(bool))


def _integrate_one(
    geometry: GridGeometry,
    log_odds: np.ndarray,
    observed: np.ndarray,
    rays: _Rays,
    delta_lut: np.ndarray,
    l_min: float,
    l_max: float,
) -> None:
    """One scan's update of ``log_odds`` / ``observed`` in place (caller-owned arrays)."""
    if len(rays.ends) == 0:
        return
    # 1. Cells of the laser and of every beam end; the scan's bounding box clipped to the grid.
    r0, c0 = geometry.world_to_cell(rays.origin[0], rays.origin[1])
    rows, cols = geometry.world_to_cell(rays.ends[:, 0], rays.ends[:, 1])
    top = max(int(min(r0, rows.min())), 0)
    bottom = min(int(max(r0, rows.max())), geometry.height - 1)
    left = max(int(min(c0, cols.min())), 0)
    right = min(int(max(c0, cols.max())), geometry.width - 1)
    if top > bottom or left > right:
        return  # the whole scan lies outside the grid
    roi = (slice(top, bottom + 1), slice(left, right + 1))
    h, w = bottom - top + 1, right - left + 1

    # 2. Label the ROI: every beam from the laser cell to its end cell is free (x = col, y = row;
    #    OpenCV clips segments that leave the ROI), then end cells of returns overwrite with hit,
    #    so each cell gets exactly one label per scan and the endpoint wins.
    segments = np.empty((len(rows), 2, 2), dtype=np.int32)
    segments[:, 0, 0] = c0 - left
    segments[:, 0, 1] = r0 - top
    segments[:, 1, 0] = cols - left
    segments[:, 1, 1] = rows - top
    label = np.zeros((h, w), dtype=np.uint8)
    # An (M, 2, 2) array is M two-point polylines to OpenCV (its stubs only know lists).
    cv2.polylines(label, segments, False, _FREE, 1, cv2.LINE_4)  # type: ignore[call-overload]
    hr, hc = rows[rays.is_hit] - top, cols[rays.is_hit] - left
    inside = (hr >= 0) & (hr < h) & (hc >= 0) & (hc < w)
    label[hr[inside], hc[inside]] = _HIT

    # 3. label -> log-odds increment, add, clamp; the ROI slices are views updated in place.
    #    (A LUT + unmasked add measured faster than two masked adds.)
    lo_roi = log_odds[roi]
    cv2.add(lo_roi, cv2.LUT(label, delta_lut), dst=lo_roi)
    cv2.min(lo_roi, l_max, dst=lo_roi)  # type: ignore[call-overload]  # scalar src2 is fine
    cv2.max(lo_roi, l_min, dst=lo_roi)  # type: ignore[call-overload]
    obs_roi = observed[roi]
    cv2.bitwise_or(obs_roi, label, dst=obs_roi)


__all__ = [
    "FREE",
    "MAX_GRID_CELLS",
    "LOADED_P_MAX",
    "LOADED_P_MIN",
    "OCCUPIED",
    "UNKNOWN",
    "GridGeometry",
    "OccupancyGrid",
    "bounds_of_scans",
    "scan_end_points",
    "check_grid_size",
    "integrate_scans",
    "logit",
]


def warp_to_geometry(
    values: np.ndarray,
    src: GridGeometry,
    T_dst_src: tuple[float, float, float] | np.ndarray,
    dst: GridGeometry,
    nearest: bool = True,
    fill: float = 0.0,
) -> np.ndarray:
    """Resample a (H, W) array laid on ``src`` (row 0 = lowest y) onto ``dst``, where the frame
    of ``src`` has pose ``T_dst_src`` (x [m], y [m], yaw [rad]) in that of ``dst``: one
    ``cv2.warpAffine`` with the inverse map (dst cell -> src cell), ``fill`` outside ``src``."""
    x, y, yaw = (float(v) for v in T_dst_src)
    c, s = math.cos(yaw), math.sin(yaw)
    # dst cell (col, row) -> dst metres -> src metres (T^-1) -> src cell; all affine.
    to_dst_m = np.array(
        [
            [dst.resolution, 0.0, dst.origin_x + 0.5 * dst.resolution],
            [0.0, dst.resolution, dst.origin_y + 0.5 * dst.resolution],
            [0.0, 0.0, 1.0],
        ]
    )
    src_from_dst = np.array([[c, s, -(c * x + s * y)], [-s, c, s * x - c * y], [0.0, 0.0, 1.0]])
    to_src_cell = np.array(
        [
            [1.0 / src.resolution, 0.0, -src.origin_x / src.resolution - 0.5],
            [0.0, 1.0 / src.resolution, -src.origin_y / src.resolution - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    m = (to_src_cell @ src_from_dst @ to_dst_m)[:2]
    arr = np.asarray(values)
    work = arr.view(np.uint8) if arr.dtype == np.bool_ else arr
    flags = (cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP
    out = cv2.warpAffine(
        work,
        m,
        (dst.width, dst.height),
        flags=flags,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=fill,
    )
    return out.view(np.bool_) if arr.dtype == np.bool_ else out
