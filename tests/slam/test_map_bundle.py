from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

import slam.map_bundle as mb
from sensors.types import LaserScan, MapError
from slam.config import MapperConfig
from slam.map_bundle import (
    GraphEdge,
    MapBundle,
    decode_pgm,
    load_bundle,
    load_map_yaml,
    save_bundle,
    save_map_yaml,
)
from slam.occupancy_grid import GridGeometry, OccupancyGrid, integrate_scans

CFG = MapperConfig()
GEOM = GridGeometry(0.1, -1.0, -0.5, 20, 10)  # 2 m x 1 m


def corner_grid() -> OccupancyGrid:
    """Laser at the lower-left looking up: a hit near the top (high y), free cells below it."""
    pose = np.array([[-0.95, -0.45, math.pi / 2]])
    s = LaserScan(0, 0.0, 0.0, np.array([0.8], np.float32), 0.1, 10.0)
    return integrate_scans(GEOM, np.repeat(pose, 3, axis=0), [s] * 3, CFG)


def make_bundle(k: int = 3) -> MapBundle:
    scans = tuple(
        LaserScan(10 + i, -1.0, 0.5, np.arange(3 + i, dtype=np.float32) + 1.0, 0.1, 5.0)
        for i in range(k)
    )
    poses = np.array([[0.1 * i, 0.0, 0.05 * i] for i in range(k)])
    edges = tuple(
        GraphEdge("odometry", i, i + 1, (0.1, 0.0, 0.05), ((1.0, 0, 0), (0, 2.0, 0), (0, 0, 3.0)))
        for i in range(k - 1)
    )
    cfg = {"resolution": 0.1, "occupied_thresh": 0.65, "free_thresh": 0.25}
    return MapBundle(
        corner_grid(),
        np.arange(k, dtype=np.int64),
        np.arange(k) + 10,
        poses,
        poses + 0.5,
        edges,
        scans,
        cfg,
        "unit test",
        "2024-01-01T00:00:00+00:00",
    )


def assert_bundles_equal(a: MapBundle, b: MapBundle) -> None:
    np.testing.assert_array_equal(a.grid.log_odds, b.grid.log_odds)
    np.testing.assert_array_equal(a.grid.observed, b.grid.observed)
    assert a.grid.geometry == b.grid.geometry
    for name in ("keyframe_ids", "keyframe_stamps_ns", "keyframe_poses", "keyframe_odom_poses"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.edges == b.edges and a.config == b.config and a.source == b.source
    assert a.created == b.created and len(a.scans) == len(b.scans)
    for s, t in zip(a.scans, b.scans, strict=True):
        np.testing.assert_array_equal(s.ranges, t.ranges)
        assert (s.stamp_ns, s.angle_min, s.angle_increment, s.range_min, s.range_max) == (
            t.stamp_ns,
            t.angle_min,
            t.angle_increment,
            t.range_min,
            t.range_max,
        )


# --- round trips -------------------------------------------------------------------------------


def test_bundle_round_trip_is_exact(tmp_path):
    bundle = make_bundle()
    save_bundle(bundle, tmp_path / "b")
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == [
        "graph.json",
        "grid.npz",
        "map.pgm",
        "map.yaml",
        "scans.npz",
    ]
    assert_bundles_equal(load_bundle(tmp_path / "b"), bundle)
    assert [p.name for p in tmp_path.iterdir()] == ["b"]  # no staging leftovers


def test_scans_npz_loads_without_pickle_with_ragged_offsets(tmp_path):
    save_bundle(make_bundle(), tmp_path / "b")
    with np.load(tmp_path / "b" / "scans.npz", allow_pickle=False) as npz:
        np.testing.assert_array_equal(npz["offsets"], [0, 3, 7, 12])
        assert npz["ranges"].dtype == np.float32 and npz["stamp_ns"].dtype == np.int64
    doc = json.loads((tmp_path / "b" / "graph.json").read_text())
    assert doc["schema_version"] == 1 and doc["frame"] == "map"
    assert doc["keyframes"][1] == {
        "id": 1,
        "stamp_ns": 11,
        "pose": [0.1, 0.0, 0.05],
        "odom_pose": [0.6, 0.5, 0.55],
    }
    assert doc["edges"][0]["kind"] == "odometry" and len(doc["edges"][0]["information"]) == 3


def test_pgm_is_trinary_and_flipped_so_high_y_is_the_top_row(tmp_path):
    save_map_yaml(corner_grid(), tmp_path / "map.yaml")
    pixels, maxval = decode_pgm((tmp_path / "map.pgm").read_bytes(), "map.pgm")
    assert maxval == 255 and pixels.shape == (10, 20)
    assert set(np.unique(pixels).tolist()) == {0, 205, 254}
    # The hit is at y = 0.35 (row 8 from the bottom) -> image row 1 from the top.
    np.testing.assert_array_equal(np.argwhere(pixels == 0), [[1, 0]])
    np.testing.assert_array_equal(pixels[2:, 0], 254)  # free cells below it
    assert pixels[0, 0] == 205 and pixels[5, 5] == 205
    text = (tmp_path / "map.yaml").read_text()
    assert "image: map.pgm\nmode: trinary\nresolution: 0.1\norigin: [-1.0, -0.5, 0.0]\n" in text
    assert "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n" in text


def test_saved_yaml_loads_with_the_plain_loader_with_the_same_classes(tmp_path):
    grid = corner_grid()
    save_map_yaml(grid, tmp_path / "map.yaml")
    loaded = load_map_yaml(tmp_path / "map.yaml")
    assert loaded.geometry == grid.geometry
    np.testing.assert_array_equal(loaded.trinary(), grid.trinary())


def test_plain_loader_modes_negate_png_and_absolute_image_path(tmp_path):
    img = np.array([[0, 100, 205, 254, 255]], np.uint8)  # one image row
    cv2.imwrite(str(tmp_path / "m.png"), img)
    base = "resolution: 0.5\norigin: [1.0, 2.0, 0.0]\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    cases = {  # nav_msgs values as Nav2 map_io computes them
        "mode: trinary\nnegate: 0\n": [100, -1, -1, 0, 0],
        "mode: trinary\nnegate: 1\n": [0, -1, 100, 100, 100],
        "mode: scale\nnegate: 0\n": [100, 91, 0, 0, 0],
        "mode: raw\nnegate: 0\n": [0, 100, -1, -1, -1],
    }
    for header, expected in cases.items():
        (tmp_path / "m.yaml").write_text(f"image: {tmp_path / 'm.png'}\n{header}{base}")
        meta = mb.parse_map_yaml(tmp_path / "m.yaml")
        shade, alpha = mb._read_image(meta.image)
        values = mb.occupancy_values_from_image(shade, alpha, meta)
        assert values[0].tolist() == expected, header
        g = load_map_yaml(tmp_path / "m.yaml")
        assert g.geometry == GridGeometry(0.5, 1.0, 2.0, 5, 1)
        np.testing.assert_array_equal(g.observed[0], np.array(expected) >= 0)


# --- atomic replace ----------------------------------------------------------------------------


def test_failed_save_leaves_the_old_bundle_and_no_temp_folder(tmp_path, monkeypatch):
    target = tmp_path / "b"
    save_bundle(make_bundle(2), target)

    def boom(folder, scans):
        raise OSError("disk full")

    monkeypatch.setattr(mb, "_write_scans", boom)
    with pytest.raises(OSError, match="disk full"):
        save_bundle(make_bundle(4), target)
    assert [p.name for p in tmp_path.iterdir()] == ["b"]
    assert len(load_bundle(target).scans) == 2


def test_a_save_killed_between_its_two_renames_still_loads_the_old_bundle(tmp_path, monkeypatch):
    # commit_staging_dir moves the old folder aside, then renames the new one in: kill -9 in
    # between (a live checkpoint) leaves no folder under the bundle's name.
    import os

    import sensors.atomic as atomic

    target = tmp_path / "b"
    save_bundle(make_bundle(2), target)
    real = os.replace
    calls = []

    def die_on_second(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise KeyboardInterrupt  # the process dies here
        real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", die_on_second)
    with pytest.raises(KeyboardInterrupt):
        save_bundle(make_bundle(4), target)
    monkeypatch.setattr(atomic.os, "replace", real)
    assert not target.exists()
    assert len(load_bundle(target).scans) == 2  # the moved-aside bundle, with a warning
    loaded = mb.load_map(target)  # what `localize --map` and `live --map` call
    assert (
        loaded.kind == "bundle"
        and loaded.grid.log_odds.shape == load_bundle(target).grid.log_odds.shape
    )
    save_bundle(make_bundle(3), target)  # and the next save puts one in place again
    assert len(load_bundle(target).scans) == 3
    assert [p.name for p in tmp_path.iterdir()] == ["b"]  # the moved-aside one is gone


def test_a_save_removes_staging_folders_of_writers_that_died(tmp_path):
    # kill -9 during a save leaves its half-written staging folder beside the bundle; the next
    # save removes it, but not the folder of a writer that is still running.
    import subprocess
    import sys

    target = tmp_path / "b"
    save_bundle(make_bundle(2), target)
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    abandoned = tmp_path / f".b.pid{int(dead.stdout)}-x1y2.partial"
    running = tmp_path / f".b.pid{os.getppid()}-z3w4.partial"
    for folder in (abandoned, running):
        folder.mkdir()
        (folder / "graph.json").write_text("{")  # half written
    save_bundle(make_bundle(3), target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["." + running.name[1:], "b"]
    assert len(load_bundle(target).scans) == 3


def test_save_replaces_an_existing_bundle(tmp_path):
    save_bundle(make_bundle(2), tmp_path / "b")
    save_bundle(make_bundle(4), tmp_path / "b")
    assert len(load_bundle(tmp_path / "b").scans) == 4
    assert [p.name for p in tmp_path.iterdir()] == ["b"]


def test_edited_pgm_wins_over_stored_log_odds(tmp_path):
    save_bundle(make_bundle(), tmp_path / "b")
    pgm = tmp_path / "b" / "map.pgm"
    pixels, _ = decode_pgm(pgm.read_bytes(), pgm)
    pixels = pixels.copy()
    pixels[1, 0] = 254  # erase the obstacle
    pgm.write_bytes(mb.encode_pgm(pixels))
    grid = load_bundle(tmp_path / "b").grid
    assert not grid.occupied_mask().any()


# --- bad input ---------------------------------------------------------------------------------


def saved(tmp_path) -> Path:
    save_bundle(make_bundle(), tmp_path / "b")
    return tmp_path / "b"


def edit_yaml(folder: Path, old: str, new: str) -> None:
    p = folder / "map.yaml"
    text = p.read_text()
    assert old in text
    p.write_text(text.replace(old, new))


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        ("image: map.pgm", "image: /etc/map.pgm", "image path '/etc/map.pgm' is absolute"),
        ("image: map.pgm", "image: ../map.pgm", "leaves the bundle folder"),
        ("resolution: 0.1", "resolution: 0.0", "'resolution' must be positive"),
        ("resolution: 0.1", "resolution: -1", "'resolution' must be positive"),
        ("free_thresh: 0.196", "free_thresh: 0.7", r"free_thresh \(0.7\) must be below"),
        ("occupied_thresh: 0.65", "occupied_thresh: 1.5", r"thresholds must lie in \[0, 1\]"),
        ("origin: [-1.0, -0.5, 0.0]", "origin: [1.0, 2.0]", "'origin' must be 3 finite numbers"),
        ("origin: [-1.0, -0.5, 0.0]", "origin: [1.0, a, 0]", "'origin' must be 3 finite numbers"),
        ("mode: trinary", "mode: fancy", "'mode' must be one of"),
        ("negate: 0", "negate: 2", "'negate' must be 0 or 1"),
        ("negate: 0\n", "", "missing key 'negate'"),
        ("image: map.pgm", "image: [", "map.yaml: not valid YAML"),
        ("negate: 0\n", "negate: 0\nnegate: 1\n", r"map.yaml: line \d+: duplicate key 'negate'"),
        ("image: map.pgm", "image: other.pgm", "other.pgm: missing image file"),
    ],
)
def test_bad_map_yaml_is_a_map_error_naming_the_problem(tmp_path, old, new, match):
    folder = saved(tmp_path)
    edit_yaml(folder, old, new)
    with pytest.raises(MapError, match=match):
        load_bundle(folder)


def _plain_map(tmp_path: Path, folder: Path, image: str) -> Path:
    yaml_path = tmp_path / "plain.yaml"
    yaml_path.write_text(
        (folder / "map.yaml").read_text().replace("image: map.pgm", f"image: {image}")
    )
    return yaml_path


def test_a_map_image_that_is_not_a_regular_file_is_refused_not_read_forever(tmp_path):
    folder = saved(tmp_path)
    with pytest.raises(MapError, match=r"/dev/zero: cannot read image \(not a regular file\)"):
        load_map_yaml(_plain_map(tmp_path, folder, "/dev/zero"))


def test_an_empty_or_oversized_map_image_is_a_map_error_before_decoding(tmp_path):
    folder = saved(tmp_path)
    for name in ("empty.pgm", "empty.png"):
        (tmp_path / name).write_bytes(b"")
        with pytest.raises(MapError, match=rf"{name}: empty image file"):
            load_map_yaml(_plain_map(tmp_path, folder, str(tmp_path / name)))
    # A 57-byte PNG whose header claims 30000 x 30000: refused from the header alone.
    ok, png = cv2.imencode(".png", np.zeros((2, 2), np.uint8))
    data = bytearray(png.tobytes())
    data[16:24] = (30000).to_bytes(4, "big") * 2
    (tmp_path / "huge.png").write_bytes(bytes(data))
    with pytest.raises(MapError, match=r"huge\.png: image declares 30000x30000 pixels"):
        load_map_yaml(_plain_map(tmp_path, folder, str(tmp_path / "huge.png")))
    (tmp_path / "huge.pgm").write_bytes(b"P5 30000 30000 255\n" + bytes(16))
    with pytest.raises(MapError, match=r"huge\.pgm: PGM declares 30000x30000 pixels"):
        load_map_yaml(_plain_map(tmp_path, folder, str(tmp_path / "huge.pgm")))


def test_plain_loader_allows_absolute_and_resolves_relative_images(tmp_path):
    folder = saved(tmp_path)
    other = tmp_path / "elsewhere"
    other.mkdir()
    (other / "m.yaml").write_text(
        (folder / "map.yaml").read_text().replace("image: map.pgm", "image: ../b/map.pgm")
    )
    assert load_map_yaml(other / "m.yaml").geometry == GEOM
    edit_yaml(folder, "image: map.pgm", f"image: {folder / 'map.pgm'}")
    assert load_map_yaml(folder / "map.yaml").geometry == GEOM


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"P2\n20 10\n255\n" + bytes(200), "needs 200 pixel values, found 1"),
        (b"P5x\n20 10\n255\n" + bytes(200), "not a PGM"),
        (b"P5\n20 10\n255\n" + bytes(199), r"needs 200 bytes of pixels, found 199"),
        (b"P5\n20 10\n65535\n" + bytes(399), "needs 400 bytes of pixels, found 399"),
        (b"P5\n20 10\n100\n" + bytes([200]) * 200, "pixel value 200 exceeds maxval 100"),
        (b"P5\n# comment\n20 10\n255\n" + bytes(200) + b"x", "found 201"),
    ],
)
def test_bad_pgm_is_a_map_error(tmp_path, data, match):
    folder = saved(tmp_path)
    (folder / "map.pgm").write_bytes(data)
    with pytest.raises(MapError, match=match):
        load_bundle(folder)


def test_pgm_header_comments_are_allowed():
    pixels, maxval = decode_pgm(b"P5\n# made by gimp\n2 1\n# x\n255\n\x00\xfe", "x.pgm")
    np.testing.assert_array_equal(pixels, [[0, 254]])


def test_pgm_size_different_from_stored_log_odds_is_a_map_error(tmp_path):
    folder = saved(tmp_path)
    (folder / "map.pgm").write_bytes(mb.encode_pgm(np.full((5, 5), 205, np.uint8)))
    with pytest.raises(MapError, match=r"grid.npz: log_odds \(10, 20\) does not match"):
        load_bundle(folder)


def test_graph_json_problems_are_map_errors(tmp_path):
    folder = saved(tmp_path)
    graph = folder / "graph.json"
    good = json.loads(graph.read_text())

    graph.write_text("{not json")
    with pytest.raises(MapError, match="graph.json: not valid JSON"):
        load_bundle(folder)
    graph.write_text(json.dumps({**good, "schema_version": 2}))
    with pytest.raises(MapError, match="graph.json: schema_version 2 is not supported"):
        load_bundle(folder)
    graph.write_text(json.dumps({**good, "keyframes": good["keyframes"][:2], "edges": []}))
    with pytest.raises(MapError, match="keyframe count mismatch: .*graph.json has 2 keyframes"):
        load_bundle(folder)
    bad_edge = {**good["edges"][0], "to": 99}
    graph.write_text(json.dumps({**good, "edges": [bad_edge]}))
    with pytest.raises(MapError, match=r"edges\[0\] links unknown keyframe ids 0 -> 99"):
        load_bundle(folder)
    bad_kf = {**good["keyframes"][0], "pose": [1, 2]}
    graph.write_text(json.dumps({**good, "keyframes": [bad_kf, *good["keyframes"][1:]]}))
    with pytest.raises(MapError, match=r"keyframes\[0\].pose must be a list of 3 numbers"):
        load_bundle(folder)
    huge = {**good["keyframes"][0], "stamp_ns": 10**30}
    graph.write_text(json.dumps({**good, "keyframes": [huge, *good["keyframes"][1:]]}))
    with pytest.raises(MapError, match=r"keyframes\[0\]\.stamp_ns 10{30} is out of range"):
        load_bundle(folder)
    graph.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(MapError, match="graph.json: not valid JSON: nested too deeply"):
        load_bundle(folder)
    graph.unlink()
    with pytest.raises(MapError, match="graph.json: missing file"):
        load_bundle(folder)


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        (
            "occupied_thresh",
            "high",
            r"config\.occupied_thresh must be a number in \(0, 1\), got 'hi",
        ),
        ("free_thresh", float("nan"), r"config\.free_thresh must be a number in \(0, 1\), got nan"),
        ("free_thresh", 0.9, r"free_thresh \(0\.9\) must be below occupied_thresh \(0\.65\)"),
        # A string where the resolution was stored skipped the check against map.yaml (#16).
        ("resolution", "fine", r"config\.resolution must be a number > 0, got 'fine'"),
        ("resolution", float("nan"), r"config\.resolution must be a number > 0, got nan"),
        ("resolution", True, r"config\.resolution must be a number > 0, got True"),
    ],
)
def test_a_stored_config_value_that_is_not_a_threshold_is_a_map_error(tmp_path, key, value, match):
    folder = saved(tmp_path)
    graph = folder / "graph.json"
    doc = json.loads(graph.read_text())
    doc["config"] = {**doc["config"], "occupied_thresh": 0.65, key: value}
    graph.write_text(json.dumps(doc))
    with pytest.raises(MapError, match=match):
        load_bundle(folder)


def test_scans_npz_problems_are_map_errors(tmp_path):
    folder = saved(tmp_path)
    scans = folder / "scans.npz"
    scans.write_bytes(b"garbage")
    with pytest.raises(MapError, match="scans.npz: corrupt or unreadable npz"):
        load_bundle(folder)
    np.savez_compressed(scans, ranges=np.zeros(3, np.float32))
    with pytest.raises(MapError, match=r"scans.npz: missing arrays \['offsets'"):
        load_bundle(folder)
    # Damaged deflate data inside an intact zip: zlib.error, not a zip error (bench/fuzz_inputs).
    np.savez_compressed(scans, **mb._scans_arrays(make_bundle().scans))
    data = bytearray(scans.read_bytes())
    start = 30 + int.from_bytes(data[26:28], "little") + int.from_bytes(data[28:30], "little")
    data[start : start + 4] = b"\xff" * 4  # the first member's compressed stream
    scans.write_bytes(bytes(data))
    with pytest.raises(MapError, match="scans.npz: corrupt or unreadable npz: Error -3"):
        load_bundle(folder)
    arrays = mb._scans_arrays(make_bundle().scans)
    arrays["offsets"] = np.array([0, 3, 2, 12])
    np.savez_compressed(scans, **arrays)
    with pytest.raises(MapError, match="'offsets' must rise from 0"):
        load_bundle(folder)
    arrays = mb._scans_arrays(make_bundle().scans)
    arrays["angle_increment"][1] = np.nan  # --continue would match against it
    np.savez_compressed(scans, **arrays)
    with pytest.raises(MapError, match="'angle_increment' of scan 1 is not a finite number"):
        load_bundle(folder)
    scans.unlink()
    with pytest.raises(MapError, match="scans.npz: missing file"):
        load_bundle(folder)


@pytest.mark.parametrize("name", ["grid.npz", "scans.npz", "graph.json", "map.yaml"])
def test_a_bundle_file_linked_from_outside_its_folder_is_refused(tmp_path, name):
    folder = saved(tmp_path)
    outside = tmp_path / f"elsewhere-{name}"
    (folder / name).rename(outside)
    (folder / name).symlink_to(outside)
    with pytest.raises(MapError, match=rf"{name}: a link out of the bundle folder"):
        load_bundle(folder)


def test_missing_files_are_map_errors(tmp_path):
    with pytest.raises(MapError, match="missing map bundle folder"):
        load_bundle(tmp_path / "nope")
    folder = saved(tmp_path)
    (folder / "map.yaml").unlink()
    with pytest.raises(MapError, match="map.yaml: missing file"):
        load_bundle(folder)


def test_grid_npz_is_optional(tmp_path):
    folder = saved(tmp_path)
    (folder / "grid.npz").unlink()
    grid = load_bundle(folder).grid
    np.testing.assert_array_equal(grid.trinary(), corner_grid().trinary())


def test_a_bundle_whose_map_yaml_resolution_was_edited_is_refused(tmp_path):
    # The scans and graph were made at the mapper's resolution; a map.yaml saying otherwise
    # would scale the grid under them silently (#16).
    target = tmp_path / "b"
    bundle = make_bundle(3)
    save_bundle(bundle, target)
    made_at = bundle.grid.geometry.resolution
    yaml_path = target / "map.yaml"
    text = yaml_path.read_text()
    assert f"resolution: {made_at!r}" in text
    yaml_path.write_text(text.replace(f"resolution: {made_at!r}", f"resolution: {made_at * 5!r}"))
    with pytest.raises(MapError, match="disagrees with"):
        load_bundle(target)
