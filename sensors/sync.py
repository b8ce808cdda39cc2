"""Time association of sensor streams: approximate-time sets, camera-info stamps, wheel odometry.

Three tools, one per kind of stream:

* **Images (rgb, depth, ...)**: :class:`ApproximateTimeSync`, the ROS ``message_filters``
  ApproximateTime policy (the adaptive algorithm, not the Python ``slop`` heuristic). A set holds
  one message per stream; its *spread* is latest minus earliest stamp. The policy guarantees:

  1. each message is used at most once;
  2. sets do not cross (per stream, set stamps only increase);
  3. sets are contiguous (no set could be formed from the messages skipped between two sets);
  4. each set has minimal spread among the sets contiguous to the previous one (with an age
     penalty: a later set must be smaller by a factor ``1 + age_penalty`` to win);
  5. the output depends on stamps only, not on how streams interleave on arrival;
  6. no emitted set spreads wider than ``slop`` (``max_interval_duration`` in ROS).

  :func:`synchronise` runs it over whole recordings.
* **Camera info** with stamps from another clock: :func:`fix_camera_info_stamps`.
* **Wheel encoders** (50 Hz, cumulative counts): not matched but interpolated to the image stamp
  by :func:`interpolate_wheels`.

Nothing is dropped silently: every message pushed ends up matched, pending, or counted under
exactly one reason in :class:`SyncStats` (see ``DROP_REASONS``).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from sensors.config import SyncConfig
from sensors.stream_stats import format_table
from sensors.types import NS_PER_S, SyncError

log = logging.getLogger(__name__)

DEFAULT_AGE_PENALTY = 0.1  # message_filters' C++ default (the wiki's "0" is out of date)
DEFAULT_WARN_FRACTION = SyncConfig().warn_fraction
WARN_MIN_MESSAGES = 100  # before flush, do not judge the drop fraction on fewer messages

# Why a message was not part of any emitted set (each dropped message has exactly one).
DROP_REASONS = ("out_of_order", "duplicate", "stale", "unmatched")


class _Message(NamedTuple):
    stamp_ns: int
    payload: Any


@dataclass(frozen=True)
class MatchedSet:
    """One message per stream: ``messages[name] = (stamp_ns, payload)``."""

    messages: Mapping[str, tuple[int, Any]]
    spread_ns: int  # [ns] latest minus earliest stamp in the set

    def stamp_ns(self, name: str) -> int:
        return self.messages[name][0]

    def payload(self, name: str) -> Any:
        return self.messages[name][1]


@dataclass(frozen=True)
class StreamSyncStats:
    """Fate of the messages pushed on one stream.

    ``received == matched + out_of_order + duplicate + stale + unmatched + pending``.
    """

    received: int = 0
    matched: int = 0  # emitted in a set
    out_of_order: int = 0  # stamp older than the last accepted one on this stream
    duplicate: int = 0  # stamp equal to the last accepted one on this stream
    stale: int = 0  # not newer than this stream's message in the last emitted set: can never match
    unmatched: int = 0  # accepted, then discarded: no partner within slop, skipped between sets,
    #                     evicted from a full queue, or still queued at flush
    overflow: int = 0  # of ``unmatched``: evicted from a full queue (raise queue_size)
    pending: int = 0  # still queued (0 after flush)

    @property
    def dropped(self) -> int:
        return self.out_of_order + self.duplicate + self.stale + self.unmatched


@dataclass(frozen=True)
class SyncStats:
    """Counts by stream and reason, plus the spread of the emitted sets."""

    streams: Mapping[str, StreamSyncStats]
    sets: int  # emitted sets
    mean_spread_ns: float  # [ns] NaN without sets
    max_spread_ns: int  # [ns] 0 without sets

    @property
    def received(self) -> int:
        return sum(s.received for s in self.streams.values())

    @property
    def dropped(self) -> int:
        return sum(s.dropped for s in self.streams.values())

    @property
    def dropped_fraction(self) -> float:
        """Dropped over received messages, all streams (0 when nothing was received)."""
        return self.dropped / self.received if self.received else 0.0

    def matched_fraction(self, name: str) -> float:
        s = self.streams[name]
        return s.matched / s.received if s.received else math.nan

    def report(self) -> str:
        """A plain aligned text table, one row per stream, then the set spread."""
        header = (
            "stream",
            "received",
            "matched",
            *DROP_REASONS,
            "(overflow)",
            "pending",
            "matched_%",
        )
        rows: list[tuple[str, ...]] = [header]
        for name, s in self.streams.items():
            pct = f"{100 * s.matched / s.received:.1f}" if s.received else "-"
            counts = (
                s.received,
                s.matched,
                s.out_of_order,
                s.duplicate,
                s.stale,
                s.unmatched,
                s.overflow,
                s.pending,
            )
            rows.append((name, *(str(c) for c in counts), pct))
        lines = format_table(rows)
        if self.sets:
            lines.append(
                f"{self.sets} sets, spread mean {self.mean_spread_ns / 1e6:.2f} ms, "
                f"max {self.max_spread_ns / 1e6:.2f} ms"
            )
        else:
            lines.append("0 sets")
        return "\n".join(lines)


class ApproximateTimeSync:
    """Streaming ApproximateTime synchroniser (ROS ``message_filters`` semantics).

    Each stream has a queue (``deque``) of messages not yet decided and a ``past`` list of
    messages already examined for the current candidate set. Let ``S`` be the last published
    set and ``T`` the one being built. Per stream the queue heads form a *candidate*; its start
    (earliest head) and end (latest head) bound its spread.

    1. With no candidate: if the heads spread wider than ``slop``, or the stream holding the
       latest head (the would-be *pivot*) has just lost a message to a full queue, discard the
       earliest head; otherwise the heads become the candidate and the latest head's stream the
       pivot. Every later candidate must include the pivot message (sets are contiguous), so
       the pivot bounds the search.
    2. Move the earliest head to ``past`` and look at the next heads: a candidate that is smaller
       (by the age-penalised comparison) replaces the current one; the messages examined before
       it are skipped (counted ``unmatched``).
    3. Publish when the candidate is provably optimal: the pivot itself became the earliest head
       (no candidate containing it remains), or any future candidate, which must span
       ``[start, pivot_time]`` and end no earlier than the current latest head, is already no
       smaller. When a queue runs dry the proof is attempted on *virtual* heads: an empty stream
       cannot deliver earlier than ``max(pivot_time, last + min_period)``.
    4. On publish, the examined messages go back to the queue fronts and the set's messages are
       removed; the search restarts from the next heads.

    A full queue (queued + examined > ``queue_size``) cancels the search and evicts the oldest
    message of the offending stream. Per message the work is O(queue_size x streams).
    """

    def __init__(
        self,
        stream_names: Iterable[str],
        queue_size: int,
        slop_ns: int,
        *,
        age_penalty: float = DEFAULT_AGE_PENALTY,
        min_period_ns: Mapping[str, int] | None = None,
        warn_fraction: float = DEFAULT_WARN_FRACTION,
    ) -> None:
        names = tuple(stream_names)
        if not names:
            raise SyncError("ApproximateTimeSync needs at least one stream")
        if len(set(names)) != len(names):
            raise SyncError(f"stream names must be unique, got {list(names)}")
        if queue_size < 1:
            raise SyncError(f"queue_size must be >= 1, got {queue_size}")
        if slop_ns < 0:
            raise SyncError(f"slop must be >= 0 ns, got {slop_ns}")
        if age_penalty < 0:
            raise SyncError(f"age_penalty must be >= 0, got {age_penalty}")
        unknown = set(min_period_ns or {}) - set(names)
        if unknown:
            raise SyncError(f"min_period_ns names unknown streams {sorted(unknown)}")
        self.names = names
        self.queue_size = int(queue_size)
        self.slop_ns = int(slop_ns)
        self.age_penalty = float(age_penalty)
        self.warn_fraction = float(warn_fraction)
        self._index = {name: i for i, name in enumerate(names)}
        self._min_period = [int((min_period_ns or {}).get(name, 0)) for name in names]
        n = len(names)
        self._queues: list[deque[_Message]] = [deque() for _ in range(n)]
        self._past: list[list[_Message]] = [[] for _ in range(n)]
        self._has_dropped = [False] * n
        self._candidate: list[_Message] | None = None
        self._pivot: int | None = None
        self._pivot_time = 0
        self._cand_start = 0
        self._cand_end = 0
        self._last_accepted: list[int | None] = [None] * n
        self._last_emitted: list[int | None] = [None] * n
        self._counts = [
            dict.fromkeys(("received", "matched", *DROP_REASONS, "overflow"), 0) for _ in range(n)
        ]
        self._sets = 0
        self._spread_sum = 0
        self._spread_max = 0
        self._warned = False
        self._out: list[MatchedSet] = []

    @classmethod
    def from_config(
        cls, stream_names: Iterable[str], cfg: SyncConfig, **kwargs: Any
    ) -> ApproximateTimeSync:
        return cls(
            stream_names,
            cfg.queue_size,
            round(cfg.slop * NS_PER_S),
            warn_fraction=cfg.warn_fraction,
            **kwargs,
        )

    # --- public API ---------------------------------------------------------------------------

    def push(self, name: str, stamp_ns: int, payload: Any = None) -> list[MatchedSet]:
        """Add one message; returns the sets this message completed (usually zero or one)."""
        i = self._index.get(name)
        if i is None:
            raise SyncError(f"unknown stream {name!r} (streams: {', '.join(self.names)})")
        stamp_ns = int(stamp_ns)
        self._counts[i]["received"] += 1
        reason = self._rejection(i, stamp_ns)
        if reason is not None:
            self._drop(i, reason)
            return []
        self._last_accepted[i] = stamp_ns
        queue = self._queues[i]
        queue.append(_Message(stamp_ns, payload))
        if len(queue) == 1 and all(self._queues):
            # This queue was the last empty one: there may be sets to find.
            self._process()
        if len(queue) + len(self._past[i]) > self.queue_size:
            # Full queue: abandon the candidate search and evict this stream's oldest message.
            self._recover_all()
            queue.popleft()
            self._drop(i, "unmatched", overflow=True)
            self._has_dropped[i] = True
            if self._pivot is not None:
                self._candidate, self._pivot = None, None
                self._process()
        out, self._out = self._out, []
        return out

    def flush(self) -> list[MatchedSet]:
        """End of all streams: publish what is still provably best, count the rest unmatched.

        With no message to come, an empty stream's virtual head lies at +inf, so a pending
        candidate is optimal; publishing it may expose further sets among the queued messages.
        """
        while self._pivot is not None:
            self._publish()
            self._process()
        for i in range(len(self.names)):
            self._counts[i]["unmatched"] += len(self._queues[i]) + len(self._past[i])
            self._queues[i].clear()
            self._past[i].clear()
            self._has_dropped[i] = False
        self._check_drop_fraction(final=True)
        out, self._out = self._out, []
        return out

    @property
    def stats(self) -> SyncStats:
        streams = {}
        for i, name in enumerate(self.names):
            c = self._counts[i]
            pending = len(self._queues[i]) + len(self._past[i])
            streams[name] = StreamSyncStats(**c, pending=pending)
        mean = self._spread_sum / self._sets if self._sets else math.nan
        return SyncStats(streams, self._sets, mean, self._spread_max)

    # --- bookkeeping --------------------------------------------------------------------------

    def _rejection(self, i: int, stamp: int) -> str | None:
        last, emitted = self._last_accepted[i], self._last_emitted[i]
        if last is not None and stamp == last:
            return "duplicate"
        if emitted is not None and stamp <= emitted:
            return "stale"  # sets do not cross: this stream already matched something later
        if last is not None and stamp < last:
            return "out_of_order"  # queues must stay sorted; ROS would warn and misbehave
        return None

    def _drop(self, i: int, reason: str, overflow: bool = False) -> None:
        self._counts[i][reason] += 1
        if overflow:
            self._counts[i]["overflow"] += 1
        self._check_drop_fraction(final=False)

    def _check_drop_fraction(self, final: bool) -> None:
        if self._warned:
            return
        received = sum(c["received"] for c in self._counts)
        dropped = sum(c[r] for c in self._counts for r in DROP_REASONS)
        if received == 0 or (not final and received < WARN_MIN_MESSAGES):
            return
        if dropped / received > self.warn_fraction:
            self._warned = True
            log.warning(
                "sync dropped %d of %d messages (%.1f %% > warn_fraction %.1f %%):\n%s",
                dropped,
                received,
                100 * dropped / received,
                100 * self.warn_fraction,
                self.stats.report(),
            )

    # --- the ApproximateTime algorithm --------------------------------------------------------

    def _heads(self) -> list[int]:
        return [q[0].stamp_ns for q in self._queues]

    def _virtual_heads(self) -> list[int]:
        """Queue heads; an empty queue's next message cannot be earlier than this bound."""
        times = []
        for i, q in enumerate(self._queues):
            if q:
                times.append(q[0].stamp_ns)
            else:
                bound = self._past[i][-1].stamp_ns + self._min_period[i]
                times.append(max(bound, self._pivot_time))
        return times

    @staticmethod
    def _bounds(times: list[int]) -> tuple[int, int, int, int]:
        """(start index, start time, end index, end time): first earliest, last latest head."""
        start_i = end_i = 0
        for i in range(1, len(times)):
            if times[i] < times[start_i]:
                start_i = i
            if times[i] >= times[end_i]:
                end_i = i
        return start_i, times[start_i], end_i, times[end_i]

    def _growth(self, end: int) -> float:
        """How much later than the candidate's a set ending at ``end`` ends, age-penalised."""
        return (end - self._cand_end) * (1 + self.age_penalty)

    def _smaller(self, start: int, end: int) -> bool:
        """Is [start, end] smaller than the current candidate? (it must start later by more)"""
        return self._growth(end) < start - self._cand_start

    def _proved_optimal(self, end: int) -> bool:
        """Any later candidate spans [.., pivot_time] and ends at ``end`` or later: no smaller."""
        return self._growth(end) >= self._pivot_time - self._cand_start

    def _move_front_to_past(self, i: int) -> None:
        self._past[i].append(self._queues[i].popleft())

    def _make_candidate(self, start: int, end: int) -> None:
        # The messages examined since the previous candidate can no longer be used.
        for i, past in enumerate(self._past):
            for _ in past:
                self._drop(i, "unmatched")
            past.clear()
        self._candidate = [q[0] for q in self._queues]
        self._cand_start, self._cand_end = start, end

    def _recover_all(self) -> None:
        for q, past in zip(self._queues, self._past, strict=True):
            q.extendleft(reversed(past))
            past.clear()

    def _publish(self) -> None:
        assert self._candidate is not None
        cand = self._candidate
        spread = self._cand_end - self._cand_start
        messages = {n: (m.stamp_ns, m.payload) for n, m in zip(self.names, cand, strict=True)}
        self._out.append(MatchedSet(messages, spread))
        self._sets += 1
        self._spread_sum += spread
        self._spread_max = max(self._spread_max, spread)
        for i, m in enumerate(cand):
            self._counts[i]["matched"] += 1
            self._last_emitted[i] = m.stamp_ns
        self._candidate, self._pivot = None, None
        # Examined messages return to the queues; the set's own messages (their fronts) go.
        self._recover_all()
        for q, m in zip(self._queues, cand, strict=True):
            assert q[0] is m
            q.popleft()

    def _process(self) -> None:
        while all(self._queues):
            start_i, start_t, end_i, end_t = self._bounds(self._heads())
            for i in range(len(self.names)):
                if i != end_i:
                    # No dropped message could have beaten the heads we hold for these streams.
                    self._has_dropped[i] = False
            if self._pivot is None:
                # 1. No candidate yet: take the heads unless too wide or the pivot lost data.
                if end_t - start_t > self.slop_ns or self._has_dropped[end_i]:
                    self._queues[start_i].popleft()
                    self._drop(start_i, "unmatched")
                    continue
                self._make_candidate(start_t, end_t)
                self._pivot, self._pivot_time = end_i, end_t
            elif self._smaller(start_t, end_t):
                # 2. A smaller candidate sharing the pivot replaces the current one.
                self._make_candidate(start_t, end_t)
            self._move_front_to_past(start_i)
            # 3. Publish when no later candidate can be smaller.
            if start_i == self._pivot or self._proved_optimal(end_t):
                self._publish()
            elif not all(self._queues):
                self._virtual_search()

    def _virtual_search(self) -> None:
        """Try to prove optimality with the earliest stamps the empty streams could still send."""
        moves = [0] * len(self.names)
        while True:
            start_i, start_t, _, end_t = self._bounds(self._virtual_heads())
            if self._proved_optimal(end_t):
                self._publish()  # also returns the virtually moved messages
                return
            if self._smaller(start_t, end_t):
                # An optimistic future candidate could still win: undo the moves and wait.
                for i, k in enumerate(moves):
                    if k:
                        self._queues[i].extendleft(reversed(self._past[i][-k:]))
                        del self._past[i][-k:]
                return
            # start_t < pivot_time here (at equality one of the tests above holds), so the start
            # stream is not a virtual head and has a real message to move.
            self._move_front_to_past(start_i)
            moves[start_i] += 1


def synchronise(
    streams: Mapping[str, np.ndarray],
    slop_ns: int,
    queue_size: int,
    *,
    age_penalty: float = DEFAULT_AGE_PENALTY,
    warn_fraction: float = DEFAULT_WARN_FRACTION,
) -> tuple[dict[str, np.ndarray], SyncStats]:
    """Approximate-time sets over whole recorded streams (stamps in file order).

    Streams are merged into one arrival order by stamp, stably, keeping each stream's own order:
    the merge key is each stream's running maximum, so a message stamped earlier than its
    predecessor arrives right after it and is counted ``out_of_order`` (as it would be live).
    Returns, per stream, the index of its message in each matched set (``n_sets`` int64 each),
    and the statistics.
    """
    names = list(streams)
    arrays = [np.asarray(streams[n], dtype=np.int64).reshape(-1) for n in names]
    sync = ApproximateTimeSync(
        names, queue_size, slop_ns, age_penalty=age_penalty, warn_fraction=warn_fraction
    )
    keys = [np.maximum.accumulate(a) if a.size else a for a in arrays]
    stamps = np.concatenate(arrays) if arrays else np.zeros(0, dtype=np.int64)
    stream_id = np.concatenate([np.full(a.size, k) for k, a in enumerate(arrays)])
    local = np.concatenate([np.arange(a.size) for a in arrays])
    order = np.argsort(np.concatenate(keys), kind="stable")

    sets: list[MatchedSet] = []
    for k, t, j in zip(
        stream_id[order].tolist(), stamps[order].tolist(), local[order].tolist(), strict=True
    ):
        sets.extend(sync.push(names[k], t, j))
    sets.extend(sync.flush())
    index = {n: np.array([s.payload(n) for s in sets], dtype=np.int64) for n in names}
    return index, sync.stats


def fix_camera_info_stamps(
    info_stamps_ns: np.ndarray, image_stamps_ns: np.ndarray, tolerance_ns: int
) -> tuple[np.ndarray, int]:
    """Re-stamp camera infos that are further than ``tolerance_ns`` from every image stamp.

    Each such info takes the stamp of its nearest image (ties to the earlier image); the others
    keep theirs. Returns (fixed stamps, int64, and how many were changed). This is right for
    infos stamped a little off their image (publish time instead of capture time, a driver
    clock drifting by less than half a frame period); for an offset of whole frames, nearest is
    the wrong image and stamps should be paired by sequence instead.
    """
    info = np.asarray(info_stamps_ns, dtype=np.int64).reshape(-1)
    images = np.sort(np.asarray(image_stamps_ns, dtype=np.int64).reshape(-1))
    if info.size == 0 or images.size == 0:
        return info.copy(), 0
    j = np.searchsorted(images, info)
    before = images[np.clip(j - 1, 0, images.size - 1)]
    after = images[np.clip(j, 0, images.size - 1)]
    nearest = np.where(np.abs(after - info) < np.abs(info - before), after, before)
    off = np.abs(nearest - info) > tolerance_ns
    return np.where(off, nearest, info), int(np.count_nonzero(off))


def interpolate_wheels(
    wheel_stamps_ns: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    image_stamps_ns: np.ndarray,
    max_gap_ns: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cumulative encoder counts linearly interpolated to image stamps.

    For an image at ``t`` bracketed by readings ``t0 <= t <= t1``::

        c(t) = c0 + (c1 - c0) * (t - t0) / (t1 - t0)

    ``ok`` is False (and the counts NaN) where the image lies outside the wheel span or the
    bracket is wider than ``max_gap_ns``; an image exactly on a reading is always ok. Wheel
    stamps must be strictly increasing (a recording's ``wheels.txt`` is).
    Returns (left, right) as float64 counts and ``ok``, one per image.
    """
    t = np.asarray(wheel_stamps_ns, dtype=np.int64).reshape(-1)
    cl = np.asarray(left, dtype=np.float64).reshape(-1)
    cr = np.asarray(right, dtype=np.float64).reshape(-1)
    img = np.asarray(image_stamps_ns, dtype=np.int64).reshape(-1)
    if not (t.size == cl.size == cr.size):
        raise SyncError(f"wheel arrays differ in length: {t.size}, {cl.size}, {cr.size}")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0)) + 1
        raise SyncError(f"wheel stamps must be strictly increasing (reading {k} is not)")
    nan = np.full(img.size, np.nan)
    if t.size == 0:
        return nan, nan.copy(), np.zeros(img.size, dtype=bool)
    if t.size == 1:
        ok = img == t[0]
        return np.where(ok, cl[0], np.nan), np.where(ok, cr[0], np.nan), ok

    hi = np.clip(np.searchsorted(t, img, side="right"), 1, t.size - 1)
    lo = hi - 1
    gap = t[hi] - t[lo]  # > 0
    frac = (img - t[lo]) / gap
    inside = (img >= t[0]) & (img <= t[-1])
    exact = (img == t[lo]) | (img == t[hi])
    ok = inside & ((gap <= max_gap_ns) | exact)
    left_f = cl[lo] + (cl[hi] - cl[lo]) * frac
    right_f = cr[lo] + (cr[hi] - cr[lo]) * frac
    return np.where(ok, left_f, np.nan), np.where(ok, right_f, np.nan), ok
