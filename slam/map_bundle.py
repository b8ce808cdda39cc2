"""Map bundles and plain Nav2 map_server maps (PGM/PNG + YAML).

A **map bundle** is a folder that other tools can read without rgbdnav::

    map.pgm      binary P5, trinary: occupied 0, free 254, unknown 205; row 0 is the TOP (max y)
    map.yaml     Nav2 map_server metadata (image, mode, resolution, origin, negate, thresholds)
    graph.json   schema_version, keyframes (id, stamp_ns, pose, odom_pose), edges, config, source
    scans.npz    keyframe scans, ragged ranges as one array + offsets (no pickle)
    grid.npz     float32 log-odds and bool observed mask, so continuing a map keeps its precision

``map.yaml`` thresholds describe the *pixels*, not the mapper: like ROS 1's map_saver and Nav2's
map_saver since ros-navigation/navigation2#5278, a trinary map is written with
``occupied_thresh: 0.65`` and ``free_thresh: 0.196`` so that map_server reads 205 back as unknown
(with ``free_thresh: 0.25`` it reads 205 as free: (255 - 205) / 255 = 0.196 < 0.25). The mapper's
own thresholds decide which cells become 0 / 254 / 205 and are kept in ``graph.json``'s config.

Saving is atomic: everything is written into a hidden folder beside the target and swapped in
with renames (:func:`sensors.atomic.commit_staging_dir`); a failure leaves the old bundle intact.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sensors.atomic import (
    atomic_write_bytes,
    atomic_write_text,
    commit_staging_dir,
    interrupted_replacement,
    make_staging_dir,
)
from sensors.bounded_read import read_bounded
from sensors.config import short_repr
from sensors.geo import GEO_YAML, GeoAnchor, geo_yaml_text, read_geo_anchor
from sensors.images import MAX_IMAGE_FILE_BYTES, MAX_IMAGE_PIXELS, decode_image
from sensors.safe_yaml import read_yaml
from sensors.types import MAX_STAMP_NS, LaserScan, MapError
from slam.occupancy_grid import OCCUPIED, UNKNOWN, GridGeometry, OccupancyGrid

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
MAP_PGM = "map.pgm"
MAP_YAML = "map.yaml"
GRAPH_JSON = "graph.json"
SCANS_NPZ = "scans.npz"
GRID_NPZ = "grid.npz"

# Trinary pixel values written by map_saver.
PIXEL_OCCUPIED = 0
PIXEL_FREE = 254
PIXEL_UNKNOWN = 205
# Thresholds written to a trinary map.yaml: they must separate the three pixel values above
# (occ = 1 - value/255: 1.0, 0.0039, 0.196) whatever the mapper's thresholds were.
TRINARY_YAML_OCCUPIED_THRESH = 0.65
TRINARY_YAML_FREE_THRESH = 0.196

EDGE_KINDS = ("odometry", "scan", "loop")
MAP_MODES = ("trinary", "scale", "raw")
_MAX_8BIT = 255


# --- records ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class GraphEdge:
    """A pose-graph constraint between two keyframes (their ``id``s)."""

    kind: str  # "odometry" | "scan" | "loop"
    from_id: int
    to_id: int
    delta: tuple[float, float, float]  # [m, m, rad] pose of ``to`` in the frame of ``from``
    information: tuple[tuple[float, ...], ...]  # 3x3 inverse covariance over (x, y, yaw)


@dataclass(frozen=True, eq=False)
class MapBundle:
    grid: OccupancyGrid
    keyframe_ids: np.ndarray  # (K,) int64
    keyframe_stamps_ns: np.ndarray  # (K,) int64 [ns]
    # the scan's frame, where each scan was taken (base_link unless depth_to_scan.output_frame
    # is a camera frame: slam.depth_to_scan.scan_pose)
    keyframe_poses: np.ndarray  # (K, 3) float64 [m, m, rad] scan frame in map (optimised)
    keyframe_odom_poses: np.ndarray  # (K, 3) float64 [m, m, rad] scan frame in odom
    edges: tuple[GraphEdge, ...]
    scans: tuple[LaserScan, ...]  # one per keyframe, same order
    config: dict[str, Any] = field(default_factory=dict)  # mapper config as plain values
    source: str = ""  # what the map was built from
    created: str = ""  # ISO 8601; filled in by save_bundle when empty
    geo: GeoAnchor | None = None  # the map frame on WGS84 (geo.yaml, sensors/geo.py)

    @property
    def occupied_thresh(self) -> float:
        return float(self.config.get("occupied_thresh", 0.65))

    @property
    def free_thresh(self) -> float:
        return float(self.config.get("free_thresh", 0.25))


@dataclass(frozen=True)
class MapYaml:
    """A parsed, validated map.yaml (Nav2 map_io ``loadMapYaml``)."""

    image: Path  # resolved path of the image
    mode: str  # trinary | scale | raw
    resolution: float  # [m/cell]
    origin: tuple[float, float, float]  # [m, m, rad] pose of the lower-left pixel
    negate: bool
    occupied_thresh: float
    free_thresh: float


# --- map.yaml + image --------------------------------------------------------------------------


def _read_yaml_doc(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise MapError(f"{path}: missing file")
    doc = read_yaml(path, MapError)
    if not isinstance(doc, dict):
        raise MapError(f"{path}: expected a mapping of map metadata, got {type(doc).__name__}")
    return doc


def _number(doc: dict[str, Any], key: str, path: Path) -> float:
    if key not in doc:
        raise MapError(f"{path}: missing key '{key}'")
    value = doc[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MapError(f"{path}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def parse_map_yaml(path: str | os.PathLike[str], inside_folder: bool = False) -> MapYaml:
    """Read and validate a Nav2 map.yaml. ``inside_folder`` (bundles): the image must be a
    relative path that stays in the YAML's folder; otherwise absolute paths are allowed and
    relative ones resolve against the YAML's folder, as map_server does."""
    path = Path(path)
    doc = _read_yaml_doc(path)
    image_text = doc.get("image")
    if not isinstance(image_text, str) or not image_text.strip():
        raise MapError(f"{path}: 'image' must be a non-empty file name, got {image_text!r}")
    image_rel = Path(image_text)
    if inside_folder:
        if image_rel.is_absolute():
            raise MapError(
                f"{path}: image path {image_text!r} is absolute; a bundle needs a "
                f"file inside its folder"
            )
        folder = path.parent.resolve()
        if not (folder / image_rel).resolve().is_relative_to(folder):
            raise MapError(f"{path}: image path {image_text!r} leaves the bundle folder")
    image = image_rel if image_rel.is_absolute() else path.parent / image_rel

    resolution = _number(doc, "resolution", path)
    if resolution <= 0.0:
        raise MapError(f"{path}: 'resolution' must be positive, got {resolution}")
    origin = doc.get("origin")
    if (
        not isinstance(origin, list)
        or len(origin) != 3
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in origin)
        or not all(math.isfinite(v) for v in origin)
    ):
        raise MapError(f"{path}: 'origin' must be 3 finite numbers [x, y, yaw], got {origin!r}")
    occ = _number(doc, "occupied_thresh", path)
    free = _number(doc, "free_thresh", path)
    if not (0.0 <= free <= 1.0 and 0.0 <= occ <= 1.0):
        raise MapError(
            f"{path}: thresholds must lie in [0, 1], got free_thresh {free}, occupied_thresh {occ}"
        )
    if free >= occ:
        raise MapError(f"{path}: free_thresh ({free}) must be below occupied_thresh ({occ})")
    mode = doc.get("mode", "trinary")
    if mode not in MAP_MODES:
        raise MapError(f"{path}: 'mode' must be one of {MAP_MODES}, got {mode!r}")
    negate = doc.get("negate", None)
    if negate is None:
        raise MapError(f"{path}: missing key 'negate'")
    if negate not in (0, 1):  # True/False compare equal to 1/0, as map_io accepts both
        raise MapError(f"{path}: 'negate' must be 0 or 1, got {negate!r}")
    return MapYaml(
        image,
        mode,
        resolution,
        (float(origin[0]), float(origin[1]), float(origin[2])),
        bool(negate),
        occ,
        free,
    )


_PGM_HEADER = re.compile(
    rb"P([25])(?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)"
    rb"(?:\s+|#[^\n]*\n)+(\d+)\s"
)
_PGM_COMMENT = re.compile(rb"#[^\n]*")
_MAX_16BIT = 65535


def decode_pgm(data: bytes, name: str | os.PathLike[str]) -> tuple[np.ndarray, int]:
    """PGM, binary (P5) or ASCII (P2), 8- or 16-bit -> ((H, W) uint8/uint16 pixels, top row
    first; maxval). Decoded here rather than by OpenCV, which rescales P2 pixels to 255 but
    leaves P5 ones as stored: map_server (ImageMagick) reads every PGM as value / maxval."""
    m = _PGM_HEADER.match(data)
    if m is None:
        raise MapError(f"{name}: not a PGM (P5 binary or P2 ASCII) image header")
    kind = m.group(1)
    if any(len(g) > 9 for g in m.groups()[1:]):  # int() refuses > 4300 digits with ValueError
        raise MapError(
            f"{name}: PGM header number {short_repr(max(m.groups()[1:], key=len))} is too large"
        )
    width, height, maxval = (int(g) for g in m.groups()[1:])
    if width < 1 or height < 1:
        raise MapError(f"{name}: PGM size {width}x{height} is empty")
    if width * height > MAX_IMAGE_PIXELS:
        raise MapError(
            f"{name}: PGM declares {width}x{height} pixels, more than the "
            f"{MAX_IMAGE_PIXELS} read here"
        )
    if not 0 < maxval <= _MAX_16BIT:
        raise MapError(f"{name}: PGM maxval {maxval} unsupported (1..65535)")
    dtype = np.dtype(np.uint8) if maxval <= _MAX_8BIT else np.dtype(">u2")
    body = data[m.end() :]
    if kind == b"5":
        need = width * height * dtype.itemsize
        if len(body) != need:
            raise MapError(
                f"{name}: PGM {width}x{height} needs {need} bytes of pixels, found {len(body)}"
            )
        pixels = np.frombuffer(body, dtype=dtype)
    else:
        tokens = _PGM_COMMENT.sub(b" ", body).split()
        if len(tokens) != width * height:
            raise MapError(
                f"{name}: ASCII PGM {width}x{height} needs {width * height} pixel "
                f"values, found {len(tokens)}"
            )
        try:
            pixels = np.array(tokens, dtype=np.int64)
        except (ValueError, OverflowError):  # OverflowError: a value beyond int64
            raise MapError(
                f"{name}: ASCII PGM holds a pixel value that is not an integer"
            ) from None
        if pixels.size and int(pixels.min()) < 0:
            raise MapError(f"{name}: PGM pixel value {int(pixels.min())} is negative")
    pixels = pixels.reshape(height, width)
    if int(pixels.max()) > maxval:
        raise MapError(f"{name}: PGM pixel value {int(pixels.max())} exceeds maxval {maxval}")
    native = np.uint8 if maxval <= _MAX_8BIT else np.uint16
    return pixels.astype(native), maxval


def encode_pgm(pixels: np.ndarray) -> bytes:
    """(H, W) uint8, top row first -> binary PGM bytes."""
    h, w = pixels.shape
    return f"P5\n{w} {h}\n255\n".encode("ascii") + np.ascontiguousarray(pixels, np.uint8).tobytes()


def _read_image(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Image -> (shade (H, W) float64 in [0, 1] averaged over colour channels, top row first;
    alpha (H, W) float64 in [0, 1] or None)."""
    if not path.exists():
        raise MapError(f"{path}: missing image file")
    # A regular file only: `image: /dev/zero` would be read until memory runs out.
    data = read_bounded(path, MAX_IMAGE_FILE_BYTES, MapError, "image")
    if data[:2] in (b"P2", b"P5"):  # PGM: value / maxval (other netpbm kinds: OpenCV)
        pixels, maxval = decode_pgm(data, path)
        return pixels.astype(np.float64) / maxval, None
    img = decode_image(data, path, MapError)  # a declared size is checked before decoding
    full = float(np.iinfo(img.dtype.type).max) if img.dtype.kind in "ui" else 1.0  # type: ignore[type-var]
    img = img.astype(np.float64) / full
    if img.ndim == 2:
        return img, None
    channels = img.shape[2]
    if channels == 2:  # grey + alpha
        return img[..., 0], img[..., 1]
    colour = img[..., :3].mean(axis=2)  # BGR order does not matter for the mean
    return colour, (img[..., 3] if channels == 4 else None)


def occupancy_values_from_image(
    shade: np.ndarray, alpha: np.ndarray | None, meta: MapYaml
) -> np.ndarray:
    """Nav2 map_io ``loadMapFromFile`` per-pixel rule -> (H, W) int8 nav_msgs values, image rows
    (top first). Vectorised; the thresholds compare strictly as upstream does."""
    if meta.mode == "trinary" and alpha is not None:
        # map_io averages the alpha in with the colour channels in trinary mode.
        shade = (shade * 3.0 + alpha) / 4.0
    occ = shade if meta.negate else 1.0 - shade
    out = np.full(shade.shape, UNKNOWN, dtype=np.int8)
    if meta.mode == "raw":
        percent = np.round(shade * _MAX_8BIT)
        ok = (percent >= 0) & (percent <= OCCUPIED)
        out[ok] = percent[ok].astype(np.int8)
        return out
    is_occ = meta.occupied_thresh < occ
    is_free = occ < meta.free_thresh
    if meta.mode == "scale":
        between = ~is_occ & ~is_free
        scaled = np.rint((occ - meta.free_thresh) / (meta.occupied_thresh - meta.free_thresh) * 100)
        out[between] = scaled[between].astype(np.int8)
    out[is_occ] = OCCUPIED
    out[is_free] = 0
    if meta.mode == "scale" and alpha is not None:
        out[alpha < 1.0] = UNKNOWN
    return out


def unrotate_grid(
    values: np.ndarray, resolution: float, origin: tuple[float, float, float]
) -> tuple[np.ndarray, float, float]:
    """Cells of a map whose ``origin`` has a yaw (row 0 = lowest row, int8 nav_msgs values)
    resampled, nearest cell, into an axis-aligned grid of the same resolution covering it:
    -> (values, origin_x, origin_y). Cells outside the rotated map are unknown (-1).

    map_server publishes such a map with a rotated ``info.origin``; our grids are axis-aligned
    in the map frame, so the rotation is applied once here and every cell keeps its place in
    the map frame (to within half a cell) and no occupied cell is lost."""
    ox, oy, yaw = origin
    h, w = values.shape
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    corners = rot @ np.array([[0.0, w, 0.0, w], [0.0, 0.0, h, h]]) * resolution
    lo = corners.min(axis=1)
    # Snap to whole cells of the rotated corners' extent (a 1e-9 cell slack for round-off).
    out_w, out_h = (
        int(math.ceil((hi - low) / resolution - 1e-9))
        for low, hi in zip(lo, corners.max(axis=1), strict=True)
    )
    new_ox, new_oy = ox + float(lo[0]), oy + float(lo[1])
    # Output cell (x, y) centre in the map frame -> source cell coordinates (centre-integer).
    d = np.array([new_ox - ox, new_oy - oy]) / resolution + 0.5
    inverse = np.hstack([rot.T, (rot.T @ d - 0.5)[:, None]])
    shifted = (values.astype(np.int16) + 1).astype(np.uint8)  # -1..100 -> 0..101, 0 = unknown
    out = cv2.warpAffine(
        shifted,
        inverse,
        (max(out_w, 1), max(out_h, 1)),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    out = (out.astype(np.int16) - 1).astype(np.int8)
    # Nearest sampling can step over a one-cell obstacle at a non-right angle: every cell with
    # some occupancy also marks the output cell that holds its centre (never less occupied).
    rows, cols = np.nonzero(values > 0)
    if rows.size:
        centres = rot @ np.stack([cols + 0.5, rows + 0.5]) * resolution - lo[:, None]
        c_out = np.clip(np.floor(centres[0] / resolution).astype(np.int64), 0, out.shape[1] - 1)
        r_out = np.clip(np.floor(centres[1] / resolution).astype(np.int64), 0, out.shape[0] - 1)
        np.maximum.at(out, (r_out, c_out), values[rows, cols])
    return out, new_ox, new_oy


def _grid_from_yaml(meta: MapYaml) -> OccupancyGrid:
    shade, alpha = _read_image(meta.image)
    values = occupancy_values_from_image(shade, alpha, meta)[::-1]  # row 0 = lowest y
    ox, oy, yaw = meta.origin
    if yaw != 0.0:
        values, ox, oy = unrotate_grid(values, meta.resolution, meta.origin)
        log.info(
            "%s: origin yaw %.4f rad; resampled into an axis-aligned %dx%d grid at (%.3f, %.3f)",
            meta.image,
            yaw,
            values.shape[1],
            values.shape[0],
            ox,
            oy,
        )
    h, w = values.shape
    geom = GridGeometry(meta.resolution, ox, oy, w, h)
    return OccupancyGrid.from_occupancy_values(geom, values)


def load_map_yaml(path: str | os.PathLike[str]) -> OccupancyGrid:
    """A plain Nav2 map (map.yaml + PGM/PNG made by any tool) as an :class:`OccupancyGrid`."""
    return _grid_from_yaml(parse_map_yaml(path))


def trinary_pixels(grid: OccupancyGrid, occupied_thresh: float, free_thresh: float) -> np.ndarray:
    """(H, W) uint8 map_saver trinary pixels, top row first (flipped from the grid)."""
    tri = grid.trinary(occupied_thresh, free_thresh)
    lut = np.full(256, PIXEL_UNKNOWN, dtype=np.uint8)
    lut[OCCUPIED] = PIXEL_OCCUPIED
    lut[0] = PIXEL_FREE
    return lut[tri.view(np.uint8)][::-1]


def _map_yaml_text(grid: OccupancyGrid, image: str) -> str:
    g = grid.geometry
    return (
        f"image: {image}\n"
        f"mode: trinary\n"
        f"resolution: {g.resolution!r}\n"
        f"origin: [{g.origin_x!r}, {g.origin_y!r}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {TRINARY_YAML_OCCUPIED_THRESH}\n"
        f"free_thresh: {TRINARY_YAML_FREE_THRESH}\n"
    )


def save_map_yaml(
    grid: OccupancyGrid,
    path: str | os.PathLike[str],
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    image: str | None = None,
) -> None:
    """Write ``path`` (map.yaml) and its trinary PGM beside it, each atomically.

    ``occupied_thresh`` / ``free_thresh`` classify the grid's probabilities; the YAML gets the
    pixel-separating thresholds (see the module doc).
    """
    path = Path(path)
    image = image or path.with_suffix(".pgm").name
    if Path(image).name != image:
        raise MapError(f"image {image!r} must be a bare file name beside {path.name}")
    atomic_write_bytes(
        path.parent / image, encode_pgm(trinary_pixels(grid, occupied_thresh, free_thresh))
    )
    atomic_write_text(path, _map_yaml_text(grid, image))


# --- graph.json --------------------------------------------------------------------------------


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, tuple):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _graph_json(bundle: MapBundle, created: str) -> str:
    keyframes = [
        {
            "id": int(i),
            "stamp_ns": int(t),
            "pose": [float(v) for v in p],
            "odom_pose": [float(v) for v in o],
        }
        for i, t, p, o in zip(
            bundle.keyframe_ids,
            bundle.keyframe_stamps_ns,
            bundle.keyframe_poses,
            bundle.keyframe_odom_poses,
            strict=True,
        )
    ]
    edges = [
        {
            "kind": e.kind,
            "from": e.from_id,
            "to": e.to_id,
            "delta": list(e.delta),
            "information": [list(row) for row in e.information],
        }
        for e in bundle.edges
    ]
    doc = {
        "schema_version": SCHEMA_VERSION,
        "frame": "map",
        "keyframes": keyframes,
        "edges": edges,
        "config": bundle.config,
        "source": bundle.source,
        "created": created,
    }
    try:
        return json.dumps(doc, indent=1, allow_nan=False, default=_json_default) + "\n"
    except ValueError as err:
        raise MapError(f"{GRAPH_JSON}: cannot store non-finite numbers: {err}") from err


def _floats(value: Any, n: int, where: str) -> tuple[float, ...]:
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        raise MapError(f"{where} must be a list of {n} numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _int(value: Any, where: str) -> int:
    """An id or stamp [ns] of graph.json: an integer the bundle's int64 arrays can hold."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise MapError(f"{where} must be an integer, got {short_repr(value)}")
    if abs(value) > MAX_STAMP_NS:
        raise MapError(f"{where} {short_repr(value)} is out of range (|value| <= {MAX_STAMP_NS})")
    return value


def _parse_graph(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise MapError(f"{path}: missing file") from err
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MapError(f"{path}: not valid JSON: {err}") from err
    except RecursionError:  # json's decoder recurses per nesting level
        raise MapError(f"{path}: not valid JSON: nested too deeply") from None
    if not isinstance(doc, dict):
        raise MapError(f"{path}: expected a JSON object")
    version = doc.get("schema_version")
    if version != SCHEMA_VERSION:
        raise MapError(
            f"{path}: schema_version {version!r} is not supported (expected {SCHEMA_VERSION})"
        )
    kfs = doc.get("keyframes")
    edges = doc.get("edges")
    if not isinstance(kfs, list) or not isinstance(edges, list):
        raise MapError(f"{path}: 'keyframes' and 'edges' must be lists")
    ids, stamps, poses, odom = [], [], [], []
    for k, kf in enumerate(kfs):
        where = f"{path}: keyframes[{k}]"
        if not isinstance(kf, dict):
            raise MapError(f"{where} must be an object")
        ids.append(_int(kf.get("id"), f"{where}.id"))
        stamps.append(_int(kf.get("stamp_ns"), f"{where}.stamp_ns"))
        poses.append(_floats(kf.get("pose"), 3, f"{where}.pose"))
        odom.append(_floats(kf.get("odom_pose"), 3, f"{where}.odom_pose"))
    if len(set(ids)) != len(ids):
        raise MapError(f"{path}: keyframe ids are not unique")
    known = set(ids)
    parsed_edges = []
    for k, e in enumerate(edges):
        where = f"{path}: edges[{k}]"
        if not isinstance(e, dict):
            raise MapError(f"{where} must be an object")
        if e.get("kind") not in EDGE_KINDS:
            raise MapError(f"{where}.kind must be one of {EDGE_KINDS}, got {e.get('kind')!r}")
        a, b = _int(e.get("from"), f"{where}.from"), _int(e.get("to"), f"{where}.to")
        if a not in known or b not in known:
            raise MapError(f"{where} links unknown keyframe ids {a} -> {b}")
        info = e.get("information")
        if not isinstance(info, list) or len(info) != 3:
            raise MapError(f"{where}.information must be a 3x3 list, got {info!r}")
        rows = tuple(_floats(r, 3, f"{where}.information") for r in info)
        dx, dy, dyaw = _floats(e.get("delta"), 3, f"{where}.delta")
        parsed_edges.append(GraphEdge(e["kind"], a, b, (dx, dy, dyaw), rows))
    config = doc.get("config", {})
    if not isinstance(config, dict):
        raise MapError(f"{path}: 'config' must be an object")
    return {
        "ids": np.array(ids, dtype=np.int64),
        "stamps": np.array(stamps, dtype=np.int64),
        "poses": np.array(poses, dtype=np.float64).reshape(-1, 3),
        "odom": np.array(odom, dtype=np.float64).reshape(-1, 3),
        "edges": tuple(parsed_edges),
        "config": config,
        "source": str(doc.get("source", "")),
        "created": str(doc.get("created", "")),
    }


# --- scans.npz / grid.npz ----------------------------------------------------------------------

_SCAN_KEYS = (
    "ranges",
    "offsets",
    "angle_min",
    "angle_increment",
    "range_min",
    "range_max",
    "stamp_ns",
)


def _scans_arrays(scans: Sequence[LaserScan]) -> dict[str, np.ndarray]:
    counts = np.array([len(s.ranges) for s in scans], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    ranges = (
        np.concatenate([np.asarray(s.ranges, np.float32) for s in scans])
        if scans
        else np.zeros(0, np.float32)
    )
    return {
        "ranges": ranges,
        "offsets": offsets,
        "angle_min": np.array([s.angle_min for s in scans], dtype=np.float64),
        "angle_increment": np.array([s.angle_increment for s in scans], dtype=np.float64),
        "range_min": np.array([s.range_min for s in scans], dtype=np.float64),
        "range_max": np.array([s.range_max for s in scans], dtype=np.float64),
        "stamp_ns": np.array([s.stamp_ns for s in scans], dtype=np.int64),
    }


def _load_npz(path: Path, keys: Sequence[str]) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in keys if k not in npz.files]
            if missing:
                raise MapError(f"{path}: missing arrays {missing}")
            return {k: npz[k] for k in keys}
    except FileNotFoundError as err:
        raise MapError(f"{path}: missing file") from err
    except MapError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error) as err:
        # zlib.error: a compressed member whose data was damaged (found by bench/fuzz_inputs)
        raise MapError(f"{path}: corrupt or unreadable npz: {err}") from err


def _parse_scans(path: Path) -> tuple[LaserScan, ...]:
    a = _load_npz(path, _SCAN_KEYS)
    offsets = a["offsets"]
    k = len(offsets) - 1
    if offsets.ndim != 1 or k < 0 or offsets.dtype.kind not in "iu":
        raise MapError(f"{path}: 'offsets' must be a 1-D integer array of K+1 entries")
    if offsets[0] != 0 or np.any(np.diff(offsets) < 0) or offsets[-1] != len(a["ranges"]):
        raise MapError(f"{path}: 'offsets' must rise from 0 to len(ranges) = {len(a['ranges'])}")
    for key in _SCAN_KEYS[2:]:
        if a[key].shape != (k,):
            raise MapError(f"{path}: '{key}' has shape {a[key].shape}, expected ({k},)")
    # The scans' geometry must be numbers (their ranges may hold inf/NaN: no return, REP-117).
    for key in ("angle_min", "angle_increment", "range_min", "range_max", "stamp_ns"):
        if a[key].dtype.kind not in "iuf":
            raise MapError(f"{path}: '{key}' must be numbers, got {a[key].dtype}")
        bad = np.flatnonzero(~np.isfinite(a[key]))
        if bad.size:
            raise MapError(f"{path}: '{key}' of scan {int(bad[0])} is not a finite number")
    ranges = a["ranges"].astype(np.float32, copy=False)
    return tuple(
        LaserScan(
            int(a["stamp_ns"][i]),
            float(a["angle_min"][i]),
            float(a["angle_increment"][i]),
            ranges[offsets[i] : offsets[i + 1]].copy(),
            float(a["range_min"][i]),
            float(a["range_max"][i]),
        )
        for i in range(k)
    )


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with path.open("wb") as fh:
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]


# --- bundle ------------------------------------------------------------------------------------


def _write_scans(folder: Path, scans: Sequence[LaserScan]) -> None:
    _write_npz(folder / SCANS_NPZ, _scans_arrays(scans))


def _write_bundle_files(bundle: MapBundle, folder: Path, created: str) -> None:
    grid = bundle.grid
    (folder / MAP_PGM).write_bytes(
        encode_pgm(trinary_pixels(grid, bundle.occupied_thresh, bundle.free_thresh))
    )
    (folder / MAP_YAML).write_text(_map_yaml_text(grid, MAP_PGM), encoding="utf-8")
    (folder / GRAPH_JSON).write_text(_graph_json(bundle, created), encoding="utf-8")
    _write_scans(folder, bundle.scans)
    _write_npz(folder / GRID_NPZ, {"log_odds": grid.log_odds, "observed": grid.observed})
    if bundle.geo is not None:
        (folder / GEO_YAML).write_text(geo_yaml_text(bundle.geo), encoding="utf-8")


def save_bundle(bundle: MapBundle, path: str | os.PathLike[str]) -> None:
    """Write ``bundle`` as the folder ``path``, replacing an existing one only when complete."""
    path = Path(path)
    k = len(bundle.keyframe_ids)
    sizes = (
        len(bundle.keyframe_stamps_ns),
        len(bundle.keyframe_poses),
        len(bundle.keyframe_odom_poses),
        len(bundle.scans),
    )
    if any(n != k for n in sizes):
        raise MapError(
            f"bundle has {k} keyframe ids but (stamps, poses, odom poses, scans) = {sizes}"
        )
    if path.exists() and not path.is_dir():
        raise MapError(f"{path}: exists and is not a bundle folder")
    created = bundle.created or datetime.now(timezone.utc).isoformat(timespec="seconds")
    staging = make_staging_dir(path)
    try:
        _write_bundle_files(bundle, staging, created)
        commit_staging_dir(staging, path)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    log.info(
        "saved map bundle %s (%d keyframes, %dx%d cells)",
        path,
        k,
        bundle.grid.geometry.width,
        bundle.grid.geometry.height,
    )


def _member(folder: Path, name: str) -> Path:
    """``folder / name``, which must not lead out of the bundle (a symlinked file): a bundle
    is self-contained, and one copied or shared must not read whatever the link points at."""
    path = folder / name
    if path.is_symlink() and not path.resolve().is_relative_to(folder.resolve()):
        raise MapError(f"{path}: a link out of the bundle folder (to {path.resolve()})")
    return path


def _bundle_grid(folder: Path, occupied_thresh: float, free_thresh: float) -> OccupancyGrid:
    """The PGM/YAML map, refined by grid.npz when present and consistent with the PGM."""
    meta = parse_map_yaml(_member(folder, MAP_YAML), inside_folder=True)
    from_image = _grid_from_yaml(meta)
    grid_path = _member(folder, GRID_NPZ)
    if not grid_path.exists():
        return from_image
    a = _load_npz(grid_path, ("log_odds", "observed"))
    geom = from_image.geometry
    if a["log_odds"].shape != geom.shape or a["observed"].shape != geom.shape:
        raise MapError(
            f"{grid_path}: log_odds {a['log_odds'].shape} does not match "
            f"{meta.image.name} ({geom.height}, {geom.width})"
        )
    if a["log_odds"].dtype != np.float32 or a["observed"].dtype != np.bool_:
        raise MapError(f"{grid_path}: need float32 log_odds and bool observed")
    precise = OccupancyGrid(geom, a["log_odds"], a["observed"])
    # A map edited in an image editor after saving: the image is what the user wants.
    if not np.array_equal(
        precise.trinary(occupied_thresh, free_thresh),
        from_image.trinary(occupied_thresh, free_thresh),
    ):
        log.warning(
            "%s differs from %s (edited?); using the image and ignoring the log-odds",
            meta.image,
            grid_path,
        )
        return from_image
    return precise


def _config_probability(config: dict[str, Any], key: str, default: float, where: str) -> float:
    value = config.get(key, default)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (ok and 0.0 < value < 1.0):  # NaN fails too
        raise MapError(f"{where}.{key} must be a number in (0, 1), got {short_repr(value)}")
    return float(value)


def load_bundle(path: str | os.PathLike[str]) -> MapBundle:
    """Read and validate a bundle folder written by :func:`save_bundle` (or by hand)."""
    folder = Path(path)
    if not folder.is_dir() and (aside := interrupted_replacement(folder)) is not None:
        log.warning(
            "%s: missing; loading %s, the bundle a save interrupted between its two "
            "renames had moved aside",
            folder,
            aside.name,
        )
        folder = aside
    if not folder.is_dir():
        raise MapError(f"{folder}: missing map bundle folder")
    graph = _parse_graph(_member(folder, GRAPH_JSON))
    scans = _parse_scans(_member(folder, SCANS_NPZ))
    if len(scans) != len(graph["ids"]):
        raise MapError(
            f"keyframe count mismatch: {folder / GRAPH_JSON} has "
            f"{len(graph['ids'])} keyframes, {folder / SCANS_NPZ} has "
            f"{len(scans)} scans"
        )
    config = graph["config"]
    where = f"{folder / GRAPH_JSON}: config"
    occupied = _config_probability(config, "occupied_thresh", 0.65, where)
    free = _config_probability(config, "free_thresh", 0.25, where)
    if not free < occupied:
        raise MapError(f"{where}: free_thresh ({free}) must be below occupied_thresh ({occupied})")
    grid = _bundle_grid(folder, occupied, free)
    made_at = config.get("resolution")
    if made_at is not None:  # bundles by other tools may not say; ours always do
        number = isinstance(made_at, (int, float)) and not isinstance(made_at, bool)
        if not (number and math.isfinite(made_at) and made_at > 0):
            raise MapError(f"{where}.resolution must be a number > 0, got {short_repr(made_at)}")
        if not math.isclose(made_at, grid.geometry.resolution, rel_tol=1e-6):
            raise MapError(
                f"{folder / MAP_YAML}: resolution {grid.geometry.resolution:g} m "
                f"disagrees with {made_at:g} m the map was built at ({GRAPH_JSON}); "
                f"the scans would not fit the grid"
            )
    return MapBundle(
        grid,
        graph["ids"],
        graph["stamps"],
        graph["poses"],
        graph["odom"],
        graph["edges"],
        scans,
        config,
        graph["source"],
        graph["created"],
        read_geo_anchor(folder),
    )


# A plain map.yaml is already thresholded into nav_msgs percentages (100 occupied, 0 free,
# -1 unknown; "scale" maps in between), so its cells are classified like map_server's own
# defaults rather than by the thresholds that made the pixels.
NAV2_OCCUPIED_THRESH = 0.65  # [probability] value >= 65 % is occupied
NAV2_FREE_THRESH = 0.25  # [probability] value < 25 % is free


@dataclass(frozen=True, eq=False)
class LoadedMap:
    grid: OccupancyGrid
    occupied_thresh: float  # [probability] classifying the grid's cells for localisation
    free_thresh: float  # [probability]
    kind: str  # "bundle" | "map.yaml"
    path: Path


def load_map(path: Path) -> LoadedMap:
    """A map bundle folder or a Nav2 map.yaml; :class:`MapError` for anything else."""
    if path.is_dir() or interrupted_replacement(path) is not None:
        bundle = load_bundle(path)  # also a bundle a save left between its two renames
        loaded = LoadedMap(bundle.grid, bundle.occupied_thresh, bundle.free_thresh, "bundle", path)
    elif path.is_file() and path.suffix.lower() in (".yaml", ".yml"):
        loaded = LoadedMap(
            load_map_yaml(path), NAV2_OCCUPIED_THRESH, NAV2_FREE_THRESH, "map.yaml", path
        )
    elif path.is_file():
        raise MapError(f"{path}: not a map: give a map bundle folder or its map.yaml")
    else:
        raise MapError(f"{path}: no such map (a map bundle folder or a map.yaml)")
    if not 0.0 < loaded.free_thresh < loaded.occupied_thresh < 1.0:
        raise MapError(
            f"{path}: need 0 < free_thresh ({loaded.free_thresh}) < occupied_thresh "
            f"({loaded.occupied_thresh}) < 1"
        )
    return loaded


__all__ = [
    "NAV2_FREE_THRESH",
    "NAV2_OCCUPIED_THRESH",
    "GRAPH_JSON",
    "LoadedMap",
    "load_map",
    "GRID_NPZ",
    "MAP_PGM",
    "MAP_YAML",
    "SCANS_NPZ",
    "SCHEMA_VERSION",
    "GraphEdge",
    "MapBundle",
    "MapYaml",
    "decode_pgm",
    "encode_pgm",
    "load_bundle",
    "load_map_yaml",
    "occupancy_values_from_image",
    "parse_map_yaml",
    "save_bundle",
    "save_map_yaml",
    "trinary_pixels",
    "unrotate_grid",
]
