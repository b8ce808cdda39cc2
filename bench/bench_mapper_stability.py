"""Does the map depend on the CPU or on noise far below any sensor's? (issue #12)

Run: ``.venv/bin/python bench/bench_mapper_stability.py [--out docs/benchmarks.md] [--only aces]
[--runs Haswell noise1 ...]`` (``--runs``: a subset of the runs below, to screen a change).
Each Radish case of ``bench_mapper`` is mapped again, each run in a fresh process, under:

1. every OpenBLAS kernel set this CPU can run (``OPENBLAS_CORETYPE``: the BLAS calls' rounding
   differs between them, as it does between an Intel and an AMD machine);
2. 1e-6 m of Gaussian noise on every range (three seeds), with the default kernels;
3. ranges rounded to float32.

The global result (mean relative-pose error over random pairs against the corrected poses)
should move by < 2 cm across all of them. Results replace the "mapper_stability" section.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import os
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench_mapper  # noqa: E402  (bench/ is on sys.path)
from common import machine, publish  # noqa: E402

SECTION = "mapper_stability"
TARGET_SPREAD_M = 0.02  # [m] issue #12: the global result moves by less than this
NOISE_M = 1e-6  # [m] range perturbation
NOISE_SEEDS = (1, 2, 3)
CASES = ("aces", "seattle")


def core_types() -> list[str]:
    """OpenBLAS kernel sets (oldest first) whose instructions this CPU has."""
    flags = set()
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            break
    kinds = [
        ("Prescott", "sse3"),
        ("Sandybridge", "avx"),
        ("Haswell", "avx2"),
        ("SkylakeX", "avx512f"),
    ]
    return [name for name, flag in kinds if flag in flags or (flag == "sse3" and "pni" in flags)]


def run(spec: bench_mapper.CaseSpec, coretype: str | None) -> dict[str, Any]:
    """One case in a fresh process whose OpenBLAS picks ``coretype`` (None: its own choice)."""
    saved = os.environ.get("OPENBLAS_CORETYPE")
    try:
        if coretype is None:
            os.environ.pop("OPENBLAS_CORETYPE", None)
        else:
            os.environ["OPENBLAS_CORETYPE"] = coretype
        return bench_mapper.in_fresh_process(spec)
    finally:
        os.environ.pop("OPENBLAS_CORETYPE", None)
        if saved is not None:
            os.environ["OPENBLAS_CORETYPE"] = saved


def table(name: str, rows: list[tuple[str, dict[str, Any]]]) -> str:
    means = [r["after"]["t_mean"] for _, r in rows]
    spread = max(means) - min(means)
    verdict = "meets" if spread < TARGET_SPREAD_M else "misses"
    verdict = (
        f"{verdict} the {100 * TARGET_SPREAD_M:.0f} cm target" if len(rows) > 1 else "no spread"
    )
    lines = [
        f"**{name}**: spread of the mean pair error **{100 * spread:.1f} cm** over "
        f"{len(rows)} runs ({verdict}); "
        f"worst {max(means):.3f} m, pairs > 1 m at most "
        f"{max(r['after']['broken'] for _, r in rows):.1%}.",
        "",
        "| run | mean / median [m] | rot mean [deg] | pairs > 1 m | loops prop. / acc. / rej. "
        "| readmitted / outvoted by the vote |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for label, r in rows:
        a, lc = r["after"], r["counts"]["loop_closures"]
        lines.append(
            f"| {label} | {a['t_mean']:.3f} / {a['t_median']:.3f} | {a['r_mean']:.2f} "
            f"| {a['broken']:.1%} | {lc['proposed']} / {lc['accepted']} / {lc['rejected']} "
            f"| {lc.get('readmitted', 0)} / {lc.get('outvoted', 0)} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    ap.add_argument("--only", nargs="+", choices=CASES, default=list(CASES))
    ap.add_argument(
        "--runs",
        nargs="+",
        help="only these runs: kernel set names, noiseN (seed N), float32 (default: all)",
    )
    args = ap.parse_args()
    missing = [
        str(bench_mapper.RADISH[n]) for n in args.only if not bench_mapper.RADISH[n].is_file()
    ]
    if missing:
        sys.exit(f"benchmark logs not found: {', '.join(missing)}")
    known = {*core_types(), *(f"noise{n}" for n in NOISE_SEEDS), "float32"}
    if args.runs and not set(args.runs) <= known:
        sys.exit(f"error: unknown run(s) {sorted(set(args.runs) - known)}; known: {sorted(known)}")

    def wanted(label: str) -> bool:
        return not args.runs or label in args.runs

    parts = [
        f"""## Mapper stability: CPUs and tiny perturbations (issue #12)

Measured {dt.date.today().isoformat()} on {machine("numpy", "scipy")}.
Command: `python bench/bench_mapper_stability.py{"" if list(args.only) == list(CASES) else " --only " + " ".join(args.only)}{" --runs " + " ".join(args.runs) if args.runs else ""}`.
The corrupted-odometry Radish cases of `bench_mapper.py`, each run in a fresh process under every
OpenBLAS kernel set the CPU runs (`OPENBLAS_CORETYPE`), with {NOISE_M:g} m of range noise
(seeds {", ".join(map(str, NOISE_SEEDS))}) and with float32 ranges. Target: the mean pair error
moves by < {100 * TARGET_SPREAD_M:.0f} cm."""
    ]
    for name in args.only:
        rows: list[tuple[str, dict[str, Any]]] = []
        base = bench_mapper.CaseSpec(name)
        for ct in core_types():
            if wanted(f"{ct}"):
                rows.append((f"OPENBLAS_CORETYPE={ct}", run(base, ct)))
                print(f"{name} {ct}: {rows[-1][1]['after']['t_mean']:.3f}", file=sys.stderr)
        for seed in NOISE_SEEDS:
            if wanted(f"noise{seed}"):
                spec = dataclasses.replace(base, range_noise_m=NOISE_M, noise_seed=seed)
                rows.append((f"range noise {NOISE_M:g} m, seed {seed}", run(spec, None)))
                print(f"{name} noise {seed}: {rows[-1][1]['after']['t_mean']:.3f}", file=sys.stderr)
        if wanted("float32"):
            f32 = dataclasses.replace(base, float32_ranges=True)
            rows.append(("float32 ranges", run(f32, None)))
        parts.append(table(name, rows))
    publish("\n\n".join(parts) + "\n", args.out, SECTION)


if __name__ == "__main__":
    main()
