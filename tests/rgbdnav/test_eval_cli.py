"""`rgbdnav eval` as a user meets it: check values, run directory, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from rgbdnav.runners.eval import evaluate_files, read_trajectory
from sensors.types import SensorError

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
TUM = DATA / "tum"
needs_tum = pytest.mark.skipif(not TUM.is_dir(), reason="shared TUM data not available")
runner = CliRunner()


def _write_tum(path: Path, stamps_s: np.ndarray, xyz: np.ndarray) -> Path:
    lines = ["# t tx ty tz qx qy qz qw"]
    lines += [
        f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1"
        for t, (x, y, z) in zip(stamps_s, xyz, strict=True)
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def line_pair(tmp_path: Path) -> tuple[Path, Path]:
    t = np.arange(50) * 0.1
    xyz = np.column_stack([0.1 * np.arange(50), np.sin(t), np.zeros(50)])
    return _write_tum(tmp_path / "est.txt", t, xyz), _write_tum(tmp_path / "gt.txt", t, xyz)


@needs_tum
def test_eval_fr1_xyz_writes_the_tum_check_value_to_summary(tmp_path: Path) -> None:
    out = tmp_path / "run"
    est, gt = TUM / "freiburg1_xyz-rgbdslam.txt", TUM / "freiburg1_xyz-groundtruth.txt"
    result = runner.invoke(app, ["eval", str(est), "--reference", str(gt), "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ate_rmse_m"] == pytest.approx(0.01347, abs=1e-5)
    assert summary["matched"] == 786 and summary["align"] == "se3"
    assert summary["rpe_trans_m"]["count"] > 0
    assert "ATE [m]     rmse 0.013473" in result.output
    for name in ("config.yaml", "ate.png"):
        assert (out / name).stat().st_size > 0, name


@needs_tum
def test_fr2_desk_orb_reproduces_the_tum_check_value_despite_a_repeated_stamp() -> None:
    reference = read_trajectory(TUM / "fr2_desk_groundtruth.txt")
    assert reference.repeated_stamps == 1  # the official file repeats 1311868229.576
    result = evaluate_files(
        read_trajectory(TUM / "fr2_desk_ORB.txt"), reference, "se3", 0.02, 1.0, "m"
    )
    assert result.ate.rmse == pytest.approx(0.00814, abs=1e-5)


@needs_tum
def test_monocular_keyframes_need_sim3() -> None:
    est = read_trajectory(TUM / "freiburg1_xyz-ORB_kf_mono.txt")
    ref = read_trajectory(TUM / "freiburg1_xyz-groundtruth.txt")
    se3 = evaluate_files(est, ref, "se3", 0.02, 1.0, "m")
    sim3 = evaluate_files(est, ref, "sim3", 0.02, 1.0, "m")
    assert sim3.ate.rmse < se3.ate.rmse
    assert sim3.ate.rmse < 0.02 and sim3.alignment.scale != pytest.approx(1.0, abs=0.01)


def test_eval_of_a_trajectory_against_itself_is_zero(
    line_pair: tuple[Path, Path], tmp_path: Path
) -> None:
    est, gt = line_pair
    out = tmp_path / "run"
    options = ["--delta", "3", "--delta-unit", "frames", "--align", "sim3"]
    result = runner.invoke(
        app, ["eval", str(est), "--reference", str(gt), "--out", str(out), *options]
    )
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ate_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert summary["rpe_trans_m"]["count"] == 47
    assert summary["alignment"]["scale"] == pytest.approx(1.0, abs=1e-9)


def test_eval_accepts_a_run_directory(line_pair: tuple[Path, Path], tmp_path: Path) -> None:
    est, gt = line_pair
    run = tmp_path / "odometry_run"
    run.mkdir()
    (run / "trajectory.tum").write_text(est.read_text())
    result = runner.invoke(
        app, ["eval", str(run), "--reference", str(gt), "--out", str(tmp_path / "out")]
    )
    assert result.exit_code == 0, result.output


def _one_line_error(args: list[str]) -> str:
    result = runner.invoke(app, args)
    assert result.exit_code == 1, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    return lines[0]


def test_missing_file_is_one_line_and_exit_1(line_pair: tuple[Path, Path], tmp_path: Path) -> None:
    _, gt = line_pair
    missing = tmp_path / "nope.txt"
    line = _one_line_error(
        ["eval", str(missing), "--reference", str(gt), "--out", str(tmp_path / "out")]
    )
    assert f"{missing}: cannot read" in line


def test_malformed_line_names_file_and_line(line_pair: tuple[Path, Path], tmp_path: Path) -> None:
    est, gt = line_pair
    text = est.read_text().splitlines()
    text[3] = text[3].replace(" 0 0 0 1", " 0 0 zero 1")
    est.write_text("\n".join(text) + "\n")
    line = _one_line_error(
        ["eval", str(est), "--reference", str(gt), "--out", str(tmp_path / "out")]
    )
    assert f"{est}:4:" in line and "not valid pose" in line


def test_no_overlap_in_time_names_both_files(line_pair: tuple[Path, Path], tmp_path: Path) -> None:
    est, _ = line_pair
    late = _write_tum(tmp_path / "late.txt", 100 + np.arange(5) * 0.1, np.zeros((5, 3)))
    line = _one_line_error(
        ["eval", str(est), "--reference", str(late), "--out", str(tmp_path / "out")]
    )
    assert str(est) in line and str(late) in line and "no estimate stamp" in line


def test_unknown_alignment_is_one_line(line_pair: tuple[Path, Path], tmp_path: Path) -> None:
    est, gt = line_pair
    line = _one_line_error(
        ["eval", str(est), "--reference", str(gt), "--align", "se4", "--out", str(tmp_path / "out")]
    )
    assert "--align 'se4'" in line


def test_a_zero_length_quaternion_is_refused_naming_its_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.txt"
    bad.write_text("# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 0\n")
    with pytest.raises(SensorError, match=r"bad.txt:3: quaternion has zero length"):
        read_trajectory(bad)


# Relations metric (Kümmerle et al. 2009) ----------------------------------------------------

CARMEN = DATA / "carmen"
needs_carmen = pytest.mark.skipif(not CARMEN.is_dir(), reason="../shared/data/carmen is absent")


@pytest.fixture
def straight_line(tmp_path: Path) -> tuple[Path, Path]:
    """A robot driving along x at 1 m/s, and four 1 s relations: two true ones and two whose
    reference is 0.1 m further along x and turned by 2 deg."""
    t = np.arange(11) * 1.0
    traj = _write_tum(tmp_path / "line.tum", t, np.column_stack([t, np.zeros(11), np.zeros(11)]))
    rel = tmp_path / "rel.txt"
    rel.write_text(
        "# t1 t2 x y z roll pitch yaw\n"
        "1 2 1.0 0 0 0 0 0\n"
        "3 4 1.0 0 0 0 0 0\n"
        "5 6 1.1 0 0 0 0 0.03490658503988659\n"
        "8 7 -1.1 0 0 0 0 -0.03490658503988659\n"
    )
    return traj, rel


def test_relations_of_a_straight_line_give_the_known_errors(
    straight_line: tuple[Path, Path], tmp_path: Path
) -> None:
    traj, rel = straight_line
    out = tmp_path / "run"
    result = runner.invoke(app, ["eval", str(traj), "--relations", str(rel), "--out", str(out)])
    assert result.exit_code == 0, result.output
    metric = json.loads((out / "summary.json").read_text())["relations_error"]
    assert (metric["count"], metric["skipped"]) == (4, 0)
    # Errors 0, 0, 0.1, 0.1 m and 0, 0, 2, 2 deg.
    assert (metric["trans_mean_m"], metric["trans_std_m"]) == pytest.approx((0.05, 0.05), abs=1e-9)
    assert metric["trans_sq_mean_m2"] == pytest.approx(0.005, abs=1e-9)
    assert (metric["rot_mean_deg"], metric["rot_std_deg"]) == pytest.approx((1.0, 1.0), abs=1e-9)
    assert metric["rot_sq_mean_deg2"] == pytest.approx(2.0, abs=1e-9)
    assert "relations   4 of 4 scored, 0 skipped" in result.output
    assert "REL [m]     0.050000 ± 0.050000" in result.output
    assert "REL [deg]   1.0000 ± 1.0000" in result.output
    assert (out / "config.yaml").stat().st_size > 0


def test_relations_without_out_print_and_write_nothing(
    straight_line: tuple[Path, Path], tmp_path: Path
) -> None:
    traj, rel = straight_line
    before = sorted(tmp_path.iterdir())
    result = runner.invoke(app, ["eval", str(traj), "--relations", str(rel)])
    assert result.exit_code == 0, result.output
    assert "REL [m]" in result.output and "wrote" not in result.output
    assert sorted(tmp_path.iterdir()) == before


def test_relations_far_from_every_pose_are_skipped_and_counted(
    straight_line: tuple[Path, Path],
) -> None:
    traj, rel = straight_line
    rel.write_text(rel.read_text() + "1 2.5 1.5 0 0 0 0 0\n")  # 2.5 s is 0.5 s from any pose
    result = runner.invoke(app, ["eval", str(traj), "--relations", str(rel)])
    assert result.exit_code == 0, result.output
    assert "relations   4 of 5 scored, 1 skipped" in result.output


def test_missing_relations_file_is_one_line(
    straight_line: tuple[Path, Path], tmp_path: Path
) -> None:
    traj, _ = straight_line
    missing = tmp_path / "nope.relations"
    line = _one_line_error(["eval", str(traj), "--relations", str(missing)])
    assert f"{missing}: cannot read" in line


@pytest.mark.parametrize(
    ("bad", "match"),
    [("5 6 1.1 0 0 0 0", "expected 8 fields"), ("5 6 1.1 nan 0 0 0 0", "not valid relation")],
)
def test_malformed_or_nan_relation_is_one_line_naming_file_and_line(
    straight_line: tuple[Path, Path], bad: str, match: str
) -> None:
    traj, rel = straight_line
    lines = rel.read_text().splitlines()
    lines[3] = bad
    rel.write_text("\n".join(lines) + "\n")
    line = _one_line_error(["eval", str(traj), "--relations", str(rel)])
    assert f"{rel}:4:" in line and match in line


def test_relations_out_of_time_name_both_files(straight_line: tuple[Path, Path]) -> None:
    traj, rel = straight_line
    rel.write_text("100 101 1 0 0 0 0 0\n")
    line = _one_line_error(["eval", str(traj), "--relations", str(rel)])
    assert str(traj) in line and str(rel) in line and "no relation has estimate poses" in line


def test_reference_and_relations_together_or_neither_are_refused(
    straight_line: tuple[Path, Path], tmp_path: Path
) -> None:
    traj, rel = straight_line
    out = ["--out", str(tmp_path / "out")]
    both = _one_line_error(
        ["eval", str(traj), "--reference", str(traj), "--relations", str(rel), *out]
    )
    neither = _one_line_error(["eval", str(traj), *out])
    assert both == neither == "error: give exactly one of --reference GT and --relations FILE"


def test_reference_without_out_prints_and_writes_nothing(
    line_pair: tuple[Path, Path], tmp_path: Path
) -> None:
    """Like evo_ape: the result on the terminal, files only when asked (--out)."""
    est, gt = line_pair
    before = set(tmp_path.iterdir())
    result = runner.invoke(app, ["eval", str(est), "--reference", str(gt)])
    assert result.exit_code == 0, result.output
    assert "ATE [m]     rmse 0.000000" in result.output and "wrote" not in result.output
    assert set(tmp_path.iterdir()) == before


def test_options_of_the_other_mode_are_refused_not_ignored(
    line_pair: tuple[Path, Path], tmp_path: Path
) -> None:
    est, _ = line_pair
    rel = tmp_path / "r.relations"
    rel.write_text("0 1 0.1 0 0 0 0 0\n")
    line = _one_line_error(["eval", str(est), "--relations", str(rel), "--align", "se2"])
    assert line == (
        "error: --align: only with --reference, not --relations; it would be ignored here"
    )


@needs_carmen
def test_raw_odometry_of_mit_csail_scores_the_published_relations_figures(tmp_path: Path) -> None:
    from sensors.carmen import CarmenSource
    from sensors.tum import write_tum_trajectory

    odom = CarmenSource(CARMEN / "mit-csail.clf").odometry()
    assert odom is not None
    traj = tmp_path / "mit-csail-odometry.tum"
    write_tum_trajectory(traj, odom.stamps_ns, odom.x, odom.y, odom.yaw)
    out, relations = tmp_path / "run", CARMEN / "mit-csail.relations"
    result = runner.invoke(
        app, ["eval", str(traj), "--relations", str(relations), "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    metric = json.loads((out / "summary.json").read_text())["relations_error"]
    assert (metric["count"], metric["skipped"]) == (1172, 0)
    # Kümmerle et al. 2009 (../shared/data/README.md): 1.6815 ± 5.2922 m, 5.072 ± 8.241 deg.
    assert (metric["trans_mean_m"], metric["trans_std_m"]) == pytest.approx(
        (1.6815, 5.2922), abs=1e-3
    )
    assert (metric["rot_mean_deg"], metric["rot_std_deg"]) == pytest.approx(
        (5.072, 8.241), abs=1e-2
    )


@needs_tum
@pytest.mark.parametrize(("est_fmt", "ref_fmt"), [("kitti", "euroc"), ("euroc", "kitti")])
def test_kitti_and_euroc_files_score_as_their_tum_originals(tmp_path, est_fmt, ref_fmt) -> None:
    """fr1/xyz written as KITTI (+ times file) and EuRoC CSV: detected, same ATE check value."""
    from sensors.tum import load_tum_trajectory, write_trajectory

    est = tmp_path / f"est.{est_fmt}"
    ref = tmp_path / f"gt.{ref_fmt}"
    write_trajectory(est, *load_tum_trajectory(TUM / "freiburg1_xyz-rgbdslam.txt"), est_fmt)
    write_trajectory(ref, *load_tum_trajectory(TUM / "freiburg1_xyz-groundtruth.txt"), ref_fmt)
    result = runner.invoke(app, ["eval", str(est), "-r", str(ref), "-q"])
    assert result.exit_code == 0, result.output
    assert "matched     786 of 788" in result.output
    assert "ATE [m]     rmse 0.013473" in result.output
