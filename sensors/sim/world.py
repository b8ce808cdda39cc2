"""Simulator world descriptions: floor plans in YAML -> boxes -> triangle mesh and floor-plan grid.

A world is 2.5-D: walls (segments with thickness, height, doors) and furniture (oriented boxes)
standing on a floor, under a ceiling. Everything becomes an oriented box; the renderer turns
boxes into triangles and the floor-plan rasteriser turns footprints into an occupancy grid.

YAML schema (units: metres, radians)::

    name: house
    wall_thickness: 0.1        # default for walls
    wall_height: 2.5           # default for walls; also the ceiling height
    door_height: 2.0
    floor: {texture: wood, scale: 1.0}     # scale = metres per texture tile
    ceiling: {texture: plaster, scale: 2.0}
    walls:
      - {from: [0, 0], to: [10, 0], texture: brick, doors: [{at: 2.0, width: 0.9}]}
    furniture:
      - {name: sofa, center: [2, 1], size: [2.0, 0.9, 0.8], yaw: 0.0, texture: coffee}
    start: [1.0, 1.0, 0.0]     # x, y, yaw
    route: [[3, 1], [3, 3]]    # waypoints driven in order
    geo: {latitude: 44.98, longitude: -93.27, altitude: 256.0, heading_deg: 0.0}  # optional:
                               # the world on WGS84 (sensors/geo.py); recordings get gps.txt
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sensors.config import short_repr
from sensors.geo import GeoAnchor, geo_from_dict
from sensors.safe_yaml import read_yaml
from sensors.types import MapError, WorldError

DEFAULT_WALL_THICKNESS = 0.1  # [m]
DEFAULT_WALL_HEIGHT = 2.5  # [m]
DEFAULT_DOOR_HEIGHT = 2.0  # [m]
MIN_WALL_PIECE = 1e-3  # [m] shorter wall pieces beside doors are dropped
MAX_WORLD_COORDINATE = 1000.0  # [m] a simulated building fits in a 2 km square


@dataclass(frozen=True)
class Box:
    """An oriented box standing upright: footprint centre, half sizes along its own axes, yaw."""

    cx: float  # [m]
    cy: float  # [m]
    half_length: float  # [m] along the box's own x axis
    half_width: float  # [m] along the box's own y axis
    yaw: float  # [rad]
    z_min: float  # [m]
    z_max: float  # [m]
    texture: str
    texture_scale: float  # [m] per texture tile
    name: str = ""

    def footprint(self) -> np.ndarray:
        """(4, 2) corners counter-clockwise."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        local = np.array(
            [
                [-self.half_length, -self.half_width],
                [self.half_length, -self.half_width],
                [self.half_length, self.half_width],
                [-self.half_length, self.half_width],
            ]
        )
        rot = np.array([[c, -s], [s, c]])
        return local @ rot.T + np.array([self.cx, self.cy])


@dataclass(frozen=True)
class Surface:
    texture: str
    scale: float  # [m] per texture tile


@dataclass(frozen=True)
class World:
    name: str
    boxes: tuple[Box, ...]
    floor: Surface
    ceiling: Surface
    ceiling_height: float  # [m]
    start: tuple[float, float, float]  # x [m], y [m], yaw [rad]
    route: np.ndarray  # (K, 2) waypoints [m]
    source: str = ""
    geo: GeoAnchor | None = None  # the world frame on WGS84: the simulator then writes gps.txt

    def bounds(self, margin: float = 0.5) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of all footprints, grown by ``margin`` [m]."""
        pts = np.concatenate([b.footprint() for b in self.boxes] + [self.route.reshape(-1, 2)])
        lo = pts.min(axis=0) - margin
        hi = pts.max(axis=0) + margin
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def route_length(self) -> float:
        pts = np.vstack([np.array(self.start[:2])[None], self.route])
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


# --- loading ----------------------------------------------------------------------------------


def _num(
    d: Mapping[str, Any],
    key: str,
    where: str,
    default: float | None = None,
    positive: bool = False,
) -> float:
    v = d.get(key, default)
    if v is None:
        raise WorldError(f"{where}: missing '{key}'")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise WorldError(f"{where}.{key}: expected a number, got {short_repr(v)}")
    if positive and not v > 0:
        raise WorldError(f"{where}.{key}: must be > 0, got {v}")
    return float(v)


def _vec(d: Mapping[str, Any], key: str, n: int, where: str) -> tuple[float, ...]:
    v = d.get(key)
    if (
        not isinstance(v, (list, tuple))
        or len(v) != n
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        or not all(math.isfinite(x) for x in v)
    ):
        raise WorldError(
            f"{where}.{key}: expected a list of {n} numbers (finite), got {short_repr(v)}"
        )
    if any(abs(x) > MAX_WORLD_COORDINATE for x in v[:2]):
        raise WorldError(
            f"{where}.{key}: {list(v)} is farther than {MAX_WORLD_COORDINATE:g} m from the origin"
        )
    return tuple(float(x) for x in v)


def _surface(d: Any, where: str, default: Surface) -> Surface:
    if d is None:
        return default
    if not isinstance(d, Mapping):
        raise WorldError(f"{where}: expected a mapping with texture and scale")
    scale = _num(d, "scale", where, default.scale, positive=True)
    return Surface(str(d.get("texture", default.texture)), scale)


def _wall_boxes(w: Mapping[str, Any], where: str, defaults: Mapping[str, float]) -> list[Box]:
    """One wall segment -> boxes: the solid pieces between doors plus a lintel over each door."""
    x0, y0 = _vec(w, "from", 2, where)
    x1, y1 = _vec(w, "to", 2, where)
    length = math.hypot(x1 - x0, y1 - y0)
    if length < MIN_WALL_PIECE:
        raise WorldError(f"{where}: wall has zero length")
    thickness = _num(w, "thickness", where, defaults["wall_thickness"], positive=True)
    height = _num(w, "height", where, defaults["wall_height"], positive=True)
    door_h = defaults["door_height"]
    tex = str(w.get("texture", "plaster"))
    scale = _num(w, "texture_scale", where, 1.5, positive=True)
    yaw = math.atan2(y1 - y0, x1 - x0)
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    # Solid intervals along the wall, after cutting out the doors.
    doors = sorted(
        (
            _num(d, "at", f"{where}.doors[{i}]"),
            _num(d, "width", f"{where}.doors[{i}]", 0.9, positive=True),
        )
        for i, d in enumerate(w.get("doors", []) or [])
    )
    cuts: list[tuple[float, float]] = []
    for i, (at, width) in enumerate(doors):
        a, b = at - width / 2, at + width / 2
        if a < 0 or b > length:
            raise WorldError(f"{where}.doors[{i}]: door [{a:.2f}, {b:.2f}] m leaves the wall")
        if cuts and a < cuts[-1][1]:
            raise WorldError(f"{where}.doors[{i}]: door overlaps the previous door")
        cuts.append((a, b))
    solid, pos = [], 0.0
    for a, b in cuts:
        solid.append((pos, a))
        pos = b
    solid.append((pos, length))

    def piece(a: float, b: float, z0: float, z1: float, name: str) -> Box:
        mid = (a + b) / 2
        return Box(
            x0 + ux * mid, y0 + uy * mid, (b - a) / 2, thickness / 2, yaw, z0, z1, tex, scale, name
        )

    boxes = [piece(a, b, 0.0, height, "wall") for a, b in solid if b - a > MIN_WALL_PIECE]
    boxes += [piece(a, b, door_h, height, "lintel") for a, b in cuts if height > door_h]
    return boxes


def load_world(path: str | Path) -> World:
    """Read and validate a world YAML; errors name the file and the offending entry."""
    path = Path(path)
    data = read_yaml(path, WorldError, "world file")
    if not isinstance(data, Mapping):
        raise WorldError(f"{path}: top level must be a mapping")
    return world_from_dict(data, source=str(path))


def _geo(data: Any, source: str) -> GeoAnchor | None:
    if data is None:
        return None
    try:
        return geo_from_dict(data, source)
    except MapError as err:
        raise WorldError(str(err)) from None


def world_from_dict(data: Mapping[str, Any], source: str = "<world>") -> World:
    known = {
        "name",
        "description",
        "wall_thickness",
        "wall_height",
        "door_height",
        "floor",
        "ceiling",
        "walls",
        "furniture",
        "start",
        "route",
        "geo",
    }
    unknown = sorted(set(data) - known)
    if unknown:
        raise WorldError(f"{source}: {unknown[0]}: unknown key (valid: {', '.join(sorted(known))})")
    defaults = {
        "wall_thickness": _num(data, "wall_thickness", source, DEFAULT_WALL_THICKNESS, True),
        "wall_height": _num(data, "wall_height", source, DEFAULT_WALL_HEIGHT, True),
        "door_height": _num(data, "door_height", source, DEFAULT_DOOR_HEIGHT, True),
    }
    walls = data.get("walls") or []
    if not isinstance(walls, list) or not walls:
        raise WorldError(f"{source}: walls: expected a non-empty list of walls")
    boxes: list[Box] = []
    for i, w in enumerate(walls):
        if not isinstance(w, Mapping):
            raise WorldError(f"{source}: walls[{i}]: expected a mapping")
        boxes += _wall_boxes(w, f"{source}: walls[{i}]", defaults)
    for i, f in enumerate(data.get("furniture") or []):
        where = f"{source}: furniture[{i}]"
        if not isinstance(f, Mapping):
            raise WorldError(f"{where}: expected a mapping")
        cx, cy = _vec(f, "center", 2, where)
        length, width, height = _vec(f, "size", 3, where)
        if min(length, width, height) <= 0:
            raise WorldError(f"{where}.size: all sizes must be > 0, got {[length, width, height]}")
        z0 = _num(f, "elevation", where, 0.0)
        boxes.append(
            Box(
                cx,
                cy,
                length / 2,
                width / 2,
                _num(f, "yaw", where, 0.0),
                z0,
                z0 + height,
                str(f.get("texture", "wood")),
                _num(f, "texture_scale", where, 1.0, True),
                str(f.get("name", f"furniture{i}")),
            )
        )
    start = _vec(data, "start", 3, source)
    route_raw = data.get("route")
    if not isinstance(route_raw, list) or not route_raw:
        raise WorldError(f"{source}: route: expected a non-empty list of [x, y] waypoints")
    route = np.array(
        [_vec({"p": p}, "p", 2, f"{source}: route[{i}]") for i, p in enumerate(route_raw)],
        dtype=np.float64,
    )
    world = World(
        name=str(data.get("name", Path(source).stem)),
        boxes=tuple(boxes),
        floor=_surface(data.get("floor"), f"{source}: floor", Surface("wood", 1.0)),
        ceiling=_surface(data.get("ceiling"), f"{source}: ceiling", Surface("plaster", 2.0)),
        ceiling_height=defaults["wall_height"],
        start=(start[0], start[1], start[2]),
        route=route,
        source=source,
        geo=_geo(data.get("geo"), source),
    )
    check_start(world, world.start, f"{source}: start")
    return world


def check_start(world: World, start: Sequence[float], what: str) -> None:
    """Refuse a start pose inside a wall or furniture: that robot would be stuck from frame 0."""
    plan = floor_plan(world)
    r, c = plan.cell_of(np.array([start[:2]]))[0]
    if 0 <= r < plan.occupied.shape[0] and 0 <= c < plan.occupied.shape[1] and plan.occupied[r, c]:
        raise WorldError(f"{what} ({start[0]:g}, {start[1]:g}) is inside a wall or furniture")


# --- floor plan -------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """Ground-truth occupancy of a height band: ``occupied[row, col]``, row 0 at the *bottom*
    (y = origin_y), as Nav2's map origin is the lower-left pixel."""

    occupied: np.ndarray  # (H, W) bool
    resolution: float  # [m/cell]
    origin_x: float  # [m] world x of the lower-left cell's corner
    origin_y: float  # [m]

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) world points -> (N, 2) integer (row, col)."""
        col = np.floor((xy[:, 0] - self.origin_x) / self.resolution).astype(np.int64)
        row = np.floor((xy[:, 1] - self.origin_y) / self.resolution).astype(np.int64)
        return np.stack([row, col], axis=1)

    def clearance(self, xy: np.ndarray) -> np.ndarray:
        """Distance [m] from each world point to the nearest occupied cell (0 outside the map)."""
        from scipy.ndimage import distance_transform_edt

        dist = distance_transform_edt(~self.occupied) * self.resolution
        rc = self.cell_of(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
        h, w = self.occupied.shape
        inside = (rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)
        out = np.zeros(len(rc))
        out[inside] = dist[rc[inside, 0], rc[inside, 1]]
        return out


def floor_plan(
    world: World, resolution: float = 0.05, z_min: float = 0.05, z_max: float = 1.5
) -> FloorPlan:
    """Rasterise box footprints whose height span meets [z_min, z_max] (a laser's view)."""
    x0, y0, x1, y1 = world.bounds()
    w = int(math.ceil((x1 - x0) / resolution))
    h = int(math.ceil((y1 - y0) / resolution))
    grid = np.zeros((h, w), dtype=np.uint8)
    for b in world.boxes:
        if b.z_max <= z_min or b.z_min >= z_max:
            continue
        # Cell centres inside the polygon are filled; scale by 2^shift for sub-cell accuracy.
        shift = 4
        poly = (b.footprint() - [x0, y0]) / resolution - 0.5
        pts = np.round(poly * (1 << shift)).astype(np.int32)
        cv2.fillPoly(grid, [pts], 1, lineType=cv2.LINE_8, shift=shift)
    return FloorPlan(grid.astype(bool), resolution, x0, y0)
