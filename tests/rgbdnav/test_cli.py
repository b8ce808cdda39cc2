"""The CLI as a user meets it: help, one-line errors, run directories."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app

REPO = Path(__file__).resolve().parents[2]
HOUSE = REPO / "scenes" / "house.yaml"
runner = CliRunner()


@pytest.fixture(scope="module")
def recording(house_recording: Path) -> Path:
    return house_recording  # tests/rgbdnav/conftest.py: rendered once per session


def test_help_lists_the_commands() -> None:
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for verb in ("info", "simulate", "odometry"):
        assert verb in result.output


def test_simulate_writes_a_recording_and_a_run_record(recording: Path) -> None:
    for name in (
        "rgb.txt",
        "depth.txt",
        "wheels.txt",
        "groundtruth.txt",
        "scene.yaml",
        "config.yaml",
        "summary.json",
    ):
        assert (recording / name).is_file(), name
    summary = json.loads((recording / "summary.json").read_text())
    assert summary["frames"] == 45 and summary["frames_per_s"] > 0


def test_info_describes_a_recording(recording: Path) -> None:
    result = runner.invoke(app, ["info", str(recording)])
    assert result.exit_code == 0
    assert "45 rgb/depth pairs" in result.output
    assert "wheels" in result.output and "groundtruth" in result.output


def test_info_describes_a_world() -> None:
    result = runner.invoke(app, ["info", str(HOUSE)])
    assert result.exit_code == 0
    assert "18 waypoints, 44.2 m" in result.output


def test_odometry_writes_trajectory_summary_and_pictures(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = runner.invoke(app, ["odometry", str(recording), "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    for name in (
        "config.yaml",
        "summary.json",
        "trajectory.tum",
        "wheel.tum",
        "vo.tum",
        "fused.tum",
        "groundtruth.tum",
        "trajectory.png",
        "frames.png",
    ):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    # Visual odometry tracked the simulated frames and the EKF fused all three sensors.
    assert summary["vo"]["pairs_tracked"] >= 40
    assert summary["ekf"]["inputs"] == ["imu0", "odom0", "vo0"]
    assert summary["vo_vs_groundtruth"]["final_position_error_m"] < 0.05
    assert summary["fused_vs_groundtruth"]["final_position_error_m"] < 0.1
    assert summary["sync"]["sets"] == 45
    drift = summary["wheel_odometry_vs_groundtruth"]
    assert drift["matched"] > 50
    assert drift["final_position_error_m"] < 0.1  # 1.5 s of driving
    # One trajectory pose per camera frame, stamped like the frames.
    lines = [ln for ln in (out / "trajectory.tum").read_text().splitlines() if ln[:1] != "#"]
    rgb = [
        ln.split()[0] for ln in (recording / "rgb.txt").read_text().splitlines() if ln[:1] != "#"
    ]
    assert [ln.split()[0] for ln in lines] == rgb


def test_set_override_reaches_the_resolved_config(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = runner.invoke(
        app,
        ["odometry", str(recording), "--out", str(out), "-q", "--set", "robot.track_width=0.31"],
    )
    assert result.exit_code == 0, result.output
    assert "track_width: 0.31" in (out / "config.yaml").read_text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["info", "no/such/place"], "no/such/place: no such file or folder"),
        (
            ["simulate", str(HOUSE), "--out", "x", "--set", "sim.max_linear_speed=3"],
            "sim.max_linear_speed: 3.0 m/s is out of range",
        ),
        (
            ["simulate", str(HOUSE), "--out", "x", "--set", "sim.warp_speed=1"],
            "sim.warp_speed: unknown key",
        ),
        (["simulate", str(HOUSE), "--out", "x", "--frames", "2", "--duration", "1"], "not both"),
        (["odometry", str(REPO / "scenes"), "--out", "x"], "not a source rgbdnav can read"),
        (
            ["simulate", str(HOUSE), "--out", "/proc/rgbdnav-test", "--frames", "1"],
            "/proc/rgbdnav-test",
        ),
        (
            ["simulate", str(HOUSE), "--out", "x", "--trajectory", "no-such.txt", "--frames", "1"],
            "no-such.txt",
        ),
        (["simulate", str(REPO / "README.md"), "--out", "x"], "README.md"),
        (["simulate", str(HOUSE), "--out", "x", "--duration", "-1"], "duration must be > 0 s"),
        (["simulate", str(HOUSE), "--out", "x", "--frames", "0"], "--frames must be >= 1"),
        (["simulate", "no-such-world.yaml", "--out", "x"], "no-such-world.yaml: no such world"),
    ],
)
def test_user_mistakes_give_one_clear_line_and_exit_1(
    args: list[str], message: str, tmp_path: Path
) -> None:
    args = [a if a != "x" else str(tmp_path / "x") for a in args]
    result = runner.invoke(app, args)
    assert result.exit_code == 1
    assert result.exception is None or isinstance(result.exception, SystemExit)
    import re

    assert re.search(message, result.output)


def test_console_script_prints_no_traceback_for_a_bad_config(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("ekf:\n  frequency: fast\n")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "rgbdnav.cli",
            "simulate",
            str(HOUSE),
            "--out",
            str(tmp_path / "o"),
            "--config",
            str(bad),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr
    assert f"{bad}: ekf.frequency: expected a number" in proc.stderr


def test_board_check_talks_to_the_emulator_and_test_drives() -> None:
    result = runner.invoke(app, ["board", "--emulator", "--test-drive"])
    assert result.exit_code == 0, result.output
    assert "firmware" in result.output and "battery" in result.output
    # 0.1 m/s for 1 s on 13.3 mm positions: about 8 positions per wheel.
    import re

    m = re.search(r"left (\d+), right (\d+) positions = ([0-9.]+) m", result.output)
    assert m is not None
    assert 0.05 < float(m.group(3)) < 0.15


@pytest.mark.parametrize(
    ("kind", "name"),
    [("thunderborg", "PiBorg ThunderBorg"), ("arduino-bridge", "ROSArduinoBridge")],
)
def test_board_check_test_drives_every_emulator_and_names_it(kind: str, name: str) -> None:
    args = ["board", kind, "--emulator", "--test-drive", "--set", "robot.ticks_per_revolution=1000"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert name in result.output and f"({kind})" in result.output
    import re

    m = re.search(r"positions = ([0-9.]+) m", result.output)
    assert m is not None and 0.05 < float(m.group(1)) < 0.15, result.output
    pose = re.search(r"wheel odometry +x ([0-9.]+) m, .*\(1-sigma ([0-9.]+) m", result.output)
    assert pose is not None and float(pose.group(1)) == pytest.approx(float(m.group(1)), abs=0.01)
    assert float(pose.group(2)) > 0, result.output


def test_board_check_rejects_a_bad_device_spec() -> None:
    result = runner.invoke(app, ["board", "thunderborg:/dev/ttyUSB0"])
    assert result.exit_code != 0
    assert "expected thunderborg:/dev/i2c-N" in result.output


def test_board_check_names_a_missing_port() -> None:
    result = runner.invoke(app, ["board", "/dev/rgbdnav-no-such-port"])
    assert result.exit_code == 1
    assert "cannot open Eddie board at /dev/rgbdnav-no-such-port" in result.output


def test_odometry_without_vo_skips_it(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = runner.invoke(app, ["odometry", str(recording), "--out", str(out), "-q", "--no-vo"])
    assert result.exit_code == 0, result.output
    assert not (out / "vo.tum").exists() and (out / "fused.tum").is_file()
    assert json.loads((out / "summary.json").read_text())["ekf"]["inputs"] == ["imu0", "odom0"]


def test_a_glitched_encoder_reading_is_counted_in_the_summary_not_driven(
    recording: Path, tmp_path: Path
) -> None:
    glitched = tmp_path / "glitched"
    shutil.copytree(recording, glitched)
    lines = (glitched / "wheels.txt").read_text().splitlines()
    rows = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#")]
    t, left, right = lines[rows[20]].split()
    lines[rows[20]] = f"{t} {int(left) + 2**31 - 1} {right}"  # one reading, high bit flipped
    (glitched / "wheels.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "run"
    result = runner.invoke(app, ["odometry", str(glitched), "--out", str(out), "-q", "--no-vo"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["wheel_readings_dropped_glitch"] == 1
    assert summary["wheel_odometry_vs_groundtruth"]["final_position_error_m"] < 0.1


def test_a_bad_frame_is_a_counted_skip_also_where_the_contact_sheet_would_draw_it(
    recording: Path, tmp_path: Path
) -> None:
    # The frames.png contact sheet re-read the frames it drew: the first one (always drawn)
    # truncated made the whole run an error after the skip had been counted (#16).
    bad = tmp_path / "bad"
    shutil.copytree(recording, bad)
    first = sorted((bad / "depth").iterdir())[0]
    first.write_bytes(first.read_bytes()[:100])
    out = tmp_path / "run"
    result = runner.invoke(app, ["odometry", str(bad), "--out", str(out), "-q", "--no-vo"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["source_skipped"] == {"truncated": 1}
    assert (out / "frames.png").is_file()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ([], "rec: no usable odometry: VO tracked none of the 1 frame pairs"),
        (["--no-vo"], "rec: no odometry input: no wheel encoder readings"),
    ],
)
def test_odometry_refuses_a_source_without_wheels_whose_frames_vo_cannot_track(
    tmp_path: Path, extra: list[str], message: str
) -> None:
    from sensors.recording import RecordingWriter
    from sensors.types import CameraIntrinsics, RgbdFrame

    intr = CameraIntrinsics(4, 3, 5.0, 5.0, 2.0, 1.5)
    with RecordingWriter(tmp_path / "rec", intr, {}) as writer:
        for k in range(2):
            writer.add_frame(
                RgbdFrame(
                    k * 33_000_000, np.zeros((3, 4, 3), np.uint8), np.ones((3, 4), np.float32), intr
                )
            )
    result = runner.invoke(
        app, ["odometry", str(tmp_path / "rec"), "--out", str(tmp_path / "o"), *extra]
    )
    assert result.exit_code == 1
    assert message in result.output


def test_the_suite_renders_no_cache_into_the_users_home() -> None:
    """tests/conftest.py points the render cache into pytest's temporary directory."""
    from rgbdnav.cache import cache_root

    home_cache = Path.home() / ".cache"
    assert not cache_root().resolve().is_relative_to(home_cache.resolve()), cache_root()


def test_an_unreadable_cached_rendering_is_rendered_again(
    tmp_path: Path, monkeypatch, caplog
) -> None:
    import logging

    from rgbdnav.cache import cached_recording_path, recording_for
    from rgbdnav.config import load_config

    monkeypatch.setenv("RGBDNAV_CACHE", str(tmp_path / "cache"))
    world = tmp_path / "tiny.yaml"
    world.write_text(
        "walls: [{from: [-1, -1], to: [3, -1]}, {from: [3, -1], to: [3, 1]},"
        " {from: [3, 1], to: [-1, 1]}, {from: [-1, 1], to: [-1, -1]}]\n"
        "start: [0, 0, 0]\nroute: [[0.15, 0]]\n"
    )
    cfg = load_config()
    cached = cached_recording_path(world, cfg, 0)
    cached.mkdir(parents=True)
    (cached / "rgb.txt").write_text("not an index\n")  # a crashed or foreign folder
    with caplog.at_level(logging.WARNING, logger="rgbdnav"):
        path = recording_for(world, cfg, 0)  # the cache batch's Dask workers use
    assert path == cached and "rendering again" in caplog.text
    from sensors.recording import Recording

    assert len(Recording.open(path)) > 10


def test_a_sensor_switched_off_in_the_ekf_config_is_not_fused_or_named(
    recording: Path, tmp_path: Path
) -> None:
    off = "[" + ",".join(["false"] * 15) + "]"
    out = tmp_path / "run"
    result = runner.invoke(
        app,
        [
            "odometry",
            str(recording),
            "--out",
            str(out),
            "-q",
            "--no-vo",
            "--set",
            f"ekf.imu0_config={off}",
        ],
    )
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ekf"]["inputs"] == ["odom0"]
    assert summary["ekf"]["stats"]["sensors"]["imu0"]["received"] == 0


def test_map_of_a_recording_decodes_each_frame_once(
    recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from sensors.recording_source import RecordingSource

    decoded = []
    frames_for = RecordingSource.frames_for  # what the front end reads through

    def counting(self: RecordingSource, rgb_wanted):  # type: ignore[no-untyped-def]
        for f in frames_for(self, rgb_wanted):
            decoded.append(f.stamp_ns)
            yield f

    monkeypatch.setattr(RecordingSource, "frames_for", counting)
    out = tmp_path / "map"
    result = runner.invoke(app, ["map", str(recording), "--out", str(out), "-q"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert len(decoded) == len(set(decoded)) == 45  # VO and depth -> scan share one decode
    assert summary["counts"]["scans"] == 45
