"""`rgbdnav fleet align / show` and `rgbdnav geo` on real logs: a Radish CARMEN log cut into two
overlapping robots, the second's odometry moved 89 m and turned 115 deg, each mapped by the mapper,
aligned without a guess; a map of another building refused. And `fleet show` on two simulated
robots' maps, each drawn where its T_world_map places it."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.commands.fleet import load_layers
from rgbdnav.live.world_view import to_world
from rgbdnav.visualize import occupied_cells_xy
from rgbdnav.world_picture import TINTS_RGB, world_geometry
from sensors.safe_yaml import read_yaml
from slam.fleet import load_fleet
from slam.geometry import oplus, wrap_angle
from slam.map_bundle import load_bundle, load_map, load_map_yaml
from slam.occupancy_grid import GridGeometry

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
from fleet_split_log import read_log_lines, split  # noqa: E402

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
ACES = DATA / "radish" / "aces-corrected.log.gz"
OREBRO = DATA / "radish" / "orebro-corrected.log.gz"
needs_data = pytest.mark.skipif(
    not (ACES.is_file() and OREBRO.is_file()), reason="../shared/data/radish is absent"
)
runner = CliRunner()
SHIFT = np.array([80.0, -40.0, 2.0])  # [m, m, rad] B's odometry frame moved in A's
REFERENCE_TOL_M, REFERENCE_TOL_DEG = 0.5, 1.0  # against the two maps' shared keyframes
SHIFT_TOL_M, SHIFT_TOL_DEG = 3.0, 2.0  # against the odometry shift (each map drifts from it)


def _invoke(*args: object):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory, orebro_map: Path) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fleet")
    text_a, text_b = split(read_log_lines(ACES), 0.6, 0.4, SHIFT)
    (root / "a.log").write_text(text_a)
    (root / "b.log").write_text(text_b)
    out = {}
    for name, log in (("a", root / "a.log"), ("b", root / "b.log")):
        result = _invoke("map", log, "--out", root / name, "-q")
        assert result.exit_code == 0, result.output
        out[name] = root / name / "map"
    out["other"] = orebro_map / "map"  # another building: `rgbdnav map` of the orebro log
    out["root"] = root
    return out


def _keyframe_reference(a: Path, b: Path) -> np.ndarray:
    """B's map frame in A's from the keyframes both maps hold (same scans): median of
    pose_a (+) pose_b^-1."""
    ka, kb = load_bundle(a), load_bundle(b)
    _, ia, ib = np.intersect1d(ka.keyframe_stamps_ns, kb.keyframe_stamps_ns, return_indices=True)
    assert len(ia) > 20
    pb = kb.keyframe_poses[ib]
    c, s = np.cos(pb[:, 2]), np.sin(pb[:, 2])
    inv = np.column_stack([-(c * pb[:, 0] + s * pb[:, 1]), s * pb[:, 0] - c * pb[:, 1], -pb[:, 2]])
    t = oplus(ka.keyframe_poses[ia], inv)
    yaw = t[0, 2] + np.median(wrap_angle(t[:, 2] - t[0, 2]))
    return np.array([np.median(t[:, 0]), np.median(t[:, 1]), yaw])


@needs_data
@pytest.mark.slow
def test_align_recovers_the_second_robot_frame_on_a_real_log(maps: dict[str, Path]) -> None:
    out = maps["root"] / "align"
    result = _invoke("fleet", "align", maps["a"], maps["b"], "--out", out)
    assert result.exit_code == 0, result.output
    doc = read_yaml(out / "alignment.yaml")
    got = np.array([doc["x"], doc["y"], doc["yaw"]])
    ref = _keyframe_reference(maps["a"], maps["b"])
    assert np.hypot(*(got[:2] - ref[:2])) < REFERENCE_TOL_M
    assert abs(math.degrees(wrap_angle(got[2] - ref[2]))) < REFERENCE_TOL_DEG
    c, s = math.cos(SHIFT[2]), math.sin(SHIFT[2])
    known = np.array([-(c * SHIFT[0] + s * SHIFT[1]), s * SHIFT[0] - c * SHIFT[1], -SHIFT[2]])
    assert np.hypot(*(got[:2] - known[:2])) < SHIFT_TOL_M
    assert abs(math.degrees(wrap_angle(got[2] - known[2]))) < SHIFT_TOL_DEG
    assert doc["confidence"] > 0.5 and doc["overlap"]["wall_matched_m"] > 50
    merged = load_map_yaml(out / "merged" / "map.yaml")  # a plain Nav2 map of both
    assert merged.occupied_mask().sum() > load_bundle(maps["a"]).grid.occupied_mask().sum()
    # The written fleet file draws both robots, each in its own tint.
    shown = _invoke("fleet", "show", out / "fleet.yaml", "--out", maps["root"] / "show")
    assert shown.exit_code == 0, shown.output
    img = cv2.imread(str(maps["root"] / "show" / "fleet.png"))[:, :, ::-1]
    for tint in TINTS_RGB[:2]:
        assert np.count_nonzero(np.all(img == tint.astype(np.uint8), axis=2)) > 1000
    assert (maps["root"] / "show" / "fleet.rrd").stat().st_size > 10_000


@needs_data
@pytest.mark.slow
def test_maps_of_two_buildings_exit_1_with_a_sentence(maps: dict[str, Path]) -> None:
    out = maps["root"] / "refused"
    result = _invoke("fleet", "align", maps["a"], maps["other"], "--out", out)
    assert result.exit_code == 1
    assert "error: cannot align the maps" in result.output
    assert not (out / "alignment.yaml").exists()


@needs_data
@pytest.mark.slow
def test_align_tunables_are_the_align_config_section(maps: dict[str, Path]) -> None:
    # The same two robots, asked for more matched wall than the buildings hold: refused (a
    # coarse 30-deg sweep keeps it quick).
    out = maps["root"] / "strict"
    args = ("fleet", "align", maps["a"], maps["b"], "--out", out, "--set", "align.yaw_step_deg=30")
    result = _invoke(*args, "--set", "align.min_overlap_m=5000")
    assert result.exit_code == 1 and "(need 5000 m)" in result.output, result.output
    assert not (out / "alignment.yaml").exists()
    bad = _invoke(*args, "--set", "align.min_agreement=2")
    assert bad.exit_code == 1 and "align.min_agreement" in bad.output, bad.output


@needs_data
def test_geo_converts_both_ways_through_a_bundle_anchor(tmp_path: Path) -> None:
    (tmp_path / "geo.yaml").write_text(
        "latitude: 44.98\nlongitude: -93.27\naltitude: 256.0\nheading_deg: 0.0\n"
    )
    there = _invoke("geo", tmp_path, "--xy", "100", "-50")
    assert there.exit_code == 0, there.output
    lat, lon = (float(v) for v in there.output.split()[1::2])
    back = _invoke("geo", tmp_path, "--latlon", lat, lon)
    x, y = (float(v) for v in back.output.split()[1::2])
    assert (x, y) == pytest.approx((100.0, -50.0), abs=0.01)
    missing = _invoke("geo", tmp_path / "nowhere", "--xy", "0", "0")
    assert missing.exit_code == 1 and "no such map" in missing.output


def _cut(recording: Path, out: Path, t0: float, t1: float) -> Path:
    """The stretch [t0, t1) [s] of a recording: its index files cut, its images shared."""
    out.mkdir(parents=True)
    for item in recording.iterdir():
        if item.suffix == ".txt":
            rows = item.read_text().splitlines()
            keep = [r for r in rows if r.startswith("#") or t0 <= float(r.split()[0]) < t1]
            (out / item.name).write_text("\n".join(keep) + "\n")
        elif item.is_dir():
            (out / item.name).symlink_to(item)
        else:
            shutil.copy(item, out / item.name)
    return out


def _shown_at(mask: np.ndarray, geom: GridGeometry, xy: np.ndarray) -> float:
    """The fraction of world points ``xy`` (N, 2) [m] on True cells of a picture-sized mask."""
    r, c = geom.world_to_cell(xy[:, 0], xy[:, 1])
    inside = (r >= 0) & (r < geom.height) & (c >= 0) & (c < geom.width)
    return float(np.count_nonzero(mask[r[inside], c[inside]]) / len(xy))


def test_show_places_two_simulated_robots_maps_where_the_fleet_file_says(
    house_recording: Path, tmp_path: Path
) -> None:
    # Two robots: overlapping stretches of the simulated house route, each mapped on its own.
    # The route's first 1.5 s face the wall at x = 7 m from 5.5 m: the scan reaches 8 m here.
    placed = {"a": (0.0, 0.0, 0.0), "b": (4.0, 12.0, math.pi / 2)}
    for name, (t0, t1) in (("a", (0.0, 0.9)), ("b", (0.6, 2.0))):
        cut = _cut(house_recording, tmp_path / f"rec-{name}", t0, t1)
        args = ("map", cut, "--out", tmp_path / name, "-q", "--set", "depth_to_scan.range_max=8")
        result = _invoke(*args)
        assert result.exit_code == 0, result.output
    robots = "".join(
        f"  - {{name: {n}, map: {n}/map, T_world_map: {{x: {x}, y: {y}, yaw: {yaw}}}}}\n"
        for n, (x, y, yaw) in placed.items()
    )
    (tmp_path / "fleet.yaml").write_text("robots:\n" + robots)
    shown = _invoke("fleet", "show", tmp_path / "fleet.yaml", "--out", tmp_path / "show")
    assert shown.exit_code == 0, shown.output
    assert (tmp_path / "show" / "fleet.rrd").stat().st_size > 1000
    img = cv2.imread(str(tmp_path / "show" / "fleet.png"))[:, :, ::-1]
    geom = world_geometry(load_layers(load_fleet(tmp_path / "fleet.yaml")))
    assert img.shape[:2] == geom.shape
    for i, (name, other) in enumerate((("a", "b"), ("b", "a"))):
        m = load_map(tmp_path / name / "map")
        g = m.grid.geometry
        occ = m.grid.occupied_mask(m.occupied_thresh)
        walls = occupied_cells_xy(occ, (g.origin_x, g.origin_y), g.resolution)
        assert len(walls) >= 20, name
        # Each map's walls are the world's (its map frame is the simulator's world frame)...
        truth = json.loads((tmp_path / name / "summary.json").read_text())["grid_vs_floor_plan"]
        assert truth["false_positive"] <= 0.1 * truth["true_positive"], truth
        # ... and the picture draws them in the robot's tint (within a pixel) where its
        # T_world_map puts them, not where the other robot's placement would.
        tinted = np.all(img == TINTS_RGB[i].astype(np.uint8), axis=2).astype(np.uint8)
        tinted = cv2.dilate(tinted, np.ones((3, 3), np.uint8))[::-1]  # row 0 at the bottom
        assert _shown_at(tinted, geom, to_world(placed[name], walls)) > 0.9, name
        assert _shown_at(tinted, geom, to_world(placed[other], walls)) < 0.1, name
