"""TUM text files (``timestamp value ...`` lines after ``#`` comments) and trajectory files.

TUM-style tables are our trajectories (``t tx ty tz qx qy qz qw``, readable by evo) and the index
files of a recording (``rgb.txt``, ``wheels.txt``, ...). Timestamps are parsed to integer
nanoseconds without float round-off; every error names the file and line.

Trajectories are also read and written in the two other formats evo knows:

- **KITTI** odometry: 12 numbers a line, the 3x4 pose ``[R | t]`` row-major, no time; times come
  from a KITTI ``times.txt`` (seconds, one a line): ``NAME.times.txt`` or ``times.txt`` beside it,
  or one given. Without one, frame i is at i seconds (evo pairs KITTI files by index too).
- **EuRoC / ASL** CSV: ``#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],
  q_RS_x [],q_RS_y [],q_RS_z []`` (quaternion **w first**); the EuRoC ground truth's further
  columns (velocity, biases) are not poses and are not read.

:func:`load_trajectory` tells the three apart by the first data line (commas: EuRoC; 8 fields:
TUM; 12: KITTI); :func:`write_trajectory` writes any of them.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensors.atomic import atomic_write_text
from sensors.config import short_repr
from sensors.types import MAX_STAMP_NS, NS_PER_S, SensorError, format_stamp, parse_stamp

log = logging.getLogger(__name__)

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


def check_poses(table: StampedText | PoseTable, data: np.ndarray) -> None:
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

    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) != len(stamps_ns):
        raise ValueError("stamps_ns and poses must have the same length")
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat() if len(poses) else np.zeros((0, 4))
    write_trajectory(path, stamps_ns, poses[:, :3, 3], quat, "tum")


def planar_tum_row(stamp_ns: int, x: float, y: float, yaw: float) -> str:
    """One line of :func:`write_tum_trajectory`'s format, for a trajectory written as it
    grows (e.g. the live run's streamed tracks)."""
    return (
        f"{format_stamp(int(stamp_ns))} {float(x)!r} {float(y)!r} 0.0 0.0 0.0 "
        f"{math.sin(yaw / 2)!r} {math.cos(yaw / 2)!r}\n"
    )


# --- TUM, KITTI and EuRoC/ASL trajectories ---------------------------------------------------

TRAJECTORY_FORMATS = ("tum", "kitti", "euroc")
KITTI_FIELDS = 12
EUROC_HEADER = (
    "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
)
EUROC_POSE_FIELDS = 8  # stamp, position, quaternion w x y z


@dataclass(frozen=True, eq=False)
class PoseTable:
    """A trajectory file as read, in any format: TUM-ordered poses and where each came from."""

    path: Path
    format: str  # tum | kitti | euroc
    stamps_ns: np.ndarray  # (N,) int64 [ns], in file order
    poses: np.ndarray  # (N, 7) float64 tx ty tz qx qy qz qw
    lines: np.ndarray  # (N,) int64 1-based line numbers


def _data_lines(path: Path) -> tuple[list[str], list[int]]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise SensorError(f"{path}: cannot read: {err}") from err
    rows, numbers = [], []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            rows.append(line)
            numbers.append(number)
    return rows, numbers


def detect_trajectory_format(path: str | os.PathLike[str]) -> str:
    """``tum``, ``kitti`` or ``euroc`` from the first data line; an error naming the shapes
    known otherwise."""
    path = Path(path)
    rows, numbers = _data_lines(path)
    if not rows:
        raise SensorError(f"{path}: no poses (an empty trajectory file)")
    first = rows[0]
    if "," in first:
        return "euroc"
    fields = len(first.split())
    if fields == len(TRAJECTORY_COLUMNS):
        return "tum"
    if fields == KITTI_FIELDS:
        return "kitti"
    raise SensorError(
        f"{path}:{numbers[0]}: {fields} fields is no trajectory format known here: TUM "
        f"'{' '.join(TRAJECTORY_COLUMNS)}' (8), KITTI 3x4 pose (12) or EuRoC/ASL CSV "
        "'timestamp_ns,px,py,pz,qw,qx,qy,qz'"
    )


def kitti_times_file(path: Path) -> Path | None:
    """The KITTI ``times.txt`` of a pose file: ``NAME.times.txt`` (as we write) or
    ``times.txt`` beside it; None when there is neither."""
    base = path.name.split(".")[0]
    for candidate in (path.with_name(f"{base}.times.txt"), path.with_name("times.txt")):
        if candidate.is_file() and candidate != path:
            return candidate
    return None


def _numbers(path: Path, rows: list[list[str]], lines: list[int], what: str) -> np.ndarray:
    table = StampedText(path, np.zeros(len(rows), np.int64), rows, np.array(lines, np.int64))
    return table.numeric(np.float64, what)


def _read_kitti(path: Path, times: Path | None) -> PoseTable:
    from scipy.spatial.transform import Rotation

    rows, numbers = _data_lines(path)
    tokens = [r.split() for r in rows]
    for toks, number in zip(tokens, numbers, strict=True):
        if len(toks) != KITTI_FIELDS:
            raise SensorError(
                f"{path}:{number}: expected {KITTI_FIELDS} fields (KITTI 3x4 "
                f"pose, row-major), got {len(toks)}"
            )
    m = _numbers(path, tokens, numbers, "KITTI pose (12 numbers)").reshape(-1, 3, 4)
    times = times or kitti_times_file(path)
    if times is None:
        log.warning("%s: KITTI poses without a times file; frame i is at i s", path)
        stamps = np.arange(len(m), dtype=np.int64) * NS_PER_S
    else:
        t_rows, t_numbers = _data_lines(times)
        stamps_list = []
        for row, number in zip(t_rows, t_numbers, strict=True):
            try:
                stamps_list.append(parse_stamp(row.split()[0]))
            except ValueError as err:
                raise SensorError(f"{times}:{number}: bad time: {err}") from err
        stamps = np.array(stamps_list, dtype=np.int64)
        if len(stamps) != len(m):
            raise SensorError(f"{times}: {len(stamps)} times for the {len(m)} poses of {path}")
    det = np.linalg.det(m[:, :, :3]) if len(m) else np.ones(0)
    bad = np.flatnonzero(np.abs(det - 1.0) > 1e-3)
    if bad.size:
        raise SensorError(
            f"{path}:{numbers[bad[0]]}: the 3x3 part is not a rotation "
            f"(determinant {det[bad[0]]:.4g})"
        )
    quat = Rotation.from_matrix(m[:, :, :3]).as_quat() if len(m) else np.zeros((0, 4))
    poses = np.concatenate([m[:, :, 3], quat], axis=1)
    return PoseTable(path, "kitti", stamps, poses, np.array(numbers, np.int64))


def _read_euroc(path: Path) -> PoseTable:
    rows, numbers = _data_lines(path)
    stamps, values = [], []
    for row, number in zip(rows, numbers, strict=True):
        fields = [f.strip() for f in row.split(",")]
        if len(fields) < EUROC_POSE_FIELDS:
            raise SensorError(
                f"{path}:{number}: expected at least {EUROC_POSE_FIELDS} "
                f"comma-separated fields (timestamp [ns], p x y z, q w x y z), "
                f"got {len(fields)}"
            )
        # isascii: str.isdigit() also passes "²" and "٣"; the bound keeps int64 from overflowing
        stamp = fields[0]
        if not (stamp.isascii() and stamp.isdigit() and len(stamp) < 20) or (
            int(stamp) > MAX_STAMP_NS
        ):
            raise SensorError(
                f"{path}:{number}: timestamp {short_repr(fields[0])} is not integer ns "
                f"(0..{MAX_STAMP_NS})"
            )
        stamps.append(int(fields[0]))
        values.append(fields[1:EUROC_POSE_FIELDS])
    data = _numbers(path, values, numbers, "EuRoC pose (px py pz qw qx qy qz)").reshape(-1, 7)
    poses = data[:, [0, 1, 2, 4, 5, 6, 3]]  # w x y z -> x y z w
    return PoseTable(path, "euroc", np.array(stamps, np.int64), poses, np.array(numbers, np.int64))


def read_pose_table(
    path: str | os.PathLike[str],
    fmt: str = "auto",
    times: str | os.PathLike[str] | None = None,
    check_order: bool = True,
) -> PoseTable:
    """A trajectory file in TUM, KITTI or EuRoC format (``fmt="auto"``: detected), its poses
    checked (:func:`check_poses`) and, with ``check_order``, its stamps strictly increasing."""
    path = Path(path)
    fmt = detect_trajectory_format(path) if fmt == "auto" else fmt
    if fmt not in TRAJECTORY_FORMATS:
        raise SensorError(f"trajectory format {fmt!r}: use one of {', '.join(TRAJECTORY_FORMATS)}")
    if times is not None and fmt != "kitti":
        raise SensorError(f"{path}: a times file is for KITTI poses; this is a {fmt} file")
    if fmt == "tum":
        text = read_stamped_text(path, TRAJECTORY_COLUMNS, check_order=False)
        data = text.numeric(np.float64, "pose (tx ty tz qx qy qz qw)").reshape(-1, 7)
        table = PoseTable(path, "tum", text.stamps_ns, data, text.lines)
    elif fmt == "kitti":
        table = _read_kitti(path, Path(times) if times is not None else None)
    else:
        table = _read_euroc(path)
    check_poses(table, table.poses)
    if check_order:
        check_increasing(path, table.stamps_ns, table.lines)
    return table


def load_trajectory(
    path: str | os.PathLike[str], times: str | os.PathLike[str] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Any trajectory file (format detected) -> (stamps_ns, xyz (N, 3), quat_xyzw (N, 4))."""
    table = read_pose_table(path, times=times)
    return table.stamps_ns, table.poses[:, :3], table.poses[:, 3:]


def _rows_text(rows: np.ndarray) -> list[str]:
    return [" ".join(repr(float(v)) for v in r) for r in rows]


def write_trajectory(
    path: str | os.PathLike[str],
    stamps_ns: np.ndarray,
    xyz: np.ndarray,
    quat_xyzw: np.ndarray,
    fmt: str = "tum",
) -> list[Path]:
    """Atomically write a trajectory as TUM, KITTI (+ ``NAME.times.txt``) or EuRoC CSV; return
    the files written."""
    from scipy.spatial.transform import Rotation

    path = Path(path)
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    quat = np.asarray(quat_xyzw, np.float64).reshape(-1, 4)
    if not len(stamps_ns) == len(xyz) == len(quat):
        raise ValueError("stamps_ns, xyz and quat_xyzw must have the same length")
    if fmt == "tum":
        rows = _rows_text(np.concatenate([xyz, quat], axis=1))
        text = "".join(
            f"{format_stamp(int(t))} {r}\n" for t, r in zip(stamps_ns, rows, strict=True)
        )
        atomic_write_text(path, f"# {' '.join(TRAJECTORY_COLUMNS)}\n" + text)
        return [path]
    if fmt == "kitti":
        rot = Rotation.from_quat(quat).as_matrix() if len(quat) else np.zeros((0, 3, 3))
        m = np.concatenate([rot, xyz[:, :, None]], axis=2).reshape(-1, KITTI_FIELDS)
        times = path.with_name(f"{path.name.split('.')[0]}.times.txt")
        atomic_write_text(path, "".join(r + "\n" for r in _rows_text(m)))
        atomic_write_text(times, "".join(format_stamp(int(t)) + "\n" for t in stamps_ns))
        return [path, times]
    if fmt == "euroc":
        wxyz = np.concatenate([xyz, quat[:, [3, 0, 1, 2]]], axis=1)
        lines = [
            f"{int(t)}," + ",".join(repr(float(v)) for v in r)
            for t, r in zip(stamps_ns, wxyz, strict=True)
        ]
        atomic_write_text(path, EUROC_HEADER + "\n" + "".join(r + "\n" for r in lines))
        return [path]
    raise SensorError(f"trajectory format {fmt!r}: use one of {', '.join(TRAJECTORY_FORMATS)}")


TRAJECTORY_SUFFIXES = {"tum": ".tum", "kitti": ".kitti.txt", "euroc": ".euroc.csv"}


def convert_tum_files(folder: Path, fmt: str) -> list[Path]:
    """Write every ``*.tum`` trajectory in ``folder`` again as ``fmt`` beside it
    (``NAME.kitti.txt`` + ``NAME.times.txt``, ``NAME.euroc.csv``); return the new files."""
    if fmt not in TRAJECTORY_FORMATS:
        raise SensorError(f"--format {fmt!r}: use one of {', '.join(TRAJECTORY_FORMATS)}")
    if fmt == "tum":
        return []
    written: list[Path] = []
    for tum in sorted(folder.glob("*.tum")):
        stamps, xyz, quat = load_tum_trajectory(tum)
        target = tum.with_name(tum.stem + TRAJECTORY_SUFFIXES[fmt])
        written += write_trajectory(target, stamps, xyz, quat, fmt)
    return written
