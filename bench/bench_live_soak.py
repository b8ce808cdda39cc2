"""Live soak on the simulated robot: memory of every process of the run, drops and latency.

Runs ``rgbdnav live --camera sim --board sim --repeat-route`` (the house route driven again and
again while mapping) from this tree for ``--minutes``, and samples from outside, every
``--sample`` seconds, the resident memory (psutil, else /proc) of the live process and of each
of its descendants (the simulated robot: renderer + board emulator), with the 1-min load
average. At the end it reads the run's own ``summary.json`` for the frames received, processed
and dropped (front end and camera side) and the frame-to-pose latency p50 / p99 / max, and
reports memory growth after the warm-up (``--warmup-minutes``): growth from the first minute
after warm-up to the peak and to the last minute, and the least-squares slope, per process and
for the whole run (target: < 10 %). The samples go to ``OUT/soak_memory.json`` as they are
taken, so a killed soak keeps what it measured.

Run: ``.venv/bin/python bench/bench_live_soak.py --minutes 60 [--out docs/benchmarks.md]``;
results replace the ``live-soak-1h`` section (``--section``) of the markdown file.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import TREE_CLI, machine, publish, tree_env  # noqa: E402  (bench/ is on sys.path)

from sensors.atomic import atomic_write_text  # noqa: E402

WORLD = REPO / "scenes" / "house.yaml"
GROWTH_TARGET = 0.10  # memory growth after warm-up
LATENCY_P99_TARGET_MS = 50.0  # issue #15 (the tool's 27), target 5
BASE_WINDOW_S = 60.0  # [s] the baseline and the end are means over this long a window


def _loadavg() -> float:
    try:
        return float(Path("/proc/loadavg").read_text().split()[0])
    except (OSError, ValueError):
        return float("nan")


def _proc_rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError):
        return None
    return None


def _proc_children(pid: int) -> list[int]:
    """Direct children of ``pid`` from /proc (every thread's ``children`` list)."""
    kids: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            kids += [int(k) for k in (task / "children").read_text().split()]
        except (OSError, ValueError):
            pass
    return kids


def _proc_name(pid: int) -> str:
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        return " ".join(a.decode(errors="replace") for a in argv if a)[:200]
    except OSError:
        return "?"


def process_tree_rss(pid: int) -> dict[int, tuple[str, float]]:
    """{pid: (command, RSS MB)} of ``pid`` and all its descendants that are alive now."""
    try:
        import psutil
    except ImportError:
        psutil = None
    out: dict[int, tuple[str, float]] = {}
    if psutil is not None:
        try:
            root = psutil.Process(pid)
            procs = [root, *root.children(recursive=True)]
        except psutil.Error:
            return out
        for p in procs:
            try:
                out[p.pid] = (" ".join(p.cmdline())[:200], p.memory_info().rss / 2**20)
            except psutil.Error:
                pass
        return out
    todo = [pid]
    while todo:
        p = todo.pop()
        rss = _proc_rss_mb(p)
        if rss is not None:
            out[p] = (_proc_name(p), rss)
            todo += _proc_children(p)
    return out


def memory_growth(t: np.ndarray, mb: np.ndarray, warmup_s: float) -> dict[str, float | None]:
    """Growth of one memory series after ``warmup_s``: the baseline is the mean over the first
    ``BASE_WINDOW_S`` after warm-up, the end the mean over the last ``BASE_WINDOW_S``; growth to
    the peak and to the end relative to the baseline, and the least-squares slope per 10 min.
    None where the run is too short (fewer than 2 samples after warm-up)."""
    t, mb = np.asarray(t, float), np.asarray(mb, float)
    after = t >= warmup_s
    if after.sum() < 2:
        return {
            "base_mb": None,
            "end_mb": None,
            "peak_mb": None,
            "growth_end": None,
            "growth_peak": None,
            "slope_mb_per_10min": None,
        }
    ta, ma = t[after], mb[after]
    base = float(ma[ta <= ta[0] + BASE_WINDOW_S].mean())
    end = float(ma[ta >= ta[-1] - BASE_WINDOW_S].mean())
    peak = float(ma.max())
    slope = float(np.polyfit(ta, ma, 1)[0]) * 600.0 if np.ptp(ta) > 0 else 0.0
    return {
        "base_mb": round(base, 1),
        "end_mb": round(end, 1),
        "peak_mb": round(peak, 1),
        "growth_end": round((end - base) / base, 4),
        "growth_peak": round((peak - base) / base, 4),
        "slope_mb_per_10min": round(slope, 2),
    }


def frame_blocks(timeline: list[list[Any]], block_s: float) -> list[dict[str, Any]]:
    """The run's ``frames_timeline`` ([t, processed so far, dropped so far, window p99]) in
    blocks of ``block_s``: frames processed and dropped in each, and the median and worst of
    its windows' latency p99 (None without windows that processed a frame)."""
    blocks: list[dict[str, Any]] = []
    prev = [0.0, 0, 0, None]
    for k in range(int(np.ceil(max((p[0] for p in timeline), default=0.0) / block_s))):
        pts = [p for p in timeline if k * block_s < p[0] <= (k + 1) * block_s]
        if not pts:
            continue
        p99s = [p[3] for p in pts if p[3] is not None]
        blocks.append(
            {
                "from_s": k * block_s,
                "to_s": (k + 1) * block_s,
                "processed": pts[-1][1] - prev[1],
                "dropped": pts[-1][2] - prev[2],
                "p99_median_ms": round(float(np.median(p99s)), 1) if p99s else None,
                "p99_worst_ms": round(float(max(p99s)), 1) if p99s else None,
            }
        )
        prev = pts[-1]
    return blocks


def role(pid: int, root: int, command: str) -> str:
    """A process's part in the run, for the report."""
    if pid == root:
        return "host (rgbdnav live)"
    if "resource_tracker" in command:
        return "multiprocessing resource tracker"
    if "spawn_main" in command or "forkserver" in command:
        return "simulated robot"  # the only process the live run spawns
    return command[:60] or str(pid)


def soak(
    out: Path, seconds: float, sample_s: float, extra: list[str]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Run the live soak, sampling its processes; (the run's summary, the samples)."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [
        *TREE_CLI,
        "live",
        "--out",
        str(out),
        "--sim-world",
        str(WORLD),
        "--duration",
        str(seconds),
        "--repeat-route",
        "-q",
        *extra,
    ]
    print("$", " ".join(cmd), flush=True)
    log = (out.parent / f"{out.name}.log").open("w")
    proc = subprocess.Popen(cmd, cwd=REPO, env=tree_env(), stdout=log, stderr=subprocess.STDOUT)
    t0 = time.monotonic()
    rec: dict[str, Any] = {
        "command": cmd,
        "sample_s": sample_s,
        "pid": proc.pid,
        "started": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "samples": [],
    }
    next_t = 0.0
    while proc.poll() is None:
        now = time.monotonic() - t0
        if now >= next_t:
            tree = process_tree_rss(proc.pid)
            rec["samples"].append(
                {
                    "t": round(now, 1),
                    "load1": _loadavg(),
                    "rss_mb": {str(p): round(m, 1) for p, (_, m) in tree.items()},
                }
            )
            rec.setdefault("commands", {}).update({str(p): c for p, (c, _) in tree.items()})
            atomic_write_text(out / "soak_memory.json", json.dumps(rec))
            next_t += sample_s
        time.sleep(min(1.0, max(0.05, next_t - (time.monotonic() - t0))))
    log.close()
    rec["returncode"] = proc.returncode
    rec["wall_s"] = round(time.monotonic() - t0, 1)
    atomic_write_text(out / "soak_memory.json", json.dumps(rec))
    summary_path = out / "summary.json"
    if proc.returncode != 0 or not summary_path.exists():
        sys.exit(f"error: the live run exited with {proc.returncode}; see {out.name}.log")
    return json.loads(summary_path.read_text()), rec


def series(rec: dict[str, Any]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per role and for the whole run: (t, MB) from the samples (a role's processes summed; the
    whole run only where all its processes were up)."""
    root, cmds = rec["pid"], rec.get("commands", {})
    out: dict[str, list[tuple[float, float]]] = {}
    full = max((len(s["rss_mb"]) for s in rec["samples"]), default=0)
    for s in rec["samples"]:
        per: dict[str, float] = {}
        for pid, mb in s["rss_mb"].items():
            r = role(int(pid), root, cmds.get(pid, ""))
            per[r] = per.get(r, 0.0) + mb
        if len(s["rss_mb"]) == full:  # not while the run starts its children or ends
            per["all processes"] = sum(s["rss_mb"].values())
        for r, mb in per.items():
            out.setdefault(r, []).append((s["t"], mb))
    return {r: tuple(np.array(v).T) for r, v in out.items()}  # type: ignore[misc]


def report(
    s: dict[str, Any], rec: dict[str, Any], minutes: float, warmup_min: float, cmdline: str
) -> str:
    c, lat = s["counts"], s.get("latency_ms") or {}
    sim, mp = s.get("sim_robot") or {}, s.get("mapper") or {}
    loads = np.array([x["load1"] for x in rec["samples"]], float)
    rows = []
    growth_ok = None
    for name, (t, mb) in series(rec).items():
        g = memory_growth(t, mb, warmup_min * 60)
        if g["base_mb"] is None:
            continue
        ok = g["growth_peak"] < GROWTH_TARGET
        if name == "all processes":
            growth_ok = ok
        rows.append(
            f"| {name} | {g['base_mb']:.0f} / {g['end_mb']:.0f} / {g['peak_mb']:.0f} MB | "
            f"{g['growth_end']:+.1%} / {g['growth_peak']:+.1%} | "
            f"{g['slope_mb_per_10min']:+.1f} MB | {'met' if ok else '**not met**'} |"
        )
    dropped = c.get("frames_dropped_front_end", 0)
    p99 = lat.get("p99")
    started = rec["started"].replace("T", " ")[:16]
    lines = [
        f"## Live soak, every process ({minutes:g} min)",
        "",
        f"Date {started} UTC; machine: {machine('numpy')}; 1-min load average during the run "
        f"(sampled every {rec['sample_s']:g} s) min / mean / max {np.nanmin(loads):.2f} / "
        f"{np.nanmean(loads):.2f} / {np.nanmax(loads):.2f}.",
        f"Command: `.venv/bin/python bench/bench_live_soak.py {cmdline}` (the house route driven "
        "again and again while mapping; resident memory of the live process and of each child "
        "sampled from outside).",
        "",
        f"Memory after the warm-up ({warmup_min:g} min): baseline = mean of the first minute "
        "after it, end = mean of the last minute, peak after it; target growth < "
        f"{GROWTH_TARGET:.0%} (judged on the peak).",
        "",
        "| process | RSS baseline / end / peak | growth to end / to peak | slope per 10 min | "
        "target |",
        "| --- | --- | --- | --- | --- |",
        *rows,
        "",
        "| measure | result |",
        "| --- | --- |",
        f"| run | {s['wall_s']:.0f} s; route laps {c.get('route_laps', 0)}, waypoints reached "
        f"{c.get('waypoints_reached', 0)} |",
        f"| camera frames rendered / received / processed | {sim.get('frames_rendered')} / "
        f"{c.get('frames_received', 0)} / {c.get('frames_processed', 0)} |",
        f"| frames dropped: front end (target 0) / camera side (not taken in time) | "
        f"{dropped} / {sim.get('frames_dropped_camera')} |",
        f"| VO skipped on a frame because another was waiting | {c.get('vo_skipped_behind', 0)} |",
        f"| frame-to-pose latency p50 / p99 / max (target p99 <= {LATENCY_P99_TARGET_MS:.0f}) | "
        f"{lat.get('p50')} / {p99} / {lat.get('max')} ms "
        f"({lat.get('samples')} frames, {lat.get('kept')} kept for percentiles) |",
        f"| median ms per stage | "
        f"{', '.join(f'{k} {v}' for k, v in (s.get('stage_ms_median') or {}).items())} |",
        f"| scans the mapper holds / keyframes | {mp.get('scans_used')} / {mp.get('keyframes')} |",
        f"| SLAM ATE vs truth, SE(2)-aligned | "
        f"{(s.get('slam_vs_groundtruth') or {}).get('ate_rmse_aligned_m')} m |",
        f"| errors | {'; '.join(s['errors']) or 'none'} |",
        "",
        *blocks_table(s.get("frames_timeline"), max(60.0, 60 * round(minutes / 6))),
        f"Targets: 0 frames dropped {'met' if dropped == 0 else '**not met**'}; latency p99 "
        f"{'met' if p99 is not None and p99 <= LATENCY_P99_TARGET_MS else '**not met**'}; memory "
        f"{'met' if growth_ok else '**not met**'} (drops and latency only count on idle cores).",
    ]
    return "\n".join(lines)


def blocks_table(timeline: list[list[Any]] | None, block_s: float) -> list[str]:
    """Markdown lines: frames, drops and window latency p99 per block of the run (none for a
    summary without ``frames_timeline``)."""
    if not timeline:
        return []
    rows = [
        f"| {b['from_s'] / 60:g}-{b['to_s'] / 60:g} min | {b['processed']} | {b['dropped']} | "
        f"{b['p99_median_ms']} / {b['p99_worst_ms']} ms |"
        for b in frame_blocks(timeline, block_s)
    ]
    return [
        "Frames over the run (the run's `frames_timeline`: latency p99 per 5-s window):",
        "",
        "| part of the run | frames processed | dropped | window p99: median / worst |",
        "| --- | --- | --- | --- |",
        *rows,
        "",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="soak length [min]")
    ap.add_argument("--sample", type=float, default=10.0, help="memory sample period [s]")
    ap.add_argument("--warmup-minutes", type=float, default=5.0)
    ap.add_argument("--run-dir", type=Path, default=REPO / "runs" / "bench_live_soak_1h")
    ap.add_argument("--out", type=Path, default=None, help="markdown file to update")
    ap.add_argument("--section", default="live-soak-1h")
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="no run: report the soak already in --run-dir (summary.json, soak_memory.json)",
    )
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        help="config override for the live run (section.key=value; repeatable)",
    )
    args = ap.parse_args()
    if args.minutes <= 0 or args.sample <= 0:
        sys.exit("error: --minutes and --sample must be > 0")
    extra = [a for o in args.overrides for a in ("--set", o)]
    if args.report_only:
        try:
            s = json.loads((args.run_dir / "summary.json").read_text())
            rec = json.loads((args.run_dir / "soak_memory.json").read_text())
        except (OSError, ValueError) as err:
            sys.exit(f"error: no finished soak in {args.run_dir}: {err}")
    else:
        s, rec = soak(args.run_dir, args.minutes * 60, args.sample, extra)
    cmdline = (
        f"--minutes {args.minutes:g} --sample {args.sample:g} "
        f"--warmup-minutes {args.warmup_minutes:g}" + "".join(f" --set {o}" for o in args.overrides)
    )
    publish(report(s, rec, args.minutes, args.warmup_minutes, cmdline), args.out, args.section)


if __name__ == "__main__":
    main()
