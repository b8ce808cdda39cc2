"""Global planner: optimality against a heapq reference, cost awareness, refusals, smoothing."""

from __future__ import annotations

import heapq
import math

import numpy as np
import pytest

from nav.config import LETHAL_OBSTACLE, NO_INFORMATION, PlannerConfig
from nav.planner import (
    GridPlanner,
    _smoothing_fixed_point,
    plan_straight_line,
    points_passable,
    replan_needed,
    resample_path,
    smooth_path,
)
from slam.occupancy_grid import GridGeometry

RES = 0.1  # [m/cell]


def geometry(h: int, w: int) -> GridGeometry:
    return GridGeometry(RES, 0.0, 0.0, w, h)


def centre(row: int, col: int) -> tuple[float, float]:
    return ((col + 0.5) * RES, (row + 0.5) * RES)


def reference_cost(
    cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], cfg: PlannerConfig
) -> float:
    """Plain heapq Dijkstra: entering a cell costs |step| (neutral + factor * cost); unknown is
    lethal_cost - 1 when allowed; diagonals may not cut past an impassable cell."""
    h, w = cost.shape

    def passable(r: int, c: int) -> bool:
        if not (0 <= r < h and 0 <= c < w):
            return False
        v = int(cost[r, c])
        if v == NO_INFORMATION:
            return cfg.allow_unknown
        return v < cfg.lethal_cost

    def enter(r: int, c: int) -> float:
        v = int(cost[r, c])
        v = cfg.lethal_cost - 1 if v == NO_INFORMATION else v
        return cfg.neutral_cost + cfg.cost_factor * v

    dist = {start: 0.0}
    heap = [(0.0, start)]
    while heap:
        d, (r, c) = heapq.heappop(heap)
        if (r, c) == goal:
            return d
        if d > dist[(r, c)]:
            continue
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if (dr, dc) == (0, 0) or not passable(r + dr, c + dc):
                    continue
                if dr and dc and not (passable(r + dr, c) and passable(r, c + dc)):
                    continue
                nd = d + math.hypot(dr, dc) * enter(r + dr, c + dc)
                if nd < dist.get((r + dr, c + dc), math.inf):
                    dist[(r + dr, c + dc)] = nd
                    heapq.heappush(heap, (nd, (r + dr, c + dc)))
    return math.inf


def random_costmap(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    cost = rng.integers(0, 200, size=(h, w)).astype(np.uint8)
    cost[rng.random((h, w)) < 0.2] = LETHAL_OBSTACLE
    cost[rng.random((h, w)) < 0.05] = NO_INFORMATION
    return cost


@pytest.mark.parametrize("use_astar", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_path_cost_equals_reference_dijkstra(seed: int, use_astar: bool) -> None:
    rng = np.random.default_rng(seed)
    cost = random_costmap(rng, 14, 17)
    start, goal = (1, 1), (12, 15)
    cost[start] = cost[goal] = 0
    cfg = PlannerConfig(use_astar=use_astar, smooth_path=False, tolerance=0.0)
    expected = reference_cost(cost, start, goal, cfg)
    result = GridPlanner(cfg).plan(cost, geometry(14, 17), centre(*start), centre(*goal))
    if math.isinf(expected):
        assert not result.success and "unreachable" in result.reason
        return
    assert result.success, result.reason
    assert result.cost == pytest.approx(expected, rel=1e-9)
    cells = result.cells
    assert tuple(cells[0]) == start and tuple(cells[-1]) == goal
    assert np.abs(np.diff(cells, axis=0)).max() == 1  # 8-connected
    on_path = cost[cells[:, 0], cells[:, 1]]
    assert np.all((on_path < cfg.lethal_cost) | (on_path == NO_INFORMATION))


def test_path_avoids_lethal_cells_and_walls() -> None:
    cost = np.zeros((20, 30), dtype=np.uint8)
    cost[0:16, 15] = LETHAL_OBSTACLE  # wall with a gap at the top
    result = GridPlanner(PlannerConfig(smooth_path=False)).plan(
        cost, geometry(20, 30), centre(2, 2), centre(2, 27)
    )
    assert result.success
    assert np.all(cost[result.cells[:, 0], result.cells[:, 1]] < LETHAL_OBSTACLE)
    assert result.cells[:, 0].max() >= 16  # went round the wall
    assert points_passable(result.poses[:, :2], cost, geometry(20, 30), PlannerConfig()).all()


def test_cost_aware_path_prefers_cheaper_cells() -> None:
    # A short corridor of cost 200 (row 5) and a longer free detour (row 15).
    cost = np.full((20, 30), LETHAL_OBSTACLE, dtype=np.uint8)
    cost[5, 2:28] = 200
    cost[5:16, 2] = 0
    cost[5:16, 27] = 0
    cost[15, 2:28] = 0
    cost[5, 2] = cost[5, 27] = 0
    geo, start, goal = geometry(20, 30), centre(5, 2), centre(5, 27)
    cheap = GridPlanner(PlannerConfig(smooth_path=False)).plan(cost, geo, start, goal)
    assert cheap.success and cheap.cells[:, 0].max() == 15
    blind = GridPlanner(PlannerConfig(smooth_path=False, cost_factor=0.0)).plan(
        cost, geo, start, goal
    )
    assert blind.success and blind.cells[:, 0].max() == 5
    assert blind.length_m < cheap.length_m


def test_start_in_obstacle_is_refused() -> None:
    cost = np.zeros((10, 10), dtype=np.uint8)
    cost[3, 3] = LETHAL_OBSTACLE
    result = GridPlanner().plan(cost, geometry(10, 10), centre(3, 3), centre(8, 8))
    assert not result.success and "start" in result.reason and "obstacle" in result.reason
    assert "wall" in result.reason


def wall_with_band() -> np.ndarray:
    """A lethal wall (rows 9..10, cols 5..34) inside a 3-cell inscribed band (cost 253)."""
    cost = np.zeros((20, 40), dtype=np.uint8)
    cost[6:14, 2:38] = 253
    cost[9:11, 5:35] = LETHAL_OBSTACLE
    return cost


@pytest.mark.parametrize("use_astar", [False, True])
def test_start_in_inscribed_band_plans_out_of_it(use_astar: bool) -> None:
    """NavFn's clearRobotCell: a start in the band (cost 253, impassable but no wall) is left by
    the shortest way out, here 2 more band cells toward row 0, instead of refusing every plan."""
    cost = wall_with_band()
    geo = geometry(20, 40)
    cfg = PlannerConfig(use_astar=use_astar, smooth_path=False, tolerance=0.0)
    result = GridPlanner(cfg).plan(cost, geo, centre(8, 20), centre(2, 20))
    assert result.success, result.reason
    np.testing.assert_array_equal(result.cells[:4], [[8, 20], [7, 20], [6, 20], [5, 20]])
    # Out of the band, the path stays in passable cells.
    assert (cost[result.cells[3:, 0], result.cells[3:, 1]] < 253).all()
    # Cost: 2 band cells entered at 50 + 3 * (lethal_cost - 1), as unknown, then 4 free cells.
    assert result.cost == pytest.approx(2 * (50 + 3 * 252) + 4 * 50)


@pytest.mark.parametrize("use_astar", [False, True])
def test_a_path_that_left_the_band_never_re_enters_it(use_astar: bool) -> None:
    """Start in the band at the wall's left end, goal beyond its right end on the same side:
    running along the band would be shorter, but once out the path stays out."""
    cost = wall_with_band()
    cost[6:9, 2:38] = 253  # the whole upper side of the band; the wall below it
    geo = geometry(20, 40)
    cfg = PlannerConfig(use_astar=use_astar, tolerance=0.0)
    result = GridPlanner(cfg).plan(cost, geo, centre(7, 4), centre(7, 39))
    assert result.success, result.reason
    in_band = cost[result.cells[:, 0], result.cells[:, 1]] >= 253
    first_out = int(np.argmin(in_band))
    assert 0 < first_out <= 3 and not in_band[first_out:].any()
    # The smoothed poses leave the band as the grid path does and stay out.
    poses_ok = points_passable(result.poses[:, :2], cost, geo, PlannerConfig())
    assert poses_ok[-1] and poses_ok[int(np.argmax(poses_ok)) :].all()


def test_start_in_unknown_is_left_when_unknown_is_not_allowed() -> None:
    cost = np.zeros((10, 10), dtype=np.uint8)
    cost[2:5, 2:5] = NO_INFORMATION
    cfg = PlannerConfig(allow_unknown=False, smooth_path=False)
    result = GridPlanner(cfg).plan(cost, geometry(10, 10), centre(3, 3), centre(8, 8))
    assert result.success, result.reason
    assert (cost[result.cells[2:, 0], result.cells[2:, 1]] == 0).all()


def test_start_in_band_walled_in_is_unreachable_not_an_error() -> None:
    cost = np.full((10, 10), 253, dtype=np.uint8)
    cost[0, :] = cost[-1, :] = cost[:, 0] = cost[:, -1] = LETHAL_OBSTACLE
    result = GridPlanner(PlannerConfig(tolerance=0.0)).plan(
        cost, geometry(10, 10), centre(3, 3), centre(6, 6)
    )
    assert not result.success and "start" in result.reason and "no passable cell" in result.reason


def test_goal_in_wall_is_refused_even_with_tolerance() -> None:
    cost = np.zeros((10, 10), dtype=np.uint8)
    cost[8, 8] = LETHAL_OBSTACLE
    result = GridPlanner(PlannerConfig(tolerance=1.0)).plan(
        cost, geometry(10, 10), centre(1, 1), centre(8, 8)
    )
    assert not result.success and "wall" in result.reason


def test_goal_in_unknown_is_refused_when_unknown_not_allowed() -> None:
    cost = np.zeros((10, 10), dtype=np.uint8)
    cost[8, 8] = NO_INFORMATION
    geo = geometry(10, 10)
    refused = GridPlanner(PlannerConfig(allow_unknown=False)).plan(
        cost, geo, centre(1, 1), centre(8, 8)
    )
    assert not refused.success and "unknown" in refused.reason
    assert (
        GridPlanner(PlannerConfig(allow_unknown=True))
        .plan(cost, geo, centre(1, 1), centre(8, 8))
        .success
    )


def test_goal_outside_map_is_refused() -> None:
    cost = np.zeros((10, 10), dtype=np.uint8)
    result = GridPlanner().plan(cost, geometry(10, 10), centre(1, 1), (5.0, 0.5))
    assert not result.success and "outside the map" in result.reason


def enclosed_goal_map() -> np.ndarray:
    """A free 3x3 pocket (rows 9..11, cols 9..11) closed by a one-cell wall ring."""
    cost = np.zeros((20, 20), dtype=np.uint8)
    cost[8:13, 8:13] = LETHAL_OBSTACLE
    cost[9:12, 9:12] = 0
    return cost


def test_unreachable_goal_is_refused_without_tolerance() -> None:
    result = GridPlanner(PlannerConfig(tolerance=0.0)).plan(
        enclosed_goal_map(), geometry(20, 20), centre(1, 1), centre(10, 10)
    )
    assert not result.success and "unreachable" in result.reason


@pytest.mark.parametrize("use_astar", [False, True])
def test_tolerance_accepts_nearest_reachable_cell(use_astar: bool) -> None:
    cfg = PlannerConfig(tolerance=0.35, use_astar=use_astar, smooth_path=False)
    result = GridPlanner(cfg).plan(
        enclosed_goal_map(), geometry(20, 20), centre(1, 1), centre(10, 10)
    )
    assert result.success, result.reason
    # Nearest reachable cells lie just outside the ring, 3 cells (0.3 m) from the goal.
    assert result.goal_offset_m == pytest.approx(0.3, abs=1e-9)
    assert result.goal_offset_m <= cfg.tolerance


def test_smoothing_keeps_path_collision_free_and_shortens_it() -> None:
    cost = np.zeros((40, 60), dtype=np.uint8)
    cost[10:30, 25:35] = LETHAL_OBSTACLE
    cost[8:32, 23:37] = np.maximum(cost[8:32, 23:37], 253)  # inscribed band
    cost[10:30, 25:35] = LETHAL_OBSTACLE
    geo = geometry(40, 60)
    start, goal = centre(20, 3), centre(20, 56)
    raw = GridPlanner(PlannerConfig(smooth_path=False)).plan(cost, geo, start, goal)
    smooth = GridPlanner(PlannerConfig(smooth_path=True)).plan(cost, geo, start, goal)
    assert raw.success and smooth.success
    assert smooth.length_m < raw.length_m - 0.05
    cfg = PlannerConfig()
    assert points_passable(smooth.poses[:, :2], cost, geo, cfg).all()
    # Resampled to about one point per cell, ends where it was asked to.
    steps = np.hypot(*np.diff(smooth.poses[:, :2], axis=0).T)
    assert steps.max() <= RES + 1e-9
    np.testing.assert_allclose(smooth.poses[0, :2], start, atol=1e-12)
    np.testing.assert_allclose(smooth.poses[-1, :2], goal, atol=1e-12)


def _iterated_smoothing(
    xy: np.ndarray, cost: np.ndarray, geo: GridGeometry, cfg: PlannerConfig
) -> np.ndarray:
    """SimpleSmoother by its iteration alone, point by point (the reference for smooth_path)."""
    out = xy.copy()
    for _ in range(2 if cfg.smoothing_do_refinement else 1):
        data = out.copy()
        for _ in range(cfg.smoothing_max_its):
            new = out.copy()
            change = 0.0
            for i in range(1, len(out) - 1):
                step = cfg.smoothing_w_data * (data[i] - out[i]) + cfg.smoothing_w_smooth * (
                    out[i - 1] + out[i + 1] - 2.0 * out[i]
                )
                cand = out[i] + step
                probes = np.array([cand, 0.5 * (cand + out[i - 1]), 0.5 * (cand + out[i + 1])])
                if points_passable(probes, cost, geo, cfg).all():
                    new[i] = cand
                    change += float(np.abs(step).sum())
            out = new
            if change < cfg.smoothing_tolerance:
                break
    return out


@pytest.mark.parametrize("corridor", [0, 1, 3])
def test_smoothing_equals_the_simple_smoother_iteration(corridor: int) -> None:
    """Open space (0): the direct solve is the answer. An L-shaped corridor 1 or 3 cells wide:
    the unconstrained limit cuts the inside corner through the wall, so the iteration runs."""
    geo = geometry(40, 40)
    cfg = PlannerConfig()
    if corridor:
        cost = np.full((40, 40), LETHAL_OBSTACLE, dtype=np.uint8)
        cost[5 : 5 + corridor, 2:31] = 0
        cost[5:36, 31 - corridor : 31] = 0
        start, goal = centre(5, 3), centre(35, 31 - corridor)
    else:
        cost = np.zeros((40, 40), dtype=np.uint8)
        start, goal = centre(5, 3), centre(35, 30)
    raw = GridPlanner(PlannerConfig(smooth_path=False, tolerance=0.0))
    xy = raw.plan(cost, geo, start, goal).poses[:, :2]
    limit = _smoothing_fixed_point(xy, cfg.smoothing_w_data, cfg.smoothing_w_smooth)
    assert points_passable(limit, cost, geo, cfg).all() == (corridor == 0)
    got = smooth_path(xy, cost, geo, cfg)
    np.testing.assert_allclose(got, _iterated_smoothing(xy, cost, geo, cfg), atol=1e-6)
    assert points_passable(got, cost, geo, cfg).all()


def test_poses_face_along_the_path_and_end_at_goal_yaw() -> None:
    cost = np.zeros((10, 30), dtype=np.uint8)
    result = GridPlanner().plan(cost, geometry(10, 30), centre(5, 2), centre(5, 25), goal_yaw=1.0)
    assert result.success
    np.testing.assert_allclose(result.poses[:-1, 2], 0.0, atol=1e-9)
    assert result.poses[-1, 2] == pytest.approx(1.0)


def test_straight_line_planner_in_open_space() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    result = plan_straight_line(cost, geometry(20, 20), (0.25, 0.25), (1.65, 1.65), goal_yaw=0.3)
    assert result.success
    assert result.length_m == pytest.approx(math.hypot(1.4, 1.4), rel=1e-9)
    np.testing.assert_allclose(result.poses[:-1, 2], math.pi / 4, atol=1e-9)
    assert result.poses[-1, 2] == pytest.approx(0.3)


def test_straight_line_planner_fails_when_blocked() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    cost[:, 10] = LETHAL_OBSTACLE
    result = plan_straight_line(cost, geometry(20, 20), (0.25, 1.0), (1.75, 1.0))
    assert not result.success and "blocked at (1.0" in result.reason


def test_replan_needed_when_path_cell_becomes_lethal() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    geo = geometry(20, 20)
    result = GridPlanner().plan(cost, geo, centre(10, 1), centre(10, 18))
    assert result.success and not replan_needed(result.poses, cost, geo)
    blocked = cost.copy()
    blocked[10, 9] = LETHAL_OBSTACLE
    assert replan_needed(result.poses, blocked, geo)
    # A lethal cell off the path does not matter.
    elsewhere = cost.copy()
    elsewhere[2, 2] = LETHAL_OBSTACLE
    assert not replan_needed(result.poses, elsewhere, geo)


def test_resample_keeps_endpoints_and_spacing() -> None:
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.55]])
    out = resample_path(xy, 0.1)
    np.testing.assert_allclose(out[[0, -1]], xy[[0, -1]])
    assert np.hypot(*np.diff(out, axis=0).T).max() <= 0.1 + 1e-12


@pytest.mark.parametrize("seed", range(5))
def test_smoothed_paths_never_enter_impassable_cells_on_random_maps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cost = np.zeros((50, 50), dtype=np.uint8)
    for _ in range(12):
        r, c = rng.integers(0, 45, size=2)
        h, w = rng.integers(2, 8, size=2)
        cost[r : r + h, c : c + w] = LETHAL_OBSTACLE
    cost[1, 1] = cost[48, 48] = 0
    geo = geometry(50, 50)
    result = GridPlanner().plan(cost, geo, centre(1, 1), centre(48, 48))
    assert result.success, result.reason
    assert points_passable(result.poses[:, :2], cost, geo, PlannerConfig()).all()


def test_goal_in_inscribed_cell_uses_tolerance() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    cost[10:13, 10:13] = 253  # inscribed: impassable with the default lethal_cost, not a wall
    geo = geometry(20, 20)
    refused = GridPlanner(PlannerConfig(tolerance=0.0)).plan(
        cost, geo, centre(1, 1), centre(11, 11)
    )
    assert not refused.success and "impassable cost 253" in refused.reason
    result = GridPlanner(PlannerConfig(tolerance=0.25)).plan(
        cost, geo, centre(1, 1), centre(11, 11)
    )
    assert result.success and result.goal_offset_m == pytest.approx(0.2, abs=1e-9)


@pytest.mark.parametrize("use_astar", [False, True])
def test_a_costmap_changed_in_place_is_not_planned_on_with_stale_weights(use_astar: bool) -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    geo = geometry(20, 20)
    planner = GridPlanner(PlannerConfig(use_astar=use_astar, smooth_path=False))
    first = planner.plan(cost, geo, centre(10, 1), centre(10, 18))
    assert first.success and (first.cells[:, 0] == 10).all()
    cost[3:17, 9] = LETHAL_OBSTACLE  # same array, new wall across the straight path
    second = planner.plan(cost, geo, centre(10, 1), centre(10, 18))
    assert second.success and not (second.cells[:, 0] == 10).all()
    assert second.cost > first.cost
    reference = reference_cost(cost, (10, 1), (10, 18), planner.config)
    assert second.cost == pytest.approx(reference, rel=1e-9)


@pytest.mark.parametrize("use_astar", [False, True])
def test_weights_patched_for_a_few_changed_cells_equal_a_fresh_computation(
    use_astar: bool,
) -> None:
    # A scan marks and clears a few cells between plans: the planner patches the edges around
    # them instead of recomputing all. Patched and fresh weights must agree exactly, and so
    # must the plans, over a run of random local changes.
    rng = np.random.default_rng(7)
    cost = rng.choice(np.array([0, 0, 0, 40, 120, 253, 254, 255], np.uint8), size=(30, 40))
    cost[5, 1] = cost[25, 38] = 0
    geo = geometry(30, 40)
    cfg = PlannerConfig(use_astar=use_astar, smooth_path=False, allow_unknown=True)
    incremental = GridPlanner(cfg)
    incremental.plan(cost, geo, centre(5, 1), centre(25, 38))
    first_base = incremental._base
    for step in range(12):
        r0, c0 = rng.integers(0, 26), rng.integers(0, 36)
        cost[r0 : r0 + 4, c0 : c0 + 4] = rng.choice(
            np.array([0, 60, 253, 254], np.uint8), size=(4, 4)
        )
        cost[5, 1] = cost[25, 38] = 0
        got = incremental.plan(cost, geo, centre(5, 1), centre(25, 38))
        fresh = GridPlanner(cfg)
        want = fresh.plan(cost, geo, centre(5, 1), centre(25, 38))
        assert np.array_equal(incremental._base, fresh._base), step
        assert got.success == want.success
        if want.success:
            assert got.cost == want.cost and np.array_equal(got.cells, want.cells)
    # Every step patched the cached weights in place (4x4 changes: under the patch limit).
    assert incremental._base is first_base


def test_the_csr_weights_follow_a_patched_costmap() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    geo = geometry(20, 20)
    planner = GridPlanner(PlannerConfig(smooth_path=False))
    planner.plan(cost, geo, centre(10, 1), centre(10, 18))
    cost[8:12, 9] = LETHAL_OBSTACLE  # a small change: patched in place
    again = planner.plan(cost, geo, centre(10, 1), centre(10, 18))
    graph = planner._graph
    assert graph is not None
    assert np.array_equal(graph.weights, planner._base.T)
    assert again.cost == pytest.approx(
        reference_cost(cost, (10, 1), (10, 18), planner.config), rel=1e-9
    )
