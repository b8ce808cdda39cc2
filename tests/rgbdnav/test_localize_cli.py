"""`rgbdnav localize` as a user meets it: a map made by `rgbdnav map`, a second CARMEN log with
bad odometry in another odometry frame, global relocalisation or a given initial pose, a plain
map.yaml from "another tool", and bad maps or initial poses that end in one line or a reason."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from sensors.tum import load_tum_trajectory, yaw_from_quaternion

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "slam"))
from scan_scenes import corrupt_steps as _corrupt  # noqa: E402
from scan_scenes import write_flaser_log as _write_log  # noqa: E402

runner = CliRunner()
DEG = math.pi / 180.0  # [rad/deg]
SHARED_MAP_SCANS = 60  # scans of the mapping lap
# The second session's odometry frame: rotated and shifted from the map frame.
ODOM_FRAME = (7.0, -3.0, 1.0)  # [m, m, rad]


def _route(
    n: int, cx: float = 4.3, cy: float = 2.9, rx: float = 1.1, ry: float = 0.9, turns: float = 1.0
) -> np.ndarray:
    """(n, 3) poses on an ellipse in ROOM clear of its stub wall and pillar, heading along the
    path (``turns`` < 0 drives it clockwise)."""
    s = np.linspace(0.0, 2 * math.pi * turns, n, endpoint=False)
    x, y = cx + rx * np.cos(s), cy + ry * np.sin(s)
    yaw = np.arctan2(ry * np.cos(s), -rx * np.sin(s)) + (math.pi if turns < 0 else 0.0)
    return np.column_stack([x, y, np.angle(np.exp(1j * yaw))])


def _in_frame(poses: np.ndarray, frame: tuple[float, float, float]) -> np.ndarray:
    tx, ty, th = frame
    c, s = math.cos(th), math.sin(th)
    return np.column_stack(
        [
            c * poses[:, 0] - s * poses[:, 1] + tx,
            s * poses[:, 0] + c * poses[:, 1] + ty,
            poses[:, 2] + th,
        ]
    )


def _localize(
    source: Path,
    map_path: Path,
    out: Path,
    *extra: str,
    initial: tuple[float, float, float] | np.ndarray | None = None,
    code: int = 0,
):
    """``rgbdnav localize SOURCE --map MAP --out OUT -q [--initial-pose X Y YAW] EXTRA``; the
    result, its exit code checked."""
    args = ["localize", str(source), "--map", str(map_path), "--out", str(out), "-q", *extra]
    if initial is not None:
        args += ["--initial-pose", *(f"{v}" for v in initial)]
    result = runner.invoke(app, args)
    assert result.exit_code == code, result.output
    return result


def _trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    stamps, xyz, quat = load_tum_trajectory(path)
    return stamps, np.column_stack([xyz[:, :2], yaw_from_quaternion(quat)])


def _errors(est: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    a = np.abs(np.angle(np.exp(1j * (est[:, 2] - truth[:, 2]))))
    return d, a


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map bundle of ROOM made by `rgbdnav map` from one lap with exact odometry."""
    tmp = tmp_path_factory.mktemp("map")
    truth = _route(SHARED_MAP_SCANS)
    log = _write_log(tmp / "lap.clf", truth, truth)
    result = runner.invoke(app, ["map", str(log), "--out", str(tmp / "run"), "-q"])
    assert result.exit_code == 0, result.output
    return tmp / "run" / "map"


@pytest.fixture(scope="module")
def second_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """Three quarters of another ellipse, driven the other way; odometry 4 % long with a yaw
    bias, in another odometry frame."""
    tmp = tmp_path_factory.mktemp("session")
    truth = _route(40, cx=4.4, cy=2.8, rx=1.0, ry=0.8, turns=-0.75)
    odom = _in_frame(_corrupt(truth, 1.04, 0.5 * DEG), ODOM_FRAME)
    return _write_log(tmp / "second.clf", truth, odom, t0=900.0), truth


def test_localize_without_initial_pose_relocalises_globally_and_tracks_within_3cm(
    mapped: Path, second_session: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    log, truth = second_session
    out = tmp_path / "run"
    result = _localize(log, mapped, out)
    assert "relocalisation" in result.output
    summary = json.loads((out / "summary.json").read_text())
    c = summary["counts"]
    assert c["scans"] == len(truth)
    reloc = summary["relocalisations"]
    assert reloc["count"] == 1 and reloc["events"][0]["after"] == "start of run"
    n_before = reloc["events"][0]["scans"] - 1  # scans without a pose before the fix
    assert c["without_pose"] == n_before <= 5
    assert summary["lost_episodes"]["count"] == 0
    assert summary["map"]["kind"] == "bundle" and summary["scans_per_s"] > 0
    assert summary["confidence_when_tracking"]["median"] > 0.8
    # One TUM line per tracked scan, each close to the truth of its scan.
    stamps, est = _trajectory(out / "trajectory.tum")
    assert len(est) == c["with_pose"] == len(truth) - n_before
    d, a = _errors(est, truth[n_before:])
    assert np.median(d) < 0.03 and d.max() < 0.1, (np.median(d), d.max())
    assert np.median(a) < 1.0 * DEG
    # The per-scan table: every scan, documented header, empty pose while relocalising.
    with (out / "localization.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["stamp_s", "x_m", "y_m", "yaw_rad", "confidence", "status", "reason"]
    assert len(rows) == len(truth)
    assert rows[0]["status"] == "relocalising" and rows[0]["x_m"] == ""
    assert rows[-1]["status"] == "tracking" and rows[-1]["reason"].startswith("matched")
    assert abs(float(rows[-1]["x_m"]) - truth[-1, 0]) < 0.1
    assert abs(float(rows[0]["stamp_s"]) - 900.0) < 1e-6
    assert (out / "map.png").is_file() and (out / "config.yaml").is_file()


def test_localize_with_initial_pose_tracks_from_the_first_scan(
    mapped: Path, second_session: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    log, truth = second_session
    out = tmp_path / "run"
    _localize(log, mapped, out, initial=truth[0] + np.array([0.1, -0.08, 0.05]))  # RViz click
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["tracking"] == len(truth)
    assert summary["relocalisations"]["count"] == 0
    assert summary["initial_pose"]["cell"] == "free"
    _, est = _trajectory(out / "trajectory.tum")
    d, _ = _errors(est, truth)
    assert np.median(d) < 0.03 and d.max() < 0.1, (np.median(d), d.max())


def test_localize_with_rrd_saves_a_rerun_recording_of_poses_scans_and_map(
    mapped: Path, second_session: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    log, truth = second_session
    out = tmp_path / "run"
    rrd = out / "run.rrd"
    result = _localize(log, mapped, out, "--rrd", str(rrd), initial=truth[0])
    assert "rerun recording" in result.output
    data = rrd.read_bytes()
    # The documented entity paths are in the recording (rrd keeps them as plain strings).
    for path in (b"world/map", b"world/robot/scan", b"world/robot/trajectory", b"world/robot/pose"):
        assert path in data, path


def test_localize_in_a_plain_map_yaml_from_another_tool(
    mapped: Path, second_session: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    """Only map.yaml + map.pgm, copied out of the bundle: no graph, no log-odds."""
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    for name in ("map.yaml", "map.pgm"):
        (foreign / name).write_bytes((mapped / name).read_bytes())
    log, truth = second_session
    out = tmp_path / "run"
    _localize(log, foreign / "map.yaml", out)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["map"]["kind"] == "map.yaml"
    assert summary["relocalisations"]["count"] == 1
    n_before = summary["counts"]["without_pose"]
    _, est = _trajectory(out / "trajectory.tum")
    d, _ = _errors(est, truth[n_before:])
    assert np.median(d) < 0.03, np.median(d)


@pytest.mark.parametrize(
    ("yaml_text", "match"),
    [
        (None, "no such map"),
        (
            "image: map.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
            "occupied_thresh: 0.2\nfree_thresh: 0.6\n",
            "free_thresh",
        ),
        (
            "image: map.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
            "occupied_thresh: 0.65\nfree_thresh: 0.196\n",
            "no free cells",
        ),
    ],
    ids=["missing", "swapped-thresholds", "no-free-space"],
)
def test_localize_refuses_a_bad_map_in_one_line(
    second_session: tuple[Path, np.ndarray], tmp_path: Path, yaml_text: str | None, match: str
) -> None:
    map_yaml = tmp_path / "bad" / "map.yaml"
    map_yaml.parent.mkdir()
    if yaml_text is not None:
        # Walls and unknown only: 0 = occupied, 205 = unknown (trinary), no free pixel.
        pixels = np.full((40, 40), 205, np.uint8)
        pixels[[0, -1], :] = 0
        pixels[:, [0, -1]] = 0
        (map_yaml.parent / "map.pgm").write_bytes(b"P5\n40 40\n255\n" + pixels.tobytes())
        map_yaml.write_text(yaml_text)
    log, _ = second_session
    out = tmp_path / "run"
    text = _localize(log, map_yaml, out, code=1).output.strip()
    assert text.startswith("error:") and "\n" not in text and match in text, text
    assert not out.exists()  # refused before anything was written


def test_localize_with_an_initial_pose_in_a_wall_reports_lost_and_never_a_wrong_pose(
    mapped: Path, second_session: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    log, truth = second_session
    out = tmp_path / "run"
    _localize(log, mapped, out, initial=(8.0, 3.0, 0.0))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["initial_pose"]["cell"] in ("occupied", "unknown", "outside")
    lost = summary["lost_episodes"]
    assert lost["count"] >= 1 and "initial pose rejected" in lost["episodes"][0]["reason"]
    with (out / "localization.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["status"] == "lost" and rows[0]["x_m"] == ""
    assert any(r["status"] == "relocalising" for r in rows)
    # Whatever is tracked afterwards is right: no confident wrong pose.
    tracked = [(i, r) for i, r in enumerate(rows) if r["status"] == "tracking"]
    for i, r in tracked:
        d = math.hypot(float(r["x_m"]) - truth[i, 0], float(r["y_m"]) - truth[i, 1])
        assert d < 0.1, (i, d)


RGBD_FRAMES = 40  # [frames] of the simulated house recording (1.3 s at 30 Hz)


def test_localize_an_rgbd_recording_of_the_house_tracks_within_6cm_of_the_ground_truth(
    tmp_path: Path,
) -> None:
    """End to end: `rgbdnav simulate` records the house, a floor-plan map.yaml stands in for a
    map made by another tool, and `rgbdnav localize` (EKF odometry, depth -> scan) tracks from
    the route's start pose."""
    from rgbd_kidnap import SCENES, floor_plan_grid, rgbd_config

    from sensors.sim.world import load_world
    from slam.map_bundle import save_map_yaml

    world = load_world(SCENES / "house.yaml")
    save_map_yaml(floor_plan_grid(world, rgbd_config()), tmp_path / "map.yaml")
    rec = tmp_path / "rec"
    result = runner.invoke(
        app,
        [
            "simulate",
            str(SCENES / "house.yaml"),
            "--out",
            str(rec),
            "--frames",
            str(RGBD_FRAMES),
            "-q",
        ],
    )
    assert result.exit_code == 0, result.output
    out = tmp_path / "run"
    _localize(rec, tmp_path / "map.yaml", out, initial=world.start)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frame"] == "base_link"
    assert summary["counts"]["tracking"] == summary["counts"]["scans"] >= RGBD_FRAMES - 2
    gt = summary["vs_groundtruth"]
    assert gt["tracked_but_wrong"] == 0
    assert gt["position_error_m"]["median"] < 0.06 and gt["position_error_m"]["max"] < 0.1, gt
    assert gt["heading_error_deg"]["max"] < 2.0, gt


def test_localize_in_a_rotated_ascii_nav2_map_tracks_as_in_the_original(
    mapped: Path, second_session: tuple[Path, np.ndarray], tmp_path: Path
) -> None:
    """The bundle's map rewritten as another tool might: an ASCII (P2) PGM turned a quarter turn
    with ``origin: [x, y, 1.5708]`` so that map_server puts every cell where it was. Localising
    in it tracks as well as in the original; --format euroc writes the trajectory for evo."""
    from slam.map_bundle import decode_pgm, parse_map_yaml

    meta = parse_map_yaml(mapped / "map.yaml")
    img, _ = decode_pgm((mapped / "map.pgm").read_bytes(), "map.pgm")
    h, w = img.shape
    turned = img[::-1].T  # J_img[i_row, j] = I_yup[...]: the y-up image transposed (see below)
    # cell (col i, row j up) of the turned image lies at origin + R(90 deg) ((i+.5) r, (j+.5) r);
    # with origin x = ox + w r it is the original's cell (col w-1-j, row i)
    ox, oy, _ = meta.origin
    rows = "\n".join(" ".join(str(int(v)) for v in row) for row in turned)
    (tmp_path / "turned.pgm").write_text(f"P2\n# turned by hand\n{h} {w}\n255\n{rows}\n")
    (tmp_path / "turned.yaml").write_text(
        f"image: turned.pgm\nmode: trinary\nresolution: {meta.resolution}\n"
        f"origin: [{ox + w * meta.resolution}, {oy}, {math.pi / 2}]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    log, truth = second_session
    out = tmp_path / "run"
    result = _localize(log, tmp_path / "turned.yaml", out, "--format", "euroc", initial=truth[0])
    _, est = _trajectory(out / "trajectory.tum")
    d, _ = _errors(est, truth)
    assert np.median(d) < 0.03 and d.max() < 0.1, (np.median(d), d.max())
    assert "trajectory.euroc.csv" in result.output
    evo = runner.invoke(
        app,
        [
            "eval",
            str(out / "trajectory.euroc.csv"),
            "-r",
            str(out / "trajectory.tum"),
            "--align",
            "none",
        ],
    )
    assert evo.exit_code == 0, evo.output
    assert "ATE [m]     rmse 0.000000" in evo.output


def test_seed_without_a_world_is_refused_not_ignored(
    second_session: tuple[Path, np.ndarray], mapped: Path, tmp_path: Path
) -> None:
    log, _ = second_session
    result = _localize(log, mapped, tmp_path / "run", "--seed", "3", code=1)
    assert result.output.strip() == (
        "error: --seed: only with a world SOURCE (it seeds the rendering); it would be ignored here"
    )
    assert not (tmp_path / "run").exists()
