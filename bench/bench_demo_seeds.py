"""`make demo`'s command over several render seeds: per-seed figures and their mean, for A/B.

Run: ``.venv/bin/python bench/bench_demo_seeds.py [--seeds 0,1,2] [--world W] [--base REV]
[--variant KEY=VALUE ...] [--jobs N] [--cut N] [--json FILE] [--out docs/benchmarks.md]``.
One recording of a simulated route moves the demo's figures (SLAM ATE, the grid's IoU, fused
odometry) about as much as a code change does: the noise draws of the renderer, wheels and gyro
differ from seed to seed. So a change is judged on the mean over seeds. Per seed and per tree,
``rgbdnav map WORLD --seed S -q`` runs in a fresh child process, one after the other (seed by
seed, the trees alternating, so a changing load falls on all alike); from each run's summary:
SLAM ATE aligned and start-anchored, the grid's IoU with the floor plan (aligned), fused
odometry ATE aligned and start-anchored; and the child's wall and CPU time (user + system,
the renderer's process included). ``--base REV`` maps with commit REV's code (``git archive``,
as bench_map_speed.py does), ``--variant KEY=VALUE`` with this tree and ``--set KEY=VALUE``.
``--jobs N`` runs N maps at once (accuracy is deterministic, CPU time nearly so; wall times
then mean nothing), ``--cut N`` keeps the route's first N waypoints (a quick check). Reported: a
table per seed, the mean ± sample standard deviation over seeds, and each tree's mean paired
difference against the first tree. Results replace the "demo_seeds" section of the output
markdown file; ``--json`` keeps the raw figures.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_map_speed import export  # noqa: E402  (bench/ is on sys.path)
from common import machine, publish  # noqa: E402

HOUSE = REPO / "scenes" / "house.yaml"
SECTION = "demo_seeds"
# (key, column heading, format): the figures taken from each run
FIGURES = (
    ("slam_aligned", "SLAM ATE aligned [m]", ".4f"),
    ("slam_anchored", "SLAM ATE anchored [m]", ".4f"),
    ("iou", "IoU", ".3f"),
    ("odom_aligned", "fused odom aligned [m]", ".4f"),
    ("odom_anchored", "fused odom anchored [m]", ".4f"),
    ("wall", "wall [s]", ".1f"),
    ("cpu", "CPU [s]", ".1f"),
)


def figures(summary: dict, wall: float, cpu: float) -> dict[str, float]:
    """The figures of one run from its summary.json and its child's times."""
    slam, odom = summary["slam_vs_groundtruth"], summary["odometry_vs_groundtruth"]
    return {
        "slam_aligned": slam["ate_rmse_aligned_m"],
        "slam_anchored": slam["ate_rmse_m"],
        "iou": summary["grid_vs_floor_plan_aligned"]["iou"],
        "odom_aligned": odom["ate_rmse_aligned_m"],
        "odom_anchored": odom["ate_rmse_m"],
        "wall": wall,
        "cpu": cpu,
    }


def _start(tree: Path, *args: str) -> subprocess.Popen:
    """``rgbdnav ARGS -q`` with ``tree``'s code in a child process (as bench_map_speed._cli)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, "-m", "rgbdnav.cli", *args, "-q"]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, cwd=tree)


def _finish(p: subprocess.Popen, t0: float) -> tuple[float, float]:
    """Wait for ``p``: (wall [s], CPU user + system [s] of it and the children it waited for:
    the renderer's process too). ``os.wait4`` gives this child's own usage, so runs may
    overlap."""
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise subprocess.CalledProcessError(p.returncode, p.args)
    return time.perf_counter() - t0, ru.ru_utime + ru.ru_stime


def run(
    world: Path,
    seeds: list[int],
    trees: dict[str, tuple[Path, list[str]]],
    tmp: Path,
    jobs: int = 1,
) -> dict:
    """Every tree on every seed, ``jobs`` at a time in that order: {tree: {seed: figures}} and
    the load range."""
    out: dict[str, dict[int, dict[str, float]]] = {name: {} for name in trees}
    load = [os.getloadavg()[0]]
    todo = [(seed, k, name) for seed in seeds for k, name in enumerate(trees)]
    running: list[tuple[int, int, str, subprocess.Popen, float]] = []
    while todo or running:
        while todo and len(running) < jobs:
            seed, k, name = todo.pop(0)
            tree, sets = trees[name]
            sets_args = [a for kv in sets for a in ("--set", kv)]
            args = ["map", str(world), "--seed", str(seed), "--out", str(tmp / f"t{k}_seed{seed}")]
            running.append((seed, k, name, _start(tree, *args, *sets_args), time.perf_counter()))
        seed, k, name, p, t0 = running.pop(0)
        wall, cpu = _finish(p, t0)
        summary = json.loads((tmp / f"t{k}_seed{seed}" / "summary.json").read_text())
        out[name][seed] = f = figures(summary, wall, cpu)
        load.append(os.getloadavg()[0])
        print(
            f"seed {seed} {name}: "
            + ", ".join(f"{key} {f[key]:{fmt}}" for key, _, fmt in FIGURES)
            + f"; load {load[-1]:.1f}",
            flush=True,
        )
    return {"figures": out, "load": (min(load), max(load))}


def _mean_sd(values: list[float], fmt: str, sign: bool = False) -> str:
    sd = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.mean(values):{'+' if sign else ''}{fmt}} ± {sd:{fmt}}"


def report(world: str, seeds: list[int], r: dict, command: str, jobs: int = 1) -> str:
    names = list(r["figures"])
    ref = r["figures"][names[0]]
    lines = [
        f"## `make demo`'s command over render seeds {', '.join(map(str, seeds))} ({world})",
        "",
        f"Measured {dt.date.today()} on {machine('numpy', 'cv2')}; 1-min load average "
        f"{r['load'][0]:.1f}-{r['load'][1]:.1f} during the runs (wall times scale with it, CPU "
        "times much less; the trees ran alternating, seed by seed"
        + (f", {jobs} maps at once: compare CPU, not wall times)." if jobs > 1 else ")."),
        f"Command: `python bench/bench_demo_seeds.py {command}`. Each run: `rgbdnav map {world} "
        "--seed S -q` in a fresh process. ± is the sample standard deviation over the seeds; "
        "'paired' is the mean (± sd) of the per-seed differences against the first tree.",
        "",
        "| tree | seed | " + " | ".join(h for _, h, _ in FIGURES) + " |",
        "| --- | --- |" + " ---: |" * len(FIGURES),
    ]
    for name in names:
        per = r["figures"][name]
        for seed in seeds:
            row = " | ".join(f"{per[seed][k]:{fmt}}" for k, _, fmt in FIGURES)
            lines.append(f"| {name} | {seed} | {row} |")
        mean = " | ".join(
            f"**{_mean_sd([per[s][k] for s in seeds], fmt)}**" for k, _, fmt in FIGURES
        )
        lines.append(f"| {name} | mean | {mean} |")
        if name != names[0]:
            diff = " | ".join(
                _mean_sd([per[s][k] - ref[s][k] for s in seeds], fmt, sign=True)
                for k, _, fmt in FIGURES
            )
            lines.append(f"| {name} | paired | {diff} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", type=Path, default=HOUSE, help="world YAML (default: the house)")
    ap.add_argument("--seeds", default="0,1,2", help="render seeds, comma-separated")
    ap.add_argument("--base", help="a commit to compare with (exported with git archive)")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="also map with this tree and `--set KEY=VALUE` (repeatable: one variant each)",
    )
    ap.add_argument("--jobs", type=int, default=1, help="maps at once (default 1: sequential)")
    ap.add_argument("--cut", type=int, help="keep only the route's first N waypoints")
    ap.add_argument("--json", type=Path, help="write the raw figures here")
    ap.add_argument("--out", type=Path, help="markdown file whose section to replace")
    args = ap.parse_args()
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        print(f"error: --seeds wants integers separated by commas, got {args.seeds!r}")
        return 2
    world = args.world.resolve()
    if not world.is_file():
        print(f"error: no world file {args.world}")
        return 2
    with tempfile.TemporaryDirectory(prefix="bench-demo-seeds-") as tmp_s:
        tmp = Path(tmp_s)
        path = world
        if args.cut:
            w = yaml.safe_load(world.read_text())
            w["route"] = w["route"][: args.cut]
            path = tmp / f"{world.stem}_cut{args.cut}.yaml"
            path.write_text(yaml.safe_dump(w))
        trees: dict[str, tuple[Path, list[str]]] = {}
        try:
            if args.base:
                trees[f"base {args.base}"] = (export(args.base, tmp / "base"), [])
            trees["this tree"] = (REPO, [])
            for kv in args.variant:
                trees[f"this tree, {kv}"] = (REPO, [kv])
            r = run(path, seeds, trees, tmp, max(1, args.jobs))
        except subprocess.CalledProcessError as e:
            print(f"error: {' '.join(map(str, e.cmd))} failed (exit {e.returncode})")
            return 1
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))
    shown = str(world.relative_to(REPO)) if world.is_relative_to(REPO) else str(world)
    shown += f" (first {args.cut} waypoints)" if args.cut else ""
    command = " ".join(a for a in sys.argv[1:] if a != "--out" and not a.endswith(".md"))
    publish(report(shown, seeds, r, command, max(1, args.jobs)), args.out, SECTION)
    return 0


if __name__ == "__main__":
    sys.exit(main())
