"""`rgbdnav odometry`: wheel odometry of a source, synchronised to its camera frames and scored
against its ground truth when it has some."""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rgbdnav.config import Config, load_config, source_options
from rgbdnav.report import contact_sheet, plot_trajectories
from rgbdnav.run_dir import RunDir
from sensors.recording_source import RecordingSource
from sensors.sim.world import floor_plan, world_from_dict
from sensors.source import Source, open_source
from sensors.sync import interpolate_wheels, synchronise
from sensors.tum import write_tum_trajectory
from sensors.types import NS_PER_S, ImuSample, Pose2, RgbdFrame, SensorError
from slam.diff_drive import (
    GLITCH_SPEED_FACTOR,
    WheelErrorModel,
    integrate_ticks,
    propagate_covariance,
    reject_encoder_glitches,
    wheel_increments,
)
from slam.ekf import TwistInput, fuse, motion_twist, wheel_twist_inputs
from slam.geometry import compose
from slam.metrics import drift_summary, interpolate_poses
from slam.visual_odometry import VisualOdometry

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
    on_frame: Callable[[RgbdFrame], None] | None = None,
) -> dict[str, Path]:
    """Odometry of any source with wheel encoders (recording, TUM folder + wheels, bag): wheel
    dead reckoning, visual odometry when it has RGB-D frames, and their EKF fusion with the gyro."""
    t0 = time.perf_counter()
    cfg = load_config(config_files, overrides)
    src = open_source(source_path, source_options(cfg))
    try:
        return _run(src, source_path, out, config_files, overrides, t0, use_vo, progress,
                    on_frame)  # fmt: skip
    finally:
        src.close()


@dataclass
class _VoTrack:
    """Visual odometry over a source's frames: per-frame twists for the EKF and the VO-only path."""

    inputs: list[TwistInput]
    stamps_ns: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    failures: dict[str, int]
    ms_median: float
    stats: dict[str, int]  # VisualOdometry.stats: depth ICP fallbacks used / failed


def _visual_odometry(src: Source, cfg: Config, start: Pose2,
                     progress: Callable[[int, int], None] | None,
                     on_frame: Callable[[RgbdFrame], None] | None = None,
                     ) -> _VoTrack | None:  # fmt: skip
    intrinsics = src.intrinsics()
    n = len(src.stream_stamps().get("rgb", ()))
    if intrinsics is None or n < 2:
        return None
    vo = VisualOdometry(intrinsics, cfg.vo, cfg.robot)
    inputs: list[TwistInput] = []
    stamps, poses, ms = [], [], []
    failures: Counter[str] = Counter()
    x, y, yaw = start.x, start.y, start.yaw
    prev_t = None
    for k, frame in enumerate(src.frames()):
        res = vo.process(frame)
        ms.append(res.ms)
        if on_frame is not None:  # e.g. the mapper's depth -> scan, without decoding twice
            on_frame(frame)
        if prev_t is not None:
            dt = (frame.stamp_ns - prev_t) / NS_PER_S
            d = res.delta_base
            if res.success and d is not None and dt > 0:
                # 1. The pair's planar motion as a body twist, its covariance scaled to rates.
                inputs.append(motion_twist(frame.stamp_ns, d, res.covariance, dt))
                # 2. The VO-only path: compose the motion (a failed pair's motion is lost).
                x, y, yaw = (float(v) for v in compose(x, y, yaw, d.x, d.y, d.yaw))
            else:
                inputs.append(TwistInput(frame.stamp_ns, 0.0, 0.0, 0.0, np.eye(3), valid=False))
                failures[res.reason] += 1
        prev_t = frame.stamp_ns
        stamps.append(frame.stamp_ns)
        poses.append((x, y, yaw))
        if progress is not None:
            progress(k + 1, n)
    arr = np.array(poses).reshape(-1, 3)
    return _VoTrack(inputs, np.array(stamps, np.int64), arr[:, 0], arr[:, 1], arr[:, 2],
                    dict(failures), float(np.median(ms)) if ms else math.nan,
                    dict(vo.stats))  # fmt: skip


def _run(src: Source, source_path: Path, out: Path, config_files: Sequence[Path],
         overrides: Sequence[str], t0: float, use_vo: bool,
         progress: Callable[[int, int], None] | None,
         on_frame: Callable[[RgbdFrame], None] | None = None) -> dict[str, Path]:  # fmt: skip
    scene = src.recording.scene if isinstance(src, RecordingSource) else {}
    # A recording's own robot description sits under the user's files and --set.
    base = {k: scene[k] for k in ("robot",) if isinstance(scene.get(k), dict)}
    cfg = load_config(config_files, overrides, base=base)
    run = RunDir(out)
    outputs = {"config": run.write_config(cfg)}

    wheels = src.wheels()
    if wheels is None or len(wheels.stamps_ns) < 2:
        raise SensorError(f"{source_path}: no wheel encoder readings (need at least 2)")
    # Plausibility gate: a glitched reading is not 300 km of motion (counted in the summary).
    clean = reject_encoder_glitches(wheels.stamps_ns, wheels.left, wheels.right, cfg.robot)
    stamps, left, right = clean.stamps_ns, clean.left, clean.right
    if clean.glitches_dropped or clean.jumps_zeroed:
        log.warning("%s: %d encoder reading(s) jumped off and back (dropped), %d step(s) "
                    "faster than %.0fx the wheel speed limit (taken as no motion)", source_path,
                    clean.glitches_dropped, clean.jumps_zeroed, GLITCH_SPEED_FACTOR)  # fmt: skip
    gt = src.groundtruth()
    start = Pose2(0.0, 0.0, 0.0)
    if gt is not None and gt.frame == "base_link":
        gx, gy, gyaw, _ = interpolate_poses(gt.stamps_ns, gt.x, gt.y, gt.yaw, stamps[:1])
        start = Pose2(float(gx[0]), float(gy[0]), float(gyaw[0]))
    x, y, yaw = integrate_ticks(left, right, cfg.robot, start)
    ds, dtheta = wheel_increments(left, right, cfg.robot)
    model = WheelErrorModel.from_robot(cfg.robot)
    cov = propagate_covariance(ds, dtheta, start.yaw, cfg.robot, model)
    write_tum_trajectory(run.file("wheel.tum"), stamps, x, y, yaw)
    outputs["wheel odom"] = run.file("wheel.tum")

    # 1. Frames: approximate-time sets of colour and depth (message_filters semantics).
    stamp_streams = src.stream_stamps()
    camera: dict[str, np.ndarray] = {
        k: stamp_streams[k] for k in ("rgb", "depth") if k in stamp_streams
    }
    frame_t = np.zeros(0, dtype=np.int64)
    sync_stats = None
    if camera:
        index, sync_stats = synchronise(
            camera,
            int(cfg.sync.slop * 1e9),
            cfg.sync.queue_size,
            warn_fraction=cfg.sync.warn_fraction,
        )
        lead = "rgb" if "rgb" in camera else next(iter(camera))
        frame_t = np.asarray(camera[lead])[index[lead]]
    # 2. One pose per frame, at the frame's stamp, where encoder readings bracket it.
    gap = int(cfg.sync.max_interpolation_gap * 1e9)
    _, _, ok = interpolate_wheels(stamps, left, right, frame_t, gap)
    fx, fy, fyaw, _ = interpolate_poses(stamps, x, y, yaw, frame_t)
    write_tum_trajectory(run.file("trajectory.tum"), frame_t[ok], fx[ok], fy[ok], fyaw[ok])
    outputs["trajectory"] = run.file("trajectory.tum")

    summary: dict = {
        "command": "odometry",
        "source": str(source_path),
        "source_kind": src.describe(),
        "estimator": "wheel odometry (diff drive, midpoint integration)",
        "frames": int(len(frame_t)),
        "wheel_readings": int(len(stamps)),
        "wheel_readings_dropped_glitch": clean.glitches_dropped,
        "wheel_jumps_taken_as_no_motion": clean.jumps_zeroed,
        "trajectory_poses": int(ok.sum()),
        "frames_without_odometry": int((~ok).sum()),
        "final_pose_sigma": {
            "x_m": float(np.sqrt(cov[-1, 0, 0])),
            "y_m": float(np.sqrt(cov[-1, 1, 1])),
            "yaw_deg": float(np.degrees(np.sqrt(cov[-1, 2, 2]))),
        },
    }
    if sync_stats is not None:
        summary["sync"] = {
            "sets": sync_stats.sets,
            "dropped_fraction": sync_stats.dropped_fraction,
            "mean_spread_ms": sync_stats.mean_spread_ns / 1e6 if sync_stats.sets else None,
            "streams": dict(sync_stats.streams),
        }
    # 3. Visual odometry over the RGB-D frames (optional: the slowest step).
    vo_track = _visual_odometry(src, cfg, start, progress, on_frame) if use_vo else None
    # 4. EKF: wheel twists (+ gyro, + VO twists) -> odom -> base_link. A sensor whose
    #    <sensor>_config selects nothing is not an input (and is not named as one).
    streams: dict[str, list] = {}
    if any(cfg.ekf.odom0_config):
        streams["odom0"] = wheel_twist_inputs(
            stamps, left, right, cfg.robot, model, vy_variance=cfg.ekf.odom0_vy_variance,
            max_interval_s=1.0 / cfg.ekf.frequency,
        )  # fmt: skip
    if vo_track is not None:
        if any(cfg.ekf.vo0_config):
            streams["vo0"] = vo_track.inputs
        write_tum_trajectory(run.file("vo.tum"), vo_track.stamps_ns, vo_track.x, vo_track.y,
                             vo_track.yaw)  # fmt: skip
        outputs["visual odom"] = run.file("vo.tum")
        summary["vo"] = {
            "frames": int(len(vo_track.stamps_ns)),
            "pairs_tracked": int(sum(i.valid for i in vo_track.inputs)),
            "failures": vo_track.failures,
            "ms_per_frame_median": round(vo_track.ms_median, 2),
            **vo_track.stats,  # fallback_used / fallback_failed (vo.fallback)
        }
    imu = src.imu()
    if imu is not None and len(imu.stamps_ns) and any(cfg.ekf.imu0_config):
        streams["imu0"] = [ImuSample(int(t), float(g)) for t, g in zip(imu.stamps_ns, imu.gyro_z,
                                                                        strict=True)]  # fmt: skip
    fused = fuse(streams, cfg.ekf, output_stamps_ns=frame_t[ok],
                 gyro_z_variance=cfg.ekf.imu0_angular_velocity_variance)  # fmt: skip
    # The filter starts at the odom origin; place odom at the start pose in the world.
    ex, ey, eyaw = compose(start.x, start.y, start.yaw, fused.x, fused.y, fused.yaw)
    good = np.isfinite(ex)
    write_tum_trajectory(run.file("fused.tum"), fused.stamps_ns[good], ex[good], ey[good],
                         eyaw[good])  # fmt: skip
    outputs["fused odom"] = run.file("fused.tum")
    summary["ekf"] = {"inputs": sorted(streams), "stats": fused.stats}

    fused_label = "EKF (" + " + ".join(LABELS[k] for k in sorted(streams)) + ")"
    paths = [("wheel odometry", x, y), (fused_label, ex[good], ey[good])]
    if vo_track is not None:
        paths.append(("visual odometry", vo_track.x, vo_track.y))
    if gt is not None and gt.frame == "base_link":
        ref = (gt.x, gt.y, gt.yaw)
        summary["wheel_odometry_vs_groundtruth"] = drift_summary(stamps, (x, y, yaw),
                                                                 gt.stamps_ns, ref)  # fmt: skip
        summary["fused_vs_groundtruth"] = drift_summary(
            fused.stamps_ns[good], (ex[good], ey[good], eyaw[good]), gt.stamps_ns, ref
        )
        if vo_track is not None:
            summary["vo_vs_groundtruth"] = drift_summary(
                vo_track.stamps_ns, (vo_track.x, vo_track.y, vo_track.yaw), gt.stamps_ns, ref
            )
        write_tum_trajectory(run.file("groundtruth.tum"), gt.stamps_ns, gt.x, gt.y, gt.yaw)
        outputs["ground truth"] = run.file("groundtruth.tum")
        paths.insert(0, ("ground truth", gt.x, gt.y))
    plan = None
    if isinstance(scene.get("world_description"), dict):
        plan = floor_plan(world_from_dict(scene["world_description"]))
    plot_trajectories(
        run.file("trajectory.png"), paths, f"{source_path.name}: odometry",
        occupied=None if plan is None else plan.occupied,
        origin=(0.0, 0.0) if plan is None else (plan.origin_x, plan.origin_y),
        resolution=0.05 if plan is None else plan.resolution,
    )  # fmt: skip
    outputs["picture"] = run.file("trajectory.png")
    if isinstance(src, RecordingSource) and len(src.recording):
        rec = src.recording
        pick = np.linspace(0, len(rec) - 1, CONTACT_SHEET_FRAMES).round().astype(int)
        frames = [(f.rgb, f.depth_m) for f in (rec.frame(int(k)) for k in np.unique(pick))]
        contact_sheet(run.file("frames.png"), frames)
        outputs["frames"] = run.file("frames.png")
    summary["wall_time_s"] = round(time.perf_counter() - t0, 3)
    summary["source_skipped"] = dict(src.skipped)  # bad records, by reason
    outputs["summary"] = run.write_summary(summary)
    return outputs
