"""Run the simulator: world + route (or a replayed trajectory) -> a recording on disk.

1. Drive the route (or replay a trajectory) at the physics rate: exact ground truth.
2. Sample encoders (true geometry, slip, backlash) at the board's polling rate, the gyro at
   the IMU rate, and ground truth at the mocap rate.
3. Pick camera frames at 30 Hz, drop a few, jitter their stamps, and render each one at its true
   capture time.
4. Write everything through the atomic recording writer.

Randomness comes from one seed split into independent streams, so the same seed and inputs give
byte-identical recordings.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sensors.config import CameraConfig, RobotConfig, SimConfig, section_to_dict
from sensors.gps import SimGpsConfig, simulate_gps
from sensors.recording import RecordingWriter
from sensors.sim.motion import (
    Trajectory,
    drive_route,
    encoder_counts,
    replay_tum,
    sample_times,
)
from sensors.sim.render import KinectRenderer
from sensors.sim.world import World, load_world
from sensors.types import NS_PER_S, RgbdFrame, WorldError

log = logging.getLogger(__name__)

MIN_STAMP_STEP_NS = 1_000_000  # [ns] reported camera stamps stay at least this far apart

Progress = Callable[[int, int], None]  # (done, total)


@dataclass(frozen=True)
class SimulationSummary:
    world: str
    seed: int
    frames: int
    dropped_frames: int
    duration_s: float
    path_length_m: float
    wheel_samples: int
    imu_samples: int

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _streams(seed: int) -> dict[str, np.random.Generator]:
    names = ("encoders", "camera", "render", "imu", "noise_bank")
    children = np.random.SeedSequence(seed).spawn(len(names))
    return {n: np.random.default_rng(c) for n, c in zip(names, children, strict=True)}


def plan_trajectory(
    world: World,
    robot: RobotConfig,
    sim: SimConfig,
    trajectory: str | Path | None = None,
    duration_s: float | None = None,
    frames: int | None = None,
) -> Trajectory:
    traj = replay_tum(trajectory, robot, sim) if trajectory else drive_route(world, sim)
    if frames is not None:
        if frames < 1:
            raise WorldError(f"frames must be >= 1, got {frames}")
        # Room for the dropped frames; camera_stamps() then keeps exactly ``frames``.
        margin = frames * 2 * sim.frame_drop_probability + 5
        duration_s = min(duration_s or math.inf, (frames + margin) / sim.camera_rate)
    if duration_s is not None:
        if duration_s <= 0:
            raise WorldError(f"duration must be > 0 s, got {duration_s}")
        traj = traj.truncated(duration_s)
    if len(traj.t_ns) < 2:
        raise WorldError("the trajectory is too short to simulate (less than one physics step)")
    return traj


def camera_stamps(
    duration_ns: int, sim: SimConfig, rng: np.random.Generator, max_frames: int | None = None
) -> tuple[np.ndarray, np.ndarray, int]:
    """(true capture times, reported stamps, dropped count): nominal 30 Hz, a few frames dropped,
    reported stamps jittered but kept strictly increasing."""
    nominal = sample_times(duration_ns, sim.camera_rate)
    keep = rng.random(len(nominal)) >= sim.frame_drop_probability
    keep[0] = True  # a recording always starts with a frame
    if max_frames is not None:
        keep &= np.cumsum(keep) <= max_frames
        nominal, keep = (
            nominal[: np.flatnonzero(keep)[-1] + 1],
            keep[: np.flatnonzero(keep)[-1] + 1],
        )
    capture = nominal[keep]
    jitter = np.round(rng.standard_normal(len(capture)) * sim.stamp_jitter * NS_PER_S)
    stamps = capture + jitter.astype(np.int64)
    stamps = np.maximum(stamps, 0)
    # Jitter never reorders frames: s_i >= s_(i-1) + MIN_STAMP_STEP, solved without a loop as
    # s'_i = i*step + max_(j<=i)(s_j - j*step).
    idx = np.arange(len(stamps), dtype=np.int64) * MIN_STAMP_STEP_NS
    stamps = np.maximum.accumulate(stamps - idx) + idx
    return capture, stamps, int((~keep).sum())


def simulate(
    world_path: str | Path,
    out: str | Path,
    robot: RobotConfig,
    camera: CameraConfig,
    sim: SimConfig,
    seed: int = 0,
    duration_s: float | None = None,
    frames: int | None = None,
    trajectory: str | Path | None = None,
    progress: Progress | None = None,
) -> SimulationSummary:
    world = load_world(world_path)
    rngs = _streams(seed)
    traj = plan_trajectory(world, robot, sim, trajectory, duration_s, frames)
    # Camera frames first: with --frames the recording ends at the last frame.
    capture, stamps, dropped = camera_stamps(int(traj.t_ns[-1]), sim, rngs["camera"], frames)
    if frames is not None:
        # Keep one encoder period past the last frame so wheel readings bracket every frame.
        traj = traj.truncated(capture[-1] / NS_PER_S + 1.0 / sim.wheel_rate)
    duration_ns = int(traj.t_ns[-1])

    # 2. Encoders, gyro and ground truth, each at its own rate.
    left, right = encoder_counts(traj, robot, sim, rngs["encoders"])
    wheel_t = sample_times(duration_ns, sim.wheel_rate)
    phys = np.searchsorted(traj.t_ns, wheel_t, side="right") - 1  # last physics step done
    imu_t = sample_times(duration_ns, sim.imu_rate)
    w_true = np.interp(imu_t, traj.t_ns, traj.w)
    gyro = w_true + sim.gyro_bias + sim.gyro_noise * rngs["imu"].standard_normal(len(imu_t))
    gt_t = sample_times(duration_ns, sim.groundtruth_rate)
    gt_x, gt_y, gt_yaw = traj.interpolate(gt_t)

    # 3. Render each camera frame at its true capture time.
    cam_x, cam_y, cam_yaw = traj.interpolate(capture)
    bank_seed = int(rngs["noise_bank"].integers(2**31))
    renderer = KinectRenderer(world, camera, robot, sim, noise_seed=bank_seed)
    scene = {
        "generator": "rgbdnav simulate",
        "world": world.name,
        "world_file": str(world_path),
        "world_description": yaml.safe_load(Path(world_path).read_text()),
        "trajectory_source": str(trajectory) if trajectory else "route",
        "seed": seed,
        "groundtruth_frame": "base_link",
        "robot": section_to_dict(robot),
        "sim": section_to_dict(sim),
    }
    render_rng = rngs["render"]
    with RecordingWriter(out, renderer.intrinsics, scene) as writer:
        for k in range(len(capture)):
            pose = float(cam_x[k]), float(cam_y[k]), float(cam_yaw[k])
            rgb, depth = renderer.render(*pose, render_rng)
            writer.add_frame(RgbdFrame(int(stamps[k]), rgb, depth, renderer.intrinsics))
            if progress is not None:
                progress(k + 1, len(capture))
        writer.add_wheels(wheel_t, left[phys], right[phys])
        if sim.gyro_enabled:
            writer.add_imu(imu_t, gyro)
        writer.set_groundtruth(gt_t, gt_x, gt_y, gt_yaw)
        if world.geo is not None:  # a receiver riding base_link (sensors/gps.py defaults)
            gps_xy = np.column_stack([gt_x, gt_y])
            writer.set_gps(simulate_gps(gt_t, gps_xy, world.geo, SimGpsConfig(), seed))
    summary = SimulationSummary(
        world=world.name,
        seed=seed,
        frames=len(capture),
        dropped_frames=dropped,
        duration_s=duration_ns / NS_PER_S,
        path_length_m=traj.length_m(),
        wheel_samples=len(wheel_t),
        imu_samples=len(imu_t) if sim.gyro_enabled else 0,
    )
    log.info(
        "simulated %s: %d frames, %.1f m in %.1f s",
        world.name,
        summary.frames,
        summary.path_length_m,
        summary.duration_s,
    )
    return summary
