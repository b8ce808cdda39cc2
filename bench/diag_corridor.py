"""Where does a Radish log's map from corrupted odometry leave the reference map? (issue #12)

Run: ``.venv/bin/python bench/diag_corridor.py infinite-corridor --seed 0 [--every 2]
[--out runs/diag.json]``.

Maps the log twice in this process, as ``bench/bench_generalisation.py`` does (the corrected
poses as odometry: the reference map; seeded corrupted odometry), optionally on every n-th
scan (exploration only), and prints the global pair error between the two maps, the mapper's
match and loop-closure counts, and where along the path the corrupted run goes wrong first:
the error of each kept scan's pose relative to the first one, and of each step, against the
reference map. Details and findings: docs/design/mapper.md ("Long corridor").
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

import bench_generalisation as bg  # noqa: E402  (bench/ is on sys.path)
import bench_mapper  # noqa: E402


def run(case: bg.Case, every: int, upto: int | None) -> dict:
    """Map the case; also score every loop closure left in the final graph against the log's
    corrected poses (its measured relative pose against theirs)."""
    from slam.config import MapperConfig
    from slam.mapper import Mapper

    src, scans, logged, odom = bg.load_case(case)
    scans, logged, odom = scans[::every][:upto], logged[::every][:upto], odom[::every][:upto]
    mapper = Mapper(MapperConfig())
    t0 = time.perf_counter()
    for scan, pose in zip(scans, odom, strict=True):
        mapper.add_scan(scan, pose)
    result = mapper.finish()
    wall = time.perf_counter() - t0
    index = {s.stamp_ns: k for k, s in enumerate(scans)}
    kept = [index[t] for t in result.scan_stamps_ns]
    kf_scan = [index[kf.stamp_ns] for kf in mapper.keyframes]
    loops = []
    for e in mapper.graph.edges:
        if e.kind != "loop":
            continue
        a, b = logged[kf_scan[e.i]], logged[kf_scan[e.j]]
        truth = bench_mapper.relative_poses(a[None], b[None])[0]
        err = e.delta - truth
        sigma = np.sqrt(np.diag(np.linalg.inv(e.information)))
        loops.append(
            [
                kf_scan[e.i],
                kf_scan[e.j],
                float(np.hypot(err[0], err[1])),
                float(np.degrees(np.angle(np.exp(1j * err[2])))),
                *sigma.tolist(),
            ]
        )
    counts = {k: (dict(v) if isinstance(v, dict) else v) for k, v in result.counts.items()}
    return {
        "kept": kept,
        "poses": np.asarray(result.scan_poses).tolist(),
        "logged": logged[kept].tolist(),
        "counts": counts,
        "wall_s": wall,
        "loops": loops,
    }


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """Each pose in the frame of the first one."""
    return bench_mapper.relative_poses(np.repeat(poses[:1], len(poses), axis=0), poses)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--upto", type=int, help="only the first n scans (after --every)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    ref = run(bg.Case(args.log, None), args.every, args.upto)
    cor = run(bg.Case(args.log, args.seed), args.every, args.upto)
    mean, median, rot = bg.global_error(cor, ref)
    print(
        f"{args.log} seed {args.seed} every {args.every}: vs reference map mean {mean:.3f} m "
        f"median {median:.3f} m rot {rot:.2f} deg; reference vs corrected poses "
        f"{bg.versus_logged(ref):.3f} m; corrupted vs corrected poses "
        f"{bg.versus_logged(cor):.3f} m"
    )
    for name, r in (("reference", ref), ("corrupted", cor)):
        print(f"{name}: wall {r['wall_s']:.1f} s, counts {json.dumps(r['counts'], default=str)}")
        wrong = [lp for lp in r["loops"] if lp[2] > 0.5 or abs(lp[3]) > 2.0]
        print(
            f"  loop closures in the final graph: {len(r['loops'])}, off the corrected poses "
            f"by > 0.5 m or 2 deg: {len(wrong)}"
        )
        for i, j, et, ey, sx, sy, syaw in wrong[:20]:
            print(
                f"    scans {i} -> {j}: off by {et:.2f} m, {ey:+.2f} deg; claimed sigma "
                f"{sx:.3f} m, {sy:.3f} m, {np.degrees(syaw):.2f} deg"
            )
    common, ia, ib = np.intersect1d(cor["kept"], ref["kept"], return_indices=True)
    a = relative_to_first(np.asarray(cor["poses"])[ia])
    b = relative_to_first(np.asarray(ref["poses"])[ib])
    drift = np.hypot(*(a[:, :2] - b[:, :2]).T)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(b[:, :2], axis=0).T))])
    for lim in (0.5, 1.0, 5.0):
        hit = np.flatnonzero(drift > lim)
        if len(hit):
            print(
                f"first scan > {lim} m off (relative to scan 0): scan {common[hit[0]]} "
                f"(path {path[hit[0]]:.0f} m)"
            )
    n = len(common)
    pa, pb = np.asarray(cor["poses"])[ia], np.asarray(ref["poses"])[ib]
    sa = bench_mapper.relative_poses(pa[:-1], pa[1:])
    sb = bench_mapper.relative_poses(pb[:-1], pb[1:])
    d = sa - sb
    along, lateral, yaw = d[:, 0].mean(), d[:, 1].mean(), np.degrees(d[:, 2]).mean()
    print(f"step error: along mean {along:.4f} m, lateral {lateral:.4f} m, yaw {yaw:.3f} deg")
    for q in np.linspace(0, n - 1, 11).astype(int):
        print(f"  scan {common[q]:5d} path {path[q]:7.1f} m drift {drift[q]:7.2f} m")
    if args.out:
        args.out.write_text(json.dumps({"reference": ref, "corrupted": cor}))


if __name__ == "__main__":
    main()
