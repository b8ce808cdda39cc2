"""The world view of robots run side by side: each robot's own map and path in the world frame.

Each robot runs as its own ``rgbdnav live --robot NAME`` process into ``DIR/NAME/`` (its own
simulated camera and board emulator, its own map; nothing shared). Its ``summary.json`` says
where its map frame sits in the world (``robot.T_world_map``: x, y, yaw, the static
``world -> NAME/map`` transform), which map it used (``robot.map``) and its keepout mask. This
reads those runs; the picture is drawn by the one world renderer (:mod:`rgbdnav.world_picture`,
as `fleet show`): every robot's map, keepout, estimated and true path in the world frame, each
robot in its own tint blended over the others, over the simulated world's floor plan.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rgbdnav.report import write_png
from rgbdnav.world_picture import (
    TRUTH_RGB,
    FloorPlanMask,
    WorldPath,
    load_layer,
    render_world,
    tint,
    world_geometry,
)
from sensors.tum import load_tum_trajectory
from sensors.types import ConfigError
from slam.occupancy_grid import GridGeometry


@dataclass(frozen=True)
class RobotRun:
    name: str
    folder: Path
    T_world_map: tuple[float, float, float]
    start_in_world: tuple[float, float, float] | None
    world: Path | None
    map_path: Path  # the run's own map (mapping) or the map it localised in (--map)
    keepout_path: Path | None  # the robot's keepout mask (from its fleet file)


def _robot_run(folder: Path) -> RobotRun | None:
    try:
        summary = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    robot = summary.get("robot") or {}
    if summary.get("command") != "live" or not robot.get("name"):
        return None
    if robot.get("T_world_map") is None:
        raise ConfigError(
            f"{folder}: robot {robot['name']} has no T_world_map (a real robot's "
            "map must be placed in the world first)"
        )
    start = robot.get("start_in_world")
    return RobotRun(
        robot["name"],
        folder,
        tuple(robot["T_world_map"]),
        tuple(start) if start else None,
        Path(summary["world"]) if summary.get("world") else None,
        Path(robot["map"]) if robot.get("map") else folder / "map",
        Path(robot["keepout"]) if robot.get("keepout") else None,
    )


def robot_runs(paths: list[Path]) -> list[RobotRun]:
    """The robot runs in ``paths``: run folders themselves, or folders holding them."""
    runs: list[RobotRun] = []
    for path in paths:
        if not path.is_dir():
            raise ConfigError(f"{path}: no such folder")
        found = (
            [_robot_run(path)]
            if (path / "summary.json").is_file()
            else [_robot_run(p) for p in sorted(path.iterdir()) if p.is_dir()]
        )
        runs += [r for r in found if r is not None]
    if not runs:
        raise ConfigError(
            f"no robot runs (rgbdnav live --robot NAME) in {', '.join(map(str, paths))}"
        )
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        raise ConfigError(f"two runs of the same robot: {', '.join(sorted(names))}")
    return runs


def to_world(t_world_map: tuple[float, float, float], xy: np.ndarray) -> np.ndarray:
    """Map-frame points [m] into the world frame."""
    x, y, yaw = t_world_map
    c, s = math.cos(yaw), math.sin(yaw)
    return xy @ np.array([[c, s], [-s, c]]) + [x, y]


def _path(folder: Path, names: tuple[str, ...]) -> np.ndarray:
    for name in names:
        if (folder / name).is_file():
            _, xyz, _ = load_tum_trajectory(folder / name)
            return xyz[:, :2]
    return np.zeros((0, 2))


def _floor_plans(runs: list[RobotRun]) -> FloorPlanMask | None:
    """The simulated world's true walls, when the runs name one world file (else none)."""
    worlds = {r.world for r in runs if r.world is not None and r.world.is_file()}
    if len(worlds) != 1:
        return None
    from sensors.sim.world import floor_plan, load_world

    fp = floor_plan(load_world(worlds.pop()))
    h, w = fp.occupied.shape
    return FloorPlanMask(fp.occupied, GridGeometry(fp.resolution, fp.origin_x, fp.origin_y, w, h))


def world_view(runs: list[RobotRun], out: Path) -> dict[str, dict]:
    """Draw ``out`` (PNG) with the one world renderer (:mod:`rgbdnav.world_picture`, as
    `fleet show`); per robot, what was drawn (cells, path length, start)."""
    layers, paths, drawn = [], [], {}
    for i, run in enumerate(runs):
        layer = load_layer(run.name, run.map_path, run.T_world_map, run.keepout_path)
        layers.append(layer)
        est = to_world(
            run.T_world_map, _path(run.folder, ("trajectory_optimised.tum", "trajectory.tum"))
        )
        truth = _path(run.folder, ("groundtruth.tum",))  # the simulator's truth: world frame
        if len(truth) > 1:
            paths.append(WorldPath(truth, TRUTH_RGB, 1))
        start = np.array([run.start_in_world[:2]]) if run.start_in_world is not None else est[:1]
        paths.append(WorldPath(est, tint(i)))
        if len(start):
            paths.append(WorldPath(start, tint(i), start_label=run.name))
        g = layer.grid.geometry
        drawn[run.name] = {
            "occupied_cells": int(
                np.count_nonzero(layer.grid.occupied_mask(layer.occupied_thresh))
            ),
            "path_poses": int(len(est)),
            "T_world_map": list(run.T_world_map),
            "map": str(run.map_path),
            "resolution": g.resolution,
        }
    plan = _floor_plans(runs)
    extra = [p.xy for p in paths]
    if plan is not None:
        g = plan.geometry
        extra.append(
            np.array(
                [
                    [g.origin_x, g.origin_y],
                    [g.origin_x + g.width * g.resolution, g.origin_y + g.height * g.resolution],
                ]
            )
        )
    geom = world_geometry(layers, np.vstack(extra) if extra else None)
    write_png(out, render_world(layers, geom, paths, plan))
    return drawn
