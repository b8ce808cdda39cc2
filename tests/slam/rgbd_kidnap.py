"""Kidnapped robot in the RGB-D simulator, built outside the simulator (which cannot teleport).

Shared by ``tests/slam/test_localization_rgbd.py`` (short, subsampled) and
``bench/bench_localization.py`` (the full figure). The robot drives a world's route
(:func:`sensors.sim.motion.drive_route`); the depth camera renders the scene at the *true*
pose, which jumps ``jump_s`` seconds further along the route after ``kidnap_s`` seconds, while
the wheel odometry continues smoothly: after the jump its increments are those of the new
stretch composed onto the pre-jump odometry pose (the wheels never felt the teleport), with a
seeded scale error and noise. Depth becomes a scan through :class:`slam.depth_to_scan.
DepthToScan` with the RGB-D profile, as ``rgbdnav map``/``localize`` do, and the localiser runs
against a map of the world's floor plan (the occupancy a laser at the depth->scan height band
would see; free space is what a flood fill from the route start reaches).

Counts are in frames after the jump (the first is 1): when the status first leaves "tracking"
(lost or relocalising), when it is "tracking" within ``success_m`` / ``success_rad`` again, and
how many frames before that were "tracking" at a wrong pose with confidence >= min_score.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rgbdnav.config import Config, load_config
from rgbdnav.scan_stream import RGBD_PROFILE
from sensors.sim.motion import Trajectory, drive_route
from sensors.sim.render import KinectRenderer
from sensors.sim.world import World, floor_plan, load_world
from sensors.types import LaserScan, RgbdFrame
from slam.depth_to_scan import DepthToScan
from slam.geometry import ominus, oplus, wrap_angle
from slam.localization import LocalizationResult, Localizer, MapModel
from slam.occupancy_grid import GridGeometry, OccupancyGrid

REPO = Path(__file__).resolve().parents[2]
SCENES = REPO / "scenes"
NS_PER_S = 1_000_000_000
MAP_RESOLUTION = 0.05  # [m/cell]
OCCUPIED_LOG_ODDS = 4.0  # log-odds of a floor-plan wall cell (p ~ 0.98)
FREE_LOG_ODDS = -4.0  # log-odds of a reachable free cell


def rgbd_config() -> Config:
    """Defaults with the RGB-D profile, as ``rgbdnav localize`` uses for a recording."""
    return load_config([RGBD_PROFILE], [])


def floor_plan_grid(world: World, cfg: Config, resolution: float = MAP_RESOLUTION) -> OccupancyGrid:
    """An occupancy grid of the world as the depth->scan height band sees it."""
    d2s = cfg.depth_to_scan
    plan = floor_plan(world, resolution, d2s.min_height, d2s.max_height)
    occ = plan.occupied.astype(np.uint8)
    # Free: the cells a flood fill from the start reaches without crossing a wall.
    h, w = occ.shape
    mask = np.zeros((h + 2, w + 2), np.uint8)
    mask[1:-1, 1:-1] = occ
    r0 = int((world.start[1] - plan.origin_y) / resolution)
    c0 = int((world.start[0] - plan.origin_x) / resolution)
    fill = np.zeros_like(occ)
    cv2.floodFill(fill, mask, (c0, r0), 1)
    # Occupied: only the wall faces free space touches, as a mapped grid has them (a 0.12 m
    # wall rasterised solid has no line-like neighbourhood, so ICP finds no normals in it).
    face = occ.astype(bool) & cv2.dilate(fill, np.ones((3, 3), np.uint8)).astype(bool)
    log_odds = np.zeros((h, w), np.float32)
    log_odds[fill.astype(bool)] = FREE_LOG_ODDS
    log_odds[face] = OCCUPIED_LOG_ODDS
    geom = GridGeometry(resolution, plan.origin_x, plan.origin_y, w, h)
    return OccupancyGrid(geom, log_odds, log_odds != 0.0)


def solid_floor_plan_grid(
    world: World, cfg: Config, resolution: float = MAP_RESOLUTION
) -> OccupancyGrid:
    """The floor plan as a CAD drawing gives it: walls filled solid, every other cell free."""
    d2s = cfg.depth_to_scan
    plan = floor_plan(world, resolution, d2s.min_height, d2s.max_height)
    log_odds = np.where(plan.occupied, OCCUPIED_LOG_ODDS, FREE_LOG_ODDS).astype(np.float32)
    h, w = plan.occupied.shape
    geom = GridGeometry(resolution, plan.origin_x, plan.origin_y, w, h)
    return OccupancyGrid(geom, log_odds, np.ones((h, w), bool))


def route_at(traj: Trajectory, t_ns: np.ndarray) -> np.ndarray:
    """(N, 3) base_link poses of the route at times ``t_ns`` (clamped to the route)."""
    x, y, yaw = traj.interpolate(t_ns)
    return np.column_stack([x, y, yaw])


def corrupt(
    felt: np.ndarray,
    rng: np.random.Generator,
    scale: float = 1.02,
    sigma_m: float = 0.003,
    sigma_rad: float = 0.003,
) -> np.ndarray:
    """Odometry from the felt path: each step scaled, with Gaussian noise, re-integrated."""
    steps = ominus(felt[:-1], felt[1:])
    steps[:, :2] *= scale
    steps += rng.normal(0.0, [sigma_m, sigma_m, sigma_rad], steps.shape)
    out = [felt[0]]
    for u in steps:
        out.append(oplus(out[-1], u))
    return np.array(out)


@dataclass(frozen=True)
class KidnapStream:
    stamps_ns: np.ndarray  # (N,) int64 [ns], evenly spaced at the frame rate
    truth: np.ndarray  # (N, 3) base_link poses the camera renders at (jumps at ``jump_index``)
    odom: np.ndarray  # (N, 3) odometry poses (continuous through the jump)
    jump_index: int  # first frame after the teleport


def kidnap_stream(
    traj: Trajectory, rate_hz: float, kidnap_s: float, jump_s: float, after_s: float, seed: int
) -> KidnapStream:
    """Frames at ``rate_hz`` for ``kidnap_s`` along the route, then ``after_s`` more from
    ``kidnap_s + jump_s`` on (the teleport); odometry as the module docstring says."""
    period = int(round(NS_PER_S / rate_hz))
    before = np.arange(0, int(kidnap_s * NS_PER_S), period, dtype=np.int64)
    after = before[-1] + period * np.arange(1, int(after_s * rate_hz) + 1, dtype=np.int64)
    jump_ns = int(jump_s * NS_PER_S)
    truth = route_at(traj, np.concatenate([before, after + jump_ns]))
    # The wheels feel the new stretch's increments, not the jump.
    felt_after = route_at(traj, np.concatenate([[before[-1] + jump_ns], after + jump_ns]))
    steps = ominus(felt_after[:-1], felt_after[1:])
    felt = list(truth[: len(before)])
    for u in steps:
        felt.append(oplus(felt[-1], u))
    odom = corrupt(np.array(felt), np.random.default_rng(seed))
    return KidnapStream(np.concatenate([before, after]), truth, odom, len(before))


class DepthScanner:
    """Renders the depth at a pose and turns it into the scan ``rgbdnav localize`` would use."""

    def __init__(self, world: World, cfg: Config, noisy: bool, seed: int = 0) -> None:
        self.renderer = KinectRenderer(world, cfg.camera, cfg.robot, cfg.sim, noise_seed=seed)
        self.d2s = DepthToScan(self.renderer.intrinsics, cfg.robot, cfg.depth_to_scan)
        self.noisy = noisy
        self.rng = np.random.default_rng(seed)
        k = self.renderer.intrinsics
        self._rgb = np.zeros((k.height, k.width, 3), np.uint8)

    def scan(self, pose: np.ndarray, stamp_ns: int) -> LaserScan:
        x, y, yaw = (float(v) for v in pose)
        if self.noisy:
            _, depth = self.renderer.render(x, y, yaw, self.rng)
        else:
            depth = self.renderer.true_depth(x, y, yaw).astype(np.float32)
            depth[~np.isfinite(depth)] = 0.0
        frame = RgbdFrame(int(stamp_ns), self._rgb, depth, self.renderer.intrinsics)
        return self.d2s.from_frame(frame).scan


@dataclass(frozen=True)
class KidnapOutcome:
    left_tracking: int | None  # [frames after the jump] first status other than "tracking"
    lost: int | None  # [frames after the jump] first "lost"
    recovered: int | None  # [frames after the jump] tracking within the tolerance again
    confident_wrong: int  # frames tracked off the tolerance with confidence >= min_score
    pre_jump_ok: bool  # tracking within the tolerance on every frame before the jump
    period_s: float  # [s] between frames
    errors_after: list[float]  # [m] position errors from the recovery on


def run_kidnap(
    model: MapModel,
    cfg: Config,
    scanner: DepthScanner,
    stream: KidnapStream,
    success_m: float = 0.2,
    success_rad: float = math.radians(5.0),
) -> tuple[KidnapOutcome, list[LocalizationResult]]:
    loc = Localizer(model, cfg.localizer, initial_pose=stream.truth[0])
    frames = zip(stream.truth, stream.stamps_ns, stream.odom, strict=True)
    results = [loc.update(scanner.scan(p, t), o) for p, t, o in frames]
    d = np.hypot(*(np.array([r.pose[:2] for r in results]) - stream.truth[:, :2]).T)
    a = np.abs(wrap_angle(np.array([r.pose[2] for r in results]) - stream.truth[:, 2]))
    tracking = np.array([r.status == "tracking" for r in results])
    good = tracking & (d <= success_m) & (a <= success_rad)
    j = stream.jump_index
    after = range(j, len(results))

    def first(mask: np.ndarray) -> int | None:
        hits = [i - j + 1 for i in after if mask[i]]
        return hits[0] if hits else None

    rec = first(good)
    end = len(results) if rec is None else j + rec - 1
    conf = np.array([r.confidence for r in results])
    wrong = tracking & ~good & (conf >= cfg.localizer.min_score)
    return KidnapOutcome(
        left_tracking=first(~tracking),
        lost=first(np.array([r.status == "lost" for r in results])),
        recovered=rec,
        confident_wrong=int(wrong[j:end].sum()),
        pre_jump_ok=bool(good[:j].all()),
        period_s=float(np.diff(stream.stamps_ns).mean()) / NS_PER_S,
        errors_after=[] if rec is None else d[j + rec - 1 :].tolist(),
    ), results


def house(scene: str = "house") -> tuple[World, Config, Trajectory, MapModel]:
    """A shipped scene (``scenes/<scene>.yaml``), the RGB-D config, its route and floor-plan
    map."""
    cfg = rgbd_config()
    world = load_world(SCENES / f"{scene}.yaml")
    model = MapModel.from_grid(floor_plan_grid(world, cfg), cfg.localizer)
    return world, cfg, drive_route(world, cfg.sim), model
