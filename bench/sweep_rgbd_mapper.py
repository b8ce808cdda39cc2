"""Mapper settings on an RGB-D recording, with the front end held fixed: ATE and grid IoU.

Run: ``.venv/bin/python bench/sweep_rgbd_mapper.py RUN_DIR [--set KEY=VALUE ...] ...``

``RUN_DIR`` is a run of ``rgbdnav map`` on a recording (``runs/demo`` after ``make demo``): its
``odom.tum`` (the front end's fused odometry) is the odometry and its ``summary.json`` names the recording. The depth
frames are turned into scans once; each variant then runs only the mapper (seconds, not the
minutes visual odometry takes), builds the grid and is scored as ``rgbdnav map`` scores it
(SLAM ATE against ground truth, occupied-cell IoU against the floor plan). A variant is one
``--set`` group: ``--set mapper.scan_match_min_sigma=0.2 --set mapper.scan_match_min_sigma=0.4``
runs two variants; several overrides in one group are separated by commas. Without ``--set``
the defaults (with ``config/profiles/rgbd_mapping.yaml``) are scored.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rgbdnav.runners.map import _score_against_truth  # noqa: E402
from rgbdnav.scan_stream import source_config  # noqa: E402
from sensors.source import open_source  # noqa: E402
from sensors.tum import load_tum_trajectory, yaw_from_quaternion  # noqa: E402
from slam.depth_to_scan import DepthToScan  # noqa: E402
from slam.mapper import Mapper, build_grid  # noqa: E402
from slam.metrics import interpolate_poses  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("run", type=Path, help="an rgbdnav map run directory of a recording")
    ap.add_argument(
        "--set",
        dest="variants",
        action="append",
        default=[],
        help="one variant: comma-separated KEY=VALUE overrides (repeatable)",
    )
    args = ap.parse_args()
    summary_path, fused_path = args.run / "summary.json", args.run / "odom.tum"
    if not summary_path.is_file() or not fused_path.is_file():
        sys.exit(
            f"{args.run}: not an rgbdnav map run of a recording (needs summary.json and odom.tum)"
        )
    src = open_source(Path(json.loads(summary_path.read_text())["source"]), {})
    # 1. Scans once (the depth -> scan settings are not swept), odometry at their stamps.
    _, _, cfg = source_config(src, [], [])
    intrinsics = src.intrinsics()
    if intrinsics is None or src.groundtruth() is None:
        sys.exit(f"{args.run}: its source has no depth camera or no ground truth")
    d2s = DepthToScan(intrinsics, cfg.robot, cfg.depth_to_scan)
    scans = [d2s.from_frame(f).scan for f in src.frames()]
    stamps, xyz, quat = load_tum_trajectory(fused_path)
    ox, oy, oyaw, inside = interpolate_poses(
        stamps,
        xyz[:, 0],
        xyz[:, 1],
        yaw_from_quaternion(quat),
        np.array([s.stamp_ns for s in scans]),
    )
    print(f"{len(scans)} scans, {int(inside.sum())} with odometry ({fused_path})")
    # 2. The mapper per variant.
    for variant in args.variants or [""]:
        overrides = [o for o in variant.split(",") if o]
        scene, _, vcfg = source_config(src, [], overrides)
        mapper = Mapper(vcfg.mapper)
        t0 = time.perf_counter()
        for k in np.flatnonzero(inside):
            mapper.add_scan(scans[k], np.array([ox[k], oy[k], oyaw[k]]))
        result = mapper.finish()
        wall = time.perf_counter() - t0
        summary: dict = {}
        _score_against_truth(
            result, build_grid(result, vcfg.mapper), src.groundtruth(), scene, vcfg, summary
        )
        ate, iou = summary["slam_vs_groundtruth"], summary.get("grid_vs_floor_plan", {})
        loops = result.counts["loop_closures"]
        print(
            f"{variant or 'defaults'}: ATE {ate['ate_rmse_m']:.4f} m "
            f"(aligned {ate['ate_rmse_aligned_m']:.4f}), grid IoU {iou.get('iou', 'n/a')}, "
            f"{len(result.keyframes)} keyframes, loops {loops['accepted']}/{loops['proposed']}, "
            f"mapper {wall:.1f} s"
        )
    src.close()


if __name__ == "__main__":
    main()
