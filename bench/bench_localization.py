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
4. **Kidnapped robot**: ``--kidnaps`` seeded teleports while the odometry rolls on smoothly;
   counted per kidnapping, in scans after the jump: when "lost" is declared, when it is recovered
   (within 0.2 m and 5 deg) and the confident wrong poses before (docs/design/bench_localization.md).
5. **Kidnapped robot, RGB-D** (``--no-rgbd`` skips it): the simulated house route, Kinect depth
   rendered with noise at poses that jump along the route while the wheel odometry rolls on,
   depth -> scan, localised against the world's floor plan (``tests/slam/rgbd_kidnap.py``).

Results replace the "localization" section of the output markdown file, stamped with date and
machine.
"""

from __future__ import annotations

import argparse
import dataclasses
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

from bench_mapper import corrupt_trajectory, integrate, relative_poses  # noqa: E402  (bench/ is on sys.path)
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
# Kidnapped robot.
KIDNAPS = 10  # teleports per log
KIDNAP_SEED = 0
KIDNAP_MIN_PATH_M = 20.0  # [m] the scan stream jumps at least this far along the path
KIDNAP_WARMUP = 5  # [scans] tracked from the true pose before the jump
MAX_KIDNAP_SCANS = 30  # [scans] fed after the jump before it counts as not recovered


# 1. Pure kernels ---------------------------------------------------------------------------------


def pose_errors(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(N, 2) position [m] and absolute heading [rad] errors of (N, 3) poses."""
    d = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
    a = np.abs(np.angle(np.exp(1j * (est[:, 2] - ref[:, 2]))))
    return np.column_stack([d, a])


def kidnap_stream(
    truth: np.ndarray, stamps: np.ndarray, k: int, j: int, warmup: int, n_after: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A kidnapping in a log: scan indices ``k - warmup .. k - 1`` then ``j .. j + n_after - 1``
    (``j >= 1``), with the (N, 3) path the wheels feel and the (N,) int64 stamps [ns]. After the
    jump the felt increments are the new stretch's ``truth[i - 1]^-1 truth[i]`` composed onto the
    pre-jump pose, and the stamps continue from ``stamps[k - 1]`` with the new stretch's periods."""
    before = np.arange(k - warmup, k)
    after = np.arange(j, min(j + n_after, len(truth)))
    steps = np.vstack(
        [
            relative_poses(truth[before[:-1]], truth[before[1:]]),
            relative_poses(truth[after - 1], truth[after]),
        ]
    )
    felt = integrate(truth[before[0]], steps)
    t = np.concatenate([stamps[before], stamps[k - 1] + (stamps[after] - stamps[j - 1])])
    return np.concatenate([before, after]), felt, t


def draw_kidnappings(
    path_m: np.ndarray,
    count: int,
    min_path_m: float,
    warmup: int,
    n_after: int,
    rng: np.random.Generator,
) -> list[tuple[int, int]]:
    """``count`` (k, j): k a scan with ``warmup`` before it, j a scan with ``n_after`` from it and
    at least ``min_path_m`` of path (cumulative ``path_m`` [m]) away from scan k - 1."""
    n = len(path_m)
    out: list[tuple[int, int]] = []
    while len(out) < count:
        k = int(rng.integers(warmup, n))
        far = np.flatnonzero(np.abs(path_m - path_m[k - 1]) >= min_path_m)
        far = far[(far >= 1) & (far <= n - n_after)]
        if len(far):
            out.append((k, int(rng.choice(far))))
    return out


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
    kidnaps: int = KIDNAPS


def _kidnappings(
    model: Any, cfg: Any, scans: list[Any], truth: np.ndarray, count: int
) -> dict[str, Any]:
    """Section 4 of the module docstring: one row of the kidnapping table."""
    from slam.localization import Localizer

    stamps = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    path_m = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))])
    draws = draw_kidnappings(
        path_m,
        count,
        KIDNAP_MIN_PATH_M,
        KIDNAP_WARMUP,
        MAX_KIDNAP_SCANS,
        np.random.default_rng(KIDNAP_SEED),
    )
    cases: list[dict[str, Any]] = []
    t_all = time.perf_counter()
    for n_case, (k, j) in enumerate(draws):
        idx, felt, t = kidnap_stream(truth, stamps, k, j, KIDNAP_WARMUP, MAX_KIDNAP_SCANS)
        odom = corrupt_trajectory(
            felt,
            ODOM_SCALE_ERROR,
            ODOM_YAW_BIAS,
            ODOM_SIGMA_XY,
            ODOM_SIGMA_YAW,
            np.random.default_rng(ODOM_SEED + n_case),
        )
        loc = Localizer(model, cfg, initial_pose=truth[idx[0]])
        case: dict[str, Any] = {
            "k": k,
            "j": j,
            "jump_m": float(np.hypot(*(truth[j, :2] - truth[k - 1, :2]))),
            "path_m": float(abs(path_m[j] - path_m[k - 1])),
            "lost": None,
            "lost_s": None,
            "recovered": None,
            "confident_wrong": 0,
            "wrong_low": 0,
            "pre_jump_ok": True,
        }
        for m, (i, o, stamp) in enumerate(zip(idx, odom, t, strict=True)):
            r = loc.update(dataclasses.replace(scans[i], stamp_ns=int(stamp)), o)
            n_after = m - KIDNAP_WARMUP + 1  # 1 = the first scan after the jump
            if n_after <= 0:
                case["pre_jump_ok"] &= r.status == "tracking"
                continue
            if r.status == "lost" and case["lost"] is None:
                case["lost"], case["lost_s"] = n_after, (stamp - t[KIDNAP_WARMUP - 1]) * 1e-9
            if r.status != "tracking":
                continue
            d, a = pose_errors(r.pose[None], truth[i][None])[0]
            if d <= SUCCESS_M and a <= SUCCESS_RAD:
                case["recovered"] = n_after
                break
            if r.confidence >= cfg.min_score:
                case["confident_wrong"] += 1
            else:
                case["wrong_low"] += 1
        cases.append(case)
    return {"cases": cases, "wall_s": time.perf_counter() - t_all}


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


def radish_case(name: str) -> tuple[Any, list[Any], np.ndarray, np.ndarray]:
    """A Radish log's source, its scans, its corrected poses (the truth) and the fake odometry
    made from them (seeded, as ``bench_mapper`` makes it)."""
    from sensors.carmen import CarmenSource

    logging.getLogger("sensors.carmen").setLevel(logging.ERROR)  # Radish ODOM stamps are all 0
    logging.getLogger("slam.localization").setLevel(logging.WARNING)
    src = CarmenSource(RADISH[name])
    scans = list(src.scans())
    stream = src.laser_poses()
    assert stream is not None
    truth = np.column_stack([stream.x, stream.y, stream.yaw])
    odom = corrupt_trajectory(
        truth,
        ODOM_SCALE_ERROR,
        ODOM_YAW_BIAS,
        ODOM_SIGMA_XY,
        ODOM_SIGMA_YAW,
        np.random.default_rng(ODOM_SEED),
    )
    return src, scans, truth, odom


def run_case(spec: CaseSpec) -> dict[str, Any]:
    from slam.config import LocalizerConfig
    from slam.localization import Localizer

    src, scans, truth, odom = radish_case(spec.name)
    cfg = LocalizerConfig()
    t0 = time.perf_counter()
    model = _build_map(scans, truth)
    g = model.grid.geometry
    out: dict[str, Any] = {
        "name": spec.name,
        "scans": len(scans),
        "stamp_source": src.log.stamp_source,
        "path_m": float(np.hypot(*np.diff(truth[:, :2], axis=0).T).sum()),
        "map_s": time.perf_counter() - t0,
        "map_size_m": (g.width * g.resolution, g.height * g.resolution),
    }
    # 1. Tracking from the true first pose.
    loc = Localizer(model, cfg, initial_pose=truth[0])
    t0, c0 = time.perf_counter(), time.process_time()
    results = [loc.update(s, o) for s, o in zip(scans, odom, strict=True)]
    track_s, track_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    tracked = np.array([r.status == "tracking" for r in results])
    est = np.array([r.pose for r in results])
    err = pose_errors(est[tracked], truth[tracked])
    odo_err = pose_errors(odom, truth)
    out["tracking"] = {
        "tracked": int(tracked.sum()),
        "lost": loc.stats.lost,
        "relocalisations": loc.stats.relocalisations,
        "kidnap_checks": loc.stats.kidnap_checks,
        "cpu_scans_per_s": len(scans) / track_cpu_s,
        "pos": percentiles(err[:, 0]),
        "yaw_deg": percentiles(np.degrees(err[:, 1])),
        "unseen_pos": percentiles(
            pose_errors(est[1::2][tracked[1::2]], truth[1::2][tracked[1::2]])[:, 0]
        ),
        "odom_pos": percentiles(odo_err[:, 0]),
        "odom_final_m": float(odo_err[-1, 0]),
        "scans_per_s": len(scans) / track_s,
    }
    # 2. Global relocalisation from random starts, within a time budget.
    rng = np.random.default_rng(STARTS_SEED)
    starts = rng.choice(len(scans) - MAX_RELOC_SCANS, spec.starts, replace=False)
    ok = wrong = miss = 0
    fix_s: list[float] = []
    fix_cpu_s: list[float] = []
    fix_scans: list[int] = []
    wrong_err: list[tuple[float, float]] = []
    t_all = time.perf_counter()
    done = 0
    for s in starts:
        if time.perf_counter() - t_all > RELOC_BUDGET_S:
            break
        done += 1
        loc = Localizer(model, cfg)
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(s, s + MAX_RELOC_SCANS):
            r = loc.update(scans[i], odom[i])
            if r.status == "tracking":
                fix_s.append(time.perf_counter() - t0)
                fix_cpu_s.append(time.process_time() - c0)
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
        "starts": done,
        "planned": spec.starts,
        "ok": ok,
        "wrong": wrong,
        "miss": miss,
        "wrong_err": wrong_err,
        "seconds": fix_s,
        "cpu_seconds": fix_cpu_s,
        "scans": fix_scans,
        "wall_s": time.perf_counter() - t_all,
    }
    # 3. Kidnappings: the tracked scan stream jumps far along the path, odometry does not.
    out["kidnap"] = _kidnappings(model, cfg, scans, truth, spec.kidnaps)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # [MiB]
    return out


# RGB-D kidnapping in the simulated house (tests/slam/rgbd_kidnap.py builds the stream).
RGBD_RATE_HZ = 5.0  # [Hz] frames fed to the localiser
RGBD_AFTER_S = 20.0  # [s] of frames after the teleport
RGBD_KIDNAPS = ((10.0, 20.0), (20.0, 30.0), (40.0, 25.0), (60.0, -30.0))  # (at [s], jump [s])


def run_rgbd_kidnaps() -> list[dict[str, Any]]:
    sys.path.insert(0, str(REPO / "tests" / "slam"))
    from rgbd_kidnap import DepthScanner, house, kidnap_stream, run_kidnap

    world, cfg, traj, model = house()
    rows = []
    for n, (at_s, jump_s) in enumerate(RGBD_KIDNAPS):
        scanner = DepthScanner(world, cfg, noisy=True, seed=n)
        st = kidnap_stream(traj, RGBD_RATE_HZ, at_s, jump_s, RGBD_AFTER_S, seed=n)
        out, _ = run_kidnap(model, cfg, scanner, st)
        j = st.jump_index
        rows.append(
            {
                "at_s": at_s,
                "jump_s": jump_s,
                "frames": len(st.stamps_ns),
                "jump_m": float(np.hypot(*(st.truth[j, :2] - st.truth[j - 1, :2]))),
                "outcome": dataclasses.asdict(out),
            }
        )
    return rows


def rgbd_table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| kidnapped at [s] | set down [s along the route] | jump [m] | tracking before it "
        "| left tracking / lost after: frames (s) | recovered after: frames (s) "
        "| tracked wrong & confident: frames |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]

    def fs(v: int | None, period: float) -> str:
        return "never" if v is None else f"{v} ({v * period:.1f})"

    for r in rows:
        o = r["outcome"]
        lines.append(
            f"| {r['at_s']:.0f} | {r['jump_s']:+.0f} | {r['jump_m']:.1f} "
            f"| {'ok' if o['pre_jump_ok'] else 'off > 0.2 m somewhere'} "
            f"| {fs(o['left_tracking'], o['period_s'])} / {fs(o['lost'], o['period_s'])} "
            f"| {fs(o['recovered'], o['period_s'])} | **{o['confident_wrong']}** |"
        )
    return "\n".join(lines)


def in_fresh_process(spec: CaseSpec) -> dict[str, Any]:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(run_case, (spec,))


# 3. Report -------------------------------------------------------------------------------------


def tracking_table(runs: list[dict[str, Any]]) -> str:
    rows = [
        "| log | scans | path [m] | tracked | lost / relocalised | position median / p95 [m] "
        "| heading median / p95 [deg] | unseen scans: position median / p95 [m] "
        "| odometry position median / p95 / final [m] | kidnap checks | scans/s wall / CPU |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
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
            f"| {t['kidnap_checks']} | {t['scans_per_s']:.0f} / {t['cpu_scans_per_s']:.0f} |"
        )
    return "\n".join(rows)


def reloc_table(runs: list[dict[str, Any]]) -> str:
    rows = [
        "| log | map [m] | starts | success | false positive (confident, wrong) | no fix "
        f"in {MAX_RELOC_SCANS} scans | scans to fix median / max "
        "| s per relocalisation median / max: wall | CPU "
        "| relocalisation wall [s] | peak RSS [MiB] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        g = r["reloc"]
        n = max(g["starts"], 1)
        starts = f"{g['starts']}" + (
            f" of {g['planned']} (time budget)" if g["starts"] < g["planned"] else ""
        )
        sec = np.array(g["seconds"])
        sc = np.array(g["scans"])
        cpu = np.array(g["cpu_seconds"])
        sec_txt = (
            f"**{np.median(sec):.2f} / {sec.max():.2f}** | {np.median(cpu):.2f} / {cpu.max():.2f}"
            if len(sec)
            else "— | —"
        )
        sc_txt = f"{np.median(sc):.0f} / {sc.max()}" if len(sc) else "—"
        w, h = r["map_size_m"]
        rows.append(
            f"| {r['name']} | {w:.0f} x {h:.0f} | {starts} | **{g['ok']} ({g['ok'] / n:.0%})** "
            f"| **{g['wrong']}** | {g['miss']} | {sc_txt} | {sec_txt} | {g['wall_s']:.0f} "
            f"| {r['peak_rss_mb']:.0f} |"
        )
    return "\n".join(rows)


def _med_max(values: list[Any], fmt: str = ".0f") -> str:
    v = np.array([x for x in values if x is not None], dtype=np.float64)
    return f"{np.median(v):{fmt}} / {v.max():{fmt}}" if len(v) else "—"


def kidnap_table(runs: list[dict[str, Any]]) -> str:
    rows = [
        "| log | kidnappings | jump: path / straight-line median [m] | lost declared after: "
        "scans median / max (never) | seconds to lost median / max | recovered after: scans "
        "median / max (never) | tracked wrong & confident: scans (kidnappings) | tracked wrong, "
        "confidence < min_score: scans | success | wall [s] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        cs = r["kidnap"]["cases"]
        lost = [c["lost"] for c in cs]
        rec = [c["recovered"] for c in cs]
        cw = [c["confident_wrong"] for c in cs]
        ok = sum(c["recovered"] is not None and c["confident_wrong"] == 0 for c in cs)
        rows.append(
            f"| {r['name']} | {len(cs)} "
            f"| {np.median([c['path_m'] for c in cs]):.0f} / "
            f"{np.median([c['jump_m'] for c in cs]):.0f} "
            f"| {_med_max(lost)} ({lost.count(None)}) "
            f"| {_med_max([c['lost_s'] for c in cs], '.1f')} "
            f"| {_med_max(rec)} ({rec.count(None)}) "
            f"| **{sum(cw)} ({sum(x > 0 for x in cw)})** "
            f"| {sum(c['wrong_low'] for c in cs)} "
            f"| **{ok}/{len(cs)}** | {r['kidnap']['wall_s']:.0f} |"
        )
    return "\n".join(rows)


def kidnap_notes(runs: list[dict[str, Any]]) -> str:
    notes = []
    for r in runs:
        for c in r["kidnap"]["cases"]:
            bad = c["recovered"] is None or c["confident_wrong"] or not c["pre_jump_ok"]
            if bad:
                notes.append(
                    f"- {r['name']} scan {c['k']} -> {c['j']} ({c['jump_m']:.1f} m): lost after "
                    f"{c['lost']}, recovered after {c['recovered']} of {MAX_KIDNAP_SCANS} scans, "
                    f"{c['confident_wrong']} scans tracked wrong and confident"
                    + ("" if c["pre_jump_ok"] else "; not tracking before the jump")
                    + "."
                )
    return "\n".join(notes) or "- Every kidnapping recovered with no confident wrong pose."


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
    ap.add_argument("--kidnaps", type=int, default=KIDNAPS, help="kidnappings per log")
    ap.add_argument("--no-rgbd", action="store_true", help="skip the RGB-D house kidnappings")
    args = ap.parse_args()
    from slam.config import LocalizerConfig

    missing = [str(RADISH[n]) for n in args.only if not RADISH[n].is_file()]
    if missing:
        sys.exit(f"benchmark logs not found: {', '.join(missing)}")
    runs = []
    for name in args.only:
        run = in_fresh_process(CaseSpec(name, args.starts, args.kidnaps))
        runs.append(run)
        print(
            f"{name}: tracking {run['scans'] / run['tracking']['scans_per_s']:.1f} s, "
            f"relocalisation {run['reloc']['wall_s']:.1f} s, "
            f"kidnapping {run['kidnap']['wall_s']:.1f} s",
            file=sys.stderr,
        )

    rgbd = ""
    if not args.no_rgbd:
        t0 = time.perf_counter()
        rows = run_rgbd_kidnaps()
        print(f"rgbd kidnappings: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        rgbd = f"""
### Kidnapped robot, RGB-D (simulated house)

`scenes/house.yaml` route, Kinect depth rendered with noise (`KinectRenderer.render`) at
{RGBD_RATE_HZ:.0f} Hz, turned into scans with `DepthToScan` and the RGB-D profile, localised against
the world's floor plan (wall faces in the depth->scan height band). The camera is teleported
along the route at the given time while the wheel odometry continues (2 % scale error, noise);
{RGBD_AFTER_S:.0f} s of frames after the jump. Frames are counted after the jump (the first is
1). Recovered: tracking within {SUCCESS_M} m and {np.degrees(SUCCESS_RAD):.0f} deg. Built by
`tests/slam/rgbd_kidnap.py` (the simulator itself cannot teleport).

{rgbd_table(rows)}
"""
    only = "" if list(args.only) == list(RADISH) else f" --only {' '.join(args.only)}"
    starts = "" if args.starts == STARTS else f" --starts {args.starts}"
    starts += "" if args.kidnaps == KIDNAPS else f" --kidnaps {args.kidnaps}"
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
`update` calls from the start scan to the fix (global search, verification), wall clock and
process CPU time (the machine is shared, so wall time is noisy; CPU time is this process's own). Starts are drawn
until {RELOC_BUDGET_S:.0f} s per log have passed (the starts column says if that cut them).

{reloc_table(runs)}

{wrong_notes(runs)}

### Kidnapped robot

{args.kidnaps} kidnappings per log (seed {KIDNAP_SEED}): tracking from the true pose
{KIDNAP_WARMUP} scans before a random scan, the scan stream then jumps to a random scan at least
{KIDNAP_MIN_PATH_M:.0f} m further along the path (either way; the straight-line jump can be
shorter) while the odometry continues smoothly (the new stretch's increments composed onto the
pre-jump odometry, same corruption as above) and the stamps continue with the new stretch's own
periods, so `lost_time` ({LocalizerConfig().lost_time} s) spans a different number of scans per
log. Scans are counted after the jump (the first is 1), at most {MAX_KIDNAP_SCANS}; seconds from the
last scan before it. Recovered:
tracking within {SUCCESS_M} m and {np.degrees(SUCCESS_RAD):.0f} deg. Wrong: a "tracking" scan
before the recovery farther off; confident when its confidence is at least `min_score`
({LocalizerConfig().min_score}). Success: recovered, and never wrong and confident.

{kidnap_table(runs)}

{kidnap_notes(runs)}
{rgbd}"""
    publish(body, args.out, SECTION)


if __name__ == "__main__":
    main()
