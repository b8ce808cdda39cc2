"""Map alignment without a guess: hand-drawn floor plans cut into two overlapping maps, one moved
and turned; two different buildings refused; merged grids and warps checked cell by cell."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from sensors.types import MapError
from slam.map_align import align_maps, merge_grids
from slam.occupancy_grid import GridGeometry, OccupancyGrid, warp_to_geometry

RES = 0.05  # [m/cell]
# A 40 m x 30 m floor: outer walls, corridors and rooms of different sizes (x0, y0, x1, y1) [m].
BUILDING = [
    (0, 0, 40, 0),
    (40, 0, 40, 30),
    (40, 30, 0, 30),
    (0, 30, 0, 0),
    (0, 12, 25, 12),
    (0, 15, 18, 15),
    (22, 15, 40, 15),
    (25, 0, 25, 12),
    (8, 0, 8, 7),
    (15, 15, 15, 30),
    (30, 15, 30, 24),
    (30, 24, 36, 24),
    (5, 22, 11, 22),
    (33, 4, 37, 8),
    (20, 20, 24, 26),
]
# Another building: a long hall with side rooms, nothing like BUILDING.
OTHER = [
    (0, 0, 60, 0),
    (60, 0, 60, 8),
    (60, 8, 0, 8),
    (0, 8, 0, 0),
    (10, 0, 10, 3),
    (20, 0, 20, 3),
    (30, 0, 30, 3),
    (40, 8, 40, 5),
    (50, 8, 50, 5),
    (5, 5, 7, 5),
]


def _grid(segments, pose, box) -> OccupancyGrid:
    """The walls inside ``box`` (x0, y0, x1, y1 in the building) drawn in a map frame whose pose
    in the building is ``pose``: walls occupied, the rest of the box free."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    corners = np.array([[box[0], box[1]], [box[2], box[1]], [box[0], box[3]], [box[2], box[3]]])
    local = (corners - pose[:2]) @ np.array([[c, -s], [s, c]])
    lo, hi = local.min(axis=0) - 1, local.max(axis=0) + 1
    geom = GridGeometry.from_bounds(lo[0], lo[1], hi[0], hi[1], RES)
    x, y = geom.cell_centres()
    bx, by = pose[0] + c * x - s * y, pose[1] + s * x + c * y  # cell centres in the building
    inside = (bx >= box[0]) & (bx <= box[2]) & (by >= box[1]) & (by <= box[3])
    walls = np.zeros(geom.shape, np.uint8)
    for x0, y0, x1, y1 in segments:  # a handful of segments, drawn by OpenCV
        p = np.array([[x0, y0], [x1, y1]], float) - pose[:2]
        q = p @ np.array([[c, -s], [s, c]])
        rc = np.round((q - [geom.origin_x, geom.origin_y]) / RES - 0.5).astype(int)
        cv2.line(walls, tuple(rc[0]), tuple(rc[1]), 1, 2)
    occ = (walls > 0) & inside
    log_odds = np.where(occ, 3.0, -3.0).astype(np.float32)
    return OccupancyGrid(geom, np.where(inside, log_odds, 0.0).astype(np.float32), inside)


def test_recovers_a_moved_and_turned_overlapping_map() -> None:
    a = _grid(BUILDING, np.array([0.0, 0.0, 0.0]), (0, 0, 26, 30))
    pose_b = np.array([31.0, -12.0, 2.3])  # B's map frame in the building (= A's frame)
    b = _grid(BUILDING, pose_b, (14, 0, 40, 30))
    al = align_maps(a, b)
    assert al.T_a_b[:2] == pytest.approx(pose_b[:2], abs=0.1)
    assert math.degrees(abs(al.T_a_b[2] - pose_b[2])) < 0.5
    assert al.confidence > 0.5
    assert al.verification.overlap_m > 15.0


def test_two_different_buildings_are_refused() -> None:
    a = _grid(BUILDING, np.array([0.0, 0.0, 0.0]), (0, 0, 40, 30))
    b = _grid(OTHER, np.array([5.0, 3.0, 0.7]), (0, 0, 60, 8))
    with pytest.raises(MapError, match="cannot align the maps"):
        align_maps(a, b)


def test_merged_grid_holds_both_maps_in_a_frame() -> None:
    a = _grid(BUILDING, np.array([0.0, 0.0, 0.0]), (0, 0, 20, 30))
    pose_b = np.array([30.0, 5.0, math.pi / 2])
    b = _grid(BUILDING, pose_b, (20, 0, 40, 30))
    merged = merge_grids(a, b, pose_b)
    full = _grid(BUILDING, np.array([0.0, 0.0, 0.0]), (0, 0, 40, 30))
    # Every wall of the whole building lies within a cell of a merged wall.
    occ = merged.occupied_mask()
    x, y = full.geometry.cell_centres()
    walls = full.occupied_mask()
    r, c = merged.geometry.world_to_cell(x[walls], y[walls])
    near = cv2.dilate(occ.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert np.mean(near[r, c]) > 0.97


def test_warp_moves_a_cell_by_the_pose() -> None:
    src = GridGeometry(0.1, 0.0, 0.0, 50, 30)
    values = np.zeros(src.shape, np.uint8)
    values[5, 10] = 7  # centre (1.05, 0.55)
    dst = GridGeometry(0.1, -5.0, -5.0, 100, 100)
    out = warp_to_geometry(values, src, (1.0, 2.0, math.pi / 2), dst)
    r, c = np.nonzero(out)
    x, y = dst.cell_to_world(r, c)
    assert (float(x[0]), float(y[0])) == pytest.approx((1.0 - 0.55, 2.0 + 1.05), abs=1e-9)
    assert out[r[0], c[0]] == 7 and len(r) == 1


def test_the_simulated_house_split_in_two_is_refused_not_aligned_half_a_turn_wrong() -> None:
    """The simulator's house (scenes/house.yaml) is nearly point-symmetric: its rooms mirror each
    other, so robot b's half turned by 180 deg explains robot a's almost as well as the truth.
    With the default rival ratio that is "more than one place", never a wrong transform."""
    from pathlib import Path

    from sensors.sim.world import floor_plan, load_world
    from slam.config import AlignConfig
    from slam.geometry import ominus

    house = Path(__file__).resolve().parents[2] / "scenes" / "house.yaml"
    fp = floor_plan(load_world(house))
    h, w = fp.occupied.shape
    src = GridGeometry(fp.resolution, fp.origin_x, fp.origin_y, w, h)
    x_cells = fp.origin_x + (np.arange(w) + 0.5) * fp.resolution
    walls = np.where(fp.occupied, 100.0, 0.0).astype(np.float32)
    a_vals, b_vals = walls.copy(), walls.copy()
    a_vals[:, x_cells > 9.0] = -1  # robot a saw x < 9 m, robot b x > 5 m
    b_vals[:, x_cells < 5.0] = -1
    a = OccupancyGrid.from_occupancy_values(src, a_vals.astype(np.int8))
    T_a_b = np.array([20.0, -5.0, 0.3])  # b's map frame in a's (= the world)
    x1, y1 = fp.origin_x + w * fp.resolution, fp.origin_y + h * fp.resolution
    box = np.array([[fp.origin_x, fp.origin_y, 0], [x1, fp.origin_y, 0], [fp.origin_x, y1, 0]])
    box = ominus(T_a_b, np.vstack([box, [x1, y1, 0]]).astype(float))
    lo, hi = box[:, :2].min(axis=0), box[:, :2].max(axis=0)
    dst = GridGeometry.from_bounds(lo[0], lo[1], hi[0], hi[1], fp.resolution)
    b_in_b = warp_to_geometry(b_vals, src, ominus(T_a_b, np.zeros(3)), dst, fill=-1.0)
    b = OccupancyGrid.from_occupancy_values(dst, np.round(b_in_b).astype(np.int8))
    with pytest.raises(MapError, match="match in more than one place"):
        align_maps(a, b, (0.65, 0.65), AlignConfig())
    # Told to accept such a rival, it returns the half-turned pose, at a low confidence.
    al = align_maps(a, b, (0.65, 0.65), AlignConfig(max_rival_ratio=0.9))
    assert abs(abs(al.T_a_b[2] - T_a_b[2]) - math.pi) < 0.05 and al.confidence < 0.3
