from __future__ import annotations

import json
from pathlib import Path

from rgbdnav.run_dir import RunDir


def test_a_rerun_removes_the_earlier_summary_before_writing_anything(tmp_path: Path) -> None:
    # A re-run killed part-way must not leave the old summary describing new files (#16).
    first = RunDir(tmp_path / "run")
    first.file("trajectory.tum").write_text("old\n")
    first.write_summary({"command": "odometry", "frames": 10})
    assert json.loads(first.file("summary.json").read_text())["frames"] == 10

    second = RunDir(tmp_path / "run")  # the re-run starts ...
    assert not second.file("summary.json").exists()  # ... and is killed here: incomplete
    assert second.file("trajectory.tum").read_text() == "old\n"  # nothing else is deleted
    second.write_summary({"command": "odometry", "frames": 3})
    assert json.loads(second.file("summary.json").read_text())["frames"] == 3
