"""The simulated robot in real time: the board emulator behind a pseudo-terminal turns the wheels,
and a 30 Hz Kinect images the world at the pose those wheels really reached.

Everything runs in a child process, as a real camera and a real control board run outside the
host program: the host opens the board's serial port and reads camera frames through exactly
the code paths it uses on the robot (:class:`sensors.eddie.EddieBoard`, a frame iterator).

Truth in the child: the robot moves by the emulator's *continuous* wheel travel (the board
reports its floor as encoder counts), through wheels that are not quite the nominal ones
(``sim.wheel_diameter_error``, ``sim.track_width_error``) and slip (AR(1), ``sim.wheel_slip``).
A pose closer to a wall or furniture than ``robot.radius`` is a collision, counted: the round
robot slides along the wall when the x or y part of its motion is free, and otherwise only turns
(:func:`sensors.sim.motion.blocked_step`). Its wheels then mostly stall against the obstacle:
the encoders count only ``sim.blocked_wheel_slip`` of the travel the body refused, so the
board reports what a real Eddie's encoders would, not freely spinning wheels.

Ground truth is streamed to a TUM file as it is made (``truth_path``), so a long run holds no
growing list in memory.

Frames cross the process boundary through a ring of shared-memory slots (:class:`_FrameRing`);
the queue carries only the stamp, the slot and the true pose (why: ``docs/design/sim_live.md``).

The serial port is a symlink (``port_link``) to the emulator's pty, as a udev rule gives a USB
adapter a stable name; a drilled "board unplugged" closes the pty, and "replugged" serves a new
one behind the same link.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import os
import queue
import signal
import time
from dataclasses import dataclass, replace
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any

import numpy as np

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.eddie_emulator import EddieEmulator
from sensors.types import CameraIntrinsics, SensorError

log = logging.getLogger(__name__)

FRAME_QUEUE_SIZE = 2  # frames in flight to the host: a USB camera's small buffer
# Ring slots: with at most FRAME_QUEUE_SIZE frames announced and not yet taken, and one being
# copied out by the host, the slot the child writes next is never one the host still reads.
FRAME_SLOTS = FRAME_QUEUE_SIZE + 2
STARTUP_TIMEOUT_S = 60.0  # [s] importing and building the renderer in the child
STOP_TIMEOUT_S = 30.0  # [s] finishing a frame and reporting, on a busy machine


@dataclass(frozen=True)
class SimFrameMsg:
    """One camera frame as it crosses the process boundary, with the truth behind it."""

    stamp_ns: int  # [ns] time.monotonic_ns() at capture (the clock the board driver stamps with)
    rgb: np.ndarray  # (H, W, 3) uint8
    depth_m: np.ndarray  # (H, W) float32 [m], 0 = invalid
    true_pose: tuple[float, float, float]  # base_link in the world [m, m, rad]


class _FrameRing:
    """``FRAME_SLOTS`` (rgb, depth) frame buffers in one shared-memory block. The host creates
    (and finally unlinks) it; the child attaches by name and writes the frames."""

    def __init__(self, width: int, height: int, name: str | None = None) -> None:
        self.shape = (height, width)
        self.rgb_bytes = height * width * 3
        self.slot_bytes = self.rgb_bytes + height * width * 4  # + float32 depth
        size = FRAME_SLOTS * self.slot_bytes
        self.owner = name is None
        # The spawned child shares the host's resource tracker: the block is unlinked by the
        # host's stop(), or by the tracker when both processes are gone (a host killed -9).
        self.shm = shared_memory.SharedMemory(name=name, create=self.owner, size=size)

    def _views(self, slot: int) -> tuple[np.ndarray, np.ndarray]:
        base = slot * self.slot_bytes
        h, w = self.shape
        rgb = np.ndarray((h, w, 3), np.uint8, self.shm.buf, base)
        depth = np.ndarray((h, w), np.float32, self.shm.buf, base + self.rgb_bytes)
        return rgb, depth

    def write(self, slot: int, rgb: np.ndarray, depth_m: np.ndarray) -> None:
        ring_rgb, ring_depth = self._views(slot)
        ring_rgb[...] = rgb
        ring_depth[...] = depth_m

    def read(self, slot: int) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the frame in ``slot`` (the slot is rewritten a few frames later)."""
        rgb, depth = self._views(slot)
        return rgb.copy(), depth.copy()

    def close(self) -> None:
        if self.shm.buf is None:
            return  # closed already
        self.shm.close()
        if self.owner:
            self.shm.unlink()


@dataclass
class SimRobotStats:
    frames_rendered: int = 0
    frames_dropped: int = 0  # the host did not take them in time (camera-side overflow)
    collisions: int = 0  # physics steps whose full motion would hit something
    wall_slides: int = 0  # ... of which the robot slid along the obstacle (x or y part free)
    stalled_travel_m: float = 0.0  # [m] travel the stalled wheels did not turn (both wheels)
    stalled_frames: int = 0  # frames not sent during a drilled camera stall
    board_disconnects: int = 0
    truth_poses: int = 0  # poses written to the ground-truth file


def _child(*args: Any) -> None:
    """The child's entry: any failure is reported to the host, not lost with the process.
    Ctrl-C reaches the whole process group; the host decides when the robot stops (it sends
    "stop"), so the child ignores SIGINT instead of dying with a KeyboardInterrupt traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    replies = args[-1]
    try:
        _simulate(*args)
    except BaseException as err:
        import traceback

        replies.put(("error", f"{type(err).__name__}: {err}\n{traceback.format_exc()}"))
        raise


class _StallingEmulator(EddieEmulator):
    """The board emulator whose wheels can be held back by the world: a blocked robot's motors
    stall against the obstacle, so the encoders advance less than the speed loop commanded."""

    def hold_back(self, left: float, right: float) -> None:
        """Take ``left``/``right`` [encoder positions] off the wheels' integrated travel."""
        with self._lock:
            self._left.pos -= left
            self._right.pos -= right


def _simulate(
    world_path: str,
    robot: RobotConfig,
    camera: CameraConfig,
    sim: SimConfig,
    seed: int,
    start: tuple[float, float, float] | None,
    port_link: str,
    truth_path: str,
    ring_name: str,
    wheels_name: str | None,
    frames: Any,
    control: Any,
    replies: Any,
) -> None:
    from scipy.ndimage import distance_transform_edt

    from sensors.sim.motion import blocked_step, gauss_markov_step
    from sensors.sim.render import KinectRenderer
    from sensors.sim.world import floor_plan, load_world
    from sensors.tum import TRAJECTORY_COLUMNS, format_stamp

    rng = np.random.default_rng(seed)
    world = load_world(world_path)
    if start is not None:  # this robot's own start (several robots in one world)
        world = replace(world, start=start)
    renderer = KinectRenderer(world, camera, robot, sim, noise_seed=int(rng.integers(2**31)))
    plan = floor_plan(world)
    clearance = distance_transform_edt(~plan.occupied) * plan.resolution
    # The true wheels: nominal geometry times a seeded error, as the recorded simulator does.
    metres = robot.metres_per_tick * (1.0 + np.asarray(sim.wheel_diameter_error))  # [m/pos] L, R
    track = robot.track_width * (1.0 + sim.track_width_error)
    emu = _StallingEmulator(robot)
    ring = _FrameRing(camera.width, camera.height, ring_name)
    slot = 0

    def is_free(px: float, py: float) -> bool:
        r, c = plan.cell_of(np.array([[px, py]]))[0]
        inside = 0 <= r < clearance.shape[0] and 0 <= c < clearance.shape[1]
        return bool(inside and clearance[r, c] >= robot.radius)

    link = Path(port_link)

    def serve(path: str) -> None:
        tmp = link.with_name(link.name + ".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(path)
        os.replace(tmp, link)

    external = None
    if wheels_name is None:
        serve(emu.serve_pty())
    else:  # another board's emulator in the host turns the wheels: read its travel
        external = shared_memory.SharedMemory(name=wheels_name)
        wheels = np.ndarray((2,), np.float64, external.buf)

    def positions() -> np.ndarray:
        return np.array(emu.positions()) if external is None else wheels.copy()

    stats = SimRobotStats()
    truth_file = open(truth_path, "w", buffering=1 << 16)  # closed when the loop ends
    truth_file.write(
        f"# planar trajectory (z = 0, rotation about z)\n# {' '.join(TRAJECTORY_COLUMNS)}\n"
    )
    x, y, yaw = world.start
    slip = np.zeros(2)
    prev = positions()
    period_ns = int(round(1e9 / sim.camera_rate))
    flush_every = max(1, int(sim.camera_rate))  # [poses] about once a second
    next_ns = time.monotonic_ns()
    stall_until_ns = 0
    replies.put(("ready", renderer.intrinsics))
    host = os.getppid()
    while os.getppid() == host:  # a host killed with -9 leaves no orphan rendering forever
        # 1. Orders from the host (fault drills, stop).
        try:
            order = control.get_nowait()
        except queue.Empty:
            order = None
        if order is not None:
            kind = order[0]
            if kind == "stop":
                break
            if kind == "unplug_board":
                emu.inject(disconnect=True)
                stats.board_disconnects += 1
            elif kind == "replug_board":
                serve(emu.reconnect())
            elif kind == "stall_camera":
                stall_until_ns = time.monotonic_ns() + int(order[1] * 1e9)
        # 2. Move the robot by what the wheels did since the last frame.
        now = positions()
        slip = gauss_markov_step(
            slip, sim.wheel_slip, sim.slip_correlation_time, period_ns / 1e9, rng.standard_normal(2)
        )
        per_pos = metres * (1.0 + slip)  # [m per encoder position] left, right
        travel = (now - prev) * per_pos  # [m] left, right
        pose, enc_l, enc_r, outcome = blocked_step(
            np.array([x, y, yaw]), travel[0], travel[1], track, is_free, sim.blocked_wheel_slip
        )
        x, y, yaw = (float(v) for v in pose)
        if outcome != "free":
            # The encoders count only what the stalled wheels turned: hold the rest back
            # (an external board's wheels spin on: its emulator is in the host).
            held = (travel - np.array([enc_l, enc_r])) / per_pos  # [positions]
            if external is None:
                emu.hold_back(float(held[0]), float(held[1]))
                now = now - held
            stats.collisions += 1
            stats.wall_slides += outcome == "slid"
            stats.stalled_travel_m += float(np.abs(held * per_pos).sum())
        prev = now
        # 3. Image the world at the capture time, unless the camera is stalled.
        stamp = time.monotonic_ns()
        truth_file.write(
            f"{format_stamp(stamp)} {x!r} {y!r} 0.0 0.0 0.0 "
            f"{math.sin(yaw / 2)!r} {math.cos(yaw / 2)!r}\n"
        )
        stats.truth_poses += 1
        if stats.truth_poses % flush_every == 0:
            truth_file.flush()  # a host killed with -9 (and us with it) leaves the truth so far
        if stamp < stall_until_ns:
            stats.stalled_frames += 1
        else:
            rgb, depth = renderer.render(x, y, yaw, rng)
            stats.frames_rendered += 1
            ring.write(slot, rgb, depth)
            try:
                frames.put_nowait((stamp, slot, (x, y, yaw)))
                slot = (slot + 1) % FRAME_SLOTS  # an unannounced slot is simply rewritten
            except queue.Full:
                stats.frames_dropped += 1
        # 4. Keep the 30 Hz phase; a frame that could not be rendered in time is skipped.
        next_ns += period_ns
        late = time.monotonic_ns() - next_ns
        if late > 0:
            next_ns += (late // period_ns + 1) * period_ns
        time.sleep(max(0.0, (next_ns - time.monotonic_ns()) / 1e9))
    emu.close()
    if external is not None:
        del wheels
        external.close()
    truth_file.close()
    ring.close()
    frames.cancel_join_thread()  # frames the host no longer reads must not block our exit
    replies.put(("stats", stats))


class SimRobot:
    """The child process: ``start()`` returns the serial port to open; ``frames()`` iterates
    camera frames as they arrive; ``stop()`` returns the child's counters; the ground truth
    is in the TUM file ``truth_path`` (default: beside the port link, ``groundtruth.tum``)."""

    def __init__(
        self,
        world_path: str | Path,
        robot: RobotConfig,
        camera: CameraConfig,
        sim: SimConfig,
        port_link: str | Path,
        seed: int = 0,
        truth_path: str | Path | None = None,
        external_wheels: bool = False,
        start: tuple[float, float, float] | None = None,
    ) -> None:
        self.world_path = str(world_path)
        self.robot, self.camera, self.sim, self.seed = robot, camera, sim, seed
        self.port_link = str(port_link)
        self.truth_path = (
            Path(truth_path)
            if truth_path is not None
            else Path(port_link).with_name("groundtruth.tum")
        )
        ctx = mp.get_context("spawn")  # the host has threads: never fork it
        self._ring = _FrameRing(camera.width, camera.height)
        # external_wheels: the host's board emulator writes the wheel travel [positions] here
        self.wheels_shm = (
            shared_memory.SharedMemory(create=True, size=16) if external_wheels else None
        )
        self.wheels = (
            None if self.wheels_shm is None else np.ndarray((2,), np.float64, self.wheels_shm.buf)
        )
        if self.wheels is not None:
            self.wheels[:] = 0.0
        self._frames: Any = ctx.Queue(maxsize=FRAME_QUEUE_SIZE)
        self._control: Any = ctx.Queue()
        self._replies: Any = ctx.Queue()
        self._proc = ctx.Process(
            target=_child,
            name="rgbdnav-sim-robot",
            daemon=True,
            args=(
                self.world_path,
                robot,
                camera,
                sim,
                seed,
                start,
                self.port_link,
                str(self.truth_path),
                self._ring.shm.name,
                None if self.wheels_shm is None else self.wheels_shm.name,
                self._frames,
                self._control,
                self._replies,
            ),
        )
        self.intrinsics: CameraIntrinsics | None = None
        self._stats: SimRobotStats | None = None
        self._error: str | None = None

    def start(self) -> str:
        try:
            return self._start()
        except BaseException:
            self._ring.close()  # no stop() follows a failed start
            self._close_wheels()
            raise

    def _start(self) -> str:
        self._proc.start()
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while True:
            try:
                kind, payload = self._replies.get(timeout=0.2)
                break
            except queue.Empty:
                if not self._proc.is_alive():
                    raise SensorError(
                        f"the simulated robot failed to start (exit code {self._proc.exitcode}); "
                        "see the log above"
                    ) from None
                if time.monotonic() > deadline:
                    self._proc.kill()
                    raise SensorError(
                        f"the simulated robot did not start within {STARTUP_TIMEOUT_S:.0f} s"
                    ) from None
        if kind == "error":
            self._proc.join(timeout=STOP_TIMEOUT_S)
            raise SensorError(f"the simulated robot failed to start: {payload.splitlines()[0]}")
        self.intrinsics = payload
        return self.port_link

    def _close_wheels(self) -> None:
        if self.wheels_shm is not None:
            self.wheels = None
            self.wheels_shm.close()
            self.wheels_shm.unlink()
            self.wheels_shm = None

    def next_frame(self, timeout_s: float) -> SimFrameMsg | None:
        """The next frame, or None after ``timeout_s`` without one (a stalled camera)."""
        try:
            stamp_ns, slot, pose = self._frames.get(timeout=timeout_s)
        except queue.Empty:
            return None
        return SimFrameMsg(stamp_ns, *self._ring.read(slot), pose)

    def order(self, *order: Any) -> None:
        """A fault drill: ("unplug_board",), ("replug_board",), ("stall_camera", seconds)."""
        self._control.put(order)

    def stop(self) -> SimRobotStats:
        if self._stats is not None:
            return self._stats
        if self._proc.is_alive():
            self._control.put(("stop",))
            deadline = time.monotonic() + STOP_TIMEOUT_S
            while time.monotonic() < deadline:
                # Drain frames so the child's last put cannot block its exit.
                try:
                    self._frames.get_nowait()
                except queue.Empty:
                    pass
                try:
                    kind, payload = self._replies.get(timeout=0.05)
                except queue.Empty:
                    continue
                if kind == "stats":
                    self._stats = payload
                    break
                if kind == "error":
                    self._error = payload
                    break
        if self._proc.pid is not None:  # not when start() failed to spawn it
            self._proc.join(timeout=STOP_TIMEOUT_S)
            if self._proc.is_alive():
                self._proc.kill()
        self._ring.close()
        self._close_wheels()
        if self._stats is None:
            if self._proc.pid is None:
                raise SensorError("the simulated robot was never started, so it has no counts")
            why = (
                self._error.splitlines()[0] if self._error else (f"exit code {self._proc.exitcode}")
            )
            raise SensorError(f"the simulated robot failed: {why}")
        return self._stats


__all__ = ["SimFrameMsg", "SimRobot", "SimRobotStats"]
