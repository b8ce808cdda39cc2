"""The collision monitor in `rgbdnav navigate`: a localiser drifting 0.32 m off sends the robot
at a door jamb; what the camera saw, carried by odometry, stops it before the footprint touches
the jamb (the nav-scenario's seed-2 graze, docs/design/navigator.md)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from sensors.sim.world import floor_plan, load_world
from slam.map_bundle import save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid
from tests.rgbdnav.test_navigate_cli import _navigate

BIAS_X = 0.32  # [m] the estimate drifts this far ahead (+x) of the truth, over RAMP_SCANS
RAMP_SCANS = 15  # [-] localiser answers (5 Hz) until the full bias
HALL = {
    "name": "door",
    "wall_thickness": 0.1,
    "walls": [
        {"from": [0, 0], "to": [5, 0]},
        {"from": [5, 0], "to": [5, 5]},
        {"from": [5, 5], "to": [0, 5]},
        {"from": [0, 5], "to": [0, 0]},
        {"from": [0, 2.5], "to": [5, 2.5], "doors": [{"at": 3.0, "width": 1.0}]},
    ],
    "start": [1.0, 1.0, 0.5],  # looking at the door's left jamb (2.5, 2.45) from 2 m
    "route": [[3.0, 4.0]],
}


@pytest.fixture(scope="module")
def hall(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("door")
    (d / "world.yaml").write_text(yaml.safe_dump(HALL))
    plan = floor_plan(load_world(d / "world.yaml"))
    h, w = plan.occupied.shape
    grid = OccupancyGrid.from_occupancy_values(
        GridGeometry(plan.resolution, plan.origin_x, plan.origin_y, w, h),
        np.where(plan.occupied, 100, 0),
    )
    save_map_yaml(grid, d / "map.yaml")
    return {"world": d / "world.yaml", "map": d / "map.yaml"}


def _drifting_localizer() -> type:
    """Tracking answers that drift to BIAS_X ahead (+x) of the truth once the camera has seen the
    left jamb: the estimate puts the robot in the middle of the 1 m door while it heads for that
    jamb (0.18 m of clearance for a 0.23 m radius), seen seconds ago and out of view since."""
    from slam.localization import Localizer

    class Drifting(Localizer):
        answers = 0

        def update(self, scan, odom_pose):  # type: ignore[no-untyped-def]
            r = super().update(scan, odom_pose)
            if r.status != "tracking":
                return r
            Drifting.answers += 1
            shift = np.array([BIAS_X * min(1.0, Drifting.answers / RAMP_SCANS), 0.0, 0.0])
            return dataclasses.replace(r, pose=r.pose + shift, map_to_odom=r.map_to_odom + shift)

    return Drifting


def test_navigate_puts_the_collision_monitor_between_the_navigator_and_the_wheels(
    hall: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rgbdnav.runners.navigate as navigate_run

    monkeypatch.setattr(navigate_run, "Localizer", _drifting_localizer())
    _, output, summary = _navigate(
        hall,
        tmp_path,
        "--goal",
        "3.0,4.0",
        "--goal-timeout",
        "15",
        "--set",
        "navigate.max_replans=1",
    )
    assert summary, output
    assert summary["collisions"]["events"] == 0, summary["collisions"]
    assert summary["collision_monitor"]["enabled"] and summary["collision_monitor"]["stops"] >= 1
