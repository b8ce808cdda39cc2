"""The simulator end to end: a recording on disk, deterministic per seed."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from sensors.config import CameraConfig, RobotConfig, SimConfig, build_section
from sensors.recording import Recording
from sensors.sim.simulator import camera_stamps, simulate
from sensors.tum import load_tum_trajectory
from sensors.types import NS_PER_S, WorldError

REPO = Path(__file__).resolve().parents[3]
HOUSE = REPO / "scenes" / "house.yaml"
PIONEER_DIR = REPO.parent / "shared" / "data" / "tum" / "pioneer_groundtruth"


def tree_digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def run(out: Path, seed: int, frames: int = 4, **kw: object) -> Recording:
    simulate(HOUSE, out, RobotConfig(), CameraConfig(), SimConfig(), seed=seed, frames=frames, **kw)
    return Recording.open(out)


def test_same_seed_gives_byte_identical_recordings(tmp_path: Path) -> None:
    run(tmp_path / "a", seed=11)
    run(tmp_path / "b", seed=11)
    assert tree_digest(tmp_path / "a") == tree_digest(tmp_path / "b")


def test_different_seeds_give_different_noise(tmp_path: Path) -> None:
    a, b = run(tmp_path / "a", seed=1), run(tmp_path / "b", seed=2)
    assert not np.array_equal(a.frame(0).depth_m, b.frame(0).depth_m)


def test_recording_holds_every_stream_with_consistent_stamps(tmp_path: Path) -> None:
    rec = run(tmp_path / "rec", seed=0, frames=6)
    assert len(rec) == 6
    stamps, left, right = rec.wheels()
    gt = rec.groundtruth_planar()
    imu = rec.imu()
    assert gt is not None and imu is not None
    assert np.all(np.diff(rec.rgb_stamps_ns) > 0)
    # Wheels, IMU and ground truth cover the camera frames.
    assert stamps[0] <= rec.rgb_stamps_ns[0] and gt[0][-1] >= rec.rgb_stamps_ns[-1] - 20_000_000
    assert left[0] == 0 and right[0] == 0
    assert gt[1][0] == pytest.approx(1.5) and gt[2][0] == pytest.approx(2.5)
    assert rec.scene["groundtruth_frame"] == "base_link"
    frame = rec.frame(0)
    assert frame.rgb.shape == (480, 640, 3) and frame.depth_m.dtype == np.float32
    assert 0.2 < float((frame.depth_m > 0).mean()) < 1.0


def test_duration_limits_the_recording(tmp_path: Path) -> None:
    simulate(HOUSE, tmp_path / "r", RobotConfig(), CameraConfig(), SimConfig(), duration_s=0.5)
    rec = Recording.open(tmp_path / "r")
    assert rec.rgb_stamps_ns[-1] <= 0.55 * NS_PER_S
    assert 12 <= len(rec) <= 16


def test_camera_stamps_drop_frames_and_never_go_backwards() -> None:
    sim = SimConfig(frame_drop_probability=0.2, stamp_jitter=0.02)
    capture, stamps, dropped = camera_stamps(10 * NS_PER_S, sim, np.random.default_rng(0))
    assert 30 < dropped < 90
    assert len(capture) + dropped == 301
    assert np.all(np.diff(stamps) >= 1_000_000)
    assert np.abs(stamps - capture).max() < 0.1 * NS_PER_S


def test_exactly_the_requested_frames_despite_drops(tmp_path: Path) -> None:
    sim = SimConfig(frame_drop_probability=0.3)
    simulate(HOUSE, tmp_path / "r", RobotConfig(), CameraConfig(), sim, seed=4, frames=5)
    assert len(Recording.open(tmp_path / "r")) == 5


def test_zero_frames_is_refused_with_a_reason(tmp_path: Path) -> None:
    with pytest.raises(WorldError, match="frames must be >= 1, got 0"):
        simulate(HOUSE, tmp_path / "r", RobotConfig(), CameraConfig(), SimConfig(), frames=0)
    assert not (tmp_path / "r").exists()


@pytest.mark.skipif(not PIONEER_DIR.is_dir(), reason="../shared/data (TUM pioneer) not present")
def test_replays_a_real_pioneer_trajectory_in_the_hall(tmp_path: Path) -> None:
    traj = PIONEER_DIR / "pioneer_360.groundtruth.txt"
    simulate(
        REPO / "scenes" / "pioneer_hall.yaml",
        tmp_path / "r",
        RobotConfig(),
        CameraConfig(),
        SimConfig(),
        frames=3,
        trajectory=traj,
    )
    rec = Recording.open(tmp_path / "r")
    gt = rec.groundtruth()
    assert gt is not None and len(rec) == 3
    _, first_xyz, _ = load_tum_trajectory(traj)
    # The replay starts where the mocap does (camera on the axle midpoint by default).
    assert np.allclose(gt[1][0, :2], first_xyz[0, :2], atol=0.05)


def test_a_world_with_a_geo_anchor_records_gps_fixes_near_the_truth(tmp_path: Path) -> None:
    from sensors.geo import GeoAnchor

    assert run(tmp_path / "rec", seed=3).gps() is None  # the plain house has no anchor
    world = tmp_path / "house_geo.yaml"
    anchor = "geo: {latitude: 44.98, longitude: -93.27, altitude: 256.0, heading_deg: 30.0}"
    world.write_text(HOUSE.read_text() + "\n" + anchor + "\n")
    # Few, small frames (2 Hz, 160x120): the fixes are what is tested, not the images. The
    # receiver is set by the `sim.gps_*` keys (defaults: 1 Hz, 3 m, outages).
    keys = {"camera_rate": 2.0, "gps_rate": 5, "gps_sigma": 0.5, "gps_outage_probability": 0}
    sim = build_section(SimConfig, keys, "sim")
    cam = CameraConfig(width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
    simulate(world, tmp_path / "geo", RobotConfig(), cam, sim, seed=3, duration_s=20.0)
    rec = Recording.open(tmp_path / "geo")
    gps = rec.gps()
    assert gps is not None and 99 <= len(gps) <= 101  # 5 Hz for 20 s, no outage
    t, x, y, _ = rec.groundtruth_planar()
    xy = gps.in_map(GeoAnchor(44.98, -93.27, 256.0, 30.0))
    err = xy - np.column_stack([np.interp(gps.stamps_ns, t, x), np.interp(gps.stamps_ns, t, y)])
    assert float(np.median(np.hypot(err[:, 0], err[:, 1]))) < 2 * 0.5  # sigma 0.5 m per axis
