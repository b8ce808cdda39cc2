"""`rgbdnav fleet show` and `rgbdnav fleet align`: several robots' maps in one world frame.

``show`` draws every robot's map and keepout mask where its fleet file puts it (``world ->
<name>/map``) with the one world renderer (:mod:`rgbdnav.world_picture`, as ``world-view``); it
also writes a rerun recording with one static transform per robot (as RViz's fixed frame
``world`` shows them). ``align`` finds B's map frame in A's without a guess
(:mod:`slam.map_align`), writes ``alignment.yaml``, the merged Nav2 map and a two-robot
``fleet.yaml`` that ``show`` can draw.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

from rgbdnav.report import write_png
from rgbdnav.world_picture import Layer, load_layer, render_world, tint, world_geometry
from sensors.atomic import atomic_write_text
from slam.config import AlignConfig
from slam.fleet import Fleet, load_fleet
from slam.map_align import Alignment, align_maps, merge_grids
from slam.map_bundle import load_map, save_map_yaml

log = logging.getLogger(__name__)


def load_layers(fleet: Fleet) -> list[Layer]:
    return [load_layer(r.name, r.map_path, r.T_world_map, r.keepout_path) for r in fleet.robots]


def run_show(fleet_path: Path, out: Path) -> dict[str, Path]:
    """Draw the fleet (PNG) and record it (rerun .rrd) into ``out``."""
    from rgbdnav.visualize import save_fleet_recording

    fleet = load_fleet(fleet_path)
    layers = load_layers(fleet)
    out.mkdir(parents=True, exist_ok=True)
    geom = world_geometry(layers)
    write_png(out / "fleet.png", render_world(layers, geom))
    save_fleet_recording(out / "fleet.rrd", layers, [tint(i) for i in range(len(layers))])
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


__all__ = ["load_layers", "run_align", "run_show"]
