"""Issue #6's RGB-D target on the shipped house, end to end: `rgbdnav map WORLD` (what `make demo`
runs on scenes/house.yaml: render the route, wheels + gyro + visual odometry in the EKF, depth ->
scan, the pose-graph mapper, the occupancy grid) must map with an ATE <= 5 cm and a grid whose
occupied cells match the floor plan's observed surfaces (IoU >= 0.9 within one cell).

The suite drives a cut of the house route: the shipped house (same walls, textures, furniture,
start, robot and sensor models), a 9 m loop of the living room that sets off along the shipped
route's first leg, comes back to the start and re-drives that leg, so it still closes a loop and
re-visits mapped ground (946 frames instead of 3970). The thresholds are the full route's; the cut
measured 0.017 m aligned ATE, 0.050 m start-anchored, IoU 0.921, 4 closures accepted. The full
44 m route, with the same targets, is `bench/bench_house_route.py` (docs/benchmarks.md, which
also says why this cut replaced a 14 m one).

Both are scored after the trajectory's SE(2) alignment, the TUM ATE that `rgbdnav eval` computes:
SLAM has no absolute reference, so where the map sits as a whole (its heading is set by the
odometry in the first metres, before a scan constrains it) is not part of its accuracy. The
start-anchored figures are in the same summary and guarded loosely below, so a map that comes out
badly placed still fails."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from rgbdnav.cli import app

HOUSE = Path(__file__).resolve().parents[2] / "scenes" / "house.yaml"
# In the living room (x 0..7, y 0..5): counter-clockwise from the start (1.5, 2.5) round the
# middle of the room, back to the start, then the first leg again.
LIVING_ROOM_LOOP = [[3.5, 1.8], [4.0, 3.5], [2.0, 3.5], [1.5, 2.5], [3.5, 1.8]]
runner = CliRunner()


@pytest.mark.slow
def test_a_loop_of_the_house_maps_within_5_cm_and_matches_the_floor_plan(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    world = yaml.safe_load(HOUSE.read_text())
    # The cut sets off as the shipped route does: its first waypoint on the route's first leg.
    (x0, y0, _), (x1, y1), (x, y) = world["start"], world["route"][0], LIVING_ROOM_LOOP[0]
    assert abs((x1 - x0) * (y - y0) - (y1 - y0) * (x - x0)) / math.hypot(x1 - x0, y1 - y0) < 0.05
    world.update(name="house_living_room", route=LIVING_ROOM_LOOP)
    cut = tmp_path / "house_living_room.yaml"
    cut.write_text(yaml.safe_dump(world))
    cache = tmp_path / "cache"
    monkeypatch.setenv("RGBDNAV_CACHE", str(cache))  # frames go straight to the front end:
    out = tmp_path / "run"
    result = runner.invoke(app, ["map", str(cut), "--out", str(out), "-q"])
    assert result.exit_code == 0, result.output
    assert not cache.exists()  # no ~1 GB rendering on disk
    s = json.loads((out / "summary.json").read_text())
    slam = s["slam_vs_groundtruth"]
    assert slam["matched"] == s["counts"]["scans"] > 900  # a pose for every frame, all scored
    assert slam["path_length_m"] > 9.0
    assert slam["ate_rmse_aligned_m"] <= 0.05, slam
    assert s["grid_vs_floor_plan_aligned"]["iou"] >= 0.9, s["grid_vs_floor_plan_aligned"]
    # Placement: the whole map off by its first metres' heading (0.069 m / IoU 0.75 at 1c1a2a1).
    assert slam["ate_rmse_m"] <= 0.1, slam
    assert s["counts"]["loop_closures"]["accepted"] >= 3  # back at the start, then re-driven
    # All of it with make demo's setting: VO on every 2nd frame, the wheels carry the EKF between.
    assert s["front_end"]["counts"]["vo_skipped_stride"] >= s["counts"]["scans"] // 2 - 1
