"""TUM text files: ``timestamp value ...`` lines after ``#`` comment lines.

Used for trajectories (``t tx ty tz qx qy qz qw``, readable by evo) and for the index files of a
recording (``rgb.txt``, ``wheels.txt``, ...). Timestamps are parsed to integer nanoseconds without
float round-off; every error names the file and line.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensors.atomic import atomic_write_text
from sensors.types import SensorError, format_stamp, parse_stamp

TRAJECTORY_COLUMNS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
MAX_COORDINATE_M = 1e8  # [m] no robot pose is farther from its origin (UTM northings < 1e7 m)
MIN_QUATERNION_NORM = 1e-9  # [-] shorter is no rotation at all
PLANAR_TUM_HEADER = (
    f"# planar trajectory (z = 0, rotation about z)\n# {' '.join(TRAJECTORY_COLUMNS)}\n"
)


@dataclass(frozen=True, eq=False)
class StampedText:
    """The data lines of a TUM-style text file, split into tokens."""

    path: Path
    stamps_ns: np.ndarray  # (N,) int64 [ns], strictly increasing
    values: list[list[str]]  # N rows of the tokens after the timestamp
    lines: np.ndarray  # (N,) int64, 1-based line number of each row (for error messages)

    def numeric(self, dtype: type[np.generic], what: str) -> np.ndarray:
        """Tokens as an (N, K) array of ``dtype``; a bad or non-finite token is an error naming
        its line."""
        width = len(self.values[0]) if self.values else 0
        try:
            out = np.array(self.values, dtype=dtype).reshape(len(self.values), width)
        except (ValueError, OverflowError):
            out = None
        if out is not None and (out.dtype.kind != "f" or np.isfinite(out).all()):
            return out
        # Slow path only to find the offending line.
        for row, line in zip(self.values, self.lines, strict=True):
            try:
                parsed = np.array(row, dtype=dtype)
            except (ValueError, OverflowError):
                parsed = None
            if parsed is None or (parsed.dtype.kind == "f" and not np.isfinite(parsed).all()):
                raise SensorError(f"{self.path}:{line}: {' '.join(row)!r} is not valid {what}")
        raise SensorError(f"{self.path}: could not parse {what}")  # pragma: no cover


def read_stamped_text(
    path: str | os.PathLike[str], columns: tuple[str, ...], check_order: bool = True
) -> StampedText:
    """Read ``columns`` (the first is the timestamp) from a TUM-style file.

    Blank lines and lines starting with ``#`` are skipped. Each data line must have exactly
    ``len(columns)`` whitespace-separated fields and, with ``check_order``, timestamps must
    strictly increase (file order and stamps are otherwise returned as read).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise SensorError(f"{path}: cannot read: {err}") from err
    stamps: list[int] = []
    values: list[list[str]] = []
    lines: list[int] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.split()
        if len(tokens) != len(columns):
            raise SensorError(
                f"{path}:{number}: expected {len(columns)} fields ({' '.join(columns)}), "
                f"got {len(tokens)}: {line!r}"
            )
        try:
            stamps.append(parse_stamp(tokens[0]))
        except ValueError as err:
            raise SensorError(f"{path}:{number}: bad timestamp: {err}") from err
        values.append(tokens[1:])
        lines.append(number)
    stamps_ns = np.array(stamps, dtype=np.int64)
    line_numbers = np.array(lines, dtype=np.int64)
    if check_order:
        check_increasing(path, stamps_ns, line_numbers)
    return StampedText(path, stamps_ns, values, line_numbers)


def check_increasing(path: Path, stamps_ns: np.ndarray, lines: np.ndarray) -> None:
    """Raise naming the first line whose timestamp repeats or goes back in time."""
    bad = np.flatnonzero(np.diff(stamps_ns) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "duplicate" if stamps_ns[i] == stamps_ns[i - 1] else "non-monotonic"
        raise SensorError(
            f"{path}:{lines[i]}: {kind} timestamp {format_stamp(int(stamps_ns[i]))} "
            f"(previous is {format_stamp(int(stamps_ns[i - 1]))} on line {lines[i - 1]}); "
            "timestamps must strictly increase"
        )


def yaw_from_quaternion(quat_xyzw: np.ndarray) -> np.ndarray:
    """Heading [rad] in (-pi, pi] of (..., 4) quaternions (x, y, z, w), i.e. the z-y-x Euler yaw."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w) of a rotation by ``yaw`` [rad] about z."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zero = np.zeros_like(half)
    return np.stack([zero, zero, np.sin(half), np.cos(half)], axis=-1)


def check_poses(table: StampedText, data: np.ndarray) -> None:
    """TUM pose rows ``(N, 7)`` (tx ty tz qx qy qz qw) that cannot be a robot's: a position
    farther than ``MAX_COORDINATE_M`` from the origin or a zero-length quaternion is an error
    naming its line (a 1e30 m pose would otherwise be scored as a huge but valid error)."""
    far = np.flatnonzero(np.abs(data[:, :3]).max(axis=1, initial=0.0) > MAX_COORDINATE_M)
    if far.size:
        raise SensorError(
            f"{table.path}:{table.lines[far[0]]}: position "
            f"{data[far[0], :3].tolist()} is farther than {MAX_COORDINATE_M:g} m "
            "from the origin"
        )
    zero = np.flatnonzero(np.linalg.norm(data[:, 3:7], axis=1) < MIN_QUATERNION_NORM)
    if zero.size:
        raise SensorError(f"{table.path}:{table.lines[zero[0]]}: quaternion has zero length")


def load_tum_trajectory(
    path: str | os.PathLike[str],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """TUM trajectory -> (stamps_ns (N,) int64, xyz (N, 3) float64 [m], quat_xyzw (N, 4))."""
    table = read_stamped_text(path, TRAJECTORY_COLUMNS)
    data = table.numeric(np.float64, "pose (tx ty tz qx qy qz qw)").reshape(-1, 7)
    check_poses(table, data)
    return table.stamps_ns, data[:, :3].reshape(-1, 3), data[:, 3:].reshape(-1, 4)


def write_tum_trajectory(
    path: str | os.PathLike[str],
    stamps_ns: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    yaw: np.ndarray,
) -> None:
    """Atomically write planar poses (z = 0, rotation about z) as a TUM trajectory."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    xyz = np.stack(
        [np.asarray(x, np.float64), np.asarray(y, np.float64), np.zeros(len(stamps_ns))], axis=-1
    )
    if xyz.shape != (len(stamps_ns), 3) or np.shape(yaw) != (len(stamps_ns),):
        raise ValueError("stamps_ns, x, y and yaw must be 1-D arrays of the same length")
    poses = np.concatenate([xyz, quaternion_from_yaw(yaw)], axis=1)
    rows = [
        format_stamp(int(t)) + " " + " ".join(repr(float(v)) for v in pose)
        for t, pose in zip(stamps_ns, poses, strict=True)
    ]
    atomic_write_text(path, PLANAR_TUM_HEADER + "".join(r + "\n" for r in rows))


def write_tum_poses(path: str | os.PathLike[str], stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """Atomically write 6-DoF poses ((N, 4, 4) homogeneous matrices) as a TUM trajectory."""
    from scipy.spatial.transform import Rotation

    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) != len(stamps_ns):
        raise ValueError("stamps_ns and poses must have the same length")
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat() if len(poses) else np.zeros((0, 4))
    rows = np.concatenate([poses[:, :3, 3], quat], axis=1)
    text = "".join(
        format_stamp(int(t)) + " " + " ".join(repr(float(v)) for v in r) + "\n"
        for t, r in zip(stamps_ns, rows, strict=True)
    )
    atomic_write_text(path, "# timestamp tx ty tz qx qy qz qw\n" + text)


def planar_tum_row(stamp_ns: int, x: float, y: float, yaw: float) -> str:
    """One line of :func:`write_tum_trajectory`'s format, for a trajectory written as it
    grows (e.g. the live run's streamed tracks)."""
    return (f"{format_stamp(int(stamp_ns))} {float(x)!r} {float(y)!r} 0.0 0.0 0.0 "
            f"{math.sin(yaw / 2)!r} {math.cos(yaw / 2)!r}\n")  # fmt: skip
