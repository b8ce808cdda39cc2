"""The run picture: drawn whatever the run produced."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from rgbdnav.report import plot_trajectories


def test_a_run_without_a_single_usable_pose_still_gets_its_picture(tmp_path: Path) -> None:
    empty = np.zeros(0)
    plot_trajectories(tmp_path / "a.png", [("SLAM", empty, empty)], "nothing mapped")
    nan = np.array([np.nan, np.inf])
    paths = [("odometry", nan, nan), ("truth", np.ones(2), np.arange(2.0))]
    plot_trajectories(tmp_path / "b.png", paths, "t")
    for name in ("a.png", "b.png"):
        image = cv2.imread(str(tmp_path / name))
        assert image is not None and image.shape[0] > 10 and image.shape[1] > 10
