"""Depth -> scan cost per 640x480 frame on noisy Kinect frames rendered from a shipped world.

Run: ``.venv/bin/python bench/bench_depth_to_scan.py [--out docs/benchmarks.md]``. Frames are
rendered once up front; only the conversion is timed. Results replace the "depth_to_scan"
section of the output markdown file, stamped with date and machine.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import machine, publish  # noqa: E402  (bench/ is on sys.path)

from sensors.config import CameraConfig, RobotConfig, SimConfig  # noqa: E402
from sensors.sim.motion import drive_route  # noqa: E402
from sensors.sim.render import KinectRenderer  # noqa: E402
from sensors.sim.world import load_world  # noqa: E402
from sensors.types import CameraIntrinsics  # noqa: E402
from slam.config import DepthToScanConfig  # noqa: E402
from slam.depth_to_scan import DepthToScan  # noqa: E402

TARGET_MS = 2.0  # [ms/frame] on 2 cores
SECTION = "depth_to_scan"


def render_frames(world_path: Path, frames: int, robot: RobotConfig) -> list[np.ndarray]:
    world = load_world(world_path)
    sim = SimConfig()
    traj = drive_route(world, sim)
    idx = np.linspace(0, len(traj.t_ns) - 1, frames).round().astype(int)
    renderer = KinectRenderer(world, CameraConfig(), robot, sim, backend="raster")
    rng = np.random.default_rng(0)
    return [
        renderer.render(float(traj.x[i]), float(traj.y[i]), float(traj.yaw[i]), rng)[1] for i in idx
    ]


def time_conversion(conv: DepthToScan, depths: list[np.ndarray]) -> dict[str, float]:
    conv(depths[0])  # warm-up
    times, kept, valid = [], [], []
    for d in depths:
        t0 = time.perf_counter()
        out = conv(d)
        times.append(time.perf_counter() - t0)
        kept.append(out.in_band_points)
        valid.append(out.valid_pixels)
    ms = 1e3 * np.array(times)
    return {
        "median": float(np.median(ms)),
        "p95": float(np.percentile(ms, 95)),
        "valid": float(np.mean(valid)),
        "kept": float(np.mean(kept)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--world", type=Path, default=REPO / "scenes" / "house.yaml")
    ap.add_argument("--frames", type=int, default=200, help="frames rendered and converted")
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    args = ap.parse_args()

    cam = CameraConfig()
    k = CameraIntrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale)
    robot, tilted = RobotConfig(), RobotConfig(camera_pitch=0.35)
    ahead = RobotConfig(camera_x=0.15)
    cfg = DepthToScanConfig()
    averaged = DepthToScanConfig(return_averaging_window=0.01)
    depths = render_frames(args.world, args.frames, robot)
    rows = {
        "sorted + reduceat (default)": time_conversion(DepthToScan(k, robot, cfg), depths),
        "np.minimum.at (reference)": time_conversion(
            DepthToScan(k, robot, cfg, reduction="minimum_at"), depths
        ),
        "sorted, camera pitched 0.35 rad": time_conversion(DepthToScan(k, tilted, cfg), depths),
        "general path, camera 0.15 m ahead of the axle": time_conversion(
            DepthToScan(k, ahead, cfg), depths
        ),
        "sorted, near-cluster averaging 0.01 /m (the rgbd_mapping and live profiles)": time_conversion(
            DepthToScan(k, robot, averaged), depths
        ),
        "np.minimum.at + bincount averaging (reference)": time_conversion(
            DepthToScan(k, robot, averaged, reduction="minimum_at"), depths
        ),
        "sorted, scan_height 10 (upstream-like band)": time_conversion(
            DepthToScan(k, robot, DepthToScanConfig(scan_height=10)), depths
        ),
    }
    lines = "\n".join(
        f"| {name} | {r['median']:.2f} | {r['p95']:.2f} | {r['valid']:.0f} | {r['kept']:.0f} |"
        for name, r in rows.items()
    )
    best = rows["sorted + reduceat (default)"]["median"]
    verdict = "meets" if best <= TARGET_MS else "misses"
    body = f"""## Depth -> scan ({args.world.name}, 640x480, noisy Kinect depth)

Measured {dt.date.today().isoformat()} on {machine("numpy")}.
Command: `python bench/bench_depth_to_scan.py --frames {args.frames}`; {args.frames} frames rendered
once up front, conversion timed alone. Default config: {cfg.angle_increment:.4f} rad beams,
height band [{cfg.min_height}, {cfg.max_height}] m, range [{cfg.range_min}, {cfg.range_max}] m.
The default path {verdict} the {TARGET_MS:.0f} ms/frame target. Frames rendered with the level
camera are reused for the other mountings (only the cost matters there). Variants run one after
the other; this machine's speed drifts by up to 2x over minutes, so compare rows of one run.

| variant | median [ms/frame] | p95 [ms/frame] | valid pixels | points kept |
| --- | --- | --- | --- | --- |
{lines}
"""
    publish(body, args.out, SECTION)


if __name__ == "__main__":
    main()
