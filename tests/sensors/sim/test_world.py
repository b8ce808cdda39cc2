"""Simulator worlds: the shipped scenes, YAML validation and the ground-truth floor plan."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from scipy import ndimage

from sensors.config import RobotConfig, SimConfig
from sensors.sim.motion import Trajectory, drive_route, replay_tum
from sensors.sim.world import World, floor_plan, load_world, world_from_dict
from sensors.types import WorldError

REPO = Path(__file__).resolve().parents[3]
SCENES = REPO / "scenes"
DATA = REPO.parent / "shared" / "data"
PIONEER_DIR = DATA / "tum" / "pioneer_groundtruth"
SHIPPED = sorted(SCENES.glob("*.yaml"))

RESOLUTION = 0.05  # [m/cell] floor-plan resolution used throughout
ROUTE_MARGIN = 0.1  # [m] driven paths keep at least robot radius + this from obstacles
REPLAY_CLEARANCE = 0.3  # [m] replayed pioneer paths keep at least this from obstacles
LOOP_AFTER = 20.0  # [m] travelled before a return to the start counts as a loop closure
LOOP_RADIUS = 0.5  # [m] how near the start that return must come
MIN_ROOM_AREA = 1.0  # [m^2] free regions smaller than this are slivers, not rooms


def _path_xy(traj: Trajectory) -> np.ndarray:
    return np.column_stack([traj.x, traj.y])


def _travelled(traj: Trajectory) -> np.ndarray:
    """Cumulative distance [m] along the path at every sample."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(traj.x), np.diff(traj.y)))])


def _closes_loop(traj: Trajectory) -> bool:
    later = _travelled(traj) >= LOOP_AFTER
    if not later.any():
        return False
    d = np.hypot(traj.x[later] - traj.x[0], traj.y[later] - traj.y[0])
    return bool(d.min() < LOOP_RADIUS)


def _rooms_without_doors(path: Path) -> int:
    """Connected free regions of the floor plan once every door is walled up, minus the outside
    (the region touching the grid border) and slivers between furniture and walls."""
    data = yaml.safe_load(path.read_text())
    for wall in data["walls"]:
        wall.pop("doors", None)
    plan = floor_plan(world_from_dict(data, source=str(path)), RESOLUTION)
    labels, n = ndimage.label(~plan.occupied)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    sizes = np.bincount(labels.ravel(), minlength=n + 1) * RESOLUTION**2
    rooms = [k for k in range(1, n + 1) if k not in border and sizes[k] >= MIN_ROOM_AREA]
    return len(rooms)


@pytest.fixture(scope="module")
def driven() -> dict[str, tuple[World, Trajectory]]:
    """Every shipped world with the path its route drives (computed once per module)."""
    out = {}
    for path in SHIPPED:
        world = load_world(path)
        out[path.stem] = (world, drive_route(world, SimConfig()))
    return out


# --- shipped worlds ---------------------------------------------------------------------------


def test_house_office_and_pioneer_hall_are_shipped():
    assert {"house", "office", "pioneer_hall"} <= {p.stem for p in SHIPPED}


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_world_route_keeps_robot_clear_of_obstacles(path, driven):
    world, traj = driven[path.stem]
    clearance = floor_plan(world, RESOLUTION).clearance(_path_xy(traj))
    assert clearance.min() > RobotConfig().radius + ROUTE_MARGIN


@pytest.mark.parametrize("name", ["house", "office"])
def test_route_is_at_least_40_m_and_closes_a_loop(name, driven):
    world, traj = driven[name]
    assert world.route_length() >= 40.0
    assert traj.length_m() >= 40.0
    assert _closes_loop(traj)


def test_house_has_at_least_four_rooms():
    assert _rooms_without_doors(SCENES / "house.yaml") >= 4


def test_office_is_a_corridor_ring_around_three_offices():
    assert _rooms_without_doors(SCENES / "office.yaml") == 4


def test_loop_closure_check_rejects_an_open_path():
    x = np.linspace(0.0, 30.0, 301)
    open_path = Trajectory(np.arange(301, dtype=np.int64), x, 0 * x, 0 * x, 0 * x, 0 * x)
    assert not _closes_loop(open_path)


@pytest.mark.skipif(not PIONEER_DIR.is_dir(), reason="../shared/data (TUM pioneer) not present")
@pytest.mark.parametrize("name", ["pioneer_360", "pioneer_slam", "pioneer_slam2", "pioneer_slam3"])
def test_pioneer_replay_stays_clear_of_the_hall_boxes(name):
    traj = replay_tum(PIONEER_DIR / f"{name}.groundtruth.txt", RobotConfig(), SimConfig())
    plan = floor_plan(load_world(SCENES / "pioneer_hall.yaml"), RESOLUTION)
    assert plan.clearance(_path_xy(traj)).min() >= REPLAY_CLEARANCE
    assert 10.0 <= traj.length_m() <= 60.0


# --- validation -------------------------------------------------------------------------------

MINIMAL: dict[str, Any] = {
    "name": "tiny",
    "walls": [{"from": [0, 0], "to": [5, 0]}],
    "furniture": [{"name": "box", "center": [2.5, 2.0], "size": [1.0, 1.0, 1.0]}],
    "start": [0.5, 1.0, 0.0],
    "route": [[4.5, 1.0]],
}


def _minimal() -> dict[str, Any]:
    return copy.deepcopy(MINIMAL)


def test_minimal_world_loads():
    world = world_from_dict(_minimal())
    assert world.name == "tiny"
    assert len(world.boxes) == 2
    assert world.route_length() == pytest.approx(4.0, abs=1e-12)


def test_unknown_top_level_key_is_rejected():
    data = _minimal() | {"furnitur": []}
    with pytest.raises(WorldError, match=r"furnitur: unknown key"):
        world_from_dict(data)


def test_door_leaving_its_wall_is_rejected():
    data = _minimal()
    data["walls"][0]["doors"] = [{"at": 4.8, "width": 0.9}]
    with pytest.raises(WorldError, match=r"walls\[0\]\.doors\[0\].*leaves the wall"):
        world_from_dict(data)


def test_overlapping_doors_are_rejected():
    data = _minimal()
    data["walls"][0]["doors"] = [{"at": 2.0, "width": 1.0}, {"at": 2.6, "width": 1.0}]
    with pytest.raises(WorldError, match=r"doors\[1\]: door overlaps the previous door"):
        world_from_dict(data)


def test_zero_length_wall_is_rejected():
    data = _minimal()
    data["walls"].append({"from": [1, 1], "to": [1, 1]})
    with pytest.raises(WorldError, match=r"walls\[1\]: wall has zero length"):
        world_from_dict(data)


def test_missing_route_is_rejected():
    data = _minimal()
    del data["route"]
    with pytest.raises(WorldError, match=r"route: expected a non-empty list"):
        world_from_dict(data)


def test_non_numeric_size_is_rejected():
    data = _minimal()
    data["furniture"][0]["size"] = [1.0, "wide", 1.0]
    with pytest.raises(WorldError, match=r"furniture\[0\]\.size: expected a list of 3 numbers"):
        world_from_dict(data)


def test_negative_furniture_size_is_rejected():
    data = _minimal()
    data["furniture"][0]["size"] = [1.0, -0.5, 1.0]
    with pytest.raises(WorldError, match=r"furniture\[0\]\.size: all sizes must be > 0"):
        world_from_dict(data)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (
            lambda d: d["walls"][0].update({"from": [float("nan"), 0]}),
            r"walls\[0\]\.from: expected a list of 2 numbers \(finite\), got \[nan, 0\]",
        ),
        (lambda d: d["walls"][0].update({"to": [float("inf"), 0]}), r"walls\[0\]\.to: expected"),
        (
            lambda d: d["walls"][0].update({"to": [1e9, 0]}),
            r"walls\[0\]\.to: .* farther than 1000 m",
        ),
        (
            lambda d: d["walls"][0].update({"thickness": -0.1}),
            r"walls\[0\]\.thickness: must be > 0, got -0\.1",
        ),
        (
            lambda d: d["walls"][0].update({"texture_scale": 0}),
            r"texture_scale: must be > 0, got 0",
        ),
        (
            lambda d: d.update({"floor": {"texture": "wood", "scale": 0}}),
            r"floor\.scale: must be > 0",
        ),
        (
            lambda d: d.update({"start": [2.5, 2.0, 0.0]}),
            r"start \(2\.5, 2\) is inside a wall or furniture",
        ),
    ],
)
def test_a_world_no_simulator_can_build_is_rejected_naming_the_entry(edit, match):
    data = _minimal()
    edit(data)
    with pytest.raises(WorldError, match=match):
        world_from_dict(data)


def test_missing_file_is_reported_as_unreadable(tmp_path):
    with pytest.raises(WorldError, match=r"cannot read world file"):
        load_world(tmp_path / "nowhere.yaml")


def test_file_that_is_not_yaml_is_rejected(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("walls: [{from: [0, 0], to: [5, 0]\nroute: ]]\n")
    with pytest.raises(WorldError, match=r"broken\.yaml: not valid YAML"):
        load_world(path)


def test_yaml_that_is_not_a_mapping_is_rejected(tmp_path):
    path = tmp_path / "list.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(WorldError, match=r"top level must be a mapping"):
        load_world(path)


def test_world_file_round_trips_through_yaml(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(_minimal()))
    world = load_world(path)
    assert world.source == str(path)
    np.testing.assert_allclose(world.route, [[4.5, 1.0]])


# --- floor plan -------------------------------------------------------------------------------


def test_one_metre_box_fills_a_20_by_20_cell_block_in_the_right_place():
    plan = floor_plan(world_from_dict(_minimal()), RESOLUTION)
    # Bounds: wall footprint x 0..5, y -0.05..0.05, grown by 0.5 m -> origin (-0.5, -0.55).
    assert (plan.origin_x, plan.origin_y) == pytest.approx((-0.5, -0.55), abs=1e-12)
    rows, cols = np.nonzero(plan.occupied)
    box = rows > 20  # the wall occupies rows 10..11 only
    # The box spans x 2..3, y 1.5..2.5: cols (2 + 0.5) / 0.05 = 50..69, rows 2.05 / 0.05 = 41..60
    # (cv2.fillPoly fills edge cells whose centres lie on the boundary, so one more may appear).
    r0, r1, c0, c1 = rows[box].min(), rows[box].max(), cols[box].min(), cols[box].max()
    assert (r0, r1, c0, c1) == pytest.approx((41, 60, 50, 69), abs=1)
    assert plan.occupied[r0 : r1 + 1, c0 : c1 + 1].all()


def test_row_zero_is_the_bottom_of_the_plan():
    plan = floor_plan(world_from_dict(_minimal()), RESOLUTION)
    # The wall at y = 0 is 0.55 m above the origin: rows near 11, not near the top of the grid.
    wall_rows = np.nonzero(plan.occupied[:, plan.occupied.shape[1] // 2])[0]
    assert wall_rows.min() >= 9
    assert wall_rows.min() <= 12


def test_boxes_above_or_below_the_height_band_are_not_in_the_plan():
    data = _minimal()
    data["furniture"] = [
        {"name": "shelf_on_wall", "center": [1.5, 2.0], "size": [0.6, 0.6, 0.3], "elevation": 2.0},
        {"name": "floor_mat", "center": [3.5, 2.0], "size": [0.6, 0.6, 0.03]},
    ]
    data["walls"][0]["doors"] = [{"at": 2.5, "width": 1.0}]  # its lintel is at 2.0..2.5 m
    world = world_from_dict(data)
    assert {b.name for b in world.boxes} >= {"lintel", "shelf_on_wall", "floor_mat"}
    plan = floor_plan(world, RESOLUTION, z_min=0.05, z_max=1.5)
    probes = np.array([[1.5, 2.0], [3.5, 2.0], [2.5, 0.0], [0.5, 0.0]])
    rc = plan.cell_of(probes)
    assert plan.occupied[rc[:, 0], rc[:, 1]].tolist() == [False, False, False, True]


def test_clearance_one_metre_from_a_wall_is_one_metre():
    data = _minimal()
    data["furniture"] = []
    plan = floor_plan(world_from_dict(data), RESOLUTION)
    face_y = 0.05  # [m] the default 0.1 m thick wall along y = 0
    clearance = plan.clearance(np.array([[2.5, face_y + 1.0]]))
    assert clearance[0] == pytest.approx(1.0, abs=0.05)


def test_clearance_outside_the_plan_is_zero():
    plan = floor_plan(world_from_dict(_minimal()), RESOLUTION)
    assert plan.clearance(np.array([[-10.0, -10.0]])).tolist() == [0.0]
