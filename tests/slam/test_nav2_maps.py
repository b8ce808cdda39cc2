"""Nav2 map_server maps as Nav2 loads them (issue 23, item 4): rotated origins, ASCII (P2) and
16-bit PGMs, 8/16-bit PNGs, and map_io's trinary / scale / raw rules with negate.

The oracle below is nav2_map_server's ``loadMapFromFile`` per-pixel rule written out pixel by
pixel (src/map_io.cpp); the loader under test is the vectorised one."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sensors.types import MapError
from slam.map_bundle import (
    MapYaml,
    decode_pgm,
    load_map,
    load_map_yaml,
    occupancy_values_from_image,
    parse_map_yaml,
    unrotate_grid,
)

# What `ros2 run nav2_map_server map_saver_cli` writes (turtlebot3_world's map.yaml shape).
MAP_SAVER_YAML = """image: {image}
mode: {mode}
resolution: 0.05
origin: [{ox}, {oy}, {yaw}]
negate: {negate}
occupied_thresh: 0.65
free_thresh: {free}
"""


Origin = tuple[float, float, float]


def write_map(
    folder: Path,
    image: str,
    mode: str = "trinary",
    negate: int = 0,
    origin: Origin = (-1.0, -0.5, 0.0),
    free: float = 0.25,
) -> Path:
    path = folder / f"{Path(image).stem}.yaml"
    ox, oy, yaw = origin
    path.write_text(
        MAP_SAVER_YAML.format(
            image=image, mode=mode, ox=ox, oy=oy, yaw=yaw, negate=negate, free=free
        )
    )
    return path


def nav2_cell(
    shade: float, alpha: float | None, mode: str, negate: bool, occ_th: float, free_th: float
) -> int:
    """map_io.cpp loadMapFromFile for one pixel (shade, alpha in [0, 1])."""
    channels = [shade, shade, shade]
    if mode == "trinary" and alpha is not None:
        channels.append(alpha)
    s = sum(channels) / len(channels)
    occ = s if negate else 1.0 - s
    if mode == "trinary":
        return 100 if occ_th < occ else 0 if occ < free_th else -1
    if mode == "scale":
        if alpha is not None and alpha < 1.0:
            return -1
        if occ_th < occ:
            return 100
        if occ < free_th:
            return 0
        return int(np.rint((occ - free_th) / (occ_th - free_th) * 100.0))
    percent = round(shade * 255)
    return int(percent) if 0 <= percent <= 100 else -1


# Every 8-bit grey level, as a 16 x 16 image.
LEVELS = np.arange(256, dtype=np.uint8).reshape(16, 16)


@pytest.mark.parametrize("mode", ["trinary", "scale", "raw"])
@pytest.mark.parametrize("negate", [0, 1])
def test_every_grey_level_is_classified_as_map_io_does(tmp_path, mode, negate):
    cv2.imwrite(str(tmp_path / "levels.png"), LEVELS)
    meta = parse_map_yaml(write_map(tmp_path, "levels.png", mode, negate, free=0.196))
    got = occupancy_values_from_image(LEVELS / 255.0, None, meta)
    want = [nav2_cell(v / 255.0, None, mode, bool(negate), 0.65, 0.196) for v in LEVELS.ravel()]
    np.testing.assert_array_equal(got.ravel(), want)
    # Through the file: the grid is the image flipped (row 0 = lowest y).
    grid = load_map_yaml(tmp_path / "levels.yaml")
    known = np.asarray(want).reshape(16, 16)[::-1] >= 0
    np.testing.assert_array_equal(grid.observed, known)


def test_alpha_is_averaged_in_trinary_and_marks_unknown_in_scale(tmp_path):
    grey = np.array([[0, 0, 254, 254]], np.uint8)
    alpha = np.array([[255, 0, 255, 100]], np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), cv2.merge([grey, grey, grey, alpha]))
    for mode in ("trinary", "scale"):
        meta = parse_map_yaml(write_map(tmp_path, "a.png", mode))
        grid = load_map_yaml(tmp_path / "a.yaml")
        want = [
            nav2_cell(g / 255, a / 255, mode, False, 0.65, 0.25)
            for g, a in zip(grey[0], alpha[0], strict=True)
        ]
        got = occupancy_values_from_image(grey / 255.0, alpha / 255.0, meta)
        np.testing.assert_array_equal(got[0], want)
        assert grid.observed[0].tolist() == [w >= 0 for w in want]
    # trinary: black + transparent averages to 0.25 shade -> occ 0.75 > 0.65: occupied
    assert nav2_cell(0.0, 0.0, "trinary", False, 0.65, 0.25) == 100


def _ascii_pgm(pixels: np.ndarray, maxval: int) -> bytes:
    h, w = pixels.shape
    rows = "\n".join(" ".join(str(int(v)) for v in row) for row in pixels)
    return f"P2\n# CREATOR: GIMP PNM Filter Version 1.1\n{w} {h}\n{maxval}\n{rows}\n".encode()


def _trinary_pixels() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.choice(np.array([0, 205, 254], np.uint8), size=(12, 20))


def test_ascii_16bit_pgm_and_16bit_png_load_like_the_8bit_pgm(tmp_path):
    pix = _trinary_pixels()
    (tmp_path / "p5.pgm").write_bytes(b"P5\n20 12\n255\n" + pix.tobytes())
    (tmp_path / "p2.pgm").write_bytes(_ascii_pgm(pix, 255))
    wide = pix.astype(np.uint16) * 257  # same shade at 16 bits
    (tmp_path / "p5w.pgm").write_bytes(b"P5\n20 12\n65535\n" + wide.astype(">u2").tobytes())
    (tmp_path / "p2w.pgm").write_bytes(_ascii_pgm(wide, 65535))
    cv2.imwrite(str(tmp_path / "w.png"), wide)
    reference = load_map_yaml(write_map(tmp_path, "p5.pgm"))
    assert reference.observed.sum() > 0
    for name in ("p2.pgm", "p5w.pgm", "p2w.pgm", "w.png"):
        grid = load_map_yaml(write_map(tmp_path, name))
        assert grid.geometry == reference.geometry, name
        np.testing.assert_array_equal(grid.trinary(), reference.trinary(), err_msg=name)


def test_pgm_values_are_read_against_maxval():
    # maxval 100: 50 is mid grey for P5 and P2 alike (OpenCV would rescale only the P2)
    p5, m5 = decode_pgm(b"P5\n2 1\n100\n" + bytes([50, 100]), "x.pgm")
    p2, m2 = decode_pgm(b"P2\n2 1\n100\n50 100\n", "x.pgm")
    assert m5 == m2 == 100
    np.testing.assert_array_equal(p5, p2)
    wide, m = decode_pgm(b"P5 2 1 1000\n" + np.array([500, 1000], ">u2").tobytes(), "x.pgm")
    assert m == 1000 and wide.dtype == np.uint16 and wide.tolist() == [[500, 1000]]


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"P2\n3 1\n255\n1 2\n", "needs 3 pixel values, found 2"),
        (b"P2\n2 1\n255\n1 x\n", "not an integer"),
        (b"P2\n2 1\n255\n1 300\n", "pixel value 300 exceeds maxval 255"),
        (b"P5\n2 1\n65535\n\x00\x01", "needs 4 bytes of pixels, found 2"),
        (b"P5\n2 1\n70000\n\x00\x01", "maxval 70000 unsupported"),
    ],
)
def test_bad_ascii_or_16bit_pgm_is_one_error(tmp_path, data, match):
    (tmp_path / "m.pgm").write_bytes(data)
    with pytest.raises(MapError, match=match):
        load_map_yaml(write_map(tmp_path, "m.pgm"))


def test_rotated_origin_puts_every_cell_where_map_server_says(tmp_path):
    """map_server: cell (col i, row j from the bottom) is centred at
    origin + R(yaw) ((i + 0.5) res, (j + 0.5) res). Every occupied cell must be found there."""
    rng = np.random.default_rng(7)
    pix = np.full((30, 40), 254, np.uint8)
    pix[rng.integers(0, 30, 25), rng.integers(0, 40, 25)] = 0
    (tmp_path / "r.pgm").write_bytes(b"P5\n40 30\n255\n" + pix.tobytes())
    res, ox, oy = 0.05, 2.0, -3.0
    for yaw in (math.pi / 2, 0.3, -2.5):
        grid = load_map_yaml(write_map(tmp_path, "r.pgm", origin=(ox, oy, yaw)))
        rows_from_top, cols = np.nonzero(pix == 0)
        j = 29 - rows_from_top
        local = np.stack([(cols + 0.5) * res, (j + 0.5) * res])
        c, s = math.cos(yaw), math.sin(yaw)
        x = ox + c * local[0] - s * local[1]
        y = oy + s * local[0] + c * local[1]
        r, cc = grid.geometry.world_to_cell(x, y)
        assert grid.geometry.contains(r, cc).all()
        occupied = grid.occupied_mask()
        assert occupied[r, cc].all(), yaw
        # nothing invented: about as many occupied cells as the image has (nearest resampling
        # may duplicate or drop a few at a non-right-angle yaw)
        assert abs(int(occupied.sum()) - len(x)) <= 0.5 * len(x)
        # free cells stay free, corners outside the rotated map are unknown
        assert grid.free_mask().sum() > 0.8 * pix.size
        # corners outside a map turned by other than a right angle are unknown
        assert grid.observed.all() == (yaw == math.pi / 2)


def test_quarter_turn_is_exact():
    values = np.arange(6, dtype=np.int8).reshape(2, 3)  # row 0 = lowest
    out, ox, oy = unrotate_grid(values, 1.0, (0.0, 0.0, math.pi / 2))
    assert (ox, oy) == pytest.approx((-2.0, 0.0))
    # out[i, 1 - j] = values[j, i]: a counter-clockwise turn of a y-up array is np.rot90's
    # clockwise one (np.rot90 assumes row 0 at the top)
    np.testing.assert_array_equal(out, np.rot90(values, -1))


def test_zero_yaw_keeps_the_image_grid(tmp_path):
    pix = _trinary_pixels()
    (tmp_path / "z.pgm").write_bytes(b"P5\n20 12\n255\n" + pix.tobytes())
    loaded = load_map(write_map(tmp_path, "z.pgm"))
    g = loaded.grid.geometry
    assert (g.width, g.height, g.origin_x, g.origin_y) == (20, 12, -1.0, -0.5)


def test_thresholds_of_zero_or_one_are_accepted_as_nav2_does(tmp_path):
    pix = _trinary_pixels()
    (tmp_path / "t.pgm").write_bytes(b"P5\n20 12\n255\n" + pix.tobytes())
    path = write_map(tmp_path, "t.pgm", free=0.0)
    grid = load_map_yaml(path)
    assert not grid.free_mask().any()  # occ < 0.0 never holds
    assert isinstance(parse_map_yaml(path), MapYaml)
