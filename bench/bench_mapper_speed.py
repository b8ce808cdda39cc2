"""CPU time of the pose-graph mapper on a laser log, this tree against a base commit, side by side.

Run: ``.venv/bin/python bench/bench_mapper_speed.py [--case mit] [--base main] [--repeat 2]``.
Issue 27's target 3 (MIT CSAIL at 30x real time) on a machine that is not idle: both trees map
the same log at the same time, each in its own process (``bench_mapper``'s scans and odometry,
``add_scan`` for every scan, then ``finish``), so a changing load falls on both alike. Printed
per run: the CPU seconds of the mapper's thread (the critical path on idle cores) and of all
threads, the wall time, and for MIT CSAIL the relations error; then whether the two trees'
keyframe and scan poses are equal to the bit (a speed-up that should not change the map says so;
exit 1 when they differ). The base tree is exported with ``git archive`` (no worktree).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_map_speed import export  # noqa: E402  (bench/ is on sys.path)
from bench_mapper import CASES  # noqa: E402


def child(tree: Path, case: str, save: Path) -> None:
    """Map ``case`` with ``tree``'s code (its bench_mapper, slam and sensors); print the figures
    as JSON."""
    here = sys.modules.pop("bench_mapper")  # this tree's: the logs are found beside it
    sys.modules.pop("common", None)  # the base's bench_mapper imports its own tree's helpers
    sys.path[:0] = [str(tree / "bench"), str(tree)]
    import bench_mapper as bm

    bm.MIT_LOG, bm.MIT_RELATIONS, bm.RADISH = here.MIT_LOG, here.MIT_RELATIONS, here.RADISH

    from sensors.carmen import CarmenSource
    from slam.config import MapperConfig
    from slam.mapper import Mapper

    spec = bm.CaseSpec(case)
    logging.getLogger("sensors.carmen").setLevel(logging.ERROR)  # Radish ODOM stamps are all 0
    src = CarmenSource(bm.MIT_LOG if case == "mit" else bm.RADISH[case])
    scans, stream = list(src.scans()), src.laser_poses()
    assert stream is not None
    logged = bm._poses(stream)
    odom = logged
    if case != "mit":
        rng = np.random.default_rng(bm.ODOM_SEED)
        odom = bm.corrupt_trajectory(
            logged, bm.ODOM_SCALE_ERROR, bm.ODOM_YAW_BIAS, bm.ODOM_SIGMA_XY, bm.ODOM_SIGMA_YAW, rng
        )
    mapper = Mapper(MapperConfig())
    cpu0, thread0, wall0 = time.process_time(), time.thread_time(), time.perf_counter()
    for scan, pose in zip(scans[:: spec.every], odom[:: spec.every], strict=True):
        mapper.add_scan(scan, pose)
    result = mapper.finish()
    out = {
        "cpu_s": time.process_time() - cpu0,
        "thread_s": time.thread_time() - thread0,
        "wall_s": time.perf_counter() - wall0,
        "data_s": (stream.stamps_ns[-1] - stream.stamps_ns[0]) * 1e-9,
    }
    if case == "mit":
        from slam.trajectory_eval import read_relations, relations_error

        rel = read_relations(bm.MIT_RELATIONS)
        err = relations_error(
            result.scan_stamps_ns, result.scan_poses, rel.t1_ns, rel.t2_ns, rel.xyyaw
        )
        out["error"] = f"{err['trans_mean_m']:.4f} m / {err['rot_mean_deg']:.3f} deg"
    np.savez(save, poses=result.poses, scan_poses=result.scan_poses)
    print(json.dumps(out))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--case", choices=CASES, default="mit")
    ap.add_argument("--base", default="main", help="commit to compare with (default main)")
    ap.add_argument("--repeat", type=int, default=2, help="side-by-side runs")
    ap.add_argument("--child", nargs=3, metavar=("TREE", "CASE", "NPZ"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(Path(args.child[0]), args.child[1], Path(args.child[2]))
        return 0
    with tempfile.TemporaryDirectory(prefix="bench-mapper-speed-") as tmp_name:
        tmp = Path(tmp_name)
        trees = {"base": export(args.base, tmp / "base"), "this": REPO}
        same = True
        for k in range(args.repeat):
            procs = {
                name: subprocess.Popen(
                    [sys.executable, __file__, "--child", str(tree), args.case]
                    + [str(tmp / f"{name}.npz")],
                    stdout=subprocess.PIPE,
                    text=True,
                )
                for name, tree in trees.items()
            }
            res = {
                name: json.loads(p.communicate()[0].splitlines()[-1]) for name, p in procs.items()
            }
            if any(p.returncode for p in procs.values()):
                print("error: a mapping run failed", file=sys.stderr)
                return 1
            load = os.getloadavg()[0]
            for name, r in res.items():
                print(
                    f"run {k + 1} {name:4s}: mapper thread {r['thread_s']:.2f} s, all threads "
                    f"{r['cpu_s']:.2f} s CPU, wall {r['wall_s']:.1f} s "
                    f"({r['data_s'] / r['wall_s']:.1f}x) {r.get('error', '')} (load {load:.0f})"
                )
            a, b = np.load(tmp / "base.npz"), np.load(tmp / "this.npz")
            same &= all(np.array_equal(a[key], b[key]) for key in a.files)
        print(f"poses equal to the bit: {'yes' if same else 'NO'}")
        return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
