"""Visual-odometry settings against the real fr3 cabinet pairs: success, accuracy and ms/frame.

Run: ``.venv/bin/python bench/sweep_vo.py [--draws N]`` (needs ../shared/data). Each row changes
one or two settings from the default; "per-frame" is the stateful odometry's median over the
keyframes.

OpenCV seeds ``solvePnPRansac`` identically on every call, so one run scores one fixed RANSAC
draw per pair, and with 28 pairs one lucky or unlucky pair moves the success rate by 3.6 %.
``--draws N`` also scores N other draws (the correspondences handed to RANSAC in a seeded random
order) and reports the mean and range: compare settings on that, not on the fixed draw.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench_vo as vo_bench  # noqa: E402  (bench/ is on sys.path)

import slam.visual_odometry as vo_module  # noqa: E402
from slam.config import VoConfig  # noqa: E402  (type of the variants)
from slam.visual_odometry import VoTuning  # noqa: E402


def variants() -> list[tuple[str, VoConfig, VoTuning]]:
    base = vo_bench.WIDE  # the cabinet keyframes are up to 0.22 m apart: wide-baseline limits

    def cfg(**kw: object) -> VoConfig:
        return dataclasses.replace(base, **kw)

    return [
        ("default", base, VoTuning()),
        ("max_features 700", cfg(max_features=700), VoTuning()),
        ("max_features 500", cfg(max_features=500), VoTuning()),
        ("RANSAC 80 iterations", cfg(ransac_iterations=80), VoTuning()),
        ("4 Gauss-Newton steps", base, VoTuning(refine_iterations=4)),
        (
            "700 features, 100 it., 4 GN",
            cfg(max_features=700, ransac_iterations=100),
            VoTuning(refine_iterations=4),
        ),  # fmt: skip
        ("detect_factor 1.2", base, VoTuning(detect_factor=1.2)),
        ("6 pyramid levels", base, VoTuning(orb_levels=6)),
        ("FAST threshold 8", base, VoTuning(fast_threshold=8)),
        ("700 features, 6 levels", cfg(max_features=700), VoTuning(orb_levels=6)),
    ]


class _PermutedPnp:
    """Stands in for the ``cv2`` module inside slam.visual_odometry: ``solvePnPRansac`` gets its
    correspondences in a seeded random order (another RANSAC draw); inlier indices are mapped
    back. Everything else is cv2's."""

    def __init__(self, cv2_module: Any, seed: int) -> None:
        self._cv2 = cv2_module
        self._rng = np.random.default_rng(seed)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._cv2, name)

    def solvePnPRansac(self, obj: np.ndarray, img: np.ndarray, *args: Any, **kw: Any) -> Any:  # noqa: N802
        p = self._rng.permutation(len(obj))
        ok, rvec, tvec, inl = self._cv2.solvePnPRansac(obj[p], img[p], *args, **kw)
        if inl is not None:
            inl = p[inl.ravel()].reshape(-1, 1)
        return ok, rvec, tvec, inl


@contextlib.contextmanager
def ransac_draw(seed: int) -> Iterator[None]:
    real = vo_module.cv2
    vo_module.cv2 = _PermutedPnp(real, seed)  # type: ignore[assignment]
    try:
        yield
    finally:
        vo_module.cv2 = real


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--draws", type=int, default=0, help="extra RANSAC draws scored per setting")
    ap.add_argument("--only", default="", help="comma-separated variant indices to run")
    args = ap.parse_args()
    frames, gt = vo_bench.load_cabinet()
    chosen = variants()
    if args.only:
        chosen = [chosen[int(i)] for i in args.only.split(",")]
    draws_head = " draws: success mean (range) | draws: median t mean [cm] |" if args.draws else ""
    print(f"| setting | success | median t [cm] | median r [deg] | wrong but accepted | "
          f"per-frame [ms] |{draws_head}")  # fmt: skip
    print("| --- " * (6 + 2 * bool(args.draws)) + "|")
    for name, cfg, tuning in chosen:
        r = vo_bench.bench_cabinet(cfg, tuning, frames, gt)
        pf = vo_bench.bench_per_frame(cfg, tuning, frames, repeats=2)
        row = (f"| {name} | {100 * r['success']:.0f} % | {r['t_med_cm']:.2f} | "
               f"{r['r_med_deg']:.2f} | {r['bad_accepted']} | {pf['ms_med']:.1f} |")  # fmt: skip
        if args.draws:
            success, median = [], []
            for seed in range(args.draws):
                with ransac_draw(seed):
                    d = vo_bench.bench_cabinet(cfg, tuning, frames, gt)
                success.append(100 * d["success"])
                median.append(d["t_med_cm"])
            row += (f" {np.mean(success):.1f} % ({min(success):.0f}-{max(success):.0f}) | "
                    f"{np.mean(median):.2f} |")  # fmt: skip
        print(row, flush=True)


if __name__ == "__main__":
    main()
