"""The fleet file: robots with their own maps and keepouts placed in world, validated by key."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sensors.geo import GeoAnchor
from sensors.types import MapError
from slam.fleet import load_fleet
from slam.map_bundle import save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid


def _map(folder: Path, name: str) -> Path:
    geom = GridGeometry(0.1, 0.0, 0.0, 20, 10)
    values = np.zeros(geom.shape, np.int8)
    values[0, :] = 100
    save_map_yaml(OccupancyGrid.from_occupancy_values(geom, values), folder / f"{name}.yaml")
    return folder / f"{name}.yaml"


def test_fleet_file_round_trips_robots_keepouts_and_geo(tmp_path: Path) -> None:
    _map(tmp_path, "alpha")
    _map(tmp_path, "beta")
    _map(tmp_path, "beta_keepout")
    (tmp_path / "fleet.yaml").write_text(
        "world:\n  geo: {latitude: 44.98, longitude: -93.27, altitude: 256.0, heading_deg: 0}\n"
        "robots:\n"
        "  - {name: alpha, map: alpha.yaml}\n"
        "  - name: beta\n    map: beta.yaml\n    keepout: beta_keepout.yaml\n"
        "    T_world_map: {x: 100.0, y: -5.0, yaw: 1.5707963}\n"
    )
    fleet = load_fleet(tmp_path / "fleet.yaml")
    alpha, beta = fleet.robots
    assert alpha.T_world_map == (0.0, 0.0, 0.0) and alpha.keepout_path is None
    assert beta.T_world_map == pytest.approx((100.0, -5.0, math.pi / 2))
    assert beta.keepout_path == (tmp_path / "beta_keepout.yaml").resolve()
    # beta's anchor is the world's moved by T_world_map: its origin is 100 m east, 5 m south.
    world = GeoAnchor(44.98, -93.27, 256.0, 0.0)
    x, y, _ = world.to_map(beta.geo.latitude, beta.geo.longitude)
    assert (float(x), float(y)) == pytest.approx((100.0, -5.0), abs=1e-3)
    assert beta.geo.heading_deg == pytest.approx(90.0, abs=1e-4)


def test_a_robot_without_t_world_map_is_placed_by_the_geo_anchors(tmp_path: Path) -> None:
    from sensors.geo import geo_yaml_text

    _map(tmp_path, "alpha")
    world = GeoAnchor(44.98, -93.27, 256.0, 10.0)
    # alpha's map frame: 120 m east-ish, 40 m north-ish of the world's, turned by 30 deg.
    (tmp_path / "geo.yaml").write_text(geo_yaml_text(world.moved(120.0, 40.0, math.radians(30))))
    (tmp_path / "fleet.yaml").write_text(
        "world:\n  geo: {latitude: 44.98, longitude: -93.27, altitude: 256.0, heading_deg: 10}\n"
        "robots:\n  - {name: alpha, map: alpha.yaml}\n"
    )
    alpha = load_fleet(tmp_path / "fleet.yaml").robot("alpha")
    assert alpha.placed_by == "geo anchors"
    assert alpha.T_world_map == pytest.approx((120.0, 40.0, math.radians(30)), abs=1e-3)


@pytest.mark.parametrize(
    ("robots", "message"),
    [
        ("  - {name: a, map: alpha.yaml}\n  - {name: a, map: alpha.yaml}\n", "'a' appears twice"),
        ("  - {name: a, map: nowhere.yaml}\n", "map .*nowhere.yaml does not exist"),
        ("  - {name: a, map: alpha.yaml, pose: {x: 1}}\n", "unknown key 'pose'"),
        ("  - {name: A B, map: alpha.yaml}\n", "name must match"),
        ("  - {name: a, map: alpha.yaml, T_world_map: {x: .nan}}\n", "T_world_map.x must be"),
    ],
)
def test_bad_fleet_files_name_robot_and_key(tmp_path: Path, robots: str, message: str) -> None:
    _map(tmp_path, "alpha")
    (tmp_path / "fleet.yaml").write_text("robots:\n" + robots)
    with pytest.raises(MapError, match=message):
        load_fleet(tmp_path / "fleet.yaml")
