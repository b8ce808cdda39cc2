"""Cut a CARMEN log into two overlapping "robots" for testing ``rgbdnav fleet align``.

Robot A keeps the first ``--a-end`` fraction of the laser scans as they are; robot B keeps the
scans from ``--b-start`` on, with every pose field (FLASER laser and odometry poses, ODOM poses)
moved by ``--shift X Y YAW``: B's odometry frame is A's turned by YAW and moved by (X, Y), so B's
map frame in A's is the inverse of the shift (printed, and written to ``shift.yaml``).

    python bench/fleet_split_log.py LOG OUT [--a-end 0.6] [--b-start 0.4] [--shift 80 -40 2.0]

Writes ``OUT/a.log``, ``OUT/b.log`` and ``OUT/shift.yaml``; map each with ``rgbdnav map``.
"""

from __future__ import annotations

import argparse
import gzip
import math
from pathlib import Path

import numpy as np

from sensors.atomic import atomic_write_text
from slam.geometry import oplus, wrap_angle


def read_log_lines(path: Path) -> list[str]:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", errors="replace") as f:
        return f.read().splitlines()


def _move(fields: list[str], at: int, shift: np.ndarray) -> None:
    """Replace the pose ``fields[at:at + 3]`` by ``shift ⊕ pose``, in place."""
    pose = np.array([float(v) for v in fields[at : at + 3]])
    moved = oplus(shift, pose)
    fields[at : at + 3] = [f"{moved[0]:.6f}", f"{moved[1]:.6f}", f"{wrap_angle(moved[2]):.6f}"]


def split(lines: list[str], a_end: float, b_start: float, shift: np.ndarray) -> tuple[str, str]:
    """The text of logs A and B (see the module doc)."""
    scan_rows = [i for i, line in enumerate(lines) if line.startswith("FLASER ")]
    cut_a = scan_rows[int(a_end * (len(scan_rows) - 1))]
    cut_b = scan_rows[int(b_start * (len(scan_rows) - 1))]
    a, b = [], []
    for i, line in enumerate(lines):
        kind = line.split(" ", 1)[0]
        if kind.startswith("#") or kind == "PARAM":
            a.append(line)
            b.append(line)
            continue
        if i <= cut_a:
            a.append(line)
        if i < cut_b:
            continue
        fields = line.split()
        if kind == "FLASER":
            n = int(fields[1])
            _move(fields, 2 + n, shift)
            _move(fields, 5 + n, shift)
        elif kind == "ODOM":
            _move(fields, 1, shift)
        else:
            continue  # other messages carry poses we do not move
        b.append(" ".join(fields))
    return "\n".join(a) + "\n", "\n".join(b) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("log", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--a-end", type=float, default=0.6)
    p.add_argument("--b-start", type=float, default=0.4)
    p.add_argument("--shift", type=float, nargs=3, default=(80.0, -40.0, 2.0))
    args = p.parse_args()
    shift = np.array(args.shift)
    text_a, text_b = split(read_log_lines(args.log), args.a_end, args.b_start, shift)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "a.log", text_a)
    atomic_write_text(args.out / "b.log", text_b)
    # B's odom frame in A's is the shift's inverse: p_A = shift^-1 ⊕ p_B.
    c, s = math.cos(shift[2]), math.sin(shift[2])
    inv = (-(c * shift[0] + s * shift[1]), s * shift[0] - c * shift[1], -shift[2])
    atomic_write_text(
        args.out / "shift.yaml",
        f"shift: [{shift[0]}, {shift[1]}, {shift[2]}]\n"
        f"T_a_b: [{inv[0]:.6f}, {inv[1]:.6f}, {wrap_angle(inv[2]):.6f}]\n",
    )
    print(f"B's odometry frame in A's: x {inv[0]:.3f} y {inv[1]:.3f} yaw {wrap_angle(inv[2]):.4f}")


if __name__ == "__main__":
    main()
