"""Where `rgbdnav map` spends its CPU: seconds of CPU per pipeline stage, on whichever thread runs it.

Run: ``.venv/bin/python bench/profile_map_cpu.py SOURCE [map options...]``, e.g.
``bench/profile_map_cpu.py REC --out /tmp/run`` with REC from ``rgbdnav simulate scenes/house.yaml
--frames 450 --out REC``. The map runs in this process with a ``time.thread_time()`` accumulator
around each stage function (each runs on one thread, so the difference is that stage's own CPU,
waits for other threads excluded). On a loaded machine a profiler's wall times count the time a
thread waited for a core; these do not, which is why docs/design/speed.md ("Session 16") quotes
them. Nested stages are counted in their parents too. A world file's renderer runs in another
process and is not counted here (``bench/bench_map_speed.py --world`` gives its CPU in the total).
"""

from __future__ import annotations

import importlib
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

# (module, function or Class.method): the stages of docs/design/speed.md's table
STAGES = (
    ("sensors.images", "read_image"),
    ("sensors.images", "decode_image"),
    ("slam.visual_odometry", "extract_features"),
    ("slam.visual_odometry", "_detect_upper"),
    ("slam.visual_odometry", "motion_from_features"),
    ("slam.visual_odometry", "knn_candidates"),
    ("slam.visual_odometry", "_refine"),
    ("slam.visual_odometry", "refine_rgbd"),
    ("slam.visual_odometry", "guided_matches"),
    ("slam.visual_odometry", "rigid_ransac"),
    ("slam.front_end", "FrontEnd.frame"),
    ("slam.front_end", "MessageFeed.until"),
    ("slam.depth_to_scan", "DepthToScan.__call__"),
    ("slam.mapper", "Mapper.add_scan"),
)

cpu: Counter[str] = Counter()
calls: Counter[str] = Counter()
_lock = threading.Lock()


def _timed(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            dt = time.thread_time() - t0
            with _lock:
                cpu[name] += dt
                calls[name] += 1

    return wrapper


def instrument() -> None:
    """Wrap every stage where its callers look it up (module globals, class attributes)."""
    for module_name, qual in STAGES:
        owner: Any = importlib.import_module(module_name)
        *path, attr = qual.split(".")
        for part in path:
            owner = getattr(owner, part)
        setattr(owner, attr, _timed(qual, getattr(owner, attr)))


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1].startswith("-"):
        print(__doc__.splitlines()[2], file=sys.stderr)
        return 2
    instrument()
    from rgbdnav.cli import main as cli_main

    t0 = time.process_time()
    sys.argv = ["rgbdnav", "map", *sys.argv[1:], "-q"]
    try:
        cli_main()
    except SystemExit as done:
        if done.code:
            return int(done.code) if isinstance(done.code, int) else 1
    total = time.process_time() - t0
    print(f"\nprocess CPU {total:.2f} s (all threads of this process)")
    print("| stage | CPU [s] | calls | per call [ms] | share |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, s in cpu.most_common():
        print(
            f"| `{name}` | {s:.2f} | {calls[name]} | {s / calls[name] * 1e3:.2f} "
            f"| {100 * s / total:.0f} % |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
