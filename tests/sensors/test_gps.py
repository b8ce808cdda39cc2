"""GPS fixes: NavSatFix read from real bag files, gps.txt round trips, the simulated receiver."""

from __future__ import annotations

import numpy as np
import pytest

from sensors.geo import GeoAnchor
from sensors.gps import GpsStream, SimGpsConfig, read_gps_txt, simulate_gps, write_gps_txt
from sensors.source import open_source
from sensors.types import NS_PER_S, SensorError
from tests.bagtools import KINDS, MS, T0, bag_path, write_bag

ANCHOR = GeoAnchor(44.98, -93.27, 256.0, 0.0)


def _navsatfix(bag, stamp_ns: int, lat: float, status: int, cov_type: int, var: float):
    t = bag.types
    return t["sensor_msgs/msg/NavSatFix"](
        header=bag.header(stamp_ns, "gps"),
        status=t["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
        latitude=lat,
        longitude=-93.27,
        altitude=256.0,
        position_covariance=np.diag([var, var, 4 * var]).ravel(),
        position_covariance_type=cov_type,
    )


@pytest.mark.parametrize("kind", KINDS)
def test_navsatfix_with_a_fix_and_covariance_is_read_the_rest_counted(tmp_path, kind) -> None:
    path = bag_path(tmp_path, kind)
    with write_bag(path, kind) as bag:
        for k, (status, cov_type) in enumerate([(0, 2), (-1, 2), (2, 0), (1, 1)]):
            t = T0 + k * 1000 * MS
            msg = _navsatfix(bag, t, 44.98 + 1e-5 * k, status, cov_type, 9.0)
            bag.write("/gps/fix", "sensor_msgs/msg/NavSatFix", t + MS, msg)
    src = open_source(path)
    try:
        gps = src.gps()
        assert gps is not None and len(gps) == 2
        assert gps.stamps_ns.tolist() == [T0, T0 + 3000 * MS]
        assert gps.latitude == pytest.approx([44.98, 44.98003])
        assert gps.sigma_m == pytest.approx([3.0, 3.0])
        assert src.skipped.get("gps_no_fix") == 1 and src.skipped.get("gps_no_covariance") == 1
    finally:
        src.close()


def test_a_navsatfix_with_a_nan_or_impossible_fix_is_a_counted_skip(tmp_path) -> None:
    # One bad fix in a bag must not make the whole GPS stream an error (#16: count, skip, go on).
    path = bag_path(tmp_path, KINDS[0])
    with write_bag(path, KINDS[0]) as bag:
        for k, lat in enumerate([44.98, float("nan"), 123.0, 44.98002]):
            t = T0 + k * 1000 * MS
            bag.write(
                "/gps/fix", "sensor_msgs/msg/NavSatFix", t + MS, _navsatfix(bag, t, lat, 0, 2, 9.0)
            )
    src = open_source(path)
    try:
        gps = src.gps()
        assert gps is not None and gps.stamps_ns.tolist() == [T0, T0 + 3000 * MS]
        assert src.skipped.get("gps_bad_fix") == 2
    finally:
        src.close()


def test_gps_txt_round_trips_and_refuses_fixes_off_the_globe(tmp_path) -> None:
    stream = GpsStream(
        np.array([T0, T0 + NS_PER_S]),
        np.array([44.98, 44.9801]),
        np.array([-93.27, -93.2701]),
        np.array([256.0, 257.5]),
        np.array([3.0, 2.5]),
    )
    write_gps_txt(tmp_path / "gps.txt", stream)
    back = read_gps_txt(tmp_path / "gps.txt")
    assert back.stamps_ns.tolist() == stream.stamps_ns.tolist()
    assert back.latitude == pytest.approx(stream.latitude, abs=1e-9)
    assert back.sigma_m == pytest.approx(stream.sigma_m)
    (tmp_path / "bad.txt").write_text("1700000000.0 95.0 -93.27 256.0 3.0\n")
    with pytest.raises(SensorError, match="bad.txt: fix 1 is not a fix"):
        read_gps_txt(tmp_path / "bad.txt")


def test_simulated_gps_has_its_sigma_rate_and_dropouts() -> None:
    stamps = np.arange(0, 3600 * NS_PER_S, NS_PER_S // 10, dtype=np.int64)  # an hour at 10 Hz
    s = stamps / NS_PER_S
    truth = np.column_stack([0.5 * s, 20.0 * np.sin(s / 60.0)])
    cfg = SimGpsConfig(sigma_m=3.0, rate_hz=1.0, p_drop=0.05, mean_outage_s=5.0)
    gps = simulate_gps(stamps, truth, ANCHOR, cfg, seed=1)
    xy = gps.in_map(ANCHOR)
    err = xy - np.column_stack([np.interp(gps.stamps_ns, stamps, truth[:, i]) for i in (0, 1)])
    assert np.std(err, axis=0) == pytest.approx([3.0, 3.0], rel=0.1)
    gaps = np.diff(gps.stamps_ns) / NS_PER_S
    assert np.all(gaps >= 1.0 - 1e-9)
    # Outages: 5 % per fix, ~5 s each -> about a fifth of the hour missing, in bursts.
    assert 0.6 * 3600 < len(gps) < 0.95 * 3600
    assert np.count_nonzero(gaps > 1.5) > 50
    again = simulate_gps(stamps, truth, ANCHOR, cfg, seed=1)
    assert again.latitude.tolist() == gps.latitude.tolist()


def test_the_receiver_fed_pose_by_pose_gives_fixes_at_its_rate_and_they_stream_to_gps_txt(
    tmp_path,
) -> None:
    from sensors.gps import GpsWriter, SimGpsReceiver

    cfg = SimGpsConfig(sigma_m=2.0, rate_hz=1.0, p_drop=0.05, mean_outage_s=5.0)
    rx = SimGpsReceiver(ANCHOR, cfg, seed=3)
    writer = GpsWriter(tmp_path / "gps.txt")
    stamps = np.arange(0, 1200 * NS_PER_S, NS_PER_S // 30, dtype=np.int64)  # 30 Hz camera
    for t in stamps:  # a robot standing at (10, -5)
        if (fix := rx.update(int(t), 10.0, -5.0)) is not None:
            writer.add(fix)
    writer.close()
    back = read_gps_txt(tmp_path / "gps.txt")
    assert back.sigma_m.tolist() == [2.0] * len(back)
    assert np.all(np.diff(back.stamps_ns) >= 0.99 * NS_PER_S)  # at the first frame due
    assert 0.6 * 1200 < len(back) < 0.97 * 1200  # 1 Hz less the outages
    err = back.in_map(ANCHOR) - [10.0, -5.0]
    assert np.std(err, axis=0) == pytest.approx([2.0, 2.0], rel=0.15)
    assert np.abs(np.mean(err, axis=0)).max() < 0.3
