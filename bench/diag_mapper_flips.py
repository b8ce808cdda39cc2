"""Which mapper decision flips between two runs that should agree? (issue #12)

Run: ``.venv/bin/python bench/diag_mapper_flips.py [--case aces] [--runs base Haswell noise1 ...]``.
Each run maps the case in a fresh process (as ``bench_mapper_stability.py`` does) with the
mapper's decision trace on (``Mapper.decisions``): every sequential match (ICP from odometry or
the correlative search, and its verdict), every loop-closure candidate (match verdict, rival /
best ratio, chi-square after optimising) and the final vote. The first run is the baseline; for
every other run the first decision whose *outcome* differs is printed with the numbers both runs
took it on (the margin to the threshold), then how many outcomes differ in all.

Run names: ``base`` (default kernels), a core type (``Prescott``, ``Sandybridge``, ``Haswell``),
``noise1``..``noise3`` (1e-6 m range noise, that seed), ``f32`` (float32 ranges).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench_mapper  # noqa: E402  (bench/ is on sys.path)
import bench_mapper_stability  # noqa: E402

# The thresholds the traced numbers are compared with (MapperConfig defaults).
AMBIGUOUS, HOLD = 0.9, 0.8


def spec_of(case: str, run: str) -> tuple[bench_mapper.CaseSpec, str | None]:
    base = bench_mapper.CaseSpec(case, trace=True)
    if run.startswith("noise"):
        return dataclasses.replace(base, range_noise_m=1e-6, noise_seed=int(run[5:])), None
    if run == "f32":
        return dataclasses.replace(base, float32_ranges=True), None
    return base, None if run == "base" else run


def outcome(row: tuple[Any, ...]) -> tuple[Any, ...]:
    """The discrete part of a decision: what two stable runs must agree on."""
    kind = row[0]
    if kind == "rival":
        ratio = row[3]
        band = "ambiguous" if ratio > AMBIGUOUS else "held" if ratio > HOLD else "unique"
        return (kind, row[1], row[2], band)
    if kind == "chi2":
        return row[:4]
    if kind == "vote":
        return row
    return row[:3]  # track: (kind, scan, verdict); loop: (kind, k, j, verdict)


def fmt(row: tuple[Any, ...]) -> str:
    return " ".join(
        f"{v:.4f}" if isinstance(v, float) and math.isfinite(v) else str(v) for v in row
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--case", default="aces")
    ap.add_argument("--runs", nargs="+", default=["base", "Sandybridge", "Prescott", "noise1"])
    args = ap.parse_args()
    results: dict[str, dict[str, Any]] = {}
    for name in args.runs:
        spec, core = spec_of(args.case, name)
        results[name] = bench_mapper_stability.run(spec, core)
        r = results[name]
        lc = r["counts"]["loop_closures"]
        print(
            f"{name}: mean {r['after']['t_mean']:.4f} m, loops {lc['proposed']}/"
            f"{lc['accepted']}/{lc['rejected']}, {len(r['decisions'])} decisions",
            flush=True,
        )
    first = args.runs[0]
    a = results[first]["decisions"]
    for name in args.runs[1:]:
        b = results[name]["decisions"]
        oa, ob = [outcome(r) for r in a], [outcome(r) for r in b]
        diverge = next((i for i, (x, y) in enumerate(zip(oa, ob, strict=False)) if x != y), None)
        print(f"\n== {first} vs {name}")
        if diverge is None:
            print(f"same outcomes over {min(len(a), len(b))} decisions")
            continue
        for i in range(max(0, diverge - 3), min(diverge + 4, len(a), len(b))):
            mark = ">>" if i == diverge else "  "
            print(f"{mark} {fmt(a[i]):60s} | {fmt(b[i])}")
        differing = sum(x != y for x, y in zip(oa, ob, strict=False))
        print(f"outcomes differing after the first flip (aligned by index): {differing}")
        # Before the flip the runs took the same decisions on slightly different numbers: the
        # smallest margins tell which thresholds are close to flipping.
        gaps = [
            (abs(x[3] - y[3]), fmt(x), fmt(y))
            for x, y in zip(a[:diverge], b[:diverge], strict=True)
            if x[0] in ("track", "loop") and isinstance(x[3], float)
        ]
        gaps.sort(reverse=True)
        for g, x, y in gaps[:3]:
            print(f"   largest response change before the flip {g:.2e}: {x} | {y}")


if __name__ == "__main__":
    main()
