"""The one world picture of `fleet show` and `world-view` on tiny hand-built grids: maps placed
by T_world_map, tints blended where two maps overlap (neither hides the other), keepouts hatched
in the robot's tint, a floor plan under the walls and paths on top."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from rgbdnav.commands.fleet import run_show
from rgbdnav.world_picture import (
    FLOOR_PLAN_RGB,
    TINTS_RGB,
    FloorPlanMask,
    Layer,
    WorldPath,
    load_layer,
    render_world,
    tint,
    world_geometry,
)
from slam.map_bundle import save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid

RES = 0.1  # [m/cell]


def _room(walls_col: int) -> OccupancyGrid:
    """A 4 m x 2 m free area with one wall column at ``walls_col``."""
    geom = GridGeometry(RES, 0.0, 0.0, 40, 20)
    values = np.zeros(geom.shape, np.int8)
    values[:, walls_col] = 100
    return OccupancyGrid.from_occupancy_values(geom, values)


def _pixel(img: np.ndarray, geom: GridGeometry, x: float, y: float) -> np.ndarray:
    r, c = geom.world_to_cell(x, y)
    return img[geom.height - 1 - int(r), int(c), ::-1].astype(float)  # RGB


def test_overlapping_maps_blend_and_a_turned_map_lands_where_placed() -> None:
    a = Layer("a", _room(10), 0.65, 0.25, (0.0, 0.0, 0.0), None)
    # b turned a quarter turn and moved by (3, -1): its wall at x = 1.05 lands on world y = 0.05.
    b = Layer("b", _room(10), 0.65, 0.25, (3.0, -1.0, math.pi / 2), None)
    geom = world_geometry([a, b])
    img = render_world([a, b], geom)
    assert np.allclose(_pixel(img, geom, 1.05, 0.5), TINTS_RGB[0], atol=1)  # a's wall
    assert np.allclose(_pixel(img, geom, 2.5, 0.05), TINTS_RGB[1], atol=1)  # b's wall
    free_a = 0.65 * 255 + 0.35 * TINTS_RGB[0]
    free_b = 0.65 * 255 + 0.35 * TINTS_RGB[1]
    both = _pixel(img, geom, 2.5, 1.5)  # free in both maps: the average, not one of them
    assert np.allclose(both, (free_a + free_b) / 2, atol=1.5)


def test_keepouts_are_hatched_in_the_robot_tint_and_the_rrd_is_written(tmp_path: Path) -> None:
    save_map_yaml(_room(10), tmp_path / "a.yaml")
    keep_geom = GridGeometry(RES, 2.0, 0.5, 10, 10)
    zone = OccupancyGrid.from_occupancy_values(keep_geom, np.full(keep_geom.shape, 100, np.int8))
    save_map_yaml(zone, tmp_path / "keepout.yaml")
    (tmp_path / "fleet.yaml").write_text(
        "robots:\n  - {name: a, map: a.yaml, keepout: keepout.yaml}\n"
    )
    out = run_show(tmp_path / "fleet.yaml", tmp_path / "show")
    # The layer loader takes the path as a plain string too, as its signature says.
    assert load_layer("a", str(tmp_path / "a.yaml"), (0.0, 0.0, 0.0)).grid.geometry.width == 40
    img = cv2.imread(str(out["picture"]))[:, :, ::-1].astype(float)
    free_a = 0.65 * 255 + 0.35 * TINTS_RGB[0]
    hatch = 0.5 * free_a + 0.5 * TINTS_RGB[0]
    n_hatch = np.count_nonzero(np.all(np.abs(img - hatch) <= 1.5, axis=2))
    assert 30 <= n_hatch <= 70  # half the 100 keepout cells, in stripes
    assert out["recording"].stat().st_size > 1000


def test_world_view_pieces_floor_plan_under_walls_and_paths_on_top() -> None:
    a = Layer("a", _room(10), 0.65, 0.25, (0.0, 0.0, 0.0), None)
    plan_geom = GridGeometry(RES, 0.0, 0.0, 40, 20)
    plan = np.zeros(plan_geom.shape, bool)
    plan[:, 30] = True  # a true wall the map did not see, at x = 3.05
    plan[:, 10] = True  # and one under the map's own wall
    path = WorldPath(np.array([[0.5, 1.0], [3.5, 1.0]]), tint(1), 3, start_label="a")
    # The path reaches beyond the map: the picture grows to hold it.
    far = WorldPath(np.array([[0.5, 1.5], [9.0, 1.5]]), tint(2), 3)
    geom = world_geometry([a], np.vstack([path.xy, far.xy]))
    assert geom.origin_x + geom.width * geom.resolution > 9.0
    img = render_world([a], geom, [path, far], FloorPlanMask(plan, plan_geom))
    assert np.allclose(_pixel(img, geom, 3.05, 0.3), FLOOR_PLAN_RGB, atol=1)
    assert np.allclose(_pixel(img, geom, 1.05, 0.3), TINTS_RGB[0], atol=1)  # the map's wall wins
    assert np.allclose(_pixel(img, geom, 2.0, 1.0), tint(1), atol=1)  # the path on top
    assert np.allclose(_pixel(img, geom, 8.0, 1.5), tint(2), atol=1)
