"""A world file as a source: its recording rendered on demand, with no images on disk.

`rgbdnav map WORLD` used to render the whole route into a PNG recording (0.7 MB a frame of
noisy, nearly incompressible images: 2.8 GB for the house) and then map it; encoding, writing,
reading and decoding the PNGs were a fifth of the run (docs/design/speed.md). Here each frame
goes straight from the renderer to the consumer, the renderer running in a second process so
that rendering and the front end use the two cores at once.

The frames are bit for bit the ones the recording would hold: the same plan
(:func:`sensors.sim.simulator.plan_simulation`), the same noise draws in the same order, and
depth passed through the recording's uint16 counts. The low-rate streams (wheels, gyro, ground
truth, GPS: a few hundred kB) are written by the recording writer, without images, to a
temporary folder and read back by :class:`~sensors.recording.Recording`, so they go through
the same text round trip as a rendered recording's and every consumer sees the same numbers.
The images travel through shared memory: QUEUE_FRAMES slots the renderer fills and the consumer
copies out and hands back, only slot numbers going through the queues (pickling 1.5 MB a frame
through a pipe cost ~2 ms of CPU in the renderer and ~3 in the consumer, against ~0.4 each;
docs/design/speed.md, "Session 16").
"""

from __future__ import annotations

import copy
import logging
import multiprocessing as mp
import queue
import shutil
import signal
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from sensors.config import CameraConfig, RobotConfig, SimConfig
from sensors.gps import GpsStream
from sensors.recording import Recording, RecordingWriter, counts_to_depth, depth_to_counts
from sensors.recording_source import RecordingSource
from sensors.sim.render import KinectRenderer
from sensors.sim.simulator import SimulationPlan, plan_simulation, render_frames
from sensors.types import RgbdFrame, SensorError

log = logging.getLogger(__name__)

QUEUE_FRAMES = 6  # frame slots the renderer may fill ahead of the consumer (~1.5 MB each)
POLL_S = 1.0  # [s] how often a waiting consumer checks that the renderer is still alive
NO_MAIN_GUARD = (
    'a script that opens a world must keep its code under `if __name__ == "__main__":` '
    "(the renderer is a spawned process, which imports the script again)"
)


def _check_not_bootstrapping() -> None:
    """A spawned process still importing its parent's main script (one without the guard)
    must not start a renderer: it would run the script's work again and then fail in
    multiprocessing's start-up check with a 30-line text. The same test as that check's."""
    if getattr(mp.current_process(), "_inheriting", False):
        raise SensorError(NO_MAIN_GUARD)


class _Slots:
    """QUEUE_FRAMES (rgb uint8 (H, W, 3), depth counts uint16 (H, W)) image slots in shared
    memory (``RawArray``: inherited by the spawned renderer at its start)."""

    def __init__(self, ctx: Any, height: int, width: int) -> None:
        self.shape = (height, width)
        self.rgb_buf = ctx.RawArray("B", QUEUE_FRAMES * height * width * 3)
        self.counts_buf = ctx.RawArray("H", QUEUE_FRAMES * height * width)

    def rgb(self, slot: int) -> np.ndarray:
        return np.frombuffer(self.rgb_buf, np.uint8).reshape(QUEUE_FRAMES, *self.shape, 3)[slot]

    def counts(self, slot: int) -> np.ndarray:
        return np.frombuffer(self.counts_buf, np.uint16).reshape(QUEUE_FRAMES, *self.shape)[slot]


def _render_worker(
    plan: SimulationPlan, slots: _Slots, free: Any, filled: Any, started: Any
) -> None:
    """Child process (``started`` set once it runs: it got past the spawn): every frame of
    ``plan`` written into a slot taken from ``free`` and the slot's number sent on ``filled``,
    then None; an exception is sent as its text (the parent raises it). Ends when the parent
    is gone. Ctrl-C reaches the whole process group: the parent decides what it means (a
    mapping run stops reading and saves its map), so the child ignores SIGINT."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    started.set()
    parent = mp.parent_process()

    def take_slot() -> int | None:
        while True:
            try:
                return int(free.get(timeout=POLL_S))
            except queue.Empty:
                if parent is not None and not parent.is_alive():
                    filled.cancel_join_thread()  # exit without flushing to a dead reader
                    return None

    try:
        scale = plan.intrinsics.depth_scale
        for frame in render_frames(plan):
            slot = take_slot()
            if slot is None:
                return
            rgb = slots.rgb(slot)
            if frame.rgb.shape != rgb.shape:
                raise ValueError(f"rendered {frame.rgb.shape} images, planned {rgb.shape}")
            rgb[...] = frame.rgb
            depth_to_counts(frame.depth_m, scale, out=slots.counts(slot))
            filled.put(slot)
        filled.put(None)
    except BaseException as err:  # the parent turns it into a one-line error
        filled.put(f"{type(err).__name__}: {err}")


class _RenderProcess:
    """The renderer child process of one pass over the frames: spawned (no fork of a process
    that runs threads), its slots and queues, and ending it."""

    def __init__(self, plan: SimulationPlan, height: int, width: int) -> None:
        _check_not_bootstrapping()
        ctx = mp.get_context("spawn")
        self.slots = _Slots(ctx, height, width)
        self.free, self.filled, self.started = ctx.Queue(), ctx.Queue(), ctx.Event()
        for slot in range(QUEUE_FRAMES):
            self.free.put(slot)
        self.proc = ctx.Process(
            target=_render_worker,
            args=(plan, self.slots, self.free, self.filled, self.started),
            name="render",
            daemon=True,
        )
        self.proc.start()

    def close(self) -> None:
        if self.proc.is_alive():  # the consumer stopped early, or an error
            self.proc.terminate()
        self.proc.join()
        self.free.close()
        self.filled.close()


class RenderedRecording(Recording):
    """A world's recording whose images are rendered when read: :meth:`frames` streams them
    from a renderer process, :meth:`frame` renders one here. Everything else was read from the
    small folder of index and stream files :func:`open_world` wrote (and removed)."""

    plan: SimulationPlan
    _streams: dict[str, Any]
    _renderer: KinectRenderer | None = None
    _started: _RenderProcess | None = None

    def keep_streams(self) -> None:
        """Read the stream files once, so the folder may go."""
        self._streams = {
            "wheels": super().wheels(),
            "imu": super().imu(),
            "gps": super().gps(),
            "groundtruth": super().groundtruth(),
        }

    def wheels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._streams["wheels"]  # type: ignore[no-any-return]

    def imu(self) -> tuple[np.ndarray, np.ndarray] | None:
        return self._streams["imu"]  # type: ignore[no-any-return]

    def gps(self) -> GpsStream | None:
        return self._streams["gps"]  # type: ignore[no-any-return]

    def groundtruth(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        return self._streams["groundtruth"]  # type: ignore[no-any-return]

    def start_rendering(self) -> None:
        """Start the renderer process of the next :meth:`frames` now, so its start-up (a new
        interpreter's imports, the texture atlas, the noise banks: ~1.5 s of CPU) and its
        first QUEUE_FRAMES frames overlap the caller's own start-up (the front end's and the
        mapper's set-up) instead of following it. The plan is handed over as it is now. A
        no-op in a daemonic process (no children allowed) or when already started."""
        if self._started is None and not mp.current_process().daemon:
            self._started = _RenderProcess(self.plan, self.intrinsics.height, self.intrinsics.width)

    def close(self) -> None:
        """End a renderer started ahead whose frames were never read."""
        started, self._started = self._started, None
        if started is not None:
            started.close()

    def frames(
        self, skip_bad: bool = False, rgb_wanted: Callable[[int], bool] | None = None
    ) -> Iterator[RgbdFrame]:
        """The frames in order, rendered in a child process up to QUEUE_FRAMES ahead (here, in
        a daemonic process, which may not have children); always with their colour (the
        renderer makes it anyway), whatever ``rgb_wanted`` says."""
        self.skipped = {}
        n = len(self.plan.stamps_ns)
        if not np.array_equal(self.rgb_index, np.arange(n)):  # one stamp list: cannot happen
            raise SensorError(f"{self.path}: rgb/depth index does not match the rendered frames")
        if mp.current_process().daemon:  # e.g. a Dask worker: no child processes allowed
            plan = copy.copy(self.plan)
            plan.render_rng = copy.deepcopy(self.plan.render_rng)
            scale = plan.intrinsics.depth_scale
            for k, f in enumerate(render_frames(plan)):
                yield self._frame(k, f.rgb, depth_to_counts(f.depth_m, scale))
            return
        self.start_rendering()
        child, self._started = self._started, None  # a second pass starts its own
        assert child is not None
        slots, free = child.slots, child.free
        try:
            for k in range(n):
                item = self._next(child)
                if not isinstance(item, int):
                    raise SensorError(f"rendering {self.plan.world.name} failed: {item}")
                frame = self._frame(k, slots.rgb(item).copy(), slots.counts(item))
                free.put(item)  # the frame owns copies: the slot may be filled again
                yield frame
            if self._next(child) is not None:
                raise SensorError(f"rendering {self.plan.world.name}: more frames than planned")
        finally:
            child.close()

    def _next(self, child: _RenderProcess) -> Any:
        while True:
            try:
                return child.filled.get(timeout=POLL_S)
            except queue.Empty:
                proc = child.proc
                if proc.is_alive():
                    continue
                if not child.started.is_set():  # died in the spawn: importing the script
                    raise SensorError(
                        f"rendering {self.plan.world.name}: the renderer process ended "
                        f"(exit code {proc.exitcode}) before it started: {NO_MAIN_GUARD}"
                    ) from None
                raise SensorError(
                    f"rendering {self.plan.world.name}: the renderer process ended "
                    f"(exit code {proc.exitcode}) before its last frame"
                ) from None

    def frame(self, k: int, rgb: bool = True) -> RgbdFrame:
        """The k-th frame, rendered in this process (its noise draws replayed up to k), with its
        colour whatever ``rgb`` says."""
        if not 0 <= k < len(self.plan.stamps_ns):
            raise SensorError(f"{self.path}: no frame {k} (0..{len(self.plan.stamps_ns) - 1})")
        if self._renderer is None:
            self._renderer = self.plan.renderer()
        rng = copy.deepcopy(self.plan.render_rng)
        for _ in range(k):
            self._renderer.noise_offsets(rng)
        x, y, yaw = (float(v) for v in self.plan.poses[k])
        colour, depth = self._renderer.render(x, y, yaw, rng)
        return self._frame(k, colour, depth_to_counts(depth, self.plan.intrinsics.depth_scale))

    def _frame(self, k: int, rgb: np.ndarray, counts: np.ndarray) -> RgbdFrame:
        """What :meth:`Recording.frame` makes of the PNGs of these images."""
        return RgbdFrame(
            stamp_ns=int(self.rgb_stamps_ns[k]),
            rgb=rgb,
            depth_m=counts_to_depth(counts, self.intrinsics.depth_scale),
            intrinsics=self.intrinsics,
        )


class WorldSource(RecordingSource):
    """:class:`RecordingSource` over a :class:`RenderedRecording`."""

    recording: RenderedRecording

    def describe(self) -> str:
        return f"world rendered on demand (no images on disk): {super().describe()}"

    def close(self) -> None:
        self.recording.close()


def open_world(
    world_path: str | Path,
    robot: RobotConfig,
    camera: CameraConfig,
    sim: SimConfig,
    seed: int = 0,
    frames: int | None = None,
    skip_bad: bool = True,
    render_ahead: bool = False,
) -> WorldSource:
    """A world rendered on demand, as :func:`sensors.sim.simulator.simulate` would record it
    with the same arguments. Nothing stays on disk. With ``render_ahead`` the renderer process
    starts as soon as the plan is made (:meth:`RenderedRecording.start_rendering`): its start-up
    then overlaps the writing of the streams here and the caller's own set-up."""
    if render_ahead:
        _check_not_bootstrapping()  # before the plan: its work is wasted in such a process
    plan = plan_simulation(world_path, robot, camera, sim, seed, frames=frames)
    ahead = None
    if render_ahead and not mp.current_process().daemon:
        ahead = _RenderProcess(plan, plan.intrinsics.height, plan.intrinsics.width)
    tmp = Path(tempfile.mkdtemp(prefix="rgbdnav-world-"))
    try:
        with RecordingWriter(tmp / "streams", plan.intrinsics, plan.scene, images=False) as w:
            for stamp in plan.stamps_ns:
                w.add_frame_stamp(int(stamp))
            plan.write_streams(w)
        rec = RenderedRecording.open(tmp / "streams")
        assert isinstance(rec, RenderedRecording)  # Recording.open builds cls
        rec.keep_streams()
    except BaseException:
        if ahead is not None:
            ahead.close()
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rec.path = Path(world_path)  # what error messages and the summary name
    rec.plan = plan
    rec._started = ahead
    return WorldSource(rec, skip_bad=skip_bad)


__all__ = ["RenderedRecording", "WorldSource", "open_world"]
