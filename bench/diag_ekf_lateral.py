"""Where the fused odometry's sideways steps come from: the front end's inputs logged once, then
the front end (wheels, gyro, the logged VO results, EKF) re-run over them in seconds.

Run::

    python bench/diag_ekf_lateral.py capture REC --out CACHE.pkl   # VO + depth->scan once
    python bench/diag_ekf_lateral.py capture WORLD.yaml --seed 1 --out CACHE.pkl
    python bench/diag_ekf_lateral.py replay CACHE.pkl [--set ekf.KEY=V ...] [--map]

``capture`` drives ``rgbdnav map``'s front end over a recording (``rgbdnav simulate WORLD --out
REC``) and logs every call it gets (wheel readings, IMU samples, odometry messages, frames) with
each frame's VO result and scan. ``replay`` feeds the same calls in the same order to a fresh
:class:`~slam.front_end.FrontEnd` of this tree whose VO and depth->scan return the logged
results, so a change to the EKF or the wheel twists is measured without re-running VO. It prints:

- the fused odometry against the ground truth (aligned ATE, drift);
- sideways motion, which a differential drive cannot make: per frame, the fused step across
  its own heading (RMS, frames over 1 cm, max), and per 10 frames the relative motion's error
  across the path against the truth's (RMS, as in docs/benchmarks.md "House route IoU 0.898");
- what moved the pose sideways: the EKF's position change in base_link split by step (predict
  = vy dt; the update of each sensor's twist through the filter's cross-covariances), summed
  over the run as RMS per frame.

With ``--map`` the scans are mapped with the replayed odometry as ``rgbdnav map`` does (SLAM
ATE, grid IoU against the floor plan, closures).
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import slam.front_end as front_end  # noqa: E402
from rgbdnav.cache import open_world_or_source  # noqa: E402
from rgbdnav.config import load_config  # noqa: E402
from rgbdnav.runners.map import _score_against_truth  # noqa: E402
from rgbdnav.scan_stream import source_config  # noqa: E402
from slam.ekf import POSE_IDX, YAW, PlanarEkf  # noqa: E402
from slam.front_end import FrontEnd, MessageFeed, odom_origin, options_for  # noqa: E402
from slam.geometry import ominus, oplus  # noqa: E402
from slam.mapper import Mapper, build_grid  # noqa: E402
from slam.metrics import drift_report, interpolate_poses  # noqa: E402

WINDOW = 10  # frames: the relative-motion window of the across-path error


# --- capture ----------------------------------------------------------------------------------


def capture(rec: Path, out: Path, overrides: list[str], seed: int = 0) -> None:
    cfg = load_config([], overrides)
    src = open_world_or_source(rec, cfg, seed)
    scene, _, cfg, _ = source_config(src, [], overrides)
    opts = options_for(src, True, False, cfg.camera.rate)
    fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, opts)
    calls: list[tuple] = []
    for name in ("wheels", "imu", "odometry"):
        orig = getattr(fe, name)

        def logged(msg, _orig=orig, _name=name):  # type: ignore[no-untyped-def]
            calls.append((_name, msg))
            return _orig(msg)

        setattr(fe, name, logged)
    messages = MessageFeed(src, fe)
    for frame in src.frames():
        messages.until(frame.stamp_ns)
        step = fe.frame(frame)
        calls.append(("frame", frame.stamp_ns, step.vo, step.scan))
    gt = src.groundtruth()
    data = {
        "calls": calls,
        "options": opts,
        "origin": odom_origin(src),
        "gt": None if gt is None else (gt.stamps_ns, gt.x, gt.y, gt.yaw),
        "scene": scene,
        "source": str(rec),
    }
    out.write_bytes(pickle.dumps(data))
    print(f"{out}: {len(calls)} calls, {sum(c[0] == 'frame' for c in calls)} frames")


# --- replay -----------------------------------------------------------------------------------


class TracedEkf(PlanarEkf):
    """PlanarEkf that keeps, per measurement, the body-frame position change of its predict and
    of its update (re-filtered measurements overwrite their earlier trace)."""

    trace: dict[int, tuple] = {}

    def _apply(self, m):  # type: ignore[no-untyped-def]
        x0, t0 = self.x.copy(), self.t_ns
        res = super()._apply(m)
        if t0 is not None:
            dt = max(0.0, (m.stamp_ns - t0) / 1e9)
            c, s = math.cos(x0[YAW]), math.sin(x0[YAW])
            # predict's sideways move is vy dt; the update's is the rest of the change
            d = self.x[POSE_IDX[:2]] - x0[POSE_IDX[:2]]
            lat_total = -s * d[0] + c * d[1]
            lon_total = c * d[0] + s * d[1]
            lat_pred = x0[4] * dt
            lon_pred = x0[3] * dt
            TracedEkf.trace[id(m)] = (
                m,
                m.stamp_ns,
                m.sensor,
                lat_pred,
                lat_total - lat_pred,
                lon_total - lon_pred,
            )
        return res


class _LoggedVo:
    def __init__(self, results: dict[int, object]) -> None:
        self.results = results
        self.stats: dict[str, int] = {}
        self.features_every_frame = False
        self.T_odom_cam = np.eye(4)

    def process(self, frame):  # type: ignore[no-untyped-def]
        return self.results[frame.stamp_ns]


class _LoggedScans:
    def __init__(self, scans: dict[int, object]) -> None:
        self.scans = scans

    def from_frame(self, frame):  # type: ignore[no-untyped-def]
        return SimpleNamespace(scan=self.scans[frame.stamp_ns])


def replay(data: dict, overrides: list[str]) -> dict:
    cfg = load_config([], overrides)
    # Only the source's config is read: no renderer process (a wrapper script that calls
    # replay needs no `if __name__ == "__main__":` guard; capture's renderer does).
    src = open_world_or_source(Path(data["source"]), cfg, 0, render_ahead=False)
    _, _, cfg, _ = source_config(src, [], overrides)
    src.close()
    TracedEkf.trace = {}
    front_end.PlanarEkf = TracedEkf  # type: ignore[misc]
    try:
        fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, data["options"])
    finally:
        front_end.PlanarEkf = PlanarEkf  # type: ignore[misc]
    frames = [c for c in data["calls"] if c[0] == "frame"]
    fe._vo = _LoggedVo({c[1]: c[2] for c in frames})  # type: ignore[assignment]
    fe._d2s = _LoggedScans({c[1]: c[3] for c in frames})  # type: ignore[assignment]
    stamps, poses, scans = [], [], []
    for c in data["calls"]:
        if c[0] == "frame":
            step = fe.frame(SimpleNamespace(stamp_ns=c[1]))  # type: ignore[arg-type]
            if step.odom is None:
                continue
            p = step.odom.pose
            stamps.append(c[1])
            poses.append((p.x, p.y, p.yaw))
            scans.append(step.scan)
        else:
            getattr(fe, c[0])(c[1])
    return {
        "cfg": cfg,
        "stamps": np.array(stamps, np.int64),
        "poses": np.array(poses),
        "scans": scans,
        "stats": fe.ekf.stats if fe.ekf else None,
        "trace": list(TracedEkf.trace.values()),
    }


def sideways(r: dict, data: dict) -> dict:
    """Per-frame sideways steps, the 10-frame relative error against the truth, and what made
    the sideways motion (per sensor: the update's position change across the heading)."""
    t, p = r["stamps"], r["poses"]
    steps = ominus(p[:-1], p[1:])
    lat = steps[:, 1]
    out = {
        "frames": len(p),
        "step_lateral_rms_mm": 1e3 * float(np.sqrt(np.mean(lat**2))),
        "steps_over_1cm": int((np.abs(lat) > 0.01).sum()),
        "steps_over_5mm": int((np.abs(lat) > 0.005).sum()),
        "step_lateral_max_mm": 1e3 * float(np.abs(lat).max()),
    }
    if data["gt"] is not None:
        gs, gx, gy, gyaw = data["gt"]
        o = data["origin"]
        odom = oplus([o.x, o.y, o.yaw], p)
        rx, ry, ryaw, inside = interpolate_poses(gs, gx, gy, gyaw, t)
        ref = np.column_stack([rx, ry, ryaw])
        i = np.flatnonzero(inside[:-WINDOW] & inside[WINDOW:])
        err = ominus(odom[i], odom[i + WINDOW]) - ominus(ref[i], ref[i + WINDOW])
        out["rel10_along_rms_mm"] = 1e3 * float(np.sqrt(np.mean(err[:, 0] ** 2)))
        out["rel10_across_rms_mm"] = 1e3 * float(np.sqrt(np.mean(err[:, 1] ** 2)))
        dr = drift_report(t, (odom[:, 0], odom[:, 1], odom[:, 2]), gs, (gx, gy, gyaw))
        out["fused_ate_aligned_m"] = dr.ate_rmse_aligned_m
        out["fused_ate_anchored_m"] = dr.ate_rmse_m
        out["fused_final_heading_deg"] = dr.final_heading_error_deg
        out["fused_drift_percent"] = dr.drift_percent
    # What moved the pose sideways, per frame interval: sum each sensor's update share.
    tr = r["trace"]
    by: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(len(t)))
    st = np.array([e[1] for e in tr], np.int64)
    k = np.searchsorted(t, st, side="left")  # the frame interval (t[k-1], t[k]] it fell in
    ok = (k > 0) & (k < len(t))
    for e, kk, good in zip(tr, k, ok, strict=True):
        if not good:
            continue
        by["predict (vy dt)"][kk] += e[3]
        by[f"{e[2]} update across"][kk] += e[4]
        by[f"{e[2]} update along"][kk] += e[5]
    out["per_frame_rms_mm"] = {
        name: round(1e3 * float(np.sqrt(np.mean(v[1:] ** 2))), 3) for name, v in sorted(by.items())
    }
    out["per_frame_max_mm"] = {
        name: round(1e3 * float(np.abs(v[1:]).max()), 2) for name, v in sorted(by.items())
    }
    return out


def map_scans(r: dict, data: dict) -> dict:
    cfg = r["cfg"]
    o = data["origin"]
    mapper = Mapper(cfg.mapper)
    for scan, q in zip(r["scans"], r["poses"], strict=True):
        if scan is not None:
            mapper.add_scan(scan, oplus([o.x, o.y, o.yaw], q))
    result = mapper.finish()
    grid = build_grid(result, cfg.mapper)
    summary: dict = {}
    gs, gx, gy, gyaw = data["gt"]
    gt = SimpleNamespace(stamps_ns=gs, x=gx, y=gy, yaw=gyaw)
    _score_against_truth(result, grid, gt, data["scene"], cfg, summary)  # type: ignore[arg-type]
    slam = summary["slam_vs_groundtruth"]
    r["slam"] = (result.scan_stamps_ns, result.scan_poses, result.poses)
    return {
        "slam_ate_aligned_m": slam["ate_rmse_aligned_m"],
        "slam_ate_anchored_m": slam["ate_rmse_m"],
        "iou_aligned": summary["grid_vs_floor_plan_aligned"]["iou"],
        "closures": result.counts.get("loop_closures"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture")
    c.add_argument("recording", type=Path)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--set", action="append", default=[], dest="overrides")
    c.add_argument("--seed", type=int, default=0, help="the simulator's seed (a world file)")
    r = sub.add_parser("replay")
    r.add_argument("cache", type=Path)
    r.add_argument("--set", action="append", default=[], dest="overrides")
    r.add_argument("--map", action="store_true", help="map the scans with the replayed odometry")
    r.add_argument("--json", type=Path, help="also write the figures here")
    r.add_argument("--npz", type=Path, help="also save the trajectories (odom, SLAM) here")
    r.add_argument(
        "--textbook",
        action="store_true",
        help="the textbook update: twists move the pose through every cross-covariance, the "
        "gyro bias's too (PlanarEkf.twist_moves_pose; the EKF before docs/design/ekf_lateral.md)",
    )
    a = ap.parse_args()
    if a.cmd == "capture":
        capture(a.recording, a.out, a.overrides, a.seed)
        return
    data = pickle.loads(a.cache.read_bytes())
    PlanarEkf.twist_moves_pose = a.textbook
    res = replay(data, a.overrides)
    fig = sideways(res, data)
    if a.map:
        fig.update(map_scans(res, data))
    fig["ekf_rejected"] = {n: s["rejected"] for n, s in res["stats"].sensors.items()}
    if a.npz:
        o = data["origin"]
        slam = res.get("slam", (np.zeros(0), np.zeros((0, 3)), np.zeros(0)))
        np.savez(
            a.npz,
            stamps=res["stamps"],
            odom=oplus([o.x, o.y, o.yaw], res["poses"]),
            slam_stamps=slam[0],
            slam=slam[1],
            keyframe_poses=np.asarray(slam[2]),
            gt=np.column_stack(data["gt"]) if data["gt"] is not None else np.zeros((0, 4)),
        )
    text = json.dumps(fig, indent=1, default=float)
    print(text)
    if a.json:
        a.json.write_text(text)


if __name__ == "__main__":
    main()
