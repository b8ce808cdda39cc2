"""LiveRecorder's failure paths (the happy path is in test_live_cli: a live run recorded and
mapped offline)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from rgbdnav.live.record import LiveRecorder
from sensors.types import CameraIntrinsics, RgbdFrame, WheelTicks

K = CameraIntrinsics(width=8, height=6, fx=5.0, fy=5.0, cx=3.5, cy=2.5)


def frame(stamp_ns: int, h: int = 6, w: int = 8) -> RgbdFrame:
    return RgbdFrame(stamp_ns, np.zeros((h, w, 3), np.uint8), np.ones((h, w), np.float32), K)


def test_a_run_without_frames_records_nothing_and_says_so(tmp_path: Path) -> None:
    rec = LiveRecorder(tmp_path / "rec", {"robot": {}})
    rec.wheels(WheelTicks(1, 0, 0))
    out = rec.close()
    assert "no camera frame" in out["error"] and not (tmp_path / "rec").exists()


def test_a_frame_the_writer_refuses_stops_the_recording_and_leaves_no_folder(
    tmp_path: Path,
) -> None:
    rec = LiveRecorder(tmp_path / "rec", {"robot": {}})
    rec.frame(frame(1))
    rec.frame(frame(2, h=4))  # the camera changed size mid-run: the writer refuses it
    deadline = time.monotonic() + 5
    while rec._error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    rec.frame(frame(3))  # after the failure frames are ignored, not queued for ever
    out = rec.close()
    assert "not written" in out["error"] and "rgb must be 6x8x3" in out["error"]
    assert not (tmp_path / "rec").exists()
    assert [p for p in tmp_path.iterdir() if p.name.startswith(".rec")] == []  # staging gone


def test_frames_the_writer_cannot_take_in_time_are_left_out_and_counted(
    tmp_path: Path, monkeypatch
) -> None:
    import rgbdnav.live.record as lr

    monkeypatch.setattr(lr, "FRAME_QUEUE_SIZE", 1)
    rec = LiveRecorder(tmp_path / "rec", {"robot": {}})
    real = rec.__class__._run

    def slow_run(self: LiveRecorder) -> None:
        time.sleep(0.3)  # a busy disk
        real(self)

    monkeypatch.setattr(lr.LiveRecorder, "_run", slow_run)
    for k in range(1, 6):
        rec.frame(frame(k))
    rec.wheels(WheelTicks(1, 0, 0))
    rec.wheels(WheelTicks(2, 3, 4))
    out = rec.close()
    assert "error" not in out
    assert out["frames_dropped"] >= 3 and out["frames"] + out["frames_dropped"] == 5
    assert len((tmp_path / "rec" / "rgb.txt").read_text().splitlines()) == 2 + out["frames"]
