"""The visualisation side channel: no-op default, rerun recordings, and dropping when behind."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from rgbdnav.visualize import (
    AsyncVisualizer,
    NullVisualizer,
    RerunVisualizer,
    VisualizerError,
    log_run,
    make_visualizer,
    occupied_cells_xy,
)


class _Slow(NullVisualizer):
    """Blocks drawing until released, and counts what it drew."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()
        self.frames = 0

    def frame(self, stamp_ns: int, rgb: np.ndarray | None, depth_m: np.ndarray | None) -> None:
        self.entered.set()
        self.release.wait(5.0)
        self.frames += 1


def test_without_rrd_or_viewer_the_visualizer_does_nothing() -> None:
    assert isinstance(make_visualizer("x", None, False), NullVisualizer)


def test_a_busy_visualizer_drops_and_counts_instead_of_blocking_the_caller() -> None:
    inner = _Slow()
    vis = AsyncVisualizer(inner, maxsize=2)
    vis.frame(0, None, None)
    assert inner.entered.wait(5.0)  # the drawing thread is now stuck on the first frame
    for k in range(1, 10):
        vis.frame(k, None, None)  # returns at once although nothing more is drawn
    # One job is being drawn, two wait in the queue, the other seven were dropped.
    assert vis.dropped == 7
    inner.release.set()
    vis.close()
    assert inner.frames == 3 and vis.drawn == 3


def test_an_rrd_holds_the_documented_entity_paths(tmp_path: Path) -> None:
    rrd = tmp_path / "run.rrd"
    vis = RerunVisualizer("test", rrd)
    poses = np.column_stack([np.linspace(0, 2, 30), np.zeros(30), np.zeros(30)])
    occ = np.zeros((10, 10), bool)
    occ[0, :] = True
    log_run(
        vis,
        np.arange(30) * 100_000_000,
        poses,
        [np.ones((5, 2))] * 30,
        occupied_cells_xy(occ, (0.0, 0.0), 0.1),
        poses[:, :2],
    )
    vis.frame(0, np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32))
    vis.plan(0, poses[:, :2])
    vis.costmap(0, np.ones((3, 2)))
    vis.close()
    data = rrd.read_bytes()
    for path in (
        "world/map",
        "world/robot/pose",
        "world/robot/trajectory",
        "world/robot/scan",
        "world/truth",
        "world/plan",
        "world/costmap",
        "camera/rgb",
        "camera/depth",
    ):
        assert path.encode() in data, path


def test_occupied_cells_are_cell_centres_with_row_zero_at_the_bottom() -> None:
    occ = np.zeros((3, 4), bool)
    occ[0, 1] = occ[2, 3] = True
    xy = occupied_cells_xy(occ, (10.0, 20.0), 0.5)
    np.testing.assert_allclose(xy, [[10.75, 20.25], [11.75, 21.25]])


def test_a_rerun_visualizer_needs_somewhere_to_send_to() -> None:
    with pytest.raises(VisualizerError, match="--rrd"):
        RerunVisualizer("test")
