"""`make demo`'s command, `rgbdnav map WORLD`, with the world rendered on demand vs through a
recording on disk, back to back.

Run: ``.venv/bin/python bench/bench_demo.py [--out docs/benchmarks.md] [--world W] [--cut N]``.
Two ways to the same map, each in child processes timed with their CPU time (user + system,
children included: the renderer process too), so a loaded machine shows in the wall time but
much less in the CPU time:
1. through a recording, as `rgbdnav map WORLD` ran before issue 27: ``rgbdnav simulate`` renders
   the route into a fresh recording (its size is what the render cache held), ``rgbdnav map``
   maps it (PNG decode ahead on two threads);
2. ``rgbdnav map WORLD``: frames rendered in a second process straight into the front end.
The two runs' trajectories, odometry and grids must be identical (exit 1 otherwise): the frames
are bit for bit the same. ``--cut N`` keeps the first N waypoints of the world's route, for a
shorter run. Results replace the "demo" section of the output markdown file.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import tempfile
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import figure_section, folder_mb, machine, publish, run_cli  # noqa: E402

HOUSE = REPO / "scenes" / "house.yaml"
SECTION = "demo"
SAME_FILES = ("trajectory.tum", "odom.tum", "map/map.pgm", "map/grid.npz")


def run(world: Path, tmp: Path) -> dict:
    rec, via_disk, direct = tmp / "recording", tmp / "via_disk", tmp / "direct"
    load = [os.getloadavg()[0]]
    render = run_cli("simulate", str(world), "--out", str(rec))
    cache_mb = folder_mb(rec)
    mapped = run_cli("map", str(rec), "--out", str(via_disk))
    load.append(os.getloadavg()[0])
    streamed = run_cli("map", str(world), "--out", str(direct))
    load.append(os.getloadavg()[0])
    same = all((via_disk / f).read_bytes() == (direct / f).read_bytes() for f in SAME_FILES)
    s = json.loads((direct / "summary.json").read_text())
    return {
        "render": render,
        "map": mapped,
        "direct": streamed,
        "cache_mb": cache_mb,
        "same": same,
        "load": (min(load), max(load)),
        "s": s,
    }


def report(world: Path, cut: int | None, r: dict) -> str:
    s = r["s"]
    slam, grid = s["slam_vs_groundtruth"], s["grid_vs_floor_plan_aligned"]
    data_s, frames = s["data_duration_s"], s["counts"]["scans"]
    old_wall = r["render"][0] + r["map"][0]
    old_cpu = r["render"][1] + r["map"][1]
    new_wall, new_cpu = r["direct"]
    rows = [
        (
            "route",
            f"{world.name}: {frames} frames, {slam['path_length_m']:.1f} m in {data_s:.1f} s",
        ),
        (
            "through a recording (simulate + map)",
            f"{old_wall:.1f} s wall ({r['render'][0]:.1f} + {r['map'][0]:.1f}), "
            f"{old_cpu:.1f} s CPU; recording {r['cache_mb']:.0f} MB",
        ),
        ("`rgbdnav map WORLD` (rendered on demand)", f"{new_wall:.1f} s wall, {new_cpu:.1f} s CPU"),
        (
            "speed-up, wall / CPU",
            f"**{old_wall / new_wall:.2f}x** / {old_cpu / new_cpu:.2f}x; "
            f"{data_s / new_wall:.2f}x real time end to end",
        ),
        ("trajectory, odometry, grid identical", "yes" if r["same"] else "**NO**"),
        (
            "ATE aligned / start-anchored, IoU",
            f"{slam['ate_rmse_aligned_m']:.4f} m / {slam['ate_rmse_m']:.4f} m, {grid['iou']:.3f}",
        ),
    ]
    shown = world.relative_to(REPO) if world.is_relative_to(REPO) else world
    cut_arg = f" --cut {cut}" if cut else ""
    return figure_section(
        "`make demo`'s command: world rendered on demand vs through a recording (issue 27)",
        [
            f"Measured {dt.date.today()} on {machine('numpy', 'cv2')}; 1-min load average "
            f"{r['load'][0]:.1f}-{r['load'][1]:.1f} during the runs (wall times scale with it; "
            "CPU times much less).",
            f"Command: `python bench/bench_demo.py --world {shown}{cut_arg}`.",
        ],
        rows,
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="markdown file whose section to replace")
    ap.add_argument("--world", type=Path, default=HOUSE, help="world YAML (default: the house)")
    ap.add_argument("--cut", type=int, help="keep only the route's first N waypoints")
    args = ap.parse_args()
    world = args.world.resolve()
    with tempfile.TemporaryDirectory(prefix="bench-demo-") as tmp:
        path = world
        if args.cut:
            w = yaml.safe_load(world.read_text())
            w["route"] = w["route"][: args.cut]
            path = Path(tmp) / f"{world.stem}_cut{args.cut}.yaml"
            path.write_text(yaml.safe_dump(w))
        r = run(path, Path(tmp))
    publish(report(world, args.cut, r), args.out, SECTION)
    return 0 if r["same"] else 1


if __name__ == "__main__":
    sys.exit(main())
