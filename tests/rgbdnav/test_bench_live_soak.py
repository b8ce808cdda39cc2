"""The live soak's memory accounting (``bench/bench_live_soak.py``): growth after warm-up, the
process tree it samples and the per-process series; the hour-long run itself lives in bench/."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import bench_live_soak as soak  # noqa: E402  (bench/ is no package)


def test_growth_ignores_the_warm_up_and_measures_from_the_first_minute_after_it() -> None:
    t = np.arange(0.0, 3600.0, 10.0)
    mb = np.where(t < 300, 100.0 + t / 3, 200.0 + (t - 300) / 3300 * 10)  # warm-up, then +10 MB
    g = soak.memory_growth(t, mb, warmup_s=300)
    assert g["base_mb"] == pytest.approx(200.1, abs=0.2)  # mean of 300..360 s
    assert g["peak_mb"] == pytest.approx(209.97, abs=0.05)
    assert g["growth_peak"] == pytest.approx(0.049, abs=0.002)
    assert 0.04 < g["growth_end"] < g["growth_peak"]
    assert g["slope_mb_per_10min"] == pytest.approx(10 / 3300 * 600, abs=0.01)
    flat = soak.memory_growth(t, np.full_like(t, 50.0), warmup_s=300)
    assert flat["growth_peak"] == 0.0 and flat["slope_mb_per_10min"] == pytest.approx(0.0, abs=1e-9)
    assert soak.memory_growth(t[:3], mb[:3], warmup_s=300)["base_mb"] is None  # too short


def test_the_process_tree_holds_the_root_and_its_descendants(monkeypatch) -> None:
    code = "import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)']); time.sleep(30)"  # noqa: E501
    parent = subprocess.Popen([sys.executable, "-c", code])
    try:
        for _ in range(100):  # the grandchild needs a moment to start
            tree = soak.process_tree_rss(parent.pid)
            if len(tree) >= 2:
                break
            time.sleep(0.05)
        assert parent.pid in tree and len(tree) == 2
        assert all(mb > 1.0 for _, mb in tree.values())
        monkeypatch.setitem(sys.modules, "psutil", None)  # the /proc fallback sees the same
        assert set(soak.process_tree_rss(parent.pid)) == set(tree)
    finally:
        for pid in soak.process_tree_rss(parent.pid):
            os.kill(pid, 9)
        parent.wait()
    assert soak.process_tree_rss(parent.pid) == {}


def test_series_sums_each_role_and_the_whole_run() -> None:
    rec = {
        "pid": 10,
        "commands": {
            "10": "python -m rgbdnav.cli live",
            "11": "python -B -c from multiprocessing.resource_tracker import main;main(7)",
            "12": "python -B -c from multiprocessing.spawn import spawn_main; spawn_main()",
        },
        "samples": [
            {"t": 0.0, "rss_mb": {"10": 100.0, "11": 10.0, "12": 50.0}},
            {"t": 10.0, "rss_mb": {"10": 110.0, "11": 10.0}},  # the robot gone at the end
        ],
    }
    s = soak.series(rec)
    assert set(s) == {
        "host (rgbdnav live)",
        "multiprocessing resource tracker",
        "simulated robot",
        "all processes",
    }
    assert s["all processes"][1].tolist() == [160.0]  # not once a process has ended
    assert s["host (rgbdnav live)"][0].tolist() == [0.0, 10.0]
    assert s["simulated robot"][1].tolist() == [50.0]


def test_frame_blocks_count_each_parts_frames_and_drops_from_the_cumulative_timeline() -> None:
    timeline = [
        [5.0, 150, 0, 30.0],
        [10.0, 300, 0, 40.0],
        [65.0, 1800, 2, 90.0],  # halving left a gap: the counts still add up
        [70.0, 1950, 2, None],
    ]
    b = soak.frame_blocks(timeline, 60.0)
    assert [(x["processed"], x["dropped"]) for x in b] == [(300, 0), (1650, 2)]
    assert b[0]["p99_median_ms"] == 35.0 and b[0]["p99_worst_ms"] == 40.0
    assert b[1]["p99_median_ms"] == 90.0
    assert soak.blocks_table(None, 60.0) == []
    assert len(soak.blocks_table(timeline, 60.0)) == 2 + 2 + 2 + 1
