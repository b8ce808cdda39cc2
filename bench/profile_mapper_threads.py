"""Where the pose-graph mapper's CPU goes on a laser log, per thread: the main thread's CPU per
component (exclusive: a wrapped call inside another is taken out of its parent), the local-map
workers' CPU, and how long the main thread waited on them.

Run: ``.venv/bin/python bench/profile_mapper_threads.py [--case mit]``. The log is read as
``bench/bench_mapper_speed.py`` reads it (``add_scan`` for every scan, then ``finish``); only the
mapping is timed. ``time.thread_time()`` counts a thread's own CPU, not the time it waited for a
core, so the shares hold on a loaded machine where a profiler's wall times do not
(docs/design/speed.md, "Session 19: mapper"). The main thread is the critical path on idle cores.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import logging
import os
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench_mapper as bm  # noqa: E402  (bench/ is on sys.path)

import slam.mapper as mm  # noqa: E402
from sensors.carmen import CarmenSource  # noqa: E402
from slam.config import MapperConfig  # noqa: E402
from slam.pose_graph import PoseGraph  # noqa: E402

# (owner, attribute, label): looked up where the mapper looks them up
PARTS = (
    (mm, "icp_refine", "point-to-line ICP"),
    (mm, "correlative_match", "correlative search"),
    (mm, "rival_score", "ambiguity test (rival_score)"),
    (mm, "build_likelihood_field", "likelihood field"),
    (mm, "_reference", "ICP reference (voxel filter, k-d tree, normals)"),
    (mm, "_response", "fine response"),
    (mm, "fuse_with_odometry", "fusion with odometry"),
    (mm.Mapper, "_make_keyframe", "scan points (_make_keyframe)"),
    (mm.Mapper, "_world_points", "local-map points (_world_points)"),
    (mm.Mapper, "_path_between", "path lengths (_path_between)"),
    (mm.Mapper, "finish", "finish (batch LM, vote)"),
    (mm.Mapper, "add_scan", "the rest of add_scan (bookkeeping, search set-up)"),
    (PoseGraph, "update", "iSAM2 updates"),
    (PoseGraph, "poses", "graph estimate (PoseGraph.poses)"),
    (PoseGraph, "pose", "graph estimate (PoseGraph.pose)"),
    (PoseGraph, "snapshot", "graph snapshot / restore"),
    (PoseGraph, "restore", "graph snapshot / restore"),
    (PoseGraph, "add_edge", "graph edges (add_edge, edge_errors)"),
    (PoseGraph, "edge_errors", "graph edges (add_edge, edge_errors)"),
)

main_cpu: Counter[str] = Counter()
main_calls: Counter[str] = Counter()
worker_cpu: Counter[str] = Counter()
waits = [0.0, 0]  # wall seconds the main thread spent in Future.result, calls
_nested: list[float] = []  # per open wrapped call on the main thread: CPU of wrapped calls inside
_main = threading.get_ident()
_lock = threading.Lock()


def _timed(label: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.thread_time()
        if threading.get_ident() != _main:
            try:
                return fn(*args, **kwargs)
            finally:
                with _lock:
                    worker_cpu[label] += time.thread_time() - t0
        _nested.append(0.0)
        try:
            return fn(*args, **kwargs)
        finally:
            dt, inner = time.thread_time() - t0, _nested.pop()
            main_cpu[label] += dt - inner
            main_calls[label] += 1
            if _nested:
                _nested[-1] += dt

    return wrapper


def instrument() -> None:
    for owner, attr, label in PARTS:
        setattr(owner, attr, _timed(label, getattr(owner, attr)))
    result = cf.Future.result

    def timed_result(self: cf.Future[Any], timeout: float | None = None) -> Any:
        if threading.get_ident() != _main:
            return result(self, timeout)
        t0 = time.perf_counter()
        try:
            return result(self, timeout)
        finally:
            waits[0] += time.perf_counter() - t0
            waits[1] += 1

    cf.Future.result = timed_result  # type: ignore[method-assign]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--case", choices=bm.CASES, default="mit")
    args = ap.parse_args()
    logging.getLogger("sensors.carmen").setLevel(logging.ERROR)  # Radish ODOM stamps are all 0
    src = CarmenSource(bm.MIT_LOG if args.case == "mit" else bm.RADISH[args.case])
    scans, stream = list(src.scans()), src.laser_poses()
    if stream is None:
        print("error: the log has no laser poses", file=sys.stderr)
        return 1
    odom = bm._poses(stream)
    if args.case != "mit":
        rng = np.random.default_rng(bm.ODOM_SEED)
        odom = bm.corrupt_trajectory(
            odom, bm.ODOM_SCALE_ERROR, bm.ODOM_YAW_BIAS, bm.ODOM_SIGMA_XY, bm.ODOM_SIGMA_YAW, rng
        )
    instrument()
    mapper = mm.Mapper(MapperConfig())
    cpu0, thread0, wall0 = time.process_time(), time.thread_time(), time.perf_counter()
    for scan, pose in zip(scans, odom, strict=True):
        mapper.add_scan(scan, pose)
    mapper.finish()
    total, main_total = time.process_time() - cpu0, time.thread_time() - thread0
    wall = time.perf_counter() - wall0
    print(
        f"{args.case}: main thread {main_total:.2f} s CPU, all threads {total:.2f} s, wall "
        f"{wall:.1f} s, 1-min load {os.getloadavg()[0]:.0f}"
    )
    print("| main thread | CPU [s] | share | calls |\n| --- | ---: | ---: | ---: |")
    for label, s in main_cpu.most_common():
        print(f"| {label} | {s:.2f} | {100 * s / main_total:.1f} % | {main_calls[label]} |")
    print("| local-map workers | CPU [s] |\n| --- | ---: |")
    for label, s in worker_cpu.most_common():
        print(f"| {label} | {s:.2f} |")
    print(f"main thread waiting on the workers: {waits[0]:.2f} s wall in {waits[1]} waits")
    return 0


if __name__ == "__main__":
    sys.exit(main())
