"""Global path planning on a Nav2 costmap: cost-aware grid search, smoothing, straight lines.

Costmap semantics (nav2_costmap_2d): a ``(H, W)`` uint8 array, row 0 = lowest y, on a
:class:`slam.occupancy_grid.GridGeometry`; ``FREE_SPACE`` 0 .. ``INSCRIBED_INFLATED_OBSTACLE``
253, ``LETHAL_OBSTACLE`` 254, ``NO_INFORMATION`` 255.

Planning (:meth:`GridPlanner.plan`), NavFn / global_planner style:

1. cells at or above ``lethal_cost`` are impassable (unknown passable with ``allow_unknown``);
   a start inside the inflated band may leave it (NavFn's ``clearRobotCell``), one on a wall
   is refused;
2. entering a cell costs ``(neutral_cost + cost_factor * cost) * |step|`` on the 8-connected
   grid, no diagonal squeezing past obstacle cells;
3. Dijkstra (default) or A* run in C through :func:`scipy.sparse.csgraph.dijkstra`, with
   cached graph topology and edge weights and early termination emulated by growing limits;
4. NavFn's goal tolerance: the reachable cell nearest an unreachable goal;
5. nav2_smoother's SimpleSmoother, repaired where it would clip an obstacle, resampled to one
   point per cell with yaw along the path.

Failures are results (``success=False`` with a reason), never exceptions. The details and the
measurements behind the search's design: docs/design/planner.md.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.linalg import solve_banded
from scipy.sparse import csr_array
from scipy.sparse.csgraph import dijkstra

from nav.config import LETHAL_OBSTACLE, NO_INFORMATION, PlannerConfig
from slam.occupancy_grid import GridGeometry

log = logging.getLogger(__name__)

FREE_SPACE = 0
INSCRIBED_INFLATED_OBSTACLE = 253

SQRT2 = math.sqrt(2.0)
# 8-connected steps (drow, dcol) in increasing flat offset, so CSR rows come out sorted.
_STEPS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
FIRST_LIMIT_RATIO = 1.5  # first search limit as a multiple of the goal's cost lower bound
LIMIT_GROWTH = 2.0  # factor by which the search limit grows when the goal was not yet settled
MAX_LIMITED_PASSES = 2  # after this many bounded passes miss the goal, search without a limit
# Straight-line collision checking samples the segment this many times per cell.
LINE_SAMPLES_PER_CELL = 2.0
SEGMENT_SAMPLES = 5  # samples per path segment (<= sqrt(2) cells) when checking smoothed paths
MAX_REPAIRS = 20  # rounds of putting raw points back where a smoothed segment clips a cell


@dataclass(frozen=True, eq=False)
class PlanResult:
    """Outcome of a planning request; on failure ``reason`` says why and the arrays are empty."""

    success: bool
    reason: str  # "" on success
    poses: np.ndarray = field(  # (N, 3) float64 x [m], y [m], yaw [rad] in the map frame
        default_factory=lambda: np.zeros((0, 3))
    )
    cells: np.ndarray = field(  # (M, 2) int64 (row, col) of the raw grid path, start first
        default_factory=lambda: np.zeros((0, 2), dtype=np.int64)
    )
    cost: float = math.inf  # accumulated traversal cost of the grid path [neutral_cost units]
    goal_offset_m: float = 0.0  # [m] distance from the requested goal to the path end
    settled_cells: int = 0  # cells the search settled, summed over its passes

    @property
    def length_m(self) -> float:
        """[m] arc length of ``poses``."""
        if len(self.poses) < 2:
            return 0.0
        return float(np.hypot(*np.diff(self.poses[:, :2], axis=0).T).sum())


def _fail(reason: str) -> PlanResult:
    return PlanResult(success=False, reason=reason)


# --- cost kernels -----------------------------------------------------------------------------


def passable_mask(costmap: np.ndarray, config: PlannerConfig) -> np.ndarray:
    """(H, W) bool: cells the planner may enter."""
    unknown = costmap == NO_INFORMATION
    blocked = (costmap >= config.lethal_cost) & ~unknown
    if not config.allow_unknown:
        blocked |= unknown
    return ~blocked


def cell_traversal_cost(
    costmap: np.ndarray, config: PlannerConfig, enterable: np.ndarray | None = None
) -> np.ndarray:
    """(H, W) float64 cost of entering each cell per unit step; +inf where impassable, except
    in ``enterable`` (H, W) bool cells (a start's way out), costed as ``lethal_cost - 1``."""
    c = costmap.astype(np.float64)
    c[costmap == NO_INFORMATION] = config.lethal_cost - 1  # (impassable unless allowed)
    blocked = ~passable_mask(costmap, config)
    if enterable is not None:
        np.minimum(c, config.lethal_cost - 1, out=c, where=enterable)
        blocked &= ~enterable
    cost = config.neutral_cost + config.cost_factor * c
    cost[blocked] = np.inf
    return cost


def octile_distance(rows: np.ndarray, cols: np.ndarray, row: int, col: int) -> np.ndarray:
    """[cells] 8-connected shortest distance on an empty grid from (rows, cols) to (row, col)."""
    dr = np.abs(rows - row)
    dc = np.abs(cols - col)
    return np.maximum(dr, dc) + (SQRT2 - 1.0) * np.minimum(dr, dc)


# --- graph search -----------------------------------------------------------------------------


class _PaddedGraph:
    """CSR topology of the 8-connected grid padded by one impassable cell on each side.

    With the border every interior node has all 8 neighbours at the constant flat offsets
    ``dr * (W + 2) + dc``, so the edge weights of one step direction are one array slice.
    Node ``i`` of the padded grid owns edges ``8 i .. 8 i + 7`` in ``_STEPS`` order. The CSR
    matrix and its (n, 8) weight buffer are built once; a plan only refills the buffer (a fresh
    10 MB array per plan costs more in page faults than the copy into it).
    """

    def __init__(self, shape: tuple[int, int]) -> None:
        h, w = shape
        self.shape = shape
        self.padded = (h + 2, w + 2)
        self.n = (h + 2) * (w + 2)
        self.offsets = np.array([dr * (w + 2) + dc for dr, dc in _STEPS], dtype=np.int64)
        self.lengths = np.array([math.hypot(dr, dc) for dr, dc in _STEPS])
        # Out-of-range neighbours of border nodes point at the node itself (weight inf).
        nodes = np.arange(self.n, dtype=np.int64)
        dst = nodes[:, None] + self.offsets[None, :]
        dst = np.where((dst >= 0) & (dst < self.n), dst, nodes[:, None])
        self.indices = dst.ravel().astype(np.int32)
        self.indptr = np.arange(0, 8 * self.n + 1, 8, dtype=np.int32)
        self.margin = w + 3  # largest |offset|
        self.rows, self.cols = np.divmod(nodes, w + 2)
        self.weights = np.full((self.n, 8), np.inf)  # node-major edge weights of the CSR
        self._reduced = np.empty((8, self.n))  # direction-major scratch for A*'s weights
        self.csr = csr_array(
            (self.weights.reshape(-1), self.indices, self.indptr), shape=(self.n, self.n)
        )
        self.csr.data = self.weights.reshape(-1)  # a view: refilling the buffer updates it
        self.loaded: object = None  # token of what the buffer holds

    def pad(self, a: np.ndarray, fill: float) -> np.ndarray:
        """Flat padded copy of ``a`` with ``margin`` extra ``fill`` entries on each side."""
        p = np.full(self.padded, fill, dtype=np.result_type(a, type(fill)))
        p[1:-1, 1:-1] = a
        edge = np.full(self.margin, fill, dtype=p.dtype)
        return np.concatenate([edge, p.ravel(), edge])

    def shifted(self, flat_ext: np.ndarray, k: int) -> np.ndarray:
        """Value at the step-``k`` neighbour of every node (a slice, no gather)."""
        s = self.margin + int(self.offsets[k])
        return flat_ext[s : s + self.n]

    def node(self, row: int, col: int) -> int:
        return (row + 1) * (self.padded[1]) + col + 1

    def cell(self, node: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, c = np.divmod(node, self.padded[1])
        return r - 1, c - 1

    def heuristic(self, goal: tuple[int, int], neutral_cost: float) -> np.ndarray:
        """(n,) ``neutral_cost * octile(v, goal)``, from one row and one column vector."""
        rows = np.arange(self.padded[0])[:, None]
        cols = np.arange(self.padded[1])[None, :]
        return (neutral_cost * octile_distance(rows, cols, goal[0] + 1, goal[1] + 1)).reshape(-1)

    def _weights(
        self, step_cost: np.ndarray, m: int, take: Callable[[np.ndarray, int], np.ndarray]
    ) -> np.ndarray:
        """(8, m) edge weights of m nodes: entering cost times step length, +inf where refused;
        ``take(flat_ext, k)`` gives the step-``k`` neighbour's value for each of them. A
        diagonal is refused when it cuts past an impassable cell."""
        ext = self.pad(step_cost, np.inf)
        blocked = np.isinf(ext)
        data = np.empty((8, m))
        for k, (dr, dc) in enumerate(_STEPS):
            np.multiply(self.lengths[k], take(ext, k), out=data[k])
            if dr and dc:
                # The two orthogonal cells the diagonal passes between must be passable.
                cut = take(blocked, _STEPS.index((dr, 0))) | take(blocked, _STEPS.index((0, dc)))
                np.copyto(data[k], np.inf, where=cut)
        return data

    def base_weights(self, step_cost: np.ndarray, escape: np.ndarray | None = None) -> np.ndarray:
        """(8, n) direction-major edge weights of every node (array slices, no gather).
        ``escape`` (H, W) bool marks impassable cells made enterable for leaving the start:
        they may only be entered from one another (and the start), never re-entered from
        passable space."""
        data = self._weights(step_cost, self.n, self.shifted)
        if escape is not None:
            esc_ext = self.pad(escape, False)
            inner = esc_ext[self.margin : self.margin + self.n]
            for k in range(8):
                np.copyto(data[k], np.inf, where=self.shifted(esc_ext, k) & ~inner)
        return data

    def node_weights(self, step_cost: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """(8, m) columns of :meth:`base_weights` (without escape) for the padded ``nodes``."""
        at = nodes + self.margin
        return self._weights(
            step_cost, len(nodes), lambda flat_ext, k: flat_ext[at + self.offsets[k]]
        )

    def load(self, base: np.ndarray, heuristic: np.ndarray | None, token: object) -> None:
        """Fill the CSR weights from (8, n) ``base``; with a ``heuristic`` (n,) reduced,
        ``w(u, v) - h(u) + h(v)``, which consistency keeps >= 0. ``token`` names the content
        so that loading the same unreduced weights again is free."""
        if heuristic is None:
            if token is not None and token is self.loaded:
                return
            np.copyto(self.weights, base.T)
            self.loaded = token
            return
        h_ext = np.concatenate([np.zeros(self.margin), heuristic, np.zeros(self.margin)])
        red = self._reduced
        for k in range(8):  # row by row while it is in cache
            row = red[k]
            np.subtract(self.shifted(h_ext, k), heuristic, out=row)
            row += base[k]
            np.maximum(row, 0.0, out=row)  # rounding only; inf stays inf
        np.copyto(self.weights, red.T)
        self.loaded = None


@dataclass(frozen=True)
class _Search:
    dist: np.ndarray  # (n,) true cost from the start; inf where not settled
    pred: np.ndarray  # (n,) predecessor node; negative at the start and unsettled nodes
    settled: int


def _search(
    graph: _PaddedGraph,
    cheapest: float,
    start: int,
    goal: int,
    heuristic: np.ndarray | None,
) -> _Search:
    """Settle nodes in order of (reduced) cost on the loaded weights until the goal is settled
    or nothing is left. ``cheapest`` is the smallest finite entering cost (a lower bound)."""
    # Dijkstra's first limit is FIRST_LIMIT_RATIO times the goal's cost lower bound ``lb``; A*
    # bounds the reduced cost d - h(start), so its first limit is (FIRST_LIMIT_RATIO - 1) * lb.
    # Each pass that misses the goal multiplies the limit by LIMIT_GROWTH; after
    # MAX_LIMITED_PASSES the last pass is unbounded, which caps the cost of unreachable goals.
    rs, cs = int(graph.rows[start]), int(graph.cols[start])
    rg, cg = int(graph.rows[goal]), int(graph.cols[goal])
    lb = max(cheapest * float(octile_distance(np.array(rs), np.array(cs), rg, cg)), 1.0)
    ratio = FIRST_LIMIT_RATIO - 1.0 if heuristic is not None else FIRST_LIMIT_RATIO
    limit = ratio * lb
    targets = graph.indices.reshape(graph.n, 8)
    settled = passes = 0
    while True:
        dist, pred = dijkstra(
            graph.csr, directed=True, indices=start, return_predecessors=True, limit=limit
        )
        reached = np.flatnonzero(np.isfinite(dist))
        settled += reached.size
        if np.isfinite(dist[goal]) or math.isinf(limit):
            break
        # Exhausted when no usable edge leaves the settled region: the goal is unreachable.
        out = np.isfinite(graph.weights[reached]) & ~np.isfinite(dist[targets[reached]])
        if not out.any():
            break
        passes += 1
        limit = limit * LIMIT_GROWTH if passes < MAX_LIMITED_PASSES else math.inf
    if heuristic is not None:
        dist = dist + float(heuristic[start]) - heuristic
    return _Search(dist, pred, settled)


def _trace(pred: np.ndarray, start: int, goal: int) -> np.ndarray:
    """Nodes from ``start`` to ``goal`` along the predecessor tree (path length loop only)."""
    nodes = [goal]
    while nodes[-1] != start:
        nodes.append(int(pred[nodes[-1]]))
    return np.array(nodes[::-1], dtype=np.int64)


# --- smoothing and poses ----------------------------------------------------------------------


def _cells_of(xy: np.ndarray, geometry: GridGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rows, cols = geometry.world_to_cell(xy[:, 0], xy[:, 1])
    inside = geometry.contains(rows, cols)
    return np.clip(rows, 0, geometry.height - 1), np.clip(cols, 0, geometry.width - 1), inside


def points_passable(
    xy: np.ndarray, costmap: np.ndarray, geometry: GridGeometry, config: PlannerConfig
) -> np.ndarray:
    """(N,) bool: which points lie on the map in a cell the planner may enter."""
    rows, cols, inside = _cells_of(xy, geometry)
    return inside & passable_mask(costmap, config)[rows, cols]


def smooth_path(
    xy: np.ndarray, costmap: np.ndarray, geometry: GridGeometry, config: PlannerConfig
) -> np.ndarray:
    """SimpleSmoother-style gradient smoothing of an (N, 2) path [m]; endpoints stay fixed.

    All interior points move together (Jacobi rather than Nav2's in-place sweep). A point whose
    update would land in an impassable cell keeps its previous position for that iteration, where
    Nav2 would abandon smoothing altogether.
    """
    if len(xy) < 3:
        return xy.copy()
    # Passable cells padded by one impassable cell, so clipping an index sends it off the map.
    padded = np.zeros((geometry.height + 2, geometry.width + 2), dtype=bool)
    padded[1:-1, 1:-1] = passable_mask(costmap, config)
    origin = np.array([geometry.origin_x, geometry.origin_y])
    hi = np.array([geometry.width + 1, geometry.height + 1])
    m = len(xy) - 2
    wd, ws = config.smoothing_w_data, config.smoothing_w_smooth

    def passable(cand: np.ndarray, prev: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """(m,) bool: interior points ``cand`` and the midpoints of their segments are free."""
        probes = np.concatenate([cand, 0.5 * (cand + prev), 0.5 * (cand + nxt)])
        cell = np.floor((probes - origin) / geometry.resolution).astype(np.int64) + 1
        np.clip(cell, 0, hi, out=cell)
        return np.asarray(padded[cell[:, 1], cell[:, 0]].reshape(3, m).all(axis=0))

    out = xy.copy()
    passes = 2 if config.smoothing_do_refinement else 1
    for _ in range(passes):
        data = out.copy()
        # The iteration below converges (contraction 1 - w_data at worst) to the solution of
        # the tridiagonal system w_data (data - x) + w_smooth (x[i-1] + x[i+1] - 2 x) = 0 with
        # the endpoints fixed. Solved directly (0.1 ms instead of ~100 Python-level sweeps), it
        # is the answer whenever nothing on it is impassable; otherwise iterate as Nav2 does.
        fixed = _smoothing_fixed_point(data, wd, ws) if wd > 0.0 else None
        if fixed is not None and passable(fixed[1:-1], fixed[:-2], fixed[2:]).all():
            out = fixed
            continue
        for _ in range(config.smoothing_max_its):
            inner = out[1:-1]
            step = wd * (data[1:-1] - inner) + ws * (out[:-2] + out[2:] - 2.0 * inner)
            cand = inner + step
            step[~passable(cand, out[:-2], out[2:])] = 0.0
            out[1:-1] = inner + step
            if float(np.abs(step).sum()) < config.smoothing_tolerance:
                break
    return out


def _smoothing_fixed_point(data: np.ndarray, wd: float, ws: float) -> np.ndarray:
    """The limit of the SimpleSmoother iteration on (N, 2) ``data`` with fixed endpoints: the
    tridiagonal system (wd + 2 ws) x[i] - ws (x[i-1] + x[i+1]) = wd data[i] (banded solve)."""
    m = len(data) - 2
    ab = np.empty((3, m))
    ab[0], ab[1], ab[2] = -ws, wd + 2.0 * ws, -ws
    rhs = wd * data[1:-1].copy()
    rhs[0] += ws * data[0]
    rhs[-1] += ws * data[-1]
    out = data.copy()
    out[1:-1] = solve_banded((1, 1), ab, rhs)
    return out


def segments_passable(
    xy: np.ndarray, costmap: np.ndarray, geometry: GridGeometry, config: PlannerConfig
) -> np.ndarray:
    """(N - 1,) bool: which segments of an (N, 2) path stay in passable cells at the samples."""
    t = np.linspace(0.0, 1.0, SEGMENT_SAMPLES)[None, :, None]
    pts = xy[:-1, None, :] + t * (xy[1:, None, :] - xy[:-1, None, :])
    ok = points_passable(pts.reshape(-1, 2), costmap, geometry, config)
    return np.asarray(ok.reshape(len(xy) - 1, SEGMENT_SAMPLES).all(axis=1))


def repair_path(
    smoothed: np.ndarray,
    raw: np.ndarray,
    costmap: np.ndarray,
    geometry: GridGeometry,
    config: PlannerConfig,
) -> np.ndarray:
    """Put back the raw points around every smoothed segment that clips an impassable cell.

    The raw grid path never clips one (diagonals do not cut corners), so resetting a growing
    neighbourhood converges; after MAX_REPAIRS rounds the raw path is returned.
    """
    out = smoothed.copy()
    for _ in range(MAX_REPAIRS):
        bad = ~segments_passable(out, costmap, geometry, config)
        if not bad.any():
            return out
        reset = np.zeros(len(out), dtype=bool)
        i = np.flatnonzero(bad)
        for shift in (-1, 0, 1, 2):  # both ends of a bad segment and one more on each side
            reset[np.clip(i + shift, 0, len(out) - 1)] = True
        out[reset] = raw[reset]
    return raw.copy()


def resample_path(xy: np.ndarray, spacing: float) -> np.ndarray:
    """(N, 2) path resampled at ``spacing`` [m] of arc length, keeping both endpoints."""
    if len(xy) < 2:
        return xy.copy()
    seg = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = float(s[-1])
    if total <= 0.0:
        return xy[:1].copy()
    n = max(1, math.ceil(total / spacing - 1e-9))  # no extra point from rounding
    t = np.linspace(0.0, total, n + 1)
    return np.column_stack([np.interp(t, s, xy[:, 0]), np.interp(t, s, xy[:, 1])])


def path_poses(
    xy: np.ndarray, goal_yaw: float | None, use_final_approach_orientation: bool
) -> np.ndarray:
    """(N, 3) poses with yaw along the path; the last yaw is the goal's when given (Nav2)."""
    yaw = np.zeros(len(xy))
    if len(xy) >= 2:
        d = np.diff(xy, axis=0)
        yaw[:-1] = np.arctan2(d[:, 1], d[:, 0])
        yaw[-1] = yaw[-2]
    if goal_yaw is not None and not use_final_approach_orientation:
        yaw[-1] = goal_yaw
    return np.column_stack([xy, yaw])


def _finish(
    xy: np.ndarray,
    costmap: np.ndarray,
    geometry: GridGeometry,
    config: PlannerConfig,
    goal_yaw: float | None,
    smooth: bool,
) -> np.ndarray:
    dense = resample_path(xy, geometry.resolution)
    if smooth and config.smooth_path:
        repaired = repair_path(
            smooth_path(xy, costmap, geometry, config), xy, costmap, geometry, config
        )
        smoothed = resample_path(repaired, geometry.resolution)
        # Resampling can cut a corner between two valid smoothed points; the grid path cannot.
        if points_passable(smoothed, costmap, geometry, config).all():
            dense = smoothed
        else:
            log.debug("smoothed path clips an impassable cell; keeping the grid path")
    return path_poses(dense, goal_yaw, config.use_final_approach_orientation)


# --- planners ---------------------------------------------------------------------------------


def _endpoint_cell(x: float, y: float, geometry: GridGeometry, what: str) -> tuple[int, int] | str:
    r, c = geometry.world_to_cell(x, y)
    if not bool(geometry.contains(r, c)):
        return f"{what} ({x:.2f}, {y:.2f}) is outside the map"
    return int(r), int(c)


def _check_shapes(costmap: np.ndarray, geometry: GridGeometry) -> str | None:
    if costmap.shape != geometry.shape or costmap.dtype != np.uint8:
        return (
            f"costmap must be uint8 of shape {geometry.shape} (height, width), "
            f"got {costmap.dtype} {costmap.shape}"
        )
    return None


def escape_region(
    costmap: np.ndarray, passable: np.ndarray, start: tuple[int, int]
) -> np.ndarray | None:
    """(H, W) bool: where a start in an impassable but non-lethal cell (inscribed band, or
    unknown without ``allow_unknown``) may move to leave it (NavFn's ``clearRobotCell``, widened
    to the band): the non-lethal impassable cells 8-connected to the start within ``d0 + 1``
    cells of it, ``d0`` [cells] being its distance to the nearest passable cell. None when no
    passable cell is left on the map."""
    free = np.argwhere(passable)
    if free.size == 0:
        return None
    d0 = float(np.hypot(free[:, 0] - start[0], free[:, 1] - start[1]).min())
    r = math.ceil(d0 + 1.0)
    r0, c0 = max(start[0] - r, 0), max(start[1] - r, 0)
    win = (slice(r0, start[0] + r + 1), slice(c0, start[1] + r + 1))
    rows, cols = np.ogrid[win]
    near = np.hypot(rows - start[0], cols - start[1]) <= d0 + 1.0
    cand = near & ~passable[win] & (costmap[win] != LETHAL_OBSTACLE)
    labels, _ = ndimage.label(cand, structure=np.ones((3, 3), dtype=bool))
    out = np.zeros(costmap.shape, dtype=bool)
    out[win] = labels == labels[start[0] - r0, start[1] - c0]
    return out


INCREMENTAL_MAX_CHANGED = 0.05  # share of changed cells up to which edge weights are patched


class GridPlanner:
    """NavFn-like cost-aware planner; caches the grid graph topology per costmap shape and the
    edge weights of the last costmap it planned on (plans on an unchanged costmap skip them)."""

    def __init__(self, config: PlannerConfig | None = None) -> None:
        self.config = config or PlannerConfig()
        self._graph: _PaddedGraph | None = None
        self._costmap: np.ndarray | None = None  # copy of the costmap the cache belongs to
        self._step_cost = np.zeros((0, 0))
        self._base = np.zeros((8, 0))  # (8, n) unreduced edge weights of that costmap
        self._cheapest = 0.0

    def clear_cache(self) -> None:
        """Forget the cached edge weights (the next plan computes them, as on a new costmap)."""
        self._costmap = None

    def _graph_for(self, shape: tuple[int, int]) -> _PaddedGraph:
        if self._graph is None or self._graph.shape != shape:
            self._graph = _PaddedGraph(shape)
            self._costmap = None
        return self._graph

    def _weights_for(self, costmap: np.ndarray, graph: _PaddedGraph) -> tuple[np.ndarray, float]:
        """(8, n) unreduced weights of ``costmap`` and its cheapest entering cost, cached. A
        costmap that differs from the cached one in a few cells (a scan marked and cleared,
        its inflation) updates only the edges leaving cells next to a changed one: an edge's
        weight depends on the cell it enters and, for a diagonal, the two it cuts past."""
        cached = self._costmap
        if cached is not None and np.array_equal(cached, costmap):
            return self._base, self._cheapest
        self._step_cost = cell_traversal_cost(costmap, self.config)
        finite = self._step_cost[np.isfinite(self._step_cost)]
        self._cheapest = float(finite.min()) if finite.size else 1.0
        changed = None if cached is None else cached != costmap
        if (
            cached is not None
            and changed is not None
            and changed.sum() <= INCREMENTAL_MAX_CHANGED * changed.size
        ):
            # In padded node space: the border nodes' edges into the grid change too.
            padded = np.zeros(graph.padded, dtype=bool)
            padded[1:-1, 1:-1] = changed
            near = ndimage.binary_dilation(padded, structure=np.ones((3, 3), dtype=bool))
            nodes = np.flatnonzero(near)
            fresh = graph.node_weights(self._step_cost, nodes)
            self._base[:, nodes] = fresh
            if graph.loaded is self._base:  # the CSR holds these weights: patch it too
                graph.weights[nodes] = fresh.T
            cached[...] = costmap
        else:
            self._base = graph.base_weights(self._step_cost)
            self._costmap = costmap.copy()
        return self._base, self._cheapest

    def plan(
        self,
        costmap: np.ndarray,
        geometry: GridGeometry,
        start_xy: tuple[float, float],
        goal_xy: tuple[float, float],
        goal_yaw: float | None = None,
    ) -> PlanResult:
        """Cheapest path from ``start_xy`` to ``goal_xy`` [m, map frame] on ``costmap``.

        A start in an impassable cell that is not a wall (the inscribed band, say, after a
        localisation jump) is left by the cheapest way to passable space through the
        :func:`escape_region`; a start on a wall is refused."""
        cfg = self.config
        if (err := _check_shapes(costmap, geometry)) is not None:
            return _fail(err)
        # 1. Validate the endpoints.
        s = _endpoint_cell(*start_xy, geometry, "start")
        g = _endpoint_cell(*goal_xy, geometry, "goal")
        if isinstance(s, str):
            return _fail(s)
        if isinstance(g, str):
            return _fail(g)
        passable = passable_mask(costmap, cfg)
        if costmap[s] == LETHAL_OBSTACLE:
            return _fail(
                f"start {s} (row, col) is in an obstacle (lethal cost {costmap[s]}, a wall)"
            )
        goal_cost = int(costmap[g])
        if goal_cost == LETHAL_OBSTACLE:
            return _fail(f"goal {g} (row, col) is in a lethal cell (a wall)")
        if goal_cost == NO_INFORMATION and not cfg.allow_unknown:
            return _fail(f"goal {g} (row, col) is in unknown space and allow_unknown is false")

        # 2. Edge weights: cached per costmap, or with an escape route out of the start's cell.
        graph = self._graph_for(geometry.shape)
        escape = None
        if not passable[s]:
            escape = escape_region(costmap, passable, s)
            if escape is None:
                return _fail(
                    f"start {s} (row, col) is in an obstacle (cost {costmap[s]}) and "
                    "no passable cell is left on the map"
                )
            escape[g] = False  # the goal keeps its own rules (tolerance)
            log.debug(
                "start %s has cost %d: leaving it through %d cells",
                s,
                costmap[s],
                int(escape.sum()),
            )
            step_cost = cell_traversal_cost(costmap, cfg, enterable=escape)
            base = graph.base_weights(step_cost, escape)
            cheapest = float(step_cost[np.isfinite(step_cost)].min())
        else:
            base, cheapest = self._weights_for(costmap, graph)

        # 3. Search from the start; A* aims at the goal cell even when it is impassable.
        start_n, goal_n = graph.node(*s), graph.node(*g)
        heuristic = graph.heuristic(g, cfg.neutral_cost) if cfg.use_astar else None
        graph.load(base, heuristic, None if escape is not None else base)
        found = _search(graph, cheapest, start_n, goal_n, heuristic)

        # 4. Goal tolerance: the reachable cell nearest the goal, cheaper first on ties.
        end_n = goal_n
        if not np.isfinite(found.dist[goal_n]):
            end = self._nearest_reachable(found.dist, graph, geometry, g, passable)
            if end is None:
                return PlanResult(
                    success=False,
                    reason=(
                        f"goal {g} (row, col) is unreachable"
                        + ("" if passable[g] else f" (impassable cost {goal_cost})")
                        + f" and no reachable cell lies within tolerance {cfg.tolerance} m"
                    ),
                    settled_cells=found.settled,
                )
            end_n = end
        nodes = _trace(found.pred, start_n, end_n)
        rows, cols = graph.cell(nodes)
        cx, cy = geometry.cell_to_world(rows, cols)
        offset = float(math.hypot(float(cx[-1]) - goal_xy[0], float(cy[-1]) - goal_xy[1]))
        # The exact goal replaces the centre of its cell so the path ends where it was asked to.
        xy = np.column_stack([cx, cy])
        xy[0] = start_xy
        if end_n == goal_n:
            xy[-1] = goal_xy
            offset = 0.0
        # 5. Smooth; the escape route counts as passable so the smoother keeps the path.
        if escape is not None:
            costmap = costmap.copy()
            costmap[escape] = cfg.lethal_cost - 1
        poses = _finish(xy, costmap, geometry, cfg, goal_yaw, smooth=True)
        return PlanResult(
            success=True,
            reason="",
            poses=poses,
            cells=np.column_stack([rows, cols]).astype(np.int64),
            cost=float(found.dist[end_n]),
            goal_offset_m=offset,
            settled_cells=found.settled,
        )

    def _nearest_reachable(
        self,
        dist: np.ndarray,
        graph: _PaddedGraph,
        geometry: GridGeometry,
        goal: tuple[int, int],
        passable: np.ndarray,
    ) -> int | None:
        """Node of the reachable passable cell nearest ``goal`` within tolerance, or None."""
        radius = self.config.tolerance / geometry.resolution  # [cells]
        if radius <= 0.0:
            return None
        rows, cols = graph.cell(np.arange(graph.n))
        d = np.hypot(rows - goal[0], cols - goal[1])
        ok = graph.pad(passable, False)[graph.margin : graph.margin + graph.n]
        candidates = np.flatnonzero(np.isfinite(dist) & ok & (d <= radius))
        if candidates.size == 0:
            return None
        order = np.lexsort((dist[candidates], d[candidates]))
        return int(candidates[order[0]])


def plan_straight_line(
    costmap: np.ndarray,
    geometry: GridGeometry,
    start_xy: tuple[float, float],
    goal_xy: tuple[float, float],
    config: PlannerConfig | None = None,
    goal_yaw: float | None = None,
) -> PlanResult:
    """The segment start -> goal if every cell it crosses is passable, else where it is blocked."""
    cfg = config or PlannerConfig()
    if (err := _check_shapes(costmap, geometry)) is not None:
        return _fail(err)
    a = np.asarray(start_xy, dtype=np.float64)
    b = np.asarray(goal_xy, dtype=np.float64)
    n = max(2, math.ceil(LINE_SAMPLES_PER_CELL * float(np.hypot(*(b - a))) / geometry.resolution))
    t = np.linspace(0.0, 1.0, n + 1)[:, None]
    xy = a + t * (b - a)
    ok = points_passable(xy, costmap, geometry, cfg)
    if not ok.all():
        i = int(np.argmin(ok))
        return _fail(
            f"straight line blocked at ({xy[i, 0]:.2f}, {xy[i, 1]:.2f}), "
            f"{float(t[i, 0]) * float(np.hypot(*(b - a))):.2f} m from the start"
        )
    rows, cols, _ = _cells_of(xy, geometry)
    poses = _finish(np.stack([a, b]), costmap, geometry, cfg, goal_yaw, smooth=False)
    step = np.hypot(*np.diff(xy, axis=0).T)
    cost = float((cell_traversal_cost(costmap, cfg)[rows[1:], cols[1:]] * step).sum())
    cost /= geometry.resolution  # per-cell units, like the grid search
    return PlanResult(
        success=True,
        reason="",
        poses=poses,
        cells=np.column_stack([rows, cols]).astype(np.int64),
        cost=cost,
    )


def replan_needed(
    path_xy: np.ndarray,
    costmap: np.ndarray,
    geometry: GridGeometry,
    config: PlannerConfig | None = None,
) -> bool:
    """True when any point of the (N, 2+) path [m] now lies in a cell the planner may not enter."""
    if len(path_xy) == 0:
        return False
    cfg = config or PlannerConfig()
    return not bool(points_passable(np.asarray(path_xy)[:, :2], costmap, geometry, cfg).all())
