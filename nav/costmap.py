"""Layered 2D costmap with Nav2 ``nav2_costmap_2d`` semantics and cost values.

Layers, combined in Nav2's order into the master grid by :meth:`Costmap.master`:

1. **Static**: the map's nav_msgs values through ``interpretValue`` (unknown, lethal, free or
   scaled); it overwrites the master.
2. **Obstacle**: live scans clear the cells their beams cross, then mark return end points
   ``LETHAL``; combined with ``updateWithMax``, so clearing removes only what this layer marked.
   ``inf_is_valid`` (our default true) lets no-return beams clear too.
3. **Inflation**: Nav2's ``computeCost`` over the Euclidean distance to the nearest lethal cell
   (``INSCRIBED`` inside the inscribed radius, exponential decay to ``inflation_radius``).
4. **Keepout filter**: mask values 0..100 scaled to costs, resampled by world coordinates; with
   ``inflate_keepout`` also combined before inflation so the whole footprint stays out.

Deliberate deviations from Nav2 (a non-overlapping keepout mask is an error, the inflation
radius compared in metres, out-of-map cost ``LETHAL``) and the exact rules of each layer:
docs/design/costmap.md. Arrays follow :mod:`slam.occupancy_grid`: ``(height, width)``, row 0 =
lowest y.
"""

from __future__ import annotations

import logging
import math
import os

import cv2
import numpy as np

from nav.config import LETHAL_OBSTACLE, CostmapConfig
from nav.config import NO_INFORMATION as _NO_INFORMATION
from sensors.types import LaserScan, MapError, Pose2
from slam.map_bundle import load_map_yaml
from slam.occupancy_grid import OCCUPIED, UNKNOWN, GridGeometry, OccupancyGrid

log = logging.getLogger(__name__)

# costmap_2d cell values.
FREE = 0
INSCRIBED = 253
LETHAL = LETHAL_OBSTACLE
NO_INFORMATION = _NO_INFORMATION

# Slack on metric radius comparisons, so a distance of exactly k cells compares as k*res does
# on paper (0.05 * 11 vs 0.55 differ in the last bit).
_RADIUS_EPS = 1e-9  # [m]


# --- static layer --------------------------------------------------------------------------------


def static_costs(values: np.ndarray, config: CostmapConfig) -> np.ndarray:
    """nav_msgs occupancy values (H, W) (0..100, -1 unknown) -> (H, W) uint8 costs, Nav2
    ``StaticLayer::interpretValue`` applied through a 256-entry lookup table."""
    v = np.arange(256)  # every byte a value can be, -1 reads as 255 like the C++ unsigned char
    lethal = config.lethal_cost_threshold
    if config.trinary_costmap:
        lut = np.full(256, FREE, dtype=np.uint8)
    else:
        # Nav2 scales by value / lethal_threshold * LETHAL and truncates.
        lut = (np.minimum(v, max(lethal, 1)) / max(lethal, 1) * LETHAL).astype(np.uint8)
    lut[v >= lethal] = LETHAL
    lut[v > OCCUPIED] = NO_INFORMATION  # not an occupancy: treat as unknown, never as lethal
    unknown = config.unknown_cost_value
    lut[unknown] = NO_INFORMATION if config.track_unknown_space else FREE
    vals = np.asarray(values)
    if vals.dtype != np.uint8:
        vals = vals.astype(np.int16).astype(np.uint8)  # two's complement: -1 -> 255
    return lut[vals]


def grid_values(
    grid: OccupancyGrid,
    config: CostmapConfig,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
) -> np.ndarray:
    """An :class:`OccupancyGrid` as nav_msgs int8 values for :func:`static_costs`.

    Trinary costmaps use the grid's trinary classes (map.yaml thresholds). Otherwise observed
    cells give ``round(100 p)`` with occupied cells forced to 100, since a loaded grid's
    probabilities are clamped below 1 and would never reach a lethal threshold of 100.
    """
    if config.trinary_costmap:
        return grid.trinary(occupied_thresh, free_thresh)
    percent = np.rint(grid.probability() * 100.0).astype(np.int8)
    percent[grid.occupied_mask(occupied_thresh)] = OCCUPIED
    percent[~grid.observed] = UNKNOWN
    return percent


# --- obstacle layer ------------------------------------------------------------------------------


Box = tuple[int, int, int, int]  # (row_min, row_max, col_min, col_max), inclusive cell bounds


def raytrace_scan(
    obstacles: np.ndarray,
    geometry: GridGeometry,
    scan: LaserScan,
    laser_pose: Pose2,
    config: CostmapConfig,
) -> Box | None:
    """Clear then mark one scan into the obstacle layer ``obstacles`` (H, W) uint8, in place.

    REP-117 beams: NaN and below ``range_min`` are ignored; ``+inf`` / beyond ``range_max`` are
    no-return beams that clear (only with ``inf_is_valid``) up to ``raytrace_max_range``.
    Returns the box of cells the scan may have changed (Nav2's ``updateBounds``), or None.
    """
    r = np.asarray(scan.ranges, dtype=np.float64)
    is_hit = (r >= scan.range_min) & (r <= scan.range_max)
    no_return = (r > scan.range_max) & config.inf_is_valid
    angles = laser_pose.yaw + scan.angles()
    direction = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    origin = np.array([laser_pose.x, laser_pose.y])

    # 1. Cells: clearing segments from raytrace_min_range to min(range, raytrace_max_range),
    #    and return end points within [obstacle_min_range, obstacle_max_range) to mark.
    clear = is_hit | no_return
    stop = np.minimum(np.where(is_hit, r, np.inf)[clear], config.raytrace_max_range)  # [m]
    keep = stop > config.raytrace_min_range
    d = direction[clear][keep]
    p0 = origin + config.raytrace_min_range * d
    p1 = origin + stop[keep, None] * d
    r0, c0 = geometry.world_to_cell(p0[:, 0], p0[:, 1])
    r1, c1 = geometry.world_to_cell(p1[:, 0], p1[:, 1])
    mark = is_hit & (r >= config.obstacle_min_range) & (r < config.obstacle_max_range)
    ends = origin + r[mark, None] * direction[mark]
    rm, cm = geometry.world_to_cell(ends[:, 0], ends[:, 1])
    rows = np.concatenate([r0, r1, rm])
    cols = np.concatenate([c0, c1, cm])
    if rows.size == 0:
        return None
    top, bottom = max(int(rows.min()), 0), min(int(rows.max()), geometry.height - 1)
    left, right = max(int(cols.min()), 0), min(int(cols.max()), geometry.width - 1)
    if top > bottom or left > right:
        return None  # the whole scan lies outside the map
    roi = obstacles[top : bottom + 1, left : right + 1]  # a view: updated in place

    # 2. Clearing, rasterised in C (4-connected, like the occupancy grid) in the scan's box.
    if r0.size:
        segments = np.empty((r0.size, 2, 2), dtype=np.int32)
        segments[:, 0, 0], segments[:, 0, 1] = c0 - left, r0 - top
        segments[:, 1, 0], segments[:, 1, 1] = c1 - left, r1 - top
        label = np.zeros(roi.shape, dtype=np.uint8)
        # An (M, 2, 2) int32 array is M two-point polylines; OpenCV clips them to the image.
        cv2.polylines(label, segments, False, 1, 1, cv2.LINE_4)  # type: ignore[call-overload]
        roi[label.view(bool)] = FREE

    # 3. Marking after clearing, so an end point wins over a ray crossing it.
    inside = geometry.contains(rm, cm)
    obstacles[rm[inside], cm[inside]] = LETHAL
    return top, bottom, left, right


def combine_max(master: np.ndarray, layer: np.ndarray) -> None:
    """Nav2 ``updateWithMax`` in place: skip the layer's unknown cells; a known layer cell wins
    when the master is unknown or lower."""
    take = (layer != NO_INFORMATION) & ((master == NO_INFORMATION) | (master < layer))
    np.copyto(master, layer, where=take)


# --- inflation layer -----------------------------------------------------------------------------


def inscribed_radius(config: CostmapConfig) -> float:
    """[m] radius of the padded circular footprint."""
    return config.robot_radius + config.footprint_padding


def inflation_cost(distance_m: np.ndarray | float, config: CostmapConfig) -> np.ndarray:
    """Nav2 ``InflationLayer::computeCost`` of distances [m] to the nearest obstacle (uint8).

    Distances beyond ``inflation_radius`` get ``FREE`` (the layer leaves those cells alone).
    """
    d = np.asarray(distance_m, dtype=np.float64)
    r_in = inscribed_radius(config)
    decay = (INSCRIBED - 1) * np.exp(-config.cost_scaling_factor * (d - r_in))
    cost = np.where(d <= config.inflation_radius + _RADIUS_EPS, decay, FREE)
    cost = np.where(d <= r_in + _RADIUS_EPS, INSCRIBED, cost)
    cost = np.where(d == 0.0, LETHAL, cost)
    return np.asarray(cost).astype(np.uint8)  # C++ truncates to unsigned char


def inflate(master: np.ndarray, resolution: float, config: CostmapConfig) -> None:
    """Apply the inflation layer to ``master`` (H, W) uint8 in place."""
    if config.inflation_radius <= 0.0:
        return
    source = master == LETHAL
    if config.inflate_around_unknown:
        source |= master == NO_INFORMATION
    if not np.any(source):
        return
    # 1. Exact Euclidean distance [cells] from every cell centre to the nearest source centre;
    #    its square is an integer, which indexes a cost table (the exp runs once per distance).
    dist = cv2.distanceTransform((~source).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    limit = math.floor(((config.inflation_radius + _RADIUS_EPS) / resolution) ** 2)
    table = np.zeros(limit + 2, dtype=np.uint8)  # the last entry: out of reach
    table[: limit + 1] = inflation_cost(np.sqrt(np.arange(limit + 1)) * resolution, config)
    sq = cv2.multiply(dist, dist)
    np.minimum(sq, np.float32(limit + 1), out=sq)
    cost = table[(sq + np.float32(0.5)).astype(np.intp)]
    # 2. Nav2 update: max with the old cost, but unknown cells only take strong enough costs.
    unknown = master == NO_INFORMATION
    min_for_unknown = FREE + 1 if config.inflate_unknown else INSCRIBED
    np.maximum(master, cost, out=master)
    np.copyto(master, cost, where=unknown & (cost >= min_for_unknown))


# --- keepout filter ------------------------------------------------------------------------------


def mask_costs(values: np.ndarray) -> np.ndarray:
    """Filter-mask nav_msgs values (0..100, -1 unknown) -> costs, as Nav2's ``Costmap2D`` built
    from an OccupancyGrid: ``round(v * LETHAL / 100)``; anything else -> ``NO_INFORMATION``."""
    v = np.arange(256)
    lut = np.full(256, NO_INFORMATION, dtype=np.uint8)
    ok = v <= OCCUPIED
    lut[ok] = np.rint(v[ok] * LETHAL / OCCUPIED).astype(np.uint8)
    return lut[np.asarray(values).astype(np.int16).astype(np.uint8)]


def resample_nearest(
    source: np.ndarray, source_geometry: GridGeometry, target: GridGeometry, fill: int
) -> tuple[np.ndarray, int]:
    """``source`` (on ``source_geometry``) sampled at every ``target`` cell centre (nearest
    cell, axis-aligned frames), ``fill`` outside; also how many target cells it covers."""
    xs, _ = target.cell_to_world(0, np.arange(target.width))
    _, ys = target.cell_to_world(np.arange(target.height), 0)
    _, cols = source_geometry.world_to_cell(xs, 0.0)
    rows, _ = source_geometry.world_to_cell(0.0, ys)
    col_ok = (cols >= 0) & (cols < source_geometry.width)
    row_ok = (rows >= 0) & (rows < source_geometry.height)
    out = np.full(target.shape, fill, dtype=source.dtype)
    if np.any(row_ok) and np.any(col_ok):
        out[np.ix_(row_ok, col_ok)] = source[np.ix_(rows[row_ok], cols[col_ok])]
    return out, int(row_ok.sum()) * int(col_ok.sum())


# --- the costmap ---------------------------------------------------------------------------------


class Costmap:
    """Static + obstacle + inflation layers and a keepout filter over one :class:`GridGeometry`.

    A thin shell: layers are arrays, the kernels above do the work, :meth:`master` caches the
    combined grid until a layer changes.
    """

    def __init__(
        self,
        geometry: GridGeometry,
        config: CostmapConfig,
        static_values: np.ndarray | None = None,
    ) -> None:
        self.geometry = geometry
        self.config = config
        unknown = NO_INFORMATION if config.track_unknown_space else FREE
        if static_values is None:
            self._static = np.full(geometry.shape, unknown, dtype=np.uint8)
        else:
            if np.shape(static_values) != geometry.shape:
                raise MapError(
                    f"static map values {np.shape(static_values)} do not match the "
                    f"geometry {geometry.shape} (height, width)"
                )
            self._static = static_costs(static_values, config)
        self._obstacles = np.full(geometry.shape, unknown, dtype=np.uint8)
        self._keepout: np.ndarray | None = None
        self._master: np.ndarray | None = None  # combined costs, None = recompute all
        self._dirty: Box | None = None  # cells changed since the master was last brought up to date
        self.revision = 0  # bumped by every layer update: a consumer can tell what changed

    # 1. Construction from maps.
    @classmethod
    def from_grid(
        cls,
        grid: OccupancyGrid,
        config: CostmapConfig,
        occupied_thresh: float = 0.65,
        free_thresh: float = 0.25,
    ) -> Costmap:
        """Static layer from a grid (the map's geometry wins over ``config.resolution``)."""
        values = grid_values(grid, config, occupied_thresh, free_thresh)
        return cls(grid.geometry, config, values)

    @classmethod
    def from_map_yaml(cls, path: str | os.PathLike[str], config: CostmapConfig) -> Costmap:
        """Static layer from a Nav2 map.yaml + image."""
        return cls.from_grid(load_map_yaml(path), config)

    # 2. Layer updates.
    def update_scan(self, scan: LaserScan, laser_pose: Pose2) -> None:
        """Clear and mark one scan taken at ``laser_pose`` (laser frame in the map frame)."""
        box = raytrace_scan(self._obstacles, self.geometry, scan, laser_pose, self.config)
        self.revision += 1
        if box is not None and self._master is not None:
            d = self._dirty or box
            self._dirty = (
                min(d[0], box[0]),
                max(d[1], box[1]),
                min(d[2], box[2]),
                max(d[3], box[3]),
            )

    def obstacle_count(self) -> int:
        """Cells the obstacle layer currently marks lethal."""
        return int(np.count_nonzero(self._obstacles == LETHAL))

    def reset_obstacles(self) -> None:
        """Forget everything the obstacle layer has seen."""
        self._obstacles.fill(NO_INFORMATION if self.config.track_unknown_space else FREE)
        self._master = None
        self.revision += 1

    def set_keepout(
        self,
        mask: OccupancyGrid | tuple[GridGeometry, np.ndarray],
        occupied_thresh: float = 0.65,
        free_thresh: float = 0.25,
    ) -> None:
        """Install a keepout mask: a grid (its trinary classes) or ``(geometry, values)`` with
        nav_msgs values (scale-mode masks keep their intermediate values this way).

        Raises :class:`MapError` when the mask covers no cell of this costmap.
        """
        if isinstance(mask, OccupancyGrid):
            geometry, values = mask.geometry, mask.trinary(occupied_thresh, free_thresh)
        else:
            geometry, values = mask
            if np.shape(values) != geometry.shape:
                raise MapError(
                    f"keepout mask values {np.shape(values)} do not match its "
                    f"geometry {geometry.shape} (height, width)"
                )
        costs, covered = resample_nearest(
            mask_costs(values), geometry, self.geometry, NO_INFORMATION
        )
        if covered == 0:
            g, m = self.geometry, geometry
            raise MapError(
                f"keepout mask [{m.origin_x}, {m.origin_x + m.width * m.resolution}] x "
                f"[{m.origin_y}, {m.origin_y + m.height * m.resolution}] m does not overlap the "
                f"costmap [{g.origin_x}, {g.origin_x + g.width * g.resolution}] x "
                f"[{g.origin_y}, {g.origin_y + g.height * g.resolution}] m; is it in the same "
                f"map frame?"
            )
        if covered < self.geometry.width * self.geometry.height:
            log.debug("keepout mask covers %d of %d costmap cells", covered, costs.size)
        self._keepout = costs
        self._master = None
        self.revision += 1

    def set_keepout_yaml(self, path: str | os.PathLike[str]) -> None:
        """Install a keepout mask from a Nav2 filter-mask map.yaml + image."""
        self.set_keepout(load_map_yaml(path))

    # 3. The combined grid.
    def master(self) -> np.ndarray:
        """(H, W) uint8 combined costs: a read-only view that later updates change in place
        (``copy()`` it to keep a snapshot).

        Like Nav2, only the window the obstacle layer touched since the last call, grown by the
        inflation radius, is recombined; sources up to one more radius away are read.
        """
        if self._master is None:
            self._master = self._combine(0, self.geometry.height - 1, 0, self.geometry.width - 1)
            self._dirty = None
        elif self._dirty is not None:
            top, bottom, left, right = self._dirty
            reach = math.ceil(self.config.inflation_radius / self.geometry.resolution) + 1
            h, w = self.geometry.shape
            # Window whose costs may change, and the larger one whose sources reach into it.
            wt, wb = max(top - reach, 0), min(bottom + reach, h - 1)
            wl, wr = max(left - reach, 0), min(right + reach, w - 1)
            st, sb = max(wt - reach, 0), min(wb + reach, h - 1)
            sl, sr = max(wl - reach, 0), min(wr + reach, w - 1)
            sub = self._combine(st, sb, sl, sr)
            self._master[wt : wb + 1, wl : wr + 1] = sub[
                wt - st : wb - st + 1, wl - sl : wr - sl + 1
            ]
            self._dirty = None
        view = self._master.view()
        view.flags.writeable = False
        return view

    def _combine(self, top: int, bottom: int, left: int, right: int) -> np.ndarray:
        """Master costs of the inclusive cell box, from the layers inside it alone."""
        box = (slice(top, bottom + 1), slice(left, right + 1))
        master = self._static[box].copy()  # static: updateWithTrueOverwrite
        combine_max(master, self._obstacles[box])  # obstacle: updateWithMax
        keepout = None if self._keepout is None else self._keepout[box]
        if keepout is not None and self.config.inflate_keepout:
            combine_max(master, keepout)  # inflated like an obstacle: the footprint stays out
        inflate(master, self.geometry.resolution, self.config)
        if keepout is not None:  # Nav2: filters run after the layers
            combine_max(master, keepout)
        return master

    # 4. Queries.
    def world_to_cell(
        self, x: float | np.ndarray, y: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World [m] -> (row, col) of the containing cell (may be out of bounds)."""
        return self.geometry.world_to_cell(x, y)

    def cell_to_world(
        self, row: int | np.ndarray, col: int | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) -> world (x, y) [m] of the cell centre."""
        return self.geometry.cell_to_world(row, col)

    def cost_at(self, x: float | np.ndarray, y: float | np.ndarray) -> np.ndarray:
        """Master cost at world points [m]; ``LETHAL`` outside the map."""
        row, col = self.geometry.world_to_cell(x, y)
        inside = self.geometry.contains(row, col)
        master = self.master()
        rr = np.where(inside, row, 0)
        cc = np.where(inside, col, 0)
        return np.where(inside, master[rr, cc], np.uint8(LETHAL)).astype(np.uint8)

    def is_free(
        self, x: float | np.ndarray, y: float | np.ndarray, allow_unknown: bool = False
    ) -> np.ndarray:
        """Whether the robot centre may stand at world points: cost below ``INSCRIBED``
        (unknown counts as free only with ``allow_unknown``)."""
        cost = self.cost_at(x, y)
        ok = cost < INSCRIBED
        if allow_unknown:
            ok |= cost == NO_INFORMATION
        return ok


__all__ = [
    "FREE",
    "INSCRIBED",
    "LETHAL",
    "NO_INFORMATION",
    "Box",
    "Costmap",
    "combine_max",
    "grid_values",
    "inflate",
    "inflation_cost",
    "inscribed_radius",
    "mask_costs",
    "raytrace_scan",
    "resample_nearest",
    "static_costs",
]
