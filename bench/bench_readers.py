"""Reader throughput: RGB-D frames/s through RecordingSource and TumFolderSource (640x480 PNG
pairs decoded to RgbdFrame), and CARMEN log parse time (scans/s).

Run: ``.venv/bin/python bench/bench_readers.py [--out docs/benchmarks.md]``. A 300-frame simulated
recording is made at ``--recording`` (default /tmp/bench-rec) when it is not there yet. Each figure
is the best of ``--repeat`` passes with a warm page cache: decoding, not the disk, is measured.
Results replace the "readers" section of the output markdown file.
"""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import machine, publish  # noqa: E402  (bench/ is on sys.path)

from sensors.carmen import read_carmen_log  # noqa: E402
from sensors.recording import Recording  # noqa: E402
from sensors.recording_source import RecordingSource  # noqa: E402
from sensors.source import Source  # noqa: E402
from sensors.tum_folder import TumFolderSource  # noqa: E402

DATA = REPO.parent / "shared" / "data"
SECTION = "readers"
RECORDING_FRAMES = 300  # frames of the simulated recording


def ensure_recording(path: Path) -> None:
    """Simulate the house world into ``path`` unless a recording is already there."""
    if (path / "rgb.txt").is_file() and (path / "scene.yaml").is_file():
        return
    from sensors.config import CameraConfig, RobotConfig, SimConfig
    from sensors.sim.simulator import simulate

    print(f"simulating {RECORDING_FRAMES} frames into {path} ...", file=sys.stderr)
    simulate(
        REPO / "scenes" / "house.yaml",
        path,
        RobotConfig(),
        CameraConfig(),
        SimConfig(),
        seed=0,
        frames=RECORDING_FRAMES,
    )


def best_of(repeat: int, fn: Callable[[], int]) -> tuple[float, int]:
    """(fastest wall time [s], items of that pass) over ``repeat`` passes."""
    best, items = float("inf"), 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        items = fn()
        best = min(best, time.perf_counter() - t0)
    return best, items


def count_frames(make_source: Callable[[], object]) -> Callable[[], int]:
    def run() -> int:
        src: Source = make_source()  # type: ignore[assignment]
        n = 0
        for _frame in src.frames():  # one frame alive at a time
            n += 1
        return n

    return run


def bench_frames(recording: Path, repeat: int) -> list[tuple[str, float, int]]:
    """(label, seconds, frames) per reader."""
    rows = []
    cases: list[tuple[str, Callable[[], object]]] = [
        ("RecordingSource (sequential decode)", lambda: RecordingSource(Recording.open(recording))),
        ("TumFolderSource, 2 decode threads", lambda: TumFolderSource(recording, workers=2)),
        ("TumFolderSource, 1 decode thread", lambda: TumFolderSource(recording, workers=1)),
    ]
    cabinet = DATA / "kinect" / "tum_fr3_cabinet_keyframes"
    if cabinet.is_dir():
        cases.append(
            ("TumFolderSource on fr3 cabinet (JPEG + PNG)", lambda: TumFolderSource(cabinet))
        )
    for label, make in cases:
        count_frames(make)()  # warm the page cache
        seconds, frames = best_of(repeat, count_frames(make))
        rows.append((label, seconds, frames))
    return rows


def bench_carmen(repeat: int) -> list[tuple[str, float, int, int]]:
    """(log name, seconds, scans, beams) per CARMEN log present."""
    logs = [DATA / "carmen" / "mit-csail.clf", *sorted((DATA / "radish").glob("*.log.gz"))]
    rows = []
    for path in logs:
        if not path.is_file():
            continue
        holder: list[int] = []

        def parse(path: Path = path, holder: list[int] = holder) -> int:
            log = read_carmen_log(path)
            holder[:] = [sum(len(s.ranges) for s in log.scans)]
            return len(log.scans)

        seconds, scans = best_of(repeat, parse)
        rows.append((path.name, seconds, scans, holder[0]))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--recording", type=Path, default=Path("/tmp/bench-rec"))
    ap.add_argument("--repeat", type=int, default=3, help="passes per figure (best is kept)")
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)  # the Radish logs' junk ODOM stamps warn every pass

    ensure_recording(args.recording)
    frames = bench_frames(args.recording, args.repeat)
    carmen = bench_carmen(args.repeat)

    lines = [
        "## Readers",
        "",
        f"Measured {dt.date.today().isoformat()} on {machine('numpy', 'cv2')}.",
        f"Command: `python bench/bench_readers.py --repeat {args.repeat}`; best of "
        f"{args.repeat} passes, warm page cache.",
        "",
        "| reader | input | frames | time | throughput |",
        "| --- | --- | --- | --- | --- |",
    ]
    for label, seconds, n in frames:
        where = "fr3 cabinet keyframes" if "cabinet" in label else "simulated house, 640x480 PNG"
        lines.append(
            f"| {label} | {where} | {n} | {seconds:.2f} s | **{n / seconds:.0f} frames/s** |"
        )
    lines += [
        "",
        "| CARMEN log | scans | beams | parse time | throughput |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, seconds, scans, beams in carmen:
        lines.append(
            f"| {name} | {scans} | {beams} | {seconds * 1e3:.0f} ms | "
            f"**{scans / seconds:.0f} scans/s** ({beams / seconds / 1e6:.1f} M beams/s) |"
        )
    body = "\n".join(lines) + "\n"
    publish(body, args.out, SECTION)


if __name__ == "__main__":
    main()
