"""The navigation target scenario: furniture moved (seeded) relative to the map, goals drawn where
a robot can reach them, keepout zones as a filter mask; and a reduced run of it in the house."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from sensors.sim.world import load_world, world_from_dict
from sensors.types import ConfigError
from slam.map_bundle import load_map_yaml
from slam.occupancy_grid import GridGeometry

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

from nav_scenario import (  # noqa: E402  (bench/ is no package)
    draw_goals,
    floor_plan_map,
    goal_candidates,
    keepout_grid,
    load_scenario,
    move_furniture,
    run_scenario,
)

REPO = Path(__file__).resolve().parents[2]
HOUSE = REPO / "scenes" / "house.yaml"
SCENARIO = REPO / "scenes" / "scenarios" / "nav_house.yaml"


def test_furniture_moves_within_the_bounds_and_walls_stay() -> None:
    world = yaml.safe_load(HOUSE.read_text())
    a = move_furniture(world, np.random.default_rng(5), 0.3, 0.2)
    b = move_furniture(world, np.random.default_rng(5), 0.3, 0.2)
    assert a == b and a["walls"] == world["walls"]
    assert a is not world and world["furniture"][0]["center"] == [1.2, 0.5]  # input untouched
    d = np.array(
        [
            np.subtract(m["center"], f["center"])
            for m, f in zip(a["furniture"], world["furniture"], strict=True)
        ]
    )
    yaw = np.array(
        [
            m["yaw"] - f.get("yaw", 0.0)
            for m, f in zip(a["furniture"], world["furniture"], strict=True)
        ]
    )
    assert np.abs(d).max() <= 0.3 + 1e-4 and np.abs(yaw).max() <= 0.2 + 1e-4
    assert np.abs(d).mean() > 0.05  # they did move
    world_from_dict(a)  # still a valid world


def test_keepout_grid_marks_cells_whose_centre_is_in_a_box() -> None:
    geo = GridGeometry(0.5, 0.0, 0.0, 6, 4)  # 3 m x 2 m
    mask = keepout_grid(geo, [(1.0, 0.5, 2.0, 1.5)]).occupied_mask()
    expected = np.zeros((4, 6), dtype=bool)
    expected[1:3, 2:4] = True  # centres 1.25, 1.75 in x and 0.75, 1.25 in y
    np.testing.assert_array_equal(mask, expected)


def test_goal_candidates_need_clearance_reachability_and_no_keepout() -> None:
    # 20 x 20 cells of 0.1 m; a wall at column 10 with no door: the right half is unreachable.
    occ = np.zeros((20, 20), dtype=bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    occ[:, 10] = True
    free = ~occ
    world = occ.copy()
    world[4:6, 4:6] = True  # moved furniture the map does not have
    keep = np.zeros_like(occ)
    keep[14:17, 2:5] = True
    cand = goal_candidates(free, occ, world, keep, (10, 5), 0.1, 0.25, 0.15)
    rows, cols = np.nonzero(cand)
    assert len(rows) > 0 and cols.max() < 10  # only the start's side
    xy = np.column_stack([cols + 0.5, rows + 0.5]) * 0.1
    walls = np.column_stack(np.nonzero(occ))[:, ::-1] * 0.1 + 0.05
    d_wall = np.min(np.hypot(*(xy[:, None, :] - walls[None]).transpose(2, 0, 1)), axis=1)
    assert d_wall.min() >= 0.25 - 1e-9
    assert not cand[3:7, 3:7].any()  # too close to the moved furniture
    assert not cand[13:18, 1:6].any()  # in or next to the keepout zone


def test_drawn_goals_keep_their_separation_and_repeat_per_seed() -> None:
    cand = np.zeros((30, 30), dtype=bool)
    cand[5:25, 5:25] = True
    geo = GridGeometry(0.1, 0.0, 0.0, 30, 30)
    goals = draw_goals(cand, geo, np.random.default_rng(1), 8, (0.5, 0.5), 1.0)
    assert goals == draw_goals(cand, geo, np.random.default_rng(1), 8, (0.5, 0.5), 1.0)
    pts = np.array([(0.5, 0.5), *goals])
    assert np.hypot(*np.diff(pts, axis=0).T).min() >= 1.0
    with pytest.raises(ConfigError, match="no candidate cell is 5.0 m"):
        draw_goals(cand, geo, np.random.default_rng(1), 2, (1.0, 1.0), 5.0)
    with pytest.raises(ConfigError, match="no cell qualifies"):
        draw_goals(np.zeros_like(cand), geo, np.random.default_rng(1), 1, (0.0, 0.0), 1.0)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("world: house.yaml\nspeed: 3\n", "speed: unknown key"),
        ("goals: 3\n", "missing 'world'"),
        ("world: nope.yaml\n", "nope.yaml"),
        ("world: house.yaml\nkeepout: [[1, 2, 0, 3]]\n", r"keepout\[0\]"),
        ("world: house.yaml\nfurniture_shift: -1\n", "furniture_shift must be a number >= 0"),
    ],
)
def test_bad_scenario_files_are_refused_with_the_key(text: str, match: str) -> None:
    path = REPO / "scenes" / "_test_scenario.yaml"  # beside house.yaml: 'world' is relative
    try:
        path.write_text(text)
        with pytest.raises(ConfigError, match=match):
            load_scenario(path)
    finally:
        path.unlink(missing_ok=True)


def test_the_shipped_scenario_loads() -> None:
    sc = load_scenario(SCENARIO)
    assert (sc.goals, sc.seed, len(sc.keepout), sc.goal_tolerance) == (20, 0, 2, 0.25)
    # Only the goal checker: the localiser's settings are the navigate profile's, not the test's.
    assert tuple(sc.overrides) == ("follower.xy_goal_tolerance=0.1",)
    assert sc.world_path == HOUSE.resolve()


@pytest.fixture(scope="module")
def house_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map of the house from its floor plan: walls and furniture at their true size."""
    path = tmp_path_factory.mktemp("house_map") / "map.yaml"
    return floor_plan_map(load_scenario(SCENARIO), path)


def test_the_floor_plan_map_has_the_world_walls_faces_where_a_scan_sees_them(
    house_map: Path,
) -> None:
    # A wall drawn one cell thick on its centre line would put the map's wall half a wall
    # thickness (6 cm) behind the face every scan hits: a bias of the map.
    grid = load_map_yaml(house_map)
    occ = grid.occupied_mask()
    g = grid.geometry
    thickness = load_scenario(SCENARIO).world["wall_thickness"]  # [m] 0.12
    assert thickness > 2 * g.resolution
    # The living room / bedroom wall runs along y = 5.0: its faces are at 5.0 -/+ 0.06 m.
    for y, wall in [
        (5.0, True),
        (5.0 - 0.04, True),
        (5.0 + 0.04, True),
        (5.0 - 0.1, False),
        (5.0 + 0.1, False),
    ]:
        assert bool(occ[g.world_to_cell(3.5, y)]) is wall, y
    assert not occ[g.world_to_cell(3.0, 5.0)]  # the door (at 3.0, 1 m wide) is open


def test_reduced_scenario_reaches_every_goal_safely(house_map: Path, tmp_path: Path) -> None:
    # Three of the twenty goals, ground-truth localisation (the localiser's own accuracy is
    # exercised in test_navigate_cli and measured in bench_nav): the navigator must avoid the
    # moved furniture it only sees with the camera and never enter a keepout zone.
    _, summary = run_scenario(SCENARIO, house_map, tmp_path, n_goals=3, localization="groundtruth")
    sc = summary["scenario"]
    assert sc["goals"] == 3
    assert sc["reached_within_tolerance"] == 3, sc["failures"]
    assert sc["collisions"] == 0
    assert sc["keepout_entries"] == 0
    assert sc["min_clearance_m"] >= 0.23  # costmap.robot_radius
    assert sc["min_keepout_distance_m"] > 0.0
    goals = json.loads((tmp_path / "scenario" / "goals.json").read_text())
    assert [g["goal"] for g in summary["goals"]] == [list(g) for g in goals]
    moved = load_world(tmp_path / "scenario" / "world_moved.yaml")
    assert moved.boxes != load_world(HOUSE).boxes
    mask = load_map_yaml(tmp_path / "scenario" / "keepout.yaml").occupied_mask()
    assert mask.any()
