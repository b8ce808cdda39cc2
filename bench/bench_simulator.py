"""Simulator throughput at 640x480: render-only frames/s and end-to-end recording frames/s.

Run: ``make bench`` (or ``.venv/bin/python bench/bench_simulator.py --out docs/benchmarks.md``).
Results replace the "simulator" section of the output markdown file, stamped with date and machine.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import re
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sensors.config import CameraConfig, RobotConfig, SimConfig  # noqa: E402
from sensors.sim.motion import drive_route  # noqa: E402
from sensors.sim.render import KinectRenderer  # noqa: E402
from sensors.sim.simulator import simulate  # noqa: E402
from sensors.sim.world import load_world  # noqa: E402

TARGET_FPS = 30.0  # [frames/s] issue 3 target on a 2-core machine
SECTION = "simulator"


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import open3d

    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"numpy {np.__version__}, open3d {open3d.__version__}")  # fmt: skip


def bench_render(world_path: Path, frames: int) -> dict[str, float]:
    world = load_world(world_path)
    sim = SimConfig()
    traj = drive_route(world, sim)
    idx = np.linspace(0, len(traj.t_ns) - 1, frames).round().astype(int)
    renderer = KinectRenderer(world, CameraConfig(), RobotConfig(), sim)
    rng = np.random.default_rng(0)
    renderer.render(traj.x[0], traj.y[0], traj.yaw[0], rng)  # warm-up
    cast, full = [], []
    for i in idx:
        t0 = time.perf_counter()
        renderer.cast(traj.x[i], traj.y[i], traj.yaw[i])
        t1 = time.perf_counter()
        renderer.render(traj.x[i], traj.y[i], traj.yaw[i], rng)
        t2 = time.perf_counter()
        cast.append(t1 - t0)
        full.append(t2 - t1)
    return {
        "render_ms_median": 1e3 * float(np.median(full)),
        "render_ms_p95": 1e3 * float(np.percentile(full, 95)),
        "raycast_ms_median": 1e3 * float(np.median(cast)),
        "render_fps": 1.0 / float(np.median(full)),
    }


def bench_simulate(world_path: Path, frames: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = simulate(world_path, Path(tmp) / "rec", RobotConfig(), CameraConfig(),
                           SimConfig(), seed=0, frames=frames)  # fmt: skip
        wall = time.perf_counter() - t0
    return {"simulate_fps": summary.frames / wall, "simulate_wall_s": wall}


def write_section(out: Path, body: str) -> None:
    text = out.read_text() if out.exists() else "# rgbdnav benchmarks\n"
    start, end = f"<!-- {SECTION}:start -->", f"<!-- {SECTION}:end -->"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text:
        text = re.sub(re.escape(start) + ".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--world", type=Path, default=REPO / "scenes" / "house.yaml")
    ap.add_argument("--frames", type=int, default=60, help="frames per measurement")
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    args = ap.parse_args()

    r = bench_render(args.world, args.frames)
    s = bench_simulate(args.world, args.frames)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    verdict = "meets" if r["render_fps"] >= TARGET_FPS else "misses"
    body = f"""## Simulator ({args.world.name}, 640x480)

Measured {dt.date.today().isoformat()} on {machine()}.
Command: `make bench` (`python bench/bench_simulator.py --frames {args.frames}`).

| figure | value |
| --- | --- |
| render only, median | {r["render_ms_median"]:.1f} ms/frame = **{r["render_fps"]:.1f} frames/s** ({verdict} the {TARGET_FPS:.0f} frames/s target) |
| render only, 95th percentile | {r["render_ms_p95"]:.1f} ms/frame |
| of which Open3D ray cast, median | {r["raycast_ms_median"]:.1f} ms/frame |
| end to end (render + PNG encode + write) | {s["simulate_fps"]:.1f} frames/s ({args.frames} frames in {s["simulate_wall_s"]:.1f} s, incl. start-up) |
| peak resident memory | {peak_mb:.0f} MB |
"""
    print(body)
    if args.out:
        write_section(args.out, body)
        print(f"updated {args.out}")


if __name__ == "__main__":
    main()
