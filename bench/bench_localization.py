"""Localisation against a saved map on the three Radish logs: tracking and global relocalisation.

Run: ``.venv/bin/python bench/bench_localization.py [--out docs/benchmarks.md] [--only aces ...]
[--starts 50]``. Each log runs in a fresh process (so its peak RSS is its own) with the default
:class:`slam.config.LocalizerConfig`:

1. **Map**: an occupancy grid (``MapperConfig`` defaults, 0.05 m) from the log's SLAM-corrected
   poses and every 2nd scan; the other scans are never in the map.
2. **Tracking**: every scan, from the true first pose, with fake odometry made from the corrected
   poses (seeded: +3 % scale, 1 deg/m yaw bias, Gaussian noise per step). Position and heading
   errors of the tracked poses against the corrected poses; scans per second of ``update``.
3. **Global relocalisation**: from ``--starts`` random scans (seeded), a fresh ``Localizer``
   without an initial pose is fed the following scans (at most ``MAX_RELOC_SCANS``) until it
   reports ``tracking``. Success: within 0.2 m and 5 deg of the corrected pose; a tracked pose
   farther off is a false positive (confident and wrong); no fix within the scans is a miss.
   Seconds per relocalisation: wall time of the ``update`` calls from the start scan to the fix.

Results replace the "localization" section of the output markdown file, stamped with date and
machine.
"""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import multiprocessing as mp
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_mapper import corrupt_trajectory  # noqa: E402  (bench/ is on sys.path)
from common import machine, publish  # noqa: E402

DATA = REPO.parent / "shared" / "data"
RADISH = {
    name: DATA / "radish" / f"{name}-corrected.log.gz" for name in ("aces", "orebro", "seattle")
}
SECTION = "localization"

MAP_EVERY = 2  # [scans] the map is built from every 2nd scan
MAP_RESOLUTION = 0.05  # [m/cell]
MAP_MARGIN = 1.0  # [m]
# Fake odometry (applied to each step of the corrected trajectory).
ODOM_SCALE_ERROR = 0.03  # [-] translation scale error (+3 %)
ODOM_YAW_BIAS = np.radians(1.0)  # [rad/m] yaw drift per metre travelled
ODOM_SIGMA_XY = 0.01  # [m] per step, each axis
ODOM_SIGMA_YAW = np.radians(0.2)  # [rad] per step
ODOM_SEED = 0
# Global relocalisation.
STARTS = 50  # random start scans per log
STARTS_SEED = 0
MAX_RELOC_SCANS = 15  # [scans] fed from a start before it counts as a miss (~1 scan/m)
RELOC_BUDGET_S = 300.0  # [s] per log: stop drawing starts after this (the table says)
SUCCESS_M = 0.2  # [m]
SUCCESS_RAD = np.radians(5.0)  # [rad]


# 1. Pure kernels ---------------------------------------------------------------------------------


def pose_errors(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(N, 2) position [m] and absolute heading [rad] errors of (N, 3) poses."""
    d = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
    a = np.abs(np.angle(np.exp(1j * (est[:, 2] - ref[:, 2]))))
    return np.column_stack([d, a])


def percentiles(values: np.ndarray) -> tuple[float, float]:
    """(median, p95); NaN for no values."""
    if len(values) == 0:
        return float("nan"), float("nan")
    return float(np.median(values)), float(np.percentile(values, 95))


# 2. One log, in a child process ------------------------------------------------------------------


@dataclass(frozen=True)
class CaseSpec:
    name: str
    starts: int = STARTS


def _build_map(scans: list[Any], poses: np.ndarray) -> Any:
    from slam.config import LocalizerConfig, MapperConfig
    from slam.localization import MapModel
    from slam.occupancy_grid import GridGeometry, bounds_of_scans, integrate_scans

    mc = MapperConfig()
    sel = slice(0, None, MAP_EVERY)
    bounds = bounds_of_scans(poses[sel], scans[sel], mc.max_laser_range)
    geom = GridGeometry.from_bounds(*bounds, resolution=MAP_RESOLUTION, margin=MAP_MARGIN)
    grid = integrate_scans(geom, poses[sel], scans[sel], mc)
    return MapModel.from_grid(grid, LocalizerConfig(), mc.occupied_thresh, mc.free_thresh)


def run_case(spec: CaseSpec) -> dict[str, Any]:
    from sensors.carmen import CarmenSource
    from slam.config import LocalizerConfig
    from slam.localization import Localizer

    logging.getLogger("sensors.carmen").setLevel(logging.ERROR)  # Radish ODOM stamps are all 0
    logging.getLogger("slam.localization").setLevel(logging.WARNING)
    src = CarmenSource(RADISH[spec.name])
    scans = list(src.scans())
    stream = src.laser_poses()
    assert stream is not None
    truth = np.column_stack([stream.x, stream.y, stream.yaw])
    odom = corrupt_trajectory(truth, ODOM_SCALE_ERROR, ODOM_YAW_BIAS, ODOM_SIGMA_XY,
                              ODOM_SIGMA_YAW, np.random.default_rng(ODOM_SEED))  # fmt: skip
    cfg = LocalizerConfig()
    t0 = time.perf_counter()
    model = _build_map(scans, truth)
    g = model.grid.geometry
    out: dict[str, Any] = {
        "name": spec.name, "scans": len(scans), "stamp_source": src.log.stamp_source,
        "path_m": float(np.hypot(*np.diff(truth[:, :2], axis=0).T).sum()),
        "map_s": time.perf_counter() - t0,
        "map_size_m": (g.width * g.resolution, g.height * g.resolution),
    }  # fmt: skip
    # 1. Tracking from the true first pose.
    loc = Localizer(model, cfg, initial_pose=truth[0])
    t0 = time.perf_counter()
    results = [loc.update(s, o) for s, o in zip(scans, odom, strict=True)]
    track_s = time.perf_counter() - t0
    tracked = np.array([r.status == "tracking" for r in results])
    est = np.array([r.pose for r in results])
    err = pose_errors(est[tracked], truth[tracked])
    odo_err = pose_errors(odom, truth)
    out["tracking"] = {
        "tracked": int(tracked.sum()), "lost": loc.stats.lost,
        "relocalisations": loc.stats.relocalisations,
        "pos": percentiles(err[:, 0]), "yaw_deg": percentiles(np.degrees(err[:, 1])),
        "unseen_pos": percentiles(pose_errors(est[1::2][tracked[1::2]],
                                              truth[1::2][tracked[1::2]])[:, 0]),
        "odom_pos": percentiles(odo_err[:, 0]), "odom_final_m": float(odo_err[-1, 0]),
        "scans_per_s": len(scans) / track_s,
    }  # fmt: skip
    # 2. Global relocalisation from random starts, within a time budget.
    rng = np.random.default_rng(STARTS_SEED)
    starts = rng.choice(len(scans) - MAX_RELOC_SCANS, spec.starts, replace=False)
    ok = wrong = miss = 0
    fix_s: list[float] = []
    fix_scans: list[int] = []
    wrong_err: list[tuple[float, float]] = []
    t_all = time.perf_counter()
    done = 0
    for s in starts:
        if time.perf_counter() - t_all > RELOC_BUDGET_S:
            break
        done += 1
        loc = Localizer(model, cfg)
        t0 = time.perf_counter()
        for i in range(s, s + MAX_RELOC_SCANS):
            r = loc.update(scans[i], odom[i])
            if r.status == "tracking":
                fix_s.append(time.perf_counter() - t0)
                fix_scans.append(i - s + 1)
                d, a = pose_errors(r.pose[None], truth[i][None])[0]
                if d <= SUCCESS_M and a <= SUCCESS_RAD:
                    ok += 1
                else:
                    wrong += 1
                    wrong_err.append((float(d), float(np.degrees(a))))
                break
        else:
            miss += 1
    out["reloc"] = {
        "starts": done, "planned": spec.starts, "ok": ok, "wrong": wrong, "miss": miss,
        "wrong_err": wrong_err, "seconds": fix_s, "scans": fix_scans,
        "wall_s": time.perf_counter() - t_all,
    }  # fmt: skip
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # [MiB]
    return out


def in_fresh_process(spec: CaseSpec) -> dict[str, Any]:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(run_case, (spec,))


# 3. Report -------------------------------------------------------------------------------------


def tracking_table(runs: list[dict[str, Any]]) -> str:
    rows = [
        "| log | scans | path [m] | tracked | lost / relocalised | position median / p95 [m] "
        "| heading median / p95 [deg] | unseen scans: position median / p95 [m] "
        "| odometry position median / p95 / final [m] | scans/s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        t = r["tracking"]
        rows.append(
            f"| {r['name']} | {r['scans']} | {r['path_m']:.0f} | {t['tracked']}/{r['scans']} "
            f"| {t['lost']} / {t['relocalisations']} "
            f"| **{t['pos'][0]:.3f} / {t['pos'][1]:.3f}** "
            f"| **{t['yaw_deg'][0]:.2f} / {t['yaw_deg'][1]:.2f}** "
            f"| {t['unseen_pos'][0]:.3f} / {t['unseen_pos'][1]:.3f} "
            f"| {t['odom_pos'][0]:.2f} / {t['odom_pos'][1]:.2f} / {t['odom_final_m']:.2f} "
            f"| {t['scans_per_s']:.0f} |"
        )
    return "\n".join(rows)


def reloc_table(runs: list[dict[str, Any]]) -> str:
    rows = [
        "| log | map [m] | starts | success | false positive (confident, wrong) | no fix "
        f"in {MAX_RELOC_SCANS} scans | scans to fix median / max "
        "| s per relocalisation median / max | relocalisation wall [s] | peak RSS [MiB] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        g = r["reloc"]
        n = max(g["starts"], 1)
        starts = f"{g['starts']}" + (f" of {g['planned']} (time budget)" if g["starts"] <
                                     g["planned"] else "")  # fmt: skip
        sec = np.array(g["seconds"])
        sc = np.array(g["scans"])
        sec_txt = f"{np.median(sec):.2f} / {sec.max():.2f}" if len(sec) else "—"
        sc_txt = f"{np.median(sc):.0f} / {sc.max()}" if len(sc) else "—"
        w, h = r["map_size_m"]
        rows.append(
            f"| {r['name']} | {w:.0f} x {h:.0f} | {starts} | **{g['ok']} ({g['ok'] / n:.0%})** "
            f"| **{g['wrong']}** | {g['miss']} | {sc_txt} | {sec_txt} | {g['wall_s']:.0f} "
            f"| {r['peak_rss_mb']:.0f} |"
        )
    return "\n".join(rows)


def wrong_notes(runs: list[dict[str, Any]]) -> str:
    notes = []
    for r in runs:
        errs = r["reloc"]["wrong_err"]
        if errs:
            listed = ", ".join(f"{d:.2f} m / {a:.1f} deg" for d, a in errs)
            notes.append(f"- {r['name']}: false positives off by {listed}.")
    return "\n".join(notes) or "- No false positives."


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    ap.add_argument("--only", nargs="+", choices=list(RADISH), default=list(RADISH))
    ap.add_argument("--starts", type=int, default=STARTS, help="relocalisation starts per log")
    args = ap.parse_args()
    missing = [str(RADISH[n]) for n in args.only if not RADISH[n].is_file()]
    if missing:
        sys.exit(f"benchmark logs not found: {', '.join(missing)}")
    runs = []
    for name in args.only:
        run = in_fresh_process(CaseSpec(name, args.starts))
        runs.append(run)
        print(f"{name}: tracking {run['scans'] / run['tracking']['scans_per_s']:.1f} s, "
              f"relocalisation {run['reloc']['wall_s']:.1f} s", file=sys.stderr)  # fmt: skip

    only = "" if list(args.only) == list(RADISH) else f" --only {' '.join(args.only)}"
    starts = "" if args.starts == STARTS else f" --starts {args.starts}"
    body = f"""## Localisation against a saved map (Radish logs)

Measured {dt.date.today().isoformat()} on {machine("numpy", "scipy", "cv2")}.
Command: `python bench/bench_localization.py{only}{starts}`; each log in a fresh process, default
`LocalizerConfig`. The map is an occupancy grid ({MAP_RESOLUTION} m) built from the logs'
SLAM-corrected poses and every {MAP_EVERY}nd scan; the other scans ("unseen") are not in it.
Fake odometry from the corrected poses (seed {ODOM_SEED}): {100 * ODOM_SCALE_ERROR:+.0f} % scale,
{np.degrees(ODOM_YAW_BIAS):.1f} deg/m yaw bias, Gaussian noise {100 * ODOM_SIGMA_XY:.0f} cm per
axis and {np.degrees(ODOM_SIGMA_YAW):.1f} deg per step. Errors are against the corrected poses.
Note the Radish logs are sparse (about one scan per metre), so each step is a large odometry gap.

### Tracking from the first pose (every scan)

Errors over the scans the localiser reports as tracking; scans/s is `Localizer.update` alone.

{tracking_table(runs)}

### Global relocalisation (no initial pose)

From random start scans (seed {STARTS_SEED}) a fresh `Localizer` gets the following scans until it
reports tracking (at most {MAX_RELOC_SCANS}). Success: within {SUCCESS_M} m and
{np.degrees(SUCCESS_RAD):.0f} deg; a false positive is a tracked pose farther off. Seconds: the
`update` calls from the start scan to the fix (global search, verification). Starts are drawn
until {RELOC_BUDGET_S:.0f} s per log have passed (the starts column says if that cut them).

{reloc_table(runs)}

{wrong_notes(runs)}
"""
    publish(body, args.out, SECTION)


if __name__ == "__main__":
    main()
