"""Keyframe pose-graph mapper on real laser logs: MIT CSAIL (Kümmerle 2009) and three Radish logs.

Run: ``.venv/bin/python bench/bench_mapper.py [--out docs/benchmarks.md] [--only mit aces ...]``.
Each case runs in a fresh process (so its peak RSS is its own) with the default
:class:`slam.config.MapperConfig`:

1. ``mit``: the raw CARMEN log (scan-frame poses = raw wheel odometry of the laser), scored with
   the published relations metric next to the published numbers.
2. ``aces``, ``orebro``, ``seattle``: the Radish logs hold SLAM-corrected poses, not odometry, so
   the corrected trajectory is corrupted into fake odometry (seeded: scale error, yaw bias per
   metre, Gaussian noise per step), the mapper runs on it, and odometry (before) and SLAM (after)
   are scored against the corrected poses with the relative-pose error over random pose pairs
   anywhere in the run, which is only small when the loops are closed.

Results replace the "mapper" section of the output markdown file, stamped with date and machine.
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
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import machine, publish, quiet_logger  # noqa: E402  (bench/ is on sys.path)

DATA = REPO.parent / "shared" / "data"
MIT_LOG = DATA / "carmen" / "mit-csail.clf"
MIT_RELATIONS = DATA / "carmen" / "mit-csail.relations"
RADISH = {
    name: DATA / "radish" / f"{name}-corrected.log.gz" for name in ("aces", "orebro", "seattle")
}
CASES = ("mit", *RADISH)
SECTION = "mapper"

# Fake odometry for the Radish logs (applied to each step of the corrected trajectory).
ODOM_SCALE_ERROR = 0.03  # [-] translation scale error (+3 %)
ODOM_YAW_BIAS = np.radians(1.5)  # [rad/m] yaw drift per metre travelled
ODOM_SIGMA_XY = 0.01  # [m] per step, each axis
ODOM_SIGMA_YAW = np.radians(0.2)  # [rad] per step
ODOM_SEED = 0
RPE_PAIRS = 1000  # random pose pairs for the relative-pose error
RPE_SEED = 0
RPE_BROKEN_M = 1.0  # [m] a pair this far off counts as broken (for the notes)
REGION_ANCHORS = 200  # scans each scan is paired with to find the regions that do not fit

# Published relations errors on mit-csail (Hess et al. ICRA 2016 Table II; Kümmerle 2009):
# (trans mean, trans std [m], rot mean, rot std [deg]); None = not published.
PUBLISHED = {
    "raw odometry": (1.6815, 5.2922, 5.072, 8.241),
    "Cartographer": (0.0319, 0.0363, 0.369, 0.365),
    "Graph Mapping": (0.004, 0.009, 0.05, 0.08),
    "GMapping": (0.049, 0.049, None, None),
}


# 1. Pure kernels ---------------------------------------------------------------------------------


def relative_poses(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a^-1 (+) b of (N, 3) poses: pose b in the frame of pose a."""
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dyaw = np.angle(np.exp(1j * (b[:, 2] - a[:, 2])))
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, dyaw])


def integrate(start: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Compose (3,) ``start`` with (N, 3) body-frame ``steps``: (N + 1, 3) poses."""
    yaw = start[2] + np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    dx = c * steps[:, 0] - s * steps[:, 1]
    dy = s * steps[:, 0] + c * steps[:, 1]
    x = start[0] + np.concatenate([[0.0], np.cumsum(dx)])
    y = start[1] + np.concatenate([[0.0], np.cumsum(dy)])
    return np.column_stack([x, y, np.angle(np.exp(1j * yaw))])


def corrupt_trajectory(
    poses: np.ndarray,
    scale_error: float,
    yaw_bias_per_m: float,
    sigma_xy: float,
    sigma_yaw: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Fake wheel odometry from a (N, 3) trajectory: each step d = p_{k-1}^-1 p_k becomes
    ``((1 + scale) dx + n_x, (1 + scale) dy + n_y, dyaw + bias |d| + n_yaw)``, integrated from
    the first pose."""
    d = relative_poses(poses[:-1], poses[1:])
    dist = np.hypot(d[:, 0], d[:, 1])
    noisy = np.column_stack(
        [
            (1.0 + scale_error) * d[:, 0] + rng.normal(0.0, sigma_xy, len(d)),
            (1.0 + scale_error) * d[:, 1] + rng.normal(0.0, sigma_xy, len(d)),
            d[:, 2] + yaw_bias_per_m * dist + rng.normal(0.0, sigma_yaw, len(d)),
        ]
    )
    return integrate(poses[0], noisy)


def pair_errors(est: np.ndarray, ref: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(P, 2) relative-pose error of pairs (i, j): |t| [m] and |yaw| [deg] of
    (est_i^-1 est_j)^-1 (ref_i^-1 ref_j)."""
    err = relative_poses(relative_poses(est[i], est[j]), relative_poses(ref[i], ref[j]))
    return np.column_stack([np.hypot(err[:, 0], err[:, 1]), np.degrees(np.abs(err[:, 2]))])


def random_pairs(n: int, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` pairs of distinct indices below ``n``, uniformly over the run."""
    i = rng.integers(0, n, count)
    j = (i + rng.integers(1, n, count)) % n  # never i itself
    return i, j


# 2. One case, in a child process -----------------------------------------------------------------


@dataclass(frozen=True)
class CaseSpec:
    name: str
    every: int = 1  # use every n-th scan
    overrides: tuple[tuple[str, float], ...] = ()  # MapperConfig fields changed from the default
    range_noise_m: float = 0.0  # [m] sigma of Gaussian noise added to every range (perturbation)
    noise_seed: int = 1
    float32_ranges: bool = False  # ranges rounded to float32 (perturbation)
    trace: bool = False  # return the mapper's decisions (bench/diag_mapper_flips.py)


def _run_mapper(
    scans: list[Any],
    odom: np.ndarray,
    overrides: tuple[tuple[str, float], ...],
    decisions: list[Any] | None = None,
) -> tuple[Any, float]:
    from slam.config import MapperConfig
    from slam.mapper import Mapper

    changed: dict[str, Any] = dict(overrides)
    mapper = Mapper(dataclasses.replace(MapperConfig(), **changed))
    mapper.decisions = decisions
    t0 = time.perf_counter()
    for scan, pose in zip(scans, odom, strict=True):
        mapper.add_scan(scan, pose)
    result = mapper.finish()
    return result, time.perf_counter() - t0


def _poses(stream: Any) -> np.ndarray:
    return np.column_stack([stream.x, stream.y, stream.yaw])


def run_case(spec: CaseSpec) -> dict[str, Any]:
    """Map one log in this (child) process; returns the numbers and the process's peak RSS."""
    from sensors.carmen import CarmenSource

    path = MIT_LOG if spec.name == "mit" else RADISH[spec.name]
    with quiet_logger("sensors.carmen", logging.ERROR):  # Radish ODOM stamps are all 0
        src = CarmenSource(path)
        scans = list(src.scans())[:: spec.every]
        stream = src.laser_poses()
    if spec.range_noise_m > 0:  # a perturbation far below any sensor's noise: the map must hold
        rng = np.random.default_rng(spec.noise_seed)
        scans = [
            dataclasses.replace(
                s,
                ranges=np.asarray(s.ranges, np.float64)
                + rng.normal(0.0, spec.range_noise_m, len(s.ranges)),
            )
            for s in scans
        ]
    if spec.float32_ranges:
        scans = [
            dataclasses.replace(s, ranges=np.asarray(s.ranges, np.float32).astype(np.float64))
            for s in scans
        ]
    assert stream is not None
    stamps = stream.stamps_ns[:: spec.every]
    logged = _poses(stream)[:: spec.every]
    out: dict[str, Any] = {
        "name": spec.name,
        "every": spec.every,
        "overrides": spec.overrides,
        "scans_in": len(scans),
        "stamp_source": src.log.stamp_source,
        "duration_s": (stamps[-1] - stamps[0]) * 1e-9,
        "path_m": float(np.hypot(*np.diff(logged[:, :2], axis=0).T).sum()),
    }
    if spec.name == "mit":
        odom = logged  # raw wheel odometry of the laser
    else:
        rng = np.random.default_rng(ODOM_SEED)
        odom = corrupt_trajectory(
            logged, ODOM_SCALE_ERROR, ODOM_YAW_BIAS, ODOM_SIGMA_XY, ODOM_SIGMA_YAW, rng
        )
    cpu0 = time.process_time()
    decisions: list[Any] | None = [] if spec.trace else None
    result, wall = _run_mapper(scans, odom, spec.overrides, decisions)
    if decisions is not None:
        out["decisions"] = decisions
        out["poses"] = result.poses
    out.update(
        wall_s=wall,
        cpu_s=time.process_time() - cpu0,  # all threads: above wall when both cores work
        counts=result.counts,
        timings_s=result.timings_s,
        scans_used=len(result.scan_stamps_ns),
    )
    if spec.name == "mit":
        from slam.trajectory_eval import read_relations, relations_error

        rel = read_relations(MIT_RELATIONS)
        args = (rel.t1_ns, rel.t2_ns, rel.xyyaw)
        out["slam"] = relations_error(result.scan_stamps_ns, result.scan_poses, *args)
        out["odom"] = relations_error(stamps, odom, *args)
    else:
        # Scans the mapper skipped have no estimate: score on the scans it kept.
        idx = np.searchsorted(stamps, result.scan_stamps_ns)
        i, j = random_pairs(len(idx), RPE_PAIRS, np.random.default_rng(RPE_SEED))
        ref = logged[idx]
        before = pair_errors(odom[idx], ref, i, j)
        after = pair_errors(result.scan_poses, ref, i, j)
        out["before"], out["after"] = _summary(before), _summary(after)
        anchors = np.random.default_rng(RPE_SEED + 1).choice(len(idx), REGION_ANCHORS)
        along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))])
        out["broken"] = [
            (a, b, along[a], along[b])
            for a, b in broken_regions(result.scan_poses, ref, anchors, RPE_BROKEN_M)
        ]
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # [MiB]
    return out


def _summary(err: np.ndarray) -> dict[str, float]:
    return {
        "t_mean": float(err[:, 0].mean()),
        "t_median": float(np.median(err[:, 0])),
        "r_mean": float(err[:, 1].mean()),
        "r_median": float(np.median(err[:, 1])),
        "broken": float((err[:, 0] > RPE_BROKEN_M).mean()),
    }


def broken_regions(
    est: np.ndarray,
    ref: np.ndarray,
    anchors: np.ndarray,
    threshold_m: float,
    min_run: int = 3,
    max_gap: int = 5,
) -> list[tuple[int, int]]:
    """Scan-index spans (first, last) that do not fit the rest of the map: a scan whose median
    pair error against the ``anchors`` exceeds ``threshold_m``; runs closer than ``max_gap`` are
    merged, runs shorter than ``min_run`` dropped."""
    n = len(est)
    i, j = np.repeat(np.arange(n), len(anchors)), np.tile(anchors, n)
    score = np.median(pair_errors(est, ref, i, j)[:, 0].reshape(n, len(anchors)), axis=1)
    bad = np.flatnonzero(score > threshold_m)
    if len(bad) == 0:
        return []
    cut = np.flatnonzero(np.diff(bad) > max_gap + 1)
    starts, ends = bad[np.r_[0, cut + 1]], bad[np.r_[cut, len(bad) - 1]]
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True) if b - a + 1 >= min_run]


def in_fresh_process(spec: CaseSpec) -> dict[str, Any]:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(run_case, (spec,))


# 3. Report -------------------------------------------------------------------------------------


def _loops(counts: dict[str, Any]) -> str:
    lc = counts["loop_closures"]
    return f"{lc['proposed']} / {lc['accepted']} / {lc['rejected']}"


def _label(run: dict[str, Any]) -> str:
    return run["name"] + "".join(f", {k} = {v:g}" for k, v in run["overrides"])


def _scans(run: dict[str, Any]) -> str:
    every = f" (every {run['every']}th)" if run["every"] > 1 else ""
    return f"{run['scans_used']}/{run['scans_in']}{every}"


def mit_table(run: dict[str, Any]) -> str:
    s, o = run["slam"], run["odom"]
    rtf = run["duration_s"] / run["wall_s"]
    rows = [
        "| system | trans error [m] | rot error [deg] |",
        "| --- | --- | --- |",
        f"| **rgbdnav mapper** | **{s['trans_mean_m']:.4f} ± {s['trans_std_m']:.4f}** "
        f"| **{s['rot_mean_deg']:.3f} ± {s['rot_std_deg']:.3f}** |",
        f"| raw odometry (our evaluation) | {o['trans_mean_m']:.4f} ± {o['trans_std_m']:.4f} "
        f"| {o['rot_mean_deg']:.3f} ± {o['rot_std_deg']:.3f} |",
    ]
    for name, (tm, ts, rm, rs) in PUBLISHED.items():
        rot = f"{rm} ± {rs}" if rm is not None else "—"
        rows.append(f"| {name} (published) | {tm} ± {ts} | {rot} |")
    perf = (
        "| wall [s] | CPU [s] | real-time factor | peak RSS [MiB] | scans used | keyframes "
        "| loops proposed / accepted / rejected | relations scored |\n"
        "| --- | --- | --- | --- | --- | --- | --- | --- |\n"
        f"| {run['wall_s']:.1f} | {run['cpu_s']:.1f} | {rtf:.1f}x ({run['duration_s']:.0f} s log) "
        f"| {run['peak_rss_mb']:.0f} | {_scans(run)} | {run['counts']['keyframes']} "
        f"| {_loops(run['counts'])} | {s['count']} (skipped {s['skipped']}) |"
    )
    return perf + "\n\n" + "\n".join(rows)


def radish_table(runs: list[dict[str, Any]]) -> str:
    rows = [
        "| log | scans used | path [m] | wall [s] | peak RSS [MiB] | keyframes "
        "| loops prop. / acc. / rej. | trans mean / median [m] before → after "
        "| rot mean / median [deg] before → after | pairs > 1 m before → after |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        b, a = r["before"], r["after"]
        rows.append(
            f"| {_label(r)} | {_scans(r)} | {r['path_m']:.0f} | {r['wall_s']:.1f} "
            f"| {r['peak_rss_mb']:.0f} | {r['counts']['keyframes']} | {_loops(r['counts'])} "
            f"| {b['t_mean']:.2f} / {b['t_median']:.2f} → **{a['t_mean']:.3f} / "
            f"{a['t_median']:.3f}** "
            f"| {b['r_mean']:.1f} / {b['r_median']:.1f} → **{a['r_mean']:.2f} / "
            f"{a['r_median']:.2f}** "
            f"| {b['broken']:.0%} → {a['broken']:.1%} |"
        )
    return "\n".join(rows)


def radish_note(run: dict[str, Any]) -> str:
    """Where the map does not fit together, and why loop closures were turned down."""
    regions = ", ".join(
        f"scans {a}-{b} (path {pa:.0f}-{pb:.0f} m)" for a, b, pa, pb in run["broken"]
    )
    where = (
        f"scans off the rest of the map by > {RPE_BROKEN_M:g} m (median over "
        f"{REGION_ANCHORS} partner scans): {regions}"
        if regions
        else f"no region off the rest of the map by > {RPE_BROKEN_M:g} m"
    )
    rejected = run["counts"]["loop_closures"]["rejected_by_reason"]
    why = ", ".join(f"{reason} {n}" for reason, n in sorted(rejected.items(), key=lambda t: -t[1]))
    stamps = (
        "; log has no usable time, stamps synthesised at 5 Hz"
        if (run["stamp_source"] == "synthesised")
        else ""
    )
    return f"- {_label(run)}: {where}; loop closures rejected: {why or 'none'}{stamps}."


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    ap.add_argument("--only", nargs="+", choices=CASES, default=list(CASES), help="cases to run")
    ap.add_argument(
        "--every",
        type=int,
        default=1,
        help="use every n-th scan (all cases; the published scans column says so)",
    )
    args = ap.parse_args()
    if args.every < 1:
        ap.error(f"--every must be a positive integer, got {args.every}")

    needed = [MIT_LOG, MIT_RELATIONS] if "mit" in args.only else []
    needed += [RADISH[n] for n in args.only if n in RADISH]
    missing = [str(p) for p in needed if not p.is_file()]
    if missing:
        sys.exit(f"benchmark logs not found: {', '.join(missing)}")
    runs: dict[str, dict[str, Any]] = {}
    extra: dict[str, dict[str, Any]] = {}  # Radish reruns with a changed config
    for name in args.only:
        run = in_fresh_process(CaseSpec(name, args.every))  # the figure never depends on load
        runs[name] = run
        print(f"{name}: {run['wall_s']:.1f} s", file=sys.stderr)
        if run["stamp_source"] == "synthesised" and name in RADISH:
            # No usable time in the log: the reader's 5 Hz stamps make minimum_time_interval,
            # not distance, decide the keyframes. Show the run without the time gate too.
            extra[name] = in_fresh_process(
                CaseSpec(name, run["every"], (("minimum_time_interval", 0.0),))
            )

    only = "" if list(args.only) == list(CASES) else f" --only {' '.join(args.only)}"
    every = "" if args.every == 1 else f" --every {args.every}"
    scans = "all its scans" if args.every == 1 else f"every {args.every}th scan"
    parts = [
        f"""## Keyframe pose-graph mapper (real laser logs)

Measured {dt.date.today().isoformat()} on {machine("numpy", "scipy")}, gtsam {metadata.version("gtsam")}.
Command: `python bench/bench_mapper.py{only}{every}`; each log in a fresh process, default
`MapperConfig`, each used scan fed to `Mapper.add_scan` and the graph batch-optimised by `finish()`.
Wall and CPU time (all threads) cover `add_scan` + `finish` (not reading the log); peak RSS is
the whole Python process.
Every log uses {scans} (`--every N` subsamples; the scans column says)."""
    ]
    if "mit" in runs:
        parts.append(f"""### MIT CSAIL (raw odometry, Kümmerle et al. 2009 relations)

Poses of every kept scan, from raw wheel odometry; relations metric of
`slam.trajectory_eval.relations_error` (mean ± std over relations, nearest scan within 20 ms).

{mit_table(runs["mit"])}""")
    radish = [r for n in RADISH if n in runs for r in (runs[n], extra.get(n)) if r is not None]
    if radish:
        notes = "\n".join(radish_note(r) for r in radish)
        parts.append(f"""### Radish logs with corrupted odometry (generalisation)

The logs' poses are SLAM-corrected; fake odometry is made from them (seed {ODOM_SEED}): every
step gets a {100 * ODOM_SCALE_ERROR:+.0f} % translation scale error, a yaw bias of
{np.degrees(ODOM_YAW_BIAS):.1f} deg per metre travelled and Gaussian noise
({100 * ODOM_SIGMA_XY:.0f} cm per axis, {np.degrees(ODOM_SIGMA_YAW):.1f} deg per step), then is
integrated. Metric: relative-pose error of {RPE_PAIRS} random pose pairs (i, j) anywhere in the
run (seed {RPE_SEED}): the error of pose j in the frame of pose i against the corrected poses —
small only when loops are closed. "Before" = the corrupted odometry, "after" = the mapper.
Note the Radish logs are sparse (about one scan per metre).

{radish_table(radish)}

{notes}""")
    publish("\n\n".join(parts) + "\n", args.out, SECTION)


if __name__ == "__main__":
    main()
