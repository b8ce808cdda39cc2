"""Visual-odometry settings against the real fr3 cabinet pairs: success, accuracy and ms/frame.

Run: ``.venv/bin/python bench/sweep_vo.py`` (needs ../shared/data). Each row changes one or two
settings from the default; "per-frame" is the stateful odometry's median over the keyframes.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench_vo as vo_bench  # noqa: E402  (bench/ is on sys.path)

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
    ]


def main() -> None:
    frames, gt = vo_bench.load_cabinet()
    print(
        "| setting | success | median t [cm] | median r [deg] | wrong but accepted | per-frame [ms] |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for name, cfg, tuning in variants():
        r = vo_bench.bench_cabinet(cfg, tuning, frames, gt)
        pf = vo_bench.bench_per_frame(cfg, tuning, frames, repeats=2)
        print(f"| {name} | {100 * r['success']:.0f} % | {r['t_med_cm']:.2f} | "
              f"{r['r_med_deg']:.2f} | {r['bad_accepted']} | {pf['ms_med']:.1f} |")  # fmt: skip


if __name__ == "__main__":
    main()
