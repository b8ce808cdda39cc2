"""`rgbdnav eval`: ATE and RPE of a trajectory (TUM, KITTI or EuRoC) against a reference, or the
Kümmerle 2009 relations metric against a relations file, printed and written to a run directory.

I/O lives here; the metrics are the pure kernels of :mod:`slam.trajectory_eval`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from rgbdnav.config import load_config
from rgbdnav.report import plot_trajectories
from rgbdnav.run_dir import RunDir
from sensors.tum import read_pose_table, yaw_from_quaternion
from sensors.types import NS_PER_S, format_stamp
from slam.trajectory_eval import (
    ALIGN_MODES,
    DELTA_UNITS,
    AlignMode,
    DeltaUnit,
    TrajectoryEvalError,
    TrajectoryEvaluation,
    evaluate,
    poses_from_tum,
    read_relations,
    relations_error,
)

log = logging.getLogger(__name__)

RUN_TRAJECTORY = "trajectory.tum"  # what a run directory holds (see RunDir)
RAD_TO_DEG = 180.0 / np.pi


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A TUM trajectory as read: sorted unique stamps, positions and quaternions."""

    path: Path
    stamps_ns: np.ndarray  # (N,) int64 [ns], strictly increasing
    xyz: np.ndarray  # (N, 3) [m]
    quat_xyzw: np.ndarray  # (N, 4)
    repeated_stamps: int  # lines dropped because a later line had the same stamp


def read_trajectory(path: Path, times: Path | None = None) -> Trajectory:
    """Read a TUM, KITTI (``times``: its times file) or EuRoC/ASL trajectory, detected from the
    content, the way the TUM benchmark tools read TUM (into a dict keyed by stamp): lines may
    come in any order, and a repeated stamp keeps its last line. The official fr2/desk ground
    truth has such a repeat. Malformed lines are errors naming file:line."""
    path = Path(path)
    if path.is_dir():
        path = path / RUN_TRAJECTORY
    table = read_pose_table(path, times=times, check_order=False)
    data = table.poses
    # Sort by stamp (stable), then keep the last line of each run of equal stamps.
    order = np.argsort(table.stamps_ns, kind="stable")
    sorted_ns = table.stamps_ns[order]
    last = np.append(sorted_ns[1:] != sorted_ns[:-1], True)
    keep = order[last]
    repeated = int(len(order) - keep.size)
    if repeated:
        log.warning("%s: %d repeated timestamp(s); kept the last line of each", path, repeated)
    return Trajectory(path, table.stamps_ns[keep], data[keep, :3], data[keep, 3:], repeated)


def _span(t: Trajectory) -> str:
    return f"{format_stamp(int(t.stamps_ns[0]))}..{format_stamp(int(t.stamps_ns[-1]))} s"


def evaluate_files(
    estimate: Trajectory,
    reference: Trajectory,
    align: str,
    max_diff_s: float,
    delta: float,
    delta_unit: str,
) -> TrajectoryEvaluation:
    """Run the kernels, turning "no overlap" into an error that names both files and spans."""
    if align not in ALIGN_MODES:
        raise TrajectoryEvalError(f"--align {align!r}: use one of {', '.join(ALIGN_MODES)}")
    if delta_unit not in DELTA_UNITS:
        raise TrajectoryEvalError(
            f"--delta-unit {delta_unit!r}: use one of {', '.join(DELTA_UNITS)}"
        )
    max_diff_ns = int(round(max_diff_s * NS_PER_S))
    if max_diff_ns <= 0:
        raise TrajectoryEvalError(f"--max-diff must be > 0 s, got {max_diff_s}")
    try:
        return evaluate(
            estimate.stamps_ns,
            poses_from_tum(estimate.xyz, estimate.quat_xyzw),
            reference.stamps_ns,
            poses_from_tum(reference.xyz, reference.quat_xyzw),
            align_mode=cast(AlignMode, align),
            max_diff_ns=max_diff_ns,
            delta=delta,
            delta_unit=cast(DeltaUnit, delta_unit),
        )
    except TrajectoryEvalError as err:
        raise TrajectoryEvalError(
            f"{estimate.path} ({_span(estimate)}) vs {reference.path} ({_span(reference)}), "
            f"max difference {max_diff_s} s: {err}"
        ) from err


def summary_of(
    result: TrajectoryEvaluation,
    estimate: Trajectory,
    reference: Trajectory,
    align: str,
    max_diff_s: float,
    delta: float,
    delta_unit: str,
) -> dict:
    """The summary.json content; flat ``ate_rmse_m`` etc. for scripts, full statistics nested."""
    summary: dict = {
        "command": "eval",
        "estimate": str(estimate.path),
        "reference": str(reference.path),
        "estimate_poses": int(len(estimate.stamps_ns)),
        "reference_poses": int(len(reference.stamps_ns)),
        "repeated_stamps": {
            "estimate": estimate.repeated_stamps,
            "reference": reference.repeated_stamps,
        },
        "matched": result.matched,
        "max_diff_s": max_diff_s,
        "align": align,
        "alignment": result.alignment.as_dict(),
        "ate_rmse_m": result.ate.rmse,
        "ate_m": result.ate.as_dict(),
        "rpe_delta": delta,
        "rpe_delta_unit": delta_unit,
    }
    if result.rpe_trans is not None and result.rpe_rot is not None:
        summary["rpe_trans_rmse_m"] = result.rpe_trans.rmse
        summary["rpe_rot_rmse_deg"] = result.rpe_rot.rmse * RAD_TO_DEG
        summary["rpe_trans_m"] = result.rpe_trans.as_dict()
        summary["rpe_rot_deg"] = result.rpe_rot.scaled(RAD_TO_DEG).as_dict()
    return summary


def format_report(summary: dict) -> str:
    """Human-readable lines for the terminal."""
    out = [
        f"matched     {summary['matched']} of {summary['estimate_poses']} estimate poses "
        f"(max difference {summary['max_diff_s']} s)",
        f"alignment   {summary['align']} (scale {summary['alignment']['scale']:.6f})",
    ]
    ate = summary["ate_m"]
    out.append(
        f"ATE [m]     rmse {ate['rmse']:.6f}  mean {ate['mean']:.6f}  "
        f"median {ate['median']:.6f}  std {ate['std']:.6f}  max {ate['max']:.6f}"
    )
    per = f"per {summary['rpe_delta']:g} {summary['rpe_delta_unit']}"
    if "rpe_trans_m" in summary:
        t, r = summary["rpe_trans_m"], summary["rpe_rot_deg"]
        out.append(
            f"RPE [m]     rmse {t['rmse']:.6f}  mean {t['mean']:.6f}  max {t['max']:.6f}"
            f"  ({t['count']} pairs, {per})"
        )
        out.append(f"RPE [deg]   rmse {r['rmse']:.4f}  mean {r['mean']:.4f}  max {r['max']:.4f}")
    else:
        out.append(f"RPE         no pose pairs {per}: the trajectory is shorter than the delta")
    return "\n".join(out)


def run_eval(
    estimate_path: Path,
    reference_path: Path,
    out: Path | None,
    *,
    align: str = "se3",
    max_diff_s: float = 0.02,
    delta: float = 1.0,
    delta_unit: str = "m",
    config_files: Sequence[Path] = (),
    overrides: Sequence[str] = (),
    estimate_times: Path | None = None,
    reference_times: Path | None = None,
) -> dict:
    """Evaluate; with ``out``, write ``config.yaml``, ``summary.json`` and ``ate.png`` there
    (without, only compute, as evo_ape prints without ``--save_results``). Return the
    summary."""
    t0 = time.perf_counter()
    cfg = load_config(list(config_files), list(overrides))
    estimate = read_trajectory(estimate_path, estimate_times)
    reference = read_trajectory(reference_path, reference_times)
    result = evaluate_files(estimate, reference, align, max_diff_s, delta, delta_unit)
    summary = summary_of(result, estimate, reference, align, max_diff_s, delta, delta_unit)
    if out is None:
        return summary

    run = RunDir(out)
    run.write_config(cfg)
    ref, est = result.ref_xyz, result.est_aligned_xyz
    plot_trajectories(
        run.file("ate.png"),
        [
            ("reference", ref[:, 0], ref[:, 1]),
            (f"estimate ({align} aligned)", est[:, 0], est[:, 1]),
        ],
        f"{estimate.path.name}: ATE rmse {result.ate.rmse:.4f} m",
    )
    summary["wall_time_s"] = round(time.perf_counter() - t0, 3)
    run.write_summary(summary)
    return summary


# Relations metric (Kümmerle et al. 2009) ------------------------------------------------------


def format_relations_report(summary: dict) -> str:
    """Human-readable lines for the terminal: mean ± std of the errors and of their squares."""
    r = summary["relations_error"]
    return "\n".join([
        f"relations   {r['count']} of {summary['relations']} scored, {r['skipped']} skipped "
        f"(no estimate pose within {summary['max_diff_s']} s of t1 or t2)",
        f"REL [m]     {r['trans_mean_m']:.6f} ± {r['trans_std_m']:.6f}  "
        f"squared [m^2] {r['trans_sq_mean_m2']:.6f} ± {r['trans_sq_std_m2']:.6f}",
        f"REL [deg]   {r['rot_mean_deg']:.4f} ± {r['rot_std_deg']:.4f}  "
        f"squared [deg^2] {r['rot_sq_mean_deg2']:.4f} ± {r['rot_sq_std_deg2']:.4f}",
    ])  # fmt: skip


def run_relations_eval(
    estimate_path: Path,
    relations_path: Path,
    out: Path | None,
    *,
    max_diff_s: float = 0.02,
    config_files: Sequence[Path] = (),
    overrides: Sequence[str] = (),
    estimate_times: Path | None = None,
) -> dict:
    """Score the planar part (x, y, yaw) of a TUM trajectory against reference relations; with
    ``out``, write ``config.yaml`` and ``summary.json`` there. Return the summary."""
    t0 = time.perf_counter()
    cfg = load_config(list(config_files), list(overrides))
    max_diff_ns = int(round(max_diff_s * NS_PER_S))
    if max_diff_ns <= 0:
        raise TrajectoryEvalError(f"--max-diff must be > 0 s, got {max_diff_s}")
    estimate = read_trajectory(estimate_path, estimate_times)
    relations = read_relations(relations_path)
    poses = np.column_stack([estimate.xyz[:, :2], yaw_from_quaternion(estimate.quat_xyzw)])
    try:
        metric = relations_error(
            estimate.stamps_ns,
            poses,
            relations.t1_ns,
            relations.t2_ns,
            relations.xyyaw,
            max_diff_ns,
        )
    except TrajectoryEvalError as err:
        raise TrajectoryEvalError(
            f"{estimate.path} ({_span(estimate)}) vs {relations.path}, "
            f"max difference {max_diff_s} s: {err}"
        ) from err
    summary: dict = {
        "command": "eval",
        "estimate": str(estimate.path),
        "reference_relations": str(relations.path),
        "estimate_poses": int(len(estimate.stamps_ns)),
        "repeated_stamps": {"estimate": estimate.repeated_stamps},
        "relations": int(len(relations.t1_ns)),
        "max_diff_s": max_diff_s,
        "rel_trans_mean_m": metric["trans_mean_m"],
        "rel_rot_mean_deg": metric["rot_mean_deg"],
        "relations_error": metric,
    }
    if out is not None:
        run = RunDir(out)
        run.write_config(cfg)
        summary["wall_time_s"] = round(time.perf_counter() - t0, 3)
        run.write_summary(summary)
    return summary
