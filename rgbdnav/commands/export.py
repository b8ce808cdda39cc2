"""`rgbdnav export RUN_DIR --to mcap`: a run folder as a rosbag2/MCAP folder for Foxglove and RViz.

What each kind of run holds (``summary.json``'s ``command``) and what it becomes:

    map / live   trajectory.tum (map -> base_link), odom.tum when the source had odometry,
                 the bundle in map/ (grid, keyframe scans and odometry poses); live runs also
                 trajectory_optimised.tum (the Path) and a --record recording with images
    localize     trajectory.tum in the map named in summary.json, odom.tum (RGB-D sources)
    navigate     estimated.tum (what the robot believed; trajectory.tum is the simulator's truth)
    odometry     fused.tum (EKF) or trajectory.tum (wheels): odom -> base_link, no map frame

``map -> odom`` is what a ROS stack would have published: the map pose composed with the
inverse odometry pose at each stamp. Without a dense odometry track, the bundle's keyframe
odometry poses give it at keyframes and it is held between them (as slam_toolbox publishes
it); with no odometry at all it is the identity. Either way ``map -> odom -> base_link``
reproduces the run's trajectory at every one of its stamps. Scans are the bundle's keyframe
scans; colour images come from the run's recording (``live --record``) or from the recording
the run was made from, when it still exists, with the registered depth beside them.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rgbdnav.config import load_config
from sensors.atomic import commit_staging_dir, make_staging_dir
from sensors.recording import intrinsics_from_scene
from sensors.ros_export import (
    BagContent,
    GridMessage,
    ImageStream,
    OdometryTrack,
    PlanarTrack,
    StaticTransform,
    quaternion_rpy,
    write_mcap_bag,
)
from sensors.tum import load_tum_trajectory, read_stamped_text, yaw_from_quaternion
from sensors.types import SensorError
from slam.depth_to_scan import scan_frame_in_base
from slam.geometry import ominus, oplus, wrap_angle
from slam.map_bundle import load_bundle, load_map
from slam.metrics import interpolate_poses

log = logging.getLogger(__name__)

FORMATS = ("mcap",)
DEFAULT_OUT = "rosbag2"  # inside the run folder
PATH_TOPIC = "/trajectory"  # nav_msgs/Path of the (optimised) trajectory
MAP_FRAME, ODOM_FRAME, BASE_FRAME = "map", "odom", "base_link"
CAMERA_FRAME, OPTICAL_FRAME, LASER_FRAME = "camera_link", "camera_color_optical_frame", "laser"
# camera_link (x forward, z up) -> optical frame (z forward, x right, y down), REP-103.
OPTICAL_RPY = (-math.pi / 2, 0.0, -math.pi / 2)


@dataclass(frozen=True)
class RunLayout:
    """Where a kind of run keeps its tracks (file names in the run folder, first found wins)."""

    map_track: tuple[str, ...]  # map -> base_link; () for runs without a map frame
    odom_track: tuple[str, ...]  # odom -> base_link
    path_track: tuple[str, ...]
    bundle: bool  # the run saved a bundle in map/


LAYOUTS = {
    "map": RunLayout(("trajectory.tum",), ("odom.tum",), ("trajectory.tum",), True),
    "live": RunLayout(
        ("trajectory.tum",), ("odom.tum",), ("trajectory_optimised.tum", "trajectory.tum"), True
    ),
    "localize": RunLayout(("trajectory.tum",), ("odom.tum",), ("trajectory.tum",), False),
    "navigate": RunLayout(("estimated.tum",), (), ("estimated.tum",), False),
    "odometry": RunLayout(
        (), ("fused.tum", "trajectory.tum"), ("fused.tum", "trajectory.tum"), False
    ),
}


def _summary(run: Path) -> dict[str, Any]:
    if not run.is_dir():
        raise SensorError(f"{run}: no such run folder")
    file = run / "summary.json"
    if not file.is_file():
        raise SensorError(f"{run}: not a finished rgbdnav run (no summary.json)")
    try:
        summary = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        # RecursionError: "[[[[..." nested deeper than the JSON decoder's stack
        raise SensorError(f"{file}: unreadable summary ({str(err)[:120]})") from None
    if not isinstance(summary, dict):
        raise SensorError(f"{file}: not a run summary (a JSON object)")
    return summary


def _track(run: Path, names: tuple[str, ...], parent: str, child: str) -> PlanarTrack | None:
    for name in names:
        if (run / name).is_file():
            stamps, xyz, quat = load_tum_trajectory(run / name)
            if len(stamps) == 0:
                raise SensorError(f"{run / name}: no poses")
            poses = np.column_stack([xyz[:, :2], yaw_from_quaternion(quat)])
            return PlanarTrack(parent, child, stamps, poses)
    return None


def _inverse(p: np.ndarray) -> np.ndarray:
    return ominus(p, np.zeros(3))


def _chain(
    map_base: PlanarTrack, odom_base: PlanarTrack | None, bundle: Any | None
) -> tuple[PlanarTrack, PlanarTrack]:
    """(map -> odom, odom -> base_link) at the stamps of ``map_base``, so that their
    composition is ``map_base`` (see the module doc for where odometry comes from)."""
    t = map_base.stamps_ns
    if odom_base is not None:
        o = odom_base.poses
        x, y, yaw, _ = interpolate_poses(odom_base.stamps_ns, o[:, 0], o[:, 1], o[:, 2], t)
        odom = np.column_stack([x, y, wrap_angle(yaw)])
        map_odom = oplus(map_base.poses, _inverse(odom))
    elif bundle is not None and len(bundle.keyframe_stamps_ns):
        key = oplus(bundle.keyframe_poses, _inverse(bundle.keyframe_odom_poses))
        k = np.clip(np.searchsorted(bundle.keyframe_stamps_ns, t, side="right") - 1, 0, None)
        map_odom = key[k]
    else:
        map_odom = np.zeros((len(t), 3))
    odom = oplus(_inverse(map_odom), map_base.poses)
    return (
        PlanarTrack(MAP_FRAME, ODOM_FRAME, t, map_odom),
        PlanarTrack(ODOM_FRAME, BASE_FRAME, t, odom),
    )


def _twist(track: PlanarTrack) -> np.ndarray:
    """(N, 2) forward speed [m/s] and yaw rate [rad/s] in base_link, by backward differences
    (the first pose gets the second's)."""
    if len(track.stamps_ns) < 2:
        return np.zeros((len(track.stamps_ns), 2))
    d = ominus(track.poses[:-1], track.poses[1:])
    dt = np.diff(track.stamps_ns).astype(np.float64) / 1e9
    v = np.column_stack([d[:, 0] / dt, d[:, 2] / dt])
    return np.vstack([v[:1], v])


def _static(cfg: Any, has_camera: bool) -> list[StaticTransform]:
    """The mounts; ``laser`` is where a depth scan was taken (depth_to_scan.output_frame)."""
    r = cfg.robot
    at = scan_frame_in_base(r, cfg.depth_to_scan) if has_camera else np.zeros(3)
    laser = (float(at[0]), float(at[1]), 0.0)
    out = [StaticTransform(BASE_FRAME, LASER_FRAME, laser, (0.0, 0.0, 0.0, 1.0))]
    if has_camera:
        out += [
            StaticTransform(
                BASE_FRAME,
                CAMERA_FRAME,
                (r.camera_x, r.camera_y, r.camera_height),
                quaternion_rpy(r.camera_roll, r.camera_pitch, 0.0),
            ),
            StaticTransform(
                CAMERA_FRAME, OPTICAL_FRAME, (0.0, 0.0, 0.0), quaternion_rpy(*OPTICAL_RPY)
            ),
        ]
    return out


def _os_ok(check: Callable[[], bool]) -> bool:
    """``check()`` (a Path's is_file / exists), False rather than OSError for a path a summary
    names that the OS cannot even look up (too long: ENAMETOOLONG; pathlib ignores only the
    ENOENT-like errors)."""
    try:
        return check()
    except OSError:
        return False


def _recording_folder(run: Path, summary: dict[str, Any]) -> Path | None:
    """The recording holding the run's camera images: ``live --record``'s, else the source."""
    rec = summary.get("recording")
    candidates = [rec.get("path") if isinstance(rec, dict) else None, summary.get("source")]
    candidates += [str(p.parent) for p in sorted(run.glob("*/rgb.txt"))]
    for c in candidates:
        if isinstance(c, str) and _os_ok((Path(c) / "rgb.txt").is_file):
            return Path(c)
    return None


def _images(folder: Path, t0: int, t1: int) -> ImageStream | None:
    """The recording's colour and depth images stamped within the run's span [t0, t1]."""
    import yaml

    try:
        scene = yaml.safe_load((folder / "scene.yaml").read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise SensorError(f"{folder / 'scene.yaml'}: unreadable ({err})") from err
    intrinsics = intrinsics_from_scene(scene or {}, str(folder / "scene.yaml"))
    streams = []
    for index in ("rgb.txt", "depth.txt"):
        table = read_stamped_text(folder / index, ("timestamp", "filename"))
        keep = (table.stamps_ns >= t0) & (table.stamps_ns <= t1)
        files = [folder / row[0] for row, k in zip(table.values, keep, strict=True) if k]
        streams.append((table.stamps_ns[keep], files))
    (rgb_t, rgb_files), (depth_t, depth_files) = streams
    if not rgb_files:
        return None
    return ImageStream(rgb_t, rgb_files, OPTICAL_FRAME, intrinsics, depth_t, depth_files)


def run_content(run: Path, images: bool = True) -> tuple[BagContent, dict[str, Any]]:
    """What ``run`` holds, as messages to write; and a description for the user."""
    summary = _summary(run)
    command = summary.get("command")
    layout = LAYOUTS.get(command) if isinstance(command, str) else None
    if layout is None:
        raise SensorError(
            f"{run}: nothing to export from a {command or 'unknown'} run; "
            f"export runs of {', '.join(LAYOUTS)}"
        )
    map_base = _track(run, layout.map_track, MAP_FRAME, BASE_FRAME)
    odom_base = _track(run, layout.odom_track, ODOM_FRAME, BASE_FRAME)
    main = map_base or odom_base
    if main is None:
        wanted = " or ".join(layout.map_track or layout.odom_track)
        raise SensorError(f"{run}: a {command} run without {wanted}: nothing to export")
    path_track = _track(run, layout.path_track, main.parent, BASE_FRAME) or main
    if not (run / "config.yaml").is_file():
        log.warning("%s: no config.yaml; /tf_static gets the default robot's camera mount", run)
    cfg = load_config([run / "config.yaml"] if (run / "config.yaml").is_file() else [])
    t0, t1 = int(main.stamps_ns[0]), int(main.stamps_ns[-1])
    bundle = grid_msg = None
    values: np.ndarray | None = None
    if layout.bundle:
        bundle = load_bundle(run / "map")
        values = bundle.grid.trinary(bundle.occupied_thresh, bundle.free_thresh)
        grid = bundle.grid
    else:
        grid, values = _used_map(summary)
    if grid is not None and values is not None:
        g = grid.geometry
        grid_msg = GridMessage(t0, MAP_FRAME, g.resolution, (g.origin_x, g.origin_y), values)
    if map_base is not None:
        transforms = list(_chain(map_base, odom_base, bundle))
        odom_track = odom_base or transforms[1]
    else:
        odom_track, transforms = main, [main]  # main is odom_base here
    has_camera = summary.get("frame", BASE_FRAME) != LASER_FRAME  # laser logs have no camera
    rec = _recording_folder(run, summary) if images and has_camera else None
    content = BagContent(
        transforms=transforms,
        static=_static(cfg, has_camera),
        static_stamp_ns=t0,
        grid=grid_msg,
        scans=bundle.scans if bundle is not None else (),
        scan_frame=LASER_FRAME,
        odometry=OdometryTrack(odom_track, _twist(odom_track)),
        paths={PATH_TOPIC: path_track},
        images=_images(rec, t0, t1) if rec is not None else None,
    )
    return content, {"command": command, "recording": rec}


def _used_map(summary: dict[str, Any]) -> tuple[Any, np.ndarray | None]:
    """The grid a localize/navigate run used (named in its summary) and its nav_msgs values."""
    entry = summary.get("map")
    path = entry.get("path") if isinstance(entry, dict) else entry
    if not isinstance(path, str):
        return None, None
    if not _os_ok(Path(path).exists):
        log.warning("%s: the map this run used is gone; no /map in the bag", path)
        return None, None
    loaded = load_map(Path(path))
    return loaded.grid, loaded.grid.trinary(loaded.occupied_thresh, loaded.free_thresh)


def run_export(run: Path, to: str, out: Path | None, images: bool = True) -> dict[str, Any]:
    """Write ``run`` as a rosbag2 folder at ``out`` (default ``RUN/rosbag2``), atomically: into a
    staging folder beside it, renamed over an earlier export only once complete."""
    if to not in FORMATS:
        raise SensorError(f"--to {to}: unknown format; choose from {', '.join(FORMATS)}")
    out = out if out is not None else run / DEFAULT_OUT
    if out.exists() and not (out / "metadata.yaml").is_file():
        raise SensorError(f"{out}: exists and is not a rosbag2 folder; not overwriting it")
    content, about = run_content(run, images)
    # rosbags' Writer creates the bag folder and names the .mcap after it: write OUT.name inside
    # a staging folder beside OUT, then rename it into place.
    staging = make_staging_dir(out)
    try:
        counts = write_mcap_bag(content, staging / out.name)
        commit_staging_dir(staging / out.name, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {"out": out, "counts": counts, **about}


__all__ = ["FORMATS", "LAYOUTS", "run_content", "run_export"]
