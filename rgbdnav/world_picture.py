"""The world picture: several robots' maps, keepouts and paths in one ``world`` frame.

One renderer for `rgbdnav fleet show` (maps and keepouts from a fleet file) and `rgbdnav
world-view` (the maps and paths of robot runs, over a simulated world's floor plan). Each robot's
map goes through its ``T_world_map`` (the static ``world -> <name>/map`` transform) onto one grid:
free space pale and walls full in the robot's tint, averaged where maps overlap so no map hides
another; keepout masks hatched in the tint; a floor plan in dark grey under the walls; paths and
start marks on top, and each map frame's axes with a legend.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slam.map_bundle import load_map, load_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid, warp_to_geometry

# Robot tints (RGB), cycled; walls are drawn in the tint, free space in a pale version of it.
TINTS_RGB = np.array(
    [
        (31, 119, 180),
        (214, 39, 40),
        (44, 160, 44),
        (148, 103, 189),
        (255, 127, 14),
        (23, 190, 207),
        (227, 119, 194),
        (140, 86, 75),
    ],
    float,
)
FREE_PALENESS = 0.65  # free space: this much white mixed into the tint
UNKNOWN_RGB = (205, 205, 205)  # map_saver's unknown grey
KEEPOUT_STRIPE_PX = 6  # [px] period of the keepout hatching
MAX_PICTURE_PX = 4000  # [px] the picture's longer side; coarser cells beyond
MARGIN_M = 2.0  # [m] around the maps
FLOOR_PLAN_RGB = (90, 90, 90)  # the simulated world's true walls
TRUTH_RGB = (90, 90, 90)  # a true path


@dataclass(frozen=True)
class Layer:
    """One robot's map in the world, ready to draw."""

    name: str
    grid: OccupancyGrid
    occupied_thresh: float
    free_thresh: float
    T_world_map: tuple[float, float, float]
    keepout: OccupancyGrid | None  # in the robot's map frame


@dataclass(frozen=True)
class WorldPath:
    """A path drawn over the maps, in the world frame."""

    xy: np.ndarray  # (N, 2) [m] world
    rgb: tuple[int, int, int]
    width_px: int = 2
    start_label: str | None = None  # a dot and this label at the first point


@dataclass(frozen=True)
class FloorPlanMask:
    """True walls (the simulator's floor plan), in the world frame."""

    occupied: np.ndarray  # (H, W) bool, row 0 at the bottom
    geometry: GridGeometry


def load_layer(
    name: str,
    map_path: str | os.PathLike[str],
    T_world_map: tuple[float, float, float],
    keepout_path: str | os.PathLike[str] | None = None,
) -> Layer:
    """A robot's map (bundle or Nav2 map.yaml) and keepout mask (Nav2 map.yaml), ready to draw."""
    m = load_map(Path(map_path))  # it takes a Path only
    keepout = None if keepout_path is None else load_map_yaml(keepout_path)
    return Layer(name, m.grid, m.occupied_thresh, m.free_thresh, T_world_map, keepout)


def _corners(grid: OccupancyGrid) -> np.ndarray:
    """(4, 2) [m] corners of the box around the grid's walls (the whole grid if none): a map's
    grid spans the laser's reach, far beyond the building."""
    g = grid.geometry
    rows, cols = np.nonzero(grid.occupied_mask())  # walls: rays past them are faint
    r0, r1, c0, c1 = (
        (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)
        if len(rows)
        else (0, g.height, 0, g.width)
    )
    x0, x1 = g.origin_x + c0 * g.resolution, g.origin_x + c1 * g.resolution
    y0, y1 = g.origin_y + r0 * g.resolution, g.origin_y + r1 * g.resolution
    return np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])


def _in_world(pts: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return pts @ np.array([[c, s], [-s, c]]) + np.array(pose[:2])


def world_geometry(layers: Sequence[Layer], extra_xy: np.ndarray | None = None) -> GridGeometry:
    """A grid over every map's walls in the world and ``extra_xy`` (N, 2) [m] (paths, a floor
    plan; a frame origin far from its map is left out: its arrow is clipped), at the finest map
    resolution (coarser if the picture would exceed ``MAX_PICTURE_PX``)."""
    parts = [_in_world(_corners(ly.grid), ly.T_world_map) for ly in layers]
    if extra_xy is not None and len(extra_xy):
        parts.append(np.asarray(extra_xy, float).reshape(-1, 2))
    pts = np.vstack(parts)
    lo, hi = pts.min(axis=0) - MARGIN_M, pts.max(axis=0) + MARGIN_M
    res = min(ly.grid.geometry.resolution for ly in layers)
    res = max(res, float(np.max(hi - lo)) / MAX_PICTURE_PX)
    return GridGeometry.from_bounds(lo[0], lo[1], hi[0], hi[1], res)


def render_world(
    layers: Sequence[Layer],
    geom: GridGeometry,
    paths: Sequence[WorldPath] = (),
    floor_plan: FloorPlanMask | None = None,
) -> np.ndarray:
    """(H, W, 3) uint8 BGR picture, top row = max y: free space pale and walls full in each
    robot's tint, averaged where several robots' maps overlap; keepouts hatched in the tint;
    the floor plan's walls under the maps' walls; ``paths`` on top."""
    h, w = geom.shape
    wall_sum, free_sum = np.zeros((h, w, 3)), np.zeros((h, w, 3))
    wall_n, free_n = np.zeros((h, w)), np.zeros((h, w))
    keep_sum, keep_n = np.zeros((h, w, 3)), np.zeros((h, w))
    for i, ly in enumerate(layers):
        tint = TINTS_RGB[i % len(TINTS_RGB)]
        g = ly.grid
        walls = warp_to_geometry(
            g.occupied_mask(ly.occupied_thresh), g.geometry, ly.T_world_map, geom
        )
        free = warp_to_geometry(g.free_mask(ly.free_thresh), g.geometry, ly.T_world_map, geom)
        wall_sum += walls[..., None] * tint
        wall_n += walls
        free_sum += free[..., None] * (FREE_PALENESS * 255 + (1 - FREE_PALENESS) * tint)
        free_n += free
        if ly.keepout is not None:
            k = ly.keepout
            zone = warp_to_geometry(k.occupied_mask(0.65), k.geometry, ly.T_world_map, geom)
            keep_sum += zone[..., None] * tint
            keep_n += zone
    img = np.empty((h, w, 3))
    img[:] = UNKNOWN_RGB
    has_free = free_n > 0
    img[has_free] = free_sum[has_free] / free_n[has_free, None]
    rows, cols = np.indices((h, w))
    stripes = ((rows + cols) % KEEPOUT_STRIPE_PX) < KEEPOUT_STRIPE_PX // 2
    hatch = (keep_n > 0) & stripes
    img[hatch] = 0.5 * img[hatch] + 0.5 * keep_sum[hatch] / keep_n[hatch, None]
    if floor_plan is not None:
        plan = warp_to_geometry(floor_plan.occupied, floor_plan.geometry, (0.0, 0.0, 0.0), geom)
        img[plan > 0] = FLOOR_PLAN_RGB
    has_wall = wall_n > 0
    img[has_wall] = wall_sum[has_wall] / wall_n[has_wall, None]
    bgr = np.ascontiguousarray(img[::-1, :, ::-1]).astype(np.uint8)
    _draw_paths(bgr, paths, geom)
    _annotate(bgr, layers, geom)
    return bgr


def _draw_paths(bgr: np.ndarray, paths: Sequence[WorldPath], geom: GridGeometry) -> None:
    """Paths as polylines (and a start dot with its label), drawn in place."""
    h, res = geom.height, geom.resolution
    scale = max(0.5, max(geom.shape) / 600)
    for p in paths:
        if not len(p.xy):
            continue
        uv = np.column_stack(
            [(p.xy[:, 0] - geom.origin_x) / res, h - (p.xy[:, 1] - geom.origin_y) / res]
        )
        uv = uv.round().astype(np.int32)
        colour = tuple(int(v) for v in p.rgb[::-1])
        if len(uv) > 1:
            cv2.polylines(bgr, [uv], False, colour, p.width_px, cv2.LINE_AA)
        if p.start_label is not None:
            u, v = (int(a) for a in uv[0])
            cv2.circle(bgr, (u, v), max(3, int(4 * scale)), colour, -1, cv2.LINE_AA)
            cv2.putText(
                bgr,
                p.start_label,
                (u + 6, v - 6),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.5 * scale,
                colour,
                max(1, int(scale)),
                cv2.LINE_AA,
            )


def _annotate(bgr: np.ndarray, layers: Sequence[Layer], geom: GridGeometry) -> None:
    """Each map frame's axes (x long) and a legend, drawn in place."""
    h = geom.height
    axis_px = max(10, h // 25)
    scale = max(0.5, max(geom.shape) / 600)  # text size grows with the picture
    for i, ly in enumerate(layers):
        colour = tuple(int(v) for v in TINTS_RGB[i % len(TINTS_RGB)][::-1])
        x, y, yaw = ly.T_world_map
        r, c = geom.world_to_cell(x, y)
        origin = (int(c), int(h - 1 - r))
        tip = (int(c + axis_px * math.cos(yaw)), int(h - 1 - r - axis_px * math.sin(yaw)))
        cv2.arrowedLine(bgr, origin, tip, colour, max(2, int(2 * scale)), tipLength=0.25)
        cv2.putText(
            bgr,
            f"{ly.name}/map",
            (origin[0] + 4, origin[1] + int(20 * scale)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5 * scale,
            colour,
            max(1, int(scale)),
            cv2.LINE_AA,
        )
        line = (8, int((30 + 30 * i) * scale))
        cv2.putText(bgr, ly.name, line, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 2, cv2.LINE_AA)


def tint(i: int) -> tuple[int, int, int]:
    """Robot ``i``'s tint (RGB)."""
    r, g, b = (int(v) for v in TINTS_RGB[i % len(TINTS_RGB)])
    return r, g, b


__all__ = [
    "TINTS_RGB",
    "TRUTH_RGB",
    "FloorPlanMask",
    "Layer",
    "WorldPath",
    "load_layer",
    "render_world",
    "tint",
    "world_geometry",
]
