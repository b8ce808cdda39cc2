"""Pose-graph optimisation on the classic 2D benchmark graphs (Intel, MIT Killian Court "MITb").

Run: ``.venv/bin/python bench/bench_pose_graph.py [--out docs/benchmarks.md]``. Each case runs in a
fresh process (so its peak RSS is its own): batch Levenberg-Marquardt from the odometry guess in
the file, and iSAM2 fed node by node (every edge enters with its later node, one ``update()`` per
node) followed by a batch refinement. Results replace the "pose_graph" section of the output
markdown file, stamped with date and machine.
"""

from __future__ import annotations

import argparse
import datetime as dt
import multiprocessing as mp
import resource
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import machine, publish  # noqa: E402  (bench/ is on sys.path)

DATA = REPO.parent / "shared" / "data" / "carmen"
GRAPHS = {"Intel": DATA / "intel_posegraph_input.g2o", "MITb": DATA / "mitb_posegraph_input.g2o"}
SECTION = "pose_graph"
MAX_LM_ITERATIONS = 1000  # enough for Intel from odometry (410 with our LM settings)


def run_case(path: Path, method: str, max_iterations: int) -> dict[str, Any]:
    """One optimisation in this (child) process; returns the numbers and the process's peak RSS."""
    from slam.pose_graph import optimize_g2o

    t0 = time.perf_counter()
    run = optimize_g2o(path, method=method, max_iterations=max_iterations)  # type: ignore[arg-type]
    graph = run.pop("graph")
    run["total_seconds"] = time.perf_counter() - t0  # including reading and building the graph
    if method == "isam2":
        stats = graph.optimize_batch(max_iterations)
        run["refined_chi2"] = graph.total_chi2()
        run["refined_error"] = stats.final_error
        run["refine_iterations"] = stats.iterations
        run["refine_seconds"] = stats.seconds
    run["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # [MiB], Linux
    return run


def in_fresh_process(path: Path, method: str, max_iterations: int) -> dict[str, Any]:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(run_case, (path, method, max_iterations))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--max-iterations", type=int, default=MAX_LM_ITERATIONS)
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    args = ap.parse_args()

    missing = [str(p) for p in GRAPHS.values() if not p.is_file()]
    if missing:
        sys.exit(f"benchmark graphs not found: {', '.join(missing)}")
    rows, notes = [], []
    for name, path in GRAPHS.items():
        batch = in_fresh_process(path, "batch", args.max_iterations)
        isam = in_fresh_process(path, "isam2", args.max_iterations)
        rows.append(
            f"| {name} | batch LM from odometry | {batch['nodes']} | {batch['edges']} "
            f"| {batch['initial_chi2']:.4g} | {batch['final_chi2']:.2f} "
            f"| {batch['final_error']:.3f} | {batch['iterations']} | {batch['seconds']:.2f} "
            f"| {batch['peak_rss_mb']:.0f} |"
        )
        rows.append(
            f"| {name} | iSAM2, one update per node | {isam['nodes']} | {isam['edges']} "
            f"| {isam['initial_chi2']:.4g} | {isam['final_chi2']:.2f} "
            f"| {isam['final_error']:.3f} | {isam['iterations']} | {isam['seconds']:.2f} "
            f"| {isam['peak_rss_mb']:.0f} |"
        )
        rows.append(
            f"| {name} | ... then batch LM | | | | {isam['refined_chi2']:.2f} "
            f"| {isam['refined_error']:.3f} | {isam['refine_iterations']} "
            f"| {isam['refine_seconds']:.2f} | |"
        )
        gap = batch["final_error"] / isam["refined_error"] - 1.0
        notes.append(f"{name}: batch-from-odometry error is {100 * gap:+.2f}% vs iSAM2 + batch")
    table = "\n".join(rows)
    body = f"""## Pose-graph optimisation (GTSAM Pose2; Intel and MITb benchmark graphs)

Measured {dt.date.today().isoformat()} on {machine("numpy")}, gtsam {metadata.version("gtsam")}.
Command: `python bench/bench_pose_graph.py --max-iterations {args.max_iterations}`; each case in a
fresh process. `chi2` = sum of e^T Omega e over edges (g2o's number); `error` = GTSAM's graph error
(0.5 chi2 plus the tight prior pinning node 0). Batch: Levenberg-Marquardt (Ceres lambda schedule,
multifrontal QR) from the file's odometry guess. iSAM2: QR factorisation, relinearize threshold
0.01, skip 1; "iterations" counts updates. Time is the optimiser alone (iSAM2: the whole feed).
Peak RSS is the whole Python process (interpreter, numpy and gtsam included).
{"; ".join(notes)}.

| graph | method | nodes | edges | initial chi2 | final chi2 | final error | iterations | time [s] | peak RSS [MiB] |
| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |
{table}
"""
    publish(body, args.out, SECTION)


if __name__ == "__main__":
    main()
