"""Two simulated robots in one world, side by side: two `rgbdnav live --robot NAME` processes,
each with its own simulated camera, board emulator and map in its own folder, and the world
view that draws both in the world frame."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.live.world_view import robot_runs, to_world
from rgbdnav.visualize import occupied_cells_xy
from sensors.tum import load_tum_trajectory
from slam.map_bundle import load_map

# Live runs against the wall clock: `make test` runs these alone, after the parallel part.
pytestmark = pytest.mark.realtime

REPO = Path(__file__).resolve().parents[2]
WORLD = REPO / "scenes" / "house.yaml"
runner = CliRunner()
# The living room and the kitchen of scenes/house.yaml, split by the wall at x = 7 m; each
# robot faces that wall from ~2 m and drives a metre towards its door.
ROBOTS = {
    "r1": ("5.0", "2.5", "0.0", "5.8,2.5"),
    "r2": ("10.0", "2.5", "3.14159", "9.2,2.5"),
}
WALL_X = 7.0


def _live(out: Path, name: str) -> subprocess.Popen:
    x, y, yaw, goal = ROBOTS[name]
    robot = ["--robot", name, "--start", x, y, yaw, "--goal", goal, "--seed", name[1]]
    # 10 Hz cameras: two simulated robots and two hosts share a busy CI machine.
    run = ["--sim-world", str(WORLD), "--duration", "8", "--set", "sim.camera_rate=10", "-q"]
    args = [sys.executable, "-m", "rgbdnav.cli", "live", "--out", str(out), *robot, *run]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        args, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


def test_two_robots_run_side_by_side_each_with_its_own_map_and_one_world_view(
    tmp_path: Path,
) -> None:
    out = tmp_path / "fleet"
    procs = {name: _live(out, name) for name in ROBOTS}  # both at once, nothing shared
    for name, proc in procs.items():
        text, _ = proc.communicate(timeout=240)
        # 3: the run ended normally but its goal was not reached in 8 s (a loaded machine)
        assert proc.returncode in (0, 3), f"{name}: {text}"
    cells = {}
    for name, (x, y, yaw, _) in ROBOTS.items():
        run = out / name
        s = json.loads((run / "summary.json").read_text())
        assert s["errors"] == [] and s["counts"].get("scans_mapped", 0) >= 1
        start = [float(x), float(y), float(yaw)]
        robot = {"name": name, "start_in_world": start, "T_world_map": [0, 0, 0]}
        assert robot.items() <= s["robot"].items()
        assert s["robot"]["T_world_map_from"] == "simulator"
        assert s["robot"]["map"] == str(run / "map") and s["robot"]["keepout"] is None
        # The simulator drove this robot from its own start, and its estimate began there.
        _, truth, _ = load_tum_trajectory(run / "groundtruth.tum")
        _, est, _ = load_tum_trajectory(run / "trajectory.tum")
        assert np.hypot(*(truth[0, :2] - start[:2])) < 0.05
        assert np.hypot(*(est[0, :2] - start[:2])) < 0.2
        loaded = load_map(run / "map")
        g = loaded.grid.geometry
        occ = loaded.grid.occupied_mask(loaded.occupied_thresh)
        cells[name] = to_world(
            tuple(s["robot"]["T_world_map"]),
            occupied_cells_xy(occ, (g.origin_x, g.origin_y), g.resolution),
        )
        assert len(cells[name]) >= 10, name
    # Each map holds its own room's side of the wall: two maps, not one shared.
    assert np.median(cells["r1"][:, 0]) < WALL_X < np.median(cells["r2"][:, 0])

    picture = tmp_path / "world.png"
    result = runner.invoke(app, ["world-view", str(out), "--out", str(picture)])
    assert result.exit_code == 0, result.output
    assert picture.stat().st_size > 5_000
    for name in ROBOTS:
        assert f"{name}  " in result.output and f"world -> {name}/map" in result.output
    assert [r.name for r in robot_runs([out])] == ["r1", "r2"]


def test_fleet_options_refuse_bad_input_in_one_line(tmp_path: Path) -> None:
    cases = [
        (["live", "--out", str(tmp_path), "--robot", "r/1"], "--robot"),
        (
            [
                "live",
                "--out",
                str(tmp_path),
                "--camera",
                "openni://",
                "--board",
                "none",
                "--start",
                "1",
                "1",
                "0",
            ],
            "--start places the simulated robot",
        ),
        (["world-view", str(tmp_path), "--out", str(tmp_path / "w.png")], "no robot runs"),
        (["live", "--out", str(tmp_path), "--fleet", str(tmp_path / "f.yaml")], "--robot NAME"),
        (
            ["live", "--out", str(tmp_path), "--fleet", str(tmp_path / "f.yaml"), "--robot", "a"],
            "no such fleet file",
        ),
        (
            [
                "live",
                "--out",
                str(tmp_path / "wall"),
                "--sim-world",
                str(WORLD),
                "--start",
                "7.0",
                "2.0",
                "0",
                "--duration",
                "1",
                "-q",
            ],
            "--start (7, 2) is inside a wall",
        ),
    ]
    for args, message in cases:
        result = runner.invoke(app, args)
        assert result.exit_code == 1, result.output
        line = result.output.strip()
        assert line.startswith("error:") and "\n" not in line and message in line, line
