"""The navigation target scenario: furniture moved relative to the map, seeded random goals, a
keepout zone; reached %, collisions, keepout entries, clearance, path length, time. Driven by
``bench/bench_nav.py --scenario`` over the ``navigate`` run; not a CLI verb, so it lives here.

A scenario file (``scenes/scenarios/nav_house.yaml``)::

    world: house.yaml          # the world the map was built from (relative to this file)
    goals: 20                  # seeded random goals
    seed: 0
    furniture_shift: 0.3       # [m] each piece of furniture moves up to this in x and in y
    furniture_yaw: 0.3         # [rad] and turns up to this
    goal_clearance: 0.45       # [m] goals at least this far from anything, in map and world
    goal_separation: 2.0       # [m] consecutive goals at least this far apart
    goal_tolerance: 0.25       # [m] a goal counts as reached when the TRUE position is this close
    keepout:                   # keepout zones [x_min, y_min, x_max, y_max] in the map frame
      - [9.0, 7.0, 11.5, 8.2]
    set:                       # config overrides for the run, as --set (before the caller's)
      - follower.xy_goal_tolerance=0.1

Everything random derives from ``seed``: the moved world (written to the run directory as
``world_moved.yaml``, so a run can be reproduced with ``rgbdnav navigate``), and the goals.
The map is never changed. A goal is drawn from the cells that are free in the map and in the
moved world with ``goal_clearance``, outside the keepout zones by the same margin, reachable from
the start in both (connected free space at the robot's inscribed radius), and at least
``goal_separation`` from the previous goal.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from nav.costmap import inscribed_radius
from rgbdnav.config import load_config
from rgbdnav.run_dir import RunDir
from sensors.atomic import atomic_write_text
from sensors.safe_yaml import read_yaml
from sensors.sim.world import FloorPlan, floor_plan, world_from_dict
from sensors.types import ConfigError
from slam.map_bundle import load_map, save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid

KEEPOUT_OCCUPANCY = 100  # nav_msgs value of a keepout cell in the mask
GOAL_TRIES_PER_GOAL = 200  # draws per goal before the separation rule gives up


@dataclass(frozen=True)
class Scenario:
    world_path: Path
    world: dict[str, Any]  # the world YAML as loaded (the map's world)
    goals: int
    seed: int
    furniture_shift: float  # [m]
    furniture_yaw: float  # [rad]
    goal_clearance: float  # [m]
    goal_separation: float  # [m]
    keepout: tuple[tuple[float, float, float, float], ...]  # [m] x_min, y_min, x_max, y_max
    goal_tolerance: float = 0.25  # [m] success criterion on the true position
    overrides: tuple[str, ...] = ()  # --set style config overrides


def _number(
    data: Mapping[str, Any], key: str, default: float, where: str, lo: float = 0.0
) -> float:
    v = data.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < lo:
        raise ConfigError(f"{where}: {key} must be a number >= {lo}, got {v!r}")
    return float(v)


def load_scenario(path: Path) -> Scenario:
    """Read a scenario YAML; unknown keys and bad values raise :class:`ConfigError`."""
    data = read_yaml(path, ConfigError, "scenario")
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: a scenario is a mapping")
    known = {
        "world",
        "goals",
        "seed",
        "furniture_shift",
        "furniture_yaw",
        "goal_clearance",
        "goal_separation",
        "goal_tolerance",
        "keepout",
        "set",
        "description",
    }
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f"{path}: {unknown[0]}: unknown key (valid: {', '.join(sorted(known))})")
    if "world" not in data:
        raise ConfigError(f"{path}: missing 'world'")
    world_path = (Path(path).parent / str(data["world"])).resolve()
    world = read_yaml(world_path, ConfigError, "world")
    world_from_dict(world, str(world_path))  # validate now
    boxes = []
    for i, k in enumerate(data.get("keepout") or []):
        if (
            not isinstance(k, list)
            or len(k) != 4
            or not all(isinstance(v, int | float) for v in k)
            or k[0] >= k[2]
            or k[1] >= k[3]
        ):
            raise ConfigError(
                f"{path}: keepout[{i}] must be [x_min, y_min, x_max, y_max] with "
                f"min < max, got {k!r}"
            )
        boxes.append((float(k[0]), float(k[1]), float(k[2]), float(k[3])))
    goals = int(_number(data, "goals", 20, str(path), 1))
    sets = data.get("set") or []
    if not isinstance(sets, list) or not all(isinstance(v, str) and "=" in v for v in sets):
        raise ConfigError(f"{path}: set must be a list of section.key=value strings")
    return Scenario(
        world_path,
        world,
        goals,
        int(_number(data, "seed", 0, str(path))),
        _number(data, "furniture_shift", 0.3, str(path)),
        _number(data, "furniture_yaw", 0.3, str(path)),
        _number(data, "goal_clearance", 0.45, str(path)),
        _number(data, "goal_separation", 2.0, str(path)),
        tuple(boxes),
        _number(data, "goal_tolerance", 0.25, str(path)),
        tuple(sets),
    )


# 1. Pure pieces ------------------------------------------------------------------------------


def move_furniture(
    world: Mapping[str, Any], rng: np.random.Generator, shift_m: float, yaw_rad: float
) -> dict[str, Any]:
    """A copy of a world dict whose furniture is moved by uniform [-shift, shift] in x and y and
    turned by uniform [-yaw, yaw]; walls stay."""
    out = copy.deepcopy(dict(world))
    pieces = out.get("furniture") or []
    d = rng.uniform(-1.0, 1.0, size=(len(pieces), 3)) * [shift_m, shift_m, yaw_rad]
    for f, (dx, dy, dyaw) in zip(pieces, d, strict=True):
        f["center"] = [round(float(f["center"][0] + dx), 4), round(float(f["center"][1] + dy), 4)]
        f["yaw"] = round(float(f.get("yaw", 0.0) + dyaw), 4)
    return out


def keepout_grid(geometry: GridGeometry, boxes: Sequence[Sequence[float]]) -> OccupancyGrid:
    """A keepout filter mask on ``geometry``: cells whose centre is in a box are occupied (100),
    the rest free (0)."""
    rows, cols = np.indices(geometry.shape)
    x, y = geometry.cell_to_world(rows, cols)
    inside = np.zeros(geometry.shape, dtype=bool)
    for x0, y0, x1, y1 in boxes:
        inside |= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return OccupancyGrid.from_occupancy_values(geometry, np.where(inside, KEEPOUT_OCCUPANCY, 0))


def _resample(plan: FloorPlan, geometry: GridGeometry) -> np.ndarray:
    """The floor plan's occupancy at each cell centre of ``geometry`` (outside = free)."""
    rows, cols = np.indices(geometry.shape)
    x, y = geometry.cell_to_world(rows, cols)
    rc = plan.cell_of(np.column_stack([x.ravel(), y.ravel()]))
    h, w = plan.occupied.shape
    ok = (rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)
    occ = np.zeros(len(rc), dtype=bool)
    occ[ok] = plan.occupied[rc[ok, 0], rc[ok, 1]]
    return occ.reshape(geometry.shape)


def _reachable(passable: np.ndarray, row: int, col: int) -> np.ndarray:
    """Cells 8-connected to (row, col) through ``passable`` cells."""
    from scipy.ndimage import label

    labels, _ = label(passable, structure=np.ones((3, 3), dtype=bool))
    if not passable[row, col]:
        return np.zeros_like(passable)
    return labels == labels[row, col]


def goal_candidates(
    map_free: np.ndarray,
    map_occupied: np.ndarray,
    world_occupied: np.ndarray,
    keepout: np.ndarray,
    start_cell: tuple[int, int],
    resolution: float,
    clearance_m: float,
    inscribed_m: float,
) -> np.ndarray:
    """(H, W) bool cells a goal may be drawn from (all arrays on the map's geometry): map-free,
    ``clearance_m`` from map obstacles, world obstacles, unknown space and keepout zones, and
    connected to ``start_cell`` through cells at least ``inscribed_m`` from obstacles in the map
    and in the world."""
    from scipy.ndimage import distance_transform_edt

    def dist(mask: np.ndarray) -> np.ndarray:
        return np.asarray(distance_transform_edt(~mask)) * resolution

    d_map, d_world = dist(map_occupied), dist(world_occupied)
    d_unknown = dist(~map_free & ~map_occupied)
    d_keep = dist(keepout) if keepout.any() else np.full(keepout.shape, np.inf)
    margin = inscribed_m + 0.5 * resolution
    reach = _reachable((d_map > margin) & (d_world > margin) & ~keepout, *start_cell)
    return (
        map_free
        & reach
        & (d_map >= clearance_m)
        & (d_world >= clearance_m)
        & (d_unknown >= clearance_m)
        & (d_keep >= clearance_m)
    )


def draw_goals(
    candidates: np.ndarray,
    geometry: GridGeometry,
    rng: np.random.Generator,
    n: int,
    first_from: tuple[float, float],
    separation_m: float,
) -> list[tuple[float, float]]:
    """``n`` goals from candidate cells, each at least ``separation_m`` from the one before (the
    first from ``first_from``); :class:`ConfigError` when the candidates cannot provide them."""
    rows, cols = np.nonzero(candidates)
    if len(rows) == 0:
        raise ConfigError("no cell qualifies as a goal (free, clear, reachable, outside keepout)")
    xs, ys = geometry.cell_to_world(rows, cols)
    goals: list[tuple[float, float]] = []
    prev = first_from
    for k in range(n):
        far = np.hypot(xs - prev[0], ys - prev[1]) >= separation_m
        if not far.any():
            raise ConfigError(
                f"goal {k}: no candidate cell is {separation_m} m from "
                f"({prev[0]:.2f}, {prev[1]:.2f})"
            )
        i = int(rng.choice(np.flatnonzero(far)))
        prev = (round(float(xs[i]), 3), round(float(ys[i]), 3))
        goals.append(prev)
    return goals


def floor_plan_map(scenario: Scenario, path: Path, resolution: float = 0.05) -> Path:
    """A Nav2 map.yaml of the scenario's (unmoved) world from its floor plan: every wall and
    piece of furniture solid at its true size -- exact geometry, the best map a mapper could
    make. (Walls drawn one cell thick on their centre line put every wall face a scan sees
    half a wall thickness, 6 cm in the house, in front of the map's wall: a bias of the map,
    not of the localiser.) Returns ``path``."""
    world = dict(scenario.world)
    plan = floor_plan(world_from_dict(world, "floor-plan map"), resolution)
    h, w = plan.occupied.shape
    grid = OccupancyGrid.from_occupancy_values(
        GridGeometry(resolution, plan.origin_x, plan.origin_y, w, h),
        np.where(plan.occupied, 100, 0),
    )
    save_map_yaml(grid, path)
    return path


# 2. The run ----------------------------------------------------------------------------------


def prepare(
    scenario: Scenario,
    map_path: Path,
    out: Path,
    n_goals: int | None = None,
    config_files: Sequence[Path] = (),
    overrides: Sequence[str] = (),
) -> tuple[Path, Path, list[tuple[float, float]]]:
    """Write the moved world and the keepout mask into ``out/scenario`` and draw the goals;
    (world path, keepout map.yaml, goals)."""
    rng = np.random.default_rng(scenario.seed)
    moved = move_furniture(scenario.world, rng, scenario.furniture_shift, scenario.furniture_yaw)
    world = world_from_dict(moved, "moved world")
    loaded = load_map(map_path)
    geo = loaded.grid.geometry
    cfg = load_config(config_files, overrides)
    keep = keepout_grid(geo, scenario.keepout)
    start = world.start
    start_cell = tuple(int(v) for v in geo.world_to_cell(start[0], start[1]))
    if not bool(geo.contains(*start_cell)):
        raise ConfigError(f"the world's start {start[:2]} is outside the map {map_path}")
    grid = loaded.grid
    cand = goal_candidates(
        grid.free_mask(loaded.free_thresh),
        grid.occupied_mask(loaded.occupied_thresh),
        _resample(floor_plan(world, resolution=geo.resolution), geo),
        keep.occupied_mask(),
        (start_cell[0], start_cell[1]),
        geo.resolution,
        scenario.goal_clearance,
        inscribed_radius(cfg.costmap),
    )
    goals = draw_goals(
        cand,
        geo,
        rng,
        scenario.goals if n_goals is None else n_goals,
        (start[0], start[1]),
        scenario.goal_separation,
    )
    d = out / "scenario"
    d.mkdir(parents=True, exist_ok=True)
    world_path = d / "world_moved.yaml"
    atomic_write_text(
        world_path,
        "# furniture moved relative to the map (seed "
        f"{scenario.seed})\n" + yaml.safe_dump(moved, sort_keys=False),
    )
    keepout_path = d / "keepout.yaml"
    save_map_yaml(keep, keepout_path)
    atomic_write_text(d / "goals.json", json.dumps(goals) + "\n")
    return world_path, keepout_path, goals


def scenario_figures(summary: Mapping[str, Any], tolerance_m: float) -> dict[str, Any]:
    """The target's numbers from a navigate summary."""
    goals = summary["goals"]
    n = len(goals)
    within = sum(g["status"] == "reached" and g["final_error_m"] <= tolerance_m for g in goals)
    return {
        "goals": n,
        "reached": sum(g["status"] == "reached" for g in goals),
        "reached_within_tolerance": within,
        "reached_within_tolerance_percent": round(100.0 * within / n, 1) if n else None,
        "goal_tolerance_m": tolerance_m,
        "collisions": summary["collisions"]["events"],
        "keepout_entries": summary["keepout_entries"]["events"],
        "min_clearance_m": summary["collisions"]["min_clearance_m"],
        "min_keepout_distance_m": summary["keepout_entries"]["min_distance_m"],
        "path_length_m": summary["path_length_m"],
        "sim_time_s": summary["sim_time_s"],
        "wall_s": summary["wall_s"],
        "ms_per_control_step": summary["control"]["ms_per_step"],
        "localization": summary["localization"]["mode"],
        "position_error_m": summary["localization"]["position_error_m"],
        "recoveries": summary["recoveries"],
        "failures": [
            {
                "goal": g["goal"],
                "status": g["status"],
                "reason": g["reason"],
                "final_error_m": g.get("final_error_m"),
            }
            for g in goals
            if not (g["status"] == "reached" and g["final_error_m"] <= tolerance_m)
        ],
    }


def run_scenario(
    scenario_path: Path,
    map_path: Path,
    out: Path,
    n_goals: int | None = None,
    config_files: Sequence[Path] = (),
    overrides: Sequence[str] = (),
    localization: str = "localizer",
    progress: Callable[[int, int], None] | None = None,
    seed: int | None = None,
) -> tuple[dict[str, Path], dict[str, Any]]:
    """Prepare the scenario, drive it with :func:`run_navigate`; the summary gains "scenario".
    ``seed`` replaces the file's (another moved world, other goals, other noise)."""
    from rgbdnav.runners.navigate import run_navigate

    scenario = load_scenario(scenario_path)
    if seed is not None:
        scenario = replace(scenario, seed=seed)
    overrides = [*scenario.overrides, *overrides]
    world_path, keepout_path, goals = prepare(
        scenario, map_path, out, n_goals, config_files, overrides
    )
    outputs, summary = run_navigate(
        map_path,
        goals,
        world_path,
        out,
        config_files,
        overrides,
        keepout_path=keepout_path,
        progress=progress,
        localization=localization,
        seed=scenario.seed,
    )
    summary["scenario"] = {
        "file": str(scenario_path),
        "seed": scenario.seed,
        "furniture_shift_m": scenario.furniture_shift,
        "furniture_yaw_rad": scenario.furniture_yaw,
        "keepout_zones": [list(k) for k in scenario.keepout],
        "overrides": list(scenario.overrides),
        **scenario_figures(summary, scenario.goal_tolerance),
    }
    RunDir(out).write_summary(summary)
    return outputs, summary


__all__ = [
    "Scenario",
    "draw_goals",
    "floor_plan_map",
    "goal_candidates",
    "keepout_grid",
    "load_scenario",
    "move_furniture",
    "prepare",
    "run_scenario",
    "scenario_figures",
]
