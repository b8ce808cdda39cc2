"""`rgbdnav localize`: track a CARMEN log or an RGB-D recording against a saved map.

The map is a bundle folder written by ``rgbdnav map`` or any Nav2 ``map.yaml`` (slam_toolbox,
map_server, ...). Scans and their odometry come from the same stream as ``rgbdnav map``
(:func:`rgbdnav.scan_stream.scan_stream`): a laser log's per-scan laser poses, or for a recording
the EKF-fused odometry with depth turned into scans. Each scan goes through
:meth:`slam.localization.Localizer.update`. The run directory holds:

``trajectory.tum``
    The pose in ``map`` of every scan on which the localiser is ``tracking``: base_link's for a
    recording (the localiser tracks the scan's frame, ``depth_to_scan.output_frame``), the
    laser's for a laser log. Scans while lost or relocalising have no established pose and no
    line (counted in the summary).
``localization.csv``
    One row per scan, ``stamp_s,x_m,y_m,yaw_rad,confidence,status,reason,sigma_x_m,sigma_y_m,
    sigma_yaw_rad``: stamp [s], pose [m, m, rad] and its 1-sigma (amcl_pose's covariance
    diagonal; empty without a pose), confidence in [0, 1], status and the localiser's reason.
``summary.json``
    Counts per status, lost episodes, relocalisations with the scans each took, confidence
    percentiles, throughput, the map, and errors against ground truth when the source has it.
``map.png``
    Occupied map cells with the localised trajectory (and ground truth).
``config.yaml``
    The resolved configuration.
"""

from __future__ import annotations

import csv
import io
import logging
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from rgbdnav.cache import open_world_or_source
from rgbdnav.config import initial_pose_array, load_config
from rgbdnav.report import gps_chart, plot_trajectories
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
from sensors.atomic import atomic_write_text
from sensors.geo import geo_anchor_of, read_geo_anchor
from sensors.gps import GpsStream, read_gps_txt
from sensors.source import PoseStream
from sensors.tum import write_tum_trajectory
from sensors.types import SensorError
from slam.depth_to_scan import base_covariance, base_pose, scan_pose
from slam.geometry import oplus, wrap_angle
from slam.localization import GpsPrior, LocalizationResult, Localizer, MapModel
from slam.map_bundle import LoadedMap, load_map
from slam.metrics import interpolate_poses
from slam.occupancy_grid import OccupancyGrid
from slam.scan_matching import scan_points, transform_points

log = logging.getLogger(__name__)

CSV_HEADER = (
    *("stamp_s", "x_m", "y_m", "yaw_rad", "confidence", "status", "reason"),
    *("sigma_x_m", "sigma_y_m", "sigma_yaw_rad"),  # appended: readers by position still work
)
EPISODES_LISTED = 50  # lost episodes / relocalisations itemised in summary.json (all are counted)
WRONG_POSITION_M = 0.2  # [m] a tracked pose this far from ground truth counts as wrong
WRONG_HEADING_RAD = np.radians(5.0)  # [rad] likewise for heading
NS_PER_S = 1_000_000_000


# 1. The map ----------------------------------------------------------------------------------


# 2. Pure summaries of a run ------------------------------------------------------------------


def has_pose(result: LocalizationResult) -> bool:
    """Only a tracking scan has an established pose (lost / relocalising: unknown covariance);
    a rejected scan (bad odometry or stamp) is not part of the trajectory."""
    return result.status == "tracking" and not result.reason.startswith("rejected")


def episodes(results: Sequence[LocalizationResult]) -> tuple[list[dict], list[dict], dict | None]:
    """Lost episodes, relocalisations and the unresolved tail of a run.

    A relocalisation is a scan that starts tracking after scans without a pose; it took
    ``scans`` = the scans from the first one without a pose up to and including itself. A lost
    episode starts at a scan whose status turns ``lost``."""
    lost: list[dict] = []
    relocs: list[dict] = []
    start: int | None = None  # first scan of the current stretch without a pose
    start_kind = ""
    prev = "tracking"
    for k, r in enumerate(results):
        if r.reason.startswith("rejected"):
            continue  # the localiser ignored the scan: its status is the previous one
        if r.status == "lost" and prev != "lost":
            lost.append({"scan": k, "stamp_s": r.stamp_ns / NS_PER_S, "reason": r.reason})
        if r.status != "tracking" and start is None:
            start, start_kind = k, ("lost" if r.status == "lost" else "start of run")
        elif r.status == "tracking" and start is not None:
            relocs.append(
                {
                    "scan": k,
                    "stamp_s": r.stamp_ns / NS_PER_S,
                    "scans": k - start + 1,
                    "after": start_kind,
                    "reason": r.reason,
                }
            )
            if lost and start_kind == "lost":
                lost[-1]["scans_to_relocalise"] = k - start + 1
            start = None
        prev = r.status
    tail = None
    if start is not None:
        tail = {
            "since_scan": start,
            "scans": len(results) - start,
            "after": start_kind,
            "last_reason": results[-1].reason,
        }
    return lost, relocs, tail


def _stats(values: np.ndarray, digits: int = 4) -> dict[str, float | int | None]:
    if len(values) == 0:
        return {"count": 0, "median": None, "p95": None, "max": None}
    return {
        "count": len(values),
        "median": round(float(np.median(values)), digits),
        "p95": round(float(np.percentile(values, 95)), digits),
        "max": round(float(values.max()), digits),
    }


def errors_against_truth(
    stamps_ns: np.ndarray, poses: np.ndarray, gt: PoseStream
) -> dict[str, Any]:
    """Position [m] and heading [deg] errors of tracked poses against ground truth interpolated
    at their stamps, and how many of them are confidently wrong (beyond WRONG_*)."""
    gx, gy, gyaw, inside = interpolate_poses(gt.stamps_ns, gt.x, gt.y, gt.yaw, stamps_ns)
    p = poses[inside]
    d = np.hypot(p[:, 0] - gx[inside], p[:, 1] - gy[inside])
    a = np.abs(wrap_angle(p[:, 2] - gyaw[inside]))
    wrong = int(np.count_nonzero((d > WRONG_POSITION_M) | (a > WRONG_HEADING_RAD)))
    return {
        "matched": int(np.count_nonzero(inside)),
        "position_error_m": _stats(d),
        "heading_error_deg": _stats(np.degrees(a), 3),
        "tracked_but_wrong": wrong,
        "wrong_means": f"> {WRONG_POSITION_M} m or > {np.degrees(WRONG_HEADING_RAD):.0f} deg",
        "note": "assumes the map frame is the ground truth's frame (true for maps that "
        "rgbdnav map built from a recording of the same world)",
    }


def _stamp_text(stamp_ns: int) -> str:
    return f"{stamp_ns // NS_PER_S}.{stamp_ns % NS_PER_S:09d}"


def csv_text(results: Sequence[LocalizationResult]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_HEADER)
    for r in results:
        pose, sigma = ["", "", ""], ["", "", ""]
        if has_pose(r):
            pose = [f"{v:.6f}" for v in r.pose]
            sigma = [f"{v:.6f}" for v in np.sqrt(np.clip(np.diag(r.covariance), 0.0, None))]
        w.writerow(
            [_stamp_text(r.stamp_ns), *pose, f"{r.confidence:.4f}", r.status, r.reason, *sigma]
        )
    return buf.getvalue()


# 3. The run ----------------------------------------------------------------------------------


def run_localize(
    source_path: Path,
    map_path: Path,
    out: Path,
    config_files: Sequence[Path],
    overrides: Sequence[str],
    initial_pose: Sequence[float] | None = None,
    progress: Callable[[int, int], None] | None = None,
    rrd: Path | None = None,
    viewer: bool = False,
    force_3dof: bool = False,
    gps_path: Path | None = None,
    seed: int = 0,
    stop: StopSignals | None = None,
) -> tuple[dict[str, Path], dict[str, Any]]:
    """Localise every scan of ``source_path`` in the map; (files written, summary). ``rrd`` /
    ``viewer`` log the run to rerun (:mod:`rgbdnav.visualize`). GPS fixes (``gps_path``, else the
    source's own NavSatFix / gps.txt) through the map's geo anchor are the global search's
    prior. A world file is rendered on demand with ``seed``."""
    t0 = time.perf_counter()
    # 1. The map first: a bad map fails before the source is read or anything is written.
    loaded = load_map(map_path)
    init = None if initial_pose is None else initial_pose_array(initial_pose)
    cfg = load_config(config_files, overrides)
    vis = make_visualizer("localize", rrd, viewer)  # fails before the run, not after it
    try:
        src = open_world_or_source(source_path, cfg, seed)
    except BaseException:
        vis.close()
        raise
    try:
        # depth->scan with the RGB-D profile, as the map was made
        _, config_files, cfg, extrinsics = source_config(src, config_files, overrides)
        t_model = time.perf_counter()
        model = MapModel.from_grid(
            loaded.grid, cfg.localizer, loaded.occupied_thresh, loaded.free_thresh
        )
        model_s = time.perf_counter() - t_model
        g = loaded.grid.geometry
        summary: dict[str, Any] = {
            "command": "localize",
            "source": str(source_path),
            "source_kind": src.describe(),
            "config_files": [str(p) for p in config_files],
            "extrinsics": extrinsics,
            "map": {
                "path": str(map_path),
                "kind": loaded.kind,
                "resolution": g.resolution,
                "width": g.width,
                "height": g.height,
                "origin": [g.origin_x, g.origin_y],
                "occupied_thresh": loaded.occupied_thresh,
                "free_thresh": loaded.free_thresh,
                "occupied_cells": int(np.count_nonzero(model.occupied)),
                "free_cells": int(np.count_nonzero(model.free)),
            },
        }
        if init is not None:
            summary["initial_pose"] = {"pose": init.tolist(), "cell": model.cell_class(init[:2])}
        run = RunDir(out)
        outputs = {"config": run.write_config(cfg)}
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
        gps = _gps_fixes(src, gps_path, map_path)
        # 2. Localise every scan (each new GPS fix narrows the global search) in the scan's
        #    frame; what is reported is base_link's pose.
        loc = Localizer(
            model, cfg.localizer, None if init is None else scan_pose(init, scan_in_base)
        )
        prior = GpsPrior(loc, scan_in_base, (cfg.robot.gps_x, cfg.robot.gps_y))
        if gps is not None:
            for t, xy, sigma in zip(*gps, strict=True):
                prior.add_fix(int(t), xy, float(sigma))
        odoms = []
        results: list[LocalizationResult] = []
        scans_map: list[np.ndarray] = []  # tracked scans in the map frame, for the visualiser
        drawing = not isinstance(vis, NullVisualizer)
        update_s = 0.0
        for k, (scan, odom) in enumerate(stream):
            t = time.perf_counter()
            odoms.append(base_pose(odom, scan_in_base))
            prior.before_scan(scan.stamp_ns, odom)
            res = loc.update(scan, odom)
            update_s += time.perf_counter() - t
            if drawing and has_pose(res):
                scans_map.append(transform_points(res.pose, scan_points(scan)))
            results.append(
                replace(
                    res,
                    pose=base_pose(res.pose, scan_in_base),
                    covariance=base_covariance(res.pose, res.covariance, scan_in_base),
                )
            )
            if progress is not None:
                progress(k + 1, total)
        if stop is not None:
            stop.record(summary, len(results), total)
        if not results:
            raise SensorError(f"{source_path}: no usable scans to localise")
        # 3. Trajectory (tracked scans only) and the per-scan table.
        posed = [r for r in results if has_pose(r)]
        stamps = np.array([r.stamp_ns for r in posed], dtype=np.int64)
        poses = np.array([r.pose for r in posed], dtype=np.float64).reshape(-1, 3)
        write_tum_trajectory(
            run.file("trajectory.tum"), stamps, poses[:, 0], poses[:, 1], poses[:, 2]
        )
        outputs["trajectory"] = run.file("trajectory.tum")
        atomic_write_text(run.file("localization.csv"), csv_text(results))
        outputs["per-scan"] = run.file("localization.csv")
        # 4. Summary.
        statuses = [r.status for r in results]
        lost, relocs, tail = episodes(results)
        conf = np.array([r.confidence for r in posed])
        scans_to_reloc = np.array([e["scans"] for e in relocs], dtype=np.float64)
        duration_s = (results[-1].stamp_ns - results[0].stamp_ns) / NS_PER_S
        summary.update(
            {
                "frame": frame,
                "counts": {
                    "scans": len(results),
                    **{s: statuses.count(s) for s in ("tracking", "lost", "relocalising")},
                    "with_pose": len(posed),
                    "without_pose": len(results) - len(posed),
                    "rejected": sum(r.reason.startswith("rejected") for r in results),
                },
                "lost_episodes": {"count": len(lost), "episodes": lost[:EPISODES_LISTED]},
                "relocalisations": {
                    "count": len(relocs),
                    "scans_to_relocalise": _stats(scans_to_reloc, 1),
                    "events": relocs[:EPISODES_LISTED],
                },
                "unresolved_at_end": tail,
                "confidence_when_tracking": {
                    **_stats(conf),
                    "p05": (round(float(np.percentile(conf, 5)), 4) if len(conf) else None),
                },
                "localizer": {
                    "global_searches": loc.stats.global_searches,
                    "kidnap_checks": loc.stats.kidnap_checks,
                    "matches": loc.stats.matches,
                    "refined": loc.stats.refined,
                    "refine_fallbacks": loc.stats.refine_fallbacks,
                },
                "timings_s": {
                    "map_model": round(model_s, 3),
                    "localisation": round(update_s, 3),
                    "wall": round(time.perf_counter() - t0, 3),
                },
                "scans_per_s": round(len(results) / update_s, 1) if update_s > 0 else None,
                "data_duration_s": round(duration_s, 3),
                "real_time_factor": round(duration_s / update_s, 2) if update_s > 0 else None,
                "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            }
        )
        paths = [("localised", poses[:, 0], poses[:, 1])]
        gt = src.groundtruth()
        if gt is not None and gt.frame == "base_link" and frame == "base_link":
            if len(posed):
                summary["vs_groundtruth"] = errors_against_truth(stamps, poses, gt)
            paths.insert(0, ("ground truth", gt.x, gt.y))
        paths = [p for p in paths if len(p[1])]
        if not paths:
            # Nothing was localised: mark the map's centre so the picture still shows the map.
            cx = g.origin_x + g.width * g.resolution / 2
            cy = g.origin_y + g.height * g.resolution / 2
            paths = [("no pose established", np.array([cx]), np.array([cy]))]
        plot_trajectories(
            run.file("map.png"),
            paths,
            f"{source_path.name} in {map_path.name}",
            occupied=model.occupied,
            origin=(g.origin_x, g.origin_y),
            resolution=g.resolution,
        )
        outputs["picture"] = run.file("map.png")
        if gps is not None:
            summary["gps"] = _gps_chart(
                run.file("gps.png"),
                results,
                np.array(odoms),
                gps,
                model,
                loaded.grid.geometry,
                source_path.name,
            )
            outputs["run chart"] = run.file("gps.png")
        _visualize(
            vis,
            stamps,
            poses,
            scans_map,
            model.occupied,
            loaded.grid,
            gt if gt is not None and gt.frame == frame == "base_link" else None,
        )
        if rrd is not None:
            outputs["rerun recording"] = rrd
        summary["source_skipped"] = dict(src.skipped)  # bad records, by reason
        # lines of message types this reader does not use (CARMEN SYNC, ...), by type
        summary["source_ignored"] = dict(getattr(src, "ignored", {}))
        outputs["summary"] = run.write_summary(summary)
        return outputs, summary
    finally:
        vis.close()
        src.close()


def _gps_fixes(
    src: Any, gps_path: Path | None, map_path: Path
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(stamps_ns, xy in the map (N, 2) [m], sigma_h [m]) of the GPS fixes, or None: from
    ``gps_path`` (a gps.txt; the map must then have a geo anchor), else the source's own fixes
    when both they and the anchor exist."""
    if gps_path is not None:
        stream = read_gps_txt(gps_path)
        if len(stream) == 0:
            raise SensorError(f"{gps_path}: no GPS fixes")
        return stream.stamps_ns, stream.in_map(geo_anchor_of(map_path)), stream.sigma_m
    gps_of = getattr(src, "gps", None)
    own: GpsStream | None = gps_of() if callable(gps_of) else None
    if own is None or len(own) == 0:
        return None
    anchor = read_geo_anchor(map_path)
    if anchor is None:
        log.warning(
            "%s has GPS fixes but %s has no geo anchor (geo.yaml): GPS unused",
            src.path,
            map_path,
        )
        return None
    return own.stamps_ns, own.in_map(anchor), own.sigma_m


def _gps_chart(
    path: Path,
    results: Sequence[LocalizationResult],
    odoms: np.ndarray,
    gps: tuple[np.ndarray, np.ndarray, np.ndarray],
    model: MapModel,
    g: Any,
    name: str,
) -> dict[str, Any]:
    """The run chart (:func:`rgbdnav.report.gps_chart`): odometry placed in the map at the
    first localised pose; and the GPS part of the summary."""
    posed = [k for k, r in enumerate(results) if has_pose(r)]
    placed = oplus(results[posed[0]].map_to_odom, odoms) if posed else np.zeros((0, 3))
    summary = gps_chart(
        path,
        (
            "localiser",
            np.array([results[k].stamp_ns for k in posed], np.int64),
            np.array([results[k].pose[:2] for k in posed]).reshape(-1, 2),
        ),
        placed[:, :2],
        gps,
        f"{name}: localiser, odometry and GPS",
        model.occupied,
        (g.origin_x, g.origin_y),
        g.resolution,
    )
    return {**summary, "scans_to_first_pose": posed[0] + 1 if posed else None}


def _visualize(
    vis: Visualizer,
    stamps: np.ndarray,
    poses: np.ndarray,
    scans_map: list[np.ndarray],
    occupied: np.ndarray,
    grid: OccupancyGrid,
    gt: PoseStream | None,
) -> None:
    """The tracked poses and their scans on rerun's time line, the map's occupied cells (and
    the ground truth when the source has it)."""
    if isinstance(vis, NullVisualizer) or not len(stamps):
        return
    g = grid.geometry
    log_run(
        vis,
        stamps,
        poses,
        scans_map,
        occupied_cells_xy(occupied, (g.origin_x, g.origin_y), g.resolution),
        None if gt is None else np.column_stack([gt.x, gt.y]),
    )


def describe(summary: dict[str, Any]) -> str:
    """One line for the terminal: how much was tracked, relocalisations and lost episodes."""
    c = summary["counts"]
    rel = summary["relocalisations"]
    conf = summary["confidence_when_tracking"]["median"]
    text = (
        f"tracked {c['tracking']}/{c['scans']} scans, {rel['count']} relocalisation(s), "
        f"{summary['lost_episodes']['count']} lost episode(s)"
    )
    if conf is not None:
        text += f", median confidence {conf:.2f}"
    tail = summary["unresolved_at_end"]
    if tail is not None:
        text += f"; no pose for the last {tail['scans']} scans ({tail['last_reason']})"
    return text


__all__ = [
    "LoadedMap",
    "csv_text",
    "describe",
    "episodes",
    "errors_against_truth",
    "has_pose",
    "load_map",
    "run_localize",
]
