"""Files and folders written atomically get the modes plain ``open``/``mkdir`` would give
(0644 / 0755 at umask 022), not ``mkstemp``/``mkdtemp``'s 0600 / 0700 (issue 23, item 5)."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from rgbdnav.run_dir import RunDir
from sensors.atomic import (
    atomic_write_text,
    commit_staging_dir,
    current_umask,
    make_staging_dir,
)
from slam.map_bundle import MapBundle, save_bundle, save_map_yaml
from slam.occupancy_grid import GridGeometry, OccupancyGrid


@pytest.fixture
def umask() -> Iterator[object]:
    old = os.umask(0o022)
    try:
        yield os.umask
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _grid() -> OccupancyGrid:
    values = np.full((4, 5), -1, dtype=np.int8)
    values[1, 1], values[2, 2] = 100, 0
    return OccupancyGrid.from_occupancy_values(GridGeometry(0.1, 0.0, 0.0, 5, 4), values)


def test_current_umask_reads_without_changing(umask) -> None:
    umask(0o027)
    assert current_umask() == 0o027
    assert current_umask() == 0o027


MODES = [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700), (0o002, 0o664, 0o775)]


@pytest.mark.parametrize(("mask", "file_mode", "dir_mode"), MODES)
def test_atomic_file_and_staging_folder_follow_umask(tmp_path, umask, mask, file_mode, dir_mode):
    umask(mask)
    atomic_write_text(tmp_path / "a.txt", "x\n")
    assert _mode(tmp_path / "a.txt") == file_mode
    staging = make_staging_dir(tmp_path / "bundle")
    assert _mode(staging) == dir_mode
    (staging / "f").write_text("y")
    commit_staging_dir(staging, tmp_path / "bundle")
    assert _mode(tmp_path / "bundle") == dir_mode


def test_map_bundle_and_map_yaml_readable_by_others(tmp_path, umask) -> None:
    umask(0o022)
    grid = _grid()
    empty = np.zeros(0, np.int64)
    bundle = MapBundle(grid, empty, empty, np.zeros((0, 3)), np.zeros((0, 3)), (), ())
    save_bundle(bundle, tmp_path / "map")
    assert _mode(tmp_path / "map") == 0o755
    modes = {p.name: _mode(p) for p in (tmp_path / "map").iterdir()}
    assert modes and set(modes.values()) == {0o644}, modes
    save_map_yaml(grid, tmp_path / "plain" / "office.yaml")
    assert _mode(tmp_path / "plain" / "office.yaml") == 0o644
    assert _mode(tmp_path / "plain" / "office.pgm") == 0o644


def test_run_dir_summary_readable(tmp_path, umask) -> None:
    umask(0o022)
    run = RunDir(tmp_path / "run")
    assert _mode(run.write_summary({"x": 1})) == 0o644
    assert _mode(tmp_path / "run") == 0o755
