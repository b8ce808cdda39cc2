"""Trajectory metrics on hand-built paths."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam.metrics import align_se2, drift_report, drift_summary, interpolate_poses


def test_identical_trajectories_have_zero_error() -> None:
    t = np.arange(0, 10) * 1_000_000_000
    x, y, yaw = np.arange(10.0), np.zeros(10), np.zeros(10)
    r = drift_report(t, (x, y, yaw), t, (x, y, yaw))
    assert r.ate_rmse_m == 0 and r.final_position_error_m == 0 and r.path_length_m == 9.0


def test_scale_error_shows_as_drift_percent() -> None:
    t = np.arange(0, 101) * 100_000_000
    x = np.linspace(0, 10, 101)
    r = drift_report(t, (1.02 * x, 0 * x, 0 * x), t, (x, 0 * x, 0 * x))
    assert r.drift_percent == pytest.approx(2.0)
    assert r.drift_per_10m_m == pytest.approx(0.2)


def test_alignment_removes_a_rigid_offset() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 2))
    a = 0.3
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    dst = src @ rot.T + [1.0, -2.0]
    r, t = align_se2(src, dst)
    assert np.allclose(r, rot) and np.allclose(t, [1.0, -2.0])


def test_reference_is_not_extrapolated() -> None:
    t_ref = np.array([0, 10])
    _, _, _, inside = interpolate_poses(
        t_ref, np.zeros(2), np.zeros(2), np.zeros(2), np.array([-1, 5, 11])
    )
    assert inside.tolist() == [False, True, False]


def test_a_drift_summary_of_tracks_that_do_not_overlap_says_so_instead_of_raising() -> None:
    t_ref = np.array([0, 10**9, 2 * 10**9], dtype=np.int64)
    ref = (np.zeros(3), np.zeros(3), np.zeros(3))
    s = drift_summary(np.array([5 * 10**9], dtype=np.int64), (np.zeros(1),) * 3, t_ref, ref)
    assert s == {
        "matched": 0,
        "not_compared": "estimate and reference do not overlap in time",
        "estimate_poses": 1,
    }
    assert drift_summary(t_ref, ref, t_ref, ref)["matched"] == 3
