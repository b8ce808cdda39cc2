from __future__ import annotations

import gzip
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from sensors.carmen import (
    CarmenSource,
    carmen_ranges,
    first_time_increase,
    flaser_geometry,
    read_carmen_log,
)
from sensors.source import Source, open_source
from sensors.types import SensorError

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
MIT = DATA / "carmen" / "mit-csail.clf"
RADISH = DATA / "radish"
needs_mit = pytest.mark.skipif(not MIT.is_file(), reason="../shared/data/carmen is absent")
needs_radish = pytest.mark.skipif(not RADISH.is_dir(), reason="../shared/data/radish is absent")

DEG = math.pi / 180.0  # [rad/deg]


def flaser(ranges: list[float | str], t: float, pose=(1.0, 2.0, 0.5), odom=(0.1, 0.2, 0.3)) -> str:
    fields = [str(len(ranges)), *map(str, ranges), *map(str, pose), *map(str, odom)]
    return f"FLASER {' '.join(fields)} {t} host {t + 0.01}"


def write_log(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def test_flaser_scan_has_carmen_geometry_stamp_and_pose(tmp_path):
    log = read_carmen_log(write_log(tmp_path / "a.clf", [flaser([1.0] * 181, 12.5)]))

    (scan,) = log.scans
    assert scan.stamp_ns == 12_500_000_000
    assert scan.angle_min == pytest.approx(-math.pi / 2, abs=1e-12)
    assert scan.angle_increment == pytest.approx(1.0 * DEG, abs=1e-12)
    assert scan.ranges.dtype == np.float32 and scan.ranges.shape == (181,)
    assert scan.range_max == pytest.approx(81.9)
    assert scan.angles()[-1] == pytest.approx(math.pi / 2, abs=1e-9)
    np.testing.assert_allclose(log.laser_pose.x, [1.0], atol=1e-12)
    np.testing.assert_allclose(log.robot_pose.yaw, [0.3], atol=1e-12)
    assert log.laser_pose.frame == "laser" and log.robot_pose.frame == "base_link"


@pytest.mark.parametrize(
    ("n", "increment_deg"), [(180, 1.0), (181, 1.0), (360, 0.5), (361, 0.5), (401, 0.25)]
)
def test_flaser_without_params_guesses_like_carmen(n, increment_deg):
    angle_min, increment = flaser_geometry(n)
    assert angle_min == pytest.approx(-math.pi / 2, abs=1e-12)
    assert increment == pytest.approx(increment_deg * DEG, abs=1e-12)


def test_param_fov_resolution_and_max_range_override_the_guess(tmp_path):
    lines = [
        "PARAM laser_front_laser_fov 100 host 0",
        "PARAM laser_front_laser_resolution 0.25 host 0",
        "PARAM robot_front_laser_max 50.0 host 0",
        flaser([10.0, 49.9, 50.0, 60.0], 1.0),
    ]
    log = read_carmen_log(write_log(tmp_path / "a.clf", lines))
    (scan,) = log.scans
    assert log.params["robot_front_laser_max"] == "50.0"
    assert scan.angle_min == pytest.approx(-50.0 * DEG, abs=1e-12)
    assert scan.angle_increment == pytest.approx(0.25 * DEG, abs=1e-12)
    assert scan.range_max == 50.0
    np.testing.assert_allclose(scan.ranges, [10.0, 49.9, np.inf, np.inf], rtol=1e-6)


def test_ranges_at_or_past_max_are_no_return_and_negative_or_nan_are_invalid():
    raw = np.array([0.0, 1.25, 81.9, 81.91, np.inf, -1.0, np.nan, -np.inf])
    out = carmen_ranges(raw, 81.9)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[:2], [0.0, 1.25])
    assert np.isposinf(out[2:5]).all() and np.isnan(out[5:]).all()


def test_robotlaser1_uses_its_own_geometry_and_robot_pose(tmp_path):
    line = (
        "ROBOTLASER1 0 -1.5 3.0 0.75 30.0 0.01 0 5 1.0 2.0 30.0 3.0 4.0 2 9 9 "
        "1.1 2.1 0.31 1.0 2.0 0.3 0.2 0.1 0 0 0 13.0 host 13.1"
    )
    log = read_carmen_log(write_log(tmp_path / "a.log", [line]))
    (scan,) = log.scans
    assert (scan.angle_min, scan.angle_increment, scan.range_max) == (-1.5, 0.75, 30.0)
    np.testing.assert_allclose(scan.ranges, [1.0, 2.0, np.inf, 3.0, 4.0])
    np.testing.assert_allclose(log.laser_pose.x, [1.1], atol=1e-12)
    np.testing.assert_allclose(log.robot_pose.yaw, [0.3], atol=1e-12)
    assert scan.stamp_ns == 13_000_000_000


def test_odom_param_comments_and_unknown_messages(tmp_path):
    lines = [
        "# message formats defined: PARAM ODOM FLASER",
        "PARAM robot_use_laser on nohost 0",
        "ODOM 0.5 0.25 0.1 0.3 0.05 0 10.0 host 10.01",
        "NEFF 60",
        "ODOM 0.6 0.25 0.1 0.3 0.05 0 10.1 host 10.11",
        flaser([1.0, 2.0, 3.0], 10.05),
        "",
    ]
    src = CarmenSource(write_log(tmp_path / "a.log", lines))
    assert isinstance(src, Source)
    assert src.log.params == {"robot_use_laser": "on"}
    assert src.log.ignored == {"NEFF": 1} and src.skipped == {}
    odom = src.odom_messages()
    assert odom is not None and odom.frame == "base_link"
    np.testing.assert_array_equal(odom.stamps_ns, [10_000_000_000, 10_100_000_000])
    np.testing.assert_allclose(odom.x, [0.5, 0.6])
    np.testing.assert_allclose(src.log.odom_twist, [[0.3, 0.05], [0.3, 0.05]])
    assert set(src.stream_stamps()) == {"scans", "odometry", "odom"}
    assert list(src.frames()) == [] and src.intrinsics() is None


MALFORMED = [
    flaser([1.0, 2.0], 1.0),
    "FLASER abc 1.0 2.0 0 0 0 0 0 0 2.0 host 2.0",  # line 2: bad count
    flaser([1.0, "x2"], 3.0),  # line 3: non-numeric range
    flaser([1.0, 2.0], 4.0).replace(" 2.0 ", " ", 1),  # line 4: a field short
    flaser([1.0, 2.0], 5.0, pose=("nan", 0, 0)),  # line 5: pose not finite
    flaser([1.0, 2.0], 6.0),
]


def test_malformed_lines_are_skipped_and_counted_by_reason(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="sensors.carmen"):
        log = read_carmen_log(write_log(tmp_path / "bad.clf", MALFORMED))
    assert len(log.scans) == 2
    np.testing.assert_array_equal(log.scan_lines, [1, 6])
    assert log.skipped == {"bad_count": 1, "non_numeric": 1, "field_count": 1, "non_finite": 1}
    assert "bad.clf:2:" in caplog.text


def test_malformed_line_in_strict_mode_is_an_error_naming_the_first_bad_line(tmp_path):
    with pytest.raises(SensorError, match=r"bad\.clf:2: beam count 'abc' is not an integer"):
        read_carmen_log(write_log(tmp_path / "bad.clf", MALFORMED), strict=True)
    with pytest.raises(SensorError, match=r"bad\.clf:2: FLASER has a non-numeric field"):
        read_carmen_log(write_log(tmp_path / "bad.clf", MALFORMED[:1] + MALFORMED[2:]), strict=True)


def test_scan_going_back_in_time_is_dropped_and_counted(tmp_path):
    lines = [flaser([1.0], t) for t in (1.0, 2.0, 1.5, 2.0, 3.0)]
    log = read_carmen_log(write_log(tmp_path / "a.clf", lines))
    np.testing.assert_array_equal([s.stamp_ns for s in log.scans], [1e9, 2e9, 3e9])
    assert log.skipped == {"non_monotonic": 1, "duplicate_stamp": 1}
    with pytest.raises(SensorError, match=r"a\.clf:3: scan time 1\.500000000 does not advance"):
        read_carmen_log(tmp_path / "a.clf", strict=True)


def test_first_time_increase_keeps_stamps_later_than_all_before():
    keep, dup = first_time_increase(np.array([5, 3, 7, 7, 6, 8]))
    np.testing.assert_array_equal(keep, [True, False, True, False, False, True])
    np.testing.assert_array_equal(dup, [False, False, False, True, False, False])


def test_log_without_time_falls_back_to_synthesised_stamps(tmp_path):
    log = read_carmen_log(write_log(tmp_path / "a.log", [flaser([1.0], 0)] * 3))
    assert log.stamp_source == "synthesised"
    np.testing.assert_array_equal([s.stamp_ns for s in log.scans], [0, 200_000_000, 400_000_000])


def test_log_whose_stamps_drop_most_scans_falls_back_to_synthesised_stamps(tmp_path, caplog):
    # Radish's csail log prints its stamps with 6 digits (1.13486e+09): 10 s apart, 400 scans.
    lines = [flaser([1.0], 1.13486e9 + 10.0 * (k // 4)) for k in range(12)]
    with caplog.at_level(logging.WARNING, logger="sensors.carmen"):
        log = read_carmen_log(write_log(tmp_path / "a.log", lines))
    assert log.stamp_source == "synthesised" and log.skipped == {}
    assert len(log.scans) == 12 and "ipc timestamps of 9 of 12 scans do not advance" in caplog.text


def test_gzipped_log_reads_like_the_plain_one(tmp_path):
    lines = [flaser([1.0, 2.0, 3.0], 1.0 + k) for k in range(4)]
    plain = write_log(tmp_path / "a.log", lines)
    zipped = tmp_path / "a.log.gz"
    zipped.write_bytes(gzip.compress(plain.read_bytes()))
    src = open_source(zipped)
    assert isinstance(src, CarmenSource)
    assert [s.stamp_ns for s in src.scans()] == [s.stamp_ns for s in read_carmen_log(plain).scans]


def test_try_open_ignores_files_that_are_not_carmen_logs(tmp_path):
    assert CarmenSource.try_open(write_log(tmp_path / "notes.log", ["started server"])) is None
    assert CarmenSource.try_open(write_log(tmp_path / "a.txt", [flaser([1.0], 1.0)])) is None
    assert CarmenSource.try_open(tmp_path) is None


@needs_mit
def test_mit_csail_reads_1988_scans_of_361_beams():
    src = open_source(MIT)
    assert isinstance(src, CarmenSource)
    scans = list(src.scans())
    assert len(scans) == 1988 and {len(s.ranges) for s in scans} == {361}
    assert src.skipped == {} and src.log.stamp_source == "ipc_timestamp"
    first = scans[0]
    assert first.angle_min == pytest.approx(-math.pi / 2, abs=1e-12)
    assert first.angle_increment == pytest.approx(0.5 * DEG, abs=1e-12)
    assert first.range_max == pytest.approx(81.9)
    ranges = np.stack([s.ranges for s in scans])
    assert np.isposinf(ranges).any() and np.nanmax(ranges[np.isfinite(ranges)]) < 81.9
    odom = src.odometry()
    assert odom is not None and len(odom.stamps_ns) == 1988
    assert np.all(np.diff(odom.stamps_ns) > 0)
    assert (odom.stamps_ns[-1] - odom.stamps_ns[0]) / 1e9 == pytest.approx(424.0, abs=1.0)
    steps = np.hypot(np.diff(odom.x), np.diff(odom.y))
    assert steps.sum() == pytest.approx(373.6, abs=0.5)  # README: 373.6 m of odometry
    assert "1988 laser scans of 361 beams" in src.describe()


@needs_radish
@pytest.mark.parametrize(
    ("name", "scans", "beams"),
    [("aces", 440, 180), ("orebro", 237, 181), ("seattle", 241, 361)],
)
def test_radish_logs_read(name, scans, beams):
    src = open_source(RADISH / f"{name}-corrected.log.gz")
    assert isinstance(src, CarmenSource)
    assert len(src.log.scans) == scans
    assert {len(s.ranges) for s in src.log.scans} == {beams}
    assert src.log.ignored == {"NEFF": scans}
    assert set(src.skipped) <= {"odom_non_monotonic"}  # their ODOM stamps are partly 0 or junk


def test_a_stamp_beyond_int64_nanoseconds_is_a_counted_skip(tmp_path):
    lines = [flaser([1.0] * 181, t) for t in (12.5, 1e30, 13.0)]
    log = read_carmen_log(write_log(tmp_path / "a.clf", lines))
    assert log.skipped == {"bad_timestamp": 1} and len(log.scans) == 2


def test_a_scan_whose_pose_is_a_kilometre_off_between_agreeing_neighbours_is_a_counted_skip(
    tmp_path,
):
    lines = [
        flaser([1.0] * 181, 10 + 0.2 * k, pose=(0.1 * k, 0.0, 0.0), odom=(0.1 * k, 0, 0))
        for k in range(6)
    ]
    lines[3] = flaser([1.0] * 181, 10.6, pose=(1000.0, 0.0, 0.0), odom=(0.3, 0.0, 0.0))
    log = read_carmen_log(write_log(tmp_path / "a.clf", lines))
    assert log.skipped == {"pose_jump": 1} and len(log.scans) == 5
    assert np.abs(log.laser_pose.x).max() < 1.0
    # A robot that really moved on (every later pose agrees) keeps all its scans.
    moved = [
        flaser([1.0] * 181, 10 + 0.2 * k, pose=(0.1 * k + (50 if k > 2 else 0), 0, 0))
        for k in range(6)
    ]
    assert read_carmen_log(write_log(tmp_path / "b.clf", moved)).skipped == {}
