"""Per-frame VO time of the current code against slam/visual_odometry.py at an older commit, on
the real cabinet keyframes, interleaved old/new per repetition (same machine state for both).

    python bench/vo_before_after.py f794272^ --reps 5

Wall ms is VoResult.ms with OpenCV's default threads; CPU ms is process time with one thread.
Prints medians and the paired new/old ratio; writes nothing."""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO))

import bench_vo as b  # noqa: E402

import slam.visual_odometry as new  # noqa: E402


def module_at(rev: str, tmp: Path) -> ModuleType:
    """slam/visual_odometry.py as it was at ``rev``, imported under another name."""
    src = subprocess.run(
        ["git", "-C", str(REPO), "show", f"{rev}:slam/visual_odometry.py"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = tmp / "vo_old.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("vo_old", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["vo_old"] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("rev", help="git revision of the old slam/visual_odometry.py")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    frames, _ = b.load_cabinet()

    def wall(mod: ModuleType) -> float:
        vo = mod.VisualOdometry(
            frames[0].intrinsics, b.WIDE, tuning=mod.VoTuning(), keyframes=False
        )
        return float(np.median([vo.process(f).ms for f in frames][1:]))

    def cpu(mod: ModuleType) -> float:
        vo = mod.VisualOdometry(
            frames[0].intrinsics, b.WIDE, tuning=mod.VoTuning(), keyframes=False
        )
        ts = []
        for f in frames:
            t = time.process_time()
            vo.process(f)
            ts.append((time.process_time() - t) * 1e3)
        return float(np.median(ts[1:]))

    with tempfile.TemporaryDirectory() as tmp:
        old = module_at(args.rev, Path(tmp))
        threads = cv2.getNumThreads()
        runs: dict[str, list[float]] = {
            k: [] for k in ("wall old", "wall new", "cpu old", "cpu new")
        }
        for _ in range(args.reps):
            cv2.setNumThreads(threads)
            runs["wall old"].append(wall(old))
            runs["wall new"].append(wall(new))
            cv2.setNumThreads(1)
            runs["cpu old"].append(cpu(old))
            runs["cpu new"].append(cpu(new))
    for k, v in runs.items():
        print(f"{k:9s} median {np.median(v):5.1f} ms/frame  (runs {min(v):.1f}-{max(v):.1f})")
    w = np.array(runs["wall new"]) / np.array(runs["wall old"])
    c = np.array(runs["cpu new"]) / np.array(runs["cpu old"])
    print(f"paired new/old ratio: wall {np.median(w):.2f}, cpu {np.median(c):.2f}")


if __name__ == "__main__":
    main()
