"""`rgbdnav map`: a pose-graph map of a CARMEN laser log or an RGB-D source, as a map bundle.

Laser logs feed their scans with the log's per-scan laser pose as odometry. RGB-D sources go
through the front end (:mod:`rgbdnav.scan_stream`: wheels, ``/odom``, IMU and VO in the EKF,
depth -> scan), each frame's scan fed with its fused pose moved to the scan's frame; ``odom.tum``
in the run directory. The bundle keeps the scan frame's poses with the scans; ``trajectory.tum``
and the scores are base_link's.
"""

from __future__ import annotations

import logging
import math
import resource
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from rgbdnav.cache import open_world_or_source
from rgbdnav.config import Config, load_config
from rgbdnav.report import plot_trajectories
from rgbdnav.run_dir import RunDir
from rgbdnav.scan_stream import scan_stream, source_config
from rgbdnav.stop_signals import StopSignals
from rgbdnav.visualize import (
    NullVisualizer,
    Visualizer,
    log_run,
    make_visualizer,
    occupied_cells_xy,
)
from sensors.sim.world import FloorPlan, floor_plan, world_from_dict
from sensors.source import PoseStream
from sensors.tum import write_tum_trajectory
from sensors.types import SensorError
from slam.depth_to_scan import base_pose
from slam.map_bundle import load_bundle, save_bundle
from slam.mapper import Mapper, MapperResult, build_grid, make_bundle
from slam.metrics import align_se2, drift_summary, interpolate_poses
from slam.occupancy_grid import GridGeometry, OccupancyGrid
from slam.scan_matching import scan_points, transform_points

log = logging.getLogger(__name__)

IOU_TOLERANCE_CELLS = 1  # a mapped wall within one cell of the true one counts


def run_map(
    source_path: Path,
    out: Path,
    config_files: Sequence[Path],
    overrides: Sequence[str],
    progress: Callable[[int, int], None] | None = None,
    continue_bundle: Path | None = None,
    rrd: Path | None = None,
    viewer: bool = False,
    force_3dof: bool = False,
    seed: int = 0,
    stop: StopSignals | None = None,
) -> dict[str, Path]:
    """Map ``source_path``: any source, or a world file rendered on demand with ``seed``.

    Once ``stop`` is set (the CLI's SIGINT/SIGTERM) no more frames are read: the scans read so
    far are optimised and saved as a complete bundle, the summary's ``interrupted`` says after
    how many."""
    t0 = time.perf_counter()
    vis = make_visualizer("map", rrd, viewer)  # fails before minutes of mapping, not after
    cfg = load_config(config_files, overrides)
    src = open_world_or_source(source_path, cfg, seed)
    try:
        scene, config_files, cfg, extrinsics = source_config(src, config_files, overrides)
        run = RunDir(out)
        outputs = {"config": run.write_config(cfg)}
        summary: dict = {
            "command": "map",
            "source": str(source_path),
            "source_kind": src.describe(),
            "extrinsics": extrinsics,
        }
        mapper_cfg = cfg.mapper
        if continue_bundle is not None:
            previous = load_bundle(continue_bundle)
            mapper = Mapper.from_bundle(mapper_cfg, previous, cfg.localizer)
            summary["continued_from"] = str(continue_bundle)
        else:
            mapper = Mapper(mapper_cfg)
        summary["config_files"] = [str(p) for p in config_files]
        stream, total, frame, scan_in_base = scan_stream(
            src,
            source_path,
            cfg,
            run,
            summary,
            outputs,
            force_3dof,
            None if stop is None else stop.is_set,
        )
        t_map = time.perf_counter()
        first_ns = last_ns = None
        read = 0
        for read, (scan, odom) in enumerate(stream, 1):
            mapper.add_scan(scan, odom)
            first_ns = scan.stamp_ns if first_ns is None else first_ns
            last_ns = scan.stamp_ns
            if progress is not None:
                progress(read, total)
        if stop is not None:
            stop.record(summary, read, total)
        result = mapper.finish()
        mapping_s = time.perf_counter() - t_map
        if len(result.scan_stamps_ns) == 0:
            raise SensorError(f"{source_path}: no usable scans to map")
        # 1. Trajectory: one pose per accepted scan, of base_link (the laser for a laser log).
        p = base_pose(result.scan_poses, scan_in_base)
        write_tum_trajectory(
            run.file("trajectory.tum"), result.scan_stamps_ns, p[:, 0], p[:, 1], p[:, 2]
        )
        outputs["trajectory"] = run.file("trajectory.tum")
        # 2. Occupancy grid from the optimised keyframes, and the bundle.
        t_grid = time.perf_counter()
        grid = build_grid(result, cfg.mapper)
        bundle = make_bundle(result, grid, cfg.mapper, str(source_path))
        save_bundle(bundle, run.file("map"))
        outputs["map bundle"] = run.file("map")
        grid_s = time.perf_counter() - t_grid
        duration_s = (last_ns - first_ns) / 1e9 if first_ns is not None and last_ns else 0.0
        wall = time.perf_counter() - t0
        summary.update(
            {
                "frame": frame,
                "counts": result.counts,
                "timings_s": {
                    **result.timings_s,
                    "mapping_total": round(mapping_s, 3),
                    "grid_and_bundle": round(grid_s, 3),
                    "wall": round(wall, 3),
                },
                "data_duration_s": round(duration_s, 3),
                "real_time_factor": round(duration_s / mapping_s, 2) if mapping_s > 0 else None,
                "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                "grid": {
                    "resolution": grid.geometry.resolution,
                    "width": grid.geometry.width,
                    "height": grid.geometry.height,
                },
            }
        )
        paths = [("SLAM", p[:, 0], p[:, 1])]
        gt = src.groundtruth()
        if gt is not None and gt.frame == "base_link" and frame == "base_link":
            _score_against_truth(result, grid, gt, scene, cfg, summary, p)
            paths.insert(0, ("ground truth", gt.x, gt.y))
        occ = grid.occupied_mask(cfg.mapper.occupied_thresh)
        g = grid.geometry
        plot_trajectories(
            run.file("map.png"),
            paths,
            f"{source_path.name}: map",
            occupied=occ,
            origin=(g.origin_x, g.origin_y),
            resolution=g.resolution,
        )
        outputs["picture"] = run.file("map.png")
        summary["source_skipped"] = dict(src.skipped)  # bad records, by reason
        # lines of message types this reader does not use (CARMEN SYNC, ...), by type
        summary["source_ignored"] = dict(getattr(src, "ignored", {}))
        outputs["summary"] = run.write_summary(summary)
        truth = gt if gt is not None and frame == "base_link" else None
        _visualize(vis, result, p, occ, g, truth)
        if rrd is not None:
            outputs["rerun recording"] = rrd
        return outputs
    finally:
        vis.close()
        src.close()


def _visualize(
    vis: Visualizer,
    result: MapperResult,
    path: np.ndarray,
    occupied: np.ndarray,
    g: GridGeometry,
    gt: PoseStream | None,
) -> None:
    """The run on rerun's time line: each keyframe's scan at its optimised pose, the path, the
    final map (and the ground truth when the source has it); ``path``: the reported poses."""
    if isinstance(vis, NullVisualizer):
        return
    kf_stamps = np.array([k.stamp_ns for k in result.keyframes], dtype=np.int64)
    scans = [
        transform_points(p, scan_points(k.scan))
        for k, p in zip(result.keyframes, result.poses, strict=True)
    ]
    log_run(
        vis,
        kf_stamps,
        np.asarray(result.poses).reshape(-1, 3),
        scans,
        occupied_cells_xy(occupied, (g.origin_x, g.origin_y), g.resolution),
        None if gt is None else np.column_stack([gt.x, gt.y]),
    )
    if len(result.scan_stamps_ns):
        vis.pose(int(result.scan_stamps_ns[-1]), path[-1], path[:, :2])


def occupancy_iou(
    mapped: np.ndarray, truth: np.ndarray, tolerance_cells: int
) -> dict[str, float | int]:
    """IoU of two aligned occupied masks where a cell within ``tolerance_cells`` of the other
    mask's occupied cells counts as matching (TP from the mapped side, FN from the truth side)."""
    k = np.ones((2 * tolerance_cells + 1,) * 2, np.uint8)
    near_truth = cv2.dilate(truth.astype(np.uint8), k) > 0
    near_mapped = cv2.dilate(mapped.astype(np.uint8), k) > 0
    tp = int(np.count_nonzero(mapped & near_truth))
    fp = int(np.count_nonzero(mapped)) - tp
    fn = int(np.count_nonzero(truth & ~near_mapped))
    iou = tp / max(tp + fp + fn, 1)
    return {"iou": round(iou, 4), "true_positive": tp, "false_positive": fp, "false_negative": fn}


def _score_against_truth(
    result: MapperResult,
    grid: OccupancyGrid,
    gt: PoseStream,
    scene: dict,
    cfg: Config,
    summary: dict,
    poses: np.ndarray | None = None,
) -> None:
    """``poses``: base_link's per scan (default: the mapper's, a scan frame at base_link)."""
    stamps_ns = result.scan_stamps_ns
    p = result.scan_poses if poses is None else poses
    summary["slam_vs_groundtruth"] = drift_summary(
        stamps_ns, (p[:, 0], p[:, 1], p[:, 2]), gt.stamps_ns, (gt.x, gt.y, gt.yaw)
    )
    world = scene.get("world_description")
    if not isinstance(world, dict):
        return
    plan = floor_plan(world_from_dict(world))
    mapped = grid.occupied_mask(cfg.mapper.occupied_thresh)
    summary["grid_vs_floor_plan"] = {
        **occupancy_iou(mapped, _true_surface(plan, grid), IOU_TOLERANCE_CELLS),
        "tolerance_cells": IOU_TOLERANCE_CELLS,
        "truth": "floor-plan surface cells (occupied next to free) the robot observed",
    }
    # The map's frame is where the robot started: a map that is right in shape but placed a
    # few cm / a fraction of a degree off as a whole loses IoU at every far wall. Scored again
    # with the floor plan moved by the SE(2) alignment of the aligned ATE, this separates the
    # map's shape from its placement (both are reported; neither replaces the other).
    rx, ry, _, inside = interpolate_poses(gt.stamps_ns, gt.x, gt.y, gt.yaw, stamps_ns)
    if inside.sum() >= 2:
        rot, t = align_se2(p[inside, :2], np.column_stack([rx, ry])[inside])
        summary["grid_vs_floor_plan_aligned"] = {
            **occupancy_iou(mapped, _true_surface(plan, grid, rot, t), IOU_TOLERANCE_CELLS),
            "tolerance_cells": IOU_TOLERANCE_CELLS,
            "alignment": {
                "yaw_deg": round(math.degrees(math.atan2(rot[1, 0], rot[0, 0])), 4),
                "x_m": round(float(t[0]), 4),
                "y_m": round(float(t[1]), 4),
            },
            "truth": "as grid_vs_floor_plan, after the trajectory's SE(2) alignment",
        }


def _true_surface(
    plan: FloorPlan, grid: OccupancyGrid, rot: np.ndarray | None = None, t: np.ndarray | None = None
) -> np.ndarray:
    """The floor plan's surface cells (occupied next to free) the robot observed, rasterised
    into the map's grid; with (rot, t) mapping map to world (``world = rot @ map + t``)."""
    g = grid.geometry
    rows, cols = np.nonzero(plan.occupied)
    xy = np.column_stack(
        [
            plan.origin_x + (cols + 0.5) * plan.resolution,
            plan.origin_y + (rows + 0.5) * plan.resolution,
        ]
    )
    if rot is not None and t is not None:
        xy = (xy - t) @ rot  # world -> map
    r, c = g.world_to_cell(xy[:, 0], xy[:, 1])
    ok = g.contains(r, c)
    truth = np.zeros((g.height, g.width), bool)
    truth[r[ok], c[ok]] = True
    # A sensor sees surfaces: the truth is the occupied cells next to free space (not the
    # inside of a wall or cabinet), and only where the robot looked.
    ring = np.ones((3, 3), np.uint8)
    surface = truth & (cv2.dilate((~truth).astype(np.uint8), ring) > 0)
    seen = cv2.dilate(grid.observed.astype(np.uint8), ring) > 0
    return surface & seen


__all__ = ["build_grid", "make_bundle", "occupancy_iou", "run_map"]
