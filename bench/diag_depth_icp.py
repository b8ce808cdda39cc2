"""Per-frame depth-ICP errors on a simulated route: the variants of the table in
docs/design/kiss_icp_and_filterpy.md ("What the measurements changed on the way").

For each variant, in lockstep on the same rendered frames (planar mode, 30 Hz): frames accepted
and lost, the planar error of the accepted frames against ground truth (median / p90 / max), the
summed error (a bias shows here), and the mean squared error over the claimed variance.

Run: ``PYTHONPATH=. .venv/bin/python bench/diag_depth_icp.py [--world scenes/house.yaml]
[--frames 150]``.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sensors.config import CameraConfig, RobotConfig, SimConfig  # noqa: E402
from sensors.types import RgbdFrame  # noqa: E402
from slam.config import VoConfig  # noqa: E402
from slam.geometry import wrap_angle  # noqa: E402
from slam.visual_odometry import VisualOdometry  # noqa: E402

VARIANTS: dict[str, dict[str, float]] = {
    "KISS-ICP alone (10 cm voxels)": dict(
        icp_voxel_size=0.1, icp_refine_iterations=0, icp_max_deviation=0.0
    ),
    "+ point-to-plane polish": dict(icp_voxel_size=0.1, icp_max_deviation=0.0),
    "+ polish, 3 cm deviation check": dict(icp_voxel_size=0.1),
    "+ polish, 3 cm deviation check, 5 cm voxels (default)": {},
    "10 cm voxels, 6 polish steps, 3 cm deviation check": dict(
        icp_voxel_size=0.1, icp_refine_iterations=6
    ),
}


def main() -> None:
    from sensors.sim.motion import drive_route
    from sensors.sim.render import KinectRenderer
    from sensors.sim.world import load_world

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--world", type=Path, default=REPO / "scenes" / "house.yaml")
    ap.add_argument("--frames", type=int, default=150)
    args = ap.parse_args()
    world, sim, robot = load_world(args.world), SimConfig(), RobotConfig()
    traj = drive_route(world, sim)
    t_cam = np.arange(args.frames) * int(1e9 / sim.camera_rate)
    x, y, yaw = traj.interpolate(t_cam)
    renderer = KinectRenderer(world, CameraConfig(), robot, sim, noise_seed=0)
    rng = np.random.default_rng(0)
    vos = {
        k: VisualOdometry(renderer.intrinsics, replace(VoConfig(), method="depth_icp", **kw), robot)  # type: ignore[arg-type]
        for k, kw in VARIANTS.items()
    }
    rec: dict[str, list[tuple[float, ...]]] = {k: [] for k in VARIANTS}
    for i in range(args.frames):
        rgb, depth = renderer.render(float(x[i]), float(y[i]), float(yaw[i]), rng)
        frame = RgbdFrame(int(t_cam[i]), rgb, depth, renderer.intrinsics)
        if i == 0:
            for vo in vos.values():
                vo.process(frame)
            continue
        c, s = math.cos(yaw[i - 1]), math.sin(yaw[i - 1])
        dx, dy = x[i] - x[i - 1], y[i] - y[i - 1]
        truth = (c * dx + s * dy, -s * dx + c * dy, wrap_angle(yaw[i] - yaw[i - 1]))
        for k, vo in vos.items():
            res = vo.process(frame)
            if res.success and res.delta_base is not None:
                d = res.delta_base
                e = (d.x - truth[0], d.y - truth[1], wrap_angle(d.yaw - truth[2]))
                rec[k].append((1.0, *e, *np.sqrt(np.diag(res.covariance))))
            else:
                rec[k].append((0.0, *truth, 0.0, 0.0, 0.0))
    for k, v in rec.items():
        a = np.array(v)
        ok = a[:, 0] == 1
        e, sig = a[ok, 1:4], a[ok, 4:7]
        exy = np.hypot(e[:, 0], e[:, 1]) * 1000
        print(
            f"{k}: accepted {ok.sum()} / {len(a)}, lost {np.hypot(a[~ok, 1], a[~ok, 2]).sum():.3f} m "
            f"and {math.degrees(np.abs(a[~ok, 3]).sum()):.1f} deg; error median / p90 / max "
            f"{np.percentile(exy, 50):.1f} / {np.percentile(exy, 90):.1f} / {exy.max():.1f} mm; "
            f"summed error x {e[:, 0].sum():.4f} m, y {e[:, 1].sum():.4f} m, yaw "
            f"{math.degrees(e[:, 2].sum()):.2f} deg; mean (error / sigma)^2 x, y, yaw "
            f"{np.round(np.mean((e / sig) ** 2, axis=0), 1)}"
        )


if __name__ == "__main__":
    main()
