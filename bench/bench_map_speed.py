"""Real-time factor of `rgbdnav map` on a recorded VGA stream, this tree against a base commit.

Run: ``.venv/bin/python bench/bench_map_speed.py [--recording DIR | --world W [--cut N] |
--frames N] [--base REV] [--repeat K] [--out docs/benchmarks.md]``.
Issue 27's target 1: mapping a recording (PNG decode, VO, depth -> scan, EKF, mapper, grid) at
2x real time or faster on two cores. Without ``--recording`` the first N frames of the house
route are rendered once (``rgbdnav simulate scenes/house.yaml --frames N``); ``--world`` maps a
world file instead, rendered on demand in a second process as `make demo` does (``--cut N``: the
route's first N waypoints). Each tree maps the
same recording in a child process, ``rgbdnav map REC -q``, the trees alternating (base, this,
base, this...) so a changing machine load falls on both alike; per run the wall time and the
child's CPU time (user + system, every thread). Real-time factor = seconds of data / wall
seconds. With ``--base`` the two trees' trajectories, odometry and grids are compared byte for
byte (a speed-up that should not change the map says so; exit 1 if it did not hold and
``--same`` was given). The accuracy of the map (ATE vs the ground truth) is printed for both.
Results replace the "map_speed" (or with ``--world`` "map_speed_world") section of the output markdown file, with the machine and load.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import machine, publish  # noqa: E402  (bench/ is on sys.path)

HOUSE = REPO / "scenes" / "house.yaml"
SECTION = "map_speed"
SAME_FILES = ("trajectory.tum", "odom.tum", "map/grid.npz")


def _cli(tree: Path, *args: str) -> tuple[float, float]:
    """``rgbdnav ARGS -q`` with ``tree``'s code in a child process: (wall [s], CPU [s])."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "rgbdnav.cli", *args, "-q"],
        check=True,
        env=env,
        stdout=subprocess.DEVNULL,
        cwd=tree,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _out(tmp: Path, name: str, k: int) -> Path:
    """The run folder of tree (or variant) ``name``'s k-th run."""
    return tmp / f"{name}_{k}".replace(" ", "_").replace(",", "").replace("=", "-")


def export(rev: str, dest: Path) -> Path:
    """The tree of commit ``rev`` as files in ``dest`` (``git archive``: no worktree)."""
    dest.mkdir(parents=True)
    tar = subprocess.run(
        ["git", "-C", str(REPO), "archive", rev], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    return dest


def run(recording: Path, trees: dict[str, tuple[Path, list[str]]], repeat: int, tmp: Path) -> dict:
    runs: dict[str, list[tuple[float, float]]] = {name: [] for name in trees}
    load = [os.getloadavg()[0]]
    for k in range(repeat):
        for name, (tree, sets) in trees.items():
            out = _out(tmp, name, k)
            sets_args = [a for kv in sets for a in ("--set", kv)]
            runs[name].append(_cli(tree, "map", str(recording), "--out", str(out), *sets_args))
            load.append(os.getloadavg()[0])
            print(
                f"{name} run {k + 1}: wall {runs[name][-1][0]:.1f} s, CPU "
                f"{runs[name][-1][1]:.1f} s, load {load[-1]:.1f}",
                flush=True,
            )
    names = list(trees)
    same = None
    if len(names) >= 2:
        a, b = (_out(tmp, n, 0) for n in names[:2])
        same = all((a / f).read_bytes() == (b / f).read_bytes() for f in SAME_FILES)
    summaries = {n: json.loads((_out(tmp, n, 0) / "summary.json").read_text()) for n in names}
    return {"runs": runs, "same": same, "load": (min(load), max(load)), "s": summaries}


def report(
    recording: Path, r: dict, command: str, repeat: int, frames: int | None, world: bool
) -> str:
    names = list(r["runs"])
    data_s = r["s"][names[-1]]["data_duration_s"]
    n_frames = r["s"][names[-1]]["counts"]["scans"]
    med = {
        n: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v))
        for n, v in r["runs"].items()
    }
    rows = []
    for n in names:
        wall, cpu = med[n]
        slam = r["s"][n]["slam_vs_groundtruth"]
        rows.append(
            f"| {n} | {wall:.1f} | {cpu:.1f} | **{data_s / wall:.2f}x** | {data_s / cpu:.2f}x "
            f"| {slam['ate_rmse_aligned_m']:.4f} / {slam['ate_rmse_m']:.4f} |"
        )
    lines = [
        "## `rgbdnav map` of a world rendered on demand (`make demo`'s path): real-time factor"
        if world
        else "## `rgbdnav map` of a recorded VGA stream: real-time factor (issue 27, target 1)",
        "",
        f"Measured {dt.date.today()} on {machine('numpy', 'cv2')}; 1-min load average "
        f"{r['load'][0]:.1f}-{r['load'][1]:.1f} during the runs (the machine was shared: wall "
        "times scale with the load, CPU times much less; compare the rows, not the absolute "
        "figures).",
        f"{'World' if world else 'Recording'}: {n_frames} frames, {data_s:.1f} s of data"
        + (f" (the house route's first {frames} frames)" if frames else f" ({recording})")
        + f"; median of {repeat} runs per tree, the trees alternating.",
        f"Command: `python bench/bench_map_speed.py {command}`.",
        "",
        "| tree | wall [s] | CPU [s] | real time (data / wall) | data / CPU "
        "| ATE aligned / start-anchored [m] |",
        "| --- | ---: | ---: | ---: | ---: | --- |",
        *rows,
    ]
    if len(names) >= 2:
        (wa, ca) = med[names[0]]
        lines.append("")
        for n in names[1:]:
            wb, cb = med[n]
            lines.append(
                f"- {n} vs {names[0]}: wall **{wa / wb:.2f}x** faster, CPU {ca / cb:.2f}x."
            )
        lines.append(
            f"- {names[1]} and {names[0]}: trajectory, odometry and grid byte-identical: "
            f"{'yes' if r['same'] else '**no**'}."
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", type=Path, help="a recording to map (default: render one)")
    ap.add_argument("--world", type=Path, help="map this world file (rendered on demand)")
    ap.add_argument("--cut", type=int, help="with --world: keep the route's first N waypoints")
    ap.add_argument("--frames", type=int, default=450, help="frames of the house route to render")
    ap.add_argument("--base", help="a commit to compare with (exported with git archive)")
    ap.add_argument("--repeat", type=int, default=2, help="runs per tree")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="also map with this tree and `--set KEY=VALUE` (repeatable: one variant each)",
    )
    ap.add_argument("--same", action="store_true", help="exit 1 unless the maps are identical")
    ap.add_argument("--out", type=Path, help="markdown file whose section to replace")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-map-speed-") as tmp_s:
        tmp = Path(tmp_s)
        rec, frames = args.recording, None
        if args.world is not None:
            rec = args.world
            if args.cut:
                w = yaml.safe_load(args.world.read_text())
                w["route"] = w["route"][: args.cut]
                rec = tmp / f"{args.world.stem}_cut{args.cut}.yaml"
                rec.write_text(yaml.safe_dump(w))
        trees: dict[str, tuple[Path, list[str]]] = {}
        if args.base:
            trees[f"base {args.base}"] = (export(args.base, tmp / "base"), [])
        if args.world is None and rec is None:
            # rendered by the oldest tree: a newer tree's recording may carry config keys
            # (its scene.yaml's robot section) that an older reader rejects
            oldest = next(iter(trees.values()))[0] if trees else REPO
            frames, rec = args.frames, tmp / "recording"
            _cli(oldest, "simulate", str(HOUSE), "--frames", str(frames), "--out", str(rec))
        trees["this tree"] = (REPO, [])
        for kv in args.variant:
            trees[f"this tree, {kv}"] = (REPO, [kv])
        r = run(rec.resolve(), trees, args.repeat, tmp)
    shown = args.world if args.world is not None else rec
    if args.cut:
        shown = Path(f"{shown} --cut {args.cut}")
    command = " ".join(a for a in sys.argv[1:] if a != "--out" and not a.endswith(".md"))
    world = args.world is not None
    body = report(shown, r, command, args.repeat, frames, world)
    publish(body, args.out, SECTION + ("_world" if world else ""))
    return 1 if args.same and not r["same"] else 0


if __name__ == "__main__":
    sys.exit(main())
