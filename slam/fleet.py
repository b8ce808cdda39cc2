"""The fleet file: independent robots, each with its own map and keepout mask, placed in ``world``.

Each robot keeps its own map bundle (or plain Nav2 map.yaml) and its own keepout mask, and works
alone; the fleet file only says where each map frame sits in a shared ``world`` frame (the static
``world -> <name>/map`` and ``world -> <name>/keepout_mask`` transforms a ROS user would publish)::

    world:
      geo: {latitude: 44.98, longitude: -93.27, altitude: 256.0, heading_deg: 0.0}  # optional
    robots:
      - name: alpha                       # [a-z0-9_-], unique; the robot's frame prefix
        map: maps/alpha                   # bundle folder or map.yaml, relative to this file
        T_world_map: {x: 0.0, y: 0.0, yaw: 0.0}      # [m, m, rad] alpha/map in world
        keepout: maps/alpha_keepout.yaml  # optional Nav2 filter mask, in alpha/map
        geo: {latitude: ..., longitude: ...}         # optional, see sensors/geo.py

A robot's geo anchor is, in order: its own ``geo``, ``geo.yaml`` in its bundle, or the world's
anchor moved by ``T_world_map``. Without ``T_world_map``, a robot whose map has an anchor (its
own ``geo`` or ``geo.yaml``) is placed by the two anchors (the world's and its map's); else its map
frame is the world frame. The keepout mask lies in the robot's map frame (as Nav2's
costmap filter info server publishes it). Paths are resolved against the fleet file's folder.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sensors.config import finite_float, short_repr, unknown_keys
from sensors.geo import GeoAnchor, geo_from_dict, read_geo_anchor
from sensors.safe_yaml import read_yaml
from sensors.types import MapError

NAME_PATTERN = re.compile(r"^[a-z0-9][a-z0-9_-]{0,62}$")
_ROBOT_KEYS = ("name", "map", "T_world_map", "keepout", "geo")
_POSE_KEYS = ("x", "y", "yaw")


@dataclass(frozen=True)
class FleetRobot:
    name: str  # frame prefix: <name>/map, <name>/keepout_mask
    map_path: Path  # bundle folder or Nav2 map.yaml (resolved)
    T_world_map: tuple[float, float, float]  # [m, m, rad] the robot's map frame in world
    keepout_path: Path | None  # Nav2 filter-mask map.yaml in the robot's map frame
    geo: GeoAnchor | None  # the robot's map origin on WGS84 (see the module doc)
    placed_by: str = "T_world_map"  # or "geo anchors", or the default identity


@dataclass(frozen=True)
class Fleet:
    path: Path
    robots: tuple[FleetRobot, ...]
    world_geo: GeoAnchor | None  # the world frame's origin on WGS84

    def robot(self, name: str) -> FleetRobot:
        for r in self.robots:
            if r.name == name:
                return r
        raise MapError(
            f"{self.path}: no robot named {name!r} (have: {', '.join(r.name for r in self.robots)})"
        )


def _pose(data: Any, where: str) -> tuple[float, float, float]:
    if not isinstance(data, dict):
        raise MapError(f"{where}: T_world_map must be a mapping {{x, y, yaw}} [m, m, rad]")
    unknown = unknown_keys(data, _POSE_KEYS)
    if unknown:
        raise MapError(f"{where}: unknown T_world_map key {unknown[0]!r} (known: x, y, yaw)")
    out = []
    for key in _POSE_KEYS:
        v = finite_float(data.get(key, 0.0))
        if v is None:
            raise MapError(
                f"{where}: T_world_map.{key} must be a finite number, "
                f"got {short_repr(data.get(key))}"
            )
        out.append(v)
    return out[0], out[1], out[2]


def _existing(base: Path, value: Any, where: str, what: str) -> Path:
    if not isinstance(value, str) or not value or "\0" in value:
        raise MapError(f"{where}: {what} must be a path, got {short_repr(value)}")
    path = (base / value).resolve() if not Path(value).is_absolute() else Path(value)
    if not path.exists():
        raise MapError(f"{where}: {what} {path} does not exist")
    return path


def _robot(item: Any, i: int, base: Path, world_geo: GeoAnchor | None, where: str) -> FleetRobot:
    at = f"{where}: robots[{i}]"
    if not isinstance(item, dict):
        raise MapError(f"{at} must be a mapping with {', '.join(_ROBOT_KEYS)}")
    unknown = unknown_keys(item, _ROBOT_KEYS)
    if unknown:
        raise MapError(f"{at}: unknown key {unknown[0]!r} (known: {', '.join(_ROBOT_KEYS)})")
    name = item.get("name")
    if not isinstance(name, str) or not NAME_PATTERN.match(name):
        raise MapError(f"{at}: name must match {NAME_PATTERN.pattern}, got {short_repr(name)}")
    if "map" not in item:
        raise MapError(f"{at} ({name}): needs map (a bundle folder or map.yaml)")
    map_path = _existing(base, item["map"], f"{at} ({name})", "map")
    keepout = item.get("keepout")
    keepout_path = (
        None if keepout is None else _existing(base, keepout, f"{at} ({name})", "keepout")
    )
    if "geo" in item:
        geo: GeoAnchor | None = geo_from_dict(item["geo"], f"{at} ({name})")
    else:
        geo = read_geo_anchor(map_path)
    if "T_world_map" in item:
        pose, placed_by = _pose(item["T_world_map"], f"{at} ({name})"), "T_world_map"
    elif geo is not None and world_geo is not None:
        pose, placed_by = world_geo.pose_of(geo), "geo anchors"
    else:
        pose, placed_by = (0.0, 0.0, 0.0), "default (map frame = world)"
    if geo is None and world_geo is not None:
        geo = world_geo.moved(*pose)
    return FleetRobot(name, map_path, pose, keepout_path, geo, placed_by)


def load_fleet(path: str | os.PathLike[str]) -> Fleet:
    """Read and validate a fleet file; :class:`MapError` naming the file, robot and key."""
    path = Path(path)
    if not path.is_file():
        raise MapError(f"{path}: no such fleet file")
    doc = read_yaml(path, MapError, "fleet file")
    if not isinstance(doc, dict):
        raise MapError(f"{path}: a fleet file is a mapping with robots: [...]")
    unknown = unknown_keys(doc, ("world", "robots"))
    if unknown:
        raise MapError(f"{path}: unknown key {unknown[0]!r} (known: world, robots)")
    world = doc.get("world") or {}
    if not isinstance(world, dict) or set(world) - {"geo"}:
        raise MapError(f"{path}: world must be a mapping with only geo")
    world_geo = geo_from_dict(world["geo"], f"{path}: world") if "geo" in world else None
    items = doc.get("robots")
    if not isinstance(items, list) or not items:
        raise MapError(f"{path}: robots must be a non-empty list")
    base = path.resolve().parent
    robots = tuple(_robot(item, i, base, world_geo, str(path)) for i, item in enumerate(items))
    names = [r.name for r in robots]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise MapError(f"{path}: robot name {dup!r} appears twice")
    return Fleet(path, robots, world_geo)


__all__ = ["NAME_PATTERN", "Fleet", "FleetRobot", "load_fleet"]
