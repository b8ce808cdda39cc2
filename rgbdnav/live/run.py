"""`rgbdnav live`: the robot's camera and control board, the front end, the mapper (or the
localiser against a saved map) and visualisation, all running at once in real time.

Threads, each with its own bounded queue, so a slow consumer can only lose its own work:

1. **board**: :class:`sensors.eddie.OdometryPoller` polls DIST at ``board.poll_rate``; the driver's
   host watchdog sends STOP when velocity commands stop (``board.watchdog_timeout``).
2. **camera**: frames from the adapter (the simulated robot, or OpenNI2) into the frame queue; a
   frame that finds the queue full is dropped and counted (``frames_dropped_front_end``).
3. **front end**: wheel ticks and VO into the EKF (``odom -> base_link``), depth -> scan; the
   scan with its odometry pose goes to the mapper queue. A camera silent for
   ``live.camera_stall_timeout`` is a stall: counted, warned, and the mapper simply waits.
4. **mapper** (or localiser): ``map -> odom``; the map bundle is checkpointed every
   ``live.checkpoint_period`` and on exit, atomically.
5. **controller** at ``live.control_rate``: drives the route/goals (``--drive route``) on the
   estimated pose, or holds still (``--drive idle``); GOSPD through the driver. The waypoints are
   goals for the navigation stack (:mod:`rgbdnav.live.nav`; ``live.route_driver: nav``, the
   default) or steered at straight (``direct``); the collision monitor has the last word.
6. **visualiser**: rerun on its own thread; dropped first when the machine falls behind.

Nothing grows with the run's length except the map: latency samples are a bounded reservoir,
trajectories are streamed to ``odom.tum``, ``trajectory.tum``, ``groundtruth.tum`` with thinned
copies in memory for drawing (``live.stats_reservoir``, ``live.track_decimation``).
SIGINT and SIGTERM end the run cleanly (motors stopped, final checkpoint, summary); after a
``kill -9`` the last checkpoint in ``OUT/map`` is a complete bundle for ``map --continue``.
"""

from __future__ import annotations

import logging
import math
import queue
import resource
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import yaml

from nav.collision_monitor import CollisionMonitor
from nav.teleop import TeleopState, teleop_key
from rgbdnav.config import (
    Config,
    camera_mount,
    initial_pose_array,
    load_config,
    section_to_dict,
    source_options,
)
from rgbdnav.live.nav import LiveNavigator, MapSnapshot
from rgbdnav.live.record import LiveRecorder
from rgbdnav.live.stats import (
    FrameWindows,
    Reservoir,
    Timeline,
    TrackWriter,
    load_track,
    tame_malloc,
)
from rgbdnav.report import gps_chart, plot_trajectories
from rgbdnav.run_dir import RunDir
from rgbdnav.scan_stream import NAVIGATE_PROFILE, RGBD_PROFILE
from rgbdnav.stop_signals import StopSignals
from rgbdnav.visualize import AsyncVisualizer, NullVisualizer, make_visualizer, occupied_cells_xy
from sensors.boards import OpenedBoard, open_board
from sensors.eddie import OdometryPoller
from sensors.geo import GeoAnchor, read_geo_anchor
from sensors.gps import (
    GPS_TXT,
    GpsFix,
    GpsStream,
    GpsWriter,
    SimGpsConfig,
    SimGpsReceiver,
    antenna_xy,
    read_gps_txt,
)
from sensors.motor_board import MotorBoard
from sensors.source import Source, open_source
from sensors.tum import write_tum_trajectory
from sensors.types import ConfigError, RgbdFrame, RgbdNavError, SensorError, WheelTicks
from slam.depth_to_scan import base_pose, scan_frame_in_base, scan_pose
from slam.fleet import FleetRobot, load_fleet
from slam.front_end import FrontEnd, FrontEndOptions, MessageFeed
from slam.geometry import ominus, oplus, path_length
from slam.localization import GpsPrior
from slam.map_bundle import load_map_yaml, save_bundle
from slam.mapper import Mapper, build_grid, make_bundle
from slam.metrics import drift_summary
from slam.scan_matching import scan_points, transform_points

log = logging.getLogger(__name__)

DRILLS = ("unplug_board", "replug_board", "stall_camera")
JOIN_TIMEOUT_S = 30.0  # [s] a thread that does not finish its queue by then is reported
MIN_LATENCIES = 1  # percentiles need at least one processed frame
SIM_WHEELS_PERIOD_S = 0.01  # [s] --board emulator:KIND: wheel travel to the simulated robot
MODE_SWITCH_KEY = "\t"  # Tab: manual (teleop keys) <-> auto (route)
GIL_SWITCH_INTERVAL_S = 0.001  # [s] (Python's default 0.005)
MEMORY_SAMPLE_S = 5.0  # [s] resident memory is sampled this often for the summary
GPS_QUEUE_SIZE = 16  # fixes waiting for the localiser (1 Hz: a stalled localiser keeps the newest)


def _interactive() -> bool:
    return sys.stdin is not None and sys.stdin.isatty()


def rss_mb() -> float:
    """Resident memory of this process now [MB] (Linux; NaN elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return math.nan


@dataclass(frozen=True)
class Drill:
    """A scheduled fault for the simulated robot: ``action@seconds[:argument]``."""

    at_s: float
    action: str
    arg: float = 0.0

    @staticmethod
    def parse(text: str) -> Drill:
        action, sep, rest = text.partition("@")
        when, _, arg = rest.partition(":")
        try:
            at_s, value = float(when), float(arg) if arg else 0.0
        except ValueError:
            at_s = value = math.nan
        if action not in DRILLS or not sep or not math.isfinite(at_s) or not math.isfinite(value):
            raise ConfigError(
                f"--drill {text!r}: expected ACTION@SECONDS[:ARG] with ACTION one of "
                f"{', '.join(DRILLS)}, e.g. unplug_board@5 or stall_camera@10:2"
            )
        return Drill(at_s, action, value)


@dataclass(frozen=True)
class LiveOptions:
    out: Path
    camera: str = "sim"  # "sim" or a camera URI/recording: openni://, realsense://, freenect://
    joystick: str | None = None  # /dev/input/eventN: evdev joystick teleop (nav.joystick)
    board: str = "sim"  # "sim", a device spec (sensors.motor_board), emulator:KIND, or "none"
    world: Path | None = None  # simulator world (camera or board "sim")
    config_files: Sequence[Path] = ()
    overrides: Sequence[str] = ()
    map_bundle: Path | None = None  # localisation-only against this map
    duration_s: float | None = None  # None: until SIGINT/SIGTERM
    drive: str = "route"  # "route" (auto: live.route_driver) | "teleop" | "idle"
    goals: Sequence[tuple[float, float]] = ()  # route for --drive route (default: the world's)
    rrd: Path | None = None
    viewer: bool = False
    seed: int = 0
    drills: Sequence[Drill] = ()
    repeat_route: bool = False  # drive the route again and again (soak runs)
    record: Path | None = None  # write the frames and encoder readings as a recording here
    initial_pose: tuple[float, float, float] | None = None  # --map: start tracking here (map)
    robot: str | None = None  # this robot's name in a fleet (the run is in OUT/NAME)
    start: tuple[float, float, float] | None = None  # simulated robot's start in the world
    fleet: Path | None = None  # fleet.yaml: this robot's map, T_world_map and keepout


class Counters:
    """Thread-safe event counts for the summary."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._c: Counter[str] = Counter()

    def inc(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._c[name] += n

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return dict(sorted(self._c.items()))


@dataclass
class _Shared:
    """State handed between threads (each field written by one thread, read under the lock)."""

    monitor: CollisionMonitor  # recent scans, the last word on every command
    lock: threading.Lock = field(default_factory=threading.Lock)
    odom: np.ndarray | None = None  # latest odom -> base_link
    map_to_odom: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tracking: bool = True  # the pose in the map is trustworthy (localiser: tracking)

    def pose_in_map(self) -> np.ndarray | None:
        with self.lock:
            return None if self.odom is None else oplus(self.map_to_odom, self.odom)


# --- driving ----------------------------------------------------------------------------------


def route_command(
    pose: np.ndarray,
    target: np.ndarray,
    max_v: float,
    max_w: float,
    turn_in_place: float,
    heading_gain: float,
) -> tuple[float, float]:
    """(v, w) towards ``target``: turn in place while the heading error exceeds
    ``turn_in_place`` [rad], otherwise drive while steering, slowing with cos(error)."""
    dx, dy = float(target[0] - pose[0]), float(target[1] - pose[1])
    err = math.atan2(math.sin(math.atan2(dy, dx) - pose[2]), math.cos(math.atan2(dy, dx) - pose[2]))
    w = max(-max_w, min(max_w, heading_gain * err))
    if abs(err) > turn_in_place:
        return 0.0, w
    return max_v * math.cos(err), w


# --- the run ----------------------------------------------------------------------------------


LIVE_PROFILE = RGBD_PROFILE.with_name("live.yaml")  # real-time front-end settings


class LiveRun:
    def __init__(self, opts: LiveOptions) -> None:
        self.fleet_robot: FleetRobot | None = None
        if opts.fleet is not None:
            opts = self._with_fleet_map(opts)
        self.opts = opts
        # Depth scans: the RGB-D mapping profile; localising (--map) on the robot's own wheels:
        # the navigate profile too, as `rgbdnav navigate` loads them; real time: the live
        # profile (optical-flow VO); yours win.
        profiles = [RGBD_PROFILE] + ([NAVIGATE_PROFILE] if opts.map_bundle is not None else [])
        profiles.append(LIVE_PROFILE)
        files = [p for p in profiles if p.is_file()] + list(opts.config_files)
        cfg = load_config(files, opts.overrides)
        # Frames reach the EKF later than wheel ticks (render, queue, VO): it must re-filter
        # lagged data (robot_localization's smooth_lagged_data) instead of dropping it.
        history = max(cfg.ekf.history_length, cfg.live.ekf_history_length)
        self.cfg: Config = replace(
            cfg, ekf=replace(cfg.ekf, smooth_lagged_data=True, history_length=history)
        )
        self.config_files = files
        if opts.drive not in ("route", "idle", "teleop"):
            raise ConfigError(f"--drive {opts.drive!r}: expected route, teleop or idle")
        if (opts.camera == "sim" or opts.board == "sim") and opts.world is None:
            raise ConfigError("--camera sim / --board sim need --sim-world WORLD.yaml")
        if opts.drills and opts.camera != "sim":
            raise ConfigError("--drill needs the simulated robot (--camera sim --board sim)")
        self.initial_pose: np.ndarray | None = None
        if opts.initial_pose is not None:
            if opts.map_bundle is None:
                raise ConfigError("--initial-pose places the robot in a saved map: give --map")
            self.initial_pose = initial_pose_array(opts.initial_pose)
        self.counts = Counters()
        self.stop = threading.Event()
        self.shared = _Shared(CollisionMonitor(self.cfg.collision_monitor, self.cfg.robot.radius))
        self.frame_q: queue.Queue[RgbdFrame | None] = queue.Queue(self.cfg.live.frame_queue_size)
        self._stall_lock = threading.Lock()
        self._stall_counted = False  # the stall under way is counted already
        self.scan_q: queue.Queue[tuple[Any, np.ndarray] | None] = queue.Queue(
            self.cfg.live.scan_queue_size
        )
        self.ticks_q: queue.Queue[WheelTicks] = queue.Queue()
        lc = self.cfg.live
        # Bounded, whatever the run's length (a soak runs for hours).
        self.latency_ms = Reservoir(lc.stats_reservoir, 1)  # frame stamp -> pose out
        self.arrival_ms = Reservoir(lc.stats_reservoir, 2)  # frame stamp -> frame in this process
        self.rss_timeline = Timeline()  # (seconds into the run, MB)
        self.frame_windows = FrameWindows()  # processed / dropped so far, window latency p99
        self.stage_ms = {
            k: Reservoir(lc.stats_reservoir, 3 + i)
            for i, k in enumerate(("wheels_ekf", "vo", "depth_to_scan", "mapper"))
        }
        self.errors: list[str] = []
        self.run = RunDir(opts.out)
        self.odom_track = TrackWriter(self.run.file("odom.tum"), lc.track_decimation)
        self.map_track = TrackWriter(self.run.file("trajectory.tum"), lc.track_decimation)
        self.navigator: LiveNavigator | None = None
        self._loaded_map: Any = None  # --map: the loaded map (the navigator's static layer)
        self._last_snapshot = -math.inf  # [s] monotonic time of the last map handed to it
        self.sim: Any = None
        self.camera_src: Source | None = None  # a camera other than the simulated robot
        self.extrinsics: dict[str, Any] = {"source": "config"}  # the camera mount's origin
        self.board: MotorBoard | None = None
        self._opened: OpenedBoard | None = None
        self.poller: OdometryPoller | None = None
        self.vis: Any = NullVisualizer()
        self.mapper: Mapper | None = None
        self.localizer: Any = None
        self._last_checkpoint = time.monotonic()
        self._checkpoint_lock = threading.Lock()
        # [s] monotonic: the first camera frame, and the devices up (the duration's clock).
        self._first_frame_at: float | None = None
        self._devices_up_at: float | None = None
        self.start_pose = np.zeros(3)  # [m, m, rad] in the map frame
        self.start_in_world: np.ndarray | None = None  # the simulated robot's
        self.route = np.zeros((0, 2))
        self.route_done = False
        self.keys: queue.Queue[str] = queue.Queue()  # terminal keys (tests put them here)
        self.mode = "manual" if opts.drive == "teleop" else "auto"
        self.joystick = None
        if opts.joystick is not None:
            from nav.joystick import JoystickTeleop

            if not opts.joystick.startswith("replay:"):  # a recording needs no evdev
                try:
                    import evdev  # noqa: F401
                except ImportError:
                    raise ConfigError(
                        "--joystick needs evdev: pip install 'rgbdnav[joystick]'"
                    ) from None

            # The mode button acts as the Tab key: the controller loop switches.
            self.joystick = JoystickTeleop(
                self.cfg.joystick, on_toggle=lambda: self.keys.put(MODE_SWITCH_KEY)
            )
        self.recorder: LiveRecorder | None = None
        self.front_end: FrontEnd | None = None
        if opts.record is not None:
            self.recorder = LiveRecorder(opts.record, self._recording_scene())
        # GPS: fixes from any receiver go to gps.txt and, in the map through its geo anchor,
        # to the localiser's global search (slam.localization.GpsPrior, as `localize --gps`).
        self.T_world_map, self.T_world_map_from = self._placement()
        self.gps_writer = GpsWriter(self.run.file(GPS_TXT))
        self.gps_source: str | None = None  # what gives the fixes: simulated, the camera's
        self.gps_q: queue.Queue[tuple[int, np.ndarray, float]] = queue.Queue(GPS_QUEUE_SIZE)
        self.map_anchor: GeoAnchor | None = None  # the run's map frame on WGS84
        self._sim_gps: SimGpsReceiver | None = None
        self._gps_prior: GpsPrior | None = None
        self._first_tracked: tuple[int, np.ndarray] | None = None  # (stamp, map -> odom)
        self._recorded_gps: GpsStream | None = None  # a recorded camera source's own fixes
        self._gps_pending: deque[GpsFix] | None = None

    def _with_fleet_map(self, opts: LiveOptions) -> LiveOptions:
        """This robot in its fleet file: it localises in its own map there (the map the fleet
        places in the world), unless told another map, which the fleet cannot place."""
        if opts.robot is None:
            raise ConfigError("--fleet needs --robot NAME: which robot of the fleet this is")
        robot = load_fleet(opts.fleet).robot(opts.robot)  # type: ignore[arg-type]
        self.fleet_robot = robot
        if opts.map_bundle is None:
            return replace(opts, map_bundle=robot.map_path)
        if Path(opts.map_bundle).resolve() != robot.map_path.resolve():
            raise ConfigError(
                f"--map {opts.map_bundle} is not robot {robot.name}'s map in {opts.fleet} "
                f"({robot.map_path}): the fleet places only that map in the world"
            )
        return opts

    def _placement(self) -> tuple[tuple[float, float, float] | None, str | None]:
        """Where this run's map frame sits in the world (``world -> NAME/map``) and who says
        so: the fleet file (its T_world_map, or its geo anchors), or the simulator (a simulated
        robot is told its true start, so the frame of a map it makes is the world frame)."""
        if self.fleet_robot is not None:
            return self.fleet_robot.T_world_map, f"{self.opts.fleet}: {self.fleet_robot.placed_by}"
        if self.opts.camera == "sim" or self.opts.board == "sim":
            return (0.0, 0.0, 0.0), "simulator"
        return None, None

    def _recording_scene(self) -> dict[str, Any]:
        """``scene.yaml`` of a ``--record`` recording: what ``map``/``odometry`` need to read
        it as this robot saw it, and the simulated world to score a map against."""
        cfg, opts = self.cfg, self.opts
        scene: dict[str, Any] = {
            "generator": "rgbdnav live",
            "camera_source": opts.camera,
            "groundtruth_frame": "base_link",
            "robot": section_to_dict(cfg.robot),
            "camera": section_to_dict(cfg.camera),
        }
        if opts.camera == "sim" and opts.world is not None:
            world = Path(opts.world)
            scene |= {
                "world": world.stem,
                "world_file": str(world),
                "world_description": yaml.safe_load(world.read_text()),
                "seed": opts.seed,
                "sim": section_to_dict(cfg.sim),
            }
        return scene

    def _robot_frame(self) -> dict[str, Any]:
        """Who this robot is and where its map sits in the world (``world -> NAME/map``). The
        simulated robot is told its true start, so its map frame is the world frame; a real
        robot's map frame is placed by its fleet file (``--fleet``), else unknown (null)."""
        simulated = self.sim is not None
        own_map = self.opts.map_bundle is None
        keepout = None if self.fleet_robot is None else self.fleet_robot.keepout_path
        return {
            "name": self.opts.robot,
            "start_in_world": (
                self.start_in_world.tolist()
                if simulated and self.start_in_world is not None
                else None
            ),
            "T_world_map": None if self.T_world_map is None else list(self.T_world_map),
            "T_world_map_from": self.T_world_map_from,
            "map": str(
                self.run.file("map")
                if own_map
                else Path(cast(Path, self.opts.map_bundle)).resolve()
            ),
            "keepout": None if keepout is None else str(keepout),
        }

    # 1. Start: the simulated robot (if any), the board, the camera adapter.

    def _start_devices(self) -> Iterator[RgbdFrame]:
        opts, cfg = self.opts, self.cfg
        sim_port = ""
        if opts.camera == "sim" or opts.board == "sim":
            from sensors.sim.live import SimRobot
            from sensors.sim.world import check_start, load_world

            world = load_world(opts.world)  # type: ignore[arg-type]
            if opts.start is not None:
                check_start(world, opts.start, "--start")
                world = replace(world, start=opts.start)
            # The start and the route are in the world; the robot drives in its map frame.
            self.start_in_world = np.array(world.start, dtype=np.float64)
            self.start_pose = self._in_map(self.start_in_world)
            route = (
                np.asarray(opts.goals, dtype=np.float64).reshape(-1, 2)
                if opts.goals
                else world.route
            )
            self.route = self._in_map(np.column_stack([route, np.zeros(len(route))]))[:, :2]
            if world.geo is not None and opts.camera == "sim":  # at robot.gps_x / gps_y
                self._sim_gps = SimGpsReceiver(
                    world.geo, SimGpsConfig.from_sim(cfg.sim), seed=opts.seed
                )
                self.gps_source = "simulated receiver"
            self._set_map_anchor(world.geo)
            self.sim = SimRobot(
                opts.world,  # type: ignore[arg-type]
                cfg.robot,
                cfg.camera,
                cfg.sim,
                self.run.file("board.pty"),
                seed=opts.seed,
                truth_path=self.run.file("groundtruth.tum"),
                external_wheels=opts.board.startswith("emulator:"),
                start=opts.start,
            )
            sim_port = self.sim.start()
        else:
            self.route = np.asarray(opts.goals, dtype=np.float64).reshape(-1, 2)
            self._set_map_anchor(None)
        if opts.drive != "idle" and cfg.live.route_driver == "nav" and len(self.route):
            loaded = self._loaded_map
            static = (
                None
                if loaded is None
                else (loaded.grid, loaded.occupied_thresh, loaded.free_thresh)
            )
            keepout_path = None if self.fleet_robot is None else self.fleet_robot.keepout_path
            self.navigator = LiveNavigator(
                cfg,
                self.route,
                self.start_pose,
                opts.repeat_route,
                static,
                keepout=None if keepout_path is None else load_map_yaml(keepout_path),
            )
            self.navigator.start()
        spec = sim_port if opts.board == "sim" else opts.board
        if opts.board != "none":
            self._opened = open_board(spec, cfg)
            self.board = self._opened.board
            if self.sim is not None and self.sim.wheels is not None:
                # The simulated robot moves by this emulator's wheels (--board emulator:KIND).
                threading.Thread(
                    target=self._turn_sim_wheels, name="sim-wheels", daemon=True
                ).start()
            if cfg.live.board_kill_switch:
                # The board's own failsafe stops the motors if this host dies or the cable
                # goes; the driver's watchdog covers a host that lives but stops commanding.
                try:
                    log.info("failsafe: %s", self.board.arm_failsafe(cfg.live.board_kill_switch))
                except SensorError as err:
                    log.warning("could not arm the board's failsafe: %s", err)
            self.poller = OdometryPoller(
                self.board, cfg.board, callback=self.ticks_q.put, read_speed_heading=False
            )
        if opts.camera == "sim":
            self._start_gps_prior()
            return self._sim_frames()
        # realtime: a device recording plays at its own pace, stamped like a camera.
        self.camera_src = open_source(opts.camera, replace(source_options(cfg), realtime=True))
        self._take_camera_mount(self.camera_src)
        gps_of = getattr(self.camera_src, "gps", None)
        gps = gps_of() if callable(gps_of) else None
        if gps is not None and len(gps):  # NavSatFix in a bag, gps.txt in a recording
            self._recorded_gps = gps
            self.gps_source = "camera source"
        self._start_gps_prior()
        return iter(self.camera_src.frames())

    def _take_camera_mount(self, src: Source) -> None:
        """The camera's own mount (a Kinect's accelerometer pitch) under the user's config keys,
        as the offline commands take a bag's /tf_static: before the front end starts."""
        base, self.extrinsics = camera_mount(src, self.config_files, self.opts.overrides)
        if self.extrinsics["source"] == "config":
            return
        robot = load_config(self.config_files, self.opts.overrides, base=base).robot
        self.cfg = replace(self.cfg, robot=robot)
        self.run.write_config(self.cfg)  # the run's config.yaml says what the run used
        if self.recorder is not None:  # its scene.yaml is written at the first frame
            self.recorder.scene["robot"] = section_to_dict(robot)
        log.info("camera mount from %s: %s", self.extrinsics["source"], self.extrinsics["chain"])

    # GPS: any receiver's fixes through one door (_on_gps_fix).

    def _in_map(self, world_poses: np.ndarray) -> np.ndarray:
        """World poses (..., 3) in this run's map frame (the simulator works in the world)."""
        if self.T_world_map is None:
            return world_poses
        return ominus(np.asarray(self.T_world_map), world_poses)

    def _set_map_anchor(self, world_geo: GeoAnchor | None) -> None:
        """The map frame's geo anchor: the map's own ``geo.yaml``, else its fleet entry's,
        else the simulated world's moved by ``T_world_map``."""
        anchor = None
        if self.opts.map_bundle is not None:
            anchor = read_geo_anchor(self.opts.map_bundle)
        if anchor is None and self.fleet_robot is not None:
            anchor = self.fleet_robot.geo
        if anchor is None and world_geo is not None and self.T_world_map is not None:
            moved = any(self.T_world_map)
            anchor = world_geo.moved(*self.T_world_map) if moved else world_geo
        self.map_anchor = anchor

    def _start_gps_prior(self) -> None:
        if self.localizer is None or self.gps_source is None or self._gps_prior is not None:
            return
        if self.map_anchor is None:
            log.warning("GPS fixes (%s) unused: the map has no geo anchor", self.gps_source)
            return
        mount = (self.cfg.robot.gps_x, self.cfg.robot.gps_y)
        self._gps_prior = GpsPrior(self.localizer, self._scan_in_base(), mount)

    def _on_gps_fix(self, fix: GpsFix) -> None:
        """A fix from any receiver: to gps.txt and, placed in the map, to the localiser."""
        self.gps_writer.add(fix)
        self.counts.inc("gps_fixes")
        if self._gps_prior is None or self.map_anchor is None:
            return
        x, y, _ = self.map_anchor.to_map(fix.latitude, fix.longitude, fix.altitude)
        try:
            self.gps_q.put_nowait((fix.stamp_ns, np.array([float(x), float(y)]), fix.sigma_m))
        except queue.Full:
            self.counts.inc("gps_fixes_dropped_localizer_behind")

    def _turn_sim_wheels(self) -> None:
        """Copy the host-side board emulator's wheel travel [positions] to the simulated robot."""
        emu = self._opened.emulator if self._opened is not None else None
        while emu is not None and not self.stop.wait(SIM_WHEELS_PERIOD_S):
            wheels = self.sim.wheels if self.sim is not None else None
            if wheels is None:
                return
            wheels[:] = emu.wheel_positions()

    def _sim_frames(self) -> Iterator[RgbdFrame]:
        assert self.sim is not None and self.sim.intrinsics is not None
        while not self.stop.is_set():
            msg = self.sim.next_frame(timeout_s=0.1)
            if msg is None:
                yield None  # type: ignore[misc]  # lets the camera thread notice a stall
                continue
            if self._sim_gps is not None:
                mount = (self.cfg.robot.gps_x, self.cfg.robot.gps_y)
                x, y, yaw = (float(v) for v in msg.true_pose[:3])
                fix = self._sim_gps.update(msg.stamp_ns, *antenna_xy(x, y, yaw, mount))
                if fix is not None:
                    self._on_gps_fix(fix)
            yield RgbdFrame(msg.stamp_ns, msg.rgb, msg.depth_m, self.sim.intrinsics)

    # 2. The threads.

    def _camera_loop(self, frames: Iterator[RgbdFrame | None]) -> None:
        last_arrival: float | None = None
        try:
            for frame in frames:
                if self.stop.is_set():
                    break
                if frame is None:
                    continue
                arrival = time.monotonic()
                if self._first_frame_at is None:
                    self._first_frame_at = arrival
                gap = 0.0 if last_arrival is None else arrival - last_arrival
                last_arrival = arrival
                self._note_camera_gap(gap)
                if self._recorded_gps is not None:
                    self._replay_gps(frame.stamp_ns)
                self.counts.inc("frames_received")
                self.arrival_ms.add((time.monotonic_ns() - frame.stamp_ns) / 1e6)
                try:
                    self.frame_q.put_nowait(frame)
                except queue.Full:
                    self.counts.inc("frames_dropped_front_end")
        except SensorError as err:
            self.errors.append(f"camera: {err}")
            log.error("camera failed: %s", err)
        finally:
            self.frame_q.put(None)

    def _note_camera_gap(self, gap_s: float, waiting: bool = False) -> None:
        """Count a camera stall once: seen by the front end waiting on an empty queue, or by the
        camera thread when a frame comes after a gap (a front end behind on queued frames
        cannot see the stall; the camera's arrivals can)."""
        with self._stall_lock:
            if gap_s >= self.cfg.live.camera_stall_timeout and not self._stall_counted:
                self.counts.inc("camera_stalls")
            self._stall_counted = waiting

    def _replay_gps(self, stamp_ns: int) -> None:
        """A recorded source's fixes, on the camera's clock, as its frames pass them."""
        if self._gps_pending is None:  # its clock is known at the first frame
            offset = int(getattr(self.camera_src, "stamp_offset_ns", 0))
            self._gps_pending = deque(self._recorded_gps.fixes(offset))  # type: ignore[union-attr]
        while self._gps_pending and self._gps_pending[0].stamp_ns <= stamp_ns:
            self._on_gps_fix(self._gps_pending.popleft())

    def _front_end_loop(self) -> None:
        """Frames and the wheel readings that came meanwhile into the front end (the one
        :class:`slam.front_end.FrontEnd` the offline commands drive); its scan and pose go to
        the mapper, the collision monitor and the navigator."""
        cfg = self.cfg
        # The camera's gyro is imu0: a D435i/D455's (or a recording's played as the camera)
        # streams as it comes (take_imu); another source's is read whole.
        src = self.camera_src
        streams = bool(getattr(src, "gyro_streams", False))
        gyro = src.imu() if src is not None and not streams else None
        opts = FrontEndOptions(
            wheels=self.opts.board != "none",
            imu=streams or (gyro is not None and len(gyro.stamps_ns) > 0),
            pose_before_vo=cfg.live.pose_before_vo,
            camera_rate_hz=cfg.camera.rate,
        )
        fe = FrontEnd(cfg.robot, cfg.ekf, cfg.vo, cfg.depth_to_scan, opts)
        # VO and depth -> scan built now, while the camera starts, not on its first frame.
        intrinsics = self.sim.intrinsics if self.sim is not None else None
        if intrinsics is None and src is not None:
            try:
                intrinsics = src.intrinsics()
            except SensorError as err:  # the first frame brings them instead
                log.debug("camera intrinsics not known before the first frame: %s", err)
        if intrinsics is not None:
            fe.prepare(intrinsics)
        scan_in_base = fe.scan_in_base  # the scans' frame in base_link (depth_to_scan)
        self.front_end = fe
        imu_feed: MessageFeed | None = None  # built at the first frame, when its clock is known
        last_mapped_ns = -(2**62)  # [ns] stamp of the last scan handed to the mapper
        stalled = False
        vis_every = cfg.live.visualize_every
        n = 0
        while True:
            try:
                frame = self.frame_q.get(timeout=cfg.live.camera_stall_timeout)
            except queue.Empty:
                if not stalled and not self.stop.is_set():
                    stalled = True
                    self._note_camera_gap(cfg.live.camera_stall_timeout, waiting=True)
                    log.warning(
                        "no camera frame for %.1f s: mapping paused", cfg.live.camera_stall_timeout
                    )
                continue
            if frame is None:
                break
            if stalled:
                stalled = False
                log.info("camera frames again: mapping resumed")
            if self.recorder is not None:
                self.recorder.frame(frame)
            # a. Wheel ticks that arrived since the last frame. The filter starts at the first
            #    frame, before the readings queued meanwhile (a loaded machine delivers them
            #    late): their motion after it is fused, not the frame left without a pose (#16).
            if fe.ekf is not None:
                fe.ekf.start(frame.stamp_ns)
            t_a = time.perf_counter()
            while True:
                try:
                    t = self.ticks_q.get_nowait()
                except queue.Empty:
                    break
                if fe.wheels(t) and self.recorder is not None:
                    self.recorder.wheels(t)
            # The gyro samples up to this frame, on its clock (the same merge as offline).
            if opts.imu and src is not None:
                if imu_feed is None:
                    offset = int(getattr(src, "stamp_offset_ns", 0))
                    imu_feed = MessageFeed(src, fe, offset, kinds=("imu",))
                if streams:
                    imu_feed.extend_imu(src.take_imu())  # type: ignore[attr-defined]
                imu_feed.until(frame.stamp_ns)
            wheels_ms = 1e3 * (time.perf_counter() - t_a)
            # b. VO (skipped when frames wait: the next VO pair spans both), the pose at the
            #    frame's stamp and the scan: latency ends here.
            step = fe.frame(
                frame, skip_vo=cfg.live.skip_vo_when_behind and not self.frame_q.empty()
            )
            if math.isfinite(step.vo_ms):
                self.stage_ms["vo"].add(step.vo_ms)
            if step.odom is None or step.scan is None:
                continue
            p = step.odom.pose
            odom = oplus(self.start_pose, [p.x, p.y, p.yaw])
            scan = step.scan
            self.stage_ms["depth_to_scan"].add(step.scan_ms)
            self.stage_ms["wheels_ekf"].add(wheels_ms + step.ekf_ms)
            with self.shared.lock:
                self.shared.odom = odom
                self.shared.monitor.add_scan(odom, scan, scan_in_base)
                m2o = self.shared.map_to_odom
            latency = (time.monotonic_ns() - frame.stamp_ns) / 1e6
            self.latency_ms.add(latency)
            self.frame_windows.add(latency)
            self.counts.inc("frames_processed")
            self.odom_track.add(frame.stamp_ns, float(odom[0]), float(odom[1]), float(odom[2]))
            if self.navigator is not None:  # the scan's frame in the map
                self.navigator.add_scan(scan, scan_pose(oplus(m2o, odom), scan_in_base))
            rate = cfg.live.mapper_rate
            if rate and frame.stamp_ns - last_mapped_ns < 1e9 / rate:
                self.counts.inc("scans_thinned_mapper_rate")
            else:
                last_mapped_ns = frame.stamp_ns
                try:  # the mapper and the localiser work in the scan's frame, as offline
                    self.scan_q.put_nowait((scan, scan_pose(odom, scan_in_base)))
                except queue.Full:
                    self.counts.inc("scans_dropped_mapper_behind")
            n += 1
            if vis_every and n % vis_every == 0:
                self.vis.frame(frame.stamp_ns, frame.rgb, frame.depth_m)
        assert fe.ekf is not None
        self.ekf_stats = fe.ekf.stats  # per sensor: received, fused, rejected by the gate, late
        for name, count in fe.counts.items():
            self.counts.inc(name, count)
        self.scan_q.put(None)

    def _mapper_loop(self) -> None:
        """Scans with the odom pose of their frame into the mapper or the localiser; map ->
        odom back to the front end, base_link's pose in the map to ``trajectory.tum``."""
        cfg = self.cfg
        scan_in_base = self._scan_in_base()
        while (item := self.scan_q.get()) is not None:
            scan, odom = item
            if self.localizer is not None:
                if self._gps_prior is not None:
                    while not self.gps_q.empty():
                        self._gps_prior.add_fix(*self.gps_q.get_nowait())
                    self._gps_prior.before_scan(scan.stamp_ns, odom)
                res = self.localizer.update(scan, odom)
                pose, m2o = res.pose, res.map_to_odom
                tracking = res.status == "tracking"
                self.counts.inc(f"localizer_{res.status}")
            else:
                assert self.mapper is not None
                t0 = time.perf_counter()
                out = self.mapper.add_scan(scan, odom)
                self.stage_ms["mapper"].add(1e3 * (time.perf_counter() - t0))
                if out is None:
                    self.counts.inc("scans_skipped_by_mapper")
                    continue
                pose, tracking = np.asarray(out), True
                m2o = oplus(pose, ominus(odom, np.zeros(3)))
                self._hand_map_to_navigator()
                if self.map_track.count == 0:
                    # The first checkpoint comes soon after mapping starts, not a whole period
                    # later: a crash in the first minute still leaves a bundle.
                    self._last_checkpoint = (
                        time.monotonic()
                        - cfg.live.checkpoint_period
                        + cfg.live.first_checkpoint_after
                    )
            with self.shared.lock:
                self.shared.map_to_odom = np.asarray(m2o, dtype=np.float64)
                self.shared.tracking = tracking
            if tracking and self._first_tracked is None:  # places odometry in the run chart
                self._first_tracked = (scan.stamp_ns, np.array(m2o, dtype=np.float64))
            base = base_pose(np.asarray(pose), scan_in_base)
            self.map_track.add(scan.stamp_ns, float(base[0]), float(base[1]), float(base[2]))
            self.counts.inc("scans_mapped")
            if self.map_track.count % max(cfg.live.visualize_every, 1) == 0:
                pts = transform_points(np.asarray(pose), scan_points(scan))
                self.vis.scan(scan.stamp_ns, pts)
                self.vis.pose(scan.stamp_ns, base, self.map_track.thinned())
            if (
                self.mapper is not None
                and time.monotonic() - self._last_checkpoint >= cfg.live.checkpoint_period
            ):
                self.checkpoint(final=False)

    def _open_estimator(self) -> None:
        """The localiser in the ``--map`` bundle, or else the mapper."""
        cfg = self.cfg
        if self.opts.map_bundle is None:
            self.mapper = Mapper(cfg.mapper)
            return
        from slam.localization import Localizer, MapModel
        from slam.map_bundle import load_map

        loaded = load_map(self.opts.map_bundle)
        self._loaded_map = loaded
        model = MapModel.from_grid(
            loaded.grid, cfg.localizer, loaded.occupied_thresh, loaded.free_thresh
        )
        self.localizer = Localizer(model, cfg.localizer)

    def _place_localizer(self) -> None:
        """``--initial-pose`` (or the simulated robot's known start) to the localiser, which
        tracks the scan's frame: base_link's pose moved to it, as offline."""
        if self.localizer is None:
            return
        if self.initial_pose is not None:
            self.localizer.set_initial_pose(scan_pose(self.initial_pose, self._scan_in_base()))
        elif self.sim is not None and self.cfg.live.sim_initial_pose:
            # The simulated robot knows where it starts, as a user gives --initial-pose.
            self.localizer.set_initial_pose(scan_pose(self.start_pose, self._scan_in_base()))

    def _scan_in_base(self) -> np.ndarray:
        """The scans' frame in base_link, for this run's robot (its mount is final once the
        devices are up: a camera's own mount replaces the config's before the front end)."""
        return scan_frame_in_base(self.cfg.robot, self.cfg.depth_to_scan)

    def _hand_map_to_navigator(self) -> None:
        """Every ``live.nav_map_period``: the mapper's keyframes (poses and scans, no copy of
        the scans) to the navigator, whose own thread turns them into a costmap."""
        if self.navigator is None or self.mapper is None or not self.mapper.keyframes:
            return
        now = time.monotonic()
        if now - self._last_snapshot < self.cfg.live.nav_map_period:
            return
        self._last_snapshot = now
        self.navigator.set_map(
            MapSnapshot(self.mapper.graph.poses(), tuple(k.scan for k in self.mapper.keyframes))
        )

    def _controller_loop(self) -> None:
        """Velocity commands at live.control_rate: the teleop keys in manual mode, the route in
        auto mode (Tab switches). Commands go out even when zero, so the board's watchdog only
        stops the motors when this loop itself stops."""
        lc = self.cfg.live
        period = 1.0 / lc.control_rate
        i = 0
        failing = False
        teleop = TeleopState(
            speed=lc.max_linear_speed,
            turn=lc.max_angular_speed,
            speed_limit=self.cfg.robot.max_wheel_speed,
        )
        manual_twist, last_key = (0.0, 0.0), -math.inf
        blocked_since: float | None = None
        guard = ""
        last_tick = time.monotonic()
        while not self.stop.wait(period):
            now_tick = time.monotonic()
            if now_tick - last_tick > 2.0 * period:  # the machine kept this thread waiting
                self.counts.inc("controller_late_ticks")
            last_tick = now_tick
            # 1. Keys: Tab switches mode; in manual mode they steer, as teleop_twist_keyboard.
            while True:
                try:
                    key = self.keys.get_nowait()
                except queue.Empty:
                    break
                if key == MODE_SWITCH_KEY:
                    self.mode = "auto" if self.mode == "manual" else "manual"
                    manual_twist, teleop = (0.0, 0.0), replace(teleop, x=0, th=0)
                    if self.navigator is not None:
                        self.navigator.reset_motion()  # the smoother starts from rest again
                    self.counts.inc("mode_switches")
                    log.info("drive mode: %s", self.mode)
                elif self.mode == "manual":
                    manual_twist, teleop = teleop_key(key, teleop)
                    last_key = time.monotonic()
            if self.board is None:
                continue
            v = w = 0.0
            if self.mode == "manual":
                if self.joystick is not None:
                    v, w = self.joystick.twist  # (0, 0) unless the deadman is held
                elif time.monotonic() - last_key <= lc.teleop_key_timeout:
                    v, w = manual_twist
            elif self.navigator is not None:
                pose = self.shared.pose_in_map()
                v, w = self.navigator.tick(
                    time.monotonic_ns(),
                    pose if self.shared.tracking else None,
                    collision_stop=guard == "stop",
                )
                self.route_done = self.navigator.done
            elif self.opts.drive == "route":
                pose = self.shared.pose_in_map()
                if self.opts.repeat_route and i >= len(self.route):
                    i = 0
                    self.counts.inc("route_laps")
                if pose is not None and i < len(self.route):
                    if math.hypot(*(self.route[i] - pose[:2])) < lc.waypoint_tolerance:
                        i += 1
                        self.counts.inc("waypoints_reached")
                        self.route_done = i >= len(self.route) and not self.opts.repeat_route
                    elif self.shared.tracking:
                        v, w = route_command(
                            pose,
                            self.route[i],
                            lc.max_linear_speed,
                            lc.max_angular_speed,
                            lc.turn_in_place_angle,
                            lc.heading_gain,
                        )
            # 2. The collision monitor has the last word: stop before what the camera saw.
            with self.shared.lock:
                odom = self.shared.odom
                if odom is not None:
                    v, w, action = self.shared.monitor.limit(v, w, odom)
            if odom is not None:
                if action == "stop" and guard != "stop":
                    self.counts.inc("collision_monitor_stops")
                guard = action
                now = time.monotonic()
                if (
                    action == "stop"
                    and self.mode == "auto"
                    and self.navigator is None
                    and i < len(self.route)
                ):
                    blocked_since = now if blocked_since is None else blocked_since
                    if now - blocked_since > lc.blocked_timeout:
                        log.warning(
                            "waypoint %d blocked for %.0f s: skipped", i, lc.blocked_timeout
                        )
                        self.counts.inc("waypoints_skipped_blocked")
                        i, blocked_since = i + 1, None
                        self.route_done = i >= len(self.route) and not self.opts.repeat_route
                else:
                    blocked_since = None
            try:
                self.board.set_velocity(v, w)
            except SensorError as err:
                if not failing:
                    log.warning("board not answering, motors assumed stopped: %s", err)
                failing = True
                self.counts.inc("board_command_errors")
                continue
            if failing:
                log.info("board answering again")
                self.counts.inc("board_recovered")
                failing = False

    def _joystick_loop(self) -> None:
        """Events from the evdev device into the joystick teleop (a daemon thread: the blocking
        read ends with the process)."""
        from nav.joystick import read_device

        assert self.joystick is not None and self.opts.joystick is not None
        for event in read_device(self.opts.joystick):
            if self.stop.is_set():
                return
            self.joystick.feed(*event)

    def _keyboard_loop(self) -> None:
        """Keys from the terminal (cbreak mode: Ctrl-C still interrupts), restored on exit."""
        import select
        import termios
        import tty

        fd = sys.stdin.fileno()
        old = termios.tcgetattr(fd)
        try:
            tty.setcbreak(fd)
            while not self.stop.is_set():
                ready, _, _ = select.select([fd], [], [], 0.1)
                if ready:
                    self.keys.put(sys.stdin.read(1))
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, old)

    # 3. Checkpoints: the bundle so far, written atomically.

    def checkpoint(self, final: bool) -> Path | None:
        if self.mapper is None:
            return None
        with self._checkpoint_lock:
            t0 = time.perf_counter()
            result = self.mapper.finish(batch_optimise=final)
            if not result.keyframes:
                return None
            grid = build_grid(result, self.cfg.mapper)
            path = self.run.file("map")
            bundle = make_bundle(result, grid, self.cfg.mapper, f"live {self.opts.camera}")
            save_bundle(replace(bundle, geo=self.map_anchor), path)
            self._last_checkpoint = time.monotonic()
            self.counts.inc("checkpoints")
            self.last_result, self.last_grid = result, grid
            log.info(
                "map checkpoint: %d keyframes in %.2f s",
                len(result.keyframes),
                time.perf_counter() - t0,
            )
            g = grid.geometry
            occ = grid.occupied_mask(self.cfg.mapper.occupied_thresh)
            self.vis.occupied(
                int(result.scan_stamps_ns[-1]) if len(result.scan_stamps_ns) else 0,
                occupied_cells_xy(occ, (g.origin_x, g.origin_y), g.resolution),
            )
            return path

    def _final_checkpoint(self) -> Path | None:
        """The run's last save, whatever happened before it: a batch optimisation that fails
        falls back to the graph as tracked, and a save that fails is an error in the summary
        (which is still written) rather than a run lost without one."""
        try:
            return self.checkpoint(final=True)
        except RgbdNavError as err:
            log.error("final map checkpoint failed: %s", err)
            self.errors.append(f"final map checkpoint: {err}")
        except Exception as err:  # gtsam and numpy raise their own types from the optimiser
            log.exception("final map checkpoint failed")
            self.errors.append(f"final map checkpoint: {type(err).__name__}: {err}")
        try:
            return self.checkpoint(final=False)
        except Exception as err:
            log.exception("map checkpoint without batch optimisation failed too")
            self.errors.append(f"map checkpoint: {type(err).__name__}: {err}")
            return None

    # 4. The whole run.

    def execute(self, progress: Callable[[float, float], None] | None = None) -> dict[str, Path]:
        opts, cfg = self.opts, self.cfg
        t0, cpu0 = time.monotonic(), resource.getrusage(resource.RUSAGE_SELF)
        # Before any thread allocates: freed memory goes back instead of creeping up for hours.
        tame_malloc(cfg.live.malloc_arena_max, cfg.live.malloc_mmap_threshold)
        outputs = {"config": self.run.write_config(cfg)}
        self._open_estimator()
        vis = make_visualizer("live", opts.rrd, opts.viewer)
        self.vis = AsyncVisualizer(vis, cfg.live.visualize_queue_size)
        try:
            sim_stats, wall = self._run_threads(t0, progress)
            if self.mapper is not None and self._final_checkpoint() is not None:
                outputs["map bundle"] = self.run.file("map")
        finally:
            self.vis.close()  # also when the devices failed to start: the .rrd is flushed
        outputs.update(self._write_outputs(wall, cpu0, sim_stats))
        return outputs

    def _run_threads(
        self, t0: float, progress: Callable[[float, float], None] | None
    ) -> tuple[Any, float]:
        """Start the devices and threads, wait for the end, stop everything; (the simulated
        robot's stats or None, wall seconds)."""
        restore = self._install_signal_handlers()
        # The board poller and watchdog are I/O threads beside CPU-bound ones: hand the GIL
        # over more often so they are not kept waiting for up to the default 5 ms.
        switch = sys.getswitchinterval()
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        threads: list[threading.Thread] = []
        try:
            frames = self._start_devices()
            self._place_localizer()
            if self.poller is not None:
                self.poller.start()
            specs: list[tuple[str, Callable[..., None], tuple[Any, ...]]] = [
                ("camera", self._camera_loop, (frames,)),
                ("front-end", self._front_end_loop, ()),
                ("mapper", self._mapper_loop, ()),
                ("controller", self._controller_loop, ()),
            ]
            if self.joystick is not None:
                specs.append(("joystick", self._joystick_loop, ()))
            if self.opts.drive != "idle" and _interactive():
                specs.append(("keyboard", self._keyboard_loop, ()))
                log.info(
                    "keys: teleop_twist_keyboard (u i o / j k l / m , .), Tab switches "
                    "manual/auto, Ctrl-C ends the run"
                )
            for name, fn, args in specs:
                th = threading.Thread(
                    target=self._guard, args=(name, fn, *args), name=name, daemon=True
                )
                th.start()
                threads.append(th)
            self._devices_up_at = time.monotonic()
            self._wait(t0, progress)
        finally:
            self.stop.set()
            for th in threads:
                th.join(timeout=JOIN_TIMEOUT_S)
                if th.is_alive():
                    self.errors.append(
                        f"thread {th.name} did not finish within {JOIN_TIMEOUT_S:.0f} s"
                    )
            if self.poller is not None:
                self.poller.stop()
            if self._opened is not None:
                self._opened.close()  # motors stopped if they may be running
            sim_stats = None
            if self.sim is not None:
                try:
                    sim_stats = self.sim.stop()
                except SensorError as err:  # the map and the run's files still get written
                    self.errors.append(f"simulated robot: {err}")
            if self.camera_src is not None:
                self.camera_src.close()
            if self.navigator is not None:
                self.navigator.close()
            self.odom_track.close()
            self.map_track.close()
            self.gps_writer.close()
            restore()
            sys.setswitchinterval(switch)
        return sim_stats, time.monotonic() - t0

    def _guard(self, name: str, fn: Callable[..., None], *args: Any) -> None:
        """A thread that dies takes the run down cleanly (motors stopped, map saved)."""
        try:
            fn(*args)
        except Exception as err:
            log.exception("%s thread failed", name)
            self.errors.append(f"{name}: {type(err).__name__}: {err}")
            self.stop.set()
            if name == "front-end":
                self.scan_q.put(None)

    def _clock_start(self) -> float | None:
        """When ``--duration`` and the drills start counting: the first camera frame, not the
        process start (on a loaded machine the devices alone can take longer than a short run),
        or ``live.camera_stall_timeout`` after the devices are up when no frame comes at all."""
        if self._first_frame_at is not None:
            return self._first_frame_at
        up = self._devices_up_at
        if up is not None and time.monotonic() - up >= self.cfg.live.camera_stall_timeout:
            return up + self.cfg.live.camera_stall_timeout
        return None

    def _wait(self, t0: float, progress: Callable[[float, float], None] | None) -> None:
        drills = sorted(self.opts.drills, key=lambda d: d.at_s)
        total = self.opts.duration_s or math.inf
        next_sample = 0.0
        next_progress = self.cfg.live.first_checkpoint_after
        while not self.stop.is_set():
            now = time.monotonic()
            if now - t0 >= next_sample:
                self.rss_timeline.add(round(now - t0, 1), round(rss_mb(), 1))
                c = self.counts.as_dict()
                self.frame_windows.sample(
                    round(now - t0, 1),
                    c.get("frames_processed", 0),
                    c.get("frames_dropped_front_end", 0),
                )
                while next_sample <= now - t0:  # one sample, also after a late start
                    next_sample += MEMORY_SAMPLE_S
            start = self._clock_start()
            elapsed = 0.0 if start is None else now - start
            if start is not None and elapsed >= next_progress:
                self._write_progress_summary(now - t0)
                next_progress = elapsed + self.cfg.live.checkpoint_period
            while start is not None and drills and drills[0].at_s <= elapsed:
                d = drills.pop(0)
                log.warning("fault drill at %.1f s: %s", elapsed, d.action)
                self.counts.inc(f"drill_{d.action}")
                self.sim.order(d.action, d.arg)
            if elapsed >= total:
                break
            if self.opts.drive == "route" and self.route_done:
                break
            if progress is not None and math.isfinite(total):
                progress(elapsed, total)
            self.stop.wait(0.1)

    def _write_progress_summary(self, wall: float) -> None:
        """A ``summary.json`` with ``status: incomplete`` while the run goes on (first at
        ``live.first_checkpoint_after``, then every ``live.checkpoint_period``): after a
        ``kill -9`` the folder still says what ran, its counts so far and that it did not end.
        The summary written at the end replaces it."""
        summary = {
            "command": "live",
            "status": "incomplete",
            "note": "written while the run went on; a run that ends replaces it",
            "camera": self.opts.camera,
            "board": self.opts.board,
            "world": str(self.opts.world) if self.opts.world else None,
            "robot": self._robot_frame(),
            "mode": "localization" if self.localizer is not None else "mapping",
            "config_files": [str(p) for p in self.config_files],
            "wall_s": round(wall, 3),
            "counts": self.counts.as_dict(),
            "errors": list(self.errors),
        }
        try:
            self.run.write_summary(summary)
        except OSError as err:  # the run goes on; the final summary will say it again
            log.warning("progress summary not written: %s", err)

    def _install_signal_handlers(self) -> Callable[[], None]:
        stop = StopSignals("stopping (motors, final map checkpoint)", self.stop, False)
        stop.__enter__()
        return lambda: stop.__exit__(None, None, None)

    def _write_outputs(self, wall: float, cpu0: Any, sim_stats: Any) -> dict[str, Path]:
        outputs: dict[str, Path] = {}
        run = self.run
        # The trajectories were streamed as they were made; read them back once for the report.
        tracks = {"slam_online": self.map_track.load(), "odometry": self.odom_track.load()}
        mapper_counts: dict[str, Any] | None = None
        if self.map_track.count:
            outputs["trajectory"] = self.map_track.path
        result = getattr(self, "last_result", None)
        if result is not None and len(result.scan_stamps_ns):
            # The map's own trajectory: every scan placed by the final, optimised graph (what a
            # recorded run reports); trajectory.tum holds the poses as tracked online.
            p = base_pose(result.scan_poses, self._scan_in_base())
            write_tum_trajectory(
                run.file("trajectory_optimised.tum"),
                result.scan_stamps_ns,
                p[:, 0],
                p[:, 1],
                p[:, 2],
            )
            outputs["optimised trajectory"] = run.file("trajectory_optimised.tum")
            tracks["slam"] = np.column_stack([result.scan_stamps_ns.astype(np.float64), p])
            mapper_counts = {
                k: result.counts[k]
                for k in ("scans", "scans_used", "keyframes", "revisits", "loop_closures")
                if k in result.counts
            }
        elif self.localizer is not None:
            tracks["slam"] = tracks["slam_online"]
        if self.odom_track.count:
            outputs["odometry"] = self.odom_track.path
        truth = np.zeros((0, 4))
        if sim_stats is not None and sim_stats.truth_poses:
            truth = load_track(run.file("groundtruth.tum"))
            outputs["ground truth"] = run.file("groundtruth.tum")
        recording = None
        if self.recorder is not None:
            recording = self.recorder.close(truth if len(truth) else None)
            if "error" in recording:
                self.errors.append(f"--record {recording['path']}: {recording['error']}")
            else:
                outputs["recording"] = Path(recording["path"])
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        lat = self.latency_ms
        summary: dict[str, Any] = {
            "command": "live",
            "status": "finished",
            "camera": self.opts.camera,
            "camera_imu": getattr(self.camera_src, "imu_note", None),
            "extrinsics": self.extrinsics,
            "board": self.opts.board,
            "world": str(self.opts.world) if self.opts.world else None,
            "robot": self._robot_frame(),
            "mode": "localization" if self.localizer is not None else "mapping",
            "initial_pose": (
                self.initial_pose.tolist()
                if self.initial_pose is not None
                else "simulator start"
                if self.localizer is not None
                and self.sim is not None
                and self.cfg.live.sim_initial_pose
                else None
            ),
            "drive": self.opts.drive,
            "config_files": [str(p) for p in self.config_files],
            "wall_s": round(wall, 3),
            "counts": self.counts.as_dict(),
            "latency_ms": (
                {
                    "p50": round(lat.percentile(50), 2),
                    "p99": round(lat.percentile(99), 2),
                    "max": round(lat.max, 2),
                    "samples": lat.count,
                    "kept": min(lat.count, lat.capacity),
                }
                if len(lat) >= MIN_LATENCIES
                else None
            ),
            "camera_to_host_ms_p50": round(self.arrival_ms.percentile(50), 2)
            if self.arrival_ms.count
            else None,
            "stage_ms_median": {
                k: round(v.percentile(50), 2) for k, v in self.stage_ms.items() if v.count
            },
            "cpu": {
                "host_cpu_s": round(
                    cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime, 2
                ),
                "host_cpu_percent": round(
                    100
                    * (cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime)
                    / max(wall, 1e-9),
                    1,
                ),
                "sim_robot_cpu_s": round(kids.ru_utime + kids.ru_stime, 2),
            },
            "peak_rss_mb": {
                "host": round(cpu1.ru_maxrss / 1024, 1),
                "sim_robot": round(kids.ru_maxrss / 1024, 1),
            },
            "rss_mb_timeline": self.rss_timeline.points,
            # [t, frames processed so far, dropped so far, latency p99 of the window ending at t]
            "frames_timeline": [[t, *v] for t, v in self.frame_windows.points],
            "mapper": mapper_counts,  # what the mapper holds: it grows with scans and keyframes
            "board_polls_per_s": round(self.poller.stats().polls / max(wall, 1e-9), 1)
            if self.poller is not None
            else None,
            "visualization": {"drawn": self.vis.drawn, "dropped": self.vis.dropped},
            "errors": self.errors,
        }
        if recording is not None:
            summary["recording"] = recording
        if self.poller is not None:
            ps = self.poller.stats()
            summary["board_link"] = {
                "port": str(self.board.url) if self.board else None,
                "polls": ps.polls,
                "errors": ps.errors,
                "board": self.board.kind if self.board else None,
                "late_replies_dropped": getattr(self.board, "late_replies_dropped", 0),
                "last_error": ps.last_error,
            }
        if sim_stats is not None:
            summary["sim_robot"] = {
                "frames_rendered": sim_stats.frames_rendered,
                "frames_dropped_camera": sim_stats.frames_dropped,
                "stalled_frames": sim_stats.stalled_frames,
                "collisions": sim_stats.collisions,
                "wall_slides": sim_stats.wall_slides,
                "stalled_wheel_travel_m": round(sim_stats.stalled_travel_m, 3),
                "board_disconnects": sim_stats.board_disconnects,
                "true_path_length_m": round(path_length(truth[:, 1:3]), 3),
            }
            summary["route_finished"] = self.route_done
        ekf_stats = getattr(self, "ekf_stats", None)
        if ekf_stats is not None:
            summary["ekf"] = asdict(ekf_stats)
        if self.navigator is not None:
            summary["navigation"] = nav = self.navigator.stats()
            for k, v in nav.items():  # the route's progress, as the direct driver counts it
                if k.startswith(("waypoints_", "route_laps")):
                    summary["counts"][k] = v
        if len(truth) > 1:
            for name, a in tracks.items():
                if len(a) >= 2:
                    ref = (truth[:, 1], truth[:, 2], truth[:, 3])
                    summary[f"{name}_vs_groundtruth"] = drift_summary(
                        a[:, 0].astype(np.int64),
                        (a[:, 1], a[:, 2], a[:, 3]),
                        truth[:, 0].astype(np.int64),
                        ref,
                    )
        paths = []
        if len(truth):
            paths.append(("ground truth", truth[:, 1], truth[:, 2]))
        if len(o := tracks["odometry"]):
            paths.append(("odometry (EKF)", o[:, 1], o[:, 2]))
        if len(m := tracks.get("slam", tracks["slam_online"])):
            paths.append(("SLAM" if self.mapper is not None else "localised", m[:, 1], m[:, 2]))
        grid = getattr(self, "last_grid", None)
        if paths:
            kw: dict[str, Any] = {}
            if grid is not None:
                g = grid.geometry
                kw = {
                    "occupied": grid.occupied_mask(self.cfg.mapper.occupied_thresh),
                    "origin": (g.origin_x, g.origin_y),
                    "resolution": g.resolution,
                }
            plot_trajectories(run.file("map.png"), paths, "live run", **kw)
            outputs["picture"] = run.file("map.png")
        if self.localizer is not None:
            summary["seconds_to_first_pose"] = self._seconds_to_first_pose(tracks)
        if self.gps_writer.count:
            outputs["gps fixes"] = self.gps_writer.path
            summary["gps"] = self._gps_outputs(tracks, grid)
            if (chart := run.file("gps.png")).is_file():
                outputs["run chart"] = chart
        outputs["summary"] = run.write_summary(summary)
        self.summary = summary
        return outputs

    def _seconds_to_first_pose(self, tracks: dict[str, np.ndarray]) -> float | None:
        """From the first scan to the first tracked one (the localiser's time to fix)."""
        online = tracks["slam_online"]
        if self._first_tracked is None or not len(online):
            return None
        return round((self._first_tracked[0] - online[0, 0]) / 1e9, 2)

    def _gps_outputs(self, tracks: dict[str, np.ndarray], grid: Any) -> dict[str, Any]:
        """The GPS part of the summary and, with the map's geo anchor, the run chart
        ``gps.png``: the localiser (or the mapper) vs odometry vs GPS, as `localize --gps`."""
        info: dict[str, Any] = {
            "source": self.gps_source,
            "geo_anchor": None if self.map_anchor is None else self.map_anchor.as_dict(),
            "fixes_used_by_localiser": (
                None if self._gps_prior is None else self._gps_prior.fixes_used
            ),
        }
        if self.map_anchor is None:
            return {"fixes": self.gps_writer.count, **info}
        fixes = read_gps_txt(self.gps_writer.path)
        gps = (fixes.stamps_ns, fixes.in_map(self.map_anchor), fixes.sigma_m)
        est, odom = tracks.get("slam", tracks["slam_online"]), tracks["odometry"]
        placed = np.zeros((0, 3))
        info["seconds_to_first_pose"] = self._seconds_to_first_pose(tracks)
        if self._first_tracked is not None and len(odom):  # estimates once it has one
            est = est[est[:, 0] >= self._first_tracked[0]]
            placed = oplus(self._first_tracked[1], odom[:, 1:4])
        else:
            est = est[:0]
        kw: dict[str, Any] = {}
        loaded = self._loaded_map
        if grid is not None or loaded is not None:
            g = (grid if grid is not None else loaded.grid).geometry
            occ = (
                grid.occupied_mask(self.cfg.mapper.occupied_thresh)
                if grid is not None
                else loaded.grid.occupied_mask(loaded.occupied_thresh)
            )
            kw = {"occupied": occ, "origin": (g.origin_x, g.origin_y), "resolution": g.resolution}
        label = "localiser" if self.localizer is not None else "mapper"
        chart = gps_chart(
            self.run.file("gps.png"),
            (label, est[:, 0].astype(np.int64), est[:, 1:3]),
            placed[:, :2],
            gps,
            f"live run: {label}, odometry and GPS",
            **kw,
        )
        return {**chart, **info}


def run_live(
    opts: LiveOptions, progress: Callable[[float, float], None] | None = None
) -> tuple[dict[str, Path], dict[str, Any]]:
    """Run live until the duration, the end of the route, or SIGINT/SIGTERM."""
    live = LiveRun(opts)
    outputs = live.execute(progress)
    return outputs, live.summary


__all__ = ["Drill", "LiveOptions", "LiveRun", "route_command", "run_live"]
