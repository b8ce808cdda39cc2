"""Scans with odometry from any source, shared by `rgbdnav map` and `rgbdnav localize`.

A laser log feeds its scans with the log's per-scan laser pose. An RGB-D source goes through
the front end (:mod:`slam.front_end`: wheels, ``/odom``, IMU and VO in the EKF, depth -> scan),
each frame's scan paired with the odom pose of the scan's frame (``depth_to_scan.output_frame``:
base_link's pose (+) :func:`slam.depth_to_scan.scan_frame_in_base`, as `live` pairs them), in one
pass over the frames. The mapper and the localiser work in the scan frame; the runners report
base_link poses through :func:`slam.depth_to_scan.base_pose`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from rgbdnav.config import Config, camera_mount, load_config
from rgbdnav.run_dir import RunDir
from sensors.carmen import CarmenSource
from sensors.recording_source import RecordingSource
from sensors.source import PoseStream, Source
from sensors.tum import write_tum_trajectory
from sensors.types import LaserScan, SensorError
from slam.depth_to_scan import scan_pose
from slam.front_end import FrontEnd, odom_origin, options_for, replay
from slam.geometry import oplus
from slam.metrics import drift_report

log = logging.getLogger(__name__)

RGBD_PROFILE = Path(__file__).resolve().parents[1] / "config" / "profiles" / "rgbd_mapping.yaml"
NAVIGATE_PROFILE = RGBD_PROFILE.with_name("navigate.yaml")  # localising on the robot's wheels
HANDHELD = (
    "a handheld camera (no wheel encoders and no /odom): a 2-D map needs a ground robot; pass "
    "--force-3dof if the camera rides on one"
)


def source_config(
    src: Source, config_files: Sequence[Path], overrides: Sequence[str]
) -> tuple[dict, list[Path], Config, dict]:
    """The source's scene (recordings), the config files with the RGB-D profile put first for
    depth-camera sources (yours still win), the config resolved over the recording's own
    robot description or a bag's /tf_static camera mount, and which of config / tf_static gave
    the camera extrinsics (for the run summary)."""
    scene = src.recording.scene if isinstance(src, RecordingSource) else {}
    base = {k: scene[k] for k in ("robot",) if isinstance(scene.get(k), dict)}
    files = list(config_files)
    if not isinstance(src, CarmenSource) and RGBD_PROFILE.is_file():
        files = [RGBD_PROFILE, *files]
    base, extrinsics = camera_mount(src, files, overrides, base)
    return scene, files, load_config(files, overrides, base=base), extrinsics


def scan_stream(
    src: Source,
    source_path: Path,
    cfg: Config,
    run: RunDir,
    summary: dict,
    outputs: dict[str, Path],
    force_3dof: bool = False,
    stop: Callable[[], bool] | None = None,
) -> tuple[Iterator[tuple[LaserScan, np.ndarray]], int, str, np.ndarray]:
    """(scan, odometry pose of the scan's frame) pairs, their count, the frame reported poses
    are of ("laser" for a laser log, else "base_link"), and the scan frame's pose in that frame
    (:func:`slam.depth_to_scan.base_pose` turns the mapper's and localiser's poses into it).
    The stream ends early, as if the source had, once ``stop()`` is true after a pair (an
    interrupted run still writes ``odom.tum`` and its summary of what it read)."""
    stop = stop or (lambda: False)
    if isinstance(src, CarmenSource):
        odo = src.laser_poses()
        if odo is None:
            raise SensorError(f"{source_path}: the log has no laser scans")
        scans = list(src.scans())
        return _with_poses(scans, odo, stop), len(scans), "laser", np.zeros(3)
    if src.intrinsics() is not None:
        return _rgbd_stream(src, source_path, cfg, run, summary, outputs, force_3dof, stop)
    raise SensorError(
        f"{source_path}: cannot map this source: it needs laser scans with odometry (CARMEN) or "
        "RGB-D frames (with wheel encoders, /odom, or --force-3dof for VO alone)"
    )


def _with_poses(
    scans: Sequence[LaserScan], odo: PoseStream, stop: Callable[[], bool]
) -> Iterator[tuple[LaserScan, np.ndarray]]:
    for k, scan in enumerate(scans):
        yield scan, np.array([odo.x[k], odo.y[k], odo.yaw[k]])
        if stop():
            return


def _rgbd_stream(
    src: Source,
    source_path: Path,
    cfg: Config,
    run: RunDir,
    summary: dict,
    outputs: dict[str, Path],
    force_3dof: bool,
    stop: Callable[[], bool],
) -> tuple[Iterator[tuple[LaserScan, np.ndarray]], int, str, np.ndarray]:
    opts = options_for(src, True, force_3dof, cfg.camera.rate)
    if not opts.planar:
        raise SensorError(f"{source_path}: {HANDHELD}")
    fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, opts)
    start = odom_origin(src)
    n = len(src.stream_stamps().get("depth", ()))
    summary["odometry_source"] = "front end: EKF (" + ", ".join(fe.inputs) + ")"
    outputs["odometry"] = run.file("odom.tum")

    def gen() -> Iterator[tuple[LaserScan, np.ndarray]]:
        timed_out = 0
        stamps, poses = [], []
        for step in replay(src, fe):
            if step.odom is None or step.scan is None:
                continue  # no input has reached the filter yet: counted by the front end
            timed_out += step.timed_out
            p = step.odom.pose
            odom = oplus([start.x, start.y, start.yaw], [p.x, p.y, p.yaw])
            stamps.append(step.stamp_ns)
            poses.append(odom)
            yield step.scan, scan_pose(odom, fe.scan_in_base)
            if stop():
                break
        a = np.array(poses, np.float64).reshape(-1, 3)
        write_tum_trajectory(
            run.file("odom.tum"), np.array(stamps, np.int64), a[:, 0], a[:, 1], a[:, 2]
        )
        gt = src.groundtruth()
        if gt is not None and gt.frame == "base_link" and len(a):
            summary["odometry_vs_groundtruth"] = drift_report(
                np.array(stamps, np.int64),
                (a[:, 0], a[:, 1], a[:, 2]),
                gt.stamps_ns,
                (gt.x, gt.y, gt.yaw),
            ).as_dict()
        assert fe.ekf is not None
        summary["front_end"] = {
            "inputs": list(fe.inputs),
            "ekf": fe.ekf.stats,
            "frames_timed_out": timed_out,
            "counts": dict(sorted(fe.counts.items())),
        }

    return gen(), n, "base_link", fe.scan_in_base


__all__ = ["HANDHELD", "RGBD_PROFILE", "scan_stream", "source_config"]
