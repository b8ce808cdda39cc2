"""The long fault-drill script's schedule and verdict (``bench/bench_live.py --drill-minutes``):
the live run itself is exercised by the short drill in test_live_cli.py; here a run summary is
judged, so a drill that was not counted, a reconnect that never came or a lost map fails it."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import bench_live  # noqa: E402  (bench/ is no package)

CYCLES = 2
GOOD = {
    "counts": {
        "drill_unplug_board": 2,
        "drill_replug_board": 2,
        "drill_stall_camera": 2,
        "board_command_errors": 40,
        "board_recovered": 2,
        "camera_stalls": 2,
        "route_laps": 1,
        "waypoints_reached": 9,
    },
    "sim_robot": {"stalled_frames": 180},
    "slam_vs_groundtruth": {"ate_rmse_aligned_m": 0.05, "ate_rmse_m": 0.2},
    "errors": [],
}


def test_the_schedule_fits_whole_cycles_into_the_run() -> None:
    args, cycles = bench_live.drill_schedule(150)
    assert cycles == 2
    drills = args[1::2]
    assert args[::2] == ["--drill"] * 6
    stall = bench_live.DRILL_STALL_S
    assert drills == [
        "unplug_board@10",
        "replug_board@25",
        f"stall_camera@40:{stall}",
        "unplug_board@70",
        "replug_board@85",
        f"stall_camera@100:{stall}",
    ]


def test_a_run_that_recovered_from_every_drill_passes_every_check() -> None:
    checks = bench_live.drill_checks(GOOD, CYCLES, bundle_ok=True)
    assert all(ok for _, _, ok in checks), [c for c in checks if not c[2]]
    assert "**FAIL**" not in bench_live.report_drills(
        {**GOOD, "latency_ms": {"p50": 20, "p99": 50}}, 2, checks, "0.1 / 0.2"
    )


@pytest.mark.parametrize(
    ("path", "value", "failing"),
    [
        (("counts", "drill_stall_camera"), 1, "drills run"),
        (("counts", "board_recovered"), 1, "reconnects"),
        (("counts", "camera_stalls"), 1, "camera stalls"),
        (("sim_robot", "stalled_frames"), 0, "held back"),
        (("counts", "waypoints_reached"), 0, "route driving"),
        (("slam_vs_groundtruth", "ate_rmse_aligned_m"), 0.4, "SLAM ATE"),
        (("errors",), ["board: gone"], "errors"),
    ],
)
def test_each_kind_of_failure_fails_its_check(path: tuple, value: object, failing: str) -> None:
    s = copy.deepcopy(GOOD)
    node = s
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    failed = [name for name, _, ok in bench_live.drill_checks(s, CYCLES, True) if not ok]
    assert len(failed) == 1 and failing in failed[0], failed


def test_a_bundle_that_does_not_load_fails_the_run() -> None:
    failed = [n for n, _, ok in bench_live.drill_checks(GOOD, CYCLES, bundle_ok=False) if not ok]
    assert failed == ["map bundle after the run loads"]
    report = bench_live.report_drills(
        {**GOOD, "latency_ms": None}, 2, bench_live.drill_checks(GOOD, CYCLES, False), "?"
    )
    assert "| map bundle after the run loads | no | **FAIL** |" in report
