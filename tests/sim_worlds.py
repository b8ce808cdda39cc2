"""Analytic worlds for the simulator's tests and the tests that render through it (depth -> scan):
a room of given walls and furniture, a long wall straight ahead, the noise-free simulator."""

from __future__ import annotations

import math
from dataclasses import replace

from sensors.config import SimConfig

NOISELESS = replace(
    SimConfig(),
    disparity_noise=0.0,
    disparity_subpixel=10**6,
    depth_dropout=0.0,
    depth_edge_threshold=0.0,
    shadows=False,
    rgb_noise=0.0,
)


def room(walls: list[dict], furniture: list[dict] | None = None) -> dict:
    """A world dict (as a world YAML loads) with these walls and furniture, start at the origin."""
    return {
        "name": "test",
        "walls": walls,
        "furniture": furniture or [],
        "start": [0.0, 0.0, 0.0],
        "route": [[1.0, 0.0]],
    }


def wall_ahead(distance: float, yaw_deg: float = 0.0) -> dict:
    """A 20 m wall, 0.1 m thick, crossing the x axis at ``distance``, turned by ``yaw_deg`` from
    facing us."""
    a = math.radians(yaw_deg)
    dx, dy = -math.sin(a) * 10, math.cos(a) * 10
    return {"from": [distance - dx, -dy], "to": [distance + dx, dy], "thickness": 0.1}
