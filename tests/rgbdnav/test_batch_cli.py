"""`rgbdnav batch` on a 2-worker Dask LocalCluster: real CARMEN logs, a simulated recording and
a broken log in, one row per source out (accuracy against each source's own ground truth, time,
memory), failures as rows, and a rerun that skips what is done."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.commands.batch import accuracy_text, map_accuracy, source_name

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
MIT = DATA / "carmen" / "mit-csail.clf"
needs_mit = pytest.mark.skipif(not MIT.is_file(), reason="../shared/data/carmen is absent")
needs_dask = pytest.mark.skipif(
    importlib.util.find_spec("distributed") is None, reason="dask[distributed] is not installed"
)
runner = CliRunner()


def _robots(tmp_path: Path) -> list[Path]:
    """Two 'robots': consecutive stretches of the MIT CSAIL log, each with the benchmark's
    relations beside it (the ones inside its time span get scored), and a broken log."""
    lines = [ln for ln in MIT.read_text().splitlines() if ln.startswith("FLASER")]
    logs = []
    for name, part in (("mit-a", lines[:100]), ("mit-b", lines[100:200])):
        log = tmp_path / f"{name}.clf"
        log.write_text("\n".join(part) + "\n")
        shutil.copy(MIT.with_suffix(".relations"), tmp_path / f"{name}.relations")
        logs.append(log)
    broken = tmp_path / "broken.clf"
    broken.write_text("FLASER 3 1.0 zwei\nthis is not a log\n")
    return [*logs, broken]


def _report(out: Path) -> dict:
    return json.loads((out / "report.json").read_text())


@needs_mit
@needs_dask
def test_batch_map_on_two_workers_reports_each_source_and_resumes(
    tmp_path: Path, house_recording: Path
) -> None:
    # The simulated robot (a recording of scenes/house.yaml, with the simulator's truth) beside
    # the real ones, on the same cluster.
    sources = [*_robots(tmp_path), house_recording]
    out = tmp_path / "batch"
    args = ["batch", "map", *map(str, sources), "--out", str(out), "--workers", "2"]
    result = runner.invoke(app, args)
    assert result.exit_code == 1, result.output  # one source failed: the batch says so
    rows = {r["name"]: r for r in _report(out)["rows"]}
    assert list(rows) == ["mit-a", "mit-b", "broken", "house"]
    for name in ("mit-a", "mit-b"):
        row = rows[name]
        assert row["status"] == "done" and row["error"] is None
        # The same run as `rgbdnav map`: its bundle, trajectory and summary in DIR/<name>/.
        assert (out / name / "map" / "map.yaml").is_file()
        assert json.loads((out / name / "summary.json").read_text())["command"] == "map"
        acc = row["accuracy"]
        assert acc["relations_scored"] > 20  # relations inside this stretch only
        assert acc["rel_trans_mean_m"] < 0.05 and acc["rel_rot_mean_deg"] < 1.0, acc
        assert row["wall_s"] > 0 and row["peak_rss_mb"] > 50
        assert row["peak_rss_scope"] == "task"
    sim = rows["house"]
    assert sim["status"] == "done" and (out / "house" / "map" / "map.yaml").is_file()
    # Scored against the recording's ground truth (no relations there), as `rgbdnav map` scores it.
    summary = json.loads((out / "house" / "summary.json").read_text())
    assert sim["accuracy"]["ate_rmse_m"] == summary["slam_vs_groundtruth"]["ate_rmse_m"]
    assert 0 < sim["accuracy"]["ate_rmse_m"] < 0.05 and "relations_scored" not in sim["accuracy"]
    # Its 1.5 s face a wall at the edge of the scan's 4 m; the map starts at the first scan with
    # a return, so the row carries the summary's grid IoU (0/0, no score, is map_accuracy's test).
    assert sim["accuracy"]["grid_iou"] == summary["grid_vs_floor_plan"]["iou"]
    bad = rows["broken"]
    assert bad["status"] == "failed" and "broken.clf" in bad["error"] and "\n" not in bad["error"]
    md = (out / "report.md").read_text()
    assert "| mit-a | done |" in md and "| broken | failed |" in md
    assert f"| house | done | {accuracy_text(sim['accuracy'])} |" in md
    assert "no laser scans" in md

    # Rerun after losing mit-b's row, and batch eval, on one cluster already running
    # (--scheduler; a LocalCluster starting costs seconds): mit-a is skipped (untouched), mit-b
    # runs again; the eval of the two runs against the full benchmark's relations scores as the
    # map tasks scored them.
    from distributed import LocalCluster

    first_summary = (out / "mit-a" / "summary.json").stat().st_mtime_ns
    (out / "mit-b" / "batch.json").unlink()
    ev = tmp_path / "eval"
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0") as cluster:
        on_cluster = ["--scheduler", cluster.scheduler_address]
        again = runner.invoke(app, [*args[:-2], *on_cluster])  # args without --workers 2
        assert again.exit_code == 1, again.output
        report = _report(out)
        rows = {r["name"]: r for r in report["rows"]}
        assert report["skipped_as_done"] == 2 and rows["mit-a"].get("resumed") is True
        assert rows["house"].get("resumed") is True
        assert rows["mit-b"]["status"] == "done" and not rows["mit-b"].get("resumed")
        assert (out / "mit-a" / "summary.json").stat().st_mtime_ns == first_summary
        assert "2 skipped as done before" in again.output

        result = runner.invoke(
            app,
            [
                "batch",
                "eval",
                str(out / "mit-a"),
                str(out / "mit-b"),
                "--relations",
                str(MIT.with_suffix(".relations")),
                "--out",
                str(ev),
                *on_cluster,
            ],
        )
    assert result.exit_code == 0, result.output
    report = _report(ev)
    assert report["scheduler"].startswith("tcp://") and report["done"] == 2
    ev_rows = {r["name"]: r for r in report["rows"]}
    for name in ("mit-a", "mit-b"):
        assert ev_rows[name]["accuracy"]["rel_trans_mean_m"] == pytest.approx(
            rows[name]["accuracy"]["rel_trans_mean_m"]
        )


def test_batch_refuses_bad_batches_in_one_line_before_any_work(tmp_path: Path) -> None:
    a, b = tmp_path / "x" / "run.clf", tmp_path / "y" / "run.clf"
    for p in (a, b):
        p.parent.mkdir()
        p.write_text("")
    cases = [
        (["batch", "map", str(a), str(b)], "two sources would write"),
        (["batch", "localize", str(a)], "needs --map"),
        (["batch", "eval", str(a)], "exactly one of --reference"),
        (["batch", "fly", str(a)], "use one of map, localize, eval"),
        (["batch", "map", str(a), "--workers", "0"], "--workers must be >= 1"),
        (["batch", "map", str(a), "--scheduler", "not an address"], "--scheduler not an"),
    ]
    for args, message in cases:
        result = runner.invoke(app, [*args, "--out", str(tmp_path / "out")])
        assert result.exit_code == 1, result.output
        line = result.output.strip()
        assert line.startswith("error:") and "\n" not in line and message in line, line
    assert not (tmp_path / "out" / "run").exists()


def test_source_names_drop_log_suffixes_and_name_runs_after_their_folder() -> None:
    assert source_name(Path("d/aces-corrected.log.gz")) == "aces-corrected"
    assert source_name(Path("d/mit-csail.clf")) == "mit-csail"
    assert source_name(Path("scenes/house.yaml")) == "house"
    assert source_name(Path("runs/robot1/trajectory.tum")) == "robot1"
    assert source_name(Path("runs/robot1")) == "robot1"


def test_map_accuracy_scores_the_grid_only_when_there_was_something_to_compare() -> None:
    ate = {"ate_rmse_m": 0.02, "ate_rmse_aligned_m": 0.01}
    scored = {"iou": 0.5, "true_positive": 5, "false_positive": 5, "false_negative": 0}
    empty = {"iou": 0.0, "true_positive": 0, "false_positive": 0, "false_negative": 0}
    summary = {"slam_vs_groundtruth": ate, "grid_vs_floor_plan": scored}
    assert map_accuracy(summary) == {**ate, "grid_iou": 0.5}
    assert map_accuracy({**summary, "grid_vs_floor_plan": empty}) == ate
    missed = {**empty, "false_negative": 3}  # walls seen, none mapped: a real 0
    assert map_accuracy({"grid_vs_floor_plan": missed}) == {"grid_iou": 0.0}
