"""GPS fixes: ``gps.txt`` in recordings, ``sensor_msgs/NavSatFix`` in bags, a simulated receiver.

``gps.txt`` (one fix per line, TUM-style stamps, ``#`` comments)::

    # timestamp latitude longitude altitude sigma_h
    1700000000.000000 44.98000312 -93.27001045 256.1 3.0

latitude/longitude [deg] WGS84, altitude [m] above the ellipsoid, sigma_h [m] the horizontal
standard deviation (NavSatFix's ``position_covariance`` as sqrt of the mean of its east and north
variances). A fix without a position (NavSatStatus -1, STATUS_NO_FIX) is not a fix: it is skipped
and counted. GPS is a rough prior for global relocalisation (metres), never a pose to drive by.

:func:`simulate_gps` samples a receiver from a true planar trajectory and a geo anchor: fixes at
``rate_hz``, Gaussian noise of ``sigma_m`` per axis, and dropouts as bursts (a two-state
Gilbert channel: ``p_drop`` to enter an outage per fix, ``mean_outage_s`` its mean length).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensors.atomic import atomic_write_text
from sensors.geo import GeoAnchor
from sensors.tum import read_stamped_text
from sensors.types import NS_PER_S, SensorError, format_stamp

GPS_TXT = "gps.txt"
GPS_COLUMNS = ("timestamp", "latitude", "longitude", "altitude", "sigma_h")


@dataclass(frozen=True, eq=False)
class GpsStream:
    stamps_ns: np.ndarray  # (N,) int64 [ns]
    latitude: np.ndarray  # (N,) [deg] WGS84
    longitude: np.ndarray  # (N,) [deg] WGS84
    altitude: np.ndarray  # (N,) [m] above the ellipsoid
    sigma_m: np.ndarray  # (N,) [m] horizontal standard deviation

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    def in_map(self, anchor: GeoAnchor) -> np.ndarray:
        """(N, 2) [m] the fixes in the anchored map frame."""
        x, y, _ = anchor.to_map(self.latitude, self.longitude, self.altitude)
        return np.column_stack([np.atleast_1d(x), np.atleast_1d(y)])


def check_fixes(stream: GpsStream, where: str) -> GpsStream:
    """SensorError naming ``where`` for coordinates off the globe or a non-positive sigma."""
    bad = ~(
        (np.abs(stream.latitude) <= 90)
        & (np.abs(stream.longitude) <= 360)
        & np.isfinite(stream.altitude)
        & (stream.sigma_m > 0)
        & np.isfinite(stream.sigma_m)
    )
    if np.any(bad):
        i = int(np.argmax(bad))
        raise SensorError(
            f"{where}: fix {i + 1} is not a fix: latitude {stream.latitude[i]}, "
            f"longitude {stream.longitude[i]}, altitude {stream.altitude[i]}, "
            f"sigma_h {stream.sigma_m[i]} (need |lat| <= 90, sigma_h > 0)"
        )
    return stream


def read_gps_txt(path: str | os.PathLike[str]) -> GpsStream:
    table = read_stamped_text(path, GPS_COLUMNS)
    v = table.numeric(np.float64, "latitude longitude altitude sigma_h").reshape(-1, 4)
    stream = GpsStream(
        table.stamps_ns, v[:, 0].copy(), v[:, 1].copy(), v[:, 2].copy(), v[:, 3].copy()
    )
    return check_fixes(stream, str(path))


def write_gps_txt(path: str | os.PathLike[str], stream: GpsStream) -> None:
    lines = [f"# GPS fixes\n# {' '.join(GPS_COLUMNS)}\n"]
    lines += [
        f"{format_stamp(int(t))} {la:.9f} {lo:.9f} {al:.3f} {s:.3f}\n"
        for t, la, lo, al, s in zip(
            stream.stamps_ns,
            stream.latitude,
            stream.longitude,
            stream.altitude,
            stream.sigma_m,
            strict=True,
        )
    ]
    atomic_write_text(Path(path), "".join(lines))


def navsatfix_sigma(position_covariance: np.ndarray, covariance_type: int) -> float:
    """Horizontal sigma [m] of a NavSatFix: sqrt of the mean of the east and north variances;
    NaN when the covariance is unknown (COVARIANCE_TYPE_UNKNOWN = 0)."""
    if covariance_type == 0:
        return math.nan
    c = np.asarray(position_covariance, dtype=np.float64).reshape(3, 3)
    return math.sqrt(max(0.5 * (c[0, 0] + c[1, 1]), 0.0))


@dataclass(frozen=True)
class SimGpsConfig:
    sigma_m: float = 3.0  # [m] per-axis noise (consumer receivers: 2-5 m)
    rate_hz: float = 1.0  # [Hz] fixes
    p_drop: float = 0.05  # probability per fix of entering an outage
    mean_outage_s: float = 5.0  # [s] mean outage length


def simulate_gps(
    stamps_ns: np.ndarray, xy_map: np.ndarray, anchor: GeoAnchor, cfg: SimGpsConfig, seed: int
) -> GpsStream:
    """Fixes of a receiver riding the true trajectory ``xy_map`` (N, 2) [m] in the anchored map
    frame (see the module doc); deterministic for a seed."""
    if len(stamps_ns) < 2 or cfg.rate_hz <= 0 or cfg.sigma_m <= 0:
        raise SensorError("simulate_gps needs a trajectory of 2+ poses, rate_hz > 0, sigma_m > 0")
    rng = np.random.default_rng(seed)
    step = int(round(NS_PER_S / cfg.rate_hz))
    t = np.arange(int(stamps_ns[0]), int(stamps_ns[-1]) + 1, step, dtype=np.int64)
    x = np.interp(t, stamps_ns, xy_map[:, 0]) + rng.normal(0.0, cfg.sigma_m, t.size)
    y = np.interp(t, stamps_ns, xy_map[:, 1]) + rng.normal(0.0, cfg.sigma_m, t.size)
    # Gilbert channel: leave an outage with p = 1 / (fixes per outage), vectorised as runs.
    p_leave = min(1.0, 1.0 / max(cfg.mean_outage_s * cfg.rate_hz, 1.0))
    enter, leave = rng.random(t.size) < cfg.p_drop, rng.random(t.size) < p_leave
    up = np.ones(t.size, bool)
    state = True
    for i in range(t.size):  # one step per fix (1 Hz): thousands, not a hot path
        state = (not enter[i]) if state else bool(leave[i])
        up[i] = state
    lat, lon, alt = anchor.to_wgs84(x[up], y[up])
    return GpsStream(
        t[up],
        np.atleast_1d(lat),
        np.atleast_1d(lon),
        np.atleast_1d(alt),
        np.full(int(up.sum()), cfg.sigma_m),
    )


__all__ = [
    "GPS_TXT",
    "GpsStream",
    "SimGpsConfig",
    "check_fixes",
    "navsatfix_sigma",
    "read_gps_txt",
    "simulate_gps",
    "write_gps_txt",
]
