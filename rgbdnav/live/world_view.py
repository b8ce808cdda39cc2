"""The world view of robots run side by side: each robot's own map and path in the world frame.

Each robot runs as its own ``rgbdnav live --robot NAME`` process into ``DIR/NAME/`` (its own
simulated camera and board emulator, its own map; nothing shared). Its ``summary.json`` says
where its map frame sits in the world (``robot.T_world_map``: x, y, yaw, the static
``world -> NAME/map`` transform). This picture puts every robot's occupied cells, estimated path
and true path through that transform into the world frame, each robot in its own tint blended
over the others (one map never hides another), over the simulated world's floor plan.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rgbdnav.report import COLORS_BGR, LINE_PX, MARGIN_PX, TARGET_SIZE_PX, write_png
from rgbdnav.visualize import occupied_cells_xy
from sensors.tum import load_tum_trajectory
from sensors.types import ConfigError
from slam.map_bundle import load_map

MAP_ALPHA = 0.55  # a robot's map over the floor plan and the other robots' maps
FLOOR_PLAN_BGR = (200, 200, 200)


@dataclass(frozen=True)
class RobotRun:
    name: str
    folder: Path
    T_world_map: tuple[float, float, float]
    start_in_world: tuple[float, float, float] | None
    world: Path | None


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


def world_view(runs: list[RobotRun], out: Path) -> dict[str, dict]:
    """Draw ``out`` (PNG); per robot, what was drawn (cells, path length, start)."""
    layers = []  # (name, occupied cells, estimated path, true path), all in the world frame
    for run in runs:
        loaded = load_map(run.folder / "map")
        g = loaded.grid.geometry
        occ = occupied_cells_xy(
            loaded.grid.occupied_mask(loaded.occupied_thresh),
            (g.origin_x, g.origin_y),
            g.resolution,
        )
        est = _path(run.folder, ("trajectory_optimised.tum", "trajectory.tum"))
        truth = _path(run.folder, ("groundtruth.tum",))  # the simulator's truth: world frame
        layers.append(
            (
                run,
                to_world(run.T_world_map, occ),
                to_world(run.T_world_map, est),
                truth,
                g.resolution,
            )
        )
    plans = []
    for world in {r.world for r in runs if r.world is not None and r.world.is_file()}:
        from sensors.sim.world import floor_plan, load_world

        fp = floor_plan(load_world(world))
        plans.append(
            (
                occupied_cells_xy(fp.occupied, (fp.origin_x, fp.origin_y), fp.resolution),
                fp.resolution,
            )
        )
    pts = [a for layer in layers for a in layer[1:4] if len(a)] + [p for p, _ in plans if len(p)]
    if not pts:
        raise ConfigError("the robot runs hold no mapped cells and no path to draw")
    allp = np.vstack(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    scale = TARGET_SIZE_PX / max(float((hi - lo).max()), 1e-3)  # [px/m]
    header = LINE_PX * (len(runs) + 1) + MARGIN_PX // 2
    w, h = ((hi - lo) * scale).astype(int) + 2 * MARGIN_PX
    h += header
    img = np.full((h, w, 3), 255.0)

    def px(xy: np.ndarray) -> np.ndarray:
        return (
            np.column_stack(
                [
                    (xy[:, 0] - lo[0]) * scale + MARGIN_PX,
                    h - ((xy[:, 1] - lo[1]) * scale + MARGIN_PX),
                ]
            )
            .round()
            .astype(np.int32)
        )

    def cells(xy: np.ndarray, resolution: float) -> np.ndarray:
        """A mask of the cells' squares at the picture's scale."""
        mask = np.zeros((h, w), np.uint8)
        uv = px(xy)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        mask[uv[ok, 1], uv[ok, 0]] = 1
        side = 2 * max(1, int(round(resolution * scale / 2))) + 1
        return cv2.dilate(mask, np.ones((side, side), np.uint8)) > 0

    for xy, res in plans:
        img[cells(xy, res)] = FLOOR_PLAN_BGR
    drawn: dict[str, dict] = {}
    for i, (run, occ, est, _truth, res) in enumerate(layers):
        tint = np.array(COLORS_BGR[i % len(COLORS_BGR)], float)
        m = cells(occ, res) if len(occ) else np.zeros((h, w), bool)
        img[m] = (1 - MAP_ALPHA) * img[m] + MAP_ALPHA * tint
        drawn[run.name] = {
            "occupied_cells": int(len(occ)),
            "path_poses": int(len(est)),
            "T_world_map": list(run.T_world_map),
        }
    canvas = img.astype(np.uint8)
    for i, (run, _, est, truth, _) in enumerate(layers):
        color = COLORS_BGR[i % len(COLORS_BGR)]
        if len(truth) > 1:
            cv2.polylines(canvas, [px(truth)], False, (90, 90, 90), 1, cv2.LINE_AA)
        if len(est) > 1:
            cv2.polylines(canvas, [px(est)], False, color, 2, cv2.LINE_AA)
        if run.start_in_world is not None:
            u, v = px(np.array([run.start_in_world[:2]]))[0]
            cv2.circle(canvas, (int(u), int(v)), 6, color, -1, cv2.LINE_AA)
            cv2.putText(
                canvas,
                run.name,
                (int(u) + 8, int(v) - 8),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.5,
                color,
                1,
                cv2.LINE_AA,
            )
        cv2.putText(
            canvas,
            f"{run.name}: map and path (grey: true path)",
            (MARGIN_PX, LINE_PX * (i + 2)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            color,
            1,
            cv2.LINE_AA,
        )
    cv2.putText(
        canvas,
        "world frame",
        (MARGIN_PX, LINE_PX),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.6,
        (0, 0, 0),
        1,
        cv2.LINE_AA,
    )
    write_png(out, canvas)
    return drawn
