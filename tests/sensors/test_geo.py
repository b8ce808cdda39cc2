"""Geo anchors: WGS84 <-> map through pymap3d, the heading turning the map's axes, and errors."""

from __future__ import annotations

import math

import pytest

from sensors.geo import GeoAnchor, geo_anchor_of, geo_from_dict, geo_yaml_text
from sensors.types import MapError

MINNEAPOLIS = GeoAnchor(44.98, -93.27, 256.0, 0.0)
M_PER_DEG_LAT_45 = 111_132.0  # [m] one degree of latitude at 45 deg (WGS84, to ~1 m)


def test_a_thousandth_of_a_degree_north_is_111_m_up_the_y_axis() -> None:
    x, y, _ = MINNEAPOLIS.to_map(44.981, -93.27)
    assert float(x) == pytest.approx(0.0, abs=1e-6)
    assert float(y) == pytest.approx(M_PER_DEG_LAT_45 / 1000, abs=0.5)


def test_heading_90_turns_the_map_x_axis_north() -> None:
    anchor = GeoAnchor(44.98, -93.27, 256.0, 90.0)
    x, y, _ = anchor.to_map(44.981, -93.27)
    assert (float(x), float(y)) == pytest.approx((111.1, 0.0), abs=0.5)


def test_map_to_wgs84_round_trips() -> None:
    anchor = GeoAnchor(44.98, -93.27, 256.0, 33.0)
    lat, lon, _ = anchor.to_wgs84(123.4, -56.7)
    x, y, _ = anchor.to_map(lat, lon)
    assert (float(x), float(y)) == pytest.approx((123.4, -56.7), abs=1e-3)


def test_moved_anchor_places_the_frame_origin() -> None:
    moved = MINNEAPOLIS.moved(100.0, 0.0, math.pi / 2)
    x, y, _ = MINNEAPOLIS.to_map(moved.latitude, moved.longitude)
    assert (float(x), float(y)) == pytest.approx((100.0, 0.0), abs=1e-3)
    assert moved.heading_deg == pytest.approx(90.0)


def test_bad_geo_keys_and_values_are_named(tmp_path) -> None:
    with pytest.raises(MapError, match="unknown geo key 'lat'"):
        geo_from_dict({"lat": 1.0, "longitude": 2.0}, "x.yaml")
    with pytest.raises(MapError, match="latitude must be in"):
        geo_from_dict({"latitude": 91.0, "longitude": 2.0}, "x.yaml")
    with pytest.raises(MapError, match="geo needs longitude"):
        geo_from_dict({"latitude": 1.0}, "x.yaml")


def test_geo_yaml_in_a_bundle_is_found_and_its_absence_explained(tmp_path) -> None:
    with pytest.raises(MapError, match="has no geo anchor: add .*geo.yaml"):
        geo_anchor_of(tmp_path)
    (tmp_path / "geo.yaml").write_text(geo_yaml_text(MINNEAPOLIS))
    assert geo_anchor_of(tmp_path) == MINNEAPOLIS
