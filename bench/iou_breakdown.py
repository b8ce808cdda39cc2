"""Where a simulated run's grid and its floor plan disagree: the IoU's misses by class, a picture.

Run: ``python bench/iou_breakdown.py RUN --world scenes/house.yaml [--png diff.png]`` on the run
directory of ``rgbdnav map`` on a world (or on a recording of one). The grid-vs-floor-plan IoU
(``grid_vs_floor_plan_aligned`` in the run's summary) counts false positives (occupied cells
more than a cell from the plan's observed surfaces) and false negatives (observed surface cells
with no occupied cell within a cell). This splits them:

- false positives by distance to the true surface (<= 2 cells: a wall drawn a little off;
  further: a misplaced wall or clutter);
- false negatives by the grid's state there: never observed (at the edge of what the camera's
  58-degree view swept), observed free (the map has free space where the plan has a wall:
  misregistration), observed but below ``occupied_thresh``;
- the IoU of the same keyframe scans inserted at their TRUE poses: the share of the misses the
  trajectory causes, against what the sensor and the grid model leave;
- the keyframes furthest from the truth (base_link's, from the bundle's scan-frame poses).

The picture (``--png``): green occupied and right, red false positive, blue false negative,
grey the plan, keyframes as dots (orange: more than 5 cm off). North up.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rgbdnav.cache import open_world_or_source  # noqa: E402
from rgbdnav.config import load_config  # noqa: E402
from rgbdnav.runners.map import IOU_TOLERANCE_CELLS, _true_surface, occupancy_iou  # noqa: E402
from sensors.sim.world import floor_plan, load_world  # noqa: E402
from sensors.tum import load_tum_trajectory  # noqa: E402
from slam.config import MapperConfig  # noqa: E402
from slam.depth_to_scan import base_pose, scan_frame_in_base, scan_pose  # noqa: E402
from slam.map_bundle import load_bundle  # noqa: E402
from slam.metrics import align_se2, interpolate_poses  # noqa: E402
from slam.occupancy_grid import integrate_scans  # noqa: E402

OFF_M = 0.05  # [m] a keyframe further than this from the truth is drawn orange


def breakdown(run: Path, world: Path) -> tuple[dict, np.ndarray]:
    bundle = load_bundle(run / "map")
    summary = json.loads((run / "summary.json").read_text())
    # The run's own source (a recording of the world, or the world) holds its ground truth.
    source = Path(summary.get("source", world))
    gt = open_world_or_source(
        source if source.exists() else world, load_config([], []), 0, render_ahead=False
    )
    gt = gt.groundtruth()
    if gt is None:
        raise SystemExit(f"error: {source}: no ground truth")
    # The scorer's SE(2) alignment (world = rot @ map + t), from the trajectory as it does.
    stamps_ns, xyz, _ = load_tum_trajectory(run / "trajectory.tum")
    rx, ry, _, inside = interpolate_poses(gt.stamps_ns, gt.x, gt.y, gt.yaw, stamps_ns)
    rot, t = align_se2(xyz[inside, :2], np.column_stack([rx, ry])[inside])
    th = math.atan2(rot[1, 0], rot[0, 0])
    grid = bundle.grid
    g = grid.geometry
    thresh = bundle.occupied_thresh
    plan = floor_plan(load_world(world))
    mapped = grid.occupied_mask(thresh)
    truth = _true_surface(plan, grid, rot, t)
    ring = np.ones((2 * IOU_TOLERANCE_CELLS + 1,) * 2, np.uint8)
    fp = mapped & ~(cv2.dilate(truth.astype(np.uint8), ring) > 0)
    fn = truth & ~(cv2.dilate(mapped.astype(np.uint8), ring) > 0)
    to_truth = cv2.distanceTransform((~truth).astype(np.uint8), cv2.DIST_L2, 5)[fp]
    lo = grid.log_odds
    # The bundle's keyframe poses and scans are the scan frame's (depth_to_scan.output_frame of
    # the run's config), the truth base_link's: the one conversion between them, both ways.
    cfg_path = run / "config.yaml"
    run_cfg = load_config([cfg_path] if cfg_path.exists() else [], [])
    scan_in_base = scan_frame_in_base(run_cfg.robot, run_cfg.depth_to_scan)
    # The same keyframe scans at their true poses (in the map frame: map = rot^T (world - t)).
    stamps = bundle.keyframe_stamps_ns
    x, y, yaw, _ = interpolate_poses(gt.stamps_ns, gt.x, gt.y, gt.yaw, stamps)
    true_xy = (np.column_stack([x, y]) - t) @ rot
    true_poses = np.column_stack([true_xy, yaw - th])
    cfg = MapperConfig(**{**bundle.config, "occupied_thresh": thresh})
    at_truth = integrate_scans(g, scan_pose(true_poses, scan_in_base), list(bundle.scans), cfg)
    est = base_pose(bundle.keyframe_poses, scan_in_base)
    err = np.hypot(*(est[:, :2] - true_xy).T)
    yaw_err = np.degrees(np.angle(np.exp(1j * (est[:, 2] - true_poses[:, 2]))))
    worst = np.argsort(-err)[:8]
    out = {
        "iou": occupancy_iou(mapped, truth, IOU_TOLERANCE_CELLS),
        "false_positive": {
            "within_2_cells_of_a_true_surface": int((to_truth <= 2.01).sum()),
            "further": int((to_truth > 2.01).sum()),
        },
        "false_negative": {
            "never_observed": int((fn & ~grid.observed).sum()),
            "observed_free": int((fn & grid.observed & (lo < 0)).sum()),
            "observed_below_occupied_thresh": int((fn & grid.observed & (lo >= 0)).sum()),
        },
        "iou_same_scans_at_true_poses": occupancy_iou(
            at_truth.occupied_mask(thresh), _true_surface(plan, at_truth, rot, t), 1
        ),
        "keyframes": len(est),
        "keyframe_error_m": {
            "mean": round(float(err.mean()), 4),
            "max": round(float(err.max()), 4),
        },
        "worst_keyframes": [
            {
                "id": int(i),
                "error_m": round(float(err[i]), 3),
                "yaw_deg": round(float(yaw_err[i]), 2),
            }
            for i in worst
        ],
    }
    # The picture, BGR, north up.
    solid = _true_surface(plan, grid, rot, t) | _solid(plan, g, rot, t)
    img = np.full((*g.shape, 3), 255, np.uint8)
    img[grid.observed] = (235, 235, 235)
    img[solid] = (200, 200, 200)
    img[mapped & ~fp] = (0, 160, 0)
    img[fp] = (0, 0, 255)
    img[fn] = (255, 0, 0)
    r, c = g.world_to_cell(est[:, 0], est[:, 1])
    for rr, cc, e in zip(r, c, err, strict=True):
        cv2.circle(img, (int(cc), int(rr)), 1, (0, 140, 255) if e > OFF_M else (0, 0, 0), -1)
    img = cv2.resize(img[::-1], None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    return out, img


def _solid(plan, g, rot: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The plan's occupied cells in the map's grid."""
    rows, cols = np.nonzero(plan.occupied)
    xy = np.column_stack(
        [
            plan.origin_x + (cols + 0.5) * plan.resolution,
            plan.origin_y + (rows + 0.5) * plan.resolution,
        ]
    )
    r, c = g.world_to_cell(*((xy - t) @ rot).T)
    ok = g.contains(r, c)
    solid = np.zeros(g.shape, bool)
    solid[r[ok], c[ok]] = True
    return solid


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="run directory of `rgbdnav map` on a world")
    ap.add_argument("--world", type=Path, required=True, help="the world YAML it was mapped in")
    ap.add_argument("--png", type=Path, help="write the difference picture here")
    args = ap.parse_args()
    for need in (*(args.run / f for f in ("map", "summary.json", "trajectory.tum")), args.world):
        if not need.exists():
            print(f"error: {need}: not found", file=sys.stderr)
            return 2
    out, img = breakdown(args.run, args.world)
    print(json.dumps(out, indent=1))
    if args.png is not None:
        cv2.imwrite(str(args.png), img)
    return 0


if __name__ == "__main__":
    sys.exit(main())
