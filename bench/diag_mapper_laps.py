"""How much of the live soak's memory growth is the mapper's? (issue 27 target 5)

Run: ``.venv/bin/python bench/diag_mapper_laps.py [--laps 12] [--trace]``.

The live soak (``bench/bench_live_soak.py``) drives the house route again and again while
mapping and measures the whole live process. This drives the same route through the live
profile's :class:`slam.mapper.Mapper` alone, with no rendering, VO or navigation: scans cast in
the house's floor plan (``sensors.sim.scan.cast_scan``: 320 beams over a depth camera's 58 deg,
0.45-5 m, 1 cm noise) at 30 Hz along the route, odometry 2 % long with a heading drift, lap after
lap (each lap starts where the route does: a 4.5 m jump, as if the robot were carried back).
Per lap: the process's resident memory, the lap's CPU, keyframes and accepted loop closures.
``--trace`` starts tracemalloc (6 frames) after lap 1 and prints the largest growth by
traceback at the end: ~10x slower.
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rgbdnav.config import load_config  # noqa: E402
from sensors.sim.motion import drive_route  # noqa: E402
from sensors.sim.scan import cast_scan  # noqa: E402
from sensors.sim.world import floor_plan, world_from_dict  # noqa: E402
from sensors.types import LaserScan  # noqa: E402
from slam.geometry import ominus, oplus  # noqa: E402
from slam.mapper import Mapper  # noqa: E402

PROFILES = [REPO / "config/profiles/rgbd_mapping.yaml", REPO / "config/profiles/live.yaml"]
PERIOD_NS = 33_333_333  # 30 Hz
FOV = math.radians(58.0)
BEAMS = 320
RANGE = (0.45, 5.0)  # [m]


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--laps", type=int, default=12)
    ap.add_argument("--world", type=Path, default=REPO / "scenes" / "house.yaml")
    ap.add_argument("--trace", action="store_true", help="tracemalloc after lap 1")
    args = ap.parse_args()
    cfg = load_config(PROFILES, [])
    world = world_from_dict(yaml.safe_load(args.world.read_text()))
    plan = floor_plan(world)
    traj = drive_route(world, cfg.sim)
    x, y, yaw = traj.interpolate(np.arange(0, traj.t_ns[-1], PERIOD_NS))
    angles = np.linspace(-FOV / 2, FOV / 2, BEAMS)
    print(f"lap: {len(x)} scans, {traj.length_m():.1f} m, {traj.duration_s:.0f} s of driving")
    rng = np.random.default_rng(0)
    mapper = Mapper(cfg.mapper)
    odom = prev = np.array([x[0], y[0], yaw[0]])
    stamp = 0
    snap0 = None
    for lap in range(args.laps):
        t0 = time.process_time()
        for k in range(len(x)):
            truth = np.array([x[k], y[k], yaw[k]])
            step, prev = ominus(prev, truth), truth
            odom = oplus(odom, step * [1.02, 1.0, 1.0] + [0.0, 0.0, 0.002 * abs(step[0])])
            r = cast_scan(plan, truth, angles, *RANGE)
            r = np.where(np.isfinite(r), r + rng.normal(0.0, 0.01, r.shape), r)
            stamp += PERIOD_NS
            scan = LaserScan(
                stamp, float(angles[0]), float(angles[1] - angles[0]), r.astype(np.float32), *RANGE
            )
            mapper.add_scan(scan, odom)
        gc.collect()
        print(
            f"lap {lap + 1}: RSS {rss_mb():.1f} MB, CPU {time.process_time() - t0:.1f} s, "
            f"keyframes {len(mapper.keyframes)}, loop closures {len(mapper.loop_edges)}",
            flush=True,
        )
        if args.trace and snap0 is None:
            tracemalloc.start(6)
            snap0 = tracemalloc.take_snapshot()
    if snap0 is not None:
        for st in tracemalloc.take_snapshot().compare_to(snap0, "traceback")[:12]:
            print(f"{st.size_diff / 1e6:+.2f} MB in {st.count_diff:+d} blocks")
            print("    " + "\n    ".join(st.traceback.format()[-6:]))


if __name__ == "__main__":
    main()
