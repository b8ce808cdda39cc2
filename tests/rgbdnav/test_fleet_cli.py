"""`rgbdnav fleet align / show` and `rgbdnav geo` on real logs: a Radish CARMEN log cut into two
overlapping robots, the second's odometry moved 89 m and turned 115 deg, each mapped by the mapper,
aligned without a guess; a map of another building refused."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.world_picture import TINTS_RGB
from sensors.safe_yaml import read_yaml
from slam.geometry import oplus, wrap_angle
from slam.map_bundle import load_bundle, load_map_yaml

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
def maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fleet")
    text_a, text_b = split(read_log_lines(ACES), 0.6, 0.4, SHIFT)
    (root / "a.log").write_text(text_a)
    (root / "b.log").write_text(text_b)
    out = {}
    for name, log in (("a", root / "a.log"), ("b", root / "b.log"), ("other", OREBRO)):
        result = _invoke("map", log, "--out", root / name, "-q")
        assert result.exit_code == 0, result.output
        out[name] = root / name / "map"
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
