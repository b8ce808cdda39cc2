"""Run a seeded mutation corpus through the readers a run reads and count how each input ends:
ok, counted skip (the reader dropped and counted something), clean error (an RgbdNavError,
or parse_stamp's documented ValueError), traceback (any other exception) or hang (no answer
within --timeout seconds). Target: 0 tracebacks and 0 hangs.

Run: ``.venv/bin/python bench/fuzz_inputs.py [--count 300] [--seed 0] [--out docs/benchmarks.md]``.
Exits 1 when any input ended in a traceback or a hang.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from common import machine, publish  # noqa: E402  (bench/ is on sys.path)

from nav.joystick import parse_events  # noqa: E402
from rgbdnav.commands.export import run_content  # noqa: E402
from rgbdnav.config import load_config  # noqa: E402
from rgbdnav.ros_params import load_ros_params  # noqa: E402
from sensors.arduino_bridge import parse_encoder_reply  # noqa: E402
from sensors.carmen import read_carmen_log  # noqa: E402
from sensors.eddie import parse_reply  # noqa: E402
from sensors.geo import read_geo_anchor  # noqa: E402
from sensors.gps import read_gps_txt  # noqa: E402
from sensors.images import decode_image  # noqa: E402
from sensors.motor_board import parse_device_spec  # noqa: E402
from sensors.recording import Recording  # noqa: E402
from sensors.rosbag_source import (  # noqa: E402
    depth_from_compressed,
    depth_from_image,
    parse_sdk_transform,
)
from sensors.sim.world import load_world  # noqa: E402
from sensors.thunderborg import parse_tacho_line  # noqa: E402
from sensors.tum import load_tum_trajectory, read_pose_table  # noqa: E402
from sensors.tum_folder import read_camera_yaml  # noqa: E402
from sensors.types import LaserScan, RgbdNavError, SensorError, parse_stamp  # noqa: E402
from slam.fleet import load_fleet  # noqa: E402
from slam.map_bundle import (  # noqa: E402
    GraphEdge,
    MapBundle,
    decode_pgm,
    load_bundle,
    load_map_yaml,
    save_bundle,
)
from slam.occupancy_grid import GridGeometry, OccupancyGrid  # noqa: E402
from slam.pose_graph import read_g2o  # noqa: E402
from slam.trajectory_eval import read_relations  # noqa: E402

OUTCOMES = ("ok", "counted skip", "clean error", "traceback", "hang")
SECTION = "fuzz_inputs"
MAX_EXAMPLES = 3  # tracebacks and hangs quoted per reader
SPECIALS = [
    b"\x00",
    b"\xff\xfe",
    b"1e30",
    b"nan",
    b".nan",
    b"-.inf",
    b"&a [*a, *a]",
    b"*a",
    b"9" * 40,
    b"[" * 200,
    b"\n" * 3,
    b"-",
    b"0",
    b"1e12",
    b"{a: 1, a: 2}",
]


SDK_TRANSFORM = b"rotation=1,0,0,0,1,0,0,0,1;translation=0.015,0,0"


class _Hang(Exception):
    pass


def mutate(rng: random.Random, base: bytes) -> bytes:
    """1-3 byte-level edits of ``base``: replace, insert, delete, repeat a span, cut, splice a
    special token (huge numbers, NaN, aliases, deep nesting, invalid UTF-8)."""
    data = bytearray(base)
    for _ in range(rng.randint(1, 3)):
        pos = rng.randint(0, len(data))
        kind = rng.randrange(6)
        if kind == 0 and pos < len(data):
            data[pos] = rng.randrange(256)
        elif kind == 1:
            data[pos:pos] = bytes([rng.randrange(256)]) * rng.randint(1, 8)
        elif kind == 2:
            del data[pos : pos + rng.randint(1, 32)]
        elif kind == 3:
            data[pos:pos] = bytes(data[pos : pos + 16]) * rng.randint(1, 64)
        elif kind == 4 and rng.random() < 0.2:
            del data[pos:]
        else:
            data[pos:pos] = rng.choice(SPECIALS)
    return bytes(data)


# --- the readers: each takes the mutated bytes and a scratch folder --------------------------


def _config(data: bytes, tmp: Path) -> str:
    (tmp / "c.yaml").write_bytes(data)
    load_config([tmp / "c.yaml"])
    return "ok"


def _override(data: bytes, tmp: Path) -> str:
    load_config(overrides=[data.decode("utf-8", errors="replace")])
    return "ok"


def _stamp(data: bytes, tmp: Path) -> str:
    try:
        parse_stamp(data.decode("utf-8", errors="replace"))
    except ValueError as err:  # parse_stamp's documented error
        raise SensorError(str(err)) from None
    return "ok"


def _tum(data: bytes, tmp: Path) -> str:
    (tmp / "t.txt").write_bytes(data)
    load_tum_trajectory(tmp / "t.txt")
    return "ok"


def _carmen(data: bytes, tmp: Path) -> str:
    (tmp / "a.clf").write_bytes(data)
    log = read_carmen_log(tmp / "a.clf")
    return "counted skip" if sum(log.skipped.values()) else "ok"


def _image(data: bytes, tmp: Path) -> str:
    decode_image(data, "x", SensorError)
    return "ok"


def _pgm(data: bytes, tmp: Path) -> str:
    decode_pgm(data, "map.pgm")
    return "ok"


def _map_yaml(data: bytes, tmp: Path) -> str:
    (tmp / "m.yaml").write_bytes(data)
    load_map_yaml(tmp / "m.yaml")
    return "ok"


def _fleet(data: bytes, tmp: Path) -> str:
    (tmp / "fleet.yaml").write_bytes(data)
    load_fleet(tmp / "fleet.yaml")
    return "ok"


def _geo(data: bytes, tmp: Path) -> str:
    (tmp / "g" / "geo.yaml").write_bytes(data)
    read_geo_anchor(tmp / "g")
    return "ok"


def _gps(data: bytes, tmp: Path) -> str:
    (tmp / "gps.txt").write_bytes(data)
    read_gps_txt(tmp / "gps.txt")
    return "ok"


def _kitti(data: bytes, tmp: Path) -> str:
    (tmp / "k.txt").write_bytes(data)
    read_pose_table(tmp / "k.txt", "kitti", tmp / "times.txt")
    return "ok"


def _kitti_times(data: bytes, tmp: Path) -> str:
    (tmp / "times_m.txt").write_bytes(data)
    read_pose_table(tmp / "kitti.txt", "kitti", tmp / "times_m.txt")
    return "ok"


def _euroc(data: bytes, tmp: Path) -> str:
    (tmp / "data.csv").write_bytes(data)
    read_pose_table(tmp / "data.csv")
    return "ok"


def _joystick(data: bytes, tmp: Path) -> str:
    parse_events(data.decode("utf-8", errors="replace"), "events.txt")
    return "ok"


def _board_spec(data: bytes, tmp: Path) -> str:
    parse_device_spec(data.decode("utf-8", errors="replace"))
    return "ok"


def _tacho(data: bytes, tmp: Path) -> str:
    rpm = parse_tacho_line(data)
    if rpm is None:
        return "counted skip"  # ThunderBorgBoard counts a line it cannot read
    if not np.isfinite(rpm).all():
        raise SensorError("a non-finite RPM passed")  # silent: reported as a traceback
    return "ok"


def _encoder_reply(data: bytes, tmp: Path) -> str:
    counts = parse_encoder_reply(data.decode("ascii", "replace"))  # as the board decodes it
    if counts is None:
        raise SensorError("unreadable")  # the board raises MotorBoardError and counts it
    return "ok"


def _run_summary(data: bytes, tmp: Path) -> str:
    (tmp / "run" / "summary.json").write_bytes(data)
    run_content(tmp / "run", images=True)
    return "ok"


def _ros_params(data: bytes, tmp: Path) -> str:
    (tmp / "p.yaml").write_bytes(data)
    load_ros_params([tmp / "p.yaml"])
    return "ok"


def _sdk_transform(data: bytes, tmp: Path) -> str:
    parse_sdk_transform(data.decode("utf-8", errors="replace"))
    return "ok"


def _bundle_file(name: str) -> Callable[[bytes, Path], str]:
    def read(data: bytes, tmp: Path) -> str:
        (tmp / "b" / name).write_bytes(data)
        try:
            load_bundle(tmp / "b")
        finally:
            (tmp / "b" / name).write_bytes((tmp / "b0" / name).read_bytes())
        return "ok"

    return read


def _recording_file(name: str) -> Callable[[bytes, Path], str]:
    def read(data: bytes, tmp: Path) -> str:
        (tmp / "rec" / name).write_bytes(data)
        try:
            rec = Recording.open(tmp / "rec")
            frames = list(rec.frames(skip_bad=True))
            rec.wheels()
            rec.imu()
        finally:
            (tmp / "rec" / name).write_bytes((tmp / "rec0" / name).read_bytes())
        return "counted skip" if len(frames) < len(rec) else "ok"

    return read


def _world(data: bytes, tmp: Path) -> str:
    (tmp / "w.yaml").write_bytes(data)
    load_world(tmp / "w.yaml")
    return "ok"


def _camera_yaml(data: bytes, tmp: Path) -> str:
    (tmp / "TUM3.yaml").write_bytes(data)
    cam = read_camera_yaml(tmp / "TUM3.yaml")
    if cam is not None and not all(np.isfinite(list(cam.values()))):
        raise SensorError("non-finite intrinsics passed")  # silent: reported as a traceback
    return "ok" if cam is not None else "counted skip"  # None: said, defaults not taken silently


def _g2o(data: bytes, tmp: Path) -> str:
    (tmp / "g.g2o").write_bytes(data)
    read_g2o(tmp / "g.g2o")
    return "ok"


def _relations(data: bytes, tmp: Path) -> str:
    (tmp / "r.relations").write_bytes(data)
    read_relations(tmp / "r.relations")
    return "ok"


def _raw_depth_message(data: bytes, tmp: Path) -> str:
    depth_from_image("16UC1", 2, 3, 6, data)  # sensor_msgs/Image data of a 3x2 16UC1 image
    return "ok"


def _compressed_depth_message(data: bytes, tmp: Path) -> str:
    depth_from_compressed("16UC1; compressedDepth png", data)
    return "ok"


def _eddie_reply(data: bytes, tmp: Path) -> str:
    parse_reply("DIST", data)
    return "ok"


def _corpus(tmp: Path) -> dict[str, tuple[Callable[[bytes, Path], str], bytes]]:
    """Reader name -> (reader, the valid input it mutates)."""
    config = (
        b"ekf:\n  frequency: 30.0\n  sensor_timeout: 0.1\ncamera:\n  fx: 525.0\n"
        b"  width: 640\nmapper: {resolution: 0.05, minimum_travel_distance: 0.5}\n"
        b"live: {checkpoint_period: 30.0}\n"
    )
    tum = b"# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.5 1.5 -2 0 0 0 0.7071 0.7071\n"
    ranges = " ".join(["1.5"] * 181)
    carmen = b"".join(
        f"FLASER 181 {ranges} 1 2 0.5 0.1 0.2 0.3 {t} host {t + 0.01}\n".encode()
        for t in (1.0, 1.2, 1.4)
    )
    png = cv2.imencode(".png", np.arange(48, dtype=np.uint8).reshape(4, 4, 3))[1].tobytes()
    jpg = cv2.imencode(".jpg", np.arange(48, dtype=np.uint8).reshape(4, 4, 3))[1].tobytes()
    pgm = b"P5\n4 3\n255\n" + bytes([0, 254, 205, 0] * 3)
    (tmp / "map.pgm").write_bytes(pgm)
    map_yaml = (
        b"image: map.pgm\nmode: trinary\nresolution: 0.05\norigin: [-1.0, -0.5, 0.0]\n"
        b"negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    geom = GridGeometry(0.1, -1.0, -0.5, 20, 10)
    grid = OccupancyGrid.from_occupancy_values(geom, np.zeros(geom.shape, np.int8))
    scans = tuple(LaserScan(10 + i, -1.0, 0.5, np.ones(3, np.float32), 0.1, 5.0) for i in range(3))
    poses = np.array([[0.1 * i, 0.0, 0.0] for i in range(3)])
    info = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    edges = tuple(GraphEdge("odometry", i, i + 1, (0.1, 0.0, 0.0), info) for i in range(2))
    save_bundle(
        MapBundle(
            grid,
            np.arange(3, dtype=np.int64),
            np.arange(3) + 10,
            poses,
            poses,
            edges,
            scans,
            {"resolution": 0.1},
            "fuzz",
            "2026-01-01T00:00:00+00:00",
        ),
        tmp / "b",
    )
    graph = (tmp / "b" / "graph.json").read_bytes()
    shutil.copytree(tmp / "b", tmp / "b0")  # each bundle reader restores its file from here
    _write_recording(tmp / "rec")
    shutil.copytree(tmp / "rec", tmp / "rec0")
    world = (REPO / "scenes" / "blank_rooms.yaml").read_bytes()
    g2o = (
        b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.0 0.1 0.2\n"
        b"EDGE_SE2 0 1 1.0 0.1 0.2 500 0 0 500 0 5000\n"
    )
    png16 = cv2.imencode(".png", np.arange(6, dtype=np.uint16).reshape(2, 3) * 900)[1].tobytes()
    compressed_depth = b"\x00\x00\x00\x00" + np.array([1, 2], "<f4").tobytes() + png16
    (tmp / "m").mkdir()
    (tmp / "g").mkdir()
    (tmp / "run").mkdir()
    (tmp / "run" / "fused.tum").write_bytes(b"1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    kitti = b"1 0 0 0.5 0 1 0 0.25 0 0 1 0\n1 0 0 1.5 0 1 0 0.5 0 0 1 0\n"
    (tmp / "kitti.txt").write_bytes(kitti)
    (tmp / "times.txt").write_bytes(b"0.0\n0.1\n")
    return {
        "config file (YAML)": (_config, config),
        "--set override": (_override, b"ekf.frequency=30"),
        "text timestamp": (_stamp, b"1305031102.175304"),
        "TUM trajectory": (_tum, tum),
        "CARMEN log": (_carmen, carmen),
        "image bytes (PNG)": (_image, png),
        "image bytes (JPEG)": (_image, jpg),
        "image bytes (PGM)": (_image, pgm),
        "PGM ASCII P2 (Nav2 map)": (_pgm, b"P2\n# c\n3 2\n255\n0 254 205\n0 100 255\n"),
        "PGM 16-bit P5 (Nav2 map)": (
            _pgm,
            b"P5\n2 2\n65535\n" + bytes([0, 0, 255, 255, 1, 0, 128, 0]),
        ),
        "Nav2 map.yaml": (_map_yaml, map_yaml),
        "bundle graph.json": (_bundle_file("graph.json"), graph),
        "fleet.yaml": (
            _fleet,
            b"world:\n  geo: {latitude: 52.0, longitude: 4.0}\nrobots:\n  - name: a\n"
            b"    map: m\n    T_world_map: {x: 1.0, y: -2.0, yaw: 0.5}\n"
            b"  - {name: b, map: m, geo: {latitude: 52.1, longitude: 4.1}}\n",
        ),
        "geo.yaml": (_geo, b"latitude: 52.0\nlongitude: 4.0\naltitude: 3.5\nheading_deg: 90\n"),
        "gps.txt": (_gps, b"# t lat lon alt sigma_h\n1.0 52.0 4.0 10 3.0\n2.0 52.1 4.1 11 2.5\n"),
        "KITTI poses": (_kitti, kitti),
        "KITTI times file": (_kitti_times, b"0.0\n0.1\n"),
        "EuRoC trajectory": (
            _euroc,
            b"#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
            b"q_RS_y [], q_RS_z []\n1403636579758555392,4.68,-1.78,0.78,0.53,-0.15,-0.82,-0.08\n"
            b"1403636579763555584,4.69,-1.78,0.78,0.53,-0.15,-0.82,-0.08\n",
        ),
        "joystick replay file": (_joystick, b"0.0 1 0 1\n0.5 3 1 -32767\n1.25 1 0 0\n"),
        "--board spec": (_board_spec, b"thunderborg:/dev/i2c-1@0x15,/dev/ttyUSB0"),
        "ThunderBorg tacho line": (_tacho, b"tacho 12.5 -3\r\n"),
        "Arduino bridge 'e' reply": (_encoder_reply, b"123 -45"),
        "export: run summary.json": (
            _run_summary,
            b'{"command": "odometry", "frame": "base_link", "source": "/nonexistent", '
            b'"map": {"path": "gone"}, "recording": {"path": "gone"}}',
        ),
        "--ros-params file": (
            _ros_params,
            b"ekf_filter_node:\n  ros__parameters:\n    frequency: 30.0\n    two_d_mode: true\n"
            b"slam_toolbox:\n  ros__parameters:\n    resolution: 0.05\n",
        ),
        "RealSense SDK transform": (_sdk_transform, SDK_TRANSFORM),
        "world file": (_world, world),
        "bundle map.yaml": (_bundle_file("map.yaml"), (tmp / "b" / "map.yaml").read_bytes()),
        "bundle scans.npz": (_bundle_file("scans.npz"), (tmp / "b" / "scans.npz").read_bytes()),
        "bundle grid.npz": (_bundle_file("grid.npz"), (tmp / "b" / "grid.npz").read_bytes()),
        "recording rgb.txt": (_recording_file("rgb.txt"), (tmp / "rec" / "rgb.txt").read_bytes()),
        "recording wheels.txt": (
            _recording_file("wheels.txt"),
            (tmp / "rec" / "wheels.txt").read_bytes(),
        ),
        "recording scene.yaml": (
            _recording_file("scene.yaml"),
            (tmp / "rec" / "scene.yaml").read_bytes(),
        ),
        "TUM camera YAML": (
            _camera_yaml,
            b"%YAML:1.0\nCamera.fx: 535.4\nCamera.fy: 539.2\nCamera.cx: 320.1\n"
            b"Camera.cy: 247.6\nCamera.width: 640\nCamera.height: 480\n",
        ),
        "g2o pose graph": (_g2o, g2o),
        "relations file": (_relations, b"1.0 2.0 0.5 0.0 0 0 0 0.1\n2.0 3.0 0.5 0.1 0 0 0 -0.1\n"),
        "rosbag Image data (16UC1)": (_raw_depth_message, bytes(range(12))),
        "rosbag compressedDepth": (_compressed_depth_message, compressed_depth),
        "Eddie DIST reply": (_eddie_reply, b"0000000A FFFFFFF6\r"),
    }


def _write_recording(path: Path) -> None:
    """Three 8x6 frames with wheels and IMU: a recording folder as `simulate` writes one."""
    from sensors.recording import RecordingWriter
    from sensors.types import CameraIntrinsics, RgbdFrame

    intr = CameraIntrinsics(width=8, height=6, fx=10.0, fy=10.0, cx=3.5, cy=2.5)
    with RecordingWriter(path, intr, {"robot": {"track_m": 0.3}}) as writer:
        for k in range(3):
            rgb = np.full((6, 8, 3), 40 * k, np.uint8)
            writer.add_frame(
                RgbdFrame(1_000_000_000 + k * 33_000_000, rgb, np.ones((6, 8), np.float32), intr)
            )
    (path / "wheels.txt").write_text("# t left right\n1.0 0 0\n1.033 3 4\n1.066 7 9\n")
    (path / "imu.txt").write_text("# t gyro_z\n1.0 0.01\n1.033 0.02\n1.066 -0.01\n")


def run_one(
    reader: Callable[[bytes, Path], str], data: bytes, tmp: Path, timeout_s: float
) -> tuple[str, str | None]:
    """(outcome, the exception for a traceback or hang)."""
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        return reader(data, tmp), None
    except _Hang:
        return "hang", f"no answer within {timeout_s} s"
    except RgbdNavError:
        return "clean error", None
    except Exception as err:  # what this benchmark exists to find
        return "traceback", f"{type(err).__name__}: {str(err)[:120]}"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=300, help="mutated inputs per reader")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=5.0, help="[s] per input before a hang")
    ap.add_argument("--out", type=Path, help="publish into this markdown file's section")
    args = ap.parse_args()

    def on_alarm(_signum: int, _frame: Any) -> None:
        raise _Hang

    signal.signal(signal.SIGALRM, on_alarm)
    cv2.utils.logging.setLogLevel(
        cv2.utils.logging.LOG_LEVEL_SILENT
    )  # OpenCV's own stderr lines for each bad image: the outcome is counted
    rng = random.Random(args.seed)
    rows, problems, total = [], [], Counter()
    load0 = os.getloadavg()[0]  # slowest [ms] depends on it: the machine is shared
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        tmp = Path(scratch)
        for name, (reader, base) in _corpus(tmp).items():
            if run_one(reader, base, tmp, args.timeout)[0] != "ok":  # else it measures nothing
                raise SystemExit(f"{name}: the unmutated input does not read")
            counts: Counter[str] = Counter()
            slowest = 0.0
            for _ in range(args.count):
                data = mutate(rng, base)
                t = time.perf_counter()
                outcome, why = run_one(reader, data, tmp, args.timeout)
                slowest = max(slowest, time.perf_counter() - t)
                counts[outcome] += 1
                if why is not None and sum(1 for p in problems if p[0] == name) < MAX_EXAMPLES:
                    problems.append((name, why, data[:60]))
            total.update(counts)
            rows.append(
                f"| {name} | {args.count} | "
                + " | ".join(str(counts[o]) for o in OUTCOMES)
                + f" | {1e3 * slowest:.0f} |"
            )
    wall = time.perf_counter() - t0
    n = args.count * len(rows)
    lines = [
        "## Hostile inputs: mutation fuzzing of the readers (issue 28)",
        "",
        f"`bench/fuzz_inputs.py --count {args.count} --seed {args.seed}`: every reader gets "
        f"{args.count} seeded mutations of a valid input (byte edits, repeats, cuts, and "
        "spliced NaN / 1e30 / huge digit strings / aliases / deep nesting / invalid UTF-8). "
        f"{n} inputs in {wall:.1f} s on {machine('cv2', 'yaml')}, {started}, load average "
        f"{load0:.0f} at the start, {os.getloadavg()[0]:.0f} at the end.",
        "",
        "| reader | inputs | " + " | ".join(OUTCOMES) + " | slowest [ms] |",
        "|---|---:|" + "---:|" * len(OUTCOMES) + "---:|",
        *rows,
        f"| **all** | {n} | " + " | ".join(f"**{total[o]}**" for o in OUTCOMES) + " | |",
        "",
        "ok and clean error are both right answers (most mutations make an input invalid); a "
        "counted skip is a CARMEN line dropped and counted in `skipped`, a tacho line counted in "
        "`tacho_bad_lines`, a recording frame skipped and counted, or a camera YAML that does "
        "not parse (warned; its folder's source says so). A traceback is any "
        "exception other than an RgbdNavError; a hang is an input still running after "
        f"{args.timeout:g} s. This cannot see a silent wrong result: those are pinned by the "
        "unit tests named after them.",
    ]
    if problems:
        lines += ["", "Tracebacks and hangs (first inputs):", ""]
        lines += [f"- {name}: `{why}` from `{data!r}`" for name, why, data in problems]
    publish("\n".join(lines), args.out, SECTION)
    return 1 if total["traceback"] or total["hang"] else 0


if __name__ == "__main__":
    sys.exit(main())
