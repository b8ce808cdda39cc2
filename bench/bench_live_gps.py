"""Live relocalisation with and without the GPS prior: the simulated robot in the house, not told
its start, localising in a map placed in the world by a fleet file (T_world_map not the identity),
driven by teleop keys (forward, then a turn) so the camera sweeps the living room.

Run: ``python bench/bench_live_gps.py WORK [--runs 3] [--first-seed 0] [--duration 30]``. Per variant (the world
with a geo anchor: the simulated receiver, sigma 3 m, 1 Hz, is the global search's prior; the same
world without one: no GPS) and seed: the seconds from the first scan to the first tracked one, and
whether the last tracked pose, placed by T_world_map, is the truth (within 0.5 m) or a false fix.
Each run is a real-time live run: the figures depend on the machine's load (printed).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "rgbdnav"))

from test_live_gps_fleet import GEO, HOUSE, T_WORLD_MAP, _map_in_its_own_frame  # noqa: E402

from rgbdnav.live.run import LiveOptions, LiveRun  # noqa: E402
from slam.geometry import oplus  # noqa: E402

FALSE_FIX_M = 0.5  # [m] a tracked pose this far from the truth is a false fix
KEYS = "i" * 25 + "j" * 40 + "k"  # 5 s forward, 8 s turning left, stop (0.2 s a key)


def one_run(work: Path, geo: bool, seed: int, duration: float) -> dict:
    name = f"{'gps' if geo else 'nogps'}_{seed}"
    folder = work / name
    folder.mkdir(parents=True, exist_ok=True)
    world = folder / "house.yaml"
    world.write_text(HOUSE.read_text() + (GEO if geo else ""))
    _map_in_its_own_frame(world, folder / "r1.yaml")
    x, y, yaw = T_WORLD_MAP
    (folder / "fleet.yaml").write_text(
        f"robots:\n  - name: r1\n    map: r1.yaml\n    T_world_map: {{x: {x}, y: {y}, yaw: {yaw}}}\n"
    )
    out = folder / "run"
    live = LiveRun(
        LiveOptions(
            out=out,
            world=world,
            fleet=folder / "fleet.yaml",
            robot="r1",
            drive="teleop",
            duration_s=duration,
            seed=seed,
            overrides=["live.sim_initial_pose=false", "sim.camera_rate=10"],
        )
    )

    def press() -> None:
        while live._first_frame_at is None:
            time.sleep(0.1)
        for key in KEYS:
            live.keys.put(key)
            time.sleep(0.2)

    threading.Thread(target=press, daemon=True).start()
    live.execute()
    s = live.summary
    track = np.loadtxt(out / "trajectory.tum", comments="#", ndmin=2)
    truth = np.loadtxt(out / "groundtruth.tum", comments="#", ndmin=2)
    err = None
    if s["seconds_to_first_pose"] is not None and len(track):
        last = track[-1]
        placed = oplus(np.array(T_WORLD_MAP), [last[1], last[2], 0.0])
        k = min(int(np.searchsorted(truth[:, 0], last[0])), len(truth) - 1)
        err = float(math.hypot(*(placed[:2] - truth[k, 1:3])))
    return {
        "variant": "GPS prior" if geo else "no GPS",
        "seed": seed,
        "seconds_to_first_pose": s["seconds_to_first_pose"],
        "last_pose_error_m": None if err is None else round(err, 2),
        "false_fix": err is not None and err > FALSE_FIX_M,
        "scans": s["counts"].get("scans_mapped", 0),
        "load": round(os.getloadavg()[0], 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=30.0)
    args = ap.parse_args()
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.runs):
        for geo in (True, False):
            rows.append(one_run(args.work, geo, seed, args.duration))
            print(json.dumps(rows[-1]), flush=True)
    print("\n| variant | seed | time to fix [s] | last pose error [m] | false fix | scans | load |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['variant']} | {r['seed']} | {r['seconds_to_first_pose']} | "
            f"{r['last_pose_error_m']} | {r['false_fix']} | {r['scans']} | {r['load']} |"
        )


if __name__ == "__main__":
    main()
