"""Timing statistics of stamped streams (rate, gaps, disorder), for ``rgbdnav info``."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sensors.source import Source
from sensors.types import NS_PER_S

GAP_FACTOR = 1.5  # an interval longer than this many median periods counts as a gap


@dataclass(frozen=True)
class StreamStats:
    name: str
    count: int
    first_ns: int | None  # [ns] earliest stamp; None when empty
    last_ns: int | None  # [ns] latest stamp; None when empty
    duration_s: float  # [s] latest - earliest
    rate_hz: float  # [Hz] 1 / median positive interval; NaN with fewer than two distinct stamps
    mean_rate_hz: float  # [Hz] (count - 1) / duration; NaN when duration is 0
    gaps: int  # intervals longer than GAP_FACTOR median periods
    max_gap_s: float  # [s] longest positive interval between consecutive stamps (0 if none)
    non_monotonic: int  # intervals < 0 (stamp earlier than its predecessor)
    duplicates: int  # intervals == 0 (stamp equal to its predecessor)


def stream_stats(name: str, stamps_ns: np.ndarray) -> StreamStats:
    """Statistics of one stream's stamps, taken in arrival (file) order."""
    t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    if t.size == 0:
        return StreamStats(name, 0, None, None, 0.0, math.nan, math.nan, 0, 0.0, 0, 0)
    dt = np.diff(t)
    positive = dt[dt > 0]
    duration_ns = int(t.max() - t.min())
    if positive.size:
        median_ns = float(np.median(positive))
        rate_hz = NS_PER_S / median_ns
        gaps = int(np.count_nonzero(positive > GAP_FACTOR * median_ns))
    else:
        rate_hz, gaps = math.nan, 0
    return StreamStats(
        name=name,
        count=int(t.size),
        first_ns=int(t.min()),
        last_ns=int(t.max()),
        duration_s=duration_ns / NS_PER_S,
        rate_hz=rate_hz,
        mean_rate_hz=(t.size - 1) * NS_PER_S / duration_ns if duration_ns > 0 else math.nan,
        gaps=gaps,
        max_gap_s=float(positive.max()) / NS_PER_S if positive.size else 0.0,
        non_monotonic=int(np.count_nonzero(dt < 0)),
        duplicates=int(np.count_nonzero(dt == 0)),
    )


def describe_source(src: Source) -> list[StreamStats]:
    """Stats of every stream a source holds, in its own order."""
    return [stream_stats(name, stamps) for name, stamps in src.stream_stamps().items()]


def format_table(rows: Sequence[tuple[str, ...]]) -> list[str]:
    """Rows of cells (the first row a header) -> aligned lines: first column left, rest right."""
    widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
    return [
        "  ".join(
            cell.ljust(w) if c == 0 else cell.rjust(w)
            for c, (cell, w) in enumerate(zip(row, widths, strict=True))
        ).rstrip()
        for row in rows
    ]


def format_stats_table(stats: list[StreamStats]) -> str:
    """A plain, aligned text table (one row per stream)."""

    def num(value: float, digits: int) -> str:
        return "-" if math.isnan(value) else f"{value:.{digits}f}"

    header = (
        "stream",
        "count",
        "duration_s",
        "rate_hz",
        "mean_hz",
        "gaps",
        "max_gap_s",
        "non_mono",
        "dups",
    )
    rows = [header] + [
        (
            s.name,
            str(s.count),
            num(s.duration_s, 3),
            num(s.rate_hz, 2),
            num(s.mean_rate_hz, 2),
            str(s.gaps),
            num(s.max_gap_s, 3),
            str(s.non_monotonic),
            str(s.duplicates),
        )
        for s in stats
    ]
    return "\n".join(format_table(rows))
