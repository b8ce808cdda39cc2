"""How each collision of a navigation scenario run happens: the motion, the side, the estimate
against the truth, and whether the camera had seen the wall it grazes.

``python bench/diag_nav_collisions.py --scenario scenes/scenarios/nav_house.yaml --map floorplan
--scenario-seed 2`` drives the scenario as ``bench_nav.py`` does (localiser) and prints, for every
step whose true footprint overlaps the world, the navigator's status, the command, the true and
estimated pose, the bearing of the nearest occupied cell in the true base_link, and the nearest
point the camera's last ``--memory`` seconds of scans left (carried by wheel odometry, as the
collision monitor keeps them) to that wall cell. Findings are in docs/design/navigator.md.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import rgbdnav.runners.navigate as navigate_runner  # noqa: E402
from nav.collision_monitor import ObstacleMemory  # noqa: E402
from slam.geometry import ominus, oplus, wrap_angle  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenario", type=Path, default=REPO / "scenes/scenarios/nav_house.yaml")
    ap.add_argument("--map", default="floorplan", help="'floorplan' or a map directory")
    ap.add_argument("--scenario-seed", type=int, default=2)
    ap.add_argument("--goals", type=int)
    ap.add_argument("--memory", type=float, default=2.0, help="[s] scans remembered")
    ap.add_argument("--set", action="append", default=[], help="extra config overrides")
    args = ap.parse_args()

    from nav_scenario import floor_plan_map, load_scenario, run_scenario  # bench/

    base = navigate_runner._Sim
    events: list[dict] = []

    class Traced(base):  # type: ignore[misc, valid-type]
        def __init__(self, *a, **k):  # noqa: ANN002, ANN003
            super().__init__(*a, **k)
            self.memory = ObstacleMemory(args.memory)
            self.diag_hit = False
            self.seen: list[tuple[int, np.ndarray]] = []
            occ = np.argwhere(self.plan.occupied)
            self.occ_xy = np.column_stack(
                [
                    self.plan.origin_x + (occ[:, 1] + 0.5) * self.plan.resolution,
                    self.plan.origin_y + (occ[:, 0] + 0.5) * self.plan.resolution,
                ]
            )

        def localize(self, scan):  # noqa: ANN001, ANN202
            super().localize(scan)
            r = np.asarray(scan.ranges, dtype=np.float64)
            a = scan.angle_min + scan.angle_increment * np.arange(len(r))
            ok = np.isfinite(r)
            pts_laser = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])
            pts_base = oplus(
                self.scan_in_base, np.column_stack([pts_laser, np.zeros(len(pts_laser))])
            )
            self.memory.add(scan.stamp_ns, self.odometry.pose, pts_base[:, :2])
            self.seen.append((scan.stamp_ns, oplus(self.pose, pts_base)[:, :2]))

        def step(self, goal, status=None, hold=None):  # noqa: ANN001, ANN202
            before = self.collision_events
            super().step(goal, status, hold)
            hit = self.in_collision
            if hit and (self.collision_events > before or not self.diag_hit):
                self._dump(goal)
            self.diag_hit = hit

        def _dump(self, goal: int) -> None:
            truth, est = self.pose, self.estimate
            d = np.hypot(*(self.occ_xy - truth[:2]).T)
            k = int(np.argmin(d))
            wall = self.occ_xy[k]
            rel = ominus(truth, np.array([[wall[0], wall[1], 0.0]]))[0]
            mem = self.memory.points_in_base(self.odometry.pose)
            # The wall cell as the odometry frame sees it (truth -> base -> odom-carried points).
            gap = np.hypot(*(mem - rel[:2]).T).min() if len(mem) else math.inf
            err = est - truth
            last_seen = None
            for stamp, pts in reversed(self.seen):
                near = np.hypot(*(pts - wall).T)
                if len(near) and near.min() < 0.1:
                    last_seen = round((self.t_ns - stamp) / 1e9, 2)
                    break
            row = self.log.rows[-1]
            events.append(
                dict(
                    t=row[0],
                    goal=goal,
                    status=row[2],
                    cmd=(round(row[3], 3), round(row[4], 3)),
                    vel=(round(row[5], 3), round(row[6], 3)),
                    truth=np.round(truth, 3).tolist(),
                    estimate=np.round(est, 3).tolist(),
                    err_xy_m=round(float(np.hypot(*err[:2])), 3),
                    err_yaw_deg=round(math.degrees(float(wrap_angle(err[2]))), 1),
                    wall_in_base=np.round(rel[:2], 3).tolist(),
                    wall_bearing_deg=round(math.degrees(math.atan2(rel[1], rel[0])), 0),
                    overlap_m=round(self.radius - float(d[k]) + self.plan.resolution / 2, 3),
                    memory_points=len(mem),
                    memory_nearest_to_wall_m=round(float(gap), 3),
                    wall_last_seen_s_ago=last_seen,
                    est_cost=int(self.costmap.cost_at(est[0], est[1])),
                )
            )

    navigate_runner._Sim = Traced
    sc = load_scenario(args.scenario)
    if args.map == "floorplan":
        d = REPO / "runs" / "nav_scenario_maps" / f"floorplan_{args.scenario.stem}"
        d.mkdir(parents=True, exist_ok=True)
        map_path = floor_plan_map(sc, d / "map.yaml")
    else:
        map_path = Path(args.map)
    out = REPO / "runs" / f"diag_nav_{Path(args.map).name}_seed{args.scenario_seed}"
    _, summary = run_scenario(
        args.scenario,
        map_path,
        out,
        args.goals,
        localization="localizer",
        seed=args.scenario_seed,
        overrides=args.set,
    )
    print("collisions:", summary["collisions"], "recoveries:", summary["recoveries"])
    print(
        "reached:",
        summary["scenario"]["reached_within_tolerance"],
        "/",
        summary["scenario"]["goals"],
    )
    for e in events:
        print(e)
    print(f"run directory: {out}")


if __name__ == "__main__":
    main()
