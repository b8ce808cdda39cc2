"""GPS fixes: ``gps.txt`` in recordings, ``sensor_msgs/NavSatFix`` in bags, a simulated receiver.

``gps.txt`` (one fix per line, TUM-style stamps, ``#`` comments)::

    # timestamp latitude longitude altitude sigma_h
    1700000000.000000 44.98000312 -93.27001045 256.1 3.0

latitude/longitude [deg] WGS84, altitude [m] above the ellipsoid, sigma_h [m] the horizontal
standard deviation (NavSatFix's ``position_covariance`` as sqrt of the mean of its east and north
variances). A fix without a position (NavSatStatus -1, STATUS_NO_FIX) is not a fix: it is skipped
and counted. GPS is a rough prior for global relocalisation (metres), never a pose to drive by.

:class:`SimGpsReceiver` (and :func:`simulate_gps` over a whole trajectory) samples a receiver
riding a true planar trajectory through a geo anchor: fixes at ``rate_hz``, Gaussian noise of
``sigma_m`` per axis, and dropouts as bursts (a two-state Gilbert channel: ``p_drop`` to enter
an outage per fix, ``mean_outage_s`` its mean length). :class:`GpsFix` is one fix from any
receiver; a live run streams them to ``gps.txt`` with :class:`GpsWriter`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from sensors.atomic import atomic_write_text
from sensors.config import SimConfig
from sensors.geo import GeoAnchor
from sensors.tum import read_stamped_text
from sensors.types import NS_PER_S, SensorError, format_stamp

GPS_TXT = "gps.txt"
GPS_COLUMNS = ("timestamp", "latitude", "longitude", "altitude", "sigma_h")
GPS_HEADER = f"# GPS fixes\n# {' '.join(GPS_COLUMNS)}\n"


@dataclass(frozen=True)
class GpsFix:
    """One fix, from any receiver (simulated, NavSatFix, a recording's gps.txt)."""

    stamp_ns: int  # [ns] on the run's clock
    latitude: float  # [deg] WGS84
    longitude: float  # [deg] WGS84
    altitude: float  # [m] above the ellipsoid
    sigma_m: float  # [m] horizontal standard deviation


@dataclass(frozen=True, eq=False)
class GpsStream:
    stamps_ns: np.ndarray  # (N,) int64 [ns]
    latitude: np.ndarray  # (N,) [deg] WGS84
    longitude: np.ndarray  # (N,) [deg] WGS84
    altitude: np.ndarray  # (N,) [m] above the ellipsoid
    sigma_m: np.ndarray  # (N,) [m] horizontal standard deviation

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    def fixes(self, offset_ns: int = 0) -> list[GpsFix]:
        """The fixes one by one, stamps moved by ``offset_ns`` (a recording replayed live)."""
        return [
            GpsFix(int(t) + offset_ns, float(la), float(lo), float(al), float(s))
            for t, la, lo, al, s in zip(
                self.stamps_ns,
                self.latitude,
                self.longitude,
                self.altitude,
                self.sigma_m,
                strict=True,
            )
        ]

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


def _gps_row(t: int, la: float, lo: float, al: float, s: float) -> str:
    return f"{format_stamp(int(t))} {la:.9f} {lo:.9f} {al:.3f} {s:.3f}\n"


def write_gps_txt(path: str | os.PathLike[str], stream: GpsStream) -> None:
    lines = [GPS_HEADER]
    lines += [
        _gps_row(t, la, lo, al, s)
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

    @classmethod
    def from_sim(cls, sim: SimConfig) -> SimGpsConfig:
        """The receiver of the ``sim`` config section (``sim.gps_*``)."""
        return cls(sim.gps_sigma, sim.gps_rate, sim.gps_outage_probability, sim.gps_mean_outage)


def antenna_xy(x: Any, y: Any, yaw: Any, mount: Sequence[float]) -> tuple[Any, Any]:
    """Where a receiver mounted at ``mount`` (x, y) [m] in base_link is when base_link is at
    (x, y, yaw) (scalars or arrays): navsat_transform's ``base_link -> gps`` transform, the
    robot's ``gps_x`` / ``gps_y``. At (0, 0) it is (x, y) as given, bit for bit."""
    mx, my = float(mount[0]), float(mount[1])
    if mx == 0.0 and my == 0.0:
        return x, y
    c, s = np.cos(yaw), np.sin(yaw)
    return x + c * mx - s * my, y + s * mx + c * my


class SimGpsReceiver:
    """A simulated receiver fed its true positions (:func:`antenna_xy`) as they happen (the
    live simulated robot) or all at once (:func:`simulate_gps`): a fix every ``1 / rate_hz``
    with Gaussian noise of ``sigma_m`` per axis, lost in bursts (the module doc's Gilbert channel);
    deterministic for a seed."""

    def __init__(self, anchor: GeoAnchor, cfg: SimGpsConfig, seed: int) -> None:
        if cfg.rate_hz <= 0 or cfg.sigma_m <= 0:
            raise SensorError("a simulated GPS needs rate_hz > 0 and sigma_m > 0")
        self.anchor, self.cfg = anchor, cfg
        self._rng = np.random.default_rng(seed)
        self._step_ns = int(round(NS_PER_S / cfg.rate_hz))
        # Leave an outage with p = 1 / (fixes per outage).
        self._p_leave = min(1.0, 1.0 / max(cfg.mean_outage_s * cfg.rate_hz, 1.0))
        self._next_ns: int | None = None  # [ns] when the next fix is due
        self._up = True  # the channel state

    def update(self, stamp_ns: int, x: float, y: float) -> GpsFix | None:
        """The true map position (x, y) [m] at ``stamp_ns``: a fix when one is due and the
        channel is up (the fix takes the stamp of the pose that made it due)."""
        if self._next_ns is None:
            self._next_ns = int(stamp_ns)
        if stamp_ns < self._next_ns:
            return None
        missed = (int(stamp_ns) - self._next_ns) // self._step_ns  # a host that fell behind
        self._next_ns += (missed + 1) * self._step_ns
        nx, ny = self._rng.normal(0.0, self.cfg.sigma_m, 2)
        enter, leave = self._rng.random(2)
        self._up = (enter >= self.cfg.p_drop) if self._up else bool(leave < self._p_leave)
        if not self._up:
            return None
        lat, lon, alt = self.anchor.to_wgs84(x + nx, y + ny)
        return GpsFix(int(stamp_ns), float(lat), float(lon), float(alt), self.cfg.sigma_m)


def simulate_gps(
    stamps_ns: np.ndarray, xy_map: np.ndarray, anchor: GeoAnchor, cfg: SimGpsConfig, seed: int
) -> GpsStream:
    """Fixes of a :class:`SimGpsReceiver` riding the true trajectory ``xy_map`` (N, 2) [m] in
    the anchored map frame, sampled at the fix times; deterministic for a seed."""
    if len(stamps_ns) < 2 or cfg.rate_hz <= 0 or cfg.sigma_m <= 0:
        raise SensorError("simulate_gps needs a trajectory of 2+ poses, rate_hz > 0, sigma_m > 0")
    rx = SimGpsReceiver(anchor, cfg, seed)
    step = int(round(NS_PER_S / cfg.rate_hz))
    t = np.arange(int(stamps_ns[0]), int(stamps_ns[-1]) + 1, step, dtype=np.int64)
    x = np.interp(t, stamps_ns, xy_map[:, 0])
    y = np.interp(t, stamps_ns, xy_map[:, 1])
    # One step per fix (1 Hz): thousands, not a hot path.
    fixes = [f for k in range(t.size) if (f := rx.update(int(t[k]), x[k], y[k])) is not None]
    return stream_of(fixes)


def stream_of(fixes: list[GpsFix]) -> GpsStream:
    """A :class:`GpsStream` of single fixes."""
    cols = np.array(
        [(f.latitude, f.longitude, f.altitude, f.sigma_m) for f in fixes], np.float64
    ).reshape(-1, 4)
    stamps = np.array([f.stamp_ns for f in fixes], np.int64)
    return GpsStream(stamps, *(cols[:, i].copy() for i in range(4)))


class GpsWriter:
    """``gps.txt`` streamed fix by fix (a live run: rows reach the OS at once, so a killed run
    keeps its fixes); read back with :func:`read_gps_txt`."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.count = 0
        self._file: IO[str] | None = None

    def add(self, fix: GpsFix) -> None:
        if self._file is None:
            self._file = open(self.path, "w", buffering=1)  # closed by close()
            self._file.write(GPS_HEADER)
        self._file.write(
            _gps_row(fix.stamp_ns, fix.latitude, fix.longitude, fix.altitude, fix.sigma_m)
        )
        self.count += 1

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


__all__ = [
    "GPS_TXT",
    "GpsFix",
    "GpsStream",
    "GpsWriter",
    "SimGpsConfig",
    "SimGpsReceiver",
    "check_fixes",
    "navsatfix_sigma",
    "read_gps_txt",
    "simulate_gps",
    "stream_of",
    "write_gps_txt",
]
