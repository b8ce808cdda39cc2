"""Fusing VO that skipped frames: one twist at the pair's end vs spread over the frames it spans.

Run: ``.venv/bin/python bench/bench_vo_gaps.py [SOURCE] [--skip 0.15] [--out docs/benchmarks.md]``.

A live front end that falls behind skips VO on some frames (``live.skip_vo_when_behind``); the
next VO pair then spans them. This replays that offline on a recording (default: the rendered
house route, as ``make demo`` maps it) with the live run's EKF and VO settings
(``config/profiles/rgbd_mapping.yaml`` + ``live.yaml``, no gyro: the Eddie has none): VO on
every frame, then VO on the frames a seeded skip pattern keeps (bursts of 1-4 skipped frames,
``--skip`` of them in all), fused as one twist at each pair's end (``motion_twist``, the live
run before 2026-11-22) and spread over the skipped frames
(``slam.ekf.spanning_motion_twists``). Scored as ``rgbdnav odometry`` scores the fused path:
unaligned ATE and drift per 10 m against the ground truth. The result replaces the
"vo-gaps" section of ``--out``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import machine, publish  # noqa: E402  (bench/ is on sys.path)

from rgbdnav.cache import recording_for  # noqa: E402
from rgbdnav.config import load_config  # noqa: E402
from rgbdnav.scan_stream import RGBD_PROFILE  # noqa: E402
from sensors.recording import Recording  # noqa: E402
from slam.diff_drive import WheelErrorModel  # noqa: E402
from slam.ekf import (  # noqa: E402
    TwistInput,
    fuse,
    motion_twist,
    spanning_motion_twists,
    wheel_twist_inputs,
)
from slam.geometry import compose  # noqa: E402
from slam.metrics import drift_report  # noqa: E402
from slam.visual_odometry import VisualOdometry  # noqa: E402

SECTION = "vo-gaps"
LIVE_PROFILE = RGBD_PROFILE.with_name("live.yaml")
NO_GYRO = "ekf.imu0_config=[" + ",".join(["false"] * 15) + "]"


def skip_pattern(n: int, share: float, rng: np.random.Generator) -> np.ndarray:
    """(n,) bool, True where VO is skipped: bursts of 1-4 frames (as a front end that fell
    behind for a moment), about ``share`` of the frames; frame 0 is never skipped."""
    skip = np.zeros(n, bool)
    mean_burst = 2.5
    k = 1
    while k < n:
        if rng.random() < share / (mean_burst * (1 - share)):
            length = int(rng.integers(1, 5))
            skip[k : k + length] = True
            k += length + 1  # VO runs on the frame after a burst
        else:
            k += 1
    return skip


def vo_inputs(rec: Recording, cfg, skip: np.ndarray, spread: bool) -> list[TwistInput]:
    vo = VisualOdometry(rec.intrinsics, cfg.vo, cfg.robot)
    out: list[TwistInput] = []
    prev, skipped = None, []
    for k, frame in enumerate(rec.frames()):
        if skip[k]:
            skipped.append(frame.stamp_ns)
            continue
        res = vo.process(frame)
        if prev is not None and res.success and res.delta_base is not None:
            dt_s = (frame.stamp_ns - prev) / 1e9
            if spread:
                out += spanning_motion_twists(
                    skipped, frame.stamp_ns, res.delta_base, res.covariance, dt_s
                )
            else:
                out.append(motion_twist(frame.stamp_ns, res.delta_base, res.covariance, dt_s))
        prev, skipped = frame.stamp_ns, []
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "source",
        type=Path,
        nargs="?",
        default=REPO / "scenes" / "house.yaml",
        help="a recording, or a world (its cached rendering, made if missing)",
    )
    ap.add_argument("--skip", type=float, default=0.15, help="share of frames VO skips")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="markdown file to update (docs/benchmarks.md)")
    args = ap.parse_args()
    recording = recording_for(args.source, load_config([], []), 0)
    rec = Recording.open(recording)
    cfg = load_config([RGBD_PROFILE, LIVE_PROFILE], [NO_GYRO])
    ws, wl, wr = rec.wheels()
    wheels = wheel_twist_inputs(
        ws,
        wl,
        wr,
        cfg.robot,
        WheelErrorModel.from_robot(cfg.robot),
        vy_variance=cfg.ekf.odom0_vy_variance,
    )
    gt = rec.groundtruth_planar()
    if gt is None:
        sys.exit(f"{recording}: no ground truth to score against")
    frame_t = np.array([f.stamp_ns for f in rec.frames()], np.int64)
    skip = skip_pattern(len(frame_t), args.skip, np.random.default_rng(args.seed))
    rows = []
    for label, vo in (
        ("VO on every frame", vo_inputs(rec, cfg, np.zeros(len(frame_t), bool), False)),
        ("VO skipped, one twist at each pair's end", vo_inputs(rec, cfg, skip, False)),
        ("VO skipped, spread over the skipped frames", vo_inputs(rec, cfg, skip, True)),
        ("wheels only", []),
    ):
        streams = {"odom0": wheels, "vo0": vo} if vo else {"odom0": wheels}
        fused = fuse(streams, cfg.ekf, output_stamps_ns=frame_t)
        x, y, yaw = compose(gt[1][0], gt[2][0], gt[3][0], fused.x, fused.y, fused.yaw)
        ok = np.isfinite(x)
        r = drift_report(frame_t[ok], (x[ok], y[ok], yaw[ok]), gt[0], gt[1:])
        rows.append(f"| {label} | {r.ate_rmse_m:.3f} | {100 * r.drift_per_10m_m:.1f} cm |")
        print(rows[-1], flush=True)
    body = f"""## Fusing VO that skipped frames (live front end behind)

Measured {dt.date.today().isoformat()} on {machine("cv2", "numpy")}.
Command: `python bench/bench_vo_gaps.py {args.source.relative_to(REPO) if args.source.is_relative_to(REPO) else args.source} --skip {args.skip} --seed {args.seed}`;
recording `{recording}`, {len(frame_t)} frames, VO skipped on {int(skip.sum())} of them
({100 * skip.mean():.0f} %, bursts of 1-4). The live run's settings (RGB-D mapping + live
profiles: optical-flow VO, wheel and VO twists, no gyro), fused offline in time order; ATE
unaligned, drift from the end point.

| VO input to the EKF | fused ATE [m] | drift per 10 m |
| --- | --- | --- |
{chr(10).join(rows)}
"""
    publish(body, args.out, SECTION)


if __name__ == "__main__":
    main()
