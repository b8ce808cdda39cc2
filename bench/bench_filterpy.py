"""slam/ekf.py's kernels against filterpy's ExtendedKalmanFilter: agreement and speed.

The same 30 Hz run (constant-velocity planar model, alternately a twist and a pose update with
an angle residual) through both (tests/slam/test_ekf.py's ``filterpy_sequence``): the largest
state and covariance difference over the run, and microseconds per predict + update cycle
(median of ``--repeats`` timed runs; process time). Decides filterpy's place:
docs/design/kiss_icp_and_filterpy.md.

Run: ``PYTHONPATH=. .venv/bin/python bench/bench_filterpy.py``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slam.ekf import angle_residual, predict, transition, update  # noqa: E402
from tests.slam.test_ekf import filterpy_sequence  # noqa: E402


def time_ours(steps: int) -> float:
    """[us] per predict + update cycle of slam.ekf's kernels."""
    dt, q = 1.0 / 30, np.eye(6) * 1e-3
    x, p = np.array([0.0, 0.0, 0.5, 0.3, 0.0, 0.4]), np.eye(6) * 0.1
    h, r, res = np.eye(6)[:3], np.eye(3) * 0.02, angle_residual(np.array([False, False, True]))
    z = np.array([0.01, 0.0, 0.5])
    c0 = time.process_time()
    for _ in range(steps):
        x, p = predict(x, p, dt, q)
        x, p, *_ = update(x, p, z, h, r, res)
    return (time.process_time() - c0) / steps * 1e6


def time_filterpy(steps: int) -> float:
    """[us] per predict + update cycle of filterpy's ExtendedKalmanFilter on the same problem."""
    from filterpy.kalman import ExtendedKalmanFilter

    dt, q = 1.0 / 30, np.eye(6) * 1e-3
    f = ExtendedKalmanFilter(dim_x=6, dim_z=3)
    f.x, f.P = np.array([0.0, 0.0, 0.5, 0.3, 0.0, 0.4]), np.eye(6) * 0.1

    def predict_x(u: Any = 0) -> None:
        f.x = transition(f.x, dt)[0]

    f.predict_x = predict_x
    h, r, res = np.eye(6)[:3], np.eye(3) * 0.02, angle_residual(np.array([False, False, True]))
    z = np.array([0.01, 0.0, 0.5])
    c0 = time.process_time()
    for _ in range(steps):
        f.F, f.Q = transition(f.x, dt)[1], dt * q
        f.predict()
        f.update(z, lambda s: h, lambda s: h @ s, R=r, residual=res)
    return (time.process_time() - c0) / steps * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    xs, ps, rx, rp = filterpy_sequence(300, seed=4)
    dx = max(float(np.max(np.abs(a - b))) for a, b in zip(xs, rx, strict=True))
    dp = max(float(np.max(np.abs(a - b))) for a, b in zip(ps, rp, strict=True))
    ours = float(np.median([time_ours(args.steps) for _ in range(args.repeats)]))
    theirs = float(np.median([time_filterpy(args.steps) for _ in range(args.repeats)]))
    print(f"300-step run: max |x - x_filterpy| = {dx:.2e}, max |P - P_filterpy| = {dp:.2e}")
    print(
        f"predict + update cycle: slam.ekf {ours:.1f} us, filterpy EKF {theirs:.1f} us "
        f"(ratio {theirs / ours:.2f}; median of {args.repeats} runs of {args.steps} cycles)"
    )
    assert math.isfinite(dx) and math.isfinite(dp)


if __name__ == "__main__":
    main()
