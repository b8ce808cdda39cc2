"""GPS as a prior for global relocalisation: time to fix and false fixes, with and without it.

Run: ``python bench/bench_gps_prior.py [--log aces] [--starts 30] [--sigma 3.0]``. As in
``bench_localization.py`` (same map from every 2nd scan of a Radish log's corrected poses, same
corrupted odometry, same success rule: 0.2 m and 5 deg): from seeded random start scans a fresh
``Localizer`` without an initial pose is fed scans until it reports ``tracking``. With the prior,
a simulated receiver (sensors/gps.py: sigma, 1 Hz, burst dropouts) rides the corrected path
through an arbitrary geo anchor, and the latest fix before each scan is handed to
``Localizer.set_gps_fix``. Counted: fixes, false fixes (tracking at a wrong pose), misses, scans
and wall seconds to the fix. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from bench_localization import (  # noqa: E402  (bench/ is on sys.path)
    MAX_RELOC_SCANS,
    RADISH,
    SUCCESS_M,
    SUCCESS_RAD,
    _build_map,
    pose_errors,
    radish_case,
)

from sensors.geo import GeoAnchor  # noqa: E402
from sensors.gps import SimGpsConfig, simulate_gps  # noqa: E402
from slam.config import LocalizerConfig  # noqa: E402
from slam.localization import Localizer  # noqa: E402

ANCHOR = GeoAnchor(44.98, -93.27, 256.0, 0.0)  # the world file
GPS_SEED = 0
STARTS_SEED = 0


def run(name: str, starts: int, sigma: float) -> list[str]:
    _, scans, truth, odom = radish_case(name)
    stamps = np.array([s.stamp_ns for s in scans], np.int64)
    model = _build_map(scans, truth)
    cfg = LocalizerConfig()
    gps = simulate_gps(stamps, truth[:, :2], ANCHOR, SimGpsConfig(sigma_m=sigma), GPS_SEED)
    gps_xy = gps.in_map(ANCHOR)
    latest = np.searchsorted(gps.stamps_ns, stamps, side="right") - 1  # fix per scan (-1: none)
    rng = np.random.default_rng(STARTS_SEED)
    chosen = rng.choice(len(scans) - MAX_RELOC_SCANS, starts, replace=False)
    rows = []
    for label, use_gps in (("without GPS", False), (f"GPS prior, sigma {sigma:g} m", True)):
        ok = wrong = miss = 0
        secs: list[float] = []
        n_scans: list[int] = []
        for s in chosen:
            loc = Localizer(model, cfg)
            t0 = time.perf_counter()
            fix_k = -1
            for i in range(s, s + MAX_RELOC_SCANS):
                if use_gps and latest[i] > fix_k:  # a new fix, at the odometry of its time
                    fix_k = latest[i]
                    at = max(int(np.searchsorted(stamps, gps.stamps_ns[fix_k], "right")) - 1, 0)
                    loc.set_gps_fix(gps_xy[fix_k], float(gps.sigma_m[fix_k]), odom[at])
                r = loc.update(scans[i], odom[i])
                if r.status == "tracking":
                    secs.append(time.perf_counter() - t0)
                    n_scans.append(i - s + 1)
                    d, a = pose_errors(r.pose[None], truth[i][None])[0]
                    ok, wrong = (
                        (ok + 1, wrong) if d <= SUCCESS_M and a <= SUCCESS_RAD else (ok, wrong + 1)
                    )
                    break
            else:
                miss += 1
        med = f"{np.median(n_scans):.0f} / {np.median(secs):.2f}" if secs else "-"
        rows.append(
            f"| {name} | {label} | {len(chosen)} | {ok} | {wrong} | {miss} | {med} | "
            f"{(np.max(secs) if secs else 0):.2f} |"
        )
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--log", default="aces", choices=sorted(RADISH))
    p.add_argument("--starts", type=int, default=30)
    p.add_argument("--sigma", type=float, default=3.0)
    args = p.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}")
    print(
        "| log | prior | starts | fixed right | false fixes | misses | "
        "median scans / s to fix | max s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(run(args.log, args.starts, args.sigma)))


if __name__ == "__main__":
    main()
