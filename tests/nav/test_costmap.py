"""Costmap layers against Nav2 costmap_2d semantics, on tiny hand-built grids."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from nav.config import CostmapConfig
from nav.costmap import (
    FREE,
    INSCRIBED,
    LETHAL,
    NO_INFORMATION,
    Costmap,
    inflation_cost,
    mask_costs,
    static_costs,
)
from sensors.types import LaserScan, MapError, Pose2
from slam.map_bundle import save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid

# Inscribed radius 0.2 m, k = 3 /m, inflation out to 0.55 m.
CFG = CostmapConfig(
    robot_radius=0.2, footprint_padding=0.0, inflation_radius=0.55, cost_scaling_factor=3.0
)
NO_INFLATION = CostmapConfig(robot_radius=0.2, footprint_padding=0.0, inflation_radius=0.0)
RANGE_MAX = 10.0  # [m]


def scan(ranges: list[float], angle_min: float = 0.0, increment: float = 0.01) -> LaserScan:
    return LaserScan(0, angle_min, increment, np.asarray(ranges, np.float32), 0.05, RANGE_MAX)


def free_geometry(n: int = 41, res: float = 0.1) -> GridGeometry:
    return GridGeometry(res, 0.0, 0.0, n, n)


def free_values(geom: GridGeometry) -> np.ndarray:
    return np.zeros(geom.shape, dtype=np.int8)


# --- inflation -----------------------------------------------------------------------------------


def test_inflation_cost_equals_nav2_formula_at_hand_computed_distances() -> None:
    # int(252 * exp(-3 (d - 0.2))): d=0.3 -> 186.69, d=0.5 -> 102.46, d=0.55 -> 88.18.
    d = np.array([0.0, 0.1, 0.2, 0.3, 0.5, 0.55, 0.56, 1.0])
    expected = [LETHAL, INSCRIBED, INSCRIBED, 186, 102, 88, FREE, FREE]
    assert inflation_cost(d, CFG).tolist() == expected
    assert int(inflation_cost(0.3, CFG)) == int(252 * math.exp(-3.0 * 0.1))


def test_inflation_around_one_lethal_cell_uses_euclidean_cell_distances() -> None:
    geom = free_geometry(21)
    values = free_values(geom)
    values[10, 10] = 100
    m = Costmap(geom, CFG, values).master()
    assert m[10, 10] == LETHAL
    assert m[10, 11] == INSCRIBED and m[12, 10] == INSCRIBED  # 0.1 m, 0.2 m
    assert m[10, 13] == 186  # 0.3 m
    assert m[13, 14] == 102  # (3, 4) cells: 0.5 m
    assert m[10, 16] == FREE  # 0.6 m is beyond the inflation radius
    assert m[13, 13] == int(252 * math.exp(-3.0 * (math.hypot(0.3, 0.3) - 0.2))) == 128


def test_inflation_keeps_the_higher_of_old_and_inflated_cost() -> None:
    geom = free_geometry(21)
    values = free_values(geom)
    values[10, 10] = 100
    values[10, 14] = 100  # 0.4 m apart: the cell between is inscribed from both
    m = Costmap(geom, CFG, values).master()
    assert m[10, 12] == INSCRIBED
    assert m[10, 14] == LETHAL


# --- static layer and unknown handling -----------------------------------------------------------


def test_tiny_hand_drawn_grid_static_costs() -> None:
    values = np.array([[0, 100, -1], [50, 99, 0]], dtype=np.int8)
    tracked = static_costs(values, NO_INFLATION)
    assert tracked.tolist() == [[FREE, LETHAL, NO_INFORMATION], [FREE, FREE, FREE]]
    untracked = CostmapConfig(track_unknown_space=False, inflation_radius=0.0)
    assert static_costs(values, untracked)[0, 2] == FREE
    scaled = CostmapConfig(trinary_costmap=False, inflation_radius=0.0)
    assert static_costs(values, scaled)[1].tolist() == [127, 251, FREE]  # int(v / 100 * 254)


def test_static_layer_from_occupancy_grid_uses_map_thresholds() -> None:
    geom = GridGeometry(0.1, -1.0, -1.0, 3, 2)
    grid = OccupancyGrid.from_occupancy_values(geom, np.array([[100, 0, -1], [0, 0, 100]]))
    m = Costmap.from_grid(grid, NO_INFLATION).master()
    assert m.tolist() == [[LETHAL, FREE, NO_INFORMATION], [FREE, FREE, LETHAL]]


def test_unknown_cells_take_only_inscribed_inflation_unless_inflate_unknown() -> None:
    geom = free_geometry(21)
    values = np.full(geom.shape, -1, dtype=np.int8)
    values[10, 10] = 100
    m = Costmap(geom, CFG, values).master()
    assert m[10, 12] == INSCRIBED  # >= INSCRIBED overwrites unknown
    assert m[10, 13] == NO_INFORMATION  # 186 does not
    inflate_unknown = CostmapConfig(**{**CFG.__dict__, "inflate_unknown": True})
    assert Costmap(geom, inflate_unknown, values).master()[10, 13] == 186


def test_inflate_around_unknown_treats_unknown_as_a_source() -> None:
    geom = free_geometry(21)
    values = free_values(geom)
    values[10, 10] = -1
    assert Costmap(geom, CFG, values).master()[10, 11] == FREE
    around = CostmapConfig(**{**CFG.__dict__, "inflate_around_unknown": True})
    assert Costmap(geom, around, values).master()[10, 11] == INSCRIBED


def test_laser_turns_unknown_static_cells_free() -> None:
    geom = free_geometry(41)
    values = np.full(geom.shape, -1, dtype=np.int8)
    cm = Costmap(geom, NO_INFLATION, values)
    cm.update_scan(scan([1.0]), Pose2(0.55, 0.55, 0.0))  # beam along row 5, cols 5..15
    m = cm.master()
    assert np.all(m[5, 5:15] == FREE)
    assert m[5, 15] == LETHAL
    assert m[6, 10] == NO_INFORMATION


# --- obstacle layer ------------------------------------------------------------------------------


def test_obstacle_marked_then_cleared_when_a_later_scan_passes_through() -> None:
    geom = free_geometry(41)
    cm = Costmap(geom, NO_INFLATION, free_values(geom))
    pose = Pose2(0.55, 0.55, 0.0)
    cm.update_scan(scan([1.0]), pose)  # a person 1 m ahead
    assert cm.cost_at(1.55, 0.55) == LETHAL
    cm.update_scan(scan([2.0]), pose)  # they walked off; the wall behind is 2 m away
    assert cm.cost_at(1.55, 0.55) == FREE
    assert cm.cost_at(2.55, 0.55) == LETHAL


def test_no_return_beam_clears_only_with_inf_is_valid() -> None:
    geom = free_geometry(41)
    pose = Pose2(0.55, 0.55, 0.0)
    for inf_is_valid, after in ((True, FREE), (False, LETHAL)):
        cfg = CostmapConfig(inflation_radius=0.0, inf_is_valid=inf_is_valid)
        cm = Costmap(geom, cfg, free_values(geom))
        cm.update_scan(scan([1.0]), pose)
        cm.update_scan(scan([math.inf]), pose)
        assert cm.cost_at(1.55, 0.55) == after


def test_marking_and_clearing_respect_their_ranges() -> None:
    geom = free_geometry(41)
    cfg = CostmapConfig(inflation_radius=0.0, obstacle_max_range=1.5, raytrace_max_range=2.0)
    cm = Costmap(geom, cfg, free_values(geom))
    pose = Pose2(0.55, 0.55, 0.0)
    cm.update_scan(scan([1.2]), pose)
    cm.update_scan(scan([1.8]), pose)  # beyond obstacle_max_range: clears, does not mark
    assert cm.cost_at(1.75, 0.55) == FREE
    assert cm.cost_at(2.35, 0.55) == FREE
    cm.update_scan(scan([1.0]), pose)
    cm.update_scan(scan([3.0]), pose)  # clears up to 2 m only
    assert cm.cost_at(1.55, 0.55) == FREE


def test_static_walls_are_not_cleared_by_raytracing() -> None:
    geom = free_geometry(41)
    values = free_values(geom)
    values[:, 15] = 100  # a wall at x in [1.5, 1.6)
    cm = Costmap(geom, NO_INFLATION, values)
    # Beams that (unphysically) pass through the wall clear the cells before and after it.
    cm.update_scan(scan([2.0] * 20, angle_min=-0.1), Pose2(0.55, 0.55, 0.0))
    assert np.all(cm.master()[:, 15] == LETHAL)
    assert cm.cost_at(1.45, 0.55) == FREE
    assert cm.cost_at(2.55, 0.55) == LETHAL


def test_reset_obstacles_forgets_marks() -> None:
    geom = free_geometry(41)
    cm = Costmap(geom, NO_INFLATION, free_values(geom))
    cm.update_scan(scan([1.0]), Pose2(0.55, 0.55, 0.0))
    cm.reset_obstacles()
    assert cm.cost_at(1.55, 0.55) == FREE


# --- keepout filter ------------------------------------------------------------------------------


def keepout_mask() -> tuple[GridGeometry, np.ndarray]:
    """10 cm mask over [-1, 1]^2 keeping out x in [0.5, 0.7), y in [0.2, 0.4)."""
    geom = GridGeometry(0.1, -1.0, -1.0, 20, 20)
    values = np.zeros(geom.shape, dtype=np.int8)
    values[12:14, 15:17] = 100
    return geom, values


def test_keepout_mask_with_other_origin_and_resolution_lands_on_world_cells() -> None:
    geom = GridGeometry(0.05, 0.0, 0.0, 40, 40)  # 5 cm over [0, 2]^2
    cm = Costmap(geom, NO_INFLATION, np.zeros(geom.shape, np.int8))
    cm.set_keepout(keepout_mask())
    m = cm.master()
    xs, ys = geom.cell_centres()
    inside = (xs > 0.5) & (xs < 0.7) & (ys > 0.2) & (ys < 0.4)
    assert inside.sum() == 16
    assert np.all(m[inside] == LETHAL)
    assert np.all(m[~inside] == FREE)
    assert cm.cost_at(0.6, 0.3) == LETHAL and cm.cost_at(0.45, 0.3) == FREE
    assert not cm.is_free(0.6, 0.3)


def test_keepout_is_applied_after_inflation_in_nav2_order() -> None:
    geom = GridGeometry(0.05, 0.0, 0.0, 40, 40)
    cm = Costmap(geom, replace(CFG, inflate_keepout=False), np.zeros(geom.shape, np.int8))
    cm.set_keepout(keepout_mask())
    assert cm.cost_at(0.45, 0.3) == FREE


def test_inflated_keepout_keeps_the_whole_footprint_out() -> None:
    geom = GridGeometry(0.05, 0.0, 0.0, 40, 40)
    cm = Costmap(geom, CFG, np.zeros(geom.shape, np.int8))  # inflate_keepout: the default
    cm.set_keepout(keepout_mask())
    assert cm.cost_at(0.6, 0.3) == LETHAL  # in the zone
    assert cm.cost_at(0.35, 0.3) == INSCRIBED  # 0.15 m from it: the footprint would overlap
    assert cm.cost_at(0.25, 0.3) < INSCRIBED  # 0.25 m: clear of it, inflated cost
    assert cm.cost_at(0.25, 0.3) > FREE


def test_keepout_mask_from_map_yaml(tmp_path: Path) -> None:
    mask_geom, values = keepout_mask()
    save_map_yaml(OccupancyGrid.from_occupancy_values(mask_geom, values), tmp_path / "k.yaml")
    geom = GridGeometry(0.05, 0.0, 0.0, 40, 40)
    cm = Costmap(geom, NO_INFLATION, np.zeros(geom.shape, np.int8))
    cm.set_keepout_yaml(tmp_path / "k.yaml")
    assert cm.cost_at(0.6, 0.3) == LETHAL
    assert cm.cost_at(0.6, 0.45) == FREE


def test_mask_values_scale_and_unknown_is_skipped() -> None:
    assert mask_costs(np.array([0, 50, 100, -1])).tolist() == [0, 127, LETHAL, NO_INFORMATION]
    geom = GridGeometry(0.1, 0.0, 0.0, 2, 1)
    cm = Costmap(geom, NO_INFLATION, np.array([[100, -1]], np.int8))
    cm.set_keepout((geom, np.array([[0, 0]], np.int8)))
    assert cm.master().tolist() == [[LETHAL, FREE]]  # keepout never lowers; fills unknown


def test_mask_that_does_not_overlap_the_map_is_refused() -> None:
    geom = GridGeometry(0.05, 0.0, 0.0, 40, 40)
    cm = Costmap(geom, NO_INFLATION, np.zeros(geom.shape, np.int8))
    far = GridGeometry(0.1, 50.0, 50.0, 20, 20)
    with pytest.raises(MapError, match="does not overlap"):
        cm.set_keepout((far, np.zeros(far.shape, np.int8)))
    with pytest.raises(MapError, match="do not match"):
        cm.set_keepout((far, np.zeros((3, 3), np.int8)))


# --- queries -------------------------------------------------------------------------------------


def test_outside_the_map_is_lethal_and_master_is_read_only() -> None:
    geom = free_geometry(5)
    cm = Costmap(geom, NO_INFLATION, free_values(geom))
    assert cm.cost_at(-0.01, 0.2) == LETHAL
    assert cm.is_free(np.array([0.2, 0.6]), np.array([0.2, 0.2])).tolist() == [True, False]
    with pytest.raises(ValueError):
        cm.master()[0, 0] = 1


def test_static_values_must_match_the_geometry() -> None:
    with pytest.raises(MapError, match="do not match"):
        Costmap(free_geometry(5), NO_INFLATION, np.zeros((4, 5), np.int8))


@pytest.mark.parametrize("around_unknown", [False, True])
def test_incremental_master_equals_full_recompute(around_unknown: bool) -> None:
    rng = np.random.default_rng(7)
    geom = GridGeometry(0.05, -5.0, -5.0, 200, 200)
    values = rng.choice(np.array([0, 100, -1], np.int8), size=geom.shape, p=[0.97, 0.01, 0.02])
    cfg = CostmapConfig(inflate_around_unknown=around_unknown, inflate_unknown=True)
    incremental = Costmap(geom, cfg, values)
    full = Costmap(geom, cfg, values)
    incremental.set_keepout(keepout_mask())
    full.set_keepout(keepout_mask())
    incremental.master()
    for i in range(8):
        ranges = rng.uniform(0.3, 4.0, 90).astype(np.float32)
        ranges[rng.random(90) < 0.2] = np.inf
        s = LaserScan(0, -0.8, 0.02, ranges, 0.1, 4.0)
        pose = Pose2(-3.0 + 0.7 * i, rng.uniform(-2.0, 2.0), rng.uniform(-np.pi, np.pi))
        incremental.update_scan(s, pose)
        full.update_scan(s, pose)
        if i % 3 == 0:
            incremental.master()
    np.testing.assert_array_equal(incremental.master(), full.master())


def test_obstacle_count_is_what_the_obstacle_layer_marks_until_reset() -> None:
    geom = GridGeometry(0.05, 0.0, 0.0, 40, 40)
    cm = Costmap(geom, NO_INFLATION, np.zeros(geom.shape, np.int8))
    assert cm.obstacle_count() == 0
    cm.update_scan(scan([1.0]), Pose2(0.5, 1.0, 0.0))  # one return at x = 1.5
    assert cm.obstacle_count() == 1
    cm.reset_obstacles()
    assert cm.obstacle_count() == 0
