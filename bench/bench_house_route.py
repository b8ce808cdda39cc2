"""The shipped house route end to end (what `make demo` runs), split into rendering and mapping.

Run: ``.venv/bin/python bench/bench_house_route.py [--out docs/benchmarks.md] [--world W]``.
Two child processes, as `rgbdnav map scenes/house.yaml` runs them one after the other: ``rgbdnav
simulate`` renders the route into a fresh recording (the render cache's content: its time and
size), then ``rgbdnav map`` maps that recording (front end: PNG decode, VO, depth -> scan, EKF;
then the pose-graph mapper and the grid). The mapping run's summary gives its accuracy (aligned
and start-anchored ATE, the grid's IoU with the floor plan, loop closures) and the split of its
time. This is the full-route check that the test suite runs on a shorter cut of the route
(tests/rgbdnav/test_house_mapping.py); it fails (exit 1) when the route misses those targets.
Results replace the "house_route" section of the output markdown file, stamped with the date,
the machine and its load.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import figure_section, folder_mb, machine, publish, run_cli  # noqa: E402

HOUSE = REPO / "scenes" / "house.yaml"
SECTION = "house_route"
ATE_TARGET_M = 0.05  # [m] issue #6, SE(2)-aligned
IOU_TARGET = 0.9  # [-] grid vs floor plan, aligned, one-cell tolerance


def run(world: Path) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-house-") as tmp:
        rec, out = Path(tmp) / "recording", Path(tmp) / "run"
        load = os.getloadavg()[0]
        render_s = run_cli("simulate", str(world), "--out", str(rec))[0]
        cache_mb = folder_mb(rec)
        map_s = run_cli("map", str(rec), "--out", str(out))[0]
        load = max(load, os.getloadavg()[0])
        s = json.loads((out / "summary.json").read_text())
    return {"render_s": render_s, "cache_mb": cache_mb, "map_s": map_s, "load": load, "s": s}


def _shown(path: Path) -> str:
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def report(world: Path, r: dict) -> str:
    s = r["s"]
    slam, grid = s["slam_vs_groundtruth"], s["grid_vs_floor_plan_aligned"]
    t = s["timings_s"]
    data_s, frames = s["data_duration_s"], s["counts"]["scans"]
    mapper = {k: v for k, v in t.items() if k not in ("mapping_total", "grid_and_bundle", "wall")}
    front_end = t["mapping_total"] - sum(mapper.values())
    total = r["render_s"] + r["map_s"]
    rows = [
        (
            "route",
            f"{world.name}: {frames} frames, {slam['path_length_m']:.1f} m in {data_s:.1f} s",
        ),
        (
            "render (`rgbdnav simulate`)",
            f"{r['render_s']:.1f} s = {frames / r['render_s']:.1f} "
            f"frames/s; recording {r['cache_mb']:.0f} MB ({r['cache_mb'] / frames:.2f} MB/frame)",
        ),
        (
            "map (`rgbdnav map` on the recording)",
            f"{r['map_s']:.1f} s wall, of which the frame "
            f"loop + mapper {t['mapping_total']:.1f} s = **{data_s / t['mapping_total']:.2f}x real "
            f"time**, grid + bundle {t['grid_and_bundle']:.1f} s",
        ),
        ("of the frame loop: front end (decode, VO, depth -> scan, EKF)", f"~{front_end:.1f} s"),
        (
            "of the frame loop: mapper stages [s]",
            ", ".join(f"{k} {v:.1f}" for k, v in mapper.items()),
        ),
        (
            "render share of the world run (render + map)",
            f"{100 * r['render_s'] / total:.0f} % of {total:.0f} s",
        ),
        (
            "ATE RMSE, SE(2)-aligned / start-anchored",
            f"{slam['ate_rmse_aligned_m']:.4f} m / "
            f"{slam['ate_rmse_m']:.4f} m (target <= {ATE_TARGET_M} m aligned)",
        ),
        ("grid vs floor plan IoU (aligned)", f"{grid['iou']:.3f} (target >= {IOU_TARGET})"),
        ("loop closures accepted", str(s["counts"]["loop_closures"]["accepted"])),
        ("peak RSS of the mapping run", f"{s['peak_rss_mb']:.0f} MB"),
    ]
    return figure_section(
        "House route end to end (`make demo`'s run, render vs mapping)",
        [
            f"Measured {dt.date.today()} on {machine('numpy', 'cv2')}; 1-min load average up to "
            f"{r['load']:.1f} during the run.",
            f"Command: `python bench/bench_house_route.py --world {_shown(world)}`.",
        ],
        rows,
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="markdown file whose section to replace")
    ap.add_argument("--world", type=Path, default=HOUSE, help="world YAML (default: the house)")
    args = ap.parse_args()
    world = args.world.resolve()
    r = run(world)
    publish(report(world, r), args.out, SECTION)
    s = r["s"]
    ok = (
        s["slam_vs_groundtruth"]["ate_rmse_aligned_m"] <= ATE_TARGET_M
        and s["grid_vs_floor_plan_aligned"]["iou"] >= IOU_TARGET
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
