from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.recording import Recording, RecordingWriter
from sensors.recording_source import RecordingSource
from sensors.stream_stats import describe_source, format_stats_table, stream_stats
from sensors.types import CameraIntrinsics, RgbdFrame

MS = 1_000_000  # [ns]


def test_regular_stream_has_its_rate_and_no_gaps():
    stats = stream_stats("rgb", np.arange(0, 1000 * MS + 1, 100 * MS))
    assert stats.count == 11
    assert stats.first_ns == 0 and stats.last_ns == 1000 * MS
    assert stats.duration_s == pytest.approx(1.0, abs=1e-12)
    assert stats.rate_hz == pytest.approx(10.0, abs=1e-9)
    assert stats.mean_rate_hz == pytest.approx(10.0, abs=1e-9)
    assert stats.gaps == 0
    assert stats.max_gap_s == pytest.approx(0.1, abs=1e-12)
    assert (stats.non_monotonic, stats.duplicates) == (0, 0)


def test_dropped_samples_count_as_gaps_but_do_not_move_the_median_rate():
    # 10 Hz with one 0.3 s hole and one 0.2 s hole
    stamps = np.array([0, 100, 200, 500, 600, 800, 900, 1000]) * MS
    stats = stream_stats("wheels", stamps)
    assert stats.rate_hz == pytest.approx(10.0, abs=1e-9)
    assert stats.mean_rate_hz == pytest.approx(7.0, abs=1e-9)
    assert stats.gaps == 2
    assert stats.max_gap_s == pytest.approx(0.3, abs=1e-12)


def test_duplicates_and_backward_steps_are_counted_separately():
    stamps = np.array([0, 100, 100, 200, 150, 300]) * MS
    stats = stream_stats("imu", stamps)
    assert stats.duplicates == 1
    assert stats.non_monotonic == 1
    assert stats.first_ns == 0 and stats.last_ns == 300 * MS


def test_empty_and_single_sample_streams_have_no_rate():
    empty = stream_stats("x", np.zeros(0, dtype=np.int64))
    assert empty.count == 0 and empty.first_ns is None and math.isnan(empty.rate_hz)
    one = stream_stats("x", np.array([5 * MS]))
    assert one.count == 1 and one.first_ns == one.last_ns == 5 * MS
    assert one.duration_s == 0.0 and one.max_gap_s == 0.0
    assert math.isnan(one.rate_hz) and math.isnan(one.mean_rate_hz)


def test_table_has_a_row_per_stream_and_dashes_for_missing_rates():
    table = format_stats_table(
        [stream_stats("rgb", np.arange(0, 10) * 33 * MS), stream_stats("imu", np.array([1]))]
    )
    lines = table.splitlines()
    assert len(lines) == 3
    assert lines[0].split()[:3] == ["stream", "count", "duration_s"]
    assert lines[1].split()[:2] == ["rgb", "10"]
    assert lines[2].split()[3] == "-"
    assert len({len(line) for line in lines[:2]}) == 1


def test_describe_source_lists_the_streams_a_recording_holds(tmp_path):
    intr = CameraIntrinsics(4, 3, 5.0, 5.0, 2.0, 1.5)
    with RecordingWriter(tmp_path / "rec", intr, {}) as writer:
        for k in range(3):
            writer.add_frame(
                RgbdFrame(
                    k * 33 * MS,
                    np.zeros((3, 4, 3), np.uint8),
                    np.ones((3, 4), np.float32),
                    intr,
                )
            )
        writer.add_wheels(np.array([0, 10 * MS]), np.array([0, 1]), np.array([0, 2]))
    names = [s.name for s in describe_source(RecordingSource(Recording.open(tmp_path / "rec")))]
    assert names == ["rgb", "depth", "wheels"]
