"""`rgbdnav odometry`: wheel odometry over a recording, scored against its ground truth."""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rgbdnav.config import load_config
from rgbdnav.report import contact_sheet, plot_trajectories
from rgbdnav.run_dir import RunDir
from sensors.recording import Recording
from sensors.sim.world import floor_plan, world_from_dict
from sensors.tum import write_tum_trajectory
from sensors.types import Pose2, SensorError
from slam.diff_drive import (
    WheelErrorModel,
    integrate_ticks,
    propagate_covariance,
    wheel_increments,
)
from slam.metrics import drift_report, interpolate_poses

CONTACT_SHEET_FRAMES = 4


def run_odometry(
    recording_path: Path, out: Path, config_files: Sequence[Path], overrides: Sequence[str]
) -> dict[str, Path]:
    t0 = time.perf_counter()
    rec = Recording.open(recording_path)
    # The recording's own robot and camera description sits under the user's files and --set.
    base = {k: rec.scene[k] for k in ("robot",) if isinstance(rec.scene.get(k), dict)}
    cfg = load_config(config_files, overrides, base=base)
    run = RunDir(out)
    outputs = {"config": run.write_config(cfg)}

    stamps, left, right = rec.wheels()
    if len(stamps) < 2:
        raise SensorError(f"{recording_path}: wheels.txt has {len(stamps)} readings; need >= 2")
    gt = rec.groundtruth_planar()
    start = Pose2(0.0, 0.0, 0.0)
    if gt is not None:
        gx, gy, gyaw, _ = interpolate_poses(gt[0], gt[1], gt[2], gt[3], stamps[:1])
        start = Pose2(float(gx[0]), float(gy[0]), float(gyaw[0]))
    x, y, yaw = integrate_ticks(left, right, cfg.robot, start)
    ds, dtheta = wheel_increments(left, right, cfg.robot)
    cov = propagate_covariance(
        ds, dtheta, start.yaw, cfg.robot, WheelErrorModel.from_robot(cfg.robot)
    )
    write_tum_trajectory(run.file("wheel.tum"), stamps, x, y, yaw)
    outputs["wheel odom"] = run.file("wheel.tum")
    # One pose per camera frame, stamped with the frame's stamp.
    frame_t = rec.rgb_stamps_ns[rec.rgb_index] if len(rec) else rec.rgb_stamps_ns
    fx, fy, fyaw, _ = interpolate_poses(stamps, x, y, yaw, frame_t)
    # Frames a little outside the encoder span hold the nearest pose (sync.max_interpolation_gap);
    # frames further out get no pose and are counted.
    gap = int(cfg.sync.max_interpolation_gap * 1e9)
    inside = (frame_t >= stamps[0] - gap) & (frame_t <= stamps[-1] + gap)
    write_tum_trajectory(run.file("trajectory.tum"), frame_t[inside], fx[inside], fy[inside],
                         fyaw[inside])  # fmt: skip
    outputs["trajectory"] = run.file("trajectory.tum")

    summary: dict = {
        "command": "odometry",
        "source": str(recording_path),
        "estimator": "wheel odometry (diff drive, midpoint integration)",
        "frames": len(rec),
        "wheel_readings": int(len(stamps)),
        "trajectory_poses": int(inside.sum()),
        "final_pose_sigma": {
            "x_m": float(np.sqrt(cov[-1, 0, 0])),
            "y_m": float(np.sqrt(cov[-1, 1, 1])),
            "yaw_deg": float(np.degrees(np.sqrt(cov[-1, 2, 2]))),
        },
        "frames_without_odometry": int((~inside).sum()),
    }
    paths = [("wheel odometry", x, y)]
    if gt is not None:
        report = drift_report(stamps, (x, y, yaw), gt[0], (gt[1], gt[2], gt[3]))
        summary["wheel_odometry_vs_groundtruth"] = report.as_dict()
        paths.insert(0, ("ground truth", gt[1], gt[2]))
    plan = None
    if isinstance(rec.scene.get("world_description"), dict):
        plan = floor_plan(world_from_dict(rec.scene["world_description"]))
    plot_trajectories(
        run.file("trajectory.png"), paths, f"{recording_path.name}: wheel odometry",
        occupied=None if plan is None else plan.occupied,
        origin=(0.0, 0.0) if plan is None else (plan.origin_x, plan.origin_y),
        resolution=0.05 if plan is None else plan.resolution,
    )  # fmt: skip
    outputs["picture"] = run.file("trajectory.png")
    if len(rec):
        pick = np.linspace(0, len(rec) - 1, CONTACT_SHEET_FRAMES).round().astype(int)
        frames = [(f.rgb, f.depth_m) for f in (rec.frame(int(k)) for k in np.unique(pick))]
        contact_sheet(run.file("frames.png"), frames)
        outputs["frames"] = run.file("frames.png")
    summary["wall_time_s"] = round(time.perf_counter() - t0, 3)
    outputs["summary"] = run.write_summary(summary)
    return outputs
