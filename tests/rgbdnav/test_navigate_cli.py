"""`rgbdnav navigate` as a user meets it: a 6 m x 4 m room with a box the map does not know about,
goals driven in order in the kinematic simulation, a goal in a wall or a keepout zone refused with
a reason while the run goes on, and a missing map ending in one line."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.navigate_run import cast_scan, parse_goal_args, unicycle_step
from sensors.sim.world import FloorPlan, floor_plan, load_world
from sensors.tum import load_tum_trajectory
from sensors.types import ConfigError
from slam.map_bundle import save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid

runner = CliRunner()
BOX_CENTRE = (3.0, 2.0)  # [m] the box the map does not have
BOX_HALF = 0.3  # [m]
ROBOT_RADIUS = 0.23  # [m] costmap.robot_radius default
ROOM = {
    "name": "room",
    "wall_thickness": 0.1,
    "walls": [{"from": [0, 0], "to": [6, 0]}, {"from": [6, 0], "to": [6, 4]},
              {"from": [6, 4], "to": [0, 4]}, {"from": [0, 4], "to": [0, 0]}],
    "start": [1.0, 2.0, 0.0],
    "route": [[5.0, 2.0]],
}  # fmt: skip


def _grid(plan: FloorPlan, values: np.ndarray) -> OccupancyGrid:
    h, w = plan.occupied.shape
    return OccupancyGrid.from_occupancy_values(
        GridGeometry(plan.resolution, plan.origin_x, plan.origin_y, w, h), values
    )


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """world.yaml (room + box), map.yaml (room only: the box is unknown to the navigator) and a
    keepout mask over the top-right corner."""
    d = tmp_path_factory.mktemp("room")
    (d / "bare.yaml").write_text(yaml.safe_dump(ROOM))
    world = dict(ROOM, furniture=[{"name": "box", "center": list(BOX_CENTRE),
                                   "size": [2 * BOX_HALF, 2 * BOX_HALF, 0.8]}])  # fmt: skip
    (d / "world.yaml").write_text(yaml.safe_dump(world))
    plan = floor_plan(load_world(d / "bare.yaml"))
    save_map_yaml(_grid(plan, np.where(plan.occupied, 100, 0)), d / "map.yaml")
    x, y = (c.ravel() for c in np.meshgrid(
        plan.origin_x + (np.arange(plan.occupied.shape[1]) + 0.5) * plan.resolution,
        plan.origin_y + (np.arange(plan.occupied.shape[0]) + 0.5) * plan.resolution))  # fmt: skip
    keep = ((x > 4.5) & (y > 2.8)).reshape(plan.occupied.shape)
    save_map_yaml(_grid(plan, np.where(keep, 100, 0)), d / "keepout.yaml")
    return {"world": d / "world.yaml", "map": d / "map.yaml", "keepout": d / "keepout.yaml"}


def _navigate(scene: dict[str, Path], out: Path, *args: str) -> tuple[int, str, dict]:
    result = runner.invoke(app, ["navigate", "--map", str(scene["map"]), "--sim",
                                 str(scene["world"]), "--out", str(out), "-q", *args])  # fmt: skip
    summary = {}
    if (out / "summary.json").is_file():
        summary = json.loads((out / "summary.json").read_text())
    return result.exit_code, result.output, summary


def test_two_goals_are_reached_around_a_box_missing_from_the_map(
    scene: dict[str, Path], tmp_path: Path
) -> None:
    # Facing away from the box at the start, the first plan runs straight through it; the camera
    # sees it once the robot turns, and the path is replanned around it.
    code, output, summary = _navigate(scene, tmp_path, "--start", "1.0", "2.0", str(math.pi),
                                      "--goal", "5.0", "2.0", "--goal", "1.0", "3.0")  # fmt: skip
    assert code == 0, output
    assert "2/2 goals reached" in output
    assert [g["status"] for g in summary["goals"]] == ["reached", "reached"]
    assert summary["goals"][0]["replans"] >= 1
    for g in summary["goals"]:
        assert g["final_error_m"] <= 0.25 + 1e-6  # follower.xy_goal_tolerance
    assert summary["collisions"]["events"] == 0
    assert summary["collisions"]["min_clearance_m"] >= ROBOT_RADIUS
    assert "ground truth" in summary["localisation"]
    for name in ("trajectory.tum", "commands.csv", "summary.json", "map.png", "config.yaml"):
        assert (tmp_path / name).is_file(), name
    _, xyz, _ = load_tum_trajectory(tmp_path / "trajectory.tum")
    x, y = xyz[:, 0], xyz[:, 1]
    d_box = np.hypot(x - BOX_CENTRE[0], y - BOX_CENTRE[1])
    assert d_box.min() > BOX_HALF + ROBOT_RADIUS - 0.05  # went around, not through
    assert summary["path_length_m"] == pytest.approx(
        float(np.hypot(np.diff(x), np.diff(y)).sum()), abs=0.01
    )
    with open(tmp_path / "commands.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(x)
    smoothed = np.array([float(r["smoothed_v_mps"]) for r in rows])
    assert np.abs(np.diff(smoothed)).max() <= 2.5 * 0.05 + 1e-6  # smoother.max_accel * period
    assert abs(smoothed[-1]) < 1e-2  # at rest at the end


def test_a_goal_in_a_wall_is_refused_and_the_run_goes_on(
    scene: dict[str, Path], tmp_path: Path
) -> None:
    code, output, summary = _navigate(scene, tmp_path, "--goal", "0.0", "2.0",
                                      "--goal", "1.5", "1.0")  # fmt: skip
    assert code == 0, output
    first, second = summary["goals"]
    assert first["status"] == "refused"
    assert "wall" in first["reason"]
    assert "refused: goal (0.00, 2.00) is in a wall" in output
    assert second["status"] == "reached"
    assert summary["counts"] == {"reached": 1, "failed": 0, "refused": 1}


def test_a_goal_in_a_keepout_zone_is_refused(scene: dict[str, Path], tmp_path: Path) -> None:
    code, output, summary = _navigate(scene, tmp_path, "--keepout", str(scene["keepout"]),
                                      "--goal", "5.2", "3.3")  # fmt: skip
    assert code == 0, output
    (goal,) = summary["goals"]
    assert goal["status"] == "refused"
    assert "keepout" in goal["reason"]
    assert summary["path_length_m"] == pytest.approx(0.0, abs=1e-9)  # never moved


def test_a_missing_map_is_a_one_line_error(scene: dict[str, Path], tmp_path: Path) -> None:
    result = runner.invoke(app, ["navigate", "--map", str(tmp_path / "nope.yaml"), "--sim",
                                 str(scene["world"]), "--out", str(tmp_path / "run"), "-q",
                                 "--goal", "1", "1"])  # fmt: skip
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "no such map" in lines[0]
    assert not (tmp_path / "run").exists()


def test_goal_arguments_are_pairs_of_numbers() -> None:
    assert parse_goal_args(["--goal", "1", "-2.5", "-g", "3e0", "4"]) == [(1.0, -2.5), (3.0, 4.0)]
    with pytest.raises(ConfigError, match="two numbers"):
        parse_goal_args(["--goal", "1"])
    with pytest.raises(ConfigError, match="unexpected argument"):
        parse_goal_args(["--gaol", "1", "2"])


def test_cast_scan_returns_the_wall_distance() -> None:
    occupied = np.zeros((40, 40), dtype=bool)
    occupied[:, 30] = True  # a wall at x = 3.0 .. 3.1 m
    plan = FloorPlan(occupied, 0.1, 0.0, 0.0)
    angles = np.array([-0.3, 0.0, 0.3])
    r = cast_scan(plan, np.array([1.0, 2.0, 0.0]), angles, 0.5, 4.5)
    np.testing.assert_allclose(r, 2.0 / np.cos(angles), atol=0.06)  # half a cell of marching
    assert np.isinf(cast_scan(plan, np.array([1.0, 2.0, math.pi]), angles, 0.5, 4.5)).all()
    assert np.isnan(cast_scan(plan, np.array([2.8, 2.0, 0.0]), angles[1:2], 0.5, 4.5)).all()


def test_unicycle_step_drives_an_arc_of_the_commanded_radius() -> None:
    pose = np.array([0.0, 0.0, 0.0])
    for _ in range(100):  # a quarter circle of radius 1 m in 100 steps
        pose = unicycle_step(pose, math.pi / 2, math.pi / 2, 0.01)
    np.testing.assert_allclose(pose, [1.0, 1.0, math.pi / 2], atol=1e-4)
