"""`rgbdnav odometry`: the front end (:mod:`slam.front_end`) over a source: wheel dead
reckoning, visual odometry and their EKF fusion with ``/odom`` and the gyro, whatever subset the
source has, scored against its ground truth when it has some. A handheld camera (no wheels, no
``/odom``) gets its 6-DoF camera poses in ``vo.tum`` (TUM convention), as evo expects."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from rgbdnav.cache import open_world_or_source
from rgbdnav.config import Config, camera_mount, load_config
from rgbdnav.report import contact_sheet, plot_trajectories
from rgbdnav.run_dir import RunDir
from rgbdnav.stop_signals import StopSignals
from sensors.recording_source import RecordingSource
from sensors.sim.world import floor_plan, world_from_dict
from sensors.source import Source
from sensors.sync import interpolate_wheels, synchronise
from sensors.tum import write_tum_poses, write_tum_trajectory
from sensors.types import Pose2, SensorError
from slam.diff_drive import (
    GLITCH_SPEED_FACTOR,
    WheelErrorModel,
    integrate_ticks,
    propagate_covariance,
    reject_encoder_glitches,
    wheel_increments,
)
from slam.front_end import FrontEnd, FrontEndStep, odom_origin, options_for, replay
from slam.geometry import compose
from slam.metrics import drift_summary, interpolate_poses

log = logging.getLogger(__name__)

CONTACT_SHEET_FRAMES = 4
LABELS = {"odom0": "wheels", "imu0": "gyro", "vo0": "VO"}


def run_odometry(
    source_path: Path,
    out: Path,
    config_files: Sequence[Path],
    overrides: Sequence[str],
    use_vo: bool = True,
    progress: Callable[[int, int], None] | None = None,
    force_3dof: bool = False,
    seed: int = 0,
    stop: StopSignals | None = None,
) -> dict[str, Path]:
    """Odometry of any source with wheels, ``/odom`` or RGB-D frames (recording, folder, bag),
    or of a world file rendered on demand with ``seed``. Once ``stop`` is set no more frames
    are read; the outputs cover the frames read (the wheel-only path, computed at once, covers
    the whole source) and the summary's ``interrupted`` says how many."""
    t0 = time.perf_counter()
    cfg = load_config(config_files, overrides)
    src = open_world_or_source(source_path, cfg, seed)
    try:
        scene = src.recording.scene if isinstance(src, RecordingSource) else {}
        # A recording's own robot description sits under the user's files and --set.
        base = {k: scene[k] for k in ("robot",) if isinstance(scene.get(k), dict)}
        base, extrinsics = camera_mount(src, config_files, overrides, base)
        cfg = load_config(config_files, overrides, base=base)
        scene = {**scene, "extrinsics": extrinsics}
        return _run(src, source_path, out, cfg, scene, t0, use_vo, progress, force_3dof, stop)
    finally:
        src.close()


def _run(
    src: Source,
    source_path: Path,
    out: Path,
    cfg: Config,
    scene: dict,
    t0: float,
    use_vo: bool,
    progress: Callable[[int, int], None] | None,
    force_3dof: bool,
    stop: StopSignals | None,
) -> dict[str, Path]:
    run = RunDir(out)
    outputs = {"config": run.write_config(cfg)}
    opts = options_for(src, use_vo, force_3dof, cfg.camera.rate)
    if not (opts.wheels or opts.odometry or opts.vo):
        raise SensorError(
            f"{source_path}: no odometry input: no wheel encoder readings (need at "
            "least 2), no odometry messages, and no visual odometry (--no-vo, or no RGB-D frames)"
        )
    wheels = src.wheels() if opts.wheels else None
    start = odom_origin(src)
    summary: dict = {
        "command": "odometry",
        "source": str(source_path),
        "source_kind": src.describe(),
        "mode": "planar (ground robot)" if opts.planar else "6-DoF (handheld camera)",
        "extrinsics": scene.get("extrinsics", {"source": "config"}),
    }
    paths: list[tuple[str, np.ndarray, np.ndarray]] = []
    if wheels is not None:
        paths += _wheel_odometry(src, cfg, start, run, summary, outputs)
    # The front end over every frame: VO, and the EKF over whatever inputs the source has.
    fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, replace(opts, scan=False))
    steps = []
    for step in replay(src, fe, progress if opts.vo else None):
        steps.append(step)
        if stop is not None and stop.is_set():
            break  # the replay is closed: no work is left queued
    if stop is not None:
        stop.record(summary, len(steps), len(src.stream_stamps().get("depth", ())), "frames")
    summary["frames"] = len(steps)
    tracked = sum(s.vo is not None and s.vo.success for s in steps)
    if not (opts.wheels or opts.odometry) and tracked == 0:
        raise SensorError(
            f"{source_path}: no usable odometry: VO tracked none of the "
            f"{max(len(steps) - 1, 0)} frame pairs and there are no wheel "
            "encoder readings or odometry messages"
        )
    vo_path = None
    if opts.vo:
        vo_path = _vo_outputs(steps, fe.vo_stats, opts.planar, start, run, summary, outputs)
        paths.append(("visual odometry", vo_path[1][:, 0], vo_path[1][:, 1]))
    if opts.planar:
        paths += _fused_outputs(src, steps, fe, start, run, summary, outputs, vo_path)
    summary["front_end_counts"] = dict(sorted(fe.counts.items()))
    gt = src.groundtruth()
    if gt is not None and gt.frame == "base_link":
        write_tum_trajectory(run.file("groundtruth.tum"), gt.stamps_ns, gt.x, gt.y, gt.yaw)
        outputs["ground truth"] = run.file("groundtruth.tum")
        paths.insert(0, ("ground truth", gt.x, gt.y))
    plan = None
    if isinstance(scene.get("world_description"), dict):
        plan = floor_plan(world_from_dict(scene["world_description"]))
    plot_trajectories(
        run.file("trajectory.png"),
        paths,
        f"{source_path.name}: odometry",
        occupied=None if plan is None else plan.occupied,
        origin=(0.0, 0.0) if plan is None else (plan.origin_x, plan.origin_y),
        resolution=0.05 if plan is None else plan.resolution,
    )
    outputs["picture"] = run.file("trajectory.png")
    if isinstance(src, RecordingSource) and len(src.recording):
        rec = src.recording
        pick = np.linspace(0, len(rec) - 1, CONTACT_SHEET_FRAMES).round().astype(int)
        frames = []
        for k in np.unique(pick):
            try:
                f = rec.frame(int(k))
            except SensorError:  # a bad image was skipped and counted above; not drawn here
                continue
            frames.append((f.rgb, f.depth_m))
        if frames:
            contact_sheet(run.file("frames.png"), frames)
            outputs["frames"] = run.file("frames.png")
    summary["wall_time_s"] = round(time.perf_counter() - t0, 3)
    summary["source_skipped"] = dict(src.skipped)  # bad records, by reason
    # lines of message types this reader does not use (CARMEN SYNC, ...), by type
    summary["source_ignored"] = dict(getattr(src, "ignored", {}))
    outputs["summary"] = run.write_summary(summary)
    return outputs


def _wheel_odometry(
    src: Source, cfg: Config, start: Pose2, run: RunDir, summary: dict, outputs: dict[str, Path]
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Dead reckoning from the encoders alone (``wheel.tum``) and at the camera frames
    (``trajectory.tum``), with the drift against ground truth."""
    wheels = src.wheels()
    assert wheels is not None
    # Plausibility gate: a glitched reading is not 300 km of motion (counted in the summary).
    clean = reject_encoder_glitches(wheels.stamps_ns, wheels.left, wheels.right, cfg.robot)
    stamps, left, right = clean.stamps_ns, clean.left, clean.right
    if clean.glitches_dropped or clean.jumps_zeroed:
        log.warning(
            "%s: %d encoder reading(s) jumped off and back (dropped), %d step(s) faster than "
            "%.0fx the wheel speed limit (taken as no motion)",
            src.describe(),
            clean.glitches_dropped,
            clean.jumps_zeroed,
            GLITCH_SPEED_FACTOR,
        )
    x, y, yaw = integrate_ticks(left, right, cfg.robot, start)
    ds, dtheta = wheel_increments(left, right, cfg.robot)
    cov = propagate_covariance(
        ds, dtheta, start.yaw, cfg.robot, WheelErrorModel.from_robot(cfg.robot)
    )
    write_tum_trajectory(run.file("wheel.tum"), stamps, x, y, yaw)
    outputs["wheel odom"] = run.file("wheel.tum")
    # Frames: approximate-time sets of colour and depth (message_filters semantics).
    stamp_streams = src.stream_stamps()
    camera: dict[str, np.ndarray] = {
        k: stamp_streams[k] for k in ("rgb", "depth") if k in stamp_streams
    }
    frame_t = np.zeros(0, dtype=np.int64)
    if camera:
        index, sync_stats = synchronise(
            camera,
            int(cfg.sync.slop * 1e9),
            cfg.sync.queue_size,
            warn_fraction=cfg.sync.warn_fraction,
        )
        lead = "rgb" if "rgb" in camera else next(iter(camera))
        frame_t = np.asarray(camera[lead])[index[lead]]
        summary["sync"] = {
            "sets": sync_stats.sets,
            "dropped_fraction": sync_stats.dropped_fraction,
            "mean_spread_ms": sync_stats.mean_spread_ns / 1e6 if sync_stats.sets else None,
            "streams": dict(sync_stats.streams),
        }
    # One pose per frame, at the frame's stamp, where encoder readings bracket it.
    gap = int(cfg.sync.max_interpolation_gap * 1e9)
    _, _, ok = interpolate_wheels(stamps, left, right, frame_t, gap)
    fx, fy, fyaw, _ = interpolate_poses(stamps, x, y, yaw, frame_t)
    write_tum_trajectory(run.file("trajectory.tum"), frame_t[ok], fx[ok], fy[ok], fyaw[ok])
    outputs["trajectory"] = run.file("trajectory.tum")
    summary |= {
        "estimator": "wheel odometry (diff drive, midpoint integration)",
        "wheel_readings": int(len(stamps)),
        "wheel_readings_dropped_glitch": clean.glitches_dropped,
        "wheel_jumps_taken_as_no_motion": clean.jumps_zeroed,
        "trajectory_poses": int(ok.sum()),
        "frames_outside_wheel_readings": int((~ok).sum()),
        "final_pose_sigma": {
            "x_m": float(np.sqrt(cov[-1, 0, 0])),
            "y_m": float(np.sqrt(cov[-1, 1, 1])),
            "yaw_deg": float(np.degrees(np.sqrt(cov[-1, 2, 2]))),
        },
    }
    gt = src.groundtruth()
    if gt is not None and gt.frame == "base_link":
        summary["wheel_odometry_vs_groundtruth"] = drift_summary(
            stamps, (x, y, yaw), gt.stamps_ns, (gt.x, gt.y, gt.yaw)
        )
    return [("wheel odometry", x, y)]


def _vo_outputs(
    steps: Sequence[FrontEndStep],
    vo_stats: dict[str, int],
    planar: bool,
    start: Pose2,
    run: RunDir,
    summary: dict,
    outputs: dict[str, Path],
) -> tuple[np.ndarray, np.ndarray]:
    """``vo.tum``: the VO alone, chained pair by pair (a failed pair's motion is lost). Planar:
    base_link poses placed at ``start``; handheld: 6-DoF camera poses (the first frame's optical
    frame is the origin), the TUM RGB-D convention. Returns (stamps, (N, 3) x, y, yaw)."""
    stamps = np.array([s.stamp_ns for s in steps], np.int64)
    results = [s.vo for s in steps if s.vo is not None]
    tracked = sum(r.success for r in results[1:])
    failures: dict[str, int] = {}
    for r in results[1:]:
        if not r.success:
            failures[r.reason] = failures.get(r.reason, 0) + 1
    ms = [s.vo_ms for s in steps if math.isfinite(s.vo_ms)]
    summary["vo"] = {
        "frames": len(steps),
        "pairs_tracked": int(tracked),
        "failures": failures,
        "ms_per_frame_median": round(float(np.median(ms)), 2) if ms else None,
        **vo_stats,  # fallback_used / fallback_failed (vo.fallback)
    }
    if not planar:
        poses = np.array([s.camera_pose for s in steps]).reshape(-1, 4, 4)
        write_tum_poses(run.file("vo.tum"), stamps, poses)
        outputs["visual odom"] = run.file("vo.tum")
        return stamps, poses[:, :3, 3]
    # Planar: compose each pair's base_link motion (cumulative, a loop over the frames' deltas).
    d = np.array(
        [
            (r.delta_base.x, r.delta_base.y, r.delta_base.yaw)
            if s.vo is not None and (r := s.vo).success and r.delta_base is not None
            else (0.0, 0.0, 0.0)
            for s in steps
        ]
    ).reshape(-1, 3)
    pose = np.zeros((len(steps), 3))
    x, y, yaw = start.x, start.y, start.yaw
    for k in range(len(steps)):
        x, y, yaw = (float(v) for v in compose(x, y, yaw, *d[k]))
        pose[k] = x, y, yaw
    write_tum_trajectory(run.file("vo.tum"), stamps, pose[:, 0], pose[:, 1], pose[:, 2])
    outputs["visual odom"] = run.file("vo.tum")
    return stamps, pose


def _fused_outputs(
    src: Source,
    steps: Sequence[FrontEndStep],
    fe: FrontEnd,
    start: Pose2,
    run: RunDir,
    summary: dict,
    outputs: dict[str, Path],
    vo_path: tuple[np.ndarray, np.ndarray] | None,
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``fused.tum``: the front end's ``odom -> base_link`` at every frame, placed at ``start``."""
    good = [s for s in steps if s.odom is not None]
    poses = [s.odom.pose for s in steps if s.odom is not None]
    t = np.array([s.stamp_ns for s in good], np.int64)
    p = np.array([(q.x, q.y, q.yaw) for q in poses]).reshape(-1, 3)
    ex, ey, eyaw = compose(start.x, start.y, start.yaw, p[:, 0], p[:, 1], p[:, 2])
    write_tum_trajectory(run.file("fused.tum"), t, ex, ey, eyaw)
    outputs["fused odom"] = run.file("fused.tum")
    assert fe.ekf is not None
    summary["ekf"] = {
        "inputs": list(fe.inputs),
        "stats": fe.ekf.stats,
        "frames_timed_out": int(sum(s.timed_out for s in good)),
    }
    gt = src.groundtruth()
    if gt is not None and gt.frame == "base_link":
        truth = (gt.stamps_ns, (gt.x, gt.y, gt.yaw))
        summary["fused_vs_groundtruth"] = drift_summary(t, (ex, ey, eyaw), *truth)
        if vo_path is not None:
            vt, vp = vo_path
            summary["vo_vs_groundtruth"] = drift_summary(vt, (vp[:, 0], vp[:, 1], vp[:, 2]), *truth)
    label = "EKF (" + " + ".join(LABELS[k] for k in fe.inputs) + ")"
    return [(label, ex, ey)]


__all__ = ["run_odometry"]
