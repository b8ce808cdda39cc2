"""Approximate-time sets (ROS message_filters ApproximateTime), camera-info and wheel stamps."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from sensors.config import SyncConfig
from sensors.sync import (
    ApproximateTimeSync,
    fix_camera_info_stamps,
    interpolate_wheels,
    synchronise,
)
from sensors.types import SyncError

MS = 1_000_000  # [ns]
SLOP = 20 * MS  # [ns]


def pairs(a_ms: list[int], b_ms: list[int], slop_ns: int = SLOP, queue_size: int = 10):
    """Matched (a, b) stamps in ms, and the stats, from ``synchronise`` on two streams."""
    idx, stats = synchronise(
        {"a": np.array(a_ms) * MS, "b": np.array(b_ms) * MS}, slop_ns, queue_size
    )
    return [(a_ms[i], b_ms[j]) for i, j in zip(idx["a"], idx["b"], strict=True)], stats


# --- ApproximateTime sets ---------------------------------------------------------------------


def test_perfectly_aligned_streams_match_one_to_one_with_zero_spread() -> None:
    t = [0, 33, 66, 100, 133]
    matched, stats = pairs(t, t)
    assert matched == list(zip(t, t, strict=True))
    assert stats.sets == 5 and stats.max_spread_ns == 0
    assert stats.dropped == 0 and stats.matched_fraction("a") == 1.0


def test_aligned_sets_are_emitted_as_soon_as_the_last_stream_arrives() -> None:
    sync = ApproximateTimeSync(["rgb", "depth"], queue_size=5, slop_ns=SLOP)
    assert sync.push("rgb", 0, "rgb0") == []
    out = sync.push("depth", 0, "depth0")
    assert len(out) == 1
    assert out[0].messages == {"rgb": (0, "rgb0"), "depth": (0, "depth0")}
    assert out[0].spread_ns == 0


def test_jittered_second_stream_pairs_each_message_with_its_neighbour() -> None:
    matched, stats = pairs([0, 100, 200, 300], [3, 98, 205, 301])
    assert matched == [(0, 3), (100, 98), (200, 205), (300, 301)]
    assert stats.max_spread_ns == 5 * MS
    assert stats.mean_spread_ns == pytest.approx(11 * MS / 4, abs=1)


def test_a_slow_stream_takes_the_closest_fast_message_and_skips_the_rest() -> None:
    fast = list(range(0, 101, 10))  # 100 Hz
    matched, stats = pairs(fast, [2, 48, 91], slop_ns=50 * MS)
    assert matched == [(0, 2), (50, 48), (90, 91)]
    assert stats.streams["a"].unmatched == 8 and stats.streams["b"].unmatched == 0


def test_a_dropped_message_leaves_its_partner_unmatched() -> None:
    matched, stats = pairs([0, 33, 66, 100, 133], [0, 33, 100, 133])
    assert matched == [(0, 0), (33, 33), (100, 100), (133, 133)]
    assert stats.streams["a"].unmatched == 1 and stats.streams["a"].matched == 4
    assert stats.streams["b"].dropped == 0


def test_slop_rejects_sets_spread_wider_than_slop() -> None:
    matched, stats = pairs([0, 100], [50, 150], slop_ns=20 * MS)
    assert matched == [] and stats.sets == 0
    assert stats.streams["a"].unmatched == 2 and stats.streams["b"].unmatched == 2
    # The same stamps with a generous slop: the best sets are 50 ms wide.
    matched, _ = pairs([0, 100], [50, 150], slop_ns=60 * MS)
    assert matched == [(0, 50), (100, 150)]


def test_spread_equal_to_slop_is_accepted() -> None:
    matched, _ = pairs([0], [20], slop_ns=20 * MS)
    assert matched == [(0, 20)]


def test_queue_overflow_evicts_the_oldest_messages_and_counts_them() -> None:
    sync = ApproximateTimeSync(["a", "b"], queue_size=3, slop_ns=50 * MS)
    for t in (0, 10, 20, 30, 40):
        assert sync.push("a", t * MS) == []
    assert sync.stats.streams["a"].overflow == 2  # a0 and a10 evicted
    assert sync.stats.streams["a"].pending == 3
    (only,) = sync.push("b", 35 * MS)  # a20 is beaten by a30; a40 is further from b35
    assert sync.flush() == []
    assert (only.stamp_ns("a"), only.stamp_ns("b")) == (30 * MS, 35 * MS)
    a = sync.stats.streams["a"]
    assert (a.matched, a.unmatched, a.overflow, a.pending) == (1, 4, 2, 0)


def test_duplicate_out_of_order_and_stale_messages_are_counted_not_queued() -> None:
    sync = ApproximateTimeSync(["a", "b"], queue_size=10, slop_ns=SLOP)
    sync.push("a", 0)
    assert len(sync.push("b", 0)) == 1  # set (0, 0) emitted
    sync.push("a", 33 * MS)
    sync.push("a", 33 * MS)  # duplicate: same stamp as the previous on "a"
    sync.push("a", 20 * MS)  # out of order: older than 33, newer than the emitted 0
    sync.push("b", 50 * MS)
    sync.push("b", -5 * MS)  # stale: older than b's message in the emitted set
    s = sync.stats.streams
    assert (s["a"].duplicate, s["a"].out_of_order, s["a"].stale) == (1, 1, 0)
    assert (s["b"].duplicate, s["b"].out_of_order, s["b"].stale) == (0, 0, 1)
    assert s["a"].pending + s["b"].pending == 2  # a33 and b50, the others never entered


def test_synchronise_counts_an_out_of_order_stamp_in_file_order() -> None:
    idx, stats = synchronise(
        {"a": np.array([0, 33, 20, 66]) * MS, "b": np.array([0, 33, 66]) * MS}, SLOP, 10
    )
    np.testing.assert_array_equal(idx["a"], [0, 1, 3])
    np.testing.assert_array_equal(idx["b"], [0, 1, 2])
    assert stats.streams["a"].out_of_order == 1 and stats.dropped == 1


def test_every_message_is_matched_dropped_or_pending() -> None:
    rng = np.random.default_rng(3)
    sync = ApproximateTimeSync(["rgb", "depth", "ir"], queue_size=4, slop_ns=10 * MS)
    t = np.arange(300) * 33 * MS
    for k in range(300):
        for name in ("rgb", "depth", "ir"):
            if rng.random() > 0.1:
                sync.push(name, int(t[k] + rng.normal(0, 4 * MS)))
        if k == 150:
            s = sync.stats.streams["rgb"]
            assert s.received == s.matched + s.dropped + s.pending
    sync.flush()
    for s in sync.stats.streams.values():
        assert s.pending == 0 and s.received == s.matched + s.dropped


def test_sets_never_cross_never_reuse_and_respect_slop() -> None:
    rng = np.random.default_rng(7)
    base = np.arange(500) * 33 * MS
    streams = {}
    for name in ("rgb", "depth"):
        kept = base[rng.random(base.size) > 0.05]  # 5 % dropped
        streams[name] = np.sort(kept + rng.integers(-4 * MS, 4 * MS, kept.size))
    idx, stats = synchronise(streams, 10 * MS, 10)
    for name in streams:
        assert np.all(np.diff(idx[name]) > 0)  # used once, in order (sets do not cross)
    spread = np.abs(streams["rgb"][idx["rgb"]] - streams["depth"][idx["depth"]])
    assert spread.max() <= 10 * MS
    assert stats.sets == idx["rgb"].size > 400


def test_output_depends_on_stamps_not_on_arrival_interleaving() -> None:
    rng = np.random.default_rng(11)
    a = np.cumsum(rng.integers(20, 40, 60)) * MS
    b = np.cumsum(rng.integers(25, 45, 50)) * MS

    def run(order: list[tuple[str, int]]) -> list[tuple[int, int]]:
        sync = ApproximateTimeSync(["a", "b"], queue_size=200, slop_ns=30 * MS)
        sets = [s for name, t in order for s in sync.push(name, t)] + sync.flush()
        return [(s.stamp_ns("a"), s.stamp_ns("b")) for s in sets]

    by_time = sorted([("a", int(t)) for t in a] + [("b", int(t)) for t in b], key=lambda m: m[1])
    a_first = [("a", int(t)) for t in a] + [("b", int(t)) for t in b]
    b_first = [("b", int(t)) for t in b] + [("a", int(t)) for t in a]
    assert run(by_time) == run(a_first) == run(b_first)
    assert len(run(by_time)) > 30


def test_a_known_minimum_period_lets_a_set_out_before_the_next_message() -> None:
    # (a0, b50) can only be proved best once "a" cannot send anything nearer to b50.
    plain = ApproximateTimeSync(["a", "b"], queue_size=5, slop_ns=60 * MS)
    bounded = ApproximateTimeSync(["a", "b"], 5, 60 * MS, min_period_ns={"a": 100 * MS})
    for sync in (plain, bounded):
        sync.push("a", 0)
    assert plain.push("b", 50 * MS) == []
    (early,) = bounded.push("b", 50 * MS)  # the next "a" is at 100 ms or later: 50 ms away
    (late,) = plain.push("a", 100 * MS)
    assert early.messages == late.messages


def test_a_single_stream_emits_every_message() -> None:
    idx, stats = synchronise({"rgb": np.array([0, 10, 20]) * MS}, SLOP, 2)
    np.testing.assert_array_equal(idx["rgb"], [0, 1, 2])
    assert stats.sets == 3


def test_warns_when_the_dropped_fraction_exceeds_warn_fraction(caplog) -> None:
    streams = {"a": np.arange(0, 400, 10) * MS, "b": np.arange(0, 400, 40) * MS}
    with caplog.at_level(logging.WARNING, logger="sensors.sync"):
        _, stats = synchronise(streams, SLOP, 10, warn_fraction=0.5)
    assert stats.dropped_fraction > 0.5
    assert "sync dropped" in caplog.text and "warn_fraction 50.0 %" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sensors.sync"):
        synchronise(streams, SLOP, 10, warn_fraction=0.9)
    assert caplog.text == ""


def test_report_lists_every_stream_and_reason() -> None:
    _, stats = pairs([0, 33, 66], [0, 66])
    text = stats.report()
    for word in ("stream", "out_of_order", "duplicate", "stale", "unmatched", "a ", "b "):
        assert word in text
    assert "2 sets" in text


def test_from_config_converts_seconds_to_nanoseconds() -> None:
    sync = ApproximateTimeSync.from_config(["rgb", "depth"], SyncConfig(queue_size=7, slop=0.015))
    assert (sync.queue_size, sync.slop_ns, sync.warn_fraction) == (7, 15 * MS, 0.05)


def test_bad_arguments_raise_sync_error() -> None:
    with pytest.raises(SyncError, match="unique"):
        ApproximateTimeSync(["a", "a"], 5, SLOP)
    with pytest.raises(SyncError, match="queue_size"):
        ApproximateTimeSync(["a", "b"], 0, SLOP)
    with pytest.raises(SyncError, match="unknown stream 'c'"):
        ApproximateTimeSync(["a", "b"], 5, SLOP).push("c", 0)


# --- camera info ------------------------------------------------------------------------------


def test_camera_info_off_by_more_than_tolerance_takes_the_nearest_image_stamp() -> None:
    images = np.array([0, 33, 66, 100]) * MS
    info = np.array([2, 45, 66, 250]) * MS  # 2 ms ok; 12 ms and 150 ms off
    fixed, n_fixed = fix_camera_info_stamps(info, images, tolerance_ns=5 * MS)
    np.testing.assert_array_equal(fixed, np.array([2, 33, 66, 100]) * MS)
    assert n_fixed == 2


def test_camera_info_within_tolerance_is_untouched() -> None:
    images = np.array([0, 33, 66]) * MS
    info = images + 3 * MS
    fixed, n_fixed = fix_camera_info_stamps(info, images, tolerance_ns=5 * MS)
    np.testing.assert_array_equal(fixed, info)
    assert n_fixed == 0
    assert fix_camera_info_stamps(info, np.zeros(0, dtype=np.int64), 0)[1] == 0


# --- wheel odometry at image stamps -----------------------------------------------------------


def test_wheel_counts_interpolate_exactly_when_counts_are_linear_in_time() -> None:
    wheel_t = np.arange(0, 1001, 20) * MS  # 50 Hz
    left, right = 3 * np.arange(wheel_t.size), -5 * np.arange(wheel_t.size) + 7
    images = np.array([0, 7, 33, 500, 999, 1000]) * MS
    lf, rf, ok = interpolate_wheels(wheel_t, left, right, images, max_gap_ns=30 * MS)
    assert ok.all()
    np.testing.assert_allclose(lf, 3 * images / (20 * MS), atol=1e-9)
    np.testing.assert_allclose(rf, -5 * images / (20 * MS) + 7, atol=1e-9)


def test_wheel_interpolation_is_not_ok_across_gaps_or_outside_the_span() -> None:
    wheel_t = np.array([0, 20, 40, 340, 360]) * MS  # 300 ms hole between 40 and 340
    counts = np.arange(5)
    images = np.array([-1, 10, 100, 340, 361]) * MS
    lf, rf, ok = interpolate_wheels(wheel_t, counts, counts, images, max_gap_ns=200 * MS)
    np.testing.assert_array_equal(ok, [False, True, False, True, False])
    assert np.isnan(lf[~ok]).all() and np.isnan(rf[~ok]).all()
    assert lf[1] == pytest.approx(0.5, abs=1e-12) and lf[3] == pytest.approx(3.0, abs=1e-12)


def test_wheel_interpolation_rejects_non_increasing_wheel_stamps() -> None:
    with pytest.raises(SyncError, match="strictly increasing"):
        interpolate_wheels(np.array([0, 10, 10]), np.zeros(3), np.zeros(3), np.array([5]), 100)
