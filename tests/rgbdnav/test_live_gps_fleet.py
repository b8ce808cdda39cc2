"""`rgbdnav live --fleet F --robot NAME` with GPS: a simulated robot in a world with a geo anchor
carries the simulated receiver; localising in its fleet map (placed in the world by the fleet's
T_world_map, not the identity) it drives the world's route, its fixes go to the localiser's
global-search prior (slam.localization.GpsPrior, as `localize --gps`), and the run writes
gps.txt, the run chart and a summary that world-view draws where the fleet puts the map. A real
camera (TUM RGB-D frames, no board) takes its T_world_map and keepout from the fleet file too."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.live.run import LiveOptions, LiveRun
from sensors.gps import read_gps_txt
from sensors.sim.world import floor_plan, load_world
from slam.geometry import ominus, oplus
from slam.map_bundle import save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid, warp_to_geometry

# Live runs against the wall clock: `make test` runs these alone, after the parallel part.
pytestmark = pytest.mark.realtime

REPO = Path(__file__).resolve().parents[2]
HOUSE = REPO / "scenes" / "house.yaml"
DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
CABINET = DATA / "kinect" / "tum_fr3_cabinet_keyframes"
GEO = "geo: {latitude: 44.98, longitude: -93.27, altitude: 256.0, heading_deg: 0.0}\n"
T_WORLD_MAP = (20.0, -5.0, 0.3)  # [m, m, rad] where the fleet puts r1's map frame
runner = CliRunner()


def _map_in_its_own_frame(world_file: Path, out: Path) -> Path:
    """The world's floor plan as a Nav2 map whose frame sits at T_WORLD_MAP in the world."""
    fp = floor_plan(load_world(world_file))
    h, w = fp.occupied.shape
    src = GridGeometry(fp.resolution, fp.origin_x, fp.origin_y, w, h)
    x0, y0 = fp.origin_x, fp.origin_y
    x1, y1 = x0 + w * fp.resolution, y0 + h * fp.resolution
    box = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x0, y1, 0.0], [x1, y1, 0.0]])
    in_map = ominus(np.array(T_WORLD_MAP), box)
    lo, hi = in_map[:, :2].min(axis=0), in_map[:, :2].max(axis=0)
    dst = GridGeometry.from_bounds(lo[0], lo[1], hi[0], hi[1], fp.resolution)
    values = np.where(fp.occupied, 100.0, 0.0).astype(np.float32)
    T_map_world = ominus(np.array(T_WORLD_MAP), np.zeros(3))
    warped = warp_to_geometry(values, src, T_map_world, dst, fill=-1.0)
    grid = OccupancyGrid.from_occupancy_values(dst, np.round(warped).astype(np.int8))
    save_map_yaml(grid, out)
    return out


@pytest.mark.slow
def test_a_fleet_robot_with_gps_drives_and_tracks_in_its_placed_map_and_world_view_places_it(
    tmp_path: Path,
) -> None:
    world = tmp_path / "house_geo.yaml"
    world.write_text(HOUSE.read_text() + GEO)
    _map_in_its_own_frame(world, tmp_path / "r1.yaml")
    x, y, yaw = T_WORLD_MAP
    (tmp_path / "fleet.yaml").write_text(
        "robots:\n  - name: r1\n    map: r1.yaml\n"
        f"    T_world_map: {{x: {x}, y: {y}, yaw: {yaw}}}\n"
    )
    out = tmp_path / "runs" / "r1"
    # The world's route (world frame) driven in r1's map frame; 10 Hz for a loaded machine.
    # 8 s from the first frame: 7 fixes and 1.6 m towards the first waypoint at load 22.
    live = LiveRun(
        LiveOptions(
            out=out,
            world=world,
            fleet=tmp_path / "fleet.yaml",
            robot="r1",
            duration_s=8.0,
            overrides=["sim.camera_rate=10"],
        )
    )
    live.execute()
    s = live.summary
    assert s["errors"] == [] and s["mode"] == "localization"
    assert s["robot"]["T_world_map"] == pytest.approx(list(T_WORLD_MAP))
    assert s["robot"]["map"] == str((tmp_path / "r1.yaml").resolve())
    assert s["robot"]["start_in_world"] == [1.5, 2.5, 0.0]  # the world's start
    # The receiver's fixes: in gps.txt, about 1 Hz, and handed to the localiser.
    fixes = read_gps_txt(out / "gps.txt")
    assert len(fixes) == s["gps"]["fixes"] >= 4 and s["gps"]["source"] == "simulated receiver"
    assert s["gps"]["fixes_used_by_localiser"] >= 1
    assert (out / "gps.png").stat().st_size > 5_000
    # Fixes through the map's anchor (the world's moved by T_world_map) lie around the pose.
    assert s["gps"]["gps_vs_localiser"]["median_m"] < 3 * s["gps"]["median_sigma_m"]
    # Told its start (the world's, turned into its map frame), it tracks; placed by the
    # fleet's T_world_map its poses are the truth, and it drove towards the route's first
    # waypoint (given in the world, driven in its map frame).
    assert s["counts"].get("localizer_tracking", 0) > 0, s["counts"]
    track = np.loadtxt(out / "trajectory.tum", comments="#", ndmin=2)
    truth = np.loadtxt(out / "groundtruth.tum", comments="#", ndmin=2)
    placed = oplus(np.array(T_WORLD_MAP), np.column_stack([track[:, 1:3], np.zeros(len(track))]))
    k = np.clip(np.searchsorted(truth[:, 0], track[:, 0]), 0, len(truth) - 1)
    assert np.median(np.hypot(*(placed[:, :2] - truth[k, 1:3]).T)) < 0.2
    first_goal = np.array([4.5, 1.5])
    assert np.hypot(*(truth[-1, 1:3] - first_goal)) < np.hypot(*(truth[0, 1:3] - first_goal)) - 0.3
    # world-view draws the run where the fleet put its map (over the world's floor plan).
    picture = tmp_path / "world.png"
    shown = runner.invoke(app, ["world-view", str(tmp_path / "runs"), "--out", str(picture)])
    assert shown.exit_code == 0, shown.output
    assert f"world -> r1/map: x={x:g} y={y:g} yaw={yaw:g}" in shown.output
    assert picture.stat().st_size > 5_000


@pytest.mark.skipif(not CABINET.is_dir(), reason="../shared/data/kinect is absent")
def test_a_real_camera_run_takes_its_t_world_map_and_keepout_from_the_fleet(
    tmp_path: Path,
) -> None:
    _map_in_its_own_frame(HOUSE, tmp_path / "r2.yaml")
    _map_in_its_own_frame(HOUSE, tmp_path / "r2_keepout.yaml")
    x, y, yaw = T_WORLD_MAP
    (tmp_path / "fleet.yaml").write_text(
        "robots:\n  - name: r2\n    map: r2.yaml\n    keepout: r2_keepout.yaml\n"
        f"    T_world_map: {{x: {x}, y: {y}, yaw: {yaw}}}\n"
    )
    args = ["live", "--out", str(tmp_path / "runs"), "--camera", str(CABINET), "--board", "none"]
    fleet = ["--fleet", str(tmp_path / "fleet.yaml"), "--robot", "r2"]
    result = runner.invoke(app, [*args, *fleet, "--duration", "2", "-q"])
    assert result.exit_code == 0, result.output
    s = json.loads((tmp_path / "runs" / "r2" / "summary.json").read_text())
    assert s["robot"]["T_world_map"] == pytest.approx(list(T_WORLD_MAP))
    assert s["robot"]["keepout"] == str((tmp_path / "r2_keepout.yaml").resolve())
    assert s["robot"]["T_world_map_from"].endswith("fleet.yaml: T_world_map")
    # world-view places the real robot's run (its map and keepout) where the fleet puts it.
    picture = tmp_path / "world.png"
    shown = runner.invoke(app, ["world-view", str(tmp_path / "runs"), "--out", str(picture)])
    assert shown.exit_code == 0, shown.output
    assert f"world -> r2/map: x={x:g} y={y:g} yaw={yaw:g}" in shown.output
    # Another map than the fleet's cannot be placed by it; a robot it lacks is named.
    other = runner.invoke(app, [*args, *fleet, "--map", str(tmp_path / "r2_keepout.yaml")])
    assert other.exit_code == 1 and "is not robot r2's map" in other.output, other.output
    missing = runner.invoke(app, [*args, "--fleet", str(tmp_path / "fleet.yaml"), "--robot", "r9"])
    assert missing.exit_code == 1 and "no robot named 'r9'" in missing.output, missing.output


def test_a_recorded_sources_fixes_go_through_the_same_door_on_the_cameras_clock(
    tmp_path: Path,
) -> None:
    from types import SimpleNamespace

    from sensors.geo import GeoAnchor
    from sensors.gps import GpsStream
    from slam.localization import GpsPrior

    anchor = GeoAnchor(44.98, -93.27, 256.0, 0.0)
    lat, lon, alt = anchor.to_wgs84(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 5.0]))
    s = 1_000_000_000
    recorded = GpsStream(np.array([s, 2 * s, 3 * s]), lat, lon, alt, np.full(3, 2.5))
    live = LiveRun(LiveOptions(out=tmp_path / "real", camera="openni://", board="none"))
    # As a bag's NavSatFix or a recording's gps.txt replayed live: stamps on the camera's clock.
    live.camera_src = SimpleNamespace(stamp_offset_ns=500)  # type: ignore[assignment]
    live._recorded_gps, live.map_anchor = recorded, anchor
    live._gps_prior = GpsPrior(None)  # type: ignore[arg-type]  # fixes queue for the localiser
    live._replay_gps(2 * s + 500)  # a frame at 2 s (camera clock): two fixes are due
    assert live.gps_writer.count == 2 and live.gps_q.qsize() == 2
    live._replay_gps(10 * s)
    live.gps_writer.close()
    back = read_gps_txt(tmp_path / "real" / "gps.txt")
    assert back.stamps_ns.tolist() == [s + 500, 2 * s + 500, 3 * s + 500]
    queued = [live.gps_q.get_nowait() for _ in range(3)]
    assert np.allclose([q[1] for q in queued], [[1, 0], [2, 0], [3, 5]], atol=1e-6)
    assert [q[2] for q in queued] == [2.5] * 3
