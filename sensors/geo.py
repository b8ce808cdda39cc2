"""A map's geo anchor: where its origin lies on the WGS84 ellipsoid, and how its axes turn.

A bundle may carry ``geo.yaml`` (and a fleet file a ``geo:`` mapping) with the WGS84 latitude and
longitude [deg] and the ellipsoidal altitude [m] of the map frame's origin, and ``heading_deg``:
the angle of the map's +x axis from **east, counter-clockwise** (ENU yaw, as REP-103 and
robot_localization's navsat_transform use it; 0 = x east, y north; 90 = x north, y west)::

    latitude: 44.98
    longitude: -93.27
    altitude: 256.0
    heading_deg: 0.0

WGS84 <-> local East-North-Up goes through pymap3d (geodetic2enu / enu2geodetic, exact on the
ellipsoid); the map frame is the ENU frame at the anchor turned by ``heading_deg``. Map z is ENU
up. GPS is a rough prior (metres), so no datum shifts or geoid heights are modelled.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from sensors.config import finite_float, short_repr, unknown_keys
from sensors.safe_yaml import read_yaml
from sensors.types import MapError

GEO_YAML = "geo.yaml"
_KEYS = ("latitude", "longitude", "altitude", "heading_deg")


@dataclass(frozen=True)
class GeoAnchor:
    """WGS84 pose of a map frame's origin (see the module doc)."""

    latitude: float  # [deg] WGS84, north positive
    longitude: float  # [deg] WGS84, east positive
    altitude: float = 0.0  # [m] above the WGS84 ellipsoid
    heading_deg: float = 0.0  # [deg] map +x from east, counter-clockwise (ENU yaw)

    def __post_init__(self) -> None:
        if not -90.0 <= self.latitude <= 90.0:
            raise MapError(f"geo latitude must be in [-90, 90] deg, got {self.latitude}")
        if not -180.0 <= self.longitude <= 360.0:
            raise MapError(f"geo longitude must be in [-180, 360] deg, got {self.longitude}")
        if not (math.isfinite(self.altitude) and math.isfinite(self.heading_deg)):
            raise MapError(
                f"geo altitude and heading_deg must be finite, got "
                f"{self.altitude}, {self.heading_deg}"
            )

    def to_map(
        self, lat: ArrayLike, lon: ArrayLike, alt: ArrayLike | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """WGS84 (deg, deg, m) -> map (x, y, z) [m]; ``alt`` defaults to the anchor's."""
        import pymap3d

        h = self.altitude if alt is None else alt
        e, n, u = pymap3d.geodetic2enu(lat, lon, h, self.latitude, self.longitude, self.altitude)
        c, s = math.cos(math.radians(self.heading_deg)), math.sin(math.radians(self.heading_deg))
        e, n = np.asarray(e, dtype=np.float64), np.asarray(n, dtype=np.float64)
        return c * e + s * n, -s * e + c * n, np.asarray(u, dtype=np.float64)

    def to_wgs84(
        self, x: ArrayLike, y: ArrayLike, z: ArrayLike = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Map (x, y, z) [m] -> WGS84 (lat [deg], lon [deg], alt [m])."""
        import pymap3d

        c, s = math.cos(math.radians(self.heading_deg)), math.sin(math.radians(self.heading_deg))
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        e, n = c * x - s * y, s * x + c * y
        lat, lon, alt = pymap3d.enu2geodetic(e, n, z, self.latitude, self.longitude, self.altitude)
        return np.asarray(lat), np.asarray(lon), np.asarray(alt)

    def moved(self, x: float, y: float, yaw: float) -> GeoAnchor:
        """The anchor of a frame whose pose in this one is (x [m], y [m], yaw [rad])."""
        lat, lon, alt = self.to_wgs84(x, y)
        return GeoAnchor(float(lat), float(lon), float(alt), self.heading_deg + math.degrees(yaw))

    def pose_of(self, other: GeoAnchor) -> tuple[float, float, float]:
        """(x [m], y [m], yaw [rad]) of ``other``'s frame in this one (the inverse of
        :meth:`moved`; the two ENU tangent planes are taken as one, as over a site)."""
        x, y, _ = self.to_map(other.latitude, other.longitude, other.altitude)
        yaw = math.radians(other.heading_deg - self.heading_deg)
        return float(x), float(y), math.atan2(math.sin(yaw), math.cos(yaw))

    def as_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in _KEYS}


def geo_from_dict(data: Any, where: str) -> GeoAnchor:
    """A :class:`GeoAnchor` from a YAML mapping; :class:`MapError` naming ``where`` and the key."""
    if not isinstance(data, dict):
        raise MapError(f"{where}: geo must be a mapping with {', '.join(_KEYS)}")
    unknown = unknown_keys(data, _KEYS)
    if unknown:
        raise MapError(f"{where}: unknown geo key {unknown[0]!r} (known: {', '.join(_KEYS)})")
    values: dict[str, float] = {}
    for key in _KEYS:
        if key not in data:
            if key in ("latitude", "longitude"):
                raise MapError(f"{where}: geo needs {key}")
            continue
        v = finite_float(data[key])
        if v is None:
            raise MapError(
                f"{where}: geo {key} must be a finite number, got {short_repr(data[key])}"
            )
        values[key] = v
    try:
        return GeoAnchor(**values)
    except MapError as err:
        raise MapError(f"{where}: {err}") from None


def read_geo_anchor(map_path: str | os.PathLike[str]) -> GeoAnchor | None:
    """The geo anchor of a map: ``geo.yaml`` in a bundle folder, or beside a map.yaml; None when
    there is none."""
    path = Path(map_path)
    geo = path / GEO_YAML if path.is_dir() else path.parent / GEO_YAML
    if not geo.is_file():
        return None
    return geo_from_dict(read_yaml(geo, MapError, "geo anchor"), str(geo))


def geo_yaml_text(anchor: GeoAnchor) -> str:
    return "".join(f"{k}: {v!r}\n" for k, v in anchor.as_dict().items())


def geo_anchor_of(path: str | os.PathLike[str]) -> GeoAnchor:
    """The anchor of a map (bundle folder or map.yaml beside a geo.yaml) or of a geo.yaml
    itself; :class:`MapError` saying how to add one when there is none."""
    p = Path(path)
    if p.is_file() and p.name == GEO_YAML:
        return geo_from_dict(read_yaml(p, MapError, "geo anchor"), str(p))
    if not p.exists():
        raise MapError(f"{p}: no such map")
    anchor = read_geo_anchor(p)
    if anchor is None:
        where = p if p.is_dir() else p.parent
        raise MapError(
            f"{p}: the map has no geo anchor: add {where / GEO_YAML} with latitude, "
            "longitude, altitude and heading_deg"
        )
    return anchor


__all__ = [
    "GEO_YAML",
    "GeoAnchor",
    "geo_anchor_of",
    "geo_from_dict",
    "geo_yaml_text",
    "read_geo_anchor",
]
