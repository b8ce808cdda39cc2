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
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench_generalisation as bg  # noqa: E402  (bench/ is on sys.path)
import bench_mapper  # noqa: E402


def run(case: bg.Case, every: int) -> dict:
    src, scans, logged, odom = bg.load_case(case)
    scans, logged, odom = scans[::every], logged[::every], odom[::every]
    result, wall = bench_mapper._run_mapper(scans, odom, ())
    index = {s.stamp_ns: k for k, s in enumerate(scans)}
    kept = [index[t] for t in result.scan_stamps_ns]
    counts = {k: (dict(v) if isinstance(v, dict) else v) for k, v in result.counts.items()}
    return {"kept": kept, "poses": np.asarray(result.scan_poses).tolist(),
            "logged": logged[kept].tolist(), "counts": counts, "wall_s": wall}  # fmt: skip


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """Each pose in the frame of the first one."""
    return bench_mapper.relative_poses(np.repeat(poses[:1], len(poses), axis=0), poses)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    ref = run(bg.Case(args.log, None), args.every)
    cor = run(bg.Case(args.log, args.seed), args.every)
    mean, median, rot = bg.global_error(cor, ref)
    print(f"{args.log} seed {args.seed} every {args.every}: vs reference map mean {mean:.3f} m "
          f"median {median:.3f} m rot {rot:.2f} deg; reference vs corrected poses "
          f"{bg.versus_logged(ref):.3f} m; corrupted vs corrected poses "
          f"{bg.versus_logged(cor):.3f} m")  # fmt: skip
    for name, r in (("reference", ref), ("corrupted", cor)):
        print(f"{name}: wall {r['wall_s']:.1f} s, counts {json.dumps(r['counts'], default=str)}")
    common, ia, ib = np.intersect1d(cor["kept"], ref["kept"], return_indices=True)
    a = relative_to_first(np.asarray(cor["poses"])[ia])
    b = relative_to_first(np.asarray(ref["poses"])[ib])
    drift = np.hypot(*(a[:, :2] - b[:, :2]).T)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(b[:, :2], axis=0).T))])
    for lim in (0.5, 1.0, 5.0):
        hit = np.flatnonzero(drift > lim)
        if len(hit):
            print(f"first scan > {lim} m off (relative to scan 0): scan {common[hit[0]]} "
                  f"(path {path[hit[0]]:.0f} m)")  # fmt: skip
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
