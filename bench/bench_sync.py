"""Sync statistics on a simulated recording with jitter and drops, and synchronise() throughput.

Run: ``.venv/bin/python bench/bench_sync.py [--out docs/benchmarks.md]``.
With ``--out``, results replace the "sync" section of the markdown file, stamped with date and
machine.

The simulator writes identical rgb and depth stamps (one capture, two images), so the bench
perturbs the depth stamps itself (Gaussian jitter, independent drops) to give the
approximate-time matcher something to do. Wheel readings (50 Hz) are not set-matched but
interpolated to the matched rgb stamps.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import machine, publish  # noqa: E402  (bench/ is on sys.path)

from sensors.config import CameraConfig, RobotConfig, SimConfig, SyncConfig  # noqa: E402
from sensors.recording import Recording  # noqa: E402
from sensors.sim.simulator import simulate  # noqa: E402
from sensors.sync import SyncStats, interpolate_wheels, synchronise  # noqa: E402
from sensors.types import NS_PER_S  # noqa: E402

SECTION = "sync"
MS = 1_000_000  # [ns]
SIM_JITTER = 0.005  # [s] camera stamp jitter sigma in the simulator
SIM_DROP = 0.05  # simulator frame drop probability (rgb and depth together)
DEPTH_JITTER_NS = 3 * MS  # [ns] extra depth-only stamp jitter sigma, added here
DEPTH_DROP = 0.02  # extra depth-only drop probability, added here
SYNTHETIC_STAMPS = 100_000  # total stamps for the throughput figure
CAMERA_PERIOD_NS = NS_PER_S // 30  # [ns] 30 Hz


def perturb(stamps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Extra per-stream jitter and independent drops (file order kept: no re-sorting)."""
    jittered = stamps + np.round(rng.normal(0.0, DEPTH_JITTER_NS, stamps.size)).astype(np.int64)
    return jittered[rng.random(stamps.size) >= DEPTH_DROP]


@dataclass(frozen=True)
class RecordingResult:
    stats: SyncStats
    sim_dropped: int  # frames the simulator dropped (rgb and depth together)
    sim_wall_s: float  # [s] time to simulate the recording
    wheel_readings: int
    images: int  # matched rgb stamps the wheels were interpolated to
    wheels_ok: int  # of those, bracketed by readings no further apart than the gap


def bench_recording(world: Path, frames: int, cfg: SyncConfig) -> RecordingResult:
    sim = SimConfig(stamp_jitter=SIM_JITTER, frame_drop_probability=SIM_DROP)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = simulate(
            world, Path(tmp) / "rec", RobotConfig(), CameraConfig(), sim, seed=0, frames=frames
        )
        sim_wall = time.perf_counter() - t0
        rec = Recording.open(Path(tmp) / "rec")
        rgb, depth = rec.rgb_stamps_ns.copy(), rec.depth_stamps_ns.copy()
        wheel_t, left, right = rec.wheels()
    depth = perturb(depth, np.random.default_rng(0))
    slop_ns = round(cfg.slop * NS_PER_S)
    index, stats = synchronise(
        {"rgb": rgb, "depth": depth}, slop_ns, cfg.queue_size, warn_fraction=cfg.warn_fraction
    )
    images = rgb[index["rgb"]]
    gap_ns = round(cfg.max_interpolation_gap * NS_PER_S)
    _, _, ok = interpolate_wheels(wheel_t, left, right, images, gap_ns)
    return RecordingResult(
        stats,
        summary.dropped_frames,
        sim_wall,
        int(wheel_t.size),
        int(images.size),
        int(np.count_nonzero(ok)),
    )


def synthetic_streams(total: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Two 30 Hz streams, 2 ms jitter, 3 % independent drops, ``total`` stamps in all."""
    n = total // 2
    frames = int(n / 0.9)  # enough frames that n survive the drops
    base = np.arange(frames, dtype=np.int64) * CAMERA_PERIOD_NS
    streams = {}
    for name in ("rgb", "depth"):
        t = base + np.round(rng.normal(0.0, 2 * MS, frames)).astype(np.int64)
        streams[name] = t[rng.random(frames) >= 0.03][:n]
    return streams


def bench_throughput(cfg: SyncConfig) -> dict[str, float]:
    streams = synthetic_streams(SYNTHETIC_STAMPS, np.random.default_rng(1))
    pushed = sum(s.size for s in streams.values())
    slop_ns = round(cfg.slop * NS_PER_S)
    walls = []
    for _ in range(3):
        t0 = time.perf_counter()
        _, stats = synchronise(streams, slop_ns, cfg.queue_size)
        walls.append(time.perf_counter() - t0)
    wall = min(walls)
    wheel_t = np.arange(0, int(stats.streams["rgb"].received * CAMERA_PERIOD_NS), 20 * MS)
    counts = np.arange(wheel_t.size)
    images = streams["rgb"]
    t0 = time.perf_counter()
    interpolate_wheels(wheel_t, counts, counts, images, 200 * MS)
    interp_wall = time.perf_counter() - t0
    return {
        "pushed": pushed,
        "wall_s": wall,
        "rate": pushed / wall,
        "sets": stats.sets,
        "interp_ms": 1e3 * interp_wall,
        "interp_images": images.size,
    }


def table(stats: SyncStats) -> str:
    rows = [
        "| stream | received | matched | out_of_order | duplicate | stale | unmatched (of which overflow) | matched fraction |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, s in stats.streams.items():
        rows.append(
            f"| {name} | {s.received} | {s.matched} | {s.out_of_order} | {s.duplicate} | "
            f"{s.stale} | {s.unmatched} ({s.overflow}) | {100 * s.matched / s.received:.1f} % |"
        )
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--world", type=Path, default=REPO / "scenes" / "house.yaml")
    ap.add_argument("--frames", type=int, default=600, help="frames to simulate")
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    args = ap.parse_args()

    cfg = SyncConfig()
    r = bench_recording(args.world, args.frames, cfg)
    t = bench_throughput(cfg)
    stats = r.stats
    body = f"""## Sync ({args.world.name}, {args.frames} frames)

Measured {dt.date.today().isoformat()} on {machine("numpy")}.
Command: `python bench/bench_sync.py --frames {args.frames}`.
Sync config: queue_size {cfg.queue_size}, slop {cfg.slop * 1e3:.0f} ms, max_interpolation_gap {cfg.max_interpolation_gap * 1e3:.0f} ms.

Recording: simulator with camera stamp jitter {SIM_JITTER * 1e3:.0f} ms and frame drop probability {SIM_DROP:.0%}
({r.sim_dropped} frames dropped, rgb and depth together; simulated in {r.sim_wall_s:.0f} s).
The simulator gives rgb and depth identical stamps, so this bench adds depth-only jitter
N(0, {DEPTH_JITTER_NS / MS:.0f} ms) and drops {DEPTH_DROP:.0%} of depth frames independently before matching.

{table(stats)}
| wheels (interpolated to matched rgb) | {r.wheel_readings} readings | {r.wheels_ok} of {r.images} images | - | - | - | {r.images - r.wheels_ok} (gap or outside span) | {100 * r.wheels_ok / max(r.images, 1):.1f} % |

Sets: {stats.sets}, spread mean {stats.mean_spread_ns / MS:.2f} ms, max {stats.max_spread_ns / MS:.2f} ms; dropped fraction {stats.dropped_fraction:.1%} of all messages.

| throughput | value |
| --- | --- |
| `synchronise` on {t["pushed"]} synthetic stamps (2 streams, 30 Hz, 2 ms jitter, 3 % drops) | {t["wall_s"] * 1e3:.0f} ms = {t["rate"] / 1e3:.0f} k stamps/s ({t["sets"]} sets) |
| `interpolate_wheels` to {t["interp_images"]} image stamps | {t["interp_ms"]:.1f} ms |
"""
    publish(body, args.out, SECTION)


if __name__ == "__main__":
    main()
