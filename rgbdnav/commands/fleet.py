"""`rgbdnav fleet show` and `rgbdnav fleet align`: several robots' maps in one world frame.

``show`` draws every robot's map and keepout mask where its fleet file puts it (``world ->
<name>/map``), each in its own tint and blended where maps overlap, so no map hides another; it
also writes a rerun recording with one static transform per robot (as RViz's fixed frame
``world`` shows them). ``align`` finds B's map frame in A's without a guess
(:mod:`slam.map_align`), writes ``alignment.yaml``, the merged Nav2 map and a two-robot
``fleet.yaml`` that ``show`` can draw.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rgbdnav.report import write_png
from sensors.atomic import atomic_write_text
from slam.fleet import Fleet, load_fleet
from slam.map_align import AlignConfig, Alignment, align_maps, merge_grids
from slam.map_bundle import load_map, load_map_yaml, save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid, warp_to_geometry

log = logging.getLogger(__name__)

# Robot tints (RGB), cycled; walls are drawn in the tint, free space in a pale version of it.
TINTS_RGB = np.array(
    [
        (31, 119, 180),
        (214, 39, 40),
        (44, 160, 44),
        (148, 103, 189),
        (255, 127, 14),
        (23, 190, 207),
        (227, 119, 194),
        (140, 86, 75),
    ],
    float,
)
FREE_PALENESS = 0.65  # free space: this much white mixed into the tint
UNKNOWN_RGB = (205, 205, 205)  # map_saver's unknown grey
KEEPOUT_STRIPE_PX = 6  # [px] period of the keepout hatching
MAX_PICTURE_PX = 4000  # [px] the picture's longer side; coarser cells beyond
MARGIN_M = 2.0  # [m] around the maps


@dataclass(frozen=True)
class Layer:
    """One robot's map in the world, ready to draw."""

    name: str
    grid: OccupancyGrid
    occupied_thresh: float
    free_thresh: float
    T_world_map: tuple[float, float, float]
    keepout: OccupancyGrid | None  # in the robot's map frame


def load_layers(fleet: Fleet) -> list[Layer]:
    layers = []
    for r in fleet.robots:
        m = load_map(r.map_path)
        keepout = None if r.keepout_path is None else load_map_yaml(r.keepout_path)
        layers.append(
            Layer(r.name, m.grid, m.occupied_thresh, m.free_thresh, r.T_world_map, keepout)
        )
    return layers


def _corners(grid: OccupancyGrid) -> np.ndarray:
    """(4, 2) [m] corners of the box around the grid's walls (the whole grid if none): a map's
    grid spans the laser's reach, far beyond the building."""
    g = grid.geometry
    rows, cols = np.nonzero(grid.occupied_mask())  # walls: rays past them are faint
    r0, r1, c0, c1 = (
        (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)
        if len(rows)
        else (0, g.height, 0, g.width)
    )
    x0, x1 = g.origin_x + c0 * g.resolution, g.origin_x + c1 * g.resolution
    y0, y1 = g.origin_y + r0 * g.resolution, g.origin_y + r1 * g.resolution
    return np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])


def _in_world(pts: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return pts @ np.array([[c, s], [-s, c]]) + np.array(pose[:2])


def world_geometry(layers: list[Layer]) -> GridGeometry:
    """A grid over every map's walls in the world (a frame origin far from its map is
    left out: its arrow is clipped), at the finest map resolution (coarser
    if the picture would exceed ``MAX_PICTURE_PX``)."""
    pts = np.vstack([_in_world(_corners(ly.grid), ly.T_world_map) for ly in layers])
    lo, hi = pts.min(axis=0) - MARGIN_M, pts.max(axis=0) + MARGIN_M
    res = min(ly.grid.geometry.resolution for ly in layers)
    res = max(res, float(np.max(hi - lo)) / MAX_PICTURE_PX)
    return GridGeometry.from_bounds(lo[0], lo[1], hi[0], hi[1], res)


def render_fleet(layers: list[Layer], geom: GridGeometry) -> np.ndarray:
    """(H, W, 3) uint8 BGR picture, top row = max y: free space pale and walls full in each
    robot's tint, averaged where several robots' maps overlap; keepouts hatched in the tint."""
    h, w = geom.shape
    wall_sum, free_sum = np.zeros((h, w, 3)), np.zeros((h, w, 3))
    wall_n, free_n = np.zeros((h, w)), np.zeros((h, w))
    keep_sum, keep_n = np.zeros((h, w, 3)), np.zeros((h, w))
    for i, ly in enumerate(layers):
        tint = TINTS_RGB[i % len(TINTS_RGB)]
        g = ly.grid
        walls = warp_to_geometry(
            g.occupied_mask(ly.occupied_thresh), g.geometry, ly.T_world_map, geom
        )
        free = warp_to_geometry(g.free_mask(ly.free_thresh), g.geometry, ly.T_world_map, geom)
        wall_sum += walls[..., None] * tint
        wall_n += walls
        free_sum += free[..., None] * (FREE_PALENESS * 255 + (1 - FREE_PALENESS) * tint)
        free_n += free
        if ly.keepout is not None:
            k = ly.keepout
            zone = warp_to_geometry(k.occupied_mask(0.65), k.geometry, ly.T_world_map, geom)
            keep_sum += zone[..., None] * tint
            keep_n += zone
    img = np.empty((h, w, 3))
    img[:] = UNKNOWN_RGB
    has_free = free_n > 0
    img[has_free] = free_sum[has_free] / free_n[has_free, None]
    rows, cols = np.indices((h, w))
    stripes = ((rows + cols) % KEEPOUT_STRIPE_PX) < KEEPOUT_STRIPE_PX // 2
    hatch = (keep_n > 0) & stripes
    img[hatch] = 0.5 * img[hatch] + 0.5 * keep_sum[hatch] / keep_n[hatch, None]
    has_wall = wall_n > 0
    img[has_wall] = wall_sum[has_wall] / wall_n[has_wall, None]
    bgr = np.ascontiguousarray(img[::-1, :, ::-1]).astype(np.uint8)
    _annotate(bgr, layers, geom)
    return bgr


def _annotate(bgr: np.ndarray, layers: list[Layer], geom: GridGeometry) -> None:
    """Each map frame's axes (x long) and a legend, drawn in place."""
    h = geom.height
    axis_px = max(10, h // 25)
    scale = max(0.5, max(geom.shape) / 600)  # text size grows with the picture
    for i, ly in enumerate(layers):
        colour = tuple(int(v) for v in TINTS_RGB[i % len(TINTS_RGB)][::-1])
        x, y, yaw = ly.T_world_map
        r, c = geom.world_to_cell(x, y)
        origin = (int(c), int(h - 1 - r))
        tip = (int(c + axis_px * math.cos(yaw)), int(h - 1 - r - axis_px * math.sin(yaw)))
        cv2.arrowedLine(bgr, origin, tip, colour, max(2, int(2 * scale)), tipLength=0.25)
        cv2.putText(
            bgr,
            f"{ly.name}/map",
            (origin[0] + 4, origin[1] + int(20 * scale)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5 * scale,
            colour,
            max(1, int(scale)),
            cv2.LINE_AA,
        )
        line = (8, int((30 + 30 * i) * scale))
        cv2.putText(bgr, ly.name, line, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 2, cv2.LINE_AA)


def run_show(fleet_path: Path, out: Path) -> dict[str, Path]:
    """Draw the fleet (PNG) and record it (rerun .rrd) into ``out``."""
    from rgbdnav.visualize import save_fleet_recording

    fleet = load_fleet(fleet_path)
    layers = load_layers(fleet)
    out.mkdir(parents=True, exist_ok=True)
    geom = world_geometry(layers)
    write_png(out / "fleet.png", render_fleet(layers, geom))
    tints = [tuple(int(v) for v in TINTS_RGB[i % len(TINTS_RGB)]) for i in range(len(layers))]
    save_fleet_recording(out / "fleet.rrd", layers, tints)
    return {"picture": out / "fleet.png", "recording": out / "fleet.rrd"}


def _alignment_yaml(a: Path, b: Path, al: Alignment) -> str:
    v = al.verification
    cov = ", ".join(f"{x:.6g}" for x in al.covariance.ravel())
    rival = "null" if al.rival is None else f"{al.rival.score / max(v.score, 1e-12):.3f}"
    return (
        f"# B's map frame in A's map frame (T_a_b): p_A = R(yaw) p_B + (x, y)\n"
        f"map_a: {str(a)!r}\nmap_b: {str(b)!r}\n"
        f"x: {al.T_a_b[0]:.4f}  # [m]\ny: {al.T_a_b[1]:.4f}  # [m]\n"
        f"yaw: {al.T_a_b[2]:.6f}  # [rad] ({math.degrees(al.T_a_b[2]):.2f} deg)\n"
        f"confidence: {al.confidence:.3f}\n"
        f"overlap:\n"
        f"  wall_matched_m: {v.overlap_m:.1f}  # [m] wall length agreeing both ways\n"
        f"  agreement_ab: {v.agreement_ab:.3f}  # B's walls over A's known area near A's walls\n"
        f"  agreement_ba: {v.agreement_ba:.3f}\n"
        f"  rival_ratio: {rival}  # best distinct other pose's score / this pose's\n"
        f"covariance: [{cov}]  # 3x3 over (x, y, yaw), row-major\n"
    )


def run_align(
    map_a: Path, map_b: Path, out: Path, cfg: AlignConfig
) -> tuple[Alignment, dict[str, Path]]:
    """Align ``map_b`` to ``map_a``; :class:`MapError` (nothing written) when unsure."""
    a, b = load_map(map_a), load_map(map_b)
    if not math.isclose(a.grid.geometry.resolution, b.grid.geometry.resolution, rel_tol=1e-6):
        log.info(
            "resolutions differ (%g, %g m): the merged map uses A's",
            a.grid.geometry.resolution,
            b.grid.geometry.resolution,
        )
    al = align_maps(a.grid, b.grid, (a.occupied_thresh, b.occupied_thresh), cfg)
    out.mkdir(parents=True, exist_ok=True)
    merged = merge_grids(a.grid, b.grid, al.T_a_b)
    (out / "merged").mkdir(exist_ok=True)
    save_map_yaml(merged, out / "merged" / "map.yaml", a.occupied_thresh, a.free_thresh)
    atomic_write_text(out / "alignment.yaml", _alignment_yaml(map_a, map_b, al))
    x, y, yaw = al.T_a_b
    atomic_write_text(
        out / "fleet.yaml",
        "robots:\n"
        f"  - name: a\n    map: {str(map_a.resolve())!r}\n"
        "    T_world_map: {x: 0.0, y: 0.0, yaw: 0.0}\n"
        f"  - name: b\n    map: {str(map_b.resolve())!r}\n"
        f"    T_world_map: {{x: {x:.4f}, y: {y:.4f}, yaw: {yaw:.6f}}}\n",
    )
    outputs = {
        "alignment": out / "alignment.yaml",
        "merged map": out / "merged" / "map.yaml",
        "fleet file": out / "fleet.yaml",
    }
    return al, outputs


__all__ = ["Layer", "load_layers", "render_fleet", "run_align", "run_show", "world_geometry"]
