"""`rgbdnav fleet align` on real logs: each log cut into two overlapping robots (the second's
odometry moved by SHIFT), both mapped with `rgbdnav map`, aligned with no guess; plus pairs of
maps of different buildings, which must be refused. Prints a markdown table.

    python bench/bench_fleet_align.py WORK_DIR   # reuses WORK_DIR/<log>/run_{a,b}/map if there

The reference for the recovered transform is the median of pose_a (+) pose_b^-1 over the
keyframes both maps hold (the same scans); the odometry shift is a looser check (each map's frame
drifts from its odometry).
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from fleet_split_log import read_log_lines, split

from sensors.atomic import atomic_write_text
from slam.geometry import oplus, wrap_angle
from slam.map_align import align_maps
from slam.map_bundle import load_bundle, load_map

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LOGS = {"aces": DATA / "radish/aces-corrected.log.gz", "mit-csail": DATA / "carmen/mit-csail.clf"}
OTHER = DATA / "radish/orebro-corrected.log.gz"
SHIFT = np.array([80.0, -40.0, 2.0])  # [m, m, rad]


def _map(log: Path, out: Path) -> Path:
    if not (out / "map").is_dir():
        cmd = [sys.executable, "-m", "rgbdnav.cli", "map", str(log), "--out", str(out), "-q"]
        subprocess.run(cmd, check=True, capture_output=True)
    return out / "map"


def _inverse(p: np.ndarray) -> np.ndarray:
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    return np.stack(
        [-(c * p[..., 0] + s * p[..., 1]), s * p[..., 0] - c * p[..., 1], -p[..., 2]], axis=-1
    )


def _reference(a: Path, b: Path) -> tuple[np.ndarray, float]:
    ka, kb = load_bundle(a), load_bundle(b)
    _, ia, ib = np.intersect1d(ka.keyframe_stamps_ns, kb.keyframe_stamps_ns, return_indices=True)
    t = oplus(ka.keyframe_poses[ia], _inverse(kb.keyframe_poses[ib]))
    ref = np.array(
        [np.median(t[:, 0]), np.median(t[:, 1]), t[0, 2] + np.median(wrap_angle(t[:, 2] - t[0, 2]))]
    )
    spread = float(np.median(np.hypot(t[:, 0] - ref[0], t[:, 1] - ref[1])))
    return ref, spread


def _align(a: Path, b: Path) -> tuple[np.ndarray | None, str, float]:
    ma, mb = load_map(a), load_map(b)
    t0 = time.perf_counter()
    try:
        al = align_maps(ma.grid, mb.grid, (ma.occupied_thresh, mb.occupied_thresh))
    except Exception as err:  # a refusal is a result here
        return None, str(err), time.perf_counter() - t0
    return al.T_a_b, f"confidence {al.confidence:.2f}", time.perf_counter() - t0


def main() -> None:
    work = Path(sys.argv[1])
    rows = [
        "| pair | result | error vs keyframes (m / deg) | error vs shift (m / deg) | "
        "keyframe spread (m) | time (s) |",
        "|---|---|---|---|---|---|",
    ]
    maps = {}
    for name, log in LOGS.items():
        folder = work / name
        if not (folder / "b.log").is_file():
            folder.mkdir(parents=True, exist_ok=True)
            text_a, text_b = split(read_log_lines(log), 0.6, 0.4, SHIFT)
            atomic_write_text(folder / "a.log", text_a)
            atomic_write_text(folder / "b.log", text_b)
        a, b = _map(folder / "a.log", folder / "run_a"), _map(folder / "b.log", folder / "run_b")
        maps[name] = (a, b)
        got, what, secs = _align(a, b)
        ref, spread = _reference(a, b)
        known = _inverse(SHIFT)
        if got is None:
            rows.append(f"| {name} A-B | refused: {what} | | | {spread:.2f} | {secs:.1f} |")
            continue
        e_ref = (np.hypot(*(got[:2] - ref[:2])), abs(math.degrees(wrap_angle(got[2] - ref[2]))))
        e_sh = (np.hypot(*(got[:2] - known[:2])), abs(math.degrees(wrap_angle(got[2] - known[2]))))
        rows.append(
            f"| {name} A-B | {what} | {e_ref[0]:.2f} / {e_ref[1]:.2f} | "
            f"{e_sh[0]:.2f} / {e_sh[1]:.2f} | {spread:.2f} | {secs:.1f} |"
        )
    other = _map(OTHER, work / "orebro")
    pairs = [
        ("aces A - orebro", maps["aces"][0], other),
        ("mit-csail A - aces B", maps["mit-csail"][0], maps["aces"][1]),
        ("orebro - mit-csail B", other, maps["mit-csail"][1]),
    ]
    for label, a, b in pairs:
        got, what, secs = _align(a, b)
        verdict = "refused (right)" if got is None else f"WRONG: aligned {got.round(2)}"
        rows.append(f"| {label} | {verdict}: {what[:60]}... | | | | {secs:.1f} |")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
