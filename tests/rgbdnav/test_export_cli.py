"""`rgbdnav export RUN --to mcap`: real runs made in tmp_path, written as rosbag2/MCAP folders and
read back with rosbags' AnyReader, as Foxglove or `ros2 bag play` would read them."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.config import load_config
from sensors.sim.simulator import simulate
from sensors.sim.world import floor_plan, load_world
from sensors.tum import load_tum_trajectory, yaw_from_quaternion
from slam.geometry import ominus, oplus, wrap_angle
from slam.map_bundle import load_bundle, save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "slam"))
from scan_scenes import corrupt_steps, write_flaser_log  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
MIT = DATA / "carmen" / "mit-csail.clf"
needs_mit = pytest.mark.skipif(not MIT.is_file(), reason="../shared/data/carmen is absent")
runner = CliRunner()
TOL_M, TOL_RAD = 1e-6, 1e-6  # [m], [rad]: transforms are float64 all the way


def _route(n: int) -> np.ndarray:
    s = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    x, y = 4.0 + 2.2 * np.cos(s), 3.0 + 1.3 * np.sin(s)
    return np.column_stack([x, y, np.arctan2(1.3 * np.cos(s), -2.2 * np.sin(s))])


def _trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    stamps, xyz, quat = load_tum_trajectory(path)
    return stamps, np.column_stack([xyz[:, :2], yaw_from_quaternion(quat)])


def _cli(*args: str) -> Any:
    return runner.invoke(app, [str(a) for a in args])


def _read(bag: Path) -> dict[str, list[tuple[int, Any]]]:
    """topic -> [(bag record time, message)] in the bag's order."""
    out: dict[str, list[tuple[int, Any]]] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    return out


def _ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _planar(tf: Any) -> np.ndarray:
    q = tf.transform.rotation
    yaw = 2 * math.atan2(q.z, q.w)
    return np.array([tf.transform.translation.x, tf.transform.translation.y, yaw])


def _chain(msgs: list[tuple[int, Any]]) -> tuple[np.ndarray, np.ndarray, set[tuple[str, str]]]:
    """Stamps and map -> base_link poses composed from each /tf message's transforms."""
    stamps, poses, edges = [], [], set()
    for t, m in msgs:
        by_child = {tf.child_frame_id: tf for tf in m.transforms}
        edges |= {(tf.header.frame_id, tf.child_frame_id) for tf in m.transforms}
        assert all(_ns(tf.header.stamp) == t for tf in m.transforms)
        p = oplus(_planar(by_child["odom"]), _planar(by_child["base_link"]))
        stamps.append(t)
        poses.append(p)
    return np.array(stamps, dtype=np.int64), np.array(poses), edges


def _same_poses(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape
    assert np.abs(a[:, :2] - b[:, :2]).max() < TOL_M
    assert np.abs(wrap_angle(a[:, 2] - b[:, 2])).max() < TOL_RAD


@pytest.fixture(scope="module")
def laser_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("laser")
    truth = _route(60)  # odometry drifts, so map -> odom moves away from the identity
    log = write_flaser_log(d / "room.clf", truth, corrupt_steps(truth, 1.05, math.radians(0.4)))
    res = _cli("map", log, "--out", d / "run", "-q")
    assert res.exit_code == 0, res.output
    return d / "run"


@pytest.fixture(scope="module")
def rgbd_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("rgbd")
    cfg = load_config()
    simulate(REPO / "scenes" / "house.yaml", d / "rec", cfg.robot, cfg.camera, cfg.sim, frames=24)
    res = _cli("map", d / "rec", "--out", d / "run", "-q", "--set", "robot.camera_height=0.52")
    assert res.exit_code == 0, res.output
    return d / "run"


def test_a_laser_map_run_becomes_a_bag_whose_tf_chain_reproduces_the_trajectory(
    laser_run: Path, tmp_path: Path
) -> None:
    bag = tmp_path / "bag"
    res = _cli("export", laser_run, "--to", "mcap", "--out", bag)
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in bag.iterdir()) == ["bag.mcap", "metadata.yaml"]
    assert "bag.mcap" in (bag / "metadata.yaml").read_text()
    msgs = _read(bag)
    assert set(msgs) == {"/tf", "/tf_static", "/map", "/scan", "/odom", "/trajectory"}
    stamps, poses = _trajectory(laser_run / "trajectory.tum")
    t, composed, edges = _chain(msgs["/tf"])
    assert edges == {("map", "odom"), ("odom", "base_link")}
    assert np.array_equal(t, stamps)  # one /tf per trajectory pose, at its stamp, in order
    _same_poses(composed, poses)
    # map -> odom at each keyframe is the mapper's correction there: pose (+) odom pose^-1.
    bundle = load_bundle(laser_run / "map")
    at_key = np.searchsorted(stamps, bundle.keyframe_stamps_ns)
    map_odom = np.array([_planar(m.transforms[0]) for _, m in msgs["/tf"]])
    correction = oplus(bundle.keyframe_poses, ominus(bundle.keyframe_odom_poses, np.zeros(3)))
    _same_poses(map_odom[at_key], correction)
    assert np.hypot(*map_odom[-1, :2]) > 0.05
    # /odom: odom -> base_link at the same stamps, composing with /tf's map -> odom.
    odom = msgs["/odom"]
    assert [ns for ns, _ in odom] == stamps.tolist()
    assert all(m.header.frame_id == "odom" and m.child_frame_id == "base_link" for _, m in odom)
    # The map is the bundle's grid, cell for cell, with Nav2's values and geometry.
    ((t_map, grid),) = msgs["/map"]
    g = bundle.grid.geometry
    assert t_map == stamps[0] and grid.header.frame_id == "map"
    assert (grid.info.width, grid.info.height) == (g.width, g.height)
    assert grid.info.resolution == pytest.approx(g.resolution)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == (g.origin_x, g.origin_y)
    expected = bundle.grid.trinary(bundle.occupied_thresh, bundle.free_thresh)
    assert np.array_equal(np.asarray(grid.data).reshape(g.height, g.width), expected)
    assert set(np.unique(expected)) == {-1, 0, 100}
    # Scans: the keyframes', at their stamps, in the laser frame the static tf hangs off base_link.
    scans = msgs["/scan"]
    assert [ns for ns, _ in scans] == bundle.keyframe_stamps_ns.tolist()
    assert np.array_equal(scans[0][1].ranges, bundle.scans[0].ranges)
    assert {m.header.frame_id for _, m in scans} == {"laser"}
    ((_, static),) = msgs["/tf_static"]
    assert {(tf.header.frame_id, tf.child_frame_id) for tf in static.transforms} == {
        ("base_link", "laser")
    }  # a laser log has no camera
    ((_, path),) = msgs["/trajectory"]
    assert len(path.poses) == len(stamps) and path.header.frame_id == "map"
    assert [_ns(p.header.stamp) for p in path.poses] == stamps.tolist()


def test_an_rgbd_map_run_carries_its_images_camera_mount_and_odometry(
    rgbd_run: Path, tmp_path: Path
) -> None:
    bag = tmp_path / "bag"
    res = _cli("export", rgbd_run, "--to", "mcap", "--out", bag)
    assert res.exit_code == 0, res.output
    msgs = _read(bag)
    assert {"/camera/color/image_raw/compressed", "/camera/color/camera_info"} <= set(msgs)
    stamps, poses = _trajectory(rgbd_run / "trajectory.tum")
    t, composed, _ = _chain(msgs["/tf"])
    assert np.array_equal(t, stamps)
    _same_poses(composed, poses)
    # odom -> base_link is the run's own odometry (odom.tum) at the trajectory's stamps.
    o_stamps, o_poses = _trajectory(rgbd_run / "odom.tum")
    odom_tf = np.array(
        [
            _planar(next(tf for tf in m.transforms if tf.child_frame_id == "base_link"))
            for _, m in msgs["/tf"]
        ]
    )
    inside = np.isin(stamps, o_stamps)
    assert inside.sum() >= len(stamps) // 2
    _same_poses(odom_tf[inside], o_poses[np.searchsorted(o_stamps, stamps[inside])])
    # Images: the recording's PNG bytes as they are, at their own stamps, with the intrinsics.
    source = Path(json.loads((rgbd_run / "summary.json").read_text())["source"])
    images = msgs["/camera/color/image_raw/compressed"]
    files = sorted((source / "rgb").glob("*.png"))
    assert len(images) == len(files) == 24
    assert images[0][1].format == "png"
    assert bytes(images[0][1].data) == files[0].read_bytes()
    assert [ns for ns, _ in images] == sorted(ns for ns, _ in images)
    # Depth: registered 16UC1 millimetres, one per recorded depth image.
    depth = msgs["/camera/aligned_depth_to_color/image_raw"]
    counts = cv2.imread(str(sorted((source / "depth").glob("*.png"))[0]), cv2.IMREAD_UNCHANGED)
    mm = np.frombuffer(bytes(depth[0][1].data), "<u2").reshape(480, 640)
    assert len(depth) == 24 and depth[0][1].encoding == "16UC1"
    assert np.abs(mm.astype(np.int64) - np.rint(counts / 5.0)).max() == 0  # 5000 counts/m
    info = msgs["/camera/color/camera_info"][0][1]
    assert info.k[0] == pytest.approx(525.0) and info.width == 640
    # The camera mount from the run's config (camera_height set to 0.52 on the command line).
    ((_, static),) = msgs["/tf_static"]
    mount = {tf.child_frame_id: tf for tf in static.transforms}
    assert mount["camera_link"].header.frame_id == "base_link"
    assert mount["camera_link"].transform.translation.z == pytest.approx(0.52)
    assert mount["camera_color_optical_frame"].header.frame_id == "camera_link"


def test_an_odometry_run_has_no_map_frame_and_no_map(rgbd_run: Path, tmp_path: Path) -> None:
    source = Path(json.loads((rgbd_run / "summary.json").read_text())["source"])
    run = tmp_path / "odo"
    assert _cli("odometry", source, "--out", run, "-q", "--no-vo").exit_code == 0
    res = _cli("export", run, "--to", "mcap", "--no-images", "-q")
    assert res.exit_code == 0, res.output
    msgs = _read(run / "rosbag2")
    assert set(msgs) == {"/tf", "/tf_static", "/odom", "/trajectory"}
    stamps, poses = _trajectory(run / "fused.tum")
    tfs = msgs["/tf"]
    assert {(tf.header.frame_id, tf.child_frame_id) for _, m in tfs for tf in m.transforms} == {
        ("odom", "base_link")
    }
    _same_poses(np.array([_planar(m.transforms[0]) for _, m in tfs]), poses)
    twist = np.array([m.twist.twist.linear.x for _, m in msgs["/odom"]])
    assert twist.max() > 0.05  # the simulated robot drives forward


def test_exporting_again_replaces_the_bag_atomically(laser_run: Path, tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    for _ in range(2):
        assert _cli("export", laser_run, "--to", "mcap", "--out", bag, "-q").exit_code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]  # no staging folder left
    assert len(_read(bag)["/map"]) == 1


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: d.mkdir(), "no summary.json"),
        (lambda d: None, "no such run folder"),
        (lambda d: (d.mkdir(), (d / "summary.json").write_text("{oops")), "unreadable summary"),
        (
            lambda d: (d.mkdir(), (d / "summary.json").write_text('{"command": "eval"}')),
            "nothing to export from a eval run",
        ),
        (
            lambda d: (d.mkdir(), (d / "summary.json").write_text('{"command": "map"}')),
            "without trajectory.tum",
        ),
    ],
)
def test_a_folder_with_nothing_to_export_is_one_error_line(
    tmp_path: Path, make: Any, message: str
) -> None:
    run = tmp_path / "run"
    make(run)
    res = _cli("export", run, "--to", "mcap")
    assert res.exit_code == 1
    assert res.output.startswith("error: ") and message in res.output, res.output
    assert not (run / "rosbag2").exists()


def test_a_corrupt_run_fails_in_one_line_and_writes_nothing(
    laser_run: Path, tmp_path: Path
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    for name in ("summary.json", "config.yaml", "trajectory.tum"):
        (run / name).write_bytes((laser_run / name).read_bytes())
    (run / "map").mkdir()  # the bundle lost its files
    res = _cli("export", run, "--to", "mcap")
    assert res.exit_code == 1 and res.output.startswith("error: "), res.output
    assert "graph.json" in res.output
    (run / "map").rmdir()
    with (run / "trajectory.tum").open("a") as fh:
        fh.write("12 nan 0 0 0 0 0 1\n")
    res = _cli("export", run, "--to", "mcap")
    assert res.exit_code == 1 and "trajectory.tum" in res.output, res.output
    assert sorted(p.name for p in run.iterdir()) == [
        "config.yaml",
        "summary.json",
        "trajectory.tum",
    ]


def test_export_will_not_overwrite_a_folder_that_is_not_a_bag(
    laser_run: Path, tmp_path: Path
) -> None:
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    res = _cli("export", laser_run, "--to", "mcap", "--out", precious)
    assert res.exit_code == 1 and "not a rosbag2 folder" in res.output
    assert (precious / "notes.txt").read_text() == "keep me"
    res = _cli("export", laser_run, "--to", "bag", "--out", tmp_path / "x")
    assert res.exit_code == 1 and "unknown format" in res.output


def test_a_localize_run_carries_the_map_it_localised_in(laser_run: Path, tmp_path: Path) -> None:
    _, poses = _trajectory(laser_run / "trajectory.tum")
    run = tmp_path / "loc"
    x, y, yaw = (str(v) for v in poses[0])
    res = _cli(
        "localize",
        laser_run.parent / "room.clf",
        "--map",
        laser_run / "map",
        "--initial-pose",
        x,
        y,
        yaw,
        "--out",
        run,
        "-q",
    )
    assert res.exit_code == 0, res.output
    assert _cli("export", run, "--to", "mcap", "-q").exit_code == 0
    msgs = _read(run / "rosbag2")
    assert set(msgs) == {"/tf", "/tf_static", "/map", "/odom", "/trajectory"}  # no scans kept
    stamps, loc = _trajectory(run / "trajectory.tum")
    t, composed, _ = _chain(msgs["/tf"])
    assert np.array_equal(t, stamps)
    _same_poses(composed, loc)
    bundle = load_bundle(laser_run / "map")
    ((_, grid),) = msgs["/map"]
    expected = bundle.grid.trinary(bundle.occupied_thresh, bundle.free_thresh)
    assert np.array_equal(np.asarray(grid.data).reshape(expected.shape), expected)


def test_a_live_run_with_its_recording_exports_images_and_the_optimised_path(
    live_recorded_run: tuple[Path, Path], tmp_path: Path
) -> None:
    run, rec = live_recorded_run  # `live --duration 5 --record REC`, shared with test_live_cli
    bag = tmp_path / "rosbag2"  # the shared run stays as it was
    assert _cli("export", run, "--to", "mcap", "--out", bag, "-q").exit_code == 0
    msgs = _read(bag)
    stamps, poses = _trajectory(run / "trajectory.tum")
    t, composed, _ = _chain(msgs["/tf"])
    assert np.array_equal(t, stamps)
    _same_poses(composed, poses)
    opt_stamps, opt = _trajectory(run / "trajectory_optimised.tum")
    ((_, path),) = msgs["/trajectory"]
    assert [_ns(p.header.stamp) for p in path.poses] == opt_stamps.tolist()
    path_xy = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses])
    assert np.abs(path_xy - opt[:, :2]).max() < TOL_M
    images = msgs["/camera/color/image_raw/compressed"]
    index = (rec / "rgb.txt").read_text().splitlines()
    recorded = len([ln for ln in index if ln and not ln.startswith("#")])
    assert 0 < len(images) <= recorded
    assert all(stamps[0] <= ns <= stamps[-1] for ns, _ in images)
    assert len(msgs["/scan"]) == len(load_bundle(run / "map").keyframe_ids)


def test_foxglove_s_own_mcap_reader_decodes_every_message_in_log_time_order(
    laser_run: Path, tmp_path: Path
) -> None:
    mcap_reader = pytest.importorskip("mcap.reader")  # the dev extra installs it
    decoder = pytest.importorskip("mcap_ros2.decoder")
    bag = tmp_path / "bag"
    assert _cli("export", laser_run, "--to", "mcap", "--out", bag, "-q").exit_code == 0
    with (bag / "bag.mcap").open("rb") as fh:
        reader = mcap_reader.make_reader(fh, decoder_factories=[decoder.DecoderFactory()])
        decoded = list(reader.iter_decoded_messages(log_time_order=True))
    times = [m.log_time for _, _, m, _ in decoded]
    assert times == sorted(times)
    assert {c.topic for _, c, _, _ in decoded} == set(_read(bag))
    grids = [ros for _, c, _, ros in decoded if c.topic == "/map"]
    bundle = load_bundle(laser_run / "map")
    expected = bundle.grid.trinary(bundle.occupied_thresh, bundle.free_thresh)
    assert np.array_equal(np.asarray(grids[0].data, np.int8).reshape(expected.shape), expected)


def test_the_exported_bag_maps_again_like_the_run_it_came_from(
    rgbd_run: Path, tmp_path: Path
) -> None:
    bag = tmp_path / "bag"
    assert _cli("export", rgbd_run, "--to", "mcap", "--out", bag, "-q").exit_code == 0
    res = _cli("map", bag, "--out", tmp_path / "again", "-q")  # colour, depth, info, /odom
    assert res.exit_code == 0, res.output
    stamps, before = _trajectory(rgbd_run / "trajectory.tum")
    again_stamps, after = _trajectory(tmp_path / "again" / "trajectory.tum")
    assert np.array_equal(again_stamps, stamps)
    # /odom is fused differentially, so the new map frame starts at the first pose: compare
    # the motion relative to the first pose.
    rel_before, rel_after = ominus(before[0], before), ominus(after[0], after)
    assert np.abs(rel_before[:, :2] - rel_after[:, :2]).max() < 0.05


@needs_mit
def test_a_map_of_the_real_mit_csail_log_exports_with_its_trajectory_intact(tmp_path: Path) -> None:
    lines = [ln for ln in MIT.read_text().splitlines() if ln.startswith("FLASER")][:150]
    log = tmp_path / "mit150.clf"
    log.write_text("\n".join(lines) + "\n")
    assert _cli("map", log, "--out", tmp_path / "run", "-q").exit_code == 0
    assert _cli("export", tmp_path / "run", "--to", "mcap", "-q").exit_code == 0
    msgs = _read(tmp_path / "run" / "rosbag2")
    stamps, poses = _trajectory(tmp_path / "run" / "trajectory.tum")
    t, composed, _ = _chain(msgs["/tf"])
    assert np.array_equal(t, stamps) and len(t) == 150
    _same_poses(composed, poses)
    assert len(msgs["/scan"]) == len(load_bundle(tmp_path / "run" / "map").keyframe_ids)
    assert len(msgs["/scan"][0][1].ranges) == 361  # the SICK's beams, as logged


def test_a_navigate_run_exports_what_the_robot_believed_in_the_map_it_used(
    tmp_path: Path,
) -> None:
    world = REPO / "scenes" / "house.yaml"
    plan = floor_plan(load_world(world))
    h, w = plan.occupied.shape
    grid = OccupancyGrid.from_occupancy_values(
        GridGeometry(plan.resolution, plan.origin_x, plan.origin_y, w, h),
        np.where(plan.occupied, 100, 0),
    )
    save_map_yaml(grid, tmp_path / "house.yaml")
    run = tmp_path / "nav"
    res = _cli(
        "navigate",
        "--map",
        tmp_path / "house.yaml",
        "--sim",
        world,
        "--goal",
        "2.5",
        "2.5",
        "--out",
        run,
        "-q",
    )
    assert res.exit_code == 0, res.output
    assert _cli("export", run, "--to", "mcap", "-q").exit_code == 0
    msgs = _read(run / "rosbag2")
    stamps, believed = _trajectory(run / "estimated.tum")
    t, composed, _ = _chain(msgs["/tf"])
    assert np.array_equal(t, stamps)
    _same_poses(composed, believed)
    ((_, occ),) = msgs["/map"]
    expected = grid.trinary(0.65, 0.25)  # map_server's reading of the trinary PGM
    assert np.array_equal(np.asarray(occ.data).reshape(h, w), expected)
