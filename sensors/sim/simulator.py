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
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sensors.config import CameraConfig, RobotConfig, SimConfig, section_to_dict
from sensors.gps import GpsStream, SimGpsConfig, antenna_xy, simulate_gps
from sensors.recording import RecordingWriter
from sensors.sim.motion import (
    Trajectory,
    drive_route,
    encoder_counts,
    replay_tum,
    sample_times,
)
from sensors.sim.render import KinectRenderer, camera_intrinsics
from sensors.sim.world import World, load_world
from sensors.types import NS_PER_S, CameraIntrinsics, RgbdFrame, WorldError

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


@dataclass
class SimulationPlan:
    """Everything a world's recording holds except the images: the frames' stamps and camera
    poses, the low-rate streams, and the seeds the renderer draws its noise from. Rendering the
    frames in order (:meth:`renderer`, :func:`render_frames`) gives the recording's images."""

    world: World
    robot: RobotConfig
    camera: CameraConfig
    sim: SimConfig
    scene: dict[str, Any]
    intrinsics: CameraIntrinsics
    stamps_ns: np.ndarray  # reported frame stamps
    poses: np.ndarray  # (N, 3) base_link x, y, yaw at each frame's true capture time
    noise_seed: int  # the renderer's noise banks
    render_rng: np.random.Generator  # per-frame noise windows, drawn in frame order
    wheels: tuple[np.ndarray, np.ndarray, np.ndarray]
    imu: tuple[np.ndarray, np.ndarray] | None
    groundtruth: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    gps: GpsStream | None
    summary: SimulationSummary

    def renderer(self) -> KinectRenderer:
        return KinectRenderer(self.world, self.camera, self.robot, self.sim, self.noise_seed)

    def write_streams(self, writer: RecordingWriter) -> None:
        """The low-rate streams (wheels, gyro, ground truth, GPS) into ``writer``."""
        writer.add_wheels(*self.wheels)
        if self.imu is not None:
            writer.add_imu(*self.imu)
        writer.set_groundtruth(*self.groundtruth)
        if self.gps is not None:
            writer.set_gps(self.gps)


def render_frames(
    plan: SimulationPlan, rng: np.random.Generator | None = None
) -> Iterator[RgbdFrame]:
    """The plan's frames in order, rendered here; ``rng`` (default: the plan's own generator,
    which this advances) must be in the state the plan's generator had before frame 0."""
    renderer = plan.renderer()
    rng = plan.render_rng if rng is None else rng
    for stamp, (x, y, yaw) in zip(plan.stamps_ns, plan.poses, strict=True):
        rgb, depth = renderer.render(float(x), float(y), float(yaw), rng)
        yield RgbdFrame(int(stamp), rgb, depth, renderer.intrinsics)


def plan_simulation(
    world_path: str | Path,
    robot: RobotConfig,
    camera: CameraConfig,
    sim: SimConfig,
    seed: int = 0,
    duration_s: float | None = None,
    frames: int | None = None,
    trajectory: str | Path | None = None,
) -> SimulationPlan:
    """Steps 1-2 and the frame schedule of step 3 (module docstring): the recording but its
    images."""
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
    gps = None
    if world.geo is not None:  # a receiver at robot.gps_x / gps_y (sim.gps_*)
        gps_xy = np.column_stack(antenna_xy(gt_x, gt_y, gt_yaw, (robot.gps_x, robot.gps_y)))
        gps = simulate_gps(gt_t, gps_xy, world.geo, SimGpsConfig.from_sim(sim), seed)

    # 3. Each camera frame is rendered at its true capture time.
    cam_x, cam_y, cam_yaw = traj.interpolate(capture)
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
    return SimulationPlan(
        world=world,
        robot=robot,
        camera=camera,
        sim=sim,
        scene=scene,
        intrinsics=camera_intrinsics(camera),
        stamps_ns=stamps,
        poses=np.column_stack([cam_x, cam_y, cam_yaw]),
        noise_seed=int(rngs["noise_bank"].integers(2**31)),
        render_rng=rngs["render"],
        wheels=(wheel_t, left[phys], right[phys]),
        imu=(imu_t, gyro) if sim.gyro_enabled else None,
        groundtruth=(gt_t, gt_x, gt_y, gt_yaw),
        gps=gps,
        summary=summary,
    )


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
    plan = plan_simulation(world_path, robot, camera, sim, seed, duration_s, frames, trajectory)
    with RecordingWriter(out, plan.intrinsics, plan.scene) as writer:
        for k, frame in enumerate(render_frames(plan)):
            writer.add_frame(frame)
            if progress is not None:
                progress(k + 1, len(plan.stamps_ns))
        plan.write_streams(writer)
    summary = plan.summary
    log.info(
        "simulated %s: %d frames, %.1f m in %.1f s",
        summary.world,
        summary.frames,
        summary.path_length_m,
        summary.duration_s,
    )
    return summary
