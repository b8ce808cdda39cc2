"""Does the mapper hold on buildings, seeds and stamps it was not tuned on? (issue #12, item 2)

Run: ``.venv/bin/python bench/bench_generalisation.py [--out docs/benchmarks.md]
[--only aces,orebro] [--seeds 0,1,2] [--rerun loc]``. Results are cached in
``runs/bench_generalisation.json``; ``--rerun loc|sharp`` recomputes that step after a change.

Every Radish log in ``../shared/data/radish`` is mapped twice per case, each run in a fresh
process with the default ``MapperConfig``:

- the **reference map**: the log's SLAM-corrected poses given as odometry;
- the **map from corrupted odometry**: fake odometry made from those poses per seed, with the
  sign of the +-3 % scale error and of the +-1.5 deg/m yaw bias varying by seed, plus noise.

The Radish "corrected" poses are SLAM output themselves, so the score compares the two *maps*:
the global relation error (mean over random scan pairs anywhere in the run) of the map from
corrupted odometry against the reference map, on the scans both kept. Target (issue #12):
<= 0.05 m on every case, none over 0.5 m. Logs with their own clock run again with 5 Hz
synthesised stamps ("no stamps"). Results are cached in ``runs/bench_generalisation.json``
(delete it to re-measure) and replace the "generalisation" section.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench_mapper  # noqa: E402  (bench/ is on sys.path)
from common import machine, publish  # noqa: E402

SECTION = "generalisation"
RADISH_DIR = bench_mapper.DATA / "radish"
CACHE = REPO / "runs" / "bench_generalisation.json"
TARGET_M = 0.05  # [m] every case
LIMIT_M = 0.5  # [m] no case over this
SEEDS = (0, 1, 2)
# (scale sign, yaw-bias sign) per seed: the corruption is not always in the same direction.
SIGNS = ((+1, +1), (-1, -1), (+1, -1), (-1, +1))
SYNTHETIC_PERIOD_NS = 200_000_000  # 5 Hz, as sensors.carmen synthesises for a log without time


@dataclasses.dataclass(frozen=True)
class Case:
    log: str
    seed: int | None  # None: the reference map (corrected poses as odometry)
    synthetic_stamps: bool = False


def logs() -> list[str]:
    return sorted(p.name.removesuffix("-corrected.log.gz") for p in RADISH_DIR.glob("*.log.gz"))


def load_case(case: Case) -> tuple[Any, list[Any], np.ndarray, np.ndarray]:
    """The log's source, its scans (restamped for ``synthetic_stamps``), its corrected poses
    and the case's odometry (the corrected poses themselves for the reference map)."""
    import logging

    from sensors.carmen import CarmenSource

    logging.getLogger("sensors.carmen").setLevel(logging.ERROR)
    logging.getLogger("slam.localization").setLevel(logging.WARNING)
    src = CarmenSource(RADISH_DIR / f"{case.log}-corrected.log.gz")
    scans = list(src.scans())
    stream = src.laser_poses()
    assert stream is not None
    logged = np.column_stack([stream.x, stream.y, stream.yaw])
    if case.synthetic_stamps:
        stamps = scans[0].stamp_ns + np.arange(len(scans), dtype=np.int64) * SYNTHETIC_PERIOD_NS
        scans = [
            dataclasses.replace(s, stamp_ns=int(t)) for s, t in zip(scans, stamps, strict=True)
        ]
    if case.seed is None:
        return src, scans, logged, logged
    scale, bias = SIGNS[case.seed % len(SIGNS)]
    odom = bench_mapper.corrupt_trajectory(
        logged,
        scale * bench_mapper.ODOM_SCALE_ERROR,
        bias * bench_mapper.ODOM_YAW_BIAS,
        bench_mapper.ODOM_SIGMA_XY,
        bench_mapper.ODOM_SIGMA_YAW,
        np.random.default_rng(case.seed),
    )
    return src, scans, logged, odom


def run_case(case: Case) -> dict[str, Any]:
    """Map one case in this (child) process: the kept scans' stamps and poses."""
    src, scans, logged, odom = load_case(case)
    result, wall = bench_mapper._run_mapper(scans, odom, ())
    index = {s.stamp_ns: k for k, s in enumerate(scans)}
    kept = np.array([index[t] for t in result.scan_stamps_ns], dtype=np.int64)
    lc = result.counts["loop_closures"]
    return {
        "kept": kept.tolist(),
        "poses": np.asarray(result.scan_poses).tolist(),
        "logged": logged[kept].tolist(),
        "scans": len(scans),
        "stamp_source": "synthesised 5 Hz" if case.synthetic_stamps else src.log.stamp_source,
        "path_m": float(np.hypot(*np.diff(logged[:, :2], axis=0).T).sum()),
        "loops": f"{lc['proposed']} / {lc['accepted']} / {lc['rejected']}",
        "wall_s": wall,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def run_localisation(case: Case, reference: dict[str, Any]) -> dict[str, Any]:
    """Issue #12 item 4: localise the case's corrupted-odometry run, with no initial pose, in
    the occupancy grid of the reference map (its kept scans at its own poses); errors against
    that map's poses of the same scans."""
    from slam.config import LocalizerConfig, MapperConfig
    from slam.localization import Localizer, MapModel
    from slam.occupancy_grid import GridGeometry, bounds_of_scans, integrate_scans

    _src, scans, _logged, odom = load_case(case)
    kept, poses = np.asarray(reference["kept"]), np.asarray(reference["poses"])
    mc = MapperConfig()
    mapped = [scans[k] for k in kept]
    bounds = bounds_of_scans(poses, mapped, mc.max_laser_range)
    geom = GridGeometry.from_bounds(*bounds, resolution=mc.resolution, margin=1.0)
    grid = integrate_scans(geom, poses, mapped, mc)
    model = MapModel.from_grid(grid, LocalizerConfig(), mc.occupied_thresh, mc.free_thresh)
    loc = Localizer(model, LocalizerConfig())
    t0 = time.perf_counter()
    results = [loc.update(s, o) for s, o in zip(scans, odom, strict=True)]
    wall = time.perf_counter() - t0
    tracking = np.array([r.status == "tracking" for r in results])
    est = np.array([r.pose for r in results])[kept]
    ok = tracking[kept]
    pos = np.hypot(*(est[ok, :2] - poses[ok, :2]).T)
    yaw = np.degrees(np.abs(np.angle(np.exp(1j * (est[ok, 2] - poses[ok, 2])))))
    first = int(np.argmax(tracking)) if tracking.any() else -1
    return {
        "tracked": int(ok.sum()),
        "compared": len(kept),
        "first_fix_scan": first,
        "pos_median": float(np.median(pos)) if len(pos) else float("nan"),
        "pos_p95": float(np.percentile(pos, 95)) if len(pos) else float("nan"),
        "yaw_median": float(np.median(yaw)) if len(yaw) else float("nan"),
        "wrong": int((pos > 0.5).sum()),
        "wall_s": wall,
        "refined": loc.stats.refined,
        "refine_fallbacks": loc.stats.refine_fallbacks,
    }


def run_sharpness(case: Case, reference: dict[str, Any]) -> dict[str, Any]:
    """Is the mapper right to move good odometry? Each set of poses (the log's corrected ones,
    the reference map's) builds a grid from the same scans; its sharpness is the mean distance
    of the scans' end points to the nearest occupied cell (lower: walls line up better) and
    the number of occupied cells (fewer: thinner walls)."""
    import cv2

    from slam.config import MapperConfig
    from slam.occupancy_grid import GridGeometry, bounds_of_scans, integrate_scans, scan_end_points

    _src, scans, logged, _odom = load_case(case)
    kept = np.asarray(reference["kept"])
    mapped = [scans[k] for k in kept]
    mc = MapperConfig()
    out: dict[str, Any] = {}
    for name, poses in (("corrected", logged[kept]), ("mapper", np.asarray(reference["poses"]))):
        geom = GridGeometry.from_bounds(
            *bounds_of_scans(poses, mapped, mc.max_laser_range),
            resolution=mc.resolution,
            margin=1.0,
        )
        occupied = integrate_scans(geom, poses, mapped, mc).occupied_mask(mc.occupied_thresh)
        free = (~occupied).astype(np.uint8)
        dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * geom.resolution
        pairs = zip(poses, mapped, strict=True)
        ends = np.concatenate([scan_end_points(p, s, mc.max_laser_range) for p, s in pairs])
        col = np.floor((ends[:, 0] - geom.origin_x) / geom.resolution).astype(np.int64)
        row = np.floor((ends[:, 1] - geom.origin_y) / geom.resolution).astype(np.int64)
        inside = (col >= 0) & (row >= 0) & (col < geom.width) & (row < geom.height)
        out[name] = {
            "end_point_m": float(dist[row[inside], col[inside]].mean()),
            "occupied": int(occupied.sum()),
        }
    return out


def in_fresh_process(fn: Any, *args: Any) -> dict[str, Any]:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args)


def key(case: Case) -> str:
    return f"{case.log}|{case.seed}|{int(case.synthetic_stamps)}"


def global_error(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, float, float]:
    """Mean / median translation [m] and mean rotation [deg] error of map a against map b over
    random pairs of the scans both kept."""
    common, ia, ib = np.intersect1d(a["kept"], b["kept"], return_indices=True)
    pa, pb = np.asarray(a["poses"])[ia], np.asarray(b["poses"])[ib]
    rng = np.random.default_rng(bench_mapper.RPE_SEED)
    i, j = bench_mapper.random_pairs(len(common), bench_mapper.RPE_PAIRS, rng)
    err = bench_mapper.pair_errors(pa, pb, i, j)
    return float(err[:, 0].mean()), float(np.median(err[:, 0])), float(err[:, 1].mean())


def versus_logged(run: dict[str, Any]) -> float:
    """Mean pair error [m] of a map against the log's corrected poses."""
    ref = {"kept": run["kept"], "poses": run["logged"]}
    return global_error(run, ref)[0]


def report(results: dict[str, dict[str, Any]], cases: list[Case], seeds: tuple[int, ...]) -> str:
    rows, worst, met, total = [], 0.0, 0, 0
    for case in cases:
        if case.seed is None:
            continue
        run = results[key(case)]
        ref = results[key(dataclasses.replace(case, seed=None))]
        mean, median, rot = global_error(run, ref)
        worst, total = max(worst, mean), total + 1
        met += mean <= TARGET_M
        scale, bias = SIGNS[case.seed % len(SIGNS)]
        rows.append(
            f"| {case.log} | {run['stamp_source']} | {case.seed} ({scale * 3:+d} %, "
            f"{bias * 1.5:+.1f} deg/m) | {len(run['kept'])}/{run['scans']} | {run['path_m']:.0f} "
            f"| **{mean:.3f}** / {median:.3f} | {rot:.2f} | {versus_logged(run):.3f} "
            f"| {versus_logged(ref):.3f} | {run['loops']} | {run['wall_s']:.1f} |"
        )
    head = [
        f"Measured {dt.date.today()} on {machine('numpy', 'scipy')}.",
        "Command: `python bench/bench_generalisation.py --out docs/benchmarks.md` (seeds "
        f"{', '.join(map(str, seeds))}; each run in a fresh process, default `MapperConfig`).",
        "",
        "Map from corrupted odometry against the map from the logs' corrected poses (both built "
        "by the mapper), mean / median over "
        f"{bench_mapper.RPE_PAIRS} random scan pairs. Corruption per seed: the scale error and "
        "yaw bias signs shown, noise 1 cm per axis and 0.2 deg per step. The two right-hand error "
        "columns score each map against the corrected poses themselves (the reference map's "
        "column says how far the mapper moves good odometry).",
        "",
        f"**{met} of {total} cases within {100 * TARGET_M:.0f} cm** of the reference map; worst "
        f"{worst:.3f} m ({'meets' if worst <= LIMIT_M else 'misses'} the none-over-"
        f"{LIMIT_M:g} m target).",
        "",
        "| log | stamps | seed (scale, yaw bias) | scans kept | path [m] | vs reference map: "
        "mean / median [m] | rot mean [deg] | map vs corrected poses [m] | reference map vs "
        "corrected poses [m] | loops prop. / acc. / rej. | wall [s] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    loc = [
        "",
        "### Localisation against the map it made (issue #12, item 4)",
        "",
        f"The seed-{seeds[0]} corrupted-odometry run localised with no initial pose in the "
        "reference map's grid (its kept scans at its own poses, default `LocalizerConfig`); "
        "position error against that map's poses of the same scans, over the scans reported "
        "as tracking. Target: median <= 0.02 m.",
        "",
        "| log | stamps | tracked / map scans | first fix at scan | position median / p95 [m] "
        "| heading median [deg] | tracked > 0.5 m off | sub-cell polished / fell back | wall [s] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for case in cases:
        r = results.get("loc|" + key(case))
        if case.seed != seeds[0] or r is None:
            continue
        loc.append(
            f"| {case.log} | {results[key(case)]['stamp_source']} | {r['tracked']}/{r['compared']} "
            f"| {r['first_fix_scan']} | **{r['pos_median']:.3f}** / {r['pos_p95']:.3f} "
            f"| {r['yaw_median']:.2f} | {r['wrong']} | {r.get('refined', '-')} / "
            f"{r.get('refine_fallbacks', '-')} | {r['wall_s']:.1f} |"
        )
    sharp = [
        "",
        "### Is the mapper right to move good odometry?",
        "",
        "The reference map moves the logs' corrected poses (themselves SLAM output) by the "
        "column above. A grid built from each set of poses with the same scans: mean distance "
        "of the scans' end points to the nearest occupied cell (lower: the walls line up) and "
        "occupied cells (fewer: thinner walls).",
        "",
        "| log | stamps | corrected poses: end point to wall [m] / occupied cells | reference "
        "map: end point to wall [m] / occupied cells |",
        "| --- | --- | --- | --- |",
    ]
    for case in cases:
        r = results.get("sharp|" + key(case))
        if case.seed is not None or r is None:
            continue
        a, b = r["corrected"], r["mapper"]
        sharp.append(
            f"| {case.log} | {results[key(case)]['stamp_source']} | {a['end_point_m']:.4f} / "
            f"{a['occupied']} | **{b['end_point_m']:.4f}** / {b['occupied']} |"
        )
    return "## Generalisation: Radish logs, seeds and stamps (issue #12)\n\n" + "\n".join(
        head + rows + loc + sharp
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--only", help="comma-separated log names")
    parser.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    parser.add_argument(
        "--rerun",
        choices=("loc", "sharp"),
        action="append",
        default=[],
        help="recompute these steps instead of reading them from the cache (after a code change)",
    )
    args = parser.parse_args()
    if not RADISH_DIR.is_dir():
        sys.exit(f"error: {RADISH_DIR} is absent")
    names = args.only.split(",") if args.only else logs()
    seeds = tuple(int(s) for s in args.seeds.split(","))
    cases: list[Case] = []
    for name in names:
        own_clock = log_stamp_source(name) != "synthesised"
        for synthetic in (False, True) if own_clock else (False,):
            cases += [Case(name, seed, synthetic) for seed in (None, *seeds)]
    results: dict[str, dict[str, Any]] = json.loads(CACHE.read_text()) if CACHE.exists() else {}
    stale = {f"{step}|{key(c)}" for step in args.rerun for c in cases}
    results = {k: v for k, v in results.items() if k not in stale}
    jobs = [(key(c), run_case, (c,)) for c in cases]
    jobs += [
        ("loc|" + key(c), run_localisation, (c, key(dataclasses.replace(c, seed=None))))
        for c in cases
        if c.seed == seeds[0]
    ]
    jobs += [("sharp|" + key(c), run_sharpness, (c, key(c))) for c in cases if c.seed is None]
    for name, fn, fn_args in jobs:
        if name in results:
            continue
        if fn is not run_case:  # the reference map's result goes in, not its cache key
            fn_args = (fn_args[0], results[fn_args[1]])
        t0 = time.perf_counter()
        results[name] = in_fresh_process(fn, *fn_args)
        print(f"{name}: {time.perf_counter() - t0:.1f} s", flush=True)
        CACHE.parent.mkdir(parents=True, exist_ok=True)
        tmp = CACHE.with_suffix(".tmp")
        tmp.write_text(json.dumps(results))
        tmp.replace(CACHE)
    publish(report(results, cases, seeds), args.out, SECTION)


def log_stamp_source(name: str) -> str:
    import logging

    from sensors.carmen import read_carmen_log

    logging.getLogger("sensors.carmen").setLevel(logging.ERROR)

    return read_carmen_log(RADISH_DIR / f"{name}-corrected.log.gz").stamp_source


if __name__ == "__main__":
    main()
